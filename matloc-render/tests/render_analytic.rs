//! The inference renderer against an analytic field: a horizontal slab of constant density
//! under thin fog. Checks the median depth (exact for piecewise-constant density), the
//! render-time fog filter (`min_density`), colour evaluated only where it is visible, and the
//! pruned render grid.

use matloc_nerf_field::{FEATURE_DIM, FeatureField, FieldError, SceneBox};
use matloc_render::{
    MarchConfig, OccupancyConfig, OccupancyGrid, RayBatch, RenderOptions, Spacing, render_rays,
};

/// Density `slab` for `z < top`, `fog` above; feature dim `d` = `d + z`; colour from f_mlp.
struct Slab {
    top: f32,
    slab: f32,
    fog: f32,
}

impl FeatureField for Slab {
    fn density_and_features(
        &self,
        points: &[[f32; 3]],
        dims: &[usize],
        density: &mut [f32],
        features: &mut [f32],
    ) -> Result<(), FieldError> {
        for (i, p) in points.iter().enumerate() {
            density[i] = if p[2] < self.top { self.slab } else { self.fog };
            for (j, &d) in dims.iter().enumerate() {
                features[i * dims.len() + j] = d as f32 + p[2];
            }
        }
        Ok(())
    }

    fn colour(
        &self,
        f_mlp: &[f32],
        _directions: &[[f32; 3]],
        _appearance: Option<u32>,
        rgb: &mut [f32],
    ) -> Result<(), FieldError> {
        for (i, row) in f_mlp.chunks_exact(15).enumerate() {
            // f_mlp dim 32 + z → a colour that varies with height.
            let z = row[0] - 32.0;
            rgb[3 * i] = (0.5 + 0.02 * z).clamp(0.0, 1.0);
            rgb[3 * i + 1] = 0.3;
            rgb[3 * i + 2] = 0.8;
        }
        Ok(())
    }
}

/// Vertical rays from z = 10 down to z = −10 (distance 20), slab top at z = 0.
fn rays(n: usize) -> RayBatch {
    let origins = (0..n).map(|i| [i as f32 * 0.1, 0.0, 10.0]).collect();
    let directions = vec![[0.0, 0.0, -1.0]; n];
    RayBatch::new(origins, directions, 0.0, 20.0).unwrap()
}

fn opts(steps: usize) -> RenderOptions {
    RenderOptions {
        march: MarchConfig {
            spacing: Spacing {
                linear_range_m: 1e9,
            },
            steps,
            max_samples: 1 << 20,
        },
        dims: (0..FEATURE_DIM).collect(),
        ..RenderOptions::default()
    }
}

#[test]
fn median_depth_is_exact_for_a_constant_slab() {
    let field = Slab {
        top: 0.0,
        slab: 0.8,
        fog: 0.0,
    };
    // 2000 steps of 1 cm: the slab starts on a step boundary at distance 10.
    let out = render_rays(&field, &rays(4), None, &opts(2000)).unwrap();
    let want = 10.0 + std::f32::consts::LN_2 / 0.8;
    for i in 0..4 {
        assert!(
            (out.median[i] - want).abs() < 1e-3,
            "median {} vs {want}",
            out.median[i]
        );
        // The expected depth of the same slab is 1/σ behind its top (for an opaque slab).
        let expected = out.depth[i] / out.accumulation[i];
        assert!((expected - (10.0 + 1.0 / 0.8)).abs() < 0.02, "{expected}");
    }
}

