//! The physical DVS pixel model: the fast tier of Stage 1.
//!
//! Per pixel, between two frames at `t0` and `t1`:
//! 1. **Log front end with a lin-log toe.** The input is linear luminance `I` (fraction of full
//!    scale) plus the photodiode's dark current `I_d`; the pixel sees `L = ln(I + I_d)` above the
//!    knee `I_k` and the tangent line `ln(I_k) + (I + I_d - I_k) / I_k` below it, so near black
//!    the response is linear and APS-like read noise on dark pixels does not turn into large log
//!    swings (a DVS pixel is not an APS pixel).
//! 2. **Photoreceptor bandwidth.** `L` drives a first-order low-pass whose cutoff grows with the
//!    light, `f_c = f_max (I + I_d) / (1 + I_d)`, so dark pixels are slow and filter their
//!    noise while bright ones follow fast edges. `f_max = 0` means an ideal, instant pixel.
//! 3. **Change detector.** The filtered `L_p` is compared with the level memorised at the last
//!    event; each crossing of `+theta_on` or `-theta_off` (per-pixel thresholds drawn once from a
//!    normal law around the preset's means, the mismatch; each event's threshold drawn anew
//!    around the pixel's own with `threshold_noise`, the comparator's and the reset's temporal
//!    noise, as IEBCS does \[IEB\]) is an event, timed by linear
//!    interpolation inside the sub-step where it happens. The input is interpolated linearly in
//!    `L` between frames (between the sub-frames warped along the optical flow, with `motion =
//!    "flow"`: [`super::motion`]) and cut into sub-steps small enough (a quarter of the smaller
//!    threshold per sub-step, up to `max_substeps`) that several crossings in one interval get
//!    distinct times.
//! 4. **Refractory period.** A crossing within `refractory_us` of the pixel's last event resets
//!    the memorised level without an event, so no pixel fires faster than `1 / refractory`.
//! 5. **Noise**, drawn sparsely so its cost follows the number of noise events: leak events (ON,
//!    `leak_hz` per pixel, each pixel at a steady period from its last event, which restarts the
//!    drift: quiet pixels leak, busy ones hardly ever: `leak.rs`), shot noise (either polarity, `shot_noise_hz` per pixel in the dark,
//!    thinned by `1 / (1 + I / I_half)` with `I_half = 0.05`), and hot pixels (a fixed set of
//!    `hot_pixel_fraction` pixels firing at `hot_pixel_hz`).
//!
//! 6. **Flicker** (optional): lamps on the mains flicker at 100 or 120 Hz, which frames at
//!    25-60 Hz cannot show. With `flicker_depth > 0` the light is `I (1 + d sin(2 pi f t))`:
//!    its log swing `atanh(d)`, diluted by the dark current and passed by the photoreceptor's
//!    low-pass (gain and phase lag at `f`), is added to the response, so a still pixel fires
//!    every cycle when the swing passes its thresholds. `v2ce calibrate` finds it in a
//!    recording's events.
//!
//! **Light.** A frame's values say how bright it is relative to its own full scale, not how
//! much photocurrent lies behind them (see [`LightModel`]). By default (`light = "scene"`)
//! the light parameters (`I_d`, `I_k`, the bandwidth curve, `I_half`) hold for a scene whose
//! mean is `scene_level` and scale with each scene's own mean, taken from its first frame that
//! is not nearly black: only contrast matters, as for a log pixel above its bandwidth limit,
//! so the same motion gives the same events at any exposure (the illumination ladder). With
//! `light = "exposure"` the photoreceptor (bandwidth, shot noise) sees absolute light from each
//! frame's exposure, against the calibration recording's. In every model an exposure change
//! between frames that report it is not a change of light.
//!
//! **Parameters, units and sources** (tags as in the project's sensor notes: \[L08\]
//! Lichtsteiner et al. JSSC 2008, \[B14\] Brandli et al. JSSC 2014, \[v2e\] the v2e simulator's
//! defaults, \[DVM\] DVS-Voltmeter's DAVIS346 fit, \[DND\] Guo & Delbruck's noise measurements,
//! \[IEB\] IEBCS, Joubert et al., Front. Neurosci. 2021):
//!
//! | parameter | unit | davis346 | published | how ours was set |
//! |---|---|---|---|---|
//! | `threshold_on/off` | ln | 0.26 / 0.305 | DAVIS240 11% contrast = 0.10 \[B14\]; ~0.19 for a DAVIS346 \[DVM\]; v2e 0.2 | `v2ce calibrate --motion flow` on the davis346 clip (their mean, 0.28, is what the linear model's count match gave: seeing the motion did not bring it nearer the published figure) |
//! | `threshold_sigma` | ln | 0.03 | 2.1% \[L08\], 3.5% \[B14\] contrast matching; v2e 0.03 | published range |
//! | `threshold_noise` | ln | 0.06 | IEBCS 0.02 (class default), 0.05 (its example) \[IEB\]; v2e none | `v2ce calibrate` on the clip's inter-event intervals and refractory floor |
//! | `refractory_us` | us | 1000 | not published for DAVIS; v2e 500, IEBCS 50 | `v2ce calibrate` (0.1, 0.5, 1, 2 ms) on the clip, whose real refractory floor (1st percentile of a pixel's intervals) is 1.95 ms |
//! | `cutoff_hz` | Hz at full scale | 200 | 3 kHz at 1 klux \[L08\]; v2e 300 at white | fitted: an effective bandwidth for frame-interpolated input, not the pixel's own |
//! | `dark_current` | fraction of full scale | 0.02 | 120-130 dB range \[L08, B14\] (the photodiode's is far lower) | the frames' noise floor: read noise of dark APS pixels would otherwise fire |
//! | `linlog_knee` | fraction of full scale | 0.08 | v2e linear below 20/255 | as `dark_current` |
//! | `leak_hz` | events/px/s | 0.001 | ~0.2 measured \[DND\]; v2e 0.01 in normal light | `v2ce calibrate` on the clip's static pixels: 0.0011 |
//! | `shot_noise_hz` | events/px/s, dark | 0 | ~10 in low light \[DND\]; v2e 0.001 good light, 5 noisy | as `leak_hz`: the daylight clip's static pixels fire 96% ON, no OFF beyond the model's own |
//! | `hot_pixel_fraction`, `hot_pixel_hz` | -, events/s | 1e-4, 2 | not published | assumption |
//! | `scene_level`, `exposure_us` | fraction, us | 0.303, 500 | - | the clip's first APS frame |
//! | `flicker_hz`, `flicker_depth` | Hz, - | 0, 0 | mains lamps 100/120 Hz | per scene: `v2ce calibrate` |
//!
//! **Work follows scene activity.** The frame is cut into tiles; a tile whose pixels are
//! identical to the previous frame and whose pixels have settled (filter at its input, nothing
//! pending) is skipped after a comparison of its rows, so a static scene costs little more than
//! reading the frame.
//!
//! The same seed gives the same events; mismatch and hot pixels are drawn from it once, noise
//! from it and the frame index.

