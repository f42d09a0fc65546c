//! Command-line names of the pose output formats and worlds
//! ([`matloc_pipeline::query::poses`]).

use clap::ValueEnum;
use matloc_pipeline::query::{PoseFormat, WorldKind};

/// A pose output format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum FormatArg {
    /// One JSON object per query: pose (`qvec_wxyz`, `tvec`), confidence, times, errors.
    Jsonl,
    /// COLMAP text model directory (cameras, images, empty points3D), or `images.txt` alone
    /// on stdout or to a `.txt` file.
    Colmap,
    /// hloc / visuallocalization.net results: `NAME QW QX QY QZ TX TY TZ` (cam_from_world).
    Hloc,
    /// TUM trajectory for evo: `timestamp tx ty tz qx qy qz qw` (camera-to-world).
    Tum,
    /// nerfstudio `transforms.json` of the localized frames.
    Nerfstudio,
}

impl From<FormatArg> for PoseFormat {
    fn from(f: FormatArg) -> Self {
        match f {
            FormatArg::Jsonl => PoseFormat::Jsonl,
            FormatArg::Colmap => PoseFormat::Colmap,
            FormatArg::Hloc => PoseFormat::Hloc,
            FormatArg::Tum => PoseFormat::Tum,
            FormatArg::Nerfstudio => PoseFormat::Nerfstudio,
        }
    }
}

/// Which world written poses are in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ValueEnum)]
pub enum WorldArg {
    /// The world of the data the map was built from (and of `--data`).
    #[default]
    Data,
    /// The original (COLMAP) world before nerfstudio's `applied_transform`.
    Original,
}

impl From<WorldArg> for WorldKind {
    fn from(w: WorldArg) -> Self {
        match w {
            WorldArg::Data => WorldKind::Data,
            WorldArg::Original => WorldKind::Original,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every library format has a command-line name, and it is the library's.
    #[test]
    fn command_line_names_are_the_library_names() {
        for f in FormatArg::value_variants() {
            let name = f.to_possible_value().unwrap().get_name().to_string();
            assert_eq!(PoseFormat::from(*f).name(), name);
        }
        assert_eq!(FormatArg::value_variants().len(), PoseFormat::ALL.len());
        for w in WorldArg::value_variants() {
            let name = w.to_possible_value().unwrap().get_name().to_string();
            assert_eq!(WorldKind::from(*w).name(), name);
        }
    }
}
