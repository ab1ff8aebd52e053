//! The pickle machine: a stack machine that understands the opcodes pickle writes for plain
//! data and **executes nothing**. The opcodes are handled by family (control, scalars, text and
//! bytes, containers, memo, objects); REDUCE and persistent ids go to [`super::callables`].

use std::cell::RefCell;
use std::collections::HashMap;
use std::rc::Rc;

use super::callables::{call, new_object, persistent_storage};
use super::value::{drain_nested, Dict, Items, Value};

/// What the machine's steps return: an error is a message (the caller adds the file's name).
pub(super) type VmResult<T> = std::result::Result<T, String>;

/// The opcodes the machine understands, named as in Python's `pickletools`.
mod op {
    pub const PROTO: u8 = 0x80;
    pub const FRAME: u8 = 0x95;
    pub const STOP: u8 = b'.';
    pub const MARK: u8 = b'(';
    pub const POP: u8 = b'0';
    pub const POP_MARK: u8 = b'1';
    pub const DUP: u8 = b'2';
    pub const NONE: u8 = b'N';
    pub const NEWTRUE: u8 = 0x88;
    pub const NEWFALSE: u8 = 0x89;
    pub const BININT: u8 = b'J';
    pub const BININT1: u8 = b'K';
    pub const BININT2: u8 = b'M';
    pub const LONG1: u8 = 0x8a;
    pub const LONG4: u8 = 0x8b;
    pub const BINFLOAT: u8 = b'G';
    pub const BINUNICODE: u8 = b'X';
    pub const SHORT_BINUNICODE: u8 = 0x8c;
    pub const BINUNICODE8: u8 = 0x8d;
    pub const BINSTRING: u8 = b'T';
    pub const SHORT_BINSTRING: u8 = b'U';
    pub const BINBYTES: u8 = b'B';
    pub const SHORT_BINBYTES: u8 = b'C';
    pub const BINBYTES8: u8 = 0x8e;
    pub const BYTEARRAY8: u8 = 0x96;
    pub const EMPTY_DICT: u8 = b'}';
    pub const EMPTY_LIST: u8 = b']';
    pub const EMPTY_TUPLE: u8 = b')';
    pub const EMPTY_SET: u8 = 0x8f;
    pub const FROZENSET: u8 = 0x91;
    pub const TUPLE: u8 = b't';
    /// TUPLE1, TUPLE2 and TUPLE3 are consecutive.
    pub const TUPLE1: u8 = 0x85;
    pub const TUPLE3: u8 = 0x87;
    pub const LIST: u8 = b'l';
    pub const DICT: u8 = b'd';
    pub const APPEND: u8 = b'a';
    pub const APPENDS: u8 = b'e';
    pub const ADDITEMS: u8 = 0x90;
    pub const SETITEM: u8 = b's';
    pub const SETITEMS: u8 = b'u';
    pub const BINPUT: u8 = b'q';
    pub const LONG_BINPUT: u8 = b'r';
    pub const MEMOIZE: u8 = 0x94;
    pub const BINGET: u8 = b'h';
    pub const LONG_BINGET: u8 = b'j';
    pub const GLOBAL: u8 = b'c';
    pub const STACK_GLOBAL: u8 = 0x93;
    pub const REDUCE: u8 = b'R';
    pub const NEWOBJ: u8 = 0x81;
    pub const NEWOBJ_EX: u8 = 0x92;
    pub const BUILD: u8 = b'b';
    pub const BINPERSID: u8 = b'Q';
}

/// The stack machine for one pickle.
pub(super) struct Vm<'a> {
    data: &'a [u8],
    pos: usize,
    stack: Vec<Value>,
    marks: Vec<usize>,
    memo: HashMap<u32, Value>,
}

impl<'a> Vm<'a> {
    /// A machine that will read `data`.
    pub(super) fn new(data: &'a [u8]) -> Self {
        Vm {
            data,
            pos: 0,
            stack: Vec::new(),
            marks: Vec::new(),
            memo: HashMap::new(),
        }
    }

