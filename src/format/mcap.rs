//! rosbag2 files in MCAP (`.mcap`, ROS 2's default bag storage): events as CDR-encoded
//! `event_camera_msgs/msg/EventPacket` messages ([`super::event_packet`]) on
//! [`DEFAULT_TOPIC`], the message definitions stored as the channel's `ros2msg` schema, as
//! `ros2 bag record` writes them. The container is the `mcap` crate's.
//!
//! The writer writes the messages unchunked (each record whole in the file as it goes), so a
//! run cut short by a full disk keeps every whole message: [`close_in_place`] cuts the file after the
//! last whole record and closes it with a data end, a footer and the magic.
//!
//! The reader takes the EventPacket messages of one topic (the first such topic in the file,
//! or the one asked for) in file order; frames in `sensor_msgs/msg/Image` messages are
//! [`crate::frame::ros_image`]'s. Chunks compressed with zstd are read; lz4 chunks are not (an
//! error says so).

use std::collections::BTreeMap;
use std::io::{BufReader, Read, Seek, SeekFrom, Write};
use std::path::Path;

use super::event_packet::{unpack, Packet, Packetizer};
use super::{EventDecoder, EventEncoder};
use crate::error::{Error, Result};
use crate::event::Event;
use crate::ros2::msg::{self, EventPacket};

/// The topic v2ce's bags put events on.
pub const DEFAULT_TOPIC: &str = "/event_camera/events";

/// The frame id of v2ce's packets.
pub const DEFAULT_FRAME_ID: &str = "event_camera";

/// The span of one packet in a bag, us (the `ros2` sink's default too).
pub const PACKET_US: i64 = 1000;

const MAGIC: &[u8; 8] = b"\x89MCAP0\r\n";

/// An error of the container, with the causes it wraps (the OS's "No space left on device"
/// under the crate's "I/O error from writing").
fn mcap_error(what: &str, e: impl std::error::Error) -> Error {
    let mut text = format!("{what}: {e}");
    let mut cause = e.source();
    while let Some(c) = cause {
        text.push_str(&format!(": {c}"));
        cause = c.source();
    }
    Error::invalid("MCAP", text)
}

/// A stamp in nanoseconds for the message's log time (0 for times before 1970).
fn log_time(p: &EventPacket) -> u64 {
    (p.header.stamp.sec.max(0) as u64) * 1_000_000_000 + p.header.stamp.nanosec as u64
}

/// Writes events as a rosbag2 `.mcap`.
pub struct Encoder<W: Write + Seek> {
    writer: Option<mcap::Writer<W>>,
    channel: u16,
    packets: Packetizer,
    ready: Vec<Packet>,
}

impl<W: Write + Seek> Encoder<W> {
    /// A bag of a `width x height` sensor's events (at most 2048 a side, as EVT 3.0).
    pub fn new(writer: W, width: u16, height: u16) -> Result<Self> {
        let packets = Packetizer::new(width, height, DEFAULT_FRAME_ID, PACKET_US)?;
        let options = mcap::WriteOptions::new()
            .profile("ros2")
            .library(concat!("v2ce ", env!("CARGO_PKG_VERSION")))
            .compression(None)
            .use_chunks(false)
            .disable_seeking(true);
        let mut w = options
            .create(writer)
            .map_err(|e| mcap_error("starting the file", e))?;
        let schema = w
            .add_schema(
                msg::EVENT_PACKET,
                "ros2msg",
                msg::event_packet_definition().as_bytes(),
            )
            .map_err(|e| mcap_error("schema", e))?;
        let mut metadata = BTreeMap::new();
        metadata.insert("offered_qos_profiles".to_string(), String::new());
        let channel = w
            .add_channel(schema, DEFAULT_TOPIC, "cdr", &metadata)
            .map_err(|e| mcap_error("channel", e))?;
        Ok(Encoder {
            writer: Some(w),
            channel,
            packets,
            ready: Vec::new(),
        })
    }

    fn write_ready(&mut self) -> Result<()> {
        let Some(w) = self.writer.as_mut() else {
            return Err(Error::invalid("MCAP output", "already finished"));
        };
        for p in self.ready.drain(..) {
            let p = p.msg;
            let t = log_time(&p);
            let header = mcap::records::MessageHeader {
                channel_id: self.channel,
                sequence: p.seq as u32,
                log_time: t,
                publish_time: t,
            };
            w.write_to_known_channel(&header, &p.to_cdr())
                .map_err(|e| mcap_error("writing a message", e))?;
        }
        Ok(())
    }
}

impl<W: Write + Seek> EventEncoder for Encoder<W> {
    fn write(&mut self, events: &[Event]) -> Result<()> {
        self.packets.push(events, &mut self.ready)?;
        self.write_ready()
    }

