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
//!
//! A map opened for one block ([`MapDir::open_block`], the `matloc map block` job) never writes
//! the manifest: its stages and files are recorded in the block's own record
//! `blocks/B/block.json` ([`BlockRecord`]) and it may write only under `blocks/B/`, so jobs of
//! different blocks can run at the same time. [`MapDir::merge_block`] (the `finish` step)
//! checks a block's record against the files and merges it into the manifest.

use std::collections::BTreeMap;
use std::fs;
use std::io::{self, Read};
use std::path::{Component, Path, PathBuf};

use matloc_core::fsutil::write_atomic;
use matloc_data::split::SplitSpec;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::map::layout::{block_record_file, block_stages, required_stages, stage_files};

/// The manifest format version this build writes. Bump it on any change of the manifest or of
/// a stage's files. Version 2 adds per-block records (`blocks/B/block.json`) and the job plan
/// (`plan.json`); the stage files are those of version 1.
pub const MANIFEST_VERSION: u32 = 2;

/// The oldest manifest version this build reads: version 1 maps have the same stage files and
/// no per-block records, so they load and resume unchanged.
pub const MANIFEST_MIN_VERSION: u32 = 1;

/// Value of [`BlockRecord::format`].
pub const BLOCK_RECORD_FORMAT: &str = "matloc-block";

/// The block record format version this build reads and writes.
pub const BLOCK_RECORD_VERSION: u32 = 1;

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
    #[error(
        "{path}: map format version {found}, this build reads versions {MANIFEST_MIN_VERSION} to \
         {supported}"
    )]
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
    /// A block id the map's partition does not have.
    #[error("block {block}: the map has {blocks} blocks (0 to {last})", last = blocks.saturating_sub(1))]
    NoSuchBlock {
        /// The requested block.
        block: usize,
        /// Blocks of the map.
        blocks: usize,
    },
    /// A block job tried to write outside its block's directory.
    #[error("{name}: the job of block {block} writes only under blocks/{block}/")]
    OutsideBlock {
        /// The file.
        name: String,
        /// The block the map was opened for.
        block: usize,
    },
    /// A block record (`blocks/B/block.json`) that does not parse or names another block.
    #[error("{path}: malformed block record: {message}")]
    BadBlockRecord {
        /// The record file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Finishing a map while some blocks have not completed.
    #[error(
        "{} of {total} blocks not built: {}; run `matloc map block MAP --block B` for each",
        blocks.len(),
        blocks.iter().map(|b| b.to_string()).collect::<Vec<_>>().join(", ")
    )]
    BlocksMissing {
        /// The blocks without a complete record.
        blocks: Vec<usize>,
        /// Blocks of the map.
        total: usize,
    },
    /// A listed file (checksum intact) whose content is not what its stage writes or what
    /// localization loads ([`crate::map::check::content_problems`]).
    #[error("{path}: {field}: {message}")]
    Content {
        /// The file.
        path: PathBuf,
        /// The part of it: a tensor, a JSON field, the header.
        field: String,
        /// What is wrong, with the bound.
        message: String,
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
    /// The place stage's virtual viewpoints, when the map config's `virtual` is on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub virtual_views: Option<VirtualViewsRecord>,
}

/// What the place stage made of the virtual viewpoints (`matloc_surface::viewpoints`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VirtualViewsRecord {
    /// Views rendered and added to the place classifier's training set.
    pub views: usize,
    /// Candidate poses drawn over all blocks.
    pub candidates: usize,
    /// Candidates dropped, by the first rule each failed.
    pub rejected: matloc_surface::viewpoints::Rejections,
    /// Accepted poses left out because no pose group's views saw any of their footprint.
    pub unlabelled: usize,
    /// Views per block.
    pub per_block: Vec<usize>,
    /// Views labelled with each pose group (indexed by group id).
    pub per_group: Vec<usize>,
    /// The survey's median camera height above the ground it saw, metres.
    pub survey_height_m: f64,
    /// Edge of the height field's cells, metres.
    pub cell_m: f64,
    /// Wall-clock seconds: the training views' surface, sampling, labelling and rendering.
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

/// What one block's job has done: its completed stages and the files they wrote, with
/// checksums. Written only by that job (`blocks/B/block.json`), merged into the manifest by
/// [`MapDir::merge_block`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BlockRecord {
    /// Always [`BLOCK_RECORD_FORMAT`].
    pub format: String,
    /// [`BLOCK_RECORD_VERSION`] when written by this build.
    pub version: u32,
    /// The block.
    pub block: usize,
    /// Completed stages of the block, in order.
    #[serde(default)]
    pub stages: Vec<StageRecord>,
    /// Files the stages wrote (relative to the map root) → size and checksum.
    #[serde(default)]
    pub files: BTreeMap<String, FileEntry>,
    /// Feature dims the selection stage chose.
    #[serde(default)]
    pub selected_dims: Vec<usize>,
}

