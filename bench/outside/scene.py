"""Procedural aerial scenes path-traced with Blender Cycles: the outside benchmark's world.

Run inside Blender (its own Python; standard library and `bpy` only):

    blender -b --factory-startup --python bench/outside/scene.py -- \
        --scene rubble|town --out DIR [--width 320 --height 240] [--samples 32] [--smoke]

Writes, under DIR:
  survey/transforms_train.json + survey/images/   the training survey (nerfstudio, no depth)
  queries/same/transforms_test.json + images/     same flight: between training frames, 1-3 m
                                                  off the line, a few degrees of jitter
  queries/novel/transforms_test.json + images/    viewpoints never flown: 12-18 m up, 35-50 deg
                                                  down, any heading, >= 5 m from every survey pose
  raw_second/frames.json + images/                the same-flight poses re-rendered under another
                                                  day's sun on a wider canvas; `post.py` turns
                                                  them into queries/second (exposure, white
                                                  balance, radial distortion, blur, noise)
  scene.json                                      seed, suns, counts, render settings, timings

Nothing here is shared with the project's own synthetic world: other geometry, materials and a
path tracer (soft shadows, indirect light). The seeds are fixed per scene; the scene content is
never tuned to the methods measured on it.
"""

import argparse
import json
import math
import os
import random
import sys
import time

import bmesh
import bpy
from mathutils import Matrix, Vector

# --------------------------------------------------------------------------------------------
# Arguments


def parse_args():
    argv = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else []
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", choices=["rubble", "town"], required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--samples", type=int, default=32)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument(
        "--smoke",
        action="store_true",
        help="a handful of survey images and four same-flight queries (CI fixture)",
    )
    p.add_argument("--queries", type=int, default=20, help="queries per set")
    return p.parse_args(argv)


SEEDS = {"rubble": 4101, "town": 4202}

# Horizontal field of view of the survey camera and of every query.
HFOV_DEG = 60.0

# --------------------------------------------------------------------------------------------
# Small deterministic noise for the terrain (value noise on a hashed lattice).


def _hash2(ix, iy, seed):
    h = (ix * 374761393 + iy * 668265263 + seed * 982451653) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    return ((h ^ (h >> 16)) & 0xFFFFFF) / float(0xFFFFFF)


def value_noise(x, y, seed):
    ix, iy = math.floor(x), math.floor(y)
    fx, fy = x - ix, y - iy
    sx, sy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    a = _hash2(ix, iy, seed)
    b = _hash2(ix + 1, iy, seed)
    c = _hash2(ix, iy + 1, seed)
    d = _hash2(ix + 1, iy + 1, seed)
    return (a + (b - a) * sx) + ((c + (d - c) * sx) - (a + (b - a) * sx)) * sy


def fbm(x, y, seed, octaves=4):
    total, amp, freq, norm = 0.0, 1.0, 1.0, 0.0
    for o in range(octaves):
        total += amp * value_noise(x * freq, y * freq, seed + o * 17)
        norm += amp
        amp *= 0.5
        freq *= 2.0
    return total / norm - 0.5


# --------------------------------------------------------------------------------------------
# Scene helpers


def reset_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    for block in (bpy.data.meshes, bpy.data.materials, bpy.data.objects):
        for item in list(block):
            block.remove(item)


def link(obj):
    bpy.context.scene.collection.objects.link(obj)
    return obj


def box_uv(mesh):
    """UVs in metres by box projection: walls get (along the wall, up), roofs (x, y)."""
    uv = mesh.uv_layers.new(name="UVMap")
    for poly in mesh.polygons:
        n = poly.normal
        for li in poly.loop_indices:
            co = mesh.vertices[mesh.loops[li].vertex_index].co
            if abs(n.z) >= max(abs(n.x), abs(n.y)):
                uv.data[li].uv = (co.x, co.y)
            elif abs(n.x) >= abs(n.y):
                uv.data[li].uv = (co.y, co.z)
            else:
                uv.data[li].uv = (co.x, co.z)


def mesh_from_bmesh(name, bm):
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    return mesh


def box_mesh(name, sx, sy, sz):
    """A box of sx × sy × sz metres, centred in x and y, standing on z = 0."""
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=1.0)
    for v in bm.verts:
        v.co = Vector((v.co.x * sx, v.co.y * sy, (v.co.z + 0.5) * sz))
    mesh = mesh_from_bmesh(name, bm)
    box_uv(mesh)
    return mesh


def rock_mesh(name, rng, subdivisions=1):
    bm = bmesh.new()
    bmesh.ops.create_icosphere(bm, subdivisions=subdivisions, radius=0.5)
    for v in bm.verts:
        v.co *= 0.7 + 0.5 * rng.random()
    mesh = mesh_from_bmesh(name, bm)
    box_uv(mesh)
    return mesh


def cone_mesh(name, r1, r2, depth, segments=8):
    bm = bmesh.new()
    bmesh.ops.create_cone(
        bm, cap_ends=True, segments=segments, radius1=r1, radius2=r2, depth=depth
    )
    for v in bm.verts:
        v.co.z += depth / 2
    return mesh_from_bmesh(name, bm)


def place(name, mesh, material, location, rotation=(0, 0, 0), scale=(1, 1, 1)):
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    obj.rotation_euler = rotation
    obj.scale = scale
    if material is not None:
        if len(obj.data.materials) == 0:
            obj.data.materials.append(material)
        obj.material_slots[0].link = "OBJECT"
        obj.material_slots[0].material = material
    return link(obj)


# --------------------------------------------------------------------------------------------
# Materials (procedural node trees, coordinates in metres)


