//! HDF5 event files in the DSEC layout (`events.h5`), read and written, in pure Rust (the
//! `rust-hdf5` crate: no system HDF5 library).
//!
//! | path | type | content |
//! |---|---|---|
//! | `events/x`, `events/y` | u16 | pixel column and row |
//! | `events/t` | u32 (i64 past 71 minutes, see below) | time in us relative to `t_offset` |
//! | `events/p` | u8 | polarity, 1 = ON, 0 = OFF |
//! | `ms_to_idx` | u64 | for each millisecond `m` from 0 to the last event's, the index of the first event with `t >= 1000 m` |
//! | `t_offset` | i64 scalar | the absolute time of relative 0, in us |
//! | root attributes `width`, `height` | u16 | the sensor size (our addition) |
//! | attribute `width` of `events/x`, `height` of `events/y` | u16 | the same, where this reader finds it |
//!
//! `events/x[ms_to_idx[m]:ms_to_idx[m + 1]]` (and likewise `y`, `t`, `p`) are the events of
//! millisecond `m`; an absolute time is `events/t[i] + t_offset`.
//!
//! Writing: `t_offset` is the first event's time, so `events/t` starts at 0. Every dataset is
//! chunked (65 536 values a chunk), extendable, and compressed with HDF5's built-in shuffle and
//! deflate (gzip) filters, which h5py and every HDF5 build read without plugins (DSEC's own
//! files use the blosc plugin instead). `events/t` is u32, as in DSEC, while the recording spans
//! under 2^32 us (about 71.6 minutes); the first event past that rewrites the column as i64 (the
//! file is closed and opened again, and the values move, in chunks, to a new dataset that takes
//! the name `events/t`), so a long recording is read the same way, and `t + t_offset` stays an
//! exact integer in NumPy (an i64 column, unlike a u64 one, does not turn into floats when
//! added to the i64 offset). Events and `ms_to_idx` are buffered a chunk at a time, so memory
//! stays flat however long the input. `ms_to_idx` has an entry per millisecond of the span
//! whatever the event count (a 5.8-hour sparse stream has 21 million, runs of equal values that
//! deflate compresses to little), so a file spans at most [`MAX_SPAN_US`] (2^40 us, 12.7 days)
//! and an event farther from the first is refused. Events must come in time order and inside
//! the sensor size given to [`Encoder::create`]. The files need HDF5 1.10 or later to read
//! (every h5py of the last years).
//! Every event also goes to the output's journal ([`super::journal`], 13 bytes an event, flushed
//! with the encoder), removed once the file is closed: the file is whole only then, so a run
//! killed before leaves the journal, from which `v2ce repair` writes the file.
//!
//! Reading: any integer types are accepted for the four columns (checked against the event's
//! ranges), polarity 1 is ON and 0 or -1 OFF, `t_offset` defaults to 0 when absent, and the
//! columns are read a slice at a time. `ms_to_idx` is not needed to read the events. The sensor
//! size comes from the `width` and `height` attributes of `events/x` and `events/y`, absent
//! from DSEC's files and from those v2ce wrote with the C library, which kept it in root
//! attributes only (there [`EventDecoder::size`] is `None`: the events tell). Compression: deflate, shuffle,
//! Fletcher-32, LZF and blosc (lz4, zstd, zlib, blosclz; DSEC's files) are read; a file with
//! another filter is refused when opened.

use std::path::{Path, PathBuf};

use rust_hdf5 as h5;

use super::journal::Journal;
use super::{check_event, EventDecoder, EventEncoder};
use crate::error::{Error, Result};
use crate::event::Event;

/// The events' group.
pub const EVENTS: &str = "events";

/// The millisecond index's dataset.
pub const MS_TO_IDX: &str = "ms_to_idx";

/// The time offset's dataset.
pub const T_OFFSET: &str = "t_offset";

/// Values per chunk, in every dataset; also the encoder's buffer, in events.
const CHUNK: usize = 1 << 16;

/// The deflate level (1 to 9): 2 writes files as small as the C library's level 1 did, as fast.
const DEFLATE_LEVEL: u32 = 2;

/// The largest relative time `events/t` holds as u32.
const T32_MAX: i64 = u32::MAX as i64;
/// The longest span an output file covers, us (2^40, about 12.7 days): its `ms_to_idx` then has
/// 1.1 billion entries (8.8 GB before deflate, which shrinks the runs of a sparse stream to a
/// fraction of that). Events farther from the first are refused.
pub const MAX_SPAN_US: i64 = 1 << 40;

/// The name `events/t`'s i64 copy has while it is filled, before it takes the name `t`.
const T_WIDE_TEMP: &str = "t_i64";

