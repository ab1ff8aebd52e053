//! Chain decoupling: the first step of LDATI (V2CE_SPEC.md 5.1), made robust.
//!
//! A cell's nodes `v_0 .. v_{C-1}` are turned into integer event counts `n_i` for the `K = C - 1`
//! sub-intervals and a *tendency* `d_i` in `[0, 1)`: for a sub-interval holding exactly one event,
//! `d_i` is that event's position inside it, recovered exactly.
//!
//! Written on cumulative sums: with `V_i = v_0 + .. + v_i`, the cumulative count through
//! sub-interval `i` is `M_i = ceil(V_i - tol)` and `d_i = M_i - V_i`. This is the reference's
//! `r = v_i - d; n = ceil(r - 1e-6); d = n - r` recursion without its error build-up, in `f64`
//! with a tolerance that grows with the mass (`1e-6 + 1e-9 V`), so float error can neither invent
//! nor lose an event. The last node folds into the last sub-interval with the total
//! `round(V_{C-1})` rather than the reference's truncation, which drops an event whenever the
//! sum lands a hair below an integer. Counts are never negative.

/// Largest `f64` below 1: keeps a position inside its sub-interval.
pub const ONE_BELOW: f64 = 1.0 - f64::EPSILON / 2.0;

/// The tolerance under which a fractional mass does not make an event.
pub fn tolerance(mass: f64) -> f64 {
    1e-6 + 1e-9 * mass.abs()
}

/// `ceil(mass - tolerance)`, at least 0.
pub fn ceil_count(mass: f64) -> u64 {
    crate::rounding::ceil_to_u64(mass - tolerance(mass))
}

/// The total number of events of a cell whose cumulative masses end with
/// `before_last = V_{C-2}` and `total = V_{C-1}`: `round(total)`, but never fewer than the
/// events the sub-intervals already need.
pub fn total_count(before_last: f64, total: f64) -> u64 {
    ceil_count(before_last).max(total.round().max(0.0) as u64)
}

/// Decouples `nodes` (finite, non-negative, at least 2) into `counts` and `tendency`
/// (each `nodes.len() - 1` long). Returns the total number of events.
pub fn decouple(nodes: &[f64], counts: &mut Vec<u64>, tendency: &mut Vec<f64>) -> u64 {
    let k = nodes.len() - 1;
    counts.clear();
    tendency.clear();
    let mut cum = 0.0;
    let mut before = 0u64;
    for &v in &nodes[..k] {
        cum += v;
        let through = ceil_count(cum).max(before);
        counts.push(through - before);
        tendency.push((through as f64 - cum).clamp(0.0, ONE_BELOW));
        before = through;
    }
    let total = total_count(cum, cum + nodes[k]);
    let extra = total - before;
    if extra > 0 {
        if counts[k - 1] == 0 {
            // The mass sits on the last node, the interval's end.
            tendency[k - 1] = ONE_BELOW;
        }
        counts[k - 1] += extra;
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(nodes: &[f64]) -> (Vec<u64>, Vec<f64>, u64) {
        let (mut c, mut t) = (Vec::new(), Vec::new());
        let n = decouple(nodes, &mut c, &mut t);
        (c, t, n)
    }

    /// V2CE_SPEC Appendix B.2: the ON cell of example 1.
    #[test]
    fn golden_single_events() {
        let (c, t, n) = run(&[1.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert_eq!(c, vec![1, 0, 1, 0, 0, 0, 0, 0, 0]);
        assert_eq!((t[0], t[2], n), (0.0, 0.5, 2));
    }

    /// Appendix B.2, OFF cell: the reference folds node 9 into sub-interval 8 at position 0; the
    /// event belongs at the interval's end, and that is where it goes here.
    #[test]
    fn node_nine_event_is_kept_at_the_end() {
        let mut v = [0.0; 10];
        v[9] = 1.0;
        let (c, t, n) = run(&v);
        assert_eq!(n, 1);
        assert_eq!(c[8], 1);
        assert_eq!(t[8], ONE_BELOW);
    }

    /// Appendix B.4: diffuse mass rounds up to one event at 0.99 of sub-interval 0.
    #[test]
    fn golden_diffuse_inflation() {
        let (c, t, n) = run(&[0.01; 10]);
        assert_eq!(n, 1);
        assert_eq!(c[0], 1);
        assert!((t[0] - 0.99).abs() < 1e-12);
        let (c, t, _) = run(&[0.3, 0.3, 0.3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert_eq!(c.iter().sum::<u64>(), 1);
        assert!((t[0] - 0.7).abs() < 1e-12);
    }

    /// The reference's truncation loses an event when the total is a hair below an integer.
    #[test]
    fn no_truncation_loss() {
        let (_, _, n) = run(&[0.3, 0.7 + 0.4, 0.6 - 1e-12, 0., 0., 0., 0., 0., 0., 1.0]);
        assert_eq!(n, 3);
    }

    #[test]
    fn tiny_values_make_no_event_and_large_ones_are_exact() {
        assert_eq!(run(&[1e-7; 10]).2, 0);
        let mut v = [0.0; 10];
        v[3] = 1e6;
        let (c, _, n) = run(&v);
        assert_eq!((n, c[3]), (1_000_000, 1_000_000));
    }
}
