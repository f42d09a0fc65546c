#!/usr/bin/env bash
# matloc-match peer comparison: writes seeded 4800 x 4800 feature sets, times the tiled MNN and
# the materialised faer baseline in Rust, then torch's materialised GEMM + row/column argmax on
# the same input, and prints both times, the ratio and GFLOP/s against the SGEMM roofline.
# Needs: pip install torch numpy (falls back to numpy if torch is missing)
# Usage: bash bench/match/run.sh [N] [DIMS] [REPS]   e.g. bash bench/match/run.sh 4800 5,10,15,32,47 15
set -euo pipefail
cd "$(dirname "$0")/../.."
N="${1:-4800}"
DIMS="${2:-5,10,15,32,47}"
REPS="${3:-15}"
OUT="${MATCH_BENCH_OUT:-target-match/bench-match}"
CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-target-match}" \
    cargo run --release -q -p matloc-match --features faer --example mnn_peer -- \
    "$OUT" "$N" "$DIMS" "$REPS"
# The faer GEMM baseline needs the `faer` feature. Prefer bench/.venv (torch).
PY=python3
[ -x bench/.venv/bin/python ] && PY=bench/.venv/bin/python
"$PY" bench/match/compare.py "$OUT" 7
