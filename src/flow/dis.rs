//! Dense Inverse Search (Kroeger, Timofte, Dai and Van Gool, "Fast Optical Flow using Dense
//! Inverse Search", ECCV 2016), written for the pixel model's motion.
//!
//! On each pyramid level from the coarsest to the finest one used:
//!
//! 1. **Patches.** A grid of `patch x patch` patches of the first frame, `stride` apart (the
//!    last row and column against the level's border), each seeded with the dense flow of the
//!    coarser level at its centre (zero on the coarsest); with spatial propagation, the flows
//!    already found for its left and upper neighbours (the right and lower ones on a second,
//!    reverse pass) are candidates too, the one with the smallest patch error kept.
//! 2. **Inverse-compositional Gauss-Newton** on the patch's mean-normalised SSD: the patch's
//!    gradients and their Hessian are computed once (on the first frame, which is the
//!    template), each iteration samples the second frame at the patch moved by its flow, and
//!    the step `H^-1 J^T r` is subtracted from the flow. A translation is the same at every
//!    pixel of a patch, so the bilinear weights are too, and a row of the patch is a fixed
//!    blend of two rows of the image: loops the compiler vectorises. A patch stops when its
//!    step falls under 1/100 px, and keeps the best flow it saw (an iteration that raised the
//!    error is not kept).
//! 3. **Densification.** Each pixel's flow is the mean of the flows of the patches covering it,
//!    each weighted by `1 / max(1, |I1(x + u) - I0(x)|)`, its photometric error there.
//!
//! The finest level's flow is upsampled to the frame (bilinear) and scaled to its pixels. No
//! variational refinement: the presets' events are as good without it (docs/physics.md).
//!
//! **Only where things move.** Given a [`Region`] (tiles of the frame), only the patches whose
//! reach (their footprint widened by what the next finer level needs to seed from) meets an
//! active tile are searched, and the flow is written only on the region's tiles; everywhere
//! else it is zero, so the cost follows the moving area.

use super::pyramid::{Level, Pyramid};
use super::Region;
use crate::error::{Error, Result};

/// The patch side, pixels of a level: 8 in every preset (as in DIS's own), fixed so that a
/// patch row is one 8-lane vector (or two 4-lane ones) and the patch arrays live in registers
/// and on the stack.
pub const PATCH: usize = 8;
const N: usize = PATCH * PATCH;

/// The estimator's parameters (one set per preset).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Params {
    /// Distance between neighbouring patches.
    pub stride: usize,
    /// Gauss-Newton iterations per patch, at most (split over the two passes of spatial
    /// propagation).
    pub iterations: usize,
    /// The finest pyramid level searched (0: the frame's resolution).
    pub finest: usize,
    /// Spatial propagation between neighbouring patches, in two passes.
    pub propagate: bool,
}

/// A step shorter than this (pixels of the level) ends a patch's search.
const CONVERGED: f32 = 0.01;
/// Candidate flows nearer than this (pixels of the level) to a patch's own are not tried.
const NEAR: f32 = 0.05;
/// So does a step that lowered the error by less than 2%: what is left is the frames' noise.
const SETTLED: f32 = 0.98;

/// A still patch is kept over a moving candidate unless the candidate's error is below this
/// share of the still one's, less `STILL_NOISE` squared levels per pixel (the read noise of a
/// frame: a few levels).
const STILL_PREFERENCE: f32 = 1.05;
const STILL_NOISE: f32 = 0.25;
/// A patch whose error is at most this (a tenth of a squared level per pixel: far below an
/// 8-bit frame's noise) is matched: no step would improve it.
const MATCHED: f32 = N as f32 * 0.1;

/// One estimator: its parameters and its buffers, kept across frames.
#[derive(Debug, Clone)]
pub struct Dis {
    params: Params,
    /// The current and the coarser level's dense flow, `[dx, dy]` per pixel of the level.
    dense: Vec<[f32; 2]>,
    coarse: Vec<[f32; 2]>,
    /// Per patch of the current level: its flow, its error, and whether it was searched.
    patches: Vec<[f32; 2]>,
    errs: Vec<f32>,
    active: Vec<bool>,
    /// Densification sums per pixel of the level: weighted flow (both components) and weight.
    sum_u: Vec<f32>,
    sum_v: Vec<f32>,
    sum_w: Vec<f32>,
    patch: PatchBuffers,
}

