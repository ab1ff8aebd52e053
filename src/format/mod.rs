//! Event and frame-time files: one module per format, picked by file extension.
//!
//! | extension | module | events | frame times |
//! |---|---|---|---|
//! | `.aedat4` | [`aedat4`] | yes | the APS frames' mid-exposure times |
//! | `.txt` | [`ijrr`] | `events.txt` (`t_seconds x y polarity`) | `images.txt` (`t_seconds path`) |
//! | `.csv` | [`csv`] | `t_us,x,y,on` | - |

pub mod aedat4;
pub mod csv;
pub mod evt2;
pub mod ijrr;

use std::path::Path;

use crate::error::{Error, Result};
use crate::event::{Event, EventPacket};

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

/// Reads the events of an `.aedat4`, IJRR `events.txt` or `.csv` file.
pub fn read_events(path: &Path) -> Result<Recording> {
    match extension(path).as_str() {
        "aedat4" => aedat4::read(path).map(|(rec, _)| rec),
        "txt" => ijrr::read_events(path),
        "csv" => csv::read(path),
        other => Err(Error::format(
            path,
            format!("unknown event file type '.{other}' (expected .aedat4, .txt or .csv)"),
        )),
    }
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

/// Checks that `times`, read from `path`, hold at least two frames (one interval).
pub fn require_frames(path: &Path, times: Vec<i64>) -> Result<Vec<i64>> {
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
