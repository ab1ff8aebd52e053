//! The learned tier: the V2CE network (an ONNX model, see `v2ce model import`) run by ONNX
//! Runtime on windows of `L` frame intervals (V2CE_SPEC.md sections 1.2, 1.3 and 3).
//!
//! Frames are preprocessed as the toolbox does ([`preprocess`]) and kept until a window is
//! complete. The [`Planner`] decides when a window runs and which of its intervals are new:
//! - with `stride = window` (the default) windows do not overlap and share one boundary frame,
//!   and at the end of the stream the last window moves back to end on the last frame and only
//!   its new intervals are kept: exactly the toolbox's sequence planning and merge;
//! - with `stride < window` (live use) a window runs every `stride` new intervals over the
//!   newest `window` intervals and keeps the newest `stride`, so an interval waits at most
//!   `stride` intervals plus one inference, with `window` intervals of context;
//! - a stream shorter than one window runs as one shorter window (the toolbox needs 17 frames).
//!
//! Each interval's output `(2*C, H, W)` becomes a [`VoxelGrid`] for Stage 2 to re-time. Values
//! that are NaN or infinite are counted here and repaired (counted again) by the sampler.

pub mod activity;
pub mod preprocess;
pub mod raw;
pub mod roi;
pub mod runtime;

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::frame::Frame;
use crate::interval::Interval;
use crate::voxel::VoxelGrid;

use activity::Activity;
pub use preprocess::{Geometry, Layout, Tile};
use roi::{Crop, Margin, Rect};
pub use runtime::{Device, Network};

use super::{SourceEncoding, Stage1, Stage1Batch, Stage1Stats};

/// The toolbox's window: 16 frame pairs.
pub const DEFAULT_WINDOW: usize = 16;

/// How a source's values reach the network.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum InputEncoding {
    /// As the source decoded them: sRGB files give back their bytes, linear sources (APS
    /// frames, `--linear` folders) their values.
    #[default]
    Auto,
    /// Encode with the sRGB transfer function, whatever the source.
    Srgb,
    /// Linear luminance as it is.
    Linear,
}

/// The model the learned tier runs when none is configured: `models/v2ce-small.onnx`, built
/// into the program (its card: `models/v2ce-small.md`).
pub const BUILTIN_MODEL: &[u8] = include_bytes!("../../../models/v2ce-small.onnx");

/// The built-in model's output floor (see `LearnedConfig::floor`), chosen on the synthetic
/// validation set (its card).
pub const BUILTIN_FLOOR: f32 = 0.1;

/// How the built-in model is named in messages.
pub const BUILTIN_NAME: &str = "v2ce-small (built in)";

