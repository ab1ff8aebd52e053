#!/usr/bin/env python3
"""Speed and peak memory of the reference V2CE network on CPU.

Backends
    torch        the PyTorch reference (train/v2ce_ref/model.py), spectral norm live
                 (one power iteration per call, as the official code does);
    ort-python   the same network exported to ONNX (spectral norm folded into plain
                 weights: W = weight_bar / sigma after one iteration; opset 17; dynamic
                 batch, height and width) and run with onnxruntime's Python API.

Measures one 16-pair window (input 1x16x2xHxW) at a given size and thread count: one
warm-up call, then --runs timed calls; reports the median as pairs/s. Every measurement
runs in a fresh subprocess so that peak RSS (getrusage ru_maxrss) of one configuration
does not mix with another's, or with the export.

    python train/bench_reference.py --size 260x346 --threads 2 --runs 3 --backend torch
    python train/bench_reference.py --size 260x346 --threads 2 --runs 3 \\
        --backend ort-python [--onnx /tmp/v2ce_seeded7.onnx]

Weights: --checkpoint PATH (a toolbox-format state dict) or, by default, the seeded
checkpoint of seed 7 (speed does not depend on the values). With ort-python, the ONNX
file given by --onnx is exported first if it does not exist (with --verify, the export
is also checked against PyTorch at 61x83). Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

L = 16


def parse_size(s):
    h, w = s.lower().split("x")
    return int(h), int(w)


def load_state_dict(path):
    import torch
    from v2ce_ref.seeded import seeded_state_dict

    if path:
        return torch.load(path, map_location="cpu")
    return seeded_state_dict(7)


def make_input(h, w):
    import numpy as np

    rng = np.random.default_rng(0)
    return rng.standard_normal((1, L, 2, h, w), dtype=np.float32)


def export_onnx(args):
    """Fold the spectral norm and export to ``args.onnx`` (runs in its own process)."""
    import torch
    from v2ce_ref.model import build_model, fold_spectral_norm

    model = build_model(load_state_dict(args.checkpoint))
    folded = fold_spectral_norm(model)
    dummy = torch.from_numpy(make_input(61, 83))
    axes = {0: "batch", 3: "height", 4: "width"}
    torch.onnx.export(folded, (dummy,), args.onnx, opset_version=17,
                      input_names=["pairs"], output_names=["voxels"],
                      dynamic_axes={"pairs": axes, "voxels": axes}, dynamo=False)
    if args.verify:
        import numpy as np
        import onnxruntime as ort

        sess = ort.InferenceSession(args.onnx, providers=["CPUExecutionProvider"])
        for h, w in ((61, 83), (33, 47)):
            x = make_input(h, w)
            with torch.no_grad():
                ref = model(torch.from_numpy(x)).numpy()
            # reload: the live model iterated u, v once more
            model = build_model(load_state_dict(args.checkpoint))
            got = sess.run(None, {"pairs": x})[0]
            dev = float(np.abs(got - ref).max() / np.abs(ref).max())
            print(f"onnx vs torch at {h}x{w}: max|diff| / max|O| = {dev:.3g}",
                  file=sys.stderr)
            assert dev < 1e-4, dev


def measure(args):
    """One configuration, in this (fresh) process. Returns the result dict."""
    h, w = parse_size(args.size)
    x = make_input(h, w)
    if args.backend == "torch":
        import torch
        from v2ce_ref.model import build_model

        torch.set_num_threads(args.threads)
        model = build_model(load_state_dict(args.checkpoint))
        xt = torch.from_numpy(x)

        def call():
            with torch.no_grad():
                return model(xt)
        version = torch.__version__
    else:
        import onnxruntime as ort

        so = ort.SessionOptions()
        so.intra_op_num_threads = args.threads
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        sess = ort.InferenceSession(args.onnx, so, providers=["CPUExecutionProvider"])

        def call():
            return sess.run(None, {sess.get_inputs()[0].name: x})[0]
        version = ort.__version__
    rss_loaded = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t = time.perf_counter()
    call()
    warm = time.perf_counter() - t
    times = []
    for _ in range(args.runs):
        t = time.perf_counter()
        call()
        times.append(time.perf_counter() - t)
    med = statistics.median(times)
    return {
        "backend": args.backend, "version": version, "size": f"{h}x{w}",
        "threads": args.threads, "runs": args.runs, "pairs": L,
        "median_s": round(med, 4), "pairs_per_s": round(L / med, 4),
        "times_s": [round(v, 4) for v in times], "warmup_s": round(warm, 4),
        "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "rss_after_load_mib": round(rss_loaded / 1024, 1),
        "cpu": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="260x346", help="HxW")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--backend", choices=["torch", "ort-python"], default="torch")
    ap.add_argument("--onnx", default="/tmp/v2ce_seeded7.onnx")
    ap.add_argument("--checkpoint", default=None,
                    help="toolbox-format .pt state dict (default: seeded, seed 7)")
    ap.add_argument("--verify", action="store_true",
                    help="when exporting, check ONNX against PyTorch at small sizes")
    ap.add_argument("--child", choices=["measure", "export"], help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args.child == "export":
        export_onnx(args)
        return
    if args.child == "measure":
        print(json.dumps(measure(args)))
        return

    base = [sys.executable, os.path.abspath(__file__), "--size", args.size,
            "--threads", str(args.threads), "--runs", str(args.runs),
            "--backend", args.backend, "--onnx", args.onnx]
    if args.checkpoint:
        base += ["--checkpoint", args.checkpoint]
    if args.backend == "ort-python" and not os.path.exists(args.onnx):
        subprocess.run(base + ["--child", "export"] + (["--verify"] if args.verify else []),
                       check=True)
    out = subprocess.run(base + ["--child", "measure"], check=True, stdout=subprocess.PIPE,
                         text=True).stdout
    print(out.strip().splitlines()[-1])


if __name__ == "__main__":
    main()
