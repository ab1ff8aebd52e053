//! `v2ce render`: event frames from an event file, the way event-camera viewers show events: a
//! PNG of one accumulated frame (the quickest answer to "did it work"), or a GIF or MP4 of
//! frames at a given rate.
//!
//! Each output frame shows the events of its window, ON and OFF in two colours over a dark
//! background: either the fixed window of one frame period (the default), or with `decay`
//! every event fading exponentially with the given time constant, so motion leaves a trail.
//! Where a pixel has events of both polarities in a frame, the later one's colour shows.
//! Streaming: memory holds one frame, whatever the file's length. MP4 goes through the `ffmpeg`
//! command-line tool (H.264); PNG and GIF are written by the `image` crate.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use serde::Serialize;

use crate::error::{Error, Result};
use crate::event::Event;
use crate::format;

/// Background colour (RGB).
pub const BACKGROUND: [u8; 3] = [20, 20, 20];
/// Colour of an ON event.
pub const ON_COLOUR: [u8; 3] = [255, 200, 40];
/// Colour of an OFF event.
pub const OFF_COLOUR: [u8; 3] = [40, 140, 255];

/// What to render.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOptions {
    /// Output frames per second of event time (GIF, MP4).
    pub fps: f64,
    /// Exponential decay time constant, us (`None`: a fixed window of one frame period).
    pub decay_us: Option<f64>,
    /// Play back this many times slower than real time (GIF, MP4).
    pub slowdown: f64,
    /// Sensor size when the file has none.
    pub size: Option<(u16, u16)>,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            fps: 30.0,
            decay_us: None,
            slowdown: 1.0,
            size: None,
        }
    }
}

/// What [`render`] wrote.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RenderReport {
    /// Frames written.
    pub frames: u64,
    /// Events drawn.
    pub events: u64,
    /// Frame width and height.
    pub size: (u16, u16),
}

/// Memory a render takes per pixel: the canvas (16), the RGB frame (3), its RGBA copy for GIF
/// (4) and the encoder's buffers (about as much again).
const BYTES_PER_PIXEL: u64 = 48;

/// One frame's state: the last polarity and time at each pixel.
struct Canvas {
    width: usize,
    height: usize,
    /// Per pixel: time of the latest event (i64::MIN: none) and its polarity.
    last: Vec<(i64, bool)>,
}

impl Canvas {
    fn new(width: u16, height: u16) -> Self {
        let n = width as usize * height as usize;
        Canvas {
            width: width as usize,
            height: height as usize,
            last: vec![(i64::MIN, false); n],
        }
    }

    fn add(&mut self, e: &Event) {
        if (e.x as usize) < self.width && (e.y as usize) < self.height {
            self.last[e.y as usize * self.width + e.x as usize] = (e.t, e.on);
        }
    }

    /// RGB pixels at time `now`: events at or after `since` in full colour (fixed window), or all
    /// faded by `decay` (time constant, us).
    fn pixels(&self, now: i64, since: i64, decay: Option<f64>, out: &mut Vec<u8>) {
        out.clear();
        for &(t, on) in &self.last {
            let colour = if on { ON_COLOUR } else { OFF_COLOUR };
            let w = match (t, decay) {
                (i64::MIN, _) => 0.0,
                (t, None) => (t >= since) as u8 as f64,
                (t, Some(tau)) => (-((now - t).max(0) as f64) / tau).exp(),
            };
            for c in 0..3 {
                let v = BACKGROUND[c] as f64 + (colour[c] as f64 - BACKGROUND[c] as f64) * w;
                out.push(v.round().clamp(0.0, 255.0) as u8);
            }
        }
    }
}

enum Output {
    Png(PathBuf),
    Gif(image::codecs::gif::GifEncoder<std::fs::File>),
    Mp4(Child),
}

