//! `v2ce bench tradeoff`: the speed/accuracy trade measured over Stage 1 settings.

use std::path::{Path, PathBuf};

use clap::Args;

use crate::config::parse_size;
use crate::error::{Error, Result};

/// The flags of `v2ce bench tradeoff`.
#[derive(Args)]
pub struct TradeoffArgs {
    /// A recording with frames and events (.aedat4 with APS frames, or events with --frames).
    #[arg(long)]
    pub real: Option<PathBuf>,
    /// The recording's frames, when it has none in it.
    #[arg(long)]
    pub frames: Option<PathBuf>,
    /// Which of the recording's frame intervals are scored (models trained by `v2ce dataset
    /// recording --split first` are scored on the second).
    #[arg(long, value_enum, default_value_t = crate::dataset::Split::Second)]
    pub split: crate::dataset::Split,
    /// Synthetic sequences to score on (made again from --synthetic-seed, as `v2ce dataset
    /// synthetic` makes them; 0: none).
    #[arg(long, default_value_t = 8)]
    pub synthetic: usize,
    /// Their seed (2: the validation set of the shipped models' cards).
    #[arg(long, default_value_t = 2)]
    pub synthetic_seed: u64,
    /// Natural-image textures for them (as given to `v2ce dataset synthetic`).
    #[arg(long)]
    pub images: Option<PathBuf>,
    /// Their frame size.
    #[arg(long, value_name = "WxH", default_value = "160x120")]
    pub size: String,
    /// More learned models to measure (ONNX), beside the built-in one.
    #[arg(long)]
    pub model: Vec<PathBuf>,
    /// Print the rows as JSON lines instead of tables.
    #[arg(long)]
    pub json: bool,
    /// Also score on this many still-camera synthetic sequences (steady light, clean frames,
    /// only objects move; seed --synthetic-seed), where the learned tier's crops save compute.
    #[arg(long, default_value_t = 0)]
    pub still: usize,
    /// Their frame size.
    #[arg(long, value_name = "WxH", default_value = "320x240")]
    pub still_size: String,
    /// Also draw TF1 against speed with the Pareto front, as a PNG here.
    #[arg(long, value_name = "OUT.png")]
    pub plot: Option<PathBuf>,
}

