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
use crate::frame::{Frame, FrameSource, SourceEncoding, FULL_SCALE};

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

/// A frame source integrating a recording's events (see the module docs).
pub struct EventFrames {
    events: Vec<Event>,
    next_event: usize,
    times: Vec<i64>,
    next_frame: usize,
    size: (u16, u16),
    log: Vec<f32>,
    last: Vec<i64>,
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
        how.validate()?;
        crate::limits::frame_size("sensor size", size.0.into(), size.1.into())?;
        let n = usize::from(size.0) * usize::from(size.1);
        crate::limits::memory(
            "sensor size",
            n as u64 * BYTES_PER_PIXEL,
            &format!("frames of {} x {} from events", size.0, size.1),
        )?;
        if let Some(e) = events.iter().find(|e| e.x >= size.0 || e.y >= size.1) {
            return Err(Error::invalid(
                "events",
                format!(
                    "an event at ({}, {}) off the {} x {} sensor",
                    e.x, e.y, size.0, size.1
                ),
            ));
        }
        if events.windows(2).any(|p| p[1].t < p[0].t) {
            return Err(Error::invalid("events", "not sorted by time"));
        }
        let first = events.first().map_or(0, |e| e.t);
        let times = match (events.first(), events.last()) {
            (Some(a), Some(b)) => {
                let intervals = crate::interval::fixed_intervals(a.t, b.t, fps)?;
                let mut times: Vec<i64> = intervals.iter().map(|iv| iv.start()).collect();
                times.extend(intervals.last().map(|iv| iv.end()));
                times
            }
            _ => Vec::new(),
        };
        Ok(EventFrames {
            events,
            next_event: 0,
            times,
            next_frame: 0,
            size,
            log: vec![0.0; n],
            last: vec![first; n],
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
        while let Some(&e) = self.events.get(self.next_event) {
            if e.t > t {
                break;
            }
            self.next_event += 1;
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
        Ok(Some(Frame {
            t,
            width: self.size.0,
            height: self.size.1,
            luma,
            exposure_us: None,
        }))
    }

    fn describe(&self) -> String {
        format!(
            "{} events integrated at contrast {}, cutoff {} Hz",
            self.events.len(),
            self.how.contrast,
            self.how.cutoff_hz
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
}
