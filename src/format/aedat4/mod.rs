//! AEDAT 4.0, the DV software's container: our own bounded decoder and encoder.
//!
//! A file is the magic `#!AER-DAT4.0\r\n`, a little-endian `u32` size and an `IOHeader`
//! flatbuffer (compression, data-table position, and an XML description of the streams with
//! their `typeIdentifier` and `sizeX`/`sizeY`), then packets: `i32` stream id, `i32` size, and
//! that many bytes of a size-prefixed flatbuffer (`EVTS` events, `FRME` frames, ...), compressed
//! as the header says (LZ4 frame or Zstd). At `dataTablePosition` a compressed `FileDataTable`
//! lists every packet. DV's network stream is the same without the magic and the data table
//! (see [`crate::sink::tcp`]). The flatbuffer tables are in [`flatbuf`].
//!
//! A frame's time is the middle of its exposure, `(exposure_begin + exposure_end) / 2`: the
//! instant the image stands for (the IJRR export of the same recording uses it too).
//!
//! Limits: a packet may hold at most [`MAX_PACKET_BYTES`] before or after decompression, and
//! decompress to at most [`MAX_RATIO`] times its size beyond [`RATIO_FREE_BYTES`]; the header at
//! most [`MAX_HEADER_BYTES`]. Larger sizes are reported as corruption before anything is
//! allocated (a few kilobytes of Zstd cannot claim hundreds of megabytes).

pub mod flatbuf;

use std::collections::VecDeque;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::Path;

use flatbuffers::FlatBufferBuilder;

use self::flatbuf::{DataDefinition, Table, EVENT_BYTES};
use super::{EventDecoder, EventEncoder, Recording};
use crate::error::{Error, Result};
use crate::event::Event;

/// The file magic.
pub const MAGIC: &[u8; 14] = b"#!AER-DAT4.0\r\n";
/// Largest packet accepted, compressed or not.
pub const MAX_PACKET_BYTES: usize = 256 << 20;
/// Largest ratio of a packet's decompressed to compressed size accepted once it decompresses to
/// more than [`RATIO_FREE_BYTES`]. LZ4 cannot exceed about 255; real event packets compress 3 to
/// 10 times; only frames of one flat colour come near it, and those up to 2048 x 2048 RGBA fit
/// under [`RATIO_FREE_BYTES`] whatever their ratio.
pub const MAX_RATIO: usize = 1024;
/// Decompressed size allowed whatever the ratio.
pub const RATIO_FREE_BYTES: usize = 16 << 20;
/// Largest `IOHeader` accepted.
pub const MAX_HEADER_BYTES: usize = 16 << 20;
/// Events per packet written by [`Writer`].
pub const PACKET_EVENTS: usize = 4096;

const WHAT: &str = "AEDAT 4.0 stream";

fn bad(message: impl Into<String>) -> Error {
    Error::invalid(WHAT, message)
}

/// Packet compression.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Compression {
    /// None (what DV's network stream uses).
    None,
    /// LZ4 frames (DV's default for files).
    #[default]
    Lz4,
    /// LZ4 frames marked high-compression (read only; written as [`Compression::Lz4`]).
    Lz4High,
    /// Zstd frames, level 3.
    Zstd,
    /// Zstd frames, level 19.
    ZstdHigh,
}

impl Compression {
    /// The `IOHeader` code.
    pub fn code(self) -> i32 {
        match self {
            Compression::None => 0,
            Compression::Lz4 => 1,
            Compression::Lz4High => 2,
            Compression::Zstd => 3,
            Compression::ZstdHigh => 4,
        }
    }

    fn from_code(code: i32) -> Result<Self> {
        Ok(match code {
            0 => Compression::None,
            1 => Compression::Lz4,
            2 => Compression::Lz4High,
            3 => Compression::Zstd,
            4 => Compression::ZstdHigh,
            _ => return Err(bad(format!("unknown compression code {code}"))),
        })
    }

