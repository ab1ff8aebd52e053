//! PyTorch `torch.save` archives: a reader that returns the state dict, and a writer.
//!
//! The format (PyTorch 1.6 and later) is a zip archive with stored (uncompressed) entries under one
//! top folder of any name:
//!
//! * `<top>/data.pkl`: a pickle (protocol 2) of the saved object. Tensors appear as calls to
//!   `torch._utils._rebuild_tensor_v2(storage, offset, size, stride, requires_grad, hooks[, metadata])`
//!   whose storage is a *persistent id* `('storage', torch.FloatStorage, key, location, numel)`;
//! * `<top>/data/<key>`: the raw little-endian bytes of each storage;
//! * `<top>/byteorder` (`little`) and `<top>/version`.
//!
//! The pickle is read by a small stack machine that understands the opcodes pickle writes for plain
//! data and **executes nothing**: a handful of known callables (`OrderedDict`, the tensor rebuild
//! functions, `_codecs.encode`) are interpreted, and any other global becomes an opaque object, so a
//! Lightning checkpoint's optimizer states and hyper-parameters are walked past. Storage bytes are
//! read lazily, only for the tensors asked for, and every size is checked against the real entry
//! lengths: a truncated or foreign file gives an error naming the file, never a panic or a huge
//! allocation.

use std::cell::RefCell;
use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, Write};
use std::path::{Path, PathBuf};
use std::rc::Rc;

use zip::result::ZipError;
use zip::write::SimpleFileOptions;
use zip::{CompressionMethod, ZipArchive, ZipWriter};

use super::{shape_string, Tensor, TensorData};
use crate::{Error, Result};

/// The element type of a PyTorch storage, from its class name (`torch.FloatStorage`, ...).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StorageType {
    /// `FloatStorage`: float32.
    F32,
    /// `DoubleStorage`: float64 (read as float32).
    F64,
    /// `HalfStorage`: float16 (read as float32).
    F16,
    /// `BFloat16Storage`: bfloat16 (read as float32).
    BF16,
    /// `LongStorage`: int64.
    I64,
    /// `IntStorage`: int32 (read as int64).
    I32,
    /// `ShortStorage`: int16 (read as int64).
    I16,
    /// `CharStorage`: int8 (read as int64).
    I8,
    /// `ByteStorage` and `UntypedStorage`: uint8 (read as int64).
    U8,
    /// `BoolStorage`: bool (read as int64 0 or 1).
    Bool,
}

impl StorageType {
    /// The type for a storage class, e.g. `("torch", "FloatStorage")`.
    fn from_class(module: &str, name: &str) -> Option<Self> {
        if !matches!(module, "torch" | "torch.cuda" | "torch.storage") {
            return None;
        }
        Some(match name {
            "FloatStorage" => StorageType::F32,
            "DoubleStorage" => StorageType::F64,
            "HalfStorage" => StorageType::F16,
            "BFloat16Storage" => StorageType::BF16,
            "LongStorage" => StorageType::I64,
            "IntStorage" => StorageType::I32,
            "ShortStorage" => StorageType::I16,
            "CharStorage" => StorageType::I8,
            "ByteStorage" | "UntypedStorage" => StorageType::U8,
            "BoolStorage" => StorageType::Bool,
            _ => return None,
        })
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            StorageType::F64 | StorageType::I64 => 8,
            StorageType::F32 | StorageType::I32 => 4,
            StorageType::F16 | StorageType::BF16 | StorageType::I16 => 2,
            StorageType::I8 | StorageType::U8 | StorageType::Bool => 1,
        }
    }

    /// The dtype's name as PyTorch spells it.
    pub fn name(self) -> &'static str {
        match self {
            StorageType::F32 => "float32",
            StorageType::F64 => "float64",
            StorageType::F16 => "float16",
            StorageType::BF16 => "bfloat16",
            StorageType::I64 => "int64",
            StorageType::I32 => "int32",
            StorageType::I16 => "int16",
            StorageType::I8 => "int8",
            StorageType::U8 => "uint8",
            StorageType::Bool => "bool",
        }
    }

    /// Whether the elements are floats (read as [`TensorData::F32`]).
    pub fn is_float(self) -> bool {
        matches!(
            self,
            StorageType::F32 | StorageType::F64 | StorageType::F16 | StorageType::BF16
        )
    }
}

/// One tensor of a state dict, described by the pickle; its data stays in the archive until
/// [`TorchArchive::load`] reads it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TensorEntry {
    /// The state-dict key.
    pub name: String,
    /// The tensor's shape (empty for a scalar).
    pub shape: Vec<usize>,
    /// The element type as stored.
    pub dtype: StorageType,
    storage_key: String,
    storage_numel: u64,
    offset: usize,
    stride: Vec<usize>,
}

/// An open `torch.save` archive whose state dict has been parsed (but whose tensors have not been
/// read).
pub struct TorchArchive {
    path: PathBuf,
    zip: ZipArchive<BufReader<File>>,
    file_len: u64,
    top: String,
    nested: bool,
    entries: Vec<TensorEntry>,
}

impl std::fmt::Debug for TorchArchive {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TorchArchive")
            .field("path", &self.path)
            .field("top", &self.top)
            .field("nested", &self.nested)
            .field("entries", &self.entries.len())
            .finish()
    }
}

