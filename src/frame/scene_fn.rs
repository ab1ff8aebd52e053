//! Frames of a scene function, for tests and benchmarks: any function of time and pixel
//! ([`SceneFn`]), sampled at a fixed rate.

use super::{Frame, FrameSource};
use crate::error::Result;

/// A scene: linear luminance in `[0, 1]` at time `t` (us) and pixel centre `(x, y)`.
pub type SceneFn = Box<dyn Fn(i64, u16, u16) -> f64 + Send>;

/// Frames of a [`SceneFn`] at `fps`, `frames` of them from time 0.
pub struct SceneSource {
    name: String,
    size: (u16, u16),
    fps: f64,
    frames: usize,
    next: usize,
    scene: SceneFn,
    exposure_us: Option<u32>,
}

impl SceneSource {
    /// A scene source.
    pub fn new(
        name: &str,
        width: u16,
        height: u16,
        fps: f64,
        frames: usize,
        scene: SceneFn,
    ) -> Self {
        SceneSource {
            name: name.to_string(),
            size: (width, height),
            fps,
            frames,
            next: 0,
            scene,
            exposure_us: None,
        }
    }

    /// The same scene with every frame reporting an exposure of `us` (an APS-like source; the
    /// scene function is then the light integrated over it, as a fraction of full scale).
    pub fn with_exposure(mut self, us: u32) -> Self {
        self.exposure_us = Some(us);
        self
    }

    /// Time of frame `i` in us.
    pub fn frame_time(fps: f64, i: usize) -> i64 {
        (i as f64 * 1e6 / fps).round() as i64
    }

    /// A vertical edge, bright (`high`) on its left and dark (`low`) on its right, moving right
    /// at `speed` pixels per second from column `x0`. Pixels see the area-weighted mix, so the
    /// luminance of column `x` ramps linearly while the edge crosses `[x, x + 1)`.
    pub fn moving_edge(
        width: u16,
        height: u16,
        fps: f64,
        frames: usize,
        x0: f64,
        speed: f64,
        (low, high): (f64, f64),
    ) -> Self {
        let scene = move |t: i64, x: u16, _y: u16| {
            let edge = x0 + speed * t as f64 * 1e-6;
            let covered = (edge - x as f64).clamp(0.0, 1.0);
            low + (high - low) * covered
        };
        SceneSource::new("moving edge", width, height, fps, frames, Box::new(scene))
    }

    /// The illumination ladder's scene at `light` times its mid-light level: a texture (a sum
    /// of gratings, contrast about 3:1) drifting right at 60 px/s, crossed by a dark bar moving
    /// down at 40 px/s, at 30 fps. At `light = 1` the luminance spans about 2% to 6% of full
    /// scale, so 16x brighter still fits below saturation; the scene's log contrast, and so
    /// an ideal log sensor's events, are the same at every level.
    pub fn ladder(width: u16, height: u16, frames: usize, light: f64) -> Self {
        let scene = move |t: i64, x: u16, y: u16| {
            let s = t as f64 * 1e-6;
            let (u, v) = (x as f64 - 60.0 * s, y as f64);
            let tau = std::f64::consts::TAU;
            let texture = 0.5
                + 0.22 * (tau * u / 17.0).sin()
                + 0.15 * (tau * (u / 7.0 + v / 11.0)).sin()
                + 0.1 * (tau * v / 23.0).cos();
            let bar = ((v - 40.0 * s).rem_euclid(height as f64) < 6.0) as u8 as f64;
            let level = 0.02 + 0.04 * texture.clamp(0.0, 1.0);
            light * level * (1.0 - 0.7 * bar)
        };
        SceneSource::new(
            &format!("illumination ladder x{light}"),
            width,
            height,
            30.0,
            frames,
            Box::new(scene),
        )
    }

    /// A still scene: a fixed pattern of gray levels.
    pub fn still(width: u16, height: u16, fps: f64, frames: usize) -> Self {
        let scene = |_t: i64, x: u16, y: u16| 0.1 + 0.8 * (((x / 8 + y / 8) % 5) as f64 / 4.0);
        SceneSource::new("still pattern", width, height, fps, frames, Box::new(scene))
    }
}

impl FrameSource for SceneSource {
    fn size(&self) -> (u16, u16) {
        self.size
    }

    fn next_frame(&mut self) -> Result<Option<Frame>> {
        if self.next >= self.frames {
            return Ok(None);
        }
        let t = Self::frame_time(self.fps, self.next);
        self.next += 1;
        let (w, h) = self.size;
        let mut luma = Vec::with_capacity(w as usize * h as usize);
        for y in 0..h {
            for x in 0..w {
                let v = (self.scene)(t, x, y);
                let v = if v.is_finite() {
                    v.clamp(0.0, 1.0)
                } else {
                    0.0
                };
                luma.push((v * 65535.0).round() as u16);
            }
        }
        Ok(Some(Frame {
            t,
            width: w,
            height: h,
            luma,
            exposure_us: self.exposure_us,
        }))
    }

    fn describe(&self) -> String {
        format!(
            "synthetic {} ({} x {}, {} fps)",
            self.name, self.size.0, self.size.1, self.fps
        )
    }

    fn frames_hint(&self) -> Option<u64> {
        Some(self.frames as u64)
    }

    fn encoding(&self) -> super::SourceEncoding {
        super::SourceEncoding::Linear
    }
}
