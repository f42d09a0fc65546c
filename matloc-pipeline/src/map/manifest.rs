//! The map directory: a versioned JSON manifest plus the files it lists.
//!
//! ```text
//! MAP/
//!   manifest.json          format, version, config, scene frame, blocks, stages, files + SHA-256
//!   blocks/0/model.safetensors, blocks/0/model.json, ...   (written by the stages)
//! ```
//!
//! Every file goes through [`MapDir::write_file`], which writes atomically (temporary file in
//! the same directory, fsync, rename) and records size and checksum; the manifest is rewritten
//! atomically after each stage ([`MapDir::complete_stage`]), so a killed build leaves the last
//! completed stage intact and a rebuild resumes from it. Loading checks the format, the version,
//! that every listed file exists with its recorded size, and (on read) its checksum.

use std::collections::BTreeMap;
use std::fs;
use std::io::{self, Read};
use std::path::{Component, Path, PathBuf};

use matloc_core::fsutil::write_atomic;
use matloc_data::split::SplitSpec;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::map::layout::{required_stages, stage_files};

/// The manifest format version this build reads and writes. Bump it on any incompatible
/// change of the manifest or of a stage's files.
pub const MANIFEST_VERSION: u32 = 1;

/// File name of the manifest inside a map directory.
pub const MANIFEST_FILE: &str = "manifest.json";

/// Value of [`Manifest::format`]: tells a map manifest from any other JSON file.
pub const MANIFEST_FORMAT: &str = "matloc-map";

/// Errors from reading or writing a map directory.
#[derive(Debug, thiserror::Error)]
pub enum MapError {
    /// An I/O error on a file of the map.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: io::Error,
    },
    /// The directory has no manifest.
    #[error("{path} is not a matloc map (no {MANIFEST_FILE})")]
    NotAMap {
        /// The directory.
        path: PathBuf,
    },
    /// The manifest does not parse or is not a map manifest.
    #[error("{path}: malformed manifest: {message}")]
    Malformed {
        /// The manifest file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The manifest was written by an incompatible version.
    #[error("{path}: map format version {found}, this build reads version {supported}")]
    Version {
        /// The manifest file.
        path: PathBuf,
        /// Version in the file.
        found: u32,
        /// Version this build supports.
        supported: u32,
    },
    /// A file listed in the manifest is missing.
    #[error("{path}: listed in the map manifest but missing")]
    MissingFile {
        /// The missing file.
        path: PathBuf,
    },
    /// A file has another size than the manifest records (truncated or replaced).
    #[error("{path}: {actual} bytes, the manifest records {expected} (truncated or modified)")]
    SizeMismatch {
        /// The file.
        path: PathBuf,
        /// Size in the manifest.
        expected: u64,
        /// Size on disk.
        actual: u64,
    },
    /// A file's content does not match its recorded checksum.
    #[error("{path}: checksum mismatch (file modified or corrupted)")]
    Checksum {
        /// The file.
        path: PathBuf,
    },
    /// A file name that would leave the map directory or is not a plain relative path.
    #[error("{name:?}: map file names must be relative paths inside the map")]
    UnsafePath {
        /// The offending name.
        name: String,
    },
    /// A file was requested that the manifest does not list.
    #[error("{name}: not listed in the map manifest")]
    NotListed {
        /// The requested name.
        name: String,
    },
    /// Building with another split rule than the map records (or with one, when the map's
    /// completed stages were built without).
    #[error(
        "{path}: the map was built with split {recorded}, not {requested}; use a new output \
         directory or the same split"
    )]
    SplitMismatch {
        /// The manifest file.
        path: PathBuf,
        /// The recorded rule (JSON), or `none`.
        recorded: String,
        /// The requested rule (JSON), or `none`.
        requested: String,
    },
    /// A stage a complete map has did not complete.
    #[error("stage {stage} has not completed (the map is incomplete)")]
    StageMissing {
        /// The first such stage.
        stage: String,
    },
    /// A completed stage's file is not listed in the manifest.
    #[error("{name}: written by stage {stage} but not listed in the map manifest")]
    StageFileNotListed {
        /// The stage.
        stage: String,
        /// The file.
        name: String,
    },
    /// Resuming a build whose recorded config differs from the requested one.
    #[error(
        "{path}: the map was started with another config; use a new output directory or the same config"
    )]
    ConfigMismatch {
        /// The manifest file.
        path: PathBuf,
    },
}

