//! Dense optical flow between two gray frames: OpenCV's DIS (Kroeger et al., "Fast Optical
//! Flow using Dense Inverse Search", ECCV 2016) through the `opencv` crate, built against the
//! system's OpenCV (Debian's `libopencv-dev`) with the `flow` feature (on by default).
//!
//! The flow of a pixel `p` of the first frame says where it went in the second: the content at
//! `p` in `from` is at `p + flow(p)` in `to`, in pixels.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// The flow's speed/quality presets, each about twice the cost of the one before it
/// (docs/physics.md has the numbers measured here).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum FlowPreset {
    /// OpenCV's `ULTRAFAST`: 8 px patches searched down to a quarter of the resolution, no
    /// variational refinement.
    Ultrafast,
    /// The same patches down to half the resolution. On the davis346 clip it gives the best
    /// events of the three (OpenCV's own `FAST`, whose variational refinement smooths the
    /// flow of small moving things away, gave fewer sub-frames and worse events than either).
    #[default]
    Fast,
    /// OpenCV's `MEDIUM`: 12 px patches down to half the resolution, variational refinement.
    Medium,
}

impl FlowPreset {
    /// The name as configs and flags spell it.
    pub fn name(self) -> &'static str {
        match self {
            FlowPreset::Ultrafast => "ultrafast",
            FlowPreset::Fast => "fast",
            FlowPreset::Medium => "medium",
        }
    }
}

/// One flow estimator, kept across frames (it holds its buffers).
pub struct DenseFlow {
    width: usize,
    height: usize,
    #[cfg(feature = "flow")]
    dis: opencv::core::Ptr<opencv::video::DISOpticalFlow>,
}

impl DenseFlow {
    /// An estimator for `width x height` frames. Fails when this build has no OpenCV (the
    /// `flow` feature off) or OpenCV cannot make one.
    pub fn new(preset: FlowPreset, width: u16, height: u16) -> Result<Self> {
        #[cfg(feature = "flow")]
        {
            use opencv::video;
            let code = match preset {
                FlowPreset::Ultrafast | FlowPreset::Fast => video::DISOpticalFlow_PRESET_ULTRAFAST,
                FlowPreset::Medium => video::DISOpticalFlow_PRESET_MEDIUM,
            };
            let mut dis = video::DISOpticalFlow::create(code).map_err(cv)?;
            if preset == FlowPreset::Fast {
                use opencv::prelude::*;
                dis.set_finest_scale(1).map_err(cv)?;
            }
            Ok(DenseFlow {
                width: width.into(),
                height: height.into(),
                dis,
            })
        }
        #[cfg(not(feature = "flow"))]
        {
            let _ = (preset, width, height);
            Err(Error::invalid(
                "motion",
                "\"flow\" needs optical flow, and this build has none (built without the \
                 `flow` feature, which links OpenCV); use motion = \"linear\"",
            ))
        }
    }

    /// The flow from `from` to `to` (row-major gray, `width x height` each) into `out`, one
    /// `[dx, dy]` per pixel of `from`. Values are finite: OpenCV's rare non-finite ones (none
    /// seen) are set to zero.
    pub fn compute(&mut self, from: &[u8], to: &[u8], out: &mut Vec<[f32; 2]>) -> Result<()> {
        let n = self.width * self.height;
        if from.len() != n || to.len() != n {
            return Err(Error::invalid(
                "flow",
                format!(
                    "frames of {} and {} values for {} x {}",
                    from.len(),
                    to.len(),
                    self.width,
                    self.height
                ),
            ));
        }
        out.clear();
        out.resize(n, [0.0; 2]);
        #[cfg(feature = "flow")]
        {
            use opencv::core::{Mat, Vec2f};
            use opencv::prelude::*;
            let (rows, cols) = (self.height as i32, self.width as i32);
            let a = Mat::new_rows_cols_with_data(rows, cols, from).map_err(cv)?;
            let b = Mat::new_rows_cols_with_data(rows, cols, to).map_err(cv)?;
            // `[f32; 2]` and `Vec2f` have one layout: two f32 in a row.
            let cells: &mut [Vec2f] = vec2f(out);
            let mut flow = Mat::new_rows_cols_with_data_mut(rows, cols, cells).map_err(cv)?;
            self.dis.calc(&a, &b, &mut flow).map_err(cv)?;
        }
        for v in out.iter_mut() {
            if !(v[0].is_finite() && v[1].is_finite()) {
                *v = [0.0; 2];
            }
        }
        Ok(())
    }
}

#[cfg(feature = "flow")]
fn vec2f(v: &mut [[f32; 2]]) -> &mut [opencv::core::Vec2f] {
    // SAFETY: `Vec2f` is `VecN<f32, 2>`, a `#[repr(C)]` wrapper of `[f32; 2]`: same size,
    // alignment and layout, and every bit pattern is valid for both.
    unsafe { std::slice::from_raw_parts_mut(v.as_mut_ptr().cast(), v.len()) }
}

#[cfg(feature = "flow")]
fn cv(e: opencv::Error) -> Error {
    Error::Run(format!("optical flow (OpenCV): {e}"))
}

#[cfg(all(test, feature = "flow"))]
mod tests {
    use super::*;

    /// A smooth texture shifted by a known amount comes back as that shift.
    #[test]
    fn a_shifted_texture_gives_its_shift() {
        let (w, h) = (96usize, 64usize);
        let tex = |x: f64, y: f64| {
            (128.0
                + 60.0 * (x * 0.31).sin() * (y * 0.23).cos()
                + 40.0 * (x * 0.11 + y * 0.17).sin()) as u8
        };
        let (dx, dy) = (8.0, -1.25);
        let a: Vec<u8> = (0..w * h)
            .map(|i| tex((i % w) as f64, (i / w) as f64))
            .collect();
        let b: Vec<u8> = (0..w * h)
            .map(|i| tex((i % w) as f64 - dx, (i / w) as f64 - dy))
            .collect();
        for preset in [FlowPreset::Ultrafast, FlowPreset::Fast, FlowPreset::Medium] {
            let mut flow = DenseFlow::new(preset, w as u16, h as u16).unwrap();
            let mut out = Vec::new();
            flow.compute(&a, &b, &mut out).unwrap();
            // The interior, away from the borders the shift uncovers.
            let mut err = Vec::new();
            for y in 8..h - 8 {
                for x in 8..w - 8 {
                    let f = out[y * w + x];
                    err.push(((f[0] as f64 - dx).powi(2) + (f[1] as f64 - dy).powi(2)).sqrt());
                }
            }
            err.sort_by(f64::total_cmp);
            let median = err[err.len() / 2];
            assert!(median < 0.25, "{preset:?}: median end-point error {median}");
        }
    }

    #[test]
    fn wrong_sizes_are_an_error() {
        let mut flow = DenseFlow::new(FlowPreset::Fast, 8, 8).unwrap();
        let mut out = Vec::new();
        assert!(flow.compute(&[0; 64], &[0; 63], &mut out).is_err());
    }
}
