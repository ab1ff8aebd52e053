//! Training data for the learned tier (`v2ce dataset`), reproducible from a seed.
//!
//! A dataset is a folder of sequences, one `.npz` each (NumPy reads them with `np.load`), and a
//! `dataset.json` manifest. A sequence holds what one training sample of the V2CE network needs
//! (V2CE_SPEC.md sections 1.1 and 2):
//! - `frames`: `uint8 (P+1, H, W)`, the input frames as 8-bit linear values, as a DAVIS APS
//!   gives them (the trainer divides by 255 and normalises, as the toolbox does);
//! - `voxels`: `float32 (P, 20, H, W)`, the ground-truth event voxels of each frame interval
//!   (ON nodes 0-9, then OFF), built by [`crate::voxel::Voxelizer`] on the interval's own
//!   times, as `v2ce eval` builds them;
//! - `times_us`: `int64 (P+1,)`, the frame times.
//!
//! Two kinds of source:
//! - **synthetic** ([`write_synthetic`]): random scenes ([`scene::Scene`]: procedural or
//!   natural-image textures under a moving homography, occluding objects, changing light)
//!   rendered at a high rate (at least `rate_hz`, an integer multiple of the sequence's frame
//!   rate); the ground-truth events are the physics tier run on the high-rate frames (sensor
//!   noise on, off, or on in half of the sequences), the inputs the same scene sampled at the
//!   sequence's frame rate (25-60 fps), with APS-like read noise;
//! - **a recording with frames and events** ([`write_recording`]): windows of `P + 1` of its
//!   frames and its real events, from one half of its frame intervals (split by time, so a
//!   model is never scored on what trained it).

pub mod scene;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;
use serde::Serialize;

use crate::error::{Error, Result};
use crate::event::{sort_events, time_slice, Event};
use crate::format::npz::{write_arrays, Array};
use crate::frame::{Frame, FULL_SCALE};
use crate::interval::Interval;
use crate::stage1::{PhysicsConfig, PhysicsSim};
use crate::voxel::{VoxelGrid, Voxelizer, DEFAULT_BINS};

pub use scene::{Image, Pace, Scene};

/// Sensor noise in the ground truth of synthetic sequences.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Default, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum NoiseMode {
    /// The sensor preset's leak, shot noise and hot pixels in every sequence.
    On,
    /// None: only the scene's own events.
    Off,
    /// On in half of the sequences (drawn from the seed).
    #[default]
    Mixed,
}

/// Settings of a synthetic dataset.
#[derive(Debug, Clone, Serialize)]
pub struct SyntheticConfig {
    /// Frame width and height.
    pub size: (u16, u16),
    /// Frame intervals per sequence (the network's window, 16).
    pub pairs: usize,
    /// Each sequence's frame rate is drawn from this range, fps.
    pub fps: (f64, f64),
    /// The scene is rendered for the ground truth at least this often, Hz.
    pub rate_hz: f64,
    /// The ground-truth sensor.
    pub sensor: PhysicsConfig,
    /// Sensor noise in the ground truth.
    pub noise: NoiseMode,
    /// Largest read noise of the input frames, in 8-bit steps (each sequence draws its own
    /// from 0 to this).
    pub input_noise: f64,
    /// How fast scenes move.
    #[serde(skip)]
    pub pace: Pace,
}

impl Default for SyntheticConfig {
    fn default() -> Self {
        SyntheticConfig {
            size: (160, 120),
            pairs: 16,
            fps: (25.0, 60.0),
            rate_hz: 1000.0,
            sensor: PhysicsConfig::default(),
            noise: NoiseMode::Mixed,
            input_noise: 1.5,
            pace: Pace::default(),
        }
    }
}

