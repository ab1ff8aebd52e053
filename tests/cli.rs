//! The `v2ce` binary, end to end.

use std::process::Command;

fn v2ce() -> Command {
    Command::new(env!("CARGO_BIN_EXE_v2ce"))
}

fn temp_dir(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("v2ce-cli-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Runs `v2ce eval stage2 ARGS --json`, checks it succeeded and parses its output.
fn eval_json(args: &[&std::ffi::OsStr]) -> serde_json::Value {
    let out = v2ce()
        .args(["eval", "stage2", "--json"])
        .args(args)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{args:?}: {err}");
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn eval_stage2_on_the_built_in_recording() {
    let dir = temp_dir("builtin");
    let csv = dir.join("out.csv");
    let ldati: Vec<&std::ffi::OsStr> = ["--sampler", "ldati", "--seed", "3"]
        .iter()
        .map(|s| s.as_ref())
        .collect();
    let mut with_csv = ldati.clone();
    with_csv.extend([std::ffi::OsStr::new("--write-events"), csv.as_os_str()]);
    let json = eval_json(&with_csv);
    for key in [
        "mete_us",
        "noe",
        "pger",
        "c_mete_us",
        "c_noe",
        "intervals",
        "events_in",
        "events_out",
    ] {
        assert!(
            json.get(key).is_some_and(|v| v.is_number()),
            "{key} in {json}"
        );
    }
    assert_eq!(json["pger"], 1.0);
    assert_eq!(json["events_in"], json["events_out"]);
    assert_eq!(json["intervals"], 60);
    // The CSV holds exactly the sampled events and reads back.
    let text = std::fs::read_to_string(&csv).unwrap();
    assert!(text.starts_with("t_us,x,y,on\n"));
    let rec = v2ce::format::read_events(&csv).unwrap();
    assert_eq!(
        rec.events.len() as u64,
        json["events_out"].as_u64().unwrap()
    );
    // Same seed, same events.
    assert_eq!(eval_json(&ldati)["mete_us"], json["mete_us"]);
    // The written CSV is an input in turn: fixed intervals from its first event cover them all.
    let again = eval_json(&[
        "--fps".as_ref(),
        "30".as_ref(),
        "--events".as_ref(),
        csv.as_os_str(),
    ]);
    assert_eq!(again["events_in"], json["events_out"]);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn human_readable_output_names_every_metric() {
    let out = v2ce()
        .args(["eval", "stage2", "--sampler", "even"])
        .output()
        .unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    for word in [
        "METE",
        "NOE",
        "PGER",
        "C-METE",
        "C-NOE",
        "time per interval",
    ] {
        assert!(text.contains(word), "{word} missing in {text}");
    }
}

#[test]
fn bad_input_gives_one_clear_error() {
    let dir = temp_dir("bad");
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec![
                "--events".into(),
                dir.join("missing.csv").display().to_string(),
                "--fps".into(),
                "30".into(),
            ],
            "missing.csv",
        ),
        (vec!["--sampler".into(), "fancy".into()], "fancy"),
        (vec!["--fps=-3".into()], "fps"),
        (vec!["--fps=0".into()], "fps"),
        (
            vec!["--events".into(), dir.join("e.csv").display().to_string()],
            "--frames",
        ),
        (
            vec![
                "--events".into(),
                dir.join("bad.aedat4").display().to_string(),
            ],
            "AEDAT",
        ),
        (
            vec!["--config".into(), dir.join("c.toml").display().to_string()],
            "line 2",
        ),
    ];
    std::fs::write(dir.join("e.csv"), "t_us,x,y,on\n1,2,3,1\n").unwrap();
    std::fs::write(dir.join("bad.aedat4"), b"#!AER-DAT4.0\r\n\xff\xff\xff\x7f").unwrap();
    std::fs::write(dir.join("c.toml"), "[stage2]\nspeed = 1\n").unwrap();
    for (args, needle) in cases {
        let out = v2ce()
            .args(["eval", "stage2"])
            .args(&args)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} succeeded");
        assert!(err.contains(needle), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn transcode_and_info() {
    let dir = temp_dir("transcode");
    let mut csv = String::from("t_us,x,y,on\n");
    for i in 0..5000 {
        csv.push_str(&format!(
            "{},{},{},{}\n",
            100 + i * 10,
            i % 50,
            i % 40,
            i % 2
        ));
    }
    std::fs::write(dir.join("in.csv"), &csv).unwrap();
    let run = |args: &[&std::ffi::OsStr]| {
        let out = v2ce().args(args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr).to_string();
        assert!(out.status.success(), "{args:?}: {err}");
        String::from_utf8_lossy(&out.stdout).to_string()
    };
    let p = |name: &str| dir.join(name).into_os_string();
    run(&[
        "transcode".as_ref(),
        &p("in.csv"),
        &p("a.raw"),
        "--evt".as_ref(),
        "2".as_ref(),
    ]);
    run(&[
        "transcode".as_ref(),
        &p("a.raw"),
        &p("b.aedat4"),
        "--compression=zstd".as_ref(),
    ]);
    run(&[
        "transcode".as_ref(),
        &p("b.aedat4"),
        &p("c.raw"),
        "--size=64x48".as_ref(),
    ]);
    run(&["transcode".as_ref(), &p("c.raw"), &p("d.csv")]);
    assert_eq!(std::fs::read_to_string(dir.join("d.csv")).unwrap(), csv);
    let info: serde_json::Value =
        serde_json::from_str(&run(&["info".as_ref(), &p("c.raw"), "--json".as_ref()])).unwrap();
    assert_eq!(info["events"], 5000);
    assert_eq!(info["size"], serde_json::json!([64, 48]));
    assert_eq!(info["first_t"], 100);
    assert_eq!(info["on_ratio"], 0.5);
    // The default .raw is EVT 2.0; info names the format, the RAW time offset and the first
    // and last events, and an AEDAT 4.0 file's compression.
    assert_eq!(info["format"], "EVT 2.0");
    assert!(info["time_offset_us"].is_i64(), "{info}");
    assert_eq!(info["first_event"][0], 100);
    assert_eq!(info["last_event"][0], info["last_t"]);
    let b: serde_json::Value =
        serde_json::from_str(&run(&["info".as_ref(), &p("b.aedat4"), "--json".as_ref()])).unwrap();
    assert_eq!(
        (b["format"].as_str(), b["compression"].as_str()),
        (Some("AEDAT 4.0"), Some("ZSTD"))
    );
    let text = run(&["info".as_ref(), &p("a.raw")]);
    assert!(text.contains("sensor size  50 x 40"), "{text}");
    assert!(text.contains("format       EVT 2.0"), "{text}");
    assert!(text.contains("first event  t 100 us"), "{text}");
    // Bad input: one clear line, no panic.
    // A file cut inside its first word: no events, one warning.
    std::fs::write(dir.join("cut.raw"), b"% evt 3.0\n% end\n\x01").unwrap();
    let out = v2ce()
        .args(["transcode".into(), p("cut.raw"), p("cut.csv")])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert_eq!(err.matches("truncated input").count(), 1, "{err}");
    assert_eq!(
        std::fs::read_to_string(dir.join("cut.csv"))
            .unwrap()
            .lines()
            .count(),
        1
    );
    std::fs::write(dir.join("bad.raw"), b"% evt 2.1\n% end\n\x01\x02\x03\x04").unwrap();
    for (args, needle) in [
        (vec![p("bad.raw"), p("x.csv")], "'evt 2.1' is not supported"),
        (vec![p("in.csv"), p("x.mp4")], ".mp4"),
        (vec![p("in.csv"), p("x.raw"), "--size=0x3".into()], "size"),
        (vec![p("missing.csv"), p("x.csv")], "missing.csv"),
    ] {
        let out = v2ce().arg("transcode").args(&args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(needle),
            "{args:?}: {err}"
        );
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn convert_frames_to_events_in_every_format() {
    let dir = temp_dir("convert");
    // A 32 x 16 gray Y4M at 100 fps: a bright square moving right over a dark background.
    let mut y4m = b"YUV4MPEG2 W32 H16 F100:1 Ip A1:1 Cmono\n".to_vec();
    for f in 0..20usize {
        y4m.extend_from_slice(b"FRAME\n");
        for y in 0..16usize {
            for x in 0..32usize {
                let inside = (4..12).contains(&y) && x >= f && x < f + 8;
                y4m.push(if inside { 220 } else { 30 });
            }
        }
    }
    std::fs::write(dir.join("in.y4m"), y4m).unwrap();
    let input = dir.join("in.y4m");
    let mut counts = Vec::new();
    for out in ["a.aedat4", "b.raw", "c.csv"] {
        let o = v2ce()
            .arg("convert")
            .arg(&input)
            .arg("-o")
            .arg(dir.join(out))
            .args(["--preset", "ideal"])
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "{out}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let info = v2ce()
            .arg("info")
            .arg(dir.join(out))
            .arg("--json")
            .output()
            .unwrap();
        let v: serde_json::Value = serde_json::from_slice(&info.stdout).unwrap();
        counts.push(v["events"].as_u64().unwrap());
        if out != "c.csv" {
            assert_eq!(v["size"], serde_json::json!([32, 16]), "{out}"); // CSV has no size
        }
    }
    assert!(counts[0] > 100, "{counts:?}");
    assert!(counts.iter().all(|&c| c == counts[0]), "{counts:?}");
    // Both motion models convert the small video (16 rows: the flow's smallest frame).
    for motion in ["linear", "flow"] {
        let o = v2ce()
            .current_dir(&dir)
            .args([
                "convert", "in.y4m", "-o", "m.csv", "--force", "--preset", "ideal",
            ])
            .args(["--motion", motion])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    // Bad input: a missing file, a bad preset, a folder without times.
    std::fs::create_dir_all(dir.join("empty")).unwrap();
    for (args, needle) in [
        (vec!["convert", "missing.mp4", "-o", "x.csv"], "missing.mp4"),
        (
            vec!["convert", "in.y4m", "-o", "x.csv", "--preset", "best"],
            "preset",
        ),
        (vec!["convert", "empty", "-o", "x.csv"], "fps"),
        // The motion model's settings, and a calibration too short to fit.
        (
            vec!["convert", "in.y4m", "-o", "x.csv", "--max-subframes", "0"],
            "max_subframes",
        ),
        (
            vec!["convert", "in.y4m", "-o", "x.csv", "--max-step-px", "NaN"],
            "max_step_px",
        ),
        (
            vec![
                "calibrate",
                "--real",
                "in.y4m",
                "-o",
                "p.toml",
                "--max-frames",
                "3",
            ],
            "--max-frames",
        ),
    ] {
        let o = v2ce().current_dir(&dir).args(&args).output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && err.contains(needle),
            "{args:?}: {err}"
        );
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `v2ce eval realism` without the shared data: the bundled video converted twice (the
/// default preset, and the noiseless `ideal` one) and measured at a fixed rate. A stream
/// against itself is at distance 0 wherever defined; the noiseless one differs; the table
/// names every statistic and says "undefined" for the noise floor, which needs frames.
#[test]
fn eval_realism_compares_two_streams() {
    let dir = temp_dir("realism");
    let convert = |preset: &str, out: &str| {
        let o = v2ce()
            .args([
                "convert",
                "fixture",
                "--max-frames",
                "40",
                "--size",
                "160x120",
                "--preset",
                preset,
                "-o",
            ])
            .arg(dir.join(out))
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    convert("davis346", "a.csv");
    convert("ideal", "b.csv");
    let run = |sim: &str, json: bool| {
        let mut c = v2ce();
        c.args(["eval", "realism", "--fps", "30", "--real"])
            .arg(dir.join("a.csv"))
            .arg("--sim")
            .arg(dir.join(sim));
        if json {
            c.arg("--json");
        }
        let o = c.output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8(o.stdout).unwrap()
    };
    let same: serde_json::Value = serde_json::from_str(&run("a.csv", true)).unwrap();
    let stats = same["statistics"].as_array().unwrap();
    assert_eq!(stats.len(), 12);
    for s in stats {
        assert!(s["distance"].is_null() || s["distance"] == 0.0, "{s}");
    }
    let other: serde_json::Value = serde_json::from_str(&run("b.csv", true)).unwrap();
    let moved = other["statistics"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|s| s["distance"].as_f64().is_some_and(|d| d > 0.0))
        .count();
    assert!(moved >= 3, "{other}");
    // The plot: a panel per distribution (rates, intervals, the spectrum where the window
    // holds a second), both streams' colours drawn.
    let plot = dir.join("r.png");
    let o = v2ce()
        .args(["eval", "realism", "--fps", "30", "--real"])
        .arg(dir.join("a.csv"))
        .arg("--sim")
        .arg(dir.join("b.csv"))
        .arg("--plot")
        .arg(&plot)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let png = image::open(&plot).unwrap().to_rgb8();
    assert!(
        png.width() >= 2 * 520 && png.height() == 420,
        "{:?}",
        png.dimensions()
    );
    let has = |rgb: [u8; 3]| png.pixels().any(|p| p.0 == rgb);
    assert!(
        has([31, 119, 180]) && has([255, 127, 14]),
        "both curves drawn"
    );
    let table = run("b.csv", false);
    for s in stats {
        assert!(table.contains(s["name"].as_str().unwrap()), "{table}");
    }
    assert!(table.contains("undefined"), "{table}");
    // Without frames or a rate there is no window.
    let o = v2ce()
        .args(["eval", "realism", "--real"])
        .arg(dir.join("a.csv"))
        .arg("--sim")
        .arg(dir.join("b.csv"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("--fps"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `v2ce reconstruct` writes frames of an event file as a frame list (one per interval bound
/// at --fps from the first event, times exact to the microsecond) that `convert` reads back;
/// `eval realism --fps` without --sim simulates the same reconstruction in memory. An
/// existing folder needs --force.
#[test]
fn reconstruct_writes_frames_that_convert_and_eval_read() {
    let dir = temp_dir("reconstruct");
    let ok = |c: &mut Command| {
        let o = c.output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        o
    };
    let events = dir.join("a.csv");
    ok(v2ce()
        .args([
            "convert",
            "fixture",
            "--max-frames",
            "30",
            "--size",
            "160x120",
            "-o",
        ])
        .arg(&events));
    let frames = dir.join("frames");
    let reconstruct = |force: bool| {
        let mut c = v2ce();
        c.arg("reconstruct")
            .arg(&events)
            .arg("-o")
            .arg(&frames)
            .args(["--fps", "30"]);
        if force {
            c.arg("--force");
        }
        c.output().unwrap()
    };
    assert!(reconstruct(false).status.success());
    assert!(!reconstruct(false).status.success(), "an existing folder");
    assert!(reconstruct(true).status.success());
    let list = std::fs::read_to_string(frames.join("images.txt")).unwrap();
    let times: Vec<i64> = list
        .lines()
        .map(|l| {
            let t = l.split_whitespace().next().unwrap();
            let (s, us) = t.split_once('.').unwrap();
            assert_eq!(us.len(), 6, "{l}");
            s.parse::<i64>().unwrap() * 1_000_000 + us.parse::<i64>().unwrap()
        })
        .collect();
    assert!(times.len() >= 10, "{list}");
    for pair in times.windows(2) {
        assert!(
            (33_333..=33_334).contains(&(pair[1] - pair[0])),
            "{times:?}"
        );
    }
    let text = std::fs::read_to_string(&events).unwrap();
    let first: i64 = text
        .lines()
        .nth(1)
        .unwrap()
        .split(',')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert_eq!(times[0], first);
    let back = dir.join("b.csv");
    ok(v2ce()
        .arg("convert")
        .arg(frames.join("images.txt"))
        .arg("-o")
        .arg(&back));
    let from_files = std::fs::read_to_string(&back).unwrap().lines().count() - 1;
    let o = ok(v2ce()
        .args(["eval", "realism", "--json", "--fps", "30", "--real"])
        .arg(&events));
    let json: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let in_memory = json["sim_events"].as_u64().unwrap() as f64;
    // The files are 8-bit sRGB; the same frames in memory are 16-bit.
    assert!(from_files > 1000, "{from_files}");
    assert!(
        (in_memory / from_files as f64 - 1.0).abs() < 0.1,
        "{in_memory} in memory, {from_files} from the files"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The events do not depend on how many threads step them: a conversion of the fixture's
/// camera pan (every pixel moving, the pixel bands handed out to the helpers, the flow found
/// ahead) on one thread, on two, and on more threads than the machine has, byte for byte.
#[test]
fn events_do_not_depend_on_the_threads() {
    let dir = temp_dir("threads");
    let mut outputs = Vec::new();
    // The last run takes the baseline's copies of the vector loops (the others take AVX2's
    // where the CPU has it): the same values.
    for (threads, simd) in [
        ("1", "auto"),
        ("2", "auto"),
        ("5", "auto"),
        ("2", "baseline"),
    ] {
        let out = dir.join(format!("t{threads}-{simd}.raw"));
        let status = v2ce()
            .env("V2CE_THREADS", threads)
            .env("V2CE_SIMD", simd)
            .args([
                "convert",
                "fixture",
                "--max-frames",
                "110",
                "--max-subframes",
                "4",
            ])
            .arg("-o")
            .arg(&out)
            .arg("--force")
            .output()
            .unwrap();
        assert!(status.status.success(), "{status:?}");
        outputs.push(std::fs::read(&out).unwrap());
    }
    // Far more than a header: the pan fires millions of events.
    assert!(outputs[0].len() > 1_000_000, "{} bytes", outputs[0].len());
    assert!(outputs[1] == outputs[0], "2 threads differ from 1");
    assert!(outputs[2] == outputs[0], "5 threads differ from 1");
    assert!(
        outputs[3] == outputs[0],
        "the baseline vectors differ from AVX2's"
    );
    // A value that is not a thread count is refused with a warning, not a crash.
    let status = v2ce()
        .env("V2CE_THREADS", "lots")
        .env("V2CE_SIMD", "fastest")
        .args(["convert", "fixture", "--max-frames", "3", "-o"])
        .arg(dir.join("bad.raw"))
        .arg("--force")
        .output()
        .unwrap();
    assert!(status.status.success(), "{status:?}");
    let stderr = String::from_utf8_lossy(&status.stderr);
    assert!(stderr.contains("V2CE_THREADS"), "{stderr}");
    assert!(stderr.contains("V2CE_SIMD"), "{stderr}");
}
