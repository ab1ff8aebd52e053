//! Event and frame-time files: one module per format, picked by file extension.
//!
//! | extension | module | events | frame times |
//! |---|---|---|---|
//! | `.aedat4` | [`aedat4`] | read and written | the APS frames' mid-exposure times |
//! | `.raw` | [`evt2`], [`evt3`] (header in [`raw`]) | read and written | - |
//! | `.csv` | [`csv`] | `t_us,x,y,on`, read and written | - |
//! | `.npz` | [`npz`] | the V2CE toolbox's `event_stream` record array, read and written | - |
//! | `.h5`, `.hdf5` | [`hdf5`] | DSEC layout (`events/x,y,t,p`, `ms_to_idx`, `t_offset`), read and written (gzip) | - |
//! | `.mcap` | [`mcap`] | rosbag2: `event_camera_msgs/msg/EventPacket` (EVT 3.0 payloads, [`event_packet`]), read and written | - |
//! | `.txt` | [`ijrr`] | `events.txt` (`t_seconds x y polarity`), read | `images.txt` (`t_seconds path`) |
//!
//! The UDP datagram word layouts (`spif` and faery's) are in [`datagram`].
//!
//! Every format has a streaming [`EventDecoder`] and (but IJRR) an [`EventEncoder`]; [`open`] and
//! [`create`] pick them by extension.

pub mod aedat4;
pub mod csv;
pub mod cut;
pub mod datagram;
pub mod event_packet;
pub mod evt2;
pub mod evt3;
pub mod hdf5;
pub mod ijrr;
pub mod journal;
pub mod mcap;
pub mod npz;
pub mod raw;

use std::io::{BufReader, BufWriter, Read};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::event::{Event, EventPacket};

pub use aedat4::Compression;

/// A stream of events read in chunks, so memory stays flat however long the input.
pub trait EventDecoder {
    /// Sensor width and height, when the input says.
    fn size(&self) -> Option<(u16, u16)>;

    /// Appends about `max` events to `out` (a format may finish the word it is in); returns
    /// how many were added, 0 at the end of the input.
    fn read_events(&mut self, out: &mut Vec<Event>, max: usize) -> Result<usize>;
}

/// A writer of events in time order.
pub trait EventEncoder {
    /// Appends events; they must come in time order (within and across calls).
    fn write(&mut self, events: &[Event]) -> Result<()>;

    /// Writes whatever the format needs at the end and flushes. Call once, last.
    fn finish(&mut self) -> Result<()>;

    /// Hands what is held to the operating system, in whole units of the format (events held
    /// for a packet become a shorter packet), so a process killed later loses nothing written
    /// before. Formats that buffer nothing of their own do nothing.
    fn flush(&mut self) -> Result<()> {
        Ok(())
    }

    /// Whether the file holds, in a form its readers take, every event written once
    /// [`EventEncoder::flush`] has returned; `false` for the formats written whole only at
    /// [`EventEncoder::finish`] (`.npz`, `.h5`).
    fn readable_after_flush(&self) -> bool {
        true
    }

    /// After a failed write (a full disk, `ulimit -f`): closes the file readably with what
    /// reached it, writing no more than the format's closing bytes, and returns the events it
    /// holds; `None` where the file needs only cutting after its last whole unit, which
    /// [`create`]'s encoder does itself. The encoder takes no more events.
    fn salvage(&mut self) -> Result<Option<u64>> {
        Ok(None)
    }

    /// After a write failed: the events the file was closed with (see
    /// [`EventEncoder::salvage`]); `None` before, or where it could not be closed.
    fn kept(&self) -> Option<u64> {
        None
    }
}

/// Checks what every encoder and sink requires of an event: time at or after `last_t`, and a
/// pixel inside the `width x height` sensor.
pub fn check_event(e: &Event, last_t: i64, width: u16, height: u16) -> Result<()> {
    if e.t < last_t {
        return Err(Error::invalid(
            "event time",
            format!("{} us comes before {last_t} us", e.t),
        ));
    }
    if e.x >= width || e.y >= height {
        return Err(Error::invalid(
            "pixel",
            format!(
                "({}, {}) is outside the {width} x {height} sensor",
                e.x, e.y
            ),
        ));
    }
    Ok(())
}

