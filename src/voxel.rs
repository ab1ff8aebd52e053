//! The V2CE event voxel and `voxelize`.
//!
//! Logically a voxel grid is the V2CE tensor `2 x C x H x W` (ON plane first, channel `p*C + c`):
//! `C` temporal nodes spanning `C - 1` equal sub-intervals of one frame interval, each event split
//! bilinearly between the two nodes around it, so the `C` nodes of a pixel sum to its number of
//! events. Node 0 sits at the interval's start and node `C - 1` at its end (the start of the next
//! interval), both given by frame times, not by the first and last event.
//!
//! Stored sparsely: only the (plane, pixel) *cells* with a non-zero node are kept, each with its
//! `C` values in `f64`. Real voxels are sparse (about 2% of MVSEC's cells are non-zero), so the
//! samplers cost time proportional to active cells, and `f64` keeps counts of thousands of events
//! per node exact enough that rounding never invents or loses one. [`VoxelGrid::to_dense`] and
//! [`VoxelGrid::from_dense`] convert to and from the dense `f32` tensor a model reads or writes.

use crate::error::{Error, Result};
use crate::event::Event;
use crate::interval::Interval;

/// Default number of temporal nodes per frame interval (V2CE's `C`).
pub const DEFAULT_BINS: usize = 10;

/// One active (plane, pixel) cell of a [`VoxelGrid`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VoxelCell<'a> {
    /// Column.
    pub x: u16,
    /// Row.
    pub y: u16,
    /// `true` for the ON plane (plane 0), `false` for OFF (plane 1).
    pub on: bool,
    /// The `C` node values, oldest first.
    pub values: &'a [f64],
}

/// A sparse `2 x C x H x W` event voxel for one frame interval (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct VoxelGrid {
    width: u16,
    height: u16,
    bins: usize,
    /// `plane * H * W + y * W + x` of each active cell, plane 0 = ON.
    cells: Vec<u32>,
    /// `cells.len() * bins` node values.
    values: Vec<f64>,
}

impl VoxelGrid {
    /// An empty grid; `bins` must be at least 2 and the sensor at least 1 x 1.
    pub fn new(width: u16, height: u16, bins: usize) -> Result<Self> {
        crate::limits::frame_size("sensor size", width.into(), height.into())?;
        if !(2..=1024).contains(&bins) {
            return Err(Error::invalid(
                "bins",
                format!("{bins} nodes per interval; need 2 to 1024"),
            ));
        }
        Ok(VoxelGrid {
            width,
            height,
            bins,
            cells: Vec::new(),
            values: Vec::new(),
        })
    }

    /// Sensor width in pixels.
    pub fn width(&self) -> u16 {
        self.width
    }

    /// Sensor height in pixels.
    pub fn height(&self) -> u16 {
        self.height
    }

    /// Number of temporal nodes `C` (sub-intervals: `C - 1`).
    pub fn bins(&self) -> usize {
        self.bins
    }

    /// Number of active (plane, pixel) cells.
    pub fn active_cells(&self) -> usize {
        self.cells.len()
    }

    /// Removes every cell, keeping the allocations for reuse.
    pub fn clear(&mut self) {
        self.cells.clear();
        self.values.clear();
    }

    /// The active cells in the order they became active.
    pub fn cells(&self) -> impl Iterator<Item = VoxelCell<'_>> + '_ {
        let plane = self.width as u32 * self.height as u32;
        self.cells
            .iter()
            .zip(self.values.chunks_exact(self.bins))
            .map(move |(&id, values)| {
                let (on, pix) = (id < plane, id % plane);
                VoxelCell {
                    x: (pix % self.width as u32) as u16,
                    y: (pix / self.width as u32) as u16,
                    on,
                    values,
                }
            })
    }

