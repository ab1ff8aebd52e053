//! Frames to the network's input: the toolbox's gray values, its resize, crop and panorama
//! tiling, and its normalisation (V2CE_SPEC.md section 1.2).
//!
//! A [`Frame`] holds linear luminance. The network was trained on, and the toolbox feeds it, the
//! 8-bit values of the file divided by 255, so the value is encoded back the way the source
//! decoded it: exactly the file's byte for sRGB-decoded 8-bit sources (every byte maps to a
//! distinct 16-bit level, so the inverse is a lookup), the sRGB transfer function in between
//! (colour video mixes channels), and `luma / 65535` for linear sources (DAVIS APS frames).
//! Colour video differs from the toolbox in one respect: the toolbox takes OpenCV's BT.601 luma
//! of gamma-encoded RGB, a frame here holds BT.709 luminance of linear RGB.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::frame::color::srgb_to_linear_lut;
use crate::frame::{Frame, FULL_SCALE};
use crate::stage1::SourceEncoding;

use super::roi::Rect;

/// The toolbox's normalisation: `(v - MEAN) / STD` on values in `[0, 1]`.
pub const MEAN: f32 = 0.153;
/// See [`MEAN`].
pub const STD: f32 = 0.165;

/// How frames are fitted to the network.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Geometry {
    /// At the frame's own size (the network is fully convolutional; each decoder resizes to its
    /// skip's exact size, so any size runs): events keep the source's geometry.
    #[default]
    Native,
    /// Resized (bilinear, half-pixel centres, no anti-aliasing, as OpenCV's `INTER_LINEAR`) to
    /// `height` rows keeping the aspect ratio (width `trunc(W * height / H)`), run whole.
    Resize,
    /// The toolbox's default: resized as above, then the centre `width` columns.
    Center,
    /// The toolbox's panorama mode: resized as above, cut into tiles `width` wide run one by
    /// one (the last tile is the rightmost `width` columns, of which the new ones are kept).
    Pano,
}

impl Geometry {
    /// The name as configs and flags spell it.
    pub fn name(self) -> &'static str {
        match self {
            Geometry::Native => "native",
            Geometry::Resize => "resize",
            Geometry::Center => "center",
            Geometry::Pano => "pano",
        }
    }
}

/// One network run over part of a frame (see [`Layout::tiles`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tile {
    /// First column of the tile in the resized plane.
    pub input_x: usize,
    /// Column of the events' frame where the tile's output starts.
    pub output_x: usize,
    /// First column of the tile's output that is kept.
    pub keep_from: usize,
}

/// The plane the network sees for one frame, and how its output maps back.
#[derive(Debug, Clone, PartialEq)]
pub struct Layout {
    geometry: Geometry,
    /// Frame size.
    source: (usize, usize),
    /// Size after resizing (the source's for `native`).
    resized: (usize, usize),
    /// First column kept (`center`).
    crop_x: usize,
    /// Width and height of the network's input (one tile for `pano`).
    net: (usize, usize),
    /// Output size (events are made at this size).
    output: (usize, usize),
}

impl Layout {
    /// The layout for `source = (width, height)` frames; `height` and `width` are the toolbox's
    /// `--height` (260) and crop / tile width (346), unused for `native`.
    pub fn new(geometry: Geometry, source: (u16, u16), height: u16, width: u16) -> Result<Self> {
        let (sw, sh) = (source.0 as usize, source.1 as usize);
        crate::limits::frame_size("frame size", sw as u32, sh as u32)?;
        if geometry == Geometry::Native {
            return Ok(Layout {
                geometry,
                source: (sw, sh),
                resized: (sw, sh),
                crop_x: 0,
                net: (sw, sh),
                output: (sw, sh),
            });
        }
        let th = height as usize;
        if th == 0 || width == 0 {
            return Err(Error::invalid(
                "stage1.learned",
                "height and width must be positive",
            ));
        }
        let rw = sw * th / sh;
        if rw == 0 || rw > u16::MAX as usize {
            return Err(Error::invalid(
                "stage1.learned",
                format!("{sw} x {sh} resized to height {th} is {rw} wide"),
            ));
        }
        let cw = width as usize;
        let (crop_x, net, output) = match geometry {
            Geometry::Resize => (0, (rw, th), (rw, th)),
            Geometry::Center | Geometry::Pano if rw < cw => {
                return Err(Error::invalid(
                    "stage1.learned",
                    format!(
                        "{sw} x {sh} resized to height {th} is {rw} wide, narrower than the \
                         {cw} columns of geometry {} (the toolbox slices wrongly here); use \
                         geometry = \"resize\" or \"native\"",
                        geometry.name()
                    ),
                ))
            }
            Geometry::Center => (rw / 2 - cw / 2, (cw, th), (cw, th)),
            _ => (0, (cw, th), (rw, th)),
        };
        Ok(Layout {
            geometry,
            source: (sw, sh),
            resized: (rw, th),
            crop_x,
            net,
            output,
        })
    }

