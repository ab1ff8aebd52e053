//! The Stage 2 timestamp metrics: METE, NOE, PGER and their calibrated forms C-METE, C-NOE
//! (V2CE_SPEC.md 6.2).
//!
//! Per frame interval `j` of duration `T_j` (from real frame times):
//! - each ground-truth event is matched to the nearest predicted event in time at the same
//!   pixel and polarity (many-to-one); its error `d` is that time difference, or 1 s when there is
//!   no candidate;
//! - the cap is `3 delta_j` with `delta_j = 1e6 / (10 fps_j) = T_j / 10` us; an error above the cap
//!   (strictly) is set to the cap and counted as an overflow;
//! - `METE_j` is the mean error, `NOE_j` the number of overflows, `PGER_j = |pred_j| / |gt_j|`.
//!
//! The scores are unweighted means over intervals that hold ground-truth events (an interval with
//! none would divide by zero; it is counted in `intervals` but not scored). Calibration follows the
//! paper, applied to the aggregates: `C-METE = METE max(1, PGER)`, `C-NOE = NOE max(1, PGER)`.

use crate::event::Event;
use crate::interval::Interval;

/// Error given to a ground-truth event with no prediction at its pixel and polarity.
pub const NO_MATCH_US: f64 = 1e6;

/// Scores of one run, as `v2ce eval stage2 --json` prints them.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Stage2Metrics {
    /// Mean timestamp error, us.
    pub mete_us: f64,
    /// Mean number of overflows per interval.
    pub noe: f64,
    /// Mean predicted-to-ground-truth event count ratio.
    pub pger: f64,
    /// `mete_us * max(1, pger)`.
    pub c_mete_us: f64,
    /// `noe * max(1, pger)`.
    pub c_noe: f64,
    /// Intervals seen.
    pub intervals: u64,
    /// Intervals with ground-truth events (the ones averaged).
    pub intervals_scored: u64,
    /// Ground-truth events inside the intervals.
    pub events_in: u64,
    /// Predicted events.
    pub events_out: u64,
}

/// Accumulates per-interval scores.
#[derive(Debug, Clone, Default)]
pub struct Stage2Scorer {
    sum_mete: f64,
    sum_noe: f64,
    sum_pger: f64,
    intervals: u64,
    scored: u64,
    events_in: u64,
    events_out: u64,
    scratch: IntervalScratch,
}

fn key(e: &Event) -> u64 {
    ((e.y as u64) << 17) | ((e.x as u64) << 1) | e.on as u64
}

/// The scores of one interval.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IntervalScore {
    /// Mean error over ground-truth events, us (`None` without ground truth).
    pub mete_us: Option<f64>,
    /// Number of overflows.
    pub noe: u64,
    /// `|pred| / |gt|` (`None` without ground truth).
    pub pger: Option<f64>,
    /// Ground-truth events.
    pub events_in: u64,
    /// Predicted events.
    pub events_out: u64,
}

/// Reusable working memory of [`IntervalScratch::score`]: one per thread.
#[derive(Debug, Clone, Default)]
pub struct IntervalScratch {
    truth: Vec<(u64, i64)>,
    predicted: Vec<(u64, i64)>,
}

impl IntervalScratch {
    /// Scores one interval: `truth` and `predicted` are the events inside `interval`, in any
    /// order. Both are sorted by pixel, polarity and time, then walked together: each
    /// ground-truth event's nearest prediction is the first at or after it or the one before.
    pub fn score(
        &mut self,
        interval: Interval,
        truth: &[Event],
        predicted: &[Event],
    ) -> IntervalScore {
        let (events_in, events_out) = (truth.len() as u64, predicted.len() as u64);
        if truth.is_empty() {
            return IntervalScore {
                mete_us: None,
                noe: 0,
                pger: None,
                events_in,
                events_out,
            };
        }
        let cap = 3.0 * interval.duration_us() as f64 / 10.0;
        let keyed = |events: &[Event], into: &mut Vec<(u64, i64)>| {
            into.clear();
            into.extend(events.iter().map(|e| (key(e), e.t)));
            into.sort_unstable();
        };
        keyed(truth, &mut self.truth);
        keyed(predicted, &mut self.predicted);
        let pred = &self.predicted;
        // Errors within the cap are whole microseconds: summed exactly, whatever the order.
        let mut within = 0u128;
        let mut overflows = 0u64;
        let mut p = 0;
        for &(k, t) in &self.truth {
            while p < pred.len() && pred[p] < (k, t) {
                p += 1;
            }
            let after = pred.get(p).filter(|q| q.0 == k).map(|q| q.1.abs_diff(t));
            let before = p
                .checked_sub(1)
                .map(|i| pred[i])
                .filter(|q| q.0 == k)
                .map(|q| q.1.abs_diff(t));
            let d = match (after, before) {
                (Some(a), Some(b)) => a.min(b) as f64,
                (Some(d), None) | (None, Some(d)) => d as f64,
                (None, None) => NO_MATCH_US,
            };
            if d > cap {
                overflows += 1;
            } else {
                within += d as u128;
            }
        }
        let total = within as f64 + overflows as f64 * cap;
        IntervalScore {
            mete_us: Some(total / truth.len() as f64),
            noe: overflows,
            pger: Some(predicted.len() as f64 / truth.len() as f64),
            events_in,
            events_out,
        }
    }
}

