//! Ray–primitive geometry: half-spaces, boxes, convex polyhedra and ellipsoids in a BVH.

use nalgebra::Vector3;

/// Half-space `n · p <= d` with unit `n`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Plane {
    pub n: Vector3<f64>,
    pub d: f64,
}

impl Plane {
    /// Normalises `n` (and `d` with it).
    pub fn new(n: Vector3<f64>, d: f64) -> Self {
        let l = n.norm();
        Plane { n: n / l, d: d / l }
    }
}

/// Axis-aligned box.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Aabb {
    pub min: Vector3<f64>,
    pub max: Vector3<f64>,
}

impl Aabb {
    pub fn new(min: Vector3<f64>, max: Vector3<f64>) -> Self {
        Aabb { min, max }
    }

    fn empty() -> Self {
        Aabb {
            min: Vector3::repeat(f64::INFINITY),
            max: Vector3::repeat(f64::NEG_INFINITY),
        }
    }

    fn grow(&mut self, o: &Aabb) {
        self.min = self.min.inf(&o.min);
        self.max = self.max.sup(&o.max);
    }

    fn center(&self) -> Vector3<f64> {
        0.5 * (self.min + self.max)
    }

    /// Slab test; returns the entry distance when the box is hit within `[t0, t1]`.
    #[inline]
    pub fn hit(&self, o: &Vector3<f64>, inv: &Vector3<f64>, t0: f64, t1: f64) -> Option<f64> {
        let mut lo = t0;
        let mut hi = t1;
        for k in 0..3 {
            let a = (self.min[k] - o[k]) * inv[k];
            let b = (self.max[k] - o[k]) * inv[k];
            let (a, b) = if a <= b { (a, b) } else { (b, a) };
            // NaN (0 · inf on a slab face) compares false and leaves the interval unchanged.
            if a > lo {
                lo = a;
            }
            if b < hi {
                hi = b;
            }
            if lo > hi {
                return None;
            }
        }
        Some(lo)
    }
}

/// Geometry of one primitive.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Shape {
    /// Intersection of the half-spaces `planes[start..start + len]` of the world.
    Convex { start: u32, len: u32 },
    /// Axis-aligned ellipsoid.
    Ellipsoid {
        center: Vector3<f64>,
        inv_radii: Vector3<f64>,
    },
}

/// A primitive with its bounding box.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Prim {
    pub shape: Shape,
    pub aabb: Aabb,
}

#[derive(Clone, Copy, Debug)]
pub(crate) struct Node {
    pub aabb: Aabb,
    /// Leaf: first index into `order`; interior: index of the left child (right = left + 1).
    pub first: u32,
    /// Number of primitives in a leaf; 0 for an interior node.
    pub count: u32,
}

/// Bounding-volume hierarchy over primitive boxes (median split on the widest centroid axis;
/// scenes have at most tens of thousands of primitives, so build time is negligible).
#[derive(Clone, Debug, Default)]
pub(crate) struct Bvh {
    pub nodes: Vec<Node>,
    pub order: Vec<u32>,
}

const LEAF_SIZE: usize = 4;

impl Bvh {
    pub fn build(prims: &[Prim]) -> Bvh {
        let mut bvh = Bvh {
            nodes: Vec::with_capacity(2 * prims.len() / LEAF_SIZE + 1),
            order: (0..prims.len() as u32).collect(),
        };
        if prims.is_empty() {
            return bvh;
        }
        bvh.nodes.push(Node {
            aabb: Aabb::empty(),
            first: 0,
            count: 0,
        });
        bvh.split(prims, 0, 0, prims.len(), 0);
        bvh
    }

    fn split(&mut self, prims: &[Prim], node: usize, lo: usize, hi: usize, depth: usize) {
        let mut bounds = Aabb::empty();
        let mut cb = Aabb::empty();
        for &i in &self.order[lo..hi] {
            let a = prims[i as usize].aabb;
            bounds.grow(&a);
            let c = a.center();
            cb.grow(&Aabb::new(c, c));
        }
        self.nodes[node].aabb = bounds;
        if hi - lo <= LEAF_SIZE {
            self.nodes[node].first = lo as u32;
            self.nodes[node].count = (hi - lo) as u32;
            return;
        }
        let mid = match self.sah_split(prims, lo, hi, &bounds, &cb, depth) {
            Some(mid) => mid,
            None if hi - lo <= 2 * LEAF_SIZE => {
                self.nodes[node].first = lo as u32;
                self.nodes[node].count = (hi - lo) as u32;
                return;
            }
            None => self.median_split(prims, lo, hi, &cb),
        };
        let left = self.nodes.len();
        self.nodes.push(Node {
            aabb: Aabb::empty(),
            first: 0,
            count: 0,
        });
        self.nodes.push(Node {
            aabb: Aabb::empty(),
            first: 0,
            count: 0,
        });
        self.nodes[node].first = left as u32;
        self.nodes[node].count = 0;
        self.split(prims, left, lo, mid, depth + 1);
        self.split(prims, left + 1, mid, hi, depth + 1);
    }

    fn median_split(&mut self, prims: &[Prim], lo: usize, hi: usize, cb: &Aabb) -> usize {
        let ext = cb.max - cb.min;
        let axis = if ext.x >= ext.y && ext.x >= ext.z {
            0
        } else if ext.y >= ext.z {
            1
        } else {
            2
        };
        let mid = (lo + hi) / 2;
        self.order[lo..hi].select_nth_unstable_by(mid - lo, |&a, &b| {
            let ca = prims[a as usize].aabb.center()[axis];
            let cb = prims[b as usize].aabb.center()[axis];
            ca.total_cmp(&cb)
        });
        mid
    }

