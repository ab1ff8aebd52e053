//! The pixel model's state cut into bands of tile rows, each stepped on its own: pixels are
//! independent and a frame's events are sorted afterwards, so a frame whose work is large is
//! stepped as two bands on two threads with the events of one (see [`PhysicsSim::advance`]).
//!
//! A band takes an interval's passes in order ([`Pass`]: the pixels of some tiles move from
//! one light to the next, a sub-frame or the frame), row by row across its active tiles, so
//! the pixels' state is read in the order it lies in memory.

use std::ops::Range;

use super::{FilterRow, PhysicsConfig, PhysicsSim, PhysicsStats, SlowPixel};
use crate::event::Event;

/// One step of some tiles' pixels: to the light `luma` at `t1` from their state at `t0`.
pub(super) struct Pass<'a> {
    pub luma: &'a [u16],
    pub t0: i64,
    pub t1: i64,
    /// `Some((mask, value))`: only the tiles whose mask entry is `value` move.
    pub only: Option<(&'a [u8], u8)>,
    /// The photoreceptor over `t1 - t0` ([`PhysicsSim::filter_table`]).
    pub filter: Vec<FilterRow>,
}

impl Pass<'_> {
    /// Whether this pass moves the frame's tile `tile` (row-major).
    fn moves(&self, tile: usize) -> bool {
        self.only.is_none_or(|(mask, value)| mask[tile] == value)
    }
}

/// Scratch of one band, kept between frames.
#[derive(Debug, Default)]
pub(super) struct Scratch {
    /// Which tiles of the tile row being advanced are active, and which changed.
    active: Vec<bool>,
    changed: Vec<bool>,
    /// The slow pixels of the tile row being advanced.
    slow: Vec<SlowPixel>,
    /// Scratch of the slow path (see [`super::crossings`]).
    pub(super) lanes: Vec<super::crossings::Lane>,
}

/// What every band reads.
pub(super) struct Shared<'a> {
    pub cfg: &'a PhysicsConfig,
    /// `L` and the filter row of every 16-bit luminance value.
    pub log_lut: &'a [f32],
    pub filter_rows: &'a [u8],
    pub width: usize,
    pub height: usize,
    pub tile: usize,
    /// Each pixel's own thresholds, which the threshold noise is drawn around (frame
    /// indices; empty without threshold noise).
    pub own_on: &'a [f32],
    pub own_off: &'a [f32],
    /// The simulator's seed, which the threshold noise is drawn from.
    pub seed: u64,
}

/// The pixels of the tile rows `rows`: their state (indexed from the band's first pixel),
/// their tiles' rest flags (from the band's first tile) and counters of their steps.
pub(super) struct Band<'a> {
    pub(super) shared: &'a Shared<'a>,
    rows: Range<usize>,
    /// Index of the band's first pixel and first tile in the frame.
    pub(super) base: usize,
    first_tile: usize,
    pub(super) l_in: &'a mut [f32],
    pub(super) l_p: &'a mut [f32],
    pub(super) l_ref: &'a mut [f32],
    pub(super) thr_on: &'a mut [f32],
    pub(super) thr_off: &'a mut [f32],
    /// Each pixel's events so far (empty without threshold noise).
    pub(super) fired: &'a mut [u32],
    pub(super) last_event: &'a mut [i64],
    prev_luma: &'a mut [u16],
    settled: &'a mut [bool],
    pub(super) scratch: &'a mut Scratch,
    pub(super) stats: PhysicsStats,
}

/// A band's work below this many pixel steps stays on one thread: starting a second costs
/// more.
const PARALLEL_PIXEL_STEPS: usize = 64 * 1024;

