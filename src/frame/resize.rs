//! Resampling frames to another size by area averaging: each output pixel is the mean of the
//! input area it covers (fractional pixels weighted by coverage). This is the right filter for
//! linear luminance (it conserves the light), and it does not alias when shrinking.

use super::{Frame, FrameSource};
use crate::error::{Error, Result};
use crate::rounding::round_to_u16;

/// Per-output-pixel spans of input pixels with their weights, along one axis.
#[derive(Debug, Clone)]
struct Axis {
    // (first input index, weights summing to 1)
    spans: Vec<(usize, Vec<f32>)>,
    /// The longest span.
    taps: usize,
    /// Every span's first index, clamped so that `taps` pixels from it lie in the input.
    starts: Vec<usize>,
    /// Every span's weights in `taps` slots, at their offsets from its start (0 elsewhere).
    flat: Vec<f32>,
}

impl Axis {
    fn new(from: usize, to: usize) -> Self {
        let scale = from as f64 / to as f64;
        let spans: Vec<(usize, Vec<f32>)> = (0..to)
            .map(|o| {
                let (a, b) = (o as f64 * scale, (o + 1) as f64 * scale);
                let first = a.floor() as usize;
                let last = (b.ceil() as usize).min(from).max(first + 1);
                let weights: Vec<f32> = (first..last)
                    .map(|i| {
                        let covered = (b.min(i as f64 + 1.0) - a.max(i as f64)).max(0.0);
                        (covered / scale) as f32
                    })
                    .collect();
                let sum: f32 = weights.iter().sum();
                (first, weights.iter().map(|w| w / sum).collect())
            })
            .collect();
        let taps = spans
            .iter()
            .map(|(_, w)| w.len())
            .max()
            .unwrap_or(1)
            .min(from);
        let mut starts = Vec::with_capacity(to);
        let mut flat = vec![0.0; to * taps];
        for (o, (first, weights)) in spans.iter().enumerate() {
            let start = (*first).min(from - taps);
            starts.push(start);
            let slots = &mut flat[o * taps..(o + 1) * taps];
            slots[first - start..first - start + weights.len()].copy_from_slice(weights);
        }
        Axis {
            spans,
            taps,
            starts,
            flat,
        }
    }

    /// One row through the spans, `K` (= `taps`) slots each. The same sums as the spans'
    /// own: each pixel's terms are added in order from the same neutral element, and an empty
    /// slot adds `0 * v = +0`, which changes no sum of non-negative terms; the slots before a
    /// span's first pixel (a span clamped at the input's end) hold such zeros too, and a sum
    /// of them stays the neutral element's `-0 + +0 = +0`, which the first real term replaces
    /// exactly.
    #[inline(always)]
    fn row<const K: usize>(&self, src: &[u16], dst: &mut [f32]) {
        let zero: f32 = std::iter::empty::<f32>().sum();
        for ((d, &start), w) in dst
            .iter_mut()
            .zip(&self.starts)
            .zip(self.flat.chunks_exact(K))
        {
            let px = &src[start..start + K];
            let mut acc = zero;
            for k in 0..K {
                acc += w[k] * px[k] as f32;
            }
            *d = acc;
        }
    }
}

/// Resamples frames of one size to another.
#[derive(Debug, Clone)]
pub struct Resampler {
    from: (u16, u16),
    to: (u16, u16),
    x: Axis,
    y: Axis,
    rows: Vec<f32>,
}

impl Resampler {
    /// A resampler from `from` to `to` (width, height), both non-zero.
    pub fn new(from: (u16, u16), to: (u16, u16)) -> Result<Self> {
        if from.0 == 0 || from.1 == 0 || to.0 == 0 || to.1 == 0 {
            return Err(Error::invalid(
                "size",
                format!("cannot resample {from:?} to {to:?}"),
            ));
        }
        Ok(Resampler {
            from,
            to,
            x: Axis::new(from.0 as usize, to.0 as usize),
            y: Axis::new(from.1 as usize, to.1 as usize),
            rows: Vec::new(),
        })
    }

