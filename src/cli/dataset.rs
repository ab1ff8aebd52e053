//! `v2ce dataset` and `v2ce calibrate`: training data and fitted presets from recordings.

use std::path::PathBuf;

use clap::{Args, Subcommand};

use crate::error::{Error, Result};
use crate::limits::parse_size;

/// The `v2ce dataset` subcommands.
#[derive(Subcommand)]
pub enum DatasetCommand {
    /// Random scenes rendered at a high rate; ground truth from the physics tier, inputs at
    /// video rate (docs/learned.md: "Training data and training").
    Synthetic(SyntheticArgs),
    /// Windows of a recording's frames with its real events, from one half of it by time.
    Recording(DatasetRecordingArgs),
}

/// The flags of `v2ce dataset synthetic`.
#[derive(Args)]
pub struct SyntheticArgs {
    /// The dataset folder (sequences seq_NNNNN.npz and dataset.json).
    #[arg(short, long)]
    pub(crate) out: PathBuf,
    /// Sequences to write.
    #[arg(long, default_value_t = 100)]
    pub(crate) count: usize,
    /// Seed: the same seed and settings give the same dataset.
    #[arg(long, default_value_t = 0)]
    pub(crate) seed: u64,
    /// Frame size.
    #[arg(long, value_name = "WxH", default_value = "160x120")]
    pub(crate) size: String,
    /// Frame intervals per sequence.
    #[arg(long, default_value_t = 16)]
    pub(crate) pairs: usize,
    /// Frame rate of the inputs: one value or a range LO..HI drawn per sequence.
    #[arg(long, default_value = "25..60")]
    pub(crate) fps: String,
    /// The ground truth is simulated at least this often, Hz.
    #[arg(long, default_value_t = 1000.0)]
    pub(crate) rate: f64,
    /// Sensor noise in the ground truth: on, off, mixed (half of the sequences).
    #[arg(long, value_enum, default_value_t = crate::dataset::NoiseMode::Mixed)]
    pub(crate) noise: crate::dataset::NoiseMode,
    /// The ground-truth sensor preset: davis346, dvxplorer, ideal.
    #[arg(long, default_value = "davis346")]
    pub(crate) preset: String,
    /// A preset file (as `v2ce calibrate` writes) instead of --preset.
    #[arg(long, conflicts_with = "preset")]
    pub(crate) preset_file: Option<PathBuf>,
    /// A folder of natural images (PNG, JPEG) used as textures beside procedural ones.
    #[arg(long)]
    pub(crate) images: Option<PathBuf>,
    /// Largest read noise of the input frames, 8-bit steps.
    #[arg(long, default_value_t = 1.5)]
    pub(crate) input_noise: f64,
    /// Threads (0: one per core).
    #[arg(long, default_value_t = 0)]
    pub(crate) threads: usize,
}

/// The flags of `v2ce dataset recording`.
#[derive(Args)]
pub struct DatasetRecordingArgs {
    /// The recording: an .aedat4 with events and APS frames, or an event file whose frames
    /// come from --frames.
    #[arg(long)]
    pub(crate) real: PathBuf,
    /// The frames, when the recording has none in it (a video, an image folder, an IJRR
    /// images.txt), on the events' time base.
    #[arg(long)]
    pub(crate) frames: Option<PathBuf>,
    /// The dataset folder.
    #[arg(short, long)]
    pub(crate) out: PathBuf,
    /// Which frame intervals: first (half, by time), second, all.
    #[arg(long, value_enum, default_value_t = crate::dataset::Split::All)]
    pub(crate) split: crate::dataset::Split,
    /// Frame intervals per sequence.
    #[arg(long, default_value_t = 16)]
    pub(crate) pairs: usize,
    /// How --frames' image values relate to the light (as convert's --color).
    #[arg(long, value_enum, default_value_t = crate::frame::images::ColorSpace::Auto)]
    pub(crate) color: crate::frame::images::ColorSpace,
    /// Use at most this many frames (they are held in memory).
    #[arg(long, default_value_t = 3000)]
    pub(crate) max_frames: usize,
}

/// The flags of `v2ce calibrate`.
#[derive(Args)]
pub struct CalibrateArgs {
    /// The real recording: an .aedat4 with events and APS frames, or an event file whose frames
    /// come from --frames (.aedat4, .raw, .csv, .h5, .npz, IJRR events.txt).
    #[arg(long)]
    pub(crate) real: PathBuf,
    /// The frames, when the recording has none in it: a video, an image folder or a frame list
    /// (IJRR images.txt), on the events' time base.
    #[arg(long)]
    pub(crate) frames: Option<PathBuf>,
    /// Write the fitted preset file here (TOML: every [stage1.physics] parameter).
    #[arg(short, long)]
    pub(crate) output: PathBuf,
    /// The preset the fit starts from and keeps what it does not fit of: davis346, dvxplorer,
    /// ideal.
    #[arg(long, default_value = "davis346")]
    pub(crate) preset: String,
    /// Seed of mismatch and noise in the fits.
    #[arg(long, default_value_t = 0)]
    pub(crate) seed: u64,
    /// How --frames' image values relate to the light (as convert's --color).
    #[arg(long, value_enum, default_value_t = crate::frame::images::ColorSpace::Auto)]
    pub(crate) color: crate::frame::images::ColorSpace,
    /// Use at most this many frames (they are held in memory; the fit needs at least 5).
    #[arg(long, default_value_t = 3000)]
    pub(crate) max_frames: usize,
    /// Print the report as one JSON object on stdout.
    #[arg(long)]
    pub(crate) json: bool,
    /// Overwrite an existing output file.
    #[arg(long)]
    pub(crate) force: bool,
    /// The motion model the fit simulates with (written into the preset file).
    #[command(flatten)]
    pub(crate) motion: super::MotionArgs,
}

