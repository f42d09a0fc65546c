//! The paper's Table 4: place predictors (ArcFace classifier, regression baseline and the
//! classifier's member-level variants) on the test views of a dataset — time per query,
//! top-1 / top-3 group accuracy, how often the top-1 coarse pose sees the same ground as the
//! true view, and how far its camera centre is from the truth.
//!
//! The command-line tool loads the views and models, calls [`variants`] and [`evaluate`] per
//! model and prints [`table_header`], [`table_line`], [`table_footer`] and [`oracle_line`].

use std::time::Instant;

use matloc_core::metrics::{median, rotation_error_deg, translation_error_m};
use matloc_core::{Camera, Image, Pose};
use matloc_place::{PlaceMethod, PlaceModel, PlacePredictor, PoseGroups, view_overlap};

use crate::error::PipelineError;

/// Hypotheses asked of the predictor per query (top-3 accuracy needs three).
const TOP_K: usize = 3;

/// Metres of camera-centre distance one radian of rotation costs in [`retrieval_oracle`]'s
/// nearest-training-pose search.
const ORACLE_M_PER_RAD: f64 = 20.0;

/// Posed test views with depth, index-aligned: the queries of Table 4. Depth gives the ground
/// a view sees, which the co-visibility score compares.
#[derive(Clone, Debug, Default)]
pub struct PlaceQueries {
    /// Dataset frame index of each view (named in errors).
    pub frames: Vec<usize>,
    /// RGB images.
    pub images: Vec<Image<f32>>,
    /// Cameras of the images.
    pub cameras: Vec<Camera>,
    /// True `cam_from_world` poses.
    pub poses: Vec<Pose>,
    /// Depth maps (z along the optical axis), one channel, the images' size.
    pub depths: Vec<Image<f32>>,
}

impl PlaceQueries {
    /// Number of views.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// True when there are no views.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// Appends one view.
    pub fn push(
        &mut self,
        frame: usize,
        image: Image<f32>,
        depth: Image<f32>,
        camera: Camera,
        pose: Pose,
    ) {
        self.frames.push(frame);
        self.images.push(image);
        self.depths.push(depth);
        self.cameras.push(camera);
        self.poses.push(pose);
    }

    /// Non-empty with all fields of one length.
    fn check(&self) -> Result<(), PipelineError> {
        let n = self.poses.len();
        if n == 0 {
            return Err(PipelineError::Config(
                "Table 4 needs at least one test view".into(),
            ));
        }
        if [
            self.frames.len(),
            self.images.len(),
            self.cameras.len(),
            self.depths.len(),
        ]
        .iter()
        .any(|&l| l != n)
        {
            return Err(PipelineError::Config(format!(
                "test views disagree in length: {} frames, {} images, {} cameras, {} poses, {} depths",
                self.frames.len(),
                self.images.len(),
                self.cameras.len(),
                n,
                self.depths.len()
            )));
        }
        Ok(())
    }
}

/// One setting of a place model's member-level options (a Table 4 row per setting).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Table4Variant {
    /// Coarse pose from the group member nearest in embedding space instead of the medoid
    /// ([`PlaceModel::set_refine_within_group`]).
    pub refine: bool,
    /// Weight of the best member similarity in a group's score
    /// ([`PlaceModel::set_member_weight`]).
    pub member_weight: f32,
    /// Temperature of the nearest member's blend with its best neighbour; 0 = none
    /// ([`PlaceModel::set_member_blend`]).
    pub blend: f32,
}

impl Table4Variant {
    /// The model as it ships: group medoid, class-centre scores, no blend.
    pub const PLAIN: Table4Variant = Table4Variant {
        refine: false,
        member_weight: 0.0,
        blend: 0.0,
    };

    /// Sets this variant's options on `model`.
    pub fn apply(&self, model: &mut PlaceModel) {
        model.set_refine_within_group(self.refine);
        model.set_member_weight(self.member_weight);
        model.set_member_blend(self.blend);
    }
}

/// The variants evaluated for a model of `method`: always [`Table4Variant::PLAIN`]; for the
/// classifier also, with `refine`, the nearest-member pose and then each blend temperature,
/// and finally each member weight (with the nearest-member pose when `refine`). The
/// regression baseline has no member-level options.
pub fn variants(
    method: PlaceMethod,
    refine: bool,
    member_weights: &[f32],
    member_blends: &[f32],
) -> Vec<Table4Variant> {
    let mut out = vec![Table4Variant::PLAIN];
    if method == PlaceMethod::ArcFace {
        if refine {
            out.push(Table4Variant {
                refine: true,
                ..Table4Variant::PLAIN
            });
            out.extend(member_blends.iter().map(|&blend| Table4Variant {
                refine: true,
                member_weight: 0.0,
                blend,
            }));
        }
        out.extend(member_weights.iter().map(|&member_weight| Table4Variant {
            refine,
            member_weight,
            blend: 0.0,
        }));
    }
    out
}

