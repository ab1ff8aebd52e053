//! The text layout of the IJRR Event Camera Dataset: `events.txt` holds one event per line as
//! `t_seconds x y polarity` (polarity 1 = ON, 0 = OFF) and `images.txt` holds `t_seconds path`
//! per frame. Seconds are parsed as decimals into whole microseconds (rounded), never through an
//! `f32`.

use std::io::{BufRead, BufReader};
use std::path::Path;

use super::EventDecoder;
use crate::error::{Error, Result};
use crate::event::Event;

/// Parses a decimal number of seconds into microseconds, rounding below 1 us.
pub fn parse_seconds_us(s: &str) -> Option<i64> {
    if s.contains(['e', 'E']) {
        let v: f64 = s.parse().ok()?;
        let us = (v * 1e6).round();
        return (us.is_finite() && us.abs() < 9e18).then_some(us as i64);
    }
    let (neg, digits) = match s.strip_prefix('-') {
        Some(rest) => (true, rest),
        None => (false, s.strip_prefix('+').unwrap_or(s)),
    };
    let (int, frac) = digits.split_once('.').unwrap_or((digits, ""));
    if (int.is_empty() && frac.is_empty())
        || !int.bytes().all(|b| b.is_ascii_digit())
        || !frac.bytes().all(|b| b.is_ascii_digit())
    {
        return None;
    }
    let whole: i64 = if int.is_empty() { 0 } else { int.parse().ok()? };
    let mut micros = 0i64;
    for (i, b) in frac.bytes().take(6).enumerate() {
        micros += (b - b'0') as i64 * 10i64.pow(5 - i as u32);
    }
    if frac.len() > 6 && frac.as_bytes()[6] >= b'5' {
        micros += 1;
    }
    let us = whole.checked_mul(1_000_000)?.checked_add(micros)?;
    Some(if neg { -us } else { us })
}

/// Microseconds as a decimal number of seconds, exactly (six decimals): what
/// [`parse_seconds_us`] reads back.
pub fn format_seconds_us(t: i64) -> String {
    let sign = if t < 0 { "-" } else { "" };
    let a = t.unsigned_abs();
    format!("{sign}{}.{:06}", a / 1_000_000, a % 1_000_000)
}

/// Whether `s` reads as a number of seconds, in range or not (NaN and infinities included):
/// what tells a time field from a word, so that a frame list with a time out of range is still
/// recognised as one, and its error names the line.
pub fn is_number(s: &str) -> bool {
    parse_seconds_us(s).is_some() || s.parse::<f64>().is_ok()
}

/// A time field in seconds as microseconds checked to lie within `±`[`crate::time::MAX_ABS_US`]:
/// `None` where `s` is no number (the caller says what it expected), an error naming the range
/// (as [`crate::time::check`] words it, under `what`) where `s` is a number out of it,
/// infinities included (NaN is no number).
pub fn seconds_in_range(what: &'static str, s: &str) -> Option<Result<i64>> {
    if let Some(t) = parse_seconds_us(s) {
        return Some(crate::time::check(what, t));
    }
    if s.parse::<f64>().ok()?.is_nan() {
        return None;
    }
    // Past what an i64 of microseconds holds: the seconds as written.
    Some(Err(crate::time::out_of_range(what, &format!("{s} s"))))
}

/// The longest line accepted, in bytes.
const MAX_LINE: u64 = 4096;

/// Reads lines of at most [`MAX_LINE`] bytes, skipping blank and `#` lines; hands each line's
/// number and whitespace-separated fields to the caller.
struct Lines<R> {
    reader: R,
    line: u64,
    buf: Vec<u8>,
}

impl<R: BufRead> Lines<R> {
    fn new(reader: R) -> Self {
        Lines {
            reader,
            line: 0,
            buf: Vec::new(),
        }
    }

    /// The next line with fields, or `None` at the end of the input.
    fn next_fields(&mut self) -> std::result::Result<Option<(u64, Vec<&str>)>, String> {
        loop {
            self.buf.clear();
            let n = std::io::Read::take(&mut self.reader, MAX_LINE)
                .read_until(b'\n', &mut self.buf)
                .map_err(|e| format!("line {}: {e}", self.line + 1))?;
            if n == 0 {
                return Ok(None);
            }
            self.line += 1;
            if n as u64 == MAX_LINE && self.buf.last() != Some(&b'\n') {
                return Err(format!("line {}: longer than {MAX_LINE} bytes", self.line));
            }
            let text = std::str::from_utf8(&self.buf)
                .map_err(|_| format!("line {}: not UTF-8", self.line))?;
            let first = text.split_whitespace().next();
            if first.is_some_and(|f| !f.starts_with('#')) {
                break;
            }
        }
        // Borrow again outside the loop: the fields live as long as the buffer.
        let text = std::str::from_utf8(&self.buf).unwrap_or_default();
        Ok(Some((self.line, text.split_whitespace().collect())))
    }
}

/// Streams the events of an IJRR `events.txt` (one line at a time: memory stays flat however
/// long the file). The text has no sensor size; times come in the file's order.
pub struct Decoder<R> {
    lines: Lines<R>,
}

impl<R: BufRead> Decoder<R> {
    /// A decoder over `events.txt` text.
    pub fn new(reader: R) -> Self {
        Decoder {
            lines: Lines::new(reader),
        }
    }
}