    /// The name used in the XML description.
    pub fn xml_name(self) -> &'static str {
        match self {
            Compression::None => "NONE",
            Compression::Lz4 => "LZ4",
            Compression::Lz4High => "LZ4_HIGH",
            Compression::Zstd => "ZSTD",
            Compression::ZstdHigh => "ZSTD_HIGH",
        }
    }

    /// Parses `none`, `lz4`, `zstd` or `zstd-high` (any case).
    pub fn from_name(name: &str) -> Result<Self> {
        match name.to_ascii_lowercase().replace('_', "-").as_str() {
            "none" => Ok(Compression::None),
            "lz4" => Ok(Compression::Lz4),
            "lz4-high" => Ok(Compression::Lz4High),
            "zstd" => Ok(Compression::Zstd),
            "zstd-high" => Ok(Compression::ZstdHigh),
            _ => Err(Error::invalid(
                "compression",
                format!("'{name}' (expected none, lz4, zstd or zstd-high)"),
            )),
        }
    }

    /// Compresses one packet's bytes.
    pub fn compress(self, data: &[u8], out: &mut Vec<u8>) -> Result<()> {
        out.clear();
        let fail = |e: String| Error::invalid("AEDAT 4.0 compression", e);
        match self {
            Compression::None => out.extend_from_slice(data),
            Compression::Lz4 | Compression::Lz4High => {
                let mut enc = lz4_flex::frame::FrameEncoder::new(std::mem::take(out));
                enc.write_all(data).map_err(|e| fail(e.to_string()))?;
                *out = enc.finish().map_err(|e| fail(e.to_string()))?;
            }
            Compression::Zstd | Compression::ZstdHigh => {
                let level = if self == Compression::Zstd { 3 } else { 19 };
                // One-shot compression records the content size in the frame header, which
                // dv-processing requires.
                *out = zstd::bulk::compress(data, level).map_err(|e| fail(e.to_string()))?;
            }
        }
        Ok(())
    }

    /// Decompresses one packet's bytes, refusing more than [`MAX_PACKET_BYTES`] or more than
    /// [`MAX_RATIO`] times `data` beyond [`RATIO_FREE_BYTES`].
    pub fn decompress(self, data: &[u8], out: &mut Vec<u8>) -> Result<()> {
        out.clear();
        let allowed = data
            .len()
            .saturating_mul(MAX_RATIO)
            .clamp(RATIO_FREE_BYTES, MAX_PACKET_BYTES);
        let limit = allowed as u64 + 1;
        let result = match self {
            Compression::None => {
                out.extend_from_slice(data);
                Ok(data.len())
            }
            Compression::Lz4 | Compression::Lz4High => lz4_flex::frame::FrameDecoder::new(data)
                .take(limit)
                .read_to_end(out),
            Compression::Zstd | Compression::ZstdHigh => {
                zstd::stream::Decoder::new(data).and_then(|d| d.take(limit).read_to_end(out))
            }
        };
        match result {
            Ok(n) if n > allowed => Err(bad(format!(
                "a packet of {} bytes decompresses to more than {allowed} bytes (at most \
                 {MAX_PACKET_BYTES}, and {MAX_RATIO} times its size beyond {RATIO_FREE_BYTES})",
                data.len()
            ))),
            Ok(_) => Ok(()),
            Err(e) => Err(bad(format!(
                "{} decompression failed: {e}",
                self.xml_name()
            ))),
        }
    }
}

/// What a stream carries, from its `typeIdentifier`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StreamInfo {
    /// Stream id used in packet headers.
    pub id: i32,
    /// `EVTS`, `FRME`, `IMUS`, `TRIG`, ...
    pub type_identifier: String,
    /// `sizeX`/`sizeY`, for event and frame streams.
    pub size: Option<(u16, u16)>,
}

/// The XML description for one event stream, as DV writes it.
pub fn description(width: u16, height: u16, compression: Compression, source: &str) -> String {
    let source = xml_escape(source);
    let c = compression.xml_name();
    format!(
        r#"<dv version="2.0">
    <node name="outInfo" path="/outInfo/">
        <node name="0" path="/outInfo/0/">
            <attr key="compression" type="string">{c}</attr>
            <attr key="originalModuleName" type="string">v2ce</attr>
            <attr key="originalOutputName" type="string">events</attr>
            <attr key="typeDescription" type="string">Array of events (polarity ON/OFF).</attr>
            <attr key="typeIdentifier" type="string">EVTS</attr>
            <node name="info" path="/outInfo/0/info/">
                <attr key="sizeX" type="int">{width}</attr>
                <attr key="sizeY" type="int">{height}</attr>
                <attr key="source" type="string">{source}</attr>
            </node>
        </node>
    </node>
</dv>
"#
    )
}

fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

fn child<'a, 'i>(
    n: roxmltree::Node<'a, 'i>,
    tag: &str,
    key: &str,
    value: &str,
) -> Option<roxmltree::Node<'a, 'i>> {
    n.children()
        .find(|c| c.has_tag_name(tag) && c.attribute(key) == Some(value))
}

fn text<'a>(n: Option<roxmltree::Node<'a, '_>>) -> Option<&'a str> {
    n.and_then(|n| n.text()).map(str::trim)
}

/// Parses the streams out of an XML description.
pub fn parse_description(xml: &str) -> Result<Vec<StreamInfo>> {
    let doc = roxmltree::Document::parse(xml)
        .map_err(|e| bad(format!("the XML description does not parse: {e}")))?;
    let out_info = doc
        .root_element()
        .children()
        .find(|c| c.has_tag_name("node") && c.attribute("name") == Some("outInfo"))
        .ok_or_else(|| bad("the description has no outInfo node"))?;
    let mut streams = Vec::new();
    for node in out_info.children().filter(|c| c.has_tag_name("node")) {
        let id = node
            .attribute("name")
            .and_then(|n| n.parse::<i32>().ok())
            .ok_or_else(|| bad("a stream node has no numeric name"))?;
        let type_identifier = text(child(node, "attr", "key", "typeIdentifier"))
            .ok_or_else(|| bad(format!("stream {id} has no typeIdentifier")))?
            .to_string();
        let info = child(node, "node", "name", "info");
        let dim = |key: &str| {
            info.and_then(|i| text(child(i, "attr", "key", key)))
                .and_then(|v| v.parse::<u16>().ok())
        };
        let size = match (dim("sizeX"), dim("sizeY")) {
            (Some(w), Some(h)) => Some((w, h)),
            _ => None,
        };
        if streams.iter().any(|s: &StreamInfo| s.id == id) {
            return Err(bad(format!("stream id {id} appears twice")));
        }
        streams.push(StreamInfo {
            id,
            type_identifier,
            size,
        });
    }
    Ok(streams)
}

/// The parsed `IOHeader`.
#[derive(Debug, Clone)]
pub struct IoHeader {
    /// Packet compression.
    pub compression: Compression,
    /// Where the file data table starts, or -1.
    pub data_table_position: i64,
    /// The streams the description lists.
    pub streams: Vec<StreamInfo>,
    /// Bytes the header took, its size word included.
    pub bytes: u64,
}

/// Reads a `u32` size and the `IOHeader` after it (what follows the magic in a file, and what
/// a network stream starts with).
pub fn read_io_header(r: &mut impl Read) -> Result<IoHeader> {
    let mut size = [0u8; 4];
    r.read_exact(&mut size)
        .map_err(|e| bad(format!("no IOHeader size: {e}")))?;
    let size = u32::from_le_bytes(size) as usize;
    if size > MAX_HEADER_BYTES {
        return Err(bad(format!(
            "IOHeader of {size} bytes (limit {MAX_HEADER_BYTES})"
        )));
    }
    let mut buf = vec![0u8; size];
    r.read_exact(&mut buf)
        .map_err(|e| bad(format!("IOHeader cut short: {e}")))?;
    let t = Table::root(&buf, b"IOHE").map_err(|e| bad(format!("bad IOHeader: {e}")))?;
    let fb = |e: String| bad(format!("bad IOHeader: {e}"));
    let compression = Compression::from_code(t.i32(0, 0).map_err(fb)?)?;
    let data_table_position = t.i64(1, -1).map_err(fb)?;
    let xml = t
        .string(2)
        .map_err(fb)?
        .ok_or_else(|| bad("the IOHeader has no description"))?;
    Ok(IoHeader {
        compression,
        data_table_position,
        streams: parse_description(xml)?,
        bytes: 4 + size as u64,
    })
}

/// Builds the `u32` size and `IOHeader` bytes.
pub fn io_header_bytes(compression: Compression, data_table_position: i64, xml: &str) -> Vec<u8> {
    let mut fbb = FlatBufferBuilder::new();
    flatbuf::build_io_header(&mut fbb, compression.code(), data_table_position, xml);
    let data = fbb.finished_data();
    let mut out = Vec::with_capacity(data.len() + 4);
    out.extend_from_slice(&(data.len() as u32).to_le_bytes());
    out.extend_from_slice(data);
    out
}