class Nodes:
    def __init__(self, name):
        self.mat = bpy.data.materials.new(name)
        self.mat.use_nodes = True
        self.tree = self.mat.node_tree
        self.tree.nodes.clear()
        self.out = self.new("ShaderNodeOutputMaterial")
        self.bsdf = self.new("ShaderNodeBsdfPrincipled")
        self.link(self.bsdf.outputs["BSDF"], self.out.inputs["Surface"])
        self.coords = self.new("ShaderNodeTexCoord")
        self.info = self.new("ShaderNodeObjectInfo")

    def new(self, kind):
        return self.tree.nodes.new(kind)

    def link(self, a, b):
        self.tree.links.new(a, b)

    def noise(self, scale, detail=4.0, roughness=0.55, vector=None):
        n = self.new("ShaderNodeTexNoise")
        n.inputs["Scale"].default_value = scale
        n.inputs["Detail"].default_value = detail
        n.inputs["Roughness"].default_value = roughness
        self.link(vector or self.coords.outputs["Object"], n.inputs["Vector"])
        return n.outputs["Fac"]

    def voronoi(self, scale, vector=None):
        n = self.new("ShaderNodeTexVoronoi")
        n.inputs["Scale"].default_value = scale
        self.link(vector or self.coords.outputs["Object"], n.inputs["Vector"])
        return n.outputs["Distance"], n.outputs["Color"]

    def ramp(self, fac, stops):
        r = self.new("ShaderNodeValToRGB")
        els = r.color_ramp.elements
        while len(els) < len(stops):
            els.new(0.5)
        for el, (pos, col) in zip(els, stops):
            el.position = pos
            el.color = (*col, 1.0)
        self.link(fac, r.inputs["Fac"])
        return r.outputs["Color"]

    def mix(self, fac, a, b, blend="MIX"):
        m = self.new("ShaderNodeMixRGB")
        m.blend_type = blend
        if isinstance(fac, float):
            m.inputs["Fac"].default_value = fac
        else:
            self.link(fac, m.inputs["Fac"])
        for sock, v in ((m.inputs["Color1"], a), (m.inputs["Color2"], b)):
            if isinstance(v, tuple):
                sock.default_value = (*v, 1.0)
            else:
                self.link(v, sock)
        return m.outputs["Color"]

    def math(self, op, a, b):
        m = self.new("ShaderNodeMath")
        m.operation = op
        for sock, v in ((m.inputs[0], a), (m.inputs[1], b)):
            if isinstance(v, float):
                sock.default_value = v
            else:
                self.link(v, sock)
        return m.outputs["Value"]

    def bump(self, height, strength):
        b = self.new("ShaderNodeBump")
        b.inputs["Strength"].default_value = strength
        b.inputs["Distance"].default_value = 0.1
        self.link(height, b.inputs["Height"])
        self.link(b.outputs["Normal"], self.bsdf.inputs["Normal"])

    def finish(self, color, roughness=0.85):
        self.link(color, self.bsdf.inputs["Base Color"])
        self.bsdf.inputs["Roughness"].default_value = roughness
        self.bsdf.inputs["Specular"].default_value = 0.3
        return self.mat


def ground_material(name, palette, seed):
    """Patches of the palette's colours at metre scale with centimetre-scale grain."""
    n = Nodes(name)
    mapping = n.new("ShaderNodeMapping")
    mapping.inputs["Location"].default_value = (seed * 13.1, seed * 7.7, 0.0)
    n.link(n.coords.outputs["Object"], mapping.inputs["Vector"])
    v = mapping.outputs["Vector"]
    patches = n.ramp(n.noise(0.06, 6.0, 0.6, v), palette["patches"])
    mid = n.ramp(n.noise(0.8, 5.0, 0.6, v), palette["mid"])
    grain = n.noise(9.0, 3.0, 0.7, v)
    dist, _ = n.voronoi(1.6, v)
    c = n.mix(0.45, patches, mid, "MULTIPLY")
    c = n.mix(n.math("MULTIPLY", dist, 0.8), c, (0.3, 0.28, 0.25), "MIX")
    c = n.mix(0.25, c, n.ramp(grain, [(0.3, (0.2, 0.2, 0.2)), (0.7, (0.9, 0.9, 0.9))]), "OVERLAY")
    n.bump(grain, 0.3)
    return n.finish(c, 0.95)


def varied_material(name, colors, noise_scale=2.5, bump=0.4, roughness=0.8):
    """A colour per object (Object Info random) with stains and grain: rocks, cars, leaves."""
    n = Nodes(name)
    stops = [(i / max(1, len(colors) - 1), c) for i, c in enumerate(colors)]
    base = n.ramp(n.info.outputs["Random"], stops)
    stain = n.noise(noise_scale, 5.0, 0.6)
    grain = n.noise(noise_scale * 6.0, 3.0, 0.6)
    c = n.mix(0.6, base, n.ramp(stain, [(0.35, (0.35, 0.35, 0.35)), (0.7, (1.0, 1.0, 1.0))]), "MULTIPLY")
    c = n.mix(0.3, c, n.ramp(grain, [(0.3, (0.3, 0.3, 0.3)), (0.7, (0.85, 0.85, 0.85))]), "OVERLAY")
    n.bump(grain, bump)
    return n.finish(c, roughness)


