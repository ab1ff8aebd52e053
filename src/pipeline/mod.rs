//! The pipeline: frames from a source through Stage 1 and Stage 2 into sinks, one thread per
//! stage, joined by bounded queues.
//!
//! ```text
//! capture ──q──▶ sequencer ──q──▶ Stage 1 ──q──▶ Stage 2 ──┬─q──▶ sink 0 (encode + send)
//!  (source,        (time order,     (pixel model,  (sampler,  ├─q──▶ sink 1
//!   pacing,         gaps)            voxelizer)     fan-out)   └─q──▶ ...
//!   reconnects)
//! ```
//!
//! - **capture** reads the source: a camera (reopened with backoff when it fails) or a file,
//!   replayed at its own pace when asked (`speed`), looped when asked. It stamps each frame with
//!   the instant it arrived, the start of the capture-to-send latency.
//! - **sequencer** keeps frame times strictly increasing (a frame that does not come after the
//!   previous one is rejected and counted).
//! - **Stage 1** runs whatever tier it was given ([`Stage1`]: the pixel model, one interval per
//!   frame, or the network, a window of intervals at a time), and at the end of the stream (or
//!   before a reopened camera's first frame) flushes what it holds. **Stage 2** re-times voxels
//!   with the sampler (counting every value it had to repair) and fans each interval's events
//!   out to one queue per sink.
//! - each **sink** thread encodes and sends. A sink that fails is reported and drained; the
//!   others go on. When every sink has failed the pipeline stops with an error.
//!
//! Every queue applies one [`QueuePolicy`] (block, or drop-oldest with counters). Shutdown
//! flows downstream: the capture thread stops (stop flag, end of source, `max_frames`,
//! `duration`, or a failure), each stage drains its input and ends when its producer has gone,
//! and the sinks are finished last, so nothing already queued is lost.
//!
//! The pipeline takes built pieces ([`Stages`]: a Stage 1 tier, a sampler, the sinks), never
//! the whole configuration, so it knows no concrete tier, sink or format. Offline conversion and
//! the live daemon run the very same stages, so both give the same events for the same frames
//! and seed.

pub mod clock;
pub mod queue;
pub mod stats;

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::error::{Error, Result};
use crate::event::Event;
use crate::frame::resize::Resized;
use crate::frame::{Frame, FrameSource};
use crate::sink::Sink;
use crate::stage1::{Stage1, Stage1Batch, Stage1Stats};
use crate::stage2::{SampleStats, Sampler};
use clock::{sleep_unless, Pacer};
use queue::{queue, QueuePolicy, QueueRx, QueueTx, Weight};
use stats::{Counters, Snapshot, Timing};

/// Opens the source again (a camera after a failure, a file to loop).
pub type Reopen = Box<dyn FnMut() -> Result<Box<dyn FrameSource>> + Send>;

/// Where frames come from and how they are read.
pub struct Source {
    /// The source, already open (its size fixes the pipeline's).
    pub first: Box<dyn FrameSource>,
    /// Opens it again; needed for `live` and `looped`.
    pub reopen: Option<Reopen>,
    /// A live camera: a read error reopens it with backoff instead of ending the run.
    pub live: bool,
    /// Start over at the end (times go on increasing).
    pub looped: bool,
    /// Replay at this multiple of real time (file sources); `None`: as fast as the pipeline
    /// takes the frames.
    pub pace: Option<f64>,
    /// First and longest wait between reopening attempts.
    pub backoff: (Duration, Duration),
}

impl Source {
    /// A file read as fast as the pipeline goes (offline conversion).
    pub fn file(first: Box<dyn FrameSource>) -> Self {
        Source {
            first,
            reopen: None,
            live: false,
            looped: false,
            pace: None,
            backoff: (Duration::from_millis(500), Duration::from_secs(10)),
        }
    }

    /// The frames' pace: a camera's is real time, a paced replay's its speed; an unpaced file
    /// has none (`None`).
    pub fn speed(&self) -> Option<f64> {
        if self.live {
            Some(1.0)
        } else {
            self.pace
        }
    }
}

/// The lag budget when no output holds events back (see [`Options::lag_budget`]).
pub const DEFAULT_LAG_BUDGET: Duration = Duration::from_millis(100);

