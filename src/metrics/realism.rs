//! Distribution-level statistics of an event stream, compared between a real recording and a
//! simulation of it (`v2ce eval realism`): what a network trained on simulated events sees as
//! the domain gap, and what no simulator can win by firing less.
//!
//! The cell-by-cell scores of [`super::stage1`] punish noise placed anywhere but where the
//! real sensor's noise was, which no simulator can know; these compare distributions instead:
//!
//! | statistic | value shown | distance |
//! |---|---|---|
//! | `rate_per_pixel` | mean events/s of a pixel | 1-D Wasserstein (W1) between the pixels' log10 rates (one that never fires at half an event over the window), decades |
//! | `firing_pixels` | share of pixels with an event | absolute difference |
//! | `inter_event_interval` | median interval between a pixel's events of one polarity, us | W1 between the log10 intervals, decades |
//! | `refractory_floor` | 1st percentile of a pixel's intervals (either polarity), us | absolute log10 ratio, decades |
//! | `timestamp_batching` | share of events that share their exact time with another event | absolute difference |
//! | `neighbour_batching` | share of events that share it with an event of one of the 8 neighbouring pixels | absolute difference |
//! | `on_share` | ON events / all events | absolute difference |
//! | `on_off_alternation` | share of a pixel's consecutive events of opposite polarity | absolute difference |
//! | `noise_floor_dark`, `noise_floor_bright` | events/s of a static pixel (its APS value unclipped and unchanged over the interval and the one before: [`FloorMeter`]), on the darker and the brighter half of those pixels | absolute log10 ratio, decades |
//! | `noise_floor_on_share` | ON events / all events on those pixels (leak fires ON, shot noise either way) | absolute difference |
//! | `rate_spectrum_peak` | the frequency, Hz, of the strongest line of the sensor's event-rate spectrum (5-500 Hz) | total variation between the two normalised spectra |
//!
//! Both streams are measured over the same window and the same pixels (the noise floor: the
//! same frames' static pixels). A statistic that a stream cannot define (no events, a pixel
//! that never fires twice, a window too short for a spectrum, no frames) is `None`, printed as
//! "undefined" and `null` in JSON, and so is its distance; no value is NaN. Every statistic
//! is computed on one thread in event order, so the numbers are the same on any machine.
//!
//! Timestamp batching is the share of events stamped at the same instant as others, which frame
//! simulators inflate (TIDES, arXiv 2606.02058).

use std::collections::HashSet;

use crate::error::{Error, Result};
use crate::event::{time_slice, Event};

/// One statistic of both streams.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Statistic {
    /// Its name (see the module docs).
    pub name: &'static str,
    /// The real stream's value.
    pub real: Option<f64>,
    /// The simulated stream's value.
    pub sim: Option<f64>,
    /// How far apart the two are (smaller is closer; see the module docs).
    pub distance: Option<f64>,
    /// The values' unit.
    pub unit: &'static str,
}

/// The statistics of both streams.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Report {
    /// The window measured, us: `[start, end)`.
    pub window_us: (i64, i64),
    /// The sensor, width and height.
    pub size: (u16, u16),
    /// Events of each stream in the window.
    pub real_events: u64,
    /// See `real_events`.
    pub sim_events: u64,
    /// The statistics, in the order of the module docs.
    pub statistics: Vec<Statistic>,
    /// The distributions behind some of them, for a plot ([`super::realism_plot`]).
    #[serde(skip)]
    pub curves: Vec<Curve>,
}

/// One distribution of both streams, as a plot draws it.
#[derive(Debug, Clone, PartialEq)]
pub struct Curve {
    /// What it is.
    pub title: &'static str,
    /// The x axis.
    pub x_label: &'static str,
    /// Where the points lie on the x axis.
    pub xs: Vec<f64>,
    /// The real stream's share at each point (0 to 1), and the simulated one's.
    pub real: Vec<f64>,
    /// See `real`.
    pub sim: Vec<f64>,
}

/// Histogram bins summed into one point of a curve (a tenth of a decade).
const CURVE_BINS: usize = 5;

/// The curve of two histograms on the same bins: shares per tenth of a decade, at their
/// centres in log10 units, trimmed to where either has any.
fn hist_curve(title: &'static str, x_label: &'static str, a: &LogHist, b: &LogHist) -> Curve {
    let points = |h: &LogHist| -> Vec<f64> {
        h.counts
            .chunks(CURVE_BINS)
            .map(|c| c.iter().sum::<u64>() as f64 / h.total.max(1) as f64)
            .collect()
    };
    let (real, sim) = (points(a), points(b));
    let xs: Vec<f64> = (0..real.len())
        .map(|i| {
            a.lo + (i * CURVE_BINS) as f64 / BINS_PER_DECADE
                + 0.5 * CURVE_BINS as f64 / BINS_PER_DECADE
        })
        .collect();
    let used = |i: &usize| real[*i] > 0.0 || sim[*i] > 0.0;
    let first = (0..real.len()).find(used).unwrap_or(0);
    let last = (0..real.len()).rev().find(used).unwrap_or(0).max(first);
    Curve {
        title,
        x_label,
        xs: xs[first..=last].to_vec(),
        real: real[first..=last].to_vec(),
        sim: sim[first..=last].to_vec(),
    }
}

