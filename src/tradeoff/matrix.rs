//! What `v2ce bench tradeoff` measures: the settings (the physics presets, and the learned tier
//! at several windows, thread counts, samplers, output floors and crop margins, on whole frames,
//! and with other models) and the scenes (a recording's half, synthetic sequences made again
//! from their seed, still-camera sequences).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::{Scene, Setting};
use crate::dataset::{Image, Pace, Split, SyntheticConfig};
use crate::error::Result;
use crate::flow::FlowPreset;
use crate::frame::SourceEncoding;
use crate::interval::intervals_between;
use crate::stage1::{Motion, PhysicsOverrides, Preset, Stage1Config, Tier};
use crate::stage2::SamplerKind;

/// Every setting the bench measures, in the order of its table: the `davis346` preset (flow,
/// its default), with linear interpolation, with sub-frame caps 2 and 4, and with the
/// `ultrafast` and `medium` flow presets; the other two physics presets;
/// the built-in model at L = 16, 8 and 4 on 2 threads, on 1 thread, with LDATI, with output
/// floors 0, 0.05 and 0.2, on whole frames, with crop margins 64 and 32; then each of `models`
/// (ONNX) at L = 16 on 2 threads, named by its file stem.
pub fn settings(models: &[PathBuf]) -> Vec<Setting> {
    let builtin = Path::new("");
    let small = |window, threads, sampler| learned("v2ce-small", builtin, window, threads, sampler);
    let mut settings = vec![physics(Preset::Davis346)];
    // The motion model's trade: linear interpolation, lower caps, other flow presets.
    settings.push(motion("linear", |p| p.motion = Some(Motion::Linear)));
    for cap in [2u32, 4] {
        settings.push(motion(&format!("flow cap {cap}"), |p| {
            p.max_subframes = Some(cap)
        }));
    }
    for preset in [FlowPreset::Ultrafast, FlowPreset::Medium] {
        settings.push(motion(&format!("flow {}", preset.name()), |p| {
            p.flow_preset = Some(preset)
        }));
    }
    settings.extend([
        physics(Preset::Dvxplorer),
        physics(Preset::Ideal),
        small(16, 2, SamplerKind::Moment),
        small(8, 2, SamplerKind::Moment),
        small(4, 2, SamplerKind::Moment),
        small(16, 1, SamplerKind::Moment),
        small(16, 2, SamplerKind::Ldati),
    ]);
    let default = || small(16, 2, SamplerKind::Moment);
    for floor in [0.0f32, 0.05, 0.2] {
        let mut s = default();
        s.stage1.learned.floor = Some(floor);
        s.label = format!("{} floor {floor}", s.label);
        settings.push(s);
    }
    // The network on whole frames, and on crops with margins inside its receptive field.
    let mut whole = default();
    whole.stage1.learned.roi = false;
    whole.label = format!("{} whole frames", whole.label);
    settings.push(whole);
    for margin in [64usize, 32] {
        let mut s = default();
        s.stage1.learned.roi_margin = Some(margin);
        s.label = format!("{} roi margin {margin}", s.label);
        settings.push(s);
    }
    for m in models {
        let name = m
            .file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .to_string();
        settings.push(learned(&name, m, 16, 2, SamplerKind::Moment));
    }
    settings
}

/// The physics tier with `preset`.
fn physics(preset: Preset) -> Setting {
    Setting {
        label: format!("physics {}", preset.name()),
        stage1: Stage1Config {
            preset,
            ..Default::default()
        },
        sampler: SamplerKind::Moment,
    }
}

/// The `davis346` preset with its motion settings changed by `set`, labelled `label`.
fn motion(label: &str, set: impl FnOnce(&mut PhysicsOverrides)) -> Setting {
    let mut s = physics(Preset::Davis346);
    set(&mut s.stage1.physics);
    s.label = format!("{} {label}", s.label);
    s
}

/// The learned tier with `model` (empty: the built-in one), labelled `label` and the rest.
fn learned(
    label: &str,
    model: &Path,
    window: usize,
    threads: usize,
    sampler: SamplerKind,
) -> Setting {
    let mut stage1 = Stage1Config {
        tier: Tier::Learned,
        ..Default::default()
    };
    stage1.learned.model = model.to_path_buf();
    stage1.learned.window = window;
    stage1.learned.threads = threads;
    Setting {
        label: format!(
            "{label} L={window} {threads} thread{} {}",
            if threads == 1 { "" } else { "s" },
            sampler.name()
        ),
        stage1,
        sampler,
    }
}

impl Scene {
    /// The recording `real` (its frames from `frames`, or its own APS frames), scored on the
    /// frame intervals of `split`, named by its file name and the split.
    pub fn recording(real: &Path, frames: Option<&Path>, split: Split) -> Result<Scene> {
        let (rec, frames) = crate::frame::load_recording(
            real,
            frames,
            crate::frame::images::ColorSpace::Auto,
            100_000,
        )?;
        let intervals = intervals_between(&frames)?;
        let scored = intervals[split.range(intervals.len())].to_vec();
        let name = format!(
            "{} ({:?} half)",
            real.file_name().unwrap_or_default().to_string_lossy(),
            split
        )
        .to_lowercase();
        Ok(Scene {
            name,
            frames,
            encoding: SourceEncoding::Linear,
            events: rec.events.events().to_vec(),
            scored,
        })
    }
}

/// Sequences `0..count` of the synthetic dataset at `size` from `seed` (as `v2ce dataset
/// synthetic` makes them, with `images` as textures), each scored on all its intervals; at
/// `fps` frames per second if given, else at the dataset's own rates.
pub fn synthetic_scenes(
    count: usize,
    size: (u16, u16),
    seed: u64,
    images: &[Arc<Image>],
    fps: Option<f64>,
) -> Result<Vec<Scene>> {
    let mut cfg = SyntheticConfig {
        size,
        ..Default::default()
    };
    let mut name = format!("synthetic seed {seed}");
    if let Some(fps) = fps {
        cfg.fps = (fps, fps);
        name = format!("{name} at {fps} fps");
    }
    cfg.validate()?;
    scenes(count, &cfg, seed, images, name)
}

/// As [`synthetic_scenes`], from a still camera: steady light, clean frames, only objects
/// move (where the learned tier's crops save compute).
pub fn still_scenes(
    count: usize,
    size: (u16, u16),
    seed: u64,
    images: &[Arc<Image>],
) -> Result<Vec<Scene>> {
    let cfg = SyntheticConfig {
        size,
        input_noise: 0.0,
        pace: Pace {
            still: true,
            ..Default::default()
        },
        ..Default::default()
    };
    scenes(
        count,
        &cfg,
        seed,
        images,
        format!("still camera, seed {seed}"),
    )
}

/// Sequences `0..count` of the synthetic dataset of `cfg` and `seed`, each a scene `name`.
fn scenes(
    count: usize,
    cfg: &SyntheticConfig,
    seed: u64,
    images: &[Arc<Image>],
    name: String,
) -> Result<Vec<Scene>> {
    (0..count)
        .map(|k| {
            let s = crate::dataset::render_synthetic(cfg, seed, k, images)?;
            let scored = intervals_between(&s.frames)?;
            Ok(Scene {
                name: name.clone(),
                frames: s.frames,
                encoding: SourceEncoding::Linear,
                events: s.events,
                scored,
            })
        })
        .collect()
}