/// Reads whole `word`-byte words into `buf`; returns the bytes read (less than `buf.len()` only
/// at the end of the input). An input that ends inside a word (a writer killed mid-write, a
/// power cut) loses that word, with a warning naming it.
pub(crate) fn read_words(
    r: &mut impl Read,
    buf: &mut [u8],
    word: usize,
    first_word: u64,
    what: &'static str,
) -> Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(Error::invalid(what, e.to_string())),
        }
    }
    let partial = n % word;
    if partial != 0 {
        tracing::warn!(
            "{what}: the input ends {partial} byte(s) into word {} (a truncated input), which is dropped",
            first_word + (n / word) as u64
        );
    }
    Ok(n - partial)
}

/// The event file formats, picked by extension (`.raw` needs the EVT version).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// AEDAT 4.0 with the given packet compression.
    Aedat4(Compression),
    /// Prophesee RAW EVT 2.0.
    Evt2,
    /// Prophesee RAW EVT 3.0.
    Evt3,
    /// CSV `t_us,x,y,on`.
    Csv,
    /// The V2CE toolbox's `.npz` (`event_stream` record array).
    Npz,
    /// HDF5 in the DSEC layout (`.h5`, `.hdf5`).
    Hdf5,
    /// A rosbag2 `.mcap` of ROS 2 EventPacket messages (EVT 3.0 payloads).
    Mcap,
}

impl Format {
    /// The output format for `path`: `.aedat4` (with `compression`), `.raw` (with `evt` 2 or 3,
    /// 2 when absent), `.csv`, `.npz`, or `.h5`/`.hdf5`.
    pub fn for_output(path: &Path, evt: Option<u8>, compression: Compression) -> Result<Self> {
        match (extension(path).as_str(), evt) {
            ("aedat4", _) => Ok(Format::Aedat4(compression)),
            // EVT 2.0 unless asked: two common readers (aestream 0.6.4, expelliarmus 1.1.12)
            // mis-time EVT 3.0, and every RAW reader reads EVT 2.0 right.
            ("raw", Some(2) | None) => Ok(Format::Evt2),
            ("raw", Some(3)) => Ok(Format::Evt3),
            ("raw", Some(v)) => Err(Error::invalid(
                "EVT version",
                format!("{v} (expected 2 or 3)"),
            )),
            ("csv", _) => Ok(Format::Csv),
            ("npz", _) => Ok(Format::Npz),
            ("h5" | "hdf5", _) => Ok(Format::Hdf5),
            ("mcap", _) => Ok(Format::Mcap),
            (other, _) => Err(Error::invalid(
                "output file",
                format!(
                    "{}: unknown extension '.{other}' (expected .aedat4, .raw, .csv, .npz, .h5, .hdf5 or .mcap)",
                    path.display()
                ),
            )),
        }
    }

    /// A short name: `aedat4`, `evt2`, `evt3`, `csv`, `npz`, `hdf5`, `mcap`.
    pub fn name(self) -> &'static str {
        match self {
            Format::Aedat4(_) => "aedat4",
            Format::Evt2 => "evt2",
            Format::Evt3 => "evt3",
            Format::Csv => "csv",
            Format::Npz => "npz",
            Format::Hdf5 => "hdf5",
            Format::Mcap => "mcap",
        }
    }
}

/// Prefixes a decoder's errors with its file, and checks its events' times where asked.
struct FileDecoder {
    path: PathBuf,
    inner: Box<dyn EventDecoder + Send>,
    /// Refuse times outside `±`[`crate::time::MAX_ABS_US`] (see [`open`]).
    check_times: bool,
}

impl EventDecoder for FileDecoder {
    fn size(&self) -> Option<(u16, u16)> {
        self.inner.size()
    }

    fn read_events(&mut self, out: &mut Vec<Event>, max: usize) -> Result<usize> {
        let start = out.len();
        let n = self
            .inner
            .read_events(out, max)
            .map_err(|e| Error::format(&self.path, e.to_string()))?;
        if !self.check_times {
            return Ok(n);
        }
        // Times enter here: every later difference of two fits (see `crate::time`).
        for e in &out[start..] {
            if let Err(err) = crate::time::check("event time", e.t) {
                let at = format!("the event at ({}, {}): {err}", e.x, e.y);
                out.truncate(start);
                return Err(Error::format(&self.path, at));
            }
        }
        Ok(n)
    }
}

/// Opens an event file for streaming: `.aedat4`, `.raw` (EVT 2.0 or 3.0, from its header),
/// `.csv`, `.npz`, `.h5`/`.hdf5` (DSEC layout), or an IJRR `events.txt`.
///
/// Every event's time is checked to lie within `±`[`crate::time::MAX_ABS_US`] as it is read
/// (a clear error past it), so that what the program computes from them cannot wrap; see
/// [`open_verbatim`] for a reader that only copies them.
pub fn open(path: &Path) -> Result<Box<dyn EventDecoder + Send>> {
    open_checked(path, true)
}

