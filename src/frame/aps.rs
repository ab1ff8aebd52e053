//! The APS frames of an AEDAT 4.0 recording (DAVIS cameras) as a frame source.
//!
//! APS values are raw, linear ADC readings, so they are scaled to 16 bits without a transfer
//! function; the frame's time is the middle of its exposure.

use std::io::BufReader;
use std::path::{Path, PathBuf};

use super::{check_order, Frame, FrameSource};
use crate::error::{Error, Result};
use crate::format::aedat4::{Item, Reader};

/// Reads APS frames from an `.aedat4` file.
pub struct ApsSource {
    path: PathBuf,
    reader: Reader<BufReader<std::fs::File>>,
    size: (u16, u16),
    last_t: Option<i64>,
    index: usize,
}

impl ApsSource {
    /// Opens `path`; it must list a frame stream.
    pub fn open(path: &Path) -> Result<Self> {
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let reader = Reader::new_file(BufReader::new(file))
            .map_err(|e| Error::format(path, e.to_string()))?;
        let size = reader
            .header()
            .streams
            .iter()
            .find(|s| s.type_identifier == "FRME")
            .and_then(|s| s.size)
            .ok_or_else(|| Error::format(path, "no APS frame stream with a size"))?;
        Ok(ApsSource {
            path: path.to_path_buf(),
            reader,
            size,
            last_t: None,
            index: 0,
        })
    }
}

impl FrameSource for ApsSource {
    fn size(&self) -> (u16, u16) {
        self.size
    }

    fn next_frame(&mut self) -> Result<Option<Frame>> {
        loop {
            let item = self
                .reader
                .next_item()
                .map_err(|e| Error::format(&self.path, e.to_string()))?;
            let f = match item {
                None => return Ok(None),
                Some(Item::Frame(f)) => f,
                Some(_) => continue,
            };
            if f.size != self.size {
                return Err(Error::format(
                    &self.path,
                    format!(
                        "frame {} is {} x {}, the stream says {} x {}",
                        self.index, f.size.0, f.size.1, self.size.0, self.size.1
                    ),
                ));
            }
            check_order(&self.path, self.last_t, f.t, self.index)?;
            self.last_t = Some(f.t);
            self.index += 1;
            let luma = match f.channels {
                1 => f.pixels.iter().map(|&v| v as u16 * 257).collect(),
                c => f
                    .pixels
                    .chunks_exact(c as usize)
                    .map(|p| {
                        // BGR(A), linear values.
                        let y = 0.0722 * p[0] as f32 + 0.7152 * p[1] as f32 + 0.2126 * p[2] as f32;
                        (y * 257.0).round().min(65535.0) as u16
                    })
                    .collect(),
            };
            return Ok(Some(Frame {
                t: f.t,
                width: self.size.0,
                height: self.size.1,
                luma,
                exposure_us: exposure_of(f.exposure),
            }));
        }
    }

    fn describe(&self) -> String {
        format!("APS frames of {}", self.path.display())
    }

    fn encoding(&self) -> super::SourceEncoding {
        super::SourceEncoding::Linear
    }
}

/// The exposure of a frame with exposure start and end `(b, e)` in us, when both are given and
/// the span is positive and fits in 32 bits.
fn exposure_of((b, e): (i64, i64)) -> Option<u32> {
    if b > 0 && e > b {
        u32::try_from(e - b).ok()
    } else {
        None
    }
}