    fn finish(&mut self) -> Result<()> {
        self.packets.close(&mut self.ready);
        self.write_ready()?;
        if let Some(mut w) = self.writer.take() {
            w.finish().map_err(|e| mcap_error("closing the file", e))?;
            w.into_inner()
                .flush()
                .map_err(|e| mcap_error("closing the file", e))?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<()> {
        self.packets.close(&mut self.ready);
        self.write_ready()?;
        if let Some(w) = self.writer.as_mut() {
            w.flush().map_err(|e| mcap_error("flushing", e))?;
        }
        Ok(())
    }
}

/// Reads the EventPacket messages of one topic as events.
pub struct Decoder<R: Read> {
    messages: mcap::io::MessageReader<R>,
    topic: Option<String>,
    size: Option<(u16, u16)>,
    pending: Vec<Event>,
    taken: usize,
    last_t: i64,
    /// Events at pixels outside a packet's sensor, dropped.
    pub off_sensor: u64,
    skipped_topics: Vec<String>,
}

impl Decoder<BufReader<std::fs::File>> {
    /// Opens a bag; `topic` chooses the events' topic (else the first EventPacket topic).
    pub fn open(path: &Path, topic: Option<&str>) -> Result<Self> {
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        Decoder::new(BufReader::with_capacity(1 << 16, file), topic)
    }
}

/// A reader of a bag's messages in file order: a record may claim no more than a chunk may
/// ([`crate::limits::MAX_CHUNK_BYTES`]), and zstd chunks (rosbag2's `zstd_fast` and
/// `zstd_small` presets) are decompressed.
pub fn message_reader<R: Read>(reader: R) -> Result<mcap::io::MessageReader<R>> {
    let options = mcap::sans_io::LinearReaderOptions::default()
        .with_record_length_limit(crate::limits::MAX_CHUNK_BYTES as usize);
    let mut r = mcap::io::MessageReader::new_with_options(reader, options);
    r.add_decompressor(ZstdChunks::default())
        .map_err(|e| mcap_error("zstd", e))?;
    Ok(r)
}

/// zstd chunks, decompressed as a stream (the `zstd` crate the project already builds).
#[derive(Default)]
struct ZstdChunks {
    stream: Option<zstd::zstd_safe::DStream<'static>>,
    /// The decoder's hint of the input it wants next (0: any).
    hint: usize,
}

fn zstd_error(code: usize) -> mcap::McapError {
    mcap::McapError::DecompressionError(zstd::zstd_safe::get_error_name(code).into())
}

impl mcap::sans_io::decompressor::Decompressor for ZstdChunks {
    fn next_read_size(&self) -> usize {
        self.hint
    }

    fn decompress(
        &mut self,
        src: &[u8],
        dst: &mut [u8],
    ) -> mcap::McapResult<mcap::sans_io::decompressor::DecompressResult> {
        let stream = match &mut self.stream {
            Some(s) => s,
            None => {
                let mut s = zstd::zstd_safe::DStream::create();
                s.init().map_err(zstd_error)?;
                self.stream.insert(s)
            }
        };
        let mut input = zstd::zstd_safe::InBuffer::around(src);
        let mut output = zstd::zstd_safe::OutBuffer::around(dst);
        self.hint = stream
            .decompress_stream(&mut output, &mut input)
            .map_err(zstd_error)?;
        Ok(mcap::sans_io::decompressor::DecompressResult {
            consumed: input.pos,
            wrote: output.pos(),
        })
    }

    fn reset(&mut self) -> mcap::McapResult<()> {
        self.hint = 0;
        if let Some(s) = &mut self.stream {
            s.reset(zstd::zstd_safe::ResetDirective::SessionOnly)
                .map_err(zstd_error)?;
        }
        Ok(())
    }

    fn name(&self) -> &'static str {
        "zstd"
    }
}

impl<R: Read> Decoder<R> {
    /// A decoder over a bag's bytes; reads up to the first packet to learn the sensor's size.
    pub fn new(reader: R, topic: Option<&str>) -> Result<Self> {
        let mut d = Decoder {
            messages: message_reader(reader)?,
            topic: topic.map(str::to_string),
            size: None,
            pending: Vec::new(),
            taken: 0,
            last_t: i64::MIN,
            off_sensor: 0,
            skipped_topics: Vec::new(),
        };
        d.fill()?;
        Ok(d)
    }

