//! An event file as a sink: any format of [`crate::format`], picked by extension.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use super::{Sink, SinkContext, SinkStats};
use crate::error::{Error, Result};
use crate::event::Event;
use crate::file_id::FileId;
use crate::format::{self, EventEncoder, Format};

/// A `[[sink]]` table of `type = "file"` (the default has no path: an output that is off).
#[derive(Debug, Clone, Default, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileSinkConfig {
    /// The file; its extension picks the format (`.aedat4` with LZ4 packets, `.raw`, `.csv`,
    /// `.npz`, `.h5`).
    pub path: String,
    /// The EVT version of a `.raw` file: 2 (the default) or 3.
    #[serde(default)]
    pub evt: Option<u8>,
}

/// Refuses two file outputs on one file (the same path, spelled differently or through a
/// link): each would report every event written while the file held a mix of both.
pub fn distinct_paths(files: &[&FileSinkConfig]) -> Result<()> {
    let mut seen: Vec<(FileId, &str)> = Vec::new();
    for f in files {
        let id = FileId::of(Path::new(&f.path));
        if let Some((_, first)) = seen.iter().find(|(other, _)| other.same(&id)) {
            return Err(Error::invalid(
                "outputs",
                format!(
                    "two file outputs write {} ('{first}' and '{}'): give each its own file",
                    id.path().display(),
                    f.path
                ),
            ));
        }
        seen.push((id, &f.path));
    }
    Ok(())
}

/// Refuses a file output that is the file the source reads (`source`, where it names a
/// file): it would be truncated before it is read.
pub fn not_the_source(files: &[&FileSinkConfig], source: &Path) -> Result<()> {
    if !source.is_file() {
        return Ok(());
    }
    let source_id = FileId::of(source);
    match files
        .iter()
        .find(|f| FileId::of(Path::new(&f.path)).same(&source_id))
    {
        Some(f) => Err(Error::invalid(
            "outputs",
            format!(
                "the file output '{}' is the source {} (the same file): it would be truncated \
                 before it is read; write to another file",
                f.path,
                source.display()
            ),
        )),
        None => Ok(()),
    }
}

impl FileSinkConfig {
    /// A file sink writing `path`.
    pub fn new(path: &str) -> Self {
        FileSinkConfig {
            path: path.to_string(),
            evt: None,
        }
    }

    fn format(&self) -> Result<Format> {
        Format::for_output(Path::new(&self.path), self.evt, format::Compression::Lz4)
    }

    /// Checks the path and format.
    pub fn validate(&self) -> Result<()> {
        if self.path.is_empty() {
            return Err(Error::invalid("file sink", "path is empty".to_string()));
        }
        self.format().map(|_| ())
    }

    /// Creates the file.
    pub fn build(&self, context: &SinkContext) -> Result<Box<dyn Sink>> {
        let path = Path::new(&self.path);
        let sink = FileSink::create(path, self.format()?, context.width, context.height)?;
        Ok(Box::new(sink.with_flush_period(FLUSH_PERIOD)))
    }
}

/// How often the daemon's file outputs hand what they hold to the operating system and ask it to
/// put it on the disk (`fdatasync`): a daemon killed (SIGKILL) or a machine that lost power loses
/// at most about this much of its events, and what it wrote before is whole packets that readers
/// take (AEDAT 4.0 events held for a packet go out as a shorter one).
pub const FLUSH_PERIOD: Duration = Duration::from_secs(1);

/// Writes events to a file.
pub struct FileSink {
    path: PathBuf,
    format: Format,
    encoder: Box<dyn EventEncoder + Send>,
    stats: SinkStats,
    /// Flush at most this long after the last flush (the daemon's outputs; `convert` writes
    /// whole packets only, so its files do not depend on timing).
    flush_every: Option<Duration>,
    /// `None` until the first flush, which comes with the first events (so a file killed
    /// after its first batch already has its header and that batch on disk).
    last_flush: Option<Instant>,
    /// Whether to sync what the encoder wrote (periodic flushes only), through a handle opened
    /// for it each time: one held open would keep a file the encoder replaces after a failed
    /// write (HDF5) from freeing its room.
    sync: bool,
    /// Events the encoder took since the last flush: counted as sent only once a flush (or the
    /// end) has put them in the file, so a full disk cannot have them reported sent.
    pending: u64,
    /// A write failed (a full disk, `ulimit -f`): the encoder closed the file with what
    /// reached it ([`EventEncoder::salvage`]), which is what counts as sent, and is not used
    /// again.
    failed: bool,
}

impl FileSink {
    /// Creates `path` in `format` for a `width x height` sensor.
    pub fn create(path: &Path, format: Format, width: u16, height: u16) -> Result<Self> {
        let encoder = format::create(path, format, width, height)?;
        Ok(FileSink {
            path: path.to_path_buf(),
            format,
            encoder,
            stats: SinkStats::default(),
            flush_every: None,
            last_flush: None,
            sync: false,
            pending: 0,
            failed: false,
        })
    }

