//! LDATI (V2CE_SPEC.md 5.1 - 5.4, 5.9 in its robust form): chain decoupling, then
//! - Type 1 (a sub-interval with one event): the event at its decoupled position, exactly;
//! - Type 2 (two or more): that many events drawn inside the sub-interval, uniformly
//!   (`ldati-random`, with the reference's missing scaling by the sub-interval fixed) or from the
//!   local linear density fitted on neighbouring counts (`ldati`, the paper's choice).
//!
//! The slope follows the reference: `s_i = (n_{i+1} - n_{i-1}) / 2` on the decoupled counts with
//! reflected ends (so the first and last sub-intervals are uniform), normalised by the centre
//! count. In sub-interval units the density is `g(x) = kappa x + beta` on `[0, 1]` with
//! `kappa = s_i / n_i` clamped to `[-2, 2]` (a valid density) and `beta = 1 - kappa / 2`; it is
//! inverted with the cancellation-free `x = 2u / (beta + sqrt(beta^2 + 2 kappa u))`, the
//! discriminant clamped at 0. No branch on `kappa == 0`: the formula gives `x = u` there.

use rand::Rng;

use super::chain::{decouple, ONE_BELOW};
use super::{CellRng, Sampler, Scratch};

/// How Type 2 sub-intervals place their events.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Type2 {
    /// Uniformly inside the sub-interval.
    Uniform,
    /// From the local linear density.
    Slope,
}

/// The LDATI sampler.
#[derive(Debug, Clone, Copy)]
pub struct Ldati {
    /// Seed of the Type 2 draws.
    pub seed: u64,
    /// Type 2 placement.
    pub type2: Type2,
}

/// The inverse CDF of the linear density with slope `kappa` (clamped to `[-2, 2]`) on `[0, 1]`,
/// at `u` in `[0, 1]`; the result is in `[0, 1)`.
pub fn linear_inverse_cdf(kappa: f64, u: f64) -> f64 {
    let kappa = if kappa.is_finite() {
        kappa.clamp(-2.0, 2.0)
    } else {
        0.0
    };
    let beta = 1.0 - kappa / 2.0;
    let disc = (beta * beta + 2.0 * kappa * u).max(0.0);
    let denom = beta + disc.sqrt();
    let x = if denom > 0.0 { 2.0 * u / denom } else { 0.0 };
    if x.is_finite() {
        x.clamp(0.0, ONE_BELOW)
    } else {
        0.0
    }
}

/// The slope of sub-interval `i` from the decoupled counts, in sub-interval units (`kappa`).
pub fn local_slope(counts: &[u64], i: usize) -> f64 {
    let k = counts.len();
    let at = |j: isize| -> f64 {
        // Reflection without repeating the edge: n_{-1} = n_1, n_K = n_{K-2}.
        let j = if j < 0 {
            -j
        } else if j >= k as isize {
            2 * (k as isize - 1) - j
        } else {
            j
        };
        counts[j.clamp(0, k as isize - 1) as usize] as f64
    };
    let s = (at(i as isize + 1) - at(i as isize - 1)) / 2.0;
    s / counts[i].max(1) as f64
}

