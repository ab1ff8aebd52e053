//! Streaming conversion between event file formats, and a summary of an event file.
//!
//! Both read the input in chunks of [`CHUNK`] events, so memory stays flat for files of any
//! length (an AEDAT 4.0 output keeps one 32-byte data-table entry per 4096 events).

use std::path::Path;

use crate::error::{Error, Result};
use crate::event::Event;
use crate::format::{self, Format};

/// Events read per step.
pub const CHUNK: usize = 1 << 16;

/// What [`transcode`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TranscodeReport {
    /// Events written.
    pub events: u64,
    /// The sensor size written.
    pub size: (u16, u16),
}

/// The sensor size to write: `size`, else the input's, else one more than the largest column
/// and row in the input (found by a first streaming pass).
fn output_size(input: &Path, size: Option<(u16, u16)>) -> Result<(u16, u16)> {
    match size.or(format::open_verbatim(input)?.size()) {
        Some(s) => Ok(s),
        // The pass that writes reads the same input and gives its warnings: this one keeps quiet.
        None => Ok(tracing::subscriber::with_default(Quiet, || summarize(input))?.extent),
    }
}

/// A subscriber that records nothing. Unlike `tracing`'s own `NoSubscriber`, it leaves every
/// callsite asking each time, so a warning first seen here still reaches the real subscriber.
struct Quiet;

impl tracing::Subscriber for Quiet {
    fn register_callsite(
        &self,
        _: &'static tracing::Metadata<'static>,
    ) -> tracing::subscriber::Interest {
        tracing::subscriber::Interest::sometimes()
    }
    fn enabled(&self, _: &tracing::Metadata<'_>) -> bool {
        false
    }
    fn new_span(&self, _: &tracing::span::Attributes<'_>) -> tracing::span::Id {
        tracing::span::Id::from_u64(1)
    }
    fn record(&self, _: &tracing::span::Id, _: &tracing::span::Record<'_>) {}
    fn record_follows_from(&self, _: &tracing::span::Id, _: &tracing::span::Id) {}
    fn event(&self, _: &tracing::Event<'_>) {}
    fn enter(&self, _: &tracing::span::Id) {}
    fn exit(&self, _: &tracing::span::Id) {}
}

/// Converts `input` to `output` in `format`, streaming. `size` overrides the sensor size. The
/// output gets its name only when complete (see [`format::PartialOutput`]).
pub fn transcode(
    input: &Path,
    output: &Path,
    format: Format,
    size: Option<(u16, u16)>,
) -> Result<TranscodeReport> {
    if crate::file_id::same_file(input, output) {
        return Err(Error::invalid(
            "output file",
            format!("{} is the input file", output.display()),
        ));
    }
    let size = output_size(input, size)?;
    let mut decoder = format::open_verbatim(input)?;
    let out = format::PartialOutput::new(output);
    let report = write_all(input, decoder.as_mut(), out.writing(), format, size)
        .and_then(|r| out.commit().map(|()| r));
    report.map_err(|e| out.explain(e))
}

/// Writes the events of `decoder` (reading `input`) to `output` in `format` for a `size`
/// sensor, checking their order and range first (an error names the input's event).
pub(crate) fn write_all(
    input: &Path,
    decoder: &mut dyn format::EventDecoder,
    output: &Path,
    format: Format,
    size: (u16, u16),
) -> Result<TranscodeReport> {
    let mut encoder = format::create(output, format, size.0, size.1)?;
    let mut buf = Vec::with_capacity(CHUNK + 16);
    let mut events = 0u64;
    let mut last_t = i64::MIN;
    loop {
        buf.clear();
        if decoder.read_events(&mut buf, CHUNK)? == 0 {
            break;
        }
        // What the input gets wrong (time going back, a pixel outside its own sensor) is the
        // input's fault: say so, with the event's index, before the encoder would blame the
        // output.
        for (i, e) in buf.iter().enumerate() {
            format::check_event(e, last_t, size.0, size.1).map_err(|err| {
                Error::format(input, format!("event {}: {err}", events + i as u64))
            })?;
            last_t = e.t;
        }
        encoder.write(&buf)?;
        events += buf.len() as u64;
    }
    encoder.finish()?;
    Ok(TranscodeReport { events, size })
}

/// A summary of an event file.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Summary {
    /// Sensor width and height from the file, when it says.
    pub size: Option<(u16, u16)>,
    /// One more than the largest column and row seen.
    pub extent: (u16, u16),
    /// Number of events.
    pub events: u64,
    /// ON events.
    pub on: u64,
    /// First and last event time (us), when there are events.
    pub first_t: Option<i64>,
    /// Last event time (us).
    pub last_t: Option<i64>,
    /// The file's format: `AEDAT 4.0`, `EVT 2.0`, `EVT 3.0`, `CSV`, `V2CE toolbox .npz`,
    /// `HDF5 (DSEC layout)`, `rosbag2 MCAP (EventPacket, EVT 3.0)`, `IJRR text`.
    pub format: String,
    /// Packet compression (AEDAT 4.0), or the HDF5 filters of `events/t` (`shuffle+deflate`).
    pub compression: Option<String>,
    /// The time a RAW file adds to every decoded time, us (its readers differ on this, so the
    /// times can be compared with theirs), or an HDF5 file's `t_offset`.
    pub time_offset_us: Option<i64>,
    /// The first and last events in file order, as `[t, x, y, on]`.
    pub first_event: Option<[i64; 4]>,
    /// See `first_event`.
    pub last_event: Option<[i64; 4]>,
}

/// The format, compression and RAW time offset of an event file, from its header.
fn describe_file(path: &Path) -> Result<(String, Option<String>, Option<i64>)> {
    use std::io::BufReader;
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut reader = BufReader::new(file);
    let wrap = |e: Error| Error::format(path, e.to_string());
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    Ok(match ext.as_str() {
        "aedat4" => {
            let r = format::aedat4::Reader::new_file(reader).map_err(wrap)?;
            (
                "AEDAT 4.0".into(),
                Some(r.header().compression.xml_name().into()),
                None,
            )
        }
        "raw" => {
            let h = format::raw::read_header(&mut reader).map_err(wrap)?;
            let name = match h.evt {
                Some(format::raw::Evt::Evt3) => "EVT 3.0",
                Some(format::raw::Evt::Evt2) => "EVT 2.0",
                None => "EVT 2.0 (no % evt line)",
            };
            (name.into(), None, Some(h.time_offset))
        }
        "csv" => ("CSV".into(), None, None),
        "npz" => ("V2CE toolbox .npz".into(), None, None),
        "h5" | "hdf5" => {
            let d = format::hdf5::Decoder::open(path).map_err(wrap)?;
            (
                "HDF5 (DSEC layout)".into(),
                Some(d.compression().into()),
                Some(d.t_offset()),
            )
        }
        "mcap" => ("rosbag2 MCAP (EventPacket, EVT 3.0)".into(), None, None),
        _ => ("IJRR text".into(), None, None),
    })
}

impl Summary {
    /// `last_t - first_t` in us (0 without events).
    pub fn span_us(&self) -> i64 {
        match (self.first_t, self.last_t) {
            (Some(a), Some(b)) => b.saturating_sub(a),
            _ => 0,
        }
    }

