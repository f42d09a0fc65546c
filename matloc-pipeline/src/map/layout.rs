//! Where each stage's files live inside a map directory, and the records stored there.

use serde::{Deserialize, Serialize};

use crate::config::CalibrationQueries;
use crate::localizer::confidence::{ConfidenceModel, Evidence};

/// Name of the partition file inside the map.
pub const PARTITION_FILE: &str = "partition.json";

/// Which surface the partition used (`matloc_surface::SurfacePlan` and point counts).
pub const SURFACE_FILE: &str = "surface.json";

/// The sparse points the partition's surface came from, when it came from points (PLY).
pub const SURFACE_POINTS_FILE: &str = "surface_points.ply";

/// The shadow-lifting record: sun, gain and the lifted training images
/// ([`crate::build::sunlight`]).
pub const SUNLIGHT_FILE: &str = "sunlight.json";

/// A lifted training image of the map (by its frame index in the working dataset).
pub fn sunlight_image(frame: usize) -> String {
    format!("sunlight/frame_{frame:05}.png")
}

/// The keypoint structure of the training images (`matloc_structure::StructureMap`).
pub const STRUCTURE_FILE: &str = "structure.safetensors";

/// Name of the job plan inside the map (`matloc map plan`).
pub const PLAN_FILE: &str = "plan.json";

/// Value of [`PlanRecord::format`].
pub const PLAN_FORMAT: &str = "matloc-plan";

/// The job list of a planned map: which blocks to build and the commands that build them and
/// then finish the map. Written once by the plan step, read by the block and finish jobs and
/// the scheduler scripts.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlanRecord {
    /// Always [`PLAN_FORMAT`].
    pub format: String,
    /// Plan format version (1).
    pub version: u32,
    /// The dataset directory the map is built from (absolute when the plan step could
    /// resolve it); the block and finish jobs read it unless told another.
    pub data: String,
    /// Block ids, one job each.
    pub blocks: Vec<usize>,
    /// Per block (same order as `blocks`), the command line of its job.
    pub block_commands: Vec<Vec<String>>,
    /// The command line of the finish job, to run once every block job has succeeded.
    pub finish_command: Vec<String>,
}

/// Directory of block `b` inside the map.
pub fn block_dir(b: usize) -> String {
    format!("blocks/{b}")
}

/// Name of a block's record inside its directory: the stages its job completed and the files
/// they wrote (`MapDir::open_block`).
pub const BLOCK_RECORD_FILE: &str = "block.json";

/// File of block `b`'s record.
pub fn block_record_file(b: usize) -> String {
    format!("{}/{BLOCK_RECORD_FILE}", block_dir(b))
}

/// Stages of one block, in build order.
pub fn block_stages(b: usize) -> [String; 4] {
    ["nerf", "pairs", "encoder", "select"].map(|s| format!("{s}/{b}"))
}

/// Name of the place model directory inside the map.
pub const PLACE_DIR: &str = "place";

/// Name of the calibration record inside the map.
pub const CONFIDENCE_FILE: &str = "confidence.json";

/// File of block `b`'s ground-truth pairs.
pub fn pairs_file(b: usize) -> String {
    format!("{}/pairs.safetensors", block_dir(b))
}

/// File of block `b`'s query encoder.
pub fn encoder_file(b: usize) -> String {
    format!("{}/encoder.safetensors", block_dir(b))
}

/// File of block `b`'s selection record.
pub fn selection_file(b: usize) -> String {
    format!("{}/selection.json", block_dir(b))
}

/// Block `b`'s selection and how it was obtained.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SelectionRecord {
    /// Selected field dims.
    pub dims: Vec<usize>,
    /// Selector name.
    pub selector: String,
    /// Its objective value.
    pub objective: f64,
    /// GT pairs it was selected on (held-out views for a selection on renders).
    pub pairs: usize,
}

/// What calibration saw, stored next to the fitted model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibrationRecord {
    /// The fitted model.
    pub model: ConfidenceModel,
    /// Samples: evidence, label, translation and rotation error of the attempt (∞ = no pose).
    pub samples: Vec<(Evidence, bool, f64, f64)>,
    /// Fraction of samples the fitted rule classifies correctly.
    pub accuracy: f64,
    /// Per sample: rotation between its pose and its hypothesis' coarse pose, degrees (1e9 =
    /// no pose). Empty in maps calibrated before it was recorded.
    #[serde(default)]
    pub corrections_deg: Vec<f64>,
    /// Calibrated bound on an accepted pose's rotation from its coarse pose (see
    /// [`CalibrationConfig::rotation_bound_margin`]); `None`: the configured one applies.
    #[serde(default)]
    pub max_accept_rotation_deg: Option<f64>,
    /// What was localized to fit the model (maps calibrated before this was recorded used
    /// the held-out views).
    #[serde(default = "held_out")]
    pub queries: CalibrationQueries,
}

fn held_out() -> CalibrationQueries {
    CalibrationQueries::HeldOut
}

/// Stages a complete map has.
pub fn required_stages(blocks: usize) -> Vec<String> {
    let mut v = vec!["partition".to_string()];
    for b in 0..blocks {
        v.extend(block_stages(b));
    }
    v.push("place".into());
    v.push("calibration".into());
    v
}

/// Files a completed stage must list in the manifest (empty for an unknown stage).
pub fn stage_files(stage: &str) -> Vec<String> {
    let block = |b: &str| b.parse::<usize>().ok();
    match stage.split_once('/') {
        None => match stage {
            "partition" => vec![PARTITION_FILE.to_string()],
            "place" => [matloc_place::MODEL_JSON, matloc_place::MODEL_WEIGHTS]
                .iter()
                .map(|f| format!("{PLACE_DIR}/{f}"))
                .collect(),
            "calibration" => vec![CONFIDENCE_FILE.to_string()],
            "structure" => vec![STRUCTURE_FILE.to_string()],
            "sunlight" => vec![SUNLIGHT_FILE.to_string()],
            _ => Vec::new(),
        },
        Some((kind, b)) => match (kind, block(b)) {
            ("nerf", Some(b)) => [matloc_render::CONFIG_FILE, matloc_render::WEIGHTS_FILE]
                .iter()
                .map(|f| format!("{}/{f}", block_dir(b)))
                .collect(),
            ("pairs", Some(b)) => vec![pairs_file(b)],
            ("encoder", Some(b)) => vec![encoder_file(b)],
            ("select", Some(b)) => vec![selection_file(b)],
            _ => Vec::new(),
        },
    }
}
