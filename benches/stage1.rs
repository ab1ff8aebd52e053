//! Stage 1 (physics tier) speed, single thread, side by side with eventcv on the same frames:
//! the `davis346` preset with linear interpolation and with its default motion model (sub-frames
//! along the optical flow; OpenCV held to one thread by `OPENCV_FOR_THREADS_NUM=1`).
//!
//! Workloads: the davis346 APS frames (a real moving scene, 59 frames at 346 x 260) when
//! ../shared/data is present, else a synthetic moving edge; the same frames upscaled to 640 x 480
//! (nearest neighbour); and a static scene (the first frame repeated) at both sizes. Our model is
//! timed on frames already in memory (median of 7 passes). eventcv (PyPI, from the project's
//! `.venv`, `RAYON_NUM_THREADS=1`, noise off and on) is timed on the same 8-bit frames, best of
//! 3, via `tools/eventcv_peer.py`; it is skipped with a note when the venv lacks it.
//!
//! `cargo bench --bench stage1` prints a Markdown table (`V2CE_BENCH_NO_PEER=1` skips eventcv).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use v2ce::frame::{Frame, FrameSource};
use v2ce::stage1::{Motion, PhysicsConfig, PhysicsSim, Preset};

/// 8-bit frames and their times.
struct Workload {
    name: String,
    width: u16,
    height: u16,
    times: Vec<i64>,
    pixels: Vec<Vec<u8>>,
}

fn load() -> Workload {
    let dir = std::env::var_os("V2CE_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    let path = dir.join("davis346/davis346.aedat4");
    let mut w = Workload {
        name: "davis346 APS (moving)".into(),
        width: 346,
        height: 260,
        times: Vec::new(),
        pixels: Vec::new(),
    };
    match v2ce::frame::aps::ApsSource::open(&path) {
        Ok(mut src) => {
            while let Ok(Some(f)) = src.next_frame() {
                w.times.push(f.t);
                w.pixels
                    .push(f.luma.iter().map(|v| (v / 257) as u8).collect());
            }
        }
        Err(e) => {
            eprintln!("stage1 bench: {e}; using a synthetic moving edge");
            w.name = "synthetic edge (moving)".into();
            let mut src = v2ce::frame::scene_fn::SceneSource::moving_edge(
                346,
                260,
                25.0,
                59,
                10.0,
                2000.0,
                (0.05, 0.8),
            );
            while let Ok(Some(f)) = src.next_frame() {
                w.times.push(f.t);
                w.pixels
                    .push(f.luma.iter().map(|v| (v / 257) as u8).collect());
            }
        }
    }
    w
}

fn upscale(src: &Workload, width: u16, height: u16) -> Workload {
    let (sw, sh) = (src.width as usize, src.height as usize);
    let pixels = src
        .pixels
        .iter()
        .map(|p| {
            let mut out = Vec::with_capacity(width as usize * height as usize);
            for y in 0..height as usize {
                let sy = y * sh / height as usize;
                for x in 0..width as usize {
                    out.push(p[sy * sw + x * sw / width as usize]);
                }
            }
            out
        })
        .collect();
    Workload {
        name: format!("{} at {width} x {height}", src.name),
        width,
        height,
        times: src.times.clone(),
        pixels,
    }
}

fn still(src: &Workload) -> Workload {
    Workload {
        name: format!("static ({} x {})", src.width, src.height),
        width: src.width,
        height: src.height,
        times: src.times.clone(),
        pixels: vec![src.pixels[0].clone(); src.pixels.len()],
    }
}

/// Our model's frames per second (median of 7 passes) and events per pass, with `motion`.
fn ours(w: &Workload, motion: Motion) -> (f64, usize) {
    let frames: Vec<Frame> = w
        .times
        .iter()
        .zip(&w.pixels)
        .map(|(&t, p)| Frame {
            t,
            width: w.width,
            height: w.height,
            luma: p.iter().map(|&v| v as u16 * 257).collect(),
            exposure_us: None,
        })
        .collect();
    let mut rates = Vec::new();
    let mut count = 0;
    let mut out = Vec::new();
    for _ in 0..7 {
        let cfg = PhysicsConfig {
            motion,
            ..Preset::Davis346.config()
        };
        let mut sim = PhysicsSim::new(cfg, w.width, w.height, 0).expect("sim");
        count = 0;
        let start = Instant::now();
        for f in &frames {
            out.clear();
            sim.step(f, &mut out).expect("step");
            count += out.len();
        }
        rates.push(frames.len() as f64 / start.elapsed().as_secs_f64());
    }
    rates.sort_by(f64::total_cmp);
    (rates[rates.len() / 2], count)
}

/// Writes an `.npy` of uint8 frames `[N, H, W]`.
fn write_npy(path: &Path, w: &Workload) -> std::io::Result<()> {
    let shape = format!("({}, {}, {})", w.pixels.len(), w.height, w.width);
    let mut bytes = v2ce::format::npz::npy_header("'|u1'", &shape, 0);
    for p in &w.pixels {
        bytes.extend_from_slice(p);
    }
    std::fs::write(path, bytes)
}

fn eventcv(w: &Workload, noise: bool) -> Option<f64> {
    if std::env::var_os("V2CE_BENCH_NO_PEER").is_some() {
        return None;
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let py = root.join(".venv/bin/python");
    if !py.exists() {
        return None;
    }
    let npy = std::env::temp_dir().join(format!("v2ce-bench-{}.npy", std::process::id()));
    write_npy(&npy, w).ok()?;
    let span = (w.times[w.times.len() - 1] - w.times[0]) as f64;
    let fps = 1e6 * (w.times.len() - 1) as f64 / span;
    let mut cmd = Command::new(py);
    cmd.arg(root.join("tools/eventcv_peer.py"))
        .arg("--npy")
        .arg(&npy)
        .arg(fps.to_string())
        .args(["--repeat", "3"])
        .env("RAYON_NUM_THREADS", "1");
    if noise {
        cmd.arg("--noise");
    }
    let out = cmd.output().ok()?;
    let _ = std::fs::remove_file(&npy);
    let text = String::from_utf8_lossy(&out.stdout);
    text.split_whitespace()
        .skip_while(|s| *s != "FPS")
        .nth(1)
        .and_then(|v| v.parse().ok())
}

fn main() {
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    // One thread for OpenCV's flow too (read when OpenCV starts its pool).
    if std::env::var_os("OPENCV_FOR_THREADS_NUM").is_none() {
        std::env::set_var("OPENCV_FOR_THREADS_NUM", "1");
    }
    let base = load();
    let big = upscale(&base, 640, 480);
    let loads = [still(&base), still(&big), base, big];
    println!("| workload | v2ce linear frames/s | v2ce flow frames/s | flow / linear | v2ce flow events | eventcv frames/s (noise off) | eventcv (noise on) | flow / eventcv (noise off) |");
    println!("|---|---:|---:|---:|---:|---:|---:|---:|");
    for w in &loads {
        let (linear, _) = ours(w, Motion::Linear);
        let (fps, events) = ours(w, Motion::Flow);
        let off = eventcv(w, false);
        let on = eventcv(w, true);
        let show = |v: Option<f64>| v.map_or("n/a".to_string(), |v| format!("{v:.1}"));
        println!(
            "| {} | {:.0} | {:.0} | {:.2} | {} | {} | {} | {} |",
            w.name,
            linear,
            fps,
            fps / linear,
            events,
            show(off),
            show(on),
            off.map_or("n/a".to_string(), |o| format!("{:.0}x", fps / o))
        );
    }
}
