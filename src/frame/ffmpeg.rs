//! Video files through the `ffmpeg` command-line tool (Debian's `ffmpeg` package).
//!
//! `ffprobe` gives the frame size; `ffmpeg` decodes the first video stream to `rgb24` on a pipe
//! with `-fps_mode passthrough` (no frame duplicated or dropped) and its `showinfo` filter
//! prints each frame's presentation timestamp, which becomes the frame's time, so variable frame
//! rates and odd rates (29.97) are kept exactly. Memory stays at one frame.

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::sync::mpsc::{channel, Receiver};

use super::color::rgb24_to_luma;
use super::{check_order, Frame, FrameSource};
use crate::error::{Error, Result};

/// Decodes a video file with `ffmpeg`.
pub struct FfmpegSource {
    path: PathBuf,
    child: Child,
    stdout: ChildStdout,
    times: Receiver<i64>,
    stderr_tail: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
    size: (u16, u16),
    frames: Option<u64>,
    rgb: Vec<u8>,
    last_t: Option<i64>,
    index: usize,
}

fn tool_error(path: &Path, tool: &str, e: std::io::Error) -> Error {
    if e.kind() == std::io::ErrorKind::NotFound {
        Error::invalid(
            "video input",
            format!(
                "{}: `{tool}` was not found; install it (Debian: apt-get install ffmpeg) or give frames as a .y4m or an image folder",
                path.display()
            ),
        )
    } else {
        Error::io(path, e)
    }
}

/// Frame width and height of the first video stream, and its frame count when the container
/// says, from `ffprobe`.
fn probe_size(path: &Path) -> Result<((u16, u16), Option<u64>)> {
    let out = Command::new("ffprobe")
        .args(["-v", "error", "-select_streams", "v:0"])
        .args([
            "-show_entries",
            "stream=width,height,nb_frames",
            "-of",
            "csv=p=0:s=x",
        ])
        .arg(path)
        .stdin(Stdio::null())
        .output()
        .map_err(|e| tool_error(path, "ffprobe", e))?;
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text.lines().next().unwrap_or("").trim();
    let mut fields = line.split('x');
    let parsed = fields
        .next()
        .zip(fields.next())
        .and_then(|(w, h)| Some((w.parse::<u16>().ok()?, h.parse::<u16>().ok()?)));
    // "N/A" where the container does not say.
    let frames = fields.next().and_then(|n| n.trim().parse::<u64>().ok());
    match parsed {
        Some((w, h)) if out.status.success() && w > 0 && h > 0 => Ok(((w, h), frames)),
        _ => Err(Error::format(
            path,
            format!(
                "not a readable video (ffprobe: {})",
                one_line(&String::from_utf8_lossy(&out.stderr))
            ),
        )),
    }
}

/// A tool's messages as one line: lines joined with " | ", blank ones dropped, at most 400
/// characters (errors stay one line on the terminal and in the journal).
fn one_line(text: &str) -> String {
    let joined = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect::<Vec<_>>()
        .join(" | ");
    match joined.char_indices().nth(400) {
        Some((at, _)) => format!("{}...", &joined[..at]),
        None => joined,
    }
}

/// Parses `config in time_base: N/D` out of a `showinfo` line.
fn parse_time_base(line: &str) -> Option<(i128, i128)> {
    let rest = line.split("config in time_base:").nth(1)?;
    let (n, d) = rest.split(',').next()?.trim().split_once('/')?;
    let (n, d) = (n.parse().ok()?, d.parse().ok()?);
    (n > 0 && d > 0).then_some((n, d))
}

/// Parses the integer `pts:` of a `showinfo` frame line and converts it to us with the stream's
/// time base, exactly (`pts_time` is printed with six significant digits only).
fn parse_pts_us(line: &str, (num, den): (i128, i128)) -> Option<i64> {
    let rest = line.split(" pts:").nth(1)?;
    let pts: i128 = rest.split_whitespace().next()?.parse().ok()?;
    let us = pts * num * 1_000_000;
    let rounded = if us >= 0 {
        (us + den / 2) / den
    } else {
        (us - den / 2) / den
    };
    i64::try_from(rounded).ok()
}

