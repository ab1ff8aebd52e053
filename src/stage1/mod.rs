//! Stage 1: frames to events (or to voxels, for Stage 2 to sample).
//!
//! Every tier implements one trait, [`Stage1`]: frames go in one at a time, and zero or more
//! [`Stage1Batch`]es (the events or the voxel of one frame interval each) come out, in interval
//! order. The pipeline and `v2ce convert` hold a `Box<dyn Stage1>` and never a concrete tier.
//!
//! - [`physics`]: a physical model of the DVS pixel (window of one interval). Its parameters
//!   come from a sensor [`Preset`] with any of them overridden in the `[stage1.physics]` table.
//! - [`learned`]: the V2CE network (an ONNX model run by ONNX Runtime) on windows of `L`
//!   frame intervals (`[stage1.learned]`).
//!
//! Adding a tier is one file implementing [`Stage1`] plus one [`Tier`] variant.

pub mod auto;
pub mod learned;
pub mod motion;
pub mod physics;

use serde::{Deserialize, Serialize};
use serde_json::value::RawValue;

use crate::error::{Error, Result};
use crate::event::Event;
use crate::frame::Frame;
pub use crate::frame::SourceEncoding;
use crate::interval::Interval;
use crate::voxel::VoxelGrid;

pub use learned::{Geometry, LearnedConfig, LearnedStage1, LearnedStats};
pub use motion::{Motion, MotionStats};
pub use physics::{LightModel, PhysicsConfig, PhysicsSim, PhysicsStage1, PhysicsStats, Preset};

/// What Stage 1 hands to Stage 2 for one frame interval.
#[derive(Debug)]
pub enum Stage1Batch {
    /// Events of the interval ending at `end` (the time of the frame that closed it), in time
    /// order.
    Events {
        /// The events.
        events: Vec<Event>,
        /// The time of the frame that closed the interval, us.
        end: i64,
    },
    /// The interval's events as a voxel grid, for the Stage 2 sampler to re-time.
    Voxels(VoxelGrid, Interval),
}

impl Stage1Batch {
    /// Events in the batch (for voxels: the grid's active cells).
    pub fn weight(&self) -> u64 {
        match self {
            Stage1Batch::Events { events, .. } => events.len() as u64,
            Stage1Batch::Voxels(g, _) => g.active_cells() as u64,
        }
    }

    /// The time of the frame that closed this batch's interval, us.
    pub fn end(&self) -> i64 {
        match self {
            Stage1Batch::Events { end, .. } => *end,
            Stage1Batch::Voxels(_, interval) => interval.end(),
        }
    }
}

/// A counter a tier fills, exported on `/metrics` as
/// `v2ce_stage1_{family}_total{result="{result}"}`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Counter {
    /// The metric family (`tiles`, `windows`).
    pub family: &'static str,
    /// The family's help line.
    pub help: &'static str,
    /// The `result` label (`active`, `skipped`, `run`).
    pub result: &'static str,
    /// The count so far.
    pub value: u64,
}

impl Counter {
    /// The counters of one family, a value per `result`.
    pub fn family(
        family: &'static str,
        help: &'static str,
        values: &[(&'static str, u64)],
    ) -> Vec<Counter> {
        values
            .iter()
            .map(|&(result, value)| Counter {
                family,
                help,
                result,
                value,
            })
            .collect()
    }
}

/// A tier's own counters: what it reports in its section of a report, the words of its
/// summary, and the [`Counter`]s it exports. The zero record stands for a tier that did not
/// run.
pub trait TierRecord: Serialize + Default + std::fmt::Debug + Send + Sync + 'static {
    /// The tier's name, the key of its section in reports.
    const TIER: &'static str;
    /// What the tier did, in words, given its window and stride.
    fn summary(&self, window: usize, stride: usize) -> String;
    /// The counters this record holds, for `/metrics`.
    fn counters(&self) -> Vec<Counter>;
    /// How the tier stands now, for the daemon's periodic stats line (the physics tier: its
    /// sub-frame cap and how it moved); `None` when there is nothing to say.
    fn status(&self) -> Option<TierStatus> {
        None
    }
}

/// How a tier stands at one moment (see [`TierRecord::status`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TierStatus {
    /// In words, for the stats line.
    pub line: String,
    /// The tier's level of detail now, where it trades detail for time (the physics tier's
    /// sub-frame cap), so that costs can be told apart by level.
    pub level: Option<u32>,
}

