//! Memory checks before allocations whose size comes from input data or settings (image
//! dimensions, ray and voxel counts): a hostile or mistaken input gets a typed error that says
//! which limit, how much was asked for and how to raise it, instead of an abort when the
//! allocator fails.
//!
//! The budget of one request is the smallest of: `MATLOC_MEMORY_LIMIT` when set (bytes, with an
//! optional `K`/`M`/`G`/`T` binary suffix), else `MemAvailable` from `/proc/meminfo`; and the
//! address space left under the process's `RLIMIT_AS` (`ulimit -v`). Where none of these can be
//! read (not Linux) nothing is refused.

use std::fmt;

/// Environment variable that sets the memory budget in bytes (`K`, `M`, `G`, `T` suffixes are
/// powers of 1024), replacing `MemAvailable`.
pub const MEMORY_LIMIT_ENV: &str = "MATLOC_MEMORY_LIMIT";

/// Where a memory budget comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BudgetSource {
    /// The `MATLOC_MEMORY_LIMIT` environment variable.
    Env,
    /// `MemAvailable` in `/proc/meminfo`.
    MemAvailable,
    /// The address space left under `RLIMIT_AS`.
    AddressSpace,
    /// Given by the caller (tests, library users).
    Explicit,
}

impl fmt::Display for BudgetSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            BudgetSource::Env => MEMORY_LIMIT_ENV,
            BudgetSource::MemAvailable => "MemAvailable in /proc/meminfo",
            BudgetSource::AddressSpace => "address space left under RLIMIT_AS (ulimit -v)",
            BudgetSource::Explicit => "the given budget",
        })
    }
}

/// Bytes one request may use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MemoryBudget {
    /// The budget, bytes.
    pub bytes: u64,
    /// Where it comes from.
    pub source: BudgetSource,
}

/// One allocation (or a set of them made together) to check: `count` items of `bytes_each`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MemoryRequest {
    /// What is allocated, e.g. `"partition ray samples of frame 3"`.
    pub what: &'static str,
    /// How many items.
    pub count: u64,
    /// What an item is, e.g. `"points"`, `"pixels"`, `"cells"`.
    pub unit: &'static str,
    /// Bytes per item (every buffer the request makes, together).
    pub bytes_each: u64,
    /// How to ask for less, e.g. `` "raise `samples.pixel_stride`" ``.
    pub remedy: &'static str,
}

impl MemoryRequest {
    /// Total bytes asked for (saturating).
    pub fn bytes(&self) -> u64 {
        self.count.saturating_mul(self.bytes_each)
    }
}

/// A request that does not fit in memory, or a budget setting that cannot be read.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum LimitError {
    /// The request is larger than the budget.
    #[error(
        "memory limit: {what}: {count} {unit} need {needed} bytes ({}), more than the {budget} \
         bytes ({}) of the budget ({budget_from}); {remedy}, or raise the budget with \
         {MEMORY_LIMIT_ENV}=BYTES (and `ulimit -v`)",
        human_bytes(*needed),
        human_bytes(*budget)
    )]
    Memory {
        /// What was to be allocated.
        what: &'static str,
        /// Items asked for.
        count: u64,
        /// What an item is.
        unit: &'static str,
        /// Bytes asked for.
        needed: u64,
        /// The budget, bytes.
        budget: u64,
        /// Where the budget comes from.
        budget_from: BudgetSource,
        /// How to ask for less.
        remedy: &'static str,
    },
    /// `MATLOC_MEMORY_LIMIT` is set to something that is not a size.
    #[error("{MEMORY_LIMIT_ENV}={value:?} is not a size in bytes (e.g. 8G, 512M, 1000000)")]
    BadSetting {
        /// The value found.
        value: String,
    },
}

/// `n` bytes as B / KiB / MiB / GiB / TiB with one decimal.
pub fn human_bytes(n: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = n as f64;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < UNITS.len() {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{n} B")
    } else {
        format!("{v:.1} {}", UNITS[u])
    }
}

/// Parses a size such as `512M`, `8G`, `8GiB`, `1000000` (binary suffixes).
pub fn parse_size(text: &str) -> Option<u64> {
    let t = text.trim();
    let t = t
        .strip_suffix("iB")
        .or_else(|| t.strip_suffix('B'))
        .unwrap_or(t);
    let (digits, shift) = match t.chars().last()? {
        'k' | 'K' => (&t[..t.len() - 1], 10),
        'm' | 'M' => (&t[..t.len() - 1], 20),
        'g' | 'G' => (&t[..t.len() - 1], 30),
        't' | 'T' => (&t[..t.len() - 1], 40),
        _ => (t, 0),
    };
    let v: u64 = digits.trim().parse().ok()?;
    v.checked_mul(1u64 << shift)
}

/// `MemAvailable` from the text of `/proc/meminfo`, bytes.
fn mem_available(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kb.checked_mul(1024)
}

/// The soft `RLIMIT_AS` from the text of `/proc/self/limits` (`None`: unlimited or unknown).
fn address_space_limit(limits: &str) -> Option<u64> {
    let line = limits
        .lines()
        .find(|l| l.starts_with("Max address space"))?;
    let soft = line["Max address space".len()..]
        .split_whitespace()
        .next()?;
    soft.parse().ok()
}

