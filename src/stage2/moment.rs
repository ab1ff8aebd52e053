//! `moment`: LDATI's chain decoupling refined with the first moment the voxel carries.
//!
//! Write `V_i` for the cumulative node mass through node `i` and `M_i` for the cumulative number
//! of events through sub-interval `i`. For a voxel made by `voxelize`, each sub-interval holding
//! `m_i = M_i - M_{i-1}` events with in-sub-interval positions `f` satisfies exactly
//!
//! ```text
//!     V_i = M_{i-1} + sum(1 - f)      so      M_{i-1} <= V_i <= M_i,
//!     S_i = sum(f) = M_i - V_i        (the first moment of the sub-interval's events).
//! ```
//!
//! So the voxel fixes, for every choice of cumulative counts, both the count *and the mean
//! position* of each sub-interval's events. Chain decoupling picks the smallest feasible
//! `M_i = ceil(V_i)`, which is exact when no sub-interval holds two events, but when one does it
//! pushes events to the start of the next sub-interval (a cluster at 0.6 and 0.7 comes back at
//! 0.3 and 1.0). LDATI then discards the moment and draws Type 2 events from a fitted slope.
//!
//! Here:
//! 1. Counts: every integer `M_i` in `[ceil(V_i), floor(V_{i+1})]` is feasible. Where that range
//!    holds more than one value, a dynamic programme over the sub-intervals picks the counts
//!    that are most probable if events arrive as a Poisson process, local rate
//!    `(v_i + v_{i+1}) / 2`, uniformly within a sub-interval: it maximises
//!    `sum_i [m_i ln(lambda_i) - ln(m_i!) + ln IH_{m_i}(S_i)]`, where `IH_m` is the Irwin-Hall
//!    density of a sum of `m` uniforms. (Events exactly on a node are improbable; the earliest
//!    choice makes them systematically.) Where the range is a single value (the common case,
//!    and always when sub-intervals hold at most one event) nothing is searched.
//! 2. Positions: one event sits at `S_i` (exact, as in LDATI); `m >= 2` events are spaced evenly
//!    around their known mean `S_i / m` over a width `min(1, 2 mean, 2 (1 - mean))`, which keeps
//!    them inside the sub-interval with the mean unchanged.
//!
//! Consequences: counts per cell are preserved exactly like chain decoupling, single events are
//! recovered exactly, and re-voxelizing the output gives back the input voxel (every
//! sub-interval's count and first moment are kept). No randomness is used.

use super::chain::{ceil_count, tolerance, total_count, ONE_BELOW};
use super::{CellRng, Sampler, Scratch};

/// At most this many candidate counts per sub-interval enter the search (evenly spread over the
/// feasible range, both ends included), bounding the cost of cells with thousands of events.
const MAX_CANDIDATES: usize = 48;

/// The moment sampler (see the module docs).
#[derive(Debug, Clone, Copy, Default)]
pub struct Moment;

impl Sampler for Moment {
    fn name(&self) -> &'static str {
        "moment"
    }

    fn seed(&self) -> u64 {
        0
    }

    fn sample_cell(
        &self,
        nodes: &[f64],
        _: &mut CellRng,
        scratch: &mut Scratch,
        out: &mut Vec<f64>,
    ) {
        cumulative_counts(nodes, scratch);
        let Scratch {
            cumulative,
            through,
            ..
        } = scratch;
        let mut before = 0u64;
        for (i, (&m_through, &v_through)) in through.iter().zip(cumulative.iter()).enumerate() {
            let m = m_through - before;
            before = m_through;
            if m == 0 {
                continue;
            }
            let sum = (m_through as f64 - v_through).clamp(0.0, m as f64);
            place(i as f64, m, sum, out);
        }
    }
}

/// Places `m` events in the sub-interval starting at node `base` with positions summing to `sum`.
fn place(base: f64, m: u64, sum: f64, out: &mut Vec<f64>) {
    let mean = (sum / m as f64).clamp(0.0, ONE_BELOW);
    if m == 1 {
        out.push(base + mean);
        return;
    }
    let width = 1f64.min(2.0 * mean).min(2.0 * (1.0 - mean));
    let step = width / m as f64;
    let first = mean - width / 2.0 + step / 2.0;
    out.extend((0..m).map(|j| base + (first + j as f64 * step).clamp(0.0, ONE_BELOW)));
}

