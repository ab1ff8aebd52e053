//! Frames to events, offline: a frame source through the pipeline (`src/pipeline`) with
//! every queue blocking (nothing is ever dropped), as fast as the stages go.
//!
//! Memory stays at a few frames and their events, whatever the video's length.

use std::sync::atomic::AtomicBool;
use std::time::Duration;

use crate::config::Config;
use crate::error::{Error, Result};
use crate::frame::FrameSource;
use crate::pipeline::queue::QueuePolicy;
use crate::pipeline::{self, Options, Source, Stages};
use crate::sink::Sink;
use crate::stage1::{Stage1, Stage1Stats, Tap, Tapped};
use crate::stage2::SampleStats;

/// What a conversion did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ConvertReport {
    /// Frames read.
    pub frames: u64,
    /// Events handed to the sinks.
    pub events: u64,
    /// Time of the first frame, us.
    pub first_t: Option<i64>,
    /// Time of the last frame.
    pub last_t: Option<i64>,
    /// Wall time, seconds.
    pub seconds: f64,
    /// Stage 1's counters.
    pub stage1: Stage1Stats,
    /// Voxel values Stage 2 had to repair.
    pub repaired: SampleStats,
}

/// The configured Stage 1 tier for `source`'s frames.
pub fn build_stage1(config: &Config, source: &dyn FrameSource) -> Result<Box<dyn Stage1>> {
    crate::stage1::build(
        &config.stage1,
        config.stage2.bins,
        source.size(),
        source.encoding(),
    )
}

/// Runs `source` through `stage1` and the configured sampler into every sink (made for
/// `stage1.output_size()`), calling `progress` a few times a second with the report so far. The
/// sinks are finished at the end. `stop` (e.g. set on SIGINT) ends the conversion early, with
/// everything read so far written; `max_frames` limits the frames read.
pub fn convert(
    source: Box<dyn FrameSource>,
    stage1: Box<dyn Stage1>,
    config: &Config,
    sinks: Vec<Box<dyn Sink>>,
    max_frames: Option<u64>,
    stop: &AtomicBool,
    mut progress: impl FnMut(&ConvertReport),
) -> Result<ConvertReport> {
    let options = Options {
        policy: QueuePolicy::Block,
        capacity: 4,
        max_frames,
        duration: None,
        tick: Duration::from_millis(250),
        stop_flush_limit: None,
        counters: None,
        lag_budget: None,
    };
    let mut on_tick = |s: &pipeline::stats::Snapshot| {
        progress(&ConvertReport {
            frames: s.frames_in,
            events: s.events_out,
            seconds: s.uptime_s,
            ..ConvertReport::default()
        })
    };
    let stages = Stages {
        stage1,
        sampler: config.stage2.sampler.build(config.stage2.seed),
        sinks,
    };
    let report = pipeline::run(Source::file(source), stages, &options, stop, &mut on_tick)?;
    if !report.end.is_clean() {
        return Err(Error::Run(report.end.describe()));
    }
    if let Some(failed) = report.stats.sinks.iter().find_map(|s| s.failed.clone()) {
        return Err(Error::Run(failed));
    }
    Ok(ConvertReport {
        frames: report.stats.frames_in,
        events: report.stats.events_out,
        first_t: report.first_t,
        last_t: report.last_t,
        seconds: report.stats.uptime_s,
        stage1: report.stage1,
        repaired: report.repaired,
    })
}

/// One input converted to one event file: what `v2ce convert` and each item of `v2ce batch` do.
#[derive(Debug, Clone)]
pub struct FileJob {
    /// A video, image folder, frame list, `.y4m`, `.aedat4` with APS frames, or
    /// [`crate::frame::fixture::NAME`].
    pub input: std::path::PathBuf,
    /// The event file, written as its partial name until complete
    /// ([`crate::format::PartialOutput`]).
    pub output: std::path::PathBuf,
    /// The output's format.
    pub format: crate::format::Format,
    /// How to read the input (frame rate of an image folder, colour space).
    pub source: crate::frame::SourceOptions,
    /// Resample frames to this size.
    pub size: Option<(u16, u16)>,
    /// Read at most this many frames.
    pub max_frames: Option<u64>,
    /// Also write Stage 1's voxels to this `.npy`.
    pub write_voxels: Option<std::path::PathBuf>,
}

/// What [`convert_file`] tells its caller as it goes.
pub trait FileJobObserver {
    /// The input opened: a line saying what goes where, and the input's frame count when known.
    fn started(&mut self, _line: &str, _frames: Option<u64>) {}
    /// The report so far, a few times a second.
    fn progress(&mut self, _report: &ConvertReport) {}
}

impl FileJobObserver for () {}

/// Converts `job.input` to `job.output` with `config`: the input is opened, Stage 1 built for
/// its frames, and the events written under the output's partial name, which is renamed when
/// complete. On failure, or when `stop` ended it early ([`Error::Interrupted`]), the partial
/// file stays and the error says where.
pub fn convert_file(
    job: &FileJob,
    config: &Config,
    stop: &AtomicBool,
    observer: &mut dyn FileJobObserver,
) -> Result<ConvertReport> {
    let mut source = if job.input.as_os_str() == crate::frame::fixture::NAME {
        crate::frame::fixture::open()?
    } else {
        crate::frame::open(&job.input, &job.source)?
    };
    if let Some(size) = job.size {
        source = Box::new(crate::frame::resize::Resized::new(source, size)?);
    }
    let mut stage1 = build_stage1(config, source.as_ref())?;
    let (w, h) = stage1.output_size();
    let total = match (source.frames_hint(), job.max_frames) {
        (Some(n), Some(m)) => Some(n.min(m)),
        (n, m) => n.or(m),
    };
    observer.started(
        &format!(
            "{} -> {} (Stage 1 {}, {} x {})",
            source.describe(),
            job.output.display(),
            stage1.describe(),
            w,
            h
        ),
        total,
    );
    let output = crate::format::PartialOutput::new(&job.output);
    let sink = crate::sink::file::FileSink::create(output.writing(), job.format, w, h)?;
    if let Some(path) = &job.write_voxels {
        stage1 = Box::new(Tapped::new(stage1, VoxelTap::new(path)?));
    }
    let sinks: Vec<Box<dyn Sink>> = vec![Box::new(sink)];
    let report = convert(source, stage1, config, sinks, job.max_frames, stop, |r| {
        observer.progress(r)
    })
    .map_err(|e| output.explain(e))?;
    if stop.load(std::sync::atomic::Ordering::Relaxed) {
        return Err(output.explain(Error::Interrupted(format!(
            "stopped by a signal after {} frames, before the input ended",
            report.frames
        ))));
    }
    output.commit()?;
    Ok(report)
}

