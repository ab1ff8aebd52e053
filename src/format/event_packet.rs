//! Events as ROS 2 `event_camera_msgs/msg/EventPacket` messages with `encoding = "evt3"` (the
//! Prophesee driver's), and back: what the `ros2` sink publishes and a `.mcap` bag holds.
//!
//! Each packet holds the events of at most `packet_us` microseconds (and at most
//! [`MAX_PACKET_BYTES`] of words) and is **decodable alone**: it starts with the time-high
//! word a decoder needs (the previous packet's last, so a reader of the packets end to end
//! sees the steps of one EVT 3.0 stream), then time-low and row words before its first event.
//!
//! Times: `header.stamp` is the time of the packet's first event (the event times as the
//! pipeline has them, microseconds, which must fit ROS time's `int32` seconds); the words hold
//! the sensor time, the event time less a multiple of 2^24 us fixed at the stream's first
//! event; `time_base` is the sensor time of the first event in nanoseconds (the message's
//! definition leaves it undefined for `evt3`). A reader takes each event's time as the stamp
//! plus its sensor time less the first event's, so any packet is read alone.

use super::evt3;
use crate::error::{Error, Result};
use crate::event::Event;
use crate::ros2::msg::{EventPacket, Header, Time};

/// The words of one packet at most (a burst longer than this continues in the next packet).
pub const MAX_PACKET_BYTES: usize = 1 << 20;

/// The sensor's sides at most, as EVT 3.0 addresses them.
const MAX_SIDE: u32 = 2048;

/// Events into self-contained EVT 3.0 packets.
#[derive(Debug)]
pub struct Packetizer {
    width: u16,
    height: u16,
    frame_id: String,
    packet_us: i64,
    words: evt3::Words,
    offset: Option<i64>,
    seq: u64,
    open: Option<Open>,
}

#[derive(Debug)]
struct Open {
    first_t: i64,
    last_t: i64,
    events: usize,
    bytes: Vec<u8>,
}

/// A packet made, with what a sender needs to know of it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Packet {
    /// The message.
    pub msg: EventPacket,
    /// Its last event's time, us: it is due to leave then.
    pub last_t: i64,
    /// Events it holds.
    pub events: usize,
}

impl Packetizer {
    /// Packets of a `width x height` sensor (1 to 2048 a side), each spanning less than
    /// `packet_us` (at least 1), stamped in `frame_id`.
    pub fn new(width: u16, height: u16, frame_id: &str, packet_us: i64) -> Result<Self> {
        if width == 0 || height == 0 || width as u32 > MAX_SIDE || height as u32 > MAX_SIDE {
            return Err(Error::invalid(
                "event packet",
                format!(
                    "EVT 3.0 holds 1 to 2048 columns and rows; {width} x {height} does not fit"
                ),
            ));
        }
        if packet_us < 1 {
            return Err(Error::invalid(
                "packet_us",
                format!("{packet_us} (at least 1)"),
            ));
        }
        Ok(Packetizer {
            width,
            height,
            frame_id: frame_id.to_string(),
            packet_us,
            words: evt3::Words::default(),
            offset: None,
            seq: 0,
            open: None,
        })
    }

    /// Packets made so far.
    pub fn packets(&self) -> u64 {
        self.seq
    }

    /// When the open packet's span ends (event time, us): it can be closed then.
    pub fn due(&self) -> Option<i64> {
        self.open
            .as_ref()
            .map(|o| o.first_t.saturating_add(self.packet_us))
    }

