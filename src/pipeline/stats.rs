//! The pipeline's counters and latency histograms, and the snapshots the daemon logs and
//! reports to systemd.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;
use serde::Serialize;

use super::queue::QueueStats;
use crate::sink::SinkStats;

/// Read from [`crate::process`], where it lives; named here too for the daemon's stats.
pub use crate::process::ProcessUsage;

/// Shared counters, updated by the stage threads.
pub struct Counters {
    started: Instant,
    /// Frames read from the source.
    pub frames_in: AtomicU64,
    /// Frames the sequencer rejected (a time not after the previous frame's).
    pub frames_out_of_order: AtomicU64,
    /// Frames Stage 1 skipped because they were already older than the lag budget (a live
    /// run falling behind; see [`crate::pipeline::Options::lag_budget`]).
    pub frames_late: AtomicU64,
    /// Frames through Stage 1.
    pub frames_processed: AtomicU64,
    /// Events handed to the sinks.
    pub events_out: AtomicU64,
    /// Times the source was reopened (a camera that came back, a replay that looped).
    pub source_restarts: AtomicU64,
    /// Messages the source refused (a ROS 2 image that does not decode, whose fields disagree,
    /// whose size changed or whose stamp went back), the stream going on.
    pub source_refused: AtomicU64,
    latency: Mutex<LatencyPair>,
    capture_lag: Mutex<LatencyPair>,
    processing: Mutex<LatencyPair>,
    emission: Mutex<LatencyPair>,
    queues: Mutex<Vec<Arc<QueueStats>>>,
    sinks: Mutex<Vec<SinkSnapshot>>,
    /// Each sink's queue, whose evictions are that sink's losses.
    sink_queues: Mutex<Vec<Option<Arc<QueueStats>>>>,
    last: Mutex<Option<Mark>>,
    /// Microseconds from `started` to the last frame read, plus one (0: none yet).
    last_frame_us: AtomicU64,
    stage1: Mutex<Option<crate::stage1::Stage1Stats>>,
}

struct LatencyPair {
    interval: Histogram<u64>,
    total: Histogram<u64>,
}

impl LatencyPair {
    fn new() -> Mutex<Self> {
        Mutex::new(LatencyPair {
            interval: histogram(),
            total: histogram(),
        })
    }

    fn record(m: &Mutex<Self>, d: Duration) {
        let us = d.as_micros().min(u64::MAX as u128) as u64;
        let mut l = lock(m);
        l.interval.saturating_record(us.max(1));
        l.total.saturating_record(us.max(1));
    }

    /// The interval's and the whole run's percentiles; starts a new interval when `advance`.
    fn take(m: &Mutex<Self>, advance: bool) -> (Latency, Latency) {
        let mut l = lock(m);
        let pair = (Latency::of(&l.interval), Latency::of(&l.total));
        if advance {
            l.interval.reset();
        }
        pair
    }
}

/// A latency histogram over the whole run in cumulative buckets (the Prometheus form).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Buckets {
    /// (upper bound in seconds, samples at or below it), bounds increasing.
    pub buckets: Vec<(f64, u64)>,
    /// Samples.
    pub count: u64,
    /// Sum of the samples, seconds (from the histogram: 3 significant digits).
    pub sum_s: f64,
}

/// Which part of a frame's way a duration measures (see [`Counters::record`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Timing {
    /// From the frame's own time (mapped onto the wall clock at the first frame: the replay
    /// clock for a file, the driver's clock for a camera) to its capture: lag inside the source.
    CaptureLag,
    /// From the capture to the interval's events leaving Stage 2 for the sinks.
    Processing,
    /// From a batch reaching a sink to its last event having left (for emission at event
    /// time: the wait for the events' own times).
    Emission,
    /// From the capture to the events having left (one sample per frame and sink).
    Latency,
}

// The state at the previous snapshot, for rates.
#[derive(Clone, Copy)]
struct Mark {
    at: Instant,
    events_out: u64,
    frames_in: u64,
    cpu_s: f64,
}

/// Latency percentiles in milliseconds.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq)]
pub struct Latency {
    /// Samples (one per frame and sink).
    pub count: u64,
    /// Median.
    pub p50_ms: f64,
    /// 90th percentile.
    pub p90_ms: f64,
    /// 99th percentile.
    pub p99_ms: f64,
    /// Largest.
    pub max_ms: f64,
}

impl Latency {
    pub(crate) fn of(h: &Histogram<u64>) -> Self {
        if h.is_empty() {
            return Latency::default();
        }
        let ms = |us: u64| us as f64 / 1000.0;
        Latency {
            count: h.len(),
            p50_ms: ms(h.value_at_quantile(0.5)),
            p90_ms: ms(h.value_at_quantile(0.9)),
            p99_ms: ms(h.value_at_quantile(0.99)),
            max_ms: ms(h.max()),
        }
    }
}

