//! Sustained UDP send rate on loopback, single sending thread, with the receiver's loss.
//!
//! For each datagram format, a receiver thread counts the events that arrive while the sink
//! sends a fixed stream as fast as it can (no pacing), then again paced. Reported: events and
//! datagrams per second sent, and the share of events the receiver never got (the kernel drops
//! datagrams when the receiver's buffer is full; the sender cannot see that).
//!
//! `cargo bench --bench udp` (plain harness: prints a table). `V2CE_UDP_EVENTS` sets the
//! stream length (default 5,000,000).

use std::net::UdpSocket;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use v2ce::event::Event;
use v2ce::sink::udp::{EmitMode, UdpFormat, UdpSink, UdpSinkConfig};
use v2ce::sink::Sink;

fn run(format: UdpFormat, events: &[Event], pace: u32) {
    let rx = UdpSocket::bind("127.0.0.1:0").expect("bind receiver");
    rx.set_read_timeout(Some(Duration::from_millis(50)))
        .expect("timeout");
    let addr = rx.local_addr().expect("address");
    let received = Arc::new(AtomicU64::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let receiver = {
        let (received, stop) = (received.clone(), stop.clone());
        let size = format.event_bytes() as u64;
        std::thread::spawn(move || {
            let mut buf = [0u8; 65_536];
            while !stop.load(Ordering::Relaxed) {
                if let Ok(n) = rx.recv(&mut buf) {
                    received.fetch_add(n as u64 / size, Ordering::Relaxed);
                }
            }
        })
    };
    let config = UdpSinkConfig {
        address: addr.to_string(),
        format,
        payload: 1472,
        rate: pace,
        emit: EmitMode::Asap,
        ..UdpSinkConfig::default()
    };
    let mut sink = UdpSink::new(&config, 1.0).expect("sink");
    let started = Instant::now();
    for chunk in events.chunks(4096) {
        sink.send(chunk).expect("send");
    }
    let secs = started.elapsed().as_secs_f64();
    std::thread::sleep(Duration::from_millis(300));
    stop.store(true, Ordering::Relaxed);
    let _ = receiver.join();
    let s = sink.stats();
    let got = received.load(Ordering::Relaxed);
    println!(
        "| {} | {} | {:.2} | {:.0} | {:.1} | {:.2}% |",
        format.name(),
        if pace == 0 {
            "none".to_string()
        } else {
            format!("{pace}/s")
        },
        s.events_sent as f64 / secs / 1e6,
        s.messages_sent as f64 / secs,
        s.bytes_sent as f64 / secs / 1e6,
        100.0 * (1.0 - got as f64 / events.len() as f64),
    );
}

fn main() {
    // `cargo bench` passes `--bench`; `cargo test --benches` passes nothing and wants no work.
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let n: usize = std::env::var("V2CE_UDP_EVENTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(5_000_000);
    let events: Vec<Event> = (0..n as i64)
        .map(|i| {
            Event::new(
                i / 4,
                (i * 7 % 346) as u16,
                (i * 13 % 260) as u16,
                i % 3 == 0,
            )
        })
        .collect();
    println!("{n} events per run, 1472-byte payloads, one sending thread, loopback");
    println!("| format | pacing | Mev/s sent | datagrams/s | MB/s | receiver loss |");
    println!("|---|---|---|---|---|---|");
    for format in [
        UdpFormat::Spif,
        UdpFormat::SpifTimestamped,
        UdpFormat::T64X16Y16On8,
        UdpFormat::T32X16Y15On1,
    ] {
        run(format, &events, 0);
    }
    for pace in [50_000, 20_000] {
        run(UdpFormat::T64X16Y16On8, &events[..n.min(2_000_000)], pace);
    }
}
