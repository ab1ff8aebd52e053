//! The illumination ladder: the same moving scene at 1/64 to 16 times its mid-light level,
//! through each physics preset; prints the event count at each level relative to mid-light.
//! A log sensor above its photoreceptor's bandwidth limit gives about the same count at every
//! level. `cargo run --release --example illumination_ladder`

use v2ce::frame::synthetic::SceneSource;
use v2ce::frame::FrameSource;
use v2ce::stage1::{PhysicsSim, Preset};

const LIGHTS: [f64; 7] = [1.0 / 64.0, 1.0 / 16.0, 0.25, 1.0, 4.0, 8.0, 16.0];

fn count(preset: Preset, light: f64) -> usize {
    let (w, h) = (96, 64);
    let mut src = SceneSource::ladder(w, h, 60, light);
    let mut sim = match PhysicsSim::new(preset.config(), w, h, 1) {
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
    for preset in [Preset::Davis346, Preset::Dvxplorer, Preset::Ideal] {
        let mid = count(preset, 1.0).max(1);
        print!("| {} | {mid} |", preset.name());
        for l in LIGHTS {
            print!(" {:.2} |", count(preset, l) as f64 / mid as f64);
        }
        println!();
    }
}
