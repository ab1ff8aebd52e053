//! The text layout of the IJRR Event Camera Dataset: `events.txt` holds one event per line as
//! `t_seconds x y polarity` (polarity 1 = ON, 0 = OFF) and `images.txt` holds `t_seconds path`
//! per frame. Seconds are parsed as decimals into whole microseconds (rounded), never through an
//! `f32`.

use std::io::{BufRead, BufReader};
use std::path::Path;

use super::Recording;
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

fn for_each_line(path: &Path, mut f: impl FnMut(usize, &[&str]) -> Result<()>) -> Result<()> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    for (i, line) in BufReader::new(file).lines().enumerate() {
        let line = line.map_err(|e| Error::io(path, e))?;
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.is_empty() || fields[0].starts_with('#') {
            continue;
        }
        f(i + 1, &fields)?;
    }
    Ok(())
}

/// Reads an IJRR `events.txt`.
pub fn read_events(path: &Path) -> Result<Recording> {
    let mut events = Vec::new();
    for_each_line(path, |line, f| {
        let bad = || {
            Error::format(
                path,
                format!(
                    "line {line}: expected 't_seconds x y polarity', got '{}'",
                    f.join(" ")
                ),
            )
        };
        if f.len() != 4 {
            return Err(bad());
        }
        let t = parse_seconds_us(f[0]).ok_or_else(bad)?;
        let x: u16 = f[1].parse().map_err(|_| bad())?;
        let y: u16 = f[2].parse().map_err(|_| bad())?;
        let on = match f[3] {
            "1" => true,
            "0" | "-1" => false,
            _ => return Err(bad()),
        };
        events.push(Event::new(t, x, y, on));
        Ok(())
    })?;
    Ok(Recording::new(events, None))
}

/// Reads the frame times of an IJRR `images.txt`.
pub fn read_frame_times(path: &Path) -> Result<Vec<i64>> {
    let mut times = Vec::new();
    for_each_line(path, |line, f| {
        let t = f.first().and_then(|s| parse_seconds_us(s)).ok_or_else(|| {
            Error::format(path, format!("line {line}: expected 't_seconds path'"))
        })?;
        times.push(t);
        Ok(())
    })?;
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
        assert_eq!(parse_seconds_us("1e-3"), Some(1000));
        for bad in ["", ".", "a", "1.2.3", "1e999", "--1"] {
            assert_eq!(parse_seconds_us(bad), None, "{bad}");
        }
    }
}
