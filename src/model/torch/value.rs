//! The values the pickle machine builds: plain Python data, storage and tensor references, and
//! opaque stand-ins for anything else. Nested containers are dropped without recursion.

use std::cell::RefCell;
use std::collections::HashMap;
use std::rc::Rc;

use super::storage::StorageType;

/// A persistent storage reference.
#[derive(Debug)]
pub(super) struct StorageRef {
    pub(super) dtype: StorageType,
    pub(super) key: Rc<str>,
    pub(super) numel: u64,
}

/// A tensor described by `_rebuild_tensor_v2`.
#[derive(Debug)]
pub(super) struct TensorRef {
    pub(super) storage: Rc<StorageRef>,
    pub(super) offset: usize,
    pub(super) shape: Vec<usize>,
    pub(super) stride: Vec<usize>,
}

/// The values the machine builds. Containers are shared (`Rc`) because the memo can refer to them
/// after they are pushed; their contents are dropped iteratively (see [`Items`]).
#[derive(Clone, Debug)]
pub(super) enum Value {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(Rc<str>),
    Bytes(Rc<[u8]>),
    Tuple(Rc<Items>),
    List(Rc<RefCell<Items>>),
    Dict(Rc<RefCell<Dict>>),
    Global(Rc<(String, String)>),
    Storage(Rc<StorageRef>),
    Tensor(Rc<TensorRef>),
    /// Anything else (an instance of an unknown class, the result of an unknown call): its
    /// description only.
    Opaque(Rc<str>),
}

impl Value {
    /// A short description for error messages.
    pub(super) fn kind(&self) -> String {
        match self {
            Value::None => "None".into(),
            Value::Bool(_) => "a bool".into(),
            Value::Int(_) => "an int".into(),
            Value::Float(_) => "a float".into(),
            Value::Str(_) => "a str".into(),
            Value::Bytes(_) => "bytes".into(),
            Value::Tuple(_) => "a tuple".into(),
            Value::List(_) => "a list".into(),
            Value::Dict(_) => "a dict".into(),
            Value::Global(g) => format!("the class {}.{}", g.0, g.1),
            Value::Storage(_) => "a storage".into(),
            Value::Tensor(_) => "a tensor".into(),
            Value::Opaque(what) => format!("an object ({what})"),
        }
    }

    /// A short rendering of a dict key.
    pub(super) fn short(&self) -> String {
        match self {
            Value::Str(s) => format!("'{s}'"),
            Value::Int(i) => i.to_string(),
            Value::Bool(b) => {
                if *b {
                    "True".into()
                } else {
                    "False".into()
                }
            }
            Value::Float(f) => f.to_string(),
            Value::Bytes(b) => format!("bytes of length {}", b.len()),
            other => other.kind(),
        }
    }
}

/// The items of a tuple or list. Dropping it walks nested containers with an explicit stack, so a
/// deeply nested (hostile) pickle cannot overflow the call stack.
#[derive(Debug, Default)]
pub(super) struct Items(pub(super) Vec<Value>);

impl Drop for Items {
    fn drop(&mut self) {
        let mut stack = std::mem::take(&mut self.0);
        drain_nested(&mut stack);
    }
}

/// Drops the values on `stack`, moving the contents of containers owned only by them onto the
/// stack instead of recursing.
pub(super) fn drain_nested(stack: &mut Vec<Value>) {
    while let Some(value) = stack.pop() {
        match value {
            Value::Tuple(rc) => {
                if let Ok(mut items) = Rc::try_unwrap(rc) {
                    stack.append(&mut items.0);
                }
            }
            Value::List(rc) => {
                if let Ok(cell) = Rc::try_unwrap(rc) {
                    stack.append(&mut cell.into_inner().0);
                }
            }
            Value::Dict(rc) => {
                if let Ok(cell) = Rc::try_unwrap(rc) {
                    let mut dict = cell.into_inner();
                    for (k, v) in dict.items.drain(..) {
                        stack.push(k);
                        stack.push(v);
                    }
                }
            }
            _ => {}
        }
    }
}

/// A key that Python would hash: strings and integers (bools are integers).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
enum Key {
    Str(Rc<str>),
    Int(i64),
}

/// An insertion-ordered dict (plain `dict` and `OrderedDict` alike).
#[derive(Debug, Default)]
pub(super) struct Dict {
    pub(super) items: Vec<(Value, Value)>,
    index: HashMap<Key, usize>,
}

impl Dict {
    pub(super) fn insert(&mut self, key: Value, value: Value) {
        let hashed = match &key {
            Value::Str(s) => Some(Key::Str(s.clone())),
            Value::Int(i) => Some(Key::Int(*i)),
            Value::Bool(b) => Some(Key::Int(i64::from(*b))),
            _ => None,
        };
        if let Some(h) = hashed {
            if let Some(&at) = self.index.get(&h) {
                self.items[at].1 = value;
                return;
            }
            self.index.insert(h, self.items.len());
        }
        self.items.push((key, value));
    }

    pub(super) fn get_str(&self, key: &str) -> Option<&Value> {
        let at = *self.index.get(&Key::Str(Rc::from(key)))?;
        Some(&self.items[at].1)
    }
}

impl Drop for Dict {
    fn drop(&mut self) {
        let mut stack = Vec::with_capacity(self.items.len() * 2);
        for (k, v) in self.items.drain(..) {
            stack.push(k);
            stack.push(v);
        }
        drain_nested(&mut stack);
    }
}