/// How the pipeline runs.
#[derive(Debug, Clone)]
pub struct Options {
    /// What a full queue does.
    pub policy: QueuePolicy,
    /// Capacity of each queue, in frames.
    pub capacity: usize,
    /// Stop after this many frames.
    pub max_frames: Option<u64>,
    /// Stop after this long.
    pub duration: Option<Duration>,
    /// How often `on_tick` gets a snapshot.
    pub tick: Duration,
    /// When the run is stopped by `stop` (a signal), Stage 1 flushes what it holds only if one
    /// window is expected to take less than this (its median so far); `None`: always. A service
    /// manager waits a bounded time for a stop, and a window of the learned tier on a CPU can
    /// take longer.
    pub stop_flush_limit: Option<Duration>,
    /// Counters to update (shared with an HTTP listener); fresh ones when `None`.
    pub counters: Option<Arc<Counters>>,
    /// Under drop-oldest with a paced or live source and a tier that takes a frame at a time:
    /// a frame whose age plus what Stage 1 has lately been taking exceeds this, with a newer
    /// frame waiting, is skipped (counted as late) instead of simulated, so a machine that
    /// falls behind sheds frames before spending time on them. `None`: half the shortest
    /// emission delay of the outputs (the events must reach their output before it sends
    /// them), else [`DEFAULT_LAG_BUDGET`].
    pub lag_budget: Option<Duration>,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            policy: QueuePolicy::Block,
            capacity: 4,
            max_frames: None,
            duration: None,
            tick: Duration::from_secs(10),
            stop_flush_limit: None,
            lag_budget: None,
            counters: None,
        }
    }
}

/// Why the pipeline stopped.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum End {
    /// The source ended (a file read to its end).
    SourceEnded,
    /// The stop flag was raised (SIGINT / SIGTERM).
    Stopped,
    /// `max_frames` were read.
    MaxFrames,
    /// `duration` passed.
    Duration,
    /// The source failed and cannot be reopened (a file).
    SourceFailed(String),
    /// A stage failed, or every sink did.
    Failed(String),
}

impl End {
    /// Whether the run ended as asked (not by an error).
    pub fn is_clean(&self) -> bool {
        !matches!(self, End::SourceFailed(_) | End::Failed(_))
    }

    /// Words for the log.
    pub fn describe(&self) -> String {
        match self {
            End::SourceEnded => "the source ended".into(),
            End::Stopped => "stopped by a signal".into(),
            End::MaxFrames => "reached the frame limit".into(),
            End::Duration => "reached the time limit".into(),
            End::SourceFailed(e) => format!("the source failed: {e}"),
            End::Failed(e) => format!("failed: {e}"),
        }
    }
}

/// What a run did.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// Why it stopped.
    pub end: End,
    /// The counters at the end (the latency covers the whole run in `latency_total`).
    pub stats: Snapshot,
    /// Stage 1's counters (the tier, its window, the pixel model's or the network's counts).
    pub stage1: Stage1Stats,
    /// Voxel values the Stage 2 sampler had to repair (NaN, negative or huge values from a
    /// model; always zero for the physics tier).
    pub repaired: SampleStats,
    /// Time of the first and last frame read, us.
    pub first_t: Option<i64>,
    /// See `first_t`.
    pub last_t: Option<i64>,
}

struct Captured {
    frame: Frame,
    at: Instant,
    // Bumped each time a live source is reopened: Stage 1 starts over on a new generation.
    generation: u64,
}

struct Computed {
    batch: Stage1Batch,
    at: Instant,
}

/// One frame's events on their way to the sinks.
pub struct Batch {
    /// The events, in time order.
    pub events: Vec<Event>,
    /// When the frame that closed their interval was captured.
    pub at: Instant,
    /// That frame's time, us.
    pub end: i64,
}

impl Weight for Captured {
    /// A frame carries no events yet: its loss is a dropped frame, not dropped events.
    fn weight(&self) -> u64 {
        0
    }
}
impl Weight for Computed {
    fn weight(&self) -> u64 {
        self.batch.weight()
    }
}
impl Weight for Arc<Batch> {
    fn weight(&self) -> u64 {
        self.events.len() as u64
    }
}

struct Ctx<'a> {
    stop: &'a AtomicBool,
    halt: AtomicBool,
    /// Raised when the run stops early (a signal, `duration`, a failure): the sinks that wait
    /// stop waiting ([`Sink::stop_waiting_on`]).
    hurry: Arc<AtomicBool>,
    failure: Mutex<Option<String>>,
    counters: Arc<Counters>,
}

