//! Byte-for-byte outputs of `convert`, `transcode` and `run --out`, held against the sha256 of
//! each output as the binary wrote it when the table was made (`tests/fixtures/golden_outputs.tsv`).
//! A refactoring must not change one byte; a deliberate change of output re-blesses the table
//! with `V2CE_BLESS_GOLDEN=1 cargo test --release --test golden_outputs` and says why in its
//! commit. Cases on the bundled fixture always run; cases on the real recordings skip with a
//! printed reason when `../shared/data` is absent.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use sha2::{Digest, Sha256};

/// One output: a name (the table's key), the command line (`{D}` is the recordings folder,
/// `{F}` the decompressed fixture video, `{O}` the output file) and the output's file name.
struct Case {
    name: &'static str,
    args: &'static str,
    output: &'static str,
    needs_data: bool,
    needs_ort: bool,
}

const fn case(name: &'static str, args: &'static str, output: &'static str) -> Case {
    Case {
        name,
        args,
        output,
        needs_data: false,
        needs_ort: false,
    }
}

const fn data_case(name: &'static str, args: &'static str, output: &'static str) -> Case {
    Case {
        name,
        args,
        output,
        needs_data: true,
        needs_ort: false,
    }
}

/// A case of the learned tier (the built-in model through ONNX Runtime, on a fixed thread
/// count so that its sums are reduced in one order).
const fn learned_case(
    name: &'static str,
    args: &'static str,
    output: &'static str,
    needs_data: bool,
) -> Case {
    Case {
        name,
        args,
        output,
        needs_data,
        needs_ort: true,
    }
}

const CASES: &[Case] = &[
    // convert: the fixture video through each output format and both Stage 1 modes.
    case("convert-fixture-aedat4", "convert {F} -o {O}", "a.aedat4"),
    case(
        "convert-fixture-evt3-voxels-ldati",
        "convert {F} -o {O} --evt 3 --mode voxels --sampler ldati --seed 3 --size 320x240 --max-frames 40",
        "a.raw",
    ),
    case(
        "convert-fixture-evt2-dvxplorer",
        "convert {F} -o {O} --preset dvxplorer --max-frames 60",
        "a.raw",
    ),
    case(
        "convert-fixture-csv-voxels-moment",
        "convert {F} -o {O} --mode voxels --sampler moment --seed 1 --max-frames 50",
        "a.csv",
    ),
    case(
        "convert-fixture-csv-voxels-spatial",
        "convert {F} -o {O} --mode voxels --seed 1 --max-frames 50",
        "a.csv",
    ),
    case(
        "convert-fixture-npz-ideal",
        "convert {F} -o {O} --preset ideal --size 160x120",
        "a.npz",
    ),
    case(
        "convert-fixture-aedat4-zstd-random",
        "convert {F} -o {O} --compression zstd --mode voxels --sampler random --seed 9 --max-frames 30",
        "a.aedat4",
    ),
    // convert --write-voxels: the voxels Stage 1 hands to Stage 2, as .npy.
    case(
        "convert-fixture-write-voxels-npy",
        "convert {F} -o {O}.csv --write-voxels {O} --mode voxels --max-frames 12",
        "a.npy",
    ),
    // convert: the real recording's APS frames and its IJRR image folder.
    data_case(
        "convert-davis346-aedat4",
        "convert {D}/davis346/davis346.aedat4 -o {O}",
        "a.aedat4",
    ),
    data_case(
        "convert-davis346-voxels-evt2",
        "convert {D}/davis346/davis346.aedat4 -o {O} --mode voxels --sampler ldati-random --seed 5",
        "a.raw",
    ),
    data_case(
        "convert-davis346-images-csv",
        "convert {D}/davis346/ijrr_export -o {O} --preset dvxplorer --seed 2",
        "a.csv",
    ),
    // transcode: every recording into every format it can be written as.
    data_case(
        "transcode-davis346-evt2",
        "transcode {D}/davis346/davis346.aedat4 {O}",
        "a.raw",
    ),
    data_case(
        "transcode-davis346-evt3",
        "transcode {D}/davis346/davis346.aedat4 {O} --evt 3",
        "a.raw",
    ),
    data_case(
        "transcode-davis346-csv",
        "transcode {D}/davis346/davis346.aedat4 {O}",
        "a.csv",
    ),
    data_case(
        "transcode-davis346-npz",
        "transcode {D}/davis346/davis346.aedat4 {O}",
        "a.npz",
    ),
    data_case(
        "transcode-davis346-aedat4-zstd-high",
        "transcode {D}/davis346/davis346.aedat4 {O} --compression zstd-high",
        "a.aedat4",
    ),
    data_case(
        "transcode-ijrr-aedat4",
        "transcode {D}/davis346/ijrr_export/events.txt {O} --size 346x260",
        "a.aedat4",
    ),
    data_case(
        "transcode-dvxplorer-evt3",
        "transcode {D}/dvxplorer/data_sample.aedat4 {O} --evt 3",
        "a.raw",
    ),
    data_case(
        "transcode-sparklers-aedat4",
        "transcode {D}/prophesee/sparklers.raw {O} --size 640x480",
        "a.aedat4",
    ),
    data_case(
        "transcode-evt2-sample-csv",
        "transcode {D}/prophesee/evt2_sample.raw {O}",
        "a.csv",
    ),
    data_case(
        "transcode-evt3-sample-evt2",
        "transcode {D}/prophesee/evt3_sample.raw {O}",
        "a.raw",
    ),
    data_case(
        "transcode-evt3-sample-aedat4-none",
        "transcode {D}/prophesee/evt3_sample.raw {O} --compression none",
        "a.aedat4",
    ),
    // run --out: the daemon's file output, lossless (block) and faster than real time. Its
    // AEDAT 4.0 files are left out: the daemon closes a packet on each one-second flush, so
    // their bytes depend on the wall clock (the events do not); the RAW, CSV and NumPy bytes
    // do not.
    case(
        "run-fixture-evt3",
        "run --source {F} --udp= --out {O} --queue-policy block --replay-speed 1000 --max-frames 90",
        "a.raw",
    ),
    case(
        "run-fixture-evt2-dvxplorer",
        "run --source {F} --udp= --out {O} --queue-policy block --replay-speed 1000 --preset dvxplorer --seed 4 --size 320x240",
        "a.raw",
    ),
    data_case(
        "run-davis346-csv",
        "run --source {D}/davis346/davis346.aedat4 --udp= --out {O} --queue-policy block --replay-speed 1000",
        "a.csv",
    ),
    data_case(
        "run-davis346-npz-ideal",
        "run --source {D}/davis346/davis346.aedat4 --udp= --out {O} --queue-policy block --replay-speed 1000 --preset ideal --seed 7",
        "a.npz",
    ),
    // The learned tier: convert and run, whole windows and overlapping ones.
    learned_case(
        "convert-fixture-learned-csv",
        "convert {F} -o {O} --stage1 learned --threads 2 --device cpu --size 320x240 --max-frames 34",
        "a.csv",
        false,
    ),
    learned_case(
        "convert-davis346-learned-evt2",
        "convert {D}/davis346/davis346.aedat4 -o {O} --stage1 learned --threads 2 --device cpu --max-frames 40",
        "a.raw",
        true,
    ),
    learned_case(
        "run-fixture-learned-stride4-csv",
        "run --source {F} --udp= --out {O} --queue-policy block --replay-speed 1000 --stage1 learned --threads 2 --device cpu --stride 4 --size 320x240 --max-frames 30",
        "a.csv",
        false,
    ),
    learned_case(
        "convert-fixture-learned-write-voxels-npy",
        "convert {F} -o {O}.csv --write-voxels {O} --stage1 learned --threads 2 --device cpu --size 160x120 --max-frames 20",
        "a.npy",
        false,
    ),
    // HDF5 (DSEC layout).
    case(
        "convert-fixture-h5",
        "convert {F} -o {O} --max-frames 40",
        "a.h5",
    ),
    data_case(
        "transcode-davis346-h5",
        "transcode {D}/davis346/davis346.aedat4 {O}",
        "a.h5",
    ),
];

