//! Stage 2 at the extremes: empty and huge voxels, slopes at and past the valid range, times far
//! from zero, tiny and large sensors.

use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;
use v2ce::stage2::SamplerKind;
use v2ce::{voxelize, Event, Interval, VoxelGrid};

fn sample(kind: SamplerKind, grid: &VoxelGrid, iv: Interval) -> Vec<Event> {
    let mut out = Vec::new();
    kind.build(5).sample(grid, iv, &mut out);
    assert!(out.iter().all(|e| iv.contains(e.t)), "{kind}: time outside");
    assert!(out.windows(2).all(|w| w[0].t <= w[1].t), "{kind}: unsorted");
    out
}

/// Event count per sub-interval of a 10-node voxel over `iv`.
fn sub_interval_of(iv: Interval, t: i64) -> usize {
    (((t - iv.start()) as f64 * 9.0 / iv.duration_us() as f64).floor() as usize).min(8)
}

#[test]
fn all_zero_voxels_give_no_event() {
    let iv = Interval::new(0, 33_333).unwrap();
    let mut grid = VoxelGrid::new(8, 8, 10).unwrap();
    assert!(SamplerKind::ALL
        .iter()
        .all(|&k| sample(k, &grid, iv).is_empty()));
    grid.push_cell(3, 3, true, &[0.0; 10]).unwrap();
    grid.push_cell(4, 3, false, &[0.0; 10]).unwrap();
    assert!(SamplerKind::ALL
        .iter()
        .all(|&k| sample(k, &grid, iv).is_empty()));
}

#[test]
fn tiny_and_huge_values_in_one_voxel() {
    let iv = Interval::new(0, 40_000).unwrap();
    let mut grid = VoxelGrid::new(2, 2, 10).unwrap();
    let mut v = [1e-7; 10];
    v[4] = 1e6;
    grid.push_cell(1, 1, true, &v).unwrap();
    for kind in [
        SamplerKind::Ldati,
        SamplerKind::LdatiRandom,
        SamplerKind::Moment,
    ] {
        let out = sample(kind, &grid, iv);
        assert_eq!(out.len(), 1_000_000, "{kind}");
    }
    for kind in [SamplerKind::Even, SamplerKind::Random] {
        let n = sample(kind, &grid, iv).len();
        assert!((1_000_000..=1_000_010).contains(&n), "{kind}: {n}");
    }
    // Beyond the clamp: counted, bounded, no panic.
    let mut grid = VoxelGrid::new(2, 2, 10).unwrap();
    let mut v = [0.0; 10];
    v[2] = 1e30;
    grid.push_cell(0, 0, false, &v).unwrap();
    let mut out = Vec::new();
    let stats = SamplerKind::Moment.build(0).sample(&grid, iv, &mut out);
    assert_eq!(stats.clamped, 1);
    assert_eq!(out.len(), 1_000_000);
}

#[test]
fn ten_thousand_events_in_one_sub_interval() {
    let iv = Interval::new(5_000_000, 5_036_000).unwrap(); // sub-intervals of 4000 us
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(11);
    let mut events: Vec<Event> = (0..10_000)
        .map(|_| Event::new(5_000_000 + 16_000 + rng.gen_range(0..4_000), 7, 3, false))
        .collect();
    events.sort_by_key(|e| e.t);
    let grid = voxelize(&events, iv, 16, 8, 10).unwrap();
    let truth_mean = events.iter().map(|e| e.t as f64).sum::<f64>() / 1e4;
    for kind in [
        SamplerKind::Ldati,
        SamplerKind::LdatiRandom,
        SamplerKind::Moment,
    ] {
        let out = sample(kind, &grid, iv);
        assert_eq!(out.len(), 10_000, "{kind}");
        assert!(out.iter().all(|e| (e.x, e.y, e.on) == (7, 3, false)));
    }
    // The moment sampler keeps them in their sub-interval (to the microsecond it is rounded
    // to), with the right mean.
    let out = sample(SamplerKind::Moment, &grid, iv);
    assert!(out
        .iter()
        .all(|e| (16_000..=20_000).contains(&(e.t - 5_000_000))));
    let mean = out.iter().map(|e| e.t as f64).sum::<f64>() / 1e4;
    assert!((mean - truth_mean).abs() < 1.0, "{mean} vs {truth_mean}");
}

/// A cell whose chain-decoupled counts are exactly `counts` (every event on a node).
fn cell_with_counts(counts: &[f64; 9]) -> VoxelGrid {
    let mut v = [0.0; 10];
    v[..9].copy_from_slice(counts);
    let mut grid = VoxelGrid::new(1, 1, 10).unwrap();
    grid.push_cell(0, 0, true, &v).unwrap();
    grid
}

