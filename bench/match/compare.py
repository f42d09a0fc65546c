"""matloc-match peer comparison: torch (CPU) materialised GEMM + row/column argmax MNN on the
inputs `mnn_peer` wrote, next to the Rust timings it recorded.

Usage: python3 bench/match/compare.py OUT_DIR [REPS]
"""
import json
import sys
import time

import numpy as np

ROOF_GFLOPS_PER_CORE = 88.0  # per core: OpenBLAS SGEMM 2048^3 measured on this machine type


def main():
    out = sys.argv[1]
    reps = int(sys.argv[2]) if len(sys.argv) > 2 else 7
    rust = json.load(open(f"{out}/rust.json"))
    try:
        import torch

        backend = f"torch {torch.__version__}"
    except ImportError:  # fall back to numpy (still materialised GEMM + argmax)
        torch = None
        backend = f"numpy {np.__version__}"
    threads = rust[0]["threads"]
    if torch is not None:
        torch.set_num_threads(threads)
    roof = ROOF_GFLOPS_PER_CORE * threads
    print(f"peer: {backend}, {threads} threads; roofline {roof:.0f} GFLOP/s ({threads} x {ROOF_GFLOPS_PER_CORE})")
    print(f"{'D':>3} {'N':>5} | {'rust tiled ms':>13} {'GFLOP/s':>8} {'% roof':>6} | {'rust+2nd ms':>11} | {'faer mat. ms':>12} | {'peer ms':>8} | {'peer/tiled':>10} | {'MNN rust':>8} {'MNN peer':>8}")
    for r in rust:
        d, n = r["d"], r["n"]
        q = np.load(f"{out}/query_{d}.npy")
        m = np.load(f"{out}/map_{d}.npy")
        if torch is not None:
            qt, mt = torch.from_numpy(q), torch.from_numpy(m)

            def mnn():
                s = qt @ mt.T
                row = s.argmax(dim=1)
                col = s.argmax(dim=0)
                ar = torch.arange(s.shape[0])
                keep = col[row] == ar
                return ar[keep].numpy(), row[keep].numpy()
        else:

            def mnn():
                s = q @ m.T
                row = s.argmax(axis=1)
                col = s.argmax(axis=0)
                ar = np.arange(s.shape[0])
                keep = col[row] == ar
                return ar[keep], row[keep]

        mnn()
        ts = []
        for _ in range(reps):
            t0 = time.perf_counter()
            qi, mi = mnn()
            ts.append((time.perf_counter() - t0) * 1e3)
        peer = float(np.median(ts))
        tiled = r["tiled_ms"]
        gf = 2.0 * n * n * d / (tiled * 1e-3) / 1e9
        first = [[int(a), int(b)] for a, b in zip(qi[:20], mi[:20])]
        agree = "" if first == r["mnn_pairs"] else "  (first pairs differ!)"
        print(f"{d:>3} {n:>5} | {tiled:>13.2f} {gf:>8.1f} {100 * gf / roof:>5.0f}% | {r['tiled_second_ms']:>11.2f} | {r['faer_ms']:>12.2f} | {peer:>8.2f} | {peer / tiled:>9.1f}x | {r['mnn_matches']:>8} {len(qi):>8}{agree}")


if __name__ == "__main__":
    main()
