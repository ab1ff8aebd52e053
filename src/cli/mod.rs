//! The command line: each command's flags (clap) and body, one module per command family, so
//! that `main.rs` only parses and dispatches.

pub(crate) mod batch;
pub(crate) mod convert;
pub(crate) mod dataset;
pub(crate) mod eval;
pub(crate) mod events;
pub(crate) mod listen;
pub(crate) mod model;
pub(crate) mod run;
pub(crate) mod tradeoff;

use std::path::{Path, PathBuf};

use clap::{Args, Subcommand};

use self::batch::BatchArgs;
use self::convert::ConvertArgs;
use self::dataset::{CalibrateArgs, DatasetCommand};
use self::eval::Eval;
use self::events::{InfoArgs, ReconstructArgs, RenderArgs, RepairArgs, TranscodeArgs};
use self::listen::ListenArgs;
use self::model::ModelCommand;
use self::run::{BenchArgs, BenchCommand, RunArgs};
use crate::config::Config;
use crate::error::Result;
use crate::format::{self};

/// Writes each flag that was given over the setting it overrides:
/// `given!(config.field => args.flag, ...)` (a flag of `Option<T>` onto a `T` or an
/// `Option<T>`).
macro_rules! given {
    ($($setting:expr => $flag:expr),* $(,)?) => {
        $(
            if let Some(v) = &$flag {
                $setting = v.to_owned().into();
            }
        )*
    };
}
pub(crate) use given;

/// The commands of `v2ce`.
#[derive(Subcommand)]
pub enum Command {
    /// Score simulated events against real recordings.
    #[command(subcommand)]
    Eval(Eval),
    /// Convert frames (a video, an image folder, a .y4m, or an .aedat4's APS frames) to events.
    Convert(ConvertArgs),
    /// Convert an event file to another format, streaming (.aedat4, .raw, .csv, .npz, .h5; IJRR
    /// .txt in).
    Transcode(TranscodeArgs),
    /// Print an event file's sensor size, event count, time span, rate and ON ratio.
    Info(InfoArgs),
    /// Make an event file a killed run left readable: cut after its last whole packet, word or
    /// line, or write an .npz / .h5 from its journal.
    Repair(RepairArgs),
    /// The live daemon: capture (a camera, a replayed file, or the bundled fixture video),
    /// simulate, and stream events over UDP / TCP / to a file until stopped.
    Run(RunArgs),
    /// List the cameras with their formats, sizes and frame rates.
    Devices,
    /// Measure the daemon: capture-to-send latency, CPU (per frame at each sub-frame cap) and
    /// memory at 346x260, 640x480 and 1280x720 on the replayed fixture video.
    Bench(BenchArgs),
    /// Draw an event file: one accumulated frame (.png) or frames at a rate (.gif, .mp4).
    Render(RenderArgs),
    /// Frames from an event file (each pixel's events integrated, high-passed), for
    /// simulating and evaluating recordings that have no frames.
    Reconstruct(ReconstructArgs),
    /// Receive what the daemon sends (UDP in any format, or its TCP stream): count events,
    /// measure rate, gaps and timing, optionally write them to a file.
    Listen(ListenArgs),
    /// The learned tier's network: import the official checkpoint, run a raw tensor.
    #[command(subcommand)]
    Model(ModelCommand),
    /// Fit the physics tier to your own sensor from a recording with frames and events, and
    /// write the fitted preset file (for --preset-file).
    Calibrate(CalibrateArgs),
    /// Write training data for the learned tier: synthetic scenes with simulated ground truth,
    /// or windows of a recording with frames and events.
    #[command(subcommand)]
    Dataset(DatasetCommand),
    /// Convert a dataset as one task of a cluster job: this task's share of a manifest (Slurm
    /// job arrays, Kubernetes Indexed Jobs), resumable, with a ledger per shard; or merge the
    /// ledgers into one report (--report DIR)
    Batch(BatchArgs),
    /// The DDS transport of a ROS 2 output or source, run by v2ce itself in a process of its
    /// own under a memory cap (`ros2::host`); not for people.
    #[command(name = "dds-host", hide = true)]
    DdsHost(DdsHostArgs),
}

/// The endpoint a `dds-host` child opens.
#[derive(Args)]
pub struct DdsHostArgs {
    /// The DDS domain.
    #[arg(long)]
    domain: u16,
    /// The ROS 2 topic.
    #[arg(long)]
    topic: String,
    /// The ROS 2 message type.
    #[arg(long = "type")]
    ros_type: String,
    /// The history depth.
    #[arg(long)]
    depth: u32,
    /// Best effort (else reliable).
    #[arg(long)]
    best_effort: bool,
    /// A publication (else a subscription).
    #[arg(long)]
    publish: bool,
}

