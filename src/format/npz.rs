//! The V2CE toolbox's event file: a NumPy `.npz` (`np.savez`: a zip archive, entries stored)
//! holding one array `event_stream`, a record array of
//! `[('timestamp', '<i8'), ('x', '<i2'), ('y', '<i2'), ('polarity', 'i1')]` (13 bytes a record,
//! polarity 1 = ON, 0 = OFF; V2CE_SPEC.md section 5.5). `np.load(f)["event_stream"]` reads it.
//!
//! The format has no sensor size. The array's length is in its header, before the records, so
//! the encoder keeps records in the output's journal beside it ([`super::journal`]) and writes
//! the archive at the end (memory stays flat; the disk holds the records twice until then). A
//! run killed before its end leaves the journal, from which `v2ce repair` writes the archive.
//! Archives over 4 GiB are written as zip64, which NumPy reads.

use std::io::{BufReader, BufWriter, Read, Seek, Write};
use std::path::Path;

use super::journal::{Journal, RECORD};
use super::{EventDecoder, EventEncoder};
use crate::error::{Error, Result};
use crate::event::Event;

/// The array's name in the archive.
pub const ARRAY: &str = "event_stream";

/// The record type as NumPy writes it for the toolbox's record array.
const DESCR: &str = "[('timestamp', '<i8'), ('x', '<i2'), ('y', '<i2'), ('polarity', '|i1')]";

fn bad(message: impl Into<String>) -> Error {
    Error::invalid("NPZ", message.into())
}

/// The `.npy` header of the event records for `n` records: 256 bytes, so that with the zip
/// entry's local header it fills the journal's head.
fn records_header(n: u64) -> Vec<u8> {
    npy_header(DESCR, &format!("({n},)"), 256)
}

/// A `.npy` 1.0 header for an array of type `descr` (NumPy's spelling, quoted, e.g. `'<f4'`)
/// and `shape` (a Python tuple), padded with spaces to a multiple of 64 bytes and to at least
/// `at_least` bytes (room to rewrite it in place with a larger shape).
pub fn npy_header(descr: &str, shape: &str, at_least: usize) -> Vec<u8> {
    let dict = format!("{{'descr': {descr}, 'fortran_order': False, 'shape': {shape}, }}");
    let unpadded = 10 + dict.len() + 1;
    let total = unpadded.div_ceil(64).max(at_least.div_ceil(64)) * 64;
    let mut h = b"\x93NUMPY\x01\x00".to_vec();
    h.extend_from_slice(&((total - 10) as u16).to_le_bytes());
    h.extend_from_slice(dict.as_bytes());
    h.resize(total - 1, b' ');
    h.push(b'\n');
    h
}

/// One array of an archive written by [`write_arrays`].
pub struct Array<'a> {
    /// Its name (the entry is `name.npy`; `np.load(f)[name]` reads it).
    pub name: &'a str,
    /// NumPy's type string: `'|u1'`, `'<f4'`, `'<i8'`, ...
    pub descr: &'a str,
    /// Its shape, C order.
    pub shape: &'a [usize],
    /// Its elements, little-endian, C order.
    pub data: &'a [u8],
}

