//! `v2ce listen`: a receiver for what the daemon sends, the tool a user runs to check a setup
//! (and what the tests use): UDP datagrams in any of the word formats, or a TCP stream (DV's
//! AEDAT 4.0 network stream or Prophesee RAW EVT 2.0/3.0). It counts events and datagrams,
//! measures the rate, the largest gap between arrivals and, for formats with timestamps, the
//! spread of arrival time minus event time, and can write what it got to an event file.
//!
//! For plain `spif`, which carries no timestamps, the arrival time is the event time: events
//! written to a file get their arrival time, in microseconds since the first datagram.

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

struct Tally {
    started: Option<Instant>,
    last: Option<Instant>,
    report: ListenReport,
    /// Arrival minus event time, us (timestamped formats).
    offsets: Offsets,
    per_ms: (u64, u64),
    out: Option<Box<dyn EventEncoder + Send>>,
}

impl Tally {
    fn new(out: Option<Box<dyn EventEncoder + Send>>) -> Self {
        Tally {
            started: None,
            last: None,
            report: ListenReport::default(),
            offsets: Offsets::new(),
            per_ms: (0, 0),
            out,
        }
    }

    fn arrive(&mut self, at: Instant, bytes: usize) {
        let first = *self.started.get_or_insert(at);
        if let Some(last) = self.last {
            let gap = (at - last).as_secs_f64() * 1e3;
            self.report.largest_gap_ms = self.report.largest_gap_ms.max(gap);
        }
        self.last = Some(at);
        let ms = (at - first).as_millis() as u64;
        self.per_ms = if ms == self.per_ms.0 {
            (ms, self.per_ms.1 + 1)
        } else {
            (ms, 1)
        };
        self.report.max_messages_per_ms = self.report.max_messages_per_ms.max(self.per_ms.1);
        self.report.messages += 1;
        self.report.bytes += bytes as u64;
    }

    fn events(&mut self, at: Instant, events: &mut [Event], timestamped: bool) -> Result<()> {
        let since = |at: Instant, first: Option<Instant>| {
            first.map_or(0, |f| (at - f).as_micros().min(i64::MAX as u128) as i64)
        };
        let arrival = since(at, self.started);
        for e in events.iter_mut() {
            if timestamped {
                self.offsets.push(arrival.saturating_sub(e.t));
            } else {
                e.t = arrival;
            }
        }
        if let (Some(f), Some(l)) = (events.first(), events.last()) {
            self.report.first_t.get_or_insert(f.t);
            self.report.last_t = Some(l.t);
        }
        self.report.events += events.len() as u64;
        if let Some(out) = self.out.as_mut() {
            out.write(events)?;
        }
        Ok(())
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
            let mut tally = Tally::new(out(options.size)?);
            tally.report.realtime = realtime;
            let timestamped = *format != UdpFormat::Spif;
            let mut buf = vec![0u8; 65_536];
            let mut events = Vec::new();
            while !done(&tally) {
                let (n, at) = match recv_stamped(&socket, &mut buf) {
                    Ok(got) => got,
                    Err(e)
                        if matches!(
                            e.kind(),
                            std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
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
                let mut tally = Tally::new(out(size)?);
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
            let mut tally = Tally::new(out(size)?);
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
    }
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
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) && !(self.give_up)() => {}
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
