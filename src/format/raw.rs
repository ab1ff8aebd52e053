//! The `% ` text header of Prophesee RAW files, shared by [`super::evt2`] and [`super::evt3`].
//!
//! The header is a run of lines starting with `%`, ended by `% end` (older files simply start
//! their binary words after the last `%` line). The keys read here:
//!
//! | line | meaning |
//! |---|---|
//! | `% evt 2.0` / `% evt 3.0` | the word format |
//! | `% format EVT3;height=720;width=1280` | word format and sensor size (newer files) |
//! | `% geometry 1280x720` | sensor size |
//! | `% plugin_name hal_plugin_gen41_evk3` | the camera, from which older files' size is inferred |
//! | `% v2ce_time_offset_us N` | written by v2ce: add `N` to every decoded time |
//!
//! Both formats carry time modulo a wrap period (2^34 us for EVT 2.0, 2^24 us for EVT 3.0). The
//! encoders write the first event's time rounded down to a multiple of that period as
//! `v2ce_time_offset_us`, so absolute times (such as Unix-epoch microseconds) come back exactly
//! from our decoder; other readers, which ignore the line, see `t - N`.

use std::io::{BufRead, Read, Write};

use crate::error::{Error, Result};

/// The longest gap between consecutive events the RAW encoders bridge (2^40 us, 12.7 days: at
/// most about 200,000 EVT 3.0 or 256 EVT 2.0 time-high words); longer gaps are refused rather
/// than written as gigabytes of time words.
pub const MAX_GAP_US: i64 = 1 << 40;

/// Refuses a gap from `last` to `t` (us) longer than [`MAX_GAP_US`], for `format`'s encoder.
pub fn check_gap(last: i64, t: i64, format: &str) -> Result<()> {
    let gap = t.saturating_sub(last);
    if gap > MAX_GAP_US {
        return Err(Error::invalid(
            "event time",
            format!(
                "a gap of {gap} us after {last} us is longer than {format} bridges ({MAX_GAP_US} us); split the stream"
            ),
        ));
    }
    Ok(())
}

/// The word formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Evt {
    /// EVT 2.0: 32-bit words, 34-bit time.
    Evt2,
    /// EVT 3.0: 16-bit words, 24-bit time.
    Evt3,
}

impl Evt {
    /// The version as written in `% evt` lines.
    pub fn version(self) -> &'static str {
        match self {
            Evt::Evt2 => "2.0",
            Evt::Evt3 => "3.0",
        }
    }

    /// How many bits of time the words hold.
    pub fn time_bits(self) -> u32 {
        match self {
            Evt::Evt2 => 34,
            Evt::Evt3 => 24,
        }
    }
}

/// What the `% ` header says.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Header {
    /// The word format, when the header names it.
    pub evt: Option<Evt>,
    /// Sensor size, from `% geometry`, `% format`, or a known camera's `% plugin_name`.
    pub size: Option<(u16, u16)>,
    /// Added to every decoded time (0 unless the file says otherwise).
    pub time_offset: i64,
    /// The header lines without their `% ` prefix.
    pub lines: Vec<String>,
    /// The header's length in bytes: the words start here.
    pub bytes: u64,
}

/// The longest header this reader accepts, in bytes (real headers are a few hundred).
pub const MAX_HEADER_BYTES: u64 = 1 << 20;

/// Reads the header: lines starting with `%`, up to and including `% end` if present.
pub fn read_header(r: &mut impl BufRead) -> Result<Header> {
    let bad = |m: String| Error::invalid("RAW header", m);
    let mut header = Header::default();
    let mut total = 0u64;
    let mut plugin_size = None;
    loop {
        let buf = r.fill_buf().map_err(|e| bad(e.to_string()))?;
        if buf.first() != Some(&b'%') {
            break;
        }
        let mut line = Vec::new();
        r.by_ref()
            .take(MAX_HEADER_BYTES - total)
            .read_until(b'\n', &mut line)
            .map_err(|e| bad(e.to_string()))?;
        total += line.len() as u64;
        if total >= MAX_HEADER_BYTES {
            return Err(bad(format!("longer than {MAX_HEADER_BYTES} bytes")));
        }
        let text = String::from_utf8_lossy(&line);
        let text = text.trim_start_matches('%').trim().to_string();
        let end = text == "end";
        parse_line(&text, &mut header, &mut plugin_size).map_err(bad)?;
        header.lines.push(text);
        if end {
            break;
        }
    }
    if header.size.is_none() {
        header.size = plugin_size;
    }
    header.bytes = total;
    Ok(header)
}