/// One queue's state.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct QueueSnapshot {
    /// Its name.
    pub name: String,
    /// Items waiting.
    pub depth: usize,
    /// Capacity.
    pub capacity: usize,
    /// Items evicted so far (drop-oldest).
    pub dropped: u64,
    /// Events in the evicted items.
    pub dropped_events: u64,
}

/// One sink's state.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct SinkSnapshot {
    /// What it is.
    pub sink: String,
    /// A recording (a file), whose queue never evicts.
    pub recording: bool,
    /// Its counters.
    pub stats: SinkStats,
    /// Why it stopped, if it failed.
    pub failed: Option<String>,
}

/// The pipeline at one moment.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Snapshot {
    /// Seconds since the start.
    pub uptime_s: f64,
    /// Frames read from the source.
    pub frames_in: u64,
    /// Frames through Stage 1.
    pub frames_processed: u64,
    /// Frames evicted from the frame queues (drop-oldest), skipped as too late, or rejected as
    /// out of order.
    pub frames_dropped: u64,
    /// Of those, rejected as out of order.
    pub frames_out_of_order: u64,
    /// Of those, skipped before Stage 1 as older than the lag budget.
    pub frames_late: u64,
    /// Times the source was reopened.
    pub source_restarts: u64,
    /// Messages the source refused (see [`Counters::source_refused`]).
    pub source_refused: u64,
    /// Events handed to the sinks.
    pub events_out: u64,
    /// Events per second since the previous snapshot.
    pub events_per_s: f64,
    /// Frames per second read since the previous snapshot.
    pub frames_per_s: f64,
    /// Queue depths and drops.
    pub queues: Vec<QueueSnapshot>,
    /// Capture-to-send latency since the previous snapshot.
    pub latency: Latency,
    /// Capture-to-send latency since the start.
    pub latency_total: Latency,
    /// Lag of the capture behind the frames' own times since the previous snapshot (grows when
    /// a source falls behind real time).
    pub capture_lag: Latency,
    /// The same since the start.
    pub capture_lag_total: Latency,
    /// Capture to the end of Stage 2, since the start.
    pub processing_total: Latency,
    /// A batch's time in a sink until its last event left, since the start.
    pub emission_total: Latency,
    /// The sinks.
    pub sinks: Vec<SinkSnapshot>,
    /// Process CPU time (user + system), seconds.
    pub cpu_s: f64,
    /// Process CPU use since the previous snapshot, percent of one core.
    pub cpu_percent: f64,
    /// Resident memory now, KiB.
    pub rss_kib: u64,
    /// Peak resident memory, KiB.
    pub max_rss_kib: u64,
    /// How Stage 1 stands (its tier's status: the physics tier's sub-frame cap), where the
    /// pipeline filled it in.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stage1: Option<crate::stage1::TierStatus>,
}

impl Snapshot {
    /// One log line: frames, drops, rates, queues, latency.
    pub fn line(&self) -> String {
        let queues: Vec<String> = self
            .queues
            .iter()
            .map(|q| format!("{}={}/{}", q.name, q.depth, q.capacity))
            .collect();
        let l = &self.latency;
        format!(
            "frames in {} (dropped {}), {:.1} frames/s, {:.0} events/s, {} events; queues {}; \
             latency p50 {:.1} ms p90 {:.1} ms p99 {:.1} ms max {:.1} ms; capture lag p99 {:.1} \
             ms; cpu {:.0}%, rss {} MiB{}",
            self.frames_in,
            self.frames_dropped,
            self.frames_per_s,
            self.events_per_s,
            self.events_out,
            queues.join(" "),
            l.p50_ms,
            l.p90_ms,
            l.p99_ms,
            l.max_ms,
            self.capture_lag.p99_ms,
            self.cpu_percent,
            self.rss_kib / 1024,
            self.stage1
                .as_ref()
                .map(|s| format!("; stage 1: {}", s.line))
                .unwrap_or_default()
        )
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A stage that panicked while holding a lock left only counters behind: keep using them.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

fn histogram() -> Histogram<u64> {
    // 1 us .. 1 hour at 3 significant digits; `saturating_record` clamps outliers.
    Histogram::new_with_bounds(1, 3_600_000_000, 3).expect("constant, valid histogram bounds")
}

impl std::fmt::Debug for Counters {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Counters")
            .field("frames_in", &self.frames_in)
            .field("events_out", &self.events_out)
            .finish_non_exhaustive()
    }
}

impl Default for Counters {
    fn default() -> Self {
        Self::new()
    }
}

impl Counters {
    /// Fresh counters; the uptime starts now.
    pub fn new() -> Self {
        Counters {
            started: Instant::now(),
            frames_in: AtomicU64::new(0),
            frames_out_of_order: AtomicU64::new(0),
            frames_late: AtomicU64::new(0),
            frames_processed: AtomicU64::new(0),
            events_out: AtomicU64::new(0),
            source_restarts: AtomicU64::new(0),
            source_refused: AtomicU64::new(0),
            latency: LatencyPair::new(),
            capture_lag: LatencyPair::new(),
            processing: LatencyPair::new(),
            emission: LatencyPair::new(),
            queues: Mutex::new(Vec::new()),
            sinks: Mutex::new(Vec::new()),
            sink_queues: Mutex::new(Vec::new()),
            last: Mutex::new(None),
            last_frame_us: AtomicU64::new(0),
            stage1: Mutex::new(None),
        }
    }