impl SyntheticConfig {
    /// Checks the settings.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::invalid("dataset", m));
        if self.size.0 < 8 || self.size.1 < 8 {
            return bad(format!("{} x {}: at least 8 x 8", self.size.0, self.size.1));
        }
        if !(1..=256).contains(&self.pairs) {
            return bad(format!("{} pairs: 1 to 256", self.pairs));
        }
        let (lo, hi) = self.fps;
        if !(lo.is_finite() && hi.is_finite() && lo >= 1.0 && hi >= lo && hi <= 1000.0) {
            return bad(format!("fps {lo}..{hi}: 1 to 1000, low to high"));
        }
        if !(self.rate_hz.is_finite() && self.rate_hz >= hi && self.rate_hz <= 100_000.0) {
            return bad(format!(
                "rate {} Hz: at least the highest frame rate, at most 100 kHz",
                self.rate_hz
            ));
        }
        if !(self.input_noise.is_finite() && (0.0..=64.0).contains(&self.input_noise)) {
            return bad(format!("input noise {}: 0 to 64 steps", self.input_noise));
        }
        self.sensor.validate()
    }
}

/// One sequence of a dataset, as the manifest lists it.
#[derive(Debug, Clone, Serialize)]
pub struct SequenceInfo {
    /// Its file, relative to the dataset folder.
    pub file: String,
    /// The seed it was drawn from (synthetic) or its first frame's index (recording).
    pub seed: u64,
    /// Its frame rate, fps (the mean one for a recording).
    pub fps: f64,
    /// The rate its ground truth was simulated at, Hz (0 for real events).
    pub rate_hz: f64,
    /// Whether its ground truth has sensor noise.
    pub noise: bool,
    /// Read noise of its input frames, 8-bit steps.
    pub input_noise: f64,
    /// Events in its voxels.
    pub events: u64,
}

/// The `dataset.json` manifest.
#[derive(Debug, Clone, Serialize)]
pub struct Manifest {
    /// The v2ce version that wrote it.
    pub version: &'static str,
    /// "synthetic" or "recording".
    pub kind: &'static str,
    /// Where the data came from: the settings and seed, or the recording and split.
    pub source: serde_json::Value,
    /// Frame width and height.
    pub size: (u16, u16),
    /// Frame intervals per sequence.
    pub pairs: usize,
    /// Voxel nodes per polarity.
    pub bins: usize,
    /// The sequences.
    pub sequences: Vec<SequenceInfo>,
}

impl Manifest {
    fn write(&self, dir: &Path) -> Result<()> {
        let path = dir.join("dataset.json");
        let text = serde_json::to_string_pretty(self)
            .map_err(|e| Error::invalid("manifest", e.to_string()))?;
        std::fs::write(&path, text).map_err(|e| Error::io(&path, e))
    }
}

