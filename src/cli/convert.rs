//! `v2ce convert`: frames to an event file.

use std::path::PathBuf;

use clap::Args;

use super::*;
use crate::config::Config;
use crate::error::Result;
use crate::limits::parse_size;
use crate::stage2::SamplerKind;

/// The flags of `v2ce convert`.
#[derive(Args)]
pub struct ConvertArgs {
    /// Frames: a video file (through ffmpeg), a folder of PNG/JPEG images, a .y4m, or an
    /// .aedat4 with APS frames.
    pub(crate) input: PathBuf,
    /// Output events; the extension picks the format: .aedat4, .raw, .csv, .npz, .h5/.hdf5.
    #[arg(short, long)]
    pub(crate) output: PathBuf,
    /// TOML configuration file (flags override it).
    #[arg(long)]
    pub(crate) config: Option<PathBuf>,
    /// The sensor_msgs/msg/Image topic of a rosbag2 .mcap input (default: its first Image
    /// topic).
    #[arg(long)]
    pub(crate) topic: Option<String>,
    /// The Stage 1 tier and its settings.
    #[command(flatten)]
    pub(crate) tier: TierArgs,
    /// Also write the voxels Stage 1 hands to Stage 2, as float32 (intervals, 2*C, H, W)
    /// (channel = polarity*C + node, ON first); needs a tier that makes voxels.
    #[arg(long, value_name = "V.npy")]
    pub(crate) write_voxels: Option<PathBuf>,
    /// Sensor preset: davis346, dvxplorer, ideal [config default: davis346].
    #[arg(long)]
    pub(crate) preset: Option<String>,
    /// A preset file (as `v2ce calibrate` writes) instead of --preset [config default: "",
    /// none].
    #[arg(long, conflicts_with = "preset")]
    pub(crate) preset_file: Option<PathBuf>,
    /// Stage 1 output: events (direct) or voxels (re-timed by the Stage 2 sampler) [config
    /// default: events].
    #[arg(long, value_parser = ["events", "voxels"])]
    pub(crate) mode: Option<String>,
    /// Stage 2 sampler for --mode voxels: spatial, moment, ldati, ldati-random, even, random
    /// [config default: spatial].
    #[arg(long)]
    pub(crate) sampler: Option<SamplerKind>,
    /// Seed of mismatch, noise and sampling [config default: 0].
    #[arg(long)]
    pub(crate) seed: Option<u64>,
    /// Frame rate of an image folder without images.txt/times.txt (none: the folder must have
    /// one).
    #[arg(long)]
    pub(crate) fps: Option<f64>,
    /// How image values relate to the light: auto (linear for a recognised DAVIS APS export,
    /// else sRGB, warning for gray images), srgb (camera video, photos) or linear (raw sensor
    /// exports).
    #[arg(long, value_enum, default_value_t = crate::frame::images::ColorSpace::Auto)]
    pub(crate) color: crate::frame::images::ColorSpace,
    /// The same as --color linear.
    #[arg(long, conflicts_with = "color")]
    pub(crate) linear: bool,
    /// How the output is encoded (`--evt`, `--compression`).
    #[command(flatten)]
    pub(crate) encoding: EncodingArgs,
    /// Resample frames to WIDTHxHEIGHT (none: the source's size).
    #[arg(long, value_name = "WxH")]
    pub(crate) size: Option<String>,
    /// Stop after this many frames (0 or none: all, as for `run`).
    #[arg(long)]
    pub(crate) max_frames: Option<u64>,
    /// Overwrite an existing output file.
    #[arg(long)]
    pub(crate) force: bool,
}

/// Runs `v2ce convert`: frames in, an event file out, with a start line and progress.
pub fn convert(args: ConvertArgs) -> Result<()> {
    use crate::stage1::{Preset, Stage1Output};
    use std::io::IsTerminal;
    let mut config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    if let Some(p) = &args.preset {
        config.stage1.preset = Preset::from_name(p)?;
        config.stage1.custom = None;
    }
    if let Some(f) = &args.preset_file {
        config.stage1.load_preset_file(f)?;
    }
    match args.mode.as_deref() {
        Some("voxels") => config.stage1.output = Stage1Output::Voxels,
        Some(_) => config.stage1.output = Stage1Output::Events,
        None => {}
    }
    if let Some(s) = args.sampler {
        config.stage2.sampler = s;
    }
    if let Some(s) = args.seed {
        config.stage1.seed = s;
        config.stage2.seed = s;
    }
    args.tier.apply(&mut config)?;
    let inputs: Vec<&std::path::Path> = [Some(&args.input), args.config.as_ref()]
        .into_iter()
        .chain([args.preset_file.as_ref(), args.tier.model.as_ref()])
        .flatten()
        .map(|p| p.as_path())
        .collect();
    crate::output::check(&args.output, &inputs, args.force)?;
    if let Some(v) = &args.write_voxels {
        crate::output::check(v, &inputs, args.force)?;
    }
    let job = crate::convert::FileJob {
        input: args.input.clone(),
        output: args.output.clone(),
        format: args.encoding.format_for(&args.output)?,
        source: crate::frame::SourceOptions {
            fps: args.fps,
            color: if args.linear {
                crate::frame::images::ColorSpace::Linear
            } else {
                args.color
            },
            topic: args.topic.clone(),
        },
        size: args.size.as_deref().map(parse_size).transpose()?,
        // 0 means no limit, as in `run` and `[run] max_frames`.
        max_frames: args.max_frames.filter(|&m| m > 0),
        write_voxels: args.write_voxels.clone(),
    };
    /// Prints the start line, and progress on a terminal.
    struct Terminal {
        tty: bool,
        total: Option<u64>,
    }
    impl crate::convert::FileJobObserver for Terminal {
        fn started(&mut self, line: &str, frames: Option<u64>) {
            eprintln!("v2ce: {line}");
            self.total = frames;
        }
        fn progress(&mut self, r: &crate::convert::ConvertReport) {
            if self.tty {
                eprint!(
                    "\r  {}",
                    progress_line(r.frames, self.total, r.events, r.seconds)
                );
            }
        }
    }
    let tty = std::io::stderr().is_terminal();
    let stop = crate::daemon::stop_on_signals()?;
    let mut terminal = Terminal { tty, total: None };
    let result = crate::convert::convert_file(&job, &config, &stop, &mut terminal);
    if tty {
        eprintln!();
    }
    let report = result?;
    let s1 = &report.stage1;
    eprintln!(
        "v2ce: {} frames, {} events in {:.2} s ({:.1} frames/s); {}",
        report.frames,
        report.events,
        report.seconds,
        report.frames as f64 / report.seconds.max(1e-9),
        s1.summary()
    );
    if s1.nonfinite > 0 || report.repaired.any() {
        eprintln!(
            "v2ce: warning: the model gave {} NaN/infinite values; Stage 2 repaired {} \
             non-finite, {} negative, {} clamped node values",
            s1.nonfinite,
            report.repaired.nonfinite,
            report.repaired.negative,
            report.repaired.clamped
        );
    }
    Ok(())
}
