//! ROS 2 messages from outside: any bytes as an EventPacket or an Image (CDR) give a message or
//! a clear error, never a panic or an allocation past the bytes given; a packet that decodes
//! gives events or an error, and those events packed again decode to themselves.
#![no_main]

use libfuzzer_sys::fuzz_target;
use v2ce::format::event_packet::{unpack, Packetizer};
use v2ce::ros2::msg::{EventPacket, Image};

fuzz_target!(|data: &[u8]| {
    if let Ok(img) = Image::from_cdr(data) {
        let _ = v2ce::frame::ros_image::to_frame(&img);
    }
    let Ok(p) = EventPacket::from_cdr(data) else {
        return;
    };
    let mut events = Vec::new();
    let Ok(u) = unpack(&p, &mut events) else {
        return;
    };
    assert_eq!(u.events, events.len());
    if events.is_empty() || v2ce::ros2::msg::Time::from_us(events[0].t).is_none() {
        return;
    }
    let mut packer = Packetizer::new(p.width as u16, p.height as u16, "f", 1000).unwrap();
    let mut packets = Vec::new();
    if packer.push(&events, &mut packets).is_err() {
        // Times past a ROS stamp's int32 seconds: refused, as they should be.
        return;
    }
    packer.close(&mut packets);
    let mut back = Vec::new();
    for q in &packets {
        unpack(&q.msg, &mut back).unwrap();
    }
    assert_eq!(back, events);
});
