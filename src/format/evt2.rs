//! Prophesee RAW EVT 2.0: a `% ` text header (see [`super::raw`]), then little-endian 32-bit
//! words.
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
//! Across a gap longer than a quarter of the range the encoder writes intermediate time-high
//! words so that the decoder can follow. An event whose time goes back (a sensor artefact) is
//! held at the latest time seen, as faery does, so the output is always in time order.

use std::io::{Read, Write};

use super::raw::{self, Evt};
use super::{check_event, read_words, EventDecoder, EventEncoder};
use crate::error::{Error, Result};
use crate::event::Event;

const TIME_BITS: u32 = 34;
const HIGH_MASK: u32 = 0x0FFF_FFFF;
const WHAT: &str = "EVT 2.0 stream";

/// Streams events out of EVT 2.0 words (the part after the header).
pub struct Decoder<R> {
    reader: R,
    size: Option<(u16, u16)>,
    time_high: Option<u32>,
    /// Time offset plus the 2^34 epochs passed.
    base: i64,
    /// Latest event time decoded.
    last_t: i64,
    /// Index of the next word, for error messages.
    word: u64,
    buf: Vec<u8>,
}

impl<R: Read> Decoder<R> {
    /// A decoder over the words after the header; `header` gives the size and time offset.
    pub fn new(reader: R, header: &raw::Header) -> Self {
        Decoder {
            reader,
            size: header.size,
            time_high: None,
            base: header.time_offset,
            last_t: i64::MIN,
            word: 0,
            buf: vec![0; 16384],
        }
    }
}

impl<R: Read> EventDecoder for Decoder<R> {
    fn size(&self) -> Option<(u16, u16)> {
        self.size
    }

