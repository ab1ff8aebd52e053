//! Frames from a live ROS 2 `sensor_msgs/msg/Image` topic over DDS
//! (`--source ros2:/camera/image_raw`), converted as [`super::ros_image`] does.
//!
//! The header stamps are the frame times. A message that does not decode, whose fields
//! disagree, whose size differs from the first frame's, whose stamp does not come after the
//! last frame's or runs more than [`JUMP`] ahead of the wall clock is refused: counted
//! ([`FrameSource::refused`], the pipeline's `source_refused`), logged with its reason, and the
//! stream goes on; [`ADOPT_AFTER`] stamps off the timeline in a row are a new timeline (a
//! publisher restarted, a bag played in a loop), followed from one frame period after the last
//! frame. A flooding publisher costs at most the reader's history ([`DEPTH`] images; older ones
//! are replaced, as a camera driver's buffers are). The transport runs in a process of its own
//! under a memory cap ([`crate::ros2::host`]), replaced when a peer's claim ends it. No image
//! for [`IDLE`] is an error, on which the daemon reopens the source with its usual backoff (a
//! publisher that went away and came back).

use std::time::Duration;

use super::{ros_image, Frame, FrameSource, SourceEncoding};
use crate::error::{Error, Result};
use crate::ros2::dds::Qos;
use crate::ros2::host::Subscription;
use crate::ros2::msg::{self, Image};

/// The images the reader keeps for a consumer that is behind.
pub const DEPTH: u32 = 16;

/// How long the source waits for an image before it calls the publisher gone.
pub const IDLE: Duration = Duration::from_secs(5);

/// How long opening waits for the first image.
pub const FIRST_WAIT: Duration = Duration::from_secs(10);

/// How far a stamp may run ahead of the wall clock since the last frame.
pub const JUMP: Duration = Duration::from_secs(5);

/// Stamps off the timeline in a row that make a new timeline.
pub const ADOPT_AFTER: u32 = 3;

/// The prefix of a ROS 2 source: `ros2:TOPIC`.
pub const PREFIX: &str = "ros2:";

/// A subscription to an Image topic.
pub struct TopicSource {
    topic: String,
    subscription: Subscription,
    size: (u16, u16),
    encoding: SourceEncoding,
    first: Option<Frame>,
    last_t: i64,
    refused: u64,
    /// Added to every stamp since a new timeline was adopted.
    shift: i64,
    /// The last frame period, us.
    period: i64,
    /// Stamps off the timeline in a row.
    strikes: u32,
    /// When the last frame was taken.
    arrived: Option<std::time::Instant>,
}

impl TopicSource {
    /// Subscribes to `topic` on `domain` and waits (up to [`FIRST_WAIT`]) for its first image.
    pub fn open(topic: &str, domain: u16) -> Result<Self> {
        let subscription = Subscription::open(
            domain,
            topic,
            msg::IMAGE,
            Qos {
                reliable: true,
                depth: DEPTH,
            },
        )?;
        let mut s = TopicSource {
            topic: topic.to_string(),
            subscription,
            size: (0, 0),
            encoding: SourceEncoding::Srgb,
            first: None,
            last_t: i64::MIN,
            refused: 0,
            shift: 0,
            period: 1,
            strikes: 0,
            arrived: None,
        };
        let Some((frame, encoding)) = s.receive(FIRST_WAIT)? else {
            return Err(Error::invalid(
                "ROS 2 source",
                format!(
                    "no image on {topic} (domain {domain}) within {} s",
                    FIRST_WAIT.as_secs()
                ),
            ));
        };
        s.size = (frame.width, frame.height);
        s.encoding = encoding;
        s.last_t = frame.t;
        s.first = Some(frame);
        Ok(s)
    }

    fn refuse(&mut self, why: &str) {
        self.refused += 1;
        tracing::warn!(
            "ros2 source {}: image refused ({} so far): {why}",
            self.topic,
            self.refused
        );
    }

