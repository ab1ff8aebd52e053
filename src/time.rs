//! Time as the program counts it: `i64` microseconds, checked where it enters.
//!
//! Two bounds make every later difference and sum of times safe to take with plain
//! arithmetic (which wraps in release builds rather than failing):
//!
//! - every timestamp taken in (frames, events, Python arrays, times parsed from text) lies
//!   within `±`[`MAX_ABS_US`] (2^61 us, about 73,000 years either side of zero: Unix time in
//!   microseconds is ~2^50), so the difference of two of them, or the sum of one and a span,
//!   always fits in `i64`;
//! - a span between two frames, an interval, or a step asked for (`--fps`) is at most
//!   [`MAX_SPAN_US`] (2^53 us, 285 years), so that it is exact as an `f64`, which the pixel
//!   model and the samplers compute with.
//!
//! [`check`] and [`span`] give a clear error naming what was out of range, [`checked_add`] a
//! sum that has to stay in range. (Floats from Python are checked finite and in range before
//! they are cast, in the package's own layer.)

use crate::error::{Error, Result};

/// The largest magnitude of a timestamp the program takes in, in microseconds (2^61).
pub const MAX_ABS_US: i64 = 1 << 61;

/// The longest span between two frames, or of one interval, in microseconds (2^53: exact as
/// an `f64`).
pub const MAX_SPAN_US: i64 = 1 << 53;

/// Whether `t` is a timestamp the program takes (within `±MAX_ABS_US`).
pub fn in_range(t: i64) -> bool {
    (-MAX_ABS_US..=MAX_ABS_US).contains(&t)
}

/// `t` where it is within `±MAX_ABS_US`, else an error naming `what`.
pub fn check(what: &'static str, t: i64) -> Result<i64> {
    if in_range(t) {
        Ok(t)
    } else {
        Err(out_of_range(what, &format!("{t} us")))
    }
}

/// `t1 - t0`, which must be positive and at most `MAX_SPAN_US` (both times in range).
pub fn span(what: &'static str, t0: i64, t1: i64) -> Result<i64> {
    check(what, t0)?;
    check(what, t1)?;
    let d = t1 - t0;
    if d <= 0 {
        return Err(Error::invalid(
            what,
            format!("{t1} us does not come after {t0} us"),
        ));
    }
    if d > MAX_SPAN_US {
        return Err(Error::invalid(
            what,
            format!(
                "{t0} us to {t1} us is {d} us, longer than the {MAX_SPAN_US} us (2^53, 285 years) a span may be"
            ),
        ));
    }
    Ok(d)
}

/// `t + d`, where the sum stays within `±MAX_ABS_US`.
pub fn checked_add(what: &'static str, t: i64, d: i64) -> Result<i64> {
    t.checked_add(d)
        .filter(|&s| in_range(s))
        .ok_or_else(|| out_of_range(what, &format!("{t} + {d} us")))
}

/// The error for a time `value` (with its unit, e.g. `"5 s"`) outside `±`[`MAX_ABS_US`].
pub fn out_of_range(what: &'static str, value: &str) -> Error {
    Error::invalid(
        what,
        format!(
            "{value} is out of range: times must lie within ±{MAX_ABS_US} us (2^61, about 73,000 years)"
        ),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Any two times in range differ, and add to a span, without wrapping.
    #[test]
    fn times_in_range_subtract_and_add_without_wrapping() {
        for t in [-MAX_ABS_US, 0, MAX_ABS_US] {
            assert_eq!(check("t", t).unwrap(), t);
            for u in [-MAX_ABS_US, 0, MAX_ABS_US] {
                assert!(t.checked_sub(u).is_some());
                assert!(t.checked_add(u).is_some());
            }
        }
        for t in [i64::MIN, i64::MAX, MAX_ABS_US + 1, -MAX_ABS_US - 1] {
            let e = check("frame time", t).unwrap_err().to_string();
            assert!(
                e.contains("frame time") && e.contains("out of range"),
                "{e}"
            );
        }
    }

    #[test]
    fn spans_are_positive_and_bounded() {
        assert_eq!(span("s", -5, 5).unwrap(), 10);
        assert_eq!(span("s", 0, MAX_SPAN_US).unwrap(), MAX_SPAN_US);
        assert!(span("s", 0, MAX_SPAN_US + 1).is_err());
        assert!(span("s", 5, 5).is_err());
        assert!(span("s", 6, 5).is_err());
        assert!(span("s", -MAX_ABS_US, MAX_ABS_US).is_err());
        assert!(span("s", i64::MIN, i64::MAX).is_err());
        assert_eq!(checked_add("t", 1, 2).unwrap(), 3);
        assert!(checked_add("t", MAX_ABS_US, 1).is_err());
        assert!(checked_add("t", i64::MAX, 1).is_err());
    }
}
