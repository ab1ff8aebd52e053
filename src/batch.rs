//! Dataset-scale conversion as a well-behaved task of a cluster engine (`v2ce batch`): a manifest
//! of inputs, a deterministic share of it per task (Slurm job arrays, Kubernetes Indexed Jobs),
//! each output written under a temporary name and renamed when complete, and a per-shard JSONL
//! ledger that lets a killed or pre-empted task resume with nothing lost or converted twice.
//!
//! - [`Manifest`]: the inputs, from a list (`path [key=value ...]` per line), JSON lines
//!   (`{"input": ..., "fps": ...}`) or a glob, with per-item [`Settings`].
//! - [`Shard`]: which share this task takes, from `--shard I/N` or the environment; items are
//!   spread by size (largest first, each to the least-loaded shard), not by position.
//! - [`run`]: converts the shard's items ([`crate::convert::convert_file`], as `v2ce convert`
//!   does), skipping what its ledger records as done with the same input and settings.
//! - [`report`]: every shard's ledger merged into one [`Report`].

use std::collections::{BTreeMap, HashMap};
use std::io::{BufRead, Read, Write};
use std::path::{Component, Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::config::Config;
use crate::convert::{convert_file, FileJob};
use crate::error::{Error, Result};
use crate::format::Format;

/// The folder of the ledgers, inside the output folder.
pub const LEDGER_DIR: &str = ".v2ce-batch";

/// Per-item settings; absent ones come from the config.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Settings {
    /// Frame rate of an image folder without times.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
    /// Resample frames to `WIDTHxHEIGHT`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub size: Option<String>,
    /// The physics tier's preset.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub preset: Option<String>,
    /// Stage 1 tier: `physics`, `learned` or `auto`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tier: Option<crate::stage1::Tier>,
    /// Seed of Stage 1 and Stage 2.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
}

/// One input of a manifest.
#[derive(Debug, Clone, PartialEq)]
pub struct Item {
    /// The input as the manifest names it (the key of the ledger).
    pub name: String,
    /// Where it is.
    pub input: PathBuf,
    /// The output, relative to the output folder.
    pub output: PathBuf,
    /// Its settings.
    pub settings: Settings,
    /// Its size in bytes (a folder: its files'), for balancing shards.
    pub bytes: u64,
}

/// A manifest line in JSON.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonItem {
    input: String,
    #[serde(default)]
    output: Option<String>,
    #[serde(flatten)]
    settings: Settings,
}

/// The inputs of a batch.
#[derive(Debug, Clone)]
pub struct Manifest {
    /// In manifest order.
    pub items: Vec<Item>,
}

impl Manifest {
    /// Reads `spec`: a manifest file (`.jsonl`, or lines starting with `{`, are JSON items;
    /// other lines are `PATH [key=value ...]`; `#` starts a comment; relative paths are taken
    /// from the manifest's folder), or, when no such file exists, a glob (`clips/*.mp4`).
    /// Outputs get `extension` (the output format's).
    pub fn load(spec: &str, extension: &str) -> Result<Manifest> {
        let path = Path::new(spec);
        let entries = if path.is_file() {
            read_entries(path)?
        } else if spec.contains(['*', '?', '[']) {
            glob_entries(spec)?
        } else {
            return Err(Error::invalid(
                "manifest",
                format!("{spec}: no such file, and not a glob pattern"),
            ));
        };
        if entries.is_empty() {
            return Err(Error::invalid(
                "manifest",
                format!("{spec}: lists no inputs"),
            ));
        }
        let mut items = Vec::with_capacity(entries.len());
        let mut outputs: HashMap<PathBuf, String> = HashMap::new();
        for (name, input, output, settings) in entries {
            let output = match output {
                Some(o) => relative_output(Path::new(&o)).ok_or_else(|| {
                    Error::invalid(
                        "manifest",
                        format!(
                            "{name}: output '{o}' must be a relative path inside the output folder"
                        ),
                    )
                })?,
                None => default_output(&name, extension),
            };
            if let Some(other) = outputs.insert(output.clone(), name.clone()) {
                return Err(Error::invalid(
                    "manifest",
                    format!(
                        "{other} and {name} would both write {}; give one an \"output\"",
                        output.display()
                    ),
                ));
            }
            let bytes = size_of(&input);
            items.push(Item {
                name,
                input,
                output,
                settings,
                bytes,
            });
        }
        Ok(Manifest { items })
    }
}

type Entry = (String, PathBuf, Option<String>, Settings);

