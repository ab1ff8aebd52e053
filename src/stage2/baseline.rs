//! The V2CE baselines (V2CE_SPEC.md 5.7): each of the `C` nodes is read as a half-open bin of
//! width `T / C` starting at `c T / C`; a node value `v` gives `floor(v)` events plus one more with
//! probability `frac(v)` (a Bernoulli draw). `Even` spaces them at `j / (n + 1)` of the bin,
//! `Random` draws them uniformly. The bins do not line up with the voxel's nodes (node `c` sits at
//! `c T / (C - 1)`); that mismatch is part of what the baselines are measured with.

use rand::Rng;

use super::{CellRng, Sampler, Scratch};

/// Floor + Bernoulli counts, evenly spaced inside each bin.
#[derive(Debug, Clone, Copy)]
pub struct Even {
    /// Seed of the Bernoulli draws.
    pub seed: u64,
}

/// Floor + Bernoulli counts, uniformly placed inside each bin.
#[derive(Debug, Clone, Copy)]
pub struct Random {
    /// Seed of the draws.
    pub seed: u64,
}

/// Visits every bin: `visit(rng, bin_start, bin_width, whole, n)` where `whole = floor(v)` and
/// `n` is `whole` plus the Bernoulli event (drawn with probability `v - whole`).
fn for_each_bin(
    nodes: &[f64],
    rng: &mut CellRng,
    mut visit: impl FnMut(&mut CellRng, f64, f64, u64, u64),
) {
    let c = nodes.len() as f64;
    let width = (c - 1.0) / c;
    for (i, &v) in nodes.iter().enumerate() {
        let whole = v.floor();
        let extra = rng.gen::<f64>() < v - whole;
        visit(
            rng,
            i as f64 * width,
            width,
            whole as u64,
            whole as u64 + extra as u64,
        );
    }
}

impl Sampler for Even {
    fn name(&self) -> &'static str {
        "even"
    }

    fn seed(&self) -> u64 {
        self.seed
    }

    fn sample_cell(&self, nodes: &[f64], rng: &mut CellRng, _: &mut Scratch, out: &mut Vec<f64>) {
        // The j-th event (the Bernoulli one last) at j / (whole + 1) of the bin.
        for_each_bin(nodes, rng, |_, start, width, whole, n| {
            let step = width / (whole + 1) as f64;
            out.extend((0..n).map(|j| start + j as f64 * step));
        });
    }
}

impl Sampler for Random {
    fn name(&self) -> &'static str {
        "random"
    }

    fn seed(&self) -> u64 {
        self.seed
    }

    fn sample_cell(&self, nodes: &[f64], rng: &mut CellRng, _: &mut Scratch, out: &mut Vec<f64>) {
        for_each_bin(nodes, rng, |rng, start, width, _, n| {
            out.extend((0..n).map(|_| start + rng.gen::<f64>() * width));
        });
    }
}
