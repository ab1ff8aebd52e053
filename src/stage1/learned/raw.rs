//! The raw-tensor entry point (`v2ce model run`): a normalised input tensor in, the network's
//! raw output out, both `.npy`, for checking a model in isolation.

use std::path::Path;
use std::time::Instant;

use ndarray::{ArrayD, IxDyn};

use crate::error::{Error, Result};

use super::runtime::Network;
use super::LearnedConfig;

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

/// The `(B, L, 2, H, W)` shape that `input`'s header claims, checked against the file's length
/// and the memory the tensor and the network's output (10 times larger) need, before anything
/// of that size is allocated.
fn checked_shape(input: &Path) -> Result<[usize; 5]> {
    let mut file = std::fs::File::open(input).map_err(|e| Error::io(input, e))?;
    let len = file.metadata().map_err(|e| Error::io(input, e))?.len();
    let header = crate::format::npz::parse_npy_header(&mut std::io::BufReader::new(&mut file))
        .map_err(|e| Error::format(input, e))?;
    if !header.dict.contains("'descr':'<f4'") {
        return Err(Error::format(
            input,
            format!(
                "not a float32 .npy tensor ({}; write it with numpy: arr.astype(np.float32))",
                header.dict
            ),
        ));
    }
    let shape: [u64; 5] = header.shape[..].try_into().map_err(|_| {
        Error::format(
            input,
            format!(
                "shape {:?}; the network takes (B, L, 2, H, W)",
                header.shape
            ),
        )
    })?;
    if shape[2] != 2 || shape.contains(&0) {
        return Err(Error::format(
            input,
            format!("shape {shape:?}; the network takes (B, L, 2, H, W) with 2 frames per pair"),
        ));
    }
    let bytes = header.elements().and_then(|n| n.checked_mul(4));
    let data = len.saturating_sub(header.data_offset);
    if bytes != Some(data) {
        return Err(Error::format(
            input,
            format!(
                "its header claims shape {shape:?} ({} bytes of float32) but {data} bytes follow it",
                bytes.map_or_else(|| "more than 2^64".to_string(), |b| b.to_string())
            ),
        ));
    }
    // The tensor read, its contiguous copy, and the output of 10 channels per frame.
    crate::limits::memory(
        "--input-npy",
        data.saturating_mul(12),
        "this tensor and its output",
    )?;
    let mut out = [0usize; 5];
    for (o, s) in out.iter_mut().zip(shape) {
        *o = usize::try_from(s).map_err(|_| Error::format(input, "shape too large"))?;
    }
    Ok(out)
}

/// Runs `model` on the float32 `(B, L, 2, H, W)` tensor in `input` and writes its output to
/// `output` (through a temporary file renamed at the end, so a failed run leaves none).
pub fn run_npy(
    model: &Path,
    input: &Path,
    output: &Path,
    options: &LearnedConfig,
) -> Result<RawReport> {
    let shape = checked_shape(input)?;
    let array: ArrayD<f32> = ndarray_npy::read_npy(input).map_err(|e| {
        Error::format(
            input,
            format!("not a float32 .npy tensor: {e} (write it with numpy: arr.astype(np.float32))"),
        )
    })?;
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

/// What [`bench()`] measured: one window of `pairs` pairs at `width x height`.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct BenchReport {
    /// Frame width.
    pub width: usize,
    /// Frame height.
    pub height: usize,
    /// Pairs per window.
    pub pairs: usize,
    /// ONNX Runtime intra-op threads (0: its default).
    pub threads: usize,
    /// Execution provider.
    pub provider: &'static str,
    /// Seconds of each timed run (after one warm-up run).
    pub runs_s: Vec<f64>,
    /// Median of `runs_s`.
    pub median_s: f64,
    /// `pairs / median_s`.
    pub pairs_per_s: f64,
    /// Peak resident set of the process, MiB (opening the model included).
    pub peak_rss_mib: f64,
}

/// Times `runs` windows of `pairs` pairs at `size = (width, height)` after one warm-up, on a
/// fixed pseudo-random input (speed does not depend on the values).
pub fn bench(
    model: &Path,
    size: (usize, usize),
    pairs: usize,
    runs: usize,
    options: &LearnedConfig,
) -> Result<BenchReport> {
    let (w, h) = size;
    if w == 0 || h == 0 || pairs == 0 || runs == 0 {
        return Err(Error::invalid(
            "bench",
            "size, pairs and runs must be positive",
        ));
    }
    let mut network = Network::open(model, options)?;
    let shape = [1, pairs, 2, h, w];
    let n: usize = shape.iter().product();
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let input: Vec<f32> = (0..n)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32 * 4.0 - 1.0
        })
        .collect();
    network.run(&input, shape)?;
    let mut runs_s = Vec::with_capacity(runs);
    for _ in 0..runs {
        let started = Instant::now();
        network.run(&input, shape)?;
        runs_s.push(started.elapsed().as_secs_f64());
    }
    let median_s = crate::stats::median(&mut runs_s.clone());
    Ok(BenchReport {
        width: w,
        height: h,
        pairs,
        threads: options.threads,
        provider: network.provider(),
        runs_s,
        median_s,
        pairs_per_s: pairs as f64 / median_s,
        peak_rss_mib: crate::process::ProcessUsage::now().max_rss_kib as f64 / 1024.0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn npy(dir: &Path, name: &str, descr: &str, shape: &str, data: usize) -> std::path::PathBuf {
        let mut dict =
            format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
        while (10 + dict.len() + 1) % 64 != 0 {
            dict.push(' ');
        }
        dict.push('\n');
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        bytes.extend((dict.len() as u16).to_le_bytes());
        bytes.extend(dict.as_bytes());
        bytes.resize(bytes.len() + data, 0);
        let path = dir.join(name);
        std::fs::write(&path, bytes).unwrap();
        path
    }

    #[test]
    fn a_tensor_header_is_checked_against_the_file_before_allocating() {
        let dir = std::env::temp_dir().join(format!("v2ce-raw-npy-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // A 4 KB file claiming 256 GB.
        let huge = npy(&dir, "huge.npy", "<f4", "(64, 16, 2, 8192, 8192)", 4000);
        let e = checked_shape(&huge).unwrap_err().to_string();
        assert!(e.contains("bytes follow"), "{e}");
        // Claims past 2^64 bytes.
        let past = npy(
            &dir,
            "past.npy",
            "<f4",
            "(4294967296, 4294967296, 2, 1, 1)",
            16,
        );
        let e = checked_shape(&past).unwrap_err().to_string();
        assert!(e.contains("more than 2^64"), "{e}");
        let f8 = npy(&dir, "f8.npy", "<f8", "(1, 1, 2, 2, 2)", 64);
        assert!(checked_shape(&f8)
            .unwrap_err()
            .to_string()
            .contains("float32"));
        let rank4 = npy(&dir, "r4.npy", "<f4", "(1, 2, 2, 2)", 32);
        assert!(checked_shape(&rank4)
            .unwrap_err()
            .to_string()
            .contains("(B, L, 2, H, W)"));
        let good = npy(&dir, "good.npy", "<f4", "(1, 3, 2, 4, 5)", 4 * 120);
        assert_eq!(checked_shape(&good).unwrap(), [1, 3, 2, 4, 5]);
        // As NumPy writes it.
        let written = dir.join("written.npy");
        ndarray_npy::write_npy(&written, &ArrayD::<f32>::zeros(IxDyn(&[2, 1, 2, 3, 7]))).unwrap();
        assert_eq!(checked_shape(&written).unwrap(), [2, 1, 2, 3, 7]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
