//! The writer: a state dict as a `torch.save` zip archive, with the protocol 2 pickle that
//! describes it.

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use zip::result::ZipError;
use zip::write::SimpleFileOptions;
use zip::{CompressionMethod, ZipWriter};

use crate::model::{shape_string, Tensor, TensorData};
use crate::{Error, Result};

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
pub(super) fn state_dict_pickle(entries: &[(String, Tensor)], location: &str) -> Vec<u8> {
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
