//! The DDS transport in a process of its own, under a memory cap.
//!
//! A DDS participant reassembles a fragmented sample into a buffer of the size its sender
//! declares, before anyone can look at the bytes (`rustdds` does so for every reader, the
//! discovery readers included), and anything that reaches the domain's ports can send such a
//! fragment: one datagram of 100 bytes made a listener resident at 512 MiB (measured). So
//! v2ce runs its participant in a child of its own binary (`v2ce dds-host`, hidden) whose
//! data segment is capped at [`limits::DDS_HOST_MEMORY`] and which the kernel's OOM killer takes
//! first: a claim past the cap ends the child, not the daemon. The parent says why (the
//! child's last words, its exit status), counts it ([`Publication::restarts`],
//! [`Subscription::restarts`]) and starts a new one after a backoff (1 s, doubling to 30 s;
//! back to 1 s after a minute of health); what is published meanwhile is counted as dropped.
//!
//! Messages cross a pair of pipes as frames: a kind byte, a 32-bit little-endian length, the
//! bytes; a length over [`limits::MAX_DDS_SAMPLE_BYTES`] ends the exchange before anything is
//! allocated. The child ends when its standard input closes (the parent dropped the endpoint
//! or died); it ignores the stop signals a terminal or systemd sends
//! to the whole group, so the daemon's last packets still leave through it.

use std::io::{BufRead, BufReader, Read, Write};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::dds::{Participant, Qos};
use crate::error::{Error, Result};
use crate::limits;

/// A message: to the child, one to publish; from it, one received.
const SAMPLE: u8 = 1;
/// To the child: wait for acknowledgements (payload: milliseconds, u64 LE).
const WAIT_ACK: u8 = 2;
/// From the child: the endpoint is open (one byte: 1 when its memory cap holds).
const READY: u8 = 3;
/// From the child: subscribers matched (u32 LE).
const MATCHED: u8 = 4;
/// From the child: a sample was published (empty) or not (the reason).
const SENT: u8 = 5;
/// From the child: whether every subscriber acknowledged (one byte).
const ACKED: u8 = 6;
/// From the child: the endpoint could not be opened (the reason).
const FAILED: u8 = 7;

/// How long opening waits for the child's endpoint.
const OPEN_WAIT: Duration = Duration::from_secs(15);
/// How long a publication waits for the child to take a sample (the writer itself blocks
/// 100 ms at most): past it the child is taken as hung and replaced.
const SEND_WAIT: Duration = Duration::from_secs(5);
/// The child's polling period for matches and for its reader.
const POLL: Duration = Duration::from_millis(20);
/// The first and the longest wait before a new child.
const BACKOFF: (Duration, Duration) = (Duration::from_secs(1), Duration::from_secs(30));
/// A child alive this long resets the backoff.
const HEALTHY: Duration = Duration::from_secs(60);
/// The longest line kept of what the child said last.
const LAST_WORDS: usize = 300;

/// What a child opens: a publication or a subscription of one topic.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Endpoint {
    /// The DDS domain.
    pub domain: u16,
    /// The ROS 2 topic (`/event_camera/events`).
    pub topic: String,
    /// The ROS 2 type (`event_camera_msgs/msg/EventPacket`).
    pub ros_type: String,
    /// Delivery.
    pub qos: Qos,
    /// A publication (else a subscription).
    pub publish: bool,
}

impl Endpoint {
    /// The child's command-line arguments after `dds-host`.
    fn args(&self) -> Vec<String> {
        let mut a = vec![
            "--domain".to_string(),
            self.domain.to_string(),
            "--topic".to_string(),
            self.topic.clone(),
            "--type".to_string(),
            self.ros_type.clone(),
            "--depth".to_string(),
            self.qos.depth.to_string(),
        ];
        if !self.qos.reliable {
            a.push("--best-effort".to_string());
        }
        if self.publish {
            a.push("--publish".to_string());
        }
        a
    }
}

