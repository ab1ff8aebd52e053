"""The V2CE Stage 1 generator (``V2ce3d`` -> ``UNet3D``) in PyTorch.

Written from the specification (V2CE_SPEC.md sections 3.1-3.4 and Appendix A), with
exactly the parameter names, shapes and registration order of the official toolbox, so
that ``V2ce3d().load_state_dict(torch.load("v2ce_3d.pt"), strict=True)`` works and
``model.state_dict()`` lists the 218 entries in Appendix A order.

Architecture (B = batch, L = 16 frame pairs):

    input (B, L, 2, H, W) -> permute -> (B, 2, L, H, W)
    head       ConvLayer3D 2->32, k3 p1, bias, LeakyReLU(0.01)          (skip s0)
    encoders   4 x ResidualBlock3D, stride (1,2,2), 32->64->128->256->512 (skips s1..s3)
    resblocks  2 x ResidualBlock3D 512->512, spectral norm
    decoders   4 x [nearest upsample per frame to the skip's H, W; concat [up, skip];
                    ResidualBlock3D with spectral norm]
    pred       ConvLayer3D 32->20, k1, bias, then ReLU
    output (B, 20, L, H, W) -> permute -> (B, L, 20, H, W)

Quirks reproduced on purpose (spec 3.2):
    * every ResidualBlock3D has the projection shortcut ``downsample`` (1x1x1 conv with
      bias, then BatchNorm3d), even when stride is 1 and cin == cout;
    * the custom SpectralNorm wrapper does one power iteration on EVERY forward call,
      in eval mode too, updating ``weight_u`` / ``weight_v`` in place. Inference is
      therefore stateful: reload (or call :func:`reset_spectral_state`) before every
      forward that must reproduce "the first call after loading".

Only what inference needs is here; training (initialisation, losses) is in ``v2ce_train``.
"""

from __future__ import annotations

import copy
from typing import Dict, List, Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F

#: Number of entries of the official state dict (Appendix A).
STATE_DICT_LEN = 218
#: Trainable parameters (spec 3.5): everything except the SN u/v vectors.
TRAINABLE_PARAMS = 52_791_508
#: All parameters including the SN u/v vectors (PyTorch counts them in parameters()).
ALL_PARAMS = 52_901_652

# Spectral-norm resolution modes. "iterate" is the official behaviour; the other two
# exist only to measure how much a wrong resolution would change the outputs.
SN_ITERATE = "iterate"   # one in-place power iteration per forward, sigma = u'^T W v
SN_EXACT = "exact"       # sigma = largest singular value of W (no state change)
SN_NO_ITER = "no_iter"   # sigma = u^T W v with the stored u, v as they are (no state change)
SN_MODES = (SN_ITERATE, SN_EXACT, SN_NO_ITER)