mod ahead;
mod band;
mod config;
mod crossings;
mod leak;
mod stats;

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal, Poisson};
use rand_xoshiro::Xoshiro256PlusPlus;

use super::motion::{Motion, MotionStats, Subframed, Subframes};
use crate::error::{Error, Result};
use crate::event::{sort_events, Event};
use crate::frame::{Frame, FULL_SCALE};

pub use config::{LightModel, PhysicsConfig, Preset, MAX_NOISE_HZ};
pub use stats::PhysicsStats;

/// The simulator state for one sensor.
pub struct PhysicsSim {
    cfg: PhysicsConfig,
    width: u16,
    height: u16,
    seed: u64,
    /// `L` for every 16-bit luminance value.
    log_lut: Vec<f32>,
    /// The filter-table row ([`filter_index`]) of every 16-bit luminance value at the current
    /// `photo_scale`.
    filter_rows: Vec<u8>,
    prev_luma: Vec<u16>,
    prev_t: Option<i64>,
    l_in: Vec<f32>,
    l_p: Vec<f32>,
    l_ref: Vec<f32>,
    /// Each pixel's thresholds for its next event: its own, moved by the threshold noise
    /// drawn at its last event of that polarity.
    thr_on: Vec<f32>,
    thr_off: Vec<f32>,
    /// Each pixel's own thresholds (the mismatch), which the noise is drawn around; empty
    /// without threshold noise.
    own_on: Vec<f32>,
    own_off: Vec<f32>,
    /// Each pixel's events so far (wrapping), which keys its threshold noise's draws; empty
    /// without threshold noise.
    fired: Vec<u32>,
    last_event: Vec<i64>,
    /// Per tile: every pixel is at rest (filter settled, nothing pending).
    settled: Vec<bool>,
    hot: Vec<u32>,
    leak: leak::Leak,
    /// Frame values per unit of calibration light in the current frame: `log_lut` and the
    /// filter rows read a value `v` as `v / light_scale` of the calibration scene's full scale.
    light_scale: f64,
    /// Frame values per unit of calibration light for the photoreceptor's bandwidth and shot
    /// noise (differs from `light_scale` under the exposure model only).
    photo_scale: f64,
    /// The scene's light relative to the calibration scene's, at `first_exposure` (scene and
    /// frame light models), once set.
    reference: Option<f64>,
    /// The exposure of the first frame that reported one, us.
    first_exposure: Option<u32>,
    /// A frame without an exposure under `light = "exposure"` has been reported.
    warned_exposure: bool,
    /// Sub-frames along the flow (`motion = "flow"`); away while the worker has it.
    motion: Option<Subframes>,
    /// The motion model's counters as they were when it left for the worker.
    motion_stats: MotionStats,
    /// Buffers of the last interval's sub-frames, for the motion model to reuse.
    spare: Option<Subframed>,
    /// An offline run: the next interval's motion is found while this one is stepped.
    look_ahead: bool,
    /// The worker that finds it, once started.
    ahead: Option<ahead::Ahead>,
    /// The wall time of the last step, its interval and whether it ran through sub-frames,
    /// for the motion model's cap keeper while the worker had it.
    unspent: Option<(f64, i64, bool)>,
    /// Scratch of the bands a frame is stepped in (see [`band`]).
    scratch: Vec<band::Scratch>,
    /// Each band's events, before they join the frame's.
    spill: Vec<Vec<Event>>,
    /// Events of the frame being stepped that memory could not hold: the frame is refused.
    unheld: u64,
    stats: PhysicsStats,
}

/// Most sub-steps per pixel and frame interval under flickering light (`max_substeps` if
/// higher): eight per cycle of 100 Hz flicker over a 1.28 s gap.
const FLICKER_MAX_SUBSTEPS: u32 = 1024;

/// A frame sets the scene's level when its mean is at least this many of its source's
/// quantization steps.
const MIN_STEPS: f64 = 8.0;