    /// Width and height of the events.
    pub fn output(&self) -> (u16, u16) {
        (self.output.0 as u16, self.output.1 as u16)
    }

    /// Width of the resized plane, and the plane column of the output's first column.
    pub fn plane_columns(&self) -> (usize, usize) {
        (self.resized.0, self.crop_x)
    }

    /// Width and height of one network input plane.
    pub fn net(&self) -> (usize, usize) {
        self.net
    }

    /// The tiles the network runs on: the first column of each in the resized plane, where
    /// its output goes in the events' frame, and the first of its output columns kept (the
    /// columns before it are already covered by the tile before).
    pub fn tiles(&self) -> Vec<Tile> {
        match self.geometry {
            Geometry::Pano => {
                let (rw, cw) = (self.resized.0, self.net.0);
                let n = rw.div_ceil(cw);
                (0..n)
                    .map(|i| {
                        // The last tile is the rightmost cw columns; only the new ones are kept.
                        let start = (i * cw).min(rw - cw);
                        Tile {
                            input_x: start,
                            output_x: start,
                            keep_from: i * cw - start,
                        }
                    })
                    .collect()
            }
            _ => vec![Tile {
                input_x: self.crop_x,
                output_x: 0,
                keep_from: 0,
            }],
        }
    }

    /// The frame as the resized plane of values in `[0, 1]` (before cropping), row-major.
    pub fn plane(&self, frame: &Frame, encoding: SourceEncoding) -> Result<Vec<f32>> {
        let (sw, sh) = self.source;
        if (frame.width as usize, frame.height as usize) != (sw, sh) || frame.luma.len() != sw * sh
        {
            return Err(Error::invalid(
                "frame",
                format!(
                    "{} x {} for a model input laid out for {sw} x {sh}",
                    frame.width, frame.height
                ),
            ));
        }
        let values: Vec<f32> = match encoding {
            SourceEncoding::Linear => frame
                .luma
                .iter()
                .map(|&v| v as f32 / FULL_SCALE as f32)
                .collect(),
            SourceEncoding::Srgb => {
                let inverse = SrgbInverse::new();
                frame.luma.iter().map(|&v| inverse.value(v)).collect()
            }
        };
        if self.resized == self.source {
            return Ok(values);
        }
        Ok(resize_linear(&values, self.source, self.resized))
    }

    /// Normalised values of the tile starting at column `x0` of a resized plane, row-major.
    pub fn tile(&self, plane: &[f32], x0: usize, out: &mut Vec<f32>) {
        self.crop(plane, x0, &Rect::full(self.net), out);
    }

    /// Normalised values of the part `rect` (in the network input's pixels, within
    /// [`Layout::net`]) of the tile starting at column `x0` of a resized plane, row-major.
    pub fn crop(&self, plane: &[f32], x0: usize, rect: &Rect, out: &mut Vec<f32>) {
        let (rw, _) = self.resized;
        out.clear();
        for y in rect.y0..rect.y1 {
            let at = y * rw + x0;
            let row = &plane[at + rect.x0..at + rect.x1];
            out.extend(row.iter().map(|&v| (v - MEAN) / STD));
        }
    }
}

/// The 8-bit value behind a 16-bit linear level decoded from sRGB.
struct SrgbInverse {
    levels: [u16; 256],
}

impl SrgbInverse {
    fn new() -> Self {
        let lut = srgb_to_linear_lut();
        let mut levels = [0u16; 256];
        for (l, v) in levels.iter_mut().zip(lut.iter()) {
            *l = v.round() as u16;
        }
        SrgbInverse { levels }
    }

    /// `byte / 255` when `level` is exactly an 8-bit value's level, else the sRGB encoding of
    /// `level / 65535`.
    fn value(&self, level: u16) -> f32 {
        if let Ok(byte) = self.levels.binary_search(&level) {
            return byte as f32 / 255.0;
        }
        let c = level as f64 / FULL_SCALE as f64;
        let v = if c <= 0.0031308 {
            c * 12.92
        } else {
            1.055 * c.powf(1.0 / 2.4) - 0.055
        };
        v as f32
    }
}

/// Per output index along one axis: the first source index and the weight of the second.
fn linear_taps(src: usize, dst: usize) -> Vec<(usize, usize, f32)> {
    // OpenCV's arithmetic: the scale in f64 as the inverse of dst / src, the coordinate rounded
    // to f32, its floor and fraction in f32.
    let scale = 1.0 / (dst as f64 / src as f64);
    (0..dst)
        .map(|d| {
            let f = ((d as f64 + 0.5) * scale - 0.5) as f32;
            let mut s = f.floor();
            let mut w = f - s;
            if s < 0.0 {
                s = 0.0;
                w = 0.0;
            }
            let mut s = s as usize;
            if s >= src - 1 {
                s = src - 1;
                w = 0.0;
            }
            (s, (s + 1).min(src - 1), w)
        })
        .collect()
}

