//! The `v2ce` command-line tool: a thin layer over the library.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};

use v2ce::config::{parse_size, Config};
use v2ce::format::{self, csv, Recording};
use v2ce::interval::{fixed_intervals, intervals_from_frames, Interval};
use v2ce::stage2::SamplerKind;
use v2ce::{Error, Result};

#[derive(Parser)]
#[command(
    name = "v2ce",
    version,
    about = "Video to continuous events: a DVS simulator (V2CE)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
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
    /// The live daemon: capture (a camera, a replayed file, or the bundled fixture video),
    /// simulate, and stream events over UDP / TCP / to a file until stopped.
    Run(RunArgs),
    /// List the cameras with their formats, sizes and frame rates.
    Devices,
    /// Measure the daemon: capture-to-send latency, CPU and memory at 346x260 and 640x480 on
    /// the replayed fixture video.
    Bench(BenchArgs),
    /// Draw an event file: one accumulated frame (.png) or frames at a rate (.gif, .mp4).
    Render(RenderArgs),
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
}

#[derive(Subcommand)]
enum DatasetCommand {
    /// Random scenes rendered at a high rate; ground truth from the physics tier, inputs at
    /// video rate (README: "Training data").
    Synthetic(SyntheticArgs),
    /// Windows of a recording's frames with its real events, from one half of it by time.
    Recording(DatasetRecordingArgs),
}

#[derive(Args)]
struct SyntheticArgs {
    /// The dataset folder (sequences seq_NNNNN.npz and dataset.json).
    #[arg(short, long)]
    out: PathBuf,
    /// Sequences to write.
    #[arg(long, default_value_t = 100)]
    count: usize,
    /// Seed: the same seed and settings give the same dataset.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Frame size.
    #[arg(long, value_name = "WxH", default_value = "160x120")]
    size: String,
    /// Frame intervals per sequence.
    #[arg(long, default_value_t = 16)]
    pairs: usize,
    /// Frame rate of the inputs: one value or a range LO..HI drawn per sequence.
    #[arg(long, default_value = "25..60")]
    fps: String,
    /// The ground truth is simulated at least this often, Hz.
    #[arg(long, default_value_t = 1000.0)]
    rate: f64,
    /// Sensor noise in the ground truth: on, off, mixed (half of the sequences).
    #[arg(long, value_enum, default_value_t = v2ce::dataset::NoiseMode::Mixed)]
    noise: v2ce::dataset::NoiseMode,
    /// The ground-truth sensor preset: davis346, dvxplorer, ideal.
    #[arg(long, default_value = "davis346")]
    preset: String,
    /// A preset file (as `v2ce calibrate` writes) instead of --preset.
    #[arg(long, conflicts_with = "preset")]
    preset_file: Option<PathBuf>,
    /// A folder of natural images (PNG, JPEG) used as textures beside procedural ones.
    #[arg(long)]
    images: Option<PathBuf>,
    /// Largest read noise of the input frames, 8-bit steps.
    #[arg(long, default_value_t = 1.5)]
    input_noise: f64,
    /// Threads (0: one per core).
    #[arg(long, default_value_t = 0)]
    threads: usize,
}

#[derive(Args)]
struct DatasetRecordingArgs {
    /// The recording: an .aedat4 with events and APS frames, or an event file whose frames
    /// come from --frames.
    #[arg(long)]
    real: PathBuf,
    /// The frames, when the recording has none in it (a video, an image folder, an IJRR
    /// images.txt), on the events' time base.
    #[arg(long)]
    frames: Option<PathBuf>,
    /// The dataset folder.
    #[arg(short, long)]
    out: PathBuf,
    /// Which frame intervals: first (half, by time), second, all.
    #[arg(long, value_enum, default_value_t = v2ce::dataset::Split::All)]
    split: v2ce::dataset::Split,
    /// Frame intervals per sequence.
    #[arg(long, default_value_t = 16)]
    pairs: usize,
    /// How --frames' image values relate to the light (as convert's --color).
    #[arg(long, value_enum, default_value_t = v2ce::frame::images::ColorSpace::Auto)]
    color: v2ce::frame::images::ColorSpace,
    /// Use at most this many frames (they are held in memory).
    #[arg(long, default_value_t = 3000)]
    max_frames: usize,
}

#[derive(Args)]
struct CalibrateArgs {
    /// The real recording: an .aedat4 with events and APS frames, or an event file whose frames
    /// come from --frames (.aedat4, .raw, .csv, .h5, .npz, IJRR events.txt).
    #[arg(long)]
    real: PathBuf,
    /// The frames, when the recording has none in it: a video, an image folder or a frame list
    /// (IJRR images.txt), on the events' time base.
    #[arg(long)]
    frames: Option<PathBuf>,
    /// Write the fitted preset file here (TOML: every [stage1.physics] parameter).
    #[arg(short, long)]
    output: PathBuf,
    /// The preset the fit starts from and keeps what it does not fit of: davis346, dvxplorer,
    /// ideal.
    #[arg(long, default_value = "davis346")]
    preset: String,
    /// Seed of mismatch and noise in the fits.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// How --frames' image values relate to the light (as convert's --color).
    #[arg(long, value_enum, default_value_t = v2ce::frame::images::ColorSpace::Auto)]
    color: v2ce::frame::images::ColorSpace,
    /// Use at most this many frames (they are held in memory).
    #[arg(long, default_value_t = 3000)]
    max_frames: usize,
    /// Print the report as one JSON object on stdout.
    #[arg(long)]
    json: bool,
    /// Overwrite an existing output file.
    #[arg(long)]
    force: bool,
}

#[derive(Args)]
struct RenderArgs {
    /// Events: .aedat4, .raw, .csv, .npz, .h5/.hdf5, IJRR .txt.
    input: PathBuf,
    /// The picture: .png (every event in one frame), .gif or .mp4 (frames at --fps).
    #[arg(short, long)]
    output: PathBuf,
    /// Frames per second of event time.
    #[arg(long, default_value_t = 30.0)]
    fps: f64,
    /// Fade events with this time constant (ms) instead of showing each frame's window.
    #[arg(long)]
    decay_ms: Option<f64>,
    /// Play back this many times slower than real time.
    #[arg(long, default_value_t = 1.0)]
    slowdown: f64,
    /// Sensor size when the file has none (CSV).
    #[arg(long, value_name = "WxH")]
    size: Option<String>,
    /// Overwrite an existing output file.
    #[arg(long)]
    force: bool,
}

#[derive(Args)]
struct ListenArgs {
    /// Bind this HOST:PORT for UDP datagrams (port 0: any; the address is printed).
    #[arg(long, conflicts_with = "tcp")]
    udp: Option<String>,
    /// The datagram format: spif, spif_timestamped, t64_x16_y16_on8, t32_x16_y15_on1.
    #[arg(long, default_value = "spif")]
    format: String,
    /// Connect to a daemon's TCP stream at HOST:PORT (AEDAT 4.0 or RAW EVT 2.0/3.0).
    #[arg(long)]
    tcp: Option<String>,
    /// Write the events to this file (.aedat4, .raw, .csv, .npz, .h5); plain spif events get their
    /// arrival time.
    #[arg(short, long)]
    out: Option<PathBuf>,
    /// Sensor size for the file (UDP formats carry none).
    #[arg(long, value_name = "WxH", default_value = "640x480")]
    size: String,
    /// Stop after this many seconds.
    #[arg(long)]
    duration: Option<f64>,
    /// Stop when nothing arrived for this many seconds after the first arrival.
    #[arg(long, default_value_t = 2.0)]
    idle: f64,
    /// Stop after this many events.
    #[arg(long)]
    max_events: Option<u64>,
    /// Kernel receive buffer for UDP, bytes (0: the system's default, about 200 KB, which holds
    /// some 50 ms of a 300,000 events/s stream; the kernel caps the request at
    /// net.core.rmem_max).
    #[arg(long, default_value_t = 4 << 20)]
    recv_buffer: usize,
    /// Realtime priority of the receiving thread, 1-99, when the process may (root or
    /// CAP_SYS_NICE; 0: normal scheduling): on busy cores a receiver at normal priority can
    /// wait milliseconds, and a default receive buffer holds about one at a million events/s.
    #[arg(long, default_value_t = 5)]
    priority: u8,
    /// Print the report as one JSON object on stdout.
    #[arg(long)]
    json: bool,
    /// Overwrite an existing output file.
    #[arg(long)]
    force: bool,
}

#[derive(Subcommand)]
enum ModelCommand {
    /// Turn a PyTorch checkpoint of the V2CE generator (the toolbox's v2ce_3d.pt, or a
    /// Lightning .ckpt) into an ONNX model, without PyTorch or a GPU.
    Import(ModelImportArgs),
    /// Run an ONNX model on a raw tensor: IN.npy float32 (B, L, 2, H, W), already normalised,
    /// to OUT.npy float32 (B, L, 20, H, W), the network's output after its final ReLU.
    Run(ModelRunArgs),
    /// Time one window of the network (pairs/s and peak memory), as one JSON line.
    Bench(ModelBenchArgs),
}

