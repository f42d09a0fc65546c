"""The second flight's camera: another day's exposure and white balance, a lens with radial
distortion (OPENCV `k1`), blur and sensor noise, applied to the path-traced renders that
`scene.py` wrote under DIR/raw_second (same poses as the same-flight queries, another sun).

    python bench/outside/post.py DIR

Writes DIR/queries/second/transforms_test.json (camera_model OPENCV with the `k1` used) and
its images. Deterministic: the noise is seeded from the scene directory's name.
"""

import json
import os
import sys
import zlib

import numpy as np
from PIL import Image, ImageFilter

# The other day's camera.
EXPOSURE = 0.72  # linear gain (-0.47 EV)
WHITE_BALANCE = (1.10, 1.0, 0.86)  # linear R, G, B gains
K1 = -0.06  # OPENCV radial distortion (barrel)
BLUR_SIGMA_PX = 0.7
NOISE_SIGMA = 2.5 / 255.0  # additive, display values
SHOT_NOISE = 0.012  # sigma = SHOT_NOISE * sqrt(linear value)


def srgb_to_linear(v):
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(v):
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.0031308, v * 12.92, 1.055 * v ** (1 / 2.4) - 0.055)


def undistort_points(xd, yd, k1):
    """Normalised pinhole coordinates whose OPENCV radial distortion (k1 only) gives (xd, yd)."""
    xu, yu = xd.copy(), yd.copy()
    for _ in range(20):
        r2 = xu * xu + yu * yu
        f = 1.0 + k1 * r2
        xu, yu = xd / f, yd / f
    return xu, yu


def bilinear(img, x, y):
    h, w, _ = img.shape
    x = np.clip(x, 0, w - 1.0001)
    y = np.clip(y, 0, h - 1.0001)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    a = img[y0, x0]
    b = img[y0, x0 + 1]
    c = img[y0 + 1, x0]
    d = img[y0 + 1, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    root = sys.argv[1]
    raw = os.path.join(root, "raw_second")
    with open(os.path.join(raw, "frames.json")) as f:
        meta = json.load(f)
    pad, W, H = meta["pad"], meta["width"], meta["height"]
    fx, fy, cx, cy = meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"]
    out_dir = os.path.join(root, "queries", "second")
    os.makedirs(os.path.join(out_dir, "images"), exist_ok=True)
    rng = np.random.default_rng(zlib.crc32(os.path.basename(os.path.abspath(root)).encode()))

    # Where each output (distorted) pixel's centre comes from in the padded pinhole render.
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    xu, yu = undistort_points((u - cx) / fx, (v - cy) / fy, K1)
    src_x = xu * fx + cx + pad - 0.5
    src_y = yu * fy + cy + pad - 0.5
    if src_x.min() < 0 or src_y.min() < 0 or src_x.max() > W + 2 * pad - 1 or src_y.max() > H + 2 * pad - 1:
        sys.exit("post.py: the padded render is too small for the distortion")

    frames = []
    for fr in meta["frames"]:
        img = np.asarray(Image.open(os.path.join(raw, "images", fr["name"])).convert("RGB"), np.float64) / 255.0
        lin = srgb_to_linear(img)
        lin = bilinear(lin, src_x, src_y)
        lin = lin * EXPOSURE * np.asarray(WHITE_BALANCE)
        lin = lin + rng.normal(size=lin.shape) * SHOT_NOISE * np.sqrt(np.clip(lin, 0, None))
        disp = linear_to_srgb(lin)
        im = Image.fromarray((np.clip(disp, 0, 1) * 255 + 0.5).astype(np.uint8))
        im = im.filter(ImageFilter.GaussianBlur(BLUR_SIGMA_PX))
        disp = np.asarray(im, np.float64) / 255.0 + rng.normal(size=disp.shape) * NOISE_SIGMA
        out = Image.fromarray((np.clip(disp, 0, 1) * 255 + 0.5).astype(np.uint8))
        tmp = os.path.join(out_dir, "images", fr["name"] + ".tmp.png")
        out.save(tmp)
        os.replace(tmp, os.path.join(out_dir, "images", fr["name"]))
        frames.append({"file_path": f"images/{fr['name']}", "transform_matrix": fr["transform_matrix"]})

    doc = {
        "camera_model": "OPENCV",
        "fl_x": fx,
        "fl_y": fy,
        "cx": cx,
        "cy": cy,
        "w": W,
        "h": H,
        "k1": K1,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "frames": frames,
        "matloc_outside": {
            "exposure_gain": EXPOSURE,
            "white_balance_gains": WHITE_BALANCE,
            "blur_sigma_px": BLUR_SIGMA_PX,
            "noise_sigma": NOISE_SIGMA,
            "shot_noise": SHOT_NOISE,
        },
    }
    path = os.path.join(out_dir, "transforms_test.json")
    with open(path + ".tmp", "w") as f:
        json.dump(doc, f, indent=1)
    os.replace(path + ".tmp", path)
    print(f"post.py: {len(frames)} second-flight queries in {out_dir}")


if __name__ == "__main__":
    main()
