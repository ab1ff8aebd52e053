//! The per-shard JSONL ledger in the output folder: one [`Record`] a line for each item
//! converted or failed, appended by one task per shard at a time (a lock), read back by every
//! later run and by the report.

use std::collections::BTreeMap;
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};

use super::lines::{for_each_line, Line};
use super::manifest::Settings;
use super::paths::output_key;
use super::shard::Shard;
use crate::error::{Error, Result};

/// The folder of the ledgers, inside the output folder; no output may be in it.
pub(crate) const LEDGER_DIR: &str = ".v2ce-batch";

/// The longest ledger line read, bytes (a record is about half a kilobyte; its error message
/// and paths make it longer, never near this); a longer line is skipped with a warning.
pub(crate) const MAX_LEDGER_LINE: usize = 1 << 20;

/// The largest ledger file read, bytes (1 GiB: about two million records, more than one
/// shard's items and re-runs); a larger one is an error naming it.
pub(crate) const MAX_LEDGER_BYTES: u64 = 1 << 30;

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

/// Every record of every ledger in `out`, in file then line order. A line that is not a
/// record (a last line cut short by a task killed while writing it, even inside a character;
/// a line longer than [`MAX_LEDGER_LINE`]) is skipped, with one warning per file. A ledger that
/// is not a regular file, or is larger than [`MAX_LEDGER_BYTES`], is an error.
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
        let skipped = read_ledger(&f, &mut records)?;
        if let Some((line, why)) = skipped.first() {
            tracing::warn!(
                "{}: skipped {} line(s) that are not ledger records (line {line}: {why})",
                f.display(),
                skipped.len()
            );
        }
    }
    Ok(records)
}

/// The records of one ledger file appended to `records`; the lines skipped (number, why).
fn read_ledger(path: &Path, records: &mut Vec<Record>) -> Result<Vec<(usize, String)>> {
    let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    if !meta.is_file() {
        return Err(Error::format(
            path,
            "a ledger must be a regular file; move this one away",
        ));
    }
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut skipped = Vec::new();
    for_each_line(
        path,
        std::io::BufReader::new(file),
        MAX_LEDGER_LINE,
        MAX_LEDGER_BYTES,
        |number, line| {
            match line {
                Line::Text(text) => match serde_json::from_str::<Record>(text) {
                    Ok(r) => records.push(r),
                    Err(e) => skipped.push((number, format!("not a record: {e}"))),
                },
                Line::NotUtf8 => skipped.push((number, "not UTF-8 (cut short?)".into())),
                Line::TooLong => {
                    skipped.push((number, format!("longer than {MAX_LEDGER_LINE} bytes")))
                }
            }
            Ok(())
        },
    )?;
    Ok(skipped)
}

