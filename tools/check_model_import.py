#!/usr/bin/env python3
"""Checks an ONNX model written by `v2ce model import` against the PyTorch reference network.

Offline and by hand only (the Rust tests never need Python). Needs onnx, onnxruntime and numpy;
the parity part also needs torch and the reference package `v2ce_ref` (train/v2ce_ref).

    python tools/check_model_import.py MODEL.onnx [--ckpt CKPT.pt] [--ref-dir train]
                                        [--sn-mode iterate|exact|no_iter] [--shapes 1x16x61x83,2x4x40x50]

It runs onnx.checker (full check, with shape inference), prints the metadata, runs the model in
onnxruntime on random inputs of each shape (proving the symbolic dimensions work) and, with
--ckpt, loads the same checkpoint into the reference network (reloaded before every forward, so
each is "the first call after loading") and prints max |onnx - torch| / max |torch| per shape.
Exit status 1 when a shape is wrong or, with --ckpt, a relative difference exceeds --tolerance.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--ckpt")
    ap.add_argument("--ref-dir", default=str(Path(__file__).resolve().parent.parent / "train"))
    ap.add_argument("--sn-mode", default="iterate")
    ap.add_argument("--shapes", default="1x16x61x83,2x4x40x50")
    ap.add_argument("--tolerance", type=float, default=1e-5)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()

    model = onnx.load(args.model)
    onnx.checker.check_model(model, full_check=True)
    meta = {p.key: p.value for p in model.metadata_props}
    print(f"checker: ok; opset {model.opset_import[0].version}, ir {model.ir_version}, "
          f"{len(model.graph.initializer)} initializers, {len(model.graph.node)} nodes")
    print("metadata:", meta)
    dims = [[d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim]
            for v in (model.graph.input[0], model.graph.output[0])]
    print("input dims:", dims[0], "output dims:", dims[1])
    del model

    so = ort.SessionOptions()
    so.intra_op_num_threads = args.threads
    sess = ort.InferenceSession(args.model, so, providers=["CPUExecutionProvider"])

    ref = None
    if args.ckpt:
        import torch
        sys.path.insert(0, args.ref_dir)
        from v2ce_ref import model as ref_model
        torch.set_num_threads(args.threads)
        state = torch.load(args.ckpt, map_location="cpu")
        if "state_dict" in state:
            state = {k.removeprefix("model."): v for k, v in state["state_dict"].items()
                     if not k.startswith("GAN.")}
        ref = (torch, ref_model, state)

    failed = False
    rng = np.random.default_rng(0)
    for spec in args.shapes.split(","):
        b, l, h, w = (int(x) for x in spec.split("x"))
        x = rng.standard_normal((b, l, 2, h, w)).astype(np.float32)
        t0 = time.time()
        (y,) = sess.run(["voxels"], {"frames": x})
        t_ort = time.time() - t0
        ok_shape = y.shape == (b, l, 20, h, w)
        failed |= not ok_shape
        line = f"{spec}: onnxruntime {y.shape} in {t_ort:.1f} s, shape {'ok' if ok_shape else 'WRONG'}"
        if ref is not None:
            torch, ref_model, state = ref
            net = ref_model.build_model(state)  # fresh: the first call after loading
            ref_model.set_sn_mode(net, args.sn_mode)
            with torch.no_grad():
                t0 = time.time()
                yr = net(torch.from_numpy(x)).numpy()
                t_ref = time.time() - t0
            diff = float(np.abs(y.astype(np.float64) - yr).max())
            scale = float(np.abs(yr).max())
            rel = diff / scale if scale > 0 else diff
            failed |= not rel <= args.tolerance
            line += (f"; torch ({args.sn_mode}) in {t_ref:.1f} s: max|diff| {diff:.3e}, "
                     f"max|ref| {scale:.3e}, relative {rel:.3e}")
        print(line, flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
