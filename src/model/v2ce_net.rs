//! The V2CE generator (spec §3.1-3.4): ONE description of the network, from which come the
//! state-dict keys and shapes a checkpoint must hold, the check of a loaded state dict, the
//! resolution of spectral norm and BatchNorm into plain convolution weights, and the ONNX graph.
//!
//! The network is a 3D UNet over (batch, 2, pairs, H, W) (time as depth): a head convolution,
//! four encoder residual blocks with stride (1, 2, 2), two bottleneck residual blocks, four decoders
//! (nearest upsampling to the skip's size, concatenation, residual block) and a 1x1x1 prediction
//! convolution followed by ReLU. Every residual block has a projection shortcut (a quirk of the
//! reference code, spec §3.2). The bottleneck and decoder blocks wrap their two 3x3x3 convolutions
//! in spectral norm; the weight used is `weight_bar / sigma`, with sigma resolved once at import
//! (see [`SpectralNorm`]).

use std::collections::{HashMap, HashSet};
use std::path::Path;

use super::onnx::{self, GraphProto, ModelProto, NodeProto, TensorProto};
use super::torch::TensorEntry;
use super::{shape_string, ImportOptions, Tensor, TensorData};
use crate::{Error, Result};

/// BatchNorm's epsilon (PyTorch's default, used by the reference).
pub const BN_EPS: f64 = 1e-5;
/// The epsilon of the reference spectral norm's `n(z) = z / (|z| + eps)`.
pub const SN_EPS: f64 = 1e-12;
pub use super::onnx::{IR_VERSION, OPSET};

/// How a spectral-norm convolution's sigma is resolved from `weight_bar`, `weight_u`, `weight_v`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum SpectralNorm {
    /// What the reference's first forward call after loading does (spec §3.2, Appendix A): from
    /// the stored u, `v = n(Wᵀu)`, `u' = n(W v)`, `sigma = u'ᵀ W v`, in f64.
    PowerIteration,
    /// `sigma = uᵀ W v` with the stored u and v as they are (wrong unless they are converged; kept
    /// to show that the parity test notices).
    Stored,
    /// The true largest singular value of W (slow; also differs from what the reference computes).
    Exact,
}

impl SpectralNorm {
    /// Every mode.
    pub const ALL: [SpectralNorm; 3] = [
        SpectralNorm::PowerIteration,
        SpectralNorm::Stored,
        SpectralNorm::Exact,
    ];

    /// The mode's name (`power-iteration`, `stored`, `exact`).
    pub fn name(self) -> &'static str {
        match self {
            SpectralNorm::PowerIteration => "power-iteration",
            SpectralNorm::Stored => "stored",
            SpectralNorm::Exact => "exact",
        }
    }
}

impl std::fmt::Display for SpectralNorm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for SpectralNorm {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        SpectralNorm::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = SpectralNorm::ALL.iter().map(|m| m.name()).collect();
                Error::invalid(
                    "spectral norm mode",
                    format!("{s:?} (expected one of {})", names.join(", ")),
                )
            })
    }
}

/// A 3D convolution of the network.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Conv {
    /// Its module path, e.g. `UNet.encoders.0.conv1`.
    pub path: String,
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    /// Cubic kernel size (1 or 3); the padding is `kernel / 2`.
    pub kernel: usize,
    /// Stride over (depth = time, height, width).
    pub stride: [usize; 3],
    /// Whether the convolution has a bias.
    pub bias: bool,
    /// Whether it is wrapped in spectral norm (keys `<path>.module.weight_{u,v,bar}`).
    pub spectral_norm: bool,
}

impl Conv {
    /// The weight's shape `[cout, cin, k, k, k]`.
    pub fn weight_shape(&self) -> Vec<usize> {
        vec![self.cout, self.cin, self.kernel, self.kernel, self.kernel]
    }

    /// Inputs per output channel (`cin * k³`), the length of `weight_v`.
    pub fn fan_in(&self) -> usize {
        self.cin * self.kernel.pow(3)
    }
}

/// A residual block (spec §3.2): conv1 → BN → ReLU → conv2 → BN, plus a projection shortcut
/// (1x1x1 conv with bias → BN), added, then ReLU.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ResidualBlock {
    /// Its module path, e.g. `UNet.decoders.0`.
    pub path: String,
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    /// conv1's and the shortcut's stride.
    pub stride: [usize; 3],
    /// Whether conv1 and conv2 are spectral-norm wrapped.
    pub spectral_norm: bool,
}

impl ResidualBlock {
    /// The first 3x3x3 convolution (carries the stride).
    pub fn conv1(&self) -> Conv {
        Conv {
            path: format!("{}.conv1", self.path),
            cin: self.cin,
            cout: self.cout,
            kernel: 3,
            stride: self.stride,
            bias: false,
            spectral_norm: self.spectral_norm,
        }
    }

    /// The second 3x3x3 convolution.
    pub fn conv2(&self) -> Conv {
        Conv {
            path: format!("{}.conv2", self.path),
            cin: self.cout,
            cout: self.cout,
            kernel: 3,
            stride: [1, 1, 1],
            bias: false,
            spectral_norm: self.spectral_norm,
        }
    }

    /// The shortcut's 1x1x1 convolution.
    pub fn shortcut(&self) -> Conv {
        Conv {
            path: format!("{}.downsample.0", self.path),
            cin: self.cin,
            cout: self.cout,
            kernel: 1,
            stride: self.stride,
            bias: true,
            spectral_norm: false,
        }
    }

    /// The three BatchNorms' module paths: after conv1, after conv2, after the shortcut.
    pub fn batch_norms(&self) -> [String; 3] {
        [
            format!("{}.bn1", self.path),
            format!("{}.bn2", self.path),
            format!("{}.downsample.1", self.path),
        ]
    }
}

/// What a state-dict entry is, which decides its role (and the seeded checkpoint's value range).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum KeyKind {
    /// A plain convolution's 5-D weight.
    ConvWeight,
    /// A convolution's bias.
    ConvBias,
    /// A spectral-norm convolution's `weight_u` (length cout).
    SnU,
    /// A spectral-norm convolution's `weight_v` (length cin·k³).
    SnV,
    /// A spectral-norm convolution's raw 5-D weight `weight_bar`.
    SnWeightBar,
    /// BatchNorm γ.
    BnWeight,
    /// BatchNorm β.
    BnBias,
    /// BatchNorm running mean.
    BnMean,
    /// BatchNorm running variance.
    BnVar,
    /// BatchNorm's `num_batches_tracked` (an int64 scalar, unused in eval).
    BnCount,
}

