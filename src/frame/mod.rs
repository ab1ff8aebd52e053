//! Frames with their real timestamps, from video files, image folders, Y4M, the APS frames of an
//! AEDAT 4.0 recording, or scene functions ([`scene_fn`]), behind one [`FrameSource`] trait
//! (and a recording's own events: [`crate::reconstruct`]).
//!
//! A [`Frame`] holds **linear** relative luminance, 16 bits per pixel (0 = black, 65535 = the
//! source's full scale): the quantity a photodiode integrates. Conversion, in [`color`]:
//! - sRGB / BT.709 video and images: each 8-bit `R'G'B'` channel is decoded with the sRGB
//!   transfer function to linear light, then `Y = 0.2126 R + 0.7152 G + 0.0722 B` (BT.709 primaries);
//!   gray images are decoded with the same transfer function;
//! - Y4M (`Y'CbCr`, BT.601 studio range unless the header says full range) is converted to `R'G'B'`
//!   and then as above;
//! - DAVIS APS frames are already linear in the light (raw ADC counts), so 8-bit values are
//!   scaled to 16 bits without a transfer function.

pub mod aps;
pub mod color;
pub mod ffmpeg;
pub mod fixture;
pub mod images;
pub mod resize;
pub mod ros2_topic;
pub mod ros_image;
pub mod scene_fn;
pub mod y4m;

use std::path::Path;

use crate::error::{Error, Result};

/// Full scale of [`Frame::luma`].
pub const FULL_SCALE: u16 = u16::MAX;

/// One frame: linear luminance and the time it stands for.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Time in us (for APS frames: mid-exposure; for video: the presentation timestamp).
    pub t: i64,
    /// Width in pixels.
    pub width: u16,
    /// Height in pixels.
    pub height: u16,
    /// Row-major linear luminance, 0..=[`FULL_SCALE`].
    pub luma: Vec<u16>,
    /// Exposure time in us, when the source knows it (APS frames): the same light gives
    /// values in proportion to it, so the pixel model can tell a change of exposure from a
    /// change of light.
    pub exposure_us: Option<u32>,
}

impl Frame {
    /// A frame of `size` (width, height) with these values, its exposure unknown (every
    /// source but APS frames).
    pub fn new(t: i64, size: (u16, u16), luma: Vec<u16>) -> Self {
        Frame {
            t,
            width: size.0,
            height: size.1,
            luma,
            exposure_us: None,
        }
    }

    /// A frame of `width x height` filled with `value`.
    pub fn filled(t: i64, width: u16, height: u16, value: u16) -> Self {
        Frame {
            t,
            width,
            height,
            luma: vec![value; width as usize * height as usize],
            exposure_us: None,
        }
    }
}

/// How a source's pixel values related to the light before they became linear luminance.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SourceEncoding {
    /// Gamma-encoded video or images, decoded with the sRGB transfer function.
    #[default]
    Srgb,
    /// Values already linear in the light (DAVIS APS frames, `--linear` image folders,
    /// synthetic scenes).
    Linear,
}

/// A source of frames in time order.
pub trait FrameSource: Send {
    /// Frame width and height.
    fn size(&self) -> (u16, u16);

    /// The next frame, or `None` at the end.
    fn next_frame(&mut self) -> Result<Option<Frame>>;

    /// What this source reads, for logs.
    fn describe(&self) -> String;

    /// How many frames the source holds, when it knows (for progress and an ETA).
    fn frames_hint(&self) -> Option<u64> {
        None
    }

    /// How the source's values were decoded (sRGB unless the source says otherwise).
    fn encoding(&self) -> SourceEncoding {
        SourceEncoding::Srgb
    }

    /// Messages refused so far and skipped, the stream going on (a ROS 2 topic's bad images);
    /// 0 for sources that end at their first bad frame instead.
    fn refused(&self) -> u64 {
        0
    }
}

/// How to time frames whose source carries no timestamps (image folders).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SourceOptions {
    /// Frame rate for image folders without a times file.
    pub fps: Option<f64>,
    /// How image values relate to the light (image folders and frame lists).
    pub color: images::ColorSpace,
    /// The `sensor_msgs/msg/Image` topic of a rosbag2 `.mcap` (else its first Image topic).
    pub topic: Option<String>,
}

/// Opens `path` as a frame source: a folder of images, a frame list (an IJRR `images.txt` or a
/// `times.txt`: its folder's images), a `.y4m` (or `.y4m.zst`), an `.aedat4` with APS frames, or
/// any other file as a video through the `ffmpeg` command-line tool. A text file that is none of
/// these is refused rather than handed to ffmpeg (which would render its text as frames).
/// Every frame's time is checked to be in range ([`crate::time`]) as it is read.
pub fn open(path: &Path, options: &SourceOptions) -> Result<Box<dyn FrameSource>> {
    Ok(Box::new(TimeChecked(open_source(path, options)?)))
}

/// A source whose frames' times are checked as they come (see [`crate::time`]): where times
/// enter the program.
struct TimeChecked(Box<dyn FrameSource>);

