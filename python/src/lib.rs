//! `v2ce._v2ce`: the native half of the Python package (`python/pysrc/v2ce/` is the other).
//!
//! Everything here calls the same library functions as the command line: a conversion is
//! [`v2ce::convert::convert`] with the same configuration, Stage 1 and sampler, so the same
//! frames and seed give the same events. Events cross the boundary as one numpy `uint8` array
//! of 16-byte records (`t` i64, `x` u16, `y` u16, `p` u8, 3 bytes of padding), which the Python
//! side views as its structured dtype without a copy. The GIL is released while the core
//! works; a conversion checks for Ctrl-C a few times a second and stops cleanly. Every error
//! is a Python exception carrying the CLI's one-line message; a panic inside the core is
//! caught and becomes a `RuntimeError`, never an abort.

// Functions stay under 150 lines (clippy.toml): a longer one holds several steps to name.
#![warn(clippy::too_many_lines)]

mod frames;

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray1, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::exceptions::{PyKeyboardInterrupt, PyOSError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyList, PyString};

use v2ce::config::Config;
use v2ce::error::Error;
use v2ce::event::Event;
use v2ce::format::EventDecoder;
use v2ce::sink::{Sink, SinkStats};
use v2ce::stage1::{Stage1, Stage1Batch};
use v2ce::stage2::Sampler;

/// Packed events and the sensor size (width, height).
type EventsAndSize<'py> = (Bound<'py, PyArray1<u8>>, (u16, u16));

/// Bytes per event record handed to Python.
const RECORD: usize = 16;

/// The library's error as the Python exception a caller expects, with the CLI's message.
pub(crate) fn py_err(e: Error) -> PyErr {
    let message = e.to_string();
    match e {
        Error::Io { .. } => PyOSError::new_err(message),
        Error::Interrupted(_) => PyKeyboardInterrupt::new_err(message),
        Error::Run(_) => PyRuntimeError::new_err(message),
        _ => PyValueError::new_err(message),
    }
}

/// Runs `f`, turning a panic into a `RuntimeError` (nothing may unwind into Python).
fn guarded<T>(what: &str, f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(p) => {
            let why = p
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "unknown".into());
            Err(PyRuntimeError::new_err(format!(
                "{what}: internal error ({why}); please report it"
            )))
        }
    }
}

/// Events packed as the records the Python side views.
/// The events as records, in memory checked first (a clear error, not an abort).
fn pack(events: &[Event]) -> v2ce::Result<Vec<u8>> {
    let bytes = events.len().saturating_mul(RECORD);
    v2ce::limits::memory("events", bytes as u64, "packing the events for NumPy")?;
    let mut out = vec![0u8; bytes];
    for (e, r) in events.iter().zip(out.chunks_exact_mut(RECORD)) {
        r[0..8].copy_from_slice(&e.t.to_le_bytes());
        r[8..10].copy_from_slice(&e.x.to_le_bytes());
        r[10..12].copy_from_slice(&e.y.to_le_bytes());
        r[12] = u8::from(e.on);
    }
    Ok(out)
}

fn records<'py>(py: Python<'py>, bytes: Vec<u8>) -> Bound<'py, PyArray1<u8>> {
    PyArray1::from_vec(py, bytes)
}

/// How deep settings may nest (tables and lists in each other): the configuration's own
/// tables are two deep; a recursive or absurdly deep value is refused, not followed.
const MAX_SETTINGS_DEPTH: usize = 32;