/// The `[stage1.learned]` table.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LearnedConfig {
    /// The ONNX model (`v2ce model import` makes one from the official checkpoint or a trained
    /// one); empty: the built-in small model ([`BUILTIN_MODEL`]).
    pub model: PathBuf,
    /// Frame intervals per window (`L`; the network was trained on 16).
    pub window: usize,
    /// New intervals per window (`1..=window`; 0: the window, no overlap); less than `window`
    /// overlaps windows for a shorter wait in live use.
    pub stride: usize,
    /// How frames are fitted to the network.
    pub geometry: Geometry,
    /// Rows after resizing (`resize`, `center`, `pano`).
    pub height: u16,
    /// Crop or tile width (`center`, `pano`).
    pub width: u16,
    /// ONNX Runtime intra-op threads (0: one per core).
    pub threads: usize,
    /// Execution provider: `cpu`, `cuda`, `auto`.
    pub device: Device,
    /// How frame values reach the network.
    pub input: InputEncoding,
    /// The ONNX Runtime library, when it is not found by itself (empty: search).
    pub ort_library: PathBuf,
    /// Keep ONNX Runtime's CPU memory arena (a pool that only grows). Off by default: measured
    /// at 346x260 with 16 pairs, the arena doubled the peak resident set (3.3 GB against 1.5 GB)
    /// and made no run faster.
    pub cpu_arena: bool,
    /// Keep the network's output only where the scene moved (see [`activity`]): tiles whose
    /// pixels did not change between a pair's frames get no events, and a window where nothing
    /// changed is not run.
    pub gate: bool,
    /// A pixel moved when its gray value (0 to 1) changed by more than this.
    pub gate_threshold: f32,
    /// Active tiles are grown by this many tiles of 16 pixels.
    pub gate_margin: usize,
    /// Output values below this are taken as zero before Stage 2 (whose chain decoupling
    /// makes any positive mass at least one event: a network's faint, diffuse output would
    /// otherwise fire everywhere; the toolbox's optional `erase_beginning` is such a floor at
    /// 0.001). 0: off; unset: the built-in model's own ([`BUILTIN_FLOOR`]), 0 for other models.
    pub floor: Option<f32>,
    /// Run the network only on crops around the tiles that changed, grown by the receptive
    /// field ([`roi`]; with `gate` on, and one tile per frame: not `pano`). With the model's own
    /// margin the kept outputs are the whole frame's.
    pub roi: bool,
    /// Pixels the crops reach beyond the changed tiles; unset: the model's receptive field as
    /// its metadata states (155 for V2CE-shaped models; a model that does not state it runs on
    /// whole frames). Less is faster and no longer exact.
    pub roi_margin: Option<usize>,
}

impl Default for LearnedConfig {
    fn default() -> Self {
        LearnedConfig {
            model: PathBuf::new(),
            window: DEFAULT_WINDOW,
            stride: 0,
            geometry: Geometry::Native,
            height: 260,
            width: 346,
            threads: 0,
            device: Device::Auto,
            input: InputEncoding::Auto,
            ort_library: PathBuf::new(),
            cpu_arena: false,
            gate: true,
            gate_threshold: 0.0,
            gate_margin: 1,
            floor: None,
            roi: true,
            roi_margin: None,
        }
    }
}

impl LearnedConfig {
    /// Checks the window settings.
    pub fn validate(&self) -> Result<()> {
        if !(1..=256).contains(&self.window) {
            return Err(Error::invalid(
                "stage1.learned.window",
                format!("{} intervals; need 1 to 256", self.window),
            ));
        }
        if !(self.gate_threshold.is_finite() && (0.0..1.0).contains(&self.gate_threshold)) {
            return Err(Error::invalid(
                "stage1.learned.gate_threshold",
                format!("{}; need 0 to 1 (a gray-value change)", self.gate_threshold),
            ));
        }
        let floor = self.floor();
        if !(floor.is_finite() && (0.0..10.0).contains(&floor)) {
            return Err(Error::invalid(
                "stage1.learned.floor",
                format!("{floor}; need 0 to 10"),
            ));
        }
        if self.gate_margin > 64 {
            return Err(Error::invalid(
                "stage1.learned.gate_margin",
                format!("{} tiles; need 0 to 64", self.gate_margin),
            ));
        }
        if let Some(m) = self.roi_margin {
            if m > 4096 {
                return Err(Error::invalid(
                    "stage1.learned.roi_margin",
                    format!("{m} pixels; need 0 to 4096"),
                ));
            }
        }
        if self.stride > self.window {
            return Err(Error::invalid(
                "stage1.learned.stride",
                format!(
                    "{}; need 1 to the window ({}), or 0 for the window",
                    self.stride, self.window
                ),
            ));
        }
        Ok(())
    }

    /// The output floor in use: `floor`, or the built-in model's when it runs.
    pub fn floor(&self) -> f32 {
        match self.floor {
            Some(f) => f,
            None if self.model.as_os_str().is_empty() => BUILTIN_FLOOR,
            None => 0.0,
        }
    }

    /// New intervals per window: `stride`, or the window when it is 0.
    pub fn stride(&self) -> usize {
        if self.stride == 0 {
            self.window
        } else {
            self.stride
        }
    }
}

