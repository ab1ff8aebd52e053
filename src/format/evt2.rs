//! Prophesee RAW EVT 2.0: a `% ` text header, then little-endian 32-bit words.
//!
//! | type (bits 31..28) | word |
//! |---|---|
//! | `0x0` CD_OFF, `0x1` CD_ON | bits 27..22 time low (6 bits), 21..11 x, 10..0 y |
//! | `0x8` EV_TIME_HIGH | bits 27..0: time bits 33..6 |
//! | `0xA` EXT_TRIGGER, `0xE` OTHERS, `0xF` CONTINUED | skipped |
//!
//! Event time is `(time_high << 6) | time_low`, 34 bits of microseconds (about 4.8 hours). The
//! encoder writes `t mod 2^34`; the decoder unwraps: a time-high word that goes back by more than
//! half the range starts the next 2^34 epoch, so streams longer than 4.8 hours come back as i64.
//! Older files end their header at the first line not starting with `%` rather than `% end`.

use std::io::{BufRead, Read, Write};

use crate::error::{Error, Result};
use crate::event::Event;

const TIME_BITS: u32 = 34;
const HIGH_MASK: u32 = 0x0FFF_FFFF;

/// What the `% ` header says.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Header {
    /// Sensor size, when the header gives it (`% geometry WxH` or `% format ...;width=W;height=H`).
    pub size: Option<(u16, u16)>,
    /// The header lines without their `% ` prefix.
    pub lines: Vec<String>,
}

/// Reads the header: lines starting with `%`, up to and including `% end` if present.
pub fn read_header(r: &mut impl BufRead) -> std::io::Result<Header> {
    let mut header = Header::default();
    loop {
        let buf = r.fill_buf()?;
        if buf.first() != Some(&b'%') {
            break;
        }
        let mut line = Vec::new();
        // Header lines are short; refuse a "line" longer than 64 KiB.
        r.by_ref().take(65_536).read_until(b'\n', &mut line)?;
        let text = String::from_utf8_lossy(&line);
        let text = text.trim_start_matches('%').trim().to_string();
        let end = text == "end";
        if let Some(size) = parse_size(&text) {
            header.size = Some(size);
        }
        header.lines.push(text);
        if end {
            break;
        }
    }
    Ok(header)
}

fn parse_size(line: &str) -> Option<(u16, u16)> {
    if let Some(g) = line.strip_prefix("geometry ") {
        let (w, h) = g.trim().split_once('x')?;
        return Some((w.parse().ok()?, h.parse().ok()?));
    }
    let f = line.strip_prefix("format ")?;
    let (mut w, mut h) = (None, None);
    for part in f.split(';') {
        match part.split_once('=') {
            Some(("width", v)) => w = v.parse().ok(),
            Some(("height", v)) => h = v.parse().ok(),
            _ => {}
        }
    }
    Some((w?, h?))
}

/// Streams events out of EVT 2.0 words.
pub struct Decoder<R> {
    reader: R,
    time_high: Option<u32>,
    epoch: i64,
    /// Position of the next word, for error messages.
    word: u64,
}

impl<R: Read> Decoder<R> {
    /// A decoder over the words after the header.
    pub fn new(reader: R) -> Self {
        Decoder {
            reader,
            time_high: None,
            epoch: 0,
            word: 0,
        }
    }

    /// Decodes up to `max` events into `out`; returns how many were added (0 at the end).
    /// Events before the first time-high word have no full time and are skipped.
    pub fn read_events(&mut self, out: &mut Vec<Event>, max: usize) -> Result<usize> {
        let start = out.len();
        let mut buf = [0u8; 4096];
        while out.len() - start < max {
            let want = ((max - (out.len() - start)) * 4).min(buf.len());
            let n = read_full(&mut self.reader, &mut buf[..want])
                .map_err(|e| Error::invalid("EVT 2.0 stream", e.to_string()))?;
            if n % 4 != 0 {
                return Err(Error::invalid(
                    "EVT 2.0 stream",
                    format!(
                        "ends inside word {} (a truncated file)",
                        self.word + n as u64 / 4
                    ),
                ));
            }
            for chunk in buf[..n].chunks_exact(4) {
                let w = u32::from_le_bytes([chunk[0], chunk[1], chunk[2], chunk[3]]);
                self.word += 1;
                match w >> 28 {
                    0x0 | 0x1 => {
                        let Some(high) = self.time_high else { continue };
                        let t = (((high as i64) << 6) | ((w >> 22) & 0x3F) as i64) + self.epoch;
                        let x = ((w >> 11) & 0x7FF) as u16;
                        let y = (w & 0x7FF) as u16;
                        out.push(Event::new(t, x, y, w >> 28 == 1));
                    }
                    0x8 => {
                        let high = w & HIGH_MASK;
                        if let Some(prev) = self.time_high {
                            if prev > high && prev - high > HIGH_MASK / 2 {
                                self.epoch += 1 << TIME_BITS;
                            }
                        }
                        self.time_high = Some(high);
                    }
                    _ => {}
                }
            }
            if n < want {
                break;
            }
        }
        Ok(out.len() - start)
    }
}

