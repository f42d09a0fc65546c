#!/usr/bin/env bash
# matloc-pnp peer comparison: writes seeded correspondence sets, solves them with matloc-pnp,
# PoseLib and OpenCV (one thread each) and prints the table recorded in docs/BENCHMARKS.md.
# Needs: pip install poselib opencv-python-headless numpy
# Usage: bash bench/pnp/run.sh [cases-per-setting] [threshold-px]
set -euo pipefail
cd "$(dirname "$0")/../.."
CASES="${1:-50}"
THRESHOLD="${2:-2.0}"
OUT="${PNP_BENCH_OUT:-target-pnp/bench-pnp}"
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-target-pnp}" \
    cargo run --release -q -p matloc-pnp --example pnp_peer -- "$OUT" "$CASES" "$THRESHOLD"
python3 bench/pnp/compare.py "$OUT"