impl Ctx<'_> {
    fn stopping(&self) -> bool {
        self.stop.load(Ordering::Relaxed) || self.halt.load(Ordering::Relaxed)
    }

    fn fail(&self, message: String) {
        tracing::error!("{message}");
        let mut f = self.failure.lock().unwrap_or_else(|e| e.into_inner());
        f.get_or_insert(message);
        self.halt.store(true, Ordering::Relaxed);
    }
}

/// The built pieces the frames go through.
pub struct Stages {
    /// Stage 1, for frames of the source's size.
    pub stage1: Box<dyn Stage1>,
    /// Stage 2's sampler (used when Stage 1 hands over voxels).
    pub sampler: Box<dyn Sampler>,
    /// The outputs, for events of Stage 1's output size.
    pub sinks: Vec<Box<dyn Sink>>,
}

/// Runs `source` through the stages into the sinks until the source ends, `stop` is raised, a
/// limit is reached or something fails. `on_tick` gets a snapshot every `options.tick`.
/// The sinks are finished before this returns.
pub fn run(
    source: Source,
    stages: Stages,
    options: &Options,
    stop: &AtomicBool,
    on_tick: &mut dyn FnMut(&Snapshot),
) -> Result<Report> {
    let Stages {
        mut stage1,
        sampler,
        sinks,
    } = stages;
    if sinks.is_empty() {
        return Err(Error::invalid("sinks", "no output configured"));
    }
    let shed_after = shedding(&source, stage1.as_mut(), &sinks, options);
    let size = source.first.size();
    let counters = options
        .counters
        .clone()
        .unwrap_or_else(|| Arc::new(Counters::new()));
    let ctx = Ctx {
        stop,
        halt: AtomicBool::new(false),
        hurry: Arc::new(AtomicBool::new(false)),
        failure: Mutex::new(None),
        counters: counters.clone(),
    };
    let policy = options.policy;
    // Stage 1 takes frames a window at a time: while it runs the network on one window, the
    // next window's frames arrive, and its intervals then leave together. Every queue holds a
    // whole window on top of its capacity, so a drop-oldest policy drops only what a tier too
    // slow for the frame rate cannot take, never part of a window in flight.
    let burst = options.capacity + stage1.stats().window.saturating_sub(1);
    let (cap_tx, cap_rx, s) = queue::<Captured>("capture", burst, policy);
    counters.watch_queue(s);
    let (seq_tx, seq_rx, s) = queue::<Captured>("sequenced", burst, policy);
    counters.watch_queue(s);
    let (s1_tx, s1_rx, s) = queue::<Computed>("stage1", burst, policy);
    counters.watch_queue(s);
    let mut sink_txs = Vec::new();
    let mut sink_ends = Vec::new();
    for (i, sink) in sinks.into_iter().enumerate() {
        // A sink that holds events back (emission at event time) keeps that long's batches
        // queued, taking frames to come no closer than 10 ms (100 frames/s).
        let held = (sink.holds_back().as_secs_f64() / 0.010).ceil() as usize;
        let sink_policy = if sink.is_recording() {
            QueuePolicy::Block
        } else {
            policy
        };
        let (tx, rx, s) = queue::<Arc<Batch>>(&format!("sink{i}"), burst + held, sink_policy);
        counters.watch_queue(s.clone());
        let index = counters.add_sink(sink.describe(), sink.is_recording(), Some(s));
        sink_txs.push(tx);
        sink_ends.push((sink, rx, index));
    }
    let sink_count = sink_ends.len();
    let failed_sinks = AtomicUsize::new(0);
    let stage1_stats = Mutex::new(stage1.stats());
    let repaired = Mutex::new(SampleStats::default());
    let times = Mutex::new((None, None));

    let end = std::thread::scope(|scope| -> Result<End> {
        let mut handles = Vec::new();
        let ctx = &ctx;
        let capture = spawn_named(scope, "v2ce-capture".into(), {
            let times = &times;
            move || {
                let end = capture_stage(source, size, cap_tx, options, ctx, times);
                if matches!(end, End::Stopped | End::Duration) || ctx.stopping() {
                    ctx.hurry.store(true, Ordering::Relaxed);
                }
                end
            }
        })?;
        handles.push(spawn_named(scope, "v2ce-sequencer".into(), move || {
            sequencer_stage(cap_rx, seq_tx, ctx)
        })?);
        handles.push(spawn_named(scope, "v2ce-stage1".into(), {
            let stats = &stage1_stats;
            let limit = options.stop_flush_limit;
            move || stage1_stage(seq_rx, s1_tx, stage1, ctx, stats, limit, shed_after)
        })?);
        handles.push(spawn_named(scope, "v2ce-stage2".into(), {
            let repaired = &repaired;
            move || stage2_stage(s1_rx, sink_txs, sampler, ctx, repaired)
        })?);
        for (sink, rx, index) in sink_ends {
            let failed_sinks = &failed_sinks;
            handles.push(spawn_named(
                scope,
                format!("v2ce-sink{index}"),
                move || sink_stage(sink, rx, index, ctx, failed_sinks, sink_count),
            )?);
        }
        let mut next_tick = Instant::now() + options.tick;
        while !(capture.is_finished() && handles.iter().all(|h| h.is_finished())) {
            std::thread::sleep(Duration::from_millis(10));
            if Instant::now() >= next_tick {
                let mut snapshot = counters.snapshot();
                snapshot.stage1 = stage1_stats
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .record
                    .status();
                on_tick(&snapshot);
                next_tick += options.tick;
            }
        }
        let end = capture
            .join()
            .map_err(|_| Error::invalid("pipeline", "the capture thread panicked"))?;
        for h in handles {
            h.join()
                .map_err(|_| Error::invalid("pipeline", "a stage thread panicked"))?;
        }
        Ok(end)
    })?;
    let failure = ctx.failure.lock().unwrap_or_else(|e| e.into_inner()).take();
    let end = match failure {
        Some(message) => End::Failed(message),
        None => end,
    };
    let (first_t, last_t) = *times.lock().unwrap_or_else(|e| e.into_inner());
    let stage1 = stage1_stats.into_inner().unwrap_or_else(|e| e.into_inner());
    let repaired = repaired.into_inner().unwrap_or_else(|e| e.into_inner());
    Ok(Report {
        end,
        stats: counters.final_snapshot(),
        stage1,
        repaired,
        first_t,
        last_t,
    })
}

