//! Scene generation: terrain, roads, buildings, rubble and trees, all from one seed.

use nalgebra::{Point3, Rotation3, Unit, Vector3};
use serde::{Deserialize, Serialize};

use super::error::SynthError;
use super::geometry::{Aabb, Bvh, Plane, Prim, Shape};
use super::noise::{Rgb, fbm2, srgb};
use super::rng::Rng;

/// Scene-content parameters (see [`crate::SynthConfig`] for the whole configuration).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct WorldConfig {
    /// Side of the square content area centred at the origin (buildings, rubble, survey), m.
    pub extent_m: f64,
    /// Terrain apron around the content so oblique views near the edge still see ground, m.
    pub margin_m: f64,
    /// Peak-to-peak scale of the terrain relief, m.
    pub terrain_relief_m: f64,
    /// Terrain grid spacing, m.
    pub terrain_cell_m: f64,
    /// Number of roads.
    pub roads: usize,
    /// Number of buildings to place (fewer when the area is full).
    pub buildings: usize,
    /// Range of building footprint sides, m.
    pub building_size_m: [f64; 2],
    /// Range of building eave heights above ground, m.
    pub building_height_m: [f64; 2],
    /// Number of rubble fields.
    pub rubble_fields: usize,
    /// Range of rubble-field radii, m.
    pub rubble_radius_m: [f64; 2],
    /// Rubble pieces per field.
    pub rocks_per_field: usize,
    /// Number of trees.
    pub trees: usize,
    /// Parked cars per 100 m of road (both sides together); static, like everything else.
    pub cars_per_100m: f64,
    /// Sun azimuth, degrees clockwise from north.
    pub sun_azimuth_deg: f64,
    /// Sun elevation above the horizon, degrees.
    pub sun_elevation_deg: f64,
}

impl Default for WorldConfig {
    fn default() -> Self {
        WorldConfig {
            extent_m: 200.0,
            margin_m: 80.0,
            terrain_relief_m: 4.0,
            terrain_cell_m: 1.0,
            roads: 3,
            buildings: 28,
            building_size_m: [8.0, 30.0],
            building_height_m: [5.0, 18.0],
            rubble_fields: 2,
            rubble_radius_m: [8.0, 16.0],
            rocks_per_field: 250,
            trees: 60,
            cars_per_100m: 4.0,
            sun_azimuth_deg: 150.0,
            sun_elevation_deg: 50.0,
        }
    }
}

impl WorldConfig {
    pub(crate) fn validate(&self) -> Result<(), SynthError> {
        let bad =
            |field: &'static str, reason: String| Err(SynthError::InvalidConfig { field, reason });
        let positive = [
            ("world.extent_m", self.extent_m),
            ("world.terrain_cell_m", self.terrain_cell_m),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, format!("must be a positive number, got {v}"));
            }
        }
        for (field, v) in [
            ("world.cars_per_100m", self.cars_per_100m),
            ("world.margin_m", self.margin_m),
            ("world.terrain_relief_m", self.terrain_relief_m),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(field, format!("must be a non-negative number, got {v}"));
            }
        }
        let cells = (self.extent_m + 2.0 * self.margin_m) / self.terrain_cell_m;
        if cells > 8192.0 {
            return bad(
                "world.terrain_cell_m",
                format!("terrain grid would have {cells:.0} cells per side (max 8192)"),
            );
        }
        for (field, r) in [
            ("world.building_size_m", self.building_size_m),
            ("world.building_height_m", self.building_height_m),
            ("world.rubble_radius_m", self.rubble_radius_m),
        ] {
            if !(r[0].is_finite() && r[1].is_finite() && r[0] > 0.0 && r[0] <= r[1]) {
                return bad(
                    field,
                    format!("must be a range [lo, hi] with 0 < lo <= hi, got {r:?}"),
                );
            }
        }
        if !(self.sun_elevation_deg > 5.0 && self.sun_elevation_deg <= 90.0) {
            return bad(
                "world.sun_elevation_deg",
                format!("must be in (5, 90], got {}", self.sun_elevation_deg),
            );
        }
        if !self.sun_azimuth_deg.is_finite() {
            return bad("world.sun_azimuth_deg", "must be finite".into());
        }
        let objects = self.buildings + self.rubble_fields * self.rocks_per_field + self.trees;
        if objects > 2_000_000 {
            return bad(
                "world",
                format!("{objects} objects is more than the 2,000,000 supported"),
            );
        }
        Ok(())
    }
}

/// Coarse surface class of a ray hit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Material {
    /// Grass, soil or dusty ground.
    Ground,
    /// Asphalt, markings and sidewalks.
    Road,
    /// A building wall (facade or gable end).
    Facade,
    /// A roof or rooftop equipment.
    Roof,
    /// A piece of rubble.
    Rubble,
    /// Tree crown or trunk.
    Vegetation,
    /// A parked car.
    Vehicle,
}

/// The piecewise-linear terrain: a height grid split into two triangles per cell along the
/// `(0,0)–(1,1)` diagonal; [`World::height_at`] and the ray caster use the same surface, so
/// rendered depth and heights agree exactly.
#[derive(Clone, Debug)]
pub(crate) struct Terrain {
    pub x0: f64,
    pub y0: f64,
    pub cell: f64,
    pub nx: usize,
    pub ny: usize,
    /// `(nx + 1) × (ny + 1)` vertex heights, row-major in y.
    pub heights: Vec<f64>,
    pub hmin: f64,
    pub hmax: f64,
    /// Height of the infinite plane outside the grid (the apron fades to it).
    pub base: f64,
    /// Per block of `BLOCK × BLOCK` cells: (min, max) height, for skipping empty space.
    pub blocks: Vec<(f64, f64)>,
    pub nbx: usize,
    pub nby: usize,
}

/// Terrain cells per block side in the min/max hierarchy.
pub(crate) const BLOCK: usize = 8;

impl Terrain {
    #[inline]
    pub fn h(&self, i: usize, j: usize) -> f64 {
        self.heights[j * (self.nx + 1) + i]
    }

