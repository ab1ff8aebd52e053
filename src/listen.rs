//! `v2ce listen`: a receiver for what the daemon sends, the tool a user runs to check a setup
//! (and what the tests use): UDP datagrams in any of the word formats, or a TCP stream (DV's
//! AEDAT 4.0 network stream or Prophesee RAW EVT 2.0/3.0). It counts events and datagrams,
//! measures the rate, the largest gap between arrivals and, for formats with timestamps, the
//! spread of arrival time minus event time, and can write what it got to an event file.
//!
//! For plain `spif`, which carries no timestamps, the arrival time is the event time: events
//! written to a file get their arrival time, in microseconds since the first datagram.
//!
//! Times from the network enter here: a datagram or packet holding an event time outside
//! `±`[`crate::time::MAX_ABS_US`] is refused whole and counted ([`ListenReport::out_of_range`]),
//! as is, when writing to a file, one whose times go back ([`ListenReport::out_of_order`]), so
//! that no sender can wrap what the listener computes or end its file. The first refusal of
//! each kind is logged with its reason.

use std::io::{BufRead, Read};
use std::net::{TcpStream, UdpSocket};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::error::{Error, Result};
use crate::event::Event;
use crate::format::datagram::UdpFormat;
use crate::format::{self, aedat4, EventEncoder};
use crate::pipeline::stats::Latency;

/// What to listen to.
#[derive(Debug, Clone, PartialEq)]
pub enum Listen {
    /// Bind this `HOST:PORT` (port 0: any) and decode datagrams of `format`.
    Udp {
        /// The address to bind.
        bind: String,
        /// The datagram format.
        format: UdpFormat,
    },
    /// Connect to a daemon's TCP stream at `HOST:PORT` (AEDAT 4.0 or RAW EVT 2.0/3.0, told
    /// apart by its first byte).
    Tcp {
        /// The address to connect to.
        connect: String,
    },
    /// Subscribe to a ROS 2 topic of `event_camera_msgs/msg/EventPacket` (`evt3`) on a DDS
    /// domain; each packet is decoded alone.
    Ros2 {
        /// The ROS 2 topic.
        topic: String,
        /// The DDS domain.
        domain: u16,
    },
}

/// How long to listen and what to keep.
#[derive(Debug, Clone, PartialEq)]
pub struct ListenOptions {
    /// The source.
    pub listen: Listen,
    /// Write the events here (the extension picks the format).
    pub out: Option<PathBuf>,
    /// Sensor size for the file (UDP formats carry none; TCP streams do).
    pub size: (u16, u16),
    /// Stop after this long.
    pub duration: Option<Duration>,
    /// Stop when nothing arrived for this long after the first arrival.
    pub idle: Duration,
    /// Stop after this many events.
    pub max_events: Option<u64>,
    /// Kernel receive buffer for UDP, bytes (0: the system's default).
    pub recv_buffer: usize,
    /// Realtime (`SCHED_FIFO`) priority of the receiving thread, 1..=99, when the process may
    /// (0: normal scheduling); see [`crate::realtime`].
    pub priority: u8,
}

