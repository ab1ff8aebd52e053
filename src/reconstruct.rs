//! Frames reconstructed from events, for recordings that have none (a DVXplorer, a Prophesee
//! sensor), so that simulators can be run on them and compared with the real stream on the
//! statistics that need no frames (`v2ce eval realism --fps`, `v2ce reconstruct`).
//!
//! Each pixel's log intensity is the sum of its events' signed contrasts, each ON event `+c`
//! and each OFF `-c`, leaking back to the scene's mean level through a first-order high-pass
//! of cutoff `f` (the pure high-pass filter of Scheerlinck, Barnes & Mahony, "Continuous-time
//! intensity estimation using event cameras", ACCV 2018, without frames to complement it):
//! `L(t) = sum_k p_k c e^(-2 pi f (t - t_k))`. A frame at `t` is the linear light
//! `level * e^L(t)` (clipped at full scale). What never fired, the static scene, comes out at
//! `level`: the frames hold what moved, which is what a simulator turns back into events.
//!
//! The frames are at fixed times from the first event ([`crate::interval::fixed_intervals`],
//! the same intervals `--fps` gives the evaluators), one at each interval's start and one at
//! the last one's end.

use crate::error::{Error, Result};
use crate::event::Event;
use crate::format::EventDecoder;
use crate::frame::{Frame, FrameSource, SourceEncoding, FULL_SCALE};
use std::path::Path;

/// How events are integrated into frames.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reconstruction {
    /// The log contrast of one event (the sensor's threshold).
    pub contrast: f64,
    /// The high-pass cutoff, Hz: how fast a pixel's level returns to `level` (0: never).
    pub cutoff_hz: f64,
    /// The linear light (fraction of full scale) of a pixel that has not fired.
    pub level: f64,
}

impl Default for Reconstruction {
    /// The `dvxplorer` preset's threshold, a cutoff slow against motion, and a quarter of full
    /// scale (room for four events' brightening before clipping).
    fn default() -> Self {
        Reconstruction {
            contrast: 0.25,
            cutoff_hz: 0.5,
            level: 0.25,
        }
    }
}

impl Reconstruction {
    /// Checks that the parameters are usable.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::invalid("reconstruction", m));
        if !(self.contrast.is_finite() && self.contrast > 0.0 && self.contrast <= 5.0) {
            return bad(format!("contrast = {} must be in (0, 5]", self.contrast));
        }
        if !(self.cutoff_hz.is_finite() && (0.0..=1000.0).contains(&self.cutoff_hz)) {
            return bad(format!(
                "cutoff = {} Hz must be in [0, 1000]",
                self.cutoff_hz
            ));
        }
        if !(self.level.is_finite() && self.level > 0.0 && self.level < 1.0) {
            return bad(format!("level = {} must be in (0, 1)", self.level));
        }
        Ok(())
    }
}

/// Bytes a reconstruction holds per pixel (level and time of its last event, the frame).
const BYTES_PER_PIXEL: u64 = 4 + 8 + 2;

/// Events read from a file per call, when the frames read it as they go.
const CHUNK: usize = 1 << 16;

/// A reconstruction's events in time order: `chunk[next..]` are not yet integrated, and the
/// decoder, if any, reads the rest of a file as the frames need them (so memory stays flat
/// however long the recording); without one, `chunk` holds them all.
struct Feed {
    chunk: Vec<Event>,
    next: usize,
    decoder: Option<Box<dyn EventDecoder + Send>>,
}

impl Feed {
    /// The next event at or before `t`, taken from the feed.
    fn take_until(&mut self, t: i64) -> Result<Option<Event>> {
        if self.next == self.chunk.len() {
            let Some(decoder) = &mut self.decoder else {
                return Ok(None);
            };
            self.chunk.clear();
            self.next = 0;
            decoder.read_events(&mut self.chunk, CHUNK)?;
        }
        match self.chunk.get(self.next) {
            Some(&e) if e.t <= t => {
                self.next += 1;
                Ok(Some(e))
            }
            _ => Ok(None),
        }
    }
}

