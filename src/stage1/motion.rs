//! Motion between frames for the pixel model: sub-frames warped along the optical flow.
//!
//! Between two frames the pixel model interpolates each pixel's light linearly in time; an
//! edge that moves several pixels per frame then fades out at its old place and in at its new
//! one, and every pixel on its path fires spread over the whole interval, by contrast rather
//! than by the time the edge reached it. With `motion = "flow"`, [`Subframes`] inserts frames
//! between the two at which the scene has moved part of the way:
//!
//! 1. **Is there motion?** Both frames go to 8-bit gamma-encoded gray (the flow's input); an
//!    interval with fewer than `MIN_CHANGED` pixels changed by `CHANGE_LEVELS` levels or more
//!    gets no sub-frames and no flow, so a still scene costs what it did. A frame's gray image
//!    and pyramid ([`crate::flow::Pyramid`]) are built once: the second frame's are kept and
//!    are the next interval's first.
//! 2. **Flow**, forward and backward ([`crate::flow`], the project's DIS by default), on two
//!    threads from the same two pyramids, and only over the tiles where some pixel changed
//!    (and their neighbours): zero elsewhere, so the flow's cost follows the moving area. A
//!    pixel's flow is trusted where the two agree (forward-backward consistency: the forward
//!    vector and the backward vector where it lands cancel to within `0.5 px + 10%`).
//! 3. **Does the flow explain the change?** Warping the first frame along the backward flow
//!    must cut the changed pixels' difference to the second frame to at most `EXPLAINED` of
//!    what it was, and at least `MIN_TRUSTED` of their flow vectors must be trusted.
//!    Otherwise (a scene cut, a lamp switched on, a flash) the interval falls back to linear
//!    interpolation, and the fallback is counted.
//! 4. **How many?** `K = ceil(m / max_step_px)` intervals, `m` the 99th percentile of the
//!    trusted flow's length over the changed pixels, capped by the sub-frame cap
//!    (`max_subframes`, or lower in a live run that needs the time) and by the interval's
//!    microseconds.
//! 5. **Sub-frames** at `tau = k / K`: the flow from the sub-frame to each neighbour is
//!    approximated from the two flows as for linear motion, `F(tau->0) = -(1-tau) tau F01 +
//!    tau^2 F10` and `F(tau->1) = (1-tau)^2 F01 - tau (1-tau) F10` (as in Jiang et al., "Super
//!    SloMo", CVPR 2018); both neighbours are sampled there (bilinear, in **linear light**) and
//!    blended with weights `1 - tau` and `tau`, each neighbour's only where its flow is
//!    trusted (an occluded pixel is seen from the side where it is visible; where neither is,
//!    the plain blend).
//! 6. **Each tile as many as it needs.** A tile whose fastest trusted pixel moves `l` pixels
//!    steps through `d` of the `K` intervals, `d` the smallest divisor of `K` at least
//!    `ceil(l / max_step_px)`: every `K / d`-th sub-frame, so its sub-frames are some of the
//!    `K` (blended only on the tiles that use them; [`Subframed::steps`]). A tile that moves
//!    `max_step_px` or less (`d = 1`) steps across the whole interval at once, as with linear
//!    interpolation, where the pixel model's tile gate skips what did not change. The frames
//!    are blended from a packed copy ([`blend`]: each pixel's value and trust in one word, the
//!    border repeated), a row's pixels at a time.

use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::error::Result;
use crate::flow::{DenseFlow, FlowBackend, FlowPreset, Pyramid, Region};
use crate::frame::color::luma_to_gray as gray;
use crate::parallel::side_by_side;

mod blend;
mod governor;
use blend::{Blend, Packed, RowScratch, BLEND_CHUNK, PACKED_BYTES_PER_PIXEL};
use governor::Governor;
#[cfg(test)]
use governor::{CALM_INTERVALS, LONG_BELOW_S, SETTLE_INTERVALS};

/// How the pixel model sees the light between two frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Motion {
    /// Each pixel's light interpolated linearly (in log) between the frames: exact for a
    /// still camera on a still scene, a fade for anything that moves.
    Linear,
    /// Sub-frames warped along the optical flow, as many as the motion needs (see the
    /// module docs). Every preset's choice.
    #[default]
    Flow,
}

/// A pixel counts as changed when its 8-bit gray value moved by this many levels: about the
/// smallest change that makes an event at mid-gray (a log step of 0.2-0.3 is 16-20 levels at
/// 128), and above the read noise of an APS frame (a few levels), which the flow cannot
/// explain.
const CHANGE_LEVELS: u8 = 16;
/// An interval with fewer changed pixels than this has no motion worth a flow.
const MIN_CHANGED: usize = 16;
/// Warping must leave at most this share of the changed pixels' difference, or the interval
/// falls back to linear interpolation (0.33 on average, 0.68 at most on the bundled walk-by
/// video; 0.66 and 0.80 on the davis346 clip, whose APS read noise stays; 0.79 across a cut
/// between two textures, which the trusted share catches).
const EXPLAINED: f64 = 0.85;
/// The share of the changed pixels' flow vectors (both ways) that must be trusted, or the
/// interval falls back to linear interpolation: 0.78-1 on the davis346 clip, 0.26-1 on the
/// bundled walk-by video (someone crossing a still background occludes much of what moves),
/// 0.06 across a scene cut between two textures.
const MIN_TRUSTED: f64 = 0.15;
/// Frames smaller than this on either side get no flow (DIS's patches and pyramid need room).
const MIN_SIDE: u16 = 16;

/// Memory the motion model takes per pixel beyond the pixel model's, with `max_subframes`
/// and `backend`: the sub-frames (2 bytes each), the kept frame's luminance (2), both flows
/// (16) and their masks (2), the flow lengths (8), the frames packed for the blend
/// ([`blend::Packed`]), and the flow's pyramids and buffers ([`crate::flow::bytes_per_pixel`]).
pub fn bytes_per_pixel(max_subframes: u32, backend: FlowBackend) -> u64 {
    2 * u64::from(max_subframes.max(1) - 1)
        + 2
        + 16
        + 2
        + 8
        + PACKED_BYTES_PER_PIXEL
        + crate::flow::bytes_per_pixel(backend)
}