/// An APS frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    /// Mid-exposure time (or the frame's time when it has no exposure times).
    pub t: i64,
    /// Start and end of exposure.
    pub exposure: (i64, i64),
    /// Width and height.
    pub size: (u16, u16),
    /// Channels per pixel: 1 gray, 3 BGR, 4 BGRA.
    pub channels: u8,
    /// Row-major pixels, `channels` bytes each.
    pub pixels: Vec<u8>,
}

fn decode_frame(buf: &[u8]) -> std::result::Result<Frame, String> {
    let t = Table::size_prefixed_root(buf, b"FRME")?;
    let time = t.i64(0, 0)?;
    let exposure = (t.i64(3, 0)?, t.i64(4, 0)?);
    let channels = match t.i8(5, 0)? {
        0 => 1,
        16 => 3,
        24 => 4,
        f => return Err(format!("unknown frame format {f}")),
    };
    let (w, h) = (t.i16(6, 0)?, t.i16(7, 0)?);
    if w < 0 || h < 0 {
        return Err(format!("negative frame size {w} x {h}"));
    }
    let pixels = t.vector(10, 1)?.unwrap_or(&[]);
    let expected = w as usize * h as usize * channels as usize;
    if pixels.len() != expected {
        return Err(format!(
            "{} pixel bytes for a {w} x {h} frame with {channels} channel(s)",
            pixels.len()
        ));
    }
    let (b, e) = exposure;
    Ok(Frame {
        t: if e >= b && b > 0 {
            b + (e - b) / 2
        } else {
            time
        },
        exposure,
        size: (w as u16, h as u16),
        channels,
        pixels: pixels.to_vec(),
    })
}

/// One decoded packet.
#[derive(Debug, Clone)]
pub enum Item {
    /// Events of the reader's event stream.
    Events(Vec<Event>),
    /// A frame of a frame stream.
    Frame(Frame),
    /// A packet of another stream (IMU, triggers, a second event stream), not decoded.
    Other(i32),
}

/// Reads AEDAT 4.0 packets from a file or a network stream.
pub struct Reader<R> {
    reader: R,
    header: IoHeader,
    /// The event stream decoded as [`Item::Events`]: the lowest-numbered `EVTS` stream.
    event_stream: Option<StreamInfo>,
    position: u64,
    packets: u64,
    /// The header's data table position pointed inside the header: ignored, and packets are
    /// read until something that is not one (the table, presumably).
    table_lost: bool,
    raw: Vec<u8>,
    data: Vec<u8>,
    pending: VecDeque<Event>,
}

impl<R: Read> Reader<R> {
    /// Reads the magic and header of a file.
    pub fn new_file(mut reader: R) -> Result<Self> {
        let mut magic = [0u8; MAGIC.len()];
        reader
            .read_exact(&mut magic)
            .map_err(|_| bad("shorter than the AEDAT 4.0 magic"))?;
        if &magic != MAGIC {
            return Err(bad("not AEDAT 4.0 (wrong magic)"));
        }
        Self::after_magic(reader, MAGIC.len() as u64)
    }

    /// Reads the header of a network stream (no magic, no data table).
    pub fn new_stream(reader: R) -> Result<Self> {
        let mut r = Self::after_magic(reader, 0)?;
        r.header.data_table_position = -1;
        Ok(r)
    }

    fn after_magic(mut reader: R, position: u64) -> Result<Self> {
        let mut header = read_io_header(&mut reader)?;
        let end = position + header.bytes;
        let table_lost =
            header.data_table_position >= 0 && (header.data_table_position as u64) < end;
        if table_lost {
            tracing::warn!(
                "AEDAT 4.0: the header's data table position {} lies inside the header (which \
                 ends at byte {end}); reading packets until the first that is not one",
                header.data_table_position
            );
            header.data_table_position = -1;
        }
        let event_stream = header
            .streams
            .iter()
            .filter(|s| s.type_identifier == "EVTS")
            .min_by_key(|s| s.id)
            .cloned();
        let position = position + header.bytes;
        Ok(Reader {
            reader,
            header,
            event_stream,
            position,
            packets: 0,
            table_lost,
            raw: Vec::new(),
            data: Vec::new(),
            pending: VecDeque::new(),
        })
    }

