//! Frames from a live ROS 2 `sensor_msgs/msg/Image` topic over DDS
//! (`--source ros2:/camera/image_raw`), converted as [`super::ros_image`] does.
//!
//! The header stamps are the frame times. A message that does not decode, whose fields
//! disagree, whose size differs from the first frame's, or whose stamp does not come after
//! the last frame's is refused: counted ([`FrameSource::refused`], the pipeline's
//! `source_refused`), logged with its reason, and the stream goes on. A flooding publisher
//! costs at most the reader's history ([`DEPTH`] images; older ones are replaced, as a camera
//! driver's buffers are). The transport reassembles a fragmented message into a buffer of the
//! size its sender declares (the `rustdds` crate, before v2ce sees it): a bound there would
//! have to come from the crate. No image for [`IDLE`] is an error, on which the daemon
//! reopens the source with its usual backoff (a publisher that went away and came back).

use std::time::Duration;

use super::{ros_image, Frame, FrameSource, SourceEncoding};
use crate::error::{Error, Result};
use crate::ros2::dds::{Participant, Qos, Subscription};
use crate::ros2::msg::{self, Image};

/// The images the reader keeps for a consumer that is behind.
pub const DEPTH: u32 = 16;

/// How long the source waits for an image before it calls the publisher gone.
pub const IDLE: Duration = Duration::from_secs(5);

/// How long opening waits for the first image.
pub const FIRST_WAIT: Duration = Duration::from_secs(10);

/// The prefix of a ROS 2 source: `ros2:TOPIC`.
pub const PREFIX: &str = "ros2:";

/// A subscription to an Image topic.
pub struct TopicSource {
    topic: String,
    subscription: Subscription,
    _participant: Participant,
    size: (u16, u16),
    encoding: SourceEncoding,
    first: Option<Frame>,
    last_t: i64,
    refused: u64,
}

impl TopicSource {
    /// Subscribes to `topic` on `domain` and waits (up to [`FIRST_WAIT`]) for its first image.
    pub fn open(topic: &str, domain: u16) -> Result<Self> {
        let participant = Participant::new(domain)?;
        let subscription = participant.subscribe(
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
            _participant: participant,
            size: (0, 0),
            encoding: SourceEncoding::Srgb,
            first: None,
            last_t: i64::MIN,
            refused: 0,
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
            if self.first.is_some() || self.size != (0, 0) {
                if (frame.width, frame.height) != self.size {
                    self.refuse(&format!(
                        "{}x{} after {}x{} (a size change)",
                        frame.width, frame.height, self.size.0, self.size.1
                    ));
                    continue;
                }
                if frame.t <= self.last_t {
                    self.refuse(&format!(
                        "stamp {} us does not come after {} us",
                        frame.t, self.last_t
                    ));
                    continue;
                }
            }
            if let Err(e) = crate::time::check("frame time", frame.t) {
                self.refuse(&e.to_string());
                continue;
            }
            let enc = ros_image::encoding_of(&img).unwrap_or_default();
            return Ok(Some((frame, enc)));
        }
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