def brick_material(name, brick_colors, mortar, size=(0.6, 0.3), dirt=0.5):
    """Masonry on UV metres: bricks of `size`, dirt at metre scale."""
    n = Nodes(name)
    b = n.new("ShaderNodeTexBrick")
    b.inputs["Scale"].default_value = 1.0
    b.inputs["Brick Width"].default_value = size[0]
    b.inputs["Row Height"].default_value = size[1]
    b.inputs["Mortar Size"].default_value = 0.03
    b.inputs["Color1"].default_value = (*brick_colors[0], 1)
    b.inputs["Color2"].default_value = (*brick_colors[1], 1)
    b.inputs["Mortar"].default_value = (*mortar, 1)
    n.link(n.coords.outputs["UV"], b.inputs["Vector"])
    stain = n.noise(0.7, 5.0, 0.6, n.coords.outputs["Object"])
    c = n.mix(dirt, b.outputs["Color"], n.ramp(stain, [(0.3, (0.3, 0.28, 0.25)), (0.75, (1, 1, 1))]), "MULTIPLY")
    n.bump(b.outputs["Fac"], 0.5)
    return n.finish(c, 0.9)


def facade_material(name, wall, glass, window=(1.4, 1.8), bay=(3.0, 3.2)):
    """Walls with a grid of windows (bays of `bay` metres) on UV metres; stained at metre scale."""
    n = Nodes(name)
    b = n.new("ShaderNodeTexBrick")
    b.offset = 0.0
    b.inputs["Scale"].default_value = 1.0
    b.inputs["Brick Width"].default_value = bay[0]
    b.inputs["Row Height"].default_value = bay[1]
    b.inputs["Mortar Size"].default_value = (bay[0] - window[0]) / 2
    b.inputs["Mortar Smooth"].default_value = 0.0
    b.inputs["Color1"].default_value = (*glass, 1)
    b.inputs["Color2"].default_value = (*[g * 0.7 for g in glass], 1)
    b.inputs["Mortar"].default_value = (*wall, 1)
    n.link(n.coords.outputs["UV"], b.inputs["Vector"])
    stain = n.noise(0.5, 6.0, 0.6)
    grain = n.noise(6.0, 3.0, 0.6)
    c = n.mix(0.5, b.outputs["Color"], n.ramp(stain, [(0.3, (0.45, 0.43, 0.4)), (0.75, (1, 1, 1))]), "MULTIPLY")
    c = n.mix(0.2, c, n.ramp(grain, [(0.3, (0.3, 0.3, 0.3)), (0.7, (0.8, 0.8, 0.8))]), "OVERLAY")
    n.bump(b.outputs["Fac"], 0.3)
    return n.finish(c, 0.7)


def tiles_material(name, colors, mortar, tile=(1.0, 1.0)):
    n = Nodes(name)
    b = n.new("ShaderNodeTexBrick")
    b.offset = 0.0
    b.inputs["Scale"].default_value = 1.0
    b.inputs["Brick Width"].default_value = tile[0]
    b.inputs["Row Height"].default_value = tile[1]
    b.inputs["Mortar Size"].default_value = 0.05
    b.inputs["Color1"].default_value = (*colors[0], 1)
    b.inputs["Color2"].default_value = (*colors[1], 1)
    b.inputs["Mortar"].default_value = (*mortar, 1)
    n.link(n.coords.outputs["Object"], b.inputs["Vector"])
    stain = n.noise(0.4, 6.0, 0.6)
    c = n.mix(0.5, b.outputs["Color"], n.ramp(stain, [(0.3, (0.5, 0.5, 0.5)), (0.75, (1, 1, 1))]), "MULTIPLY")
    return n.finish(c, 0.85)


def flat_material(name, color, roughness=0.6):
    n = Nodes(name)
    grain = n.noise(4.0, 3.0, 0.6)
    c = n.mix(0.15, (color[0], color[1], color[2]), n.ramp(grain, [(0.3, (0.3, 0.3, 0.3)), (0.7, (0.9, 0.9, 0.9))]), "OVERLAY")
    return n.finish(c, roughness)


# --------------------------------------------------------------------------------------------
# Terrain


def terrain(name, half, cells, amplitude, seed, material):
    """A height field over [-half, half]²; returns it and its height function."""

    def height(x, y):
        return amplitude * (fbm(x / 40.0, y / 40.0, seed, 4) + 0.3 * fbm(x / 9.0, y / 9.0, seed + 5, 2))

    bm = bmesh.new()
    step = 2.0 * half / cells
    verts = []
    for j in range(cells + 1):
        row = []
        for i in range(cells + 1):
            x, y = -half + i * step, -half + j * step
            row.append(bm.verts.new((x, y, height(x, y))))
        verts.append(row)
    for j in range(cells):
        for i in range(cells):
            bm.faces.new((verts[j][i], verts[j][i + 1], verts[j + 1][i + 1], verts[j + 1][i]))
    mesh = mesh_from_bmesh(name, bm)
    for poly in mesh.polygons:
        poly.use_smooth = True
    place(name, mesh, material, (0, 0, 0))
    return height


# --------------------------------------------------------------------------------------------
# Trees (shared by both scenes)


def tree_kit(rng):
    leaves = varied_material(
        "leaves",
        [(0.06, 0.16, 0.04), (0.12, 0.22, 0.05), (0.09, 0.13, 0.05), (0.16, 0.2, 0.07)],
        noise_scale=1.8,
        bump=0.8,
    )
    bark = varied_material("bark", [(0.12, 0.08, 0.05), (0.18, 0.13, 0.09)], 4.0)
    crowns = [rock_mesh(f"crown{i}", rng, 2) for i in range(4)]
    trunk = cone_mesh("trunk", 0.25, 0.15, 1.0)
    return leaves, bark, crowns, trunk


