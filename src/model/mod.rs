//! The learned Stage 1 model's weights: from a PyTorch checkpoint of the V2CE generator to an ONNX
//! model, without PyTorch.
//!
//! The parts, each usable on its own:
//!
//! * [`torch`] reads (and writes) `torch.save` zip archives with a small pickle interpreter that
//!   executes nothing;
//! * [`v2ce_net`] is the one description of the network (spec §3.3): the state-dict keys and shapes it
//!   expects, the check of a loaded state dict, the spectral-norm and BatchNorm resolution, and the
//!   ONNX graph;
//! * [`onnx`] declares the few ONNX protobuf messages the graph needs, with builder helpers;
//! * [`seeded`] makes the deterministic test checkpoint that a Python script reproduces bit for bit.
//!
//! [`import`] ties them together: checkpoint in, ONNX model out, with a report.

pub mod onnx;
pub mod seeded;
pub mod torch;
pub mod v2ce_net;

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use crate::{Error, Result};

pub use v2ce_net::{Architecture, SpectralNorm};

/// The elements of a [`Tensor`], in row-major order.
#[derive(Clone, Debug, PartialEq)]
pub enum TensorData {
    /// 32-bit floats (also what 16-bit and 64-bit float storages are converted to).
    F32(Vec<f32>),
    /// 64-bit integers (also what narrower integer and boolean storages are converted to).
    I64(Vec<i64>),
}

/// A dense tensor: a shape and its elements in row-major order.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    /// The size of each dimension; empty for a scalar.
    pub shape: Vec<usize>,
    /// The elements; their number is the product of `shape`.
    pub data: TensorData,
}

impl Tensor {
    /// A float tensor. The caller keeps `data.len()` equal to the product of `shape`.
    pub fn f32(shape: Vec<usize>, data: Vec<f32>) -> Self {
        Tensor {
            shape,
            data: TensorData::F32(data),
        }
    }

    /// An int64 tensor. The caller keeps `data.len()` equal to the product of `shape`.
    pub fn i64(shape: Vec<usize>, data: Vec<i64>) -> Self {
        Tensor {
            shape,
            data: TensorData::I64(data),
        }
    }

    /// The number of elements.
    pub fn len(&self) -> usize {
        match &self.data {
            TensorData::F32(v) => v.len(),
            TensorData::I64(v) => v.len(),
        }
    }

    /// Whether the tensor holds no element.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The element type's name as PyTorch spells it (`float32`, `int64`).
    pub fn dtype_name(&self) -> &'static str {
        match self.data {
            TensorData::F32(_) => "float32",
            TensorData::I64(_) => "int64",
        }
    }

    /// The elements when the tensor holds floats.
    pub fn as_f32(&self) -> Option<&[f32]> {
        match &self.data {
            TensorData::F32(v) => Some(v),
            TensorData::I64(_) => None,
        }
    }
}

/// Formats a shape the way PyTorch prints it: `[64, 32, 3, 3, 3]`, `[]` for a scalar.
pub fn shape_string(shape: &[usize]) -> String {
    let parts: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    format!("[{}]", parts.join(", "))
}

/// How [`import`] turns the checkpoint into a graph.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImportOptions {
    /// How each spectral-norm convolution's weight is resolved (default: one power iteration, as
    /// the reference code's first forward call does).
    pub spectral_norm: SpectralNorm,
    /// Fold each BatchNorm into the convolution before it (default). When false the graph keeps
    /// `BatchNormalization` nodes, which is slower but shows the checkpoint's statistics as they are.
    pub fold_batch_norm: bool,
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions {
            spectral_norm: SpectralNorm::PowerIteration,
            fold_batch_norm: true,
        }
    }
}

/// What [`import`] read and wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct ImportReport {
    /// The checkpoint that was read.
    pub checkpoint: PathBuf,
    /// The ONNX model that was written.
    pub output: PathBuf,
    /// Tensors in the checkpoint's state dict, before any was dropped.
    pub keys_read: usize,
    /// Whether the keys carried Lightning's `model.` prefix (stripped).
    pub prefix_stripped: bool,
    /// Discriminator (`GAN.*`) tensors of a Lightning checkpoint, dropped.
    pub dropped_gan_keys: usize,
    /// The generator's trainable parameters (52,791,508 for V2CE).
    pub parameters: u64,
    /// Each spectral-norm convolution (module path) with the sigma its weight was divided by.
    pub spectral_norms: Vec<(String, f64)>,
    /// Initializers in the graph.
    pub initializers: usize,
    /// Size of the written model in bytes.
    pub output_bytes: u64,
}

