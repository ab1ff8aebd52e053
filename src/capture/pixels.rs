//! Decoding of camera buffers to linear-luminance [`Frame`]s (pure).
//!
//! Every format is reduced to its gamma-encoded luma `Y'` (GREY: the value; YUYV: the Y byte of
//! each pixel; MJPEG: the decoded image's luma), which then goes through the sRGB transfer
//! function with [`color::gray_to_luma`], as gray images do elsewhere in the crate.

use std::borrow::Cow;
use std::io::Cursor;

use image::codecs::jpeg::JpegDecoder;
use image::DynamicImage;

use super::PixelFormat;
use crate::error::{Error, Result};
use crate::frame::{color, Frame};

/// How the driver lays out one buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Layout {
    /// Pixel format.
    pub format: PixelFormat,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Bytes per line (V4L2 `bytesperline`) for GREY and YUYV; 0 means tightly packed. Unused
    /// for MJPEG.
    pub stride: u32,
}

/// Decodes one buffer laid out as `layout` to a frame at time `t` (us). `origin` names the
/// camera in error messages. Short, corrupt or mis-sized buffers give an error, never a panic.
pub fn decode(layout: &Layout, data: &[u8], t: i64, origin: &str) -> Result<Frame> {
    let (width, height) = frame_size(layout, origin)?;
    let luma = match layout.format {
        PixelFormat::Grey => packed_luma(layout, data, 1, origin)?,
        PixelFormat::Yuyv => packed_luma(layout, data, 2, origin)?,
        PixelFormat::Mjpeg => mjpeg_luma(layout, data, origin)?,
    };
    Ok(Frame::new(t, (width, height), luma))
}

fn frame_size(layout: &Layout, origin: &str) -> Result<(u16, u16)> {
    match (u16::try_from(layout.width), u16::try_from(layout.height)) {
        (Ok(w), Ok(h)) if w > 0 && h > 0 => Ok((w, h)),
        _ => Err(Error::format(
            origin,
            format!(
                "frame size {}x{} is not usable (1 to 65535 pixels a side)",
                layout.width, layout.height
            ),
        )),
    }
}

/// The first byte of every pixel, `bytes_per_pixel` apart, on lines `stride` apart.
fn packed_luma(
    layout: &Layout,
    data: &[u8],
    bytes_per_pixel: usize,
    origin: &str,
) -> Result<Vec<u16>> {
    let (w, h) = (layout.width as usize, layout.height as usize);
    let line = w * bytes_per_pixel;
    let stride = if layout.stride == 0 {
        line
    } else {
        layout.stride as usize
    };
    let name = super::fourcc_str(layout.format.fourcc());
    if stride < line {
        return Err(Error::format(
            origin,
            format!("{name} line stride {stride} is shorter than a {w}-pixel line ({line} bytes)"),
        ));
    }
    let needed = (h - 1) * stride + line;
    if data.len() < needed {
        return Err(Error::format(
            origin,
            format!(
                "{name} buffer of {} bytes is too short for {w}x{h} with stride {stride} \
                 ({needed} bytes)",
                data.len()
            ),
        ));
    }
    let mut luma = Vec::with_capacity(w * h);
    for row in data.chunks(stride).take(h) {
        luma.extend(
            row[..line]
                .iter()
                .step_by(bytes_per_pixel)
                .map(|&v| color::gray_to_luma(v)),
        );
    }
    Ok(luma)
}

fn mjpeg_luma(layout: &Layout, data: &[u8], origin: &str) -> Result<Vec<u16>> {
    let jpeg = with_huffman_tables(data).map_err(|m| Error::format(origin, m))?;
    let decoded = JpegDecoder::new(Cursor::new(&jpeg[..]))
        .and_then(DynamicImage::from_decoder)
        .map_err(|e| Error::format(origin, format!("MJPEG frame does not decode: {e}")))?;
    if (decoded.width(), decoded.height()) != (layout.width, layout.height) {
        return Err(Error::format(
            origin,
            format!(
                "MJPEG frame is {}x{}, the stream was set up for {}x{}",
                decoded.width(),
                decoded.height(),
                layout.width,
                layout.height
            ),
        ));
    }
    Ok(decoded
        .to_luma8()
        .as_raw()
        .iter()
        .map(|&v| color::gray_to_luma(v))
        .collect())
}