    /// Adds events (in time order, after every event before), appending each packet that
    /// they close to `out`.
    pub fn push(&mut self, events: &[Event], out: &mut Vec<Packet>) -> Result<()> {
        let mut i = 0;
        while i < events.len() {
            let t = events[i].t;
            if self.due().is_some_and(|end| t >= end) {
                self.close(out);
            }
            if self.open.is_none() {
                if Time::from_us(t).is_none() {
                    return Err(Error::invalid(
                        "event time",
                        format!("{t} us is past what a ROS 2 stamp holds (int32 seconds)"),
                    ));
                }
                self.offset
                    .get_or_insert_with(|| super::raw::time_offset_for(super::raw::Evt::Evt3, t));
                let mut bytes = Vec::new();
                self.words.restart(&mut bytes);
                self.open = Some(Open {
                    first_t: t,
                    last_t: t,
                    events: 0,
                    bytes,
                });
            }
            let end = self.due().unwrap_or(i64::MAX);
            let room = (MAX_PACKET_BYTES / 2).max(1);
            let n = events[i..]
                .iter()
                .take(room)
                .take_while(|e| e.t < end)
                .count()
                .max(1);
            let offset = self.offset.unwrap_or(0);
            let (w, h) = (self.width, self.height);
            if let Some(open) = self.open.as_mut() {
                self.words
                    .encode(&events[i..i + n], offset, w, h, &mut open.bytes)?;
                open.events += n;
                open.last_t = events[i + n - 1].t;
                if open.bytes.len() >= MAX_PACKET_BYTES {
                    self.close(out);
                }
            }
            i += n;
        }
        Ok(())
    }

    /// Closes the open packet, if any, appending it to `out`.
    pub fn close(&mut self, out: &mut Vec<Packet>) {
        let Some(open) = self.open.take() else {
            return;
        };
        let offset = self.offset.unwrap_or(0);
        let sensor_us = open.first_t.saturating_sub(offset).max(0) as u64;
        let msg = EventPacket {
            header: Header {
                // Checked when the packet was opened.
                stamp: Time::from_us(open.first_t).unwrap_or_default(),
                frame_id: self.frame_id.clone(),
            },
            height: self.height as u32,
            width: self.width as u32,
            seq: self.seq,
            time_base: sensor_us.saturating_mul(1000),
            encoding: "evt3".into(),
            is_bigendian: false,
            events: open.bytes,
        };
        out.push(Packet {
            msg,
            last_t: open.last_t,
            events: open.events,
        });
        self.seq += 1;
    }
}

/// What one packet held.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Unpacked {
    /// Events appended.
    pub events: usize,
    /// Events at a pixel outside the packet's `width x height`, dropped.
    pub off_sensor: u64,
}

