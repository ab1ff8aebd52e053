//! Third-party readers (faery, aedat, dv-processing, aestream, expelliarmus, NumPy, h5py from
//! PyPI) read back what v2ce writes.
//!
//! The Python side is `tests/python/crosscheck.py`, run with the interpreter in `V2CE_PYTHON`
//! or the project's `.venv` (which `.ci/run` creates). Without one these tests print why they
//! skip, unless `V2CE_REQUIRE_PYTHON` is set (as in CI), where a missing interpreter fails.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use common::{script, start_receiver, temp_dir};

use v2ce::event::Event;
use v2ce::format::{self, csv, raw, Compression, Format};

/// Runs `crosscheck.py file READER PATH EXPECTED [OFFSET]` and asserts an exact match.
fn check_file(py: &Path, reader: &str, path: &Path, expected: &Path, offset: i64) {
    let out = Command::new(py)
        .arg(script())
        .args(["file", reader])
        .arg(path)
        .arg(expected)
        .arg(offset.to_string())
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{reader} {}: {}", path.display(), text.trim());
    assert!(
        out.status.success(),
        "{reader} on {}: {text}",
        path.display()
    );
}

/// A test stream: a sweeping bar from a Unix-epoch start (so EVT files need their offset).
fn stream() -> (u16, u16, Vec<Event>) {
    let rec = v2ce::sweeping_bar::recording(128, 96, 500_000, 3);
    let t0 = 1_700_000_000_000_000;
    let events = rec
        .events
        .events()
        .iter()
        .map(|e| Event::new(e.t + t0, e.x, e.y, e.on))
        .collect();
    (rec.width, rec.height, events)
}

fn write_all(path: &Path, format: Format, w: u16, h: u16, events: &[Event]) {
    let mut enc = format::create(path, format, w, h).unwrap();
    for chunk in events.chunks(5000) {
        enc.write(chunk).unwrap();
    }
    enc.finish().unwrap();
}

fn offset(format: Format, events: &[Event]) -> i64 {
    let first = events.first().map_or(0, |e| e.t);
    match format {
        Format::Evt2 => raw::time_offset_for(raw::Evt::Evt2, first),
        Format::Evt3 => raw::time_offset_for(raw::Evt::Evt3, first),
        _ => 0,
    }
}