/// One patch's template, row-major.
#[derive(Debug, Clone)]
struct PatchBuffers {
    /// The template minus its mean.
    t: [f32; N],
    /// The template's gradients minus their means.
    jx: [f32; N],
    jy: [f32; N],
}

impl Default for PatchBuffers {
    fn default() -> Self {
        PatchBuffers {
            t: [0.0; N],
            jx: [0.0; N],
            jy: [0.0; N],
        }
    }
}

/// A patch's fixed data on one level: where it is and its Hessian's inverse.
struct Template {
    x: usize,
    y: usize,
    /// `H^-1` as `[a, b, c]` for `[[a, b], [b, c]]`, once a search has needed it; `None`
    /// within where the patch has no texture (its flow stays the best candidate's).
    inverse: Option<Option<[f32; 3]>>,
}

impl Dis {
    /// An estimator with `params`.
    pub fn new(params: Params) -> Self {
        Dis {
            params,
            dense: Vec::new(),
            coarse: Vec::new(),
            patches: Vec::new(),
            errs: Vec::new(),
            active: Vec::new(),
            sum_u: Vec::new(),
            sum_v: Vec::new(),
            sum_w: Vec::new(),
            patch: PatchBuffers::default(),
        }
    }

    /// The pyramid levels this estimator reads on a `width x height` frame: the finest and the
    /// coarsest, where the coarsest is about four patches across the longer side and at
    /// least one patch across the shorter. An error where not even the finest level holds a
    /// patch.
    pub fn levels(&self, width: usize, height: usize) -> Result<(usize, usize)> {
        let p = PATCH;
        let fits = |s: usize| {
            let k = 1usize << s;
            width.div_ceil(k) >= p && height.div_ceil(k) >= p
        };
        let mut finest = self.params.finest;
        while finest > 0 && !fits(finest) {
            finest -= 1;
        }
        if !fits(finest) {
            return Err(Error::invalid(
                "flow",
                format!("a {width} x {height} frame is smaller than one {p} px patch"),
            ));
        }
        let mut coarsest = finest;
        while coarsest < 12
            && fits(coarsest + 1)
            && width.max(height).div_ceil(1 << (coarsest + 1)) >= 4 * p
        {
            coarsest += 1;
        }
        Ok((finest, coarsest))
    }

    /// The flow from `p0`'s frame to `p1`'s into `out` (one `[dx, dy]` per pixel, frame
    /// pixels): on `region`'s tiles only where one is given (zero elsewhere), else the whole
    /// frame. Both pyramids must be of one size ([`super::DenseFlow::compute_on`] checks) and
    /// hold levels `levels(..)` (see [`Pyramid::ensure`]).
    pub(crate) fn compute(
        &mut self,
        p0: &Pyramid,
        p1: &Pyramid,
        region: Option<&Region>,
        out: &mut Vec<[f32; 2]>,
    ) -> Result<()> {
        let (w, h) = (p0.width(), p0.height());
        let (finest, coarsest) = self.levels(w, h)?;
        out.clear();
        out.resize(w * h, [0.0; 2]);
        for s in (finest..=coarsest).rev() {
            std::mem::swap(&mut self.dense, &mut self.coarse);
            let seeded = s < coarsest;
            self.level(p0.level(s), p1.level(s), s, seeded, region);
        }
        upsample(&self.dense, p0.level(finest), finest, w, h, region, out);
        Ok(())
    }

