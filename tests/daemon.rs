//! The live daemon (`v2ce run`) end to end, driven by the bundled fixture video (and the APS
//! frames of ../shared/data/davis346 when present): real receivers on loopback get exactly what
//! `v2ce convert` writes for the same frames and seed; signals, stalled receivers and broken
//! sources end or degrade the run as documented.

mod common;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use common::{start_receiver, temp_dir};

fn v2ce() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_v2ce"));
    c.env_remove("NOTIFY_SOCKET").env_remove("JOURNAL_STREAM");
    c
}

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(v2ce::frame::fixture::PATH)
}

/// `v2ce convert INPUT -o OUT ARGS`, which must succeed.
fn convert(input: &Path, out: &Path, args: &[&str]) {
    let o = v2ce()
        .arg("convert")
        .arg(input)
        .arg("-o")
        .arg(out)
        .args(args)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// A running daemon whose log lines arrive on a channel.
struct Daemon {
    child: Child,
    lines: mpsc::Receiver<String>,
    log: Vec<String>,
}

impl Daemon {
    /// `v2ce run ARGS --json`, with a stats line every 0.2 s unless ARGS set the interval.
    fn start(args: &[&str]) -> Daemon {
        let mut command = v2ce();
        command.arg("run").args(args).arg("--json");
        if !args.contains(&"--stats-interval") {
            command.args(["--stats-interval", "0.2"]);
        }
        let mut child = command
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let stderr = child.stderr.take().unwrap();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(|l| l.ok()) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Daemon {
            child,
            lines,
            log: Vec::new(),
        }
    }

    /// Waits for a log line containing `needle` and returns it.
    fn wait_for(&mut self, needle: &str) -> String {
        loop {
            let line = self
                .lines
                .recv_timeout(Duration::from_secs(60))
                .unwrap_or_else(|_| panic!("no log line with {needle:?}; log: {:#?}", self.log));
            self.log.push(line.clone());
            if line.contains(needle) {
                return line;
            }
        }
    }

    /// Waits for the exit; returns success, the JSON report and the whole log.
    fn finish(mut self) -> (bool, serde_json::Value, Vec<String>) {
        let mut stdout = String::new();
        use std::io::Read;
        self.child
            .stdout
            .take()
            .unwrap()
            .read_to_string(&mut stdout)
            .unwrap();
        let status = self.child.wait().unwrap();
        while let Ok(line) = self.lines.recv_timeout(Duration::from_secs(5)) {
            self.log.push(line);
        }
        let report = serde_json::from_str(stdout.trim()).unwrap_or(serde_json::Value::Null);
        (status.success(), report, self.log)
    }

    fn signal(&self, sig: i32) {
        // SAFETY: plain kill(2) on our own child.
        assert_eq!(unsafe { libc::kill(self.child.id() as i32, sig) }, 0);
    }
}

fn run_to_end(args: &[&str]) -> (bool, serde_json::Value, Vec<String>) {
    Daemon::start(args).finish()
}

fn stat(report: &serde_json::Value, key: &str) -> u64 {
    report["stats"][key]
        .as_u64()
        .unwrap_or_else(|| panic!("no stats.{key} in {report}"))
}

fn same_events(a: &Path, b: &Path) {
    let ea = v2ce::format::read_events(a).unwrap();
    let eb = v2ce::format::read_events(b).unwrap();
    assert!(!ea.events.is_empty(), "no events in {}", a.display());
    assert_eq!(ea.events.len(), eb.events.len(), "event counts differ");
    assert!(
        ea.events.events() == eb.events.events(),
        "{} and {} differ",
        a.display(),
        b.display()
    );
}

#[test]
fn with_no_camera_and_no_config_it_replays_the_bundled_fixture_to_local_udp() {
    let (ok, report, log) = run_to_end(&["--duration", "1.5"]);
    assert!(ok, "{log:#?}");
    let first = &log[0];
    assert!(
        first.contains("no camera found") && first.contains("bundled fixture"),
        "{first}"
    );
    assert!(first.contains("udp 127.0.0.1:3333"), "{first}");
    assert_eq!(report["end"], "duration");
    // Paced by the video's own clock: at most 1.5 s x 30 fps (+1 for the frame at t = 0) of
    // the 180 frames, however fast the machine; fewer only if it is overloaded.
    let frames = stat(&report, "frames_in");
    assert!((1..=46).contains(&frames), "{frames} frames");
    assert!(stat(&report, "events_out") > 0);
    assert!(
        log.iter().any(|l| l.contains("latency p50")),
        "no stats line"
    );
}

#[test]
fn faery_receives_over_udp_exactly_what_convert_writes() {
    let py = python_or_skip!("faery_receives_over_udp_exactly_what_convert_writes");
    let dir = temp_dir("daemon-udp");
    let expected = dir.join("expected.csv");
    let args = ["--size", "320x240", "--max-frames", "60", "--seed", "7"];
    convert(&fixture(), &expected, &args);
    let port = common::free_udp_port();
    let mut receiver = start_receiver(
        &py,
        &[
            "udp".into(),
            "t64_x16_y16_on8".into(),
            port.to_string(),
            expected.display().to_string(),
            "320".into(),
            "240".into(),
        ],
    );
    // The rate cap keeps a Python receiver on a loaded machine from losing datagrams.
    let config = dir.join("v2ce.toml");
    std::fs::write(
        &config,
        format!(
            "[run]\nudp = \"127.0.0.1:{port}\"\nudp_format = \"t64_x16_y16_on8\"\nudp_rate = 3000\n\
             queue_policy = \"block\"\n"
        ),
    )
    .unwrap();
    let fixture = fixture().display().to_string();
    let (ok, report, log) = run_to_end(
        &[
            &["--config", config.to_str().unwrap(), "--source", &fixture],
            &args[..],
        ]
        .concat(),
    );
    assert!(ok, "{log:#?}");
    assert_eq!(report["end"], "max-frames");
    assert_eq!(stat(&report, "frames_in"), 60);
    let status = receiver.wait().unwrap();
    assert!(status.success(), "receiver: {status}; daemon: {report}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn dv_processing_receives_over_tcp_exactly_what_convert_writes() {
    let py = python_or_skip!("dv_processing_receives_over_tcp_exactly_what_convert_writes");
    let dir = temp_dir("daemon-tcp");
    let expected = dir.join("expected.csv");
    let args = ["--size", "346x260", "--max-frames", "90", "--seed", "11"];
    convert(&fixture(), &expected, &args);
    let fixture = fixture().display().to_string();
    let mut daemon = Daemon::start(
        &[
            &[
                "--source",
                &fixture,
                "--udp",
                "",
                "--tcp",
                "127.0.0.1:0",
                "--wait-for-client",
                "--queue-policy",
                "block",
            ],
            &args[..],
        ]
        .concat(),
    );
    let first = daemon.wait_for("tcp 127.0.0.1:");
    let port = first
        .split("tcp 127.0.0.1:")
        .nth(1)
        .and_then(|s| s.split(|c: char| !c.is_ascii_digit()).next())
        .unwrap()
        .to_string();
    let mut receiver = start_receiver(&py, &["tcp".into(), port, expected.display().to_string()]);
    let status = receiver.wait().unwrap();
    let (ok, report, log) = daemon.finish();
    assert!(ok, "{log:#?}");
    assert!(status.success(), "receiver: {status}; daemon: {report}");
    assert_eq!(stat(&report, "frames_in"), 90);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn sigterm_with_the_block_policy_loses_nothing_already_queued() {
    let dir = temp_dir("daemon-sigterm");
    let out = dir.join("live.csv");
    let fixture = fixture().display().to_string();
    // Replayed 40x faster than real time (at least 150 ms for the 180 frames), capture outruns
    // Stage 1 and the queues fill up; a stats line every 20 ms shows it.
    let mut daemon = Daemon::start(&[
        "--stats-interval",
        "0.02",
        "--source",
        &fixture,
        "--udp",
        "",
        "--out",
        out.to_str().unwrap(),
        "--seed",
        "3",
        "--replay-speed",
        "40",
        "--queue-policy",
        "block",
    ]);
    let busy = daemon.wait_for("capture=4/4");
    daemon.signal(libc::SIGTERM);
    let (ok, report, log) = daemon.finish();
    assert!(ok, "{log:#?}");
    assert_eq!(report["end"], "stopped", "{busy}");
    let frames = stat(&report, "frames_in");
    assert!(frames < 180, "the signal came after the end");
    assert_eq!(stat(&report, "frames_processed"), frames);
    assert_eq!(stat(&report, "frames_dropped"), 0);
    let expected = dir.join("expected.csv");
    convert(
        Path::new(&fixture),
        &expected,
        &["--seed", "3", "--max-frames", &frames.to_string()],
    );
    same_events(&out, &expected);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn absent_and_stalled_receivers_do_not_stop_the_frames() {
    // A UDP port nobody listens on, a TCP client that connects and never reads, and Stage 1
    // outrun 50x by the replay: frames keep flowing, every loss is counted.
    let free = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let fixture = fixture().display().to_string();
    let udp = free.to_string();
    let mut daemon = Daemon::start(&[
        "--source",
        &fixture,
        "--udp",
        &udp,
        "--tcp",
        "127.0.0.1:0",
        "--wait-for-client",
        "--replay-speed",
        "50",
        "--queue-policy",
        "drop-oldest",
    ]);
    let first = daemon.wait_for("tcp 127.0.0.1:");
    let port: u16 = first
        .split("tcp 127.0.0.1:")
        .nth(1)
        .and_then(|s| s.split(|c: char| !c.is_ascii_digit()).next())
        .and_then(|p| p.parse().ok())
        .unwrap();
    let stalled = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    let (ok, report, log) = daemon.finish();
    drop(stalled);
    assert!(ok, "{log:#?}");
    assert_eq!(report["end"], "source-ended");
    assert_eq!(stat(&report, "frames_in"), 180);
    let processed = stat(&report, "frames_processed");
    let dropped = stat(&report, "frames_dropped");
    assert_eq!(processed + dropped, 180, "{report}");
    assert!(dropped > 0, "Stage 1 kept up with 50x real time?");
    let sinks = report["stats"]["sinks"].as_array().unwrap();
    let tcp = sinks
        .iter()
        .find(|s| s["sink"].as_str().unwrap().starts_with("tcp"))
        .unwrap();
    // Dropped packets, a client disconnected as too slow, or (when shedding late frames left
    // too few events to fill its socket before the end) the client cut off at the stop with
    // its queue undelivered: each is a counted loss.
    let tcp_losses = tcp["stats"]["events_dropped"].as_u64().unwrap()
        + tcp["stats"]["clients_dropped"].as_u64().unwrap()
        + tcp["stats"]["clients_abandoned"].as_u64().unwrap();
    assert!(tcp_losses > 0, "the stalled client lost nothing? {tcp}");
    assert!(sinks.iter().all(|s| s["failed"].is_null()), "{sinks:?}");
}

#[test]
fn a_source_that_breaks_mid_stream_ends_the_run_cleanly_with_a_message() {
    let dir = temp_dir("daemon-broken");
    // The fixture cut in the middle of frame 20.
    let mut y4m = Vec::new();
    std::io::Read::read_to_end(
        &mut zstd::stream::read::Decoder::new(std::fs::File::open(fixture()).unwrap()).unwrap(),
        &mut y4m,
    )
    .unwrap();
    let header = y4m.iter().position(|&b| b == b'\n').unwrap() + 1;
    let frame = 6 + 640 * 480;
    let broken = dir.join("broken.y4m");
    std::fs::write(&broken, &y4m[..header + 20 * frame + frame / 2]).unwrap();
    let out = dir.join("live.aedat4");
    let (ok, report, log) = run_to_end(&[
        "--source",
        broken.to_str().unwrap(),
        "--udp",
        "",
        "--out",
        out.to_str().unwrap(),
        "--replay-speed",
        "10",
        "--queue-policy",
        "block",
    ]);
    assert!(!ok, "a broken source must fail the run");
    assert!(
        report["end"]["source-failed"]
            .as_str()
            .is_some_and(|m| m.contains("broken.y4m")),
        "{report}"
    );
    let last = log.last().unwrap();
    assert!(
        last.contains("error") && last.contains("the source failed"),
        "{last}"
    );
    // Everything before the break was written, and the file is complete.
    assert_eq!(stat(&report, "frames_in"), 20);
    let expected = dir.join("expected.aedat4");
    convert(&fixture(), &expected, &["--max-frames", "20"]);
    same_events(&out, &expected);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn the_aps_frames_of_a_real_recording_stream_as_converted() {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/davis346/davis346.aedat4");
    if !path.exists() {
        skipped!("SKIPPED: {} is absent", path.display());
        return;
    }
    let dir = temp_dir("daemon-aps");
    let expected = dir.join("expected.raw");
    convert(&path, &expected, &["--seed", "5"]);
    let out = dir.join("live.raw");
    let (ok, report, log) = run_to_end(&[
        "--source",
        path.to_str().unwrap(),
        "--udp",
        "",
        "--out",
        out.to_str().unwrap(),
        "--seed",
        "5",
        "--replay-speed",
        "2",
        "--queue-policy",
        "block",
    ]);
    assert!(ok, "{log:#?}");
    assert_eq!(report["end"], "source-ended");
    same_events(&out, &expected);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn systemd_gets_readiness_the_stats_line_and_stopping() {
    use std::os::unix::net::UnixDatagram;
    let dir = temp_dir("daemon-notify");
    let path = dir.join("notify.sock");
    let socket = UnixDatagram::bind(&path).unwrap();
    socket
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_v2ce"))
        .args(["run", "--duration", "1", "--stats-interval", "0.3"])
        .env("NOTIFY_SOCKET", &path)
        .env_remove("JOURNAL_STREAM")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut messages = Vec::new();
    let mut buf = [0u8; 4096];
    socket
        .set_read_timeout(Some(Duration::from_millis(500)))
        .unwrap();
    while let Ok(n) = socket.recv(&mut buf) {
        messages.push(String::from_utf8_lossy(&buf[..n]).to_string());
    }
    let all = messages.join("\n");
    assert!(
        messages.first().is_some_and(|m| m.contains("READY=1")),
        "{all}"
    );
    assert!(
        messages
            .iter()
            .any(|m| m.contains("STATUS=frames in") && m.contains("latency p50")),
        "{all}"
    );
    assert!(
        messages.last().is_some_and(|m| m.contains("STOPPING=1")),
        "{all}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// With `wait_for_client`, READY goes out while the daemon waits for its first client (a
/// service manager's start timeout would kill it otherwise), and a stop while waiting ends it.
#[test]
fn a_daemon_waiting_for_a_client_is_ready() {
    use std::os::unix::net::UnixDatagram;
    let dir = temp_dir("daemon-notify-wait");
    let path = dir.join("notify.sock");
    let socket = UnixDatagram::bind(&path).unwrap();
    socket
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let mut child = Command::new(env!("CARGO_BIN_EXE_v2ce"))
        .args(["run", "--udp", "", "--wait-for-client", "--tcp"])
        .arg(format!("127.0.0.1:{port}"))
        .env("NOTIFY_SOCKET", &path)
        .env_remove("JOURNAL_STREAM")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut buf = [0u8; 4096];
    let n = socket.recv(&mut buf).unwrap_or(0);
    let first = String::from_utf8_lossy(&buf[..n]).to_string();
    // SIGTERM while it still waits: it stops.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let status = child.wait().unwrap();
    assert!(
        first.contains("READY=1") && first.contains("waiting for a TCP client"),
        "{first:?}"
    );
    assert!(status.code().is_some(), "{status:?}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A recording under the default `drop-oldest` on a machine that cannot keep up (the fixture
/// replayed at 8 times real time at 1280x720): the file holds exactly the events its closing
/// line and the report say were written, none dropped; frames the pipeline shed are on the log
/// as the recording's loss, and the network output's losses are counted as its own.
#[test]
fn a_recording_under_drop_oldest_holds_what_it_says_and_names_its_loss() {
    let dir = common::temp_dir("daemon-starved-recording");
    let out = dir.join("rec.aedat4");
    let (ok, report, log) = run_to_end(&[
        "--source",
        fixture().to_str().unwrap(),
        "--replay-speed",
        "8",
        "--size",
        "1280x720",
        "--max-frames",
        "90",
        "--udp",
        "127.0.0.1:9",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{log:#?}");
    let sinks = report["stats"]["sinks"].as_array().unwrap();
    let file = sinks
        .iter()
        .find(|s| s["recording"] == true)
        .unwrap_or_else(|| panic!("no recording in {report}"));
    let written = v2ce::format::read_events(&out).unwrap().events.len() as u64;
    assert_eq!(file["stats"]["events_sent"].as_u64(), Some(written));
    assert_eq!(file["stats"]["events_dropped"].as_u64(), Some(0));
    assert_eq!(stat(&report, "events_out"), written);
    let line = log
        .iter()
        .find(|l| l.contains("rec.aedat4") && l.contains("events sent"))
        .unwrap_or_else(|| panic!("no closing line for the file: {log:#?}"));
    assert!(
        line.contains(&format!("{written} events sent, 0 dropped")),
        "{line}"
    );
    let shed = stat(&report, "frames_dropped") - stat(&report, "frames_out_of_order");
    if shed > 0 {
        assert!(
            line.contains(&format!("lacks the events of the {shed} frames")),
            "{line}"
        );
    }
    // Every output: what it was given is what it sent, lost, or had refused (UDP to a closed
    // port).
    for s in sinks {
        let st = &s["stats"];
        let n = |k: &str| st[k].as_u64().unwrap();
        assert_eq!(
            n("events_in"),
            n("events_sent") + n("events_dropped") + n("events_refused"),
            "{s}"
        );
        assert!(n("events_evicted") <= n("events_dropped"), "{s}");
    }
    eprintln!(
        "{written} events recorded; {shed} of {} frames shed upstream",
        stat(&report, "frames_in")
    );
}
