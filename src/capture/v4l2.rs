//! The V4L2 backend (Linux), through the `v4l` crate: capability and format enumeration,
//! negotiation, memory-mapped streaming.

use std::io;
use std::path::{Path, PathBuf};
use std::time::Duration;

use v4l::buffer::{Flags as BufferFlags, Type};
use v4l::capability::Flags as CapFlags;
use v4l::frameinterval::FrameIntervalEnum;
use v4l::framesize::FrameSizeEnum;
use v4l::io::mmap::Stream;
use v4l::io::traits::CaptureStream;
use v4l::video::capture::Parameters;
use v4l::video::Capture;
use v4l::{Device, Format, FourCC, Fraction};

use super::camera_source::{self, CameraSource};
use super::negotiate::{self, Interval, Offer, Rates, Sizes};
use super::pixels::{self, Layout};
use super::{CameraConfig, CameraInfo, PixelFormat};
use crate::error::{Error, Result};
use crate::frame::{Frame, FrameSource};

/// `V4L2_FRMIVAL_TYPE_CONTINUOUS`.
const FRMIVAL_TYPE_CONTINUOUS: u32 = 2;

/// How many unusable buffers in a row (error flag, time not advancing, not decodable) before
/// giving up.
const MAX_SKIPPED: u32 = 64;

/// The `/dev/video<N>` nodes, in index order; empty when there is no `/dev` to read.
fn video_nodes() -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir("/dev") else {
        return Vec::new();
    };
    let mut nodes: Vec<(u32, PathBuf)> = entries
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name();
            let index = super::camera_index(&format!("/dev/{}", name.to_str()?))?;
            Some((index, e.path()))
        })
        .collect();
    nodes.sort();
    nodes.into_iter().map(|(_, p)| p).collect()
}

fn io_err(path: &str, what: &str, e: io::Error) -> Error {
    Error::io(path, io::Error::new(e.kind(), format!("{what}: {e}")))
}

fn fraction(i: Interval) -> Fraction {
    Fraction::new(i.num, i.den)
}

fn interval(f: Fraction) -> Interval {
    Interval::new(f.numerator, f.denominator)
}

/// The frame rates the driver lists for one format and size; unknown when it lists none.
fn rates(dev: &Device, fourcc: FourCC, width: u32, height: u32) -> Rates {
    let Ok(list) = dev.enum_frameintervals(fourcc, width, height) else {
        return Rates::Discrete(Vec::new());
    };
    let mut discrete = Vec::new();
    for fi in list {
        match fi.interval {
            FrameIntervalEnum::Discrete(f) => discrete.push(interval(f)),
            FrameIntervalEnum::Stepwise(s) if fi.typ == FRMIVAL_TYPE_CONTINUOUS => {
                return Rates::Continuous {
                    min: interval(s.min),
                    max: interval(s.max),
                }
            }
            FrameIntervalEnum::Stepwise(s) => {
                return Rates::Stepwise {
                    min: interval(s.min),
                    max: interval(s.max),
                    step: interval(s.step),
                }
            }
        }
    }
    Rates::Discrete(discrete)
}

/// Everything the device offers for capture. Rates of a size range are enumerated at the size
/// of the range that fits `request`, or at its largest size.
fn offers(dev: &Device, request: Option<(u32, u32)>) -> Vec<Offer> {
    let mut out = Vec::new();
    for desc in dev.enum_formats().unwrap_or_default() {
        let fourcc = desc.fourcc;
        let Ok(sizes) = dev.enum_framesizes(fourcc) else {
            continue;
        };
        for fs in sizes {
            let sizes = match fs.size {
                FrameSizeEnum::Discrete(d) => Sizes::Discrete {
                    width: d.width,
                    height: d.height,
                },
                FrameSizeEnum::Stepwise(s) => Sizes::Stepwise {
                    min_width: s.min_width,
                    max_width: s.max_width,
                    step_width: s.step_width,
                    min_height: s.min_height,
                    max_height: s.max_height,
                    step_height: s.step_height,
                },
            };
            let (w, h) = match request {
                Some((w, h)) => sizes.fit(w, h),
                None => sizes.largest(),
            };
            out.push(Offer {
                fourcc: fourcc.repr,
                rates: rates(dev, fourcc, w, h),
                sizes,
            });
        }
    }
    if out.is_empty() {
        // Drivers without size enumeration: offer what is currently set.
        if let Ok(f) = dev.format() {
            out.push(Offer {
                fourcc: f.fourcc.repr,
                sizes: Sizes::Discrete {
                    width: f.width,
                    height: f.height,
                },
                rates: rates(dev, f.fourcc, f.width, f.height),
            });
        }
    }
    out
}

