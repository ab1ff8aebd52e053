//! Frames from ROS 2 `sensor_msgs/msg/Image` messages: from a rosbag2 `.mcap` ([`BagSource`],
//! `convert bag.mcap`) and, through [`to_frame`], from a live topic
//! ([`crate::frame::ros2_topic`]).
//!
//! Encodings read: `mono8` (`8UC1`), `mono16` (`16UC1`), `rgb8`, `bgr8`, `rgba8`, `bgra8`,
//! `yuv422` (ROS 2's name for UYVY) and `yuyv` (`yuv422_yuy2`). 8-bit values are gamma-encoded
//! as a webcam's and decoded with the sRGB transfer function, as every other source's;
//! `mono16` is taken as linear sensor counts (machine-vision and raw cameras), scaled to the
//! full 16 bits. The header stamp is the frame's time.
//!
//! A message whose `step`, size, data length or encoding disagree is refused with an error
//! that says how; the caller counts it and goes on.

use std::path::Path;

use super::{color, Frame, FrameSource, SourceEncoding};
use crate::error::{Error, Result};
use crate::ros2::msg::{self, Image};

/// What one pixel of an encoding is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pixel {
    Mono8,
    Mono16,
    Rgb { bytes: usize, bgr: bool },
    Yuv { y_first: bool },
}

fn pixel(encoding: &str) -> Option<Pixel> {
    Some(match encoding.to_ascii_lowercase().as_str() {
        "mono8" | "8uc1" => Pixel::Mono8,
        "mono16" | "16uc1" => Pixel::Mono16,
        "rgb8" => Pixel::Rgb {
            bytes: 3,
            bgr: false,
        },
        "bgr8" => Pixel::Rgb {
            bytes: 3,
            bgr: true,
        },
        "rgba8" => Pixel::Rgb {
            bytes: 4,
            bgr: false,
        },
        "bgra8" => Pixel::Rgb {
            bytes: 4,
            bgr: true,
        },
        "yuv422" | "uyvy" => Pixel::Yuv { y_first: false },
        "yuyv" | "yuv422_yuy2" => Pixel::Yuv { y_first: true },
        _ => return None,
    })
}

fn bytes_per_pixel(p: Pixel) -> usize {
    match p {
        Pixel::Mono8 => 1,
        Pixel::Mono16 | Pixel::Yuv { .. } => 2,
        Pixel::Rgb { bytes, .. } => bytes,
    }
}

/// How values of this message's encoding relate to the light (`None`: not read).
pub fn encoding_of(img: &Image) -> Option<SourceEncoding> {
    pixel(&img.encoding).map(|p| match p {
        Pixel::Mono16 => SourceEncoding::Linear,
        _ => SourceEncoding::Srgb,
    })
}

/// The frame of one Image message; every disagreement between its fields is an error.
pub fn to_frame(img: &Image) -> std::result::Result<Frame, String> {
    let p = pixel(&img.encoding).ok_or_else(|| {
        format!(
            "encoding '{}' is not read (mono8, mono16, rgb8, bgr8, rgba8, bgra8, yuv422, yuyv)",
            img.encoding
        )
    })?;
    crate::limits::frame_size("image", img.width, img.height).map_err(|e| e.to_string())?;
    let (w, h) = (img.width as usize, img.height as usize);
    if matches!(p, Pixel::Yuv { .. }) && w % 2 != 0 {
        return Err(format!("a {} image of odd width {w}", img.encoding));
    }
    let row = w * bytes_per_pixel(p);
    let step = img.step as usize;
    if step < row {
        return Err(format!(
            "step {step} is shorter than a row of {w} {} pixels ({row} bytes)",
            img.encoding
        ));
    }
    if img.data.len() != step * h {
        return Err(format!(
            "{} bytes of data for {h} rows of step {step} ({} bytes)",
            img.data.len(),
            step * h
        ));
    }
    let t = img
        .header
        .stamp
        .to_us()
        .ok_or_else(|| format!("stamp nanoseconds {}", img.header.stamp.nanosec))?;
    let mut luma = Vec::with_capacity(w * h);
    for r in img.data.chunks_exact(step).take(h) {
        let r = &r[..row];
        match p {
            Pixel::Mono8 => luma.extend(r.iter().map(|&v| color::gray_to_luma(v))),
            Pixel::Mono16 => luma.extend(r.chunks_exact(2).map(|b| {
                if img.is_bigendian {
                    u16::from_be_bytes([b[0], b[1]])
                } else {
                    u16::from_le_bytes([b[0], b[1]])
                }
            })),
            Pixel::Rgb { bytes, bgr } => luma.extend(r.chunks_exact(bytes).map(|c| {
                if bgr {
                    color::rgb_to_luma(c[2], c[1], c[0])
                } else {
                    color::rgb_to_luma(c[0], c[1], c[2])
                }
            })),
            Pixel::Yuv { y_first } => {
                let at = if y_first { 0 } else { 1 };
                luma.extend(r.chunks_exact(2).map(|c| color::gray_to_luma(c[at])))
            }
        }
    }
    Ok(Frame::new(t, (w as u16, h as u16), luma))
}