impl Sampler for Ldati {
    fn name(&self) -> &'static str {
        match self.type2 {
            Type2::Uniform => "ldati-random",
            Type2::Slope => "ldati",
        }
    }

    fn seed(&self) -> u64 {
        self.seed
    }

    fn sample_cell(
        &self,
        nodes: &[f64],
        rng: &mut CellRng,
        scratch: &mut Scratch,
        out: &mut Vec<f64>,
    ) {
        decouple(nodes, &mut scratch.counts, &mut scratch.tendency);
        for (i, (&n, &d)) in scratch.counts.iter().zip(&scratch.tendency).enumerate() {
            let base = i as f64;
            match n {
                0 => {}
                1 => out.push(base + d),
                _ => {
                    let kappa = match self.type2 {
                        Type2::Uniform => 0.0,
                        Type2::Slope => local_slope(&scratch.counts, i),
                    };
                    for _ in 0..n {
                        out.push(base + linear_inverse_cdf(kappa, rng.gen::<f64>()));
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// V2CE_SPEC Appendix B.5: counts (0, 2, 4), u = 0.5 -> 2289.0148 us at 30 fps.
    #[test]
    fn golden_slope_sample() {
        let counts = [0, 2, 4, 0, 0, 0, 0, 0, 0];
        let kappa = local_slope(&counts, 1);
        assert_eq!(kappa, 1.0);
        let delta_us = 1e6 / 270.0;
        let t = linear_inverse_cdf(kappa, 0.5) * delta_us;
        assert!((t - 2289.0148).abs() < 1e-3, "{t}");
        // First and last sub-intervals are uniform (reflection).
        assert_eq!(local_slope(&[5, 2, 0, 0, 0, 0, 0, 0, 3], 0), 0.0);
        assert_eq!(local_slope(&[5, 2, 0, 0, 0, 0, 0, 1, 3], 8), 0.0);
    }

    /// V2CE_SPEC Appendix B.2 end to end: the voxel of example 1 sampled over a 30 fps interval.
    /// The ON events come back at 0 and 2.5 delta = 9259 us. The OFF event on node 9 is the
    /// interval's end: the reference emits it at 8 delta (29629 us), here it stays at the end
    /// (the last microsecond of the interval).
    /// Appendix B.4: diffuse mass 0.01 on every node is one event at 0.99 delta = 3666.67 us,
    /// which the reference truncates to 3666 and this port rounds to 3667.
    #[test]
    fn golden_timestamps() {
        use crate::{voxelize, Event, Interval, VoxelGrid};
        let events = [
            Event::new(0, 0, 0, true),
            Event::new(500, 0, 0, true),
            Event::new(1800, 1, 0, false),
        ];
        let grid = voxelize(&events, Interval::new(0, 1800).unwrap(), 2, 1, 10).unwrap();
        let frame = Interval::new(0, 33_333).unwrap();
        for type2 in [Type2::Slope, Type2::Uniform] {
            let mut out = Vec::new();
            Ldati { seed: 0, type2 }.sample(&grid, frame, &mut out);
            let got: Vec<_> = out.iter().map(|e| (e.t, e.x, e.on)).collect();
            assert_eq!(got, vec![(0, 0, true), (9259, 0, true), (33_332, 1, false)]);
        }
        let mut diffuse = VoxelGrid::new(1, 1, 10).unwrap();
        diffuse.push_cell(0, 0, true, &[0.01; 10]).unwrap();
        let mut out = Vec::new();
        Ldati {
            seed: 0,
            type2: Type2::Slope,
        }
        .sample(&diffuse, frame, &mut out);
        assert_eq!(out, vec![Event::new(3667, 0, 0, true)]);
    }

    #[test]
    fn inverse_cdf_is_stable_and_bounded() {
        for &kappa in &[
            0.0,
            1e-300,
            -1e-12,
            1e-6,
            1.999,
            2.0,
            -2.0,
            5.0,
            -7.0,
            f64::NAN,
        ] {
            for i in 0..=1000 {
                let u = i as f64 / 1000.0;
                let x = linear_inverse_cdf(kappa, u);
                assert!((0.0..1.0).contains(&x), "kappa {kappa} u {u} -> {x}");
            }
        }
        // Tiny slopes give the uniform answer without cancellation.
        assert!((linear_inverse_cdf(1e-12, 0.3) - 0.3).abs() < 1e-12);
        // The CDF is inverted: G(x) = kappa x^2 / 2 + beta x.
        let (k, u) = (1.5, 0.37);
        let x = linear_inverse_cdf(k, u);
        assert!((k * x * x / 2.0 + (1.0 - k / 2.0) * x - u).abs() < 1e-12);
    }
}