/// A tier's record as [`Stage1Stats`] carries it: read only when asked (a report, a scrape,
/// the end of a conversion), so publishing the stats after every frame costs a copy.
pub trait Record: std::fmt::Debug + Send + Sync {
    /// See [`TierRecord::summary`].
    fn summary(&self, window: usize, stride: usize) -> String;
    /// See [`TierRecord::counters`].
    fn counters(&self) -> Vec<Counter>;
    /// See [`TierRecord::status`].
    fn status(&self) -> Option<TierStatus>;
    /// The record as JSON text, its fields in their declared order.
    fn json(&self) -> Box<RawValue>;
}

impl<R: TierRecord> Record for R {
    fn summary(&self, window: usize, stride: usize) -> String {
        TierRecord::summary(self, window, stride)
    }

    fn counters(&self) -> Vec<Counter> {
        TierRecord::counters(self)
    }

    fn status(&self) -> Option<TierStatus> {
        TierRecord::status(self)
    }

    fn json(&self) -> Box<RawValue> {
        serde_json::value::to_raw_value(self).unwrap_or_else(|_| null())
    }
}

/// The record of stats no tier has filled yet.
#[derive(Debug)]
struct NoRecord;

impl Record for NoRecord {
    fn summary(&self, _: usize, _: usize) -> String {
        String::new()
    }

    fn counters(&self) -> Vec<Counter> {
        Vec::new()
    }

    fn status(&self) -> Option<TierStatus> {
        None
    }

    fn json(&self) -> Box<RawValue> {
        null()
    }
}

fn null() -> Box<RawValue> {
    RawValue::from_string("null".into()).expect("null is JSON")
}

/// A zero section of every tier (its name, its record as JSON, its counters), in the order
/// reports list them.
fn zero_sections() -> Vec<(&'static str, Box<RawValue>, Vec<Counter>)> {
    fn zero<R: TierRecord>() -> (&'static str, Box<RawValue>, Vec<Counter>) {
        let r = R::default();
        (R::TIER, Record::json(&r), TierRecord::counters(&r))
    }
    vec![zero::<PhysicsStats>(), zero::<LearnedStats>()]
}

/// Every tier's counters, each with the value `stats` holds (zero for the tiers that did not
/// run): the families `/metrics` always exports.
pub fn all_counters(stats: &Stage1Stats) -> Vec<Counter> {
    let own = &stats.record.counters();
    zero_sections()
        .into_iter()
        .flat_map(|(tier, _, zeros)| {
            zeros.into_iter().map(move |zero| {
                let value = own
                    .iter()
                    .find(|c| {
                        tier == stats.tier && c.family == zero.family && c.result == zero.result
                    })
                    .map_or(0, |c| c.value);
                Counter { value, ..zero }
            })
        })
        .collect()
}

/// What a Stage 1 tier did, in the terms every tier shares: the pipeline, `/metrics`, `bench
/// tradeoff` and the command line read these and never a concrete tier's record.
#[derive(Debug, Clone)]
pub struct Stage1Stats {
    /// The tier's name (`physics`, `learned`).
    pub tier: &'static str,
    /// Frame intervals per window (1 for a tier that works interval by interval).
    pub window: usize,
    /// New intervals per window (equal to `window` when windows do not overlap).
    pub stride: usize,
    /// Median time of one window's work, ms (0 for a tier that does not time its windows).
    pub window_ms_p50: f64,
    /// The share of whole-frame work the tier spent (1 when it ran on everything, or before
    /// any work).
    pub compute: f64,
    /// Values the tier's model gave that were NaN or infinite.
    pub nonfinite: u64,
    /// The tier's own record: its section of a report, its summary and its counters.
    pub record: std::sync::Arc<dyn Record>,
}

