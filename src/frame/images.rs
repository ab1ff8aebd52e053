//! A folder of PNG or JPEG images as a frame source.
//!
//! Frame times come from, in order of preference: an `images.txt` in the folder (IJRR layout:
//! `t_seconds relative/path` per line, which also names the images), a `times.txt` (one time in
//! seconds per line, for the images sorted by name), or a frame rate (`--fps`). Images are
//! decoded with the `image` crate; colour and gray values go through the sRGB transfer function
//! unless the source is marked linear (raw sensor exports such as DAVIS APS frames).

use std::path::{Path, PathBuf};

use super::color::{gray_to_luma, rgb_to_luma};
use super::{check_order, Frame, FrameSource};
use crate::error::{Error, Result};
use crate::format::ijrr::parse_seconds_us;

/// Reads images from a folder.
pub struct ImageFolder {
    folder: PathBuf,
    frames: Vec<(i64, PathBuf)>,
    next: usize,
    size: (u16, u16),
    linear: bool,
}

fn list_images(folder: &Path) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(folder)
        .map_err(|e| Error::io(folder, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
        })
        .collect();
    files.sort();
    Ok(files)
}

fn read_lines(path: &Path) -> Result<Vec<String>> {
    Ok(std::fs::read_to_string(path)
        .map_err(|e| Error::io(path, e))?
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(String::from)
        .collect())
}

impl ImageFolder {
    /// Lists the folder's frames and reads the first to learn the size; `linear` skips the
    /// sRGB transfer function.
    pub fn open(folder: &Path, fps: Option<f64>, linear: bool) -> Result<Self> {
        let ijrr = folder.join("images.txt");
        let times = folder.join("times.txt");
        let frames: Vec<(i64, PathBuf)> = if ijrr.is_file() {
            read_lines(&ijrr)?
                .iter()
                .enumerate()
                .map(|(i, line)| {
                    let mut f = line.split_whitespace();
                    match (f.next().and_then(parse_seconds_us), f.next()) {
                        (Some(t), Some(p)) => Ok((t, folder.join(p))),
                        _ => Err(Error::format(
                            &ijrr,
                            format!("line {}: expected 't_seconds path', got '{line}'", i + 1),
                        )),
                    }
                })
                .collect::<Result<_>>()?
        } else {
            let files = list_images(folder)?;
            let stamps: Vec<i64> = if times.is_file() {
                let lines = read_lines(&times)?;
                if lines.len() != files.len() {
                    return Err(Error::format(
                        &times,
                        format!("{} times for {} images", lines.len(), files.len()),
                    ));
                }
                lines
                    .iter()
                    .enumerate()
                    .map(|(i, l)| {
                        parse_seconds_us(l).ok_or_else(|| {
                            Error::format(&times, format!("line {}: bad time '{l}'", i + 1))
                        })
                    })
                    .collect::<Result<_>>()?
            } else {
                let fps = fps.filter(|f| f.is_finite() && *f > 0.0).ok_or_else(|| {
                    Error::invalid(
                        "frame times",
                        format!(
                            "{} has no images.txt or times.txt: give --fps",
                            folder.display()
                        ),
                    )
                })?;
                (0..files.len())
                    .map(|i| (i as f64 * 1e6 / fps).round() as i64)
                    .collect()
            };
            stamps.into_iter().zip(files).collect()
        };
        let first = frames
            .first()
            .ok_or_else(|| Error::format(folder, "no PNG or JPEG images"))?;
        let img = image::open(&first.1).map_err(|e| Error::format(&first.1, e.to_string()))?;
        let size = match (u16::try_from(img.width()), u16::try_from(img.height())) {
            (Ok(w), Ok(h)) => (w, h),
            _ => return Err(Error::format(&first.1, "image too large")),
        };
        Ok(ImageFolder {
            folder: folder.to_path_buf(),
            frames,
            next: 0,
            size,
            linear,
        })
    }
}

impl FrameSource for ImageFolder {
    fn size(&self) -> (u16, u16) {
        self.size
    }

    fn next_frame(&mut self) -> Result<Option<Frame>> {
        let Some((t, path)) = self.frames.get(self.next).cloned() else {
            return Ok(None);
        };
        let previous = self.next.checked_sub(1).map(|i| self.frames[i].0);
        check_order(&self.folder, previous, t, self.next)?;
        self.next += 1;
        let img = image::open(&path).map_err(|e| Error::format(&path, e.to_string()))?;
        if (img.width(), img.height()) != (self.size.0 as u32, self.size.1 as u32) {
            return Err(Error::format(
                &path,
                format!(
                    "{} x {} where the first image is {} x {}",
                    img.width(),
                    img.height(),
                    self.size.0,
                    self.size.1
                ),
            ));
        }
        let luma = if img.color().has_color() {
            let rgb = img.to_rgb8();
            if self.linear {
                rgb.pixels()
                    .map(|p| {
                        let y = 0.2126 * p[0] as f32 + 0.7152 * p[1] as f32 + 0.0722 * p[2] as f32;
                        (y * 257.0).round().min(65535.0) as u16
                    })
                    .collect()
            } else {
                rgb.pixels()
                    .map(|p| rgb_to_luma(p[0], p[1], p[2]))
                    .collect()
            }
        } else {
            let gray = img.to_luma8();
            if self.linear {
                gray.pixels().map(|p| p[0] as u16 * 257).collect()
            } else {
                gray.pixels().map(|p| gray_to_luma(p[0])).collect()
            }
        };
        Ok(Some(Frame {
            t,
            width: self.size.0,
            height: self.size.1,
            luma,
        }))
    }

    fn describe(&self) -> String {
        format!(
            "{} images in {}{}",
            self.frames.len(),
            self.folder.display(),
            if self.linear { " (linear)" } else { "" }
        )
    }

    fn frames_hint(&self) -> Option<u64> {
        Some(self.frames.len() as u64)
    }

    fn encoding(&self) -> super::SourceEncoding {
        if self.linear {
            super::SourceEncoding::Linear
        } else {
            super::SourceEncoding::Srgb
        }
    }
}