/// The source's quantization step, as seen in a frame: the smallest difference between two
/// levels present in it (257 for 8-bit linear values, 1 for 16-bit ones); `u16::MAX` for a flat
/// frame.
fn quantization_step(luma: &[u16]) -> u16 {
    let mut present = vec![false; FULL_SCALE as usize + 1];
    for &v in luma {
        present[v as usize] = true;
    }
    let mut step = u16::MAX;
    let mut last: Option<usize> = None;
    for (v, &p) in present.iter().enumerate() {
        if p {
            if let Some(l) = last {
                step = step.min((v - l) as u16);
            }
            last = Some(v);
        }
    }
    step
}

/// The mean of `frame` (a fraction of full scale) if it can set a scene's level under the
/// scene light model: at least `MIN_STEPS` of the source's quantization steps.
fn scene_mean(frame: &Frame) -> Option<f64> {
    let n = frame.luma.len().max(1);
    // Summed as integers (exact, and on vectors): a frame's sum fits in u64 by far.
    let mean = frame.luma.iter().map(|&v| u64::from(v)).sum::<u64>() as f64 / n as f64;
    (mean >= MIN_STEPS * quantization_step(&frame.luma) as f64).then_some(mean / FULL_SCALE as f64)
}

/// The `exposure_us` that makes `light = "exposure"` see `frames` (a recording from the
/// sensor `cfg` was fitted to, with its exposures) as the scene model sees them: the exposure
/// at which the scene's mean would be `scene_level`. `None` when the frame that sets the
/// scene's level has no exposure.
pub fn reference_exposure(cfg: &PhysicsConfig, frames: &[Frame]) -> Option<f64> {
    let (mean, frame) = frames.iter().find_map(|f| scene_mean(f).map(|m| (m, f)))?;
    let e = frame.exposure_us.filter(|&e| e > 0)? as f64;
    Some(
        if cfg.light == LightModel::Frame || cfg.scene_level <= 0.0 {
            e
        } else {
            e * cfg.scene_level / mean
        },
    )
}

/// The filter-table row of luminance `v` (`inv_g`: 1 over the scene's light scale): 256 rows
/// over the calibration scene's full range.
fn filter_index(v: u16, inv_g: f32) -> usize {
    if inv_g == 1.0 {
        (v >> 8) as usize
    } else {
        ((v as f32 * inv_g) as u32 >> 8).min(255) as usize
    }
}

/// The log front end at light `i`, a fraction of the calibration scene's full scale (above 1
/// for a brighter scene).
fn log_response(i: f64, cfg: &PhysicsConfig) -> f64 {
    let x = i + cfg.dark_current;
    let k = cfg.linlog_knee;
    if x >= k {
        x.ln()
    } else {
        k.ln() + (x - k) / k
    }
}

/// [`log_response`] of every 16-bit frame value at `g` frame values per unit of calibration
/// light.
fn log_table(cfg: &PhysicsConfig, g: f64) -> Vec<f32> {
    let scale = 1.0 / (FULL_SCALE as f64 * g);
    (0..=FULL_SCALE as u32)
        .map(|v| log_response(v as f64 * scale, cfg) as f32)
        .collect()
}

/// A pixel left to the slow path by [`PhysicsSim::row`]: its index, column, row and light at
/// the interval's end.
#[derive(Debug, Clone, Copy)]
struct SlowPixel {
    i: usize,
    x: u16,
    y: u16,
    v: u16,
}

/// The photoreceptor at one light level over a frame interval.
#[derive(Debug, Clone, Copy, Default)]
struct FilterRow {
    /// Time constant, us (0: an instant pixel).
    tau: f32,
    /// `e^(-dt/tau)` over the frame interval.
    decay: f32,
    /// Amplitude of the flicker in the filtered log response (0: steady light).
    amp: f32,
    /// The flicker's phase lag behind the light, radians.
    lag: f32,
}

/// Memory the pixel model and the frames and events around it take per pixel, checked before
/// anything is allocated (measured: 3.15 GB peak converting two 8192 x 8192 frames).
const BYTES_PER_PIXEL: u64 = 48;