/// The learned tier's counters.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct LearnedStats {
    /// Windows run (a panorama's tiles count once).
    pub windows: u64,
    /// Frame pairs fed to the network (overlapping windows feed some twice, and each tile of a
    /// panorama counts).
    pub pairs_run: u64,
    /// Frames repeated in front of a window too short for a model that fixes its pair count.
    pub frames_padded: u64,
    /// Intervals handed to Stage 2.
    pub intervals: u64,
    /// Output values that were NaN or infinite.
    pub nonfinite: u64,
    /// Windows not run because nothing changed in the intervals they would keep.
    pub windows_skipped: u64,
    /// Tiles of kept intervals whose outputs were dropped because nothing changed there.
    pub tiles_gated: u64,
    /// Pixels the network ran on, times pairs (crops of [`roi`], or whole frames).
    pub pixels_run: u64,
    /// Pixels whole-frame runs of every window (skipped ones too) would have taken, times pairs.
    pub pixels_full: u64,
    /// Median time of one window's inference, ms.
    pub window_ms_p50: f64,
    /// Longest, ms.
    pub window_ms_max: f64,
    /// The execution provider (`cpu`, `cuda`).
    pub provider: &'static str,
}

impl super::TierRecord for LearnedStats {
    const TIER: &'static str = "learned";

    fn summary(&self, window: usize, stride: usize) -> String {
        format!(
            "{} windows of L={window} (stride {stride}, {} skipped as still), median {:.0} ms \
             per window on {}, the network ran on {:.0}% of the pixels",
            self.windows,
            self.windows_skipped,
            self.window_ms_p50,
            self.provider,
            100.0 * self.compute()
        )
    }

    fn counters(&self) -> Vec<super::Counter> {
        super::Counter::family(
            "windows",
            "Windows the learned tier ran, by result (run, skipped as still).",
            &[("run", self.windows), ("skipped", self.windows_skipped)],
        )
    }
}

impl LearnedStats {
    /// The share of whole-frame compute spent: pixels run over pixels a whole-frame run of
    /// every window would take (1 before any window).
    pub fn compute(&self) -> f64 {
        if self.pixels_full == 0 {
            1.0
        } else {
            self.pixels_run as f64 / self.pixels_full as f64
        }
    }
}

/// When windows run, for a stream of frames (pure bookkeeping; see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Planner {
    window: usize,
    stride: usize,
    /// Frames held (at most `window + 1`).
    held: usize,
    /// Intervals not handed on yet.
    pending: usize,
}

/// A window to run: the newest `frames` held frames, of whose `frames - 1` intervals the last
/// `keep` are new.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Run {
    /// Frames in the window (pairs + 1).
    pub frames: usize,
    /// New intervals, the window's last ones.
    pub keep: usize,
}

impl Planner {
    /// A planner for windows of `window` intervals advancing by `stride`.
    pub fn new(window: usize, stride: usize) -> Self {
        Planner {
            window,
            stride,
            held: 0,
            pending: 0,
        }
    }

    /// Frames the caller must keep (the newest ones).
    pub fn capacity(&self) -> usize {
        self.window + 1
    }

    /// A frame arrived; returns the window to run now, if any.
    pub fn push(&mut self) -> Option<Run> {
        if self.held > 0 {
            self.pending += 1;
        }
        self.held = (self.held + 1).min(self.window + 1);
        if self.held == self.window + 1 && self.pending >= self.stride {
            let keep = std::mem::take(&mut self.pending);
            return Some(Run {
                frames: self.held,
                keep,
            });
        }
        None
    }

    /// End of the stream: the window that hands on what is pending, if anything is.
    pub fn finish(&mut self) -> Option<Run> {
        let keep = std::mem::take(&mut self.pending);
        (keep > 0).then_some(Run {
            frames: self.held,
            keep,
        })
    }

    /// Forgets every frame (after a break in the stream).
    pub fn restart(&mut self) {
        self.held = 0;
        self.pending = 0;
    }
}

