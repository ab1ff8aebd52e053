//! Writes `tests/fixtures/zstd_chunks.mcap`: EventPacket messages of a known stream and five rgb8
//! images, in zstd chunks of 16 KiB (see Cargo.toml).
use std::collections::BTreeMap;
use v2ce::event::Event;
use v2ce::format::event_packet::Packetizer;
use v2ce::ros2::msg;
fn main() {
    let events: Vec<Event> = (0..8_000i64)
        .map(|i| {
            Event::new(
                5_000_000 + i * 7,
                (i % 97) as u16,
                (i % 61) as u16,
                i % 3 == 0,
            )
        })
        .collect();
    let mut p = Packetizer::new(128, 64, "event_camera", 1000).unwrap();
    let mut packets = Vec::new();
    p.push(&events, &mut packets).unwrap();
    p.close(&mut packets);
    let f =
        std::io::BufWriter::new(std::fs::File::create(std::env::args().nth(1).unwrap()).unwrap());
    let mut w = mcap::WriteOptions::new()
        .profile("ros2")
        .compression(Some(mcap::Compression::Zstd))
        .chunk_size(Some(16384))
        .create(f)
        .unwrap();
    let s = w
        .add_schema(
            msg::EVENT_PACKET,
            "ros2msg",
            msg::event_packet_definition().as_bytes(),
        )
        .unwrap();
    let c = w
        .add_channel(s, "/dvs/events", "cdr", &BTreeMap::new())
        .unwrap();
    let si = w
        .add_schema(msg::IMAGE, "ros2msg", msg::image_definition().as_bytes())
        .unwrap();
    let ci = w
        .add_channel(si, "/cam/image_raw", "cdr", &BTreeMap::new())
        .unwrap();
    for (i, pk) in packets.iter().enumerate() {
        let t = 1000 * (5_000_000 + i as u64 * 1000);
        w.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: c,
                sequence: i as u32,
                log_time: t,
                publish_time: t,
            },
            &pk.msg.to_cdr(),
        )
        .unwrap();
    }
    for k in 0..5u32 {
        let data: Vec<u8> = (0..32 * 24 * 3)
            .map(|j| ((j as u32 * 7 + k * 40) % 256) as u8)
            .collect();
        let img = msg::Image {
            header: msg::Header {
                stamp: msg::Time::from_us(5_000_000 + k as i64 * 40_000).unwrap(),
                frame_id: "cam".into(),
            },
            height: 24,
            width: 32,
            encoding: "rgb8".into(),
            is_bigendian: false,
            step: 96,
            data: std::borrow::Cow::Owned(data),
        };
        w.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: ci,
                sequence: k,
                log_time: 0,
                publish_time: 0,
            },
            &img.to_cdr(),
        )
        .unwrap();
    }
    w.finish().unwrap();
    println!("{} packets", packets.len());
}
