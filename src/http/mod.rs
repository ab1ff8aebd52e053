//! The daemon's optional HTTP listener (`[run] http`, off by default, loopback unless set
//! otherwise), on hyper (see [`server`] for its limits):
//!
//! | path | what |
//! |---|---|
//! | `/metrics` | Prometheus text format: frames, events per sink, drops by cause, queue depths, latency histograms, CPU, RSS, Stage 1 |
//! | `/healthz` | 200 while the process is up |
//! | `/readyz` | 200 when the pipeline runs, a frame came within the stall timeout and no output failed; else 503 and why |
//! | `/` | the live preview page (no external assets) |
//! | `/events?window_ms=N` | the page's server-sent events: the event frame (a PNG) and the stats, 5 times a second |
//!
//! A scrape reads the pipeline's atomic counters and takes its histograms' locks for a copy;
//! the stage threads never wait on the listener, and no client can hold it (see [`server`]).
//! The preview frames are drawn and encoded on a thread of their own ([`encoder`]), once per
//! push and accumulation window for all the pages open, so the listener's thread only copies
//! bytes and a probe never waits behind a PNG.

pub mod encoder;
mod metrics;
pub mod server;

pub use metrics::metrics;
pub use server::{HttpServer, ListenerCounters};

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use crate::pipeline::stats::Counters;
use crate::sink::preview::PreviewBuffer;

/// Server-sent event streams served at once; more get 503.
pub const MAX_STREAMS: usize = 8;
/// How often the page gets a frame.
pub const PUSH_PERIOD: Duration = Duration::from_millis(200);

/// What the listener reports, shared with the daemon.
pub struct Status {
    /// The pipeline's counters.
    pub counters: Arc<Counters>,
    /// The recent events, for the page.
    pub preview: Arc<PreviewBuffer>,
    /// Stage 1's tier and preset, for `v2ce_stage1_info`.
    pub tier: String,
    /// The physics preset (or the model, for the learned tier).
    pub preset: String,
    /// Settings shown on the page, in order.
    pub settings: Vec<(String, String)>,
    /// No frame for this long: not ready.
    pub stall: Duration,
    /// Set while the pipeline runs.
    pub running: AtomicBool,
    /// What the listener refused or cut off.
    pub listener: ListenerCounters,
}

impl Status {
    /// Why the daemon is not ready, or `Ok` when it is.
    pub fn readiness(&self) -> std::result::Result<(), String> {
        if !self.running.load(Ordering::Relaxed) {
            return Err("the pipeline is not running".into());
        }
        match self.counters.last_frame_age() {
            None => return Err("no frame yet".into()),
            Some(age) if age > self.stall => {
                return Err(format!(
                    "no frame for {:.1} s (the source stalled)",
                    age.as_secs_f64()
                ))
            }
            Some(_) => {}
        }
        match self.counters.failed_sink() {
            Some(failure) => Err(format!("output down: {failure}")),
            None => Ok(()),
        }
    }
}

/// The preview page: one static document, no external assets.
pub const PAGE: &str = include_str!("page.html");

fn base64(data: &[u8]) -> String {
    use base64::Engine;
    base64::engine::general_purpose::STANDARD.encode(data)
}

/// The `window_ms` of a query string: 1 ms to the preview's whole buffer, 33 by default.
fn window_ms(query: &str) -> f64 {
    query
        .split('&')
        .find_map(|kv| kv.strip_prefix("window_ms="))
        .and_then(|v| v.parse::<f64>().ok())
        .filter(|v| v.is_finite() && *v >= 1.0)
        .unwrap_or(33.0)
        .min(crate::sink::preview::KEEP_US as f64 / 1e3)
}

/// The page with the settings and the current frame (the PNG in base64, when there is one)
/// filled in, so it shows events at once, before the first push.
fn page(status: &Status, window_ms: f64, png_base64: Option<&str>) -> String {
    // Inside a <script>: no "</" may appear.
    let settings = serde_json::to_string(&status.settings)
        .unwrap_or_else(|_| "[]".into())
        .replace('<', "\\u003c");
    let frame = png_base64.map_or(String::new(), |png| format!("data:image/png;base64,{png}"));
    PAGE.replace("SETTINGS_JSON", &settings)
        .replace("INITIAL_FRAME", &frame)
        .replace("WINDOW_MS", &format!("{}", window_ms.round()))
}

/// The frame of the last `window_us` as a PNG, and how many events it shows.
fn frame_png(status: &Status, window_us: i64) -> (Vec<u8>, usize) {
    let (w, h) = status.preview.size();
    let (rgb, shown) = status.preview.frame(window_us);
    let mut png = Vec::new();
    let encoded = image::codecs::png::PngEncoder::new(&mut png);
    if image::ImageEncoder::write_image(
        encoded,
        &rgb,
        u32::from(w),
        u32::from(h),
        image::ExtendedColorType::Rgb8,
    )
    .is_err()
    {
        png.clear();
    }
    (png, shown)
}

