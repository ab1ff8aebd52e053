//! Cutting an event file after its last whole unit (packet, word, line), in place: what
//! `v2ce repair` does to a file a killed writer left, and what an encoder whose write failed
//! (a full disk) does to its own file, needing no room on the disk.

use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use super::{aedat4, raw, Format};
use crate::error::{Error, Result};

/// Cuts `path` (`.csv`, `.raw`, `.aedat4`) after its last whole unit in place; returns the
/// events it then holds (read through with this program's decoder).
pub fn cut_in_place(path: &Path) -> Result<u64> {
    let format = Format::for_output(path, None, super::Compression::default())?;
    if format == Format::Mcap {
        return super::mcap::close_in_place(path);
    }
    let len = std::fs::metadata(path)
        .map_err(|e| Error::io(path, e))?
        .len();
    let kept = whole_prefix(path, format)?;
    if kept < len {
        std::fs::OpenOptions::new()
            .write(true)
            .open(path)
            .and_then(|f| f.set_len(kept))
            .map_err(|e| Error::io(path, e))?;
        unfinished(path, format)?;
    }
    let mut decoder = super::open(path)?;
    let (mut events, mut buf) = (0u64, Vec::new());
    loop {
        buf.clear();
        match decoder.read_events(&mut buf, 1 << 16)? {
            0 => return Ok(events),
            n => events += n as u64,
        }
    }
}

/// After a cut: an `.aedat4` that was finished (its data table, after the packets, is cut
/// away) is marked unfinished, so that readers do not look for the table; an `.mcap` gets its
/// closing records.
pub fn unfinished(path: &Path, format: Format) -> Result<()> {
    if format == Format::Mcap {
        // A bag cut after a whole record is closed again.
        return super::mcap::close_after_cut(path);
    }
    if !matches!(format, Format::Aedat4(_)) {
        return Ok(());
    }
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let header = aedat4::Reader::new_file(std::io::BufReader::new(file))?;
    if header.header().data_table_position >= 0 {
        aedat4::forget_data_table(path)?;
    }
    Ok(())
}

/// The length of `path`'s leading whole units (packets, words, lines) in `format`.
pub fn whole_prefix(path: &Path, format: Format) -> Result<u64> {
    let open = || std::fs::File::open(path).map_err(|e| Error::io(path, e));
    let reader = || Ok::<_, Error>(std::io::BufReader::with_capacity(1 << 16, open()?));
    let len = std::fs::metadata(path)
        .map_err(|e| Error::io(path, e))?
        .len();
    let wrap = |e: Error| Error::format(path, e.to_string());
    match format {
        Format::Aedat4(_) => {
            let scan = || -> Result<(bool, u64)> {
                let mut r = aedat4::Reader::new_file(reader()?).map_err(wrap)?;
                let finished = r.header().data_table_position >= 0;
                let read = (|| {
                    while r.next_item()?.is_some() {}
                    Ok::<_, Error>(())
                })();
                match read {
                    // A finished file ends with its data table, after the packets.
                    Ok(()) if finished => Ok((true, len)),
                    Ok(()) => Ok((false, r.whole_bytes())),
                    // A finished file cut short (a copy on a full disk): its table is lost.
                    Err(_) if finished => Ok((true, u64::MAX)),
                    Err(e) => Err(wrap(e)),
                }
            };
            match scan()? {
                (true, u64::MAX) => {
                    // Read as an unfinished file (up to its last whole packet), on a copy of
                    // the header whose table position is forgotten.
                    let mut file = reader()?;
                    let mut magic = [0u8; aedat4::MAGIC.len()];
                    file.read_exact(&mut magic)
                        .map_err(|e| Error::io(path, e))?;
                    let mut r = aedat4::Reader::new_stream(file).map_err(wrap)?;
                    while r.next_item().map_err(wrap)?.is_some() {}
                    Ok(r.whole_bytes() + magic.len() as u64)
                }
                (_, kept) => Ok(kept),
            }
        }
        Format::Evt2 | Format::Evt3 => {
            // The header says which words follow (the extension does not).
            let header = raw::read_header(&mut reader()?).map_err(wrap)?;
            let word = match header.evt {
                Some(raw::Evt::Evt3) => 2,
                _ => 4,
            };
            let body = len.saturating_sub(header.bytes);
            Ok(header.bytes + body / word * word)
        }
        Format::Csv => {
            // After the last newline, unless what follows it is a whole line (a file whose
            // writer left out the last newline).
            let mut file = open()?;
            let mut end = len;
            let mut buf = vec![0u8; 1 << 16];
            let mut cut = 0;
            while end > 0 {
                let start = end.saturating_sub(buf.len() as u64);
                let chunk = &mut buf[..(end - start) as usize];
                file.seek(SeekFrom::Start(start))
                    .and_then(|_| file.read_exact(chunk))
                    .map_err(|e| Error::io(path, e))?;
                if let Some(i) = chunk.iter().rposition(|&b| b == b'\n') {
                    cut = start + i as u64 + 1;
                    break;
                }
                end = start;
            }
            if cut < len && csv_tail_is_whole(path, cut)? {
                return Ok(len);
            }
            Ok(cut)
        }
        Format::Mcap => super::mcap::whole_prefix(path),
        // Written whole from their journal.
        Format::Npz | Format::Hdf5 => Ok(len),
    }
}

/// Whether the CSV file `path`'s text after byte `from` (its last line, without a newline)
/// is a whole event in the file's columns. Reads the first two lines and the tail, each
/// bounded by the reader's longest line.
fn csv_tail_is_whole(path: &Path, from: u64) -> Result<bool> {
    use std::io::BufRead;
    const LINE: u64 = 4096;
    let mut file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    if len - from > LINE {
        return Ok(false);
    }
    let mut tail = Vec::new();
    file.seek(SeekFrom::Start(from))
        .and_then(|_| file.read_to_end(&mut tail))
        .map_err(|e| Error::io(path, e))?;
    file.seek(SeekFrom::Start(0))
        .map_err(|e| Error::io(path, e))?;
    let mut lines = std::io::BufReader::new(file.take(2 * LINE)).lines();
    let first = lines.next().and_then(|l| l.ok()).unwrap_or_default();
    let data = lines.next().and_then(|l| l.ok()).unwrap_or_default();
    let (Ok(tail), true) = (std::str::from_utf8(&tail), from > 0) else {
        return Ok(false);
    };
    Ok(super::csv::is_whole_last_line(&first, &data, tail))
}
