//! Event streams over TCP, served to any number of clients, in one of three byte streams:
//!
//! | format | what a client receives |
//! |---|---|
//! | `aedat4` | DV's AEDAT 4.0 network stream: a `u32` size and the `IOHeader` (no compression, one event stream with the sensor size in its XML description), then one message per packet: `i32` stream id 0, `i32` size, and a size-prefixed `EventPacket` flatbuffer of up to [`aedat4::PACKET_EVENTS`] events. `dv_processing.io.NetworkReader` and DV's network input read it. |
//! | `evt2`, `evt3` | Prophesee RAW: the text header, then EVT 2.0 or 3.0 words, exactly the bytes the file sink writes for the same events, so a client that saves the stream has a `.raw` file every RAW reader opens. |
//!
//! Each client has its own writer thread, its own encoder (a client that connects later gets
//! a stream of its own that starts with a header) and a bounded queue of batches. [`TcpSink::send`]
//! never waits: a client whose queue is full skips that batch (counted), and one that has
//! skipped `max_skipped` batches in a row, or whose socket fails or stalls past the write
//! timeout, is disconnected. The other clients are not slowed.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{bounded, Sender, TrySendError};
use flatbuffers::FlatBufferBuilder;

use super::{Sink, SinkContext, SinkStats};
use crate::error::{Error, Result};
use crate::event::Event;
use crate::format::aedat4::{self, flatbuf, Compression};
use crate::format::{self, evt2, evt3, EventEncoder};

/// The byte stream a TCP client receives.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    serde::Deserialize,
    serde::Serialize,
    clap::ValueEnum,
)]
#[serde(rename_all = "snake_case")]
pub enum TcpFormat {
    /// DV's AEDAT 4.0 network stream.
    #[default]
    Aedat4,
    /// Prophesee RAW EVT 2.0 (header, then words).
    Evt2,
    /// Prophesee RAW EVT 3.0 (header, then words).
    Evt3,
}

impl TcpFormat {
    /// The name in configs and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            TcpFormat::Aedat4 => "aedat4",
            TcpFormat::Evt2 => "evt2",
            TcpFormat::Evt3 => "evt3",
        }
    }

    /// What the format is called in logs.
    fn long_name(self) -> &'static str {
        match self {
            TcpFormat::Aedat4 => "AEDAT 4.0 network stream",
            TcpFormat::Evt2 => "Prophesee RAW EVT 2.0",
            TcpFormat::Evt3 => "Prophesee RAW EVT 3.0",
        }
    }

    /// Most events in one queued batch: an AEDAT 4.0 packet's worth; for RAW a whole batch of
    /// [`TcpSink::send`], as the file sink's encoder gets it (EVT 3.0 words depend on where a
    /// batch ends, and the stream must match the file's bytes).
    fn batch_events(self) -> usize {
        match self {
            TcpFormat::Aedat4 => aedat4::PACKET_EVENTS,
            TcpFormat::Evt2 | TcpFormat::Evt3 => usize::MAX,
        }
    }
}

/// A `[[sink]]` table of `type = "tcp"` (the `[run]` keys `tcp` and `tcp_format` are a
/// shorthand for one).
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TcpSinkConfig {
    /// Address to listen on, `HOST:PORT`.
    pub address: String,
    /// The byte stream clients receive: aedat4 (the default), evt2 or evt3.
    #[serde(default)]
    pub format: TcpFormat,
    /// Clients served at once (one writer thread each); more are refused and counted
    /// (default 64).
    #[serde(default = "default_max_clients")]
    pub max_clients: usize,
}

fn default_max_clients() -> usize {
    DEFAULT_MAX_CLIENTS
}

/// No address (an output that is off), an AEDAT 4.0 stream, the default client cap.
impl Default for TcpSinkConfig {
    fn default() -> Self {
        TcpSinkConfig {
            address: String::new(),
            format: TcpFormat::default(),
            max_clients: DEFAULT_MAX_CLIENTS,
        }
    }
}

/// Clients a TCP sink serves at once unless configured.
pub const DEFAULT_MAX_CLIENTS: usize = 64;

/// How long a stopping TCP sink waits for its clients' queues to be written before it cuts the
/// remaining clients off (counted in `clients_abandoned`): within the service's stop timeout
/// whatever the clients do.
pub const FINISH_DEADLINE: Duration = Duration::from_secs(5);

