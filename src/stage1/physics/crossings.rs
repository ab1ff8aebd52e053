//! The slow path of the pixel model: sub-steps with timed crossings, for the pixels of a tile
//! row whose response may reach a threshold in the interval (see [`PhysicsSim::row`]).
//!
//! Pixels are stepped [`LANES`] at a time, side by side. Each pixel's photoreceptor filter is a
//! chain of dependent operations, so a pixel stepped alone waits on every step's latency; a
//! group keeps the floating-point units busy. Each pixel's arithmetic is exactly what it is
//! alone (the same operations in the same order), and a frame's events are sorted afterwards,
//! so the events do not depend on the grouping.

use super::{FilterRow, PhysicsSim, FLICKER_MAX_SUBSTEPS};
use crate::event::Event;
use crate::rounding::{ceil_to_u32, round_to_i64};

/// Pixels stepped side by side.
const LANES: usize = 4;

/// One pixel's state and constants over the interval.
#[derive(Debug, Clone, Copy, Default)]
struct Lane {
    i: usize,
    x: u16,
    row: u16,
    l0: f64,
    l1: f64,
    tau: f64,
    /// Flicker amplitude, phase at the interval's start, and angular frequency per us.
    amp: f64,
    phase: f64,
    omega: f64,
    on: f64,
    off: f64,
    steps: u32,
    h: f64,
    decay: f64,
    rt: f64,
    /// The filtered response, the input at the last step's end, the memorised level and the
    /// last event's time.
    y: f64,
    u_prev: f64,
    lref: f64,
    last: i64,
}

impl Lane {
    /// The flicker's swing at `t` us into the interval.
    fn flicker(&self, t: f64) -> f64 {
        if self.amp > 0.0 {
            self.amp * (self.phase + self.omega * t).sin()
        } else {
            0.0
        }
    }
}

impl PhysicsSim {
    /// Steps `pixels` of row `y` (index, column, light at `t1`) from `t0` to `t1` in
    /// sub-steps, appending their timed threshold crossings to `out` (unsorted).
    pub(super) fn crossings(
        &mut self,
        y: u16,
        pixels: &[(usize, u16, u16)],
        t0: i64,
        t1: i64,
        filter: &[FilterRow],
        out: &mut Vec<Event>,
    ) {
        for group in pixels.chunks(LANES) {
            let mut lanes = [Lane::default(); LANES];
            for (lane, &(i, x, v)) in lanes.iter_mut().zip(group) {
                *lane = Lane {
                    x,
                    row: y,
                    ..self.lane(i, v, t0, t1, filter)
                };
            }
            self.step_lanes(&mut lanes[..group.len()], t0, t1, out);
            for lane in &lanes[..group.len()] {
                let i = lane.i;
                self.l_in[i] = lane.l1 as f32;
                self.l_p[i] = lane.y as f32;
                self.l_ref[i] = lane.lref as f32;
                self.last_event[i] = lane.last;
            }
        }
    }

    /// Pixel `i`'s state at `t0` and its constants for the interval to `t1`, where its light
    /// is `v` (its column and row left to the caller).
    fn lane(&self, i: usize, v: u16, t0: i64, t1: i64, filter: &[FilterRow]) -> Lane {
        let l1 = self.log_lut[v as usize] as f64;
        let l0 = self.l_in[i] as f64;
        let row = filter[super::filter_index(v, (1.0 / self.photo_scale) as f32)];
        let tau = row.tau as f64;
        let amp = row.amp as f64;
        let y = self.l_p[i] as f64;
        let (on, off) = (self.thr_on[i] as f64, self.thr_off[i] as f64);
        let dt = (t1 - t0) as f64;
        let span = (l1 - l0).abs().max((l1 - y).abs());
        let mut steps = ceil_to_u32(span / (0.25 * on.min(off)));
        if tau > 0.0 {
            // Short steps against the time constant, so the filter's curve is followed.
            // `dt / tau` is finite and positive here (`tau > 0`, `dt >= 1`).
            steps = steps.max(ceil_to_u32(dt / tau).min(8));
        }
        let mut most = self.cfg.max_substeps;
        let (mut phase, mut omega) = (0.0, 0.0);
        if amp > 0.0 {
            // Eight steps per flicker cycle, so each cycle's crossings are found and timed.
            steps = steps.max((8.0 * self.cfg.flicker_hz * dt * 1e-6).ceil().min(1e6) as u32);
            most = most.max(FLICKER_MAX_SUBSTEPS);
            phase = self.flicker_phase(t0) - row.lag as f64;
            omega = std::f64::consts::TAU * self.cfg.flicker_hz * 1e-6;
        }
        let steps = steps.clamp(1, most);
        let h = dt / steps as f64;
        Lane {
            i,
            x: 0,
            row: 0,
            l0,
            l1,
            tau,
            amp,
            phase,
            omega,
            on,
            off,
            steps,
            h,
            decay: if tau > 0.0 { (-h / tau).exp() } else { 0.0 },
            rt: (l1 - l0) / dt * tau,
            y,
            // The input at the first step's start: `l0` (the step formula at k = 0).
            u_prev: l0,
            lref: self.l_ref[i] as f64,
            last: self.last_event[i],
        }
    }

    /// Steps every lane through its sub-steps, side by side.
    fn step_lanes(&mut self, lanes: &mut [Lane], t0: i64, t1: i64, out: &mut Vec<Event>) {
        let refractory = self.cfg.refractory_us;
        let most = lanes.iter().map(|l| l.steps).max().unwrap_or(0);
        for k in 1..=most {
            for s in lanes.iter_mut() {
                if k > s.steps {
                    continue;
                }
                let u = s.l0 + (s.l1 - s.l0) * k as f64 / s.steps as f64;
                let y_prev = s.y;
                s.y = if s.tau > 0.0 {
                    u - s.rt + (y_prev - s.u_prev + s.rt) * s.decay
                } else {
                    u
                };
                s.u_prev = u;
                // In steady light the response is the filter's alone: most steps cross
                // nothing (the same test as the loop's below, without the flicker's zero).
                if s.amp == 0.0 && s.y - s.lref < s.on && s.lref - s.y < s.off {
                    continue;
                }
                // Relative to the interval's start: absolute times (~1.6e15 us for a DAVIS
                // clock) would cost f64 its microseconds, and a recording and its export with
                // times from another origin would differ by 1 us here and there.
                let t_start = s.h * (k - 1) as f64;
                // The response with the flicker's swing, at the step's start and end.
                let prev = y_prev + s.flicker(t_start);
                let now = s.y + s.flicker(t_start + s.h);
                loop {
                    let (level, polarity) = if now - s.lref >= s.on {
                        (s.lref + s.on, true)
                    } else if s.lref - now >= s.off {
                        (s.lref - s.off, false)
                    } else {
                        break;
                    };
                    let frac = if (now - prev).abs() > 1e-12 {
                        ((level - prev) / (now - prev)).clamp(0.0, 1.0)
                    } else {
                        1.0
                    };
                    let te = (t0 + round_to_i64(t_start + frac * s.h)).clamp(t0 + 1, t1);
                    s.lref = level;
                    if ((te - s.last) as f64) < refractory {
                        self.stats.refractory_drops += 1;
                        continue;
                    }
                    s.last = te;
                    out.push(Event::new(te, s.x, s.row, polarity));
                }
            }
        }
    }
}