/// Fills `scratch.cumulative` with `V_i` (i < K) and `scratch.through` with the chosen `M_i`.
pub(super) fn cumulative_counts(nodes: &[f64], scratch: &mut Scratch) {
    let k = nodes.len() - 1;
    let cum = &mut scratch.cumulative;
    cum.clear();
    let mut acc = 0.0;
    for &v in nodes {
        acc += v;
        cum.push(acc);
    }
    let total = total_count(cum[k - 1], cum[k]);
    // Feasible ranges; the smallest values are chain decoupling's choice.
    let through = &mut scratch.through;
    through.clear();
    let mut ambiguous = false;
    let mut lo_prev = 0u64;
    let ranges = &mut scratch.search.ranges;
    ranges.clear();
    for i in 0..k {
        let lo = if i + 1 == k {
            total // the last sub-interval takes the fold of the last node
        } else {
            ceil_count(cum[i]).max(lo_prev).min(total)
        };
        let hi = if i + 1 == k {
            total
        } else {
            // The floor, at least 0: truncation (rounding.rs).
            let h = (cum[i + 1] + tolerance(cum[i + 1])) as u64;
            h.clamp(lo, total)
        };
        ambiguous |= hi > lo;
        through.push(lo);
        ranges.push((lo, hi));
        lo_prev = lo;
    }
    cum.truncate(k);
    if ambiguous {
        search(nodes, cum, &mut scratch.search, through);
    }
}

/// Buffers of the count search, reused across cells.
#[derive(Debug, Clone, Default)]
pub struct SearchBuffers {
    /// Feasible `(lo, hi)` cumulative counts per sub-interval.
    ranges: Vec<(u64, u64)>,
    /// Candidate cumulative counts, all sub-intervals back to back.
    candidates: Vec<u64>,
    /// Start of each sub-interval's candidates in `candidates` (one more entry at the end).
    offsets: Vec<usize>,
    /// Best log-likelihood up to each candidate.
    score: Vec<f64>,
    /// The previous sub-interval's candidate (absolute index) on that best path.
    back: Vec<usize>,
}

/// The dynamic programme of the module docs over candidate cumulative counts.
fn search(nodes: &[f64], cum: &[f64], buf: &mut SearchBuffers, through: &mut [u64]) {
    let SearchBuffers {
        ranges,
        candidates,
        offsets,
        score,
        back,
    } = buf;
    let k = ranges.len();
    candidates.clear();
    offsets.clear();
    for &(lo, hi) in ranges.iter() {
        offsets.push(candidates.len());
        if hi - lo < MAX_CANDIDATES as u64 {
            candidates.extend(lo..=hi);
        } else {
            let span = (hi - lo) as f64;
            let step = span / (MAX_CANDIDATES - 1) as f64;
            for j in 0..MAX_CANDIDATES {
                let v = lo + (j as f64 * step).round() as u64;
                if j == 0 || candidates.last() != Some(&v) {
                    candidates.push(v);
                }
            }
        }
    }
    offsets.push(candidates.len());
    score.clear();
    back.clear();
    for i in 0..k {
        let ln_lambda = ((nodes[i] + nodes[i + 1]) / 2.0).max(1e-3).ln();
        let prevs = if i == 0 {
            0..0
        } else {
            offsets[i - 1]..offsets[i]
        };
        for c in offsets[i]..offsets[i + 1] {
            let cur = candidates[c];
            let excess = cur as f64 - cum[i];
            let mut best = (f64::NEG_INFINITY, usize::MAX);
            if i == 0 {
                best = (
                    sub_interval_log_likelihood(cur, excess, ln_lambda),
                    usize::MAX,
                );
            }
            for p in prevs.clone() {
                let prev = candidates[p];
                if prev > cur {
                    continue;
                }
                let s = score[p] + sub_interval_log_likelihood(cur - prev, excess, ln_lambda);
                if s > best.0 {
                    best = (s, p);
                }
            }
            score.push(best.0);
            back.push(best.1);
        }
    }
    // Trace back from the best final candidate (the last range is a single value).
    let last = offsets[k - 1]..offsets[k];
    let Some(mut c) = last.max_by(|&a, &b| score[a].total_cmp(&score[b])) else {
        return;
    };
    if !score[c].is_finite() {
        return; // keep chain decoupling's counts
    }
    for i in (0..k).rev() {
        through[i] = candidates[c];
        c = back[c];
        if c == usize::MAX {
            break;
        }
    }
}

/// `m ln(lambda) - ln(m!) + ln IH_m(sum)` for `m` events whose positions sum to `sum`.
fn sub_interval_log_likelihood(m: u64, sum: f64, ln_lambda: f64) -> f64 {
    if m == 0 {
        // No event: the sub-interval's node must carry no mass of its own.
        return if sum.abs() <= tolerance(sum) {
            0.0
        } else {
            f64::NEG_INFINITY
        };
    }
    let mf = m as f64;
    mf * ln_lambda - ln_factorial(m) + ln_irwin_hall(m, sum.clamp(0.0, mf))
}

fn ln_factorial(m: u64) -> f64 {
    const TABLE: usize = 128;
    static SMALL: std::sync::OnceLock<[f64; TABLE]> = std::sync::OnceLock::new();
    let table = SMALL.get_or_init(|| {
        let mut t = [0.0; TABLE];
        for i in 1..TABLE {
            t[i] = t[i - 1] + (i as f64).ln();
        }
        t
    });
    if (m as usize) < TABLE {
        table[m as usize]
    } else {
        // Stirling's series; its error is below 1e-9 here.
        let x = m as f64;
        x * x.ln() - x + 0.5 * (2.0 * std::f64::consts::PI * x).ln() + 1.0 / (12.0 * x)
            - 1.0 / (360.0 * x * x * x)
    }
}