/// A TOML value from a Python one (str, bool, int, float, dict, list), `depth` tables or lists
/// down.
fn toml_value(v: &Bound<'_, PyAny>, key: &str, depth: usize) -> PyResult<toml::Value> {
    if depth > MAX_SETTINGS_DEPTH {
        return Err(PyValueError::new_err(format!(
            "{key}: settings nested more than {MAX_SETTINGS_DEPTH} deep (a value that contains itself?)"
        )));
    }
    // bool before int: Python's bool is an int.
    if v.is_instance_of::<PyBool>() {
        return Ok(toml::Value::Boolean(v.extract()?));
    }
    if v.is_instance_of::<PyInt>() {
        return v
            .extract::<i64>()
            .map(toml::Value::Integer)
            .map_err(|_| PyValueError::new_err(format!("{key}: {v} does not fit 64 bits")));
    }
    if v.is_instance_of::<PyFloat>() {
        return Ok(toml::Value::Float(v.extract()?));
    }
    if v.is_instance_of::<PyString>() {
        return Ok(toml::Value::String(v.extract()?));
    }
    if let Ok(d) = v.cast::<PyDict>() {
        return Ok(toml::Value::Table(toml_table(d, depth + 1)?));
    }
    if let Ok(l) = v.cast::<PyList>() {
        return l
            .iter()
            .map(|item| toml_value(&item, key, depth + 1))
            .collect::<PyResult<Vec<_>>>()
            .map(toml::Value::Array);
    }
    if let Ok(p) = v.extract::<PathBuf>() {
        return Ok(toml::Value::String(p.display().to_string()));
    }
    Err(PyValueError::new_err(format!(
        "{key}: a {} cannot be a setting (str, bool, int, float, dict or list)",
        v.get_type().name()?
    )))
}

fn toml_table(d: &Bound<'_, PyDict>, depth: usize) -> PyResult<toml::Table> {
    if depth > MAX_SETTINGS_DEPTH {
        return Err(PyValueError::new_err(format!(
            "settings nested more than {MAX_SETTINGS_DEPTH} deep (a value that contains itself?)"
        )));
    }
    let mut t = toml::Table::new();
    for (k, v) in d.iter() {
        let key: String = k.extract()?;
        if v.is_none() {
            continue;
        }
        t.insert(key.clone(), toml_value(&v, &key, depth)?);
    }
    Ok(t)
}

/// `overrides` merged into `base`, table by table.
fn merge(base: &mut toml::Table, overrides: toml::Table) {
    for (k, v) in overrides {
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge(b, o),
            (_, v) => {
                base.insert(k, v);
            }
        }
    }
}

/// The configuration: a TOML file (`config`), then `settings` (the same tables as a dict)
/// over it, checked as the CLI checks a config file.
fn configuration(config: Option<PathBuf>, settings: &Bound<'_, PyDict>) -> PyResult<Config> {
    let (mut table, origin) = match &config {
        Some(path) => {
            let text = std::fs::read_to_string(path).map_err(|e| py_err(Error::io(path, e)))?;
            let table: toml::Table = text
                .parse()
                .map_err(|e| py_err(Error::format(path, format!("{e}"))))?;
            (table, path.clone())
        }
        None => (toml::Table::new(), PathBuf::from("the arguments")),
    };
    merge(&mut table, toml_table(settings, 0)?);
    let text = toml::to_string(&table).map_err(|e| PyValueError::new_err(e.to_string()))?;
    Config::parse(&text, &origin).map_err(py_err)
}

/// Collects every event the pipeline hands on.
struct Collect {
    events: Arc<Mutex<Vec<Event>>>,
    stats: SinkStats,
}

impl Sink for Collect {
    fn describe(&self) -> String {
        "numpy array".into()
    }

    fn send(&mut self, events: &[Event]) -> v2ce::Result<()> {
        self.stats.events_in += events.len() as u64;
        self.stats.events_sent += events.len() as u64;
        self.events
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .extend_from_slice(events);
        Ok(())
    }

    fn finish(&mut self) -> v2ce::Result<()> {
        Ok(())
    }

    fn stats(&self) -> SinkStats {
        self.stats
    }

    fn is_recording(&self) -> bool {
        true
    }
}

/// Runs `work` with the GIL released. `work` calls the `tick` it is given between units of
/// work: once Ctrl-C has been pressed the tick fails, `work` ends with that error, and the call
/// raises `KeyboardInterrupt`.
fn detached<T: Send>(
    py: Python<'_>,
    what: &str,
    work: impl FnOnce(&(dyn Fn() -> v2ce::Result<()> + Sync)) -> PyResult<T> + Send,
) -> PyResult<T> {
    let interrupted = AtomicBool::new(false);
    let tick = || -> v2ce::Result<()> {
        if Python::attach(|py| py.check_signals().is_err()) {
            interrupted.store(true, Ordering::Relaxed);
            return Err(Error::Run(format!("{what} interrupted")));
        }
        Ok(())
    };
    let result = py.detach(|| work(&tick));
    if interrupted.load(Ordering::Relaxed) {
        return Err(PyKeyboardInterrupt::new_err(format!(
            "v2ce.{what} interrupted"
        )));
    }
    result
}

