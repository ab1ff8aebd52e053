//! CSV events: a header line `t_us,x,y,on`, then one event per line with `on` = 1 or 0.
//!
//! Read by the header's column names, in any order, so the files other tools write read too
//! (`t_us,x,y,p`, `timestamp,x,y,polarity`, `t,x,y,p` with times in seconds): see [`Layout`].
//! Without a header the columns are `t_us,x,y,on`. Written as `t_us,x,y,on`.

use std::io::{BufRead, Write};
use std::path::Path;

use super::{EventDecoder, EventEncoder};
use crate::error::{Error, Result};
use crate::event::Event;

/// The header line.
pub const HEADER: &str = "t_us,x,y,on";

/// The longest line accepted, in bytes.
const MAX_LINE: u64 = 4096;

/// Writes events as CSV rows (no header) to `w`.
pub fn write_rows(w: &mut impl Write, events: &[Event]) -> std::io::Result<()> {
    let mut ints = itoa::Buffer::new();
    let mut line = Vec::with_capacity(48);
    for e in events {
        line.clear();
        line.extend_from_slice(ints.format(e.t).as_bytes());
        line.push(b',');
        line.extend_from_slice(ints.format(e.x).as_bytes());
        line.push(b',');
        line.extend_from_slice(ints.format(e.y).as_bytes());
        line.extend_from_slice(if e.on { b",1\n" } else { b",0\n" });
        w.write_all(&line)?;
    }
    Ok(())
}

/// Writes the header and events as CSV to `w`.
pub fn write_to(mut w: impl Write, events: &[Event]) -> std::io::Result<()> {
    writeln!(w, "{HEADER}")?;
    write_rows(&mut w, events)?;
    w.flush()
}

/// Writes events to a CSV file.
pub fn write(path: &Path, events: &[Event]) -> Result<()> {
    let file = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    write_to(std::io::BufWriter::new(file), events).map_err(|e| Error::io(path, e))
}

/// The names a header may give each column (compared without case): time in microseconds,
/// time in seconds, column, row, polarity.
const TIME_US: &[&str] = &[
    "t_us",
    "t",
    "ts",
    "timestamp",
    "time",
    "timestamp_us",
    "time_us",
];
const TIME_S: &[&str] = &["t_s", "timestamp_s", "time_s", "seconds", "t_sec"];
const X: &[&str] = &["x"];
const Y: &[&str] = &["y"];
const POLARITY: &[&str] = &["on", "p", "pol", "polarity"];

/// Where each quantity is in a line, from the header's names (see the consts above; other
/// columns are ignored), and the time's unit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Layout {
    t: usize,
    x: usize,
    y: usize,
    p: usize,
    /// The number of columns a line has.
    columns: usize,
    /// Times in seconds: the header says so, or (`None` until the first line) its values are
    /// fractional.
    seconds: Option<bool>,
}

impl Default for Layout {
    /// The project's own columns, `t_us,x,y,on`.
    fn default() -> Self {
        Layout {
            t: 0,
            x: 1,
            y: 2,
            p: 3,
            columns: 4,
            seconds: Some(false),
        }
    }
}

impl Layout {
    /// The layout a header line names; `None` for a line that is not a header (its first
    /// field is a number: data without a header, read as `t_us,x,y,on`); an error for a header
    /// that lacks a quantity, listing what is accepted.
    pub fn from_header(line: &str) -> Result<Option<Layout>> {
        let names: Vec<String> = line
            .split(',')
            .map(|n| n.trim().trim_matches('"').to_ascii_lowercase())
            .collect();
        if names.first().is_some_and(|n| n.parse::<f64>().is_ok()) {
            return Ok(None);
        }
        let find = |accepted: &[&str]| names.iter().position(|n| accepted.contains(&n.as_str()));
        let (t, seconds) = match (find(TIME_US), find(TIME_S)) {
            (Some(t), _) => (
                Some(t),
                if names[t] == "t_us" {
                    Some(false)
                } else {
                    None
                },
            ),
            (None, Some(t)) => (Some(t), Some(true)),
            (None, None) => (None, None),
        };
        match (t, find(X), find(Y), find(POLARITY)) {
            (Some(t), Some(x), Some(y), Some(p)) => Ok(Some(Layout {
                t,
                x,
                y,
                p,
                columns: names.len(),
                seconds,
            })),
            _ => Err(Error::invalid(
                "CSV header",
                format!(
                    "'{}' does not name a time, x, y and polarity column (accepted, in any \
                     order: time in us {}, in s {}; {}; {}; polarity {}, with values 1/0, \
                     1/-1 or true/false)",
                    line.escape_debug(),
                    TIME_US.join("/"),
                    TIME_S.join("/"),
                    X.join("/"),
                    Y.join("/"),
                    POLARITY.join("/")
                ),
            )),
        }
    }