/// Bytes of working memory per pixel and frame pair of one window: measured at 346x260 with 16
/// pairs (1.5 GB peak with the CPU arena off) and rounded up.
const BYTES_PER_PAIR_PIXEL: f64 = 1200.0;

/// The memory available to the process, from `/proc/meminfo` (`None` where it cannot be read).
fn available_memory() -> Option<f64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024.0)
}

/// The learned tier behind the [`Stage1`] trait.
pub struct LearnedStage1 {
    network: Network,
    layout: Layout,
    encoding: SourceEncoding,
    bins: usize,
    planner: Planner,
    config: LearnedConfig,
    /// The newest frames: time and resized plane in `[0, 1]`.
    frames: VecDeque<(i64, Vec<f32>)>,
    stats: LearnedStats,
    /// Inference time of each window, us (bounded whatever the run's length).
    window_us: hdrhistogram::Histogram<u64>,
    input: Vec<f32>,
    tile: Vec<f32>,
    /// How far crops reach, when the network runs on the regions that changed only.
    roi: Option<Margin>,
}

impl LearnedStage1 {
    /// Opens the model for frames of `size`; `bins` must match the model's `C`. Refuses a
    /// model whose fixed sizes do not fit, and a window that would not fit in memory.
    pub fn new(
        config: &LearnedConfig,
        bins: usize,
        size: (u16, u16),
        encoding: SourceEncoding,
    ) -> Result<Self> {
        config.validate()?;
        let layout = Layout::new(config.geometry, size, config.height, config.width)?;
        let (nw, nh) = layout.net();
        let (ow, oh) = layout.output();
        let need = config.window as f64 * (nw * nh) as f64 * BYTES_PER_PAIR_PIXEL
            + (config.window * 2 * bins * ow as usize * oh as usize * 4) as f64;
        if let Some(free) = available_memory() {
            if need > free {
                return Err(Error::invalid(
                    "stage1.learned",
                    format!(
                        "a window of {} pairs at {nw} x {nh} needs about {:.1} GB, {:.1} GB are \
                         free; use a smaller frame (--size, geometry = \"resize\" or \"center\") \
                         or a shorter window",
                        config.window,
                        need / 1e9,
                        free / 1e9
                    ),
                ));
            }
        }
        let network = if config.model.as_os_str().is_empty() {
            Network::open_bytes(Path::new(BUILTIN_NAME), BUILTIN_MODEL, config)?
        } else {
            Network::open(&config.model, config)?
        };
        let fixed = network.fixed_sizes();
        let mismatch = |what: &str, fixed: usize, want: usize| {
            Error::invalid(
                "stage1.learned",
                format!(
                    "{} takes a fixed {what} of {fixed}, this run needs {want} (a model made by \
                     `v2ce model import` takes any size)",
                    config.model.display()
                ),
            )
        };
        if let Some(c) = fixed[2] {
            if c != 2 * bins {
                return Err(Error::invalid(
                    "stage2.bins",
                    format!(
                        "the model gives {c} channels per interval (C = {}), Stage 2 expects \
                         C = {bins}; set [stage2] bins = {}",
                        c / 2,
                        c / 2
                    ),
                ));
            }
        }
        for (axis, what, want) in [(0, "batch", 1), (3, "height", nh), (4, "width", nw)] {
            if let Some(f) = fixed[axis] {
                if f != want {
                    return Err(mismatch(what, f, want));
                }
            }
        }
        if let Some(p) = fixed[1] {
            if p != config.window {
                return Err(mismatch("number of pairs", p, config.window));
            }
        }
        let encoding = match config.input {
            InputEncoding::Auto => encoding,
            InputEncoding::Srgb => SourceEncoding::Srgb,
            InputEncoding::Linear => SourceEncoding::Linear,
        };
        let window_us = hdrhistogram::Histogram::new_with_bounds(1, 3_600_000_000, 3)
            .map_err(|e| Error::invalid("histogram", e.to_string()))?;
        let croppable = config.roi
            && config.gate
            && config.geometry != Geometry::Pano
            && fixed[3].is_none()
            && fixed[4].is_none();
        let field = network.receptive_field();
        let roi = match (croppable, config.roi_margin, field) {
            (false, _, _) => None,
            (true, Some(m), field) => Some(Margin {
                before: m,
                after: m,
                align: field.map_or(activity::TILE, |f| f.align),
            }),
            (true, None, Some(f)) => Some(f),
            (true, None, None) => {
                tracing::info!(
                    "{} does not state its receptive field (a model made by `v2ce model import` \
                     does); it runs on whole frames (set stage1.learned.roi_margin to crop)",
                    network.path().display()
                );
                None
            }
        };
        Ok(LearnedStage1 {
            roi,
            stats: LearnedStats {
                provider: network.provider(),
                ..LearnedStats::default()
            },
            network,
            layout,
            encoding,
            bins,
            planner: Planner::new(config.window, config.stride()),
            config: config.clone(),
            frames: VecDeque::new(),
            window_us,
            input: Vec::new(),
            tile: Vec::new(),
        })
    }