/// Reads the state dict of the checkpoint at `path`: every tensor, in the file's order.
///
/// A Lightning checkpoint (a dict with a `state_dict` entry) gives that entry's tensors; keys are
/// returned as stored (with Lightning's `model.` prefix, if any).
pub fn read_state_dict(path: &Path) -> Result<Vec<(String, Tensor)>> {
    let mut archive = TorchArchive::open(path)?;
    let mut out = Vec::with_capacity(archive.entries.len());
    for i in 0..archive.entries.len() {
        let tensor = archive.load(i)?;
        out.push((archive.entries[i].name.clone(), tensor));
    }
    Ok(out)
}

impl TorchArchive {
    /// Opens the archive at `path` and parses its `data.pkl`.
    pub fn open(path: &Path) -> Result<Self> {
        let mut file = File::open(path).map_err(|e| Error::io(path, e))?;
        let file_len = file.metadata().map_err(|e| Error::io(path, e))?.len();
        let mut head = [0u8; 512];
        let mut got = 0;
        while got < head.len() {
            let n = file
                .read(&mut head[got..])
                .map_err(|e| Error::io(path, e))?;
            if n == 0 {
                break;
            }
            got += n;
        }
        if let Some(what) = not_a_zip(&head[..got], file_len) {
            return Err(Error::format(path, what));
        }
        file.rewind().map_err(|e| Error::io(path, e))?;
        let zip = ZipArchive::new(BufReader::new(file)).map_err(|e| {
            Error::format(
                path,
                format!("not a readable zip archive (truncated or damaged?): {e}"),
            )
        })?;
        let mut names = Vec::with_capacity(zip.len());
        for name in zip.file_names() {
            match name {
                Ok(n) => names.push(n.into_owned()),
                Err(e) => {
                    return Err(Error::format(path, format!("unreadable entry name: {e}")));
                }
            }
        }
        let top = find_top(path, &names)?;
        let mut archive = TorchArchive {
            path: path.to_path_buf(),
            zip,
            file_len,
            top,
            nested: false,
            entries: Vec::new(),
        };
        let byteorder_name = format!("{}/byteorder", archive.top);
        if names.contains(&byteorder_name) {
            let order = archive.read_entry(&byteorder_name, 64)?;
            let order = String::from_utf8_lossy(&order);
            if order.trim() != "little" {
                return Err(Error::format(
                    path,
                    format!(
                        "byteorder is {:?}: only little-endian archives are supported",
                        order.trim()
                    ),
                ));
            }
        }
        let pickle = archive.read_entry(&format!("{}/data.pkl", archive.top), file_len)?;
        let top_value = Vm::new(&pickle)
            .run()
            .map_err(|e| Error::format(path, format!("{}/data.pkl: {e}", archive.top)))?;
        drop(pickle);
        let (entries, nested) = collect_entries(path, top_value)?;
        archive.entries = entries;
        archive.nested = nested;
        Ok(archive)
    }

    /// The archive's file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The state dict's tensors, in the file's order (not yet read).
    pub fn entries(&self) -> &[TensorEntry] {
        &self.entries
    }

    /// Whether the state dict came from a `state_dict` entry of a larger dict (a Lightning
    /// checkpoint) rather than being the saved object itself.
    pub fn nested(&self) -> bool {
        self.nested
    }

    /// Reads the data of entry `index` (an index into [`entries`](Self::entries)).
    pub fn load(&mut self, index: usize) -> Result<Tensor> {
        let entry = self.entries.get(index).cloned().ok_or_else(|| {
            Error::invalid(
                "tensor index",
                format!("{index} is past the {} entries", self.entries.len()),
            )
        })?;
        let entry_name = format!("{}/data/{}", self.top, entry.storage_key);
        let path = self.path.clone();
        let fail = |message: String| {
            Error::format(
                &path,
                format!("tensor {} (storage {}): {message}", entry.name, entry_name),
            )
        };
        let esize = entry.dtype.size() as u64;
        let mut file = self.zip.by_name(&entry_name).map_err(|e| match e {
            ZipError::FileNotFound => fail("the storage entry is missing".into()),
            other => fail(other.to_string()),
        })?;
        if file.compression() != CompressionMethod::Stored {
            return Err(fail(format!(
                "compressed (zip method {:?}): {RESAVE}",
                file.compression()
            )));
        }
        let expected = entry
            .storage_numel
            .checked_mul(esize)
            .ok_or_else(|| fail("storage size overflows".into()))?;
        if file.size() != expected {
            return Err(fail(format!(
                "the entry holds {} bytes but the pickle describes {} {} elements ({} bytes)",
                file.size(),
                entry.storage_numel,
                entry.dtype.name(),
                expected
            )));
        }
        if expected > self.file_len {
            return Err(fail(format!(
                "{expected} bytes claimed, more than the whole file ({} bytes)",
                self.file_len
            )));
        }
        let numel: usize = entry.shape.iter().product();
        let contiguous = is_contiguous(&entry.shape, &entry.stride);
        // The span of storage elements the tensor touches (checked against numel at parse time).
        let span = if numel == 0 {
            0
        } else if contiguous {
            numel
        } else {
            1 + entry
                .shape
                .iter()
                .zip(&entry.stride)
                .map(|(&n, &s)| (n - 1) * s)
                .sum::<usize>()
        };
        let skip = entry.offset as u64 * esize;
        std::io::copy(&mut (&mut file).take(skip), &mut std::io::sink())
            .map_err(|e| fail(format!("reading: {e}")))?;
        let mut bytes = vec![0u8; span * esize as usize];
        file.read_exact(&mut bytes)
            .map_err(|e| fail(format!("reading (truncated file?): {e}")))?;
        let data = decode(entry.dtype, &bytes);
        drop(bytes);
        let data = if contiguous {
            data
        } else {
            match data {
                TensorData::F32(v) => TensorData::F32(gather(&v, &entry.shape, &entry.stride)),
                TensorData::I64(v) => TensorData::I64(gather(&v, &entry.shape, &entry.stride)),
            }
        };
        Ok(Tensor {
            shape: entry.shape,
            data,
        })
    }

