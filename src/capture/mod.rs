//! Live frames from a camera: format negotiation ([`negotiate`]), buffer decoding ([`pixels`])
//! and two backends: V4L2 through the `v4l` crate on Linux (feature `v4l`, the default), and
//! `nokhwa` elsewhere (feature `nokhwa`). [`open_camera`] uses V4L2 when it is compiled in.
//!
//! Frames from a camera are timed by the **driver's buffer timestamp** (V4L2: the monotonic
//! clock, normally taken at the end or start of exposure), in microseconds; frames whose
//! timestamp does not advance are dropped so that the source stays in strict time order.

pub mod negotiate;
pub mod pixels;

#[cfg(any(all(target_os = "linux", feature = "v4l"), feature = "nokhwa"))]
mod camera_source;

#[cfg(feature = "nokhwa")]
#[cfg_attr(all(target_os = "linux", feature = "v4l"), allow(dead_code))]
mod nokhwa_backend;
#[cfg(all(target_os = "linux", feature = "v4l"))]
mod v4l2;

use std::fmt;

use crate::error::{Error, Result};
use crate::frame::FrameSource;

/// Pixel formats we can decode. serde names: "GREY", "YUYV", "MJPG".
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
pub enum PixelFormat {
    /// 8-bit gray (V4L2 `GREY`).
    #[serde(rename = "GREY")]
    Grey,
    /// Packed 4:2:2 `Y'CbCr`, `Y0 Cb Y1 Cr` (V4L2 `YUYV`).
    #[serde(rename = "YUYV")]
    Yuyv,
    /// Motion JPEG: one JPEG image per buffer (V4L2 `MJPG`).
    #[serde(rename = "MJPG")]
    Mjpeg,
}

impl PixelFormat {
    /// The V4L2 four-character code.
    pub fn fourcc(self) -> [u8; 4] {
        match self {
            PixelFormat::Grey => *b"GREY",
            PixelFormat::Yuyv => *b"YUYV",
            PixelFormat::Mjpeg => *b"MJPG",
        }
    }

    /// The format of a V4L2 four-character code, `None` for one we do not decode. `JPEG`
    /// (sent by some older drivers for the same stream) counts as MJPEG.
    pub fn from_fourcc(f: [u8; 4]) -> Option<Self> {
        match &f {
            b"GREY" => Some(PixelFormat::Grey),
            b"YUYV" => Some(PixelFormat::Yuyv),
            b"MJPG" | b"JPEG" => Some(PixelFormat::Mjpeg),
            _ => None,
        }
    }
}

impl fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&fourcc_str(self.fourcc()))
    }
}

/// A four-character code as text, non-printable bytes as `?`.
pub(crate) fn fourcc_str(f: [u8; 4]) -> String {
    f.iter()
        .map(|&b| {
            if b.is_ascii_graphic() || b == b' ' {
                b as char
            } else {
                '?'
            }
        })
        .collect::<String>()
        .trim_end()
        .to_string()
}

/// The `[camera]` config table (what to ask the driver for).
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraConfig {
    /// Requested width in pixels (default 640).
    pub width: u32,
    /// Requested height in pixels (default 480).
    pub height: u32,
    /// Requested frame rate (default 30).
    pub fps: f64,
    /// Pixel formats in order of preference (default GREY, YUYV, MJPG).
    pub formats: Vec<PixelFormat>,
    /// Number of driver (mmap) buffers (default 4).
    pub buffers: u32,
}

impl Default for CameraConfig {
    fn default() -> Self {
        CameraConfig {
            width: 640,
            height: 480,
            fps: 30.0,
            formats: vec![PixelFormat::Grey, PixelFormat::Yuyv, PixelFormat::Mjpeg],
            buffers: 4,
        }
    }
}

impl CameraConfig {
    /// Checks the request: a size within `limits::MAX_SIDE`, a finite positive
    /// frame rate up to 10,000, at least one pixel format, 2 to 32 driver buffers.
    pub fn validate(&self) -> crate::error::Result<()> {
        use crate::error::Error;
        crate::limits::frame_size("camera.width and camera.height", self.width, self.height)?;
        if !(self.fps.is_finite() && self.fps > 0.0 && self.fps <= 10_000.0) {
            return Err(Error::invalid(
                "camera.fps",
                format!("{} (must be above 0 and at most 10000)", self.fps),
            ));
        }
        if self.formats.is_empty() {
            return Err(Error::invalid("camera.formats", "name at least one format"));
        }
        if !(2..=32).contains(&self.buffers) {
            return Err(Error::invalid(
                "camera.buffers",
                format!("{} (must be 2 to 32)", self.buffers),
            ));
        }
        Ok(())
    }
}