    /// Parses one data line (`None` where it does not hold an event in this layout); the
    /// first one decides whether a time column of unstated unit is in seconds.
    pub fn parse(&mut self, line: &str) -> Option<Event> {
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        if f.len() != self.columns {
            return None;
        }
        let time = f[self.t];
        let seconds = *self
            .seconds
            .get_or_insert_with(|| time.contains(['.', 'e', 'E']));
        let t = if seconds {
            let s: f64 = time.parse().ok()?;
            let us = (s * 1e6).round();
            // Within the times the program takes (checked again where they enter).
            if !us.is_finite() || us.abs() > crate::time::MAX_ABS_US as f64 {
                return None;
            }
            us as i64
        } else {
            time.parse().ok()?
        };
        let x = f[self.x].parse().ok()?;
        let y = f[self.y].parse().ok()?;
        let on = match f[self.p].to_ascii_lowercase().as_str() {
            "1" | "true" => true,
            "0" | "-1" | "false" => false,
            _ => return None,
        };
        Some(Event::new(t, x, y, on))
    }
}

/// Whether `last`, a file's last line without its newline, holds a whole event in the columns
/// the file's first line `first` names (a writer killed mid-line leaves one that does not);
/// `data`, its first data line, settles the unit of a time column that does not state one.
pub fn is_whole_last_line(first: &str, data: &str, last: &str) -> bool {
    let mut layout = match Layout::from_header(first.trim()) {
        Ok(Some(layout)) => layout,
        Ok(None) => Layout::default(),
        Err(_) => return false,
    };
    let _ = layout.parse(data.trim());
    let last = last.trim();
    !last.is_empty() && layout.parse(last).is_some()
}

/// Streams events out of CSV text (the header line is optional).
pub struct Decoder<R> {
    reader: R,
    line: u64,
    buf: Vec<u8>,
    /// The columns, from the header (the project's own without one).
    layout: Layout,
}

impl<R: BufRead> Decoder<R> {
    /// A decoder over CSV text.
    pub fn new(reader: R) -> Self {
        Decoder {
            reader,
            line: 0,
            buf: Vec::new(),
            layout: Layout::default(),
        }
    }
}

impl<R: BufRead> EventDecoder for Decoder<R> {
    /// CSV has no sensor size.
    fn size(&self) -> Option<(u16, u16)> {
        None
    }

    fn read_events(&mut self, out: &mut Vec<Event>, max: usize) -> Result<usize> {
        let start = out.len();
        let bad = |line: u64, m: String| Error::invalid("CSV stream", format!("line {line}: {m}"));
        while out.len() - start < max {
            self.buf.clear();
            let n = std::io::Read::take(&mut self.reader, MAX_LINE)
                .read_until(b'\n', &mut self.buf)
                .map_err(|e| bad(self.line + 1, e.to_string()))?;
            if n == 0 {
                break;
            }
            self.line += 1;
            if n as u64 == MAX_LINE && self.buf.last() != Some(&b'\n') {
                return Err(bad(self.line, format!("longer than {MAX_LINE} bytes")));
            }
            // Only the input's last line can lack its newline.
            let last = self.buf.last() != Some(&b'\n');
            let text = std::str::from_utf8(&self.buf).map(str::trim);
            let event = match text {
                Ok("") => continue,
                Ok(t) if self.line == 1 => match Layout::from_header(t)? {
                    Some(layout) => {
                        self.layout = layout;
                        continue;
                    }
                    None => self.layout.parse(t).ok_or_else(|| {
                        bad(self.line, format!("not an event: '{}'", t.escape_debug()))
                    }),
                },
                Ok(t) => self.layout.parse(t).ok_or_else(|| {
                    bad(
                        self.line,
                        format!(
                            "not an event in the header's columns: '{}'",
                            t.escape_debug()
                        ),
                    )
                }),
                Err(_) => Err(bad(self.line, "not UTF-8".into())),
            };
            match event {
                Ok(e) => out.push(e),
                // A writer killed mid-write (SIGKILL, a power cut) leaves part of a line.
                Err(e) if last => {
                    tracing::warn!(
                        "{e}; the input ends inside this line (a truncated input), which is dropped"
                    );
                    break;
                }
                Err(e) => return Err(e),
            }
        }
        Ok(out.len() - start)
    }
}

/// Writes CSV: the header on creation, then one row per event.
pub struct Encoder<W: Write> {
    writer: W,
    /// The last event's time: events come in time order, as in every other format.
    last_t: i64,
}

impl<W: Write> Encoder<W> {
    /// Writes the header line.
    pub fn new(mut writer: W) -> Result<Self> {
        writeln!(writer, "{HEADER}").map_err(output_error)?;
        Ok(Encoder {
            writer,
            last_t: i64::MIN,
        })
    }
}

fn output_error(e: std::io::Error) -> Error {
    Error::invalid("CSV output", e.to_string())
}

impl<W: Write> EventEncoder for Encoder<W> {
    fn write(&mut self, events: &[Event]) -> Result<()> {
        // Refused before anything of the batch is written.
        let mut last_t = self.last_t;
        for e in events {
            if e.t < last_t {
                return Err(Error::invalid(
                    "event time",
                    format!("{} us comes before {last_t} us", e.t),
                ));
            }
            last_t = e.t;
        }
        write_rows(&mut self.writer, events).map_err(output_error)?;
        self.last_t = last_t;
        Ok(())
    }

