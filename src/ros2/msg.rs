//! The ROS 2 messages v2ce reads and writes, in CDR ([`super::cdr`]): the event camera's
//! `event_camera_msgs/msg/EventPacket` and the camera's `sensor_msgs/msg/Image`, with their
//! `std_msgs/msg/Header` and `builtin_interfaces/msg/Time`; and their `.msg` definitions, as a
//! rosbag2 file stores them for its readers.

use super::cdr::{CdrError, Reader, Writer};

/// The longest `frame_id` or `encoding` string taken from a message.
pub const MAX_STRING: usize = 4096;

/// The ROS 2 type of an event packet.
pub const EVENT_PACKET: &str = "event_camera_msgs/msg/EventPacket";
/// The ROS 2 type of a camera image.
pub const IMAGE: &str = "sensor_msgs/msg/Image";

/// `builtin_interfaces/msg/Time`: seconds and nanoseconds since the clock's epoch.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Time {
    /// Whole seconds (may be negative).
    pub sec: i32,
    /// Nanoseconds, `0..1e9`.
    pub nanosec: u32,
}

impl Time {
    /// The time of `t_us` microseconds, or `None` outside the seconds an `int32` holds.
    pub fn from_us(t_us: i64) -> Option<Self> {
        let sec = i32::try_from(t_us.div_euclid(1_000_000)).ok()?;
        let nanosec = (t_us.rem_euclid(1_000_000) * 1000) as u32;
        Some(Time { sec, nanosec })
    }

    /// Microseconds, rounded down; `None` for nanoseconds of 1e9 or more.
    pub fn to_us(self) -> Option<i64> {
        (self.nanosec < 1_000_000_000)
            .then(|| self.sec as i64 * 1_000_000 + (self.nanosec / 1000) as i64)
    }
}

/// `std_msgs/msg/Header`: a stamp and a coordinate frame.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Header {
    /// The stamp.
    pub stamp: Time,
    /// The coordinate frame.
    pub frame_id: String,
}

impl Header {
    fn write(&self, w: &mut Writer) {
        w.i32(self.stamp.sec);
        w.u32(self.stamp.nanosec);
        w.string(&self.frame_id);
    }

    fn read(r: &mut Reader) -> Result<Self, CdrError> {
        Ok(Header {
            stamp: Time {
                sec: r.i32("header.stamp.sec")?,
                nanosec: r.u32("header.stamp.nanosec")?,
            },
            frame_id: r.string("header.frame_id", MAX_STRING)?,
        })
    }
}

/// `event_camera_msgs/msg/EventPacket`: events of one sensor in a packed encoding.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct EventPacket {
    /// Stamp (the ROS time of the first event) and frame.
    pub header: Header,
    /// Sensor height.
    pub height: u32,
    /// Sensor width.
    pub width: u32,
    /// The packet's number, from 0.
    pub seq: u64,
    /// v2ce: the sensor time of the first event in nanoseconds (`evt3` leaves it undefined).
    pub time_base: u64,
    /// How `events` is packed (`evt3`).
    pub encoding: String,
    /// Whether the words are big-endian.
    pub is_bigendian: bool,
    /// The packed events.
    pub events: Vec<u8>,
}

impl EventPacket {
    /// The message in CDR.
    pub fn to_cdr(&self) -> Vec<u8> {
        let mut w = Writer::with_capacity(self.events.len() + 64 + self.header.frame_id.len());
        self.header.write(&mut w);
        w.u32(self.height);
        w.u32(self.width);
        w.u64(self.seq);
        w.u64(self.time_base);
        w.string(&self.encoding);
        w.bool(self.is_bigendian);
        w.bytes(&self.events);
        w.finish()
    }

    /// The message from CDR.
    pub fn from_cdr(data: &[u8]) -> Result<Self, CdrError> {
        let mut r = Reader::new(data)?;
        Ok(EventPacket {
            header: Header::read(&mut r)?,
            height: r.u32("height")?,
            width: r.u32("width")?,
            seq: r.u64("seq")?,
            time_base: r.u64("time_base")?,
            encoding: r.string("encoding", MAX_STRING)?,
            is_bigendian: r.bool("is_bigendian")?,
            events: r.bytes("events")?.to_vec(),
        })
    }
}

/// `sensor_msgs/msg/Image`, its pixels borrowed from the message.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Image<'a> {
    /// Stamp (the frame's time) and camera frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding (`mono8`, `rgb8`, `yuv422`, ...).
    pub encoding: String,
    /// Whether 16-bit values are big-endian.
    pub is_bigendian: bool,
    /// Bytes per row.
    pub step: u32,
    /// `height` rows of `step` bytes.
    pub data: std::borrow::Cow<'a, [u8]>,
}

impl<'a> Image<'a> {
    /// The message in CDR.
    pub fn to_cdr(&self) -> Vec<u8> {
        let mut w = Writer::with_capacity(self.data.len() + 64 + self.header.frame_id.len());
        self.header.write(&mut w);
        w.u32(self.height);
        w.u32(self.width);
        w.string(&self.encoding);
        w.bool(self.is_bigendian);
        w.u32(self.step);
        w.bytes(&self.data);
        w.finish()
    }