    fn take(&mut self, n: u64) -> VmResult<&'a [u8]> {
        let left = (self.data.len() - self.pos) as u64;
        if n > left {
            return Err(format!(
                "{n} bytes wanted at byte {} but only {left} remain (truncated pickle)",
                self.pos
            ));
        }
        let start = self.pos;
        self.pos += n as usize;
        Ok(&self.data[start..self.pos])
    }

    fn array<const N: usize>(&mut self) -> VmResult<[u8; N]> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N as u64)?);
        Ok(a)
    }

    fn byte(&mut self) -> VmResult<u8> {
        Ok(self.array::<1>()?[0])
    }

    fn u32(&mut self) -> VmResult<u32> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    fn line(&mut self) -> VmResult<&'a str> {
        let rest = &self.data[self.pos..];
        let end = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| format!("unterminated line at byte {}", self.pos))?;
        let text = std::str::from_utf8(&rest[..end])
            .map_err(|_| format!("a name that is not UTF-8 at byte {}", self.pos))?;
        self.pos += end + 1;
        Ok(text)
    }

    fn pop(&mut self) -> VmResult<Value> {
        if self.marks.last().is_some_and(|&m| m >= self.stack.len()) {
            return Err(format!("pop across a mark at byte {}", self.pos));
        }
        self.stack
            .pop()
            .ok_or_else(|| format!("stack underflow at byte {}", self.pos))
    }

    fn top(&mut self) -> VmResult<&mut Value> {
        let pos = self.pos;
        self.stack
            .last_mut()
            .ok_or_else(|| format!("stack underflow at byte {pos}"))
    }

    fn pop_mark(&mut self) -> VmResult<Vec<Value>> {
        let mark = self
            .marks
            .pop()
            .ok_or_else(|| format!("no mark on the stack at byte {}", self.pos))?;
        if mark > self.stack.len() {
            return Err(format!("mark above the stack at byte {}", self.pos));
        }
        Ok(self.stack.split_off(mark))
    }

    fn push(&mut self, v: Value) {
        self.stack.push(v);
    }

    fn memo_get(&self, index: u32) -> VmResult<Value> {
        self.memo
            .get(&index)
            .cloned()
            .ok_or_else(|| format!("memo entry {index} missing at byte {}", self.pos))
    }

    fn memo_put(&mut self, index: u32) -> VmResult<()> {
        let v = self.top()?.clone();
        self.memo.insert(index, v);
        Ok(())
    }

    fn string(&mut self, n: u64) -> VmResult<Value> {
        let bytes = self.take(n)?;
        let s = std::str::from_utf8(bytes)
            .map_err(|_| format!("a str that is not UTF-8 before byte {}", self.pos))?;
        Ok(Value::Str(Rc::from(s)))
    }

    /// A Python 2 `str` (BINSTRING): read as Latin-1 text.
    fn latin1(&mut self, n: u64) -> VmResult<Value> {
        let bytes = self.take(n)?;
        let s: String = bytes.iter().map(|&b| char::from(b)).collect();
        Ok(Value::Str(Rc::from(s.as_str())))
    }

    /// Runs the pickle to its STOP opcode and returns the value it leaves.
    pub(super) fn run(mut self) -> VmResult<Value> {
        loop {
            let at = self.pos;
            let op = self.byte()?;
            if op == op::STOP {
                return self.pop();
            }
            self.step(op, at)?;
        }
    }

    /// Executes one opcode (other than STOP), read at byte `at`, by its family.
    fn step(&mut self, op: u8, at: usize) -> VmResult<()> {
        use op::*;
        match op {
            PROTO | FRAME | MARK | POP | POP_MARK | DUP => self.control(op, at),
            NONE | NEWTRUE | NEWFALSE | BININT | BININT1 | BININT2 | LONG1 | LONG4 | BINFLOAT => {
                self.scalar(op, at)
            }
            BINUNICODE | SHORT_BINUNICODE | BINUNICODE8 | BINSTRING | SHORT_BINSTRING
            | BINBYTES | SHORT_BINBYTES | BINBYTES8 | BYTEARRAY8 => self.text_or_bytes(op, at),
            EMPTY_DICT
            | EMPTY_LIST
            | EMPTY_TUPLE
            | EMPTY_SET
            | FROZENSET
            | TUPLE
            | TUPLE1..=TUPLE3
            | LIST
            | DICT => self.new_container(op, at),
            ADDITEMS | SETITEM | SETITEMS | APPEND | APPENDS => self.fill_container(op, at),
            BINPUT | LONG_BINPUT | MEMOIZE | BINGET | LONG_BINGET => self.memo_op(op, at),
            GLOBAL | STACK_GLOBAL | REDUCE | NEWOBJ | NEWOBJ_EX | BUILD | BINPERSID => {
                self.object_op(op, at)
            }
            _ => Err(unsupported(op, at)),
        }
    }

    /// The protocol header, framing, marks and plain stack manipulation.
    fn control(&mut self, op: u8, at: usize) -> VmResult<()> {
        match op {
            op::PROTO => {
                let protocol = self.byte()?;
                if protocol > 5 {
                    return Err(format!("unsupported pickle protocol {protocol}"));
                }
            }
            op::FRAME => {
                self.take(8)?; // a length hint only
            }
            op::MARK => self.marks.push(self.stack.len()),
            op::POP => {
                self.pop()?;
            }
            op::POP_MARK => {
                self.pop_mark()?;
            }
            op::DUP => {
                let v = self.top()?.clone();
                self.push(v);
            }
            _ => return Err(unsupported(op, at)),
        }
        Ok(())
    }

    /// None, booleans, integers and floats.
    fn scalar(&mut self, op: u8, at: usize) -> VmResult<()> {
        let v = match op {
            op::NONE => Value::None,
            op::NEWTRUE => Value::Bool(true),
            op::NEWFALSE => Value::Bool(false),
            op::BININT => Value::Int(i64::from(i32::from_le_bytes(self.array()?))),
            op::BININT1 => Value::Int(i64::from(self.byte()?)),
            op::BININT2 => Value::Int(i64::from(u16::from_le_bytes(self.array()?))),
            op::LONG1 => {
                let n = self.byte()?;
                long(self.take(u64::from(n))?)
            }
            op::LONG4 => {
                let n = self.u32()?;
                long(self.take(u64::from(n))?)
            }
            op::BINFLOAT => Value::Float(f64::from_be_bytes(self.array()?)),
            _ => return Err(unsupported(op, at)),
        };
        self.push(v);
        Ok(())
    }

    /// Strings (UTF-8, or Latin-1 for Python 2 `str`) and byte strings, each after its length.
    fn text_or_bytes(&mut self, op: u8, at: usize) -> VmResult<()> {
        let v = match op {
            op::BINUNICODE => {
                let n = self.u32()?;
                self.string(u64::from(n))?
            }
            op::SHORT_BINUNICODE => {
                let n = self.byte()?;
                self.string(u64::from(n))?
            }
            op::BINUNICODE8 => {
                let n = u64::from_le_bytes(self.array()?);
                self.string(n)?
            }
            op::BINSTRING => {
                let n = self.u32()?;
                self.latin1(u64::from(n))?
            }
            op::SHORT_BINSTRING => {
                let n = self.byte()?;
                self.latin1(u64::from(n))?
            }
            op::BINBYTES => {
                let n = self.u32()?;
                Value::Bytes(Rc::from(self.take(u64::from(n))?))
            }
            op::SHORT_BINBYTES => {
                let n = self.byte()?;
                Value::Bytes(Rc::from(self.take(u64::from(n))?))
            }
            op::BINBYTES8 | op::BYTEARRAY8 => {
                let n = u64::from_le_bytes(self.array()?);
                Value::Bytes(Rc::from(self.take(n)?))
            }
            _ => return Err(unsupported(op, at)),
        };
        self.push(v);
        Ok(())
    }

    /// Empty containers, and containers made of the items above the mark (or the top 1-3 items).
    fn new_container(&mut self, op: u8, at: usize) -> VmResult<()> {
        let v = match op {
            op::EMPTY_DICT => Value::Dict(Rc::default()),
            op::EMPTY_LIST => Value::List(Rc::default()),
            op::EMPTY_TUPLE => Value::Tuple(Rc::default()),
            op::EMPTY_SET => Value::List(Rc::default()), // kept as a list
            op::FROZENSET | op::LIST => {
                let items = self.pop_mark()?;
                Value::List(Rc::new(RefCell::new(Items(items))))
            }
            op::TUPLE => {
                let items = self.pop_mark()?;
                Value::Tuple(Rc::new(Items(items)))
            }
            op::TUPLE1..=op::TUPLE3 => {
                let n = usize::from(op - op::TUPLE1 + 1);
                let mut items = Vec::with_capacity(n);
                for _ in 0..n {
                    items.push(self.pop()?);
                }
                items.reverse();
                Value::Tuple(Rc::new(Items(items)))
            }
            op::DICT => {
                let items = self.pop_mark()?;
                let mut dict = Dict::default();
                set_items(&mut dict, items, at)?;
                Value::Dict(Rc::new(RefCell::new(dict)))
            }
            _ => return Err(unsupported(op, at)),
        };
        self.push(v);
        Ok(())
    }

    /// Adding items to the list or dict on top of the stack (ignored on an opaque object).
    fn fill_container(&mut self, op: u8, at: usize) -> VmResult<()> {
        match op {
            op::APPEND => {
                let value = self.pop()?;
                self.extend_top_list("APPEND", vec![value], at)
            }
            op::APPENDS => {
                let items = self.pop_mark()?;
                self.extend_top_list("APPENDS", items, at)
            }
            op::ADDITEMS => {
                let items = self.pop_mark()?;
                self.extend_top_list("ADDITEMS", items, at)
            }
            op::SETITEM => {
                let value = self.pop()?;
                let key = self.pop()?;
                self.set_top_dict("SETITEM", vec![key, value], at)
            }
            op::SETITEMS => {
                let items = self.pop_mark()?;
                self.set_top_dict("SETITEMS", items, at)
            }
            _ => Err(unsupported(op, at)),
        }
    }

    /// Appends `items` to the list on top of the stack; `name` (the opcode) for errors.
    fn extend_top_list(&mut self, name: &str, items: Vec<Value>, at: usize) -> VmResult<()> {
        match self.top()? {
            Value::List(list) => list.borrow_mut().0.extend(items),
            Value::Opaque(_) => {}
            other => return Err(format!("{name} on {} at byte {at}", other.kind())),
        }
        Ok(())
    }

    /// Sets `items` (key, value, key, value, ...) in the dict on top of the stack; `name` (the
    /// opcode) for errors.
    fn set_top_dict(&mut self, name: &str, items: Vec<Value>, at: usize) -> VmResult<()> {
        match self.top()? {
            Value::Dict(d) => set_items(&mut d.borrow_mut(), items, at)?,
            Value::Opaque(_) => {}
            other => return Err(format!("{name} on {} at byte {at}", other.kind())),
        }
        Ok(())
    }

    /// Storing the top of the stack in the memo, and pushing a memo entry.
    fn memo_op(&mut self, op: u8, at: usize) -> VmResult<()> {
        match op {
            op::BINPUT => {
                let i = self.byte()?;
                self.memo_put(u32::from(i))
            }
            op::LONG_BINPUT => {
                let i = self.u32()?;
                self.memo_put(i)
            }
            op::MEMOIZE => {
                let i = u32::try_from(self.memo.len()).map_err(|_| "memo too large".to_string())?;
                self.memo_put(i)
            }
            op::BINGET => {
                let i = self.byte()?;
                let v = self.memo_get(u32::from(i))?;
                self.push(v);
                Ok(())
            }
            op::LONG_BINGET => {
                let i = self.u32()?;
                let v = self.memo_get(i)?;
                self.push(v);
                Ok(())
            }
            _ => Err(unsupported(op, at)),
        }
    }

    /// Globals, calls, object creation and state, and persistent (storage) references: the
    /// opcodes that would run code in Python, interpreted here without running anything.
    fn object_op(&mut self, op: u8, at: usize) -> VmResult<()> {
        let v = match op {
            op::GLOBAL => {
                let module = self.line()?.to_string();
                let name = self.line()?.to_string();
                Value::Global(Rc::new((module, name)))
            }
            op::STACK_GLOBAL => {
                let name = self.pop()?;
                let module = self.pop()?;
                let (Value::Str(module), Value::Str(name)) = (module, name) else {
                    return Err(format!("STACK_GLOBAL without two strs at byte {at}"));
                };
                Value::Global(Rc::new((module.to_string(), name.to_string())))
            }
            op::REDUCE => {
                let args = self.pop()?;
                let callable = self.pop()?;
                let Value::Tuple(args) = args else {
                    return Err(format!(
                        "REDUCE with {} as arguments at byte {at}",
                        args.kind()
                    ));
                };
                call(&callable, &args.0, 0).map_err(|e| format!("{e} (byte {at})"))?
            }
            op::NEWOBJ => {
                let _args = self.pop()?;
                let cls = self.pop()?;
                new_object(&cls)
            }
            op::NEWOBJ_EX => {
                let _kwargs = self.pop()?;
                let _args = self.pop()?;
                let cls = self.pop()?;
                new_object(&cls)
            }
            op::BUILD => {
                // The state of objects is not needed (an OrderedDict's _metadata, a Namespace's
                // attributes).
                let _state = self.pop()?;
                self.top()?;
                return Ok(());
            }
            op::BINPERSID => {
                let pid = self.pop()?;
                persistent_storage(&pid).map_err(|e| format!("{e} (byte {at})"))?
            }
            _ => return Err(unsupported(op, at)),
        };
        self.push(v);
        Ok(())
    }
}