/// Sets up shedding for a live run that may drop frames, which sheds work in order as the
/// machine falls behind: Stage 1 first trades its own detail for time (`pace`: the physics
/// tier's sub-frames); then whole frames that would be late are skipped before Stage 1 spends
/// time on them (the lag budget this returns); last, full queues evict. Under `block`, which
/// loses nothing, it runs as offline and a slow machine lags instead. An offline source (read
/// as fast as Stage 1 takes it) lets Stage 1 look a frame ahead ([`Stage1::look_ahead`]); a
/// live one within the lag budget, where the outputs hold events back
/// ([`Stage1::look_ahead_within`]).
fn shedding(
    source: &Source,
    stage1: &mut dyn Stage1,
    sinks: &[Box<dyn Sink>],
    options: &Options,
) -> Option<Duration> {
    if source.speed().is_none() {
        stage1.look_ahead();
    }
    let (QueuePolicy::DropOldest, Some(speed)) = (options.policy, source.speed()) else {
        return None;
    };
    stage1.pace(speed);
    if stage1.stats().window > 1 {
        return None;
    }
    let held_back = sinks
        .iter()
        .map(|s| s.holds_back())
        .filter(|d| !d.is_zero())
        .min();
    // Events held back by every output (or a budget of lateness the user set) leave room
    // for Stage 1 to hold a frame within the budget: the events are still ready before the
    // outputs send them (the budget is half their shortest delay). Outputs that send as
    // soon as they can get every interval without that wait.
    if let Some(budget) = options.lag_budget.or(held_back.map(|d| d / 2)) {
        stage1.look_ahead_within(budget);
    }
    Some(
        options
            .lag_budget
            .unwrap_or_else(|| held_back.map_or(DEFAULT_LAG_BUDGET, |d| d / 2)),
    )
}

/// Starts a named thread in `scope`.
fn spawn_named<'scope, T: Send + 'scope>(
    scope: &'scope std::thread::Scope<'scope, '_>,
    name: String,
    f: impl FnOnce() -> T + Send + 'scope,
) -> Result<std::thread::ScopedJoinHandle<'scope, T>> {
    std::thread::Builder::new()
        .name(name)
        .spawn_scoped(scope, f)
        .map_err(|e| Error::invalid("thread", e.to_string()))
}

