//! Query intrinsics as a request or a query list states them: a COLMAP model name with its
//! parameters (hloc's `queries_with_intrinsics.txt`, the `camera` part of a request), nerfstudio
//! keys, or a matloc [`Camera`]. Only models the renderer and solver handle (pinhole +
//! Brown–Conrady) are read; any other is rejected by name, with the supported list. Image sizes
//! are whole numbers, written as integers or as whole-valued floats (`160.0`, as Python's
//! `json.dumps` writes a float); [`check_plausible`] rejects intrinsics no real camera has.

use crate::colmap::{ColmapCamera, ColmapCameraModel};
use matloc_core::{Camera, CameraError, Distortion, ImplausibleCamera};
use serde::Deserialize;
use serde_json::Value;

/// Why intrinsics cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum CameraSpecError {
    /// The text is not JSON.
    #[error("not valid JSON: {0}")]
    Json(#[source] serde_json::Error),
    /// The model name is not one of COLMAP's.
    #[error("camera model {model} is not a COLMAP model (supported: {supported})")]
    UnknownModel {
        /// The name given (upper case).
        model: String,
        /// The supported names, comma-separated.
        supported: String,
    },
    /// A COLMAP or nerfstudio model matloc does not handle (fisheye, full OpenCV, ...).
    #[error("camera model {model} is not supported (supported: {supported})")]
    UnsupportedModel {
        /// The name given (upper case).
        model: String,
        /// The supported names, comma-separated.
        supported: String,
    },
    /// The parameter list does not have the model's length.
    #[error("{model} takes {expected} parameters, got {got}")]
    ParamCount {
        /// The model.
        model: &'static str,
        /// Parameters the model takes.
        expected: usize,
        /// Parameters given.
        got: usize,
    },
    /// One field has the wrong type or value.
    #[error("`{field}`: {message}")]
    Field {
        /// The field.
        field: &'static str,
        /// What is wrong with it.
        message: String,
    },
    /// The object has none of the accepted key sets.
    #[error(
        "expected a COLMAP camera (model, width, height, params), nerfstudio intrinsics (w, h, fl_x, fl_y, cx, cy) or a matloc camera (width, height, fx, fy, cx, cy): {0}"
    )]
    Shape(String),
    /// The values do not make a valid camera (non-positive focal length, empty image, ...).
    #[error("invalid {model} camera: {source}")]
    Invalid {
        /// The model read.
        model: &'static str,
        /// What is wrong.
        source: CameraError,
    },
    /// Well-formed intrinsics that no real camera has (see [`Camera::plausibility`]).
    #[error("implausible camera: {0}")]
    Implausible(#[source] ImplausibleCamera),
}

impl CameraSpecError {
    /// The camera field at fault, where one is (`width`, `fx`, `k4`, `distortion`, ...).
    pub fn field(&self) -> Option<&'static str> {
        match self {
            CameraSpecError::Field { field, .. } => Some(field),
            CameraSpecError::Implausible(p) => Some(p.field()),
            CameraSpecError::Invalid {
                source:
                    CameraError::NonFinite { field, .. } | CameraError::NonPositiveFocal { field, .. },
                ..
            } => Some(field),
            _ => None,
        }
    }
}

/// Rejects intrinsics that break the bounds of a real camera ([`Camera::check_plausible`]:
/// image sides up to [`matloc_core::camera::MAX_IMAGE_SIDE`], a field of view inside
/// [`matloc_core::camera::FOV_RANGE_DEG`], the principal point near the image, bounded lens
/// distortion), naming the field and the bound. Depends only on the camera, so it runs before
/// the image is decoded.
pub fn check_plausible(camera: &Camera) -> Result<(), CameraSpecError> {
    camera
        .check_plausible()
        .map_err(CameraSpecError::Implausible)
}

/// The supported COLMAP model names, comma-separated.
pub fn supported_models() -> String {
    ColmapCameraModel::ALL.map(|m| m.name()).join(", ")
}

/// A COLMAP camera model by name (case-insensitive), rejecting models matloc does not handle.
pub fn colmap_model(name: &str) -> Result<ColmapCameraModel, CameraSpecError> {
    let model = name.to_ascii_uppercase();
    ColmapCameraModel::from_name(&model).map_err(|desc| {
        let supported = supported_models();
        if desc.starts_with("unknown") {
            CameraSpecError::UnknownModel { model, supported }
        } else {
            CameraSpecError::UnsupportedModel { model, supported }
        }
    })
}