#[derive(Args)]
struct ModelBenchArgs {
    /// The ONNX model.
    model: PathBuf,
    /// Frame size.
    #[arg(long, value_name = "WxH", default_value = "346x260")]
    size: String,
    /// Pairs per window.
    #[arg(long, default_value_t = 16)]
    pairs: usize,
    /// Timed runs after one warm-up (the median is reported).
    #[arg(long, default_value_t = 3)]
    runs: usize,
    #[command(flatten)]
    runtime: RuntimeArgs,
}

#[derive(Args)]
struct ModelImportArgs {
    /// The checkpoint (a torch.save zip archive of the state dict).
    checkpoint: PathBuf,
    /// The ONNX model to write (written under a temporary name, renamed when complete).
    #[arg(short, long, value_name = "M.onnx")]
    output: PathBuf,
    /// How spectral-norm weights are resolved: power-iteration (what the reference does at its
    /// first call after loading; the only one that reproduces it), stored, exact.
    #[arg(long, value_enum, default_value_t = v2ce::model::SpectralNorm::PowerIteration)]
    spectral_norm: v2ce::model::SpectralNorm,
    /// Keep BatchNorm as nodes instead of folding it into the convolutions.
    #[arg(long)]
    keep_bn: bool,
    /// Overwrite an existing output file.
    #[arg(long)]
    force: bool,
}

#[derive(Args)]
struct ModelRunArgs {
    /// The ONNX model.
    model: PathBuf,
    /// Input tensor (.npy, float32, 5 dimensions).
    #[arg(long, value_name = "IN.npy")]
    input_npy: PathBuf,
    /// Where to write the output tensor (.npy, float32).
    #[arg(long, value_name = "OUT.npy")]
    output_npy: PathBuf,
    #[command(flatten)]
    runtime: RuntimeArgs,
    /// Overwrite an existing output file.
    #[arg(long)]
    force: bool,
}

/// How `v2ce model run` and `bench` run the network.
#[derive(Args)]
struct RuntimeArgs {
    /// ONNX Runtime threads (0: one per core).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Execution provider: cpu, cuda, auto (CUDA when the library has it and it starts).
    #[arg(long, value_enum, default_value_t = v2ce::stage1::learned::Device::Auto)]
    device: v2ce::stage1::learned::Device,
    /// Keep ONNX Runtime's CPU memory arena (off by default: half the peak memory).
    #[arg(long)]
    cpu_arena: bool,
}

impl RuntimeArgs {
    fn options(&self) -> v2ce::stage1::learned::RuntimeOptions {
        v2ce::stage1::learned::RuntimeOptions {
            threads: self.threads,
            device: self.device,
            library: None,
            cpu_arena: self.cpu_arena,
        }
    }
}

/// Stage 1 tier flags shared by `convert` and `run` (each overrides `[stage1]` and
/// `[stage1.learned]`).
#[derive(Args)]
struct TierArgs {
    /// Stage 1 tier: physics (the pixel model), learned (the V2CE network; the built-in model
    /// unless --model), auto (learned when this machine runs it at --budget-fps, else
    /// physics) [config default: physics].
    #[arg(long, value_enum)]
    stage1: Option<v2ce::stage1::Tier>,
    /// The frame rate `--stage1 auto` must hold (0: none) [config default: 30].
    #[arg(long, value_name = "FPS")]
    budget_fps: Option<f64>,
    /// ONNX model of the learned tier (implies --stage1 learned) [config default: none].
    #[arg(long, value_name = "M.onnx")]
    model: Option<PathBuf>,
    /// Frame intervals per window of the learned tier (the network was trained on 16) [config
    /// default: 16].
    #[arg(long)]
    window: Option<usize>,
    /// New intervals per window (1..=window; less overlaps windows for a shorter wait) [config
    /// default: 0, the window].
    #[arg(long)]
    stride: Option<usize>,
    /// How frames are fitted to the network: native, resize, center, pano [config default:
    /// native].
    #[arg(long, value_enum)]
    geometry: Option<v2ce::stage1::Geometry>,
    /// ONNX Runtime threads (0: one per core) [config default: 0].
    #[arg(long)]
    threads: Option<usize>,
    /// Execution provider: cpu, cuda, auto [config default: auto].
    #[arg(long, value_enum)]
    device: Option<v2ce::stage1::learned::Device>,
    /// Learned tier: output values below this are zero before Stage 2 [config default: unset,
    /// the built-in model's own floor, 0 for other models].
    #[arg(long)]
    floor: Option<f32>,
    /// Learned tier: pixels the network's crops reach beyond the regions that changed (less
    /// than the model's receptive field is faster, no longer exact) [config default: unset, the
    /// model's receptive field].
    #[arg(long, value_name = "PX")]
    roi_margin: Option<usize>,
    /// Learned tier: run the network on whole frames, not only around what changed.
    #[arg(long)]
    no_roi: bool,
}

impl TierArgs {
    fn apply(&self, config: &mut Config) -> Result<()> {
        let learned = &mut config.stage1.learned;
        if let Some(m) = &self.model {
            learned.model = m.clone();
            config.stage1.tier = v2ce::stage1::Tier::Learned;
        }
        if let Some(t) = self.stage1 {
            config.stage1.tier = t;
        }
        if let Some(v) = self.window {
            learned.window = v;
        }
        if let Some(v) = self.stride {
            learned.stride = v;
        }
        if let Some(v) = self.geometry {
            learned.geometry = v;
        }
        if let Some(v) = self.threads {
            learned.threads = v;
        }
        if let Some(v) = self.device {
            learned.device = v;
        }
        if let Some(v) = self.floor {
            learned.floor = Some(v);
        }
        if let Some(v) = self.roi_margin {
            learned.roi_margin = Some(v);
        }
        if self.no_roi {
            learned.roi = false;
        }
        if let Some(v) = self.budget_fps {
            config.stage1.budget_fps = v;
        }
        config.stage1.validate()?;
        config.stage1.learned.validate()
    }
}

#[derive(Args)]
struct RunArgs {
    /// TOML configuration file (the flags below override it); see config/v2ce.toml.
    #[arg(long)]
    config: Option<PathBuf>,
    /// A camera (/dev/video0 or an index), a file or image folder, or `fixture` [config default:
    /// "", the first camera, else the fixture].
    #[arg(long)]
    source: Option<String>,
    /// Send UDP datagrams to HOST:PORT (an empty string turns UDP off) [config default:
    /// 127.0.0.1:3333].
    #[arg(long)]
    udp: Option<String>,
    /// Datagram format: spif, spif_timestamped, t64_x16_y16_on8, t32_x16_y15_on1 [config
    /// default: spif].
    #[arg(long)]
    udp_format: Option<String>,
    /// Largest UDP payload in bytes [config default: 512, which aestream and SpiNNaker's SPIF
    /// listener read whole].
    #[arg(long)]
    udp_payload: Option<usize>,
    /// Most UDP datagrams per second (0: unpaced) [config default: 0].
    #[arg(long)]
    udp_rate: Option<u32>,
    /// When UDP events leave: event-time (each at its own time + the delay) or asap
    /// [config default: event-time].
    #[arg(long, value_enum)]
    emit: Option<v2ce::config::EmitMode>,
    /// How far behind the frames events leave at event time, ms [config default: 100].
    #[arg(long)]
    emit_delay_ms: Option<f64>,
    /// Realtime priority of the thread that sends at event time, 1-99 (0: normal scheduling)
    /// [config default: 10, when the process may].
    #[arg(long)]
    emit_priority: Option<u8>,
    /// Sensor preset of the physics tier: davis346, dvxplorer, ideal [config default: davis346].
    #[arg(long)]
    preset: Option<String>,
    /// A preset file (as `v2ce calibrate` writes) instead of --preset [config default: "",
    /// none].
    #[arg(long, conflicts_with = "preset")]
    preset_file: Option<PathBuf>,
    /// Serve an event stream to TCP clients on HOST:PORT [config default: "", off].
    #[arg(long)]
    tcp: Option<String>,
    /// What TCP clients receive: aedat4 (DV's network stream), evt2 or evt3 (Prophesee RAW,
    /// a .raw file's bytes) [config default: aedat4].
    #[arg(long, value_enum)]
    tcp_format: Option<v2ce::sink::tcp::TcpFormat>,
    /// Hold the source until the first TCP client has connected.
    #[arg(long)]
    wait_for_client: bool,
    /// Also write the events to this file (.aedat4, .raw, .csv, .npz, .h5) [config default: "",
    /// none].
    #[arg(long)]
    out: Option<String>,
    /// Seed of mismatch, noise and sampling [config default: 0].
    #[arg(long)]
    seed: Option<u64>,
    /// A full queue: block (lose nothing) or drop-oldest (stay live) [config default:
    /// drop-oldest].
    #[arg(long)]
    queue_policy: Option<String>,
    /// Stop after this many seconds [config default: 0, no limit].
    #[arg(long)]
    duration: Option<f64>,
    /// Stop after this many frames [config default: 0, no limit].
    #[arg(long)]
    max_frames: Option<u64>,
    /// Resample frames to WIDTHxHEIGHT [config default: "", the source's size].
    #[arg(long, value_name = "WxH")]
    size: Option<String>,
    /// Replay a file at this multiple of real time [config default: 1].
    #[arg(long)]
    replay_speed: Option<f64>,
    /// Replay a file again and again.
    #[arg(long = "loop")]
    loop_source: bool,
    /// Seconds between stats lines [config default: 10].
    #[arg(long)]
    stats_interval: Option<f64>,
    /// Serve /metrics, /healthz, /readyz and the live preview page on IP:PORT (port 0: any;
    /// the address is logged) [config default: off]
    #[arg(long, value_name = "IP:PORT")]
    http: Option<String>,
    /// /readyz turns not ready after this many seconds without a frame [config default: 2]
    #[arg(long)]
    ready_timeout: Option<f64>,
    /// Print the final report as one JSON object on stdout.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    tier: TierArgs,
}

