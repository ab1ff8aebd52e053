//! Nothing lost, nothing overwritten: an output that would replace an input or a device node
//! is refused before any work, for every command that writes a file.

use std::path::{Path, PathBuf};
use std::process::Command;

fn v2ce() -> Command {
    Command::new(env!("CARGO_BIN_EXE_v2ce"))
}

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("v2ce-lost-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A small event file in the project's CSV.
fn events_csv(path: &Path) {
    let mut text = String::from("t_us,x,y,on\n");
    for i in 0..200u32 {
        text.push_str(&format!(
            "{},{},{},{}\n",
            1000 + i * 50,
            i % 30,
            i % 20,
            i % 2
        ));
    }
    std::fs::write(path, text).unwrap();
}

/// Runs `v2ce ARGS`, which must fail with one error line naming `why`.
fn refused(args: &[&std::ffi::OsStr], why: &str) {
    let out = v2ce().args(args).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{args:?}: {stderr}");
    assert!(stderr.contains(why), "{args:?}: {stderr}");
}

#[test]
fn an_output_never_replaces_an_input_or_a_device() {
    let dir = temp_dir("inputs");
    let real = dir.join("v.csv");
    events_csv(&real);
    let sim = dir.join("s.csv");
    events_csv(&sim);
    let before = std::fs::read(&real).unwrap();
    let link = dir.join("link.toml");
    #[cfg(unix)]
    std::os::unix::fs::symlink(&real, &link).unwrap();
    let os = |s: &str| std::ffi::OsString::from(s);
    let p = |p: &Path| p.as_os_str().to_os_string();
    let cases: Vec<(Vec<std::ffi::OsString>, &str)> = vec![
        // The red team's reproduction: the recording replaced by a 1 KB preset, exit 0.
        (
            vec![
                os("calibrate"),
                os("--real"),
                p(&real),
                os("-o"),
                p(&real),
                os("--force"),
            ],
            "is an input",
        ),
        (
            vec![
                os("calibrate"),
                os("--real"),
                p(&real),
                os("-o"),
                p(&link),
                os("--force"),
            ],
            "is an input",
        ),
        (
            vec![
                os("eval"),
                os("realism"),
                os("--real"),
                p(&real),
                os("--sim"),
                p(&sim),
                os("--fps"),
                os("100"),
                os("--plot"),
                p(&sim),
                os("--force"),
            ],
            "is an input",
        ),
        (
            vec![
                os("eval"),
                os("stage2"),
                os("--events"),
                p(&real),
                os("--fps"),
                os("100"),
                os("--write-events"),
                p(&real),
                os("--force"),
            ],
            "is an input",
        ),
        (
            vec![
                os("transcode"),
                p(&real),
                p(&dir.join("./v.csv")),
                os("--force"),
            ],
            "is an input",
        ),
        (
            vec![
                os("render"),
                p(&real),
                os("--output"),
                p(&real),
                os("--force"),
            ],
            "is an input",
        ),
        (
            vec![os("transcode"), p(&real), os("/dev/null"), os("--force")],
            "device",
        ),
        (
            vec![os("transcode"), p(&real), p(&dir), os("--force")],
            "directory",
        ),
        (vec![os("transcode"), p(&real), p(&sim)], "--force"),
    ];
    for (args, why) in &cases {
        let args: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
        refused(&args, why);
    }
    assert_eq!(std::fs::read(&real).unwrap(), before, "an input changed");
    assert!(Path::new("/dev/null").exists());
    // Nothing was left under a partial name either.
    let names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(names.iter().all(|n| !n.contains("partial")), "{names:?}");
    let _ = std::fs::remove_dir_all(&dir);
}