    /// Reads a whole (small) entry, refusing more than `limit` bytes.
    fn read_entry(&mut self, name: &str, limit: u64) -> Result<Vec<u8>> {
        let path = self.path.clone();
        let mut file = self
            .zip
            .by_name(name)
            .map_err(|e| Error::format(&path, format!("{name}: {e}")))?;
        if file.compression() != CompressionMethod::Stored {
            return Err(Error::format(
                &path,
                format!(
                    "{name}: compressed (zip method {:?}): {RESAVE}",
                    file.compression()
                ),
            ));
        }
        let size = file.size();
        if size > limit || size > self.file_len {
            return Err(Error::format(
                &path,
                format!("{name}: claims {size} bytes, more than the file can hold"),
            ));
        }
        let mut buf = Vec::with_capacity(size as usize);
        (&mut file)
            .take(size)
            .read_to_end(&mut buf)
            .map_err(|e| Error::format(&path, format!("{name}: reading (truncated file?): {e}")))?;
        if buf.len() as u64 != size {
            return Err(Error::format(
                &path,
                format!(
                    "{name}: {} of {size} bytes present (truncated file)",
                    buf.len()
                ),
            ));
        }
        Ok(buf)
    }
}

/// The advice for an archive whose entries were compressed after torch.save wrote it.
const RESAVE: &str = "torch.save stores entries uncompressed and only such archives are read; \
                      load it with PyTorch and save it again";

/// Says what a file is when it does not start like a zip archive, or `None` when it does.
fn not_a_zip(head: &[u8], len: u64) -> Option<String> {
    if head.starts_with(b"PK\x03\x04") || head.starts_with(b"PK\x05\x06") {
        return None;
    }
    if len == 0 {
        return Some("empty file, not a PyTorch checkpoint".into());
    }
    // A legacy torch.save file starts with a pickled magic number (a LONG1 of 10 bytes).
    if head.len() >= 3 && head[0] == 0x80 && head[2] == 0x8a {
        return Some(
            "a legacy PyTorch file (the pre-1.6 format, a bare pickle stream), not a zip archive; \
             load it with PyTorch and save it again with a current version"
                .into(),
        );
    }
    if head.first() == Some(&0x80) {
        return Some("a bare pickle, not a PyTorch zip archive".into());
    }
    if head.len() > 262 && &head[257..262] == b"ustar" {
        return Some(
            "a tar archive (the oldest PyTorch format?), not a PyTorch zip archive".into(),
        );
    }
    if head.len() >= 9 && head[8] == b'{' {
        return Some(
            "a safetensors file (or other JSON-headed file), not a PyTorch zip archive".into(),
        );
    }
    let shown: Vec<String> = head.iter().take(8).map(|b| format!("{b:02x}")).collect();
    Some(format!(
        "not a PyTorch checkpoint: no zip signature (the file starts with {})",
        shown.join(" ")
    ))
}

/// The top folder holding `data.pkl`.
fn find_top(path: &Path, names: &[String]) -> Result<String> {
    let candidates: Vec<&str> = names
        .iter()
        .filter_map(|n| n.strip_suffix("/data.pkl"))
        .filter(|top| !top.is_empty() && !top.contains('/'))
        .collect();
    let first_top = names.first().and_then(|n| n.split('/').next());
    if let Some(top) = first_top {
        if candidates.contains(&top) {
            return Ok(top.to_string());
        }
    }
    match candidates.as_slice() {
        [one] => Ok(one.to_string()),
        [] => {
            let torchscript = names
                .iter()
                .any(|n| n.ends_with("/constants.pkl") || n.contains("/code/"));
            let listed: Vec<&str> = names.iter().take(5).map(String::as_str).collect();
            let what = if torchscript {
                "a TorchScript archive (torch.jit.save), not a torch.save state dict".to_string()
            } else {
                format!(
                    "a zip archive without <folder>/data.pkl, so not a torch.save archive \
                     ({} entries: {}{})",
                    names.len(),
                    listed.join(", "),
                    if names.len() > listed.len() {
                        ", ..."
                    } else {
                        ""
                    }
                )
            };
            Err(Error::format(path, what))
        }
        several => Err(Error::format(
            path,
            format!(
                "several data.pkl folders ({}): ambiguous archive",
                several.join(", ")
            ),
        )),
    }
}

/// Whether `stride` is the row-major stride of `shape` (ignoring dimensions of size 1).
fn is_contiguous(shape: &[usize], stride: &[usize]) -> bool {
    let mut expected = 1usize;
    for (&n, &s) in shape.iter().zip(stride).rev() {
        if n != 1 && s != expected {
            return false;
        }
        expected = expected.saturating_mul(n);
    }
    true
}

