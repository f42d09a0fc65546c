//! Ray casting against a world: the object BVH and a grid DDA over the terrain.

use nalgebra::{Point3, Vector3};

use super::geometry::{Aabb, Shape, intersect_convex, intersect_ellipsoid};
use super::world::{BLOCK, Class, Material, Terrain, World};

/// A ray hit inside the crate: distance, geometric normal (facing the ray) and what was hit.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RawHit {
    pub t: f64,
    pub normal: Vector3<f64>,
    /// Primitive index, or [`TERRAIN`].
    pub prim: u32,
}

/// Primitive id used for terrain hits.
pub(crate) const TERRAIN: u32 = u32::MAX - 1;

/// A public ray hit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the (normalised) ray direction, m.
    pub t: f64,
    /// World point of the hit.
    pub point: Point3<f64>,
    /// Unit surface normal, facing against the ray.
    pub normal: Vector3<f64>,
    /// What kind of surface was hit.
    pub material: Material,
}

impl Terrain {
    /// First hit of the ray with the terrain surface within `(t0, t1)`; outside the grid the
    /// terrain continues as the flat plane `z = base`.
    pub(crate) fn intersect(
        &self,
        o: &Vector3<f64>,
        d: &Vector3<f64>,
        t1: f64,
    ) -> Option<(f64, Vector3<f64>)> {
        let eps = 1e-6;
        let gx1 = self.x0 + self.nx as f64 * self.cell;
        let gy1 = self.y0 + self.ny as f64 * self.cell;
        let slab = Aabb::new(
            Vector3::new(self.x0, self.y0, self.hmin - 1e-3),
            Vector3::new(gx1, gy1, self.hmax + 1e-3),
        );
        let inv = d.map(|v| 1.0 / v);
        if let Some(tin) = slab.hit(o, &inv, eps, t1) {
            let tout = {
                // Exit distance of the slab (the same slab test from the far side).
                let mut hi = t1;
                for k in 0..3 {
                    let a = (slab.min[k] - o[k]) * inv[k];
                    let b = (slab.max[k] - o[k]) * inv[k];
                    let m = a.max(b);
                    if m < hi {
                        hi = m;
                    }
                }
                hi
            };
            if let Some(h) = self.block_dda(o, d, tin, tout) {
                return Some(h);
            }
        }
        // The flat plane beyond the apron (also a safety net for grazing misses at cell seams).
        if d.z < -1e-12 {
            let t = (self.base - o.z) / d.z;
            if t > eps && t < t1 {
                let p = o + d * t;
                let inside = p.x > self.x0 && p.y > self.y0 && p.x < gx1 && p.y < gy1;
                if !inside || (p.z - self.height_at(p.x, p.y)).abs() < 1e-3 {
                    return Some((t, Vector3::z()));
                }
            }
        }
        None
    }

