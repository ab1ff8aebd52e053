//! The pixel model's parameters: one struct, its defaults (the sensor presets) and its one check.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::flow::{FlowBackend, FlowPreset};
use crate::frame::FULL_SCALE;
use crate::stage1::motion::Motion;

/// The highest noise rate per pixel a config may set, Hz (10 kHz: a DVS pixel's refractory
/// period allows at most a few kHz).
pub const MAX_NOISE_HZ: f64 = 10_000.0;

/// Parameters of the pixel model (see the module docs). Every one is a config key.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PhysicsConfig {
    /// Mean ON threshold, in log (natural) units of intensity.
    pub threshold_on: f64,
    /// Mean OFF threshold, in log units.
    pub threshold_off: f64,
    /// Standard deviation of the per-pixel thresholds (mismatch), in log units.
    pub threshold_sigma: f64,
    /// Standard deviation of each event's threshold around its pixel's own, in log units:
    /// temporal noise of the comparator and of the reset, drawn anew for a polarity each time
    /// the pixel fires it (0: every event at the pixel's own threshold).
    pub threshold_noise: f64,
    /// Refractory period after an event, us.
    pub refractory_us: f64,
    /// Photoreceptor cutoff at full-scale light, Hz (0: instant).
    pub cutoff_hz: f64,
    /// Dark current, as a fraction of full-scale luminance.
    pub dark_current: f64,
    /// Below this luminance (fraction of full scale) the log response is linearised.
    pub linlog_knee: f64,
    /// Leak (ON) events per pixel per second.
    pub leak_hz: f64,
    /// Shot-noise events per pixel per second in the dark.
    pub shot_noise_hz: f64,
    /// Fraction of pixels that are hot.
    pub hot_pixel_fraction: f64,
    /// Events per second of a hot pixel.
    pub hot_pixel_hz: f64,
    /// Most sub-steps per pixel and frame interval.
    pub max_substeps: u32,
    /// Side of the activity-gating tiles, pixels.
    pub tile: u16,
    /// Scene-relative light (0: off, the parameters above are fractions of the frame's full
    /// scale). Otherwise the mean luminance (fraction of full scale) of the scene the light
    /// parameters were calibrated on: a scene whose first frame is `g` times brighter or darker
    /// on average has its dark current, lin-log knee, photoreceptor bandwidth curve and
    /// shot-noise half-light scaled by `g`, so only its contrast matters, as for a log pixel
    /// above its bandwidth limit (the illumination ladder, docs/results.md).
    pub scene_level: f64,
    /// Where the scene's light comes from (see [`LightModel`]).
    pub light: LightModel,
    /// The exposure (us) at which the light parameters above are fractions of full scale:
    /// the calibration recording's APS exposure. Used by `light = "exposure"`.
    pub exposure_us: f64,
    /// Frequency of the light's flicker, Hz (0: steady light). Lamps on the mains flicker at
    /// twice its frequency: 100 Hz on 50 Hz grids, 120 Hz on 60 Hz ones. Frames at 25-60 Hz
    /// cannot show it (it aliases or averages out over the exposure), a DVS records every
    /// cycle; `v2ce calibrate` finds it in a recording's events.
    pub flicker_hz: f64,
    /// Depth of the flicker: the light is `I (1 + depth sin(2 pi flicker_hz t))`, 0 to 0.99.
    pub flicker_depth: f64,
    /// How the light moves between frames: `linear` interpolation per pixel, or sub-frames
    /// warped along the optical `flow` (see [`super::motion`]).
    pub motion: Motion,
    /// Under `motion = "flow"`: the most a pixel may move per sub-frame, pixels.
    pub max_step_px: f64,
    /// Under `motion = "flow"`: the most intervals a frame interval is cut into (1: linear).
    pub max_subframes: u32,
    /// Under `motion = "flow"`: the optical flow's speed/quality preset.
    pub flow_preset: FlowPreset,
    /// Under `motion = "flow"`: which optical flow computes it: the project's own DIS
    /// (`dis`), or OpenCV's (`opencv`, for comparison, in a build with the `opencv-flow`
    /// feature).
    pub flow_backend: FlowBackend,
}

