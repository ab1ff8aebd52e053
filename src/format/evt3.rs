//! Prophesee RAW EVT 3.0: a `% ` text header (see [`super::raw`]), then little-endian 16-bit
//! words that update a decoder state (row, time, vector base) and emit events.
//!
//! | type (bits 15..12) | word |
//! |---|---|
//! | `0x0` EVT_ADDR_Y | bits 10..0 row (bit 11: system type, ignored) |
//! | `0x2` EVT_ADDR_X | bit 11 polarity, bits 10..0 column: one event at the current row and time |
//! | `0x3` VECT_BASE_X | bit 11 polarity, bits 10..0 column: base of the next vector words |
//! | `0x4` VECT_12 | bits 11..0: events at base + i for each set bit i (bits past the sensor's width are ignored); base += 12 |
//! | `0x5` VECT_8 | bits 7..0: likewise; base += 8 |
//! | `0x6` EVT_TIME_LOW | bits 11..0: time bits 11..0 |
//! | `0x8` EVT_TIME_HIGH | bits 11..0: time bits 23..12 |
//! | `0x7`, `0xA`, `0xE`, `0xF` | continued, trigger and other words: skipped |
//!
//! Time has 24 bits (16.8 s). The decoder follows the rules of faery, the reference reader here
//! (it reads every sample recording the same way):
//! - time never decreases: a time-low word behind the current time (sensors send a few) leaves
//!   the time where it is;
//! - a time-high word is taken if it moves forward by less than 4094 units of 4096 us, or back by
//!   more than 4094 (a wrap: 4095 to 0 starts the next 2^24 us epoch); it resets time-low to 0;
//!   other jumps are ignored as glitches.
//!
//! The encoder writes time-high words that obey those rules across any gap: forward steps of at
//! most 2048 units, and every wrap as 4095 then 0, so any span comes back exactly.
//!
//! The encoder keeps the order of its input. A run of three or more consecutive events with the
//! same time, row and polarity and increasing columns within 12 of the first is written as
//! VECT_BASE_X + VECT_12 (two words instead of one per event); further VECT_12 words follow while
//! the run continues in the next 12 columns.

use std::io::{Read, Write};

use super::raw::{self, Evt};
use super::{check_event, read_words, EventDecoder, EventEncoder};
use crate::error::{Error, Result};
use crate::event::Event;

const TIME_BITS: u32 = 24;
/// A time-high word that moves forward by this much or more is a glitch and is ignored; one that
/// moves back by more is a wrap into the next 2^24 us epoch (any other step back is ignored).
const WRAP_STEP: u16 = (1 << 12) - 2;
/// The encoder's largest forward step between time-high words.
const MAX_STEP: i64 = 2048;
pub use super::raw::MAX_GAP_US;
const WHAT: &str = "EVT 3.0 stream";

/// Streams events out of EVT 3.0 words (the part after the header).
pub struct Decoder<R> {
    reader: R,
    size: Option<(u16, u16)>,
    y: u16,
    time_high: u16,
    time_low: u16,
    base_x: u16,
    base_on: bool,
    /// Time offset plus the 2^24 epochs passed.
    base_t: i64,
    /// The current time: never decreases.
    t: i64,
    word: u64,
    buf: Vec<u8>,
    /// The next time-high word is taken whatever it is (a packet read alone).
    free_high: bool,
}

impl<R: Read> Decoder<R> {
    /// A decoder over the words after the header; `header` gives the size and time offset.
    pub fn new(reader: R, header: &raw::Header) -> Self {
        Decoder {
            reader,
            size: header.size,
            y: 0,
            time_high: 0,
            time_low: 0,
            base_x: 0,
            base_on: false,
            base_t: header.time_offset,
            t: header.time_offset,
            word: 0,
            buf: vec![0; 16384],
            free_high: false,
        }
    }

