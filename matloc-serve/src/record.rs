//! The JSON record of one localized query, shared by `matloc localize --format jsonl` (one per
//! line) and `matloc serve` (the response body): the method's [`QueryResult`] with the pose as
//! COLMAP's `qvec_wxyz` (w ≥ 0) + `tvec` (cam_from_world), the camera centre, the world the
//! pose is in, and the errors against ground truth when known.

use matloc_core::Pose;
use matloc_core::metrics::{rotation_error_deg, translation_error_m};
use matloc_core::pose::{camera_center, colmap_from_cam_from_world};
use matloc_pipeline::methods::QueryResult;
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