/// The latest record of each output, by the output normalised (a record of `./x` is one of
/// `x`, as the manifest normalises outputs).
pub(super) fn latest(records: Vec<Record>) -> BTreeMap<String, Record> {
    let mut by_output = BTreeMap::new();
    for mut r in records {
        r.output = output_key(&r.output);
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
    /// Opens (creates) the ledger of `shard` in `out`, locked for this task; a last line cut
    /// short by a killed task is ended, so the next record starts on a line of its own.
    pub(super) fn open(out: &Path, shard: Shard) -> Result<Ledger> {
        let dir = ledger_dir(out);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        let path = dir.join(format!("shard-{}-of-{}.jsonl", shard.index, shard.count));
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .read(true)
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
        end_last_line(&mut file).map_err(|e| Error::io(&path, e))?;
        Ok(Ledger {
            path,
            file: Mutex::new(file),
        })
    }

    /// Appends `r` as one line, synced to the disk.
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

/// Ends the file's last line with `\n` when it was cut short (a task killed while writing it):
/// else the next record would be glued to it, and both lost.
fn end_last_line(file: &mut std::fs::File) -> std::io::Result<()> {
    let meta = file.metadata()?;
    let len = meta.len();
    if len == 0 || !meta.is_file() {
        return Ok(());
    }
    file.seek(std::io::SeekFrom::Start(len - 1))?;
    let mut last = [0u8];
    file.read_exact(&mut last)?;
    if last[0] != b'\n' {
        file.write_all(b"\n")?;
        file.sync_data()?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(output: &str, finished_unix: f64) -> Record {
        Record {
            input: format!("in/{output}"),
            output: output.into(),
            status: "done".into(),
            error: None,
            input_sha256: "ab".into(),
            input_stamp: (1, 2),
            settings: Settings::default(),
            settings_sha256: "cd".into(),
            version: "0".into(),
            frames: 3,
            events: 4,
            span_us: 5,
            bytes: 6,
            wall_s: 0.5,
            shard: "0/1".into(),
            finished_unix,
        }
    }

    fn line(r: &Record) -> Vec<u8> {
        let mut l = serde_json::to_vec(r).unwrap();
        l.push(b'\n');
        l
    }

    fn out_dir(tag: &str) -> PathBuf {
        let out =
            std::env::temp_dir().join(format!("v2ce-batch-ledger-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        std::fs::create_dir_all(ledger_dir(&out)).unwrap();
        out
    }

    #[test]
    fn lines_that_are_not_records_are_skipped() {
        let out = out_dir("skip");
        let file = ledger_dir(&out).join("shard-0-of-1.jsonl");
        let (a, b) = (record("a.aedat4", 1.0), record("b\u{e9}.aedat4", 2.0));
        // A record, an over-long line, a record, and a last line cut inside the 'é'.
        let mut bytes = line(&a);
        bytes.extend(std::iter::repeat_n(b'x', MAX_LEDGER_LINE + 10));
        bytes.push(b'\n');
        bytes.extend(line(&b));
        let cut = line(&b);
        let at = cut.iter().position(|&c| c == 0xc3).unwrap() + 1;
        bytes.extend_from_slice(&cut[..at]);
        std::fs::write(&file, &bytes).unwrap();
        let mut records = Vec::new();
        let skipped = read_ledger(&file, &mut records).unwrap();
        assert_eq!(records, [a.clone(), b.clone()]);
        assert_eq!(skipped.iter().map(|s| s.0).collect::<Vec<_>>(), [2, 4]);
        assert!(skipped[1].1.contains("UTF-8"), "{skipped:?}");
        assert_eq!(read_records(&out).unwrap(), [a.clone(), b.clone()]);
        // The next task ends the cut line before it appends: nothing after it is lost.
        let c = record("c.aedat4", 3.0);
        Ledger::open(&out, Shard::ALL).unwrap().append(&c).unwrap();
        assert_eq!(read_records(&out).unwrap(), [a, b, c]);
        std::fs::remove_dir_all(&out).unwrap();
    }

    #[test]
    fn a_ledger_that_is_no_file_is_an_error_not_an_endless_read() {
        let out = out_dir("dev");
        let file = ledger_dir(&out).join("shard-0-of-1.jsonl");
        for device in ["/dev/zero", "/dev/full"] {
            let _ = std::fs::remove_file(&file);
            std::os::unix::fs::symlink(device, &file).unwrap();
            let err = read_records(&out).unwrap_err().to_string();
            assert!(
                err.contains("shard-0-of-1.jsonl") && err.contains("regular file"),
                "{err}"
            );
        }
        std::fs::remove_dir_all(&out).unwrap();
    }

    #[test]
    fn records_of_one_output_written_two_ways_are_one_output() {
        let old = record("./d//x.aedat4", 1.0);
        let new = record("d/x.aedat4", 2.0);
        let by_output = latest(vec![old, new.clone()]);
        assert_eq!(by_output.len(), 1);
        assert_eq!(by_output["d/x.aedat4"], new);
    }
}