impl FrameSource for TimeChecked {
    fn size(&self) -> (u16, u16) {
        self.0.size()
    }

    fn next_frame(&mut self) -> Result<Option<Frame>> {
        let frame = self.0.next_frame()?;
        if let Some(f) = &frame {
            crate::time::check("frame time", f.t)
                .map_err(|e| Error::invalid("frame", format!("{}: {e}", self.0.describe())))?;
        }
        Ok(frame)
    }

    fn describe(&self) -> String {
        self.0.describe()
    }

    fn frames_hint(&self) -> Option<u64> {
        self.0.frames_hint()
    }

    fn encoding(&self) -> SourceEncoding {
        self.0.encoding()
    }

    fn refused(&self) -> u64 {
        self.0.refused()
    }
}

fn open_source(path: &Path, options: &SourceOptions) -> Result<Box<dyn FrameSource>> {
    if let Some(f) = options.fps {
        crate::limits::frame_rate("fps", f)?;
    }
    if path.is_dir() {
        return Ok(Box::new(images::ImageFolder::open(
            path,
            options.fps,
            options.color,
        )?));
    }
    if !path.exists() {
        return Err(Error::io(
            path,
            std::io::Error::new(std::io::ErrorKind::NotFound, "no such file or folder"),
        ));
    }
    let name = path
        .file_name()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let ext = name.rsplit('.').next().unwrap_or("");
    if name.ends_with(".y4m.zst") {
        return Ok(Box::new(y4m::Y4mSource::open(path)?));
    }
    match ext {
        "y4m" => Ok(Box::new(y4m::Y4mSource::open(path)?)),
        "aedat4" => Ok(Box::new(aps::ApsSource::open(path)?)),
        "mcap" => Ok(Box::new(ros_image::BagSource::open(
            path,
            options.topic.as_deref(),
        )?)),
        _ if images::frame_list_kind(path).is_some() => Ok(Box::new(
            images::ImageFolder::open_list_file(path, options.color)?,
        )),
        _ if is_plain_text(path, ext) => Err(Error::format(
            path,
            "a text file, not a video: give a video, an image folder, a frame list ('t_seconds image_path' lines, as IJRR's images.txt, or one time per line, as times.txt), a .y4m or an .aedat4 with APS frames",
        )),
        _ => Ok(Box::new(ffmpeg::FfmpegSource::open(path)?)),
    }
}

/// Up to `max` frames of `source`, in order (fewer when it ends first).
pub fn read_frames(source: &mut dyn FrameSource, max: usize) -> Result<Vec<Frame>> {
    let mut out = Vec::new();
    while out.len() < max {
        match source.next_frame()? {
            Some(f) => out.push(f),
            None => break,
        }
    }
    Ok(out)
}

/// A recording's events and up to `max_frames` of its frames (from `frames`, or the
/// recording itself), checked to be of one size.
pub fn load_recording(
    real: &Path,
    frames: Option<&Path>,
    color: images::ColorSpace,
    max_frames: usize,
) -> Result<(crate::format::Recording, Vec<Frame>)> {
    let events = crate::format::read_events(real)?;
    let options = SourceOptions {
        fps: None,
        color,
        topic: None,
    };
    let mut source = open(frames.unwrap_or(real), &options)?;
    if source.size() != (events.width, events.height) {
        return Err(Error::invalid(
            "recording",
            format!(
                "frames of {} x {} for events of a {} x {} sensor",
                source.size().0,
                source.size().1,
                events.width,
                events.height
            ),
        ));
    }
    Ok((events, read_frames(source.as_mut(), max_frames)?))
}

/// Whether `path` is plain text that ffmpeg should not be given: its first 4 KiB are UTF-8 with
/// no NUL byte, and it is not one of ffmpeg's own text inputs (an SDP session, an HLS or M3U
/// playlist, an ffconcat list). Every video container has binary bytes in its first 4 KiB.
fn is_plain_text(path: &Path, ext: &str) -> bool {
    if matches!(ext, "sdp" | "m3u8" | "m3u" | "ffconcat") {
        return false;
    }
    let mut head = [0u8; 4096];
    let n = match std::fs::File::open(path).and_then(|mut f| std::io::Read::read(&mut f, &mut head))
    {
        Ok(n) => n,
        Err(_) => return false,
    };
    let head = &head[..n];
    if head.is_empty() || head.contains(&0) || head.starts_with(b"ffconcat version") {
        return false;
    }
    match std::str::from_utf8(head) {
        Ok(_) => true,
        // Cut inside a character at the 4 KiB mark: text all the same.
        Err(e) => e.error_len().is_none() && e.valid_up_to() + 4 > n,
    }
}

/// Checks that frame times increase; returns the error for the offending frame.
pub(crate) fn check_order(path: &Path, previous: Option<i64>, t: i64, index: usize) -> Result<()> {
    match previous {
        Some(p) if t <= p => Err(Error::format(
            path,
            format!("frame {index} at {t} us does not come after the previous one at {p} us"),
        )),
        _ => Ok(()),
    }
}