/// What [`listen`] got.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ListenReport {
    /// Events decoded.
    pub events: u64,
    /// Datagrams (UDP) or packets (TCP) received.
    pub messages: u64,
    /// Payload bytes received.
    pub bytes: u64,
    /// Datagrams whose length is not a whole number of events (cut short by the sender or a
    /// receiver buffer).
    pub ragged: u64,
    /// Datagrams (UDP) or packets (TCP) refused whole, their events neither counted nor
    /// written: one holding an event time outside `±`[`crate::time::MAX_ABS_US`] (see
    /// [`crate::time`]).
    pub out_of_range: u64,
    /// Datagrams or packets refused whole when writing to a file, their events neither counted
    /// nor written: one whose event times go back (within it, or before the last event
    /// written), which an event file cannot hold (datagrams reordered on the way, a sender
    /// restarted, a 32-bit time wrapped).
    pub out_of_order: u64,
    /// Datagrams or packets refused whole when writing to a file, their events neither counted
    /// nor written: one holding a pixel off the sensor (`--size`, or the stream's header),
    /// which the file cannot hold.
    pub off_sensor: u64,
    /// ROS 2 packets refused whole: a message that does not decode (malformed CDR, an
    /// encoding other than `evt3`, words cut short).
    pub malformed: u64,
    /// ROS 2 packets missing from the `seq` numbering (sent but not received, or before this
    /// receiver joined: not counted).
    pub seq_gaps: u64,
    /// ROS 2: times the DDS transport's process was replaced (a peer's sample past its
    /// memory cap ended it; see `ros2::host`).
    pub transport_restarts: u64,
    /// Seconds from the first arrival to the last.
    pub seconds: f64,
    /// Events per second over that span.
    pub events_per_s: f64,
    /// Longest time between two arrivals, ms.
    pub largest_gap_ms: f64,
    /// Most messages that arrived within one millisecond.
    pub max_messages_per_ms: u64,
    /// Arrival time minus event time, less its smallest value (formats with timestamps; a
    /// sender at event time keeps this near zero).
    pub arrival_spread: Option<Latency>,
    /// The receiving thread ran at realtime priority (UDP; see `ListenOptions::priority`).
    pub realtime: bool,
    /// First and last event time as received, us.
    pub first_t: Option<i64>,
    /// See `first_t`.
    pub last_t: Option<i64>,
}

/// Arrival minus event time of every event: a uniform sample of at most [`Offsets::SAMPLE`]
/// values (reservoir sampling, seeded), so memory stays flat however long a listen runs, and
/// the exact extremes.
struct Offsets {
    sample: Vec<i64>,
    seen: u64,
    min: i64,
    max: i64,
    rng: rand_xoshiro::Xoshiro256PlusPlus,
}

impl Offsets {
    /// Values kept for the percentiles (8 MiB): a p99 from a million draws is within a few
    /// hundredths of a percentile of the whole stream's.
    const SAMPLE: usize = 1 << 20;

    fn new() -> Self {
        use rand::SeedableRng;
        Offsets {
            sample: Vec::new(),
            seen: 0,
            min: i64::MAX,
            max: i64::MIN,
            rng: rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(0),
        }
    }

    fn push(&mut self, offset: i64) {
        use rand::Rng;
        self.seen += 1;
        self.min = self.min.min(offset);
        self.max = self.max.max(offset);
        if self.sample.len() < Self::SAMPLE {
            self.sample.push(offset);
        } else {
            let j = self.rng.gen_range(0..self.seen);
            if let Some(slot) = self.sample.get_mut(j as usize) {
                *slot = offset;
            }
        }
    }

    /// The spread above the smallest offset: percentiles from the sample, count and maximum
    /// exact.
    fn spread(&self) -> Result<Option<Latency>> {
        if self.seen == 0 {
            return Ok(None);
        }
        let mut h = hdrhistogram::Histogram::<u64>::new_with_bounds(1, 3_600_000_000, 3)
            .map_err(|e| Error::invalid("histogram", e.to_string()))?;
        for o in &self.sample {
            h.saturating_record((o.saturating_sub(self.min).max(0) as u64).max(1));
        }
        let mut spread = Latency::of(&h);
        spread.count = self.seen;
        spread.max_ms = self.max.saturating_sub(self.min) as f64 / 1000.0;
        Ok(Some(spread))
    }
}

/// Why a message was refused (see [`ListenReport::out_of_range`] and
/// [`ListenReport::out_of_order`]).
#[derive(Debug, Clone, Copy)]
enum Refusal {
    OutOfRange,
    OutOfOrder,
    OffSensor,
}

struct Tally {
    started: Option<Instant>,
    last: Option<Instant>,
    report: ListenReport,
    /// Arrival minus event time, us (timestamped formats).
    offsets: Offsets,
    per_ms: (u64, u64),
    out: Option<Box<dyn EventEncoder + Send>>,
    /// The sensor size of `out`'s file, whose pixels it can hold.
    size: (u16, u16),
    /// The time of the last event written to `out`.
    written_t: Option<i64>,
    /// The latest arrival time given to untimestamped events, us: arrival stamps mapped from
    /// the kernel's clock may step back a little, and those events keep time order.
    arrival_t: i64,
}