/// HDF5 filter ids this reader decodes (deflate, shuffle, Fletcher-32, LZF, blosc).
const READABLE_FILTERS: [u16; 5] = [1, 2, 3, 32000, 32001];

fn bad(message: impl Into<String>) -> Error {
    Error::invalid("HDF5", message.into())
}

fn h5err(what: &str) -> impl Fn(h5::Hdf5Error) -> Error + '_ {
    move |e| bad(format!("{what}: {e}"))
}

/// How the files are locked: as HDF5 does (honouring `HDF5_USE_FILE_LOCKING`), and not at all
/// where the file system has no locks.
fn options() -> h5::H5FileOptions {
    h5::H5File::options().best_effort_locking()
}

/// A new 1-D, extendable, chunked, compressed dataset of `T` named `name` in `group`.
fn column<T: h5::H5Type>(group: &h5::H5Group, name: &str) -> Result<h5::H5Dataset> {
    group
        .new_dataset::<T>()
        .shape([0usize])
        .chunk(&[CHUNK])
        .max_shape(&[None])
        .shuffle_deflate(DEFLATE_LEVEL)
        .create(name)
        .map_err(h5err(name))
}

/// Appends `values` to a dataset made by [`column`].
fn append<T: h5::H5Type>(ds: &h5::H5Dataset, values: &[T], what: &str) -> Result<()> {
    if values.is_empty() {
        return Ok(());
    }
    ds.append(values).map_err(h5err(what))
}

/// The datasets the encoder writes.
struct Columns {
    x: h5::H5Dataset,
    y: h5::H5Dataset,
    t: h5::H5Dataset,
    p: h5::H5Dataset,
    ms_to_idx: h5::H5Dataset,
    t_offset: h5::H5Dataset,
}

impl Columns {
    /// The datasets of a file written so far, opened again for appending.
    fn reopen(file: &h5::H5File) -> Result<Self> {
        let open = |name: &str| file.dataset_writer(name).map_err(h5err(name));
        Ok(Columns {
            x: open("events/x")?,
            y: open("events/y")?,
            t: open("events/t")?,
            p: open("events/p")?,
            ms_to_idx: open(MS_TO_IDX)?,
            t_offset: open(T_OFFSET)?,
        })
    }
}

/// Writes an HDF5 event file in the DSEC layout (see the module docs).
pub struct Encoder {
    // The datasets close before the file (fields drop in this order).
    columns: Option<Columns>,
    file: Option<h5::H5File>,
    path: PathBuf,
    width: u16,
    height: u16,
    /// Whether `events/t` is i64 (the recording outgrew u32).
    t_wide: bool,
    t_offset: Option<i64>,
    last_t: i64,
    /// Events accepted (flushed or buffered).
    count: u64,
    /// Events flushed to the datasets.
    flushed: usize,
    /// `ms_to_idx` entries made (flushed or buffered): the next millisecond to index.
    next_ms: u64,
    bx: Vec<u16>,
    by: Vec<u16>,
    bt: Vec<i64>,
    bp: Vec<u8>,
    bms: Vec<u64>,
    /// Every event taken, for `v2ce repair` should the run be killed before the file is
    /// closed (see [`super::journal`]); `None` when written from a journal.
    journal: Option<Journal>,
}

impl Encoder {
    /// Creates (or truncates) `path` for a `width x height` sensor.
    pub fn create(path: &Path, width: u16, height: u16) -> Result<Self> {
        let mut encoder = Self::create_unjournaled(path, width, height)?;
        encoder.journal = Some(Journal::create(path, width, height)?);
        Ok(encoder)
    }

    /// [`Encoder::create`] without a journal: for a file written from one.
    fn create_unjournaled(path: &Path, width: u16, height: u16) -> Result<Self> {
        let file = options()
            .create(path)
            .map_err(h5err("cannot create the file"))?;
        for (name, value) in [("width", width), ("height", height)] {
            file.set_attr_numeric(name, &value).map_err(h5err(name))?;
        }
        let events = file.create_group(EVENTS).map_err(h5err(EVENTS))?;
        let columns = Columns {
            x: column::<u16>(&events, "x")?,
            y: column::<u16>(&events, "y")?,
            t: column::<u32>(&events, "t")?,
            p: column::<u8>(&events, "p")?,
            ms_to_idx: column::<u64>(&file.root_group(), MS_TO_IDX)?,
            // 0 until the first event, whose time it then holds.
            t_offset: file
                .new_dataset::<i64>()
                .scalar()
                .create(T_OFFSET)
                .and_then(|d| d.write_raw(&[0i64]).map(|_| d))
                .map_err(h5err(T_OFFSET))?,
        };
        for (ds, name, value) in [(&columns.x, "width", width), (&columns.y, "height", height)] {
            ds.new_attr::<u16>()
                .create(name)
                .and_then(|a| a.write_numeric(&value))
                .map_err(h5err(name))?;
        }
        Ok(Encoder {
            journal: None,
            columns: Some(columns),
            file: Some(file),
            path: path.to_path_buf(),
            width,
            height,
            t_wide: false,
            t_offset: None,
            last_t: i64::MIN,
            count: 0,
            flushed: 0,
            next_ms: 0,
            bx: Vec::with_capacity(CHUNK),
            by: Vec::with_capacity(CHUNK),
            bt: Vec::with_capacity(CHUNK),
            bp: Vec::with_capacity(CHUNK),
            bms: Vec::with_capacity(CHUNK),
        })
    }

