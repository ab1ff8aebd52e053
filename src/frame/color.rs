//! Conversion of encoded pixel values to linear luminance (see [`super`] for the conventions).

use std::sync::OnceLock;

use crate::rounding::round_to_u16;

/// The sRGB transfer function decoded for every 8-bit value, scaled to 0..=65535.
pub fn srgb_to_linear_lut() -> &'static [f32; 256] {
    static LUT: OnceLock<[f32; 256]> = OnceLock::new();
    LUT.get_or_init(|| {
        let mut lut = [0f32; 256];
        for (v, out) in lut.iter_mut().enumerate() {
            let c = v as f64 / 255.0;
            let lin = if c <= 0.04045 {
                c / 12.92
            } else {
                ((c + 0.055) / 1.055).powf(2.4)
            };
            *out = (lin * 65535.0) as f32;
        }
        lut
    })
}

/// Linear luminance of one gamma-encoded `R'G'B'` pixel (BT.709 weights on linear channels).
pub fn rgb_to_luma(r: u8, g: u8, b: u8) -> u16 {
    let lut = srgb_to_linear_lut();
    let y = 0.2126 * lut[r as usize] + 0.7152 * lut[g as usize] + 0.0722 * lut[b as usize];
    round_to_u16(y)
}

/// Linear luminance of every gamma-encoded gray value: a table, so converting a frame costs a
/// lookup per pixel (no rounding call).
pub fn gray_to_luma_lut() -> &'static [u16; 256] {
    static LUT: OnceLock<[u16; 256]> = OnceLock::new();
    LUT.get_or_init(|| {
        let f = srgb_to_linear_lut();
        std::array::from_fn(|v| f[v].round() as u16)
    })
}

/// Linear luminance of a gamma-encoded gray value.
pub fn gray_to_luma(v: u8) -> u16 {
    gray_to_luma_lut()[v as usize]
}

/// Linear luminance of every luma code `Y'` of a gray `Y'CbCr` pixel (chroma 128): what
/// [`ycbcr_to_rgb`] then [`rgb_to_luma`] give, as a table for monochrome video.
pub fn gray_ycbcr_to_luma_lut(full_range: bool) -> [u16; 256] {
    std::array::from_fn(|y| {
        let (r, g, b) = ycbcr_to_rgb(y as u8, 128, 128, full_range);
        rgb_to_luma(r, g, b)
    })
}

/// Converts interleaved `R'G'B'` bytes to linear luminance.
pub fn rgb24_to_luma(rgb: &[u8], out: &mut Vec<u16>) {
    out.clear();
    out.extend(rgb.chunks_exact(3).map(|p| rgb_to_luma(p[0], p[1], p[2])));
}

/// `Y'CbCr` (8-bit, BT.601 matrix) to gamma-encoded `R'G'B'`; `full_range` for 0..255 luma.
pub fn ycbcr_to_rgb(y: u8, cb: u8, cr: u8, full_range: bool) -> (u8, u8, u8) {
    let (y, cb, cr) = (y as f32, cb as f32 - 128.0, cr as f32 - 128.0);
    let (y, scale_c) = if full_range {
        (y, 1.0)
    } else {
        ((y - 16.0) * 255.0 / 219.0, 255.0 / 224.0)
    };
    let (cb, cr) = (cb * scale_c, cr * scale_c);
    let r = y + 1.402 * cr;
    let g = y - 0.344_136 * cb - 0.714_136 * cr;
    let b = y + 1.772 * cb;
    let q = |v: f32| round_to_u16(v).min(255) as u8;
    (q(r), q(g), q(b))
}

/// 8-bit gamma-encoded (sRGB) gray of linear luminance (times `scale`, saturating) into `out`:
/// the optical flow's input.
pub fn luma_to_gray(luma: &[u16], scale: f32, out: &mut Vec<u8>) {
    let table = encode_table();
    out.clear();
    if scale == 1.0 {
        out.extend(luma.iter().map(|&v| table[v as usize]));
    } else {
        out.extend(
            luma.iter()
                .map(|&v| table[(v as f32 * scale + 0.5).min(65535.0) as usize]),
        );
    }
}

/// The sRGB transfer function for every 16-bit linear value, to 8 bits.
fn encode_table() -> &'static [u8] {
    static TABLE: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        (0..=u16::MAX)
            .map(|v| {
                let c = v as f64 / 65535.0;
                let e = if c <= 0.0031308 {
                    12.92 * c
                } else {
                    1.055 * c.powf(1.0 / 2.4) - 0.055
                };
                (e * 255.0).round().clamp(0.0, 255.0) as u8
            })
            .collect()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transfer_function_and_weights() {
        assert_eq!(gray_to_luma(0), 0);
        assert_eq!(gray_to_luma(255), 65535);
        // Mid-gray 128 is about 21.6% of full linear light, not 50%.
        let mid = gray_to_luma(128) as f64 / 65535.0;
        assert!((mid - 0.2158).abs() < 0.001, "{mid}");
        // Pure green is far brighter than pure blue at the same code value.
        assert!(rgb_to_luma(0, 255, 0) > 9 * rgb_to_luma(0, 0, 255));
        assert_eq!(rgb_to_luma(255, 255, 255), 65535);
        assert_eq!(ycbcr_to_rgb(16, 128, 128, false), (0, 0, 0));
        assert_eq!(ycbcr_to_rgb(235, 128, 128, false), (255, 255, 255));
        assert_eq!(ycbcr_to_rgb(200, 128, 128, true), (200, 200, 200));
    }
}