/// log10 bins per decade of the histograms.
const BINS_PER_DECADE: f64 = 50.0;

/// A histogram of positive values on a log10 scale, `lo` to `hi` decades (values outside go
/// to the end bins).
#[derive(Debug, Clone, PartialEq)]
struct LogHist {
    lo: f64,
    counts: Vec<u64>,
    total: u64,
}

impl LogHist {
    fn new(lo: f64, hi: f64) -> Self {
        let n = ((hi - lo) * BINS_PER_DECADE).ceil() as usize;
        LogHist {
            lo,
            counts: vec![0; n.max(1)],
            total: 0,
        }
    }

    fn add(&mut self, value: f64, times: u64) {
        let at = (value.log10() - self.lo) * BINS_PER_DECADE;
        // NaN and values at or below zero land in the first bin.
        let i = if at.is_nan() || at < 0.0 {
            0
        } else {
            (at as usize).min(self.counts.len() - 1)
        };
        self.counts[i] += times;
        self.total += times;
    }

    /// The value at quantile `q` (0 to 1), at its bin's centre on the log scale.
    fn quantile(&self, q: f64) -> Option<f64> {
        if self.total == 0 {
            return None;
        }
        let want = ((q * self.total as f64).ceil() as u64).clamp(1, self.total);
        let mut seen = 0;
        for (i, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= want {
                return Some(10f64.powf(self.lo + (i as f64 + 0.5) / BINS_PER_DECADE));
            }
        }
        None
    }

    /// The 1-D Wasserstein distance between the two distributions of log10 values, decades.
    fn w1(&self, other: &LogHist) -> Option<f64> {
        if self.total == 0 || other.total == 0 || self.counts.len() != other.counts.len() {
            return None;
        }
        let (mut a, mut b, mut sum) = (0u64, 0u64, 0.0);
        for (&x, &y) in self.counts.iter().zip(&other.counts) {
            a += x;
            b += y;
            sum += (a as f64 / self.total as f64 - b as f64 / other.total as f64).abs();
        }
        Some(sum / BINS_PER_DECADE)
    }
}

/// Spectrum: event counts in bins of this many us.
const SPECTRUM_BIN_US: i64 = 1000;
/// Bins per segment (about a second).
const SPECTRUM_SEGMENT: usize = 1024;
/// Lines below this frequency (the scene's own motion) are left out.
const SPECTRUM_LOW_HZ: f64 = 5.0;
/// At most this many segments, spread evenly over the window, are averaged.
const SPECTRUM_MAX_SEGMENTS: usize = 256;

/// What [`profile`] measures of one stream.
#[derive(Debug, Clone, PartialEq)]
struct Profile {
    events: u64,
    rates: LogHist,
    firing: Option<f64>,
    intervals: LogHist,
    any_intervals: LogHist,
    batching: Option<f64>,
    neighbour_batching: Option<f64>,
    on_share: Option<f64>,
    alternation: Option<f64>,
    /// Normalised power per frequency line from `SPECTRUM_LOW_HZ` up (`None`: too short or no
    /// events), and the frequency of each line.
    spectrum: Option<Vec<f64>>,
}

/// Per-pixel state while a stream is read: 13 bytes a pixel.
const BYTES_PER_PIXEL: u64 = 13;

/// Measures `events` (sorted by time) of a `size` sensor in `window`.
fn profile(events: &[Event], size: (u16, u16), window: (i64, i64)) -> Result<Profile> {
    let (w, h) = (usize::from(size.0), usize::from(size.1));
    let pixels = w * h;
    crate::limits::memory(
        "sensor size",
        pixels as u64 * BYTES_PER_PIXEL,
        &format!("the realism statistics of a {} x {} sensor", size.0, size.1),
    )?;
    let events = time_slice(events, window.0, window.1);
    let seconds = (window.1 - window.0) as f64 * 1e-6;
    let mut last_t = vec![i64::MIN; pixels];
    let mut last_on = vec![false; pixels];
    let mut count = vec![0u32; pixels];
    // Intervals from 1 us (and 0) to 10^12 us.
    let mut intervals = LogHist::new(0.0, 12.0);
    let mut any_intervals = LogHist::new(0.0, 12.0);
    let (mut pairs, mut flips, mut on) = (0u64, 0u64, 0u64);
    for e in events {
        let i = usize::from(e.y) * w + usize::from(e.x);
        if i >= pixels {
            return Err(Error::invalid(
                "event",
                format!(
                    "({}, {}) is outside the {} x {} sensor",
                    e.x, e.y, size.0, size.1
                ),
            ));
        }
        on += u64::from(e.on);
        if last_t[i] != i64::MIN {
            let dt = e.t.saturating_sub(last_t[i]) as f64;
            any_intervals.add(dt, 1);
            pairs += 1;
            flips += u64::from(last_on[i] != e.on);
        }
        last_t[i] = e.t;
        last_on[i] = e.on;
        count[i] = count[i].saturating_add(1);
    }
    // Same-polarity intervals: a second pass per polarity keeps the state at 13 bytes a pixel.
    for polarity in [true, false] {
        last_t.iter_mut().for_each(|t| *t = i64::MIN);
        for e in events.iter().filter(|e| e.on == polarity) {
            let i = usize::from(e.y) * w + usize::from(e.x);
            if last_t[i] != i64::MIN {
                intervals.add(e.t.saturating_sub(last_t[i]) as f64, 1);
            }
            last_t[i] = e.t;
        }
    }
    // Rates from 10^-4 to 10^7 events/s; a pixel without an event at half an event over the
    // window (its rate is below that, and the log needs a value).
    let mut rates = LogHist::new(-4.0, 7.0);
    let floor = 0.5 / seconds.max(1e-6);
    for &c in &count {
        rates.add(
            if c == 0 {
                floor
            } else {
                f64::from(c) / seconds
            },
            1,
        );
    }
    let firing =
        (pixels > 0).then(|| count.iter().filter(|&&c| c > 0).count() as f64 / pixels as f64);
    let n = events.len() as u64;
    let share = |k: u64, of: u64| (of > 0).then(|| k as f64 / of as f64);
    let (batched, neighbours) = batching(events, w, h);
    Ok(Profile {
        events: n,
        rates,
        firing,
        intervals,
        any_intervals,
        batching: share(batched, n),
        neighbour_batching: share(neighbours, n),
        on_share: share(on, n),
        alternation: share(flips, pairs),
        spectrum: spectrum(events, window),
    })
}

