//! The command line against hostile input: generated cases for every command that reads a file
//! or a flag (truncated and mutated event files and videos, absurd headers, extreme numbers in
//! flags and config keys), each run as its own process under a memory cap (address space) and a
//! time limit. Every case must end in a valid output (exit 0; a written event file reads back)
//! or one error line (exit 1): no panic, no abort, no other signal, no hang, bounded memory.
//!
//! The cases are deterministic (a fixed seed); the count and the outcome are printed, and the
//! README's testing section quotes them.

mod common;

use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use v2ce::event::Event;
use v2ce::format::{self, Compression, Format};

/// Address space allowed to each run.
const MEMORY_CAP: u64 = 3 << 30;
/// Peak resident memory allowed to each run.
const MAX_RSS_KIB: i64 = 2 << 20;
/// Wall-clock limit of each run (generous: the cases share two cores).
const TIME_LIMIT: Duration = Duration::from_secs(60);
/// How long a run past the time limit may take to stop on one SIGTERM.
const STOP_BUDGET: Duration = Duration::from_secs(5);

/// One generated case: a command line run in `dir`, and the output file to read back when it
/// succeeds.
struct Case {
    name: String,
    args: Vec<String>,
    check_output: Option<String>,
}

/// How a run ended.
struct Outcome {
    code: Option<i32>,
    signal: Option<i32>,
    timed_out: bool,
    /// After the time limit: whether the run ignored one SIGTERM for `STOP_BUDGET`.
    ignored_sigterm: Option<bool>,
    max_rss_kib: i64,
    stderr: String,
    seconds: f64,
}

