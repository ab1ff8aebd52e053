//! Where the scene moves: the learned tier's outputs are kept only where a frame pair changed.
//!
//! A DVS pixel whose light does not change fires nothing but noise, and the network's output
//! there (small values it has no reason to emit, or worse on inputs unlike its training data:
//! black or saturated frames, a still scene) would become events. For each frame pair, the
//! output frame is cut into `TILE x TILE` tiles; a tile is active when any of its pixels moved
//! by more than the threshold between the pair's two frames, and the active set is grown by a
//! margin of whole tiles (motion just outside a tile reaches into it). Outputs of inactive
//! tiles are zero; a window with no active tile anywhere is not run at all.

/// Side of an activity tile, pixels.
pub const TILE: usize = 16;

/// Active tiles of one frame pair.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Activity {
    tiles_x: usize,
    tiles_y: usize,
    active: Vec<bool>,
}

impl Activity {
    /// The tiles of an `out_w x out_h` output where planes `a` and `b` (row stride
    /// `plane_w`, output column `x` at plane column `x + offset_x`) differ by more than
    /// `threshold` at some pixel, grown by `margin` tiles.
    pub fn of_pair(
        a: &[f32],
        b: &[f32],
        plane_w: usize,
        offset_x: usize,
        (out_w, out_h): (usize, usize),
        threshold: f32,
        margin: usize,
    ) -> Self {
        let (tiles_x, tiles_y) = (out_w.div_ceil(TILE), out_h.div_ceil(TILE));
        let mut moved = vec![false; tiles_x * tiles_y];
        for y in 0..out_h {
            let row = y * plane_w + offset_x;
            let (ra, rb) = (&a[row..row + out_w], &b[row..row + out_w]);
            let ty = y / TILE;
            for tx in 0..tiles_x {
                let t = ty * tiles_x + tx;
                if moved[t] {
                    continue;
                }
                let (x0, x1) = (tx * TILE, ((tx + 1) * TILE).min(out_w));
                moved[t] = ra[x0..x1]
                    .iter()
                    .zip(&rb[x0..x1])
                    .any(|(p, q)| (p - q).abs() > threshold || p.is_nan() != q.is_nan());
            }
        }
        let mut active = vec![false; moved.len()];
        let m = margin as isize;
        for ty in 0..tiles_y {
            for tx in 0..tiles_x {
                if !moved[ty * tiles_x + tx] {
                    continue;
                }
                for dy in -m..=m {
                    for dx in -m..=m {
                        let (x, y) = (tx as isize + dx, ty as isize + dy);
                        if x >= 0 && y >= 0 && (x as usize) < tiles_x && (y as usize) < tiles_y {
                            active[y as usize * tiles_x + x as usize] = true;
                        }
                    }
                }
            }
        }
        Activity {
            tiles_x,
            tiles_y,
            active,
        }
    }

    /// Tiles across and down.
    pub fn tiles(&self) -> (usize, usize) {
        (self.tiles_x, self.tiles_y)
    }

    /// Whether each tile is active, row-major.
    pub fn active(&self) -> &[bool] {
        &self.active
    }

    /// Whether any tile is active.
    pub fn any(&self) -> bool {
        self.active.iter().any(|&a| a)
    }

    /// Tiles that are not active.
    pub fn inactive(&self) -> usize {
        self.active.iter().filter(|&&a| !a).count()
    }

    /// Zeroes the pixels of inactive tiles in each of the `planes` (`out_w x out_h` each,
    /// back to back) of `values`.
    pub fn clear_inactive(&self, values: &mut [f32], (out_w, out_h): (usize, usize)) {
        let plane = out_w * out_h;
        if plane == 0 || !self.active.contains(&false) {
            return;
        }
        for p in values.chunks_exact_mut(plane) {
            for ty in 0..self.tiles_y {
                for tx in 0..self.tiles_x {
                    if self.active[ty * self.tiles_x + tx] {
                        continue;
                    }
                    let (x0, x1) = (tx * TILE, ((tx + 1) * TILE).min(out_w));
                    for y in ty * TILE..((ty + 1) * TILE).min(out_h) {
                        p[y * out_w + x0..y * out_w + x1].fill(0.0);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_changed_pixel_activates_its_tile_and_the_margin() {
        let (w, h) = (64, 48);
        let a = vec![0.5f32; w * h];
        let mut b = a.clone();
        b[20 * w + 40] = 0.6; // tile (2, 1)
        let still = Activity::of_pair(&a, &a, w, 0, (w, h), 0.0, 1);
        assert!(!still.any());
        let one = Activity::of_pair(&a, &b, w, 0, (w, h), 0.0, 0);
        assert_eq!(one.inactive(), 4 * 3 - 1);
        let grown = Activity::of_pair(&a, &b, w, 0, (w, h), 0.0, 1);
        // Tiles x 1..=3, y 0..=2: all 3 rows of 3 columns.
        assert_eq!(grown.inactive(), 12 - 9);
        // Below the threshold it is still.
        assert!(!Activity::of_pair(&a, &b, w, 0, (w, h), 0.2, 1).any());
        let mut out = vec![1.0f32; 2 * w * h];
        one.clear_inactive(&mut out, (w, h));
        assert_eq!(out[20 * w + 40], 1.0);
        assert_eq!(out[w * h + 20 * w + 40], 1.0);
        assert_eq!(out[0], 0.0);
        assert_eq!(out.iter().filter(|&&v| v == 1.0).count(), 2 * 16 * 16);
    }

    #[test]
    fn an_offset_plane_is_read_at_the_output_columns() {
        // A plane 10 columns wider than the output, the output at columns 5..; a change in
        // column 2 of the plane is outside the output.
        let (pw, ow, h) = (42, 32, 16);
        let a = vec![0.0f32; pw * h];
        let mut b = a.clone();
        b[2] = 1.0;
        assert!(!Activity::of_pair(&a, &b, pw, 5, (ow, h), 0.0, 0).any());
        b[5 + 20] = 1.0;
        let act = Activity::of_pair(&a, &b, pw, 5, (ow, h), 0.0, 0);
        assert_eq!(act.inactive(), 1);
    }
}
