//! `v2ce bench tradeoff`: every Stage 1 tier and setting on the same frames, measured for speed
//! (pairs per second, latency) and scored against real or ground-truth events (TF1, TPF1, the
//! event-count ratio, C-METE), so users can see what accuracy each setting buys.
//!
//! A [`Scene`] is frames with the events a sensor gave for them (a real recording, with the
//! frame intervals to score, e.g. the half a model did not train on) or that the physics tier
//! gave at 1 kHz (a synthetic sequence of `v2ce dataset`, made again from its seed). A
//! [`Setting`] is a Stage 1 configuration and a Stage 2 sampler. [`measure`] runs one setting on
//! one scene in this process, single pass, and scores it as `v2ce eval stage1` does
//! ([`crate::eval::stage1`]); [`run`] measures every setting on every group of scenes.
//! [`matrix`] holds what the bench measures (the settings, the scenes), `chart` draws its [`plot`].

mod chart;
pub mod matrix;

pub use chart::plot;
pub use matrix::{settings, still_scenes, synthetic_scenes};

use std::time::Instant;

use serde::Serialize;

use crate::error::Result;
use crate::event::{sort_events, Event};
use crate::frame::{Frame, SourceEncoding};
use crate::interval::Interval;
use crate::stage1::{Stage1Batch, Stage1Config};
use crate::stage2::SamplerKind;
use crate::voxel::DEFAULT_BINS;

/// Frames and the events to score against.
pub struct Scene {
    /// Its name in the table.
    pub name: String,
    /// The frames, in time order.
    pub frames: Vec<Frame>,
    /// How the frames' values were decoded (for the learned tier's input).
    pub encoding: SourceEncoding,
    /// The real (or ground-truth) events, sorted.
    pub events: Vec<Event>,
    /// The frame intervals scored.
    pub scored: Vec<Interval>,
}

/// One Stage 1 configuration and sampler.
#[derive(Clone)]
pub struct Setting {
    /// Its name in the table.
    pub label: String,
    /// Stage 1.
    pub stage1: Stage1Config,
    /// Stage 2's sampler (for tiers that hand over voxels).
    pub sampler: SamplerKind,
}

/// What one setting did on one scene.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    /// The setting.
    pub setting: String,
    /// The scene.
    pub scene: String,
    /// Frame intervals simulated.
    pub pairs: u64,
    /// Wall time of Stage 1 and Stage 2 over the whole scene, s.
    pub seconds: f64,
    /// Frame intervals per second.
    pub pairs_per_s: f64,
    /// Median time of one window's inference (learned tier), ms; 0 for the physics tier.
    pub window_ms: f64,
    /// The share of whole-frame network compute spent (learned tier: crops around what
    /// changed, still windows skipped); 1 for the physics tier.
    pub compute: f64,
    /// TF1 on the scored intervals.
    pub tf1: f64,
    /// TPF1.
    pub tpf1: f64,
    /// Simulated over real events on the scored intervals.
    pub count_ratio: f64,
    /// C-METE, us.
    pub c_mete_us: f64,
    /// Simulated events on the scored intervals.
    pub events: u64,
    /// Real (or ground-truth) events on the scored intervals.
    pub real_events: u64,
}

/// Runs `setting` on `scene` (see the module docs).
pub fn measure(setting: &Setting, scene: &Scene) -> Result<Row> {
    let Some(first) = scene.frames.first() else {
        return Err(crate::Error::invalid("tradeoff", "a scene without frames"));
    };
    let size = (first.width, first.height);
    let mut stage1 = crate::stage1::build(&setting.stage1, DEFAULT_BINS, size, scene.encoding)?;
    let sampler = setting.sampler.build(setting.stage1.seed);
    let mut batches = Vec::new();
    let mut events = Vec::new();
    let drain = |batches: &mut Vec<Stage1Batch>, events: &mut Vec<Event>| {
        for b in batches.drain(..) {
            match b {
                Stage1Batch::Events { events: e, .. } => events.extend(e),
                Stage1Batch::Voxels(grid, interval) => {
                    sampler.sample(&grid, interval, events);
                }
            }
        }
    };
    let started = Instant::now();
    for f in &scene.frames {
        stage1.push(f, &mut batches)?;
        drain(&mut batches, &mut events);
    }
    stage1.finish(&mut batches)?;
    drain(&mut batches, &mut events);
    let seconds = started.elapsed().as_secs_f64();
    sort_events(&mut events);
    let report = crate::eval::stage1(&scene.events, &events, &scene.scored, size)?;
    let m = report.voxels;
    let pairs = scene.frames.len().saturating_sub(1) as u64;
    let stats = stage1.stats();
    Ok(Row {
        setting: setting.label.clone(),
        scene: scene.name.clone(),
        pairs,
        seconds,
        pairs_per_s: pairs as f64 / seconds.max(1e-9),
        window_ms: stats.window_ms_p50,
        compute: stats.compute,
        tf1: m.tf1,
        tpf1: m.tpf1,
        count_ratio: m.count_ratio(),
        c_mete_us: report.timing.c_mete_us,
        events: m.sim_events,
        real_events: m.real_events,
    })
}