/// What the motion model did, for the physics tier's record.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct MotionStats {
    /// Intervals whose flow was computed.
    pub flow_intervals: u64,
    /// Sub-frames inserted (over all intervals).
    pub subframes: u64,
    /// Intervals whose flow did not explain the change (scene cut, light change) and that
    /// fell back to linear interpolation.
    pub fallbacks: u64,
    /// Time spent computing flow, us.
    pub flow_us: u64,
    /// Pixels the flow was computed on (its region: the changed tiles and their neighbours),
    /// over all intervals whose flow ran: with `flow_intervals` and the frame's size, the
    /// share of the frame the flow cost.
    pub flow_pixels: u64,
    /// Pixels of a frame.
    pub frame_pixels: u64,
    /// Times a live run lowered the sub-frame cap to keep up.
    pub cap_lowered: u64,
    /// Times a live run raised it again, having time to spare.
    pub cap_raised: u64,
    /// The sub-frame cap now (intervals per frame interval; 1: linear).
    pub cap: u32,
    /// The configured cap (`max_subframes`), the most a live run raises it to.
    pub cap_most: u32,
    /// The cap integrated over the frame time stepped (cap times each interval's us), and
    /// that time, us: their ratio is the cap's time-weighted mean.
    pub cap_us: u64,
    /// See `cap_us`.
    pub paced_us: u64,
}

impl MotionStats {
    /// The sub-frame cap's mean over the frame time stepped, weighted by time; `None` before
    /// any interval.
    pub fn cap_mean(&self) -> Option<f64> {
        (self.paced_us > 0).then(|| self.cap_us as f64 / self.paced_us as f64)
    }
}

impl MotionStats {
    /// Adds another run's counters (the cap and the frame's size are the later run's).
    pub fn add(&mut self, o: MotionStats) {
        self.flow_intervals += o.flow_intervals;
        self.subframes += o.subframes;
        self.fallbacks += o.fallbacks;
        self.flow_us += o.flow_us;
        self.flow_pixels += o.flow_pixels;
        self.frame_pixels = o.frame_pixels;
        self.cap_lowered += o.cap_lowered;
        self.cap_raised += o.cap_raised;
        self.cap = o.cap;
        self.cap_most = o.cap_most;
        self.cap_us = self.cap_us.saturating_add(o.cap_us);
        self.paced_us = self.paced_us.saturating_add(o.paced_us);
    }
}

/// Sub-frames between consecutive frames (see the module docs); kept across frames for its
/// buffers and its flow estimator.
pub struct Subframes {
    /// The forward and backward flows' estimators, run side by side.
    flow: DenseFlow,
    back: DenseFlow,
    /// The interval's two frames: gray images and pyramids.
    p0: Pyramid,
    p1: Pyramid,
    /// The last interval's second frame (its luminance and pyramid), the next one's first
    /// when the values match.
    kept: Pyramid,
    kept_luma: Vec<u16>,
    kept_valid: bool,
    /// The region the flow is computed on (the changed tiles and their neighbours).
    region: Region,
    width: usize,
    height: usize,
    max_step_px: f64,
    max_subframes: u32,
    cap: u32,
    /// A live run's cap keeper; `None` offline.
    live: Option<Governor>,
    warned_error: bool,
    f01: Vec<[f32; 2]>,
    f10: Vec<[f32; 2]>,
    ok0: Vec<bool>,
    ok1: Vec<bool>,
    /// The two frames and their flows' trust, packed for the blend.
    packed: Packed,
    /// Per tile of the last interval: the intervals its pixels step through (see
    /// [`Subframed::steps`]).
    steps: Vec<u8>,
    /// Scratch: per tile, the longest trusted flow of a changed pixel.
    longest: Vec<f32>,
    /// The sub-frames of the last interval: time and linear luminance.
    frames: Vec<(i64, Vec<u16>)>,
    /// `frames` and `steps` hold the last computation's sub-frames.
    ready: bool,
    stats: MotionStats,
}

impl Subframes {
    /// Sub-frames for `width x height` frames: at most `max_subframes` intervals per frame
    /// interval, each moving no pixel more than `max_step_px`.
    pub fn new(
        (backend, preset): (FlowBackend, FlowPreset),
        max_step_px: f64,
        max_subframes: u32,
        width: u16,
        height: u16,
    ) -> Result<Self> {
        Ok(Subframes {
            flow: DenseFlow::new(backend, preset, width, height)?,
            back: DenseFlow::new(backend, preset, width, height)?,
            p0: Pyramid::new(),
            p1: Pyramid::new(),
            kept: Pyramid::new(),
            kept_luma: Vec::new(),
            kept_valid: false,
            region: Region::default(),
            width: width.into(),
            height: height.into(),
            max_step_px,
            max_subframes,
            cap: max_subframes,
            live: None,
            warned_error: false,
            f01: Vec::new(),
            f10: Vec::new(),
            ok0: Vec::new(),
            ok1: Vec::new(),
            packed: Packed::default(),
            steps: Vec::new(),
            longest: Vec::new(),
            frames: Vec::new(),
            ready: false,
            stats: MotionStats {
                cap: max_subframes,
                cap_most: max_subframes,
                frame_pixels: u64::from(width) * u64::from(height),
                ..Default::default()
            },
        })
    }

    /// The counters so far.
    pub fn stats(&self) -> MotionStats {
        self.stats
    }

    /// A live run at `speed`: from now on the cap follows the time each interval takes (see
    /// [`Subframes::spent`]).
    pub fn pace(&mut self, speed: f64) {
        self.live = (speed.is_finite() && speed > 0.0).then(|| Governor::new(speed));
    }