impl TcpSinkConfig {
    /// Checks the address is set.
    pub fn validate(&self) -> Result<()> {
        if self.address.is_empty() {
            return Err(bad("address is empty".into()));
        }
        if !(1..=4096).contains(&self.max_clients) {
            return Err(bad(format!(
                "max_clients = {} (must be 1 to 4096)",
                self.max_clients
            )));
        }
        Ok(())
    }

    /// Starts listening.
    pub fn build(&self, context: &SinkContext) -> Result<Box<dyn Sink>> {
        let c = TcpConfig {
            sink: self.clone(),
            ..TcpConfig::new(&self.address, context.width, context.height)
        };
        Ok(Box::new(TcpSink::new(c)?))
    }
}

/// Settings of a [`TcpSink`]: the output's configuration, the sensor it serves, and how
/// patient it is with clients.
#[derive(Debug, Clone, PartialEq)]
pub struct TcpConfig {
    /// The output as configured (address, format, client cap).
    pub sink: TcpSinkConfig,
    /// Sensor size announced in the header.
    pub size: (u16, u16),
    /// Batches each client may have waiting.
    pub queue_packets: usize,
    /// A client that skips this many batches in a row is disconnected.
    pub max_skipped: u64,
    /// A write to a client that blocks this long disconnects it.
    pub write_timeout: Duration,
    /// How long `finish` waits for clients before cutting them off.
    pub finish_deadline: Duration,
}

impl TcpConfig {
    /// Settings for an AEDAT 4.0 stream on `address` for a `width x height` sensor: 256 queued
    /// batches per client, disconnect after 1024 skipped in a row or a write stalled for 2 s.
    pub fn new(address: &str, width: u16, height: u16) -> Self {
        TcpConfig {
            sink: TcpSinkConfig {
                address: address.to_string(),
                format: TcpFormat::Aedat4,
                max_clients: DEFAULT_MAX_CLIENTS,
            },
            size: (width, height),
            queue_packets: 256,
            max_skipped: 1024,
            write_timeout: Duration::from_secs(2),
            finish_deadline: FINISH_DEADLINE,
        }
    }
}

/// One client's encoder: turns its batches into the bytes of its stream.
enum ClientEncoder {
    Aedat4 {
        header: Arc<Vec<u8>>,
        fbb: FlatBufferBuilder<'static>,
    },
    Evt2(evt2::Encoder<Vec<u8>>),
    Evt3(evt3::Encoder<Vec<u8>>),
}

impl ClientEncoder {
    fn new(format: TcpFormat, (w, h): (u16, u16)) -> Result<Self> {
        Ok(match format {
            TcpFormat::Aedat4 => {
                aedat4::check_size(w, h)?;
                let xml = aedat4::description(w, h, Compression::None, "v2ce");
                ClientEncoder::Aedat4 {
                    header: Arc::new(aedat4::io_header_bytes(Compression::None, -1, &xml)),
                    fbb: FlatBufferBuilder::new(),
                }
            }
            TcpFormat::Evt2 => ClientEncoder::Evt2(evt2::Encoder::new(Vec::new(), w, h)?),
            TcpFormat::Evt3 => ClientEncoder::Evt3(evt3::Encoder::new(Vec::new(), w, h)?),
        })
    }

    /// What a client receives first.
    fn greeting(&self, out: &mut Vec<u8>) {
        if let ClientEncoder::Aedat4 { header, .. } = self {
            out.extend_from_slice(header);
        }
    }

    fn encode(&mut self, events: &[Event], out: &mut Vec<u8>) -> Result<()> {
        match self {
            ClientEncoder::Aedat4 { fbb, .. } => {
                flatbuf::build_event_packet(fbb, events);
                let data = fbb.finished_data();
                out.extend_from_slice(&0i32.to_le_bytes());
                out.extend_from_slice(&(data.len() as i32).to_le_bytes());
                out.extend_from_slice(data);
            }
            ClientEncoder::Evt2(e) => {
                e.write(events)?;
                out.append(e.get_mut());
            }
            ClientEncoder::Evt3(e) => {
                e.write(events)?;
                out.append(e.get_mut());
            }
        }
        Ok(())
    }