/// Runs a conversion of `source` with the GIL released, checking for Ctrl-C between ticks;
/// returns the packed events and the sensor size.
fn run_conversion(
    py: Python<'_>,
    source: Box<dyn v2ce::frame::FrameSource>,
    size: Option<(u16, u16)>,
    config: &Config,
    max_frames: Option<u64>,
) -> PyResult<(Vec<u8>, (u16, u16))> {
    let interrupted = AtomicBool::new(false);
    let stop = AtomicBool::new(false);
    let result = py.detach(|| -> v2ce::Result<(Vec<u8>, (u16, u16))> {
        let mut source = source;
        if let Some(size) = size {
            source = Box::new(v2ce::frame::resize::Resized::new(source, size)?);
        }
        let stage1 = v2ce::convert::build_stage1(config, source.as_ref())?;
        let out_size = stage1.output_size();
        let events = Arc::new(Mutex::new(Vec::new()));
        let sink = Collect {
            events: events.clone(),
            stats: SinkStats::default(),
        };
        let progress = |_: &v2ce::convert::ConvertReport| {
            let signalled = Python::attach(|py| py.check_signals().is_err());
            if signalled {
                interrupted.store(true, Ordering::Relaxed);
                stop.store(true, Ordering::Relaxed);
            }
        };
        v2ce::convert::convert(
            source,
            stage1,
            config,
            vec![Box::new(sink)],
            max_frames,
            &stop,
            progress,
        )?;
        let events = std::mem::take(&mut *events.lock().unwrap_or_else(|e| e.into_inner()));
        Ok((pack(&events)?, out_size))
    });
    if interrupted.load(Ordering::Relaxed) {
        return Err(PyKeyboardInterrupt::new_err("v2ce.convert interrupted"));
    }
    result.map_err(py_err)
}

/// Converts a video, image folder, frame list, `.y4m`, `.aedat4` with APS frames, or
/// `"fixture"`; returns the packed events and the sensor size.
#[pyfunction]
#[pyo3(signature = (source, settings, config=None, size=None, fps=None, color="auto", max_frames=None))]
#[allow(clippy::too_many_arguments)]
fn convert_path<'py>(
    py: Python<'py>,
    source: PathBuf,
    settings: &Bound<'py, PyDict>,
    config: Option<PathBuf>,
    size: Option<(u16, u16)>,
    fps: Option<f64>,
    color: &str,
    max_frames: Option<u64>,
) -> PyResult<EventsAndSize<'py>> {
    guarded("convert", || {
        let config = configuration(config, settings)?;
        let color = match color {
            "auto" => v2ce::frame::images::ColorSpace::Auto,
            "srgb" => v2ce::frame::images::ColorSpace::Srgb,
            "linear" => v2ce::frame::images::ColorSpace::Linear,
            other => {
                return Err(PyValueError::new_err(format!(
                    "color '{other}': expected auto, srgb or linear"
                )))
            }
        };
        let options = v2ce::frame::SourceOptions {
            fps,
            color,
            topic: None,
        };
        let frames = py
            .detach(|| {
                if source.as_os_str() == v2ce::frame::fixture::NAME {
                    v2ce::frame::fixture::open()
                } else {
                    v2ce::frame::open(&source, &options)
                }
            })
            .map_err(py_err)?;
        let (bytes, size) = run_conversion(py, frames, size, &config, max_frames)?;
        Ok((records(py, bytes), size))
    })
}

