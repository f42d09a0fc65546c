//! A train/test split for data that has none (a COLMAP model, a capture exported without one).
//!
//! - [`SplitRule::Every`]`(n)`: frames sorted by image path, every n-th one from the first
//!   (index `i` with `i % n == 0`) is a test frame. This is nerfstudio's
//!   `--eval-mode interval --eval-interval n`, which sorts frames by file name first; for a
//!   COLMAP model the order is the same as the reader's (sorted by image name).
//! - [`SplitRule::List`]: the listed image paths (relative to the dataset root, as the frames
//!   name them; a bare suffix such as a file name is accepted when it names exactly one frame)
//!   are the test frames. An entry that names no frame is an error naming it.
//!
//! All other frames become train frames. A dataset that already has test or val frames keeps
//! its split: [`Dataset::apply_split`] refuses it, and only [`SplitSpec::resplit`] (the CLI's
//! `--resplit`) replaces it.

use std::collections::HashSet;
use std::io;
use std::path::{Component, Path, PathBuf};

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::dataset::{Dataset, Split};

/// How test frames are chosen.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SplitRule {
    /// Every n-th frame by image path (n ≥ 2), starting with the first.
    Every(usize),
    /// These image paths.
    List(Vec<PathBuf>),
}

/// A rule together with whether it may replace a split the dataset already has; what a map
/// manifest records.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SplitSpec {
    /// The rule.
    pub rule: SplitRule,
    /// Replace the dataset's own test/val frames instead of refusing.
    #[serde(default)]
    pub resplit: bool,
}

/// Errors raised when reading or applying a split rule.
#[derive(Debug, Error)]
pub enum SplitError {
    /// `Every(n)` with n < 2 (n = 1 would leave no training frame).
    #[error("test interval {n}: must be at least 2 (every n-th frame becomes a test frame)")]
    BadInterval {
        /// The interval.
        n: usize,
    },
    /// A list entry names no frame of the dataset.
    #[error("test list entry `{entry}` is not an image of the dataset")]
    UnknownEntry {
        /// The entry.
        entry: PathBuf,
    },
    /// A list entry matches several frames.
    #[error(
        "test list entry `{entry}` matches {count} images of the dataset; give more of its path"
    )]
    AmbiguousEntry {
        /// The entry.
        entry: PathBuf,
        /// How many frames it matches.
        count: usize,
    },
    /// The test list file cannot be read.
    #[error("reading test list {path}: {source}")]
    Io {
        /// The list file.
        path: PathBuf,
        /// The underlying error.
        source: io::Error,
    },
    /// The test list file lists nothing.
    #[error("test list {path} names no image")]
    EmptyList {
        /// The list file.
        path: PathBuf,
    },
    /// The dataset has its own split and no override was asked for.
    #[error(
        "the dataset already has {test} test and {val} val frames; pass --resplit to replace \
         its split with the rule"
    )]
    AlreadySplit {
        /// Test frames.
        test: usize,
        /// Val frames.
        val: usize,
    },
    /// The rule would leave no training frame.
    #[error("the split rule leaves no training frame ({frames} frames)")]
    NoTrainFrames {
        /// Frames in the dataset.
        frames: usize,
    },
}

/// A path with `.` components dropped and `/` separators, for comparing list entries.
fn normalized(p: &Path) -> PathBuf {
    p.components()
        .filter(|c| !matches!(c, Component::CurDir))
        .collect()
}

impl SplitRule {
    /// Reads a test list: one image path per line; blank lines and lines starting with `#`
    /// are skipped, surrounding whitespace is trimmed.
    pub fn read_list(path: &Path) -> Result<SplitRule, SplitError> {
        let text = std::fs::read_to_string(path).map_err(|source| SplitError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let entries: Vec<PathBuf> = text
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.starts_with('#'))
            .map(|l| normalized(Path::new(l)))
            .collect();
        if entries.is_empty() {
            return Err(SplitError::EmptyList {
                path: path.to_path_buf(),
            });
        }
        Ok(SplitRule::List(entries))
    }

    /// Indices of the frames the rule makes test frames.
    pub fn test_indices(&self, dataset: &Dataset) -> Result<Vec<usize>, SplitError> {
        match self {
            SplitRule::Every(n) => {
                if *n < 2 {
                    return Err(SplitError::BadInterval { n: *n });
                }
                let mut order: Vec<usize> = (0..dataset.frames.len()).collect();
                order.sort_by(|&a, &b| {
                    dataset.frames[a]
                        .image_path
                        .cmp(&dataset.frames[b].image_path)
                });
                let mut test: Vec<usize> = order.into_iter().step_by(*n).collect();
                test.sort_unstable();
                Ok(test)
            }
            SplitRule::List(entries) => {
                let paths: Vec<PathBuf> = dataset
                    .frames
                    .iter()
                    .map(|f| normalized(&f.image_path))
                    .collect();
                let mut test = HashSet::new();
                for entry in entries {
                    let entry_n = normalized(entry);
                    let exact: Vec<usize> =
                        (0..paths.len()).filter(|&i| paths[i] == entry_n).collect();
                    let found = if exact.is_empty() {
                        (0..paths.len())
                            .filter(|&i| paths[i].ends_with(&entry_n))
                            .collect()
                    } else {
                        exact
                    };
                    match found.len() {
                        0 => {
                            return Err(SplitError::UnknownEntry {
                                entry: entry.clone(),
                            });
                        }
                        1 => {
                            test.insert(found[0]);
                        }
                        count => {
                            return Err(SplitError::AmbiguousEntry {
                                entry: entry.clone(),
                                count,
                            });
                        }
                    }
                }
                let mut test: Vec<usize> = test.into_iter().collect();
                test.sort_unstable();
                Ok(test)
            }
        }
    }
}

impl SplitSpec {
    /// Applies the rule to `dataset` ([`Dataset::apply_split`], or [`Dataset::resplit`] when
    /// `resplit` is set).
    pub fn apply(&self, dataset: &mut Dataset) -> Result<(), SplitError> {
        if self.resplit {
            dataset.resplit(&self.rule)
        } else {
            dataset.apply_split(&self.rule)
        }
    }
}

impl Dataset {
    /// Makes the frames `rule` picks test frames and all others train frames. A dataset that
    /// already has test or val frames is refused ([`SplitError::AlreadySplit`]); use
    /// [`Dataset::resplit`] to replace its split. Nothing changes on error.
    pub fn apply_split(&mut self, rule: &SplitRule) -> Result<(), SplitError> {
        let test = self.split(Split::Test).count();
        let val = self.split(Split::Val).count();
        if test + val > 0 {
            return Err(SplitError::AlreadySplit { test, val });
        }
        self.resplit(rule)
    }

    /// Like [`Dataset::apply_split`], replacing whatever split the dataset has.
    pub fn resplit(&mut self, rule: &SplitRule) -> Result<(), SplitError> {
        let test = rule.test_indices(self)?;
        if test.len() == self.frames.len() {
            return Err(SplitError::NoTrainFrames {
                frames: self.frames.len(),
            });
        }
        for f in &mut self.frames {
            f.split = Split::Train;
        }
        for i in test {
            self.frames[i].split = Split::Test;
        }
        Ok(())
    }
}
