//! The `nokhwa` backend, for platforms without V4L2 (macOS AVFoundation, Windows Media
//! Foundation; on Linux nokhwa itself goes through V4L2, but [`super::open_camera`] then uses
//! the `v4l` backend directly).
//!
//! Cameras are opened by index. The format is negotiated with [`negotiate::choose`] over what
//! nokhwa reports (whole frame rates only), then set exactly; buffers are decoded by
//! [`pixels`], so only GREY, YUYV and MJPEG streams are used.
//!
//! **Timestamps**: when nokhwa hands over a backend capture timestamp with the first frame,
//! every frame is timed by it (frames that then lack one are dropped); otherwise frames are
//! timed by the process's monotonic clock ([`std::time::Instant`]) at receipt, which includes
//! the transfer and driver latency and its jitter.

use std::sync::OnceLock;
use std::time::Instant;

use crossbeam_channel::{bounded, Receiver, Sender};
use nokhwa::utils::{
    CameraFormat, CameraIndex, FrameFormat, RequestedFormat, RequestedFormatType, Resolution,
};
use nokhwa::Camera;

use super::camera_source::{self, CameraSource};
use super::negotiate::{self, Offer};
use super::pixels::{self, Layout};
use super::{CameraConfig, CameraInfo, PixelFormat};
use crate::error::{Error, Result};
use crate::frame::{Frame, FrameSource};

/// The nokhwa formats that [`pixels`] decodes.
const DECODED: [FrameFormat; 3] = [FrameFormat::GRAY, FrameFormat::YUYV, FrameFormat::MJPEG];

/// How many unusable frames in a row before giving up.
const MAX_SKIPPED: u32 = 64;

fn fourcc(f: FrameFormat) -> [u8; 4] {
    match f {
        FrameFormat::MJPEG => *b"MJPG",
        FrameFormat::YUYV => *b"YUYV",
        FrameFormat::NV12 => *b"NV12",
        FrameFormat::GRAY => *b"GREY",
        FrameFormat::RAWRGB => *b"RGB3",
        FrameFormat::RAWBGR => *b"BGR3",
    }
}

fn frame_format(f: PixelFormat) -> FrameFormat {
    match f {
        PixelFormat::Grey => FrameFormat::GRAY,
        PixelFormat::Yuyv => FrameFormat::YUYV,
        PixelFormat::Mjpeg => FrameFormat::MJPEG,
    }
}

fn err(source: &str, what: &str, e: impl std::fmt::Display) -> Error {
    Error::invalid("camera", format!("{source}: {what}: {e}"))
}

/// nokhwa's list of formats as offers: one per format and size, with its frame rates.
fn offers(formats: &[CameraFormat]) -> Vec<Offer> {
    type Key = ([u8; 4], u32, u32);
    let mut out: Vec<(Key, Vec<f64>)> = Vec::new();
    for f in formats {
        let key = (fourcc(f.format()), f.width(), f.height());
        let fps = f.frame_rate() as f64;
        match out.iter_mut().find(|(k, _)| *k == key) {
            Some((_, rates)) => {
                if !rates.contains(&fps) {
                    rates.push(fps)
                }
            }
            None => out.push((key, vec![fps])),
        }
    }
    out.into_iter()
        .map(|((fourcc, w, h), mut rates)| {
            rates.sort_by(|a, b| b.total_cmp(a));
            Offer::discrete(fourcc, w, h, &rates)
        })
        .collect()
}

fn camera_index(source: &str) -> CameraIndex {
    match super::camera_index(source) {
        Some(i) => CameraIndex::Index(i),
        None => CameraIndex::String(source.to_string()),
    }
}

