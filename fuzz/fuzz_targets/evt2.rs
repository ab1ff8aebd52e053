//! EVT 2.0: any bytes (header and words) decode to events or a clear error, never a panic; the
//! decoded events re-encode and decode to themselves.
#![no_main]

use libfuzzer_sys::fuzz_target;
use v2ce::format::{evt2, raw, EventDecoder, EventEncoder};

fuzz_target!(|data: &[u8]| {
    let mut r = data;
    let Ok(header) = raw::read_header(&mut r) else {
        return;
    };
    let mut dec = evt2::Decoder::new(r, &header);
    let mut events = Vec::new();
    while let Ok(n) = dec.read_events(&mut events, 4096) {
        if n == 0 {
            break;
        }
    }
    let mut enc = evt2::Encoder::new(Vec::new(), 2048, 2048).unwrap();
    enc.write(&events).unwrap();
    let bytes = enc.into_inner().unwrap();
    let mut r = &bytes[..];
    let header = raw::read_header(&mut r).unwrap();
    let mut back = Vec::new();
    let mut dec = evt2::Decoder::new(r, &header);
    while dec.read_events(&mut back, 4096).unwrap() > 0 {}
    assert_eq!(back, events);
});