/// Rows of the same setting on several scenes as one: times and events added, the count ratio
/// of the totals, scores averaged over the scenes that have real events (each counts once, as
/// the paper averages over chunks; a scene where nothing happened has no score, but its time
/// and compute count).
pub fn combine(rows: &[Row], scene: &str) -> Option<Row> {
    let first = rows.first()?;
    let scored: Vec<&Row> = rows.iter().filter(|r| r.real_events > 0).collect();
    let mean = |f: fn(&Row) -> f64| {
        if scored.is_empty() {
            0.0
        } else {
            scored.iter().map(|r| f(r)).sum::<f64>() / scored.len() as f64
        }
    };
    let pairs = rows.iter().map(|r| r.pairs).sum();
    let seconds = rows.iter().map(|r| r.seconds).sum::<f64>();
    let events = rows.iter().map(|r| r.events).sum::<u64>();
    let real_events = rows.iter().map(|r| r.real_events).sum::<u64>();
    Some(Row {
        setting: first.setting.clone(),
        scene: scene.to_string(),
        pairs,
        seconds,
        pairs_per_s: pairs as f64 / seconds.max(1e-9),
        window_ms: rows.iter().map(|r| r.window_ms).sum::<f64>() / rows.len() as f64,
        compute: rows.iter().map(|r| r.compute * r.pairs as f64).sum::<f64>()
            / (pairs as f64).max(1.0),
        tf1: mean(|r| r.tf1),
        tpf1: mean(|r| r.tpf1),
        count_ratio: if real_events > 0 {
            events as f64 / real_events as f64
        } else {
            0.0
        },
        c_mete_us: mean(|r| r.c_mete_us),
        events,
        real_events,
    })
}

/// A group's name: that of its scenes (they share one).
pub fn group_name(group: &[Scene]) -> String {
    group.first().map(|s| s.name.clone()).unwrap_or_default()
}

/// Measures every setting on every group of scenes, in order, combining each setting's rows on
/// a group ([`combine`]); each combined row goes to `on_row` as it is made, and all are
/// returned.
pub fn run(
    groups: &[Vec<Scene>],
    settings: &[Setting],
    mut on_row: impl FnMut(&Row) -> Result<()>,
) -> Result<Vec<Row>> {
    let mut rows = Vec::new();
    for group in groups {
        let name = group_name(group);
        for setting in settings {
            let each = group
                .iter()
                .map(|scene| measure(setting, scene))
                .collect::<Result<Vec<_>>>()?;
            if let Some(row) = combine(&each, &name) {
                on_row(&row)?;
                rows.push(row);
            }
        }
    }
    Ok(rows)
}

/// The rows as a Markdown table.
pub fn table(rows: &[Row]) -> String {
    let mut out = String::from(
        "| setting | scene | pairs/s | window ms | compute | TF1 | TPF1 | count ratio | C-METE (us) |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in rows {
        out.push_str(&format!(
            "| {} | {} | {:.1} | {:.0} | {:.0}% | {:.3} | {:.3} | {:.2} | {:.0} |\n",
            r.setting,
            r.scene,
            r.pairs_per_s,
            r.window_ms,
            100.0 * r.compute,
            r.tf1,
            r.tpf1,
            r.count_ratio,
            r.c_mete_us
        ));
    }
    out
}

/// The settings on the Pareto front of speed (pairs/s) and TF1 for `scene`: no other row is
/// at least as fast and as accurate, and better in one.
pub fn pareto<'a>(rows: &'a [Row], scene: &str) -> Vec<&'a Row> {
    let of: Vec<&Row> = rows.iter().filter(|r| r.scene == scene).collect();
    of.iter()
        .filter(|r| {
            !of.iter().any(|o| {
                o.pairs_per_s >= r.pairs_per_s
                    && o.tf1 >= r.tf1
                    && (o.pairs_per_s > r.pairs_per_s || o.tf1 > r.tf1)
            })
        })
        .copied()
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(setting: &str, speed: f64, tf1: f64) -> Row {
        Row {
            setting: setting.into(),
            scene: "s".into(),
            pairs: 10,
            seconds: 10.0 / speed,
            pairs_per_s: speed,
            window_ms: 0.0,
            compute: 1.0,
            tf1,
            tpf1: tf1,
            count_ratio: 1.0,
            c_mete_us: 0.0,
            events: 100,
            real_events: 100,
        }
    }

    #[test]
    fn the_front_keeps_what_nothing_beats() {
        let rows = vec![
            row("fast", 100.0, 0.5),
            row("good", 1.0, 0.7),
            row("worse", 50.0, 0.4),
        ];
        let front: Vec<&str> = pareto(&rows, "s")
            .iter()
            .map(|r| r.setting.as_str())
            .collect();
        assert_eq!(front, vec!["fast", "good"]);
    }

    #[test]
    fn combined_rows_average_scores_and_add_counts() {
        let mut a = row("x", 10.0, 0.6);
        a.real_events = 50; // 100 events for 50 real
        let b = row("x", 10.0, 0.4); // 100 for 100
                                     // A scene where nothing happened: no score, but its events count.
        let mut still = row("x", 10.0, 0.0);
        still.real_events = 0;
        still.events = 30;
        let c = combine(&[a, b, still], "all").unwrap();
        assert!((c.tf1 - 0.5).abs() < 1e-12);
        assert!((c.count_ratio - 230.0 / 150.0).abs() < 1e-9);
        assert_eq!(c.pairs, 30);
    }
}