    /// One level: patches seeded from `self.coarse` (when `seeded`), searched, densified
    /// into `self.dense`.
    #[inline(never)]
    fn level(&mut self, l0: &Level, l1: &Level, s: usize, seeded: bool, region: Option<&Region>) {
        let (ps, stride) = (PATCH, self.params.stride);
        let (w, h) = (l0.w, l0.h);
        let xs = grid(w, ps, stride);
        let ys = grid(h, ps, stride);
        let (nx, ny) = (xs.len(), ys.len());
        self.patches.clear();
        self.patches.resize(nx * ny, [0.0; 2]);
        self.errs.clear();
        self.errs.resize(nx * ny, f32::INFINITY);
        self.active.clear();
        let k = 1isize << s;
        // A patch's reach in frame pixels: its footprint, widened by the footprint of the
        // patches of the next finer level that seed from it (and one more for rounding).
        let margin = (ps as isize + 1) * k;
        for &y in &ys {
            for &x in &xs {
                self.active.push(region.is_none_or(|r| {
                    let (x0, y0) = (x as isize * k - margin, y as isize * k - margin);
                    let (x1, y1) = (
                        (x + ps) as isize * k + margin,
                        (y + ps) as isize * k + margin,
                    );
                    r.any(x0, y0, x1, y1)
                }));
            }
        }
        // Seeds: the coarser level's dense flow at each patch's centre, doubled.
        let coarse_w = w.div_ceil(2).max(1);
        let coarse_h = h.div_ceil(2).max(1);
        for (j, &y) in ys.iter().enumerate() {
            for (i, &x) in xs.iter().enumerate() {
                let n = j * nx + i;
                if !self.active[n] || !seeded {
                    continue;
                }
                let cx = (x as f32 + ps as f32 / 2.0) / 2.0 - 0.5;
                let cy = (y as f32 + ps as f32 / 2.0) / 2.0 - 0.5;
                let [u, v] = bilinear2(&self.coarse, coarse_w, coarse_h, cx, cy);
                self.patches[n] = [2.0 * u, 2.0 * v];
            }
        }
        let mut templates: Vec<Template> = ys
            .iter()
            .flat_map(|&y| xs.iter().map(move |&x| (x, y)))
            .map(|(x, y)| Template {
                x,
                y,
                inverse: None,
            })
            .collect();
        let iterations = self.params.iterations;
        if self.params.propagate {
            let first = iterations.div_ceil(2);
            self.pass(l0, l1, &mut templates, nx, ny, first, false);
            self.pass(l0, l1, &mut templates, nx, ny, iterations - first, true);
        } else {
            self.pass(l0, l1, &mut templates, nx, ny, iterations, false);
        }
        self.densify(l0, l1, &templates);
    }

    /// One pass over the patches in raster order (or its reverse), each refined by up to
    /// `iterations` steps after trying its already-refined neighbours' flows (with spatial
    /// propagation).
    #[allow(clippy::too_many_arguments)]
    fn pass(
        &mut self,
        l0: &Level,
        l1: &Level,
        templates: &mut [Template],
        nx: usize,
        ny: usize,
        iterations: usize,
        reverse: bool,
    ) {
        let ps = PATCH;
        let order: Box<dyn Iterator<Item = usize>> = if reverse {
            Box::new((0..nx * ny).rev())
        } else {
            Box::new(0..nx * ny)
        };
        for n in order {
            if !self.active[n] || (reverse && self.errs[n] <= MATCHED) {
                // Inactive, or already matched to within the frames' noise.
                continue;
            }
            let tpl = &mut templates[n];
            self.patch.load(l0, tpl.x, tpl.y);
            let mut u = self.patches[n];
            // The error at `u`, and its Gauss-Newton gradient where known (the reverse pass
            // knows the error of the forward one).
            let (mut best_err, mut grad) = if reverse {
                (self.errs[n], None)
            } else {
                let (err, g) = self.patch.step(l1, tpl.x, tpl.y, u);
                (err, Some(g))
            };
            if self.params.propagate && best_err > MATCHED {
                let (i, j) = (n % nx, n / nx);
                let neighbours = if reverse {
                    [(i + 1 < nx).then(|| n + 1), (j + 1 < ny).then(|| n + nx)]
                } else {
                    [(i > 0).then(|| n - 1), (j > 0).then(|| n - nx)]
                };
                for m in neighbours.into_iter().flatten() {
                    let cand = self.patches[m];
                    let (ex, ey) = (cand[0] - u[0], cand[1] - u[1]);
                    // A neighbour's flow within a twentieth of a pixel of this one's is where
                    // the search would go anyway.
                    if !self.active[m] || ex * ex + ey * ey < NEAR * NEAR {
                        continue;
                    }
                    let (err, g) = self.patch.step(l1, tpl.x, tpl.y, cand);
                    if err < best_err {
                        (u, best_err, grad) = (cand, err, Some(g));
                    }
                }
            }
            // A still patch (most of a frame in most videos) as a candidate of its own,
            // taken where it is about as good: a repeating texture has copies of a patch
            // elsewhere that a seed or a neighbour may have reached.
            if !reverse && u != [0.0, 0.0] {
                let (err, g) = self.patch.step(l1, tpl.x, tpl.y, [0.0, 0.0]);
                if err <= STILL_PREFERENCE * best_err + N as f32 * STILL_NOISE {
                    (u, best_err, grad) = ([0.0, 0.0], err, Some(g));
                }
            }
            // The reverse pass searches again only from a neighbour's flow that did better:
            // from its own, the forward pass's search already ended.
            let moved = !reverse || grad.is_some();
            let inverse = if best_err > MATCHED && moved {
                *tpl.inverse
                    .get_or_insert_with(|| hessian_inverse(l0, tpl.x, tpl.y))
            } else {
                None
            };
            if let Some(inv) = inverse {
                // The search refines the level's start: it stays within half a patch of it,
                // each step at most a quarter of one (a texture that repeats would otherwise
                // let a weakly textured patch jump to a copy of itself).
                let anchor = u;
                let (reach, stride) = (ps as f32 / 2.0, ps as f32 / 4.0);
                let mut grad = match grad {
                    Some(g) => g,
                    None => self.patch.step(l1, tpl.x, tpl.y, u).1,
                };
                for _ in 0..iterations {
                    let [bx, by] = grad;
                    let dx = (inv[0] * bx + inv[1] * by).clamp(-stride, stride);
                    let dy = (inv[1] * bx + inv[2] * by).clamp(-stride, stride);
                    if !(dx.is_finite() && dy.is_finite()) {
                        break;
                    }
                    let next = [
                        (u[0] - dx).clamp(anchor[0] - reach, anchor[0] + reach),
                        (u[1] - dy).clamp(anchor[1] - reach, anchor[1] + reach),
                    ];
                    let next = clamp_flow(next, tpl.x, tpl.y, l1);
                    let (err, g) = self.patch.step(l1, tpl.x, tpl.y, next);
                    if err.partial_cmp(&best_err) != Some(std::cmp::Ordering::Less) {
                        // The step raised the error: the best flow is the one before it.
                        break;
                    }
                    let settled = err > SETTLED * best_err;
                    (u, best_err, grad) = (next, err, g);
                    if settled || dx * dx + dy * dy < CONVERGED * CONVERGED || best_err <= MATCHED {
                        break;
                    }
                }
            }
            self.errs[n] = best_err;
            let best = u;
            self.patches[n] = best;
        }
    }

