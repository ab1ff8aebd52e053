//! The pixel model's counters.

use serde::Serialize;

use crate::stage1::motion::MotionStats;

/// Counters of a simulation.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct PhysicsStats {
    /// Frames stepped.
    pub frames: u64,
    /// Tiles processed.
    pub tiles_active: u64,
    /// Tiles skipped as static (identical to the previous frame and settled).
    pub tiles_skipped: u64,
    /// Signal events (threshold crossings).
    pub signal_events: u64,
    /// Crossings swallowed by the refractory period.
    pub refractory_drops: u64,
    /// Noise events (leak, shot, hot pixels).
    pub noise_events: u64,
    /// What the motion model did (all zero under `motion = "linear"`).
    pub motion: MotionStats,
}

impl crate::stage1::TierRecord for PhysicsStats {
    const TIER: &'static str = "physics";

    fn summary(&self, _window: usize, _stride: usize) -> String {
        let tiles = format!(
            "{} of {} tiles skipped as static",
            self.tiles_skipped,
            self.tiles_skipped + self.tiles_active
        );
        let m = &self.motion;
        if m.flow_intervals == 0 {
            return tiles;
        }
        let intervals = self.frames.saturating_sub(1).max(1);
        let frame = m.frame_pixels.max(1) as f64 * m.flow_intervals as f64;
        format!(
            "{tiles}; flow on {} of {intervals} intervals ({:.0}% of their pixels), {:.2} \
             sub-frames per interval, {:.1} ms of flow per interval, {} fell back to linear",
            m.flow_intervals,
            100.0 * m.flow_pixels as f64 / frame,
            m.subframes as f64 / intervals as f64,
            m.flow_us as f64 * 1e-3 / m.flow_intervals as f64,
            m.fallbacks
        )
    }

    fn status(&self) -> Option<crate::stage1::TierStatus> {
        let m = &self.motion;
        let mean = m.cap_mean()?;
        let moves = if m.cap_lowered + m.cap_raised == 0 {
            String::new()
        } else {
            format!(
                ", lowered {} and raised {} times",
                m.cap_lowered, m.cap_raised
            )
        };
        Some(crate::stage1::TierStatus {
            line: format!(
                "sub-frame cap {} of {} (mean {mean:.2}{moves})",
                m.cap, m.cap_most
            ),
            level: Some(m.cap),
        })
    }

    fn counters(&self) -> Vec<crate::stage1::Counter> {
        let m = &self.motion;
        let mut counters = crate::stage1::Counter::family(
            "tiles",
            "Tiles the pixel model updated or skipped as static.",
            &[
                ("active", self.tiles_active),
                ("skipped", self.tiles_skipped),
            ],
        );
        counters.extend(crate::stage1::Counter::family(
            "flow",
            "Frame intervals whose optical flow ran (motion = \"flow\"), and those of them \
             that fell back to linear interpolation (a scene cut, a change of light).",
            &[("run", m.flow_intervals), ("fallback", m.fallbacks)],
        ));
        counters.extend(crate::stage1::Counter::family(
            "subframes",
            "Sub-frames inserted between frames along the flow.",
            &[("inserted", m.subframes)],
        ));
        counters.extend(crate::stage1::Counter::family(
            "flow_microseconds",
            "Time spent computing optical flow, us.",
            &[("spent", m.flow_us)],
        ));
        counters.extend(crate::stage1::Counter::family(
            "subframe_cap",
            "Times a live run lowered the sub-frame cap to keep up with the frames, and raised it \
             again with time to spare.",
            &[("lowered", m.cap_lowered), ("raised", m.cap_raised)],
        ));
        counters
    }
}

impl PhysicsStats {
    /// Adds another run's counters (a simulation restarted mid-stream).
    pub fn add(&mut self, o: PhysicsStats) {
        self.frames += o.frames;
        self.tiles_active += o.tiles_active;
        self.tiles_skipped += o.tiles_skipped;
        self.signal_events += o.signal_events;
        self.refractory_drops += o.refractory_drops;
        self.noise_events += o.noise_events;
        self.motion.add(o.motion);
    }
}
