//! One sub-frame's blend of its two neighbouring frames along the flows (the module docs of
//! [`super`], step 5), a row's pixels at a time.
//!
//! Each pixel samples both frames bilinearly where its flows land and trusts each sample
//! where the flow of the pixel nearest that position is consistent. Both lookups come from
//! one packed copy of each frame ([`Packed`]): a pixel's value and its flow's trust in one
//! word, with the last column and row repeated, so that the four corners of a bilinear
//! sample are two pairs of neighbouring words and the nearest pixel is one of them. The
//! positions and the blend run on vectors; only the two pairs of loads per frame are scalar.

use super::{inside, whole, Subframes};

/// Pixels of a sub-frame row blended together.
pub(super) const BLEND_CHUNK: usize = 64;

/// The interval's two frames packed for [`Blend`]: per pixel, its value (low 16 bits) and
/// whether its flow is trusted (bit 16), `(w + 1) x (h + 1)` words, the last column and row
/// repeated (the border a bilinear sample repeats).
#[derive(Debug, Default)]
pub(super) struct Packed {
    p0: Vec<u32>,
    p1: Vec<u32>,
}

/// Bytes per frame pixel [`Packed`] holds (two frames of 4-byte words; the padding's one
/// row and column are within a frame's own size for frames of at least 16 x 16).
pub(super) const PACKED_BYTES_PER_PIXEL: u64 = 2 * 4 + 1;

impl Packed {
    /// Packs `f0` and `f1` (`w x h`) with their flows' trust `ok0` and `ok1`.
    pub(super) fn set(
        &mut self,
        (w, h): (usize, usize),
        f0: (&[u16], &[bool]),
        f1: (&[u16], &[bool]),
    ) {
        pack(&mut self.p0, w, h, f0.0, f0.1);
        pack(&mut self.p1, w, h, f1.0, f1.1);
    }
}

/// `frame` and `ok` (`w x h`) into `out` (see [`Packed`]).
fn pack(out: &mut Vec<u32>, w: usize, h: usize, frame: &[u16], ok: &[bool]) {
    out.clear();
    out.reserve((w + 1) * (h + 1));
    for (values, oks) in frame.chunks_exact(w).zip(ok.chunks_exact(w)).take(h) {
        out.extend(
            values
                .iter()
                .zip(oks)
                .map(|(&v, &ok)| u32::from(v) | u32::from(ok) << 16),
        );
        let last = out.last().copied().unwrap_or(0);
        out.push(last);
    }
    let start = out.len().saturating_sub(w + 1);
    out.extend_from_within(start..);
}

/// One sub-frame's blend at `tau` between the packed frames.
pub(super) struct Blend<'a> {
    p0: &'a [u32],
    p1: &'a [u32],
    f01: &'a [[f32; 2]],
    f10: &'a [[f32; 2]],
    w: usize,
    h: usize,
    scale0: f32,
    tau: f32,
    s: f32,
    /// The flows' factors in `F(tau->0) = -(1-tau) tau F01 + tau^2 F10` and `F(tau->1) =
    /// (1-tau)^2 F01 - tau (1-tau) F10`.
    to0: (f32, f32),
    to1: (f32, f32),
}

/// Where a chunk of pixels sample one frame, one array per quantity.
struct Taps {
    /// The packed index of the bilinear sample's top-left corner.
    at: [u32; BLEND_CHUNK],
    /// The sample's weights (as [`super::sample`] takes them).
    fx: [f32; BLEND_CHUNK],
    fy: [f32; BLEND_CHUNK],
    /// The pixel nearest the position (as [`super::nearest`] finds it) is the right or the
    /// lower corner.
    right: [bool; BLEND_CHUNK],
    below: [bool; BLEND_CHUNK],
}

impl Taps {
    fn new() -> Self {
        Taps {
            at: [0; BLEND_CHUNK],
            fx: [0.0; BLEND_CHUNK],
            fy: [0.0; BLEND_CHUNK],
            right: [false; BLEND_CHUNK],
            below: [false; BLEND_CHUNK],
        }
    }

    /// The taps of position `(x, y)` for pixel `j`, in a frame whose last column and row
    /// are `last` and whose packed rows are `stride` words: the same values as
    /// [`super::sample`] and [`super::nearest`] find, in 32 bits so that they run on vectors.
    #[inline(always)]
    fn set(&mut self, j: usize, last: (f32, f32), stride: u32, x: f32, y: f32) {
        let nx = whole(inside(x + 0.5, last.0));
        let ny = whole(inside(y + 0.5, last.1));
        let (x, y) = (inside(x, last.0), inside(y, last.1));
        let (xi, yi) = (whole(x), whole(y));
        self.fx[j] = x - xi as f32;
        self.fy[j] = y - yi as f32;
        self.at[j] = (yi * stride as i32 + xi) as u32;
        (self.right[j], self.below[j]) = (nx > xi, ny > yi);
    }
}

/// The corners of a chunk's samples of one packed frame: top left, top right, bottom left,
/// bottom right.
type Corners = [[u32; 4]; BLEND_CHUNK];

/// What [`Blend::row`] works in, kept by its caller across rows (arrays on the stack would be
/// cleared at every call).
pub(super) struct RowScratch {
    taps0: Taps,
    taps1: Taps,
    c0: Corners,
    c1: Corners,
}

