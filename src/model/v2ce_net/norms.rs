//! Resolving spectral norm and BatchNorm into plain convolution weights: the sigma a
//! spectral-norm convolution divides by (see [`SpectralNorm`]) and the folding of an eval-mode
//! BatchNorm into the convolution before it.

use crate::{Error, Result};

/// BatchNorm's epsilon (PyTorch's default, used by the reference).
pub const BN_EPS: f64 = 1e-5;
/// The epsilon of the reference spectral norm's `n(z) = z / (|z| + eps)`.
pub const SN_EPS: f64 = 1e-12;

/// How a spectral-norm convolution's sigma is resolved from `weight_bar`, `weight_u`, `weight_v`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum SpectralNorm {
    /// What the reference's first forward call after loading does (spec §3.2, Appendix A): from
    /// the stored u, `v = n(Wᵀu)`, `u' = n(W v)`, `sigma = u'ᵀ W v`, in f64.
    PowerIteration,
    /// `sigma = uᵀ W v` with the stored u and v as they are (wrong unless they are converged; kept
    /// to show that the parity test notices).
    Stored,
    /// The true largest singular value of W (slow; also differs from what the reference computes).
    Exact,
}

impl SpectralNorm {
    /// Every mode.
    pub const ALL: [SpectralNorm; 3] = [
        SpectralNorm::PowerIteration,
        SpectralNorm::Stored,
        SpectralNorm::Exact,
    ];

    /// The mode's name (`power-iteration`, `stored`, `exact`).
    pub fn name(self) -> &'static str {
        match self {
            SpectralNorm::PowerIteration => "power-iteration",
            SpectralNorm::Stored => "stored",
            SpectralNorm::Exact => "exact",
        }
    }
}

impl std::fmt::Display for SpectralNorm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for SpectralNorm {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        SpectralNorm::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = SpectralNorm::ALL.iter().map(|m| m.name()).collect();
                Error::invalid(
                    "spectral norm mode",
                    format!("{s:?} (expected one of {})", names.join(", ")),
                )
            })
    }
}

/// BatchNorm (eval) folded into the preceding convolution, in f64: returns `(scale, shift)` with
/// `scale = γ/√(var+ε)` multiplying the weights of the output channel and `shift = (b − mean)·scale
/// + β` its new bias (`b` the convolution's bias, 0 without one). `None` when `var + ε ≤ 0`.
pub fn fold_batch_norm(b: f64, gamma: f32, beta: f32, mean: f32, var: f32) -> Option<(f64, f64)> {
    let denom = f64::from(var) + BN_EPS;
    if denom.is_nan() || denom <= 0.0 {
        return None;
    }
    let scale = f64::from(gamma) / denom.sqrt();
    Some((scale, (b - f64::from(mean)) * scale + f64::from(beta)))
}

/// The sigma a spectral-norm convolution divides `weight_bar` by, viewed as a `rows x cols`
/// row-major matrix W, with the stored `u` (length rows) and `v` (length cols). Computed in f64.
///
/// # Panics
///
/// When `w` holds fewer than `rows * cols` values or `u`, `v` are shorter than stated.
pub fn spectral_sigma(
    mode: SpectralNorm,
    w: &[f32],
    rows: usize,
    cols: usize,
    u: &[f32],
    v: &[f32],
) -> f64 {
    match mode {
        SpectralNorm::PowerIteration => {
            // v = n(Wᵀu)
            let mut wtu = vec![0f64; cols];
            for (r, &ur) in u.iter().enumerate().take(rows) {
                let ur = f64::from(ur);
                for (acc, &x) in wtu.iter_mut().zip(&w[r * cols..(r + 1) * cols]) {
                    *acc += f64::from(x) * ur;
                }
            }
            let norm = wtu.iter().map(|x| x * x).sum::<f64>().sqrt();
            wtu.iter_mut().for_each(|x| *x /= norm + SN_EPS);
            // u' = n(W v); sigma = u'ᵀ W v = |Wv|² / (|Wv| + eps)
            let wv = mat_vec(w, rows, cols, &wtu);
            let norm_sq: f64 = wv.iter().map(|x| x * x).sum();
            norm_sq / (norm_sq.sqrt() + SN_EPS)
        }
        SpectralNorm::Stored => {
            let v64: Vec<f64> = v.iter().map(|&x| f64::from(x)).collect();
            mat_vec(w, rows, cols, &v64)
                .iter()
                .zip(u)
                .map(|(a, &b)| a * f64::from(b))
                .sum()
        }
        SpectralNorm::Exact => largest_singular_value(w, rows, cols),
    }
}

fn mat_vec(w: &[f32], rows: usize, cols: usize, v: &[f64]) -> Vec<f64> {
    (0..rows)
        .map(|r| {
            w[r * cols..(r + 1) * cols]
                .iter()
                .zip(v)
                .map(|(&a, b)| f64::from(a) * b)
                .sum()
        })
        .collect()
}