/// Bilinear resampling with half-pixel centres and no anti-aliasing, the arithmetic of OpenCV's
/// `INTER_LINEAR` on float images (source coordinate `(d + 0.5) * scale - 0.5`, clamped at the
/// borders).
pub fn resize_linear(src: &[f32], from: (usize, usize), to: (usize, usize)) -> Vec<f32> {
    let (sw, _sh) = from;
    let (dw, dh) = to;
    let xs = linear_taps(from.0, dw);
    let ys = linear_taps(from.1, dh);
    let mut out = Vec::with_capacity(dw * dh);
    let mut row0 = vec![0f32; dw];
    let mut row1 = vec![0f32; dw];
    for &(y0, y1, wy) in &ys {
        for (r, y) in [(&mut row0, y0), (&mut row1, y1)] {
            let line = &src[y * sw..(y + 1) * sw];
            for (o, &(x0, x1, wx)) in r.iter_mut().zip(&xs) {
                *o = line[x0] * (1.0 - wx) + line[x1] * wx;
            }
        }
        out.extend(
            row0.iter()
                .zip(&row1)
                .map(|(&a, &b)| a * (1.0 - wy) + b * wy),
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::color::gray_to_luma;

    #[test]
    fn srgb_bytes_come_back_exactly() {
        let inverse = SrgbInverse::new();
        for b in 0..=255u8 {
            assert_eq!(inverse.value(gray_to_luma(b)), b as f32 / 255.0, "byte {b}");
        }
        // Between two bytes' levels: the transfer function, strictly between them.
        let (a, b) = (gray_to_luma(100), gray_to_luma(101));
        let v = inverse.value((a + b) / 2);
        assert!(v > 100.0 / 255.0 && v < 101.0 / 255.0, "{v}");
    }

    #[test]
    fn toolbox_sizes() {
        // 640x480 -> 346x260 (spec 1.2); 1920x1080 -> 462x260, centre crop from 58.
        let l = Layout::new(Geometry::Center, (640, 480), 260, 346).unwrap();
        assert_eq!((l.resized, l.net, l.crop_x), ((346, 260), (346, 260), 0));
        let l = Layout::new(Geometry::Center, (1920, 1080), 260, 346).unwrap();
        assert_eq!(
            (l.resized, l.crop_x, l.output()),
            ((462, 260), 58, (346, 260))
        );
        // Pano: 462 wide -> tiles at 0 and 116, the second keeping its last 116 columns.
        let l = Layout::new(Geometry::Pano, (1920, 1080), 260, 346).unwrap();
        let t = |input_x, output_x, keep_from| Tile {
            input_x,
            output_x,
            keep_from,
        };
        assert_eq!(l.tiles(), vec![t(0, 0, 0), t(116, 116, 230)]);
        assert_eq!(l.output(), (462, 260));
        // A width that divides: no overlap. The centre crop writes from column 0.
        let l = Layout::new(Geometry::Pano, (692, 260), 260, 346).unwrap();
        assert_eq!(l.tiles(), vec![t(0, 0, 0), t(346, 346, 0)]);
        let l = Layout::new(Geometry::Center, (1920, 1080), 260, 346).unwrap();
        assert_eq!(l.tiles(), vec![t(58, 0, 0)]);
        // Narrower than the crop: an error, not the toolbox's wrong slice.
        assert!(Layout::new(Geometry::Center, (320, 320), 260, 346).is_err());
        let l = Layout::new(Geometry::Native, (83, 61), 260, 346).unwrap();
        assert_eq!((l.net(), l.output()), ((83, 61), (83, 61)));
    }

    #[test]
    fn resize_matches_half_pixel_bilinear() {
        // Identity at the same size.
        let src: Vec<f32> = (0..12).map(|v| v as f32).collect();
        assert_eq!(resize_linear(&src, (4, 3), (4, 3)), src);
        // Halving averages pairs: x = (d + 0.5) * 2 - 0.5 = 2d + 0.5.
        let src = vec![0.0, 1.0, 2.0, 3.0];
        assert_eq!(resize_linear(&src, (4, 1), (2, 1)), vec![0.5, 2.5]);
        // Doubling: d = 0 -> -0.25 clamps to 0; d = 3 -> 1.25 clamps to the last column.
        let src = vec![0.0, 4.0];
        assert_eq!(
            resize_linear(&src, (2, 1), (4, 1)),
            vec![0.0, 1.0, 3.0, 4.0]
        );
    }
}
