//! Evaluation runs: score simulated events against real ones (Stage 1, [`stage1`]) or a sampler
//! on a real or synthetic recording (Stage 2, [`stage2`]), and read what they score: real events
//! with their frame intervals ([`load_events_and_intervals`]), the physics tier's events for a
//! recording's own frames ([`simulate_physics`]), the built-in recording ([`sweeping_bar`]).

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use crate::error::{Error, Result};
use crate::event::{time_slice, Event};
use crate::format::{self, Recording};
use crate::interval::{fixed_intervals, intervals_from_frames, Interval};
use crate::metrics::{IntervalScore, IntervalScratch, Stage1Metrics, Stage2Metrics, Stage2Scorer};
use crate::stage1::Stage1Config;
use crate::stage2::{SampleStats, Sampler};
use crate::voxel::{VoxelGrid, Voxelizer, DEFAULT_BINS};

/// The median of timings, as the reports give it (kept here under its old path).
pub use crate::stats::median;

/// What a Stage 2 evaluation measured.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Stage2Report {
    /// The sampler's name.
    pub sampler: String,
    /// The timestamp metrics.
    #[serde(flatten)]
    pub metrics: Stage2Metrics,
    /// Values the sampler had to repair (always zero for voxels of real events).
    pub repaired: SampleStats,
    /// Median wall time to voxelize one interval, us.
    pub voxelize_us_median: f64,
    /// Median wall time to sample one interval, us.
    pub sample_us_median: f64,
}

/// Intervals each worker of [`stage2`] takes per round: enough to keep the threads busy, few
/// enough that a round's sampled events stay small.
const INTERVALS_PER_WORKER: usize = 8;

/// One thread's working state in [`stage2`].
struct Stage2Worker {
    voxelizer: Voxelizer,
    grid: VoxelGrid,
    scratch: IntervalScratch,
}

/// What [`stage2`] learned from one interval.
struct Stage2Interval {
    score: IntervalScore,
    repaired: SampleStats,
    events: Vec<Event>,
    voxelize_us: f64,
    sample_us: f64,
}

impl Stage2Worker {
    fn run(
        &mut self,
        recording: &Recording,
        interval: Interval,
        sampler: &dyn Sampler,
    ) -> Result<Stage2Interval> {
        let truth = recording
            .events
            .time_slice(interval.start(), interval.end());
        let t0 = Instant::now();
        self.voxelizer
            .voxelize_into(truth, interval, &mut self.grid)?;
        let t1 = Instant::now();
        let mut events = Vec::new();
        let repaired = sampler.sample(&self.grid, interval, &mut events);
        let t2 = Instant::now();
        Ok(Stage2Interval {
            score: self.scratch.score(interval, truth, &events),
            repaired,
            events,
            voxelize_us: (t1 - t0).as_secs_f64() * 1e6,
            sample_us: (t2 - t1).as_secs_f64() * 1e6,
        })
    }
}