impl Stage1Stats {
    /// What the tier did, in words, for the end of a conversion's report line.
    pub fn summary(&self) -> String {
        self.record.summary(self.window, self.stride)
    }
}

impl Default for Stage1Stats {
    fn default() -> Self {
        Stage1Stats {
            tier: "",
            window: 0,
            stride: 0,
            window_ms_p50: 0.0,
            compute: 1.0,
            nonfinite: 0,
            record: std::sync::Arc::new(NoRecord),
        }
    }
}

/// Reports show the tier, its window and stride, then a section per tier: the record of the
/// one that ran, zeros for the others.
impl Serialize for Stage1Stats {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        use serde::ser::SerializeStruct;
        let sections = zero_sections();
        let mut m = s.serialize_struct("Stage1Stats", 3 + sections.len())?;
        m.serialize_field("tier", self.tier)?;
        m.serialize_field("window", &self.window)?;
        m.serialize_field("stride", &self.stride)?;
        for (tier, zero, _) in &sections {
            if *tier == self.tier {
                m.serialize_field(tier, &self.record.json())?;
            } else {
                m.serialize_field(tier, zero)?;
            }
        }
        m.end()
    }
}

/// One Stage 1 tier: frames in, batches of events or voxels out.
pub trait Stage1: Send {
    /// Takes the next frame (times strictly increasing) and appends to `out` the batches of
    /// every interval this frame completes: none while a window fills, one per frame for the
    /// physics tier, a window's worth at once for the learned tier.
    fn push(&mut self, frame: &Frame, out: &mut Vec<Stage1Batch>) -> Result<()>;

    /// End of the stream: appends the batches of intervals still held (a partial window).
    fn finish(&mut self, out: &mut Vec<Stage1Batch>) -> Result<()>;

    /// Starts over after a break in the frames (a camera that came back): the next frame only
    /// opens an interval, as the first one did. Call [`Stage1::finish`] first to keep what is
    /// held.
    fn restart(&mut self) -> Result<()>;

    /// Width and height of the events it makes (the frames' size, unless the tier resamples).
    fn output_size(&self) -> (u16, u16);

    /// The tier's counters so far (across restarts).
    fn stats(&self) -> Stage1Stats;

    /// What this tier is, for logs (`physics (preset davis346)`, `learned (model.onnx, L=16)`).
    fn describe(&self) -> String;

    /// A live run that drops frames it cannot take: frames arrive at their own times divided
    /// by `speed`, and the tier must keep up. A tier with a knob of cost may turn it down while
    /// its work per frame outgrows the frames' pace, and say so (the physics tier lowers its
    /// sub-frame cap). Offline runs, and live ones that lose nothing (`block`), never call
    /// this, so their output depends on their input alone.
    fn pace(&mut self, _speed: f64) {}

    /// An offline run, whose frames are read as fast as the tier takes them: the tier may hold
    /// a frame back to overlap its work on the next (the physics tier finds the next interval's
    /// motion while it steps the current one). Each interval's batch then comes with the next
    /// frame, or at [`Stage1::finish`]; the batches are the same. Live runs never call this.
    fn look_ahead(&mut self) {}

    /// A live run (after [`Stage1::pace`]) whose latency budget leaves room to hold a frame
    /// back: the tier may do so, as [`Stage1::look_ahead`] does, while consecutive frames are
    /// at most `most` apart in wall time (each interval's batch then comes up to that much
    /// later, and its work overlaps the next interval's). Frames further apart are not held.
    fn look_ahead_within(&mut self, _most: std::time::Duration) {}
}

/// What a wrapper adds to the tier it wraps (see [`Tapped`]): a look at each batch the tier
/// hands on, a step at the end of the stream, and words for [`Stage1::describe`]. Everything
/// else goes to the tier as it is.
pub trait Tap: Send {
    /// Sees the batches the tier just handed on.
    fn batches(&mut self, _batches: &[Stage1Batch]) -> Result<()> {
        Ok(())
    }

    /// The end of the stream (or a break in it), after the tier's own [`Stage1::finish`].
    fn finished(&mut self) -> Result<()> {
        Ok(())
    }