    /// Flushes (see [`EventEncoder::flush`]) with the first events, then whenever events arrive
    /// `period` or more after the last flush.
    pub fn with_flush_period(mut self, period: Duration) -> Self {
        self.flush_every = Some(period);
        // Syncing through any descriptor of the file puts its data on the disk.
        self.sync = true;
        self
    }

    /// Flushes the encoder, then has the data (and, the first time, the file's directory
    /// entry) put on the disk, so a power loss keeps what was flushed.
    /// Hands what the encoder holds to the file; the events it took count as sent where the
    /// file now holds them readably (not `.npz` or `.h5`, whole only at the end).
    fn flush_into_file(&mut self) -> Result<()> {
        self.encoder.flush()?;
        if self.encoder.readable_after_flush() {
            // In the file (the kernel has it: a killed process loses none of it).
            self.stats.events_sent += std::mem::take(&mut self.pending);
        }
        Ok(())
    }

    /// After a failed write: the file closed with what reached it (see
    /// [`EventEncoder::salvage`]), which is then what counts as sent.
    fn cut_back(&mut self) {
        match self.encoder.salvage() {
            Ok(Some(kept)) => self.stats.events_sent = kept,
            Ok(None) | Err(_) => tracing::warn!(
                "{}: could not be closed readably after the failed write",
                self.path.display()
            ),
        }
    }

    /// `e`, saying how to read what a file whole only at its end (`.npz`, `.h5`) took.
    fn explain(&self, e: Error) -> Error {
        let journal = crate::format::journal::path_for(&self.path);
        if self.encoder.readable_after_flush() || !journal.exists() {
            return e;
        }
        Error::Run(format!(
            "{e}; `v2ce repair {}` writes the file from its journal {}",
            self.path.display(),
            journal.display()
        ))
    }

    fn flush_to_disk(&mut self) -> Result<()> {
        self.flush_into_file()?;
        if self.sync {
            self.sync_data()?;
            if self.last_flush.is_none() {
                let dir = match self.path.parent() {
                    Some(p) if !p.as_os_str().is_empty() => p,
                    _ => Path::new("."),
                };
                // A directory that cannot be opened to sync (some filesystems) is not fatal.
                if let Ok(d) = std::fs::File::open(dir) {
                    let _ = d.sync_all();
                }
            }
        }
        Ok(())
    }
}

impl FileSink {
    /// Puts what the file holds on the disk.
    fn sync_data(&self) -> Result<()> {
        std::fs::File::open(&self.path)
            .and_then(|f| f.sync_data())
            .map_err(|e| Error::io(&self.path, e))
    }
}

impl Sink for FileSink {
    fn is_recording(&self) -> bool {
        true
    }

    fn describe(&self) -> String {
        format!("file {} ({})", self.path.display(), self.format.name())
    }

    fn send(&mut self, events: &[Event]) -> Result<()> {
        if self.failed {
            return Err(Error::Run(format!(
                "{}: an earlier write failed",
                self.path.display()
            )));
        }
        let sent = self.send_and_flush(events);
        if sent.is_err() {
            self.failed = true;
            self.cut_back();
        }
        sent.map_err(|e| self.explain(e))
    }

    fn finish(&mut self) -> Result<()> {
        if self.failed {
            // Reported when the write failed; the file holds what was counted as sent.
            return Ok(());
        }
        let finished = self.finish_file();
        if finished.is_err() {
            self.failed = true;
            self.cut_back();
        }
        finished.map_err(|e| self.explain(e))
    }

    fn stats(&self) -> SinkStats {
        self.stats
    }
}

impl FileSink {
    fn send_and_flush(&mut self, events: &[Event]) -> Result<()> {
        self.stats.events_in += events.len() as u64;
        self.encoder.write(events)?;
        self.pending += events.len() as u64;
        self.stats.messages_sent += 1;
        if let Some(period) = self.flush_every {
            if self.last_flush.is_none_or(|at| at.elapsed() >= period) {
                self.flush_to_disk()?;
                self.last_flush = Some(Instant::now());
            } else {
                // Each batch into the file (one write a frame): what counts as sent is what
                // the file holds, also when the disk fills.
                self.flush_into_file()?;
            }
        }
        Ok(())
    }

    fn finish_file(&mut self) -> Result<()> {
        self.encoder.finish()?;
        self.stats.events_sent += std::mem::take(&mut self.pending);
        if self.sync {
            self.sync_data()?;
        }
        self.stats.bytes_sent = std::fs::metadata(&self.path).map_or(0, |m| m.len());
        Ok(())
    }
}