/// A sequence's seed: `seed` and its index mixed (SplitMix64), so neighbours are unrelated.
fn sequence_seed(seed: u64, index: usize) -> u64 {
    let mut z = seed
        .wrapping_add(0x9E37_79B9_7F4A_7C15)
        .wrapping_add((index as u64).wrapping_mul(0xBF58_476D_1CE4_E5B9));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The voxels (`P x 20 x H x W`, V2CE layout) of `events` (sorted by time) on the intervals
/// between consecutive `times`; returns them and the events they hold.
fn voxels_of(events: &[Event], times: &[i64], size: (u16, u16)) -> Result<(Vec<f32>, u64)> {
    let mut voxelizer = Voxelizer::new(size.0, size.1, DEFAULT_BINS)?;
    let mut out = Vec::new();
    let mut held = 0u64;
    for w in times.windows(2) {
        let interval = Interval::new(w[0], w[1])?;
        let inside = time_slice(events, w[0], w[1]);
        held += inside.len() as u64;
        let mut grid = VoxelGrid::new(size.0, size.1, DEFAULT_BINS)?;
        voxelizer.voxelize_into(inside, interval, &mut grid)?;
        out.extend(grid.to_dense());
    }
    Ok((out, held))
}

/// Writes one sequence's arrays to `path`.
fn write_sequence(
    path: &Path,
    frames: &[u8],
    voxels: &[f32],
    times: &[i64],
    size: (u16, u16),
) -> Result<()> {
    let (w, h) = (size.0 as usize, size.1 as usize);
    let p = times.len() - 1;
    let voxel_bytes: Vec<u8> = voxels.iter().flat_map(|v| v.to_le_bytes()).collect();
    let time_bytes: Vec<u8> = times.iter().flat_map(|t| t.to_le_bytes()).collect();
    write_arrays(
        path,
        &[
            Array {
                name: "frames",
                descr: "'|u1'",
                shape: &[p + 1, h, w],
                data: frames,
            },
            Array {
                name: "voxels",
                descr: "'<f4'",
                shape: &[p, 2 * DEFAULT_BINS, h, w],
                data: &voxel_bytes,
            },
            Array {
                name: "times_us",
                descr: "'<i8'",
                shape: &[p + 1],
                data: &time_bytes,
            },
        ],
        true,
    )
}

/// A synthetic sequence in memory: what [`synthetic_sequence`] writes, made again from the
/// same settings, seed and index (`v2ce bench tradeoff` scores tiers on it without files).
pub struct SyntheticSequence {
    /// The input frames (8-bit linear values, as an APS gives them), in time order.
    pub frames: Vec<Frame>,
    /// The ground-truth events, sorted.
    pub events: Vec<Event>,
    /// How it was made (`file` names where it would be written).
    pub info: SequenceInfo,
}

/// Renders sequence `index` of the synthetic dataset of `cfg` and `seed` (see the module docs).
pub fn render_synthetic(
    cfg: &SyntheticConfig,
    seed: u64,
    index: usize,
    images: &[Arc<Image>],
) -> Result<SyntheticSequence> {
    let s = sequence_seed(seed, index);
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(s);
    let fps = if cfg.fps.1 > cfg.fps.0 {
        rng.gen_range(cfg.fps.0..=cfg.fps.1)
    } else {
        cfg.fps.0
    };
    let noise = match cfg.noise {
        NoiseMode::On => true,
        NoiseMode::Off => false,
        NoiseMode::Mixed => rng.gen_bool(0.5),
    };
    let input_noise = if cfg.input_noise > 0.0 {
        rng.gen_range(0.0..=cfg.input_noise)
    } else {
        0.0
    };
    let scene = Scene::random(s, cfg.size, images, cfg.pace);
    // `m` high-rate steps per frame interval, at least `rate_hz`.
    let m = (cfg.rate_hz / fps).ceil().max(1.0) as usize;
    let step = 1e6 / (fps * m as f64);
    let mut sensor = if noise {
        cfg.sensor.clone()
    } else {
        cfg.sensor.noiseless()
    };
    // The ground truth's frames come at `rate_hz` or faster, where nothing moves a pixel
    // between two: linear interpolation is exact there, and the flow would cost for nothing.
    sensor.motion = crate::stage1::Motion::Linear;
    let (w, h) = cfg.size;
    let mut sim = PhysicsSim::new(sensor, w, h, s)?;
    let mut events = Vec::new();
    let mut frames = Vec::with_capacity(cfg.pairs + 1);
    let read_noise = Normal::new(0.0, input_noise.max(1e-12))
        .map_err(|e| Error::invalid("dataset", e.to_string()))?;
    for j in 0..=cfg.pairs * m {
        let t = (j as f64 * step).round() as i64;
        let luma = scene.render(t);
        if j % m == 0 {
            let bytes = luma.iter().map(|&v| {
                let dn = v as f64 / 257.0 + read_noise.sample(&mut rng);
                dn.round().clamp(0.0, 255.0) as u16 * 257
            });
            frames.push(Frame {
                t,
                width: w,
                height: h,
                luma: bytes.collect(),
                exposure_us: None,
            });
        }
        let frame = Frame {
            t,
            width: w,
            height: h,
            luma,
            exposure_us: None,
        };
        sim.step(&frame, &mut events)?;
    }
    sort_events(&mut events);
    let times: Vec<i64> = frames.iter().map(|f| f.t).collect();
    let held = {
        let (lo, hi) = (times[0], times[times.len() - 1]);
        events.iter().filter(|e| e.t >= lo && e.t < hi).count() as u64
    };
    Ok(SyntheticSequence {
        frames,
        events,
        info: SequenceInfo {
            file: format!("seq_{index:05}.npz"),
            seed: s,
            fps,
            rate_hz: fps * m as f64,
            noise,
            input_noise,
            events: held,
        },
    })
}

/// One synthetic sequence (see the module docs): its file is written to `dir`.
pub fn synthetic_sequence(
    dir: &Path,
    cfg: &SyntheticConfig,
    seed: u64,
    index: usize,
    images: &[Arc<Image>],
) -> Result<SequenceInfo> {
    let seq = render_synthetic(cfg, seed, index, images)?;
    let times: Vec<i64> = seq.frames.iter().map(|f| f.t).collect();
    let bytes: Vec<u8> = seq
        .frames
        .iter()
        .flat_map(|f| f.luma.iter().map(|&v| (v / 257) as u8))
        .collect();
    let (voxels, held) = voxels_of(&seq.events, &times, cfg.size)?;
    debug_assert_eq!(held, seq.info.events);
    write_sequence(&dir.join(&seq.info.file), &bytes, &voxels, &times, cfg.size)?;
    Ok(seq.info)
}

/// Writes `count` synthetic sequences drawn from `seed` to `dir` (created), on `threads`
/// threads, and the manifest; `images` are natural-image textures (may be empty).
pub fn write_synthetic(
    dir: &Path,
    cfg: &SyntheticConfig,
    seed: u64,
    count: usize,
    images: &[Arc<Image>],
    threads: usize,
) -> Result<Manifest> {
    cfg.validate()?;
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let next = std::sync::atomic::AtomicUsize::new(0);
    let results: Vec<Result<Vec<(usize, SequenceInfo)>>> = std::thread::scope(|scope| {
        let workers: Vec<_> = (0..threads.clamp(1, 64))
            .map(|_| {
                scope.spawn(|| {
                    let mut done = Vec::new();
                    loop {
                        let k = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        if k >= count {
                            return Ok(done);
                        }
                        done.push((k, synthetic_sequence(dir, cfg, seed, k, images)?));
                    }
                })
            })
            .collect();
        workers
            .into_iter()
            .map(|w| {
                w.join()
                    .unwrap_or_else(|_| Err(Error::invalid("dataset", "a worker panicked")))
            })
            .collect()
    });
    let mut sequences = Vec::with_capacity(count);
    for r in results {
        sequences.extend(r?);
    }
    sequences.sort_by_key(|(k, _)| *k);
    let manifest = Manifest {
        version: env!("CARGO_PKG_VERSION"),
        kind: "synthetic",
        source: serde_json::json!({ "seed": seed, "count": count, "config": cfg }),
        size: cfg.size,
        pairs: cfg.pairs,
        bins: DEFAULT_BINS,
        sequences: sequences.into_iter().map(|(_, s)| s).collect(),
    };
    manifest.write(dir)?;
    Ok(manifest)
}

/// Which frame intervals of a recording a dataset takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Split {
    /// The first half of the frame intervals (by time).
    First,
    /// The second half.
    Second,
    /// All of them.
    All,
}

