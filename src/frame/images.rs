//! A folder of PNG or JPEG images as a frame source.
//!
//! Frame times come from, in order of preference: a frame list given by name (an IJRR
//! `images.txt` or a `times.txt` anywhere), an `images.txt` in the folder (IJRR layout:
//! `t_seconds relative/path` per line, which also names the images), a `times.txt` (one time in
//! seconds per line, for the images sorted by name), or a frame rate (`--fps`). Images are
//! decoded with the `image` crate.
//!
//! Colour space ([`ColorSpace`]): values go through the sRGB transfer function (camera video,
//! photos) or are taken as linear in the light (raw sensor exports such as DAVIS APS frames).
//! `auto` (the default) reads an APS export as linear when it recognises one, the IJRR layout
//! of 8-bit gray images listed in an `images.txt` beside an `events.txt`, and otherwise takes
//! sRGB, with a warning for gray images, whose colour space is then a guess.

use std::path::{Path, PathBuf};

use clap::ValueEnum;
use serde::{Deserialize, Serialize};

use super::color::{gray_to_luma, rgb_to_luma};
use super::{check_order, Frame, FrameSource};
use crate::error::{Error, Result};
use crate::format::ijrr::{is_number, seconds_in_range};

/// How image values relate to the light.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize, ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum ColorSpace {
    /// Linear for a recognised APS export, else sRGB (warning for gray images).
    #[default]
    Auto,
    /// sRGB-encoded (camera video, photos).
    Srgb,
    /// Linear in the light (raw sensor exports).
    Linear,
}

/// Reads images from a folder.
pub struct ImageFolder {
    folder: PathBuf,
    frames: Vec<(i64, PathBuf)>,
    next: usize,
    size: (u16, u16),
    linear: bool,
    /// Why the colour space is what it is, for logs.
    color_note: &'static str,
}

/// What a frame list file holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameList {
    /// IJRR `images.txt`: `t_seconds image_path` per line.
    Images,
    /// `times.txt`: one time in seconds per line, for the folder's images sorted by name.
    Times,
}

/// Whether the text file `path` is a frame list, and which kind (from its first line that is
/// not blank or a comment); `None` for anything else. A first time out of range still makes a
/// list (whose reading then names the line), not a text file of another kind.
pub fn frame_list_kind(path: &Path) -> Option<FrameList> {
    let text = std::fs::read(path).ok()?;
    let head = &text[..text.len().min(1 << 16)];
    let line = std::str::from_utf8(head)
        .ok()?
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))?;
    let mut fields = line.split_whitespace();
    let time = fields.next().filter(|f| is_number(f));
    match (time, fields.next(), fields.next()) {
        (Some(_), Some(image), None) if is_image(Path::new(image)) => Some(FrameList::Images),
        (Some(_), None, None) => Some(FrameList::Times),
        _ => None,
    }
}

/// What an out-of-range time in a frame list is called in its error.
const FRAME_TIME: &str = "frame time";

fn is_image(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
}

fn list_images(folder: &Path) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(folder)
        .map_err(|e| Error::io(folder, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| is_image(p))
        .collect();
    files.sort();
    Ok(files)
}

/// The lines of `path` that are not blank or comments, each with its line number in the file
/// (from 1), for error messages.
fn read_lines(path: &Path) -> Result<Vec<(usize, String)>> {
    Ok(std::fs::read_to_string(path)
        .map_err(|e| Error::io(path, e))?
        .lines()
        .map(str::trim)
        .enumerate()
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
        .map(|(i, l)| (i + 1, l.to_string()))
        .collect())
}

impl ImageFolder {
    /// Lists the folder's frames and reads the first to learn the size and, for
    /// [`ColorSpace::Auto`], the colour space.
    pub fn open(folder: &Path, fps: Option<f64>, color: ColorSpace) -> Result<Self> {
        Self::open_list(folder, None, fps, color)
    }

    /// [`ImageFolder::open`] with the frame list named: an IJRR `images.txt` or a `times.txt`
    /// (its folder holds the images).
    pub fn open_list_file(list: &Path, color: ColorSpace) -> Result<Self> {
        let kind = frame_list_kind(list).ok_or_else(|| {
            Error::format(
                list,
                "not a frame list: expected 't_seconds image_path' lines (IJRR images.txt) or one time in seconds per line (times.txt)",
            )
        })?;
        let folder = match list.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        Self::open_list(&folder, Some((list, kind)), None, color)
    }