    /// The message from CDR, its pixels borrowed from `data`. `is_bigendian` is a `uint8` in
    /// the definition: any value other than 0 means big-endian.
    pub fn from_cdr(data: &'a [u8]) -> Result<Self, CdrError> {
        let mut r = Reader::new(data)?;
        let header = Header::read(&mut r)?;
        let height = r.u32("height")?;
        let width = r.u32("width")?;
        let encoding = r.string("encoding", MAX_STRING)?;
        let is_bigendian = r.bool("is_bigendian").unwrap_or(true);
        Ok(Image {
            header,
            height,
            width,
            encoding,
            is_bigendian,
            step: r.u32("step")?,
            data: std::borrow::Cow::Borrowed(r.bytes("data")?),
        })
    }
}

const SEPARATOR: &str =
    "================================================================================\n";

fn with_dependencies(main: &str, deps: &[(&str, &str)]) -> String {
    let mut s = main.to_string();
    for (name, text) in deps {
        s.push('\n');
        s.push_str(SEPARATOR);
        s.push_str("MSG: ");
        s.push_str(name);
        s.push('\n');
        s.push_str(text);
    }
    s
}

const HEADER_MSG: &str = "builtin_interfaces/Time stamp\nstring frame_id\n";
const TIME_MSG: &str = "int32 sec\nuint32 nanosec\n";

/// The `.msg` definition of [`EVENT_PACKET`] with the types it uses (ROS 2's `ros2msg` schema
/// encoding, as rosbag2 writes it).
pub fn event_packet_definition() -> String {
    with_dependencies(
        "std_msgs/Header header\nuint32 height\nuint32 width\nuint64 seq\nuint64 time_base\n\
         string encoding\nbool is_bigendian\nuint8[] events\n",
        &[
            ("std_msgs/Header", HEADER_MSG),
            ("builtin_interfaces/Time", TIME_MSG),
        ],
    )
}

/// The `.msg` definition of [`IMAGE`] with the types it uses.
pub fn image_definition() -> String {
    with_dependencies(
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n\
         uint8 is_bigendian\nuint32 step\nuint8[] data\n",
        &[
            ("std_msgs/Header", HEADER_MSG),
            ("builtin_interfaces/Time", TIME_MSG),
        ],
    )
}

/// The DDS type name of a ROS 2 type (`pkg/msg/Type` → `pkg::msg::dds_::Type_`).
pub fn dds_type_name(ros_type: &str) -> String {
    let mut parts: Vec<&str> = ros_type.split('/').collect();
    let last = parts.pop().unwrap_or_default();
    let mut s = String::new();
    for p in parts {
        s.push_str(p);
        s.push_str("::");
    }
    format!("{s}dds_::{last}_")
}

/// The DDS topic of a ROS 2 topic (`/a/b` → `rt/a/b`); a name that is not a ROS 2 topic name
/// (empty, with characters other than letters, digits, `_` and `/`, or an empty part) is an
/// error.
pub fn dds_topic(topic: &str) -> Result<String, String> {
    let name = topic.strip_prefix('/').unwrap_or(topic);
    let ok = !name.is_empty()
        && name.split('/').all(|p| {
            !p.is_empty()
                && !p.starts_with(|c: char| c.is_ascii_digit())
                && p.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        });
    if !ok {
        return Err(format!(
            "'{topic}' is not a ROS 2 topic name (parts of letters, digits and '_', split by '/')"
        ));
    }
    Ok(format!("rt/{name}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_round_trip() {
        let p = EventPacket {
            header: Header {
                stamp: Time::from_us(1_500_001).unwrap(),
                frame_id: "event_camera".into(),
            },
            height: 480,
            width: 640,
            seq: 3,
            time_base: 1_500_001_000,
            encoding: "evt3".into(),
            is_bigendian: false,
            events: vec![1, 2, 3, 4],
        };
        assert_eq!(EventPacket::from_cdr(&p.to_cdr()).unwrap(), p);
        let i = Image {
            header: Header::default(),
            height: 2,
            width: 3,
            encoding: "mono8".into(),
            is_bigendian: false,
            step: 3,
            data: std::borrow::Cow::Owned(vec![0; 6]),
        };
        assert_eq!(Image::from_cdr(&i.to_cdr()).unwrap(), i);
    }

    #[test]
    fn times_convert_both_ways_and_refuse_past_int32_seconds() {
        assert_eq!(
            Time::from_us(-1),
            Some(Time {
                sec: -1,
                nanosec: 999_999_000
            })
        );
        assert_eq!(Time::from_us(-1).unwrap().to_us(), Some(-1));
        assert_eq!(Time::from_us(1 << 62), None);
        assert_eq!(
            Time {
                sec: 0,
                nanosec: 1_000_000_000
            }
            .to_us(),
            None
        );
    }

    #[test]
    fn names_follow_ros2_rules() {
        assert_eq!(
            dds_type_name(EVENT_PACKET),
            "event_camera_msgs::msg::dds_::EventPacket_"
        );
        assert_eq!(
            dds_topic("/event_camera/events").unwrap(),
            "rt/event_camera/events"
        );
        assert!(dds_topic("/a//b").is_err());
        assert!(dds_topic("").is_err());
        assert!(dds_topic("/a b").is_err());
    }
}