/// Converts frames held in a numpy array `(N, H, W)` (uint8: sRGB-encoded gray; uint16:
/// linear 0..65535; float32: linear 0..1) at `times_us`, reading them in place.
#[pyfunction]
#[pyo3(signature = (frames, times_us, settings, config=None, size=None, linear=false, max_frames=None))]
#[allow(clippy::too_many_arguments)]
fn convert_frames<'py>(
    py: Python<'py>,
    frames: &Bound<'py, PyUntypedArray>,
    times_us: PyReadonlyArray1<'py, i64>,
    settings: &Bound<'py, PyDict>,
    config: Option<PathBuf>,
    size: Option<(u16, u16)>,
    linear: bool,
    max_frames: Option<u64>,
) -> PyResult<EventsAndSize<'py>> {
    guarded("convert", || {
        let config = configuration(config, settings)?;
        let times = times_us.as_slice()?.to_vec();
        let view = frames::FramesView::new(frames, linear)?;
        // SAFETY: `view` borrows the array read-only (its borrow guard lives until this
        // function returns); the source made from it is consumed by `run_conversion`, whose
        // pipeline joins every thread before it returns, so no frame is read after that.
        let source = unsafe { view.source(times)? };
        let (bytes, size) = run_conversion(py, Box::new(source), size, &config, max_frames)?;
        drop(view);
        Ok((records(py, bytes), size))
    })
}

/// Stage 1 and the sampler run frame by frame in the caller's thread, as `esim_py` and
/// eventcv do: the events of each interval as its closing frame comes.
#[pyclass(module = "v2ce._v2ce")]
struct Simulator {
    inner: Mutex<Streaming>,
    width: u16,
    height: u16,
    linear: bool,
}

struct Streaming {
    stage1: Box<dyn Stage1>,
    sampler: Box<dyn Sampler>,
    last_t: Option<i64>,
    finished: bool,
}

impl Streaming {
    fn events(&mut self, batches: Vec<Stage1Batch>) -> Vec<Event> {
        let mut out = Vec::new();
        for b in batches {
            out.extend(v2ce::stage2::events_of(b, self.sampler.as_ref()).0);
        }
        out
    }
}

#[pymethods]
impl Simulator {
    #[new]
    #[pyo3(signature = (width, height, settings, config=None, linear=false))]
    fn new(
        width: u16,
        height: u16,
        settings: &Bound<'_, PyDict>,
        config: Option<PathBuf>,
        linear: bool,
    ) -> PyResult<Self> {
        guarded("Simulator", || {
            v2ce::limits::frame_size("Simulator", u32::from(width), u32::from(height))
                .map_err(py_err)?;
            let config = configuration(config, settings)?;
            let encoding = if linear {
                v2ce::frame::SourceEncoding::Linear
            } else {
                v2ce::frame::SourceEncoding::Srgb
            };
            let stage1 = v2ce::stage1::build(
                &config.stage1,
                config.stage2.bins,
                (width, height),
                encoding,
            )
            .map_err(py_err)?;
            Ok(Simulator {
                inner: Mutex::new(Streaming {
                    stage1,
                    sampler: config.stage2.sampler.build(config.stage2.seed),
                    last_t: None,
                    finished: false,
                }),
                width,
                height,
                linear,
            })
        })
    }

    /// The events of the interval that `frame` (at `t_us`) closes.
    fn push<'py>(
        &self,
        py: Python<'py>,
        frame: &Bound<'py, PyUntypedArray>,
        t_us: i64,
    ) -> PyResult<Bound<'py, PyArray1<u8>>> {
        guarded("Simulator.push", || {
            let frame = frames::one_frame(frame, t_us, (self.width, self.height), self.linear)?;
            v2ce::time::check("t_us", t_us).map_err(py_err)?;
            // The simulator's lock is taken with the GIL released: a thread waiting for it
            // holds nothing another thread needs (pushes from several threads take turns).
            let bytes = py.detach(|| -> PyResult<Vec<u8>> {
                let mut s = self.inner.lock().unwrap_or_else(|e| e.into_inner());
                if s.finished {
                    return Err(PyValueError::new_err("push after finish()"));
                }
                if let Some(last) = s.last_t {
                    if t_us <= last {
                        return Err(PyValueError::new_err(format!(
                            "frame at {t_us} us does not come after the previous one at {last} us"
                        )));
                    }
                    v2ce::time::span("t_us", last, t_us).map_err(py_err)?;
                }
                let mut batches = Vec::new();
                s.stage1.push(&frame, &mut batches).map_err(py_err)?;
                s.last_t = Some(t_us);
                pack(&s.events(batches)).map_err(py_err)
            })?;
            Ok(records(py, bytes))
        })
    }

    /// What Stage 1 still holds (the learned tier's last window); no frame may follow.
    fn finish<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray1<u8>>> {
        guarded("Simulator.finish", || {
            let bytes = py.detach(|| -> PyResult<Vec<u8>> {
                let mut s = self.inner.lock().unwrap_or_else(|e| e.into_inner());
                if s.finished {
                    return Ok(Vec::new());
                }
                s.finished = true;
                let mut batches = Vec::new();
                s.stage1.finish(&mut batches).map_err(py_err)?;
                pack(&s.events(batches)).map_err(py_err)
            })?;
            Ok(records(py, bytes))
        })
    }

    /// The sensor's width and height.
    #[getter]
    fn size(&self) -> (u16, u16) {
        (self.width, self.height)
    }
}