/// Size and checksum of one file of the map.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileEntry {
    /// Size in bytes.
    pub bytes: u64,
    /// Lower-case hex SHA-256 of the content.
    pub sha256: String,
}

/// One sub-NeRF block of the map.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BlockEntry {
    /// Block id (index into the partition).
    pub id: usize,
    /// Axis-aligned world bounds of the block's sampling space, metres.
    pub bounds_min: [f64; 3],
    /// Upper corner of the bounds.
    pub bounds_max: [f64; 3],
    /// Training poses served by the block.
    pub num_poses: usize,
    /// Feature dims (of the 47) selected for matching in this block's region.
    #[serde(default)]
    pub selected_dims: Vec<usize>,
}

/// A completed build stage.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StageRecord {
    /// Stage name (e.g. `partition`, `nerf/3`, `encoder`).
    pub name: String,
    /// Wall-clock seconds the stage took.
    pub seconds: f64,
}

/// The manifest of a map directory.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Always [`MANIFEST_FORMAT`].
    pub format: String,
    /// Format version ([`MANIFEST_VERSION`] when written by this build).
    pub version: u32,
    /// Writer, e.g. `matloc-pipeline 0.1.0`.
    pub created_by: String,
    /// The build configuration, as given (opaque to the manifest).
    pub config: serde_json::Value,
    /// Free-form scene description: dataset path, bounds, frame conventions.
    #[serde(default)]
    pub scene: serde_json::Value,
    /// The test split rule the build applied to its dataset, if it applied one; evaluation
    /// applies the same rule ([`MapDir::record_split`]). Absent in maps built without one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub split: Option<SplitSpec>,
    /// Sub-NeRF blocks.
    #[serde(default)]
    pub blocks: Vec<BlockEntry>,
    /// Completed stages, in order.
    #[serde(default)]
    pub stages: Vec<StageRecord>,
    /// Every file of the map (relative path with `/` separators → entry).
    #[serde(default)]
    pub files: BTreeMap<String, FileEntry>,
}

impl Manifest {
    fn new(config: serde_json::Value) -> Self {
        Self {
            format: MANIFEST_FORMAT.to_string(),
            version: MANIFEST_VERSION,
            created_by: concat!("matloc-pipeline ", env!("CARGO_PKG_VERSION")).to_string(),
            config,
            scene: serde_json::Value::Null,
            split: None,
            blocks: Vec::new(),
            stages: Vec::new(),
            files: BTreeMap::new(),
        }
    }
}

/// An open map directory.
#[derive(Clone, Debug)]
pub struct MapDir {
    root: PathBuf,
    manifest: Manifest,
}

fn io_err(path: &Path) -> impl FnOnce(io::Error) -> MapError + '_ {
    move |source| MapError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Maps an I/O error on a listed file: "not found" becomes [`MapError::MissingFile`].
fn file_err(path: &Path) -> impl FnOnce(io::Error) -> MapError + '_ {
    move |e| {
        if e.kind() == io::ErrorKind::NotFound {
            MapError::MissingFile {
                path: path.to_path_buf(),
            }
        } else {
            MapError::Io {
                path: path.to_path_buf(),
                source: e,
            }
        }
    }
}

/// Lower-case hex SHA-256 of `bytes`.
pub fn sha256_hex(bytes: &[u8]) -> String {
    let digest = Sha256::digest(bytes);
    let mut s = String::with_capacity(64);
    for b in digest {
        s.push_str(&format!("{b:02x}"));
    }
    s
}