    /// Events before the first time-high word have no full time and are skipped.
    fn read_events(&mut self, out: &mut Vec<Event>, max: usize) -> Result<usize> {
        let start = out.len();
        while out.len() - start < max {
            let want = ((max - (out.len() - start)) * 4).min(self.buf.len());
            let n = read_words(&mut self.reader, &mut self.buf[..want], 4, self.word, WHAT)?;
            for chunk in self.buf[..n].chunks_exact(4) {
                let w = u32::from_le_bytes([chunk[0], chunk[1], chunk[2], chunk[3]]);
                self.word += 1;
                match w >> 28 {
                    0x0 | 0x1 => {
                        let Some(high) = self.time_high else { continue };
                        let t = ((((high as i64) << 6) | ((w >> 22) & 0x3F) as i64)
                            .saturating_add(self.base))
                        .max(self.last_t);
                        self.last_t = t;
                        let x = ((w >> 11) & 0x7FF) as u16;
                        let y = (w & 0x7FF) as u16;
                        out.push(Event::new(t, x, y, w >> 28 == 1));
                    }
                    0x8 => {
                        let high = w & HIGH_MASK;
                        if let Some(prev) = self.time_high {
                            if prev > high && prev - high > HIGH_MASK / 2 {
                                self.base = self.base.saturating_add(1 << TIME_BITS);
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

/// Writes EVT 2.0: the header (on the first write), then a time-high word whenever bits 33..6
/// of the time change.
pub struct Encoder<W: Write> {
    writer: W,
    header: raw::LazyHeader,
    /// `(t - offset) >> 6` of the last time-high word written.
    time_high: Option<i64>,
    last_t: i64,
    words: Vec<u8>,
}

impl<W: Write> Encoder<W> {
    /// An encoder for a `width x height` sensor (at most 2048 x 2048).
    pub fn new(writer: W, width: u16, height: u16) -> Result<Self> {
        Ok(Encoder {
            writer,
            header: raw::LazyHeader::new(Evt::Evt2, width, height)?,
            time_high: None,
            last_t: i64::MIN,
            words: Vec::new(),
        })
    }

    fn header(&mut self, first_t: i64) -> Result<i64> {
        self.header
            .offset(&mut self.writer, first_t)
            .map_err(output_error)
    }

    /// The writer, e.g. to take the bytes written so far from a `Vec<u8>`.
    pub fn get_mut(&mut self) -> &mut W {
        &mut self.writer
    }

    /// Flushes and returns the writer.
    pub fn into_inner(mut self) -> Result<W> {
        EventEncoder::finish(&mut self)?;
        Ok(self.writer)
    }
}

fn output_error(e: std::io::Error) -> Error {
    Error::invalid("EVT 2.0 output", e.to_string())
}

impl<W: Write> EventEncoder for Encoder<W> {
    /// Appends events, which must be in time order and inside the sensor.
    fn write(&mut self, events: &[Event]) -> Result<()> {
        let Some(first) = events.first() else {
            return Ok(());
        };
        let offset = self.header(first.t)?;
        self.words.clear();
        self.words.reserve(events.len() * 4 + 8);
        for e in events {
            check_event(e, self.last_t, self.header.width, self.header.height)?;
            if self.time_high.is_some() {
                super::raw::check_gap(self.last_t, e.t, "EVT 2.0")?;
            }
            self.last_t = e.t;
            let rel = e.t - offset;
            let target = rel >> 6;
            let step = (HIGH_MASK / 4) as i64;
            let words = &mut self.words;
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
                | (((rel & 0x3F) as u32) << 22)
                | ((e.x as u32) << 11)
                | e.y as u32;
            self.words.extend_from_slice(&word.to_le_bytes());
        }
        self.writer.write_all(&self.words).map_err(output_error)
    }

    /// Writes the header if no event came, and flushes.
    fn finish(&mut self) -> Result<()> {
        self.header(0)?;
        self.writer.flush().map_err(output_error)
    }

    fn flush(&mut self) -> Result<()> {
        self.writer.flush().map_err(output_error)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(events: &[Event]) -> (raw::Header, Vec<Event>) {
        let mut enc = Encoder::new(Vec::new(), 640, 480).unwrap();
        enc.write(events).unwrap();
        let bytes = enc.into_inner().unwrap();
        let mut r = std::io::BufReader::new(&bytes[..]);
        let header = raw::read_header(&mut r).unwrap();
        let mut out = Vec::new();
        let mut dec = Decoder::new(r, &header);
        while dec.read_events(&mut out, 1000).unwrap() > 0 {}
        (header, out)
    }

    #[test]
    fn round_trip_with_header() {
        let events: Vec<Event> = (0..5000)
            .map(|i| Event::new(i * 37, (i % 640) as u16, (i % 480) as u16, i % 3 == 0))
            .collect();
        let (header, back) = round_trip(&events);
        assert_eq!(
            (header.size, header.evt),
            (Some((640, 480)), Some(Evt::Evt2))
        );
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
        // Gaps of exactly 2^34 us (same wrapped time) and of more than half the range, from
        // a Unix-epoch start and from a negative one.
        for t0 in [1_589_163_147_364_965, -5, 0] {
            let events = vec![
                Event::new(t0 + 7, 0, 0, true),
                Event::new(t0 + 7 + (1 << 34), 0, 0, true),
                Event::new(t0 + 3 * (1 << 34) + (1 << 33) + 100, 0, 0, false),
            ];
            assert_eq!(round_trip(&events).1, events);
        }
    }

    #[test]
    fn bad_input_is_an_error() {
        let mut enc = Encoder::new(Vec::new(), 640, 480).unwrap();
        enc.write(&[Event::new(10, 0, 0, true)]).unwrap();
        assert!(enc.write(&[Event::new(9, 0, 0, true)]).is_err());
        assert!(enc.write(&[Event::new(11, 640, 0, true)]).is_err());
        assert!(Encoder::new(Vec::new(), 4096, 10).is_err());
        // A stream cut inside its last word keeps the events before it.
        let events = [Event::new(10, 1, 2, true), Event::new(20, 3, 4, false)];
        let mut enc = Encoder::new(Vec::new(), 640, 480).unwrap();
        enc.write(&events).unwrap();
        let bytes = enc.into_inner().unwrap();
        for cut in 1..4 {
            let mut r = std::io::BufReader::new(&bytes[..bytes.len() - cut]);
            let h = raw::read_header(&mut r).unwrap();
            let (mut dec, mut out) = (Decoder::new(r, &h), Vec::new());
            while dec.read_events(&mut out, 10).unwrap() > 0 {}
            assert_eq!(out, events[..1], "cut {cut} bytes");
        }
        // An old-style header without `% end`, no geometry.
        let bytes = b"% evt 2.0\n% serial 1\n\x00\x00\x00\x80";
        let mut r = std::io::BufReader::new(&bytes[..]);
        let h = raw::read_header(&mut r).unwrap();
        assert_eq!((h.size, h.lines.len()), (None, 2));
        let mut out = Vec::new();
        Decoder::new(r, &h).read_events(&mut out, 10).unwrap();
        assert!(out.is_empty());
    }

    #[test]
    fn empty_stream_still_has_a_header() {
        let bytes = Encoder::new(Vec::new(), 10, 10)
            .unwrap()
            .into_inner()
            .unwrap();
        let h = raw::read_header(&mut std::io::BufReader::new(&bytes[..])).unwrap();
        assert_eq!(h.size, Some((10, 10)));
    }
}