/// Reads a whole event file; returns the packed events and the sensor size.
#[pyfunction]
fn read(py: Python<'_>, path: PathBuf) -> PyResult<EventsAndSize<'_>> {
    guarded("read", || {
        let (bytes, size) = py
            .detach(|| {
                v2ce::format::read_events(&path)
                    .and_then(|r| Ok((pack(r.events.events())?, (r.width, r.height))))
            })
            .map_err(py_err)?;
        Ok((records(py, bytes), size))
    })
}

/// Writes events (columns) to `path` in the format its extension names, under its partial
/// name until complete as the CLI does.
#[pyfunction]
#[pyo3(signature = (path, t, x, y, p, width, height, evt=2, compression="lz4"))]
#[allow(clippy::too_many_arguments)]
fn write(
    py: Python<'_>,
    path: PathBuf,
    t: PyReadonlyArray1<'_, i64>,
    x: PyReadonlyArray1<'_, u16>,
    y: PyReadonlyArray1<'_, u16>,
    p: PyReadonlyArray1<'_, u8>,
    width: u16,
    height: u16,
    evt: u8,
    compression: &str,
) -> PyResult<()> {
    guarded("write", || {
        let (t, x, y, p) = (t.as_slice()?, x.as_slice()?, y.as_slice()?, p.as_slice()?);
        if x.len() != t.len() || y.len() != t.len() || p.len() != t.len() {
            return Err(PyValueError::new_err("t, x, y and p differ in length"));
        }
        times_in_range("t", t)?;
        py.detach(|| -> v2ce::Result<()> {
            let compression = v2ce::format::Compression::from_name(compression)?;
            let format = v2ce::format::Format::for_output(&path, Some(evt), compression)?;
            let output = v2ce::format::PartialOutput::new(&path);
            let written = (|| {
                let mut enc = v2ce::format::create(output.writing(), format, width, height)?;
                let mut chunk = Vec::with_capacity(1 << 16);
                for start in (0..t.len()).step_by(1 << 16) {
                    let end = (start + (1 << 16)).min(t.len());
                    chunk.clear();
                    chunk.extend((start..end).map(|i| Event::new(t[i], x[i], y[i], p[i] != 0)));
                    enc.write(&chunk)?;
                }
                enc.finish()
            })();
            written.map_err(|e| output.explain(e))?;
            output.commit()
        })
        .map_err(py_err)
    })
}

/// Event columns as the library's events (`p != 0` is ON), checked to be in time order.
fn events_of_columns(
    t: &[i64],
    x: &[u16],
    y: &[u16],
    p: &[u8],
    what: &str,
) -> PyResult<Vec<Event>> {
    if x.len() != t.len() || y.len() != t.len() || p.len() != t.len() {
        return Err(PyValueError::new_err(format!(
            "{what}: t, x, y and p differ in length"
        )));
    }
    times_in_range("t", t).map_err(|e| PyValueError::new_err(format!("{what}: {e}")))?;
    if let Some(k) = t.windows(2).position(|w| w[1] < w[0]) {
        return Err(PyValueError::new_err(format!(
            "{what}: not sorted by time (event {} at {} us comes after {} us)",
            k + 1,
            t[k + 1],
            t[k]
        )));
    }
    Ok((0..t.len())
        .map(|i| Event::new(t[i], x[i], y[i], p[i] != 0))
        .collect())
}

/// An error naming the first of `t` out of the range times may take (see `v2ce::time`).
pub(crate) fn times_in_range(what: &'static str, t: &[i64]) -> PyResult<()> {
    for (i, &v) in t.iter().enumerate() {
        if let Err(e) = v2ce::time::check(what, v) {
            return Err(PyValueError::new_err(format!("value {i}: {e}")));
        }
    }
    Ok(())
}

/// Frame times as intervals, as the CLI makes them.
fn intervals(frame_times_us: &[i64]) -> PyResult<Vec<v2ce::Interval>> {
    v2ce::interval::intervals_from_frames(frame_times_us)
        .map_err(|e| PyValueError::new_err(format!("frame_times_us: {e}")))
}

/// Events given as columns.
type Columns<'py> = (
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray1<'py, u16>,
    PyReadonlyArray1<'py, u16>,
    PyReadonlyArray1<'py, u8>,
);

