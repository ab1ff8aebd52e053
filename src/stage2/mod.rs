//! Stage 2: turning event voxels into events with continuous timestamps.
//!
//! Every sampler works on one active voxel cell at a time (a pixel and polarity with its `C`
//! node values) and places events at *node positions* `tau` in `[0, C - 1]`; the shared driver
//! ([`Sampler::sample`]) sanitises the cell, seeds a generator for it, converts positions into
//! microsecond timestamps inside the frame interval and sorts the result. Cost is proportional
//! to the number of active cells plus events emitted.
//!
//! Samplers (see [`SamplerKind`]):
//! - `even`, `random`: the V2CE baselines (10 half-open bins per interval, floor + Bernoulli);
//! - `ldati-random`: chain decoupling, Type 2 events uniform in their sub-interval;
//! - `ldati`: chain decoupling, Type 2 events from the local linear (slope) density (the paper);
//! - `moment`: the project's refinement of LDATI that also uses the first moment the voxel
//!   carries for each sub-interval (see [`moment`]);
//! - `spatial`: `moment`'s counts and means, its events spaced at the pace the pixel's
//!   neighbours in time and space show (see [`spatial`]); the default, because it measures
//!   better.

pub mod baseline;
pub mod chain;
pub mod ldati;
pub mod moment;
pub mod spatial;

use rand::SeedableRng;
use rand_xoshiro::Xoshiro256PlusPlus;

use crate::error::{Error, Result};
use crate::event::{sort_events, Event};
use crate::interval::Interval;
use crate::seed::splitmix;
use crate::voxel::VoxelGrid;

/// The random generator handed to a sampler for one cell.
pub type CellRng = Xoshiro256PlusPlus;

/// Node values above this are clamped (and counted): a model that predicts more than a million
/// events for one pixel node is broken, and honouring it could exhaust memory.
pub const MAX_NODE_VALUE: f64 = 1e6;

/// What a sampler had to repair in its input voxels; all zero for voxels made by `voxelize`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct SampleStats {
    /// NaN or infinite node values, treated as 0.
    pub nonfinite: u64,
    /// Negative node values, treated as 0.
    pub negative: u64,
    /// Node values above [`MAX_NODE_VALUE`], clamped to it.
    pub clamped: u64,
}

impl SampleStats {
    /// Adds `other` into `self`.
    pub fn add(&mut self, other: SampleStats) {
        self.nonfinite += other.nonfinite;
        self.negative += other.negative;
        self.clamped += other.clamped;
    }

    /// Whether any value had to be repaired.
    pub fn any(&self) -> bool {
        self.nonfinite + self.negative + self.clamped > 0
    }
}

/// Turns voxel cells into event positions.
pub trait Sampler: Send + Sync {
    /// The sampler's name as the CLI spells it.
    fn name(&self) -> &'static str;

    /// The seed from which every cell's generator is derived.
    fn seed(&self) -> u64;

    /// Appends to `out` the positions of the events of one cell, in node units: `tau` in
    /// `[0, C - 1]` where node `c` sits at `tau = c`. `nodes` holds `C >= 2` finite values in
    /// `[0, MAX_NODE_VALUE]`.
    /// `scratch` is reusable working memory with no meaning between calls.
    fn sample_cell(
        &self,
        nodes: &[f64],
        rng: &mut CellRng,
        scratch: &mut Scratch,
        out: &mut Vec<f64>,
    );

    /// Samples every cell of `voxels` into events inside `interval`, appended to `out` in the
    /// project's event order (time, then row, column, polarity).
    ///
    /// Timestamps are `start + round(tau * duration / (C - 1))`, clamped into the interval.
    /// Identical inputs and seed give identical output, whatever the order of the cells.
    fn sample(&self, voxels: &VoxelGrid, interval: Interval, out: &mut Vec<Event>) -> SampleStats {
        let mut stats = SampleStats::default();
        let bins = voxels.bins();
        let scale = interval.duration_us() as f64 / (bins - 1) as f64;
        let first = out.len();
        let mut nodes = vec![0.0; bins];
        let mut taus = Vec::new();
        let mut scratch = Scratch::default();
        for cell in voxels.cells() {
            stats.add(sanitize(cell.values, &mut nodes));
            let mut rng = cell_rng(
                self.seed(),
                interval.start(),
                cell.x,
                cell.y,
                cell.on,
                voxels.width(),
            );
            taus.clear();
            self.sample_cell(&nodes, &mut rng, &mut scratch, &mut taus);
            push_events(&taus, (cell.x, cell.y, cell.on), interval, scale, out);
        }
        sort_events(&mut out[first..]);
        stats
    }
}

/// Appends the events of the cell at `(x, y, on)` at node positions `taus` (`scale` us per
/// node): [`Sampler::sample`]'s timestamps.
fn push_events(
    taus: &[f64],
    (x, y, on): (u16, u16, bool),
    interval: Interval,
    scale: f64,
    out: &mut Vec<Event>,
) {
    out.extend(taus.iter().map(|&tau| Event {
        t: interval.timestamp_at(tau * scale),
        x,
        y,
        on,
    }));
}

/// Working memory reused across cells, so sampling a cell allocates nothing in the common case.
#[derive(Debug, Clone, Default)]
pub struct Scratch {
    /// Event count per sub-interval.
    pub counts: Vec<u64>,
    /// Chain-decoupling tendency per sub-interval.
    pub tendency: Vec<f64>,
    /// Cumulative node mass.
    pub cumulative: Vec<f64>,
    /// Cumulative event count after each sub-interval.
    pub through: Vec<u64>,
    /// The moment sampler's count search.
    pub search: moment::SearchBuffers,
}

