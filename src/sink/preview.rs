//! The live preview's tap: a sink that keeps the daemon's events of the last seconds for the
//! HTTP listener's page (`src/http`) to draw, as `v2ce render` draws a file.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

use super::{Sink, SinkStats};
use crate::error::Result;
use crate::event::Event;
use crate::render::{BACKGROUND, OFF_COLOUR, ON_COLOUR};

/// Event time kept, us (the longest accumulation window the page offers).
pub const KEEP_US: i64 = 1_000_000;
/// Events kept at most (the oldest go first): 32 MB.
pub const MAX_EVENTS: usize = 2_000_000;

/// The recent events, shared between the sink and the HTTP listener.
pub struct PreviewBuffer {
    width: u16,
    height: u16,
    events: Mutex<VecDeque<Event>>,
}

impl PreviewBuffer {
    /// An empty buffer for a `width x height` sensor.
    pub fn new(width: u16, height: u16) -> Arc<Self> {
        Arc::new(PreviewBuffer {
            width,
            height,
            events: Mutex::new(VecDeque::new()),
        })
    }

    /// The sensor size.
    pub fn size(&self) -> (u16, u16) {
        (self.width, self.height)
    }

    fn push(&self, events: &[Event]) {
        let mut q = self.events.lock().unwrap_or_else(|e| e.into_inner());
        q.extend(events.iter().copied());
        let newest = q.back().map_or(0, |e| e.t);
        while q.len() > MAX_EVENTS || q.front().is_some_and(|e| e.t < newest - KEEP_US) {
            q.pop_front();
        }
    }

    /// The events of the last `window_us` of event time as an RGB image (row-major,
    /// `width x height x 3`): ON and OFF in `v2ce render`'s colours (the later event of a pixel
    /// shows) over its background; and how many events it shows.
    pub fn frame(&self, window_us: i64) -> (Vec<u8>, usize) {
        let (w, h) = (self.width as usize, self.height as usize);
        let mut rgb = BACKGROUND.repeat(w * h);
        let q = self.events.lock().unwrap_or_else(|e| e.into_inner());
        let Some(newest) = q.back().map(|e| e.t) else {
            return (rgb, 0);
        };
        let from = newest.saturating_sub(window_us.max(1));
        let start = q.partition_point(|e| e.t <= from);
        let mut shown = 0;
        for e in q.range(start..) {
            let (x, y) = (e.x as usize, e.y as usize);
            if x < w && y < h {
                let c = if e.on { ON_COLOUR } else { OFF_COLOUR };
                rgb[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&c);
                shown += 1;
            }
        }
        (rgb, shown)
    }
}

/// The sink side of a [`PreviewBuffer`].
pub struct PreviewSink {
    buffer: Arc<PreviewBuffer>,
    stats: SinkStats,
}

impl PreviewSink {
    /// A sink feeding `buffer`.
    pub fn new(buffer: Arc<PreviewBuffer>) -> Self {
        PreviewSink {
            buffer,
            stats: SinkStats::default(),
        }
    }
}

impl Sink for PreviewSink {
    fn describe(&self) -> String {
        "preview (HTTP page)".into()
    }

    fn send(&mut self, events: &[Event]) -> Result<()> {
        self.buffer.push(events);
        self.stats.events_in += events.len() as u64;
        self.stats.events_sent += events.len() as u64;
        self.stats.messages_sent += 1;
        Ok(())
    }

    fn finish(&mut self) -> Result<()> {
        Ok(())
    }

    fn stats(&self) -> SinkStats {
        self.stats
    }

    fn counts_latency(&self) -> bool {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_frame_shows_the_last_window_in_render_colours() {
        let buffer = PreviewBuffer::new(4, 2);
        let mut sink = PreviewSink::new(buffer.clone());
        sink.send(&[
            Event::new(0, 0, 0, true),
            Event::new(500_000, 1, 0, false),
            Event::new(900_000, 2, 1, true),
            Event::new(950_000, 2, 1, false),
        ])
        .unwrap();
        let (rgb, shown) = buffer.frame(100_000);
        assert_eq!(shown, 2);
        let px = |x: usize, y: usize| &rgb[(y * 4 + x) * 3..(y * 4 + x) * 3 + 3];
        assert_eq!(px(2, 1), OFF_COLOUR); // the later of the two
        assert_eq!(px(1, 0), BACKGROUND); // outside the window
        let (rgb, shown) = buffer.frame(1_000_000);
        assert_eq!(shown, 4);
        assert_eq!(&rgb[..3], ON_COLOUR);
        // More than KEEP_US behind the newest (the event at 0): gone.
        sink.send(&[Event::new(1_400_000, 3, 1, true)]).unwrap();
        assert_eq!(buffer.frame(10_000_000).1, 4);
        assert_eq!(sink.stats().events_sent, 5);
    }
}