impl Stage2Scorer {
    /// A scorer with nothing accumulated.
    pub fn new() -> Self {
        Self::default()
    }

    /// Scores one interval and adds it: `truth` and `predicted` are the events inside
    /// `interval`, in any order.
    pub fn add_interval(
        &mut self,
        interval: Interval,
        truth: &[Event],
        predicted: &[Event],
    ) -> IntervalScore {
        let score = self.scratch.score(interval, truth, predicted);
        self.add(score);
        score
    }

    /// Adds the score of one interval, computed apart (on another thread). Scores added in the
    /// same order give the same aggregate.
    pub fn add(&mut self, score: IntervalScore) {
        self.intervals += 1;
        self.events_in += score.events_in;
        self.events_out += score.events_out;
        if let (Some(mete), Some(pger)) = (score.mete_us, score.pger) {
            self.scored += 1;
            self.sum_mete += mete;
            self.sum_noe += score.noe as f64;
            self.sum_pger += pger;
        }
    }

    /// The aggregate scores so far.
    pub fn finish(&self) -> Stage2Metrics {
        let n = self.scored.max(1) as f64;
        let (mete, noe, pger) = if self.scored == 0 {
            (0.0, 0.0, 0.0)
        } else {
            (self.sum_mete / n, self.sum_noe / n, self.sum_pger / n)
        };
        let calib = pger.max(1.0);
        Stage2Metrics {
            mete_us: mete,
            noe,
            pger,
            c_mete_us: mete * calib,
            c_noe: noe * calib,
            intervals: self.intervals,
            intervals_scored: self.scored,
            events_in: self.events_in,
            events_out: self.events_out,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// V2CE_SPEC Appendix B.8: GT at 100 and 5000 us, one prediction at 150 us, 30 fps.
    #[test]
    fn golden_mete() {
        let iv = Interval::new(0, 100_000 / 3).unwrap();
        let truth = [Event::new(100, 3, 4, true), Event::new(5000, 3, 4, true)];
        let pred = [Event::new(150, 3, 4, true)];
        let mut s = Stage2Scorer::new();
        let one = s.add_interval(iv, &truth, &pred);
        assert_eq!(one.mete_us, Some(2450.0));
        assert_eq!(one.noe, 0);
        assert_eq!(one.pger, Some(0.5));
        let m = s.finish();
        assert_eq!((m.mete_us, m.c_mete_us, m.pger), (2450.0, 2450.0, 0.5));
    }

    #[test]
    fn polarity_pixel_and_cap() {
        let iv = Interval::new(1 << 35, (1 << 35) + 40_000).unwrap(); // cap 12000 us
        let t0 = iv.start();
        let truth = [
            Event::new(t0 + 10, 0, 0, true), // only an OFF prediction at its pixel: no match
            Event::new(t0 + 10, 1, 0, true), // nearest 20_000 us away: overflow, capped
            Event::new(t0 + 500, 2, 0, false), // exact
        ];
        let pred = [
            Event::new(t0 + 10, 0, 0, false),
            Event::new(t0 + 20_010, 1, 0, true),
            Event::new(t0 + 500, 2, 0, false),
            Event::new(t0 + 30_000, 2, 0, false),
        ];
        let mut s = Stage2Scorer::new();
        let one = s.add_interval(iv, &truth, &pred);
        assert_eq!(one.noe, 2);
        assert_eq!(one.mete_us, Some(24_000.0 / 3.0));
        // Empty ground truth is counted but not scored.
        s.add_interval(iv, &[], &pred);
        let m = s.finish();
        assert_eq!((m.intervals, m.intervals_scored), (2, 1));
        assert!((m.c_mete_us - 8000.0 * 4.0 / 3.0).abs() < 1e-9);
        assert!((m.c_noe - 2.0 * 4.0 / 3.0).abs() < 1e-9);
    }
}