    fn columns(&self) -> Result<&Columns> {
        self.columns.as_ref().ok_or_else(|| bad("already finished"))
    }

    /// Writes the buffered events.
    fn flush_events(&mut self) -> Result<()> {
        let c = self.columns()?;
        append(&c.x, &self.bx, "events/x")?;
        append(&c.y, &self.by, "events/y")?;
        if self.t_wide {
            append(&c.t, &self.bt, "events/t")?;
        } else {
            // Below `T32_MAX` until the column widens (see `write`).
            let narrow: Vec<u32> = self.bt.iter().map(|&t| t as u32).collect();
            append(&c.t, &narrow, "events/t")?;
        }
        append(&c.p, &self.bp, "events/p")?;
        self.flushed += self.bx.len();
        self.bx.clear();
        self.by.clear();
        self.bt.clear();
        self.bp.clear();
        Ok(())
    }

    /// Writes the buffered `ms_to_idx` entries.
    fn flush_ms(&mut self) -> Result<()> {
        append(&self.columns()?.ms_to_idx, &self.bms, MS_TO_IDX)?;
        self.bms.clear();
        Ok(())
    }

    /// Rewrites the flushed part of `events/t` as i64, in chunks, under the same name. A file
    /// being written cannot be read from: it is closed, opened again for writing, and the old
    /// column read through a second handle.
    fn widen_t(&mut self) -> Result<()> {
        let (Some(columns), Some(file)) = (self.columns.take(), self.file.take()) else {
            return Err(bad("already finished"));
        };
        drop(columns);
        file.close_no_sync()
            .map_err(h5err("cannot close the file to widen events/t"))?;
        let file = options()
            .open_rw(&self.path)
            .map_err(h5err("cannot open the file again to widen events/t"))?;
        let events = file.root_group().group(EVENTS).map_err(h5err(EVENTS))?;
        let wide = column::<i64>(&events, T_WIDE_TEMP)?;
        {
            let old = h5::H5File::options()
                .no_locking()
                .open(&self.path)
                .map_err(h5err("events/t"))?;
            let t = old.dataset("events/t").map_err(h5err("events/t"))?;
            let mut at = 0;
            while at < self.flushed {
                let n = CHUNK.min(self.flushed - at);
                let part = t
                    .read_numeric_slice_as::<i64>(&[at], &[n])
                    .map_err(h5err("events/t"))?;
                append(&wide, &part, "events/t")?;
                at += n;
            }
        }
        drop(wide);
        let temp = format!("{EVENTS}/{T_WIDE_TEMP}");
        file.delete_dataset("events/t").map_err(h5err("events/t"))?;
        events
            .link("t", &format!("/{temp}"))
            .map_err(h5err("events/t"))?;
        file.delete_dataset(&temp).map_err(h5err("events/t"))?;
        self.columns = Some(Columns::reopen(&file)?);
        self.file = Some(file);
        self.t_wide = true;
        Ok(())
    }
}

impl Encoder {
    /// Takes `events` into the buffers, counting in `taken` those taken.
    fn take(&mut self, events: &[Event], taken: &mut usize) -> Result<()> {
        self.columns()?;
        for e in events {
            check_event(e, self.last_t, self.width, self.height)?;
            self.last_t = e.t;
            let offset = match self.t_offset {
                Some(o) => o,
                None => {
                    self.columns()?
                        .t_offset
                        .write_raw(&[e.t])
                        .map_err(h5err(T_OFFSET))?;
                    *self.t_offset.insert(e.t)
                }
            };
            // Events come in time order, so `rel` is at least 0; it saturates far past the span.
            let rel = e.t.saturating_sub(offset);
            if rel > MAX_SPAN_US {
                return Err(bad(format!(
                    "{} us is {rel} us after the first event's {offset} us; an .h5 file spans at \
                     most {MAX_SPAN_US} us (its ms_to_idx has an entry per millisecond): split \
                     the stream",
                    e.t
                )));
            }
            if rel > T32_MAX && !self.t_wide {
                // The buffered times go out as u32 first: all are below the limit.
                self.flush_events()?;
                self.widen_t()?;
            }
            // The first event at or after millisecond `next_ms` (events come in time order):
            // every millisecond up to this event's starts here, a chunk at a time.
            let ms = (rel / 1000) as u64;
            while self.next_ms <= ms {
                let room = (CHUNK - self.bms.len()) as u64;
                let n = (ms + 1 - self.next_ms).min(room);
                self.bms.resize(self.bms.len() + n as usize, self.count);
                self.next_ms += n;
                if self.bms.len() >= CHUNK {
                    self.flush_ms()?;
                }
            }
            self.bx.push(e.x);
            self.by.push(e.y);
            self.bt.push(rel);
            self.bp.push(e.on as u8);
            self.count += 1;
            *taken += 1;
            if self.bx.len() >= CHUNK {
                self.flush_events()?;
            }
        }
        Ok(())
    }
}