/// The standard Huffman tables of the JPEG specification (ITU-T T.81 Annex K.3), as one DHT
/// segment: luminance DC (table 0), chrominance DC (1), luminance AC (0), chrominance AC (1).
fn default_dht_segment() -> Vec<u8> {
    const DC_LUMA_BITS: [u8; 16] = [0, 1, 5, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0];
    const DC_CHROMA_BITS: [u8; 16] = [0, 3, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0];
    const DC_VALUES: [u8; 12] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11];
    const AC_LUMA_BITS: [u8; 16] = [0, 2, 1, 3, 3, 2, 4, 3, 5, 5, 4, 4, 0, 0, 1, 0x7d];
    const AC_LUMA_VALUES: [u8; 162] = [
        0x01, 0x02, 0x03, 0x00, 0x04, 0x11, 0x05, 0x12, 0x21, 0x31, 0x41, 0x06, 0x13, 0x51, 0x61,
        0x07, 0x22, 0x71, 0x14, 0x32, 0x81, 0x91, 0xa1, 0x08, 0x23, 0x42, 0xb1, 0xc1, 0x15, 0x52,
        0xd1, 0xf0, 0x24, 0x33, 0x62, 0x72, 0x82, 0x09, 0x0a, 0x16, 0x17, 0x18, 0x19, 0x1a, 0x25,
        0x26, 0x27, 0x28, 0x29, 0x2a, 0x34, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3a, 0x43, 0x44, 0x45,
        0x46, 0x47, 0x48, 0x49, 0x4a, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5a, 0x63, 0x64,
        0x65, 0x66, 0x67, 0x68, 0x69, 0x6a, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7a, 0x83,
        0x84, 0x85, 0x86, 0x87, 0x88, 0x89, 0x8a, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99,
        0x9a, 0xa2, 0xa3, 0xa4, 0xa5, 0xa6, 0xa7, 0xa8, 0xa9, 0xaa, 0xb2, 0xb3, 0xb4, 0xb5, 0xb6,
        0xb7, 0xb8, 0xb9, 0xba, 0xc2, 0xc3, 0xc4, 0xc5, 0xc6, 0xc7, 0xc8, 0xc9, 0xca, 0xd2, 0xd3,
        0xd4, 0xd5, 0xd6, 0xd7, 0xd8, 0xd9, 0xda, 0xe1, 0xe2, 0xe3, 0xe4, 0xe5, 0xe6, 0xe7, 0xe8,
        0xe9, 0xea, 0xf1, 0xf2, 0xf3, 0xf4, 0xf5, 0xf6, 0xf7, 0xf8, 0xf9, 0xfa,
    ];
    const AC_CHROMA_BITS: [u8; 16] = [0, 2, 1, 2, 4, 4, 3, 4, 7, 5, 4, 4, 0, 1, 2, 0x77];
    const AC_CHROMA_VALUES: [u8; 162] = [
        0x00, 0x01, 0x02, 0x03, 0x11, 0x04, 0x05, 0x21, 0x31, 0x06, 0x12, 0x41, 0x51, 0x07, 0x61,
        0x71, 0x13, 0x22, 0x32, 0x81, 0x08, 0x14, 0x42, 0x91, 0xa1, 0xb1, 0xc1, 0x09, 0x23, 0x33,
        0x52, 0xf0, 0x15, 0x62, 0x72, 0xd1, 0x0a, 0x16, 0x24, 0x34, 0xe1, 0x25, 0xf1, 0x17, 0x18,
        0x19, 0x1a, 0x26, 0x27, 0x28, 0x29, 0x2a, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3a, 0x43, 0x44,
        0x45, 0x46, 0x47, 0x48, 0x49, 0x4a, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5a, 0x63,
        0x64, 0x65, 0x66, 0x67, 0x68, 0x69, 0x6a, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7a,
        0x82, 0x83, 0x84, 0x85, 0x86, 0x87, 0x88, 0x89, 0x8a, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97,
        0x98, 0x99, 0x9a, 0xa2, 0xa3, 0xa4, 0xa5, 0xa6, 0xa7, 0xa8, 0xa9, 0xaa, 0xb2, 0xb3, 0xb4,
        0xb5, 0xb6, 0xb7, 0xb8, 0xb9, 0xba, 0xc2, 0xc3, 0xc4, 0xc5, 0xc6, 0xc7, 0xc8, 0xc9, 0xca,
        0xd2, 0xd3, 0xd4, 0xd5, 0xd6, 0xd7, 0xd8, 0xd9, 0xda, 0xe2, 0xe3, 0xe4, 0xe5, 0xe6, 0xe7,
        0xe8, 0xe9, 0xea, 0xf2, 0xf3, 0xf4, 0xf5, 0xf6, 0xf7, 0xf8, 0xf9, 0xfa,
    ];
    let tables: [(u8, &[u8; 16], &[u8]); 4] = [
        (0x00, &DC_LUMA_BITS, &DC_VALUES),
        (0x01, &DC_CHROMA_BITS, &DC_VALUES),
        (0x10, &AC_LUMA_BITS, &AC_LUMA_VALUES),
        (0x11, &AC_CHROMA_BITS, &AC_CHROMA_VALUES),
    ];
    let body: usize = tables.iter().map(|(_, _, v)| 17 + v.len()).sum();
    let length = (2 + body) as u16;
    let mut seg = vec![0xFF, 0xC4];
    seg.extend_from_slice(&length.to_be_bytes());
    for (class_id, bits, values) in tables {
        seg.push(class_id);
        seg.extend_from_slice(bits);
        seg.extend_from_slice(values);
    }
    seg
}