#[derive(Args)]
#[command(args_conflicts_with_subcommands = true)]
struct BenchArgs {
    /// Another measurement instead of the daemon's.
    #[command(subcommand)]
    what: Option<BenchCommand>,
    /// Seconds per configuration.
    #[arg(long, default_value_t = 30.0)]
    seconds: f64,
    /// Sizes to measure.
    #[arg(long, value_delimiter = ',', default_value = "346x260,640x480")]
    sizes: Vec<String>,
    /// Print the results as JSON lines.
    #[arg(long)]
    json: bool,
    /// Replay the fixture at this multiple of real time (below 1 for a tier slower than real
    /// time).
    #[arg(long, default_value_t = 1.0)]
    replay_speed: f64,
    /// Run the HTTP listener on IP:PORT during the bench (to measure what it, a scraper and an
    /// open preview page cost)
    #[arg(long, value_name = "IP:PORT")]
    http: Option<String>,
    /// TOML configuration for Stage 1 and Stage 2 (the flags below override it).
    #[arg(long)]
    config: Option<PathBuf>,
    #[command(flatten)]
    tier: TierArgs,
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Every Stage 1 tier and setting on the same frames: speed (pairs/s, window latency) and
    /// accuracy (TF1, TPF1, count ratio, C-METE) against a real recording's held-out half and
    /// synthetic sequences, with the Pareto front (README: "The speed/accuracy trade").
    Tradeoff(TradeoffArgs),
}

#[derive(Args)]
struct TradeoffArgs {
    /// A recording with frames and events (.aedat4 with APS frames, or events with --frames).
    #[arg(long)]
    real: Option<PathBuf>,
    /// The recording's frames, when it has none in it.
    #[arg(long)]
    frames: Option<PathBuf>,
    /// Which of the recording's frame intervals are scored (models trained by `v2ce dataset
    /// recording --split first` are scored on the second).
    #[arg(long, value_enum, default_value_t = v2ce::dataset::Split::Second)]
    split: v2ce::dataset::Split,
    /// Synthetic sequences to score on (made again from --synthetic-seed, as `v2ce dataset
    /// synthetic` makes them; 0: none).
    #[arg(long, default_value_t = 8)]
    synthetic: usize,
    /// Their seed (2: the validation set of the shipped models' cards).
    #[arg(long, default_value_t = 2)]
    synthetic_seed: u64,
    /// Natural-image textures for them (as given to `v2ce dataset synthetic`).
    #[arg(long)]
    images: Option<PathBuf>,
    /// Their frame size.
    #[arg(long, value_name = "WxH", default_value = "160x120")]
    size: String,
    /// More learned models to measure (ONNX), beside the built-in one.
    #[arg(long)]
    model: Vec<PathBuf>,
    /// Print the rows as JSON lines instead of tables.
    #[arg(long)]
    json: bool,
    /// Also score on this many still-camera synthetic sequences (steady light, clean frames,
    /// only objects move; seed --synthetic-seed), where the learned tier's crops save compute.
    #[arg(long, default_value_t = 0)]
    still: usize,
    /// Their frame size.
    #[arg(long, value_name = "WxH", default_value = "320x240")]
    still_size: String,
    /// Also draw TF1 against speed with the Pareto front, as a PNG here.
    #[arg(long, value_name = "OUT.png")]
    plot: Option<PathBuf>,
}

#[derive(Args)]
struct TranscodeArgs {
    /// Input: .aedat4, .raw (EVT 2.0 or 3.0, from its header), .csv, .npz, .h5/.hdf5 (DSEC
    /// layout), or IJRR events.txt.
    input: PathBuf,
    /// Output; its extension picks the format: .aedat4, .raw, .csv, .npz, .h5/.hdf5.
    output: PathBuf,
    #[command(flatten)]
    encoding: EncodingArgs,
    /// Sensor size WIDTHxHEIGHT to write (default: the input's, or the events' extent).
    #[arg(long, value_name = "WxH")]
    size: Option<String>,
    /// Overwrite an existing output file.
    #[arg(long)]
    force: bool,
}

#[derive(Args)]
struct BatchArgs {
    /// The inputs: a list (`PATH [key=value ...]` per line, keys fps, size, preset, tier, seed,
    /// output; relative paths from the list's folder), JSON lines (`{"input": PATH, ...}`), or
    /// a glob in quotes ('clips/*.mp4')
    manifest: Option<String>,
    /// The output folder (outputs keep the inputs' relative paths; ledgers go in .v2ce-batch/)
    #[arg(long, short)]
    out: Option<PathBuf>,
    /// This task's share, I/N from 0 (default: SLURM_ARRAY_TASK_ID and SLURM_ARRAY_TASK_COUNT,
    /// or JOB_COMPLETION_INDEX with --shards; else the whole manifest)
    #[arg(long)]
    shard: Option<String>,
    /// The shard count of a Kubernetes Indexed Job (its completions; or V2CE_SHARDS)
    #[arg(long)]
    shards: Option<u32>,
    /// Threads of this task (default: SLURM_CPUS_PER_TASK, else the machine's)
    #[arg(long)]
    threads: Option<usize>,
    /// Inputs converted at once (default: the threads; each physics conversion uses about one)
    #[arg(long)]
    jobs: Option<usize>,
    /// The output format, by extension: aedat4, raw, csv, npz or h5
    #[arg(long, default_value = "aedat4")]
    format: String,
    #[command(flatten)]
    encoding: EncodingArgs,
    /// A config file for every input (per-item settings override it)
    #[arg(long)]
    config: Option<PathBuf>,
    /// Merge the ledgers of every shard in DIR into one summary instead of converting (with a
    /// manifest, inputs not yet converted are listed as pending); exit status 1 if any failed
    #[arg(long, value_name = "DIR")]
    report: Option<PathBuf>,
    /// Print the summary as one JSON object on stdout
    #[arg(long)]
    json: bool,
}

/// How an output file is encoded, beyond what its extension says.
#[derive(Args)]
struct EncodingArgs {
    /// EVT version of a .raw output (2 by default: some readers mis-time EVT 3.0).
    #[arg(long, value_parser = ["2", "3"], default_value = "2")]
    evt: String,
    /// Packet compression of an .aedat4 output: lz4, zstd, zstd-high or none.
    #[arg(long, default_value = "lz4")]
    compression: String,
}

impl EncodingArgs {
    /// The output format for `path`.
    fn format_for(&self, path: &Path) -> Result<format::Format> {
        let compression = format::Compression::from_name(&self.compression)?;
        format::Format::for_output(path, self.evt.parse::<u8>().ok(), compression)
    }
}

