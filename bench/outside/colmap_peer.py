#!/usr/bin/env python3
"""COLMAP peer for the outside localization benchmark.

Localizes query images against a survey of images with KNOWN poses, the classic COLMAP way:

  survey (once, cached in WORK_DIR/survey/):
    1. `feature_extractor`: SIFT (CPU) of the training images, one run per distinct camera so
       each group gets one COLMAP camera with the dataset's intrinsics (`single_camera 1`).
    2. `exhaustive_matcher` among the training images (or, above --exhaustive-max images,
       `matches_importer` with the k nearest training images by known camera centre), with
       COLMAP's default geometric verification.
    3. a text model with the known poses (cameras.txt, images.txt with the database's ids and
       an empty points line, empty points3D.txt), then `point_triangulator`.
  queries (fresh in WORK_DIR/<basename of QUERY_DIR>/ on every run):
    4. copy of the survey database, `feature_extractor` of the queries (their own cameras,
       OPENCV when the lens distorts), `matches_importer --match_type pairs` with every
       query x every training image, `image_registrator` into the triangulated model,
       `model_converter --output_type TXT`, and the query poses read back from images.txt.

What COLMAP 3.8 does with the training poses (read in colmap/colmap tag 3.8):
  - point_triangulator (src/exe/sfm.cc, RunPointTriangulatorImpl): triangulates every
    registered image (IncrementalMapper::TriangulateImage), CompleteAndMergeTracks, then
    bundle-adjusts with `ba_options.refine_focal_length = false; refine_principal_point = false;
    refine_extra_params = false; refine_extrinsics = false;` hard-coded, i.e. only the 3D points
    move: the known poses and intrinsics stay fixed whatever --Mapper.* says.
  - image_registrator (src/exe/image.cc, RunImageRegistrator): loads the model, then for each
    unregistered image calls IncrementalMapper::RegisterNextImage (P3P RANSAC +
    RefineAbsolutePose of that image only) and writes the model. There is NO bundle adjustment
    and no triangulation in 3.8's registrator, so the training poses and the 3D points are not
    moved. RegisterNextImage may refine the query camera's focal length and distortion
    (abs_pose_refine_focal_length / _extra_params, which IncrementalMapperOptions::Mapper()
    copies from --Mapper.ba_refine_focal_length / ba_refine_extra_params): both are set to 0
    here, so the queries' given intrinsics are kept. The script checks afterwards that the
    training poses in the registrator's output equal the known ones and reports the largest
    difference in "notes".

Python 3.11 standard library only. COLMAP (the `colmap` binary, 3.8 tested) must be on PATH or
given with --colmap. Poses are COLMAP cam_from_world (x_cam = R(q) x_world + t, q = wxyz) in
the world of the transforms' transform_matrix (OpenGL camera-to-world).

Usage:
  python3 bench/outside/colmap_peer.py --survey SURVEY_DIR --queries QUERY_DIR \
      --work WORK_DIR --out RESULT.json [--threads 2] [--report-errors]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import resource
import shutil
import sqlite3
import struct
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

SURVEY_MARKER = "survey.json"  # written last: its presence means the survey stage is complete
SURVEY_FORMAT = 1

# COLMAP camera model ids (src/base/camera_models.h) and their parameter names.
CAMERA_MODELS = {
    "SIMPLE_PINHOLE": (0, ("f", "cx", "cy")),
    "PINHOLE": (1, ("fx", "fy", "cx", "cy")),
    "SIMPLE_RADIAL": (2, ("f", "cx", "cy", "k")),
    "RADIAL": (3, ("f", "cx", "cy", "k1", "k2")),
    "OPENCV": (4, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    "OPENCV_FISHEYE": (5, ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    "FULL_OPENCV": (6, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
}
MODEL_BY_ID = {v[0]: k for k, v in CAMERA_MODELS.items()}


class PeerError(Exception):
    """An error to report to the user (bad input, failed COLMAP step)."""


# ----------------------------------------------------------------------------------------------
# small linear algebra (3x3 lists of lists)
# ----------------------------------------------------------------------------------------------


def mat_t(a):
    return [[a[j][i] for j in range(3)] for i in range(3)]


def mat_mul(a, b):
    return [[sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)] for i in range(3)]


def mat_vec(a, v):
    return [sum(a[i][k] * v[k] for k in range(3)) for i in range(3)]


def quat_from_rot(r):
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Hamilton, as COLMAP)."""
    tr = r[0][0] + r[1][1] + r[2][2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s
    elif r[0][0] > r[1][1] and r[0][0] > r[2][2]:
        s = 2.0 * math.sqrt(1.0 + r[0][0] - r[1][1] - r[2][2])
        w, x, y, z = (r[2][1] - r[1][2]) / s, 0.25 * s, (r[0][1] + r[1][0]) / s, (r[0][2] + r[2][0]) / s
    elif r[1][1] > r[2][2]:
        s = 2.0 * math.sqrt(1.0 + r[1][1] - r[0][0] - r[2][2])
        w, x, y, z = (r[0][2] - r[2][0]) / s, (r[0][1] + r[1][0]) / s, 0.25 * s, (r[1][2] + r[2][1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r[2][2] - r[0][0] - r[1][1])
        w, x, y, z = (r[1][0] - r[0][1]) / s, (r[0][2] + r[2][0]) / s, (r[1][2] + r[2][1]) / s, 0.25 * s
    n = math.sqrt(w * w + x * x + y * y + z * z)
    q = [w / n, x / n, y / n, z / n]
    return q if q[0] >= 0.0 else [-c for c in q]


def rot_from_quat(q):
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]


def rotation_angle_deg(r):
    c = max(-1.0, min(1.0, (r[0][0] + r[1][1] + r[2][2] - 1.0) / 2.0))
    return math.degrees(math.acos(c))


def cam_from_world_from_opengl(m):
    """OpenGL camera-to-world 4x4 (x right, y up, z back) -> COLMAP cam_from_world (R, t).

    c2w_cv = c2w_gl . diag(1, -1, -1, 1); cam_from_world = c2w_cv^-1.
    """
    r_cv = [[m[i][0], -m[i][1], -m[i][2]] for i in range(3)]
    c = [m[0][3], m[1][3], m[2][3]]
    r = mat_t(r_cv)
    t = [-v for v in mat_vec(r, c)]
    return r, t


def camera_center(r, t):
    return [-v for v in mat_vec(mat_t(r), t)]


# ----------------------------------------------------------------------------------------------
# nerfstudio datasets
# ----------------------------------------------------------------------------------------------


@dataclass
class Frame:
    name: str  # file_path exactly as in the json
    path: Path  # absolute image path
    camera: tuple  # (model, width, height, params tuple)
    c2w: list  # 4x4 OpenGL camera-to-world
    json_path: Path
    index: int


def normalize_rel(raw: str) -> str:
    parts = [p for p in raw.replace("\\", "/").split("/") if p not in ("", ".")]
    return "/".join(parts)


def image_size(path: Path):
    """(width, height) from a PNG or JPEG header, or None."""
    try:
        with open(path, "rb") as f:
            head = f.read(32)
            if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
                return struct.unpack(">II", head[16:24])
            if head[:2] == b"\xff\xd8":
                f.seek(2)
                while True:
                    b = f.read(1)
                    while b and b != b"\xff":
                        b = f.read(1)
                    while b == b"\xff":
                        b = f.read(1)
                    if not b:
                        return None
                    marker = b[0]
                    seg_len = struct.unpack(">H", f.read(2))[0]
                    if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
                        _, h, w = struct.unpack(">BHH", f.read(5))
                        return w, h
                    f.seek(seg_len - 2, 1)
    except (OSError, struct.error):
        return None
    return None


class DatasetReader:
    def __init__(self, json_path: Path):
        self.json_path = json_path
        self.root = json_path.parent
        try:
            text = json_path.read_text()
        except OSError as e:
            raise PeerError(f"{json_path}: cannot read: {e}") from e
        try:
            self.top = json.loads(text)
        except json.JSONDecodeError as e:
            raise PeerError(f"{json_path}: not valid JSON: {e}") from e
        if not isinstance(self.top, dict):
            raise PeerError(f"{json_path}: expected a JSON object at the top level")
        frames = self.top.get("frames")
        if not isinstance(frames, list) or not frames:
            raise PeerError(f"{json_path}: field `frames`: expected a non-empty array")
        self.raw_frames = frames

    def err(self, index, field, msg):
        where = f"frame {index}: " if index is not None else ""
        return PeerError(f"{self.json_path}: {where}field `{field}`: {msg}")

    def number(self, fo, index, key):
        """A number from the frame (overriding the top level), or None when absent."""
        if key in fo:
            v, at = fo[key], index
        elif key in self.top:
            v, at = self.top[key], None
        else:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.err(at, key, f"expected a finite number, got {v!r}")
        return float(v)

    def name_list(self, key):
        v = self.top.get(key)
        if v is None:
            return None
        if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
            raise self.err(None, key, "expected an array of file paths")
        return v

    def frame(self, index) -> Frame:
        fo = self.raw_frames[index]
        if not isinstance(fo, dict):
            raise PeerError(f"{self.json_path}: frame {index}: expected an object")
        raw = fo.get("file_path")
        if not isinstance(raw, str) or not raw:
            raise self.err(index, "file_path", "expected a non-empty string")
        path = self.root / raw
        if not Path(raw).suffix and not path.exists() and Path(str(path) + ".png").exists():
            path = Path(str(path) + ".png")  # Blender layout: no extension
        if not path.is_file():
            raise self.err(index, "file_path", f"image {path} does not exist")
        path = path.resolve()

        m = fo.get("transform_matrix")
        ok = isinstance(m, list) and len(m) in (3, 4) and all(
            isinstance(row, list) and len(row) == 4 for row in m
        )
        if ok:
            try:
                m = [[float(x) for x in row] for row in m]
            except (TypeError, ValueError):
                ok = False
        if not ok:
            raise self.err(index, "transform_matrix", "expected 4x4 (or 3x4) numbers")
        if len(m) == 3:
            m.append([0.0, 0.0, 0.0, 1.0])
        if not all(math.isfinite(x) for row in m for x in row):
            raise self.err(index, "transform_matrix", "has non-finite entries")
        rot = [row[:3] for row in m[:3]]
        rtr = mat_mul(mat_t(rot), rot)
        dev = max(abs(rtr[i][j] - (1.0 if i == j else 0.0)) for i in range(3) for j in range(3))
        det = (
            rot[0][0] * (rot[1][1] * rot[2][2] - rot[1][2] * rot[2][1])
            - rot[0][1] * (rot[1][0] * rot[2][2] - rot[1][2] * rot[2][0])
            + rot[0][2] * (rot[1][0] * rot[2][1] - rot[1][1] * rot[2][0])
        )
        if dev > 1e-4 or det < 0:
            raise self.err(index, "transform_matrix", f"rotation part is not a rotation (|R^T R - I| = {dev:.2g}, det = {det:.4g})")

        return Frame(raw, path, self.camera(fo, index, path), m, self.json_path, index)

    def camera(self, fo, index, path):
        model = fo.get("camera_model", self.top.get("camera_model"))
        if model is not None:
            if not isinstance(model, str):
                raise self.err(index, "camera_model", "expected a string")
            model = model.upper()
            if model not in ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "OPENCV_FISHEYE", "SIMPLE_RADIAL", "RADIAL"):
                raise self.err(index, "camera_model", f"unsupported camera model {model!r} (supported: PINHOLE, SIMPLE_PINHOLE, OPENCV, OPENCV_FISHEYE, SIMPLE_RADIAL, RADIAL)")
        w, h = self.number(fo, index, "w"), self.number(fo, index, "h")
        if w is None or h is None:
            size = image_size(path)
            if size is None:
                raise self.err(index, "w", f"missing `w`/`h` and cannot read the size of {path}")
            w, h = float(size[0]), float(size[1])
        for key, v in (("w", w), ("h", h)):
            if v < 1 or v != int(v):
                raise self.err(index, key, f"expected a positive whole number of pixels, got {v}")
        w, h = int(w), int(h)
        fx = self.number(fo, index, "fl_x")
        if fx is None:
            angle = self.number(fo, index, "camera_angle_x")
            if angle is None:
                raise self.err(index, "fl_x", "missing (and no `camera_angle_x`)")
            if not 0 < angle < math.pi:
                raise self.err(index, "camera_angle_x", f"{angle} is not a field of view in radians")
            fx = 0.5 * w / math.tan(0.5 * angle)
        fy = self.number(fo, index, "fl_y")
        fy = fx if fy is None else fy
        cx = self.number(fo, index, "cx")
        cx = 0.5 * w if cx is None else cx
        cy = self.number(fo, index, "cy")
        cy = 0.5 * h if cy is None else cy
        if fx <= 0 or fy <= 0:
            raise self.err(index, "fl_x", f"focal lengths must be positive, got {fx}, {fy}")
        d = {k: (self.number(fo, index, k) or 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2")}
        if model == "OPENCV_FISHEYE":
            return ("OPENCV_FISHEYE", w, h, (fx, fy, cx, cy, d["k1"], d["k2"], d["k3"], d["k4"]))
        if model in ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", None):
            if d["k4"] != 0.0:
                raise self.err(index, "k4", "k4 needs camera_model OPENCV_FISHEYE")
            if d["k3"] != 0.0:
                return ("FULL_OPENCV", w, h, (fx, fy, cx, cy, d["k1"], d["k2"], d["p1"], d["p2"], d["k3"], 0.0, 0.0, 0.0))
            if model == "OPENCV" or any(d[k] != 0.0 for k in ("k1", "k2", "p1", "p2")):
                return ("OPENCV", w, h, (fx, fy, cx, cy, d["k1"], d["k2"], d["p1"], d["p2"]))
            return ("PINHOLE", w, h, (fx, fy, cx, cy))
        raise AssertionError(model)

    def frames(self, keep=None):
        """All frames, or those whose normalized file_path is in `keep` (a set)."""
        out = []
        for i in range(len(self.raw_frames)):
            raw = self.raw_frames[i].get("file_path") if isinstance(self.raw_frames[i], dict) else None
            if keep is not None and (not isinstance(raw, str) or normalize_rel(raw) not in keep):
                continue
            out.append(self.frame(i))
        return out

    def check_list(self, key):
        """Normalized entries of a split list; each must name a frame."""
        entries = self.name_list(key)
        if entries is None:
            return None
        known = {
            normalize_rel(f["file_path"])
            for f in self.raw_frames
            if isinstance(f, dict) and isinstance(f.get("file_path"), str)
        }
        out = set()
        for e in entries:
            n = normalize_rel(e)
            if n not in known:
                raise self.err(None, key, f"entry {e!r} names no frame")
            out.add(n)
        return out


def load_survey(d: Path):
    if (d / "transforms_train.json").is_file():
        return DatasetReader(d / "transforms_train.json").frames()
    if not (d / "transforms.json").is_file():
        raise PeerError(f"{d}: no transforms_train.json or transforms.json")
    r = DatasetReader(d / "transforms.json")
    held_out = set()
    for key in ("test_filenames", "val_filenames"):
        held_out |= r.check_list(key) or set()
    keep = {
        normalize_rel(f["file_path"])
        for f in r.raw_frames
        if isinstance(f, dict) and isinstance(f.get("file_path"), str)
    } - held_out
    frames = r.frames(keep)
    if len(frames) < 2:
        raise PeerError(f"{r.json_path}: only {len(frames)} training frame(s) outside test/val lists; need at least 2")
    return frames


def load_queries(d: Path):
    if (d / "transforms_test.json").is_file():
        return DatasetReader(d / "transforms_test.json").frames()
    if not (d / "transforms.json").is_file():
        raise PeerError(f"{d}: no transforms_test.json or transforms.json")
    r = DatasetReader(d / "transforms.json")
    keep = r.check_list("test_filenames")
    frames = r.frames(keep)
    if not frames:
        raise PeerError(f"{r.json_path}: field `test_filenames`: selects no frame")
    return frames


def staged_name(prefix: str, raw: str) -> str:
    """A COLMAP image name for a dataset file_path: no spaces, no `..`, unique per prefix."""
    parts = []
    p = raw.replace("\\", "/")
    if p.startswith("/"):
        parts.append("_abs_")
    for c in p.split("/"):
        if c in ("", "."):
            continue
        c = "_up_" if c == ".." else c
        parts.append("".join(ch if (ch.isalnum() or ch in "._-+") else "_" for ch in c))
    return prefix + "/" + "/".join(parts)


def stage_images(frames, prefix: str, root: Path):
    """Symlinks root/<staged name> -> image; returns staged names (in frame order)."""
    names = []
    seen = {}
    for f in frames:
        n = staged_name(prefix, f.name)
        if n in seen:
            raise PeerError(f"{f.json_path}: frames {seen[n]} and {f.index}: field `file_path`: {f.name!r} is given twice (or maps to the same COLMAP name {n!r})")
        seen[n] = f.index
        link = root / n
        link.parent.mkdir(parents=True, exist_ok=True)
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(f.path)
        names.append(n)
    return names


# ----------------------------------------------------------------------------------------------
# COLMAP
# ----------------------------------------------------------------------------------------------


class Colmap:
    def __init__(self, exe: str, threads: int):
        found = shutil.which(exe)
        if found is None:
            raise PeerError(f"COLMAP executable {exe!r} not found (install colmap or pass --colmap)")
        self.exe = found
        self.threads = threads
        self.env = dict(os.environ)
        self.env["QT_QPA_PLATFORM"] = "offscreen"
        self.env["OMP_NUM_THREADS"] = str(threads)
        out = subprocess.run([self.exe, "-h"], capture_output=True, text=True, env=self.env)
        first = (out.stdout or out.stderr).strip().splitlines()
        self.version_line = first[0].strip() if first else "unknown"
        # "COLMAP 3.8 -- Structure-from-Motion and Multi-View Stereo"
        tok = self.version_line.split()
        self.version = tok[1] if len(tok) > 1 and tok[0] == "COLMAP" else self.version_line
        self.steps = {}  # step -> [cpu seconds, wall seconds] of each COLMAP call

    def run(self, step: str, args, log_dir: Path):
        log_dir.mkdir(parents=True, exist_ok=True)
        log = log_dir / f"{step}.log"
        cmd = [self.exe] + [str(a) for a in args]
        ru0, w0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.monotonic()
        with open(log, "w") as fh:
            fh.write(" ".join(cmd) + "\n\n")
            fh.flush()
            rc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=self.env).returncode
        ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        self.steps[step] = [
            round((ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime), 3),
            round(time.monotonic() - w0, 3),
        ]
        if rc != 0:
            text = log.read_text(errors="replace")
            hint = ""
            if args[0] == "point_triangulator" and "bundle_adjuster.Solve" in text:
                n = sum(int(x.split()[2]) for x in text.splitlines() if x.strip().startswith("=> Triangulated "))
                if n == 0:
                    hint = ("\nhint: no 3D point was triangulated (COLMAP 3.8 then aborts in bundle adjustment): "
                            "the training images share too few verified SIFT matches")
            tail = text.splitlines()[-25:]
            raise PeerError(f"colmap {args[0]} ({step}) failed with exit status {rc}; log {log}:\n" + "\n".join(tail) + hint)
        return log

    def sift_extraction(self):
        return ["--SiftExtraction.use_gpu", "0", "--SiftExtraction.num_threads", self.threads]

    def sift_matching(self):
        return ["--SiftMatching.use_gpu", "0", "--SiftMatching.num_threads", self.threads]

    def mapper_fixed_intrinsics(self):
        return [
            "--Mapper.ba_refine_focal_length", "0",
            "--Mapper.ba_refine_principal_point", "0",
            "--Mapper.ba_refine_extra_params", "0",
            "--Mapper.num_threads", self.threads,
        ]


def extract_features(colmap: Colmap, db: Path, image_root: Path, frames, names, work: Path, tag: str):
    """One feature_extractor run per distinct camera; returns {staged name: camera tuple}."""
    groups = {}
    for f, n in zip(frames, names):
        groups.setdefault(f.camera, []).append(n)
    for gi, (cam, group_names) in enumerate(sorted(groups.items(), key=lambda kv: kv[1][0])):
        model, _w, _h, params = cam
        lst = work / f"{tag}_images_{gi}.txt"
        write_atomic(lst, "".join(n + "\n" for n in group_names))
        colmap.run(
            f"{tag}_feature_extractor_{gi}",
            [
                "feature_extractor",
                "--database_path", db,
                "--image_path", image_root,
                "--image_list_path", lst,
                "--ImageReader.camera_model", model,
                "--ImageReader.camera_params", ",".join(repr(float(p)) for p in params),
                "--ImageReader.single_camera", "1",
            ]
            + colmap.sift_extraction(),
            work / "logs",
        )
    return {n: f.camera for f, n in zip(frames, names)}


def read_db(db: Path):
    """{name: (image_id, camera_id)}, {camera_id: (model, width, height, params)}."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        images = {name: (iid, cid) for iid, name, cid in con.execute("SELECT image_id, name, camera_id FROM images")}
        cams = {}
        for cid, model, w, h, blob in con.execute("SELECT camera_id, model, width, height, params FROM cameras"):
            cams[cid] = (MODEL_BY_ID.get(model, str(model)), w, h, struct.unpack(f"<{len(blob) // 8}d", blob))
        kp = {iid: rows for iid, rows in con.execute("SELECT image_id, rows FROM keypoints")}
    finally:
        con.close()
    return images, cams, kp


def check_extracted(db: Path, cams_by_name, frames_by_name):
    images, cams, kp = read_db(db)
    missing = [n for n in cams_by_name if n not in images]
    if missing:
        raise PeerError(f"feature_extractor did not add {len(missing)} image(s) to {db}, e.g. {frames_by_name[missing[0]].path} (unreadable image?)")
    for n, cam in cams_by_name.items():
        model, w, h, params = cams[images[n][1]]
        f = frames_by_name[n]
        if (w, h) != (cam[1], cam[2]):
            raise PeerError(f"{f.json_path}: frame {f.index}: fields `w`/`h`: {cam[1]}x{cam[2]} but the image {f.path} is {w}x{h}")
        if model != cam[0] or any(abs(a - b) > 1e-9 * max(1.0, abs(b)) for a, b in zip(params, cam[3])):
            raise PeerError(f"internal: camera of {n} in the database is {model} {params}, expected {cam[0]} {cam[3]}")
    return images, cams, kp


def write_atomic(path: Path, text: str):
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    with open(tmp, "w") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def read_model_txt(d: Path):
    """images: {name: (image_id, qvec, tvec, camera_id, n_points3D)}, points3D: [(error, track_len)]."""
    images = {}
    lines = (d / "images.txt").read_text().split("\n")
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        if not line or line.startswith("#"):
            i += 1
            continue
        tok = line.split()
        pts = lines[i + 1].split() if i + 1 < len(lines) else []
        n3d = sum(1 for k in range(2, len(pts), 3) if pts[k] != "-1")
        images[tok[9]] = (int(tok[0]), [float(x) for x in tok[1:5]], [float(x) for x in tok[5:8]], int(tok[8]), n3d)
        i += 2
    points = []
    for line in (d / "points3D.txt").read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        tok = line.split()
        points.append((float(tok[7]), (len(tok) - 8) // 2))
    return images, points


def nearest_pairs(frames, names, k):
    centers = []
    for f in frames:
        centers.append([f.c2w[0][3], f.c2w[1][3], f.c2w[2][3]])
    pairs = set()
    for i, ci in enumerate(centers):
        d = sorted(
            (sum((a - b) ** 2 for a, b in zip(ci, cj)), j) for j, cj in enumerate(centers) if j != i
        )
        for _, j in d[:k]:
            pairs.add((min(i, j), max(i, j)))
    return [(names[i], names[j]) for i, j in sorted(pairs)]


# ----------------------------------------------------------------------------------------------
# stages
# ----------------------------------------------------------------------------------------------


def survey_fingerprint(frames, names, colmap, args):
    h = hashlib.sha256()
    h.update(f"format {SURVEY_FORMAT} colmap {colmap.version_line} exhaustive_max {args.exhaustive_max} knn {args.knn}\n".encode())
    for f, n in zip(frames, names):
        st = f.path.stat()
        h.update(json.dumps([n, str(f.path), st.st_size, st.st_mtime_ns, f.camera, f.c2w]).encode())
    return h.hexdigest()


def run_survey(colmap: Colmap, frames, work: Path, args):
    sdir = work / "survey"
    names = [staged_name("train", f.name) for f in frames]
    fp = survey_fingerprint(frames, names, colmap, args)
    marker = sdir / SURVEY_MARKER
    if marker.is_file():
        try:
            info = json.loads(marker.read_text())
        except (OSError, json.JSONDecodeError):
            info = {}
        if info.get("fingerprint") == fp and (sdir / "triangulated" / "images.bin").is_file():
            print(f"survey: reusing {sdir}", file=sys.stderr)
            info["stats"]["cached"] = True
            return info, names
        print(f"survey: {sdir} was built from other inputs; rebuilding", file=sys.stderr)
    if sdir.exists():
        shutil.rmtree(sdir)
    sdir.mkdir(parents=True)

    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    w0 = time.monotonic()
    image_root = sdir / "images"
    names = stage_images(frames, "train", image_root)
    frames_by_name = dict(zip(names, frames))
    db = sdir / "database.db"
    cams_by_name = extract_features(colmap, db, image_root, frames, names, sdir, "survey")
    images, cams, kp = check_extracted(db, cams_by_name, frames_by_name)
    print(f"survey: {len(names)} training images, {sum(kp.get(images[n][0], 0) for n in names) / len(names):.0f} SIFT features/image", file=sys.stderr)

    if len(names) <= args.exhaustive_max:
        colmap.run("survey_exhaustive_matcher", ["exhaustive_matcher", "--database_path", db] + colmap.sift_matching(), sdir / "logs")
        matching = "exhaustive"
    else:
        pairs = nearest_pairs(frames, names, args.knn)
        pl = sdir / "survey_pairs.txt"
        write_atomic(pl, "".join(f"{a} {b}\n" for a, b in pairs))
        colmap.run("survey_matches_importer", ["matches_importer", "--database_path", db, "--match_list_path", pl, "--match_type", "pairs"] + colmap.sift_matching(), sdir / "logs")
        matching = f"pairs: {args.knn} nearest training images by known camera centre ({len(pairs)} pairs)"

    # Known-pose model with the database's ids.
    known = sdir / "known_poses"
    known.mkdir()
    used_cams = sorted({images[n][1] for n in names})
    write_atomic(
        known / "cameras.txt",
        "".join(f"{cid} {cams[cid][0]} {cams[cid][1]} {cams[cid][2]} " + " ".join(repr(p) for p in cams[cid][3]) + "\n" for cid in used_cams),
    )
    lines = []
    for f, n in zip(frames, names):
        r, t = cam_from_world_from_opengl(f.c2w)
        q = quat_from_rot(r)
        iid, cid = images[n]
        lines.append(f"{iid} " + " ".join(repr(v) for v in q + t) + f" {cid} {n}\n\n")
    write_atomic(known / "images.txt", "".join(lines))
    write_atomic(known / "points3D.txt", "")

    tri = sdir / "triangulated"
    tri.mkdir()
    colmap.run(
        "survey_point_triangulator",
        ["point_triangulator", "--database_path", db, "--image_path", image_root, "--input_path", known, "--output_path", tri] + colmap.mapper_fixed_intrinsics(),
        sdir / "logs",
    )
    tri_txt = sdir / "triangulated_txt"
    tri_txt.mkdir()
    colmap.run("survey_model_converter", ["model_converter", "--input_path", tri, "--output_path", tri_txt, "--output_type", "TXT"], sdir / "logs")
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    wall = time.monotonic() - w0

    model_images, points = read_model_txt(tri_txt)
    n_obs = sum(tl for _, tl in points)
    errors = [e for e, _ in points if e >= 0]
    stats = {
        "images": len(model_images),
        "points3D": len(points),
        "mean_track_length": (n_obs / len(points)) if points else 0.0,
        "mean_reprojection_error_px": (sum(errors) / len(errors)) if errors else 0.0,
        "cpu_seconds": (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime),
        "wall_seconds": wall,
        "matching": matching,
        "mean_sift_features_per_image": sum(kp.get(images[n][0], 0) for n in names) / len(names),
    }
    if not points:
        raise PeerError(f"point_triangulator produced no 3D points (see {sdir / 'logs'}); too few matches between training images?")
    info = {"fingerprint": fp, "stats": stats, "train_names": names}
    write_atomic(marker, json.dumps(info, indent=1) + "\n")
    stats = dict(stats, cached=False)
    return dict(info, stats=stats), names


def query_dir_name(qdir: Path):
    base = qdir.resolve().name or "queries"
    return "queries_survey" if base == "survey" else base


def run_queries(colmap: Colmap, qframes, train_names, known_frames, work: Path, query_dir: Path):
    qwork = work / query_dir_name(query_dir)
    if qwork.exists():
        shutil.rmtree(qwork)
    qwork.mkdir(parents=True)
    sdir = work / "survey"

    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    w0 = time.monotonic()
    db = qwork / "database.db"
    shutil.copyfile(sdir / "database.db", db)
    image_root = qwork / "images"
    qnames = stage_images(qframes, "query", image_root)
    frames_by_name = dict(zip(qnames, qframes))
    cams_by_name = extract_features(colmap, db, image_root, qframes, qnames, qwork, "query")
    check_extracted(db, cams_by_name, frames_by_name)

    pl = qwork / "query_pairs.txt"
    write_atomic(pl, "".join(f"{q} {t}\n" for q in qnames for t in train_names))
    colmap.run("query_matches_importer", ["matches_importer", "--database_path", db, "--match_list_path", pl, "--match_type", "pairs"] + colmap.sift_matching(), qwork / "logs")

    reg = qwork / "registered"
    reg.mkdir()
    colmap.run(
        "query_image_registrator",
        ["image_registrator", "--database_path", db, "--input_path", sdir / "triangulated", "--output_path", reg] + colmap.mapper_fixed_intrinsics(),
        qwork / "logs",
    )
    reg_txt = qwork / "registered_txt"
    reg_txt.mkdir()
    colmap.run("query_model_converter", ["model_converter", "--input_path", reg, "--output_path", reg_txt, "--output_type", "TXT"], qwork / "logs")
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    wall = time.monotonic() - w0
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)

    model_images, _ = read_model_txt(reg_txt)
    results = []
    for f, n in zip(qframes, qnames):
        m = model_images.get(n)
        if m is None:
            results.append({"name": f.name, "registered": False, "qvec_wxyz": None, "tvec": None, "inliers": None})
        else:
            results.append({"name": f.name, "registered": True, "qvec_wxyz": m[1], "tvec": m[2], "inliers": m[4]})

    # The registrator must not have moved the training poses (it has no bundle adjustment in 3.8).
    max_dt, max_dr = 0.0, 0.0
    for f, n in known_frames:
        m = model_images.get(n)
        if m is None:
            continue
        r, t = cam_from_world_from_opengl(f.c2w)
        rm = rot_from_quat(m[1])
        max_dr = max(max_dr, rotation_angle_deg(mat_mul(rm, mat_t(r))))
        max_dt = max(max_dt, math.dist(camera_center(rm, m[2]), camera_center(r, t)))
    return results, cpu, wall, (max_dt, max_dr)


def report_errors(qframes, results):
    rows = []
    for f, res in zip(qframes, results):
        if not res["registered"]:
            print(f"  {f.name:40s} not registered", file=sys.stderr)
            continue
        r_gt, t_gt = cam_from_world_from_opengl(f.c2w)
        r = rot_from_quat(res["qvec_wxyz"])
        de = math.dist(camera_center(r, res["tvec"]), camera_center(r_gt, t_gt))
        dr = rotation_angle_deg(mat_mul(r, mat_t(r_gt)))
        rows.append((de, dr))
        print(f"  {f.name:40s} inliers {res['inliers']:5d}  dt {de:.4f}  dR {dr:.3f} deg", file=sys.stderr)
    if rows:
        dts = sorted(r[0] for r in rows)
        drs = sorted(r[1] for r in rows)
        print(
            f"registered {len(rows)}/{len(results)}; median dt {dts[len(dts) // 2]:.4f} (max {dts[-1]:.4f}), "
            f"median dR {drs[len(drs) // 2]:.3f} deg (max {drs[-1]:.3f})",
            file=sys.stderr,
        )
    else:
        print(f"registered 0/{len(results)}", file=sys.stderr)


def main(argv=None):
    ap = argparse.ArgumentParser(description="COLMAP known-pose triangulation + image_registrator localization peer.")
    ap.add_argument("--survey", required=True, help="nerfstudio dataset of the training images")
    ap.add_argument("--queries", required=True, help="nerfstudio dataset of the queries")
    ap.add_argument("--work", required=True, help="cache / work directory")
    ap.add_argument("--out", required=True, help="result JSON")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--colmap", default="colmap", help="COLMAP executable (default: colmap on PATH)")
    ap.add_argument("--exhaustive-max", type=int, default=200, help="survey matching is exhaustive up to this many training images (default 200)")
    ap.add_argument("--knn", type=int, default=30, help="above --exhaustive-max: pairs with this many nearest training images (default 30)")
    ap.add_argument("--report-errors", action="store_true", help="debug: print per-query errors against the queries' ground truth to stderr")
    args = ap.parse_args(argv)
    if args.threads < 1:
        raise PeerError("--threads must be at least 1")

    survey_dir, query_dir = Path(args.survey).resolve(), Path(args.queries).resolve()
    work, out = Path(args.work).resolve(), Path(args.out).resolve()
    for d, what in ((survey_dir, "--survey"), (query_dir, "--queries")):
        if not d.is_dir():
            raise PeerError(f"{what} {d}: not a directory")
    frames = load_survey(survey_dir)
    qframes = load_queries(query_dir)
    colmap = Colmap(args.colmap, args.threads)
    work.mkdir(parents=True, exist_ok=True)

    info, train_names = run_survey(colmap, frames, work, args)
    results, qcpu, qwall, (max_dt, max_dr) = run_queries(colmap, qframes, train_names, list(zip(frames, train_names)), work, query_dir)

    stats = info["stats"]
    survey = {k: stats[k] for k in ("images", "points3D", "mean_track_length", "mean_reprojection_error_px", "cpu_seconds", "wall_seconds")}
    survey.update({"training_frames": len(frames), "matching": stats["matching"], "mean_sift_features_per_image": stats["mean_sift_features_per_image"], "cached": stats["cached"]})
    n_reg = sum(1 for r in results if r["registered"])
    result = {
        "peer": f"colmap {colmap.version}",
        "colmap_version_line": colmap.version_line,
        "survey": survey,
        "queries": results,
        "registered": n_reg,
        "query_cpu_seconds": qcpu,
        "query_wall_seconds": qwall,
        "cpu_seconds_per_query": qcpu / len(qframes),
        "threads": args.threads,
        "steps_cpu_wall_seconds": colmap.steps,
        "notes": [
            "SIFT on CPU with COLMAP defaults; survey: known training poses -> point_triangulator "
            "(3.8 bundle-adjusts the 3D points only: refine_extrinsics and all intrinsics are hard-coded off)",
            "queries: matched against every training image (matches_importer pairs, geometric verification on), "
            "registered one by one by image_registrator (3.8: P3P RANSAC + pose refinement of the query only, "
            "no bundle adjustment, no triangulation; query intrinsics kept fixed via --Mapper.ba_refine_* 0)",
            f"training poses after image_registrator differ from the known ones by at most {max_dt:.3g} (position) "
            f"and {max_dr:.3g} deg",
            "inliers = the registered query's observations of 3D points in the output model (the P3P inliers)",
            "survey cpu/wall seconds are those of the run that built WORK_DIR/survey" + (" (reused from cache in this run)" if stats["cached"] else ""),
        ],
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out, json.dumps(result, indent=1) + "\n")
    print(
        f"{colmap.version_line}: survey {survey['images']} images, {survey['points3D']} points; "
        f"registered {n_reg}/{len(results)} queries, {qcpu / len(qframes):.2f} CPU s/query -> {out}",
        file=sys.stderr,
    )
    if args.report_errors:
        report_errors(qframes, results)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except PeerError as e:
        print(f"colmap_peer: error: {e}", file=sys.stderr)
        sys.exit(1)
