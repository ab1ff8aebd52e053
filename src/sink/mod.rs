//! Where events go: one [`Sink`] trait, implemented by a file ([`file`](mod@file)), UDP datagrams
//! ([`udp`]) and byte streams over TCP ([`tcp`]: DV's AEDAT 4.0 network stream or Prophesee
//! RAW), and ROS 2 topics ([`ros2`]: `event_camera_msgs/msg/EventPacket` over DDS). `convert` and the daemon hand each sink time-ordered batches of events.
//!
//! Each kind of sink has a typed configuration (one `[[sink]]` table of the TOML file, see
//! [`SinkConfig`]) that builds it, so the daemon opens its outputs as a map over a list of
//! configurations; adding a sink is one module plus one variant.
//!
//! A network sink never blocks its caller on a receiver: what cannot be sent at once is dropped
//! and counted in [`SinkStats`].

mod datagrams;
pub mod emit;
pub mod file;
pub mod preview;
pub mod ros2;
pub mod tcp;
pub mod udp;

use std::time::Instant;

use crate::error::Result;
use crate::event::Event;

/// One output as configured: a `[[sink]]` table with its `type` (the `[run]` keys `udp`, `tcp`
/// and `out` are shorthands for one sink each).
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum SinkConfig {
    /// UDP datagrams to a receiver.
    Udp(udp::UdpSinkConfig),
    /// A byte stream served to TCP clients.
    Tcp(tcp::TcpSinkConfig),
    /// An event file.
    File(file::FileSinkConfig),
    /// ROS 2 EventPacket messages on a DDS topic.
    Ros2(ros2::Ros2SinkConfig),
}

/// What every sink is built for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SinkContext {
    /// Sensor width.
    pub width: u16,
    /// Sensor height.
    pub height: u16,
    /// How many times faster than the wall clock the frames' times run (a file's replay speed;
    /// 1 for a camera).
    pub speed: f64,
}

impl SinkConfig {
    /// Checks the values that TOML types cannot.
    pub fn validate(&self) -> Result<()> {
        match self {
            SinkConfig::Udp(c) => c.validate(),
            SinkConfig::Tcp(c) => c.validate(),
            SinkConfig::File(c) => c.validate(),
            SinkConfig::Ros2(c) => c.validate(),
        }
    }

    /// Opens the sink.
    pub fn build(&self, context: &SinkContext) -> Result<Box<dyn Sink>> {
        self.validate()?;
        match self {
            SinkConfig::Udp(c) => c.build(context),
            SinkConfig::Tcp(c) => c.build(context),
            SinkConfig::File(c) => c.build(context),
            SinkConfig::Ros2(c) => c.build(context),
        }
    }

    /// Whether clients connect to it (a TCP server), which `wait_for_client` waits for.
    pub fn serves_clients(&self) -> bool {
        matches!(self, SinkConfig::Tcp(_))
    }
}

/// Counters a sink keeps.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct SinkStats {
    /// Events handed to the sink.
    pub events_in: u64,
    /// Events written or sent (for TCP: to at least one client; for a file: once a flush or
    /// the end has put them in the file, not while they wait in its buffer).
    pub events_sent: u64,
    /// Events this output lost: dropped by the output itself (a datagram that could not be
    /// sent, a packet no client could take) or evicted from its queue (`events_evicted`).
    pub events_dropped: u64,
    /// Of `events_dropped`, those evicted from the output's queue before it could take them
    /// (drop-oldest, an output slower than the pipeline; never a recording's).
    pub events_evicted: u64,
    /// Events in datagrams the kernel refused because the receiver's port was closed (UDP: an
    /// ICMP port-unreachable came back for an earlier datagram); `events_sent` counts what was
    /// handed to the kernel, which UDP cannot follow further.
    pub events_refused: u64,
    /// Datagrams or packets sent (TCP: per client).
    pub messages_sent: u64,
    /// Datagrams or packets dropped (TCP: per client).
    pub messages_dropped: u64,
    /// Bytes written or sent.
    pub bytes_sent: u64,
    /// Clients connected now (TCP only).
    pub clients: u64,
    /// Clients disconnected for being too slow or gone (TCP only).
    pub clients_dropped: u64,
    /// Clients refused: over `max_clients`, or no writer thread could start (TCP only).
    pub clients_refused: u64,
    /// Clients still being written at the stop deadline, cut off (TCP only).
    pub clients_abandoned: u64,
    /// Events sent later than their due time (emission at event time only; see [`emit`]).
    pub events_late: u64,
    /// Times the emission clock started over after a stall (emission at event time only).
    pub reanchors: u64,
}

/// The frame that closed a batch of events: its time and the instant it was captured, which
/// anchor a sink that emits events at their own times.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClosedBy {
    /// The frame's time, us.
    pub t: i64,
    /// When it was captured.
    pub captured: Instant,
}

/// A destination for events.
pub trait Sink: Send {
    /// A short description for logs, e.g. `udp 127.0.0.1:3333 (spif)`.
    fn describe(&self) -> String;

    /// Takes a batch of events in time order (and after the previous batch).
    fn send(&mut self, events: &[Event]) -> Result<()>;

    /// [`Sink::send`] for a batch whose interval was closed by `closed_by` (the pipeline's
    /// call): a sink that emits events at their own times anchors its clock on it.
    fn send_closed(&mut self, events: &[Event], closed_by: ClosedBy) -> Result<()> {
        let _ = closed_by;
        self.send(events)
    }

    /// How long the sink holds events back before they leave (emission at event time: its
    /// delay); the pipeline gives its queue room for that many batches on top.
    fn holds_back(&self) -> std::time::Duration {
        std::time::Duration::ZERO
    }

    /// Flushes and closes; the sink takes no more events.
    fn finish(&mut self) -> Result<()>;

    /// The counters so far.
    fn stats(&self) -> SinkStats;

    /// Whether it is a recording that must hold every event it is given (a file): its queue
    /// then blocks, whatever the queue policy, so it never evicts; a live run that cannot
    /// keep up drops whole frames before Stage 1 instead (counted, and named on its closing
    /// line). Network outputs keep the policy: a late event is worth less than a live stream.
    fn is_recording(&self) -> bool {
        false
    }

    /// Whether its deliveries count in the pipeline's latency figures (`false` for the preview
    /// tap, which only copies events for the HTTP page and would pull the median down).
    fn counts_latency(&self) -> bool {
        true
    }

    /// The flag the run raises when it stops early (a signal, `duration`): a sink that waits
    /// (a pacing limit) stops waiting then, dropping and counting what it has not sent, so the
    /// run ends within its stop budget. Sinks that never wait ignore it.
    fn stop_waiting_on(&mut self, _flag: std::sync::Arc<std::sync::atomic::AtomicBool>) {}
}