/// Opens `path` and checks that it captures video (metadata nodes of UVC cameras do not).
fn open_capture_device(path: &str) -> Result<(Device, v4l::capability::Capabilities)> {
    let dev = Device::with_path(path).map_err(|e| io_err(path, "cannot open camera", e))?;
    let caps = dev
        .query_caps()
        .map_err(|e| io_err(path, "cannot query camera capabilities", e))?;
    Ok((dev, caps))
}

/// Lists the video-capture nodes under `/dev`.
pub(super) fn list() -> Result<Vec<CameraInfo>> {
    let mut cameras = Vec::new();
    for node in video_nodes() {
        let path = node.to_string_lossy().into_owned();
        let (dev, caps) = match open_capture_device(&path) {
            Ok(x) => x,
            Err(Error::Io { source, .. }) if source.kind() == io::ErrorKind::PermissionDenied => {
                return Err(Error::io(
                    &node,
                    io::Error::new(
                        io::ErrorKind::PermissionDenied,
                        "permission denied (is the user in the \"video\" group?)",
                    ),
                ))
            }
            // Vanished between listing and opening, or not a V4L2 device after all.
            Err(_) => continue,
        };
        if !caps.capabilities.contains(CapFlags::VIDEO_CAPTURE) {
            continue;
        }
        cameras.push(CameraInfo {
            path,
            name: caps.card.clone(),
            driver: caps.driver.clone(),
            offers: offers(&dev, None),
        });
    }
    Ok(cameras)
}

/// A streaming V4L2 camera.
struct V4l2Source {
    path: String,
    name: String,
    layout: Layout,
    fps: Option<f64>,
    /// `Option` only so that `Drop` can take it (see there).
    stream: Option<Stream<'static>>,
    last_t: Option<i64>,
    // Dropped after the stream (declaration order); the stream holds its own handle anyway.
    _device: Device,
}

