use super::*;

/// A smooth texture (no period under about 14 px), 8-bit.
fn texture(x: f64, y: f64) -> f64 {
    128.0 + 60.0 * (x * 0.31).sin() * (y * 0.23).cos() + 40.0 * (x * 0.11 + y * 0.17).sin()
}

/// Frames `a` and `b` of `w x h` where the content at `p` in `a` is at `motion(p)` in `b`
/// (`inverse` maps a pixel of `b` back to where it came from).
fn pair(w: usize, h: usize, inverse: impl Fn(f64, f64) -> (f64, f64)) -> (Vec<u8>, Vec<u8>) {
    let a = (0..w * h)
        .map(|i| texture((i % w) as f64, (i / w) as f64) as u8)
        .collect();
    let b = (0..w * h)
        .map(|i| {
            let (x, y) = inverse((i % w) as f64, (i / w) as f64);
            texture(x, y) as u8
        })
        .collect();
    (a, b)
}

/// The median and 90th percentile end-point error against `truth` over the pixels at least
/// `border` from the frame's edges.
fn errors(
    flow: &[[f32; 2]],
    w: usize,
    h: usize,
    border: usize,
    truth: impl Fn(f64, f64) -> (f64, f64),
) -> (f64, f64) {
    let mut err = Vec::new();
    for y in border..h - border {
        for x in border..w - border {
            let f = flow[y * w + x];
            let (tx, ty) = truth(x as f64, y as f64);
            err.push(((f[0] as f64 - tx).powi(2) + (f[1] as f64 - ty).powi(2)).sqrt());
        }
    }
    err.sort_by(f64::total_cmp);
    (err[err.len() / 2], err[err.len() * 9 / 10])
}

const PRESETS: [FlowPreset; 3] = [FlowPreset::Ultrafast, FlowPreset::Fast, FlowPreset::Medium];

fn flow_of(
    backend: FlowBackend,
    preset: FlowPreset,
    w: usize,
    h: usize,
    a: &[u8],
    b: &[u8],
) -> Vec<[f32; 2]> {
    let mut flow = DenseFlow::new(backend, preset, w as u16, h as u16).unwrap();
    let mut out = Vec::new();
    flow.compute(a, b, &mut out).unwrap();
    out
}

/// A shifted texture comes back as its shift, with every preset.
#[test]
fn a_shifted_texture_gives_its_shift() {
    let (w, h) = (96usize, 64usize);
    for (dx, dy) in [(8.0, -1.25), (-3.5, 2.75), (0.4, 0.0)] {
        let (a, b) = pair(w, h, |x, y| (x - dx, y - dy));
        for preset in PRESETS {
            let out = flow_of(FlowBackend::Dis, preset, w, h, &a, &b);
            let (median, p90) = errors(&out, w, h, 10, |_, _| (dx, dy));
            // Measured: medians 0.02-0.06 px.
            assert!(
                median < 0.25 && p90 < 0.6,
                "{preset:?} ({dx}, {dy}): {median} / {p90}"
            );
        }
    }
}

/// A rotation and a zoom about the frame's centre: a flow that changes across the frame.
#[test]
fn a_rotation_and_a_zoom_give_their_flow() {
    let (w, h) = (160usize, 120usize);
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    // 3 degrees: 4 px at the frame's corners.
    let a = 3f64.to_radians();
    let (c, s) = (a.cos(), a.sin());
    let rotation = |x: f64, y: f64| {
        let (u, v) = (x - cx, y - cy);
        (c * u - s * v + cx - x, s * u + c * v + cy - y)
    };
    let (fa, fb) = pair(w, h, |x, y| {
        let (u, v) = (x - cx, y - cy);
        (c * u + s * v + cx, -s * u + c * v + cy)
    });
    for preset in PRESETS {
        let out = flow_of(FlowBackend::Dis, preset, w, h, &fa, &fb);
        let (median, p90) = errors(&out, w, h, 12, rotation);
        assert!(
            median < 0.3 && p90 < 0.8,
            "rotation, {preset:?}: {median} / {p90}"
        );
    }
    // A zoom of 5%: 4 px at the left and right edges.
    let k = 1.05;
    let zoom = |x: f64, y: f64| ((k - 1.0) * (x - cx), (k - 1.0) * (y - cy));
    let (fa, fb) = pair(w, h, |x, y| ((x - cx) / k + cx, (y - cy) / k + cy));
    for preset in PRESETS {
        let out = flow_of(FlowBackend::Dis, preset, w, h, &fa, &fb);
        let (median, p90) = errors(&out, w, h, 12, zoom);
        assert!(
            median < 0.3 && p90 < 0.8,
            "zoom, {preset:?}: {median} / {p90}"
        );
    }
}