impl PhysicsSim {
    /// A simulator for a `width x height` sensor; `seed` fixes mismatch, hot pixels and noise.
    pub fn new(cfg: PhysicsConfig, width: u16, height: u16, seed: u64) -> Result<Self> {
        cfg.validate()?;
        crate::limits::frame_size("frame size", width.into(), height.into())?;
        let n = width as usize * height as usize;
        let per_pixel = BYTES_PER_PIXEL
            + if cfg.leak_hz > 0.0 {
                leak::BYTES_PER_PIXEL
            } else {
                0
            }
            + if cfg.threshold_noise > 0.0 { 12 } else { 0 }
            + match cfg.motion {
                Motion::Linear => 0,
                Motion::Flow => super::motion::bytes_per_pixel(cfg.max_subframes, cfg.flow_backend),
            };
        crate::limits::memory(
            "frame size",
            n as u64 * per_pixel,
            &format!("{width} x {height} in the pixel model"),
        )?;
        let log_lut = log_table(&cfg, 1.0);
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed ^ 0x005E_ED0F_71C5);
        let mut draw = |mean: f64| -> Vec<f32> {
            match Normal::new(mean, cfg.threshold_sigma) {
                Ok(d) if cfg.threshold_sigma > 0.0 => (0..n)
                    .map(|_| d.sample(&mut rng).max(0.01) as f32)
                    .collect(),
                _ => vec![mean as f32; n],
            }
        };
        let thr_on = draw(cfg.threshold_on);
        let thr_off = draw(cfg.threshold_off);
        let (own_on, own_off, fired) = if cfg.threshold_noise > 0.0 {
            (thr_on.clone(), thr_off.clone(), vec![0; n])
        } else {
            (Vec::new(), Vec::new(), Vec::new())
        };
        let hot_count = (cfg.hot_pixel_fraction * n as f64).round() as usize;
        let mut hot: Vec<u32> = (0..hot_count).map(|_| rng.gen_range(0..n as u32)).collect();
        hot.sort_unstable();
        hot.dedup();
        let tiles = (width as usize).div_ceil(cfg.tile as usize)
            * (height as usize).div_ceil(cfg.tile as usize);
        let motion = match cfg.motion {
            Motion::Linear => None,
            Motion::Flow => Some(Subframes::new(
                (cfg.flow_backend, cfg.flow_preset),
                cfg.max_step_px,
                cfg.max_subframes,
                width,
                height,
            )?),
        };
        Ok(PhysicsSim {
            motion,
            motion_stats: MotionStats::default(),
            spare: None,
            look_ahead: false,
            ahead: None,
            unspent: None,
            scratch: Vec::new(),
            spill: Vec::new(),
            unheld: 0,
            width,
            height,
            seed,
            log_lut,
            filter_rows: Vec::new(),
            prev_luma: Vec::new(),
            prev_t: None,
            l_in: vec![0.0; n],
            l_p: vec![0.0; n],
            l_ref: vec![0.0; n],
            thr_on,
            thr_off,
            own_on,
            own_off,
            fired,
            last_event: vec![i64::MIN / 2; n],
            settled: vec![false; tiles],
            hot,
            leak: leak::Leak::new(cfg.leak_hz, seed),
            cfg,
            light_scale: 1.0,
            photo_scale: 1.0,
            reference: None,
            first_exposure: None,
            warned_exposure: false,
            stats: PhysicsStats::default(),
        })
    }

    /// The counters so far.
    pub fn stats(&self) -> PhysicsStats {
        let mut stats = self.stats;
        if let Some(m) = &self.motion {
            stats.motion = m.stats();
        } else if self.cfg.motion == Motion::Flow {
            stats.motion = self.motion_stats;
        }
        stats
    }

    /// A live run at `speed` (frames come at their times divided by it): the sub-frame cap
    /// of `motion = "flow"` follows the time each interval takes, so the program lowers its
    /// accuracy before the pipeline has to drop frames (see [`Subframes::spent`]).
    pub fn pace(&mut self, speed: f64) {
        self.look_ahead = false;
        if let Some(m) = &mut self.motion {
            m.pace(speed);
        }
    }

    /// [`PhysicsSim::step_next`] finds the next interval's motion on a thread of its own
    /// while it steps the current one (see [`ahead`]): offline, or live after
    /// [`PhysicsSim::pace`] (the sub-frame cap then follows the time the steps take here).
    /// With one thread (`V2CE_THREADS=1`) everything runs in turn on the caller's.
    pub fn look_ahead(&mut self) {
        self.look_ahead = self.motion.is_some() && crate::parallel::threads() > 1;
    }

    /// [`PhysicsSim::look_ahead`] was called and there is a motion model to look ahead with.
    pub fn looks_ahead(&self) -> bool {
        self.look_ahead
    }

    /// Takes the next frame and appends the events of the interval since the previous one to
    /// `out`, sorted by [`Event::order_key`]. The first frame only sets the state.
    pub fn step(&mut self, frame: &Frame, out: &mut Vec<Event>) -> Result<()> {
        self.step_next(frame, None, out)
    }

    /// [`PhysicsSim::step`], told the frame that comes after `frame` where it is known, so
    /// that the next interval's motion can be found while this one is stepped (after
    /// [`PhysicsSim::look_ahead`]). The events are the same as without.
    pub fn step_next(
        &mut self,
        frame: &Frame,
        next: Option<&Frame>,
        out: &mut Vec<Event>,
    ) -> Result<()> {
        let n = self.width as usize * self.height as usize;
        if (frame.width, frame.height) != (self.width, self.height) || frame.luma.len() != n {
            return Err(Error::invalid(
                "frame",
                format!(
                    "{} x {} ({} values) for a {} x {} sensor",
                    frame.width,
                    frame.height,
                    frame.luma.len(),
                    self.width,
                    self.height
                ),
            ));
        }
        // Times in range and spans exact as f64 (the filter's decay finite), before any state
        // changes.
        crate::time::check("frame time", frame.t)?;
        if let Some(t0) = self.prev_t.filter(|&t0| frame.t > t0) {
            crate::time::span("frame interval", t0, frame.t)?;
        }
        let before = self.light_scale;
        let (g, photo) = self.frame_light(frame);
        if g != self.light_scale {
            self.light_scale = g;
            self.log_lut = log_table(&self.cfg, g);
        }
        if photo != self.photo_scale || self.filter_rows.is_empty() {
            let inv_g = (1.0 / photo) as f32;
            self.filter_rows = (0..=u16::MAX)
                .map(|v| filter_index(v, inv_g) as u8)
                .collect();
        }
        self.photo_scale = photo;
        let Some(t0) = self.prev_t else {
            for (i, &v) in frame.luma.iter().enumerate() {
                let l = self.log_lut[v as usize];
                self.l_in[i] = l;
                self.l_p[i] = l;
                self.l_ref[i] = l;
            }
            self.prev_luma.clone_from(&frame.luma);
            self.prev_t = Some(frame.t);
            // Under flickering light a pixel at rest may still fire: the first interval
            // finds out which. Each pixel's memorised level was set by its last event, at a
            // phase of the flicker this model cannot know: drawn once per pixel, so a swing
            // wider than the threshold but narrower than twice it fires at some pixels.
            let steady = self.cfg.flicker_hz <= 0.0 || self.cfg.flicker_depth <= 0.0;
            self.settled.iter_mut().for_each(|s| *s = steady);
            if !steady {
                let table = self.filter_table(0.0);
                let inv_g = (1.0 / self.photo_scale) as f32;
                let mut rng = Xoshiro256PlusPlus::seed_from_u64(self.seed ^ 0xF11C_4E12);
                for (i, &v) in frame.luma.iter().enumerate() {
                    let row = table[filter_index(v, inv_g)];
                    let phase: f32 = rng.gen_range(0.0..std::f32::consts::TAU);
                    self.l_ref[i] += row.amp * phase.sin();
                }
            }
            self.stats.frames += 1;
            return Ok(());
        };
        if frame.t <= t0 {
            return Err(Error::invalid(
                "frame time",
                format!("{} us does not come after {t0} us", frame.t),
            ));
        }
        let started = std::time::Instant::now();
        let start = out.len();
        let mut stepped = false;
        // `prev_luma` is in the previous frame's units of light, the sub-frames in this
        // frame's (an exposure change between them is not a change of light).
        let scale0 = (g / before) as f32;
        if let Some(mut motion) = self.motion_for(frame, scale0, t0)? {
            let used = motion.take();
            self.send_ahead(motion, frame, next, g);
            if !used.frames.is_empty() {
                // Through the sub-frames where the scene moves, each tile through as many as
                // it needs, at once elsewhere.
                let (steps, k) = (&used.steps, used.frames.len() + 1);
                let mut present = [false; 256];
                steps.iter().for_each(|&d| present[usize::from(d)] = true);
                let mut passes = Vec::new();
                for d in (2..=u8::MAX).filter(|&d| present[usize::from(d)]) {
                    let mut t = t0;
                    for (t_sub, luma) in used
                        .frames
                        .iter()
                        .skip(k / d as usize - 1)
                        .step_by(k / d as usize)
                    {
                        passes.push(self.pass(luma, t, *t_sub, Some((steps, d))));
                        t = *t_sub;
                    }
                    passes.push(self.pass(&frame.luma, t, frame.t, Some((steps, d))));
                }
                passes.push(self.pass(&frame.luma, t0, frame.t, Some((steps, 1))));
                self.advance(&passes, out);
                stepped = true;
            }
            self.spare = Some(used);
        }
        if !stepped {
            let pass = self.pass(&frame.luma, t0, frame.t, None);
            self.advance(&[pass], out);
        }
        self.stats.signal_events += (out.len() - start) as u64;
        self.noise(t0, frame, out);
        self.prev_t = Some(frame.t);
        self.stats.frames += 1;
        if std::mem::take(&mut self.unheld) > 0 {
            let held = out.len() - start;
            out.truncate(start);
            return Err(Error::invalid(
                "frame",
                format!(
                    "the frame at {} us produced more events than memory holds ({held} held, \
                     the rest refused): lower its size, the frame rate's gaps or the \
                     thresholds' sensitivity",
                    frame.t
                ),
            ));
        }
        sort_events(&mut out[start..]);
        let spent = (started.elapsed().as_secs_f64(), frame.t - t0, stepped);
        match &mut self.motion {
            Some(motion) => motion.spent(spent.0, spent.1, spent.2),
            // With the worker: told when it comes back.
            None => self.unspent = Some(spent),
        }
        Ok(())
    }

    /// The motion model with the sub-frames of the interval from `t0` to `frame` computed:
    /// those the worker found ahead if it found them from exactly these inputs, else found
    /// here. `None` without a motion model.
    fn motion_for(&mut self, frame: &Frame, scale0: f32, t0: i64) -> Result<Option<Subframes>> {
        let tile = self.cfg.tile as usize;
        let unspent = self.unspent.take();
        let mut motion = match self.ahead.as_mut().map(|a| a.wait()).transpose()?.flatten() {
            Some(done) => {
                let job = done.job;
                let same = (job.t0, job.t1) == (t0, frame.t)
                    && job.scale0.to_bits() == scale0.to_bits()
                    && job.tile == tile
                    && job.f0 == self.prev_luma
                    && job.f1 == frame.luma;
                let mut motion = job.motion;
                if !same {
                    motion.restore_stats(done.before);
                }
                if let Some((seconds, span, subframed)) = unspent {
                    motion.spent(seconds, span, subframed);
                }
                if same {
                    return Ok(Some(motion));
                }
                motion
            }
            None => match self.motion.take() {
                Some(motion) => motion,
                None => return Ok(None),
            },
        };
        if let Some(used) = self.spare.take() {
            motion.give_back(used);
        }
        motion.compute(&self.prev_luma, scale0, &frame.luma, t0, frame.t, tile);
        Ok(Some(motion))
    }

    /// Hands `motion` to the worker with the interval from `frame` to `next` when looking
    /// ahead, or keeps it. `g`: `frame`'s light scale.
    fn send_ahead(&mut self, mut motion: Subframes, frame: &Frame, next: Option<&Frame>, g: f64) {
        self.motion_stats = motion.stats();
        let next =
            next.filter(|n| self.look_ahead && n.t > frame.t && n.luma.len() == frame.luma.len());
        let (Some(next), Some(scale0)) = (next, next.and_then(|n| self.next_scale(n, g))) else {
            self.motion = Some(motion);
            return;
        };
        if self.ahead.is_none() {
            match ahead::Ahead::start() {
                Ok(a) => self.ahead = Some(a),
                Err(e) => {
                    tracing::warn!("{e}: the motion is found in turn");
                    self.look_ahead = false;
                    self.motion = Some(motion);
                    return;
                }
            }
        }
        if let Some(used) = self.spare.take() {
            motion.give_back(used);
        }
        let job = ahead::Job {
            motion,
            f0: frame.luma.clone(),
            scale0,
            f1: next.luma.clone(),
            t0: frame.t,
            t1: next.t,
            tile: self.cfg.tile as usize,
        };
        if let Some(Err(job)) = self.ahead.as_mut().map(|a| a.send(job)) {
            self.motion = Some(job.motion);
        }
    }

    /// The factor that will bring `frame`'s light into `next`'s units at the next step
    /// ([`PhysicsSim::frame_light`]'s scale of `next` over `g`), if it can be told now: not
    /// before the scene's level is set (the frame that sets it starts the pixels over).
    fn next_scale(&self, next: &Frame, g: f64) -> Option<f32> {
        let reference = self.reference?;
        let exposure = next.exposure_us.filter(|&e| e > 0);
        let ratio = match (exposure, self.first_exposure.or(exposure)) {
            (Some(e), Some(e0)) => e as f64 / e0 as f64,
            _ => 1.0,
        };
        Some(((reference * ratio).clamp(1e-4, 1e4) / g) as f32)
    }

    /// Frame values per unit of calibration light in `frame` (see [`LightModel`]): for the
    /// log front end (the scene model's scale, which also sets the frames' noise floor: the
    /// dark current and knee act on frame values), and for the photoreceptor (its bandwidth
    /// and shot noise: absolute under the exposure model). Under the scene model the scene's
    /// level comes from its first frame that is not nearly black: a mean of at least
    /// `MIN_STEPS` of the source's quantization steps (a video that fades in from black would
    /// otherwise set the dark current and knee so low that its dark noise fires). Until then
    /// the preset's own values hold, and the pixels start over from the frame that sets it.
    fn frame_light(&mut self, frame: &Frame) -> (f64, f64) {
        let cfg = &self.cfg;
        let exposure = frame.exposure_us.filter(|&e| e > 0);
        if self.first_exposure.is_none() {
            self.first_exposure = exposure;
        }
        // Frame values per unit of light, relative to the first frame with an exposure.
        let ratio = match (exposure, self.first_exposure) {
            (Some(e), Some(e0)) => e as f64 / e0 as f64,
            _ => 1.0,
        };
        if self.reference.is_none() {
            if cfg.light == LightModel::Frame || cfg.scene_level <= 0.0 {
                self.reference = Some(1.0);
            } else if let Some(mean) = scene_mean(frame) {
                self.reference = Some((mean / cfg.scene_level / ratio).clamp(1e-4, 1e4));
                self.prev_t = None;
            }
        }
        let scene = (self.reference.unwrap_or(1.0) * ratio).clamp(1e-4, 1e4);
        if cfg.light != LightModel::Exposure {
            return (scene, scene);
        }
        match exposure {
            Some(e) => (scene, (e as f64 / cfg.exposure_us).clamp(1e-4, 1e4)),
            None => {
                if !self.warned_exposure {
                    self.warned_exposure = true;
                    tracing::warn!(
                        "light = \"exposure\": a frame at {} us has no exposure time; its \
                         light is taken relative to the scene instead",
                        frame.t
                    );
                }
                (scene, scene)
            }
        }
    }

    /// A step of the tiles `only` selects (all with `None`) to the light `luma` at `t1`
    /// from `t0` (see [`band::Pass`]).
    fn pass<'a>(
        &self,
        luma: &'a [u16],
        t0: i64,
        t1: i64,
        only: Option<(&'a [u8], u8)>,
    ) -> band::Pass<'a> {
        band::Pass {
            luma,
            t0,
            t1,
            only,
            filter: self.filter_table((t1 - t0) as f64),
        }
    }

    /// The photoreceptor at each of 256 light levels, relative to the scene's (see
    /// [`filter_index`]), over a frame interval of `dt` us.
    fn filter_table(&self, dt: f64) -> Vec<FilterRow> {
        let cfg = &self.cfg;
        let flicker = cfg.flicker_hz > 0.0 && cfg.flicker_depth > 0.0;
        (0..256)
            .map(|b| {
                let intensity = (b as f64 + 0.5) / 256.0;
                let fc = cfg.cutoff_hz * (intensity + cfg.dark_current) / (1.0 + cfg.dark_current);
                let (tau, decay) = if cfg.cutoff_hz > 0.0 {
                    let tau = 1e6 / (2.0 * std::f64::consts::PI * fc.max(1e-3));
                    (tau, (-dt / tau).exp())
                } else {
                    (0.0, 0.0)
                };
                // The flicker's log amplitude, diluted by the dark current and passed by the
                // first-order low-pass with its gain and phase lag at the flicker frequency.
                let (amp, lag) = if flicker {
                    let ratio = if cfg.cutoff_hz > 0.0 {
                        cfg.flicker_hz / fc.max(1e-3)
                    } else {
                        0.0
                    };
                    let dilution = intensity / (intensity + cfg.dark_current);
                    (
                        cfg.flicker_depth.atanh() * dilution / (1.0 + ratio * ratio).sqrt(),
                        ratio.atan(),
                    )
                } else {
                    (0.0, 0.0)
                };
                FilterRow {
                    tau: tau as f32,
                    decay: decay as f32,
                    amp: amp as f32,
                    lag: lag as f32,
                }
            })
            .collect()
    }

    /// Sparse noise events in `(t0, frame.t]`.
    fn noise(&mut self, t0: i64, frame: &Frame, out: &mut Vec<Event>) {
        let light_scale = self.photo_scale;
        let cfg = &self.cfg;
        // Noise over the interval's last MAX_NOISE_SPAN_US at most: a longer gap is a break in
        // the input, and drawing its noise would cost time in proportion to the gap.
        let t0 = t0.max(frame.t.saturating_sub(MAX_NOISE_SPAN_US));
        let dt_s = (frame.t - t0) as f64 * 1e-6;
        let n = self.width as usize * self.height as usize;
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(
            self.seed ^ (self.stats.frames.wrapping_mul(0x9E37_79B9_7F4A_7C15)),
        );
        let count = |rate: f64, rng: &mut Xoshiro256PlusPlus| -> u64 {
            let mean = rate * dt_s;
            match Poisson::new(mean) {
                Ok(p) if mean > 0.0 => p.sample(rng) as u64,
                _ => 0,
            }
        };
        let before = out.len();
        let w = self.width as usize;
        self.leak.fire(
            (t0, frame.t),
            &mut self.last_event,
            cfg.refractory_us,
            w,
            out,
        );
        let mut emit = |i: usize, on: bool, rng: &mut Xoshiro256PlusPlus, last: &mut [i64]| {
            let t = rng.gen_range(t0 + 1..=frame.t);
            if ((t - last[i]) as f64) >= cfg.refractory_us && crate::limits::room_for_one(out) {
                last[i] = last[i].max(t);
                out.push(Event::new(t, (i % w) as u16, (i / w) as u16, on));
            }
        };
        for _ in 0..count(cfg.shot_noise_hz * n as f64, &mut rng) {
            let i = rng.gen_range(0..n);
            let intensity = frame.luma[i] as f64 / FULL_SCALE as f64;
            if rng.gen::<f64>() < 1.0 / (1.0 + intensity / (SHOT_HALF_LIGHT * light_scale)) {
                let on = rng.gen::<bool>();
                emit(i, on, &mut rng, &mut self.last_event);
            }
        }
        for h in 0..self.hot.len() {
            let i = self.hot[h] as usize;
            for _ in 0..count(cfg.hot_pixel_hz, &mut rng) {
                emit(i, true, &mut rng, &mut self.last_event);
            }
        }
        self.stats.noise_events += (out.len() - before) as u64;
    }
}