fn capture_stage(
    source: Source,
    size: (u16, u16),
    tx: QueueTx<Captured>,
    options: &Options,
    ctx: &Ctx,
    times: &Mutex<(Option<i64>, Option<i64>)>,
) -> End {
    // The replay clock's speed (cameras: 1); unpaced files have no clock to lag behind.
    let clock_speed = source.speed();
    let Source {
        first,
        mut reopen,
        live,
        looped,
        pace,
        backoff,
    } = source;
    let mut current = first;
    let mut pacer = pace.map(Pacer::new);
    let deadline = options.duration.map(|d| Instant::now() + d);
    let past_deadline = || deadline.is_some_and(|d| Instant::now() >= d);
    // Waits (a paced replay, a reopening camera) end at a stop and at the deadline alike.
    let stopping = || ctx.stopping() || past_deadline();
    let cut_short = || {
        if ctx.stopping() {
            End::Stopped
        } else {
            End::Duration
        }
    };
    let mut frames = 0u64;
    let mut generation = 0u64;
    let (mut offset, mut period, mut realign) = (0i64, 0i64, false);
    let mut last_t: Option<i64> = None;
    let mut lag_anchor: Option<(i64, Instant)> = None;
    let mut refused_seen = 0u64;
    loop {
        if ctx.stopping() {
            return End::Stopped;
        }
        if options.max_frames.is_some_and(|m| frames >= m) {
            return End::MaxFrames;
        }
        if past_deadline() {
            return End::Duration;
        }
        let read = current.next_frame();
        let refused = current.refused();
        if refused > refused_seen {
            ctx.counters
                .source_refused
                .fetch_add(refused - refused_seen, Ordering::Relaxed);
        }
        refused_seen = refused;
        match read {
            Ok(Some(mut frame)) => {
                if realign {
                    // A looped replay goes on one frame period after the last frame.
                    offset = last_t.map_or(0, |l| l + period.max(1) - frame.t);
                    realign = false;
                }
                frame.t += offset;
                if let Some(p) = pacer.as_mut() {
                    if !p.wait(frame.t, &stopping) {
                        return cut_short();
                    }
                }
                if let Some(l) = last_t {
                    if frame.t > l {
                        period = frame.t - l;
                    }
                }
                last_t = Some(frame.t);
                {
                    let mut t = times.lock().unwrap_or_else(|e| e.into_inner());
                    t.0.get_or_insert(frame.t);
                    t.1 = Some(frame.t);
                }
                frames += 1;
                ctx.counters.frame_read();
                let at = Instant::now();
                // How far the capture is behind the frame's own time on the source's clock
                // (anchored on its first frame; a camera's clock runs at 1x).
                if let Some(speed) = clock_speed {
                    let (t0, a0) = *lag_anchor.get_or_insert((frame.t, at));
                    let due = a0
                        + Duration::from_secs_f64(
                            ((frame.t - t0).max(0) as f64 / 1e6 / speed).min(1e9),
                        );
                    ctx.counters
                        .record(Timing::CaptureLag, at.saturating_duration_since(due));
                }
                let item = Captured {
                    frame,
                    at,
                    generation,
                };
                if tx.push(item).is_err() {
                    // The next stage has gone, having recorded why.
                    return End::Stopped;
                }
            }
            Ok(None) if looped => match reopen.as_mut().map(|r| open_sized(r, size)) {
                Some(Ok(source)) => {
                    tracing::info!("replay looped: {}", source.describe());
                    Counters::bump(&ctx.counters.source_restarts);
                    current = source;
                    realign = true;
                }
                Some(Err(e)) => return End::SourceFailed(format!("reopening to loop: {e}")),
                None => return End::SourceEnded,
            },
            Ok(None) if !live => return End::SourceEnded,
            Err(e) if !live => return End::SourceFailed(e.to_string()),
            other => {
                let why = match other {
                    Err(e) => e.to_string(),
                    _ => "the stream ended".to_string(),
                };
                tracing::warn!("{}: {why}; reopening", current.describe());
                let Some(r) = reopen.as_mut() else {
                    return End::SourceFailed(why);
                };
                let mut wait = backoff.0;
                current = loop {
                    if !sleep_unless(wait, &stopping) {
                        return cut_short();
                    }
                    match open_sized(r, size) {
                        Ok(s) => {
                            tracing::info!("source back: {}", s.describe());
                            break s;
                        }
                        Err(e) => {
                            wait = (wait * 2).min(backoff.1);
                            tracing::warn!("reopening failed: {e}; next try in {wait:?}");
                        }
                    }
                };
                generation += 1;
                lag_anchor = None;
                Counters::bump(&ctx.counters.source_restarts);
                if let Some(p) = pacer.as_mut() {
                    *p = Pacer::new(pace.unwrap_or(1.0));
                }
            }
        }
    }
}

