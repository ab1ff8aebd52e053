//! Bounds on what comes from outside the process: frame and sensor sizes, durations, counts of
//! intervals. Every reader, flag and config key that takes such a value checks it here, before
//! anything is allocated or a loop is started on it, so a hostile file or a typo gets a clear
//! error instead of a panic, an abort for memory, or a run that never ends.

use std::time::Duration;

use crate::error::{Error, Result};

/// The largest frame or sensor side, pixels (8192: twice the widest event sensor published,
/// and beyond any webcam's 4K; a 8192 x 8192 pixel model takes about 2.3 GB).
pub const MAX_SIDE: u32 = 8192;

/// The longest duration or period taken in seconds (about 3.2 years).
pub const MAX_SECONDS: f64 = 1e8;

/// The most frame intervals one evaluation builds (160 MB of intervals).
pub const MAX_INTERVALS: u64 = 10_000_000;

/// Checks a frame or sensor size of `what`: both sides from 1 to [`MAX_SIDE`].
pub fn frame_size(what: &'static str, width: u32, height: u32) -> Result<()> {
    if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
        return Err(Error::invalid(
            what,
            format!("{width} x {height}: each side must be 1 to {MAX_SIDE} pixels"),
        ));
    }
    Ok(())
}

/// A duration of `what` given in seconds: finite, from 0 (when `zero` is allowed; else
/// above 0) to [`MAX_SECONDS`].
pub fn seconds(what: &'static str, value: f64, zero: bool) -> Result<Duration> {
    let low_ok = if zero { value >= 0.0 } else { value > 0.0 };
    if !(value.is_finite() && low_ok && value <= MAX_SECONDS) {
        return Err(Error::invalid(
            what,
            format!(
                "{} s: must be {} to {MAX_SECONDS:e} s",
                number(value),
                if zero { "0" } else { "above 0" }
            ),
        ));
    }
    Ok(Duration::from_secs_f64(value))
}

/// Checks a frame rate of `what`: finite, above 0, at most 1,000,000 fps (frames would share a
/// microsecond), and a period of at most [`MAX_SECONDS`].
pub fn frame_rate(what: &'static str, fps: f64) -> Result<()> {
    if !(fps.is_finite() && fps > 0.0 && fps <= 1e6 && 1.0 / fps <= MAX_SECONDS) {
        return Err(Error::invalid(
            what,
            format!(
                "{} frames per second: must be above {:e} and at most 1,000,000",
                number(fps),
                1.0 / MAX_SECONDS
            ),
        ));
    }
    Ok(())
}

/// `v` as a person reads it: plain, or in scientific notation when huge or tiny.
fn number(v: f64) -> String {
    if v != 0.0 && v.is_finite() && !(1e-4..1e9).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// Checks a count of frame intervals about to be built for `what`.
pub fn intervals(what: &'static str, count: f64) -> Result<()> {
    if !(count.is_finite() && count <= MAX_INTERVALS as f64) {
        return Err(Error::invalid(
            what,
            format!(
                "{count:.0} frame intervals, more than the {MAX_INTERVALS} one run takes; use a \
                 lower rate or a shorter stretch"
            ),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_durations_and_counts_are_bounded() {
        assert!(frame_size("f", 346, 260).is_ok());
        assert!(frame_size("f", 8192, 8192).is_ok());
        for (w, h) in [(0, 1), (1, 0), (8193, 1), (16000, 16000), (65535, 65535)] {
            let e = frame_size("frame", w, h).unwrap_err().to_string();
            assert!(e.contains("8192"), "{e}");
        }
        assert_eq!(
            seconds("d", 1.5, false).unwrap(),
            Duration::from_millis(1500)
        );
        assert_eq!(seconds("d", 0.0, true).unwrap(), Duration::ZERO);
        for v in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e20, 1e308] {
            assert!(seconds("d", v, false).is_err(), "{v}");
        }
        assert!(seconds("d", -0.5, true).is_err());
        assert!(intervals("i", 1e6).is_ok());
        assert!(intervals("i", 3.6e9).is_err());
        assert!(intervals("i", f64::NAN).is_err());
    }
}
