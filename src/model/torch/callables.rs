//! The callables a state dict needs, interpreted rather than run: `OrderedDict`, the tensor and
//! parameter rebuild functions, `torch.Size`, `_codecs.encode`, and the persistent storage
//! references. Any other callable or class gives an opaque object.

use std::cell::RefCell;
use std::rc::Rc;

use super::pickle::VmResult;
use super::storage::StorageType;
use super::value::{Dict, StorageRef, TensorRef, Value};
use crate::model::shape_string;

/// How deep `_rebuild_from_type_v2` may nest calls.
const MAX_CALL_DEPTH: usize = 8;
/// The most dimensions a tensor may have (PyTorch allows 64).
const MAX_RANK: usize = 64;

/// `cls.__new__(cls, ...)`: an OrderedDict becomes a dict, anything else an opaque object.
pub(super) fn new_object(cls: &Value) -> Value {
    match cls {
        Value::Global(g) if g.0 == "collections" && g.1 == "OrderedDict" => {
            Value::Dict(Rc::default())
        }
        Value::Global(g) => Value::Opaque(Rc::from(format!("{}.{}", g.0, g.1).as_str())),
        other => Value::Opaque(Rc::from(format!("instance of {}", other.kind()).as_str())),
    }
}

/// Interprets a REDUCE: the few callables a state dict needs; anything else is opaque.
pub(super) fn call(callable: &Value, args: &[Value], depth: usize) -> VmResult<Value> {
    let Value::Global(g) = callable else {
        return Ok(Value::Opaque(Rc::from(
            format!("result of calling {}", callable.kind()).as_str(),
        )));
    };
    let (module, name) = (g.0.as_str(), g.1.as_str());
    match (module, name) {
        ("collections", "OrderedDict") => {
            let mut dict = Dict::default();
            // OrderedDict([(k, v), ...]) as older pickles write it.
            if let Some(Value::List(pairs)) = args.first() {
                for pair in &pairs.borrow().0 {
                    if let Value::Tuple(kv) = pair {
                        if let [k, v] = kv.0.as_slice() {
                            dict.insert(k.clone(), v.clone());
                        }
                    }
                }
            }
            Ok(Value::Dict(Rc::new(RefCell::new(dict))))
        }
        ("torch._utils", "_rebuild_tensor_v2") | ("torch._utils", "_rebuild_tensor") => {
            rebuild_tensor(args)
        }
        ("torch._utils", "_rebuild_parameter")
        | ("torch._utils", "_rebuild_parameter_with_state") => match args.first() {
            Some(t @ Value::Tensor(_)) => Ok(t.clone()),
            Some(other) => Err(format!("{name} of {}, not of a tensor", other.kind())),
            None => Err(format!("{name} without arguments")),
        },
        ("torch._tensor", "_rebuild_from_type_v2") | ("torch._tensor", "_rebuild_from_type") => {
            if depth >= MAX_CALL_DEPTH {
                return Err(format!("{name} nested too deeply"));
            }
            match args {
                [func, _new_type, Value::Tuple(inner), ..] => call(func, &inner.0, depth + 1),
                _ => Err(format!("{name} with unexpected arguments")),
            }
        }
        ("torch", "Size") => match args.first() {
            Some(t @ Value::Tuple(_)) => Ok(t.clone()),
            _ => Ok(Value::Opaque(Rc::from("torch.Size"))),
        },
        ("_codecs", "encode") => match args {
            // How protocol 2 writes Python 3 bytes: _codecs.encode(text, 'latin1').
            [Value::Str(text), Value::Str(enc)] if enc.as_ref() == "latin1" => {
                let bytes: Option<Vec<u8>> = text
                    .chars()
                    .map(|c| u8::try_from(u32::from(c)).ok())
                    .collect();
                Ok(bytes.map_or_else(
                    || Value::Opaque(Rc::from("_codecs.encode result")),
                    |b| Value::Bytes(Rc::from(b.as_slice())),
                ))
            }
            _ => Ok(Value::Opaque(Rc::from("_codecs.encode result"))),
        },
        _ => Ok(Value::Opaque(Rc::from(format!("{module}.{name}").as_str()))),
    }
}

fn as_usize(v: &Value, what: &str) -> VmResult<usize> {
    match v {
        Value::Int(i) => usize::try_from(*i).map_err(|_| format!("{what} is negative ({i})")),
        other => Err(format!("{what} is {}, not an int", other.kind())),
    }
}

