//! ONNX Runtime for the learned tier: finding the library for the user, opening a model, and
//! running one batch of windows.
//!
//! The library is loaded at run time (`ort`'s `load-dynamic`), so the physics tier and every
//! other command work on a machine without it. It is looked for, in order, at:
//! 1. `ORT_DYLIB_PATH` (a file);
//! 2. the `ort_library` key of `[stage1.learned]` (a file);
//! 3. the `onnxruntime` package of a Python environment: `$VIRTUAL_ENV`, then `.venv` in the
//!    current folder, beside the executable, or up to three folders above it (the project's
//!    venv for a `target/release/v2ce` build), then the user's and the system's site-packages;
//! 4. the usual system folders (`/usr/local/lib`, `/usr/lib`, the multiarch folder,
//!    `/opt/onnxruntime/lib`) and `LD_LIBRARY_PATH`.
//!
//! When none has it, the error gives the one command that installs it.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use ort::ep::ExecutionProvider;
use ort::session::Session;
use ort::value::{TensorRef, ValueType};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::model::v2ce_net::{ALIGN_KEY, RECEPTIVE_MARGIN_KEY};

use super::roi::Margin;
use super::LearnedConfig;

/// The ONNX Runtime release the project is built against (`ort`'s `api-31`).
pub const ORT_VERSION: &str = "1.31.1";

/// The command that installs the library where [`find_library`] looks.
pub const INSTALL_HINT: &str = "python3 -m venv .venv && .venv/bin/pip install onnxruntime==1.31.1";

/// Where the network runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Device {
    /// The CPU execution provider.
    Cpu,
    /// CUDA, or an error when the library has no CUDA provider or no GPU is usable.
    Cuda,
    /// CUDA when the library has it and it starts, else the CPU (the default).
    #[default]
    Auto,
}

fn library_names(dir: &Path) -> Option<PathBuf> {
    let exact = dir.join(format!("libonnxruntime.so.{ORT_VERSION}"));
    if exact.is_file() {
        return Some(exact);
    }
    // Any other release: ort refuses older ones with a clear message when it loads them.
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n == "libonnxruntime.so" || n.starts_with("libonnxruntime.so."))
        })
        .collect();
    // The newest release by number (1.31.1 after 1.9.0), the plain name last.
    let version = |p: &PathBuf| -> Vec<u64> {
        p.file_name()
            .and_then(|n| n.to_str())
            .and_then(|n| n.strip_prefix("libonnxruntime.so."))
            .map(|v| v.split('.').map(|x| x.parse().unwrap_or(0)).collect())
            .unwrap_or_default()
    };
    found.sort_by_key(version);
    found.pop()
}

fn site_packages(prefix: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for lib in ["lib", "lib64", "local/lib"] {
        let Ok(entries) = std::fs::read_dir(prefix.join(lib)) else {
            continue;
        };
        for e in entries.flatten() {
            let name = e.file_name();
            if name.to_string_lossy().starts_with("python3") {
                for sub in ["site-packages", "dist-packages"] {
                    out.push(e.path().join(sub).join("onnxruntime").join("capi"));
                }
            }
        }
    }
    out
}

/// Every folder searched, in order (see the module docs).
pub fn search_path() -> Vec<PathBuf> {
    let mut dirs = Vec::new();
    let mut prefixes = Vec::new();
    if let Some(v) = std::env::var_os("VIRTUAL_ENV") {
        prefixes.push(PathBuf::from(v));
    }
    if let Ok(cwd) = std::env::current_dir() {
        prefixes.push(cwd.join(".venv"));
    }
    if let Ok(exe) = std::env::current_exe() {
        let mut dir = exe.parent().map(Path::to_path_buf);
        for _ in 0..4 {
            let Some(d) = dir else { break };
            prefixes.push(d.join(".venv"));
            dir = d.parent().map(Path::to_path_buf);
        }
    }
    if let Some(home) = std::env::var_os("HOME") {
        prefixes.push(PathBuf::from(home).join(".local"));
    }
    prefixes.push(PathBuf::from("/usr/local"));
    prefixes.push(PathBuf::from("/usr"));
    for p in &prefixes {
        dirs.extend(site_packages(p));
    }
    if let Some(ld) = std::env::var_os("LD_LIBRARY_PATH") {
        dirs.extend(std::env::split_paths(&ld));
    }
    for d in [
        "/usr/local/lib",
        "/usr/lib",
        "/usr/lib/x86_64-linux-gnu",
        "/usr/lib/aarch64-linux-gnu",
        "/opt/onnxruntime/lib",
    ] {
        dirs.push(PathBuf::from(d));
    }
    dirs
}