/// [`open`] for a reader that computes nothing from its events' times (`transcode`, `info`):
/// any `i64` time is read as it is.
pub fn open_verbatim(path: &Path) -> Result<Box<dyn EventDecoder + Send>> {
    open_checked(path, false)
}

fn open_checked(path: &Path, check_times: bool) -> Result<Box<dyn EventDecoder + Send>> {
    if path.is_dir() {
        return Err(Error::format(path, "a folder, not an event file"));
    }
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut reader = BufReader::with_capacity(1 << 16, file);
    let wrap = |e: Error| Error::format(path, e.to_string());
    let inner: Box<dyn EventDecoder + Send> = match extension(path).as_str() {
        "aedat4" => Box::new(aedat4::Reader::new_file(reader).map_err(wrap)?),
        "raw" => {
            let header = raw::read_header(&mut reader).map_err(wrap)?;
            match header.evt {
                Some(raw::Evt::Evt3) => Box::new(evt3::Decoder::new(reader, &header)),
                _ => Box::new(evt2::Decoder::new(reader, &header)),
            }
        }
        "csv" => Box::new(csv::Decoder::new(reader)),
        "npz" => {
            drop(reader);
            Box::new(npz::Decoder::open(path)?)
        }
        "h5" | "hdf5" => {
            drop(reader);
            Box::new(hdf5::Decoder::open(path).map_err(wrap)?)
        }
        "txt" => Box::new(ijrr::Decoder::new(reader)),
        "mcap" => Box::new(mcap::Decoder::new(reader, None).map_err(wrap)?),
        other => {
            return Err(Error::format(
                path,
                format!(
                "unknown event file type '.{other}' (expected .aedat4, .raw, .csv, .npz, .h5, .hdf5, .mcap or .txt)"
            ),
            ))
        }
    };
    Ok(Box::new(FileDecoder {
        path: path.to_path_buf(),
        inner,
        check_times,
    }))
}

/// An encoder of a file: its errors name the file, it refuses events out of order or off the
/// sensor (taking those before), and when a write fails it closes the file readably with
/// what reached it ([`EventEncoder::salvage`], or cut after its last whole unit).
struct FileEncoder {
    path: PathBuf,
    /// `None` once a write failed.
    inner: Option<Box<dyn EventEncoder + Send>>,
    seal: Seal,
    size: (u16, u16),
    last_t: i64,
    kept: Option<u64>,
}

impl FileEncoder {
    fn inner(&mut self) -> Result<&mut Box<dyn EventEncoder + Send>> {
        let path = &self.path;
        self.inner
            .as_mut()
            .ok_or_else(|| Error::format(path, "an earlier write failed"))
    }

    /// `e` from the encoder: closes the file with what reached it, and says so.
    fn failed(&mut self, e: Error) -> Error {
        let Some(mut inner) = self.inner.take() else {
            return e;
        };
        // No more writes through the encoder's buffer, positioned past the cut.
        self.seal.seal();
        let kept = match inner.salvage() {
            Ok(Some(n)) => Ok(n),
            Ok(None) => {
                drop(inner);
                cut::cut_in_place(&self.path)
            }
            Err(why) => Err(why),
        };
        let e = e.to_string();
        let e = e
            .strip_prefix(&format!("{}: ", self.path.display()))
            .unwrap_or(&e);
        match kept {
            Ok(n) => {
                self.kept = Some(n);
                Error::format(
                    &self.path,
                    format!(
                        "{e}; {} was closed readably with the {n} events that reached it",
                        self.path.display()
                    ),
                )
            }
            Err(why) => Error::format(
                &self.path,
                format!("{e}; and it could not be closed readably ({why})"),
            ),
        }
    }
}

impl EventEncoder for FileEncoder {
    fn write(&mut self, events: &[Event]) -> Result<()> {
        let (w, h) = self.size;
        let mut valid = events.len();
        let mut refused = Ok(());
        for (i, e) in events.iter().enumerate() {
            if let Err(why) = check_event(e, self.last_t, w, h) {
                refused = Err(Error::format(&self.path, why.to_string()));
                valid = i;
                break;
            }
            self.last_t = e.t;
        }
        let written = self.inner()?.write(&events[..valid]);
        written.map_err(|e| self.failed(e))?;
        refused
    }