    /// Runs the network once on `pairs` pairs of whole (gray) frames, outputs discarded: to
    /// time it (see [`super::auto`]).
    pub fn probe(&mut self, pairs: usize) -> Result<()> {
        let (nw, nh) = self.layout.net();
        let pairs = self.network.pairs().unwrap_or(pairs);
        let input = vec![0f32; pairs * 2 * nh * nw];
        self.network
            .run_with(&input, [1, pairs, 2, nh, nw], |_, _| Ok(()))
    }

    /// Runs the newest `run.frames` frames and appends the `run.keep` new intervals. A model that
    /// fixes its pair count gets a short window (a stream, or a stretch between camera gaps,
    /// shorter than one window) padded in front with copies of its first frame: still pairs,
    /// whose outputs are not kept.
    fn run(&mut self, run: Run, out: &mut Vec<Stage1Batch>) -> Result<()> {
        let frames: Vec<&(i64, Vec<f32>)> = self
            .frames
            .iter()
            .skip(self.frames.len() - run.frames)
            .collect();
        let pad = match self.network.pairs() {
            Some(p) if p + 1 > run.frames => p + 1 - run.frames,
            _ => 0,
        };
        self.stats.frames_padded += pad as u64;
        let pairs = run.frames - 1 + pad;
        let (nw, nh) = self.layout.net();
        let (ow, oh) = self.layout.output();
        let (ow, oh) = (ow as usize, oh as usize);
        let channels = 2 * self.bins;
        let mut voxels = vec![0f32; run.keep * channels * oh * ow];
        let first = frames.len() - 1 - run.keep;
        let activity: Vec<Activity> = if self.config.gate {
            let (plane_w, offset) = self.layout.plane_columns();
            frames[first..]
                .windows(2)
                .map(|p| {
                    Activity::of_pair(
                        &p[0].1,
                        &p[1].1,
                        plane_w,
                        offset,
                        (ow, oh),
                        self.config.gate_threshold,
                        self.config.gate_margin,
                    )
                })
                .collect()
        } else {
            Vec::new()
        };
        let still = self.config.gate && !activity.iter().any(Activity::any);
        let started = Instant::now();
        let tiles = self.layout.tiles();
        self.stats.pixels_full += (tiles.len() * nw * nh * pairs) as u64;
        // Each run: where its crop starts in the resized plane, where its output goes, the
        // crop (in the network input's pixels) and what of its output is kept.
        let runs: Vec<(Tile, Crop)> = match (still, self.roi, activity.first()) {
            (true, _, _) => {
                self.stats.windows_skipped += 1;
                Vec::new()
            }
            (false, Some(margin), Some(a)) => {
                let mut union = vec![false; a.active().len()];
                for a in &activity {
                    union.iter_mut().zip(a.active()).for_each(|(u, &b)| *u |= b);
                }
                roi::plan(&union, a.tiles(), (nw, nh), margin)
                    .into_iter()
                    .flat_map(|c| tiles.iter().map(move |&t| (t, c.clone())))
                    .collect()
            }
            _ => tiles
                .iter()
                .map(|&t| {
                    let rect = Rect::full((nw, nh));
                    let keep = vec![Rect {
                        x0: t.keep_from,
                        ..rect
                    }];
                    (t, Crop { rect, keep })
                })
                .collect(),
        };
        for (tile, crop) in runs {
            let (cw, ch) = (crop.rect.width(), crop.rect.height());
            self.input.clear();
            let padded = std::iter::repeat_n(frames[0], pad).chain(frames.iter().copied());
            let padded: Vec<&(i64, Vec<f32>)> = padded.collect();
            for pair in padded.windows(2) {
                for (_, plane) in pair {
                    self.layout
                        .crop(plane, tile.input_x, &crop.rect, &mut self.tile);
                    self.input.extend_from_slice(&self.tile);
                }
            }
            let path = self.network.path().to_path_buf();
            self.network
                .run_with(&self.input, [1, pairs, 2, ch, cw], |shape, values| {
                    if shape[2] != channels {
                        return Err(Error::format(
                            &path,
                            format!("{} channels per interval, expected {channels}", shape[2]),
                        ));
                    }
                    // The kept parts of the crop go to the same pixels of the network's
                    // input, shifted by the tile's place in the events' frame.
                    let plane = ch * cw;
                    for k in 0..run.keep {
                        let j = pairs - run.keep + k;
                        for c in 0..channels {
                            let src = &values[(j * channels + c) * plane..][..plane];
                            let dst = &mut voxels[(k * channels + c) * oh * ow..][..oh * ow];
                            for r in &crop.keep {
                                for y in r.y0..r.y1 {
                                    let at = (y - crop.rect.y0) * cw + r.x0 - crop.rect.x0;
                                    let to = y * ow + tile.output_x + r.x0;
                                    dst[to..to + r.width()]
                                        .copy_from_slice(&src[at..at + r.width()]);
                                }
                            }
                        }
                    }
                    Ok(())
                })?;
            self.stats.pairs_run += pairs as u64;
            self.stats.pixels_run += (crop.rect.area() * pairs) as u64;
        }
        if !still {
            let us = started.elapsed().as_micros().clamp(1, 3_600_000_000) as u64;
            // Within the bounds just clamped to: recording cannot fail.
            let _ = self.window_us.record(us);
            self.stats.windows += 1;
        }
        self.stats.nonfinite += voxels.iter().filter(|v| !v.is_finite()).count() as u64;
        let size = channels * oh * ow;
        let floor = self.config.floor();
        if floor > 0.0 {
            voxels
                .iter_mut()
                .filter(|v| **v < floor)
                .for_each(|v| *v = 0.0);
        }
        for (k, a) in activity.iter().enumerate() {
            a.clear_inactive(&mut voxels[k * size..(k + 1) * size], (ow, oh));
            self.stats.tiles_gated += a.inactive() as u64;
        }
        for k in 0..run.keep {
            let (t0, t1) = (frames[first + k].0, frames[first + k + 1].0);
            let interval = Interval::new(t0, t1)?;
            let grid = VoxelGrid::from_dense(
                ow as u16,
                oh as u16,
                self.bins,
                &voxels[k * size..(k + 1) * size],
            )?;
            out.push(Stage1Batch::Voxels(grid, interval));
            self.stats.intervals += 1;
        }
        Ok(())
    }
}

