//! Seeds spread into independent streams: the SplitMix64 mixer (Steele, Lea & Flood, "Fast
//! splittable pseudorandom number generators", OOPSLA 2014), a well-spread 64-bit hash by which
//! one user seed gives each cell, pixel or interval draws of its own, the same on any thread.

/// The SplitMix64 mixer of `z`.
pub fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A standard normal deviate drawn from `key` (Box-Muller on two SplitMix64 outputs): the same
/// key gives the same deviate.
pub fn normal(key: u64) -> f64 {
    let a = splitmix(key);
    let b = splitmix(a);
    // Uniforms in (0, 1): 53 bits and a half, so the logarithm is finite.
    let unit = |z: u64| ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
    (-2.0 * unit(a).ln()).sqrt() * (std::f64::consts::TAU * unit(b)).cos()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The deviates have the standard normal's mean, spread and tails, and a key gives one.
    #[test]
    fn normal_deviates_are_standard_normal() {
        let n = 200_000;
        let z: Vec<f64> = (0..n).map(|k| normal(splitmix(k))).collect();
        let mean = z.iter().sum::<f64>() / n as f64;
        let var = z.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(mean.abs() < 0.01, "mean {mean}");
        assert!((var - 1.0).abs() < 0.01, "variance {var}");
        let beyond = z.iter().filter(|v| v.abs() > 2.0).count() as f64 / n as f64;
        assert!(
            (beyond - 0.0455).abs() < 0.003,
            "share beyond 2 sigma {beyond}"
        );
        assert!(z.iter().all(|v| v.is_finite()));
        assert_eq!(normal(7).to_bits(), normal(7).to_bits());
    }
}