fn read_entries(path: &Path) -> Result<Vec<Entry>> {
    let base = path.parent().unwrap_or(Path::new(""));
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let jsonl = path.extension().is_some_and(|e| e == "jsonl");
    let mut entries = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |m: String| Error::format(path, format!("line {}: {m}", i + 1));
        let (name, output, settings) = if jsonl || line.starts_with('{') {
            let item: JsonItem = serde_json::from_str(line).map_err(|e| bad(e.to_string()))?;
            (item.input, item.output, item.settings)
        } else {
            let mut fields = line.split_whitespace();
            let name = fields.next().unwrap_or_default().to_string();
            let mut map = serde_json::Map::new();
            let mut output = None;
            for f in fields {
                let (k, v) = f
                    .split_once('=')
                    .ok_or_else(|| bad(format!("'{f}' is not key=value")))?;
                if k == "output" {
                    output = Some(v.to_string());
                    continue;
                }
                let value = match v.parse::<u64>() {
                    Ok(n) => serde_json::Value::from(n),
                    Err(_) => match v.parse::<f64>() {
                        Ok(x) if x.is_finite() => serde_json::Value::from(x),
                        _ => serde_json::Value::from(v),
                    },
                };
                map.insert(k.to_string(), value);
            }
            let settings: Settings = serde_json::from_value(serde_json::Value::Object(map))
                .map_err(|e| bad(e.to_string()))?;
            (name, output, settings)
        };
        let input = base.join(&name);
        entries.push((name, input, output, settings));
    }
    Ok(entries)
}

fn glob_entries(pattern: &str) -> Result<Vec<Entry>> {
    let paths = glob::glob(pattern)
        .map_err(|e| Error::invalid("manifest", format!("bad glob '{pattern}': {e}")))?;
    let mut entries = Vec::new();
    for p in paths {
        let p = p.map_err(|e| Error::invalid("manifest", e.to_string()))?;
        let name = p.to_string_lossy().into_owned();
        entries.push((name, p, None, Settings::default()));
    }
    Ok(entries)
}

/// `p` if it stays inside a folder (relative, no `..`).
fn relative_output(p: &Path) -> Option<PathBuf> {
    let inside = !p.as_os_str().is_empty()
        && p.components()
            .all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
    inside.then(|| p.to_path_buf())
}

/// The input's own relative path with the output's extension; an absolute or escaping path
/// keeps its file name only.
fn default_output(name: &str, extension: &str) -> PathBuf {
    let p = Path::new(name.trim_end_matches('/'));
    let base =
        relative_output(p).unwrap_or_else(|| PathBuf::from(p.file_name().unwrap_or_default()));
    base.with_extension(extension)
}

fn size_of(path: &Path) -> u64 {
    match std::fs::metadata(path) {
        Ok(m) if m.is_dir() => std::fs::read_dir(path)
            .map(|d| {
                d.filter_map(|e| e.ok()?.metadata().ok())
                    .filter(|m| m.is_file())
                    .map(|m| m.len())
                    .sum()
            })
            .unwrap_or(0),
        Ok(m) => m.len(),
        Err(_) => 0,
    }
}

/// This task's share: shard `index` of `count` (from 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    /// From 0.
    pub index: u32,
    /// At least 1.
    pub count: u32,
}

impl Shard {
    /// Everything, as one shard.
    pub const ALL: Shard = Shard { index: 0, count: 1 };

    /// Parses `I/N` (I from 0 to N-1).
    pub fn parse(text: &str) -> Result<Shard> {
        let bad = || {
            Error::invalid(
                "--shard",
                format!("'{text}' (expected I/N with 0 <= I < N, e.g. 0/4)"),
            )
        };
        let (i, n) = text.split_once('/').ok_or_else(bad)?;
        let index: u32 = i.trim().parse().map_err(|_| bad())?;
        let count: u32 = n.trim().parse().map_err(|_| bad())?;
        Shard::new(index, count).map_err(|_| bad())
    }

    /// Shard `index` of `count`.
    pub fn new(index: u32, count: u32) -> Result<Shard> {
        if count == 0 || index >= count {
            return Err(Error::invalid(
                "shard",
                format!("{index} of {count}: the index must be below the count"),
            ));
        }
        Ok(Shard { index, count })
    }

