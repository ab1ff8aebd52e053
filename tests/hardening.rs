//! Hostile sizes, times and counts from the command line, config files and inputs: each gets
//! a one-line error and a non-zero exit, within a time limit and without a panic (each case
//! panicked, aborted for memory or ran for ever before `limits` bounded it).

mod common;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Runs v2ce with `args` for at most `limit`; returns the exit code (None: killed at the limit)
/// and stderr.
fn run(args: &[&str], dir: &Path, limit: Duration) -> (Option<i32>, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_v2ce"))
        .args(args)
        .current_dir(dir)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let started = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            let mut err = String::new();
            use std::io::Read;
            child
                .stderr
                .take()
                .unwrap()
                .read_to_string(&mut err)
                .unwrap();
            return (status.code(), err);
        }
        if started.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            return (None, String::new());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The command fails with exit status 1 (an error, not a panic's 101 or a signal) within 20 s,
/// with one error line that contains `expect`.
fn refused(args: &[&str], dir: &Path, expect: &str) {
    let (code, err) = run(args, dir, Duration::from_secs(20));
    assert_eq!(code, Some(1), "{args:?}: exit {code:?}: {err}");
    let lines: Vec<&str> = err.lines().filter(|l| l.contains("error")).collect();
    assert_eq!(lines.len(), 1, "{args:?}: {err}");
    assert!(lines[0].contains(expect), "{args:?}: {err}");
    assert!(!err.contains("panicked"), "{args:?}: {err}");
}

#[test]
fn durations_from_flags_and_config_are_bounded() {
    let dir = common::temp_dir("hardening-durations");
    refused(
        &["run", "--source", "fixture", "--duration", "1e20"],
        &dir,
        "run.duration",
    );
    refused(
        &["run", "--source", "fixture", "--stats-interval", "1e308"],
        &dir,
        "run.stats_interval",
    );
    std::fs::write(dir.join("c.toml"), "[run]\nduration = 1e20\n").unwrap();
    refused(&["run", "--config", "c.toml"], &dir, "run.duration");
    for s in ["inf", "1e20", "0", "nan"] {
        refused(&["bench", "--seconds", s], &dir, "--seconds");
    }
}

#[test]
fn sizes_are_bounded_before_anything_is_allocated() {
    let dir = common::temp_dir("hardening-sizes");
    std::fs::write(
        dir.join("b.y4m"),
        "YUV4MPEG2 W16000 H16000 F30:1 Cmono\nFRAME\n",
    )
    .unwrap();
    refused(&["convert", "b.y4m", "-o", "o.csv"], &dir, "8192");
    // Frames a quarter of a microsecond apart all fell on one time and were dropped.
    let mut y4m = b"YUV4MPEG2 W4 H4 F4000000000:1 Cmono\n".to_vec();
    for _ in 0..60 {
        y4m.extend_from_slice(b"FRAME\n");
        y4m.extend_from_slice(&[128u8; 16]);
    }
    std::fs::write(dir.join("fast.y4m"), y4m).unwrap();
    refused(
        &["convert", "fast.y4m", "-o", "f.csv"],
        &dir,
        "1,000,000 fps",
    );
    refused(
        &["bench", "--sizes", "65535x65535", "--seconds", "1"],
        &dir,
        "8192",
    );
    std::fs::write(dir.join("xy.csv"), "t_us,x,y,on\n0,60000,60000,1\n").unwrap();
    refused(
        &["eval", "stage2", "--events", "xy.csv", "--fps", "30"],
        &dir,
        "8192",
    );
    for (key, value) in [("fps", "nan"), ("width", "0"), ("buffers", "0")] {
        std::fs::write(dir.join("cam.toml"), format!("[camera]\n{key} = {value}\n")).unwrap();
        refused(
            &["run", "--config", "cam.toml"],
            &dir,
            &format!("camera.{key}"),
        );
    }
}

#[test]
fn counts_and_gaps_are_bounded() {
    let dir = common::temp_dir("hardening-counts");
    // An hour at a million intervals a second.
    std::fs::write(
        dir.join("long.csv"),
        "t_us,x,y,on\n0,1,1,1\n3600000000,2,2,0\n",
    )
    .unwrap();
    refused(
        &["eval", "stage2", "--events", "long.csv", "--fps", "1000000"],
        &dir,
        "frame intervals",
    );
    // A gap of 2^63 us: EVT 2.0 would write 2^31 time-high words; both encoders refuse it.
    std::fs::write(
        dir.join("g.csv"),
        "t_us,x,y,on\n0,1,1,1\n9223372036854775807,2,2,0\n",
    )
    .unwrap();
    for evt in ["2", "3"] {
        refused(
            &["transcode", "--evt", evt, "g.csv", &format!("g{evt}.raw")],
            &dir,
            "longer than EVT",
        );
    }
}

/// `--max-frames 0` means no limit for `convert`, as it does for `run` and `[run] max_frames`.
#[test]
fn max_frames_zero_means_no_limit_everywhere() {
    let dir = common::temp_dir("hardening-max-frames");
    let frames = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/learned/frames_61x83");
    let frames = frames.to_str().unwrap();
    let mut lines = Vec::new();
    for (tag, extra) in [("all", vec![]), ("zero", vec!["--max-frames", "0"])] {
        let out = dir.join(format!("{tag}.csv"));
        let mut args = vec![
            "convert",
            frames,
            "--fps",
            "30",
            "-o",
            out.to_str().unwrap(),
        ];
        args.extend(extra);
        let (code, err) = run(&args, &dir, Duration::from_secs(60));
        assert_eq!(code, Some(0), "{err}");
        assert!(err.contains("59 frames"), "{err}");
        lines.push(std::fs::read_to_string(&out).unwrap().lines().count());
    }
    assert_eq!(lines[0], lines[1]);
}

/// `info` on events spanning the whole i64 range reports the span, not a negative one.
#[test]
fn info_reports_a_span_across_the_whole_time_range() {
    let dir = common::temp_dir("hardening-span");
    std::fs::write(
        dir.join("span.csv"),
        "t_us,x,y,on\n-9223372036854775808,1,1,1\n9223372036854775807,2,2,0\n",
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_v2ce"))
        .args(["info", "span.csv"])
        .current_dir(&dir)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}");
    assert!(text.contains("time span    18446744073709.55"), "{text}");
}

/// An AEDAT 4.0 file whose header points its data table inside the header (0, 1, 20) used to
/// read as 0 events with exit 0: its packets are now read, with a warning, up to the table.
#[test]
fn a_data_table_position_inside_the_header_loses_no_events() {
    use v2ce::event::Event;
    use v2ce::format::aedat4::{self, Compression};
    use v2ce::format::EventEncoder;
    let dir = common::temp_dir("hardening-aedat4-table");
    let events: Vec<Event> = (0..10_000)
        .map(|i| Event::new(i * 10, (i % 64) as u16, (i % 48) as u16, i % 3 == 0))
        .collect();
    let mut w =
        aedat4::Writer::new(std::io::Cursor::new(Vec::new()), 64, 48, Compression::Lz4).unwrap();
    w.write(&events).unwrap();
    w.finish().unwrap();
    let good = w.into_inner().unwrap().into_inner();
    let magic = aedat4::MAGIC.len();
    let header = aedat4::read_io_header(&mut &good[magic..]).unwrap();
    assert!(header.data_table_position > 0);
    let packets = &good[magic + header.bytes as usize..];
    let xml = aedat4::description(64, 48, Compression::Lz4, "v2ce");
    for position in [0i64, 1, 20] {
        let mut bad = aedat4::MAGIC.to_vec();
        bad.extend(aedat4::io_header_bytes(Compression::Lz4, position, &xml));
        bad.extend_from_slice(packets);
        let name = format!("t{position}.aedat4");
        std::fs::write(dir.join(&name), &bad).unwrap();
        let out = Command::new(env!("CARGO_BIN_EXE_v2ce"))
            .args(["info", &name])
            .current_dir(&dir)
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{position}: {err}");
        assert!(text.contains("events       10000"), "{position}: {text}");
        assert!(err.contains("data table position"), "{position}: {err}");
    }
}

/// An input whose times go back is named as the culprit, not the output being written.
#[test]
fn input_faults_name_the_input() {
    let dir = common::temp_dir("hardening-blame");
    std::fs::write(dir.join("dec.csv"), "t_us,x,y,on\n10,1,1,1\n5,2,2,0\n").unwrap();
    let (code, err) = run(
        &["transcode", "dec.csv", "out.aedat4"],
        &dir,
        Duration::from_secs(20),
    );
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("error: dec.csv: event 1"), "{err}");
    assert!(!err.contains("aedat4: "), "{err}");
}