/// `data` itself when it carries Huffman tables (a DHT segment before the first scan), else a
/// copy with the standard tables inserted before the scan: many webcams send MJPEG frames
/// without DHT, relying on the decoder to know the defaults. Errors when `data` is not a JPEG.
pub(crate) fn with_huffman_tables(data: &[u8]) -> std::result::Result<Cow<'_, [u8]>, String> {
    if data.len() < 4 || data[0] != 0xFF || data[1] != 0xD8 {
        return Err(format!(
            "MJPEG frame of {} bytes does not start with a JPEG start-of-image marker",
            data.len()
        ));
    }
    let mut pos = 2;
    loop {
        // Markers may be preceded by fill bytes 0xFF.
        while data.get(pos) == Some(&0xFF) && data.get(pos + 1) == Some(&0xFF) {
            pos += 1;
        }
        let (Some(&0xFF), Some(&marker)) = (data.get(pos), data.get(pos + 1)) else {
            // Truncated or malformed headers: let the decoder report it.
            return Ok(Cow::Borrowed(data));
        };
        match marker {
            0xC4 => return Ok(Cow::Borrowed(data)),
            0xDA => {
                let mut fixed = Vec::with_capacity(data.len() + 432);
                fixed.extend_from_slice(&data[..pos]);
                fixed.extend_from_slice(&default_dht_segment());
                fixed.extend_from_slice(&data[pos..]);
                return Ok(Cow::Owned(fixed));
            }
            // Standalone markers: no length.
            0x01 | 0xD0..=0xD7 => pos += 2,
            0xD9 => return Ok(Cow::Borrowed(data)),
            _ => {
                let (Some(&hi), Some(&lo)) = (data.get(pos + 2), data.get(pos + 3)) else {
                    return Ok(Cow::Borrowed(data));
                };
                pos += 2 + u16::from_be_bytes([hi, lo]) as usize;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::codecs::jpeg::JpegEncoder;
    use image::{ExtendedColorType, ImageEncoder};

    const ORIGIN: &str = "/dev/video9";

    fn layout(format: PixelFormat, width: u32, height: u32, stride: u32) -> Layout {
        Layout {
            format,
            width,
            height,
            stride,
        }
    }

    #[test]
    fn grey_tight_and_strided() {
        let data = [0u8, 128, 255, 10, 20, 30];
        let f = decode(&layout(PixelFormat::Grey, 3, 2, 0), &data, 42, ORIGIN).unwrap();
        assert_eq!((f.t, f.width, f.height), (42, 3, 2));
        let expect: Vec<u16> = data.iter().map(|&v| color::gray_to_luma(v)).collect();
        assert_eq!(f.luma, expect);
        assert_eq!(f.luma[2], 65535);
        // Stride 5: two padding bytes per line; the last line need not be padded.
        let padded = [0u8, 128, 255, 99, 99, 10, 20, 30];
        let g = decode(&layout(PixelFormat::Grey, 3, 2, 5), &padded, 0, ORIGIN).unwrap();
        assert_eq!(g.luma, expect);
    }

    #[test]
    fn yuyv_takes_y() {
        // 2x2: Y0 U Y1 V per pixel pair, stride 6 (2 padding bytes).
        let data = [10u8, 1, 20, 2, 77, 77, 30, 3, 40, 4];
        let f = decode(&layout(PixelFormat::Yuyv, 2, 2, 6), &data, 0, ORIGIN).unwrap();
        let expect: Vec<u16> = [10u8, 20, 30, 40]
            .iter()
            .map(|&v| color::gray_to_luma(v))
            .collect();
        assert_eq!(f.luma, expect);
        let tight = [10u8, 1, 20, 2, 30, 3, 40, 4];
        let g = decode(&layout(PixelFormat::Yuyv, 2, 2, 0), &tight, 0, ORIGIN).unwrap();
        assert_eq!(g.luma, expect);
    }

    #[test]
    fn short_and_bad_buffers_are_errors() {
        let l = layout(PixelFormat::Yuyv, 4, 4, 0);
        let err = decode(&l, &[0u8; 31], 0, ORIGIN).unwrap_err().to_string();
        assert!(
            err.contains("/dev/video9") && err.contains("too short"),
            "{err}"
        );
        assert!(decode(&layout(PixelFormat::Grey, 4, 4, 2), &[0u8; 64], 0, ORIGIN).is_err());
        assert!(decode(&layout(PixelFormat::Grey, 0, 4, 0), &[], 0, ORIGIN).is_err());
        assert!(decode(&layout(PixelFormat::Grey, 70000, 1, 0), &[], 0, ORIGIN).is_err());
        let m = layout(PixelFormat::Mjpeg, 8, 8, 0);
        assert!(decode(&m, &[], 0, ORIGIN).is_err());
        assert!(decode(&m, &[1, 2, 3, 4, 5], 0, ORIGIN).is_err());
    }

    fn gradient(w: u32, h: u32) -> Vec<u8> {
        (0..w * h)
            .map(|i| ((i % w) * 255 / (w - 1)) as u8)
            .collect()
    }

    fn encode(pixels: &[u8], w: u32, h: u32, color: ExtendedColorType) -> Vec<u8> {
        let mut out = Vec::new();
        JpegEncoder::new_with_quality(&mut out, 95)
            .write_image(pixels, w, h, color)
            .unwrap();
        out
    }

    /// Removes every DHT segment (the encoder writes them before the scan).
    fn strip_dht(jpeg: &[u8]) -> Vec<u8> {
        let mut out = jpeg[..2].to_vec();
        let mut pos = 2;
        while jpeg[pos + 1] != 0xDA {
            let len = u16::from_be_bytes([jpeg[pos + 2], jpeg[pos + 3]]) as usize;
            if jpeg[pos + 1] != 0xC4 {
                out.extend_from_slice(&jpeg[pos..pos + 2 + len]);
            }
            pos += 2 + len;
        }
        out.extend_from_slice(&jpeg[pos..]);
        out
    }

    #[test]
    fn mjpeg_gray_decodes_close_to_source() {
        let (w, h) = (32, 16);
        let src = gradient(w, h);
        let jpeg = encode(&src, w, h, ExtendedColorType::L8);
        let f = decode(&layout(PixelFormat::Mjpeg, w, h, 0), &jpeg, 7, ORIGIN).unwrap();
        assert_eq!((f.width, f.height, f.t), (32, 16, 7));
        for (got, &want) in f.luma.iter().zip(&src) {
            let want = color::gray_to_luma(want) as i32;
            assert!((*got as i32 - want).abs() < 2500, "{got} vs {want}");
        }
        // A size other than negotiated is an error, not a silently different frame.
        assert!(decode(&layout(PixelFormat::Mjpeg, 16, 16, 0), &jpeg, 0, ORIGIN).is_err());
        // Truncated JPEG: error, no panic.
        let cut = &jpeg[..jpeg.len() / 3];
        assert!(decode(&layout(PixelFormat::Mjpeg, w, h, 0), cut, 0, ORIGIN).is_err());
    }

    #[test]
    fn mjpeg_without_huffman_tables() {
        let (w, h) = (24, 16);
        let l = layout(PixelFormat::Mjpeg, w, h, 0);
        // Gray (luminance tables) and colour (chrominance tables too).
        let gray = gradient(w, h);
        let rgb: Vec<u8> = gray.iter().flat_map(|&v| [v, 255 - v, v / 2]).collect();
        for jpeg in [
            encode(&gray, w, h, ExtendedColorType::L8),
            encode(&rgb, w, h, ExtendedColorType::Rgb8),
        ] {
            let reference = decode(&l, &jpeg, 0, ORIGIN).unwrap();
            let stripped = strip_dht(&jpeg);
            assert!(stripped.len() < jpeg.len());
            assert!(matches!(with_huffman_tables(&jpeg), Ok(Cow::Borrowed(_))));
            assert!(matches!(with_huffman_tables(&stripped), Ok(Cow::Owned(_))));
            // Without the fix the decoder fails.
            assert!(JpegDecoder::new(Cursor::new(&stripped[..]))
                .and_then(DynamicImage::from_decoder)
                .is_err());
            let fixed = decode(&l, &stripped, 0, ORIGIN).unwrap();
            assert_eq!(fixed.luma, reference.luma);
        }
    }

    #[test]
    fn default_tables_are_consistent() {
        let seg = default_dht_segment();
        assert_eq!(&seg[..2], &[0xFF, 0xC4]);
        assert_eq!(u16::from_be_bytes([seg[2], seg[3]]) as usize, seg.len() - 2);
        // Each table's code counts add up to its number of values.
        let mut pos = 4;
        while pos < seg.len() {
            let n: usize = seg[pos + 1..pos + 17].iter().map(|&b| b as usize).sum();
            pos += 17 + n;
        }
        assert_eq!(pos, seg.len());
    }
}
