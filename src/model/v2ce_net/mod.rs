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
//!
//! The parts, a file each: `layers` ([`Conv`], [`ResidualBlock`]), `architecture` (the network:
//! [`Architecture`], its family and [`ReceptiveField`]), `keys` (the expected state dict and
//! [`Architecture::select`]), `norms` (spectral norm and BatchNorm resolution) and `graph`
//! ([`Architecture::build_model`]).

mod architecture;
mod graph;
mod keys;
mod layers;
mod norms;

pub use super::onnx::{IR_VERSION, OPSET};
pub use architecture::{Architecture, ReceptiveField};
pub use graph::{fold_upsampling, BuiltModel, WeightSource, ALIGN_KEY, RECEPTIVE_MARGIN_KEY};
pub use keys::{KeyKind, KeySpec, Selection};
pub use layers::{Conv, ResidualBlock};
pub use norms::{
    fold_batch_norm, largest_singular_value, spectral_sigma, SpectralNorm, BN_EPS, SN_EPS,
};