    /// Reads messages until one holds events (or the end); false at the end.
    fn fill(&mut self) -> Result<bool> {
        self.pending.clear();
        self.taken = 0;
        while self.pending.is_empty() {
            let Some(m) = self.messages.next() else {
                return Ok(false);
            };
            let m = m.map_err(|e| mcap_error("reading", e))?;
            let is_packets = m
                .channel
                .schema
                .as_ref()
                .is_some_and(|s| s.name == msg::EVENT_PACKET);
            if !is_packets {
                continue;
            }
            match &self.topic {
                None => self.topic = Some(m.channel.topic.clone()),
                Some(t) if *t != m.channel.topic => {
                    if !self.skipped_topics.contains(&m.channel.topic) {
                        tracing::warn!(
                            "{}: EventPacket messages on {} too; reading {t} only",
                            "MCAP",
                            m.channel.topic
                        );
                        self.skipped_topics.push(m.channel.topic.clone());
                    }
                    continue;
                }
                Some(_) => {}
            }
            if m.channel.message_encoding != "cdr" {
                return Err(Error::invalid(
                    "MCAP",
                    format!(
                        "channel {} holds '{}' messages (v2ce reads cdr)",
                        m.channel.topic, m.channel.message_encoding
                    ),
                ));
            }
            let p = EventPacket::from_cdr(&m.data).map_err(|e| {
                mcap_error(&format!("message {} on {}", m.sequence, m.channel.topic), e)
            })?;
            let size = (p.width as u16, p.height as u16);
            let u = unpack(&p, &mut self.pending)?;
            self.off_sensor += u.off_sensor;
            if u.events > 0 && self.size.is_none() {
                self.size = Some(size);
            }
            // Packets whose stamps step back a little (a driver's stamps) are kept in order.
            for e in &mut self.pending {
                e.t = e.t.max(self.last_t);
                self.last_t = e.t;
            }
        }
        Ok(true)
    }
}

impl<R: Read> EventDecoder for Decoder<R> {
    fn size(&self) -> Option<(u16, u16)> {
        self.size
    }

