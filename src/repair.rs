//! `v2ce repair`: makes an event file that a killed writer left (SIGKILL, a power cut, a full
//! disk) readable by the field's readers, keeping every whole event it holds.
//!
//! | format | a killed writer leaves | repair |
//! |---|---|---|
//! | `.npz`, `.h5` | a file that does not open, and its journal ([`format::journal`]) | the file written from the journal's whole records, the journal removed |
//! | `.aedat4` | whole packets, perhaps a last one cut short, no data table | cut after the last whole packet |
//! | `.raw` (EVT 2.0, 3.0) | whole words, perhaps a last one cut short | cut after the last whole word |
//! | `.csv` | whole lines, perhaps a last one cut short | cut after the last whole line |
//!
//! The repaired file is read through once with this program's decoder before it is called
//! repaired. A file that is already whole is left as it is.

use std::io::Read;
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::format::{self, journal, EventDecoder, Format};

/// What [`repair`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Report {
    /// The repaired file.
    pub output: PathBuf,
    /// Whole events it holds.
    pub events: u64,
    /// What was done.
    pub action: Action,
}

/// How a file was repaired.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Action {
    /// Already whole: left as it was (copied where an output was given).
    Whole,
    /// Cut after its last whole unit (packet, word, line), dropping `dropped` bytes.
    Cut {
        /// Bytes kept.
        kept: u64,
        /// Bytes dropped after them.
        dropped: u64,
    },
    /// Written from its journal, which is removed.
    FromJournal(PathBuf),
}

impl std::fmt::Display for Report {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (out, n) = (self.output.display(), self.events);
        match &self.action {
            Action::Whole => write!(f, "{out} is whole ({n} events): nothing to repair"),
            Action::Cut { kept, dropped } => write!(
                f,
                "{out}: cut after its last whole unit, {kept} bytes kept, {dropped} dropped; \
                 {n} events"
            ),
            Action::FromJournal(j) => write!(
                f,
                "{out}: written from its journal {} ({n} events); the journal is removed",
                j.display()
            ),
        }
    }
}

/// Repairs `path` (see the module docs) in place, or into `output` (leaving `path` as it is).
pub fn repair(path: &Path, output: Option<&Path>) -> Result<Report> {
    let target = output.unwrap_or(path);
    if output.is_some() && crate::file_id::same_file(path, target) {
        return Err(Error::invalid(
            "output file",
            format!(
                "{} is the file to repair (leave out --out to repair in place)",
                target.display()
            ),
        ));
    }
    let format = Format::for_output(path, None, format::Compression::default()).map_err(|_| {
        Error::format(
            path,
            "cannot repair this file type (expected .aedat4, .raw, .csv, .npz, .h5, .hdf5 or .mcap)",
        )
    })?;
    let journal_path = journal::path_for(path);
    if matches!(format, Format::Npz | Format::Hdf5) {
        // A whole file first: a journal beside it is another run's (a finished writer removes
        // its own), and writing the file from it would replace every event the file holds.
        if let Ok(events) = count(path) {
            if journal_path.exists() {
                tracing::warn!(
                    "{} is whole; the journal {} beside it is not this file's (a finished \
                     writer removes its own) and was not used",
                    path.display(),
                    journal_path.display()
                );
            }
            return whole(path, output, events);
        }
        if journal_path.exists() {
            return from_journal(&journal_path, target, format);
        }
        // No journal: whole, or not ours to mend.
        let events = count(path).map_err(|e| {
            Error::format(
                path,
                format!(
                    "{e}; and it has no journal ({}) to write it from: written by another \
                     program or an older v2ce, or the journal was removed",
                    journal_path.display()
                ),
            )
        })?;
        return whole(path, output, events);
    }
    if !path.is_file() {
        return Err(Error::format(path, "not a file"));
    }
    let len = std::fs::metadata(path)
        .map_err(|e| Error::io(path, e))?
        .len();
    let kept = format::cut::whole_prefix(path, format)?;
    if kept >= len {
        let events = count(path)?;
        return whole(path, output, events);
    }
    match output {
        None => std::fs::OpenOptions::new()
            .write(true)
            .open(path)
            .and_then(|f| f.set_len(kept))
            .map_err(|e| Error::io(path, e))?,
        Some(out) => {
            let partial = format::PartialOutput::new(out);
            copy_prefix(path, partial.writing(), kept)
                .map_err(|e| close_copy(e, partial.writing(), format))
                .and_then(|()| partial.commit())
                .map_err(|e| partial.explain(e))?;
        }
    }
    format::cut::unfinished(target, format)?;
    let events = count(target)?;
    Ok(Report {
        output: target.to_path_buf(),
        events,
        action: Action::Cut {
            kept,
            dropped: len - kept,
        },
    })
}