/// With a region, the flow is the whole frame's on the region's tiles, zero elsewhere.
#[test]
fn a_region_restricts_the_flow() {
    let (w, h) = (128usize, 96usize);
    let (a, b) = pair(w, h, |x, y| (x - 3.0, y - 1.0));
    let tile = 16;
    let (tx, ty) = (w / tile, h / tile);
    // Two tiles far apart.
    let mut active = vec![false; tx * ty];
    active[tx + 1] = true;
    active[4 * tx + 6] = true;
    let region = Region::new(tile, tx, &active);
    assert_eq!(region.count(), 2);
    let mut flow = DenseFlow::new(FlowBackend::Dis, FlowPreset::Fast, w as u16, h as u16).unwrap();
    let (mut p0, mut p1) = (Pyramid::new(), Pyramid::new());
    p0.set(w, h, |g| g.extend_from_slice(&a));
    p1.set(w, h, |g| g.extend_from_slice(&b));
    let (first, last) = flow.levels().unwrap();
    p0.ensure(first, last);
    p1.ensure(first, last);
    let mut out = Vec::new();
    flow.compute_on(&p0, &p1, Some(&region), &mut out).unwrap();
    for y in 0..h {
        for x in 0..w {
            let on = active[(y / tile) * tx + x / tile];
            let [u, v] = out[y * w + x];
            if on {
                let e = ((u - 3.0).powi(2) + (v - 1.0).powi(2)).sqrt();
                assert!(e < 0.5, "({x}, {y}): {u}, {v}");
            } else {
                assert_eq!([u, v], [0.0, 0.0], "({x}, {y})");
            }
        }
    }
    // No active tile: no flow anywhere.
    let empty = Region::new(tile, tx, &vec![false; tx * ty]);
    flow.compute_on(&p0, &p1, Some(&empty), &mut out).unwrap();
    assert!(out.iter().all(|&f| f == [0.0, 0.0]));
}

/// The region's rectangle queries against the tiles one by one.
#[test]
fn region_queries_match_the_tiles() {
    let (tile, tx, ty) = (8usize, 5usize, 4usize);
    let active: Vec<bool> = (0..tx * ty).map(|i| i % 7 == 3).collect();
    let r = Region::new(tile, tx, &active);
    for (x0, y0, x1, y1) in [
        (-20, -20, 100, 100),
        (0, 0, 8, 8),
        (24, 0, 32, 8),
        (9, 9, 10, 10),
        (-5, 17, 3, 30),
        (39, 31, 80, 90),
    ] {
        let mut want = false;
        for j in 0..ty {
            for i in 0..tx {
                let (a, b) = ((i * tile) as isize, (j * tile) as isize);
                let meets = a < x1 && a + tile as isize > x0 && b < y1 && b + tile as isize > y0;
                want |= meets && active[j * tx + i];
            }
        }
        assert_eq!(r.any(x0, y0, x1, y1), want, "({x0}, {y0}) - ({x1}, {y1})");
    }
    let spans: Vec<_> = r.row_spans(9, 37).collect();
    let want: Vec<_> = (0..tx)
        .filter(|&i| active[tx + i])
        .map(|i| i * tile..((i + 1) * tile).min(37))
        .collect();
    assert_eq!(spans, want);
}