/// One Table 4 row: a model in one variant on all test views.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Table4Row {
    /// The model's network.
    pub method: PlaceMethod,
    /// The options it ran with.
    pub variant: Table4Variant,
    /// Mean wall time of one prediction, milliseconds.
    pub mean_ms: f64,
    /// Median wall time of one prediction, milliseconds.
    pub median_ms: f64,
    /// Fraction of queries whose true group is the top hypothesis.
    pub top1: f64,
    /// Fraction of queries whose true group is among the top three.
    pub top3: f64,
    /// Fraction of queries whose top-1 coarse pose sees at least the required share of the
    /// ground the true view sees.
    pub covisible: f64,
    /// Median distance of the top-1 coarse camera centre to the truth, metres (NaN when no
    /// query got a hypothesis).
    pub median_coarse_m: f64,
}

impl Table4Row {
    /// Method and variant, e.g. `ArcFace+member w=0.5 blend=0.1` (options at their defaults
    /// are left out).
    pub fn name(&self) -> String {
        let v = &self.variant;
        let mut s = format!("{:?}", self.method);
        if v.refine {
            s.push_str("+member");
        }
        if v.member_weight > 0.0 {
            s.push_str(&format!(" w={}", v.member_weight));
        }
        if v.blend > 0.0 {
            s.push_str(&format!(" blend={}", v.blend));
        }
        s
    }
}

/// What one query gave.
#[derive(Clone, Copy, Debug, PartialEq)]
struct QueryResult {
    /// Prediction wall time, milliseconds.
    ms: f64,
    /// True group is the top hypothesis.
    top1: bool,
    /// True group is among the top three.
    top3: bool,
    /// The top-1 coarse pose is co-visible with the true view.
    covisible: bool,
    /// Camera-centre distance of the top-1 coarse pose (`None` without a hypothesis).
    coarse_m: Option<f64>,
}

/// Rates and medians over the queries; `None` for no queries.
fn aggregate(
    method: PlaceMethod,
    variant: Table4Variant,
    results: &[QueryResult],
) -> Option<Table4Row> {
    if results.is_empty() {
        return None;
    }
    let n = results.len() as f64;
    let rate = |f: fn(&QueryResult) -> bool| results.iter().filter(|r| f(r)).count() as f64 / n;
    let times: Vec<f64> = results.iter().map(|r| r.ms).collect();
    let coarse: Vec<f64> = results.iter().filter_map(|r| r.coarse_m).collect();
    Some(Table4Row {
        method,
        variant,
        mean_ms: times.iter().sum::<f64>() / n,
        median_ms: median(&times)?,
        top1: rate(|r| r.top1),
        top3: rate(|r| r.top3),
        covisible: rate(|r| r.covisible),
        median_coarse_m: median(&coarse).unwrap_or(f64::NAN),
    })
}

/// Runs `model` in `variant` (set on the model, which keeps it) on every test view, one at a
/// time after one untimed warm-up query, and scores the top hypotheses against the group the
/// true pose falls in. `coarse_camera` is the camera a coarse pose would be rendered with
/// (the survey's); a top-1 pose counts as co-visible when it sees at least `min_overlap` of
/// the ground the true view sees.
pub fn evaluate(
    model: &mut PlaceModel,
    variant: Table4Variant,
    test: &PlaceQueries,
    coarse_camera: &Camera,
    min_overlap: f64,
) -> Result<Table4Row, PipelineError> {
    test.check()?;
    variant.apply(model);
    let model: &PlaceModel = model;
    let groups = model.groups();
    // One warm-up query so the first timing does not include lazy initialisation.
    model.predict(&test.images[0], &test.cameras[0], TOP_K)?;
    let mut results = Vec::with_capacity(test.len());
    for i in 0..test.len() {
        let t = Instant::now();
        let h = model.predict(&test.images[i], &test.cameras[i], TOP_K)?;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        let truth = groups.assign(&test.poses[i]).ok_or_else(|| {
            PipelineError::Config(format!(
                "test frame {} cannot be assigned to a pose group (non-finite pose or no groups)",
                test.frames[i]
            ))
        })?;
        let best = h.first();
        results.push(QueryResult {
            ms,
            top1: best.is_some_and(|x| x.group == truth),
            top3: h.iter().any(|x| x.group == truth),
            covisible: best.is_some_and(|b| {
                view_overlap(
                    &test.cameras[i],
                    &test.poses[i],
                    &test.depths[i],
                    coarse_camera,
                    &b.cam_from_world,
                    4,
                ) >= min_overlap
            }),
            coarse_m: best.map(|b| translation_error_m(&b.cam_from_world, &test.poses[i])),
        });
    }
    aggregate(model.method(), variant, &results)
        .ok_or(PipelineError::Internal("no Table 4 query results"))
}