/// How the pixel model learns how bright a scene is. A frame's values say only how bright it
/// is relative to its own full scale; the photocurrent behind them, which sets the dark
/// current's share, the knee and the photoreceptor's bandwidth, also depends on the exposure
/// and the lens, which most sources do not report. In every model, frames that carry their
/// exposure (APS frames) are read as light per unit of exposure, so an exposure change
/// between frames (auto-exposure) is not a change of light and makes no events.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum LightModel {
    /// The scene's mean is the calibration scene's light (`scene_level`): only contrast
    /// matters, the same motion gives the same events at any brightness. The default, for
    /// videos and image folders whose exposure and lens are unknown.
    #[default]
    Scene,
    /// Absolute light from each frame's exposure, against the calibration recording's
    /// (`exposure_us`): a frame with a mean of `m` at exposure `E` has `m * exposure_us / E`
    /// of the calibration scene's light, so a dim scene's photoreceptors are slower and its
    /// noise relatively higher. Frames without an exposure fall back to `scene`.
    Exposure,
    /// The light parameters are fractions of the frame's full scale (no scaling).
    Frame,
}

impl Default for PhysicsConfig {
    fn default() -> Self {
        Preset::Davis346.config()
    }
}

/// Sensor presets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    /// A DAVIS346 in daylight (calibrated on the davis346 recording; see docs/physics.md).
    #[default]
    Davis346,
    /// A DVXplorer: lower thresholds, no APS, faster front end.
    Dvxplorer,
    /// A noiseless ideal sensor: instant pixels, equal thresholds, no mismatch, no noise.
    Ideal,
}

impl Preset {
    /// All presets.
    pub const ALL: [Preset; 3] = [Preset::Davis346, Preset::Dvxplorer, Preset::Ideal];

    /// The preset's name.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Davis346 => "davis346",
            Preset::Dvxplorer => "dvxplorer",
            Preset::Ideal => "ideal",
        }
    }

    /// Parses a preset name.
    pub fn from_name(name: &str) -> Result<Self> {
        Preset::ALL
            .into_iter()
            .find(|p| p.name() == name)
            .ok_or_else(|| {
                Error::invalid(
                    "preset",
                    format!("'{name}' (expected davis346, dvxplorer or ideal)"),
                )
            })
    }

    /// The preset's parameters.
    pub fn config(self) -> PhysicsConfig {
        match self {
            Preset::Davis346 => PhysicsConfig {
                // Fitted by `v2ce calibrate --motion flow` on the davis346 clip (docs/physics.md).
                threshold_on: 0.26,
                threshold_off: 0.305,
                threshold_sigma: 0.03,
                threshold_noise: 0.06,
                // `v2ce calibrate` on the clip's refractory floor (docs/physics.md).
                refractory_us: 1000.0,
                cutoff_hz: 200.0,
                dark_current: 0.02,
                linlog_knee: 0.08,
                // Fitted by `v2ce calibrate` to the clip's static pixels (0.0011; shot noise
                // 0: the real floor there is 96% ON, as leak fires): docs/physics.md.
                leak_hz: 0.001,
                shot_noise_hz: 0.0,
                hot_pixel_fraction: 0.0001,
                hot_pixel_hz: 2.0,
                max_substeps: 32,
                tile: 16,
                // The davis346 clip's first APS frame: mean linear luminance 0.303 of full
                // scale at a 500 us exposure, where the light parameters above were calibrated.
                scene_level: 0.303,
                light: LightModel::Scene,
                exposure_us: 500.0,
                flicker_hz: 0.0,
                flicker_depth: 0.0,
                motion: Motion::Flow,
                max_step_px: 1.0,
                max_subframes: 8,
                flow_preset: FlowPreset::Fast,
                flow_backend: FlowBackend::Dis,
            },
            Preset::Dvxplorer => PhysicsConfig {
                threshold_on: 0.25,
                threshold_off: 0.25,
                threshold_sigma: 0.03,
                threshold_noise: 0.06,
                refractory_us: 50.0,
                cutoff_hz: 500.0,
                dark_current: 0.01,
                linlog_knee: 0.05,
                leak_hz: 0.05,
                shot_noise_hz: 0.02,
                // Noise of hot pixels, sub-steps, tiles, light and motion: as the DAVIS346.
                ..Preset::Davis346.config()
            },
            Preset::Ideal => PhysicsConfig {
                threshold_on: 0.2,
                threshold_off: 0.2,
                threshold_sigma: 0.0,
                threshold_noise: 0.0,
                refractory_us: 0.0,
                cutoff_hz: 0.0,
                dark_current: 0.0,
                linlog_knee: 1.0 / FULL_SCALE as f64,
                leak_hz: 0.0,
                shot_noise_hz: 0.0,
                hot_pixel_fraction: 0.0,
                hot_pixel_hz: 0.0,
                max_substeps: 64,
                tile: 16,
                scene_level: 0.0,
                light: LightModel::Frame,
                exposure_us: 0.0,
                flicker_hz: 0.0,
                flicker_depth: 0.0,
                motion: Motion::Flow,
                max_step_px: 1.0,
                max_subframes: 8,
                flow_preset: FlowPreset::Fast,
                flow_backend: FlowBackend::Dis,
            },
        }
    }
}