#[derive(Args)]
struct InfoArgs {
    /// An event file: .aedat4, .raw, .csv, .npz, .h5/.hdf5 or IJRR events.txt.
    file: PathBuf,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

#[derive(Subcommand)]
enum Eval {
    /// Stage 2: voxelize real events per frame interval, re-sample them, and score the
    /// timestamps (METE, NOE, PGER, C-METE, C-NOE). Without --events, runs on a built-in
    /// synthetic recording.
    Stage2(Stage2Args),
    /// Stage 1: voxelize a simulated and a real event stream on the real recording's frame
    /// intervals and score them (TPF1, TF1, RF1, accuracies, PMSE-2/4), plus the Stage 2
    /// timestamp metrics between the two.
    Stage1(Stage1Args),
}

#[derive(Args)]
struct ConvertArgs {
    /// Frames: a video file (through ffmpeg), a folder of PNG/JPEG images, a .y4m, or an
    /// .aedat4 with APS frames.
    input: PathBuf,
    /// Output events; the extension picks the format: .aedat4, .raw, .csv, .npz, .h5/.hdf5.
    #[arg(short, long)]
    output: PathBuf,
    /// TOML configuration file (flags override it).
    #[arg(long)]
    config: Option<PathBuf>,
    #[command(flatten)]
    tier: TierArgs,
    /// Also write the voxels Stage 1 hands to Stage 2, as float32 (intervals, 2*C, H, W)
    /// (channel = polarity*C + node, ON first); needs a tier that makes voxels.
    #[arg(long, value_name = "V.npy")]
    write_voxels: Option<PathBuf>,
    /// Sensor preset: davis346, dvxplorer, ideal [config default: davis346].
    #[arg(long)]
    preset: Option<String>,
    /// A preset file (as `v2ce calibrate` writes) instead of --preset [config default: "",
    /// none].
    #[arg(long, conflicts_with = "preset")]
    preset_file: Option<PathBuf>,
    /// Stage 1 output: events (direct) or voxels (re-timed by the Stage 2 sampler) [config
    /// default: events].
    #[arg(long, value_parser = ["events", "voxels"])]
    mode: Option<String>,
    /// Stage 2 sampler for --mode voxels: moment, ldati, ldati-random, even, random [config
    /// default: moment].
    #[arg(long)]
    sampler: Option<SamplerKind>,
    /// Seed of mismatch, noise and sampling [config default: 0].
    #[arg(long)]
    seed: Option<u64>,
    /// Frame rate of an image folder without images.txt/times.txt (none: the folder must have
    /// one).
    #[arg(long)]
    fps: Option<f64>,
    /// How image values relate to the light: auto (linear for a recognised DAVIS APS export,
    /// else sRGB, warning for gray images), srgb (camera video, photos) or linear (raw sensor
    /// exports).
    #[arg(long, value_enum, default_value_t = v2ce::frame::images::ColorSpace::Auto)]
    color: v2ce::frame::images::ColorSpace,
    /// The same as --color linear.
    #[arg(long, conflicts_with = "color")]
    linear: bool,
    #[command(flatten)]
    encoding: EncodingArgs,
    /// Resample frames to WIDTHxHEIGHT (none: the source's size).
    #[arg(long, value_name = "WxH")]
    size: Option<String>,
    /// Stop after this many frames (0 or none: all, as for `run`).
    #[arg(long)]
    max_frames: Option<u64>,
    /// Overwrite an existing output file.
    #[arg(long)]
    force: bool,
}

#[derive(Args)]
struct Stage1Args {
    /// The real events (and, for an .aedat4 with APS frames, the frame intervals).
    #[arg(long)]
    real: PathBuf,
    /// The simulated events; without it, the physics tier simulates them here from the
    /// recording's APS frames (or the --frames images) with --preset / --preset-file.
    #[arg(long)]
    sim: Option<PathBuf>,
    /// Frame times (an .aedat4 with APS frames or an IJRR images.txt) when --real has none.
    #[arg(long, conflicts_with = "fps")]
    frames: Option<PathBuf>,
    /// Fixed frame rate for the intervals instead.
    #[arg(long)]
    fps: Option<f64>,
    /// Without --sim: the sensor preset to simulate with (davis346, dvxplorer, ideal).
    #[arg(long, default_value = "davis346", conflicts_with = "sim")]
    preset: String,
    /// Without --sim: a preset file (as `v2ce calibrate` writes) instead of --preset.
    #[arg(long, conflicts_with = "sim")]
    preset_file: Option<PathBuf>,
    /// Without --sim: the seed of mismatch and noise.
    #[arg(long, default_value_t = 0, conflicts_with = "sim")]
    seed: u64,
    /// Score only these frame intervals: first (half, by time), second, all (as `v2ce dataset
    /// recording --split`, so a model is scored on the half it did not train on).
    #[arg(long, value_enum, default_value_t = v2ce::dataset::Split::All)]
    split: v2ce::dataset::Split,
    /// Print the scores as one JSON object.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct Stage2Args {
    /// Real events: .aedat4, IJRR events.txt, or .csv (t_us,x,y,on).
    #[arg(long)]
    events: Option<PathBuf>,
    /// Frame times: an .aedat4 with APS frames or an IJRR images.txt.
    #[arg(long, conflicts_with = "fps")]
    frames: Option<PathBuf>,
    /// Fixed frame rate for the intervals, starting at the first event.
    #[arg(long)]
    fps: Option<f64>,
    /// Sampler: moment (default), ldati, ldati-random, even, random.
    #[arg(long)]
    sampler: Option<SamplerKind>,
    /// Seed of the sampler's random draws.
    #[arg(long)]
    seed: Option<u64>,
    /// Temporal nodes per interval (C).
    #[arg(long)]
    bins: Option<usize>,
    /// TOML configuration file (flags override it).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Write the sampled events as CSV (t_us,x,y,on).
    #[arg(long, value_name = "OUT.csv")]
    write_events: Option<PathBuf>,
    /// Print the scores as one JSON object.
    #[arg(long)]
    json: bool,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Every command logs its warnings (a guessed colour space, frames without exposure).
    init_logging();
    let result = match cli.command {
        Command::Eval(Eval::Stage2(args)) => eval_stage2(args),
        Command::Eval(Eval::Stage1(args)) => eval_stage1(args),
        Command::Convert(args) => convert(args),
        Command::Transcode(args) => transcode(args),
        Command::Info(args) => info(args),
        Command::Run(args) => run(args),
        Command::Devices => devices(),
        Command::Bench(BenchArgs {
            what: Some(BenchCommand::Tradeoff(args)),
            ..
        }) => tradeoff(args),
        Command::Bench(args) => bench(args),
        Command::Listen(args) => listen(args),
        Command::Render(args) => render(args),
        Command::Model(ModelCommand::Import(args)) => model_import(args),
        Command::Model(ModelCommand::Run(args)) => model_run(args),
        Command::Model(ModelCommand::Bench(args)) => model_bench(args),
        Command::Calibrate(args) => calibrate(args),
        Command::Dataset(DatasetCommand::Synthetic(args)) => dataset_synthetic(args),
        Command::Dataset(DatasetCommand::Recording(args)) => dataset_recording(args),
        Command::Batch(args) => batch(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(Error::Interrupted(why)) => {
            eprintln!("v2ce: interrupted: {why}");
            ExitCode::from(130)
        }
        Err(e) => {
            eprintln!("v2ce: error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Logs to stderr; under systemd (JOURNAL_STREAM set) without timestamps or colours, which the
/// journal adds or does not want. `V2CE_LOG` sets the level (error, warn, info, debug, trace).
fn init_logging() {
    use std::io::IsTerminal;
    let level = std::env::var("V2CE_LOG")
        .ok()
        .and_then(|l| l.parse::<tracing::Level>().ok())
        .unwrap_or(tracing::Level::INFO);
    let builder = tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_max_level(level)
        .with_target(false);
    if std::env::var_os("JOURNAL_STREAM").is_some() {
        builder.without_time().with_ansi(false).init();
    } else {
        builder.with_ansi(std::io::stderr().is_terminal()).init();
    }
}

fn run_config(args: &RunArgs) -> Result<Config> {
    let mut config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    let run = &mut config.run;
    if let Some(v) = &args.source {
        run.source = v.clone();
    }
    if let Some(v) = &args.udp {
        run.udp = v.clone();
    }
    if let Some(v) = &args.udp_format {
        run.udp_format = v2ce::format::datagram::UdpFormat::from_name(v)?;
    }
    if let Some(v) = args.udp_payload {
        run.udp_payload = v;
    }
    if let Some(v) = args.udp_rate {
        run.udp_rate = v;
    }
    if let Some(v) = args.emit {
        run.emit = v;
    }
    if let Some(v) = args.emit_delay_ms {
        run.emit_delay_ms = v;
    }
    if let Some(v) = args.emit_priority {
        run.emit_priority = v;
    }
    if let Some(v) = &args.tcp {
        run.tcp = v.clone();
    }
    if let Some(v) = args.tcp_format {
        run.tcp_format = v;
    }
    if let Some(v) = &args.out {
        run.out = v.clone();
    }
    if args.wait_for_client {
        run.wait_for_client = true;
    }
    if let Some(v) = &args.queue_policy {
        run.queue_policy = v2ce::pipeline::queue::QueuePolicy::from_name(v)?;
    }
    if let Some(v) = args.duration {
        run.duration = v;
    }
    if let Some(v) = args.max_frames {
        run.max_frames = v;
    }
    if let Some(v) = &args.size {
        run.size = v.clone();
    }
    if let Some(v) = args.replay_speed {
        run.replay_speed = v;
    }
    if args.loop_source {
        run.loop_source = true;
    }
    if let Some(v) = args.stats_interval {
        run.stats_interval = v;
    }
    if let Some(v) = &args.http {
        run.http = v.clone();
    }
    if let Some(v) = args.ready_timeout {
        run.ready_timeout = v;
    }
    if let Some(s) = args.seed {
        config.stage1.seed = s;
        config.stage2.seed = s;
    }
    if let Some(p) = &args.preset {
        config.stage1.preset = v2ce::stage1::Preset::from_name(p)?;
        config.stage1.custom = None;
    }
    if let Some(f) = &args.preset_file {
        config.stage1.load_preset_file(f)?;
    }
    args.tier.apply(&mut config)?;
    config.validate()?;
    Ok(config)
}

fn run(args: RunArgs) -> Result<()> {
    let config = run_config(&args)?;
    let stop = v2ce::daemon::stop_on_signals()?;
    let report = v2ce::daemon::run(&config, &stop)?;
    if args.json {
        let text =
            serde_json::to_string(&report).map_err(|e| Error::invalid("report", e.to_string()))?;
        println!("{text}");
    }
    if report.end.is_clean() {
        Ok(())
    } else {
        Err(Error::Run(report.end.describe()))
    }
}

fn devices() -> Result<()> {
    let cameras = v2ce::capture::list_cameras()?;
    if cameras.is_empty() {
        println!("no cameras found");
    }
    for camera in cameras {
        println!("{camera}");
    }
    Ok(())
}

fn bench(args: BenchArgs) -> Result<()> {
    let stop = v2ce::daemon::stop_on_signals()?;
    let mut config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    args.tier.apply(&mut config)?;
    if let Some(h) = &args.http {
        config.run.http = h.clone();
        config.run.validate()?;
    }
    for size in &args.sizes {
        let result = v2ce::daemon::bench(
            parse_size(size)?,
            args.seconds,
            args.replay_speed,
            &config,
            &stop,
        )?;
        if args.json {
            let text = serde_json::to_string(&result)
                .map_err(|e| Error::invalid("report", e.to_string()))?;
            println!("{text}");
        } else {
            println!("{}", result.line());
        }
        if result.end == v2ce::pipeline::End::Stopped {
            break;
        }
    }
    Ok(())
}

fn convert(args: ConvertArgs) -> Result<()> {
    use std::io::IsTerminal;
    use v2ce::stage1::{Preset, Stage1Output};
    let mut config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    if let Some(p) = &args.preset {
        config.stage1.preset = Preset::from_name(p)?;
        config.stage1.custom = None;
    }
    if let Some(f) = &args.preset_file {
        config.stage1.load_preset_file(f)?;
    }
    match args.mode.as_deref() {
        Some("voxels") => config.stage1.output = Stage1Output::Voxels,
        Some(_) => config.stage1.output = Stage1Output::Events,
        None => {}
    }
    if let Some(s) = args.sampler {
        config.stage2.sampler = s;
    }
    if let Some(s) = args.seed {
        config.stage1.seed = s;
        config.stage2.seed = s;
    }
    args.tier.apply(&mut config)?;
    check_output(&args.output, args.force)?;
    if let Some(v) = &args.write_voxels {
        check_output(v, args.force)?;
    }
    let job = v2ce::convert::FileJob {
        input: args.input.clone(),
        output: args.output.clone(),
        format: args.encoding.format_for(&args.output)?,
        source: v2ce::frame::SourceOptions {
            fps: args.fps,
            color: if args.linear {
                v2ce::frame::images::ColorSpace::Linear
            } else {
                args.color
            },
        },
        size: args.size.as_deref().map(parse_size).transpose()?,
        // 0 means no limit, as in `run` and `[run] max_frames`.
        max_frames: args.max_frames.filter(|&m| m > 0),
        write_voxels: args.write_voxels.clone(),
    };
    /// Prints the start line, and progress on a terminal.
    struct Terminal {
        tty: bool,
        total: Option<u64>,
    }
    impl v2ce::convert::FileJobObserver for Terminal {
        fn started(&mut self, line: &str, frames: Option<u64>) {
            eprintln!("v2ce: {line}");
            self.total = frames;
        }
        fn progress(&mut self, r: &v2ce::convert::ConvertReport) {
            if self.tty {
                eprint!(
                    "\r  {}",
                    progress_line(r.frames, self.total, r.events, r.seconds)
                );
            }
        }
    }
    let tty = std::io::stderr().is_terminal();
    let stop = v2ce::daemon::stop_on_signals()?;
    let mut terminal = Terminal { tty, total: None };
    let result = v2ce::convert::convert_file(&job, &config, &stop, &mut terminal);
    if tty {
        eprintln!();
    }
    let report = result?;
    let s1 = &report.stage1;
    let detail = match s1.tier {
        "learned" => format!(
            "{} windows of L={} (stride {}, {} skipped as still), median {:.0} ms per window on \
             {}, the network ran on {:.0}% of the pixels",
            s1.learned.windows,
            s1.window,
            s1.stride,
            s1.learned.windows_skipped,
            s1.learned.window_ms_p50,
            s1.learned.provider,
            100.0 * s1.learned.compute()
        ),
        _ => format!(
            "{} of {} tiles skipped as static",
            s1.physics.tiles_skipped,
            s1.physics.tiles_skipped + s1.physics.tiles_active
        ),
    };
    eprintln!(
        "v2ce: {} frames, {} events in {:.2} s ({:.1} frames/s); {detail}",
        report.frames,
        report.events,
        report.seconds,
        report.frames as f64 / report.seconds.max(1e-9),
    );
    if s1.learned.nonfinite > 0 || report.repaired.any() {
        eprintln!(
            "v2ce: warning: the model gave {} NaN/infinite values; Stage 2 repaired {} \
             non-finite, {} negative, {} clamped node values",
            s1.learned.nonfinite,
            report.repaired.nonfinite,
            report.repaired.negative,
            report.repaired.clamped
        );
    }
    Ok(())
}

/// Refuses to replace an existing file unless `force` (the `--force` flag).
fn check_output(path: &Path, force: bool) -> Result<()> {
    if path.exists() && !force {
        return Err(Error::invalid(
            "output",
            format!("{} exists; add --force to overwrite it", path.display()),
        ));
    }
    Ok(())
}

fn render(args: RenderArgs) -> Result<()> {
    check_output(&args.output, args.force)?;
    let options = v2ce::render::RenderOptions {
        fps: args.fps,
        decay_us: args.decay_ms.map(|ms| ms * 1e3),
        slowdown: args.slowdown,
        size: args.size.as_deref().map(parse_size).transpose()?,
    };
    let r = v2ce::render::render(&args.input, &args.output, &options)?;
    eprintln!(
        "v2ce: {} events in {} frame{} of {} x {} to {}",
        r.events,
        r.frames,
        if r.frames == 1 { "" } else { "s" },
        r.size.0,
        r.size.1,
        args.output.display()
    );
    Ok(())
}

fn listen(args: ListenArgs) -> Result<()> {
    if let Some(out) = &args.out {
        check_output(out, args.force)?;
    }
    use v2ce::listen::{Listen, ListenOptions};
    let seconds = |what: &'static str, v: f64| v2ce::limits::seconds(what, v, true);
    let listen = match (&args.udp, &args.tcp) {
        (_, Some(connect)) => Listen::Tcp {
            connect: connect.clone(),
        },
        (Some(bind), None) => Listen::Udp {
            bind: bind.clone(),
            format: v2ce::format::datagram::UdpFormat::from_name(&args.format)?,
        },
        (None, None) => Listen::Udp {
            bind: "127.0.0.1:3333".into(),
            format: v2ce::format::datagram::UdpFormat::from_name(&args.format)?,
        },
    };
    let options = ListenOptions {
        listen,
        out: args.out.clone(),
        size: parse_size(&args.size)?,
        duration: args
            .duration
            .map(|d| seconds("--duration", d))
            .transpose()?,
        idle: seconds("--idle", args.idle)?,
        max_events: args.max_events,
        recv_buffer: args.recv_buffer,
        priority: args.priority,
    };
    let stop = v2ce::daemon::stop_on_signals()?;
    let report = v2ce::listen::listen(&options, &stop, |at| {
        println!("listening on {at}");
        let _ = std::io::stdout().flush();
    })?;
    if args.json {
        let text =
            serde_json::to_string(&report).map_err(|e| Error::invalid("report", e.to_string()))?;
        println!("{text}");
    } else {
        println!(
            "{} events in {} messages ({} ragged) over {:.2} s: {:.0} events/s; largest gap \
             {:.1} ms; at most {} messages in one ms{}",
            report.events,
            report.messages,
            report.ragged,
            report.seconds,
            report.events_per_s,
            report.largest_gap_ms,
            report.max_messages_per_ms,
            report
                .arrival_spread
                .map(|l| format!(
                    "; arrival minus event time (less its minimum) p50 {:.2} ms p99 {:.2} ms \
                     max {:.2} ms",
                    l.p50_ms, l.p99_ms, l.max_ms
                ))
                .unwrap_or_default()
        );
    }
    let udp = args.udp.is_some() || args.tcp.is_none();
    if udp && !report.realtime && args.priority > 0 {
        eprintln!(
            "v2ce listen: the receiver ran at normal priority (realtime {} refused: needs root or \
             CAP_SYS_NICE); on busy cores it may lose datagrams",
            args.priority
        );
    }
    Ok(())
}

fn calibrate(args: CalibrateArgs) -> Result<()> {
    check_output(&args.output, args.force)?;
    let base = v2ce::stage1::Preset::from_name(&args.preset)?;
    let (real, frames) = load_recording(
        &args.real,
        args.frames.as_deref(),
        args.color,
        args.max_frames.max(5),
    )?;
    let rec = v2ce::calibrate::Recording {
        frames: &frames,
        events: real.events.events(),
        size: (real.width, real.height),
    };
    let fit = v2ce::calibrate::calibrate(&rec, &base.config(), args.seed)?;
    let text = v2ce::calibrate::preset_file(&fit, base.name(), &args.real.display().to_string())?;
    let tmp = args.output.with_extension("toml.partial");
    std::fs::write(&tmp, text).map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, &args.output).map_err(|e| Error::io(&args.output, e))?;
    if args.json {
        let text =
            serde_json::to_string(&fit).map_err(|e| Error::invalid("report", e.to_string()))?;
        println!("{text}");
    } else {
        print!(
            "{}",
            v2ce::calibrate::report(&fit, &base.config(), base.name())
        );
        eprintln!("v2ce: wrote {}", args.output.display());
    }
    Ok(())
}

/// A recording's events and up to `max_frames` of its frames (from `frames`, or the
/// recording itself), checked to be of one size.
fn load_recording(
    real: &Path,
    frames: Option<&Path>,
    color: v2ce::frame::images::ColorSpace,
    max_frames: usize,
) -> Result<(format::Recording, Vec<v2ce::frame::Frame>)> {
    use v2ce::frame::FrameSource;
    let events = format::read_events(real)?;
    let options = v2ce::frame::SourceOptions { fps: None, color };
    let frames_path = frames.unwrap_or(real);
    let mut source: Box<dyn FrameSource> = v2ce::frame::open(frames_path, &options)?;
    if source.size() != (events.width, events.height) {
        return Err(Error::invalid(
            "recording",
            format!(
                "frames of {} x {} for events of a {} x {} sensor",
                source.size().0,
                source.size().1,
                events.width,
                events.height
            ),
        ));
    }
    let mut out = Vec::new();
    while out.len() < max_frames {
        match source.next_frame()? {
            Some(f) => out.push(f),
            None => break,
        }
    }
    Ok((events, out))
}

fn dataset_synthetic(args: SyntheticArgs) -> Result<()> {
    let (w, h) = parse_size(&args.size)?;
    let fps = match args.fps.split_once("..") {
        Some((lo, hi)) => (
            lo.trim()
                .parse::<f64>()
                .map_err(|_| Error::invalid("--fps", args.fps.clone()))?,
            hi.trim()
                .parse::<f64>()
                .map_err(|_| Error::invalid("--fps", args.fps.clone()))?,
        ),
        None => {
            let f = args
                .fps
                .trim()
                .parse::<f64>()
                .map_err(|_| Error::invalid("--fps", args.fps.clone()))?;
            (f, f)
        }
    };
    let sensor = match &args.preset_file {
        Some(f) => {
            let mut s1 = v2ce::stage1::Stage1Config::default();
            s1.load_preset_file(f)?;
            s1.physics_config()
        }
        None => v2ce::stage1::Preset::from_name(&args.preset)?.config(),
    };
    let images = match &args.images {
        Some(dir) => v2ce::dataset::load_images(dir)?,
        None => Vec::new(),
    };
    let cfg = v2ce::dataset::SyntheticConfig {
        size: (w, h),
        pairs: args.pairs,
        fps,
        rate_hz: args.rate,
        sensor,
        noise: args.noise,
        input_noise: args.input_noise,
        pace: Default::default(),
    };
    let threads = if args.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        args.threads
    };
    let started = std::time::Instant::now();
    let m =
        v2ce::dataset::write_synthetic(&args.out, &cfg, args.seed, args.count, &images, threads)?;
    let events: u64 = m.sequences.iter().map(|s| s.events).sum();
    eprintln!(
        "v2ce: {} sequences of {} intervals at {} x {} ({} natural images), {} events, in {:.1} s: {}",
        m.sequences.len(),
        m.pairs,
        w,
        h,
        images.len(),
        events,
        started.elapsed().as_secs_f64(),
        args.out.display()
    );
    Ok(())
}

fn dataset_recording(args: DatasetRecordingArgs) -> Result<()> {
    let (real, frames) = load_recording(
        &args.real,
        args.frames.as_deref(),
        args.color,
        args.max_frames,
    )?;
    let m = v2ce::dataset::write_recording(
        &args.out,
        &frames,
        real.events.events(),
        args.pairs,
        args.split,
        &args.real.display().to_string(),
    )?;
    let events: u64 = m.sequences.iter().map(|s| s.events).sum();
    eprintln!(
        "v2ce: {} sequences of {} intervals at {} x {}, {} real events: {}",
        m.sequences.len(),
        m.pairs,
        m.size.0,
        m.size.1,
        events,
        args.out.display()
    );
    Ok(())
}

fn tradeoff(args: TradeoffArgs) -> Result<()> {
    use v2ce::stage1::{Preset, Stage1Config, Tier};
    use v2ce::stage2::SamplerKind;
    use v2ce::tradeoff::{Scene, Setting};
    let mut scenes: Vec<Vec<Scene>> = Vec::new();
    if let Some(real) = &args.real {
        let (rec, frames) = load_recording(
            real,
            args.frames.as_deref(),
            v2ce::frame::images::ColorSpace::Auto,
            100_000,
        )?;
        let intervals: Vec<v2ce::interval::Interval> = frames
            .windows(2)
            .map(|w| v2ce::interval::Interval::new(w[0].t, w[1].t))
            .collect::<Result<_>>()?;
        let scored = intervals[args.split.range(intervals.len())].to_vec();
        let name = format!(
            "{} ({:?} half)",
            real.file_name().unwrap_or_default().to_string_lossy(),
            args.split
        )
        .to_lowercase();
        scenes.push(vec![Scene {
            name,
            frames,
            encoding: v2ce::frame::SourceEncoding::Linear,
            events: rec.events.events().to_vec(),
            scored,
        }]);
    }
    let images = match &args.images {
        Some(dir) if args.synthetic > 0 || args.still > 0 => v2ce::dataset::load_images(dir)?,
        _ => Vec::new(),
    };
    let synthetic = |count: usize, cfg: &v2ce::dataset::SyntheticConfig, name: String| {
        (0..count)
            .map(|k| {
                let s = v2ce::dataset::render_synthetic(cfg, args.synthetic_seed, k, &images)?;
                let scored = s
                    .frames
                    .windows(2)
                    .map(|w| v2ce::interval::Interval::new(w[0].t, w[1].t))
                    .collect::<Result<_>>()?;
                Ok(Scene {
                    name: name.clone(),
                    frames: s.frames,
                    encoding: v2ce::frame::SourceEncoding::Linear,
                    events: s.events,
                    scored,
                })
            })
            .collect::<Result<Vec<Scene>>>()
    };
    if args.synthetic > 0 {
        let cfg = v2ce::dataset::SyntheticConfig {
            size: parse_size(&args.size)?,
            ..Default::default()
        };
        let name = format!("synthetic seed {}", args.synthetic_seed);
        scenes.push(synthetic(args.synthetic, &cfg, name)?);
    }
    if args.still > 0 {
        let cfg = v2ce::dataset::SyntheticConfig {
            size: parse_size(&args.still_size)?,
            input_noise: 0.0,
            pace: v2ce::dataset::Pace {
                still: true,
                ..Default::default()
            },
            ..Default::default()
        };
        let name = format!("still camera, seed {}", args.synthetic_seed);
        scenes.push(synthetic(args.still, &cfg, name)?);
    }
    if scenes.is_empty() {
        return Err(Error::invalid(
            "bench tradeoff",
            "nothing to score on: give --real, --synthetic N and/or --still N",
        ));
    }
    let physics = |preset: Preset| Setting {
        label: format!("physics {}", preset.name()),
        stage1: Stage1Config {
            preset,
            ..Default::default()
        },
        sampler: SamplerKind::Moment,
    };
    let learned = |label: &str, model: &Path, window: usize, threads: usize, sampler| {
        let mut stage1 = Stage1Config {
            tier: Tier::Learned,
            ..Default::default()
        };
        stage1.learned.model = model.to_path_buf();
        stage1.learned.window = window;
        stage1.learned.threads = threads;
        Setting {
            label: format!(
                "{label} L={window} {threads} thread{} {}",
                if threads == 1 { "" } else { "s" },
                sampler_name(sampler)
            ),
            stage1,
            sampler,
        }
    };
    let builtin = Path::new("");
    let mut settings = vec![
        physics(Preset::Davis346),
        physics(Preset::Dvxplorer),
        physics(Preset::Ideal),
        learned("v2ce-small", builtin, 16, 2, SamplerKind::Moment),
        learned("v2ce-small", builtin, 8, 2, SamplerKind::Moment),
        learned("v2ce-small", builtin, 4, 2, SamplerKind::Moment),
        learned("v2ce-small", builtin, 16, 1, SamplerKind::Moment),
        learned("v2ce-small", builtin, 16, 2, SamplerKind::Ldati),
    ];
    for floor in [0.0f32, 0.05, 0.2] {
        let mut s = learned("v2ce-small", builtin, 16, 2, SamplerKind::Moment);
        s.stage1.learned.floor = Some(floor);
        s.label = format!("{} floor {floor}", s.label);
        settings.push(s);
    }
    // The network on whole frames, and on crops with margins inside its receptive field.
    let mut whole = learned("v2ce-small", builtin, 16, 2, SamplerKind::Moment);
    whole.stage1.learned.roi = false;
    whole.label = format!("{} whole frames", whole.label);
    settings.push(whole);
    for margin in [64usize, 32] {
        let mut s = learned("v2ce-small", builtin, 16, 2, SamplerKind::Moment);
        s.stage1.learned.roi_margin = Some(margin);
        s.label = format!("{} roi margin {margin}", s.label);
        settings.push(s);
    }
    for m in &args.model {
        let name = m
            .file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .to_string();
        settings.push(learned(&name, m, 16, 2, SamplerKind::Moment));
    }
    let mut rows = Vec::new();
    for group in &scenes {
        let name = group.first().map(|s| s.name.clone()).unwrap_or_default();
        for setting in &settings {
            let each = group
                .iter()
                .map(|scene| v2ce::tradeoff::measure(setting, scene))
                .collect::<Result<Vec<_>>>()?;
            if let Some(row) = v2ce::tradeoff::combine(&each, &name) {
                if args.json {
                    let text = serde_json::to_string(&row)
                        .map_err(|e| Error::invalid("report", e.to_string()))?;
                    println!("{text}");
                } else {
                    eprintln!(
                        "v2ce: {} on {}: {:.1} pairs/s, TF1 {:.3}, ratio {:.2}",
                        row.setting, row.scene, row.pairs_per_s, row.tf1, row.count_ratio
                    );
                }
                rows.push(row);
            }
        }
    }
    if let Some(path) = &args.plot {
        v2ce::tradeoff::plot(&rows, path)?;
        eprintln!("v2ce: plot written to {}", path.display());
    }
    if !args.json {
        println!("{}", v2ce::tradeoff::table(&rows));
        for group in &scenes {
            let name = group.first().map(|s| s.name.clone()).unwrap_or_default();
            let front: Vec<&str> = v2ce::tradeoff::pareto(&rows, &name)
                .iter()
                .map(|r| r.setting.as_str())
                .collect();
            println!(
                "Pareto front (pairs/s, TF1) on {name}: {}",
                front.join("; ")
            );
        }
    }
    Ok(())
}

fn sampler_name(s: v2ce::stage2::SamplerKind) -> String {
    serde_json::to_value(s)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_default()
}

fn model_import(args: ModelImportArgs) -> Result<()> {
    check_output(&args.output, args.force)?;
    let options = v2ce::model::ImportOptions {
        spectral_norm: args.spectral_norm,
        fold_batch_norm: !args.keep_bn,
    };
    let r = v2ce::model::import(&args.checkpoint, &args.output, &options)?;
    let sigmas: Vec<f64> = r.spectral_norms.iter().map(|(_, s)| *s).collect();
    let (lo, hi) = sigmas
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &s| {
            (a.min(s), b.max(s))
        });
    eprintln!(
        "v2ce: {} -> {} ({:.1} MB): {} tensors read{}{}, {} parameters, {} spectral norms \
         resolved by {} (sigma {:.4}..{:.4}), BatchNorm {}, {} initializers",
        r.checkpoint.display(),
        r.output.display(),
        r.output_bytes as f64 / 1e6,
        r.keys_read,
        if r.prefix_stripped {
            ", Lightning prefix `model.` stripped"
        } else {
            ""
        },
        if r.dropped_gan_keys > 0 {
            format!(", {} discriminator tensors dropped", r.dropped_gan_keys)
        } else {
            String::new()
        },
        r.parameters,
        sigmas.len(),
        args.spectral_norm.name(),
        lo,
        hi,
        if args.keep_bn { "kept" } else { "folded" },
        r.initializers
    );
    Ok(())
}

fn model_bench(args: ModelBenchArgs) -> Result<()> {
    let (w, h) = parse_size(&args.size)?;
    let options = args.runtime.options();
    let report = v2ce::stage1::learned::raw::bench(
        &args.model,
        (w as usize, h as usize),
        args.pairs,
        args.runs,
        &options,
    )?;
    let text =
        serde_json::to_string(&report).map_err(|e| Error::invalid("report", e.to_string()))?;
    println!("{text}");
    Ok(())
}

/// `frames/total frames (pct), N events, rate, ETA` (without a total: frames, events, rate).
fn progress_line(frames: u64, total: Option<u64>, events: u64, seconds: f64) -> String {
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

fn model_run(args: ModelRunArgs) -> Result<()> {
    check_output(&args.output_npy, args.force)?;
    let options = args.runtime.options();
    let report = v2ce::stage1::learned::raw::run_npy(
        &args.model,
        &args.input_npy,
        &args.output_npy,
        &options,
    )?;
    eprintln!(
        "v2ce: {} -> {}: output {:?} in {:.2} s on {}, max {:.6}, {} NaN/infinite",
        args.input_npy.display(),
        args.output_npy.display(),
        report.shape,
        report.seconds,
        report.provider,
        report.max,
        report.nonfinite
    );
    Ok(())
}

fn eval_stage1(args: Stage1Args) -> Result<()> {
    let (real, intervals) =
        load_events_and_intervals(&args.real, args.frames.as_deref(), args.fps)?;
    let intervals = intervals[args.split.range(intervals.len())].to_vec();
    if intervals.is_empty() {
        return Err(Error::invalid(
            "--split",
            format!("no frame intervals in the {:?} part", args.split),
        ));
    }
    let sim = match &args.sim {
        Some(path) => format::read_events(path)?,
        None => simulate_for_eval(&args, (real.width, real.height))?,
    };
    let sim_name = args
        .sim
        .clone()
        .unwrap_or_else(|| PathBuf::from("the simulated events"));
    if let Some(e) = sim
        .events
        .events()
        .iter()
        .find(|e| e.x >= real.width || e.y >= real.height)
    {
        return Err(Error::format(
            &sim_name,
            format!(
                "event at ({}, {}) outside the real {} x {} sensor",
                e.x, e.y, real.width, real.height
            ),
        ));
    }
    let m = v2ce::metrics::stage1::score(
        real.events.events(),
        sim.events.events(),
        &intervals,
        real.width,
        real.height,
        v2ce::voxel::DEFAULT_BINS,
    )?;
    let mut scorer = v2ce::metrics::Stage2Scorer::new();
    for iv in &intervals {
        scorer.add_interval(
            *iv,
            real.events.time_slice(iv.start(), iv.end()),
            sim.events.time_slice(iv.start(), iv.end()),
        );
    }
    let t = scorer.finish();
    let mut out = std::io::stdout().lock();
    let text = if args.json {
        let mut v = serde_json::to_value(m).map_err(|e| Error::invalid("json", e.to_string()))?;
        v["count_ratio"] = m.count_ratio().into();
        v["c_mete_us"] = t.c_mete_us.into();
        v["mete_us"] = t.mete_us.into();
        v["pger"] = t.pger.into();
        v.to_string()
    } else {
        format!(
            "intervals {} ({} chunks); real events {}, simulated {} (ratio {:.3})\n\
             TPF1 {:.4}  TF1 {:.4}  RF1 {:.4}\n\
             TPAcc {:.4}  TAcc {:.4}  RAcc {:.4}\n\
             PMSE-2 {:.5}  PMSE-4 {:.5}\n\
             C-METE {:.1} us  METE {:.1} us  PGER {:.3}",
            m.intervals,
            m.chunks,
            m.real_events,
            m.sim_events,
            m.count_ratio(),
            m.tpf1,
            m.tf1,
            m.rf1,
            m.tpacc,
            m.tacc,
            m.racc,
            m.pmse2,
            m.pmse4,
            t.c_mete_us,
            t.mete_us,
            t.pger
        )
    };
    writeln!(out, "{text}").map_err(|e| Error::io("stdout", e))
}

fn batch(args: BatchArgs) -> Result<()> {
    use v2ce::batch::{self, Manifest, Shard};
    let format = args
        .encoding
        .format_for(Path::new(&format!("out.{}", args.format)))?;
    let extension = args.format.to_ascii_lowercase();
    let print = |text: String| -> Result<()> {
        let mut out = std::io::stdout().lock();
        writeln!(out, "{text}").map_err(|e| Error::io("stdout", e))
    };
    if let Some(dir) = &args.report {
        let manifest = match &args.manifest {
            Some(m) => Some(Manifest::load(m, &extension)?),
            None => None,
        };
        let report = batch::report(dir, manifest.as_ref())?;
        if args.json {
            let mut v = serde_json::to_value(&report)
                .map_err(|e| Error::invalid("report", e.to_string()))?;
            v["frames_per_busy_s"] = report.frames_per_busy_s().into();
            v["frames_per_s"] = report.frames_per_s().into();
            print(v.to_string())?;
        } else {
            print(report.to_string().trim_end().to_string())?;
        }
        if !report.failed.is_empty() {
            return Err(Error::Run(format!(
                "{} of {} inputs failed",
                report.failed.len(),
                report.failed.len() + report.done
            )));
        }
        return Ok(());
    }
    let (Some(spec), Some(out)) = (&args.manifest, &args.out) else {
        return Err(Error::invalid(
            "arguments",
            "give a MANIFEST and --out DIR (or --report DIR)",
        ));
    };
    let manifest = Manifest::load(spec, &extension)?;
    let env = |k: &str| std::env::var(k).ok();
    let shard = match &args.shard {
        Some(s) => Shard::parse(s)?,
        None => Shard::from_env(env, args.shards)?.unwrap_or(Shard::ALL),
    };
    let threads = args
        .threads
        .filter(|&t| t > 0)
        .unwrap_or_else(|| batch::task_threads(env));
    let (config, config_text) = match &args.config {
        Some(path) => (
            Config::load(path)?,
            std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?,
        ),
        None => (Config::default(), String::new()),
    };
    let options = batch::Options {
        out: out.clone(),
        format,
        config,
        config_text,
        shard,
        jobs: args.jobs.filter(|&j| j > 0).unwrap_or(threads),
        threads,
    };
    let stop = v2ce::daemon::stop_on_signals()?;
    eprintln!(
        "v2ce batch: shard {shard} of {} inputs into {} ({threads} threads, {} at once)",
        manifest.items.len(),
        out.display(),
        options.jobs.min(manifest.items.len())
    );
    let log = |line: &str| eprintln!("v2ce batch: {line}");
    let summary = batch::run(&manifest, &options, &stop, &log)?;
    let line = format!(
        "shard {shard}: {} items, {} converted, {} skipped (done before), {} failed; {} frames, \
         {} events in {:.1} s ({:.1} frames/s)",
        summary.items,
        summary.converted,
        summary.skipped,
        summary.failed.len(),
        summary.frames,
        summary.events,
        summary.wall_s,
        summary.frames as f64 / summary.wall_s.max(1e-9)
    );
    if args.json {
        print(
            serde_json::to_string(&summary)
                .map_err(|e| Error::invalid("summary", e.to_string()))?,
        )?;
    }
    eprintln!("v2ce batch: {line}");
    if !summary.failed.is_empty() {
        return Err(Error::Run(format!(
            "{} of {} inputs of shard {shard} failed (first: {}: {})",
            summary.failed.len(),
            summary.items,
            summary.failed[0].0,
            summary.failed[0].1
        )));
    }
    Ok(())
}

fn transcode(args: TranscodeArgs) -> Result<()> {
    check_output(&args.output, args.force)?;
    let fmt = args.encoding.format_for(&args.output)?;
    let size = args.size.as_deref().map(parse_size).transpose()?;
    let started = std::time::Instant::now();
    let report = v2ce::transcode::transcode(&args.input, &args.output, fmt, size)?;
    let secs = started.elapsed().as_secs_f64();
    eprintln!(
        "v2ce: wrote {} events ({} x {}, {}) to {} in {:.2} s",
        report.events,
        report.size.0,
        report.size.1,
        fmt.name(),
        args.output.display(),
        secs
    );
    Ok(())
}

fn info(args: InfoArgs) -> Result<()> {
    let s = v2ce::transcode::summarize(&args.file)?;
    let mut out = std::io::stdout().lock();
    let text = if args.json {
        let mut v = serde_json::to_value(&s).map_err(|e| Error::invalid("json", e.to_string()))?;
        v["span_us"] = s.span_us().into();
        v["rate_hz"] = s.rate_hz().into();
        v["on_ratio"] = s.on_ratio().into();
        v.to_string()
    } else {
        format!("{}\n{s}", args.file.display())
    };
    writeln!(out, "{text}").map_err(|e| Error::io("stdout", e))
}

fn is_aedat4(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("aedat4"))
}

fn eval_stage2(args: Stage2Args) -> Result<()> {
    let mut config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    if let Some(s) = args.sampler {
        config.stage2.sampler = s;
    }
    if let Some(s) = args.seed {
        config.stage2.seed = s;
    }
    if let Some(b) = args.bins {
        config.stage2.bins = b;
    }
    let (recording, intervals) = load_stage2_input(&args)?;
    let sampler = config.stage2.sampler.build(config.stage2.seed);
    let mut writer = match &args.write_events {
        Some(path) => {
            let file = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
            let mut w = std::io::BufWriter::new(file);
            writeln!(w, "{}", csv::HEADER).map_err(|e| Error::io(path, e))?;
            Some((path.clone(), w))
        }
        None => None,
    };
    let report = v2ce::eval::stage2(
        &recording,
        &intervals,
        config.stage2.bins,
        sampler.as_ref(),
        |events| {
            if let Some((path, w)) = writer.as_mut() {
                csv::write_rows(w, events).map_err(|err| Error::io(path.clone(), err))?;
            }
            Ok(())
        },
    )?;
    if let Some((path, mut w)) = writer {
        w.flush().map_err(|e| Error::io(path, e))?;
    }
    if report.repaired.any() {
        eprintln!(
            "v2ce: warning: repaired voxel values: {} non-finite, {} negative, {} clamped",
            report.repaired.nonfinite, report.repaired.negative, report.repaired.clamped
        );
    }
    if args.json {
        let text =
            serde_json::to_string(&report).map_err(|e| Error::invalid("report", e.to_string()))?;
        println!("{text}");
    } else {
        let m = &report.metrics;
        println!("sampler            {}", report.sampler);
        println!(
            "intervals          {} ({} with events)",
            m.intervals, m.intervals_scored
        );
        println!("events in / out    {} / {}", m.events_in, m.events_out);
        println!("METE               {:.1} us", m.mete_us);
        println!("NOE                {:.3}", m.noe);
        println!("PGER               {:.6}", m.pger);
        println!("C-METE             {:.1} us", m.c_mete_us);
        println!("C-NOE              {:.3}", m.c_noe);
        println!(
            "time per interval  {:.1} us voxelize, {:.1} us sample (median)",
            report.voxelize_us_median, report.sample_us_median
        );
    }
    Ok(())
}

/// The recording and its intervals, from the arguments or the built-in synthetic scene.
fn load_stage2_input(args: &Stage2Args) -> Result<(Recording, Vec<Interval>)> {
    let Some(events_path) = &args.events else {
        let fps = args.fps.unwrap_or(30.0);
        eprintln!(
            "v2ce: no --events given: using the built-in synthetic recording \
             (a sweeping bar, 128 x 96, 2 s, frames at {fps} fps)"
        );
        let intervals = fixed_intervals(0, 1_999_999, fps)?;
        let recording = v2ce::synthetic::sweeping_bar(128, 96, 2_000_000, 1);
        return Ok((recording, intervals));
    };
    load_events_and_intervals(events_path, args.frames.as_deref(), args.fps)
}

/// Reads real events and their frame intervals: from `frames` (an .aedat4 with APS frames or
/// IJRR images.txt), from a fixed `fps` starting at the first event, or, when neither is given,
/// from the APS frames of an .aedat4 event file (decoded once with its events).
/// `eval stage1` without `--sim`: the physics tier's events for the recording's own frames
/// (its APS frames, or `--frames` when that is a frame source) with the chosen preset.
fn simulate_for_eval(args: &Stage1Args, size: (u16, u16)) -> Result<Recording> {
    let mut stage1 = v2ce::stage1::Stage1Config::default();
    match &args.preset_file {
        Some(f) => stage1.load_preset_file(f)?,
        None => stage1.preset = v2ce::stage1::Preset::from_name(&args.preset)?,
    }
    let path = match &args.frames {
        Some(f) if !is_aedat4(f) => f.clone(),
        _ => args.real.clone(),
    };
    let mut source = v2ce::frame::open(&path, &Default::default())?;
    if source.size() != size {
        return Err(Error::invalid(
            "eval stage1",
            format!(
                "frames of {} x {} for a {} x {} recording",
                source.size().0,
                source.size().1,
                size.0,
                size.1
            ),
        ));
    }
    let mut frames = Vec::new();
    while let Some(f) = source.next_frame()? {
        frames.push(f);
    }
    eprintln!(
        "v2ce: simulating {} frames of {} with the physics tier (preset {})",
        frames.len(),
        path.display(),
        stage1.preset_name()
    );
    let events = v2ce::calibrate::simulate(&frames, size, &stage1.physics_config(), args.seed)?;
    Ok(Recording::new(events, Some(size)))
}

fn load_events_and_intervals(
    events_path: &Path,
    frames: Option<&Path>,
    fps: Option<f64>,
) -> Result<(Recording, Vec<Interval>)> {
    let own_frames =
        fps.is_none() && is_aedat4(events_path) && frames.is_none_or(|f| f == events_path);
    let (recording, frames) = if own_frames {
        if frames.is_none() {
            eprintln!(
                "v2ce: no --frames or --fps: using the APS frames of {}",
                events_path.display()
            );
        }
        let (recording, frames) = format::aedat4::read(events_path)?;
        (
            recording,
            Some(format::require_frames(events_path, frames)?),
        )
    } else {
        let frames = match frames {
            Some(path) => Some(format::read_frame_times(path)?),
            None => None,
        };
        (format::read_events(events_path)?, frames)
    };
    let intervals = if let Some(frames) = frames {
        intervals_from_frames(&frames)?
    } else if let Some(fps) = fps {
        let ev = recording.events.events();
        match (ev.first(), ev.last()) {
            (Some(a), Some(b)) => fixed_intervals(a.t, b.t, fps)?,
            _ => Vec::new(),
        }
    } else {
        return Err(Error::invalid(
            "arguments",
            "give --frames FILE or --fps F to define the frame intervals",
        ));
    };
    Ok((recording, intervals))
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