    /// The shard the environment gives: a Slurm job array's task (`SLURM_ARRAY_TASK_ID`,
    /// `SLURM_ARRAY_TASK_COUNT`, less `SLURM_ARRAY_TASK_MIN`, over `SLURM_ARRAY_TASK_STEP`), or
    /// a Kubernetes Indexed Job's `JOB_COMPLETION_INDEX` with `count` (`--shards`, or
    /// `V2CE_SHARDS`); `None` when neither is set.
    pub fn from_env(
        var: impl Fn(&str) -> Option<String>,
        count: Option<u32>,
    ) -> Result<Option<Shard>> {
        let num = |name: &str| -> Result<Option<u64>> {
            match var(name) {
                None => Ok(None),
                Some(v) => v.trim().parse::<u64>().map(Some).map_err(|_| {
                    Error::invalid("shard", format!("{name}={v} is not a whole number"))
                }),
            }
        };
        if let Some(id) = num("SLURM_ARRAY_TASK_ID")? {
            let total = num("SLURM_ARRAY_TASK_COUNT")?.ok_or_else(|| {
                Error::invalid(
                    "shard",
                    "SLURM_ARRAY_TASK_ID without SLURM_ARRAY_TASK_COUNT",
                )
            })?;
            let min = num("SLURM_ARRAY_TASK_MIN")?.unwrap_or(0);
            let step = num("SLURM_ARRAY_TASK_STEP")?.unwrap_or(1).max(1);
            let index = id.saturating_sub(min) / step;
            return Shard::new(
                u32::try_from(index).unwrap_or(u32::MAX),
                u32::try_from(total).unwrap_or(u32::MAX),
            )
            .map(Some);
        }
        if let Some(index) = num("JOB_COMPLETION_INDEX")? {
            let count = match count {
                Some(c) => u64::from(c),
                None => num("V2CE_SHARDS")?.ok_or_else(|| {
                    Error::invalid(
                        "shard",
                        "JOB_COMPLETION_INDEX is set: give the Job's completions as --shards N or V2CE_SHARDS",
                    )
                })?,
            };
            return Shard::new(
                u32::try_from(index).unwrap_or(u32::MAX),
                u32::try_from(count).unwrap_or(u32::MAX),
            )
            .map(Some);
        }
        Ok(None)
    }

    /// The items of this shard, in manifest order: items sorted by size (largest first, then
    /// by name) each go to the least-loaded shard (the lowest index on a tie). Every task
    /// computes the same split from the same manifest.
    pub fn select<'a>(&self, items: &'a [Item]) -> Vec<&'a Item> {
        let mut order: Vec<usize> = (0..items.len()).collect();
        order.sort_by(|&a, &b| {
            items[b]
                .bytes
                .cmp(&items[a].bytes)
                .then_with(|| items[a].name.cmp(&items[b].name))
        });
        let mut load = vec![0u64; self.count as usize];
        let mut mine = vec![false; items.len()];
        for i in order {
            let (shard, _) = load
                .iter()
                .enumerate()
                .min_by_key(|&(s, l)| (*l, s))
                .unwrap_or((0, &0));
            // Count an empty file as one byte, so empty inputs spread too.
            load[shard] += items[i].bytes.max(1);
            mine[i] = shard == self.index as usize;
        }
        items
            .iter()
            .zip(mine)
            .filter_map(|(it, m)| m.then_some(it))
            .collect()
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// One line of a ledger: an item converted or failed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Record {
    /// The input as the manifest names it.
    pub input: String,
    /// The output, relative to the output folder.
    pub output: String,
    /// `done` or `failed`.
    pub status: String,
    /// Why it failed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// SHA-256 of the input's bytes (a folder: of its files' names and bytes, in name order).
    pub input_sha256: String,
    /// The input's size and latest modification (ns since the epoch) when it was hashed: a
    /// re-run trusts the hash while both are unchanged instead of reading the input again.
    #[serde(default)]
    pub input_stamp: (u64, i128),
    /// The item's settings.
    pub settings: Settings,
    /// SHA-256 of everything else that decides the output: settings, format, config, version.
    pub settings_sha256: String,
    /// The v2ce version that wrote it.
    pub version: String,
    /// Frames read.
    pub frames: u64,
    /// Events written.
    pub events: u64,
    /// Time from the first frame to the last, us.
    pub span_us: i64,
    /// Bytes of the output file.
    pub bytes: u64,
    /// Seconds the conversion took.
    pub wall_s: f64,
    /// The shard that did it, `I/N`.
    pub shard: String,
    /// When it finished, seconds since the Unix epoch.
    pub finished_unix: f64,
}

/// How [`run`] converts.
#[derive(Debug, Clone)]
pub struct Options {
    /// The output folder.
    pub out: PathBuf,
    /// The output format.
    pub format: Format,
    /// The base config (its file's text is part of what decides an output).
    pub config: Config,
    /// The config file's text, if one was given.
    pub config_text: String,
    /// This task's share.
    pub shard: Shard,
    /// Items converted at once.
    pub jobs: usize,
    /// Threads of the task (the learned tier's ONNX Runtime gets `threads / jobs`).
    pub threads: usize,
}

/// What [`run`] did in this shard.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ShardSummary {
    /// Items of this shard.
    pub items: usize,
    /// Converted now.
    pub converted: usize,
    /// Already done with the same input and settings.
    pub skipped: usize,
    /// Failed (input and error).
    pub failed: Vec<(String, String)>,
    /// Frames converted now.
    pub frames: u64,
    /// Events written now.
    pub events: u64,
    /// Wall time of the shard, seconds.
    pub wall_s: f64,
}