impl FfmpegSource {
    /// Starts decoding `path`.
    pub fn open(path: &Path) -> Result<Self> {
        let (size, frames) = probe_size(path)?;
        let mut child = Command::new("ffmpeg")
            .args([
                "-nostdin",
                "-hide_banner",
                "-nostats",
                "-loglevel",
                "info",
                "-i",
            ])
            .arg(path)
            .args([
                "-map",
                "0:v:0",
                "-fps_mode",
                "passthrough",
                "-vf",
                "showinfo",
            ])
            .args(["-f", "rawvideo", "-pix_fmt", "rgb24", "pipe:1"])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| tool_error(path, "ffmpeg", e))?;
        let stdout = child
            .stdout
            .take()
            .ok_or_else(|| Error::format(path, "ffmpeg gave no output pipe"))?;
        let stderr = child
            .stderr
            .take()
            .ok_or_else(|| Error::format(path, "ffmpeg gave no error pipe"))?;
        let (tx, times) = channel();
        let stderr_tail = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let tail = stderr_tail.clone();
        std::thread::spawn(move || {
            let mut time_base = None;
            for line in BufReader::new(stderr).lines().map_while(|l| l.ok()) {
                if let Some(tb) = parse_time_base(&line) {
                    time_base = Some(tb);
                } else if line.contains("Parsed_showinfo") && line.contains(" n:") {
                    if let Some(t) = time_base.and_then(|tb| parse_pts_us(&line, tb)) {
                        if tx.send(t).is_err() {
                            break;
                        }
                    }
                } else if let Ok(mut tail) = tail.lock() {
                    tail.push(line);
                    if tail.len() > 8 {
                        tail.remove(0);
                    }
                }
            }
        });
        Ok(FfmpegSource {
            path: path.to_path_buf(),
            child,
            stdout,
            times,
            stderr_tail,
            size,
            frames,
            rgb: vec![0; size.0 as usize * size.1 as usize * 3],
            last_t: None,
            index: 0,
        })
    }

    fn failure(&mut self, what: &str) -> Error {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let tail = self
            .stderr_tail
            .lock()
            .map(|t| one_line(&t.join("\n")))
            .unwrap_or_default();
        Error::format(&self.path, format!("{what} (ffmpeg: {tail})"))
    }
}

impl FrameSource for FfmpegSource {
    fn size(&self) -> (u16, u16) {
        self.size
    }

    fn next_frame(&mut self) -> Result<Option<Frame>> {
        let mut filled = 0;
        while filled < self.rgb.len() {
            match self.stdout.read(&mut self.rgb[filled..]) {
                Ok(0) => break,
                Ok(n) => filled += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(Error::io(&self.path, e)),
            }
        }
        if filled == 0 {
            let status = self.child.wait().map_err(|e| Error::io(&self.path, e))?;
            if !status.success() {
                return Err(self.failure(&format!("decoding failed after {} frames", self.index)));
            }
            return Ok(None);
        }
        if filled < self.rgb.len() {
            return Err(self.failure(&format!("frame {} cut short", self.index)));
        }
        let Ok(t) = self.times.recv() else {
            return Err(self.failure(&format!("no timestamp for frame {}", self.index)));
        };
        check_order(&self.path, self.last_t, t, self.index)?;
        self.last_t = Some(t);
        self.index += 1;
        let mut luma = Vec::new();
        rgb24_to_luma(&self.rgb, &mut luma);
        Ok(Some(Frame::new(t, self.size, luma)))
    }

    fn describe(&self) -> String {
        format!("video {} (ffmpeg)", self.path.display())
    }

    fn frames_hint(&self) -> Option<u64> {
        self.frames
    }
}

impl Drop for FfmpegSource {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn showinfo_times() {
        let tb =
            "[Parsed_showinfo_0 @ 0x5] config in time_base: 1001/30000, frame_rate: 30000/1001";
        let tb = super::parse_time_base(tb).unwrap();
        assert_eq!(tb, (1001, 30000));
        let line = "[Parsed_showinfo_0 @ 0x55] n:   1 pts:      1 pts_time:0.0333667 pos: -1";
        assert_eq!(super::parse_pts_us(line, tb), Some(33_367));
        // Past 1000 s, where pts_time's six digits would lose a millisecond.
        let line = "[Parsed_showinfo_0 @ 0x55] n: 40000 pts:  40000 pts_time:1334.67";
        assert_eq!(super::parse_pts_us(line, tb), Some(1_334_666_667));
        assert_eq!(super::parse_pts_us("n: 0", tb), None);
    }
}