    /// What a client receives last (a RAW stream without events still gets its header).
    fn end(&mut self, out: &mut Vec<u8>) -> Result<()> {
        match self {
            ClientEncoder::Aedat4 { .. } => {}
            ClientEncoder::Evt2(e) => {
                e.finish()?;
                out.append(e.get_mut());
            }
            ClientEncoder::Evt3(e) => {
                e.finish()?;
                out.append(e.get_mut());
            }
        }
        Ok(())
    }
}

struct Client {
    tx: Sender<Arc<[Event]>>,
    alive: Arc<AtomicBool>,
    skipped_in_a_row: u64,
    thread: JoinHandle<()>,
    /// The connection, to cut off a client still being written at the stop deadline.
    stream: Option<TcpStream>,
    /// Set once every byte for the client is written and its side shut (see [`serve`]).
    delivered: Arc<AtomicBool>,
}

/// Serves events to TCP clients.
pub struct TcpSink {
    config: TcpConfig,
    local: SocketAddr,
    clients: Arc<Mutex<Vec<Client>>>,
    stop: Arc<AtomicBool>,
    acceptor: Option<JoinHandle<()>>,
    /// Bytes the client threads have written.
    written: Arc<AtomicU64>,
    /// Clients refused (at the cap, or when a writer thread could not start).
    refused: Arc<AtomicU64>,
    stats: SinkStats,
    last_t: i64,
}

fn bad(m: String) -> Error {
    Error::invalid("TCP sink", m)
}

impl TcpSink {
    /// Listens on `config.sink.address`; clients may connect from now on.
    pub fn new(config: TcpConfig) -> Result<Self> {
        // Checks the size against the format.
        ClientEncoder::new(config.sink.format, config.size)?;
        if config.queue_packets == 0 {
            return Err(bad("queue_packets must be at least 1".into()));
        }
        let addr = config
            .sink
            .address
            .to_socket_addrs()
            .map_err(|e| bad(format!("{}: {e}", config.sink.address)))?
            .next()
            .ok_or_else(|| bad(format!("{} resolves to no address", config.sink.address)))?;
        let listener =
            TcpListener::bind(addr).map_err(|e| bad(format!("cannot listen on {addr}: {e}")))?;
        let local = listener.local_addr().map_err(|e| bad(e.to_string()))?;
        listener
            .set_nonblocking(true)
            .map_err(|e| bad(e.to_string()))?;
        let clients = Arc::new(Mutex::new(Vec::new()));
        let stop = Arc::new(AtomicBool::new(false));
        let written = Arc::new(AtomicU64::new(0));
        let refused = Arc::new(AtomicU64::new(0));
        let acceptor = {
            let accept = Acceptor {
                listener,
                format: config.sink.format,
                size: config.size,
                clients: clients.clone(),
                stop: stop.clone(),
                written: written.clone(),
                refused: refused.clone(),
                queue: config.queue_packets,
                timeout: config.write_timeout,
                max_clients: config.sink.max_clients,
            };
            std::thread::Builder::new()
                .name("v2ce-tcp-accept".into())
                .spawn(move || accept.run())
                .map_err(|e| bad(e.to_string()))?
        };
        Ok(TcpSink {
            config,
            local,
            clients,
            stop,
            acceptor: Some(acceptor),
            written,
            refused,
            stats: SinkStats::default(),
            last_t: i64::MIN,
        })
    }

    /// The address clients connect to.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// Clients connected now.
    pub fn client_count(&self) -> usize {
        self.clients.lock().map_or(0, |c| c.len())
    }
}

/// The listening side: accepts clients and starts a writer thread for each.
struct Acceptor {
    listener: TcpListener,
    format: TcpFormat,
    size: (u16, u16),
    clients: Arc<Mutex<Vec<Client>>>,
    stop: Arc<AtomicBool>,
    written: Arc<AtomicU64>,
    refused: Arc<AtomicU64>,
    queue: usize,
    timeout: Duration,
    max_clients: usize,
}