impl Stage1 for LearnedStage1 {
    fn push(&mut self, frame: &Frame, out: &mut Vec<Stage1Batch>) -> Result<()> {
        let plane = self.layout.plane(frame, self.encoding)?;
        self.frames.push_back((frame.t, plane));
        while self.frames.len() > self.planner.capacity() {
            self.frames.pop_front();
        }
        match self.planner.push() {
            Some(run) => self.run(run, out),
            None => Ok(()),
        }
    }

    fn finish(&mut self, out: &mut Vec<Stage1Batch>) -> Result<()> {
        match self.planner.finish() {
            Some(run) => self.run(run, out),
            None => Ok(()),
        }
    }

    fn restart(&mut self) -> Result<()> {
        self.planner.restart();
        self.frames.clear();
        Ok(())
    }

    fn output_size(&self) -> (u16, u16) {
        self.layout.output()
    }

    fn stats(&self) -> Stage1Stats {
        let mut learned = self.stats.clone();
        if !self.window_us.is_empty() {
            learned.window_ms_p50 = self.window_us.value_at_quantile(0.5) as f64 / 1e3;
            learned.window_ms_max = self.window_us.max() as f64 / 1e3;
        }
        Stage1Stats {
            tier: <LearnedStats as super::TierRecord>::TIER,
            window: self.config.window,
            stride: self.config.stride(),
            window_ms_p50: learned.window_ms_p50,
            compute: learned.compute(),
            nonfinite: learned.nonfinite,
            record: std::sync::Arc::new(learned),
        }
    }

