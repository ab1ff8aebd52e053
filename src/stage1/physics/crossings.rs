//! The slow path of the pixel model: sub-steps with timed crossings, for the pixels of a tile
//! whose response may reach a threshold in the interval (the bands' fast path leaves them here).
//!
//! A tile's slow pixels are ordered by their number of sub-steps and stepped [`LANES`] at a
//! time, side by side, one array per quantity, so the step's arithmetic runs on vectors and a
//! group's lanes mostly end together. Each pixel's photoreceptor filter is a chain of
//! dependent operations: a pixel stepped alone waits on every step's latency. Each pixel's
//! arithmetic is exactly what it is alone (the same operations in the same order), and a
//! frame's events are sorted afterwards, so the events depend neither on the grouping nor on
//! the order.
//!
//! This file reads only the model's shared types ([`super`]); the bands that call it
//! ([`super::band`]) hand it a view of their state ([`Slow`]).

use super::{FilterRow, PhysicsConfig, SlowPixel, FLICKER_MAX_SUBSTEPS};
use crate::event::Event;
use crate::rounding::{ceil_to_u32, round_to_i64};

/// Pixels stepped side by side.
const LANES: usize = 4;

/// One pixel's state and constants over the interval.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Lane {
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
    /// The pixel's events so far, and its own thresholds which the noise is drawn around
    /// (with threshold noise; read with the rest of its state, in memory order).
    fired: u32,
    own_on: f64,
    own_off: f64,
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

/// The quantities of a group's step, one array each (lane `j` of every array is one pixel).
/// Lanes past the group's pixels have no steps.
#[derive(Debug, Clone, Copy)]
struct Group {
    /// Each lane's number of steps (0 past the group's pixels).
    last_step: [f64; LANES],
    /// The divisor of the input's ramp: the number of steps (1 past the group's pixels).
    steps: [f64; LANES],
    l0: [f64; LANES],
    /// `l1 - l0`.
    span: [f64; LANES],
    /// All bits set where the lane has a filter (`tau > 0`), clear where it follows its input.
    filtered: [f64; LANES],
    /// All bits set where the light is steady (no flicker).
    steady: [f64; LANES],
    rt: [f64; LANES],
    decay: [f64; LANES],
    on: [f64; LANES],
    off: [f64; LANES],
    y: [f64; LANES],
    u_prev: [f64; LANES],
    lref: [f64; LANES],
}

/// A lane mask: all bits set or clear.
fn mask(b: bool) -> f64 {
    f64::from_bits(if b { u64::MAX } else { 0 })
}

impl Group {
    fn new(lanes: &[Lane]) -> Self {
        let mut g = Group {
            last_step: [0.0; LANES],
            steps: [1.0; LANES],
            l0: [0.0; LANES],
            span: [0.0; LANES],
            filtered: [0.0; LANES],
            steady: [mask(true); LANES],
            rt: [0.0; LANES],
            decay: [0.0; LANES],
            on: [0.0; LANES],
            off: [0.0; LANES],
            y: [0.0; LANES],
            u_prev: [0.0; LANES],
            lref: [0.0; LANES],
        };
        for (j, s) in lanes.iter().enumerate() {
            g.last_step[j] = s.steps as f64;
            g.steps[j] = s.steps as f64;
            g.l0[j] = s.l0;
            g.span[j] = s.l1 - s.l0;
            g.filtered[j] = mask(s.tau > 0.0);
            g.steady[j] = mask(s.amp == 0.0);
            g.rt[j] = s.rt;
            g.decay[j] = s.decay;
            g.on[j] = s.on;
            g.off[j] = s.off;
            g.y[j] = s.y;
            g.u_prev[j] = s.u_prev;
            g.lref[j] = s.lref;
        }
        g
    }

    /// Step `k` of every lane that has one; returns the responses before it and a bit per
    /// lane that may cross a threshold in it (in steady light most steps cross nothing: the
    /// test of [`PhysicsSim::cross`] without the flicker's zero).
    #[inline(always)]
    fn step(&mut self, k: u32) -> ([f64; LANES], u32) {
        #[cfg(target_arch = "x86_64")]
        {
            self.step_sse2(k)
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            self.step_scalar(k)
        }
    }

