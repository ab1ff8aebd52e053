//! Dense optical flow between two gray frames, for the pixel model's motion
//! ([`crate::stage1::motion`]).
//!
//! The default backend is the project's own Dense Inverse Search ([`dis`]; Kroeger et al.,
//! "Fast Optical Flow using Dense Inverse Search", ECCV 2016), pure Rust, on the frames'
//! [`Pyramid`]s (built once per frame and shared by both flows and both intervals a frame
//! belongs to) and, given a [`Region`], only on the tiles where something moves. OpenCV's DIS
//! is kept as a cross-check (`flow_backend = "opencv"`, in a build with the `opencv-flow`
//! cargo feature, off by default; [`opencv`]).
//!
//! The flow of a pixel `p` of the first frame says where it went in the second: the content at
//! `p` in `from` is at `p + flow(p)` in `to`, in pixels.

pub mod dis;
#[cfg(feature = "opencv-flow")]
pub mod opencv;
pub mod pyramid;

use serde::{Deserialize, Serialize};

pub use pyramid::Pyramid;

use crate::error::{Error, Result};

/// The flow's speed/quality presets, each about twice the cost of the one before it
/// (docs/physics.md has the numbers measured here).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum FlowPreset {
    /// 8 px patches 4 apart searched down to a quarter of the resolution, 12 iterations (DIS's
    /// `ULTRAFAST`).
    Ultrafast,
    /// 8 px patches 6 apart down to half the resolution, 12 iterations: on the davis346
    /// clip the events of patches 4 apart (TF1 0.673 either way) at about half the cost.
    #[default]
    Fast,
    /// 8 px patches 3 apart down to half the resolution, 25 iterations (DIS's `MEDIUM`
    /// search, without its variational refinement).
    Medium,
}

impl FlowPreset {
    /// The name as configs and flags spell it.
    pub fn name(self) -> &'static str {
        match self {
            FlowPreset::Ultrafast => "ultrafast",
            FlowPreset::Fast => "fast",
            FlowPreset::Medium => "medium",
        }
    }

    /// The preset's parameters for the project's DIS.
    pub fn params(self) -> dis::Params {
        let base = dis::Params {
            stride: 6,
            iterations: 12,
            finest: 1,
            propagate: true,
        };
        match self {
            FlowPreset::Ultrafast => dis::Params {
                stride: 4,
                finest: 2,
                ..base
            },
            FlowPreset::Fast => base,
            FlowPreset::Medium => dis::Params {
                stride: 3,
                iterations: 25,
                ..base
            },
        }
    }
}

/// Which implementation computes the flow.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum FlowBackend {
    /// The project's own DIS (pure Rust, only where the scene moves).
    #[default]
    Dis,
    /// OpenCV's DIS on the whole frame, for comparison: needs a build with the `opencv-flow`
    /// feature (and the system's OpenCV).
    Opencv,
}

impl FlowBackend {
    /// The name as configs and flags spell it.
    pub fn name(self) -> &'static str {
        match self {
            FlowBackend::Dis => "dis",
            FlowBackend::Opencv => "opencv",
        }
    }
}

/// Where the flow is wanted: a mask of square tiles over a frame. Queries take rectangles
/// in frame pixels, answered from a summed-area table of the mask.
#[derive(Debug, Clone, Default)]
pub struct Region {
    tile: usize,
    tiles_x: usize,
    tiles_y: usize,
    active: Vec<bool>,
    /// `sum[(j) * (tiles_x + 1) + i]`: active tiles in columns `< i` of rows `< j`.
    sum: Vec<u32>,
}

impl Region {
    /// A region of `tile`-pixel tiles, `tiles_x` across, from `active` (row-major, one per
    /// tile).
    pub fn new(tile: usize, tiles_x: usize, active: &[bool]) -> Self {
        let tile = tile.max(1);
        let tiles_x = tiles_x.max(1);
        let tiles_y = active.len() / tiles_x;
        let mut sum = vec![0u32; (tiles_x + 1) * (tiles_y + 1)];
        for j in 0..tiles_y {
            let mut row = 0u32;
            for i in 0..tiles_x {
                row += u32::from(active[j * tiles_x + i]);
                sum[(j + 1) * (tiles_x + 1) + i + 1] = sum[j * (tiles_x + 1) + i + 1] + row;
            }
        }
        Region {
            tile,
            tiles_x,
            tiles_y,
            active: active[..tiles_x * tiles_y].to_vec(),
            sum,
        }
    }