fn unsupported(what: &str) -> String {
    format!("the event format '{what}' is not supported (EVT 2.0 and EVT 3.0 are)")
}

fn parse_line(
    line: &str,
    header: &mut Header,
    plugin_size: &mut Option<(u16, u16)>,
) -> std::result::Result<(), String> {
    let (key, value) = line.split_once(' ').unwrap_or((line, ""));
    let value = value.trim();
    match key {
        "evt" => {
            header.evt = match value {
                "2.0" => Some(Evt::Evt2),
                "3.0" => Some(Evt::Evt3),
                // Read as EVT 2.0, another layout (EVT 2.1, EVT 4.0) is garbage: refuse it.
                v => return Err(unsupported(&format!("evt {v}"))),
            }
        }
        "geometry" => {
            if let Some((w, h)) = value.split_once('x') {
                header.size = Some((parse_dim(w)?, parse_dim(h)?));
            }
        }
        "format" => {
            let mut parts = value.split(';');
            match parts.next() {
                Some("EVT2") => header.evt = Some(Evt::Evt2),
                Some("EVT3") => header.evt = Some(Evt::Evt3),
                Some(tag) if tag.starts_with("EVT") => return Err(unsupported(tag)),
                _ => {}
            }
            let (mut w, mut h) = (None, None);
            for part in parts {
                match part.split_once('=') {
                    Some(("width", v)) => w = Some(parse_dim(v)?),
                    Some(("height", v)) => h = Some(parse_dim(v)?),
                    _ => {}
                }
            }
            if let (Some(w), Some(h)) = (w, h) {
                header.size = Some((w, h));
            }
        }
        "plugin_name" => *plugin_size = plugin_geometry(value),
        "v2ce_time_offset_us" => {
            // Any i64: the encoders write offsets down to i64::MIN and up to the last wrap
            // period below i64::MAX, and the decoders add them saturating.
            header.time_offset = value
                .parse::<i64>()
                .map_err(|_| format!("bad v2ce_time_offset_us '{value}'"))?
        }
        _ => {}
    }
    Ok(())
}

fn parse_dim(v: &str) -> std::result::Result<u16, String> {
    match v.trim().parse::<u16>() {
        Ok(d) if d > 0 => Ok(d),
        _ => Err(format!("bad sensor dimension '{v}'")),
    }
}

/// Sensor sizes of Prophesee cameras whose files predate the `geometry` line.
fn plugin_geometry(plugin: &str) -> Option<(u16, u16)> {
    if plugin.contains("gen41") || plugin.contains("imx636") {
        Some((1280, 720))
    } else if plugin.contains("gen31") || plugin.contains("gen3") {
        Some((640, 480))
    } else if plugin.contains("genx320") {
        Some((320, 320))
    } else {
        None
    }
}

/// The multiple of the format's wrap period at or below `t`, written as the time offset.
pub fn time_offset_for(evt: Evt, first_t: i64) -> i64 {
    let period = 1i64 << evt.time_bits();
    first_t.div_euclid(period) * period
}

/// Writes a header that both our decoder and other readers understand. Its length is a
/// multiple of 4 bytes (a `% v2ce` line pads it), so the words after it are aligned in the
/// file: a writer killed mid-write leaves a file cut at a page boundary (the kernel stops a
/// write between pages on a fatal signal), which is then a whole number of words.
pub fn write_header(
    w: &mut impl Write,
    evt: Evt,
    width: u16,
    height: u16,
    time_offset: i64,
) -> std::io::Result<()> {
    let v = evt.version();
    let tag = match evt {
        Evt::Evt2 => "EVT2",
        Evt::Evt3 => "EVT3",
    };
    let mut text = format!(
        "% evt {v}\n% format {tag};height={height};width={width}\n% geometry {width}x{height}\n"
    );
    if time_offset != 0 {
        text.push_str(&format!("% v2ce_time_offset_us {time_offset}\n"));
    }
    const PAD: &str = "% v2ce";
    const END: &str = "% end\n";
    let spaces = (4 - (text.len() + PAD.len() + 1 + END.len()) % 4) % 4;
    text.push_str(PAD);
    text.push_str(&" ".repeat(spaces));
    text.push('\n');
    text.push_str(END);
    w.write_all(text.as_bytes())
}

/// The header an encoder writes just before its first event, when the time offset is known.
#[derive(Debug, Clone)]
pub struct LazyHeader {
    evt: Evt,
    /// Sensor width.
    pub width: u16,
    /// Sensor height.
    pub height: u16,
    offset: Option<i64>,
}

