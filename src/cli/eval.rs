//! `v2ce eval stage1` and `v2ce eval stage2`: scores against real recordings.

use std::io::Write;
use std::path::PathBuf;

use clap::{Args, Subcommand};

use crate::config::Config;
use crate::error::{Error, Result};
use crate::format::{self, csv, Recording};
use crate::interval::Interval;
use crate::stage2::SamplerKind;

/// The `v2ce eval` subcommands.
#[derive(Subcommand)]
pub enum Eval {
    /// Stage 2: voxelize real events per frame interval, re-sample them, and score the
    /// timestamps (METE, NOE, PGER, C-METE, C-NOE). Without --events, runs on a built-in
    /// synthetic recording.
    Stage2(Stage2Args),
    /// Stage 1: voxelize a simulated and a real event stream on the real recording's frame
    /// intervals and score them (TPF1, TF1, RF1, accuracies, PMSE-2/4), plus the Stage 2
    /// timestamp metrics between the two.
    Stage1(Stage1Args),
    /// Realism: distribution-level statistics of a simulated and a real event stream over the
    /// same window and pixels (rates, inter-event intervals, refractory floor, timestamp
    /// batching, polarity, the noise floor on static pixels, the event-rate spectrum), each
    /// with a distance: scores that silence does not win.
    Realism(RealismArgs),
}

/// The flags of `v2ce eval realism`.
#[derive(Args)]
pub struct RealismArgs {
    /// The two streams: the real one with its frames (the window, and the noise floor's
    /// static pixels; with --fps the noise floor is undefined) and the simulated one.
    #[command(flatten)]
    pub(crate) streams: CompareArgs,
    /// Print the report as one JSON object.
    #[arg(long)]
    pub(crate) json: bool,
    /// Also draw the distributions (per-pixel rates, inter-event intervals, the rate
    /// spectrum), real and simulated side by side, as a PNG here.
    #[arg(long, value_name = "P.png")]
    pub(crate) plot: Option<PathBuf>,
    /// Overwrite an existing --plot file.
    #[arg(long)]
    pub(crate) force: bool,
}

/// How `v2ce eval` simulates the events it scores when it is given none.
#[derive(Args)]
pub struct SimulateArgs {
    /// Without --sim: the sensor preset to simulate with (davis346, dvxplorer, ideal).
    #[arg(long, default_value = "davis346", conflicts_with = "sim")]
    pub(crate) preset: String,
    /// Without --sim: a preset file (as `v2ce calibrate` writes) instead of --preset.
    #[arg(long, conflicts_with = "sim")]
    pub(crate) preset_file: Option<PathBuf>,
    /// Without --sim: the seed of mismatch and noise.
    #[arg(long, default_value_t = 0, conflicts_with = "sim")]
    pub(crate) seed: u64,
}

impl CompareArgs {
    /// The files these flags read (an output must be none of them).
    fn inputs(&self) -> Vec<&std::path::Path> {
        [Some(&self.real), self.sim.as_ref(), self.frames.as_ref()]
            .into_iter()
            .chain([self.simulate.preset_file.as_ref()])
            .flatten()
            .map(|p| p.as_path())
            .collect()
    }
}

/// The real and the simulated stream `v2ce eval stage1` and `v2ce eval realism` compare.
#[derive(Args)]
pub struct CompareArgs {
    /// The real events (and, for an .aedat4 with APS frames, the frames and their intervals).
    #[arg(long)]
    pub(crate) real: PathBuf,
    /// The simulated events; without it, the physics tier simulates them here from the
    /// recording's APS frames (or the --frames images; with --fps and no frames, frames
    /// reconstructed from its own events) with --preset / --preset-file.
    #[arg(long)]
    pub(crate) sim: Option<PathBuf>,
    /// Frames (an .aedat4 with APS frames, an IJRR images.txt or another frame list) when
    /// --real has none.
    #[arg(long, conflicts_with = "fps")]
    pub(crate) frames: Option<PathBuf>,
    /// No frames: intervals at this fixed rate from the first real event.
    #[arg(long)]
    pub(crate) fps: Option<f64>,
    /// How the events are simulated without --sim.
    #[command(flatten)]
    pub(crate) simulate: SimulateArgs,
}