/// The log density of the sum of `m` independent uniforms on `[0, 1]` at `s` in `[0, m]`;
/// floored at `ln(1e-300)` so that boundary values rank last instead of being impossible.
///
/// The boundaries themselves (every event exactly on a node, within the chain tolerance) get the
/// floor even for `m = 1`: the voxel then shows an exact integer cumulative mass, which an empty
/// neighbouring sub-interval explains with positive probability and a node-aligned event only
/// with probability zero.
fn ln_irwin_hall(m: u64, s: f64) -> f64 {
    const FLOOR: f64 = -690.8;
    let mf = m as f64;
    let tol = tolerance(mf);
    if s <= tol || s >= mf - tol {
        return FLOOR;
    }
    if m == 1 {
        return 0.0;
    }
    if m > 16 {
        let var = mf / 12.0;
        let d = s - mf / 2.0;
        return (-0.5 * (2.0 * std::f64::consts::PI * var).ln() - d * d / (2.0 * var)).max(FLOOR);
    }
    let s = s.min(mf - s); // symmetric
    let mut sum = 0.0;
    let mut binom = 1.0;
    for j in 0..=(s as u64) {
        let term = binom * (s - j as f64).powi(m as i32 - 1);
        sum += if j % 2 == 0 { term } else { -term };
        binom = binom * (mf - j as f64) / (j as f64 + 1.0);
    }
    let density = sum / (1..m).map(|i| i as f64).product::<f64>();
    if density > 1e-300 {
        density.ln()
    } else {
        FLOOR
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stage2::{cell_rng, Scratch};

    fn taus(nodes: &[f64]) -> Vec<f64> {
        let mut out = Vec::new();
        let mut rng = cell_rng(0, 0, 0, 0, true, 1);
        Moment.sample_cell(nodes, &mut rng, &mut Scratch::default(), &mut out);
        out
    }

    fn voxel(taus: &[f64]) -> Vec<f64> {
        let mut v = vec![0.0; 10];
        for &t in taus {
            let a = (t as usize).min(8); // the floor (rounding.rs)
            v[a] += 1.0 - (t - a as f64);
            v[a + 1] += t - a as f64;
        }
        v
    }

    #[test]
    fn irwin_hall_is_a_density() {
        for m in [2u64, 3, 5, 16, 17, 40] {
            let n = 20_000;
            let integral: f64 = (0..n)
                .map(|i| ln_irwin_hall(m, (i as f64 + 0.5) * m as f64 / n as f64).exp())
                .sum::<f64>()
                * m as f64
                / n as f64;
            assert!((integral - 1.0).abs() < 2e-3, "m {m}: {integral}");
        }
        // Node-aligned sums rank last.
        assert_eq!(ln_irwin_hall(1, 0.0), ln_irwin_hall(3, 3.0));
        assert!(ln_irwin_hall(1, 0.0) < -600.0);
        // Triangle for m = 2.
        assert!((ln_irwin_hall(2, 0.5).exp() - 0.5).abs() < 1e-12);
        assert!((ln_irwin_hall(2, 1.5).exp() - 0.5).abs() < 1e-12);
        // The factorial table and Stirling's series meet smoothly.
        let direct: f64 = (1..=200).map(|i| (i as f64).ln()).sum();
        assert!((ln_factorial(200) - direct).abs() < 1e-9);
        assert!((ln_factorial(127) - (ln_factorial(128) - 128f64.ln())).abs() < 1e-9);
    }

    /// The example of the module docs: a pair at 0.6 and 0.7 in sub-interval 3.
    #[test]
    fn cluster_keeps_its_place() {
        let got = taus(&voxel(&[3.6, 3.7]));
        assert_eq!(got.len(), 2);
        let mean = (got[0] + got[1]) / 2.0;
        assert!((mean - 3.65).abs() < 1e-9, "{got:?}");
        assert!(got.iter().all(|t| (3.0..4.0).contains(t)), "{got:?}");
    }

    #[test]
    fn single_events_are_exact_and_output_revoxelizes_to_input() {
        let truth = [0.25, 1.5, 2.999, 5.0, 7.75, 8.5];
        let got = taus(&voxel(&truth));
        for (g, t) in got.iter().zip(truth) {
            assert!((g - t).abs() < 1e-9, "{got:?}");
        }
        let input = voxel(&[1.2, 1.3, 1.9, 4.5, 4.6, 4.65, 4.99, 6.1]);
        let again = voxel(&taus(&input));
        for (a, b) in input.iter().zip(&again) {
            assert!((a - b).abs() < 1e-9, "{input:?} vs {again:?}");
        }
    }
}
