#!/usr/bin/env bash
# Speed and peak memory of the learned tier's network, measured in one run: one 16-pair window
# at 346x260 and 640x480 with 1 and 2 threads, for the Rust path (`v2ce model bench`), the same
# ONNX model in onnxruntime's Python API, and the PyTorch reference (train/v2ce_ref). Each
# configuration runs in a fresh process (peak RSS is per process): one warm-up, then RUNS timed
# calls, median reported. Weights: the seeded checkpoint (speed does not depend on the values).
#
#   TORCH_PYTHON=/path/to/torch-venv/bin/python tools/bench_learned.sh [OUT.jsonl]
#
# Needs the project venv (.venv, with onnxruntime and numpy) and, for the PyTorch rows, a venv
# with torch (train/README.md); without TORCH_PYTHON those rows are skipped.
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-target/bench_learned.jsonl}"
runs="${RUNS:-2}"
work="${TMPDIR:-/tmp}/v2ce-bench-learned"
mkdir -p "$work"
cargo build --release --quiet --bin v2ce --example model_tool
model="$work/seeded7.onnx"
if [ ! -f "$model" ]; then
  target/release/examples/model_tool seeded 7 "$work/seeded7.pt"
  target/release/v2ce model import "$work/seeded7.pt" -o "$model"
  rm -f "$work/seeded7.pt"
fi
: > "$out"
for size in 346x260 640x480; do
  w="${size%x*}"; h="${size#*x}"
  for threads in 1 2; do
    target/release/v2ce model bench "$model" --size "$size" --threads "$threads" --runs "$runs" \
      | sed 's/^{/{"backend":"v2ce (Rust, ort)",/' | tee -a "$out"
    .venv/bin/python train/bench_reference.py --backend ort-python --onnx "$model" \
      --size "${h}x${w}" --threads "$threads" --runs "$runs" | tee -a "$out"
    if [ -n "${TORCH_PYTHON:-}" ]; then
      "$TORCH_PYTHON" train/bench_reference.py --backend torch \
        --size "${h}x${w}" --threads "$threads" --runs "$runs" | tee -a "$out"
    fi
  done
done
echo "results in $out"
