"""The V2CE generator (a 3D UNet over frame pairs, time as depth) and the PatchGAN
discriminator of its adversarial loss, written from V2CE_SPEC.md sections 3.1-3.7.

Parameter names follow the toolbox's state dict (Appendix A): ``UNet.head.conv3d``,
``UNet.encoders.N``, ``UNet.resblocks.N``, ``UNet.decoders.N``, ``UNet.pred.conv3d``, with
spectral-norm convolutions stored as ``module.weight_u``, ``module.weight_v`` and
``module.weight_bar``. ``base=32, encoders=4, resblocks=2`` is the released network's shape.
"""

import torch
import torch.nn as nn
import torch.nn.functional as F

SN_EPS = 1e-12


def _normalize(z):
    return z / (z.norm() + SN_EPS)


class SpectralNormConv3d(nn.Module):
    """A Conv3d whose weight is ``weight_bar / sigma``, sigma from one power iteration per call
    (in training and in eval, as the reference does; u and v are updated in place)."""

    def __init__(self, conv: nn.Conv3d):
        super().__init__()
        weight = conv.weight.detach().clone()
        del conv._parameters["weight"]
        cout, fan = weight.shape[0], weight[0].numel()
        u = _normalize(torch.randn(cout))
        v = _normalize(torch.randn(fan))
        # Registration order as in the toolbox's state dict: u, v, bar.
        conv.register_parameter("weight_u", nn.Parameter(u, requires_grad=False))
        conv.register_parameter("weight_v", nn.Parameter(v, requires_grad=False))
        conv.register_parameter("weight_bar", nn.Parameter(weight))
        self.module = conv

    def forward(self, x):
        conv = self.module
        w = conv.weight_bar.view(conv.weight_bar.shape[0], -1)
        with torch.no_grad():
            v = _normalize(w.t() @ conv.weight_u)
            u = _normalize(w @ v)
            conv.weight_u.copy_(u)
            conv.weight_v.copy_(v)
        sigma = u @ (w @ v)
        return F.conv3d(x, conv.weight_bar / sigma, conv.bias, conv.stride, conv.padding)


class ConvLayer3D(nn.Module):
    """A convolution with a bias and an activation (head: LeakyReLU 0.01; prediction: ReLU)."""

    def __init__(self, cin, cout, kernel, activation):
        super().__init__()
        self.conv3d = nn.Conv3d(cin, cout, kernel, 1, kernel // 2, bias=True)
        self.activation = activation

    def forward(self, x):
        x = self.conv3d(x)
        return F.leaky_relu(x, 0.01) if self.activation == "leaky" else torch.relu(x)


class ResidualBlock3D(nn.Module):
    """Two 3x3x3 convolutions with BatchNorm, and a projection shortcut in every block (the
    reference's quirk, section 3.2)."""

    def __init__(self, cin, cout, stride, spectral_norm):
        super().__init__()
        wrap = SpectralNormConv3d if spectral_norm else (lambda c: c)
        self.conv1 = wrap(nn.Conv3d(cin, cout, 3, stride, 1, bias=False))
        self.bn1 = nn.BatchNorm3d(cout)
        self.bn2 = nn.BatchNorm3d(cout)
        self.conv2 = wrap(nn.Conv3d(cout, cout, 3, 1, 1, bias=False))
        self.downsample = nn.Sequential(
            nn.Conv3d(cin, cout, 1, stride, 0, bias=True), nn.BatchNorm3d(cout)
        )

    def forward(self, x):
        out = torch.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return torch.relu(out + self.downsample(x))


class UNet3D(nn.Module):
    def __init__(self, base=32, encoders=4, resblocks=2, inputs=2, outputs=20):
        super().__init__()
        ch = [base << i for i in range(encoders + 1)]
        self.head = ConvLayer3D(inputs, base, 3, "leaky")
        self.encoders = nn.ModuleList(
            [ResidualBlock3D(ch[i], ch[i + 1], (1, 2, 2), False) for i in range(encoders)]
        )
        self.resblocks = nn.ModuleList(
            [ResidualBlock3D(ch[-1], ch[-1], 1, True) for _ in range(resblocks)]
        )
        self.decoders = nn.ModuleList(
            [
                ResidualBlock3D(ch[encoders - i] + ch[encoders - i - 1], ch[encoders - i - 1], 1, True)
                for i in range(encoders)
            ]
        )
        self.pred = ConvLayer3D(base, outputs, 1, "relu")

    def forward(self, x):
        x = self.head(x)
        skips = []
        for enc in self.encoders:
            skips.append(x)
            x = enc(x)
        for block in self.resblocks:
            x = block(x)
        for dec, skip in zip(self.decoders, reversed(skips)):
            # Nearest upsampling of each frame to the skip's size (the time axis is kept).
            x = F.interpolate(x, size=skip.shape[2:], mode="nearest")
            x = dec(torch.cat([x, skip], dim=1))
        return self.pred(x)


class V2ce3d(nn.Module):
    """Input (B, L, 2, H, W), normalised frame pairs; output (B, L, 20, H, W) voxels, >= 0."""

    def __init__(self, base=32, encoders=4, resblocks=2):
        super().__init__()
        self.UNet = UNet3D(base, encoders, resblocks)
        self.init_weights()

    def init_weights(self):
        """Section 3.6: Kaiming-normal (a=10, fan in) on plain Conv3d weights, zero biases,
        BatchNorm 1/0; spectral-norm convolutions keep PyTorch's default initialisation."""
        for m in self.modules():
            if isinstance(m, nn.Conv3d) and "weight" in m._parameters:
                nn.init.kaiming_normal_(m.weight, a=10)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, nn.BatchNorm3d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, x):
        y = self.UNet(x.permute(0, 2, 1, 3, 4))
        return y.permute(0, 2, 1, 3, 4)


class PatchDiscriminator(nn.Module):
    """The 2D PatchGAN of section 3.7 (ndf 64, 3 layers, biases, no normalisation) on one
    interval's 20-channel voxel; logits per patch."""

    def __init__(self, channels=20, ndf=64):
        super().__init__()
        layers = [nn.Conv2d(channels, ndf, 4, 2, 1), nn.LeakyReLU(0.2)]
        c = ndf
        for stride in (2, 2, 1):
            layers += [nn.Conv2d(c, c * 2, 4, stride, 1), nn.LeakyReLU(0.2)]
            c *= 2
        layers.append(nn.Conv2d(c, 1, 4, 1, 1))
        self.model = nn.Sequential(*layers)

    def forward(self, x):
        return self.model(x)


def parameter_count(model: nn.Module) -> int:
    """Trainable parameters (the spectral norm's u and v excluded)."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def toolbox_state_dict(model: V2ce3d) -> dict:
    """The generator's state dict as the toolbox saves it (keys ``UNet.*``), on the CPU."""
    return {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}


def from_state_dict(state: dict) -> V2ce3d:
    """A generator shaped like `state` (a toolbox-format state dict), with its weights."""
    base = state["UNet.head.conv3d.weight"].shape[0]

    def count(group):
        idx = {int(k.split(".")[2]) for k in state if k.startswith(group)}
        return max(idx) + 1 if idx else 0

    model = V2ce3d(base, count("UNet.encoders."), count("UNet.resblocks."))
    model.load_state_dict(state)
    return model