    /// Each pixel's flow: the patches covering it, weighted by their photometric error there.
    #[inline(never)]
    fn densify(&mut self, l0: &Level, l1: &Level, templates: &[Template]) {
        let (w, h) = (l0.w, l0.h);
        for v in [&mut self.sum_u, &mut self.sum_v, &mut self.sum_w] {
            v.clear();
            v.resize(w * h, 0.0);
        }
        let mut warped = [0f32; N];
        for ((tpl, &u), &on) in templates.iter().zip(&self.patches).zip(&self.active) {
            if !on {
                continue;
            }
            Taps::new(l1, tpl.x, tpl.y, u).patch(l1, &mut warped);
            for (r, row) in warped.chunks_exact(PATCH).enumerate() {
                let at = (tpl.y + r) * w + tpl.x;
                let i0: &[f32; PATCH] = l0.img[at..at + PATCH].try_into().expect("a row");
                let su: &mut [f32; PATCH] =
                    (&mut self.sum_u[at..at + PATCH]).try_into().expect("a row");
                let sv: &mut [f32; PATCH] =
                    (&mut self.sum_v[at..at + PATCH]).try_into().expect("a row");
                let sw: &mut [f32; PATCH] =
                    (&mut self.sum_w[at..at + PATCH]).try_into().expect("a row");
                let weight: [f32; PATCH] =
                    std::array::from_fn(|c| 1.0 / (row[c] - i0[c]).abs().max(1.0));
                for c in 0..PATCH {
                    su[c] += weight[c] * u[0];
                }
                for c in 0..PATCH {
                    sv[c] += weight[c] * u[1];
                }
                for c in 0..PATCH {
                    sw[c] += weight[c];
                }
            }
        }
        // Where no patch reached, the sums are zero and so is the flow.
        self.dense.clear();
        self.dense
            .extend(
                self.sum_u
                    .iter()
                    .zip(&self.sum_v)
                    .zip(&self.sum_w)
                    .map(|((&a, &b), &wt)| {
                        let r = 1.0 / wt.max(f32::MIN_POSITIVE);
                        [a * r, b * r]
                    }),
            );
    }
}

