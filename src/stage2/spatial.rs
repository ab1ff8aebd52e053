//! `spatial`: the `moment` sampler's counts and means, with the spacing of a sub-interval's
//! events taken from the pixel's neighbours in time and, where it has none, in space.
//!
//! The voxel fixes each sub-interval's event count `m` and the mean position of its events
//! exactly (see [`super::moment`]); what it does not fix, when `m >= 2`, is how far apart the
//! events lie. `moment` spreads them as if they were uniform in the sub-interval. They are not:
//! a DVS pixel fires in runs whose events are nearly evenly spaced in time (the log intensity
//! ramps through one threshold after the next, and a pixel cannot fire again within its
//! refractory period), and the pixels an edge crosses fire in runs of similar pace.
//!
//! So, per cell:
//! 1. Counts and means as `moment` finds them (the same counts: no event moves to another
//!    sub-interval, and the mean of every sub-interval's events is kept).
//! 2. Where a sub-interval holds `m >= 2` events and the pixel has events within [`REACH`]
//!    sub-intervals before or after, the run is taken as evenly spaced through them: with the
//!    run's centre `c` and a neighbouring group of `m'` events centred at `c'`, the period is
//!    `|c' - c| / ((m + m') / 2)`; the estimates from both sides are averaged.
//! 3. Where the pixel has no such neighbour in time, the period is the mean of the periods its
//!    spatial neighbours (the 8 around it, same polarity) showed in step 2.
//! 4. Where they show none either, a pair of events (`m = 2`) is spaced at the median spacing
//!    the interval's stream shows below the widest the pair allows (see [`Gaps`]: a sensor
//!    whose pixels fire in tight bursts shows them there); a group of more, or a pair in a
//!    stream that shows too little, at half the widest spacing ([`FALLBACK_SHARE`]: `moment`'s
//!    for two events, closer for more). Both measured better than the alternatives on every
//!    recording we have (docs/results.md).
//! 5. The events sit evenly spaced at that period around their known mean, the period capped so
//!    that all stay inside the sub-interval (`(m - 1) p <= min(2 mean, 2 (1 - mean))`).
//!
//! No randomness is used; every value is finite for finite voxels (the driver sanitises them),
//! and the result does not depend on the order of the cells.

use super::chain::ONE_BELOW;
use super::moment::cumulative_counts;
use super::{push_events, sanitize, CellRng, SampleStats, Sampler, Scratch};
use crate::event::{sort_events, Event};
use crate::interval::Interval;
use crate::voxel::VoxelGrid;

/// How far (in sub-intervals, centre to centre) a pixel's neighbouring group of events may lie
/// to be taken as part of the same run.
pub const REACH: f64 = 1.5;

/// The share of the widest spacing used where neither the pixel nor its neighbours show a pace.
pub const FALLBACK_SHARE: f64 = 0.5;

/// The spatial sampler (see the module docs).
#[derive(Debug, Clone, Copy, Default)]
pub struct Spatial;

/// One sub-interval's events of one cell: where, how many, their mean position in it, and the
/// spacing found for them (NaN until found).
#[derive(Debug, Clone, Copy)]
struct Group {
    sub: u32,
    count: u64,
    mean: f64,
    period: f64,
}

/// The groups of one cell, where it is, and its pace from step 2.
#[derive(Debug, Clone)]
struct CellGroups {
    x: u16,
    y: u16,
    on: bool,
    groups: std::ops::Range<usize>,
    pace: f64,
}

/// A cell's place in key order: plane, row, column.
fn cell_key(on: bool, x: u16, y: u16) -> u64 {
    ((!on as u64) << 32) | ((y as u64) << 16) | x as u64
}