/// What one pass over a recording's events found.
#[derive(Debug, Clone, Copy, Default)]
struct Scan {
    count: u64,
    /// The first and the last event's time.
    span: Option<(i64, i64)>,
    /// The largest column and row.
    most: (u16, u16),
    /// An event before the one ahead of it, if any: its index.
    unsorted: Option<u64>,
}

impl Scan {
    fn add(&mut self, events: &[Event]) {
        for e in events {
            match &mut self.span {
                None => self.span = Some((e.t, e.t)),
                Some((_, last)) => {
                    if e.t < *last && self.unsorted.is_none() {
                        self.unsorted = Some(self.count);
                    }
                    *last = (*last).max(e.t);
                }
            }
            self.most = (self.most.0.max(e.x), self.most.1.max(e.y));
            self.count += 1;
        }
    }

    /// The sensor `size` (given, or one more than the largest column and row), checked
    /// against the events.
    fn sensor(&self, size: Option<(u16, u16)>) -> Result<(u16, u16)> {
        let size = size.unwrap_or((self.most.0.saturating_add(1), self.most.1.saturating_add(1)));
        if self.count > 0 && (self.most.0 >= size.0 || self.most.1 >= size.1) {
            return Err(Error::invalid(
                "events",
                format!(
                    "an event at column {} or row {}, off the {} x {} sensor",
                    self.most.0, self.most.1, size.0, size.1
                ),
            ));
        }
        Ok(size)
    }
}

/// A frame source integrating a recording's events (see the module docs).
pub struct EventFrames {
    feed: Feed,
    count: u64,
    times: Vec<i64>,
    next_frame: usize,
    size: (u16, u16),
    log: Vec<f32>,
    last: Vec<i64>,
    /// The last integrated event's time.
    last_t: i64,
    how: Reconstruction,
}

impl EventFrames {
    /// Frames of `events` (sorted by time) on a `size` sensor at `fps` from the first event.
    pub fn new(
        events: Vec<Event>,
        size: (u16, u16),
        fps: f64,
        how: Reconstruction,
    ) -> Result<Self> {
        let mut scan = Scan::default();
        scan.add(&events);
        if scan.unsorted.is_some() {
            return Err(Error::invalid("events", "not sorted by time"));
        }
        let size = scan.sensor(Some(size))?;
        let feed = Feed {
            chunk: events,
            next: 0,
            decoder: None,
        };
        Self::build(feed, &scan, size, fps, how)
    }

    /// Frames of the events in `path` (any format [`crate::format::open`] reads) at `fps`
    /// from the first event, on a `size` sensor (`None`: the file's, or the events' extent).
    /// A file in time order is read twice, once for its span and once as the frames need its
    /// events, so memory does not grow with its length; one out of order is read whole and
    /// sorted, within the memory this machine has.
    pub fn open(
        path: &Path,
        size: Option<(u16, u16)>,
        fps: f64,
        how: Reconstruction,
    ) -> Result<Self> {
        how.validate()?;
        let mut decoder = crate::format::open(path)?;
        let size = size.or(decoder.size());
        let mut scan = Scan::default();
        let mut chunk = Vec::new();
        while decoder.read_events(&mut chunk, CHUNK)? > 0 {
            scan.add(&chunk);
            chunk.clear();
        }
        if let Some(at) = scan.unsorted {
            eprintln!(
                "v2ce: {}: event {at} comes before the one ahead of it; reading the file whole to sort it",
                path.display()
            );
            crate::limits::memory(
                "events",
                scan.count
                    .saturating_mul(std::mem::size_of::<Event>() as u64),
                &format!("sorting the {} events of {}", scan.count, path.display()),
            )?;
            let recording = crate::format::read_events(path)?;
            let size = size.unwrap_or((recording.width, recording.height));
            return Self::new(recording.events.into_events(), size, fps, how);
        }
        let size = scan.sensor(size)?;
        let feed = Feed {
            chunk,
            next: 0,
            decoder: Some(crate::format::open(path)?),
        };
        Self::build(feed, &scan, size, fps, how)
    }

