//! The network's building blocks: a 3D convolution and a residual block, with the module paths
//! their state-dict keys are named by.

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