/// A whole file: nothing done, or copied to `output`.
fn whole(path: &Path, output: Option<&Path>, events: u64) -> Result<Report> {
    if let Some(out) = output {
        let partial = format::PartialOutput::new(out);
        let format = Format::for_output(path, None, format::Compression::default())?;
        std::fs::copy(path, partial.writing())
            .map_err(|e| close_copy(Error::io(out, e), partial.writing(), format))
            .and_then(|_| partial.commit())
            .map_err(|e| partial.explain(e))?;
    }
    Ok(Report {
        output: output.unwrap_or(path).to_path_buf(),
        events,
        action: Action::Whole,
    })
}

/// `e`, a copy to `partial` (in `format`) that failed (a full disk): the copy closed readably
/// with what reached it (cut after its last whole unit), or removed where that cannot be
/// (`.npz`, `.h5`: whole only complete), and said.
fn close_copy(e: Error, partial: &Path, format: Format) -> Error {
    if matches!(format, Format::Npz | Format::Hdf5) {
        let _ = std::fs::remove_file(partial);
        return Error::Run(format!(
            "{e}; the copy was removed (whole only when complete)"
        ));
    }
    match format::cut::cut_in_place(partial) {
        Ok(n) => Error::Run(format!(
            "{e}; {} was closed readably with the {n} events that reached it",
            partial.display()
        )),
        Err(why) => Error::Run(format!(
            "{e}; and the copy could not be closed readably ({why})"
        )),
    }
}

/// Writes `target` in `format` from the journal at `journal_path`, then removes the journal.
fn from_journal(journal_path: &Path, target: &Path, format: Format) -> Result<Report> {
    if format == Format::Npz && journal::is_archive(journal_path) {
        // Closed in place, not yet renamed: read through, then given the name.
        let mut decoder = format::npz::Decoder::open(journal_path)?;
        let (mut events, mut buf) = (0u64, Vec::new());
        loop {
            buf.clear();
            match decoder.read_events(&mut buf, 1 << 16)? {
                0 => break,
                n => events += n as u64,
            }
        }
        std::fs::rename(journal_path, target).map_err(|e| Error::io(target, e))?;
        return Ok(Report {
            output: target.to_path_buf(),
            events,
            action: Action::FromJournal(journal_path.to_path_buf()),
        });
    }
    // An `.npz` journal becomes the archive in place (it holds the records already).
    if format == Format::Npz {
        if let Some(written) = format::npz::archive_journal(journal_path, target)? {
            let events = count(target)?;
            if events != written {
                return Err(Error::format(
                    target,
                    format!("holds {events} events after the repair, {written} written"),
                ));
            }
            return Ok(Report {
                output: target.to_path_buf(),
                events,
                action: Action::FromJournal(journal_path.to_path_buf()),
            });
        }
    }
    let out = format::PartialOutput::new(target);
    let written = if format == Format::Hdf5 {
        // Without a second journal: the one read is the copy a kill would leave.
        format::hdf5::write_from_journal(journal_path, out.writing())
    } else {
        let mut decoder = journal::Decoder::open(journal_path)?;
        let size = decoder.size().unwrap_or((0, 0));
        crate::transcode::write_all(journal_path, &mut decoder, out.writing(), format, size)
            .map(|r| r.events)
    };
    let written = written
        .and_then(|n| out.commit().map(|()| n))
        .map_err(|e| out.explain(e))?;
    // Read back before the journal goes.
    let events = count(target)?;
    if events != written {
        return Err(Error::format(
            target,
            format!("holds {events} events after the repair, {written} written"),
        ));
    }
    std::fs::remove_file(journal_path).map_err(|e| Error::io(journal_path, e))?;
    Ok(Report {
        output: target.to_path_buf(),
        events,
        action: Action::FromJournal(journal_path.to_path_buf()),
    })
}

/// The events of `path`, read through with this program's decoder.
fn count(path: &Path) -> Result<u64> {
    Ok(crate::transcode::summarize(path)?.events)
}