/// The largest singular value of a `rows x cols` matrix, in f64: the Gram matrix of the smaller
/// side, raised to the power 2^14 by repeated squaring (so the top eigenvector dominates even when
/// the spectrum's gap is small), then a Rayleigh quotient refined by a few power steps.
///
/// # Panics
///
/// When `w` holds fewer than `rows * cols` values.
pub fn largest_singular_value(w: &[f32], rows: usize, cols: usize) -> f64 {
    let n = rows.min(cols);
    if n == 0 {
        return 0.0;
    }
    let mut gram = vec![0f64; n * n];
    if rows <= cols {
        let w64: Vec<f64> = w.iter().map(|&x| f64::from(x)).collect();
        for i in 0..n {
            let ri = &w64[i * cols..(i + 1) * cols];
            for j in i..n {
                let rj = &w64[j * cols..(j + 1) * cols];
                let d: f64 = ri.iter().zip(rj).map(|(a, b)| a * b).sum();
                gram[i * n + j] = d;
                gram[j * n + i] = d;
            }
        }
    } else {
        for r in 0..rows {
            let row = &w[r * cols..(r + 1) * cols];
            for i in 0..n {
                let a = f64::from(row[i]);
                for j in i..n {
                    gram[i * n + j] += a * f64::from(row[j]);
                }
            }
        }
        for i in 0..n {
            for j in 0..i {
                gram[i * n + j] = gram[j * n + i];
            }
        }
    }
    let trace = |m: &[f64]| (0..n).map(|i| m[i * n + i]).sum::<f64>();
    let mut m = gram.clone();
    let mut tmp = vec![0f64; n * n];
    for _ in 0..14 {
        let t = trace(&m);
        if !(t.is_finite() && t > 0.0) {
            return 0.0;
        }
        m.iter_mut().for_each(|x| *x /= t);
        tmp.iter_mut().for_each(|x| *x = 0.0);
        for i in 0..n {
            for k in 0..n {
                let a = m[i * n + k];
                if a == 0.0 {
                    continue;
                }
                let (row_k, out_i) = (&m[k * n..(k + 1) * n], &mut tmp[i * n..(i + 1) * n]);
                for (o, &b) in out_i.iter_mut().zip(row_k) {
                    *o += a * b;
                }
            }
        }
        std::mem::swap(&mut m, &mut tmp);
    }
    // The column with the largest diagonal entry is (nearly) the top eigenvector.
    let j = (0..n)
        .max_by(|&a, &b| m[a * n + a].total_cmp(&m[b * n + b]))
        .unwrap_or(0);
    let mut x: Vec<f64> = (0..n).map(|i| m[i * n + j]).collect();
    let mut lambda = 0.0;
    for _ in 0..8 {
        let norm = x.iter().map(|a| a * a).sum::<f64>().sqrt();
        if norm == 0.0 {
            return 0.0;
        }
        x.iter_mut().for_each(|a| *a /= norm);
        let gx: Vec<f64> = (0..n)
            .map(|i| {
                gram[i * n..(i + 1) * n]
                    .iter()
                    .zip(&x)
                    .map(|(a, b)| a * b)
                    .sum()
            })
            .collect();
        lambda = x.iter().zip(&gx).map(|(a, b)| a * b).sum::<f64>();
        x = gx;
    }
    lambda.max(0.0).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn power_iteration_sigma_by_hand() {
        // W = diag(3, 2, 1), u = (1, 1, 1): v = n(3, 2, 1), W v = (9, 4, 1)/√14,
        // sigma = |W v| = √(98/14) = √7 (less the epsilons).
        let w = [3.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0];
        let s = spectral_sigma(
            SpectralNorm::PowerIteration,
            &w,
            3,
            3,
            &[1.0, 1.0, 1.0],
            &[0.0; 3],
        );
        assert!((s - 7f64.sqrt()).abs() < 1e-9, "{s}");
        // Stored: uᵀ W v with u = (1, 0, 0), v = (0.5, 1, 1) gives 1.5.
        let s = spectral_sigma(
            SpectralNorm::Stored,
            &w,
            3,
            3,
            &[1.0, 0.0, 0.0],
            &[0.5, 1.0, 1.0],
        );
        assert!((s - 1.5).abs() < 1e-12, "{s}");
        // Exact: the largest singular value, 3.
        let s = spectral_sigma(SpectralNorm::Exact, &w, 3, 3, &[1.0; 3], &[1.0; 3]);
        assert!((s - 3.0).abs() < 1e-9, "{s}");
    }

    #[test]
    fn exact_sigma_of_a_wide_and_a_tall_matrix() {
        // [[1, 1, 0], [0, 0, 2]] has singular values 2 and √2; the transpose has the same.
        let wide = [1.0, 1.0, 0.0, 0.0, 0.0, 2.0];
        let tall = [1.0, 0.0, 1.0, 0.0, 0.0, 2.0];
        assert!((largest_singular_value(&wide, 2, 3) - 2.0).abs() < 1e-9);
        assert!((largest_singular_value(&tall, 3, 2) - 2.0).abs() < 1e-9);
        // A close gap (1 and 0.999) still converges to the larger.
        let near = [1.0, 0.0, 0.0, 0.999];
        assert!((largest_singular_value(&near, 2, 2) - 1.0).abs() < 1e-9);
    }

    #[test]
    fn batch_norm_folding_by_hand() {
        // γ = 3, var = 4 - eps: scale 1.5; b = 1, mean = 0.25, β = 0.5: shift 0.75*1.5 + 0.5.
        let (scale, shift) = fold_batch_norm(1.0, 3.0, 0.5, 0.25, (4.0 - BN_EPS) as f32).unwrap();
        assert!((scale - 1.5).abs() < 1e-7, "{scale}");
        assert!((shift - 1.625).abs() < 1e-7, "{shift}");
        assert!(fold_batch_norm(0.0, 1.0, 0.0, 0.0, -1.0).is_none());
    }

    #[test]
    fn spectral_norm_names_round_trip() {
        for mode in SpectralNorm::ALL {
            assert_eq!(mode.name().parse::<SpectralNorm>().unwrap(), mode);
        }
        assert!("power".parse::<SpectralNorm>().is_err());
    }
}