def _l2n(z: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """n(z) = z / (||z||_2 + eps), as in the official SpectralNorm."""
    return z / (z.norm() + eps)


class SpectralNorm(nn.Module):
    """Spectral-norm wrapper with the official layout.

    The wrapped conv loses its ``weight`` parameter and instead holds, registered in
    this order, ``weight_u`` (cout), ``weight_v`` (cin*k^3) and ``weight_bar`` (the raw
    weight). u and v are parameters with ``requires_grad=False``. The state dict path
    is therefore ``<name>.module.weight_u`` etc.

    Forward (mode "iterate", the official one): with Wm = weight_bar viewed as
    (cout, cin*k^3): v <- n(Wm^T u), u <- n(Wm v) (both in place), sigma = u^T Wm v,
    and the conv runs with weight_bar / sigma.
    """

    def __init__(self, module: nn.Conv3d):
        super().__init__()
        self.module = module
        w = module.weight
        cout = w.shape[0]
        fan = w[0].numel()
        del module._parameters["weight"]
        module.register_parameter(
            "weight_u", nn.Parameter(torch.zeros(cout), requires_grad=False))
        module.register_parameter(
            "weight_v", nn.Parameter(torch.zeros(fan), requires_grad=False))
        module.register_parameter("weight_bar", nn.Parameter(w.data.clone()))
        self.mode = SN_ITERATE

    def sigma(self) -> torch.Tensor:
        """Return sigma for the current mode (mutating u, v in mode "iterate")."""
        m = self.module
        wm = m.weight_bar.reshape(m.weight_bar.shape[0], -1)
        if self.mode == SN_ITERATE:
            with torch.no_grad():
                m.weight_v.data.copy_(_l2n(wm.t().mv(m.weight_u.data)))
                m.weight_u.data.copy_(_l2n(wm.mv(m.weight_v.data)))
            return m.weight_u.dot(wm.mv(m.weight_v))
        if self.mode == SN_EXACT:
            with torch.no_grad():
                return torch.linalg.matrix_norm(wm.double(), ord=2).to(wm.dtype)
        if self.mode == SN_NO_ITER:
            return m.weight_u.dot(wm.mv(m.weight_v))
        raise ValueError(f"unknown spectral-norm mode {self.mode!r}")

    def effective_weight(self) -> torch.Tensor:
        """weight_bar / sigma (runs :meth:`sigma`, so it iterates in mode "iterate")."""
        return self.module.weight_bar / self.sigma()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        m = self.module
        return F.conv3d(x, self.effective_weight(), m.bias, m.stride, m.padding,
                        m.dilation, m.groups)


class ConvLayer3D(nn.Module):
    """Conv3d with bias followed by an activation (head and pred layers).

    ``activation`` is "LeakyReLU" (nn.LeakyReLU, slope 0.01) or "relu" (torch.relu).
    """

    def __init__(self, cin: int, cout: int, k: int, padding: int, activation: str):
        super().__init__()
        self.conv3d = nn.Conv3d(cin, cout, k, stride=1, padding=padding, bias=True)
        if activation == "LeakyReLU":
            self.activation = nn.LeakyReLU(0.01)
        elif activation == "relu":
            self.activation = torch.relu
        else:
            raise ValueError(activation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.activation(self.conv3d(x))


class ResidualBlock3D(nn.Module):
    """Residual block with BatchNorm and the always-present projection shortcut.

    out = ReLU(bn2(conv2(ReLU(bn1(conv1(x))))) + downsample(x)),
    downsample = Conv3d(k1, stride, bias) -> BatchNorm3d.

    Registration order (hence state-dict order) is conv1, bn1, bn2, conv2, downsample,
    as in Appendix A.
    """

    def __init__(self, cin: int, cout: int, stride: Tuple[int, int, int], sn: bool):
        super().__init__()
        conv1 = nn.Conv3d(cin, cout, 3, stride=stride, padding=1, bias=False)
        self.conv1 = SpectralNorm(conv1) if sn else conv1
        self.bn1 = nn.BatchNorm3d(cout)
        self.bn2 = nn.BatchNorm3d(cout)
        conv2 = nn.Conv3d(cout, cout, 3, stride=1, padding=1, bias=False)
        self.conv2 = SpectralNorm(conv2) if sn else conv2
        self.relu = nn.ReLU()
        self.downsample = nn.Sequential(
            nn.Conv3d(cin, cout, 1, stride=stride, padding=0, bias=True),
            nn.BatchNorm3d(cout),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + self.downsample(x))


def upsample_to(x: torch.Tensor, size: Tuple[int, int]) -> torch.Tensor:
    """Legacy ``nearest`` resize of every frame of (B, C, L, h, w) to (H, W) = size.

    Done per frame like the official code: (B, C, L, h, w) -> (B*L, C, h, w) ->
    F.interpolate(mode="nearest") -> back to (B, C, L, H, W).
    """
    b, c, l, h, w = x.shape
    y = x.permute(0, 2, 1, 3, 4).reshape(b * l, c, h, w)
    y = F.interpolate(y, size=size, mode="nearest")
    return y.reshape(b, l, c, size[0], size[1]).permute(0, 2, 1, 3, 4)


class UNet3D(nn.Module):
    """The concat-skip 3D UNet of V2CE (4 encoders, base 32 channels, 2 resblocks)."""

    def __init__(self, num_input_channels: int = 2, num_output_channels: int = 20,
                 base_num_channels: int = 32, num_encoders: int = 4,
                 num_residual_blocks: int = 2):
        super().__init__()
        b = base_num_channels
        enc_in = [b * 2 ** i for i in range(num_encoders)]          # 32, 64, 128, 256
        enc_out = [b * 2 ** (i + 1) for i in range(num_encoders)]   # 64, 128, 256, 512
        top = enc_out[-1]
        self.head = ConvLayer3D(num_input_channels, b, 3, 1, "LeakyReLU")
        self.encoders = nn.ModuleList(
            ResidualBlock3D(i, o, (1, 2, 2), sn=False) for i, o in zip(enc_in, enc_out))
        self.resblocks = nn.ModuleList(
            ResidualBlock3D(top, top, (1, 1, 1), sn=True) for _ in range(num_residual_blocks))
        # Decoder i: input = upsampled (enc_out reversed) ++ skip (enc_in reversed).
        self.decoders = nn.ModuleList(
            ResidualBlock3D(o + i, i, (1, 1, 1), sn=True)
            for o, i in zip(reversed(enc_out), reversed(enc_in)))
        self.pred = ConvLayer3D(b, num_output_channels, 1, 0, "relu")

    def forward(self, x: torch.Tensor, trace: Dict[str, float] | None = None) -> torch.Tensor:
        """x: (B, 2, L, H, W) -> (B, 20, L, H, W).

        If ``trace`` is a dict, the standard deviation of every block's output is
        stored in it (used to check that activations stay O(1)).
        """
        def note(name, t):
            if trace is not None:
                trace[name] = float(t.double().std())

        x = self.head(x)
        note("head", x)
        skips: List[torch.Tensor] = []
        for k, enc in enumerate(self.encoders):
            skips.append(x)
            x = enc(x)
            note(f"encoders.{k}", x)
        for k, rb in enumerate(self.resblocks):
            x = rb(x)
            note(f"resblocks.{k}", x)
        for k, dec in enumerate(self.decoders):
            skip = skips[-k - 1]
            x = torch.cat([upsample_to(x, skip.shape[-2:]), skip], dim=1)
            x = dec(x)
            note(f"decoders.{k}", x)
        x = self.pred(x)
        note("pred", x)
        return x


class V2ce3d(nn.Module):
    """Top level: (B, L, 2, H, W) normalized frame pairs -> (B, L, 20, H, W) voxels.

    ``base``, ``encoders`` and ``resblocks`` choose a narrower or shallower member of the
    family (the trainer's small models); the defaults are the released network."""

    def __init__(self, base: int = 32, encoders: int = 4, resblocks: int = 2):
        super().__init__()
        self.UNet = UNet3D(base_num_channels=base, num_encoders=encoders,
                           num_residual_blocks=resblocks)

    def forward(self, x: torch.Tensor, trace: Dict[str, float] | None = None) -> torch.Tensor:
        y = self.UNet(x.permute(0, 2, 1, 3, 4), trace=trace)
        return y.permute(0, 2, 1, 3, 4)


# ---------------------------------------------------------------------------------------
# Helpers


def spectral_norms(model: nn.Module) -> List[SpectralNorm]:
    """All SpectralNorm wrappers of ``model`` in registration order (12 for V2ce3d)."""
    return [m for m in model.modules() if isinstance(m, SpectralNorm)]


def set_sn_mode(model: nn.Module, mode: str) -> None:
    """Switch every SpectralNorm of ``model`` to ``mode`` (see SN_MODES)."""
    if mode not in SN_MODES:
        raise ValueError(mode)
    for sn in spectral_norms(model):
        sn.mode = mode


def sn_state(model: nn.Module) -> Dict[str, torch.Tensor]:
    """Copy of every weight_u / weight_v (the state mutated by forward calls)."""
    return {k: v.detach().clone() for k, v in model.state_dict().items()
            if k.endswith((".weight_u", ".weight_v"))}


def reset_spectral_state(model: nn.Module, saved: Dict[str, torch.Tensor]) -> None:
    """Restore the u / v vectors saved by :func:`sn_state` (undo forward calls)."""
    sd = model.state_dict()
    with torch.no_grad():
        for k, v in saved.items():
            sd[k].copy_(v)


def build_model(state_dict=None) -> V2ce3d:
    """A V2ce3d in eval mode, loaded with ``state_dict`` (strict) when given."""
    model = V2ce3d()
    if state_dict is not None:
        model.load_state_dict(state_dict, strict=True)
    model.eval()
    return model


def fold_spectral_norm(model: V2ce3d) -> V2ce3d:
    """A stateless copy of ``model`` for export: every SN conv becomes a plain Conv3d.

    The folded weight is weight_bar / sigma after ONE power iteration from the stored
    u (exactly what the first forward call after loading uses). ``model`` itself is
    left untouched.
    """
    out = copy.deepcopy(model)
    for parent in list(out.modules()):
        for name, child in list(parent.named_children()):
            if isinstance(child, SpectralNorm):
                with torch.no_grad():
                    w = child.effective_weight().detach().clone()
                m = child.module
                conv = nn.Conv3d(m.in_channels, m.out_channels, m.kernel_size,
                                 stride=m.stride, padding=m.padding, bias=False)
                conv.weight = nn.Parameter(w)
                setattr(parent, name, conv)
    out.eval()
    return out


def count_params(model: nn.Module) -> Tuple[int, int]:
    """(trainable parameters, all parameters incl. the SN u/v vectors)."""
    trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    total = sum(p.numel() for p in model.parameters())
    return trainable, total