impl KeyKind {
    /// Whether the entry is a trainable parameter (what the 52,791,508 count covers).
    pub fn trainable(self) -> bool {
        matches!(
            self,
            KeyKind::ConvWeight
                | KeyKind::ConvBias
                | KeyKind::SnWeightBar
                | KeyKind::BnWeight
                | KeyKind::BnBias
        )
    }

    /// Whether the entry holds integers (only `num_batches_tracked`).
    pub fn is_int(self) -> bool {
        self == KeyKind::BnCount
    }
}

/// One expected state-dict entry.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct KeySpec {
    /// The key (toolbox format, e.g. `UNet.head.conv3d.weight`).
    pub name: String,
    /// Its shape.
    pub shape: Vec<usize>,
    /// Its role.
    pub kind: KeyKind,
}

/// The ONNX metadata key of the receptive margin in pixels ([`ReceptiveField::margin`]).
pub const RECEPTIVE_MARGIN_KEY: &str = "receptive_margin";
/// The ONNX metadata key of the crop alignment in pixels ([`ReceptiveField::align`]).
pub const ALIGN_KEY: &str = "spatial_align";

/// How far an output pixel of the network can see (see [`Architecture::receptive_field`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReceptiveField {
    /// Input pixels to the left of (or above) an output pixel it can depend on.
    pub before: usize,
    /// Input pixels to the right of (or below) it.
    pub after: usize,
    /// The product of the encoders' strides: where a crop may start.
    pub align: usize,
}

impl ReceptiveField {
    /// The larger side: the margin that covers both.
    pub fn margin(&self) -> usize {
        self.before.max(self.after)
    }
}

/// The network, layer by layer, in PyTorch registration order.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Architecture {
    /// The head convolution (followed by LeakyReLU 0.01).
    pub head: Conv,
    /// The encoders, each producing the next scale; the tensor entering each is a skip.
    pub encoders: Vec<ResidualBlock>,
    /// The bottleneck blocks.
    pub resblocks: Vec<ResidualBlock>,
    /// The decoders, in order (the first takes the deepest skip).
    pub decoders: Vec<ResidualBlock>,
    /// The prediction convolution (followed by ReLU).
    pub pred: Conv,
}

impl Architecture {
    /// The released V2CE generator: head 2→32, encoders 32→64→128→256→512 with stride (1,2,2),
    /// two 512 bottleneck blocks, decoders 768→256, 384→128, 192→64, 96→32, prediction 32→20.
    pub fn v2ce() -> Self {
        Self::unet(2, 20, 32, 4, 2)
    }

    /// A UNet of the same family: `base` channels after the head, doubled by each of `encoders`,
    /// `resblocks` bottleneck blocks, and mirrored decoders.
    pub fn unet(
        inputs: usize,
        outputs: usize,
        base: usize,
        encoders: usize,
        resblocks: usize,
    ) -> Self {
        let head = Conv {
            path: "UNet.head.conv3d".into(),
            cin: inputs,
            cout: base,
            kernel: 3,
            stride: [1, 1, 1],
            bias: true,
            spectral_norm: false,
        };
        let channels = |i: usize| base << i;
        let encoder_blocks = (0..encoders)
            .map(|i| ResidualBlock {
                path: format!("UNet.encoders.{i}"),
                cin: channels(i),
                cout: channels(i + 1),
                stride: [1, 2, 2],
                spectral_norm: false,
            })
            .collect();
        let deepest = channels(encoders);
        let bottleneck = (0..resblocks)
            .map(|i| ResidualBlock {
                path: format!("UNet.resblocks.{i}"),
                cin: deepest,
                cout: deepest,
                stride: [1, 1, 1],
                spectral_norm: true,
            })
            .collect();
        let decoders = (0..encoders)
            .map(|i| {
                let below = channels(encoders - i);
                let skip = channels(encoders - i - 1);
                ResidualBlock {
                    path: format!("UNet.decoders.{i}"),
                    cin: below + skip,
                    cout: skip,
                    stride: [1, 1, 1],
                    spectral_norm: true,
                }
            })
            .collect();
        let pred = Conv {
            path: "UNet.pred.conv3d".into(),
            cin: base,
            cout: outputs,
            kernel: 1,
            stride: [1, 1, 1],
            bias: true,
            spectral_norm: false,
        };
        Architecture {
            head,
            encoders: encoder_blocks,
            resblocks: bottleneck,
            decoders,
            pred,
        }
    }

    /// The member of this family a state dict holds (`(name, shape)` per entry; Lightning's
    /// `model.` prefix allowed): base channels and inputs from the head's weight, outputs from
    /// the prediction's, encoders and bottleneck blocks counted by their indices. `None` when
    /// the head or the prediction weight is missing or not 5-D (the full check then names what
    /// is wrong against [`Architecture::v2ce`]).
    pub fn infer(entries: &[(&str, &[usize])]) -> Option<Self> {
        let find = |key: &str| {
            entries
                .iter()
                .find(|(n, _)| n.strip_prefix("model.").unwrap_or(n) == key)
                .map(|(_, s)| *s)
        };
        let head = find("UNet.head.conv3d.weight")?;
        let pred = find("UNet.pred.conv3d.weight")?;
        if head.len() != 5 || pred.len() != 5 || head[0] == 0 || head[0] != pred[1] {
            return None;
        }
        let count = |group: &str| {
            entries
                .iter()
                .filter_map(|(n, _)| {
                    let n = n.strip_prefix("model.").unwrap_or(n);
                    n.strip_prefix(group)?
                        .split('.')
                        .next()?
                        .parse::<usize>()
                        .ok()
                })
                .max()
                .map_or(0, |i| i + 1)
        };
        let (encoders, resblocks) = (count("UNet.encoders."), count("UNet.resblocks."));
        if encoders == 0 || encoders > 8 || resblocks > 16 {
            return None;
        }
        Some(Self::unet(head[1], pred[0], head[0], encoders, resblocks))
    }

    /// Every residual block, in registration order.
    pub fn blocks(&self) -> impl Iterator<Item = &ResidualBlock> {
        self.encoders
            .iter()
            .chain(&self.resblocks)
            .chain(&self.decoders)
    }

