//! Where events go: one [`Sink`] trait, implemented by a file ([`file`]), UDP datagrams
//! ([`udp`]) and DV's AEDAT 4.0 network stream over TCP ([`tcp`]). `convert` and the daemon
//! hand each sink time-ordered batches of events.
//!
//! A network sink never blocks its caller on a receiver: what cannot be sent at once is dropped
//! and counted in [`SinkStats`].

pub mod file;
pub mod tcp;
pub mod udp;

use crate::error::Result;
use crate::event::Event;

/// Counters a sink keeps.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct SinkStats {
    /// Events handed to the sink.
    pub events_in: u64,
    /// Events written or sent (for TCP: to at least one client).
    pub events_sent: u64,
    /// Events dropped (a datagram that could not be sent, a packet no client could take).
    pub events_dropped: u64,
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
}

/// A destination for events.
pub trait Sink: Send {
    /// A short description for logs, e.g. `udp 127.0.0.1:3333 (spif)`.
    fn describe(&self) -> String;

    /// Takes a batch of events in time order (and after the previous batch).
    fn send(&mut self, events: &[Event]) -> Result<()>;

    /// Flushes and closes; the sink takes no more events.
    fn finish(&mut self) -> Result<()>;

    /// The counters so far.
    fn stats(&self) -> SinkStats;
}