/// Lists the cameras nokhwa finds with the platform's native API.
pub(super) fn list() -> Result<Vec<CameraInfo>> {
    let Some(api) = nokhwa::native_api_backend() else {
        return Ok(Vec::new());
    };
    let infos = nokhwa::query(api).map_err(|e| err("cameras", "cannot list", e))?;
    let mut cameras = Vec::new();
    for info in infos {
        let index = info.index().clone();
        let mut formats = Vec::new();
        let request = RequestedFormat::with_formats(RequestedFormatType::None, &DECODED);
        if let Ok(mut cam) = Camera::new(index.clone(), request) {
            formats = cam.compatible_camera_formats().unwrap_or_default();
        }
        cameras.push(CameraInfo {
            path: index.to_string(),
            name: info.human_name(),
            driver: format!("nokhwa {api:?}"),
            offers: offers(&formats),
        });
    }
    Ok(cameras)
}

/// A streaming nokhwa camera. nokhwa's `Camera` is not `Send`, so it lives on its own thread,
/// which opens it, streams, and hands decoded frames over a bounded channel; dropping the
/// source ends that thread after its next frame.
struct NokhwaSource {
    source: String,
    name: String,
    layout: Layout,
    fps: u32,
    frames: Receiver<Result<Frame>>,
}

/// What the camera thread reports once the stream runs.
struct Opened {
    name: String,
    layout: Layout,
    fps: u32,
}

/// Microseconds on the monotonic clock since the first call in this process.
fn receipt_us() -> i64 {
    static ANCHOR: OnceLock<Instant> = OnceLock::new();
    let anchor = *ANCHOR.get_or_init(Instant::now);
    i64::try_from(anchor.elapsed().as_micros()).unwrap_or(i64::MAX)
}

/// Opens camera `source` (an index), negotiates, starts streaming and reads the first frame.
pub(super) fn open(source: &str, config: &CameraConfig) -> Result<Box<dyn FrameSource>> {
    super::check_buffers(config)?;
    let (opened_tx, opened_rx) = bounded::<Result<Opened>>(1);
    let (frames_tx, frames_rx) = bounded::<Result<Frame>>(config.buffers as usize);
    let (thread_source, thread_config) = (source.to_string(), config.clone());
    std::thread::Builder::new()
        .name("v2ce-camera".into())
        .spawn(move || {
            let camera = match start(&thread_source, &thread_config) {
                Ok((camera, opened)) => {
                    let layout = opened.layout;
                    if opened_tx.send(Ok(opened)).is_err() {
                        return;
                    }
                    (camera, layout)
                }
                Err(e) => {
                    let _ = opened_tx.send(Err(e));
                    return;
                }
            };
            stream(&thread_source, camera.0, camera.1, &frames_tx);
        })
        .map_err(|e| Error::io(source, e))?;
    let opened = opened_rx.recv().map_err(|_| {
        Error::invalid(
            "camera",
            format!("{source}: the camera thread ended while opening"),
        )
    })??;
    CameraSource::start(NokhwaSource {
        source: source.to_string(),
        name: opened.name,
        layout: opened.layout,
        fps: opened.fps,
        frames: frames_rx,
    })
}

/// On the camera thread: opens, negotiates and starts the stream.
fn start(source: &str, config: &CameraConfig) -> Result<(Camera, Opened)> {
    let any = RequestedFormat::with_formats(RequestedFormatType::None, &DECODED);
    let mut camera =
        Camera::new(camera_index(source), any).map_err(|e| err(source, "cannot open", e))?;
    let formats = camera
        .compatible_camera_formats()
        .map_err(|e| err(source, "cannot list formats", e))?;
    let choice =
        negotiate::choose(&offers(&formats), config).map_err(|e| super::about_camera(source, e))?;
    let fps = choice.fps().unwrap_or(config.fps).round().max(1.0) as u32;
    let wanted = CameraFormat::new(
        Resolution::new(choice.width, choice.height),
        frame_format(choice.format),
        fps,
    );
    camera
        .set_camera_requset(RequestedFormat::with_formats(
            RequestedFormatType::Exact(wanted),
            &DECODED,
        ))
        .map_err(|e| err(source, "cannot set the format", e))?;
    camera
        .open_stream()
        .map_err(|e| err(source, "cannot start streaming", e))?;
    // What the backend actually runs.
    let actual = camera.camera_format();
    let format = match actual.format() {
        FrameFormat::GRAY => PixelFormat::Grey,
        FrameFormat::YUYV => PixelFormat::Yuyv,
        FrameFormat::MJPEG => PixelFormat::Mjpeg,
        other => {
            return Err(err(
                source,
                "the backend switched to a format v2ce does not decode",
                other,
            ))
        }
    };
    let opened = Opened {
        name: camera.info().human_name(),
        layout: Layout {
            format,
            width: actual.width(),
            height: actual.height(),
            stride: 0,
        },
        fps: actual.frame_rate(),
    };
    Ok((camera, opened))
}

