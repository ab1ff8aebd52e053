//! The trainer (`train/`): its smoke test (a tiny dataset, the same loss curve from the same
//! seed, an export through `v2ce model import`, PyTorch against ONNX Runtime) runs where the
//! trainer's venv has PyTorch, and says it skipped otherwise (the script checks).

use std::path::Path;
use std::process::Command;

#[test]
fn the_trainer_reproduces_its_loss_curve_and_exports_what_it_trained() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = Command::new("bash")
        .arg(root.join("train/smoke_test.sh"))
        .env("V2CE_BIN", env!("CARGO_BIN_EXE_v2ce"))
        .output()
        .expect("run train/smoke_test.sh");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "train/smoke_test.sh failed:\n{stdout}\n{stderr}"
    );
    let last = stdout.lines().last().unwrap_or("");
    assert!(
        last.starts_with("SKIPPED") || last == "train smoke test: ok",
        "{stdout}"
    );
    eprintln!("{last}");
}