    fn finish(&mut self) -> Result<()> {
        self.writer.flush().map_err(output_error)
    }

    fn flush(&mut self) -> Result<()> {
        self.writer.flush().map_err(output_error)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode(text: &str) -> Result<Vec<Event>> {
        let mut out = Vec::new();
        Decoder::new(text.as_bytes()).read_events(&mut out, usize::MAX)?;
        Ok(out)
    }

    /// Other tools' headers read by their names, in any order, times in seconds where the
    /// header says so or the values are fractional, polarity as 1/0, 1/-1 or true/false.
    #[test]
    fn columns_are_read_by_their_names() {
        let want = vec![Event::new(1500, 3, 4, true), Event::new(2500, 5, 6, false)];
        for text in [
            "t_us,x,y,on\n1500,3,4,1\n2500,5,6,0\n",
            "t_us,x,y,p\n1500,3,4,1\n2500,5,6,0\n",
            "timestamp,x,y,polarity\n1500,3,4,1\n2500,5,6,-1\n",
            "t,x,y,p\n0.0015,3,4,1\n0.0025,5,6,0\n",
            "p,y,x,t_s\ntrue,4,3,0.0015\nfalse,6,5,0.0025\n",
            "X, Y, T_US, Pol, extra\n3,4,1500,1,a\n5,6,2500,0,b\n",
            "\"timestamp\",\"x\",\"y\",\"p\"\n1500,3,4,1\n2500,5,6,0",
            "1500,3,4,1\n2500,5,6,0\n",
        ] {
            assert_eq!(decode(text).unwrap(), want, "{text}");
        }
        // A header without a polarity names what is accepted.
        let err = decode("t_us,x,y,brightness\n1,2,3,1\n")
            .unwrap_err()
            .to_string();
        assert!(err.contains("polarity") && err.contains("t_us"), "{err}");
        // A line that is not an event in the header's columns names its line.
        let err = decode("t_us,x,y,p\n1,2,3,1\n4,5,6\n7,8,9,1\n")
            .unwrap_err()
            .to_string();
        assert!(err.contains("line 3"), "{err}");
        // Seconds too large for the program's times are refused, not wrapped.
        assert!(decode("t_s,x,y,p\n1e300,1,1,1\n2,1,1,1\n").is_err());
    }

    #[test]
    fn round_trip_and_errors() {
        let dir = std::env::temp_dir().join(format!("v2ce-csv-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("e.csv");
        let events = vec![
            Event::new(-5, 1, 2, true),
            Event::new(1 << 40, 65535, 0, false),
            Event::new(i64::MAX, 0, 65535, false),
        ];
        write(&p, &events).unwrap();
        // Any i64 time is carried by a reader that only copies times (transcode)...
        let mut all = Vec::new();
        let mut d = super::super::open_verbatim(&p).unwrap();
        while d.read_events(&mut all, 1000).unwrap() > 0 {}
        assert_eq!(all, events);
        // ...and refused, clearly, by one that computes with them.
        let err = super::super::read_events(&p).unwrap_err().to_string();
        assert!(err.contains("out of range"), "{err}");
        write(&p, &events[..2]).unwrap();
        let back = super::super::read_events(&p).unwrap();
        assert_eq!(back.events.events(), &events[..2]);
        assert_eq!((back.width, back.height), (65535, 3));
        // Events out of time order are refused, within a batch and across batches, and
        // nothing of a refused batch is written.
        let mut enc = Encoder::new(Vec::new()).unwrap();
        assert!(enc.write(&[events[1], events[0]]).is_err());
        enc.write(&events[1..2]).unwrap();
        assert!(enc.write(&events[..1]).is_err());
        let text = String::from_utf8(enc.writer.clone()).unwrap();
        assert_eq!(text.lines().count(), 2, "{text}");
        std::fs::write(&p, "t_us,x,y,on\n1,2,3,1\n4,5,x,0\n").unwrap();
        let err = super::super::read_events(&p).unwrap_err().to_string();
        assert!(err.contains("line 3"), "{err}");
        // A last line cut short is dropped (with a warning); one that is whole is kept.
        std::fs::write(&p, "t_us,x,y,on\n1,2,3,1\n4,5,6,0\n2156").unwrap();
        let back = super::super::read_events(&p).unwrap();
        assert_eq!(back.events.len(), 2);
        std::fs::write(&p, "t_us,x,y,on\n1,2,3,1\n4,5,6,0").unwrap();
        let back = super::super::read_events(&p).unwrap();
        assert_eq!(back.events.len(), 2);
        std::fs::write(&p, "t_us,x,y,on\n1,2,3,1\n4,5,x,0\n7,8,9,1").unwrap();
        let err = super::super::read_events(&p).unwrap_err().to_string();
        assert!(err.contains("line 3"), "{err}");
        std::fs::write(&p, vec![b'1'; 10_000]).unwrap();
        let err = super::super::read_events(&p).unwrap_err().to_string();
        assert!(err.contains("longer than"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