fn write_frame(w: &mut impl Write, kind: u8, payload: &[u8]) -> std::io::Result<()> {
    let len = u32::try_from(payload.len())
        .ok()
        .filter(|n| u64::from(*n) <= limits::MAX_DDS_SAMPLE_BYTES)
        .ok_or_else(|| std::io::Error::other("a DDS sample over the limit"))?;
    let mut head = [0u8; 5];
    head[0] = kind;
    head[1..].copy_from_slice(&len.to_le_bytes());
    w.write_all(&head)?;
    w.write_all(payload)?;
    w.flush()
}

/// The next frame; `None` at the end of the stream. A length over the limit is an error,
/// found before anything is allocated.
fn read_frame(r: &mut impl Read) -> std::io::Result<Option<(u8, Vec<u8>)>> {
    let mut head = [0u8; 5];
    match r.read_exact(&mut head) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(None),
        Err(e) => return Err(e),
    }
    let len = u32::from_le_bytes([head[1], head[2], head[3], head[4]]);
    if u64::from(len) > limits::MAX_DDS_SAMPLE_BYTES {
        return Err(std::io::Error::other(format!(
            "a frame of {len} bytes from the DDS transport (at most {})",
            limits::MAX_DDS_SAMPLE_BYTES
        )));
    }
    let mut payload = vec![0u8; len as usize];
    r.read_exact(&mut payload)?;
    Ok(Some((head[0], payload)))
}

/// A running child.
struct Running {
    process: Child,
    stdin: Option<ChildStdin>,
    /// Frames from the child but its match counts.
    from: Receiver<(u8, Vec<u8>)>,
    matched: Arc<AtomicUsize>,
    ended: Arc<AtomicBool>,
    last_words: Arc<Mutex<String>>,
    started: Instant,
}

impl Running {
    fn spawn(endpoint: &Endpoint) -> Result<Running> {
        let exe = std::env::current_exe()
            .map_err(|e| Error::invalid("ROS 2", format!("finding the v2ce binary: {e}")))?;
        let mut command = Command::new(&exe);
        command
            .arg("dds-host")
            .args(endpoint.args())
            .env("RUST_BACKTRACE", "0")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        cap_the_child(&mut command);
        let mut process = command.spawn().map_err(|e| {
            Error::invalid(
                "ROS 2",
                format!("starting the DDS transport ({}): {e}", exe.display()),
            )
        })?;
        let (Some(stdin), Some(stdout), Some(stderr)) = (
            process.stdin.take(),
            process.stdout.take(),
            process.stderr.take(),
        ) else {
            let _ = process.kill();
            let _ = process.wait();
            return Err(Error::invalid("ROS 2", "the DDS transport's pipes"));
        };
        let matched = Arc::new(AtomicUsize::new(0));
        let ended = Arc::new(AtomicBool::new(false));
        let last_words = Arc::new(Mutex::new(String::new()));
        let (to, from) = std::sync::mpsc::sync_channel(4);
        spawn_reader(stdout, to, matched.clone(), ended.clone())?;
        spawn_stderr(stderr, last_words.clone())?;
        let mut running = Running {
            process,
            stdin: Some(stdin),
            from,
            matched,
            ended,
            last_words,
            started: Instant::now(),
        };
        match running.from.recv_timeout(OPEN_WAIT) {
            Ok((READY, capped)) => {
                if capped.first() != Some(&1) {
                    tracing::warn!(
                        "ros2 {}: the DDS transport runs without its memory cap (the limit \
                         was refused, as the systemd unit's system call filter does): the \
                         kernel's OOM killer takes it first, the service's MemoryMax bounds it",
                        endpoint.topic
                    );
                }
                Ok(running)
            }
            Ok((FAILED, why)) => Err(Error::invalid(
                "ROS 2",
                String::from_utf8_lossy(&why).into_owned(),
            )),
            Ok((kind, _)) => Err(Error::invalid(
                "ROS 2",
                format!("the DDS transport began with a frame of kind {kind}"),
            )),
            Err(_) => Err(Error::invalid(
                "ROS 2",
                format!("the DDS transport did not start: {}", running.end()),
            )),
        }
    }