/// What a JSON value is, for messages ("a string", "an integer", ...).
fn json_kind(v: &serde_json::Value) -> &'static str {
    use serde_json::Value;
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(n) if n.is_u64() => "an integer",
        Value::Number(n) if n.is_i64() => "a negative integer",
        Value::Number(_) => "a fractional number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// Checks the manifest's top-level fields: each present with the JSON type its field has
/// (`split` may be null), the required ones present.
fn check_field_types(value: &serde_json::Value) -> Result<(), String> {
    use serde_json::Value;
    let Value::Object(fields) = value else {
        return Err(format!("expected an object, found {}", json_kind(value)));
    };
    let string = |v: &Value| v.is_string();
    let integer = |v: &Value| v.is_u64();
    let any = |_: &Value| true;
    let array = |v: &Value| v.is_array();
    let object = |v: &Value| v.is_object();
    let object_or_null = |v: &Value| v.is_object() || v.is_null();
    type Check<'a> = (&'a str, bool, &'a str, &'a dyn Fn(&Value) -> bool);
    let checks: [Check; 9] = [
        ("format", true, "a string", &string),
        ("version", true, "an integer", &integer),
        ("created_by", true, "a string", &string),
        ("config", true, "any value", &any),
        ("scene", false, "any value", &any),
        ("split", false, "an object or null", &object_or_null),
        ("blocks", false, "an array", &array),
        ("stages", false, "an array", &array),
        ("files", false, "an object", &object),
    ];
    for (name, required, expected, ok) in checks {
        match fields.get(name) {
            None if required => return Err(format!("missing `{name}`")),
            None => {}
            Some(v) if !ok(v) => {
                return Err(format!(
                    "`{name}`: expected {expected}, found {}",
                    json_kind(v)
                ));
            }
            Some(_) => {}
        }
    }
    Ok(())
}

/// Checks that `name` is a relative path of normal components (no `..`, no root).
fn checked_name(name: &str) -> Result<&str, MapError> {
    let path = Path::new(name);
    let ok = !name.is_empty()
        && !name.contains('\\')
        && path.components().all(|c| matches!(c, Component::Normal(_)))
        && name != MANIFEST_FILE;
    if ok {
        Ok(name)
    } else {
        Err(MapError::UnsafePath {
            name: name.to_string(),
        })
    }
}

impl MapDir {
    /// Starts a new map in `root`, or resumes the one there if it was started with the same
    /// `config` (then its completed stages are kept). A different config is an error, so a
    /// half-built map is never silently mixed with another build's files.
    pub fn create_or_resume(root: &Path, config: serde_json::Value) -> Result<Self, MapError> {
        let manifest_path = root.join(MANIFEST_FILE);
        if manifest_path.exists() {
            let dir = Self::open(root)?;
            if dir.manifest.config != config {
                return Err(MapError::ConfigMismatch {
                    path: manifest_path,
                });
            }
            return Ok(dir);
        }
        fs::create_dir_all(root).map_err(io_err(root))?;
        let dir = Self {
            root: root.to_path_buf(),
            manifest: Manifest::new(config),
        };
        dir.save()?;
        Ok(dir)
    }

    /// Opens an existing map: parses and checks the manifest, and checks that every listed file
    /// exists with its recorded size. Checksums are verified when files are read
    /// ([`MapDir::read_file`]) or all at once by [`MapDir::verify`].
    pub fn open(root: &Path) -> Result<Self, MapError> {
        let dir = Self::open_manifest(root)?;
        for (name, entry) in &dir.manifest.files {
            let p = dir.root.join(name);
            let meta = fs::metadata(&p).map_err(file_err(&p))?;
            if meta.len() != entry.bytes {
                return Err(MapError::SizeMismatch {
                    path: p,
                    expected: entry.bytes,
                    actual: meta.len(),
                });
            }
        }
        Ok(dir)
    }

