//! Stage 2 throughput on real-recording voxels, single thread: voxelize, and each sampler.
//!
//! Uses ../shared/data/davis346 (346 x 260, APS frame intervals) and dvxplorer (320 x 240, 30 fps
//! intervals) when present (or `V2CE_DATA`); otherwise the built-in synthetic scene at 346 x 260,
//! and says so; and the synthetic scene at 1280 x 720 always. Throughput is reported in intervals per second.

use std::path::PathBuf;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use v2ce::format::{self, Recording};
use v2ce::interval::{fixed_intervals, intervals_from_frames, Interval};
use v2ce::stage2::SamplerKind;
use v2ce::{VoxelGrid, Voxelizer};

struct Case {
    name: &'static str,
    recording: Recording,
    intervals: Vec<Interval>,
}

fn cases() -> Vec<Case> {
    let dir = std::env::var_os("V2CE_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    let mut out = Vec::new();
    let davis = dir.join("davis346/davis346.aedat4");
    if let (Ok(rec), Ok(frames)) = (
        format::read_events(&davis),
        format::read_frame_times(&davis),
    ) {
        if let Ok(intervals) = intervals_from_frames(&frames) {
            out.push(Case {
                name: "davis346",
                recording: rec,
                intervals,
            });
        }
    }
    if let Ok(rec) = format::read_events(&dir.join("dvxplorer/data_sample.aedat4")) {
        let ev = rec.events.events();
        if let Ok(intervals) = fixed_intervals(ev[0].t, ev[ev.len() - 1].t, 30.0) {
            out.push(Case {
                name: "dvxplorer",
                recording: rec,
                intervals,
            });
        }
    }
    // Always: the synthetic scene at 1280 x 720 (an HD sensor's cost per interval).
    out.push(Case {
        name: "synthetic1280x720",
        recording: v2ce::sweeping_bar::recording(1280, 720, 1_000_000, 1),
        intervals: fixed_intervals(0, 999_999, 30.0).expect("valid rate"),
    });
    if out.len() == 1 {
        eprintln!(
            "no recordings under {}: benchmarking the synthetic scene",
            dir.display()
        );
        out.push(Case {
            name: "synthetic346",
            recording: v2ce::sweeping_bar::recording(346, 260, 2_000_000, 1),
            intervals: fixed_intervals(0, 1_999_999, 30.0).expect("valid rate"),
        });
    }
    out
}

fn bench(c: &mut Criterion) {
    for case in cases() {
        let rec = &case.recording;
        let mut voxelizer = Voxelizer::new(rec.width, rec.height, 10).expect("sensor size");
        let slices: Vec<_> = case
            .intervals
            .iter()
            .map(|iv| rec.events.time_slice(iv.start(), iv.end()))
            .collect();
        let grids: Vec<VoxelGrid> = case
            .intervals
            .iter()
            .zip(&slices)
            .map(|(iv, ev)| {
                voxelizer
                    .voxelize(ev, *iv)
                    .expect("events inside the sensor")
            })
            .collect();
        let mut group = c.benchmark_group(format!("stage2/{}", case.name));
        group.throughput(Throughput::Elements(case.intervals.len() as u64));
        group.sample_size(20);
        let mut grid = VoxelGrid::new(rec.width, rec.height, 10).expect("sensor size");
        group.bench_function("voxelize", |b| {
            b.iter(|| {
                for (iv, ev) in case.intervals.iter().zip(&slices) {
                    voxelizer
                        .voxelize_into(ev, *iv, &mut grid)
                        .expect("events inside the sensor");
                }
                grid.active_cells()
            })
        });
        let mut out = Vec::new();
        for kind in SamplerKind::ALL {
            let sampler = kind.build(1);
            group.bench_with_input(
                BenchmarkId::new("sample", kind.name()),
                &grids,
                |b, grids| {
                    b.iter(|| {
                        let mut n = 0;
                        for (grid, iv) in grids.iter().zip(&case.intervals) {
                            out.clear();
                            sampler.sample(grid, *iv, &mut out);
                            n += out.len();
                        }
                        n
                    })
                },
            );
        }
        group.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