    /// Counts a frame read from the source, and when.
    pub fn frame_read(&self) {
        self.frames_in.fetch_add(1, Ordering::Relaxed);
        let us = self.started.elapsed().as_micros().min(u64::MAX as u128 - 1) as u64;
        self.last_frame_us.store(us + 1, Ordering::Relaxed);
    }

    /// How long ago the last frame was read (`None` before the first).
    pub fn last_frame_age(&self) -> Option<Duration> {
        match self.last_frame_us.load(Ordering::Relaxed) {
            0 => None,
            us => Some(
                self.started
                    .elapsed()
                    .saturating_sub(Duration::from_micros(us - 1)),
            ),
        }
    }

    /// Publishes Stage 1's counters (the Stage 1 thread, now and then).
    pub fn set_stage1(&self, stats: crate::stage1::Stage1Stats) {
        *lock(&self.stage1) = Some(stats);
    }

    /// Stage 1's counters as last published.
    pub fn stage1(&self) -> crate::stage1::Stage1Stats {
        lock(&self.stage1).clone().unwrap_or_default()
    }

    /// The whole run's histogram of `timing` in cumulative buckets with upper `bounds_s`.
    pub fn histogram(&self, timing: Timing, bounds_s: &[f64]) -> Buckets {
        let l = lock(self.pair(timing));
        let h = &l.total;
        let buckets = bounds_s
            .iter()
            .map(|&b| {
                let us = (b * 1e6) as u64;
                let count = if h.is_empty() {
                    0
                } else {
                    h.count_between(0, us.min(h.high()))
                };
                (b, count)
            })
            .collect();
        Buckets {
            buckets,
            count: h.len(),
            sum_s: h.mean() * h.len() as f64 / 1e6,
        }
    }

    fn pair(&self, timing: Timing) -> &Mutex<LatencyPair> {
        match timing {
            Timing::CaptureLag => &self.capture_lag,
            Timing::Processing => &self.processing,
            Timing::Emission => &self.emission,
            Timing::Latency => &self.latency,
        }
    }

    /// Adds 1 to a counter.
    pub fn bump(counter: &AtomicU64) {
        counter.fetch_add(1, Ordering::Relaxed);
    }

    /// Registers a queue for the snapshots.
    pub fn watch_queue(&self, q: Arc<QueueStats>) {
        lock(&self.queues).push(q);
    }

    /// Registers a sink (a recording or not, see [`crate::sink::Sink::is_recording`]) fed by
    /// `queue`, whose evictions count as its losses; returns its index for
    /// [`Counters::update_sink`].
    pub fn add_sink(
        &self,
        describe: String,
        recording: bool,
        queue: Option<Arc<QueueStats>>,
    ) -> usize {
        let mut sinks = lock(&self.sinks);
        sinks.push(SinkSnapshot {
            sink: describe,
            recording,
            stats: SinkStats::default(),
            failed: None,
        });
        lock(&self.sink_queues).push(queue);
        sinks.len() - 1
    }

    /// Every sink's state, its queue's evictions counted among what it was given and lost.
    fn sinks(&self) -> Vec<SinkSnapshot> {
        let mut sinks = lock(&self.sinks).clone();
        for (s, q) in sinks.iter_mut().zip(lock(&self.sink_queues).iter()) {
            let evicted = q.as_ref().map_or(0, |q| q.dropped_weight());
            s.stats.events_evicted = evicted;
            s.stats.events_in += evicted;
            s.stats.events_dropped += evicted;
        }
        sinks
    }

    /// Publishes a sink's counters (and its failure).
    pub fn update_sink(&self, index: usize, stats: SinkStats, failed: Option<String>) {
        if let Some(s) = lock(&self.sinks).get_mut(index) {
            s.stats = stats;
            if failed.is_some() {
                s.failed = failed;
            }
        }
    }

