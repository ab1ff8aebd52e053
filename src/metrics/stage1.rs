//! Stage 1 metrics (V2CE_SPEC.md section 6.1): binary F1 and accuracy on the voxel at three
//! reductions, and pooled MSE, between a simulated and a real event stream voxelized on the same
//! frame intervals.
//!
//! - **R** (`raw`): every `2 x C x H x W` element; **T** (`sum_c`): nodes summed per pixel and
//!   polarity; **TP** (`sum_cp`): nodes and polarities summed per pixel.
//! - Binarization at `value > 0.01`. F1 is micro-averaged within a chunk of 16 consecutive
//!   intervals (0 when neither side has a positive), then macro-averaged over chunks, as the
//!   reference evaluates its 16-interval test chunks; accuracy counts true negatives.
//! - **PMSE-k**: per chunk, the `(2, 10 L, H, W)` reshaped voxel is average-pooled with a cubic
//!   kernel `k` and stride `k` (floor mode), and the MSE taken; averaged over chunks.
//!
//! Everything runs on the sparse voxels, so the cost follows the active cells.

use serde::Serialize;

use crate::error::Result;
use crate::event::{time_slice, Event};
use crate::interval::Interval;
use crate::voxel::{VoxelGrid, Voxelizer};

/// Intervals per chunk, as in the reference evaluation.
pub const CHUNK_INTERVALS: usize = 16;
/// The binarization threshold.
pub const THRESHOLD: f64 = 0.01;

/// The Stage 1 scores.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Stage1Metrics {
    /// F1 on per-pixel totals (both polarities, all nodes).
    pub tpf1: f64,
    /// F1 on per-pixel, per-polarity totals.
    pub tf1: f64,
    /// F1 on every voxel element.
    pub rf1: f64,
    /// Accuracy on per-pixel totals.
    pub tpacc: f64,
    /// Accuracy on per-pixel, per-polarity totals.
    pub tacc: f64,
    /// Accuracy on every element.
    pub racc: f64,
    /// Pooled MSE, kernel 2.
    pub pmse2: f64,
    /// Pooled MSE, kernel 4.
    pub pmse4: f64,
    /// Chunks scored.
    pub chunks: usize,
    /// Intervals scored.
    pub intervals: usize,
    /// Real events inside the intervals.
    pub real_events: u64,
    /// Simulated events inside the intervals.
    pub sim_events: u64,
}

impl Stage1Metrics {
    /// Simulated over real event count.
    pub fn count_ratio(&self) -> f64 {
        if self.real_events == 0 {
            0.0
        } else {
            self.sim_events as f64 / self.real_events as f64
        }
    }
}

#[derive(Default, Clone, Copy)]
struct Confusion {
    tp: u64,
    fp: u64,
    fn_: u64,
    total: u64,
}

impl Confusion {
    fn add(&mut self, pred: bool, truth: bool) {
        match (pred, truth) {
            (true, true) => self.tp += 1,
            (true, false) => self.fp += 1,
            (false, true) => self.fn_ += 1,
            _ => {}
        }
    }

    fn f1(&self) -> f64 {
        let (tp, fp, fn_) = (self.tp as f64, self.fp as f64, self.fn_ as f64);
        let prec = tp / (tp + fp + 1e-8);
        let rec = tp / (tp + fn_ + 1e-8);
        2.0 * prec * rec / (prec + rec + 1e-8)
    }

    fn accuracy(&self) -> f64 {
        let wrong = self.fp + self.fn_;
        if self.total == 0 {
            0.0
        } else {
            (self.total - wrong) as f64 / self.total as f64
        }
    }
}

/// Pooled sums of (sim - real) for one kernel size over one chunk.
struct Pool {
    k: usize,
    nodes: usize,
    wk: usize,
    hk: usize,
    diff: Vec<f64>,
}

impl Pool {
    fn new(k: usize, nodes_total: usize, w: usize, h: usize) -> Self {
        let (nodes, wk, hk) = (nodes_total / k, w / k, h / k);
        Pool {
            k,
            nodes,
            wk,
            hk,
            diff: vec![0.0; 2 * nodes * wk * hk],
        }
    }

    fn add(&mut self, plane: usize, node: usize, x: usize, y: usize, v: f64) {
        let (n, px, py) = (node / self.k, x / self.k, y / self.k);
        if n < self.nodes && px < self.wk && py < self.hk {
            self.diff[((plane * self.nodes + n) * self.hk + py) * self.wk + px] += v;
        }
    }

    fn mse(&self) -> f64 {
        if self.diff.is_empty() {
            return 0.0;
        }
        let k3 = (self.k * self.k * self.k) as f64;
        self.diff.iter().map(|d| (d / k3).powi(2)).sum::<f64>() / self.diff.len() as f64
    }
}