impl<R: BufRead> EventDecoder for Decoder<R> {
    /// IJRR text has no sensor size.
    fn size(&self) -> Option<(u16, u16)> {
        None
    }

    fn read_events(&mut self, out: &mut Vec<Event>, max: usize) -> Result<usize> {
        let start = out.len();
        let bad = |m: String| Error::invalid("IJRR events", m);
        while out.len() - start < max {
            let Some((line, f)) = self.lines.next_fields().map_err(bad)? else {
                break;
            };
            let wrong = || {
                bad(format!(
                    "line {line}: expected 't_seconds x y polarity', got '{}'",
                    f.join(" ").escape_debug()
                ))
            };
            if f.len() != 4 {
                return Err(wrong());
            }
            let t = parse_seconds_us(f[0]).ok_or_else(wrong)?;
            let x: u16 = f[1].parse().map_err(|_| wrong())?;
            let y: u16 = f[2].parse().map_err(|_| wrong())?;
            let on = match f[3] {
                "1" => true,
                "0" | "-1" => false,
                _ => return Err(wrong()),
            };
            out.push(Event::new(t, x, y, on));
        }
        Ok(out.len() - start)
    }
}

/// Reads the frame times of an IJRR `images.txt`, each checked to be in range
/// ([`crate::time`]; an error names the file and line).
pub fn read_frame_times(path: &Path) -> Result<Vec<i64>> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut lines = Lines::new(BufReader::new(file));
    let mut times = Vec::new();
    while let Some((line, f)) = lines.next_fields().map_err(|m| Error::format(path, m))? {
        let t = f
            .first()
            .and_then(|s| seconds_in_range("frame time", s))
            .ok_or_else(|| Error::format(path, format!("line {line}: expected 't_seconds path'")))?
            .map_err(|e| Error::format(path, format!("line {line}: {e}")))?;
        times.push(t);
    }
    Ok(times)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seconds_parse_exactly() {
        assert_eq!(parse_seconds_us("0.003903"), Some(3903));
        assert_eq!(parse_seconds_us("2.363848"), Some(2_363_848));
        assert_eq!(
            parse_seconds_us("1589163147.364965"),
            Some(1_589_163_147_364_965)
        );
        assert_eq!(parse_seconds_us("0.0000015"), Some(2));
        assert_eq!(parse_seconds_us("-1.5"), Some(-1_500_000));
        assert_eq!(parse_seconds_us("12"), Some(12_000_000));
        for t in [
            0,
            1,
            -1,
            -500_000,
            1_605_116_853_975_736,
            1 << 61,
            -(1 << 61),
        ] {
            assert_eq!(parse_seconds_us(&format_seconds_us(t)), Some(t), "{t}");
        }
        assert_eq!(parse_seconds_us("1e-3"), Some(1000));
        for bad in ["", ".", "a", "1.2.3", "1e999", "--1"] {
            assert_eq!(parse_seconds_us(bad), None, "{bad}");
        }
    }

    #[test]
    fn frame_times_out_of_range_name_the_line_and_the_range() {
        assert_eq!(seconds_in_range("t", "1.5").unwrap().unwrap(), 1_500_000);
        assert!(seconds_in_range("t", "a").is_none());
        assert!(seconds_in_range("t", "nan").is_none());
        assert!(is_number("nan") && is_number("-9223372036854") && !is_number("a.png"));
        let bound = crate::time::MAX_ABS_US.to_string();
        for s in [
            "-9223372036854",
            "9223372036854.775807",
            "1e300",
            "inf",
            "2305843009213.693953",
        ] {
            let e = seconds_in_range("frame time", s)
                .unwrap()
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("frame time") && e.contains("out of range") && e.contains(&bound),
                "{s}: {e}"
            );
        }
        let dir = std::env::temp_dir().join(format!("v2ce-ijrr-range-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let list = dir.join("images.txt");
        std::fs::write(&list, "0 a.png\n\n1e300 b.png\n").unwrap();
        let e = read_frame_times(&list).unwrap_err().to_string();
        assert!(
            e.contains("images.txt")
                && e.contains("line 3")
                && e.contains("1e300 s is out of range")
                && e.contains(&bound),
            "{e}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn events_stream_in_chunks() {
        let text = "# t x y p\n0.000001 1 2 1\n\n0.000002 3 4 0\n0.5 5 6 -1\n";
        let mut d = Decoder::new(text.as_bytes());
        let mut out = Vec::new();
        assert_eq!(d.read_events(&mut out, 2).unwrap(), 2);
        assert_eq!(d.read_events(&mut out, 2).unwrap(), 1);
        assert_eq!(d.read_events(&mut out, 2).unwrap(), 0);
        assert_eq!(
            out,
            [
                Event::new(1, 1, 2, true),
                Event::new(2, 3, 4, false),
                Event::new(500_000, 5, 6, false)
            ]
        );
        let err = Decoder::new("0.1 1 2 1\n0.2 1 2\n".as_bytes())
            .read_events(&mut Vec::new(), 10)
            .unwrap_err()
            .to_string();
        assert!(err.contains("line 2"), "{err}");
        let long = vec![b'1'; 10_000];
        let err = Decoder::new(&long[..])
            .read_events(&mut Vec::new(), 10)
            .unwrap_err()
            .to_string();
        assert!(err.contains("longer than"), "{err}");
    }
}
