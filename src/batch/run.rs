//! The run loop of one shard: its items converted `jobs` at a time, each result appended to
//! the shard's ledger, and what the shard did in a [`ShardSummary`].

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;

use serde::Serialize;

use super::item::{do_item, Outcome};
use super::ledger::{latest, read_records, Ledger};
use super::manifest::Manifest;
use super::options::Options;
use super::shard::Shard;
use crate::error::{Error, Result};

/// What [`run`] did in this shard.
#[derive(Debug, Clone, Serialize)]
pub struct ShardSummary {
    /// The shard.
    #[serde(skip)]
    pub(crate) shard: Shard,
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

impl ShardSummary {
    /// The summary as one JSON object.
    pub fn to_json(&self) -> Result<String> {
        serde_json::to_string(self).map_err(|e| Error::invalid("summary", e.to_string()))
    }

    /// An error when an item failed (how many, and the first).
    pub fn check(&self) -> Result<()> {
        if let Some((input, why)) = self.failed.first() {
            return Err(Error::Run(format!(
                "{} of {} inputs of shard {} failed (first: {input}: {why})",
                self.failed.len(),
                self.items,
                self.shard
            )));
        }
        Ok(())
    }
}

/// The summary line: items, converted, skipped, failed, frames, events, time and speed.
impl std::fmt::Display for ShardSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "shard {}: {} items, {} converted, {} skipped (done before), {} failed; {} frames, \
             {} events in {:.1} s ({:.1} frames/s)",
            self.shard,
            self.items,
            self.converted,
            self.skipped,
            self.failed.len(),
            self.frames,
            self.events,
            self.wall_s,
            self.frames as f64 / self.wall_s.max(1e-9)
        )
    }
}

/// Converts this shard's items of `manifest` into `options.out`, `options.jobs` at a time,
/// skipping each item whose latest ledger record is `done` with the same input and settings
/// and whose output is there at the recorded size. A failing item is recorded with its error
/// and the shard goes on; `stop` (a signal) ends it after the items in hand stop
/// ([`Error::Interrupted`]). `log` gets one line per item. Before anything is converted, the
/// manifest's outputs are checked in `options.out` as the disk resolves them
/// (`Manifest::check_outputs`: none into the ledgers' folder, no two one file).
pub fn run(
    manifest: &Manifest,
    options: &Options,
    stop: &AtomicBool,
    log: &(dyn Fn(&str) + Sync),
) -> Result<ShardSummary> {
    let started = std::time::Instant::now();
    std::fs::create_dir_all(&options.out).map_err(|e| Error::io(&options.out, e))?;
    manifest.check_outputs(&options.out)?;
    let mine = options.shard.select(&manifest.items);
    let done = latest(read_records(&options.out)?);
    let ledger = Ledger::open(&options.out, options.shard)?;
    let jobs = options.jobs.clamp(1, mine.len().max(1));
    let learned_threads = (options.threads / jobs).max(1);
    let next = AtomicUsize::new(0);
    let summary = Mutex::new(ShardSummary {
        shard: options.shard,
        items: mine.len(),
        converted: 0,
        skipped: 0,
        failed: Vec::new(),
        frames: 0,
        events: 0,
        wall_s: 0.0,
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