impl PhysicsConfig {
    /// The same sensor without noise: no leak, shot noise, hot pixels or threshold noise.
    pub fn noiseless(&self) -> Self {
        PhysicsConfig {
            threshold_noise: 0.0,
            leak_hz: 0.0,
            shot_noise_hz: 0.0,
            hot_pixel_fraction: 0.0,
            ..self.clone()
        }
    }

    /// Checks that every parameter is usable.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::invalid("stage1.physics", m));
        let finite_nonneg = [
            ("threshold_sigma", self.threshold_sigma),
            ("refractory_us", self.refractory_us),
            ("cutoff_hz", self.cutoff_hz),
            ("dark_current", self.dark_current),
            ("leak_hz", self.leak_hz),
            ("shot_noise_hz", self.shot_noise_hz),
            ("hot_pixel_hz", self.hot_pixel_hz),
        ];
        for (name, v) in finite_nonneg {
            if !(v.is_finite() && v >= 0.0) {
                return bad(format!("{name} = {v} must be a finite number >= 0"));
            }
        }
        for (name, v) in [
            ("leak_hz", self.leak_hz),
            ("shot_noise_hz", self.shot_noise_hz),
            ("hot_pixel_hz", self.hot_pixel_hz),
        ] {
            if v > MAX_NOISE_HZ {
                return bad(format!("{name} = {v} is above {MAX_NOISE_HZ} Hz per pixel"));
            }
        }
        for (name, v) in [
            ("threshold_on", self.threshold_on),
            ("threshold_off", self.threshold_off),
        ] {
            if !(v.is_finite() && (0.01..=5.0).contains(&v)) {
                return bad(format!("{name} = {v} must be in [0.01, 5] log units"));
            }
        }
        if !(self.scene_level.is_finite() && (0.0..=1.0).contains(&self.scene_level)) {
            return bad(format!(
                "scene_level = {} must be in [0, 1] (0: off)",
                self.scene_level
            ));
        }
        if !(self.exposure_us.is_finite() && (0.0..=1e8).contains(&self.exposure_us)) {
            return bad(format!(
                "exposure_us = {} must be in [0, 1e8] us",
                self.exposure_us
            ));
        }
        if !(self.flicker_hz.is_finite() && (0.0..=10_000.0).contains(&self.flicker_hz)) {
            return bad(format!(
                "flicker_hz = {} must be in [0, 10000] Hz (0: steady light)",
                self.flicker_hz
            ));
        }
        if !(self.flicker_depth.is_finite() && (0.0..=0.99).contains(&self.flicker_depth)) {
            return bad(format!(
                "flicker_depth = {} must be in [0, 0.99]",
                self.flicker_depth
            ));
        }
        if self.light == LightModel::Exposure && self.exposure_us <= 0.0 {
            return bad(
                "light = \"exposure\" needs exposure_us, the calibration recording's exposure"
                    .into(),
            );
        }
        if !(self.linlog_knee > 0.0 && self.linlog_knee <= 1.0) {
            return bad(format!(
                "linlog_knee = {} must be in (0, 1]",
                self.linlog_knee
            ));
        }
        if !(self.threshold_noise.is_finite() && (0.0..=1.0).contains(&self.threshold_noise)) {
            return bad(format!(
                "threshold_noise = {} must be in [0, 1] log units",
                self.threshold_noise
            ));
        }
        if !(0.0..=1.0).contains(&self.hot_pixel_fraction) {
            return bad(format!(
                "hot_pixel_fraction = {} must be in [0, 1]",
                self.hot_pixel_fraction
            ));
        }
        if !(self.max_step_px.is_finite() && (0.1..=100.0).contains(&self.max_step_px)) {
            return bad(format!(
                "max_step_px = {} must be in [0.1, 100] pixels",
                self.max_step_px
            ));
        }
        if !(1..=64).contains(&self.max_subframes) {
            return bad(format!(
                "max_subframes = {} must be 1..=64 (1: linear interpolation)",
                self.max_subframes
            ));
        }
        if self.max_substeps == 0 || self.max_substeps > 4096 || !(1..=64).contains(&self.tile) {
            return bad("max_substeps must be 1..=4096 and tile 1..=64".into());
        }
        Ok(())
    }
}