    /// [`Group::step`] one lane at a time: the definition, and the path off x86-64.
    #[cfg_attr(target_arch = "x86_64", allow(dead_code))]
    #[allow(clippy::needless_range_loop)]
    fn step_scalar(&mut self, k: u32) -> ([f64; LANES], u32) {
        let kf = k as f64;
        let before = self.y;
        let mut check = 0;
        for j in 0..LANES {
            if kf > self.last_step[j] {
                continue;
            }
            let u = self.l0[j] + self.span[j] * kf / self.steps[j];
            self.y[j] = if self.filtered[j].to_bits() != 0 {
                u - self.rt[j] + (before[j] - self.u_prev[j] + self.rt[j]) * self.decay[j]
            } else {
                u
            };
            self.u_prev[j] = u;
            let quiet = self.steady[j].to_bits() != 0
                && self.y[j] - self.lref[j] < self.on[j]
                && self.lref[j] - self.y[j] < self.off[j];
            check |= u32::from(!quiet) << j;
        }
        (before, check)
    }

    /// [`Group::step`] on SSE2 vectors, two lanes each: the same operations in the same
    /// order per lane, so the same values bit for bit.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn step_sse2(&mut self, k: u32) -> ([f64; LANES], u32) {
        use std::arch::x86_64::*;
        let before = self.y;
        let mut check = 0;
        // SAFETY: SSE2 is part of the x86-64 baseline; every load and store is an unaligned
        // access within a `[f64; LANES]` of `self` (or `before`), two lanes at `h`.
        unsafe {
            let kf = _mm_set1_pd(k as f64);
            for h in (0..LANES).step_by(2) {
                let ld = |a: &[f64; LANES]| _mm_loadu_pd(a.as_ptr().add(h));
                let y_prev = ld(&before);
                let active = _mm_cmple_pd(kf, ld(&self.last_step));
                let u = _mm_add_pd(
                    ld(&self.l0),
                    _mm_div_pd(_mm_mul_pd(ld(&self.span), kf), ld(&self.steps)),
                );
                let rt = ld(&self.rt);
                let filtered = _mm_add_pd(
                    _mm_sub_pd(u, rt),
                    _mm_mul_pd(
                        _mm_add_pd(_mm_sub_pd(y_prev, ld(&self.u_prev)), rt),
                        ld(&self.decay),
                    ),
                );
                let f = ld(&self.filtered);
                let y_new = _mm_or_pd(_mm_and_pd(f, filtered), _mm_andnot_pd(f, u));
                let y = _mm_or_pd(_mm_and_pd(active, y_new), _mm_andnot_pd(active, y_prev));
                let u_prev = ld(&self.u_prev);
                let u_prev = _mm_or_pd(_mm_and_pd(active, u), _mm_andnot_pd(active, u_prev));
                _mm_storeu_pd(self.y.as_mut_ptr().add(h), y);
                _mm_storeu_pd(self.u_prev.as_mut_ptr().add(h), u_prev);
                let lref = ld(&self.lref);
                let quiet = _mm_and_pd(
                    ld(&self.steady),
                    _mm_and_pd(
                        _mm_cmplt_pd(_mm_sub_pd(y, lref), ld(&self.on)),
                        _mm_cmplt_pd(_mm_sub_pd(lref, y), ld(&self.off)),
                    ),
                );
                let bits = _mm_movemask_pd(_mm_andnot_pd(quiet, active)) as u32;
                check |= bits << h;
            }
        }
        (before, check)
    }
}

/// What every band reads.
pub(super) struct Shared<'a> {
    pub cfg: &'a PhysicsConfig,
    /// `L` and the filter row of every 16-bit luminance value.
    pub log_lut: &'a [f32],
    pub filter_rows: &'a [u8],
    pub width: usize,
    pub height: usize,
    pub tile: usize,
    /// Each pixel's own thresholds, which the threshold noise is drawn around (frame
    /// indices; empty without threshold noise).
    pub own_on: &'a [f32],
    pub own_off: &'a [f32],
    /// The simulator's seed, which the threshold noise is drawn from.
    pub seed: u64,
    /// What the frame's event buffers may still grow by, all bands together.
    pub budget: crate::limits::Budget,
}

/// A band's pixels as the slow path sees them: their state, indexed from the band's first
/// pixel (`base` in the frame), and the band's count of crossings the refractory period
/// swallowed.
pub(super) struct Slow<'a, 'b> {
    pub shared: &'a Shared<'a>,
    pub base: usize,
    pub l_in: &'b mut [f32],
    pub l_p: &'b mut [f32],
    pub l_ref: &'b mut [f32],
    pub thr_on: &'b mut [f32],
    pub thr_off: &'b mut [f32],
    /// Each pixel's events so far (empty without threshold noise).
    pub fired: &'b mut [u32],
    pub last_event: &'b mut [i64],
    pub refractory_drops: &'b mut u64,
    /// Crossings memory could not hold (see [`crate::limits::room_for_one`]).
    pub unheld: &'b mut u64,
}