/// Fraction of `queries` whose group is the group of their nearest training pose: an upper
/// bound for place recognition by image retrieval against the training views. `None` without
/// queries, when the model does not know its training poses, or when a query falls in no
/// group.
pub fn retrieval_oracle(model: &PlaceModel, queries: &[Pose]) -> Option<f64> {
    oracle_over(model.groups(), model.training_poses(), queries)
}

/// [`retrieval_oracle`] over `groups` of the training poses `train` (index-aligned with
/// `groups.labels`). Nearest means smallest centre distance plus [`ORACLE_M_PER_RAD`] per
/// radian of rotation.
fn oracle_over(groups: &PoseGroups, train: &[Pose], queries: &[Pose]) -> Option<f64> {
    if queries.is_empty() || train.len() != groups.labels.len() {
        return None;
    }
    let mut hits = 0usize;
    for q in queries {
        let truth = groups.assign(q)?;
        let cost = |j: usize| {
            translation_error_m(&train[j], q)
                + ORACLE_M_PER_RAD * rotation_error_deg(&train[j], q).to_radians()
        };
        let nearest = (0..train.len()).min_by(|&a, &b| cost(a).total_cmp(&cost(b)))?;
        hits += usize::from(groups.labels[nearest] == truth);
    }
    Some(hits as f64 / queries.len() as f64)
}

/// Column titles of the fixed-width table.
pub fn table_header() -> String {
    format!(
        "{:<40} {:>10} {:>10} {:>8} {:>8} {:>12} {:>14}",
        "model", "ms/query", "(median)", "top-1", "top-3", "co-visible", "coarse t (m)"
    )
}

/// One line of the fixed-width table: the row's [`Table4Row::name`] followed by `(model)`,
/// the model's label (e.g. its directory name).
pub fn table_line(model: &str, row: &Table4Row) -> String {
    format!(
        "{:<40} {:>10.2} {:>10.2} {:>7.1}% {:>7.1}% {:>11.1}% {:>14.2}",
        format!("{} ({model})", row.name()),
        row.mean_ms,
        row.median_ms,
        100.0 * row.top1,
        100.0 * row.top3,
        100.0 * row.covisible,
        row.median_coarse_m
    )
}

/// The note under the table: how many views and what co-visible means.
pub fn table_footer(num_queries: usize, min_overlap: f64) -> String {
    format!(
        "{num_queries} test views; co-visible = coarse pose sees >= {:.0} % of the ground the \
         true view sees",
        100.0 * min_overlap
    )
}

