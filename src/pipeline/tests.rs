//! Tests of the pipeline: stages wired together, outputs, sources that fail or loop.

use super::*;
use crate::frame::scene_fn::SceneSource;
use crate::sink::SinkStats;
use std::sync::atomic::AtomicU64;

/// Records what it gets; fails on the `fail_at`-th send when set; takes `delay` per send.
struct Recorder {
    got: Arc<Mutex<Vec<Event>>>,
    sends: u64,
    fail_at: Option<u64>,
    stats: SinkStats,
    delay: Duration,
    recording: bool,
}

impl Sink for Recorder {
    fn describe(&self) -> String {
        "recorder".into()
    }
    fn is_recording(&self) -> bool {
        self.recording
    }
    fn send(&mut self, events: &[Event]) -> Result<()> {
        std::thread::sleep(self.delay);
        self.sends += 1;
        if Some(self.sends) == self.fail_at {
            return Err(Error::Run("disk full".into()));
        }
        self.stats.events_in += events.len() as u64;
        self.stats.events_sent += events.len() as u64;
        self.got
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .extend_from_slice(events);
        Ok(())
    }
    fn finish(&mut self) -> Result<()> {
        Ok(())
    }
    fn stats(&self) -> SinkStats {
        self.stats
    }
}

fn recorder(fail_at: Option<u64>) -> (Box<dyn Sink>, Arc<Mutex<Vec<Event>>>) {
    let got = Arc::new(Mutex::new(Vec::new()));
    let sink = Recorder {
        got: got.clone(),
        sends: 0,
        fail_at,
        stats: SinkStats::default(),
        delay: Duration::ZERO,
        recording: false,
    };
    (Box::new(sink), got)
}

/// An output taking `ms` per batch: a recording (a file) or not.
fn slow(recording: bool, ms: u64) -> (Box<dyn Sink>, Arc<Mutex<Vec<Event>>>) {
    let got = Arc::new(Mutex::new(Vec::new()));
    let sink = Recorder {
        got: got.clone(),
        sends: 0,
        fail_at: None,
        stats: SinkStats::default(),
        delay: Duration::from_millis(ms),
        recording,
    };
    (Box::new(sink), got)
}

#[test]
fn a_live_run_behind_its_lag_budget_sheds_frames_before_stage1_and_block_never_does() {
    let run_with = |policy: QueuePolicy| {
        let (sink, got) = recorder(None);
        let options = Options {
            tick: Duration::from_secs(3600),
            policy,
            // Every frame with a newer one waiting is too old.
            lag_budget: Some(Duration::ZERO),
            ..Options::default()
        };
        // 120 frames of 5 ms at 50 times real time: a frame every 0.1 ms, faster than
        // Stage 1 takes them. The edge crosses the frame over the whole replay (100 px/s), so
        // every interval, however many are folded into it, holds its events (with `edge`'s,
        // gone after 41 ms, the last events were noise, and how late they fell depended on
        // which frames a loaded machine shed).
        let scene = SceneSource::moving_edge(64, 48, 200.0, 120, 2.0, 100.0, (0.1, 0.8));
        let source = Source {
            pace: Some(50.0),
            ..Source::file(Box::new(scene))
        };
        let report = run_with(source, vec![sink], &options);
        let got = got.lock().unwrap();
        (report, got.len() as u64, got.last().map_or(0, |e| e.t))
    };
    let (shed, events, last) = run_with(QueuePolicy::DropOldest);
    let s = &shed.stats;
    assert!(s.frames_late > 0, "{s:?}");
    assert!(s.frames_processed + s.frames_late <= s.frames_in, "{s:?}");
    // Shed only with a newer frame waiting: the newest frames are simulated, and the events
    // still reach the end of the replay (skipped intervals fold into the next).
    assert!(last > 100 * 5_000, "{last}");
    assert!(events > 0);
    let (kept, _, _) = run_with(QueuePolicy::Block);
    assert_eq!(kept.stats.frames_late, 0);
    assert_eq!(kept.stats.frames_processed, 120);
}

