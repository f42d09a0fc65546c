#!/usr/bin/env bash
# Trains the Rust field and the PyTorch-CPU reference for the same number of steps on the same
# dataset (batch 4096, 48 samples per ray) and prints rays/s of each and the ratio.
# usage: bench/nerf/run.sh [DATA=data/tiny] [STEPS=20] [THREADS=all cores]
# THREADS=1 compares single-threaded runs (no thread-synchronisation cost in either CPU time).
# On a shared machine the torch figure moves a lot with the other load (430-1440 rays per
# CPU-second on 2026-12-01), so repeat runs and note the load average.
# Needs bench/.venv with torch (python3 -m venv bench/.venv && bench/.venv/bin/pip install torch numpy pillow).
set -euo pipefail
cd "$(dirname "$0")/../.."
DATA=${1:-data/tiny}
STEPS=${2:-20}
THREADS=${3:-$(nproc)}
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
cargo build --release -q -p matloc-render --example nerf_throughput
OUT=$(mktemp)
RAYON_NUM_THREADS=$THREADS "$CARGO_TARGET_DIR/release/examples/nerf_throughput" "$DATA" "$STEPS" uniform48 > "$OUT"
bench/.venv/bin/python bench/nerf/torch_ref.py --data "$DATA" --steps "$STEPS" --threads "$THREADS" --rust-json "$OUT"
rm -f "$OUT"
