"""Trains the V2CE generator on ``v2ce dataset`` folders.

    python -m v2ce_train.train --data DS [--data DS2] --val VAL --out RUN \
        --base 8 --encoders 4 --resblocks 2 --steps 2000 --seed 1234

Writes to RUN: ``loss.csv`` (every step's loss terms), ``val.csv`` (validation scores),
``last.pt`` (everything needed to resume: models, optimisers, random states), ``best.pt``
(the generator with the best validation TF1, in the toolbox's state-dict format, which
``v2ce model import`` reads) and ``run.json`` (the settings). The same seed, settings, data and
thread count give the same loss curve on the CPU.
"""

import argparse
import csv
import json
import os
import time

import numpy as np
import torch

from . import losses
from .data import Sequences
from .model import generator, parameter_count, toolbox_state_dict


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", action="append", required=True, help="a dataset folder (repeatable)")
    p.add_argument(
        "--val",
        action="append",
        default=[],
        help="a validation dataset folder (repeatable: each is scored and logged; the first picks best.pt)",
    )
    p.add_argument("--out", required=True, help="the run's folder")
    p.add_argument("--base", type=int, default=32, help="channels after the head (32: V2CE)")
    p.add_argument("--encoders", type=int, default=4)
    p.add_argument("--resblocks", type=int, default=2)
    p.add_argument("--ndf", type=int, default=64, help="the discriminator's first width")
    p.add_argument("--no-adv", action="store_true", help="train without the adversarial loss")
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--batch", type=int, default=2)
    p.add_argument("--crop", default="", help="HxW random crops (default: whole frames)")
    p.add_argument("--window", type=int, default=0, help="intervals per sample (0: all)")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=1234)
    p.add_argument("--threads", type=int, default=0, help="CPU threads (0: PyTorch's choice)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--val-every", type=int, default=200)
    p.add_argument("--ckpt-every", type=int, default=200)
    p.add_argument("--resume", action="store_true", help="continue from RUN/last.pt")
    return p.parse_args(argv)


def validate(model, val, device):
    """TF1, TPF1, RF1 (section 6.1, per sequence, averaged) and the voxel-mass ratio."""
    model.eval()
    scores = {"tf1": [], "tpf1": [], "rf1": []}
    mass_p = mass_g = 0.0
    with torch.no_grad():
        for k in range(len(val)):
            x, y = val.whole(k)
            p = model(x.to(device)).cpu()
            scores["tf1"].append(losses.f1(p, y, "sum_c"))
            scores["tpf1"].append(losses.f1(p, y, "sum_cp"))
            scores["rf1"].append(losses.f1(p, y, "raw"))
            mass_p += float(p.sum())
            mass_g += float(y.sum())
    model.train()
    out = {k: float(np.mean(v)) for k, v in scores.items()}
    out["count_ratio"] = mass_p / mass_g if mass_g > 0 else float("nan")
    return out


def main(argv=None):
    a = parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    if a.threads > 0:
        torch.set_num_threads(a.threads)
    torch.manual_seed(a.seed)
    torch.use_deterministic_algorithms(True)
    rng = np.random.default_rng(a.seed)
    device = torch.device(a.device)
    crop = tuple(int(v) for v in a.crop.lower().split("x")) if a.crop else None
    window = a.window or None

    data = Sequences(a.data)
    vals = [(os.path.basename(os.path.normpath(v)), Sequences([v])) for v in a.val]
    model = generator(a.base, a.encoders, a.resblocks).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=a.lr, betas=(0.9, 0.999), weight_decay=1e-5)
    adversarial = None if a.no_adv else losses.Adversarial(a.ndf, 3, device)
    step, best = 0, -1.0
    last = os.path.join(a.out, "last.pt")
    if a.resume and os.path.exists(last):
        state = torch.load(last, weights_only=False)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["opt"])
        if adversarial is not None and state.get("disc"):
            adversarial.disc.load_state_dict(state["disc"])
            adversarial.opt.load_state_dict(state["opt_d"])
        torch.set_rng_state(state["torch_rng"])
        rng.bit_generator.state = state["numpy_rng"]
        step, best = state["step"], state["best"]
    settings = vars(a) | {
        "parameters": parameter_count(model),
        "sequences": len(data),
        "torch": torch.__version__,
        "threads_used": torch.get_num_threads(),
    }
    with open(os.path.join(a.out, "run.json"), "w") as f:
        json.dump(settings, f, indent=2)
    print(f"v2ce_train: {parameter_count(model):,} parameters, {len(data)} sequences, from step {step}", flush=True)

    loss_file = open(os.path.join(a.out, "loss.csv"), "a", newline="")
    loss_log = csv.writer(loss_file)
    if step == 0:
        loss_log.writerow(["step", "total", "stp", "tp", "ef", "adv", "bc", "seconds"])
    val_file = open(os.path.join(a.out, "val.csv"), "a", newline="")
    val_log = csv.writer(val_file)
    if step == 0:
        val_log.writerow(["step", "set", "tf1", "tpf1", "rf1", "count_ratio"])
    started = time.time()
    model.train()
    while step < a.steps:
        x, y = data.sample(rng, a.batch, crop, window)
        x, y = x.to(device), y.to(device)
        pred = model(x)
        total, terms = losses.total_loss(pred, y, adversarial)
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
        step += 1
        loss_log.writerow(
            [step, f"{float(total.detach()):.6g}"]
            + [f"{terms.get(k, 0.0):.6g}" for k in ("stp", "tp", "ef", "adv", "bc")]
            + [f"{time.time() - started:.1f}"]
        )
        if not np.isfinite(float(total.detach())):
            raise SystemExit(f"v2ce_train: the loss is {float(total.detach())} at step {step}")
        if vals and (step % a.val_every == 0 or step == a.steps):
            for i, (name, val) in enumerate(vals):
                s = validate(model, val, device)
                val_log.writerow([step, name] + [f"{s[k]:.5f}" for k in ("tf1", "tpf1", "rf1", "count_ratio")])
                print(f"step {step}: loss {float(total.detach()):.4g}, {name} TF1 {s['tf1']:.4f} ratio {s['count_ratio']:.3f}", flush=True)
                if i == 0 and s["tf1"] > best:
                    best = s["tf1"]
                    torch.save(toolbox_state_dict(model), os.path.join(a.out, "best.pt"))
            val_file.flush()
        if step % a.ckpt_every == 0 or step == a.steps:
            loss_file.flush()
            torch.save(
                {
                    "step": step,
                    "best": best,
                    "model": model.state_dict(),
                    "opt": opt.state_dict(),
                    "disc": adversarial.disc.state_dict() if adversarial else None,
                    "opt_d": adversarial.opt.state_dict() if adversarial else None,
                    "torch_rng": torch.get_rng_state(),
                    "numpy_rng": rng.bit_generator.state,
                },
                last + ".partial",
            )
            os.replace(last + ".partial", last)
    if not vals:
        torch.save(toolbox_state_dict(model), os.path.join(a.out, "best.pt"))
    loss_file.close()
    val_file.close()


if __name__ == "__main__":
    main()