#[test]
fn under_drop_oldest_a_recording_keeps_every_event_and_other_outputs_count_evictions() {
    let (file, recorded) = slow(true, 1);
    let (net, sent) = slow(false, 25);
    let options = Options {
        tick: Duration::from_secs(3600),
        policy: QueuePolicy::DropOldest,
        capacity: 2,
        ..Options::default()
    };
    // 200 frames at 5 ms replayed at half speed: 10 ms a frame, which Stage 1 and the
    // recording keep up with and the other output (25 ms a batch) does not.
    let source = Source {
        pace: Some(0.5),
        ..Source::file(edge(200))
    };
    let report = run_with(source, vec![file, net], &options);
    let s = &report.stats;
    let (f, n) = (&s.sinks[0], &s.sinks[1]);
    assert!(f.recording && !n.recording);
    // The recording holds every event Stage 2 handed out, and says it lost none.
    assert_eq!(recorded.lock().unwrap().len() as u64, s.events_out);
    assert_eq!(f.stats.events_sent, s.events_out);
    assert_eq!((f.stats.events_dropped, f.stats.events_evicted), (0, 0));
    // The other output's queue evicted (it is slower, and never blocks Stage 2), and its
    // counts say so: given = sent + dropped, every drop an eviction.
    let got = sent.lock().unwrap().len() as u64;
    assert_eq!(n.stats.events_sent, got);
    assert!(n.stats.events_evicted > 0, "{:?} {s:?}", n.stats);
    assert_eq!(n.stats.events_dropped, n.stats.events_evicted);
    assert_eq!(n.stats.events_in, got + n.stats.events_evicted);
    assert_eq!(n.stats.events_in, s.events_out);
    assert!(s.frames_processed > 100, "{s:?}");
    // Frames a queue evicted carry no events yet: the frame queues count none.
    for q in s
        .queues
        .iter()
        .filter(|q| q.name == "capture" || q.name == "sequenced")
    {
        assert_eq!(q.dropped_events, 0, "{q:?}");
    }
}

fn edge(frames: usize) -> Box<dyn FrameSource> {
    Box::new(SceneSource::moving_edge(
        64,
        48,
        200.0,
        frames,
        2.0,
        1500.0,
        (0.1, 0.8),
    ))
}

/// Runs with the default config and no ticks.
fn run_quiet(source: Source, sinks: Vec<Box<dyn Sink>>, max_frames: Option<u64>) -> Report {
    let options = Options {
        tick: Duration::from_secs(3600),
        max_frames,
        ..Options::default()
    };
    run_with(source, sinks, &options)
}

/// Runs the default config's stages with `options`.
fn run_with(source: Source, sinks: Vec<Box<dyn Sink>>, options: &Options) -> Report {
    let stop = AtomicBool::new(false);
    let config = crate::config::Config::default();
    let size = source.first.size();
    let stages = Stages {
        stage1: crate::stage1::build(&config.stage1, config.stage2.bins, size, Default::default())
            .unwrap(),
        sampler: config.stage2.sampler.build(config.stage2.seed),
        sinks,
    };
    run(source, stages, options, &stop, &mut |_| {}).unwrap()
}

#[test]
fn a_failing_sink_does_not_stop_the_others() {
    let (good, got) = recorder(None);
    let (bad, _) = recorder(Some(2));
    let report = run_quiet(Source::file(edge(20)), vec![bad, good], None);
    assert_eq!(report.end, End::SourceEnded);
    assert_eq!(report.stats.frames_in, 20);
    let events = got.lock().unwrap().len() as u64;
    assert!(events > 0);
    assert_eq!(events, report.stats.events_out);
    assert!(report.stats.sinks[0]
        .failed
        .as_deref()
        .unwrap()
        .contains("disk full"));
    assert!(report.stats.sinks[1].failed.is_none());
    // What the failed sink did not write is counted as dropped, from the failed send on.
    let bad = report.stats.sinks[0].stats;
    assert_eq!(bad.events_in, events);
    assert!(bad.events_sent > 0 && bad.events_dropped > 0, "{bad:?}");
    assert_eq!(bad.events_sent + bad.events_dropped, events);
}