    /// Finds the sub-frames between `f0` at `t0` and `f1` at `t1` (linear luminance, `f0`'s
    /// values multiplied by `scale0` to be in `f1`'s units), in time order, strictly between
    /// the two, with the tiles (`tile` pixels square, row-major) they cover: those where some
    /// pixel moves more than `max_step_px`; the other tiles' values in them are not set, and
    /// those tiles need no more than linear interpolation. They are kept in `self` until
    /// [`Subframes::take`]; returns the number of intervals (1: no sub-frames).
    pub fn compute(
        &mut self,
        f0: &[u16],
        scale0: f32,
        f1: &[u16],
        t0: i64,
        t1: i64,
        tile: usize,
    ) -> usize {
        // The cap this interval runs under, over its frame time.
        let span = t1.saturating_sub(t0).max(0) as u64;
        self.stats.paced_us = self.stats.paced_us.saturating_add(span);
        self.stats.cap_us = self
            .stats
            .cap_us
            .saturating_add(span.saturating_mul(u64::from(self.cap)));
        let k = self.intervals(f0, scale0, f1, t1 - t0, tile);
        self.ready = k > 1;
        if k <= 1 {
            return 1;
        }
        self.stats.subframes += k as u64 - 1;
        self.frames.resize_with(k - 1, || (0, Vec::new()));
        let mut frames = std::mem::take(&mut self.frames);
        for (j, (t, _)) in frames.iter_mut().enumerate() {
            let tau = (j + 1) as f64 / k as f64;
            *t = t0 + ((t1 - t0) as f64 * tau).round() as i64;
        }
        self.packed
            .set((self.width, self.height), (f0, &self.ok0), (f1, &self.ok1));
        // The sub-frames are independent: those of about half the work on a second thread.
        let work: Vec<usize> = (1..k)
            .map(|j| {
                let tiles = self.steps.iter().filter(|&&d| covers(d, j, k)).count();
                tiles * tile * tile
            })
            .collect();
        let total: usize = work.iter().sum();
        let split = crate::parallel::halfway(&work);
        let (first, second) = frames.split_at_mut(split);
        let this = &*self;
        let make = |part: &mut [(i64, Vec<u16>)], offset: usize| {
            for (j, (_, luma)) in part.iter_mut().enumerate() {
                this.synthesize(scale0, offset + j + 1, k, tile, luma);
            }
        };
        side_by_side(
            total >= PARALLEL_PIXELS,
            || make(first, 0),
            || make(second, split),
        );
        self.frames = frames;
        k
    }

    /// The last [`Subframes::compute`]'s sub-frames and tiles, moved out (empty where it found
    /// none); [`Subframes::give_back`] returns their buffers for reuse.
    pub fn take(&mut self) -> Subframed {
        if !std::mem::take(&mut self.ready) {
            return Subframed::default();
        }
        Subframed {
            frames: std::mem::take(&mut self.frames),
            steps: std::mem::take(&mut self.steps),
        }
    }

    /// Buffers of an earlier [`Subframes::take`], to be reused.
    pub fn give_back(&mut self, used: Subframed) {
        if self.frames.is_empty() && !self.ready {
            self.frames = used.frames;
            self.steps = used.steps;
        }
    }

    /// The counters as they were at `stats` (a computation whose result was not used).
    pub fn restore_stats(&mut self, stats: MotionStats) {
        self.stats = stats;
    }

    /// In a live run, the wall time the last interval (`interval_us` of frame time) took,
    /// and whether it was stepped through sub-frames; the cap follows it (see [`Governor`]).
    pub fn spent(&mut self, seconds: f64, interval_us: i64, subframed: bool) {
        let Some(governor) = &mut self.live else {
            return;
        };
        let (cap, most) = (self.cap, self.max_subframes);
        if let Some(cap) = governor.spent(seconds, interval_us, subframed, cap, most) {
            if cap < self.cap {
                self.stats.cap_lowered += 1;
            } else {
                self.stats.cap_raised += 1;
            }
            self.cap = cap;
            self.stats.cap = cap;
        }
    }

    /// How many intervals the frame interval needs (1: no sub-frames).
    fn intervals(
        &mut self,
        f0: &[u16],
        scale0: f32,
        f1: &[u16],
        span_us: i64,
        tile: usize,
    ) -> usize {
        let (w, h) = (self.width, self.height);
        if self.cap <= 1 || span_us < 2 || w < MIN_SIDE as usize || h < MIN_SIDE as usize {
            return 1;
        }
        if scale0 == 1.0 && f0 == f1 {
            return 1;
        }
        self.load(f0, scale0, f1);
        let k = self.flow_intervals(span_us, tile);
        // The second frame is the next interval's first.
        std::mem::swap(&mut self.kept, &mut self.p1);
        self.kept_luma.clear();
        self.kept_luma.extend_from_slice(f1);
        self.kept_valid = true;
        k
    }

    /// The interval's gray frames and pyramids: the first one kept from the last interval
    /// where it is that interval's second frame (the same values, no exposure scale).
    fn load(&mut self, f0: &[u16], scale0: f32, f1: &[u16]) {
        let (w, h) = (self.width, self.height);
        if self.kept_valid && scale0 == 1.0 && self.kept_luma == f0 {
            std::mem::swap(&mut self.p0, &mut self.kept);
        } else {
            self.p0.set(w, h, |g| gray(f0, scale0, g));
        }
        self.kept_valid = false;
        self.p1.set(w, h, |g| gray(f1, 1.0, g));
    }

