//! Frames to events, offline: a frame source through the [`pipeline`](crate::pipeline) with
//! every queue blocking (nothing is ever dropped), as fast as the stages go.
//!
//! Memory stays at a few frames and their events, whatever the video's length.

use std::sync::atomic::AtomicBool;
use std::time::Duration;

use crate::config::Config;
use crate::error::{Error, Result};
use crate::frame::FrameSource;
use crate::pipeline::queue::QueuePolicy;
use crate::pipeline::{self, Options, Source};
use crate::sink::Sink;
use crate::stage1::PhysicsStats;

/// What a conversion did.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct ConvertReport {
    /// Frames read.
    pub frames: u64,
    /// Events handed to the sinks.
    pub events: u64,
    /// Time of the first frame, us.
    pub first_t: Option<i64>,
    /// Time of the last frame.
    pub last_t: Option<i64>,
    /// Wall time, seconds.
    pub seconds: f64,
    /// The pixel model's counters.
    pub physics: PhysicsStats,
}

/// Runs `source` through the configured stages into every sink, calling `progress` a few times
/// a second with the report so far. The sinks are finished at the end. `stop` (e.g. set on
/// SIGINT) ends the conversion early, with everything read so far written; `max_frames`
/// limits the frames read.
pub fn convert(
    source: Box<dyn FrameSource>,
    config: &Config,
    sinks: Vec<Box<dyn Sink>>,
    max_frames: Option<u64>,
    stop: &AtomicBool,
    mut progress: impl FnMut(&ConvertReport),
) -> Result<ConvertReport> {
    let options = Options {
        policy: QueuePolicy::Block,
        capacity: 4,
        max_frames,
        duration: None,
        tick: Duration::from_millis(250),
    };
    let mut on_tick = |s: &pipeline::stats::Snapshot| {
        progress(&ConvertReport {
            frames: s.frames_in,
            events: s.events_out,
            seconds: s.uptime_s,
            ..ConvertReport::default()
        })
    };
    let report = pipeline::run(
        Source::file(source),
        config,
        sinks,
        &options,
        stop,
        &mut on_tick,
    )?;
    if !report.end.is_clean() {
        return Err(Error::Run(report.end.describe()));
    }
    if let Some(failed) = report.stats.sinks.iter().find_map(|s| s.failed.clone()) {
        return Err(Error::Run(failed));
    }
    Ok(ConvertReport {
        frames: report.stats.frames_in,
        events: report.stats.events_out,
        first_t: report.first_t,
        last_t: report.last_t,
        seconds: report.stats.uptime_s,
        physics: report.physics,
    })
}
