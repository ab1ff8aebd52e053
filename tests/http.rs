//! The daemon's HTTP listener (`[run] http`): `/metrics` scraped during a replay fed through a
//! named pipe, parsed by prometheus_client's parser and checked against the final report;
//! `/readyz` unready while the pipe stalls and ready again when frames resume; `/healthz`; and
//! the preview page loaded in headless Chromium, its screenshots showing events where the
//! fixture moves and changing over time (kept in `target/test-output/`).

mod common;

use std::io::{BufRead, ErrorKind, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// A daemon with the listener on a free port; its stderr lines are collected.
struct Daemon {
    child: Child,
    lines: Arc<Mutex<Vec<String>>>,
    address: String,
}

impl Daemon {
    fn start(args: &[&str], dir: &Path) -> Daemon {
        let mut child = Command::new(env!("CARGO_BIN_EXE_v2ce"))
            .arg("run")
            .args(args)
            .args(["--http", "127.0.0.1:0"])
            .current_dir(dir)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let lines = Arc::new(Mutex::new(Vec::new()));
        let stderr = child.stderr.take().unwrap();
        std::thread::spawn({
            let lines = lines.clone();
            move || {
                for line in std::io::BufReader::new(stderr).lines() {
                    let Ok(line) = line else { break };
                    lines.lock().unwrap().push(line);
                }
            }
        });
        let started = Instant::now();
        let address = loop {
            let found = lines.lock().unwrap().iter().find_map(|l| {
                let at = l.find("http://")?;
                Some(l[at + 7..].trim_end_matches('/').trim().to_string())
            });
            if let Some(a) = found {
                break a.split('/').next().unwrap_or("").to_string();
            }
            assert!(
                started.elapsed() < Duration::from_secs(30),
                "no listener line: {:?}",
                lines.lock().unwrap()
            );
            std::thread::sleep(Duration::from_millis(20));
        };
        Daemon {
            child,
            lines,
            address,
        }
    }

    /// GET `path`: the status code and the body.
    fn get(&self, path: &str) -> (u16, String) {
        if std::net::TcpStream::connect(&self.address).is_err() {
            panic!(
                "cannot connect to {} for {path}; the daemon said: {}",
                self.address,
                self.lines.lock().unwrap().join("\n")
            );
        }
        get(&self.address, path)
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn get(address: &str, path: &str) -> (u16, String) {
    let mut s = std::net::TcpStream::connect(address).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(s, "GET {path} HTTP/1.0\r\nHost: {address}\r\n\r\n").unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let code = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = text
        .split_once("\r\n\r\n")
        .map_or("", |(_, b)| b)
        .to_string();
    (code, body)
}

/// The value of the sample `name{labels}` (labels as written, "" for none) in Prometheus text.
fn sample(text: &str, name_and_labels: &str) -> Option<f64> {
    text.lines().filter(|l| !l.starts_with('#')).find_map(|l| {
        let (k, v) = l.rsplit_once(' ')?;
        (k == name_and_labels).then(|| v.parse().ok())?
    })
}

fn wait_for(limit: Duration, what: &str, mut ok: impl FnMut() -> bool) {
    let started = Instant::now();
    while !ok() {
        assert!(started.elapsed() < limit, "waited {limit:?} for {what}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Writes a Y4M stream of a moving bar into `pipe`: `first` frames, then waits for a message
/// on `resume`, then `second` frames, then waits for another message and closes it.
fn feed(pipe: PathBuf, first: usize, second: usize, resume: std::sync::mpsc::Receiver<()>) {
    let (w, h) = (160usize, 120usize);
    let mut f = std::fs::OpenOptions::new().write(true).open(pipe).unwrap();
    f.write_all(format!("YUV4MPEG2 W{w} H{h} F30:1 Cmono\n").as_bytes())
        .unwrap();
    let frame = |k: usize| {
        let mut v = b"FRAME\n".to_vec();
        v.extend((0..w * h).map(|p| if (p % w + 4 * k) % 80 < 20 { 220u8 } else { 30 }));
        v
    };
    for k in 0..first {
        f.write_all(&frame(k)).unwrap();
    }
    resume.recv().unwrap();
    for k in first..first + second {
        f.write_all(&frame(k)).unwrap();
    }
    resume.recv().unwrap();
}

#[test]
fn metrics_match_the_report_and_readiness_follows_the_source() {
    let dir = common::temp_dir("http-metrics");
    let pipe = dir.join("live.y4m");
    let c = std::ffi::CString::new(pipe.to_str().unwrap()).unwrap();
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    // The writer first: opening a pipe waits for the other end, and the daemon opens its
    // source before it listens.
    let (tx, rx) = std::sync::mpsc::channel();
    let writer = std::thread::spawn({
        let pipe = pipe.clone();
        move || feed(pipe, 30, 30, rx)
    });
    let daemon = Daemon::start(
        &[
            "--source",
            "live.y4m",
            "--out",
            "out.csv",
            "--udp",
            "127.0.0.1:9",
            "--queue-policy",
            "block",
            "--ready-timeout",
            "0.5",
            "--json",
        ],
        &dir,
    );
    assert_eq!(daemon.get("/healthz").0, 200);
    let frames = |d: &Daemon| sample(&d.get("/metrics").1, "v2ce_frames_total").unwrap_or(-1.0);
    // Ready while frames flow (the first ones come in at 30 fps).
    wait_for(Duration::from_secs(20), "/readyz 200", || {
        daemon.get("/readyz").0 == 200
    });
    wait_for(Duration::from_secs(20), "30 frames", || {
        frames(&daemon) == 30.0
    });
    // The pipe stalls: unready after the timeout, with the reason.
    wait_for(Duration::from_secs(10), "/readyz 503", || {
        daemon.get("/readyz").0 == 503
    });
    let (_, why) = daemon.get("/readyz");
    assert!(why.contains("stalled"), "{why}");
    assert_eq!(sample(&daemon.get("/metrics").1, "v2ce_ready"), Some(0.0));
    // Frames again: ready again.
    tx.send(()).unwrap();
    wait_for(Duration::from_secs(20), "/readyz 200 again", || {
        daemon.get("/readyz").0 == 200
    });
    wait_for(Duration::from_secs(20), "60 frames", || {
        frames(&daemon) == 60.0
    });
    // Settled: every frame through and the counters still.
    let mut last = String::new();
    wait_for(Duration::from_secs(20), "the counters to settle", || {
        let text = daemon.get("/metrics").1;
        let settled = sample(&text, "v2ce_frames_processed_total") == Some(60.0)
            && stable(&text) == stable(&last);
        last = text;
        settled
    });
    let scraped = last;
    std::fs::write(dir.join("metrics.txt"), &scraped).unwrap();
    // The end of the stream: the daemon finishes and reports.
    tx.send(()).unwrap();
    writer.join().unwrap();
    let mut daemon = daemon;
    let status = daemon.child.wait().unwrap();
    let mut stdout = String::new();
    daemon
        .child
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut stdout)
        .unwrap();
    assert!(
        status.success(),
        "{:?}",
        daemon.lines.lock().unwrap().join("\n")
    );
    let report: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let stats = &report["stats"];
    assert_eq!(stats["frames_in"], 60);
    assert_eq!(
        sample(&scraped, "v2ce_frames_total"),
        stats["frames_in"].as_f64()
    );
    assert_eq!(
        sample(&scraped, "v2ce_events_total"),
        stats["events_out"].as_f64()
    );
    let sinks = stats["sinks"].as_array().unwrap();
    assert!(sinks.len() >= 3, "udp, file and the preview: {sinks:?}");
    for s in sinks {
        let name = s["sink"].as_str().unwrap().replace('"', "\\\"");
        for (result, key) in [("sent", "events_sent"), ("dropped", "events_dropped")] {
            assert_eq!(
                sample(
                    &scraped,
                    &format!("v2ce_sink_events_total{{sink=\"{name}\",result=\"{result}\"}}")
                ),
                s["stats"][key].as_f64(),
                "{name} {result}"
            );
        }
    }
    // The text parses with prometheus_client's parser, with the families and types expected.
    let Some(py) = common::python() else {
        skipped!("SKIPPED the prometheus_client parse: no Python venv (run .ci/run)");
        return;
    };
    let out = Command::new(py)
        .arg(common::script())
        .arg("prom")
        .arg(dir.join("metrics.txt"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let samples: Vec<serde_json::Value> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let family = |name: &str| samples.iter().find(|s| s["family"] == name).cloned();
    let frames = family("v2ce_frames").expect("v2ce_frames_total");
    assert_eq!(frames["type"], "counter");
    assert_eq!(frames["value"], 60.0);
    assert_eq!(family("v2ce_latency_seconds").unwrap()["type"], "histogram");
    assert_eq!(
        family("process_resident_memory_bytes").unwrap()["type"],
        "gauge"
    );
    let info = family("v2ce_stage1_info").unwrap();
    assert_eq!(info["labels"]["tier"], "physics");
}

/// The scrape without the lines that change by themselves (uptime, CPU, memory, readiness,
/// the listener's own connections), so two scrapes compare equal when nothing else moved.
fn stable(text: &str) -> String {
    text.lines()
        .filter(|l| {
            ![
                "v2ce_uptime_seconds",
                "process_",
                "v2ce_ready",
                "v2ce_http_",
            ]
            .iter()
            .any(|p| l.starts_with(p))
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// Headless Chromium (the Debian package), or `None` with a printed reason, unless
/// `V2CE_REQUIRE_CHROMIUM` is set (CI), where its absence fails.
fn chromium() -> Option<PathBuf> {
    let found = ["chromium", "chromium-browser", "google-chrome"]
        .iter()
        .flat_map(|n| ["/usr/bin", "/usr/local/bin"].map(|d| Path::new(d).join(n)))
        .find(|p| p.is_file());
    if found.is_none() {
        assert!(
            std::env::var_os("V2CE_REQUIRE_CHROMIUM").is_none(),
            "V2CE_REQUIRE_CHROMIUM is set but there is no chromium (apt install chromium)"
        );
    }
    found
}

fn screenshot(browser: &Path, url: &str, out: &Path, profile: &Path) {
    let o = Command::new(browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--no-first-run",
            "--window-size=800,700",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(format!("--screenshot={}", out.display()))
        .arg(url)
        .output()
        .unwrap();
    assert!(
        out.exists(),
        "no screenshot: {}",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Pixels of the screenshot in the ON and OFF colours, and where they lie (bounding box).
fn event_pixels(path: &Path) -> (usize, usize, image::RgbImage) {
    let img = image::open(path).unwrap().to_rgb8();
    let near = |p: &image::Rgb<u8>, c: [u8; 3]| {
        p.0.iter()
            .zip(c)
            .all(|(a, b)| (*a as i16 - b as i16).abs() <= 12)
    };
    let on = img
        .pixels()
        .filter(|p| near(p, v2ce::render::ON_COLOUR))
        .count();
    let off = img
        .pixels()
        .filter(|p| near(p, v2ce::render::OFF_COLOUR))
        .count();
    (on, off, img)
}

#[test]
fn the_preview_page_shows_the_moving_fixture_in_a_browser() {
    let Some(browser) = chromium() else {
        skipped!(
            "SKIPPED the_preview_page_shows_the_moving_fixture_in_a_browser: no chromium (apt install chromium)"
        );
        return;
    };
    let dir = common::temp_dir("http-page");
    let daemon = Daemon::start(
        &["--source", "fixture", "--loop", "--udp", "127.0.0.1:9"],
        &dir,
    );
    wait_for(Duration::from_secs(30), "frames flowing", || {
        daemon.get("/readyz").0 == 200
    });
    // A second into the fixture: the bar sweeps.
    std::thread::sleep(Duration::from_secs(1));
    let (code, page) = daemon.get("/");
    assert_eq!(code, 200);
    assert!(
        !page.contains("http://") && !page.contains("https://"),
        "external assets"
    );
    let keep = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/test-output");
    std::fs::create_dir_all(&keep).unwrap();
    let url = format!("http://{}/?window_ms=100", daemon.address);
    let shots = [keep.join("preview-1.png"), keep.join("preview-2.png")];
    screenshot(&browser, &url, &shots[0], &dir.join("profile1"));
    std::thread::sleep(Duration::from_millis(1500));
    screenshot(&browser, &url, &shots[1], &dir.join("profile2"));
    let (on1, off1, img1) = event_pixels(&shots[0]);
    let (on2, off2, img2) = event_pixels(&shots[1]);
    eprintln!(
        "screenshots in {}: ON/OFF pixels {on1}/{off1} and {on2}/{off2}",
        keep.display()
    );
    // Events of both polarities where the fixture moves, and the page changed between loads.
    assert!(on1 > 100 && off1 > 100, "{on1} ON, {off1} OFF pixels");
    assert!(on2 > 100 && off2 > 100, "{on2} ON, {off2} OFF pixels");
    let differ = img1
        .pixels()
        .zip(img2.pixels())
        .filter(|(a, b)| a != b)
        .count();
    assert!(
        differ > 100,
        "the two screenshots differ in {differ} pixels"
    );

    // The push channel itself: server-sent events, each a new frame, several a second.
    let mut s = std::net::TcpStream::connect(&daemon.address).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(s, "GET /events?window_ms=33 HTTP/1.0\r\n\r\n").unwrap();
    let mut reader = std::io::BufReader::new(s);
    let started = Instant::now();
    let mut messages: Vec<serde_json::Value> = Vec::new();
    while messages.len() < 4 {
        let mut line = String::new();
        assert!(reader.read_line(&mut line).unwrap() > 0, "the stream ended");
        if let Some(data) = line.strip_prefix("data: ") {
            messages.push(serde_json::from_str(data.trim()).unwrap());
        }
    }
    let seconds = started.elapsed().as_secs_f64();
    assert!(seconds < 3.0, "4 pushes took {seconds:.1} s");
    let frames: Vec<u64> = messages
        .iter()
        .map(|m| m["frames"].as_u64().unwrap())
        .collect();
    assert!(frames[3] > frames[0], "{frames:?}");
    assert_ne!(messages[0]["png"], messages[3]["png"]);
    assert_eq!(messages[0]["width"], 640);
}

/// The process's thread count and resident memory (KiB), from /proc.
/// A size in KiB from `/proc/<pid>/status` (`VmRSS:`, `VmHWM:`), 0 when unreadable.
fn status_kib(pid: u32, key: &str) -> u64 {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    text.lines()
        .find_map(|l| l.strip_prefix(key))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or(0)
}

fn threads_and_rss(pid: u32) -> (Threads, u64) {
    let rss = status_kib(pid, "VmRSS:");
    let mut threads = Threads::default();
    for task in std::fs::read_dir(format!("/proc/{pid}/task"))
        .into_iter()
        .flatten()
    {
        let Ok(task) = task else { continue };
        let name = std::fs::read_to_string(task.path().join("comm")).unwrap_or_default();
        *threads.0.entry(name.trim().to_string()).or_default() += 1;
    }
    (threads, rss)
}

/// The threads of `pid` once its pipeline is whole: every stage and `sinks` outputs started
/// (the listener answers before the pipeline has spawned them all; a busy machine can leave
/// that window open for a while).
fn pipeline_threads_and_rss(pid: u32, sinks: u64) -> (Threads, u64) {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let (threads, rss) = threads_and_rss(pid);
        let started = threads
            .0
            .iter()
            .filter(|(name, _)| name.starts_with("v2ce-sink"))
            .map(|(_, n)| n)
            .sum::<u64>();
        if (threads.0.contains_key("v2ce-stage2") && started >= sinks) || Instant::now() > deadline
        {
            return (threads, rss);
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// The daemon's peak resident memory over one whole loop of the fixture (200 frames, the
/// fixture's 180 and more) with the preview encoder started by a stream read for a second: the
/// pipeline's own buffers at their largest, so that what the attack adds is measured apart from
/// them. Taken at the stages' spawn, the baseline missed those buffers (CI read 18 MiB there and
/// 84 MiB under attack, the pipeline's start and not the attack).
fn warmed_peak_rss(daemon: &Daemon, pid: u32) -> u64 {
    {
        let mut s = std::net::TcpStream::connect(&daemon.address).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        s.write_all(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
            .unwrap();
        let (started, mut got, mut buf) = (Instant::now(), Vec::new(), [0u8; 4096]);
        while started.elapsed() < Duration::from_secs(1) {
            match s.read(&mut buf) {
                Ok(n) if n > 0 => got.extend_from_slice(&buf[..n]),
                _ => break,
            }
        }
        let head = String::from_utf8_lossy(&got[..got.len().min(200)]).into_owned();
        assert_eq!(code(&head), 200, "{head}");
    }
    let frames = || sample(&daemon.get("/metrics").1, "v2ce_frames_total").unwrap_or(0.0);
    wait_for(Duration::from_secs(90), "200 frames", || frames() >= 200.0);
    status_kib(pid, "VmHWM:")
}

/// A process's threads counted by name.
#[derive(Debug, Default)]
struct Threads(std::collections::BTreeMap<String, u64>);

impl Threads {
    /// The workers started on first use, at a fixed number whatever clients do: the pipeline's
    /// helper pool (one per core) and the motion model's look-ahead worker (one), and the
    /// listener's preview encoder (one, with the first page or stream).
    const LAZY: [(&'static str, u64); 3] =
        [("v2ce-helper", 0), ("v2ce-motion", 1), ("v2ce-preview", 1)];

    /// Threads other than the lazily started compute workers.
    fn others(&self) -> u64 {
        self.0
            .iter()
            .filter(|(name, _)| !Self::LAZY.iter().any(|(lazy, _)| lazy == name))
            .map(|(_, n)| n)
            .sum()
    }

    /// Whether each lazily started kind stays within its fixed bound (0: one per core).
    fn lazy_bounded(&self) -> bool {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get()) as u64;
        Self::LAZY.iter().all(|(name, bound)| {
            let bound = if *bound == 0 { cores } else { *bound };
            self.0.get(*name).copied().unwrap_or(0) <= bound
        })
    }
}

/// Sends `request` raw and reads what comes back within `limit` (until the server closes).
fn raw(address: &str, request: &[u8], limit: Duration) -> String {
    let mut s = std::net::TcpStream::connect(address).unwrap();
    s.set_read_timeout(Some(limit)).unwrap();
    let _ = s.write_all(request);
    let mut got = Vec::new();
    let _ = s.read_to_end(&mut got);
    String::from_utf8_lossy(&got).into_owned()
}

fn code(response: &str) -> u16 {
    response
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0)
}

/// The listener attacked on loopback while the daemon streams: huge and never-sent bodies,
/// other methods, an endless header line, pipelined requests never read, a slowloris of
/// half-open connections, preview streams past the cap and one never read. Each gets its
/// refusal or a timeout; `/healthz` stays answered; the process grows no threads and no
/// memory; and one SIGTERM, with the attackers still connected, stops it promptly with its
/// closing report.
#[test]
fn the_listener_holds_under_attack_and_never_holds_the_daemon() {
    let dir = common::temp_dir("http-attacks");
    let daemon = Daemon::start(
        &[
            "--source",
            "fixture",
            "--loop",
            "--udp",
            "127.0.0.1:9",
            "--duration",
            "120",
            "--json",
        ],
        &dir,
    );
    let a = daemon.address.clone();
    let pid = daemon.child.id();
    assert_eq!(daemon.get("/healthz").0, 200);
    // The UDP output and the preview's.
    let (threads0, _) = pipeline_threads_and_rss(pid, 2);
    let second = Duration::from_secs(1);
    let rss0 = warmed_peak_rss(&daemon, pid);

    // A body announced larger than memory: refused at once, nothing read or allocated.
    let r = raw(
        &a,
        b"GET /healthz HTTP/1.1\r\nHost: x\r\nContent-Length: 99999999999999\r\n\r\n",
        second * 5,
    );
    assert_eq!(code(&r), 413, "{r}");
    // A body announced and never sent: refused at once, not waited for.
    let started = Instant::now();
    let r = raw(
        &a,
        b"POST /metrics HTTP/1.1\r\nHost: x\r\nContent-Length: 2000\r\n\r\n",
        second * 5,
    );
    assert_eq!(code(&r), 405, "{r}");
    assert!(r.contains("allow: GET, HEAD"), "{r}");
    let r = raw(
        &a,
        b"GET /readyz HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\n",
        second * 5,
    );
    assert_eq!(code(&r), 413, "{r}");
    assert!(started.elapsed() < second * 3, "{:?}", started.elapsed());
    for method in ["PUT", "DELETE", "OPTIONS", "PATCH"] {
        let r = raw(
            &a,
            format!("{method} / HTTP/1.1\r\nHost: x\r\n\r\n").as_bytes(),
            second * 5,
        );
        assert_eq!(code(&r), 405, "{method}: {r}");
    }
    // HEAD: the headers alone.
    let r = raw(&a, b"HEAD /metrics HTTP/1.1\r\nHost: x\r\n\r\n", second * 5);
    assert_eq!(code(&r), 200, "{r}");
    assert!(!r.contains("v2ce_frames_total"), "{r}");
    // An endless header line and too many headers: 431 and closed, memory not following.
    {
        let mut s = std::net::TcpStream::connect(&a).unwrap();
        s.set_write_timeout(Some(second * 5)).unwrap();
        s.set_read_timeout(Some(second * 5)).unwrap();
        let _ = s.write_all(b"GET /healthz HTTP/1.1\r\nX-Long: ");
        let chunk = vec![b'a'; 64 * 1024];
        let mut sent = 0usize;
        while sent < 64 << 20 && s.write_all(&chunk).is_ok() {
            sent += chunk.len();
        }
        assert!(
            sent < 64 << 20,
            "the listener read 64 MiB of one header line"
        );
        let mut got = Vec::new();
        let _ = s.read_to_end(&mut got);
    }
    let many: String = (0..200).map(|i| format!("X-{i}: {i}\r\n")).collect();
    let r = raw(
        &a,
        format!("GET /healthz HTTP/1.1\r\nHost: x\r\n{many}\r\n").as_bytes(),
        second * 5,
    );
    assert_eq!(code(&r), 431, "{r}");

    // Pipelined requests whose responses are never read, on 16 connections.
    let mut held: Vec<std::net::TcpStream> = Vec::new();
    let burst: String = (0..200)
        .map(|_| "GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
        .collect();
    for _ in 0..16 {
        let mut s = std::net::TcpStream::connect(&a).unwrap();
        s.set_write_timeout(Some(second)).unwrap();
        let _ = s.write_all(burst.as_bytes());
        held.push(s);
    }
    // Preview streams: up to the cap, then 503; one is never read.
    let mut streams = Vec::new();
    for _ in 0..8 {
        let mut s = std::net::TcpStream::connect(&a).unwrap();
        s.write_all(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
            .unwrap();
        streams.push(s);
    }
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(daemon.get("/events").0, 503);
    // A slowloris: 300 connections, each a byte of a request head and then nothing.
    for _ in 0..300 {
        match std::net::TcpStream::connect(&a) {
            Ok(mut s) => {
                let _ = s.write_all(b"G");
                held.push(s);
            }
            Err(_) => break,
        }
    }
    // The process neither spawned a thread per connection nor grew with them.
    let (threads1, rss1) = threads_and_rss(pid);
    eprintln!("resident memory {rss1} KiB under attack, the warmed pipeline's peak {rss0} KiB");
    // (The pipeline's compute workers start on first use, at a fixed number, whenever the
    // frames first ask for them: counted apart, within their bounds.)
    assert!(
        threads1.others() <= threads0.others() + 1 && threads1.lazy_bounded(),
        "threads {threads0:?} -> {threads1:?} under attack"
    );
    assert!(
        rss1 < rss0 + 64 * 1024,
        "resident memory {rss0} KiB -> {rss1} KiB under attack"
    );
    // The oldest half-open connections gave way to the newer ones at the cap, and give way to
    // each probe: the listener answers at once.
    let started = Instant::now();
    wait_for(Duration::from_secs(30), "/healthz 200 under attack", || {
        code(&raw(&a, b"GET /healthz HTTP/1.0\r\n\r\n", second * 2)) == 200
    });
    let waited = started.elapsed();
    let text = daemon.get("/metrics").1;
    let timed_out = sample(&text, "v2ce_http_connections_total{result=\"timed_out\"}").unwrap();
    let evicted = sample(&text, "v2ce_http_connections_total{result=\"evicted\"}").unwrap();
    assert!(evicted >= 1.0, "{text}");
    let rejected = sample(&text, "v2ce_http_rejected_requests_total").unwrap();
    assert!(rejected >= 7.0, "{rejected}");
    eprintln!(
        "listener answered {:.2} s after the slowloris; {evicted} half-open connections evicted, \
         {timed_out} timed out",
        waited.as_secs_f64()
    );
    // The daemon kept streaming through it all.
    let before = sample(&text, "v2ce_frames_total").unwrap();
    wait_for(Duration::from_secs(10), "frames to keep coming", || {
        sample(&daemon.get("/metrics").1, "v2ce_frames_total").unwrap_or(0.0) > before
    });

    // Attackers still connected (a fresh slowloris): one SIGTERM stops it, promptly.
    for _ in 0..100 {
        if let Ok(mut s) = std::net::TcpStream::connect(&a) {
            let _ = s.write_all(b"GET / HTTP/1.1\r\n");
            held.push(s);
        }
    }
    let mut daemon = daemon;
    let started = Instant::now();
    assert_eq!(unsafe { libc::kill(pid as i32, libc::SIGTERM) }, 0);
    let status = loop {
        if let Some(s) = daemon.child.try_wait().unwrap() {
            break s;
        }
        assert!(
            started.elapsed() < Duration::from_secs(10),
            "no exit 10 s after SIGTERM while attacked"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(status.success(), "{status:?}");
    let mut out = String::new();
    daemon
        .child
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut out)
        .unwrap();
    assert!(out.contains("\"frames_in\""), "no report: {out}");
    eprintln!(
        "stopped {:.2} s after SIGTERM with {} attacking connections open",
        started.elapsed().as_secs_f64(),
        held.len() + streams.len()
    );
}

/// The latency of one `/healthz` probe (connect, request, the whole answer) and its status.
fn probe(address: &str, limit: Duration) -> (u16, Duration) {
    let started = Instant::now();
    let r = raw(address, b"GET /healthz HTTP/1.0\r\n\r\n", limit);
    (code(&r), started.elapsed())
}

/// The `q` quantile (nearest rank) of `samples`.
fn quantile(samples: &[Duration], q: f64) -> Duration {
    let mut sorted = samples.to_vec();
    sorted.sort();
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[rank - 1]
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// A slowloris holding every connection slot (300 half-open connections, each one byte of a
/// request head, against a cap of 256) delays no probe: the oldest half-open connection gives
/// way to each new one, so `/healthz` answers 200 at once (a liveness probe would otherwise
/// restart a healthy daemon), and the half-open ones that gave way are the oldest.
#[test]
fn half_open_connections_give_way_to_probes() {
    let dir = common::temp_dir("http-half-open");
    let daemon = Daemon::start(
        &["--source", "fixture", "--loop", "--udp", "127.0.0.1:9"],
        &dir,
    );
    let a = daemon.address.clone();
    assert_eq!(daemon.get("/healthz").0, 200);
    let mut held = Vec::new();
    for _ in 0..300 {
        let mut s = std::net::TcpStream::connect(&a).unwrap();
        let _ = s.write_all(b"G");
        held.push(s);
    }
    let attacked = Instant::now();
    let mut latencies = Vec::new();
    for i in 0..20 {
        let (code, took) = probe(&a, Duration::from_secs(5));
        assert_eq!(code, 200, "probe {i} with 300 half-open connections held");
        assert!(
            took < Duration::from_secs(1),
            "probe {i} took {took:?} with 300 half-open connections held"
        );
        latencies.push(took);
        std::thread::sleep(Duration::from_millis(20));
    }
    eprintln!(
        "/healthz with 300 half-open connections held: p50 {:.1} ms, p99 {:.1} ms (20 probes)",
        ms(quantile(&latencies, 0.5)),
        ms(quantile(&latencies, 0.99))
    );
    // The oldest gave way (closed without an answer); the newest still wait for their heads
    // (until the head timeout, 5 s after they came).
    let state = |s: &mut std::net::TcpStream| {
        s.set_read_timeout(Some(Duration::from_millis(200)))
            .unwrap();
        match s.read(&mut [0u8; 64]) {
            Ok(0) => "closed",
            Ok(_) => "answered",
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => "open",
            Err(_) => "closed",
        }
    };
    assert_eq!(state(&mut held[0]), "closed");
    if attacked.elapsed() < Duration::from_secs(4) {
        assert_eq!(state(&mut held[299]), "open");
    }
    let text = daemon.get("/metrics").1;
    let evicted = sample(&text, "v2ce_http_connections_total{result=\"evicted\"}").unwrap();
    // 300 through 256 slots (then each probe takes the slot the last one left, but the first).
    assert!(evicted >= 300.0 - 256.0, "{evicted} evicted");
    assert_eq!(
        sample(&text, "v2ce_http_connections_total{result=\"refused\"}"),
        Some(0.0)
    );
}

/// A reader of one `/events` stream (`query` after `?`), as a page: counts the messages until
/// told to stop; and whether the stream was still open then.
fn stream_reader(
    address: &str,
    query: &str,
    stop: Arc<std::sync::atomic::AtomicBool>,
) -> std::thread::JoinHandle<(u64, bool)> {
    let mut s = std::net::TcpStream::connect(address).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(s, "GET /events?{query} HTTP/1.0\r\nHost: x\r\n\r\n").unwrap();
    std::thread::spawn(move || {
        let mut reader = std::io::BufReader::new(s);
        let (mut messages, mut line) = (0u64, String::new());
        while !stop.load(std::sync::atomic::Ordering::Relaxed) {
            line.clear();
            match reader.read_line(&mut line) {
                Ok(0) | Err(_) => return (messages, false),
                Ok(_) => messages += u64::from(line.starts_with("data: ")),
            }
        }
        (messages, true)
    })
}

/// Eight preview pages (the most allowed) of a 1280x720 run, showing the last second of events:
/// the frames are encoded off the listener's thread, once per push for all of them, so
/// `/healthz` stays prompt (the target: p99 under 100 ms, printed; asserted with room
/// for a busy CI machine), the streams all keep coming, and no thread is added per stream.
#[test]
fn preview_streams_never_delay_probes() {
    let dir = common::temp_dir("http-streams");
    let daemon = Daemon::start(
        &[
            "--source",
            "fixture",
            "--size",
            "1280x720",
            "--loop",
            "--udp",
            "127.0.0.1:9",
        ],
        &dir,
    );
    let a = daemon.address.clone();
    let pid = daemon.child.id();
    wait_for(Duration::from_secs(60), "frames flowing", || {
        daemon.get("/readyz").0 == 200
    });
    let (threads0, _) = pipeline_threads_and_rss(pid, 2);
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    // The page's longest window: the densest frames, the slowest to encode.
    let readers: Vec<_> = (0..8)
        .map(|_| stream_reader(&a, "window_ms=1000", stop.clone()))
        .collect();
    std::thread::sleep(Duration::from_secs(1));
    let frames = |d: &Daemon| sample(&d.get("/metrics").1, "v2ce_http_preview_frames_total");
    let (encoded0, started) = (frames(&daemon).unwrap(), Instant::now());
    let mut latencies = Vec::new();
    for i in 0..50 {
        let (code, took) = probe(&a, Duration::from_secs(10));
        assert_eq!(code, 200, "probe {i}");
        latencies.push(took);
        std::thread::sleep(Duration::from_millis(20));
    }
    let (p50, p99) = (quantile(&latencies, 0.5), quantile(&latencies, 0.99));
    eprintln!(
        "/healthz with 8 preview streams of 1280x720 open: p50 {:.1} ms, p99 {:.1} ms, max {:.1} \
         ms (50 probes; the issue's target: p99 under 100 ms)",
        ms(p50),
        ms(p99),
        ms(*latencies.iter().max().unwrap())
    );
    assert!(p99 < Duration::from_millis(500), "p99 {p99:?}");
    // Still 8 streams: a ninth is refused; one encoder thread, one listener thread.
    assert_eq!(daemon.get("/events").0, 503);
    let (threads1, _) = threads_and_rss(pid);
    assert_eq!(threads1.0.get("v2ce-preview"), Some(&1), "{threads1:?}");
    assert_eq!(threads1.0.get("http"), Some(&1), "{threads1:?}");
    assert!(
        threads1.others() <= threads0.others() && threads1.lazy_bounded(),
        "threads {threads0:?} -> {threads1:?} with 8 streams"
    );
    let encoded = frames(&daemon).unwrap() - encoded0;
    let periods = started.elapsed().as_secs_f64() / 0.2;
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let got: Vec<(u64, bool)> = readers.into_iter().map(|r| r.join().unwrap()).collect();
    let messages: u64 = got.iter().map(|(m, _)| m).sum();
    eprintln!(
        "{encoded} frames encoded in {periods:.0} push periods; the 8 streams got {:?} messages",
        got.iter().map(|(m, _)| m).collect::<Vec<_>>()
    );
    assert!(got.iter().all(|(m, open)| *open && *m >= 2), "{got:?}");
    // Once per push for all 8 streams (one window), not once per stream.
    assert!(
        encoded <= periods + 2.0,
        "{encoded} frames in {periods:.0} periods"
    );
    assert!(
        messages as f64 >= 2.0 * encoded,
        "{messages} messages of {encoded} frames"
    );
}
