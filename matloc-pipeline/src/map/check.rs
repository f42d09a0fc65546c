//! The content of a map's files, checked beyond their checksums: a file replaced together with
//! its manifest entry (size and SHA-256 updated) must still be what its stage writes and what
//! localization loads.
//!
//! [`content_problems`] parses every listed file that passed its checksum: a safetensors
//! container's header and tensors (every float value finite), a JSON file into its type, a PNG
//! decoded, a PLY parsed; then the map's parts as [`crate::map::LoadedMap::open`] loads them
//! (the config in the manifest, the partition, each block's NeRF, encoder and selection
//! through [`NerfMapComponents`], the place predictor, the calibration, the keypoint
//! structure), with the checks between them: the partition has the manifest's blocks, each
//! selection names distinct dims below the field's feature dimension that its encoder
//! produces and the manifest records.

use std::collections::BTreeSet;
use std::path::Path;

use matloc_nerf_field::FEATURE_DIM;
use matloc_partition::Partition;
use safetensors::{Dtype, SafeTensors};

use crate::config::MapConfig;
use crate::gt::GtPairSet;
use crate::map::layout::{
    CONFIDENCE_FILE, CalibrationRecord, PARTITION_FILE, PLACE_DIR, PLAN_FILE, PlanRecord,
    STRUCTURE_FILE, SelectionRecord, block_dir, encoder_file, pairs_file, selection_file,
};
use crate::map::load::{MapComponents, NerfMapComponents};
use crate::map::manifest::{MANIFEST_FILE, MapDir, MapError};

fn content(map: &MapDir, name: &str, field: impl Into<String>, message: String) -> MapError {
    MapError::Content {
        path: map.root().join(name),
        field: field.into(),
        message,
    }
}

/// Every value of a float tensor finite: the first one that is not, with the count.
fn non_finite(dtype: Dtype, data: &[u8]) -> Option<(usize, f64, usize)> {
    let values: Box<dyn Iterator<Item = f64> + '_> = match dtype {
        Dtype::F32 => Box::new(
            data.chunks_exact(4)
                .map(|b| f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]]))),
        ),
        Dtype::F64 => Box::new(
            data.chunks_exact(8)
                .map(|b| f64::from_le_bytes(b.try_into().unwrap_or([0; 8]))),
        ),
        _ => return None,
    };
    let mut first = None;
    let mut count = 0;
    for (i, v) in values.enumerate() {
        if !v.is_finite() {
            count += 1;
            first.get_or_insert((i, v));
        }
    }
    first.map(|(i, v)| (i, v, count))
}

/// Dtypes the map's writers use.
const DTYPES: [Dtype; 5] = [Dtype::F32, Dtype::F64, Dtype::U8, Dtype::U32, Dtype::U64];

/// A safetensors container: its header parses, each tensor has a dtype the map's writers use,
/// and every float value is finite.
fn check_safetensors(map: &MapDir, name: &str, bytes: &[u8]) -> Vec<MapError> {
    let st = match SafeTensors::deserialize(bytes) {
        Ok(st) => st,
        Err(e) => return vec![content(map, name, "header", e.to_string())],
    };
    let mut problems = Vec::new();
    let mut tensors = st.tensors();
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    for (tensor, view) in tensors {
        if !DTYPES.contains(&view.dtype()) {
            problems.push(content(
                map,
                name,
                format!("tensor `{tensor}`"),
                format!("dtype {:?}, expected one of {DTYPES:?}", view.dtype()),
            ));
        } else if let Some((i, v, count)) = non_finite(view.dtype(), view.data()) {
            problems.push(content(
                map,
                name,
                format!("tensor `{tensor}`"),
                format!(
                    "{count} of {} values not finite (the first, {v}, at index {i})",
                    view.shape().iter().product::<usize>()
                ),
            ));
        }
    }
    problems
}

/// The file's own format: safetensors, JSON, PNG, PLY (by extension).
fn check_format(map: &MapDir, name: &str, bytes: &[u8]) -> Vec<MapError> {
    let path = map.root().join(name);
    let ext = Path::new(name)
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("");
    match ext {
        "safetensors" => check_safetensors(map, name, bytes),
        "json" => match serde_json::from_slice::<serde_json::Value>(bytes) {
            Ok(_) => Vec::new(),
            Err(e) => vec![content(map, name, "JSON", e.to_string())],
        },
        "png" => match matloc_data::images::check_image(&path) {
            Ok(_) => Vec::new(),
            Err(e) => vec![content(map, name, "image", e.to_string())],
        },
        "ply" => match matloc_data::ply::parse_ply(bytes, &path) {
            Ok(_) => Vec::new(),
            Err(e) => vec![content(map, name, "points", e.to_string())],
        },
        _ => Vec::new(),
    }
}