    /// The flow of the loaded frames and the intervals it asks for.
    fn flow_intervals(&mut self, span_us: i64, tile: usize) -> usize {
        let (w, h) = (self.width, self.height);
        let (region, changed) =
            Region::around_changes(self.p0.gray(), self.p1.gray(), w, tile, CHANGE_LEVELS);
        if changed < MIN_CHANGED {
            return 1;
        }
        let started = Instant::now();
        self.region = region;
        let tiles_x = w.div_ceil(tile);
        let region_pixels = self.region.pixels(w, h);
        self.stats.flow_pixels += region_pixels as u64;
        if let Some((first, last)) = self.flow.levels() {
            self.p0.ensure(first, last);
            self.p1.ensure(first, last);
        }
        // Forward and backward on two threads: the two are independent, and each estimator
        // gives the same flow wherever it runs.
        let Subframes {
            flow,
            back,
            p0,
            p1,
            f01,
            f10,
            region,
            ..
        } = self;
        let region = &*region;
        let (p0, p1) = (&*p0, &*p1);
        let parallel = region_pixels >= PARALLEL_PIXELS;
        let (forward, backward) = side_by_side(
            parallel,
            || flow.compute_on(p0, p1, Some(region), f01),
            || back.compute_on(p1, p0, Some(region), f10),
        );
        // A failed flow (none seen) leaves the interval to linear interpolation, with a
        // warning.
        let computed = forward.and(backward);
        self.stats.flow_us += started.elapsed().as_micros() as u64;
        self.stats.flow_intervals += 1;
        if let Err(e) = computed {
            self.stats.fallbacks += 1;
            if !self.warned_error {
                self.warned_error = true;
                tracing::warn!("{e}: intervals whose flow fails are interpolated linearly");
            }
            return 1;
        }
        {
            let Subframes {
                f01,
                f10,
                ok0,
                ok1,
                region,
                ..
            } = self;
            let (f01, f10, region) = (&*f01, &*f10, &*region);
            side_by_side(
                parallel,
                || consistent(f01, f10, w, h, region, ok0),
                || consistent(f10, f01, w, h, region, ok1),
            );
        }
        let (mut before, mut after) = (0f64, 0f64);
        let mut lengths = Vec::with_capacity(2 * changed);
        self.longest.clear();
        self.longest.resize(tiles_x * h.div_ceil(tile), 0.0);
        let (g0, g1) = (self.p0.gray(), self.p1.gray());
        for y in 0..h {
            for span in self.region.row_spans(y, w) {
                for i in y * w + span.start..y * w + span.end {
                    let (a, b) = (g0[i], g1[i]);
                    if a.abs_diff(b) < CHANGE_LEVELS {
                        continue;
                    }
                    before += (a as f64 - b as f64).abs();
                    let [dx, dy] = self.f10[i];
                    let (x, yf) = ((i % w) as f32 + dx, y as f32 + dy);
                    after += (sample(g0, w, h, x, yf) - b as f32).abs() as f64;
                    for (flow, ok) in [(&self.f01, &self.ok0), (&self.f10, &self.ok1)] {
                        if ok[i] {
                            let [dx, dy] = flow[i];
                            let length = dx.hypot(dy);
                            lengths.push(length);
                            let longest = &mut self.longest[(y / tile) * tiles_x + (i % w) / tile];
                            *longest = longest.max(length);
                        }
                    }
                }
            }
        }
        let trusted = lengths.len() as f64 / (2 * changed) as f64;
        if after > EXPLAINED * before || trusted < MIN_TRUSTED {
            self.stats.fallbacks += 1;
            return 1;
        }
        let at = (lengths.len() - 1) * 99 / 100;
        let (_, &mut m, _) = lengths.select_nth_unstable_by(at, f32::total_cmp);
        let k = (self.needs(m) as usize)
            .min(self.cap as usize)
            .min(span_us as usize);
        // Each tile as many of the intervals as its own fastest pixel needs, of those that
        // divide the interval evenly (so that its sub-frames are some of the `k`).
        self.steps.clear();
        let divisors: Vec<usize> = (1..=k).filter(|&d| k.is_multiple_of(d)).collect();
        for &longest in &self.longest {
            let need = (self.needs(longest) as usize).min(k);
            let d = divisors.iter().copied().find(|&d| d >= need).unwrap_or(k);
            self.steps.push(d as u8);
        }
        k
    }

    /// The intervals a flow of `length` pixels needs (at least 1; large for NaN or infinity,
    /// which the cap bounds).
    fn needs(&self, length: f32) -> f64 {
        let n = (length as f64 / self.max_step_px).ceil();
        if n >= 1.0 {
            n.min(4096.0)
        } else {
            1.0
        }
    }

    /// Sub-frame `j` of `k` intervals (at `tau = j / k`) into `out`, on the tiles it covers
    /// (see the module docs, step 5).
    fn synthesize(&self, scale0: f32, j: usize, k: usize, tile: usize, out: &mut Vec<u16>) {
        let (w, h) = (self.width, self.height);
        out.resize(w * h, 0);
        let tiles_x = w.div_ceil(tile);
        let blend = Blend::new(self, scale0, j as f32 / k as f32);
        let mut scratch = RowScratch::new();
        for ty in 0..h.div_ceil(tile) {
            let steps = &self.steps[ty * tiles_x..(ty + 1) * tiles_x];
            let moving = |tx: usize| covers(steps[tx], j, k);
            // Runs of covered tiles, row by row: the frames are read in memory order.
            let mut tx = 0;
            while tx < tiles_x {
                if !moving(tx) {
                    tx += 1;
                    continue;
                }
                let run = (tx..tiles_x).take_while(|&t| moving(t)).count();
                let (x0, x1) = (tx * tile, ((tx + run) * tile).min(w));
                for y in ty * tile..((ty + 1) * tile).min(h) {
                    for x in (x0..x1).step_by(BLEND_CHUNK) {
                        let xs = x..(x + BLEND_CHUNK).min(x1);
                        let pixels = &mut out[y * w + xs.start..y * w + xs.end];
                        blend.row(y, xs.clone(), pixels, &mut scratch);
                    }
                }
                tx += run;
            }
        }
    }
}

/// Sub-frame `j` (of `1..k`) of an interval cut into `k` covers a tile that steps through
/// `steps` of them (see [`Subframed::steps`]).
fn covers(steps: u8, j: usize, k: usize) -> bool {
    let steps = usize::from(steps);
    steps > 1 && j.is_multiple_of(k / steps)
}

/// Sub-frames moved out of [`Subframes`] (see [`Subframes::take`]): their times and linear
/// luminance, in time order, and the tiles they cover. Empty where the interval needs none.
#[derive(Debug, Default)]
pub struct Subframed {
    /// Time and luminance of each sub-frame: `k - 1` of them, at `j / k` of the interval.
    pub frames: Vec<(i64, Vec<u16>)>,
    /// Per tile (row-major): the intervals `d` its pixels step through, a divisor of `k`:
    /// every `k / d`-th sub-frame and then the frame (1: the whole interval at once, no
    /// sub-frame; their values there are not set).
    pub steps: Vec<u8>,
}

/// Work on fewer pixels than this runs on one thread: starting a second costs more.
const PARALLEL_PIXELS: usize = 32 * 1024;

/// Forward-backward consistency of `forward` into `ok`: a pixel's vector and the `backward`
/// vector where it lands cancel to within `0.5 px + 10%` (squared: `|f + b|^2 < 0.01 (|f|^2 +
/// |b|^2) + 0.5`). Checked on `region`'s tiles; elsewhere both flows are zero, which is
/// consistent.
fn consistent(
    forward: &[[f32; 2]],
    backward: &[[f32; 2]],
    w: usize,
    h: usize,
    region: &Region,
    ok: &mut Vec<bool>,
) {
    crate::simd::run(
        #[inline(always)]
        || consistent_here(forward, backward, w, h, region, ok),
    )
}