/// Reads a PyTorch checkpoint of the V2CE generator (a toolbox `.pt` state dict or a Lightning
/// `.ckpt`) and writes the equivalent ONNX model to `output`.
///
/// The state dict is checked against the architecture before any weight is read; weights are then
/// read one at a time as the graph needs them, so memory holds about one copy of the model. The
/// model is written to a temporary file beside `output` and renamed at the end, so a failed import
/// never leaves a file that looks complete.
pub fn import(checkpoint: &Path, output: &Path, options: &ImportOptions) -> Result<ImportReport> {
    let mut archive = torch::TorchArchive::open(checkpoint)?;
    // The released network, or a narrower or shallower one of its family (a model trained by
    // `train/`): read off the checkpoint's shapes, then checked key by key.
    let listed: Vec<(&str, &[usize])> = archive
        .entries()
        .iter()
        .map(|e| (e.name.as_str(), e.shape.as_slice()))
        .collect();
    let arch = Architecture::infer(&listed).unwrap_or_else(Architecture::v2ce);
    drop(listed);
    let selection = arch.select(checkpoint, archive.entries())?;
    let keys_read = archive.entries().len();
    let mut source = ArchiveSource {
        archive: &mut archive,
        selection: &selection,
    };
    let built = arch.build_model(&mut source, options, checkpoint)?;
    let initializers = built
        .model
        .graph
        .as_ref()
        .map(|g| g.initializer.len())
        .unwrap_or(0);
    let output_bytes = write_model_atomically(built.model, output)?;
    Ok(ImportReport {
        checkpoint: checkpoint.to_path_buf(),
        output: output.to_path_buf(),
        keys_read,
        prefix_stripped: selection.prefix_stripped,
        dropped_gan_keys: selection.dropped_gan_keys,
        parameters: arch.trainable_parameters(),
        spectral_norms: built.spectral_norms,
        initializers,
        output_bytes,
    })
}

/// Weights read lazily from an open archive, by their normalised (toolbox) key.
struct ArchiveSource<'a> {
    archive: &'a mut torch::TorchArchive,
    selection: &'a v2ce_net::Selection,
}

impl v2ce_net::WeightSource for ArchiveSource<'_> {
    fn take(&mut self, key: &str) -> Result<Tensor> {
        let index = self.selection.index_of(key).ok_or_else(|| {
            Error::format(
                self.archive.path(),
                format!("missing key {key} (checked earlier, so this is a bug)"),
            )
        })?;
        self.archive.load(index)
    }
}

/// Writes `model` to a temporary file beside `output`, then renames it to `output`. Returns the
/// size written.
pub fn write_model_atomically(model: onnx::ModelProto, output: &Path) -> Result<u64> {
    let file_name = output
        .file_name()
        .ok_or_else(|| Error::invalid("output", format!("{} names no file", output.display())))?;
    let tmp = output.with_file_name(format!(
        ".{}.tmp-{}",
        file_name.to_string_lossy(),
        std::process::id()
    ));
    let mut guard = RemoveOnDrop(Some(tmp.clone()));
    let file = File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    let mut writer = BufWriter::with_capacity(1 << 20, file);
    let bytes = onnx::write_model(model, &mut writer).map_err(|e| Error::io(&tmp, e))?;
    let file = writer
        .into_inner()
        .map_err(|e| Error::io(&tmp, e.into_error()))?;
    file.sync_all().map_err(|e| Error::io(&tmp, e))?;
    drop(file);
    std::fs::rename(&tmp, output).map_err(|e| Error::io(output, e))?;
    guard.0 = None;
    Ok(bytes)
}

/// Removes a file when dropped (a temporary output abandoned by an error).
struct RemoveOnDrop(Option<PathBuf>);

impl Drop for RemoveOnDrop {
    fn drop(&mut self) {
        if let Some(path) = self.0.take() {
            // Best effort: the error being returned matters more than a leftover temporary file.
            let _ = std::fs::remove_file(path);
        }
    }
}

/// Writes all of `bytes` and counts them (a small helper for the streaming writers).
pub(crate) fn write_counted(
    w: &mut impl Write,
    bytes: &[u8],
    count: &mut u64,
) -> std::io::Result<()> {
    w.write_all(bytes)?;
    *count += bytes.len() as u64;
    Ok(())
}
