//! Nothing lost, nothing overwritten: an output that would replace an input or a device node
//! is refused before any work, for every command that writes a file.

mod common;

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

/// A small tmpfs mounted for a test, unmounted when dropped; `None` (with the reason) where
/// this machine does not let the test mount one (not root, or no mount privilege).
struct SmallDisk(PathBuf);

impl SmallDisk {
    fn mount(name: &str, size: &str) -> std::result::Result<SmallDisk, String> {
        let dir = temp_dir(name);
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(&dir)
            .output()
            .map_err(|e| format!("mount: {e}"))?;
        if !out.status.success() {
            return Err(format!(
                "mount -t tmpfs: {}",
                String::from_utf8_lossy(&out.stderr).trim()
            ));
        }
        Ok(SmallDisk(dir))
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The file and count in "...; FILE was closed readably with the N events ...".
fn closed_with(stderr: &str) -> Option<(PathBuf, u64)> {
    let at = stderr.find(" was closed readably with the ")?;
    let n = stderr[at..]
        .split_whitespace()
        .nth(5)
        .and_then(|n| n.parse().ok())?;
    let path = stderr[..at].rsplit("; ").next()?;
    Some((PathBuf::from(path), n))
}

/// Checks what a command that failed on the full disk `disk` said (`err`): the file it names
/// is on that disk and reads back, with our decoder and (with `py`) the independent
/// `readers`, holding exactly the count said; returns the count.
fn check_closed(
    case: &str,
    err: &str,
    disk: &Path,
    py: Option<&Path>,
    work: &Path,
    evt: Option<&str>,
    readers: &[&str],
) -> u64 {
    let (path, kept) = closed_with(err).unwrap_or_else(|| panic!("{case}: no count said: {err}"));
    assert!(path.starts_with(disk), "{case}: {}", path.display());
    assert!(kept > 0, "{case}: {err}");
    let back = v2ce::format::read_events(&path)
        .unwrap_or_else(|e| panic!("{case}: {} does not read back: {e}", path.display()));
    assert_eq!(back.events.len() as u64, kept, "{case}: {err}");
    assert!(
        !v2ce::format::journal::path_for(&path).exists(),
        "{case}: a journal left beside the closed file"
    );
    if path.extension().is_some_and(|e| e == "csv") {
        assert!(
            !std::fs::read(&path).unwrap().contains(&0),
            "{case}: zero bytes"
        );
    }
    if let Some(py) = py {
        let expected = work.join("expected.csv");
        v2ce::format::csv::write(&expected, back.events.events()).unwrap();
        let first = back.events.events().first().map_or(0, |e| e.t);
        let evt = match evt {
            Some("2") => Some(v2ce::format::raw::Evt::Evt2),
            Some("3") => Some(v2ce::format::raw::Evt::Evt3),
            _ => None,
        };
        let offset = evt.map_or(0, |evt| v2ce::format::raw::time_offset_for(evt, first));
        for reader in readers {
            let out = Command::new(py)
                .arg(common::script())
                .args(["file", reader])
                .arg(&path)
                .arg(&expected)
                .arg(offset.to_string())
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "{case}: {reader} on {}: {}{}",
                path.display(),
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
        }
    }
    println!("{case}: {} holds the {kept} events said", path.display());
    kept
}

/// A full disk (a 2 MiB tmpfs) under every command that writes events, in every format: the
/// command says it failed (exit 1; `run` names the output while its UDP output goes on) and
/// how many events the file was closed with; the file reads back with our decoder and with
/// the independent reader of its format (with the project's venv) holding exactly those. The
/// red team's file had zero bytes where a failed write was cut back (CSV unreadable, the
/// binary formats decoding fake events) and `.npz`/`.h5` were left unreadable.
#[test]
fn a_full_disk_leaves_a_readable_file_holding_what_was_reported() {
    let disk = match SmallDisk::mount("tmpfs", "2m") {
        Ok(d) => d,
        Err(why) => {
            println!("SKIPPED: a full disk needs a tmpfs this test can mount ({why})");
            return;
        }
    };
    let py = common::python();
    if py.is_none() {
        println!("SKIPPED the independent readers of the full-disk files: no Python venv");
    }
    let work = temp_dir("full-disk-work");
    let source = work.join("source.aedat4");
    let made = v2ce()
        .args(["convert", "fixture", "--max-frames", "100", "-o"])
        .arg(&source)
        .output()
        .unwrap();
    assert!(made.status.success(), "{made:?}");
    for (ext, evt, readers) in [
        ("csv", None, &["faery"][..]),
        ("raw", Some("2"), &["faery", "expelliarmus"]),
        ("raw", Some("3"), &["faery"]),
        ("aedat4", None, &["faery", "aedat", "dv"]),
        ("npz", None, &["numpy"]),
        ("h5", None, &["h5py"]),
        ("mcap", None, &["rosbags"]),
    ] {
        // The same events as a whole file of this format, for `repair --out` to copy.
        let whole = work.join(format!("whole.{ext}"));
        let mut t = v2ce();
        t.arg("transcode").arg(&source).arg(&whole).arg("--force");
        if let Some(evt) = evt {
            t.args(["--evt", evt]);
        }
        assert!(t.output().unwrap().status.success());
        let mut commands = vec!["run", "convert", "transcode"];
        // A whole .npz or .h5 copied short cannot be read: that copy is removed (and said).
        if !matches!(ext, "npz" | "h5") {
            commands.push("repair");
        }
        if matches!(ext, "csv" | "aedat4") {
            commands.push("listen");
        }
        for command in commands {
            let case = format!("{command} .{ext} {}", evt.unwrap_or(""));
            for entry in std::fs::read_dir(&disk.0).unwrap() {
                std::fs::remove_file(entry.unwrap().path()).unwrap();
            }
            let out = disk.0.join(format!("f.{ext}"));
            let mut c = v2ce();
            match command {
                "run" => {
                    let config = work.join("run.toml");
                    std::fs::write(
                        &config,
                        format!(
                            "[[sink]]\ntype = \"file\"\npath = {:?}\nevt = {}\n",
                            out.display().to_string(),
                            evt.unwrap_or("2")
                        ),
                    )
                    .unwrap();
                    c.args(["run", "--source", "fixture", "--max-frames", "100"])
                        .args(["--udp", "127.0.0.1:9", "--queue-policy", "block"])
                        .args(["--replay-speed", "8", "--config"])
                        .arg(&config);
                }
                "convert" => {
                    c.args(["convert", "fixture", "--max-frames", "100", "-o"])
                        .arg(&out);
                }
                "repair" => {
                    c.arg("repair").arg(&whole).arg("--out").arg(&out);
                }
                "listen" => {
                    let port = std::net::UdpSocket::bind("127.0.0.1:0")
                        .and_then(|s| s.local_addr())
                        .unwrap()
                        .port();
                    let address = format!("127.0.0.1:{port}");
                    c.args(["listen", "--udp", &address, "--idle", "3", "-o"])
                        .arg(&out);
                    let listener = c
                        .stdout(std::process::Stdio::piped())
                        .stderr(std::process::Stdio::piped())
                        .spawn()
                        .unwrap();
                    std::thread::sleep(std::time::Duration::from_millis(500));
                    let sent = v2ce()
                        .args(["run", "--source", "fixture", "--max-frames", "100"])
                        .args(["--queue-policy", "block", "--udp", &address])
                        .output()
                        .unwrap();
                    assert!(sent.status.success(), "{case}: {sent:?}");
                    c = Command::new("true");
                    let done = listener.wait_with_output().unwrap();
                    let err = String::from_utf8_lossy(&done.stderr).into_owned();
                    assert_eq!(done.status.code(), Some(1), "{case}: {err}");
                    check_closed(&case, &err, &disk.0, py.as_deref(), &work, evt, readers);
                    continue;
                }
                _ => {
                    c.arg("transcode").arg(&source).arg(&out);
                }
            }
            if let (Some(evt), true) = (evt, matches!(command, "convert" | "transcode")) {
                c.args(["--evt", evt]);
            }
            let done = c.output().unwrap();
            let err = String::from_utf8_lossy(&done.stderr);
            assert_eq!(done.status.code(), Some(1), "{case}: {err}");
            let kept = check_closed(&case, &err, &disk.0, py.as_deref(), &work, evt, readers);
            if command == "run" {
                assert!(err.contains("output(s) failed"), "{case}: {err}");
                // The closing line's count is the file's.
                let line = err
                    .lines()
                    .find(|l| {
                        l.contains(&format!("file {}", out.display())) && l.contains("events sent")
                    })
                    .unwrap_or_else(|| panic!("{case}: no closing line for the file: {err}"));
                assert!(
                    line.contains(&format!("): {kept} events sent")),
                    "{case}: {line}"
                );
            }
        }
    }
    std::fs::remove_dir_all(&work).unwrap();
}

/// A pacing UDP output (`udp_rate = 1`, a datagram a second for a frame's thousands) stops
/// waiting when the run reaches its `duration`: the run ends (it ran past 180 s before), the
/// datagrams it never sent counted as dropped. A hang check, far above the few seconds it takes.
#[test]
fn a_pacing_output_honours_the_duration() {
    let dir = temp_dir("pacing");
    let config = dir.join("rate.toml");
    std::fs::write(
        &config,
        "[run]\nsource = \"fixture\"\nudp = \"127.0.0.1:9\"\nudp_rate = 1\nduration = 2\n",
    )
    .unwrap();
    let mut child = v2ce()
        .args(["run", "--config"])
        .arg(&config)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let started = std::time::Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if started.elapsed() > std::time::Duration::from_secs(90) {
            let _ = child.kill();
            panic!("the paced run did not end 88 s after its duration");
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    };
    let mut err = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err).unwrap();
    assert!(status.success(), "{err}");
    assert!(err.contains("reached the time limit"), "{err}");
    let line = err
        .lines()
        .find(|l| l.contains("udp 127.0.0.1:9") && l.contains("events sent"))
        .unwrap_or("");
    assert!(line.contains("dropped"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `repair` never loses events of a whole file: a whole `.npz` or `.h5` beside another run's
/// journal stays as it is (it was replaced by the journal's 7 events), and a whole CSV whose
/// last line has no newline keeps that line (a line cut short is still cut).
#[test]
fn repair_keeps_every_event_of_a_whole_file() {
    use v2ce::event::Event;
    use v2ce::format::{self, Format};
    let dir = temp_dir("repair");
    let events: Vec<Event> = (0..3000)
        .map(|i| Event::new(1000 + i * 10, (i % 30) as u16, (i % 20) as u16, i % 3 == 0))
        .collect();
    for (name, fmt) in [("whole.npz", Format::Npz), ("whole.h5", Format::Hdf5)] {
        let path = dir.join(name);
        let mut enc = format::create(&path, fmt, 64, 48).unwrap();
        enc.write(&events).unwrap();
        enc.finish().unwrap();
        drop(enc);
        // Another run's journal of 7 records: an encoder dropped before its end leaves it.
        let other = dir.join(format!("other-{name}"));
        let mut enc = format::create(&other, fmt, 64, 48).unwrap();
        enc.write(&events[..7]).unwrap();
        enc.flush().unwrap();
        drop(enc);
        let journal = format::journal::path_for(&other);
        assert!(journal.exists(), "{name}: no journal left");
        std::fs::rename(&journal, format::journal::path_for(&path)).unwrap();
        let report = v2ce::repair::repair(&path, None).unwrap();
        assert_eq!(report.events, 3000, "{name}: {report}");
        assert_eq!(report.action, v2ce::repair::Action::Whole, "{name}");
        assert_eq!(format::read_events(&path).unwrap().events.len(), 3000);
    }
    let csv = dir.join("no-newline.csv");
    std::fs::write(&csv, "t_us,x,y,p\n1,2,3,1\n4,5,6,0\n7,8,9,1").unwrap();
    let report = v2ce::repair::repair(&csv, None).unwrap();
    assert_eq!(
        (report.events, report.action.clone()),
        (3, v2ce::repair::Action::Whole)
    );
    std::fs::write(&csv, "t_us,x,y,p\n1,2,3,1\n4,5,6,0\n7,8").unwrap();
    let report = v2ce::repair::repair(&csv, None).unwrap();
    assert_eq!(report.events, 2, "{report}");
    assert_eq!(
        std::fs::read_to_string(&csv).unwrap(),
        "t_us,x,y,p\n1,2,3,1\n4,5,6,0\n"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Sends `signal` to `child` `after_ms` after `path` appears (it is running and writing; a
/// busy machine takes longer to start), and waits for its end.
fn signal_once_writing(
    child: std::process::Child,
    path: &Path,
    after_ms: u64,
    signal: i32,
) -> std::process::Output {
    let started = std::time::Instant::now();
    while !path.exists() && started.elapsed() < std::time::Duration::from_secs(60) {
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    std::thread::sleep(std::time::Duration::from_millis(after_ms));
    // SAFETY: kill sends a signal to the child's pid.
    unsafe { libc::kill(child.id() as i32, signal) };
    child.wait_with_output().unwrap()
}

/// Every signal a daemon gets (SIGINT from a terminal, SIGTERM from systemd, SIGHUP from a
/// closed terminal or `systemctl reload`) stops `run` and `convert` cleanly with their files
/// whole: `run` exits 0 and its closing line counts what its file holds; `convert` exits 130
/// saying the input did not end, its partial file readable with the events of the frames it
/// took. SIGHUP killed both before (exit 129, files unfinished).
#[test]
fn every_signal_stops_with_its_files_whole() {
    let dir = temp_dir("signals");
    for (signal, name) in [
        (libc::SIGINT, "int"),
        (libc::SIGTERM, "term"),
        (libc::SIGHUP, "hup"),
    ] {
        for ext in ["csv", "aedat4", "npz", "h5", "mcap"] {
            let out = dir.join(format!("{name}.{ext}"));
            let case = format!("run .{ext} {name}");
            let child = v2ce()
                .args([
                    "run",
                    "--source",
                    "fixture",
                    "--loop",
                    "--udp",
                    "127.0.0.1:9",
                ])
                .args(["--queue-policy", "block", "--out"])
                .arg(&out)
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap();
            let done = signal_once_writing(child, &out, 700, signal);
            let err = String::from_utf8_lossy(&done.stderr);
            assert!(done.status.success(), "{case}: {err}");
            let line = err
                .lines()
                .find(|l| {
                    l.contains(&format!("file {}", out.display())) && l.contains("events sent")
                })
                .unwrap_or_else(|| panic!("{case}: no closing line: {err}"));
            let sent: u64 = line
                .split("): ")
                .nth(1)
                .and_then(|r| r.split_whitespace().next())
                .and_then(|n| n.parse().ok())
                .unwrap_or_else(|| panic!("{case}: {line}"));
            let back = v2ce::format::read_events(&out)
                .unwrap_or_else(|e| panic!("{case}: unreadable: {e}"));
            assert_eq!(back.events.len() as u64, sent, "{case}: {line}");
            assert!(!v2ce::format::journal::path_for(&out).exists(), "{case}");
        }
        for ext in ["npz", "h5"] {
            let out = dir.join(format!("c-{name}.{ext}"));
            let case = format!("convert .{ext} {name}");
            // Large frames on one thread, so the signal comes well before the input's end.
            let partial = dir.join(format!("c-{name}.partial.{ext}"));
            let child = v2ce()
                .env("V2CE_THREADS", "1")
                .args(["convert", "fixture", "--size", "1280x960", "-o"])
                .arg(&out)
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap();
            let done = signal_once_writing(child, &partial, 800, signal);
            let err = String::from_utf8_lossy(&done.stderr);
            assert_eq!(done.status.code(), Some(130), "{case}: {err}");
            assert!(err.contains("stopped by a signal"), "{case}: {err}");
            let back = v2ce::format::read_events(&partial)
                .unwrap_or_else(|e| panic!("{case}: unreadable: {e}"));
            assert!(!back.events.is_empty(), "{case}");
            assert!(!out.exists(), "{case}: named as if whole");
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Runs `v2ce ARGS` under an address-space limit of `kib` (as `ulimit -v`), so that memory
/// runs out at the size a test chooses; the output, which must not be an abort.
fn under_memory_limit(kib: u64, args: &[&str]) -> std::process::Output {
    let mut script = format!("ulimit -v {kib} && exec \"$0\"");
    for i in 0..args.len() {
        script.push_str(&format!(" \"${}\"", i + 1));
    }
    // Two workers and two malloc arenas whatever the machine's cores: each thread's stack and
    // arena take address space, which the limit counts.
    let out = Command::new("sh")
        .env("V2CE_THREADS", "2")
        .env("RAYON_NUM_THREADS", "2")
        .env("MALLOC_ARENA_MAX", "2")
        .arg("-c")
        .arg(&script)
        .arg(env!("CARGO_BIN_EXE_v2ce"))
        .args(args)
        .output()
        .unwrap();
    use std::os::unix::process::ExitStatusExt;
    assert!(
        out.status.signal().is_none() && out.status.code() != Some(134),
        "{args:?} aborted: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Memory budgeted where outside sizes it: a frame whose events outgrow what is left (a
/// 2048 x 2048 flash from black to white on the ideal pixel, 250 million events) is refused
/// with a clear error where the pixel model aborted in its buffers; `eval realism --fps 1e6`
/// on a recording without frames streams its reconstructed frames (it held them all: 8,000
/// frames of 346 x 260, past the limit) and completes.
#[test]
fn memory_from_outside_is_budgeted_not_aborted() {
    let dir = temp_dir("memory");
    let flash = dir.join("flash.y4m");
    let (w, h) = (2048usize, 2048usize);
    let mut y4m = format!("YUV4MPEG2 W{w} H{h} F30:1 Ip A1:1 C420jpeg\n").into_bytes();
    for v in [0u8, 255, 0] {
        y4m.extend_from_slice(b"FRAME\n");
        y4m.extend(std::iter::repeat_n(v, w * h));
        y4m.extend(std::iter::repeat_n(128u8, w * h / 2));
    }
    std::fs::write(&flash, y4m).unwrap();
    let out = dir.join("flash.csv");
    let (f, o) = (flash.to_str().unwrap(), out.to_str().unwrap());
    let done = under_memory_limit(1_500_000, &["convert", f, "-o", o, "--preset", "ideal"]);
    let err = String::from_utf8_lossy(&done.stderr);
    assert_eq!(done.status.code(), Some(1), "{err}");
    assert!(err.contains("more events than memory holds"), "{err}");

    let csv = dir.join("span.csv");
    let mut text = String::from("t_us,x,y,on\n");
    for i in 0..8000u32 {
        text.push_str(&format!(
            "{i},{},{},{}\n",
            (i * 7) % 346,
            (i * 13) % 260,
            i % 2
        ));
    }
    std::fs::write(&csv, text).unwrap();
    let c = csv.to_str().unwrap();
    let done = under_memory_limit(1_200_000, &["eval", "realism", "--real", c, "--fps", "1e6"]);
    let err = String::from_utf8_lossy(&done.stderr);
    assert!(done.status.success(), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// HDF5 files that declare sizes they do not hold (made by h5py, from the project's venv):
/// a chunk declared at 300 MB is refused before a byte of it is read (the HDF5 reader
/// allocated what the file declared); a billion events declared and a thousand written give
/// a clear error past the memory budget of a whole-file read, not an abort.
#[test]
fn hdf5_sizes_declared_from_outside_are_bounded() {
    let Some(py) = common::python() else {
        println!("SKIPPED hdf5_sizes_declared_from_outside_are_bounded: no Python venv (h5py)");
        return;
    };
    let dir = temp_dir("hdf5-sizes");
    let make = r#"
import sys, h5py, numpy as np
path, n, chunk = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
with h5py.File(path, "w") as f:
    g = f.create_group("events")
    for name, dt in [("x", "u2"), ("y", "u2"), ("t", "u4"), ("p", "u1")]:
        d = g.create_dataset(name, shape=(n,), maxshape=(None,), dtype=dt,
                             chunks=(chunk,), compression="gzip")
        d[:1000] = 0
    f.create_dataset("t_offset", data=np.int64(0))
"#;
    let big_chunk = dir.join("chunk.h5");
    let claims = dir.join("claims.h5");
    for (path, n, chunk) in [
        (&big_chunk, "1000", "150000000"),
        (&claims, "1000000000", "65536"),
    ] {
        let made = Command::new(&py)
            .args(["-c", make])
            .arg(path)
            .args([n, chunk])
            .output()
            .unwrap();
        assert!(made.status.success(), "{made:?}");
    }
    let chunk = big_chunk.to_str().unwrap();
    for args in [
        vec!["info", chunk],
        vec!["transcode", chunk, "/dev/null/never.csv"],
    ] {
        let done = under_memory_limit(1_500_000, &args);
        let err = String::from_utf8_lossy(&done.stderr);
        assert_eq!(done.status.code(), Some(1), "{args:?}: {err}");
        assert!(err.contains("declares chunks"), "{args:?}: {err}");
    }
    let c = claims.to_str().unwrap();
    let done = under_memory_limit(1_500_000, &["eval", "realism", "--real", c, "--sim", c]);
    let err = String::from_utf8_lossy(&done.stderr);
    assert_eq!(done.status.code(), Some(1), "{err}");
    assert!(err.contains("need more memory"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The red team's CSV from another tool (eventcv's header `t_us,x,y,p`) is read by `eval
/// realism --sim` (refused before: "expected 't_us,x,y,on' fields"), and the same events with
/// times in fractional seconds under `t,x,y,polarity` and columns in another order transcode
/// to the same file as the project's own CSV.
#[test]
fn csv_from_other_tools_is_read_by_its_column_names() {
    let dir = temp_dir("peer-csv");
    let ours = dir.join("ours.csv");
    let peer = dir.join("peer.csv");
    let seconds = dir.join("seconds.csv");
    let (mut a, mut b, mut c) = (
        String::from("t_us,x,y,on\n"),
        String::from("t_us,x,y,p\n"),
        String::from("polarity,y,x,t\n"),
    );
    for i in 0..3000u32 {
        let (t, x, y, on) = (1000 + i * 37, i % 64, (i * 7) % 48, i % 3 == 0);
        a.push_str(&format!("{t},{x},{y},{}\n", u8::from(on)));
        b.push_str(&format!("{t},{x},{y},{}\n", u8::from(on)));
        let p = if on { "1" } else { "-1" };
        c.push_str(&format!("{p},{y},{x},{:.6}\n", f64::from(t) / 1e6));
    }
    std::fs::write(&ours, a).unwrap();
    std::fs::write(&peer, b).unwrap();
    std::fs::write(&seconds, c).unwrap();
    let done = v2ce()
        .args(["eval", "realism", "--real"])
        .arg(&ours)
        .arg("--sim")
        .arg(&peer)
        .args(["--fps", "100"])
        .output()
        .unwrap();
    assert!(
        done.status.success(),
        "{}",
        String::from_utf8_lossy(&done.stderr)
    );
    let want = std::fs::read(&ours).unwrap();
    for input in [&peer, &seconds] {
        let out = dir.join("back.csv");
        let done = v2ce()
            .arg("transcode")
            .arg(input)
            .arg(&out)
            .args(["--size", "64x48", "--force"])
            .output()
            .unwrap();
        assert!(
            done.status.success(),
            "{}",
            String::from_utf8_lossy(&done.stderr)
        );
        assert!(std::fs::read(&out).unwrap() == want, "{}", input.display());
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