    /// `frame` at the target size (the same time).
    pub fn resample(&mut self, frame: &Frame) -> Result<Frame> {
        if (frame.width, frame.height) != self.from {
            return Err(Error::invalid(
                "frame",
                format!(
                    "{}x{} frame given to a resampler for {}x{}",
                    frame.width, frame.height, self.from.0, self.from.1
                ),
            ));
        }
        let (fw, fh) = (self.from.0 as usize, self.from.1 as usize);
        let tw = self.to.0 as usize;
        // Horizontal pass into f32 rows, then the vertical pass.
        self.rows.clear();
        self.rows.resize(tw * fh, 0.0);
        let taps = self.x.taps;
        for y in 0..fh {
            let src = &frame.luma[y * fw..(y + 1) * fw];
            let dst = &mut self.rows[y * tw..(y + 1) * tw];
            match taps {
                1 => self.x.row::<1>(src, dst),
                2 => self.x.row::<2>(src, dst),
                3 => self.x.row::<3>(src, dst),
                4 => self.x.row::<4>(src, dst),
                5 => self.x.row::<5>(src, dst),
                6 => self.x.row::<6>(src, dst),
                _ => {
                    for (d, (first, weights)) in dst.iter_mut().zip(&self.x.spans) {
                        *d = weights
                            .iter()
                            .zip(&src[*first..])
                            .map(|(w, &v)| w * v as f32)
                            .sum();
                    }
                }
            }
        }
        // Row by row: each output row sums its input rows in order (the same sum as pixel by
        // pixel, from the same neutral element), on vectors.
        let zero: f32 = std::iter::empty::<f32>().sum();
        let mut luma = Vec::with_capacity(tw * self.to.1 as usize);
        let mut acc = vec![zero; tw];
        for (first, weights) in &self.y.spans {
            acc.fill(zero);
            for (k, &w) in weights.iter().enumerate() {
                let row = &self.rows[(first + k) * tw..(first + k + 1) * tw];
                for (a, &r) in acc.iter_mut().zip(row) {
                    *a += w * r;
                }
            }
            luma.extend(acc.iter().map(|&v| round_to_u16(v)));
        }
        Ok(Frame {
            t: frame.t,
            width: self.to.0,
            height: self.to.1,
            luma,
            exposure_us: frame.exposure_us,
        })
    }
}

/// A source whose frames are resampled to a fixed size.
pub struct Resized {
    inner: Box<dyn FrameSource>,
    resampler: Option<Resampler>,
    size: (u16, u16),
}

impl Resized {
    /// Wraps `inner`; frames already at `size` pass through untouched.
    pub fn new(inner: Box<dyn FrameSource>, size: (u16, u16)) -> Result<Self> {
        let from = inner.size();
        let resampler = if from == size {
            None
        } else {
            Some(Resampler::new(from, size)?)
        };
        Ok(Resized {
            inner,
            resampler,
            size,
        })
    }
}

impl FrameSource for Resized {
    fn size(&self) -> (u16, u16) {
        self.size
    }

    fn next_frame(&mut self) -> Result<Option<Frame>> {
        let Some(frame) = self.inner.next_frame()? else {
            return Ok(None);
        };
        match &mut self.resampler {
            None => Ok(Some(frame)),
            Some(r) => r.resample(&frame).map(Some),
        }
    }

    fn describe(&self) -> String {
        match &self.resampler {
            None => self.inner.describe(),
            Some(r) => format!(
                "{} resampled to {}x{}",
                self.inner.describe(),
                r.to.0,
                r.to.1
            ),
        }
    }

    fn frames_hint(&self) -> Option<u64> {
        self.inner.frames_hint()
    }