/// Parses listed file `name` as `T` (the bytes read through the map, checksum verified).
fn parse<T: for<'de> serde::Deserialize<'de>>(map: &MapDir, name: &str) -> Result<T, MapError> {
    let bytes = map.read_file(name)?;
    serde_json::from_slice(&bytes).map_err(|e| {
        content(
            map,
            name,
            std::any::type_name::<T>()
                .rsplit("::")
                .next()
                .unwrap_or("JSON"),
            e.to_string(),
        )
    })
}

/// A block's selection: dims distinct, below [`FEATURE_DIM`], at most `config`'s count, and
/// those the manifest records for the block.
fn check_selection(map: &MapDir, b: usize, sel: &SelectionRecord) -> Vec<MapError> {
    let name = selection_file(b);
    let mut problems = Vec::new();
    if sel.dims.is_empty() {
        problems.push(content(map, &name, "dims", "no dim selected".into()));
    }
    if let Some(d) = sel.dims.iter().find(|&&d| d >= FEATURE_DIM) {
        problems.push(content(
            map,
            &name,
            "dims",
            format!("dim {d} is not below the feature dimension {FEATURE_DIM}"),
        ));
    }
    let distinct: BTreeSet<usize> = sel.dims.iter().copied().collect();
    if distinct.len() != sel.dims.len() {
        problems.push(content(map, &name, "dims", "a dim is listed twice".into()));
    }
    if let Some(entry) = map.manifest().blocks.get(b)
        && entry.selected_dims != sel.dims
    {
        problems.push(content(
            map,
            &name,
            "dims",
            format!(
                "{:?}, the manifest records {:?} for block {b}",
                sel.dims, entry.selected_dims
            ),
        ));
    }
    problems
}

/// The partition: blocks numbered in order, each with poses below its pose count, and as many
/// as the manifest lists.
fn check_partition(map: &MapDir, p: &Partition) -> Vec<MapError> {
    let mut problems = Vec::new();
    let listed = map.manifest().blocks.len();
    if p.blocks.is_empty() {
        problems.push(content(map, PARTITION_FILE, "blocks", "no block".into()));
    } else if p.blocks.len() != listed {
        problems.push(content(
            map,
            PARTITION_FILE,
            "blocks",
            format!("{} blocks, the manifest lists {listed}", p.blocks.len()),
        ));
    }
    for (i, block) in p.blocks.iter().enumerate() {
        if block.id != i {
            problems.push(content(
                map,
                PARTITION_FILE,
                format!("blocks[{i}].id"),
                format!("{}, expected {i}", block.id),
            ));
        }
        if block.pose_ids.is_empty() {
            problems.push(content(
                map,
                PARTITION_FILE,
                format!("blocks[{i}].pose_ids"),
                "no pose".into(),
            ));
        }
        if let Some(id) = block.pose_ids.iter().find(|&&id| id >= p.num_poses) {
            problems.push(content(
                map,
                PARTITION_FILE,
                format!("blocks[{i}].pose_ids"),
                format!("pose {id}, the partition has {} poses", p.num_poses),
            ));
        }
    }
    problems
}

/// What `map info` shows of the keypoint structure.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct StructureSummary {
    /// Triangulated points.
    pub points: usize,
    /// Keypoints observing them.
    pub observations: usize,
    /// Training images with an observation.
    pub images: usize,
    /// Descriptors kept per observation: `binary` or `binary+gradient`.
    pub descriptors: &'static str,
    /// How far the points project from their keypoints (`None` for maps without the images'
    /// cameras).
    pub reprojection: Option<matloc_structure::ReprojectionStats>,
}

/// The map's structure summarised, when it has one that loads.
pub fn structure_summary(map: &MapDir) -> Option<StructureSummary> {
    let bytes = map.read_file(STRUCTURE_FILE).ok()?;
    let s = matloc_structure::StructureMap::from_bytes(&bytes, &map.root().join(STRUCTURE_FILE))
        .ok()?;
    Some(StructureSummary {
        points: s.points().len(),
        observations: s.observations(),
        images: s.images().len(),
        descriptors: if s.has_gradients() {
            "binary+gradient"
        } else {
            "binary"
        },
        reprojection: s.reprojection_errors(),
    })
}