/// The number of threads the task was given: `SLURM_CPUS_PER_TASK`, else the machine's.
pub fn task_threads(var: impl Fn(&str) -> Option<String>) -> usize {
    var("SLURM_CPUS_PER_TASK")
        .and_then(|v| v.trim().parse::<usize>().ok())
        .filter(|&n| n > 0)
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// SHA-256 of a file's bytes, or of a folder's files (names and bytes, in name order).
pub fn input_sha256(path: &Path) -> Result<String> {
    let mut h = Sha256::new();
    let feed = |p: &Path, h: &mut Sha256| -> Result<()> {
        let mut f = std::fs::File::open(p).map_err(|e| Error::io(p, e))?;
        let mut buf = vec![0u8; 1 << 16];
        loop {
            let n = f.read(&mut buf).map_err(|e| Error::io(p, e))?;
            if n == 0 {
                return Ok(());
            }
            h.update(&buf[..n]);
        }
    };
    if path.is_dir() {
        let mut files: Vec<PathBuf> = std::fs::read_dir(path)
            .map_err(|e| Error::io(path, e))?
            .filter_map(|e| Some(e.ok()?.path()))
            .filter(|p| p.is_file())
            .collect();
        files.sort();
        for f in files {
            h.update(f.file_name().unwrap_or_default().as_encoded_bytes());
            h.update([0]);
            feed(&f, &mut h)?;
        }
    } else {
        feed(path, &mut h)?;
    }
    Ok(hex(&h.finalize()))
}

/// The size and latest modification time (ns since the epoch) of a file, or of a folder's
/// files (and the folder itself); (0, 0) when it cannot be read.
pub fn input_stamp(path: &Path) -> (u64, i128) {
    let mtime = |m: &std::fs::Metadata| {
        m.modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_nanos() as i128)
    };
    match std::fs::metadata(path) {
        Ok(m) if m.is_dir() => {
            let files: Vec<std::fs::Metadata> = std::fs::read_dir(path)
                .map(|d| {
                    d.filter_map(|e| e.ok()?.metadata().ok())
                        .filter(|m| m.is_file())
                        .collect()
                })
                .unwrap_or_default();
            let bytes = files.iter().map(|m| m.len()).sum();
            let latest = files.iter().map(mtime).max().unwrap_or(0).max(mtime(&m));
            (bytes, latest)
        }
        Ok(m) => (m.len(), mtime(&m)),
        Err(_) => (0, 0),
    }
}

fn settings_sha256(settings: &Settings, options: &Options) -> String {
    let mut h = Sha256::new();
    h.update(serde_json::to_string(settings).unwrap_or_default());
    h.update([0]);
    h.update(format!("{:?}", options.format));
    h.update([0]);
    h.update(&options.config_text);
    h.update([0]);
    h.update(env!("CARGO_PKG_VERSION"));
    hex(&h.finalize())
}

/// The ledgers' folder in `out`.
pub fn ledger_dir(out: &Path) -> PathBuf {
    out.join(LEDGER_DIR)
}