    /// Walks the blocks of the min/max hierarchy and runs the cell DDA only where the ray's
    /// height range over a block overlaps the block's terrain heights.
    fn block_dda(
        &self,
        o: &Vector3<f64>,
        d: &Vector3<f64>,
        tin: f64,
        tout: f64,
    ) -> Option<(f64, Vector3<f64>)> {
        let c = self.cell * BLOCK as f64;
        let (nbx, nby) = (self.nbx as i64, self.nby as i64);
        let p = o + d * tin;
        let mut i = (((p.x - self.x0) / c).floor() as i64).clamp(0, nbx - 1);
        let mut j = (((p.y - self.y0) / c).floor() as i64).clamp(0, nby - 1);
        let step_i: i64 = if d.x >= 0.0 { 1 } else { -1 };
        let step_j: i64 = if d.y >= 0.0 { 1 } else { -1 };
        let dtx = if d.x.abs() > 1e-15 {
            c / d.x.abs()
        } else {
            f64::INFINITY
        };
        let dty = if d.y.abs() > 1e-15 {
            c / d.y.abs()
        } else {
            f64::INFINITY
        };
        let bound = |k: i64, step: i64| (k + i64::from(step > 0)) as f64 * c;
        let mut tmx = if d.x.abs() > 1e-15 {
            (self.x0 + bound(i, step_i) - o.x) / d.x
        } else {
            f64::INFINITY
        };
        let mut tmy = if d.y.abs() > 1e-15 {
            (self.y0 + bound(j, step_j) - o.y) / d.y
        } else {
            f64::INFINITY
        };
        let mut t_enter = tin;
        let pad = 1e-6 * (1.0 + tout);
        loop {
            let t_exit = tmx.min(tmy).min(tout);
            let (bmin, bmax) = self.blocks[j as usize * self.nbx + i as usize];
            let (za, zb) = (o.z + d.z * t_enter, o.z + d.z * t_exit);
            if za.min(zb) <= bmax + 1e-9 && za.max(zb) >= bmin - 1e-9 {
                // Narrow to where the ray is inside the block's height range.
                let (mut ta, mut tb) = (t_enter, t_exit);
                if d.z.abs() > 1e-15 {
                    let t_hi = (bmax - o.z) / d.z;
                    let t_lo = (bmin - o.z) / d.z;
                    ta = ta.max(t_hi.min(t_lo));
                    tb = tb.min(t_hi.max(t_lo));
                }
                if let Some(h) = self.dda(o, d, (ta - pad).max(tin), (tb + pad).min(tout)) {
                    return Some(h);
                }
            }
            if t_exit >= tout {
                return None;
            }
            if tmx < tmy {
                i += step_i;
                t_enter = tmx;
                tmx += dtx;
            } else {
                j += step_j;
                t_enter = tmy;
                tmy += dty;
            }
            if i < 0 || j < 0 || i >= nbx || j >= nby {
                return None;
            }
        }
    }

    fn dda(
        &self,
        o: &Vector3<f64>,
        d: &Vector3<f64>,
        tin: f64,
        tout: f64,
    ) -> Option<(f64, Vector3<f64>)> {
        let c = self.cell;
        let p = o + d * tin;
        let mut i = (((p.x - self.x0) / c).floor() as i64).clamp(0, self.nx as i64 - 1);
        let mut j = (((p.y - self.y0) / c).floor() as i64).clamp(0, self.ny as i64 - 1);
        let step_i: i64 = if d.x >= 0.0 { 1 } else { -1 };
        let step_j: i64 = if d.y >= 0.0 { 1 } else { -1 };
        let next_x = |i: i64| self.x0 + (i + i64::from(step_i > 0)) as f64 * c;
        let next_y = |j: i64| self.y0 + (j + i64::from(step_j > 0)) as f64 * c;
        let dtx = if d.x.abs() > 1e-15 {
            c / d.x.abs()
        } else {
            f64::INFINITY
        };
        let dty = if d.y.abs() > 1e-15 {
            c / d.y.abs()
        } else {
            f64::INFINITY
        };
        let mut tmx = if d.x.abs() > 1e-15 {
            (next_x(i) - o.x) / d.x
        } else {
            f64::INFINITY
        };
        let mut tmy = if d.y.abs() > 1e-15 {
            (next_y(j) - o.y) / d.y
        } else {
            f64::INFINITY
        };
        let mut t_enter = tin;
        loop {
            let t_exit = tmx.min(tmy).min(tout);
            if let Some(h) = self.cell_hit(i as usize, j as usize, o, d, t_enter, t_exit) {
                return Some(h);
            }
            if t_exit >= tout {
                return None;
            }
            if tmx < tmy {
                i += step_i;
                t_enter = tmx;
                tmx += dtx;
            } else {
                j += step_j;
                t_enter = tmy;
                tmy += dty;
            }
            if i < 0 || j < 0 || i >= self.nx as i64 || j >= self.ny as i64 {
                return None;
            }
        }
    }