    /// A decoder of one self-contained packet of words (no header): its first time-high word
    /// sets the time whatever it is, and times count from 0 at that word's epoch.
    pub fn packet(reader: R, size: Option<(u16, u16)>) -> Self {
        let mut d = Decoder::new(
            reader,
            &raw::Header {
                size,
                ..raw::Header::default()
            },
        );
        d.buf = vec![0; 4096];
        d.free_high = true;
        d
    }

    fn update_time(&mut self) {
        let t =
            (((self.time_high as i64) << 12) | self.time_low as i64).saturating_add(self.base_t);
        self.t = self.t.max(t);
    }

    fn time_high(&mut self, high: u16) {
        if std::mem::take(&mut self.free_high) {
            self.time_high = high;
            self.time_low = 0;
            self.update_time();
            return;
        }
        let prev = self.time_high;
        let accept = if high > prev {
            high - prev < WRAP_STEP
        } else if high < prev {
            let wrapped = prev - high > WRAP_STEP;
            if wrapped {
                self.base_t = self.base_t.saturating_add(1 << TIME_BITS);
            }
            wrapped
        } else {
            false
        };
        if accept {
            self.time_high = high;
            self.time_low = 0;
            self.update_time();
        }
    }

    fn vector(&mut self, mask: u16, bits: u16, out: &mut Vec<Event>) {
        // Bits past the sensor's last column (or the 11-bit address space) are not pixels.
        let width = self.size.map_or(2048, |s| s.0.min(2048));
        let room = width.saturating_sub(self.base_x).min(16) as u32;
        let mut m = (mask as u32 & ((1u32 << room) - 1)) as u16;
        while m != 0 {
            let i = m.trailing_zeros() as u16;
            out.push(Event::new(self.t, self.base_x + i, self.y, self.base_on));
            m &= m - 1;
        }
        self.base_x = (self.base_x + bits) & 0x7FF;
    }
}

impl<R: Read> EventDecoder for Decoder<R> {
    fn size(&self) -> Option<(u16, u16)> {
        self.size
    }