impl Command {
    /// Runs the command.
    pub fn run(self) -> Result<()> {
        // A write past `ulimit -f` is an error like a full disk, not a silent death.
        crate::process::file_size_limit_is_an_error();
        match self {
            Command::Eval(Eval::Stage2(args)) => eval::eval_stage2(args),
            Command::Eval(Eval::Stage1(args)) => eval::eval_stage1(args),
            Command::Eval(Eval::Realism(args)) => eval::eval_realism(args),
            Command::Convert(args) => convert::convert(args),
            Command::Transcode(args) => events::transcode(args),
            Command::Info(args) => events::info(args),
            Command::Repair(args) => events::repair(args),
            Command::Run(args) => run::run(args),
            Command::Devices => run::devices(),
            Command::Bench(BenchArgs {
                what: Some(BenchCommand::Tradeoff(args)),
                ..
            }) => tradeoff::tradeoff(args),
            Command::Bench(args) => run::bench(args),
            Command::Listen(args) => listen::listen(args),
            Command::Render(args) => events::render(args),
            Command::Reconstruct(args) => events::reconstruct(args),
            Command::Model(ModelCommand::Import(args)) => model::model_import(args),
            Command::Model(ModelCommand::Run(args)) => model::model_run(args),
            Command::Model(ModelCommand::Bench(args)) => model::model_bench(args),
            Command::Calibrate(args) => dataset::calibrate(args),
            Command::Dataset(DatasetCommand::Synthetic(args)) => dataset::dataset_synthetic(args),
            Command::Dataset(DatasetCommand::Recording(args)) => dataset::dataset_recording(args),
            Command::Batch(args) => batch::batch(args),
            Command::DdsHost(a) => crate::ros2::host::serve(&crate::ros2::host::Endpoint {
                domain: crate::ros2::dds::check_domain("--domain", a.domain.into())?,
                topic: a.topic,
                ros_type: a.ros_type,
                qos: crate::ros2::dds::Qos {
                    reliable: !a.best_effort,
                    depth: a.depth,
                },
                publish: a.publish,
            }),
        }
    }
}

/// How `v2ce model run` and `bench` run the network.
#[derive(Args)]
pub struct RuntimeArgs {
    /// ONNX Runtime threads (0: one per core).
    #[arg(long, default_value_t = 0)]
    pub(crate) threads: usize,
    /// Execution provider: cpu, cuda, auto (CUDA when the library has it and it starts).
    #[arg(long, value_enum, default_value_t = crate::stage1::learned::Device::Auto)]
    pub(crate) device: crate::stage1::learned::Device,
    /// Keep ONNX Runtime's CPU memory arena (off by default: half the peak memory).
    #[arg(long)]
    pub(crate) cpu_arena: bool,
}

impl RuntimeArgs {
    /// The learned tier's settings these flags ask for (the runtime's; the rest default).
    pub fn options(&self) -> crate::stage1::LearnedConfig {
        crate::stage1::LearnedConfig {
            threads: self.threads,
            device: self.device,
            cpu_arena: self.cpu_arena,
            ..Default::default()
        }
    }
}

/// Stage 1 tier flags shared by `convert` and `run` (each overrides `[stage1]` and
/// `[stage1.learned]`).
#[derive(Args)]
pub struct TierArgs {
    /// Stage 1 tier: physics (the pixel model), learned (the V2CE network; the built-in model
    /// unless --model), auto (learned when this machine runs it at --budget-fps, else
    /// physics) [config default: physics].
    #[arg(long, value_enum)]
    pub(crate) stage1: Option<crate::stage1::Tier>,
    /// The frame rate `--stage1 auto` must hold (0: none) [config default: 30].
    #[arg(long, value_name = "FPS")]
    pub(crate) budget_fps: Option<f64>,
    /// ONNX model of the learned tier (implies --stage1 learned) [config default: none].
    #[arg(long, value_name = "M.onnx")]
    pub(crate) model: Option<PathBuf>,
    /// Frame intervals per window of the learned tier (the network was trained on 16) [config
    /// default: 16].
    #[arg(long)]
    pub(crate) window: Option<usize>,
    /// New intervals per window (1..=window; less overlaps windows for a shorter wait) [config
    /// default: 0, the window].
    #[arg(long)]
    pub(crate) stride: Option<usize>,
    /// How frames are fitted to the network: native, resize, center, pano [config default:
    /// native].
    #[arg(long, value_enum)]
    pub(crate) geometry: Option<crate::stage1::Geometry>,
    /// ONNX Runtime threads (0: one per core) [config default: 0].
    #[arg(long)]
    pub(crate) threads: Option<usize>,
    /// Execution provider: cpu, cuda, auto [config default: auto].
    #[arg(long, value_enum)]
    pub(crate) device: Option<crate::stage1::learned::Device>,
    /// Learned tier: output values below this are zero before Stage 2 [config default: unset,
    /// the built-in model's own floor, 0 for other models].
    #[arg(long)]
    pub(crate) floor: Option<f32>,
    /// Learned tier: pixels the network's crops reach beyond the regions that changed (less
    /// than the model's receptive field is faster, no longer exact) [config default: unset, the
    /// model's receptive field].
    #[arg(long, value_name = "PX")]
    pub(crate) roi_margin: Option<usize>,
    /// Learned tier: run the network on whole frames, not only around what changed.
    #[arg(long)]
    pub(crate) no_roi: bool,
    #[command(flatten)]
    pub(crate) motion: MotionArgs,
}