def plant_tree(kit, rng, x, y, z, size):
    leaves, bark, crowns, trunk = kit
    h = size * (0.9 + 0.3 * rng.random())
    place("trunk", trunk, bark, (x, y, z), scale=(size / 5, size / 5, h * 0.6))
    for k in range(2 + rng.randrange(2)):
        dx, dy = rng.uniform(-0.25, 0.25) * size, rng.uniform(-0.25, 0.25) * size
        s = size * rng.uniform(0.55, 0.8)
        place(
            "crown",
            rng.choice(crowns),
            leaves,
            (x + dx, y + dy, z + h * 0.55 + k * 0.2 * size),
            (rng.random() * 6, rng.random() * 6, rng.random() * 6),
            (s, s, s * 0.85),
        )


# --------------------------------------------------------------------------------------------
# The scenes


def build_rubble(rng, seed):
    """A field of ruins: broken masonry walls, debris heaps, beams, scattered trees."""
    ground = ground_material(
        "ground",
        {
            "patches": [
                (0.2, (0.2, 0.15, 0.1)),
                (0.4, (0.31, 0.3, 0.28)),
                (0.6, (0.12, 0.17, 0.07)),
                (0.8, (0.42, 0.38, 0.32)),
            ],
            "mid": [(0.25, (0.35, 0.33, 0.3)), (0.75, (1.0, 0.97, 0.93))],
        },
        seed,
    )
    height = terrain("terrain", 110.0, 110, 3.0, seed, ground)
    masonry = [
        brick_material("brick_red", [(0.42, 0.16, 0.09), (0.36, 0.12, 0.07)], (0.55, 0.52, 0.48)),
        brick_material("stone", [(0.46, 0.43, 0.38), (0.38, 0.36, 0.33)], (0.3, 0.29, 0.27), (0.9, 0.45)),
        brick_material("concrete", [(0.52, 0.52, 0.5), (0.47, 0.47, 0.46)], (0.4, 0.4, 0.4), (3.0, 1.5), 0.8),
    ]
    debris = varied_material(
        "debris",
        [(0.42, 0.4, 0.37), (0.4, 0.17, 0.1), (0.55, 0.54, 0.5), (0.3, 0.28, 0.25), (0.48, 0.36, 0.26)],
    )
    wood = varied_material("wood", [(0.3, 0.2, 0.12), (0.22, 0.15, 0.09)], 3.0)
    rocks = [rock_mesh(f"rock{i}", rng, 1) for i in range(8)]
    beam = box_mesh("beam", 4.0, 0.25, 0.25)
    kit = tree_kit(rng)

    sites = []
    for _ in range(30):
        for _attempt in range(50):
            x, y = rng.uniform(-85, 85), rng.uniform(-85, 85)
            if all((x - a) ** 2 + (y - b) ** 2 > 18.0**2 for a, b, _ in sites):
                sites.append((x, y, rng.uniform(0, math.pi)))
                break
    for si, (cx, cy, rot) in enumerate(sites):
        mat = rng.choice(masonry)
        w, d = rng.uniform(6, 14), rng.uniform(5, 11)
        c, s = math.cos(rot), math.sin(rot)
        z0 = height(cx, cy) - 0.4
        # Four walls broken into segments of random height (some missing).
        for side in range(4):
            length = w if side % 2 == 0 else d
            n_seg = max(2, int(length / 1.6))
            for k in range(n_seg):
                if rng.random() < 0.2:
                    continue
                t = (k + 0.5) / n_seg - 0.5
                if side == 0:
                    lx, ly, ang = t * w, -d / 2, 0.0
                elif side == 1:
                    lx, ly, ang = w / 2, t * d, math.pi / 2
                elif side == 2:
                    lx, ly, ang = -t * w, d / 2, 0.0
                else:
                    lx, ly, ang = -w / 2, -t * d, math.pi / 2
                seg_h = rng.uniform(0.8, 6.5) if rng.random() < 0.7 else rng.uniform(0.4, 1.5)
                mesh = box_mesh(f"wall{si}_{side}_{k}", length / n_seg + 0.02, 0.5, seg_h + 0.4)
                place(
                    "wall",
                    mesh,
                    mat,
                    (cx + c * lx - s * ly, cy + s * lx + c * ly, z0),
                    (0, 0, rot + ang),
                )
        # Debris heaps inside and around.
        for _ in range(rng.randrange(20, 45)):
            r = rng.uniform(0, max(w, d) * 0.8)
            a = rng.uniform(0, 2 * math.pi)
            x, y = cx + r * math.cos(a), cy + r * math.sin(a)
            sz = rng.uniform(0.3, 1.6)
            place(
                "rock",
                rng.choice(rocks),
                debris,
                (x, y, height(x, y) + sz * 0.15),
                (rng.random() * 6, rng.random() * 6, rng.random() * 6),
                (sz, sz * rng.uniform(0.6, 1.2), sz * rng.uniform(0.4, 0.9)),
            )
        for _ in range(rng.randrange(2, 6)):
            x, y = cx + rng.uniform(-w, w) * 0.6, cy + rng.uniform(-d, d) * 0.6
            place(
                "beam",
                beam,
                wood,
                (x, y, height(x, y) + 0.1),
                (rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), rng.uniform(0, math.pi)),
                (rng.uniform(0.5, 1.2), 1, 1),
            )
    # Loose stones everywhere and trees in the gaps.
    for _ in range(1500):
        x, y = rng.uniform(-100, 100), rng.uniform(-100, 100)
        sz = rng.uniform(0.2, 0.9)
        place(
            "stone",
            rng.choice(rocks),
            debris,
            (x, y, height(x, y)),
            (rng.random() * 6, rng.random() * 6, rng.random() * 6),
            (sz, sz, sz * 0.6),
        )
    for _ in range(70):
        x, y = rng.uniform(-100, 100), rng.uniform(-100, 100)
        if any((x - a) ** 2 + (y - b) ** 2 < 9.0**2 for a, b, _ in sites):
            continue
        plant_tree(kit, rng, x, y, height(x, y) - 0.2, rng.uniform(4.0, 8.0))
    return {"max_height_m": 9.5}


