#!/usr/bin/env python3
"""Make the learned-Stage-1 parity fixtures (tests/fixtures/learned/).

What it makes
    * a seeded V2CE checkpoint (seed 7, rule in train/v2ce_ref/seeded.py), saved with
      torch.save(model.state_dict(), PATH) to --checkpoint (default
      /tmp/v2ce_seeded7.pt; 212 MB, NOT committed: the Rust tests write the same
      checkpoint themselves);
    * in --out (default tests/fixtures/learned/):
        frames_61x83/frame_000000.png ... frame_000058.png, frames_61x83/times.txt
            the 59 DAVIS346 APS frames cropped to rows 100..160, cols 130..212, and
            their mid-exposure times in seconds, 6 decimals (images.txt rounded to the us);
        parity_260x346_values.npy / _meta.json
            the first forward call after loading, on the first 17 full-size frames
            (input 1x16x2x260x346), output sampled with stride 307;
        parity_61x83_values.npy / _meta.json
            the same on the first 17 cropped frames, stride 13; the meta also holds
            how much the output moves if the spectral norm is resolved differently;
        e2e_61x83_values.npy / _meta.json
            all 59 cropped frames, toolbox sequence planning (starts 0, 16, 32, 42),
            the 4 windows as one batch in one forward call, merged to (58, 20, 61, 83),
            stride 37;
        seeded7_digest.json
            per-entry SHA-256 of the seeded checkpoint (to debug a port's PRNG).
    The .npy files are numpy format, little-endian float32, 1-D:
    values = O.ravel()[::stride] with O in (B, L, 20, H, W) (or (58, 20, H, W)) order.

How to run (from the repository root; about 2 minutes and ~3 GB on 2 cores)
    /path/to/venv/bin/python train/make_parity_fixture.py [--checkpoint PATH]

Needs PyTorch and numpy (see train/README.md) and the recording in ../shared/data
(davis346/ijrr_export/images.txt and images/*.png), relative to the repository root
(override with --data).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import sys
import time
from decimal import Decimal

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
sys.path.insert(0, HERE)

from v2ce_ref import pipeline  # noqa: E402
from v2ce_ref.model import (SN_EXACT, SN_ITERATE, SN_NO_ITER, build_model,  # noqa: E402
                            set_sn_mode)
from v2ce_ref.png import read_gray8, write_gray8  # noqa: E402
from v2ce_ref.seeded import seeded_state_dict  # noqa: E402

SEED = 7
CROP_ROWS = (100, 161)   # 61 rows
CROP_COLS = (130, 213)   # 83 columns
STRIDE_FULL = 307
STRIDE_CROP = 13
STRIDE_E2E = 37
FRAMES_DESC = "first 17 APS frames of davis346"


def load_recording(data_dir):
    """The APS frames sorted by frame number, and their times in integer microseconds."""
    root = os.path.join(data_dir, "davis346", "ijrr_export")
    rows = []
    with open(os.path.join(root, "images.txt")) as f:
        for line in f:
            if line.strip():
                t, rel = line.split()
                num = int(re.search(r"(\d+)\.png$", rel).group(1))
                rows.append((num, int((Decimal(t) * 1_000_000).to_integral_value()), rel))
    rows.sort()
    assert [r[0] for r in rows] == list(range(len(rows))), "frame numbers not 0..N-1"
    frames = np.stack([read_gray8(os.path.join(root, rel)) for _, _, rel in rows])
    return frames, [t for _, t, _ in rows]


def forward_fresh(model, sd, x, mode=SN_ITERATE, trace=None):
    """Reload ``sd`` (so u / v are as stored), then one forward call of ``x``."""
    model.load_state_dict(sd, strict=True)
    model.eval()
    set_sn_mode(model, mode)
    with torch.no_grad():
        out = model(torch.from_numpy(np.ascontiguousarray(x)), trace=trace)
    set_sn_mode(model, SN_ITERATE)
    return out.numpy()


def stats(o):
    return {"max": float(o.max()), "sum": float(o.sum(dtype=np.float64)),
            "zero_fraction": float(np.count_nonzero(o == 0) / o.size)}


def save_values(out_dir, name, o, stride, meta):
    vals = np.ascontiguousarray(o.ravel()[::stride], dtype="<f4")
    np.save(os.path.join(out_dir, f"{name}_values.npy"), vals)
    meta = dict(meta, stride=stride, shape=list(o.shape), seed=SEED, count=int(vals.size),
                **stats(o))
    with open(os.path.join(out_dir, f"{name}_meta.json"), "w") as f:
        json.dump(meta, f, indent=1)
        f.write("\n")
    print(f"{name}: shape {list(o.shape)} max {meta['max']:.6g} "
          f"zeros {meta['zero_fraction']:.4f} sum {meta['sum']:.6g}", flush=True)
    return meta


def digest(sd):
    """Per-entry SHA-256 of the raw little-endian bytes, plus one over all entries."""
    total = hashlib.sha256()
    entries = []
    for k, (key, t) in enumerate(sd.items()):
        a = t.numpy()
        raw = a.astype(a.dtype.newbyteorder("<")).tobytes()
        total.update(raw)
        first = [float(v) for v in a.reshape(-1)[:3]] if a.dtype == np.float32 else [int(a)]
        entries.append({"k": k, "key": key, "shape": list(a.shape), "dtype": str(a.dtype),
                        "sha256": hashlib.sha256(raw).hexdigest(), "first": first})
    return {"seed": SEED, "rule": "train/v2ce_ref/seeded.py", "total_sha256":
            total.hexdigest(), "entries": entries}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", default="/tmp/v2ce_seeded7.pt",
                    help="where to torch.save the seeded state dict (not committed)")
    ap.add_argument("--data", default=os.path.join(REPO, "..", "shared", "data"))
    ap.add_argument("--out", default=os.path.join(REPO, "tests", "fixtures", "learned"))
    args = ap.parse_args()
    torch.manual_seed(0)
    t0 = time.time()

    frames, times = load_recording(args.data)
    assert frames.shape == (59, 260, 346), frames.shape
    crop = frames[:, CROP_ROWS[0]:CROP_ROWS[1], CROP_COLS[0]:CROP_COLS[1]]
    fdir = os.path.join(args.out, "frames_61x83")
    os.makedirs(fdir, exist_ok=True)
    for i, img in enumerate(crop):
        write_gray8(os.path.join(fdir, f"frame_{i:06d}.png"), img)
        assert np.array_equal(read_gray8(os.path.join(fdir, f"frame_{i:06d}.png")), img)
    with open(os.path.join(fdir, "times.txt"), "w") as f:
        f.writelines(f"{t / 1e6:.6f}\n" for t in times)

    sd = seeded_state_dict(SEED)
    model = build_model(sd)
    torch.save(model.state_dict(), args.checkpoint)
    reread = torch.load(args.checkpoint)
    assert list(reread) == list(sd) and all(torch.equal(reread[k], sd[k]) for k in sd)
    build_model(reread)  # strict load of what was saved
    with open(os.path.join(args.out, "seeded7_digest.json"), "w") as f:
        d = digest(sd)
        head = {k: v for k, v in d.items() if k != "entries"}
        f.write(json.dumps(head)[:-1] + ', "entries": [\n')
        f.write(",\n".join(json.dumps(e) for e in d["entries"]) + "\n]}\n")
    print(f"checkpoint {args.checkpoint} ({os.path.getsize(args.checkpoint)} bytes)", flush=True)

    norm_full = pipeline.normalize(frames)
    norm_crop = pipeline.normalize(crop)

    # Parity at 260x346 (first forward call after loading), with per-block std.
    x = pipeline.make_pairs(norm_full[:17])[None]
    trace = {}
    o = forward_fresh(model, sd, x, trace=trace)
    print("block output std (260x346):", json.dumps({k: round(v, 4) for k, v in trace.items()}))
    save_values(args.out, "parity_260x346", o, STRIDE_FULL,
                {"frames": FRAMES_DESC, "block_std": trace})
    del o

    # Parity at 61x83, and the spectral-norm alternatives.
    x = pipeline.make_pairs(norm_crop[:17])[None]
    trace = {}
    o = forward_fresh(model, sd, x, trace=trace)
    print("block output std (61x83):", json.dumps({k: round(v, 4) for k, v in trace.items()}))
    omax = float(np.abs(o).max())
    # A second call without reloading (u, v iterated twice): the statefulness itself.
    with torch.no_grad():
        o2 = model(torch.from_numpy(x)).numpy()
    alt = {"second_call_without_reload": float(np.abs(o2 - o).max() / omax)}
    print(f"second call without reload: max|O2 - O| / max|O| = "
          f"{alt['second_call_without_reload']:.4g}")
    del o2
    for name, mode in (("exact_sigma", SN_EXACT), ("stored_uv_no_iteration", SN_NO_ITER)):
        oa = forward_fresh(model, sd, x, mode=mode)
        alt[name] = float(np.abs(oa - o).max() / omax)
        print(f"SN alternative {name}: max|O_alt - O| / max|O| = {alt[name]:.4g}")
    o_parity_crop = o
    save_values(args.out, "parity_61x83", o, STRIDE_CROP,
                {"frames": "first 17 frames of frames_61x83 (davis346 crop rows 100..160, "
                 "cols 130..212)", "block_std": trace,
                 "sn_alternative_rel_max_dev": alt})

    # End to end on all 59 cropped frames: 4 windows in one batch, merged.
    n = crop.shape[0]
    starts = pipeline.plan_starts(n)
    x = pipeline.sequences(pipeline.make_pairs(norm_crop), starts)
    o = forward_fresh(model, sd, x)
    merged = pipeline.merge(o, n)
    # Window 0 has the parity_61x83 input: batching must not change it (beyond rounding).
    w0 = float(np.abs(o[0] - o_parity_crop[0]).max() / np.abs(o_parity_crop).max())
    print(f"e2e window 0 vs parity_61x83: max|diff| / max|O| = {w0:.3g}")
    save_values(args.out, "e2e_61x83", merged, STRIDE_E2E,
                {"frames": "all 59 frames of frames_61x83", "starts": starts,
                 "batch": len(starts), "window0_vs_parity_61x83_rel_max_dev": w0,
                 "merge": "all 16 intervals of windows 0..2, the "
                 f"final {(n - 1) % 16} intervals of the last window"})
    print(f"done in {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
