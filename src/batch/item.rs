//! One item of a shard: skipped when its ledger records it done with the same input and
//! settings, else converted (as `v2ce convert` does) into a `done` or `failed` [`Record`].

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};

use super::hash::{input_sha256, input_stamp, settings_sha256};
use super::ledger::Record;
use super::manifest::{Item, Settings};
use super::options::Options;
use crate::config::Config;
use crate::convert::{convert_file, FileJob};
use crate::error::{Error, Result};

/// What became of an item.
pub(super) enum Outcome {
    /// Done before with the same input and settings.
    Skipped,
    /// Converted now.
    Converted(Record),
    /// Failed (the record says why).
    Failed(Record),
    /// Stopped by a signal; redone next time.
    Interrupted,
}

/// Converts one item unless done; errors of the item become a `failed` record, errors of the
/// batch itself (the ledger) are returned.
pub(super) fn do_item(
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
    let size = match item.settings.size.as_deref().map(crate::limits::parse_size) {
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
            topic: None,
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

fn now_unix() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}