    /// Parses and checks the manifest only; the files are checked by [`MapDir::problems`].
    pub fn open_manifest(root: &Path) -> Result<Self, MapError> {
        let path = root.join(MANIFEST_FILE);
        if !path.is_file() {
            return Err(MapError::NotAMap {
                path: root.to_path_buf(),
            });
        }
        let text = fs::read_to_string(&path).map_err(io_err(&path))?;
        let value: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| MapError::Malformed {
                path: path.clone(),
                message: e.to_string(),
            })?;
        if value.get("format").and_then(|f| f.as_str()) != Some(MANIFEST_FORMAT) {
            return Err(MapError::Malformed {
                path,
                message: format!("\"format\" is not \"{MANIFEST_FORMAT}\""),
            });
        }
        check_field_types(&value).map_err(|message| MapError::Malformed {
            path: path.clone(),
            message,
        })?;
        // Check the version before the schema, so an old or new map reports its version
        // instead of a field-level parse error.
        let found = value.get("version").and_then(|v| v.as_u64()).unwrap_or(0);
        if found != u64::from(MANIFEST_VERSION) {
            return Err(MapError::Version {
                path,
                found: u32::try_from(found).unwrap_or(u32::MAX),
                supported: MANIFEST_VERSION,
            });
        }
        let manifest: Manifest =
            serde_json::from_value(value).map_err(|e| MapError::Malformed {
                path: path.clone(),
                message: e.to_string(),
            })?;
        for name in manifest.files.keys() {
            checked_name(name)?;
        }
        Ok(Self {
            root: root.to_path_buf(),
            manifest,
        })
    }

    /// The map's root directory.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The manifest as loaded or built so far.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// Mutable access to the manifest's descriptive parts (scene, blocks); persisted by the
    /// next [`MapDir::save`] or [`MapDir::complete_stage`].
    pub fn manifest_mut(&mut self) -> &mut Manifest {
        &mut self.manifest
    }

    /// Absolute path of a map file.
    pub fn path_of(&self, name: &str) -> Result<PathBuf, MapError> {
        Ok(self.root.join(checked_name(name)?))
    }

    /// Writes a file of the map atomically and records its size and checksum (in memory until
    /// the next [`MapDir::save`]).
    pub fn write_file(&mut self, name: &str, bytes: &[u8]) -> Result<(), MapError> {
        let path = self.path_of(name)?;
        if let Some(parent) = path.parent() {
            fs::create_dir_all(parent).map_err(io_err(parent))?;
        }
        write_atomic(&path, bytes).map_err(io_err(&path))?;
        self.manifest.files.insert(
            name.to_string(),
            FileEntry {
                bytes: bytes.len() as u64,
                sha256: sha256_hex(bytes),
            },
        );
        Ok(())
    }

    /// Lists a file that another component already wrote (atomically) inside the map, with
    /// its size and checksum.
    pub fn register_file(&mut self, name: &str) -> Result<(), MapError> {
        let path = self.path_of(name)?;
        let bytes = fs::read(&path).map_err(file_err(&path))?;
        self.manifest.files.insert(
            name.to_string(),
            FileEntry {
                bytes: bytes.len() as u64,
                sha256: sha256_hex(&bytes),
            },
        );
        Ok(())
    }

    /// Serialises `value` as pretty JSON into a map file (see [`MapDir::write_file`]).
    pub fn write_json<T: Serialize>(&mut self, name: &str, value: &T) -> Result<(), MapError> {
        let text = serde_json::to_vec_pretty(value).map_err(|e| MapError::Malformed {
            path: self.root.join(name),
            message: e.to_string(),
        })?;
        self.write_file(name, &text)
    }

    /// Reads a listed file and verifies its checksum.
    pub fn read_file(&self, name: &str) -> Result<Vec<u8>, MapError> {
        let path = self.path_of(name)?;
        let entry = self
            .manifest
            .files
            .get(name)
            .ok_or_else(|| MapError::NotListed {
                name: name.to_string(),
            })?;
        let mut bytes = Vec::with_capacity(entry.bytes as usize);
        fs::File::open(&path)
            .and_then(|mut f| f.read_to_end(&mut bytes))
            .map_err(file_err(&path))?;
        if bytes.len() as u64 != entry.bytes {
            return Err(MapError::SizeMismatch {
                path,
                expected: entry.bytes,
                actual: bytes.len() as u64,
            });
        }
        if sha256_hex(&bytes) != entry.sha256 {
            return Err(MapError::Checksum { path });
        }
        Ok(bytes)
    }

    /// Reads and parses a listed JSON file (checksum verified).
    pub fn read_json<T: for<'de> Deserialize<'de>>(&self, name: &str) -> Result<T, MapError> {
        let bytes = self.read_file(name)?;
        serde_json::from_slice(&bytes).map_err(|e| MapError::Malformed {
            path: self.root.join(name),
            message: e.to_string(),
        })
    }

    /// Verifies every listed file's checksum.
    pub fn verify(&self) -> Result<(), MapError> {
        for name in self.manifest.files.keys() {
            self.read_file(name)?;
        }
        Ok(())
    }

    /// What keeps the map from being complete with `blocks` blocks: the first required stage
    /// not done, and each required file of a done stage the manifest does not list.
    pub fn completeness(&self, blocks: usize) -> Vec<MapError> {
        let stages = required_stages(blocks);
        let mut problems: Vec<MapError> = stages
            .iter()
            .find(|s| !self.stage_done(s))
            .map(|s| MapError::StageMissing { stage: s.clone() })
            .into_iter()
            .collect();
        for stage in stages.iter().filter(|s| self.stage_done(s)) {
            for name in stage_files(stage) {
                if !self.manifest.files.contains_key(&name) {
                    problems.push(MapError::StageFileNotListed {
                        stage: stage.clone(),
                        name,
                    });
                }
            }
        }
        problems
    }

    /// Every problem of the map: each listed file missing, resized or with another checksum,
    /// then [`MapDir::completeness`] for the manifest's blocks. Empty for a complete map.
    pub fn problems(&self) -> Vec<MapError> {
        let mut problems: Vec<MapError> = self
            .manifest
            .files
            .keys()
            .filter_map(|name| self.read_file(name).err())
            .collect();
        problems.extend(self.completeness(self.manifest.blocks.len()));
        problems
    }

    /// Whether a stage has completed (in this build or the one being resumed).
    pub fn stage_done(&self, name: &str) -> bool {
        self.manifest.stages.iter().any(|s| s.name == name)
    }

    /// Records a completed stage and persists the manifest; a build killed after this call
    /// resumes after the stage.
    pub fn complete_stage(&mut self, name: &str, seconds: f64) -> Result<(), MapError> {
        self.manifest.stages.retain(|s| s.name != name);
        self.manifest.stages.push(StageRecord {
            name: name.to_string(),
            seconds,
        });
        self.save()
    }

    /// Records the test split rule a build applies and saves the manifest. The map must record
    /// the same rule already, or none while no stage has completed (its stages would have been
    /// built on another split).
    pub fn record_split(&mut self, split: Option<&SplitSpec>) -> Result<(), MapError> {
        let recorded = self.manifest.split.as_ref();
        if recorded == split {
            return Ok(());
        }
        if recorded.is_some() || !self.manifest.stages.is_empty() {
            let show = |s: Option<&SplitSpec>| {
                s.map_or("none".to_string(), |s| {
                    serde_json::to_string(s).unwrap_or_default()
                })
            };
            return Err(MapError::SplitMismatch {
                path: self.root.join(MANIFEST_FILE),
                recorded: show(recorded),
                requested: show(split),
            });
        }
        self.manifest.split = split.cloned();
        self.save()
    }

    /// Writes the manifest atomically.
    pub fn save(&self) -> Result<(), MapError> {
        let path = self.root.join(MANIFEST_FILE);
        let text = serde_json::to_vec_pretty(&self.manifest).map_err(|e| MapError::Malformed {
            path: path.clone(),
            message: e.to_string(),
        })?;
        write_atomic(&path, &text).map_err(io_err(&path))
    }

    /// Total bytes of all listed files.
    pub fn total_bytes(&self) -> u64 {
        self.manifest.files.values().map(|f| f.bytes).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sha256_of_abc() {
        // FIPS 180-2 test vector.
        assert_eq!(
            sha256_hex(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }

    #[test]
    fn split_is_recorded_once_and_old_manifests_load() {
        use matloc_data::split::SplitRule;
        let dir = tempfile::tempdir().unwrap();
        let spec = SplitSpec {
            rule: SplitRule::Every(8),
            resplit: false,
        };
        let mut map = MapDir::create_or_resume(dir.path(), serde_json::json!({})).unwrap();
        map.record_split(Some(&spec)).unwrap();
        let mut map = MapDir::open(dir.path()).unwrap();
        assert_eq!(map.manifest().split, Some(spec.clone()));
        map.record_split(Some(&spec)).unwrap();
        let other = SplitSpec {
            rule: SplitRule::Every(4),
            resplit: false,
        };
        let e = map.record_split(Some(&other)).unwrap_err();
        assert!(matches!(e, MapError::SplitMismatch { .. }), "{e}");
        assert!(matches!(
            map.record_split(None),
            Err(MapError::SplitMismatch { .. })
        ));

        // A map with stages built without a rule cannot take one.
        let dir = tempfile::tempdir().unwrap();
        let mut map = MapDir::create_or_resume(dir.path(), serde_json::json!({})).unwrap();
        map.complete_stage("partition", 1.0).unwrap();
        assert!(map.record_split(Some(&spec)).is_err());
        map.record_split(None).unwrap();
        // Manifests without the field load, with no split; the field is not written then.
        let text = fs::read_to_string(dir.path().join(MANIFEST_FILE)).unwrap();
        assert!(!text.contains("\"split\""), "{text}");
        assert_eq!(MapDir::open(dir.path()).unwrap().manifest().split, None);
    }

    #[test]
    fn a_field_of_the_wrong_type_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let mut v = serde_json::to_value(Manifest::new(serde_json::json!({}))).unwrap();
        v["version"] = serde_json::json!("1");
        fs::write(dir.path().join(MANIFEST_FILE), v.to_string()).unwrap();
        let e = MapDir::open(dir.path()).unwrap_err().to_string();
        assert!(
            e.contains("`version`: expected an integer, found a string"),
            "{e}"
        );
        v["version"] = serde_json::json!(1);
        v["files"] = serde_json::json!([]);
        fs::write(dir.path().join(MANIFEST_FILE), v.to_string()).unwrap();
        let e = MapDir::open(dir.path()).unwrap_err().to_string();
        assert!(
            e.contains("`files`: expected an object, found an array"),
            "{e}"
        );
    }

    #[test]
    fn completed_stages_need_their_files() {
        let dir = tempfile::tempdir().unwrap();
        let mut map = MapDir::create_or_resume(dir.path(), serde_json::json!({})).unwrap();
        let problems = |map: &MapDir| -> Vec<String> {
            map.problems().iter().map(|p| p.to_string()).collect()
        };
        assert_eq!(
            problems(&map),
            ["stage partition has not completed (the map is incomplete)"]
        );
        for s in required_stages(0) {
            map.complete_stage(&s, 0.0).unwrap();
        }
        let p = problems(&map);
        assert_eq!(p.len(), 4, "{p:?}");
        assert!(p[0].starts_with("partition.json: written by stage partition"));
        for s in required_stages(0) {
            for f in stage_files(&s) {
                map.write_file(&f, b"x").unwrap();
            }
        }
        assert!(problems(&map).is_empty());
        fs::write(dir.path().join("confidence.json"), b"y").unwrap();
        let p = problems(&map);
        assert_eq!(p.len(), 1, "{p:?}");
        assert!(p[0].contains("checksum mismatch"), "{p:?}");
    }

    #[test]
    fn names_must_stay_inside_the_map() {
        for bad in [
            "",
            "../x",
            "/etc/passwd",
            "a/../../b",
            "a\\b",
            MANIFEST_FILE,
        ] {
            assert!(checked_name(bad).is_err(), "{bad}");
        }
        for good in ["a", "blocks/0/field.safetensors"] {
            assert!(checked_name(good).is_ok(), "{good}");
        }
    }
}