    /// The header.
    pub fn header(&self) -> &IoHeader {
        &self.header
    }

    /// The bytes from the file's start to the end of the last whole packet read (after the
    /// header when none was).
    pub fn whole_bytes(&self) -> u64 {
        self.position
    }

    /// The event stream that [`Item::Events`] comes from.
    pub fn event_stream(&self) -> Option<&StreamInfo> {
        self.event_stream.as_ref()
    }

    /// The next packet, or `None` at the end of the packets (end of input at a packet
    /// boundary, or the data table).
    pub fn next_item(&mut self) -> Result<Option<Item>> {
        let table = self.header.data_table_position;
        if table >= 0 && self.position >= table as u64 {
            return Ok(None);
        }
        let index = self.packets;
        // A file without its data table was not finished (its writer was killed, the machine
        // lost power): a last packet cut short is what was being written then, and everything
        // before it is whole.
        let unfinished = table < 0;
        let cut = |byte: u64, what: &str| {
            tracing::warn!(
                "AEDAT 4.0: the input ends inside packet {index} (byte {byte}, {what}) and has no \
                 data table: an unfinished file; the {index} whole packets before it are read"
            );
        };
        let mut head = [0u8; 8];
        let mut got = 0;
        while got < 8 {
            match self.reader.read(&mut head[got..]) {
                Ok(0) => break,
                Ok(k) => got += k,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(bad(format!("packet {index}: {e}"))),
            }
        }
        match got {
            0 => return Ok(None),
            8 => {}
            _ if unfinished => {
                cut(self.position, "its header");
                return Ok(None);
            }
            _ => {
                return Err(bad(format!(
                    "packet {index} (byte {}): the input ends inside its header",
                    self.position
                )))
            }
        }
        let stream_id = i32::from_le_bytes([head[0], head[1], head[2], head[3]]);
        let size = i32::from_le_bytes([head[4], head[5], head[6], head[7]]);
        let byte = self.position;
        let at = |m: String| bad(format!("packet {index} (byte {byte}): {m}"));
        let known = self.header.streams.iter().find(|s| s.id == stream_id);
        let plausible = size >= 0 && (size as usize) <= MAX_PACKET_BYTES && known.is_some();
        if !plausible && self.table_lost && index > 0 {
            tracing::warn!(
                "AEDAT 4.0: stopped at byte {byte}, which is not a packet (the data table the \
                 damaged header lost, presumably), after {index} packets"
            );
            return Ok(None);
        }
        if size < 0 || size as usize > MAX_PACKET_BYTES {
            return Err(at(format!("size {size} out of range")));
        }
        let stream = known
            .ok_or_else(|| at(format!("unknown stream id {stream_id}")))?
            .clone();
        self.raw.clear();
        let got = (&mut self.reader)
            .take(size as u64)
            .read_to_end(&mut self.raw)
            .map_err(|e| at(e.to_string()))?;
        if got != size as usize {
            if unfinished {
                cut(byte, &format!("{got} of its {size} bytes"));
                return Ok(None);
            }
            return Err(at(format!("cut short: {got} of {size} bytes")));
        }
        self.position += 8 + size as u64;
        self.packets += 1;
        let is_events = self
            .event_stream
            .as_ref()
            .is_some_and(|s| s.id == stream_id);
        if !is_events && stream.type_identifier != "FRME" {
            return Ok(Some(Item::Other(stream_id)));
        }
        self.header
            .compression
            .decompress(&self.raw, &mut self.data)
            .map_err(|e| at(e.to_string()))?;
        if is_events {
            let t = Table::size_prefixed_root(&self.data, b"EVTS").map_err(&at)?;
            let bytes = t.vector(0, EVENT_BYTES).map_err(&at)?.unwrap_or(&[]);
            let mut events = Vec::new();
            flatbuf::decode_events(bytes, &mut events).map_err(&at)?;
            if let Some((w, h)) = stream.size {
                if let Some(e) = events.iter().find(|e| e.x >= w || e.y >= h) {
                    return Err(at(format!(
                        "event at ({}, {}) outside the {w} x {h} sensor",
                        e.x, e.y
                    )));
                }
            }
            Ok(Some(Item::Events(events)))
        } else {
            Ok(Some(Item::Frame(decode_frame(&self.data).map_err(at)?)))
        }
    }
}

