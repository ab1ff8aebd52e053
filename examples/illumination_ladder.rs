//! The illumination ladder: the same moving scene at 1/64 to 16 times its mid-light level,
//! through each physics preset; prints the event count at each level relative to mid-light.
//!
//! Two tables: with the scene light model (the presets' default: a video's exposure and lens
//! are unknown, so its mean is taken as the calibration scene's light) and with the exposure
//! light model (APS-like frames at a fixed exposure, mid-light set to the calibration scene's
//! light, so 1/64 is 64 times less photocurrent). The second table also gives the
//! photoreceptor cutoff at the scene's mean at each level, which is where the model predicts
//! the count to fall once it drops to the scene's temporal frequencies (3.5 and 8.6 Hz here),
//! and the count that the filter's gain at those frequencies predicts.
//!
//! `cargo run --release --example illumination_ladder`

use v2ce::frame::scene_fn::SceneSource;
use v2ce::frame::{Frame, FrameSource, FULL_SCALE};
use v2ce::stage1::physics::reference_exposure;
use v2ce::stage1::{LightModel, PhysicsConfig, PhysicsSim, Preset};

const LIGHTS: [f64; 7] = [1.0 / 64.0, 1.0 / 16.0, 0.25, 1.0, 4.0, 8.0, 16.0];
const SIZE: (u16, u16) = (96, 64);
const FRAMES: usize = 60;
/// The exposure the ladder's frames report, us.
const EXPOSURE: u32 = 1000;

fn frames(light: f64) -> Vec<Frame> {
    let mut src = SceneSource::ladder(SIZE.0, SIZE.1, FRAMES, light).with_exposure(EXPOSURE);
    let mut out = Vec::new();
    while let Ok(Some(f)) = src.next_frame() {
        out.push(f);
    }
    out
}

fn count(cfg: &PhysicsConfig, light: f64) -> usize {
    let mut sim = match PhysicsSim::new(cfg.clone(), SIZE.0, SIZE.1, 1) {
        Ok(s) => s,
        Err(e) => panic!("{e}"),
    };
    let mut events = Vec::new();
    for f in frames(light) {
        if let Err(e) = sim.step(&f, &mut events) {
            panic!("{e}");
        }
    }
    events.len()
}

/// The model's photoreceptor cutoff (Hz) at the ladder's mean light at `light`, under the
/// exposure model (see `PhysicsConfig::cutoff_hz`).
fn cutoff_at_mean(cfg: &PhysicsConfig, light: f64) -> f64 {
    let f = &frames(light)[0];
    let mean = f.luma.iter().map(|&v| v as f64).sum::<f64>() / f.luma.len() as f64;
    let calibration_units = (mean / FULL_SCALE as f64 * cfg.exposure_us / EXPOSURE as f64).min(1.0);
    cfg.cutoff_hz * (calibration_units + cfg.dark_current) / (1.0 + cfg.dark_current)
}

/// The scene's texture drifts at 60 px/s past gratings of 17 and 7 px: temporal frequencies
/// of 3.5 and 8.6 Hz.
const SCENE_HZ: [f64; 2] = [60.0 / 17.0, 60.0 / 7.0];

/// The mean gain of a first-order low-pass with cutoff `fc` at the scene's frequencies: the
/// share of the scene's log-contrast the photoreceptor passes, and so roughly of its events.
fn gain(fc: f64) -> f64 {
    SCENE_HZ
        .iter()
        .map(|f| 1.0 / (1.0 + (f / fc).powi(2)).sqrt())
        .sum::<f64>()
        / SCENE_HZ.len() as f64
}

fn header() {
    print!("| preset | mid-light events |");
    for l in LIGHTS {
        print!(" x{l} |");
    }
    println!();
    println!("|---|---:|{}", "---:|".repeat(LIGHTS.len()));
}

fn row(name: &str, cfg: &PhysicsConfig) {
    let mid = count(cfg, 1.0).max(1);
    print!("| {name} | {mid} |");
    for l in LIGHTS {
        print!(" {:.2} |", count(cfg, l) as f64 / mid as f64);
    }
    println!();
}

fn main() {
    let presets = [Preset::Davis346, Preset::Dvxplorer, Preset::Ideal];
    println!("Scene light model (the default):\n");
    header();
    for p in presets {
        row(p.name(), &p.config());
    }
    println!("\nExposure light model (mid-light = the calibration scene's light):\n");
    header();
    let mid = frames(1.0);
    for p in [Preset::Davis346, Preset::Dvxplorer] {
        let mut cfg = p.config();
        cfg.light = LightModel::Exposure;
        cfg.exposure_us = reference_exposure(&cfg, &mid).unwrap_or(cfg.exposure_us);
        row(&format!("{} (exposure)", p.name()), &cfg);
        print!("| cutoff at the mean, Hz | |");
        for l in LIGHTS {
            print!(" {:.1} |", cutoff_at_mean(&cfg, l));
        }
        println!();
        print!("| predicted by the filter's gain | |");
        let mid_gain = gain(cutoff_at_mean(&cfg, 1.0));
        for l in LIGHTS {
            print!(" {:.2} |", gain(cutoff_at_mean(&cfg, l)) / mid_gain);
        }
        println!();
    }
}
