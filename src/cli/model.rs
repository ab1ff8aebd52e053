//! `v2ce model`: import the official checkpoint, run or time a network on raw tensors.

use std::path::PathBuf;

use clap::{Args, Subcommand};

use super::*;
use crate::error::{Error, Result};
use crate::limits::parse_size;

/// The `v2ce model` subcommands.
#[derive(Subcommand)]
pub enum ModelCommand {
    /// Turn a PyTorch checkpoint of the V2CE generator (the toolbox's v2ce_3d.pt, or a
    /// Lightning .ckpt) into an ONNX model, without PyTorch or a GPU.
    Import(ModelImportArgs),
    /// Run an ONNX model on a raw tensor: IN.npy float32 (B, L, 2, H, W), already normalised,
    /// to OUT.npy float32 (B, L, 20, H, W), the network's output after its final ReLU.
    Run(ModelRunArgs),
    /// Time one window of the network (pairs/s and peak memory), as one JSON line.
    Bench(ModelBenchArgs),
}

/// The flags of `v2ce model bench`.
#[derive(Args)]
pub struct ModelBenchArgs {
    /// The ONNX model.
    pub(crate) model: PathBuf,
    /// Frame size.
    #[arg(long, value_name = "WxH", default_value = "346x260")]
    pub(crate) size: String,
    /// Pairs per window.
    #[arg(long, default_value_t = 16)]
    pub(crate) pairs: usize,
    /// Timed runs after one warm-up (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub(crate) runs: usize,
    /// How ONNX Runtime runs the network.
    #[command(flatten)]
    pub(crate) runtime: RuntimeArgs,
}

/// The flags of `v2ce model import`.
#[derive(Args)]
pub struct ModelImportArgs {
    /// The checkpoint (a torch.save zip archive of the state dict).
    pub(crate) checkpoint: PathBuf,
    /// The ONNX model to write (written under a temporary name, renamed when complete).
    #[arg(short, long, value_name = "M.onnx")]
    pub(crate) output: PathBuf,
    /// How spectral-norm weights are resolved: power-iteration (what the reference does at its
    /// first call after loading; the only one that reproduces it), stored, exact.
    #[arg(long, value_enum, default_value_t = crate::model::SpectralNorm::PowerIteration)]
    pub(crate) spectral_norm: crate::model::SpectralNorm,
    /// Keep BatchNorm as nodes instead of folding it into the convolutions.
    #[arg(long)]
    pub(crate) keep_bn: bool,
    /// Overwrite an existing output file.
    #[arg(long)]
    pub(crate) force: bool,
}

/// The flags of `v2ce model run`.
#[derive(Args)]
pub struct ModelRunArgs {
    /// The ONNX model.
    pub(crate) model: PathBuf,
    /// Input tensor (.npy, float32, 5 dimensions).
    #[arg(long, value_name = "IN.npy")]
    pub(crate) input_npy: PathBuf,
    /// Where to write the output tensor (.npy, float32).
    #[arg(long, value_name = "OUT.npy")]
    pub(crate) output_npy: PathBuf,
    /// How ONNX Runtime runs the network.
    #[command(flatten)]
    pub(crate) runtime: RuntimeArgs,
    /// Overwrite an existing output file.
    #[arg(long)]
    pub(crate) force: bool,
}

/// Runs `v2ce model import`.
pub fn model_import(args: ModelImportArgs) -> Result<()> {
    crate::output::check(&args.output, &[&args.checkpoint], args.force)?;
    let options = crate::model::ImportOptions {
        spectral_norm: args.spectral_norm,
        fold_batch_norm: !args.keep_bn,
    };
    let r = crate::model::import(&args.checkpoint, &args.output, &options)?;
    let sigmas: Vec<f64> = r.spectral_norms.iter().map(|(_, s)| *s).collect();
    let (lo, hi) = sigmas
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &s| {
            (a.min(s), b.max(s))
        });
    eprintln!(
        "v2ce: {} -> {} ({:.1} MB): {} tensors read{}{}, {} parameters, {} spectral norms \
         resolved by {} (sigma {:.4}..{:.4}), BatchNorm {}, {} initializers",
        r.checkpoint.display(),
        r.output.display(),
        r.output_bytes as f64 / 1e6,
        r.keys_read,
        if r.prefix_stripped {
            ", Lightning prefix `model.` stripped"
        } else {
            ""
        },
        if r.dropped_gan_keys > 0 {
            format!(", {} discriminator tensors dropped", r.dropped_gan_keys)
        } else {
            String::new()
        },
        r.parameters,
        sigmas.len(),
        args.spectral_norm.name(),
        lo,
        hi,
        if args.keep_bn { "kept" } else { "folded" },
        r.initializers
    );
    Ok(())
}

/// Runs `v2ce model bench`.
pub fn model_bench(args: ModelBenchArgs) -> Result<()> {
    let (w, h) = parse_size(&args.size)?;
    let options = args.runtime.options();
    let report = crate::stage1::learned::raw::bench(
        &args.model,
        (w as usize, h as usize),
        args.pairs,
        args.runs,
        &options,
    )?;
    let text =
        serde_json::to_string(&report).map_err(|e| Error::invalid("report", e.to_string()))?;
    println!("{text}");
    Ok(())
}

/// Runs `v2ce model run`.
pub fn model_run(args: ModelRunArgs) -> Result<()> {
    crate::output::check(
        &args.output_npy,
        &[&args.model, &args.input_npy],
        args.force,
    )?;
    let options = args.runtime.options();
    let report = crate::stage1::learned::raw::run_npy(
        &args.model,
        &args.input_npy,
        &args.output_npy,
        &options,
    )?;
    eprintln!(
        "v2ce: {} -> {}: output {:?} in {:.2} s on {}, max {:.6}, {} NaN/infinite",
        args.input_npy.display(),
        args.output_npy.display(),
        report.shape,
        report.seconds,
        report.provider,
        report.max,
        report.nonfinite
    );
    Ok(())
}