impl Acceptor {
    /// Accepts until stopped. A client over the cap, or whose writer thread cannot start (a
    /// task limit), is closed, logged and counted; the port stays open for the next.
    fn run(self) {
        while !self.stop.load(Ordering::Relaxed) {
            match self.listener.accept() {
                Ok((stream, peer)) => {
                    let serving = self.clients.lock().map_or(usize::MAX, |l| {
                        l.iter().filter(|c| !c.thread.is_finished()).count()
                    });
                    if serving >= self.max_clients {
                        self.refused.fetch_add(1, Ordering::Relaxed);
                        tracing::warn!(
                            "TCP client {peer} refused: {serving} clients already (max_clients)"
                        );
                        continue;
                    }
                    let Ok(encoder) = ClientEncoder::new(self.format, self.size) else {
                        return;
                    };
                    let cut_off = stream.try_clone().ok();
                    let (tx, rx) = bounded::<Arc<[Event]>>(self.queue);
                    let alive = Arc::new(AtomicBool::new(true));
                    let flag = alive.clone();
                    let (timeout, written) = (self.timeout, self.written.clone());
                    let delivered = Arc::new(AtomicBool::new(false));
                    let done = delivered.clone();
                    let thread = std::thread::Builder::new()
                        .name(format!("v2ce-tcp-{peer}"))
                        .spawn(move || {
                            let _ = serve(stream, encoder, rx, timeout, &written, &done);
                            flag.store(false, Ordering::Relaxed);
                        });
                    match thread {
                        Ok(thread) => match self.clients.lock() {
                            Ok(mut list) => list.push(Client {
                                tx,
                                alive,
                                skipped_in_a_row: 0,
                                thread,
                                stream: cut_off,
                                delivered,
                            }),
                            Err(_) => return,
                        },
                        Err(e) => {
                            self.refused.fetch_add(1, Ordering::Relaxed);
                            tracing::warn!(
                                "TCP client {peer} refused: no writer thread ({e}); still \
                                 accepting"
                            );
                        }
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    std::thread::sleep(Duration::from_millis(5))
                }
                Err(_) => std::thread::sleep(Duration::from_millis(50)),
            }
        }
    }
}

/// How long a client's connection stays open, once everything is written and our side is
/// shut, for the client to close its own (see [`serve`]).
const LINGER: Duration = Duration::from_secs(1);

/// Writes the greeting, every batch and the end to one client; then waits, for at most
/// [`LINGER`], for the client to close its side, shuts ours, and for at most [`LINGER`] more
/// reads (and discards) until the client closes. That last step is a lingering close: a socket closed while the client's bytes wait unread in it resets the
/// connection, and a client that gets the reset discards what it had not read yet, our last
/// message among them (seen as dv-processing's reader missing the last packet on a loaded
/// machine).
fn serve(
    mut stream: TcpStream,
    mut encoder: ClientEncoder,
    rx: crossbeam_channel::Receiver<Arc<[Event]>>,
    timeout: Duration,
    written: &AtomicU64,
    delivered: &AtomicBool,
) -> Result<()> {
    let io = |e: std::io::Error| bad(format!("client: {e}"));
    stream.set_nonblocking(false).map_err(io)?;
    stream.set_nodelay(true).map_err(io)?;
    stream.set_write_timeout(Some(timeout)).map_err(io)?;
    let mut buf = Vec::new();
    // The greeting goes at once: a client may wait for the header before it says it is ready.
    encoder.greeting(&mut buf);
    stream.write_all(&buf).map_err(io)?;
    written.fetch_add(buf.len() as u64, Ordering::Relaxed);
    buf.clear();
    for batch in rx {
        encoder.encode(&batch, &mut buf)?;
        stream.write_all(&buf).map_err(io)?;
        written.fetch_add(buf.len() as u64, Ordering::Relaxed);
        buf.clear();
    }
    encoder.end(&mut buf)?;
    stream.write_all(&buf).map_err(io)?;
    written.fetch_add(buf.len() as u64, Ordering::Relaxed);
    stream.flush().map_err(io)?;
    delivered.store(true, Ordering::Relaxed);
    // A client that stops once it has everything closes first, and gets our last message
    // before any end of stream: dv-processing's reader drops a last message that reaches it
    // together with the end (seen on a loaded machine). One that reads to the end gets it
    // after at most `LINGER`.
    if !closed_within(&mut stream, LINGER) {
        stream.shutdown(std::net::Shutdown::Write).map_err(io)?;
        closed_within(&mut stream, LINGER);
    }
    Ok(())
}

/// Reads (and discards) what the client sends until it closes its side, for at most `wait`:
/// whether it closed (or failed).
fn closed_within(stream: &mut TcpStream, wait: Duration) -> bool {
    let until = Instant::now() + wait;
    let mut scratch = [0u8; 4096];
    while let Some(left) = until.checked_duration_since(Instant::now()) {
        if left.is_zero() || stream.set_read_timeout(Some(left)).is_err() {
            return false;
        }
        match stream.read(&mut scratch) {
            Ok(0) => return true,
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => {
                return !matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                )
            }
        }
    }
    false
}