#[test]
fn fog_filter_removes_fog_and_keeps_the_surface() {
    let foggy = Slab {
        top: 0.0,
        slab: 5.0,
        fog: 0.02,
    };
    let clear = Slab {
        top: 0.0,
        slab: 5.0,
        fog: 0.0,
    };
    let o = opts(1000);
    let with_fog = render_rays(&foggy, &rays(2), None, &o).unwrap();
    let reference = render_rays(&clear, &rays(2), None, &o).unwrap();
    let filtered = render_rays(
        &foggy,
        &rays(2),
        None,
        &RenderOptions {
            min_density: 0.1,
            ..o.clone()
        },
    )
    .unwrap();
    // 10 m of fog at 0.02/m absorbs 18 % and pulls the expected depth ~1 m forward.
    let d = |r: &matloc_render::RenderedRays| r.depth[0] / r.accumulation[0];
    assert!(d(&reference) - d(&with_fog) > 0.5);
    assert!((d(&filtered) - d(&reference)).abs() < 1e-4);
    assert!((filtered.median[0] - reference.median[0]).abs() < 1e-4);
    for k in 0..FEATURE_DIM {
        assert!((filtered.features[k] - reference.features[k]).abs() < 1e-3);
    }
}

#[test]
fn colour_is_composited_from_the_visible_samples() {
    let field = Slab {
        top: 0.0,
        slab: 3.0,
        fog: 0.01,
    };
    let o = RenderOptions {
        rgb: true,
        background: [0.1, 0.2, 0.3],
        min_transmittance: 0.0,
        ..opts(400)
    };
    let out = render_rays(&field, &rays(3), None, &o).unwrap();
    // Reference: composite every sample in double precision.
    let dt = 20.0f64 / 400.0;
    let mut t = 1.0f64;
    let mut c = [0f64; 3];
    for i in 0..400 {
        let z = 10.0 - (i as f64 + 0.5) * dt;
        let s = if z < 0.0 { 3.0 } else { 0.01 };
        let a = 1.0 - (-s * dt).exp();
        let col = [(0.5 + 0.02 * z).clamp(0.0, 1.0), 0.3, 0.8];
        for ch in 0..3 {
            c[ch] += t * a * col[ch];
        }
        t *= 1.0 - a;
    }
    for ch in 0..3 {
        let want = c[ch] + t * o.background[ch] as f64;
        assert!(
            (out.rgb[ch] as f64 - want).abs() < 1e-4,
            "channel {ch}: {} vs {want}",
            out.rgb[ch]
        );
    }
}

#[test]
fn pruned_grid_keeps_dense_cells_only() {
    let sb = SceneBox {
        min: [-10.0, -10.0, -10.0],
        max: [10.0, 10.0, 10.0],
    };
    let field = Slab {
        top: 0.0,
        slab: 1.0,
        fog: 0.002,
    };
    let cfg = OccupancyConfig {
        resolution: 16,
        density_threshold: 0.01,
        cap_at_mean: false,
        ..OccupancyConfig::default()
    };
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
    let grid = OccupancyGrid::from_field(cfg, sb, &field, &mut rng).unwrap();
    // density_scale = 0.1/m: fog is 0.02 units, the slab 10 units.
    assert!(grid.occupied_fraction_in_box() > 0.99);
    let pruned = grid.pruned(1.0);
    let f = pruned.occupied_fraction_in_box();
    assert!((f - 0.5).abs() < 0.01, "{f}");
    assert!(pruned.is_occupied_world([0.0, 0.0, -5.0]));
    assert!(!pruned.is_occupied_world([0.0, 0.0, 5.0]));
    assert!(grid.pruned(0.0).occupied_fraction() == grid.occupied_fraction());
}

#[test]
fn median_depth_is_zero_where_the_transmittance_stays_above_half() {
    // τ = 0.5 in total: A ≈ 0.39, the transmittance never reaches 0.5 (render_view then
    // reports the expected depth).
    let field = Slab {
        top: 0.0,
        slab: 0.05,
        fog: 0.0,
    };
    let out = render_rays(&field, &rays(1), None, &opts(2000)).unwrap();
    let a = out.accumulation[0];
    assert!((a - (1.0 - (-0.5f32).exp())).abs() < 1e-3, "{a}");
    assert_eq!(out.median[0], 0.0);
}