    /// The source over `feed`, whose events `scan` describes (sorted, on the `size` sensor).
    fn build(
        feed: Feed,
        scan: &Scan,
        size: (u16, u16),
        fps: f64,
        how: Reconstruction,
    ) -> Result<Self> {
        how.validate()?;
        crate::limits::frame_size("sensor size", size.0.into(), size.1.into())?;
        let n = usize::from(size.0) * usize::from(size.1);
        crate::limits::memory(
            "sensor size",
            n as u64 * BYTES_PER_PIXEL,
            &format!("frames of {} x {} from events", size.0, size.1),
        )?;
        let times = match scan.span {
            Some((first, last)) => {
                let intervals = crate::interval::fixed_intervals(first, last, fps)?;
                let mut times: Vec<i64> = intervals.iter().map(|iv| iv.start()).collect();
                times.extend(intervals.last().map(|iv| iv.end()));
                times
            }
            None => Vec::new(),
        };
        Ok(EventFrames {
            feed,
            count: scan.count,
            times,
            next_frame: 0,
            size,
            log: vec![0.0; n],
            last: vec![scan.span.map_or(0, |s| s.0); n],
            last_t: i64::MIN,
            how,
        })
    }

    /// The decay of a pixel's level over `dt` us.
    fn decay(&self, dt: i64) -> f32 {
        (-std::f64::consts::TAU * self.how.cutoff_hz * dt as f64 * 1e-6).exp() as f32
    }
}

impl FrameSource for EventFrames {
    fn size(&self) -> (u16, u16) {
        self.size
    }

    fn next_frame(&mut self) -> Result<Option<Frame>> {
        let Some(&t) = self.times.get(self.next_frame) else {
            return Ok(None);
        };
        self.next_frame += 1;
        let width = usize::from(self.size.0);
        let contrast = self.how.contrast as f32;
        while let Some(e) = self.feed.take_until(t)? {
            // The scan checked them; a file that changed since is refused, not trusted.
            crate::format::check_event(&e, self.last_t, self.size.0, self.size.1)?;
            self.last_t = e.t;
            let i = usize::from(e.y) * width + usize::from(e.x);
            let kept = self.decay(e.t - self.last[i]);
            self.log[i] = self.log[i] * kept + if e.on { contrast } else { -contrast };
            self.last[i] = e.t;
        }
        let full = f64::from(FULL_SCALE);
        let luma = self
            .log
            .iter()
            .zip(&self.last)
            .map(|(&l, &at)| {
                let l = if l == 0.0 {
                    0.0
                } else {
                    l * self.decay(t - at)
                };
                (self.how.level * f64::from(l).exp() * full)
                    .round()
                    .clamp(0.0, full) as u16
            })
            .collect();
        Ok(Some(Frame::new(t, self.size, luma)))
    }

    fn describe(&self) -> String {
        format!(
            "{} events integrated at contrast {}, cutoff {} Hz",
            self.count, self.how.contrast, self.how.cutoff_hz
        )
    }

    fn frames_hint(&self) -> Option<u64> {
        Some(self.times.len() as u64)
    }