impl Split {
    /// The indices of `intervals` frame intervals this part covers: the first half (rounded
    /// down), the rest, or all.
    pub fn range(self, intervals: usize) -> std::ops::Range<usize> {
        let half = intervals / 2;
        match self {
            Split::First => 0..half,
            Split::Second => half..intervals,
            Split::All => 0..intervals,
        }
    }
}

/// Writes windows of `pairs` intervals of a recording's `frames` (in time order) with its real
/// `events` (sorted) to `dir`, from the intervals of `split`; `source` names the recording in
/// the manifest.
pub fn write_recording(
    dir: &Path,
    frames: &[Frame],
    events: &[Event],
    pairs: usize,
    split: Split,
    source: &str,
) -> Result<Manifest> {
    let Some(first) = frames.first() else {
        return Err(Error::invalid("dataset", "the recording has no frames"));
    };
    let size = (first.width, first.height);
    let range = split.range(frames.len().saturating_sub(1));
    let (lo, hi) = (range.start, range.end);
    if pairs == 0 || hi - lo < pairs {
        return Err(Error::invalid(
            "dataset",
            format!(
                "{} frame intervals in the {split:?} part, fewer than a window of {pairs}",
                hi - lo
            ),
        ));
    }
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let mut sequences = Vec::new();
    // Windows share their boundary frame, as the toolbox chains them.
    let mut start = lo;
    while start + pairs <= hi {
        let window = &frames[start..=start + pairs];
        let times: Vec<i64> = window.iter().map(|f| f.t).collect();
        let mut bytes = Vec::with_capacity(window.len() * size.0 as usize * size.1 as usize);
        for f in window {
            if (f.width, f.height) != size {
                return Err(Error::invalid("dataset", "frames of different sizes"));
            }
            bytes.extend(f.luma.iter().map(|&v| {
                (v as f64 * 255.0 / FULL_SCALE as f64)
                    .round()
                    .clamp(0.0, 255.0) as u8
            }));
        }
        let (voxels, held) = voxels_of(events, &times, size)?;
        let file = format!("seq_{start:05}.npz");
        write_sequence(&dir.join(&file), &bytes, &voxels, &times, size)?;
        let span = (times[pairs] - times[0]) as f64 * 1e-6;
        sequences.push(SequenceInfo {
            file,
            seed: start as u64,
            fps: if span > 0.0 { pairs as f64 / span } else { 0.0 },
            rate_hz: 0.0,
            noise: true,
            input_noise: 0.0,
            events: held,
        });
        start += pairs;
    }
    let manifest = Manifest {
        version: env!("CARGO_PKG_VERSION"),
        kind: "recording",
        source: serde_json::json!({
            "recording": source,
            "split": split,
            "intervals": [lo, hi],
        }),
        size,
        pairs,
        bins: DEFAULT_BINS,
        sequences,
    };
    manifest.write(dir)?;
    Ok(manifest)
}

