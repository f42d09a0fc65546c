//! A batch of queries localized in order: each query that cannot be read or localized becomes
//! a [`QueryRecord::Failed`] with the reason, and the batch goes on.

use std::error::Error;

use matloc_core::Camera;
use matloc_data::query::{Query, QuerySpec, load_query};

use super::poses::{Localized, QueryRecord};
use crate::PipelineError;
use crate::map::LoadedMap;
use crate::methods::{LocalizationMethod, MethodOptions, QueryResult, localize_with};

/// Why a batch as a whole did not localize.
#[derive(Debug, thiserror::Error)]
pub enum BatchError {
    /// There were no queries.
    #[error("no queries to localize")]
    Empty,
    /// Every query failed.
    #[error("every query failed ({0})")]
    AllFailed(usize),
}

/// `err` and its causes joined by `: `, leaving out a cause whose text the message before it
/// already ends with (many error types print their source in their own message as well as
/// returning it as `source()`).
pub fn error_chain(err: &(dyn Error + 'static)) -> String {
    let mut out = String::new();
    let mut cause = Some(err);
    while let Some(e) = cause {
        let text = e.to_string();
        if out.is_empty() || !out.ends_with(&text) {
            if !out.is_empty() {
                out.push_str(": ");
            }
            out.push_str(&text);
        }
        cause = e.source();
    }
    out
}

/// Localizes every query in order with `localize`: a query whose camera, image or localization
/// fails becomes [`QueryRecord::Failed`] (logged) and the batch goes on. `target` is the map's
/// camera (queries are brought to its resolution); `emit` sees each record as it is made, and
/// its error stops the batch.
pub fn localize_each<E>(
    specs: &[QuerySpec],
    target: Option<&Camera>,
    mut localize: impl FnMut(&Query) -> Result<QueryResult, PipelineError>,
    mut emit: impl FnMut(&QueryRecord) -> Result<(), E>,
) -> Result<Vec<QueryRecord>, E> {
    let mut records = Vec::with_capacity(specs.len());
    for (index, spec) in specs.iter().enumerate() {
        let outcome = load_query(spec, target)
            .map_err(|e| error_chain(&e))
            .and_then(|q| match localize(&q) {
                Ok(result) => Ok((q, result)),
                Err(e) => Err(format!("localizing {}: {}", q.name, error_chain(&e))),
            });
        let record = match outcome {
            Ok((q, result)) => QueryRecord::Done(Box::new(Localized {
                index,
                path: q.path,
                camera: q.file_camera,
                result,
                cam_from_world_gt: q.cam_from_world,
            })),
            Err(error) => {
                tracing::warn!(query = %spec.name, "{error}");
                QueryRecord::Failed {
                    name: spec.name.clone(),
                    error,
                }
            }
        };
        emit(&record)?;
        records.push(record);
    }
    Ok(records)
}

/// Localizes every query against `map` with `method` (see [`localize_each`]), at the map's
/// resolution.
pub fn localize_batch<E>(
    map: &LoadedMap,
    method: &dyn LocalizationMethod,
    options: &MethodOptions,
    specs: &[QuerySpec],
    emit: impl FnMut(&QueryRecord) -> Result<(), E>,
) -> Result<Vec<QueryRecord>, E> {
    localize_each(
        specs,
        map.camera().as_ref(),
        |q| localize_with(map, method, &q.name, &q.image, &q.camera, options),
        emit,
    )
}

/// The batch's outcome: an error when there were no queries or every one failed.
pub fn batch_status(records: &[QueryRecord]) -> Result<(), BatchError> {
    if records.is_empty() {
        return Err(BatchError::Empty);
    }
    if records
        .iter()
        .all(|r| matches!(r, QueryRecord::Failed { .. }))
    {
        return Err(BatchError::AllFailed(records.len()));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::query::poses::{OutputWorld, PoseFormat, WorldKind, render_text};
    use matloc_core::Pose;
    use matloc_core::pose::camera_center;
    use matloc_data::query::parse_query_list;

    fn write_png(path: &Path, w: u32, h: u32) {
        image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 4) as u8, (y * 4) as u8, 90]))
            .save(path)
            .unwrap();
    }

    fn result(q: &Query) -> QueryResult {
        let p = Pose::translation(q.image.shape().0 as f64, 0.0, 1.0);
        QueryResult {
            name: q.name.clone(),
            method: "matloc".into(),
            localized: true,
            cam_from_world: Some(p),
            camera_center: Some(camera_center(&p).coords.into()),
            confidence: Some(1.0),
            inliers: 10,
            iterations: 1,
            hypotheses: Vec::new(),
            stage_seconds: Vec::new(),
            total_seconds: 0.0,
        }
    }

    #[test]
    fn failing_queries_become_error_records_and_the_rest_localize() {
        let dir = tempfile::tempdir().unwrap();
        let images = dir.path();
        write_png(&images.join("good.png"), 32, 24);
        write_png(&images.join("small.png"), 16, 12);
        write_png(&images.join("wide.png"), 40, 24);
        write_png(&images.join("boom.png"), 32, 24);
        std::fs::write(images.join("corrupt.png"), b"\x89PNG\r\n\x1a\nnot really").unwrap();
        let list = "good.png PINHOLE 32 24 30 30 16 12\n\
                    missing.png PINHOLE 32 24 30 30 16 12\n\
                    corrupt.png PINHOLE 32 24 30 30 16 12\n\
                    fisheye.png OPENCV_FISHEYE 32 24 30 30 16 12 0.1 0.01 0 0\n\
                    small.png SIMPLE_RADIAL 32 24 30 16 12 0.01\n\
                    wide.png PINHOLE 32 24 30 30 16 12\n\
                    boom.png PINHOLE 32 24 30 30 16 12\n";
        let specs = parse_query_list(list, Path::new("q.txt"), images, None);
        let target = Camera::pinhole(32, 24, 30.0, 30.0, 16.0, 12.0).unwrap();
        let mut emitted = Vec::new();
        let records = localize_each(
            &specs,
            Some(&target),
            |q| {
                if q.name == "boom.png" {
                    return Err(PipelineError::NoPlaceHypothesis);
                }
                assert_eq!((q.camera.width, q.camera.height), (32, 24));
                Ok(result(q))
            },
            |r| {
                emitted.push(r.name().to_string());
                Ok::<(), ()>(())
            },
        )
        .unwrap();
        assert_eq!(
            emitted,
            [
                "good.png",
                "missing.png",
                "corrupt.png",
                "fisheye.png",
                "small.png",
                "wide.png",
                "boom.png"
            ]
        );
        let error = |i: usize| match &records[i] {
            QueryRecord::Failed { error, .. } => error.clone(),
            QueryRecord::Done(_) => panic!("{} should have failed", records[i].name()),
        };
        assert!(error(1).contains("missing.png"), "{}", error(1));
        assert!(error(2).contains("corrupt.png"), "{}", error(2));
        assert!(error(3).contains("OPENCV_FISHEYE"), "{}", error(3));
        assert!(
            error(5).contains("40×24") && error(5).contains("32×24"),
            "{}",
            error(5)
        );
        assert!(error(6).contains("localizing boom.png"), "{}", error(6));
        for i in [0, 4] {
            let QueryRecord::Done(l) = &records[i] else {
                panic!("{i} failed: {records:?}")
            };
            assert_eq!(l.index, i);
            assert_eq!(images.join(&l.result.name), l.path);
        }
        // The 16×12 image keeps its own-size intrinsics for the output.
        let QueryRecord::Done(small) = &records[4] else {
            unreachable!()
        };
        assert_eq!((small.camera.width, small.camera.fx), (16, 15.0));
        assert!(batch_status(&records).is_ok());

        let text = render_text(
            PoseFormat::Jsonl,
            &records,
            &OutputWorld::new(WorldKind::Data, None).unwrap(),
        )
        .unwrap();
        let lines: Vec<serde_json::Value> = text
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        assert_eq!(lines.len(), 7);
        assert!(
            lines[3]["error"]
                .as_str()
                .unwrap()
                .contains("OPENCV_FISHEYE")
        );
        assert_eq!(lines[0]["localized"], true);
    }

    #[test]
    fn the_batch_fails_only_when_every_query_failed() {
        let failed = |i| QueryRecord::Failed {
            name: format!("q{i}"),
            error: "x".into(),
        };
        let e = batch_status(&[failed(0), failed(1)]).unwrap_err();
        assert!(e.to_string().contains("every query failed (2)"), "{e}");
        assert!(batch_status(&[]).is_err());
    }
}