    /// The first failed sink's failure, if any (without building a whole snapshot).
    pub fn failed_sink(&self) -> Option<String> {
        lock(&self.sinks).iter().find_map(|s| s.failed.clone())
    }

    /// Records one capture-to-send latency.
    pub fn record_latency(&self, latency: Duration) {
        self.record(Timing::Latency, latency);
    }

    /// Records one duration of `timing`.
    pub fn record(&self, timing: Timing, d: Duration) {
        LatencyPair::record(self.pair(timing), d);
    }

    /// The state now, with rates over the whole run (the final report).
    pub fn final_snapshot(&self) -> Snapshot {
        lock(&self.last).take();
        self.snapshot()
    }

    /// The state now; rates and the interval latency cover the time since the previous call.
    pub fn snapshot(&self) -> Snapshot {
        self.state(true)
    }

    /// The state now, leaving the interval of [`Counters::snapshot`] alone (an HTTP scrape
    /// between two stats lines): rates and interval latency since the previous snapshot.
    pub fn peek(&self) -> Snapshot {
        self.state(false)
    }

    fn state(&self, advance: bool) -> Snapshot {
        let now = Instant::now();
        let usage = ProcessUsage::now();
        let (latency, latency_total) = LatencyPair::take(&self.latency, advance);
        let (capture_lag, capture_lag_total) = LatencyPair::take(&self.capture_lag, advance);
        let (_, processing_total) = LatencyPair::take(&self.processing, advance);
        let (_, emission_total) = LatencyPair::take(&self.emission, advance);
        let queues: Vec<QueueSnapshot> = lock(&self.queues)
            .iter()
            .map(|q| QueueSnapshot {
                name: q.name.clone(),
                depth: q.depth(),
                capacity: q.capacity,
                dropped: q.dropped(),
                dropped_events: q.dropped_weight(),
            })
            .collect();
        let frames_in = self.frames_in.load(Ordering::Relaxed);
        let events_out = self.events_out.load(Ordering::Relaxed);
        let out_of_order = self.frames_out_of_order.load(Ordering::Relaxed);
        let late = self.frames_late.load(Ordering::Relaxed);
        // Frames are lost in the queues before the sinks (a sink queue loses events instead).
        let frames_evicted: u64 = queues
            .iter()
            .filter(|q| !q.name.starts_with("sink"))
            .map(|q| q.dropped)
            .sum();
        let mark = Mark {
            at: now,
            events_out,
            frames_in,
            cpu_s: usage.cpu_s,
        };
        let mut last = lock(&self.last);
        let previous = if advance { last.replace(mark) } else { *last }.unwrap_or(Mark {
            at: self.started,
            events_out: 0,
            frames_in: 0,
            cpu_s: 0.0,
        });
        drop(last);
        let dt = (now - previous.at).as_secs_f64().max(1e-9);
        Snapshot {
            uptime_s: (now - self.started).as_secs_f64(),
            frames_in,
            frames_processed: self.frames_processed.load(Ordering::Relaxed),
            frames_dropped: frames_evicted + out_of_order + late,
            frames_out_of_order: out_of_order,
            frames_late: late,
            source_restarts: self.source_restarts.load(Ordering::Relaxed),
            source_refused: self.source_refused.load(Ordering::Relaxed),
            events_out,
            events_per_s: (events_out - previous.events_out) as f64 / dt,
            frames_per_s: (frames_in - previous.frames_in) as f64 / dt,
            queues,
            latency,
            latency_total,
            capture_lag,
            capture_lag_total,
            processing_total,
            emission_total,
            sinks: self.sinks(),
            cpu_s: usage.cpu_s,
            cpu_percent: 100.0 * (usage.cpu_s - previous.cpu_s) / dt,
            rss_kib: usage.rss_kib,
            max_rss_kib: usage.max_rss_kib,
            stage1: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latency_percentiles_and_interval_reset() {
        let c = Counters::new();
        for ms in 1..=100 {
            c.record_latency(Duration::from_millis(ms));
        }
        let s = c.snapshot();
        assert_eq!(s.latency.count, 100);
        assert!((s.latency.p50_ms - 50.0).abs() < 0.1, "{:?}", s.latency);
        assert!((s.latency.p99_ms - 99.0).abs() < 0.1, "{:?}", s.latency);
        assert!((s.latency.max_ms - 100.0).abs() < 0.1, "{:?}", s.latency);
        c.record_latency(Duration::from_millis(5));
        let s = c.snapshot();
        assert_eq!(s.latency.count, 1);
        assert_eq!(s.latency_total.count, 101);
    }
}