/// The camera of a COLMAP model `name` (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL or
/// OPENCV) with `params` in COLMAP's order, for `width`×`height` images.
pub fn colmap_camera(
    name: &str,
    width: u32,
    height: u32,
    params: &[f64],
) -> Result<Camera, CameraSpecError> {
    let model = colmap_model(name)?;
    if params.len() != model.num_params() {
        return Err(CameraSpecError::ParamCount {
            model: model.name(),
            expected: model.num_params(),
            got: params.len(),
        });
    }
    ColmapCamera {
        id: 0,
        model,
        width,
        height,
        params: params.to_vec(),
    }
    .to_camera()
    .map_err(|source| CameraSpecError::Invalid {
        model: model.name(),
        source,
    })
}

/// nerfstudio `camera_model` values read as pinhole + Brown–Conrady (as the transforms.json
/// reader does); every other model (fisheye, equirectangular) is rejected by name.
pub const NERFSTUDIO_MODELS: [&str; 5] = [
    "PINHOLE",
    "SIMPLE_PINHOLE",
    "OPENCV",
    "SIMPLE_RADIAL",
    "RADIAL",
];

#[derive(Deserialize)]
struct NerfstudioIntrinsics {
    w: u32,
    h: u32,
    fl_x: f64,
    fl_y: f64,
    cx: f64,
    cy: f64,
    #[serde(default)]
    k1: f64,
    #[serde(default)]
    k2: f64,
    #[serde(default)]
    p1: f64,
    #[serde(default)]
    p2: f64,
    #[serde(default)]
    k3: f64,
    #[serde(default)]
    k4: f64,
}

#[derive(Deserialize)]
struct ColmapParams {
    params: Vec<f64>,
}

/// A JSON number as a positive whole number of pixels: an integer, or a float with no
/// fractional part (`160.0`), at most `u32::MAX`.
fn size_value(v: &Value, field: &'static str) -> Result<u32, CameraSpecError> {
    let whole = match v {
        Value::Number(n) => n.as_u64().or_else(|| {
            n.as_f64()
                .filter(|f| f.fract() == 0.0 && *f >= 0.0 && *f <= f64::from(u32::MAX))
                .map(|f| f as u64)
        }),
        _ => None,
    };
    whole
        .filter(|&n| n > 0 && n <= u64::from(u32::MAX))
        .map(|n| n as u32)
        .ok_or_else(|| CameraSpecError::Field {
            field,
            message: format!("expected a positive whole number, got {v}"),
        })
}

/// `field` of `value` as a positive whole number.
fn size_field(value: &Value, field: &'static str) -> Result<u32, CameraSpecError> {
    let v = value.get(field).ok_or_else(|| CameraSpecError::Field {
        field,
        message: "missing".into(),
    })?;
    size_value(v, field)
}