/// Every record of every ledger in `out`, in file then line order. A last line cut short (a
/// task killed while writing it) is ignored.
pub fn read_records(out: &Path) -> Result<Vec<Record>> {
    let dir = ledger_dir(out);
    let mut files: Vec<PathBuf> = match std::fs::read_dir(&dir) {
        Ok(d) => d
            .filter_map(|e| Some(e.ok()?.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "jsonl"))
            .collect(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(Error::io(&dir, e)),
    };
    files.sort();
    let mut records = Vec::new();
    for f in files {
        let file = std::fs::File::open(&f).map_err(|e| Error::io(&f, e))?;
        for line in std::io::BufReader::new(file).lines() {
            let line = line.map_err(|e| Error::io(&f, e))?;
            if let Ok(r) = serde_json::from_str::<Record>(&line) {
                records.push(r);
            }
        }
    }
    Ok(records)
}

/// The latest record of each output.
fn latest(records: Vec<Record>) -> BTreeMap<String, Record> {
    let mut by_output = BTreeMap::new();
    for r in records {
        let newer = by_output
            .get(&r.output)
            .is_none_or(|old: &Record| old.finished_unix <= r.finished_unix);
        if newer {
            by_output.insert(r.output.clone(), r);
        }
    }
    by_output
}

/// The config for one item: `base` with the item's settings.
fn item_config(base: &Config, settings: &Settings, learned_threads: usize) -> Result<Config> {
    let mut config = base.clone();
    if let Some(p) = &settings.preset {
        config.stage1.preset = crate::stage1::Preset::from_name(p)?;
        config.stage1.custom = None;
    }
    if let Some(t) = settings.tier {
        config.stage1.tier = t;
    }
    if let Some(s) = settings.seed {
        config.stage1.seed = s;
        config.stage2.seed = s;
    }
    if config.stage1.learned.threads == 0 {
        config.stage1.learned.threads = learned_threads;
    }
    Ok(config)
}

/// Appends records to this shard's ledger, one whole line per write.
struct Ledger {
    path: PathBuf,
    file: Mutex<std::fs::File>,
}

impl Ledger {
    fn open(out: &Path, shard: Shard) -> Result<Ledger> {
        let dir = ledger_dir(out);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        let path = dir.join(format!("shard-{}-of-{}.jsonl", shard.index, shard.count));
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(|e| Error::io(&path, e))?;
        // One task per shard at a time: a second (a requeued task while the first still runs)
        // would write the same partial files.
        use std::os::fd::AsRawFd;
        // SAFETY: flock on a descriptor this function owns; released when the file closes.
        if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
            return Err(Error::Run(format!(
                "shard {shard} is already running here ({} is locked)",
                path.display()
            )));
        }
        Ok(Ledger {
            path,
            file: Mutex::new(file),
        })
    }

    fn append(&self, r: &Record) -> Result<()> {
        let mut line =
            serde_json::to_string(r).map_err(|e| Error::invalid("ledger", e.to_string()))?;
        line.push('\n');
        let mut f = self.file.lock().unwrap_or_else(|e| e.into_inner());
        f.write_all(line.as_bytes())
            .and_then(|()| f.sync_data())
            .map_err(|e| Error::io(&self.path, e))
    }
}