/// A `convert` stopped by SIGINT says so and exits 130; what it wrote is a complete file, kept
/// under the partial name.
#[test]
fn an_interrupted_convert_exits_130_with_a_readable_file() {
    let dir = common::temp_dir("hardening-interrupt");
    let (w, h, n) = (160usize, 120usize, 3000usize);
    let mut y4m = format!("YUV4MPEG2 W{w} H{h} F30:1 Cmono\n").into_bytes();
    for i in 0..n {
        y4m.extend_from_slice(b"FRAME\n");
        y4m.extend((0..w * h).map(|p| ((p % w + 3 * i) % 200 + 20) as u8));
    }
    std::fs::write(dir.join("long.y4m"), y4m).unwrap();
    let out = dir.join("out.partial.csv");
    let mut child = Command::new(env!("CARGO_BIN_EXE_v2ce"))
        .args(["convert", "long.y4m", "-o", "out.csv"])
        .current_dir(&dir)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The output exists once the signal handlers are in place.
    for _ in 0..2000 {
        if out.exists() {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    std::thread::sleep(Duration::from_millis(100));
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let status = child.wait().unwrap();
    let mut err = String::new();
    use std::io::Read;
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    assert_eq!(status.code(), Some(130), "{err}");
    assert!(
        err.contains("interrupted: ") && err.contains("out.partial.csv"),
        "{err}"
    );
    assert!(
        !dir.join("out.csv").exists(),
        "a partial output under the final name"
    );
    let info = Command::new(env!("CARGO_BIN_EXE_v2ce"))
        .args(["info", "out.partial.csv"])
        .current_dir(&dir)
        .output()
        .unwrap();
    assert!(
        info.status.success(),
        "{}",
        String::from_utf8_lossy(&info.stderr)
    );
}

/// An AEDAT 4.0 file whose writer was killed (no data table, the last packet cut anywhere, even
/// inside its header) reads up to the last whole packet with a warning; a finished file cut
/// short is still an error.
#[test]
fn an_unfinished_aedat4_file_reads_to_its_last_whole_packet() {
    use v2ce::event::Event;
    use v2ce::format::aedat4::{self, Compression};
    use v2ce::format::EventEncoder;
    let dir = common::temp_dir("hardening-aedat4-unfinished");
    let per = aedat4::PACKET_EVENTS;
    let events: Vec<Event> = (0..(3 * per + 100) as i64)
        .map(|i| Event::new(i * 10, (i % 64) as u16, (i % 48) as u16, i % 3 == 0))
        .collect();
    let mut w =
        aedat4::Writer::new(std::io::Cursor::new(Vec::new()), 64, 48, Compression::Lz4).unwrap();
    w.write(&events).unwrap();
    w.finish().unwrap();
    let good = w.into_inner().unwrap().into_inner();
    let magic = aedat4::MAGIC.len();
    let header = aedat4::read_io_header(&mut &good[magic..]).unwrap();
    let start = magic + header.bytes as usize;
    let table = header.data_table_position as usize;
    // The header as a writer leaves it until it finishes: no data table yet.
    let xml = aedat4::description(64, 48, Compression::Lz4, "v2ce");
    let mut unfinished = aedat4::MAGIC.to_vec();
    unfinished.extend(aedat4::io_header_bytes(Compression::Lz4, -1, &xml));
    let head_len = unfinished.len();
    unfinished.extend_from_slice(&good[start..table]);
    // Packet boundaries: walk the sizes.
    let mut bounds = vec![head_len];
    let mut at = head_len;
    while at < unfinished.len() {
        let size = i32::from_le_bytes(unfinished[at + 4..at + 8].try_into().unwrap()) as usize;
        at += 8 + size;
        bounds.push(at);
    }
    assert_eq!(bounds.len(), 5, "4 packets");
    let info = |name: &str, bytes: &[u8]| {
        std::fs::write(dir.join(name), bytes).unwrap();
        let out = Command::new(env!("CARGO_BIN_EXE_v2ce"))
            .args(["info", name])
            .current_dir(&dir)
            .output()
            .unwrap();
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stdout).to_string(),
            String::from_utf8_lossy(&out.stderr).to_string(),
        )
    };
    // Cut inside the fourth packet's body, and inside its 8-byte header.
    for (tag, cut) in [("body", bounds[3] + 100), ("head", bounds[3] + 5)] {
        let (ok, text, err) = info(&format!("{tag}.aedat4"), &unfinished[..cut]);
        assert!(ok, "{tag}: {err}");
        assert!(
            text.contains(&format!("events       {}", 3 * per)),
            "{tag}: {text}"
        );
        assert!(err.contains("unfinished file"), "{tag}: {err}");
    }
    // Whole packets only: every event, no warning.
    let (ok, text, err) = info("whole.aedat4", &unfinished);
    assert!(
        ok && text.contains(&format!("events       {}", events.len())),
        "{text}{err}"
    );
    // A finished file (with its table) cut short is damaged, not unfinished.
    let (ok, _, err) = info("cut.aedat4", &good[..bounds[3] - head_len + start + 100]);
    assert!(!ok, "{err}");
}

