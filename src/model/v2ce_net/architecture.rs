//! The network as a whole: the V2CE generator and the family of UNets it belongs to, inferred
//! from a checkpoint's shapes, and its receptive field.

use super::layers::{Conv, ResidualBlock};

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
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