/// Copies the first `n` bytes of `from` to `to`.
fn copy_prefix(from: &Path, to: &Path, n: u64) -> Result<()> {
    let mut src = std::fs::File::open(from).map_err(|e| Error::io(from, e))?;
    let mut dst = std::fs::File::create(to).map_err(|e| Error::io(to, e))?;
    let copied = std::io::copy(&mut (&mut src).take(n), &mut dst).map_err(|e| Error::io(to, e))?;
    if copied != n {
        return Err(Error::format(
            from,
            format!("shrank while read: {copied} of {n} bytes"),
        ));
    }
    dst.sync_all().map_err(|e| Error::io(to, e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::event::Event;

    fn events(n: i64) -> Vec<Event> {
        (0..n)
            .map(|i| {
                Event::new(
                    1000 + i * 13,
                    (i % 346) as u16,
                    (i % 260) as u16,
                    i % 2 == 0,
                )
            })
            .collect()
    }

    fn read(path: &Path) -> Vec<Event> {
        let mut d = format::open(path).unwrap();
        let mut got = Vec::new();
        while d.read_events(&mut got, 1000).unwrap() > 0 {}
        got
    }

    /// An encoder dropped before its end (as a killed run leaves it): the streaming formats
    /// cut short inside their last unit read up to it after the repair, and `.npz` / `.h5`
    /// are written from their journals; a whole file is left alone.
    #[test]
    fn killed_files_read_after_repair() {
        let dir = std::env::temp_dir().join(format!("v2ce-repair-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let all = events(20_000);
        for name in ["a.aedat4", "b.raw", "c.raw", "d.csv", "e.npz", "f.h5"] {
            let path = dir.join(name);
            let evt = (name == "c.raw").then_some(3);
            let fmt = Format::for_output(&path, evt, Default::default()).unwrap();
            {
                let mut enc = format::create(&path, fmt, 346, 260).unwrap();
                enc.write(&all[..12_345]).unwrap();
                enc.flush().unwrap();
                // Dropped without `finish`, like a killed run.
                std::mem::forget(enc);
            }
            let streaming = !matches!(fmt, Format::Npz | Format::Hdf5);
            if streaming {
                // Cut inside the last unit (the EVT 3.0 file 3 bytes in: 1 byte into a 2-byte
                // word, which a 4-byte word would not tell apart; the CSV's last line loses its
                // polarity with its newline: a line without only its newline is whole).
                let len = std::fs::metadata(&path).unwrap().len();
                let f = std::fs::OpenOptions::new().write(true).open(&path).unwrap();
                let cut = match name {
                    "c.raw" => 3,
                    "d.csv" => 2,
                    _ => 1,
                };
                f.set_len(len - cut).unwrap();
            } else {
                assert!(
                    format::open(&path).is_err(),
                    "{name} opens before the repair"
                );
            }
            let report = repair(&path, None).unwrap();
            let got = read(&path);
            assert_eq!(report.events, got.len() as u64, "{name}");
            assert_eq!(got[..], all[..got.len()], "{name}");
            if streaming {
                assert!(
                    matches!(report.action, Action::Cut { dropped, .. } if dropped > 0),
                    "{name}: {report}"
                );
                // At most one packet (AEDAT 4.0 holds a batch in one), word or line lost.
                assert!(
                    !got.is_empty() && got.len() <= 12_345,
                    "{name}: {}",
                    got.len()
                );
                if !name.ends_with(".aedat4") {
                    assert!(got.len() >= 12_343, "{name}: {}", got.len());
                }
                // An EVT 3.0 file (2-byte words, told by its header) loses only the cut byte.
                if name == "c.raw" {
                    assert!(
                        matches!(report.action, Action::Cut { dropped: 1, .. }),
                        "{report}"
                    );
                }
            } else {
                assert_eq!(got.len(), 12_345, "{name}");
                assert!(
                    matches!(report.action, Action::FromJournal(_)),
                    "{name}: {report}"
                );
                assert!(!journal::path_for(&path).exists());
            }
            // Again: whole now.
            let again = repair(&path, None).unwrap();
            assert_eq!(again.action, Action::Whole, "{name}");
            assert_eq!(again.events, got.len() as u64);
        }
        // Into another file, leaving the original.
        let path = dir.join("g.csv");
        let mut enc = format::create(&path, Format::Csv, 346, 260).unwrap();
        enc.write(&all[..100]).unwrap();
        enc.finish().unwrap();
        drop(enc);
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
        let out = dir.join("g2.csv");
        let report = repair(&path, Some(&out)).unwrap();
        assert_eq!(report.events, 99);
        assert_eq!(std::fs::read(&path).unwrap().len(), bytes.len() - 3);
        assert!(repair(&path, Some(&path)).is_err());
        // An archive closed in place under its journal's name (stopped before the rename).
        let path = dir.join("h.npz");
        let mut enc = format::create(&path, Format::Npz, 346, 260).unwrap();
        enc.write(&all[..500]).unwrap();
        enc.finish().unwrap();
        drop(enc);
        std::fs::rename(&path, journal::path_for(&path)).unwrap();
        std::fs::write(&path, b"").unwrap();
        let report = repair(&path, None).unwrap();
        assert_eq!(report.events, 500, "{report}");
        assert_eq!(read(&path), all[..500]);
        assert!(!journal::path_for(&path).exists());
        // Not ours to mend: an .npz without its journal; a type it cannot write.
        std::fs::write(dir.join("x.npz"), b"PK nonsense").unwrap();
        let e = repair(&dir.join("x.npz"), None).unwrap_err().to_string();
        assert!(e.contains("no journal"), "{e}");
        std::fs::write(dir.join("x.txt"), b"0.1 1 2 1\n").unwrap();
        assert!(repair(&dir.join("x.txt"), None).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