/// Events that share their exact time with another event, and those that share it with an
/// event of one of their 8 neighbouring pixels.
fn batching(events: &[Event], w: usize, h: usize) -> (u64, u64) {
    let (mut batched, mut neighbours) = (0u64, 0u64);
    let mut at = HashSet::new();
    for run in events.chunk_by(|a, b| a.t == b.t) {
        if run.len() < 2 {
            continue;
        }
        batched += run.len() as u64;
        at.clear();
        at.extend(run.iter().map(|e| (e.x, e.y)));
        for e in run {
            let (x, y) = (usize::from(e.x), usize::from(e.y));
            let near = (y.saturating_sub(1)..=(y + 1).min(h.saturating_sub(1))).any(|ny| {
                (x.saturating_sub(1)..=(x + 1).min(w.saturating_sub(1)))
                    .any(|nx| (nx, ny) != (x, y) && at.contains(&(nx as u16, ny as u16)))
            });
            neighbours += u64::from(near);
        }
    }
    (batched, neighbours)
}

/// The normalised power spectrum of the sensor's event rate (counts in 1 ms bins, segments of
/// 1024 bins with a Hann window, averaged), lines from `SPECTRUM_LOW_HZ` to 500 Hz; `None`
/// for a window shorter than a segment or without events.
fn spectrum(events: &[Event], window: (i64, i64)) -> Option<Vec<f64>> {
    let bins = usize::try_from((window.1 - window.0) / SPECTRUM_BIN_US).ok()?;
    let segments = bins / SPECTRUM_SEGMENT;
    if segments == 0 || events.is_empty() {
        return None;
    }
    let n = SPECTRUM_SEGMENT;
    let lines: Vec<usize> = (1..=n / 2)
        .filter(|&k| line_hz(k) >= SPECTRUM_LOW_HZ)
        .collect();
    let hann: Vec<f64> = (0..n)
        .map(|i| 0.5 - 0.5 * (std::f64::consts::TAU * i as f64 / n as f64).cos())
        .collect();
    let (cos, sin): (Vec<f64>, Vec<f64>) = (0..n)
        .map(|i| {
            let a = std::f64::consts::TAU * i as f64 / n as f64;
            (a.cos(), a.sin())
        })
        .unzip();
    let used = segments.min(SPECTRUM_MAX_SEGMENTS);
    let mut power = vec![0.0f64; lines.len()];
    let mut counts = vec![0.0f64; n];
    for s in 0..used {
        // Evenly spread, always the same ones.
        let seg = s * segments / used;
        let start = window.0 + (seg * n) as i64 * SPECTRUM_BIN_US;
        counts.iter_mut().for_each(|c| *c = 0.0);
        for e in time_slice(events, start, start + n as i64 * SPECTRUM_BIN_US) {
            counts[((e.t - start) / SPECTRUM_BIN_US) as usize] += 1.0;
        }
        let mean = counts.iter().sum::<f64>() / n as f64;
        for (p, &k) in power.iter_mut().zip(&lines) {
            let (mut re, mut im) = (0.0, 0.0);
            for i in 0..n {
                let v = (counts[i] - mean) * hann[i];
                let j = (i * k) % n;
                re += v * cos[j];
                im -= v * sin[j];
            }
            *p += re * re + im * im;
        }
    }
    let total: f64 = power.iter().sum();
    if total <= 0.0 || !total.is_finite() {
        return None;
    }
    Some(power.iter().map(|p| p / total).collect())
}

