//! The optical flow of one frame pair, one thread: the project's DIS against OpenCV's (built
//! with `--features opencv-flow`; OpenCV held to one thread by `OPENCV_FOR_THREADS_NUM=1`), at
//! each preset, both pyramids built inside the timing.
//!
//! Pairs: two frames of the bundled walk-by video (640 x 480, someone crossing a still room),
//! the whole frame and, for ours, only the tiles that changed (what the motion model asks
//! for); and two APS frames of the davis346 clip (346 x 260) when ../shared/data is there.
//!
//! `cargo bench --bench flow [--features opencv-flow]`.

use std::path::PathBuf;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use v2ce::flow::{DenseFlow, FlowBackend, FlowPreset, Pyramid, Region};

/// A frame pair in 8-bit gray.
struct Pair {
    name: &'static str,
    width: usize,
    height: usize,
    a: Vec<u8>,
    b: Vec<u8>,
}

fn gray(luma: &[u16]) -> Vec<u8> {
    let mut out = Vec::new();
    v2ce::frame::color::luma_to_gray(luma, 1.0, &mut out);
    out
}

fn pairs() -> Vec<Pair> {
    let mut out = Vec::new();
    let mut fixture = v2ce::frame::fixture::open().expect("the bundled fixture");
    let frames = v2ce::frame::read_frames(fixture.as_mut(), 64).expect("fixture frames");
    // Mid-way through the walk-by: someone in the middle of the room.
    let (a, b) = (&frames[60], &frames[61]);
    out.push(Pair {
        name: "fixture 640x480",
        width: a.width.into(),
        height: a.height.into(),
        a: gray(&a.luma),
        b: gray(&b.luma),
    });
    let data = std::env::var_os("V2CE_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    match v2ce::frame::aps::ApsSource::open(&data.join("davis346/davis346.aedat4")) {
        Ok(mut src) => {
            let frames = v2ce::frame::read_frames(&mut src, 32).expect("APS frames");
            let (a, b) = (&frames[20], &frames[21]);
            out.push(Pair {
                name: "davis346 346x260",
                width: a.width.into(),
                height: a.height.into(),
                a: gray(&a.luma),
                b: gray(&b.luma),
            });
        }
        Err(e) => eprintln!("flow bench: {e}: the davis346 pair is left out"),
    }
    out
}

/// The motion model's region: the 16 px tiles where some pixel changed by 16 levels, and their
/// neighbours.
fn changed_region(p: &Pair) -> Region {
    Region::around_changes(&p.a, &p.b, p.width, 16, 16).0
}

fn bench(c: &mut Criterion) {
    if std::env::var_os("OPENCV_FOR_THREADS_NUM").is_none() {
        std::env::set_var("OPENCV_FOR_THREADS_NUM", "1");
    }
    let mut group = c.benchmark_group("flow");
    group.sample_size(30);
    for pair in pairs() {
        let (w, h) = (pair.width as u16, pair.height as u16);
        for preset in [FlowPreset::Ultrafast, FlowPreset::Fast, FlowPreset::Medium] {
            let mut out = Vec::new();
            let mut ours = DenseFlow::new(FlowBackend::Dis, preset, w, h).expect("ours");
            group.bench_function(
                BenchmarkId::new(format!("dis/{}", preset.name()), pair.name),
                |b| b.iter(|| ours.compute(&pair.a, &pair.b, &mut out).expect("flow")),
            );
            // The motion model's way: the changed tiles only.
            let region = changed_region(&pair);
            let (first, last) = ours.levels().expect("levels");
            group.bench_function(
                BenchmarkId::new(format!("dis-changed/{}", preset.name()), pair.name),
                |b| {
                    b.iter(|| {
                        let (mut p0, mut p1) = (Pyramid::new(), Pyramid::new());
                        p0.set(pair.width, pair.height, |g| g.extend_from_slice(&pair.a));
                        p1.set(pair.width, pair.height, |g| g.extend_from_slice(&pair.b));
                        p0.ensure(first, last);
                        p1.ensure(first, last);
                        ours.compute_on(&p0, &p1, Some(&region), &mut out)
                            .expect("flow")
                    })
                },
            );
            if let Ok(mut cv) = DenseFlow::new(FlowBackend::Opencv, preset, w, h) {
                group.bench_function(
                    BenchmarkId::new(format!("opencv/{}", preset.name()), pair.name),
                    |b| b.iter(|| cv.compute(&pair.a, &pair.b, &mut out).expect("flow")),
                );
            }
        }
        let region = changed_region(&pair);
        eprintln!(
            "flow bench: {}: the changed tiles and their neighbours are {} of {}",
            pair.name,
            region.count(),
            pair.width.div_ceil(16) * pair.height.div_ceil(16)
        );
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
