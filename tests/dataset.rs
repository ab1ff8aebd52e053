//! `v2ce dataset`: synthetic training data is reproducible from its seed and reads in NumPy
//! as the trainer expects; a recording's windows hold exactly its real events, halves apart.

mod common;

use std::path::Path;
use std::process::Command;

fn v2ce(args: &[&str]) -> std::process::Output {
    let out = Command::new(env!("CARGO_BIN_EXE_v2ce"))
        .args(args)
        .output()
        .expect("run v2ce");
    assert!(
        out.status.success(),
        "v2ce {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn manifest(dir: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(dir.join("dataset.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

/// NumPy's view of every sequence: shapes, types, and checks that the voxels hold the
/// manifest's events, are finite and not negative, and that times increase. Prints "ok N".
const CHECK: &str = r#"
import json, sys
import numpy as np
d = sys.argv[1]
m = json.load(open(d + "/dataset.json"))
p, (w, h) = m["pairs"], m["size"]
for s in m["sequences"]:
    z = np.load(d + "/" + s["file"])
    f, v, t = z["frames"], z["voxels"], z["times_us"]
    assert f.dtype == np.uint8 and f.shape == (p + 1, h, w), (f.dtype, f.shape)
    assert v.dtype == np.float32 and v.shape == (p, 20, h, w), (v.dtype, v.shape)
    assert t.dtype == np.int64 and t.shape == (p + 1,) and (np.diff(t) > 0).all()
    assert np.isfinite(v).all() and (v >= 0).all()
    assert abs(float(v.sum(dtype=np.float64)) - s["events"]) < 1e-3 * max(1, s["events"]), (v.sum(), s["events"])
print("ok", len(m["sequences"]))
"#;

fn numpy_check(py: &Path, dir: &Path) {
    let out = Command::new(py)
        .args(["-c", CHECK])
        .arg(dir)
        .output()
        .expect("run python");
    assert!(
        out.status.success(),
        "numpy check: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{}", String::from_utf8_lossy(&out.stdout).trim());
}

#[test]
fn synthetic_data_is_reproducible_from_its_seed_and_reads_in_numpy() {
    let dir = common::temp_dir("dataset-synthetic");
    let write = |name: &str, seed: &str, threads: &str| {
        let out = dir.join(name);
        v2ce(&[
            "dataset",
            "synthetic",
            "-o",
            out.to_str().unwrap(),
            "--count",
            "4",
            "--seed",
            seed,
            "--size",
            "48x32",
            "--pairs",
            "4",
            "--threads",
            threads,
        ]);
        out
    };
    let (a, b, c) = (
        write("a", "5", "2"),
        write("b", "5", "1"),
        write("c", "6", "2"),
    );
    let m = manifest(&a);
    assert_eq!(m["sequences"].as_array().unwrap().len(), 4);
    assert_eq!(m["kind"], "synthetic");
    for s in m["sequences"].as_array().unwrap() {
        let file = s["file"].as_str().unwrap();
        let bytes = std::fs::read(a.join(file)).unwrap();
        // The same seed gives the same bytes whatever the threads; another seed does not.
        assert_eq!(bytes, std::fs::read(b.join(file)).unwrap(), "{file}");
        assert_ne!(bytes, std::fs::read(c.join(file)).unwrap(), "{file}");
        assert!(s["rate_hz"].as_f64().unwrap() >= 1000.0, "{s}");
        let fps = s["fps"].as_f64().unwrap();
        assert!((25.0..=60.0).contains(&fps), "{s}");
    }
    // A scene may be still (a still camera, no objects, steady light): not all of them.
    let events: u64 = m["sequences"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["events"].as_u64().unwrap())
        .sum();
    assert!(events > 1000, "{events}");
    let py = python_or_skip!("synthetic_data_is_reproducible_from_its_seed_and_reads_in_numpy");
    numpy_check(&py, &a);
}

#[test]
fn bad_dataset_settings_are_errors() {
    let dir = common::temp_dir("dataset-bad");
    for extra in [
        &["--fps", "60..25"][..],
        &["--size", "4x4"],
        &["--rate", "10"],
        &["--pairs", "0"],
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_v2ce"))
            .args(["dataset", "synthetic", "-o"])
            .arg(dir.join("x"))
            .args(["--count", "1"])
            .args(extra)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{extra:?} was accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("v2ce: error"), "{extra:?}: {err}");
    }
}

#[test]
fn a_recordings_halves_hold_exactly_its_events_in_their_windows() {
    let data = match common::data_dir() {
        Ok(d) => d,
        Err(p) => {
            skipped!("SKIPPED: no recordings at {}", p.display());
            return;
        }
    };
    let rec = data.join("davis346/davis346.aedat4");
    let dir = common::temp_dir("dataset-recording");
    let mut windows = Vec::new();
    for split in ["first", "second"] {
        let out = dir.join(split);
        v2ce(&[
            "dataset",
            "recording",
            "--real",
            rec.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--split",
            split,
            "--pairs",
            "8",
        ]);
        let m = manifest(&out);
        let seqs = m["sequences"].as_array().unwrap().clone();
        // 58 intervals: 29 per half, three windows of 8 in each.
        assert_eq!(seqs.len(), 3, "{split}");
        windows.push((out, seqs));
    }
    let real = v2ce::format::read_events(&rec).unwrap();
    let times = v2ce::format::read_frame_times(&rec).unwrap();
    let (first, second) = (&windows[0].1, &windows[1].1);
    // The halves do not overlap: the second's first window starts at or after the first's last
    // window ends.
    let start = |s: &serde_json::Value| s["seed"].as_u64().unwrap() as usize;
    assert!(start(&second[0]) >= start(&first[2]) + 8);
    for (_, seqs) in &windows {
        for s in seqs {
            let k = start(s);
            let (t0, t1) = (times[k], times[k + 8]);
            let n = real
                .events
                .events()
                .iter()
                .filter(|e| e.t >= t0 && e.t < t1)
                .count() as u64;
            assert_eq!(s["events"].as_u64().unwrap(), n, "{s}");
        }
    }
    // `eval stage1 --split` scores the same halves: 29 intervals each, all real events once.
    let mut real_events = 0;
    for split in ["first", "second"] {
        let out = v2ce(&[
            "eval",
            "stage1",
            "--real",
            rec.to_str().unwrap(),
            "--split",
            split,
            "--json",
        ]);
        let m: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(m["intervals"], 29, "{split}");
        real_events += m["real_events"].as_u64().unwrap();
    }
    let inside = real
        .events
        .events()
        .iter()
        .filter(|e| e.t >= times[0] && e.t < times[58])
        .count() as u64;
    assert_eq!(real_events, inside);
    if let Some(py) = common::python() {
        numpy_check(&py, &windows[0].0);
    } else {
        skipped!("SKIPPED the NumPy check: no Python venv");
    }
}
