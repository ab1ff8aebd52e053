//! The `v2ce` command-line tool: a thin layer over the library.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};

use v2ce::config::Config;
use v2ce::format::{self, csv, Recording};
use v2ce::interval::{fixed_intervals, intervals_from_frames, Interval};
use v2ce::stage2::SamplerKind;
use v2ce::{Error, Result};

#[derive(Parser)]
#[command(
    name = "v2ce",
    version,
    about = "Video to continuous events: a DVS simulator (V2CE)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Score simulated events against real recordings.
    #[command(subcommand)]
    Eval(Eval),
}

#[derive(Subcommand)]
enum Eval {
    /// Stage 2: voxelize real events per frame interval, re-sample them, and score the
    /// timestamps (METE, NOE, PGER, C-METE, C-NOE). Without --events, runs on a built-in
    /// synthetic recording.
    Stage2(Stage2Args),
}

#[derive(Args)]
struct Stage2Args {
    /// Real events: .aedat4, IJRR events.txt, or .csv (t_us,x,y,on).
    #[arg(long)]
    events: Option<PathBuf>,
    /// Frame times: an .aedat4 with APS frames or an IJRR images.txt.
    #[arg(long, conflicts_with = "fps")]
    frames: Option<PathBuf>,
    /// Fixed frame rate for the intervals, starting at the first event.
    #[arg(long)]
    fps: Option<f64>,
    /// Sampler: moment (default), ldati, ldati-random, even, random.
    #[arg(long)]
    sampler: Option<SamplerKind>,
    /// Seed of the sampler's random draws.
    #[arg(long)]
    seed: Option<u64>,
    /// Temporal nodes per interval (C).
    #[arg(long)]
    bins: Option<usize>,
    /// TOML configuration file (flags override it).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Write the sampled events as CSV (t_us,x,y,on).
    #[arg(long, value_name = "OUT.csv")]
    write_events: Option<PathBuf>,
    /// Print the scores as one JSON object.
    #[arg(long)]
    json: bool,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Eval(Eval::Stage2(args)) => eval_stage2(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("v2ce: error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn is_aedat4(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("aedat4"))
}

fn eval_stage2(args: Stage2Args) -> Result<()> {
    let mut config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    if let Some(s) = args.sampler {
        config.stage2.sampler = s;
    }
    if let Some(s) = args.seed {
        config.stage2.seed = s;
    }
    if let Some(b) = args.bins {
        config.stage2.bins = b;
    }
    let (recording, intervals) = load_stage2_input(&args)?;
    let sampler = config.stage2.sampler.build(config.stage2.seed);
    let mut writer = match &args.write_events {
        Some(path) => {
            let file = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
            let mut w = std::io::BufWriter::new(file);
            writeln!(w, "{}", csv::HEADER).map_err(|e| Error::io(path, e))?;
            Some((path.clone(), w))
        }
        None => None,
    };
    let report = v2ce::eval::stage2(
        &recording,
        &intervals,
        config.stage2.bins,
        sampler.as_ref(),
        |events| {
            if let Some((path, w)) = writer.as_mut() {
                csv::write_rows(w, events).map_err(|err| Error::io(path.clone(), err))?;
            }
            Ok(())
        },
    )?;
    if let Some((path, mut w)) = writer {
        w.flush().map_err(|e| Error::io(path, e))?;
    }
    if report.repaired.any() {
        eprintln!(
            "v2ce: warning: repaired voxel values: {} non-finite, {} negative, {} clamped",
            report.repaired.nonfinite, report.repaired.negative, report.repaired.clamped
        );
    }
    if args.json {
        let text =
            serde_json::to_string(&report).map_err(|e| Error::invalid("report", e.to_string()))?;
        println!("{text}");
    } else {
        let m = &report.metrics;
        println!("sampler            {}", report.sampler);
        println!(
            "intervals          {} ({} with events)",
            m.intervals, m.intervals_scored
        );
        println!("events in / out    {} / {}", m.events_in, m.events_out);
        println!("METE               {:.1} us", m.mete_us);
        println!("NOE                {:.3}", m.noe);
        println!("PGER               {:.6}", m.pger);
        println!("C-METE             {:.1} us", m.c_mete_us);
        println!("C-NOE              {:.3}", m.c_noe);
        println!(
            "time per interval  {:.1} us voxelize, {:.1} us sample (median)",
            report.voxelize_us_median, report.sample_us_median
        );
    }
    Ok(())
}

/// The recording and its intervals, from the arguments or the built-in synthetic scene.
fn load_stage2_input(args: &Stage2Args) -> Result<(Recording, Vec<Interval>)> {
    let Some(events_path) = &args.events else {
        let fps = args.fps.unwrap_or(30.0);
        eprintln!(
            "v2ce: no --events given: using the built-in synthetic recording \
             (a sweeping bar, 128 x 96, 2 s, frames at {fps} fps)"
        );
        let intervals = fixed_intervals(0, 1_999_999, fps)?;
        let recording = v2ce::synthetic::sweeping_bar(128, 96, 2_000_000, 1);
        return Ok((recording, intervals));
    };
    // An AEDAT4 event file that also supplies the frames is decoded once.
    let own_frames = args.fps.is_none()
        && is_aedat4(events_path)
        && args.frames.as_deref().is_none_or(|f| f == events_path);
    let (recording, frames) = if own_frames {
        if args.frames.is_none() {
            eprintln!(
                "v2ce: no --frames or --fps: using the APS frames of {}",
                events_path.display()
            );
        }
        let (recording, frames) = format::aedat4::read(events_path)?;
        (
            recording,
            Some(format::require_frames(events_path, frames)?),
        )
    } else {
        let frames = match &args.frames {
            Some(path) => Some(format::read_frame_times(path)?),
            None => None,
        };
        (format::read_events(events_path)?, frames)
    };
    let intervals = if let Some(frames) = frames {
        intervals_from_frames(&frames)?
    } else if let Some(fps) = args.fps {
        let ev = recording.events.events();
        match (ev.first(), ev.last()) {
            (Some(a), Some(b)) => fixed_intervals(a.t, b.t, fps)?,
            _ => Vec::new(),
        }
    } else {
        return Err(Error::invalid(
            "arguments",
            "give --frames FILE or --fps F to define the frame intervals",
        ));
    };
    Ok((recording, intervals))
}
