//! The reader: an open `torch.save` zip archive, the state dict found in its unpickled
//! `data.pkl`, and each tensor's bytes read from its storage entry on demand.

use std::fs::File;
use std::io::{BufReader, Read, Seek};
use std::path::{Path, PathBuf};

use zip::result::ZipError;
use zip::{CompressionMethod, ZipArchive};

use super::pickle::Vm;
use super::storage::{decode, gather, is_contiguous, StorageType};
use super::value::Value;
use crate::model::{Tensor, TensorData};
use crate::{Error, Result};

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::torch::writer::state_dict_pickle;

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
