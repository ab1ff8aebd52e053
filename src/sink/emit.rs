//! Emission at event time: the wall-clock instant at which each event is due, so that a network
//! sink spreads a frame interval's events over the interval as a real sensor would, instead of
//! sending them in one burst when the interval closes.
//!
//! The clock is anchored on the first batch: the frame that closed it (its time `t0`, the
//! instant it was captured `c0`). An event at time `t` is then due at
//! `c0 + delay + (t - t0) / speed`, where `speed` is the replay speed (1 for a camera). An event
//! at the start of an interval can only be known when the interval closes, so `delay` must cover
//! one frame interval (a window's `stride` intervals for the learned tier) plus the pipeline's
//! processing time; events that come later than their due time are counted as late, never
//! reordered, and catch up at twice the stream's rate (see [`super::udp`]). When an event is
//! more than [`EmitClock::REANCHOR`] late (the pipeline stalled, or a replay runs slower than
//! real time), the clock is anchored again on it, counted, so one stall does not turn the rest
//! of the run into a burst.

use std::time::{Duration, Instant};

/// The times at which events are due.
#[derive(Debug, Clone)]
pub struct EmitClock {
    delay: Duration,
    speed: f64,
    anchor: Option<(i64, Instant)>,
    /// Times the clock was anchored again after a stall.
    pub reanchors: u64,
}

impl EmitClock {
    /// An event later than this is taken as a stall: the clock starts over from it.
    pub const REANCHOR: Duration = Duration::from_secs(1);

    /// A clock `delay` behind the frames, whose times run `speed` times faster than the wall
    /// clock (a replay at that speed).
    pub fn new(delay: Duration, speed: f64) -> Self {
        EmitClock {
            delay,
            speed: if speed.is_finite() && speed > 0.0 {
                speed
            } else {
                1.0
            },
            anchor: None,
            reanchors: 0,
        }
    }

    /// The delay behind the frames.
    pub fn delay(&self) -> Duration {
        self.delay
    }

    /// Anchors the clock on the frame that closed the first batch (later calls do nothing).
    pub fn anchor(&mut self, frame_t: i64, captured: Instant) {
        self.anchor.get_or_insert((frame_t, captured));
    }

    /// When the event at `t` is due (`None` before the clock is anchored). Events of the
    /// interval the anchoring frame closed come before it and are due before `c0 + delay`,
    /// spread as the others; nothing is due before the anchor instant itself.
    pub fn due(&self, t: i64) -> Option<Instant> {
        let (t0, c0) = self.anchor?;
        let at = c0 + self.delay;
        let span = |us: i64| self.wall(us);
        Some(if t >= t0 {
            at + span(t.saturating_sub(t0))
        } else {
            at.checked_sub(span(t0.saturating_sub(t)))
                .map_or(c0, |d| d.max(c0))
        })
    }

    /// The wall-clock time that `us` microseconds of event time (at least 0) take: integer
    /// arithmetic in real time (speed 1), one multiplication otherwise. Beyond ~30 years a
    /// time is nonsense; the arithmetic stays finite.
    fn wall(&self, us: i64) -> Duration {
        const MOST_US: u64 = 1_000_000_000 * 1_000_000;
        let us = (us.max(0) as u64).min(MOST_US);
        if self.speed == 1.0 {
            Duration::from_micros(us)
        } else {
            Duration::from_nanos((us as f64 * 1e3 / self.speed).min(MOST_US as f64 * 1e3) as u64)
        }
    }

    /// The event time, us, that a wall-clock `span` covers (at least 0): the events within it
    /// of a first one are due within `span` of it.
    pub fn event_span(&self, span: Duration) -> i64 {
        (span.as_nanos() as f64 * self.speed / 1e3).min(i64::MAX as f64 / 2.0) as i64
    }

    /// The due time of the event at `t`, after anchoring the clock again on it when it is more
    /// than [`EmitClock::REANCHOR`] late at `now`.
    pub fn due_at(&mut self, t: i64, now: Instant) -> Option<Instant> {
        let due = self.due(t)?;
        if now.saturating_duration_since(due) > Self::REANCHOR {
            // The event is due now: as if its frame had just been captured `delay` ago.
            self.anchor = Some((t, now.checked_sub(self.delay).unwrap_or(now)));
            self.reanchors += 1;
            return self.due(t);
        }
        Some(due)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn events_are_due_at_their_time_plus_the_delay() {
        let c0 = Instant::now();
        let mut clock = EmitClock::new(Duration::from_millis(100), 1.0);
        assert!(clock.due(5).is_none());
        clock.anchor(1_000_000, c0);
        clock.anchor(9_000_000, c0 + Duration::from_secs(3)); // ignored: anchored once
        assert_eq!(clock.due(1_000_000), Some(c0 + Duration::from_millis(100)));
        assert_eq!(clock.due(1_033_000), Some(c0 + Duration::from_millis(133)));
        // Before the anchor (the interval its frame closed): spread the same way, but never
        // before the anchor instant.
        assert_eq!(clock.due(990_000), Some(c0 + Duration::from_millis(90)));
        assert_eq!(clock.due(0), Some(c0));
        // A replay at 10x: 1 s of events in 100 ms.
        let mut fast = EmitClock::new(Duration::ZERO, 10.0);
        fast.anchor(0, c0);
        assert_eq!(fast.due(1_000_000), Some(c0 + Duration::from_millis(100)));
        // Nonsense speeds fall back to real time; huge times stay finite.
        let mut odd = EmitClock::new(Duration::ZERO, f64::NAN);
        odd.anchor(0, c0);
        assert_eq!(odd.due(2_000), Some(c0 + Duration::from_millis(2)));
        assert!(odd.due(i64::MAX).is_some());
        assert!(odd.due(i64::MIN).is_some());
        // A wall-clock slice covers speed times as much event time.
        assert_eq!(clock.event_span(Duration::from_micros(500)), 500);
        assert_eq!(fast.event_span(Duration::from_micros(500)), 5_000);
        // The integer path of real time and the multiplication of a replay agree.
        let mut half = EmitClock::new(Duration::ZERO, 0.5);
        half.anchor(0, c0);
        assert_eq!(half.due(1_000), Some(c0 + Duration::from_millis(2)));
    }

    #[test]
    fn a_stall_reanchors_once_and_keeps_the_order() {
        let c0 = Instant::now();
        let mut clock = EmitClock::new(Duration::from_millis(50), 1.0);
        clock.anchor(0, c0);
        // 0.5 s late: within the limit, due time unchanged (sent on catching up, counted late).
        let now = c0 + Duration::from_millis(550 + 10);
        assert_eq!(clock.due_at(10_000, now), clock.due(10_000));
        assert_eq!(clock.reanchors, 0);
        // 5 s late: anchored again, due now; the next events follow from there.
        let now = c0 + Duration::from_secs(6);
        let due = clock.due_at(1_000_000, now).unwrap();
        assert_eq!(due, now);
        assert_eq!(clock.reanchors, 1);
        assert_eq!(clock.due(1_010_000), Some(now + Duration::from_millis(10)));
    }
}
