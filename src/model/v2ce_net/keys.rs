//! The state dict the network expects, and the check of a checkpoint's entries against it.

use std::collections::{HashMap, HashSet};
use std::path::Path;

use super::architecture::Architecture;
use super::layers::Conv;
use crate::model::torch::TensorEntry;
use crate::model::{shape_string, Tensor, TensorData};
use crate::{Error, Result};

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

impl Architecture {
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
    /// key, ready to be a [`WeightSource`](super::WeightSource).
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
        let keys = NormalisedKeys::new(origin, entries)?;
        let expected = self.state_dict_keys();
        let mismatch = KeyMismatch::find(&expected, &keys, entries);
        if let Some((key, problem)) = &mismatch.first_problem {
            let summary = mismatch.summary();
            return Err(state_dict_error(
                origin,
                key,
                format!(
                    "{problem} [in all: {summary}; {} entries read, {} expected]",
                    entries.len(),
                    expected.len()
                ),
            ));
        }
        Ok(Selection {
            prefix_stripped: keys.prefix_stripped,
            dropped_gan_keys: keys.dropped_gan_keys,
            index: keys.index,
        })
    }
}

/// A checkpoint's keys with Lightning's `model.` prefix stripped and the discriminator's
/// (`GAN.*`) keys dropped.
struct NormalisedKeys {
    /// The position in the entry list of each normalised key.
    index: HashMap<String, usize>,
    /// The normalised keys, in the file's order.
    order: Vec<String>,
    /// How many `GAN.*` keys were dropped.
    dropped_gan_keys: usize,
    /// Whether any key carried the `model.` prefix.
    prefix_stripped: bool,
}

impl NormalisedKeys {
    /// Normalises the names of `entries`; a key that appears twice is an error.
    fn new(origin: &Path, entries: &[(&str, &[usize], bool)]) -> Result<Self> {
        let mut keys = NormalisedKeys {
            index: HashMap::with_capacity(entries.len()),
            order: Vec::with_capacity(entries.len()),
            dropped_gan_keys: 0,
            prefix_stripped: false,
        };
        for (i, (name, _, _)) in entries.iter().enumerate() {
            if name.starts_with("GAN.") || name.starts_with("model.GAN.") {
                keys.dropped_gan_keys += 1;
                continue;
            }
            let key = match name.strip_prefix("model.") {
                Some(rest) => {
                    keys.prefix_stripped = true;
                    rest
                }
                None => name,
            };
            if keys.index.insert(key.to_string(), i).is_some() {
                return Err(state_dict_error(
                    origin,
                    key,
                    "appears twice (once with Lightning's model. prefix?)".into(),
                ));
            }
            keys.order.push(key.to_string());
        }
        Ok(keys)
    }
}

/// How a checkpoint's keys differ from the expected ones.
struct KeyMismatch<'a> {
    /// Expected keys that are absent.
    missing: usize,
    /// Expected keys present with the wrong shape or element type.
    misfits: usize,
    /// Keys the network does not have, in the file's order.
    unexpected: Vec<&'a str>,
    /// The key to report and what is wrong with it: the first missing or misfit key in the
    /// expected order, else the first unexpected one.
    first_problem: Option<(String, String)>,
}

impl<'a> KeyMismatch<'a> {
    /// Compares `keys` (positions in `entries`) with the `expected` ones.
    fn find(
        expected: &[KeySpec],
        keys: &'a NormalisedKeys,
        entries: &[(&str, &[usize], bool)],
    ) -> Self {
        let expected_names: HashSet<&str> = expected.iter().map(|k| k.name.as_str()).collect();
        let mut mismatch = KeyMismatch {
            missing: 0,
            misfits: 0,
            unexpected: keys
                .order
                .iter()
                .map(String::as_str)
                .filter(|k| !expected_names.contains(k))
                .collect(),
            first_problem: None,
        };
        for spec in expected {
            let problem = match keys.index.get(&spec.name) {
                None => {
                    mismatch.missing += 1;
                    format!(
                        "missing (expected a {} tensor of shape {})",
                        if spec.kind.is_int() { "int64" } else { "float" },
                        shape_string(&spec.shape)
                    )
                }
                Some(&i) => {
                    let (_, shape, is_float) = entries[i];
                    let Some(problem) = misfit(spec, shape, is_float) else {
                        continue;
                    };
                    mismatch.misfits += 1;
                    problem
                }
            };
            if mismatch.first_problem.is_none() {
                mismatch.first_problem = Some((spec.name.clone(), problem));
            }
        }
        if mismatch.first_problem.is_none() {
            if let Some(first) = mismatch.unexpected.first() {
                mismatch.first_problem = Some((
                    first.to_string(),
                    "unexpected: the V2CE generator has no such entry".into(),
                ));
            }
        }
        mismatch
    }

    /// The counts of each kind of problem, e.g. `2 missing, 1 unexpected (the first: x)`.
    fn summary(&self) -> String {
        let mut also = Vec::new();
        if self.missing > 0 {
            also.push(format!("{} missing", self.missing));
        }
        if self.misfits > 0 {
            also.push(format!("{} mis-shaped or mis-typed", self.misfits));
        }
        if let Some(first) = self.unexpected.first() {
            also.push(format!(
                "{} unexpected (the first: {first})",
                self.unexpected.len()
            ));
        }
        also.join(", ")
    }
}

/// What is wrong with an entry of `shape` holding floats (or not) where `spec` is expected, if
/// anything.
fn misfit(spec: &KeySpec, shape: &[usize], is_float: bool) -> Option<String> {
    if shape != spec.shape.as_slice() {
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

/// The error for checkpoint entry `key` of `origin`.
pub(super) fn state_dict_error(origin: &Path, key: &str, message: String) -> Error {
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
    pub(super) index: HashMap<String, usize>,
}

impl Selection {
    /// The position (in the checked entry list) of the entry with normalised key `key`.
    pub fn index_of(&self, key: &str) -> Option<usize> {
        self.index.get(key).copied()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