/// Every problem in the content of the map's files that passed their checksums (see the
/// module docs); empty for a map that localization loads as it was built. Files that fail
/// their checksum are left to [`MapDir::problems`].
pub fn content_problems(map: &MapDir) -> Vec<MapError> {
    let mut problems = Vec::new();
    // Files whose bytes cannot be trusted or parsed: the loads that read them are skipped.
    let mut bad: BTreeSet<String> = BTreeSet::new();
    for name in map.manifest().files.keys() {
        let found = match map.read_file(name) {
            Ok(bytes) => check_format(map, name, &bytes),
            Err(_) => {
                bad.insert(name.clone());
                continue;
            }
        };
        if !found.is_empty() {
            bad.insert(name.clone());
            problems.extend(found);
        }
    }
    let usable = |names: &[String]| {
        names
            .iter()
            .all(|n| map.manifest().files.contains_key(n) && !bad.contains(n))
    };

    let config: Option<MapConfig> = match serde_json::from_value(map.manifest().config.clone()) {
        Ok(c) => Some(c),
        Err(e) => {
            problems.push(content(map, MANIFEST_FILE, "config", e.to_string()));
            None
        }
    };
    let partition: Option<Partition> = if usable(&[PARTITION_FILE.to_string()]) {
        match parse::<Partition>(map, PARTITION_FILE) {
            Ok(p) => {
                let found = check_partition(map, &p);
                let ok = found.is_empty();
                problems.extend(found);
                ok.then_some(p)
            }
            Err(e) => {
                problems.push(e);
                None
            }
        }
    } else {
        None
    };
    let blocks = partition
        .as_ref()
        .map_or(map.manifest().blocks.len(), |p| p.blocks.len());
    let components = NerfMapComponents;

    for b in 0..blocks {
        let selection = selection_file(b);
        let sel = if usable(std::slice::from_ref(&selection)) {
            match parse::<SelectionRecord>(map, &selection) {
                Ok(sel) => {
                    let found = check_selection(map, b, &sel);
                    let ok = found.is_empty();
                    problems.extend(found);
                    ok.then_some(sel)
                }
                Err(e) => {
                    problems.push(e);
                    None
                }
            }
        } else {
            None
        };
        let nerf_files = [
            format!("{}/{}", block_dir(b), matloc_render::CONFIG_FILE),
            format!("{}/{}", block_dir(b), matloc_render::WEIGHTS_FILE),
        ];
        if let Some(config) = &config
            && usable(&nerf_files)
            && let Err(e) = components.renderer(map, b, &config.localize)
        {
            problems.push(content(map, &nerf_files[1], "model", e.to_string()));
        }
        let encoder = encoder_file(b);
        if usable(std::slice::from_ref(&encoder)) {
            match components.encoder(map, b) {
                Err(e) => problems.push(content(map, &encoder, "encoder", e.to_string())),
                Ok(enc) => {
                    if let Some(sel) = &sel
                        && let Err(e) = components.matcher(enc.as_ref(), &sel.dims, None)
                    {
                        problems.push(content(map, &selection, "dims", e.to_string()));
                    }
                }
            }
        }
        let pairs = pairs_file(b);
        if usable(std::slice::from_ref(&pairs)) {
            let path = map.root().join(&pairs);
            match map
                .read_file(&pairs)
                .map(|bytes| GtPairSet::from_bytes(&bytes, &path))
            {
                Ok(Err(e)) => problems.push(content(map, &pairs, "pairs", e.to_string())),
                Ok(Ok(set)) => {
                    if let Some(d) = set.provenance.dims.iter().find(|&&d| d >= FEATURE_DIM) {
                        problems.push(content(
                            map,
                            &pairs,
                            "provenance.dims",
                            format!("dim {d} is not below the feature dimension {FEATURE_DIM}"),
                        ));
                    }
                }
                Err(_) => {}
            }
        }
    }

    let place_files =
        [matloc_place::MODEL_JSON, matloc_place::MODEL_WEIGHTS].map(|f| format!("{PLACE_DIR}/{f}"));
    if let Some(config) = &config
        && usable(&place_files)
        && let Err(e) = components.place(map, config)
    {
        problems.push(content(map, &place_files[1], "place model", e.to_string()));
    }
    if usable(&[CONFIDENCE_FILE.to_string()])
        && let Err(e) = parse::<CalibrationRecord>(map, CONFIDENCE_FILE)
    {
        problems.push(e);
    }
    if usable(&[PLAN_FILE.to_string()]) {
        match parse::<PlanRecord>(map, PLAN_FILE) {
            Err(e) => problems.push(e),
            Ok(plan) => {
                if let Some(b) = plan.blocks.iter().find(|&&b| b >= blocks) {
                    problems.push(content(
                        map,
                        PLAN_FILE,
                        "blocks",
                        format!("block {b}, the map has {blocks}"),
                    ));
                }
            }
        }
    }
    if usable(&[STRUCTURE_FILE.to_string()]) {
        let path = map.root().join(STRUCTURE_FILE);
        if let Ok(bytes) = map.read_file(STRUCTURE_FILE)
            && let Err(e) = matloc_structure::StructureMap::from_bytes(&bytes, &path)
        {
            problems.push(content(map, STRUCTURE_FILE, "structure", e.to_string()));
        }
    }
    problems
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::manifest::BlockEntry;
    use safetensors::tensor::TensorView;

    fn floats(values: &[f32]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    fn container(tensors: &[(&str, Dtype, Vec<usize>, Vec<u8>)]) -> Vec<u8> {
        let views: Vec<(String, TensorView<'_>)> = tensors
            .iter()
            .map(|(n, d, s, b)| (n.to_string(), TensorView::new(*d, s.clone(), b).unwrap()))
            .collect();
        safetensors::serialize(views, None).unwrap()
    }

    fn map_with(files: &[(&str, Vec<u8>)]) -> (tempfile::TempDir, MapDir) {
        let dir = tempfile::tempdir().unwrap();
        let mut map = MapDir::create_or_resume(dir.path(), serde_json::json!({})).unwrap();
        map.manifest_mut().blocks.push(BlockEntry {
            id: 0,
            bounds_min: [0.0; 3],
            bounds_max: [1.0; 3],
            num_poses: 3,
            selected_dims: vec![1, 2],
        });
        for (name, bytes) in files {
            std::fs::create_dir_all(dir.path().join(name).parent().unwrap()).unwrap();
            map.write_file(name, bytes).unwrap();
        }
        map.save().unwrap();
        (dir, map)
    }

    fn messages(problems: &[MapError]) -> Vec<String> {
        problems.iter().map(|p| p.to_string()).collect()
    }

    #[test]
    fn safetensors_are_parsed_and_every_float_must_be_finite() {
        let good = container(&[
            ("a", Dtype::F32, vec![2, 2], floats(&[1.0, 2.0, 3.0, 4.0])),
            ("n", Dtype::U32, vec![1], 7u32.to_le_bytes().to_vec()),
        ]);
        let nan = container(&[(
            "weights",
            Dtype::F32,
            vec![3],
            floats(&[0.5, f32::NAN, f32::INFINITY]),
        )]);
        let f16 = container(&[("half", Dtype::F16, vec![2], vec![0; 4])]);
        let (_dir, map) = map_with(&[
            ("good.safetensors", good.clone()),
            ("nan.safetensors", nan),
            ("cut.safetensors", good[..good.len() / 2].to_vec()),
            ("f16.safetensors", f16),
            ("half.json", b"{\"dims\": [1, ".to_vec()),
        ]);
        let found = messages(&content_problems(&map));
        assert_eq!(found.len(), 4, "{found:#?}");
        let has = |file: &str, parts: &[&str]| {
            found
                .iter()
                .any(|m| m.contains(file) && parts.iter().all(|p| m.contains(p)))
        };
        assert!(
            has(
                "nan.safetensors",
                &["tensor `weights`", "2 of 3 values not finite", "NaN"]
            ),
            "{found:#?}"
        );
        assert!(has("cut.safetensors", &["header"]), "{found:#?}");
        assert!(
            has("f16.safetensors", &["tensor `half`", "F16"]),
            "{found:#?}"
        );
        assert!(has("half.json", &["JSON", "EOF"]), "{found:#?}");
    }

    #[test]
    fn a_selection_names_distinct_dims_below_the_feature_dimension_as_the_manifest_records() {
        let record = |dims: &[usize]| {
            serde_json::to_vec(&SelectionRecord {
                dims: dims.to_vec(),
                selector: "test".into(),
                objective: 0.0,
                pairs: 0,
            })
            .unwrap()
        };
        let (_dir, map) = map_with(&[(&selection_file(0), record(&[1, 2]))]);
        assert!(content_problems(&map).is_empty());
        for (dims, want) in [
            (
                vec![1_000_000, 2],
                "dim 1000000 is not below the feature dimension 47",
            ),
            (vec![1, 1], "a dim is listed twice"),
            (vec![], "no dim selected"),
            (vec![2, 3], "the manifest records [1, 2] for block 0"),
        ] {
            let (_dir, map) = map_with(&[(&selection_file(0), record(&dims))]);
            let found = messages(&content_problems(&map));
            assert!(
                found
                    .iter()
                    .any(|m| m.contains("selection.json: dims:") && m.contains(want)),
                "{dims:?}: {found:#?}"
            );
        }
    }
}