/// Appends the groups of one cell (`nodes` sanitised) to `groups`; finds the spacing of those
/// whose pixel shows its pace (step 2) and returns the cell's mean pace (NaN if none). Appends
/// to `gaps` the distance between each two single events in adjacent sub-intervals less than a
/// sub-interval apart (see [`Gaps`]).
fn groups_of(
    nodes: &[f64],
    scratch: &mut Scratch,
    groups: &mut Vec<Group>,
    gaps: &mut Vec<f64>,
) -> f64 {
    cumulative_counts(nodes, scratch);
    let first = groups.len();
    let mut before = 0u64;
    for (i, (&through, &mass)) in scratch
        .through
        .iter()
        .zip(scratch.cumulative.iter())
        .enumerate()
    {
        let count = through - before;
        before = through;
        if count == 0 {
            continue;
        }
        let sum = (through as f64 - mass).clamp(0.0, count as f64);
        groups.push(Group {
            sub: i as u32,
            count,
            mean: (sum / count as f64).clamp(0.0, ONE_BELOW),
            period: f64::NAN,
        });
    }
    let cell = &mut groups[first..];
    let centre = |g: &Group| g.sub as f64 + g.mean;
    for pair in cell.windows(2) {
        let (a, b) = (&pair[0], &pair[1]);
        if a.count == 1 && b.count == 1 && b.sub == a.sub + 1 {
            let gap = centre(b) - centre(a);
            if gap < 1.0 {
                gaps.push(gap);
            }
        }
    }
    let (mut paces, mut n) = (0.0, 0u32);
    for j in 0..cell.len() {
        let (mut sum, mut k) = (0.0, 0u32);
        let here = centre(&cell[j]);
        let mut side = |other: &Group| {
            let gap = (centre(other) - here).abs();
            if gap < REACH {
                sum += gap / ((cell[j].count + other.count) as f64 / 2.0);
                k += 1;
            }
        };
        if j > 0 {
            side(&cell[j - 1]);
        }
        if j + 1 < cell.len() {
            side(&cell[j + 1]);
        }
        if k > 0 {
            let pace = sum / k as f64;
            paces += pace;
            n += 1;
            if cell[j].count >= 2 {
                cell[j].period = pace;
            }
        }
    }
    if n > 0 {
        paces / n as f64
    } else {
        f64::NAN
    }
}

/// The spacing of two events of one pixel in the interval's stream, learnt from its single
/// events: where two lie in adjacent sub-intervals less than a sub-interval apart, the voxel
/// gives both exactly, and their distance is a sample of the pixel's spacing, taken with
/// probability in proportion to it (two events `g` apart straddle a sub-interval's boundary
/// with probability `g`); weighted by `1 / g`, the samples give the spacing's distribution
/// below one sub-interval. A sensor whose pixels fire in tight bursts shows it here.
#[derive(Debug, Default)]
struct Gaps {
    /// The samples, ascending.
    gaps: Vec<f64>,
    /// Cumulative `1 / g` weights.
    weight: Vec<f64>,
}

/// Fewest samples from which [`Gaps`] is trusted.
const MIN_GAPS: usize = 16;

impl Gaps {
    fn new(mut gaps: Vec<f64>) -> Self {
        gaps.sort_unstable_by(f64::total_cmp);
        let mut acc = 0.0;
        let weight = gaps
            .iter()
            .map(|&g| {
                acc += 1.0 / g.max(1e-3);
                acc
            })
            .collect();
        Gaps { gaps, weight }
    }

    /// The median spacing among those up to `widest` (NaN with too few samples).
    fn median_below(&self, widest: f64) -> f64 {
        let n = self.gaps.partition_point(|&g| g <= widest);
        if self.gaps.len() < MIN_GAPS || n == 0 {
            return f64::NAN;
        }
        let half = self.weight[n - 1] / 2.0;
        self.gaps[self.weight[..n].partition_point(|&w| w < half).min(n - 1)]
    }
}

/// The widest spacing that keeps a group's events, centred on their mean, in its sub-interval.
fn widest(g: &Group) -> f64 {
    (2.0 * g.mean).min(2.0 * (1.0 - g.mean)) / (g.count.max(2) - 1) as f64
}

