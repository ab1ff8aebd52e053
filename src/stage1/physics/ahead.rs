//! Offline runs: the motion of the next interval found on a thread of its own while the pixel
//! model steps through the current one.
//!
//! Under `motion = "flow"` an interval's sub-frames (the flows, their checks, the warp) must be
//! known before its pixels are stepped, and they take about as long. A run that reads its
//! frames as fast as it can (a convert) hands the pixel model each frame together with the
//! next one ([`super::PhysicsSim::step_next`]); the model then starts the next interval's
//! motion on the worker before it steps the current interval, and takes the result at the next
//! step. What the worker computed is used only if it was computed from exactly what that step
//! sees (the same frames, times and exposure scale, compared value for value); otherwise it is
//! computed again there, so the events are those of a run without the worker. Live runs do not
//! use it: their frames come one at a time.

use std::sync::mpsc::{channel, Receiver, Sender};
use std::thread::JoinHandle;

use crate::error::{Error, Result};
use crate::stage1::motion::{MotionStats, Subframes};

/// What the worker is given: the motion model and one interval's inputs.
pub(super) struct Job {
    pub motion: Subframes,
    pub f0: Vec<u16>,
    pub scale0: f32,
    pub f1: Vec<u16>,
    pub t0: i64,
    pub t1: i64,
    pub tile: usize,
}

/// One interval's motion computed ahead, with the inputs it was computed from.
pub(super) struct Done {
    pub job: Job,
    /// The motion model's counters before the computation (restored when it goes unused).
    pub before: MotionStats,
}

/// The worker thread and the job it holds.
pub(super) struct Ahead {
    jobs: Option<Sender<(Job, MotionStats)>>,
    done: Receiver<Done>,
    worker: Option<JoinHandle<()>>,
    /// The counters of the motion model at the job's start, while a job is out.
    pub out: Option<MotionStats>,
}

impl Ahead {
    /// Starts the worker.
    pub fn start() -> Result<Self> {
        let (jobs, inbox) = channel::<(Job, MotionStats)>();
        let (outbox, done) = channel();
        let worker = std::thread::Builder::new()
            .name("v2ce-motion".into())
            .spawn(move || {
                for (mut job, before) in inbox {
                    job.motion
                        .compute(&job.f0, job.scale0, &job.f1, job.t0, job.t1, job.tile);
                    if outbox.send(Done { job, before }).is_err() {
                        return;
                    }
                }
            })
            .map_err(|e| Error::Run(format!("no thread for the motion ahead: {e}")))?;
        Ok(Ahead {
            jobs: Some(jobs),
            done,
            worker: Some(worker),
            out: None,
        })
    }

    /// Hands `job` to the worker; gives it back if the worker is gone.
    pub fn send(&mut self, job: Job) -> std::result::Result<(), Box<Job>> {
        let before = job.motion.stats();
        match &self.jobs {
            Some(jobs) => match jobs.send((job, before)) {
                Ok(()) => {
                    self.out = Some(before);
                    Ok(())
                }
                Err(e) => Err(Box::new(e.0 .0)),
            },
            None => Err(Box::new(job)),
        }
    }

    /// The job out, once the worker is done with it; an error if the worker stopped with it.
    pub fn wait(&mut self) -> Result<Option<Done>> {
        if self.out.take().is_none() {
            return Ok(None);
        }
        self.done
            .recv()
            .map(Some)
            .map_err(|_| Error::Run("the motion worker stopped with its interval".into()))
    }
}

