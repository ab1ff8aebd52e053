//! YUV4MPEG2 (`.y4m`) files as a frame source, through the `y4m` crate.
//!
//! Frame `i` is at `round(i * 1e6 * den / num)` us from the header's frame rate (the format
//! carries no per-frame timestamps). 8-bit 4:2:0, 4:2:2, 4:4:4 and mono are accepted; a
//! `.y4m.zst` file is decompressed on the fly.

use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use super::color::{gray_ycbcr_to_luma_lut, rgb_to_luma, ycbcr_to_rgb};
use super::{Frame, FrameSource};
use crate::error::{Error, Result};

/// Reads a `.y4m` file.
pub struct Y4mSource {
    path: PathBuf,
    decoder: y4m::Decoder<Box<dyn Read + Send>>,
    size: (u16, u16),
    rate: (usize, usize),
    full_range: bool,
    index: i64,
    // Bytes the decoder has taken, and how many it had at the end of the last whole frame:
    // the decoder reports a frame cut short as a plain end of file.
    consumed: Arc<AtomicU64>,
    frame_end: u64,
    /// Monochrome streams: luminance per `Y'` code, made at the first frame.
    mono: Option<[u16; 256]>,
}

/// Counts the bytes read through it.
struct Counting {
    inner: Box<dyn Read + Send>,
    count: Arc<AtomicU64>,
}

impl Read for Counting {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.count.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }
}

impl Y4mSource {
    /// Opens `path` (`.y4m`, or `.y4m.zst` compressed with Zstandard) and reads its header.
    pub fn open(path: &Path) -> Result<Self> {
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let zst = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("zst"));
        let reader: Box<dyn Read + Send> = if zst {
            Box::new(zstd::stream::read::Decoder::new(file).map_err(|e| Error::io(path, e))?)
        } else {
            Box::new(BufReader::new(file))
        };
        Self::from_reader(reader, path)
    }

    /// Reads a Y4M stream from `reader`; `path` names it in messages.
    pub fn from_reader(reader: Box<dyn Read + Send>, path: &Path) -> Result<Self> {
        let consumed = Arc::new(AtomicU64::new(0));
        let reader: Box<dyn Read + Send> = Box::new(Counting {
            inner: reader,
            count: consumed.clone(),
        });
        let decoder = y4m::Decoder::new(reader).map_err(|e| {
            Error::format(path, format!("not a readable Y4M file: {}", describe(&e)))
        })?;
        let (w, h) = (decoder.get_width(), decoder.get_height());
        let size = match (u16::try_from(w), u16::try_from(h)) {
            (Ok(w), Ok(h)) if w > 0 && h > 0 => (w, h),
            _ => {
                return Err(Error::format(
                    path,
                    format!("frame size {w} x {h} unsupported"),
                ))
            }
        };
        if decoder.get_bit_depth() != 8 {
            return Err(Error::format(path, "only 8-bit Y4M is supported"));
        }
        let r = decoder.get_framerate();
        if r.num == 0 || r.den == 0 {
            return Err(Error::format(path, "frame rate 0 in the header"));
        }
        if r.num as f64 / r.den as f64 > 1e6 {
            return Err(Error::format(
                path,
                format!(
                    "frame rate {}/{} in the header is above 1,000,000 fps: frames would share \
                     a microsecond",
                    r.num, r.den
                ),
            ));
        }
        let full_range =
            String::from_utf8_lossy(decoder.get_raw_params()).contains("COLORRANGE=FULL");
        Ok(Y4mSource {
            path: path.to_path_buf(),
            decoder,
            size,
            rate: (r.num, r.den),
            full_range,
            index: 0,
            frame_end: consumed.load(Ordering::Relaxed),
            mono: None,
            consumed,
        })
    }
}

impl FrameSource for Y4mSource {
    fn size(&self) -> (u16, u16) {
        self.size
    }

    fn next_frame(&mut self) -> Result<Option<Frame>> {
        let (w, h) = (self.size.0 as usize, self.size.1 as usize);
        let full = self.full_range;
        let colorspace = self.decoder.get_colorspace();
        let frame = match self.decoder.read_frame() {
            Ok(f) => f,
            Err(y4m::Error::EOF) if self.consumed.load(Ordering::Relaxed) == self.frame_end => {
                return Ok(None)
            }
            Err(y4m::Error::EOF) => {
                return Err(Error::format(
                    &self.path,
                    format!(
                        "frame {} is cut short (the file ends inside it)",
                        self.index
                    ),
                ))
            }
            Err(e) => {
                return Err(Error::format(
                    &self.path,
                    format!("frame {}: {}", self.index, describe(&e)),
                ))
            }
        };
        self.frame_end = self.consumed.load(Ordering::Relaxed);
        let (yp, up, vp) = (
            frame.get_y_plane(),
            frame.get_u_plane(),
            frame.get_v_plane(),
        );
        let (sx, sy) = match colorspace {
            y4m::Colorspace::C420
            | y4m::Colorspace::C420jpeg
            | y4m::Colorspace::C420paldv
            | y4m::Colorspace::C420mpeg2 => (2, 2),
            y4m::Colorspace::C422 => (2, 1),
            y4m::Colorspace::C444 => (1, 1),
            y4m::Colorspace::Cmono => (0, 0),
            other => {
                return Err(Error::format(
                    &self.path,
                    format!("colour space {other:?} is not supported"),
                ))
            }
        };
        let cw = if sx == 0 { 0 } else { w.div_ceil(sx) };
        let mut luma = Vec::with_capacity(w * h);
        if sx == 0 {
            // Monochrome: the luminance is a function of Y' alone.
            let lut = self
                .mono
                .get_or_insert_with(|| gray_ycbcr_to_luma_lut(full));
            luma.extend(yp.iter().take(w * h).map(|&v| lut[v as usize]));
            luma.resize(w * h, lut[0]);
        }
        for y in (0..h).filter(|_| sx != 0) {
            for x in 0..w {
                let yy = yp.get(y * w + x).copied().unwrap_or(0);
                let (cb, cr) = match (x.checked_div(sx), y.checked_div(sy)) {
                    (Some(cx), Some(cy)) => {
                        let i = cy * cw + cx;
                        (
                            up.get(i).copied().unwrap_or(128),
                            vp.get(i).copied().unwrap_or(128),
                        )
                    }
                    _ => (128, 128),
                };
                let (r, g, b) = ycbcr_to_rgb(yy, cb, cr, full);
                luma.push(rgb_to_luma(r, g, b));
            }
        }
        let t = (self.index as i128 * 1_000_000 * self.rate.1 as i128 + self.rate.0 as i128 / 2)
            / self.rate.0 as i128;
        self.index += 1;
        Ok(Some(Frame::new(t as i64, self.size, luma)))
    }

    fn describe(&self) -> String {
        format!(
            "Y4M {} ({}/{} fps)",
            self.path.display(),
            self.rate.0,
            self.rate.1
        )
    }
}

/// The Y4M crate's error in words (its own text for an unknown colour space says "bad input").
fn describe(e: &y4m::Error) -> String {
    match e {
        y4m::Error::UnknownColorspace => "unknown or unsupported colour space (C tag)".into(),
        y4m::Error::ParseError(p) => format!("bad header: {}", p.to_string().to_lowercase()),
        y4m::Error::OutOfMemory => "a frame larger than the reader allows".into(),
        other => other.to_string(),
    }
}
