//! `--test-every N` / `--test-list FILE` / `--resplit`: a test split for data that has none,
//! shared by `map build`, `eval` and `localize`, and the rule a map records.

use std::path::PathBuf;

use clap::Args;
use matloc_data::Dataset;
use matloc_data::split::{SplitError, SplitRule, SplitSpec};
use thiserror::Error;

/// The split flags.
#[derive(Args, Clone, Debug, Default)]
pub struct SplitArgs {
    /// Make every N-th frame (sorted by image path, starting with the first) a test frame and
    /// the rest training frames, like nerfstudio's `--eval-mode interval`. Recorded in the map,
    /// so `eval` and `localize` use the same split.
    #[arg(long, value_name = "N", conflicts_with = "test_list")]
    pub test_every: Option<usize>,
    /// Make the images listed in FILE (one path per line, relative to the dataset; `#`
    /// comments) the test frames and the rest training frames. Recorded like --test-every.
    #[arg(long, value_name = "FILE")]
    pub test_list: Option<PathBuf>,
    /// Replace a split the dataset already has with the rule (else that is an error).
    #[arg(long)]
    pub resplit: bool,
}

/// Errors of the split flags.
#[derive(Debug, Error)]
pub enum SplitArgsError {
    /// Both rules given.
    #[error("--test-every and --test-list are mutually exclusive")]
    BothRules,
    /// `--resplit` without a rule.
    #[error("--resplit needs --test-every or --test-list")]
    ResplitWithoutRule,
    /// The flags give another rule than the map records.
    #[error(
        "the map was built with split {recorded}, the flags ask for {requested}; drop the flags \
         to use the map's split"
    )]
    DisagreesWithMap {
        /// The map's rule (JSON).
        recorded: String,
        /// The flags' rule (JSON).
        requested: String,
    },
    /// The rule cannot be read or applied.
    #[error(transparent)]
    Split(#[from] SplitError),
}

impl SplitArgs {
    /// The rule the flags ask for, if any (reads the list file).
    pub fn spec(&self) -> Result<Option<SplitSpec>, SplitArgsError> {
        let rule = match (self.test_every, &self.test_list) {
            (Some(_), Some(_)) => return Err(SplitArgsError::BothRules),
            (Some(n), None) => SplitRule::Every(n),
            (None, Some(path)) => SplitRule::read_list(path)?,
            (None, None) if self.resplit => return Err(SplitArgsError::ResplitWithoutRule),
            (None, None) => return Ok(None),
        };
        Ok(Some(SplitSpec {
            rule,
            resplit: self.resplit,
        }))
    }

    /// The rule to apply to a map's dataset: the map's recorded rule, or the flags' when the
    /// map records none (a warning: the map's own training frames may become queries). Flags
    /// that disagree with the recorded rule are an error.
    pub fn for_map(
        &self,
        recorded: Option<&SplitSpec>,
    ) -> Result<Option<SplitSpec>, SplitArgsError> {
        let requested = self.spec()?;
        match (recorded, requested) {
            (Some(r), Some(q)) if *r != q => Err(SplitArgsError::DisagreesWithMap {
                recorded: show(r),
                requested: show(&q),
            }),
            (Some(r), _) => Ok(Some(r.clone())),
            (None, Some(q)) => {
                tracing::warn!(
                    rule = %show(&q),
                    "the map records no split rule: it was built on the dataset's own split, so \
                     some test frames of this rule may be frames it was trained on"
                );
                Ok(Some(q))
            }
            (None, None) => Ok(None),
        }
    }
}

fn show(spec: &SplitSpec) -> String {
    serde_json::to_string(spec).unwrap_or_default()
}

/// Applies `spec` (if any) to `dataset`.
pub fn apply(spec: Option<&SplitSpec>, dataset: &mut Dataset) -> Result<(), SplitArgsError> {
    if let Some(s) = spec {
        s.apply(dataset)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn every(n: usize) -> SplitSpec {
        SplitSpec {
            rule: SplitRule::Every(n),
            resplit: false,
        }
    }

    #[test]
    fn flags_resolve_against_the_map() {
        let none = SplitArgs::default();
        let eight = SplitArgs {
            test_every: Some(8),
            ..SplitArgs::default()
        };
        assert_eq!(none.spec().unwrap(), None);
        assert_eq!(eight.spec().unwrap(), Some(every(8)));
        // The map's rule applies without flags, and agrees with the same flags.
        assert_eq!(none.for_map(Some(&every(8))).unwrap(), Some(every(8)));
        assert_eq!(eight.for_map(Some(&every(8))).unwrap(), Some(every(8)));
        assert!(matches!(
            eight.for_map(Some(&every(4))),
            Err(SplitArgsError::DisagreesWithMap { .. })
        ));
        assert_eq!(eight.for_map(None).unwrap(), Some(every(8)));
        assert_eq!(none.for_map(None).unwrap(), None);
    }

    #[test]
    fn bad_flag_combinations_are_errors() {
        let both = SplitArgs {
            test_every: Some(2),
            test_list: Some("x.txt".into()),
            resplit: false,
        };
        assert!(matches!(both.spec(), Err(SplitArgsError::BothRules)));
        let resplit = SplitArgs {
            resplit: true,
            ..SplitArgs::default()
        };
        assert!(matches!(
            resplit.spec(),
            Err(SplitArgsError::ResplitWithoutRule)
        ));
        let missing = SplitArgs {
            test_list: Some("/nonexistent/list.txt".into()),
            ..SplitArgs::default()
        };
        assert!(matches!(missing.spec(), Err(SplitArgsError::Split(_))));
    }
}