    fn build_blocks(&mut self) {
        self.nbx = self.nx.div_ceil(BLOCK);
        self.nby = self.ny.div_ceil(BLOCK);
        self.blocks = vec![(f64::INFINITY, f64::NEG_INFINITY); self.nbx * self.nby];
        for j in 0..=self.ny {
            for i in 0..=self.nx {
                let h = self.h(i, j);
                // A vertex on a block border belongs to both blocks.
                for bj in [j.saturating_sub(1) / BLOCK, j / BLOCK] {
                    for bi in [i.saturating_sub(1) / BLOCK, i / BLOCK] {
                        if bi < self.nbx && bj < self.nby {
                            let b = &mut self.blocks[bj * self.nbx + bi];
                            b.0 = b.0.min(h);
                            b.1 = b.1.max(h);
                        }
                    }
                }
            }
        }
    }

    pub fn height_at(&self, x: f64, y: f64) -> f64 {
        let gx = (x - self.x0) / self.cell;
        let gy = (y - self.y0) / self.cell;
        if !(gx >= 0.0 && gy >= 0.0 && gx <= self.nx as f64 && gy <= self.ny as f64) {
            return self.base;
        }
        let i = (gx.floor() as usize).min(self.nx - 1);
        let j = (gy.floor() as usize).min(self.ny - 1);
        let fx = gx - i as f64;
        let fy = gy - j as f64;
        let h00 = self.h(i, j);
        let h10 = self.h(i + 1, j);
        let h01 = self.h(i, j + 1);
        let h11 = self.h(i + 1, j + 1);
        if fx >= fy {
            h00 + (h10 - h00) * fx + (h11 - h10) * fy
        } else {
            h00 + (h11 - h01) * fx + (h01 - h00) * fy
        }
    }
}

/// A road as a polyline with its cumulative arc length (for dashed markings).
#[derive(Clone, Debug)]
pub(crate) struct Road {
    pub pts: Vec<[f64; 2]>,
    pub cum: Vec<f64>,
    pub half_width: f64,
}

/// Where a ground point lies relative to the nearest road.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RoadQuery {
    /// Signed distance from the centre line, m.
    pub d: f64,
    /// Arc length along the road, m.
    pub s: f64,
    pub half_width: f64,
}

/// Width of the sidewalk band on each side of a road, m.
pub(crate) const SIDEWALK_M: f64 = 2.0;

/// Buckets of road segments so a ground lookup tests only nearby segments.
#[derive(Clone, Debug)]
pub(crate) struct RoadIndex {
    x0: f64,
    y0: f64,
    cell: f64,
    nx: usize,
    ny: usize,
    /// Per bucket: (road, segment) pairs.
    buckets: Vec<Vec<(u32, u32)>>,
}

impl RoadIndex {
    fn build(roads: &[Road], lo: [f64; 2], hi: [f64; 2]) -> Self {
        let cell = 8.0;
        let nx = (((hi[0] - lo[0]) / cell).ceil() as usize).max(1);
        let ny = (((hi[1] - lo[1]) / cell).ceil() as usize).max(1);
        let mut buckets = vec![Vec::new(); nx * ny];
        for (ri, r) in roads.iter().enumerate() {
            let reach = r.half_width + SIDEWALK_M + 0.5;
            for s in 0..r.pts.len() - 1 {
                let (a, b) = (r.pts[s], r.pts[s + 1]);
                let bx0 = ((a[0].min(b[0]) - reach - lo[0]) / cell).floor().max(0.0) as usize;
                let by0 = ((a[1].min(b[1]) - reach - lo[1]) / cell).floor().max(0.0) as usize;
                let bx1 = ((a[0].max(b[0]) + reach - lo[0]) / cell).floor().max(0.0) as usize;
                let by1 = ((a[1].max(b[1]) + reach - lo[1]) / cell).floor().max(0.0) as usize;
                for by in by0..=by1.min(ny - 1) {
                    for bx in bx0..=bx1.min(nx - 1) {
                        buckets[by * nx + bx].push((ri as u32, s as u32));
                    }
                }
            }
        }
        RoadIndex {
            x0: lo[0],
            y0: lo[1],
            cell,
            nx,
            ny,
            buckets,
        }
    }

    pub fn query(&self, roads: &[Road], x: f64, y: f64) -> Option<RoadQuery> {
        let bx = ((x - self.x0) / self.cell).floor();
        let by = ((y - self.y0) / self.cell).floor();
        if bx < 0.0 || by < 0.0 || bx >= self.nx as f64 || by >= self.ny as f64 {
            return None;
        }
        let mut best: Option<(f64, RoadQuery)> = None;
        for &(ri, si) in &self.buckets[by as usize * self.nx + bx as usize] {
            let r = &roads[ri as usize];
            let (a, b) = (r.pts[si as usize], r.pts[si as usize + 1]);
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let len2 = dx * dx + dy * dy;
            let u = (((x - a[0]) * dx + (y - a[1]) * dy) / len2).clamp(0.0, 1.0);
            let (px, py) = (a[0] + u * dx, a[1] + u * dy);
            let dist = ((x - px).powi(2) + (y - py).powi(2)).sqrt();
            if dist > r.half_width + SIDEWALK_M || best.is_some_and(|(bd, _)| bd <= dist) {
                continue;
            }
            let len = len2.sqrt();
            let side = if dx * (y - a[1]) - dy * (x - a[0]) >= 0.0 {
                1.0
            } else {
                -1.0
            };
            best = Some((
                dist,
                RoadQuery {
                    d: side * dist,
                    s: r.cum[si as usize] + u * len,
                    half_width: r.half_width,
                },
            ));
        }
        best.map(|(_, q)| q)
    }
}

/// Roof shapes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum RoofKind {
    Flat,
    Gable,
    Hip,
}

/// Facade finishes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum WallKind {
    Brick,
    Plaster,
    Concrete,
}

/// Roof coverings.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum RoofMat {
    Tiles,
    Gravel,
    Metal,
}

