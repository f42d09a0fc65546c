//! Procedural materials: gradient noise, prefiltered patterns and the albedo of every surface.
//!
//! Aliasing is removed at the source rather than by brute-force supersampling: every pattern
//! takes the world-space footprint `fw` of the pixel (metres) and drops or box-filters detail
//! finer than it. A NeRF cannot fit per-view aliasing noise, and a 1-sample-per-pixel texture
//! lookup is what keeps the renderer at tens of images per second on two cores.

use nalgebra::Vector3;

use super::noise::{
    Rgb, cell_rand, detail, fbm2, fbm3, mix, periodic_pulse, pulse, scale, smooth, spots, srgb,
    vary,
};
use super::raycast::TERRAIN;
use super::rng::{hash3, unit};
use super::world::{Building, Class, RoofMat, SIDEWALK_M, WallKind, World};

impl World {
    /// Linear albedo at world point `p` with geometric normal `n` on primitive `prim`, prefiltered
    /// for a pixel footprint of `fw` metres.
    pub(crate) fn albedo(&self, p: &Vector3<f64>, n: &Vector3<f64>, prim: u32, fw: f32) -> Rgb {
        if prim == TERRAIN {
            return self.ground_albedo(p.x, p.y, fw);
        }
        let s = self.noise_seed;
        let pf = [p.x as f32, p.y as f32, p.z as f32];
        match self.classes[prim as usize] {
            Class::Body(b) => {
                let bd = &self.buildings[b as usize];
                if n.z > 0.7 {
                    self.flat_roof_albedo(bd, p, fw)
                } else {
                    self.facade_albedo(bd, p, n, fw, true)
                }
            }
            Class::PitchedRoof(b) => {
                let bd = &self.buildings[b as usize];
                if n.z.abs() > 0.3 {
                    self.pitched_roof_albedo(bd, p, n, fw)
                } else {
                    self.facade_albedo(bd, p, n, fw, false)
                }
            }
            Class::RoofUnit(b) => {
                let bd = &self.buildings[b as usize];
                let base = srgb(175, 178, 180);
                let ribs = if n.z > 0.7 {
                    let l = bd.local(p.x, p.y);
                    let u = (l[0] as f32).rem_euclid(0.3);
                    1.0 - 0.35 * periodic_pulse(u, 0.0, 0.08, 0.3, fw)
                } else {
                    1.0
                };
                vary(scale(base, ribs), 0.15, fbm3(pf, 1.5, 3, s ^ 0x51, fw))
            }
            Class::Rock(col, seed) => {
                let big = fbm3(pf, 1.2, 4, seed, fw);
                let speck = fbm3(pf, 9.0, 2, seed ^ 3, fw);
                let c = vary(col, 0.35, big);
                // Dust settles on upward faces.
                let dust = (0.35 * n.z.max(0.0) as f32) * (0.6 + 0.4 * speck);
                vary(
                    mix(c, srgb(170, 160, 140), dust.clamp(0.0, 1.0)),
                    0.25,
                    speck,
                )
            }
            Class::Crown(col, seed) => {
                let leaves = fbm3(pf, 2.5, 5, seed, fw);
                // Clumps of leaves with dark gaps between them.
                let clump = smooth(-0.35, 0.35, leaves);
                let c = mix(scale(col, 0.45), scale(col, 1.25), clump);
                let hue = fbm3(pf, 0.4, 2, seed ^ 9, fw);
                mix(c, srgb(120, 125, 50), (0.3 * hue).clamp(0.0, 0.3))
            }
            Class::Trunk => vary(srgb(85, 65, 45), 0.3, fbm3(pf, 4.0, 3, s ^ 0x77, fw)),
            Class::CarBody(paint) => vary(paint, 0.06, fbm3(pf, 2.0, 2, s ^ 0x78, fw)),
            Class::CarCabin(paint) => {
                if n.z > 0.7 {
                    // Roof panel with a darker sunroof/antenna strip for some structure.
                    let c = vary(paint, 0.06, fbm3(pf, 2.0, 2, s ^ 0x79, fw));
                    scale(c, 0.9)
                } else {
                    srgb(35, 40, 48)
                }
            }
        }
    }