impl Sink for TcpSink {
    fn describe(&self) -> String {
        format!(
            "tcp {} ({})",
            self.local,
            self.config.sink.format.long_name()
        )
    }

    fn send(&mut self, events: &[Event]) -> Result<()> {
        self.stats.events_in += events.len() as u64;
        let (w, h) = self.config.size;
        for e in events {
            format::check_event(e, self.last_t, w, h)?;
            self.last_t = e.t;
        }
        for chunk in events.chunks(self.config.sink.format.batch_events()) {
            let batch: Arc<[Event]> = Arc::from(chunk);
            let mut delivered = false;
            let max_skipped = self.config.max_skipped;
            let mut list = self
                .clients
                .lock()
                .map_err(|_| bad("client list poisoned".into()))?;
            let mut i = 0;
            while i < list.len() {
                let c = &mut list[i];
                let mut drop_client = !c.alive.load(Ordering::Relaxed);
                if !drop_client {
                    match c.tx.try_send(batch.clone()) {
                        Ok(()) => {
                            delivered = true;
                            c.skipped_in_a_row = 0;
                            self.stats.messages_sent += 1;
                        }
                        Err(TrySendError::Full(_)) => {
                            c.skipped_in_a_row += 1;
                            self.stats.messages_dropped += 1;
                            drop_client = c.skipped_in_a_row >= max_skipped;
                        }
                        Err(TrySendError::Disconnected(_)) => drop_client = true,
                    }
                }
                if drop_client {
                    // Dropping the sender ends the writer thread once its queue is written
                    // or its socket fails; it is not joined here, so nothing waits on it.
                    list.swap_remove(i);
                    self.stats.clients_dropped += 1;
                } else {
                    i += 1;
                }
            }
            self.stats.clients = list.len() as u64;
            if delivered {
                self.stats.events_sent += chunk.len() as u64;
            } else {
                self.stats.events_dropped += chunk.len() as u64;
            }
        }
        Ok(())
    }

    /// Stops accepting, then waits for every client's queue to be written (each write is
    /// bounded by the write timeout).
    fn finish(&mut self) -> Result<()> {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(a) = self.acceptor.take() {
            let _ = a.join();
        }
        let clients = match self.clients.lock() {
            Ok(mut list) => std::mem::take(&mut *list),
            Err(_) => Vec::new(),
        };
        // Every queue is closed at once, then written within one deadline for all.
        let clients: Vec<(JoinHandle<()>, Option<TcpStream>, Arc<AtomicBool>)> = clients
            .into_iter()
            .map(|c| {
                drop(c.tx);
                (c.thread, c.stream, c.delivered)
            })
            .collect();
        let deadline = Instant::now() + self.config.finish_deadline;
        while Instant::now() < deadline && clients.iter().any(|(t, _, _)| !t.is_finished()) {
            std::thread::sleep(Duration::from_millis(10));
        }
        // Clients with everything written get their lingering close (see `serve`) before the
        // process may end: a process that exits while a client's bytes wait unread in its
        // socket resets the connection, and the client loses what it had not read yet.
        let linger = Instant::now() + 2 * LINGER;
        while Instant::now() < linger
            && clients
                .iter()
                .any(|(t, _, d)| d.load(Ordering::Relaxed) && !t.is_finished())
        {
            std::thread::sleep(Duration::from_millis(10));
        }
        for (thread, stream, delivered) in clients {
            if thread.is_finished() {
                let _ = thread.join();
                continue;
            }
            if delivered.load(Ordering::Relaxed) {
                // Everything written; the client has not closed its side yet: not cut off
                // (that could reset what it has still to read), its thread ends on its own.
                continue;
            }
            // Still writing at the deadline (a client reading slowly): cut it off. Its
            // writer's next write fails and the thread ends; it is not waited for.
            self.stats.clients_abandoned += 1;
            if let Some(s) = stream {
                let _ = s.shutdown(std::net::Shutdown::Both);
            }
        }
        if self.stats.clients_abandoned > 0 {
            tracing::warn!(
                "{}: {} client(s) still being written after {:?}, cut off",
                self.describe(),
                self.stats.clients_abandoned,
                self.config.finish_deadline
            );
        }
        self.stats.clients = 0;
        Ok(())
    }

