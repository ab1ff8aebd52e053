//! CSV: any bytes decode to events or a clear error, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use v2ce::format::{csv, EventDecoder};

fuzz_target!(|data: &[u8]| {
    let mut dec = csv::Decoder::new(data);
    let mut events = Vec::new();
    while let Ok(n) = dec.read_events(&mut events, 1024) {
        if n == 0 {
            break;
        }
    }
});