/// [`consistent`] in the caller's instruction set.
#[inline(always)]
fn consistent_here(
    forward: &[[f32; 2]],
    backward: &[[f32; 2]],
    w: usize,
    h: usize,
    region: &Region,
    ok: &mut Vec<bool>,
) {
    ok.clear();
    ok.resize(w * h, true);
    for (row, (line, oks)) in forward
        .chunks_exact(w)
        .zip(ok.chunks_exact_mut(w))
        .enumerate()
    {
        for span in region.row_spans(row, w) {
            // A chunk of pixels at a time, in three passes so that the arithmetic runs on
            // vectors: where each vector lands, the backward vectors there, the test. The
            // same operations per pixel as one at a time.
            let mut at = [0usize; CONSISTENT_CHUNK];
            let mut back = [[0f32; 2]; CONSISTENT_CHUNK];
            for start in span.clone().step_by(CONSISTENT_CHUNK) {
                let end = (start + CONSISTENT_CHUNK).min(span.end);
                let n = end - start;
                let fwd = &line[start..end];
                for (j, [fx, fy]) in fwd.iter().enumerate() {
                    // Through `i32`: an unsigned conversion has no vector form on SSE2.
                    let (x, y) = ((start + j) as i32 as f32 + fx, row as i32 as f32 + fy);
                    at[j] = nearest(w, h, x, y);
                }
                for (b, &i) in back[..n].iter_mut().zip(&at[..n]) {
                    *b = backward[i];
                }
                for ((ok, [fx, fy]), [bx, by]) in
                    oks[start..end].iter_mut().zip(fwd).zip(&back[..n])
                {
                    let (sx, sy) = (fx + bx, fy + by);
                    *ok = sx * sx + sy * sy < 0.01 * (fx * fx + fy * fy + bx * bx + by * by) + 0.5;
                }
            }
        }
    }
}

/// Pixels [`consistent`] checks together.
const CONSISTENT_CHUNK: usize = 64;

/// `v` clamped into `0..=last` (`last` a frame's last column or row, below 8192), NaN to 0.
#[inline(always)]
fn inside(v: f32, last: f32) -> f32 {
    // `max` takes NaN to 0.
    v.max(0.0).min(last)
}

/// The whole part of [`inside`]'s value: its floor, as it is not negative. The conversion
/// needs no saturation, so it runs on vectors.
#[inline(always)]
fn whole(inside: f32) -> i32 {
    debug_assert!((0.0..8192.0).contains(&inside));
    // SAFETY: a value of `inside` is finite and in `0..8192`, which `i32` holds.
    unsafe { inside.to_int_unchecked::<i32>() }
}

/// The index of the pixel nearest `(x, y)`, clamped to the frame (NaN to 0).
#[inline(always)]
fn nearest(w: usize, h: usize, x: f32, y: f32) -> usize {
    let xi = whole(inside(x + 0.5, (w - 1) as f32)) as usize;
    let yi = whole(inside(y + 0.5, (h - 1) as f32)) as usize;
    yi * w + xi
}

/// Bilinear sample of `img` at `(x, y)`, the border repeated outside (NaN to 0).
fn sample<T: Copy + Into<f32>>(img: &[T], w: usize, h: usize, x: f32, y: f32) -> f32 {
    let x = inside(x, (w - 1) as f32);
    let y = inside(y, (h - 1) as f32);
    let (xi, yi) = (whole(x) as usize, whole(y) as usize);
    let (fx, fy) = (x - xi as f32, y - yi as f32);
    let (xj, yj) = ((xi + 1).min(w - 1), (yi + 1).min(h - 1));
    let at = |x: usize, y: usize| -> f32 { img[y * w + x].into() };
    let top = at(xi, yi) * (1.0 - fx) + at(xj, yi) * fx;
    let bottom = at(xi, yj) * (1.0 - fx) + at(xj, yj) * fx;
    top * (1.0 - fy) + bottom * fy
}

#[cfg(test)]
mod tests {
    use super::*;

    const DIS_FAST: (FlowBackend, FlowPreset) = (FlowBackend::Dis, FlowPreset::Fast);
    use crate::event::Event;
    use crate::frame::scene_fn::SceneSource;
    use crate::frame::{Frame, FrameSource};
    use crate::stage1::{PhysicsConfig, PhysicsSim, Preset};

    const W: u16 = 160;
    const H: u16 = 96;
    const FPS: f64 = 30.0;
    /// Pixels per second: 8 pixels per frame.
    const SPEED: f64 = 240.0;
    const DARK: f64 = 0.1;

    /// A textured bright bar 32 px wide, its leading edge at `x = 40` at time 0, moving right
    /// at `SPEED` over a still, dark texture; pixels see the area-weighted mix.
    fn bar(frames: usize) -> Vec<Frame> {
        let scene = |t: i64, x: u16, y: u16| {
            let edge = 40.0 + SPEED * t as f64 * 1e-6;
            let (x, y) = (x as f64, y as f64);
            // The part of [x, x + 1) inside [edge - 16, edge].
            let cover = ((edge - x).min(1.0) - (edge - 32.0 - x).max(0.0)).clamp(0.0, 1.0);
            let u = x + 0.5 - edge;
            // No period under 16 px: a motion of 8 px per frame is not aliased.
            let tex =
                0.55 + 0.2 * (u * 0.19).sin() * (y * 0.3).cos() + 0.1 * (u * 0.37 + y * 0.21).sin();
            // The background: a still texture, dark.
            let back = DARK * (1.0 + 0.3 * (x * 0.23).sin() * (y * 0.17 + 1.0).cos());
            back * (1.0 - cover) + tex * cover
        };
        let mut src = SceneSource::new("bar", W, H, FPS, frames, Box::new(scene));
        std::iter::from_fn(|| src.next_frame().unwrap()).collect()
    }

    fn ideal(motion: Motion) -> PhysicsConfig {
        PhysicsConfig {
            motion,
            max_subframes: 16,
            ..Preset::Ideal.config()
        }
    }

