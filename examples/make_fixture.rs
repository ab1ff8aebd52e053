//! Renders the project's fixture video, `tests/fixtures/walkby.y4m.zst`: 6 s of a synthetic
//! scene at 640x480, 30 fps, 8-bit gray (sRGB-encoded, full range), compressed with Zstandard.
//! The daemon embeds it as its default source and the integration tests drive the pipeline with
//! it.
//!
//! The scene: a brick wall under a soft light gradient; a dark ball rolls across it; a bright
//! bar turns around a pivot; a small lamp blinks at 2 Hz; from the middle on, the camera pans
//! left at 2 pixels per frame. Edges are anti-aliased (4x4 samples per pixel).
//!
//! ```text
//! cargo run --release --example make_fixture [-- OUT]
//! ```

use std::io::Write;

const W: usize = 640;
const H: usize = 480;
const FPS: usize = 30;
const FRAMES: usize = 180;

fn hash(a: i64, b: i64) -> f64 {
    let mut z = (a as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (b as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
}

/// The wall at world position (u, v): bricks 48x20 with 3-pixel mortar, rows offset by half.
fn wall(u: f64, v: f64) -> f64 {
    let row = (v / 20.0).floor();
    let shift = if row as i64 % 2 == 0 { 0.0 } else { 24.0 };
    let col = ((u + shift) / 48.0).floor();
    let (bu, bv) = ((u + shift) - col * 48.0, v - row * 20.0);
    let light = 0.55 + 0.45 * (-((u - 200.0).powi(2) + (v - 120.0).powi(2)) / 300_000.0).exp();
    if bu < 3.0 || bv < 3.0 {
        0.08 * light
    } else {
        (0.18 + 0.22 * hash(col as i64, row as i64)) * light
    }
}

fn scene(frame: usize, x: f64, y: f64) -> f64 {
    let t = frame as f64 / FPS as f64;
    let pan = if frame >= FRAMES / 2 {
        2.0 * (frame - FRAMES / 2) as f64
    } else {
        0.0
    };
    let mut value = wall(x + pan, y);
    // The lamp: on for the first half of every 0.5 s.
    if (560.0..590.0).contains(&x) && (40.0..70.0).contains(&y) && (t * 2.0).fract() < 0.5 {
        value = 0.9;
    }
    // The bar: 160 x 14 pixels turning about (430, 150) once every 3 s.
    let angle = t * std::f64::consts::TAU / 3.0;
    let (dx, dy) = (x - 430.0, y - 150.0);
    let along = dx * angle.cos() + dy * angle.sin();
    let across = -dx * angle.sin() + dy * angle.cos();
    if along.abs() < 80.0 && across.abs() < 7.0 {
        value = 0.75;
    }
    // The ball: radius 45, rolling right at 120 pixels per second.
    let (bx, by) = (-50.0 + 120.0 * t, 330.0);
    if (x - bx).powi(2) + (y - by).powi(2) < 45.0 * 45.0 {
        value = 0.03;
    }
    value
}

fn encode_srgb(linear: f64) -> u8 {
    let l = linear.clamp(0.0, 1.0);
    let v = if l <= 0.003_130_8 {
        12.92 * l
    } else {
        1.055 * l.powf(1.0 / 2.4) - 0.055
    };
    (v * 255.0).round() as u8
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "tests/fixtures/walkby.y4m.zst".to_string());
    let file = std::fs::File::create(&out)?;
    let mut zst = zstd::stream::write::Encoder::new(file, 19)?;
    zst.long_distance_matching(true)?;
    zst.window_log(24)?;
    let mut plane = vec![0u8; W * H];
    {
        let mut encoder = y4m::encode(W, H, y4m::Ratio::new(FPS, 1))
            .with_colorspace(y4m::Colorspace::Cmono)
            .append_vendor_extension(y4m::VendorExtensionString::new(
                b"COLORRANGE=FULL".to_vec(),
            )?)
            .write_header(&mut zst)?;
        for frame in 0..FRAMES {
            for y in 0..H {
                for x in 0..W {
                    let mut sum = 0.0;
                    for sy in 0..4 {
                        for sx in 0..4 {
                            let (fx, fy) = (
                                x as f64 + (sx as f64 + 0.5) / 4.0,
                                y as f64 + (sy as f64 + 0.5) / 4.0,
                            );
                            sum += scene(frame, fx, fy);
                        }
                    }
                    plane[y * W + x] = encode_srgb(sum / 16.0);
                }
            }
            encoder.write_frame(&y4m::Frame::new([&plane, &[], &[]], None))?;
        }
    }
    zst.finish()?.flush()?;
    let bytes = std::fs::metadata(&out)?.len();
    println!("{out}: {FRAMES} frames {W}x{H} at {FPS} fps, {bytes} bytes");
    Ok(())
}