impl PhysicsSim {
    /// Takes `passes` in order, appending the signal events (unsorted); each pass's `luma`
    /// becomes the previous light of the tiles it moves. The tiles whose light did not change
    /// and whose pixels are at rest are skipped. Where the passes move many pixels, the frame
    /// is cut into two bands of about equal work, stepped side by side.
    pub(super) fn advance(&mut self, passes: &[Pass], out: &mut Vec<Event>) {
        let tile = self.cfg.tile as usize;
        let (w, h) = (self.width as usize, self.height as usize);
        let (tiles_x, rows) = (w.div_ceil(tile), h.div_ceil(tile));
        // Tiles moved per tile row, over all passes: the work a row may take.
        let work: Vec<usize> = (0..rows)
            .map(|ty| {
                let tiles = ty * tiles_x..(ty + 1) * tiles_x;
                passes
                    .iter()
                    .map(|p| tiles.clone().filter(|&t| p.moves(t)).count())
                    .sum()
            })
            .collect();
        let total: usize = work.iter().sum();
        let parallel = total * tile * tile >= PARALLEL_PIXEL_STEPS && rows >= 2;
        let split = if parallel {
            crate::parallel::halfway(&work).clamp(1, rows - 1)
        } else {
            rows
        };
        let PhysicsSim {
            cfg,
            width,
            height,
            log_lut,
            filter_rows,
            prev_luma,
            l_in,
            l_p,
            l_ref,
            thr_on,
            thr_off,
            own_on,
            own_off,
            fired,
            seed,
            last_event,
            settled,
            scratch,
            spill,
            stats,
            ..
        } = self;
        let shared = Shared {
            cfg,
            log_lut,
            filter_rows,
            width: usize::from(*width),
            height: usize::from(*height),
            tile,
            own_on,
            own_off,
            seed: *seed,
        };
        let at = (split * tile).min(h) * w;
        let (in_a, in_b) = l_in.split_at_mut(at);
        let (p_a, p_b) = l_p.split_at_mut(at);
        let (ref_a, ref_b) = l_ref.split_at_mut(at);
        let (on_a, on_b) = thr_on.split_at_mut(at);
        let (off_a, off_b) = thr_off.split_at_mut(at);
        let (last_a, last_b) = last_event.split_at_mut(at);
        let fired_at = at.min(fired.len());
        let (fired_a, fired_b) = fired.split_at_mut(fired_at);
        let (prev_a, prev_b) = prev_luma.split_at_mut(at);
        let (settled_a, settled_b) = settled.split_at_mut(split * tiles_x);
        let [scratch_a, scratch_b] = scratch;
        let mut a = Band {
            shared: &shared,
            rows: 0..split,
            base: 0,
            first_tile: 0,
            l_in: in_a,
            l_p: p_a,
            l_ref: ref_a,
            thr_on: on_a,
            thr_off: off_a,
            fired: fired_a,
            last_event: last_a,
            prev_luma: prev_a,
            settled: settled_a,
            scratch: scratch_a,
            stats: PhysicsStats::default(),
        };
        let mut b = Band {
            shared: &shared,
            rows: split..rows,
            base: at,
            first_tile: split * tiles_x,
            l_in: in_b,
            l_p: p_b,
            l_ref: ref_b,
            thr_on: on_b,
            thr_off: off_b,
            fired: fired_b,
            last_event: last_b,
            prev_luma: prev_b,
            settled: settled_b,
            scratch: scratch_b,
            stats: PhysicsStats::default(),
        };
        spill.clear();
        crate::parallel::side_by_side(parallel, || a.run(passes, out), || b.run(passes, spill));
        stats.add(a.stats);
        stats.add(b.stats);
        out.append(spill);
    }
}