/// The bytes [`score`] holds beyond the two streams for a `width x height` sensor with `bins`
/// nodes: the pooled errors of a chunk of intervals at both kernel sizes, the per-pixel sums
/// and cell index, and a voxelizer.
pub fn score_bytes(width: u16, height: u16, bins: usize) -> u64 {
    let hw = u64::from(width) * u64::from(height);
    let nodes = (bins * CHUNK_INTERVALS) as u64;
    // Per kernel size k: 2 planes x nodes / k x (W / k) x (H / k) f64 sums.
    let pools: u64 = [2u64, 4]
        .iter()
        .map(|k| 2 * (nodes / k) * (hw / (k * k)) * 8)
        .sum();
    pools + 2 * hw * 4 + 2 * hw * 8 + Voxelizer::fixed_bytes(width, height)
}

/// Scores `sim` against `real` on `intervals` (both streams sorted by time) for a
/// `width x height` sensor with `bins` nodes per interval.
pub fn score(
    real: &[Event],
    sim: &[Event],
    intervals: &[Interval],
    width: u16,
    height: u16,
    bins: usize,
) -> Result<Stage1Metrics> {
    score_with(real, sim, intervals, width, height, bins, &|| Ok(()))
}

/// [`score`], calling `tick` before each chunk of intervals: its error (an interrupt) ends the
/// scoring.
pub fn score_with(
    real: &[Event],
    sim: &[Event],
    intervals: &[Interval],
    width: u16,
    height: u16,
    bins: usize,
    tick: &dyn Fn() -> Result<()>,
) -> Result<Stage1Metrics> {
    let (w, h) = (width as usize, height as usize);
    crate::limits::memory(
        "sensor size",
        score_bytes(width, height, bins),
        &format!("scoring a {width} x {height} sensor"),
    )?;
    let mut vox = Voxelizer::new(width, height, bins)?;
    let mut real_grid = VoxelGrid::new(width, height, bins)?;
    let mut sim_grid = VoxelGrid::new(width, height, bins)?;
    // Per (plane, pixel): index of the real cell, or u32::MAX.
    let mut real_index = vec![u32::MAX; 2 * w * h];
    let mut pixel_real = vec![0f64; w * h];
    let mut pixel_sim = vec![0f64; w * h];
    let mut touched: Vec<usize> = Vec::new();
    let mut m = Stage1Metrics::default();
    let (mut f1s, mut accs, mut pm2, mut pm4) = ([0.0; 3], [0.0; 3], 0.0, 0.0);
    for chunk in intervals.chunks(CHUNK_INTERVALS) {
        tick()?;
        let mut conf = [Confusion::default(); 3];
        let nodes_total = bins * chunk.len();
        let mut pools = [
            Pool::new(2, nodes_total, w, h),
            Pool::new(4, nodes_total, w, h),
        ];
        for (l, &iv) in chunk.iter().enumerate() {
            let r = time_slice(real, iv.start(), iv.end());
            let s = time_slice(sim, iv.start(), iv.end());
            m.real_events += r.len() as u64;
            m.sim_events += s.len() as u64;
            vox.voxelize_into(r, iv, &mut real_grid)?;
            vox.voxelize_into(s, iv, &mut sim_grid)?;
            let plane_of = |on: bool| if on { 0 } else { 1 };
            for (ci, c) in real_grid.cells().enumerate() {
                let p = plane_of(c.on);
                real_index[p * w * h + c.y as usize * w + c.x as usize] = ci as u32;
            }
            let real_cells: Vec<_> = real_grid.cells().collect();
            let mut matched = vec![false; real_cells.len()];
            // Simulated cells, against the real cell at the same place (if any).
            for c in sim_grid.cells() {
                let (p, pix) = (plane_of(c.on), c.y as usize * w + c.x as usize);
                let ri = real_index[p * w * h + pix];
                let rv = (ri != u32::MAX).then(|| real_cells[ri as usize].values);
                if ri != u32::MAX {
                    matched[ri as usize] = true;
                }
                for (node, &v) in c.values.iter().enumerate() {
                    let g = rv.map_or(0.0, |rv| rv[node]);
                    conf[0].add(v > THRESHOLD, g > THRESHOLD);
                    for pool in &mut pools {
                        pool.add(p, l * bins + node, c.x as usize, c.y as usize, v - g);
                    }
                }
                let sum: f64 = c.values.iter().sum();
                let gsum: f64 = rv.map_or(0.0, |rv| rv.iter().sum());
                conf[1].add(sum > THRESHOLD, gsum > THRESHOLD);
                if pixel_real[pix] == 0.0 && pixel_sim[pix] == 0.0 {
                    touched.push(pix);
                }
                pixel_sim[pix] += sum;
            }
            // Real cells with no simulated cell.
            for (ri, c) in real_cells.iter().enumerate() {
                let (p, pix) = (plane_of(c.on), c.y as usize * w + c.x as usize);
                real_index[p * w * h + pix] = u32::MAX;
                let sum: f64 = c.values.iter().sum();
                if pixel_real[pix] == 0.0 && pixel_sim[pix] == 0.0 {
                    touched.push(pix);
                }
                pixel_real[pix] += sum;
                if matched[ri] {
                    continue;
                }
                for (node, &g) in c.values.iter().enumerate() {
                    conf[0].add(false, g > THRESHOLD);
                    for pool in &mut pools {
                        pool.add(p, l * bins + node, c.x as usize, c.y as usize, -g);
                    }
                }
                conf[1].add(false, sum > THRESHOLD);
            }
            touched.sort_unstable();
            touched.dedup();
            for &pix in &touched {
                conf[2].add(pixel_sim[pix] > THRESHOLD, pixel_real[pix] > THRESHOLD);
                pixel_sim[pix] = 0.0;
                pixel_real[pix] = 0.0;
            }
            touched.clear();
            conf[0].total += (2 * bins * w * h) as u64;
            conf[1].total += (2 * w * h) as u64;
            conf[2].total += (w * h) as u64;
        }
        for i in 0..3 {
            f1s[i] += conf[i].f1();
            accs[i] += conf[i].accuracy();
        }
        pm2 += pools[0].mse();
        pm4 += pools[1].mse();
        m.chunks += 1;
        m.intervals += chunk.len();
    }
    let n = m.chunks.max(1) as f64;
    m.rf1 = f1s[0] / n;
    m.tf1 = f1s[1] / n;
    m.tpf1 = f1s[2] / n;
    m.racc = accs[0] / n;
    m.tacc = accs[1] / n;
    m.tpacc = accs[2] / n;
    m.pmse2 = pm2 / n;
    m.pmse4 = pm4 / n;
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::interval::fixed_intervals;

    fn stream(seed: u64) -> Vec<Event> {
        crate::sweeping_bar::recording(64, 48, 1_000_000, seed)
            .events
            .into_events()
    }

    #[test]
    fn identical_streams_score_perfectly_and_empty_scores_zero() {
        let real = stream(1);
        let iv = fixed_intervals(0, 999_999, 30.0).unwrap();
        let m = score(&real, &real, &iv, 64, 48, 10).unwrap();
        assert_eq!((m.rf1 * 1e6).round(), 1e6, "{m:?}");
        assert_eq!((m.tf1 * 1e6).round(), 1e6);
        assert_eq!((m.tpf1 * 1e6).round(), 1e6);
        assert_eq!((m.racc, m.tacc, m.tpacc), (1.0, 1.0, 1.0));
        assert_eq!((m.pmse2, m.pmse4), (0.0, 0.0));
        assert_eq!(m.count_ratio(), 1.0);
        assert_eq!(m.chunks, iv.len().div_ceil(16));
        let none = score(&real, &[], &iv, 64, 48, 10).unwrap();
        assert_eq!((none.rf1, none.tf1, none.tpf1), (0.0, 0.0, 0.0));
        assert!(none.pmse2 > 0.0 && none.racc < 1.0);
    }

    #[test]
    fn f1_follows_hand_counts() {
        // One interval, 4 x 1 sensor. Real: ON at pixel 0 and 1; sim: ON at 1, OFF at 1, ON at 3.
        let iv = [Interval::new(0, 900).unwrap()];
        let real = vec![Event::new(0, 0, 0, true), Event::new(0, 1, 0, true)];
        let sim = vec![
            Event::new(0, 1, 0, true),
            Event::new(0, 1, 0, false),
            Event::new(0, 3, 0, true),
        ];
        let m = score(&real, &sim, &iv, 4, 1, 10).unwrap();
        // T: tp 1 (1 ON), fp 2 (1 OFF, 3 ON), fn 1 (0 ON): F1 = 2/5 = 0.4.
        assert!((m.tf1 - 0.4).abs() < 1e-6, "{m:?}");
        // TP: pixels real {0, 1}, sim {1, 3}: tp 1, fp 1, fn 1: 0.5.
        assert!((m.tpf1 - 0.5).abs() < 1e-6, "{m:?}");
        // T accuracy: 8 elements, 3 wrong.
        assert!((m.tacc - 5.0 / 8.0).abs() < 1e-12);
        assert!((m.tpacc - 2.0 / 4.0).abs() < 1e-12);
    }
}
