//! `--method-options FILE`: the methods' settings (`MethodOptions`) as JSON, shared by
//! `localize` and `eval`. Keys left out keep their defaults, so `{"keypoints": {"passes": 1}}`
//! changes one setting; an unknown key or a wrong type is an error naming the file and field.

use std::path::{Path, PathBuf};

use anyhow::{Result, anyhow, bail};
use clap::Args;
use matloc_pipeline::methods::MethodOptions;

/// The flag.
#[derive(Args, Clone, Debug, Default)]
pub struct MethodOptionsArgs {
    /// Settings of the methods as JSON, e.g. `{"keypoints": {"passes": 1}}` (rgb-keypoints
    /// with the paper's single render), `{"structure": {"neighbours": 10}}` or `{"matloc":
    /// {"keypoint_finish": false}}` (MatLoc's NeRF-feature passes alone; sections `structure`,
    /// `matloc`, `keypoints`, `inerf`); keys left out keep their defaults.
    #[arg(long, value_name = "FILE")]
    pub method_options: Option<PathBuf>,
}

impl MethodOptionsArgs {
    /// The options the flag gives, or the defaults without it.
    pub fn load(&self) -> Result<MethodOptions> {
        self.method_options
            .as_deref()
            .map_or_else(|| Ok(MethodOptions::default()), read)
    }
}

/// Reads and checks a method options file.
pub fn read(path: &Path) -> Result<MethodOptions> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| anyhow!("method options {}: {e}", path.display()))?;
    // Overlaid on the defaults, so that a partial section keeps the defaults of its own
    // fields (`{"structure": {"gradient_matching": {"ratio": 0.8}}}` keeps the gradient
    // matcher's distance cap, not a binary matcher's).
    let over: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| anyhow!("method options {}: {e}", path.display()))?;
    let mut merged = serde_json::to_value(MethodOptions::default())?;
    matloc_pipeline::config::overlay_json(&mut merged, over);
    let options: MethodOptions = serde_path_to_error::deserialize(merged).map_err(|e| {
        anyhow!(
            "method options {}: field `{}`: {}",
            path.display(),
            e.path(),
            e.inner()
        )
    })?;
    if options.keypoints.passes == 0 {
        bail!(
            "method options {}: field `keypoints.passes`: must be at least 1",
            path.display()
        );
    }
    if options.matloc.top_k == Some(0) {
        bail!(
            "method options {}: field `matloc.top_k`: must be at least 1",
            path.display()
        );
    }
    Ok(options)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(name: &str, text: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("matloc_method_options_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn a_partial_section_keeps_its_own_defaults() {
        let p = write(
            "section.json",
            r#"{"structure": {"gradient_matching": {"ratio": 0.8}}}"#,
        );
        let o = read(&p).unwrap();
        let mut expected = MethodOptions::default();
        expected.structure.gradient_matching.ratio = 0.8;
        assert_eq!(o, expected);
        assert_ne!(
            o.structure.gradient_matching.max_distance,
            o.structure.matching.max_distance
        );
    }

    #[test]
    fn a_partial_file_keeps_the_other_defaults() {
        let p = write("partial.json", r#"{"keypoints": {"passes": 1}}"#);
        let o = read(&p).unwrap();
        assert_eq!(o.keypoints.passes, 1);
        assert_ne!(MethodOptions::default().keypoints.passes, 1);
        let mut expected = MethodOptions::default();
        expected.keypoints.passes = 1;
        assert_eq!(o, expected);
        assert_eq!(
            MethodOptionsArgs::default().load().unwrap(),
            MethodOptions::default()
        );
    }

    #[test]
    fn bad_files_name_the_file_and_field() {
        for (name, text, field) in [
            (
                "typo.json",
                r#"{"keypoints": {"pases": 2}}"#,
                "keypoints.pases",
            ),
            (
                "type.json",
                r#"{"keypoints": {"passes": "two"}}"#,
                "keypoints.passes",
            ),
            (
                "zero.json",
                r#"{"keypoints": {"passes": 0}}"#,
                "keypoints.passes",
            ),
            ("section.json", r#"{"structur": {}}"#, "structur"),
            ("top.json", r#"{"matloc": {"top_k": 0}}"#, "matloc.top_k"),
            (
                "finish.json",
                r#"{"matloc": {"keypoint_finsh": false}}"#,
                "matloc.keypoint_finsh",
            ),
        ] {
            let p = write(name, text);
            let e = format!("{:#}", read(&p).unwrap_err());
            assert!(e.contains(name) && e.contains(field), "{e}");
        }
        let e = format!(
            "{:#}",
            read(Path::new("/nonexistent/opts.json")).unwrap_err()
        );
        assert!(e.contains("/nonexistent/opts.json"), "{e}");
    }
}