    /// Stops the child (its input closed, then killed after a second) and says how it ended.
    fn end(&mut self) -> String {
        self.stdin = None;
        let deadline = Instant::now() + Duration::from_secs(1);
        let status = loop {
            match self.process.try_wait() {
                Ok(Some(s)) => break Some(s),
                Ok(None) if Instant::now() < deadline => std::thread::sleep(POLL),
                _ => {
                    let _ = self.process.kill();
                    break self.process.wait().ok();
                }
            }
        };
        // Its stderr drains within moments of its end.
        std::thread::sleep(Duration::from_millis(50));
        let words = self
            .last_words
            .lock()
            .map(|w| w.clone())
            .unwrap_or_default();
        let status = status.map_or("no status".to_string(), |s| s.to_string());
        if words.contains("memory allocation of") {
            format!(
                "{status}: {words}: past its cap of {} MiB, a sample a DDS peer declared",
                limits::DDS_HOST_MEMORY >> 20
            )
        } else if words.is_empty() {
            status
        } else {
            format!("{status}: {words}")
        }
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        self.end();
    }
}

/// Caps the child's data segment. (Its life is tied to the parent's by its input, whose
/// end closes with the parent: a parent-death signal would follow the spawning thread.)
fn cap_the_child(command: &mut Command) {
    use std::os::unix::process::CommandExt;
    let cap = limits::DDS_HOST_MEMORY as libc::rlim_t;
    // SAFETY: between fork and exec only an async-signal-safe call (setrlimit) is made,
    // on values computed before the fork.
    unsafe {
        command.pre_exec(move || {
            let limit = libc::rlimit {
                rlim_cur: cap,
                rlim_max: cap,
            };
            // Refused under a seccomp filter (the systemd unit's refuses @resources): the
            // child says so when it is ready, and the kernel's OOM killer takes it first.
            libc::setrlimit(libc::RLIMIT_DATA, &limit);
            Ok(())
        });
    }
}

/// Reads the child's frames: match counts kept, the rest passed on; `ended` at its end.
fn spawn_reader(
    stdout: std::process::ChildStdout,
    to: SyncSender<(u8, Vec<u8>)>,
    matched: Arc<AtomicUsize>,
    ended: Arc<AtomicBool>,
) -> Result<()> {
    std::thread::Builder::new()
        .name("v2ce-dds".into())
        .spawn(move || {
            let mut r = BufReader::new(stdout);
            while let Ok(Some((kind, payload))) = read_frame(&mut r) {
                if kind == MATCHED {
                    let n = payload
                        .get(..4)
                        .map_or(0, |b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize);
                    matched.store(n, Ordering::Relaxed);
                } else if to.send((kind, payload)).is_err() {
                    break;
                }
            }
            ended.store(true, Ordering::Relaxed);
        })
        .map(|_| ())
        .map_err(|e| Error::invalid("ROS 2", format!("a thread for the DDS transport: {e}")))
}

/// Keeps the last line the child wrote on stderr (its reason when it ends), bounded.
fn spawn_stderr(stderr: std::process::ChildStderr, last: Arc<Mutex<String>>) -> Result<()> {
    std::thread::Builder::new()
        .name("v2ce-dds-err".into())
        .spawn(move || {
            let mut r = BufReader::new(stderr);
            let mut line = Vec::new();
            loop {
                line.clear();
                // Lines are read in pieces of at most LAST_WORDS bytes.
                match r
                    .by_ref()
                    .take(LAST_WORDS as u64)
                    .read_until(b'\n', &mut line)
                {
                    Ok(0) | Err(_) => break,
                    Ok(_) => {
                        let text = String::from_utf8_lossy(&line).trim().to_string();
                        // A panic's closing hint says nothing of the cause.
                        if !text.is_empty() && !text.starts_with("note: ") {
                            if let Ok(mut l) = last.lock() {
                                *l = text;
                            }
                        }
                    }
                }
            }
        })
        .map(|_| ())
        .map_err(|e| Error::invalid("ROS 2", format!("a thread for the DDS transport: {e}")))
}

/// A child that is replaced with backoff when it ends.
struct Host {
    endpoint: Endpoint,
    running: Option<Running>,
    backoff: Duration,
    next_start: Instant,
    restarts: u64,
}