/// Rewrites the size `fields` present in `value` as integers ([`size_value`]), so the typed
/// readers take `160.0` as 160; a size that is not a positive whole number is an error naming
/// the field.
fn whole_sizes(value: &mut Value, fields: [&'static str; 2]) -> Result<(), CameraSpecError> {
    for field in fields {
        if let Some(v) = value.get_mut(field) {
            *v = Value::from(size_value(v, field)?);
        }
    }
    Ok(())
}

/// Reads intrinsics JSON: `{"model": "PINHOLE", "width": W, "height": H, "params": [...]}`
/// (COLMAP names and parameter order), nerfstudio keys (`w`, `h`, `fl_x`, `fl_y`, `cx`, `cy`,
/// optional `camera_model`, `k1 k2 p1 p2 k3`), or a matloc camera (`width`, `height`, `fx`,
/// `fy`, `cx`, `cy`, optional `distortion`).
pub fn parse_camera_json(text: &str) -> Result<Camera, CameraSpecError> {
    let mut value: Value = serde_json::from_str(text).map_err(CameraSpecError::Json)?;
    if !value.is_object() {
        return Err(CameraSpecError::Shape(format!("got {}", json_kind(&value))));
    }
    if let Some(model) = value.get("model") {
        let name = model
            .as_str()
            .ok_or_else(|| CameraSpecError::Field {
                field: "model",
                message: format!("expected a string, got {model}"),
            })?
            .to_string();
        // Checked first so an unsupported model is named even when its parameters differ.
        colmap_model(&name)?;
        let width = size_field(&value, "width")?;
        let height = size_field(&value, "height")?;
        let c: ColmapParams =
            serde_json::from_value(value).map_err(|e| CameraSpecError::Field {
                field: "params",
                message: e.to_string(),
            })?;
        return colmap_camera(&name, width, height, &c.params);
    }
    if let Some(model) = value.get("camera_model") {
        let model = model
            .as_str()
            .ok_or_else(|| CameraSpecError::Field {
                field: "camera_model",
                message: format!("expected a string, got {model}"),
            })?
            .to_ascii_uppercase();
        if !NERFSTUDIO_MODELS.contains(&model.as_str()) {
            return Err(CameraSpecError::UnsupportedModel {
                model,
                supported: NERFSTUDIO_MODELS.join(", "),
            });
        }
    }
    let (camera, model) = if value.get("w").is_some() || value.get("fl_x").is_some() {
        whole_sizes(&mut value, ["w", "h"])?;
        let n: NerfstudioIntrinsics = serde_json::from_value(value)
            .map_err(|e| CameraSpecError::Shape(format!("nerfstudio intrinsics: {e}")))?;
        if n.k4 != 0.0 {
            return Err(CameraSpecError::Field {
                field: "k4",
                message:
                    "fisheye / rational models are not supported; use OPENCV with k1 k2 p1 p2 k3"
                        .into(),
            });
        }
        let camera = Camera {
            width: n.w,
            height: n.h,
            fx: n.fl_x,
            fy: n.fl_y,
            cx: n.cx,
            cy: n.cy,
            distortion: Distortion {
                k1: n.k1,
                k2: n.k2,
                p1: n.p1,
                p2: n.p2,
                k3: n.k3,
            },
        };
        (camera, "nerfstudio")
    } else {
        whole_sizes(&mut value, ["width", "height"])?;
        let camera: Camera = serde_json::from_value(value)
            .map_err(|e| CameraSpecError::Shape(format!("matloc camera: {e}")))?;
        (camera, "matloc")
    };
    camera
        .validate()
        .map_err(|source| CameraSpecError::Invalid { model, source })?;
    Ok(camera)
}

fn json_kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colmap_json_reads_parameters_in_colmap_order() {
        let c = parse_camera_json(
            r#"{"model": "opencv", "width": 640, "height": 480, "params": [500, 510, 320, 240, 0.1, -0.02, 0.001, 0.002]}"#,
        )
        .unwrap();
        assert_eq!((c.fx, c.fy, c.cx, c.cy), (500.0, 510.0, 320.0, 240.0));
        assert_eq!(c.distortion.p2, 0.002);
        let c = parse_camera_json(
            r#"{"model": "SIMPLE_RADIAL", "width": 64, "height": 48, "params": [50, 32, 24, 0.1]}"#,
        )
        .unwrap();
        assert_eq!((c.fx, c.fy, c.distortion.k1), (50.0, 50.0, 0.1));
    }

    #[test]
    fn bad_cameras_name_the_model_or_field() {
        let err = |t: &str| parse_camera_json(t).unwrap_err().to_string();
        let e = err(
            r#"{"model": "OPENCV_FISHEYE", "width": 64, "height": 48, "params": [1, 1, 1, 1, 0, 0, 0, 0]}"#,
        );
        assert!(
            e.contains("OPENCV_FISHEYE") && e.contains("not supported"),
            "{e}"
        );
        let e = err(r#"{"model": "NOPE", "width": 64, "height": 48, "params": []}"#);
        assert!(e.contains("NOPE is not a COLMAP model"), "{e}");
        let e = err(r#"{"model": "PINHOLE", "width": 64, "height": 48, "params": [1, 1, 1]}"#);
        assert!(e.contains("PINHOLE takes 4 parameters, got 3"), "{e}");
        let e = err(r#"{"model": "PINHOLE", "width": 0, "height": 48, "params": [1, 1, 1, 1]}"#);
        assert!(e.contains("`width`"), "{e}");
        let e = err(r#"{"model": "PINHOLE", "width": 64, "height": 48, "params": "x"}"#);
        assert!(e.contains("`params`"), "{e}");
        let e = err(r#"{"model": "PINHOLE", "width": 64, "height": 48, "params": [-5, 1, 1, 1]}"#);
        assert!(e.contains("focal"), "{e}");
        let e = err(
            r#"{"w": 64, "h": 48, "fl_x": 50, "fl_y": 50, "cx": 32, "cy": 24, "camera_model": "FISHEYE"}"#,
        );
        assert!(e.contains("FISHEYE"), "{e}");
        let e = err(r#"{"w": 64, "h": 48, "fl_x": 50, "fl_y": 50, "cx": 32, "cy": 24, "k4": 0.1}"#);
        assert!(e.contains("k4"), "{e}");
        let e = err(r#"{"width": 64}"#);
        assert!(e.contains("matloc camera"), "{e}");
        assert!(err("[1, 2]").contains("an array"));
        assert!(err("{").contains("not valid JSON"));
    }

    #[test]
    fn whole_valued_float_sizes_read_as_integers() {
        let want = Camera::pinhole(160, 120, 150.0, 150.0, 80.0, 60.0).unwrap();
        for text in [
            r#"{"model": "PINHOLE", "width": 160.0, "height": 120.0, "params": [150, 150, 80, 60]}"#,
            r#"{"w": 160.0, "h": 1.2e2, "fl_x": 150, "fl_y": 150, "cx": 80, "cy": 60}"#,
            r#"{"width": 160.0, "height": 120, "fx": 150, "fy": 150, "cx": 80, "cy": 60}"#,
        ] {
            assert_eq!(parse_camera_json(text).unwrap(), want, "{text}");
        }
        for (text, field) in [
            (
                r#"{"model": "PINHOLE", "width": 160.5, "height": 120, "params": [150, 150, 80, 60]}"#,
                "width",
            ),
            (
                r#"{"w": 160, "h": 120.25, "fl_x": 150, "fl_y": 150, "cx": 80, "cy": 60}"#,
                "h",
            ),
            (
                r#"{"width": 160, "height": -120.0, "fx": 150, "fy": 150, "cx": 80, "cy": 60}"#,
                "height",
            ),
            (
                r#"{"width": 1e300, "height": 120, "fx": 150, "fy": 150, "cx": 80, "cy": 60}"#,
                "width",
            ),
            (
                r#"{"width": "160", "height": 120, "fx": 150, "fy": 150, "cx": 80, "cy": 60}"#,
                "width",
            ),
        ] {
            let e = parse_camera_json(text).unwrap_err();
            assert_eq!(e.field(), Some(field), "{e}");
            assert!(
                e.to_string().contains(&format!("`{field}`"))
                    && e.to_string().contains("positive whole number"),
                "{e}"
            );
        }
    }

    #[test]
    fn implausible_cameras_name_the_field_and_the_bound() {
        let cases = [
            (
                r#"{"model": "PINHOLE", "width": 1000000000, "height": 750000000, "params": [150, 150, 80, 60]}"#,
                "width",
                "1..=65536",
            ),
            (
                r#"{"model": "PINHOLE", "width": 160, "height": 120, "params": [1e308, 1e308, 80, 60]}"#,
                "fx",
                "0.5–170°",
            ),
            (
                r#"{"model": "PINHOLE", "width": 160, "height": 120, "params": [150, 150, 1e308, -1e308]}"#,
                "cx",
                "0.25 × the image side",
            ),
            (
                r#"{"model": "OPENCV", "width": 160, "height": 120, "params": [150, 150, 80, 60, 1e30, 0, 0, 0]}"#,
                "distortion",
                "4×",
            ),
            (
                r#"{"model": "OPENCV", "width": 160, "height": 120, "params": [150, 150, 80, 60, 0, 0, 10, 0]}"#,
                "p1",
                "±0.1",
            ),
        ];
        for (text, field, bound) in cases {
            let camera = parse_camera_json(text).unwrap();
            let e = check_plausible(&camera).unwrap_err();
            assert_eq!(e.field(), Some(field), "{e}");
            let msg = e.to_string();
            assert!(
                msg.contains(&format!("`{field}`")) && msg.contains(bound),
                "{msg}"
            );
        }
        let ok = parse_camera_json(
            r#"{"model": "OPENCV", "width": 160, "height": 120, "params": [150, 150, 80, 60, -0.1, 0.01, 0.001, 0]}"#,
        )
        .unwrap();
        check_plausible(&ok).unwrap();
    }

    #[test]
    fn nerfstudio_and_matloc_keys_read() {
        let c = parse_camera_json(
            r#"{"w": 64, "h": 48, "fl_x": 50, "fl_y": 51, "cx": 32, "cy": 24, "camera_model": "OPENCV", "k1": 0.1}"#,
        )
        .unwrap();
        assert_eq!((c.width, c.fy, c.distortion.k1), (64, 51.0, 0.1));
        let c = parse_camera_json(
            r#"{"width": 64, "height": 48, "fx": 50, "fy": 50, "cx": 32, "cy": 24}"#,
        )
        .unwrap();
        assert_eq!(c, Camera::pinhole(64, 48, 50.0, 50.0, 32.0, 24.0).unwrap());
    }
}