impl Tally {
    fn new(out: Option<Box<dyn EventEncoder + Send>>, size: (u16, u16)) -> Self {
        Tally {
            size,
            started: None,
            last: None,
            report: ListenReport::default(),
            offsets: Offsets::new(),
            per_ms: (0, 0),
            out,
            written_t: None,
            arrival_t: 0,
        }
    }

    /// Counts a message that arrived `at` (arrival stamps may step back a little: differences
    /// saturate at zero).
    fn arrive(&mut self, at: Instant, bytes: usize) {
        let first = *self.started.get_or_insert(at);
        if let Some(last) = self.last {
            let gap = at.saturating_duration_since(last).as_secs_f64() * 1e3;
            self.report.largest_gap_ms = self.report.largest_gap_ms.max(gap);
        }
        self.last = Some(at);
        let ms = u64::try_from(at.saturating_duration_since(first).as_millis()).unwrap_or(u64::MAX);
        self.per_ms = if ms == self.per_ms.0 {
            (ms, self.per_ms.1.saturating_add(1))
        } else {
            (ms, 1)
        };
        self.report.max_messages_per_ms = self.report.max_messages_per_ms.max(self.per_ms.1);
        self.report.messages = self.report.messages.saturating_add(1);
        self.report.bytes = self.report.bytes.saturating_add(bytes as u64);
    }

    /// Takes one message's events: refuses it whole (counted) where a time is out of range, or
    /// goes back while writing to a file; else counts them, measures arrival minus event time
    /// (`timestamped`) or gives them their arrival time, and writes them.
    fn events(&mut self, at: Instant, events: &mut [Event], timestamped: bool) -> Result<()> {
        // Microseconds since the first arrival, at most 2^61 (73,000 years): in range.
        let arrival = self.started.map_or(0, |f| {
            let us = at.saturating_duration_since(f).as_micros();
            i64::try_from(us).map_or(crate::time::MAX_ABS_US, |us| {
                us.min(crate::time::MAX_ABS_US)
            })
        });
        if timestamped {
            // Times enter here: every later difference of two fits (see `crate::time`).
            let bad = events.iter().find_map(|e| {
                crate::time::check("event time", e.t)
                    .err()
                    .map(|err| format!("the event at ({}, {}): {err}", e.x, e.y))
            });
            if let Some(why) = bad {
                self.refuse(Refusal::OutOfRange, &why);
                return Ok(());
            }
        } else {
            self.arrival_t = self.arrival_t.max(arrival);
            for e in events.iter_mut() {
                e.t = self.arrival_t;
            }
        }
        if self.out.is_some() {
            let (w, h) = self.size;
            if let Some(e) = events.iter().find(|e| e.x >= w || e.y >= h) {
                let why = format!("({}, {}) on a {w} x {h} sensor", e.x, e.y);
                self.refuse(Refusal::OffSensor, &why);
                return Ok(());
            }
            let mut last = self.written_t.unwrap_or(i64::MIN);
            for e in events.iter() {
                if e.t < last {
                    let why = format!("event time {} us comes before {last} us", e.t);
                    self.refuse(Refusal::OutOfOrder, &why);
                    return Ok(());
                }
                last = e.t;
            }
        }
        if timestamped {
            for e in events.iter() {
                // Both within 2^61 us: the difference fits.
                self.offsets.push(arrival - e.t);
            }
        }
        if let (Some(f), Some(l)) = (events.first(), events.last()) {
            self.report.first_t.get_or_insert(f.t);
            self.report.last_t = Some(l.t);
        }
        self.report.events = self.report.events.saturating_add(events.len() as u64);
        if let Some(out) = self.out.as_mut() {
            out.write(events)?;
            if let Some(l) = events.last() {
                self.written_t = Some(l.t);
            }
        }
        Ok(())
    }