impl CompareArgs {
    /// The real recording, its frame intervals, and the simulated events of `--sim` or those
    /// the physics tier makes of the recording's frames, checked to lie on its sensor.
    fn load(&self) -> Result<(format::Recording, Vec<Interval>, format::Recording)> {
        let (real, intervals) = crate::eval::load_events_and_intervals(
            &self.real,
            self.frames.as_deref(),
            self.fps,
            note,
        )?;
        let size = (real.width, real.height);
        let sim = match &self.sim {
            Some(path) => format::read_events(path)?,
            None => {
                let s = &self.simulate;
                let mut stage1 = crate::stage1::Stage1Config::default();
                match &s.preset_file {
                    Some(f) => stage1.load_preset_file(f)?,
                    None => stage1.preset = crate::stage1::Preset::from_name(&s.preset)?,
                }
                let frames = self.frames.as_deref();
                let own = (real.events.events(), self.fps);
                crate::eval::simulate_physics(&self.real, frames, own, &stage1, s.seed, size, note)?
            }
        };
        let name = self
            .sim
            .clone()
            .unwrap_or_else(|| PathBuf::from("the simulated events"));
        crate::eval::check_sensor(sim.events.events(), size, &name)?;
        Ok((real, intervals, sim))
    }
}

/// The flags of `v2ce eval stage1`.
#[derive(Args)]
pub struct Stage1Args {
    /// The two streams.
    #[command(flatten)]
    pub(crate) streams: CompareArgs,
    /// Score only these frame intervals: first (half, by time), second, all (as `v2ce dataset
    /// recording --split`, so a model is scored on the half it did not train on).
    #[arg(long, value_enum, default_value_t = crate::dataset::Split::All)]
    pub(crate) split: crate::dataset::Split,
    /// Print the scores as one JSON object.
    #[arg(long)]
    pub(crate) json: bool,
}

/// The flags of `v2ce eval stage2`.
#[derive(Args)]
pub struct Stage2Args {
    /// Real events: .aedat4, IJRR events.txt, or .csv (t_us,x,y,on).
    #[arg(long)]
    pub(crate) events: Option<PathBuf>,
    /// Frame times: an .aedat4 with APS frames or an IJRR images.txt.
    #[arg(long, conflicts_with = "fps")]
    pub(crate) frames: Option<PathBuf>,
    /// Fixed frame rate for the intervals, starting at the first event.
    #[arg(long)]
    pub(crate) fps: Option<f64>,
    /// Sampler: spatial (default), moment, ldati, ldati-random, even, random.
    #[arg(long)]
    pub(crate) sampler: Option<SamplerKind>,
    /// Seed of the sampler's random draws.
    #[arg(long)]
    pub(crate) seed: Option<u64>,
    /// Temporal nodes per interval (C).
    #[arg(long)]
    pub(crate) bins: Option<usize>,
    /// TOML configuration file (flags override it).
    #[arg(long)]
    pub(crate) config: Option<PathBuf>,
    /// Write the sampled events as CSV (t_us,x,y,on).
    #[arg(long, value_name = "OUT.csv")]
    pub(crate) write_events: Option<PathBuf>,
    /// Overwrite an existing --write-events file.
    #[arg(long)]
    pub(crate) force: bool,
    /// Print the scores as one JSON object.
    #[arg(long)]
    pub(crate) json: bool,
}

/// Runs `v2ce eval stage1`.
pub fn eval_stage1(args: Stage1Args) -> Result<()> {
    let (real, intervals, sim) = args.streams.load()?;
    let intervals = intervals[args.split.range(intervals.len())].to_vec();
    if intervals.is_empty() {
        return Err(Error::invalid(
            "--split",
            format!("no frame intervals in the {:?} part", args.split),
        ));
    }
    let size = (real.width, real.height);
    let report = crate::eval::stage1(real.events.events(), sim.events.events(), &intervals, size)?;
    let (m, t) = (report.voxels, report.timing);
    let mut out = std::io::stdout().lock();
    let text = if args.json {
        report.to_json().to_string()
    } else {
        format!(
            "intervals {} ({} chunks); real events {}, simulated {} (ratio {:.3})\n\
             TPF1 {:.4}  TF1 {:.4}  RF1 {:.4}\n\
             TPAcc {:.4}  TAcc {:.4}  RAcc {:.4}\n\
             PMSE-2 {:.5}  PMSE-4 {:.5}\n\
             C-METE {:.1} us  METE {:.1} us  PGER {:.3}",
            m.intervals,
            m.chunks,
            m.real_events,
            m.sim_events,
            m.count_ratio(),
            m.tpf1,
            m.tf1,
            m.rf1,
            m.tpacc,
            m.tacc,
            m.racc,
            m.pmse2,
            m.pmse4,
            t.c_mete_us,
            t.mete_us,
            t.pger
        )
    };
    writeln!(out, "{text}").map_err(|e| Error::io("stdout", e))
}

