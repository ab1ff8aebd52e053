//! Hot loops compiled twice: for the x86-64 baseline (SSE2, 4 `f32` lanes) and for AVX2
//! (8 lanes), the copy chosen at run time by what the CPU has, so one portable binary (and
//! the Python wheel) runs the wider vectors where they exist. The loops are written as
//! portable code the compiler vectorises; the two copies compute the same values bit for
//! bit (no fused multiply-add is enabled: Rust never contracts `a * b + c` on its own).
//! `V2CE_SIMD=baseline` keeps the baseline copy (to compare the two); `auto`, the default,
//! takes the widest the CPU has.

use std::sync::OnceLock;

/// Whether the AVX2 copies run: the CPU has AVX2 and `V2CE_SIMD` does not say `baseline`
/// (any value but `baseline` and `auto` is warned about once and taken as `auto`).
pub fn wide() -> bool {
    static WIDE: OnceLock<bool> = OnceLock::new();
    *WIDE.get_or_init(|| {
        match std::env::var("V2CE_SIMD").ok().as_deref() {
            Some("baseline") => return false,
            None | Some("auto") | Some("") => {}
            Some(other) => tracing::warn!(
                "V2CE_SIMD={other:?} is neither \"auto\" nor \"baseline\": taken as \"auto\""
            ),
        }
        #[cfg(target_arch = "x86_64")]
        {
            std::arch::is_x86_feature_detected!("avx2")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    })
}

/// Runs `f`, compiled for AVX2 where [`wide`] says so. `f` should call `#[inline(always)]`
/// code: what it calls without inlining keeps the baseline's instructions.
#[inline(always)]
pub fn run<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    if wide() {
        // SAFETY: `wide` checked that this CPU has AVX2.
        return unsafe { avx2(f) };
    }
    f()
}

/// `f()` with AVX2 enabled for the code inlined into it.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn avx2<R>(f: impl FnOnce() -> R) -> R {
    f()
}