/// The light (fraction of full scale, at the calibration scene's level) at which shot noise
/// fires half its dark rate: it is thinned by `1 / (1 + I / SHOT_HALF_LIGHT)`.
pub const SHOT_HALF_LIGHT: f64 = 0.05;

/// The longest stretch of an interval whose noise is drawn, us (see `PhysicsSim::noise`).
pub const MAX_NOISE_SPAN_US: i64 = 1_000_000;

/// The physics tier behind the [`Stage1`](super::Stage1) trait: a window of one interval.
/// In `events` output the model's own events pass on; in `voxels` output each interval's events
/// are voxelized for Stage 2 to re-time.
pub struct PhysicsStage1 {
    config: super::Stage1Config,
    bins: usize,
    size: (u16, u16),
    sim: PhysicsSim,
    voxelizer: Option<crate::voxel::Voxelizer>,
    previous: Option<i64>,
    scratch: Vec<Event>,
    // Counters of the simulations before the last restart.
    earlier: PhysicsStats,
    /// A live run's speed (see [`super::Stage1::pace`]), kept across restarts.
    speed: Option<f64>,
    /// An offline run with motion, or a live one within its budget: one frame is held back
    /// (see [`super::Stage1::look_ahead`]).
    look_ahead: bool,
    /// A live run's most frame time between a held frame and the next (see
    /// [`super::Stage1::look_ahead_within`]), us; frames further apart are not held.
    hold_within: Option<i64>,
    /// The frame held back.
    held: Option<Frame>,
}