/// A [`Tap`] that writes every voxel its tier hands on to a `.npy` file: float32
/// `(intervals, 2*C, H, W)` in V2CE's channel layout (`polarity * C + node`, ON first), one
/// interval after the other as they are made. The file is written under a temporary name
/// (`.npy.partial`); at the end of the stream its header gets the interval count and it is
/// renamed, so a run that fails leaves no file that looks complete (the partial one is
/// removed). Ctrl-C ends the stream early: like the event file, it then holds everything
/// converted so far.
pub struct VoxelTap {
    path: std::path::PathBuf,
    partial: std::path::PathBuf,
    file: std::io::BufWriter<std::fs::File>,
    shape: Option<(usize, u16, u16)>,
    intervals: usize,
    renamed: bool,
}

/// Bytes reserved for the `.npy` header (format 1.0: a multiple of 64), so the interval count
/// can be filled in at the end.
const NPY_HEADER: usize = 128;

fn npy_header(intervals: usize, channels: usize, height: u16, width: u16) -> Vec<u8> {
    let shape = format!("({intervals}, {channels}, {height}, {width})");
    crate::format::npz::npy_header("'<f4'", &shape, NPY_HEADER)
}

impl VoxelTap {
    /// A tap writing to `path`.
    pub fn new(path: &std::path::Path) -> Result<Self> {
        use std::io::Write;
        let partial = path.with_extension("npy.partial");
        let file = std::fs::File::create(&partial).map_err(|e| Error::io(&partial, e))?;
        let mut file = std::io::BufWriter::new(file);
        if let Err(e) = file.write_all(&npy_header(0, 0, 0, 0)) {
            let _ = std::fs::remove_file(&partial);
            return Err(Error::io(&partial, e));
        }
        Ok(VoxelTap {
            path: path.to_path_buf(),
            partial,
            file,
            shape: None,
            intervals: 0,
            renamed: false,
        })
    }

    fn write(&mut self, batches: &[crate::stage1::Stage1Batch]) -> Result<()> {
        use std::io::Write;
        for b in batches {
            let crate::stage1::Stage1Batch::Voxels(grid, _) = b else {
                return Err(Error::invalid(
                    "--write-voxels",
                    "this Stage 1 hands over events, not voxels (use the learned tier, or the \
                     physics tier with --mode voxels)",
                ));
            };
            let shape = (2 * grid.bins(), grid.height(), grid.width());
            if *self.shape.get_or_insert(shape) != shape {
                return Err(Error::invalid("--write-voxels", "the voxel size changed"));
            }
            let (c, h, w) = shape;
            let dense_bytes = 4 * c as u64 * u64::from(h) * u64::from(w);
            crate::limits::memory("--write-voxels", dense_bytes, "one interval's dense voxels")?;
            // Written a slice at a time: no second copy of the tensor as bytes.
            let mut bytes = Vec::with_capacity(4 << 16);
            for chunk in grid.to_dense().chunks(1 << 16) {
                bytes.clear();
                chunk
                    .iter()
                    .for_each(|v| bytes.extend_from_slice(&v.to_le_bytes()));
                self.file
                    .write_all(&bytes)
                    .map_err(|e| Error::io(&self.partial, e))?;
            }
            self.intervals += 1;
        }
        Ok(())
    }

    /// Writes the header for what is in the file and gives the file its name.
    fn complete(&mut self) -> Result<()> {
        use std::io::{Seek, SeekFrom, Write};
        let (c, h, w) = self.shape.unwrap_or((0, 0, 0));
        let header = npy_header(self.intervals, c, h, w);
        let at = if self.renamed {
            &self.path
        } else {
            &self.partial
        };
        self.file
            .flush()
            .and_then(|()| {
                let f = self.file.get_mut();
                f.seek(SeekFrom::Start(0))?;
                f.write_all(&header)?;
                f.seek(SeekFrom::End(0))?;
                f.sync_all()
            })
            .map_err(|e| Error::io(at, e))?;
        if !self.renamed {
            std::fs::rename(&self.partial, &self.path).map_err(|e| Error::io(&self.path, e))?;
            self.renamed = true;
        }
        Ok(())
    }
}

impl Drop for VoxelTap {
    fn drop(&mut self) {
        if !self.renamed {
            let _ = std::fs::remove_file(&self.partial);
        }
    }
}

impl Tap for VoxelTap {
    fn batches(&mut self, batches: &[crate::stage1::Stage1Batch]) -> Result<()> {
        self.write(batches)
    }

    /// The end of the stream or a break in it: the file is complete up to here (a later
    /// interval goes on after it and rewrites the header).
    fn finished(&mut self) -> Result<()> {
        self.complete()
    }

    fn describe(&self, tier: String) -> String {
        format!("{tier}, voxels to {}", self.path.display())
    }
}