fn open_sized(reopen: &mut Reopen, size: (u16, u16)) -> Result<Box<dyn FrameSource>> {
    let source = reopen()?;
    if source.size() == size {
        return Ok(source);
    }
    Ok(Box::new(Resized::new(source, size)?))
}

fn sequencer_stage(rx: QueueRx<Captured>, tx: QueueTx<Captured>, ctx: &Ctx) {
    let mut last: Option<i64> = None;
    while let Some(item) = rx.recv() {
        if let Some(l) = last {
            if item.frame.t <= l {
                let n = ctx
                    .counters
                    .frames_out_of_order
                    .fetch_add(1, Ordering::Relaxed);
                if n == 0 || n.is_power_of_two() {
                    tracing::warn!(
                        "frame at {} us does not come after {} us: dropped ({} so far)",
                        item.frame.t,
                        l,
                        n + 1
                    );
                }
                continue;
            }
        }
        last = Some(item.frame.t);
        if tx.push(item).is_err() {
            return;
        }
    }
}

/// Capture instants of the newest frames, to time each batch from the frame that closed it.
const ARRIVALS_KEPT: usize = 512;

fn stage1_stage(
    rx: QueueRx<Captured>,
    tx: QueueTx<Computed>,
    mut stage1: Box<dyn Stage1>,
    ctx: &Ctx,
    stats: &Mutex<Stage1Stats>,
    stop_flush_limit: Option<Duration>,
    shed_after: Option<Duration>,
) {
    let mut generation = 0;
    let mut took = Duration::ZERO;
    let mut batches: Vec<Stage1Batch> = Vec::new();
    let mut arrivals: VecDeque<(i64, Instant)> = VecDeque::new();
    // Hands the batches on; false when the next stage has gone.
    let send = |batches: &mut Vec<Stage1Batch>, arrivals: &VecDeque<(i64, Instant)>| {
        for batch in batches.drain(..) {
            let end = batch.end();
            let at = arrivals
                .iter()
                .rev()
                .find(|(t, _)| *t == end)
                .map_or_else(Instant::now, |(_, at)| *at);
            if tx.push(Computed { batch, at }).is_err() {
                return false;
            }
        }
        true
    };
    let publish = |stage1: &dyn Stage1| {
        let s = stage1.stats();
        ctx.counters.set_stage1(s.clone());
        *stats.lock().unwrap_or_else(|e| e.into_inner()) = s;
    };
    while let Some(item) = rx.recv() {
        // Too old to be on time once simulated (its age plus what Stage 1 has been taking),
        // and a newer frame waits: skipped, its interval folded into the next (the pixel model
        // integrates over the longer interval).
        if let Some(budget) = shed_after {
            if item.generation == generation && !rx.is_empty() && item.at.elapsed() + took > budget
            {
                Counters::bump(&ctx.counters.frames_late);
                continue;
            }
        }
        if item.generation != generation {
            generation = item.generation;
            // What the tier holds from before the break goes on; then it starts over.
            let flushed = stage1.finish(&mut batches);
            if !send(&mut batches, &arrivals) {
                return;
            }
            if let Err(e) = flushed.and_then(|()| stage1.restart()) {
                return ctx.fail(format!("Stage 1: {e}"));
            }
        }
        arrivals.push_back((item.frame.t, item.at));
        if arrivals.len() > ARRIVALS_KEPT {
            arrivals.pop_front();
        }
        let started = Instant::now();
        if let Err(e) = stage1.push(&item.frame, &mut batches) {
            return ctx.fail(format!("Stage 1 at {} us: {e}", item.frame.t));
        }
        // What a frame has been taking lately (a smoothed wall time: the machine's load in it).
        took = (took * 3 + started.elapsed()) / 4;
        Counters::bump(&ctx.counters.frames_processed);
        publish(stage1.as_ref());
        if !send(&mut batches, &arrivals) {
            return;
        }
    }
    // The end of the stream (or a stop): what is held still goes out, unless a stop must not
    // wait for a slow window.
    let s = stage1.stats();
    let window = Duration::from_secs_f64(s.window_ms_p50 / 1e3);
    if ctx.stop.load(Ordering::Relaxed) && stop_flush_limit.is_some_and(|limit| window > limit) {
        tracing::warn!(
            "stopping: the intervals held for the next window are dropped (a window takes \
             about {:.1} s, longer than a stop may wait)",
            window.as_secs_f64()
        );
        return;
    }
    let flushed = stage1.finish(&mut batches);
    publish(stage1.as_ref());
    if !send(&mut batches, &arrivals) {
        return;
    }
    if let Err(e) = flushed {
        ctx.fail(format!("Stage 1 at the end of the stream: {e}"));
    }
}