impl PhysicsStage1 {
    /// The counters so far, across restarts.
    fn counters(&self) -> PhysicsStats {
        let mut physics = self.earlier;
        physics.add(self.sim.stats());
        physics
    }

    /// The configured preset and overrides for `size` frames; `bins` nodes per voxel.
    pub fn new(config: &super::Stage1Config, bins: usize, size: (u16, u16)) -> Result<Self> {
        let voxelizer = match config.output {
            super::Stage1Output::Voxels => {
                // The grid at its fullest (every pixel firing both ways) with the voxelizer.
                let bytes = crate::voxel::VoxelGrid::max_bytes(size.0, size.1, bins)
                    + crate::voxel::Voxelizer::fixed_bytes(size.0, size.1);
                crate::limits::memory(
                    "frame size",
                    bytes,
                    &format!("a {} x {} voxel grid of {bins} nodes", size.0, size.1),
                )?;
                Some(crate::voxel::Voxelizer::new(size.0, size.1, bins)?)
            }
            super::Stage1Output::Events => None,
        };
        Ok(PhysicsStage1 {
            sim: PhysicsSim::new(config.physics_config(), size.0, size.1, config.seed)?,
            config: config.clone(),
            bins,
            size,
            voxelizer,
            previous: None,
            scratch: Vec::new(),
            earlier: PhysicsStats::default(),
            speed: None,
            look_ahead: false,
            hold_within: None,
            held: None,
        })
    }
}

