//! Helpers of the `v2ce batch` tests (`tests/batch.rs`, `tests/slurm.rs`): a small dataset,
//! and checks of what a batch wrote.

use std::path::Path;
use std::process::{Command, Output};

/// Writes `n` Y4M clips of different lengths (`frames(i)` frames of `w x h`), a corrupt one,
/// and `list.txt` naming them all (clip 3 with its own seed).
pub fn dataset(dir: &Path, n: usize, w: usize, h: usize, frames: impl Fn(usize) -> usize) {
    std::fs::create_dir_all(dir.join("clips")).unwrap();
    let mut list = String::from("# a test dataset\n");
    for i in 0..n {
        let mut v = format!("YUV4MPEG2 W{w} H{h} F30:1 Cmono\n").into_bytes();
        for k in 0..frames(i) {
            v.extend_from_slice(b"FRAME\n");
            v.extend((0..w * h).map(|p| ((p % w + 3 * k + 7 * i) % 200 + 20) as u8));
        }
        std::fs::write(dir.join(format!("clips/c{i}.y4m")), v).unwrap();
        list.push_str(&format!(
            "clips/c{i}.y4m{}\n",
            if i == 3 { " seed=7" } else { "" }
        ));
    }
    std::fs::write(
        dir.join("clips/bad.y4m"),
        b"YUV4MPEG2 W64 H48 F30:1 Cmono\nFRAME\nnot a frame",
    )
    .unwrap();
    list.push_str("clips/bad.y4m\n");
    std::fs::write(dir.join("list.txt"), list).unwrap();
}

pub fn v2ce(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_v2ce"))
        .args(args)
        .current_dir(dir)
        .output()
        .unwrap()
}

pub fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// Every good clip's output equals `v2ce convert` of it with the same settings.
pub fn assert_identical_to_convert(dir: &Path, out: &str, n: usize) {
    for i in 0..n {
        let clip = format!("clips/c{i}.y4m");
        let reference = format!("ref{i}.aedat4");
        let mut args = vec![
            "convert",
            clip.as_str(),
            "-o",
            reference.as_str(),
            "--force",
        ];
        if i == 3 {
            args.extend(["--seed", "7"]);
        }
        let o = v2ce(&args, dir);
        assert!(o.status.success(), "{}", text(&o));
        let want = std::fs::read(dir.join(&reference)).unwrap();
        let got = std::fs::read(dir.join(out).join(format!("clips/c{i}.aedat4")))
            .unwrap_or_else(|e| panic!("{out}/clips/c{i}.aedat4: {e}"));
        assert!(
            got == want,
            "{out}/clips/c{i}.aedat4 differs from convert's"
        );
    }
}

/// The ledger records of `out`: (output, status) per line.
pub fn ledger(dir: &Path, out: &str) -> Vec<(String, String)> {
    let mut records = Vec::new();
    for e in std::fs::read_dir(dir.join(out).join(".v2ce-batch")).unwrap() {
        let text = std::fs::read_to_string(e.unwrap().path()).unwrap();
        for line in text.lines() {
            let v: serde_json::Value = serde_json::from_str(line).unwrap();
            records.push((
                v["output"].as_str().unwrap().to_string(),
                v["status"].as_str().unwrap().to_string(),
            ));
        }
    }
    records
}

/// Files under `dir` whose name contains `.partial.` (none when `dir` is absent).
pub fn partials(dir: &Path) -> Vec<String> {
    let mut found = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.to_string_lossy().contains(".partial.") {
                found.push(p.display().to_string());
            }
        }
    }
    found
}