/// Runs `v2ce dataset synthetic`.
pub fn dataset_synthetic(args: SyntheticArgs) -> Result<()> {
    let (w, h) = parse_size(&args.size)?;
    let fps = match args.fps.split_once("..") {
        Some((lo, hi)) => (
            lo.trim()
                .parse::<f64>()
                .map_err(|_| Error::invalid("--fps", args.fps.clone()))?,
            hi.trim()
                .parse::<f64>()
                .map_err(|_| Error::invalid("--fps", args.fps.clone()))?,
        ),
        None => {
            let f = args
                .fps
                .trim()
                .parse::<f64>()
                .map_err(|_| Error::invalid("--fps", args.fps.clone()))?;
            (f, f)
        }
    };
    let sensor = match &args.preset_file {
        Some(f) => {
            let mut s1 = crate::stage1::Stage1Config::default();
            s1.load_preset_file(f)?;
            s1.physics_config()
        }
        None => crate::stage1::Preset::from_name(&args.preset)?.config(),
    };
    let images = match &args.images {
        Some(dir) => crate::dataset::load_images(dir)?,
        None => Vec::new(),
    };
    let cfg = crate::dataset::SyntheticConfig {
        size: (w, h),
        pairs: args.pairs,
        fps,
        rate_hz: args.rate,
        sensor,
        noise: args.noise,
        input_noise: args.input_noise,
        pace: Default::default(),
    };
    let threads = if args.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        args.threads
    };
    let started = std::time::Instant::now();
    let m =
        crate::dataset::write_synthetic(&args.out, &cfg, args.seed, args.count, &images, threads)?;
    let events: u64 = m.sequences.iter().map(|s| s.events).sum();
    eprintln!(
        "v2ce: {} sequences of {} intervals at {} x {} ({} natural images), {} events, in {:.1} s: {}",
        m.sequences.len(),
        m.pairs,
        w,
        h,
        images.len(),
        events,
        started.elapsed().as_secs_f64(),
        args.out.display()
    );
    Ok(())
}

/// Runs `v2ce dataset recording`.
pub fn dataset_recording(args: DatasetRecordingArgs) -> Result<()> {
    let (real, frames) = crate::frame::load_recording(
        &args.real,
        args.frames.as_deref(),
        args.color,
        args.max_frames,
    )?;
    let m = crate::dataset::write_recording(
        &args.out,
        &frames,
        real.events.events(),
        args.pairs,
        args.split,
        &args.real.display().to_string(),
    )?;
    let events: u64 = m.sequences.iter().map(|s| s.events).sum();
    eprintln!(
        "v2ce: {} sequences of {} intervals at {} x {}, {} real events: {}",
        m.sequences.len(),
        m.pairs,
        m.size.0,
        m.size.1,
        events,
        args.out.display()
    );
    Ok(())
}

/// Runs `v2ce calibrate`: fits a preset and writes its file.
pub fn calibrate(args: CalibrateArgs) -> Result<()> {
    let inputs: Vec<&std::path::Path> = [Some(&args.real), args.frames.as_ref()]
        .into_iter()
        .flatten()
        .map(|p| p.as_path())
        .collect();
    crate::output::check(&args.output, &inputs, args.force)?;
    let preset = crate::stage1::Preset::from_name(&args.preset)?;
    let mut overrides = crate::stage1::PhysicsOverrides::default();
    args.motion.apply(&mut overrides);
    let base = overrides.apply(preset.config());
    base.validate()?;
    let least = crate::calibrate::MIN_FRAMES;
    if args.max_frames < least {
        return Err(Error::invalid(
            "--max-frames",
            format!(
                "{}: the fit needs at least {least} frames ({} intervals, two per half)",
                args.max_frames,
                least - 1
            ),
        ));
    }
    let (real, frames) = crate::frame::load_recording(
        &args.real,
        args.frames.as_deref(),
        args.color,
        args.max_frames,
    )?;
    let rec = crate::calibrate::Recording {
        frames: &frames,
        events: real.events.events(),
        size: (real.width, real.height),
    };
    let fit = crate::calibrate::calibrate(&rec, &base, args.seed)?;
    let text =
        crate::calibrate::preset_file(&fit, preset.name(), &args.real.display().to_string())?;
    crate::output::write_whole(&args.output, text.as_bytes())?;
    if args.json {
        let text =
            serde_json::to_string(&fit).map_err(|e| Error::invalid("report", e.to_string()))?;
        println!("{text}");
    } else {
        print!("{}", crate::calibrate::report(&fit, &base, preset.name()));
        eprintln!("v2ce: wrote {}", args.output.display());
    }
    Ok(())
}