    /// The state dict the network expects, in PyTorch registration order (218 entries for V2CE,
    /// as in spec Appendix A).
    pub fn state_dict_keys(&self) -> Vec<KeySpec> {
        let mut keys = Vec::new();
        conv_keys(&self.head, &mut keys);
        for block in self.blocks() {
            let [bn1, bn2, bn_down] = block.batch_norms();
            conv_keys(&block.conv1(), &mut keys);
            bn_keys(&bn1, block.cout, &mut keys);
            bn_keys(&bn2, block.cout, &mut keys);
            conv_keys(&block.conv2(), &mut keys);
            conv_keys(&block.shortcut(), &mut keys);
            bn_keys(&bn_down, block.cout, &mut keys);
        }
        conv_keys(&self.pred, &mut keys);
        keys
    }

    /// Trainable parameters (conv weights and biases, BatchNorm γ and β): 52,791,508 for V2CE.
    pub fn trainable_parameters(&self) -> u64 {
        self.state_dict_keys()
            .iter()
            .filter(|k| k.kind.trainable())
            .map(|k| k.shape.iter().product::<usize>() as u64)
            .sum()
    }

    /// The spatial receptive field: how many input pixels to the left (or above) and to the
    /// right (or below) an output pixel can depend on, at most over every position, and the
    /// alignment (the product of the encoders' strides) a crop must start at for its scales
    /// to fall on the whole frame's grids.
    ///
    /// So a crop that starts at a multiple of the alignment and extends at least this far
    /// beyond a region on every side (or reaches the frame's edge) computes exactly the whole
    /// frame's outputs in that region (the crop's zero padding stays outside the region's
    /// receptive field; see `stage1::learned::roi`). Worked out by following an output pixel's
    /// span back through every layer: padded convolutions grow it by `kernel / 2` at their
    /// scale, a stride-`s` convolution maps `[a, b]` to `[s*a - k/2, s*b + k/2]`, a decoder's
    /// nearest resize to its skip's size reads `floor(x / s)` (exactly, since every scale is
    /// `ceil` of the one above over `s`), and each skip adds its own path to the input.
    pub fn receptive_field(&self) -> ReceptiveField {
        let scale = |b: &ResidualBlock| b.stride[2] as i64;
        // The input span of tensor s_l (l = 0: the head's output; l >= 1: encoder l's).
        let skip_span = |l: usize, (mut a, mut b): (i64, i64)| {
            for enc in self.encoders[..l].iter().rev() {
                let s = scale(enc);
                (a, b) = (a - 1, b + 1); // conv2, k3 stride 1
                (a, b) = (s * a - 1, s * b + 1); // conv1, k3 stride s
            }
            let h = (self.head.kernel / 2) as i64;
            (a - h, b + h)
        };
        let span_of = |x: i64| {
            let p = (self.pred.kernel / 2) as i64;
            let mut span = (x - p, x + p);
            let mut all = span;
            let levels = self.decoders.len().min(self.encoders.len());
            for l in 0..levels {
                span = (span.0 - 2, span.1 + 2); // the decoder's two k3 convolutions
                let skip = skip_span(l, span);
                all = (all.0.min(skip.0), all.1.max(skip.1));
                let s = scale(&self.encoders[l]);
                span = (span.0.div_euclid(s), span.1.div_euclid(s));
            }
            for _ in &self.resblocks {
                span = (span.0 - 2, span.1 + 2);
            }
            let deepest = skip_span(levels, span);
            (all.0.min(deepest.0), all.1.max(deepest.1))
        };
        let align: i64 = self.encoders.iter().map(scale).product::<i64>().max(1);
        let (mut before, mut after) = (0i64, 0i64);
        // Far from 0 so that every position modulo the alignment is seen twice.
        let origin = 1 << 20;
        for x in origin..origin + 2 * align {
            let (a, b) = span_of(x);
            before = before.max(x - a);
            after = after.max(b - x);
        }
        ReceptiveField {
            before: before as usize,
            after: after as usize,
            align: align as usize,
        }
    }

    /// Checks a checkpoint's entries (names, shapes, dtypes) against the network: strips a
    /// Lightning `model.` prefix, drops `GAN.*` (discriminator) keys, then requires exactly the
    /// expected keys with the expected shapes. The error names the first missing, mis-shaped or
    /// unexpected key. `origin` names the checkpoint in errors.
    pub fn select(&self, origin: &Path, entries: &[TensorEntry]) -> Result<Selection> {
        let listed: Vec<(&str, &[usize], bool)> = entries
            .iter()
            .map(|e| (e.name.as_str(), e.shape.as_slice(), e.dtype.is_float()))
            .collect();
        self.check_keys(origin, &listed)
    }

    /// [`select`](Self::select) for tensors already in memory; returns them by their normalised
    /// key, ready to be a [`WeightSource`].
    pub fn select_tensors(
        &self,
        origin: &Path,
        entries: Vec<(String, Tensor)>,
    ) -> Result<(HashMap<String, Tensor>, Selection)> {
        let listed: Vec<(&str, &[usize], bool)> = entries
            .iter()
            .map(|(n, t)| {
                (
                    n.as_str(),
                    t.shape.as_slice(),
                    matches!(t.data, TensorData::F32(_)),
                )
            })
            .collect();
        let selection = self.check_keys(origin, &listed)?;
        drop(listed);
        let mut map = HashMap::with_capacity(selection.index.len());
        let by_index: HashMap<usize, &str> = selection
            .index
            .iter()
            .map(|(k, &i)| (i, k.as_str()))
            .collect();
        for (i, (_, tensor)) in entries.into_iter().enumerate() {
            if let Some(key) = by_index.get(&i) {
                map.insert(key.to_string(), tensor);
            }
        }
        drop(by_index);
        Ok((map, selection))
    }

