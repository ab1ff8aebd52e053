//! Property tests of voxelize + the samplers.

use proptest::prelude::*;
use std::collections::HashMap;
use v2ce::stage2::{Sampler, SamplerKind};
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
        for kind in [SamplerKind::Ldati, SamplerKind::LdatiRandom, SamplerKind::Moment] {
            let out = run(kind, &grid, iv);
            prop_assert_eq!(counts(&out), counts(&events), "{}", kind);
            prop_assert!(out.iter().all(|e| iv.contains(e.t)));
            prop_assert!(out.windows(2).all(|w| w[0].order_key() <= w[1].order_key()));
        }
    }
}