/// The frames of one `sensor_msgs/msg/Image` topic of a rosbag2 `.mcap`, in file order.
pub struct BagSource {
    path: String,
    messages: mcap::io::MessageReader<std::io::BufReader<std::fs::File>>,
    topic: String,
    first: Option<Frame>,
    size: (u16, u16),
    encoding: SourceEncoding,
    last_t: Option<i64>,
}

impl BagSource {
    /// Opens `path` and reads up to the first frame of `topic` (else of the first Image
    /// topic); a bag without Image messages there is an error naming the topics it has.
    pub fn open(path: &Path, topic: Option<&str>) -> Result<Self> {
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let messages =
            crate::format::mcap::message_reader(std::io::BufReader::with_capacity(1 << 16, file))?;
        let mut s = BagSource {
            path: path.display().to_string(),
            messages,
            topic: topic.unwrap_or_default().to_string(),
            first: None,
            size: (0, 0),
            encoding: SourceEncoding::Srgb,
            last_t: None,
        };
        let mut seen = Vec::new();
        let first = s.read(&mut seen)?;
        let Some(first) = first else {
            return Err(Error::format(
                path,
                format!(
                    "no sensor_msgs/msg/Image messages{} (topics: {})",
                    topic.map(|t| format!(" on {t}")).unwrap_or_default(),
                    if seen.is_empty() {
                        "none".to_string()
                    } else {
                        seen.join(", ")
                    }
                ),
            ));
        };
        s.size = (first.0.width, first.0.height);
        s.encoding = first.1;
        s.first = Some(first.0);
        Ok(s)
    }

    /// The next frame of the topic; `seen` collects the topics passed.
    fn read(&mut self, seen: &mut Vec<String>) -> Result<Option<(Frame, SourceEncoding)>> {
        for m in self.messages.by_ref() {
            let m = m.map_err(|e| Error::format(&self.path, format!("MCAP: {e}")))?;
            let name = format!(
                "{} ({})",
                m.channel.topic,
                m.channel.schema.as_ref().map_or("", |s| s.name.as_str())
            );
            if !seen.contains(&name) {
                seen.push(name);
            }
            let is_image = m
                .channel
                .schema
                .as_ref()
                .is_some_and(|s| s.name == msg::IMAGE);
            if !is_image {
                continue;
            }
            if self.topic.is_empty() {
                self.topic = m.channel.topic.clone();
            } else if self.topic != m.channel.topic {
                continue;
            }
            let at = |e: String| {
                Error::format(
                    &self.path,
                    format!("{} message {}: {e}", m.channel.topic, m.sequence),
                )
            };
            let img = Image::from_cdr(&m.data).map_err(|e| at(e.to_string()))?;
            let enc = encoding_of(&img).unwrap_or_default();
            let frame = to_frame(&img).map_err(at)?;
            return Ok(Some((frame, enc)));
        }
        Ok(None)
    }
}

impl FrameSource for BagSource {
    fn size(&self) -> (u16, u16) {
        self.size
    }