    /// How the wrapped tier is described, given the tier's own words.
    fn describe(&self, tier: String) -> String {
        tier
    }
}

/// A tier with a [`Tap`] on it: itself a [`Stage1`].
pub struct Tapped<T: Tap> {
    tier: Box<dyn Stage1>,
    tap: T,
}

impl<T: Tap> Tapped<T> {
    /// `tier` with `tap` on it.
    pub fn new(tier: Box<dyn Stage1>, tap: T) -> Self {
        Tapped { tier, tap }
    }
}

impl<T: Tap> Stage1 for Tapped<T> {
    fn push(&mut self, frame: &Frame, out: &mut Vec<Stage1Batch>) -> Result<()> {
        let from = out.len();
        self.tier.push(frame, out)?;
        self.tap.batches(&out[from..])
    }

    fn finish(&mut self, out: &mut Vec<Stage1Batch>) -> Result<()> {
        let from = out.len();
        self.tier.finish(out)?;
        self.tap.batches(&out[from..])?;
        self.tap.finished()
    }

    fn restart(&mut self) -> Result<()> {
        self.tier.restart()
    }

    fn output_size(&self) -> (u16, u16) {
        self.tier.output_size()
    }

    fn stats(&self) -> Stage1Stats {
        self.tier.stats()
    }

    fn describe(&self) -> String {
        self.tap.describe(self.tier.describe())
    }

    fn pace(&mut self, speed: f64) {
        self.tier.pace(speed)
    }

    fn look_ahead(&mut self) {
        self.tier.look_ahead()
    }

    fn look_ahead_within(&mut self, most: std::time::Duration) {
        self.tier.look_ahead_within(most)
    }
}

/// The Stage 1 tiers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Tier {
    /// The physical pixel model (fast, CPU, real time).
    #[default]
    Physics,
    /// The V2CE network through ONNX Runtime (`[stage1.learned]`; the built-in model unless
    /// one is configured).
    Learned,
    /// The learned tier when this machine runs it fast enough for `budget_fps`, else physics
    /// (the rule: [`auto`]).
    Auto,
}

impl Tier {
    /// The name as configs and flags spell it.
    pub fn name(self) -> &'static str {
        match self {
            Tier::Physics => "physics",
            Tier::Learned => "learned",
            Tier::Auto => "auto",
        }
    }
}

/// Builds the configured tier for frames of `size`; `bins` is Stage 2's node count, which a
/// voxel-emitting tier must honour; `encoding` says how the source's values were decoded.
pub fn build(
    config: &Stage1Config,
    bins: usize,
    size: (u16, u16),
    encoding: SourceEncoding,
) -> Result<Box<dyn Stage1>> {
    Ok(match config.tier {
        Tier::Physics => Box::new(PhysicsStage1::new(config, bins, size)?),
        Tier::Learned => Box::new(LearnedStage1::new(&config.learned, bins, size, encoding)?),
        Tier::Auto => auto::build(config, bins, size, encoding)?,
    })
}

/// How Stage 1's output reaches the event stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Stage1Output {
    /// The model's events, with their interpolated crossing times (the most accurate).
    #[default]
    Events,
    /// The model's events voxelized per frame interval and re-timed by the Stage 2 sampler (the
    /// V2CE pipeline's shape: what a learned Stage 1 would hand over).
    Voxels,
}

/// Overrides of single physics parameters (each optional; see [`PhysicsConfig`]).
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(missing_docs)]
pub struct PhysicsOverrides {
    pub threshold_on: Option<f64>,
    pub threshold_off: Option<f64>,
    pub threshold_sigma: Option<f64>,
    pub threshold_noise: Option<f64>,
    pub refractory_us: Option<f64>,
    pub cutoff_hz: Option<f64>,
    pub dark_current: Option<f64>,
    pub linlog_knee: Option<f64>,
    pub leak_hz: Option<f64>,
    pub shot_noise_hz: Option<f64>,
    pub hot_pixel_fraction: Option<f64>,
    pub hot_pixel_hz: Option<f64>,
    pub max_substeps: Option<u32>,
    pub tile: Option<u16>,
    pub scene_level: Option<f64>,
    pub light: Option<LightModel>,
    pub exposure_us: Option<f64>,
    pub flicker_hz: Option<f64>,
    pub flicker_depth: Option<f64>,
    pub motion: Option<Motion>,
    pub max_step_px: Option<f64>,
    pub max_subframes: Option<u32>,
    pub flow_preset: Option<crate::flow::FlowPreset>,
    pub flow_backend: Option<crate::flow::FlowBackend>,
}

