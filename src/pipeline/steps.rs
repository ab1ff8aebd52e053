//! The per-frame work of Stage 1 and Stage 2, as steps a stage thread calls in a loop. Offline
//! conversion and the live daemon run the very same steps, so both give the same events for the
//! same frames and seed.

use crate::config::Config;
use crate::error::Result;
use crate::event::Event;
use crate::frame::Frame;
use crate::interval::Interval;
use crate::stage1::{PhysicsSim, PhysicsStats, Stage1Output};
use crate::stage2::Sampler;
use crate::voxel::{VoxelGrid, Voxelizer};

/// What Stage 1 hands to Stage 2 for one frame.
#[derive(Debug)]
pub enum Stage1Batch {
    /// Events of the interval ending at this frame, in time order.
    Events(Vec<Event>),
    /// The interval's events as a voxel grid, for the Stage 2 sampler to re-time.
    Voxels(VoxelGrid, Interval),
}

impl Stage1Batch {
    /// Events in the batch (for voxels: the grid's active cells).
    pub fn weight(&self) -> u64 {
        match self {
            Stage1Batch::Events(e) => e.len() as u64,
            Stage1Batch::Voxels(g, _) => g.active_cells() as u64,
        }
    }
}

/// Stage 1: the pixel model, and in voxel mode the voxelizer.
pub struct Stage1Step {
    config: Config,
    size: (u16, u16),
    sim: PhysicsSim,
    voxelizer: Option<Voxelizer>,
    previous: Option<i64>,
    scratch: Vec<Event>,
    // Counters of the simulations before the last restart.
    earlier: PhysicsStats,
}

impl Stage1Step {
    /// Stage 1 for `width x height` frames.
    pub fn new(config: &Config, width: u16, height: u16) -> Result<Self> {
        let voxelizer = match config.stage1.output {
            Stage1Output::Voxels => Some(Voxelizer::new(width, height, config.stage2.bins)?),
            Stage1Output::Events => None,
        };
        Ok(Stage1Step {
            sim: PhysicsSim::new(
                config.stage1.physics_config(),
                width,
                height,
                config.stage1.seed,
            )?,
            config: config.clone(),
            size: (width, height),
            voxelizer,
            previous: None,
            scratch: Vec::new(),
            earlier: PhysicsStats::default(),
        })
    }

    /// Starts over after a break in the frames (a camera that came back): the next frame only
    /// initialises the pixels, as the first one did. The sensor's fixed pattern (threshold
    /// mismatch, hot pixels) stays the same, since it comes from the same seed.
    pub fn restart(&mut self) -> Result<()> {
        let mut earlier = self.stats();
        *self = Stage1Step::new(&self.config, self.size.0, self.size.1)?;
        std::mem::swap(&mut self.earlier, &mut earlier);
        Ok(())
    }

    /// Events of the interval that ends at `frame` (none for the first frame).
    pub fn process(&mut self, frame: &Frame) -> Result<Stage1Batch> {
        let previous = self.previous.replace(frame.t);
        match (&mut self.voxelizer, previous) {
            (Some(voxelizer), Some(t0)) => {
                self.scratch.clear();
                self.sim.step(frame, &mut self.scratch)?;
                // Events of (t0, t1] voxelized on [t0, t1): one at t1 lands on the last node.
                let interval = Interval::new(t0, frame.t)?;
                let mut grid = VoxelGrid::new(self.size.0, self.size.1, self.config.stage2.bins)?;
                voxelizer.voxelize_into(&self.scratch, interval, &mut grid)?;
                Ok(Stage1Batch::Voxels(grid, interval))
            }
            _ => {
                let mut events = Vec::new();
                self.sim.step(frame, &mut events)?;
                Ok(Stage1Batch::Events(events))
            }
        }
    }

    /// The pixel model's counters.
    pub fn stats(&self) -> PhysicsStats {
        let mut s = self.earlier;
        s.add(self.sim.stats());
        s
    }
}

/// Stage 2: re-times voxels into events (events from Stage 1 pass through).
pub struct Stage2Step {
    sampler: Box<dyn Sampler>,
}

impl Stage2Step {
    /// Stage 2 with the configured sampler and seed.
    pub fn new(config: &Config) -> Self {
        Stage2Step {
            sampler: config.stage2.sampler.build(config.stage2.seed),
        }
    }

    /// The batch's events in time order.
    pub fn process(&self, batch: Stage1Batch) -> Vec<Event> {
        match batch {
            Stage1Batch::Events(events) => events,
            Stage1Batch::Voxels(grid, interval) => {
                let mut out = Vec::new();
                self.sampler.sample(&grid, interval, &mut out);
                out
            }
        }
    }
}