/// Renders `input` to `output` (`.png`: every event in one frame; `.gif`, `.mp4`: frames at
/// `options.fps`).
pub fn render(input: &Path, output: &Path, options: &RenderOptions) -> Result<RenderReport> {
    if !(options.fps.is_finite() && options.fps > 0.0 && options.fps <= 10_000.0) {
        return Err(Error::invalid(
            "fps",
            format!("{} (must be in (0, 10000])", options.fps),
        ));
    }
    // The lowest rate too: a frame period any time in range can be added to.
    crate::limits::frame_rate("fps", options.fps)?;
    if !(options.slowdown.is_finite() && options.slowdown > 0.0) {
        return Err(Error::invalid("slowdown", "must be positive"));
    }
    if let Some(d) = options.decay_us {
        if !(d.is_finite() && d > 0.0) {
            return Err(Error::invalid("decay", "must be positive"));
        }
    }
    let mut decoder = format::open(input)?;
    let (w, h) = decoder.size().or(options.size).ok_or_else(|| {
        Error::invalid(
            "size",
            format!("{} has no sensor size: give --size WxH", input.display()),
        )
    })?;
    // The size may come from a file's header: bounded before the canvas is allocated.
    crate::limits::frame_size("size", w.into(), h.into())?;
    crate::limits::memory(
        "size",
        w as u64 * h as u64 * BYTES_PER_PIXEL,
        &format!("rendering {w} x {h}"),
    )?;
    let ext = output
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let mut out = match ext.as_str() {
        "png" => Output::Png(output.to_path_buf()),
        "gif" => {
            let file = std::fs::File::create(output).map_err(|e| Error::io(output, e))?;
            let mut enc = image::codecs::gif::GifEncoder::new_with_speed(file, 10);
            enc.set_repeat(image::codecs::gif::Repeat::Infinite)
                .map_err(|e| Error::format(output, e.to_string()))?;
            Output::Gif(enc)
        }
        "mp4" => Output::Mp4(ffmpeg(output, w, h, options.fps / options.slowdown)?),
        other => {
            return Err(Error::invalid(
                "output",
                format!("'.{other}': render writes .png, .gif or .mp4"),
            ))
        }
    };
    let mut canvas = Canvas::new(w, h);
    let period = (1e6 / options.fps).round().max(1.0) as i64;
    let mut report = RenderReport {
        frames: 0,
        events: 0,
        size: (w, h),
    };
    let mut rgb = Vec::new();
    let mut buf = Vec::new();
    // The end of the current frame's window (set by the first event).
    let mut frame_end: Option<i64> = None;
    let mut emit = |canvas: &Canvas, end: i64, out: &mut Output, report: &mut RenderReport| {
        canvas.pixels(end, end - period, options.decay_us, &mut rgb);
        report.frames += 1;
        write_frame(out, &rgb, w, h, options.fps / options.slowdown, output)
    };
    loop {
        buf.clear();
        if decoder.read_events(&mut buf, 1 << 16)? == 0 {
            break;
        }
        for e in &buf {
            report.events += 1;
            if matches!(out, Output::Png(_)) {
                canvas.add(e);
                continue;
            }
            let end = match frame_end {
                Some(end) => end,
                None => *frame_end.insert(crate::time::checked_add("frame end", e.t, period)?),
            };
            if e.t >= end {
                // Close every frame up to the one this event falls in (empty ones too): as
                // many frames as one run takes at most (times are in range: no wrap).
                let closing = (e.t - end) / period + 1;
                crate::limits::intervals("render --fps", report.frames as f64 + closing as f64)?;
                let mut end = end;
                while e.t >= end {
                    emit(&canvas, end, &mut out, &mut report)?;
                    end += period;
                }
                frame_end = Some(end);
            }
            canvas.add(e);
        }
    }
    match out {
        Output::Png(path) => {
            // One frame holding every event.
            canvas.pixels(i64::MAX, i64::MIN, None, &mut rgb);
            image::save_buffer(
                &path,
                &rgb,
                w as u32,
                h as u32,
                image::ExtendedColorType::Rgb8,
            )
            .map_err(|e| Error::format(&path, e.to_string()))?;
            report.frames = 1;
        }
        mut out => {
            if let Some(end) = frame_end {
                emit(&canvas, end, &mut out, &mut report)?;
            }
            if let Output::Mp4(mut child) = out {
                drop(child.stdin.take());
                let status = child.wait().map_err(|e| Error::io("ffmpeg", e))?;
                if !status.success() {
                    return Err(Error::format(output, format!("ffmpeg failed: {status}")));
                }
            }
        }
    }
    Ok(report)
}

fn write_frame(out: &mut Output, rgb: &[u8], w: u16, h: u16, fps: f64, path: &Path) -> Result<()> {
    match out {
        Output::Png(_) => Ok(()),
        Output::Gif(enc) => {
            let mut rgba = Vec::with_capacity(rgb.len() / 3 * 4);
            for p in rgb.chunks_exact(3) {
                rgba.extend_from_slice(&[p[0], p[1], p[2], 255]);
            }
            let buffer = image::RgbaImage::from_raw(w as u32, h as u32, rgba)
                .ok_or_else(|| Error::invalid("frame", "size mismatch"))?;
            let delay =
                image::Delay::from_numer_denom_ms((1000.0 / fps).round().max(1.0) as u32, 1);
            enc.encode_frame(image::Frame::from_parts(buffer, 0, 0, delay))
                .map_err(|e| Error::format(path, e.to_string()))
        }
        Output::Mp4(child) => {
            let stdin = child
                .stdin
                .as_mut()
                .ok_or_else(|| Error::invalid("ffmpeg", "no input pipe"))?;
            stdin
                .write_all(rgb)
                .map_err(|e| Error::io("ffmpeg (it stopped reading)", e))
        }
    }
}

/// `ffmpeg` encoding raw RGB frames from its standard input to H.264 in `output` (odd sizes
/// padded to even, as yuv420p needs).
fn ffmpeg(output: &Path, w: u16, h: u16, fps: f64) -> Result<Child> {
    Command::new("ffmpeg")
        .args(["-loglevel", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24"])
        .args(["-s", &format!("{w}x{h}"), "-r", &format!("{fps}"), "-i", "-"])
        .args(["-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-pix_fmt", "yuv420p"])
        .args(["-c:v", "libx264"])
        .arg(output)
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .map_err(|e| {
            Error::invalid(
                "ffmpeg",
                format!("cannot start it for an MP4 ({e}); install it (apt-get install ffmpeg) or write .gif"),
            )
        })
}
