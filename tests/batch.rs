//! `v2ce batch` on this machine: shards that together convert every input once, identical to
//! `v2ce convert`; a corrupt input recorded and reported; a shard killed with SIGKILL resumed
//! with nothing lost and nothing converted twice; the deployment files checked (the Kubernetes
//! Job against its schema). The same on a real Slurm cluster is in `tests/slurm.rs`.

mod common;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::batch::{assert_identical_to_convert, dataset, ledger, partials, text, v2ce};

#[test]
fn shards_convert_every_input_once_like_convert_and_report_the_corrupt_one() {
    let dir = common::temp_dir("batch-shards");
    dataset(&dir, 8, 64, 48, |i| 8 + 4 * i);
    for i in 0..4 {
        let shard = format!("{i}/4");
        let o = v2ce(
            &["batch", "list.txt", "--out", "out", "--shard", &shard],
            &dir,
        );
        let log = text(&o);
        // The shard with the corrupt clip says so in its exit status; the others succeed.
        if log.contains("bad.y4m") {
            assert_eq!(o.status.code(), Some(1), "{log}");
            assert!(log.contains("FAILED") && log.contains("cut short"), "{log}");
        } else {
            assert!(o.status.success(), "{log}");
        }
    }
    assert_identical_to_convert(&dir, "out", 8);
    let records = ledger(&dir, "out");
    assert_eq!(records.len(), 9, "{records:?}");
    for i in 0..8 {
        let output = format!("clips/c{i}.aedat4");
        assert_eq!(
            records
                .iter()
                .filter(|(o, s)| *o == output && s == "done")
                .count(),
            1,
            "{output}: {records:?}"
        );
    }
    assert!(records.contains(&("clips/bad.aedat4".into(), "failed".into())));
    assert!(!dir.join("out/clips/bad.aedat4").exists());

    // The merged report: exact counts, the failure with its reason, exit status 1.
    let o = v2ce(&["batch", "--report", "out", "list.txt", "--json"], &dir);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["done"], 8);
    assert_eq!(r["failed"].as_array().unwrap().len(), 1);
    assert_eq!(r["failed"][0][0], "clips/bad.y4m");
    assert!(r["failed"][0][1].as_str().unwrap().contains("cut short"));
    assert_eq!(r["pending"].as_array().unwrap().len(), 0);
    let frames: u64 = (0..8).map(|i| 8 + 4 * i as u64).sum();
    assert_eq!(r["frames"], frames);
    assert_eq!(r["shards"].as_object().unwrap().len(), 4);

    // Again: everything done is skipped, the corrupt one tried again and reported again.
    let o = v2ce(
        &["batch", "list.txt", "--out", "out", "--shard", "0/1"],
        &dir,
    );
    let log = text(&o);
    assert_eq!(o.status.code(), Some(1), "{log}");
    assert!(log.contains("8 skipped"), "{log}");
    assert_eq!(
        ledger(&dir, "out")
            .iter()
            .filter(|(_, s)| s == "done")
            .count(),
        8
    );
    // Other settings redo the item: the seed changes clip 0's output.
    let list = std::fs::read_to_string(dir.join("list.txt")).unwrap();
    std::fs::write(
        dir.join("list.txt"),
        list.replace("clips/c0.y4m\n", "clips/c0.y4m seed=9\n"),
    )
    .unwrap();
    let o = v2ce(&["batch", "list.txt", "--out", "out"], &dir);
    assert!(text(&o).contains("1 converted, 7 skipped"), "{}", text(&o));
    // A changed input is redone: same size, other content (its time changes too).
    let clip = dir.join("clips/c1.y4m");
    let mut bytes = std::fs::read(&clip).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 0x55;
    std::thread::sleep(Duration::from_millis(20));
    std::fs::write(&clip, bytes).unwrap();
    let o = v2ce(&["batch", "list.txt", "--out", "out"], &dir);
    assert!(text(&o).contains("1 converted, 7 skipped"), "{}", text(&o));
    let records = ledger(&dir, "out");
    assert_eq!(
        records
            .iter()
            .filter(|(o, s)| o == "clips/c1.aedat4" && s == "done")
            .count(),
        2
    );
}

