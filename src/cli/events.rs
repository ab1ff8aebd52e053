//! `v2ce transcode`, `v2ce info`, `v2ce repair` and `v2ce render`: event files in, event files
//! or pictures out.

use std::io::Write;
use std::path::PathBuf;

use clap::Args;

use super::*;
use crate::error::{Error, Result};
use crate::limits::parse_size;

/// The flags of `v2ce transcode`.
#[derive(Args)]
pub struct TranscodeArgs {
    /// Input: .aedat4, .raw (EVT 2.0 or 3.0, from its header), .csv, .npz, .h5/.hdf5 (DSEC
    /// layout), or IJRR events.txt.
    pub(crate) input: PathBuf,
    /// Output; its extension picks the format: .aedat4, .raw, .csv, .npz, .h5/.hdf5.
    pub(crate) output: PathBuf,
    /// How the output is encoded (`--evt`, `--compression`).
    #[command(flatten)]
    pub(crate) encoding: EncodingArgs,
    /// Sensor size WIDTHxHEIGHT to write (default: the input's, or the events' extent).
    #[arg(long, value_name = "WxH")]
    pub(crate) size: Option<String>,
    /// Overwrite an existing output file.
    #[arg(long)]
    pub(crate) force: bool,
}

/// The flags of `v2ce info`.
#[derive(Args)]
pub struct InfoArgs {
    /// An event file: .aedat4, .raw, .csv, .npz, .h5/.hdf5 or IJRR events.txt.
    pub(crate) file: PathBuf,
    /// Print one JSON object.
    #[arg(long)]
    pub(crate) json: bool,
}

/// The flags of `v2ce repair`.
#[derive(Args)]
pub struct RepairArgs {
    /// The file a killed writer left: .aedat4, .raw, .csv (cut after the last whole packet,
    /// word or line), .npz or .h5/.hdf5 (written from the journal beside it).
    pub(crate) file: PathBuf,
    /// Write the repaired file here and leave FILE as it is (default: repair FILE in place).
    #[arg(short, long)]
    pub(crate) out: Option<PathBuf>,
    /// Overwrite an existing --out file.
    #[arg(long)]
    pub(crate) force: bool,
}

/// The flags of `v2ce reconstruct`.
#[derive(Args)]
pub struct ReconstructArgs {
    /// Events: .aedat4, .raw, .csv, .npz, .h5/.hdf5, IJRR .txt.
    pub(crate) input: PathBuf,
    /// The folder to write: images.txt and images/frame_NNNNNNNN.png (a frame list that
    /// convert, eval --frames and calibrate --frames read).
    #[arg(short, long)]
    pub(crate) output: PathBuf,
    /// Frames per second of event time, from the first event.
    #[arg(long, default_value_t = 30.0)]
    pub(crate) fps: f64,
    /// Log contrast of one event (the sensor's threshold).
    #[arg(long, default_value_t = crate::reconstruct::Reconstruction::default().contrast)]
    pub(crate) contrast: f64,
    /// High-pass cutoff, Hz: how fast a pixel returns to the mean level (0: never).
    #[arg(long, default_value_t = crate::reconstruct::Reconstruction::default().cutoff_hz)]
    pub(crate) cutoff_hz: f64,
    /// Sensor size when the file has none (CSV).
    #[arg(long, value_name = "WxH")]
    pub(crate) size: Option<String>,
    /// Write into an existing folder.
    #[arg(long)]
    pub(crate) force: bool,
}

/// Runs `v2ce reconstruct`.
pub fn reconstruct(args: ReconstructArgs) -> Result<()> {
    crate::output::check_folder(
        &args.output,
        &["images.txt", "images"],
        &[&args.input],
        args.force,
    )?;
    let size = args.size.as_deref().map(parse_size).transpose()?;
    let how = crate::reconstruct::Reconstruction {
        contrast: args.contrast,
        cutoff_hz: args.cutoff_hz,
        ..Default::default()
    };
    let mut source = crate::reconstruct::EventFrames::open(&args.input, size, args.fps, how)?;
    let size = crate::frame::FrameSource::size(&source);
    let what = crate::frame::FrameSource::describe(&source);
    let frames = crate::frame::images::write_list(&mut source, &args.output)?;
    eprintln!(
        "v2ce: {frames} frames of {} x {} ({what}) to {}",
        size.0,
        size.1,
        args.output.join("images.txt").display()
    );
    Ok(())
}