impl PhysicsStage1 {
    /// Holds a frame back while the next comes at most `most` us of frame time later.
    fn hold_within(&mut self, most: i64) {
        self.sim.look_ahead();
        self.look_ahead = self.sim.looks_ahead();
        self.hold_within = Some(most);
    }

    /// Steps `frame` (with the frame after it, where known) and appends its interval's batch.
    fn process(
        &mut self,
        frame: &Frame,
        next: Option<&Frame>,
        out: &mut Vec<super::Stage1Batch>,
    ) -> Result<()> {
        let previous = self.previous.replace(frame.t);
        match (&mut self.voxelizer, previous) {
            (Some(voxelizer), Some(t0)) => {
                self.scratch.clear();
                self.sim.step_next(frame, next, &mut self.scratch)?;
                // Events of (t0, t1] voxelized on [t0, t1): one at t1 lands on the last node.
                let interval = crate::interval::Interval::new(t0, frame.t)?;
                let mut grid = crate::voxel::VoxelGrid::new(self.size.0, self.size.1, self.bins)?;
                voxelizer.voxelize_into(&self.scratch, interval, &mut grid)?;
                out.push(super::Stage1Batch::Voxels(grid, interval));
            }
            (_, None) => {
                // The first frame only sets the pixels: no interval ends here.
                self.scratch.clear();
                self.sim.step_next(frame, next, &mut self.scratch)?;
            }
            (None, Some(_)) => {
                let mut events = Vec::new();
                self.sim.step_next(frame, next, &mut events)?;
                out.push(super::Stage1Batch::Events {
                    events,
                    end: frame.t,
                });
            }
        }
        Ok(())
    }
}