#[test]
fn every_sink_failing_stops_the_run_with_an_error() {
    let (bad, _) = recorder(Some(1));
    let report = run_quiet(Source::file(edge(400)), vec![bad], None);
    assert!(matches!(&report.end, End::Failed(m) if m.contains("every output failed")));
    assert!(report.stats.frames_in < 400);
}

/// `left` frames, then an error (a camera unplugged); times shifted by `offset`, as a
/// camera's monotonic clock goes on while it is away.
struct Flaky {
    inner: Box<dyn FrameSource>,
    left: usize,
    offset: i64,
}

impl FrameSource for Flaky {
    fn size(&self) -> (u16, u16) {
        self.inner.size()
    }
    fn next_frame(&mut self) -> Result<Option<Frame>> {
        if self.left == 0 {
            return Err(Error::Run("device went away".into()));
        }
        self.left -= 1;
        let offset = self.offset;
        Ok(self.inner.next_frame()?.map(|f| Frame {
            t: f.t + offset,
            ..f
        }))
    }
    fn describe(&self) -> String {
        "flaky camera".into()
    }
}

#[test]
fn a_live_source_that_fails_is_reopened_with_backoff() {
    let opened = Arc::new(AtomicU64::new(0));
    let open = {
        let opened = opened.clone();
        move || -> Result<Box<dyn FrameSource>> {
            let n = opened.fetch_add(1, Ordering::Relaxed);
            // The second attempt fails too, as a camera still re-enumerating would.
            if n == 1 {
                return Err(Error::Run("no such device".into()));
            }
            Ok(Box::new(Flaky {
                inner: edge(1000),
                left: 5,
                offset: n as i64 * 1_000_000,
            }))
        }
    };
    let mut reopen: Reopen = Box::new(open);
    let first = reopen().unwrap();
    let source = Source {
        first,
        reopen: Some(reopen),
        live: true,
        looped: false,
        pace: None,
        backoff: (Duration::from_millis(1), Duration::from_millis(4)),
    };
    let (sink, got) = recorder(None);
    let report = run_quiet(source, vec![sink], Some(12));
    assert_eq!(report.end, End::MaxFrames);
    assert_eq!(report.stats.frames_in, 12);
    // 5 frames per opening: the first, a failed attempt, then two more openings.
    assert_eq!(opened.load(Ordering::Relaxed), 4);
    assert_eq!(report.stats.source_restarts, 2);
    assert_eq!(report.stats.frames_processed, 12);
    assert_eq!(report.stats.frames_out_of_order, 0);
    // Stage 1 starts over on each new opening: the first frame after a gap only sets the
    // pixels, so no event falls in the gap between 20 ms and 2 s.
    let events = got.lock().unwrap();
    assert!(!events.iter().any(|e| e.t > 25_000 && e.t <= 2_000_000));
}

#[test]
fn a_file_that_fails_ends_the_run_and_flushes_what_came_before() {
    let (sink, got) = recorder(None);
    let source = Source::file(Box::new(Flaky {
        inner: edge(100),
        left: 10,
        offset: 0,
    }));
    let report = run_quiet(source, vec![sink], None);
    assert!(matches!(&report.end, End::SourceFailed(m) if m.contains("device went away")));
    assert_eq!(report.stats.frames_processed, 10);
    assert_eq!(got.lock().unwrap().len() as u64, report.stats.events_out);
}

#[test]
fn a_looped_replay_keeps_time_increasing() {
    let (sink, got) = recorder(None);
    let source = Source {
        reopen: Some(Box::new(|| Ok(edge(10)))),
        looped: true,
        ..Source::file(edge(10))
    };
    let report = run_quiet(source, vec![sink], Some(25));
    assert_eq!(report.stats.frames_processed, 25);
    assert_eq!(report.stats.frames_out_of_order, 0);
    assert_eq!(report.last_t, Some(24 * 5_000));
    let events = got.lock().unwrap();
    assert!(events.windows(2).all(|w| w[0].t <= w[1].t));
}
