//! Frames to events: a frame source through Stage 1 (and, in voxel mode, Stage 2) into sinks.
//!
//! Memory stays at one frame and one interval's events, whatever the video's length.

use std::time::Instant;

use crate::config::Config;
use crate::error::Result;
use crate::event::Event;
use crate::frame::FrameSource;
use crate::interval::Interval;
use crate::sink::Sink;
use crate::stage1::{PhysicsSim, PhysicsStats, Stage1Output};
use crate::voxel::{VoxelGrid, Voxelizer};

/// What a conversion did.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct ConvertReport {
    /// Frames read.
    pub frames: u64,
    /// Events handed to the sinks.
    pub events: u64,
    /// Time of the first and last frame, us.
    pub first_t: Option<i64>,
    /// Time of the last frame.
    pub last_t: Option<i64>,
    /// Wall time, seconds.
    pub seconds: f64,
    /// The pixel model's counters.
    pub physics: PhysicsStats,
}

/// Runs `source` through the configured pipeline into every sink, calling `progress` after each
/// frame with the report so far. The sinks are finished at the end.
pub fn convert(
    source: &mut dyn FrameSource,
    config: &Config,
    sinks: &mut [Box<dyn Sink>],
    mut progress: impl FnMut(&ConvertReport),
) -> Result<ConvertReport> {
    let started = Instant::now();
    let (w, h) = source.size();
    let mut sim = PhysicsSim::new(config.stage1.physics_config(), w, h, config.stage1.seed)?;
    let voxel_mode = config.stage1.output == Stage1Output::Voxels;
    let bins = config.stage2.bins;
    let mut voxelizer = Voxelizer::new(w, h, bins)?;
    let mut grid = VoxelGrid::new(w, h, bins)?;
    let sampler = config.stage2.sampler.build(config.stage2.seed);
    let mut report = ConvertReport::default();
    let mut events: Vec<Event> = Vec::new();
    let mut sampled: Vec<Event> = Vec::new();
    while let Some(frame) = source.next_frame()? {
        events.clear();
        let previous = report.last_t;
        sim.step(&frame, &mut events)?;
        report.frames += 1;
        report.first_t.get_or_insert(frame.t);
        report.last_t = Some(frame.t);
        let batch = match (voxel_mode, previous) {
            (true, Some(t0)) => {
                // Events of (t0, t1] voxelized on [t0, t1): one at t1 lands on the last node.
                let interval = Interval::new(t0, frame.t)?;
                voxelizer.voxelize_into(&events, interval, &mut grid)?;
                sampled.clear();
                sampler.sample(&grid, interval, &mut sampled);
                &sampled
            }
            _ => &events,
        };
        if !batch.is_empty() {
            for sink in sinks.iter_mut() {
                sink.send(batch)?;
            }
        }
        report.events += batch.len() as u64;
        report.physics = sim.stats();
        report.seconds = started.elapsed().as_secs_f64();
        progress(&report);
    }
    for sink in sinks.iter_mut() {
        sink.finish()?;
    }
    report.seconds = started.elapsed().as_secs_f64();
    report.physics = sim.stats();
    Ok(report)
}
