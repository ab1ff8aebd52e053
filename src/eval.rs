//! Evaluation runs: score a sampler (Stage 2) on a real or synthetic recording.

use std::time::Instant;

use crate::error::Result;
use crate::event::Event;
use crate::format::Recording;
use crate::interval::Interval;
use crate::metrics::{Stage2Metrics, Stage2Scorer};
use crate::stage2::{SampleStats, Sampler};
use crate::voxel::{VoxelGrid, Voxelizer};

/// The median of timings, as the reports give it (kept here under its old path).
pub use crate::stats::median;

/// What a Stage 2 evaluation measured.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Stage2Report {
    /// The sampler's name.
    pub sampler: String,
    /// The timestamp metrics.
    #[serde(flatten)]
    pub metrics: Stage2Metrics,
    /// Values the sampler had to repair (always zero for voxels of real events).
    pub repaired: SampleStats,
    /// Median wall time to voxelize one interval, us.
    pub voxelize_us_median: f64,
    /// Median wall time to sample one interval, us.
    pub sample_us_median: f64,
}

/// Voxelizes the events of each interval with `bins` nodes, re-samples them with `sampler`,
/// scores the result against the original events, and hands each interval's sampled events
/// (sorted) to `on_events`.
pub fn stage2(
    recording: &Recording,
    intervals: &[Interval],
    bins: usize,
    sampler: &dyn Sampler,
    mut on_events: impl FnMut(&[Event]) -> Result<()>,
) -> Result<Stage2Report> {
    let mut voxelizer = Voxelizer::new(recording.width, recording.height, bins)?;
    let mut grid = VoxelGrid::new(recording.width, recording.height, bins)?;
    let mut scorer = Stage2Scorer::new();
    let mut repaired = SampleStats::default();
    let mut out = Vec::new();
    let (mut vox_us, mut smp_us) = (Vec::new(), Vec::new());
    for &interval in intervals {
        let truth = recording
            .events
            .time_slice(interval.start(), interval.end());
        let t0 = Instant::now();
        voxelizer.voxelize_into(truth, interval, &mut grid)?;
        let t1 = Instant::now();
        out.clear();
        repaired.add(sampler.sample(&grid, interval, &mut out));
        let t2 = Instant::now();
        vox_us.push((t1 - t0).as_secs_f64() * 1e6);
        smp_us.push((t2 - t1).as_secs_f64() * 1e6);
        scorer.add_interval(interval, truth, &out);
        on_events(&out)?;
    }
    Ok(Stage2Report {
        sampler: sampler.name().to_string(),
        metrics: scorer.finish(),
        repaired,
        voxelize_us_median: median(&mut vox_us),
        sample_us_median: median(&mut smp_us),
    })
}