impl EventEncoder for Encoder {
    fn write(&mut self, events: &[Event]) -> Result<()> {
        let mut taken = 0;
        let took = self.take(events, &mut taken);
        if let Some(journal) = self.journal.as_mut() {
            journal.append(&events[..taken])?;
        }
        took
    }

    /// The events go to the journal, which a killed run leaves for `v2ce repair`.
    fn flush(&mut self) -> Result<()> {
        match self.journal.as_mut() {
            Some(journal) => journal.flush(),
            None => Ok(()),
        }
    }

    /// The file written again from the records that reached the journal (the library's file,
    /// whose writes failed, removed first: its room is what the new one takes). As many events
    /// as the failed file held, fewer where even that does not fit; the rest go with the
    /// journal, as the file holds exactly what is reported.
    fn salvage(&mut self) -> Result<Option<u64>> {
        let Some(mut journal) = self.journal.take() else {
            return Ok(None);
        };
        let (file, count) = journal.into_file()?;
        drop(file);
        drop(self.columns.take());
        if let Some(file) = self.file.take() {
            // Closed, not dropped: the library says on stderr when a drop cannot finish.
            let _ = file.close();
        }
        let journal_path = journal.path().to_path_buf();
        // All it took, else as many as the failed file held, else fewer.
        let mut tries = [count, count.min(self.flushed as u64)].into_iter();
        let mut want = count;
        let mut last_error = None;
        for _ in 0..8 {
            want = tries.next().unwrap_or(want / 2);
            let _ = std::fs::remove_file(&self.path);
            let size = Some((self.width, self.height));
            match write_journal(&journal_path, &self.path, size, want) {
                Ok(written) if written == want => {
                    journal.complete();
                    return Ok(Some(want));
                }
                Ok(written) => {
                    let _ = std::fs::remove_file(&self.path);
                    last_error = Some(bad(format!("the journal held {written} of {want} events")));
                    break;
                }
                Err(e) if want > 0 => {
                    tracing::debug!("{}: {e}; trying fewer events", self.path.display());
                    last_error = Some(e);
                }
                Err(e) => {
                    last_error = Some(e);
                    break;
                }
            }
        }
        let _ = std::fs::remove_file(&self.path);
        Err(Error::Run(format!(
            "{}; the {count} events are in {} (`v2ce repair {}` writes the file once the disk \
             has room)",
            last_error.map_or_else(String::new, |e| e.to_string()),
            journal_path.display(),
            self.path.display()
        )))
    }
    /// Written whole only at the end (the file's index comes last); until then `v2ce repair`
    /// makes the file from its journal.
    fn readable_after_flush(&self) -> bool {
        false
    }

    fn finish(&mut self) -> Result<()> {
        self.flush_events()?;
        self.flush_ms()?;
        let (Some(columns), Some(file)) = (self.columns.take(), self.file.take()) else {
            return Err(bad("finished twice"));
        };
        drop(columns);
        file.close().map_err(h5err("cannot close the file"))?;
        if let Some(journal) = self.journal.as_mut() {
            journal.complete();
        }
        Ok(())
    }
}

/// Writes `path` from the journal at `journal` (its sensor size, every whole record), without
/// a journal of its own (the one it reads is the copy a kill would leave); returns the events.
pub fn write_from_journal(journal: &Path, path: &Path) -> Result<u64> {
    write_journal(journal, path, None, u64::MAX)
}

