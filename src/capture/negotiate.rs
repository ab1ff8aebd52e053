//! Choosing a pixel format, frame size and frame rate from what a camera offers (pure; no driver
//! types, so every rule is unit-tested).
//!
//! # The rule
//!
//! Only offers in one of the [`CameraConfig::formats`] are candidates. Each candidate (format,
//! size, rate) is ranked by, in this order:
//! 1. **size class**: the exact requested size, else a size covering the request (width and
//!    height both at least the requested ones), else any other size;
//! 2. **rate class**: a rate at or above the requested one (within 0.2%, so 29.97 meets 30), else
//!    a lower rate, else an unknown rate (the driver did not enumerate frame intervals);
//! 3. **size closeness**: among covering sizes the smallest area, among the others the largest;
//! 4. **rate closeness**: among rates meeting the request the lowest, among lower rates the
//!    highest;
//! 5. **format preference**: the position in [`CameraConfig::formats`];
//! 6. then the smaller width and height, then the earlier offer.
//!
//! So a size or rate match always outweighs format preference: a camera offering YUYV 640x480
//! only at 10 fps and MJPEG 640x480 at 30 fps streams MJPEG when 640x480 at 30 fps is asked for,
//! whatever the preference order.
//!
//! Drivers may describe sizes and frame intervals as stepwise or continuous ranges
//! ([`Sizes::Stepwise`], [`Rates::Stepwise`], [`Rates::Continuous`]); a range contributes the
//! one point of its grid that the rule above prefers.

use std::fmt;

use super::{fourcc_str, CameraConfig, PixelFormat};
use crate::error::{Error, Result};

/// Relative tolerance under which a rate still counts as meeting the requested one.
const RATE_TOLERANCE: f64 = 0.002;

/// A frame interval in seconds as a fraction `num / den` (the V4L2 convention: `1/30` is 30 fps).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Interval {
    /// Numerator (seconds).
    pub num: u32,
    /// Denominator.
    pub den: u32,
}

impl Interval {
    /// `num / den` seconds.
    pub fn new(num: u32, den: u32) -> Self {
        Interval { num, den }
    }

    /// The interval of a frame rate, with a millihertz resolution (30 -> 1/30, 29.97 -> 100/2997).
    /// `None` for a rate that is not finite and positive or too high to express.
    pub fn from_fps(fps: f64) -> Option<Self> {
        if !fps.is_finite() || fps <= 0.0 {
            return None;
        }
        let den = (fps * 1000.0).round();
        if !(1.0..=u32::MAX as f64).contains(&den) {
            return None;
        }
        Some(reduced(1000, den as u64))
    }

    /// The interval in seconds, `None` when it is zero or has a zero denominator.
    pub fn seconds(self) -> Option<f64> {
        (self.num > 0 && self.den > 0).then(|| self.num as f64 / self.den as f64)
    }

    /// The frame rate, `None` for an invalid interval.
    pub fn fps(self) -> Option<f64> {
        self.seconds().map(|s| 1.0 / s)
    }
}

impl fmt::Display for Interval {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.fps() {
            Some(fps) => write!(f, "{}", format_fps(fps)),
            None => write!(f, "{}/{} s", self.num, self.den),
        }
    }
}

