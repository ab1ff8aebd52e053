//! AEDAT 4.0 files (the DV software's container), read with the `aedat` crate: the events of
//! the first event stream and the times of the APS frames.
//!
//! A frame's time is the middle of its exposure, `(exposure_begin + exposure_end) / 2`: the
//! instant the image stands for (the IJRR export of the same recording uses it too).

use std::path::Path;

use aedat::base::{Decoder, StreamContent};

use super::Recording;
use crate::error::{Error, Result};
use crate::event::Event;

/// Reads the events and the APS frame times of an AEDAT 4.0 file.
pub fn read(path: &Path) -> Result<(Recording, Vec<i64>)> {
    let bad = |m: String| Error::format(path, m);
    let decoder = Decoder::new_from_file(path)
        .map_err(|e| bad(format!("not a readable AEDAT 4.0 file: {e}")))?;
    let mut event_stream = None;
    for (id, stream) in &decoder.id_to_stream {
        if matches!(stream.content, StreamContent::Events)
            && event_stream.is_none_or(|(best, _, _)| *id < best)
        {
            event_stream = Some((*id, stream.width, stream.height));
        }
    }
    let frame_streams: Vec<u32> = decoder
        .id_to_stream
        .iter()
        .filter(|(_, s)| matches!(s.content, StreamContent::Frame))
        .map(|(id, _)| *id)
        .collect();
    let mut events = Vec::new();
    let mut frames = Vec::new();
    for (index, packet) in decoder.enumerate() {
        let packet = packet.map_err(|e| bad(format!("packet {index}: {e}")))?;
        if Some(packet.stream_id) == event_stream.map(|s| s.0) {
            let p = aedat::events_generated::size_prefixed_root_as_event_packet(&packet.buffer)
                .map_err(|e| bad(format!("packet {index}: bad event packet: {e}")))?;
            for e in p.elements().into_iter().flatten() {
                let (x, y) = (e.x(), e.y());
                if x < 0 || y < 0 {
                    return Err(bad(format!("packet {index}: negative pixel ({x}, {y})")));
                }
                events.push(Event::new(e.t(), x as u16, y as u16, e.on()));
            }
        } else if frame_streams.contains(&packet.stream_id) {
            let f = aedat::frame_generated::size_prefixed_root_as_frame(&packet.buffer)
                .map_err(|e| bad(format!("packet {index}: bad frame: {e}")))?;
            let (b, e) = (f.exposure_begin_t(), f.exposure_end_t());
            frames.push(if e >= b && b > 0 {
                b + (e - b) / 2
            } else {
                f.t()
            });
        }
    }
    let Some((_, width, height)) = event_stream else {
        return Err(bad("no event stream".into()));
    };
    if let Some(e) = events.iter().find(|e| e.x >= width || e.y >= height) {
        return Err(bad(format!(
            "event at ({}, {}) outside the {width} x {height} sensor",
            e.x, e.y
        )));
    }
    frames.sort_unstable();
    frames.dedup();
    Ok((Recording::new(events, Some((width, height))), frames))
}
