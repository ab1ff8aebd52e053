//! Tests of the pipeline's timing: pacing, stats and rates.

use super::*;
use crate::frame::scene_fn::SceneSource;
use crate::sink::SinkStats;

/// Takes everything, keeps nothing.
struct Null(SinkStats);

impl Sink for Null {
    fn describe(&self) -> String {
        "null".into()
    }
    fn send(&mut self, events: &[Event]) -> Result<()> {
        self.0.events_in += events.len() as u64;
        Ok(())
    }
    fn finish(&mut self) -> Result<()> {
        Ok(())
    }
    fn stats(&self) -> SinkStats {
        self.0
    }
}

/// Frames 5 ms apart that take 30 ms each to read: a source slower than real time.
struct Slow(SceneSource);

impl FrameSource for Slow {
    fn size(&self) -> (u16, u16) {
        self.0.size()
    }
    fn next_frame(&mut self) -> Result<Option<Frame>> {
        std::thread::sleep(Duration::from_millis(30));
        self.0.next_frame()
    }
    fn describe(&self) -> String {
        "slow".into()
    }
}

fn run_paced(source: Box<dyn FrameSource>) -> Report {
    let config = crate::config::Config::default();
    let size = source.size();
    let stages = Stages {
        stage1: crate::stage1::build(&config.stage1, 10, size, Default::default()).unwrap(),
        sampler: config.stage2.sampler.build(0),
        sinks: vec![Box::new(Null(SinkStats::default()))],
    };
    let source = Source {
        pace: Some(1.0),
        ..Source::file(source)
    };
    let options = Options {
        tick: Duration::from_secs(3600),
        ..Options::default()
    };
    run(
        source,
        stages,
        &options,
        &AtomicBool::new(false),
        &mut |_| {},
    )
    .unwrap()
}

#[test]
fn a_source_slower_than_real_time_shows_as_capture_lag() {
    let scene = SceneSource::moving_edge(32, 24, 200.0, 20, 2.0, 1500.0, (0.1, 0.8));
    let report = run_paced(Box::new(Slow(scene)));
    let s = &report.stats;
    assert_eq!(s.frames_in, 20);
    // The 20th frame is due 95 ms after the first and read at least 570 ms after it.
    assert!(
        s.capture_lag_total.max_ms >= 400.0,
        "{:?}",
        s.capture_lag_total
    );
    assert_eq!(s.capture_lag_total.count, 20);
    assert_eq!(s.processing_total.count, 19);
    // The final report's rates cover the whole run.
    assert!((s.frames_per_s * s.uptime_s - s.frames_in as f64).abs() < 1e-6);
    assert!((s.events_per_s * s.uptime_s - s.events_out as f64).abs() < 1e-3);
}