impl LazyHeader {
    /// A header for `evt` and a `width x height` sensor (checked).
    pub fn new(evt: Evt, width: u16, height: u16) -> Result<Self> {
        check_size(evt, width, height)?;
        Ok(LazyHeader {
            evt,
            width,
            height,
            offset: None,
        })
    }

    /// The time offset, writing the header first if it has not been written yet.
    pub fn offset(&mut self, w: &mut impl Write, first_t: i64) -> std::io::Result<i64> {
        if let Some(offset) = self.offset {
            return Ok(offset);
        }
        let offset = time_offset_for(self.evt, first_t);
        write_header(w, self.evt, self.width, self.height, offset)?;
        self.offset = Some(offset);
        Ok(offset)
    }
}

/// Checks a sensor size against the format's coordinate bits (11 for both formats).
pub fn check_size(evt: Evt, width: u16, height: u16) -> Result<()> {
    if width == 0 || height == 0 || width > 2048 || height > 2048 {
        return Err(Error::invalid(
            "sensor size",
            format!(
                "EVT {} holds 1 to 2048 columns and rows; {width} x {height} does not fit",
                evt.version()
            ),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &[u8]) -> Header {
        read_header(&mut std::io::BufReader::new(text)).unwrap()
    }

    #[test]
    fn headers_old_and_new() {
        let h = parse(b"% evt 3.0\n% format EVT3;height=720;width=1280\n% end\n\x00\x80");
        assert_eq!(
            (h.evt, h.size, h.time_offset),
            (Some(Evt::Evt3), Some((1280, 720)), 0)
        );
        let h = parse(b"% Date 2020\n% evt 3.0\n% plugin_name hal_plugin_gen41_evk3\n\x00\x80");
        assert_eq!(
            (h.evt, h.size, h.lines.len()),
            (Some(Evt::Evt3), Some((1280, 720)), 3)
        );
        let h = parse(b"% geometry 640x480\n% v2ce_time_offset_us 17179869184\n% end\n");
        assert_eq!((h.size, h.time_offset), (Some((640, 480)), 1 << 34));
        let mut out = Vec::new();
        write_header(&mut out, Evt::Evt2, 346, 260, 5 << 34).unwrap();
        let h = parse(&out);
        assert_eq!(
            (h.evt, h.size, h.time_offset),
            (Some(Evt::Evt2), Some((346, 260)), 5 << 34)
        );
    }

    /// Whatever the size and offset, the header is a whole number of 4-byte words and reads
    /// back: the events after it are aligned in the file.
    #[test]
    fn headers_we_write_end_on_a_word_boundary() {
        for evt in [Evt::Evt2, Evt::Evt3] {
            for (w, h) in [
                (1u16, 1u16),
                (346, 260),
                (640, 480),
                (1280, 720),
                (65535, 9),
            ] {
                for offset in [0i64, 1 << 34, 123 << 34] {
                    let mut out = Vec::new();
                    write_header(&mut out, evt, w, h, offset).unwrap();
                    assert_eq!(out.len() % 4, 0, "{evt:?} {w}x{h} {offset}");
                    let back = parse(&out);
                    assert_eq!(
                        (back.evt, back.size, back.time_offset),
                        (Some(evt), Some((w, h)), offset)
                    );
                }
            }
        }
    }

    #[test]
    fn bad_headers_are_errors() {
        let r = |b: &[u8]| read_header(&mut std::io::BufReader::new(b));
        assert!(r(b"% geometry 0x480\n").is_err());
        assert!(r(b"% format EVT3;height=99999;width=1\n").is_err());
        assert!(r(b"% v2ce_time_offset_us abc\n").is_err());
        // Another word layout is refused, not read as EVT 2.0.
        for h in [
            &b"% evt 2.1\n"[..],
            b"% evt 4.0\n",
            b"% format EVT21;height=2;width=2\n",
        ] {
            let err = r(h).unwrap_err().to_string();
            assert!(err.contains("not supported"), "{err}");
        }
        let long = vec![b'%'; MAX_HEADER_BYTES as usize + 10];
        assert!(r(&long).is_err());
    }

    #[test]
    fn offsets_are_multiples_of_the_period() {
        assert_eq!(time_offset_for(Evt::Evt3, (1 << 24) * 3 + 5), (1 << 24) * 3);
        assert_eq!(time_offset_for(Evt::Evt2, 5), 0);
        assert_eq!(time_offset_for(Evt::Evt2, -1), -(1 << 34));
    }
}