fn events_arg(c: &Columns<'_>, what: &str) -> PyResult<Vec<Event>> {
    events_of_columns(
        c.0.as_slice()?,
        c.1.as_slice()?,
        c.2.as_slice()?,
        c.3.as_slice()?,
        what,
    )
}

/// Each interval's voxel grid as a dense float32 tensor `(intervals, 2 * bins, H, W)` in V2CE's
/// layout (channel = polarity * bins + node, ON first), as `convert --write-voxels` writes it.
#[pyfunction]
#[pyo3(signature = (events, frame_times_us, width, height, bins=10))]
fn voxelize<'py>(
    py: Python<'py>,
    events: Columns<'py>,
    frame_times_us: PyReadonlyArray1<'py, i64>,
    width: u16,
    height: u16,
    bins: usize,
) -> PyResult<Bound<'py, numpy::PyArray4<f32>>> {
    guarded("voxelize", || {
        let events = events_arg(&events, "events")?;
        let intervals = intervals(frame_times_us.as_slice()?)?;
        let per = 2 * bins * width as usize * height as usize;
        let bytes = (per as u64)
            .saturating_mul(intervals.len() as u64)
            .saturating_mul(4);
        v2ce::limits::memory("voxelize", bytes, "the voxel tensor").map_err(py_err)?;
        let dense = detached(py, "voxelize", |tick| {
            let work = || -> v2ce::Result<Vec<f32>> {
                let mut v = v2ce::Voxelizer::new(width, height, bins)?;
                let mut out = Vec::with_capacity(per * intervals.len());
                for iv in &intervals {
                    tick()?;
                    let slice = v2ce::event::time_slice(&events, iv.start(), iv.end());
                    out.extend(v.voxelize(slice, *iv)?.to_dense());
                }
                Ok(out)
            };
            work().map_err(py_err)
        })?;
        let shape = [intervals.len(), 2 * bins, height as usize, width as usize];
        numpy::PyArray1::from_vec(py, dense)
            .reshape(shape)
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))
    })
}

/// The events voxel values imply (their sum, NaN and negatives counting none, as the samplers
/// take them), or an error naming a value above [`v2ce::stage2::MAX_NODE_VALUE`], which a
/// sampler would clamp and so lose events.
fn implied_events(data: &[f32]) -> PyResult<u64> {
    let cap = v2ce::stage2::MAX_NODE_VALUE;
    let mut sum = 0f64;
    for (i, &v) in data.iter().enumerate() {
        let v = f64::from(v);
        if v > cap {
            return Err(PyValueError::new_err(format!(
                "voxels: value {v} at flat index {i} is above the {cap} events one node may hold"
            )));
        }
        if v > 0.0 {
            sum += v;
        }
    }
    Ok(sum.ceil() as u64)
}