    /// Counts a refused message; logs the first of each kind with `why`.
    fn refuse(&mut self, kind: Refusal, why: &str) {
        let (count, what) = match kind {
            Refusal::OutOfRange => (&mut self.report.out_of_range, "a time out of range"),
            Refusal::OutOfOrder => (&mut self.report.out_of_order, "times that go back"),
            Refusal::OffSensor => (&mut self.report.off_sensor, "a pixel off the sensor"),
        };
        *count = count.saturating_add(1);
        if *count == 1 {
            tracing::warn!(
                "listen: refused a message with {what} ({why}); further ones are counted in the report"
            );
        } else {
            tracing::debug!("listen: refused a message with {what} ({why})");
        }
    }

    fn finish(mut self) -> Result<ListenReport> {
        if let Some(out) = self.out.as_mut() {
            out.finish()?;
        }
        let mut r = self.report;
        if let (Some(a), Some(b)) = (self.started, self.last) {
            r.seconds = (b - a).as_secs_f64();
            r.events_per_s = r.events as f64 / r.seconds.max(1e-9);
        }
        r.arrival_spread = self.offsets.spread()?;
        Ok(r)
    }
}

/// Listens until `stop`, a limit, or the idle time after the first arrival; `ready` gets the
/// local (UDP) or remote (TCP) address once listening.
pub fn listen(
    options: &ListenOptions,
    stop: &AtomicBool,
    ready: impl FnOnce(&str),
) -> Result<ListenReport> {
    let deadline = options.duration.map(|d| Instant::now() + d);
    let out = |size: (u16, u16)| -> Result<Option<Box<dyn EventEncoder + Send>>> {
        match &options.out {
            None => Ok(None),
            Some(path) => {
                let format = format::Format::for_output(path, None, format::Compression::Lz4)?;
                Ok(Some(format::create(path, format, size.0, size.1)?))
            }
        }
    };
    let done = |t: &Tally| {
        stop.load(Ordering::Relaxed)
            || deadline.is_some_and(|d| Instant::now() >= d)
            || options.max_events.is_some_and(|m| t.report.events >= m)
            || t.last.is_some_and(|l| l.elapsed() >= options.idle)
    };
    match &options.listen {
        Listen::Udp { bind, format } => {
            let err = |e: std::io::Error| Error::io(PathBuf::from(bind), e);
            let socket = UdpSocket::bind(bind).map_err(err)?;
            if options.recv_buffer > 0 {
                crate::sink::udp::set_socket_buffer(&socket, libc::SO_RCVBUF, options.recv_buffer);
            }
            socket
                .set_read_timeout(Some(Duration::from_millis(50)))
                .map_err(err)?;
            kernel_timestamps(&socket);
            if let Err(e) = crate::realtime::make_realtime(options.priority) {
                tracing::debug!(
                    "receiver at normal priority (realtime {} refused: {e})",
                    options.priority
                );
            }
            let realtime = crate::realtime::is_realtime();
            let local = socket.local_addr().map_err(err)?;
            ready(&local.to_string());
            let mut tally = Tally::new(out(options.size)?, options.size);
            tally.report.realtime = realtime;
            let timestamped = *format != UdpFormat::Spif;
            let mut buf = vec![0u8; 65_536];
            let mut events = Vec::new();
            while !done(&tally) {
                let (n, at) = match recv_stamped(&socket, &mut buf) {
                    Ok(got) => got,
                    // A signal interrupts the wait (a stop then ends the loop).
                    Err(e)
                        if matches!(
                            e.kind(),
                            std::io::ErrorKind::WouldBlock
                                | std::io::ErrorKind::TimedOut
                                | std::io::ErrorKind::Interrupted
                        ) =>
                    {
                        continue
                    }
                    Err(e) => return Err(err(e)),
                };
                tally.arrive(at, n);
                if n % format.event_bytes() != 0 {
                    tally.report.ragged += 1;
                }
                events.clear();
                format.decode(&buf[..n], &mut events);
                tally.events(at, &mut events, timestamped)?;
            }
            tally.finish()
        }
        Listen::Tcp { connect } => {
            let err = |e: std::io::Error| Error::io(PathBuf::from(connect), e);
            let stream = TcpStream::connect(connect).map_err(err)?;
            stream
                .set_read_timeout(Some(Duration::from_millis(200)))
                .map_err(err)?;
            let peer = stream.peer_addr().map_err(err)?;
            let reader = Patient {
                inner: stream,
                give_up: &|| stop.load(Ordering::Relaxed),
            };
            let mut reader = std::io::BufReader::with_capacity(1 << 16, reader);
            // A RAW stream starts with its text header ('%'); DV's network stream with the
            // IOHeader's size.
            let is_raw = reader.fill_buf().map_err(err)?.first() == Some(&b'%');
            if is_raw {
                let header = format::raw::read_header(&mut reader)?;
                let mut decoder: Box<dyn format::EventDecoder> = match header.evt {
                    Some(format::raw::Evt::Evt3) => {
                        Box::new(format::evt3::Decoder::new(reader, &header))
                    }
                    _ => Box::new(format::evt2::Decoder::new(reader, &header)),
                };
                let size = decoder.size().unwrap_or(options.size);
                ready(&peer.to_string());
                let mut tally = Tally::new(out(size)?, size);
                let mut events = Vec::new();
                while !done(&tally) {
                    events.clear();
                    // Small reads: a decoder waits until its words have arrived.
                    let n = decoder.read_events(&mut events, 64)?;
                    if n == 0 {
                        break;
                    }
                    let at = Instant::now();
                    tally.arrive(at, n * 4);
                    tally.events(at, &mut events, true)?;
                }
                return tally.finish();
            }
            let mut reader = aedat4::Reader::new_stream(reader)?;
            let size = reader
                .event_stream()
                .and_then(|s| s.size)
                .unwrap_or(options.size);
            ready(&peer.to_string());
            let mut tally = Tally::new(out(size)?, size);
            while !done(&tally) {
                match reader.next_item()? {
                    None => break,
                    Some(aedat4::Item::Events(mut events)) => {
                        let at = Instant::now();
                        tally.arrive(at, events.len() * 16);
                        tally.events(at, &mut events, true)?;
                    }
                    Some(_) => {}
                }
            }
            tally.finish()
        }
        Listen::Ros2 { topic, domain } => listen_ros2(
            topic,
            *domain,
            out(options.size)?,
            options.size,
            &done,
            ready,
        ),
    }
}

