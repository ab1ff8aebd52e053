//! Events and time-ordered packets of events.
//!
//! Time is `i64` microseconds everywhere: an `f32` cannot hold 1 us past about 16 s and a
//! 32-bit integer wraps after 71.6 minutes (unsigned) or 35.8 minutes (signed).

/// One DVS event: a brightness change at a pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Event {
    /// Timestamp in microseconds (absolute or relative to a recording's start; never wraps).
    pub t: i64,
    /// Column, 0 at the left.
    pub x: u16,
    /// Row, 0 at the top.
    pub y: u16,
    /// `true` for an ON (brightness increase) event, `false` for OFF.
    pub on: bool,
}

impl Event {
    /// Creates an event.
    pub fn new(t: i64, x: u16, y: u16, on: bool) -> Self {
        Event { t, x, y, on }
    }

    /// The total order used for every event stream the project emits: time first, then row,
    /// column and polarity (OFF before ON), so ties are broken the same way on every run.
    pub fn order_key(&self) -> (i64, u16, u16, bool) {
        (self.t, self.y, self.x, self.on)
    }
}

/// Events sorted by [`Event::order_key`].
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct EventPacket {
    events: Vec<Event>,
}

impl EventPacket {
    /// Sorts `events` into a packet (stable for equal keys, which are identical events).
    pub fn from_unsorted(mut events: Vec<Event>) -> Self {
        sort_events(&mut events);
        EventPacket { events }
    }

    /// Wraps events already sorted by time; returns them back if they are not.
    ///
    /// Only the time order is checked: a recording's ties keep the order the sensor gave them.
    pub fn from_time_sorted(events: Vec<Event>) -> std::result::Result<Self, Vec<Event>> {
        if events.windows(2).all(|w| w[0].t <= w[1].t) {
            Ok(EventPacket { events })
        } else {
            Err(events)
        }
    }

    /// The events, in time order.
    pub fn events(&self) -> &[Event] {
        &self.events
    }

    /// Number of events.
    pub fn len(&self) -> usize {
        self.events.len()
    }

    /// Whether the packet holds no event.
    pub fn is_empty(&self) -> bool {
        self.events.is_empty()
    }

    /// Gives the events back.
    pub fn into_events(self) -> Vec<Event> {
        self.events
    }

    /// The events with `start <= t < end` (a binary search; the packet is sorted).
    pub fn time_slice(&self, start: i64, end: i64) -> &[Event] {
        time_slice(&self.events, start, end)
    }
}

/// The events of `events` (sorted by time) with `start <= t < end`, by binary search.
pub fn time_slice(events: &[Event], start: i64, end: i64) -> &[Event] {
    let lo = events.partition_point(|e| e.t < start);
    let hi = events.partition_point(|e| e.t < end);
    &events[lo..hi.max(lo)]
}

/// Sorts events by [`Event::order_key`].
pub fn sort_events(events: &mut [Event]) {
    events.sort_unstable_by_key(Event::order_key);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packet_sorts_with_deterministic_ties() {
        let p = EventPacket::from_unsorted(vec![
            Event::new(5, 1, 0, true),
            Event::new(5, 0, 0, true),
            Event::new(5, 0, 0, false),
            Event::new(-3, 9, 9, true),
        ]);
        let keys: Vec<_> = p.events().iter().map(|e| (e.t, e.x, e.on)).collect();
        assert_eq!(
            keys,
            vec![(-3, 9, true), (5, 0, false), (5, 0, true), (5, 1, true)]
        );
    }

    #[test]
    fn time_slice_is_half_open() {
        let p = EventPacket::from_unsorted((0..10).map(|t| Event::new(t, 0, 0, true)).collect());
        let s = p.time_slice(2, 5);
        assert_eq!(s.iter().map(|e| e.t).collect::<Vec<_>>(), vec![2, 3, 4]);
        assert!(p.time_slice(7, 3).is_empty());
    }

    #[test]
    fn unsorted_input_is_refused() {
        let events = vec![Event::new(2, 0, 0, true), Event::new(1, 0, 0, true)];
        assert!(EventPacket::from_time_sorted(events).is_err());
    }
}