fn read_full(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

/// Writes EVT 2.0: the header, then a time-high word whenever bits 33..6 of the time change.
///
/// Across a gap of more than a quarter of the 34-bit range, intermediate time-high words are
/// written so that a decoder can follow the wrap (it only sees wrapped values).
pub struct Encoder<W: Write> {
    writer: W,
    /// `t >> 6` of the last time-high word written, unwrapped.
    time_high: Option<i64>,
    last_t: i64,
}

impl<W: Write> Encoder<W> {
    /// Writes the header for a `width x height` sensor (at most 2048 x 2048).
    pub fn new(mut writer: W, width: u16, height: u16) -> Result<Self> {
        if width > 2048 || height > 2048 {
            return Err(Error::invalid(
                "sensor size",
                format!("EVT 2.0 holds 11-bit coordinates; {width} x {height} is too large"),
            ));
        }
        write!(
            writer,
            "% evt 2.0\n% format EVT2;width={width};height={height}\n% geometry {width}x{height}\n% end\n"
        )
        .map_err(|e| Error::invalid("EVT 2.0 output", e.to_string()))?;
        Ok(Encoder {
            writer,
            time_high: None,
            last_t: 0,
        })
    }

    /// Appends events, which must be in time order with `t >= 0`.
    pub fn write(&mut self, events: &[Event]) -> Result<()> {
        let mut words = Vec::with_capacity(events.len() * 4 + 8);
        for e in events {
            if e.t < self.last_t || e.t < 0 {
                return Err(Error::invalid(
                    "event time",
                    format!("{} us comes before {} us or is negative", e.t, self.last_t),
                ));
            }
            if e.x > 0x7FF || e.y > 0x7FF {
                return Err(Error::invalid(
                    "pixel",
                    format!("({}, {}) does not fit 11 bits", e.x, e.y),
                ));
            }
            self.last_t = e.t;
            let target = e.t >> 6;
            let step = (HIGH_MASK / 4) as i64;
            let mut emit = |high: i64| {
                let w = (0x8 << 28) | (high as u32 & HIGH_MASK);
                words.extend_from_slice(&w.to_le_bytes());
            };
            match self.time_high {
                Some(mut high) if high != target => {
                    while target - high > step {
                        high += step;
                        emit(high);
                    }
                    emit(target);
                }
                None => emit(target),
                Some(_) => {}
            }
            self.time_high = Some(target);
            let word = ((e.on as u32) << 28)
                | (((e.t & 0x3F) as u32) << 22)
                | ((e.x as u32) << 11)
                | e.y as u32;
            words.extend_from_slice(&word.to_le_bytes());
        }
        self.writer
            .write_all(&words)
            .map_err(|e| Error::invalid("EVT 2.0 output", e.to_string()))
    }

    /// Flushes and returns the writer.
    pub fn finish(mut self) -> Result<W> {
        self.writer
            .flush()
            .map_err(|e| Error::invalid("EVT 2.0 output", e.to_string()))?;
        Ok(self.writer)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(events: &[Event]) -> (Header, Vec<Event>) {
        let mut enc = Encoder::new(Vec::new(), 640, 480).unwrap();
        enc.write(events).unwrap();
        let bytes = enc.finish().unwrap();
        let mut r = std::io::BufReader::new(&bytes[..]);
        let header = read_header(&mut r).unwrap();
        let mut out = Vec::new();
        let mut dec = Decoder::new(r);
        while dec.read_events(&mut out, 1000).unwrap() > 0 {}
        (header, out)
    }

    #[test]
    fn round_trip_with_header() {
        let events: Vec<Event> = (0..5000)
            .map(|i| Event::new(i * 37, (i % 640) as u16, (i % 480) as u16, i % 3 == 0))
            .collect();
        let (header, back) = round_trip(&events);
        assert_eq!(header.size, Some((640, 480)));
        assert_eq!(back, events);
    }

    #[test]
    fn spans_past_2_pow_34_us_round_trip() {
        // Sparse events over about 11 hours, crossing the 34-bit wrap twice.
        let events: Vec<Event> = (0..400)
            .map(|i| Event::new(i * 100_000_000 + (i % 64), 1, 2, i % 2 == 0))
            .collect();
        assert!(events[399].t > 2 << 34);
        let (_, back) = round_trip(&events);
        assert_eq!(back, events);
        // Gaps of exactly 2^34 us (same wrapped time) and of more than half the range.
        let events = vec![
            Event::new(7, 0, 0, true),
            Event::new(7 + (1 << 34), 0, 0, true),
            Event::new(3 * (1 << 34) + (1 << 33) + 100, 0, 0, false),
        ];
        assert_eq!(round_trip(&events).1, events);
    }

    #[test]
    fn bad_input_is_an_error() {
        let mut enc = Encoder::new(Vec::new(), 640, 480).unwrap();
        assert!(enc.write(&[Event::new(-1, 0, 0, true)]).is_err());
        assert!(enc.write(&[Event::new(5, 2048, 0, true)]).is_err());
        assert!(Encoder::new(Vec::new(), 4096, 10).is_err());
        // A truncated word.
        let mut dec = Decoder::new(&[0u8, 0, 0, 0x80, 1, 2][..]);
        assert!(dec.read_events(&mut Vec::new(), 10).is_err());
        // An old-style header without `% end`, no geometry.
        let bytes = b"% evt 2.0\n% serial 1\n\x00\x00\x00\x80";
        let mut r = std::io::BufReader::new(&bytes[..]);
        let h = read_header(&mut r).unwrap();
        assert_eq!((h.size, h.lines.len()), (None, 2));
        let mut out = Vec::new();
        Decoder::new(r).read_events(&mut out, 10).unwrap();
        assert!(out.is_empty());
    }
}