/// The ONNX Runtime library to load: `ORT_DYLIB_PATH`, then `configured`, then the search path.
pub fn find_library(configured: Option<&Path>) -> Result<PathBuf> {
    if let Some(p) = std::env::var_os("ORT_DYLIB_PATH").filter(|p| !p.is_empty()) {
        let p = PathBuf::from(p);
        if p.is_file() {
            return Ok(p);
        }
        return Err(Error::invalid(
            "ONNX Runtime",
            format!(
                "ORT_DYLIB_PATH names {}, which is not a file; unset it to search, or install \
                 the library with: {INSTALL_HINT}",
                p.display()
            ),
        ));
    }
    if let Some(p) = configured {
        if p.is_file() {
            return Ok(p.to_path_buf());
        }
        return Err(Error::invalid(
            "ONNX Runtime",
            format!("ort_library names {}, which is not a file", p.display()),
        ));
    }
    search_path()
        .iter()
        .find_map(|d| library_names(d))
        .ok_or_else(|| {
            Error::invalid(
                "ONNX Runtime",
                format!(
                    "the library (libonnxruntime.so) was not found in ORT_DYLIB_PATH, a Python \
                     venv's onnxruntime package or the system folders; install it with: {INSTALL_HINT}"
                ),
            )
        })
}

type Loaded = std::result::Result<(PathBuf, ort::environment::Environment), String>;
static LOADED: OnceLock<Loaded> = OnceLock::new();

/// Loads the library once per process and builds the environment (kept for the process's
/// life); returns the library's path and the environment.
pub fn load(
    configured: Option<&Path>,
) -> Result<(PathBuf, &'static ort::environment::Environment)> {
    let loaded = LOADED.get_or_init(|| {
        let path = find_library(configured).map_err(|e| e.to_string())?;
        let builder = ort::init_from(&path).map_err(|e| {
            format!("ONNX Runtime: {e}; install a matching one with: {INSTALL_HINT}")
        })?;
        let env = builder
            .with_name("v2ce")
            .build()
            .map_err(|e| format!("ONNX Runtime at {}: {e}", path.display()))?;
        tracing::debug!("ONNX Runtime loaded from {}", path.display());
        Ok((path, env))
    });
    match loaded {
        Ok((path, env)) => Ok((path.clone(), env)),
        Err(e) => Err(Error::invalid("ONNX Runtime", e.clone())),
    }
}

fn ort_err(what: &str) -> impl Fn(ort::Error) -> Error + '_ {
    move |e| Error::invalid("ONNX Runtime", format!("{what}: {e}"))
}

/// Turns off ONNX Runtime's CPU memory arena: each tensor is freed when its last reader is
/// done instead of staying in a pool that only grows.
fn disable_cpu_arena(builder: &mut ort::session::builder::SessionBuilder) -> Result<()> {
    use ort::AsPointer;
    // SAFETY: the builder owns a valid OrtSessionOptions; the call only sets a flag on it and
    // returns a status we own (null on success).
    let status = unsafe { (ort::api().DisableCpuMemArena)(builder.ptr_mut()) };
    if status.0.is_null() {
        return Ok(());
    }
    // SAFETY: a non-null status is ours to read and release exactly once.
    unsafe { (ort::api().ReleaseStatus)(status.0) };
    Err(Error::invalid(
        "ONNX Runtime",
        "could not turn off the CPU memory arena",
    ))
}

/// Symbolic or fixed dimensions of a model input or output (-1: any).
fn dims(t: &ValueType) -> Option<Vec<i64>> {
    match t {
        ValueType::Tensor { shape, .. } => Some(shape.iter().copied().collect()),
        _ => None,
    }
}

