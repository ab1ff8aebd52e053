//! `v2ce run`, the live daemon, wired from the configuration: the source (a camera, a file
//! replayed in real time, or the bundled fixture), the outputs (UDP, TCP, file), signals,
//! systemd readiness and status, and periodic stats on the log; and [`bench()`], which measures it.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use serde::Serialize;
use std::time::Duration;

use crate::config::{Config, RunConfig};
use crate::error::{Error, Result};
use crate::frame;
use crate::pipeline::stats::{Latency, ProcessUsage, Snapshot};
use crate::pipeline::{self, End, Options, Report, Stages};
use crate::sink::{Sink, SinkContext};

/// Raises the returned flag on the first SIGINT, SIGTERM or SIGHUP (the pipeline then flushes
/// and stops: a hang-up, which a closing terminal or a lost SSH session sends, is a clean stop,
/// its files finished and its report printed); a second one exits at once with status 130.
pub fn stop_on_signals() -> Result<Arc<AtomicBool>> {
    use signal_hook::consts::{SIGHUP, SIGINT, SIGTERM};
    let flag = Arc::new(AtomicBool::new(false));
    let err = |e: std::io::Error| Error::invalid("signal handler", e.to_string());
    for sig in [SIGINT, SIGTERM, SIGHUP] {
        // Order matters: the conditional exit sees the flag from an earlier signal only.
        signal_hook::flag::register_conditional_shutdown(sig, 130, flag.clone()).map_err(err)?;
        signal_hook::flag::register(sig, flag.clone()).map_err(err)?;
    }
    Ok(flag)
}

/// Opens every configured output (see [`Config::outputs`]) for a `width x height` sensor whose
/// frame times run `speed` times faster than the wall clock (a file's replay speed; 1 for a
/// camera).
pub fn open_sinks(
    config: &Config,
    width: u16,
    height: u16,
    speed: f64,
) -> Result<Vec<Box<dyn Sink>>> {
    let context = SinkContext {
        width,
        height,
        speed,
    };
    let outputs = config.outputs()?;
    outputs.iter().map(|sink| sink.build(&context)).collect()
}

/// The pipeline options of a `[run]` table.
pub fn options(run: &RunConfig) -> Options {
    Options {
        policy: run.queue_policy,
        capacity: run.queue_capacity,
        max_frames: (run.max_frames > 0).then_some(run.max_frames),
        duration: (run.duration > 0.0).then(|| Duration::from_secs_f64(run.duration)),
        tick: Duration::from_secs_f64(run.stats_interval),
        // The systemd unit gives a stop 20 s (TimeoutStopSec) for everything.
        stop_flush_limit: Some(Duration::from_secs(8)),
        counters: None,
        lag_budget: None,
    }
}

fn notify(state: &[sd_notify::NotifyState]) {
    // Outside systemd there is no socket and this does nothing.
    if let Err(e) = sd_notify::notify(false, state) {
        tracing::debug!("systemd notification: {e}");
    }
}

/// Starts the HTTP listener when `[run] http` is set: shared counters for the pipeline, and a
/// preview sink (added to `sinks`) for the page.
fn start_http(
    config: &Config,
    what: &str,
    stage1: &dyn crate::stage1::Stage1,
    sinks: &mut Vec<Box<dyn crate::sink::Sink>>,
) -> Result<Option<(crate::http::HttpServer, Arc<crate::http::Status>)>> {
    if config.run.http.is_empty() {
        return Ok(None);
    }
    let (w, h) = stage1.output_size();
    let preview = crate::sink::preview::PreviewBuffer::new(w, h);
    let mut settings: Vec<(String, String)> = vec![
        ("source".into(), what.to_string()),
        ("size".into(), format!("{w} x {h}")),
        ("stage 1".into(), stage1.describe()),
        (
            "sampler".into(),
            format!("{:?}", config.stage2.sampler).to_lowercase(),
        ),
        (
            "queues".into(),
            format!(
                "{} x{}",
                config.run.queue_policy.name(),
                config.run.queue_capacity
            ),
        ),
    ];
    settings.extend(sinks.iter().map(|s| ("output".to_string(), s.describe())));
    sinks.push(Box::new(crate::sink::preview::PreviewSink::new(
        preview.clone(),
    )));
    let status = Arc::new(crate::http::Status {
        counters: Arc::new(crate::pipeline::stats::Counters::new()),
        preview,
        tier: config.stage1.tier.name().into(),
        preset: match config.stage1.tier {
            crate::stage1::Tier::Physics => config.stage1.preset_name(),
            _ => stage1.describe(),
        },
        settings,
        stall: crate::limits::seconds("run.ready_timeout", config.run.ready_timeout, false)?,
        running: std::sync::atomic::AtomicBool::new(false),
        listener: crate::http::ListenerCounters::default(),
    });
    let server = crate::http::HttpServer::start(&config.run.http, status.clone())?;
    tracing::info!(
        "HTTP listener on http://{}/ (/metrics, /healthz, /readyz, the preview page)",
        server.address()
    );
    Ok(Some((server, status)))
}

