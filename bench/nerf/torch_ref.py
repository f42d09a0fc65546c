"""PyTorch-CPU reference of the matloc-nerf field and training step, for throughput only.

Same architecture as matloc-nerf-field: 16-level x 2-feature hash grid (tiny-cuda-nn hash with
primes 1, 2654435761, 805459861 in 32-bit wrapping arithmetic, dense indexing where the level
fits the table, trilinear interpolation), nerfstudio scene contraction, geometry MLP
32-64-16 (density via exp, 15-d f_mlp), colour MLP on [SH4(d), f_mlp, appearance(8)] with
64-64-3. Same sample budget (48 stratified samples per ray inside the scene box), batch 4096,
MSE + distortion loss (weight 0.002), learned background, fused Adam with exponential decay.
The field + rendering + loss is compiled with torch.compile.

Prints one JSON line. With --rust-json (the output of the Rust `nerf_throughput` example) it
also prints the Rust/PyTorch ratio of rays per second.
"""

import argparse
import json
import math
import os
import time

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

PRIMES = [1, 2654435761, 805459861]
N_LEVELS = 16


def to_i32(v):
    return v - (1 << 32) if v >= (1 << 31) else v


def layout(log2_t, n_min, n_max):
    t = 1 << log2_t
    b = math.exp((math.log(n_max) - math.log(n_min)) / (N_LEVELS - 1))
    levels, off = [], 0
    for l in range(N_LEVELS):
        res = max(1, int(math.floor(n_min * b**l + 1e-9)))
        verts = (res + 1) ** 3
        dense = verts <= t
        size = verts if dense else t
        levels.append((res, off, size, dense))
        off += size
    return levels, off


def load_dataset(root):
    meta = json.load(open(os.path.join(root, "transforms.json")))
    train = set(meta.get("train_filenames", []))
    frames = [f for f in meta["frames"] if not train or f["file_path"] in train]
    imgs, c2ws, intr = [], [], []
    for f in frames:
        g = lambda k: f.get(k, meta.get(k))
        img = np.asarray(Image.open(os.path.join(root, f["file_path"])).convert("RGB"))
        imgs.append(img)
        c2ws.append(np.array(f["transform_matrix"], dtype=np.float64)[:3])
        intr.append((g("fl_x"), g("fl_y"), g("cx"), g("cy")))
    m = meta["matloc"]
    return imgs, c2ws, intr, np.array(m["bounds_min"]), np.array(m["bounds_max"])