/// The frequency of spectrum line `k`, Hz.
fn line_hz(k: usize) -> f64 {
    k as f64 * 1e6 / (SPECTRUM_SEGMENT as f64 * SPECTRUM_BIN_US as f64)
}

/// The frequency of the strongest line of a spectrum from [`spectrum`].
fn peak_hz(spectrum: &[f64]) -> Option<f64> {
    let first = (1..).find(|&k| line_hz(k) >= SPECTRUM_LOW_HZ)?;
    let (i, _) = spectrum
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1).then(b.0.cmp(&a.0)))?;
    Some(line_hz(first + i))
}

/// The rates of the settled static pixels (see [`FloorMeter`]), dark and bright halves:
/// events and pixel-seconds of each, and the ON events of both.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct NoiseFloor {
    /// Events on the darker half of the static pixels, and their pixel-seconds.
    pub dark: (u64, f64),
    /// The same on the brighter half.
    pub bright: (u64, f64),
    /// ON events on either half.
    pub on: u64,
}

impl NoiseFloor {
    /// Events per pixel-second on the dark and the bright static pixels.
    pub fn rates(&self) -> (Option<f64>, Option<f64>) {
        let rate = |(n, s): (u64, f64)| (s > 0.0).then(|| n as f64 / s);
        (rate(self.dark), rate(self.bright))
    }

    /// The share of the floor's events that are ON (leak fires ON only, shot noise either way).
    pub fn on_share(&self) -> Option<f64> {
        let all = self.dark.0 + self.bright.0;
        (all > 0).then(|| self.on as f64 / all as f64)
    }
}

/// A pixel whose value changes by at most this share of it (or of the dark floor below) from
/// one frame to the next is still over that interval.
const STATIC_SHARE: f64 = 0.03;
/// Values below this share of full scale count as this (APS read noise dominates there).
const DARK_FLOOR: f64 = 0.01;
/// A pixel at or above this share of full scale in either frame is clipped: its value cannot
/// show a change of light, so it is never static. On the davis346 clip its clipped "still"
/// pixels fire 2.0 events/s, two hundred times the others' floor.
const CLIPPED: f64 = 0.98;
/// Intervals in a row a pixel must be still to count: the interval measured and the one
/// before. One is not enough: a pixel whose light changed just before the interval still
/// fires as its photoreceptor settles and its half-crossed threshold completes. On the
/// davis346 clip one still interval gives a real floor of 0.016 / 0.009 events/s (dark /
/// bright), two 0.0045 / 0.0038, most of them ON (leak); more intervals barely lower it.
pub const SETTLED_INTERVALS: u8 = 2;

/// Measures the noise floors of a real and a simulated stream over consecutive frames: a pixel
/// is static over an interval where it is settled, its value below `CLIPPED` and changed by at
/// most `STATIC_SHARE` in this interval and each of the `SETTLED_INTERVALS - 1` before; the
/// static pixels of each interval are split at their median value into dark and bright.
/// Intervals must be added in time order; a gap between them starts the count again.
#[derive(Debug, Clone)]
pub struct FloorMeter {
    width: usize,
    full: u16,
    class: Vec<u8>,
    still_for: Vec<u8>,
    last_end: Option<i64>,
    values: Vec<u16>,
    /// The real stream's floor and the simulated stream's.
    pub floors: [NoiseFloor; 2],
}

impl FloorMeter {
    /// A meter for frames `width` pixels wide of linear luminance up to `full`.
    pub fn new(width: usize, full: u16) -> Self {
        FloorMeter {
            width,
            full,
            class: Vec::new(),
            still_for: Vec::new(),
            last_end: None,
            values: Vec::new(),
            floors: [NoiseFloor::default(); 2],
        }
    }

    /// Whether pixel `i` (row-major) was static in the interval last added: `Some(false)` for
    /// a dark one, `Some(true)` for a bright one, `None` where it was not static.
    pub fn static_pixel(&self, i: usize) -> Option<bool> {
        match self.class.get(i) {
            Some(1) => Some(false),
            Some(2) => Some(true),
            _ => None,
        }
    }

