//! The model import: PyTorch archives read and written without PyTorch, the state-dict check,
//! and the ONNX model made from the seeded checkpoint.
//!
//! `tests/fixtures/torch/*.pt|ckpt` were written by `torch.save` (PyTorch 2.15, see
//! `make_fixtures.py` there); nothing here needs Python. The ONNX model's numbers were checked
//! against the PyTorch reference with `tools/check_model_import.py` (by hand).

mod common;

use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use prost::Message;

use common::temp_dir;
use v2ce::model::onnx::{DimensionValue, ModelProto};
use v2ce::model::torch::{self, TorchArchive};
use v2ce::model::{self, seeded, Architecture, ImportOptions, SpectralNorm, Tensor, TensorData};
use v2ce::Error;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/torch")
        .join(name)
}

fn small_state_dict() -> Vec<(String, Tensor)> {
    vec![
        (
            "conv.weight".into(),
            Tensor::f32(
                vec![2, 1, 1, 2, 3],
                (0..12).map(|i| i as f32 * 0.5 - 2.0).collect(),
            ),
        ),
        (
            "bn.num_batches_tracked".into(),
            Tensor::i64(vec![], vec![-7]),
        ),
        ("empty".into(), Tensor::f32(vec![0, 3], vec![])),
        (
            "big".into(),
            Tensor::f32(
                vec![100_003],
                (0..100_003).map(|i| (i as f32).sin()).collect(),
            ),
        ),
        (
            "ids".into(),
            Tensor::i64(vec![3], vec![i64::MIN, 0, i64::MAX]),
        ),
    ]
}

fn message(e: &Error) -> String {
    e.to_string()
}