fn now_unix() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// Converts this shard's items of `manifest` into `options.out`, `options.jobs` at a time,
/// skipping each item whose latest ledger record is `done` with the same input and settings
/// and whose output is there at the recorded size. A failing item is recorded with its error
/// and the shard goes on; `stop` (a signal) ends it after the items in hand stop
/// ([`Error::Interrupted`]). `log` gets one line per item.
pub fn run(
    manifest: &Manifest,
    options: &Options,
    stop: &AtomicBool,
    log: &(dyn Fn(&str) + Sync),
) -> Result<ShardSummary> {
    let started = std::time::Instant::now();
    std::fs::create_dir_all(&options.out).map_err(|e| Error::io(&options.out, e))?;
    let mine = options.shard.select(&manifest.items);
    let done = latest(read_records(&options.out)?);
    let ledger = Ledger::open(&options.out, options.shard)?;
    let jobs = options.jobs.clamp(1, mine.len().max(1));
    let learned_threads = (options.threads / jobs).max(1);
    let next = AtomicUsize::new(0);
    let summary = Mutex::new(ShardSummary {
        items: mine.len(),
        ..ShardSummary::default()
    });
    let fatal: Mutex<Option<Error>> = Mutex::new(None);
    let shard = options.shard.to_string();
    let total = mine.len();
    std::thread::scope(|s| {
        for _ in 0..jobs {
            s.spawn(|| loop {
                if stop.load(Ordering::Relaxed) {
                    break;
                }
                let k = next.fetch_add(1, Ordering::Relaxed);
                let Some(item) = mine.get(k) else { break };
                let tag = format!("[{}/{total}] {}", k + 1, item.name);
                match do_item(item, options, &done, learned_threads, &shard, stop) {
                    Ok(Outcome::Skipped) => {
                        log(&format!("{tag}: done before, skipped"));
                        lock(&summary).skipped += 1;
                    }
                    Ok(Outcome::Converted(r)) => {
                        log(&format!(
                            "{tag} -> {}: {} frames, {} events in {:.1} s",
                            r.output, r.frames, r.events, r.wall_s
                        ));
                        if let Err(e) = ledger.append(&r) {
                            lock(&fatal).get_or_insert(e);
                            stop.store(true, Ordering::Relaxed);
                        }
                        let mut s = lock(&summary);
                        s.converted += 1;
                        s.frames += r.frames;
                        s.events += r.events;
                    }
                    Ok(Outcome::Failed(r)) => {
                        let why = r.error.clone().unwrap_or_default();
                        log(&format!("{tag}: FAILED: {why}"));
                        if let Err(e) = ledger.append(&r) {
                            lock(&fatal).get_or_insert(e);
                            stop.store(true, Ordering::Relaxed);
                        }
                        lock(&summary).failed.push((item.name.clone(), why));
                    }
                    Ok(Outcome::Interrupted) => {
                        log(&format!(
                            "{tag}: interrupted; its partial output stays, the next run redoes it"
                        ));
                    }
                    Err(e) => {
                        lock(&fatal).get_or_insert(e);
                        stop.store(true, Ordering::Relaxed);
                    }
                }
            });
        }
    });
    if let Some(e) = fatal.into_inner().unwrap_or_else(|e| e.into_inner()) {
        return Err(e);
    }
    let mut summary = summary.into_inner().unwrap_or_else(|e| e.into_inner());
    summary.wall_s = started.elapsed().as_secs_f64();
    if stop.load(Ordering::Relaxed) {
        return Err(Error::Interrupted(format!(
            "shard {shard} stopped by a signal: {} converted, {} skipped, {} failed of {}; \
             run it again to finish",
            summary.converted,
            summary.skipped,
            summary.failed.len(),
            summary.items
        )));
    }
    Ok(summary)
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

enum Outcome {
    Skipped,
    Converted(Record),
    Failed(Record),
    Interrupted,
}

/// Converts one item unless done; errors of the item become a `failed` record, errors of the
/// batch itself (the ledger) are returned.
fn do_item(
    item: &Item,
    options: &Options,
    done: &BTreeMap<String, Record>,
    learned_threads: usize,
    shard: &str,
    stop: &AtomicBool,
) -> Result<Outcome> {
    let started = std::time::Instant::now();
    let output = options.out.join(&item.output);
    let key = item.output.to_string_lossy().into_owned();
    let settings_sha = settings_sha256(&item.settings, options);
    let mut record = Record {
        input: item.name.clone(),
        output: key.clone(),
        status: "failed".into(),
        error: None,
        input_sha256: String::new(),
        input_stamp: input_stamp(&item.input),
        settings: item.settings.clone(),
        settings_sha256: settings_sha.clone(),
        version: env!("CARGO_PKG_VERSION").into(),
        frames: 0,
        events: 0,
        span_us: 0,
        bytes: 0,
        wall_s: 0.0,
        shard: shard.into(),
        finished_unix: 0.0,
    };
    let fail = |mut r: Record, e: Error| {
        r.error = Some(e.to_string());
        r.wall_s = started.elapsed().as_secs_f64();
        r.finished_unix = now_unix();
        Ok(Outcome::Failed(r))
    };
    let previous = done.get(&key);
    // Unchanged size and time since it was hashed: the recorded hash stands (a re-run of a
    // large dataset does not read every input again).
    record.input_sha256 = match previous {
        Some(p) if p.input_stamp == record.input_stamp && p.input_stamp != (0, 0) => {
            p.input_sha256.clone()
        }
        _ => match input_sha256(&item.input) {
            Ok(h) => h,
            Err(e) => return fail(record, e),
        },
    };
    if let Some(prev) = previous {
        let same = prev.status == "done"
            && prev.input_sha256 == record.input_sha256
            && prev.settings_sha256 == settings_sha;
        let there = std::fs::metadata(&output).is_ok_and(|m| m.len() == prev.bytes);
        if same && there {
            return Ok(Outcome::Skipped);
        }
    }
    if let Some(dir) = output.parent() {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    let config = match item_config(&options.config, &item.settings, learned_threads) {
        Ok(c) => c,
        Err(e) => return fail(record, e),
    };
    let size = match item.settings.size.as_deref().map(crate::config::parse_size) {
        Some(Ok(s)) => Some(s),
        Some(Err(e)) => return fail(record, e),
        None => None,
    };
    let job = FileJob {
        input: item.input.clone(),
        output: output.clone(),
        format: options.format,
        source: crate::frame::SourceOptions {
            fps: item.settings.fps,
            color: Default::default(),
        },
        size,
        max_frames: None,
        write_voxels: None,
    };
    match convert_file(&job, &config, stop, &mut ()) {
        Ok(report) => {
            record.status = "done".into();
            record.frames = report.frames;
            record.events = report.events;
            record.span_us = match (report.first_t, report.last_t) {
                (Some(a), Some(b)) => b.saturating_sub(a),
                _ => 0,
            };
            record.bytes = std::fs::metadata(&output).map_or(0, |m| m.len());
            record.wall_s = started.elapsed().as_secs_f64();
            record.finished_unix = now_unix();
            Ok(Outcome::Converted(record))
        }
        Err(Error::Interrupted(_)) => Ok(Outcome::Interrupted),
        // Stopped while failing: not surely the input's fault; redone next time.
        Err(_) if stop.load(Ordering::Relaxed) => Ok(Outcome::Interrupted),
        Err(e) => fail(record, e),
    }
}

/// Every shard's ledger in one summary.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Report {
    /// Outputs done.
    pub done: usize,
    /// Failed inputs and why.
    pub failed: Vec<(String, String)>,
    /// Manifest inputs with no record (when a manifest was given).
    pub pending: Vec<String>,
    /// Frames converted (done outputs).
    pub frames: u64,
    /// Events written (done outputs).
    pub events: u64,
    /// Sum of the items' conversion times, seconds.
    pub busy_s: f64,
    /// From the first item's start to the last item's end over all shards, seconds.
    pub span_s: f64,
    /// Per shard: items done, frames, busy seconds.
    pub shards: BTreeMap<String, (usize, u64, f64)>,
}

impl Report {
    /// Frames per second of conversion time (one task's speed).
    pub fn frames_per_busy_s(&self) -> f64 {
        self.frames as f64 / self.busy_s.max(1e-9)
    }

    /// Frames per second of elapsed time over the whole batch (all tasks together).
    pub fn frames_per_s(&self) -> f64 {
        self.frames as f64 / self.span_s.max(1e-9)
    }
}

impl std::fmt::Display for Report {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "{} done, {} failed, {} pending; {} frames, {} events",
            self.done,
            self.failed.len(),
            self.pending.len(),
            self.frames,
            self.events
        )?;
        writeln!(
            f,
            "conversion time {:.1} s ({:.1} frames/s per task); elapsed {:.1} s ({:.1} frames/s in all)",
            self.busy_s,
            self.frames_per_busy_s(),
            self.span_s,
            self.frames_per_s()
        )?;
        for (shard, (n, frames, busy)) in &self.shards {
            writeln!(
                f,
                "  shard {shard}: {n} done, {frames} frames in {busy:.1} s"
            )?;
        }
        for (input, why) in &self.failed {
            writeln!(f, "  FAILED {input}: {why}")?;
        }
        for input in &self.pending {
            writeln!(f, "  pending {input}")?;
        }
        Ok(())
    }
}