#[test]
fn slopes_near_zero_and_past_the_valid_range() {
    let iv = Interval::new(0, 90_000).unwrap(); // sub-intervals of 10_000 us
                                                // Near zero: kappa = 0.5 / 50_000 = 1e-5 in sub-interval 1.
    let grid = cell_with_counts(&[50_000.0, 50_000.0, 50_001.0, 0., 0., 0., 0., 0., 0.]);
    let out = sample(SamplerKind::Ldati, &grid, iv);
    assert_eq!(out.len(), 150_001);
    // Sub-interval 1 is [10_000, 20_000); a draw at its very end rounds to 20_000.
    let sub1: Vec<i64> = out
        .iter()
        .filter(|e| (10_000..20_000).contains(&e.t))
        .map(|e| e.t - 10_000)
        .collect();
    assert!((49_990..=50_000).contains(&sub1.len()), "{}", sub1.len());
    // Nearly uniform: mean in the middle of the sub-interval.
    let mean = sub1.iter().sum::<i64>() as f64 / sub1.len() as f64;
    assert!((mean - 5_000.0).abs() < 100.0, "{mean}");
    // |k| delta^2 = 25 (counts 0, 2, 100): clamped to the steepest valid density, mass towards
    // the end of the sub-interval; and the mirrored case.
    for (counts, later) in [
        ([0.0, 2.0, 100.0, 0., 0., 0., 0., 0., 0.], true),
        ([100.0, 2.0, 0.0, 0., 0., 0., 0., 0., 0.], false),
    ] {
        let grid = cell_with_counts(&counts);
        for seed in 0..50u64 {
            let mut out = Vec::new();
            SamplerKind::Ldati.build(seed).sample(&grid, iv, &mut out);
            assert_eq!(out.len(), 102);
            for e in out.iter().filter(|e| sub_interval_of(iv, e.t) == 1) {
                let off = e.t - 10_000;
                assert!((0..10_000).contains(&off));
                // With kappa = 2 the density 2x vanishes at 0: nothing lands at the very start.
                if later {
                    assert!(off > 0, "{off}");
                } else {
                    assert!(off < 9_999, "{off}");
                }
            }
        }
    }
}

#[test]
fn absolute_times_past_2_pow_32_and_10_days() {
    for start in [
        (1i64 << 32) + 17,
        10 * 86_400 * 1_000_000 + 123_456,
        1_589_163_147_364_965,
    ] {
        let iv = Interval::new(start, start + 40_000).unwrap();
        let truth: Vec<Event> = [1i64, 4_445, 17_001, 39_999]
            .iter()
            .map(|&o| Event::new(start + o, 2, 1, true))
            .collect();
        let grid = voxelize(&truth, iv, 4, 4, 10).unwrap();
        for kind in [
            SamplerKind::Ldati,
            SamplerKind::Moment,
            SamplerKind::Spatial,
        ] {
            let out = sample(kind, &grid, iv);
            assert_eq!(out.len(), 4);
            for (o, t) in out.iter().zip(&truth) {
                assert!((o.t - t.t).abs() <= 1, "{kind} {start}: {} vs {}", o.t, t.t);
            }
        }
    }
}

#[test]
fn one_by_one_1280_by_720_and_8192_wide_sensors() {
    let iv = Interval::new(0, 33_333).unwrap();
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(1);
    for (w, h, n) in [
        (1u16, 1u16, 50usize),
        (1280, 720, 200_000),
        (8192, 3, 60_000),
    ] {
        let mut events: Vec<Event> = (0..n)
            .map(|_| {
                Event::new(
                    rng.gen_range(0..33_333),
                    rng.gen_range(0..w),
                    rng.gen_range(0..h),
                    rng.gen(),
                )
            })
            .collect();
        events.sort_by_key(|e| e.t);
        let grid = voxelize(&events, iv, w, h, 10).unwrap();
        for kind in SamplerKind::ALL {
            let out = sample(kind, &grid, iv);
            assert!(out.iter().all(|e| e.x < w && e.y < h));
            if matches!(
                kind,
                SamplerKind::Ldati | SamplerKind::Moment | SamplerKind::Spatial
            ) {
                assert_eq!(out.len(), n, "{kind} {w}x{h}");
            }
        }
        let dense = grid.to_dense();
        assert_eq!(dense.len(), 2 * 10 * w as usize * h as usize);
        assert!((dense.iter().map(|&v| v as f64).sum::<f64>() - n as f64).abs() < 1e-2 * n as f64);
    }
}