    fn describe(&self) -> String {
        format!(
            "learned ({}, L={} stride {}, {} geometry, {})",
            self.network.path().display(),
            self.config.window,
            self.config.stride(),
            self.config.geometry.name(),
            self.network.provider()
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Start frames and kept intervals of every window for `n` frames.
    fn plan(n: usize, window: usize, stride: usize) -> Vec<(usize, usize)> {
        let mut p = Planner::new(window, stride);
        let mut runs = Vec::new();
        for i in 0..n {
            if let Some(r) = p.push() {
                runs.push((i + 1 - r.frames, r.keep));
            }
        }
        if let Some(r) = p.finish() {
            runs.push((n - r.frames, r.keep));
        }
        runs
    }

    #[test]
    fn the_toolbox_plan() {
        // Spec 1.3 / Appendix B.6: N = 100 -> starts 0, 16, .., 80, 83; the last keeps 3.
        let runs = plan(100, 16, 16);
        let starts: Vec<usize> = runs.iter().map(|r| r.0).collect();
        assert_eq!(starts, vec![0, 16, 32, 48, 64, 80, 83]);
        assert_eq!(runs.last(), Some(&(83, 3)));
        assert_eq!(runs.iter().map(|r| r.1).sum::<usize>(), 99);
        // 59 frames (the davis346 clip): 4 windows, the last moved back to 42, keeping 10.
        assert_eq!(
            plan(59, 16, 16),
            vec![(0, 16), (16, 16), (32, 16), (42, 10)]
        );
        // 17 frames: one window; 33: two, nothing left over.
        assert_eq!(plan(17, 16, 16), vec![(0, 16)]);
        assert_eq!(plan(33, 16, 16), vec![(0, 16), (16, 16)]);
    }

    #[test]
    fn short_streams_and_overlap() {
        // Fewer than 17 frames: one shorter window over all of them; one frame: nothing.
        assert_eq!(plan(5, 16, 16), vec![(0, 4)]);
        assert!(plan(1, 16, 16).is_empty());
        // Live overlap: L = 8, stride 2: the first window keeps all 8, then every 2 frames.
        let runs = plan(14, 8, 2);
        assert_eq!(runs[0], (0, 8));
        assert_eq!(
            runs[1..].iter().map(|r| r.1).collect::<Vec<_>>(),
            vec![2, 2, 1]
        );
        assert_eq!(runs.iter().map(|r| r.1).sum::<usize>(), 13);
        // Every interval handed on exactly once, in order, for many settings.
        for (n, l, s) in [(50, 16, 16), (50, 16, 5), (3, 4, 1), (40, 1, 1), (23, 7, 3)] {
            let runs = plan(n, l, s);
            let mut next = 0;
            for (start, keep) in runs {
                let frames = (start..n).len().min(l + 1);
                let first_new = start + frames - 1 - keep;
                assert_eq!(first_new, next, "n {n} l {l} s {s}");
                next += keep;
            }
            assert_eq!(next, n - 1);
        }
    }
}