/// Patch positions along a side of `n` pixels: `0, stride, ...` and the last against the
/// border.
fn grid(n: usize, patch: usize, stride: usize) -> Vec<usize> {
    if n < patch {
        return Vec::new();
    }
    let last = n - patch;
    let mut v: Vec<usize> = (0..=last).step_by(stride.max(1)).collect();
    if v.last() != Some(&last) {
        v.push(last);
    }
    v
}

/// The inverse of the patch's Hessian of mean-normalised gradients, `None` where it is
/// (nearly) singular: a flat patch, or an edge with no texture along it.
fn hessian_inverse(l0: &Level, x: usize, y: usize) -> Option<[f32; 3]> {
    let n = N as f32;
    let mut lanes = [[0f32; PATCH]; 5];
    for r in 0..PATCH {
        let at = (y + r) * l0.w + x;
        let (gxs, gys) = (&l0.gx[at..at + PATCH], &l0.gy[at..at + PATCH]);
        for c in 0..PATCH {
            let (gx, gy) = (gxs[c], gys[c]);
            lanes[0][c] += gx;
            lanes[1][c] += gy;
            lanes[2][c] += gx * gx;
            lanes[3][c] += gx * gy;
            lanes[4][c] += gy * gy;
        }
    }
    let [sx, sy, sxx, sxy, syy] = lanes.map(|l| l.iter().sum::<f32>());
    let (mx, my) = (sx / n, sy / n);
    let a = sxx - n * mx * mx;
    let b = sxy - n * mx * my;
    let c = syy - n * my * my;
    let det = a * c - b * b;
    // Texture of less than about a tenth of a level per pixel in the weaker direction.
    let floor = 0.01 * n;
    if !(det.is_finite() && det > floor * (a + c).max(floor)) {
        return None;
    }
    Some([c / det, -b / det, a / det])
}

impl PatchBuffers {
    /// The template at `(x, y)` of `l0`: its values and gradients minus their means.
    fn load(&mut self, l0: &Level, x: usize, y: usize) {
        for r in 0..PATCH {
            let at = (y + r) * l0.w + x;
            let span = r * PATCH..(r + 1) * PATCH;
            self.t[span.clone()].copy_from_slice(&l0.img[at..at + PATCH]);
            self.jx[span.clone()].copy_from_slice(&l0.gx[at..at + PATCH]);
            self.jy[span].copy_from_slice(&l0.gy[at..at + PATCH]);
        }
        for v in [&mut self.t, &mut self.jx, &mut self.jy] {
            let mean = lane_sum(v) / N as f32;
            v.iter_mut().for_each(|e| *e -= mean);
        }
    }

    /// The mean-normalised SSD at flow `u` and the Gauss-Newton right-hand side `J^T r`.
    fn step(&self, l1: &Level, x: usize, y: usize, u: [f32; 2]) -> (f32, [f32; 2]) {
        let mut warped = [0f32; N];
        Taps::new(l1, x, y, u).patch(l1, &mut warped);
        let mean = lane_sum(&warped) / N as f32;
        let (mut ssd, mut bx, mut by) = ([0f32; PATCH], [0f32; PATCH], [0f32; PATCH]);
        // Lane by lane over the rows: eight independent sums, which the compiler keeps in
        // vector registers.
        for r in 0..PATCH {
            for c in 0..PATCH {
                let i = r * PATCH + c;
                let e = warped[i] - mean - self.t[i];
                ssd[c] += e * e;
                bx[c] += self.jx[i] * e;
                by[c] += self.jy[i] * e;
            }
        }
        let sum = |v: [f32; PATCH]| v.iter().sum::<f32>();
        (sum(ssd), [sum(bx), sum(by)])
    }
}

/// The sum of a patch's values, column by column first: eight independent sums (a vector
/// register's worth) where one running sum would wait on every addition.
#[inline(always)]
fn lane_sum(v: &[f32; N]) -> f32 {
    let mut lanes = [0f32; PATCH];
    for row in v.chunks_exact(PATCH) {
        for (l, &x) in lanes.iter_mut().zip(row) {
            *l += x;
        }
    }
    lanes.iter().sum()
}

/// Keeps a patch moved by `u` within a patch of the level's border (and finite).
fn clamp_flow(u: [f32; 2], x: usize, y: usize, l: &Level) -> [f32; 2] {
    let p = PATCH as f32;
    let lo = |pos: usize| -(pos as f32) - p;
    let hi = |pos: usize, n: usize| (n as f32) - (pos as f32);
    let cx = if u[0].is_nan() { 0.0 } else { u[0] };
    let cy = if u[1].is_nan() { 0.0 } else { u[1] };
    [cx.clamp(lo(x), hi(x, l.w)), cy.clamp(lo(y), hi(y, l.h))]
}