    /// Appends a cell; values may be anything, including NaN (samplers count and ignore those).
    pub fn push_cell(&mut self, x: u16, y: u16, on: bool, values: &[f64]) -> Result<()> {
        if x >= self.width || y >= self.height {
            return Err(Error::invalid(
                "pixel",
                format!("({x}, {y}) outside {} x {}", self.width, self.height),
            ));
        }
        if values.len() != self.bins {
            return Err(Error::invalid(
                "cell",
                format!("{} values for {} bins", values.len(), self.bins),
            ));
        }
        self.room_for_one()?;
        self.cells.push(self.cell_id(x, y, on));
        self.values.extend_from_slice(values);
        Ok(())
    }

    /// Room for one more cell, or a clear error where the memory cannot be had (a grid holds
    /// up to `2 x W x H` cells of `bins` values: 2.7 GB at 4096 x 4096 and 10 bins).
    fn room_for_one(&mut self) -> Result<()> {
        let (w, h, n) = (self.width, self.height, self.cells.len());
        let full = |e: std::collections::TryReserveError| {
            Error::invalid(
                "voxel grid",
                format!("{w} x {h} with {n} active cells: no memory for more ({e})"),
            )
        };
        if self.cells.len() == self.cells.capacity() {
            let more = self.cells.len().max(1024);
            self.cells.try_reserve(more).map_err(full)?;
            self.values.try_reserve(more * self.bins).map_err(full)?;
        }
        Ok(())
    }

    /// The most bytes a `width x height` grid with `bins` nodes holds (every cell of both
    /// polarities active).
    pub fn max_bytes(width: u16, height: u16, bins: usize) -> u64 {
        2 * u64::from(width) * u64::from(height) * (4 + 8 * bins as u64)
    }

    /// Node `c` of the cell at (`x`, `y`, `on`), 0 where the cell is inactive.
    ///
    /// A linear search over active cells: meant for tests and inspection, not for hot loops.
    pub fn get(&self, x: u16, y: u16, on: bool, c: usize) -> f64 {
        let id = self.cell_id(x, y, on);
        self.cells
            .iter()
            .position(|&k| k == id)
            .map_or(0.0, |i| self.values[i * self.bins + c])
    }

    /// Sum of every node value (the grid's total event mass).
    pub fn total_mass(&self) -> f64 {
        self.values.iter().sum()
    }

    /// The dense `f32` tensor in V2CE layout: index `((p * C + c) * H + y) * W + x`, p = 0 for ON.
    pub fn to_dense(&self) -> Vec<f32> {
        let hw = self.width as usize * self.height as usize;
        let mut out = vec![0f32; 2 * self.bins * hw];
        for (&id, values) in self.cells.iter().zip(self.values.chunks_exact(self.bins)) {
            let (p, pix) = (id as usize / hw, id as usize % hw);
            for (c, v) in values.iter().enumerate() {
                out[(p * self.bins + c) * hw + pix] += *v as f32;
            }
        }
        out
    }

    /// Reads a dense `f32` tensor in V2CE layout (see [`VoxelGrid::to_dense`]).
    ///
    /// A cell is kept when any of its nodes is not exactly zero (NaN and negative values are kept
    /// so that samplers can count them). Costs one pass over the tensor.
    pub fn from_dense(width: u16, height: u16, bins: usize, data: &[f32]) -> Result<Self> {
        let mut grid = VoxelGrid::new(width, height, bins)?;
        let hw = width as usize * height as usize;
        if data.len() != 2 * bins * hw {
            return Err(Error::invalid(
                "voxel tensor",
                format!(
                    "{} values, expected 2 x {bins} x {height} x {width} = {}",
                    data.len(),
                    2 * bins * hw
                ),
            ));
        }
        let mut node = vec![0f64; bins];
        for p in 0..2 {
            for pix in 0..hw {
                let mut any = false;
                for (c, n) in node.iter_mut().enumerate() {
                    let v = data[(p * bins + c) * hw + pix];
                    any |= v != 0.0;
                    *n = v as f64;
                }
                if any {
                    grid.room_for_one()?;
                    grid.cells.push((p * hw + pix) as u32);
                    grid.values.extend_from_slice(&node);
                }
            }
        }
        Ok(grid)
    }

    fn cell_id(&self, x: u16, y: u16, on: bool) -> u32 {
        let plane = self.width as u32 * self.height as u32;
        let pix = y as u32 * self.width as u32 + x as u32;
        if on {
            pix
        } else {
            plane + pix
        }
    }
}