impl Host {
    fn open(endpoint: Endpoint) -> Result<Host> {
        let running = Running::spawn(&endpoint)?;
        Ok(Host {
            endpoint,
            running: Some(running),
            backoff: BACKOFF.0,
            next_start: Instant::now(),
            restarts: 0,
        })
    }

    /// The child, replaced when it ended and its backoff has passed; `None` meanwhile.
    fn running(&mut self) -> Option<&mut Running> {
        if self
            .running
            .as_ref()
            .is_some_and(|r| r.ended.load(Ordering::Relaxed))
        {
            self.lost(None);
        }
        if self.running.is_none() && Instant::now() >= self.next_start {
            match Running::spawn(&self.endpoint) {
                Ok(r) => {
                    self.restarts += 1;
                    tracing::info!(
                        "ros2 {}: a new DDS transport (restart {})",
                        self.endpoint.topic,
                        self.restarts
                    );
                    self.running = Some(r);
                }
                Err(e) => self.schedule(&e.to_string()),
            }
        }
        self.running.as_mut()
    }

    /// The child ended or failed (`why`, else its exit): stopped, and a new one scheduled.
    fn lost(&mut self, why: Option<&str>) {
        let Some(mut r) = self.running.take() else {
            return;
        };
        if r.started.elapsed() >= HEALTHY {
            self.backoff = BACKOFF.0;
        }
        let ended = r.end();
        let why = why.map_or(ended.clone(), |w| format!("{w} ({ended})"));
        self.schedule(&why);
    }

    fn schedule(&mut self, why: &str) {
        tracing::warn!(
            "ros2 {}: the DDS transport ended ({why}); a new one in {} s",
            self.endpoint.topic,
            self.backoff.as_secs_f64()
        );
        self.next_start = Instant::now() + self.backoff;
        self.backoff = (self.backoff * 2).min(BACKOFF.1);
    }

    /// Sends a frame to the child; false (and the child replaced) when it cannot take it.
    fn tell(&mut self, kind: u8, payload: &[u8]) -> bool {
        let Some(r) = self.running() else {
            return false;
        };
        let ok = r
            .stdin
            .as_mut()
            .is_some_and(|w| write_frame(w, kind, payload).is_ok());
        if !ok {
            self.lost(Some("its input closed"));
        }
        ok
    }

    /// The child's answer of `kind`, within `wait`; the child replaced when it gives none.
    fn answer(&mut self, kind: u8, wait: Duration) -> Option<Vec<u8>> {
        let deadline = Instant::now() + wait;
        let r = self.running.as_mut()?;
        loop {
            match r
                .from
                .recv_timeout(deadline.saturating_duration_since(Instant::now()))
            {
                Ok((k, payload)) if k == kind => return Some(payload),
                Ok(_) => {}
                Err(RecvTimeoutError::Timeout) => {
                    self.lost(Some("no answer"));
                    return None;
                }
                Err(RecvTimeoutError::Disconnected) => {
                    self.lost(None);
                    return None;
                }
            }
        }
    }
}

/// A publication of one ROS 2 topic through a DDS transport process.
pub struct Publication {
    host: Host,
}

impl Publication {
    /// Opens a publication of `ros_type` on `topic` in `domain`.
    pub fn open(domain: u16, topic: &str, ros_type: &str, qos: Qos) -> Result<Self> {
        Ok(Publication {
            host: Host::open(Endpoint {
                domain,
                topic: topic.to_string(),
                ros_type: ros_type.to_string(),
                qos,
                publish: true,
            })?,
        })
    }

    /// Publishes one CDR message. A reliable writer whose subscribers' history is full waits
    /// for them up to its blocking time, then errs; while the transport is being replaced,
    /// an error.
    pub fn send(&mut self, message: &[u8]) -> Result<()> {
        if !self.host.tell(SAMPLE, message) {
            return Err(Error::invalid("ROS 2", "the DDS transport is restarting"));
        }
        match self.host.answer(SENT, SEND_WAIT) {
            Some(why) if why.is_empty() => Ok(()),
            Some(why) => Err(Error::invalid(
                "ROS 2",
                String::from_utf8_lossy(&why).into_owned(),
            )),
            None => Err(Error::invalid("ROS 2", "the DDS transport ended")),
        }
    }

