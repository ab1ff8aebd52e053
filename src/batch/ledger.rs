//! The per-shard JSONL ledger in the output folder: one [`Record`] a line for each item
//! converted or failed, appended by one task per shard at a time (a lock), read back by every
//! later run and by the report.

use std::collections::BTreeMap;
use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};

use super::manifest::Settings;
use super::shard::Shard;
use crate::error::{Error, Result};

/// The folder of the ledgers, inside the output folder.
pub(crate) const LEDGER_DIR: &str = ".v2ce-batch";

/// One line of a ledger: an item converted or failed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct Record {
    /// The input as the manifest names it.
    pub input: String,
    /// The output, relative to the output folder.
    pub output: String,
    /// `done` or `failed`.
    pub status: String,
    /// Why it failed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// SHA-256 of the input's bytes (a folder: of its files' names and bytes, in name order).
    pub input_sha256: String,
    /// The input's size and latest modification (ns since the epoch) when it was hashed: a
    /// re-run trusts the hash while both are unchanged instead of reading the input again.
    #[serde(default)]
    pub input_stamp: (u64, i128),
    /// The item's settings.
    pub settings: Settings,
    /// SHA-256 of everything else that decides the output: settings, format, config, version.
    pub settings_sha256: String,
    /// The v2ce version that wrote it.
    pub version: String,
    /// Frames read.
    pub frames: u64,
    /// Events written.
    pub events: u64,
    /// Time from the first frame to the last, us.
    pub span_us: i64,
    /// Bytes of the output file.
    pub bytes: u64,
    /// Seconds the conversion took.
    pub wall_s: f64,
    /// The shard that did it, `I/N`.
    pub shard: String,
    /// When it finished, seconds since the Unix epoch.
    pub finished_unix: f64,
}

/// The ledgers' folder in `out`.
fn ledger_dir(out: &Path) -> PathBuf {
    out.join(LEDGER_DIR)
}

/// Every record of every ledger in `out`, in file then line order. A last line cut short (a
/// task killed while writing it) is ignored.
pub(crate) fn read_records(out: &Path) -> Result<Vec<Record>> {
    let dir = ledger_dir(out);
    let mut files: Vec<PathBuf> = match std::fs::read_dir(&dir) {
        Ok(d) => d
            .filter_map(|e| Some(e.ok()?.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "jsonl"))
            .collect(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(Error::io(&dir, e)),
    };
    files.sort();
    let mut records = Vec::new();
    for f in files {
        let file = std::fs::File::open(&f).map_err(|e| Error::io(&f, e))?;
        for line in std::io::BufReader::new(file).lines() {
            let line = line.map_err(|e| Error::io(&f, e))?;
            if let Ok(r) = serde_json::from_str::<Record>(&line) {
                records.push(r);
            }
        }
    }
    Ok(records)
}

/// The latest record of each output.
pub(super) fn latest(records: Vec<Record>) -> BTreeMap<String, Record> {
    let mut by_output = BTreeMap::new();
    for r in records {
        let newer = by_output
            .get(&r.output)
            .is_none_or(|old: &Record| old.finished_unix <= r.finished_unix);
        if newer {
            by_output.insert(r.output.clone(), r);
        }
    }
    by_output
}

/// Appends records to this shard's ledger, one whole line per write.
pub(super) struct Ledger {
    path: PathBuf,
    file: Mutex<std::fs::File>,
}

impl Ledger {
    pub(super) fn open(out: &Path, shard: Shard) -> Result<Ledger> {
        let dir = ledger_dir(out);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        let path = dir.join(format!("shard-{}-of-{}.jsonl", shard.index, shard.count));
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(|e| Error::io(&path, e))?;
        // One task per shard at a time: a second (a requeued task while the first still runs)
        // would write the same partial files.
        use std::os::fd::AsRawFd;
        // SAFETY: flock on a descriptor this function owns; released when the file closes.
        if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
            return Err(Error::Run(format!(
                "shard {shard} is already running here ({} is locked)",
                path.display()
            )));
        }
        Ok(Ledger {
            path,
            file: Mutex::new(file),
        })
    }

    pub(super) fn append(&self, r: &Record) -> Result<()> {
        let mut line =
            serde_json::to_string(r).map_err(|e| Error::invalid("ledger", e.to_string()))?;
        line.push('\n');
        let mut f = self.file.lock().unwrap_or_else(|e| e.into_inner());
        f.write_all(line.as_bytes())
            .and_then(|()| f.sync_data())
            .map_err(|e| Error::io(&self.path, e))
    }
}