/// Runs v2ce with `args` in `dir` under the memory cap and the time limit. The peak RSS is the
/// child's from `wait4`, which includes this process's pages shared at the fork (a few MiB).
fn run_capped(args: &[String], dir: &Path, tag: &str) -> Outcome {
    use std::os::unix::process::CommandExt;
    let err_path = dir.join(format!("{tag}.stderr"));
    let err_file = std::fs::File::create(&err_path).unwrap();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_v2ce"));
    cmd.args(args)
        .current_dir(dir)
        .env_remove("V2CE_LOG")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(err_file);
    unsafe {
        cmd.pre_exec(|| {
            let cap = libc::rlimit {
                rlim_cur: MEMORY_CAP,
                rlim_max: MEMORY_CAP,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &cap) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let started = Instant::now();
    let child = cmd.spawn().unwrap();
    let pid = child.id() as libc::pid_t;
    let mut status = 0;
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    let mut timed_out = false;
    let mut ignored_sigterm = None;
    loop {
        let r = unsafe { libc::wait4(pid, &mut status, libc::WNOHANG, &mut usage) };
        if r == pid {
            break;
        }
        assert!(r == 0, "wait4: {}", std::io::Error::last_os_error());
        if started.elapsed() > TIME_LIMIT {
            timed_out = true;
            // One SIGTERM first: a run that hangs must still stop on it (its stop budget).
            unsafe { libc::kill(pid, libc::SIGTERM) };
            let asked = Instant::now();
            while asked.elapsed() < STOP_BUDGET {
                if unsafe { libc::wait4(pid, &mut status, libc::WNOHANG, &mut usage) } == pid {
                    ignored_sigterm = Some(false);
                    break;
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            if ignored_sigterm.is_some() {
                break;
            }
            ignored_sigterm = Some(true);
            unsafe { libc::kill(pid, libc::SIGKILL) };
            let r = unsafe { libc::wait4(pid, &mut status, 0, &mut usage) };
            assert_eq!(r, pid);
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    // The child was reaped by wait4: std must not wait for it again.
    std::mem::forget(child);
    let (code, signal) = if libc::WIFEXITED(status) {
        (Some(libc::WEXITSTATUS(status)), None)
    } else {
        (None, Some(libc::WTERMSIG(status)))
    };
    Outcome {
        code,
        signal,
        timed_out,
        ignored_sigterm,
        max_rss_kib: usage.ru_maxrss,
        stderr: std::fs::read_to_string(&err_path).unwrap_or_default(),
        seconds: started.elapsed().as_secs_f64(),
    }
}

/// What is wrong with an outcome, if anything.
fn judge(case: &Case, o: &Outcome, dir: &Path) -> Option<String> {
    if o.timed_out {
        let term = match o.ignored_sigterm {
            Some(true) => format!("; one SIGTERM ignored for {STOP_BUDGET:?}"),
            _ => "; stopped on one SIGTERM".to_string(),
        };
        return Some(format!("no exit within {TIME_LIMIT:?}{term}"));
    }
    if let Some(sig) = o.signal {
        return Some(format!("killed by signal {sig}"));
    }
    if o.max_rss_kib > MAX_RSS_KIB {
        return Some(format!("peak RSS {} MiB", o.max_rss_kib / 1024));
    }
    if o.stderr.contains("panicked") {
        return Some("panicked".into());
    }
    match o.code {
        Some(0) => {
            let out = case.check_output.as_ref()?;
            let back = Command::new(env!("CARGO_BIN_EXE_v2ce"))
                .args(["info", out])
                .current_dir(dir)
                .output()
                .unwrap();
            (!back.status.success()).then(|| {
                format!(
                    "exit 0, but its output does not read: {}",
                    String::from_utf8_lossy(&back.stderr).trim()
                )
            })
        }
        Some(1) => {
            let errors: Vec<&str> = o.stderr.lines().filter(|l| l.contains("error")).collect();
            if errors.len() != 1 || !errors[0].starts_with("v2ce: error: ") {
                Some(format!("exit 1 without one error line: {:?}", errors))
            } else {
                None
            }
        }
        // A command line clap cannot parse: its usage error, status 2.
        Some(2) if o.stderr.starts_with("error: ") => None,
        other => Some(format!("exit status {other:?}")),
    }
}

/// A tiny deterministic generator.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0 >> 16
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// Mutations of `data`: truncations at fixed and random places, then byte flips, overwrites
/// with extreme bytes, insertions and deletions.
fn mutations(data: &[u8], rng: &mut Rng, count: usize) -> Vec<(String, Vec<u8>)> {
    let n = data.len();
    let mut out = Vec::new();
    let mut cuts = vec![0, 1, 7, 16, 40, 100, 300, n / 4, n / 2, n - 1, n - 3];
    cuts.extend((0..5).map(|_| rng.below(n)));
    for cut in cuts.into_iter().filter(|&c| c < n) {
        out.push((format!("cut{cut}"), data[..cut].to_vec()));
    }
    for i in 0..count {
        let mut d = data.to_vec();
        let kind = i % 4;
        for _ in 0..1 + rng.below(8) {
            let at = rng.below(d.len());
            match kind {
                0 => d[at] ^= 1 << rng.below(8),
                1 => d[at] = [0x00, 0xff, 0x7f, 0x80][rng.below(4)],
                2 => {
                    let fill = [0xffu8, 0x00, 0x7f][rng.below(3)];
                    d.splice(at..at, std::iter::repeat_n(fill, 1 + rng.below(8)));
                }
                _ => {
                    let end = (at + 1 + rng.below(16)).min(d.len());
                    d.drain(at..end);
                }
            }
            if d.is_empty() {
                break;
            }
        }
        out.push((format!("mut{i}"), d));
    }
    out
}

/// `.h5` files made from a clean one (see the call in [`cases`]); returns their names.
fn forged_h5(dir: &Path, events: &[Event]) -> Vec<String> {
    let clean = dir.join("forge-clean.h5");
    write_events(&clean, Format::Hdf5, events);
    let data = std::fs::read(&clean).unwrap();
    let mut files = Vec::new();
    let mut save = |tag: String, bytes: Vec<u8>| {
        let name = format!("forged-{tag}.h5");
        std::fs::write(dir.join(&name), bytes).unwrap();
        files.push(name);
    };
    let n = data.len();
    for k in 1..64 {
        save(format!("cut{k}"), data[..n * k / 64].to_vec());
    }
    let count = events.len() as u64;
    let fields: [(&str, u64, usize); 4] = [
        ("count64", count, 8),
        ("count32", count, 4),
        ("chunk64", 1 << 16, 8),
        ("chunk32", 1 << 16, 4),
    ];
    for (what, value, width) in fields {
        let word = &value.to_le_bytes()[..width];
        let places: Vec<usize> = (0..n.saturating_sub(width))
            .filter(|&i| &data[i..i + width] == word)
            .take(12)
            .collect();
        for &at in &places {
            for (j, absurd) in [0u64, 1, 1 << 31, 1 << 40, 1 << 62, u64::MAX]
                .into_iter()
                .enumerate()
            {
                let mut d = data.clone();
                d[at..at + width].copy_from_slice(&absurd.to_le_bytes()[..width]);
                save(format!("{what}-{at}-{j}"), d);
            }
        }
    }
    files
}

/// A short recording: a bar sweeping a 64 x 48 sensor, with a Unix-epoch start.
fn events() -> Vec<Event> {
    let rec = v2ce::sweeping_bar::recording(64, 48, 200_000, 2);
    rec.events
        .events()
        .iter()
        .map(|e| Event::new(e.t + 1_700_000_000_000_000, e.x, e.y, e.on))
        .collect()
}

fn write_events(path: &Path, format: Format, events: &[Event]) {
    let mut enc = format::create(path, format, 64, 48).unwrap();
    for chunk in events.chunks(1000) {
        enc.write(chunk).unwrap();
    }
    enc.finish().unwrap();
}

fn y4m(w: usize, h: usize, frames: usize) -> Vec<u8> {
    let mut v = format!("YUV4MPEG2 W{w} H{h} F30:1 Cmono\n").into_bytes();
    for i in 0..frames {
        v.extend_from_slice(b"FRAME\n");
        v.extend((0..w * h).map(|p| ((p % w + 5 * i) % 200 + 20) as u8));
    }
    v
}

fn strings(v: &[&str]) -> Vec<String> {
    v.iter().map(|s| s.to_string()).collect()
}

/// Numbers no flag or key should take without a clear answer.
const EXTREMES: [&str; 12] = [
    "0",
    "-1",
    "nan",
    "inf",
    "-inf",
    "1e308",
    "1e-300",
    "18446744073709551616",
    "-9223372036854775809",
    "",
    "abc",
    "4294967297",
];

/// TOML values for config keys.
const TOML_EXTREMES: [&str; 9] = [
    "0",
    "-1",
    "nan",
    "inf",
    "-inf",
    "1e308",
    "1e-300",
    "9223372036854775807",
    "-9223372036854775808",
];

/// Every case: inputs are written into `dir`.
fn cases(dir: &Path) -> Vec<Case> {
    let mut rng = Rng(0x0bad_5eed);
    let mut cases = Vec::new();
    let evs = events();

    // Event files of every format, each mutated, through info, transcode and render.
    let formats = [
        ("e.aedat4", Format::Aedat4(Compression::Lz4), 40),
        ("ez.aedat4", Format::Aedat4(Compression::Zstd), 20),
        ("en.aedat4", Format::Aedat4(Compression::None), 20),
        ("e2.raw", Format::Evt2, 30),
        ("e3.raw", Format::Evt3, 30),
        ("e.csv", Format::Csv, 25),
        ("e.npz", Format::Npz, 20),
        ("e.h5", Format::Hdf5, 15),
    ];
    let mut event_inputs = Vec::new();
    for (name, fmt, count) in formats {
        let clean = dir.join(format!("clean-{name}"));
        write_events(&clean, fmt, &evs);
        let data = std::fs::read(&clean).unwrap();
        for (tag, bytes) in mutations(&data, &mut rng, count) {
            let file = format!("{tag}-{name}");
            std::fs::write(dir.join(&file), bytes).unwrap();
            event_inputs.push(file);
        }
    }
    // HDF5 forged where it says how much there is: every place the clean file holds the event
    // count (a dataset's dimensions) or the chunk length as a little-endian word, set to
    // absurd sizes; and cut at every 64th of its length.
    event_inputs.extend(forged_h5(dir, &evs));
    // IJRR text and CSV with extreme numbers and absurd lines.
    let texts = [
        ("x1.csv", "t_us,x,y,on\n0,65535,65535,1\n"),
        (
            "x2.csv",
            "t_us,x,y,on\n-9223372036854775808,0,0,1\n9223372036854775807,1,1,0\n",
        ),
        ("x3.csv", "t_us,x,y,on\n10,1,1,1\n5,1,1,1\n"),
        ("x4.csv", "t_us,x,y,on\n0,1,1,2\n"),
        ("x5.csv", "t_us,x,y,on\n1e3,1,1,1\n"),
        ("x6.csv", "t_us,x,y,on\n0,-1,1,1\n"),
        ("x1.txt", "0.000001 1 2 1\n1e300 1 2 0\n"),
        ("x2.txt", "nan 1 2 1\n"),
        ("x3.txt", "0.1 65535 65535 -1\n9223372036854.775807 0 0 1\n"),
        (
            "x1.raw",
            "% evt 2.0\n% geometry 65535x65535\n% end\n\u{0}\u{0}\u{0}\u{10}",
        ),
        (
            "x2.raw",
            "% evt 3.0\n% geometry 0x0\n% v2ce_time_offset_us 9223372036854775807\n% end\n",
        ),
        ("x3.raw", "% evt 7.0\n% end\n"),
        (
            "x4.raw",
            "% evt 2.0\n% v2ce_time_offset_us -9223372036854775808\n% end\n\u{ff}\u{ff}\u{ff}\u{8f}",
        ),
    ];
    let mut long_header = "% evt 2.0\n".repeat(200_000);
    long_header.push_str("% end\n");
    std::fs::write(dir.join("x5.raw"), long_header).unwrap();
    event_inputs.push("x5.raw".into());
    for (name, text) in texts {
        std::fs::write(dir.join(name), text).unwrap();
        event_inputs.push(name.into());
    }
    for (i, input) in event_inputs.iter().enumerate() {
        cases.push(Case {
            name: format!("info {input}"),
            args: strings(&["info", input]),
            check_output: None,
        });
        let out = format!("out{i}.aedat4");
        cases.push(Case {
            name: format!("transcode {input}"),
            args: strings(&["transcode", input, &out]),
            check_output: Some(out),
        });
        if i % 3 == 0 {
            let out = format!("out{i}.raw");
            cases.push(Case {
                name: format!("transcode {input} to EVT 3.0"),
                args: strings(&["transcode", "--evt", "3", input, &out]),
                check_output: Some(out),
            });
        }
        if i % 4 == 0 {
            cases.push(Case {
                name: format!("render {input}"),
                args: strings(&["render", input, "-o", &format!("r{i}.png")]),
                check_output: None,
            });
            cases.push(Case {
                name: format!("eval stage2 {input}"),
                args: strings(&["eval", "stage2", "--events", input, "--fps", "100"]),
                check_output: None,
            });
        }
    }

    // Videos: mutated Y4M, and absurd Y4M headers, through convert.
    let video = y4m(64, 48, 8);
    let mut videos = Vec::new();
    for (tag, bytes) in mutations(&video, &mut rng, 30) {
        let file = format!("{tag}.y4m");
        std::fs::write(dir.join(&file), bytes).unwrap();
        videos.push(file);
    }
    for (i, header) in [
        "YUV4MPEG2 W16000 H16000 F30:1 Cmono\nFRAME\n",
        "YUV4MPEG2 W0 H0 F30:1 Cmono\nFRAME\n",
        "YUV4MPEG2 W64 H48 F4000000000:1 Cmono\n",
        "YUV4MPEG2 W64 H48 F0:0 Cmono\n",
        "YUV4MPEG2 W64 H48 F1:4000000000 Cmono\n",
        "YUV4MPEG2 W4294967295 H2 F30:1 Cmono\n",
        "YUV4MPEG2 W64 H48 F30:1 C444\n",
        "YUV4MPEG2 W64 H48 F30:1 Cmono XYSCSS=bogus\n",
    ]
    .iter()
    .enumerate()
    {
        let mut bytes = header.as_bytes().to_vec();
        if !header.contains("FRAME") {
            bytes.extend_from_slice(&video[video.iter().position(|&b| b == b'\n').unwrap() + 1..]);
        }
        let file = format!("h{i}.y4m");
        std::fs::write(dir.join(&file), bytes).unwrap();
        videos.push(file);
    }
    // The largest frame allowed, 8192 x 8192: more than the memory cap lets the pixel model
    // take, which must be found before allocating.
    let mut big = b"YUV4MPEG2 W8192 H8192 F30:1 Cmono\nFRAME\n".to_vec();
    big.resize(big.len() + 8192 * 8192, 100);
    std::fs::write(dir.join("big.y4m"), big).unwrap();
    videos.push("big.y4m".into());
    for (i, v) in videos.iter().enumerate() {
        let out = format!("v{i}.csv");
        cases.push(Case {
            name: format!("convert {v}"),
            args: strings(&["convert", v, "-o", &out]),
            check_output: Some(out),
        });
    }
    // Not a video at all, a folder named like an event file, a missing file.
    std::fs::create_dir_all(dir.join("folder.aedat4")).unwrap();
    std::fs::write(dir.join("garbage.mp4"), b"\x00\x00\x00\x18ftypmp42garbage").unwrap();
    for (i, input) in ["garbage.mp4", "folder.aedat4", "missing.y4m"]
        .iter()
        .enumerate()
    {
        cases.push(Case {
            name: format!("convert {input}"),
            args: strings(&["convert", input, "-o", &format!("g{i}.csv")]),
            check_output: None,
        });
        cases.push(Case {
            name: format!("info {input}"),
            args: strings(&["info", input]),
            check_output: None,
        });
    }

    // Extreme numbers in every numeric flag.
    let flags: Vec<(&str, Vec<&str>)> = vec![
        (
            "--fps",
            vec!["convert", "fixture", "--max-frames", "3", "-o", "f.csv"],
        ),
        (
            "--size",
            vec!["convert", "fixture", "--max-frames", "3", "-o", "f.csv"],
        ),
        ("--max-frames", vec!["convert", "clean.y4m", "-o", "f.csv"]),
        (
            "--seed",
            vec!["convert", "clean.y4m", "--max-frames", "3", "-o", "f.csv"],
        ),
        (
            "--budget-fps",
            vec!["convert", "clean.y4m", "--max-frames", "3", "-o", "f.csv"],
        ),
        (
            "--evt",
            vec!["convert", "clean.y4m", "--max-frames", "3", "-o", "f.raw"],
        ),
        ("--fps", vec!["render", "clean-e.csv", "-o", "f.gif"]),
        ("--decay-ms", vec!["render", "clean-e.csv", "-o", "f.png"]),
        ("--slowdown", vec!["render", "clean-e.csv", "-o", "f.gif"]),
        ("--size", vec!["render", "clean-e.csv", "-o", "f.png"]),
        ("--size", vec!["transcode", "clean-e.csv", "f.aedat4"]),
        ("--fps", vec!["eval", "stage2", "--events", "clean-e.csv"]),
        (
            "--duration",
            vec![
                "run",
                "--source",
                "fixture",
                "--out",
                "r.csv",
                "--max-frames",
                "3",
            ],
        ),
        (
            "--stats-interval",
            vec![
                "run",
                "--source",
                "fixture",
                "--out",
                "r.csv",
                "--max-frames",
                "3",
            ],
        ),
        (
            "--replay-speed",
            vec![
                "run",
                "--source",
                "fixture",
                "--out",
                "r.csv",
                "--max-frames",
                "3",
            ],
        ),
        (
            "--max-frames",
            vec![
                "run",
                "--source",
                "fixture",
                "--out",
                "r.csv",
                "--duration",
                "1",
            ],
        ),
        (
            "--size",
            vec![
                "run",
                "--source",
                "fixture",
                "--out",
                "r.csv",
                "--max-frames",
                "3",
            ],
        ),
        (
            "--udp-payload",
            vec!["run", "--source", "fixture", "--max-frames", "3"],
        ),
        (
            "--ready-timeout",
            vec![
                "run",
                "--source",
                "fixture",
                "--out",
                "r.csv",
                "--max-frames",
                "3",
            ],
        ),
        (
            "--http",
            vec![
                "run",
                "--source",
                "fixture",
                "--out",
                "r.csv",
                "--max-frames",
                "3",
            ],
        ),
        (
            "--emit-delay-ms",
            vec!["run", "--source", "fixture", "--max-frames", "3"],
        ),
        ("--seconds", vec!["bench", "--sizes", "64x48"]),
        (
            "--replay-speed",
            vec!["bench", "--sizes", "64x48", "--seconds", "1"],
        ),
        ("--sizes", vec!["bench", "--seconds", "1"]),
        (
            "--duration",
            vec!["listen", "--udp", "127.0.0.1:0", "--idle", "1"],
        ),
        (
            "--idle",
            vec!["listen", "--udp", "127.0.0.1:0", "--duration", "1"],
        ),
        (
            "--recv-buffer",
            vec!["listen", "--udp", "127.0.0.1:0", "--duration", "1"],
        ),
        (
            "--max-events",
            vec!["listen", "--udp", "127.0.0.1:0", "--duration", "1"],
        ),
    ];
    std::fs::write(dir.join("clean.y4m"), &video).unwrap();
    for (flag, base) in &flags {
        let values: Vec<String> = if flag.contains("size") {
            strings(&[
                "0x0",
                "1x1",
                "65536x65536",
                "65535x65535",
                "8193x2",
                "-1x5",
                "x",
                "",
                "4294967297x1",
            ])
        } else {
            strings(&EXTREMES)
        };
        for v in values {
            // `--flag=VALUE`, so that "-1" reaches our checks rather than clap's.
            let mut args = strings(base);
            args.push(format!("{flag}={v}"));
            args.push("--force".into());
            // `bench` and `listen` have no --force; `eval` neither.
            if matches!(base[0], "bench" | "listen" | "eval" | "run") {
                args.pop();
            }
            cases.push(Case {
                name: format!("{} {flag} {v:?}", base[0]),
                args,
                check_output: None,
            });
        }
    }

    // Extreme values in every numeric config key, loaded by the command that uses them.
    let shipped =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("config/v2ce.toml"))
            .unwrap();
    let mut keys: Vec<(String, String)> = Vec::new();
    let mut text_keys: Vec<(String, String)> = Vec::new();
    let mut section = String::new();
    for line in shipped.lines() {
        let l = line.trim();
        if l.starts_with('[') {
            section = l.trim_matches(['[', ']']).to_string();
            continue;
        }
        // The physics keys are commented out (the preset sets them); elsewhere comments are
        // examples of other tables.
        let l = if section == "stage1.physics" {
            l.trim_start_matches(['#', ' '])
        } else {
            l
        };
        if let Some((k, v)) = l.split_once(" = ") {
            let v = v.split(" #").next().unwrap_or(v).trim();
            let numeric = v.parse::<f64>().is_ok();
            if numeric && !k.contains(' ') && !keys.iter().any(|(s, key)| *s == section && key == k)
            {
                keys.push((section.clone(), k.to_string()));
            }
            if v.starts_with('"') && !k.contains(' ') {
                text_keys.push((section.clone(), k.to_string()));
            }
        }
    }
    // The physics tier's keys (commented out in the shipped file: the preset sets them).
    for k in [
        "threshold_off",
        "threshold_sigma",
        "refractory_us",
        "cutoff_hz",
        "dark_current",
        "linlog_knee",
        "leak_hz",
        "shot_noise_hz",
        "hot_pixel_fraction",
        "hot_pixel_hz",
        "max_substeps",
        "tile",
        "scene_level",
        "exposure_us",
        "flicker_hz",
        "flicker_depth",
        "max_step_px",
        "max_subframes",
    ] {
        keys.push(("stage1.physics".into(), k.into()));
    }
    for k in ["light", "motion", "flow_preset"] {
        text_keys.push(("stage1.physics".into(), k.into()));
    }
    assert!(keys.len() > 40, "{keys:?}");
    assert!(text_keys.len() > 15, "{text_keys:?}");
    let long = format!("\"{}\"", "a".repeat(5000));
    let text_values = [
        "\"\"",
        "\"nonsense\"",
        "\"/nonexistent/x.onnx\"",
        "\"65536x65536\"",
        "\"127.0.0.1:99999\"",
        "\"\\u0000\"",
        long.as_str(),
    ];
    let settings: Vec<(String, String, Vec<String>)> = keys
        .iter()
        .map(|(s, k)| (s.clone(), k.clone(), strings(&TOML_EXTREMES)))
        .chain(
            text_keys
                .iter()
                .map(|(s, k)| (s.clone(), k.clone(), strings(&text_values))),
        )
        .collect();
    for (i, (section, key, values)) in settings.iter().enumerate() {
        for (j, v) in values.iter().enumerate() {
            let file = format!("c{i}-{j}.toml");
            std::fs::write(dir.join(&file), format!("[{section}]\n{key} = {v}\n")).unwrap();
            let args = if section == "run" || section == "camera" {
                strings(&[
                    "run",
                    "--config",
                    &file,
                    "--source",
                    "fixture",
                    "--udp",
                    "",
                    "--out",
                    &format!("c{i}-{j}.csv"),
                    "--max-frames",
                    "3",
                    "--duration",
                    "5",
                ])
            } else {
                strings(&[
                    "convert",
                    "clean.y4m",
                    "--config",
                    &file,
                    "--max-frames",
                    "4",
                    "-o",
                    &format!("c{i}-{j}.csv"),
                ])
            };
            cases.push(Case {
                name: format!("[{section}] {key} = {}", &v[..v.len().min(40)]),
                args,
                check_output: None,
            });
        }
    }
    cases.extend(sizes_and_times(dir, &mut rng));
    cases.extend(extreme_times(dir, &mut rng));
    cases
}

/// Times as text (seconds for frame lists, microseconds for events): the ends of `i64` and of
/// the range the program takes (2^61 us), spans just past what an `f64` holds exactly (2^53
/// us), what a float cast makes of NaN and infinities, equal and decreasing times.
const EXTREME_SECONDS: [(&str, &str); 12] = [
    ("-9223372036854", "9223372036854"),
    ("-9223372036855", "0"),
    ("0", "9223372036854.775807"),
    ("0", "9007199254.740993"),
    ("2305843009213.693952", "2305843009213.693953"),
    ("nan", "1"),
    ("0", "inf"),
    ("-inf", "0"),
    ("1e300", "2e300"),
    ("5", "5"),
    ("5", "4"),
    ("0", "0.0000001"),
];

/// Extreme times (issue 36) through every command that takes them: frame lists through
/// `convert` and `calibrate`, event files and frame times through `eval stage1`, `eval stage2`
/// (`--frames`, `--fps`) and `render --fps`, and event files with any `i64` time through
/// `transcode` and `info`, which only carry them.
fn extreme_times(dir: &Path, rng: &mut Rng) -> Vec<Case> {
    let mut cases = Vec::new();
    let gray = |v: u8| {
        image::GrayImage::from_fn(16, 12, |x, _| image::Luma([v.wrapping_add(x as u8 * 9)]))
    };
    std::fs::write(dir.join("near.csv"), "t_us,x,y,on\n100,1,1,1\n200,2,2,0\n").unwrap();
    for (i, (a, b)) in EXTREME_SECONDS.iter().enumerate() {
        let folder = dir.join(format!("times{i}"));
        std::fs::create_dir_all(&folder).unwrap();
        gray(10).save(folder.join("a.png")).unwrap();
        gray(200).save(folder.join("b.png")).unwrap();
        std::fs::write(folder.join("images.txt"), format!("{a} a.png\n{b} b.png\n")).unwrap();
        let list = format!("times{i}/images.txt");
        for args in [
            strings(&["convert", &list, "-o", &format!("times{i}.csv")]),
            strings(&[
                "calibrate",
                "--real",
                "near.csv",
                "--frames",
                &list,
                "-o",
                &format!("times{i}.toml"),
            ]),
            strings(&["eval", "stage2", "--events", "near.csv", "--frames", &list]),
            strings(&[
                "eval", "stage1", "--real", "near.csv", "--sim", "near.csv", "--frames", &list,
            ]),
        ] {
            cases.push(Case {
                name: format!("{} with frames at {a} s and {b} s", args[..2].join(" ")),
                args,
                check_output: None,
            });
        }
    }
    let ends = [
        i64::MIN,
        i64::MIN + 1,
        -(1 << 61) - 1,
        -(1 << 61),
        -(1 << 53),
        0,
        1 << 53,
        (1 << 61) + 1,
        i64::MAX - 5,
        i64::MAX,
    ];
    for i in 0..16 {
        let mut t: Vec<i64> = (0..2).map(|_| ends[rng.below(ends.len())]).collect();
        t.sort();
        let file = format!("ends{i}.csv");
        let csv: String = std::iter::once("t_us,x,y,on\n".to_string())
            .chain(t.iter().map(|t| format!("{t},1,1,1\n")))
            .collect();
        std::fs::write(dir.join(&file), csv).unwrap();
        for (args, out) in [
            (
                strings(&["eval", "stage2", "--events", &file, "--fps", "30"]),
                None,
            ),
            (
                strings(&[
                    "eval", "stage1", "--real", &file, "--sim", &file, "--fps", "30",
                ]),
                None,
            ),
            (
                strings(&[
                    "render",
                    &file,
                    "--size",
                    "8x8",
                    "--fps",
                    "30",
                    "-o",
                    &format!("ends{i}.gif"),
                ]),
                None,
            ),
            (strings(&["info", &file]), None),
            (
                strings(&["transcode", &file, &format!("ends{i}.raw"), "--size", "8x8"]),
                Some(format!("ends{i}.raw")),
            ),
        ] {
            cases.push(Case {
                name: format!("{} with events at {t:?} us", args[..2].join(" ")),
                args,
                check_output: out,
            });
        }
    }
    cases
}

/// A value drawn from the edges and the inside of `0..=max`.
fn edgy(rng: &mut Rng, max: u64) -> u64 {
    match rng.below(5) {
        0 => 0,
        1 => 1,
        2 => max,
        3 => max / 2 + rng.next() % 3,
        _ => rng.next() % max.saturating_add(1).max(1),
    }
}

/// The inputs that size memory or span time, drawn at random (issue 25): sensor sizes claimed
/// by a RAW header through `render`, `info` and `transcode`; shard counts up to 2^32 through
/// `batch`; tensor shapes claimed by a `.npy` header through `model run`; event times anywhere in
/// i64 through the EVT 2.0, EVT 3.0 and HDF5 writers; two file outputs on one path.
fn sizes_and_times(dir: &Path, rng: &mut Rng) -> Vec<Case> {
    let mut cases = Vec::new();
    for i in 0..24 {
        let (w, h) = (edgy(rng, 65535), edgy(rng, 65535));
        let file = format!("geom{i}.raw");
        let evt = if i % 2 == 0 { "2.0" } else { "3.0" };
        let mut bytes = format!("% evt {evt}\n% geometry {w}x{h}\n% end\n").into_bytes();
        bytes.extend((0..64).map(|_| rng.next() as u8));
        std::fs::write(dir.join(&file), bytes).unwrap();
        let args = match i % 3 {
            0 => strings(&["render", &file, "-o", &format!("geom{i}.png")]),
            1 => strings(&["info", &file]),
            _ => strings(&["transcode", &file, &format!("geom{i}.csv")]),
        };
        cases.push(Case {
            name: format!("{} of a {w}x{h} RAW header", args[0]),
            args,
            check_output: None,
        });
    }
    std::fs::write(dir.join("shard.y4m"), y4m(16, 12, 3)).unwrap();
    std::fs::write(dir.join("shard.txt"), "shard.y4m\n").unwrap();
    for i in 0..16 {
        let n = edgy(rng, u64::from(u32::MAX) + 1);
        let index = if i % 4 == 0 {
            n
        } else {
            edgy(rng, n.saturating_sub(1))
        };
        cases.push(Case {
            name: format!("batch --shard {index}/{n}"),
            args: strings(&[
                "batch",
                "shard.txt",
                "-o",
                &format!("shards{i}"),
                "--shard",
                &format!("{index}/{n}"),
            ]),
            check_output: None,
        });
    }
    for i in 0..16 {
        let dims: Vec<u64> = (0..5)
            .map(|d| if d == 2 { 2 } else { edgy(rng, 1 << 33) })
            .collect();
        let shape = format!(
            "({})",
            dims.iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
        let mut dict = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
        while (10 + dict.len() + 1) % 64 != 0 {
            dict.push(' ');
        }
        dict.push('\n');
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        bytes.extend((dict.len() as u16).to_le_bytes());
        bytes.extend(dict.as_bytes());
        bytes.extend((0..rng.below(4096)).map(|_| 0u8));
        let file = format!("shape{i}.npy");
        std::fs::write(dir.join(&file), bytes).unwrap();
        cases.push(Case {
            name: format!("model run on a .npy claiming {shape}"),
            args: strings(&[
                "model",
                "run",
                "absent.onnx",
                "--input-npy",
                &file,
                "--output-npy",
                &format!("shape{i}-out.npy"),
            ]),
            check_output: None,
        });
    }
    for i in 0..18 {
        let mut t: Vec<i64> = (0..3)
            .map(|_| match rng.below(4) {
                0 => i64::MIN + rng.below(1000) as i64,
                1 => i64::MAX - rng.below(1000) as i64,
                2 => rng.next() as i64 - (1 << 40),
                _ => rng.next() as i64,
            })
            .collect();
        t.sort();
        let csv: String = std::iter::once("t_us,x,y,on\n".to_string())
            .chain(t.iter().map(|t| format!("{t},1,1,1\n")))
            .collect();
        let file = format!("times{i}.csv");
        std::fs::write(dir.join(&file), csv).unwrap();
        let (out, extra): (String, &[&str]) = match i % 3 {
            0 => (format!("times{i}.raw"), &["--evt", "2"]),
            1 => (format!("times{i}.raw"), &["--evt", "3"]),
            _ => (format!("times{i}.h5"), &[]),
        };
        let mut args = strings(&["transcode", &file, &out, "--size", "8x8"]);
        args.extend(strings(extra));
        cases.push(Case {
            name: format!("transcode times {t:?} to {out}"),
            args,
            check_output: Some(out),
        });
    }
    for (i, (a, b)) in [
        ("same.csv", "same.csv"),
        ("same.csv", "./same.csv"),
        ("d/same.aedat4", "d/../d/same.aedat4"),
    ]
    .iter()
    .enumerate()
    {
        std::fs::create_dir_all(dir.join("d")).unwrap();
        let file = format!("same{i}.toml");
        std::fs::write(
            dir.join(&file),
            format!("[[sink]]\ntype = \"file\"\npath = \"{b}\"\n"),
        )
        .unwrap();
        cases.push(Case {
            name: format!("run --out {a} and a [[sink]] file {b}"),
            args: strings(&[
                "run",
                "--config",
                &file,
                "--source",
                "shard.y4m",
                "--udp",
                "",
                "--out",
                a,
            ]),
            check_output: None,
        });
    }
    cases
}

/// The two tests take turns: a child's peak RSS (from `wait4`) starts at what this process
/// held when it forked the child, so the flat-memory test must not fork while the hostile suite
/// holds its generated inputs (it once read 40 MiB that way for a 13 MiB transcode).
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

#[test]
fn hostile_inputs_end_in_valid_output_or_one_error_line() {
    let _turn = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = common::temp_dir("robustness");
    let cases = cases(&dir);
    let next = AtomicUsize::new(0);
    let failures = Mutex::new(Vec::new());
    let tally = Mutex::new((0usize, 0usize, 0i64, 0f64));
    let heaviest = Mutex::new(Vec::new());
    let workers = std::thread::available_parallelism().map_or(2, |n| n.get().min(4));
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(case) = cases.get(i) else { break };
                let o = run_capped(&case.args, &dir, &format!("case{i}"));
                if let Some(why) = judge(case, &o, &dir) {
                    failures.lock().unwrap().push(format!(
                        "{}: {why}\n    v2ce {}\n    {}",
                        case.name,
                        case.args
                            .iter()
                            .map(|a| format!("{a:?}"))
                            .collect::<Vec<_>>()
                            .join(" "),
                        o.stderr.trim().replace('\n', "\n    ")
                    ));
                }
                let mut t = tally.lock().unwrap();
                if o.code == Some(0) {
                    t.0 += 1;
                } else {
                    t.1 += 1;
                }
                t.2 = t.2.max(o.max_rss_kib);
                t.3 = t.3.max(o.seconds);
                heaviest
                    .lock()
                    .unwrap()
                    .push((o.max_rss_kib, o.seconds, case.name.clone()));
            });
        }
    });
    let failures = failures.into_inner().unwrap();
    let (ok, refused, rss, slowest) = tally.into_inner().unwrap();
    eprintln!(
        "robustness: {} cases: {ok} valid outputs, {refused} refused with an error; {} failed; \
         peak RSS {} MiB, slowest {slowest:.1} s",
        cases.len(),
        failures.len(),
        rss / 1024
    );
    let mut heaviest = heaviest.into_inner().unwrap();
    heaviest.sort_by_key(|h| std::cmp::Reverse(h.0));
    for (rss, secs, name) in heaviest.iter().take(5) {
        eprintln!("  {} MiB, {secs:.1} s: {name}", rss / 1024);
    }
    heaviest.sort_by(|a, b| b.1.total_cmp(&a.1));
    for (rss, secs, name) in heaviest.iter().take(5) {
        eprintln!("  {secs:.1} s, {} MiB: {name}", rss / 1024);
    }
    assert!(
        failures.is_empty(),
        "{} of {} cases failed:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}

/// IJRR `events.txt` streams a line at a time: transcoding 2 million lines (about 55 MB) peaks
/// far below the file's size (it was read whole, twice: 318 MB for a 183 MB file).
#[test]
fn ijrr_text_transcodes_in_flat_memory() {
    let _turn = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = common::temp_dir("robustness-ijrr");
    let mut text = String::with_capacity(60 << 20);
    let mut rng = Rng(7);
    for i in 0..2_000_000u64 {
        use std::fmt::Write;
        let (s, us) = (1_589_163_147 + i / 100_000, (i % 100_000) * 10);
        let (x, y, p) = (rng.below(346), rng.below(260), rng.below(2));
        writeln!(text, "{s}.{us:06} {x} {y} {p}").unwrap();
    }
    std::fs::write(dir.join("events.txt"), &text).unwrap();
    let size_mib = text.len() as i64 >> 20;
    // The child is forked from this process: its peak RSS counts what this one holds at the
    // fork, so free the text first.
    drop(text);
    let o = run_capped(
        &strings(&["transcode", "events.txt", "e.aedat4"]),
        &dir,
        "ijrr",
    );
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    let rss_mib = o.max_rss_kib / 1024;
    eprintln!("IJRR text of {size_mib} MiB transcoded with a peak RSS of {rss_mib} MiB");
    assert!(
        rss_mib < 40,
        "peak RSS {rss_mib} MiB for a {size_mib} MiB file"
    );
}