impl RowScratch {
    pub(super) fn new() -> Box<Self> {
        Box::new(RowScratch {
            taps0: Taps::new(),
            taps1: Taps::new(),
            c0: [[0; 4]; BLEND_CHUNK],
            c1: [[0; 4]; BLEND_CHUNK],
        })
    }
}

/// Loads the corners of `taps` (`n` of them) from `packed`, whose rows are `stride` words.
#[inline(always)]
fn gather(taps: &Taps, n: usize, packed: &[u32], stride: usize, out: &mut Corners) {
    for (c, &at) in out.iter_mut().zip(&taps.at).take(n) {
        let at = at as usize;
        let (top, bottom) = (&packed[at..at + 2], &packed[at + stride..at + stride + 2]);
        *c = [top[0], top[1], bottom[0], bottom[1]];
    }
}

/// Pixel `j`'s bilinear sample of its packed corners `c`, and the trust of the corner nearest
/// its position.
#[inline(always)]
fn sample(c: [u32; 4], taps: &Taps, j: usize) -> (f32, bool) {
    let (fx, fy, right, below) = (taps.fx[j], taps.fy[j], taps.right[j], taps.below[j]);
    let v = |i: usize| (c[i] & 0xFFFF) as f32;
    let top = v(0) * (1.0 - fx) + v(1) * fx;
    let bottom = v(2) * (1.0 - fx) + v(3) * fx;
    let near = match (right, below) {
        (false, false) => c[0],
        (true, false) => c[1],
        (false, true) => c[2],
        (true, true) => c[3],
    };
    (top * (1.0 - fy) + bottom * fy, near >> 16 & 1 == 1)
}

impl<'a> Blend<'a> {
    /// The blend at `tau` of `m`'s packed frames (the first one's values times `scale0`).
    pub(super) fn new(m: &'a Subframes, scale0: f32, tau: f32) -> Self {
        let s = 1.0 - tau;
        Blend {
            p0: &m.packed.p0,
            p1: &m.packed.p1,
            f01: &m.f01,
            f10: &m.f10,
            w: m.width,
            h: m.height,
            scale0,
            tau,
            s,
            to0: (-s * tau, tau * tau),
            to1: (s * s, tau * s),
        }
    }

    /// Pixels `xs` of row `y` (at most [`BLEND_CHUNK`]) into `out`: in three passes, so the
    /// arithmetic runs on vectors: where each pixel's flows land, the frames' packed corners
    /// there, and the blend. Each pixel's arithmetic is the same as alone, in the same order.
    pub(super) fn row(
        &self,
        y: usize,
        xs: std::ops::Range<usize>,
        out: &mut [u16],
        scratch: &mut RowScratch,
    ) {
        crate::simd::run(
            #[inline(always)]
            || self.row_here(y, xs, out, scratch),
        )
    }

    /// [`Blend::row`] in the caller's instruction set.
    #[inline(always)]
    fn row_here(
        &self,
        y: usize,
        xs: std::ops::Range<usize>,
        out: &mut [u16],
        scratch: &mut RowScratch,
    ) {
        let (w, h) = (self.w, self.h);
        let n = xs.len().min(BLEND_CHUNK).min(out.len());
        let start = y * w + xs.start;
        let (f01, f10) = (&self.f01[start..start + n], &self.f10[start..start + n]);
        let last = ((w - 1) as f32, (h - 1) as f32);
        let stride = w + 1;
        let RowScratch {
            taps0,
            taps1,
            c0,
            c1,
        } = scratch;
        for j in 0..n {
            let [ax, ay] = f01[j];
            let [bx, by] = f10[j];
            let to0 = (
                self.to0.0 * ax + self.to0.1 * bx,
                self.to0.0 * ay + self.to0.1 * by,
            );
            let to1 = (
                self.to1.0 * ax - self.to1.1 * bx,
                self.to1.0 * ay - self.to1.1 * by,
            );
            // Through `i32`: an unsigned conversion has no vector form on SSE2.
            let (x, yf) = ((xs.start + j) as i32 as f32, y as i32 as f32);
            taps0.set(j, last, stride as u32, x + to0.0, yf + to0.1);
            taps1.set(j, last, stride as u32, x + to1.0, yf + to1.1);
        }
        gather(taps0, n, self.p0, stride, c0);
        gather(taps1, n, self.p1, stride, c1);
        let (s, tau) = (self.s, self.tau);
        for j in 0..n {
            let (v0, seen0) = sample(c0[j], taps0, j);
            let (v1, seen1) = sample(c1[j], taps1, j);
            let v0 = v0 * self.scale0;
            // Each neighbour where its flow is trusted; where neither is, the plain blend.
            let (w0, w1) = (if seen0 { s } else { 0.0 }, if seen1 { tau } else { 0.0 });
            let neither = w0 + w1 <= 0.0;
            let (a, b) = if neither { (s, tau) } else { (w0, w1) };
            let v = (a * v0 + b * v1) / (a + b);
            // Non-negative: `+ 0.5` and truncation round it (no libm call in the loop).
            // Through `i32` (on vectors), as for the taps: the same values.
            out[j] = (v + 0.5).clamp(0.0, 65535.0) as i32 as u16;
        }
    }
}
