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

/// Sorts events by [`Event::order_key`]. When the times' span and the coordinates fit one
/// 64-bit word together (a frame interval's events on any sensor do), the events are sorted
/// by that word: the same order, and a comparison is one integer compare instead of four.
pub fn sort_events(events: &mut [Event]) {
    let Some(key) = PackedKey::fitting(events) else {
        events.sort_unstable_by_key(Event::order_key);
        return;
    };
    if events.len() < RADIX_FROM {
        events.sort_unstable_by_key(|e| key.of(e));
        return;
    }
    // The word holds the whole event: sort the words (a radix sort over the bits in use) and
    // write the events back from them.
    let mut words: Vec<u64> = events.iter().map(|e| key.of(e)).collect();
    let top = words.iter().copied().max().unwrap_or(0);
    radix_sort(&mut words, 64 - top.leading_zeros());
    for (e, &w) in events.iter_mut().zip(&words) {
        *e = key.event(w);
    }
}

/// Fewer events than this are sorted by comparisons (a radix sort's passes cost more there).
const RADIX_FROM: usize = 512;

/// Bits per radix digit.
const DIGIT_BITS: u32 = 11;

/// Sorts `words` whose values use their lowest `bits` bits, least significant digit first
/// (stable passes, one histogram pass for all digits).
fn radix_sort(words: &mut Vec<u64>, bits: u32) {
    const BUCKETS: usize = 1 << DIGIT_BITS;
    let passes = bits.div_ceil(DIGIT_BITS) as usize;
    let mut counts = vec![[0usize; BUCKETS]; passes];
    for &w in words.iter() {
        for (p, c) in counts.iter_mut().enumerate() {
            c[((w >> (p as u32 * DIGIT_BITS)) as usize) & (BUCKETS - 1)] += 1;
        }
    }
    let mut other = vec![0u64; words.len()];
    for (p, c) in counts.iter_mut().enumerate() {
        // A digit that is the same in every word leaves the order as it is.
        if c.contains(&words.len()) {
            continue;
        }
        let mut start = 0;
        for n in c.iter_mut() {
            (*n, start) = (start, start + *n);
        }
        let shift = p as u32 * DIGIT_BITS;
        for &w in words.iter() {
            let d = ((w >> shift) as usize) & (BUCKETS - 1);
            other[c[d]] = w;
            c[d] += 1;
        }
        std::mem::swap(words, &mut other);
    }
}

/// [`Event::order_key`] packed into one word for a set of events: time since the earliest,
/// row, column and polarity, from the highest bits down.
#[derive(Debug, Clone, Copy)]
struct PackedKey {
    t_min: i64,
    /// Bits of the column and polarity together (the row sits above them).
    x_bits: u32,
    /// Bits of row, column and polarity together (the time sits above them).
    low_bits: u32,
}

impl PackedKey {
    /// The packing for `events`, if their time span and coordinates fit 64 bits.
    fn fitting(events: &[Event]) -> Option<PackedKey> {
        let first = events.first()?;
        let (mut t_min, mut t_max, mut x_max, mut y_max) = (first.t, first.t, 0u16, 0u16);
        for e in events {
            t_min = t_min.min(e.t);
            t_max = t_max.max(e.t);
            x_max = x_max.max(e.x);
            y_max = y_max.max(e.y);
        }
        let bits = |v: u64| 64 - v.leading_zeros();
        let x_bits = bits(x_max.into()) + 1;
        let low_bits = x_bits + bits(y_max.into());
        let span = t_max.checked_sub(t_min)? as u64;
        (bits(span) + low_bits <= 64).then_some(PackedKey {
            t_min,
            x_bits,
            low_bits,
        })
    }

    /// The event a word holds.
    fn event(self, w: u64) -> Event {
        let x_mask = (1u64 << self.x_bits) - 1;
        Event {
            t: self.t_min.wrapping_add((w >> self.low_bits) as i64),
            y: ((w & ((1u64 << self.low_bits) - 1)) >> self.x_bits) as u16,
            x: ((w & x_mask) >> 1) as u16,
            on: w & 1 == 1,
        }
    }

    fn of(self, e: &Event) -> u64 {
        // `low_bits` is at most 33, and `fitting` checked that the time fits above it.
        let t = e.t.wrapping_sub(self.t_min) as u64;
        (t << self.low_bits) | ((e.y as u64) << self.x_bits) | ((e.x as u64) << 1) | e.on as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_packed_sort_orders_as_the_key_does() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(7);
        // Narrow and wide coordinates and spans, up to the widest that packs and past it.
        for (t_lo, t_hi, x_hi, y_hi) in [
            (0i64, 33_000i64, 639u16, 479u16),
            (1_600_000_000_000_000, 1_600_000_000_040_000, 345, 259),
            (-5, 5, 1, 0),
            (i64::MIN, i64::MAX, u16::MAX, u16::MAX),
            (0, 1 << 31, u16::MAX, u16::MAX),
            (0, 1 << 30, u16::MAX, u16::MAX),
        ] {
            let mut events: Vec<Event> = (0..20_000)
                .map(|_| {
                    Event::new(
                        rng.gen_range(t_lo..=t_hi),
                        rng.gen_range(0..=x_hi),
                        rng.gen_range(0..=y_hi),
                        rng.gen(),
                    )
                })
                .collect();
            // Ties in time, and identical events.
            for k in 0..200 {
                events[k + 1].t = events[k].t;
            }
            events[500] = events[501];
            let mut want = events.clone();
            want.sort_by_key(Event::order_key);
            sort_events(&mut events);
            assert_eq!(events, want, "{t_lo}..{t_hi}, {x_hi} x {y_hi}");
        }
        sort_events(&mut []);
        // Below the radix sort's size, and one event.
        for n in [1, 2, 300, 511, 512, 513] {
            let mut events: Vec<Event> = (0..n)
                .map(|i| Event::new((i * 7919 % 1000) as i64, (i % 13) as u16, 3, i % 3 == 0))
                .collect();
            let mut want = events.clone();
            want.sort_by_key(Event::order_key);
            sort_events(&mut events);
            assert_eq!(events, want, "{n}");
        }
    }

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
