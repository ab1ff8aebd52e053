//! The journal beside an output written whole only at its end (`.npz`, `.h5`): every event the
//! encoder took, in fixed records, so that a writer killed before its end (SIGKILL, a power
//! cut, a full disk) leaves what it flushed in a form `v2ce repair` turns into the file asked
//! for ([`crate::repair`]).
//!
//! The journal of `out.npz` is `out.npz.v2ce-journal`: a 384-byte head (`V2CEJRNL`, version
//! u16 = 2, sensor width u16, height u16, record size u16 = 13, then zeros), then one record per
//! event: time i64, x u16, y u16, polarity u8 (1 = ON), little-endian. Version 1 journals (a
//! 16-byte head) are still read. The `.npz` encoder turns its journal into the archive in place
//! (the toolbox's record layout is the same bytes while x and y fit `int16`, and the head has
//! room for the archive's headers, see [`super::npz`]), so a full disk can still be closed
//! readably; the `.h5` encoder writes each event to both. The journal is removed (or becomes the
//! `.npz`) once the output is complete; an encoder dropped before that leaves it.

use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::EventDecoder;
use crate::error::{Error, Result};
use crate::event::Event;

/// Bytes per record.
pub const RECORD: usize = 13;

/// The head's bytes: the header, then zeros (room for an `.npz` archive's headers).
pub const HEAD: usize = 384;

/// The header's bytes in version 1, whose records followed it.
const HEADER_V1: usize = 16;

const MAGIC: &[u8; 8] = b"V2CEJRNL";

const VERSION: u16 = 2;

fn bad(message: impl Into<String>) -> Error {
    Error::invalid("journal", message.into())
}

/// The journal of the output `path` (whether it exists or not).
pub fn path_for(output: &Path) -> PathBuf {
    let mut name = output.file_name().unwrap_or_default().to_owned();
    name.push(".v2ce-journal");
    output.with_file_name(name)
}

/// Whether the journal at `path` is already an `.npz` archive: closed in place by a writer
/// stopped before it gave the archive its name (see [`super::npz`]).
pub fn is_archive(path: &Path) -> bool {
    let mut magic = [0u8; 4];
    std::fs::File::open(path)
        .and_then(|mut f| f.read_exact(&mut magic))
        .is_ok_and(|()| &magic == b"PK\x03\x04")
}

/// A journal being written.
pub struct Journal {
    path: PathBuf,
    /// `None` once handed over ([`Journal::into_file`]).
    out: Option<BufWriter<std::fs::File>>,
    count: u64,
    /// Set once the output is complete: the journal is then removed when dropped.
    done: bool,
}

impl Journal {
    /// Creates the journal of the output `output`, for a `width x height` sensor.
    pub fn create(output: &Path, width: u16, height: u16) -> Result<Self> {
        let path = path_for(output);
        // Read as well: the `.npz` encoder reads its records back to close the archive.
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(&path)
            .map_err(|e| Error::io(&path, e))?;
        let mut out = BufWriter::with_capacity(1 << 16, file);
        let mut header = Vec::with_capacity(HEAD);
        header.extend_from_slice(MAGIC);
        for v in [VERSION, width, height, RECORD as u16] {
            header.extend_from_slice(&v.to_le_bytes());
        }
        header.resize(HEAD, 0);
        out.write_all(&header).map_err(|e| Error::io(&path, e))?;
        Ok(Journal {
            path,
            out: Some(out),
            count: 0,
            done: false,
        })
    }

    /// Where it is.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Events appended so far.
    pub fn len(&self) -> u64 {
        self.count
    }

    /// Whether no event was appended.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Appends `events` (the encoder has checked their order and range).
    pub fn append(&mut self, events: &[Event]) -> Result<()> {
        let mut rec = [0u8; RECORD];
        for e in events {
            rec[..8].copy_from_slice(&e.t.to_le_bytes());
            rec[8..10].copy_from_slice(&e.x.to_le_bytes());
            rec[10..12].copy_from_slice(&e.y.to_le_bytes());
            rec[12] = e.on as u8;
            self.writer()?
                .write_all(&rec)
                .map_err(|e| Error::io(&self.path, e))?;
        }
        self.count += events.len() as u64;
        Ok(())
    }

