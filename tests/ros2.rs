//! ROS 2 without ROS, against real independent implementations on loopback: Cyclone DDS (PyPI
//! `cyclonedds`, the DDS of `rmw_cyclonedds`) subscribing to the `ros2` sink and publishing
//! images into `--source ros2:...`, rosbags (PyPI) reading our `.mcap` and writing the image
//! bags we read, faery decoding the EVT 3.0 payloads (tests/python/ros2_peer.py).
//!
//! Each test uses its own DDS domain (from the process id), so parallel runs do not meet.

mod common;

use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

fn v2ce() -> Command {
    Command::new(env!("CARGO_BIN_EXE_v2ce"))
}

/// `python tests/python/ros2_peer.py`, its arguments to follow.
fn peer_cmd(py: &Path) -> Command {
    let mut c = Command::new(py);
    c.arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/ros2_peer.py"));
    c
}

/// A domain of its own for each test of this process (ROS 2 allows 0 to 232).
fn domain(test: u32) -> String {
    (((std::process::id() % 46) * 5 + test) % 230 + 1).to_string()
}

/// The interpreter when it has cyclonedds, rosbags and faery; else a printed reason (a failure
/// under `V2CE_REQUIRE_PYTHON`).
fn peer_python(test: &str) -> Option<PathBuf> {
    let py = common::python()?;
    let ok = Command::new(&py)
        .args(["-c", "import cyclonedds, rosbags, faery, numpy"])
        .status()
        .is_ok_and(|s| s.success());
    if !ok {
        if std::env::var_os("V2CE_REQUIRE_PYTHON").is_some() {
            panic!("V2CE_REQUIRE_PYTHON is set but the venv lacks cyclonedds/rosbags/faery");
        }
        skipped!("SKIPPED {test}: the venv lacks cyclonedds, rosbags or faery (tests/python/requirements.txt)");
        return None;
    }
    Some(py)
}