    /// The check behind [`select`](Self::select), on `(name, shape, holds floats)` per entry; the
    /// [`Selection`] indexes refer to positions in `entries`.
    pub fn check_keys(
        &self,
        origin: &Path,
        entries: &[(&str, &[usize], bool)],
    ) -> Result<Selection> {
        let mut index: HashMap<String, usize> = HashMap::with_capacity(entries.len());
        let mut order: Vec<(String, usize)> = Vec::with_capacity(entries.len());
        let mut dropped_gan_keys = 0;
        let mut prefix_stripped = false;
        for (i, (name, _, _)) in entries.iter().enumerate() {
            if name.starts_with("GAN.") || name.starts_with("model.GAN.") {
                dropped_gan_keys += 1;
                continue;
            }
            let key = match name.strip_prefix("model.") {
                Some(rest) => {
                    prefix_stripped = true;
                    rest
                }
                None => name,
            };
            if index.insert(key.to_string(), i).is_some() {
                return Err(state_dict_error(
                    origin,
                    key,
                    "appears twice (once with Lightning's model. prefix?)".into(),
                ));
            }
            order.push((key.to_string(), i));
        }
        let expected = self.state_dict_keys();
        let expected_names: HashSet<&str> = expected.iter().map(|k| k.name.as_str()).collect();
        let unexpected: Vec<&str> = order
            .iter()
            .filter(|(k, _)| !expected_names.contains(k.as_str()))
            .map(|(k, _)| k.as_str())
            .collect();
        let mut missing = Vec::new();
        let mut first_problem: Option<(String, String)> = None;
        let mut misfits = 0;
        for spec in &expected {
            match index.get(&spec.name) {
                None => {
                    if first_problem.is_none() {
                        first_problem = Some((
                            spec.name.clone(),
                            format!(
                                "missing (expected a {} tensor of shape {})",
                                if spec.kind.is_int() { "int64" } else { "float" },
                                shape_string(&spec.shape)
                            ),
                        ));
                    }
                    missing.push(spec.name.as_str());
                }
                Some(&i) => {
                    let (_, shape, is_float) = entries[i];
                    let problem = if shape != spec.shape.as_slice() {
                        Some(format!(
                            "shape {} where the network expects {}",
                            shape_string(shape),
                            shape_string(&spec.shape)
                        ))
                    } else if is_float == spec.kind.is_int() {
                        Some(format!(
                            "holds {} where the network expects {}",
                            if is_float { "floats" } else { "integers" },
                            if is_float { "integers" } else { "floats" }
                        ))
                    } else {
                        None
                    };
                    if let Some(p) = problem {
                        misfits += 1;
                        if first_problem.is_none() {
                            first_problem = Some((spec.name.clone(), p));
                        }
                    }
                }
            }
        }
        if first_problem.is_none() {
            if let Some(first) = unexpected.first() {
                first_problem = Some((
                    first.to_string(),
                    "unexpected: the V2CE generator has no such entry".into(),
                ));
            }
        }
        if let Some((key, problem)) = first_problem {
            let mut also = Vec::new();
            if !missing.is_empty() {
                also.push(format!("{} missing", missing.len()));
            }
            if misfits > 0 {
                also.push(format!("{misfits} mis-shaped or mis-typed"));
            }
            if !unexpected.is_empty() {
                also.push(format!(
                    "{} unexpected (the first: {})",
                    unexpected.len(),
                    unexpected[0]
                ));
            }
            return Err(state_dict_error(
                origin,
                &key,
                format!(
                    "{problem} [in all: {}; {} entries read, {} expected]",
                    also.join(", "),
                    entries.len(),
                    expected.len()
                ),
            ));
        }
        Ok(Selection {
            prefix_stripped,
            dropped_gan_keys,
            index,
        })
    }

    /// Builds the ONNX model, reading each weight from `source` as the graph needs it.
    /// `origin` (the checkpoint) names the weights in errors; its file name goes into the
    /// metadata.
    pub fn build_model(
        &self,
        source: &mut dyn WeightSource,
        options: &ImportOptions,
        origin: &Path,
    ) -> Result<BuiltModel> {
        let source_name = origin
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let mut g = GraphBuilder {
            origin,
            source,
            options: *options,
            nodes: Vec::new(),
            initializers: Vec::new(),
            spectral_norms: Vec::new(),
        };
        let x0 = "frames_ncdhw".to_string();
        g.nodes.push(onnx::node(
            "Transpose",
            "input_transpose",
            &["frames"],
            &[&x0],
            vec![onnx::attr_ints("perm", &[0, 2, 1, 3, 4])],
        ));
        let head_out = g.conv(&self.head, None, &x0)?;
        let mut x = format!("{}.out", self.head.path);
        g.nodes.push(onnx::node(
            "LeakyRelu",
            &format!("{}.act", self.head.path),
            &[&head_out],
            &[&x],
            vec![onnx::attr_float("alpha", 0.01)],
        ));
        let mut skips = Vec::with_capacity(self.encoders.len());
        for block in &self.encoders {
            skips.push(x.clone());
            x = g.block(block, &x)?;
        }
        for block in &self.resblocks {
            x = g.block(block, &x)?;
        }
        for (block, skip) in self.decoders.iter().zip(skips.iter().rev()) {
            let p = &block.path;
            let (lead, tail, sizes, up, cat) = (
                format!("{p}.up.lead_dims"),
                format!("{p}.up.skip_hw"),
                format!("{p}.up.sizes"),
                format!("{p}.up"),
                format!("{p}.cat"),
            );
            g.nodes.push(onnx::node(
                "Shape",
                &lead,
                &[&x],
                &[&lead],
                vec![onnx::attr_int("start", 0), onnx::attr_int("end", 3)],
            ));
            g.nodes.push(onnx::node(
                "Shape",
                &tail,
                &[skip],
                &[&tail],
                vec![onnx::attr_int("start", 3), onnx::attr_int("end", 5)],
            ));
            g.nodes.push(onnx::node(
                "Concat",
                &sizes,
                &[&lead, &tail],
                &[&sizes],
                vec![onnx::attr_int("axis", 0)],
            ));
            g.nodes.push(onnx::node(
                "Resize",
                &up,
                &[&x, "", "", &sizes],
                &[&up],
                vec![
                    onnx::attr_string("mode", "nearest"),
                    onnx::attr_string("coordinate_transformation_mode", "asymmetric"),
                    onnx::attr_string("nearest_mode", "floor"),
                ],
            ));
            g.nodes.push(onnx::node(
                "Concat",
                &cat,
                &[&up, skip],
                &[&cat],
                vec![onnx::attr_int("axis", 1)],
            ));
            x = g.block(block, &cat)?;
        }
        let pred_out = g.conv(&self.pred, None, &x)?;
        let relu_out = format!("{}.out", self.pred.path);
        g.nodes.push(onnx::node(
            "Relu",
            &format!("{}.act", self.pred.path),
            &[&pred_out],
            &[&relu_out],
            vec![],
        ));
        g.nodes.push(onnx::node(
            "Transpose",
            "output_transpose",
            &[&relu_out],
            &["voxels"],
            vec![onnx::attr_ints("perm", &[0, 2, 1, 3, 4])],
        ));
        let dims = |channels: usize| {
            [
                Err("batch"),
                Err("pairs"),
                Ok(channels as i64),
                Err("height"),
                Err("width"),
            ]
        };
        let graph = GraphProto {
            node: g.nodes,
            name: Some("v2ce".into()),
            initializer: g.initializers,
            input: vec![onnx::tensor_value(
                "frames",
                onnx::FLOAT,
                &dims(self.head.cin),
            )],
            output: vec![onnx::tensor_value(
                "voxels",
                onnx::FLOAT,
                &dims(self.pred.cout),
            )],
            doc_string: Some(
                "V2CE Stage 1: frame pairs (batch, pairs, 2, height, width), normalised as \
                 (x/255 - 0.153)/0.165, to event voxels (batch, pairs, 20, height, width), \
                 channel = p*10 + c with ON first"
                    .into(),
            ),
            value_info: Vec::new(),
        };
        let batch_norm = if options.fold_batch_norm {
            "folded"
        } else {
            "kept"
        };
        let field = self.receptive_field();
        let metadata = vec![
            onnx::metadata("producer", "v2ce"),
            onnx::metadata("architecture", "v2ce-3d-unet"),
            onnx::metadata("source", &source_name),
            onnx::metadata("spectral_norm", options.spectral_norm.name()),
            onnx::metadata("batch_norm", batch_norm),
            onnx::metadata("parameters", &self.trainable_parameters().to_string()),
            onnx::metadata("input_mean", "0.153"),
            onnx::metadata("input_std", "0.165"),
            onnx::metadata("time_bins", &(self.pred.cout / 2).to_string()),
            onnx::metadata(RECEPTIVE_MARGIN_KEY, &field.margin().to_string()),
            onnx::metadata(ALIGN_KEY, &field.align.to_string()),
        ];
        let model = onnx::model(graph, "v2ce", metadata);
        Ok(BuiltModel {
            model,
            spectral_norms: g.spectral_norms,
        })
    }
}