/// One building: an oriented box body plus an optional pitched roof.
#[derive(Clone, Debug)]
pub(crate) struct Building {
    pub center: [f64; 2],
    /// Local x axis (unit, horizontal); local y is its left-hand perpendicular.
    pub ax: [f64; 2],
    pub half: [f64; 2],
    pub base_z: f64,
    pub eave_z: f64,
    pub roof: RoofKind,
    pub wall_kind: WallKind,
    pub wall_col: Rgb,
    pub trim_col: Rgb,
    pub roof_mat: RoofMat,
    pub roof_col: Rgb,
    pub glass_col: Rgb,
    pub floor_h: f64,
    pub win_spacing: f64,
    pub win_frac: f64,
    pub seed: u32,
}

impl Building {
    /// World point → building-local (x along `ax`, y across).
    pub fn local(&self, x: f64, y: f64) -> [f64; 2] {
        let (dx, dy) = (x - self.center[0], y - self.center[1]);
        [
            dx * self.ax[0] + dy * self.ax[1],
            -dx * self.ax[1] + dy * self.ax[0],
        ]
    }

    /// World direction → building-local direction (rotation only).
    pub fn local_dir(&self, dx: f64, dy: f64) -> [f64; 2] {
        [
            dx * self.ax[0] + dy * self.ax[1],
            -dx * self.ax[1] + dy * self.ax[0],
        ]
    }

    fn ay(&self) -> [f64; 2] {
        [-self.ax[1], self.ax[0]]
    }

    fn corners(&self, pad: f64) -> [[f64; 2]; 4] {
        let (hx, hy) = (self.half[0] + pad, self.half[1] + pad);
        let ay = self.ay();
        let c = self.center;
        let p = |sx: f64, sy: f64| {
            [
                c[0] + sx * hx * self.ax[0] + sy * hy * ay[0],
                c[1] + sx * hx * self.ax[1] + sy * hy * ay[1],
            ]
        };
        [p(-1.0, -1.0), p(1.0, -1.0), p(1.0, 1.0), p(-1.0, 1.0)]
    }

    /// Separating-axis test of the two footprints each grown by `gap / 2`.
    fn overlaps(&self, other: &Building, gap: f64) -> bool {
        let a = self.corners(0.5 * gap);
        let b = other.corners(0.5 * gap);
        for axis in [self.ax, self.ay(), other.ax, other.ay()] {
            let proj = |pts: &[[f64; 2]; 4]| {
                pts.iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                        let v = p[0] * axis[0] + p[1] * axis[1];
                        (lo.min(v), hi.max(v))
                    })
            };
            let (a0, a1) = proj(&a);
            let (b0, b1) = proj(&b);
            if a1 < b0 || b1 < a0 {
                return false;
            }
        }
        true
    }
}

/// What a primitive is, for texturing.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Class {
    /// Walls and (flat) roof of building `b`.
    Body(u32),
    /// Pitched roof of building `b` (its vertical faces are gable walls).
    PitchedRoof(u32),
    /// Rooftop equipment on building `b`.
    RoofUnit(u32),
    /// Rubble piece with its base colour and pattern seed.
    Rock(Rgb, u32),
    /// Tree crown with its leaf colour and seed.
    Crown(Rgb, u32),
    /// Tree trunk.
    Trunk,
    /// Car body with its paint colour.
    CarBody(Rgb),
    /// Car cabin (glass on the sides) with its paint colour.
    CarCabin(Rgb),
}

/// A rubble field: a debris pile on dusty ground.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RubbleField {
    pub center: [f64; 2],
    pub radius: f64,
    /// Height of the debris mound at its centre (part of the terrain), m.
    pub pile_h: f64,
}

/// The generated scene. Immutable after [`World::generate`]; rendering and ray queries take
/// `&self`, so one world serves every rayon worker.
#[derive(Clone, Debug)]
pub struct World {
    pub(crate) config: WorldConfig,
    pub(crate) seed: u64,
    pub(crate) terrain: Terrain,
    pub(crate) roads: Vec<Road>,
    pub(crate) road_index: RoadIndex,
    pub(crate) buildings: Vec<Building>,
    pub(crate) rubble: Vec<RubbleField>,
    pub(crate) prims: Vec<Prim>,
    pub(crate) classes: Vec<Class>,
    pub(crate) planes: Vec<Plane>,
    pub(crate) bvh: Bvh,
    pub(crate) sun: Vector3<f64>,
    /// Highest point of any object (for bounds and shadow-ray clipping).
    pub(crate) top_z: f64,
    pub(crate) noise_seed: u32,
}

fn smoothstep(e0: f64, e1: f64, x: f64) -> f64 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Planes of an oriented box with unit axes `axes` and half extents `half` around `c`.
fn box_planes(c: Vector3<f64>, axes: [Vector3<f64>; 3], half: [f64; 3]) -> Vec<Plane> {
    let mut out = Vec::with_capacity(6);
    for k in 0..3 {
        let a = axes[k];
        out.push(Plane::new(a, a.dot(&c) + half[k]));
        out.push(Plane::new(-a, -a.dot(&c) + half[k]));
    }
    out
}

fn box_aabb(c: Vector3<f64>, axes: [Vector3<f64>; 3], half: [f64; 3]) -> Aabb {
    let mut e = Vector3::zeros();
    for k in 0..3 {
        e += axes[k].abs() * half[k];
    }
    Aabb::new(c - e, c + e)
}

struct Builder {
    prims: Vec<Prim>,
    classes: Vec<Class>,
    planes: Vec<Plane>,
}

impl Builder {
    fn convex(&mut self, planes: Vec<Plane>, aabb: Aabb, class: Class) {
        let start = self.planes.len() as u32;
        let len = planes.len() as u32;
        self.planes.extend(planes);
        self.prims.push(Prim {
            shape: Shape::Convex { start, len },
            aabb,
        });
        self.classes.push(class);
    }

    fn ellipsoid(&mut self, c: Vector3<f64>, r: Vector3<f64>, class: Class) {
        self.prims.push(Prim {
            shape: Shape::Ellipsoid {
                center: c,
                inv_radii: r.map(|v| 1.0 / v),
            },
            aabb: Aabb::new(c - r, c + r),
        });
        self.classes.push(class);
    }
}