    /// Adds the interval between frame `a` at `t0` and frame `b` at `t1`, for the `real` and
    /// `sim` events (each sorted by time).
    pub fn add(&mut self, a: &[u16], b: &[u16], (t0, t1): (i64, i64), streams: [&[Event]; 2]) {
        let seconds = (t1 - t0) as f64 * 1e-6;
        let follows = self.last_end == Some(t0) && self.still_for.len() == a.len();
        self.last_end = Some(t1);
        self.class.clear();
        if !follows {
            self.still_for.clear();
            self.still_for.resize(a.len(), 0);
        }
        if seconds <= 0.0 || a.len() != b.len() {
            self.still_for.iter_mut().for_each(|s| *s = 0);
            return;
        }
        let dark_floor = DARK_FLOOR * f64::from(self.full);
        let clipped = CLIPPED * f64::from(self.full);
        let values = &mut self.values;
        values.clear();
        self.class
            .extend(a.iter().zip(b).zip(self.still_for.iter_mut()).map(
                |((&va, &vb), still_for)| {
                    let top = f64::from(va.max(vb));
                    let still = top < clipped
                        && f64::from(va.abs_diff(vb)) <= STATIC_SHARE * top.max(dark_floor);
                    *still_for = if still {
                        still_for.saturating_add(1)
                    } else {
                        0
                    };
                    let settled = *still_for >= SETTLED_INTERVALS;
                    if settled {
                        values.push(va.max(vb));
                    }
                    u8::from(settled)
                },
            ));
        if values.is_empty() {
            return;
        }
        let mid = values.len() / 2;
        let (_, &mut median, _) = values.select_nth_unstable(mid);
        let (mut dark, mut bright) = (0u64, 0u64);
        for (c, (&va, &vb)) in self.class.iter_mut().zip(a.iter().zip(b)) {
            if *c == 1 {
                if va.max(vb) < median {
                    dark += 1;
                } else {
                    *c = 2;
                    bright += 1;
                }
            }
        }
        for (events, floor) in streams.iter().zip(self.floors.iter_mut()) {
            floor.dark.1 += dark as f64 * seconds;
            floor.bright.1 += bright as f64 * seconds;
            for e in time_slice(events, t0, t1) {
                let counted = match self
                    .class
                    .get(usize::from(e.y) * self.width + usize::from(e.x))
                {
                    Some(1) => &mut floor.dark.0,
                    Some(2) => &mut floor.bright.0,
                    _ => continue,
                };
                *counted += 1;
                floor.on += u64::from(e.on);
            }
        }
    }
}

/// `floors`, where frames were given, are their noise floors ([`FloorMeter`]).
pub fn compare(
    real: &[Event],
    sim: &[Event],
    size: (u16, u16),
    window: (i64, i64),
    floors: Option<[NoiseFloor; 2]>,
) -> Result<Report> {
    if window.1 <= window.0 {
        return Err(Error::invalid(
            "window",
            format!("[{}, {}) us is empty", window.0, window.1),
        ));
    }
    crate::time::span("window", window.0, window.1)?;
    let a = profile(real, size, window)?;
    let b = profile(sim, size, window)?;
    let diff = |x: Option<f64>, y: Option<f64>| Some((x? - y?).abs());
    let log_ratio = |x: Option<f64>, y: Option<f64>| {
        let (x, y) = (x?, y?);
        (x > 0.0 && y > 0.0).then(|| (x / y).log10().abs())
    };
    let stat = |name, unit, real: Option<f64>, sim: Option<f64>, distance: Option<f64>| Statistic {
        name,
        real: real.filter(|v| v.is_finite()),
        sim: sim.filter(|v| v.is_finite()),
        distance: distance.filter(|v| v.is_finite()),
        unit,
    };
    let pixels = f64::from(size.0) * f64::from(size.1);
    let seconds = (window.1 - window.0) as f64 * 1e-6;
    let mean_rate = |p: &Profile| (pixels > 0.0).then(|| p.events as f64 / pixels / seconds);
    let floor_a = a.any_intervals.quantile(0.01);
    let floor_b = b.any_intervals.quantile(0.01);
    let mut statistics = vec![
        stat(
            "rate_per_pixel",
            "events/s",
            mean_rate(&a),
            mean_rate(&b),
            a.rates.w1(&b.rates),
        ),
        stat(
            "firing_pixels",
            "share",
            a.firing,
            b.firing,
            diff(a.firing, b.firing),
        ),
        stat(
            "inter_event_interval",
            "us",
            a.intervals.quantile(0.5),
            b.intervals.quantile(0.5),
            a.intervals.w1(&b.intervals),
        ),
        stat(
            "refractory_floor",
            "us",
            floor_a,
            floor_b,
            log_ratio(floor_a, floor_b),
        ),
        stat(
            "timestamp_batching",
            "share",
            a.batching,
            b.batching,
            diff(a.batching, b.batching),
        ),
        stat(
            "neighbour_batching",
            "share",
            a.neighbour_batching,
            b.neighbour_batching,
            diff(a.neighbour_batching, b.neighbour_batching),
        ),
        stat(
            "on_share",
            "share",
            a.on_share,
            b.on_share,
            diff(a.on_share, b.on_share),
        ),
        stat(
            "on_off_alternation",
            "share",
            a.alternation,
            b.alternation,
            diff(a.alternation, b.alternation),
        ),
    ];
    let [(real_dark, real_bright), (sim_dark, sim_bright)] =
        floors.map_or([(None, None); 2], |[r, s]| [r.rates(), s.rates()]);
    for (name, r, s) in [
        ("noise_floor_dark", real_dark, sim_dark),
        ("noise_floor_bright", real_bright, sim_bright),
    ] {
        statistics.push(stat(name, "events/s", r, s, log_ratio(r, s)));
    }
    let [real_on, sim_on] = floors.map_or([None; 2], |[r, s]| [r.on_share(), s.on_share()]);
    statistics.push(stat(
        "noise_floor_on_share",
        "share",
        real_on,
        sim_on,
        diff(real_on, sim_on),
    ));
    let tv = match (&a.spectrum, &b.spectrum) {
        (Some(x), Some(y)) => Some(0.5 * x.iter().zip(y).map(|(p, q)| (p - q).abs()).sum::<f64>()),
        _ => None,
    };
    statistics.push(stat(
        "rate_spectrum_peak",
        "Hz",
        a.spectrum.as_deref().and_then(peak_hz),
        b.spectrum.as_deref().and_then(peak_hz),
        tv,
    ));
    let mut curves = vec![
        hist_curve(
            "events per second of a pixel",
            "log10 events/s",
            &a.rates,
            &b.rates,
        ),
        hist_curve(
            "intervals between a pixel's events of one polarity",
            "log10 us",
            &a.intervals,
            &b.intervals,
        ),
    ];
    if let (Some(x), Some(y)) = (&a.spectrum, &b.spectrum) {
        let first = (1..).find(|&k| line_hz(k) >= SPECTRUM_LOW_HZ).unwrap_or(1);
        curves.push(Curve {
            title: "spectrum of the sensor's event rate",
            x_label: "Hz",
            xs: (0..x.len()).map(|i| line_hz(first + i)).collect(),
            real: x.clone(),
            sim: y.clone(),
        });
    }
    Ok(Report {
        window_us: window,
        size,
        real_events: a.events,
        sim_events: b.events,
        statistics,
        curves,
    })
}