fn conv_keys(conv: &Conv, keys: &mut Vec<KeySpec>) {
    if conv.spectral_norm {
        let m = format!("{}.module", conv.path);
        keys.push(KeySpec {
            name: format!("{m}.weight_u"),
            shape: vec![conv.cout],
            kind: KeyKind::SnU,
        });
        keys.push(KeySpec {
            name: format!("{m}.weight_v"),
            shape: vec![conv.fan_in()],
            kind: KeyKind::SnV,
        });
        keys.push(KeySpec {
            name: format!("{m}.weight_bar"),
            shape: conv.weight_shape(),
            kind: KeyKind::SnWeightBar,
        });
    } else {
        keys.push(KeySpec {
            name: format!("{}.weight", conv.path),
            shape: conv.weight_shape(),
            kind: KeyKind::ConvWeight,
        });
    }
    if conv.bias {
        keys.push(KeySpec {
            name: format!("{}.bias", conv.path),
            shape: vec![conv.cout],
            kind: KeyKind::ConvBias,
        });
    }
}

fn bn_keys(path: &str, channels: usize, keys: &mut Vec<KeySpec>) {
    for (suffix, kind) in [
        ("weight", KeyKind::BnWeight),
        ("bias", KeyKind::BnBias),
        ("running_mean", KeyKind::BnMean),
        ("running_var", KeyKind::BnVar),
    ] {
        keys.push(KeySpec {
            name: format!("{path}.{suffix}"),
            shape: vec![channels],
            kind,
        });
    }
    keys.push(KeySpec {
        name: format!("{path}.num_batches_tracked"),
        shape: vec![],
        kind: KeyKind::BnCount,
    });
}

fn state_dict_error(origin: &Path, key: &str, message: String) -> Error {
    Error::StateDict {
        path: origin.to_path_buf(),
        key: key.to_string(),
        message,
    }
}

/// The outcome of [`Architecture::select`]: where each expected key is, and what was dropped.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Selection {
    /// Whether keys carried Lightning's `model.` prefix.
    pub prefix_stripped: bool,
    /// How many `GAN.*` keys were dropped.
    pub dropped_gan_keys: usize,
    index: HashMap<String, usize>,
}

impl Selection {
    /// The position (in the checked entry list) of the entry with normalised key `key`.
    pub fn index_of(&self, key: &str) -> Option<usize> {
        self.index.get(key).copied()
    }
}

/// Where the graph builder gets each weight, by normalised key; each key is taken once.
pub trait WeightSource {
    /// The tensor stored under `key` (its shape was checked by [`Architecture::select`]).
    fn take(&mut self, key: &str) -> Result<Tensor>;
}

impl WeightSource for HashMap<String, Tensor> {
    fn take(&mut self, key: &str) -> Result<Tensor> {
        self.remove(key)
            .ok_or_else(|| Error::invalid("state dict", format!("no tensor {key}")))
    }
}

/// A built model and the sigma of each spectral-norm convolution.
#[derive(Clone, Debug, PartialEq)]
pub struct BuiltModel {
    /// The ONNX model.
    pub model: ModelProto,
    /// `(module path, sigma)` per spectral-norm convolution.
    pub spectral_norms: Vec<(String, f64)>,
}

struct GraphBuilder<'a> {
    origin: &'a Path,
    source: &'a mut dyn WeightSource,
    options: ImportOptions,
    nodes: Vec<NodeProto>,
    initializers: Vec<TensorProto>,
    spectral_norms: Vec<(String, f64)>,
}