const WALL_PALETTE: [(u8, u8, u8); 8] = [
    (168, 92, 70),
    (150, 80, 62),
    (214, 200, 170),
    (225, 215, 195),
    (190, 175, 150),
    (200, 170, 130),
    (170, 170, 165),
    (210, 190, 160),
];
const ROOF_TILE_PALETTE: [(u8, u8, u8); 4] =
    [(160, 70, 45), (130, 60, 45), (90, 80, 80), (110, 75, 55)];
const ROOF_METAL_PALETTE: [(u8, u8, u8); 4] = [
    (90, 110, 100),
    (120, 60, 50),
    (100, 105, 115),
    (150, 150, 150),
];
const ROCK_PALETTE: [(u8, u8, u8); 9] = [
    (150, 148, 142),
    (120, 118, 112),
    (175, 170, 160),
    (160, 85, 65),
    (135, 75, 60),
    (70, 68, 66),
    (120, 90, 60),
    (140, 100, 70),
    (200, 195, 185),
];

impl World {
    /// Generates the scene for `config` and `seed`; the same inputs always give the same world.
    pub fn generate(config: &WorldConfig, seed: u64) -> Result<World, SynthError> {
        config.validate()?;
        let root = Rng::new(seed);
        let noise_seed = root.fork(1).u32();
        let half = 0.5 * config.extent_m;
        let outer = half + config.margin_m;

        let roads = make_roads(config, &mut root.fork(3), half, outer);
        let road_index = RoadIndex::build(&roads, [-outer, -outer], [outer, outer]);
        let road_dist = |x: f64, y: f64| {
            road_index
                .query(&roads, x, y)
                .map_or(f64::INFINITY, |q| q.d.abs() - q.half_width)
        };

        let mut rng = root.fork(4);
        let mut rubble = Vec::new();
        for _ in 0..config.rubble_fields {
            for _ in 0..50 {
                let radius = rng.range(config.rubble_radius_m[0], config.rubble_radius_m[1]);
                let lim = (half - radius).max(0.0);
                let c = [rng.range(-lim, lim), rng.range(-lim, lim)];
                let clash = rubble
                    .iter()
                    .any(|f: &RubbleField| dist2(f.center, c).sqrt() < f.radius + radius);
                if !clash && road_dist(c[0], c[1]) > 0.5 * radius {
                    // Low enough that the mound cannot shadow itself (slope < 35°).
                    let pile_h = rng.range(0.08, 0.16) * radius;
                    rubble.push(RubbleField {
                        center: c,
                        radius,
                        pile_h,
                    });
                    break;
                }
            }
        }

        let terrain = make_terrain(config, root.fork(2).u32(), half, outer, &rubble);
        let mut b = Builder {
            prims: Vec::new(),
            classes: Vec::new(),
            planes: Vec::new(),
        };
        let buildings = make_buildings(
            config,
            &mut root.fork(5),
            half,
            &terrain,
            &roads,
            &road_dist,
            &rubble,
        );
        for (bi, bd) in buildings.iter().enumerate() {
            add_building(&mut b, bd, bi as u32, &mut root.fork(100 + bi as u64));
        }
        let mut rng = root.fork(6);
        for f in &rubble {
            add_rubble(&mut b, f, config.rocks_per_field, &terrain, &mut rng);
        }
        add_trees(
            &mut b,
            config,
            &mut root.fork(7),
            half,
            &terrain,
            &road_dist,
            &buildings,
            &rubble,
        );

        add_cars(
            &mut b,
            config,
            &mut root.fork(8),
            half,
            &terrain,
            &roads,
            &rubble,
        );

        let top_z = b
            .prims
            .iter()
            .map(|p| p.aabb.max.z)
            .fold(terrain.hmax, f64::max);
        let bvh = Bvh::build(&b.prims);
        let (az, el) = (
            config.sun_azimuth_deg.to_radians(),
            config.sun_elevation_deg.to_radians(),
        );
        let sun = Vector3::new(az.sin() * el.cos(), az.cos() * el.cos(), el.sin());
        Ok(World {
            config: config.clone(),
            seed,
            terrain,
            roads,
            road_index,
            buildings,
            rubble,
            prims: b.prims,
            classes: b.classes,
            planes: b.planes,
            bvh,
            sun,
            top_z,
            noise_seed,
        })
    }

    /// The seed the world was generated from.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// The configuration the world was generated from.
    pub fn config(&self) -> &WorldConfig {
        &self.config
    }

    /// Axis-aligned bounds `(min, max)` of everything rendered except the flat plane beyond the
    /// terrain apron: the terrain grid in x/y, lowest terrain to highest object top in z.
    pub fn bounds(&self) -> (Point3<f64>, Point3<f64>) {
        let t = &self.terrain;
        (
            Point3::new(t.x0, t.y0, t.hmin),
            Point3::new(
                t.x0 + t.nx as f64 * t.cell,
                t.y0 + t.ny as f64 * t.cell,
                self.top_z,
            ),
        )
    }

    /// Bounds of the content area (where objects stand and the survey flies).
    pub fn content_bounds(&self) -> (Point3<f64>, Point3<f64>) {
        let h = 0.5 * self.config.extent_m;
        (
            Point3::new(-h, -h, self.terrain.hmin),
            Point3::new(h, h, self.top_z),
        )
    }

    /// Terrain height at `(x, y)` (objects excluded); the flat base height outside the grid.
    pub fn height_at(&self, x: f64, y: f64) -> f64 {
        self.terrain.height_at(x, y)
    }

    /// Unit vector towards the sun.
    pub fn sun_direction(&self) -> Vector3<f64> {
        self.sun
    }