    #[inline]
    fn cell_hit(
        &self,
        i: usize,
        j: usize,
        o: &Vector3<f64>,
        d: &Vector3<f64>,
        t0: f64,
        t1: f64,
    ) -> Option<(f64, Vector3<f64>)> {
        let h00 = self.h(i, j);
        let h10 = self.h(i + 1, j);
        let h01 = self.h(i, j + 1);
        let h11 = self.h(i + 1, j + 1);
        let (z0, z1) = (o.z + d.z * t0, o.z + d.z * t1);
        let cmin = h00.min(h10).min(h01).min(h11);
        let cmax = h00.max(h10).max(h01).max(h11);
        if z0.min(z1) > cmax + 1e-9 || z0.max(z1) < cmin - 1e-9 {
            return None;
        }
        let c = self.cell;
        let (x0, y0) = (self.x0 + i as f64 * c, self.y0 + j as f64 * c);
        let slack = 1e-7 * (1.0 + t1);
        let mut best: Option<(f64, Vector3<f64>)> = None;
        // Lower-right triangle (fx >= fy): h = h00 + a fx + b fy; upper-left: likewise.
        for lower in [true, false] {
            let (a, b) = if lower {
                (h10 - h00, h11 - h10)
            } else {
                (h11 - h01, h01 - h00)
            };
            // Plane z = h00 + a (x − x0)/c + b (y − y0)/c, i.e. n = (−a/c, −b/c, 1).
            let n = Vector3::new(-a / c, -b / c, 1.0);
            let denom = n.dot(d);
            if denom.abs() < 1e-15 {
                continue;
            }
            let q = Vector3::new(x0, y0, h00);
            let t = n.dot(&(q - o)) / denom;
            if t < t0 - slack || t > t1 + slack || t <= 1e-6 {
                continue;
            }
            let p = o + d * t;
            let fx = (p.x - x0) / c;
            let fy = (p.y - y0) / c;
            let e = 1e-9;
            let inside = fx >= -e && fy >= -e && fx <= 1.0 + e && fy <= 1.0 + e;
            let tri = if lower { fx >= fy - e } else { fx <= fy + e };
            if inside && tri && best.is_none_or(|(bt, _)| t < bt) {
                let n = n.normalize();
                best = Some((t, if denom > 0.0 { -n } else { n }));
            }
        }
        best
    }
}

impl World {
    fn prim_hit(
        &self,
        idx: u32,
        o: &Vector3<f64>,
        d: &Vector3<f64>,
        t0: f64,
        t1: f64,
    ) -> Option<(f64, Vector3<f64>)> {
        match self.prims[idx as usize].shape {
            Shape::Convex { start, len } => intersect_convex(
                &self.planes[start as usize..(start + len) as usize],
                o,
                d,
                t0,
                t1,
            ),
            Shape::Ellipsoid { center, inv_radii } => {
                intersect_ellipsoid(&center, &inv_radii, o, d, t0, t1)
            }
        }
    }

    /// Closest object hit in `[t0, t1]` (terrain excluded).
    fn bvh_closest(&self, o: &Vector3<f64>, d: &Vector3<f64>, t0: f64, t1: f64) -> Option<RawHit> {
        let nodes = &self.bvh.nodes;
        if nodes.is_empty() {
            return None;
        }
        let inv = d.map(|v| 1.0 / v);
        let mut best_t = t1;
        let mut best: Option<RawHit> = None;
        let mut stack = [0u32; 64];
        let mut sp = 0usize;
        nodes[0].aabb.hit(o, &inv, t0, best_t)?;
        stack[sp] = 0;
        sp += 1;
        while sp > 0 {
            sp -= 1;
            let node = &nodes[stack[sp] as usize];
            if node.count > 0 {
                let first = node.first as usize;
                for &pi in &self.bvh.order[first..first + node.count as usize] {
                    if let Some((t, n)) = self.prim_hit(pi, o, d, t0, best_t) {
                        best_t = t;
                        best = Some(RawHit {
                            t,
                            normal: n,
                            prim: pi,
                        });
                    }
                }
                continue;
            }
            let l = node.first as usize;
            let hl = nodes[l].aabb.hit(o, &inv, t0, best_t);
            let hr = nodes[l + 1].aabb.hit(o, &inv, t0, best_t);
            // Push the farther child first so the nearer one is visited first.
            match (hl, hr) {
                (Some(a), Some(b)) => {
                    let (near, far) = if a <= b { (l, l + 1) } else { (l + 1, l) };
                    if sp + 2 <= stack.len() {
                        stack[sp] = far as u32;
                        stack[sp + 1] = near as u32;
                        sp += 2;
                    }
                }
                (Some(_), None) => {
                    stack[sp] = l as u32;
                    sp += 1;
                }
                (None, Some(_)) => {
                    stack[sp] = (l + 1) as u32;
                    sp += 1;
                }
                (None, None) => {}
            }
        }
        best
    }