/// `listen --ros2`: EventPacket messages, each decoded alone.
fn listen_ros2(
    topic: &str,
    domain: u16,
    out: Option<Box<dyn EventEncoder + Send>>,
    size: (u16, u16),
    done: &dyn Fn(&Tally) -> bool,
    ready: impl FnOnce(&str),
) -> Result<ListenReport> {
    let mut sub = crate::ros2::host::Subscription::open(
        domain,
        topic,
        crate::ros2::msg::EVENT_PACKET,
        crate::ros2::dds::Qos {
            reliable: true,
            depth: 1000,
        },
    )?;
    ready(&format!("{topic} (domain {domain})"));
    let mut tally = Tally::new(out, size);
    let mut events = Vec::new();
    let mut next_seq: Option<u64> = None;
    while !done(&tally) {
        let Some(bytes) = sub.next(Duration::from_millis(50))? else {
            continue;
        };
        let at = Instant::now();
        tally.arrive(at, bytes.len());
        let packet = match crate::ros2::msg::EventPacket::from_cdr(&bytes) {
            Ok(p) => p,
            Err(e) => {
                tally.report.malformed += 1;
                tracing::warn!("{topic}: a malformed packet refused: {e}");
                continue;
            }
        };
        if let Some(want) = next_seq {
            tally.report.seq_gaps += packet.seq.saturating_sub(want);
        }
        next_seq = Some(packet.seq.saturating_add(1));
        events.clear();
        match format::event_packet::unpack(&packet, &mut events) {
            Err(e) => {
                tally.report.malformed += 1;
                tracing::warn!("{topic}: packet {} refused: {e}", packet.seq);
                continue;
            }
            // Refused whole, as a datagram with a pixel off the sensor is.
            Ok(u) if u.off_sensor > 0 => {
                tally.report.off_sensor += 1;
                continue;
            }
            Ok(_) => {}
        }
        tally.events(at, &mut events, true)?;
    }
    let mut report = tally.finish()?;
    report.transport_restarts = sub.restarts();
    Ok(report)
}

