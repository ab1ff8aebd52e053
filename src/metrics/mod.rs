//! Metrics that score simulated events against real recordings (V2CE_SPEC.md section 6).

pub mod realism;
pub mod realism_plot;
pub mod stage1;
pub mod stage2;

pub use stage1::Stage1Metrics;
pub use stage2::{IntervalScore, IntervalScratch, Stage2Metrics, Stage2Scorer};
