//! What decides an output, hashed: the input's bytes (with a cheaper stamp of its size and
//! time) and everything else (settings, format, config, version).

use std::io::Read;
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

use super::manifest::Settings;
use super::options::Options;
use crate::error::{Error, Result};

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// SHA-256 of a file's bytes, or of a folder's files (names and bytes, in name order).
pub(crate) fn input_sha256(path: &Path) -> Result<String> {
    let mut h = Sha256::new();
    let feed = |p: &Path, h: &mut Sha256| -> Result<()> {
        let mut f = std::fs::File::open(p).map_err(|e| Error::io(p, e))?;
        let mut buf = vec![0u8; 1 << 16];
        loop {
            let n = f.read(&mut buf).map_err(|e| Error::io(p, e))?;
            if n == 0 {
                return Ok(());
            }
            h.update(&buf[..n]);
        }
    };
    if path.is_dir() {
        let mut files: Vec<PathBuf> = std::fs::read_dir(path)
            .map_err(|e| Error::io(path, e))?
            .filter_map(|e| Some(e.ok()?.path()))
            .filter(|p| p.is_file())
            .collect();
        files.sort();
        for f in files {
            h.update(f.file_name().unwrap_or_default().as_encoded_bytes());
            h.update([0]);
            feed(&f, &mut h)?;
        }
    } else {
        feed(path, &mut h)?;
    }
    Ok(hex(&h.finalize()))
}

/// The size and latest modification time (ns since the epoch) of a file, or of a folder's
/// files (and the folder itself); (0, 0) when it cannot be read.
pub(crate) fn input_stamp(path: &Path) -> (u64, i128) {
    let mtime = |m: &std::fs::Metadata| {
        m.modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_nanos() as i128)
    };
    match std::fs::metadata(path) {
        Ok(m) if m.is_dir() => {
            let files: Vec<std::fs::Metadata> = std::fs::read_dir(path)
                .map(|d| {
                    d.filter_map(|e| e.ok()?.metadata().ok())
                        .filter(|m| m.is_file())
                        .collect()
                })
                .unwrap_or_default();
            let bytes = files.iter().map(|m| m.len()).sum();
            let latest = files.iter().map(mtime).max().unwrap_or(0).max(mtime(&m));
            (bytes, latest)
        }
        Ok(m) => (m.len(), mtime(&m)),
        Err(_) => (0, 0),
    }
}

pub(super) fn settings_sha256(settings: &Settings, options: &Options) -> String {
    let mut h = Sha256::new();
    h.update(serde_json::to_string(settings).unwrap_or_default());
    h.update([0]);
    h.update(format!("{:?}", options.format));
    h.update([0]);
    h.update(&options.config_text);
    h.update([0]);
    h.update(env!("CARGO_PKG_VERSION"));
    hex(&h.finalize())
}
