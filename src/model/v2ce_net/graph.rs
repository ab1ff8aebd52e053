//! The ONNX graph of the network: built node by node, each weight read from a [`WeightSource`]
//! as it is needed and resolved (spectral norm, BatchNorm folding) on the way.

use std::collections::HashMap;
use std::path::Path;

use super::architecture::Architecture;
use super::keys::state_dict_error;
use super::layers::{Conv, ResidualBlock};
use super::norms::{fold_batch_norm, spectral_sigma, BN_EPS};
use crate::model::onnx::{
    self, GraphProto, ModelProto, NodeProto, StringStringEntryProto, TensorProto,
};
use crate::model::{ImportOptions, Tensor, TensorData};
use crate::{Error, Result};

/// The ONNX metadata key of the receptive margin in pixels
/// ([`ReceptiveField::margin`](super::ReceptiveField::margin)).
pub const RECEPTIVE_MARGIN_KEY: &str = "receptive_margin";
/// The ONNX metadata key of the crop alignment in pixels
/// ([`ReceptiveField::align`](super::ReceptiveField::align)).
pub const ALIGN_KEY: &str = "spatial_align";

/// The initializer `[0, -1]` that folds `(B, C, L, H, W)` to `(B, C*L, H, W)` with `H, W`.
const FOLD_LEAD: &str = "fold_lead";

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

impl Architecture {
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
        let mut x = g.input_and_head(&self.head)?;
        let mut skips = Vec::with_capacity(self.encoders.len());
        for block in &self.encoders {
            skips.push(x.clone());
            x = g.block(block, &x)?;
        }
        for block in &self.resblocks {
            x = g.block(block, &x)?;
        }
        for (block, skip) in self.decoders.iter().zip(skips.iter().rev()) {
            let cat = g.upsample_and_concat(&block.path, &x, skip);
            x = g.block(block, &cat)?;
        }
        g.prediction_and_output(&self.pred, &x)?;
        let GraphBuilder {
            nodes,
            mut initializers,
            spectral_norms,
            ..
        } = g;
        if !self.decoders.is_empty() {
            // After the weights, where a rewritten older import has it too.
            add_fold_lead(&mut initializers);
        }
        let graph = self.graph(nodes, initializers);
        let model = onnx::model(graph, "v2ce", self.metadata(&source_name, options));
        Ok(BuiltModel {
            model,
            spectral_norms,
        })
    }

    /// The graph of `nodes` and `initializers`, with its input `frames` and output `voxels`.
    fn graph(&self, nodes: Vec<NodeProto>, initializers: Vec<TensorProto>) -> GraphProto {
        let dims = |channels: usize| {
            [
                Err("batch"),
                Err("pairs"),
                Ok(channels as i64),
                Err("height"),
                Err("width"),
            ]
        };
        GraphProto {
            node: nodes,
            name: Some("v2ce".into()),
            initializer: initializers,
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
        }
    }

    /// The model's metadata: provenance, the import options, the input normalisation, and the
    /// receptive field the learned runtime crops by.
    fn metadata(&self, source_name: &str, options: &ImportOptions) -> Vec<StringStringEntryProto> {
        let batch_norm = if options.fold_batch_norm {
            "folded"
        } else {
            "kept"
        };
        let field = self.receptive_field();
        vec![
            onnx::metadata("producer", "v2ce"),
            onnx::metadata("architecture", "v2ce-3d-unet"),
            onnx::metadata("source", source_name),
            onnx::metadata("spectral_norm", options.spectral_norm.name()),
            onnx::metadata("batch_norm", batch_norm),
            onnx::metadata("parameters", &self.trainable_parameters().to_string()),
            onnx::metadata("input_mean", "0.153"),
            onnx::metadata("input_std", "0.165"),
            onnx::metadata("time_bins", &(self.pred.cout / 2).to_string()),
            onnx::metadata(RECEPTIVE_MARGIN_KEY, &field.margin().to_string()),
            onnx::metadata(ALIGN_KEY, &field.align.to_string()),
        ]
    }
}

