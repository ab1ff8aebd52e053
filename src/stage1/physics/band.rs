//! The pixel model's state cut into bands of tile rows, each stepped on its own: pixels are
//! independent and a frame's events are sorted afterwards, so a frame whose work is large is
//! stepped band by band on every helper thread with the events of one (see
//! [`PhysicsSim::advance`]).
//!
//! A band takes an interval's passes in order ([`Pass`]: the pixels of some tiles move from
//! one light to the next, a sub-frame or the frame), row by row across its active tiles, so
//! the pixels' state is read in the order it lies in memory.

use std::ops::Range;

use super::crossings::{Lane, Shared, Slow};
use super::{FilterRow, PhysicsSim, PhysicsStats, SlowPixel};
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
    lanes: Vec<Lane>,
    /// Scratch of [`Band::row`].
    row: RowScratch,
}

/// The per-pixel quantities of one tile row's pixels (at most 64) in [`Band::row`].
#[derive(Debug)]
struct RowScratch {
    l1s: [f32; 64],
    taus: [f32; 64],
    decays: [f32; 64],
    amps: [f32; 64],
    kept: [bool; 64],
}

impl Default for RowScratch {
    fn default() -> Self {
        RowScratch {
            l1s: [0.0; 64],
            taus: [0.0; 64],
            decays: [0.0; 64],
            amps: [0.0; 64],
            kept: [false; 64],
        }
    }
}

/// The pixels of the tile rows `rows`: their state (indexed from the band's first pixel),
/// their tiles' rest flags (from the band's first tile) and counters of their steps.
pub(super) struct Band<'a> {
    shared: &'a Shared<'a>,
    rows: Range<usize>,
    /// Index of the band's first pixel and first tile in the frame.
    base: usize,
    first_tile: usize,
    l_in: &'a mut [f32],
    l_p: &'a mut [f32],
    l_ref: &'a mut [f32],
    thr_on: &'a mut [f32],
    thr_off: &'a mut [f32],
    /// Each pixel's events so far (empty without threshold noise).
    fired: &'a mut [u32],
    last_event: &'a mut [i64],
    prev_luma: &'a mut [u16],
    settled: &'a mut [bool],
    scratch: &'a mut Scratch,
    stats: PhysicsStats,
    /// Crossings memory could not hold.
    unheld: u64,
}

/// A frame's work below this many pixel steps stays on one thread: handing it out costs more.
const PARALLEL_PIXEL_STEPS: usize = 64 * 1024;

/// The pixel arrays of one band, cut from the frame's.
type Cut<'a, T> = std::vec::IntoIter<&'a mut [T]>;

/// `data` cut into pieces of `chunk` values (the last one shorter), `bands` of them; an empty
/// `data` (an array a setting leaves out) gives empty pieces.
fn cut<T>(data: &mut [T], chunk: usize, bands: usize) -> Cut<'_, T> {
    let mut pieces: Vec<&mut [T]> = data.chunks_mut(chunk.max(1)).collect();
    pieces.resize_with(bands, || &mut []);
    pieces.into_iter()
}