    /// Binned surface-area-heuristic split: buildings, roof units, rocks and crowns differ in
    /// size by orders of magnitude, which a median split handles poorly. `None` when a leaf is
    /// cheaper (or the tree is already deep, so traversal stacks stay bounded).
    fn sah_split(
        &mut self,
        prims: &[Prim],
        lo: usize,
        hi: usize,
        bounds: &Aabb,
        cb: &Aabb,
        depth: usize,
    ) -> Option<usize> {
        const BINS: usize = 16;
        if depth > 40 {
            return Some(self.median_split(prims, lo, hi, cb));
        }
        let area = |a: &Aabb| {
            let e = a.max - a.min;
            if e.x < 0.0 {
                0.0
            } else {
                e.x * e.y + e.y * e.z + e.z * e.x
            }
        };
        let mut best = (f64::INFINITY, 0usize, 0usize);
        for axis in 0..3 {
            let (c0, c1) = (cb.min[axis], cb.max[axis]);
            if c1 - c0 < 1e-9 {
                continue;
            }
            let bin_of = |p: &Prim| {
                let c = p.aabb.center()[axis];
                (((c - c0) / (c1 - c0) * BINS as f64) as usize).min(BINS - 1)
            };
            let mut boxes = [Aabb::empty(); BINS];
            let mut counts = [0usize; BINS];
            for &i in &self.order[lo..hi] {
                let p = &prims[i as usize];
                let b = bin_of(p);
                boxes[b].grow(&p.aabb);
                counts[b] += 1;
            }
            let mut right_area = [0.0; BINS];
            let mut acc = Aabb::empty();
            for b in (1..BINS).rev() {
                acc.grow(&boxes[b]);
                right_area[b] = area(&acc);
            }
            let mut left = Aabb::empty();
            let mut n_left = 0;
            for b in 0..BINS - 1 {
                left.grow(&boxes[b]);
                n_left += counts[b];
                let n_right = hi - lo - n_left;
                if n_left == 0 || n_right == 0 {
                    continue;
                }
                let cost = area(&left) * n_left as f64 + right_area[b + 1] * n_right as f64;
                if cost < best.0 {
                    best = (cost, axis, b);
                }
            }
        }
        // Leaf cost ≈ one intersection per primitive; traversal cost ≈ one box test.
        let leaf_cost = area(bounds) * (hi - lo) as f64;
        if !best.0.is_finite() || (hi - lo <= 2 * LEAF_SIZE && best.0 + area(bounds) >= leaf_cost) {
            return None;
        }
        let (_, axis, split_bin) = best;
        let (c0, c1) = (cb.min[axis], cb.max[axis]);
        let slice = &mut self.order[lo..hi];
        let mut i = 0;
        let mut j = slice.len();
        while i < j {
            let c = prims[slice[i] as usize].aabb.center()[axis];
            let b = (((c - c0) / (c1 - c0) * BINS as f64) as usize).min(BINS - 1);
            if b <= split_bin {
                i += 1;
            } else {
                j -= 1;
                slice.swap(i, j);
            }
        }
        if i == 0 || i == slice.len() {
            return Some(self.median_split(prims, lo, hi, cb));
        }
        Some(lo + i)
    }
}

#[inline]
pub(crate) fn intersect_convex(
    planes: &[Plane],
    o: &Vector3<f64>,
    d: &Vector3<f64>,
    t0: f64,
    t1: f64,
) -> Option<(f64, Vector3<f64>)> {
    let mut near = f64::NEG_INFINITY;
    let mut far = f64::INFINITY;
    let mut n_near = None;
    for pl in planes {
        let denom = pl.n.dot(d);
        let dist = pl.d - pl.n.dot(o);
        if denom.abs() < 1e-14 {
            if dist < 0.0 {
                return None;
            }
            continue;
        }
        let t = dist / denom;
        if denom < 0.0 {
            if t > near {
                near = t;
                n_near = Some(pl.n);
            }
        } else if t < far {
            far = t;
        }
        if near > far || far < t0 || near > t1 {
            return None;
        }
    }
    // Rays starting inside a solid (shadow rays leaving a surface) do not hit it.
    if near < t0 {
        return None;
    }
    n_near.map(|n| (near, n))
}

#[inline]
pub(crate) fn intersect_ellipsoid(
    center: &Vector3<f64>,
    inv_r: &Vector3<f64>,
    o: &Vector3<f64>,
    d: &Vector3<f64>,
    t0: f64,
    t1: f64,
) -> Option<(f64, Vector3<f64>)> {
    let oc = (o - center).component_mul(inv_r);
    let dd = d.component_mul(inv_r);
    let a = dd.norm_squared();
    let b = oc.dot(&dd);
    let c = oc.norm_squared() - 1.0;
    let disc = b * b - a * c;
    if disc < 0.0 {
        return None;
    }
    let t = (-b - disc.sqrt()) / a;
    if t < t0 || t > t1 {
        return None;
    }
    let p = o + d * t - center;
    let n = p.component_mul(inv_r).component_mul(inv_r).normalize();
    Some((t, n))
}
