//! Checkpoint tools for checking the model import by hand (e.g. against PyTorch and onnxruntime):
//!
//! ```text
//! cargo run --release --example model_tool -- seeded SEED OUT.pt [LOCATION [BIAS_SHIFT]]   # the seeded checkpoint
//! cargo run --release --example model_tool -- list CKPT                       # keys, shapes, sums
//! cargo run --release --example model_tool -- copy CKPT OUT.pt [LOCATION]       # read, then write again
//! cargo run --release --example model_tool -- import CKPT OUT.onnx [power-iteration|stored|exact] [keep-bn]
//! cargo run --release --example model_tool -- refold IN.onnx OUT.onnx         # an older import's 5-D resizes to 4-D
//! ```

use std::path::Path;
use std::process::ExitCode;

use v2ce::model::{self, torch, ImportOptions, TensorData};

fn run(args: &[String]) -> v2ce::Result<()> {
    let usage = || {
        v2ce::Error::invalid(
            "arguments",
            "seeded SEED OUT [LOCATION] | list CKPT | copy CKPT OUT [LOCATION] | import CKPT OUT [MODE] [keep-bn] | refold IN OUT",
        )
    };
    match args.first().map(String::as_str) {
        Some("seeded") => {
            let seed: u64 = args.get(1).and_then(|s| s.parse().ok()).ok_or_else(usage)?;
            let out = args.get(2).ok_or_else(usage)?;
            let location = args.get(3).map_or("cpu", String::as_str);
            let mut sd = model::seeded::state_dict(seed);
            // An optional shift of the prediction's bias: a negative one makes the voxels as
            // sparse as real ones (the seeded network fires everywhere), for timing the
            // pipeline with a realistic event rate.
            if let Some(shift) = args.get(4).and_then(|s| s.parse::<f32>().ok()) {
                for (key, tensor) in sd.iter_mut() {
                    if key == "UNet.pred.conv3d.bias" {
                        if let TensorData::F32(v) = &mut tensor.data {
                            v.iter_mut().for_each(|b| *b += shift);
                        }
                    }
                }
            }
            torch::write_state_dict(Path::new(out), &sd, location)?;
            println!("wrote {} tensors to {out}", sd.len());
        }
        Some("copy") => {
            // Read with the reader, write with the writer: a round trip through both.
            let input = args.get(1).ok_or_else(usage)?;
            let out = args.get(2).ok_or_else(usage)?;
            let location = args.get(3).map_or("cpu", String::as_str);
            let sd = torch::read_state_dict(Path::new(input))?;
            torch::write_state_dict(Path::new(out), &sd, location)?;
            println!("copied {} tensors to {out}", sd.len());
        }
        Some("list") => {
            let path = args.get(1).ok_or_else(usage)?;
            for (name, t) in torch::read_state_dict(Path::new(path))? {
                let sum: f64 = match &t.data {
                    TensorData::F32(v) => v.iter().map(|&x| f64::from(x)).sum(),
                    TensorData::I64(v) => v.iter().map(|&x| x as f64).sum(),
                };
                println!(
                    "{name} {} {} sum={sum:.9e}",
                    t.dtype_name(),
                    model::shape_string(&t.shape)
                );
            }
        }
        Some("import") => {
            let ckpt = args.get(1).ok_or_else(usage)?;
            let out = args.get(2).ok_or_else(usage)?;
            let mut options = ImportOptions::default();
            for extra in &args[3..] {
                if extra == "keep-bn" {
                    options.fold_batch_norm = false;
                } else {
                    options.spectral_norm = extra.parse()?;
                }
            }
            let report = model::import(Path::new(ckpt), Path::new(out), &options)?;
            println!("{report:#?}");
        }
        Some("refold") => {
            use prost::Message;
            let input = args.get(1).ok_or_else(usage)?;
            let out = args.get(2).ok_or_else(usage)?;
            let bytes =
                std::fs::read(input).map_err(|e| v2ce::Error::invalid("model", e.to_string()))?;
            let mut m = model::onnx::ModelProto::decode(bytes.as_slice())
                .map_err(|e| v2ce::Error::invalid("model", e.to_string()))?;
            let n = model::v2ce_net::fold_upsampling(&mut m);
            let mut file = std::fs::File::create(out)
                .map_err(|e| v2ce::Error::invalid("output", e.to_string()))?;
            model::onnx::write_model(m, &mut file)
                .map_err(|e| v2ce::Error::invalid("output", e.to_string()))?;
            println!("{input} -> {out}: {n} resizes folded to 4-D");
        }
        _ => return Err(usage()),
    }
    Ok(())
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("model_tool: {e}");
            ExitCode::FAILURE
        }
    }
}