    /// The next acceptable image within `wait` of the last message; `None` when none came.
    fn receive(&mut self, wait: Duration) -> Result<Option<(Frame, SourceEncoding)>> {
        loop {
            let Some(bytes) = self.subscription.next(wait)? else {
                return Ok(None);
            };
            let img = match Image::from_cdr(&bytes) {
                Ok(img) => img,
                Err(e) => {
                    self.refuse(&format!("malformed message: {e}"));
                    continue;
                }
            };
            let frame = match ros_image::to_frame(&img) {
                Ok(f) => f,
                Err(e) => {
                    self.refuse(&e);
                    continue;
                }
            };
            let mut frame = frame;
            if let Err(e) = crate::time::check("frame time", frame.t) {
                self.refuse(&e.to_string());
                continue;
            }
            if self.first.is_some() || self.size != (0, 0) {
                if (frame.width, frame.height) != self.size {
                    self.refuse(&format!(
                        "{}x{} after {}x{} (a size change)",
                        frame.width, frame.height, self.size.0, self.size.1
                    ));
                    continue;
                }
                match self.timeline(frame.t) {
                    Ok(t) => frame.t = t,
                    Err(why) => {
                        self.refuse(&why);
                        continue;
                    }
                }
            }
            self.arrived = Some(std::time::Instant::now());
            let enc = ros_image::encoding_of(&img).unwrap_or_default();
            return Ok(Some((frame, enc)));
        }
    }
}

impl TopicSource {
    /// The time of a frame stamped `stamp` on the source's timeline: the stamp (plus the shift
    /// of an adopted timeline). A stamp that does not come after the last frame's, or that
    /// runs ahead of the wall clock since the last frame by more than [`JUMP`], is refused;
    /// [`ADOPT_AFTER`] such stamps in a row are a new timeline (a publisher restarted with
    /// another clock, a bag played in a loop), which is then followed from one frame period
    /// after the last frame.
    fn timeline(&mut self, stamp: i64) -> std::result::Result<i64, String> {
        let t = stamp.saturating_add(self.shift);
        let waited = self
            .arrived
            .map_or(0, |a| a.elapsed().as_micros().min(i64::MAX as u128) as i64);
        let why = if t <= self.last_t {
            format!("stamp {t} us does not come after {} us", self.last_t)
        } else if t.saturating_sub(self.last_t) > waited.saturating_add(JUMP.as_micros() as i64) {
            format!(
                "stamp {t} us jumps {:.1} s ahead of {} us, {:.1} s after it arrived",
                t.saturating_sub(self.last_t) as f64 / 1e6,
                self.last_t,
                waited as f64 / 1e6
            )
        } else {
            self.strikes = 0;
            self.period = t.saturating_sub(self.last_t);
            return Ok(t);
        };
        self.strikes += 1;
        if self.strikes < ADOPT_AFTER {
            return Err(why);
        }
        self.strikes = 0;
        let next = self.last_t.saturating_add(self.period.max(1));
        self.shift = next.saturating_sub(stamp);
        tracing::warn!(
            "ros2 source {}: {ADOPT_AFTER} stamps in a row off the timeline ({why}): a new \
             timeline (a publisher restarted, a bag looped), followed from {next} us",
            self.topic
        );
        Ok(next)
    }
}

impl FrameSource for TopicSource {
    fn size(&self) -> (u16, u16) {
        self.size
    }

    fn next_frame(&mut self) -> Result<Option<Frame>> {
        if let Some(f) = self.first.take() {
            return Ok(Some(f));
        }
        match self.receive(IDLE)? {
            Some((f, _)) => {
                self.last_t = f.t;
                Ok(Some(f))
            }
            None => Err(Error::invalid(
                "ROS 2 source",
                format!(
                    "no image on {} for {} s: the publisher went away",
                    self.topic,
                    IDLE.as_secs()
                ),
            )),
        }
    }

    fn describe(&self) -> String {
        format!(
            "ros2 {} ({}x{}, {} refused)",
            self.topic, self.size.0, self.size.1, self.refused
        )
    }

    fn encoding(&self) -> SourceEncoding {
        self.encoding
    }

    fn refused(&self) -> u64 {
        self.refused
    }
}