/// Places a group's events at node positions, evenly spaced at its period (NaN:
/// [`FALLBACK_SHARE`] of the widest) around their mean, inside the sub-interval.
fn place(g: &Group, out: &mut Vec<f64>) {
    let base = g.sub as f64;
    if g.count == 1 {
        out.push(base + g.mean);
        return;
    }
    let spread = (g.count - 1) as f64;
    let widest = widest(g);
    let period = if g.period.is_finite() {
        g.period.clamp(0.0, widest)
    } else {
        FALLBACK_SHARE * widest
    };
    let first = g.mean - spread * period / 2.0;
    out.extend((0..g.count).map(|j| base + (first + j as f64 * period).clamp(0.0, ONE_BELOW)));
}

impl Sampler for Spatial {
    fn name(&self) -> &'static str {
        "spatial"
    }

    fn seed(&self) -> u64 {
        0
    }

    /// One cell alone: steps 1, 2 and 5 (neither spatial neighbours nor the stream).
    fn sample_cell(
        &self,
        nodes: &[f64],
        _: &mut CellRng,
        scratch: &mut Scratch,
        out: &mut Vec<f64>,
    ) {
        let mut groups = Vec::new();
        groups_of(nodes, scratch, &mut groups, &mut Vec::new());
        for g in &groups {
            place(g, out);
        }
    }

    fn sample(&self, voxels: &VoxelGrid, interval: Interval, out: &mut Vec<Event>) -> SampleStats {
        let mut stats = SampleStats::default();
        let bins = voxels.bins();
        let scale = interval.duration_us() as f64 / (bins - 1) as f64;
        let mut nodes = vec![0.0; bins];
        let mut scratch = Scratch::default();
        let mut groups = Vec::new();
        let mut gaps = Vec::new();
        let mut cells = Vec::with_capacity(voxels.active_cells());
        for cell in voxels.cells() {
            stats.add(sanitize(cell.values, &mut nodes));
            let start = groups.len();
            let pace = groups_of(&nodes, &mut scratch, &mut groups, &mut gaps);
            cells.push(CellGroups {
                x: cell.x,
                y: cell.y,
                on: cell.on,
                groups: start..groups.len(),
                pace,
            });
        }
        // Step 3: the pace of the spatial neighbours, for groups whose pixel shows none.
        let mut paces: Vec<(u64, f64)> = cells
            .iter()
            .filter(|c| c.pace.is_finite())
            .map(|c| (cell_key(c.on, c.x, c.y), c.pace))
            .collect();
        paces.sort_unstable_by_key(|&(k, _)| k);
        let (w, h) = (voxels.width() as i32, voxels.height() as i32);
        for c in &cells {
            if !groups[c.groups.clone()]
                .iter()
                .any(|g| g.count >= 2 && g.period.is_nan())
            {
                continue;
            }
            let (mut sum, mut n) = (0.0, 0u32);
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (x, y) = (c.x as i32 + dx, c.y as i32 + dy);
                    if (dx, dy) == (0, 0) || x < 0 || y < 0 || x >= w || y >= h {
                        continue;
                    }
                    let key = cell_key(c.on, x as u16, y as u16);
                    if let Ok(at) = paces.binary_search_by_key(&key, |&(k, _)| k) {
                        sum += paces[at].1;
                        n += 1;
                    }
                }
            }
            if n > 0 {
                let pace = sum / n as f64;
                for g in &mut groups[c.groups.clone()] {
                    if g.count >= 2 && g.period.is_nan() {
                        g.period = pace;
                    }
                }
            }
        }
        // Step 4: the stream's own spacing, for groups still without one.
        let gaps = Gaps::new(gaps);
        for g in groups
            .iter_mut()
            .filter(|g| g.count == 2 && g.period.is_nan())
        {
            g.period = gaps.median_below(widest(g));
        }
        let first = out.len();
        let mut taus = Vec::new();
        for c in &cells {
            taus.clear();
            for g in &groups[c.groups.clone()] {
                place(g, &mut taus);
            }
            push_events(&taus, (c.x, c.y, c.on), interval, scale, out);
        }
        sort_events(&mut out[first..]);
        stats
    }
}