/// Runs the daemon until the source ends, `stop` is raised or a limit is reached; logs a stats
/// line every `stats_interval` and mirrors it in the systemd status.
pub fn run(config: &Config, stop: &AtomicBool) -> Result<Report> {
    config.validate()?;
    let (source, what) = config.run.parts.source.build(&config.camera)?;
    let stage1 = crate::convert::build_stage1(config, source.first.as_ref())?;
    let (w, h) = stage1.output_size();
    let mut sinks = open_sinks(config, w, h, source.pace.unwrap_or(1.0))?;
    let http = start_http(config, &what, stage1.as_ref(), &mut sinks)?;
    let outputs: Vec<String> = sinks.iter().map(|s| s.describe()).collect();
    tracing::info!(
        "v2ce {}: {what} -> {} ({}x{}, Stage 1 {}, queues {} x{})",
        env!("CARGO_PKG_VERSION"),
        outputs.join(", "),
        w,
        h,
        stage1.describe(),
        config.run.queue_policy.name(),
        config.run.queue_capacity
    );
    if config.run.wait_for_client {
        tracing::info!("waiting for a TCP client");
        // Up and serving: READY now, or a service manager's start timeout would kill (and
        // restart) a daemon that only waits for its first client.
        notify(&[
            sd_notify::NotifyState::Ready,
            sd_notify::NotifyState::Status("waiting for a TCP client"),
        ]);
        while !sinks.iter().any(|s| s.stats().clients > 0) {
            if !crate::pipeline::clock::sleep_unless(Duration::from_millis(20), &|| {
                stop.load(Ordering::Relaxed)
            }) {
                break;
            }
        }
    }
    notify(&[
        sd_notify::NotifyState::Ready,
        sd_notify::NotifyState::Status(&format!("running: {what}")),
    ]);
    let mut on_tick = |s: &Snapshot| {
        let line = s.line();
        tracing::info!("{line}");
        notify(&[sd_notify::NotifyState::Status(&line)]);
        for sink in s.sinks.iter().filter(|k| k.failed.is_some()) {
            tracing::warn!("output down: {}", sink.sink);
        }
    };
    let stages = Stages {
        stage1,
        sampler: config.stage2.sampler.build(config.stage2.seed),
        sinks,
    };
    let mut pipeline_options = options(&config.run);
    pipeline_options.counters = http.as_ref().map(|(_, status)| status.counters.clone());
    if let Some((_, status)) = &http {
        status.running.store(true, Ordering::Relaxed);
    }
    let report = pipeline::run(source, stages, &pipeline_options, stop, &mut on_tick);
    if let Some((_, status)) = &http {
        status.running.store(false, Ordering::Relaxed);
    }
    notify(&[sd_notify::NotifyState::Stopping]);
    let report = report?;
    let s = &report.stats;
    let l = &s.latency_total;
    let summary = format!(
        "stopped: {}; {} frames in, {} dropped{}, {} events out in {:.1} s; latency p50 {:.1} ms \
         p99 {:.1} ms max {:.1} ms; cpu {:.1} s; peak rss {} MiB{}",
        report.end.describe(),
        s.frames_in,
        s.frames_dropped,
        if s.source_refused > 0 {
            format!(", {} refused by the source", s.source_refused)
        } else {
            String::new()
        },
        s.events_out,
        s.uptime_s,
        l.p50_ms,
        l.p99_ms,
        l.max_ms,
        s.cpu_s,
        s.max_rss_kib / 1024,
        report
            .stage1
            .record
            .status()
            .map(|t| format!("; stage 1: {}", t.line))
            .unwrap_or_default()
    );
    if report.end.is_clean() {
        tracing::info!("{summary}");
    } else {
        tracing::error!("{summary}");
    }
    for sink in &s.sinks {
        let line = format!(
            "{}: {} events sent, {} dropped{}{}{}",
            sink.sink,
            sink.stats.events_sent,
            sink.stats.events_dropped,
            if sink.stats.events_evicted > 0 {
                format!(
                    " ({} evicted from its queue: the output could not keep up)",
                    sink.stats.events_evicted
                )
            } else {
                String::new()
            },
            if sink.stats.events_refused > 0 {
                format!(
                    ", {} refused (no receiver on the port)",
                    sink.stats.events_refused
                )
            } else {
                String::new()
            },
            sink.failed
                .as_ref()
                .map(|f| format!(" (failed: {f})"))
                .unwrap_or_default()
        );
        let starved = s.frames_dropped.saturating_sub(s.frames_out_of_order);
        if sink.recording && starved > 0 {
            // The file holds every event it was given, but not those of frames lost upstream.
            tracing::warn!(
                "{line}; it lacks the events of the {} frames dropped before Stage 2 (the machine \
                 could not keep up under --queue-policy drop-oldest; `block` keeps every frame)",
                starved
            );
        } else if sink.stats.events_dropped > 0 || sink.failed.is_some() {
            tracing::warn!("{line}");
        } else {
            tracing::info!("{line}");
        }
    }
    Ok(report)
}