    /// The same scene under another sun (azimuth clockwise from north, elevation above the
    /// horizon, degrees): what a flight on another day or hour sees. Geometry and albedo are
    /// untouched, so a map of one sun and queries of another differ only in light and shadow.
    pub fn with_sun(
        mut self,
        azimuth_deg: f64,
        elevation_deg: f64,
    ) -> Result<World, crate::SynthError> {
        let elevation_ok = elevation_deg > 5.0 && elevation_deg <= 90.0;
        if !elevation_ok || !azimuth_deg.is_finite() {
            return Err(crate::SynthError::InvalidConfig {
                field: "sun",
                reason: format!(
                    "azimuth must be finite and elevation in (5, 90] degrees, got {azimuth_deg}, {elevation_deg}"
                ),
            });
        }
        let (az, el) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
        self.sun = Vector3::new(az.sin() * el.cos(), az.cos() * el.cos(), el.sin());
        self.config.sun_azimuth_deg = azimuth_deg;
        self.config.sun_elevation_deg = elevation_deg;
        Ok(self)
    }

    /// Number of buildings that were placed.
    pub fn building_count(&self) -> usize {
        self.buildings.len()
    }

    /// Number of geometric primitives (boxes, roofs, rubble pieces, crowns, trunks).
    pub fn primitive_count(&self) -> usize {
        self.prims.len()
    }

    /// Highest object or terrain point, m.
    pub fn top_z(&self) -> f64 {
        self.top_z
    }
}

fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)
}

fn make_terrain(
    config: &WorldConfig,
    seed: u32,
    half: f64,
    outer: f64,
    rubble: &[RubbleField],
) -> Terrain {
    let cell = config.terrain_cell_m;
    let n = ((2.0 * outer) / cell).ceil().max(1.0) as usize;
    let x0 = -0.5 * n as f64 * cell;
    let mut heights = Vec::with_capacity((n + 1) * (n + 1));
    for j in 0..=n {
        for i in 0..=n {
            let x = x0 + i as f64 * cell;
            let y = x0 + j as f64 * cell;
            // Relief fades out across the apron so the grid meets the flat plane beyond it
            // without a step.
            let edge = x.abs().max(y.abs());
            let w = 1.0 - smoothstep(half + 0.2 * (outer - half), outer - cell, edge);
            let n = fbm2(x as f32, y as f32, 1.0 / 160.0, 4, seed, 0.0) as f64;
            let mut h = w * config.terrain_relief_m * 1.4 * n;
            // Debris mounds are terrain, so pieces rest on a closed surface, not in the air.
            for f in rubble {
                let rr2 = dist2(f.center, [x, y]) / (f.radius * f.radius);
                if rr2 < 1.0 {
                    h += f.pile_h * (1.0 - rr2) * (1.0 - rr2);
                }
            }
            heights.push(h);
        }
    }
    let hmin = heights.iter().copied().fold(0.0, f64::min);
    let hmax = heights.iter().copied().fold(0.0, f64::max);
    let mut t = Terrain {
        x0,
        y0: x0,
        cell,
        nx: n,
        ny: n,
        heights,
        hmin,
        hmax,
        base: 0.0,
        blocks: Vec::new(),
        nbx: 0,
        nby: 0,
    };
    t.build_blocks();
    t
}

fn make_roads(config: &WorldConfig, rng: &mut Rng, half: f64, outer: f64) -> Vec<Road> {
    let mut roads = Vec::new();
    let mut last_angle: Option<f64> = None;
    let mut placed: Vec<(f64, f64)> = Vec::new();
    for k in 0..config.roads {
        let mut angle = 0.0;
        let mut off = 0.0;
        // Retry so that near-parallel roads keep a block's width apart.
        for _ in 0..20 {
            // Alternate roughly perpendicular directions so roads form a network.
            angle = match last_angle {
                Some(a) if k % 2 == 1 => a + std::f64::consts::FRAC_PI_2 + rng.range(-0.3, 0.3),
                _ => rng.range(0.0, std::f64::consts::PI),
            };
            off = rng.range(-0.55, 0.55) * half;
            let clash = placed.iter().any(|&(a, o)| {
                let da = (angle - a).rem_euclid(std::f64::consts::PI);
                let parallel = da.min(std::f64::consts::PI - da) < 0.4;
                // Same or opposite direction: compare offsets along the shared normal.
                let same_dir = (angle - a).cos() > 0.0;
                let o2 = if same_dir { o } else { -o };
                parallel && (off - o2).abs() < 0.45 * half
            });
            if !clash {
                break;
            }
        }
        placed.push((angle, off));
        last_angle = Some(angle);
        let dir = [angle.cos(), angle.sin()];
        let nrm = [-dir[1], dir[0]];
        let along = rng.range(-0.3, 0.3) * half;
        let c = [nrm[0] * off + dir[0] * along, nrm[1] * off + dir[1] * along];
        let len = 1.5 * outer;
        let a = [c[0] - dir[0] * len, c[1] - dir[1] * len];
        let bpt = [c[0] + dir[0] * len, c[1] + dir[1] * len];
        let bend = if rng.f64() < 0.5 {
            rng.range(-0.35, 0.35) * half
        } else {
            0.0
        };
        let ctrl = [c[0] + nrm[0] * bend, c[1] + nrm[1] * bend];
        let segs = 48;
        let mut pts = Vec::with_capacity(segs + 1);
        for s in 0..=segs {
            let t = s as f64 / segs as f64;
            let (u, v, w) = ((1.0 - t) * (1.0 - t), 2.0 * t * (1.0 - t), t * t);
            pts.push([
                u * a[0] + v * ctrl[0] + w * bpt[0],
                u * a[1] + v * ctrl[1] + w * bpt[1],
            ]);
        }
        let mut cum = vec![0.0];
        for s in 1..pts.len() {
            let l = cum[s - 1] + dist2(pts[s - 1], pts[s]).sqrt();
            cum.push(l);
        }
        roads.push(Road {
            pts,
            cum,
            half_width: rng.range(3.0, 4.5),
        });
    }
    roads
}

fn road_direction_near(roads: &[Road], p: [f64; 2]) -> Option<[f64; 2]> {
    let mut best = (f64::INFINITY, None);
    for r in roads {
        for s in 0..r.pts.len() - 1 {
            let m = [
                (r.pts[s][0] + r.pts[s + 1][0]) * 0.5,
                (r.pts[s][1] + r.pts[s + 1][1]) * 0.5,
            ];
            let d = dist2(m, p);
            if d < best.0 {
                let (dx, dy) = (r.pts[s + 1][0] - r.pts[s][0], r.pts[s + 1][1] - r.pts[s][1]);
                let l = (dx * dx + dy * dy).sqrt();
                best = (d, Some([dx / l, dy / l]));
            }
        }
    }
    best.1
}