/// A frame rate with at most two decimals and no trailing zeros: "30", "29.97", "7.5".
pub(crate) fn format_fps(fps: f64) -> String {
    let s = format!("{fps:.2}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

fn gcd(mut a: u64, mut b: u64) -> u64 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// `num / den` reduced; approximated with a microsecond resolution when it does not fit `u32`.
fn reduced(num: u64, den: u64) -> Interval {
    let g = gcd(num, den).max(1);
    let (n, d) = (num / g, den / g);
    match (u32::try_from(n), u32::try_from(d)) {
        (Ok(n), Ok(d)) => Interval::new(n, d),
        _ => {
            let us = (n as f64 / d as f64 * 1e6)
                .round()
                .clamp(1.0, u32::MAX as f64) as u64;
            let g = gcd(us, 1_000_000);
            Interval::new((us / g) as u32, (1_000_000 / g) as u32)
        }
    }
}

/// The frame sizes of one offer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Sizes {
    /// One size.
    Discrete {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
    },
    /// Every size `min + k * step` up to `max` in each dimension (a continuous range has step 1).
    Stepwise {
        /// Smallest width.
        min_width: u32,
        /// Largest width.
        max_width: u32,
        /// Width step (0 is read as 1).
        step_width: u32,
        /// Smallest height.
        min_height: u32,
        /// Largest height.
        max_height: u32,
        /// Height step (0 is read as 1).
        step_height: u32,
    },
}

impl Sizes {
    /// The size of this offer the rule prefers for a `width x height` request: the exact or the
    /// smallest covering grid point when the request fits under the maxima, else the largest size.
    pub fn fit(&self, width: u32, height: u32) -> (u32, u32) {
        match *self {
            Sizes::Discrete { width, height } => (width, height),
            Sizes::Stepwise {
                min_width,
                max_width,
                step_width,
                min_height,
                max_height,
                step_height,
            } => {
                let max_w = max_width.max(min_width);
                let max_h = max_height.max(min_height);
                if width > max_w || height > max_h {
                    // Nothing covers the request: the largest grid point.
                    return (
                        grid_floor(min_width, step_width, max_w),
                        grid_floor(min_height, step_height, max_h),
                    );
                }
                (
                    grid_ceil(min_width, step_width, max_w, width),
                    grid_ceil(min_height, step_height, max_h, height),
                )
            }
        }
    }

    /// The largest size of this offer.
    pub fn largest(&self) -> (u32, u32) {
        self.fit(u32::MAX, u32::MAX)
    }
}

/// The largest `min + k * step` not above `max`.
fn grid_floor(min: u32, step: u32, max: u32) -> u32 {
    let step = step.max(1) as u64;
    let k = (max as u64 - min as u64) / step;
    (min as u64 + k * step) as u32
}

/// The smallest `min + k * step` at or above `want`, at most the largest grid point.
fn grid_ceil(min: u32, step: u32, max: u32, want: u32) -> u32 {
    if want <= min {
        return min;
    }
    let s = step.max(1) as u64;
    let k = (want as u64 - min as u64).div_ceil(s);
    let v = min as u64 + k * s;
    (v.min(grid_floor(min, step, max) as u64)) as u32
}

impl fmt::Display for Sizes {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Sizes::Discrete { width, height } => write!(f, "{width}x{height}"),
            Sizes::Stepwise {
                min_width,
                max_width,
                step_width,
                min_height,
                max_height,
                step_height,
            } => write!(
                f,
                "{min_width}x{min_height} to {max_width}x{max_height} in steps of \
                 {step_width}x{step_height}"
            ),
        }
    }
}

/// The frame rates of one offer, as frame intervals.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Rates {
    /// A list of intervals; empty when the driver did not enumerate any (rate unknown).
    Discrete(Vec<Interval>),
    /// Every interval `min + k * step` up to `max`.
    Stepwise {
        /// Shortest interval (highest rate).
        min: Interval,
        /// Longest interval (lowest rate).
        max: Interval,
        /// Interval step.
        step: Interval,
    },
    /// Any interval from `min` to `max`.
    Continuous {
        /// Shortest interval (highest rate).
        min: Interval,
        /// Longest interval (lowest rate).
        max: Interval,
    },
}

impl Rates {
    /// The intervals of this offer worth considering for a request of `fps`: every discrete
    /// one, or the grid point of a range the rule prefers (the longest interval not above the
    /// requested one, else the shortest).
    pub fn candidates(&self, fps: f64) -> Vec<Interval> {
        let want = 1.0 / fps;
        match self {
            Rates::Discrete(list) => list.iter().copied().filter(|i| i.fps().is_some()).collect(),
            Rates::Continuous { min, max } => {
                let (Some(lo), Some(hi)) = (min.seconds(), max.seconds()) else {
                    return Vec::new();
                };
                if want <= lo {
                    vec![*min]
                } else if want >= hi {
                    vec![*max]
                } else {
                    Interval::from_fps(fps).into_iter().collect()
                }
            }
            Rates::Stepwise { min, max, step } => {
                let (Some(lo), Some(hi)) = (min.seconds(), max.seconds()) else {
                    return Vec::new();
                };
                let Some(st) = step.seconds() else {
                    return vec![*min];
                };
                // Number of steps, capped at the last grid point not above max.
                let last = ((hi - lo) / st + 1e-9).floor().max(0.0);
                let k = ((want - lo) / st + 1e-9).floor().clamp(0.0, last) as u64;
                // min + k * step as an exact fraction.
                let num = min.num as u64 * step.den as u64 + k * step.num as u64 * min.den as u64;
                let den = min.den as u64 * step.den as u64;
                vec![reduced(num, den)]
            }
        }
    }
}

