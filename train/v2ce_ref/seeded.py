"""Deterministic seeded checkpoint for the V2CE generator.

The real weights cannot be committed (212 MB, separate licence), so the parity tests
use a checkpoint that is a pure function of a seed. The Rust test suite writes the
same checkpoint itself, bit for bit, so both sides must follow this rule exactly.

Rule (all integer arithmetic modulo 2^64):

    Entries: the 218 keys in Appendix A order (= registration order of
    V2ce3d().state_dict()), numbered k = 0..217.
    A float tensor with n elements gets, for element j (row-major, 0..n-1):
        x = seed * 0x9E3779B97F4A7C15 + (k + 1) * 0xD1B54A32D192ED03 + j
        z = x ^ (x >> 30);  z = z * 0xBF58476D1CE4E5B9
        z = z ^ (z >> 27);  z = z * 0x94D049BB133111EB
        z = z ^ (z >> 31)
        unit  = float64(z >> 40) / 2**24                     # in [0, 1)
        value = float32(lo + (hi - lo) * unit)               # float64 math, then cast
                                                             # (round to nearest even)
    (lo, hi) by key:
        5-D conv weights (``*.weight`` with 5 dims, ``*.weight_bar``):
            a = sqrt(6 / fan_in), fan_in = shape[1]*shape[2]*shape[3]*shape[4]; (-a, a)
        conv biases (head.conv3d.bias, *.downsample.0.bias, pred.conv3d.bias): (-0.1, 0.1)
        BatchNorm (*.bn1.*, *.bn2.*, *.downsample.1.*):
            weight (0.5, 1.5), bias (-0.2, 0.2), running_mean (-0.2, 0.2),
            running_var (0.5, 2.0)
        *.num_batches_tracked: int64 scalar (shape []), value 1000 + k, no draw
        *.weight_u, *.weight_v: (-1, 1), stored as drawn (not normalised)

The hash is the SplitMix64 finaliser applied to a per-tensor counter.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import List, Tuple

import numpy as np
import torch

MASK64 = (1 << 64) - 1
GOLDEN = 0x9E3779B97F4A7C15
KEY_MUL = 0xD1B54A32D192ED03
MIX1 = 0xBF58476D1CE4E5B9
MIX2 = 0x94D049BB133111EB


def unit_draws(seed: int, k: int, n: int) -> np.ndarray:
    """The n float64 numbers in [0, 1) of entry k (numpy uint64 arithmetic wraps)."""
    base = (seed * GOLDEN + (k + 1) * KEY_MUL) & MASK64
    x = np.uint64(base) + np.arange(n, dtype=np.uint64)
    z = x ^ (x >> np.uint64(30))
    z = z * np.uint64(MIX1)
    z = z ^ (z >> np.uint64(27))
    z = z * np.uint64(MIX2)
    z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(40)).astype(np.float64) / float(2 ** 24)


def value_range(key: str, shape: Tuple[int, ...]) -> Tuple[float, float]:
    """(lo, hi) of a float entry, by key (see the module docstring)."""
    if key.endswith(".weight_bar") or (key.endswith(".weight") and len(shape) == 5):
        fan_in = shape[1] * shape[2] * shape[3] * shape[4]
        a = math.sqrt(6.0 / fan_in)
        return -a, a
    if key.endswith((".weight_u", ".weight_v")):
        return -1.0, 1.0
    if key.endswith(("head.conv3d.bias", ".downsample.0.bias", "pred.conv3d.bias")):
        return -0.1, 0.1
    if any(p in key for p in (".bn1.", ".bn2.", ".downsample.1.")):
        leaf = key.rsplit(".", 1)[1]
        ranges = {"weight": (0.5, 1.5), "bias": (-0.2, 0.2),
                  "running_mean": (-0.2, 0.2), "running_var": (0.5, 2.0)}
        if leaf in ranges:
            return ranges[leaf]
    raise KeyError(f"no seeded rule for {key} {shape}")


def template() -> List[Tuple[str, Tuple[int, ...], torch.dtype]]:
    """(key, shape, dtype) of the 218 entries, in registration (Appendix A) order."""
    from .model import V2ce3d, STATE_DICT_LEN

    with torch.device("meta"):
        sd = V2ce3d().state_dict()
    out = [(k, tuple(v.shape), v.dtype) for k, v in sd.items()]
    assert len(out) == STATE_DICT_LEN, len(out)
    return out


def seeded_state_dict(seed: int) -> "OrderedDict[str, torch.Tensor]":
    """The seeded checkpoint: an OrderedDict with the 218 official keys."""
    sd: "OrderedDict[str, torch.Tensor]" = OrderedDict()
    for k, (key, shape, dtype) in enumerate(template()):
        if key.endswith(".num_batches_tracked"):
            assert shape == () and dtype == torch.int64
            sd[key] = torch.tensor(1000 + k, dtype=torch.int64)
            continue
        assert dtype == torch.float32, key
        lo, hi = value_range(key, shape)
        n = int(np.prod(shape, dtype=np.int64))
        vals = (lo + (hi - lo) * unit_draws(seed, k, n)).astype(np.float32)
        sd[key] = torch.from_numpy(vals.reshape(shape))
    return sd


if __name__ == "__main__":
    # Print a few values that a port can check its PRNG against.
    import sys

    seed = int(sys.argv[1]) if len(sys.argv) > 1 else 7
    sd = seeded_state_dict(seed)
    for k, (key, t) in enumerate(sd.items()):
        flat = t.reshape(-1)
        head = [float(v) for v in flat[:3]] if t.dtype == torch.float32 else [int(t)]
        print(k, key, list(t.shape), head)