#[test]
fn files_we_write_are_read_back_by_faery_aedat_and_dv_processing() {
    let py = python_or_skip!("files_we_write_are_read_back_by_faery_aedat_and_dv_processing");
    let _one_at_a_time = one_at_a_time();
    let dir = temp_dir("readers");
    let (w, h, events) = stream();
    assert!(events.len() > 10_000);
    // A second, sparse stream spanning several EVT 3.0 wraps and one EVT 2.0 wrap.
    let sparse: Vec<Event> = (0..300i64)
        .map(|i| {
            Event::new(
                i * 70_000_000 + i * 13,
                (i % 128) as u16,
                (i % 96) as u16,
                i % 2 == 0,
            )
        })
        .collect();
    assert!(sparse[299].t > 1 << 34);
    for (name, events) in [("bar", &events), ("sparse", &sparse)] {
        let expected = dir.join(format!("{name}-expected.csv"));
        csv::write(&expected, events).unwrap();
        for (file, format, readers) in [
            (
                "lz4.aedat4",
                Format::Aedat4(Compression::Lz4),
                &["faery", "aedat", "dv", "aestream"][..],
            ),
            (
                "zstd.aedat4",
                Format::Aedat4(Compression::Zstd),
                &["faery", "aedat", "dv"],
            ),
            (
                "none.aedat4",
                Format::Aedat4(Compression::None),
                &["faery", "aedat", "dv"],
            ),
            // The default .raw: expelliarmus reads it as faery does (both mis-time EVT 3.0).
            ("e2.raw", Format::Evt2, &["faery", "expelliarmus"]),
            ("e3.raw", Format::Evt3, &["faery"]),
            ("e.csv", Format::Csv, &["faery"]),
            ("e.npz", Format::Npz, &["numpy"]),
            // The sparse stream outgrows u32 times: events/t is i64 there.
            ("e.h5", Format::Hdf5, &["h5py"]),
        ] {
            let path = dir.join(format!("{name}-{file}"));
            write_all(&path, format, w, h, events);
            // Our own decoder reads the same file to the same events the readers must match.
            let ours = format::read_events(&path).unwrap();
            assert!(ours.events.events() == &events[..], "our decoder on {file}");
            for reader in readers {
                // The sparse stream (one event every 70 s, over 5 hours) defeats two readers
                // where faery, aedat and dv-processing agree with us: aestream 0.6.4 returns
                // garbage from its 255th event on, and expelliarmus 1.1.12 does not follow
                // EVT 2.0's 34-bit time across its wrap (4.8 hours). They are held to the
                // realistic stream.
                if matches!(*reader, "aestream" | "expelliarmus") && name == "sparse" {
                    continue;
                }
                check_file(&py, reader, &path, &expected, offset(format, events));
            }
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn our_decoders_agree_with_faery_on_every_recording() {
    let py = python_or_skip!("our_decoders_agree_with_faery_on_every_recording");
    let _one_at_a_time = one_at_a_time();
    let data = std::env::var_os("V2CE_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    if !data.is_dir() {
        skipped!(
            "SKIPPED our_decoders_agree_with_faery_on_every_recording: no recordings at {}",
            data.display()
        );
        return;
    }
    let dir = temp_dir("faery-agree");
    for name in [
        "davis346/davis346.aedat4",
        "dvxplorer/data_sample.aedat4",
        "prophesee/sparklers.raw",
        "prophesee/evt2_sample.raw",
        "prophesee/evt3_sample.raw",
    ] {
        let path = data.join(name);
        let rec = format::read_events(&path).unwrap();
        let ours = dir.join("ours.csv");
        csv::write(&ours, rec.events.events()).unwrap();
        check_file(&py, "faery", &path, &ours, 0);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn faery_and_a_spif_decoder_receive_what_our_udp_sink_sends() {
    let _one_at_a_time = one_at_a_time();
    use v2ce::sink::udp::{EmitMode, UdpFormat, UdpSink, UdpSinkConfig};
    use v2ce::sink::Sink;
    let py = python_or_skip!("faery_and_a_spif_decoder_receive_what_our_udp_sink_sends");
    let dir = temp_dir("udp");
    let (w, h, events) = stream();
    let expected = dir.join("expected.csv");
    csv::write(&expected, &events).unwrap();
    for format in [
        UdpFormat::T64X16Y16On8,
        UdpFormat::T32X16Y15On1,
        UdpFormat::SpifTimestamped,
        UdpFormat::Spif,
    ] {
        let port = common::free_udp_port();
        let name = match format {
            UdpFormat::Spif | UdpFormat::SpifTimestamped => "spif",
            f => f.name(),
        };
        let mut child = start_receiver(
            &py,
            &[
                "udp".into(),
                name.into(),
                port.to_string(),
                expected.display().to_string(),
                w.to_string(),
                h.to_string(),
            ],
        );
        let config = UdpSinkConfig {
            address: format!("127.0.0.1:{port}"),
            format,
            payload: 1472,
            // Paced so a Python receiver on a shared 2-core machine keeps up.
            rate: 1_000,
            emit: EmitMode::Asap,
            ..UdpSinkConfig::default()
        };
        let mut sink = UdpSink::new(&config, 1.0).unwrap();
        for chunk in events.chunks(1000) {
            sink.send(chunk).unwrap();
        }
        sink.finish().unwrap();
        let status = child.wait().unwrap();
        assert!(
            status.success(),
            "{format:?}: receiver failed ({status}), {:?}",
            sink.stats()
        );
        assert_eq!(sink.stats().events_dropped, 0);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn dv_processing_network_reader_receives_what_our_tcp_sink_sends() {
    use v2ce::sink::tcp::{TcpConfig, TcpSink};
    use v2ce::sink::Sink;
    let py = python_or_skip!("dv_processing_network_reader_receives_what_our_tcp_sink_sends");
    let _one_at_a_time = one_at_a_time();
    let dir = temp_dir("tcp");
    let (w, h, events) = stream();
    let expected = dir.join("expected.csv");
    csv::write(&expected, &events).unwrap();
    let mut sink = TcpSink::new(TcpConfig::new("127.0.0.1:0", w, h)).unwrap();
    let port = sink.local_addr().port();
    let mut child = start_receiver(
        &py,
        &[
            "tcp".into(),
            port.to_string(),
            expected.display().to_string(),
        ],
    );
    for _ in 0..2000 {
        if sink.client_count() == 1 {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    assert_eq!(sink.client_count(), 1);
    for chunk in events.chunks(2000) {
        sink.send(chunk).unwrap();
    }
    // Stay connected, as a live stream does, until the reader has everything.
    let status = child.wait().unwrap();
    sink.finish().unwrap();
    assert!(
        status.success(),
        "receiver failed ({status}), {:?}",
        sink.stats()
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The tests of this file run one at a time: a UDP receiver on a 2-core machine loses datagrams
/// when the other tests' readers take the cores (seen: aestream 0.44% short at 640x480 while
/// faery and dv-processing read files beside it).
fn one_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

/// aestream's UDP receiver (the usual SPIF receiver, and the entry point of its PyTorch, Norse
/// and snnTorch tensors) gets every event the daemon sends with its default settings (the
/// motion model with its live cap keeper, drop-oldest queues, emission at event time, 512-byte
/// datagrams that fit aestream's 512-byte reads), counted per pixel against the daemon's own
/// recording of the run (`--out`, which never drops: what it holds is what was sent), at
/// 346x260 and at 640x480 (a million events a second, about 9,000 datagrams a second). Also
/// checked: the recording equals what the UDP output reports sent. The kernel's default
/// receive buffer holds some 20 ms of datagrams at 640x480, so a receiving thread kept off its
/// core longer than that loses some (the daemon cannot see it: UDP); on a loaded machine that
/// happened (0.04% once in CI before issue 25, 3-7% beside two busy builds). So what holds
/// under any load is checked: every event is received, or every one missing is accounted for
/// by the datagrams the kernel dropped at the receiver's full buffer (its socket's `drops` in
/// /proc/net/udp, at most 128 events each), and no pixel ever gets more than it was sent. Meant
/// for release builds, as CI runs it: a debug build cannot keep up with 640x480 in real time.
#[test]
fn aestream_receives_every_event_of_the_default_daemon() {
    let py = python_or_skip!("aestream_receives_every_event_of_the_default_daemon");
    let _one_at_a_time = one_at_a_time();
    let dir = temp_dir("aestream");
    for (w, h) in [(346u16, 260u16), (640, 480)] {
        let size = format!("{w}x{h}");
        let attempt = |n: usize| -> Result<String, String> {
            let recorded = dir.join(format!("recorded-{size}-{n}.csv"));
            let port = common::free_udp_port();
            let mut receiver = start_receiver(
                &py,
                &[
                    "aestream".into(),
                    port.to_string(),
                    recorded.display().to_string(),
                    w.to_string(),
                    h.to_string(),
                ],
            );
            let run = Command::new(env!("CARGO_BIN_EXE_v2ce"))
                .args(["run", "--source", "fixture", "--size", &size, "--json"])
                .args(["--udp", &format!("127.0.0.1:{port}")])
                .arg("--out")
                .arg(&recorded)
                .output()
                .unwrap();
            assert!(
                run.status.success(),
                "{}",
                String::from_utf8_lossy(&run.stderr)
            );
            let report: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
            let sinks = report["stats"]["sinks"].as_array().unwrap();
            let udp = sinks
                .iter()
                .find(|s| s["recording"] == false)
                .unwrap_or_else(|| panic!("no UDP output in {report}"));
            let file = sinks.iter().find(|s| s["recording"] == true).unwrap();
            // The recording holds exactly what the UDP output sent.
            assert_eq!(
                udp["stats"]["events_sent"], file["stats"]["events_sent"],
                "{report}"
            );
            assert_eq!(udp["stats"]["events_dropped"], 0, "{report}");
            let status = receiver.wait().unwrap();
            let summary = format!(
                "frames {} (dropped {}), udp {}",
                report["stats"]["frames_in"], report["stats"]["frames_dropped"], udp["stats"]
            );
            if status.success() {
                Ok(summary)
            } else {
                Err(summary)
            }
        };
        match attempt(1) {
            Ok(summary) => {
                eprintln!("{size}: every event sent reached aestream's socket; {summary}")
            }
            Err(summary) => panic!("{size}: aestream did not get what was sent: {summary}"),
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