/// How the physics tier sees motion between frames (`[stage1.physics]` motion keys); shared by
/// `convert`, `run`, `bench` and `calibrate`.
#[derive(Args)]
pub struct MotionArgs {
    /// Physics tier: the light between frames, linear (per pixel) or flow (sub-frames warped
    /// along the optical flow) [config default: the preset's].
    #[arg(long, value_enum)]
    pub(crate) motion: Option<crate::stage1::Motion>,
    /// Physics tier, --motion flow: the most a pixel moves per sub-frame, pixels [config
    /// default: the preset's].
    #[arg(long, value_name = "PX")]
    pub(crate) max_step_px: Option<f64>,
    /// Physics tier, --motion flow: the most sub-frame intervals per frame interval (1:
    /// linear) [config default: the preset's].
    #[arg(long, value_name = "N")]
    pub(crate) max_subframes: Option<u32>,
    /// Physics tier, --motion flow: the optical flow's preset, ultrafast, fast, medium
    /// [config default: the preset's].
    #[arg(long, value_enum)]
    pub(crate) flow_preset: Option<crate::flow::FlowPreset>,
    /// Physics tier, --motion flow: which optical flow, dis (the project's own) or opencv (a
    /// build with the `opencv-flow` feature only, for comparison) [config default: dis].
    #[arg(long, value_enum)]
    pub(crate) flow_backend: Option<crate::flow::FlowBackend>,
}

impl MotionArgs {
    /// Writes the flags given onto the physics tier's overrides.
    pub fn apply(&self, physics: &mut crate::stage1::PhysicsOverrides) {
        given!(
            physics.motion => self.motion,
            physics.max_step_px => self.max_step_px,
            physics.max_subframes => self.max_subframes,
            physics.flow_preset => self.flow_preset,
            physics.flow_backend => self.flow_backend,
        );
    }
}

impl TierArgs {
    /// Writes the flags given onto `config` (`[stage1]`, `[stage1.learned]`) and checks the result.
    pub fn apply(&self, config: &mut Config) -> Result<()> {
        let stage1 = &mut config.stage1;
        if self.model.is_some() {
            stage1.tier = crate::stage1::Tier::Learned;
        }
        given!(
            stage1.learned.model => self.model,
            stage1.tier => self.stage1,
            stage1.learned.window => self.window,
            stage1.learned.stride => self.stride,
            stage1.learned.geometry => self.geometry,
            stage1.learned.threads => self.threads,
            stage1.learned.device => self.device,
            stage1.learned.floor => self.floor,
            stage1.learned.roi_margin => self.roi_margin,
            stage1.budget_fps => self.budget_fps,
        );
        self.motion.apply(&mut stage1.physics);
        stage1.learned.roi &= !self.no_roi;
        config.stage1.validate()?;
        config.stage1.learned.validate()
    }
}

/// How an output file is encoded, beyond what its extension says.
#[derive(Args)]
pub struct EncodingArgs {
    /// EVT version of a .raw output (2 by default: some readers mis-time EVT 3.0).
    #[arg(long, value_parser = ["2", "3"], default_value = "2")]
    pub(crate) evt: String,
    /// Packet compression of an .aedat4 output: lz4, zstd, zstd-high or none.
    #[arg(long, default_value = "lz4")]
    pub(crate) compression: String,
}

impl EncodingArgs {
    /// The output format for `path`.
    pub fn format_for(&self, path: &Path) -> Result<format::Format> {
        let compression = format::Compression::from_name(&self.compression)?;
        format::Format::for_output(path, self.evt.parse::<u8>().ok(), compression)
    }
}

/// `frames/total frames (pct), N events, rate, ETA` (without a total: frames, events, rate).
pub fn progress_line(frames: u64, total: Option<u64>, events: u64, seconds: f64) -> String {
    let rate = frames as f64 / seconds.max(1e-9);
    match total {
        Some(total) if total > 0 => {
            let left = total.saturating_sub(frames) as f64 / rate.max(1e-9);
            format!(
                "{frames}/{total} frames ({:.1}%), {events} events, {rate:.1} frames/s, ETA {}   ",
                100.0 * frames as f64 / total as f64,
                if frames == 0 {
                    "-".to_string()
                } else {
                    format!("{:.0} s", left)
                }
            )
        }
        _ => format!("{frames} frames, {events} events, {rate:.1} frames/s   "),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn progress_shows_total_percentage_and_eta_when_the_length_is_known() {
        let line = super::progress_line(50, Some(200), 1234, 5.0);
        assert!(
            line.starts_with("50/200 frames (25.0%), 1234 events, 10.0 frames/s, ETA 15 s"),
            "{line}"
        );
        let line = super::progress_line(7, None, 9, 1.0);
        assert!(
            line.starts_with("7 frames, 9 events, 7.0 frames/s"),
            "{line}"
        );
    }
}