/// A V2CE-shaped network: input `(B, L, 2, H, W)` normalised frame pairs, output
/// `(B, L, 2*C, H, W)` voxels.
pub struct Network {
    session: Session,
    input: String,
    path: PathBuf,
    provider: &'static str,
    fixed: [Option<usize>; 5],
    field: Option<Margin>,
}

impl Network {
    /// Opens `path` with `options`; checks that the model takes one rank-5 float input with 2
    /// channels in axis 2 and gives a rank-5 output.
    pub fn open(path: &Path, options: &LearnedConfig) -> Result<Self> {
        if !path.is_file() {
            return Err(Error::io(
                path,
                std::io::Error::new(std::io::ErrorKind::NotFound, "no such model file"),
            ));
        }
        Self::open_from(path, None, options)
    }

    /// Opens a model held in memory (one built into v2ce), named `name` in messages.
    pub fn open_bytes(name: &Path, bytes: &[u8], options: &LearnedConfig) -> Result<Self> {
        Self::open_from(name, Some(bytes), options)
    }

    fn open_from(path: &Path, bytes: Option<&[u8]>, options: &LearnedConfig) -> Result<Self> {
        let commit = |b: &mut ort::session::builder::SessionBuilder| match bytes {
            Some(bytes) => b.commit_from_memory(bytes),
            None => b.commit_from_file(path),
        };
        let library = Some(options.ort_library.as_path()).filter(|p| !p.as_os_str().is_empty());
        let (_, env) = load(library)?;
        let mut builder = Session::builder(env).map_err(ort_err("session options"))?;
        if options.threads > 0 {
            builder = builder
                .with_intra_threads(options.threads)
                .map_err(|e| Error::invalid("ONNX Runtime", format!("threads: {e}")))?;
        }
        if !options.cpu_arena {
            disable_cpu_arena(&mut builder)?;
        }
        let mut provider = "cpu";
        // Without CUDA, for `auto` to fall back on when CUDA starts but the session cannot.
        let cpu_builder = builder.clone();
        let cuda = ort::ep::CUDA::default();
        match options.device {
            Device::Cpu => {}
            Device::Cuda => {
                builder = builder
                    .with_execution_providers([cuda.build().error_on_failure()])
                    .map_err(|e| {
                        Error::invalid(
                            "ONNX Runtime",
                            format!(
                                "CUDA provider: {e} (the onnxruntime-gpu package's library \
                                 has it; the CPU package has not)"
                            ),
                        )
                    })?;
                provider = "cuda";
            }
            Device::Auto => {
                if ort::ep::CUDA::is_available().unwrap_or(false) {
                    match builder
                        .clone()
                        .with_execution_providers([cuda.build().error_on_failure()])
                    {
                        Ok(b) => {
                            builder = b;
                            provider = "cuda";
                        }
                        Err(e) => {
                            tracing::warn!("CUDA provider unusable ({e}); running on the CPU")
                        }
                    }
                }
            }
        }
        let cannot = |e: ort::Error| {
            Error::format(path, format!("ONNX Runtime cannot load this model: {e}"))
        };
        let session = match commit(&mut builder) {
            Ok(s) => s,
            // The CUDA provider creates its device with the session (no GPU, an old driver).
            Err(e) if options.device == Device::Auto && provider == "cuda" => {
                tracing::warn!("CUDA could not run this model ({e}); running on the CPU");
                provider = "cpu";
                let mut b = cpu_builder;
                commit(&mut b).map_err(cannot)?
            }
            Err(e) => return Err(cannot(e)),
        };
        let inputs = session.inputs();
        let outputs = session.outputs();
        if inputs.len() != 1 || outputs.is_empty() {
            return Err(Error::format(
                path,
                format!(
                    "a V2CE model has one input and one output; this one has {} and {}",
                    inputs.len(),
                    outputs.len()
                ),
            ));
        }
        let din = dims(inputs[0].dtype());
        if !din
            .as_ref()
            .is_some_and(|d| d.len() == 5 && (d[2] == 2 || d[2] < 0))
        {
            return Err(Error::format(
                path,
                format!(
                    "input {:?} has shape {:?}; a V2CE model takes (batch, pairs, 2, height, width)",
                    inputs[0].name(),
                    din
                ),
            ));
        }
        let dout = dims(outputs[0].dtype());
        let Some([_, _, out_channels, _, _]) = dout.as_deref() else {
            return Err(Error::format(
                path,
                format!(
                    "output has shape {dout:?}; a V2CE model gives (batch, pairs, 2*C, height, width)"
                ),
            ));
        };
        let known = |d: i64| (d > 0).then_some(d as usize);
        let din = din.unwrap_or_default();
        let fixed = [
            known(din[0]),
            known(din[1]),
            known(*out_channels),
            known(din[3]),
            known(din[4]),
        ];
        let metadata = session.metadata().ok();
        let read = |key: &str| {
            metadata
                .as_ref()
                .and_then(|m| m.custom(key))
                .and_then(|v| v.trim().parse::<usize>().ok())
        };
        let field = match (read(RECEPTIVE_MARGIN_KEY), read(ALIGN_KEY)) {
            (Some(margin), Some(align)) if align > 0 => Some(Margin {
                before: margin,
                after: margin,
                align,
            }),
            _ => None,
        };
        drop(metadata);
        Ok(Network {
            field,
            input: inputs[0].name().to_string(),
            session,
            path: path.to_path_buf(),
            provider,
            fixed,
        })
    }