    fn encoding(&self) -> SourceEncoding {
        SourceEncoding::Linear
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pixel's level is its events' contrasts, decayed by the cutoff; a pixel without
    /// events stays at `level`; frames fall at the fixed intervals' bounds.
    #[test]
    fn frames_integrate_the_events() {
        let how = Reconstruction {
            contrast: 0.2,
            cutoff_hz: 1.0,
            level: 0.25,
        };
        let events = vec![
            Event::new(1_000, 1, 0, true),
            Event::new(1_000, 2, 1, false),
            Event::new(2_000, 1, 0, true),
            Event::new(101_000, 0, 0, true),
        ];
        let mut src = EventFrames::new(events, (3, 2), 10.0, how).unwrap();
        assert_eq!(src.frames_hint(), Some(3));
        let frames = crate::frame::read_frames(&mut src, usize::MAX).unwrap();
        let times: Vec<i64> = frames.iter().map(|f| f.t).collect();
        assert_eq!(times, [1_000, 101_000, 201_000]);
        let full = f64::from(FULL_SCALE);
        let expect = |l: f64| (0.25 * l.exp() * full).round() as u16;
        // At 1 ms: pixel (1, 0) and (2, 1) have one event each.
        assert_eq!(frames[0].luma[1], expect(0.2));
        assert_eq!(frames[0].luma[5], expect(-0.2));
        assert_eq!(frames[0].luma[4], expect(0.0));
        // At 101 ms: (1, 0) had a second event at 2 ms; both decay at 1 Hz.
        let d = |dt_us: f64| (-std::f64::consts::TAU * dt_us * 1e-6).exp();
        let level = (0.2 * d(1_000.0) + 0.2) * d(99_000.0);
        assert!(frames[1].luma[1].abs_diff(expect(level)) <= 1);
        assert_eq!(frames[1].luma[0], expect(0.2));
    }

    /// No events: no frames. Events off the sensor, unsorted events and bad parameters are
    /// errors.
    #[test]
    fn bad_input_is_refused() {
        let how = Reconstruction::default();
        let mut none = EventFrames::new(Vec::new(), (4, 4), 30.0, how).unwrap();
        assert!(none.next_frame().unwrap().is_none());
        let off = vec![Event::new(0, 4, 0, true)];
        assert!(EventFrames::new(off, (4, 4), 30.0, how).is_err());
        let unsorted = vec![Event::new(5, 0, 0, true), Event::new(1, 0, 0, true)];
        assert!(EventFrames::new(unsorted, (4, 4), 30.0, how).is_err());
        let one = vec![Event::new(0, 0, 0, true)];
        for bad in [
            Reconstruction {
                contrast: f64::NAN,
                ..how
            },
            Reconstruction { level: 1.0, ..how },
            Reconstruction {
                cutoff_hz: -1.0,
                ..how
            },
        ] {
            assert!(EventFrames::new(one.clone(), (4, 4), 30.0, bad).is_err());
        }
        assert!(EventFrames::new(one, (4, 4), 0.0, how).is_err());
    }

    /// Frames read from a file as they go (more events than one read's chunk, two sensor
    /// sizes) are the frames of the same events held in memory; a file out of time order is
    /// sorted first; a size the events do not fit is refused.
    #[test]
    fn a_file_streams_to_the_frames_its_events_give() {
        let dir = std::env::temp_dir().join(format!("v2ce-reconstruct-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let how = Reconstruction::default();
        let mut t = 0i64;
        let events: Vec<Event> = (0..3 * CHUNK as u64)
            .map(|k| {
                let r = crate::seed::splitmix(k);
                t += (r >> 40 & 7) as i64;
                Event::new(t, (r % 40) as u16, ((r >> 8) % 30) as u16, r >> 20 & 1 == 1)
            })
            .collect();
        let write = |name: &str, events: &[Event]| {
            let path = dir.join(name);
            let mut out = crate::format::create(&path, crate::format::Format::Csv, 40, 30).unwrap();
            out.write(events).unwrap();
            out.finish().unwrap();
            path
        };
        let frames =
            |mut src: EventFrames| crate::frame::read_frames(&mut src, usize::MAX).unwrap();
        let held = frames(EventFrames::new(events.clone(), (40, 30), 100.0, how).unwrap());
        assert!(held.len() > 10, "{} frames", held.len());
        let sorted = write("sorted.csv", &events);
        let read = frames(EventFrames::open(&sorted, Some((40, 30)), 100.0, how).unwrap());
        assert_eq!(read, held);
        // No size given: a CSV has none, so the events' extent (40 x 30 here).
        let read = frames(EventFrames::open(&sorted, None, 100.0, how).unwrap());
        assert_eq!(read, held);
        // Out of order in the file: the same frames, read whole and sorted.
        let mut shuffled = events.clone();
        shuffled.swap(10, 20_000);
        let path = dir.join("unsorted.csv");
        let text: String = std::iter::once("t_us,x,y,on\n".to_string())
            .chain(
                shuffled
                    .iter()
                    .map(|e| format!("{},{},{},{}\n", e.t, e.x, e.y, u8::from(e.on))),
            )
            .collect();
        std::fs::write(&path, text).unwrap();
        let read = frames(EventFrames::open(&path, Some((40, 30)), 100.0, how).unwrap());
        assert_eq!(read, held);
        assert!(EventFrames::open(&sorted, Some((40, 29)), 100.0, how).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }
}
