//! nerfstudio `applied_transform`: read, validated, written back, and poses mapped to the
//! original COLMAP world, checked against a pose worked out by hand.

use std::path::Path;

use matloc_core::Pose;
use matloc_data::Split;
use matloc_data::nerfstudio::{
    NerfstudioError, cam_from_world_from_original, original_cam_from_world, parse_transforms,
    read_nerfstudio, write_nerfstudio,
};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use proptest::prelude::*;

/// What `ns-process-data` writes for a COLMAP world: `np.eye(4)[:3]` with rows (0, 2, 1) and
/// the last row negated, i.e. `x_ns = (x, z, −y)`.
const NS_PROCESS_DATA: [[f64; 4]; 3] = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, -1.0, 0.0, 0.0],
];

/// A transforms.json with one frame of a COLMAP camera with identity rotation at centre
/// (1, 2, 3), converted the way nerfstudio's `colmap_to_json` does: c2w = inverse(w2c),
/// columns 1 and 2 negated (OpenCV → OpenGL), rows reordered (0, 2, 1), row 2 negated. That
/// gives the centre (1, 3, −2) = applied_transform · (1, 2, 3).
fn ns_document(applied: &str) -> String {
    format!(
        r#"{{
  "w": 4, "h": 3, "fl_x": 5, "fl_y": 5, "cx": 2, "cy": 1.5,
  "frames": [{{"file_path": "images/a.png", "transform_matrix":
    [[1, 0, 0, 1], [0, 0, -1, 3], [0, 1, 0, -2], [0, 0, 0, 1]]}}]
  {applied}
}}"#
    )
}

fn parse(doc: &str) -> Result<matloc_data::Dataset, NerfstudioError> {
    parse_transforms(
        doc.as_bytes(),
        Path::new("t/transforms.json"),
        Path::new("t"),
        Split::Train,
    )
}

fn close_pose(a: &Pose, b: &Pose, tol: f64) -> bool {
    (a.translation.vector - b.translation.vector).norm() < tol
        && a.rotation.angle_to(&b.rotation) < tol
}

#[test]
fn maps_a_ns_process_data_pose_back_to_the_colmap_pose() {
    let ds = parse(&ns_document(
        r#", "applied_transform": [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0]]"#,
    ))
    .unwrap();
    assert_eq!(ds.metadata.applied_transform, Some(NS_PROCESS_DATA));
    let cam_from_ns = ds.frames[0].cam_from_world;
    // By hand: R_cam_from_ns = R_cam_from_colmap · Aᵀ = Aᵀ, t = −Aᵀ (1, 3, −2) = (−1, −2, −3).
    let a_t = nalgebra::Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0);
    assert!((cam_from_ns.rotation.to_rotation_matrix().into_inner() - a_t).norm() < 1e-12);
    assert!((cam_from_ns.translation.vector - Vector3::new(-1.0, -2.0, -3.0)).norm() < 1e-12);

    // The COLMAP image pose: identity rotation, t = −centre = (−1, −2, −3).
    let colmap = Isometry3::from_parts(
        Translation3::new(-1.0, -2.0, -3.0),
        UnitQuaternion::identity(),
    );
    let back = original_cam_from_world(&NS_PROCESS_DATA, &cam_from_ns).unwrap();
    assert!(close_pose(&back, &colmap, 1e-12), "{back:?}");
    let again = cam_from_world_from_original(&NS_PROCESS_DATA, &colmap).unwrap();
    assert!(close_pose(&again, &cam_from_ns, 1e-12));
}