def build_town(rng, seed):
    """A town: a street grid with markings and sidewalks, buildings with windowed facades and
    varied roofs, parked and driving cars, parks with trees and paths."""
    grass = ground_material(
        "grass",
        {
            "patches": [(0.3, (0.16, 0.24, 0.08)), (0.6, (0.22, 0.3, 0.1)), (0.85, (0.3, 0.28, 0.15))],
            "mid": [(0.3, (0.6, 0.6, 0.55)), (0.7, (1.0, 1.0, 0.95))],
        },
        seed,
    )
    place("ground", box_mesh("ground", 240, 240, 0.1), grass, (0, 0, -0.1))
    asphalt = varied_material("asphalt", [(0.09, 0.09, 0.09), (0.11, 0.11, 0.1)], 1.2, 0.2, 0.9)
    sidewalk = tiles_material("sidewalk", [(0.5, 0.49, 0.46), (0.44, 0.43, 0.4)], (0.3, 0.3, 0.3), (1.2, 1.2))
    plaza = tiles_material("plaza", [(0.55, 0.45, 0.38), (0.48, 0.38, 0.32)], (0.35, 0.33, 0.3), (0.8, 0.8))
    paint = flat_material("paint", (0.85, 0.85, 0.8), 0.5)
    facades = [
        facade_material("facade_cream", (0.62, 0.56, 0.44), (0.08, 0.1, 0.13)),
        facade_material("facade_brick", (0.42, 0.2, 0.13), (0.07, 0.08, 0.1), (1.2, 1.6), (2.6, 3.0)),
        facade_material("facade_grey", (0.45, 0.46, 0.47), (0.1, 0.12, 0.16), (2.0, 2.2), (3.2, 3.4)),
        facade_material("facade_blue", (0.3, 0.36, 0.44), (0.06, 0.07, 0.09), (1.0, 1.5), (2.2, 3.0)),
        facade_material("facade_ochre", (0.6, 0.42, 0.2), (0.08, 0.08, 0.09)),
    ]
    roofs = [
        tiles_material("roof_tiles", [(0.42, 0.14, 0.08), (0.36, 0.12, 0.07)], (0.25, 0.1, 0.06), (0.4, 0.3)),
        varied_material("roof_flat", [(0.25, 0.25, 0.26), (0.33, 0.32, 0.3), (0.2, 0.22, 0.24)], 0.8),
        tiles_material("roof_slate", [(0.2, 0.22, 0.26), (0.17, 0.18, 0.21)], (0.1, 0.1, 0.12), (0.5, 0.35)),
    ]
    car_paint = varied_material(
        "car",
        [(0.6, 0.05, 0.04), (0.85, 0.85, 0.85), (0.05, 0.05, 0.06), (0.1, 0.2, 0.5), (0.5, 0.5, 0.52), (0.7, 0.6, 0.1), (0.15, 0.3, 0.15)],
        6.0,
        0.1,
        0.35,
    )
    glass = flat_material("car_glass", (0.03, 0.04, 0.05), 0.15)
    unit = varied_material("roof_unit", [(0.6, 0.6, 0.6), (0.4, 0.4, 0.42)], 3.0)
    kit = tree_kit(rng)
    body = box_mesh("car_body", 4.3, 1.8, 0.8)
    cabin = box_mesh("car_cabin", 2.3, 1.6, 0.6)

    # Street grid: irregular block sizes.
    xs, ys = [-110.0], [-110.0]
    while xs[-1] < 110:
        xs.append(xs[-1] + rng.uniform(34, 52))
    while ys[-1] < 110:
        ys.append(ys[-1] + rng.uniform(30, 48))
    road_w, walk_w = 8.0, 2.5
    for i, x in enumerate(xs):
        place("road", box_mesh(f"road_x{i}", road_w, 240, 0.05), asphalt, (x, 0, 0))
        for side in (-1, 1):
            place("walk", box_mesh(f"walk_x{i}{side}", walk_w, 240, 0.15), sidewalk, (x + side * (road_w / 2 + walk_w / 2), 0, 0))
        for k in range(-40, 40):
            place("mark", box_mesh(f"mark_x{i}_{k}", 0.15, 2.5, 0.06), paint, (x, k * 6.0, 0.0))
    for j, y in enumerate(ys):
        place("road", box_mesh(f"road_y{j}", 240, road_w, 0.055), asphalt, (0, y, 0))
        for side in (-1, 1):
            place("walk", box_mesh(f"walk_y{j}{side}", 240, walk_w, 0.16), sidewalk, (0, y + side * (road_w / 2 + walk_w / 2), 0))
        for k in range(-40, 40):
            place("mark", box_mesh(f"mark_y{j}_{k}", 2.5, 0.15, 0.065), paint, (k * 6.0, y, 0.0))
    # Cars along the roads.
    for _ in range(140):
        if rng.random() < 0.5:
            x = rng.choice(xs) + rng.choice((-2.2, 2.2))
            y, yaw = rng.uniform(-105, 105), math.pi / 2
        else:
            x, yaw = rng.uniform(-105, 105), 0.0
            y = rng.choice(ys) + rng.choice((-2.2, 2.2))
        yaw += rng.choice((0.0, math.pi)) + rng.uniform(-0.05, 0.05)
        place("car", body, car_paint, (x, y, 0.3), (0, 0, yaw))
        cx, cy = x - 0.3 * math.cos(yaw), y - 0.3 * math.sin(yaw)
        place("cabin", cabin, glass, (cx, cy, 1.1), (0, 0, yaw))
    # Blocks: buildings, parks, a plaza.
    margin = road_w / 2 + walk_w + 0.5
    for i in range(len(xs) - 1):
        for j in range(len(ys) - 1):
            x0, x1 = xs[i] + margin, xs[i + 1] - margin
            y0, y1 = ys[j] + margin, ys[j + 1] - margin
            kind = rng.random()
            if kind < 0.18:
                # Park: trees and a diagonal path.
                length = math.hypot(x1 - x0, y1 - y0)
                place(
                    "path",
                    box_mesh(f"path{i}_{j}", length, 2.5, 0.04),
                    plaza,
                    ((x0 + x1) / 2, (y0 + y1) / 2, 0),
                    (0, 0, math.atan2(y1 - y0, x1 - x0)),
                )
                for _ in range(rng.randrange(8, 16)):
                    plant_tree(kit, rng, rng.uniform(x0 + 2, x1 - 2), rng.uniform(y0 + 2, y1 - 2), 0.0, rng.uniform(4.5, 8.0))
                continue
            if kind < 0.26:
                place("plaza", box_mesh(f"plaza{i}_{j}", x1 - x0, y1 - y0, 0.12), plaza, ((x0 + x1) / 2, (y0 + y1) / 2, 0))
                for _ in range(rng.randrange(3, 7)):
                    plant_tree(kit, rng, rng.uniform(x0 + 2, x1 - 2), rng.uniform(y0 + 2, y1 - 2), 0.1, rng.uniform(3.5, 6.0))
                continue
            # Buildings along the block's edges, a yard in the middle.
            x = x0
            while x < x1 - 6:
                w = min(rng.uniform(8, 18), x1 - x)
                for y_edge, sign in ((y0, 1), (y1, -1)):
                    d = min(rng.uniform(8, 14), (y1 - y0) / 2 - 1)
                    h = rng.uniform(4.0, 10.0)
                    cy = y_edge + sign * d / 2
                    place("building", box_mesh(f"b{i}_{j}_{x:.0f}_{sign}", w - 0.6, d, h), rng.choice(facades), (x + w / 2, cy, 0))
                    roof = rng.choice(roofs)
                    place("roof", box_mesh(f"r{i}_{j}_{x:.0f}_{sign}", w - 0.4, d + 0.2, 0.25), roof, (x + w / 2, cy, h))
                    for _ in range(rng.randrange(0, 4)):
                        place(
                            "unit",
                            box_mesh(f"u{rng.random()}", rng.uniform(1, 2.5), rng.uniform(1, 2.5), rng.uniform(0.6, 1.6)),
                            unit,
                            (x + w / 2 + rng.uniform(-w / 3, w / 3), cy + rng.uniform(-d / 3, d / 3), h + 0.25),
                        )
                x += w
            for _ in range(rng.randrange(1, 4)):
                plant_tree(kit, rng, rng.uniform(x0 + 3, x1 - 3), (y0 + y1) / 2 + rng.uniform(-2, 2), 0.0, rng.uniform(3.5, 6.0))
    return {"max_height_m": 10.5}