/// Row-major copy of a strided view whose element (0, ..., 0) is `span[0]`.
fn gather<T: Copy>(span: &[T], shape: &[usize], stride: &[usize]) -> Vec<T> {
    let numel: usize = shape.iter().product();
    let mut out = Vec::with_capacity(numel);
    if numel == 0 {
        return out;
    }
    let mut index = vec![0usize; shape.len()];
    let mut at = 0usize;
    loop {
        out.push(span[at]);
        // Odometer increment, last dimension fastest.
        let mut d = shape.len();
        loop {
            if d == 0 {
                return out;
            }
            d -= 1;
            index[d] += 1;
            at += stride[d];
            if index[d] < shape[d] {
                break;
            }
            at -= stride[d] * shape[d];
            index[d] = 0;
        }
    }
}

/// Decodes little-endian storage bytes (a whole number of elements) into tensor data.
fn decode(dtype: StorageType, bytes: &[u8]) -> TensorData {
    fn each<const N: usize, T>(bytes: &[u8], f: impl Fn([u8; N]) -> T) -> Vec<T> {
        bytes
            .chunks_exact(N)
            .map(|c| {
                let mut a = [0u8; N];
                a.copy_from_slice(c);
                f(a)
            })
            .collect()
    }
    match dtype {
        StorageType::F32 => TensorData::F32(each(bytes, f32::from_le_bytes)),
        StorageType::F64 => TensorData::F32(each(bytes, |b| f64::from_le_bytes(b) as f32)),
        StorageType::F16 => TensorData::F32(each(bytes, |b| f16_to_f32(u16::from_le_bytes(b)))),
        StorageType::BF16 => TensorData::F32(each(bytes, |b: [u8; 2]| {
            f32::from_bits(u32::from(u16::from_le_bytes(b)) << 16)
        })),
        StorageType::I64 => TensorData::I64(each(bytes, i64::from_le_bytes)),
        StorageType::I32 => TensorData::I64(each(bytes, |b| i64::from(i32::from_le_bytes(b)))),
        StorageType::I16 => TensorData::I64(each(bytes, |b| i64::from(i16::from_le_bytes(b)))),
        StorageType::I8 => TensorData::I64(each(bytes, |b: [u8; 1]| i64::from(b[0] as i8))),
        StorageType::U8 => TensorData::I64(each(bytes, |b: [u8; 1]| i64::from(b[0]))),
        StorageType::Bool => TensorData::I64(each(bytes, |b: [u8; 1]| i64::from(b[0] != 0))),
    }
}

/// IEEE half precision to single precision (exact).
fn f16_to_f32(h: u16) -> f32 {
    let sign = u32::from(h >> 15) << 31;
    let exp = u32::from((h >> 10) & 0x1f);
    let mant = u32::from(h & 0x3ff);
    if exp == 0 {
        // Zero or subnormal: mant * 2^-24, exact in f32.
        let v = mant as f32 * (1.0 / 16_777_216.0);
        return if sign != 0 { -v } else { v };
    }
    let bits = if exp == 31 {
        sign | 0x7f80_0000 | (mant << 13)
    } else {
        sign | ((exp + 112) << 23) | (mant << 13)
    };
    f32::from_bits(bits)
}

/// Finds the state dict in the unpickled object and lists its tensors.
fn collect_entries(path: &Path, top: Value) -> Result<(Vec<TensorEntry>, bool)> {
    let Value::Dict(dict) = top else {
        return Err(Error::format(
            path,
            format!("data.pkl holds {}, not a dict of tensors", top.kind()),
        ));
    };
    let inner = match dict.borrow().get_str("state_dict") {
        Some(Value::Dict(inner)) => Some(inner.clone()),
        Some(other) => {
            return Err(Error::format(
                path,
                format!(
                    "the checkpoint's state_dict entry is {}, not a dict",
                    other.kind()
                ),
            ));
        }
        None => None,
    };
    let (source, nested) =
        match inner {
            Some(inner) => (inner, true),
            None => {
                let d = dict.borrow();
                let any_tensor = d.items.iter().any(|(_, v)| matches!(v, Value::Tensor(_)));
                if !any_tensor && !d.items.is_empty() {
                    let keys: Vec<String> =
                        d.items.iter().take(8).map(|(k, _)| k.short()).collect();
                    return Err(Error::format(
                        path,
                        format!(
                        "no state dict: the saved dict holds no tensor and no 'state_dict' entry \
                         (its keys: {}{})",
                        keys.join(", "),
                        if d.items.len() > keys.len() { ", ..." } else { "" }
                    ),
                    ));
                }
                drop(d);
                (dict, false)
            }
        };
    let source = source.borrow();
    let mut entries = Vec::with_capacity(source.items.len());
    for (key, value) in &source.items {
        let Value::Str(name) = key else {
            return Err(Error::format(
                path,
                format!("state-dict key {} is not a string", key.short()),
            ));
        };
        let Value::Tensor(t) = value else {
            return Err(Error::format(
                path,
                format!("state-dict entry {name} is {}, not a tensor", value.kind()),
            ));
        };
        entries.push(TensorEntry {
            name: name.to_string(),
            shape: t.shape.clone(),
            dtype: t.storage.dtype,
            storage_key: t.storage.key.to_string(),
            storage_numel: t.storage.numel,
            offset: t.offset,
            stride: t.stride.clone(),
        });
    }
    Ok((entries, nested))
}