/// Runs the intervals of `round` on the `workers`, one thread each (none with one worker);
/// returns what each gave, in the round's order.
fn run_round(
    workers: &mut [Stage2Worker],
    round: &[Interval],
    recording: &Recording,
    sampler: &dyn Sampler,
) -> Result<Vec<Result<Stage2Interval>>> {
    if let [worker] = workers {
        return Ok(round
            .iter()
            .map(|&iv| worker.run(recording, iv, sampler))
            .collect());
    }
    let next = AtomicUsize::new(0);
    let parts = std::thread::scope(|scope| {
        let handles: Vec<_> = workers
            .iter_mut()
            .map(|worker| {
                let next = &next;
                scope.spawn(move || {
                    let mut mine = Vec::new();
                    loop {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        let Some(&iv) = round.get(i) else { break };
                        mine.push((i, worker.run(recording, iv, sampler)));
                    }
                    mine
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join()).collect::<Vec<_>>()
    });
    let mut slots: Vec<Option<Result<Stage2Interval>>> =
        std::iter::repeat_with(|| None).take(round.len()).collect();
    for part in parts {
        let part = part
            .map_err(|_| Error::invalid("eval stage2", "a worker thread panicked".to_string()))?;
        for (i, r) in part {
            slots[i] = Some(r);
        }
    }
    Ok(slots.into_iter().flatten().collect())
}

/// Voxelizes the events of each interval with `bins` nodes, re-samples them with `sampler`,
/// scores the result against the original events, and hands each interval's sampled events
/// (sorted) to `on_events`, in interval order.
///
/// Intervals are independent, so they run on every core the machine has, in rounds of a few
/// per thread; their scores are added in interval order, so the report is the same on any
/// number of threads.
pub fn stage2(
    recording: &Recording,
    intervals: &[Interval],
    bins: usize,
    sampler: &dyn Sampler,
    on_events: impl FnMut(&[Event]) -> Result<()>,
) -> Result<Stage2Report> {
    // Each thread holds a voxelizer (512 MiB at 8192 x 8192): more threads only while theirs
    // take at most a quarter of the memory left.
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let each = Voxelizer::fixed_bytes(recording.width, recording.height).max(1);
    let by_memory = crate::limits::memory_available().map_or(cores, |free| {
        usize::try_from(free / 4 / each).unwrap_or(usize::MAX)
    });
    let threads = cores.min(by_memory).max(1);
    stage2_on(threads, recording, intervals, bins, sampler, on_events)
}

/// [`stage2`] on `threads` threads.
fn stage2_on(
    threads: usize,
    recording: &Recording,
    intervals: &[Interval],
    bins: usize,
    sampler: &dyn Sampler,
    mut on_events: impl FnMut(&[Event]) -> Result<()>,
) -> Result<Stage2Report> {
    let threads = threads.clamp(1, intervals.len().max(1));
    let mut workers = (0..threads)
        .map(|_| {
            Ok(Stage2Worker {
                voxelizer: Voxelizer::new(recording.width, recording.height, bins)?,
                grid: VoxelGrid::new(recording.width, recording.height, bins)?,
                scratch: IntervalScratch::default(),
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let mut scorer = Stage2Scorer::new();
    let mut repaired = SampleStats::default();
    let (mut vox_us, mut smp_us) = (Vec::new(), Vec::new());
    for round in intervals.chunks(threads * INTERVALS_PER_WORKER) {
        for d in run_round(&mut workers, round, recording, sampler)? {
            let d = d?;
            scorer.add(d.score);
            repaired.add(d.repaired);
            vox_us.push(d.voxelize_us);
            smp_us.push(d.sample_us);
            on_events(&d.events)?;
        }
    }
    Ok(Stage2Report {
        sampler: sampler.name().to_string(),
        metrics: scorer.finish(),
        repaired,
        voxelize_us_median: median(&mut vox_us),
        sample_us_median: median(&mut smp_us),
    })
}

/// What a Stage 1 evaluation measured.
#[derive(Debug, Clone, Copy)]
pub struct Stage1Report {
    /// The voxel scores (TPF1, TF1, RF1, accuracies, PMSE-2/4) and event counts.
    pub voxels: Stage1Metrics,
    /// The timestamp metrics between the two streams (C-METE, METE, PGER).
    pub timing: Stage2Metrics,
}

impl Stage1Report {
    /// The report as `v2ce eval stage1 --json` prints it: the voxel scores, the count ratio and
    /// the timestamp metrics in one object.
    pub fn to_json(&self) -> serde_json::Value {
        let (m, t) = (self.voxels, self.timing);
        let mut v = serde_json::to_value(m).unwrap_or_default();
        v["count_ratio"] = m.count_ratio().into();
        v["c_mete_us"] = t.c_mete_us.into();
        v["mete_us"] = t.mete_us.into();
        v["pger"] = t.pger.into();
        v
    }
}

/// Scores `sim` against `real` (both sorted by time) on `intervals` for a sensor of `size`:
/// both voxelized with [`DEFAULT_BINS`] nodes per interval and compared, and the Stage 2
/// timestamp metrics of `sim`'s events against `real`'s in each interval.
pub fn stage1(
    real: &[Event],
    sim: &[Event],
    intervals: &[Interval],
    size: (u16, u16),
) -> Result<Stage1Report> {
    stage1_with(real, sim, intervals, size, &|| Ok(()))
}

/// [`stage1`], calling `tick` between chunks of intervals: its error (an interrupt) ends the
/// scoring.
pub fn stage1_with(
    real: &[Event],
    sim: &[Event],
    intervals: &[Interval],
    size: (u16, u16),
    tick: &dyn Fn() -> Result<()>,
) -> Result<Stage1Report> {
    let voxels = crate::metrics::stage1::score_with(
        real,
        sim,
        intervals,
        size.0,
        size.1,
        DEFAULT_BINS,
        tick,
    )?;
    let mut scorer = Stage2Scorer::new();
    for (i, iv) in intervals.iter().enumerate() {
        if i % 1024 == 0 {
            tick()?;
        }
        scorer.add_interval(
            *iv,
            time_slice(real, iv.start(), iv.end()),
            time_slice(sim, iv.start(), iv.end()),
        );
    }
    Ok(Stage1Report {
        voxels,
        timing: scorer.finish(),
    })
}

/// Checks that every event of `events` (read from `name`) lies on a `size` sensor.
pub fn check_sensor(events: &[Event], size: (u16, u16), name: &Path) -> Result<()> {
    match events.iter().find(|e| e.x >= size.0 || e.y >= size.1) {
        Some(e) => Err(Error::format(
            name,
            format!(
                "event at ({}, {}) outside the real {} x {} sensor",
                e.x, e.y, size.0, size.1
            ),
        )),
        None => Ok(()),
    }
}

/// The built-in recording `v2ce eval stage2` scores without real events: the sweeping bar
/// (128 x 96, 2 s) with fixed intervals at `fps`.
pub fn sweeping_bar(fps: f64) -> Result<(Recording, Vec<Interval>)> {
    let intervals = fixed_intervals(0, 1_999_999, fps)?;
    Ok((
        crate::sweeping_bar::recording(128, 96, 2_000_000, 1),
        intervals,
    ))
}

/// Whether `path` names an AEDAT 4.0 file (by its extension).
pub fn is_aedat4(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("aedat4"))
}

/// Reads real events and their frame intervals: from `frames` (an .aedat4 with APS frames or
/// IJRR images.txt), from a fixed `fps` starting at the first event, or, when neither is given,
/// from the APS frames of an .aedat4 event file (decoded once with its events; `note` is told
/// so first).
pub fn load_events_and_intervals(
    events_path: &Path,
    frames: Option<&Path>,
    fps: Option<f64>,
    note: impl FnOnce(&str),
) -> Result<(Recording, Vec<Interval>)> {
    let own_frames =
        fps.is_none() && is_aedat4(events_path) && frames.is_none_or(|f| f == events_path);
    let (recording, frames) = if own_frames {
        if frames.is_none() {
            note(&format!(
                "no --frames or --fps: using the APS frames of {}",
                events_path.display()
            ));
        }
        let (recording, frames) = format::aedat4::read(events_path)?;
        (
            recording,
            Some(format::require_frames(events_path, frames)?),
        )
    } else {
        let frames = match frames {
            Some(path) => Some(format::read_frame_times(path)?),
            None => None,
        };
        (format::read_events(events_path)?, frames)
    };
    let intervals = if let Some(frames) = frames {
        intervals_from_frames(&frames)?
    } else if let Some(fps) = fps {
        let ev = recording.events.events();
        match (ev.first(), ev.last()) {
            (Some(a), Some(b)) => fixed_intervals(a.t, b.t, fps)?,
            _ => Vec::new(),
        }
    } else {
        return Err(Error::invalid(
            "arguments",
            "give --frames FILE or --fps F to define the frame intervals",
        ));
    };
    Ok((recording, intervals))
}

/// The physics tier's events, with `stage1`'s preset and `seed`, for the frames of the
/// recording `real` of `size`: its own APS frames, or those of `frames` when that is a frame
/// source rather than an .aedat4 (`v2ce eval stage1` without `--sim`). A recording without
/// frames, given a frame rate `fps`, is simulated from frames reconstructed from its own
/// `events` ([`crate::reconstruct`]). `note` is told what is simulated before it is.
pub fn simulate_physics(
    real: &Path,
    frames: Option<&Path>,
    (events, fps): (&[crate::event::Event], Option<f64>),
    stage1: &Stage1Config,
    seed: u64,
    size: (u16, u16),
    note: impl FnOnce(&str),
) -> Result<Recording> {
    let path = match frames {
        Some(f) if !is_aedat4(f) => f,
        _ => real,
    };
    // A recording has frames of its own only as an .aedat4 with an APS stream.
    let own = (frames.is_some() || is_aedat4(real))
        .then(|| crate::frame::open(path, &Default::default()));
    let mut source = match (own, fps) {
        (Some(Ok(source)), _) => source,
        (None | Some(Err(_)), Some(fps)) if frames.is_none() => {
            let how = crate::reconstruct::Reconstruction::default();
            Box::new(crate::reconstruct::EventFrames::new(
                events.to_vec(),
                size,
                fps,
                how,
            )?) as Box<dyn crate::frame::FrameSource>
        }
        (Some(Err(e)), _) => return Err(e),
        (None, _) => {
            return Err(Error::invalid(
                "frames",
                format!(
                    "{} has no frames to simulate: give --frames, --fps (frames reconstructed                      from its events) or --sim",
                    real.display()
                ),
            ))
        }
    };
    if source.size() != size {
        return Err(Error::invalid(
            "eval stage1",
            format!(
                "frames of {} x {} for a {} x {} recording",
                source.size().0,
                source.size().1,
                size.0,
                size.1
            ),
        ));
    }
    // One frame at a time: a high --fps over a long recording makes more frames than memory
    // holds, the events they make are bounded as the pixel model's are.
    note(&format!(
        "simulating the frames of {} with the physics tier (preset {})",
        source.describe(),
        stage1.preset_name()
    ));
    let (events, frames) =
        crate::calibrate::simulate_source(source.as_mut(), size, &stage1.physics_config(), seed)?;
    tracing::info!("simulated {frames} frames");
    Ok(Recording::new(events, Some(size)))
}

/// The noise floors ([`crate::metrics::realism::FloorMeter`]) of the `real` and `sim` events
/// of a `size` sensor over the consecutive frames of `frames` (read one at a time).
pub fn noise_floors(
    frames: &Path,
    size: (u16, u16),
    streams: [&[crate::event::Event]; 2],
) -> Result<[crate::metrics::realism::NoiseFloor; 2]> {
    let mut source = crate::frame::open(frames, &Default::default())?;
    if source.size() != size {
        return Err(Error::invalid(
            "frames",
            format!(
                "{}: frames of {} x {} for a {} x {} recording",
                frames.display(),
                source.size().0,
                source.size().1,
                size.0,
                size.1
            ),
        ));
    }
    let mut meter =
        crate::metrics::realism::FloorMeter::new(usize::from(size.0), crate::frame::FULL_SCALE);
    let mut previous = source.next_frame()?;
    while let Some(frame) = source.next_frame()? {
        if let Some(p) = &previous {
            meter.add(&p.luma, &frame.luma, (p.t, frame.t), streams);
        }
        previous = Some(frame);
    }
    Ok(meter.floors)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stage2::SamplerKind;

    /// The report and the events handed out are the same on one thread and on several, where
    /// rounds end mid-recording and threads finish out of order.
    #[test]
    fn stage2_gives_the_same_on_any_number_of_threads() {
        let (recording, intervals) = sweeping_bar(30.0).unwrap();
        for kind in [SamplerKind::Spatial, SamplerKind::Ldati] {
            let sampler = kind.build(7);
            let run = |threads| {
                let mut events = Vec::new();
                let report =
                    stage2_on(threads, &recording, &intervals, 10, sampler.as_ref(), |e| {
                        events.push(e.to_vec());
                        Ok(())
                    })
                    .unwrap();
                (
                    serde_json::to_value(report.metrics).unwrap(),
                    report.repaired,
                    events,
                )
            };
            let one = run(1);
            assert_eq!(one.2.len(), intervals.len());
            assert!(one.2.iter().map(Vec::len).sum::<usize>() > 1000);
            for threads in [2, 3, 5] {
                let many = run(threads);
                assert_eq!(many.0, one.0, "{} on {threads} threads", kind.name());
                assert_eq!(many.1, one.1);
                assert!(many.2 == one.2, "{} on {threads} threads", kind.name());
            }
        }
    }
}