/// The [`retrieval_oracle`] line printed after the table.
pub fn oracle_line(oracle: f64) -> String {
    format!(
        "top-1 of perfect retrieval (the group of the training pose nearest each query, centre \
         distance + {ORACLE_M_PER_RAD} m per radian of rotation): {:.1}%",
        100.0 * oracle
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use matloc_place::{GroupConfig, PoseGroup};

    /// Identity-rotation camera whose centre is at `(x, 0, 0)`.
    fn at(x: f64) -> Pose {
        Pose::translation(-x, 0.0, 0.0)
    }

    fn group(id: usize, centre_x: f64, members: Vec<usize>, train: &[Pose]) -> PoseGroup {
        PoseGroup {
            id,
            spatial: id,
            spatial_center: [centre_x, 0.0, 0.0],
            direction: [0.0, 0.0, 1.0],
            medoid: members[0],
            coarse_pose: train[members[0]],
            members,
            block: None,
        }
    }

    /// Group 0 = the camera at x = 0 (centre 0); group 1 = cameras at x = 4 and 16 (centre
    /// 10), so a query at x = 3 falls in group 0 but its nearest training camera is group 1's.
    fn two_groups() -> (PoseGroups, Vec<Pose>) {
        let train = vec![at(0.0), at(4.0), at(16.0)];
        let groups = PoseGroups {
            config: GroupConfig::default(),
            spatial_radius_m: 6.0,
            num_spatial: 2,
            groups: vec![
                group(0, 0.0, vec![0], &train),
                group(1, 10.0, vec![1, 2], &train),
            ],
            labels: vec![0, 1, 1],
        };
        (groups, train)
    }

    #[test]
    fn oracle_counts_queries_whose_nearest_training_pose_shares_their_group() {
        let (groups, train) = two_groups();
        let queries = [at(0.5), at(3.0), at(15.0)];
        let o = oracle_over(&groups, &train, &queries).unwrap();
        assert!((o - 2.0 / 3.0).abs() < 1e-12, "{o}");
        assert_eq!(oracle_over(&groups, &train, &queries[..1]), Some(1.0));
        assert_eq!(oracle_over(&groups, &train, &queries[1..2]), Some(0.0));
    }

    #[test]
    fn oracle_is_undefined_without_queries_or_training_poses() {
        let (groups, train) = two_groups();
        assert_eq!(oracle_over(&groups, &train, &[]), None);
        assert_eq!(oracle_over(&groups, &train[..2], &[at(0.0)]), None);
        let mut bad = at(0.0);
        bad.translation.x = f64::NAN;
        assert_eq!(oracle_over(&groups, &train, &[bad]), None);
    }

    fn result(
        ms: f64,
        top1: bool,
        top3: bool,
        covisible: bool,
        coarse_m: Option<f64>,
    ) -> QueryResult {
        QueryResult {
            ms,
            top1,
            top3,
            covisible,
            coarse_m,
        }
    }

    #[test]
    fn even_length_medians_average_the_two_middle_values() {
        let results = [
            result(10.0, true, true, true, Some(4.0)),
            result(1.0, false, true, false, Some(1.0)),
            result(3.0, false, false, false, None),
            result(2.0, true, true, true, Some(2.0)),
            result(4.0, false, true, true, Some(3.0)),
            result(6.0, false, false, false, None),
        ];
        let row = aggregate(PlaceMethod::ArcFace, Table4Variant::PLAIN, &results).unwrap();
        // Times 1 2 3 4 6 10: the middle pair 3, 4 (the upper middle alone would be 4).
        assert_eq!(row.median_ms, 3.5);
        assert!((row.mean_ms - 26.0 / 6.0).abs() < 1e-12);
        // Coarse distances 1 2 3 4 of the four queries with a hypothesis.
        assert_eq!(row.median_coarse_m, 2.5);
        assert!((row.top1 - 2.0 / 6.0).abs() < 1e-12);
        assert!((row.top3 - 4.0 / 6.0).abs() < 1e-12);
        assert!((row.covisible - 3.0 / 6.0).abs() < 1e-12);
    }

    #[test]
    fn aggregate_of_no_hypotheses_and_no_queries() {
        let results = [result(1.0, false, false, false, None)];
        let row = aggregate(PlaceMethod::Regression, Table4Variant::PLAIN, &results).unwrap();
        assert!(row.median_coarse_m.is_nan());
        assert_eq!(row.median_ms, 1.0);
        assert_eq!(
            aggregate(PlaceMethod::Regression, Table4Variant::PLAIN, &[]),
            None
        );
    }

    #[test]
    fn variants_follow_the_flags() {
        let v = |refine, member_weight, blend| Table4Variant {
            refine,
            member_weight,
            blend,
        };
        assert_eq!(
            variants(PlaceMethod::Regression, true, &[0.5], &[0.1]),
            vec![Table4Variant::PLAIN]
        );
        assert_eq!(
            variants(PlaceMethod::ArcFace, false, &[0.5], &[0.1]),
            vec![Table4Variant::PLAIN, v(false, 0.5, 0.0)]
        );
        assert_eq!(
            variants(PlaceMethod::ArcFace, true, &[0.5, 1.0], &[0.1]),
            vec![
                Table4Variant::PLAIN,
                v(true, 0.0, 0.0),
                v(true, 0.0, 0.1),
                v(true, 0.5, 0.0),
                v(true, 1.0, 0.0),
            ]
        );
    }

    #[test]
    fn table_line_names_method_variant_and_model() {
        let row = Table4Row {
            method: PlaceMethod::ArcFace,
            variant: Table4Variant {
                refine: true,
                member_weight: 0.5,
                blend: 0.0,
            },
            mean_ms: 1.234,
            median_ms: 1.0,
            top1: 0.5,
            top3: 0.75,
            covisible: 0.625,
            median_coarse_m: 3.456,
        };
        assert_eq!(row.name(), "ArcFace+member w=0.5");
        let line = table_line("place-arcface", &row);
        assert_eq!(
            line,
            format!(
                "{:<40} {:>10} {:>10} {:>8} {:>8} {:>12} {:>14}",
                "ArcFace+member w=0.5 (place-arcface)",
                "1.23",
                "1.00",
                "50.0%",
                "75.0%",
                "62.5%",
                "3.46"
            )
        );
        assert_eq!(line.len(), table_header().len());
    }
}
