//! `v2ce run`, `v2ce devices` and `v2ce bench`: the daemon, its cameras, its measurement.

use std::path::PathBuf;

use clap::{Args, Subcommand};

use super::tradeoff::TradeoffArgs;
use super::*;
use crate::config::Config;
use crate::error::{Error, Result};
use crate::limits::parse_size;

/// The flags of `v2ce run`.
#[derive(Args)]
pub struct RunArgs {
    /// TOML configuration file (the flags below override it); see config/v2ce.toml.
    #[arg(long)]
    pub(crate) config: Option<PathBuf>,
    /// A camera (/dev/video0 or an index), a file or image folder, or `fixture` [config default:
    /// "", the first camera, else the fixture].
    #[arg(long)]
    pub(crate) source: Option<String>,
    /// Send UDP datagrams to HOST:PORT (an empty string turns UDP off) [config default:
    /// 127.0.0.1:3333].
    #[arg(long)]
    pub(crate) udp: Option<String>,
    /// Datagram format: spif, spif_timestamped, t64_x16_y16_on8, t32_x16_y15_on1 [config
    /// default: spif].
    #[arg(long)]
    pub(crate) udp_format: Option<String>,
    /// Largest UDP payload in bytes [config default: 512, which aestream and SpiNNaker's SPIF
    /// listener read whole].
    #[arg(long)]
    pub(crate) udp_payload: Option<usize>,
    /// Most UDP datagrams per second (0: unpaced) [config default: 0].
    #[arg(long)]
    pub(crate) udp_rate: Option<u32>,
    /// UDP socket send buffer to ask for, bytes (0: the kernel's default) [config default: 0].
    #[arg(long, value_name = "BYTES")]
    pub(crate) udp_send_buffer: Option<usize>,
    /// When UDP events leave: event-time (each at its own time + the delay) or asap
    /// [config default: event-time].
    #[arg(long, value_enum)]
    pub(crate) emit: Option<crate::config::EmitMode>,
    /// How far behind the frames events leave at event time, ms [config default: 100].
    #[arg(long)]
    pub(crate) emit_delay_ms: Option<f64>,
    /// Realtime priority of the thread that sends at event time, 1-99 (0: normal scheduling)
    /// [config default: 10, when the process may].
    #[arg(long)]
    pub(crate) emit_priority: Option<u8>,
    /// Publish events on this ROS 2 topic as event_camera_msgs/msg/EventPacket (evt3) over DDS
    /// [config default: "", off; a `[[sink]]` of type "ros2" defaults to /event_camera/events].
    #[arg(long, value_name = "TOPIC")]
    pub(crate) ros2: Option<String>,
    /// The ROS 2 output's DDS domain [config default: ROS_DOMAIN_ID, else 0].
    #[arg(long, value_name = "ID")]
    pub(crate) ros2_domain_id: Option<u32>,
    /// The ROS 2 output's delivery: reliable or best-effort [config default: reliable].
    #[arg(long, value_enum)]
    pub(crate) ros2_reliability: Option<crate::sink::ros2::Reliability>,
    /// Hold the ROS 2 output's first packet until this many subscribers are matched
    /// [config default: 0].
    #[arg(long, value_name = "N")]
    pub(crate) ros2_wait_subscribers: Option<u32>,
    /// Sensor preset of the physics tier: davis346, dvxplorer, ideal [config default: davis346].
    #[arg(long)]
    pub(crate) preset: Option<String>,
    /// A preset file (as `v2ce calibrate` writes) instead of --preset [config default: "",
    /// none].
    #[arg(long, conflicts_with = "preset")]
    pub(crate) preset_file: Option<PathBuf>,
    /// Serve an event stream to TCP clients on HOST:PORT [config default: "", off].
    #[arg(long)]
    pub(crate) tcp: Option<String>,
    /// What TCP clients receive: aedat4 (DV's network stream), evt2 or evt3 (Prophesee RAW,
    /// a .raw file's bytes) [config default: aedat4].
    #[arg(long, value_enum)]
    pub(crate) tcp_format: Option<crate::sink::tcp::TcpFormat>,
    /// Hold the source until the first TCP client has connected.
    #[arg(long)]
    pub(crate) wait_for_client: bool,
    /// Also write the events to this file (.aedat4, .raw, .csv, .npz, .h5) [config default: "",
    /// none].
    #[arg(long)]
    pub(crate) out: Option<String>,
    /// Seed of mismatch, noise and sampling [config default: 0].
    #[arg(long)]
    pub(crate) seed: Option<u64>,
    /// A full queue: block (lose nothing) or drop-oldest (stay live) [config default:
    /// drop-oldest].
    #[arg(long)]
    pub(crate) queue_policy: Option<String>,
    /// Stop after this many seconds [config default: 0, no limit].
    #[arg(long)]
    pub(crate) duration: Option<f64>,
    /// Stop after this many frames [config default: 0, no limit].
    #[arg(long)]
    pub(crate) max_frames: Option<u64>,
    /// Resample frames to WIDTHxHEIGHT [config default: "", the source's size].
    #[arg(long, value_name = "WxH")]
    pub(crate) size: Option<String>,
    /// Replay a file at this multiple of real time [config default: 1].
    #[arg(long)]
    pub(crate) replay_speed: Option<f64>,
    /// Replay a file again and again.
    #[arg(long = "loop")]
    pub(crate) loop_source: bool,
    /// Seconds between stats lines [config default: 10].
    #[arg(long)]
    pub(crate) stats_interval: Option<f64>,
    /// Serve /metrics, /healthz, /readyz and the live preview page on IP:PORT (port 0: any;
    /// the address is logged) [config default: off]
    #[arg(long, value_name = "IP:PORT")]
    pub(crate) http: Option<String>,
    /// /readyz turns not ready after this many seconds without a frame [config default: 2]
    #[arg(long)]
    pub(crate) ready_timeout: Option<f64>,
    /// Print the final report as one JSON object on stdout.
    #[arg(long)]
    pub(crate) json: bool,
    /// The Stage 1 tier and its settings.
    #[command(flatten)]
    pub(crate) tier: TierArgs,
}

