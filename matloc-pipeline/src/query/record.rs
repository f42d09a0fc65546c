//! The JSON record of one localized query, shared by `matloc localize --format jsonl` (one per
//! line) and `matloc serve` (the response body): the method's [`QueryResult`] with the pose as
//! COLMAP's `qvec_wxyz` (w ≥ 0) + `tvec` (cam_from_world), the camera centre, the world the
//! pose is in, and the errors against ground truth when known.

use crate::methods::QueryResult;
use matloc_core::Pose;
use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_core::pose::{camera_center, colmap_from_cam_from_world};
use serde_json::{Value, json};

/// The record of `result`. Poses are written in the output world: `to_world` maps a pose of
/// the data's (and map's) world into it, and `world` names it (`data` or `original`).
/// `cam_from_world_gt` (data world) adds `gt_qvec_wxyz`, `gt_tvec` and, when localized,
/// `error_translation_m` and `error_rotation_deg`.
pub fn localization_record(
    result: &QueryResult,
    world: &str,
    to_world: &dyn Fn(&Pose) -> Pose,
    cam_from_world_gt: Option<&Pose>,
) -> Result<Value, serde_json::Error> {
    let r = result;
    let mut v = serde_json::to_value(r)?;
    let Value::Object(obj) = &mut v else {
        return Ok(v);
    };
    obj.remove("cam_from_world");
    let pose = r.cam_from_world.map(|p| to_world(&p));
    let (q, t) = pose.as_ref().map(colmap_from_cam_from_world).unzip();
    obj.insert("qvec_wxyz".into(), json!(q));
    obj.insert("tvec".into(), json!(t));
    let center: Option<[f64; 3]> = pose.map(|p| camera_center(&p).coords.into());
    obj.insert("camera_center".into(), json!(center));
    obj.insert("world".into(), json!(world));
    if let Some(Value::Array(hyps)) = obj.get_mut("hypotheses") {
        for (hv, h) in hyps.iter_mut().zip(&r.hypotheses) {
            if let Some(ho) = hv.as_object_mut() {
                ho.remove("coarse_cam_from_world");
                let (q, t) = colmap_from_cam_from_world(&to_world(&h.coarse_cam_from_world));
                ho.insert("coarse_qvec_wxyz".into(), json!(q));
                ho.insert("coarse_tvec".into(), json!(t));
                ho.remove("refined_cam_from_world");
                if let Some(refined) = &h.refined_cam_from_world {
                    let (q, t) = colmap_from_cam_from_world(&to_world(refined));
                    ho.insert("refined_qvec_wxyz".into(), json!(q));
                    ho.insert("refined_tvec".into(), json!(t));
                }
            }
        }
    }
    if let Some(gt) = cam_from_world_gt {
        let (q, t) = colmap_from_cam_from_world(&to_world(gt));
        obj.insert("gt_qvec_wxyz".into(), json!(q));
        obj.insert("gt_tvec".into(), json!(t));
        if let Some(est) = &r.cam_from_world {
            obj.insert(
                "error_translation_m".into(),
                json!(translation_error_m(est, gt)),
            );
            obj.insert(
                "error_rotation_deg".into(),
                json!(rotation_error_deg(est, gt)),
            );
        }
    }
    Ok(v)
}

/// The record of a query that failed before or during localization.
pub fn error_record(name: &str, error: &str) -> Value {
    json!({"name": name, "error": error})
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::HypothesisReport;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    fn pose(x: f64, yaw: f64) -> Pose {
        Pose::from_parts(
            Translation3::new(x, 2.0, 30.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
        )
    }

    /// A hypothesis's coarse and reached poses are written in the output world as COLMAP's
    /// `qvec_wxyz` / `tvec`, and nothing of the library's own pose layout is left.
    #[test]
    fn hypothesis_poses_are_written_in_the_output_world() {
        let (coarse, refined) = (pose(1.0, 0.2), pose(1.5, 0.25));
        let report = |refined_cam_from_world| HypothesisReport {
            group: 3,
            score: 0.5,
            block: 0,
            coarse_cam_from_world: coarse,
            matches: 40,
            inliers: 20,
            confidence: 0.9,
            passes: 1,
            accepted: false,
            failure: None,
            alignment: 0.0,
            log10_nfa: Some(-3.0),
            refined_cam_from_world,
        };
        let result = QueryResult {
            name: "q".into(),
            method: "structure".into(),
            localized: false,
            cam_from_world: None,
            camera_center: None,
            confidence: Some(0.0),
            inliers: 20,
            iterations: 2,
            hypotheses: vec![report(Some(refined)), report(None)],
            stage_seconds: Vec::new(),
            total_seconds: 0.1,
        };
        let shift = Pose::from_parts(
            Translation3::new(10.0, 0.0, 0.0),
            UnitQuaternion::identity(),
        );
        let to_world = |p: &Pose| *p * shift.inverse();
        let v = localization_record(&result, "original", &to_world, None).unwrap();
        let hyps = v["hypotheses"].as_array().unwrap();
        let (q, t) = colmap_from_cam_from_world(&to_world(&refined));
        assert_eq!(hyps[0]["refined_qvec_wxyz"], json!(q));
        assert_eq!(hyps[0]["refined_tvec"], json!(t));
        let (q, t) = colmap_from_cam_from_world(&to_world(&coarse));
        assert_eq!(hyps[0]["coarse_qvec_wxyz"], json!(q));
        assert_eq!(hyps[0]["coarse_tvec"], json!(t));
        for h in hyps {
            assert!(h.get("refined_cam_from_world").is_none());
            assert!(h.get("coarse_cam_from_world").is_none());
        }
        assert!(hyps[1].get("refined_tvec").is_none());
    }
}