impl Report {
    /// The statistic `name`.
    pub fn get(&self, name: &str) -> Option<&Statistic> {
        self.statistics.iter().find(|s| s.name == name)
    }

    /// A table: one statistic a line, the values side by side with their distance.
    pub fn table(&self) -> String {
        let show =
            |v: Option<f64>| v.map_or_else(|| "undefined".to_string(), |v| format!("{v:.4}"));
        let mut out = format!(
            "window {} .. {} us, {} x {} pixels; real events {}, simulated {}\n{:<22} {:>14} {:>14} {:>10}  unit\n",
            self.window_us.0,
            self.window_us.1,
            self.size.0,
            self.size.1,
            self.real_events,
            self.sim_events,
            "statistic",
            "real",
            "sim",
            "distance"
        );
        for s in &self.statistics {
            out.push_str(&format!(
                "{:<22} {:>14} {:>14} {:>10}  {}\n",
                s.name,
                show(s.real),
                show(s.sim),
                show(s.distance),
                s.unit
            ));
        }
        out.pop();
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_xoshiro::Xoshiro256PlusPlus;

    /// Poisson events of `rate` per pixel (random polarity) over `seconds` on a `w x h` sensor.
    fn poisson(rate: f64, seconds: f64, w: u16, h: u16, seed: u64) -> Vec<Event> {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        let mut events = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let mut t = 0.0;
                loop {
                    let u: f64 = rng.gen_range(f64::MIN_POSITIVE..1.0);
                    t += -u.ln() / rate;
                    if t >= seconds {
                        break;
                    }
                    events.push(Event::new((t * 1e6) as i64, x, y, rng.gen_bool(0.5)));
                }
            }
        }
        events.sort_by_key(|e| e.t);
        events
    }

    fn value(r: &Report, name: &str) -> (Option<f64>, Option<f64>, Option<f64>) {
        let s = r.get(name).unwrap();
        (s.real, s.sim, s.distance)
    }

    /// Poisson noise of a known rate: the mean rate is the rate, the pixels that fire are
    /// `1 - exp(-rate T)`, the same-polarity intervals (rate / 2 each) have median
    /// `ln 2 / (rate / 2)`, ON is half, and the alternation is half. Two draws of the same
    /// process are close; a rate ten times higher is a decade off.
    #[test]
    fn poisson_noise_gives_its_closed_forms() {
        let (rate, seconds) = (20.0, 10.0);
        let a = poisson(rate, seconds, 64, 48, 1);
        let b = poisson(rate, seconds, 64, 48, 2);
        let window = (0, (seconds * 1e6) as i64);
        let r = compare(&a, &b, (64, 48), window, None).unwrap();
        let close = |v: Option<f64>, want: f64, tol: f64| {
            let v = v.unwrap();
            assert!((v / want - 1.0).abs() < tol, "{v} vs {want}");
        };
        close(value(&r, "rate_per_pixel").0, rate, 0.02);
        close(
            value(&r, "firing_pixels").0,
            1.0 - (-rate * seconds).exp(),
            1e-9,
        );
        close(
            value(&r, "inter_event_interval").0,
            2f64.ln() / (rate / 2.0) * 1e6,
            0.06,
        );
        close(value(&r, "on_share").0, 0.5, 0.03);
        close(value(&r, "on_off_alternation").0, 0.5, 0.03);
        assert!(value(&r, "rate_per_pixel").2.unwrap() < 0.05);
        assert!(value(&r, "inter_event_interval").2.unwrap() < 0.05);
        let c = poisson(10.0 * rate, seconds, 64, 48, 3);
        let far = compare(&a, &c, (64, 48), window, None).unwrap();
        let d = value(&far, "rate_per_pixel").2.unwrap();
        assert!((d - 1.0).abs() < 0.1, "{d}");
        let d = value(&far, "inter_event_interval").2.unwrap();
        assert!((d - 1.0).abs() < 0.1, "{d}");
        // Deterministic: the same numbers again.
        assert_eq!(compare(&a, &b, (64, 48), window, None).unwrap(), r);
    }

    /// Pixels that fire every `R` us exactly (a refractory period that binds) have their
    /// floor and every interval at `R`; events all stamped at frame times are all batched,
    /// and with their neighbours; distinct times batch none.
    #[test]
    fn refractory_and_batching_are_exact() {
        let period = 500i64;
        let mut events = Vec::new();
        for k in 0..2000i64 {
            for x in 0..4u16 {
                // Times staggered by pixel: no two events share one.
                events.push(Event::new(k * period + i64::from(x), x, 0, k % 2 == 0));
            }
        }
        let window = (0, 2000 * period);
        let r = compare(&events, &events, (4, 1), window, None).unwrap();
        let floor = value(&r, "refractory_floor").0.unwrap();
        assert!((floor / period as f64 - 1.0).abs() < 0.025, "{floor}");
        assert_eq!(value(&r, "refractory_floor").2, Some(0.0));
        assert_eq!(value(&r, "timestamp_batching").0, Some(0.0));
        assert_eq!(value(&r, "on_off_alternation").0, Some(1.0));
        // Same-polarity intervals are two periods.
        let iei = value(&r, "inter_event_interval").0.unwrap();
        assert!((iei / (2 * period) as f64 - 1.0).abs() < 0.025, "{iei}");
        let framed: Vec<Event> = events
            .iter()
            .map(|e| Event::new(e.t - e.t % period, e.x, e.y, e.on))
            .collect();
        let r = compare(&events, &framed, (4, 1), window, None).unwrap();
        assert_eq!(value(&r, "timestamp_batching").1, Some(1.0));
        assert_eq!(value(&r, "neighbour_batching").1, Some(1.0));
        assert_eq!(value(&r, "timestamp_batching").2, Some(1.0));
        // Two far-apart pixels at one time: batched, not with a neighbour.
        let apart = [Event::new(5, 0, 0, true), Event::new(5, 3, 0, true)];
        let r = compare(&apart, &apart, (4, 1), (0, 10), None).unwrap();
        assert_eq!(value(&r, "timestamp_batching").0, Some(1.0));
        assert_eq!(value(&r, "neighbour_batching").0, Some(0.0));
    }

    /// A sensor-wide rate modulated at a known frequency peaks there.
    #[test]
    fn flicker_shows_as_its_frequency() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(9);
        let hz = 100.0;
        let mut events = Vec::new();
        for ms in 0..4000i64 {
            let phase = std::f64::consts::TAU * hz * ms as f64 * 1e-3;
            let n = (20.0 * (1.0 + phase.sin())).round() as usize;
            for _ in 0..n {
                let t = ms * 1000 + rng.gen_range(0..1000);
                events.push(Event::new(
                    t,
                    rng.gen_range(0..32),
                    rng.gen_range(0..32),
                    true,
                ));
            }
        }
        events.sort_by_key(|e| e.t);
        let flat = poisson(40.0 / 1024.0 * 1000.0, 4.0, 32, 32, 4);
        let r = compare(&events, &flat, (32, 32), (0, 4_000_000), None).unwrap();
        let (peak, _, tv) = value(&r, "rate_spectrum_peak");
        assert!((peak.unwrap() - hz).abs() < 1.0, "{peak:?}");
        assert!(tv.unwrap() > 0.5, "{tv:?}");
        let same = compare(&events, &events, (32, 32), (0, 4_000_000), None).unwrap();
        assert_eq!(value(&same, "rate_spectrum_peak").2, Some(0.0));
    }

    /// Static frames with Poisson noise of one rate on the dark half and another on the bright
    /// half: the noise floor finds both; moving pixels are left out.
    #[test]
    fn the_noise_floor_is_the_rate_on_static_pixels() {
        let (w, h) = (40u16, 40u16);
        let n = usize::from(w) * usize::from(h);
        // Left half dark, right half bright; the bottom rows change (moving).
        let frame = |k: u16| -> Vec<u16> {
            (0..n)
                .map(|i| {
                    let (x, y) = (i % 40, i / 40);
                    if y >= 36 {
                        1000 + 5000 * (k % 2)
                    } else if x < 20 {
                        2000
                    } else {
                        40000
                    }
                })
                .collect()
        };
        let (dark_rate, bright_rate) = (5.0, 0.5);
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(5);
        let mut events = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let rate = if y >= 36 {
                    100.0
                } else if x < 20 {
                    dark_rate
                } else {
                    bright_rate
                };
                let mut t = 0.0;
                loop {
                    t += -rng.gen_range(f64::MIN_POSITIVE..1.0f64).ln() / rate;
                    if t >= 20.0 {
                        break;
                    }
                    events.push(Event::new((t * 1e6) as i64, x, y, true));
                }
            }
        }
        events.sort_by_key(|e| e.t);
        let mut meter = FloorMeter::new(usize::from(w), u16::MAX);
        for k in 0..20u16 {
            let t0 = i64::from(k) * 1_000_000;
            meter.add(
                &frame(k),
                &frame(k + 1),
                (t0, t0 + 1_000_000),
                [&events, &[]],
            );
        }
        let floors = meter.floors;
        let (dark, bright) = floors[0].rates();
        assert!((dark.unwrap() / dark_rate - 1.0).abs() < 0.1, "{dark:?}");
        assert!(
            (bright.unwrap() / bright_rate - 1.0).abs() < 0.15,
            "{bright:?}"
        );
        let r = compare(&events, &[], (w, h), (0, 20_000_000), Some(floors)).unwrap();
        // Silence has no noise floor to compare: a zero rate is undefined on a log scale.
        assert_eq!(value(&r, "noise_floor_dark").1, Some(0.0));
        assert_eq!(value(&r, "noise_floor_dark").2, None);
        // Every event here is ON; silence has no share.
        assert_eq!(value(&r, "noise_floor_on_share").0, Some(1.0));
        assert_eq!(value(&r, "noise_floor_on_share").1, None);
    }

    /// A pixel is static only once still for `SETTLED_INTERVALS` intervals in a row, never
    /// where clipped, and a gap between intervals starts the count again.
    #[test]
    fn the_noise_floor_takes_settled_unclipped_pixels() {
        // Four pixels: 0 still throughout, 1 clipped and still, 2 changes in interval 0 only,
        // 3 still but dark (below the dark floor, judged against it).
        let frames: [[u16; 4]; 4] = [
            [30000, 65535, 10000, 100],
            [30000, 65535, 20000, 110],
            [30100, 65535, 20000, 100],
            [30000, 65535, 20100, 105],
        ];
        let one_each: Vec<Event> = (0..3i64)
            .flat_map(|k| {
                (0..4u16).map(move |x| Event::new(k * 1_000_000 + 500_000, x, 0, x % 2 == 0))
            })
            .collect();
        let mut meter = FloorMeter::new(4, u16::MAX);
        let mut statics = Vec::new();
        for k in 0..3usize {
            let t0 = k as i64 * 1_000_000;
            meter.add(
                &frames[k],
                &frames[k + 1],
                (t0, t0 + 1_000_000),
                [&one_each, &[]],
            );
            statics.push((0..4).map(|i| meter.static_pixel(i)).collect::<Vec<_>>());
        }
        // Interval 0: nothing settled yet. Interval 1: pixels 0 and 3 (2 changed in 0).
        // Interval 2: pixel 2 has been still for two intervals too.
        assert_eq!(statics[0], [None; 4]);
        assert_eq!(statics[1], [Some(true), None, None, Some(false)]);
        assert_eq!(statics[2].iter().filter(|s| s.is_some()).count(), 3);
        assert_eq!(statics[2][1], None);
        let floor = meter.floors[0];
        assert_eq!(floor.dark.0 + floor.bright.0, 5);
        assert!((floor.dark.1 + floor.bright.1 - 5.0).abs() < 1e-9);
        // Counted: pixel 0 twice and pixel 2 once (ON), pixel 3 twice (OFF).
        assert_eq!(floor.on, 3);
        // A gap: the next interval does not follow the last, so nothing is settled in it.
        meter.add(&frames[2], &frames[3], (9_000_000, 10_000_000), [&[], &[]]);
        assert_eq!((0..4).filter_map(|i| meter.static_pixel(i)).count(), 0);
    }

    /// Empty streams, one event, one pixel, a wide sensor, a window without events: numbers or
    /// undefined, never NaN, and JSON that parses.
    #[test]
    fn bad_input_gives_undefined_not_nan() {
        let one = [Event::new(10, 0, 0, true)];
        type Case = (Vec<Event>, (u16, u16), (i64, i64));
        let cases: Vec<Case> = vec![
            (vec![], (10, 10), (0, 1000)),
            (one.to_vec(), (1, 1), (0, 1000)),
            (one.to_vec(), (8192, 2), (0, 2_000_000)),
            (one.to_vec(), (10, 10), (5000, 9000)),
            (
                (0..100).map(|t| Event::new(t, 0, 0, t % 3 == 0)).collect(),
                (1, 1),
                (0, 100),
            ),
        ];
        for (events, size, window) in cases {
            let r = compare(&events, &[], size, window, None).unwrap();
            let text = serde_json::to_string(&r).unwrap();
            assert!(!text.contains("NaN") && !text.contains("inf"), "{text}");
            let back: serde_json::Value = serde_json::from_str(&text).unwrap();
            assert_eq!(
                back["statistics"].as_array().unwrap().len(),
                r.statistics.len()
            );
            assert!(r.table().contains("undefined"));
        }
        assert!(compare(&one, &one, (4, 4), (10, 10), None).is_err());
        assert!(compare(&one, &one, (4, 4), (i64::MIN, i64::MAX), None).is_err());
        let outside = [Event::new(1, 9, 9, true)];
        assert!(compare(&outside, &[], (4, 4), (0, 10), None).is_err());
    }
}