impl GraphBuilder<'_> {
    /// The floats stored under `key`, which must number `len` and be finite.
    fn take_floats(&mut self, key: &str, len: usize) -> Result<Vec<f32>> {
        let fail = |message: String| state_dict_error(self.origin, key, message);
        let values = match self.source.take(key)?.data {
            TensorData::F32(v) => v,
            TensorData::I64(_) => {
                return Err(fail("holds integers where floats are expected".into()));
            }
        };
        if values.len() != len {
            return Err(fail(format!(
                "holds {} values where {len} are expected",
                values.len()
            )));
        }
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(fail(format!(
                "holds a non-finite value ({}) at element {i}",
                values[i]
            )));
        }
        Ok(values)
    }

    /// Adds a Conv node (and, unless folded, the BatchNormalization `bn` after it); returns the
    /// output's name.
    fn conv(&mut self, conv: &Conv, bn: Option<&str>, input: &str) -> Result<String> {
        let rows = conv.cout;
        let cols = conv.fan_in();
        let (mut weight, sigma) = if conv.spectral_norm {
            let m = format!("{}.module", conv.path);
            let bar = self.take_floats(&format!("{m}.weight_bar"), rows * cols)?;
            let u = self.take_floats(&format!("{m}.weight_u"), rows)?;
            let v = self.take_floats(&format!("{m}.weight_v"), cols)?;
            let sigma = spectral_sigma(self.options.spectral_norm, &bar, rows, cols, &u, &v);
            // Only the Stored mode can give a negative sigma (random u, v); it is used as it
            // is, like the formula says, to show how wrong that resolution is.
            if !sigma.is_finite() || sigma == 0.0 {
                return Err(state_dict_error(
                    self.origin,
                    &format!("{m}.weight_bar"),
                    format!("spectral norm sigma is {sigma}, cannot divide by it"),
                ));
            }
            self.spectral_norms.push((conv.path.clone(), sigma));
            (bar, sigma)
        } else {
            (
                self.take_floats(&format!("{}.weight", conv.path), rows * cols)?,
                1.0,
            )
        };
        let bias: Option<Vec<f32>> = if conv.bias {
            Some(self.take_floats(&format!("{}.bias", conv.path), rows)?)
        } else {
            None
        };
        let fold = bn.filter(|_| self.options.fold_batch_norm);
        let weight_name = format!("{}.weight", conv.path);
        let bias_name = format!("{}.bias", conv.path);
        let has_bias;
        if let Some(bn) = fold {
            let gamma = self.take_floats(&format!("{bn}.weight"), rows)?;
            let beta = self.take_floats(&format!("{bn}.bias"), rows)?;
            let mean = self.take_floats(&format!("{bn}.running_mean"), rows)?;
            let var = self.take_floats(&format!("{bn}.running_var"), rows)?;
            let mut folded_bias = Vec::with_capacity(rows);
            for o in 0..rows {
                let b = bias.as_ref().map_or(0.0, |b| f64::from(b[o]));
                let (scale, shift) = fold_batch_norm(b, gamma[o], beta[o], mean[o], var[o])
                    .ok_or_else(|| {
                        state_dict_error(
                            self.origin,
                            &format!("{bn}.running_var"),
                            format!("element {o} is {}, not above -eps", var[o]),
                        )
                    })?;
                let factor = scale / sigma;
                for w in &mut weight[o * cols..(o + 1) * cols] {
                    *w = (f64::from(*w) * factor) as f32;
                }
                folded_bias.push(shift as f32);
            }
            self.initializers.push(onnx::initializer_f32(
                &weight_name,
                &conv.weight_shape(),
                &weight,
            ));
            drop(weight);
            self.initializers
                .push(onnx::initializer_f32(&bias_name, &[rows], &folded_bias));
            has_bias = true;
        } else {
            if conv.spectral_norm {
                for w in &mut weight {
                    *w = (f64::from(*w) / sigma) as f32;
                }
            }
            self.initializers.push(onnx::initializer_f32(
                &weight_name,
                &conv.weight_shape(),
                &weight,
            ));
            drop(weight);
            if let Some(b) = &bias {
                self.initializers
                    .push(onnx::initializer_f32(&bias_name, &[rows], b));
            }
            has_bias = bias.is_some();
        }
        let k = conv.kernel as i64;
        let p = (conv.kernel / 2) as i64;
        let s = conv.stride.map(|x| x as i64);
        let out = format!("{}.conv", conv.path);
        let mut inputs = vec![input, weight_name.as_str()];
        if has_bias {
            inputs.push(&bias_name);
        }
        self.nodes.push(onnx::node(
            "Conv",
            &conv.path,
            &inputs,
            &[&out],
            vec![
                onnx::attr_ints("kernel_shape", &[k, k, k]),
                onnx::attr_ints("pads", &[p, p, p, p, p, p]),
                onnx::attr_ints("strides", &s),
                onnx::attr_ints("dilations", &[1, 1, 1]),
                onnx::attr_int("group", 1),
            ],
        ));
        match bn {
            Some(bn) if fold.is_none() => {
                let names =
                    ["weight", "bias", "running_mean", "running_var"].map(|s| format!("{bn}.{s}"));
                for name in &names {
                    let values = self.take_floats(name, rows)?;
                    self.initializers
                        .push(onnx::initializer_f32(name, &[rows], &values));
                }
                let bn_out = format!("{bn}.out");
                self.nodes.push(onnx::node(
                    "BatchNormalization",
                    bn,
                    &[&out, &names[0], &names[1], &names[2], &names[3]],
                    &[&bn_out],
                    vec![onnx::attr_float("epsilon", BN_EPS as f32)],
                ));
                Ok(bn_out)
            }
            _ => Ok(out),
        }
    }

    /// Adds a residual block; returns its output's name.
    fn block(&mut self, block: &ResidualBlock, input: &str) -> Result<String> {
        let [bn1, bn2, bn_down] = block.batch_norms();
        let p = &block.path;
        let c1 = self.conv(&block.conv1(), Some(&bn1), input)?;
        let r1 = format!("{p}.relu1");
        self.nodes
            .push(onnx::node("Relu", &r1, &[&c1], &[&r1], vec![]));
        let c2 = self.conv(&block.conv2(), Some(&bn2), &r1)?;
        let d = self.conv(&block.shortcut(), Some(&bn_down), input)?;
        let sum = format!("{p}.add");
        self.nodes
            .push(onnx::node("Add", &sum, &[&c2, &d], &[&sum], vec![]));
        let out = format!("{p}.out");
        self.nodes
            .push(onnx::node("Relu", &out, &[&sum], &[&out], vec![]));
        Ok(out)
    }
}

/// BatchNorm (eval) folded into the preceding convolution, in f64: returns `(scale, shift)` with
/// `scale = γ/√(var+ε)` multiplying the weights of the output channel and `shift = (b − mean)·scale
/// + β` its new bias (`b` the convolution's bias, 0 without one). `None` when `var + ε ≤ 0`.
pub fn fold_batch_norm(b: f64, gamma: f32, beta: f32, mean: f32, var: f32) -> Option<(f64, f64)> {
    let denom = f64::from(var) + BN_EPS;
    if denom.is_nan() || denom <= 0.0 {
        return None;
    }
    let scale = f64::from(gamma) / denom.sqrt();
    Some((scale, (b - f64::from(mean)) * scale + f64::from(beta)))
}