/// Runs `command` to its end and asserts it succeeded (its stderr as the message).
fn succeeds(command: &mut Command) -> std::process::Output {
    let out = command.output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// Events of a file, read by faery: (t, x, y, on) columns as one list.
fn faery_events(py: &Path, path: &Path) -> String {
    let script = "import sys, faery, numpy as np, hashlib\n\
             p = list(faery.events_stream_from_file(sys.argv[1]))\n\
             a = np.concatenate(p) if p else np.zeros(0)\n\
             print(len(a), hashlib.sha256(b''.join(np.ascontiguousarray(a[k]).tobytes() for k in ['t','x','y','on'])).hexdigest() if len(a) else 0)";
    let out = succeeds(Command::new(py).args(["-c", script]).arg(path));
    String::from_utf8_lossy(&out.stdout).trim().to_string()
}

#[test]
fn cyclone_subscribes_and_every_event_equals_convert() {
    let Some(py) = peer_python("cyclone_subscribes_and_every_event_equals_convert") else {
        return;
    };
    let dir = common::temp_dir("ros2-sub");
    let d: &Path = &dir;
    let dom = domain(0);
    let mut sub = peer_cmd(&py)
        .args(["subscribe", "/v2ce_test/events"])
        .arg(d.join("sub.raw"))
        .arg("90")
        .env("ROS_DOMAIN_ID", &dom)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let run = v2ce()
        .args([
            "run",
            "--source",
            "fixture",
            "--max-frames",
            "90",
            "--udp",
            "",
        ])
        .args([
            "--ros2",
            "/v2ce_test/events",
            "--ros2-wait-subscribers",
            "1",
        ])
        .args(["--queue-policy", "block", "--seed", "5"])
        .env("ROS_DOMAIN_ID", &dom)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // A second subscriber that starts while the stream runs: 1 s after the first subscriber
    // got its first packet (the stream lasts 3 s).
    {
        use std::io::BufRead;
        let mut lines = std::io::BufReader::new(sub.stdout.take().unwrap()).lines();
        while let Some(Ok(line)) = lines.next() {
            if line == "first" {
                break;
            }
        }
    }
    std::thread::sleep(std::time::Duration::from_millis(1000));
    let late = peer_cmd(&py)
        .args(["subscribe", "/v2ce_test/events"])
        .arg(d.join("late.raw"))
        .arg("60")
        .env("ROS_DOMAIN_ID", &dom)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let run = run.wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{log}");
    let sub = sub.wait_with_output().unwrap();
    assert!(sub.status.success());
    let late = late.wait_with_output().unwrap();
    assert!(
        late.status.success(),
        "{}",
        String::from_utf8_lossy(&late.stderr)
    );
    let conv = v2ce()
        .args([
            "convert",
            "fixture",
            "--max-frames",
            "90",
            "--seed",
            "5",
            "--evt",
            "3",
            "-o",
        ])
        .arg(d.join("conv.raw"))
        .output()
        .unwrap();
    assert!(conv.status.success());
    let summary = json(&d.join("sub.raw.json"));
    let seqs: Vec<u64> = serde_json::from_value(summary["seqs"].clone()).unwrap();
    assert!(!seqs.is_empty(), "no packet arrived: {log}");
    // Every packet, from seq 0, in order.
    assert!(seqs.iter().enumerate().all(|(i, s)| *s == i as u64));
    assert_eq!(summary["frame_ids"], serde_json::json!(["event_camera"]));
    assert_eq!(summary["encodings"], serde_json::json!(["evt3"]));
    assert_eq!(summary["sizes"], serde_json::json!([[640, 480]]));
    // Each packet decodes alone (a subscriber that joins at any packet reads it).
    let alone: Vec<u64> = serde_json::from_value(summary["alone"].clone()).unwrap();
    assert!(
        !alone.is_empty() && alone.iter().all(|n| *n > 0),
        "{alone:?}"
    );
    // The payloads end to end, read by faery, equal convert's file event for event.
    let (a, b) = (
        faery_events(&py, &d.join("sub.raw")),
        faery_events(&py, &d.join("conv.raw")),
    );
    assert!(!a.starts_with("0 "), "{a}");
    assert_eq!(a, b);
    // The late subscriber: it missed the first packets, and every packet it got decodes alone
    // and, end to end, its events are convert's from its first packet's time on.
    let late = json(&d.join("late.raw.json"));
    let seqs: Vec<u64> = serde_json::from_value(late["seqs"].clone()).unwrap();
    assert!(seqs.first().is_some_and(|s| *s > 0), "{seqs:?}");
    assert!(seqs.windows(2).all(|w| w[1] == w[0] + 1));
    let alone: Vec<u64> = serde_json::from_value(late["alone"].clone()).unwrap();
    assert!(
        !alone.is_empty() && alone.iter().all(|n| *n > 0),
        "{alone:?}"
    );
    let same = Command::new(&py)
        .args([
            "-c",
            "import sys, faery, numpy as np\n\
             a = faery.events_stream_from_file(sys.argv[1]).to_array()\n\
             b = faery.events_stream_from_file(sys.argv[2]).to_array()\n\
             b = b[b['t'] >= a['t'][0]]\n\
             print(len(a), len(b), all(np.array_equal(a[k], b[k]) for k in ['t','x','y','on']) if len(a) == len(b) else False)",
        ])
        .arg(d.join("late.raw"))
        .arg(d.join("conv.raw"))
        .output()
        .unwrap();
    let same = String::from_utf8_lossy(&same.stdout);
    assert!(same.trim().ends_with("True"), "late subscriber: {same}");
}

fn frames(py: &Path, d: &Path) {
    succeeds(
        peer_cmd(py)
            .arg("frames")
            .arg(d.join("fr.npz"))
            .arg(d.join("fr")),
    );
}

#[test]
fn cyclone_images_feed_the_source_and_hostile_ones_are_counted() {
    let Some(py) = peer_python("cyclone_images_feed_the_source_and_hostile_ones_are_counted")
    else {
        return;
    };
    let dir = common::temp_dir("ros2-src");
    let d: &Path = &dir;
    frames(&py, d);
    let dom = domain(1);
    let run = v2ce()
        .args([
            "run",
            "--source",
            "ros2:/v2ce_test/image_raw",
            "--max-frames",
            "40",
        ])
        .args([
            "--udp",
            "",
            "--queue-policy",
            "block",
            "--seed",
            "3",
            "--out",
        ])
        .arg(d.join("live.csv"))
        .env("ROS_DOMAIN_ID", &dom)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    succeeds(
        peer_cmd(&py)
            .args(["publish", "/v2ce_test/image_raw"])
            .arg(d.join("fr.npz"))
            .arg("--hostile")
            .env("ROS_DOMAIN_ID", &dom),
    );
    let run = run.wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{log}");
    // Eight hostile messages (short step, short data, unknown encoding, size against data, a
    // stamp back in time, a stamp an hour ahead, an absurd size, bytes that are no Image),
    // each refused and counted; the run went on.
    assert!(log.contains("image refused (8 so far)"), "{log}");
    assert!(!log.contains("image refused (9 so far)"), "{log}");
    assert!(log.contains("malformed message"), "{log}");
    assert!(log.contains("jumps 3600.0 s ahead"), "{log}");
    assert!(
        log.contains("40 frames in, 0 dropped, 8 refused by the source"),
        "{log}"
    );
    let conv = v2ce()
        .args(["convert", "--seed", "3"])
        .arg(d.join("fr"))
        .arg("-o")
        .arg(d.join("conv.csv"))
        .output()
        .unwrap();
    assert!(conv.status.success());
    let live = std::fs::read(d.join("live.csv")).unwrap();
    assert!(live.len() > 1000);
    assert!(
        live == std::fs::read(d.join("conv.csv")).unwrap(),
        "the live events differ from convert's"
    );
}

#[test]
fn rosbags_reads_our_bags_and_we_read_its_image_bags() {
    let Some(py) = peer_python("rosbags_reads_our_bags_and_we_read_its_image_bags") else {
        return;
    };
    let dir = common::temp_dir("ros2-bag");
    let d: &Path = &dir;
    frames(&py, d);
    // Our events bag, read by rosbags, payloads decoded by faery: convert's events.
    for (args, name) in [(
        vec!["convert", "fixture", "--max-frames", "20", "--seed", "9"],
        "ev",
    )] {
        for ext in ["mcap", "raw"] {
            let mut c = v2ce();
            c.args(&args)
                .args(["--evt", "3", "-o"])
                .arg(d.join(format!("{name}.{ext}")));
            assert!(c.output().unwrap().status.success());
        }
    }
    succeeds(
        peer_cmd(&py)
            .arg("bag-read")
            .arg(d.join("ev.mcap"))
            .arg(d.join("bag.raw")),
    );
    let s = json(&d.join("bag.raw.json"));
    assert!(s["packets"].as_u64().unwrap() > 100);
    assert_eq!(
        faery_events(&py, &d.join("bag.raw")),
        faery_events(&py, &d.join("ev.raw"))
    );
    // v2ce reads its own bag back (info, transcode) with the same events.
    succeeds(
        v2ce()
            .arg("transcode")
            .arg(d.join("ev.mcap"))
            .arg(d.join("back.raw"))
            .args(["--evt", "3"]),
    );
    assert_eq!(
        faery_events(&py, &d.join("back.raw")),
        faery_events(&py, &d.join("ev.raw"))
    );
    // A bag of Images that rosbags wrote (two cameras): --topic picks one; its events equal
    // the same frames from PNGs with their times.
    succeeds(
        peer_cmd(&py)
            .arg("bag-write")
            .arg(d.join("fr.npz"))
            .arg(d.join("images"))
            .arg("/cam/image_raw"),
    );
    let bag = d.join("images/images.mcap");
    succeeds(
        v2ce()
            .arg("convert")
            .arg(&bag)
            .args(["--topic", "/cam/image_raw", "--seed", "2", "-o"])
            .arg(d.join("bag.csv")),
    );
    let c = v2ce()
        .arg("convert")
        .arg(d.join("fr"))
        .args(["--seed", "2", "-o"])
        .arg(d.join("png.csv"))
        .output()
        .unwrap();
    assert!(c.status.success());
    let a = std::fs::read(d.join("bag.csv")).unwrap();
    assert!(a.len() > 1000);
    assert!(a == std::fs::read(d.join("png.csv")).unwrap());
    // A topic the bag does not have: an error naming the topics it has.
    let c = v2ce()
        .arg("convert")
        .arg(&bag)
        .args(["--topic", "/nope", "-o"])
        .arg(d.join("x.csv"))
        .output()
        .unwrap();
    assert!(!c.status.success());
    assert!(String::from_utf8_lossy(&c.stderr).contains("/cam/image_raw"));
}

#[test]
fn listen_checks_what_a_cyclone_publisher_sends() {
    let Some(py) = peer_python("listen_checks_what_a_cyclone_publisher_sends") else {
        return;
    };
    let dom = domain(2);
    let listen = v2ce()
        .args([
            "listen",
            "--ros2",
            "/v2ce_test/packets",
            "--idle",
            "3",
            "--json",
        ])
        .env("ROS_DOMAIN_ID", &dom)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    succeeds(
        peer_cmd(&py)
            .args(["publish-packets", "/v2ce_test/packets"])
            .env("ROS_DOMAIN_ID", &dom),
    );
    let out = listen.wait_with_output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
    // Two good packets of two events; seq 1 missing; an encoding not read, words cut in half
    // and a sensor of width 0 refused as malformed; a pixel off the sensor refused whole.
    assert_eq!(report["events"], 4, "{report}");
    assert_eq!(report["messages"], 6, "{report}");
    assert_eq!(report["seq_gaps"], 1, "{report}");
    assert_eq!(report["malformed"], 3, "{report}");
    assert_eq!(report["off_sensor"], 1, "{report}");
    assert_eq!(report["first_t"], 1_000_000, "{report}");
    assert_eq!(report["last_t"], 1_000_002, "{report}");
}

/// A bag played in a loop (stamps back at the start) is followed as a new timeline after two
/// refusals; a publisher that goes away is a lost source (no image for 5 s), reopened with the
/// daemon's backoff; frames from the publisher that comes back go on where the first left
/// off, and a flood of them costs drops that are counted, never the daemon.
#[test]
fn a_publisher_that_goes_away_and_floods_back_is_survived() {
    let Some(py) = peer_python("a_publisher_that_goes_away_and_floods_back_is_survived") else {
        return;
    };
    let dir = common::temp_dir("ros2-back");
    let d: &Path = &dir;
    frames(&py, d);
    let dom = domain(3);
    let config = d.join("back.toml");
    std::fs::write(
        &config,
        "[run]\nreconnect_min_ms = 200\nreconnect_max_ms = 400\n",
    )
    .unwrap();
    let run = v2ce()
        .args([
            "run",
            "--source",
            "ros2:/v2ce_test/back",
            "--max-frames",
            "40",
        ])
        .arg("--config")
        .arg(&config)
        .args(["--udp", "", "--out"])
        .arg(d.join("back.csv"))
        .env("ROS_DOMAIN_ID", &dom)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let publish = |extra: &[&str]| {
        succeeds(
            peer_cmd(&py)
                .args(["publish", "/v2ce_test/back"])
                .arg(d.join("fr.npz"))
                .args(extra)
                .env("ROS_DOMAIN_ID", &dom),
        );
    };
    // 15 frames, then the same again (a bag played in a loop: stamps back at the start): two
    // refused, then followed as a new timeline.
    publish(&["--last", "15", "--twice"]);
    // Gone for longer than the source waits (5 s), then back, flooding.
    std::thread::sleep(std::time::Duration::from_secs(7));
    publish(&["--first", "15", "--flood"]);
    let mut run = run;
    let status = {
        let started = std::time::Instant::now();
        loop {
            if let Some(s) = run.try_wait().unwrap() {
                break Some(s);
            }
            if started.elapsed() > std::time::Duration::from_secs(30) {
                break None;
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
    };
    if status.is_none() {
        // The flood's last frames were dropped: the run waits for more; a signal ends it.
        // SAFETY: kill sends SIGINT to the child's pid.
        unsafe { libc::kill(run.id() as i32, libc::SIGINT) };
    }
    let out = run.wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{log}");
    assert!(log.contains("the publisher went away"), "{log}");
    assert!(log.contains("a new timeline"), "{log}");
    assert!(log.contains("source back: ros2 /v2ce_test/back"), "{log}");
    let line = log.lines().find(|l| l.contains("stopped: ")).unwrap();
    let frames_in: u64 = line
        .split(" frames in")
        .next()
        .and_then(|s| s.rsplit(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{line}"));
    assert!(frames_in > 15, "{line}");
    assert!(std::fs::read(d.join("back.csv")).unwrap().len() > 1000);
}

/// The children of `pid` (its threads' children).
fn children(pid: u32) -> Vec<u32> {
    let mut v = Vec::new();
    for task in std::fs::read_dir(format!("/proc/{pid}/task"))
        .into_iter()
        .flatten()
        .flatten()
    {
        let text = std::fs::read_to_string(task.path().join("children")).unwrap_or_default();
        v.extend(
            text.split_whitespace()
                .filter_map(|p| p.parse::<u32>().ok()),
        );
    }
    v
}

/// An RTPS message of one DATA_FRAG submessage to the discovery reader of a participant
/// (SPDP, entity 0x000100c7), declaring a sample of `size` bytes and carrying 16 of them.
fn data_frag(sender: u32, size: u32) -> Vec<u8> {
    let mut m = b"RTPS".to_vec();
    m.extend_from_slice(&[2, 3, 1, 15]);
    m.extend_from_slice(&sender.to_be_bytes());
    m.extend_from_slice(&[1; 8]);
    let mut body = Vec::new();
    body.extend_from_slice(&0u16.to_le_bytes()); // extra flags
    body.extend_from_slice(&28u16.to_le_bytes()); // octets to inline QoS
    body.extend_from_slice(&[0x00, 0x01, 0x00, 0xc7]); // reader: SPDP
    body.extend_from_slice(&[0x00, 0x01, 0x00, 0xc2]); // writer: SPDP
    body.extend_from_slice(&0i32.to_le_bytes()); // sequence number, high
    body.extend_from_slice(&1u32.to_le_bytes()); // low
    body.extend_from_slice(&1u32.to_le_bytes()); // first fragment
    body.extend_from_slice(&1u16.to_le_bytes()); // fragments here
    body.extend_from_slice(&1024u16.to_le_bytes()); // fragment size
    body.extend_from_slice(&size.to_le_bytes()); // the sample's size, as declared
    body.extend_from_slice(&[0, 1, 0, 0]);
    body.extend_from_slice(&[b'x'; 12]);
    m.extend_from_slice(&[0x16, 0x01]);
    m.extend_from_slice(&(body.len() as u16).to_le_bytes());
    m.extend_from_slice(&body);
    m
}

/// A peer on the domain declares a 4 GiB sample in one datagram (a DATA_FRAG, which the DDS
/// transport sizes its reassembly buffer from): the transport's process ends at its memory
/// cap, the daemon says why, starts a new one and goes on publishing (`listen --ros2`
/// receives its packets afterwards); the daemon's own memory never follows the claim. Needs
/// nothing but the v2ce binary.
#[test]
fn a_peer_declaring_a_huge_sample_ends_the_transport_not_the_daemon() {
    use std::io::BufRead;
    let dom = domain(4);
    let mut run = v2ce()
        .args([
            "run",
            "--source",
            "fixture",
            "--loop",
            "--udp",
            "",
            "--ros2",
            "/v2ce_test/attack",
            "--duration",
            "60",
            "--json",
        ])
        .env("ROS_DOMAIN_ID", &dom)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .process_group(0)
        .spawn()
        .unwrap();
    let pid = run.id();
    // A failed assertion leaves no daemon on the domain (its transport included).
    struct KillGroup(i32);
    impl Drop for KillGroup {
        fn drop(&mut self) {
            // SAFETY: kill sends SIGKILL to a group this test started (gone when it ended).
            unsafe { libc::kill(-self.0, libc::SIGKILL) };
        }
    }
    let _group = KillGroup(pid as i32);
    let log = std::sync::Arc::new(std::sync::Mutex::new(String::new()));
    let stderr = run.stderr.take().unwrap();
    let keep = log.clone();
    let reader = std::thread::spawn(move || {
        for line in std::io::BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
        {
            let mut l = keep.lock().unwrap();
            l.push_str(&line);
            l.push('\n');
        }
    });
    let wait = |what: &str, ok: &dyn Fn() -> bool| {
        let started = std::time::Instant::now();
        while !ok() {
            assert!(
                started.elapsed() < std::time::Duration::from_secs(30),
                "waited 30 s for {what}: {}",
                log.lock().unwrap()
            );
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
    };
    wait("the DDS transport", &|| children(pid).len() == 1);
    let first = children(pid)[0];
    std::thread::sleep(std::time::Duration::from_millis(500));

    // Every discovery port of the domain: its multicast group and the participants' unicast
    // ports (RTPS 9.6.1.1: 7400 + 250 d, + 10 + 2 i).
    let base = 7400 + 250 * dom.parse::<u16>().unwrap();
    let socket = std::net::UdpSocket::bind("0.0.0.0:0").unwrap();
    socket.set_multicast_loop_v4(true).unwrap();
    let claim = data_frag(0xdead_0001, u32::MAX - (1 << 20));
    let _ = socket.send_to(&claim, ("239.255.0.1", base));
    for i in 0..4 {
        let _ = socket.send_to(&claim, ("127.0.0.1", base + 10 + 2 * i));
    }
    wait("a new DDS transport", &|| {
        log.lock()
            .unwrap()
            .contains("a new DDS transport (restart 1)")
    });
    let second = children(pid);
    assert_eq!(second.len(), 1, "{second:?}");
    assert_ne!(second[0], first);
    {
        let l = log.lock().unwrap();
        assert!(
            l.contains("the DDS transport ended") && l.contains("memory allocation of"),
            "{l}"
        );
    }

    // The new transport publishes: a subscriber that joins now receives whole packets.
    let listen = succeeds(
        v2ce()
            .args([
                "listen",
                "--ros2",
                "/v2ce_test/attack",
                "--duration",
                "3",
                "--json",
            ])
            .env("ROS_DOMAIN_ID", &dom),
    );
    let text = String::from_utf8_lossy(&listen.stdout);
    let report: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
    assert!(report["events"].as_u64().unwrap() > 10_000, "{report}");
    assert_eq!(report["malformed"], 0, "{report}");

    // The daemon's memory never followed the claim; one SIGTERM to its whole process group
    // (as systemd stops a unit, as Ctrl-C reaches a terminal's) ends it with its report, its
    // last packets sent through the transport, which waits for the daemon to close it.
    let peak = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.split_whitespace().next()?.parse::<u64>().ok())
        .unwrap();
    assert!(peak < 512 * 1024, "the daemon's peak {peak} KiB");
    // SAFETY: kill sends SIGTERM to the group the child leads.
    assert_eq!(unsafe { libc::kill(-(pid as i32), libc::SIGTERM) }, 0);
    let out = run.wait_with_output().unwrap();
    reader.join().unwrap();
    assert!(out.status.success(), "{}", log.lock().unwrap());
    let ended = log.lock().unwrap().matches("a new one in").count();
    assert_eq!(ended, 1, "{}", log.lock().unwrap());
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let sink = &report["stats"]["sinks"][0]["stats"];
    assert!(sink["messages_sent"].as_u64().unwrap() > 1000, "{sink}");
    for line in log.lock().unwrap().lines() {
        if line.contains("DDS transport") {
            eprintln!("{line}");
        }
    }
    eprintln!(
        "daemon peak {} MiB; listen after the restart: {} events; sink {sink}",
        peak >> 10,
        report_events(&text)
    );
}

fn report_events(listen_stdout: &str) -> u64 {
    listen_stdout
        .lines()
        .last()
        .and_then(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .and_then(|v| v["events"].as_u64())
        .unwrap_or(0)
}