/// The frame of the last `window_us` (a PNG, in base64) and the stats, as one server-sent
/// event; drawn on the encoder's thread ([`encoder`]), never the listener's.
fn encode(status: &Status, window_us: i64) -> encoder::Encoded {
    let (w, h) = status.preview.size();
    let (png, shown) = frame_png(status, window_us);
    status
        .listener
        .preview_frames
        .fetch_add(1, Ordering::Relaxed);
    let png_base64 = base64(&png);
    let s = status.counters.peek();
    let body = serde_json::json!({
        "png": png_base64,
        "width": w,
        "height": h,
        "shown": shown,
        "window_ms": window_us as f64 / 1e3,
        "line": s.line(),
        "frames": s.frames_in,
        "events": s.events_out,
        "ready": status.readiness().err().unwrap_or_else(|| "ready".into()),
    });
    encoder::Encoded {
        event: bytes::Bytes::from(format!("data: {body}\n\n")),
        png_base64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::stats::Timing;
    use crate::sink::SinkStats;

    fn status() -> Status {
        let counters = Arc::new(Counters::new());
        let i = counters.add_sink("file \"a\\b\".csv".into(), true, None);
        counters.update_sink(
            i,
            SinkStats {
                events_in: 7,
                events_sent: 5,
                events_dropped: 2,
                ..SinkStats::default()
            },
            None,
        );
        counters.frame_read();
        counters.record(Timing::Latency, Duration::from_millis(3));
        counters.record(Timing::Latency, Duration::from_millis(300));
        Status {
            counters,
            preview: PreviewBuffer::new(4, 3),
            tier: "physics".into(),
            preset: "davis346".into(),
            settings: vec![("source".into(), "</script>".into())],
            stall: Duration::from_secs(60),
            running: AtomicBool::new(true),
            listener: ListenerCounters::default(),
        }
    }

    #[test]
    fn metrics_follow_the_text_format() {
        let s = status();
        let text = metrics(&s);
        assert!(text.contains("v2ce_frames_total 1\n"), "{text}");
        // Label values escaped; every result of the sink.
        assert!(
            text.contains(
                "v2ce_sink_events_total{sink=\"file \\\"a\\\\b\\\".csv\",result=\"dropped\"} 2"
            ),
            "{text}"
        );
        // Histogram buckets cumulative, ending in +Inf with the count.
        assert!(
            text.contains("v2ce_latency_seconds_bucket{le=\"0.005\"} 1\n"),
            "{text}"
        );
        assert!(
            text.contains("v2ce_latency_seconds_bucket{le=\"0.5\"} 2\n"),
            "{text}"
        );
        assert!(
            text.contains("v2ce_latency_seconds_bucket{le=\"+Inf\"} 2\n"),
            "{text}"
        );
        assert!(text.contains("v2ce_latency_seconds_count 2\n"), "{text}");
        assert!(text.contains("v2ce_stage1_info{tier=\"physics\",preset=\"davis346\"} 1"));
        // Every tier's counters, whichever tier runs (zero before Stage 1 reports).
        assert!(text.contains("v2ce_stage1_tiles_total{result=\"active\"} 0\n"));
        assert!(text.contains("v2ce_stage1_windows_total{result=\"skipped\"} 0\n"));
        assert!(text.contains("v2ce_ready 1\n"), "{text}");
        // Every sample line belongs to a family declared before it.
        let mut declared = std::collections::HashSet::new();
        for line in text.lines() {
            if let Some(rest) = line.strip_prefix("# TYPE ") {
                declared.insert(rest.split(' ').next().unwrap().to_string());
            } else if !line.starts_with('#') {
                let name = line.split(['{', ' ']).next().unwrap();
                let family = ["_bucket", "_sum", "_count"]
                    .iter()
                    .find_map(|s| name.strip_suffix(s).filter(|f| declared.contains(*f)))
                    .unwrap_or(name);
                assert!(declared.contains(family), "{line}");
            }
        }
    }

    #[test]
    fn readiness_needs_a_recent_frame_and_a_running_pipeline() {
        let mut s = status();
        assert_eq!(s.readiness(), Ok(()));
        s.stall = Duration::ZERO;
        std::thread::sleep(Duration::from_millis(2));
        assert!(s.readiness().unwrap_err().contains("stalled"));
        s.running.store(false, Ordering::Relaxed);
        assert!(s.readiness().unwrap_err().contains("not running"));
    }

    #[test]
    fn the_page_is_self_contained_and_escapes_settings() {
        let s = status();
        let html = page(&s, 100.0, Some("iVBORw0KGgo="));
        assert!(
            !html.contains("</script>\""),
            "settings break out of the script"
        );
        assert!(html.contains("\\u003c/script>"));
        assert!(html.contains("src=\"data:image/png;base64,iVBORw0KGgo=\""));
        assert!(page(&s, 100.0, None).contains("src=\"\""));
        assert!(!html.contains("SETTINGS_JSON") && !html.contains("INITIAL_FRAME"));
        assert!(!html.contains("http://") && !html.contains("https://"));
        assert_eq!(window_ms("window_ms=100"), 100.0);
        assert_eq!(window_ms("window_ms=nan"), 33.0);
        assert_eq!(window_ms("window_ms=1e9"), 1000.0);
    }
}