    fn stats(&self) -> SinkStats {
        let mut s = self.stats;
        s.clients = self.client_count() as u64;
        s.bytes_sent = self.written.load(Ordering::Relaxed);
        s.clients_refused = self.refused.load(Ordering::Relaxed);
        s
    }
}

impl Drop for TcpSink {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::aedat4::{Item, Reader};

    fn read_all(stream: TcpStream, want: usize) -> Vec<Event> {
        read_counting(stream, want, &std::sync::atomic::AtomicUsize::new(0))
    }

    /// Reads until `want` events, publishing the count so far in `progress`.
    fn read_counting(
        stream: TcpStream,
        want: usize,
        progress: &std::sync::atomic::AtomicUsize,
    ) -> Vec<Event> {
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        let mut r = Reader::new_stream(std::io::BufReader::new(stream)).unwrap();
        assert_eq!(r.event_stream().unwrap().size, Some((64, 48)));
        let mut got = Vec::new();
        while got.len() < want {
            match r.next_item().unwrap() {
                Some(Item::Events(e)) => got.extend(e),
                Some(_) => {}
                None => break,
            }
            progress.store(got.len(), Ordering::Relaxed);
        }
        got
    }

    fn wait_for_clients(sink: &TcpSink, n: usize) {
        for _ in 0..1000 {
            if sink.client_count() == n {
                return;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        panic!("{} clients, expected {n}", sink.client_count());
    }

    /// A client that sent bytes we never read still gets everything up to the end, also when
    /// it reads only after we finished: the connection is shut and closed without a reset (a
    /// close with unread input resets it, and the reset makes the client's kernel discard what
    /// it had not read yet).
    #[test]
    fn a_client_that_talked_still_reads_the_last_message_after_the_end() {
        use std::io::Read as _;
        let mut sink = TcpSink::new(TcpConfig::new("127.0.0.1:0", 64, 48)).unwrap();
        let mut client = TcpStream::connect(sink.local_addr()).unwrap();
        client.write_all(&[7u8; 4096]).unwrap();
        wait_for_clients(&sink, 1);
        let events: Vec<Event> = (0..50_000)
            .map(|i| Event::new(i * 3, (i % 64) as u16, (i % 48) as u16, i % 2 == 0))
            .collect();
        for chunk in events.chunks(5_000) {
            sink.send(chunk).unwrap();
        }
        // The client reads only after the sink has finished and its thread let go.
        let reader = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(300));
            client
                .set_read_timeout(Some(Duration::from_secs(10)))
                .unwrap();
            let mut bytes = Vec::new();
            let read = client.read_to_end(&mut bytes);
            (read.map(|_| ()), bytes)
        });
        sink.finish().unwrap();
        let (read, bytes) = reader.join().unwrap();
        read.expect("the connection ended by a reset, not a close");
        let mut r = Reader::new_stream(std::io::Cursor::new(bytes)).unwrap();
        let mut got = Vec::new();
        while let Some(item) = r.next_item().unwrap() {
            if let Item::Events(e) = item {
                got.extend(e);
            }
        }
        assert_eq!(got, events);
    }

    #[test]
    fn several_clients_get_every_event() {
        let mut sink = TcpSink::new(TcpConfig::new("127.0.0.1:0", 64, 48)).unwrap();
        let addr = sink.local_addr();
        let events: Vec<Event> = (0..20_000)
            .map(|i| Event::new(i * 3, (i % 64) as u16, (i % 48) as u16, i % 2 == 0))
            .collect();
        let readers: Vec<_> = (0..3)
            .map(|_| {
                let s = TcpStream::connect(addr).unwrap();
                std::thread::spawn(move || read_all(s, 20_000))
            })
            .collect();
        wait_for_clients(&sink, 3);
        for chunk in events.chunks(777) {
            sink.send(chunk).unwrap();
        }
        sink.finish().unwrap();
        for r in readers {
            assert_eq!(r.join().unwrap(), events);
        }
        let s = sink.stats();
        assert_eq!(
            (s.events_sent, s.events_dropped, s.messages_dropped),
            (20_000, 0, 0)
        );
    }

    #[test]
    fn clients_over_the_cap_are_refused_and_counted_and_the_port_stays_open() {
        let mut config = TcpConfig::new("127.0.0.1:0", 64, 48);
        config.sink.max_clients = 1;
        let mut sink = TcpSink::new(config).unwrap();
        let addr = sink.local_addr();
        let first = TcpStream::connect(addr).unwrap();
        wait_for_clients(&sink, 1);
        // The second is closed at once: it reads end of stream, not a header.
        let mut second = TcpStream::connect(addr).unwrap();
        second
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        let mut buf = [0u8; 16];
        use std::io::Read;
        assert_eq!(second.read(&mut buf).unwrap_or(0), 0);
        assert_eq!(sink.stats().clients_refused, 1);
        // Once the first leaves, the next is served.
        drop(first);
        let events = vec![Event::new(1, 1, 1, true)];
        for _ in 0..1000 {
            sink.send(&events).unwrap();
            if sink.client_count() == 0 {
                break;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let third = TcpStream::connect(addr).unwrap();
        wait_for_clients(&sink, 1);
        drop(third);
        sink.finish().unwrap();
    }

    #[test]
    fn a_stop_cuts_off_a_client_that_reads_too_slowly_at_the_deadline() {
        let mut config = TcpConfig::new("127.0.0.1:0", 64, 48);
        // Writes never time out here: only the stop deadline ends the client.
        config.write_timeout = Duration::from_secs(3600);
        config.finish_deadline = Duration::from_millis(300);
        config.queue_packets = 1024;
        let mut sink = TcpSink::new(config).unwrap();
        // A client that connects and never reads: its queue cannot drain.
        let _stalled = TcpStream::connect(sink.local_addr()).unwrap();
        wait_for_clients(&sink, 1);
        let n = 200 * aedat4::PACKET_EVENTS;
        let events: Vec<Event> = (0..n as i64)
            .map(|i| Event::new(i, (i % 64) as u16, (i % 48) as u16, true))
            .collect();
        for chunk in events.chunks(aedat4::PACKET_EVENTS) {
            sink.send(chunk).unwrap();
        }
        sink.finish().unwrap();
        assert_eq!(sink.stats().clients_abandoned, 1, "{:?}", sink.stats());
    }

    #[test]
    fn a_stalled_client_is_skipped_then_dropped_without_slowing_the_others() {
        let mut config = TcpConfig::new("127.0.0.1:0", 64, 48);
        config.queue_packets = 4;
        config.max_skipped = 50;
        config.write_timeout = Duration::from_millis(300);
        let mut sink = TcpSink::new(config).unwrap();
        let addr = sink.local_addr();
        // A client that connects and never reads.
        let stalled = TcpStream::connect(addr).unwrap();
        let n = 400 * aedat4::PACKET_EVENTS;
        let progress = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let fast = {
            let s = TcpStream::connect(addr).unwrap();
            let progress = progress.clone();
            std::thread::spawn(move || read_counting(s, n, &progress))
        };
        wait_for_clients(&sink, 2);
        let events: Vec<Event> = (0..n as i64)
            .map(|i| Event::new(i, (i % 64) as u16, (i % 48) as u16, true))
            .collect();
        for (i, chunk) in events.chunks(aedat4::PACKET_EVENTS).enumerate() {
            sink.send(chunk).unwrap();
            // A live stream's pace: the reading client keeps up (it has read each packet
            // before the next is sent, however loaded the machine), the stalled one never reads.
            let sent = (i + 1) * aedat4::PACKET_EVENTS;
            for _ in 0..20_000 {
                if progress.load(Ordering::Relaxed) >= sent {
                    break;
                }
                std::thread::sleep(Duration::from_micros(500));
            }
        }
        let s = sink.stats();
        sink.finish().unwrap();
        let got = fast.join().unwrap();
        assert_eq!(got.len(), n, "the reading client lost events");
        assert_eq!(got, events);
        assert!(s.messages_dropped >= 50, "{s:?}");
        assert_eq!(s.clients, 1, "the stalled client was not dropped: {s:?}");
        assert_eq!(s.clients_dropped, 1, "{s:?}");
        drop(stalled);
    }

    /// Reads a whole stream until the server closes it.
    fn read_to_end(stream: TcpStream) -> Vec<u8> {
        use std::io::Read;
        let mut stream = stream;
        stream
            .set_read_timeout(Some(Duration::from_secs(20)))
            .unwrap();
        let mut bytes = Vec::new();
        stream.read_to_end(&mut bytes).unwrap();
        bytes
    }

    #[test]
    fn raw_streams_are_the_file_sinks_bytes_and_a_late_client_gets_a_stream_of_its_own() {
        use crate::format::Format;
        use crate::sink::file::FileSink;
        let events: Vec<Event> = (0..30_000i64)
            .map(|i| {
                // Runs of neighbours on a row (EVT 3.0 vectors) and a gap past EVT 2.0's
                // time-high period.
                let t = 5_000_000 + i * 37 + if i > 20_000 { 3_000_000 } else { 0 };
                Event::new(
                    t - t % 5,
                    ((i * 7) % 64) as u16,
                    ((i / 9) % 48) as u16,
                    i % 3 != 0,
                )
            })
            .collect();
        let dir = std::env::temp_dir().join(format!("v2ce-tcp-raw-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for (format, file_format) in [
            (TcpFormat::Evt2, Format::Evt2),
            (TcpFormat::Evt3, Format::Evt3),
        ] {
            let mut config = TcpConfig::new("127.0.0.1:0", 64, 48);
            config.sink.format = format;
            let mut sink = TcpSink::new(config).unwrap();
            let path = dir.join(format!("{}.raw", format.name()));
            let mut file = FileSink::create(&path, file_format, 64, 48).unwrap();
            let first = TcpStream::connect(sink.local_addr()).unwrap();
            let first = std::thread::spawn(move || read_to_end(first));
            wait_for_clients(&sink, 1);
            let batches: Vec<&[Event]> = events.chunks(1_777).collect();
            let (early, late) = batches.split_at(10);
            for b in early {
                sink.send(b).unwrap();
                file.send(b).unwrap();
            }
            let second = TcpStream::connect(sink.local_addr()).unwrap();
            let second = std::thread::spawn(move || read_to_end(second));
            wait_for_clients(&sink, 2);
            for b in late {
                sink.send(b).unwrap();
                file.send(b).unwrap();
            }
            sink.finish().unwrap();
            file.finish().unwrap();
            let whole = first.join().unwrap();
            assert_eq!(whole, std::fs::read(&path).unwrap(), "{}", format.name());
            let s = sink.stats();
            assert_eq!((s.events_sent, s.events_dropped), (30_000, 0));
            // The late client's stream is a RAW file of its own: a header, then the events
            // from when it joined.
            let tail = second.join().unwrap();
            assert!(tail.starts_with(b"% evt "), "{}", format.name());
            let late_path = dir.join(format!("{}-late.raw", format.name()));
            std::fs::write(&late_path, &tail).unwrap();
            let back = crate::format::read_events(&late_path).unwrap();
            let since = early.iter().map(|b| b.len()).sum::<usize>();
            assert_eq!(back.events.events(), &events[since..], "{}", format.name());
            assert_eq!((back.width, back.height), (64, 48));
            assert_eq!(s.bytes_sent, (whole.len() + tail.len()) as u64);
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_aedat4_client_gets_its_header_before_any_event() {
        let mut sink = TcpSink::new(TcpConfig::new("127.0.0.1:0", 64, 48)).unwrap();
        let stream = TcpStream::connect(sink.local_addr()).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        wait_for_clients(&sink, 1);
        // Nothing sent yet: the header must already be there (clients wait for it).
        let r = Reader::new_stream(std::io::BufReader::new(stream)).unwrap();
        assert_eq!(r.event_stream().unwrap().size, Some((64, 48)));
        sink.finish().unwrap();
    }

    #[test]
    fn a_raw_client_without_events_still_gets_a_header() {
        let mut config = TcpConfig::new("127.0.0.1:0", 64, 48);
        config.sink.format = TcpFormat::Evt2;
        let mut sink = TcpSink::new(config).unwrap();
        let c = TcpStream::connect(sink.local_addr()).unwrap();
        let c = std::thread::spawn(move || read_to_end(c));
        wait_for_clients(&sink, 1);
        sink.finish().unwrap();
        let bytes = c.join().unwrap();
        assert!(
            bytes.starts_with(b"% evt 2.0\n"),
            "{:?}",
            String::from_utf8_lossy(&bytes)
        );
        assert!(bytes.ends_with(b"% end\n"));
    }

    #[test]
    fn a_size_the_format_cannot_hold_is_refused() {
        let mut config = TcpConfig::new("127.0.0.1:0", 4096, 48);
        config.sink.format = TcpFormat::Evt3;
        assert!(TcpSink::new(config).is_err());
    }
}