/// The flags of `v2ce render`.
#[derive(Args)]
pub struct RenderArgs {
    /// Events: .aedat4, .raw, .csv, .npz, .h5/.hdf5, IJRR .txt.
    pub(crate) input: PathBuf,
    /// The picture: .png (every event in one frame), .gif or .mp4 (frames at --fps).
    #[arg(short, long)]
    pub(crate) output: PathBuf,
    /// Frames per second of event time.
    #[arg(long, default_value_t = 30.0)]
    pub(crate) fps: f64,
    /// Fade events with this time constant (ms) instead of showing each frame's window.
    #[arg(long)]
    pub(crate) decay_ms: Option<f64>,
    /// Play back this many times slower than real time.
    #[arg(long, default_value_t = 1.0)]
    pub(crate) slowdown: f64,
    /// Sensor size when the file has none (CSV).
    #[arg(long, value_name = "WxH")]
    pub(crate) size: Option<String>,
    /// Overwrite an existing output file.
    #[arg(long)]
    pub(crate) force: bool,
}

/// Runs `v2ce repair`.
pub fn repair(args: RepairArgs) -> Result<()> {
    if let Some(out) = &args.out {
        crate::output::check(out, &[&args.file], args.force)?;
    }
    let report = crate::repair::repair(&args.file, args.out.as_deref())?;
    eprintln!("v2ce: {report}");
    Ok(())
}

/// Runs `v2ce transcode`.
pub fn transcode(args: TranscodeArgs) -> Result<()> {
    crate::output::check(&args.output, &[&args.input], args.force)?;
    let fmt = args.encoding.format_for(&args.output)?;
    let size = args.size.as_deref().map(parse_size).transpose()?;
    let started = std::time::Instant::now();
    let report = crate::transcode::transcode(&args.input, &args.output, fmt, size)?;
    let secs = started.elapsed().as_secs_f64();
    eprintln!(
        "v2ce: wrote {} events ({} x {}, {}) to {} in {:.2} s",
        report.events,
        report.size.0,
        report.size.1,
        fmt.name(),
        args.output.display(),
        secs
    );
    Ok(())
}

/// Runs `v2ce info`.
pub fn info(args: InfoArgs) -> Result<()> {
    let s = crate::transcode::summarize(&args.file)?;
    let mut out = std::io::stdout().lock();
    let text = if args.json {
        let mut v = serde_json::to_value(&s).map_err(|e| Error::invalid("json", e.to_string()))?;
        v["span_us"] = s.span_us().into();
        v["rate_hz"] = s.rate_hz().into();
        v["on_ratio"] = s.on_ratio().into();
        v.to_string()
    } else {
        format!("{}\n{s}", args.file.display())
    };
    writeln!(out, "{text}").map_err(|e| Error::io("stdout", e))
}

/// Runs `v2ce render`.
pub fn render(args: RenderArgs) -> Result<()> {
    crate::output::check(&args.output, &[&args.input], args.force)?;
    let options = crate::render::RenderOptions {
        fps: args.fps,
        decay_us: args.decay_ms.map(|ms| ms * 1e3),
        slowdown: args.slowdown,
        size: args.size.as_deref().map(parse_size).transpose()?,
    };
    let r = crate::render::render(&args.input, &args.output, &options)?;
    eprintln!(
        "v2ce: {} events in {} frame{} of {} x {} to {}",
        r.events,
        r.frames,
        if r.frames == 1 { "" } else { "s" },
        r.size.0,
        r.size.1,
        args.output.display()
    );
    Ok(())
}