/// Builds voxel grids from events, reusing its buffers between intervals.
///
/// Cost is proportional to the number of events plus active cells, never to `H x W x C`.
#[derive(Debug, Clone)]
pub struct Voxelizer {
    width: u16,
    height: u16,
    bins: usize,
    /// Cell id -> position in the grid being built, `u32::MAX` when not yet active.
    slot: Vec<u32>,
}

impl Voxelizer {
    /// A voxelizer for a `width x height` sensor and `bins` nodes per interval.
    pub fn new(width: u16, height: u16, bins: usize) -> Result<Self> {
        VoxelGrid::new(width, height, bins)?;
        Ok(Voxelizer {
            width,
            height,
            bins,
            slot: vec![u32::MAX; 2 * width as usize * height as usize],
        })
    }

    /// The bytes a voxelizer for a `width x height` sensor holds whatever it voxelizes: a slot
    /// per cell (pixel and polarity).
    pub fn fixed_bytes(width: u16, height: u16) -> u64 {
        2 * u64::from(width) * u64::from(height) * std::mem::size_of::<u32>() as u64
    }

    /// Voxelizes `events` over `interval` into `grid` (cleared first).
    ///
    /// Each event at normalised time `tau = (t - start) * (C - 1) / (end - start)` adds
    /// `1 - frac(tau)` to node `floor(tau)` and `frac(tau)` to the next node; `tau` is clamped to
    /// `[0, C - 1]`, so an event outside the interval lands on its nearest end. Times are
    /// subtracted as `i64` before any float arithmetic. An event outside the sensor is an error.
    pub fn voxelize_into(
        &mut self,
        events: &[Event],
        interval: Interval,
        grid: &mut VoxelGrid,
    ) -> Result<()> {
        if (grid.width, grid.height, grid.bins) != (self.width, self.height, self.bins) {
            *grid = VoxelGrid::new(self.width, self.height, self.bins)?;
        }
        grid.clear();
        let scale = (self.bins - 1) as f64 / interval.duration_us() as f64;
        let last = (self.bins - 1) as f64;
        let mut result = Ok(());
        for e in events {
            if e.x >= self.width || e.y >= self.height {
                result = Err(Error::invalid(
                    "event",
                    format!(
                        "pixel ({}, {}) at t = {} us is outside the {} x {} sensor",
                        e.x, e.y, e.t, self.width, self.height
                    ),
                ));
                break;
            }
            let id = grid.cell_id(e.x, e.y, e.on) as usize;
            let slot = match self.slot[id] {
                u32::MAX => {
                    if let Err(e) = grid.room_for_one() {
                        result = Err(e);
                        break;
                    }
                    let s = grid.cells.len() as u32;
                    self.slot[id] = s;
                    grid.cells.push(id as u32);
                    grid.values.resize(grid.values.len() + self.bins, 0.0);
                    s
                }
                s => s,
            } as usize;
            let tau = ((e.t - interval.start()) as f64 * scale).clamp(0.0, last);
            // The floor: truncation of a non-negative value (rounding.rs).
            let a = (tau as usize).min(self.bins - 2);
            let frac = tau - a as f64;
            let v = &mut grid.values[slot * self.bins + a..slot * self.bins + a + 2];
            v[0] += 1.0 - frac;
            v[1] += frac;
        }
        for &id in &grid.cells {
            self.slot[id as usize] = u32::MAX;
        }
        result
    }

    /// Voxelizes `events` over `interval` into a new grid.
    pub fn voxelize(&mut self, events: &[Event], interval: Interval) -> Result<VoxelGrid> {
        let mut grid = VoxelGrid::new(self.width, self.height, self.bins)?;
        self.voxelize_into(events, interval, &mut grid)?;
        Ok(grid)
    }
}