    fn open_list(
        folder: &Path,
        list: Option<(&Path, FrameList)>,
        fps: Option<f64>,
        color: ColorSpace,
    ) -> Result<Self> {
        if let Some(f) = fps {
            crate::limits::frame_rate("fps", f)?;
        }
        let (ijrr, times) = match list {
            Some((p, FrameList::Images)) => (p.to_path_buf(), PathBuf::new()),
            Some((p, FrameList::Times)) => (PathBuf::new(), p.to_path_buf()),
            None => (folder.join("images.txt"), folder.join("times.txt")),
        };
        let listed = ijrr.is_file();
        let frames: Vec<(i64, PathBuf)> = if ijrr.is_file() {
            read_lines(&ijrr)?
                .iter()
                .map(|(n, line)| {
                    let mut f = line.split_whitespace();
                    match (
                        f.next().and_then(|t| seconds_in_range(FRAME_TIME, t)),
                        f.next(),
                    ) {
                        (Some(Ok(t)), Some(p)) => Ok((t, folder.join(p))),
                        (Some(Err(e)), Some(_)) => {
                            Err(Error::format(&ijrr, format!("line {n}: {e}")))
                        }
                        _ => Err(Error::format(
                            &ijrr,
                            format!("line {n}: expected 't_seconds path', got '{line}'"),
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
                    .map(|(n, l)| {
                        seconds_in_range(FRAME_TIME, l)
                            .ok_or_else(|| {
                                Error::format(&times, format!("line {n}: bad time '{l}'"))
                            })?
                            .map_err(|e| Error::format(&times, format!("line {n}: {e}")))
                    })
                    .collect::<Result<_>>()?
            } else {
                let fps = fps.ok_or_else(|| {
                    Error::invalid(
                        "frame times",
                        format!(
                            "{} has no images.txt or times.txt: give a frame rate (--fps for \
                             convert, [run] fps for the daemon)",
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
        let gray8 = img.color() == image::ColorType::L8;
        let aps_export = listed && gray8 && folder.join("events.txt").is_file();
        let (linear, color_note) = match color {
            ColorSpace::Linear => (true, "linear, as asked"),
            ColorSpace::Srgb => (false, "sRGB, as asked"),
            ColorSpace::Auto if aps_export => (
                true,
                "linear: recognised as a DAVIS APS export (8-bit gray images in an images.txt beside events.txt); --color srgb to override",
            ),
            ColorSpace::Auto if !img.color().has_color() => {
                tracing::warn!(
                    "{}: gray images of unknown colour space, read as sRGB (camera video); raw sensor exports such as DAVIS APS frames are linear: pass --color linear",
                    folder.display()
                );
                (false, "sRGB, a guess for gray images: --color linear for raw sensor exports")
            }
            ColorSpace::Auto => (false, "sRGB (colour images)"),
        };
        if aps_export && color == ColorSpace::Auto {
            tracing::info!("{}: {color_note}", folder.display());
        }
        Ok(ImageFolder {
            folder: folder.to_path_buf(),
            frames,
            next: 0,
            size,
            linear,
            color_note,
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
        Ok(Some(Frame::new(t, self.size, luma)))
    }

    fn describe(&self) -> String {
        format!(
            "{} images in {} ({})",
            self.frames.len(),
            self.folder.display(),
            self.color_note
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

/// Writes every frame of `source` into the folder `dir` as a frame list the readers here take
/// back (an IJRR `images.txt`: `t_seconds images/frame_NNNNNNNN.png` lines, each time exact to
/// the microsecond), the images 8-bit gray PNG, sRGB-encoded (as camera images are; read them
/// back with `--color srgb` or the default). Returns how many frames it wrote.
pub fn write_list(source: &mut dyn FrameSource, dir: &Path) -> Result<usize> {
    use std::io::Write;
    let images = dir.join("images");
    std::fs::create_dir_all(&images).map_err(|e| Error::io(&images, e))?;
    let list_path = dir.join("images.txt");
    let file = std::fs::File::create(&list_path).map_err(|e| Error::io(&list_path, e))?;
    let mut list = std::io::BufWriter::new(file);
    let (w, h) = source.size();
    let mut gray = Vec::new();
    let mut count = 0usize;
    while let Some(frame) = source.next_frame()? {
        let name = format!("images/frame_{count:08}.png");
        super::color::luma_to_gray(&frame.luma, 1.0, &mut gray);
        let img = image::GrayImage::from_raw(u32::from(w), u32::from(h), std::mem::take(&mut gray))
            .ok_or_else(|| Error::invalid("frame", "size differs from the source's"))?;
        let path = dir.join(&name);
        img.save(&path)
            .map_err(|e| Error::format(&path, e.to_string()))?;
        gray = img.into_raw();
        writeln!(
            list,
            "{} {name}",
            crate::format::ijrr::format_seconds_us(frame.t)
        )
        .map_err(|e| Error::io(&list_path, e))?;
        count += 1;
    }
    list.flush().map_err(|e| Error::io(&list_path, e))?;
    Ok(count)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame list whose time is out of range (past an `i64` of microseconds, infinite, or
    /// just past 2^61 us) is read as a frame list, and its error names the file, the line and
    /// the range times take, not "a text file, not a video".
    #[test]
    fn a_time_out_of_range_in_a_frame_list_names_its_line_and_the_range() {
        let dir = std::env::temp_dir().join(format!("v2ce-images-range-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        image::GrayImage::new(4, 3).save(dir.join("a.png")).unwrap();
        image::GrayImage::new(4, 3).save(dir.join("b.png")).unwrap();
        let bound = crate::time::MAX_ABS_US.to_string();
        let open = |name: &str, text: &str| {
            let list = dir.join(name);
            std::fs::write(&list, text).unwrap();
            let options = crate::frame::SourceOptions {
                fps: None,
                color: ColorSpace::Auto,
                topic: None,
            };
            match crate::frame::open(&list, &options) {
                Ok(_) => panic!("{text:?} opened"),
                Err(e) => e.to_string(),
            }
        };
        for (first, second) in [
            ("-9223372036854", "0"),
            ("1e300", "2e300"),
            ("0", "-inf"),
            ("0", "2305843009213.693953"),
            ("-2305843009213.693953", "0"),
        ] {
            // The bad line's number in the file (blank and comment lines count).
            let bad = if crate::format::ijrr::parse_seconds_us(first)
                .is_some_and(crate::time::in_range)
            {
                1
            } else {
                0
            };
            for (name, text, bad_line) in [
                (
                    "images.txt",
                    format!("# t path\n{first} a.png\n\n{second} b.png\n"),
                    [2, 4][bad],
                ),
                ("times.txt", format!("{first}\n{second}\n"), [1, 2][bad]),
            ] {
                let e = open(name, &text);
                assert!(
                    e.contains(name)
                        && e.contains(&format!("line {bad_line}: "))
                        && e.contains("frame time")
                        && e.contains("out of range")
                        && e.contains(&bound)
                        && !e.contains("not a video"),
                    "{text:?}: {e}"
                );
            }
        }
        // Not a number at all: the line's expected layout.
        let e = open("images.txt", "nan a.png\n1 b.png\n");
        assert!(
            e.contains("line 1: expected 't_seconds path'") && !e.contains("not a video"),
            "{e}"
        );
        let e = open("times.txt", "0\nnan\n");
        assert!(e.contains("line 2: bad time 'nan'"), "{e}");
        // The range's ends themselves are times.
        std::fs::write(
            dir.join("images.txt"),
            "-2305843009213.693952 a.png\n2305843009213.693952 b.png\n",
        )
        .unwrap();
        let options = crate::frame::SourceOptions {
            fps: None,
            color: ColorSpace::Auto,
            topic: None,
        };
        let mut source = crate::frame::open(&dir.join("images.txt"), &options).unwrap();
        let times: Vec<i64> = crate::frame::read_frames(source.as_mut(), 3)
            .unwrap()
            .iter()
            .map(|f| f.t)
            .collect();
        assert_eq!(times, [-crate::time::MAX_ABS_US, crate::time::MAX_ABS_US]);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
