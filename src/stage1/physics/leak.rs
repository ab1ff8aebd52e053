//! Leak events. Junction leakage in a DVS pixel's reset switch slowly moves its memorised level
//! towards the ON threshold, so a pixel that has not fired for a while fires an ON event; every
//! event of the pixel resets the level, and with it the drift (Nozaki & Delbruck, IEEE TED 2017).
//! So leak fires in pixels that are quiet, at a steady period per pixel, and hardly ever in
//! pixels busy with signal; a memoryless (Poisson) draw would instead add events at random to
//! busy pixels, lengthening their inter-event intervals where a real sensor does not. On the
//! davis346 clip the real static pixels' events are 96% ON and none has another event of its
//! pixel within 10 ms: isolated, as this model fires them.
//!
//! Each pixel's period is `1 / leak_hz`, spread across pixels log-normally by
//! [`SPREAD_DECADES`] (leakage mismatch), and its drift starts at a random phase. The next leak
//! time of every pixel waits in a min-heap; an event of the pixel only postpones it, so the heap
//! is corrected lazily when an entry comes due: cost follows the leak events, not the pixels.

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use crate::event::Event;
use crate::seed::splitmix;

/// Standard deviation of a pixel's log10 leak rate across pixels, decades (the v2e simulator's
/// default rate spread, 0.1 decade: ../shared/SENSORS.md).
pub const SPREAD_DECADES: f64 = 0.1;

/// Memory of the leak heap per pixel, bytes.
pub const BYTES_PER_PIXEL: u64 = 16;

/// The leak of every pixel of one sensor.
pub(super) struct Leak {
    rate_hz: f64,
    seed: u64,
    /// Per pixel, the time its next leak event is due at the earliest, us.
    due: BinaryHeap<Reverse<(i64, u32)>>,
    started: bool,
}

impl Leak {
    /// Leak at `rate_hz` per pixel (0: none); `seed` fixes each pixel's rate and phase.
    pub(super) fn new(rate_hz: f64, seed: u64) -> Self {
        Leak {
            rate_hz,
            seed: seed ^ 0x1EA4_D21F_7000_0001,
            due: BinaryHeap::new(),
            started: false,
        }
    }

    /// Two uniforms in (0, 1) fixed by the seed and pixel `i`.
    fn uniforms(&self, i: usize) -> (f64, f64) {
        let a = splitmix(self.seed ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let b = splitmix(a);
        let unit = |v: u64| ((v >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
        (unit(a), unit(b))
    }

    /// Pixel `i`'s leak period, us (at least 1).
    fn period_us(&self, i: usize) -> i64 {
        let (u, v) = self.uniforms(i);
        let z = (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos();
        // Log-normal around a mean of `rate_hz`.
        let s = SPREAD_DECADES * std::f64::consts::LN_10;
        let rate = self.rate_hz * (s * z - 0.5 * s * s).exp();
        (1e6 / rate).round().clamp(1.0, i64::MAX as f64 / 4.0) as i64
    }

    /// Fires the leak events due in `(t0, t1]` (only the part from `from` on is drawn: see
    /// `MAX_NOISE_SPAN_US`) into `out`, for pixels whose last events are `last` (updated: a
    /// leak event is an event), on a sensor `width` pixels wide; an event within `refractory`
    /// us of the pixel's last is dropped.
    pub(super) fn fire(
        &mut self,
        (from, t1): (i64, i64),
        last: &mut [i64],
        refractory: f64,
        width: usize,
        out: &mut Vec<Event>,
    ) {
        if self.rate_hz <= 0.0 || last.is_empty() || width == 0 {
            return;
        }
        if !self.started {
            self.started = true;
            let entries: Vec<_> = (0..last.len())
                .map(|i| {
                    let phase = self.uniforms(i ^ 0x5A5A_5A5A).0;
                    let wait = ((1.0 - phase) * self.period_us(i) as f64).ceil() as i64;
                    Reverse((from.saturating_add(wait.max(1)), i as u32))
                })
                .collect();
            self.due = BinaryHeap::from(entries);
        }
        while let Some(&Reverse((due, i))) = self.due.peek() {
            if due > t1 {
                break;
            }
            self.due.pop();
            let i = i as usize;
            let period = self.period_us(i);
            // An event since this entry was made restarted the drift from there.
            let mut at = due.max(last[i].saturating_add(period));
            if at <= from {
                // Due before the part of the interval drawn (after a gap): the same phase,
                // whole periods on.
                let behind = from - at;
                at = at.saturating_add((behind / period + 1).saturating_mul(period));
            }
            if at > t1 {
                self.due.push(Reverse((at, i as u32)));
                continue;
            }
            if ((at - last[i]) as f64) >= refractory {
                last[i] = last[i].max(at);
                out.push(Event::new(at, (i % width) as u16, (i / width) as u16, true));
            }
            self.due
                .push(Reverse((at.saturating_add(period), i as u32)));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A quiet sensor fires leak at its rate, each pixel at a steady period; a pixel busy with
    /// events every 100 ms never leaks (every event restarts the drift).
    #[test]
    fn leak_fires_quiet_pixels_at_their_rate_and_spares_busy_ones() {
        let (w, h) = (100usize, 100usize);
        let rate = 2.0;
        let mut leak = Leak::new(rate, 9);
        let mut last = vec![i64::MIN / 2; w * h];
        let mut out = Vec::new();
        let seconds = 20i64;
        for k in 0..seconds * 10 {
            let t0 = k * 100_000;
            // Pixel 0 fires a signal event at the start of each 100 ms.
            last[0] = t0 + 1;
            leak.fire((t0, t0 + 100_000), &mut last, 0.0, w, &mut out);
        }
        let measured = out.len() as f64 / (w * h) as f64 / seconds as f64;
        assert!((measured / rate - 1.0).abs() < 0.03, "{measured}");
        assert!(out.iter().all(|e| e.on));
        assert!(!out.iter().any(|e| (e.x, e.y) == (0, 0)));
        // One pixel's events are a period apart.
        let mut times: Vec<i64> = out
            .iter()
            .filter(|e| (e.x, e.y) == (5, 7))
            .map(|e| e.t)
            .collect();
        times.sort_unstable();
        let gaps: Vec<i64> = times.windows(2).map(|p| p[1] - p[0]).collect();
        assert!(gaps.len() > 20);
        assert!(gaps.iter().all(|&g| g == gaps[0]), "{gaps:?}");
    }

    /// After a gap of a year only the interval's drawn part fires, each pixel at most its few
    /// periods there, all inside it.
    #[test]
    fn a_gap_draws_only_the_span() {
        let mut leak = Leak::new(1.0, 3);
        let mut last = vec![i64::MIN / 2; 400];
        let mut out = Vec::new();
        leak.fire((0, 40_000), &mut last, 0.0, 20, &mut out);
        out.clear();
        let year = 31_536_000_000_000i64;
        leak.fire((year - 1_000_000, year), &mut last, 0.0, 20, &mut out);
        assert!(out.len() <= 3 * 400, "{}", out.len());
        assert!(out.len() >= 200, "{}", out.len());
        assert!(out.iter().all(|e| e.t > year - 1_000_000 && e.t <= year));
    }
}