/// Writes `path` without a journal from the first `n` (at most) events of `journal`, for a
/// sensor of `size` (`None`: the journal's); returns the events written.
fn write_journal(journal: &Path, path: &Path, size: Option<(u16, u16)>, n: u64) -> Result<u64> {
    let mut from = super::journal::Decoder::open(journal)?;
    let (w, h) = size.or(from.size()).unwrap_or((0, 0));
    let mut to = Encoder::create_unjournaled(path, w, h)?;
    let mut buf = Vec::with_capacity(CHUNK);
    let mut written = 0u64;
    while written < n {
        buf.clear();
        let want = CHUNK.min(usize::try_from(n - written).unwrap_or(CHUNK));
        if from.read_events(&mut buf, want)? == 0 {
            break;
        }
        buf.truncate(want);
        to.write(&buf)?;
        written += buf.len() as u64;
    }
    to.finish()?;
    Ok(written)
}

/// Opens `NAME` (a path from the root), checks it is a 1-D integer dataset whose filters this
/// reader decodes.
fn open_column(file: &h5::H5File, name: &str) -> Result<h5::H5Dataset> {
    let ds = file
        .dataset(name)
        .map_err(|_| bad(format!("no {name} dataset")))?;
    let shape = ds.shape();
    if shape.len() != 1 {
        return Err(bad(format!(
            "{name} has shape {shape:?}; expected one dimension"
        )));
    }
    match ds.datatype().map_err(h5err(name))? {
        h5::DatatypeMessage::FixedPoint { .. } => {}
        other => return Err(bad(format!("{name} holds {other:?}; expected integers"))),
    }
    // A chunk is decoded whole, in memory the size the file declares.
    if let Some(dims) = ds.chunk_dims() {
        let bytes = dims
            .iter()
            .try_fold(ds.element_size() as u64, |b, &d| b.checked_mul(d as u64));
        if bytes.is_none_or(|b| b > crate::limits::MAX_CHUNK_BYTES) {
            return Err(bad(format!(
                "{name} declares chunks of {dims:?} values, more than the {} MiB a chunk may \
                 take",
                crate::limits::MAX_CHUNK_BYTES >> 20
            )));
        }
    }
    let filters = ds.filters().map_err(h5err(name))?;
    if let Some(f) = filters.iter().find(|f| !READABLE_FILTERS.contains(&f.id)) {
        return Err(bad(format!(
            "{name} is compressed with HDF5 filter number {}, which this reader lacks \
             (rewrite the file with gzip, blosc or no compression)",
            f.id
        )));
    }
    Ok(ds)
}

/// Reads `n` values of a column from `at` as i64 (any integer type; a u64 above `i64::MAX`
/// is an error).
fn read_column(ds: &h5::H5Dataset, at: usize, n: usize, what: &str) -> Result<Vec<i64>> {
    let values = ds
        .read_numeric_slice_as::<i64>(&[at], &[n])
        .map_err(h5err(what))?;
    if values.len() != n {
        return Err(bad(format!(
            "{what}: {} values read of {n} asked",
            values.len()
        )));
    }
    Ok(values)
}

/// An integer attribute `name` of dataset `ds`, `None` when absent.
fn read_attr(ds: &h5::H5Dataset, name: &str) -> Result<Option<i64>> {
    if !ds
        .attr_names()
        .map_err(h5err("attributes"))?
        .iter()
        .any(|n| n == name)
    {
        return Ok(None);
    }
    let values = ds
        .attr(name)
        .and_then(|a| a.read_numeric_as::<i64>())
        .map_err(h5err(name))?;
    match values[..] {
        [v] => Ok(Some(v)),
        _ => Err(bad(format!(
            "{name} has {} values; expected one",
            values.len()
        ))),
    }
}

/// Reads an HDF5 event file in the DSEC layout (see the module docs) a slice at a time.
pub struct Decoder {
    x: h5::H5Dataset,
    y: h5::H5Dataset,
    t: h5::H5Dataset,
    p: h5::H5Dataset,
    len: usize,
    pos: usize,
    t_offset: i64,
    size: Option<(u16, u16)>,
    compression: String,
    _file: h5::H5File,
}