/// The flags of `v2ce bench`.
#[derive(Args)]
#[command(args_conflicts_with_subcommands = true)]
pub struct BenchArgs {
    /// Another measurement instead of the daemon's.
    #[command(subcommand)]
    pub(crate) what: Option<BenchCommand>,
    /// Seconds per configuration.
    #[arg(long, default_value_t = 30.0)]
    pub(crate) seconds: f64,
    /// Sizes to measure.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "346x260,640x480,1280x720"
    )]
    pub(crate) sizes: Vec<String>,
    /// Print the results as JSON lines.
    #[arg(long)]
    pub(crate) json: bool,
    /// Replay the fixture at this multiple of real time (below 1 for a tier slower than real
    /// time).
    #[arg(long, default_value_t = 1.0)]
    pub(crate) replay_speed: f64,
    /// Run the HTTP listener on IP:PORT during the bench (to measure what it, a scraper and an
    /// open preview page cost)
    #[arg(long, value_name = "IP:PORT")]
    pub(crate) http: Option<String>,
    /// TOML configuration for Stage 1 and Stage 2 (the flags below override it).
    #[arg(long)]
    pub(crate) config: Option<PathBuf>,
    /// The Stage 1 tier and its settings.
    #[command(flatten)]
    pub(crate) tier: TierArgs,
}

/// The `v2ce bench` subcommands.
#[derive(Subcommand)]
pub enum BenchCommand {
    /// Every Stage 1 tier and setting on the same frames: speed (pairs/s, window latency) and
    /// accuracy (TF1, TPF1, count ratio, C-METE) against a real recording's held-out half and
    /// synthetic sequences, with the Pareto front (docs/learned.md: "The speed/accuracy trade").
    Tradeoff(TradeoffArgs),
}