    /// The subscribers matched so far (0 while the transport is being replaced).
    pub fn subscribers(&mut self) -> usize {
        self.host
            .running()
            .map_or(0, |r| r.matched.load(Ordering::Relaxed))
    }

    /// The subscribers matched, as last known (0 while the transport is being replaced),
    /// without replacing an ended transport.
    pub fn matched(&self) -> usize {
        self.host
            .running
            .as_ref()
            .filter(|r| !r.ended.load(Ordering::Relaxed))
            .map_or(0, |r| r.matched.load(Ordering::Relaxed))
    }

    /// Waits until every reliable subscriber has acknowledged what was sent, at most `wait`;
    /// whether they all did.
    pub fn wait_acknowledged(&mut self, wait: Duration) -> bool {
        let ms = u64::try_from(wait.as_millis()).unwrap_or(u64::MAX);
        self.host.tell(WAIT_ACK, &ms.to_le_bytes())
            && self
                .host
                .answer(ACKED, wait + SEND_WAIT)
                .is_some_and(|a| a.first() == Some(&1))
    }

    /// Times the transport was replaced.
    pub fn restarts(&self) -> u64 {
        self.host.restarts
    }
}

/// A subscription to one ROS 2 topic through a DDS transport process.
pub struct Subscription {
    host: Host,
}

impl Subscription {
    /// Opens a subscription to `ros_type` on `topic` in `domain`.
    pub fn open(domain: u16, topic: &str, ros_type: &str, qos: Qos) -> Result<Self> {
        Ok(Subscription {
            host: Host::open(Endpoint {
                domain,
                topic: topic.to_string(),
                ros_type: ros_type.to_string(),
                qos,
                publish: false,
            })?,
        })
    }

    /// The next message (a whole CDR message), waiting at most `timeout`; `None` when none
    /// came (a transport being replaced included).
    pub fn next(&mut self, timeout: Duration) -> Result<Option<Vec<u8>>> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let Some(r) = self.host.running() else {
                // Waiting out the backoff, within the caller's time.
                let wake = self.host.next_start.min(deadline);
                std::thread::sleep(wake.saturating_duration_since(Instant::now()));
                if Instant::now() >= deadline {
                    return Ok(None);
                }
                continue;
            };
            match r.from.recv_timeout(left) {
                Ok((SAMPLE, payload)) => return Ok(Some(payload)),
                Ok(_) => {}
                Err(RecvTimeoutError::Timeout) => return Ok(None),
                Err(RecvTimeoutError::Disconnected) => self.host.lost(None),
            }
        }
    }

    /// Times the transport was replaced.
    pub fn restarts(&self) -> u64 {
        self.host.restarts
    }
}