    fn ground_albedo(&self, x: f64, y: f64, fw: f32) -> Rgb {
        let s = self.noise_seed;
        let (xf, yf) = (x as f32, y as f32);
        let natural = || {
            let region = fbm2(xf, yf, 1.0 / 45.0, 3, s ^ 0x10, fw);
            let patch = fbm2(xf, yf, 1.0 / 7.0, 3, s ^ 0x11, fw);
            let clump = fbm2(xf, yf, 0.6, 3, s ^ 0x14, fw);
            let fine = fbm2(xf, yf, 2.5, 3, s ^ 0x12, fw);
            // Only evaluate the materials that the blend actually shows.
            let m = smooth(0.05, 0.35, region + 0.3 * patch);
            let grass = if m < 1.0 {
                let grass = mix(
                    srgb(62, 92, 36),
                    srgb(125, 140, 64),
                    smooth(-0.4, 0.4, patch),
                );
                let grass = vary(grass, 0.55, 1.2 * clump + 0.5 * fine);
                // Shrubs and flower/weed spots: blob features at the 1 m scale.
                let (shrub, sr) = spots(xf, yf, 3.0, 0.35, 0.3, 1.0, s ^ 0x15, fw);
                let shrub_col = mix(srgb(40, 62, 25), srgb(95, 105, 40), sr);
                let grass = mix(grass, shrub_col, shrub);
                let (flower, fr) = spots(xf, yf, 1.3, 0.2, 0.15, 0.35, s ^ 0x16, fw);
                mix(
                    grass,
                    mix(srgb(200, 190, 120), srgb(170, 150, 150), fr),
                    0.7 * flower,
                )
            } else {
                [0.0; 3]
            };
            let soil = if m > 0.0 {
                let soil = vary(srgb(125, 100, 72), 0.4, 1.2 * clump + fine + 0.5 * patch);
                let (stone, st) = spots(xf, yf, 1.5, 0.3, 0.12, 0.4, s ^ 0x17, fw);
                mix(soil, scale(srgb(170, 160, 145), 0.8 + 0.4 * st), stone)
            } else {
                [0.0; 3]
            };
            let mut c = mix(grass, soil, m);
            for f in &self.rubble {
                let reach = 1.35 * f.radius + 6.0;
                if (x - f.center[0]).abs() > reach || (y - f.center[1]).abs() > reach {
                    continue;
                }
                let d = ((x - f.center[0]).powi(2) + (y - f.center[1]).powi(2)).sqrt() as f32;
                let w = 1.0
                    - smooth(
                        f.radius as f32,
                        1.35 * f.radius as f32 + 2.0,
                        d + 3.0 * patch,
                    );
                if w > 0.0 {
                    let grit = fbm2(xf, yf, 2.0, 4, s ^ 0x13, fw);
                    let dusty = vary(srgb(145, 135, 118), 0.45, grit + clump + 0.5 * patch);
                    // Small debris fragments lying flat in the dust.
                    let (frag, fr) = spots(xf, yf, 0.9, 0.45, 0.1, 0.3, s ^ 0x18, fw);
                    let frag_col = mix(srgb(150, 80, 60), srgb(90, 88, 85), fr);
                    c = mix(c, mix(dusty, frag_col, frag), w);
                }
            }
            c
        };
        let Some(q) = self.road_index.query(&self.roads, x, y) else {
            return natural();
        };
        let (d, sl, w) = (q.d as f32, q.s as f32, q.half_width as f32);
        let ad = d.abs();
        if ad > w {
            // Sidewalk: 1 m concrete slabs aligned with the road, then a kerb.
            let u = sl.rem_euclid(1.0);
            let v = (ad - w).rem_euclid(1.0);
            let slab = hash3(
                sl.div_euclid(1.0) as i32,
                (ad - w).div_euclid(1.0) as i32,
                3,
                s,
            );
            let groove =
                periodic_pulse(u, 0.0, 0.04, 1.0, fw).max(periodic_pulse(v, 0.0, 0.04, 1.0, fw));
            let k = detail(1.0, fw);
            let mut c = vary(srgb(158, 154, 146), 0.12, unit(slab) * 2.0 - 1.0);
            c = vary(c, 0.2, fbm2(xf, yf, 2.0, 3, s ^ 0x20, fw));
            c = scale(c, 1.0 - 0.3 * groove * k);
            let kerb = pulse(ad - w, 0.0, 0.18, fw);
            let c = mix(c, srgb(200, 198, 190), kerb);
            // Grass creeps over the outer edge.
            let edge = smooth(
                SIDEWALK_M as f32 - 0.4,
                SIDEWALK_M as f32,
                ad - w + 0.3 * fbm2(xf, yf, 1.0, 2, s, fw),
            );
            return mix(c, natural(), edge);
        }
        let grain = fbm2(xf, yf, 3.0, 4, s ^ 0x30, fw);
        let wear = fbm2(xf, yf, 1.0 / 6.0, 3, s ^ 0x31, fw);
        let mottle = fbm2(xf, yf, 0.7, 3, s ^ 0x34, fw);
        let mut c = vary(srgb(74, 74, 77), 0.3, grain + 0.8 * wear + 1.2 * mottle);
        // Rectangular repair patches (older, lighter or fresh, darker) in road coordinates.
        let cell = 8.0f32;
        let ci = sl.div_euclid(cell) as i32;
        let side = if d >= 0.0 { 1 } else { 0 };
        let hp = hash3(ci, side, 5, s);
        if unit(hp) < 0.45 {
            let len = 2.0 + 4.0 * unit(hp.rotate_left(8));
            let s0 = (cell - len) * unit(hp.rotate_left(16));
            let d0 = 0.3 + (w - 1.5) * 0.5 * unit(hp.rotate_left(24));
            let d1 = (d0 + 1.0 + 2.0 * unit(hp.rotate_left(4))).min(w - 0.6);
            let cov = pulse(sl.rem_euclid(cell), s0, s0 + len, fw) * pulse(ad, d0, d1, fw);
            let tone = if unit(hp.rotate_left(12)) < 0.5 {
                srgb(52, 52, 55)
            } else {
                srgb(98, 97, 95)
            };
            c = mix(c, vary(tone, 0.2, grain), cov);
        }
        // Oil stains along the middle of each lane.
        let (oil, _) = spots(sl, ad - 0.5 * w, 2.5, 0.35, 0.2, 0.6, s ^ 0x35, fw);
        c = scale(c, 1.0 - 0.35 * oil);
        let crack = fbm2(xf, yf, 0.7, 3, s ^ 0x33, fw).abs();
        c = scale(
            c,
            1.0 - 0.5 * (1.0 - smooth(0.0, 0.03, crack)) * detail(0.5, fw),
        );
        let paint = srgb(230, 230, 220);
        let edge_line = pulse(ad, w - 0.5, w - 0.35, fw);
        let dash =
            pulse(d, -0.08, 0.08, fw) * periodic_pulse(sl.rem_euclid(9.0), 0.0, 3.0, 9.0, fw);
        let worn = 0.75 + 0.25 * grain;
        mix(c, scale(paint, worn), (edge_line + dash).min(1.0) * 0.9)
    }