/// Frame rates that are no rate are refused as such (they were taken as "none", or gave
/// "give --fps" though one was given); a folder named like an event file is called a folder.
#[test]
fn bad_frame_rates_and_folders_get_their_own_errors() {
    let dir = common::temp_dir("hardening-fps");
    let frames = dir.join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    for i in 0..3 {
        image::GrayImage::from_fn(8, 6, |x, _| image::Luma([(x * 20 + i * 5) as u8]))
            .save(frames.join(format!("f{i}.png")))
            .unwrap();
    }
    for fps in ["0", "-1", "nan", "inf", "1e-300", "1e7"] {
        refused(
            &["convert", "frames", "-o", "o.csv", &format!("--fps={fps}")],
            &dir,
            "frames per second",
        );
    }
    refused(
        &["convert", "frames", "-o", "o.csv"],
        &dir,
        "give a frame rate (--fps for convert, [run] fps for the daemon)",
    );
    std::fs::write(dir.join("r.toml"), "[run]\nfps = 1e-300\n").unwrap();
    refused(&["run", "--config", "r.toml"], &dir, "run.fps");
    std::fs::create_dir_all(dir.join("x.aedat4")).unwrap();
    refused(&["info", "x.aedat4"], &dir, "a folder, not an event file");
}

/// A file ffprobe cannot read gets one error line (ffprobe's own several lines joined).
#[test]
fn an_unreadable_video_is_one_error_line() {
    if Command::new("ffprobe").arg("-version").output().is_err() {
        skipped!("SKIPPED an_unreadable_video_is_one_error_line: no ffprobe");
        return;
    }
    let dir = common::temp_dir("hardening-video");
    // Not text (that is refused before ffprobe), not a video.
    let noise: Vec<u8> = (0..3000u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    std::fs::write(dir.join("bad.mp4"), noise).unwrap();
    let (code, err) = run(
        &["convert", "bad.mp4", "-o", "o.csv"],
        &dir,
        Duration::from_secs(30),
    );
    assert_eq!(code, Some(1), "{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(err.contains("not a readable video (ffprobe: "), "{err}");
}

/// A truncated input fails `convert` and `transcode` with exit status 1 and an error that says
/// the output is partial and where it is; nothing is left under the name asked for, and the
/// partial file reads.
#[test]
fn a_truncated_input_leaves_a_partial_output_that_says_so() {
    let dir = common::temp_dir("hardening-partial");
    let (w, h) = (64usize, 48usize);
    let mut y4m = format!("YUV4MPEG2 W{w} H{h} F30:1 Cmono\n").into_bytes();
    for i in 0..40 {
        y4m.extend_from_slice(b"FRAME\n");
        y4m.extend((0..w * h).map(|p| ((p % w + 3 * i) % 200 + 20) as u8));
    }
    y4m.truncate(y4m.len() - 100);
    std::fs::write(dir.join("cut.y4m"), &y4m).unwrap();
    let (code, err) = run(
        &["convert", "cut.y4m", "-o", "out.aedat4"],
        &dir,
        Duration::from_secs(60),
    );
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("cut.y4m"), "{err}");
    assert!(err.contains("out.partial.aedat4"), "{err}");
    assert!(!dir.join("out.aedat4").exists());
    let (code, info) = run(
        &["info", "out.partial.aedat4"],
        &dir,
        Duration::from_secs(20),
    );
    assert_eq!(code, Some(0), "{info}");

    // The same for transcode: an event file corrupt halfway through.
    let (code, err) = run(
        &[
            "convert",
            "cut.y4m",
            "--max-frames",
            "30",
            "-o",
            "whole.csv",
        ],
        &dir,
        Duration::from_secs(60),
    );
    assert_eq!(code, Some(0), "{err}");
    let whole = std::fs::read_to_string(dir.join("whole.csv")).unwrap();
    let lines: Vec<&str> = whole.lines().collect();
    assert!(lines.len() > 100, "{} lines", lines.len());
    let mut bad = lines[..lines.len() / 2].join("\n");
    bad.push_str("\n12,x,3,1\n");
    bad.push_str(&lines[lines.len() / 2..].join("\n"));
    std::fs::write(dir.join("bad.csv"), bad).unwrap();
    let (code, err) = run(
        // (a size given, so no pass over the input to find its extent fails first)
        &["transcode", "bad.csv", "out.raw", "--size", "64x48"],
        &dir,
        Duration::from_secs(20),
    );
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("bad.csv") && err.contains("out.partial.raw"),
        "{err}"
    );
    assert!(!dir.join("out.raw").exists());
    assert!(!dir.join("whole.partial.csv").exists());
}

/// An event file whose writer was killed mid-write (SIGKILL, a power cut) ends inside its last
/// word or line: `transcode` keeps every whole event before the cut and warns, exit status 0.
#[test]
fn an_event_file_cut_mid_write_reads_up_to_the_cut() {
    let dir = common::temp_dir("hardening-cut");
    let mut csv = String::from("t_us,x,y,on\n");
    for i in 0..500u32 {
        csv.push_str(&format!("{},{},{},{}\n", 10 * i, i % 64, i % 48, i % 2));
    }
    std::fs::write(dir.join("whole.csv"), &csv).unwrap();
    for out in ["whole.raw", "whole3.raw"] {
        let evt = if out == "whole.raw" { "2" } else { "3" };
        let (code, err) = run(
            &["transcode", "whole.csv", out, "--evt", evt],
            &dir,
            Duration::from_secs(20),
        );
        assert_eq!(code, Some(0), "{err}");
    }
    let whole: Vec<String> = csv.lines().map(str::to_owned).collect();
    // (file, bytes cut off its end, events lost)
    let cases = [
        ("whole.raw", 3usize, 1usize),
        ("whole3.raw", 1, 1),
        ("whole.csv", 4, 1),
    ];
    for (file, cut, lost) in cases {
        let bytes = std::fs::read(dir.join(file)).unwrap();
        let name = format!("cut-{file}");
        std::fs::write(dir.join(&name), &bytes[..bytes.len() - cut]).unwrap();
        let back = format!("{name}.csv");
        let (code, err) = run(&["transcode", &name, &back], &dir, Duration::from_secs(20));
        assert_eq!(code, Some(0), "{file}: {err}");
        assert!(err.contains("truncated input"), "{file}: {err}");
        let got = std::fs::read_to_string(dir.join(&back)).unwrap();
        let got: Vec<&str> = got.lines().collect();
        assert_eq!(got, whole[..whole.len() - lost], "{file}");
    }
}

/// Times at both ends of the i64 range go through both RAW encodings and come back exactly
/// (the header's time offset was refused beyond 2^62 by the same program that wrote it).
#[test]
fn raw_files_carry_times_at_both_ends_of_the_range() {
    let dir = common::temp_dir("hardening-raw-ends");
    let cases = [
        (
            "high.csv",
            "t_us,x,y,on\n9223372036854775000,1,1,1\n9223372036854775807,2,2,0\n",
        ),
        (
            "low.csv",
            "t_us,x,y,on\n-9223372036854775808,1,1,1\n-9223372036854775000,2,2,0\n",
        ),
    ];
    for (name, text) in cases {
        std::fs::write(dir.join(name), text).unwrap();
        for evt in ["2", "3"] {
            let raw = format!("{name}.{evt}.raw");
            let back = format!("{name}.{evt}.csv");
            for args in [
                vec!["transcode", "--evt", evt, "--size", "4x4", name, &raw],
                vec!["transcode", &raw, &back],
            ] {
                let (code, err) = run(&args, &dir, Duration::from_secs(20));
                assert_eq!(code, Some(0), "{args:?}: {err}");
            }
            assert_eq!(
                std::fs::read_to_string(dir.join(&back)).unwrap(),
                text,
                "{raw}"
            );
        }
    }
}

/// A few kilobytes of Zstd may not claim hundreds of megabytes: past 16 MiB, a packet may
/// decompress to at most 1024 times its size (it reached 773 MB from a 9 KB file). A flat
/// 1280 x 720 RGBA frame, the most compressible real packet, still decompresses.
#[test]
fn decompression_is_bounded_by_ratio() {
    use v2ce::format::aedat4::Compression;
    for c in [Compression::Zstd, Compression::Lz4] {
        let (mut packed, mut back) = (Vec::new(), Vec::new());
        let frame = vec![0u8; 1280 * 720 * 4];
        c.compress(&frame, &mut packed).unwrap();
        c.decompress(&packed, &mut back).unwrap();
        assert_eq!(back, frame);
        let bomb = vec![7u8; 64 << 20];
        c.compress(&bomb, &mut packed).unwrap();
        let ratio = bomb.len() / packed.len();
        let result = c.decompress(&packed, &mut back);
        if ratio > 1024 {
            let err = result.unwrap_err().to_string();
            assert!(err.contains("1024 times"), "{err}");
            // It stopped one byte past the bound.
            assert!(
                back.len() <= (16 << 20) + 1,
                "{c:?}: {} bytes held",
                back.len()
            );
        } else {
            // LZ4 cannot compress more than about 255 times: 64 MiB needs 256 KiB of input.
            assert!(result.is_ok(), "{c:?}: ratio {ratio}");
        }
    }
}

/// A replay speed too slow to mean anything is refused, and the daemon's deadline ends even a
/// wait for a frame due far in the future (`--replay-speed 1e-300` ran past `--duration`).
#[test]
fn replay_speeds_are_bounded_and_the_deadline_cuts_waits_short() {
    let dir = common::temp_dir("hardening-replay");
    for v in ["1e-300", "0", "nan", "1e300"] {
        refused(
            &[
                "run",
                "--source",
                "fixture",
                "--out",
                "r.csv",
                &format!("--replay-speed={v}"),
            ],
            &dir,
            "run.replay_speed",
        );
        refused(
            &["bench", "--seconds", "1", &format!("--replay-speed={v}")],
            &dir,
            "--replay-speed",
        );
    }
    // The slowest speed allowed: the second frame is due 33 s in; the deadline stops it at 1 s.
    let started = Instant::now();
    let (code, err) = run(
        &[
            "run",
            "--source",
            "fixture",
            "--out",
            "r.csv",
            "--replay-speed",
            "0.001",
            "--duration",
            "1",
        ],
        &dir,
        Duration::from_secs(20),
    );
    assert_eq!(code, Some(0), "{err}");
    assert!(started.elapsed() < Duration::from_secs(15), "{err}");
}

/// Under a file-size limit (`ulimit -f`) a command that writes past it fails like a full disk:
/// exit status 1 with one error line naming what was written, not death by SIGXFSZ.
#[test]
fn a_file_size_limit_is_an_error_not_a_signal() {
    let dir = common::temp_dir("hardening-fsize");
    for (args, out) in [
        (
            vec!["convert", "fixture", "--max-frames", "40", "-o", "f.csv"],
            "f.csv",
        ),
        (vec!["transcode", "f-src.csv", "t.csv"], "t.csv"),
    ] {
        if args[0] == "transcode" {
            let rows: String = (0..200_000).map(|i| format!("{i},1,1,1\n")).collect();
            std::fs::write(dir.join("f-src.csv"), format!("t_us,x,y,on\n{rows}")).unwrap();
        }
        let done = under_file_size_limit(&args, &dir, 64 * 1024);
        let err = String::from_utf8_lossy(&done.stderr);
        assert_eq!(
            done.status.code(),
            Some(1),
            "{args:?}: {:?} {err}",
            done.status
        );
        let last = err.lines().last().unwrap_or_default();
        assert!(last.starts_with("v2ce: error: "), "{args:?}: {err}");
        assert!(
            last.contains("too large") && last.contains("partial"),
            "{args:?}: {err}"
        );
        assert!(
            !dir.join(out).exists(),
            "{out} was written whole under the limit"
        );
    }
}

/// Runs v2ce with `args` in `dir` under a file-size limit of `bytes` (`ulimit -f`).
fn under_file_size_limit(args: &[&str], dir: &Path, bytes: u64) -> std::process::Output {
    use std::os::unix::process::CommandExt;
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_v2ce"));
    cmd.args(args)
        .current_dir(dir)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    unsafe {
        cmd.pre_exec(move || {
            let cap = libc::rlimit {
                rlim_cur: bytes,
                rlim_max: bytes,
            };
            if libc::setrlimit(libc::RLIMIT_FSIZE, &cap) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    cmd.output().unwrap()
}

/// A daemon's file output that fills its disk (here a file-size limit) reports as sent exactly
/// the events its file holds, and the file reads back: the failed write is cut back to the last
/// whole flush, not left as part of an event, and events still in a buffer are not called sent.
#[test]
fn a_full_disk_leaves_a_file_holding_exactly_what_was_reported_sent() {
    let dir = common::temp_dir("hardening-full-disk");
    for out in ["full.csv", "full.aedat4", "full.raw"] {
        let args = [
            "run",
            "--source",
            "fixture",
            "--out",
            out,
            "--udp",
            "",
            "--replay-speed",
            "4",
            "--duration",
            "5",
        ];
        let done = under_file_size_limit(&args, &dir, 512 * 1024);
        let err = String::from_utf8_lossy(&done.stderr);
        assert_eq!(done.status.code(), Some(1), "{out}: {err}");
        let line = err
            .lines()
            .find(|l| l.contains(&format!("file {out}")) && l.contains("events sent"))
            .unwrap_or_else(|| panic!("{out}: no closing line for the file: {err}"));
        let sent: u64 = line
            .split("): ")
            .nth(1)
            .and_then(|rest| rest.split_whitespace().next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("{out}: no count in {line}"));
        assert!(sent > 0, "{line}");
        let back = v2ce::format::read_events(&dir.join(out))
            .unwrap_or_else(|e| panic!("{out} does not read back: {e}"));
        assert_eq!(back.events.len() as u64, sent, "{out}: {line}");
    }
}