/// Opens `source`, negotiates, starts streaming and reads the first frame.
pub(super) fn open(source: &str, config: &CameraConfig) -> Result<Box<dyn FrameSource>> {
    super::check_buffers(config)?;
    let path = super::device_path(source);
    let (dev, caps) = open_capture_device(&path)?;
    if !caps.capabilities.contains(CapFlags::VIDEO_CAPTURE) {
        return Err(Error::invalid(
            "source",
            format!(
                "{path} ({}) is not a video capture node (a metadata node?)",
                caps.card
            ),
        ));
    }
    if !caps.capabilities.contains(CapFlags::STREAMING) {
        return Err(Error::invalid(
            "source",
            format!("{path} ({}) does not support streaming I/O", caps.card),
        ));
    }
    let offers = offers(&dev, Some((config.width, config.height)));
    let choice = negotiate::choose(&offers, config)
        .map_err(|e| super::about_camera(&format!("{path} ({})", caps.card), e))?;

    let wanted = Format::new(
        choice.width,
        choice.height,
        FourCC::new(&choice.format.fourcc()),
    );
    let set = dev
        .set_format(&wanted)
        .map_err(|e| io_err(&path, "cannot set the capture format", e))?;
    // Drivers may adjust what was asked for: use what they actually set.
    let Some(format) = PixelFormat::from_fourcc(set.fourcc.repr) else {
        return Err(Error::invalid(
            "camera",
            format!(
                "{path}: asked for {}, the driver set {} which v2ce does not decode",
                choice.format,
                super::fourcc_str(set.fourcc.repr)
            ),
        ));
    };
    let layout = Layout {
        format,
        width: set.width,
        height: set.height,
        stride: set.stride,
    };
    let want_interval = choice
        .interval
        .or_else(|| Interval::from_fps(config.fps))
        .unwrap_or(Interval::new(1, 30));
    // Not every driver can set the rate (S_PARM); then report whatever it runs at, if it says.
    let fps = match dev.set_params(&Parameters::new(fraction(want_interval))) {
        Ok(p) => interval(p.interval).fps(),
        Err(_) => dev.params().ok().and_then(|p| interval(p.interval).fps()),
    };

    let mut stream = Stream::with_buffers(&dev, Type::VideoCapture, config.buffers)
        .map_err(|e| io_err(&path, "cannot map capture buffers", e))?;
    // A stalled or unplugged camera must not block forever.
    let frame_s = fps.map(|f| 1.0 / f).unwrap_or(1.0);
    stream.set_timeout(Duration::from_secs_f64((4.0 * frame_s).clamp(2.0, 30.0)));

    CameraSource::start(V4l2Source {
        path,
        name: caps.card,
        layout,
        fps,
        stream: Some(stream),
        last_t: None,
        _device: dev,
    })
}

impl camera_source::Stream for V4l2Source {
    fn layout(&self) -> &Layout {
        &self.layout
    }

    /// Dequeues buffers until one decodes to a frame later than the previous one.
    fn read(&mut self) -> Result<Option<Frame>> {
        let Some(stream) = self.stream.as_mut() else {
            return Err(Error::invalid("camera", format!("{} is closed", self.path)));
        };
        let mut skipped = 0;
        let mut last_error = None;
        loop {
            let (buf, meta) = CaptureStream::next(stream)
                .map_err(|e| io_err(&self.path, "capture failed (camera unplugged?)", e))?;
            let used = match meta.bytesused as usize {
                0 => buf.len(),
                n => n.min(buf.len()),
            };
            // time_t is i64 on 64-bit Linux but not everywhere.
            #[allow(clippy::useless_conversion)]
            let t = super::timeval_us(
                i64::from(meta.timestamp.sec),
                i64::from(meta.timestamp.usec),
            );
            let usable =
                !meta.flags.contains(BufferFlags::ERROR) && self.last_t.is_none_or(|last| t > last);
            if usable {
                // A corrupt frame (USB glitch) is skipped, not fatal; many in a row are.
                match pixels::decode(&self.layout, &buf[..used], t, &self.path) {
                    Ok(frame) => {
                        self.last_t = Some(t);
                        return Ok(Some(frame));
                    }
                    Err(e) => last_error = Some(e),
                }
            }
            skipped += 1;
            if skipped >= MAX_SKIPPED {
                return Err(last_error.unwrap_or_else(|| {
                    Error::format(
                        Path::new(&self.path),
                        format!(
                            "{MAX_SKIPPED} buffers in a row were flagged as corrupt or did not \
                             advance in time"
                        ),
                    )
                }));
            }
        }
    }

    fn describe(&self) -> String {
        let rate = match self.fps {
            Some(f) => format!("{} fps", negotiate::format_fps(f)),
            None => "unknown fps".to_string(),
        };
        format!(
            "camera {} ({}) {}x{} {} {rate}",
            self.path, self.name, self.layout.width, self.layout.height, self.layout.format
        )
    }
}

impl Drop for V4l2Source {
    fn drop(&mut self) {
        // The v4l stream panics in its own Drop when stopping fails for a reason other than an
        // unplugged device; a camera source must never bring the process down on close.
        if let Some(stream) = self.stream.take() {
            let _ = std::panic::catch_unwind(std::panic::AssertUnwindSafe(move || drop(stream)));
        }
    }
}