/// Whether ONNX Runtime can be found; a printed reason when not, and a failure when
/// `V2CE_REQUIRE_ORT` is set (CI).
fn ort_available() -> bool {
    match v2ce::stage1::learned::runtime::find_library(None) {
        Ok(_) => true,
        Err(e) if std::env::var_os("V2CE_REQUIRE_ORT").is_some() => {
            panic!("V2CE_REQUIRE_ORT is set but: {e}")
        }
        Err(e) => {
            skipped!("SKIPPED the golden cases of the learned tier: {e}");
            false
        }
    }
}

/// The vector units ONNX Runtime's CPU kernels are chosen by: `avx512`, `avx2` or `base`.
fn cpu_class() -> &'static str {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let flags = info
        .lines()
        .find(|l| l.starts_with("flags"))
        .unwrap_or_default();
    let has = |f: &str| flags.split_whitespace().any(|x| x == f);
    if has("avx512f") {
        "avx512"
    } else if has("avx2") {
        "avx2"
    } else {
        "base"
    }
}

fn table_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/golden_outputs.tsv")
}

fn read_table() -> BTreeMap<String, String> {
    let text = std::fs::read_to_string(table_path()).unwrap_or_default();
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .filter_map(|l| {
            let (name, hash) = l.split_once('\t')?;
            Some((name.to_string(), hash.to_string()))
        })
        .collect()
}

/// Writes the table (blessing).
fn write_table(table: &BTreeMap<String, String>) {
    let mut text = String::from(
        "# sha256 of each output of tests/golden_outputs.rs, as written when blessed\n",
    );
    for (name, hash) in table {
        text.push_str(&format!("{name}\t{hash}\n"));
    }
    std::fs::write(table_path(), text).unwrap();
    eprintln!("blessed {} rows", table.len());
}

