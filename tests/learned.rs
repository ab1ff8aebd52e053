//! The learned tier end to end: a seeded checkpoint of the V2CE generator (written here, the
//! same bytes the PyTorch reference in `train/` loaded) is imported by `v2ce model import`,
//! run by `v2ce model run` and `v2ce convert --stage1 learned`, and compared with the reference
//! outputs committed in `tests/fixtures/learned/` (see its README). Also: a spectral norm
//! resolved another way fails the same comparison, and bad input gives clear errors.
//!
//! These tests need the ONNX Runtime library (`.venv` from `tests/python/requirements.txt`);
//! without it they print SKIPPED, unless `V2CE_REQUIRE_ORT` is set (CI), where they fail.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use ndarray::{ArrayD, IxDyn};

fn v2ce() -> Command {
    Command::new(env!("CARGO_BIN_EXE_v2ce"))
}

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/learned")
}

/// Whether ONNX Runtime can be found; panics when it cannot and `V2CE_REQUIRE_ORT` is set.
fn ort_available(test: &str) -> bool {
    match v2ce::stage1::learned::runtime::find_library(None) {
        Ok(_) => true,
        Err(e) if std::env::var_os("V2CE_REQUIRE_ORT").is_some() => {
            panic!("V2CE_REQUIRE_ORT is set but: {e}")
        }
        Err(e) => {
            skipped!("SKIPPED {test}: {e}");
            false
        }
    }
}

macro_rules! ort_or_skip {
    ($test:literal) => {
        if !ort_available($test) {
            return;
        }
    };
}

/// Runs a command, asserting success; returns stderr.
fn ok(cmd: &mut Command) -> String {
    let out = cmd.output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(out.status.success(), "{cmd:?} failed: {err}");
    err
}

/// Runs a command, asserting failure; returns stderr.
fn fails(cmd: &mut Command) -> String {
    let out = cmd.output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(!out.status.success(), "{cmd:?} should have failed: {err}");
    err
}

/// The seeded checkpoint (seed 7, `cuda:0` tags as the official file may have) and its
/// imports, made once per test run: (checkpoint, model by spectral-norm mode).
fn models() -> &'static (PathBuf, Vec<(String, PathBuf)>) {
    static MODELS: OnceLock<(PathBuf, Vec<(String, PathBuf)>)> = OnceLock::new();
    MODELS.get_or_init(|| {
        // Kept for the whole run (a static is never dropped), so one fixed folder, made anew
        // each run, rather than 800 MB more per run.
        let dir = std::env::temp_dir().join("v2ce-learned-models");
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let ckpt = dir.join("v2ce_seeded7.pt");
        let sd = v2ce::model::seeded::state_dict(7);
        v2ce::model::torch::write_state_dict(&ckpt, &sd, "cuda:0").unwrap();
        drop(sd);
        let mut models = Vec::new();
        for mode in ["power-iteration", "stored", "exact"] {
            let out = dir.join(format!("seeded7-{mode}.onnx"));
            ok(v2ce()
                .args(["model", "import"])
                .arg(&ckpt)
                .arg("-o")
                .arg(&out)
                .args(["--spectral-norm", mode]));
            models.push((mode.to_string(), out));
        }
        (ckpt, models)
    })
}

fn model(mode: &str) -> PathBuf {
    models()
        .1
        .iter()
        .find(|(m, _)| m == mode)
        .map(|(_, p)| p.clone())
        .unwrap()
}

/// 8-bit gray PNG as values in [0, 1].
fn gray(path: &Path) -> (usize, usize, Vec<f32>) {
    let img = image::open(path).unwrap().to_luma8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    (
        w,
        h,
        img.into_raw().iter().map(|&v| v as f32 / 255.0).collect(),
    )
}

/// The toolbox's input for 17 frames: (1, 16, 2, H, W), `(v - 0.153) / 0.165`.
fn network_input(frames: &[PathBuf]) -> ArrayD<f32> {
    assert_eq!(frames.len(), 17);
    let planes: Vec<(usize, usize, Vec<f32>)> = frames.iter().map(|p| gray(p)).collect();
    let (w, h) = (planes[0].0, planes[0].1);
    let norm = |v: f32| (v - 0.153f32) / 0.165f32;
    let mut data = Vec::with_capacity(16 * 2 * h * w);
    for j in 0..16 {
        for k in [j, j + 1] {
            data.extend(planes[k].2.iter().map(|&v| norm(v)));
        }
    }
    ArrayD::from_shape_vec(IxDyn(&[1, 16, 2, h, w]), data).unwrap()
}

struct Expected {
    values: Vec<f32>,
    stride: usize,
    max: f64,
    shape: Vec<usize>,
}

fn expected(name: &str) -> Expected {
    let meta: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(fixtures().join(format!("{name}_meta.json"))).unwrap(),
    )
    .unwrap();
    let values: ndarray::Array1<f32> =
        ndarray_npy::read_npy(fixtures().join(format!("{name}_values.npy"))).unwrap();
    Expected {
        values: values.to_vec(),
        stride: meta["stride"].as_u64().unwrap() as usize,
        max: meta["max"].as_f64().unwrap(),
        shape: meta["shape"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap() as usize)
            .collect(),
    }
}

