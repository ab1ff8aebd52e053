//! An event file as a sink: any format of [`crate::format`], picked by extension.

use std::path::{Path, PathBuf};

use super::{Sink, SinkStats};
use crate::error::Result;
use crate::event::Event;
use crate::format::{self, EventEncoder, Format};

/// Writes events to a file.
pub struct FileSink {
    path: PathBuf,
    format: Format,
    encoder: Box<dyn EventEncoder + Send>,
    stats: SinkStats,
}

impl FileSink {
    /// Creates `path` in `format` for a `width x height` sensor.
    pub fn create(path: &Path, format: Format, width: u16, height: u16) -> Result<Self> {
        Ok(FileSink {
            path: path.to_path_buf(),
            format,
            encoder: format::create(path, format, width, height)?,
            stats: SinkStats::default(),
        })
    }
}

impl Sink for FileSink {
    fn describe(&self) -> String {
        format!("file {} ({})", self.path.display(), self.format.name())
    }

    fn send(&mut self, events: &[Event]) -> Result<()> {
        self.stats.events_in += events.len() as u64;
        self.encoder.write(events)?;
        self.stats.events_sent += events.len() as u64;
        self.stats.messages_sent += 1;
        Ok(())
    }

    fn finish(&mut self) -> Result<()> {
        self.encoder.finish()?;
        self.stats.bytes_sent = std::fs::metadata(&self.path).map_or(0, |m| m.len());
        Ok(())
    }

    fn stats(&self) -> SinkStats {
        self.stats
    }
}
