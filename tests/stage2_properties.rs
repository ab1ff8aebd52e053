//! Property tests of voxelize + the samplers.

use proptest::prelude::*;
use std::collections::HashMap;
use v2ce::stage2::SamplerKind;
use v2ce::{voxelize, Event, Interval, VoxelGrid};

const W: u16 = 5;
const H: u16 = 3;

fn counts(events: &[Event]) -> HashMap<(u16, u16, bool), usize> {
    let mut m = HashMap::new();
    for e in events {
        *m.entry((e.x, e.y, e.on)).or_insert(0) += 1;
    }
    m
}

fn arb_events(max_t: i64) -> impl Strategy<Value = Vec<Event>> {
    prop::collection::vec(
        (0..max_t, 0..W, 0..H, any::<bool>()).prop_map(|(t, x, y, on)| Event::new(t, x, y, on)),
        0..400,
    )
}

fn run(kind: SamplerKind, grid: &VoxelGrid, iv: Interval) -> Vec<Event> {
    let mut out = Vec::new();
    kind.build(9).sample(grid, iv, &mut out);
    out
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]

    /// voxelize -> ldati (and moment, and ldati-random) keeps every cell's event count: PGER = 1.
    #[test]
    fn chain_samplers_preserve_counts(
        events in arb_events(40_000),
        start in -(1i64 << 40)..(1i64 << 40),
        dur in 9i64..200_000,
    ) {
        let iv = Interval::new(start, start + dur).unwrap();
        let events: Vec<Event> = events
            .into_iter()
            .map(|e| Event { t: start + e.t % dur, ..e })
            .collect();
        let grid = voxelize(&events, iv, W, H, 10).unwrap();
        for kind in [SamplerKind::Ldati, SamplerKind::LdatiRandom, SamplerKind::Moment, SamplerKind::Spatial] {
            let out = run(kind, &grid, iv);
            prop_assert_eq!(counts(&out), counts(&events), "{}", kind);
            prop_assert!(out.iter().all(|e| iv.contains(e.t)));
            prop_assert!(out.windows(2).all(|w| w[0].order_key() <= w[1].order_key()));
        }
    }
}

/// A value a model might emit, including the broken ones.
fn arb_value() -> impl Strategy<Value = f64> {
    prop_oneof![
        4 => Just(0.0),
        4 => 0.0..3.0f64,
        1 => 0.0..1e-5f64,
        1 => 3.0..200.0f64,
        1 => -2.0..0.0f64,
        1 => Just(f64::NAN),
        1 => Just(f64::INFINITY),
        1 => Just(f64::NEG_INFINITY),
        1 => (0u32..200).prop_map(|n| n as f64),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]

    /// A cell with at most one event per sub-interval comes back within 1 us (here: exactly,
    /// since timestamps are rounded to the nearest microsecond).
    #[test]
    fn single_events_per_sub_interval_are_recovered(
        picks in prop::collection::vec((0usize..9, 0.0..1.0f64), 0..12),
        start in -(1i64 << 45)..(1i64 << 45),
        dur in 9i64..1_000_000,
    ) {
        let iv = Interval::new(start, start + dur).unwrap();
        let mut used = [false; 9];
        let mut truth = Vec::new();
        for (sub, f) in picks {
            let t = start + ((sub as f64 + f) * dur as f64 / 9.0).floor() as i64;
            let tau = (t - start) as f64 * 9.0 / dur as f64;
            let s = (tau.floor() as usize).min(8);
            if !used[s] && iv.contains(t) {
                used[s] = true;
                truth.push(Event::new(t, 1, 2, true));
            }
        }
        truth.sort_by_key(|e| e.t);
        let grid = voxelize(&truth, iv, W, H, 10).unwrap();
        for kind in [SamplerKind::Ldati, SamplerKind::LdatiRandom, SamplerKind::Moment, SamplerKind::Spatial] {
            let out = run(kind, &grid, iv);
            prop_assert_eq!(out.len(), truth.len());
            for (o, t) in out.iter().zip(&truth) {
                prop_assert!((o.t - t.t).abs() <= 1, "{}: {} vs {}", kind, o.t, t.t);
            }
        }
    }

    /// No sampler panics or emits a time outside the interval, whatever the voxel holds; the
    /// NaN/Inf and negative values are counted.
    #[test]
    fn any_voxel_is_sampled_safely(
        cells in prop::collection::vec(
            (0..W, 0..H, any::<bool>(), prop::collection::vec(arb_value(), 10)),
            0..12,
        ),
        start in any::<i32>(),
        dur in 1i64..100_000,
    ) {
        let iv = Interval::new(start as i64, start as i64 + dur).unwrap();
        let mut grid = VoxelGrid::new(W, H, 10).unwrap();
        let (mut nonfinite, mut negative) = (0, 0);
        for (x, y, on, values) in &cells {
            grid.push_cell(*x, *y, *on, values).unwrap();
            nonfinite += values.iter().filter(|v| !v.is_finite()).count() as u64;
            negative += values.iter().filter(|v| v.is_finite() && **v < 0.0).count() as u64;
        }
        for kind in SamplerKind::ALL {
            let mut out = Vec::new();
            let stats = kind.build(3).sample(&grid, iv, &mut out);
            prop_assert_eq!((stats.nonfinite, stats.negative), (nonfinite, negative));
            prop_assert!(out.iter().all(|e| iv.contains(e.t)), "{}", kind);
            // Same seed, same events.
            let mut again = Vec::new();
            kind.build(3).sample(&grid, iv, &mut again);
            prop_assert_eq!(&out, &again);
        }
    }
}