impl Drop for Ahead {
    fn drop(&mut self) {
        // Closing the queue ends the worker after its job.
        self.jobs = None;
        if let Some(worker) = self.worker.take() {
            let _ = worker.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::event::Event;
    use crate::frame::scene_fn::SceneSource;
    use crate::frame::{Frame, FrameSource};
    use crate::stage1::{PhysicsConfig, PhysicsSim, Preset};

    /// On [`frames`]: a textured bar moving 6 px a frame, the first frames black (the scene's level is set
    /// late, which starts the pixels over), and an exposure that changes mid-way (the light's
    /// scale between frames changes): looking ahead gives the events, and the motion's
    /// counters, of stepping frame by frame; so does a caller that names the wrong next frame
    /// (the motion found ahead goes unused).
    /// The test scene's frames (see [`looking_ahead_changes_no_event`]).
    pub(super) fn frames() -> Vec<Frame> {
        let scene = |t: i64, x: u16, y: u16| {
            if t < 70_000 {
                return 0.0;
            }
            let edge = 20.0 + 180.0 * t as f64 * 1e-6;
            let (x, y) = (x as f64, y as f64);
            let inside = x < edge && x > edge - 24.0;
            let tex = 0.5 + 0.3 * (x * 0.4).sin() * (y * 0.3).cos();
            if inside {
                0.6 * tex
            } else {
                0.15 * tex
            }
        };
        let mut source = SceneSource::new("bar", 120, 72, 30.0, 14, Box::new(scene));
        let mut frames: Vec<Frame> = Vec::new();
        while let Some(mut f) = source.next_frame().unwrap() {
            let k = frames.len();
            f.exposure_us = Some(if k < 9 { 4000 } else { 2000 });
            frames.push(f);
        }
        frames
    }

    #[test]
    fn looking_ahead_changes_no_event() {
        let frames = frames();
        let cfg = PhysicsConfig {
            max_subframes: 8,
            ..Preset::Davis346.config()
        };
        // Frames told as next: none, the next one, or the one after it.
        let run = |ahead: Option<usize>| -> (Vec<Event>, PhysicsSim) {
            let mut sim = PhysicsSim::new(cfg.clone(), 120, 72, 5).unwrap();
            if ahead.is_some() {
                sim.look_ahead();
                assert!(sim.looks_ahead());
            }
            let mut events = Vec::new();
            for (k, f) in frames.iter().enumerate() {
                let next = ahead.and_then(|d| frames.get(k + d));
                sim.step_next(f, next, &mut events).unwrap();
            }
            (events, sim)
        };
        let counters = |sim: &PhysicsSim| {
            let mut stats = sim.stats();
            stats.motion.flow_us = 0;
            stats
        };
        let (plain, a) = run(None);
        assert!(a.stats().motion.subframes > 0, "{:?}", a.stats());
        assert!(plain.len() > 1_000, "{} events", plain.len());
        for told in [1, 2] {
            let (ahead, b) = run(Some(told));
            assert_eq!(plain, ahead, "told frame k + {told} as next");
            assert_eq!(counters(&a), counters(&b), "told frame k + {told} as next");
        }
    }

    /// The physics tier looking ahead holds one frame back and hands on the same batches, each one
    /// frame later, the last at `finish`; in both outputs.
    #[test]
    fn a_tier_looking_ahead_hands_on_the_same_batches() {
        use crate::stage1::{Stage1Batch, Stage1Config, Stage1Output};
        let frames = frames();
        for output in [Stage1Output::Events, Stage1Output::Voxels] {
            let config = Stage1Config {
                output,
                ..Default::default()
            };
            let run = |ahead: bool| -> Vec<String> {
                let mut tier =
                    crate::stage1::build(&config, 10, (120, 72), Default::default()).unwrap();
                if ahead {
                    tier.look_ahead();
                }
                let mut out = Vec::new();
                for (k, f) in frames.iter().enumerate() {
                    tier.push(f, &mut out).unwrap();
                    let closed = if ahead { k.saturating_sub(1) } else { k };
                    assert_eq!(out.len(), closed, "{output:?}, frame {k}");
                }
                tier.finish(&mut out).unwrap();
                assert_eq!(out.len(), frames.len() - 1);
                out.iter()
                    .map(|b| match b {
                        Stage1Batch::Events { events, end } => format!("{end} {events:?}"),
                        Stage1Batch::Voxels(grid, interval) => format!("{interval:?} {grid:?}"),
                    })
                    .collect()
            };
            let (plain, ahead) = (run(false), run(true));
            assert!(plain.iter().map(String::len).sum::<usize>() > 10_000);
            assert_eq!(plain, ahead, "{output:?}");
        }
    }

    /// A live tier that may hold a frame back within 50 ms holds it while frames come 33 ms
    /// apart (each batch with the next frame) and hands it on at once once they come 200 ms
    /// apart; every interval's batch comes, in order, the last one held at `finish`.
    #[test]
    fn a_live_tier_holds_a_frame_only_within_its_budget() {
        use crate::stage1::{Stage1Batch, Stage1Config};
        let mut frames = frames();
        let mut t = 0;
        for (k, f) in frames.iter_mut().enumerate() {
            t += if k < 8 { 33_333 } else { 200_000 };
            f.t = t;
        }
        let mut tier =
            crate::stage1::build(&Stage1Config::default(), 10, (120, 72), Default::default())
                .unwrap();
        tier.pace(1.0);
        tier.look_ahead_within(std::time::Duration::from_millis(50));
        let mut out = Vec::new();
        for (k, f) in frames.iter().enumerate() {
            tier.push(f, &mut out).unwrap();
            // Held while the frames are close: the interval of frame k - 1 comes with frame k;
            // from frame 8 on (200 ms after the last) each interval comes with its own frame.
            let closed = if k < 8 { k.saturating_sub(1) } else { k };
            assert_eq!(out.len(), closed, "frame {k}");
        }
        tier.finish(&mut out).unwrap();
        let ends: Vec<i64> = out.iter().map(Stage1Batch::end).collect();
        let want: Vec<i64> = frames[1..].iter().map(|f| f.t).collect();
        assert_eq!(ends, want);
        let events: usize = out
            .iter()
            .map(|b| match b {
                Stage1Batch::Events { events, .. } => events.len(),
                Stage1Batch::Voxels(..) => 0,
            })
            .sum();
        assert!(events > 1_000, "{events} events");
    }
}