/// Writes `arrays` as an `.npz` at `path` (deflated when `compressed`, as
/// `np.savez_compressed` does): to a temporary name beside it, renamed when complete.
pub fn write_arrays(path: &Path, arrays: &[Array], compressed: bool) -> Result<()> {
    let tmp = path.with_extension("npz.partial");
    let file = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    let mut zip = zip::ZipWriter::new(BufWriter::new(file));
    let method = if compressed {
        zip::CompressionMethod::Deflated
    } else {
        zip::CompressionMethod::Stored
    };
    let zerr = |e: zip::result::ZipError| bad(e.to_string());
    for a in arrays {
        let shape = match a.shape {
            [n] => format!("({n},)"),
            dims => format!(
                "({})",
                dims.iter()
                    .map(|d| d.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        };
        let options = zip::write::SimpleFileOptions::default()
            .compression_method(method)
            .large_file(a.data.len() as u64 > u32::MAX as u64 / 2);
        zip.start_file(format!("{}.npy", a.name), options)
            .map_err(zerr)?;
        zip.write_all(&npy_header(a.descr, &shape, 0))
            .and_then(|_| zip.write_all(a.data))
            .map_err(|e| Error::io(&tmp, e))?;
    }
    let mut out = zip.finish().map_err(zerr)?;
    out.flush().map_err(|e| Error::io(&tmp, e))?;
    drop(out);
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

/// Writes the toolbox's `.npz` (see the module docs).
pub struct Encoder {
    journal: Journal,
    path: std::path::PathBuf,
    last_t: i64,
}

impl Encoder {
    /// An encoder of the file `path` (created empty now, replaced by the archive at the end),
    /// keeping its records in `path`'s journal ([`super::journal`]) until then; `width x
    /// height` is the sensor, for the journal.
    pub fn new(path: &Path, width: u16, height: u16) -> Result<Self> {
        std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
        Ok(Encoder {
            journal: Journal::create(path, width, height)?,
            path: path.to_path_buf(),
            last_t: i64::MIN,
        })
    }

    /// After a failed write (a full disk): the archive made from the records that reached the
    /// journal, in place (it needs a few hundred bytes more, found by dropping the last records
    /// where the disk has none). Returns the events the archive holds.
    fn close_after_failure(&mut self) -> Result<u64> {
        let (file, count) = self.journal.into_file()?;
        archive_in_place(file, self.journal.path(), &self.path, count)
            .inspect(|_| self.journal.complete())
    }
}

impl EventEncoder for Encoder {
    fn write(&mut self, events: &[Event]) -> Result<()> {
        // The events before one refused are taken, as by every other encoder.
        let mut refused = Ok(());
        let mut taken = 0;
        for e in events {
            if e.t < self.last_t {
                refused = Err(bad(format!("{} us comes before {} us", e.t, self.last_t)));
                break;
            }
            if e.x > i16::MAX as u16 || e.y > i16::MAX as u16 {
                refused = Err(bad(format!("({}, {}) does not fit int16", e.x, e.y)));
                break;
            }
            self.last_t = e.t;
            taken += 1;
        }
        // The journal's records are the toolbox's bytes while x and y fit int16.
        self.journal.append(&events[..taken])?;
        refused
    }

    /// The records go to the journal, which a killed run leaves for `v2ce repair`.
    fn flush(&mut self) -> Result<()> {
        self.journal.flush()
    }

    fn salvage(&mut self) -> Result<Option<u64>> {
        self.close_after_failure().map(Some)
    }

    /// Written whole only at the end (the archive's index comes last); until then `v2ce
    /// repair` makes the file from its journal.
    fn readable_after_flush(&self) -> bool {
        false
    }

    fn finish(&mut self) -> Result<()> {
        let appended = self.journal.len();
        let (file, count) = self.journal.into_file()?;
        let kept = archive_in_place(file, self.journal.path(), &self.path, count)?;
        self.journal.complete();
        if kept != appended {
            return Err(Error::Run(format!(
                "{}: the disk took {kept} of the {appended} events",
                self.path.display()
            )));
        }
        Ok(())
    }
}

/// Turns the journal at `journal` (version 2, whose head has room for the archive's headers)
/// into the archive `target` in place, from its whole records: no copy, and the disk needs only
/// the directory's few hundred bytes more. `None` where the journal is of version 1 (written
/// by an older v2ce), which must be copied.
pub fn archive_journal(journal: &Path, target: &Path) -> Result<Option<u64>> {
    let err = |e| Error::io(journal, e);
    let mut file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(journal)
        .map_err(err)?;
    let mut head = [0u8; 10];
    file.read_exact(&mut head).map_err(err)?;
    if &head[..8] != b"V2CEJRNL" || u16::from_le_bytes([head[8], head[9]]) < 2 {
        return Ok(None);
    }
    let len = file.metadata().map_err(err)?.len();
    let count = len.saturating_sub(super::journal::HEAD as u64) / RECORD as u64;
    archive_in_place(file, journal, target, count).map(Some)
}

/// The zip entry's name.
const ENTRY: &str = "event_stream.npy";

/// A zip extra field of padding (the id zip aligners use), so the records start at the end
/// of the journal's head.
const PADDING_ID: u16 = 0xD935;

/// Makes the archive of the journal `file` (at `journal`, `count` whole records after its
/// head) in place: the head becomes the zip entry's local header and the `.npy` header, the
/// central directory goes after the records, and the file is renamed `target`. Where the disk
/// has no room for the directory, the last records are dropped until it fits. Returns the
/// events the archive holds.
fn archive_in_place(
    mut file: std::fs::File,
    journal: &Path,
    target: &Path,
    mut count: u64,
) -> Result<u64> {
    use std::io::SeekFrom;
    let err = |e| Error::io(journal, e);
    let head = super::journal::HEAD as u64;
    let rec = RECORD as u64;
    let mut tries = 0;
    loop {
        file.set_len(head + count * rec).map_err(err)?;
        let mut crc = crc32fast::Hasher::new();
        let npy = records_header(count);
        crc.update(&npy);
        file.seek(SeekFrom::Start(head)).map_err(err)?;
        let mut left = count * rec;
        let mut buf = vec![0u8; 1 << 20];
        while left > 0 {
            let n = left.min(buf.len() as u64) as usize;
            file.read_exact(&mut buf[..n]).map_err(err)?;
            crc.update(&buf[..n]);
            left -= n as u64;
        }
        let (local, directory) = zip_records(crc.finalize(), count, &npy);
        let written = file
            .write_all(&directory)
            .and_then(|()| file.seek(SeekFrom::Start(0)).map(|_| ()))
            .and_then(|()| file.write_all(&local))
            .and_then(|()| file.sync_data());
        match written {
            Ok(()) => break,
            // No room for the directory: fewer records (each try frees more).
            Err(e) if tries < 8 && count > 0 => {
                tracing::debug!("{}: {e}; dropping records to close it", journal.display());
                tries += 1;
                count = count.saturating_sub(((directory.len() as u64).div_ceil(rec)) << tries);
            }
            Err(e) => return Err(err(e)),
        }
    }
    drop(file);
    std::fs::rename(journal, target).map_err(|e| Error::io(target, e))?;
    Ok(count)
}

/// The local header (with the `.npy` header `npy` after it, filling the journal's head) and
/// the central directory (with its end records) of a stored zip entry of `count` records whose
/// CRC-32 is `crc`. Zip64 fields where sizes or offsets pass 4 GiB.
fn zip_records(crc: u32, count: u64, npy: &[u8]) -> (Vec<u8>, Vec<u8>) {
    let head = super::journal::HEAD as u64;
    let size = npy.len() as u64 + count * RECORD as u64;
    let directory_at = head + count * RECORD as u64;
    let zip64 = size >= u32::MAX as u64 || directory_at >= u32::MAX as u64;
    let version: u16 = if zip64 { 45 } else { 20 };
    let small = |v: u64| if zip64 { u32::MAX } else { v as u32 };
    // DOS date 1980-01-01, time 00:00 (as NumPy's archives of no date).
    let (time, date): (u16, u16) = (0, (1 << 5) | 1);
    let mut zip64_extra = Vec::new();
    if zip64 {
        zip64_extra.extend_from_slice(&1u16.to_le_bytes());
        zip64_extra.extend_from_slice(&16u16.to_le_bytes());
        zip64_extra.extend_from_slice(&size.to_le_bytes());
        zip64_extra.extend_from_slice(&size.to_le_bytes());
    }
    let fixed = 30 + ENTRY.len() + zip64_extra.len() + 4 + npy.len();
    let padding = (head as usize).saturating_sub(fixed);
    let mut local = Vec::with_capacity(head as usize);
    local.extend_from_slice(&0x0403_4b50u32.to_le_bytes());
    for v in [version, 0, 0, time, date] {
        local.extend_from_slice(&v.to_le_bytes());
    }
    local.extend_from_slice(&crc.to_le_bytes());
    local.extend_from_slice(&small(size).to_le_bytes());
    local.extend_from_slice(&small(size).to_le_bytes());
    local.extend_from_slice(&(ENTRY.len() as u16).to_le_bytes());
    local.extend_from_slice(&((zip64_extra.len() + 4 + padding) as u16).to_le_bytes());
    local.extend_from_slice(ENTRY.as_bytes());
    local.extend_from_slice(&zip64_extra);
    local.extend_from_slice(&PADDING_ID.to_le_bytes());
    local.extend_from_slice(&(padding as u16).to_le_bytes());
    local.resize(local.len() + padding, 0);
    local.extend_from_slice(npy);

    let mut central = Vec::new();
    central.extend_from_slice(&0x0201_4b50u32.to_le_bytes());
    for v in [version, version, 0, 0, time, date] {
        central.extend_from_slice(&v.to_le_bytes());
    }
    central.extend_from_slice(&crc.to_le_bytes());
    central.extend_from_slice(&small(size).to_le_bytes());
    central.extend_from_slice(&small(size).to_le_bytes());
    central.extend_from_slice(&(ENTRY.len() as u16).to_le_bytes());
    central.extend_from_slice(&(zip64_extra.len() as u16).to_le_bytes());
    // Comment length, disk, internal and external attributes (u16, u16, u16, u32), offset 0.
    central.extend_from_slice(&[0u8; 2 + 2 + 2 + 4 + 4]);
    central.extend_from_slice(ENTRY.as_bytes());
    central.extend_from_slice(&zip64_extra);
    let central_len = central.len() as u64;
    if zip64 {
        let end64_at = directory_at + central_len;
        central.extend_from_slice(&0x0606_4b50u32.to_le_bytes());
        central.extend_from_slice(&44u64.to_le_bytes());
        for v in [45u16, 45] {
            central.extend_from_slice(&v.to_le_bytes());
        }
        central.extend_from_slice(&[0u8; 8]);
        for v in [1u64, 1, central_len, directory_at] {
            central.extend_from_slice(&v.to_le_bytes());
        }
        central.extend_from_slice(&0x0706_4b50u32.to_le_bytes());
        central.extend_from_slice(&0u32.to_le_bytes());
        central.extend_from_slice(&end64_at.to_le_bytes());
        central.extend_from_slice(&1u32.to_le_bytes());
    }
    central.extend_from_slice(&0x0605_4b50u32.to_le_bytes());
    central.extend_from_slice(&[0u8; 4]);
    let entries: u16 = if zip64 { u16::MAX } else { 1 };
    central.extend_from_slice(&entries.to_le_bytes());
    central.extend_from_slice(&entries.to_le_bytes());
    central.extend_from_slice(&small(central_len).to_le_bytes());
    central.extend_from_slice(&small(directory_at).to_le_bytes());
    central.extend_from_slice(&0u16.to_le_bytes());
    (local, central)
}

/// Reads the toolbox's `.npz` (the `event_stream` array; other arrays are ignored).
pub struct Decoder {
    records: Box<dyn Read + Send>,
    left: u64,
    buf: Vec<u8>,
}

/// A `.npy` array's header: what the bytes after it hold.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct NpyHeader {
    /// The dictionary with every space removed (`{'descr':'<f4','fortran_order':False,...}`).
    pub dict: String,
    /// The shape, one entry per dimension.
    pub shape: Vec<u64>,
    /// Bytes from the file's start to the data.
    pub data_offset: u64,
}

impl NpyHeader {
    /// The element count, `None` past `u64`.
    pub fn elements(&self) -> Option<u64> {
        self.shape.iter().try_fold(1u64, |n, &d| n.checked_mul(d))
    }
}

/// Parses a `.npy` header (format 1.0 to 3.0) from `r`, reading nothing past it; the sizes it
/// claims are only parsed, never allocated.
pub(crate) fn parse_npy_header(r: &mut impl Read) -> std::result::Result<NpyHeader, String> {
    let mut magic = [0u8; 8];
    r.read_exact(&mut magic)
        .map_err(|_| "shorter than a .npy magic".to_string())?;
    if &magic[..6] != b"\x93NUMPY" {
        return Err("not a .npy array".into());
    }
    let (len, prefix) = match magic[6] {
        1 => {
            let mut l = [0u8; 2];
            r.read_exact(&mut l).map_err(|_| "truncated header")?;
            (u16::from_le_bytes(l) as usize, 10)
        }
        2 | 3 => {
            let mut l = [0u8; 4];
            r.read_exact(&mut l).map_err(|_| "truncated header")?;
            (u32::from_le_bytes(l) as usize, 12)
        }
        v => return Err(format!(".npy version {v}")),
    };
    if len > 1 << 16 {
        return Err(format!("a {len}-byte .npy header"));
    }
    let mut dict = vec![0u8; len];
    r.read_exact(&mut dict).map_err(|_| "truncated header")?;
    let dict: String = String::from_utf8_lossy(&dict)
        .chars()
        .filter(|c| !c.is_whitespace())
        .collect();
    let shape = dict
        .split("'shape':(")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .ok_or("no shape in the .npy header")?;
    let shape = shape
        .split(',')
        .filter(|d| !d.is_empty())
        .map(|d| d.trim_end_matches('L').parse::<u64>())
        .collect::<std::result::Result<Vec<u64>, _>>()
        .map_err(|_| format!("shape ({shape}) is not a list of sizes"))?;
    Ok(NpyHeader {
        dict,
        shape,
        data_offset: prefix + len as u64,
    })
}

/// Parses the event records' `.npy` header from `r`; returns the record count.
fn read_npy_header(r: &mut impl Read) -> Result<u64> {
    let header = parse_npy_header(r).map_err(|e| bad(format!("event_stream.npy: {e}")))?;
    let squeeze = &header.dict;
    let want: String = DESCR.chars().filter(|c| !c.is_whitespace()).collect();
    // NumPy may spell the int8 field '|i1' or 'i1'.
    if !(squeeze.contains(&want) || squeeze.contains(&want.replace("'|i1'", "'i1'"))) {
        return Err(bad(format!(
            "event_stream has another record type ({squeeze}); expected {DESCR}"
        )));
    }
    if squeeze.contains("'fortran_order':True") {
        return Err(bad("a Fortran-ordered event_stream"));
    }
    match header.shape[..] {
        [n] => Ok(n),
        _ => Err(bad(format!(
            "event_stream has shape {:?}; expected one dimension",
            header.shape
        ))),
    }
}

impl Decoder {
    /// Opens the archive at `path`.
    pub fn open(path: &Path) -> Result<Self> {
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
        let mut archive = zip::ZipArchive::new(BufReader::new(file))
            .map_err(|e| bad(format!("not an .npz (zip) archive: {e}")))?;
        let name = format!("{ARRAY}.npy");
        let index = archive
            .index_for_name(&name)
            .ok_or_else(|| bad(format!("no {name} in the archive")))?;
        let entry = archive.by_index(index).map_err(|e| bad(e.to_string()))?;
        if entry.compression() != zip::CompressionMethod::Stored {
            return Err(bad(
                "a compressed .npz (np.savez_compressed): load and save it with np.savez",
            ));
        }
        let start = entry
            .data_start()
            .ok_or_else(|| bad("cannot find where event_stream.npy's data starts"))?;
        let size = entry.size();
        drop(entry);
        let mut file = archive.into_inner();
        if start + size > len {
            return Err(bad("event_stream.npy reaches past the end of the file"));
        }
        file.seek(std::io::SeekFrom::Start(start))
            .map_err(|e| Error::io(path, e))?;
        let mut records = file.take(size);
        let n = read_npy_header(&mut records)?;
        if n.checked_mul(RECORD as u64)
            .is_none_or(|b| b > records.limit())
        {
            return Err(bad(format!(
                "{n} records do not fit the {} bytes of event_stream.npy",
                size
            )));
        }
        Ok(Decoder {
            records: Box::new(records),
            left: n,
            buf: Vec::new(),
        })
    }
}

impl EventDecoder for Decoder {
    fn size(&self) -> Option<(u16, u16)> {
        None
    }

    fn read_events(&mut self, out: &mut Vec<Event>, max: usize) -> Result<usize> {
        let n = (max.max(1) as u64).min(self.left) as usize;
        if n == 0 {
            return Ok(0);
        }
        self.buf.resize(n * RECORD, 0);
        self.records
            .read_exact(&mut self.buf)
            .map_err(|_| bad("event_stream.npy is cut short"))?;
        for r in self.buf.chunks_exact(RECORD) {
            let mut t = [0u8; 8];
            t.copy_from_slice(&r[..8]);
            let x = i16::from_le_bytes([r[8], r[9]]);
            let y = i16::from_le_bytes([r[10], r[11]]);
            if x < 0 || y < 0 {
                return Err(bad(format!("negative pixel ({x}, {y})")));
            }
            out.push(Event::new(
                i64::from_le_bytes(t),
                x as u16,
                y as u16,
                r[12] != 0,
            ));
        }
        self.left -= n as u64;
        Ok(n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn headers_are_numpy_format_1_0() {
        for n in [0, 7, 123_456_789_012] {
            let h = records_header(n);
            assert_eq!(h.len() % 64, 0);
            assert_eq!(u16::from_le_bytes([h[8], h[9]]) as usize, h.len() - 10);
            assert_eq!(*h.last().unwrap(), b'\n');
            assert_eq!(read_npy_header(&mut &h[..]).unwrap(), n);
        }
    }

    #[test]
    fn round_trip_and_bad_archives() {
        let dir = std::env::temp_dir().join(format!("v2ce-npz-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("e.npz");
        let events: Vec<Event> = (0..1000)
            .map(|i| Event::new(i * 37 - 500, (i % 300) as u16, (i % 200) as u16, i % 3 == 0))
            .collect();
        {
            let mut enc = Encoder::new(&path, 300, 200).unwrap();
            enc.write(&events[..400]).unwrap();
            enc.write(&events[400..]).unwrap();
            enc.finish().unwrap();
        }
        assert!(!super::super::journal::path_for(&path).exists());
        let mut dec = Decoder::open(&path).unwrap();
        let mut got = Vec::new();
        while dec.read_events(&mut got, 333).unwrap() > 0 {}
        assert_eq!(got, events);
        // Not a zip; a zip without the array; cut short.
        std::fs::write(dir.join("x.npz"), b"PK nonsense").unwrap();
        assert!(Decoder::open(&dir.join("x.npz")).is_err());
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(dir.join("cut.npz"), &bytes[..bytes.len() / 2]).unwrap();
        assert!(Decoder::open(&dir.join("cut.npz")).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