impl Drop for Vm<'_> {
    fn drop(&mut self) {
        let mut stack = std::mem::take(&mut self.stack);
        stack.extend(self.memo.drain().map(|(_, v)| v));
        drain_nested(&mut stack);
    }
}

/// Inserts `items` (key, value, key, value, ...) into `dict`; `at` (the opcode's byte) for errors.
fn set_items(dict: &mut Dict, items: Vec<Value>, at: usize) -> VmResult<()> {
    if !items.len().is_multiple_of(2) {
        return Err(format!("SETITEMS with an odd number of items at byte {at}"));
    }
    let mut it = items.into_iter();
    while let (Some(k), Some(v)) = (it.next(), it.next()) {
        dict.insert(k, v);
    }
    Ok(())
}

/// A little-endian two's-complement integer (LONG1, LONG4).
fn long(bytes: &[u8]) -> Value {
    if bytes.is_empty() {
        return Value::Int(0);
    }
    let negative = bytes[bytes.len() - 1] & 0x80 != 0;
    let fill = if negative { 0xff } else { 0 };
    if bytes.len() > 8 {
        let fits = bytes[8..].iter().all(|&b| b == fill) && ((bytes[7] & 0x80 != 0) == negative);
        if !fits {
            return Value::Opaque(Rc::from("int beyond 64 bits"));
        }
    }
    let mut a = [fill; 8];
    let n = bytes.len().min(8);
    a[..n].copy_from_slice(&bytes[..n]);
    Value::Int(i64::from_le_bytes(a))
}