impl<R: Read> EventDecoder for Reader<R> {
    fn size(&self) -> Option<(u16, u16)> {
        self.event_stream.as_ref().and_then(|s| s.size)
    }

    fn read_events(&mut self, out: &mut Vec<Event>, max: usize) -> Result<usize> {
        if self.event_stream.is_none() {
            return Err(bad("the file has no event stream"));
        }
        let start = out.len();
        while out.len() - start < max {
            if self.pending.is_empty() {
                match self.next_item()? {
                    Some(Item::Events(events)) => self.pending.extend(events),
                    Some(_) => continue,
                    None => break,
                }
            }
            let take = (max - (out.len() - start)).min(self.pending.len());
            out.extend(self.pending.drain(..take));
        }
        Ok(out.len() - start)
    }
}

/// Reads the events and the APS frame times of an AEDAT 4.0 file.
pub fn read(path: &Path) -> Result<(Recording, Vec<i64>)> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let wrap = |e: Error| Error::format(path, e.to_string());
    let mut reader = Reader::new_file(std::io::BufReader::new(file)).map_err(wrap)?;
    let size = reader
        .event_stream()
        .ok_or_else(|| Error::format(path, "no event stream"))?
        .size;
    let mut events = Vec::new();
    let mut frames = Vec::new();
    while let Some(item) = reader.next_item().map_err(wrap)? {
        match item {
            Item::Events(e) => events.extend(e),
            Item::Frame(f) => frames.push(f.t),
            Item::Other(_) => {}
        }
    }
    frames.sort_unstable();
    frames.dedup();
    Ok((Recording::new(events, size), frames))
}

/// Writes an AEDAT 4.0 file with one event stream.
///
/// Events are grouped into packets of up to [`PACKET_EVENTS`]; [`EventEncoder::finish`] writes
/// the last packet and the data table and, for a seekable output, patches the header's
/// data-table position.
pub struct Writer<W: Write + Seek> {
    writer: W,
    compression: Compression,
    width: u16,
    height: u16,
    position: u64,
    /// Byte offset of the data-table position inside the file (an `i64`).
    table_field: u64,
    table: Vec<DataDefinition>,
    pending: Vec<Event>,
    fbb: FlatBufferBuilder<'static>,
    compressed: Vec<u8>,
    /// One packet, header and body, as written.
    packet: Vec<u8>,
    last_t: i64,
    finished: bool,
}

fn output_error(e: std::io::Error) -> Error {
    Error::invalid("AEDAT 4.0 output", e.to_string())
}

impl<W: Write + Seek> Writer<W> {
    /// Writes the magic and header for a `width x height` event stream.
    pub fn new(mut writer: W, width: u16, height: u16, compression: Compression) -> Result<Self> {
        check_size(width, height)?;
        let compression = match compression {
            Compression::Lz4High => Compression::Lz4,
            c => c,
        };
        let xml = description(width, height, compression, "v2ce");
        let header = io_header_bytes(compression, -1, &xml);
        let table_field = find_table_field(&header[4..])? + MAGIC.len() as u64 + 4;
        writer.write_all(MAGIC).map_err(output_error)?;
        writer.write_all(&header).map_err(output_error)?;
        Ok(Writer {
            writer,
            compression,
            width,
            height,
            position: (MAGIC.len() + header.len()) as u64,
            table_field,
            table: Vec::new(),
            pending: Vec::with_capacity(PACKET_EVENTS),
            fbb: FlatBufferBuilder::new(),
            compressed: Vec::new(),
            packet: Vec::new(),
            last_t: i64::MIN,
            finished: false,
        })
    }