    /// The receptive field the model's metadata states (`v2ce model import` writes it), as a
    /// margin for [`super::roi`]; `None` when it does not.
    pub fn receptive_field(&self) -> Option<Margin> {
        self.field
    }

    /// The execution provider in use (`cpu`, `cuda`).
    pub fn provider(&self) -> &'static str {
        self.provider
    }

    /// The sizes the model fixes, as `(batch, pairs, output channels, height, width)`; `None`
    /// where it takes any (a model made by `v2ce model import` fixes only the channels).
    pub fn fixed_sizes(&self) -> [Option<usize>; 5] {
        self.fixed
    }

    /// Pairs per window when the model fixes them.
    pub fn pairs(&self) -> Option<usize> {
        self.fixed[1]
    }

    /// The model file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Runs one batch: `input` holds `shape = [B, L, 2, H, W]` values; `f` gets the output's
    /// shape and values (row-major) where ONNX Runtime left them, without a copy.
    pub fn run_with<T>(
        &mut self,
        input: &[f32],
        shape: [usize; 5],
        f: impl FnOnce(&[usize], &[f32]) -> Result<T>,
    ) -> Result<T> {
        let expected: usize = shape.iter().product();
        if input.len() != expected || shape[2] != 2 {
            return Err(Error::invalid(
                "network input",
                format!("{} values for shape {shape:?}", input.len()),
            ));
        }
        let tensor = TensorRef::from_array_view((shape, input)).map_err(ort_err("input tensor"))?;
        let outputs = self
            .session
            .run(ort::inputs![self.input.as_str() => tensor])
            .map_err(|e| {
                Error::invalid(
                    "ONNX Runtime",
                    format!("running {} on {shape:?}: {e}", self.path.display()),
                )
            })?;
        let (out_shape, values) = outputs[0]
            .try_extract_tensor::<f32>()
            .map_err(ort_err("output"))?;
        let out_shape: Vec<usize> = out_shape.iter().map(|&d| d.max(0) as usize).collect();
        if out_shape.len() != 5
            || out_shape[0] != shape[0]
            || out_shape[1] != shape[1]
            || out_shape[3] != shape[3]
            || out_shape[4] != shape[4]
            || out_shape.iter().product::<usize>() != values.len()
        {
            return Err(Error::format(
                &self.path,
                format!("output shape {out_shape:?} does not match the input's {shape:?}"),
            ));
        }
        f(&out_shape, values)
    }

    /// [`Network::run_with`], returning a copy of the output's shape and values.
    pub fn run(&mut self, input: &[f32], shape: [usize; 5]) -> Result<(Vec<usize>, Vec<f32>)> {
        self.run_with(input, shape, |s, v| Ok((s.to_vec(), v.to_vec())))
    }
}