impl super::Stage1 for PhysicsStage1 {
    fn push(&mut self, frame: &Frame, out: &mut Vec<super::Stage1Batch>) -> Result<()> {
        if !self.look_ahead {
            return self.process(frame, None, out);
        }
        // One frame held back: its interval is stepped once the next frame is known.
        if let Some(held) = self.held.take() {
            self.process(&held, Some(frame), out)?;
        }
        // A live run does not hold a frame that far from the last: it goes now (its motion
        // found while the last one was stepped, where that one was held).
        let far = |most: i64, last: i64| frame.t.saturating_sub(last) > most;
        if let (Some(most), Some(last)) = (self.hold_within, self.previous) {
            if far(most, last) {
                return self.process(frame, None, out);
            }
        }
        self.held = Some(frame.clone());
        Ok(())
    }

    fn finish(&mut self, out: &mut Vec<super::Stage1Batch>) -> Result<()> {
        // Every interval is emitted when its frame arrives, or with the next one when
        // looking ahead: the frame held back goes now.
        match self.held.take() {
            Some(held) => self.process(&held, None, out),
            None => Ok(()),
        }
    }

    /// The sensor's fixed pattern (threshold mismatch, hot pixels) stays the same, since it
    /// comes from the same seed.
    fn restart(&mut self) -> Result<()> {
        let mut earlier = self.counters();
        let (speed, look_ahead, within) = (self.speed, self.look_ahead, self.hold_within);
        *self = PhysicsStage1::new(&self.config, self.bins, self.size)?;
        std::mem::swap(&mut self.earlier, &mut earlier);
        if let Some(speed) = speed {
            super::Stage1::pace(self, speed);
        }
        match within {
            Some(most) if look_ahead => self.hold_within(most),
            _ if look_ahead => super::Stage1::look_ahead(self),
            _ => {}
        }
        Ok(())
    }

    fn output_size(&self) -> (u16, u16) {
        self.size
    }

    fn stats(&self) -> super::Stage1Stats {
        let physics = self.counters();
        super::Stage1Stats {
            tier: <PhysicsStats as super::TierRecord>::TIER,
            window: 1,
            stride: 1,
            record: std::sync::Arc::new(physics),
            ..Default::default()
        }
    }

    fn pace(&mut self, speed: f64) {
        self.speed = Some(speed);
        (self.look_ahead, self.hold_within) = (false, None);
        self.sim.pace(speed);
    }

    fn look_ahead_within(&mut self, most: std::time::Duration) {
        if let Some(speed) = self.speed {
            // In frame time: a replay at twice real time has frames twice as far apart.
            let us = most.as_secs_f64() * 1e6 * speed;
            self.hold_within(if us.is_finite() { us as i64 } else { 0 });
        }
    }

    fn look_ahead(&mut self) {
        if self.speed.is_none() {
            self.sim.look_ahead();
            self.look_ahead = self.sim.looks_ahead();
        }
    }

    fn describe(&self) -> String {
        format!(
            "physics (preset {}, {})",
            self.config.preset_name(),
            match self.config.output {
                super::Stage1Output::Events => "events",
                super::Stage1Output::Voxels => "voxels re-timed by Stage 2",
            }
        )
    }
}