/// Largest deviation from the reference at the fixture's sampled positions, relative to the
/// reference output's largest value.
fn deviation(out: &ArrayD<f32>, e: &Expected) -> f64 {
    assert_eq!(out.shape(), &e.shape[..]);
    let flat: Vec<f32> = out.iter().copied().collect();
    let sampled: Vec<f32> = flat.iter().step_by(e.stride).copied().collect();
    assert_eq!(sampled.len(), e.values.len());
    let worst = sampled
        .iter()
        .zip(&e.values)
        .map(|(a, b)| (*a as f64 - *b as f64).abs())
        .fold(0.0, f64::max);
    worst / e.max
}

/// `v2ce model run MODEL` on 17 frames; the output tensor.
fn run_model(model: &Path, frames: &[PathBuf], tag: &str) -> ArrayD<f32> {
    let dir = common::temp_dir(&format!("learned-run-{tag}"));
    let input = dir.join("in.npy");
    let output = dir.join("out.npy");
    ndarray_npy::write_npy(&input, &network_input(frames)).unwrap();
    ok(v2ce()
        .args(["model", "run"])
        .arg(model)
        .arg("--input-npy")
        .arg(&input)
        .arg("--output-npy")
        .arg(&output));
    ndarray_npy::read_npy(&output).unwrap()
}

