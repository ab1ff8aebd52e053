//! Frame intervals: the time spans between consecutive frames, from REAL frame timestamps.
//!
//! Webcams jitter and drop frames and the DAVIS346 fixture runs at 25 Hz, so nothing here
//! assumes a frame rate unless the user asks for fixed intervals explicitly.

use crate::error::{Error, Result};
use crate::frame::Frame;

/// A half-open time span `[start, end)` in microseconds, with `end > start`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Interval {
    start: i64,
    end: i64,
}

impl Interval {
    /// Creates `[start, end)`; fails unless `end > start`, both lie within
    /// `±`[`crate::time::MAX_ABS_US`] and the span is at most [`crate::time::MAX_SPAN_US`] (so
    /// that its length, and any offset in it, is exact as an `f64`).
    pub fn new(start: i64, end: i64) -> Result<Self> {
        if end <= start {
            return Err(Error::invalid(
                "interval",
                format!("end {end} us is not after start {start} us"),
            ));
        }
        crate::time::span("interval", start, end)?;
        Ok(Interval { start, end })
    }

    /// First microsecond of the interval.
    pub fn start(&self) -> i64 {
        self.start
    }

    /// First microsecond after the interval.
    pub fn end(&self) -> i64 {
        self.end
    }

    /// Length in microseconds (always at least 1).
    pub fn duration_us(&self) -> i64 {
        self.end - self.start
    }

    /// Whether `t` lies in `[start, end)`.
    pub fn contains(&self, t: i64) -> bool {
        t >= self.start && t < self.end
    }

    /// Converts an offset from `start` in microseconds (any float) to a timestamp inside the
    /// interval: rounded to the nearest microsecond and clamped to `[start, end - 1]`.
    /// A non-finite offset maps to `start`.
    pub fn timestamp_at(&self, offset_us: f64) -> i64 {
        let last = (self.end - self.start - 1) as f64;
        let off = if offset_us.is_finite() {
            offset_us.round().clamp(0.0, last)
        } else {
            0.0
        };
        self.start + off as i64
    }
}

/// The intervals between consecutive frame times.
///
/// Frame times must be strictly increasing; a repeated or backwards time is an error (it would
/// give an empty or negative interval), reported with its index.
pub fn intervals_from_frames(frame_times: &[i64]) -> Result<Vec<Interval>> {
    frame_times
        .windows(2)
        .enumerate()
        .map(|(i, w)| {
            Interval::new(w[0], w[1]).map_err(|e| {
                if w[1] > w[0] {
                    // Far enough apart to be out of range: say so.
                    return e;
                }
                Error::invalid(
                    "frame times",
                    format!(
                        "frame {} at {} us does not come after frame {} at {} us",
                        i + 1,
                        w[1],
                        i,
                        w[0]
                    ),
                )
            })
        })
        .collect()
}

/// The intervals between consecutive `frames`, by their times (as [`intervals_from_frames`]).
pub fn intervals_between(frames: &[Frame]) -> Result<Vec<Interval>> {
    let times: Vec<i64> = frames.iter().map(|f| f.t).collect();
    intervals_from_frames(&times)
}

/// Fixed-rate intervals covering `[first, last]` at `fps` frames per second.
///
/// Boundaries sit at `first + floor(i * 1e6 / fps)` microseconds (the reference's
/// `trunc(i * 1e6 / fps)` offsets), computed from `i` each time, so a rate like 29.97 does not
/// accumulate drift. The last interval is the one that contains `last`.
pub fn fixed_intervals(first: i64, last: i64, fps: f64) -> Result<Vec<Interval>> {
    crate::limits::frame_rate("fps", fps)?;
    if last < first {
        return Ok(Vec::new());
    }
    // Both in range, so the span and every boundary up to one period past `last` fit.
    crate::time::check("first time", first)?;
    crate::time::check("last time", last)?;
    let period = 1e6 / fps;
    crate::limits::intervals("fps", ((last as f64 - first as f64) / period).floor() + 1.0)?;
    let boundary = |i: u64| first + (i as f64 * period).floor() as i64;
    let mut out = Vec::new();
    let mut i = 0u64;
    loop {
        let (a, b) = (boundary(i), boundary(i + 1));
        out.push(Interval::new(a, b.max(a + 1))?);
        if b > last {
            return Ok(out);
        }
        i += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn intervals_follow_real_frame_times() {
        let iv = intervals_from_frames(&[0, 40_000, 80_500, 120_000]).unwrap();
        assert_eq!(iv.len(), 3);
        assert_eq!(iv[1].start(), 40_000);
        assert_eq!(iv[1].duration_us(), 40_500);
    }

    #[test]
    fn repeated_frame_time_is_an_error() {
        let err = intervals_from_frames(&[0, 10, 10]).unwrap_err();
        assert!(err.to_string().contains("frame 2"), "{err}");
    }

    #[test]
    fn intervals_between_frames_follow_their_times() {
        let frame = |t| Frame {
            t,
            width: 1,
            height: 1,
            luma: vec![0],
            exposure_us: None,
        };
        let iv = intervals_between(&[frame(5), frame(40), frame(90)]).unwrap();
        assert_eq!(iv, intervals_from_frames(&[5, 40, 90]).unwrap());
        assert!(intervals_between(&[frame(5), frame(5)]).is_err());
        assert!(intervals_between(&[frame(5)]).unwrap().is_empty());
    }

    #[test]
    fn fixed_intervals_match_golden_offsets() {
        // V2CE_SPEC Appendix B.9: trunc(i * 1e6 / 30).
        let iv = fixed_intervals(0, 170_000, 30.0).unwrap();
        let starts: Vec<i64> = iv.iter().map(|i| i.start()).collect();
        assert_eq!(starts, vec![0, 33_333, 66_666, 100_000, 133_333, 166_666]);
        assert!(iv.last().unwrap().contains(170_000));
        // 29.97 fps over an hour drifts by no more than rounding.
        let iv = fixed_intervals(0, 3_600_000_000, 29.97).unwrap();
        assert_eq!(iv.len(), 107_893);
    }

    #[test]
    fn bad_rates_are_rejected() {
        for fps in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(fixed_intervals(0, 10, fps).is_err());
        }
    }

    #[test]
    fn timestamp_at_stays_inside() {
        let iv = Interval::new(1 << 40, (1 << 40) + 100).unwrap();
        assert_eq!(iv.timestamp_at(-5.0), 1 << 40);
        assert_eq!(iv.timestamp_at(99.7), (1 << 40) + 99);
        assert_eq!(iv.timestamp_at(f64::NAN), 1 << 40);
        assert_eq!(iv.timestamp_at(42.4), (1 << 40) + 42);
    }
}
