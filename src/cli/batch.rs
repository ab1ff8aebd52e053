//! `v2ce batch`: one task's share of a dataset conversion, or the merged report.

use std::io::Write;
use std::path::{Path, PathBuf};

use clap::Args;

use super::*;
use crate::batch::{self, Manifest};
use crate::error::{Error, Result};

/// The flags of `v2ce batch`.
#[derive(Args)]
pub struct BatchArgs {
    /// The inputs: a list (`PATH [key=value ...]` per line, keys fps, size, preset, tier, seed,
    /// output; relative paths from the list's folder), JSON lines (`{"input": PATH, ...}`), or
    /// a glob in quotes ('clips/*.mp4')
    pub(crate) manifest: Option<String>,
    /// The output folder (outputs keep the inputs' relative paths; ledgers go in .v2ce-batch/)
    #[arg(long, short)]
    pub(crate) out: Option<PathBuf>,
    /// This task's share, I/N from 0 (default: SLURM_ARRAY_TASK_ID and SLURM_ARRAY_TASK_COUNT,
    /// or JOB_COMPLETION_INDEX with --shards; else the whole manifest)
    #[arg(long)]
    pub(crate) shard: Option<String>,
    /// The shard count of a Kubernetes Indexed Job (its completions; or V2CE_SHARDS)
    #[arg(long)]
    pub(crate) shards: Option<u32>,
    /// Threads of this task (default: SLURM_CPUS_PER_TASK, else the machine's)
    #[arg(long)]
    pub(crate) threads: Option<usize>,
    /// Inputs converted at once (default: the threads; each physics conversion uses about one)
    #[arg(long)]
    pub(crate) jobs: Option<usize>,
    /// The output format, by extension: aedat4, raw, csv, npz or h5
    #[arg(long, default_value = "aedat4")]
    pub(crate) format: String,
    /// How the output is encoded (`--evt`, `--compression`).
    #[command(flatten)]
    pub(crate) encoding: EncodingArgs,
    /// A config file for every input (per-item settings override it)
    #[arg(long)]
    pub(crate) config: Option<PathBuf>,
    /// Merge the ledgers of every shard in DIR into one summary instead of converting (with a
    /// manifest, inputs not yet converted are listed as pending); exit status 1 if any failed
    #[arg(long, value_name = "DIR")]
    pub(crate) report: Option<PathBuf>,
    /// Print the summary as one JSON object on stdout
    #[arg(long)]
    pub(crate) json: bool,
}

/// Runs `v2ce batch`: converts this task's shard, or merges the ledgers (`--report`).
pub fn batch(args: BatchArgs) -> Result<()> {
    let format = args
        .encoding
        .format_for(Path::new(&format!("out.{}", args.format)))?;
    let extension = args.format.to_ascii_lowercase();
    if let Some(dir) = &args.report {
        return report(&args, dir, &extension);
    }
    let (Some(spec), Some(out)) = (&args.manifest, &args.out) else {
        return Err(Error::invalid(
            "arguments",
            "give a MANIFEST and --out DIR (or --report DIR)",
        ));
    };
    let manifest = Manifest::load(spec, &extension)?;
    let flags = batch::Flags {
        out,
        format,
        shard: args.shard.as_deref(),
        shards: args.shards,
        threads: args.threads,
        jobs: args.jobs,
        config: args.config.as_deref(),
    };
    let options = batch::Options::from_flags(&flags, |k| std::env::var_os(k))?;
    let stop = crate::daemon::stop_on_signals()?;
    eprintln!("v2ce batch: {}", options.describe(&manifest));
    let log = |line: &str| eprintln!("v2ce batch: {line}");
    let summary = batch::run(&manifest, &options, &stop, &log)?;
    if args.json {
        print(&summary.to_json()?)?;
    }
    eprintln!("v2ce batch: {summary}");
    summary.check()
}

/// `v2ce batch --report DIR`: the ledgers in `dir` merged, with the manifest's inputs not yet
/// converted as pending.
fn report(args: &BatchArgs, dir: &Path, extension: &str) -> Result<()> {
    let manifest = match &args.manifest {
        Some(m) => Some(Manifest::load(m, extension)?),
        None => None,
    };
    let report = batch::report(dir, manifest.as_ref())?;
    if args.json {
        print(&report.to_json()?)?;
    } else {
        print(report.to_string().trim_end())?;
    }
    report.check()
}

/// Writes `text` and a newline to stdout.
fn print(text: &str) -> Result<()> {
    let mut out = std::io::stdout().lock();
    writeln!(out, "{text}").map_err(|e| Error::io("stdout", e))
}
