"""The outside benchmark's driver: path-traced scenes (Blender Cycles), maps built by `matloc`,
every method and the COLMAP peer on three query sets, one table.

    python bench/outside/outside.py all   [--work DIR] [--scenes rubble,town] [--width 320 --height 240]
    python bench/outside/outside.py all   --scenes rubble,rubble-gps,rubble-gps-refined
                                          # + the survey with GPS-level pose noise, as given / refined
    python bench/outside/outside.py table [--work DIR]
    python bench/outside/outside.py smoke --out DIR      # the CI fixture (160x120, a handful of images)

`bench/outside/run.sh` installs what this needs and runs `all`. Every step is skipped when its
output exists, so an interrupted run resumes; delete WORK/<scene> to start a scene afresh.
"""

import argparse
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from colmap_peer import (  # noqa: E402  (the peer's pose helpers, shared)
    cam_from_world_from_opengl,
    camera_center,
    mat_mul,
    mat_t,
    rot_from_quat,
    rotation_angle_deg,
)
ROOT = os.path.dirname(os.path.dirname(HERE))
SETS = ["same", "second", "novel"]
METHODS = ["structure", "matloc", "rgb-keypoints"]
THRESHOLDS = [(0.25, 2.0), (0.5, 5.0), (5.0, 10.0)]
# A `<scene>-gps` variant: the scene's survey with its training poses as a GPS/IMU gives them,
# each camera centre moved by a random vector and its attitude turned about a random axis,
# with these root-mean-square sizes (metres, degrees); images and queries are the scene's own.
GPS_SUFFIX = "-gps"
GPS_NOISE = (0.3, 1.0)
GPS_SEED = 7
# `<scene>-gps-refined`: the same noisy survey, its poses refined by `matloc dataset
# refine-poses` before the map is built (the peer gets the noisy poses, as in `-gps`).
REFINED_SUFFIX = "-gps-refined"


def variant_base(scene):
    """The scene a GPS variant is made from (`None` for a scene of its own)."""
    for suffix in (REFINED_SUFFIX, GPS_SUFFIX):
        if scene.endswith(suffix):
            return scene[: -len(suffix)]
    return None


def log(msg):
    print(f"[outside] {msg}", file=sys.stderr, flush=True)


