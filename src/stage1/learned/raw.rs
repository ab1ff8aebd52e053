//! The raw-tensor entry point (`v2ce model run`): a normalised input tensor in, the network's
//! raw output out, both `.npy`, for checking a model in isolation.

use std::path::Path;
use std::time::Instant;

use ndarray::{ArrayD, IxDyn};

use crate::error::{Error, Result};

use super::runtime::{Network, RuntimeOptions};

/// What [`run_npy`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct RawReport {
    /// Output shape `(B, L, 2*C, H, W)`.
    pub shape: Vec<usize>,
    /// Inference time, s.
    pub seconds: f64,
    /// Execution provider.
    pub provider: &'static str,
    /// Largest finite output value.
    pub max: f32,
    /// NaN or infinite output values (written as they are).
    pub nonfinite: u64,
}

/// Runs `model` on the float32 `(B, L, 2, H, W)` tensor in `input` and writes its output to
/// `output` (through a temporary file renamed at the end, so a failed run leaves none).
pub fn run_npy(
    model: &Path,
    input: &Path,
    output: &Path,
    options: &RuntimeOptions,
) -> Result<RawReport> {
    let array: ArrayD<f32> = ndarray_npy::read_npy(input).map_err(|e| {
        Error::format(
            input,
            format!("not a float32 .npy tensor: {e} (write it with numpy: arr.astype(np.float32))"),
        )
    })?;
    let shape: [usize; 5] = array.shape().try_into().map_err(|_| {
        Error::format(
            input,
            format!(
                "shape {:?}; the network takes (B, L, 2, H, W)",
                array.shape()
            ),
        )
    })?;
    if shape[2] != 2 || shape.contains(&0) {
        return Err(Error::format(
            input,
            format!("shape {shape:?}; the network takes (B, L, 2, H, W) with 2 frames per pair"),
        ));
    }
    let data = array.as_standard_layout();
    let values = data
        .as_slice()
        .ok_or_else(|| Error::format(input, "tensor is not contiguous"))?;
    let mut network = Network::open(model, options)?;
    let started = Instant::now();
    let (out_shape, out) = network.run(values, shape)?;
    let seconds = started.elapsed().as_secs_f64();
    let nonfinite = out.iter().filter(|v| !v.is_finite()).count() as u64;
    let max = out
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(f32::NEG_INFINITY, f32::max);
    let result = ArrayD::from_shape_vec(IxDyn(&out_shape), out)
        .map_err(|e| Error::invalid("network output", e.to_string()))?;
    let tmp = output.with_extension("npy.partial");
    ndarray_npy::write_npy(&tmp, &result).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        Error::io(output, std::io::Error::other(e.to_string()))
    })?;
    std::fs::rename(&tmp, output).map_err(|e| Error::io(output, e))?;
    Ok(RawReport {
        shape: out_shape,
        seconds,
        provider: network.provider(),
        max,
        nonfinite,
    })
}
