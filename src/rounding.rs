//! Rounding of floats to integers without a call into the maths library: x86-64's baseline
//! instructions have no rounding to nearest or up, so `f32::round` and `f64::ceil` are calls
//! (`roundf`, `ceil`), which cost more than the arithmetic around them in per-pixel and
//! per-event loops. Truncation is one instruction and the remainder it leaves is exact, so
//! each function here gives what its `std` spelling gives, for every input.

/// `v.round().clamp(0.0, 65535.0) as u16`: halves away from zero, NaN to 0.
#[inline]
pub fn round_to_u16(v: f32) -> u16 {
    // Saturating: negatives and NaN give 0 (and NaN's remainder compares false).
    let n = v as u32;
    let up = u32::from(v - n as f32 >= 0.5);
    n.saturating_add(up).min(u16::MAX.into()) as u16
}

/// `v.round() as i64`: halves away from zero, NaN to 0, saturating.
#[inline]
pub fn round_to_i64(v: f64) -> i64 {
    let n = v as i64;
    // The remainder's sign is the value's; exact below 2^52, and beyond the value is whole.
    let rest = v - n as f64;
    if rest >= 0.5 {
        n.saturating_add(1)
    } else if rest <= -0.5 {
        n.saturating_sub(1)
    } else {
        n
    }
}

/// `v.ceil() as u32`: negatives and NaN to 0, saturating.
#[inline]
pub fn ceil_to_u32(v: f64) -> u32 {
    let n = v as u32;
    n.saturating_add(u32::from(v > f64::from(n)))
}

/// `v.ceil() as u64`: negatives and NaN to 0, saturating. (Its floor needs no helper:
/// `v.floor() as u64` is `v as u64` for every `v`, truncation being the floor of a non-negative
/// value and both casts saturating.)
#[inline]
pub fn ceil_to_u64(v: f64) -> u64 {
    let n = v as u64;
    n.saturating_add(u64::from(v > n as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values around every half and whole number up to past `top`, specials, and a sweep of
    /// bit patterns of both signs.
    fn cases_f64(top: f64) -> Vec<f64> {
        let mut cases = vec![
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            -0.0,
            f64::MAX,
            f64::MIN,
            4294967295.0,
            4294967296.0,
            4294967295.5,
            9.2e18,
            -9.3e18,
            1e10,
            (1u64 << 52) as f64 + 0.5,
        ];
        for k in -3..(top as i64) {
            for v in [k as f64 + 0.5, k as f64] {
                cases.extend([v, v.next_down(), v.next_up(), -v, -v.next_up()]);
            }
        }
        let step = (top.to_bits() / 50_000).max(1) as usize;
        cases.extend((0..top.to_bits()).step_by(step).map(f64::from_bits));
        cases.extend(
            (0..top.to_bits())
                .step_by(step + 1)
                .map(|b| -f64::from_bits(b)),
        );
        cases
    }

    #[test]
    fn round_to_u16_is_round_then_clamp() {
        let mut cases: Vec<f32> = cases_f64(70_000.0).into_iter().map(|v| v as f32).collect();
        for k in -2..70_000 {
            let h = k as f32 + 0.5;
            cases.extend([h, h.next_down(), h.next_up()]);
        }
        for v in cases {
            let want = v.round().clamp(0.0, 65535.0) as u16;
            assert_eq!(round_to_u16(v), want, "{v:e} ({:#x})", v.to_bits());
        }
    }

    #[test]
    fn round_to_i64_is_round() {
        for v in cases_f64(70_000.0) {
            assert_eq!(
                round_to_i64(v),
                v.round() as i64,
                "{v:e} ({:#x})",
                v.to_bits()
            );
        }
    }

    #[test]
    fn ceil_to_u64_is_ceil_and_truncation_is_floor() {
        let mut cases = cases_f64(70_000.0);
        cases.extend([1.8e19, 1.9e19, u64::MAX as f64, (1u64 << 53) as f64 + 2.0]);
        for v in cases {
            let b = v.to_bits();
            assert_eq!(ceil_to_u64(v), v.ceil() as u64, "{v:e} ({b:#x})");
            assert_eq!(v as u64, v.floor() as u64, "{v:e} ({b:#x})");
            assert_eq!(v as usize, v.floor() as usize, "{v:e} ({b:#x})");
        }
    }

    #[test]
    fn ceil_to_u32_is_ceil() {
        for v in cases_f64(70_000.0) {
            assert_eq!(
                ceil_to_u32(v),
                v.ceil() as u32,
                "{v:e} ({:#x})",
                v.to_bits()
            );
        }
    }
}