    /// Active tiles.
    pub fn count(&self) -> usize {
        self.sum.last().map_or(0, |&n| n as usize)
    }

    /// Whether some active tile meets the pixels `[x0, x1) x [y0, y1)` (clipped to the tiles).
    pub fn any(&self, x0: isize, y0: isize, x1: isize, y1: isize) -> bool {
        let t = self.tile as isize;
        let clip = |v: isize, n: usize| v.clamp(0, n as isize) as usize;
        let (i0, j0) = (
            clip(x0.div_euclid(t), self.tiles_x),
            clip(y0.div_euclid(t), self.tiles_y),
        );
        let (i1, j1) = (
            clip((x1 + t - 1).div_euclid(t), self.tiles_x),
            clip((y1 + t - 1).div_euclid(t), self.tiles_y),
        );
        if i0 >= i1 || j0 >= j1 {
            return false;
        }
        let s = |i: usize, j: usize| self.sum[j * (self.tiles_x + 1) + i];
        s(i1, j1) + s(i0, j0) > s(i0, j1) + s(i1, j0)
    }

    /// The runs of active tiles on pixel row `y`, as column ranges within `0..w`.
    pub fn row_spans(
        &self,
        y: usize,
        w: usize,
    ) -> impl Iterator<Item = std::ops::Range<usize>> + '_ {
        let j = y / self.tile;
        let row = if j < self.tiles_y {
            &self.active[j * self.tiles_x..(j + 1) * self.tiles_x]
        } else {
            &[]
        };
        let mut i = 0;
        std::iter::from_fn(move || {
            while i < row.len() {
                if !row[i] {
                    i += 1;
                    continue;
                }
                let run = row[i..].iter().take_while(|&&a| a).count();
                let (a, b) = ((i * self.tile).min(w), ((i + run) * self.tile).min(w));
                i += run;
                if a < b {
                    return Some(a..b);
                }
            }
            None
        })
    }

    /// The region the motion model computes the flow on: the `tile`-pixel tiles of two gray
    /// frames (`w` wide) where some pixel changed by `levels` or more, and every neighbour of
    /// those (what moved out of a changed tile lands in one: it changed both where it was and
    /// where it went). Also returns how many pixels changed.
    pub fn around_changes(
        g0: &[u8],
        g1: &[u8],
        w: usize,
        tile: usize,
        levels: u8,
    ) -> (Self, usize) {
        let tile = tile.max(1);
        let w = w.max(1);
        let h = g0.len().min(g1.len()) / w;
        let (tiles_x, tiles_y) = (w.div_ceil(tile), h.div_ceil(tile));
        let mut changed_tiles = vec![false; tiles_x * tiles_y];
        let mut changed = 0;
        for (y, (r0, r1)) in g0.chunks_exact(w).zip(g1.chunks_exact(w)).enumerate() {
            let tiles = &mut changed_tiles[(y / tile) * tiles_x..][..tiles_x];
            for (t, (c0, c1)) in tiles.iter_mut().zip(r0.chunks(tile).zip(r1.chunks(tile))) {
                let n = c0
                    .iter()
                    .zip(c1)
                    .filter(|(&a, &b)| a.abs_diff(b) >= levels)
                    .count();
                changed += n;
                *t |= n > 0;
            }
        }
        let mut grown = vec![false; changed_tiles.len()];
        for j in 0..tiles_y {
            for i in 0..tiles_x {
                if changed_tiles[j * tiles_x + i] {
                    for y in j.saturating_sub(1)..(j + 2).min(tiles_y) {
                        grown
                            [y * tiles_x + i.saturating_sub(1)..y * tiles_x + (i + 2).min(tiles_x)]
                            .fill(true);
                    }
                }
            }
        }
        (Region::new(tile, tiles_x, &grown), changed)
    }

    /// Pixels of a `w x h` frame on the region's tiles.
    pub fn pixels(&self, w: usize, h: usize) -> usize {
        (0..h)
            .map(|y| self.row_spans(y, w).map(|s| s.len()).sum::<usize>())
            .sum()
    }
}

/// One flow estimator, kept across frames (it holds its buffers).
pub struct DenseFlow {
    width: usize,
    height: usize,
    engine: Engine,
}

enum Engine {
    Dis(Box<dis::Dis>),
    #[cfg(feature = "opencv-flow")]
    Opencv(opencv::OpencvFlow),
}

