//! Encode and decode throughput per event format, in memory, single thread.
//!
//! Input: the dvxplorer recording (323,963 events, 320 x 240) from ../shared/data when present
//! (or `V2CE_DATA`), otherwise the built-in synthetic scene, and says which. Throughput is in
//! elements (events) per second; divide by 1e6 for Mev/s.

use std::io::Cursor;
use std::path::PathBuf;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use v2ce::event::Event;
use v2ce::format::{aedat4, csv, evt2, evt3, raw, Compression, EventDecoder, EventEncoder};

fn input() -> (u16, u16, Vec<Event>) {
    let dir = std::env::var_os("V2CE_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    let path = dir.join("dvxplorer/data_sample.aedat4");
    match v2ce::format::read_events(&path) {
        Ok(rec) => {
            eprintln!(
                "formats bench: {} ({} events)",
                path.display(),
                rec.events.len()
            );
            (rec.width, rec.height, rec.events.into_events())
        }
        Err(e) => {
            eprintln!("formats bench: {e}; using the synthetic scene");
            let rec = v2ce::sweeping_bar::recording(320, 240, 4_000_000, 1);
            (rec.width, rec.height, rec.events.into_events())
        }
    }
}

#[derive(Clone, Copy)]
enum Kind {
    Aedat4(Compression),
    Evt2,
    Evt3,
    Csv,
}

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::Aedat4(Compression::None) => "aedat4-none",
            Kind::Aedat4(Compression::Zstd) => "aedat4-zstd",
            Kind::Aedat4(_) => "aedat4-lz4",
            Kind::Evt2 => "evt2",
            Kind::Evt3 => "evt3",
            Kind::Csv => "csv",
        }
    }

    fn encode(self, w: u16, h: u16, events: &[Event]) -> Vec<u8> {
        match self {
            Kind::Aedat4(c) => {
                let mut e = aedat4::Writer::new(Cursor::new(Vec::new()), w, h, c).unwrap();
                e.write(events).unwrap();
                e.into_inner().unwrap().into_inner()
            }
            Kind::Evt2 => {
                let mut e = evt2::Encoder::new(Vec::new(), w, h).unwrap();
                e.write(events).unwrap();
                e.into_inner().unwrap()
            }
            Kind::Evt3 => {
                let mut e = evt3::Encoder::new(Vec::new(), w, h).unwrap();
                e.write(events).unwrap();
                e.into_inner().unwrap()
            }
            Kind::Csv => {
                let mut out = Vec::new();
                csv::write_to(&mut out, events).unwrap();
                out
            }
        }
    }

    fn decode(self, bytes: &[u8]) -> usize {
        let mut dec: Box<dyn EventDecoder + '_> = match self {
            Kind::Aedat4(_) => Box::new(aedat4::Reader::new_file(bytes).unwrap()),
            Kind::Evt2 | Kind::Evt3 => {
                let mut r = bytes;
                let header = raw::read_header(&mut r).unwrap();
                match self {
                    Kind::Evt2 => Box::new(evt2::Decoder::new(r, &header)),
                    _ => Box::new(evt3::Decoder::new(r, &header)),
                }
            }
            Kind::Csv => Box::new(csv::Decoder::new(bytes)),
        };
        let mut buf = Vec::with_capacity(65_600);
        let mut n = 0;
        loop {
            buf.clear();
            let k = dec.read_events(&mut buf, 65_536).unwrap();
            if k == 0 {
                break n;
            }
            n += k;
        }
    }
}

const KINDS: [Kind; 6] = [
    Kind::Aedat4(Compression::None),
    Kind::Aedat4(Compression::Lz4),
    Kind::Aedat4(Compression::Zstd),
    Kind::Evt2,
    Kind::Evt3,
    Kind::Csv,
];

fn bench(c: &mut Criterion) {
    let (w, h, events) = input();
    let mut enc = c.benchmark_group("encode");
    enc.sample_size(10);
    enc.throughput(Throughput::Elements(events.len() as u64));
    for kind in KINDS {
        let bytes = kind.encode(w, h, &events);
        eprintln!(
            "{}: {} bytes, {:.2} bytes/event",
            kind.name(),
            bytes.len(),
            bytes.len() as f64 / events.len() as f64
        );
        enc.bench_with_input(
            BenchmarkId::from_parameter(kind.name()),
            &events,
            |b, ev| b.iter(|| kind.encode(w, h, ev).len()),
        );
    }
    enc.finish();
    let mut dec = c.benchmark_group("decode");
    dec.sample_size(10);
    dec.throughput(Throughput::Elements(events.len() as u64));
    for kind in KINDS {
        let bytes = kind.encode(w, h, &events);
        assert_eq!(kind.decode(&bytes), events.len());
        dec.bench_with_input(BenchmarkId::from_parameter(kind.name()), &bytes, |b, by| {
            b.iter(|| kind.decode(by))
        });
    }
    dec.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