fn stage2_stage(
    rx: QueueRx<Computed>,
    sinks: Vec<QueueTx<Arc<Batch>>>,
    sampler: Box<dyn Sampler>,
    ctx: &Ctx,
    repaired: &Mutex<SampleStats>,
) {
    while let Some(item) = rx.recv() {
        let end = item.batch.end();
        let (events, r) = crate::stage2::events_of(item.batch, sampler.as_ref());
        if r.any() {
            let mut total = repaired.lock().unwrap_or_else(|e| e.into_inner());
            if !total.any() {
                tracing::warn!(
                    "Stage 2 repaired voxel values from Stage 1 ({} non-finite, {} negative, {} \
                     clamped in the interval ending at {end} us); counted in the report",
                    r.nonfinite,
                    r.negative,
                    r.clamped,
                );
            }
            total.add(r);
        }
        ctx.counters
            .events_out
            .fetch_add(events.len() as u64, Ordering::Relaxed);
        ctx.counters.record(Timing::Processing, item.at.elapsed());
        let batch = Arc::new(Batch {
            events,
            at: item.at,
            end,
        });
        let mut delivered = false;
        for tx in &sinks {
            delivered |= tx.push(batch.clone()).is_ok();
        }
        if !delivered {
            return;
        }
    }
}

fn sink_stage(
    mut sink: Box<dyn Sink>,
    rx: QueueRx<Arc<Batch>>,
    index: usize,
    ctx: &Ctx,
    failed_sinks: &AtomicUsize,
    sink_count: usize,
) {
    // Events handed to this sink. After a failure every one not sent is counted as dropped
    // (the failed batch and all drained after it), so the report does not say "0 dropped".
    sink.stop_waiting_on(ctx.hurry.clone());
    let mut handed = 0u64;
    let mut failed: Option<String> = None;
    let after_failure = |sink: &dyn Sink, handed: u64| {
        let mut stats = sink.stats();
        stats.events_in = handed;
        stats.events_dropped = handed.saturating_sub(stats.events_sent);
        stats
    };
    let fail = |sink: &dyn Sink, what: &str, e: Error, handed: u64| {
        let message = format!("{}: {what}: {e}", sink.describe());
        tracing::error!("{message}; the other outputs go on");
        ctx.counters
            .update_sink(index, after_failure(sink, handed), Some(message.clone()));
        if failed_sinks.fetch_add(1, Ordering::Relaxed) + 1 == sink_count {
            ctx.fail(format!("every output failed (last: {message})"));
        }
        message
    };
    while let Some(batch) = rx.recv() {
        let received = Instant::now();
        handed += batch.events.len() as u64;
        if let Some(message) = &failed {
            // Drained, so the stages upstream never wait on a dead output.
            if !batch.events.is_empty() {
                let stats = after_failure(sink.as_ref(), handed);
                ctx.counters
                    .update_sink(index, stats, Some(message.clone()));
            }
            continue;
        }
        if !batch.events.is_empty() {
            let closed_by = crate::sink::ClosedBy {
                t: batch.end,
                captured: batch.at,
            };
            if let Err(e) = sink.send_closed(&batch.events, closed_by) {
                failed = Some(fail(sink.as_ref(), "send failed", e, handed));
                continue;
            }
        }
        if sink.counts_latency() {
            ctx.counters.record(Timing::Emission, received.elapsed());
            ctx.counters.record_latency(batch.at.elapsed());
        }
        ctx.counters.update_sink(index, sink.stats(), None);
    }
    if failed.is_none() {
        match sink.finish() {
            Ok(()) => ctx.counters.update_sink(index, sink.stats(), None),
            Err(e) => {
                fail(sink.as_ref(), "closing failed", e, handed);
            }
        }
    }
}

#[cfg(test)]
mod tests;
#[cfg(test)]
mod timing_tests;
