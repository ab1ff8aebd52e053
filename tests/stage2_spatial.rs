//! The `spatial` sampler against `moment` on a scene whose every event time is known: an edge
//! crossing the sensor at a steady speed, each pixel firing a run of evenly spaced events as
//! the edge's blurred ramp passes it (as a DVS pixel does while its log intensity climbs
//! through one threshold after another).

mod common;

use v2ce::metrics::stage2::Stage2Scorer;
use v2ce::{voxelize, Event, Interval, SamplerKind};

const W: u16 = 96;
const H: u16 = 24;
const BINS: usize = 10;

/// Edge runs of `per_pixel` events over `ramp_us`, the edge moving `speed` px/s from x = 0 at
/// `t0`; one interval of `duration` us. Returns the interval and its events, time-sorted.
fn moving_edge(per_pixel: u32, ramp_us: f64, speed: f64, duration: i64) -> (Interval, Vec<Event>) {
    let t0 = 1_000_000i64;
    let interval = Interval::new(t0, t0 + duration).expect("a valid interval");
    let mut events = Vec::new();
    for y in 0..H {
        // Each row's edge a little behind the last (a slanted edge), so rows differ.
        let lag = y as f64 * 150.0;
        for x in 0..W {
            let arrive = x as f64 / speed * 1e6 + lag;
            for k in 0..per_pixel {
                let t = t0 + (arrive + (k as f64 + 0.5) * ramp_us / per_pixel as f64) as i64;
                if interval.contains(t) {
                    events.push(Event::new(t, x, y, true));
                }
            }
        }
    }
    events.sort_by_key(|e| (e.t, e.y, e.x));
    (interval, events)
}

fn c_mete(kind: SamplerKind, interval: Interval, truth: &[Event]) -> (f64, usize) {
    let grid = voxelize(truth, interval, W, H, BINS).expect("voxelize");
    let mut out = Vec::new();
    let repaired = kind.build(0).sample(&grid, interval, &mut out);
    assert!(!repaired.any());
    let mut scorer = Stage2Scorer::new();
    scorer.add_interval(interval, truth, &out);
    (scorer.finish().c_mete_us, out.len())
}

#[test]
fn a_moving_edge_is_timed_at_least_twice_as_well_as_by_moment() {
    // Runs of 4 to 6 events over 3 to 6 ms, sub-intervals of 3.7 ms: most pixels hold two or
    // more events in some sub-interval, where `moment` can only guess their spread.
    for (per_pixel, ramp_us, speed) in [
        (4, 3_000.0, 3_000.0),
        (5, 6_000.0, 3_000.0),
        (6, 4_500.0, 2_900.0),
    ] {
        let (interval, truth) = moving_edge(per_pixel, ramp_us, speed, 33_333);
        assert!(truth.len() > 5_000, "{} events", truth.len());
        let (moment, n_moment) = c_mete(SamplerKind::Moment, interval, &truth);
        let (spatial, n_spatial) = c_mete(SamplerKind::Spatial, interval, &truth);
        // Counts are exact for both.
        assert_eq!((n_moment, n_spatial), (truth.len(), truth.len()));
        println!(
            "{per_pixel} events over {ramp_us} us: moment {moment:.1} us, spatial {spatial:.1} us"
        );
        assert!(
            moment > 20.0,
            "moment's error {moment} us: the scene is too easy"
        );
        assert!(
            spatial <= moment / 2.0,
            "{per_pixel} events over {ramp_us} us: spatial {spatial:.1} us, moment {moment:.1} us"
        );
    }
}

#[test]
fn the_same_voxel_gives_the_same_events_whatever_the_cell_order() {
    let (interval, truth) = moving_edge(5, 6_000.0, 3_000.0, 33_333);
    let grid = voxelize(&truth, interval, W, H, BINS).expect("voxelize");
    // The same cells pushed in reverse order.
    let cells: Vec<_> = grid
        .cells()
        .map(|c| (c.x, c.y, c.on, c.values.to_vec()))
        .collect();
    let mut reversed = v2ce::VoxelGrid::new(W, H, BINS).expect("grid");
    for (x, y, on, values) in cells.iter().rev() {
        reversed.push_cell(*x, *y, *on, values).expect("cell");
    }
    let sampler = SamplerKind::Spatial.build(7);
    let (mut a, mut b) = (Vec::new(), Vec::new());
    sampler.sample(&grid, interval, &mut a);
    sampler.sample(&reversed, interval, &mut b);
    assert_eq!(a, b);
    assert_eq!(a.len(), truth.len());
}