/// Runs `v2ce bench tradeoff`.
pub fn tradeoff(args: TradeoffArgs) -> Result<()> {
    use crate::stage1::{Preset, Stage1Config, Tier};
    use crate::stage2::SamplerKind;
    use crate::tradeoff::{Scene, Setting};
    let mut scenes: Vec<Vec<Scene>> = Vec::new();
    if let Some(real) = &args.real {
        let (rec, frames) = crate::frame::load_recording(
            real,
            args.frames.as_deref(),
            crate::frame::images::ColorSpace::Auto,
            100_000,
        )?;
        let intervals = crate::interval::intervals_between(&frames)?;
        let scored = intervals[args.split.range(intervals.len())].to_vec();
        let name = format!(
            "{} ({:?} half)",
            real.file_name().unwrap_or_default().to_string_lossy(),
            args.split
        )
        .to_lowercase();
        scenes.push(vec![Scene {
            name,
            frames,
            encoding: crate::frame::SourceEncoding::Linear,
            events: rec.events.events().to_vec(),
            scored,
        }]);
    }
    let images = match &args.images {
        Some(dir) if args.synthetic > 0 || args.still > 0 => crate::dataset::load_images(dir)?,
        _ => Vec::new(),
    };
    let synthetic = |count: usize, cfg: &crate::dataset::SyntheticConfig, name: String| {
        (0..count)
            .map(|k| {
                let s = crate::dataset::render_synthetic(cfg, args.synthetic_seed, k, &images)?;
                let scored = crate::interval::intervals_between(&s.frames)?;
                Ok(Scene {
                    name: name.clone(),
                    frames: s.frames,
                    encoding: crate::frame::SourceEncoding::Linear,
                    events: s.events,
                    scored,
                })
            })
            .collect::<Result<Vec<Scene>>>()
    };
    if args.synthetic > 0 {
        let cfg = crate::dataset::SyntheticConfig {
            size: parse_size(&args.size)?,
            ..Default::default()
        };
        let name = format!("synthetic seed {}", args.synthetic_seed);
        scenes.push(synthetic(args.synthetic, &cfg, name)?);
    }
    if args.still > 0 {
        let cfg = crate::dataset::SyntheticConfig {
            size: parse_size(&args.still_size)?,
            input_noise: 0.0,
            pace: crate::dataset::Pace {
                still: true,
                ..Default::default()
            },
            ..Default::default()
        };
        let name = format!("still camera, seed {}", args.synthetic_seed);
        scenes.push(synthetic(args.still, &cfg, name)?);
    }
    if scenes.is_empty() {
        return Err(Error::invalid(
            "bench tradeoff",
            "nothing to score on: give --real, --synthetic N and/or --still N",
        ));
    }
    let physics = |preset: Preset| Setting {
        label: format!("physics {}", preset.name()),
        stage1: Stage1Config {
            preset,
            ..Default::default()
        },
        sampler: SamplerKind::Moment,
    };
    let learned = |label: &str, model: &Path, window: usize, threads: usize, sampler| {
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
                sampler_name(sampler)
            ),
            stage1,
            sampler,
        }
    };
    let builtin = Path::new("");
    let mut settings = vec![
        physics(Preset::Davis346),
        physics(Preset::Dvxplorer),
        physics(Preset::Ideal),
        learned("v2ce-small", builtin, 16, 2, SamplerKind::Moment),
        learned("v2ce-small", builtin, 8, 2, SamplerKind::Moment),
        learned("v2ce-small", builtin, 4, 2, SamplerKind::Moment),
        learned("v2ce-small", builtin, 16, 1, SamplerKind::Moment),
        learned("v2ce-small", builtin, 16, 2, SamplerKind::Ldati),
    ];
    for floor in [0.0f32, 0.05, 0.2] {
        let mut s = learned("v2ce-small", builtin, 16, 2, SamplerKind::Moment);
        s.stage1.learned.floor = Some(floor);
        s.label = format!("{} floor {floor}", s.label);
        settings.push(s);
    }
    // The network on whole frames, and on crops with margins inside its receptive field.
    let mut whole = learned("v2ce-small", builtin, 16, 2, SamplerKind::Moment);
    whole.stage1.learned.roi = false;
    whole.label = format!("{} whole frames", whole.label);
    settings.push(whole);
    for margin in [64usize, 32] {
        let mut s = learned("v2ce-small", builtin, 16, 2, SamplerKind::Moment);
        s.stage1.learned.roi_margin = Some(margin);
        s.label = format!("{} roi margin {margin}", s.label);
        settings.push(s);
    }
    for m in &args.model {
        let name = m
            .file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .to_string();
        settings.push(learned(&name, m, 16, 2, SamplerKind::Moment));
    }
    let mut rows = Vec::new();
    for group in &scenes {
        let name = group.first().map(|s| s.name.clone()).unwrap_or_default();
        for setting in &settings {
            let each = group
                .iter()
                .map(|scene| crate::tradeoff::measure(setting, scene))
                .collect::<Result<Vec<_>>>()?;
            if let Some(row) = crate::tradeoff::combine(&each, &name) {
                if args.json {
                    let text = serde_json::to_string(&row)
                        .map_err(|e| Error::invalid("report", e.to_string()))?;
                    println!("{text}");
                } else {
                    eprintln!(
                        "v2ce: {} on {}: {:.1} pairs/s, TF1 {:.3}, ratio {:.2}",
                        row.setting, row.scene, row.pairs_per_s, row.tf1, row.count_ratio
                    );
                }
                rows.push(row);
            }
        }
    }
    if let Some(path) = &args.plot {
        crate::tradeoff::plot(&rows, path)?;
        eprintln!("v2ce: plot written to {}", path.display());
    }
    if !args.json {
        println!("{}", crate::tradeoff::table(&rows));
        for group in &scenes {
            let name = group.first().map(|s| s.name.clone()).unwrap_or_default();
            let front: Vec<&str> = crate::tradeoff::pareto(&rows, &name)
                .iter()
                .map(|r| r.setting.as_str())
                .collect();
            println!(
                "Pareto front (pairs/s, TF1) on {name}: {}",
                front.join("; ")
            );
        }
    }
    Ok(())
}

/// The sampler's name as configs and flags spell it.
pub fn sampler_name(s: crate::stage2::SamplerKind) -> String {
    serde_json::to_value(s)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_default()
}