    /// A vector word may add up to 11 events beyond `max`.
    fn read_events(&mut self, out: &mut Vec<Event>, max: usize) -> Result<usize> {
        let start = out.len();
        while out.len() - start < max {
            let want = ((max - (out.len() - start)) * 2).min(self.buf.len());
            let n = read_words(&mut self.reader, &mut self.buf[..want], 2, self.word, WHAT)?;
            for i in (0..n).step_by(2) {
                let w = u16::from_le_bytes([self.buf[i], self.buf[i + 1]]);
                self.word += 1;
                let low12 = w & 0xFFF;
                match w >> 12 {
                    0x0 => self.y = w & 0x7FF,
                    0x2 => out.push(Event::new(self.t, w & 0x7FF, self.y, w & 0x800 != 0)),
                    0x3 => {
                        self.base_x = w & 0x7FF;
                        self.base_on = w & 0x800 != 0;
                    }
                    0x4 => self.vector(low12, 12, out),
                    0x5 => self.vector(w & 0xFF, 8, out),
                    0x6 => {
                        self.time_low = low12;
                        self.update_time();
                    }
                    0x8 => self.time_high(low12),
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

/// The EVT 3.0 words of events, with the state they share across calls (time-high, time-low,
/// row): what [`Encoder`] writes after its header, and each self-contained packet of
/// [`super::event_packet`] ([`Words::restart`]).
#[derive(Debug, Clone)]
pub struct Words {
    /// `(t - offset) >> 12` of the last time-high word, unwrapped.
    time_high: Option<i64>,
    time_low: Option<u16>,
    y: Option<u16>,
    last_t: i64,
}

impl Default for Words {
    fn default() -> Self {
        Words {
            time_high: None,
            time_low: None,
            y: None,
            last_t: i64::MIN,
        }
    }
}

fn word(out: &mut Vec<u8>, w: u16) {
    out.extend_from_slice(&w.to_le_bytes());
}

impl Words {
    /// Starts a unit a decoder can read alone: the current time-high word again, and the
    /// time-low and row written again before the next event.
    pub fn restart(&mut self, out: &mut Vec<u8>) {
        if let Some(h) = self.time_high {
            word(out, 0x8000 | (h & 0xFFF) as u16);
        }
        self.time_low = None;
        self.y = None;
    }

    fn set_time(&mut self, rel: i64, out: &mut Vec<u8>) {
        let target = rel >> 12;
        let low = (rel & 0xFFF) as u16;
        let mut high = match self.time_high {
            Some(h) => h,
            None => {
                // Start at the epoch's 0, which every reader accepts as a first word.
                let start = target & !0xFFF;
                word(out, 0x8000);
                start
            }
        };
        let changed = high != target;
        while high != target {
            let epoch_end = high | 0xFFF;
            let stop = target.min(epoch_end);
            while stop - high > MAX_STEP {
                high += MAX_STEP;
                word(out, 0x8000 | (high & 0xFFF) as u16);
            }
            if high != stop {
                high = stop;
                word(out, 0x8000 | (high & 0xFFF) as u16);
            }
            if high != target {
                high += 1;
                word(out, 0x8000);
            }
        }
        self.time_high = Some(high);
        if changed || self.time_low != Some(low) {
            word(out, 0x6000 | low);
            self.time_low = Some(low);
        }
    }

    /// Appends the words of `events` (in time order, inside a `width x height` sensor: checked)
    /// at times relative to `offset` to `out`.
    pub fn encode(
        &mut self,
        events: &[Event],
        offset: i64,
        width: u16,
        height: u16,
        out: &mut Vec<u8>,
    ) -> Result<()> {
        let mut last = self.last_t;
        for e in events {
            check_event(e, last, width, height)?;
            last = e.t;
        }
        out.reserve(events.len() * 2 + 16);
        let mut i = 0;
        while i < events.len() {
            let e = events[i];
            // Not `last_t != i64::MIN`: a first event may be at i64::MIN itself.
            if self.time_high.is_some() {
                super::raw::check_gap(self.last_t, e.t, "EVT 3.0")?;
            }
            self.last_t = e.t;
            self.set_time(e.t - offset, out);
            if self.y != Some(e.y) {
                word(out, e.y);
                self.y = Some(e.y);
            }
            let pol = (e.on as u16) << 11;
            let run = &events[i..i + run_len(&events[i..])];
            let first_block = run.iter().take_while(|r| r.x < e.x + 12).count();
            if first_block < 3 {
                word(out, 0x2000 | pol | e.x);
                i += 1;
                continue;
            }
            word(out, 0x3000 | pol | e.x);
            let mut base = e.x;
            let mut k = 0;
            while k < run.len() && run[k].x < base + 12 {
                let mut mask = 0u16;
                while k < run.len() && run[k].x < base + 12 {
                    mask |= 1 << (run[k].x - base);
                    k += 1;
                }
                word(out, 0x4000 | mask);
                base += 12;
            }
            i += k;
        }
        Ok(())
    }
}

/// Writes EVT 3.0: the header on the first write, then state-change and event words.
pub struct Encoder<W: Write> {
    writer: W,
    header: raw::LazyHeader,
    state: Words,
    words: Vec<u8>,
}

impl<W: Write> Encoder<W> {
    /// An encoder for a `width x height` sensor (at most 2048 x 2048).
    pub fn new(writer: W, width: u16, height: u16) -> Result<Self> {
        Ok(Encoder {
            writer,
            header: raw::LazyHeader::new(Evt::Evt3, width, height)?,
            state: Words::default(),
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
    Error::invalid("EVT 3.0 output", e.to_string())
}

/// Length of the run starting at `events[0]` that vector words can carry, and whether the
/// first 12 columns hold enough of it to pay off.
fn run_len(events: &[Event]) -> usize {
    let first = events[0];
    let mut n = 1;
    while n < events.len() {
        let (p, e) = (events[n - 1], events[n]);
        if e.t != first.t || e.y != first.y || e.on != first.on || e.x <= p.x {
            break;
        }
        n += 1;
    }
    n
}

impl<W: Write> EventEncoder for Encoder<W> {
    /// Appends events, which must be in time order and inside the sensor.
    fn write(&mut self, events: &[Event]) -> Result<()> {
        let Some(first) = events.first() else {
            return Ok(());
        };
        let offset = self.header(first.t)?;
        self.words.clear();
        let (w, h) = (self.header.width, self.header.height);
        self.state.encode(events, offset, w, h, &mut self.words)?;
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

    fn encode(events: &[Event], w: u16, h: u16) -> Vec<u8> {
        let mut enc = Encoder::new(Vec::new(), w, h).unwrap();
        enc.write(events).unwrap();
        enc.into_inner().unwrap()
    }

    fn decode(bytes: &[u8]) -> Vec<Event> {
        let mut r = std::io::BufReader::new(bytes);
        let header = raw::read_header(&mut r).unwrap();
        let mut dec = Decoder::new(r, &header);
        let mut out = Vec::new();
        while dec.read_events(&mut out, 777).unwrap() > 0 {}
        out
    }

    #[test]
    fn round_trip_mixed_stream() {
        let events: Vec<Event> = (0..20_000i64)
            .map(|i| {
                Event::new(
                    i / 3 * 11,
                    (i * 7 % 1280) as u16,
                    (i % 720) as u16,
                    i % 5 < 2,
                )
            })
            .collect();
        assert_eq!(decode(&encode(&events, 1280, 720)), events);
    }

    #[test]
    fn vectors_carry_rows_of_events_in_fewer_words() {
        // A full row edge: 1280 ON events at one time and row, then OFF events at every
        // other column, then scattered singles.
        let mut events: Vec<Event> = (0..1280).map(|x| Event::new(50, x, 3, true)).collect();
        events.extend((0..640).map(|x| Event::new(50, 2 * x, 3, false)));
        events.extend((0..50).map(|i| Event::new(60 + i, (i * 13) as u16, 9, false)));
        let bytes = encode(&events, 1280, 720);
        assert_eq!(decode(&bytes), events);
        let header_len = bytes.len() - bytes.rsplit(|b| *b == b'\n').next().unwrap().len();
        let words = (bytes.len() - header_len) / 2;
        // 1280 / 12 + 1 words for the ON row, 1280 / 12 + 1 for the OFF row, ~3 per single.
        assert!(words < 450, "{words} words");
    }

    #[test]
    fn spans_past_2_pow_24_us_round_trip() {
        // An event every 3 s for 2 minutes (several 16.8 s wraps), one gap of exactly 2^24 us,
        // one of more than half the range, starting at a Unix-epoch time.
        let t0 = 1_700_000_000_000_000i64;
        let mut events: Vec<Event> = (0..40)
            .map(|i| Event::new(t0 + i * 3_000_000 + i, (i % 17) as u16, 4, i % 2 == 0))
            .collect();
        let last = events[39].t;
        events.push(Event::new(last + (1 << 24), 1, 1, true));
        events.push(Event::new(last + (1 << 24) + (3 << 22) + 5, 2, 2, false));
        events.push(Event::new(last + (9 << 24), 3, 3, false));
        assert_eq!(decode(&encode(&events, 64, 64)), events);
    }

    #[test]
    fn time_never_goes_back_and_glitches_are_ignored() {
        // y=5; high 2; low 0x32b; event; low 0x320 (behind); event; high 4000 (a forward
        // glitch of 3998 is taken: under 4094); event; high 10 (back by 3990: ignored); event.
        let words: [u16; 9] = [
            0x0005, 0x8002, 0x632b, 0x2001, 0x6320, 0x2002, 0x8FA0, 0x2003, 0x800A,
        ];
        let mut bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        bytes.extend_from_slice(&0x2004u16.to_le_bytes());
        let mut out = Vec::new();
        Decoder::new(&bytes[..], &raw::Header::default())
            .read_events(&mut out, 100)
            .unwrap();
        let t: Vec<i64> = out.iter().map(|e| e.t).collect();
        let a = (2 << 12) | 0x32b;
        assert_eq!(t, vec![a, a, 4000 << 12, 4000 << 12]);
        assert!(out.iter().all(|e| e.y == 5));
    }

    #[test]
    fn vector_bits_past_the_sensor_are_not_events() {
        // A 16-column sensor: base x 10 with all 12 bits set gives columns 10..=15 only; the
        // same at base 2046 without a size gives 2046 and 2047 (found by fuzzing).
        let words: [u16; 4] = [0x8001, 0x0003, 0x300A, 0x4FFF];
        let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        let header = raw::Header {
            size: Some((16, 16)),
            ..Default::default()
        };
        let mut out = Vec::new();
        Decoder::new(&bytes[..], &header)
            .read_events(&mut out, 100)
            .unwrap();
        assert_eq!(
            out.iter().map(|e| e.x).collect::<Vec<_>>(),
            (10..16).collect::<Vec<_>>()
        );
        let words: [u16; 4] = [0x8001, 0x0003, 0x37FE, 0x4FFF];
        let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        let mut out = Vec::new();
        Decoder::new(&bytes[..], &raw::Header::default())
            .read_events(&mut out, 100)
            .unwrap();
        assert_eq!(
            out.iter().map(|e| e.x).collect::<Vec<_>>(),
            vec![2046, 2047]
        );
    }

    #[test]
    fn times_across_the_whole_i64_range_are_refused_like_evt2() {
        for (a, b) in [(i64::MIN, i64::MAX), (i64::MIN, 0), (-5, i64::MAX)] {
            let events = [Event::new(a, 0, 0, true), Event::new(b, 1, 0, false)];
            let mut enc = Encoder::new(Vec::new(), 64, 64).unwrap();
            let e = enc.write(&events).unwrap_err().to_string();
            assert!(e.contains("gap"), "{e}");
            // One write at a time: the same.
            let mut enc = Encoder::new(Vec::new(), 64, 64).unwrap();
            enc.write(&events[..1]).unwrap();
            assert!(enc.write(&events[1..]).is_err());
            let mut enc2 = crate::format::evt2::Encoder::new(Vec::new(), 64, 64).unwrap();
            assert!(enc2.write(&events).is_err());
        }
        // What fits comes back exactly, from the first representable time on.
        let events = [
            Event::new(i64::MIN, 0, 0, true),
            Event::new(i64::MIN + 1000, 1, 0, false),
        ];
        assert_eq!(decode(&encode(&events, 64, 64)), events);
    }

    #[test]
    fn bad_input_is_an_error() {
        let mut enc = Encoder::new(Vec::new(), 64, 64).unwrap();
        enc.write(&[Event::new(10, 0, 0, true)]).unwrap();
        assert!(enc.write(&[Event::new(9, 0, 0, true)]).is_err());
        assert!(enc.write(&[Event::new(11, 0, 64, true)]).is_err());
        assert!(Encoder::new(Vec::new(), 0, 10).is_err());
    }

    #[test]
    fn a_stream_cut_inside_a_word_keeps_the_events_before_it() {
        let events = [Event::new(10, 1, 2, true), Event::new(20, 3, 4, false)];
        let bytes = encode(&events, 64, 64);
        assert_eq!(decode(&bytes), events);
        // The last word (the second event's column) loses one of its two bytes.
        assert_eq!(decode(&bytes[..bytes.len() - 1]), events[..1]);
    }
}