impl DenseFlow {
    /// An estimator for `width x height` frames. Fails for the OpenCV backend in a build
    /// without the `opencv-flow` feature, or when OpenCV cannot make one.
    pub fn new(backend: FlowBackend, preset: FlowPreset, width: u16, height: u16) -> Result<Self> {
        let engine = match backend {
            FlowBackend::Dis => Engine::Dis(Box::new(dis::Dis::new(preset.params()))),
            #[cfg(feature = "opencv-flow")]
            FlowBackend::Opencv => Engine::Opencv(opencv::OpencvFlow::new(preset)?),
            #[cfg(not(feature = "opencv-flow"))]
            FlowBackend::Opencv => {
                return Err(Error::invalid(
                    "flow_backend",
                    "\"opencv\" needs a build with the `opencv-flow` cargo feature (and the \
                     system's OpenCV); the default, \"dis\", needs neither",
                ))
            }
        };
        Ok(DenseFlow {
            width: width.into(),
            height: height.into(),
            engine,
        })
    }

    /// The pyramid levels [`DenseFlow::compute_on`] reads (first, last), to be built with
    /// [`Pyramid::ensure`]; `None` where the backend reads only the gray frames (OpenCV) or
    /// the frame is too small for a patch (then the flow fails).
    pub fn levels(&self) -> Option<(usize, usize)> {
        match &self.engine {
            Engine::Dis(d) => d.levels(self.width, self.height).ok(),
            #[cfg(feature = "opencv-flow")]
            Engine::Opencv(_) => None,
        }
    }

    /// The flow from `p0`'s frame to `p1`'s into `out`, one `[dx, dy]` per pixel: on
    /// `region`'s tiles, zero elsewhere, where the backend can restrict it (the project's DIS;
    /// OpenCV's computes the whole frame). Values are finite (non-finite ones set to zero).
    pub fn compute_on(
        &mut self,
        p0: &Pyramid,
        p1: &Pyramid,
        region: Option<&Region>,
        out: &mut Vec<[f32; 2]>,
    ) -> Result<()> {
        let n = self.width * self.height;
        for p in [p0, p1] {
            if p.gray().len() != n || p.width() != self.width {
                return Err(Error::invalid(
                    "flow",
                    format!(
                        "a frame of {} x {} for a {} x {} estimator",
                        p.width(),
                        p.height(),
                        self.width,
                        self.height
                    ),
                ));
            }
        }
        match &mut self.engine {
            Engine::Dis(d) => d.compute(p0, p1, region, out)?,
            #[cfg(feature = "opencv-flow")]
            Engine::Opencv(cv) => cv.compute(p0.gray(), p1.gray(), self.width, self.height, out)?,
        }
        for v in out.iter_mut() {
            if !(v[0].is_finite() && v[1].is_finite()) {
                *v = [0.0; 2];
            }
        }
        Ok(())
    }

    /// The flow from `from` to `to` (row-major gray, `width x height` each) over the whole
    /// frame into `out`: builds both pyramids (for callers that hold gray frames only).
    pub fn compute(&mut self, from: &[u8], to: &[u8], out: &mut Vec<[f32; 2]>) -> Result<()> {
        let n = self.width * self.height;
        if from.len() != n || to.len() != n {
            return Err(Error::invalid(
                "flow",
                format!(
                    "frames of {} and {} values for {} x {}",
                    from.len(),
                    to.len(),
                    self.width,
                    self.height
                ),
            ));
        }
        let (mut p0, mut p1) = (Pyramid::new(), Pyramid::new());
        p0.set(self.width, self.height, |g| g.extend_from_slice(from));
        p1.set(self.width, self.height, |g| g.extend_from_slice(to));
        if let Some((first, last)) = self.levels() {
            p0.ensure(first, last);
            p1.ensure(first, last);
        }
        self.compute_on(&p0, &p1, None, out)
    }
}

/// Memory a forward and a backward estimator take per pixel of the frame with `backend`,
/// beyond the flows they write: for the project's DIS, the pyramids of three frames (the
/// interval's two and the next one's, built while looking ahead) and each estimator's
/// per-level buffers (dense flows and sums, on a quarter of a frame's pixels and less); for
/// OpenCV, its pyramids and buffers (48 bytes per direction, an estimate from DIS's per-level
/// images at half resolution and below).
pub fn bytes_per_pixel(backend: FlowBackend) -> u64 {
    match backend {
        FlowBackend::Dis => 3 * Pyramid::BYTES_PER_PIXEL + 2 * 8,
        FlowBackend::Opencv => 2 * 48,
    }
}

#[cfg(test)]
mod tests;