fn make_buildings(
    config: &WorldConfig,
    rng: &mut Rng,
    half: f64,
    terrain: &Terrain,
    roads: &[Road],
    road_dist: &dyn Fn(f64, f64) -> f64,
    rubble: &[RubbleField],
) -> Vec<Building> {
    let mut out: Vec<Building> = Vec::new();
    let [smin, smax] = config.building_size_m;
    let [hmin, hmax] = config.building_height_m;
    for _ in 0..config.buildings {
        for _attempt in 0..60 {
            // Skewed towards smaller houses, with the occasional large block.
            let sx = smin + (smax - smin) * rng.f64().powf(1.6);
            let sy = (sx * rng.range(0.45, 1.0)).max(smin);
            let lim = half - 0.5 * sx.max(sy) - 1.0;
            if lim <= 0.0 {
                break;
            }
            let center = [rng.range(-lim, lim), rng.range(-lim, lim)];
            let mut ax = match road_direction_near(roads, center) {
                Some(d) if rng.f64() < 0.8 => d,
                _ => {
                    let a = rng.range(0.0, std::f64::consts::PI);
                    [a.cos(), a.sin()]
                }
            };
            if rng.f64() < 0.5 {
                ax = [-ax[1], ax[0]];
            }
            let wall_kind = match rng.index(3) {
                0 => WallKind::Brick,
                1 => WallKind::Plaster,
                _ => WallKind::Concrete,
            };
            let large = sx.min(sy) > 22.0;
            let roof = if large || rng.f64() < 0.3 {
                RoofKind::Flat
            } else if rng.f64() < 0.6 {
                RoofKind::Gable
            } else {
                RoofKind::Hip
            };
            let roof_mat = match roof {
                RoofKind::Flat => RoofMat::Gravel,
                _ if rng.f64() < 0.7 => RoofMat::Tiles,
                _ => RoofMat::Metal,
            };
            let height = hmin + (hmax - hmin) * rng.f64().powf(if large { 0.7 } else { 1.5 });
            let wall_col = {
                let (r, g, bb) = match wall_kind {
                    WallKind::Brick => WALL_PALETTE[rng.index(2)],
                    WallKind::Plaster => WALL_PALETTE[2 + rng.index(4)],
                    WallKind::Concrete => WALL_PALETTE[6 + rng.index(2)],
                };
                let j = rng.range(0.85, 1.1) as f32;
                let c = srgb(r, g, bb);
                [c[0] * j, c[1] * j, c[2] * j]
            };
            let roof_col = {
                let (r, g, bb) = match roof_mat {
                    RoofMat::Tiles => ROOF_TILE_PALETTE[rng.index(4)],
                    RoofMat::Metal => ROOF_METAL_PALETTE[rng.index(4)],
                    RoofMat::Gravel => {
                        let v = rng.range(100.0, 150.0) as u8;
                        (v, v, v.saturating_sub(5))
                    }
                };
                srgb(r, g, bb)
            };
            let mut bd = Building {
                center,
                ax,
                half: [0.5 * sx, 0.5 * sy],
                base_z: 0.0,
                eave_z: 0.0,
                roof,
                wall_kind,
                wall_col,
                trim_col: srgb(230, 228, 220),
                roof_mat,
                roof_col,
                glass_col: srgb(
                    rng.range(40.0, 70.0) as u8,
                    rng.range(55.0, 80.0) as u8,
                    rng.range(70.0, 100.0) as u8,
                ),
                floor_h: rng.range(2.9, 3.5),
                win_spacing: rng.range(2.4, 3.6),
                win_frac: rng.range(0.35, 0.6),
                seed: rng.u32(),
            };
            let corners = bd.corners(0.0);
            let mut gmin = f64::INFINITY;
            let mut clear = true;
            let mut probe: Vec<[f64; 2]> = corners.to_vec();
            probe.push(center);
            for k in 0..4 {
                let (a, c) = (corners[k], corners[(k + 1) % 4]);
                probe.push([(a[0] + c[0]) * 0.5, (a[1] + c[1]) * 0.5]);
            }
            for p in &probe {
                gmin = gmin.min(terrain.height_at(p[0], p[1]));
                if road_dist(p[0], p[1]) < SIDEWALK_M + 0.5 {
                    clear = false;
                }
            }
            let r = (bd.half[0].powi(2) + bd.half[1].powi(2)).sqrt();
            if !clear
                || out.iter().any(|o| o.overlaps(&bd, 3.0))
                || rubble
                    .iter()
                    .any(|f| dist2(f.center, center).sqrt() < f.radius + 0.6 * r)
            {
                continue;
            }
            // Sunk a little so the walls meet sloped ground without a gap.
            bd.base_z = gmin - 0.5;
            bd.eave_z = gmin + height;
            out.push(bd);
            break;
        }
    }
    out
}