impl PhysicsOverrides {
    /// `base` with the overridden parameters replaced.
    pub fn apply(&self, mut base: PhysicsConfig) -> PhysicsConfig {
        macro_rules! set {
            ($($f:ident),*) => { $( if let Some(v) = self.$f { base.$f = v; } )* };
        }
        set!(
            threshold_on,
            threshold_off,
            threshold_sigma,
            threshold_noise,
            refractory_us,
            cutoff_hz,
            dark_current,
            linlog_knee,
            leak_hz,
            shot_noise_hz,
            hot_pixel_fraction,
            hot_pixel_hz,
            max_substeps,
            tile,
            scene_level,
            light,
            exposure_us,
            flicker_hz,
            flicker_depth,
            motion,
            max_step_px,
            max_subframes,
            flow_preset,
            flow_backend
        );
        base
    }
}

/// Stage 1 settings.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Stage1Config {
    /// The tier: `physics` or `learned`.
    pub tier: Tier,
    /// Sensor preset.
    pub preset: Preset,
    /// A preset file (as `v2ce calibrate` writes: every `[stage1.physics]` parameter) used
    /// instead of `preset` (empty: none). Relative paths are from the configuration file.
    pub preset_file: std::path::PathBuf,
    /// The parameters read from `preset_file`.
    #[serde(skip)]
    pub custom: Option<PhysicsConfig>,
    /// Events directly, or voxels through Stage 2.
    pub output: Stage1Output,
    /// Seed of mismatch, hot pixels and noise.
    pub seed: u64,
    /// Single-parameter overrides of the preset.
    pub physics: PhysicsOverrides,
    /// The learned tier's model and windows.
    pub learned: LearnedConfig,
    /// The frame rate `tier = "auto"` must hold, fps (0: no budget, learned whenever it can
    /// run).
    pub budget_fps: f64,
}

impl Default for Stage1Config {
    fn default() -> Self {
        Stage1Config {
            tier: Tier::default(),
            preset: Preset::default(),
            preset_file: Default::default(),
            custom: None,
            output: Stage1Output::default(),
            seed: 0,
            physics: PhysicsOverrides::default(),
            learned: LearnedConfig::default(),
            budget_fps: auto::DEFAULT_BUDGET_FPS,
        }
    }
}

impl Stage1Config {
    /// The physics parameters: the preset (or the preset file's parameters) with the
    /// overrides applied.
    pub fn physics_config(&self) -> PhysicsConfig {
        let base = self.custom.clone().unwrap_or_else(|| self.preset.config());
        self.physics.apply(base)
    }

    /// Checks the settings that are not the physics or learned tables'.
    pub fn validate(&self) -> Result<()> {
        let b = self.budget_fps;
        if !(b.is_finite() && (0.0..=100_000.0).contains(&b)) {
            return Err(Error::invalid(
                "stage1.budget_fps",
                format!("{b}; need 0 (no budget) to 100000 fps"),
            ));
        }
        Ok(())
    }

    /// Reads `path` as a preset file (see `preset_file`) and uses it from now on.
    pub fn load_preset_file(&mut self, path: &std::path::Path) -> Result<()> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let config: PhysicsConfig = crate::toml_doc::parse(&text, path)?;
        config
            .validate()
            .map_err(|e| Error::format(path, e.to_string()))?;
        self.preset_file = path.to_path_buf();
        self.custom = Some(config);
        Ok(())
    }

    /// What the physics tier's parameters come from, for logs: the preset's name or the file.
    pub fn preset_name(&self) -> String {
        if self.custom.is_some() {
            format!("file {}", self.preset_file.display())
        } else {
            self.preset.name().to_string()
        }
    }
}