/// Events re-timed from voxels `(intervals, 2 * bins, H, W)` by a Stage 2 sampler.
#[pyfunction]
#[pyo3(signature = (voxels, frame_times_us, sampler="spatial", seed=0))]
fn sample<'py>(
    py: Python<'py>,
    voxels: numpy::PyReadonlyArray4<'py, f32>,
    frame_times_us: PyReadonlyArray1<'py, i64>,
    sampler: &str,
    seed: u64,
) -> PyResult<Bound<'py, PyArray1<u8>>> {
    guarded("sample", || {
        let shape = voxels.shape().to_vec();
        let (k, c2, h, w) = (shape[0], shape[1], shape[2], shape[3]);
        let intervals = intervals(frame_times_us.as_slice()?)?;
        if intervals.len() != k {
            return Err(PyValueError::new_err(format!(
                "{k} voxel grids for {} frame intervals ({} frame times)",
                intervals.len(),
                intervals.len() + 1
            )));
        }
        if c2 % 2 != 0 || c2 < 4 {
            return Err(PyValueError::new_err(format!(
                "{c2} channels: expected 2 x bins (ON then OFF), bins >= 2"
            )));
        }
        let fit = |v: usize| u32::try_from(v).unwrap_or(u32::MAX);
        v2ce::limits::frame_size("voxels", fit(w), fit(h)).map_err(py_err)?;
        let kind: v2ce::SamplerKind = sampler.parse().map_err(py_err)?;
        let data = voxels
            .as_slice()
            .map_err(|_| PyValueError::new_err("voxels: not C-contiguous"))?;
        // Every count is kept: a node above the most a sampler takes is refused, not clamped;
        // and the events the voxels imply must fit in memory (an event and its record).
        let implied = implied_events(data)?;
        v2ce::limits::memory(
            "voxels",
            implied.saturating_mul((std::mem::size_of::<Event>() + RECORD) as u64),
            &format!("the {implied} events the voxels imply"),
        )
        .map_err(py_err)?;
        let bytes = detached(py, "sample", |tick| {
            let work = || -> v2ce::Result<Vec<u8>> {
                let s = kind.build(seed);
                let per = c2 * h * w;
                let mut out = Vec::new();
                for (i, iv) in intervals.iter().enumerate() {
                    tick()?;
                    let grid = v2ce::VoxelGrid::from_dense(
                        w as u16,
                        h as u16,
                        c2 / 2,
                        &data[i * per..(i + 1) * per],
                    )?;
                    let mut events = Vec::new();
                    s.sample(&grid, *iv, &mut events);
                    out.extend(events);
                }
                pack(&out)
            };
            work().map_err(py_err)
        })?;
        Ok(records(py, bytes))
    })
}

/// `v2ce eval stage1`'s scores of `sim` against `real` on the frame intervals, as JSON.
#[pyfunction]
fn eval_stage1(
    py: Python<'_>,
    real: Columns<'_>,
    sim: Columns<'_>,
    frame_times_us: PyReadonlyArray1<'_, i64>,
    width: u16,
    height: u16,
) -> PyResult<String> {
    guarded("eval_stage1", || {
        let real = events_arg(&real, "real")?;
        let sim = events_arg(&sim, "sim")?;
        let intervals = intervals(frame_times_us.as_slice()?)?;
        let size = (width, height);
        detached(py, "eval_stage1", |tick| {
            let work = || -> v2ce::Result<String> {
                v2ce::eval::check_sensor(&real, size, std::path::Path::new("real"))?;
                v2ce::eval::check_sensor(&sim, size, std::path::Path::new("sim"))?;
                Ok(
                    v2ce::eval::stage1_with(&real, &sim, &intervals, size, tick)?
                        .to_json()
                        .to_string(),
                )
            };
            work().map_err(py_err)
        })
    })
}