/// The graph under construction: nodes and initializers in the order they are added.
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

    /// Adds the transpose of the input `frames` to (batch, 2, pairs, H, W), the head convolution
    /// and its LeakyReLU; returns the output's name.
    fn input_and_head(&mut self, head: &Conv) -> Result<String> {
        let x0 = "frames_ncdhw".to_string();
        self.nodes.push(onnx::node(
            "Transpose",
            "input_transpose",
            &["frames"],
            &[&x0],
            vec![onnx::attr_ints("perm", &[0, 2, 1, 3, 4])],
        ));
        let head_out = self.conv(head, None, &x0)?;
        let x = format!("{}.out", head.path);
        self.nodes.push(onnx::node(
            "LeakyRelu",
            &format!("{}.act", head.path),
            &[&head_out],
            &[&x],
            vec![onnx::attr_float("alpha", 0.01)],
        ));
        Ok(x)
    }

    /// Adds the prediction convolution, its ReLU and the transpose back to the output `voxels`
    /// (batch, pairs, channels, H, W).
    fn prediction_and_output(&mut self, pred: &Conv, input: &str) -> Result<()> {
        let pred_out = self.conv(pred, None, input)?;
        let relu_out = format!("{}.out", pred.path);
        self.nodes.push(onnx::node(
            "Relu",
            &format!("{}.act", pred.path),
            &[&pred_out],
            &[&relu_out],
            vec![],
        ));
        self.nodes.push(onnx::node(
            "Transpose",
            "output_transpose",
            &[&relu_out],
            &["voxels"],
            vec![onnx::attr_ints("perm", &[0, 2, 1, 3, 4])],
        ));
        Ok(())
    }

    /// Adds a decoder's input: `x` resized (nearest) to the spatial size of `skip` (see
    /// [`upsample_nodes`]), then concatenated with it along the channels; returns the
    /// concatenation's name. `p` is the decoder's module path.
    fn upsample_and_concat(&mut self, p: &str, x: &str, skip: &str) -> String {
        let (up, cat) = (format!("{p}.up"), format!("{p}.cat"));
        self.nodes.extend(upsample_nodes(p, x, skip));
        self.nodes.push(onnx::node(
            "Concat",
            &cat,
            &[&up, skip],
            &[&cat],
            vec![onnx::attr_int("axis", 1)],
        ));
        cat
    }

    /// Adds a Conv node (and, unless folded, the BatchNormalization `bn` after it); returns the
    /// output's name.
    fn conv(&mut self, conv: &Conv, bn: Option<&str>, input: &str) -> Result<String> {
        let rows = conv.cout;
        let (mut weight, sigma) = self.conv_weight(conv)?;
        let bias: Option<Vec<f32>> = if conv.bias {
            Some(self.take_floats(&format!("{}.bias", conv.path), rows)?)
        } else {
            None
        };
        let fold = bn.filter(|_| self.options.fold_batch_norm);
        let bias = match fold {
            Some(bn) => {
                Some(self.fold_batch_norm_into(bn, conv, &mut weight, sigma, bias.as_deref())?)
            }
            None => {
                if conv.spectral_norm {
                    for w in &mut weight {
                        *w = (f64::from(*w) / sigma) as f32;
                    }
                }
                bias
            }
        };
        let weight_name = format!("{}.weight", conv.path);
        let bias_name = format!("{}.bias", conv.path);
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
        let bias_input = bias.as_ref().map(|_| bias_name.as_str());
        let out = self.conv_node(conv, input, &weight_name, bias_input);
        match bn {
            Some(bn) if fold.is_none() => self.batch_norm_node(bn, rows, &out),
            _ => Ok(out),
        }
    }

    /// The convolution's weight (`cout` rows of `fan_in`), and the sigma it is still to be
    /// divided by: a spectral-norm convolution's `weight_bar` and its resolved sigma (recorded in
    /// `spectral_norms`), or a plain weight and 1.
    fn conv_weight(&mut self, conv: &Conv) -> Result<(Vec<f32>, f64)> {
        let rows = conv.cout;
        let cols = conv.fan_in();
        if !conv.spectral_norm {
            let weight = self.take_floats(&format!("{}.weight", conv.path), rows * cols)?;
            return Ok((weight, 1.0));
        }
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
        Ok((bar, sigma))
    }

    /// Folds the BatchNorm `bn` into the convolution: scales each output channel's `weight` by
    /// the BatchNorm's scale over `sigma`, and returns the new bias (from `bias`, if any).
    fn fold_batch_norm_into(
        &mut self,
        bn: &str,
        conv: &Conv,
        weight: &mut [f32],
        sigma: f64,
        bias: Option<&[f32]>,
    ) -> Result<Vec<f32>> {
        let rows = conv.cout;
        let cols = conv.fan_in();
        let gamma = self.take_floats(&format!("{bn}.weight"), rows)?;
        let beta = self.take_floats(&format!("{bn}.bias"), rows)?;
        let mean = self.take_floats(&format!("{bn}.running_mean"), rows)?;
        let var = self.take_floats(&format!("{bn}.running_var"), rows)?;
        let mut folded_bias = Vec::with_capacity(rows);
        for o in 0..rows {
            let b = bias.map_or(0.0, |b| f64::from(b[o]));
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
        Ok(folded_bias)
    }

    /// Adds the Conv node over `input` with the initializers `weight` and `bias` (if any);
    /// returns its output's name.
    fn conv_node(&mut self, conv: &Conv, input: &str, weight: &str, bias: Option<&str>) -> String {
        let k = conv.kernel as i64;
        let p = (conv.kernel / 2) as i64;
        let s = conv.stride.map(|x| x as i64);
        let out = format!("{}.conv", conv.path);
        let mut inputs = vec![input, weight];
        inputs.extend(bias);
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
        out
    }

    /// Adds the (unfolded) BatchNormalization `bn` over `input`, its four tensors as
    /// initializers; returns its output's name.
    fn batch_norm_node(&mut self, bn: &str, channels: usize, input: &str) -> Result<String> {
        let names = ["weight", "bias", "running_mean", "running_var"].map(|s| format!("{bn}.{s}"));
        for name in &names {
            let values = self.take_floats(name, channels)?;
            self.initializers
                .push(onnx::initializer_f32(name, &[channels], &values));
        }
        let bn_out = format!("{bn}.out");
        self.nodes.push(onnx::node(
            "BatchNormalization",
            bn,
            &[input, &names[0], &names[1], &names[2], &names[3]],
            &[&bn_out],
            vec![onnx::attr_float("epsilon", BN_EPS as f32)],
        ));
        Ok(bn_out)
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

/// The nodes that resize `x` (nearest) to the spatial size of `skip` into `{p}.up`, for the
/// decoder at module path `p`; they need the [`FOLD_LEAD`] initializer ([`add_fold_lead`]).
///
/// The resize runs on four dimensions: `(B, C, L, H, W)` is folded to `(B, C*L, H, W)`,
/// resized and unfolded, because ONNX Runtime's 5-D nearest `Resize` is a slow generic loop
/// (2.07 s of a 10.7 s window of the full network at 346x260). A nearest resize copies
/// values, so the output is the same.
fn upsample_nodes(p: &str, x: &str, skip: &str) -> Vec<NodeProto> {
    let name = |part: &str| format!("{p}.up.{part}");
    let (lead, skip_hw, sizes) = (name("lead_dims"), name("skip_hw"), name("sizes"));
    let (x_hw, fold_shape, folded) = (name("x_hw"), name("fold_shape"), name("folded"));
    let (folded_lead, folded_sizes, resized) =
        (name("folded_lead"), name("folded_sizes"), name("resized"));
    let up = format!("{p}.up");
    let shape = |out: &str, of: &str, start: i64, end: i64| {
        onnx::node(
            "Shape",
            out,
            &[of],
            &[out],
            vec![onnx::attr_int("start", start), onnx::attr_int("end", end)],
        )
    };
    let concat = |out: &str, parts: &[&str]| {
        onnx::node(
            "Concat",
            out,
            parts,
            &[out],
            vec![onnx::attr_int("axis", 0)],
        )
    };
    vec![
        // (B, C, L) and the sizes to unfold to, (B, C, L, Hs, Ws).
        shape(&lead, x, 0, 3),
        shape(&skip_hw, skip, 3, 5),
        concat(&sizes, &[&lead, &skip_hw]),
        // Fold: (B, C*L, H, W), the reshape's 0 copying B.
        shape(&x_hw, x, 3, 5),
        concat(&fold_shape, &[FOLD_LEAD, &x_hw]),
        onnx::node("Reshape", &folded, &[x, &fold_shape], &[&folded], vec![]),
        shape(&folded_lead, &folded, 0, 2),
        concat(&folded_sizes, &[&folded_lead, &skip_hw]),
        onnx::node(
            "Resize",
            &resized,
            &[&folded, "", "", &folded_sizes],
            &[&resized],
            vec![
                onnx::attr_string("mode", "nearest"),
                onnx::attr_string("coordinate_transformation_mode", "asymmetric"),
                onnx::attr_string("nearest_mode", "floor"),
            ],
        ),
        onnx::node("Reshape", &up, &[&resized, &sizes], &[&up], vec![]),
    ]
}

/// Adds the [`FOLD_LEAD`] initializer unless it is there.
fn add_fold_lead(initializers: &mut Vec<TensorProto>) {
    if !initializers
        .iter()
        .any(|t| t.name.as_deref() == Some(FOLD_LEAD))
    {
        initializers.push(onnx::initializer_i64(FOLD_LEAD, &[2], &[0, -1]));
    }
}

/// Rewrites a model imported before the 4-D fold (each decoder's `{p}.up` a 5-D `Resize`
/// fed by `{p}.up.lead_dims`, `{p}.up.skip_hw` and `{p}.up.sizes`) into the nodes an import
/// writes now, so a model whose checkpoint is gone runs as fast as a new import; weights and
/// outputs are unchanged. Returns how many resizes were folded (0 for a model that has none
/// of the old form).
pub fn fold_upsampling(model: &mut ModelProto) -> usize {
    let Some(graph) = model.graph.as_mut() else {
        return 0;
    };
    let mut folded = 0;
    loop {
        let old = graph.node.iter().position(|n| {
            n.op_type.as_deref() == Some("Resize")
                && n.name.as_deref().is_some_and(|name| name.ends_with(".up"))
                && n.input.first().is_some_and(|x| !x.ends_with(".up.folded"))
        });
        let Some(at) = old else { break };
        let resize = &graph.node[at];
        let name = resize.name.clone().unwrap_or_default();
        let p = name.trim_end_matches(".up").to_string();
        let x = resize.input[0].clone();
        let skip_hw = format!("{p}.up.skip_hw");
        let Some(skip) = graph
            .node
            .iter()
            .find(|n| n.name.as_deref() == Some(skip_hw.as_str()))
            .and_then(|n| n.input.first().cloned())
        else {
            break;
        };
        let helpers = [
            format!("{p}.up.lead_dims"),
            skip_hw,
            format!("{p}.up.sizes"),
        ];
        let first = graph
            .node
            .iter()
            .position(|n| {
                n.name
                    .as_deref()
                    .is_some_and(|m| helpers.iter().any(|h| h == m))
            })
            .unwrap_or(at)
            .min(at);
        graph.node.retain(|n| {
            n.name
                .as_deref()
                .is_none_or(|m| m != name && !helpers.iter().any(|h| h == m))
        });
        let tail = graph.node.split_off(first);
        graph.node.extend(upsample_nodes(&p, &x, &skip));
        graph.node.extend(tail);
        folded += 1;
    }
    if folded > 0 {
        add_fold_lead(&mut graph.initializer);
    }
    folded
}