fn as_usizes(v: &Value, what: &str) -> VmResult<Vec<usize>> {
    let items = match v {
        Value::Tuple(t) => &t.0,
        other => return Err(format!("{what} is {}, not a tuple", other.kind())),
    };
    if items.len() > MAX_RANK {
        return Err(format!("{what} has {} dimensions", items.len()));
    }
    items.iter().map(|x| as_usize(x, what)).collect()
}

/// `_rebuild_tensor_v2(storage, offset, size, stride, ...)`, checked against the storage's size.
fn rebuild_tensor(args: &[Value]) -> VmResult<Value> {
    let [storage, offset, size, stride, ..] = args else {
        return Err("a tensor rebuilt with fewer than 4 arguments".into());
    };
    let Value::Storage(storage) = storage else {
        return Err(format!(
            "a tensor whose storage is {}, not a persistent storage",
            storage.kind()
        ));
    };
    let offset = as_usize(offset, "tensor offset")?;
    let shape = as_usizes(size, "tensor size")?;
    let stride = as_usizes(stride, "tensor stride")?;
    if shape.len() != stride.len() {
        return Err(format!(
            "tensor size {} and stride {} differ in rank",
            shape_string(&shape),
            shape_string(&stride)
        ));
    }
    let numel = shape
        .iter()
        .try_fold(1usize, |a, &n| a.checked_mul(n))
        .ok_or("tensor size overflows")?;
    if numel > 0 {
        let mut last = offset;
        for (&n, &s) in shape.iter().zip(&stride) {
            last = (n - 1)
                .checked_mul(s)
                .and_then(|x| last.checked_add(x))
                .ok_or("tensor extent overflows")?;
        }
        if last as u64 >= storage.numel {
            return Err(format!(
                "a tensor of size {} (offset {offset}, stride {}) reaches element {last} of \
                 storage {} which holds {}",
                shape_string(&shape),
                shape_string(&stride),
                storage.key,
                storage.numel
            ));
        }
    }
    Ok(Value::Tensor(Rc::new(TensorRef {
        storage: storage.clone(),
        offset,
        shape,
        stride,
    })))
}

/// `persistent_load(('storage', storage_type, key, location, numel))`.
pub(super) fn persistent_storage(pid: &Value) -> VmResult<Value> {
    let Value::Tuple(t) = pid else {
        return Err(format!(
            "a persistent id that is {}, not a tuple",
            pid.kind()
        ));
    };
    let [Value::Str(tag), class, key, _location, numel] = t.0.as_slice() else {
        return Err("a persistent id that is not ('storage', type, key, location, numel)".into());
    };
    if tag.as_ref() != "storage" {
        return Err(format!("a persistent id of kind {tag:?}, not 'storage'"));
    }
    let Value::Global(g) = class else {
        return Err(format!("a storage whose type is {}", class.kind()));
    };
    let dtype = StorageType::from_class(&g.0, &g.1)
        .ok_or_else(|| format!("unsupported storage type {}.{}", g.0, g.1))?;
    let key: Rc<str> = match key {
        Value::Str(s) => s.clone(),
        Value::Int(i) => Rc::from(i.to_string().as_str()),
        other => return Err(format!("a storage key that is {}", other.kind())),
    };
    if key.is_empty() || key.contains('/') || key.contains("..") {
        return Err(format!("a storage key {key:?} that is not a plain name"));
    }
    let numel = match numel {
        Value::Int(n) => u64::try_from(*n).map_err(|_| format!("storage size {n} is negative"))?,
        other => return Err(format!("a storage size that is {}", other.kind())),
    };
    Ok(Value::Storage(Rc::new(StorageRef { dtype, key, numel })))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::torch::value::Items;

    #[test]
    fn a_tensor_past_its_storage_is_rejected() {
        let storage = Value::Storage(Rc::new(StorageRef {
            dtype: StorageType::F32,
            key: Rc::from("0"),
            numel: 6,
        }));
        let tuple =
            |v: Vec<i64>| Value::Tuple(Rc::new(Items(v.into_iter().map(Value::Int).collect())));
        let ok = rebuild_tensor(&[
            storage.clone(),
            Value::Int(0),
            tuple(vec![2, 3]),
            tuple(vec![3, 1]),
        ]);
        assert!(ok.is_ok());
        let err = rebuild_tensor(&[
            storage.clone(),
            Value::Int(1),
            tuple(vec![2, 3]),
            tuple(vec![3, 1]),
        ])
        .unwrap_err();
        assert!(err.contains("reaches element 6"), "{err}");
        let err = rebuild_tensor(&[storage, Value::Int(0), tuple(vec![2, 3]), tuple(vec![1])])
            .unwrap_err();
        assert!(err.contains("rank"), "{err}");
    }
}
