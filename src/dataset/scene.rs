//! Random scenes for training data: a textured background seen through a moving homography,
//! textured objects moving over it, and light that changes over time, all drawn from a seed
//! and rendered at any time, so the same scene can be sampled at a high rate (for ground-truth
//! events) and at a video rate (for the network's input).

use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;

/// A grayscale image in linear light, values in `[0, 1]`, used as a texture.
#[derive(Debug, Clone)]
pub struct Image {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Row-major linear values.
    pub values: Vec<f32>,
}

impl Image {
    /// Bilinear sample at `(u, v)` pixels, mirrored at the borders (the image tiles without
    /// seams).
    fn sample(&self, u: f64, v: f64) -> f64 {
        let mirror = |x: f64, n: usize| {
            let p = 2.0 * n as f64;
            let m = x.rem_euclid(p);
            if m < n as f64 {
                m
            } else {
                p - m - 1e-9
            }
        };
        let (u, v) = (
            mirror(u, self.width).min(self.width as f64 - 1.0),
            mirror(v, self.height).min(self.height as f64 - 1.0),
        );
        let (x0, y0) = (u.floor() as usize, v.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (fx, fy) = (u - x0 as f64, v - y0 as f64);
        let at = |x: usize, y: usize| self.values[y * self.width + x] as f64;
        let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
        let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
        top * (1.0 - fy) + bottom * fy
    }
}

/// A reflectance pattern over the plane, values in `[0, 1]`.
#[derive(Debug, Clone)]
pub enum Texture {
    /// A sum of sinusoidal gratings: (direction x, direction y, cycles per pixel, phase,
    /// amplitude) each, around 0.5.
    Gratings(Vec<[f64; 5]>),
    /// Value noise: octaves of (lattice seed, cell size in pixels, amplitude).
    Noise(Vec<(u64, f64, f64)>),
    /// A checkerboard: cell size, angle, dark and light reflectance.
    Checker(f64, f64, f64, f64),
    /// Discs on a plain ground: ground level and (x, y, radius, level) each; the plane repeats
    /// every `period` pixels.
    Blobs(f64, f64, Vec<[f64; 4]>),
    /// An image, scaled by the factor.
    Image(Arc<Image>, f64),
}

/// An integer hash to `[0, 1)`.
fn hash01(seed: u64, x: i64, y: i64) -> f64 {
    let mut h = seed
        ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    h ^= h >> 33;
    h = h.wrapping_mul(0xFF51_AFD7_ED55_8CCD);
    h ^= h >> 33;
    h = h.wrapping_mul(0xC4CE_B9FE_1A85_EC53);
    h ^= h >> 33;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

impl Texture {
    /// Reflectance at plane point `(u, v)`.
    pub fn sample(&self, u: f64, v: f64) -> f64 {
        let r = match self {
            Texture::Gratings(g) => {
                0.5 + g
                    .iter()
                    .map(|[dx, dy, f, ph, a]| {
                        a * (std::f64::consts::TAU * f * (dx * u + dy * v) + ph).sin()
                    })
                    .sum::<f64>()
            }
            Texture::Noise(octaves) => {
                let mut sum = 0.5;
                for &(seed, cell, amp) in octaves {
                    let (x, y) = (u / cell, v / cell);
                    let (x0, y0) = (x.floor(), y.floor());
                    let (fx, fy) = (x - x0, y - y0);
                    // Smoothstep between lattice values.
                    let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
                    let (xi, yi) = (x0 as i64, y0 as i64);
                    let at = |dx: i64, dy: i64| hash01(seed, xi + dx, yi + dy) - 0.5;
                    let top = at(0, 0) * (1.0 - sx) + at(1, 0) * sx;
                    let bottom = at(0, 1) * (1.0 - sx) + at(1, 1) * sx;
                    sum += 2.0 * amp * (top * (1.0 - sy) + bottom * sy);
                }
                sum
            }
            Texture::Checker(cell, angle, lo, hi) => {
                let (c, s) = (angle.cos(), angle.sin());
                let (x, y) = ((c * u + s * v) / cell, (-s * u + c * v) / cell);
                // A soft edge a pixel wide, so the pattern is band-limited.
                let (fx, fy) = (x - x.floor(), y - y.floor());
                let d = fx.min(1.0 - fx).min(fy.min(1.0 - fy)) * cell;
                let parity = ((x.floor() + y.floor()) as i64).rem_euclid(2) as f64;
                let mix = 0.5 + (parity - 0.5) * (2.0 * d).min(1.0);
                lo + (hi - lo) * mix
            }
            Texture::Blobs(ground, period, blobs) => {
                let (x, y) = (u.rem_euclid(*period), v.rem_euclid(*period));
                let mut level = *ground;
                for [bx, by, r, l] in blobs {
                    let d = ((x - bx).powi(2) + (y - by).powi(2)).sqrt() - r;
                    let cover = (0.5 - d).clamp(0.0, 1.0);
                    level += (l - level) * cover;
                }
                level
            }
            Texture::Image(img, scale) => img.sample(u / scale, v / scale),
        };
        r.clamp(0.0, 1.0)
    }

    /// A random procedural texture, or one of `images` when there are any (half the time).
    pub fn random(rng: &mut impl Rng, images: &[Arc<Image>]) -> Self {
        if !images.is_empty() && rng.gen_bool(0.5) {
            let img = images[rng.gen_range(0..images.len())].clone();
            return Texture::Image(img, rng.gen_range(0.5..2.0));
        }
        match rng.gen_range(0..4) {
            0 => Texture::Gratings(
                (0..rng.gen_range(1..5))
                    .map(|_| {
                        let a: f64 = rng.gen_range(0.0..std::f64::consts::PI);
                        [
                            a.cos(),
                            a.sin(),
                            1.0 / rng.gen_range(4.0..60.0),
                            rng.gen_range(0.0..std::f64::consts::TAU),
                            rng.gen_range(0.05..0.25),
                        ]
                    })
                    .collect(),
            ),
            1 => Texture::Noise(
                (0..rng.gen_range(2..6))
                    .map(|k| {
                        (
                            rng.gen(),
                            rng.gen_range(24.0..64.0) / 2f64.powi(k),
                            0.4 / 1.6f64.powi(k),
                        )
                    })
                    .collect(),
            ),
            2 => {
                let lo = rng.gen_range(0.02..0.4);
                Texture::Checker(
                    rng.gen_range(4.0..40.0),
                    rng.gen_range(0.0..std::f64::consts::PI),
                    lo,
                    rng.gen_range(lo + 0.1..1.0),
                )
            }
            _ => {
                let period = rng.gen_range(60.0..200.0);
                Texture::Blobs(
                    rng.gen_range(0.05..0.8),
                    period,
                    (0..rng.gen_range(3..15))
                        .map(|_| {
                            [
                                rng.gen_range(0.0..period),
                                rng.gen_range(0.0..period),
                                rng.gen_range(2.0..period / 4.0),
                                rng.gen_range(0.0..1.0),
                            ]
                        })
                        .collect(),
                )
            }
        }
    }
}

/// A parameter moving over time: `p0 + v t + a sin(w t + phase)`, `t` in seconds.
#[derive(Debug, Clone, Copy)]
pub struct Path1 {
    p0: f64,
    v: f64,
    a: f64,
    w: f64,
    phase: f64,
}

impl Path1 {
    fn at(&self, t: f64) -> f64 {
        self.p0 + self.v * t + self.a * (self.w * t + self.phase).sin()
    }

    fn random(rng: &mut impl Rng, p0: std::ops::Range<f64>, speed: f64, swing: f64) -> Self {
        Path1 {
            p0: rng.gen_range(p0),
            v: rng.gen_range(-speed..=speed),
            a: rng.gen_range(0.0..=swing),
            w: rng.gen_range(1.0..12.0),
            phase: rng.gen_range(0.0..std::f64::consts::TAU),
        }
    }

    fn still(p0: f64) -> Self {
        Path1 {
            p0,
            v: 0.0,
            a: 0.0,
            w: 0.0,
            phase: 0.0,
        }
    }
}

/// The camera's motion over the background: a homography from pixel to plane coordinates
/// (translation, rotation, zoom and a small perspective tilt, each moving over time).
#[derive(Debug, Clone)]
pub struct Motion {
    tx: Path1,
    ty: Path1,
    angle: Path1,
    log_zoom: Path1,
    tilt_x: Path1,
    tilt_y: Path1,
}

impl Motion {
    /// Plane coordinates of pixel `(x, y)` (relative to the image centre) at `t` seconds.
    fn map(&self, x: f64, y: f64, t: f64) -> (f64, f64) {
        let (a, z) = (self.angle.at(t), self.log_zoom.at(t).exp());
        let (c, s) = (a.cos(), a.sin());
        let w = 1.0 + self.tilt_x.at(t) * x + self.tilt_y.at(t) * y;
        let (px, py) = (x / w, y / w);
        (
            (c * px - s * py) / z + self.tx.at(t),
            (s * px + c * py) / z + self.ty.at(t),
        )
    }
}

/// An object in front of the background: a disc or a rounded rectangle with its own texture.
#[derive(Debug, Clone)]
pub struct Occluder {
    cx: Path1,
    cy: Path1,
    /// Half width and half height (equal, with a full corner radius, for a disc).
    half: (f64, f64),
    corner: f64,
    texture: Texture,
}

impl Occluder {
    /// An object of random size, shape, path and texture in a `w x h` frame.
    fn random(
        rng: &mut Xoshiro256PlusPlus,
        (w, h): (f64, f64),
        pace: Pace,
        images: &[Arc<Image>],
    ) -> Self {
        let r = rng.gen_range(4.0..(w.min(h) / 3.0).max(5.0));
        let disc = rng.gen_bool(0.5);
        let half = if disc {
            (r, r)
        } else {
            (r, rng.gen_range(r / 3.0..r * 1.5))
        };
        Occluder {
            cx: Path1::random(rng, 0.0..w, pace.objects, 30.0),
            cy: Path1::random(rng, 0.0..h, pace.objects, 30.0),
            half,
            corner: if disc {
                r
            } else {
                rng.gen_range(0.0..half.0.min(half.1))
            },
            texture: Texture::random(rng, images),
        }
    }

    /// Coverage of pixel `(x, y)` (image coordinates) in `[0, 1]` and the object's reflectance
    /// there.
    fn at(&self, x: f64, y: f64, t: f64) -> (f64, f64) {
        let (dx, dy) = (x - self.cx.at(t), y - self.cy.at(t));
        let (hx, hy) = (self.half.0 - self.corner, self.half.1 - self.corner);
        let (qx, qy) = ((dx.abs() - hx).max(0.0), (dy.abs() - hy).max(0.0));
        let d = (qx * qx + qy * qy).sqrt() - self.corner;
        let cover = (0.5 - d).clamp(0.0, 1.0);
        if cover <= 0.0 {
            return (0.0, 0.0);
        }
        (cover, self.texture.sample(dx, dy))
    }
}

/// A random scene (see the module docs).
#[derive(Debug, Clone)]
pub struct Scene {
    background: Texture,
    motion: Motion,
    occluders: Vec<Occluder>,
    /// Light: log of the overall level over time (full scale = 0).
    log_light: Path1,
    size: (u16, u16),
}

/// How fast scenes move, for [`Scene::random`].
#[derive(Debug, Clone, Copy)]
pub struct Pace {
    /// Largest camera translation speed, pixels per second.
    pub pan: f64,
    /// Largest object speed, pixels per second.
    pub objects: f64,
    /// Hold the camera and the light still, so only the objects move (drawn as usual, then
    /// held: the same seed gives the same objects and textures either way).
    pub still: bool,
}

impl Default for Pace {
    fn default() -> Self {
        Pace {
            pan: 150.0,
            objects: 250.0,
            still: false,
        }
    }
}

impl Scene {
    /// A scene of `size` drawn from `seed`, with textures from `images` (may be empty).
    pub fn random(seed: u64, size: (u16, u16), images: &[Arc<Image>], pace: Pace) -> Self {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        let (w, h) = (size.0 as f64, size.1 as f64);
        // A third of the scenes have a still camera, so only the objects (and light) move.
        let still = rng.gen_bool(1.0 / 3.0);
        let motion = if still {
            Motion {
                tx: Path1::still(rng.gen_range(0.0..1000.0)),
                ty: Path1::still(rng.gen_range(0.0..1000.0)),
                angle: Path1::still(rng.gen_range(0.0..std::f64::consts::TAU)),
                log_zoom: Path1::still(rng.gen_range(-0.5..0.5)),
                tilt_x: Path1::still(0.0),
                tilt_y: Path1::still(0.0),
            }
        } else {
            let tilt = 0.3 / w.max(h);
            Motion {
                tx: Path1::random(&mut rng, 0.0..1000.0, pace.pan, 20.0),
                ty: Path1::random(&mut rng, 0.0..1000.0, pace.pan, 20.0),
                angle: Path1::random(&mut rng, 0.0..6.3, 0.5, 0.1),
                log_zoom: Path1::random(&mut rng, -0.5..0.5, 0.3, 0.05),
                tilt_x: Path1::random(&mut rng, -tilt..tilt, tilt, tilt / 2.0),
                tilt_y: Path1::random(&mut rng, -tilt..tilt, tilt, tilt / 2.0),
            }
        };
        let occluders = (0..rng.gen_range(0..4))
            .map(|_| Occluder::random(&mut rng, (w, h), pace, images))
            .collect();
        let background = Texture::random(&mut rng, images);
        // Overall light from 4% to 90% of full scale; a third of scenes change it (a cloud,
        // a lamp dimmed) by up to a factor of 1.6 either way.
        let level = rng.gen_range(0.04f64.ln()..0.9f64.ln());
        let log_light = if rng.gen_bool(1.0 / 3.0) {
            Path1 {
                p0: level,
                v: 0.0,
                a: rng.gen_range(0.1..0.5),
                w: rng.gen_range(0.5..6.0),
                phase: rng.gen_range(0.0..std::f64::consts::TAU),
            }
        } else {
            Path1::still(level)
        };
        let mut scene = Scene {
            background,
            motion,
            occluders,
            log_light,
            size,
        };
        if pace.still {
            let m = &mut scene.motion;
            for p in [
                &mut m.tx,
                &mut m.ty,
                &mut m.angle,
                &mut m.log_zoom,
                &mut m.tilt_x,
                &mut m.tilt_y,
            ] {
                *p = Path1::still(p.p0);
            }
            scene.log_light = Path1::still(scene.log_light.p0);
            // Something must move: one object more, drawn after everything else.
            if scene.occluders.is_empty() {
                let o = Occluder::random(&mut rng, (w, h), pace, images);
                scene.occluders.push(o);
            }
        }
        scene
    }

    /// Linear luminance (fraction of full scale) of pixel `(x, y)` at `t_us`.
    pub fn luminance(&self, t_us: i64, x: u16, y: u16) -> f64 {
        let t = t_us as f64 * 1e-6;
        let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
        let (cx, cy) = (self.size.0 as f64 / 2.0, self.size.1 as f64 / 2.0);
        let (u, v) = self.motion.map(px - cx, py - cy, t);
        let mut r = self.background.sample(u, v);
        for o in &self.occluders {
            let (cover, level) = o.at(px, py, t);
            r += (level - r) * cover;
        }
        (self.log_light.at(t).exp() * r).clamp(0.0, 1.0)
    }

    /// The frame at `t_us`, 16-bit linear luminance, row-major.
    pub fn render(&self, t_us: i64) -> Vec<u16> {
        let (w, h) = self.size;
        let mut out = Vec::with_capacity(w as usize * h as usize);
        for y in 0..h {
            for x in 0..w {
                out.push((self.luminance(t_us, x, y) * 65535.0).round() as u16);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scenes_are_deterministic_varied_and_in_range() {
        let a = Scene::random(7, (40, 30), &[], Pace::default());
        let b = Scene::random(7, (40, 30), &[], Pace::default());
        let c = Scene::random(8, (40, 30), &[], Pace::default());
        assert_eq!(a.render(12_345), b.render(12_345));
        assert_ne!(a.render(12_345), c.render(12_345));
        for seed in 0..20 {
            let s = Scene::random(seed, (40, 30), &[], Pace::default());
            let f = s.render(100_000);
            assert_eq!(f.len(), 1200);
            let (lo, hi) = (f.iter().min().unwrap(), f.iter().max().unwrap());
            assert!(hi >= lo);
        }
    }

    #[test]
    fn image_textures_sample_bilinearly_and_mirror() {
        let img = Image {
            width: 2,
            height: 1,
            values: vec![0.0, 1.0],
        };
        assert!((img.sample(0.5, 0.0) - 0.5).abs() < 1e-9);
        // Mirrored: just past the right edge reads the right pixel again.
        assert!((img.sample(2.2, 0.0) - 1.0).abs() < 1e-6);
        let t = Texture::Image(Arc::new(img), 1.0);
        assert!((0.0..=1.0).contains(&t.sample(-5.3, 7.1)));
    }
}