/// The name of `v2ce bench`'s in-process receiver thread, whose CPU is not the daemon's.
pub const BENCH_RECEIVER: &str = "bench-receiver";

/// What [`bench()`] measured for one frame size.
#[derive(Debug, Clone, Serialize)]
pub struct BenchResult {
    /// Frame width and height.
    pub size: (u16, u16),
    /// Why the run stopped (`duration`, or `stopped` by a signal).
    pub end: End,
    /// Seconds run.
    pub seconds: f64,
    /// Frames read from the source.
    pub frames: u64,
    /// Frames dropped (drop-oldest queues).
    pub frames_dropped: u64,
    /// Events sent per second.
    pub events_per_s: f64,
    /// Datagrams the loopback receiver got.
    pub datagrams_received: u64,
    /// Events the loopback receiver got, and the UDP sink sent.
    pub events_received: u64,
    /// See `events_received`.
    pub events_sent: u64,
    /// Events the sink sent later than their due time (emission at event time).
    pub events_late: u64,
    /// The receiver's arrival time minus event time, less its minimum (`spif_timestamped`).
    pub arrival_spread: Option<Latency>,
    /// Most datagrams the receiver got within one millisecond.
    pub max_datagrams_per_ms: u64,
    /// Capture-to-send latency over the whole run.
    pub latency: Latency,
    /// The latency budget: Stage 1's wait for its window (the stride: one interval for the
    /// physics tier) plus one frame interval, or plus the emit delay at event time, at the
    /// replay speed.
    pub budget_ms: f64,
    /// Stage 1 as it ran (tier, window, stride, the network's time per window).
    pub stage1: crate::stage1::Stage1Stats,
    /// The physics tier's sub-frame cap (`motion = "flow"`) over the run: its mean weighted
    /// by frame time, and its value at the end; `None` for a tier or motion model without one.
    pub subframe_cap_mean: Option<f64>,
    /// See `subframe_cap_mean`.
    pub subframe_cap_final: Option<u32>,
    /// The process's CPU per frame at each sub-frame cap it ran under (the tier's level of
    /// detail), highest first: over the seconds whose cap did not change, with the frames
    /// they held. Empty for a tier without levels.
    pub cpu_per_frame: Vec<LevelCost>,
    /// The process's CPU over the run's wall time: the cores it kept busy on average.
    pub cores_used: f64,
    /// This run's CPU time over its wall time, percent of one core (the receiver's included).
    pub cpu_percent: f64,
    /// The daemon's own threads' CPU (all but the bench's receiver), percent of one core.
    pub daemon_cpu_percent: f64,
    /// Each thread's CPU by name (`v2ce-capture`, `v2ce-stage1`, `v2ce-sink0`, ...,
    /// `bench-receiver`), percent of one core, largest first.
    pub threads: Vec<(String, f64)>,
    /// Smallest and largest resident set at the stats ticks (10 s apart; the end
    /// when the run was shorter), KiB.
    pub rss_range_kib: (u64, u64),
    /// Largest resident set in the first and in the last minute of ticks, KiB: growth shows
    /// as the second above the first.
    pub rss_first_last_minute_kib: (u64, u64),
}