# --------------------------------------------------------------------------------------------
# Light, camera, render settings


def set_light(sun_obj, world, light):
    """Sun from azimuth / elevation (degrees), its colour and strength, and the sky's."""
    az, el = math.radians(light["sun_azimuth_deg"]), math.radians(light["sun_elevation_deg"])
    towards_sun = Vector((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)))
    # A sun lamp shines along its local -Z.
    sun_obj.rotation_euler = towards_sun.to_track_quat("Z", "Y").to_euler()
    sun_obj.data.energy = light["sun_strength"]
    sun_obj.data.color = light["sun_color"]
    sun_obj.data.angle = math.radians(light["sun_angle_deg"])
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (*light["sky_color"], 1.0)
    bg.inputs["Strength"].default_value = light["sky_strength"]
    return [towards_sun.x, towards_sun.y, towards_sun.z]


def setup_render(args, sun_light):
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = args.samples
    scene.cycles.use_adaptive_sampling = True
    scene.cycles.adaptive_threshold = 0.02
    scene.cycles.max_bounces = 4
    scene.cycles.diffuse_bounces = 3
    scene.cycles.glossy_bounces = 2
    scene.cycles.transmission_bounces = 2
    scene.cycles.sample_clamp_indirect = 5.0
    scene.cycles.seed = 0
    scene.cycles.use_animated_seed = False
    denoiser = "none"
    try:
        scene.cycles.use_denoising = True
        scene.cycles.denoiser = "OPENIMAGEDENOISE"
        denoiser = "OpenImageDenoise"
    except (TypeError, AttributeError):
        scene.cycles.use_denoising = False
    scene.render.use_persistent_data = True
    scene.render.threads_mode = "FIXED"
    scene.render.threads = args.threads
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGB"
    scene.render.image_settings.color_depth = "8"
    scene.render.film_transparent = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.render.dither_intensity = 0.0

    world = bpy.data.worlds.new("World")
    world.use_nodes = True
    scene.world = world
    sun_data = bpy.data.lights.new("sun", "SUN")
    sun = bpy.data.objects.new("sun", sun_data)
    link(sun)
    sun_dir = set_light(sun, world, sun_light)

    cam_data = bpy.data.cameras.new("camera")
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.clip_start = 0.1
    cam_data.clip_end = 2000.0
    cam = link(bpy.data.objects.new("camera", cam_data))
    scene.camera = cam
    return scene, sun, world, cam, sun_dir, denoiser


