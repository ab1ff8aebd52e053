//! CSV events: a header line `t_us,x,y,on`, then one event per line with `on` = 1 or 0.

use std::io::{BufRead, BufReader, BufWriter, Write};
use std::path::Path;

use super::Recording;
use crate::error::{Error, Result};
use crate::event::Event;

/// The header line.
pub const HEADER: &str = "t_us,x,y,on";

/// Writes events as CSV rows (no header) to `w`.
pub fn write_rows(w: &mut impl Write, events: &[Event]) -> std::io::Result<()> {
    for e in events {
        writeln!(w, "{},{},{},{}", e.t, e.x, e.y, e.on as u8)?;
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
    write_to(BufWriter::new(file), events).map_err(|e| Error::io(path, e))
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

/// Reads a CSV event file (the header is optional).
pub fn read(path: &Path) -> Result<Recording> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut events = Vec::new();
    for (i, line) in BufReader::new(file).lines().enumerate() {
        let line = line.map_err(|e| Error::io(path, e))?;
        let line = line.trim();
        if line.is_empty() || (i == 0 && line == HEADER) {
            continue;
        }
        events.push(parse_line(line).ok_or_else(|| {
            Error::format(
                path,
                format!("line {}: expected '{HEADER}' fields, got '{line}'", i + 1),
            )
        })?);
    }
    Ok(Recording::new(events, None))
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
        ];
        write(&p, &events).unwrap();
        let back = read(&p).unwrap();
        assert_eq!(back.events.events(), &events[..]);
        assert_eq!((back.width, back.height), (65535, 3));
        std::fs::write(&p, "t_us,x,y,on\n1,2,3,1\n4,5,x,0\n").unwrap();
        let err = read(&p).unwrap_err().to_string();
        assert!(err.contains("line 3"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
