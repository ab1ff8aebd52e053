//! Replaying recorded frames at their own pace, and sleeping in a way a shutdown can cut short.

use std::time::{Duration, Instant};

/// Sleeps for `duration` in slices, returning early (with `false`) once `stop()` says so.
pub fn sleep_unless(duration: Duration, stop: &dyn Fn() -> bool) -> bool {
    let end = Instant::now() + duration;
    loop {
        if stop() {
            return false;
        }
        let now = Instant::now();
        if now >= end {
            return true;
        }
        std::thread::sleep((end - now).min(Duration::from_millis(20)));
    }
}

/// Holds each frame back until its time comes: frame `t` (us) is released at
/// `origin + (t - t_origin) / speed`. A source that falls behind by more than `max_lag` (a
/// pipeline that blocked, a slow decoder) is re-anchored instead of catching up in a burst,
/// as a camera would.
#[derive(Debug, Clone)]
pub struct Pacer {
    speed: f64,
    max_lag: Duration,
    origin: Option<(i64, Instant)>,
    /// Times the schedule was re-anchored.
    pub reanchored: u64,
}

impl Pacer {
    /// A pacer replaying at `speed` times real time (1.0: real time).
    pub fn new(speed: f64) -> Self {
        Pacer {
            speed,
            max_lag: Duration::from_millis(250),
            origin: None,
            reanchored: 0,
        }
    }

    /// When frame `t` is due.
    pub fn due(&mut self, t: i64) -> Instant {
        let now = Instant::now();
        let (t0, i0) = *self.origin.get_or_insert((t, now));
        let offset = (t - t0).max(0) as f64 / self.speed;
        let due = i0 + Duration::from_micros(offset as u64);
        if now > due + self.max_lag {
            self.origin = Some((t, now));
            self.reanchored += 1;
            return now;
        }
        due
    }

    /// Waits until frame `t` is due; `false` when `stop()` cut the wait short.
    pub fn wait(&mut self, t: i64, stop: &dyn Fn() -> bool) -> bool {
        let due = self.due(t);
        sleep_unless(due.saturating_duration_since(Instant::now()), stop)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_are_due_at_their_time_over_the_speed() {
        let mut p = Pacer::new(2.0);
        let start = p.due(1_000_000);
        let later = p.due(1_500_000);
        let d = later - start;
        assert!((d.as_secs_f64() - 0.25).abs() < 0.01, "{d:?}");
    }

    #[test]
    fn a_late_source_is_reanchored() {
        let mut p = Pacer::new(1000.0);
        p.due(0);
        std::thread::sleep(Duration::from_millis(300));
        // Frame at 1 ms was due 1 us after the start, 300 ms ago.
        let due = p.due(1_000);
        assert!(due + Duration::from_millis(50) > Instant::now());
        assert_eq!(p.reanchored, 1);
    }

    #[test]
    fn stop_cuts_a_sleep_short() {
        let t = Instant::now();
        assert!(!sleep_unless(Duration::from_secs(5), &|| true));
        assert!(t.elapsed() < Duration::from_secs(1));
        assert!(sleep_unless(Duration::from_millis(1), &|| false));
    }
}