def look(position, heading_deg, pitch_down_deg, roll_deg=0.0):
    """OpenGL camera-to-world (x right, y up, z back) at `position`, looking along the heading
    (degrees from +x towards +y) pitched down by `pitch_down_deg`, rolled about the view axis."""
    h, p = math.radians(heading_deg), math.radians(pitch_down_deg)
    forward = Vector((math.cos(p) * math.cos(h), math.cos(p) * math.sin(h), -math.sin(p)))
    right = forward.cross(Vector((0, 0, 1))).normalized()
    up = right.cross(forward).normalized()
    if roll_deg:
        rot = Matrix.Rotation(math.radians(roll_deg), 3, forward)
        right, up = rot @ right, rot @ up
    back = -forward
    m = Matrix.Identity(4)
    for r in range(3):
        m[r][0], m[r][1], m[r][2], m[r][3] = right[r], up[r], back[r], position[r]
    return m


def render_views(scene, cam, views, folder, width, height, hfov_deg, log):
    os.makedirs(folder, exist_ok=True)
    scene.render.resolution_x = width
    scene.render.resolution_y = height
    scene.render.resolution_percentage = 100
    cam.data.angle = math.radians(hfov_deg)
    t0 = time.time()
    for i, v in enumerate(views):
        cam.matrix_world = Matrix(v["transform_matrix"])
        path = os.path.join(folder, v["name"])
        scene.render.filepath = path
        bpy.ops.render.render(write_still=True)
        if i % 10 == 0 or i + 1 == len(views):
            log(f"  {folder}: {i + 1}/{len(views)} ({time.time() - t0:.0f} s)")
    return time.time() - t0


# --------------------------------------------------------------------------------------------
# Flight plans


def survey_plan(smoke):
    """Boustrophedon passes at two altitudes and pitches, the camera looking ahead along the
    line; 75 % forward and 60 % side overlap at the footprint's centre."""
    hfov = math.radians(HFOV_DEG)
    vfov = 2 * math.atan(math.tan(hfov / 2) * 0.75)
    passes = [
        {"altitude": 24.0, "pitch": 60.0, "lines": 7, "shots": 11},
        {"altitude": 28.0, "pitch": 50.0, "lines": 7, "shots": 11},
    ]
    if smoke:
        passes = [{"altitude": 24.0, "pitch": 60.0, "lines": 3, "shots": 6}]
    views = []
    for pi, ps in enumerate(passes):
        alt, pitch = ps["altitude"], math.radians(ps["pitch"])
        near = alt / math.tan(min(pitch + vfov / 2, math.radians(89.0)))
        far = alt / math.tan(pitch - vfov / 2)
        along = far - near
        width = 2 * (alt / math.sin(pitch)) * math.tan(hfov / 2)
        step, line_gap = 0.25 * along, 0.4 * width
        # The footprint's centre lies ahead of the camera; centre the covered ground on 0.
        ahead = alt / math.tan(pitch)
        for li in range(ps["lines"]):
            y = (li - (ps["lines"] - 1) / 2) * line_gap
            forward = li % 2 == 0
            for si in range(ps["shots"]):
                s = (si - (ps["shots"] - 1) / 2) * step
                x = (s - ahead) if forward else (-s + ahead)
                heading = 0.0 if forward else 180.0
                views.append(
                    {
                        "pass": pi,
                        "line": li,
                        "shot": si,
                        "position": [x, y, alt],
                        "heading": heading,
                        "pitch": ps["pitch"],
                    }
                )
    return views


def same_flight_queries(rng, survey, n):
    """Between two consecutive shots of a line, 1-3 m off the line, a few degrees of jitter."""
    out = []
    pairs = [
        (a, b)
        for a, b in zip(survey, survey[1:])
        if a["pass"] == b["pass"] and a["line"] == b["line"]
    ]
    picks = rng.sample(pairs, n)
    for a, b in picks:
        t = rng.uniform(0.3, 0.7)
        pos = [a["position"][k] + t * (b["position"][k] - a["position"][k]) for k in range(3)]
        side = rng.choice((-1, 1)) * rng.uniform(1.0, 3.0)
        h = math.radians(a["heading"])
        pos[0] += -math.sin(h) * side
        pos[1] += math.cos(h) * side
        pos[2] += rng.uniform(-0.5, 0.5)
        out.append(
            {
                "position": pos,
                "heading": a["heading"] + rng.uniform(-4, 4),
                "pitch": a["pitch"] + rng.uniform(-3, 3),
                "roll": rng.uniform(-2, 2),
            }
        )
    return out


def novel_queries(rng, survey, n, max_height):
    """12-18 m up (the survey flew 24-28 m), 35-50 deg down (survey 50-60), any heading, looking
    at a point of the ground the survey saw, >= 5 m from every survey camera."""
    out = []
    xs = [v["position"][0] for v in survey]
    ys = [v["position"][1] for v in survey]
    x_lo, x_hi = min(xs) + 0.25 * (max(xs) - min(xs)), max(xs) - 0.25 * (max(xs) - min(xs))
    y_lo, y_hi = min(ys) + 0.25 * (max(ys) - min(ys)), max(ys) - 0.25 * (max(ys) - min(ys))
    while len(out) < n:
        alt = rng.uniform(12.0, 18.0)
        pitch = rng.uniform(35.0, 50.0)
        heading = rng.uniform(0.0, 360.0)
        tx, ty = rng.uniform(x_lo, x_hi), rng.uniform(y_lo, y_hi)
        back = alt / math.tan(math.radians(pitch))
        h = math.radians(heading)
        pos = [tx - back * math.cos(h), ty - back * math.sin(h), alt]
        nearest = min(
            math.dist(pos, v["position"]) for v in survey
        )
        if nearest < 5.0 or alt < max_height + 1.0:
            continue
        out.append({"position": pos, "heading": heading, "pitch": pitch, "roll": 0.0, "nearest_survey_m": nearest})
    return out