/// The sigma a spectral-norm convolution divides `weight_bar` by, viewed as a `rows x cols`
/// row-major matrix W, with the stored `u` (length rows) and `v` (length cols). Computed in f64.
///
/// # Panics
///
/// When `w` holds fewer than `rows * cols` values or `u`, `v` are shorter than stated.
pub fn spectral_sigma(
    mode: SpectralNorm,
    w: &[f32],
    rows: usize,
    cols: usize,
    u: &[f32],
    v: &[f32],
) -> f64 {
    match mode {
        SpectralNorm::PowerIteration => {
            // v = n(Wᵀu)
            let mut wtu = vec![0f64; cols];
            for (r, &ur) in u.iter().enumerate().take(rows) {
                let ur = f64::from(ur);
                for (acc, &x) in wtu.iter_mut().zip(&w[r * cols..(r + 1) * cols]) {
                    *acc += f64::from(x) * ur;
                }
            }
            let norm = wtu.iter().map(|x| x * x).sum::<f64>().sqrt();
            wtu.iter_mut().for_each(|x| *x /= norm + SN_EPS);
            // u' = n(W v); sigma = u'ᵀ W v = |Wv|² / (|Wv| + eps)
            let wv = mat_vec(w, rows, cols, &wtu);
            let norm_sq: f64 = wv.iter().map(|x| x * x).sum();
            norm_sq / (norm_sq.sqrt() + SN_EPS)
        }
        SpectralNorm::Stored => {
            let v64: Vec<f64> = v.iter().map(|&x| f64::from(x)).collect();
            mat_vec(w, rows, cols, &v64)
                .iter()
                .zip(u)
                .map(|(a, &b)| a * f64::from(b))
                .sum()
        }
        SpectralNorm::Exact => largest_singular_value(w, rows, cols),
    }
}

fn mat_vec(w: &[f32], rows: usize, cols: usize, v: &[f64]) -> Vec<f64> {
    (0..rows)
        .map(|r| {
            w[r * cols..(r + 1) * cols]
                .iter()
                .zip(v)
                .map(|(&a, b)| f64::from(a) * b)
                .sum()
        })
        .collect()
}

/// The largest singular value of a `rows x cols` matrix, in f64: the Gram matrix of the smaller
/// side, raised to the power 2^14 by repeated squaring (so the top eigenvector dominates even when
/// the spectrum's gap is small), then a Rayleigh quotient refined by a few power steps.
///
/// # Panics
///
/// When `w` holds fewer than `rows * cols` values.
pub fn largest_singular_value(w: &[f32], rows: usize, cols: usize) -> f64 {
    let n = rows.min(cols);
    if n == 0 {
        return 0.0;
    }
    let mut gram = vec![0f64; n * n];
    if rows <= cols {
        let w64: Vec<f64> = w.iter().map(|&x| f64::from(x)).collect();
        for i in 0..n {
            let ri = &w64[i * cols..(i + 1) * cols];
            for j in i..n {
                let rj = &w64[j * cols..(j + 1) * cols];
                let d: f64 = ri.iter().zip(rj).map(|(a, b)| a * b).sum();
                gram[i * n + j] = d;
                gram[j * n + i] = d;
            }
        }
    } else {
        for r in 0..rows {
            let row = &w[r * cols..(r + 1) * cols];
            for i in 0..n {
                let a = f64::from(row[i]);
                for j in i..n {
                    gram[i * n + j] += a * f64::from(row[j]);
                }
            }
        }
        for i in 0..n {
            for j in 0..i {
                gram[i * n + j] = gram[j * n + i];
            }
        }
    }
    let trace = |m: &[f64]| (0..n).map(|i| m[i * n + i]).sum::<f64>();
    let mut m = gram.clone();
    let mut tmp = vec![0f64; n * n];
    for _ in 0..14 {
        let t = trace(&m);
        if !(t.is_finite() && t > 0.0) {
            return 0.0;
        }
        m.iter_mut().for_each(|x| *x /= t);
        tmp.iter_mut().for_each(|x| *x = 0.0);
        for i in 0..n {
            for k in 0..n {
                let a = m[i * n + k];
                if a == 0.0 {
                    continue;
                }
                let (row_k, out_i) = (&m[k * n..(k + 1) * n], &mut tmp[i * n..(i + 1) * n]);
                for (o, &b) in out_i.iter_mut().zip(row_k) {
                    *o += a * b;
                }
            }
        }
        std::mem::swap(&mut m, &mut tmp);
    }
    // The column with the largest diagonal entry is (nearly) the top eigenvector.
    let j = (0..n)
        .max_by(|&a, &b| m[a * n + a].total_cmp(&m[b * n + b]))
        .unwrap_or(0);
    let mut x: Vec<f64> = (0..n).map(|i| m[i * n + j]).collect();
    let mut lambda = 0.0;
    for _ in 0..8 {
        let norm = x.iter().map(|a| a * a).sum::<f64>().sqrt();
        if norm == 0.0 {
            return 0.0;
        }
        x.iter_mut().for_each(|a| *a /= norm);
        let gx: Vec<f64> = (0..n)
            .map(|i| {
                gram[i * n..(i + 1) * n]
                    .iter()
                    .zip(&x)
                    .map(|(a, b)| a * b)
                    .sum()
            })
            .collect();
        lambda = x.iter().zip(&gx).map(|(a, b)| a * b).sum::<f64>();
        x = gx;
    }
    lambda.max(0.0).sqrt()
}

#[cfg(test)]
mod tests {

    /// The family member is read back off its own state dict, with or without Lightning's
    /// prefix; a dict without a head is not guessed at.
    #[test]
    fn the_architecture_is_inferred_from_a_state_dict() {
        for arch in [
            Architecture::v2ce(),
            Architecture::unet(2, 20, 8, 4, 2),
            Architecture::unet(2, 20, 16, 3, 1),
        ] {
            let keys = arch.state_dict_keys();
            let listed: Vec<(&str, &[usize])> = keys
                .iter()
                .map(|k| (k.name.as_str(), k.shape.as_slice()))
                .collect();
            assert_eq!(Architecture::infer(&listed), Some(arch.clone()));
            let prefixed: Vec<(String, Vec<usize>)> = keys
                .iter()
                .map(|k| (format!("model.{}", k.name), k.shape.clone()))
                .collect();
            let listed: Vec<(&str, &[usize])> = prefixed
                .iter()
                .map(|(n, s)| (n.as_str(), s.as_slice()))
                .collect();
            assert_eq!(Architecture::infer(&listed), Some(arch));
        }
        assert_eq!(
            Architecture::infer(&[("UNet.pred.conv3d.weight", &[20, 32, 1, 1, 1])]),
            None
        );
    }

    use super::*;