/// Where a patch moved by `u` samples a level: one integer offset and one pair of bilinear
/// weights for all its pixels.
struct Taps {
    x0: isize,
    y0: isize,
    fx: f32,
    fy: f32,
    /// The whole footprint (with the right and lower neighbours) is inside the level.
    inside: bool,
}

impl Taps {
    fn new(l: &Level, x: usize, y: usize, u: [f32; 2]) -> Self {
        let (px, py) = (x as f32 + u[0], y as f32 + u[1]);
        // The floor without a libm call (the flow is finite and within a level's reach).
        let floor = |v: f32| {
            let t = v as isize;
            t - isize::from((t as f32) > v)
        };
        let (x0, y0) = (floor(px), floor(py));
        let (fx0, fy0) = (x0 as f32, y0 as f32);
        let inside = x0 >= 0
            && y0 >= 0
            && x0 + (PATCH as isize) < l.w as isize
            && y0 + (PATCH as isize) < l.h as isize;
        Taps {
            x0,
            y0,
            fx: px - fx0,
            fy: py - fy0,
            inside,
        }
    }

    /// The whole moved patch into `out`, row-major. Inside the level, separably: each of
    /// the nine image rows it reads blended along the row once, then each pair of those
    /// between the rows (fewer operations than four taps a pixel, on neighbouring values).
    #[inline(always)]
    fn patch(&self, l: &Level, out: &mut [f32; N]) {
        if !self.inside {
            for (r, row) in out.chunks_exact_mut(PATCH).enumerate() {
                let row: &mut [f32; PATCH] = row.try_into().expect("a patch row");
                self.row(l, r, row);
            }
            return;
        }
        let (fx, fy) = (self.fx, self.fy);
        let along = |r: usize| -> [f32; PATCH] {
            let at = (self.y0 as usize + r) * l.w + self.x0 as usize;
            let src: &[f32; PATCH + 1] = l.img[at..at + PATCH + 1].try_into().expect("a row");
            std::array::from_fn(|c| src[c] + fx * (src[c + 1] - src[c]))
        };
        let mut above = along(0);
        for (r, row) in out.chunks_exact_mut(PATCH).enumerate() {
            let below = along(r + 1);
            for c in 0..PATCH {
                row[c] = above[c] + fy * (below[c] - above[c]);
            }
            above = below;
        }
    }

    /// Row `r` of the moved patch into `out`.
    #[inline(always)]
    fn row(&self, l: &Level, r: usize, out: &mut [f32; PATCH]) {
        let (fx, fy) = (self.fx, self.fy);
        let (a, b, c, d) = (
            (1.0 - fx) * (1.0 - fy),
            fx * (1.0 - fy),
            (1.0 - fx) * fy,
            fx * fy,
        );
        let y = self.y0 + r as isize;
        if self.inside {
            let at = y as usize * l.w + self.x0 as usize;
            let top: &[f32; PATCH + 1] = l.img[at..at + PATCH + 1].try_into().expect("a row");
            let bot: &[f32; PATCH + 1] = l.img[at + l.w..at + l.w + PATCH + 1]
                .try_into()
                .expect("a row");
            for c0 in 0..PATCH {
                out[c0] = a * top[c0] + b * top[c0 + 1] + c * bot[c0] + d * bot[c0 + 1];
            }
        } else {
            let (wm, hm) = (l.w as isize - 1, l.h as isize - 1);
            let yt = y.clamp(0, hm) as usize;
            let yb = (y + 1).clamp(0, hm) as usize;
            for (c0, o) in out.iter_mut().enumerate() {
                let xl = (self.x0 + c0 as isize).clamp(0, wm) as usize;
                let xr = (self.x0 + c0 as isize + 1).clamp(0, wm) as usize;
                let at = |yy: usize, xx: usize| l.img[yy * l.w + xx];
                *o = a * at(yt, xl) + b * at(yt, xr) + c * at(yb, xl) + d * at(yb, xr);
            }
        }
    }
}