impl fmt::Display for Rates {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Rates::Discrete(list) if list.is_empty() => write!(f, "rate unknown"),
            Rates::Discrete(list) => {
                let rates: Vec<String> = list.iter().map(|i| i.to_string()).collect();
                write!(f, "{} fps", rates.join(", "))
            }
            Rates::Stepwise { min, max, step } => write!(
                f,
                "{max} to {min} fps (interval step {}/{} s)",
                step.num, step.den
            ),
            Rates::Continuous { min, max } => write!(f, "{max} to {min} fps"),
        }
    }
}

/// One pixel format at one size (or size range) with its frame rates, as a driver reports it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Offer {
    /// The driver's four-character code; kept even when we cannot decode it, for listings.
    pub fourcc: [u8; 4],
    /// The frame sizes.
    pub sizes: Sizes,
    /// The frame rates (for a [`Sizes::Stepwise`] offer, as enumerated at one size of the range).
    pub rates: Rates,
}

impl Offer {
    /// A discrete size with discrete frame rates (in fps), mostly for tests and simple drivers.
    pub fn discrete(fourcc: [u8; 4], width: u32, height: u32, fps: &[f64]) -> Self {
        Offer {
            fourcc,
            sizes: Sizes::Discrete { width, height },
            rates: Rates::Discrete(fps.iter().filter_map(|&r| Interval::from_fps(r)).collect()),
        }
    }

    /// The format, when it is one we decode.
    pub fn format(&self) -> Option<PixelFormat> {
        PixelFormat::from_fourcc(self.fourcc)
    }
}

impl fmt::Display for Offer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} {} {}",
            fourcc_str(self.fourcc),
            self.sizes,
            self.rates
        )?;
        if self.format().is_none() {
            write!(f, " (not decoded by v2ce)")?;
        }
        Ok(())
    }
}

/// The format, size and rate to ask the driver for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Choice {
    /// Pixel format.
    pub format: PixelFormat,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Frame interval; `None` when the offer did not say (then the requested rate is asked for).
    pub interval: Option<Interval>,
}

impl Choice {
    /// The chosen frame rate, when known.
    pub fn fps(&self) -> Option<f64> {
        self.interval.and_then(Interval::fps)
    }
}

/// Checks the parts of `config` that negotiation depends on.
fn check_config(config: &CameraConfig) -> Result<()> {
    if config.width == 0 || config.height == 0 {
        return Err(Error::invalid(
            "camera",
            format!("size {}x{} must be positive", config.width, config.height),
        ));
    }
    if !config.fps.is_finite() || config.fps <= 0.0 {
        return Err(Error::invalid(
            "camera",
            format!("fps {} must be a positive number", config.fps),
        ));
    }
    if config.formats.is_empty() {
        return Err(Error::invalid(
            "camera",
            "formats is empty: name at least one of GREY, YUYV, MJPG",
        ));
    }
    Ok(())
}

/// One line per fourcc: "YUYV (640x480, 1280x720)".
fn summarize(offers: &[Offer]) -> String {
    let mut groups: Vec<([u8; 4], Vec<String>)> = Vec::new();
    for o in offers {
        let size = o.sizes.to_string();
        match groups.iter_mut().find(|(f, _)| *f == o.fourcc) {
            Some((_, sizes)) => {
                if !sizes.contains(&size) {
                    sizes.push(size)
                }
            }
            None => groups.push((o.fourcc, vec![size])),
        }
    }
    groups
        .iter()
        .map(|(f, sizes)| format!("{} ({})", fourcc_str(*f), sizes.join(", ")))
        .collect::<Vec<_>>()
        .join("; ")
}

/// Size class, rate class, size closeness, rate closeness, format rank, width, height: smaller
/// is better, compared in this order (see the [module documentation](self)).
type RankKey = (u8, u8, i64, i64, usize, u32, u32);