/// A TCP stream whose reads wait out timeouts until `give_up` says so (the stream's own read
/// timeout only lets the caller check for a stop).
struct Patient<'a> {
    inner: TcpStream,
    give_up: &'a dyn Fn() -> bool,
}

impl Read for Patient<'_> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        loop {
            match self.inner.read(buf) {
                // A wait cut short by the timeout or a signal: on, or the end where the
                // caller stops (its files are finished and its report printed).
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock
                            | std::io::ErrorKind::TimedOut
                            | std::io::ErrorKind::Interrupted
                    ) =>
                {
                    if (self.give_up)() {
                        return Ok(0);
                    }
                }
                other => return other,
            }
        }
    }
}

/// Asks the kernel to stamp each datagram with the time it arrived (`SO_TIMESTAMPNS`), so
/// arrival times do not include how long this thread took to be scheduled. (In a process that
/// is the machine's first to ask, the kernel's switch takes a moment, and datagrams read before
/// then are stamped at the read.)
fn kernel_timestamps(socket: &UdpSocket) {
    use std::os::fd::AsRawFd;
    let on: libc::c_int = 1;
    // SAFETY: an integer option on a socket we own, with its exact size.
    unsafe {
        libc::setsockopt(
            socket.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_TIMESTAMPNS,
            (&on as *const libc::c_int).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        );
    }
}

