//! v2ce: video to continuous events.
//!
//! A library and the `v2ce` command-line tool that turn ordinary video into the event stream a
//! Dynamic Vision Sensor would have produced, following the V2CE method: Stage 1 predicts event
//! voxels from frames, Stage 2 recovers continuous timestamps from the voxels.

#![warn(missing_docs)]
// Functions stay under 150 lines (clippy.toml): a longer one holds several steps to name.
#![warn(clippy::too_many_lines)]

pub(crate) mod batch;
pub mod calibrate;
pub mod capture;
pub mod cli;
pub mod config;
pub mod convert;
pub(crate) mod daemon;
pub(crate) mod dataset;
pub mod error;
pub mod eval;
pub mod event;
pub mod file_id;
pub mod flow;
pub mod format;
pub mod frame;
pub(crate) mod http;
pub mod interval;
pub mod limits;
pub(crate) mod listen;
pub mod metrics;
pub mod model;
pub mod output;
pub(crate) mod parallel;
pub(crate) mod pipeline;
pub(crate) mod plot;
pub(crate) mod process;
pub(crate) mod realtime;
pub mod reconstruct;
pub mod render;
pub mod repair;
pub mod ros2;
pub(crate) mod rounding;
pub mod seed;
pub mod simd;
pub mod sink;
pub(crate) mod source;
pub mod stage1;
pub mod stage2;
pub(crate) mod stats;
pub mod sweeping_bar;
pub mod time;
pub(crate) mod toml_doc;
pub(crate) mod tradeoff;
pub(crate) mod transcode;
pub mod voxel;

pub use error::{Error, Result};
pub use event::{Event, EventPacket};
pub use interval::Interval;
pub use stage2::{Sampler, SamplerKind};
pub use voxel::{voxelize, VoxelGrid, Voxelizer};
