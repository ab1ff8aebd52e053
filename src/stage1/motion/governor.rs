//! The live run's sub-frame cap keeper (see [`Governor`]): the motion model's detail traded
//! for time so that Stage 1 keeps up with the frames.

/// In a live run, the share of the frame interval Stage 1 may spend (smoothed) before the cap
/// falls. Stage 1 keeps up with the frames while it takes less than the frame interval; the
/// rest is the margin for a slower interval (the queues, four frames deep, absorb a few) and
/// for the threads beside it, whose contention its wall time already shows.
const LIVE_SHARE: f64 = 0.8;
/// Intervals well inside the budget (under half of it) before the cap rises by one; doubled
/// (up to `MAX_CALM_INTERVALS`) each time a raise has to be taken back within that many.
pub(super) const CALM_INTERVALS: u32 = 30;
const MAX_CALM_INTERVALS: u32 = 30 * 64;
/// Intervals the smoothed time needs after a change of cap before it may lower the cap.
pub(super) const SETTLE_INTERVALS: u32 = 3;

/// Keeps a live run's sub-frame cap where Stage 1 keeps up with the frames: the cap falls
/// when the time per interval stepped through sub-frames, smoothed over a few of them, passes
/// `LIVE_SHARE` of the interval's wall time (in proportion to the overshoot: by one at least,
/// to half at most in one step, so a pan that needs a little less keeps most of its
/// sub-frames), and rises by one after `CALM_INTERVALS` intervals under half of that. An interval stepped without sub-frames (nothing moved, or a scene cut
/// or a change of light that fell back to linear) costs the same at any cap: it does not
/// lower the cap, and counts as calm when it took under half the budget. A raise taken back
/// soon after doubles the wait before the next (a machine that cannot afford the flow at all
/// settles on linear interpolation instead of trying every second).
#[derive(Debug, Clone)]
pub(super) struct Governor {
    speed: f64,
    /// Smoothed seconds per interval with sub-frames since the last change of cap, and how
    /// many intervals.
    smoothed: f64,
    samples: u32,
    calm: u32,
    wait: u32,
    /// Intervals since the last raise, while it may still be taken back.
    since_raise: Option<u32>,
    /// Seconds of the run (wall time at its speed) spent with the cap below the configured
    /// one, without a break; `None` once the warning that says so has been given.
    pub(super) below_s: Option<f64>,
}

/// A live run whose cap stays below the configured one this long (seconds, without a break)
/// says so once, as a warning: the changes themselves are summarised in the stats line.
pub(super) const LONG_BELOW_S: f64 = 60.0;

impl Governor {
    pub(super) fn new(speed: f64) -> Self {
        Governor {
            speed,
            smoothed: 0.0,
            samples: 0,
            calm: 0,
            wait: CALM_INTERVALS,
            since_raise: None,
            below_s: Some(0.0),
        }
    }

    /// Counts `frame` seconds at `cap` of `most`; says once when the cap has stayed below
    /// `most` for `LONG_BELOW_S`.
    fn watch(&mut self, frame: f64, cap: u32, most: u32) {
        let Some(below) = &mut self.below_s else {
            return;
        };
        *below = if cap < most { *below + frame } else { 0.0 };
        if *below >= LONG_BELOW_S {
            self.below_s = None;
            tracing::warn!(
                "the sub-frame cap has stayed below its configured {most} for {LONG_BELOW_S:.0} \
                 s (now {cap}; 1 is linear interpolation): this machine cannot run the full \
                 motion model at this frame size and rate in real time (the stats line shows \
                 the cap; a smaller frame or a lower max_subframes holds steady)"
            );
        }
    }

    /// The new cap, if it changes, after an interval of `interval_us` took `seconds` at `cap`
    /// (`subframed`: through sub-frames).
    pub(super) fn spent(
        &mut self,
        seconds: f64,
        interval_us: i64,
        subframed: bool,
        cap: u32,
        most: u32,
    ) -> Option<u32> {
        let frame = interval_us as f64 * 1e-6 / self.speed;
        self.watch(frame, cap, most);
        let budget = LIVE_SHARE * frame;
        if subframed {
            self.smoothed = if self.samples == 0 {
                seconds
            } else {
                0.7 * self.smoothed + 0.3 * seconds
            };
            self.samples += 1;
        }
        if let Some(n) = &mut self.since_raise {
            *n += 1;
            if *n > 2 * self.wait {
                // The raise held: the machine has the time, back to the short wait.
                self.since_raise = None;
                self.wait = CALM_INTERVALS;
            }
        }
        // An interval through sub-frames that took longer than the frame interval itself,
        // with the smoothed time over the budget too (not a lone hiccup), puts Stage 1
        // behind at once (the frames queue, then are shed): lowered without waiting for the
        // smoothed time to settle. Not on the first interval since the start or the last
        // change: the run's first pays for starting its threads, and the one after a change
        // had its motion found ahead under the cap before.
        let behind = subframed && seconds > frame && self.smoothed > budget && self.samples >= 2;
        if ((self.samples >= SETTLE_INTERVALS && self.smoothed > budget) || behind) && cap > 1 {
            // Time falls at most in proportion to the cap (a part of it, the frame's own
            // step, does not depend on it): lower by the overshoot, then again if needed.
            let spent = if behind {
                self.smoothed.max(seconds)
            } else {
                self.smoothed
            };
            let fits = (f64::from(cap) * budget / spent).floor() as u32;
            let lowered = fits.clamp((cap / 2).max(1), cap - 1);
            if self.since_raise.take().is_some() {
                self.wait = (self.wait * 2).min(MAX_CALM_INTERVALS);
            }
            tracing::debug!(
                "stage 1 takes {:.1} ms of a {:.1} ms frame: sub-frame cap lowered to {lowered} \
                 to keep up (motion = \"flow\"; 1 is linear interpolation; next raise tried \
                 after {} calm frames)",
                spent * 1e3,
                frame * 1e3,
                self.wait
            );
            (self.samples, self.calm) = (0, 0);
            return Some(lowered);
        }
        let calm = if subframed {
            self.smoothed < budget / 2.0
        } else {
            seconds < budget / 2.0 && (self.samples == 0 || self.smoothed < budget / 2.0)
        };
        if calm && cap < most {
            self.calm += 1;
            if self.calm >= self.wait {
                tracing::debug!(
                    "stage 1 has time again: sub-frame cap raised to {}",
                    cap + 1
                );
                (self.samples, self.calm) = (0, 0);
                self.since_raise = Some(0);
                return Some(cap + 1);
            }
        } else {
            self.calm = 0;
        }
        None
    }
}