/// `v2ce eval stage2`'s scores: `events` voxelized per frame interval, re-timed by the sampler
/// and compared with themselves, as JSON.
#[pyfunction]
#[pyo3(signature = (events, frame_times_us, width, height, sampler="spatial", bins=10, seed=0))]
#[allow(clippy::too_many_arguments)]
fn eval_stage2(
    py: Python<'_>,
    events: Columns<'_>,
    frame_times_us: PyReadonlyArray1<'_, i64>,
    width: u16,
    height: u16,
    sampler: &str,
    bins: usize,
    seed: u64,
) -> PyResult<String> {
    guarded("eval_stage2", || {
        let events = events_arg(&events, "events")?;
        let intervals = intervals(frame_times_us.as_slice()?)?;
        let kind: v2ce::SamplerKind = sampler.parse().map_err(py_err)?;
        detached(py, "eval_stage2", |tick| {
            let work = || -> v2ce::Result<String> {
                v2ce::eval::check_sensor(&events, (width, height), std::path::Path::new("events"))?;
                let recording = v2ce::format::Recording::new(events, Some((width, height)));
                let s = kind.build(seed);
                // Called in interval order as the scoring goes.
                let report =
                    v2ce::eval::stage2(&recording, &intervals, bins, s.as_ref(), |_| tick())?;
                serde_json::to_string(&report).map_err(|e| Error::invalid("report", e.to_string()))
            };
            work().map_err(py_err)
        })
    })
}

/// An event file read a chunk at a time.
#[pyclass(module = "v2ce._v2ce")]
struct Reader {
    decoder: Mutex<Box<dyn EventDecoder + Send>>,
    path: PathBuf,
}

#[pymethods]
impl Reader {
    #[new]
    fn new(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        guarded("open", || {
            let decoder = py.detach(|| v2ce::format::open(&path)).map_err(py_err)?;
            Ok(Reader {
                decoder: Mutex::new(decoder),
                path,
            })
        })
    }

    /// The sensor size the file states, if any.
    #[getter]
    fn size(&self, py: Python<'_>) -> Option<(u16, u16)> {
        // The lock with the GIL released (see `read`).
        py.detach(|| {
            self.decoder
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .size()
        })
    }

    /// About `n` more events (packed); empty at the end.
    fn read<'py>(&self, py: Python<'py>, n: usize) -> PyResult<Bound<'py, PyArray1<u8>>> {
        guarded("read", || {
            if n == 0 {
                return Err(PyValueError::new_err("a chunk of 0 events"));
            }
            let path = self.path.clone();
            // The reader's lock is taken with the GIL released: a thread waiting for it holds
            // nothing another thread needs (reads from several threads take turns).
            let bytes = py
                .detach(|| -> v2ce::Result<Vec<u8>> {
                    let mut d = self.decoder.lock().unwrap_or_else(|e| e.into_inner());
                    // A piece at a time, memory checked as it grows: `n` comes from the caller.
                    let mut out = Vec::new();
                    while out.len() < n {
                        let want = (n - out.len()).min(1 << 20);
                        if !v2ce::limits::room_for(&mut out, want) {
                            return Err(Error::format(
                                &path,
                                format!(
                                    "a chunk of {n} events needs more memory than this machine \
                                     has left ({} read): ask for fewer",
                                    out.len()
                                ),
                            ));
                        }
                        let got = d
                            .read_events(&mut out, want)
                            .map_err(|e| Error::format(&path, e.to_string()))?;
                        if got == 0 {
                            break;
                        }
                    }
                    pack(&out)
                })
                .map_err(py_err)?;
            Ok(records(py, bytes))
        })
    }
}

/// The library's version.
#[pyfunction]
fn version() -> &'static str {
    env!("CARGO_PKG_VERSION")
}

#[pymodule]
fn _v2ce(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(convert_path, m)?)?;
    m.add_function(wrap_pyfunction!(convert_frames, m)?)?;
    m.add_function(wrap_pyfunction!(read, m)?)?;
    m.add_function(wrap_pyfunction!(write, m)?)?;
    m.add_function(wrap_pyfunction!(version, m)?)?;
    m.add_function(wrap_pyfunction!(voxelize, m)?)?;
    m.add_function(wrap_pyfunction!(sample, m)?)?;
    m.add_function(wrap_pyfunction!(eval_stage1, m)?)?;
    m.add_function(wrap_pyfunction!(eval_stage2, m)?)?;
    m.add_class::<Simulator>()?;
    m.add_class::<Reader>()?;
    m.add("RECORD_BYTES", RECORD)?;
    Ok(())
}