impl BenchResult {
    /// One line for people.
    pub fn line(&self) -> String {
        let l = &self.latency;
        format!(
            "{}x{} {} L={} stride {}: {:.1} frames/s ({} dropped){}, {:.0} events/s; capture-to-send latency p50 \
             {:.2} ms, p90 {:.2} ms, p99 {:.2} ms, max {:.2} ms (budget {:.1} ms: {}); cpu \
             {:.1}% of a core ({:.2} cores; the daemon's threads {:.1}%: {}){}; rss {}..{} KiB, first minute max {} KiB, last minute max {} KiB; \
             udp receiver: {} of {} events ({} sent late), arrival minus event time{}, at most {} \
             datagrams in one ms",
            self.size.0,
            self.size.1,
            self.stage1.tier,
            self.stage1.window,
            self.stage1.stride,
            self.frames as f64 / self.seconds.max(1e-9),
            self.frames_dropped,
            match (self.subframe_cap_mean, self.subframe_cap_final) {
                (Some(mean), Some(last)) => format!(", sub-frame cap mean {mean:.2}, final {last}"),
                _ => String::new(),
            },
            self.events_per_s,
            l.p50_ms,
            l.p90_ms,
            l.p99_ms,
            l.max_ms,
            self.budget_ms,
            if l.p99_ms <= self.budget_ms {
                "met"
            } else {
                "missed"
            },
            self.cpu_percent,
            self.cores_used,
            self.daemon_cpu_percent,
            self.threads
                .iter()
                .filter(|(_, p)| *p >= 0.5)
                .map(|(n, p)| format!("{n} {p:.1}"))
                .collect::<Vec<_>>()
                .join(", "),
            if self.cpu_per_frame.is_empty() {
                String::new()
            } else {
                format!(
                    "; cpu per frame by sub-frame cap: {}",
                    self.cpu_per_frame
                        .iter()
                        .map(|c| format!("{} {:.1} ms ({} frames)", c.level, c.cpu_ms, c.frames))
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            },
            self.rss_range_kib.0,
            self.rss_range_kib.1,
            self.rss_first_last_minute_kib.0,
            self.rss_first_last_minute_kib.1,
            self.events_received,
            self.events_sent,
            self.events_late,
            self.arrival_spread
                .map(|a| format!(" p50 {:.2} ms p99 {:.2} ms max {:.2} ms", a.p50_ms, a.p99_ms, a.max_ms))
                .unwrap_or_else(|| " -".into()),
            self.max_datagrams_per_ms
        )
    }
}

/// The CPU a frame took at one level of Stage 1's detail (see [`BenchResult::cpu_per_frame`]).
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct LevelCost {
    /// The level: the physics tier's sub-frame cap.
    pub level: u32,
    /// Frames through Stage 1 at it.
    pub frames: u64,
    /// The process's CPU (user + system) per frame, ms.
    pub cpu_ms: f64,
}

/// The bench's snapshots every second: the process's CPU and the frames through Stage 1,
/// summed by Stage 1's level of detail over the seconds it held one level.
#[derive(Debug, Default)]
struct ByLevel {
    last: Option<(Option<u32>, f64, u64)>,
    /// Per level: frames and CPU seconds.
    sums: std::collections::BTreeMap<u32, (u64, f64)>,
}

impl ByLevel {
    fn tick(&mut self, s: &Snapshot) {
        let level = s.stage1.as_ref().and_then(|t| t.level);
        let now = (level, s.cpu_s, s.frames_processed);
        if let Some((Some(before), cpu, frames)) = self.last.replace(now) {
            if level == Some(before) && s.frames_processed > frames {
                let sum = self.sums.entry(before).or_default();
                sum.0 += s.frames_processed - frames;
                sum.1 += s.cpu_s - cpu;
            }
        }
    }

