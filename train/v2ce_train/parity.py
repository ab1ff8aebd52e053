"""PyTorch against the ONNX model `v2ce model import` made of the same checkpoint, on one
random input through `v2ce model run`: prints the largest difference and fails above a
tolerance.

    python -m v2ce_train.parity best.pt model.onnx [--v2ce PATH] [--pairs 4 --size 48x32]
"""

import argparse
import os
import subprocess
import sys
import tempfile

import numpy as np
import torch

from .model import from_state_dict


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("checkpoint")
    p.add_argument("onnx")
    p.add_argument("--v2ce", default="v2ce")
    p.add_argument("--pairs", type=int, default=4)
    p.add_argument("--size", default="48x32", help="WxH")
    p.add_argument("--tolerance", type=float, default=1e-4, help="relative to the output's range")
    a = p.parse_args(argv)
    w, h = (int(v) for v in a.size.lower().split("x"))
    model = from_state_dict(torch.load(a.checkpoint, weights_only=True)).eval()
    x = np.random.default_rng(0).normal(size=(1, a.pairs, 2, h, w)).astype(np.float32)
    with torch.no_grad():
        want = model(torch.from_numpy(x)).numpy()
    with tempfile.TemporaryDirectory() as tmp:
        xin, yout = os.path.join(tmp, "x.npy"), os.path.join(tmp, "y.npy")
        np.save(xin, x)
        subprocess.run(
            [a.v2ce, "model", "run", a.onnx, "--input-npy", xin, "--output-npy", yout, "--threads", "1"],
            check=True,
        )
        got = np.load(yout)
    if got.shape != want.shape:
        sys.exit(f"parity: shape {got.shape} against PyTorch's {want.shape}")
    diff = float(np.abs(got - want).max())
    scale = max(float(np.abs(want).max()), 1e-6)
    print(f"parity: largest difference {diff:.3g} (output range {scale:.3g})")
    if diff > a.tolerance * scale:
        sys.exit(f"parity: {diff} exceeds {a.tolerance} of the output's range")


if __name__ == "__main__":
    main()
