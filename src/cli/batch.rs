//! `v2ce batch`: one task's share of a dataset conversion, or the merged report.

use std::io::Write;
use std::path::{Path, PathBuf};

use clap::Args;

use super::*;
use crate::config::Config;
use crate::error::{Error, Result};

/// The flags of `v2ce batch`.
#[derive(Args)]
pub struct BatchArgs {
    /// The inputs: a list (`PATH [key=value ...]` per line, keys fps, size, preset, tier, seed,
    /// output; relative paths from the list's folder), JSON lines (`{"input": PATH, ...}`), or
    /// a glob in quotes ('clips/*.mp4')
    pub manifest: Option<String>,
    /// The output folder (outputs keep the inputs' relative paths; ledgers go in .v2ce-batch/)
    #[arg(long, short)]
    pub out: Option<PathBuf>,
    /// This task's share, I/N from 0 (default: SLURM_ARRAY_TASK_ID and SLURM_ARRAY_TASK_COUNT,
    /// or JOB_COMPLETION_INDEX with --shards; else the whole manifest)
    #[arg(long)]
    pub shard: Option<String>,
    /// The shard count of a Kubernetes Indexed Job (its completions; or V2CE_SHARDS)
    #[arg(long)]
    pub shards: Option<u32>,
    /// Threads of this task (default: SLURM_CPUS_PER_TASK, else the machine's)
    #[arg(long)]
    pub threads: Option<usize>,
    /// Inputs converted at once (default: the threads; each physics conversion uses about one)
    #[arg(long)]
    pub jobs: Option<usize>,
    /// The output format, by extension: aedat4, raw, csv, npz or h5
    #[arg(long, default_value = "aedat4")]
    pub format: String,
    /// How the output is encoded (`--evt`, `--compression`).
    #[command(flatten)]
    pub encoding: EncodingArgs,
    /// A config file for every input (per-item settings override it)
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Merge the ledgers of every shard in DIR into one summary instead of converting (with a
    /// manifest, inputs not yet converted are listed as pending); exit status 1 if any failed
    #[arg(long, value_name = "DIR")]
    pub report: Option<PathBuf>,
    /// Print the summary as one JSON object on stdout
    #[arg(long)]
    pub json: bool,
}

/// Runs `v2ce batch`: converts this task's shard, or merges the ledgers (`--report`).
pub fn batch(args: BatchArgs) -> Result<()> {
    use crate::batch::{self, Manifest, Shard};
    let format = args
        .encoding
        .format_for(Path::new(&format!("out.{}", args.format)))?;
    let extension = args.format.to_ascii_lowercase();
    let print = |text: String| -> Result<()> {
        let mut out = std::io::stdout().lock();
        writeln!(out, "{text}").map_err(|e| Error::io("stdout", e))
    };
    if let Some(dir) = &args.report {
        let manifest = match &args.manifest {
            Some(m) => Some(Manifest::load(m, &extension)?),
            None => None,
        };
        let report = batch::report(dir, manifest.as_ref())?;
        if args.json {
            let mut v = serde_json::to_value(&report)
                .map_err(|e| Error::invalid("report", e.to_string()))?;
            v["frames_per_busy_s"] = report.frames_per_busy_s().into();
            v["frames_per_s"] = report.frames_per_s().into();
            print(v.to_string())?;
        } else {
            print(report.to_string().trim_end().to_string())?;
        }
        if !report.failed.is_empty() {
            return Err(Error::Run(format!(
                "{} of {} inputs failed",
                report.failed.len(),
                report.failed.len() + report.done
            )));
        }
        return Ok(());
    }
    let (Some(spec), Some(out)) = (&args.manifest, &args.out) else {
        return Err(Error::invalid(
            "arguments",
            "give a MANIFEST and --out DIR (or --report DIR)",
        ));
    };
    let manifest = Manifest::load(spec, &extension)?;
    let env = |k: &str| std::env::var(k).ok();
    let shard = match &args.shard {
        Some(s) => Shard::parse(s)?,
        None => Shard::from_env(env, args.shards)?.unwrap_or(Shard::ALL),
    };
    let threads = args
        .threads
        .filter(|&t| t > 0)
        .unwrap_or_else(|| batch::task_threads(env));
    let (config, config_text) = match &args.config {
        Some(path) => (
            Config::load(path)?,
            std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?,
        ),
        None => (Config::default(), String::new()),
    };
    let options = batch::Options {
        out: out.clone(),
        format,
        config,
        config_text,
        shard,
        jobs: args.jobs.filter(|&j| j > 0).unwrap_or(threads),
        threads,
    };
    let stop = crate::daemon::stop_on_signals()?;
    eprintln!(
        "v2ce batch: shard {shard} of {} inputs into {} ({threads} threads, {} at once)",
        manifest.items.len(),
        out.display(),
        options.jobs.min(manifest.items.len())
    );
    let log = |line: &str| eprintln!("v2ce batch: {line}");
    let summary = batch::run(&manifest, &options, &stop, &log)?;
    let line = format!(
        "shard {shard}: {} items, {} converted, {} skipped (done before), {} failed; {} frames, \
         {} events in {:.1} s ({:.1} frames/s)",
        summary.items,
        summary.converted,
        summary.skipped,
        summary.failed.len(),
        summary.frames,
        summary.events,
        summary.wall_s,
        summary.frames as f64 / summary.wall_s.max(1e-9)
    );
    if args.json {
        print(
            serde_json::to_string(&summary)
                .map_err(|e| Error::invalid("summary", e.to_string()))?,
        )?;
    }
    eprintln!("v2ce batch: {line}");
    if !summary.failed.is_empty() {
        return Err(Error::Run(format!(
            "{} of {} inputs of shard {shard} failed (first: {}: {})",
            summary.failed.len(),
            summary.items,
            summary.failed[0].0,
            summary.failed[0].1
        )));
    }
    Ok(())
}