impl BlockRecord {
    fn new(block: usize) -> Self {
        Self {
            format: BLOCK_RECORD_FORMAT.to_string(),
            version: BLOCK_RECORD_VERSION,
            block,
            stages: Vec::new(),
            files: BTreeMap::new(),
            selected_dims: Vec::new(),
        }
    }
}

/// An open map directory: the whole map, or one block of it ([`MapDir::open_block`]).
#[derive(Clone, Debug)]
pub struct MapDir {
    root: PathBuf,
    manifest: Manifest,
    /// The block this map was opened for, with its record.
    block: Option<BlockRecord>,
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
            let mut dir = dir;
            // Written from here on in this build's format (version 1 files are unchanged).
            dir.manifest.version = MANIFEST_VERSION;
            return Ok(dir);
        }
        fs::create_dir_all(root).map_err(io_err(root))?;
        let dir = Self {
            root: root.to_path_buf(),
            manifest: Manifest::new(config),
            block: None,
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
        if !(u64::from(MANIFEST_MIN_VERSION)..=u64::from(MANIFEST_VERSION)).contains(&found) {
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
            block: None,
        })
    }

    /// Opens a map for the job of block `b` ([`MapDir::open`] plus the block's record, empty
    /// when the job has not run before). Stages and files are then recorded in the block's
    /// record, never in the manifest, and files may be written only under `blocks/B/`.
    pub fn open_block(root: &Path, b: usize) -> Result<Self, MapError> {
        let mut dir = Self::open(root)?;
        let blocks = dir.manifest.blocks.len();
        if b >= blocks {
            return Err(MapError::NoSuchBlock { block: b, blocks });
        }
        dir.block = Some(
            dir.read_block_record(b)?
                .unwrap_or_else(|| BlockRecord::new(b)),
        );
        Ok(dir)
    }

    /// The block this map was opened for ([`MapDir::open_block`]).
    pub fn block(&self) -> Option<usize> {
        self.block.as_ref().map(|r| r.block)
    }

    /// Block `b`'s record as its job left it; `None` when the job has not saved one.
    pub fn read_block_record(&self, b: usize) -> Result<Option<BlockRecord>, MapError> {
        let path = self.root.join(block_record_file(b));
        let text = match fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(MapError::Io { path, source: e }),
        };
        let bad = |message: String| MapError::BadBlockRecord {
            path: path.clone(),
            message,
        };
        let record: BlockRecord = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
        if record.format != BLOCK_RECORD_FORMAT {
            return Err(bad(format!("\"format\" is not \"{BLOCK_RECORD_FORMAT}\"")));
        }
        if record.version != BLOCK_RECORD_VERSION {
            return Err(bad(format!(
                "`version` {}, this build reads {BLOCK_RECORD_VERSION}",
                record.version
            )));
        }
        if record.block != b {
            return Err(bad(format!("`block` is {}, expected {b}", record.block)));
        }
        let prefix = format!("blocks/{b}/");
        for name in record.files.keys() {
            checked_name(name)?;
            if !name.starts_with(&prefix) {
                return Err(bad(format!("`files`: {name} is outside {prefix}")));
            }
        }
        Ok(Some(record))
    }

    /// Whether every stage of block `b` has completed: in the manifest, or in the block's
    /// record (checked against its files by [`MapDir::merge_block`]).
    pub fn block_done(&self, b: usize) -> Result<bool, MapError> {
        if block_stages(b).iter().all(|s| self.stage_done(s)) {
            return Ok(true);
        }
        Ok(self.read_block_record(b)?.is_some_and(|r| {
            block_stages(b)
                .iter()
                .all(|s| r.stages.iter().any(|x| x.name == *s))
        }))
    }

    /// Merges block `b`'s record into the manifest (in memory; persisted by the next
    /// [`MapDir::save`]): its stages, its files after checking each one's size and checksum,
    /// and its selected dims. Returns false, changing nothing, when the block has not
    /// completed; true when it has (or the manifest records it already).
    pub fn merge_block(&mut self, b: usize) -> Result<bool, MapError> {
        if block_stages(b).iter().all(|s| self.stage_done(s)) {
            return Ok(true);
        }
        let Some(record) = self.read_block_record(b)? else {
            return Ok(false);
        };
        let stages = block_stages(b);
        if !stages
            .iter()
            .all(|s| record.stages.iter().any(|x| x.name == *s))
        {
            return Ok(false);
        }
        for (name, entry) in &record.files {
            let path = self.path_of(name)?;
            let bytes = fs::read(&path).map_err(file_err(&path))?;
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
        }
        self.manifest.files.extend(record.files);
        for s in &stages {
            if let Some(r) = record.stages.iter().find(|x| x.name == *s) {
                self.manifest.stages.retain(|x| x.name != *s);
                self.manifest.stages.push(r.clone());
            }
        }
        if let Some(e) = self.manifest.blocks.get_mut(b) {
            e.selected_dims = record.selected_dims;
        }
        Ok(true)
    }

    /// Records the feature dims selected for block `b` (in the manifest, or in the block's
    /// record for a block job); persisted by the next [`MapDir::save`].
    pub fn set_selected_dims(&mut self, b: usize, dims: Vec<usize>) {
        match &mut self.block {
            Some(r) if r.block == b => r.selected_dims = dims,
            _ => {
                if let Some(e) = self.manifest.blocks.get_mut(b) {
                    e.selected_dims = dims;
                }
            }
        }
    }

    /// Where the training curve of `stage` goes: `curves/<stage>.jsonl`, or under the block's
    /// directory for a block job (`/` in the stage name becomes `_`).
    pub fn curve_name(&self, stage: &str) -> String {
        let file = format!("{}.jsonl", stage.replace('/', "_"));
        match self.block() {
            Some(b) => format!("blocks/{b}/curves/{file}"),
            None => format!("curves/{file}"),
        }
    }

    /// Checks that a block job may write `name`.
    fn check_writable(&self, name: &str) -> Result<(), MapError> {
        match self.block() {
            Some(b) if !name.starts_with(&format!("blocks/{b}/")) => Err(MapError::OutsideBlock {
                name: name.to_string(),
                block: b,
            }),
            _ => Ok(()),
        }
    }

    /// The file table written entries go to: the block record's for a block job, else the
    /// manifest's.
    fn files_mut(&mut self) -> &mut BTreeMap<String, FileEntry> {
        match &mut self.block {
            Some(r) => &mut r.files,
            None => &mut self.manifest.files,
        }
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
        self.check_writable(name)?;
        if let Some(parent) = path.parent() {
            fs::create_dir_all(parent).map_err(io_err(parent))?;
        }
        write_atomic(&path, bytes).map_err(io_err(&path))?;
        self.files_mut().insert(
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
        self.check_writable(name)?;
        let bytes = fs::read(&path).map_err(file_err(&path))?;
        self.files_mut().insert(
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
            .block
            .as_ref()
            .and_then(|r| r.files.get(name))
            .or_else(|| self.manifest.files.get(name))
            .ok_or_else(|| MapError::NotListed {
                name: name.to_string(),
            })?;
        // The file's real size bounds the read (never the manifest's claim), and a size that
        // differs from the record is reported before anything is read.
        let mut file = fs::File::open(&path).map_err(file_err(&path))?;
        let actual = file.metadata().map_err(file_err(&path))?.len();
        if actual != entry.bytes {
            return Err(MapError::SizeMismatch {
                path,
                expected: entry.bytes,
                actual,
            });
        }
        let mut bytes = Vec::with_capacity(usize::try_from(actual).unwrap_or(0));
        file.read_to_end(&mut bytes).map_err(file_err(&path))?;
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
            || self
                .block
                .as_ref()
                .is_some_and(|r| r.stages.iter().any(|s| s.name == name))
    }

    /// Records a completed stage and persists the manifest; a build killed after this call
    /// resumes after the stage.
    pub fn complete_stage(&mut self, name: &str, seconds: f64) -> Result<(), MapError> {
        self.complete_stage_record(StageRecord {
            name: name.to_string(),
            seconds,
            virtual_views: None,
        })
    }

    /// [`MapDir::complete_stage`] with the whole record (a stage's counts beside its time).
    pub fn complete_stage_record(&mut self, record: StageRecord) -> Result<(), MapError> {
        let stages = match &mut self.block {
            Some(r) => &mut r.stages,
            None => &mut self.manifest.stages,
        };
        stages.retain(|s| s.name != record.name);
        stages.push(record);
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

    /// Writes the manifest atomically (a block job: the block's record).
    pub fn save(&self) -> Result<(), MapError> {
        if let Some(r) = &self.block {
            let path = self.root.join(block_record_file(r.block));
            if let Some(parent) = path.parent() {
                fs::create_dir_all(parent).map_err(io_err(parent))?;
            }
            let text = serde_json::to_vec_pretty(r).map_err(|e| MapError::BadBlockRecord {
                path: path.clone(),
                message: e.to_string(),
            })?;
            return write_atomic(&path, &text).map_err(io_err(&path));
        }
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

    /// A map with `blocks` blocks and its partition stage done, as the plan step leaves it.
    fn planned(dir: &Path, blocks: usize) -> MapDir {
        let mut map = MapDir::create_or_resume(dir, serde_json::json!({})).unwrap();
        map.manifest_mut().blocks = (0..blocks)
            .map(|id| BlockEntry {
                id,
                bounds_min: [0.0; 3],
                bounds_max: [1.0; 3],
                num_poses: 1,
                selected_dims: Vec::new(),
            })
            .collect();
        map.write_file("partition.json", b"{}").unwrap();
        map.complete_stage("partition", 0.0).unwrap();
        map
    }

    #[test]
    fn block_jobs_record_in_their_block_and_finish_merges() {
        let dir = tempfile::tempdir().unwrap();
        let mut map = planned(dir.path(), 2);
        let manifest_before = fs::read(dir.path().join(MANIFEST_FILE)).unwrap();

        // Block 1's job: its files and stages go to its record, never to the manifest.
        let mut job = MapDir::open_block(dir.path(), 1).unwrap();
        assert_eq!(job.block(), Some(1));
        job.write_file("blocks/1/model.safetensors", b"w").unwrap();
        job.complete_stage("nerf/1", 1.0).unwrap();
        let e = job.write_file("blocks/0/x", b"x").unwrap_err();
        assert!(matches!(e, MapError::OutsideBlock { block: 1, .. }), "{e}");
        assert!(job.write_file("confidence.json", b"x").is_err());
        assert_eq!(job.curve_name("nerf/1"), "blocks/1/curves/nerf_1.jsonl");
        assert_eq!(
            fs::read(dir.path().join(MANIFEST_FILE)).unwrap(),
            manifest_before
        );
        // A killed job rerun resumes from its record.
        let mut job = MapDir::open_block(dir.path(), 1).unwrap();
        assert!(job.stage_done("nerf/1"));
        assert_eq!(job.read_file("blocks/1/model.safetensors").unwrap(), b"w");
        assert!(!map.block_done(1).unwrap());
        assert!(!map.merge_block(1).unwrap(), "an unfinished block merged");
        for s in ["pairs/1", "encoder/1", "select/1"] {
            job.complete_stage(s, 0.5).unwrap();
        }
        job.set_selected_dims(1, vec![3, 4]);
        job.save().unwrap();
        assert!(map.block_done(1).unwrap());
        assert!(!map.block_done(0).unwrap());
        assert!(matches!(
            MapDir::open_block(dir.path(), 2),
            Err(MapError::NoSuchBlock {
                block: 2,
                blocks: 2
            })
        ));

        // Finish: the record merges; a file changed after its job fails the merge.
        assert!(map.merge_block(1).unwrap());
        assert!(map.stage_done("select/1"));
        assert_eq!(map.manifest().blocks[1].selected_dims, vec![3, 4]);
        assert!(
            map.manifest()
                .files
                .contains_key("blocks/1/model.safetensors")
        );
        fs::write(dir.path().join("blocks/1/model.safetensors"), b"v").unwrap();
        let mut fresh = MapDir::open(dir.path()).unwrap();
        assert!(matches!(
            fresh.merge_block(1),
            Err(MapError::Checksum { .. })
        ));
    }

    #[test]
    fn a_malformed_block_record_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let map = planned(dir.path(), 2);
        fs::create_dir_all(dir.path().join("blocks/0")).unwrap();
        let path = dir.path().join(block_record_file(0));
        for (text, expect) in [
            ("[", "malformed block record"),
            (
                r#"{"format":"matloc-block","version":1,"block":1}"#,
                "`block` is 1, expected 0",
            ),
            (
                r#"{"format":"matloc-block","version":9,"block":0}"#,
                "`version` 9",
            ),
            (
                r#"{"format":"matloc-block","version":1,"block":0,
                    "files":{"blocks/1/x":{"bytes":1,"sha256":"0"}}}"#,
                "outside blocks/0/",
            ),
        ] {
            fs::write(&path, text).unwrap();
            let e = map.read_block_record(0).unwrap_err().to_string();
            assert!(e.contains(expect) && e.contains("block.json"), "{e}");
        }
    }

    #[test]
    fn version_1_maps_load_and_other_versions_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let mut v = serde_json::to_value(Manifest::new(serde_json::json!({}))).unwrap();
        v["version"] = serde_json::json!(1);
        fs::write(dir.path().join(MANIFEST_FILE), v.to_string()).unwrap();
        assert_eq!(MapDir::open(dir.path()).unwrap().manifest().version, 1);
        // Resumed, it is written in this build's version.
        let map = MapDir::create_or_resume(dir.path(), serde_json::json!({})).unwrap();
        map.save().unwrap();
        assert_eq!(
            MapDir::open(dir.path()).unwrap().manifest().version,
            MANIFEST_VERSION
        );
        v["version"] = serde_json::json!(0);
        fs::write(dir.path().join(MANIFEST_FILE), v.to_string()).unwrap();
        let e = MapDir::open(dir.path()).unwrap_err().to_string();
        assert!(
            e.contains("map format version 0, this build reads versions 1 to 2"),
            "{e}"
        );
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