/// The bundled fixture video, decompressed to `dir/walkby.y4m`.
fn fixture_video(dir: &Path) -> PathBuf {
    let packed = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/walkby.y4m.zst");
    let bytes = zstd::decode_all(std::fs::File::open(packed).unwrap()).unwrap();
    let path = dir.join("walkby.y4m");
    std::fs::write(&path, bytes).unwrap();
    path
}

fn sha256(path: &Path) -> String {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    Sha256::digest(&bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

#[test]
fn outputs_are_byte_identical_to_the_golden_table() {
    let dir = common::temp_dir("golden");
    let fixture = fixture_video(&dir);
    let data = common::data_dir();
    if let Err(d) = &data {
        skipped!(
            "SKIPPED the golden cases on recordings: no recordings at {} (set V2CE_DATA)",
            d.display()
        );
    }
    let ort = ort_available();
    let bless = std::env::var_os("V2CE_BLESS_GOLDEN").is_some();
    let expected = read_table();
    let mut got = BTreeMap::new();
    let mut mismatches = Vec::new();
    for case in CASES {
        if case.needs_ort && !ort {
            continue;
        }
        let data_dir = match (&data, case.needs_data) {
            (Ok(d), _) => d.display().to_string(),
            (Err(_), true) => continue,
            (Err(_), false) => String::new(),
        };
        let out_dir = dir.join(case.name);
        std::fs::create_dir_all(&out_dir).unwrap();
        let output = out_dir.join(case.output);
        let args: Vec<String> = case
            .args
            .split_whitespace()
            .map(|a| {
                a.replace("{D}", &data_dir)
                    .replace("{F}", &fixture.display().to_string())
                    .replace("{O}", &output.display().to_string())
            })
            .collect();
        let run = Command::new(env!("CARGO_BIN_EXE_v2ce"))
            .args(&args)
            .env("V2CE_LOG", "warn")
            .output()
            .unwrap();
        assert!(
            run.status.success(),
            "{}: v2ce {}: {}",
            case.name,
            args.join(" "),
            String::from_utf8_lossy(&run.stderr)
        );
        let hash = sha256(&output);
        // ONNX Runtime picks its kernels by the CPU's vector units, and another kernel sums
        // in another order: the learned tier's rows are per CPU class.
        let name = if case.needs_ort {
            format!("{}@{}", case.name, cpu_class())
        } else {
            case.name.to_string()
        };
        eprintln!("{name}\t{hash}");
        match expected.get(&name) {
            Some(h) if *h == hash => {}
            Some(h) => mismatches.push(format!("{name}: expected {h}, got {hash}")),
            None if bless => {}
            None if case.needs_ort => skipped!(
                "SKIPPED {name}: no row for the learned tier on a {} CPU (bless one on such a \
                 machine from a commit whose outputs are known good)",
                cpu_class()
            ),
            None => mismatches.push(format!("{name}: not in the table")),
        }
        got.insert(name, hash);
    }
    if bless {
        // The other test blesses its rows at the same time: read the table again.
        let mut table = read_table();
        table.extend(got);
        write_table(&table);
        return;
    }
    assert!(
        mismatches.is_empty(),
        "outputs changed:\n{}",
        mismatches.join("\n")
    );
}

/// Every command's `--help`, the interface its flags form: held to the table as the outputs are.
#[test]
fn help_texts_are_unchanged() {
    const COMMANDS: &[&str] = &[
        "",
        "run",
        "devices",
        "bench",
        "bench tradeoff",
        "convert",
        "transcode",
        "info",
        "repair",
        "eval",
        "eval stage1",
        "eval stage2",
        "eval realism",
        "listen",
        "render",
        "reconstruct",
        "model",
        "model import",
        "model run",
        "model bench",
        "calibrate",
        "dataset",
        "dataset synthetic",
        "dataset recording",
        "batch",
    ];
    let bless = std::env::var_os("V2CE_BLESS_GOLDEN").is_some();
    let mut table = read_table();
    let mut mismatches = Vec::new();
    for command in COMMANDS {
        let out = Command::new(env!("CARGO_BIN_EXE_v2ce"))
            .args(command.split_whitespace())
            .arg("--help")
            .output()
            .unwrap();
        assert!(out.status.success(), "v2ce {command} --help failed");
        let hash: String = Sha256::digest(&out.stdout)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        let name = format!("help {command}").trim_end().replace(' ', "-");
        match table.get(&name) {
            Some(h) if *h == hash => {}
            _ if bless => {}
            Some(h) => mismatches.push(format!("{name}: expected {h}, got {hash}")),
            None => mismatches.push(format!("{name}: not in the table")),
        }
        table.insert(name, hash);
    }
    if bless {
        write_table(&table);
        return;
    }
    assert!(
        mismatches.is_empty(),
        "help texts changed:\n{}",
        mismatches.join("\n")
    );
}
