//! Running the network only on the regions that changed.
//!
//! The network is fully convolutional, so its output at a pixel depends only on the input
//! within its receptive field ([`crate::model::v2ce_net::Architecture::receptive_field`]: 155
//! pixels before and 140 after for the V2CE topology, whatever its width). A window's active
//! tiles ([`super::activity`], the union over the intervals it keeps) are grouped into
//! connected regions; each region is grown by the margin, snapped outwards to the alignment
//! (16 pixels for four encoders) and clipped to the frame; crops that overlap, or whose
//! bounding box costs no more than the two, are merged. The network runs on each crop, and a
//! crop's outputs are kept only for the active tiles inside its *trusted* part: the crop less
//! the margin on every side that is not the frame's edge.
//!
//! With the model's own margin the kept outputs are the whole frame's (the crop's zero padding
//! lies outside every kept pixel's receptive field, and the crop's scales fall on the frame's
//! grids); up to the floating-point order of ONNX Runtime's kernels, measured identical in
//! `tests/learned.rs`. A smaller margin (`roi_margin`) trades that exactness for speed.

use super::activity::TILE;

/// A rectangle of pixels, half-open: columns `x0..x1`, rows `y0..y1`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rect {
    /// First column.
    pub x0: usize,
    /// First row.
    pub y0: usize,
    /// One past the last column.
    pub x1: usize,
    /// One past the last row.
    pub y1: usize,
}

impl Rect {
    /// The whole `width x height` frame.
    pub fn full((width, height): (usize, usize)) -> Self {
        Rect {
            x0: 0,
            y0: 0,
            x1: width,
            y1: height,
        }
    }

    /// Columns.
    pub fn width(&self) -> usize {
        self.x1 - self.x0
    }

    /// Rows.
    pub fn height(&self) -> usize {
        self.y1 - self.y0
    }

    /// Pixels.
    pub fn area(&self) -> usize {
        self.width() * self.height()
    }

    /// The smallest rectangle holding both.
    pub fn union(&self, o: &Rect) -> Rect {
        Rect {
            x0: self.x0.min(o.x0),
            y0: self.y0.min(o.y0),
            x1: self.x1.max(o.x1),
            y1: self.y1.max(o.y1),
        }
    }

    /// Whether they share a pixel.
    pub fn intersects(&self, o: &Rect) -> bool {
        self.x0 < o.x1 && o.x0 < self.x1 && self.y0 < o.y1 && o.y0 < self.y1
    }

    /// Whether `o` lies inside.
    pub fn contains(&self, o: &Rect) -> bool {
        self.x0 <= o.x0 && o.x1 <= self.x1 && self.y0 <= o.y0 && o.y1 <= self.y1
    }
}

/// How far crops reach beyond what they keep.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Margin {
    /// Pixels before (left of, above) a kept region.
    pub before: usize,
    /// Pixels after (right of, below) it.
    pub after: usize,
    /// Crops start at multiples of this.
    pub align: usize,
}

/// One network run: the crop, and the tiles of it whose outputs are kept.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Crop {
    /// The pixels fed to the network.
    pub rect: Rect,
    /// The tiles kept (each inside the crop's trusted part).
    pub keep: Vec<Rect>,
}