fn add_building(b: &mut Builder, bd: &Building, bi: u32, rng: &mut Rng) {
    let ax = Vector3::new(bd.ax[0], bd.ax[1], 0.0);
    let ay = Vector3::new(-bd.ax[1], bd.ax[0], 0.0);
    let z = Vector3::z();
    let c = Vector3::new(bd.center[0], bd.center[1], 0.5 * (bd.base_z + bd.eave_z));
    let half = [bd.half[0], bd.half[1], 0.5 * (bd.eave_z - bd.base_z)];
    b.convex(
        box_planes(c, [ax, ay, z], half),
        box_aabb(c, [ax, ay, z], half),
        Class::Body(bi),
    );
    match bd.roof {
        RoofKind::Flat => {
            // Rooftop equipment: small boxes that give flat roofs mid-scale structure.
            let units = 1 + rng.index(4);
            for _ in 0..units {
                let hx = rng.range(0.5, 1.6).min(0.3 * bd.half[0]);
                let hy = rng.range(0.5, 1.6).min(0.3 * bd.half[1]);
                let hz = rng.range(0.4, 1.0);
                let lx = rng.range(-1.0, 1.0) * (bd.half[0] - hx - 1.0).max(0.0);
                let ly = rng.range(-1.0, 1.0) * (bd.half[1] - hy - 1.0).max(0.0);
                let uc =
                    Vector3::new(bd.center[0], bd.center[1], bd.eave_z + hz) + ax * lx + ay * ly;
                b.convex(
                    box_planes(uc, [ax, ay, z], [hx, hy, hz]),
                    box_aabb(uc, [ax, ay, z], [hx, hy, hz]),
                    Class::RoofUnit(bi),
                );
            }
        }
        RoofKind::Gable | RoofKind::Hip => {
            let pitch = rng.range(22.0f64, 38.0).to_radians();
            let tanp = pitch.tan();
            let overhang = 0.4;
            // The ridge runs along the longer side.
            let (long, short, hl, hs) = if bd.half[0] >= bd.half[1] {
                (ax, ay, bd.half[0], bd.half[1])
            } else {
                (ay, ax, bd.half[1], bd.half[0])
            };
            let (hl, hs) = (hl + overhang, hs + overhang);
            let base = bd.eave_z - overhang * tanp;
            let cc = Vector3::new(bd.center[0], bd.center[1], 0.0);
            let mut planes = vec![Plane::new(-z, -base)];
            // Sloped faces: z + tanp * (±short·(p − c)) ≤ base + tanp * hs.
            for s in [1.0, -1.0] {
                let n = z + short * (s * tanp);
                planes.push(Plane::new(n, base + tanp * hs + n.dot(&cc) - cc.z));
            }
            if bd.roof == RoofKind::Gable {
                for s in [1.0, -1.0] {
                    let n = long * s;
                    planes.push(Plane::new(n, n.dot(&cc) + hl));
                }
            } else {
                for s in [1.0, -1.0] {
                    let n = z + long * (s * tanp);
                    planes.push(Plane::new(n, base + tanp * hl + n.dot(&cc) - cc.z));
                }
            }
            let ridge = base + tanp * hs;
            let e = long.abs() * hl + short.abs() * hs;
            let aabb = Aabb::new(
                Vector3::new(cc.x - e.x, cc.y - e.y, base),
                Vector3::new(cc.x + e.x, cc.y + e.y, ridge),
            );
            b.convex(planes, aabb, Class::PitchedRoof(bi));
        }
    }
}

fn random_rotation(rng: &mut Rng) -> Rotation3<f64> {
    let axis = Vector3::new(rng.normal(), rng.normal(), rng.normal());
    let axis = Unit::try_new(axis, 1e-9).unwrap_or(Vector3::z_axis());
    Rotation3::from_axis_angle(&axis, rng.range(0.0, std::f64::consts::TAU))
}

fn add_rubble(b: &mut Builder, f: &RubbleField, n: usize, terrain: &Terrain, rng: &mut Rng) {
    for _ in 0..n {
        let r = f.radius * rng.f64().powf(0.6);
        let a = rng.range(0.0, std::f64::consts::TAU);
        let (x, y) = (f.center[0] + r * a.cos(), f.center[1] + r * a.sin());
        // Log-normal sizes: many fist-to-chair sized pieces, a few slabs.
        let s = (0.45 * (0.6 * rng.normal()).exp()).clamp(0.12, 2.2);
        let half = [
            s * rng.range(0.6, 1.4),
            s * rng.range(0.5, 1.2),
            s * rng.range(0.25, 0.8),
        ];
        // Partly embedded in the mound.
        let zc = terrain.height_at(x, y) + half[2] * rng.range(-0.4, 0.6);
        let c = Vector3::new(x, y, zc);
        let rot = random_rotation(rng);
        let axes = [rot * Vector3::x(), rot * Vector3::y(), rot * Vector3::z()];
        let mut planes = box_planes(c, axes, half);
        // Chop corners off so pieces read as broken chunks rather than bricks.
        let hmin = half.iter().copied().fold(f64::INFINITY, f64::min);
        for _ in 0..rng.index(4) {
            let n = Vector3::new(rng.normal(), rng.normal(), rng.normal());
            if let Some(n) = n.try_normalize(1e-9) {
                planes.push(Plane::new(
                    n,
                    n.dot(&c) + hmin * rng.range(0.6, 1.0) + 0.4 * (half[0] + half[1]) * rng.f64(),
                ));
            }
        }
        let (cr, cg, cb) = ROCK_PALETTE[rng.index(ROCK_PALETTE.len())];
        let j = rng.range(0.8, 1.15) as f32;
        let col = srgb(cr, cg, cb);
        b.convex(
            planes,
            box_aabb(c, axes, half),
            Class::Rock([col[0] * j, col[1] * j, col[2] * j], rng.u32()),
        );
    }
}

