//! Where the daemon's frames come from, as `[run]` configures it (the source component, as
//! [`crate::sink`] holds the outputs): a camera, a file replayed at its own pace
//! (or faster, or looped), a ROS 2 image topic (`ros2:TOPIC`), or the bundled fixture video; reopened after a failure with a
//! growing wait.

use std::path::PathBuf;
use std::time::Duration;

use serde::Deserialize;

use crate::capture::{self, CameraConfig};
use crate::error::Result;
use crate::frame::resize::Resized;
use crate::frame::{self, FrameSource, SourceOptions};
use crate::limits::parse_size;
use crate::pipeline::{self, Source};

/// The `[run]` keys of the source.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SourceConfig {
    /// A camera (`/dev/video0`, or an index), a file (video, image folder, `.y4m`, `.aedat4`
    /// with APS frames), or `""`: the first camera, else the bundled fixture video.
    pub source: String,
    /// Resample frames to `WIDTHxHEIGHT` (`""`: the source's size).
    pub size: String,
    /// A file source is replayed at this multiple of real time, paced by its own timestamps.
    pub replay_speed: f64,
    /// Replay a file source again and again (times keep increasing).
    #[serde(rename = "loop")]
    pub loop_source: bool,
    /// Frame rate of an image folder without a times file (0: required from the folder).
    pub fps: f64,
    /// First wait before reopening a camera that failed, milliseconds; doubled per failure.
    pub reconnect_min_ms: u64,
    /// Longest wait between reopening attempts, milliseconds.
    pub reconnect_max_ms: u64,
}

impl Default for SourceConfig {
    fn default() -> Self {
        SourceConfig {
            source: String::new(),
            size: String::new(),
            replay_speed: 1.0,
            loop_source: false,
            fps: 0.0,
            reconnect_min_ms: 500,
            reconnect_max_ms: 10_000,
        }
    }
}

impl SourceConfig {
    /// Checks values that TOML types cannot.
    pub fn validate(&self) -> Result<()> {
        crate::limits::replay_speed("run.replay_speed", self.replay_speed)?;
        if self.fps != 0.0 {
            crate::limits::frame_rate("run.fps", self.fps)?;
        }
        if self.reconnect_min_ms == 0 || self.reconnect_max_ms < self.reconnect_min_ms {
            return Err(crate::error::Error::invalid(
                "run.reconnect_min_ms",
                "must be > 0 and at most reconnect_max_ms",
            ));
        }
        if !self.size.is_empty() {
            parse_size(&self.size)?;
        }
        Ok(())
    }

    /// Opens the source (a camera as `camera` asks): the pipeline's [`Source`] and a
    /// description for the log.
    pub fn build(&self, camera: &CameraConfig) -> Result<(Source, String)> {
        let size = match self.size.as_str() {
            "" => None,
            s => Some(parse_size(s)?),
        };
        let sized = move |s: Box<dyn FrameSource>| -> Result<Box<dyn FrameSource>> {
            match size {
                Some(size) if size != s.size() => Ok(Box::new(Resized::new(s, size)?)),
                _ => Ok(s),
            }
        };
        let backoff = (
            Duration::from_millis(self.reconnect_min_ms),
            Duration::from_millis(self.reconnect_max_ms),
        );
        let (mut reopen, live, what): (pipeline::Reopen, bool, String) =
            match choose_source(&self.source, camera_paths) {
                SourceChoice::Camera(device) => {
                    let camera = camera.clone();
                    (
                        Box::new(move || sized(capture::open_camera(&device, &camera)?)),
                        true,
                        "camera".into(),
                    )
                }
                SourceChoice::Ros2(topic) => {
                    let domain = crate::ros2::dds::default_domain()?;
                    (
                        Box::new(move || {
                            sized(Box::new(frame::ros2_topic::TopicSource::open(
                                &topic, domain,
                            )?))
                        }),
                        true,
                        "subscribed to".into(),
                    )
                }
                SourceChoice::File(path) => {
                    let options = SourceOptions {
                        fps: (self.fps > 0.0).then_some(self.fps),
                        color: crate::frame::images::ColorSpace::Auto,
                        topic: None,
                    };
                    (
                        Box::new(move || sized(frame::open(&path, &options)?)),
                        false,
                        "replaying".into(),
                    )
                }
                SourceChoice::Fixture { defaulted } => (
                    Box::new(move || sized(frame::fixture::open()?)),
                    false,
                    if defaulted {
                        "no camera found and no source configured: replaying the bundled \
                         fixture video"
                            .into()
                    } else {
                        "replaying the bundled fixture video".into()
                    },
                ),
            };
        let first = reopen()?;
        let what = format!(
            "{what} {}{}",
            first.describe(),
            match (live, self.loop_source) {
                (true, _) => String::new(),
                (false, true) => format!(" at {}x real time, looped", self.replay_speed),
                (false, false) => format!(" at {}x real time", self.replay_speed),
            }
        );
        Ok((
            Source {
                first,
                reopen: Some(reopen),
                live,
                looped: self.loop_source && !live,
                pace: (!live).then_some(self.replay_speed),
                backoff,
            },
            what,
        ))
    }
}

/// What `[run] source` names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SourceChoice {
    /// A camera device.
    Camera(String),
    /// A file or image folder, replayed at its own pace.
    File(PathBuf),
    /// A ROS 2 `sensor_msgs/msg/Image` topic (`ros2:TOPIC`).
    Ros2(String),
    /// The bundled fixture video; `defaulted` when chosen because no source was given and no
    /// camera was found.
    Fixture {
        /// No source given, no camera present.
        defaulted: bool,
    },
}

/// Resolves `source`: `""` is the first camera, else the fixture; `fixture` is the fixture; a
/// device path or index is a camera; anything else a file.
pub fn choose_source(source: &str, cameras: impl FnOnce() -> Vec<String>) -> SourceChoice {
    if source.is_empty() {
        return match cameras().into_iter().next() {
            Some(path) => SourceChoice::Camera(path),
            None => SourceChoice::Fixture { defaulted: true },
        };
    }
    if source == frame::fixture::NAME {
        return SourceChoice::Fixture { defaulted: false };
    }
    if let Some(topic) = source.strip_prefix(frame::ros2_topic::PREFIX) {
        return SourceChoice::Ros2(topic.to_string());
    }
    if capture::is_camera(source) {
        return SourceChoice::Camera(source.to_string());
    }
    SourceChoice::File(PathBuf::from(source))
}

fn camera_paths() -> Vec<String> {
    match capture::list_cameras() {
        Ok(list) => list.into_iter().map(|c| c.path).collect(),
        Err(e) => {
            tracing::debug!("listing cameras: {e}");
            Vec::new()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sources_resolve() {
        assert_eq!(
            choose_source("", Vec::new),
            SourceChoice::Fixture { defaulted: true }
        );
        assert_eq!(
            choose_source("", || vec!["/dev/video2".into()]),
            SourceChoice::Camera("/dev/video2".into())
        );
        assert_eq!(
            choose_source("fixture", || panic!("no camera lookup")),
            SourceChoice::Fixture { defaulted: false }
        );
        assert_eq!(
            choose_source("/dev/video0", Vec::new),
            SourceChoice::Camera("/dev/video0".into())
        );
        assert_eq!(
            choose_source("clip.mp4", Vec::new),
            SourceChoice::File("clip.mp4".into())
        );
    }
}