    fn simulate(cfg: PhysicsConfig, frames: &[Frame]) -> (Vec<Event>, PhysicsSim) {
        let (w, h) = (frames[0].width, frames[0].height);
        let mut sim = PhysicsSim::new(cfg, w, h, 3).unwrap();
        let mut events = Vec::new();
        for f in frames {
            sim.step(f, &mut events).unwrap();
        }
        (events, sim)
    }

    /// The bar's flow: 8 px per frame where the bar is (measured: median end-point error 0.13
    /// px with the `fast` preset). Objects entering at the frame's border come out slower.
    #[test]
    fn the_flow_of_a_moving_bar_is_its_motion() {
        let frames = bar(3);
        let mut sub = Subframes::new(DIS_FAST, 1.0, 16, W, H).unwrap();
        let (mut g0, mut g1) = (Vec::new(), Vec::new());
        gray(&frames[1].luma, 1.0, &mut g0);
        gray(&frames[2].luma, 1.0, &mut g1);
        sub.flow.compute(&g0, &g1, &mut sub.f01).unwrap();
        let per_frame = SPEED / FPS;
        let mut err = Vec::new();
        // Frame 1's bar spans [16, 48): its inner columns, away from the rows' ends.
        for y in 8..H as usize - 8 {
            for x in 20..44 {
                let [dx, dy] = sub.f01[y * W as usize + x];
                err.push(((dx as f64 - per_frame).powi(2) + (dy as f64).powi(2)).sqrt());
            }
        }
        err.sort_by(f64::total_cmp);
        let median = err[err.len() / 2];
        assert!(median < 0.5, "median end-point error {median} px");
    }

    /// Each pixel the bar's leading edge crosses fires first when the edge reaches it: with
    /// sub-frames along the flow the first ON event of each pixel is within 15% of the frame
    /// interval of that time on average; linear interpolation fires the whole path at once and
    /// misses by more than a quarter.
    #[test]
    fn first_events_follow_the_edge_only_with_flow() {
        let frames = bar(6);
        let interval = 1e6 / FPS;
        let threshold = Preset::Ideal.config().threshold_on;
        // The edge covers `c` of a dark pixel when its light has risen by the threshold.
        let tex_min = 0.55 - 0.2 - 0.1;
        let c = ((threshold.exp() - 1.0) * DARK / (tex_min - DARK)).min(1.0);
        let error = |motion: Motion| {
            let (events, sim) = simulate(ideal(motion), &frames);
            let mut first = vec![i64::MAX; W as usize * H as usize];
            for e in events.iter().filter(|e| e.on) {
                let i = e.y as usize * W as usize + e.x as usize;
                first[i] = first[i].min(e.t);
            }
            // Columns the edge crosses in the intervals after the first (edge from 48 to 80).
            let mut errs = Vec::new();
            for y in 4..H as usize - 4 {
                for x in 49..80 {
                    let truth = (x as f64 + c - 40.0) / SPEED * 1e6;
                    let got = first[y * W as usize + x];
                    assert!(got < i64::MAX, "{motion:?}: no event at ({x}, {y})");
                    errs.push((got as f64 - truth).abs() / interval);
                }
            }
            (
                errs.iter().sum::<f64>() / errs.len() as f64,
                sim.stats().motion,
            )
        };
        let (flow, stats) = error(Motion::Flow);
        let (linear, _) = error(Motion::Linear);
        assert!(stats.subframes >= 5 * 6, "{stats:?}");
        assert_eq!(stats.fallbacks, 0, "{stats:?}");
        // Measured: 0.096 (sub-frames of 1/6 of the interval here) against 0.370.
        assert!(flow < 0.15, "flow: mean error {flow} of an interval");
        assert!(linear > 0.25, "linear: mean error {linear} of an interval");
    }

    /// Where the flow cannot help, the events are exactly the linear model's.
    #[test]
    fn without_usable_motion_the_events_are_the_linear_models() {
        let tex = |seed: f64| {
            move |_t: i64, x: u16, y: u16| {
                0.3 + 0.25 * (x as f64 * 0.7 + seed).sin() * (y as f64 * 0.5 * seed).cos()
            }
        };
        let frame = |t: i64, w: u16, h: u16, f: &dyn Fn(i64, u16, u16) -> f64| Frame {
            t,
            width: w,
            height: h,
            luma: (0..w as usize * h as usize)
                .map(|i| (f(t, (i % w as usize) as u16, (i / w as usize) as u16) * 65535.0) as u16)
                .collect(),
            exposure_us: None,
        };
        let cases: Vec<(&str, Vec<Frame>, u64)> = vec![
            // A scene cut: one texture, then an unrelated one.
            (
                "cut",
                vec![frame(0, W, H, &tex(1.0)), frame(33_000, W, H, &tex(2.3))],
                1,
            ),
            // Black, then saturated, then black.
            (
                "flash",
                vec![
                    Frame::filled(0, W, H, 0),
                    Frame::filled(33_000, W, H, u16::MAX),
                    Frame::filled(66_000, W, H, 0),
                ],
                0,
            ),
            // A flat frame whose light changes: no motion to see.
            (
                "flat",
                vec![
                    Frame::filled(0, W, H, 9000),
                    Frame::filled(33_000, W, H, 30000),
                ],
                0,
            ),
            // Frames too small for the flow.
            (
                "tiny",
                vec![Frame::filled(0, 8, 8, 9000), frame(33_000, 8, 8, &tex(1.0))],
                0,
            ),
            // One frame only.
            ("single", vec![frame(0, W, H, &tex(1.0))], 0),
        ];
        for (name, frames, fallbacks) in cases {
            let cfg = |m| PhysicsConfig {
                motion: m,
                ..Preset::Davis346.config()
            };
            let (flow, sim) = simulate(cfg(Motion::Flow), &frames);
            let (linear, _) = simulate(cfg(Motion::Linear), &frames);
            let stats = sim.stats().motion;
            assert_eq!(flow, linear, "{name}: {:?}", sim.stats().motion);
            assert_eq!(stats.subframes, 0, "{name}: {stats:?}");
            assert!(stats.fallbacks >= fallbacks, "{name}: {stats:?}");
            if name == "flash" {
                assert!(!linear.is_empty());
            }
        }
    }