    fn read_events(&mut self, out: &mut Vec<Event>, max: usize) -> Result<usize> {
        if self.taken == self.pending.len() && !self.fill()? {
            return Ok(0);
        }
        let n = max.min(self.pending.len() - self.taken);
        out.extend_from_slice(&self.pending[self.taken..self.taken + n]);
        self.taken += n;
        Ok(n)
    }
}

fn count_events(path: &Path) -> Result<u64> {
    let mut d = Decoder::open(path, None)?;
    let (mut n, mut buf) = (0u64, Vec::new());
    loop {
        buf.clear();
        match d.read_events(&mut buf, 1 << 16)? {
            0 => return Ok(n),
            k => n += k as u64,
        }
    }
}

/// The ends of the whole records after the magic, up to a data end or footer (where a writer
/// had begun closing) or the first record cut short; an error for a file without the magic.
fn record_ends(path: &Path) -> Result<Vec<u64>> {
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = f.metadata().map_err(|e| Error::io(path, e))?.len();
    let mut r = BufReader::new(f);
    let mut magic = [0u8; 8];
    if r.read_exact(&mut magic).is_err() || &magic != MAGIC {
        return Err(Error::format(path, "not an MCAP file (no magic)"));
    }
    let mut ends = Vec::new();
    let mut end = 8u64;
    loop {
        let mut head = [0u8; 9];
        if end + 9 > len || r.read_exact(&mut head).is_err() {
            break;
        }
        if head[0] == 0x0F || head[0] == 0x02 {
            break;
        }
        let body = u64::from_le_bytes(head[1..9].try_into().unwrap_or_default());
        let Some(next) = (end + 9).checked_add(body).filter(|n| *n <= len) else {
            break;
        };
        r.seek_relative(body as i64)
            .map_err(|e| Error::io(path, e))?;
        end = next;
        ends.push(end);
    }
    Ok(ends)
}

/// The length of `path`'s whole part: all of it when it reads whole, else the end of its last
/// whole record (for `repair`, which cuts there and closes it with [`close_after_cut`]).
pub fn whole_prefix(path: &Path) -> Result<u64> {
    if count_events(path).is_ok() {
        return Ok(std::fs::metadata(path)
            .map_err(|e| Error::io(path, e))?
            .len());
    }
    Ok(record_ends(path)?.last().copied().unwrap_or(8))
}

/// The closing records of a bag cut after a whole record: a data end, a footer without a
/// summary, the magic (51 bytes).
fn closing_bytes() -> Vec<u8> {
    let mut tail = Vec::with_capacity(51);
    // Data end: opcode 0x0F, length 4, data section CRC 0 (not checked).
    tail.push(0x0F);
    tail.extend_from_slice(&4u64.to_le_bytes());
    tail.extend_from_slice(&0u32.to_le_bytes());
    // Footer: opcode 0x02, length 20, no summary.
    tail.push(0x02);
    tail.extend_from_slice(&20u64.to_le_bytes());
    tail.extend_from_slice(&[0u8; 20]);
    tail.extend_from_slice(MAGIC);
    tail
}

/// Closes a bag that `repair` has cut after its last whole record (appends
/// [`closing_bytes`]).
pub fn close_after_cut(path: &Path) -> Result<()> {
    let mut f = std::fs::OpenOptions::new()
        .append(true)
        .open(path)
        .map_err(|e| Error::io(path, e))?;
    f.write_all(&closing_bytes())
        .and_then(|_| f.sync_all())
        .map_err(|e| Error::io(path, e))
}

/// Closes a bag whose writing stopped (a full disk, a killed run) in place: a bag that reads
/// whole is left as it is; another is cut after its last whole record and closed with a data
/// end, a footer and the magic (51 bytes; where even those do not fit, one more record is cut
/// away). Returns the events it then holds. A file that does not start with the magic is
/// refused.
pub fn close_in_place(path: &Path) -> Result<u64> {
    if let Ok(n) = count_events(path) {
        return Ok(n);
    }
    let ends = record_ends(path)?;
    let mut end = ends.last().copied().unwrap_or(8);
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .open(path)
        .map_err(|e| Error::io(path, e))?;
    let tail = closing_bytes();
    loop {
        let closed = f
            .set_len(end)
            .and_then(|_| f.seek(SeekFrom::Start(end)))
            .and_then(|_| f.write_all(&tail))
            .and_then(|_| f.sync_all());
        match closed {
            Ok(()) => break,
            Err(e) => {
                // No room for the closing bytes: give up the last record and try again.
                match ends.iter().rev().find(|e| **e < end) {
                    Some(&before) if e.raw_os_error() == Some(libc::ENOSPC) => end = before,
                    _ => return Err(Error::io(path, e)),
                }
            }
        }
    }
    drop(f);
    count_events(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `tests/fixtures/zstd_chunks.mcap`: written by the `mcap` crate with zstd chunks of 16 KiB
    /// (its default features), EventPacket messages on `/dvs/events` and five rgb8 Images.
    #[test]
    fn zstd_chunked_bags_are_read() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/zstd_chunks.mcap");
        let expected: Vec<Event> = (0..8_000i64)
            .map(|i| {
                Event::new(
                    5_000_000 + i * 7,
                    (i % 97) as u16,
                    (i % 61) as u16,
                    i % 3 == 0,
                )
            })
            .collect();
        let mut d = Decoder::open(&path, None).unwrap();
        assert_eq!(d.size(), Some((128, 64)));
        let mut back = Vec::new();
        while d.read_events(&mut back, 1000).unwrap() > 0 {}
        assert_eq!(back, expected);
        let mut frames = crate::frame::ros_image::BagSource::open(&path, None).unwrap();
        let mut n = 0;
        while let Some(f) = crate::frame::FrameSource::next_frame(&mut frames).unwrap() {
            assert_eq!((f.width, f.height, f.t), (32, 24, 5_000_000 + n * 40_000));
            n += 1;
        }
        assert_eq!(n, 5);
    }

    #[test]
    fn a_bag_round_trips_and_a_cut_one_is_closed_with_its_whole_messages() {
        let events: Vec<Event> = (0..20_000)
            .map(|i| Event::new(i * 13, (i % 300) as u16, (i % 200) as u16, i % 2 == 0))
            .collect();
        let dir = std::env::temp_dir().join(format!("v2ce-mcap-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.mcap");
        let file = std::fs::File::create(&path).unwrap();
        let mut enc = Encoder::new(std::io::BufWriter::new(file), 320, 240).unwrap();
        enc.write(&events[..7000]).unwrap();
        enc.write(&events[7000..]).unwrap();
        enc.finish().unwrap();
        drop(enc);
        let mut d = Decoder::open(&path, None).unwrap();
        assert_eq!(d.size(), Some((320, 240)));
        let mut back = Vec::new();
        while d.read_events(&mut back, 4096).unwrap() > 0 {}
        assert_eq!(back, events);
        assert!(Decoder::open(&path, Some("/other")).is_ok());

        // Cut in the middle of a message: closed with the messages before it.
        let bytes = std::fs::read(&path).unwrap();
        let cut = dir.join("b.mcap");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let n = close_in_place(&cut).unwrap();
        assert!(n > 0 && n < events.len() as u64, "{n}");
        let mut d = Decoder::open(&cut, None).unwrap();
        let mut again = Vec::new();
        while d.read_events(&mut again, 4096).unwrap() > 0 {}
        assert_eq!(again.len() as u64, n);
        assert_eq!(&again[..], &events[..n as usize]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