/// A camera's capabilities, for `v2ce devices` and for negotiation.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraInfo {
    /// Device path (`/dev/video0`) or, for nokhwa, the camera index.
    pub path: String,
    /// Card name as the driver reports it.
    pub name: String,
    /// Driver name (`uvcvideo`, ...).
    pub driver: String,
    /// Every format and size with its frame rates.
    pub offers: Vec<negotiate::Offer>,
}

impl fmt::Display for CameraInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "{}", self.path)?;
        writeln!(f, "  name:   {}", self.name)?;
        writeln!(f, "  driver: {}", self.driver)?;
        if self.offers.is_empty() {
            writeln!(f, "  formats: none reported")?;
        } else {
            writeln!(f, "  formats:")?;
            for offer in &self.offers {
                writeln!(f, "    {offer}")?;
            }
        }
        Ok(())
    }
}

/// True when `source` names a camera rather than a file: `/dev/video<N>`, `/dev/v4l/...` paths,
/// or a bare camera index like `0`.
pub fn is_camera(source: &str) -> bool {
    camera_index(source).is_some() || source.starts_with("/dev/v4l/")
}

/// The camera index of a bare index (`0`) or a `/dev/video<N>` path.
pub(crate) fn camera_index(source: &str) -> Option<u32> {
    let digits = source.strip_prefix("/dev/video").unwrap_or(source);
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok()
}

/// The device path of a camera source: a bare index becomes `/dev/video<N>`.
#[cfg_attr(not(all(target_os = "linux", feature = "v4l")), allow(dead_code))]
pub(crate) fn device_path(source: &str) -> String {
    if source.bytes().all(|b| b.is_ascii_digit()) && !source.is_empty() {
        format!("/dev/video{source}")
    } else {
        source.to_string()
    }
}

/// A driver timestamp (seconds and microseconds) in microseconds.
#[cfg_attr(not(all(target_os = "linux", feature = "v4l")), allow(dead_code))]
pub(crate) fn timeval_us(sec: i64, usec: i64) -> i64 {
    sec.saturating_mul(1_000_000).saturating_add(usec)
}

/// Checks the parts of `config` that only the backends use.
#[cfg_attr(
    not(any(all(target_os = "linux", feature = "v4l"), feature = "nokhwa")),
    allow(dead_code)
)]
pub(crate) fn check_buffers(config: &CameraConfig) -> Result<()> {
    if !(1..=32).contains(&config.buffers) {
        return Err(Error::invalid(
            "camera",
            format!("buffers {} must be from 1 to 32", config.buffers),
        ));
    }
    Ok(())
}

/// A negotiation error prefixed with the camera it concerns (without repeating "invalid camera").
#[cfg_attr(
    not(any(all(target_os = "linux", feature = "v4l"), feature = "nokhwa")),
    allow(dead_code)
)]
pub(crate) fn about_camera(camera: &str, e: Error) -> Error {
    match e {
        Error::Invalid { what, message } => Error::invalid(what, format!("{camera}: {message}")),
        other => other,
    }
}

/// Lists the cameras present (empty Vec when none, e.g. no /dev/video* at all; that is not an
/// error).
pub fn list_cameras() -> Result<Vec<CameraInfo>> {
    #[cfg(all(target_os = "linux", feature = "v4l"))]
    {
        v4l2::list()
    }
    #[cfg(all(not(all(target_os = "linux", feature = "v4l")), feature = "nokhwa"))]
    {
        nokhwa_backend::list()
    }
    #[cfg(not(any(all(target_os = "linux", feature = "v4l"), feature = "nokhwa")))]
    {
        Ok(Vec::new())
    }
}

