"""The trainer's networks: the V2CE generator is ``v2ce_ref.model.V2ce3d`` (the official
parameter names, shapes and order; any width and depth), initialised for training as the
reference does (V2CE_SPEC.md section 3.6); the discriminator of the adversarial loss is the
2D PatchGAN of section 3.7."""

import torch
import torch.nn as nn

from v2ce_ref.model import SpectralNorm, V2ce3d


def generator(base=32, encoders=4, resblocks=2) -> V2ce3d:
    """A generator ready to train: section 3.6's initialisation (Kaiming-normal with a=10,
    fan in, on plain Conv3d weights; zero biases; BatchNorm 1/0; spectral-norm convolutions
    keep PyTorch's default), and the spectral norms' u and v drawn as random unit vectors
    (the inference model leaves them at zero until a checkpoint fills them)."""
    model = V2ce3d(base, encoders, resblocks)
    for m in model.modules():
        if isinstance(m, nn.Conv3d) and "weight" in m._parameters:
            nn.init.kaiming_normal_(m.weight, a=10)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm3d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)
    with torch.no_grad():
        for sn in (m for m in model.modules() if isinstance(m, SpectralNorm)):
            for p in (sn.module.weight_u, sn.module.weight_v):
                p.copy_(torch.randn_like(p))
                p.div_(p.norm() + 1e-12)
    return model


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