fn add_trees(
    b: &mut Builder,
    config: &WorldConfig,
    rng: &mut Rng,
    half: f64,
    terrain: &Terrain,
    road_dist: &dyn Fn(f64, f64) -> f64,
    buildings: &[Building],
    rubble: &[RubbleField],
) {
    let mut placed: Vec<([f64; 2], f64)> = Vec::new();
    let mut cluster = [rng.range(-half, half), rng.range(-half, half)];
    for k in 0..config.trees {
        if k % 6 == 0 {
            cluster = [rng.range(-half, half), rng.range(-half, half)];
        }
        for _ in 0..30 {
            // Trees grow in loose groups (rows along roads, garden clumps).
            let p = [
                (cluster[0] + 12.0 * rng.normal()).clamp(-half, half),
                (cluster[1] + 12.0 * rng.normal()).clamp(-half, half),
            ];
            let rad = rng.range(1.8, 3.6);
            let ok = road_dist(p[0], p[1]) > SIDEWALK_M + 0.3
                && buildings.iter().all(|bd| {
                    let l = bd.local(p[0], p[1]);
                    l[0].abs() > bd.half[0] + 0.5 * rad || l[1].abs() > bd.half[1] + 0.5 * rad
                })
                && rubble
                    .iter()
                    .all(|f| dist2(f.center, p).sqrt() > f.radius + rad)
                && placed
                    .iter()
                    .all(|(q, r)| dist2(*q, p).sqrt() > 0.8 * (r + rad));
            if !ok {
                continue;
            }
            let g = terrain.height_at(p[0], p[1]);
            let rz = rad * rng.range(0.8, 1.3);
            let trunk_h = rng.range(1.5, 3.5);
            let cz = g + trunk_h + rz * 0.9;
            let tr = 0.15 + 0.05 * rad;
            let tc = Vector3::new(p[0], p[1], 0.5 * (g - 0.3 + cz));
            let th = [tr, tr, 0.5 * (cz - g + 0.3)];
            let axes = [Vector3::x(), Vector3::y(), Vector3::z()];
            b.convex(
                box_planes(tc, axes, th),
                box_aabb(tc, axes, th),
                Class::Trunk,
            );
            let leaf = srgb(
                rng.range(45.0, 85.0) as u8,
                rng.range(80.0, 115.0) as u8,
                rng.range(30.0, 55.0) as u8,
            );
            let seed = rng.u32();
            b.ellipsoid(
                Vector3::new(p[0], p[1], cz),
                Vector3::new(rad, rad * rng.range(0.85, 1.15), rz),
                Class::Crown(leaf, seed),
            );
            // Smaller lobes break the silhouette so crowns read as foliage, not balls.
            for _ in 0..2 + rng.index(3) {
                let a = rng.range(0.0, std::f64::consts::TAU);
                let lr = rad * rng.range(0.45, 0.7);
                let off = rad * rng.range(0.45, 0.75);
                let lc = Vector3::new(
                    p[0] + off * a.cos(),
                    p[1] + off * a.sin(),
                    cz + rz * rng.range(-0.3, 0.45),
                );
                b.ellipsoid(
                    lc,
                    Vector3::new(lr, lr, lr * rng.range(0.8, 1.1)),
                    Class::Crown(leaf, seed),
                );
            }
            placed.push((p, rad));
            break;
        }
    }
}

const CAR_PALETTE: [(u8, u8, u8); 8] = [
    (235, 235, 232),
    (170, 172, 175),
    (35, 36, 40),
    (150, 30, 30),
    (40, 60, 120),
    (90, 95, 100),
    (200, 190, 160),
    (30, 80, 60),
];

fn add_cars(
    b: &mut Builder,
    config: &WorldConfig,
    rng: &mut Rng,
    half: f64,
    terrain: &Terrain,
    roads: &[Road],
    rubble: &[RubbleField],
) {
    if config.cars_per_100m <= 0.0 {
        return;
    }
    let mean_gap = 100.0 / config.cars_per_100m;
    // Roads are not flattened into the terrain; the relief is gentle enough that a car placed
    // at the height under its centre neither floats visibly nor sinks.
    for (ri, r) in roads.iter().enumerate() {
        let total = *r.cum.last().unwrap_or(&0.0);
        let mut s = rng.range(0.0, mean_gap);
        while s < total {
            let step = mean_gap * rng.range(0.3, 1.7);
            let side = if rng.f64() < 0.5 { 1.0 } else { -1.0 };
            let seg = r.cum.partition_point(|&c| c <= s).clamp(1, r.pts.len() - 1) - 1;
            let (p0, p1) = (r.pts[seg], r.pts[seg + 1]);
            let len = r.cum[seg + 1] - r.cum[seg];
            let u = ((s - r.cum[seg]) / len).clamp(0.0, 1.0);
            let dir = [(p1[0] - p0[0]) / len, (p1[1] - p0[1]) / len];
            let nrm = [-dir[1], dir[0]];
            let off = side * (r.half_width - 1.4);
            let c = [
                p0[0] + u * (p1[0] - p0[0]) + off * nrm[0],
                p0[1] + u * (p1[1] - p0[1]) + off * nrm[1],
            ];
            s += step;
            let inside = c[0].abs() < half && c[1].abs() < half;
            let clear_of_rubble = rubble
                .iter()
                .all(|f| dist2(f.center, c).sqrt() > f.radius + 4.0);
            // Keep junctions free: no other road's carriageway within reach.
            let clear_of_junctions = roads.iter().enumerate().all(|(rj, o)| {
                rj == ri
                    || o.pts
                        .windows(2)
                        .all(|w| seg_dist(w[0], w[1], c) > o.half_width + 4.0)
            });
            if !(inside && clear_of_rubble && clear_of_junctions) {
                continue;
            }
            let heading = if rng.f64() < 0.5 { 1.0 } else { -1.0 };
            let ax = Vector3::new(dir[0] * heading, dir[1] * heading, 0.0);
            let ay = Vector3::new(-ax.y, ax.x, 0.0);
            let z = Vector3::z();
            let g = terrain.height_at(c[0], c[1]);
            let (hl, hw) = (rng.range(2.0, 2.4), rng.range(0.85, 0.95));
            let (cr, cg, cb) = CAR_PALETTE[rng.index(CAR_PALETTE.len())];
            let paint = srgb(cr, cg, cb);
            let body_c = Vector3::new(c[0], c[1], g + 0.6);
            let body_h = [hl, hw, 0.4];
            b.convex(
                box_planes(body_c, [ax, ay, z], body_h),
                box_aabb(body_c, [ax, ay, z], body_h),
                Class::CarBody(paint),
            );
            let cab_c = body_c + ax * (-0.15 * hl) + z * 0.65;
            let cab_h = [0.55 * hl, 0.9 * hw, 0.25];
            b.convex(
                box_planes(cab_c, [ax, ay, z], cab_h),
                box_aabb(cab_c, [ax, ay, z], cab_h),
                Class::CarCabin(paint),
            );
        }
    }
}

fn seg_dist(a: [f64; 2], b: [f64; 2], p: [f64; 2]) -> f64 {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let l2 = (dx * dx + dy * dy).max(1e-12);
    let t = (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / l2).clamp(0.0, 1.0);
    dist2([a[0] + t * dx, a[1] + t * dy], p).sqrt()
}