/// Appends the events of one packet to `out`, in time order (see the module's times);
/// a packet whose encoding is not `evt3`, whose size is not one EVT 3.0 holds, whose stamp is
/// not a time, or whose words are cut is an error, and `out` is left as it was.
pub fn unpack(p: &EventPacket, out: &mut Vec<Event>) -> Result<Unpacked> {
    let bad = |m: String| Err(Error::invalid("event packet", m));
    if !p.encoding.eq_ignore_ascii_case("evt3") {
        return bad(format!(
            "encoding '{}' is not read (v2ce reads evt3)",
            p.encoding
        ));
    }
    if p.width == 0 || p.height == 0 || p.width > MAX_SIDE || p.height > MAX_SIDE {
        return bad(format!(
            "a {} x {} sensor (EVT 3.0 holds 1 to 2048 a side)",
            p.width, p.height
        ));
    }
    if !p.events.len().is_multiple_of(2) {
        return bad(format!(
            "{} bytes of events is not a whole number of 16-bit words",
            p.events.len()
        ));
    }
    let Some(stamp) = p.header.stamp.to_us() else {
        return bad(format!(
            "stamp nanoseconds {} (1e9 or more)",
            p.header.stamp.nanosec
        ));
    };
    let swapped;
    let words: &[u8] = if p.is_bigendian {
        swapped = p
            .events
            .chunks_exact(2)
            .flat_map(|w| [w[1], w[0]])
            .collect::<Vec<u8>>();
        &swapped
    } else {
        &p.events
    };
    let size = (p.width as u16, p.height as u16);
    let mut decoder = evt3::Decoder::packet(words, Some(size));
    let start = out.len();
    loop {
        if !crate::limits::room_for(out, 65_536) {
            out.truncate(start);
            return Err(Error::invalid(
                "event packet",
                "its events pass the memory left to hold them".to_string(),
            ));
        }
        let n = super::EventDecoder::read_events(&mut decoder, out, 65_536)?;
        if n == 0 {
            break;
        }
    }
    // Times from the stamp: each event's sensor time less the first event's.
    let mut off_sensor = 0;
    let first_rel = out.get(start).map_or(0, |e| e.t);
    let mut kept = start;
    for i in start..out.len() {
        let mut e = out[i];
        if e.x >= size.0 || e.y >= size.1 {
            off_sensor += 1;
            continue;
        }
        e.t = match crate::time::checked_add("event time", stamp, e.t - first_rel) {
            Ok(t) => t,
            Err(err) => {
                out.truncate(start);
                return Err(err);
            }
        };
        out[kept] = e;
        kept += 1;
    }
    out.truncate(kept);
    Ok(Unpacked {
        events: kept - start,
        off_sensor,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::EventDecoder;

    fn stream(n: usize, t0: i64, step: i64) -> Vec<Event> {
        (0..n)
            .map(|i| {
                Event::new(
                    t0 + i as i64 * step,
                    (i * 7 % 640) as u16,
                    (i * 3 % 480) as u16,
                    i % 3 == 0,
                )
            })
            .collect()
    }

    fn pack(events: &[Event], packet_us: i64) -> Vec<EventPacket> {
        pack_all(events, packet_us)
            .into_iter()
            .map(|p| p.msg)
            .collect()
    }

    fn pack_all(events: &[Event], packet_us: i64) -> Vec<Packet> {
        let mut p = Packetizer::new(640, 480, "cam", packet_us).unwrap();
        let mut out = Vec::new();
        for chunk in events.chunks(333) {
            p.push(chunk, &mut out).unwrap();
        }
        p.close(&mut out);
        out
    }

    #[test]
    fn every_packet_decodes_alone_and_spans_at_most_packet_us() {
        // Unix-epoch times, and a gap of 20 s (past the 24-bit time) in the middle.
        let mut events = stream(5000, 1_700_000_000_000_000, 37);
        let later = stream(3000, events.last().unwrap().t + 20_000_000, 11);
        events.extend(later);
        let packets = pack(&events, 1000);
        let mut all = Vec::new();
        for (i, p) in packets.iter().enumerate() {
            assert_eq!(p.seq, i as u64);
            let mut one = Vec::new();
            unpack(p, &mut one).unwrap();
            assert!(one.last().unwrap().t - one[0].t < 1000);
            assert_eq!(Time::from_us(one[0].t).unwrap(), p.header.stamp);
            // Decoded alone, through CDR.
            let again = EventPacket::from_cdr(&p.to_cdr()).unwrap();
            let mut two = Vec::new();
            unpack(&again, &mut two).unwrap();
            assert_eq!(one, two);
            all.extend(one);
        }
        assert_eq!(all, events);
    }

    #[test]
    fn packets_end_to_end_are_one_evt3_stream() {
        let events = stream(4000, 0, 3000);
        let packets = pack(&events, 50_000);
        let mut words = Vec::new();
        for p in &packets {
            words.extend_from_slice(&p.events);
        }
        let mut d = evt3::Decoder::new(&words[..], &crate::format::raw::Header::default());
        let mut back = Vec::new();
        while d.read_events(&mut back, 10_000).unwrap() > 0 {}
        assert_eq!(back, events);
    }

    #[test]
    fn bad_packets_are_errors_and_off_sensor_events_are_counted() {
        let packets = pack(&stream(100, 0, 10), 1_000_000);
        let mut p = packets[0].clone();
        let mut out = Vec::new();
        p.encoding = "mono".into();
        assert!(unpack(&p, &mut out).is_err());
        p = packets[0].clone();
        p.events.push(0);
        assert!(unpack(&p, &mut out).is_err());
        p = packets[0].clone();
        p.width = 5000;
        assert!(unpack(&p, &mut out).is_err());
        assert!(out.is_empty());
        p = packets[0].clone();
        p.width = 10;
        let u = unpack(&p, &mut out).unwrap();
        assert!(u.off_sensor > 0);
        assert!(out.iter().all(|e| e.x < 10));
        assert!(Packetizer::new(640, 480, "c", 1)
            .unwrap()
            .push(&[Event::new(1 << 52, 0, 0, true)], &mut Vec::new())
            .is_err());
    }
}