    /// Mean event rate over the span, in events per second (0 for a span of 0).
    pub fn rate_hz(&self) -> f64 {
        let span = match (self.first_t, self.last_t) {
            (Some(a), Some(b)) => b as i128 - a as i128,
            _ => 0,
        };
        match span {
            0 => 0.0,
            s => self.events as f64 / (s as f64 * 1e-6),
        }
    }

    /// Share of ON events (0 without events).
    pub fn on_ratio(&self) -> f64 {
        if self.events == 0 {
            0.0
        } else {
            self.on as f64 / self.events as f64
        }
    }
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "format       {}", self.format)?;
        match &self.compression {
            Some(c) => writeln!(f, ", {c} compression")?,
            None => writeln!(f)?,
        }
        if let Some(o) = self.time_offset_us {
            writeln!(f, "time offset  {o} us (added to the file's event times)")?;
        }
        match self.size {
            Some((w, h)) => writeln!(f, "sensor size  {w} x {h}")?,
            None => writeln!(
                f,
                "sensor size  not in the file; events fit {} x {}",
                self.extent.0, self.extent.1
            )?,
        }
        writeln!(f, "events       {}", self.events)?;
        match (self.first_t, self.last_t) {
            // In i128: a span across the whole i64 range overflows i64.
            (Some(a), Some(b)) => writeln!(
                f,
                "time span    {:.6} s ({a} .. {b} us)",
                (b as i128 - a as i128) as f64 * 1e-6
            )?,
            _ => writeln!(f, "time span    -")?,
        }
        let row = |r: &Option<[i64; 4]>| {
            r.map_or("-".to_string(), |[t, x, y, on]| {
                format!(
                    "t {t} us, x {x}, y {y}, {}",
                    if on == 1 { "ON" } else { "OFF" }
                )
            })
        };
        writeln!(f, "first event  {}", row(&self.first_event))?;
        writeln!(f, "last event   {}", row(&self.last_event))?;
        writeln!(f, "event rate   {:.0} ev/s", self.rate_hz())?;
        write!(f, "ON ratio     {:.4}", self.on_ratio())
    }
}