/// The error for an opcode the machine does not know, read at byte `at`.
fn unsupported(op: u8, at: usize) -> String {
    format!("unsupported pickle opcode 0x{op:02x} at byte {at} (not a torch.save pickle?)")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(bytes: &[u8]) -> VmResult<Value> {
        Vm::new(bytes).run()
    }

    #[test]
    fn long_decodes_twos_complement() {
        assert!(matches!(long(&[]), Value::Int(0)));
        assert!(matches!(long(&[0xff]), Value::Int(-1)));
        assert!(matches!(long(&[0x00, 0x01]), Value::Int(256)));
        assert!(matches!(long(&[0xff, 0x7f]), Value::Int(32767)));
        assert!(matches!(long(&[0x00, 0x80]), Value::Int(-32768)));
        // Nine bytes that still fit, and nine that do not.
        assert!(matches!(long(&[1, 0, 0, 0, 0, 0, 0, 0, 0]), Value::Int(1)));
        assert!(matches!(
            long(&[0, 0, 0, 0, 0, 0, 0, 0, 1]),
            Value::Opaque(_)
        ));
    }

    #[test]
    fn vm_builds_nested_containers_and_memo() {
        // {'a': [1, 2.5, None], 'b': (True,)} with the list memoized and fetched again.
        let mut p = vec![
            0x80, 2, b'}', b'q', 0, b'(', 0x8c, 1, b'a', b']', b'q', 1, b'(', b'K', 1,
        ];
        p.push(b'G');
        p.extend_from_slice(&2.5f64.to_be_bytes());
        p.extend_from_slice(&[
            b'N', b'e', 0x8c, 1, b'b', 0x88, 0x85, 0x8c, 1, b'c', b'h', 1,
        ]);
        p.extend_from_slice(b"u.");
        let Value::Dict(d) = run(&p).unwrap() else {
            panic!("not a dict")
        };
        let d = d.borrow();
        assert_eq!(d.items.len(), 3);
        let Some(Value::List(a)) = d.get_str("a") else {
            panic!("a is not a list")
        };
        assert_eq!(a.borrow().0.len(), 3);
        let Some(Value::List(c)) = d.get_str("c") else {
            panic!("c is not a list")
        };
        // The memo shares the list rather than copying it.
        assert!(Rc::ptr_eq(a, c));
        assert!(
            matches!(d.get_str("b"), Some(Value::Tuple(t)) if matches!(t.0[0], Value::Bool(true)))
        );
    }

    #[test]
    fn vm_rejects_bad_input_without_panicking() {
        for bad in [
            &b""[..],
            &[0x80, 2],
            &[0x80, 9, b'.'],
            &[b'X', 0xff, 0xff, 0xff, 0x7f],
            &[b'h', 7, b'.'],
            b"u.",
            b"(0.",
            b".",
            &[0x85, b'.'],
            b"I1\n.",
        ] {
            assert!(run(bad).is_err(), "{bad:?} was accepted");
        }
    }

    #[test]
    fn deep_nesting_drops_without_overflowing_the_stack() {
        // 200,000 nested lists: a recursive drop would overflow a 2 MiB test thread stack.
        let n = 200_000;
        let mut p = vec![0x80, 2];
        p.extend(std::iter::repeat_n(b']', n));
        p.extend(std::iter::repeat_n(b'a', n - 1));
        p.push(b'.');
        assert!(matches!(run(&p), Ok(Value::List(_))));
    }

    #[test]
    fn unknown_globals_are_opaque_and_nothing_runs() {
        // os.system('x') becomes an opaque object inside the dict; parsing goes on.
        let mut p = vec![0x80, 2, b'}', b'(', 0x8c, 1, b'k'];
        p.extend_from_slice(b"cos\nsystem\n");
        p.extend_from_slice(&[0x8c, 1, b'x', 0x85, b'R', b'u', b'.']);
        let Value::Dict(d) = run(&p).unwrap() else {
            panic!("not a dict")
        };
        let d = d.borrow();
        assert!(matches!(d.get_str("k"), Some(Value::Opaque(w)) if w.as_ref() == "os.system"));
    }
}