/// Bad input: frames of the wrong size are an error; frames too small for a patch are an
/// error; flat, black and saturated frames give a finite flow of zero.
#[test]
fn bad_input_is_an_error_or_a_still_flow() {
    let mut flow = DenseFlow::new(FlowBackend::Dis, FlowPreset::Fast, 8, 8).unwrap();
    let mut out = Vec::new();
    assert!(flow.compute(&[0; 64], &[0; 63], &mut out).is_err());
    let mut tiny = DenseFlow::new(FlowBackend::Dis, FlowPreset::Fast, 6, 40).unwrap();
    let err = tiny.compute(&[9; 240], &[9; 240], &mut out).unwrap_err();
    assert!(err.to_string().contains("patch"), "{err}");
    for preset in PRESETS {
        for (a, b) in [(0u8, 0u8), (255, 255), (0, 255), (90, 140)] {
            let (w, h) = (64usize, 48usize);
            let out = flow_of(
                FlowBackend::Dis,
                preset,
                w,
                h,
                &vec![a; w * h],
                &vec![b; w * h],
            );
            assert!(
                out.iter().all(|&f| f == [0.0, 0.0]),
                "{preset:?} {a} -> {b}"
            );
        }
    }
    // Noise against noise: finite, bounded by the frame.
    let (w, h) = (64usize, 48usize);
    let noise = |seed: u64| -> Vec<u8> {
        (0..w * h)
            .map(|i| ((i as u64 * 2_654_435_761 + seed).wrapping_mul(0x9E37_79B9) >> 24) as u8)
            .collect()
    };
    let out = flow_of(
        FlowBackend::Dis,
        FlowPreset::Medium,
        w,
        h,
        &noise(1),
        &noise(2),
    );
    assert!(out
        .iter()
        .all(|f| f[0].abs() <= w as f32 + 16.0 && f[1].abs() <= h as f32 + 16.0));
}

#[cfg(not(feature = "opencv-flow"))]
#[test]
fn the_opencv_backend_needs_its_feature() {
    let err = DenseFlow::new(FlowBackend::Opencv, FlowPreset::Fast, 64, 64)
        .err()
        .unwrap();
    assert!(err.to_string().contains("opencv-flow"), "{err}");
}

/// The project's DIS against OpenCV's on the same frames: the shift, the rotation and the
/// zoom, each no worse than OpenCV's error plus a tenth of a pixel.
#[cfg(feature = "opencv-flow")]
#[test]
fn the_flow_is_as_good_as_opencvs() {
    let (w, h) = (160usize, 120usize);
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    let a = 3f64.to_radians();
    let (c, s) = (a.cos(), a.sin());
    type Case = (
        Box<dyn Fn(f64, f64) -> (f64, f64)>,
        Box<dyn Fn(f64, f64) -> (f64, f64)>,
    );
    let cases: Vec<(&str, Case)> = vec![
        (
            "shift",
            (
                Box::new(|x, y| (x - 5.5, y + 2.25)),
                Box::new(|_, _| (5.5, -2.25)),
            ),
        ),
        (
            "rotation",
            (
                Box::new(move |x, y| {
                    let (u, v) = (x - cx, y - cy);
                    (c * u + s * v + cx, -s * u + c * v + cy)
                }),
                Box::new(move |x, y| {
                    let (u, v) = (x - cx, y - cy);
                    (c * u - s * v + cx - x, s * u + c * v + cy - y)
                }),
            ),
        ),
    ];
    for (name, (inverse, truth)) in cases {
        let (fa, fb) = pair(w, h, inverse);
        for preset in PRESETS {
            let ours = flow_of(FlowBackend::Dis, preset, w, h, &fa, &fb);
            let theirs = flow_of(FlowBackend::Opencv, preset, w, h, &fa, &fb);
            let (m0, p0) = errors(&ours, w, h, 12, &truth);
            let (m1, p1) = errors(&theirs, w, h, 12, &truth);
            assert!(
                m0 <= m1 + 0.1 && p0 <= p1 + 0.1,
                "{name} {preset:?}: ours {m0} / {p0}, OpenCV {m1} / {p1}"
            );
        }
    }
}