/// Receives one datagram; returns its length and when it arrived: the kernel's stamp mapped
/// onto the monotonic clock, or now when the kernel gave none.
fn recv_stamped(socket: &UdpSocket, buf: &mut [u8]) -> std::io::Result<(usize, Instant)> {
    use std::os::fd::AsRawFd;
    let mut iov = libc::iovec {
        iov_base: buf.as_mut_ptr().cast(),
        iov_len: buf.len(),
    };
    // Room for one control message holding a timespec, aligned for cmsghdr.
    let mut control = [0u64; 16];
    // SAFETY: msghdr is plain data; every pointer set below outlives the call.
    let mut msg: libc::msghdr = unsafe { std::mem::zeroed() };
    msg.msg_iov = &mut iov;
    msg.msg_iovlen = 1;
    msg.msg_control = control.as_mut_ptr().cast();
    msg.msg_controllen = std::mem::size_of_val(&control) as _;
    // SAFETY: a socket we own and a msghdr whose buffers are valid for their stated lengths.
    let n = unsafe { libc::recvmsg(socket.as_raw_fd(), &mut msg, 0) };
    let now = Instant::now();
    if n < 0 {
        return Err(std::io::Error::last_os_error());
    }
    let mut at = now;
    // SAFETY: the CMSG macros walk the control buffer the kernel filled, within its length.
    unsafe {
        let mut c = libc::CMSG_FIRSTHDR(&msg);
        while !c.is_null() {
            if (*c).cmsg_level == libc::SOL_SOCKET && (*c).cmsg_type == libc::SCM_TIMESTAMPNS {
                let ts = std::ptr::read_unaligned(libc::CMSG_DATA(c) as *const libc::timespec);
                let stamp = std::time::UNIX_EPOCH
                    + Duration::new(
                        ts.tv_sec.max(0) as u64,
                        ts.tv_nsec.clamp(0, 999_999_999) as u32,
                    );
                // How long ago the datagram arrived, on the wall clock; onto the monotonic one.
                if let Ok(ago) = std::time::SystemTime::now().duration_since(stamp) {
                    at = now.checked_sub(ago).unwrap_or(now);
                }
            }
            c = libc::CMSG_NXTHDR(&msg, c);
        }
    }
    Ok((n as usize, at))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offsets_keep_a_bounded_sample_with_exact_extremes() {
        let mut o = Offsets::new();
        let n = 3 * Offsets::SAMPLE as i64;
        // Offsets 1000..1000+n us in a scrambled order, one outlier 50 ms late.
        for i in 0..n {
            o.push(1000 + (i * 7919) % n);
        }
        o.push(1000 + 50_000 + n);
        assert_eq!(o.sample.len(), Offsets::SAMPLE);
        let s = o.spread().unwrap().unwrap();
        assert_eq!(s.count, n as u64 + 1);
        assert_eq!(s.max_ms, (50_000 + n) as f64 / 1000.0);
        // Uniform over 0..n us: the median is n/2 within a percent.
        let p50_us = s.p50_ms * 1000.0;
        assert!((p50_us / (n as f64 / 2.0) - 1.0).abs() < 0.01, "{s:?}");
        assert!(Offsets::new().spread().unwrap().is_none());
    }

    fn at(ts: &[i64]) -> Vec<Event> {
        ts.iter().map(|&t| Event::new(t, 1, 2, true)).collect()
    }

    /// A datagram with a time outside ±2^61 us (the ends of `i64`, one past the range) is
    /// refused whole and counted; the range's ends themselves and times that go back are taken
    /// (nothing is written), and what is computed from them does not wrap.
    #[test]
    fn times_out_of_range_refuse_their_datagram() {
        use crate::time::MAX_ABS_US;
        let mut tally = Tally::new(None, (8, 8));
        let now = Instant::now();
        for bad in [i64::MIN, i64::MAX, MAX_ABS_US + 1, -MAX_ABS_US - 1] {
            tally.arrive(now, 26);
            tally.events(now, &mut at(&[0, bad]), true).unwrap();
        }
        assert_eq!(tally.report.out_of_range, 4);
        assert_eq!((tally.report.events, tally.report.messages), (0, 4));
        assert_eq!(tally.report.first_t, None);
        for ts in [[MAX_ABS_US, -MAX_ABS_US], [5, 3]] {
            let later = now + Duration::from_millis(1);
            tally.arrive(later, 26);
            tally.events(later, &mut at(&ts), true).unwrap();
        }
        let r = tally.finish().unwrap();
        assert_eq!(
            (r.events, r.messages, r.out_of_range, r.out_of_order),
            (4, 6, 4, 0)
        );
        assert_eq!((r.first_t, r.last_t), (Some(MAX_ABS_US), Some(3)));
        // Offsets from -2^61 to 2^61 us (plus the arrival): a spread of 2^62 us, exact.
        let spread = r.arrival_spread.unwrap();
        assert_eq!(spread.count, 4);
        assert_eq!(spread.max_ms, (2 * MAX_ABS_US) as f64 / 1000.0);
        // Plain spif: whatever the words hold, events get their arrival time, which never
        // goes back (a stamp 4 ms early keeps the latest).
        let mut tally = Tally::new(None, (8, 8));
        tally.arrive(now, 4);
        let mut first = at(&[i64::MIN]);
        tally
            .events(now + Duration::from_millis(5), &mut first, false)
            .unwrap();
        let mut early = at(&[i64::MAX]);
        tally.arrive(now + Duration::from_millis(1), 4);
        tally
            .events(now + Duration::from_millis(1), &mut early, false)
            .unwrap();
        assert_eq!((first[0].t, early[0].t), (5000, 5000));
        assert_eq!((tally.report.out_of_range, tally.report.events), (0, 2));
    }

    /// Writing to a file, a datagram whose times go back (within it or before what was
    /// written) is refused whole and counted, and the file holds the rest, in order.
    #[test]
    fn times_that_go_back_are_refused_when_writing() {
        let dir = std::env::temp_dir().join(format!("v2ce-listen-order-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("got.csv");
        let out = format::create(&path, format::Format::Csv, 8, 8).unwrap();
        let mut tally = Tally::new(Some(out), (8, 8));
        let now = Instant::now();
        for ts in [&[1, 2][..], &[0], &[3, 2], &[2, 4], &[i64::MIN], &[5]] {
            tally.arrive(now, 13 * ts.len());
            tally.events(now, &mut at(ts), true).unwrap();
        }
        let r = tally.finish().unwrap();
        assert_eq!((r.out_of_order, r.out_of_range, r.events), (2, 1, 5));
        let got: Vec<i64> = format::read_events(&path)
            .unwrap()
            .events
            .events()
            .iter()
            .map(|e| e.t)
            .collect();
        assert_eq!(got, [1, 2, 2, 4, 5]);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Over a socket: `t64` datagrams carrying the ends of `i64` and times just past 2^61 us
    /// are refused and reported; the others, decreasing ones included, are taken.
    #[test]
    fn listen_refuses_datagrams_with_times_out_of_range() {
        use crate::time::MAX_ABS_US;
        let format = UdpFormat::T64X16Y16On8;
        let options = ListenOptions {
            listen: Listen::Udp {
                bind: "127.0.0.1:0".into(),
                format,
            },
            out: None,
            size: (8, 8),
            duration: Some(Duration::from_secs(20)),
            idle: Duration::from_millis(500),
            max_events: None,
            recv_buffer: 0,
            priority: 0,
        };
        let (tx, rx) = std::sync::mpsc::channel();
        let listener = std::thread::spawn(move || {
            let stop = AtomicBool::new(false);
            listen(&options, &stop, |a| tx.send(a.to_string()).unwrap())
        });
        let address = rx.recv().unwrap();
        let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
        let datagrams: [&[i64]; 7] = [
            &[10, 20],
            &[i64::MIN],
            &[30, i64::MAX],
            &[MAX_ABS_US + 1],
            &[-MAX_ABS_US - 1, 0],
            &[15, 5],
            &[MAX_ABS_US, -MAX_ABS_US],
        ];
        for ts in datagrams {
            let mut bytes = Vec::new();
            at(ts).iter().for_each(|e| format.encode(e, &mut bytes));
            socket.send_to(&bytes, &address).unwrap();
        }
        let r = listener.join().unwrap().unwrap();
        assert_eq!(
            (r.messages, r.out_of_range, r.out_of_order),
            (7, 4, 0),
            "{r:?}"
        );
        assert_eq!(r.events, 6, "{r:?}");
        assert_eq!((r.first_t, r.last_t), (Some(10), Some(-MAX_ABS_US)));
        assert_eq!(r.arrival_spread.map(|s| s.count), Some(6));
    }

    #[test]
    fn arrival_is_the_kernels_stamp_not_when_the_receiver_woke() {
        let rx = UdpSocket::bind("127.0.0.1:0").unwrap();
        kernel_timestamps(&rx);
        let tx = UdpSocket::bind("127.0.0.1:0").unwrap();
        // The kernel turns receive stamping on for the whole machine a moment after the first
        // socket asks (a deferred switch); until then it stamps at the read. Let it.
        std::thread::sleep(Duration::from_millis(50));
        tx.send_to(b"warm", rx.local_addr().unwrap()).unwrap();
        let mut warm = [0u8; 16];
        recv_stamped(&rx, &mut warm).unwrap();
        let sent = Instant::now();
        tx.send_to(b"four", rx.local_addr().unwrap()).unwrap();
        // The receiver comes late to the datagram.
        std::thread::sleep(Duration::from_millis(80));
        let mut buf = [0u8; 16];
        let (n, at) = recv_stamped(&rx, &mut buf).unwrap();
        let read = Instant::now();
        assert_eq!(&buf[..n], b"four");
        assert!(
            at >= sent - Duration::from_millis(5),
            "stamped before it was sent"
        );
        assert!(
            read - at >= Duration::from_millis(70),
            "arrival {:?} before the read: the kernel's stamp was not used",
            read - at
        );
    }
}