#[test]
fn writer_then_reader_round_trips_exactly() {
    let dir = temp_dir("model-roundtrip");
    let path = dir.join("small.pt");
    let sd = small_state_dict();
    torch::write_state_dict(&path, &sd, "cpu").unwrap();
    let back = torch::read_state_dict(&path).unwrap();
    assert_eq!(back, sd);

    // Every storage starts on a 64-byte boundary, as PyTorch aligns them.
    let mut zip = zip::ZipArchive::new(std::fs::File::open(&path).unwrap()).unwrap();
    let mut storages = 0;
    for i in 0..zip.len() {
        let f = zip.by_index(i).unwrap();
        let name = f.name().unwrap().into_owned();
        if name.starts_with("archive/data/") {
            storages += 1;
            assert_eq!(f.data_start().unwrap() % 64, 0, "{name}");
        }
    }
    assert_eq!(storages, sd.len());
    let mut order = String::new();
    zip.by_name("archive/byteorder")
        .unwrap()
        .read_to_string(&mut order)
        .unwrap();
    assert_eq!(order, "little");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_cuda_location_reads_the_same() {
    let dir = temp_dir("model-cuda");
    let (cpu, cuda) = (dir.join("cpu.pt"), dir.join("cuda.pt"));
    let sd = small_state_dict();
    torch::write_state_dict(&cpu, &sd, "cpu").unwrap();
    torch::write_state_dict(&cuda, &sd, "cuda:0").unwrap();
    // The tag is really in the file (torch.load refuses it without a GPU or map_location) ...
    let bytes = std::fs::read(&cuda).unwrap();
    assert!(bytes.windows(6).any(|w| w == b"cuda:0"));
    assert_ne!(bytes, std::fs::read(&cpu).unwrap());
    // ... and does not matter to the reader.
    assert_eq!(torch::read_state_dict(&cuda).unwrap(), sd);
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn reads_what_torch_save_writes() {
    let sd = torch::read_state_dict(&fixture("plain.pt")).unwrap();
    let names: Vec<&str> = sd.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(
        names,
        [
            "w",
            "count",
            "half",
            "bf16",
            "f64",
            "transposed",
            "offset",
            "param",
            "i32",
            "flags",
            "empty"
        ]
    );
    let get = |name: &str| &sd.iter().find(|(n, _)| n == name).unwrap().1;
    let w: Vec<f32> = (0..12).map(|i| i as f32 / 8.0 - 0.5).collect();
    assert_eq!(get("w"), &Tensor::f32(vec![3, 4], w.clone()));
    assert_eq!(get("count"), &Tensor::i64(vec![], vec![1_234_567_890_123]));
    assert_eq!(
        get("half"),
        &Tensor::f32(vec![5], vec![0.5, -1.25, 65504.0, 2f32.powi(-24), 0.0])
    );
    assert_eq!(
        get("bf16"),
        &Tensor::f32(vec![2, 2], vec![1.5, -2.0, 3.140625, 0.0])
    );
    assert_eq!(
        get("f64"),
        &Tensor::f32(vec![3], vec![0.1f64 as f32, -0.2f64 as f32, 1e-3f64 as f32])
    );
    // The transpose is a strided view of w's storage: read in its own row-major order.
    let wt: Vec<f32> = (0..12).map(|i| w[(i % 3) * 4 + i / 3]).collect();
    assert_eq!(get("transposed"), &Tensor::f32(vec![4, 3], wt));
    assert_eq!(
        get("offset"),
        &Tensor::f32(vec![2, 3], vec![5.0, 6.0, 7.0, 8.0, 9.0, 10.0])
    );
    assert_eq!(get("param"), &Tensor::f32(vec![2, 3], vec![0.25; 6]));
    assert_eq!(get("i32"), &Tensor::i64(vec![2], vec![-1, 2]));
    assert_eq!(get("flags"), &Tensor::i64(vec![2], vec![1, 0]));
    assert_eq!(get("empty"), &Tensor::f32(vec![0, 3], vec![]));
}

#[test]
fn a_lightning_checkpoint_gives_its_state_dict() {
    // torch.save of {'epoch', 'state_dict', 'optimizer_states', 'hyper_parameters':
    // argparse.Namespace(...), 'callbacks', sets, a 2**70 int, ...}: everything but the state dict
    // is walked past.
    let path = fixture("lightning.ckpt");
    let mut archive = TorchArchive::open(&path).unwrap();
    assert!(archive.nested());
    let names: Vec<&str> = archive.entries().iter().map(|e| e.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "model.UNet.head.conv3d.bias",
            "GAN.discriminator.disc.model.8.bias"
        ]
    );
    let bias = archive.load(0).unwrap();
    let values = bias.as_f32().unwrap();
    assert_eq!(bias.shape, vec![32]);
    assert_eq!((values[0], values[31]), (-1.0, 1.0));
    assert!(values.windows(2).all(|p| p[1] > p[0]));
    assert_eq!(archive.load(1).unwrap(), Tensor::f32(vec![1], vec![0.75]));

    // As a V2CE checkpoint it lacks nearly everything: the first missing key is named.
    let err = Architecture::v2ce()
        .select(&path, archive.entries())
        .unwrap_err();
    match &err {
        Error::StateDict { path: p, key, .. } => {
            assert_eq!(p, &path);
            assert_eq!(key, "UNet.head.conv3d.weight");
        }
        other => panic!("unexpected error {other}"),
    }
    assert!(message(&err).contains("missing"), "{err}");
    assert!(message(&err).contains("lightning.ckpt"), "{err}");
}

/// The V2CE key list as `(name, shape, holds floats)`, optionally with Lightning's layout.
fn v2ce_keys(lightning: bool) -> Vec<(String, Vec<usize>, bool)> {
    let mut keys: Vec<(String, Vec<usize>, bool)> = Architecture::v2ce()
        .state_dict_keys()
        .into_iter()
        .map(|k| {
            let name = if lightning {
                format!("model.{}", k.name)
            } else {
                k.name
            };
            (name, k.shape, !k.kind.is_int())
        })
        .collect();
    if lightning {
        for (i, (o, c)) in [(64, 20), (128, 64), (256, 128), (512, 256), (1, 512)]
            .into_iter()
            .enumerate()
        {
            let p = format!("GAN.discriminator.disc.model.{}", 2 * i);
            keys.push((format!("{p}.weight"), vec![o, c, 4, 4], true));
            keys.push((format!("{p}.bias"), vec![o], true));
        }
    }
    keys
}

fn check(keys: &[(String, Vec<usize>, bool)]) -> v2ce::Result<model::v2ce_net::Selection> {
    let listed: Vec<(&str, &[usize], bool)> = keys
        .iter()
        .map(|(n, s, f)| (n.as_str(), s.as_slice(), *f))
        .collect();
    Architecture::v2ce().check_keys(Path::new("ckpt.pt"), &listed)
}

fn key_of(err: Error) -> (String, String) {
    match err {
        Error::StateDict { key, message, .. } => (key, message),
        other => panic!("not a state-dict error: {other}"),
    }
}

#[test]
fn the_state_dict_check_names_the_first_bad_key() {
    let good = v2ce_keys(false);
    let sel = check(&good).unwrap();
    assert!(!sel.prefix_stripped);
    assert_eq!(sel.dropped_gan_keys, 0);
    assert_eq!(sel.index_of("UNet.pred.conv3d.bias"), Some(217));

    // Lightning: model. prefix stripped, the discriminator's 10 keys dropped.
    let sel = check(&v2ce_keys(true)).unwrap();
    assert!(sel.prefix_stripped);
    assert_eq!(sel.dropped_gan_keys, 10);
    assert_eq!(sel.index_of("UNet.head.conv3d.weight"), Some(0));

    // A missing key.
    let mut keys = good.clone();
    keys.remove(100);
    let (key, msg) = key_of(check(&keys).unwrap_err());
    assert_eq!(key, good[100].0);
    assert!(
        msg.contains("missing") && msg.contains("1 missing"),
        "{msg}"
    );

    // An extra key.
    let mut keys = good.clone();
    keys.insert(5, ("UNet.head.conv3d.extra".into(), vec![3], true));
    let (key, msg) = key_of(check(&keys).unwrap_err());
    assert_eq!(key, "UNet.head.conv3d.extra");
    assert!(msg.contains("unexpected"), "{msg}");

    // A mis-shaped key: expected and found shapes both named.
    let mut keys = good.clone();
    let at = keys
        .iter()
        .position(|k| k.0 == "UNet.decoders.0.conv1.module.weight_bar")
        .unwrap();
    keys[at].1 = vec![256, 512, 3, 3, 3];
    let (key, msg) = key_of(check(&keys).unwrap_err());
    assert_eq!(key, "UNet.decoders.0.conv1.module.weight_bar");
    assert!(
        msg.contains("[256, 512, 3, 3, 3]") && msg.contains("[256, 768, 3, 3, 3]"),
        "{msg}"
    );

    // Integers where floats belong.
    let mut keys = good.clone();
    keys[1].2 = false;
    let (key, msg) = key_of(check(&keys).unwrap_err());
    assert_eq!(key, "UNet.head.conv3d.bias");
    assert!(msg.contains("integers"), "{msg}");

    // The same key with and without the prefix.
    let mut keys = good.clone();
    keys.push((format!("model.{}", good[0].0), good[0].1.clone(), true));
    let (key, msg) = key_of(check(&keys).unwrap_err());
    assert_eq!(key, good[0].0);
    assert!(msg.contains("twice"), "{msg}");
}

#[test]
fn a_truncated_archive_is_a_clear_error() {
    let dir = temp_dir("model-truncated");
    let path = dir.join("small.pt");
    torch::write_state_dict(&path, &small_state_dict(), "cpu").unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let cut = dir.join("cut.pt");
    std::fs::write(&cut, &bytes[..bytes.len() * 6 / 10]).unwrap();
    let err = torch::read_state_dict(&cut).unwrap_err();
    let msg = message(&err);
    assert!(msg.contains("cut.pt") && msg.contains("truncated"), "{msg}");
    std::fs::remove_dir_all(dir).unwrap();
}

/// Copies the archive at `from` to `to`, replacing the entry `name` by `data`.
fn rewrite_entry(from: &Path, to: &Path, name: &str, data: &[u8]) {
    let mut src = zip::ZipArchive::new(std::fs::File::open(from).unwrap()).unwrap();
    let mut out = zip::ZipWriter::new(std::fs::File::create(to).unwrap());
    let options =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for i in 0..src.len() {
        let mut f = src.by_index(i).unwrap();
        let entry = f.name().unwrap().into_owned();
        let mut content = Vec::new();
        f.read_to_end(&mut content).unwrap();
        out.start_file(entry.as_str(), options).unwrap();
        out.write_all(if entry == name { data } else { &content })
            .unwrap();
    }
    out.finish().unwrap();
}

#[test]
fn a_storage_shorter_than_its_tensor_is_a_clear_error() {
    let dir = temp_dir("model-short");
    let good = dir.join("good.pt");
    torch::write_state_dict(&good, &small_state_dict(), "cpu").unwrap();
    let bad = dir.join("short.pt");
    rewrite_entry(&good, &bad, "archive/data/3", &[0u8; 400]);
    let mut archive = TorchArchive::open(&bad).unwrap();
    // The other tensors still read; the damaged one names itself, its entry and both sizes.
    assert!(archive.load(0).is_ok());
    let msg = message(&archive.load(3).unwrap_err());
    assert!(
        msg.contains("short.pt") && msg.contains("tensor big"),
        "{msg}"
    );
    assert!(
        msg.contains("400 bytes") && msg.contains("400012 bytes"),
        "{msg}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn foreign_files_say_what_they_are_not() {
    let dir = temp_dir("model-foreign");
    let text = dir.join("notes.txt");
    std::fs::write(&text, "hello, not a checkpoint").unwrap();
    let msg = message(&torch::read_state_dict(&text).unwrap_err());
    assert!(
        msg.contains("notes.txt") && msg.contains("no zip signature"),
        "{msg}"
    );

    // The pre-1.6 format starts with a pickled magic number.
    let legacy = dir.join("old.pt");
    std::fs::write(
        &legacy,
        [0x80, 0x02, 0x8a, 0x0a, 0x6c, 0xfc, 0x9c, 0x46, 0xf9, 0x20],
    )
    .unwrap();
    let msg = message(&torch::read_state_dict(&legacy).unwrap_err());
    assert!(msg.contains("old.pt") && msg.contains("legacy"), "{msg}");

    let empty = dir.join("empty.pt");
    std::fs::write(&empty, b"").unwrap();
    let msg = message(&torch::read_state_dict(&empty).unwrap_err());
    assert!(msg.contains("empty"), "{msg}");

    let missing = dir.join("absent.pt");
    assert!(matches!(
        torch::read_state_dict(&missing),
        Err(Error::Io { .. })
    ));

    // A zip that is not a torch archive.
    let other = dir.join("other.zip");
    let mut zip = zip::ZipWriter::new(std::fs::File::create(&other).unwrap());
    zip.start_file("docs/readme.txt", zip::write::SimpleFileOptions::default())
        .unwrap();
    zip.write_all(b"hi").unwrap();
    zip.finish().unwrap();
    let msg = message(&torch::read_state_dict(&other).unwrap_err());
    assert!(
        msg.contains("other.zip") && msg.contains("data.pkl"),
        "{msg}"
    );
    assert!(msg.contains("docs/readme.txt"), "{msg}");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_damaged_pickle_is_an_error_not_a_panic() {
    let dir = temp_dir("model-pickle");
    let good = dir.join("good.pt");
    torch::write_state_dict(&good, &small_state_dict(), "cpu").unwrap();
    let mut pickle = Vec::new();
    zip::ZipArchive::new(std::fs::File::open(&good).unwrap())
        .unwrap()
        .by_name("archive/data.pkl")
        .unwrap()
        .read_to_end(&mut pickle)
        .unwrap();
    // Every truncation of the pickle is refused cleanly.
    let bad = dir.join("bad.pt");
    for cut in (0..pickle.len()).step_by(7) {
        rewrite_entry(&good, &bad, "archive/data.pkl", &pickle[..cut]);
        let err = TorchArchive::open(&bad).unwrap_err();
        assert!(message(&err).contains("data.pkl"), "cut {cut}: {err}");
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_damaged_archive_never_panics() {
    // Random byte changes anywhere in a small archive (zip headers, pickle, data): opening and
    // reading every tensor gives tensors or errors.
    let dir = temp_dir("model-damaged");
    let good = dir.join("good.pt");
    let mut sd = small_state_dict();
    sd.retain(|(n, _)| n != "big");
    torch::write_state_dict(&good, &sd, "cpu").unwrap();
    let clean = std::fs::read(&good).unwrap();
    let bad = dir.join("bad.pt");
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let mut opened = 0;
    for _ in 0..400 {
        let mut bytes = clean.clone();
        for _ in 0..1 + next() % 3 {
            let at = (next() % bytes.len() as u64) as usize;
            bytes[at] = next() as u8;
        }
        std::fs::write(&bad, &bytes).unwrap();
        if let Ok(mut archive) = TorchArchive::open(&bad) {
            opened += 1;
            for i in 0..archive.entries().len() {
                let _ = archive.load(i);
            }
        }
    }
    assert!(opened > 0);
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn importing_the_seeded_checkpoint() {
    let dir = temp_dir("model-seeded");
    let ckpt = dir.join("seeded42.pt");
    let sd = seeded::state_dict(42);
    torch::write_state_dict(&ckpt, &sd, "cuda:0").unwrap();
    let out = dir.join("v2ce.onnx");
    let report = model::import(&ckpt, &out, &ImportOptions::default()).unwrap();
    assert_eq!(report.keys_read, 218);
    assert_eq!(report.dropped_gan_keys, 0);
    assert!(!report.prefix_stripped);
    assert_eq!(report.parameters, 52_791_508);
    // 64 weights and the shape that folds the upsamplings to 4-D.
    assert_eq!(report.initializers, 65);
    assert_eq!(report.spectral_norms.len(), 12);
    // sigma after one power iteration, computed independently with torch in float64.
    let (name, sigma) = &report.spectral_norms[0];
    assert_eq!(name, "UNet.resblocks.0.conv1");
    assert!((sigma - 1.438_748_030_906_050_5).abs() < 1e-12, "{sigma}");
    let (name, sigma) = &report.spectral_norms[11];
    assert_eq!(name, "UNet.decoders.3.conv2");
    assert!((sigma - 1.443_495_000_380_588_9).abs() < 1e-12, "{sigma}");

    let bytes = std::fs::read(&out).unwrap();
    assert_eq!(report.output_bytes, bytes.len() as u64);
    // Nothing but the model is left in the folder (the temporary file was renamed).
    let mut files: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    files.sort();
    assert_eq!(files, ["seeded42.pt", "v2ce.onnx"]);

    let m = ModelProto::decode(bytes.as_slice()).unwrap();
    drop(bytes);
    assert_eq!(m.ir_version, Some(8));
    assert_eq!(m.opset_import[0].version, Some(17));
    assert_eq!(m.producer_name.as_deref(), Some("v2ce"));
    let meta = |k: &str| {
        m.metadata_props
            .iter()
            .find(|p| p.key.as_deref() == Some(k))
            .and_then(|p| p.value.clone())
    };
    assert_eq!(meta("producer").as_deref(), Some("v2ce"));
    assert_eq!(meta("source").as_deref(), Some("seeded42.pt"));
    assert_eq!(meta("spectral_norm").as_deref(), Some("power-iteration"));
    assert_eq!(meta("batch_norm").as_deref(), Some("folded"));
    let g = m.graph.as_ref().unwrap();
    // The weights and the fold of the four upsamplings to 4-D (`fold_lead`).
    assert_eq!(g.initializer.len(), 65);
    let dims = |v: &v2ce::model::onnx::ValueInfoProto| -> Vec<String> {
        v.r#type
            .as_ref()
            .unwrap()
            .tensor_type
            .as_ref()
            .unwrap()
            .shape
            .as_ref()
            .unwrap()
            .dim
            .iter()
            .map(|d| match d.value.as_ref().unwrap() {
                DimensionValue::DimValue(n) => n.to_string(),
                DimensionValue::DimParam(p) => p.clone(),
            })
            .collect()
    };
    assert_eq!(g.input[0].name.as_deref(), Some("frames"));
    assert_eq!(
        dims(&g.input[0]),
        ["batch", "pairs", "2", "height", "width"]
    );
    assert_eq!(g.output[0].name.as_deref(), Some("voxels"));
    assert_eq!(
        dims(&g.output[0]),
        ["batch", "pairs", "20", "height", "width"]
    );
    let count = |op: &str| {
        g.node
            .iter()
            .filter(|n| n.op_type.as_deref() == Some(op))
            .count()
    };
    assert_eq!(count("Conv"), 32);
    assert_eq!(count("Resize"), 4);
    assert_eq!(count("Reshape"), 8, "each resize folded to 4-D and back");
    assert_eq!(count("BatchNormalization"), 0);
    assert_eq!(count("Transpose"), 2);

    let init = |name: &str| -> Vec<f32> {
        let t = g
            .initializer
            .iter()
            .find(|t| t.name.as_deref() == Some(name))
            .unwrap_or_else(|| panic!("no initializer {name}"));
        t.raw_data
            .as_ref()
            .unwrap()
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    };
    // The head has no BatchNorm: its weights are the checkpoint's, bit for bit.
    assert_eq!(init("UNet.head.conv3d.weight"), sd[0].1.as_f32().unwrap());
    // encoders.0.conv1 with bn1 folded: element [5, 3, 1, 2, 0] and the bias of channel 5,
    // computed with torch in float64 from the same checkpoint, rounded to float32.
    let w = init("UNet.encoders.0.conv1.weight");
    assert_eq!(
        w[(((5 * 32 + 3) * 3 + 1) * 3 + 2) * 3].to_bits(),
        0xbda2_5b41 // -0.0792756155...
    );
    assert_eq!(
        init("UNet.encoders.0.conv1.bias")[5].to_bits(),
        0x3e5a_b179 // 0.2135676294...
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_failed_import_leaves_no_file_behind() {
    let dir = temp_dir("model-failed");
    let ckpt = fixture("lightning.ckpt");
    let out = dir.join("model.onnx");
    std::fs::write(&out, b"previous model").unwrap();
    let err = model::import(&ckpt, &out, &ImportOptions::default()).unwrap_err();
    assert!(matches!(err, Error::StateDict { .. }), "{err}");
    // The previous file is untouched and no temporary file is left.
    assert_eq!(std::fs::read(&out).unwrap(), b"previous model");
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn other_options_change_the_graph() {
    // BatchNorm kept as nodes, and the stored-vector spectral norm, on a small in-memory
    // state dict: build_model straight from the tensors.
    let arch = Architecture::v2ce();
    let sd = seeded::state_dict(3);
    let (mut tensors, _) = arch.select_tensors(Path::new("seeded3"), sd).unwrap();
    let options = ImportOptions {
        spectral_norm: SpectralNorm::Stored,
        fold_batch_norm: false,
    };
    let built = arch
        .build_model(&mut tensors, &options, Path::new("seeded3"))
        .unwrap();
    let g = built.model.graph.as_ref().unwrap();
    let bn = g
        .node
        .iter()
        .filter(|n| n.op_type.as_deref() == Some("BatchNormalization"))
        .count();
    assert_eq!(bn, 30);
    assert_eq!(g.initializer.len(), 165);
    assert!(
        tensors
            .values()
            .all(|t| matches!(t.data, TensorData::I64(_))),
        "only the unused counters remain"
    );
    let meta: Vec<(String, String)> = built
        .model
        .metadata_props
        .iter()
        .map(|p| (p.key.clone().unwrap(), p.value.clone().unwrap()))
        .collect();
    assert!(meta.contains(&("spectral_norm".into(), "stored".into())));
    assert!(meta.contains(&("batch_norm".into(), "kept".into())));
}

/// A tiny member of the same UNet family, with every float 0.5 (and variances 1).
fn tiny() -> (Architecture, Vec<(String, Tensor)>) {
    let arch = Architecture::unet(2, 4, 4, 1, 1);
    let sd = arch
        .state_dict_keys()
        .into_iter()
        .map(|k| {
            let n: usize = k.shape.iter().product();
            let t = if k.kind.is_int() {
                Tensor::i64(k.shape, vec![0])
            } else if k.name.ends_with("running_var") {
                Tensor::f32(k.shape, vec![1.0; n])
            } else {
                Tensor::f32(k.shape, vec![0.5; n])
            };
            (k.name, t)
        })
        .collect();
    (arch, sd)
}

#[test]
fn bad_values_name_their_key() {
    let (arch, sd) = tiny();
    let origin = Path::new("tiny.pt");
    let (mut ok, _) = arch.select_tensors(origin, sd.clone()).unwrap();
    let built = arch
        .build_model(&mut ok, &ImportOptions::default(), origin)
        .unwrap();
    // head, 1 encoder (3 convs), 1 resblock (3), 1 decoder (3), pred: 11 convs, 22 initializers,
    // and the shape that folds the upsampling to 4-D.
    assert_eq!(built.model.graph.unwrap().initializer.len(), 23);

    for (key, value, expected) in [
        ("UNet.encoders.0.conv2.weight", f32::NAN, "non-finite"),
        ("UNet.encoders.0.bn1.running_var", -1.0, "not above -eps"),
        (
            "UNet.resblocks.0.conv1.module.weight_bar",
            0.0,
            "sigma is 0",
        ),
    ] {
        let mut sd = sd.clone();
        let t = &mut sd.iter_mut().find(|(n, _)| n == key).unwrap().1;
        match &mut t.data {
            TensorData::F32(v) => v.iter_mut().for_each(|x| *x = value),
            TensorData::I64(_) => unreachable!(),
        }
        let (mut tensors, _) = arch.select_tensors(origin, sd).unwrap();
        let err = arch
            .build_model(&mut tensors, &ImportOptions::default(), origin)
            .unwrap_err();
        let msg = err.to_string();
        assert!(
            matches!(&err, Error::StateDict { key: k, .. } if k == key),
            "{msg}"
        );
        assert!(msg.contains("tiny.pt") && msg.contains(expected), "{msg}");
    }
}

/// A model as imports wrote it before the 4-D fold: each `{p}.up` one 5-D `Resize` after three
/// shape nodes, and no `fold_lead`.
fn unfolded(model: &v2ce::model::onnx::ModelProto) -> v2ce::model::onnx::ModelProto {
    use v2ce::model::onnx;
    let mut old = model.clone();
    let g = old.graph.as_mut().unwrap();
    let resizes: Vec<String> = g
        .node
        .iter()
        .filter(|n| n.op_type.as_deref() == Some("Resize"))
        .map(|n| {
            n.name
                .clone()
                .unwrap()
                .trim_end_matches(".up.resized")
                .to_string()
        })
        .collect();
    for p in resizes {
        let part = |n: &onnx::NodeProto| {
            n.name
                .as_deref()
                .is_some_and(|m| m == format!("{p}.up") || m.starts_with(&format!("{p}.up.")))
        };
        let first = g.node.iter().position(part).unwrap();
        let x = g.node[first].input[0].clone();
        let skip = g
            .node
            .iter()
            .find(|n| n.name.as_deref() == Some(format!("{p}.up.skip_hw").as_str()))
            .unwrap()
            .input[0]
            .clone();
        g.node.retain(|n| !part(n));
        let (lead, tail, sizes, up) = (
            format!("{p}.up.lead_dims"),
            format!("{p}.up.skip_hw"),
            format!("{p}.up.sizes"),
            format!("{p}.up"),
        );
        let shape = |name: &str, of: &str, s: i64, e: i64| {
            onnx::node(
                "Shape",
                name,
                &[of],
                &[name],
                vec![onnx::attr_int("start", s), onnx::attr_int("end", e)],
            )
        };
        let old_nodes = vec![
            shape(&lead, &x, 0, 3),
            shape(&tail, &skip, 3, 5),
            onnx::node(
                "Concat",
                &sizes,
                &[&lead, &tail],
                &[&sizes],
                vec![onnx::attr_int("axis", 0)],
            ),
            onnx::node(
                "Resize",
                &up,
                &[&x, "", "", &sizes],
                &[&up],
                vec![
                    onnx::attr_string("mode", "nearest"),
                    onnx::attr_string("coordinate_transformation_mode", "asymmetric"),
                    onnx::attr_string("nearest_mode", "floor"),
                ],
            ),
        ];
        let rest = g.node.split_off(first);
        g.node.extend(old_nodes);
        g.node.extend(rest);
    }
    g.initializer
        .retain(|t| t.name.as_deref() != Some("fold_lead"));
    old
}

#[test]
fn a_model_imported_before_the_fold_is_rewritten_to_a_new_import() {
    let (arch, sd) = tiny();
    let origin = Path::new("tiny.pt");
    let (mut ok, _) = arch.select_tensors(origin, sd).unwrap();
    let built = arch
        .build_model(&mut ok, &ImportOptions::default(), origin)
        .unwrap();
    let mut old = unfolded(&built.model);
    assert_ne!(old, built.model);
    assert_eq!(model::v2ce_net::fold_upsampling(&mut old), 1);
    // Node for node and byte for byte what an import writes now; a second pass finds nothing.
    let (mut a, mut b) = (Vec::new(), Vec::new());
    v2ce::model::onnx::write_model(old.clone(), &mut a).unwrap();
    v2ce::model::onnx::write_model(built.model.clone(), &mut b).unwrap();
    assert!(a == b, "the rewritten model differs from a new import");
    assert_eq!(model::v2ce_net::fold_upsampling(&mut old), 0);
}