    /// A still scene costs no flow, and its tiles stay skipped.
    #[test]
    fn a_still_scene_runs_no_flow() {
        let frames: Vec<Frame> = (0..5)
            .map(|i| Frame::filled(i * 33_000, W, H, 20000))
            .collect();
        let (events, sim) = simulate(ideal(Motion::Flow), &frames);
        assert!(events.is_empty());
        let stats = sim.stats();
        assert_eq!(stats.motion.flow_intervals, 0);
        assert_eq!(stats.tiles_active, 0);
    }

    /// Each tile steps through as many of the interval's sub-frames as its own fastest pixel
    /// needs: a bar moving 8 px a frame above one moving 2 px, the interval cut into about 8
    /// for the fast bar, the slow bar's tiles through a few evenly spaced sub-frames, the fast
    /// bar's through all, the background's through none.
    #[test]
    fn each_tile_steps_through_the_subframes_it_needs() {
        let scene = |t: i64, x: u16, y: u16| {
            let (x, y, t) = (x as f64, y as f64, t as f64 * 1e-6);
            let speed = if y < 48.0 { SPEED } else { SPEED / 4.0 };
            let u = x - 16.0 - speed * t;
            let tex = 0.5 + 0.3 * (u * 0.4).sin() * (y * 0.3).cos();
            if (0.0..32.0).contains(&u) {
                tex
            } else {
                DARK
            }
        };
        let mut src = SceneSource::new("bars", W, H, FPS, 3, Box::new(scene));
        let frames: Vec<Frame> = std::iter::from_fn(|| src.next_frame().unwrap()).collect();
        let mut sub = Subframes::new(DIS_FAST, 1.0, 16, W, H).unwrap();
        let (f0, f1) = (&frames[1], &frames[2]);
        let k = sub.compute(&f0.luma, 1.0, &f1.luma, f0.t, f1.t, 16);
        // The fast bar's 8 px, give or take the flow's error at its edges.
        assert!((8..=12).contains(&k), "{k} intervals");
        let used = sub.take();
        assert_eq!(used.frames.len(), k - 1);
        let tiles_x = (W as usize).div_ceil(16);
        let (top, bottom) = used.steps.split_at(3 * tiles_x);
        assert_eq!(top.iter().max(), Some(&(k as u8)), "{top:?}");
        // The slow bar's 2 px (3 at most with the flow's error), rounded up to a divisor, on
        // the tiles a tile row away from the fast bar (the patches on the boundary see both).
        let slow = (2..k).find(|&d| d >= 3 && k.is_multiple_of(d)).unwrap_or(k);
        let inner = &bottom[tiles_x..];
        let most = *inner.iter().max().unwrap_or(&0) as usize;
        assert!((2..=slow).contains(&most) && most < k, "{k}: {bottom:?}");
        assert!(used.steps.contains(&1), "{:?}", used.steps);
        // A tile stepping through `d` intervals is covered by `d - 1` evenly spaced sub-frames.
        for (t, &d) in used.steps.iter().enumerate() {
            let covered: Vec<usize> = (1..k).filter(|&j| covers(d, j, k)).collect();
            let every = k / d as usize;
            let want: Vec<usize> = (1..d as usize).map(|m| m * every).collect();
            assert_eq!(covered, want, "tile {t}, {d} of {k}");
        }
    }