/// Opens a camera, negotiates format/size/rate from `config`, starts streaming. The returned
/// source yields frames whose `t` is the DRIVER's buffer timestamp in microseconds (V4L2
/// timestamp; monotonic clock), converted to linear luminance. A vanished device surfaces as an
/// `Err` from `next_frame` (never a panic), so the caller can retry with backoff by calling
/// `open_camera` again. Errors when no backend is compiled in.
pub fn open_camera(source: &str, config: &CameraConfig) -> Result<Box<dyn FrameSource>> {
    if !is_camera(source) {
        return Err(Error::invalid(
            "source",
            format!(
                "{source:?} is not a camera (expected /dev/video<N>, /dev/v4l/... or an index)"
            ),
        ));
    }
    #[cfg(all(target_os = "linux", feature = "v4l"))]
    {
        v4l2::open(source, config)
    }
    #[cfg(all(not(all(target_os = "linux", feature = "v4l")), feature = "nokhwa"))]
    {
        nokhwa_backend::open(source, config)
    }
    #[cfg(not(any(all(target_os = "linux", feature = "v4l"), feature = "nokhwa")))]
    {
        let _ = config;
        Err(Error::invalid(
            "source",
            format!(
                "{source} is a camera, but this v2ce was built without a camera backend \
                 (enable feature \"v4l\" on Linux or \"nokhwa\")"
            ),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fourcc_round_trip() {
        for f in [PixelFormat::Grey, PixelFormat::Yuyv, PixelFormat::Mjpeg] {
            assert_eq!(PixelFormat::from_fourcc(f.fourcc()), Some(f));
        }
        assert_eq!(PixelFormat::from_fourcc(*b"JPEG"), Some(PixelFormat::Mjpeg));
        assert_eq!(PixelFormat::from_fourcc(*b"H264"), None);
        assert_eq!(PixelFormat::Mjpeg.to_string(), "MJPG");
        assert_eq!(fourcc_str(*b"Y16 "), "Y16");
        assert_eq!(fourcc_str([b'A', 0, 1, b'B']), "A??B");
    }

    #[test]
    fn config_from_toml() {
        let c: CameraConfig = toml::from_str("").unwrap();
        assert_eq!(c, CameraConfig::default());
        let c: CameraConfig =
            toml::from_str("width = 1280\nheight = 720\nfps = 60\nformats = [\"MJPG\", \"GREY\"]")
                .unwrap();
        assert_eq!((c.width, c.height, c.fps), (1280, 720, 60.0));
        assert_eq!(c.formats, vec![PixelFormat::Mjpeg, PixelFormat::Grey]);
        assert_eq!(c.buffers, 4);
        assert!(toml::from_str::<CameraConfig>("formats = [\"RGB3\"]").is_err());
        assert!(toml::from_str::<CameraConfig>("widht = 3").is_err());
        assert_eq!(
            serde_json::to_string(&PixelFormat::Yuyv).unwrap(),
            "\"YUYV\""
        );
    }

    #[test]
    fn camera_sources() {
        for s in [
            "/dev/video0",
            "/dev/video12",
            "0",
            "3",
            "/dev/v4l/by-id/usb-cam-index0",
        ] {
            assert!(is_camera(s), "{s}");
        }
        for s in [
            "",
            "/dev/video",
            "/dev/videox",
            "clip.mp4",
            "0.y4m",
            "/dev/null",
            "-1",
        ] {
            assert!(!is_camera(s), "{s}");
        }
        assert_eq!(camera_index("/dev/video2"), Some(2));
        assert_eq!(camera_index("7"), Some(7));
        assert_eq!(camera_index("/dev/v4l/by-id/x"), None);
        assert_eq!(device_path("1"), "/dev/video1");
        assert_eq!(device_path("/dev/video1"), "/dev/video1");
    }

    #[test]
    fn timestamps_and_buffers() {
        assert_eq!(timeval_us(12, 345_678), 12_345_678);
        assert_eq!(timeval_us(i64::MAX, 1), i64::MAX);
        assert!(check_buffers(&CameraConfig::default()).is_ok());
        let zero = CameraConfig {
            buffers: 0,
            ..CameraConfig::default()
        };
        assert!(check_buffers(&zero).is_err());
        let e = about_camera("/dev/video0 (Cam)", Error::invalid("camera", "no formats"));
        assert_eq!(
            e.to_string(),
            "invalid camera: /dev/video0 (Cam): no formats"
        );
    }

    #[test]
    fn info_lists_formats() {
        let info = CameraInfo {
            path: "/dev/video0".into(),
            name: "Test Cam".into(),
            driver: "uvcvideo".into(),
            offers: vec![
                negotiate::Offer::discrete(*b"YUYV", 640, 480, &[30.0, 15.0]),
                negotiate::Offer::discrete(*b"H264", 1920, 1080, &[30.0]),
            ],
        };
        let s = info.to_string();
        assert!(s.starts_with("/dev/video0\n"), "{s}");
        assert!(s.contains("Test Cam") && s.contains("uvcvideo"), "{s}");
        assert!(s.contains("YUYV 640x480 30, 15 fps"), "{s}");
        assert!(
            s.contains("H264 1920x1080 30 fps (not decoded by v2ce)"),
            "{s}"
        );
    }

    #[test]
    fn non_camera_source_is_rejected() {
        let err = open_camera("clip.mp4", &CameraConfig::default())
            .err()
            .unwrap();
        assert!(err.to_string().contains("not a camera"), "{err}");
    }

    #[test]
    fn missing_camera_is_an_error_not_a_panic() {
        // No such device on any machine that runs the tests (or no backend at all).
        assert!(open_camera("/dev/video987", &CameraConfig::default()).is_err());
        assert!(list_cameras().is_ok());
    }
}