def run(cmd, **kw):
    """Runs `cmd`; returns (wall seconds, CPU seconds of the child)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.time()
    log(" ".join(str(c) for c in cmd))
    subprocess.run([str(c) for c in cmd], check=True, **kw)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return time.time() - t, cpu


def write_json(path, doc):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(doc, f, indent=1)
    os.replace(tmp, path)


def render(scene, out, width, height, samples, smoke=False):
    cmd = ["blender", "-b", "--factory-startup", "--python", os.path.join(HERE, "scene.py"), "--"]
    cmd += ["--scene", scene, "--out", out, "--width", width, "--height", height, "--samples", samples]
    if smoke:
        cmd.append("--smoke")
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with open(out + ".render.log", "w") as logf:
        run(cmd, stdout=logf, stderr=subprocess.STDOUT)


def rotation_about(axis_angle):
    """Rotation matrix of a rotation vector (radians), Rodrigues' formula."""
    theta = math.sqrt(sum(a * a for a in axis_angle))
    if theta < 1e-12:
        return [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    x, y, z = (a / theta for a in axis_angle)
    c, s, v = math.cos(theta), math.sin(theta), 1.0 - math.cos(theta)
    return [
        [c + x * x * v, x * y * v - z * s, x * z * v + y * s],
        [y * x * v + z * s, c + y * y * v, y * z * v - x * s],
        [z * x * v - y * s, z * y * v + x * s, c + z * z * v],
    ]


def noisy_transform(m, rng, noise_m, noise_deg):
    """`m` (4x4 camera-to-world) with its centre moved and its attitude turned in the world
    frame: each axis drawn from N(0, size / sqrt 3), so the sizes are the RMS of the whole."""
    dt = [rng.gauss(0.0, noise_m / math.sqrt(3.0)) for _ in range(3)]
    dr = rotation_about([math.radians(rng.gauss(0.0, noise_deg / math.sqrt(3.0))) for _ in range(3)])
    r = [row[:3] for row in m[:3]]
    r2 = mat_mul(dr, r)
    return [r2[i] + [m[i][3] + dt[i]] for i in range(3)] + [list(m[3])]


def make_gps_variant(work, scene, d):
    """WORK/<base>-gps: the base scene's images and queries (links) and its survey poses with
    GPS-level noise ([`GPS_NOISE`]); scene.json records the noise and the applied offsets."""
    import random

    base = os.path.join(work, variant_base(scene))
    if not os.path.exists(os.path.join(base, "queries", "second", "transforms_test.json")):
        raise SystemExit(f"{scene}: render its base scene first (--scenes {os.path.basename(base)},{scene})")
    shutil.rmtree(d, ignore_errors=True)
    os.makedirs(os.path.join(d, "survey"))
    for link in ["queries", "raw_second", os.path.join("survey", "images")]:
        at = os.path.join(d, link)
        os.symlink(os.path.relpath(os.path.join(base, link), os.path.dirname(at)), at)
    with open(os.path.join(base, "survey", "transforms_train.json")) as f:
        doc = json.load(f)
    rng = random.Random(GPS_SEED)
    moved, turned = [], []
    for fr in doc["frames"]:
        m = fr["transform_matrix"]
        n = noisy_transform(m, rng, *GPS_NOISE)
        moved.append(math.dist([row[3] for row in m[:3]], [row[3] for row in n[:3]]))
        rel = mat_mul(mat_t([row[:3] for row in n[:3]]), [row[:3] for row in m[:3]])
        turned.append(math.degrees(math.acos(max(-1.0, min(1.0, (rel[0][0] + rel[1][1] + rel[2][2] - 1.0) / 2.0)))))
        fr["transform_matrix"] = n
    write_json(os.path.join(d, "survey", "transforms_train.json"), doc)
    with open(os.path.join(base, "scene.json")) as f:
        sc = json.load(f)
    sc["variant"] = {
        "of": os.path.basename(base),
        "pose_noise_rms_m": GPS_NOISE[0],
        "pose_noise_rms_deg": GPS_NOISE[1],
        "seed": GPS_SEED,
        "moved_m": {"median": median(moved), "max": max(moved)},
        "turned_deg": {"median": median(turned), "max": max(turned)},
    }
    sc["total_seconds"] = 0.0  # nothing rendered: the base scene's images
    write_json(os.path.join(d, "scene.json"), sc)
    log(f"{scene}: survey poses moved {median(moved):.2f} m and turned {median(turned):.2f}° (median)")


# --------------------------------------------------------------------------------------------
# Poses and errors


def gt_from_transform(m):
    """(R_cam_from_world, camera centre) from an OpenGL camera-to-world 4x4."""
    r, t = cam_from_world_from_opengl(m)
    return r, camera_center(r, t)


def pose_errors(qvec, tvec, gt):
    """Translation (camera centres, m) and rotation (degrees) errors of a COLMAP pose."""
    r_est = rot_from_quat(qvec)
    r_gt, c_gt = gt
    t_err = math.dist(camera_center(r_est, tvec), c_gt)
    return t_err, rotation_angle_deg(mat_mul(r_est, mat_t(r_gt)))


def query_truth(query_dir):
    with open(os.path.join(query_dir, "transforms_test.json")) as f:
        doc = json.load(f)
    return {fr["file_path"]: gt_from_transform(fr["transform_matrix"]) for fr in doc["frames"]}


# --------------------------------------------------------------------------------------------
# Methods


def eval_method(bin_path, scene_dir, qset, method, overhead_cpu):
    out = os.path.join(scene_dir, "eval", qset, method)
    done = os.path.join(out, "run.json")
    if os.path.exists(done):
        return
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(os.path.dirname(out), exist_ok=True)
    wall, cpu = run(
        [bin_path, "--quiet", "eval", "--map", os.path.join(scene_dir, "map"), "--data",
         os.path.join(scene_dir, "queries", qset), "--methods", method, "--out", out],
    )
    n = sum(1 for _ in open(os.path.join(out, "results.jsonl")))
    write_json(done, {"wall_seconds": wall, "cpu_seconds": cpu, "queries": n,
                      "overhead_cpu_seconds": overhead_cpu})


def eval_overhead(bin_path, scene_dir, method):
    """CPU seconds of an eval run beyond its queries (map loading, report, plots): one query."""
    path = os.path.join(scene_dir, "eval", f"overhead-{method}.json")
    if os.path.exists(path):
        with open(path) as f:
            return json.load(f)["cpu_seconds"]
    out = os.path.join(scene_dir, "eval", f"overhead-{method}")
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(os.path.dirname(out), exist_ok=True)
    _, cpu = run([bin_path, "--quiet", "eval", "--map", os.path.join(scene_dir, "map"), "--data",
                  os.path.join(scene_dir, "queries", "same"), "--methods", method, "--queries", "1",
                  "--out", out])
    with open(os.path.join(out, "results.jsonl")) as f:
        one = json.loads(f.readline())
    fixed = max(0.0, cpu - one.get("total_seconds", 0.0))
    write_json(path, {"cpu_seconds": fixed, "one_query_cpu_seconds": cpu})
    return fixed


def method_rows(scene_dir, qset, method):
    out = os.path.join(scene_dir, "eval", qset, method)
    with open(os.path.join(out, "run.json")) as f:
        run_info = json.load(f)
    truth = query_truth(os.path.join(scene_dir, "queries", qset))
    errors = []
    seconds = []
    for line in open(os.path.join(out, "results.jsonl")):
        r = json.loads(line)
        seconds.append(r.get("total_seconds", float("nan")))
        name = os.path.relpath(r["name"], os.path.join(scene_dir, "queries", qset)) if os.path.isabs(r["name"]) else r["name"]
        if r.get("localized") and r.get("qvec_wxyz"):
            errors.append(pose_errors(r["qvec_wxyz"], r["tvec"], truth[name]))
        else:
            errors.append(None)
    cpu = (run_info["cpu_seconds"] - run_info["overhead_cpu_seconds"]) / max(1, run_info["queries"])
    return errors, sum(seconds) / max(1, len(seconds)), cpu


def peer_rows(scene_dir, qset):
    path = os.path.join(scene_dir, "colmap", f"{qset}.json")
    with open(path) as f:
        doc = json.load(f)
    truth = query_truth(os.path.join(scene_dir, "queries", qset))
    errors = []
    for q in doc["queries"]:
        if q["registered"]:
            errors.append(pose_errors(q["qvec_wxyz"], q["tvec"], truth[q["name"]]))
        else:
            errors.append(None)
    n = max(1, len(errors))
    return errors, doc["query_wall_seconds"] / n, doc["cpu_seconds_per_query"], doc


def run_peer(scene_dir, qset):
    path = os.path.join(scene_dir, "colmap", f"{qset}.json")
    if os.path.exists(path):
        return
    os.makedirs(os.path.dirname(path), exist_ok=True)
    run([sys.executable, os.path.join(HERE, "colmap_peer.py"), "--survey", os.path.join(scene_dir, "survey"),
         "--queries", os.path.join(scene_dir, "queries", qset), "--work", os.path.join(scene_dir, "colmap", "work"),
         "--out", path])


# --------------------------------------------------------------------------------------------
# The table


def median(v):
    s = sorted(v)
    if not s:
        return float("nan")
    m = len(s) // 2
    return s[m] if len(s) % 2 else 0.5 * (s[m - 1] + s[m])


def summarize(errors):
    n = len(errors)
    inf = (float("inf"), float("inf"))
    full = [e if e is not None else inf for e in errors]
    accepted = [e for e in errors if e is not None]
    row = {
        "queries": n,
        "recall": [sum(1 for t, r in full if t <= tt and r <= rr) / n for tt, rr in THRESHOLDS],
        "median_t": median([t for t, _ in full]),
        "median_r": median([r for _, r in full]),
        "refused": (n - len(accepted)) / n,
        "false_accepts": sum(1 for t, r in accepted if t > 5.0 or r > 10.0) / n,
        "beyond_1m_5deg": sum(1 for t, r in accepted if t > 1.0 or r > 5.0) / n,
    }
    return row


def fmt_len(m):
    if math.isinf(m):
        return "∞"
    return f"{m * 100:.1f} cm" if m < 1 else f"{m:.2f} m"


def fmt_deg(d):
    return "∞" if math.isinf(d) else f"{d:.2f}°"


def table(work, scenes):
    lines = [
        "| scene | query set | method | recall 0.25 m, 2° | 0.5 m, 5° | 5 m, 10° | median t / r | refused | false accepts | beyond 1 m / 5° | s/query | CPU-s/query |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for scene in scenes:
        scene_dir = os.path.join(work, scene)
        for qset in SETS:
            if not os.path.exists(os.path.join(scene_dir, "queries", qset)):
                continue
            rows = []
            for method in METHODS:
                if os.path.exists(os.path.join(scene_dir, "eval", qset, method, "run.json")):
                    errors, s, cpu = method_rows(scene_dir, qset, method)
                    rows.append((f"`{method}`", errors, s, cpu))
            if os.path.exists(os.path.join(scene_dir, "colmap", f"{qset}.json")):
                errors, s, cpu, _ = peer_rows(scene_dir, qset)
                rows.append(("COLMAP (peer)", errors, s, cpu))
            for name, errors, s, cpu in rows:
                r = summarize(errors)
                lines.append(
                    f"| {scene} | {qset} | {name} | {r['recall'][0]:.2f} | {r['recall'][1]:.2f} | {r['recall'][2]:.2f} | "
                    f"{fmt_len(r['median_t'])} / {fmt_deg(r['median_r'])} | {100 * r['refused']:.0f} % | "
                    f"{100 * r['false_accepts']:.0f} % | {100 * r['beyond_1m_5deg']:.0f} % | {s:.3f} | {cpu:.2f} |"
                )
    return "\n".join(lines)


def diagnostics(work, scenes):
    """Where each query set is lost: the place predictor's first hypothesis (distance of its
    coarse pose to the true camera, share within 5 m) and the accepted poses' PnP inliers."""
    lines = [
        "| scene | query set | method | first hypothesis: median distance | within 5 m | median inliers (accepted) | median inliers (COLMAP) |",
        "|---|---|---|---|---|---|---|",
    ]
    for scene in scenes:
        scene_dir = os.path.join(work, scene)
        for qset in SETS:
            peer = os.path.join(scene_dir, "colmap", f"{qset}.json")
            peer_inl = "–"
            if os.path.exists(peer):
                with open(peer) as f:
                    inl = [q["inliers"] for q in json.load(f)["queries"] if q["registered"]]
                peer_inl = f"{median(inl):.0f}" if inl else "–"
            for method in METHODS:
                res = os.path.join(scene_dir, "eval", qset, method, "results.jsonl")
                if not os.path.exists(res):
                    continue
                truth = query_truth(os.path.join(scene_dir, "queries", qset))
                first, inliers = [], []
                for line in open(res):
                    r = json.loads(line)
                    hyps = r.get("hypotheses") or []
                    if hyps:
                        t, _ = pose_errors(hyps[0]["coarse_qvec_wxyz"], hyps[0]["coarse_tvec"], truth[r["name"]])
                        first.append(t)
                    if r.get("localized"):
                        inliers.append(r.get("inliers", 0))
                within = sum(1 for d in first if d <= 5.0) / max(1, len(first))
                lines.append(
                    f"| {scene} | {qset} | `{method}` | {median(first):.1f} m | {100 * within:.0f} % | "
                    f"{median(inliers) if inliers else float('nan'):.0f} | {peer_inl} |"
                )
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------


def costs(work, scenes):
    """What making each scene's map and the peer's model cost."""
    lines = [
        "| scene | survey images | render (s, all sets) | `matloc map build` wall / CPU s | map size | COLMAP survey CPU s | COLMAP points |",
        "|---|---|---|---|---|---|---|",
    ]
    for scene in scenes:
        d = os.path.join(work, scene)
        if not os.path.exists(os.path.join(d, "scene.json")):
            continue
        with open(os.path.join(d, "scene.json")) as f:
            sc = json.load(f)
        build = {"wall_seconds": float("nan"), "cpu_seconds": float("nan")}
        if os.path.exists(os.path.join(d, "map-build.json")):
            with open(os.path.join(d, "map-build.json")) as f:
                build = json.load(f)
        size = sum(os.path.getsize(os.path.join(r, n)) for r, _, ns in os.walk(os.path.join(d, "map")) for n in ns)
        survey = {}
        for qset in SETS:
            p = os.path.join(d, "colmap", f"{qset}.json")
            if os.path.exists(p):
                with open(p) as f:
                    survey = json.load(f)["survey"]
                break
        lines.append(
            f"| {scene} | {sc['survey_images']} | {sc['total_seconds']:.0f} | {build['wall_seconds']:.0f} / "
            f"{build['cpu_seconds']:.0f} | {size / 1e6:.1f} MB | {survey.get('cpu_seconds', float('nan')):.0f} | "
            f"{survey.get('points3D', '–')} |"
        )
    return "\n".join(lines)


def report(work, scenes):
    return table(work, scenes) + "\n\n" + diagnostics(work, scenes) + "\n\n" + costs(work, scenes)


def matloc_bin():
    run(["cargo", "build", "--release", "-p", "matloc-cli"], cwd=ROOT)
    return os.path.join(ROOT, "target", "release", "matloc")


def cmd_all(args):
    scenes = args.scenes.split(",")
    if args.no_build:
        bin_path = os.path.join(ROOT, "target", "release", "matloc")
    else:
        bin_path = matloc_bin()
    for scene in scenes:
        d = os.path.join(args.work, scene)
        if variant_base(scene) and not os.path.exists(os.path.join(d, "scene.json")):
            make_gps_variant(os.path.abspath(args.work), scene, d)
        survey = os.path.join(d, "survey")
        if scene.endswith(REFINED_SUFFIX):
            survey = os.path.join(d, "survey-refined")
            if not os.path.exists(os.path.join(survey, "transforms.json")):
                wall, cpu = run([bin_path, "--quiet", "dataset", "refine-poses", os.path.join(d, "survey"),
                                 "--out", survey])
                write_json(os.path.join(d, "refine-poses.json"), {"wall_seconds": wall, "cpu_seconds": cpu})
            peer = os.path.join(args.work, variant_base(scene) + GPS_SUFFIX, "colmap")
            if os.path.isdir(peer) and not os.path.exists(os.path.join(d, "colmap")):
                os.symlink(os.path.relpath(peer, d), os.path.join(d, "colmap"))
        if not os.path.exists(os.path.join(d, "scene.json")):
            shutil.rmtree(d, ignore_errors=True)
            os.makedirs(args.work, exist_ok=True)
            render(scene, d, args.width, args.height, args.samples)
        if not os.path.exists(os.path.join(d, "queries", "second", "transforms_test.json")):
            run([sys.executable, os.path.join(HERE, "post.py"), d])
        if not os.path.exists(os.path.join(d, "map-build.json")):
            # GPS-level poses put a point's views pixels apart (1° is 5 px at 320 px wide): the
            # variant's map loosens the triangulation gates (map-config-gps.json).
            config = "map-config-gps.json" if scene.endswith(GPS_SUFFIX) else "map-config.json"
            wall, cpu = run([bin_path, "--quiet", "map", "build", "--data", survey,
                             "--out", os.path.join(d, "map"), "--config", os.path.join(HERE, config)])
            write_json(os.path.join(d, "map-build.json"), {"wall_seconds": wall, "cpu_seconds": cpu})
        for method in METHODS:
            overhead = eval_overhead(bin_path, d, method)
            for qset in SETS:
                eval_method(bin_path, d, qset, method, overhead)
        for qset in SETS:
            run_peer(d, qset)
    text = report(args.work, scenes)
    with open(os.path.join(args.work, "table.md"), "w") as f:
        f.write(text + "\n")
    print(text)


def cmd_table(args):
    print(report(args.work, args.scenes.split(",")))


def cmd_smoke(args):
    """The CI fixture: rubble at 320x240 (at 160x120 too few points triangulate for a surface),
    18 survey images and 4 same-flight queries, stored as JPEG (quality 95) to stay small."""
    from PIL import Image

    tmp = args.out.rstrip("/") + ".render"
    shutil.rmtree(tmp, ignore_errors=True)
    render("rubble", tmp, 320, 240, 32, smoke=True)
    shutil.rmtree(args.out, ignore_errors=True)
    for src, dst, name in (("survey", "survey", "transforms_train.json"),
                           (os.path.join("queries", "same"), "queries", "transforms_test.json")):
        os.makedirs(os.path.join(args.out, dst, "images"))
        with open(os.path.join(tmp, src, name)) as f:
            doc = json.load(f)
        for fr in doc["frames"]:
            jpg = os.path.splitext(fr["file_path"])[0] + ".jpg"
            Image.open(os.path.join(tmp, src, fr["file_path"])).convert("RGB").save(
                os.path.join(args.out, dst, jpg), quality=95)
            fr["file_path"] = jpg
        write_json(os.path.join(args.out, dst, name), doc)
    shutil.copy(os.path.join(tmp, "scene.json"), os.path.join(args.out, "scene.json"))
    shutil.rmtree(tmp)
    os.remove(tmp + ".render.log")
    log(f"smoke fixture in {args.out}")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    default_work = os.path.join(ROOT, "target", "outside")
    a = sub.add_parser("all")
    a.add_argument("--work", default=default_work)
    a.add_argument("--scenes", default="rubble,town")
    a.add_argument("--width", type=int, default=320)
    a.add_argument("--height", type=int, default=240)
    a.add_argument("--samples", type=int, default=32)
    a.add_argument("--no-build", action="store_true", help="use target/release/matloc as it is")
    a.set_defaults(fn=cmd_all)
    t = sub.add_parser("table")
    t.add_argument("--work", default=default_work)
    t.add_argument("--scenes", default="rubble,town")
    t.set_defaults(fn=cmd_table)
    s = sub.add_parser("smoke")
    s.add_argument("--out", required=True)
    s.set_defaults(fn=cmd_smoke)
    args = p.parse_args()
    args.fn(args)


if __name__ == "__main__":
    main()