#[test]
fn a_sensor_firing_tight_pairs_is_timed_from_its_own_stream() {
    // Every pixel of a 200 x 100 sensor fires one pair 150 us apart at a random time: no pixel
    // has a neighbour in time, and its spatial neighbours fire at unrelated times. The pairs that
    // happen to straddle a sub-interval's boundary show the spacing (step 4 of the sampler).
    use rand::{Rng, SeedableRng};
    let (w, h) = (200u16, 100u16);
    let interval = Interval::new(0, 33_333).expect("interval");
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(28);
    let mut truth = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let t = rng.gen_range(0..33_333 - 150);
            truth.push(Event::new(t, x, y, true));
            truth.push(Event::new(t + 150, x, y, true));
        }
    }
    truth.sort_by_key(|e| (e.t, e.y, e.x));
    let score = |kind: SamplerKind| {
        let grid = voxelize(&truth, interval, w, h, BINS).expect("voxelize");
        let mut out = Vec::new();
        kind.build(0).sample(&grid, interval, &mut out);
        assert_eq!(out.len(), truth.len(), "{kind}");
        let mut scorer = Stage2Scorer::new();
        scorer.add_interval(interval, &truth, &out);
        scorer.finish().c_mete_us
    };
    let (moment, spatial) = (score(SamplerKind::Moment), score(SamplerKind::Spatial));
    println!("tight pairs: moment {moment:.1} us, spatial {spatial:.1} us");
    assert!(moment > 100.0, "moment {moment} us: the scene is too easy");
    assert!(
        spatial <= moment / 2.0,
        "spatial {spatial:.1} us, moment {moment:.1} us"
    );
}

/// `eval stage2`'s score of the default sampler on dvxplorer, recomputed by numpy
/// (`tools/stage2_numpy.py --predicted`) from the events it wrote: the metric, independently.
#[test]
fn numpy_scores_the_default_sampler_on_dvxplorer_as_eval_does() {
    let data = data_or_skip!("numpy_scores_the_default_sampler_on_dvxplorer_as_eval_does");
    let python = python_or_skip!("numpy_scores_the_default_sampler_on_dvxplorer_as_eval_does");
    let dir = common::temp_dir("stage2_numpy");
    let (truth, predicted) = (dir.join("truth.csv"), dir.join("predicted.csv"));
    let v2ce = env!("CARGO_BIN_EXE_v2ce");
    let recording = data.join("dvxplorer/data_sample.aedat4");
    let run = |args: &[&std::ffi::OsStr]| {
        let out = std::process::Command::new(v2ce)
            .args(args)
            .output()
            .expect("v2ce runs");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    run(&[
        "transcode".as_ref(),
        recording.as_os_str(),
        truth.as_os_str(),
    ]);
    let ours: serde_json::Value = serde_json::from_str(&run(&[
        "eval".as_ref(),
        "stage2".as_ref(),
        "--events".as_ref(),
        recording.as_os_str(),
        "--fps".as_ref(),
        "30".as_ref(),
        "--json".as_ref(),
        "--write-events".as_ref(),
        predicted.as_os_str(),
    ]))
    .expect("one JSON object");
    let tool = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/stage2_numpy.py");
    let out = std::process::Command::new(python)
        .arg(tool)
        .arg(&truth)
        .arg("--predicted")
        .arg(&predicted)
        .output()
        .expect("python runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let numpy: serde_json::Value =
        serde_json::from_slice(&out.stdout).expect("one JSON object from numpy");
    println!("eval: {ours}\nnumpy: {numpy}");
    assert_eq!(ours["sampler"], "spatial");
    for key in ["c_mete_us", "pger"] {
        let (a, b) = (ours[key].as_f64().unwrap(), numpy[key].as_f64().unwrap());
        assert!(
            (a - b).abs() <= 1e-9 * a.abs().max(1.0),
            "{key}: eval {a}, numpy {b}"
        );
    }
    assert_eq!(ours["events_out"], numpy["events_out"]);
}