    fn facade_albedo(
        &self,
        bd: &Building,
        p: &Vector3<f64>,
        n: &Vector3<f64>,
        fw: f32,
        windows: bool,
    ) -> Rgb {
        let s = bd.seed;
        let l = bd.local(p.x, p.y);
        // Horizontal coordinate along the wall from its left corner, and the wall's length.
        let nl = bd.local_dir(n.x, n.y);
        let (u, len, face) = if nl[0].abs() > nl[1].abs() {
            (
                l[1] * nl[0].signum() + bd.half[1],
                2.0 * bd.half[1],
                if nl[0] > 0.0 { 0 } else { 1 },
            )
        } else {
            (
                -l[0] * nl[1].signum() + bd.half[0],
                2.0 * bd.half[0],
                if nl[1] > 0.0 { 2 } else { 3 },
            )
        };
        let (u, len) = (u as f32, len as f32);
        let v = (p.z - bd.base_z) as f32 - 0.5;
        let fseed = s.wrapping_add(face * 101);
        let stain = fbm2(u * 0.7, v * 0.18, 1.0, 4, fseed ^ 0x40, fw);
        let blotch = fbm2(u, v, 0.6, 4, fseed ^ 0x41, fw);
        let mut c = match bd.wall_kind {
            WallKind::Brick => {
                let (bw, bh) = (0.5f32, 0.2f32);
                let row = (v / bh).floor();
                let uu = u + if row as i32 % 2 == 0 { 0.0 } else { 0.5 * bw };
                let col = (uu / bw).floor();
                let r = cell_rand(col as i32, row as i32, fseed);
                let k = detail(bh, fw);
                let mortar = periodic_pulse(uu.rem_euclid(bw), 0.0, 0.03, bw, fw)
                    .max(periodic_pulse(v.rem_euclid(bh), 0.0, 0.03, bh, fw));
                let brick = vary(bd.wall_col, 0.25 * k, 2.0 * r - 1.0);
                let c = mix(
                    brick,
                    srgb(175, 170, 160),
                    0.15 * (1.0 - k) + mortar * k * 0.8,
                );
                vary(c, 0.12, blotch)
            }
            WallKind::Plaster => vary(bd.wall_col, 0.18, blotch + 0.6 * stain),
            WallKind::Concrete => {
                let ph = bd.floor_h as f32;
                let pw = 3.0f32;
                let joint = periodic_pulse(u.rem_euclid(pw), 0.0, 0.05, pw, fw)
                    .max(periodic_pulse(v.rem_euclid(ph), 0.0, 0.05, ph, fw));
                let panel = cell_rand((u / pw).floor() as i32, (v / ph).floor() as i32, fseed);
                let c = vary(bd.wall_col, 0.1, 2.0 * panel - 1.0);
                scale(vary(c, 0.15, blotch + 0.8 * stain), 1.0 - 0.35 * joint)
            }
        };
        // Darker, dirtier plinth near the ground.
        c = scale(c, 0.8 + 0.2 * smooth(0.0, 1.2, v));
        if !windows {
            return c;
        }
        let height = (bd.eave_z - bd.base_z) as f32 - 0.5;
        let sp = bd.win_spacing as f32;
        let ncol = (len / sp).floor();
        if ncol < 1.0 {
            return c;
        }
        let margin = 0.5 * (len - ncol * sp);
        let uc = u - margin;
        if uc < 0.0 || uc > ncol * sp {
            return c;
        }
        let fh = bd.floor_h as f32;
        let floor = (v / fh).floor();
        if v < 0.0 || (floor + 1.0) * fh > height + 0.3 {
            return c;
        }
        let wf = bd.win_frac as f32;
        let cu = uc.rem_euclid(sp);
        let cv = v.rem_euclid(fh);
        let (u0, u1) = (0.5 * sp * (1.0 - wf), 0.5 * sp * (1.0 + wf));
        let (v0, v1) = if floor == 0.0 { (0.7, 2.5) } else { (0.9, 2.4) };
        let frame_cov = pulse(cu, u0 - 0.1, u1 + 0.1, fw) * pulse(cv, v0 - 0.1, v1 + 0.12, fw);
        let glass_cov = pulse(cu, u0, u1, fw) * pulse(cv, v0, v1, fw);
        let wi = hash3((uc / sp).floor() as i32, floor as i32, face as i32, s);
        // Per-window variation (curtains, lights, reflections baked as albedo) is fixed in the
        // world, so every view sees the same value.
        let g = vary(bd.glass_col, 0.5, 2.0 * unit(wi) - 1.0);
        let g = mix(g, srgb(150, 155, 160), 0.25 * (1.0 - cv / fh));
        let c = mix(c, bd.trim_col, frame_cov);
        mix(c, g, glass_cov)
    }