impl Slow<'_, '_> {
    /// Steps `pixels` (a tile's slow pixels, light at `t1`) from `t0` to `t1` in sub-steps,
    /// appending their timed threshold crossings to `out` (unsorted); `lanes` is scratch.
    pub(super) fn crossings(
        &mut self,
        pixels: &[SlowPixel],
        (t0, t1): (i64, i64),
        filter: &[FilterRow],
        lanes: &mut Vec<Lane>,
        out: &mut Vec<Event>,
    ) {
        lanes.clear();
        if !crate::limits::room_for(lanes, pixels.len()) {
            *self.unheld += pixels.len() as u64;
            return;
        }
        lanes.extend(pixels.iter().map(|p| Lane {
            x: p.x,
            row: p.y,
            ..self.lane(p.i, p.v, t0, t1, filter)
        }));
        lanes.sort_unstable_by_key(|l| l.steps);
        for group in lanes.chunks_mut(LANES) {
            self.step_lanes(group, t0, t1, out);
            for lane in group.iter() {
                let i = lane.i;
                self.l_in[i] = lane.l1 as f32;
                self.l_p[i] = lane.y as f32;
                self.l_ref[i] = lane.lref as f32;
                self.thr_on[i] = lane.on as f32;
                self.thr_off[i] = lane.off as f32;
                if let Some(f) = self.fired.get_mut(i) {
                    *f = lane.fired;
                }
                self.last_event[i] = lane.last;
            }
        }
    }

    /// The flicker's phase (radians) at time `t` us.
    fn flicker_phase(&self, t: i64) -> f64 {
        let period = 1e6 / self.shared.cfg.flicker_hz;
        std::f64::consts::TAU * (t as f64).rem_euclid(period) / period
    }

    /// Pixel `i`'s state at `t0` and its constants for the interval to `t1`, where its light
    /// is `v` (its column and row left to the caller).
    fn lane(&self, i: usize, v: u16, t0: i64, t1: i64, filter: &[FilterRow]) -> Lane {
        let l1 = self.shared.log_lut[v as usize] as f64;
        let l0 = self.l_in[i] as f64;
        let row = filter[self.shared.filter_rows[v as usize] as usize];
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
        let mut most = self.shared.cfg.max_substeps;
        let (mut phase, mut omega) = (0.0, 0.0);
        if amp > 0.0 {
            // Eight steps per flicker cycle, so each cycle's crossings are found and timed.
            steps = steps.max(
                (8.0 * self.shared.cfg.flicker_hz * dt * 1e-6)
                    .ceil()
                    .min(1e6) as u32,
            );
            most = most.max(FLICKER_MAX_SUBSTEPS);
            phase = self.flicker_phase(t0) - row.lag as f64;
            omega = std::f64::consts::TAU * self.shared.cfg.flicker_hz * 1e-6;
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
            fired: self.fired.get(i).copied().unwrap_or(0),
            own_on: self
                .shared
                .own_on
                .get(self.base + i)
                .map_or(0.0, |&v| v as f64),
            own_off: self
                .shared
                .own_off
                .get(self.base + i)
                .map_or(0.0, |&v| v as f64),
        }
    }

    /// Steps every lane (at most [`LANES`]) through its sub-steps, side by side.
    fn step_lanes(&mut self, lanes: &mut [Lane], t0: i64, t1: i64, out: &mut Vec<Event>) {
        let mut g = Group::new(lanes);
        let most = lanes.iter().map(|l| l.steps).max().unwrap_or(0);
        for k in 1..=most {
            let (before, check) = g.step(k);
            if check == 0 {
                continue;
            }
            for (j, s) in lanes.iter_mut().enumerate() {
                if check & (1 << j) != 0 {
                    s.lref = g.lref[j];
                    self.cross(s, k, before[j], g.y[j], t0, t1, out);
                    (g.lref[j], g.on[j], g.off[j]) = (s.lref, s.on, s.off);
                }
            }
        }
        for (j, s) in lanes.iter_mut().enumerate() {
            (s.y, s.u_prev, s.lref) = (g.y[j], g.u_prev[j], g.lref[j]);
        }
    }

