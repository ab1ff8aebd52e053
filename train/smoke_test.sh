#!/usr/bin/env bash
# Smoke test of train/: a tiny dataset from `v2ce dataset`, two 3-step runs with one seed that
# must give the same loss curve, an export through `v2ce model import`, and PyTorch against ONNX
# Runtime on one input. Skips, saying why, when the trainer's venv has no PyTorch (CI runs it
# only where PyTorch is already installed: it is ~5.5 GB).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
py=${V2CE_TRAIN_PYTHON:-$root/train/.venv/bin/python}
if ! "$py" -c "import torch" 2>/dev/null; then
    echo "SKIPPED train smoke test: no PyTorch at $py (python3 -m venv train/.venv && train/.venv/bin/pip install -r train/requirements.txt)"
    exit 0
fi
v2ce=${V2CE_BIN:-$root/target/release/v2ce}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$v2ce" dataset synthetic -o "$tmp/ds" --count 4 --size 48x32 --pairs 4 --seed 3
for run in a b; do
    (cd "$root/train" && "$py" -m v2ce_train.train --data "$tmp/ds" --val "$tmp/ds" \
        --out "$tmp/run_$run" --base 4 --encoders 2 --resblocks 1 --ndf 8 --steps 3 \
        --val-every 3 --ckpt-every 3 --threads 1 --seed 7)
done
# Every loss term of every step, the wall-clock column left out.
if ! cmp -s <(cut -d, -f1-7 "$tmp/run_a/loss.csv") <(cut -d, -f1-7 "$tmp/run_b/loss.csv"); then
    echo "train smoke test: the same seed gave different loss curves" >&2
    diff <(cut -d, -f1-7 "$tmp/run_a/loss.csv") <(cut -d, -f1-7 "$tmp/run_b/loss.csv") >&2 || true
    exit 1
fi
"$v2ce" model import "$tmp/run_a/best.pt" -o "$tmp/m.onnx"
(cd "$root/train" && "$py" -m v2ce_train.parity "$tmp/run_a/best.pt" "$tmp/m.onnx" --v2ce "$v2ce")
echo "train smoke test: ok"