    /// Hands what is buffered to the operating system (a process killed later loses none of
    /// it).
    pub fn flush(&mut self) -> Result<()> {
        let path = self.path.clone();
        self.writer()?.flush().map_err(|e| Error::io(path, e))
    }

    fn writer(&mut self) -> Result<&mut BufWriter<std::fs::File>> {
        self.out
            .as_mut()
            .ok_or_else(|| bad(format!("{}: already closed", self.path.display())))
    }

    /// The journal's file, cut after its last whole record, and the records it holds: all
    /// that was appended where the buffer can still be written, else (a full disk) what of it
    /// reached the file, the rest dropped unwritten. The journal stays on disk (see
    /// [`Journal::complete`]); nothing more can be appended.
    pub fn into_file(&mut self) -> Result<(std::fs::File, u64)> {
        let out = self.out.take().ok_or_else(|| bad("already closed"))?;
        let err = |e| Error::io(&self.path, e);
        let file = match out.into_inner() {
            Ok(file) => file,
            Err(e) => e.into_inner().into_parts().0,
        };
        let len = file.metadata().map_err(err)?.len();
        let whole = (len.saturating_sub(HEAD as u64) / RECORD as u64).min(self.count);
        file.set_len(HEAD as u64 + whole * RECORD as u64)
            .map_err(err)?;
        self.count = whole;
        Ok((file, whole))
    }

    /// The records appended so far, from the first (flushes first).
    pub fn records(&mut self) -> Result<impl Read> {
        self.flush()?;
        let err = |e| Error::io(&self.path, e);
        let mut file = std::fs::File::open(&self.path).map_err(err)?;
        file.seek(SeekFrom::Start(HEAD as u64)).map_err(err)?;
        Ok(BufReader::with_capacity(
            1 << 16,
            file.take(self.count * RECORD as u64),
        ))
    }

    /// The output is complete: the journal goes when dropped.
    pub fn complete(&mut self) {
        self.done = true;
    }
}

impl Drop for Journal {
    fn drop(&mut self) {
        if self.done {
            let _ = std::fs::remove_file(&self.path);
        } else if let Some(out) = self.out.as_mut() {
            let _ = out.flush();
        }
    }
}

/// Reads a journal's events (see the module docs); a last record cut short (a writer killed
/// inside it) is dropped with a warning.
pub struct Decoder {
    path: PathBuf,
    records: BufReader<std::fs::File>,
    size: (u16, u16),
    read: u64,
    buf: Vec<u8>,
    last_t: i64,
}

impl Decoder {
    /// Opens the journal at `path` (see [`path_for`]).
    pub fn open(path: &Path) -> Result<Self> {
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let mut records = BufReader::with_capacity(1 << 16, file);
        let mut header = [0u8; HEADER_V1];
        records
            .read_exact(&mut header)
            .map_err(|_| bad(format!("{}: shorter than its header", path.display())))?;
        let u16_at = |i: usize| u16::from_le_bytes([header[i], header[i + 1]]);
        if &header[..8] != MAGIC {
            return Err(bad(format!("{}: not a v2ce journal", path.display())));
        }
        if !(1..=VERSION).contains(&u16_at(8)) || usize::from(u16_at(14)) != RECORD {
            return Err(bad(format!(
                "{}: version {} with {}-byte records (this v2ce reads versions 1 to {VERSION}, \
                 {RECORD}-byte records)",
                path.display(),
                u16_at(8),
                u16_at(14)
            )));
        }
        if u16_at(8) >= 2 {
            let mut rest = [0u8; HEAD - HEADER_V1];
            records
                .read_exact(&mut rest)
                .map_err(|_| bad(format!("{}: shorter than its head", path.display())))?;
        }
        Ok(Decoder {
            path: path.to_path_buf(),
            records,
            size: (u16_at(10), u16_at(12)),
            read: 0,
            buf: Vec::new(),
            last_t: i64::MIN,
        })
    }
}

impl EventDecoder for Decoder {
    fn size(&self) -> Option<(u16, u16)> {
        Some(self.size)
    }