    fn encoding(&self) -> super::SourceEncoding {
        self.inner.encoding()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn halving_averages_blocks_and_conserves_light() {
        let luma: Vec<u16> = (0..16).map(|i| i * 1000).collect();
        let frame = Frame {
            t: 7,
            width: 4,
            height: 4,
            luma,
            exposure_us: None,
        };
        let out = Resampler::new((4, 4), (2, 2))
            .unwrap()
            .resample(&frame)
            .unwrap();
        assert_eq!(out.t, 7);
        // Block (0,0): pixels 0, 1, 4, 5 -> mean 2.5 * 1000.
        assert_eq!(out.luma, vec![2500, 4500, 10500, 12500]);
    }

    #[test]
    fn odd_ratio_keeps_a_flat_frame_flat_and_conserves_a_ramp() {
        let frame = Frame::filled(0, 640, 480, 30_000);
        let mut r = Resampler::new((640, 480), (346, 260)).unwrap();
        let out = r.resample(&frame).unwrap();
        assert_eq!((out.width, out.height), (346, 260));
        assert!(out.luma.iter().all(|&v| v == 30_000));
        let ramp = Frame {
            t: 0,
            width: 640,
            height: 480,
            luma: (0..640 * 480).map(|i| ((i % 640) * 100) as u16).collect(),
            exposure_us: None,
        };
        let out = r.resample(&ramp).unwrap();
        let mean_in: f64 =
            ramp.luma.iter().map(|&v| v as f64).sum::<f64>() / ramp.luma.len() as f64;
        let mean_out: f64 = out.luma.iter().map(|&v| v as f64).sum::<f64>() / out.luma.len() as f64;
        assert!((mean_in - mean_out).abs() < 1.0, "{mean_in} vs {mean_out}");
        assert!(out.luma.windows(2).take(345).all(|w| w[0] < w[1]));
    }

    /// The definition, pixel by pixel: each output pixel the weighted sum down its column of
    /// the horizontal pass's rows, rounded.
    fn by_pixel(r: &Resampler, frame: &Frame) -> Vec<u16> {
        let (fw, fh, tw) = (r.from.0 as usize, r.from.1 as usize, r.to.0 as usize);
        let mut rows = vec![0f32; tw * fh];
        for y in 0..fh {
            for (x, (first, weights)) in r.x.spans.iter().enumerate() {
                rows[y * tw + x] = weights
                    .iter()
                    .zip(&frame.luma[y * fw + first..])
                    .map(|(w, &v)| w * v as f32)
                    .sum();
            }
        }
        let mut out = Vec::new();
        for (first, weights) in &r.y.spans {
            for x in 0..tw {
                let v: f32 = weights
                    .iter()
                    .enumerate()
                    .map(|(k, w)| w * rows[(first + k) * tw + x])
                    .sum();
                out.push(v.round().clamp(0.0, u16::MAX as f32) as u16);
            }
        }
        out
    }

    #[test]
    fn row_by_row_gives_the_pixel_by_pixel_result() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(3);
        for (from, to) in [
            ((640, 480), (346, 260)),
            ((346, 260), (640, 480)),
            ((1280, 720), (640, 480)),
            ((97, 13), (31, 29)),
            // Spans of every length the row pass takes (1 to 6 pixels) and longer ones.
            ((640, 480), (256, 200)),
            ((640, 480), (128, 100)),
            ((640, 480), (64, 48)),
            ((5, 3), (1, 1)),
            ((1, 1), (7, 5)),
            ((31, 7), (6, 7)),
        ] {
            let frame = Frame {
                t: 0,
                width: from.0,
                height: from.1,
                // Black pixels half the time: sums of zeros keep their sign.
                luma: (0..from.0 as usize * from.1 as usize)
                    .map(|_| if rng.gen() { 0 } else { rng.gen() })
                    .collect(),
                exposure_us: None,
            };
            let mut r = Resampler::new(from, to).unwrap();
            let want = by_pixel(&r, &frame);
            assert_eq!(r.resample(&frame).unwrap().luma, want, "{from:?} -> {to:?}");
        }
    }

    #[test]
    fn wrong_size_is_an_error() {
        let mut r = Resampler::new((4, 4), (2, 2)).unwrap();
        assert!(r.resample(&Frame::filled(0, 3, 4, 0)).is_err());
        assert!(Resampler::new((0, 4), (2, 2)).is_err());
    }
}