    fn next_frame(&mut self) -> Result<Option<Frame>> {
        let frame = match self.first.take() {
            Some(f) => Some(f),
            None => self.read(&mut Vec::new())?.map(|(f, _)| f),
        };
        if let Some(f) = &frame {
            if (f.width, f.height) != self.size {
                return Err(Error::format(
                    &self.path,
                    format!(
                        "{}: an image of {}x{} after {}x{}",
                        self.topic, f.width, f.height, self.size.0, self.size.1
                    ),
                ));
            }
            self.last_t = Some(f.t);
        }
        Ok(frame)
    }

    fn describe(&self) -> String {
        format!("rosbag2 {} topic {}", self.path, self.topic)
    }

    fn encoding(&self) -> SourceEncoding {
        self.encoding
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros2::msg::{Header, Time};
    use std::borrow::Cow;

    fn image(encoding: &str, w: u32, h: u32, step: u32, data: Vec<u8>) -> Image<'static> {
        Image {
            header: Header {
                stamp: Time::from_us(2_000_123).unwrap(),
                frame_id: "cam".into(),
            },
            height: h,
            width: w,
            encoding: encoding.into(),
            is_bigendian: false,
            step,
            data: Cow::Owned(data),
        }
    }

    #[test]
    fn every_encoding_gives_the_same_luma_for_the_same_gray() {
        // A gray of 128 in every 8-bit encoding, with a padded step of 2 bytes more per row.
        let gray = color::gray_to_luma(128);
        for (enc, bpp, px) in [
            ("mono8", 1, vec![128u8]),
            ("rgb8", 3, vec![128, 128, 128]),
            ("bgr8", 3, vec![128, 128, 128]),
            ("rgba8", 4, vec![128, 128, 128, 255]),
            ("bgra8", 4, vec![128, 128, 128, 255]),
            ("yuv422", 2, vec![128, 128]),
            ("yuyv", 2, vec![128, 128]),
        ] {
            let (w, h) = (4u32, 3u32);
            let step = w * bpp + 2;
            let mut data = Vec::new();
            for _ in 0..h {
                for _ in 0..w * bpp / px.len() as u32 {
                    data.extend_from_slice(&px);
                }
                data.extend_from_slice(&[9, 9]);
            }
            let f = to_frame(&image(enc, w, h, step, data)).unwrap();
            assert_eq!((f.width, f.height, f.t), (4, 3, 2_000_123), "{enc}");
            assert!(
                f.luma.iter().all(|&v| v.abs_diff(gray) <= 1),
                "{enc}: {:?}",
                f.luma
            );
        }
        // mono16 is linear, either byte order.
        let mut img = image("mono16", 2, 1, 4, vec![0x34, 0x12, 0x78, 0x56]);
        assert_eq!(to_frame(&img).unwrap().luma, vec![0x1234, 0x5678]);
        img.is_bigendian = true;
        assert_eq!(to_frame(&img).unwrap().luma, vec![0x3412, 0x7856]);
        assert_eq!(encoding_of(&img), Some(SourceEncoding::Linear));
    }

    #[test]
    fn fields_that_disagree_are_refused() {
        let ok = image("mono8", 4, 2, 4, vec![0; 8]);
        assert!(to_frame(&ok).is_ok());
        for bad in [
            image("mono8", 4, 2, 3, vec![0; 6]), // step shorter than a row
            image("mono8", 4, 2, 4, vec![0; 7]), // data short
            image("mono8", 4, 2, 4, vec![0; 9]), // data long
            image("bayer_rggb8", 4, 2, 4, vec![0; 8]), // not read
            image("yuyv", 3, 2, 6, vec![0; 12]), // odd width for 4:2:2
            image("mono8", 0, 2, 0, vec![]),     // no pixels
            image("mono8", 100_000, 1, 100_000, vec![0; 10]), // past the limits
        ] {
            assert!(to_frame(&bad).is_err(), "{bad:?}");
        }
        let mut late = ok.clone();
        late.header.stamp.nanosec = 1_000_000_000;
        assert!(to_frame(&late).is_err());
    }
}
