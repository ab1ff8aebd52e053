//! How a shard is converted ([`Options`]), from the command line's choices ([`Flags`]) and,
//! where it gives none, the environment: the shard from a Slurm job array or a Kubernetes
//! Indexed Job, the threads from `SLURM_CPUS_PER_TASK`.

use std::path::{Path, PathBuf};

use super::manifest::Manifest;
use super::shard::Shard;
use crate::config::Config;
use crate::error::{Error, Result};
use crate::format::Format;

/// How [`run`](super::run) converts.
#[derive(Debug, Clone)]
pub struct Options {
    /// The output folder.
    pub(crate) out: PathBuf,
    /// The output format.
    pub(crate) format: Format,
    /// The base config (its file's text is part of what decides an output).
    pub(crate) config: Config,
    /// The config file's text, if one was given.
    pub(crate) config_text: String,
    /// This task's share.
    pub(crate) shard: Shard,
    /// Items converted at once.
    pub(crate) jobs: usize,
    /// Threads of the task (the learned tier's ONNX Runtime gets `threads / jobs`).
    pub(crate) threads: usize,
}

/// What the command line (`v2ce batch`) chose; each `None` is taken from the environment, or
/// is the default.
#[derive(Debug, Clone, Copy)]
pub struct Flags<'a> {
    /// The output folder.
    pub out: &'a Path,
    /// The output format.
    pub format: Format,
    /// This task's share, `I/N` (`--shard`); else from the environment; else everything.
    pub shard: Option<&'a str>,
    /// The shard count of a Kubernetes Indexed Job (`--shards`; else `V2CE_SHARDS`).
    pub shards: Option<u32>,
    /// Threads of this task (`--threads`; else `SLURM_CPUS_PER_TASK`, else the machine's).
    pub threads: Option<usize>,
    /// Inputs converted at once (`--jobs`; else the threads).
    pub jobs: Option<usize>,
    /// A config file for every input (`--config`; else the default config).
    pub config: Option<&'a Path>,
}

impl Options {
    /// The options `flags` give, completed from the environment (`var`, e.g.
    /// `|k| std::env::var(k).ok()`): the shard (a Slurm job array's task, or a Kubernetes
    /// Indexed Job's index), the threads, and the config file's text.
    pub fn from_flags(flags: &Flags, var: impl Fn(&str) -> Option<String>) -> Result<Options> {
        let shard = match flags.shard {
            Some(s) => Shard::parse(s)?,
            None => Shard::from_env(&var, flags.shards)?.unwrap_or(Shard::ALL),
        };
        let threads = flags
            .threads
            .filter(|&t| t > 0)
            .unwrap_or_else(|| task_threads(&var));
        let (config, config_text) = match flags.config {
            Some(path) => (
                Config::load(path)?,
                std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?,
            ),
            None => (Config::default(), String::new()),
        };
        Ok(Options {
            out: flags.out.to_path_buf(),
            format: flags.format,
            config,
            config_text,
            shard,
            jobs: flags.jobs.filter(|&j| j > 0).unwrap_or(threads),
            threads,
        })
    }

    /// What the task is about to do, as one line: its shard of `manifest`, where, with how
    /// many threads and how many inputs at once.
    pub fn describe(&self, manifest: &Manifest) -> String {
        format!(
            "shard {} of {} inputs into {} ({} threads, {} at once)",
            self.shard,
            manifest.items.len(),
            self.out.display(),
            self.threads,
            self.jobs.min(manifest.items.len())
        )
    }
}

/// The number of threads the task was given: `SLURM_CPUS_PER_TASK`, else the machine's.
fn task_threads(var: impl Fn(&str) -> Option<String>) -> usize {
    var("SLURM_CPUS_PER_TASK")
        .and_then(|v| v.trim().parse::<usize>().ok())
        .filter(|&n| n > 0)
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env(pairs: &'static [(&'static str, &'static str)]) -> impl Fn(&str) -> Option<String> {
        move |k: &str| {
            pairs
                .iter()
                .find(|(n, _)| *n == k)
                .map(|(_, v)| v.to_string())
        }
    }

    #[test]
    fn threads_come_from_slurm() {
        assert_eq!(task_threads(env(&[("SLURM_CPUS_PER_TASK", "3")])), 3);
    }

    #[test]
    fn flags_come_before_the_environment() {
        let slurm = env(&[
            ("SLURM_ARRAY_TASK_ID", "1"),
            ("SLURM_ARRAY_TASK_COUNT", "2"),
            ("SLURM_CPUS_PER_TASK", "3"),
        ]);
        let flags = Flags {
            out: Path::new("out"),
            format: Format::Csv,
            shard: None,
            shards: None,
            threads: None,
            jobs: None,
            config: None,
        };
        let o = Options::from_flags(&flags, &slurm).unwrap();
        assert_eq!(
            (o.shard, o.threads, o.jobs),
            (Shard::new(1, 2).unwrap(), 3, 3)
        );
        assert_eq!(o.config_text, "");
        let given = Flags {
            shard: Some("0/4"),
            threads: Some(8),
            jobs: Some(2),
            ..flags
        };
        let o = Options::from_flags(&given, &slurm).unwrap();
        assert_eq!(
            (o.shard, o.threads, o.jobs),
            (Shard::new(0, 4).unwrap(), 8, 2)
        );
        let manifest = Manifest { items: Vec::new() };
        assert_eq!(
            o.describe(&manifest),
            "shard 0/4 of 0 inputs into out (8 threads, 0 at once)"
        );
        // No flags and no cluster: everything, as one shard.
        assert_eq!(
            Options::from_flags(&flags, env(&[])).unwrap().shard,
            Shard::ALL
        );
        assert!(Options::from_flags(
            &Flags {
                shard: Some("4/4"),
                ..flags
            },
            env(&[])
        )
        .is_err());
    }
}
