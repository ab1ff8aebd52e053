//! Stage 1: frames to events (or to voxels, for Stage 2 to sample).
//!
//! The fast tier is [`physics`], a physical model of the DVS pixel. Its parameters come from a
//! sensor [`Preset`] with any of them overridden in the `[stage1.physics]` config table.

pub mod physics;

use serde::Deserialize;

pub use physics::{PhysicsConfig, PhysicsSim, PhysicsStats, Preset};

/// How Stage 1's output reaches the event stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Stage1Output {
    /// The model's events, with their interpolated crossing times (the most accurate).
    #[default]
    Events,
    /// The model's events voxelized per frame interval and re-timed by the Stage 2 sampler (the
    /// V2CE pipeline's shape: what a learned Stage 1 would hand over).
    Voxels,
}

/// Overrides of single physics parameters (each optional; see [`PhysicsConfig`]).
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(missing_docs)]
pub struct PhysicsOverrides {
    pub threshold_on: Option<f64>,
    pub threshold_off: Option<f64>,
    pub threshold_sigma: Option<f64>,
    pub refractory_us: Option<f64>,
    pub cutoff_hz: Option<f64>,
    pub dark_current: Option<f64>,
    pub linlog_knee: Option<f64>,
    pub leak_hz: Option<f64>,
    pub shot_noise_hz: Option<f64>,
    pub hot_pixel_fraction: Option<f64>,
    pub hot_pixel_hz: Option<f64>,
    pub max_substeps: Option<u32>,
    pub tile: Option<u16>,
}

impl PhysicsOverrides {
    /// `base` with the overridden parameters replaced.
    pub fn apply(&self, mut base: PhysicsConfig) -> PhysicsConfig {
        macro_rules! set {
            ($($f:ident),*) => { $( if let Some(v) = self.$f { base.$f = v; } )* };
        }
        set!(
            threshold_on,
            threshold_off,
            threshold_sigma,
            refractory_us,
            cutoff_hz,
            dark_current,
            linlog_knee,
            leak_hz,
            shot_noise_hz,
            hot_pixel_fraction,
            hot_pixel_hz,
            max_substeps,
            tile
        );
        base
    }
}

/// Stage 1 settings.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Stage1Config {
    /// Sensor preset.
    pub preset: Preset,
    /// Events directly, or voxels through Stage 2.
    pub output: Stage1Output,
    /// Seed of mismatch, hot pixels and noise.
    pub seed: u64,
    /// Single-parameter overrides of the preset.
    pub physics: PhysicsOverrides,
}

impl Stage1Config {
    /// The physics parameters: the preset with the overrides applied.
    pub fn physics_config(&self) -> PhysicsConfig {
        self.physics.apply(self.preset.config())
    }
}