/// The daemon's configuration: the `--config` file (or the defaults) with the flags given written over it, checked.
pub fn run_config(args: &RunArgs) -> Result<Config> {
    let mut config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    let run = &mut config.run;
    let parts = &mut run.parts;
    super::given!(
        parts.source.source => args.source,
        parts.source.size => args.size,
        parts.source.replay_speed => args.replay_speed,
        parts.udp.address => args.udp,
        parts.udp.payload => args.udp_payload,
        parts.udp.rate => args.udp_rate,
        parts.udp.send_buffer => args.udp_send_buffer,
        parts.udp.emit => args.emit,
        parts.udp.emit_delay_ms => args.emit_delay_ms,
        parts.udp.emit_priority => args.emit_priority,
        parts.tcp.address => args.tcp,
        parts.tcp.format => args.tcp_format,
        parts.out.path => args.out,
        parts.ros2.topic => args.ros2,
        parts.ros2.reliability => args.ros2_reliability,
        parts.ros2.wait_subscribers => args.ros2_wait_subscribers,
        run.duration => args.duration,
        run.max_frames => args.max_frames,
        run.stats_interval => args.stats_interval,
        run.http => args.http,
        run.ready_timeout => args.ready_timeout,
    );
    if let Some(d) = args.ros2_domain_id {
        parts.ros2.domain_id = Some(d);
    }
    if let Some(v) = &args.udp_format {
        parts.udp.format = crate::format::datagram::UdpFormat::from_name(v)?;
    }
    if let Some(v) = &args.queue_policy {
        run.queue_policy = crate::pipeline::queue::QueuePolicy::from_name(v)?;
    }
    parts.source.loop_source |= args.loop_source;
    run.wait_for_client |= args.wait_for_client;
    if let Some(s) = args.seed {
        config.stage1.seed = s;
        config.stage2.seed = s;
    }
    if let Some(p) = &args.preset {
        config.stage1.preset = crate::stage1::Preset::from_name(p)?;
        config.stage1.custom = None;
    }
    if let Some(f) = &args.preset_file {
        config.stage1.load_preset_file(f)?;
    }
    args.tier.apply(&mut config)?;
    config.validate()?;
    Ok(config)
}

/// Runs `v2ce run` until the source ends, a limit is reached or a signal stops it.
pub fn run(args: RunArgs) -> Result<()> {
    let config = run_config(&args)?;
    let stop = crate::daemon::stop_on_signals()?;
    let report = crate::daemon::run(&config, &stop)?;
    if args.json {
        let text =
            serde_json::to_string(&report).map_err(|e| Error::invalid("report", e.to_string()))?;
        println!("{text}");
    }
    if !report.end.is_clean() {
        return Err(Error::Run(report.end.describe()));
    }
    // The daemon went on with its other outputs; the run still failed to write one.
    let failed: Vec<&str> = report
        .stats
        .sinks
        .iter()
        .filter(|s| s.failed.is_some())
        .map(|s| s.sink.as_str())
        .collect();
    if failed.is_empty() {
        Ok(())
    } else {
        Err(Error::Run(format!(
            "{} output(s) failed (the others went on; see above): {}",
            failed.len(),
            failed.join(", ")
        )))
    }
}

/// Runs `v2ce devices`.
pub fn devices() -> Result<()> {
    let cameras = crate::capture::list_cameras()?;
    if cameras.is_empty() {
        println!("no cameras found");
    }
    for camera in cameras {
        println!("{camera}");
    }
    Ok(())
}

/// Runs `v2ce bench` (the daemon on the replayed fixture, per size).
pub fn bench(args: BenchArgs) -> Result<()> {
    let stop = crate::daemon::stop_on_signals()?;
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
        let result = crate::daemon::bench(
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
        if result.end == crate::pipeline::End::Stopped {
            break;
        }
    }
    Ok(())
}
