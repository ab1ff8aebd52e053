"""Writes a model card (Markdown) for a trained model from its run folder: the data (each
dataset's manifest and how it was made), the command, seed, hardware, wall time, the
validation scores, and the sha256 of the checkpoint and of the ONNX model.

    python train/make_card.py train/runs/small models/v2ce-small.onnx --name v2ce-small \
        --score "davis346 validation half (v2ce eval stage1 --split second)=FILE.json" ...

`--score LABEL=FILE.json` adds a row of scores from `v2ce eval stage1 --json` (or any JSON
object with tf1, tpf1, count_ratio, c_mete_us), and `--speed LABEL=FILE.json` a row from
`v2ce model bench --json`.
"""

import argparse
import csv
import hashlib
import json
import os
import platform


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def cpu():
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def labelled(items):
    out = []
    for item in items:
        label, path = item.rsplit("=", 1)
        with open(path) as f:
            out.append((label, json.load(f)))
    return out


def main():
    p = argparse.ArgumentParser()
    p.add_argument("run")
    p.add_argument("onnx")
    p.add_argument("--name", required=True)
    p.add_argument("--score", action="append", default=[])
    p.add_argument("--speed", action="append", default=[])
    p.add_argument("--note", action="append", default=[])
    a = p.parse_args()

    with open(os.path.join(a.run, "run.json")) as f:
        run = json.load(f)
    cmd_file = a.run.rstrip("/") + ".cmd"
    command = open(cmd_file).read().strip() if os.path.exists(cmd_file) else "(not recorded)"
    with open(os.path.join(a.run, "loss.csv")) as f:
        losses = list(csv.DictReader(f))
    with open(os.path.join(a.run, "val.csv")) as f:
        vals = list(csv.DictReader(f))
    steps = int(losses[-1]["step"]) if losses else 0
    seconds = float(losses[-1]["seconds"]) if losses else 0.0
    first_set = vals[0]["set"] if vals else None
    best = max((v for v in vals if v["set"] == first_set), key=lambda v: float(v["tf1"]), default=None)

    lines = [f"# Model card: {a.name}", ""]
    lines += [
        f"- **File**: `{os.path.basename(a.onnx)}` ({os.path.getsize(a.onnx) / 1e6:.2f} MB), "
        f"sha256 `{sha256(a.onnx)}`",
        f"- **Checkpoint**: `best.pt` of the run, sha256 `{sha256(os.path.join(a.run, 'best.pt'))}`; "
        f"`v2ce model import best.pt -o {os.path.basename(a.onnx)}` made the ONNX model",
        f"- **Network**: the V2CE generator with base {run['base']} channels, {run['encoders']} encoders, "
        f"{run['resblocks']} bottleneck blocks: {run['parameters']:,} trainable parameters "
        "(the released V2CE: 32, 4, 2 and 52,791,508)",
        f"- **Training**: {steps} steps of batch {run['batch']}, crops {run['crop'] or 'whole frames'}, "
        f"windows of {run['window'] or 'all'} intervals, Adam lr {run['lr']} (weight decay 1e-5), "
        f"losses STP/TP/EF/ADV/BC weighted 1000/1000/0.5/1/1"
        + (" without ADV" if run.get("no_adv") else f" (discriminator width {run['ndf']})")
        + f", seed {run['seed']}",
        f"- **Hardware**: {cpu()}, {run['threads_used']} PyTorch threads, no GPU; torch {run['torch']}",
        f"- **Wall time**: {seconds / 3600:.2f} h ({seconds:.0f} s)",
        "",
        "## Data",
        "",
    ]
    for folder in dict.fromkeys(run["data"] + run.get("val", [])):
        with open(os.path.join(folder, "dataset.json")) as f:
            m = json.load(f)
        used = "training" if folder in run["data"] else "validation"
        times = run["data"].count(folder)
        weight = f", drawn with weight {times}" if times > 1 else ""
        src = m["source"]
        if m["kind"] == "synthetic":
            how = (f"`v2ce dataset synthetic --count {src['count']} --seed {src['seed']} "
                   f"--size {m['size'][0]}x{m['size'][1]} --pairs {m['pairs']}` "
                   f"(fps {src['config']['fps'][0]:g}..{src['config']['fps'][1]:g}, ground truth at "
                   f">= {src['config']['rate_hz']:g} Hz, noise {src['config']['noise']})")
        else:
            how = (f"`v2ce dataset recording --real {src['recording']} --split {src['split']} "
                   f"--pairs {m['pairs']}` (intervals {src['intervals'][0]}..{src['intervals'][1]})")
        events = sum(s["events"] for s in m["sequences"])
        lines.append(
            f"- {used}: `{os.path.basename(folder.rstrip('/'))}`, {len(m['sequences'])} sequences of "
            f"{m['pairs']} intervals at {m['size'][0]}x{m['size'][1]}, {events:,} events{weight}: {how}"
        )
    lines += ["", "## Command", "", "From `train/`:", "", "```", command, "```", ""]
    lines += ["## Validation during training (section 6.1 F1 per sequence, voxel-mass ratio)", ""]
    if best:
        lines.append(f"Best `{first_set}` TF1 at step {best['step']} (the checkpoint shipped):")
        lines += ["", "| set | TF1 | TPF1 | RF1 | count ratio |", "|---|---:|---:|---:|---:|"]
        for v in vals:
            if v["step"] == best["step"]:
                lines.append(
                    f"| {v['set']} | {float(v['tf1']):.4f} | {float(v['tpf1']):.4f} | "
                    f"{float(v['rf1']):.4f} | {float(v['count_ratio']):.3f} |"
                )
    if a.score:
        lines += ["", "## Scored by v2ce (events through Stage 2, `v2ce eval stage1`)", "",
                  "| on | TF1 | TPF1 | count ratio | C-METE (us) |", "|---|---:|---:|---:|---:|"]
        for label, s in labelled(a.score):
            lines.append(
                f"| {label} | {s['tf1']:.4f} | {s['tpf1']:.4f} | {s['count_ratio']:.3f} | "
                f"{s.get('c_mete_us', float('nan')):,.0f} |"
            )
    if a.speed:
        lines += ["", "## Speed (`v2ce model bench`)", "", "| setting | pairs/s | peak RSS (MiB) |", "|---|---:|---:|"]
        for label, s in labelled(a.speed):
            lines.append(f"| {label} | {s['pairs_per_s']:.1f} | {s['peak_rss_mib']:.0f} |")
    if a.note:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in a.note]
    lines.append("")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
