//! The sweeping-bar recording: synthetic events made by the project, the built-in input of
//! `v2ce eval stage2` and a recording for tests and benchmarks when no real one is at hand.
//!
//! The scene: a bright bar sweeping back and forth across a dark background on a small sensor.
//! Each pixel fires a burst of ON events when the bar's leading edge passes it and OFF events at
//! the trailing edge, several thresholds' worth while the edge is fast, with timing jitter, plus
//! sparse background noise.

use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;

use crate::event::Event;
use crate::format::Recording;

/// The sweeping-bar recording: `width x height`, events in `[0, duration_us)`, from `seed`.
pub fn recording(width: u16, height: u16, duration_us: i64, seed: u64) -> Recording {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let (w, h) = (width as f64, height as f64);
    let bar = (w / 8.0).max(1.0);
    let period = 1_000_000.0;
    // Bar left edge position at time t (us): a cosine sweep over the sensor.
    let pos = |t: f64| (w - bar) * 0.5 * (1.0 - (2.0 * std::f64::consts::PI * t / period).cos());
    let rows = (h * 0.25) as u16..(h * 0.75).ceil() as u16;
    let mut events = Vec::new();
    let step = 50.0; // us
    let mut t = 0.0;
    while t < duration_us as f64 {
        let (a, b) = (pos(t), pos(t + step));
        let moving_right = b >= a;
        // Columns whose edge crossing happens in [t, t + step): leading and trailing edges.
        for (edge_a, edge_b, leading) in [(a, b, true), (a + bar, b + bar, false)] {
            let (lo, hi) = (edge_a.min(edge_b), edge_a.max(edge_b));
            let mut x = lo.ceil();
            while x < hi && x < w {
                // Entering pixels brighten (ON), leaving pixels darken (OFF).
                let on = leading != moving_right;
                let frac = (x - edge_a) / (edge_b - edge_a);
                let tc = t + frac * step;
                let speed = (edge_b - edge_a).abs() / step * 1e3; // px per ms
                let bursts = 1 + (speed * 2.0).min(4.0) as u32;
                for y in rows.clone() {
                    for k in 0..bursts {
                        let jitter = rng.gen::<f64>() * 300.0 + k as f64 * 150.0;
                        let te = (tc + jitter) as i64;
                        if te < duration_us {
                            events.push(Event::new(te, x as u16, y, on));
                        }
                    }
                }
                x += 1.0;
            }
        }
        t += step;
    }
    // Background noise: about 2 events per pixel per second.
    let noise = (2.0 * w * h * duration_us as f64 / 1e6) as usize;
    for _ in 0..noise {
        events.push(Event::new(
            rng.gen_range(0..duration_us.max(1)),
            rng.gen_range(0..width),
            rng.gen_range(0..height),
            rng.gen(),
        ));
    }
    crate::event::sort_events(&mut events);
    Recording::new(events, Some((width, height)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deterministic_and_inside_the_sensor() {
        let a = recording(64, 48, 500_000, 7);
        let b = recording(64, 48, 500_000, 7);
        assert_eq!(a.events, b.events);
        assert!(a.events.len() > 5_000);
        assert!(a
            .events
            .events()
            .iter()
            .all(|e| e.x < 64 && e.y < 48 && (0..500_000).contains(&e.t)));
        let on = a.events.events().iter().filter(|e| e.on).count();
        assert!(on > 1000 && on < a.events.len() - 1000);
    }
}