/// The crops for the active tiles `active` (`tiles.0 x tiles.1` tiles of [`TILE`] pixels,
/// row-major) of a `size = (width, height)` frame. Empty when no tile is active.
pub fn plan(active: &[bool], tiles: (usize, usize), size: (usize, usize), m: Margin) -> Vec<Crop> {
    let (tx, ty) = tiles;
    let (w, h) = size;
    let align = m.align.max(1);
    let tile_rect = |i: usize| {
        let (x, y) = (i % tx, i / tx);
        Rect {
            x0: x * TILE,
            y0: y * TILE,
            x1: ((x + 1) * TILE).min(w),
            y1: ((y + 1) * TILE).min(h),
        }
    };
    let grow = |r: Rect| Rect {
        x0: r.x0.saturating_sub(m.before) / align * align,
        y0: r.y0.saturating_sub(m.before) / align * align,
        x1: (r.x1 + m.after)
            .div_ceil(align)
            .saturating_mul(align)
            .min(w),
        y1: (r.y1 + m.after)
            .div_ceil(align)
            .saturating_mul(align)
            .min(h),
    };
    // Connected regions of active tiles (8-neighbours), as bounding boxes with their tiles.
    let mut seen = vec![false; active.len()];
    let mut regions: Vec<(Rect, Vec<usize>)> = Vec::new();
    for start in 0..active.len().min(tx * ty) {
        if !active[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        let mut stack = vec![start];
        let mut members = Vec::new();
        let mut bbox = tile_rect(start);
        while let Some(i) = stack.pop() {
            members.push(i);
            bbox = bbox.union(&tile_rect(i));
            let (x, y) = ((i % tx) as isize, (i / tx) as isize);
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (nx, ny) = (x + dx, y + dy);
                    if nx < 0 || ny < 0 || nx >= tx as isize || ny >= ty as isize {
                        continue;
                    }
                    let j = ny as usize * tx + nx as usize;
                    if active[j] && !seen[j] {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        regions.push((grow(bbox), members));
    }
    // Merge crops that overlap or cost no more together, until none does.
    loop {
        let mut merged = false;
        'pairs: for i in 0..regions.len() {
            for j in i + 1..regions.len() {
                let (a, b) = (regions[i].0, regions[j].0);
                let u = a.union(&b);
                if a.intersects(&b) || u.area() <= a.area() + b.area() {
                    let (_, tiles_b) = regions.swap_remove(j);
                    regions[i].0 = u;
                    regions[i].1.extend(tiles_b);
                    merged = true;
                    break 'pairs;
                }
            }
        }
        if !merged {
            break;
        }
    }
    regions
        .into_iter()
        .map(|(rect, members)| {
            let mut keep: Vec<Rect> = members.into_iter().map(tile_rect).collect();
            keep.sort_by_key(|r| (r.y0, r.x0));
            Crop { rect, keep }
        })
        .collect()
}

/// The part of `crop` (of a `size` frame) whose outputs equal the whole frame's: the crop less
/// the margin on each side that is not the frame's edge.
pub fn trusted(crop: &Rect, size: (usize, usize), m: Margin) -> Rect {
    let inner = |lo: usize, hi: usize, end: usize| {
        let a = if lo == 0 { 0 } else { lo + m.before };
        let b = if hi == end {
            end
        } else {
            hi.saturating_sub(m.after)
        };
        (a, b.max(a))
    };
    let (x0, x1) = inner(crop.x0, crop.x1, size.0);
    let (y0, y1) = inner(crop.y0, crop.y1, size.1);
    Rect { x0, y0, x1, y1 }
}

#[cfg(test)]
mod tests {
    use super::*;

    const M: Margin = Margin {
        before: 40,
        after: 30,
        align: 16,
    };

    fn grid(tiles: (usize, usize), on: &[(usize, usize)]) -> Vec<bool> {
        let mut g = vec![false; tiles.0 * tiles.1];
        for &(x, y) in on {
            g[y * tiles.0 + x] = true;
        }
        g
    }

    #[test]
    fn nothing_active_runs_nothing() {
        assert!(plan(&grid((8, 6), &[]), (8, 6), (128, 96), M).is_empty());
    }

    #[test]
    fn a_tile_is_grown_aligned_and_clipped_and_trusted_where_kept() {
        // 40 x 30 tiles of a 640 x 480 frame; tile (10, 10) = pixels 160..176.
        let size = (640, 480);
        let crops = plan(&grid((40, 30), &[(10, 10)]), (40, 30), size, M);
        assert_eq!(crops.len(), 1);
        let c = &crops[0];
        // 160 - 40 = 120 -> 112 (aligned); 176 + 30 = 206 -> 208.
        assert_eq!(
            c.rect,
            Rect {
                x0: 112,
                y0: 112,
                x1: 208,
                y1: 208
            }
        );
        assert_eq!(
            c.keep,
            vec![Rect {
                x0: 160,
                y0: 160,
                x1: 176,
                y1: 176
            }]
        );
        let t = trusted(&c.rect, size, M);
        assert!(t.contains(&c.keep[0]), "{t:?}");
        // At the frame's corner the crop stops at the edge, which it trusts.
        let crops = plan(&grid((40, 30), &[(0, 0)]), (40, 30), size, M);
        assert_eq!(
            crops[0].rect,
            Rect {
                x0: 0,
                y0: 0,
                x1: 48,
                y1: 48
            }
        );
        assert_eq!(trusted(&crops[0].rect, size, M).x0, 0);
    }

    #[test]
    fn far_regions_run_apart_and_near_ones_together() {
        let size = (640, 480);
        let far = plan(&grid((40, 30), &[(2, 2), (35, 25)]), (40, 30), size, M);
        assert_eq!(far.len(), 2);
        let near = plan(&grid((40, 30), &[(10, 10), (13, 10)]), (40, 30), size, M);
        assert_eq!(near.len(), 1);
        assert_eq!(near[0].keep.len(), 2);
        // Every kept tile lies in its crop's trusted part, and crops do not overlap.
        for crops in [&far, &near] {
            for c in crops.iter() {
                let t = trusted(&c.rect, size, M);
                assert!(c.keep.iter().all(|k| t.contains(k)));
                assert_eq!(c.rect.x0 % 16, 0);
                assert_eq!(c.rect.y0 % 16, 0);
            }
            for (i, a) in crops.iter().enumerate() {
                for b in &crops[i + 1..] {
                    assert!(!a.rect.intersects(&b.rect));
                }
            }
        }
    }

    #[test]
    fn a_ragged_frame_edge_is_kept() {
        // 346 x 260: the last tiles are 10 and 4 pixels; the crop ends at the frame.
        let size = (346, 260);
        let crops = plan(&grid((22, 17), &[(21, 16)]), (22, 17), size, M);
        assert_eq!(crops[0].rect.x1, 346);
        assert_eq!(crops[0].rect.y1, 260);
        assert_eq!(
            crops[0].keep,
            vec![Rect {
                x0: 336,
                y0: 256,
                x1: 346,
                y1: 260
            }]
        );
        let t = trusted(&crops[0].rect, size, M);
        assert!(t.contains(&crops[0].keep[0]));
    }
}
