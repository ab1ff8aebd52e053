//! DV's AEDAT 4.0 network stream over TCP, served to any number of clients.
//!
//! On connect a client receives a `u32` size and the `IOHeader` (no compression, one event
//! stream with the sensor size in its XML description), then one message per packet: `i32`
//! stream id 0, `i32` size, and a size-prefixed `EventPacket` flatbuffer of up to
//! [`aedat4::PACKET_EVENTS`] events. This is what `dv_processing.io.NetworkReader` and DV's
//! network input read.
//!
//! Each client has its own writer thread and a bounded queue of packets. [`TcpSink::send`] never
//! waits: a client whose queue is full skips that packet (counted), and one that has skipped
//! `max_skipped` packets in a row, or whose socket fails or stalls past the write timeout, is
//! disconnected. The other clients are not slowed.

use std::io::Write;
use std::net::{SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use crossbeam_channel::{bounded, Sender, TrySendError};
use flatbuffers::FlatBufferBuilder;

use super::{Sink, SinkStats};
use crate::error::{Error, Result};
use crate::event::Event;
use crate::format;
use crate::format::aedat4::{self, flatbuf, Compression};

/// Settings of a [`TcpSink`].
#[derive(Debug, Clone, PartialEq)]
pub struct TcpConfig {
    /// Address to listen on, `host:port` (port 0 picks a free one).
    pub address: String,
    /// Sensor size announced in the header.
    pub size: (u16, u16),
    /// Packets each client may have waiting.
    pub queue_packets: usize,
    /// A client that skips this many packets in a row is disconnected.
    pub max_skipped: u64,
    /// A write to a client that blocks this long disconnects it.
    pub write_timeout: Duration,
}

impl TcpConfig {
    /// Settings for `address` and a `width x height` sensor: 256 queued packets per client,
    /// disconnect after 1024 skipped in a row or a write stalled for 2 s.
    pub fn new(address: &str, width: u16, height: u16) -> Self {
        TcpConfig {
            address: address.to_string(),
            size: (width, height),
            queue_packets: 256,
            max_skipped: 1024,
            write_timeout: Duration::from_secs(2),
        }
    }
}

struct Client {
    tx: Sender<Arc<Vec<u8>>>,
    alive: Arc<AtomicBool>,
    skipped_in_a_row: u64,
    thread: JoinHandle<()>,
}

/// Serves events to TCP clients.
pub struct TcpSink {
    config: TcpConfig,
    local: SocketAddr,
    clients: Arc<Mutex<Vec<Client>>>,
    stop: Arc<AtomicBool>,
    acceptor: Option<JoinHandle<()>>,
    fbb: FlatBufferBuilder<'static>,
    stats: SinkStats,
    last_t: i64,
}

fn bad(m: String) -> Error {
    Error::invalid("TCP sink", m)
}

impl TcpSink {
    /// Listens on `config.address`; clients may connect from now on.
    pub fn new(config: TcpConfig) -> Result<Self> {
        aedat4::check_size(config.size.0, config.size.1)?;
        if config.queue_packets == 0 {
            return Err(bad("queue_packets must be at least 1".into()));
        }
        let addr = config
            .address
            .to_socket_addrs()
            .map_err(|e| bad(format!("{}: {e}", config.address)))?
            .next()
            .ok_or_else(|| bad(format!("{} resolves to no address", config.address)))?;
        let listener =
            TcpListener::bind(addr).map_err(|e| bad(format!("cannot listen on {addr}: {e}")))?;
        let local = listener.local_addr().map_err(|e| bad(e.to_string()))?;
        listener
            .set_nonblocking(true)
            .map_err(|e| bad(e.to_string()))?;
        let xml = aedat4::description(config.size.0, config.size.1, Compression::None, "v2ce");
        let header = Arc::new(aedat4::io_header_bytes(Compression::None, -1, &xml));
        let clients = Arc::new(Mutex::new(Vec::new()));
        let stop = Arc::new(AtomicBool::new(false));
        let acceptor = {
            let (clients, stop) = (clients.clone(), stop.clone());
            let (queue, timeout) = (config.queue_packets, config.write_timeout);
            std::thread::Builder::new()
                .name("v2ce-tcp-accept".into())
                .spawn(move || accept_loop(listener, header, clients, stop, queue, timeout))
                .map_err(|e| bad(e.to_string()))?
        };
        Ok(TcpSink {
            config,
            local,
            clients,
            stop,
            acceptor: Some(acceptor),
            fbb: FlatBufferBuilder::new(),
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

    fn packet(&mut self, events: &[Event]) -> Arc<Vec<u8>> {
        flatbuf::build_event_packet(&mut self.fbb, events);
        let data = self.fbb.finished_data();
        let mut msg = Vec::with_capacity(data.len() + 8);
        msg.extend_from_slice(&0i32.to_le_bytes());
        msg.extend_from_slice(&(data.len() as i32).to_le_bytes());
        msg.extend_from_slice(data);
        Arc::new(msg)
    }
}

fn accept_loop(
    listener: TcpListener,
    header: Arc<Vec<u8>>,
    clients: Arc<Mutex<Vec<Client>>>,
    stop: Arc<AtomicBool>,
    queue: usize,
    timeout: Duration,
) {
    while !stop.load(Ordering::Relaxed) {
        match listener.accept() {
            Ok((stream, peer)) => {
                let (tx, rx) = bounded::<Arc<Vec<u8>>>(queue);
                let alive = Arc::new(AtomicBool::new(true));
                let header = header.clone();
                let flag = alive.clone();
                let thread = std::thread::Builder::new()
                    .name(format!("v2ce-tcp-{peer}"))
                    .spawn(move || {
                        let _ = serve(stream, &header, rx, timeout);
                        flag.store(false, Ordering::Relaxed);
                    });
                match (thread, clients.lock()) {
                    (Ok(thread), Ok(mut list)) => list.push(Client {
                        tx,
                        alive,
                        skipped_in_a_row: 0,
                        thread,
                    }),
                    _ => return,
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(5))
            }
            Err(_) => std::thread::sleep(Duration::from_millis(50)),
        }
    }
}

fn serve(
    mut stream: TcpStream,
    header: &[u8],
    rx: crossbeam_channel::Receiver<Arc<Vec<u8>>>,
    timeout: Duration,
) -> std::io::Result<()> {
    stream.set_nonblocking(false)?;
    stream.set_nodelay(true)?;
    stream.set_write_timeout(Some(timeout))?;
    stream.write_all(header)?;
    for packet in rx {
        stream.write_all(&packet)?;
    }
    stream.flush()?;
    stream.shutdown(std::net::Shutdown::Write)
}

impl Sink for TcpSink {
    fn describe(&self) -> String {
        format!("tcp {} (AEDAT 4.0 network stream)", self.local)
    }

    fn send(&mut self, events: &[Event]) -> Result<()> {
        self.stats.events_in += events.len() as u64;
        let (w, h) = self.config.size;
        for e in events {
            format::check_event(e, self.last_t, w, h)?;
            self.last_t = e.t;
        }
        for chunk in events.chunks(aedat4::PACKET_EVENTS) {
            let packet = self.packet(chunk);
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
                    match c.tx.try_send(packet.clone()) {
                        Ok(()) => {
                            delivered = true;
                            c.skipped_in_a_row = 0;
                            self.stats.messages_sent += 1;
                            self.stats.bytes_sent += packet.len() as u64;
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
        for c in clients {
            drop(c.tx);
            let _ = c.thread.join();
        }
        self.stats.clients = 0;
        Ok(())
    }

    fn stats(&self) -> SinkStats {
        let mut s = self.stats;
        s.clients = self.client_count() as u64;
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
}