/// Reads an event file through once and summarizes it.
pub fn summarize(path: &Path) -> Result<Summary> {
    let mut decoder = format::open_verbatim(path)?;
    let mut s = Summary {
        size: decoder.size(),
        extent: (0, 0),
        events: 0,
        on: 0,
        first_t: None,
        last_t: None,
        format: String::new(),
        compression: None,
        time_offset_us: None,
        first_event: None,
        last_event: None,
    };
    (s.format, s.compression, s.time_offset_us) = describe_file(path)?;
    let as_row = |e: &Event| [e.t, e.x as i64, e.y as i64, e.on as i64];
    let mut buf: Vec<Event> = Vec::with_capacity(CHUNK + 16);
    loop {
        buf.clear();
        if decoder.read_events(&mut buf, CHUNK)? == 0 {
            break;
        }
        if s.first_event.is_none() {
            s.first_event = buf.first().map(as_row);
        }
        s.last_event = buf.last().map(as_row);
        for e in &buf {
            s.extent.0 = s.extent.0.max(e.x.saturating_add(1));
            s.extent.1 = s.extent.1.max(e.y.saturating_add(1));
            s.on += e.on as u64;
            s.first_t = Some(s.first_t.map_or(e.t, |t| t.min(e.t)));
            s.last_t = Some(s.last_t.map_or(e.t, |t| t.max(e.t)));
        }
        s.events += buf.len() as u64;
    }
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::csv;

    #[test]
    fn transcode_chain_and_summary() {
        let dir = std::env::temp_dir().join(format!("v2ce-transcode-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let events: Vec<Event> = (0..200_000i64)
            .map(|i| {
                Event::new(
                    1_000 + i * 3,
                    (i % 300) as u16,
                    (i % 200) as u16,
                    i % 4 == 0,
                )
            })
            .collect();
        let src = dir.join("in.csv");
        csv::write(&src, &events).unwrap();
        let a = dir.join("a.aedat4");
        let b = dir.join("b.raw");
        let c = dir.join("c.raw");
        let d = dir.join("d.csv");
        let h = dir.join("h.h5");
        let r = transcode(&src, &a, Format::Aedat4(format::Compression::Zstd), None).unwrap();
        assert_eq!(
            r,
            TranscodeReport {
                events: 200_000,
                size: (300, 200)
            }
        );
        transcode(&a, &b, Format::Evt3, None).unwrap();
        transcode(&b, &c, Format::Evt2, Some((640, 480))).unwrap();
        transcode(&c, &h, Format::Hdf5, None).unwrap();
        let s = summarize(&h).unwrap();
        assert_eq!((s.size, s.events), (Some((640, 480)), 200_000));
        assert_eq!(s.format, "HDF5 (DSEC layout)");
        assert_eq!(s.compression.as_deref(), Some("shuffle+deflate"));
        assert_eq!(s.time_offset_us, Some(1_000));
        transcode(&h, &d, Format::Csv, None).unwrap();
        assert_eq!(
            format::read_events(&d).unwrap().events.events(),
            &events[..]
        );
        let s = summarize(&c).unwrap();
        assert_eq!(s.size, Some((640, 480)));
        assert_eq!((s.events, s.on, s.extent), (200_000, 50_000, (300, 200)));
        assert_eq!(
            (s.first_t, s.last_t),
            (Some(1_000), Some(1_000 + 199_999 * 3))
        );
        assert!((s.rate_hz() - 200_000.0 / 0.599_997).abs() < 1.0);
        assert!(s.to_string().contains("ON ratio     0.2500"));
        assert!(transcode(&d, &d, Format::Csv, None).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
