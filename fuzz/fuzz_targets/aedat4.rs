//! AEDAT 4.0: any bytes after the magic (header, packets, compression) give packets or a clear
//! error, never a panic or an allocation beyond the documented limits.
#![no_main]

use libfuzzer_sys::fuzz_target;
use v2ce::format::aedat4::{Reader, MAGIC};

fuzz_target!(|data: &[u8]| {
    let mut file = MAGIC.to_vec();
    file.extend_from_slice(data);
    for bytes in [&file[..], data] {
        let Ok(mut reader) = (if bytes.starts_with(MAGIC) {
            Reader::new_file(bytes)
        } else {
            Reader::new_stream(bytes)
        }) else {
            continue;
        };
        for _ in 0..10_000 {
            match reader.next_item() {
                Ok(Some(_)) => {}
                Ok(None) | Err(_) => break,
            }
        }
    }
});