    /// True when any object blocks the ray within `[t0, t1]` (terrain excluded: with a few
    /// metres of relief over hundreds of metres it cannot shadow itself at sun elevations > 5°).
    pub(crate) fn occluded(&self, o: &Vector3<f64>, d: &Vector3<f64>, t0: f64, t1: f64) -> bool {
        let nodes = &self.bvh.nodes;
        if nodes.is_empty() {
            return false;
        }
        let inv = d.map(|v| 1.0 / v);
        let mut stack = [0u32; 64];
        let mut sp = 1usize;
        while sp > 0 {
            sp -= 1;
            let node = &nodes[stack[sp] as usize];
            if node.aabb.hit(o, &inv, t0, t1).is_none() {
                continue;
            }
            if node.count > 0 {
                let first = node.first as usize;
                for &pi in &self.bvh.order[first..first + node.count as usize] {
                    if self.prim_hit(pi, o, d, t0, t1).is_some() {
                        return true;
                    }
                }
            } else if sp + 2 <= stack.len() {
                stack[sp] = node.first;
                stack[sp + 1] = node.first + 1;
                sp += 2;
            }
        }
        false
    }

    /// Closest hit of a unit-direction ray, terrain included.
    pub(crate) fn trace(&self, o: &Vector3<f64>, d: &Vector3<f64>) -> Option<RawHit> {
        let terrain = self
            .terrain
            .intersect(o, d, f64::INFINITY)
            .map(|(t, n)| RawHit {
                t,
                normal: n,
                prim: TERRAIN,
            });
        let t1 = terrain.map_or(f64::INFINITY, |h| h.t);
        // Objects never rise above `top_z`: clip the object search to the slab below it.
        let t0 = if o.z > self.top_z && d.z < 0.0 {
            (self.top_z - o.z) / d.z
        } else {
            1e-6
        };
        if o.z > self.top_z && d.z >= 0.0 {
            return terrain;
        }
        self.bvh_closest(o, d, t0.max(1e-6), t1).or(terrain)
    }

    /// Coarse material of a hit (for the public [`Hit`]).
    pub(crate) fn material_of(&self, prim: u32, p: &Vector3<f64>, n: &Vector3<f64>) -> Material {
        if prim == TERRAIN {
            return match self.road_index.query(&self.roads, p.x, p.y) {
                Some(_) => Material::Road,
                None => Material::Ground,
            };
        }
        match self.classes[prim as usize] {
            Class::Body(_) => {
                if n.z > 0.7 {
                    Material::Roof
                } else {
                    Material::Facade
                }
            }
            Class::PitchedRoof(_) => {
                if n.z.abs() > 0.3 {
                    Material::Roof
                } else {
                    Material::Facade
                }
            }
            Class::RoofUnit(_) => Material::Roof,
            Class::Rock(..) => Material::Rubble,
            Class::Crown(..) | Class::Trunk => Material::Vegetation,
            Class::CarBody(_) | Class::CarCabin(_) => Material::Vehicle,
        }
    }

    /// First surface hit by the ray from `origin` along `dir` (normalised here; a zero or
    /// non-finite direction gives `None`). `t` of the hit is in metres.
    pub fn raycast(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<Hit> {
        let d = dir.try_normalize(1e-300)?;
        if !(origin.coords.iter().all(|v| v.is_finite()) && d.iter().all(|v| v.is_finite())) {
            return None;
        }
        let h = self.trace(&origin.coords, &d)?;
        let p = origin.coords + d * h.t;
        Some(Hit {
            t: h.t,
            point: Point3::from(p),
            normal: h.normal,
            material: self.material_of(h.prim, &p, &h.normal),
        })
    }
}
