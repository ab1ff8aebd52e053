//! The merged report: every shard's ledger in one [`Report`] (the latest record of each
//! output), with the manifest's inputs not yet converted as pending.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

use super::ledger::{latest, read_records};
use super::manifest::Manifest;
use crate::error::{Error, Result};

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
    pub(crate) fn frames_per_busy_s(&self) -> f64 {
        self.frames as f64 / self.busy_s.max(1e-9)
    }

    /// Frames per second of elapsed time over the whole batch (all tasks together).
    pub(crate) fn frames_per_s(&self) -> f64 {
        self.frames as f64 / self.span_s.max(1e-9)
    }

    /// The report as one JSON object, with the two speeds.
    pub fn to_json(&self) -> Result<String> {
        let mut v =
            serde_json::to_value(self).map_err(|e| Error::invalid("report", e.to_string()))?;
        v["frames_per_busy_s"] = self.frames_per_busy_s().into();
        v["frames_per_s"] = self.frames_per_s().into();
        Ok(v.to_string())
    }

    /// An error when an input failed (how many, of how many with a record).
    pub fn check(&self) -> Result<()> {
        if !self.failed.is_empty() {
            return Err(Error::Run(format!(
                "{} of {} inputs failed",
                self.failed.len(),
                self.failed.len() + self.done
            )));
        }
        Ok(())
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