// ---------------------------------------------------------------------------------------------
// The pickle machine.

/// A persistent storage reference.
#[derive(Debug)]
struct StorageRef {
    dtype: StorageType,
    key: Rc<str>,
    numel: u64,
}

/// A tensor described by `_rebuild_tensor_v2`.
#[derive(Debug)]
struct TensorRef {
    storage: Rc<StorageRef>,
    offset: usize,
    shape: Vec<usize>,
    stride: Vec<usize>,
}

/// The values the machine builds. Containers are shared (`Rc`) because the memo can refer to them
/// after they are pushed; their contents are dropped iteratively (see [`Items`]).
#[derive(Clone, Debug)]
enum Value {
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
    fn kind(&self) -> String {
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
    fn short(&self) -> String {
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
struct Items(Vec<Value>);

impl Drop for Items {
    fn drop(&mut self) {
        let mut stack = std::mem::take(&mut self.0);
        drain_nested(&mut stack);
    }
}

/// Drops the values on `stack`, moving the contents of containers owned only by them onto the
/// stack instead of recursing.
fn drain_nested(stack: &mut Vec<Value>) {
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
struct Dict {
    items: Vec<(Value, Value)>,
    index: HashMap<Key, usize>,
}

impl Dict {
    fn insert(&mut self, key: Value, value: Value) {
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

    fn get_str(&self, key: &str) -> Option<&Value> {
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

type VmResult<T> = std::result::Result<T, String>;

/// How deep `_rebuild_from_type_v2` may nest calls.
const MAX_CALL_DEPTH: usize = 8;
/// The most dimensions a tensor may have (PyTorch allows 64).
const MAX_RANK: usize = 64;

/// The stack machine for one pickle.
struct Vm<'a> {
    data: &'a [u8],
    pos: usize,
    stack: Vec<Value>,
    marks: Vec<usize>,
    memo: HashMap<u32, Value>,
}

impl<'a> Vm<'a> {
    fn new(data: &'a [u8]) -> Self {
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

    fn run(mut self) -> VmResult<Value> {
        loop {
            let at = self.pos;
            let op = self.byte()?;
            match op {
                0x80 => {
                    let protocol = self.byte()?;
                    if protocol > 5 {
                        return Err(format!("unsupported pickle protocol {protocol}"));
                    }
                }
                0x95 => {
                    self.take(8)?; // FRAME: a length hint only
                }
                b'.' => return self.pop(),
                b'(' => self.marks.push(self.stack.len()),
                b'0' => {
                    self.pop()?;
                }
                b'1' => {
                    self.pop_mark()?;
                }
                b'2' => {
                    let v = self.top()?.clone();
                    self.push(v);
                }
                b'N' => self.push(Value::None),
                0x88 => self.push(Value::Bool(true)),
                0x89 => self.push(Value::Bool(false)),
                b'J' => {
                    let v = i32::from_le_bytes(self.array()?);
                    self.push(Value::Int(i64::from(v)));
                }
                b'K' => {
                    let v = self.byte()?;
                    self.push(Value::Int(i64::from(v)));
                }
                b'M' => {
                    let v = u16::from_le_bytes(self.array()?);
                    self.push(Value::Int(i64::from(v)));
                }
                0x8a => {
                    let n = self.byte()?;
                    let bytes = self.take(u64::from(n))?;
                    self.push(long(bytes));
                }
                0x8b => {
                    let n = self.u32()?;
                    let bytes = self.take(u64::from(n))?;
                    self.push(long(bytes));
                }
                b'G' => {
                    let v = f64::from_be_bytes(self.array()?);
                    self.push(Value::Float(v));
                }
                b'X' => {
                    let n = self.u32()?;
                    let v = self.string(u64::from(n))?;
                    self.push(v);
                }
                0x8c => {
                    let n = self.byte()?;
                    let v = self.string(u64::from(n))?;
                    self.push(v);
                }
                0x8d => {
                    let n = u64::from_le_bytes(self.array()?);
                    let v = self.string(n)?;
                    self.push(v);
                }
                b'T' => {
                    let n = self.u32()?;
                    let v = self.latin1(u64::from(n))?;
                    self.push(v);
                }
                b'U' => {
                    let n = self.byte()?;
                    let v = self.latin1(u64::from(n))?;
                    self.push(v);
                }
                b'B' => {
                    let n = self.u32()?;
                    let bytes = self.take(u64::from(n))?;
                    self.push(Value::Bytes(Rc::from(bytes)));
                }
                b'C' => {
                    let n = self.byte()?;
                    let bytes = self.take(u64::from(n))?;
                    self.push(Value::Bytes(Rc::from(bytes)));
                }
                0x8e | 0x96 => {
                    let n = u64::from_le_bytes(self.array()?);
                    let bytes = self.take(n)?;
                    self.push(Value::Bytes(Rc::from(bytes)));
                }
                b'}' => self.push(Value::Dict(Rc::default())),
                b']' => self.push(Value::List(Rc::default())),
                b')' => self.push(Value::Tuple(Rc::default())),
                0x8f => self.push(Value::List(Rc::default())), // EMPTY_SET, kept as a list
                0x90 => {
                    // ADDITEMS
                    let items = self.pop_mark()?;
                    match self.top()? {
                        Value::List(list) => list.borrow_mut().0.extend(items),
                        Value::Opaque(_) => {}
                        other => return Err(format!("ADDITEMS on {} at byte {at}", other.kind())),
                    }
                }
                0x91 => {
                    // FROZENSET
                    let items = self.pop_mark()?;
                    self.push(Value::List(Rc::new(RefCell::new(Items(items)))));
                }
                b't' => {
                    let items = self.pop_mark()?;
                    self.push(Value::Tuple(Rc::new(Items(items))));
                }
                0x85..=0x87 => {
                    let n = usize::from(op - 0x84);
                    let mut items = Vec::with_capacity(n);
                    for _ in 0..n {
                        items.push(self.pop()?);
                    }
                    items.reverse();
                    self.push(Value::Tuple(Rc::new(Items(items))));
                }
                b'l' => {
                    let items = self.pop_mark()?;
                    self.push(Value::List(Rc::new(RefCell::new(Items(items)))));
                }
                b'd' => {
                    let items = self.pop_mark()?;
                    let mut dict = Dict::default();
                    set_items(&mut dict, items, at)?;
                    self.push(Value::Dict(Rc::new(RefCell::new(dict))));
                }
                b'q' => {
                    let i = self.byte()?;
                    self.memo_put(u32::from(i))?;
                }
                b'r' => {
                    let i = self.u32()?;
                    self.memo_put(i)?;
                }
                0x94 => {
                    let i =
                        u32::try_from(self.memo.len()).map_err(|_| "memo too large".to_string())?;
                    self.memo_put(i)?;
                }
                b'h' => {
                    let i = self.byte()?;
                    let v = self.memo_get(u32::from(i))?;
                    self.push(v);
                }
                b'j' => {
                    let i = self.u32()?;
                    let v = self.memo_get(i)?;
                    self.push(v);
                }
                b'c' => {
                    let module = self.line()?.to_string();
                    let name = self.line()?.to_string();
                    self.push(Value::Global(Rc::new((module, name))));
                }
                0x93 => {
                    let name = self.pop()?;
                    let module = self.pop()?;
                    let (Value::Str(module), Value::Str(name)) = (module, name) else {
                        return Err(format!("STACK_GLOBAL without two strs at byte {at}"));
                    };
                    self.push(Value::Global(Rc::new((
                        module.to_string(),
                        name.to_string(),
                    ))));
                }
                b'R' => {
                    let args = self.pop()?;
                    let callable = self.pop()?;
                    let Value::Tuple(args) = args else {
                        return Err(format!(
                            "REDUCE with {} as arguments at byte {at}",
                            args.kind()
                        ));
                    };
                    let v = call(&callable, &args.0, 0).map_err(|e| format!("{e} (byte {at})"))?;
                    self.push(v);
                }
                0x81 => {
                    let _args = self.pop()?;
                    let cls = self.pop()?;
                    self.push(new_object(&cls));
                }
                0x92 => {
                    let _kwargs = self.pop()?;
                    let _args = self.pop()?;
                    let cls = self.pop()?;
                    self.push(new_object(&cls));
                }
                b'b' => {
                    // BUILD: the state of objects is not needed (an OrderedDict's _metadata,
                    // a Namespace's attributes).
                    let _state = self.pop()?;
                    self.top()?;
                }
                b's' => {
                    let value = self.pop()?;
                    let key = self.pop()?;
                    match self.top()? {
                        Value::Dict(d) => d.borrow_mut().insert(key, value),
                        Value::Opaque(_) => {}
                        other => return Err(format!("SETITEM on {} at byte {at}", other.kind())),
                    }
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    match self.top()? {
                        Value::Dict(d) => set_items(&mut d.borrow_mut(), items, at)?,
                        Value::Opaque(_) => {}
                        other => return Err(format!("SETITEMS on {} at byte {at}", other.kind())),
                    }
                }
                b'a' => {
                    let value = self.pop()?;
                    match self.top()? {
                        Value::List(l) => l.borrow_mut().0.push(value),
                        Value::Opaque(_) => {}
                        other => return Err(format!("APPEND on {} at byte {at}", other.kind())),
                    }
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    match self.top()? {
                        Value::List(l) => l.borrow_mut().0.extend(items),
                        Value::Opaque(_) => {}
                        other => return Err(format!("APPENDS on {} at byte {at}", other.kind())),
                    }
                }
                b'Q' => {
                    let pid = self.pop()?;
                    let storage =
                        persistent_storage(&pid).map_err(|e| format!("{e} (byte {at})"))?;
                    self.push(storage);
                }
                other => {
                    return Err(format!(
                        "unsupported pickle opcode 0x{other:02x} at byte {at} (not a torch.save pickle?)"
                    ));
                }
            }
        }
    }
}

impl Drop for Vm<'_> {
    fn drop(&mut self) {
        let mut stack = std::mem::take(&mut self.stack);
        stack.extend(self.memo.drain().map(|(_, v)| v));
        drain_nested(&mut stack);
    }
}

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

/// `cls.__new__(cls, ...)`: an OrderedDict becomes a dict, anything else an opaque object.
fn new_object(cls: &Value) -> Value {
    match cls {
        Value::Global(g) if g.0 == "collections" && g.1 == "OrderedDict" => {
            Value::Dict(Rc::default())
        }
        Value::Global(g) => Value::Opaque(Rc::from(format!("{}.{}", g.0, g.1).as_str())),
        other => Value::Opaque(Rc::from(format!("instance of {}", other.kind()).as_str())),
    }
}

/// Interprets a REDUCE: the few callables a state dict needs; anything else is opaque.
fn call(callable: &Value, args: &[Value], depth: usize) -> VmResult<Value> {
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
fn persistent_storage(pid: &Value) -> VmResult<Value> {
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

// ---------------------------------------------------------------------------------------------
// The writer.

/// Writes `entries` as a state dict (an `OrderedDict` of tensors) that `torch.load` reads: the
/// same layout PyTorch writes (`archive/data.pkl` as a protocol 2 pickle, `archive/data/N`,
/// `archive/byteorder`, `archive/version`), data aligned to 64 bytes. `location` is the device
/// tag recorded with each storage (`cpu`, `cuda:0`); readers map it as they like.
pub fn write_state_dict(path: &Path, entries: &[(String, Tensor)], location: &str) -> Result<()> {
    for (name, t) in entries {
        let numel: usize = t.shape.iter().product();
        if numel != t.len() {
            return Err(Error::invalid(
                "tensor",
                format!(
                    "{name}: shape {} holds {numel} elements but the data has {}",
                    shape_string(&t.shape),
                    t.len()
                ),
            ));
        }
    }
    let pickle = state_dict_pickle(entries, location);
    let file = File::create(path).map_err(|e| Error::io(path, e))?;
    let zip_err = |e: ZipError| match e {
        ZipError::Io(io) => Error::io(path, io),
        other => Error::format(path, format!("writing the zip archive: {other}")),
    };
    let io_err = |e: std::io::Error| Error::io(path, e);
    let mut zip = ZipWriter::new(BufWriter::with_capacity(1 << 20, file));
    let options = SimpleFileOptions::default()
        .compression_method(CompressionMethod::Stored)
        .with_alignment(64)
        .large_file(false);
    zip.start_file("archive/data.pkl", options)
        .map_err(zip_err)?;
    zip.write_all(&pickle).map_err(io_err)?;
    zip.start_file("archive/byteorder", options)
        .map_err(zip_err)?;
    zip.write_all(b"little").map_err(io_err)?;
    let mut buf = Vec::with_capacity(1 << 16);
    for (i, (_, t)) in entries.iter().enumerate() {
        let big = t.len() * 8 >= u32::MAX as usize;
        zip.start_file(format!("archive/data/{i}"), options.large_file(big))
            .map_err(zip_err)?;
        match &t.data {
            TensorData::F32(v) => {
                for chunk in v.chunks(1 << 14) {
                    buf.clear();
                    chunk
                        .iter()
                        .for_each(|x| buf.extend_from_slice(&x.to_le_bytes()));
                    zip.write_all(&buf).map_err(io_err)?;
                }
            }
            TensorData::I64(v) => {
                for chunk in v.chunks(1 << 13) {
                    buf.clear();
                    chunk
                        .iter()
                        .for_each(|x| buf.extend_from_slice(&x.to_le_bytes()));
                    zip.write_all(&buf).map_err(io_err)?;
                }
            }
        }
    }
    zip.start_file("archive/version", options)
        .map_err(zip_err)?;
    zip.write_all(b"3\n").map_err(io_err)?;
    let writer = zip.finish().map_err(zip_err)?;
    let file = writer
        .into_inner()
        .map_err(|e| Error::io(path, e.into_error()))?;
    file.sync_all().map_err(io_err)?;
    Ok(())
}

/// A protocol 2 pickle writer for the few shapes a state dict needs.
struct PickleWriter {
    out: Vec<u8>,
    memo_len: u32,
    globals: HashMap<(&'static str, &'static str), u32>,
}

impl PickleWriter {
    fn put(&mut self) {
        if self.memo_len < 256 {
            self.out.push(b'q');
            self.out.push(self.memo_len as u8);
        } else {
            self.out.push(b'r');
            self.out.extend_from_slice(&self.memo_len.to_le_bytes());
        }
        self.memo_len += 1;
    }

    fn global(&mut self, module: &'static str, name: &'static str) {
        if let Some(&i) = self.globals.get(&(module, name)) {
            if i < 256 {
                self.out.push(b'h');
                self.out.push(i as u8);
            } else {
                self.out.push(b'j');
                self.out.extend_from_slice(&i.to_le_bytes());
            }
            return;
        }
        self.out.push(b'c');
        self.out.extend_from_slice(module.as_bytes());
        self.out.push(b'\n');
        self.out.extend_from_slice(name.as_bytes());
        self.out.push(b'\n');
        self.globals.insert((module, name), self.memo_len);
        self.put();
    }

    fn int(&mut self, v: i64) {
        if (0..256).contains(&v) {
            self.out.push(b'K');
            self.out.push(v as u8);
        } else if (0..65536).contains(&v) {
            self.out.push(b'M');
            self.out.extend_from_slice(&(v as u16).to_le_bytes());
        } else if let Ok(small) = i32::try_from(v) {
            self.out.push(b'J');
            self.out.extend_from_slice(&small.to_le_bytes());
        } else {
            self.out.push(0x8a);
            self.out.push(8);
            self.out.extend_from_slice(&v.to_le_bytes());
        }
    }

    fn str(&mut self, s: &str) {
        self.out.push(b'X');
        self.out.extend_from_slice(&(s.len() as u32).to_le_bytes());
        self.out.extend_from_slice(s.as_bytes());
        self.put();
    }

    fn int_tuple(&mut self, values: &[usize]) {
        match values.len() {
            0 => self.out.push(b')'),
            n => {
                if n > 3 {
                    self.out.push(b'(');
                }
                for &v in values {
                    self.int(v as i64);
                }
                self.out.push(match n {
                    1 => 0x85,
                    2 => 0x86,
                    3 => 0x87,
                    _ => b't',
                });
            }
        }
    }
}

/// The `data.pkl` of a state dict: an OrderedDict of `_rebuild_tensor_v2` calls over storages
/// `data/0`, `data/1`, ...
fn state_dict_pickle(entries: &[(String, Tensor)], location: &str) -> Vec<u8> {
    let mut w = PickleWriter {
        out: vec![0x80, 2],
        memo_len: 0,
        globals: HashMap::new(),
    };
    w.global("collections", "OrderedDict");
    w.out.push(b')');
    w.out.push(b'R');
    w.put();
    for (batch_start, batch) in entries.chunks(1000).enumerate() {
        w.out.push(b'(');
        for (i, (name, t)) in batch.iter().enumerate() {
            let index = batch_start * 1000 + i;
            w.str(name);
            w.global("torch._utils", "_rebuild_tensor_v2");
            w.out.push(b'(');
            // The persistent id ('storage', type, key, location, numel).
            w.out.push(b'(');
            w.str("storage");
            match t.data {
                TensorData::F32(_) => w.global("torch", "FloatStorage"),
                TensorData::I64(_) => w.global("torch", "LongStorage"),
            }
            w.str(&index.to_string());
            w.str(location);
            w.int(t.len() as i64);
            w.out.push(b't');
            w.out.push(b'Q');
            w.int(0);
            w.int_tuple(&t.shape);
            let mut stride = vec![1usize; t.shape.len()];
            for d in (0..t.shape.len().saturating_sub(1)).rev() {
                stride[d] = stride[d + 1] * t.shape[d + 1];
            }
            w.int_tuple(&stride);
            w.out.push(0x89); // requires_grad = False
            w.global("collections", "OrderedDict");
            w.out.push(b')');
            w.out.push(b'R'); // backward hooks: OrderedDict()
            w.out.push(b't');
            w.out.push(b'R');
        }
        w.out.push(b'u');
    }
    w.out.push(b'.');
    w.out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(bytes: &[u8]) -> VmResult<Value> {
        Vm::new(bytes).run()
    }

    #[test]
    fn f16_conversion_is_exact() {
        assert_eq!(f16_to_f32(0x3c00), 1.0);
        assert_eq!(f16_to_f32(0xc000), -2.0);
        assert_eq!(f16_to_f32(0x0001), 2f32.powi(-24));
        assert_eq!(f16_to_f32(0x7bff), 65504.0);
        assert!(f16_to_f32(0x7c00).is_infinite());
        assert!(f16_to_f32(0x7e00).is_nan());
        assert_eq!(f16_to_f32(0x8000).to_bits(), (-0.0f32).to_bits());
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
    fn gather_transposes() {
        // A 2x3 row-major matrix viewed as its 3x2 transpose.
        let span = [1, 2, 3, 4, 5, 6];
        assert_eq!(gather(&span, &[3, 2], &[1, 3]), vec![1, 4, 2, 5, 3, 6]);
        assert!(is_contiguous(&[2, 3], &[3, 1]));
        assert!(!is_contiguous(&[3, 2], &[1, 3]));
        assert!(is_contiguous(&[1, 3], &[99, 1]));
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

    #[test]
    fn mutated_pickles_never_panic() {
        // Random byte changes to a real state-dict pickle: each gives entries or an error.
        let entries = vec![
            (
                "a.weight".to_string(),
                Tensor::f32(vec![2, 3], vec![0.5; 6]),
            ),
            ("a.count".to_string(), Tensor::i64(vec![], vec![3])),
            ("b".to_string(), Tensor::f32(vec![4], vec![1.0; 4])),
        ];
        let clean = state_dict_pickle(&entries, "cpu");
        let parsed = collect_entries(Path::new("x"), Vm::new(&clean).run().unwrap()).unwrap();
        assert_eq!(parsed.0.len(), 3);
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let (mut ok, mut err) = (0, 0);
        for _ in 0..20_000 {
            let mut p = clean.clone();
            for _ in 0..1 + next() % 4 {
                let at = (next() % p.len() as u64) as usize;
                p[at] = next() as u8;
            }
            match Vm::new(&p)
                .run()
                .map(|v| collect_entries(Path::new("x"), v))
            {
                Ok(Ok(_)) => ok += 1,
                _ => err += 1,
            }
        }
        // Both outcomes occur (some bytes are payload, e.g. inside names).
        assert!(ok > 0 && err > 0, "ok {ok}, err {err}");
    }

    #[test]
    fn sniffing_names_what_a_file_is() {
        let legacy = [0x80, 0x02, 0x8a, 0x0a, 0x6c, 0xfc];
        assert!(not_a_zip(&legacy, 100).is_some_and(|m| m.contains("legacy PyTorch")));
        assert!(not_a_zip(b"hello world", 11).is_some_and(|m| m.contains("no zip signature")));
        assert!(not_a_zip(b"", 0).is_some_and(|m| m.contains("empty")));
        assert!(not_a_zip(b"PK\x03\x04rest", 8).is_none());
    }
}