/// The samplers the project ships, by name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SamplerKind {
    /// V2CE's "Even" baseline.
    Even,
    /// V2CE's "Random" baseline.
    Random,
    /// Chain decoupling with uniform Type 2 placement.
    LdatiRandom,
    /// Chain decoupling with slope-distributed Type 2 placement (the paper's LDATI).
    Ldati,
    /// Chain decoupling refined with the voxel's first moment.
    Moment,
    /// `moment` with each sub-interval's events spaced at the pace of the pixel's neighbours
    /// (the project's default).
    Spatial,
}

impl SamplerKind {
    /// Every sampler, in the order the tables of docs/results.md list them.
    pub const ALL: [SamplerKind; 6] = [
        SamplerKind::Even,
        SamplerKind::Random,
        SamplerKind::LdatiRandom,
        SamplerKind::Ldati,
        SamplerKind::Moment,
        SamplerKind::Spatial,
    ];

    /// The default sampler (docs/results.md: it times real recordings best).
    pub const DEFAULT: SamplerKind = SamplerKind::Spatial;

    /// The CLI name.
    pub fn name(self) -> &'static str {
        match self {
            SamplerKind::Even => "even",
            SamplerKind::Random => "random",
            SamplerKind::LdatiRandom => "ldati-random",
            SamplerKind::Ldati => "ldati",
            SamplerKind::Moment => "moment",
            SamplerKind::Spatial => "spatial",
        }
    }

    /// Parses a CLI name.
    pub fn from_name(name: &str) -> Result<Self> {
        SamplerKind::ALL
            .into_iter()
            .find(|k| k.name() == name)
            .ok_or_else(|| {
                let names: Vec<_> = SamplerKind::ALL.iter().map(|k| k.name()).collect();
                Error::invalid(
                    "sampler",
                    format!("'{name}' is not one of {}", names.join(", ")),
                )
            })
    }

    /// Builds the sampler with `seed`.
    pub fn build(self, seed: u64) -> Box<dyn Sampler> {
        match self {
            SamplerKind::Even => Box::new(baseline::Even { seed }),
            SamplerKind::Random => Box::new(baseline::Random { seed }),
            SamplerKind::LdatiRandom => Box::new(ldati::Ldati {
                seed,
                type2: ldati::Type2::Uniform,
            }),
            SamplerKind::Ldati => Box::new(ldati::Ldati {
                seed,
                type2: ldati::Type2::Slope,
            }),
            SamplerKind::Moment => Box::new(moment::Moment),
            SamplerKind::Spatial => Box::new(spatial::Spatial),
        }
    }
}

impl std::fmt::Display for SamplerKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for SamplerKind {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        SamplerKind::from_name(s)
    }
}

/// The events of one Stage 1 batch: events as they are, voxels re-timed by `sampler`; with
/// what the sampler had to repair. The one place Stage 1's output becomes events, for the
/// pipeline and the streaming API alike.
pub fn events_of(
    batch: crate::stage1::Stage1Batch,
    sampler: &dyn Sampler,
) -> (Vec<crate::event::Event>, SampleStats) {
    match batch {
        crate::stage1::Stage1Batch::Events { events, .. } => (events, SampleStats::default()),
        crate::stage1::Stage1Batch::Voxels(grid, interval) => {
            let mut out = Vec::new();
            let repaired = sampler.sample(&grid, interval, &mut out);
            (out, repaired)
        }
    }
}

/// Copies `values` into `out`, replacing NaN/Inf and negative values by 0 and clamping values
/// above [`MAX_NODE_VALUE`], and counts each repair.
pub fn sanitize(values: &[f64], out: &mut [f64]) -> SampleStats {
    let mut stats = SampleStats::default();
    for (o, &v) in out.iter_mut().zip(values) {
        *o = if !v.is_finite() {
            stats.nonfinite += 1;
            0.0
        } else if v < 0.0 {
            stats.negative += 1;
            0.0
        } else if v > MAX_NODE_VALUE {
            stats.clamped += 1;
            MAX_NODE_VALUE
        } else {
            v
        };
    }
    stats
}

/// A generator for one cell, derived from the seed, the interval and the cell alone, so the
/// draws do not depend on the order in which cells are visited.
pub fn cell_rng(seed: u64, interval_start: i64, x: u16, y: u16, on: bool, width: u16) -> CellRng {
    let cell = ((y as u64 * width as u64 + x as u64) << 1) | on as u64;
    let h = splitmix(splitmix(seed ^ splitmix(interval_start as u64)) ^ cell);
    CellRng::seed_from_u64(h)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for k in SamplerKind::ALL {
            assert_eq!(SamplerKind::from_name(k.name()).unwrap(), k);
            assert_eq!(k.build(1).name(), k.name());
        }
        let err = SamplerKind::from_name("nope").unwrap_err().to_string();
        assert!(err.contains("ldati-random"), "{err}");
    }

    #[test]
    fn sanitize_counts_each_repair() {
        let mut out = [0.0; 6];
        let s = sanitize(&[1.0, f64::NAN, -0.5, f64::INFINITY, 1e9, 0.25], &mut out);
        assert_eq!(out, [1.0, 0.0, 0.0, 0.0, MAX_NODE_VALUE, 0.25]);
        assert_eq!((s.nonfinite, s.negative, s.clamped), (2, 1, 1));
    }
}