def to_views(plan, prefix):
    views = []
    for i, p in enumerate(plan):
        m = look(Vector(p["position"]), p["heading"], p["pitch"], p.get("roll", 0.0))
        views.append({"name": f"{prefix}_{i:05d}.png", "transform_matrix": [list(r) for r in m], "plan": p})
    return views


def intrinsics(width, height, hfov_deg):
    fx = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
    return {"fl_x": fx, "fl_y": fx, "cx": width / 2, "cy": height / 2, "w": width, "h": height}


def write_transforms(path, views, width, height, extra=None):
    doc = {"camera_model": "PINHOLE", **intrinsics(width, height, HFOV_DEG)}
    doc["frames"] = [
        {"file_path": f"images/{v['name']}", "transform_matrix": v["transform_matrix"]} for v in views
    ]
    if extra:
        doc.update(extra)
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(doc, f, indent=1)
    os.replace(tmp, path)


# --------------------------------------------------------------------------------------------


def main():
    args = parse_args()
    t_start = time.time()

    def log(msg):
        print(f"[scene {args.scene}] {msg}", flush=True)

    seed = SEEDS[args.scene]
    rng = random.Random(seed)
    reset_scene()
    survey_light = {
        "sun_azimuth_deg": 135.0 if args.scene == "rubble" else 210.0,
        "sun_elevation_deg": 52.0 if args.scene == "rubble" else 58.0,
        "sun_strength": 3.2,
        "sun_color": (1.0, 0.97, 0.92),
        "sun_angle_deg": 1.5,
        "sky_color": (0.55, 0.68, 0.95),
        "sky_strength": 0.8,
    }
    # Another day: the sun turned and lowered, warmer, a hazier sky.
    second_light = dict(survey_light)
    second_light.update(
        {
            "sun_azimuth_deg": survey_light["sun_azimuth_deg"] + 70.0,
            "sun_elevation_deg": 33.0,
            "sun_strength": 2.8,
            "sun_color": (1.0, 0.88, 0.74),
            "sun_angle_deg": 3.0,
            "sky_color": (0.62, 0.7, 0.86),
            "sky_strength": 1.0,
        }
    )
    t0 = time.time()
    info = build_rubble(rng, seed) if args.scene == "rubble" else build_town(rng, seed)
    log(f"built {len(bpy.data.objects)} objects in {time.time() - t0:.1f} s")
    scene, sun, world, cam, sun_dir, denoiser = setup_render(args, survey_light)

    plan_rng = random.Random(seed + 1)
    survey = survey_plan(args.smoke)
    n_q = 4 if args.smoke else args.queries
    same = same_flight_queries(plan_rng, survey, n_q)
    novel = [] if args.smoke else novel_queries(plan_rng, survey, n_q, info["max_height_m"])

    out = args.out
    W, H = args.width, args.height
    timings = {}
    survey_views = to_views(survey, "survey")
    timings["survey"] = render_views(scene, cam, survey_views, f"{out}/survey/images", W, H, HFOV_DEG, log)
    write_transforms(
        f"{out}/survey/transforms_train.json",
        survey_views,
        W,
        H,
        {"matloc_outside": {"scene": args.scene, "seed": seed, "sun_direction": sun_dir}},
    )
    same_views = to_views(same, "same")
    timings["same"] = render_views(scene, cam, same_views, f"{out}/queries/same/images", W, H, HFOV_DEG, log)
    write_transforms(f"{out}/queries/same/transforms_test.json", same_views, W, H)
    if novel:
        novel_views = to_views(novel, "novel")
        timings["novel"] = render_views(scene, cam, novel_views, f"{out}/queries/novel/images", W, H, HFOV_DEG, log)
        write_transforms(f"{out}/queries/novel/transforms_test.json", novel_views, W, H)

    # Another day: the same-flight poses, on a canvas wide enough for the lens's distortion.
    second_dir = None
    if not args.smoke:
        pad = max(8, W // 16)
        second_dir = set_light(sun, world, second_light)
        fx = intrinsics(W, H, HFOV_DEG)["fl_x"]
        wide_hfov = math.degrees(2 * math.atan((W / 2 + pad) / fx))
        second_views = to_views(same, "second")
        timings["second"] = render_views(
            scene, cam, second_views, f"{out}/raw_second/images", W + 2 * pad, H + 2 * pad, wide_hfov, log
        )
        with open(f"{out}/raw_second/frames.json", "w") as f:
            json.dump(
                {
                    "pad": pad,
                    "width": W,
                    "height": H,
                    **intrinsics(W, H, HFOV_DEG),
                    "frames": [{"name": v["name"], "transform_matrix": v["transform_matrix"]} for v in second_views],
                },
                f,
                indent=1,
            )

    record = {
        "scene": args.scene,
        "seed": seed,
        "renderer": f"Blender {bpy.app.version_string} Cycles, {args.samples} samples (adaptive), denoiser {denoiser}, 4 bounces",
        "size": [W, H],
        "hfov_deg": HFOV_DEG,
        "objects": len(bpy.data.objects),
        "survey_images": len(survey_views),
        "queries": {"same": len(same), "novel": len(novel), "second": 0 if args.smoke else len(same)},
        "survey_light": {**survey_light, "sun_direction": sun_dir},
        "second_light": {**second_light, "sun_direction": second_dir},
        "novel_nearest_survey_m": [q["nearest_survey_m"] for q in novel],
        "render_seconds": timings,
        "total_seconds": time.time() - t_start,
    }
    with open(f"{out}/scene.json", "w") as f:
        json.dump(record, f, indent=1)
    log(f"done in {time.time() - t_start:.0f} s")


if __name__ == "__main__":
    main()
