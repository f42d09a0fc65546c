//! Evaluation: the paper's Tables 1–2 (per-method accuracy, refusal and timing) in [`tables`],
//! Table 3 (feature sets × matching time, precision, pose error) on a built map in [`table3`]
//! and on the synthetic world's analytic field in [`table3_field`], Table 4 (place recognition)
//! in [`table4`], and diagnostic stand-ins for learned stages in [`diagnostics`]. The
//! command-line tool only prints what these return.

pub mod diagnostics;
pub mod table3;
pub mod table3_field;
pub mod table4;
pub mod tables;

pub use tables::{
    MethodSummary, QueryOutcome, RECALL_THRESHOLDS, RecallThreshold, Reliability, ReliabilityBin,
    accuracy_table, reliability, reliability_table, summarize, summarize_with, timing_table,
};
