//! The `/metrics` text: the pipeline's counters in the Prometheus exposition format 0.0.4,
//! one family after another, each with its help and type lines.

use std::fmt::{Display, Write as _};

use super::Status;
use crate::pipeline::stats::{QueueSnapshot, SinkSnapshot, Snapshot, Timing};

/// Bucket bounds of the latency histograms, seconds.
pub const BUCKETS_S: [f64; 14] = [
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

/// A label value escaped for the exposition format.
fn label(v: &str) -> String {
    v.replace('\\', "\\\\")
        .replace('"', "\\\"")
        .replace('\n', "\\n")
}

/// The text being written.
struct Exposition(String);

impl Exposition {
    /// A family's help and type lines.
    fn family(&mut self, name: &str, kind: &str, help: &str) {
        let _ = writeln!(self.0, "# HELP {name} {help}\n# TYPE {name} {kind}");
    }

    /// One sample; `labels` is `key="value"` pairs already escaped, comma-separated (or empty).
    fn sample(&mut self, name: &str, labels: &str, value: impl Display) {
        if labels.is_empty() {
            let _ = writeln!(self.0, "{name} {value}");
        } else {
            let _ = writeln!(self.0, "{name}{{{labels}}} {value}");
        }
    }

    /// A family of one unlabelled sample.
    fn single(&mut self, name: &str, kind: &str, help: &str, value: impl Display) {
        self.family(name, kind, help);
        self.sample(name, "", value);
    }
}

/// The `/metrics` text.
pub fn metrics(status: &Status) -> String {
    let s = status.counters.peek();
    let mut x = Exposition(String::with_capacity(8192));
    pipeline(&mut x, &s);
    sinks(&mut x, &s.sinks);
    queues(&mut x, &s.queues);
    timings(&mut x, status);
    stage1(&mut x, status);
    process(&mut x, &s, status);
    listener(&mut x, status);
    x.0
}

/// What the listener turned away or cut off.
fn listener(x: &mut Exposition, status: &Status) {
    let l = &status.listener;
    let name = "v2ce_http_connections_total";
    x.family(
        name,
        "counter",
        "Connections to this listener, by result: accepted, refused (at the connection cap, no half-open one to evict), evicted (half-open at the cap, the oldest first, for a new one), timed_out (head, exchange or stalled stream), accept_error.",
    );
    let get = |a: &std::sync::atomic::AtomicU64| a.load(std::sync::atomic::Ordering::Relaxed);
    x.sample(name, "result=\"accepted\"", get(&l.accepted));
    x.sample(name, "result=\"refused\"", get(&l.refused));
    x.sample(name, "result=\"evicted\"", get(&l.evicted));
    x.sample(name, "result=\"timed_out\"", get(&l.timed_out));
    x.sample(name, "result=\"accept_error\"", get(&l.accept_errors));
    x.single(
        "v2ce_http_rejected_requests_total",
        "counter",
        "Requests refused: a method other than GET or HEAD, a request body, too many preview streams.",
        get(&l.rejected),
    );
    x.single(
        "v2ce_http_preview_frames_total",
        "counter",
        "Preview frames drawn and encoded for the page: one per push and accumulation window, however many pages show it.",
        get(&l.preview_frames),
    );
}

/// Frames and events through the pipeline.
fn pipeline(x: &mut Exposition, s: &Snapshot) {
    x.single(
        "v2ce_frames_total",
        "counter",
        "Frames read from the source.",
        s.frames_in,
    );
    x.single(
        "v2ce_frames_processed_total",
        "counter",
        "Frames through Stage 1.",
        s.frames_processed,
    );
    x.family(
        "v2ce_frames_dropped_total",
        "counter",
        "Frames dropped, by cause: evicted from a full queue, skipped before Stage 1 as older than the lag budget (late), or out of order.",
    );
    let name = "v2ce_frames_dropped_total";
    let queue = s
        .frames_dropped
        .saturating_sub(s.frames_out_of_order + s.frames_late);
    x.sample(name, "cause=\"queue\"", queue);
    x.sample(name, "cause=\"late\"", s.frames_late);
    x.sample(name, "cause=\"out_of_order\"", s.frames_out_of_order);
    x.single(
        "v2ce_source_restarts_total",
        "counter",
        "Times the source was reopened (a camera back, a replay looped).",
        s.source_restarts,
    );
    x.single(
        "v2ce_source_refused_total",
        "counter",
        "Messages the source refused (a ROS 2 image that does not decode or disagrees).",
        s.source_refused,
    );
    x.single(
        "v2ce_events_total",
        "counter",
        "Events handed to the outputs.",
        s.events_out,
    );
}

/// Per-output families.
fn sinks(x: &mut Exposition, sinks: &[SinkSnapshot]) {
    let name = "v2ce_sink_events_total";
    x.family(
        name,
        "counter",
        "Events per output, by result: sent (handed to the kernel or written), dropped (lost by the output or evicted from its queue), refused (UDP port closed).",
    );
    for k in sinks {
        let n = label(&k.sink);
        let st = &k.stats;
        x.sample(
            name,
            &format!("sink=\"{n}\",result=\"sent\""),
            st.events_sent,
        );
        x.sample(
            name,
            &format!("sink=\"{n}\",result=\"dropped\""),
            st.events_dropped,
        );
        x.sample(
            name,
            &format!("sink=\"{n}\",result=\"refused\""),
            st.events_refused,
        );
    }
    type SinkValue = fn(&SinkSnapshot) -> u64;
    let per_sink: [(&str, &str, &str, SinkValue); 5] = [
        (
            "v2ce_sink_evicted_events_total",
            "counter",
            "Of the dropped events, those evicted from the output's queue before it took them (drop-oldest; never a file's).",
            |k| k.stats.events_evicted,
        ),
        (
            "v2ce_sink_late_events_total",
            "counter",
            "Events sent after their due time (emission at event time).",
            |k| k.stats.events_late,
        ),
        (
            "v2ce_sink_sent_bytes_total",
            "counter",
            "Bytes sent or written per output.",
            |k| k.stats.bytes_sent,
        ),
        (
            "v2ce_sink_clients",
            "gauge",
            "Clients connected (TCP outputs).",
            |k| k.stats.clients,
        ),
        (
            "v2ce_sink_up",
            "gauge",
            "1 while the output works, 0 once it failed.",
            |k| u64::from(k.failed.is_none()),
        ),
    ];
    for (name, kind, help, value) in per_sink {
        x.family(name, kind, help);
        for k in sinks {
            x.sample(name, &format!("sink=\"{}\"", label(&k.sink)), value(k));
        }
    }
}

/// Per-queue families.
fn queues(x: &mut Exposition, queues: &[QueueSnapshot]) {
    type QueueValue = fn(&QueueSnapshot) -> u64;
    let per_queue: [(&str, &str, &str, QueueValue); 4] = [
        (
            "v2ce_queue_depth",
            "gauge",
            "Items waiting in each queue between stages.",
            |q| q.depth as u64,
        ),
        (
            "v2ce_queue_capacity",
            "gauge",
            "Capacity of each queue.",
            |q| q.capacity as u64,
        ),
        (
            "v2ce_queue_dropped_items_total",
            "counter",
            "Items a full queue evicted (drop-oldest): frames in capture, sequenced and stage1, event batches in an output's queue.",
            |q| q.dropped,
        ),
        (
            "v2ce_queue_dropped_events_total",
            "counter",
            "Simulated events in the items a full queue evicted (0 for frames still without events).",
            |q| q.dropped_events,
        ),
    ];
    for (name, kind, help, value) in per_queue {
        x.family(name, kind, help);
        for q in queues {
            x.sample(name, &format!("queue=\"{}\"", label(&q.name)), value(q));
        }
    }
}

/// The latency histograms.
fn timings(x: &mut Exposition, status: &Status) {
    for (name, timing, help) in [
        (
            "v2ce_capture_lag_seconds",
            Timing::CaptureLag,
            "Lag of a frame's capture behind its own time.",
        ),
        (
            "v2ce_processing_seconds",
            Timing::Processing,
            "From a frame's capture to its interval's events leaving Stage 2.",
        ),
        (
            "v2ce_emission_seconds",
            Timing::Emission,
            "From a batch reaching an output to its last event having left.",
        ),
        (
            "v2ce_latency_seconds",
            Timing::Latency,
            "From a frame's capture to its events having left, per output.",
        ),
    ] {
        x.family(name, "histogram", help);
        let h = status.counters.histogram(timing, &BUCKETS_S);
        let bucket = format!("{name}_bucket");
        for (le, count) in &h.buckets {
            x.sample(&bucket, &format!("le=\"{le}\""), count);
        }
        x.sample(&bucket, "le=\"+Inf\"", h.count);
        x.sample(&format!("{name}_sum"), "", h.sum_s);
        x.sample(&format!("{name}_count"), "", h.count);
    }
}

/// Stage 1: which tier, its window latency, and the counters of every tier.
fn stage1(x: &mut Exposition, status: &Status) {
    let s1 = status.counters.stage1();
    x.family(
        "v2ce_stage1_info",
        "gauge",
        "Stage 1's tier and preset (always 1).",
    );
    let info = format!(
        "tier=\"{}\",preset=\"{}\"",
        label(&status.tier),
        label(&status.preset)
    );
    x.sample("v2ce_stage1_info", &info, 1);
    x.single(
        "v2ce_stage1_window_seconds",
        "gauge",
        "Stage 1's window latency, median so far (0 for a tier without timed windows).",
        s1.window_ms_p50 / 1e3,
    );
    let counters = crate::stage1::all_counters(&s1);
    for (i, c) in counters.iter().enumerate() {
        let name = format!("v2ce_stage1_{}_total", c.family);
        if i == 0 || counters[i - 1].family != c.family {
            x.family(&name, "counter", c.help);
        }
        x.sample(&name, &format!("result=\"{}\"", c.result), c.value);
    }
}

/// The process and readiness.
fn process(x: &mut Exposition, s: &Snapshot, status: &Status) {
    x.single(
        "process_cpu_seconds_total",
        "counter",
        "User and system CPU time of the process.",
        s.cpu_s,
    );
    x.single(
        "process_resident_memory_bytes",
        "gauge",
        "Resident memory of the process.",
        s.rss_kib * 1024,
    );
    x.single(
        "v2ce_uptime_seconds",
        "gauge",
        "Seconds since the pipeline started.",
        s.uptime_s,
    );
    x.single(
        "v2ce_ready",
        "gauge",
        "1 when /readyz answers 200.",
        u8::from(status.readiness().is_ok()),
    );
}