impl Band<'_> {
    /// Takes `passes` in order on this band's tiles.
    fn run(&mut self, passes: &[Pass], out: &mut Vec<Event>) {
        for pass in passes {
            self.advance(pass, out);
        }
    }

    /// One pass on this band's tiles.
    fn advance(&mut self, pass: &Pass, out: &mut Vec<Event>) {
        let Shared {
            width: w,
            height: h,
            tile,
            ..
        } = *self.shared;
        let tiles_x = w.div_ceil(tile);
        let (mut active, mut changed, mut slow) = (
            std::mem::take(&mut self.scratch.active),
            std::mem::take(&mut self.scratch.changed),
            std::mem::take(&mut self.scratch.slow),
        );
        for ty in self.rows.clone() {
            let (y0, y1) = (ty * tile, ((ty + 1) * tile).min(h));
            let tiles = ty * tiles_x..(ty + 1) * tiles_x;
            let local = tiles.start - self.first_tile;
            active.clear();
            active.extend(tiles.clone().map(|t| pass.moves(t)));
            // A tile is skipped when its light did not change and its pixels are at rest.
            changed.clear();
            changed.resize(tiles_x, false);
            for y in y0..y1 {
                let row = y * w..(y + 1) * w;
                let now = &pass.luma[row.clone()];
                let before = &self.prev_luma[row.start - self.base..row.end - self.base];
                for (tx, c) in changed.iter_mut().enumerate() {
                    if active[tx] && !*c {
                        let seg = tx * tile..((tx + 1) * tile).min(w);
                        *c = now[seg.clone()] != before[seg];
                    }
                }
            }
            for (tx, a) in active.iter_mut().enumerate() {
                if *a && !changed[tx] && self.settled[local + tx] {
                    self.stats.tiles_skipped += 1;
                    *a = false;
                } else if *a {
                    self.stats.tiles_active += 1;
                    self.settled[local + tx] = true;
                }
            }
            if !active.contains(&true) {
                continue;
            }
            slow.clear();
            for y in y0..y1 {
                for tx in (0..tiles_x).filter(|&tx| active[tx]) {
                    let row = y * w + tx * tile..y * w + ((tx + 1) * tile).min(w);
                    let before = slow.len();
                    let settled = self.row(y, row.clone(), pass, &mut slow);
                    self.settled[local + tx] &= settled && slow.len() == before;
                    self.prev_luma[row.start - self.base..row.end - self.base]
                        .copy_from_slice(&pass.luma[row]);
                }
            }
            if !slow.is_empty() {
                self.crossings(&slow, pass.t0, pass.t1, &pass.filter, out);
            }
        }
        (self.scratch.active, self.scratch.changed, self.scratch.slow) = (active, changed, slow);
    }

    /// Advances the pixels of `range` (frame indices of one tile row, row `y`) through
    /// `pass`; returns whether all are at rest. The common case, a pixel whose filtered
    /// response cannot reach a threshold, is handled here on slices; the rest are appended to
    /// `slow` (with band indices) for [`Band::crossings`], which leaves their state untouched
    /// until then.
    fn row(
        &mut self,
        y: usize,
        range: Range<usize>,
        pass: &Pass,
        slow: &mut Vec<SlowPixel>,
    ) -> bool {
        let inv_dt = 1.0 / (pass.t1 - pass.t0) as f32;
        let x0 = range.start - y * self.shared.width;
        let luma = &pass.luma[range.clone()];
        let local = range.start - self.base..range.end - self.base;
        let start = local.start;
        let l_in = &mut self.l_in[local.clone()];
        let l_p = &mut self.l_p[local.clone()];
        let l_ref = &self.l_ref[local.clone()];
        let on = &self.thr_on[local.clone()];
        let off = &self.thr_off[local];
        // In three passes over the row, so the middle one, the arithmetic, runs on vectors:
        // the tables' values of each pixel's light, one array per quantity; each pixel's
        // response over the interval and whether it stays within its thresholds (kept) or may
        // cross one (the slow path); the slow pixels. A tile row has at most 64 pixels
        // (checked by `validate`).
        let n = luma.len().min(64);
        let mut l1s = [0.0f32; 64];
        let mut taus = [0.0f32; 64];
        let mut decays = [0.0f32; 64];
        let mut amps = [0.0f32; 64];
        for j in 0..n {
            let v = luma[j];
            l1s[j] = self.shared.log_lut[v as usize];
            let row = pass.filter[self.shared.filter_rows[v as usize] as usize];
            (taus[j], decays[j], amps[j]) = (row.tau, row.decay, row.amp);
        }
        let mut kept = [false; 64];
        let mut settled = true;
        let (l_in, l_p, l_ref, on, off) = (
            &mut l_in[..n],
            &mut l_p[..n],
            &l_ref[..n],
            &on[..n],
            &off[..n],
        );
        for j in 0..n {
            let (l1, l0, y0) = (l1s[j], l_in[j], l_p[j]);
            let (tau, decay, amp) = (taus[j], decays[j], amps[j]);
            let rt = (l1 - l0) * inv_dt * tau;
            let filtered = l1 - rt + (y0 - l0 + rt) * decay;
            let y1 = if tau > 0.0 { filtered } else { l1 };
            // The flicker swings the response by up to `amp` either way.
            let hi = y0.max(l0).max(l1).max(y1) + amp;
            let lo = y0.min(l0).min(l1).min(y1) - amp;
            let lref = l_ref[j];
            let keep = (hi - lref < on[j]) & (lref - lo < off[j]);
            kept[j] = keep;
            settled &= !keep | ((l0 == l1) & ((y1 - l1).abs() < 1e-4));
            l_in[j] = if keep { l1 } else { l0 };
            l_p[j] = if keep { y1 } else { y0 };
        }
        for (j, &keep) in kept[..n].iter().enumerate() {
            if !keep {
                slow.push(SlowPixel {
                    i: start + j,
                    x: (x0 + j) as u16,
                    y: y as u16,
                    v: luma[j],
                });
            }
        }
        settled
    }

    /// The flicker's phase (radians) at time `t` us.
    pub(super) fn flicker_phase(&self, t: i64) -> f64 {
        let period = 1e6 / self.shared.cfg.flicker_hz;
        std::f64::consts::TAU * (t as f64).rem_euclid(period) / period
    }
}