class Rays:
    """Random training rays of all images (pinhole, OpenGL camera-to-world as nerfstudio)."""

    def __init__(self, imgs, c2ws, intr, lo, hi):
        self.h, self.w = imgs[0].shape[:2]
        self.rgb = torch.from_numpy(np.stack(imgs)).reshape(len(imgs), -1, 3)
        self.c2w = torch.tensor(np.stack(c2ws), dtype=torch.float32)
        self.k = torch.tensor(intr, dtype=torch.float32)
        pad = 0.02 * (hi - lo)
        self.lo = torch.tensor(lo - pad, dtype=torch.float32)
        self.hi = torch.tensor(hi + pad, dtype=torch.float32)

    def sample(self, n, gen):
        i = torch.randint(0, self.rgb.shape[0], (n,), generator=gen)
        p = torch.randint(0, self.h * self.w, (n,), generator=gen)
        u = (p % self.w).float() + 0.5
        v = (p // self.w).float() + 0.5
        k = self.k[i]
        d_cam = torch.stack([(u - k[:, 2]) / k[:, 0], -(v - k[:, 3]) / k[:, 1], -torch.ones(n)], -1)
        c2w = self.c2w[i]
        d = torch.einsum("nij,nj->ni", c2w[:, :, :3], d_cam)
        d = d / d.norm(dim=-1, keepdim=True)
        o = c2w[:, :, 3]
        inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
        t0 = (self.lo - o) * inv
        t1 = (self.hi - o) * inv
        near = torch.minimum(t0, t1).amax(-1).clamp(min=0.01)
        far = torch.maximum(t0, t1).amin(-1)
        far = torch.where(far > near + 1e-3, far, near + 1.0)
        rgb = self.rgb[i, p].float() / 255.0
        return o, d, near, far, i, rgb


def sh4(d):
    x, y, z = d.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    return torch.stack(
        [
            torch.full_like(x, 0.2820948),
            -0.4886025 * y,
            0.4886025 * z,
            -0.4886025 * x,
            1.0925484 * x * y,
            -1.0925484 * y * z,
            0.9461747 * zz - 0.31539157,
            -1.0925484 * x * z,
            0.5462742 * (xx - yy),
            0.5900436 * y * (-3.0 * xx + yy),
            2.8906114 * x * y * z,
            0.4570458 * y * (1.0 - 5.0 * zz),
            0.37317633 * z * (5.0 * zz - 3.0),
            0.4570458 * x * (1.0 - 5.0 * zz),
            1.4453057 * z * (xx - yy),
            0.5900436 * x * (-xx + 3.0 * yy),
        ],
        -1,
    )


class Field(torch.nn.Module):
    def __init__(self, log2_t, lo, hi, n_images, app_dim=8, n_min=16, n_max=2048):
        super().__init__()
        levels, entries = layout(log2_t, n_min, n_max)
        self.table = torch.nn.Parameter(torch.empty(entries, 2).uniform_(-1e-4, 1e-4))
        self.register_buffer("res", torch.tensor([l[0] for l in levels], dtype=torch.int32))
        self.register_buffer("off", torch.tensor([l[1] for l in levels], dtype=torch.int32))
        self.register_buffer("dense", torch.tensor([l[3] for l in levels]))
        self.mask = (1 << log2_t) - 1
        self.register_buffer("primes", torch.tensor([to_i32(p) for p in PRIMES], dtype=torch.int32))
        self.register_buffer("lo", torch.tensor(lo, dtype=torch.float32))
        self.register_buffer("hi", torch.tensor(hi, dtype=torch.float32))
        self.scale = float(2.0 / np.mean(hi - lo))
        self.geo = torch.nn.Sequential(torch.nn.Linear(32, 64), torch.nn.ReLU(), torch.nn.Linear(64, 16))
        self.col = torch.nn.Sequential(
            torch.nn.Linear(16 + 15 + app_dim, 64),
            torch.nn.ReLU(),
            torch.nn.Linear(64, 64),
            torch.nn.ReLU(),
            torch.nn.Linear(64, 3),
        )
        self.app = torch.nn.Embedding(n_images, app_dim)
        torch.nn.init.uniform_(self.app.weight, -0.1, 0.1)
        self.bg = torch.nn.Parameter(torch.full((3,), 0.5))

    def encode(self, x01):
        # x01: [N, 3] in [0, 1]. All levels at once: [N, L, 3].
        res = self.res.float()
        x = x01[:, None, :] * res[None, :, None]
        fl = torch.minimum(x.floor(), (res - 1)[None, :, None])
        fr = x - fl
        i0 = fl.to(torch.int32)
        out = 0
        for c in range(8):
            bits = torch.tensor([(c >> a) & 1 for a in range(3)], dtype=torch.int32)
            ic = i0 + bits
            w = torch.prod(torch.where(bits.bool(), fr, 1 - fr), -1)  # [N, L]
            r1 = (self.res + 1)[None, :]
            dense_idx = ic[..., 0] + r1 * (ic[..., 1] + r1 * ic[..., 2])
            h = (ic[..., 0] * self.primes[0]) ^ (ic[..., 1] * self.primes[1]) ^ (ic[..., 2] * self.primes[2])
            hash_idx = h & self.mask
            idx = torch.where(self.dense[None, :], dense_idx, hash_idx) + self.off[None, :]
            out = out + w[..., None] * F.embedding(idx, self.table)  # [N, L, 2]
        return out.reshape(x01.shape[0], 32)

    def contract01(self, p):
        q = (p - self.lo) / (self.hi - self.lo) * 2 - 1
        n = q.abs().amax(-1, keepdim=True)
        c = torch.where(n <= 1, q, (2 - 1 / n) / n * q)
        return ((c + 2) * 0.25).clamp(0, 1)

    def forward(self, pts, dirs, app_idx):
        enc = self.encode(self.contract01(pts))
        g = self.geo(enc)
        sigma = self.scale * torch.exp(g[:, 0].clamp(max=15.0))
        c_in = torch.cat([sh4(dirs), g[:, 1:], self.app(app_idx)], -1)
        rgb = torch.sigmoid(self.col(c_in))
        return sigma, rgb


def step_loss(field, o, d, near, far, app, target, jitter, n_samples: int, dist_w: float):
    n = o.shape[0]
    # Stratified: the step grid shifted by a per-ray jitter, end intervals clipped.
    u = ((torch.arange(n_samples + 1, dtype=torch.float32)[None, :] - jitter[:, None]) / n_samples).clamp(0, 1)
    edges = near[:, None] + (far - near)[:, None] * u
    t0, t1 = edges[:, :-1], edges[:, 1:]
    tm = 0.5 * (t0 + t1)
    pts = o[:, None, :] + tm[..., None] * d[:, None, :]
    dirs = d[:, None, :].expand(-1, t0.shape[1], -1)
    sigma, rgb = field(pts.reshape(-1, 3), dirs.reshape(-1, 3), app[:, None].expand(-1, t0.shape[1]).reshape(-1))
    sigma = sigma.reshape(n, -1)
    rgb = rgb.reshape(n, -1, 3)
    delta = t1 - t0
    alpha = 1 - torch.exp(-sigma * delta)
    trans = torch.exp(-torch.cumsum(torch.cat([torch.zeros(n, 1), sigma * delta], -1), -1))[:, :-1]
    w = alpha * trans
    acc = w.sum(-1)
    out = (w[..., None] * rgb).sum(1) + (1 - acc)[:, None] * field.bg
    mse = ((out - target) ** 2).mean()
    # Distortion loss in the normalised ray coordinate, O(S) form (mip-NeRF 360).
    s0 = (t0 - near[:, None]) / (far - near)[:, None]
    s1 = (t1 - near[:, None]) / (far - near)[:, None]
    sm = 0.5 * (s0 + s1)
    wm = w * sm
    cw = torch.cumsum(w, -1) - w
    cwm = torch.cumsum(wm, -1) - wm
    dist = (2 * (wm * cw - w * cwm)).sum(-1) + (w * w * (s1 - s0)).sum(-1) / 3
    return mse + dist_w * dist.mean(), mse


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--batch", type=int, default=4096)
    ap.add_argument("--samples", type=int, default=48)
    ap.add_argument("--log2-table", type=int, default=19)
    ap.add_argument("--threads", type=int, default=os.cpu_count())
    ap.add_argument("--no-compile", action="store_true")
    ap.add_argument("--rust-json")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    imgs, c2ws, intr, lo, hi = load_dataset(a.data)
    rays = Rays(imgs, c2ws, intr, lo, hi)
    field = Field(a.log2_table, lo, hi, len(imgs))
    try:
        opt = torch.optim.Adam(field.parameters(), lr=1e-2, eps=1e-15, fused=True)
        fused = True
    except (RuntimeError, TypeError):
        opt = torch.optim.Adam(field.parameters(), lr=1e-2, eps=1e-15, foreach=True)
        fused = False
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: (1e-2) ** (min(s, 10000) / 10000))
    fn = step_loss if a.no_compile else torch.compile(step_loss, dynamic=False)
    gen = torch.Generator().manual_seed(0)

    def one():
        o, d, near, far, app, target = rays.sample(a.batch, gen)
        jitter = torch.rand(a.batch, generator=gen)
        loss, mse = fn(field, o, d, near, far, app, target, jitter, a.samples, 0.002)
        opt.zero_grad(set_to_none=False)
        loss.backward()
        opt.step()
        sched.step()
        return float(mse.detach())

    t = time.time()
    for _ in range(a.warmup):
        one()
    warm_s = time.time() - t
    t0, c0 = time.time(), time.process_time()
    for _ in range(a.steps):
        mse = one()
    wall, cpu = time.time() - t0, time.process_time() - c0
    rays_n = a.steps * a.batch
    res = {
        "impl": "torch" + ("" if a.no_compile else "+compile"),
        "torch": torch.__version__,
        "fused_adam": fused,
        "threads": a.threads,
        "steps": a.steps,
        "batch": a.batch,
        "warmup_s": round(warm_s, 1),
        "wall_s": round(wall, 3),
        "cpu_s": round(cpu, 3),
        "rays_per_s": round(rays_n / wall, 1),
        "rays_per_cpu_s": round(rays_n / cpu, 1),
        "final_mse": round(mse, 5),
    }
    print(json.dumps(res))
    if a.rust_json:
        r = json.loads(open(a.rust_json).read().strip().splitlines()[-1])
        print(json.dumps(r))
        print(
            f"rays/s: rust {r['rays_per_s']:.0f}, torch {res['rays_per_s']:.0f}, ratio {r['rays_per_s'] / res['rays_per_s']:.1f}x; "
            f"rays per CPU-second: rust {r['rays_per_cpu_s']:.0f}, torch {res['rays_per_cpu_s']:.0f}, "
            f"ratio {r['rays_per_cpu_s'] / res['rays_per_cpu_s']:.1f}x"
        )


if __name__ == "__main__":
    main()