    fn table(&self) -> Vec<LevelCost> {
        self.sums
            .iter()
            .rev()
            .map(|(&level, &(frames, cpu))| LevelCost {
                level,
                frames,
                cpu_ms: cpu * 1e3 / frames.max(1) as f64,
            })
            .collect()
    }
}

/// Ticks of one second between two of the bench's stats lines.
const BENCH_TICKS_PER_LINE: u64 = 10;

/// The sub-frame cap's time-weighted mean and final value from a tier's record, where it has
/// one (the physics tier's `motion`, after some interval ran under `motion = "flow"`).
fn subframe_cap(stage1: &crate::stage1::Stage1Stats) -> Option<(f64, u32)> {
    let record: serde_json::Value = serde_json::from_str(stage1.record.json().get()).ok()?;
    let motion: crate::stage1::motion::MotionStats =
        serde_json::from_value(record.get("motion")?.clone()).ok()?;
    Some((motion.cap_mean()?, motion.cap))
}

/// Measures the daemon for `seconds`: the bundled fixture, resampled to `size`, replayed at
/// `speed` times real time and looped, through the pipeline with `base`'s Stage 1 and Stage 2
/// (drop-oldest queues) to a UDP receiver thread on loopback that drains the datagrams as a
/// consumer would.
pub fn bench(
    size: (u16, u16),
    seconds: f64,
    speed: f64,
    base: &Config,
    stop: &AtomicBool,
) -> Result<BenchResult> {
    crate::limits::seconds("bench --seconds", seconds, false)?;
    crate::limits::replay_speed("bench --replay-speed", speed)?;
    // A receiver thread: `v2ce listen`'s, on timestamped SPIF words (the default datagram
    // size), measuring when events arrive against their own times.
    let done = Arc::new(AtomicBool::new(false));
    let (port_tx, port_rx) = crossbeam_channel::bounded::<String>(1);
    let receiver = std::thread::Builder::new()
        .name(BENCH_RECEIVER.into())
        .spawn({
            let done = done.clone();
            move || {
                let options = crate::listen::ListenOptions {
                    listen: crate::listen::Listen::Udp {
                        bind: "127.0.0.1:0".into(),
                        format: crate::format::datagram::UdpFormat::SpifTimestamped,
                    },
                    out: None,
                    size: (1, 1),
                    duration: None,
                    idle: Duration::from_secs(3600),
                    max_events: None,
                    recv_buffer: 0,
                    priority: 5,
                };
                crate::listen::listen(&options, &done, |at| {
                    let _ = port_tx.send(at.to_string());
                })
            }
        })
        .map_err(|e| Error::Run(format!("cannot start the bench's receiver: {e}")))?;
    let address = port_rx
        .recv_timeout(Duration::from_secs(5))
        .map_err(|_| Error::invalid("bench", "the UDP receiver did not start"))?;
    let mut config = Config {
        run: RunConfig::default(),
        sink: Vec::new(),
        ..base.clone()
    };
    let source = &mut config.run.parts.source;
    source.replay_speed = speed;
    source.source = frame::fixture::NAME.into();
    source.size = format!("{}x{}", size.0, size.1);
    source.loop_source = true;
    config.run.duration = seconds;
    config.run.parts.udp.address = address;
    config.run.parts.udp.format = crate::format::datagram::UdpFormat::SpifTimestamped;
    // The HTTP listener, to measure what it and a preview page cost.
    config.run.http = base.run.http.clone();
    let (source, what) = config.run.parts.source.build(&config.camera)?;
    let stage1 = crate::convert::build_stage1(&config, source.first.as_ref())?;
    let mut sinks = open_sinks(&config, size.0, size.1, speed)?;
    let http = start_http(&config, &what, stage1.as_ref(), &mut sinks)?;
    let stages = Stages {
        stage1,
        sampler: config.stage2.sampler.build(config.stage2.seed),
        sinks,
    };
    tracing::info!("bench {}x{}: {what}, {seconds} s", size.0, size.1);
    let cpu_before = ProcessUsage::now().cpu_s;
    let threads = crate::process::ThreadCpu::start()
        .map_err(|e| Error::Run(format!("cannot start the CPU sampler: {e}")))?;
    let mut rss = Vec::new();
    let mut by_level = ByLevel::default();
    let mut ticks = 0u64;
    let mut on_tick = |s: &Snapshot| {
        by_level.tick(s);
        // The stats line and the memory every 10 s, as a daemon logs them.
        if ticks % BENCH_TICKS_PER_LINE == BENCH_TICKS_PER_LINE - 1 {
            tracing::info!("{}", s.line());
            rss.push(s.rss_kib);
        }
        ticks += 1;
    };
    let mut pipeline_options = options(&config.run);
    pipeline_options.tick = Duration::from_secs(1);
    pipeline_options.counters = http.as_ref().map(|(_, status)| status.counters.clone());
    if let Some((_, status)) = &http {
        status.running.store(true, Ordering::Relaxed);
    }
    let report = pipeline::run(source, stages, &pipeline_options, stop, &mut on_tick);
    drop(http);
    let threads = threads.finish();
    // Let the last datagrams land, then stop the receiver.
    std::thread::sleep(Duration::from_millis(200));
    done.store(true, Ordering::Relaxed);
    let received = receiver
        .join()
        .map_err(|_| Error::invalid("bench", "the UDP receiver panicked"))??;
    let report = report?;
    let udp = report
        .stats
        .sinks
        .first()
        .map(|k| k.stats)
        .unwrap_or_default();
    let s = &report.stats;
    // A run shorter than one interval has no tick: take the end (after the stages freed
    // their buffers, so lower than while running).
    if rss.is_empty() {
        rss.push(s.rss_kib);
    }
    let minute = rss.len().min(6);
    let max_of = |v: &[u64]| v.iter().copied().max().unwrap_or(0);
    let seconds = s.uptime_s.max(1e-9);
    let cap = subframe_cap(&report.stage1);
    Ok(BenchResult {
        size,
        end: report.end.clone(),
        seconds: s.uptime_s,
        frames: s.frames_in,
        frames_dropped: s.frames_dropped,
        events_per_s: s.events_out as f64 / seconds,
        datagrams_received: received.messages,
        events_received: received.events,
        events_sent: udp.events_sent,
        events_late: udp.events_late,
        arrival_spread: received.arrival_spread,
        max_datagrams_per_ms: received.max_messages_per_ms,
        latency: s.latency_total,
        // The fixture runs at 30 fps; at event time the last event of a batch leaves the emit
        // delay after its frame, and a window's stride of intervals waits before that.
        budget_ms: match config.run.parts.udp.emit {
            crate::config::EmitMode::Asap => {
                (1 + report.stage1.stride) as f64 * 1000.0 / 30.0 / speed.max(1e-9)
            }
            crate::config::EmitMode::EventTime => {
                config.run.parts.udp.emit_delay_ms
                    + report.stage1.stride as f64 * 1000.0 / 30.0 / speed.max(1e-9)
            }
        },
        subframe_cap_mean: cap.map(|c| c.0),
        subframe_cap_final: cap.map(|c| c.1),
        cpu_per_frame: by_level.table(),
        cores_used: (s.cpu_s - cpu_before) / seconds,
        stage1: report.stage1.clone(),
        cpu_percent: 100.0 * (s.cpu_s - cpu_before) / seconds,
        daemon_cpu_percent: threads
            .iter()
            .filter(|(n, _)| n != BENCH_RECEIVER)
            .map(|(_, p)| p)
            .sum(),
        threads,
        rss_range_kib: (rss.iter().copied().min().unwrap_or(0), max_of(&rss)),
        rss_first_last_minute_kib: (max_of(&rss[..minute]), max_of(&rss[rss.len() - minute..])),
    })
}