/// Voxelizes `events` over `interval` for a `width x height` sensor with `bins` nodes.
///
/// A convenience over [`Voxelizer`], which reuses its buffers across intervals.
pub fn voxelize(
    events: &[Event],
    interval: Interval,
    width: u16,
    height: u16,
    bins: usize,
) -> Result<VoxelGrid> {
    Voxelizer::new(width, height, bins)?.voxelize(events, interval)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fixed_bytes_are_what_a_voxelizer_holds() {
        let v = Voxelizer::new(346, 260, 10).unwrap();
        let held = std::mem::size_of_val(v.slot.as_slice()) as u64;
        assert_eq!(Voxelizer::fixed_bytes(346, 260), held);
        assert_eq!(Voxelizer::fixed_bytes(8192, 8192), 512 << 20);
    }

    /// V2CE_SPEC Appendix B.1, with the interval given by its ends (0 and 1800 us), which here
    /// coincide with the first and last event.
    #[test]
    fn golden_voxelization() {
        let events = [
            Event::new(0, 0, 0, true),
            Event::new(500, 0, 0, true),
            Event::new(1800, 1, 0, false),
        ];
        // The OFF event sits exactly at the interval's end and lands on node 9 through the clamp.
        let iv = Interval::new(0, 1800).unwrap();
        let g = voxelize(&events, iv, 2, 1, 10).unwrap();
        let dense = g.to_dense();
        let at = |ch: usize, y: usize, x: usize| dense[(ch + y) * 2 + x]; // H = 1
        assert_eq!(at(0, 0, 0), 1.0);
        assert_eq!(at(2, 0, 0), 0.5);
        assert_eq!(at(3, 0, 0), 0.5);
        assert_eq!(at(19, 0, 1), 1.0);
        let nonzero = dense.iter().filter(|v| **v != 0.0).count();
        assert_eq!(nonzero, 4);
    }

    #[test]
    fn mass_per_cell_equals_event_count() {
        let iv = Interval::new(1_000, 41_000).unwrap();
        let events: Vec<Event> = (0..1000)
            .map(|i| {
                Event::new(
                    1_000 + i * 37 % 40_000,
                    (i % 7) as u16,
                    (i % 3) as u16,
                    i % 2 == 0,
                )
            })
            .collect();
        let g = voxelize(&events, iv, 7, 3, 10).unwrap();
        for cell in g.cells() {
            let n = events
                .iter()
                .filter(|e| e.x == cell.x && e.y == cell.y && e.on == cell.on)
                .count();
            let mass: f64 = cell.values.iter().sum();
            assert!((mass - n as f64).abs() < 1e-9, "{mass} vs {n}");
        }
        assert!((g.total_mass() - 1000.0).abs() < 1e-9);
    }

    #[test]
    fn dense_round_trip_and_reuse() {
        let iv = Interval::new(0, 900).unwrap();
        let mut vx = Voxelizer::new(4, 3, 10).unwrap();
        let mut grid = VoxelGrid::new(4, 3, 10).unwrap();
        vx.voxelize_into(&[Event::new(150, 3, 2, false)], iv, &mut grid)
            .unwrap();
        let back = VoxelGrid::from_dense(4, 3, 10, &grid.to_dense()).unwrap();
        assert_eq!(back.active_cells(), 1);
        assert!((back.get(3, 2, false, 1) - 0.5).abs() < 1e-7);
        assert!((back.get(3, 2, false, 2) - 0.5).abs() < 1e-7);
        // Reuse: the previous interval's cells are gone.
        vx.voxelize_into(&[Event::new(0, 0, 0, true)], iv, &mut grid)
            .unwrap();
        assert_eq!(grid.active_cells(), 1);
        assert_eq!(grid.get(0, 0, true, 0), 1.0);
        assert_eq!(grid.get(3, 2, false, 1), 0.0);
    }

    #[test]
    fn out_of_sensor_event_is_an_error() {
        let iv = Interval::new(0, 10).unwrap();
        assert!(voxelize(&[Event::new(1, 4, 0, true)], iv, 4, 4, 10).is_err());
        assert!(VoxelGrid::new(0, 4, 10).is_err());
        assert!(VoxelGrid::new(4, 4, 1).is_err());
        assert!(VoxelGrid::from_dense(2, 2, 10, &[0.0; 5]).is_err());
    }
}