/// Runs `v2ce eval realism`.
pub fn eval_realism(args: RealismArgs) -> Result<()> {
    let streams = &args.streams;
    if let Some(path) = &args.plot {
        crate::output::check(path, &streams.inputs(), args.force)?;
    }
    let (real, intervals, sim) = streams.load()?;
    let (Some(first), Some(last)) = (intervals.first(), intervals.last()) else {
        return Err(Error::invalid(
            "frames",
            "no frame intervals: nothing to measure",
        ));
    };
    let window = (first.start(), last.end());
    let size = (real.width, real.height);
    let (real, sim) = (real.events.events(), sim.events.events());
    let floors = match streams.fps {
        Some(_) => None,
        None => {
            let frames = streams.frames.as_deref().unwrap_or(&streams.real);
            Some(crate::eval::noise_floors(frames, size, [real, sim])?)
        }
    };
    let report = crate::metrics::realism::compare(real, sim, size, window, floors)?;
    if let Some(path) = &args.plot {
        crate::output::write_via(path, |partial| {
            crate::metrics::realism_plot::plot(&report, partial)
        })?;
    }
    let text = if args.json {
        serde_json::to_string(&report).map_err(|e| Error::invalid("report", e.to_string()))?
    } else {
        report.table()
    };
    writeln!(std::io::stdout().lock(), "{text}").map_err(|e| Error::io("stdout", e))
}

/// Prints a note of the library's on stderr.
fn note(line: &str) {
    eprintln!("v2ce: {line}");
}

/// Runs `v2ce eval stage2`.
pub fn eval_stage2(args: Stage2Args) -> Result<()> {
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
    if let Some(path) = &args.write_events {
        let inputs: Vec<&std::path::Path> = [&args.events, &args.frames, &args.config]
            .into_iter()
            .flatten()
            .map(|p| p.as_path())
            .collect();
        crate::output::check(path, &inputs, args.force)?;
    }
    let (recording, intervals) = load_stage2_input(&args)?;
    let sampler = config.stage2.sampler.build(config.stage2.seed);
    // Written under the partial name, renamed when whole.
    let mut writer = match &args.write_events {
        Some(path) => {
            let out = crate::format::PartialOutput::new(path);
            let partial = out.writing().to_path_buf();
            let file = std::fs::File::create(&partial).map_err(|e| Error::io(&partial, e))?;
            let mut w = std::io::BufWriter::new(file);
            writeln!(w, "{}", csv::HEADER).map_err(|e| Error::io(&partial, e))?;
            Some((partial, w, out))
        }
        None => None,
    };
    let report = crate::eval::stage2(
        &recording,
        &intervals,
        config.stage2.bins,
        sampler.as_ref(),
        |events| {
            if let Some((path, w, _)) = writer.as_mut() {
                csv::write_rows(w, events).map_err(|err| Error::io(path.clone(), err))?;
            }
            Ok(())
        },
    )?;
    if let Some((path, w, out)) = writer {
        let file = w
            .into_inner()
            .map_err(|e| Error::io(&path, e.into_error()))?;
        file.sync_all().map_err(|e| Error::io(&path, e))?;
        out.commit()?;
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
pub fn load_stage2_input(args: &Stage2Args) -> Result<(Recording, Vec<Interval>)> {
    let Some(events_path) = &args.events else {
        let fps = args.fps.unwrap_or(30.0);
        eprintln!(
            "v2ce: no --events given: using the built-in synthetic recording \
             (a sweeping bar, 128 x 96, 2 s, frames at {fps} fps)"
        );
        return crate::eval::sweeping_bar(fps);
    };
    crate::eval::load_events_and_intervals(events_path, args.frames.as_deref(), args.fps, note)
}
