//! CSV events: a header line `t_us,x,y,on`, then one event per line with `on` = 1 or 0.

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

/// Parses one data line.
fn parse_line(line: &str) -> Option<Event> {
    let mut f = line.split(',').map(str::trim);
    let t = f.next()?.parse().ok()?;
    let x = f.next()?.parse().ok()?;
    let y = f.next()?.parse().ok()?;
    let on = match f.next()? {
        "1" => true,
        "0" => false,
        _ => return None,
    };
    f.next().is_none().then_some(Event::new(t, x, y, on))
}

/// Streams events out of CSV text (the header line is optional).
pub struct Decoder<R> {
    reader: R,
    line: u64,
    buf: Vec<u8>,
}

impl<R: BufRead> Decoder<R> {
    /// A decoder over CSV text.
    pub fn new(reader: R) -> Self {
        Decoder {
            reader,
            line: 0,
            buf: Vec::new(),
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
                Ok(t) if t.is_empty() || (self.line == 1 && t == HEADER) => continue,
                Ok(t) => parse_line(t).ok_or_else(|| {
                    bad(
                        self.line,
                        format!("expected '{HEADER}' fields, got '{}'", t.escape_debug()),
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