    fn finish(&mut self) -> Result<()> {
        let finished = self.inner()?.finish();
        finished.map_err(|e| self.failed(e))
    }

    fn flush(&mut self) -> Result<()> {
        let flushed = self.inner()?.flush();
        flushed.map_err(|e| self.failed(e))
    }

    fn readable_after_flush(&self) -> bool {
        self.inner
            .as_ref()
            .is_none_or(|inner| inner.readable_after_flush())
    }

    /// Closes the file with what reached it (see [`EventEncoder::salvage`]), once.
    fn salvage(&mut self) -> Result<Option<u64>> {
        if self.inner.is_some() {
            let _ = self.failed(Error::Run("closed after a failed write".into()));
        }
        Ok(self.kept)
    }

    fn kept(&self) -> Option<u64> {
        self.kept
    }
}

/// Creates an event file of `format` for a `width x height` sensor.
pub fn create(
    path: &Path,
    format: Format,
    width: u16,
    height: u16,
) -> Result<Box<dyn EventEncoder + Send>> {
    let seal = Seal::default();
    let buffered = || -> Result<BufWriter<SealableFile>> {
        let file = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
        let file = SealableFile {
            file,
            sealed: seal.clone(),
        };
        Ok(BufWriter::with_capacity(1 << 16, file))
    };
    let wrap = |e: Error| Error::format(path, e.to_string());
    let inner: Box<dyn EventEncoder + Send> = match format {
        Format::Aedat4(c) => {
            Box::new(aedat4::Writer::new(buffered()?, width, height, c).map_err(wrap)?)
        }
        Format::Evt2 => Box::new(evt2::Encoder::new(buffered()?, width, height).map_err(wrap)?),
        Format::Evt3 => Box::new(evt3::Encoder::new(buffered()?, width, height).map_err(wrap)?),
        Format::Csv => Box::new(csv::Encoder::new(buffered()?).map_err(wrap)?),
        Format::Npz => Box::new(npz::Encoder::new(path, width, height).map_err(wrap)?),
        // The HDF5 library creates the file itself.
        Format::Hdf5 => Box::new(hdf5::Encoder::create(path, width, height).map_err(wrap)?),
        Format::Mcap => Box::new(mcap::Encoder::new(buffered()?, width, height).map_err(wrap)?),
    };
    Ok(Box::new(FileEncoder {
        path: path.to_path_buf(),
        inner: Some(inner),
        seal,
        size: (width, height),
        last_t: i64::MIN,
        kept: None,
    }))
}

/// The file an encoder writes through: its owner can [`Seal`] it, after which every write and
/// seek fails. A file cut back after a failed write (a full disk) is sealed first, so the
/// encoder's buffered writer, whose position lies past the cut, can never write there later
/// (its flush on drop would leave a hole of zero bytes that readers take for events).
struct SealableFile {
    file: std::fs::File,
    sealed: Seal,
}

/// Seals a [`SealableFile`] (shared with it).
#[derive(Debug, Clone, Default)]
struct Seal(std::sync::Arc<std::sync::atomic::AtomicBool>);

impl Seal {
    /// From now on the file takes no write and no seek.
    pub fn seal(&self) {
        self.0.store(true, std::sync::atomic::Ordering::SeqCst);
    }

    fn check(&self) -> std::io::Result<()> {
        if self.0.load(std::sync::atomic::Ordering::SeqCst) {
            return Err(std::io::Error::other(
                "the file was closed after a failed write",
            ));
        }
        Ok(())
    }
}

impl std::io::Write for SealableFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.sealed.check()?;
        self.file.write(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.sealed.check()?;
        self.file.flush()
    }
}

impl std::io::Seek for SealableFile {
    fn seek(&mut self, pos: std::io::SeekFrom) -> std::io::Result<u64> {
        self.sealed.check()?;
        self.file.seek(pos)
    }
}

/// An output written under a temporary name (`out.csv` is written as `out.partial.csv`, so
/// readers still know its format) and given its own name only when complete, so a file under
/// the name asked for is always whole: a failed or interrupted command leaves the partial file
/// (readable up to where it stopped) and says so.
#[derive(Debug, Clone)]
pub struct PartialOutput {
    path: PathBuf,
    partial: PathBuf,
}

impl PartialOutput {
    /// The output `path`, written as `STEM.partial.EXT` beside it until
    /// [`PartialOutput::commit`].
    pub fn new(path: &Path) -> Self {
        let mut name = path.file_stem().unwrap_or_default().to_owned();
        name.push(".partial");
        if let Some(ext) = path.extension() {
            name.push(".");
            name.push(ext);
        }
        PartialOutput {
            path: path.to_path_buf(),
            partial: path.with_file_name(name),
        }
    }