/// Natural-image textures: every PNG or JPEG in `dir` (sorted by name), as gray linear light
/// (sRGB decoded).
pub fn load_images(dir: &Path) -> Result<Vec<Arc<Image>>> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| Error::io(dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
        })
        .collect();
    paths.sort();
    let lut = crate::frame::color::srgb_to_linear_lut();
    paths
        .iter()
        .map(|p| {
            let img = image::open(p)
                .map_err(|e| Error::format(p, e.to_string()))?
                .to_luma8();
            if img.width() < 8 || img.height() < 8 {
                return Err(Error::format(p, "smaller than 8 x 8".to_string()));
            }
            Ok(Arc::new(Image {
                width: img.width() as usize,
                height: img.height() as usize,
                values: img.pixels().map(|px| lut[px.0[0] as usize]).collect(),
            }))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> SyntheticConfig {
        SyntheticConfig {
            size: (32, 24),
            pairs: 3,
            ..Default::default()
        }
    }

    #[test]
    fn sequence_seeds_differ_and_repeat() {
        assert_eq!(sequence_seed(1, 2), sequence_seed(1, 2));
        assert_ne!(sequence_seed(1, 2), sequence_seed(1, 3));
        assert_ne!(sequence_seed(1, 2), sequence_seed(2, 2));
    }

    #[test]
    fn bad_settings_are_errors() {
        let mut c = small();
        c.fps = (60.0, 25.0);
        assert!(c.validate().is_err());
        let mut c = small();
        c.rate_hz = 10.0;
        assert!(c.validate().is_err());
        let mut c = small();
        c.pairs = 0;
        assert!(c.validate().is_err());
    }
}