/// `VmSize` from the text of `/proc/self/status`, bytes.
fn vm_size(status: &str) -> Option<u64> {
    let line = status.lines().find(|l| l.starts_with("VmSize:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kb.checked_mul(1024)
}

/// The budget for one request now (see the module docs); `Ok(None)` when nothing limits it.
pub fn current_budget() -> Result<Option<MemoryBudget>, LimitError> {
    let mut best: Option<MemoryBudget> = match std::env::var(MEMORY_LIMIT_ENV) {
        Ok(v) if !v.trim().is_empty() => Some(MemoryBudget {
            bytes: parse_size(&v).ok_or(LimitError::BadSetting { value: v })?,
            source: BudgetSource::Env,
        }),
        _ => std::fs::read_to_string("/proc/meminfo")
            .ok()
            .and_then(|t| mem_available(&t))
            .map(|bytes| MemoryBudget {
                bytes,
                source: BudgetSource::MemAvailable,
            }),
    };
    let as_left = std::fs::read_to_string("/proc/self/limits")
        .ok()
        .and_then(|t| address_space_limit(&t))
        .map(|limit| {
            let used = std::fs::read_to_string("/proc/self/status")
                .ok()
                .and_then(|t| vm_size(&t))
                .unwrap_or(0);
            limit.saturating_sub(used)
        });
    if let Some(bytes) = as_left
        && best.is_none_or(|b| bytes < b.bytes)
    {
        best = Some(MemoryBudget {
            bytes,
            source: BudgetSource::AddressSpace,
        });
    }
    Ok(best)
}

/// Checks `request` against `budget` (`None`: no limit).
pub fn check_against(
    request: &MemoryRequest,
    budget: Option<MemoryBudget>,
) -> Result<(), LimitError> {
    let needed = request.bytes();
    match budget {
        Some(b) if needed > b.bytes => Err(LimitError::Memory {
            what: request.what,
            count: request.count,
            unit: request.unit,
            needed,
            budget: b.bytes,
            budget_from: b.source,
            remedy: request.remedy,
        }),
        _ => Ok(()),
    }
}

/// Requests below this many bytes are not checked (reading `/proc` costs more than they do).
pub const CHECK_ABOVE_BYTES: u64 = 16 << 20;

/// Checks `request` against the [`current_budget`]; requests under [`CHECK_ABOVE_BYTES`]
/// always pass.
pub fn check_memory(request: &MemoryRequest) -> Result<(), LimitError> {
    if request.bytes() < CHECK_ABOVE_BYTES {
        return Ok(());
    }
    check_against(request, current_budget()?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(count: u64) -> MemoryRequest {
        MemoryRequest {
            what: "test buffer",
            count,
            unit: "cells",
            bytes_each: 4,
            remedy: "lower `test.resolution`",
        }
    }

    #[test]
    fn a_request_over_the_budget_names_the_limit_the_amount_and_the_remedy() {
        let budget = Some(MemoryBudget {
            bytes: 1000,
            source: BudgetSource::Explicit,
        });
        assert!(check_against(&request(250), budget).is_ok());
        let e = check_against(&request(251), budget)
            .unwrap_err()
            .to_string();
        for part in [
            "test buffer",
            "251 cells",
            "1004 bytes",
            "1000 bytes",
            "`test.resolution`",
            MEMORY_LIMIT_ENV,
        ] {
            assert!(e.contains(part), "{part} missing from {e}");
        }
        assert!(check_against(&request(u64::MAX), None).is_ok());
        // Overflowing requests saturate rather than wrap.
        assert!(check_against(&request(u64::MAX), budget).is_err());
    }

    #[test]
    fn sizes_parse_with_binary_suffixes() {
        assert_eq!(parse_size("1000"), Some(1000));
        assert_eq!(parse_size("512M"), Some(512 << 20));
        assert_eq!(parse_size("8G"), Some(8 << 30));
        assert_eq!(parse_size("8GiB"), Some(8 << 30));
        assert_eq!(parse_size(" 2k "), Some(2048));
        assert_eq!(parse_size("lots"), None);
        assert_eq!(parse_size(""), None);
        assert_eq!(parse_size("99999999999T"), None);
    }

    #[test]
    fn proc_files_are_read() {
        assert_eq!(
            mem_available("MemTotal: 100 kB\nMemAvailable:   2048 kB\n"),
            Some(2048 * 1024)
        );
        let limits = "Limit                     Soft Limit           Hard Limit           Units\n\
                      Max address space         unlimited            unlimited            bytes\n";
        assert_eq!(address_space_limit(limits), None);
        let limits = "Max address space         4294967296           unlimited            bytes\n";
        assert_eq!(address_space_limit(limits), Some(4 << 30));
        assert_eq!(vm_size("Name: x\nVmSize:\t  1000 kB\n"), Some(1_024_000));
        if std::path::Path::new("/proc/meminfo").exists() {
            let b = current_budget().unwrap().expect("Linux has MemAvailable");
            assert!(b.bytes > 0);
        }
    }

    #[test]
    fn small_requests_pass_without_reading_the_budget() {
        assert!(check_memory(&request(1000)).is_ok());
    }
}