#[test]
fn applied_transform_with_translation_maps_points_as_documented() {
    // x_world = R x_original + t with a 90° turn about z and t = (10, 0, 0).
    let applied = [
        [0.0, -1.0, 0.0, 10.0],
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    // A camera at original (1, 0, 0) is at world (10, 1, 0).
    let cam_from_original = Isometry3::from_parts(
        Translation3::new(-1.0, 0.0, 0.0),
        UnitQuaternion::identity(),
    );
    let cam_from_world = cam_from_world_from_original(&applied, &cam_from_original).unwrap();
    let centre = cam_from_world.inverse_transform_point(&nalgebra::Point3::origin());
    assert!((centre.coords - Vector3::new(10.0, 1.0, 0.0)).norm() < 1e-12);
}

#[test]
fn a_4x4_applied_transform_is_accepted_and_bad_ones_are_refused() {
    let ds = parse(&ns_document(
        r#", "applied_transform": [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]]"#,
    ))
    .unwrap();
    assert_eq!(ds.metadata.applied_transform, Some(NS_PROCESS_DATA));
    for bad in [
        r#", "applied_transform": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]"#,
        r#", "applied_transform": [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]"#,
        r#", "applied_transform": [[1, 0, 0, NaN], [0, 1, 0, 0], [0, 0, 1, 0]]"#,
        r#", "applied_transform": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]"#,
        r#", "applied_transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]"#,
        r#", "applied_transform": "identity""#,
    ] {
        let e = parse(&ns_document(bad)).unwrap_err();
        assert!(
            matches!(&e, NerfstudioError::InvalidField { field, .. } if field == "applied_transform"),
            "{bad}: {e}"
        );
    }
    // Absent: none recorded.
    assert_eq!(
        parse(&ns_document("")).unwrap().metadata.applied_transform,
        None
    );
}

#[test]
fn written_back_as_a_top_level_key_not_in_the_matloc_object() {
    let dir = tempfile::tempdir().unwrap();
    let mut ds = parse(&ns_document(
        r#", "applied_transform": [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0]]"#,
    ))
    .unwrap();
    ds.root = dir.path().to_path_buf();
    write_nerfstudio(&ds, dir.path()).unwrap();
    let text = std::fs::read_to_string(dir.path().join("transforms.json")).unwrap();
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(
        json["applied_transform"],
        serde_json::json!([
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, -1.0, 0.0, 0.0]
        ])
    );
    assert!(json.get("matloc").is_none(), "{text}");
    let back = read_nerfstudio(dir.path()).unwrap();
    assert_eq!(back.metadata.applied_transform, Some(NS_PROCESS_DATA));
    assert!(close_pose(
        &back.frames[0].cam_from_world,
        &ds.frames[0].cam_from_world,
        1e-12
    ));
}

fn pose_strategy() -> impl Strategy<Value = Pose> {
    (
        prop::array::uniform3(-1.0..1.0f64),
        0.0..3.1f64,
        prop::array::uniform3(-100.0..100.0f64),
    )
        .prop_filter_map("non-zero axis", |(axis, angle, t)| {
            let axis = nalgebra::Unit::try_new(Vector3::from(axis), 1e-3)?;
            Some(Isometry3::from_parts(
                Translation3::from(Vector3::from(t)),
                UnitQuaternion::from_axis_angle(&axis, angle),
            ))
        })
}

proptest! {
    #[test]
    fn original_and_back_is_identity(world_from_original in pose_strategy(), pose in pose_strategy()) {
        let m = world_from_original.to_homogeneous();
        let applied = [
            [m[(0, 0)], m[(0, 1)], m[(0, 2)], m[(0, 3)]],
            [m[(1, 0)], m[(1, 1)], m[(1, 2)], m[(1, 3)]],
            [m[(2, 0)], m[(2, 1)], m[(2, 2)], m[(2, 3)]],
        ];
        let original = original_cam_from_world(&applied, &pose).unwrap();
        let back = cam_from_world_from_original(&applied, &original).unwrap();
        prop_assert!(close_pose(&back, &pose, 1e-9));
        // A camera centre maps like a point: c_world = R c_original + t.
        let c_orig = original.inverse_transform_point(&nalgebra::Point3::origin());
        let c_world = pose.inverse_transform_point(&nalgebra::Point3::origin());
        prop_assert!((world_from_original * c_orig - c_world).norm() < 1e-9);
    }
}