/// Chooses what to stream from `offers` for `config`, by the rule in the [module
/// documentation](self). Errors when the configuration is unusable, the camera offers nothing,
/// or none of its formats is in `config.formats` (naming what it does offer).
pub fn choose(offers: &[Offer], config: &CameraConfig) -> Result<Choice> {
    check_config(config)?;
    if offers.is_empty() {
        return Err(Error::invalid(
            "camera",
            "the camera reported no capture formats",
        ));
    }
    let (rw, rh, fps) = (config.width, config.height, config.fps);
    let area = |w: u32, h: u32| w as i64 * h as i64;
    let mut best: Option<(RankKey, Choice)> = None;
    for offer in offers {
        let Some(format) = offer.format() else {
            continue;
        };
        let Some(rank) = config.formats.iter().position(|&f| f == format) else {
            continue;
        };
        let (w, h) = offer.sizes.fit(rw, rh);
        if w == 0 || h == 0 || w > u16::MAX as u32 || h > u16::MAX as u32 {
            continue;
        }
        let (size_class, size_metric) = if (w, h) == (rw, rh) {
            (0, 0)
        } else if w >= rw && h >= rh {
            (1, area(w, h))
        } else {
            (2, -area(w, h))
        };
        let mut rates: Vec<Option<Interval>> =
            offer.rates.candidates(fps).into_iter().map(Some).collect();
        if rates.is_empty() {
            rates.push(None);
        }
        for interval in rates {
            let (rate_class, rate_metric) = match interval.and_then(Interval::fps) {
                None => (2, 0),
                Some(r) => {
                    let mhz = (r * 1000.0).round() as i64;
                    if r >= fps * (1.0 - RATE_TOLERANCE) {
                        (0, mhz)
                    } else {
                        (1, -mhz)
                    }
                }
            };
            let key = (size_class, rate_class, size_metric, rate_metric, rank, w, h);
            if best.as_ref().is_none_or(|(k, _)| key < *k) {
                let choice = Choice {
                    format,
                    width: w,
                    height: h,
                    interval,
                };
                best = Some((key, choice));
            }
        }
    }
    match best {
        Some((_, choice)) => Ok(choice),
        None => {
            let wanted: Vec<&str> = config
                .formats
                .iter()
                .map(|f| fourcc_str_static(*f))
                .collect();
            Err(Error::invalid(
                "camera",
                format!(
                    "the camera offers none of the formats asked for ({}); it offers: {}",
                    wanted.join(", "),
                    summarize(offers)
                ),
            ))
        }
    }
}