/// Bilinear sample of a `w x h` flow at `(x, y)`, the border repeated.
fn bilinear2(f: &[[f32; 2]], w: usize, h: usize, x: f32, y: f32) -> [f32; 2] {
    if f.len() < w * h || w == 0 || h == 0 {
        return [0.0; 2];
    }
    let x = x.clamp(0.0, (w - 1) as f32);
    let y = y.clamp(0.0, (h - 1) as f32);
    let (xi, yi) = (x as usize, y as usize);
    let (ax, ay) = (x - xi as f32, y - yi as f32);
    let (xj, yj) = ((xi + 1).min(w - 1), (yi + 1).min(h - 1));
    let mut out = [0f32; 2];
    for (k, o) in out.iter_mut().enumerate() {
        let top = f[yi * w + xi][k] * (1.0 - ax) + f[yi * w + xj][k] * ax;
        let bot = f[yj * w + xi][k] * (1.0 - ax) + f[yj * w + xj][k] * ax;
        *o = top * (1.0 - ay) + bot * ay;
    }
    out
}

/// The finest level's flow (`level`'s size, level `s`) to the `w x h` frame, scaled to its
/// pixels, on `region`'s tiles (all of the frame without one): bilinear, the border repeated,
/// rows first (a level row blended from two, on vectors), then along the row.
#[inline(never)]
fn upsample(
    flow: &[[f32; 2]],
    level: &Level,
    s: usize,
    w: usize,
    h: usize,
    region: Option<&Region>,
    out: &mut [[f32; 2]],
) {
    let k = (1usize << s) as f32;
    let (lw, lh) = (level.w, level.h);
    if flow.len() < lw * lh || lw == 0 || lh == 0 {
        return;
    }
    // Where each frame position falls between two level pixels: the first and its weight.
    let taps = |n: usize, ln: usize| -> Vec<(usize, usize, f32)> {
        (0..n)
            .map(|x| {
                let lx = ((x as f32 + 0.5) / k - 0.5).clamp(0.0, (ln - 1) as f32);
                let i = lx as usize;
                (i, (i + 1).min(ln - 1), lx - i as f32)
            })
            .collect()
    };
    let (cols, rows) = (taps(w, lw), taps(h, lh));
    let mut line = vec![0f32; 2 * lw];
    let mut padded: Vec<[f32; 2]> = Vec::with_capacity(lw + 2);
    let mut spans: Vec<std::ops::Range<usize>> = Vec::new();
    let flat = flow.as_flattened();
    for (y, out_row) in out.chunks_exact_mut(w).enumerate().take(h) {
        spans.clear();
        match region {
            Some(r) => spans.extend(r.row_spans(y, w)),
            None => spans.push(0..w),
        }
        if spans.is_empty() {
            continue;
        }
        let (j0, j1, fy) = rows[y];
        let (top, bot) = (
            &flat[2 * j0 * lw..2 * (j0 + 1) * lw],
            &flat[2 * j1 * lw..2 * (j1 + 1) * lw],
        );
        for ((l, &a), &b) in line.iter_mut().zip(top).zip(bot) {
            *l = (a + (b - a) * fy) * k;
        }
        if s == 1 && w.div_ceil(2) == lw {
            // Twice the level's size: pixel `2i` is `(line[i - 1] + 3 line[i]) / 4`, pixel
            // `2i + 1` is `(3 line[i] + line[i + 1]) / 4` (the border repeated: `padded` has
            // one more value at either end), the same values as the taps give.
            padded.clear();
            padded.push([line[0], line[1]]);
            padded.extend(line.chunks_exact(2).map(|p| [p[0], p[1]]));
            padded.push(padded[lw]);
            for span in spans.iter().cloned() {
                for x in span {
                    let i = x / 2;
                    let (near, far) = (padded[i + 1], padded[i + 2 * (x % 2)]);
                    out_row[x] = [
                        0.75 * near[0] + 0.25 * far[0],
                        0.75 * near[1] + 0.25 * far[1],
                    ];
                }
            }
            continue;
        }
        for span in spans.iter().cloned() {
            for (o, &(i0, i1, fx)) in out_row[span.clone()].iter_mut().zip(&cols[span]) {
                let (u0, v0) = (line[2 * i0], line[2 * i0 + 1]);
                let (u1, v1) = (line[2 * i1], line[2 * i1 + 1]);
                *o = [u0 + (u1 - u0) * fx, v0 + (v1 - v0) * fx];
            }
        }
    }
}