    fn read_events(&mut self, out: &mut Vec<Event>, max: usize) -> Result<usize> {
        self.buf.resize(max.clamp(1, 1 << 20) * RECORD, 0);
        let what = "journal";
        let n = super::read_words(&mut self.records, &mut self.buf, RECORD, self.read, what)?;
        let (w, h) = self.size;
        for rec in self.buf[..n].chunks_exact(RECORD) {
            let t = i64::from_le_bytes(rec[..8].try_into().unwrap_or_default());
            let x = u16::from_le_bytes([rec[8], rec[9]]);
            let y = u16::from_le_bytes([rec[10], rec[11]]);
            let e = Event::new(t, x, y, rec[12] != 0);
            super::check_event(&e, self.last_t, w, h).map_err(|err| {
                bad(format!(
                    "{}: record {}: {err}",
                    self.path.display(),
                    self.read
                ))
            })?;
            self.last_t = t;
            self.read += 1;
            out.push(e);
        }
        Ok(n / RECORD)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What is flushed reads back; a record cut short is dropped; the journal goes once
    /// complete and stays otherwise; a file that is not a journal is refused.
    #[test]
    fn journals_read_back_up_to_the_cut() {
        let dir = std::env::temp_dir().join(format!("v2ce-journal-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let out = dir.join("e.h5");
        let events: Vec<Event> = (0..1000)
            .map(|i| Event::new(i * 7 - 50, (i % 640) as u16, (i % 480) as u16, i % 3 == 0))
            .collect();
        let path = {
            let mut j = Journal::create(&out, 640, 480).unwrap();
            j.append(&events[..600]).unwrap();
            j.append(&events[600..]).unwrap();
            j.flush().unwrap();
            let mut raw = Vec::new();
            j.records().unwrap().read_to_end(&mut raw).unwrap();
            assert_eq!(raw.len(), 1000 * RECORD);
            j.path().to_path_buf()
        };
        assert_eq!(path, dir.join("e.h5.v2ce-journal"));
        let read = |p: &Path| {
            let mut d = Decoder::open(p).unwrap();
            assert_eq!(d.size(), Some((640, 480)));
            let mut got = Vec::new();
            while d.read_events(&mut got, 77).unwrap() > 0 {}
            got
        };
        assert_eq!(read(&path), events);
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 5]).unwrap();
        assert_eq!(read(&path), events[..999]);
        // Not a journal; out of order.
        std::fs::write(dir.join("x"), b"V2CEJRN? and more bytes").unwrap();
        assert!(Decoder::open(&dir.join("x")).is_err());
        let mut swapped = bytes[..HEAD + 2 * RECORD].to_vec();
        swapped[HEAD..HEAD + 8].copy_from_slice(&1000i64.to_le_bytes());
        std::fs::write(dir.join("y"), &swapped).unwrap();
        let mut d = Decoder::open(&dir.join("y")).unwrap();
        let e = d.read_events(&mut Vec::new(), 10).unwrap_err().to_string();
        assert!(e.contains("comes before"), "{e}");
        // Version 1 (a 16-byte head) still reads.
        let mut v1 = bytes[..HEADER_V1].to_vec();
        v1[8..10].copy_from_slice(&1u16.to_le_bytes());
        v1.extend_from_slice(&bytes[HEAD..HEAD + 3 * RECORD]);
        std::fs::write(dir.join("v1"), &v1).unwrap();
        assert_eq!(read(&dir.join("v1")), events[..3]);
        // Closed after a failed write: cut after its last whole record, nothing more taken.
        let mut j = Journal::create(&out, 640, 480).unwrap();
        j.append(&events[..10]).unwrap();
        j.flush().unwrap();
        let (file, n) = j.into_file().unwrap();
        assert_eq!(
            (n, file.metadata().unwrap().len()),
            (10, (HEAD + 10 * RECORD) as u64)
        );
        assert!(j.append(&events[10..11]).is_err());
        drop((file, j));
        assert_eq!(read(&path), events[..10]);
        // Complete: removed.
        let mut j = Journal::create(&out, 640, 480).unwrap();
        j.complete();
        drop(j);
        assert!(!path.exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