/// Merges the ledgers in `out`: the latest record of each output counts. With `manifest`, its
/// inputs without a record are listed as pending, and records of outputs it no longer lists
/// are left out.
pub fn report(out: &Path, manifest: Option<&Manifest>) -> Result<Report> {
    let latest = latest(read_records(out)?);
    let mut r = Report::default();
    let wanted: Option<std::collections::HashSet<String>> = manifest.map(|m| {
        m.items
            .iter()
            .map(|i| i.output.to_string_lossy().into_owned())
            .collect()
    });
    let (mut first, mut last) = (f64::INFINITY, f64::NEG_INFINITY);
    for rec in latest.values() {
        if wanted.as_ref().is_some_and(|w| !w.contains(&rec.output)) {
            continue;
        }
        first = first.min(rec.finished_unix - rec.wall_s);
        last = last.max(rec.finished_unix);
        if rec.status == "done" {
            r.done += 1;
            r.frames += rec.frames;
            r.events += rec.events;
            r.busy_s += rec.wall_s;
            let s = r.shards.entry(rec.shard.clone()).or_default();
            s.0 += 1;
            s.1 += rec.frames;
            s.2 += rec.wall_s;
        } else {
            r.failed
                .push((rec.input.clone(), rec.error.clone().unwrap_or_default()));
        }
    }
    if let Some(m) = manifest {
        for item in &m.items {
            if !latest.contains_key(item.output.to_string_lossy().as_ref()) {
                r.pending.push(item.name.clone());
            }
        }
    }
    r.span_s = if last >= first { last - first } else { 0.0 };
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn item(name: &str, bytes: u64) -> Item {
        Item {
            name: name.into(),
            input: name.into(),
            output: default_output(name, "aedat4"),
            settings: Settings::default(),
            bytes,
        }
    }

    #[test]
    fn shards_cover_every_item_once_balanced_by_size() {
        let items: Vec<Item> = (0..23)
            .map(|i| item(&format!("c{i}.mp4"), 1000 + (i * 7919 % 50_000)))
            .collect();
        for count in [1u32, 2, 4, 7, 30] {
            let mut seen = vec![0; items.len()];
            let mut loads = Vec::new();
            for index in 0..count {
                let shard = Shard::new(index, count).unwrap();
                let mine = shard.select(&items);
                // The same split every time.
                assert_eq!(mine, shard.select(&items));
                loads.push(mine.iter().map(|i| i.bytes).sum::<u64>());
                for m in mine {
                    seen[items.iter().position(|i| i.name == m.name).unwrap()] += 1;
                }
            }
            assert!(seen.iter().all(|&n| n == 1), "{count}: {seen:?}");
            let biggest = items.iter().map(|i| i.bytes).max().unwrap();
            let (lo, hi) = (loads.iter().min().unwrap(), loads.iter().max().unwrap());
            if count as usize <= items.len() {
                // Greedy largest-first: no shard exceeds another by more than one item.
                assert!(hi - lo <= biggest, "{count}: {loads:?}");
            }
        }
        // By size, not position: the two largest go to different shards.
        let items = vec![item("a", 100), item("b", 100), item("c", 1), item("d", 1)];
        let first = Shard::new(0, 2).unwrap().select(&items);
        assert_eq!(
            first.iter().map(|i| i.name.as_str()).collect::<Vec<_>>(),
            ["a", "c"]
        );
    }

    #[test]
    fn shards_come_from_flags_slurm_and_kubernetes() {
        assert_eq!(Shard::parse("1/4").unwrap(), Shard { index: 1, count: 4 });
        for bad in ["4/4", "1/0", "x/2", "3", "-1/2"] {
            assert!(Shard::parse(bad).is_err(), "{bad}");
        }
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |k: &str| {
                pairs
                    .iter()
                    .find(|(n, _)| *n == k)
                    .map(|(_, v)| v.to_string())
            }
        };
        let slurm = env(&[
            ("SLURM_ARRAY_TASK_ID", "3"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
        ]);
        assert_eq!(
            Shard::from_env(slurm, None).unwrap(),
            Some(Shard { index: 3, count: 4 })
        );
        // --array=1-4: ids start at 1.
        let from_one = env(&[
            ("SLURM_ARRAY_TASK_ID", "1"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
            ("SLURM_ARRAY_TASK_MIN", "1"),
        ]);
        assert_eq!(
            Shard::from_env(from_one, None).unwrap(),
            Some(Shard { index: 0, count: 4 })
        );
        let k8s = env(&[("JOB_COMPLETION_INDEX", "2")]);
        assert_eq!(
            Shard::from_env(k8s, Some(3)).unwrap(),
            Some(Shard { index: 2, count: 3 })
        );
        assert!(Shard::from_env(k8s, None).is_err());
        let k8s_env = env(&[("JOB_COMPLETION_INDEX", "2"), ("V2CE_SHARDS", "5")]);
        assert_eq!(
            Shard::from_env(k8s_env, None).unwrap(),
            Some(Shard { index: 2, count: 5 })
        );
        assert_eq!(Shard::from_env(env(&[]), None).unwrap(), None);
        assert_eq!(task_threads(env(&[("SLURM_CPUS_PER_TASK", "3")])), 3);
    }

    #[test]
    fn manifests_in_every_form() {
        let dir = std::env::temp_dir().join(format!("v2ce-batch-manifest-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("clips")).unwrap();
        for f in ["a.y4m", "b.y4m", "c.mp4"] {
            std::fs::write(dir.join("clips").join(f), b"x").unwrap();
        }
        let list = dir.join("list.txt");
        std::fs::write(
            &list,
            "# clips\nclips/a.y4m fps=25 size=64x48 preset=davis346 seed=3\n\nclips/b.y4m tier=learned output=x/b.raw\n",
        )
        .unwrap();
        let m = Manifest::load(list.to_str().unwrap(), "aedat4").unwrap();
        assert_eq!(m.items.len(), 2);
        assert_eq!(m.items[0].input, dir.join("clips/a.y4m"));
        assert_eq!(m.items[0].output, PathBuf::from("clips/a.aedat4"));
        assert_eq!(m.items[0].settings.fps, Some(25.0));
        assert_eq!(m.items[0].settings.size.as_deref(), Some("64x48"));
        assert_eq!(m.items[0].settings.seed, Some(3));
        assert_eq!(m.items[1].settings.tier, Some(crate::stage1::Tier::Learned));
        assert_eq!(m.items[1].output, PathBuf::from("x/b.raw"));
        let jsonl = dir.join("m.jsonl");
        std::fs::write(&jsonl, "{\"input\": \"clips/c.mp4\", \"fps\": 30}\n").unwrap();
        let m = Manifest::load(jsonl.to_str().unwrap(), "csv").unwrap();
        assert_eq!(m.items[0].output, PathBuf::from("clips/c.csv"));
        let pattern = format!("{}/clips/*.y4m", dir.display());
        let m = Manifest::load(&pattern, "aedat4").unwrap();
        assert_eq!(m.items.len(), 2);
        // Errors: an unknown key, two inputs to one output, an output outside the folder.
        for (text, expect) in [
            ("clips/a.y4m colour=red\n", "colour"),
            ("clips/a.y4m\nclips/a.y4m\n", "would both write"),
            ("clips/a.y4m output=../x.aedat4\n", "relative path"),
            ("{\"input\": 3}\n", "line 1"),
        ] {
            std::fs::write(&list, text).unwrap();
            let err = Manifest::load(list.to_str().unwrap(), "aedat4")
                .unwrap_err()
                .to_string();
            assert!(err.contains(expect), "{text}: {err}");
        }
        assert!(Manifest::load("/nonexistent/list.txt", "aedat4").is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