fn fourcc_str_static(f: PixelFormat) -> &'static str {
    match f {
        PixelFormat::Grey => "GREY",
        PixelFormat::Yuyv => "YUYV",
        PixelFormat::Mjpeg => "MJPG",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(width: u32, height: u32, fps: f64) -> CameraConfig {
        CameraConfig {
            width,
            height,
            fps,
            ..CameraConfig::default()
        }
    }

    fn pick(offers: &[Offer], cfg: &CameraConfig) -> (PixelFormat, u32, u32, Option<f64>) {
        let c = choose(offers, cfg).expect("a choice");
        (c.format, c.width, c.height, c.fps())
    }

    #[test]
    fn intervals_from_rates() {
        assert_eq!(Interval::from_fps(30.0), Some(Interval::new(1, 30)));
        assert_eq!(Interval::from_fps(29.97), Some(Interval::new(100, 2997)));
        assert_eq!(Interval::from_fps(7.5), Some(Interval::new(2, 15)));
        assert_eq!(Interval::from_fps(0.0), None);
        assert_eq!(Interval::from_fps(f64::NAN), None);
        assert_eq!(Interval::new(0, 30).fps(), None);
        assert_eq!(Interval::new(1, 0).fps(), None);
        assert_eq!(Interval::new(1, 30).to_string(), "30");
        assert_eq!(Interval::new(100, 2997).to_string(), "29.97");
    }

    #[test]
    fn exact_match() {
        let offers = [
            Offer::discrete(*b"YUYV", 320, 240, &[30.0]),
            Offer::discrete(*b"YUYV", 640, 480, &[30.0, 15.0]),
            Offer::discrete(*b"YUYV", 1280, 720, &[10.0]),
        ];
        assert_eq!(
            pick(&offers, &config(640, 480, 30.0)),
            (PixelFormat::Yuyv, 640, 480, Some(30.0))
        );
        assert_eq!(
            pick(&offers, &config(640, 480, 15.0)),
            (PixelFormat::Yuyv, 640, 480, Some(15.0))
        );
    }

    #[test]
    fn smallest_covering_size_else_largest() {
        let offers = [
            Offer::discrete(*b"YUYV", 320, 240, &[30.0]),
            Offer::discrete(*b"YUYV", 1920, 1080, &[30.0]),
            Offer::discrete(*b"YUYV", 800, 600, &[30.0]),
            Offer::discrete(*b"YUYV", 1280, 720, &[30.0]),
        ];
        assert_eq!(pick(&offers, &config(640, 480, 30.0)).1, 800);
        // 1000x500: 800x600 is too narrow, 1280x720 is the smallest covering.
        assert_eq!(pick(&offers, &config(1000, 500, 30.0)).1, 1280);
        // Nothing covers 4000x3000: the largest.
        assert_eq!(pick(&offers, &config(4000, 3000, 30.0)).1, 1920);
        // Wide but short: covering needs both dimensions.
        assert_eq!(pick(&offers, &config(1900, 100, 30.0)).1, 1920);
    }

    #[test]
    fn no_format_in_preference_list_names_what_is_offered() {
        let offers = [
            Offer::discrete(*b"H264", 1920, 1080, &[30.0]),
            Offer::discrete(*b"RGB3", 640, 480, &[30.0]),
            Offer::discrete(*b"RGB3", 320, 240, &[30.0]),
            Offer::discrete(*b"YUYV", 640, 480, &[30.0]),
        ];
        let cfg = CameraConfig {
            formats: vec![PixelFormat::Grey, PixelFormat::Mjpeg],
            ..CameraConfig::default()
        };
        let err = choose(&offers, &cfg).unwrap_err().to_string();
        assert!(err.contains("GREY, MJPG"), "{err}");
        assert!(err.contains("H264 (1920x1080)"), "{err}");
        assert!(err.contains("RGB3 (640x480, 320x240)"), "{err}");
        assert!(err.contains("YUYV (640x480)"), "{err}");
        // With YUYV allowed it works.
        assert_eq!(pick(&offers, &CameraConfig::default()).0, PixelFormat::Yuyv);
        assert!(choose(&[], &CameraConfig::default()).is_err());
    }

    #[test]
    fn bad_config_is_rejected() {
        let offers = [Offer::discrete(*b"YUYV", 640, 480, &[30.0])];
        for cfg in [
            config(0, 480, 30.0),
            config(640, 480, 0.0),
            config(640, 480, f64::INFINITY),
            CameraConfig {
                formats: vec![],
                ..CameraConfig::default()
            },
        ] {
            assert!(choose(&offers, &cfg).is_err(), "{cfg:?}");
        }
    }

    #[test]
    fn rate_fallbacks() {
        let offers = [Offer::discrete(
            *b"YUYV",
            640,
            480,
            &[5.0, 15.0, 60.0, 25.0],
        )];
        // Closest at or above the request.
        assert_eq!(pick(&offers, &config(640, 480, 20.0)).3, Some(25.0));
        assert_eq!(pick(&offers, &config(640, 480, 30.0)).3, Some(60.0));
        // Nothing at or above: the highest.
        assert_eq!(pick(&offers, &config(640, 480, 120.0)).3, Some(60.0));
        // 29.97 meets a request of 30.
        let ntsc = [Offer::discrete(*b"YUYV", 640, 480, &[29.97, 60.0])];
        let c = choose(&ntsc, &config(640, 480, 30.0)).unwrap();
        assert_eq!(c.interval, Some(Interval::new(100, 2997)));
        // Unknown rates still give a choice, without an interval.
        let unknown = [Offer::discrete(*b"GREY", 640, 480, &[])];
        assert_eq!(
            pick(&unknown, &config(640, 480, 30.0)),
            (PixelFormat::Grey, 640, 480, None)
        );
    }

    #[test]
    fn size_and_rate_outweigh_format_preference() {
        // Typical USB 2 webcam: YUYV at full size only slowly, MJPEG fast.
        let offers = [
            Offer::discrete(*b"YUYV", 640, 480, &[10.0]),
            Offer::discrete(*b"MJPG", 640, 480, &[30.0]),
            Offer::discrete(*b"GREY", 320, 240, &[30.0]),
        ];
        assert_eq!(
            pick(&offers, &config(640, 480, 30.0)),
            (PixelFormat::Mjpeg, 640, 480, Some(30.0))
        );
        // Asking for 10 fps, both meet it; YUYV's 10 is the closer rate.
        assert_eq!(pick(&offers, &config(640, 480, 10.0)).0, PixelFormat::Yuyv);
        // Exact size beats a better rate at the wrong size.
        assert_eq!(pick(&offers, &config(320, 240, 30.0)).0, PixelFormat::Grey);
    }

    #[test]
    fn ties_go_to_format_preference_then_order() {
        let offers = [
            Offer::discrete(*b"MJPG", 640, 480, &[30.0]),
            Offer::discrete(*b"YUYV", 640, 480, &[30.0]),
            Offer::discrete(*b"GREY", 640, 480, &[30.0]),
        ];
        assert_eq!(pick(&offers, &config(640, 480, 30.0)).0, PixelFormat::Grey);
        let cfg = CameraConfig {
            formats: vec![PixelFormat::Mjpeg, PixelFormat::Yuyv],
            ..CameraConfig::default()
        };
        assert_eq!(pick(&offers, &cfg).0, PixelFormat::Mjpeg);
        // Two covering sizes of equal area: the narrower first.
        let same_area = [
            Offer::discrete(*b"YUYV", 800, 600, &[30.0]),
            Offer::discrete(*b"YUYV", 600, 800, &[30.0]),
        ];
        assert_eq!(pick(&same_area, &config(500, 500, 30.0)).1, 600);
        // Duplicate offers: deterministic.
        let dup = [offers[1].clone(), offers[1].clone()];
        assert_eq!(pick(&dup, &config(640, 480, 30.0)).1, 640);
    }

    #[test]
    fn stepwise_sizes() {
        let sizes = Sizes::Stepwise {
            min_width: 160,
            max_width: 1920,
            step_width: 16,
            min_height: 120,
            max_height: 1080,
            step_height: 8,
        };
        assert_eq!(sizes.fit(640, 480), (640, 480));
        assert_eq!(sizes.fit(650, 481), (656, 488));
        assert_eq!(sizes.fit(100, 100), (160, 120));
        assert_eq!(sizes.fit(4000, 100), (1920, 1080));
        assert_eq!(sizes.largest(), (1920, 1080));
        // Maximum off the grid: the last grid point.
        let odd = Sizes::Stepwise {
            min_width: 10,
            max_width: 105,
            step_width: 10,
            min_height: 10,
            max_height: 100,
            step_height: 0,
        };
        assert_eq!(odd.fit(101, 50), (100, 50));
        assert_eq!(odd.largest(), (100, 100));
        let offers = [Offer {
            fourcc: *b"GREY",
            sizes,
            rates: Rates::Continuous {
                min: Interval::new(1, 60),
                max: Interval::new(1, 1),
            },
        }];
        assert_eq!(
            pick(&offers, &config(650, 481, 24.0)),
            (PixelFormat::Grey, 656, 488, Some(24.0))
        );
        assert_eq!(pick(&offers, &config(640, 480, 100.0)).3, Some(60.0));
        assert_eq!(pick(&offers, &config(640, 480, 0.5)).3, Some(1.0));
    }

    #[test]
    fn stepwise_rates() {
        // Intervals 1/60 + k/60: 60, 30, 20, 15, 12, 10 fps.
        let rates = Rates::Stepwise {
            min: Interval::new(1, 60),
            max: Interval::new(1, 10),
            step: Interval::new(1, 60),
        };
        let one = |fps: f64| rates.candidates(fps)[0];
        assert_eq!(one(30.0), Interval::new(1, 30));
        assert_eq!(one(25.0), Interval::new(1, 30));
        assert_eq!(one(16.0), Interval::new(1, 20));
        assert_eq!(one(100.0), Interval::new(1, 60));
        assert_eq!(one(1.0), Interval::new(1, 10));
        assert!(rates.to_string().contains("10 to 60 fps"));
    }

    #[test]
    fn offers_display() {
        let o = Offer::discrete(*b"YUYV", 640, 480, &[30.0, 15.0]);
        assert_eq!(o.to_string(), "YUYV 640x480 30, 15 fps");
        let h = Offer::discrete(*b"H264", 1920, 1080, &[30.0]);
        assert!(h.to_string().ends_with("(not decoded by v2ce)"));
    }
}
