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
