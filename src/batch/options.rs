//! How a shard is converted ([`Options`]), from the command line's choices ([`Flags`]) and,
//! where it gives none, the environment: the shard from a Slurm job array or a Kubernetes
//! Indexed Job, the threads from `SLURM_CPUS_PER_TASK`.

use std::ffi::OsString;
use std::path::{Path, PathBuf};

use super::manifest::Manifest;
use super::shard::Shard;
use crate::config::Config;
use crate::error::Result;
use crate::format::Format;

/// The largest config file read, bytes (16 MiB; the shipped one is a few kilobytes); a larger
/// one (or `/dev/zero`) is an error naming it.
pub(crate) const MAX_CONFIG_BYTES: u64 = 16 << 20;

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
    /// The options `flags` give, completed from the environment (`var`: `std::env::var_os`,
    /// so that a shard variable that is not UTF-8 is refused rather than taken as unset; a
    /// closure giving `String`s also does, for tests): the shard (a Slurm job array's task,
    /// or a Kubernetes Indexed Job's index), the threads, and the config file (read once, at
    /// most `MAX_CONFIG_BYTES`, 16 MiB; its text is what is hashed and what is parsed).
    pub fn from_flags<V: Into<OsString>>(
        flags: &Flags,
        var: impl Fn(&str) -> Option<V>,
    ) -> Result<Options> {
        let var = |k: &str| var(k).map(Into::into);
        let shard = match flags.shard {
            Some(s) => Shard::parse(s)?,
            None => Shard::from_env(var, flags.shards)?.unwrap_or(Shard::ALL),
        };
        let threads = flags
            .threads
            .filter(|&t| t > 0)
            .unwrap_or_else(|| task_threads(var));
        let (config, config_text) = match flags.config {
            Some(path) => {
                let text = super::lines::read_text(path, MAX_CONFIG_BYTES)?;
                (Config::parse(&text, path)?, text)
            }
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
fn task_threads(var: impl Fn(&str) -> Option<OsString>) -> usize {
    var("SLURM_CPUS_PER_TASK")
        .and_then(|v| v.to_str()?.trim().parse::<usize>().ok())
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
        let var = env(&[("SLURM_CPUS_PER_TASK", "3")]);
        assert_eq!(task_threads(|k| var(k).map(OsString::from)), 3);
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

    #[test]
    fn a_shard_from_the_os_environment_that_is_not_utf8_is_refused() {
        use std::os::unix::ffi::OsStringExt;
        let flags = Flags {
            out: Path::new("out"),
            format: Format::Csv,
            shard: None,
            shards: None,
            threads: Some(1),
            jobs: None,
            config: None,
        };
        let var = |k: &str| match k {
            "SLURM_ARRAY_TASK_ID" => Some(OsString::from_vec(vec![0xff])),
            "SLURM_ARRAY_TASK_COUNT" => Some(OsString::from("4")),
            _ => None,
        };
        let err = Options::from_flags(&flags, var).unwrap_err().to_string();
        assert!(
            err.contains("SLURM_ARRAY_TASK_ID") && err.contains("not UTF-8"),
            "{err}"
        );
    }

    #[test]
    fn the_config_is_read_once_and_bounded() {
        let dir = std::env::temp_dir().join(format!("v2ce-batch-options-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("c.toml");
        std::fs::write(&file, "[stage1]\nseed = 5\n").unwrap();
        let flags = Flags {
            out: Path::new("out"),
            format: Format::Csv,
            shard: None,
            shards: None,
            threads: Some(1),
            jobs: None,
            config: Some(&file),
        };
        let o = Options::from_flags(&flags, env(&[])).unwrap();
        assert_eq!(o.config_text, "[stage1]\nseed = 5\n");
        assert_eq!(o.config.stage1.seed, 5);
        let zero = Flags {
            config: Some(Path::new("/dev/zero")),
            ..flags
        };
        let err = Options::from_flags(&zero, env(&[]))
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("/dev/zero: larger than"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