/// The child's side (`v2ce dds-host`): opens `endpoint` and serves it over standard input and
/// output until its input closes.
pub fn serve(endpoint: &Endpoint) -> Result<()> {
    // Under memory pressure the kernel takes this process before the daemon.
    let _ = std::fs::write("/proc/self/oom_score_adj", "1000");
    // A stop signal for the whole group (Ctrl-C in a terminal, systemd's stop of the unit's
    // cgroup) is the daemon's to act on: it sends its last packets through this process and
    // then closes its input, which ends it.
    for signal in [libc::SIGINT, libc::SIGTERM, libc::SIGHUP, libc::SIGQUIT] {
        // SAFETY: setting a signal's disposition to ignore, no handler involved.
        unsafe { libc::signal(signal, libc::SIG_IGN) };
    }
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit fills the struct it is given.
    let capped = unsafe { libc::getrlimit(libc::RLIMIT_DATA, &mut limit) } == 0
        && limit.rlim_cur <= limits::DDS_HOST_MEMORY as libc::rlim_t;
    let mut out = std::io::stdout().lock();
    let io = |e: std::io::Error| Error::invalid("DDS transport", e.to_string());
    let participant = match Participant::new(endpoint.domain) {
        Ok(p) => p,
        Err(e) => {
            write_frame(&mut out, FAILED, e.to_string().as_bytes()).map_err(io)?;
            return Err(e);
        }
    };
    // The parent's frames, read on a thread of their own; the channel closes with the input.
    let (to, commands) = std::sync::mpsc::sync_channel::<(u8, Vec<u8>)>(1);
    std::thread::Builder::new()
        .name("v2ce-dds-in".into())
        .spawn(move || {
            let mut input = std::io::stdin().lock();
            while let Ok(Some(frame)) = read_frame(&mut input) {
                if to.send(frame).is_err() {
                    break;
                }
            }
        })
        .map_err(io)?;
    let (topic, ty, qos) = (&endpoint.topic, &endpoint.ros_type, endpoint.qos);
    if endpoint.publish {
        let publication = match participant.publish(topic, ty, qos) {
            Ok(p) => p,
            Err(e) => {
                write_frame(&mut out, FAILED, e.to_string().as_bytes()).map_err(io)?;
                return Err(e);
            }
        };
        write_frame(&mut out, READY, &[capped as u8]).map_err(io)?;
        let mut matched = 0;
        loop {
            match commands.recv_timeout(POLL) {
                Ok((SAMPLE, message)) => {
                    let said = publication.send(message).err().map(|e| e.to_string());
                    write_frame(&mut out, SENT, said.unwrap_or_default().as_bytes()).map_err(io)?;
                }
                Ok((WAIT_ACK, ms)) => {
                    let ms = ms.get(..8).map_or(0, |b| {
                        u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]])
                    });
                    let all = publication.wait_acknowledged(Duration::from_millis(ms));
                    write_frame(&mut out, ACKED, &[all as u8]).map_err(io)?;
                }
                Ok(_) | Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => return Ok(()),
            }
            let now = publication.subscribers();
            if now != matched {
                matched = now;
                let n = u32::try_from(now).unwrap_or(u32::MAX);
                write_frame(&mut out, MATCHED, &n.to_le_bytes()).map_err(io)?;
            }
        }
    } else {
        let mut subscription = match participant.subscribe(topic, ty, qos) {
            Ok(s) => s,
            Err(e) => {
                write_frame(&mut out, FAILED, e.to_string().as_bytes()).map_err(io)?;
                return Err(e);
            }
        };
        write_frame(&mut out, READY, &[capped as u8]).map_err(io)?;
        loop {
            if let Err(std::sync::mpsc::TryRecvError::Disconnected) = commands.try_recv() {
                return Ok(());
            }
            if let Some(message) = subscription.next(POLL)? {
                // A message over the frame limit is the parent's to refuse: it is not sent.
                if message.len() as u64 <= limits::MAX_DDS_SAMPLE_BYTES {
                    write_frame(&mut out, SAMPLE, &message).map_err(io)?;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_round_trip_and_lengths_are_bounded_before_allocation() {
        let mut buf = Vec::new();
        write_frame(&mut buf, SAMPLE, b"abc").unwrap();
        write_frame(&mut buf, READY, &[1]).unwrap();
        let mut r = &buf[..];
        assert_eq!(read_frame(&mut r).unwrap(), Some((SAMPLE, b"abc".to_vec())));
        assert_eq!(read_frame(&mut r).unwrap(), Some((READY, vec![1])));
        assert_eq!(read_frame(&mut r).unwrap(), None);
        // A length past the limit: an error, nothing allocated.
        let mut huge = vec![SAMPLE];
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        assert!(read_frame(&mut &huge[..]).is_err());
        // A frame cut short: an error, not a short frame.
        let cut = &buf[..6];
        assert!(read_frame(&mut &cut[..]).is_err());
    }

    #[test]
    fn the_child_arguments_say_the_endpoint() {
        let e = Endpoint {
            domain: 7,
            topic: "/a/b".into(),
            ros_type: "x/msg/Y".into(),
            qos: Qos {
                reliable: false,
                depth: 3,
            },
            publish: true,
        };
        let a = e.args().join(" ");
        assert_eq!(
            a,
            "--domain 7 --topic /a/b --type x/msg/Y --depth 3 --best-effort --publish"
        );
    }
}