#[test]
fn a_killed_shard_resumes_with_nothing_lost_or_converted_twice() {
    let dir = common::temp_dir("batch-kill");
    dataset(&dir, 6, 320, 240, |_| 90);
    let list = std::fs::read_to_string(dir.join("list.txt")).unwrap();
    std::fs::write(dir.join("list.txt"), list.replace("clips/bad.y4m\n", "")).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_v2ce"))
        .args(["batch", "list.txt", "--out", "out", "--jobs", "1"])
        .current_dir(&dir)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Kill it once one output is complete and the next one is being written.
    let started = Instant::now();
    loop {
        let done = ledger_or_empty(&dir).len();
        if done >= 1 && !partials(&dir.join("out")).is_empty() {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "no progress to interrupt"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    unsafe { libc::kill(child.id() as i32, libc::SIGKILL) };
    child.wait().unwrap();
    let before = ledger(&dir, "out");
    assert!(!before.is_empty() && before.len() < 6, "{before:?}");
    // What is under a final name is complete: each is in the ledger as done.
    for i in 0..6 {
        let name = format!("clips/c{i}.aedat4");
        if dir.join("out").join(&name).exists() {
            assert!(before.contains(&(name.clone(), "done".into())), "{name}");
        }
    }
    let o = v2ce(&["batch", "list.txt", "--out", "out"], &dir);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains(&format!("{} skipped", before.len())),
        "{}",
        text(&o)
    );
    assert!(partials(&dir.join("out")).is_empty());
    let after = ledger(&dir, "out");
    for i in 0..6 {
        let name = format!("clips/c{i}.aedat4");
        assert_eq!(
            after.iter().filter(|(o, _)| *o == name).count(),
            1,
            "{name}: {after:?}"
        );
    }
    assert_identical_to_convert(&dir, "out", 6);
}

fn ledger_or_empty(dir: &Path) -> Vec<(String, String)> {
    if dir.join("out/.v2ce-batch").exists() {
        ledger(dir, "out")
    } else {
        Vec::new()
    }
}

/// The Slurm script is valid shell with the array, CPU and requeue directives; the Kubernetes
/// Indexed Job validates against the Job schema (kubernetes-validate, strict), and a broken
/// copy does not.
#[test]
fn deployment_files_are_valid() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let sbatch = root.join("deploy/slurm/convert.sbatch");
    let o = Command::new("bash")
        .arg("-n")
        .arg(&sbatch)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let script = std::fs::read_to_string(&sbatch).unwrap();
    for directive in [
        "#SBATCH --array=",
        "#SBATCH --cpus-per-task=",
        "#SBATCH --requeue",
    ] {
        assert!(script.contains(directive), "{directive}");
    }
    let py = python_or_skip!("deployment_files_are_valid (the Kubernetes schema check)");
    let validator = py.with_file_name("kubernetes-validate");
    let job = root.join("deploy/k8s/convert-job.yaml");
    let o = Command::new(&validator)
        .arg("--strict")
        .arg(&job)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let yaml = std::fs::read_to_string(&job).unwrap();
    assert!(yaml.contains("completionMode: Indexed"));
    let dir = common::temp_dir("batch-k8s");
    let broken = dir.join("broken.yaml");
    std::fs::write(&broken, yaml.replace("parallelism:", "paralelism:")).unwrap();
    let o = Command::new(&validator)
        .arg("--strict")
        .arg(&broken)
        .output()
        .unwrap();
    assert!(!o.status.success(), "a misspelt field passed: {}", text(&o));
}

/// Two tasks of one shard never run at once: the second is refused while the first holds its
/// ledger (a requeued task would otherwise write the same partial files).
#[test]
fn one_task_per_shard_at_a_time() {
    let dir = common::temp_dir("batch-lock");
    dataset(&dir, 4, 320, 240, |_| 150);
    let mut first = Command::new(env!("CARGO_BIN_EXE_v2ce"))
        .args(["batch", "list.txt", "--out", "out", "--jobs", "1"])
        .current_dir(&dir)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let started = Instant::now();
    while partials(&dir.join("out")).is_empty() {
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "no output begun"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    let o = v2ce(&["batch", "list.txt", "--out", "out"], &dir);
    let _ = first.kill();
    first.wait().unwrap();
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("already running"), "{}", text(&o));
}

/// Outputs are checked before anything is written: one inside the ledgers' folder (as written,
/// or through a link) is refused and the ledger left whole; `x` and `./x` are one output; a
/// ledger whose last line was cut inside a character does not stop the next run from resuming.
#[test]
fn outputs_are_checked_and_a_cut_ledger_resumes() {
    let dir = common::temp_dir("batch-outputs");
    dataset(&dir, 2, 64, 48, |_| 8);
    let o = v2ce(&["batch", "list.txt", "--out", "out"], &dir);
    let log = text(&o);
    assert_eq!(o.status.code(), Some(1), "{log}");
    assert!(log.contains("2 converted"), "{log}");
    let ledger_file = dir.join("out/.v2ce-batch/shard-0-of-1.jsonl");
    let before = std::fs::read(&ledger_file).unwrap();
    std::os::unix::fs::symlink(".v2ce-batch", dir.join("out/link")).unwrap();
    for (list, expect) in [
        (
            "clips/c0.y4m output=./.v2ce-batch/shard-0-of-1.jsonl\n",
            "folder the batch keeps for its ledgers",
        ),
        (
            "clips/c0.y4m output=link/shard-0-of-1.jsonl\n",
            "folder of the batch's ledgers",
        ),
        (
            "clips/c0.y4m output=x.aedat4\nclips/c1.y4m output=./x.aedat4\n",
            "would both write",
        ),
        (
            "clips/c0.y4m output=x.aedat4\nclips/c1.y4m output=d/../x.aedat4\n",
            "would both write",
        ),
    ] {
        std::fs::write(dir.join("bad.txt"), list).unwrap();
        let o = v2ce(&["batch", "bad.txt", "--out", "out"], &dir);
        let log = text(&o);
        assert_eq!(o.status.code(), Some(1), "{list}: {log}");
        assert!(log.contains(expect), "{list}: {log}");
        assert_eq!(std::fs::read(&ledger_file).unwrap(), before, "{list}");
    }
    // A task killed while writing a record with an 'é': the line is cut inside it.
    let mut cut = before.clone();
    cut.extend_from_slice(b"{\"input\": \"clips/caf\xc3");
    std::fs::write(&ledger_file, &cut).unwrap();
    let o = v2ce(&["batch", "list.txt", "--out", "out"], &dir);
    let log = text(&o);
    assert_eq!(o.status.code(), Some(1), "{log}");
    assert!(
        log.contains("2 skipped") && log.contains("not UTF-8"),
        "{log}"
    );
    let o = v2ce(&["batch", "--report", "out", "list.txt", "--json"], &dir);
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["done"], 2, "{}", text(&o));
    assert_eq!(r["failed"].as_array().unwrap().len(), 1);
}