/// On the camera thread: reads, times and decodes frames until the receiver goes away or
/// capture fails (the error is the last message).
fn stream(source: &str, mut camera: Camera, layout: Layout, out: &Sender<Result<Frame>>) {
    let mut backend_times = None;
    let mut last_t: Option<i64> = None;
    let mut skipped = 0;
    loop {
        let buffer = match camera.frame() {
            Ok(b) => b,
            Err(e) => {
                let _ = out.send(Err(err(source, "capture failed (camera unplugged?)", e)));
                return;
            }
        };
        let received = receipt_us();
        let stamp = buffer
            .capture_timestamp()
            .map(|d| i64::try_from(d.as_micros()).unwrap_or(i64::MAX));
        let use_backend = *backend_times.get_or_insert(stamp.is_some());
        let t = if use_backend { stamp } else { Some(received) };
        let decoded = match t {
            Some(t) if last_t.is_none_or(|last| t > last) => {
                pixels::decode(&layout, buffer.buffer(), t, source).map_err(Some)
            }
            _ => Err(None),
        };
        let message = match decoded {
            Ok(frame) => {
                skipped = 0;
                last_t = Some(frame.t);
                Ok(frame)
            }
            // A corrupt or untimed frame is skipped, not fatal; many in a row are.
            Err(e) => {
                skipped += 1;
                if skipped < MAX_SKIPPED {
                    continue;
                }
                Err(e.unwrap_or_else(|| {
                    err(
                        source,
                        "capture failed",
                        format!("{MAX_SKIPPED} frames in a row had no usable timestamp"),
                    )
                }))
            }
        };
        let failed = message.is_err();
        if out.send(message).is_err() || failed {
            return;
        }
    }
}

impl camera_source::Stream for NokhwaSource {
    fn layout(&self) -> &Layout {
        &self.layout
    }

    fn read(&mut self) -> Result<Option<Frame>> {
        match self.frames.recv() {
            Ok(frame) => frame.map(Some),
            Err(_) => Err(Error::invalid(
                "camera",
                format!("{}: the camera thread has stopped", self.source),
            )),
        }
    }

    fn describe(&self) -> String {
        format!(
            "camera {} ({}) {}x{} {} {} fps",
            self.source,
            self.name,
            self.layout.width,
            self.layout.height,
            self.layout.format,
            self.fps
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offers_group_rates_by_format_and_size() {
        let formats = [
            CameraFormat::new_from(640, 480, FrameFormat::YUYV, 15),
            CameraFormat::new_from(640, 480, FrameFormat::YUYV, 30),
            CameraFormat::new_from(640, 480, FrameFormat::MJPEG, 30),
            CameraFormat::new_from(640, 480, FrameFormat::NV12, 30),
        ];
        let o = offers(&formats);
        assert_eq!(o.len(), 3);
        assert_eq!(o[0].to_string(), "YUYV 640x480 30, 15 fps");
        assert_eq!(o[1].format(), Some(PixelFormat::Mjpeg));
        assert_eq!(o[2].format(), None);
        let c = negotiate::choose(&o, &CameraConfig::default()).unwrap();
        assert_eq!((c.format, c.fps()), (PixelFormat::Yuyv, Some(30.0)));
    }

    #[test]
    fn receipt_clock_is_monotonic() {
        let a = receipt_us();
        let b = receipt_us();
        assert!(b >= a && a >= 0);
    }
}
