//! `v2ce bench tradeoff`: the speed/accuracy trade measured over Stage 1 settings.

use std::path::PathBuf;

use clap::Args;

use crate::error::{Error, Result};
use crate::limits::parse_size;

/// The flags of `v2ce bench tradeoff`.
#[derive(Args)]
pub struct TradeoffArgs {
    /// A recording with frames and events (.aedat4 with APS frames, or events with --frames).
    #[arg(long)]
    pub(crate) real: Option<PathBuf>,
    /// The recording's frames, when it has none in it.
    #[arg(long)]
    pub(crate) frames: Option<PathBuf>,
    /// Which of the recording's frame intervals are scored (models trained by `v2ce dataset
    /// recording --split first` are scored on the second).
    #[arg(long, value_enum, default_value_t = crate::dataset::Split::Second)]
    pub(crate) split: crate::dataset::Split,
    /// Synthetic sequences to score on (made again from --synthetic-seed, as `v2ce dataset
    /// synthetic` makes them; 0: none).
    #[arg(long, default_value_t = 8)]
    pub(crate) synthetic: usize,
    /// Their seed (2: the validation set of the shipped models' cards).
    #[arg(long, default_value_t = 2)]
    pub(crate) synthetic_seed: u64,
    /// Natural-image textures for them (as given to `v2ce dataset synthetic`).
    #[arg(long)]
    pub(crate) images: Option<PathBuf>,
    /// Their frame size.
    #[arg(long, value_name = "WxH", default_value = "160x120")]
    pub(crate) size: String,
    /// More learned models to measure (ONNX), beside the built-in one.
    #[arg(long)]
    pub(crate) model: Vec<PathBuf>,
    /// Print the rows as JSON lines instead of tables.
    #[arg(long)]
    pub(crate) json: bool,
    /// Also score on this many still-camera synthetic sequences (steady light, clean frames,
    /// only objects move; seed --synthetic-seed), where the learned tier's crops save compute.
    #[arg(long, default_value_t = 0)]
    pub(crate) still: usize,
    /// Their frame size.
    #[arg(long, value_name = "WxH", default_value = "320x240")]
    pub(crate) still_size: String,
    /// Also draw TF1 against speed with the Pareto front, as a PNG here.
    #[arg(long, value_name = "OUT.png")]
    pub(crate) plot: Option<PathBuf>,
    /// Overwrite an existing --plot file.
    #[arg(long)]
    pub(crate) force: bool,
    /// Make the synthetic sequences at these frame rates, one group each (e.g. 15,30,60; the
    /// ground truth stays at 1 kHz or more) instead of the dataset's own rates.
    #[arg(long, value_delimiter = ',')]
    pub(crate) fps: Vec<f64>,
    /// Measure only the settings whose label contains this (e.g. "physics").
    #[arg(long)]
    pub(crate) only: Option<String>,
}

/// Runs `v2ce bench tradeoff`.
pub fn tradeoff(args: TradeoffArgs) -> Result<()> {
    use crate::tradeoff::{self, Scene};
    if let Some(path) = &args.plot {
        let inputs: Vec<&std::path::Path> = [&args.real, &args.frames]
            .into_iter()
            .flatten()
            .chain(&args.model)
            .map(|p| p.as_path())
            .collect();
        crate::output::check(path, &inputs, args.force)?;
    }
    let mut groups: Vec<Vec<Scene>> = Vec::new();
    if let Some(real) = &args.real {
        groups.push(vec![Scene::recording(
            real,
            args.frames.as_deref(),
            args.split,
        )?]);
    }
    let images = match &args.images {
        Some(dir) if args.synthetic > 0 || args.still > 0 => crate::dataset::load_images(dir)?,
        _ => Vec::new(),
    };
    let seed = args.synthetic_seed;
    if args.synthetic > 0 {
        let size = parse_size(&args.size)?;
        let rates: Vec<Option<f64>> = if args.fps.is_empty() {
            vec![None]
        } else {
            args.fps.iter().map(|&f| Some(f)).collect()
        };
        for fps in rates {
            groups.push(tradeoff::synthetic_scenes(
                args.synthetic,
                size,
                seed,
                &images,
                fps,
            )?);
        }
    }
    if args.still > 0 {
        let size = parse_size(&args.still_size)?;
        groups.push(tradeoff::still_scenes(args.still, size, seed, &images)?);
    }
    if groups.is_empty() {
        return Err(Error::invalid(
            "bench tradeoff",
            "nothing to score on: give --real, --synthetic N and/or --still N",
        ));
    }
    let mut settings = tradeoff::settings(&args.model);
    if let Some(only) = &args.only {
        settings.retain(|s| s.label.contains(only.as_str()));
        if settings.is_empty() {
            return Err(Error::invalid(
                "--only",
                format!("'{only}' is in no setting's label"),
            ));
        }
    }
    let rows = tradeoff::run(&groups, &settings, |row| {
        if args.json {
            let text =
                serde_json::to_string(row).map_err(|e| Error::invalid("report", e.to_string()))?;
            println!("{text}");
        } else {
            eprintln!(
                "v2ce: {} on {}: {:.1} pairs/s, TF1 {:.3}, ratio {:.2}",
                row.setting, row.scene, row.pairs_per_s, row.tf1, row.count_ratio
            );
        }
        Ok(())
    })?;
    if let Some(path) = &args.plot {
        crate::output::write_via(path, |partial| tradeoff::plot(&rows, partial))?;
        eprintln!("v2ce: plot written to {}", path.display());
    }
    if !args.json {
        println!("{}", tradeoff::table(&rows));
        for group in &groups {
            let name = tradeoff::group_name(group);
            let front: Vec<&str> = tradeoff::pareto(&rows, &name)
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