    /// Where to write until the output is complete.
    pub fn writing(&self) -> &Path {
        &self.partial
    }

    /// Gives the complete output its name.
    pub fn commit(&self) -> Result<()> {
        std::fs::rename(&self.partial, &self.path).map_err(|e| Error::io(&self.path, e))
    }

    /// `e`, saying where what was written before it is (when anything was).
    pub fn explain(&self, e: Error) -> Error {
        if !self.partial.exists() {
            return e;
        }
        let mut kept = format!(
            "{} was not written; what was written before this is in {}",
            self.path.display(),
            self.partial.display()
        );
        // `.npz` and `.h5` are whole only at their end: their journals hold what they took.
        if journal::path_for(&self.partial).exists() {
            kept.push_str(&format!(
                " (`v2ce repair {}` makes it readable)",
                self.partial.display()
            ));
        }
        match e {
            Error::Interrupted(why) => Error::Interrupted(format!("{why}; {kept}")),
            e => Error::Run(format!("{e}; {kept}")),
        }
    }
}

/// Events read from a file, with the sensor size.
#[derive(Debug, Clone)]
pub struct Recording {
    /// Sensor width (from the file, or one more than the largest column when the format has none).
    pub width: u16,
    /// Sensor height (likewise).
    pub height: u16,
    /// The events, sorted by time.
    pub events: EventPacket,
}

impl Recording {
    /// Builds a recording, sorting events by time if the file did not (stable, so ties keep
    /// the file's order) and inferring the sensor size from the events when `size` is `None`.
    pub fn new(events: Vec<Event>, size: Option<(u16, u16)>) -> Self {
        let events = EventPacket::from_time_sorted(events).unwrap_or_else(|mut events| {
            events.sort_by_key(|e| e.t);
            EventPacket::from_time_sorted(events).unwrap_or_default()
        });
        let (width, height) = size.unwrap_or_else(|| {
            let w = events.events().iter().map(|e| e.x).max().unwrap_or(0);
            let h = events.events().iter().map(|e| e.y).max().unwrap_or(0);
            (w.saturating_add(1), h.saturating_add(1))
        });
        Recording {
            width,
            height,
            events,
        }
    }
}

fn extension(path: &Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase()
}

/// Reads all the events of a file [`open`] accepts.
pub fn read_events(path: &Path) -> Result<Recording> {
    let mut decoder = open(path)?;
    let mut events = Vec::new();
    loop {
        // Memory for what the file holds (or claims: a header's count of events never
        // written) is checked as it grows: a clear error, not an abort.
        let grow = events.len().max(1 << 16);
        if events.capacity() - events.len() < 1 << 16 && !crate::limits::room_for(&mut events, grow)
        {
            return Err(Error::format(
                path,
                format!(
                    "its events need more memory than this machine has left ({} read so far); \
                     commands that stream (transcode, info) read it a piece at a time",
                    events.len()
                ),
            ));
        }
        if decoder.read_events(&mut events, 1 << 16)? == 0 {
            break;
        }
    }
    Ok(Recording::new(events, decoder.size()))
}

/// Reads frame times (us, increasing) from an `.aedat4` with APS frames or an IJRR `images.txt`.
pub fn read_frame_times(path: &Path) -> Result<Vec<i64>> {
    let times = match extension(path).as_str() {
        "aedat4" => aedat4::read(path)?.1,
        "txt" => ijrr::read_frame_times(path)?,
        other => {
            return Err(Error::format(
                path,
                format!("unknown frame-time file type '.{other}' (expected .aedat4 or .txt)"),
            ))
        }
    };
    require_frames(path, times)
}

/// Checks that `times`, read from `path`, hold at least two frames (one interval), each in
/// the range times may take ([`crate::time`]).
pub fn require_frames(path: &Path, times: Vec<i64>) -> Result<Vec<i64>> {
    if let Some(&t) = times.iter().find(|&&t| !crate::time::in_range(t)) {
        let e = crate::time::check("frame time", t).err();
        return Err(Error::format(
            path,
            e.map_or_else(String::new, |e| e.to_string()),
        ));
    }
    if times.len() < 2 {
        return Err(Error::format(
            path,
            format!(
                "{} frame time(s); need at least 2 to make an interval",
                times.len()
            ),
        ));
    }
    Ok(times)
}
