//! OpenCV's DIS through the `opencv` crate, built against the system's OpenCV (Debian's
//! `libopencv-dev`, and clang for the binding generator): the `opencv-flow` cargo feature, off
//! by default. Kept to compare the project's own DIS against (`flow_backend = "opencv"`, the
//! flow bench and the tests that hold the two side by side); it computes the whole frame.

use crate::error::{Error, Result};

use super::FlowPreset;

/// OpenCV's estimator with a preset's settings (behind a lock, so that the motion model that
/// holds it can be shared between the threads that blend its sub-frames).
pub struct OpencvFlow {
    dis: std::sync::Mutex<opencv::core::Ptr<opencv::video::DISOpticalFlow>>,
}

impl OpencvFlow {
    /// OpenCV's DIS: `ULTRAFAST` for `ultrafast`; `ULTRAFAST` searched down to half the
    /// resolution for `fast`; `MEDIUM` for `medium`.
    pub fn new(preset: FlowPreset) -> Result<Self> {
        use opencv::prelude::*;
        use opencv::video;
        let code = match preset {
            FlowPreset::Ultrafast | FlowPreset::Fast => video::DISOpticalFlow_PRESET_ULTRAFAST,
            FlowPreset::Medium => video::DISOpticalFlow_PRESET_MEDIUM,
        };
        let mut dis = video::DISOpticalFlow::create(code).map_err(cv)?;
        if preset == FlowPreset::Fast {
            dis.set_finest_scale(1).map_err(cv)?;
        }
        Ok(OpencvFlow {
            dis: std::sync::Mutex::new(dis),
        })
    }

    /// The flow from `from` to `to` (`width x height` gray each) into `out`.
    pub fn compute(
        &mut self,
        from: &[u8],
        to: &[u8],
        width: usize,
        height: usize,
        out: &mut Vec<[f32; 2]>,
    ) -> Result<()> {
        use opencv::core::{Mat, Vec2f};
        use opencv::prelude::*;
        out.clear();
        out.resize(width * height, [0.0; 2]);
        let (rows, cols) = (height as i32, width as i32);
        let a = Mat::new_rows_cols_with_data(rows, cols, from).map_err(cv)?;
        let b = Mat::new_rows_cols_with_data(rows, cols, to).map_err(cv)?;
        // `[f32; 2]` and `Vec2f` have one layout: two f32 in a row.
        let cells: &mut [Vec2f] = vec2f(out);
        let mut flow = Mat::new_rows_cols_with_data_mut(rows, cols, cells).map_err(cv)?;
        let dis = self
            .dis
            .get_mut()
            .map_err(|_| Error::Run("optical flow (OpenCV): a thread failed with it".into()))?;
        dis.calc(&a, &b, &mut flow).map_err(cv)?;
        Ok(())
    }
}

fn vec2f(v: &mut [[f32; 2]]) -> &mut [opencv::core::Vec2f] {
    // SAFETY: `Vec2f` is `VecN<f32, 2>`, a `#[repr(C)]` wrapper of `[f32; 2]`: same size,
    // alignment and layout, and every bit pattern is valid for both.
    unsafe { std::slice::from_raw_parts_mut(v.as_mut_ptr().cast(), v.len()) }
}

fn cv(e: opencv::Error) -> Error {
    Error::Run(format!("optical flow (OpenCV): {e}"))
}