    fn flush_packet(&mut self) -> Result<()> {
        if self.pending.is_empty() {
            return Ok(());
        }
        flatbuf::build_event_packet(&mut self.fbb, &self.pending);
        self.compression
            .compress(self.fbb.finished_data(), &mut self.compressed)?;
        let size = self.compressed.len() as i32;
        // Header and body in one write: a packet reaches the file whole or not at all (as far
        // as one write does), so a killed writer leaves whole packets.
        self.packet.clear();
        self.packet.extend_from_slice(&[0u8; 4]);
        self.packet.extend_from_slice(&size.to_le_bytes());
        self.packet.extend_from_slice(&self.compressed);
        self.writer.write_all(&self.packet).map_err(output_error)?;
        self.table.push(DataDefinition {
            byte_offset: self.position as i64 + 8,
            stream_id: 0,
            size,
            num_elements: self.pending.len() as i64,
            timestamp_start: self.pending[0].t,
            timestamp_end: self.pending[self.pending.len() - 1].t,
        });
        self.position += 8 + size as u64;
        self.pending.clear();
        Ok(())
    }

    /// Finishes the file and returns the writer.
    pub fn into_inner(mut self) -> Result<W> {
        EventEncoder::finish(&mut self)?;
        Ok(self.writer)
    }
}

/// Checks that a sensor size fits AEDAT 4.0's `i16` coordinates.
pub fn check_size(width: u16, height: u16) -> Result<()> {
    if width == 0 || height == 0 || width > i16::MAX as u16 || height > i16::MAX as u16 {
        return Err(Error::invalid(
            "sensor size",
            format!("AEDAT 4.0 holds 1 to 32767 columns and rows; {width} x {height} does not fit"),
        ));
    }
    Ok(())
}

/// Marks the file at `path` unfinished: its header's data-table position set to -1 (in
/// place), as for a file cut short before its table (`v2ce repair`), whose readers then take
/// the packets up to the cut.
pub fn forget_data_table(path: &Path) -> Result<()> {
    let io = |e: std::io::Error| Error::io(path, e);
    let mut file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(path)
        .map_err(io)?;
    let mut head = [0u8; MAGIC.len() + 4];
    file.read_exact(&mut head).map_err(io)?;
    if &head[..MAGIC.len()] != MAGIC {
        return Err(bad("not AEDAT 4.0 (wrong magic)"));
    }
    let n = MAGIC.len();
    let size = u32::from_le_bytes([head[n], head[n + 1], head[n + 2], head[n + 3]]) as usize;
    if size > MAX_HEADER_BYTES {
        return Err(bad(format!(
            "IOHeader of {size} bytes (limit {MAX_HEADER_BYTES})"
        )));
    }
    let mut buf = vec![0u8; size];
    file.read_exact(&mut buf).map_err(io)?;
    let at = find_table_field(&buf)? + head.len() as u64;
    file.seek(SeekFrom::Start(at))
        .and_then(|_| file.write_all(&(-1i64).to_le_bytes()))
        .map_err(io)
}

/// Offset of the data-table position `i64` inside an `IOHeader` buffer.
fn find_table_field(buf: &[u8]) -> Result<u64> {
    // Found through the vtable, so a change in the builder's layout cannot move it silently.
    let t = Table::root(buf, b"IOHE").map_err(bad)?;
    let pos = t.field_position(1).map_err(bad)?;
    pos.map(|p| p as u64)
        .ok_or_else(|| bad("the IOHeader lacks its data-table position"))
}

impl<W: Write + Seek> EventEncoder for Writer<W> {
    fn write(&mut self, events: &[Event]) -> Result<()> {
        for e in events {
            super::check_event(e, self.last_t, self.width, self.height)?;
            self.last_t = e.t;
            self.pending.push(*e);
            if self.pending.len() == PACKET_EVENTS {
                self.flush_packet()?;
            }
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<()> {
        if self.finished {
            return Ok(());
        }
        self.flush_packet()?;
        self.writer.flush().map_err(output_error)
    }

    fn finish(&mut self) -> Result<()> {
        if self.finished {
            return Ok(());
        }
        self.flush_packet()?;
        flatbuf::build_data_table(&mut self.fbb, &self.table);
        self.compression
            .compress(self.fbb.finished_data(), &mut self.compressed)?;
        self.writer
            .write_all(&self.compressed)
            .map_err(output_error)?;
        let table_at = self.position as i64;
        self.position += self.compressed.len() as u64;
        self.writer
            .seek(SeekFrom::Start(self.table_field))
            .and_then(|_| self.writer.write_all(&table_at.to_le_bytes()))
            .and_then(|_| self.writer.seek(SeekFrom::Start(self.position)))
            .and_then(|_| self.writer.flush())
            .map_err(output_error)?;
        self.finished = true;
        Ok(())
    }
}