    /// The crossings of lane `s` in its step `k`, from the response `y_prev` to `y`.
    #[allow(clippy::too_many_arguments)]
    fn cross(
        &mut self,
        s: &mut Lane,
        k: u32,
        y_prev: f64,
        y: f64,
        t0: i64,
        t1: i64,
        out: &mut Vec<Event>,
    ) {
        let refractory = self.shared.cfg.refractory_us;
        // Relative to the interval's start: absolute times (~1.6e15 us for a DAVIS clock)
        // would cost f64 its microseconds, and a recording and its export with times from
        // another origin would differ by 1 us here and there.
        let t_start = s.h * (k - 1) as f64;
        // The response with the flicker's swing, at the step's start and end.
        let prev = y_prev + s.flicker(t_start);
        let now = y + s.flicker(t_start + s.h);
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
                *self.refractory_drops += 1;
                continue;
            }
            s.last = te;
            // Once memory refused one, the frame is refused: the rest are only counted.
            if *self.unheld > 0 || !self.shared.budget.room_for_one(out) {
                *self.unheld += 1;
                continue;
            }
            out.push(Event::new(te, s.x, s.row, polarity));
            self.redraw_threshold(s, polarity);
        }
    }

    /// After lane `s` fired an event of `polarity`: that polarity's threshold for its next
    /// event, drawn around the pixel's own by the threshold noise (the comparator's and the
    /// reset's: IEBCS, Joubert et al., Front. Neurosci. 2021, draws each event's threshold so).
    /// The draw is a hash of the seed, the pixel and its count of events, so the events depend
    /// neither on the order pixels are stepped in nor on the time origin. A draw below a
    /// quarter of the pixel's own threshold is held there: a threshold stays positive.
    fn redraw_threshold(&self, s: &mut Lane, polarity: bool) {
        let sigma = self.shared.cfg.threshold_noise;
        if sigma <= 0.0 {
            return;
        }
        let pixel = self.base + s.i;
        let own = if polarity { s.own_on } else { s.own_off };
        s.fired = s.fired.wrapping_add(1);
        let key = crate::seed::splitmix(self.shared.seed ^ 0x7E5E_7D0E)
            ^ (pixel as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ u64::from(s.fired).rotate_left(40);
        let drawn = (own + sigma * crate::seed::normal(key)).max(0.25 * own);
        if polarity {
            s.on = drawn;
        } else {
            s.off = drawn;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// A group of random lanes: filtered or not, steady or flickering, steps 0 (a missing
    /// lane) to 40, responses near their thresholds so that crossings are common.
    fn group(rng: &mut rand_xoshiro::Xoshiro256PlusPlus) -> Group {
        let lanes: Vec<Lane> = (0..rng.gen_range(1..=LANES))
            .map(|_| {
                let l0 = rng.gen_range(-4.0..0.5);
                let l1 = l0 + rng.gen_range(-1.0..1.0);
                let tau = if rng.gen_bool(0.8) {
                    rng.gen_range(100.0..5000.0)
                } else {
                    0.0
                };
                Lane {
                    l0,
                    l1,
                    tau,
                    amp: if rng.gen_bool(0.9) { 0.0 } else { 0.1 },
                    on: rng.gen_range(0.1..0.4),
                    off: rng.gen_range(0.1..0.4),
                    steps: rng.gen_range(1..=40),
                    decay: if tau > 0.0 {
                        rng.gen_range(0.0..1.0)
                    } else {
                        0.0
                    },
                    rt: (l1 - l0) * tau / 33_333.0,
                    y: l0 + rng.gen_range(-0.2..0.2),
                    u_prev: l0,
                    lref: l0 + rng.gen_range(-0.3..0.3),
                    ..Lane::default()
                }
            })
            .collect();
        Group::new(&lanes)
    }

    #[test]
    #[cfg(target_arch = "x86_64")]
    fn the_vector_step_is_the_scalar_step_bit_for_bit() {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(27);
        let mut crossing = 0;
        for _ in 0..2_000 {
            let mut a = group(&mut rng);
            let mut b = a;
            for k in 1..=41 {
                let (before_a, check_a) = a.step_scalar(k);
                let (before_b, check_b) = b.step_sse2(k);
                assert_eq!(check_a, check_b, "step {k}");
                crossing += (check_a != 0) as u32;
                for j in 0..LANES {
                    assert_eq!(before_a[j].to_bits(), before_b[j].to_bits());
                    assert_eq!(a.y[j].to_bits(), b.y[j].to_bits(), "lane {j} step {k}");
                    assert_eq!(a.u_prev[j].to_bits(), b.u_prev[j].to_bits());
                }
                // A crossing moves the memorised level, as `cross` does.
                for j in 0..LANES {
                    if check_a & (1 << j) != 0 {
                        a.lref[j] = a.y[j];
                        b.lref[j] = b.y[j];
                    }
                }
            }
        }
        assert!(crossing > 1_000, "{crossing} steps with a crossing");
    }
}
