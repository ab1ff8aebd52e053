//! The illumination ladder: the same moving scene at 1/64 to 16 times its mid-light level,
//! through each physics preset; prints the event count at each level relative to mid-light.
//! A log sensor above its photoreceptor's bandwidth limit gives about the same count at every
//! level. `cargo run --release --example illumination_ladder`

use v2ce::frame::synthetic::SceneSource;
use v2ce::frame::FrameSource;
use v2ce::stage1::{PhysicsConfig, PhysicsSim, Preset};

const LIGHTS: [f64; 7] = [1.0 / 64.0, 1.0 / 16.0, 0.25, 1.0, 4.0, 8.0, 16.0];

fn count(cfg: &PhysicsConfig, light: f64) -> usize {
    let (w, h) = (96, 64);
    let mut src = SceneSource::ladder(w, h, 60, light);
    let mut sim = match PhysicsSim::new(cfg.clone(), w, h, 1) {
        Ok(s) => s,
        Err(e) => panic!("{e}"),
    };
    let mut events = Vec::new();
    while let Ok(Some(f)) = src.next_frame() {
        if let Err(e) = sim.step(&f, &mut events) {
            panic!("{e}");
        }
    }
    events.len()
}

fn main() {
    print!("| preset | mid-light events |");
    for l in LIGHTS {
        print!(" x{l} |");
    }
    println!();
    println!("|---|---:|{}", "---:|".repeat(LIGHTS.len()));
    let mut rows: Vec<(String, PhysicsConfig)> =
        [Preset::Davis346, Preset::Dvxplorer, Preset::Ideal]
            .into_iter()
            .map(|p| (p.name().to_string(), p.config()))
            .collect();
    // The same presets with scene-relative light, at the level given as the first argument
    // (the calibration clip's mean, as a fraction of full scale).
    if let Some(level) = std::env::args().nth(1).and_then(|a| a.parse::<f64>().ok()) {
        for p in [Preset::Davis346, Preset::Dvxplorer] {
            let mut c = p.config();
            c.scene_level = level;
            rows.push((format!("{}, scene_level {level}", p.name()), c));
        }
    }
    for (name, cfg) in rows {
        let mid = count(&cfg, 1.0).max(1);
        print!("| {name} | {mid} |");
        for l in LIGHTS {
            print!(" {:.2} |", count(&cfg, l) as f64 / mid as f64);
        }
        println!();
    }
}
