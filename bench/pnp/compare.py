#!/usr/bin/env python3
"""Peer comparison for matloc-pnp: PoseLib and OpenCV on the correspondence sets written by
`cargo run --release -p matloc-pnp --example pnp_peer`, same inlier threshold for everyone.

Usage: python3 bench/pnp/compare.py <out-dir>   (reads cases.json and ours.json)

Success: translation error <= 0.1 m and rotation error <= 0.1 deg (camera centres; geodesic
angle of R_est R_gt^T). Timings are wall-clock per solve, one thread per solver; ours and
PoseLib take the best of 3 identical solves per case, OpenCV (far slower) one solve.
"""
import json
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import poselib  # noqa: E402

cv2.setNumThreads(1)

T_MAX_M = 0.1
R_MAX_DEG = 0.1
OPENCV_MAX_ITERS = 10000
CONFIDENCE = 0.9999
# PoseLib with our termination rule (its defaults: min 1000 iterations, 3x the RANSAC count).
MATCHED = {"min_iterations": 50, "dyn_num_trials_mult": 1.0}


def errors(R, t, R_gt, t_gt):
    c = -R.T @ t
    c_gt = -R_gt.T @ t_gt
    t_err = float(np.linalg.norm(c - c_gt))
    cos = (np.trace(R @ R_gt.T) - 1.0) / 2.0
    r_err = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return t_err, r_err


def run_poselib(case, pixels, points, threshold, extra=None):
    cam = case["camera"]
    camera = {
        "model": "PINHOLE",
        "width": cam["width"],
        "height": cam["height"],
        "params": [cam["fx"], cam["fy"], cam["cx"], cam["cy"]],
    }
    ransac_opt = {"max_reproj_error": threshold}
    ransac_opt.update(extra or {})
    # Best of 3 identical solves (fixed seed), as the Rust side does: the machine is shared.
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        pose, _info = poselib.estimate_absolute_pose(pixels, points, camera, ransac_opt, {})
        best = min(best, time.perf_counter() - start)
    return best, np.asarray(pose.R), np.asarray(pose.t)


def run_opencv(case, pixels, points, threshold, flag):
    cam = case["camera"]
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    start = time.perf_counter()
    ok, rvec, tvec, _inl = cv2.solvePnPRansac(
        points,
        pixels,
        K,
        None,
        iterationsCount=OPENCV_MAX_ITERS,
        reprojectionError=threshold,
        confidence=CONFIDENCE,
        flags=flag,
    )
    seconds = time.perf_counter() - start
    if not ok:
        return seconds, None, None
    R, _ = cv2.Rodrigues(rvec)
    return seconds, R, tvec.reshape(3)


def summarise(times, errs):
    t = np.array([e[0] if e is not None else np.inf for e in errs])
    r = np.array([e[1] if e is not None else np.inf for e in errs])
    success = float(np.mean((t <= T_MAX_M) & (r <= R_MAX_DEG)))
    # Gross failures only: a loose criterion separates wrong poses from noise-floor misses.
    success_loose = float(np.mean((t <= 1.0) & (r <= 1.0)))
    return {
        "success_loose": success_loose,
        "time_ms": 1e3 * float(np.median(times)),
        "success": success,
        "t_med_m": float(np.median(t)),
        "r_med_deg": float(np.median(r)),
    }


def main():
    out_dir = sys.argv[1] if len(sys.argv) > 1 else "bench/pnp/out"
    with open(os.path.join(out_dir, "cases.json")) as f:
        cases_doc = json.load(f)
    with open(os.path.join(out_dir, "ours.json")) as f:
        ours_doc = json.load(f)
    threshold = cases_doc["threshold_px"]
    ours_by_name = {s["name"]: s["results"] for s in ours_doc["settings"]}

    rows = []
    for setting in cases_doc["settings"]:
        name = setting["name"]
        ours = ours_by_name[name]
        peers = {
            "poselib": ([], []),
            "poselib_matched": ([], []),
            "opencv_p3p": ([], []),
            "opencv_sqpnp": ([], []),
        }
        for case in setting["cases"]:
            pixels = np.ascontiguousarray(case["pixels"], dtype=np.float64)
            points = np.ascontiguousarray(case["points"], dtype=np.float64)
            R_gt = np.array(case["gt_R"])
            t_gt = np.array(case["gt_t"])
            runs = {
                "poselib": run_poselib(case, pixels, points, threshold),
                "poselib_matched": run_poselib(case, pixels, points, threshold, MATCHED),
                "opencv_p3p": run_opencv(case, pixels, points, threshold, cv2.SOLVEPNP_P3P),
                "opencv_sqpnp": run_opencv(case, pixels, points, threshold, cv2.SOLVEPNP_SQPNP),
            }
            for key, (seconds, R, t) in runs.items():
                peers[key][0].append(seconds)
                peers[key][1].append(None if R is None else errors(R, t, R_gt, t_gt))
        our_times = [r["time_s"] for r in ours]
        our_errs = [
            None if r["t_err_m"] is None else (r["t_err_m"], r["r_err_deg"]) for r in ours
        ]
        row = {"name": name, "cases": len(ours), "ours": summarise(our_times, our_errs)}
        for key, (times, errs) in peers.items():
            row[key] = summarise(times, errs)
        rows.append(row)

    print(f"threshold {threshold} px, 1 px noise, success = t <= {T_MAX_M} m and r <= {R_MAX_DEG} deg")
    print(
        "PoseLib = defaults (min_iterations 1000, dyn_num_trials_mult 3); PoseLib-m = "
        "min_iterations 50, dyn_num_trials_mult 1 (our termination rule)"
    )
    keys = ["ours", "poselib", "poselib_matched", "opencv_p3p", "opencv_sqpnp"]
    names = "ours / PoseLib / PoseLib-m / CV-P3P / CV-SQPnP"
    print(
        f"| setting | cases | median ms: {names} | ours/PoseLib | ours/PoseLib-m "
        f"| success: {names} | success at 1 m / 1 deg: {names} "
        f"| median t (cm): {names} | median r (deg): {names} |"
    )
    print("|" + "---|" * 9)
    for row in rows:
        ratio = row["ours"]["time_ms"] / row["poselib"]["time_ms"]
        ratio_m = row["ours"]["time_ms"] / row["poselib_matched"]["time_ms"]
        times = " / ".join(f"{row[k]['time_ms']:.2f}" for k in keys)
        succ = " / ".join(f"{100 * row[k]['success']:.0f}" for k in keys)
        loose = " / ".join(f"{100 * row[k]['success_loose']:.0f}" for k in keys)
        tmed = " / ".join(f"{100 * row[k]['t_med_m']:.1f}" for k in keys)
        rmed = " / ".join(f"{row[k]['r_med_deg']:.3f}" for k in keys)
        print(
            f"| {row['name']} | {row['cases']} | {times} | {ratio:.2f} | {ratio_m:.2f} "
            f"| {succ} | {loose} | {tmed} | {rmed} |"
        )
    with open(os.path.join(out_dir, "summary.json"), "w") as f:
        json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
