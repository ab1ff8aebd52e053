#!/usr/bin/env bash
# Re-runs the first N steps (default 30) of the training command on models/v2ce-small.md and
# compares every loss term of every step with the curve the shipped model was trained with
# (models/v2ce-small.loss.csv, its first 200 steps). DATA is a folder holding the card's four
# datasets (syn_train, syn_val, davis_train, davis_val), made by the `v2ce dataset` commands the
# card lists. Needs the trainer's venv (train/.venv with PyTorch); about 1 s per step on 2 cores.
#
#     train/card_check.sh DATA [N]
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
data=${1:?usage: train/card_check.sh DATA [STEPS]}
steps=${2:-30}
data=$(cd "$data" && pwd)
py=${V2CE_TRAIN_PYTHON:-$root/train/.venv/bin/python}
reference=$root/models/v2ce-small.loss.csv
if [ "$steps" -gt 200 ]; then
    echo "card check: the reference curve has 200 steps" >&2
    exit 2
fi
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
# The card's command: syn_train once and davis_train 20 times (its weight), as on the card.
args=(--data "$data/syn_train")
for _ in $(seq 20); do args+=(--data "$data/davis_train"); done
(cd "$root/train" && "$py" -u -m v2ce_train.train "${args[@]}" \
    --val "$data/syn_val" --val "$data/davis_val" --out "$tmp/run" \
    --base 4 --encoders 4 --resblocks 2 --ndf 16 --steps "$steps" --batch 2 --crop 96x128 \
    --window 8 --threads 2 --seed 1234 --val-every 100000 --ckpt-every 100000)
want=$(head -n $((steps + 1)) "$reference")
got=$(cut -d, -f1-7 "$tmp/run/loss.csv" | head -n $((steps + 1)))
if [ "$want" != "$got" ]; then
    echo "card check: the loss curve differs from the shipped model's:" >&2
    diff <(echo "$want") <(echo "$got") | head -20 >&2
    exit 1
fi
echo "card check: $steps steps identical to the shipped model's loss curve"
