//! A frame's gray image and its Gaussian pyramid, built once when the frame arrives and kept
//! while the frame is the first or second of an interval: the change mask reads the gray
//! image, both flows (forward and backward) and both intervals the frame belongs to read the
//! levels and their gradients.
//!
//! Level `s` holds the frame at `1 / 2^s` of its resolution: each level is the one below it
//! filtered by the binomial `[1 3 3 1] / 8` (a discrete Gaussian of sigma about 0.9 px, the
//! border repeated) in both directions and decimated by two, so pixel `i` of level `s + 1`
//! covers pixels `2i` and `2i + 1` of level `s`. A pixel's centre `x_s` on level `s` is at
//! `(x_s + 0.5) 2^s - 0.5` in the frame. Each level from the first one used keeps its image
//! and its Sobel gradients (divided by 8: intensity levels per pixel), in `f32`.

/// One level of a [`Pyramid`].
#[derive(Debug, Clone, Default)]
pub struct Level {
    /// Width and height in pixels.
    pub w: usize,
    /// Height in pixels.
    pub h: usize,
    /// The image, row-major, in gray levels (0-255).
    pub img: Vec<f32>,
    /// Its horizontal gradient (levels per pixel).
    pub gx: Vec<f32>,
    /// Its vertical gradient (levels per pixel).
    pub gy: Vec<f32>,
}

/// A frame's 8-bit gray image and the pyramid levels built from it so far (see the module
/// docs). Levels are built on demand ([`Pyramid::ensure`]) and kept.
#[derive(Debug, Clone, Default)]
pub struct Pyramid {
    width: usize,
    height: usize,
    gray: Vec<u8>,
    /// `levels[s]` is level `s`; those below the first one asked for stay empty.
    levels: Vec<Level>,
    /// The first level with gradients, and the last level built (`None`: none built).
    built: Option<(usize, usize)>,
}

impl Pyramid {
    /// An empty pyramid (no frame yet).
    pub fn new() -> Self {
        Self::default()
    }

    /// Starts over with a new frame: `fill` writes its `width x height` gray values into the
    /// buffer it is given (cleared, to be extended); levels are dropped (kept as buffers).
    pub fn set(&mut self, width: usize, height: usize, fill: impl FnOnce(&mut Vec<u8>)) {
        self.width = width;
        self.height = height;
        self.gray.clear();
        fill(&mut self.gray);
        debug_assert_eq!(self.gray.len(), width * height);
        self.built = None;
    }

    /// Width of the frame.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height of the frame.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The frame's gray values, row-major.
    pub fn gray(&self) -> &[u8] {
        &self.gray
    }

    /// The size of level `s` (without building it).
    pub fn level_size(&self, s: usize) -> (usize, usize) {
        let (mut w, mut h) = (self.width, self.height);
        for _ in 0..s {
            (w, h) = (w.div_ceil(2).max(1), h.div_ceil(2).max(1));
        }
        (w, h)
    }

    /// Builds levels `first..=last` with their gradients, if not built already.
    pub fn ensure(&mut self, first: usize, last: usize) {
        if let Some((f, l)) = self.built {
            if f <= first && l >= last {
                return;
            }
        }
        if self.levels.len() <= last {
            self.levels.resize_with(last + 1, Level::default);
        }
        // Level 0's image is kept only when level 0 is used; the levels above are built from
        // the gray bytes directly.
        let (w, h) = (self.width, self.height);
        for s in 0..=last {
            let (lw, lh) = self.level_size(s);
            let (done, rest) = self.levels.split_at_mut(s);
            let level = &mut rest[0];
            level.w = lw;
            level.h = lh;
            if s == 0 {
                level.img.clear();
                if first == 0 {
                    level.img.extend(self.gray.iter().map(|&v| f32::from(v)));
                }
            } else if s == 1 {
                down(&self.gray, w, h, &mut level.img);
            } else {
                let below = &done[s - 1];
                down(&below.img, below.w, below.h, &mut level.img);
            }
            if s >= first {
                sobel(&level.img, lw, lh, &mut level.gx, &mut level.gy);
            } else {
                level.gx.clear();
                level.gy.clear();
            }
        }
        self.built = Some((first, last));
    }

    /// Level `s`, which [`Pyramid::ensure`] must have built.
    pub fn level(&self, s: usize) -> &Level {
        &self.levels[s]
    }

    /// Bytes held per pixel of the frame, at most: the gray byte, and each level's image and
    /// gradients (12 bytes a pixel of a level; a third of a frame's pixels over levels 1 and
    /// up), with level 0's image.
    pub const BYTES_PER_PIXEL: u64 = 1 + 4 + 12 / 3 + 2;
}