    /// The receptive field against the sum worked out by hand for a symmetric chain (head 1,
    /// encoder i adds 2^(i-1) + 2^i, each bottleneck block 2 * 2^e, decoder i 2 * 2^(i-1): 140
    /// pixels for V2CE), which the nearest resizes can only widen, by less than one deepest-scale
    /// pixel per side.
    #[test]
    fn the_receptive_field_of_the_unet() {
        for (e, r) in [(4usize, 2usize), (3, 1), (5, 2), (1, 0)] {
            let f = Architecture::unet(2, 20, 8, e, r).receptive_field();
            let deep = 1usize << e;
            let chain = 1 + 5 * (deep - 1) + 2 * r * deep;
            eprintln!("e {e} r {r}: {f:?}, chain {chain}");
            assert_eq!(f.align, deep);
            for side in [f.before, f.after] {
                assert!(side >= chain && side < chain + deep, "{f:?} vs {chain}");
            }
        }
        let v2ce = Architecture::v2ce().receptive_field();
        assert_eq!(v2ce, Architecture::unet(2, 20, 4, 4, 2).receptive_field());
    }

    #[test]
    fn the_key_list_matches_appendix_a() {
        let arch = Architecture::v2ce();
        let keys = arch.state_dict_keys();
        assert_eq!(keys.len(), 218);
        let find = |name: &str| {
            keys.iter()
                .find(|k| k.name == name)
                .map(|k| k.shape.clone())
                .unwrap_or_else(|| panic!("{name} missing"))
        };
        assert_eq!(keys[0].name, "UNet.head.conv3d.weight");
        assert_eq!(keys[0].shape, vec![32, 2, 3, 3, 3]);
        assert_eq!(keys[7].name, "UNet.encoders.0.bn1.num_batches_tracked");
        assert_eq!(keys[13].name, "UNet.encoders.0.conv2.weight");
        assert_eq!(keys[217].name, "UNet.pred.conv3d.bias");
        assert_eq!(
            find("UNet.encoders.3.conv1.weight"),
            vec![512, 256, 3, 3, 3]
        );
        assert_eq!(find("UNet.resblocks.0.conv1.module.weight_v"), vec![13824]);
        assert_eq!(
            find("UNet.resblocks.1.downsample.0.weight"),
            vec![512, 512, 1, 1, 1]
        );
        assert_eq!(
            find("UNet.decoders.0.conv1.module.weight_bar"),
            vec![256, 768, 3, 3, 3]
        );
        assert_eq!(find("UNet.decoders.0.conv1.module.weight_v"), vec![20736]);
        assert_eq!(find("UNet.decoders.3.conv2.module.weight_v"), vec![864]);
        assert_eq!(
            find("UNet.decoders.3.downsample.0.weight"),
            vec![32, 96, 1, 1, 1]
        );
        assert_eq!(find("UNet.pred.conv3d.weight"), vec![20, 32, 1, 1, 1]);
        assert_eq!(
            find("UNet.decoders.2.bn2.num_batches_tracked"),
            Vec::<usize>::new()
        );
        // Per spec §3.4: head 2, each encoder 19, each SN block 23, pred 2.
        let in_block = |p: &str| keys.iter().filter(|k| k.name.starts_with(p)).count();
        assert_eq!(in_block("UNet.head."), 2);
        assert_eq!(in_block("UNet.encoders.1."), 19);
        assert_eq!(in_block("UNet.resblocks.1."), 23);
        assert_eq!(in_block("UNet.decoders.1."), 23);
    }

    #[test]
    fn parameter_counts_match_the_spec() {
        let arch = Architecture::v2ce();
        assert_eq!(arch.trainable_parameters(), 52_791_508);
        // With the spectral-norm u and v vectors, as model.parameters() counts (spec §3.5).
        let with_uv: u64 = arch
            .state_dict_keys()
            .iter()
            .filter(|k| k.kind.trainable() || matches!(k.kind, KeyKind::SnU | KeyKind::SnV))
            .map(|k| k.shape.iter().product::<usize>() as u64)
            .sum();
        assert_eq!(with_uv, 52_901_652);
    }

    #[test]
    fn power_iteration_sigma_by_hand() {
        // W = diag(3, 2, 1), u = (1, 1, 1): v = n(3, 2, 1), W v = (9, 4, 1)/√14,
        // sigma = |W v| = √(98/14) = √7 (less the epsilons).
        let w = [3.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0];
        let s = spectral_sigma(
            SpectralNorm::PowerIteration,
            &w,
            3,
            3,
            &[1.0, 1.0, 1.0],
            &[0.0; 3],
        );
        assert!((s - 7f64.sqrt()).abs() < 1e-9, "{s}");
        // Stored: uᵀ W v with u = (1, 0, 0), v = (0.5, 1, 1) gives 1.5.
        let s = spectral_sigma(
            SpectralNorm::Stored,
            &w,
            3,
            3,
            &[1.0, 0.0, 0.0],
            &[0.5, 1.0, 1.0],
        );
        assert!((s - 1.5).abs() < 1e-12, "{s}");
        // Exact: the largest singular value, 3.
        let s = spectral_sigma(SpectralNorm::Exact, &w, 3, 3, &[1.0; 3], &[1.0; 3]);
        assert!((s - 3.0).abs() < 1e-9, "{s}");
    }

    #[test]
    fn exact_sigma_of_a_wide_and_a_tall_matrix() {
        // [[1, 1, 0], [0, 0, 2]] has singular values 2 and √2; the transpose has the same.
        let wide = [1.0, 1.0, 0.0, 0.0, 0.0, 2.0];
        let tall = [1.0, 0.0, 1.0, 0.0, 0.0, 2.0];
        assert!((largest_singular_value(&wide, 2, 3) - 2.0).abs() < 1e-9);
        assert!((largest_singular_value(&tall, 3, 2) - 2.0).abs() < 1e-9);
        // A close gap (1 and 0.999) still converges to the larger.
        let near = [1.0, 0.0, 0.0, 0.999];
        assert!((largest_singular_value(&near, 2, 2) - 1.0).abs() < 1e-9);
    }

    #[test]
    fn batch_norm_folding_by_hand() {
        // γ = 3, var = 4 - eps: scale 1.5; b = 1, mean = 0.25, β = 0.5: shift 0.75*1.5 + 0.5.
        let (scale, shift) = fold_batch_norm(1.0, 3.0, 0.5, 0.25, (4.0 - BN_EPS) as f32).unwrap();
        assert!((scale - 1.5).abs() < 1e-7, "{scale}");
        assert!((shift - 1.625).abs() < 1e-7, "{shift}");
        assert!(fold_batch_norm(0.0, 1.0, 0.0, 0.0, -1.0).is_none());
    }

    #[test]
    fn spectral_norm_names_round_trip() {
        for mode in SpectralNorm::ALL {
            assert_eq!(mode.name().parse::<SpectralNorm>().unwrap(), mode);
        }
        assert!("power".parse::<SpectralNorm>().is_err());
    }
}