impl PhysicsSim {
    /// Takes `passes` in order, appending the signal events (unsorted); each pass's `luma`
    /// becomes the previous light of the tiles it moves. The tiles whose light did not change
    /// and whose pixels are at rest are skipped. Where the passes move many pixels, the frame
    /// is cut into bands of one tile row, which the helper threads take from one queue
    /// ([`crate::parallel::each`]); pixels are independent and the events are sorted
    /// afterwards, so they do not depend on which thread stepped which band.
    pub(super) fn advance(&mut self, passes: &[Pass], out: &mut Vec<Event>) {
        let tile = self.cfg.tile as usize;
        let (w, h) = (self.width as usize, self.height as usize);
        let (tiles_x, rows) = (w.div_ceil(tile), h.div_ceil(tile));
        // Tiles moved over all passes: the work the frame may take.
        let total: usize = passes
            .iter()
            .map(|p| match p.only {
                None => tiles_x * rows,
                Some((mask, value)) => mask.iter().filter(|&&m| m == value).count(),
            })
            .sum();
        let parallel = total * tile * tile >= PARALLEL_PIXEL_STEPS
            && rows >= 2
            && crate::parallel::threads() > 1;
        let band_rows = if parallel { 1 } else { rows };
        let bands = rows.div_ceil(band_rows);
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
            unheld,
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
            budget: crate::limits::Budget::of_memory_left(),
        };
        // Grown, never shrunk: a frame stepped in one band keeps the others' buffers for the
        // next frame stepped in many (only the first `bands` are used).
        if scratch.len() < bands {
            scratch.resize_with(bands, Default::default);
            spill.resize_with(bands, Vec::new);
        }
        let chunk = band_rows * tile * w;
        let (mut l_in, mut l_p, mut l_ref) = (
            cut(l_in, chunk, bands),
            cut(l_p, chunk, bands),
            cut(l_ref, chunk, bands),
        );
        let (mut thr_on, mut thr_off, mut fired) = (
            cut(thr_on, chunk, bands),
            cut(thr_off, chunk, bands),
            cut(fired, chunk, bands),
        );
        let (mut last_event, mut prev_luma) =
            (cut(last_event, chunk, bands), cut(prev_luma, chunk, bands));
        let mut settled = cut(settled, band_rows * tiles_x, bands);
        let mut work: Vec<(Band, &mut Vec<Event>)> = scratch
            .iter_mut()
            .zip(spill.iter_mut())
            .take(bands)
            .enumerate()
            .filter_map(|(b, (scratch, spill))| {
                let first = b * band_rows;
                spill.clear();
                let band = Band {
                    shared: &shared,
                    rows: first..(first + band_rows).min(rows),
                    base: first * tile * w,
                    first_tile: first * tiles_x,
                    l_in: l_in.next()?,
                    l_p: l_p.next()?,
                    l_ref: l_ref.next()?,
                    thr_on: thr_on.next()?,
                    thr_off: thr_off.next()?,
                    fired: fired.next()?,
                    last_event: last_event.next()?,
                    prev_luma: prev_luma.next()?,
                    settled: settled.next()?,
                    scratch,
                    stats: PhysicsStats::default(),
                    unheld: 0,
                };
                Some((band, spill))
            })
            .collect();
        crate::parallel::each(parallel, &mut work, |(band, events)| {
            band.run(passes, events)
        });
        for (band, events) in work {
            stats.add(band.stats);
            *unheld += band.unheld;
            if crate::limits::room_for(out, events.len()) {
                out.append(events);
            } else {
                *unheld += events.len() as u64;
            }
        }
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
                let mut view = Slow {
                    shared: self.shared,
                    base: self.base,
                    l_in: &mut *self.l_in,
                    l_p: &mut *self.l_p,
                    l_ref: &mut *self.l_ref,
                    thr_on: &mut *self.thr_on,
                    thr_off: &mut *self.thr_off,
                    fired: &mut *self.fired,
                    last_event: &mut *self.last_event,
                    refractory_drops: &mut self.stats.refractory_drops,
                    unheld: &mut self.unheld,
                };
                let span = (pass.t0, pass.t1);
                view.crossings(&slow, span, &pass.filter, &mut self.scratch.lanes, out);
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
        crate::simd::run(
            #[inline(always)]
            || self.row_here(y, range, pass, slow),
        )
    }

    /// [`Band::row`] in the caller's instruction set.
    #[inline(always)]
    fn row_here(
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
        // Kept in the band's scratch: arrays on the stack would be cleared at every call.
        let RowScratch {
            l1s,
            taus,
            decays,
            amps,
            kept,
        } = &mut self.scratch.row;
        for j in 0..n {
            let v = luma[j];
            l1s[j] = self.shared.log_lut[v as usize];
            let row = pass.filter[self.shared.filter_rows[v as usize] as usize];
            (taus[j], decays[j], amps[j]) = (row.tau, row.decay, row.amp);
        }
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
        // Room for the row's slow pixels where memory has it (else the frame is refused).
        if slow.capacity() - slow.len() < n && !crate::limits::room_for(slow, n.max(slow.len())) {
            self.unheld += n as u64;
            return settled;
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
}