    fn flat_roof_albedo(&self, bd: &Building, p: &Vector3<f64>, fw: f32) -> Rgb {
        let l = bd.local(p.x, p.y);
        let edge = (bd.half[0] - l[0].abs()).min(bd.half[1] - l[1].abs()) as f32;
        let (x, y) = (p.x as f32, p.y as f32);
        let grit = fbm2(x, y, 5.0, 3, bd.seed ^ 0x50, fw);
        let stains = fbm2(x, y, 0.25, 4, bd.seed ^ 0x51, fw);
        let mut c = vary(bd.roof_col, 0.35, grit + 1.2 * stains);
        let (puddle, pr) = spots(x, y, 4.0, 0.4, 0.5, 1.35, bd.seed ^ 0x52, fw);
        c = scale(c, 1.0 - (0.25 + 0.2 * pr) * puddle);
        // Membrane seams every 2 m in one direction.
        let seam = periodic_pulse((l[0] as f32).rem_euclid(2.0), 0.0, 0.06, 2.0, fw);
        c = scale(c, 1.0 - 0.2 * seam);
        // Parapet coping around the edge.
        mix(c, srgb(200, 195, 185), pulse(edge, -1.0, 0.35, fw))
    }

    fn pitched_roof_albedo(
        &self,
        bd: &Building,
        p: &Vector3<f64>,
        n: &Vector3<f64>,
        fw: f32,
    ) -> Rgb {
        // Coordinates on the roof plane: u along the eave, v up the slope.
        let t = Vector3::new(-n.y, n.x, 0.0)
            .try_normalize(1e-9)
            .unwrap_or(Vector3::x());
        let b = n.cross(&t);
        let c0 = Vector3::new(bd.center[0], bd.center[1], bd.eave_z);
        let (u, v) = ((p - c0).dot(&t) as f32, (p - c0).dot(&b) as f32);
        let (x, y) = (p.x as f32, p.y as f32);
        let dirt = fbm2(x, y, 0.3, 4, bd.seed ^ 0x60, fw);
        match bd.roof_mat {
            RoofMat::Tiles => {
                let (tw, th) = (0.3f32, 0.35f32);
                let row = (v / th).floor();
                let uu = u + if row as i32 % 2 == 0 { 0.0 } else { 0.5 * tw };
                let r = cell_rand((uu / tw).floor() as i32, row as i32, bd.seed);
                let k = detail(th, fw);
                let shadow = periodic_pulse(v.rem_euclid(th), 0.0, 0.07, th, fw);
                let c = vary(bd.roof_col, 0.3 * k, 2.0 * r - 1.0);
                let c = scale(c, 1.0 - 0.35 * shadow * k - 0.12 * (1.0 - k));
                // Moss and soot patches, and per-course colour drift from replaced tiles.
                let moss = smooth(0.1, 0.45, dirt);
                let course = cell_rand(0, (v / (4.0 * th)).floor() as i32, bd.seed ^ 7);
                let c = vary(c, 0.2, 2.0 * course - 1.0);
                let c = mix(c, srgb(80, 85, 55), 0.6 * moss);
                // Roof windows on a coarse grid.
                let (gu, gv) = (3.5f32, 3.0f32);
                let hw = hash3((u / gu).floor() as i32, (v / gv).floor() as i32, 8, bd.seed);
                let win = if unit(hw) < 0.25 {
                    pulse(u.rem_euclid(gu), 1.0, 2.0, fw) * pulse(v.rem_euclid(gv), 0.8, 2.1, fw)
                } else {
                    0.0
                };
                let c = mix(c, scale(bd.glass_col, 0.8), win);
                vary(c, 0.2, dirt)
            }
            RoofMat::Metal => {
                let rib = periodic_pulse(u.rem_euclid(0.6), 0.0, 0.06, 0.6, fw);
                let c = scale(bd.roof_col, 1.0 + 0.35 * rib);
                let rust = smooth(0.15, 0.5, dirt);
                vary(
                    mix(c, srgb(120, 70, 40), 0.4 * rust),
                    0.15,
                    fbm2(u, v, 2.0, 3, bd.seed, fw),
                )
            }
            RoofMat::Gravel => vary(bd.roof_col, 0.3, fbm2(x, y, 4.0, 4, bd.seed, fw) + dirt),
        }
    }
}