impl Decoder {
    /// Opens `path` and checks its layout (the four columns, their lengths, `t_offset`, the
    /// size attributes).
    pub fn open(path: &Path) -> Result<Self> {
        let file = options()
            .open(path)
            .map_err(|e| bad(format!("cannot open as HDF5: {e}")))?;
        if file.root_group().group(EVENTS).is_err() {
            return Err(bad(format!(
                "no {EVENTS} group (not a DSEC-layout event file)"
            )));
        }
        let x = open_column(&file, "events/x")?;
        let y = open_column(&file, "events/y")?;
        let t = open_column(&file, "events/t")?;
        let p = open_column(&file, "events/p")?;
        let len = x.shape()[0];
        for (name, col) in [("y", &y), ("t", &t), ("p", &p)] {
            if col.shape()[0] != len {
                return Err(bad(format!(
                    "{EVENTS}/x has {len} values but {EVENTS}/{name} has {}",
                    col.shape()[0]
                )));
            }
        }
        let t_offset = match file.dataset(T_OFFSET) {
            Ok(ds) => {
                if ds.total_elements() != 1 {
                    return Err(bad(format!(
                        "{T_OFFSET} has {} values; expected one",
                        ds.total_elements()
                    )));
                }
                ds.read_numeric_as::<i64>()
                    .map_err(h5err(T_OFFSET))?
                    .first()
                    .copied()
                    .ok_or_else(|| bad(format!("{T_OFFSET} has no value")))?
            }
            Err(_) => 0,
        };
        let size = match (read_attr(&x, "width")?, read_attr(&y, "height")?) {
            (Some(w), Some(h)) => {
                let fit = |v: i64| u16::try_from(v).ok().filter(|&v| v > 0);
                match (fit(w), fit(h)) {
                    (Some(w), Some(h)) => Some((w, h)),
                    _ => return Err(bad(format!("a {w} x {h} sensor"))),
                }
            }
            _ => None,
        };
        let compression = describe_filters(&t);
        Ok(Decoder {
            x,
            y,
            t,
            p,
            len,
            pos: 0,
            t_offset,
            size,
            compression,
            _file: file,
        })
    }

    /// The file's `t_offset` (0 when absent), in us: added to `events/t`.
    pub fn t_offset(&self) -> i64 {
        self.t_offset
    }

    /// The number of events in the file.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether the file has no events.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The filters `events/t` is stored with, e.g. `shuffle+deflate` (`none` without).
    pub fn compression(&self) -> &str {
        &self.compression
    }
}

/// A dataset's filters by name, joined with `+`, or `none`.
fn describe_filters(ds: &h5::H5Dataset) -> String {
    let names: Vec<String> = ds
        .filters()
        .unwrap_or_default()
        .iter()
        .map(|f| match f.id {
            1 => "deflate".to_string(),
            2 => "shuffle".to_string(),
            3 => "fletcher32".to_string(),
            4 => "szip".to_string(),
            5 => "nbit".to_string(),
            6 => "scaleoffset".to_string(),
            32000 => "lzf".to_string(),
            32001 => "blosc".to_string(),
            id => format!("filter {id}"),
        })
        .collect();
    if names.is_empty() {
        "none".into()
    } else {
        names.join("+")
    }
}

impl EventDecoder for Decoder {
    fn size(&self) -> Option<(u16, u16)> {
        self.size
    }