fn crop_frames() -> Vec<PathBuf> {
    let mut f: Vec<PathBuf> = std::fs::read_dir(fixtures().join("frames_61x83"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    f.sort();
    f
}

#[test]
fn the_seeded_checkpoint_is_the_one_the_reference_used() {
    // Every entry's first values and the digest of all entries, from the Python rule.
    let digest: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(fixtures().join("seeded7_digest.json")).unwrap(),
    )
    .unwrap();
    let sd = v2ce::model::seeded::state_dict(7);
    let entries = digest["entries"].as_array().unwrap();
    assert_eq!(sd.len(), entries.len());
    for ((key, tensor), e) in sd.iter().zip(entries) {
        assert_eq!(key, e["key"].as_str().unwrap());
        let shape: Vec<usize> = e["shape"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap() as usize)
            .collect();
        assert_eq!(tensor.shape, shape, "{key}");
        if let Some(values) = tensor.as_f32() {
            for (a, b) in values.iter().zip(e["first"].as_array().unwrap()) {
                assert_eq!(*a, b.as_f64().unwrap() as f32, "{key}");
            }
        }
    }
}

#[test]
fn import_and_run_reproduce_the_reference_at_61x83() {
    ort_or_skip!("import_and_run_reproduce_the_reference_at_61x83");
    let out = run_model(&model("power-iteration"), &crop_frames()[..17], "61");
    let dev = deviation(&out, &expected("parity_61x83"));
    eprintln!("61x83: max deviation {dev:.2e} of the largest output");
    assert!(dev <= 1e-4, "{dev}");
}

#[test]
fn a_spectral_norm_resolved_another_way_fails_the_parity_check() {
    ort_or_skip!("a_spectral_norm_resolved_another_way_fails_the_parity_check");
    let e = expected("parity_61x83");
    for mode in ["stored", "exact"] {
        let out = run_model(&model(mode), &crop_frames()[..17], mode);
        let dev = deviation(&out, &e);
        eprintln!("spectral norm {mode}: max deviation {dev:.2e} of the largest output");
        assert!(dev > 1e-2, "{mode}: {dev}");
    }
}

#[test]
fn import_and_run_reproduce_the_reference_at_260x346() {
    ort_or_skip!("import_and_run_reproduce_the_reference_at_260x346");
    let d = data_or_skip!("import_and_run_reproduce_the_reference_at_260x346");
    let images = d.join("davis346/ijrr_export/images");
    let frames: Vec<PathBuf> = (0..17)
        .map(|i| images.join(format!("frame_{i:08}.png")))
        .collect();
    let out = run_model(&model("power-iteration"), &frames, "260");
    let dev = deviation(&out, &expected("parity_260x346"));
    eprintln!("260x346: max deviation {dev:.2e} of the largest output");
    assert!(dev <= 1e-4, "{dev}");
}

#[test]
fn convert_plans_and_merges_windows_as_the_reference() {
    ort_or_skip!("convert_plans_and_merges_windows_as_the_reference");
    let dir = common::temp_dir("learned-e2e");
    let voxels = dir.join("v.npy");
    let events = dir.join("ev.csv");
    let err = ok(v2ce()
        .arg("convert")
        .arg(fixtures().join("frames_61x83"))
        .args(["--stage1", "learned", "--model"])
        .arg(model("power-iteration"))
        .arg("--write-voxels")
        .arg(&voxels)
        .arg("-o")
        .arg(&events));
    assert!(err.contains("4 windows"), "{err}");
    let out: ArrayD<f32> = ndarray_npy::read_npy(&voxels).unwrap();
    let dev = deviation(&out, &expected("e2e_61x83"));
    eprintln!("59 frames, 4 windows: max deviation {dev:.2e} of the largest output");
    assert!(dev <= 1e-4, "{dev}");
    // Stage 2 re-timed them: events inside the frames' span, in time order.
    let rec = v2ce::format::read_events(&events).unwrap();
    let ev = rec.events.events();
    assert!(!ev.is_empty());
    assert!(ev.windows(2).all(|w| w[0].t <= w[1].t));
    assert!(ev.first().unwrap().t >= 250 && ev.last().unwrap().t <= 2_320_251);
    // Every interval of the 58 has events (a random-weight network fires everywhere).
    let per_interval = |k: i64| {
        ev.iter()
            .filter(|e| e.t >= 250 + 40_000 * k && e.t < 250 + 40_000 * (k + 1))
            .count()
    };
    assert!((0..57).all(|k| per_interval(k) > 0));
}

#[test]
fn bad_checkpoints_are_clear_errors_and_leave_no_model() {
    let dir = common::temp_dir("learned-bad");
    let out = dir.join("m.onnx");
    // Not an archive at all.
    let foreign = dir.join("foreign.pt");
    std::fs::write(&foreign, b"this is not a PyTorch checkpoint").unwrap();
    let err = fails(
        v2ce()
            .args(["model", "import"])
            .arg(&foreign)
            .arg("-o")
            .arg(&out),
    );
    assert!(err.contains("foreign.pt"), "{err}");
    // A real checkpoint cut short.
    let small = dir.join("small.pt");
    let mut sd = v2ce::model::seeded::state_dict(1);
    sd.truncate(40);
    v2ce::model::torch::write_state_dict(&small, &sd, "cpu").unwrap();
    let bytes = std::fs::read(&small).unwrap();
    let cut = dir.join("cut.pt");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    fails(
        v2ce()
            .args(["model", "import"])
            .arg(&cut)
            .arg("-o")
            .arg(&out),
    );
    // A whole archive missing keys: the first missing one is named.
    let err = fails(
        v2ce()
            .args(["model", "import"])
            .arg(&small)
            .arg("-o")
            .arg(&out),
    );
    assert!(
        err.contains("UNet.encoders.2.conv1.weight: missing"),
        "{err}"
    );
    assert!(!out.exists(), "a failed import left {}", out.display());
}

#[test]
fn a_missing_runtime_library_says_how_to_install_it() {
    let dir = common::temp_dir("learned-nolib");
    let run = || {
        fails(
            v2ce()
                .env("ORT_DYLIB_PATH", dir.join("libonnxruntime.so.1.31.1"))
                .args(["model", "run"])
                .arg(dir.join("m.onnx"))
                .arg("--input-npy")
                .arg(dir.join("in.npy"))
                .arg("--output-npy")
                .arg(dir.join("out.npy")),
        )
    };
    let err = run();
    assert!(err.contains("in.npy"), "{err}");
    // With an input, the library is the next thing missing.
    ndarray_npy::write_npy(
        dir.join("in.npy"),
        &ArrayD::<f32>::zeros(IxDyn(&[1, 2, 2, 4, 4])),
    )
    .unwrap();
    std::fs::write(dir.join("m.onnx"), b"not a model").unwrap();
    let err = run();
    assert!(err.contains("ORT_DYLIB_PATH"), "{err}");
    assert!(err.contains("pip install onnxruntime==1.31.1"), "{err}");
    assert!(!dir.join("out.npy").exists());
}

/// The interface of a [`tiny_model`].
#[derive(Clone, Copy, PartialEq)]
enum Tiny {
    /// V2CE's, every size dynamic but the channels.
    V2ce,
    /// V2CE's with a fixed number of pairs (an export without dynamic axes).
    FixedPairs(i64),
    /// (batch, 2, height, width): not a V2CE model.
    Rank4,
}

/// A tiny model for fast pipeline tests: each frame pair's two planes tiled to `2 * 10`
/// channels, then `op` (`Relu`: non-negative voxels that depend on their own pair alone; `Log`:
/// NaN where the normalised input is negative, as a broken model would give).
fn tiny_model(path: &Path, op: &str, interface: Tiny) {
    use v2ce::model::onnx::*;
    let pairs = match interface {
        Tiny::FixedPairs(p) => Ok(p),
        _ => Err("pairs"),
    };
    let dims5 = |c: i64| vec![Err("batch"), pairs, Ok(c), Err("height"), Err("width")];
    type Dims<'a> = Vec<Result<i64, &'a str>>;
    let (input, output, repeats): (Dims, Dims, Vec<i64>) = if interface == Tiny::Rank4 {
        (
            vec![Err("batch"), Ok(2), Err("height"), Err("width")],
            vec![Err("batch"), Ok(20), Err("height"), Err("width")],
            vec![1, 10, 1, 1],
        )
    } else {
        (dims5(2), dims5(20), vec![1, 1, 10, 1, 1])
    };
    let mut raw = Vec::new();
    for r in &repeats {
        raw.extend_from_slice(&r.to_le_bytes());
    }
    let repeats = TensorProto {
        dims: vec![repeats.len() as i64],
        data_type: Some(INT64),
        name: Some("repeats".into()),
        raw_data: Some(raw),
    };
    let graph = GraphProto {
        node: vec![
            node("Tile", "tile", &["frames", "repeats"], &["tiled"], vec![]),
            node(op, "op", &["tiled"], &["voxels"], vec![]),
        ],
        name: Some("tiny".into()),
        initializer: vec![repeats],
        input: vec![tensor_value("frames", FLOAT, &input)],
        output: vec![tensor_value("voxels", FLOAT, &output)],
        ..Default::default()
    };
    let model = model(graph, "v2ce tests", Vec::new());
    let mut file = std::fs::File::create(path).unwrap();
    write_model(model, &mut file).unwrap();
}

#[test]
fn a_model_with_another_interface_is_refused_clearly() {
    ort_or_skip!("a_model_with_another_interface_is_refused_clearly");
    let dir = common::temp_dir("learned-rank4");
    let model = dir.join("rank4.onnx");
    tiny_model(&model, "Relu", Tiny::Rank4);
    let err = fails(
        v2ce()
            .arg("convert")
            .arg(fixtures().join("frames_61x83"))
            .arg("--model")
            .arg(&model)
            .arg("-o")
            .arg(dir.join("ev.csv")),
    );
    assert!(err.contains("(batch, pairs, 2, height, width)"), "{err}");
    assert!(!dir.join("ev.csv").exists());
    // A raw tensor of the wrong rank for a good model.
    let good = dir.join("relu.onnx");
    tiny_model(&good, "Relu", Tiny::V2ce);
    let input = dir.join("in.npy");
    ndarray_npy::write_npy(&input, &ArrayD::<f32>::zeros(IxDyn(&[1, 2, 4, 4]))).unwrap();
    let err = fails(
        v2ce()
            .args(["model", "run"])
            .arg(&good)
            .arg("--input-npy")
            .arg(&input)
            .arg("--output-npy")
            .arg(dir.join("out.npy")),
    );
    assert!(err.contains("(B, L, 2, H, W)"), "{err}");
    assert!(!dir.join("out.npy").exists());
}

#[test]
fn nan_from_a_model_is_counted_and_repaired() {
    ort_or_skip!("nan_from_a_model_is_counted_and_repaired");
    let dir = common::temp_dir("learned-nan");
    let model = dir.join("log.onnx");
    tiny_model(&model, "Log", Tiny::V2ce);
    let events = dir.join("ev.csv");
    let err = ok(v2ce()
        .arg("convert")
        .arg(fixtures().join("frames_61x83"))
        .arg("--model")
        .arg(&model)
        .args(["--max-frames", "9"])
        .arg("-o")
        .arg(&events));
    // "the model gave N NaN/infinite values; Stage 2 repaired N non-finite, M negative, ..."
    let summary = err
        .lines()
        .find(|l| l.starts_with("v2ce: warning: the model gave"))
        .unwrap_or_else(|| panic!("no summary line in {err}"));
    let count = |after: &str| -> u64 {
        let at = summary
            .find(after)
            .unwrap_or_else(|| panic!("{after:?} in {summary}"));
        summary[..at]
            .split_whitespace()
            .last()
            .unwrap()
            .parse()
            .unwrap()
    };
    let nan = count(" NaN/infinite");
    assert!(nan > 0, "{err}");
    assert_eq!(count(" non-finite"), nan, "{err}");
    assert!(count(" negative") > 0, "{err}");
    // The finite positive values still made events.
    let rec = v2ce::format::read_events(&events).unwrap();
    assert!(!rec.events.events().is_empty());
}

#[test]
fn the_daemon_runs_overlapping_windows_and_flushes_at_the_end() {
    ort_or_skip!("the_daemon_runs_overlapping_windows_and_flushes_at_the_end");
    let dir = common::temp_dir("learned-daemon");
    let model = dir.join("relu.onnx");
    tiny_model(&model, "Relu", Tiny::V2ce);
    let out = dir.join("ev.csv");
    let run = v2ce()
        .arg("run")
        .arg("--source")
        .arg(fixtures().join("frames_61x83"))
        .args([
            "--udp",
            "",
            "--queue-policy",
            "block",
            "--replay-speed",
            "20",
        ])
        .arg("--out")
        .arg(&out)
        .arg("--model")
        .arg(&model)
        .args(["--window", "8", "--stride", "3", "--json"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{err}");
    let report: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    let s1 = &report["stage1"];
    assert_eq!(s1["tier"], "learned");
    assert_eq!(
        (s1["window"].as_u64(), s1["stride"].as_u64()),
        (Some(8), Some(3))
    );
    // 58 intervals: the first window hands on 8, then one every 3 frames hands on 3 (16
    // windows, 48 intervals), and at the end a window hands on the 2 left.
    assert_eq!(s1["learned"]["intervals"], 58);
    assert_eq!(s1["learned"]["windows"], 1 + 16 + 1);
    assert_eq!(s1["learned"]["pairs_run"], 8 * 18);
    let rec = v2ce::format::read_events(&out).unwrap();
    assert_eq!(
        rec.events.events().len() as u64,
        report["stats"]["events_out"].as_u64().unwrap()
    );
}

#[test]
fn writing_voxels_needs_a_tier_that_makes_them() {
    let dir = common::temp_dir("learned-novoxels");
    let err = fails(
        v2ce()
            .arg("convert")
            .arg(fixtures().join("frames_61x83"))
            .arg("--write-voxels")
            .arg(dir.join("v.npy"))
            .arg("-o")
            .arg(dir.join("ev.csv")),
    );
    assert!(err.contains("--mode voxels"), "{err}");
    assert!(!dir.join("v.npy").exists());
    assert!(
        !dir.join("v.npy.partial").exists(),
        "a failed run left its partial file"
    );
    // The physics tier in voxel mode writes them: one grid per interval.
    ok(v2ce()
        .arg("convert")
        .arg(fixtures().join("frames_61x83"))
        .args(["--mode", "voxels", "--max-frames", "6"])
        .arg("--write-voxels")
        .arg(dir.join("v.npy"))
        .arg("-o")
        .arg(dir.join("ev2.csv")));
    let v: ArrayD<f32> = ndarray_npy::read_npy(dir.join("v.npy")).unwrap();
    assert_eq!(v.shape(), &[5, 20, 61, 83]);
    // An existing output is kept unless --force.
    let err = fails(
        v2ce()
            .arg("convert")
            .arg(fixtures().join("frames_61x83"))
            .args(["--mode", "voxels", "--max-frames", "3"])
            .arg("--write-voxels")
            .arg(dir.join("v.npy"))
            .arg("-o")
            .arg(dir.join("ev3.csv")),
    );
    assert!(err.contains("--force"), "{err}");
    let kept: ArrayD<f32> = ndarray_npy::read_npy(dir.join("v.npy")).unwrap();
    assert_eq!(kept, v);
    ok(v2ce()
        .arg("convert")
        .arg(fixtures().join("frames_61x83"))
        .args(["--mode", "voxels", "--max-frames", "3", "--force"])
        .arg("--write-voxels")
        .arg(dir.join("v.npy"))
        .arg("-o")
        .arg(dir.join("ev2.csv")));
    let v: ArrayD<f32> = ndarray_npy::read_npy(dir.join("v.npy")).unwrap();
    assert_eq!(v.shape(), &[2, 20, 61, 83]);
}

#[test]
fn geometries_crop_and_tile_the_resized_frames_consistently() {
    ort_or_skip!("geometries_crop_and_tile_the_resized_frames_consistently");
    let dir = common::temp_dir("learned-geometry");
    let model = dir.join("relu.onnx");
    tiny_model(&model, "Relu", Tiny::V2ce);
    // Three 200 x 100 gray frames with structure everywhere.
    let frames = dir.join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    let mut bytes = Vec::new();
    for i in 0..3u32 {
        let img = image::GrayImage::from_fn(200, 100, |x, y| {
            image::Luma([((x * 7 + y * 13 + i * 40 + (x * y) % 23) % 256) as u8])
        });
        bytes.push(img.clone().into_raw());
        img.save(frames.join(format!("f{i}.png"))).unwrap();
    }
    let voxels = |geometry: &str| -> ArrayD<f32> {
        let v = dir.join(format!("{geometry}.npy"));
        ok(v2ce()
            .arg("convert")
            .arg(&frames)
            .args(["--fps", "10", "--model"])
            .arg(&model)
            .args(["--geometry", geometry])
            .arg("--write-voxels")
            .arg(&v)
            .arg("-o")
            .arg(dir.join(format!("{geometry}.csv"))));
        ndarray_npy::read_npy(&v).unwrap()
    };
    // Native: the PNG's own bytes through the toolbox's normalisation, exactly.
    let native = voxels("native");
    assert_eq!(native.shape(), &[2, 20, 100, 200]);
    for (j, c) in [(0usize, 0usize), (0, 1), (1, 0), (1, 19)] {
        let frame = &bytes[j + c % 2];
        for (k, &b) in frame.iter().enumerate().step_by(37) {
            let want = ((b as f32 / 255.0 - 0.153) / 0.165).max(0.0);
            assert_eq!(
                native[[j, c, k / 200, k % 200]],
                want,
                "interval {j} channel {c}"
            );
        }
    }
    // Resized to 260 rows: 520 columns; the centre crop and the panorama's tiles are parts of it.
    let resize = voxels("resize");
    assert_eq!(resize.shape(), &[2, 20, 260, 520]);
    let pano = voxels("pano");
    assert_eq!(pano, resize, "tiles at 0 and 174 assemble to the whole");
    let center = voxels("center");
    assert_eq!(center.shape(), &[2, 20, 260, 346]);
    let x0 = 520 / 2 - 173;
    let crop = resize
        .slice(ndarray::s![.., .., .., x0..x0 + 346])
        .to_owned();
    assert_eq!(center, crop.into_dyn());
}

/// The voxels `v2ce convert` writes for the fixture frames with `model` and extra flags.
fn convert_voxels(model: &Path, tag: &str, flags: &[&str]) -> ArrayD<f32> {
    let dir = common::temp_dir(&format!("learned-windows-{tag}"));
    let v = dir.join("v.npy");
    ok(v2ce()
        .arg("convert")
        .arg(fixtures().join("frames_61x83"))
        .arg("--model")
        .arg(model)
        .args(flags)
        .arg("--write-voxels")
        .arg(&v)
        .arg("-o")
        .arg(dir.join("ev.csv")));
    ndarray_npy::read_npy(&v).unwrap()
}

#[test]
fn every_window_setting_hands_on_each_interval_once_in_order() {
    ort_or_skip!("every_window_setting_hands_on_each_interval_once_in_order");
    // With a model whose output for a pair depends on that pair alone, any plan must give the
    // same voxels as the toolbox's: each interval once, in order, from the right pair.
    let dir = common::temp_dir("learned-windows");
    let model = dir.join("relu.onnx");
    tiny_model(&model, "Relu", Tiny::V2ce);
    let reference = convert_voxels(&model, "16", &[]);
    assert_eq!(reference.shape(), &[58, 20, 61, 83]);
    for (window, stride) in [("8", "3"), ("5", "5"), ("1", "1"), ("16", "7")] {
        let tag = format!("{window}-{stride}");
        let got = convert_voxels(&model, &tag, &["--window", window, "--stride", stride]);
        assert!(got == reference, "window {window} stride {stride}");
    }
    // A model fixing 16 pairs on a stream of 9 frames: padded in front, the 8 real intervals.
    let fixed = dir.join("fixed16.onnx");
    tiny_model(&fixed, "Relu", Tiny::FixedPairs(16));
    let got = convert_voxels(&fixed, "fixed", &["--max-frames", "9"]);
    let want = reference
        .slice(ndarray::s![..8, .., .., ..])
        .to_owned()
        .into_dyn();
    assert!(got == want, "fixed-pairs model on a short stream");
    // The same model refuses a window it cannot take.
    let err = fails(
        v2ce()
            .arg("convert")
            .arg(fixtures().join("frames_61x83"))
            .arg("--model")
            .arg(&fixed)
            .args(["--window", "8"])
            .arg("-o")
            .arg(dir.join("ev.csv")),
    );
    assert!(err.contains("fixed number of pairs of 16"), "{err}");
}

/// Stability at the extremes: black, saturated and still textured frames give no voxels and no
/// events whatever the model outputs there (a model that passes its input through, as `Relu`
/// does, answers a white frame with large values everywhere), and a single flickering pixel
/// gives voxels only in the tiles around it. Every voxel is finite and not negative. Without
/// the gate, the white frames would fire everywhere.
#[test]
fn where_nothing_changes_the_learned_tier_gives_nothing() {
    ort_or_skip!("where_nothing_changes_the_learned_tier_gives_nothing");
    let dir = common::temp_dir("learned-extremes");
    let model = dir.join("relu.onnx");
    tiny_model(&model, "Relu", Tiny::V2ce);
    let (w, h) = (64u32, 48u32);
    let texture = |x: u32, y: u32| ((x * 37 + y * 11) % 200 + 30) as u8;
    type Scene = Box<dyn Fn(u32, u32, u32) -> u8>;
    let scenes: [(&str, Scene); 4] = [
        ("black", Box::new(|_, _, _| 0)),
        ("white", Box::new(|_, _, _| 255)),
        ("still", Box::new(move |x, y, _| texture(x, y))),
        (
            "flicker",
            Box::new(move |x, y, i| {
                if (x, y) == (30, 20) {
                    if i % 2 == 0 {
                        0
                    } else {
                        255
                    }
                } else {
                    texture(x, y)
                }
            }),
        ),
    ];
    let convert = |frames: &Path, tag: &str, config: Option<&Path>| -> (ArrayD<f32>, usize) {
        let v = dir.join(format!("{tag}.npy"));
        let ev = dir.join(format!("{tag}.csv"));
        let mut cmd = v2ce();
        cmd.arg("convert")
            .arg(frames)
            .args(["--fps", "25", "--model"]);
        cmd.arg(&model)
            .arg("--write-voxels")
            .arg(&v)
            .arg("-o")
            .arg(&ev);
        if let Some(c) = config {
            cmd.arg("--config").arg(c);
        }
        ok(&mut cmd);
        let events = std::fs::read_to_string(&ev).unwrap().lines().count() - 1;
        (ndarray_npy::read_npy(&v).unwrap(), events)
    };
    for (name, scene) in &scenes {
        let frames = dir.join(name);
        std::fs::create_dir_all(&frames).unwrap();
        for i in 0..6 {
            image::GrayImage::from_fn(w, h, |x, y| image::Luma([scene(x, y, i)]))
                .save(frames.join(format!("f{i}.png")))
                .unwrap();
        }
        let (voxels, events) = convert(&frames, name, None);
        assert_eq!(voxels.shape(), &[5, 20, h as usize, w as usize], "{name}");
        assert!(voxels.iter().all(|v| v.is_finite() && *v >= 0.0), "{name}");
        if *name == "flicker" {
            // The pixel's tile (1, 1) and one tile around it: columns 0..48, rows 0..48.
            let mut inside = 0;
            for ((_, _, y, x), &v) in voxels
                .view()
                .into_dimensionality::<ndarray::Ix4>()
                .unwrap()
                .indexed_iter()
            {
                if v > 0.0 {
                    assert!(
                        x < 48 && y < 48,
                        "voxel at ({x}, {y}), far from the flicker"
                    );
                    inside += 1;
                }
            }
            assert!(inside > 0 && events > 0, "the flicker left no trace");
        } else {
            assert!(
                voxels.iter().all(|&v| v == 0.0),
                "{name}: voxels where nothing moved"
            );
            assert_eq!(events, 0, "{name}: events where nothing moved");
        }
    }
    let off = dir.join("gate-off.toml");
    std::fs::write(&off, "[stage1.learned]\ngate = false\n").unwrap();
    let (voxels, events) = convert(&dir.join("white"), "white-ungated", Some(&off));
    assert!(
        voxels.iter().any(|&v| v > 0.0) && events > 0,
        "the gate made no difference"
    );
}

/// `--stage1 learned` without a model runs the small model built into v2ce: finite,
/// non-negative voxels where a bar moves, nothing on still frames.
#[test]
fn the_built_in_model_runs_when_no_model_is_given() {
    ort_or_skip!("the_built_in_model_runs_when_no_model_is_given");
    let dir = common::temp_dir("learned-builtin");
    let (w, h) = (64u32, 48u32);
    for (name, speed) in [("moving", 6u32), ("still", 0)] {
        let frames = dir.join(name);
        std::fs::create_dir_all(&frames).unwrap();
        for i in 0..6u32 {
            image::GrayImage::from_fn(w, h, |x, y| {
                let bar = (x + 64 - (i * speed) % 64) % 64 < 10;
                image::Luma([if bar { 220 } else { 30 + (y % 7) as u8 }])
            })
            .save(frames.join(format!("f{i}.png")))
            .unwrap();
        }
        let v = dir.join(format!("{name}.npy"));
        let out = v2ce()
            .arg("convert")
            .arg(&frames)
            .args(["--fps", "25", "--stage1", "learned", "--write-voxels"])
            .arg(&v)
            .arg("-o")
            .arg(dir.join(format!("{name}.csv")))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{err}");
        assert!(err.contains("v2ce-small (built in)"), "{err}");
        let voxels: ArrayD<f32> = ndarray_npy::read_npy(&v).unwrap();
        assert_eq!(voxels.shape(), &[5, 20, h as usize, w as usize]);
        assert!(voxels.iter().all(|v| v.is_finite() && *v >= 0.0), "{name}");
        if name == "still" {
            assert!(voxels.iter().all(|&v| v == 0.0), "voxels on still frames");
        }
    }
    // A floor zeroes every output below it.
    let v = dir.join("floored.npy");
    ok(v2ce()
        .arg("convert")
        .arg(dir.join("moving"))
        .args([
            "--fps",
            "25",
            "--stage1",
            "learned",
            "--floor",
            "0.05",
            "--write-voxels",
        ])
        .arg(&v)
        .arg("-o")
        .arg(dir.join("floored.csv")));
    let voxels: ArrayD<f32> = ndarray_npy::read_npy(&v).unwrap();
    assert!(voxels.iter().all(|&v| v == 0.0 || v >= 0.05));
}

/// `v2ce bench tradeoff` measures every tier on the same synthetic sequences: a row per
/// setting with scores in range, and a Pareto front named from those rows.
#[test]
fn the_tradeoff_bench_measures_every_setting() {
    ort_or_skip!("the_tradeoff_bench_measures_every_setting");
    let dir = common::temp_dir("tradeoff");
    let plot = dir.join("front.png");
    let out = v2ce()
        .args([
            "bench",
            "tradeoff",
            "--synthetic",
            "2",
            "--size",
            "48x32",
            "--still",
            "1",
            "--still-size",
            "320x240",
            "--json",
        ])
        .arg("--plot")
        .arg(&plot)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rows: Vec<serde_json::Value> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    // 19 settings (8 physics, 11 learned) on 2 scene groups.
    assert_eq!(rows.len(), 38, "{rows:?}");
    // The plot: a panel per scene, points of both tiers' colours.
    let png = image::open(&plot).unwrap().to_rgb8();
    assert_eq!(png.dimensions(), (1440, 560));
    let count = |c: [u8; 3]| png.pixels().filter(|p| p.0 == c).count();
    assert!(count([31, 119, 180]) > 40, "no physics points");
    assert!(count([214, 39, 40]) > 40, "no learned points");
    for r in &rows {
        let compute = r["compute"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&compute), "{r}");
        let tf1 = r["tf1"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&tf1), "{r}");
        assert!(r["pairs_per_s"].as_f64().unwrap() > 0.0, "{r}");
        assert!(r["real_events"].as_u64().unwrap() > 0, "{r}");
        let pairs = if r["scene"].as_str().unwrap().starts_with("still") {
            16
        } else {
            32
        };
        assert_eq!(r["pairs"], pairs, "{r}");
    }
    let physics = rows
        .iter()
        .find(|r| r["setting"] == "physics davis346")
        .unwrap();
    // The ground truth is the same pixel model at 1 kHz: it scores well, not perfectly.
    assert!(physics["tf1"].as_f64().unwrap() > 0.3, "{physics}");
    // Seeing the motion between frames (the default) scores above interpolating linearly.
    let linear = rows
        .iter()
        .find(|r| r["setting"] == "physics davis346 linear" && r["scene"] == physics["scene"])
        .unwrap();
    assert!(
        physics["tf1"].as_f64().unwrap() > linear["tf1"].as_f64().unwrap(),
        "{physics} {linear}"
    );
    // On the still camera, crops with a narrower margin run on less of the frame, and the
    // whole-frame setting on all of what it runs.
    let still = |setting: &str| {
        rows.iter()
            .find(|r| {
                r["scene"].as_str().unwrap().starts_with("still")
                    && r["setting"].as_str().unwrap().ends_with(setting)
            })
            .unwrap()["compute"]
            .as_f64()
            .unwrap()
    };
    assert!(
        still("roi margin 32") < still("whole frames"),
        "{} vs {}",
        still("roi margin 32"),
        still("whole frames")
    );
}

/// The network runs only on crops around what changed (`roi`): with the model's own receptive
/// field as the margin the voxels are exactly the whole frame's, on less of the frame; with a
/// margin far inside the receptive field they are not (so the crops are really taken).
#[test]
fn crops_around_what_moved_give_the_whole_frames_voxels() {
    ort_or_skip!("crops_around_what_moved_give_the_whole_frames_voxels");
    let dir = common::temp_dir("learned-roi");
    let frames = dir.join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    let (w, h) = (320u32, 240u32);
    for i in 0..17u32 {
        let (sx, sy) = (20 + 3 * i, 24);
        image::GrayImage::from_fn(w, h, |x, y| {
            let v = if (sx..sx + 24).contains(&x) && (sy..sy + 24).contains(&y) {
                230
            } else {
                ((x * 37 + y * 11) % 120 + 40) as u8
            };
            image::Luma([v])
        })
        .save(frames.join(format!("f{i:02}.png")))
        .unwrap();
    }
    let convert = |tag: &str, flags: &[&str]| -> (ArrayD<f32>, String) {
        let v = dir.join(format!("{tag}.npy"));
        let out = v2ce()
            .arg("convert")
            .arg(&frames)
            .args(["--fps", "30", "--stage1", "learned", "--threads", "2"])
            .args(flags)
            .arg("--write-voxels")
            .arg(&v)
            .arg("-o")
            .arg(dir.join(format!("{tag}.csv")))
            .output()
            .unwrap();
        let log = String::from_utf8_lossy(&out.stderr).to_string();
        assert!(out.status.success(), "{tag}: {log}");
        (ndarray_npy::read_npy(&v).unwrap(), log)
    };
    let share = |log: &str| -> f64 {
        let at = log.find("ran on ").expect(log);
        let rest = &log[at + 7..];
        rest[..rest.find('%').unwrap()].parse().unwrap()
    };
    let (whole, log_whole) = convert("whole", &["--no-roi"]);
    let (roi, log_roi) = convert("roi", &[]);
    assert_eq!(share(&log_whole), 100.0);
    assert!(share(&log_roi) < 80.0, "{log_roi}");
    assert!(whole.iter().any(|&v| v > 0.0), "the square left no voxels");
    let differ = whole.iter().zip(roi.iter()).filter(|(a, b)| a != b).count();
    assert_eq!(differ, 0, "{differ} voxels differ from the whole frame's");
    eprintln!(
        "roi: {} voxels identical, the network on {}% of the pixels",
        whole.len(),
        share(&log_roi)
    );
    let (narrow, log_narrow) = convert("narrow", &["--roi-margin", "8"]);
    assert!(share(&log_narrow) < share(&log_roi), "{log_narrow}");
    let differ = whole
        .iter()
        .zip(narrow.iter())
        .filter(|(a, b)| (*a - *b).abs() > 1e-6)
        .count();
    assert!(differ > 0, "an 8-pixel margin changed nothing");
}

/// `--stage1 auto` takes the learned tier when there is no budget, the physics tier when the
/// network cannot hold the budget or cannot run at all, and says why.
#[test]
fn the_automatic_tier_follows_the_budget() {
    ort_or_skip!("the_automatic_tier_follows_the_budget");
    let dir = common::temp_dir("learned-auto");
    let run = |tag: &str, flags: &[&str]| -> String {
        let out = v2ce()
            .arg("convert")
            .arg(fixtures().join("frames_61x83"))
            .args(["--fps", "30", "--stage1", "auto", "--max-frames", "20"])
            .args(flags)
            .arg("-o")
            .arg(dir.join(format!("{tag}.csv")))
            .output()
            .unwrap();
        let log = String::from_utf8_lossy(&out.stderr).to_string();
        assert!(out.status.success(), "{tag}: {log}");
        log
    };
    let free = run("free", &["--budget-fps", "0"]);
    assert!(
        free.contains("Stage 1 learned") && free.contains("chosen by auto: no frame rate budget"),
        "{free}"
    );
    let tight = run("tight", &["--budget-fps", "100000"]);
    assert!(
        tight.contains("Stage 1 physics") && tight.contains("pairs/s on whole frames, less than"),
        "{tight}"
    );
    let missing = dir.join("missing.onnx");
    let broken = run("broken", &["--model", missing.to_str().unwrap()]);
    assert!(
        broken.contains("Stage 1 physics") && broken.contains("cannot run here"),
        "{broken}"
    );
    // The budget is checked like any setting.
    let err = fails(
        v2ce()
            .arg("convert")
            .arg(fixtures().join("frames_61x83"))
            .args([
                "--fps",
                "30",
                "--stage1",
                "auto",
                "--budget-fps",
                "nan",
                "-o",
            ])
            .arg(dir.join("nan.csv")),
    );
    assert!(err.contains("budget_fps"), "{err}");
}