    /// The blend of a sub-frame, a row's pixels at a time on vectors, is the per-pixel
    /// definition bit for bit: bilinear samples of both neighbours along the flows (positions
    /// inside, on the border and far outside the frame), each trusted where the nearest
    /// pixel's flow is, the plain blend where neither is.
    #[test]
    fn the_blend_by_rows_is_the_per_pixel_blend() {
        use rand::{Rng, SeedableRng};
        let (w, h) = (37usize, 23usize);
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(27);
        let mut m = Subframes::new(DIS_FAST, 1.0, 8, w as u16, h as u16).unwrap();
        let flow = |rng: &mut rand_xoshiro::Xoshiro256PlusPlus| -> Vec<[f32; 2]> {
            (0..w * h)
                .map(|_| {
                    // A few flows that are not numbers or infinite: their positions are
                    // taken to the frame's edge (NaN to 0), the same in both.
                    if rng.gen_bool(0.02) {
                        let odd = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 1e30];
                        return [odd[rng.gen_range(0..4)], odd[rng.gen_range(0..4)]];
                    }
                    let reach = if rng.gen_bool(0.1) { 60.0 } else { 3.0 };
                    [rng.gen_range(-reach..reach), rng.gen_range(-reach..reach)]
                })
                .collect()
        };
        (m.f01, m.f10) = (flow(&mut rng), flow(&mut rng));
        m.ok0 = (0..w * h).map(|_| rng.gen_bool(0.7)).collect();
        m.ok1 = (0..w * h).map(|_| rng.gen_bool(0.7)).collect();
        let f0: Vec<u16> = (0..w * h).map(|_| rng.gen()).collect();
        let f1: Vec<u16> = (0..w * h).map(|_| rng.gen()).collect();
        for (tau, scale0) in [(0.25f32, 1.0f32), (0.5, 0.8), (0.875, 1.3)] {
            m.packed.set((w, h), (&f0, &m.ok0), (&f1, &m.ok1));
            let blend = Blend::new(&m, scale0, tau);
            let mut out = vec![0u16; w];
            let mut scratch = RowScratch::new();
            for y in 0..h {
                blend.row(y, 0..w, &mut out, &mut scratch);
                for (x, &got) in out.iter().enumerate() {
                    let i = y * w + x;
                    let ([ax, ay], [bx, by]) = (m.f01[i], m.f10[i]);
                    let s = 1.0 - tau;
                    let to0 = (
                        -s * tau * ax + tau * tau * bx,
                        -s * tau * ay + tau * tau * by,
                    );
                    let to1 = (s * s * ax - tau * s * bx, s * s * ay - tau * s * by);
                    let (x0, y0) = (x as f32 + to0.0, y as f32 + to0.1);
                    let (x1, y1) = (x as f32 + to1.0, y as f32 + to1.1);
                    let v0 = sample(&f0, w, h, x0, y0) * scale0;
                    let v1 = sample(&f1, w, h, x1, y1);
                    let mut wt = (
                        if m.ok0[nearest(w, h, x0, y0)] { s } else { 0.0 },
                        if m.ok1[nearest(w, h, x1, y1)] {
                            tau
                        } else {
                            0.0
                        },
                    );
                    if wt.0 + wt.1 <= 0.0 {
                        wt = (s, tau);
                    }
                    let v = (wt.0 * v0 + wt.1 * v1) / (wt.0 + wt.1);
                    let want = (v + 0.5).clamp(0.0, 65535.0) as u16;
                    assert_eq!(got, want, "pixel ({x}, {y}) at tau {tau}");
                }
            }
        }
    }

    /// An interval stepped without sub-frames (a scene cut that fell back to linear, nothing
    /// moving) costs the same at any cap: however long it takes, it does not lower the cap,
    /// and a cheap one counts as calm.
    #[test]
    fn intervals_without_subframes_do_not_lower_the_cap() {
        let mut sub = Subframes::new(DIS_FAST, 1.0, 8, W, H).unwrap();
        sub.pace(1.0);
        for _ in 0..10 * SETTLE_INTERVALS {
            sub.spent(0.050, 33_333, false);
        }
        assert_eq!(sub.stats().cap, 8);
        // The same time through sub-frames lowers it: at the second interval, since 50 ms
        // is more than the frame itself (Stage 1 falls behind).
        sub.spent(0.050, 33_333, true);
        assert_eq!(sub.stats().cap, 8);
        sub.spent(0.050, 33_333, true);
        assert_eq!(sub.stats().cap, 4);
        for _ in 0..CALM_INTERVALS - 1 {
            sub.spent(0.001, 33_333, false);
        }
        assert_eq!(sub.stats().cap, 4);
        sub.spent(0.001, 33_333, false);
        assert_eq!(sub.stats().cap, 5);
    }

    /// The cap's changes are counted both ways for the stats line; the warning that the cap
    /// stays low is given once, after `LONG_BELOW_S` below the configured cap without a
    /// break (time at the configured cap starts the count over).
    #[test]
    fn a_cap_held_low_is_said_once() {
        let mut sub = Subframes::new(DIS_FAST, 1.0, 8, W, H).unwrap();
        sub.pace(1.0);
        for _ in 0..SETTLE_INTERVALS {
            sub.spent(0.050, 33_333, true);
        }
        assert_eq!((sub.stats().cap, sub.stats().cap_lowered), (4, 1));
        let governor = |sub: &Subframes| sub.live.clone().unwrap();
        let below = |sub: &Subframes| governor(sub).below_s;
        // Slow enough to stay at 4 (no raise), not so slow as to lower it again.
        let hold = |sub: &mut Subframes, n: usize| {
            for _ in 0..n {
                sub.spent(0.016, 33_333, false);
            }
        };
        hold(&mut sub, 100);
        let held = below(&sub).unwrap();
        assert!((3.0..4.0).contains(&held), "{held} s below");
        // Back at the configured cap: the count starts over.
        sub.cap = 8;
        hold(&mut sub, 1);
        assert_eq!(below(&sub), Some(0.0));
        sub.cap = 4;
        hold(&mut sub, (LONG_BELOW_S * 30.0) as usize + 2);
        assert_eq!(below(&sub), None, "warned");
        assert_eq!(sub.stats().cap, 4);
        assert_eq!(sub.stats().cap_raised, 0);
        assert_eq!(sub.stats().cap_most, 8);
    }

    /// A live run that cannot keep up lowers the cap, by the overshoot (by one at least, to
    /// half at most in one step), down to linear interpolation, and says so in its counters;
    /// with time to spare it raises the cap again, one step at a time, and a raise taken back
    /// doubles the wait before the next.
    #[test]
    fn a_live_run_lowers_the_cap_to_keep_up() {
        let mut sub = Subframes::new(DIS_FAST, 1.0, 8, W, H).unwrap();
        // Offline: no budget.
        sub.spent(1.0, 33_333, true);
        assert_eq!(sub.stats().cap, 8);
        sub.pace(1.0);
        // One slow interval is not enough; a run of them is. A little over the budget (26.7
        // ms of a 33.3 ms frame) lowers the cap a little: 30 ms at 8 fit 8 x 26.7 / 30 = 7.1.
        let mut caps = Vec::new();
        for _ in 0..2 * SETTLE_INTERVALS {
            sub.spent(0.030, 33_333, true);
            caps.push(sub.stats().cap);
        }
        assert_eq!(caps, [8, 8, 7, 7, 7, 6]);
        // Far over it, longer than the frame itself: to half at most per step, without
        // waiting for the smoothed time, but never on the first interval after a change
        // (its motion was found ahead under the cap before).
        caps.clear();
        for _ in 0..4 {
            sub.spent(0.100, 33_333, true);
            caps.push(sub.stats().cap);
        }
        assert_eq!(caps, [6, 3, 3, 1]);
        assert_eq!(sub.stats().cap_lowered, 4);
        let calm = |sub: &mut Subframes, n: u32| {
            for _ in 0..n {
                sub.spent(0.001, 33_333, true);
            }
        };
        calm(&mut sub, CALM_INTERVALS);
        assert_eq!(sub.stats().cap, 2);
        // Too slow at 2 (slower than the frame: at its second interval): back to 1, and the
        // next raise waits twice as long.
        for _ in 0..2 {
            sub.spent(0.040, 33_333, true);
        }
        assert_eq!(sub.stats().cap, 1);
        calm(&mut sub, CALM_INTERVALS);
        assert_eq!(sub.stats().cap, 1);
        calm(&mut sub, CALM_INTERVALS);
        assert_eq!(sub.stats().cap, 2);
        // At cap 1 no flow runs (linear interpolation).
        let mut sub = Subframes::new(DIS_FAST, 1.0, 1, W, H).unwrap();
        let frames = bar(2);
        let (f0, f1) = (&frames[0], &frames[1]);
        assert_eq!(sub.compute(&f0.luma, 1.0, &f1.luma, f0.t, f1.t, 16), 1);
        assert!(sub.take().frames.is_empty());
        assert_eq!(sub.stats().flow_intervals, 0);
    }
}