    fn read_events(&mut self, out: &mut Vec<Event>, max: usize) -> Result<usize> {
        let n = max.max(1).min(self.len - self.pos);
        if n == 0 {
            return Ok(0);
        }
        let at = self.pos;
        let x = read_column(&self.x, at, n, "events/x")?;
        let y = read_column(&self.y, at, n, "events/y")?;
        let t = read_column(&self.t, at, n, "events/t")?;
        let p = read_column(&self.p, at, n, "events/p")?;
        out.reserve(n);
        for (i, (((&x, &y), &t), &p)) in x.iter().zip(&y).zip(&t).zip(&p).enumerate() {
            let at = self.pos + i;
            let pixel = |v: i64, what: &str| {
                u16::try_from(v).map_err(|_| bad(format!("event {at}: {what} = {v}")))
            };
            let on = match p {
                1 => true,
                0 | -1 => false,
                _ => return Err(bad(format!("event {at}: polarity {p} (expected 1 or 0)"))),
            };
            let t = t.checked_add(self.t_offset).ok_or_else(|| {
                bad(format!(
                    "event {at}: time {t} + t_offset {} overflows",
                    self.t_offset
                ))
            })?;
            out.push(Event::new(t, pixel(x, "x")?, pixel(y, "y")?, on));
        }
        self.pos += n;
        Ok(n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_dir(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("v2ce-h5-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn write(path: &Path, w: u16, h: u16, events: &[Event], chunk: usize) {
        let mut enc = Encoder::create(path, w, h).unwrap();
        for part in events.chunks(chunk.max(1)) {
            enc.write(part).unwrap();
        }
        enc.finish().unwrap();
    }

    fn read(path: &Path, max: usize) -> (Option<(u16, u16)>, Vec<Event>) {
        let mut dec = Decoder::open(path).unwrap();
        let mut got = Vec::new();
        while dec.read_events(&mut got, max).unwrap() > 0 {}
        (dec.size(), got)
    }

    /// `ms_to_idx` computed directly from the definition (for sorted times): the count of
    /// events before each millisecond.
    fn ms_to_idx_of(rel: &[i64]) -> Vec<u64> {
        let Some(&last) = rel.last() else {
            return Vec::new();
        };
        (0..=last / 1000)
            .map(|m| rel.partition_point(|&t| t < m * 1000) as u64)
            .collect()
    }

    /// `events/t` (as i64), `ms_to_idx`, `t_offset` and the type of `events/t`.
    fn stored(path: &Path) -> (Vec<i64>, Vec<u64>, i64, h5::DatatypeMessage) {
        let f = h5::H5File::open(path).unwrap();
        let t = f.dataset("events/t").unwrap();
        (
            t.read_numeric_as::<i64>().unwrap(),
            f.dataset(MS_TO_IDX)
                .unwrap()
                .read_numeric_as::<u64>()
                .unwrap(),
            f.dataset(T_OFFSET)
                .unwrap()
                .read_numeric_as::<i64>()
                .unwrap()[0],
            t.datatype().unwrap(),
        )
    }

    /// Whether `dtype` is an integer type of `size` bytes, `signed` or not.
    fn is_int(dtype: &h5::DatatypeMessage, size: u32, signed: bool) -> bool {
        matches!(dtype, h5::DatatypeMessage::FixedPoint { size: s, signed: g, .. } if *s == size && *g == signed)
    }

    #[test]
    fn round_trip_with_ms_to_idx() {
        let dir = temp_dir("round");
        let path = dir.join("e.h5");
        // Several seconds, ON and OFF, runs of equal times, gaps of several milliseconds, and
        // more events than a chunk.
        let t0 = 1_700_000_000_123_456;
        let events: Vec<Event> = (0..150_000i64)
            .map(|i| {
                let t = t0 + (i / 3) * 97 + (i / 10_000) * 7_000;
                Event::new(t, (i % 640) as u16, (i * 7 % 480) as u16, i % 5 < 2)
            })
            .collect();
        assert!(events.last().unwrap().t - t0 > 4_000_000);
        write(&path, 640, 480, &events, 7_777);
        let (size, got) = read(&path, 10_000);
        assert_eq!(size, Some((640, 480)));
        assert_eq!(got, events);
        let (t, ms, offset, dtype) = stored(&path);
        assert_eq!(offset, t0);
        assert!(is_int(&dtype, 4, false), "{dtype:?}");
        assert_eq!(t[0], 0);
        assert_eq!(ms, ms_to_idx_of(&t));
        // Through `open` and `read_events`, by extension.
        std::fs::copy(&path, dir.join("e.hdf5")).unwrap();
        let rec = super::super::read_events(&dir.join("e.hdf5")).unwrap();
        assert_eq!(rec.events.events(), &events[..]);
        assert_eq!((rec.width, rec.height), (640, 480));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn spans_are_bounded_from_any_first_time() {
        let dir = temp_dir("span");
        // From i64::MIN: the first event sets the offset, one past the span is refused at once
        // (it used to fill ms_to_idx for 9e15 milliseconds).
        let path = dir.join("min.h5");
        let mut enc = Encoder::create(&path, 8, 8).unwrap();
        enc.write(&[Event::new(i64::MIN, 0, 0, true)]).unwrap();
        let e = enc
            .write(&[Event::new(i64::MIN + MAX_SPAN_US + 1, 1, 0, true)])
            .unwrap_err()
            .to_string();
        assert!(e.contains("split the stream"), "{e}");
        let e = enc
            .write(&[Event::new(i64::MAX, 1, 0, true)])
            .unwrap_err()
            .to_string();
        assert!(e.contains("split the stream"), "{e}");
        // A gap of 10 hours is filled a chunk at a time and comes back exactly.
        let path = dir.join("gap.h5");
        let events = [
            Event::new(i64::MIN + 5, 0, 0, true),
            Event::new(i64::MIN + 5 + 36_000_000_000, 1, 1, false),
        ];
        write(&path, 8, 8, &events, 1);
        let (_, got) = read(&path, 10);
        assert_eq!(got, events);
        let (t, ms, _, _) = stored(&path);
        assert_eq!(ms.len(), 36_000_001);
        assert_eq!(ms, ms_to_idx_of(&t));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn long_recordings_widen_t_to_i64() {
        let dir = temp_dir("wide");
        let path = dir.join("e.h5");
        // 100 000 events over 5 hours, so the widening copies more than a chunk.
        let events: Vec<Event> = (0..100_000i64)
            .map(|i| Event::new(-5_000 + i * 180_000, (i % 8) as u16, 3, i % 2 == 0))
            .collect();
        write(&path, 8, 4, &events, 50_000);
        let (_, got) = read(&path, 65_536);
        assert_eq!(got, events);
        let (t, ms, offset, dtype) = stored(&path);
        assert_eq!(offset, -5_000);
        assert!(is_int(&dtype, 8, true), "{dtype:?}");
        assert_eq!(ms.len() as i64, t.last().unwrap() / 1000 + 1);
        for (m, &i) in ms.iter().enumerate().step_by(997) {
            let i = i as usize;
            assert!(t[i] >= m as i64 * 1000 && (i == 0 || t[i - 1] < m as i64 * 1000));
        }
        let f = h5::H5File::open(&path).unwrap();
        assert!(f.dataset(&format!("{EVENTS}/{T_WIDE_TEMP}")).is_err());
        drop(f);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn empty_stream_and_encoder_errors() {
        let dir = temp_dir("empty");
        let path = dir.join("e.h5");
        write(&path, 32, 16, &[], 1);
        let (size, got) = read(&path, 100);
        assert_eq!((size, got.len()), (Some((32, 16)), 0));
        let (t, ms, offset, _) = stored(&path);
        assert_eq!((t.len(), ms.len(), offset), (0, 0, 0));
        let mut enc = Encoder::create(&path, 32, 16).unwrap();
        assert!(enc.write(&[Event::new(5, 32, 0, true)]).is_err());
        enc.write(&[Event::new(5, 31, 15, true)]).unwrap();
        assert!(enc.write(&[Event::new(4, 0, 0, true)]).is_err());
        enc.finish().unwrap();
        assert!(enc.finish().is_err());
        assert!(enc.write(&[Event::new(6, 0, 0, true)]).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Writes an HDF5 file with the given `events/NAME` u16 columns (`t` as u32), `p` the
    /// values 0, 1, 0, ... with `bad_p` at index 1 where given.
    fn write_columns(path: &Path, columns: &[(&str, usize)], bad_p: Option<u16>) {
        let f = h5::H5File::create(path).unwrap();
        let g = f.create_group(EVENTS).unwrap();
        for &(name, n) in columns {
            let values: Vec<u32> = (0..n as u32).collect();
            if name == "t" {
                let ds = g.new_dataset::<u32>().shape([n]).create(name).unwrap();
                ds.write_raw(&values).unwrap();
            } else {
                let mut values: Vec<u16> = values.iter().map(|&v| (v % 2) as u16).collect();
                if let (Some(v), "p") = (bad_p, name) {
                    values[1] = v;
                }
                let ds = g.new_dataset::<u16>().shape([n]).create(name).unwrap();
                ds.write_raw(&values).unwrap();
            }
        }
        f.close().unwrap();
    }

    fn open_error(path: &Path) -> String {
        match Decoder::open(path) {
            Ok(_) => panic!("{} opened", path.display()),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn bad_files_are_errors() {
        let dir = temp_dir("bad");
        let p = dir.join("not.h5");
        std::fs::write(&p, b"this is not an HDF5 file").unwrap();
        assert!(open_error(&p).contains("cannot open as HDF5"));
        let err = super::super::open(&p).err().unwrap().to_string();
        assert!(err.contains("not.h5") && err.contains("HDF5"), "{err}");
        let p = dir.join("no-t.h5");
        write_columns(&p, &[("x", 3), ("y", 3), ("p", 3)], None);
        assert!(open_error(&p).contains("no events/t"), "{}", open_error(&p));
        let p = dir.join("lengths.h5");
        write_columns(&p, &[("x", 3), ("y", 3), ("t", 4), ("p", 3)], None);
        assert!(
            open_error(&p).contains("events/t has 4"),
            "{}",
            open_error(&p)
        );
        // Well formed, no t_offset, no size: DSEC-like; then a polarity out of range.
        let p = dir.join("ok.h5");
        write_columns(&p, &[("x", 3), ("y", 3), ("t", 3), ("p", 3)], None);
        let (size, got) = read(&p, 2);
        assert_eq!(size, None);
        assert_eq!(
            got,
            [
                Event::new(0, 0, 0, false),
                Event::new(1, 1, 1, true),
                Event::new(2, 0, 0, false)
            ]
        );
        let p = dir.join("polarity.h5");
        write_columns(&p, &[("x", 3), ("y", 3), ("t", 3), ("p", 3)], Some(7));
        let mut dec = Decoder::open(&p).unwrap();
        let err = dec
            .read_events(&mut Vec::new(), 10)
            .unwrap_err()
            .to_string();
        assert!(err.contains("polarity 7"), "{err}");
        // Cut short: the file's end is gone.
        let p = dir.join("cut.h5");
        let bytes = std::fs::read(dir.join("ok.h5")).unwrap();
        assert!(bytes.len() > 64);
        std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
        if let Ok(mut dec) = Decoder::open(&p) {
            let mut out = Vec::new();
            while let Ok(n) = dec.read_events(&mut out, 10) {
                if n == 0 {
                    break;
                }
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