/// `src` (`w x h`) filtered by `[1 3 3 1] / 8` both ways and decimated by two into `out`.
/// Each row is split into its even and odd pixels first, so that the filter reads
/// neighbouring values (and runs on vectors): output `i` is `odd[i - 1] + 3 (even[i] +
/// odd[i]) + even[i + 1]`, the border repeated.
#[inline(never)]
fn down<T: Copy + Into<f32>>(src: &[T], w: usize, h: usize, out: &mut Vec<f32>) {
    let (w2, h2) = (w.div_ceil(2).max(1), h.div_ceil(2).max(1));
    let mut rows = vec![0f32; w2 * h];
    // `even[i] = x[2i]`, `odd[i] = x[2i + 1]`, each with one repeated value at either end:
    // index 0 is the one before the row, `i + 1` is pixel `i`.
    let mut even = vec![0f32; w2 + 2];
    let mut odd = vec![0f32; w2 + 2];
    for (y, line) in src.chunks_exact(w).enumerate().take(h) {
        let pairs = line.chunks_exact(2);
        if let [last] = pairs.remainder() {
            (even[w2], odd[w2]) = ((*last).into(), (*last).into());
        }
        for ((e, o), pair) in even[1..].iter_mut().zip(&mut odd[1..]).zip(pairs) {
            (*e, *o) = (pair[0].into(), pair[1].into());
        }
        // Before the row: x[-1] = x[0]; after it: x[w] = x[w - 1] (and x[w + 1] too).
        odd[0] = even[1];
        even[w2 + 1] = if w.is_multiple_of(2) {
            odd[w2]
        } else {
            even[w2]
        };
        let row = &mut rows[y * w2..(y + 1) * w2];
        for (i, r) in row.iter_mut().enumerate() {
            *r = (odd[i] + 3.0 * (even[i + 1] + odd[i + 1]) + even[i + 2]) * 0.125;
        }
    }
    out.clear();
    out.resize(w2 * h2, 0.0);
    let last = h.saturating_sub(1);
    for (i, line) in out.chunks_exact_mut(w2).enumerate() {
        let y = 2 * i;
        let r = |y: usize| &rows[y.min(last) * w2..y.min(last) * w2 + w2];
        let (a, b, c, d) = (r(y.saturating_sub(1)), r(y), r(y + 1), r(y + 2));
        for x in 0..w2 {
            line[x] = (a[x] + 3.0 * (b[x] + c[x]) + d[x]) * 0.125;
        }
    }
}

/// Sobel gradients of `img` (`w x h`, the border repeated), divided by 8.
#[inline(never)]
fn sobel(img: &[f32], w: usize, h: usize, gx: &mut Vec<f32>, gy: &mut Vec<f32>) {
    gx.clear();
    gx.resize(w * h, 0.0);
    gy.clear();
    gy.resize(w * h, 0.0);
    if w == 0 || h == 0 {
        return;
    }
    // Per row: the vertical smoothing `[1 2 1]` and difference `[-1 0 1]` of the three rows,
    // then the horizontal difference and smoothing of those (the interior on neighbouring
    // values, the two border pixels apart).
    let mut smooth = vec![0f32; w];
    let mut diff = vec![0f32; w];
    for y in 0..h {
        let up = &img[y.saturating_sub(1) * w..][..w];
        let mid = &img[y * w..][..w];
        let down = &img[(y + 1).min(h - 1) * w..][..w];
        for x in 0..w {
            smooth[x] = up[x] + 2.0 * mid[x] + down[x];
            diff[x] = down[x] - up[x];
        }
        let (rx, ry) = (&mut gx[y * w..(y + 1) * w], &mut gy[y * w..(y + 1) * w]);
        if w >= 3 {
            for x in 1..w - 1 {
                rx[x] = (smooth[x + 1] - smooth[x - 1]) * 0.125;
                ry[x] = (diff[x - 1] + 2.0 * diff[x] + diff[x + 1]) * 0.125;
            }
        }
        for x in [0, w - 1] {
            let (l, r) = (x.saturating_sub(1), (x + 1).min(w - 1));
            rx[x] = (smooth[r] - smooth[l]) * 0.125;
            ry[x] = (diff[l] + 2.0 * diff[x] + diff[r]) * 0.125;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A linear ramp stays a ramp of half the size, at the positions the module docs give,
    /// and its gradient is the slope (the Sobel filter is exact on a plane).
    #[test]
    fn a_ramp_keeps_its_slope_and_positions() {
        let (w, h) = (128usize, 64usize);
        let mut p = Pyramid::new();
        p.set(w, h, |g| {
            g.extend((0..w * h).map(|i| (i % w + 2 * (i / w)) as u8))
        });
        p.ensure(1, 3);
        for s in 1..=3 {
            let l = p.level(s);
            assert_eq!((l.w, l.h), p.level_size(s));
            let k = (1usize << s) as f32;
            // Away from the repeated border: the value at the centre of the pixels covered.
            for y in 3..l.h - 3 {
                for x in 3..l.w - 3 {
                    let (fx, fy) = ((x as f32 + 0.5) * k - 0.5, (y as f32 + 0.5) * k - 0.5);
                    let want = fx + 2.0 * fy;
                    let got = l.img[y * l.w + x];
                    assert!(
                        (got - want).abs() < 1e-3,
                        "level {s} ({x}, {y}): {got} vs {want}"
                    );
                    assert!((l.gx[y * l.w + x] - k).abs() < 1e-3);
                    assert!((l.gy[y * l.w + x] - 2.0 * k).abs() < 1e-3);
                }
            }
        }
        assert!(p.level(0).img.is_empty());
    }

    /// Odd and tiny sizes: every level at least one pixel, no panic, values in range.
    #[test]
    fn odd_and_tiny_sizes() {
        for (w, h) in [(1usize, 1usize), (2, 3), (5, 1), (7, 9), (17, 16)] {
            let mut p = Pyramid::new();
            p.set(w, h, |g| g.extend((0..w * h).map(|i| (i * 37 % 256) as u8)));
            p.ensure(0, 5);
            for s in 0..=5 {
                let l = p.level(s);
                assert_eq!(l.img.len(), l.w * l.h);
                assert!(l.w >= 1 && l.h >= 1);
                assert!(l.img.iter().all(|v| (0.0..=255.0).contains(v)));
                assert!(l.gx.iter().chain(&l.gy).all(|v| v.is_finite()));
            }
        }
    }
}
