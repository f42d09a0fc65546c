//! The build as jobs: the job list a planned map records (`plan.json`: each block's command and
//! the finish command) and the Slurm scripts that run it as a job array followed by a finish job
//! depending on all of it.

use std::path::{Path, PathBuf};

use crate::map::layout::{PLAN_FILE, PLAN_FORMAT, PlanRecord};
use crate::map::manifest::{MapDir, MapError};

/// Why the job list or its scripts cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// The map's files.
    #[error(transparent)]
    Map(#[from] MapError),
    /// The map has no readable plan.
    #[error("map {root} has no job plan; run `matloc map plan` first: {source}")]
    NoPlan {
        /// The map root.
        root: PathBuf,
        /// Why the plan cannot be read.
        source: MapError,
    },
    /// The plan file is not one this version writes.
    #[error("{path}: {message}")]
    BadPlan {
        /// The plan file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A Slurm setting cannot be used.
    #[error("{0}")]
    Options(String),
    /// A script cannot be written.
    #[error("{path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
}

/// What the jobs run: the `matloc` program and the dataset they read.
#[derive(Clone, Debug, PartialEq)]
pub struct JobCommands {
    /// The program (absolute, so a job on another node finds it on a shared file system).
    pub program: PathBuf,
    /// The dataset directory.
    pub data: PathBuf,
}

impl JobCommands {
    /// The command line `matloc map STEP ROOT ARGS...`.
    fn command(&self, root: &Path, step: &str, args: &[String]) -> Vec<String> {
        let mut v = vec![
            self.program.display().to_string(),
            "map".to_string(),
            step.to_string(),
            root.display().to_string(),
        ];
        v.extend_from_slice(args);
        v
    }
}

/// `path` made absolute where it exists (unchanged otherwise).
fn absolute(path: &Path) -> PathBuf {
    std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf())
}

/// Writes the job list of a planned map with `blocks` blocks into its `plan.json`
/// (checksummed in the manifest): one `map block ROOT --block B` per block, then
/// `map finish ROOT`.
pub fn write_plan(
    map: &mut MapDir,
    blocks: usize,
    jobs: &JobCommands,
) -> Result<PlanRecord, JobError> {
    let root = absolute(map.root());
    let blocks: Vec<usize> = (0..blocks).collect();
    let record = PlanRecord {
        format: PLAN_FORMAT.to_string(),
        version: 1,
        data: absolute(&jobs.data).display().to_string(),
        block_commands: blocks
            .iter()
            .map(|b| jobs.command(&root, "block", &["--block".into(), b.to_string()]))
            .collect(),
        finish_command: jobs.command(&root, "finish", &[]),
        blocks,
    };
    map.write_json(PLAN_FILE, &record)?;
    map.save()?;
    Ok(record)
}

/// The plan of a planned map (checksum verified), checked against this version's format.
pub fn read_plan(map: &MapDir) -> Result<PlanRecord, JobError> {
    let plan: PlanRecord = map
        .read_json(PLAN_FILE)
        .map_err(|source| JobError::NoPlan {
            root: map.root().to_path_buf(),
            source,
        })?;
    let bad = |message: String| JobError::BadPlan {
        path: map.root().join(PLAN_FILE),
        message,
    };
    if plan.format != PLAN_FORMAT || plan.version != 1 {
        return Err(bad(format!(
            "format {:?} version {}, expected {PLAN_FORMAT:?} version 1",
            plan.format, plan.version
        )));
    }
    if plan.block_commands.len() != plan.blocks.len() {
        return Err(bad(format!(
            "`block_commands` has {} entries for {} blocks",
            plan.block_commands.len(),
            plan.blocks.len()
        )));
    }
    Ok(plan)
}

/// `s` quoted for a POSIX shell (unchanged when it needs no quoting).
pub fn shell_quote(s: &str) -> String {
    let plain = !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || "/._-+=:,@%".contains(c));
    if plain {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', r"'\''"))
    }
}

/// A command line for a POSIX shell.
pub fn shell_line(argv: &[String]) -> String {
    argv.iter()
        .map(|a| shell_quote(a))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Settings of the Slurm scripts.
#[derive(Clone, Debug, PartialEq)]
pub struct SlurmOptions {
    /// `--partition`.
    pub partition: Option<String>,
    /// CPUs of each block job (`--cpus-per-task`; the job's rayon threads).
    pub cpus_per_task: u32,
    /// CPUs of the finish job (default: `cpus_per_task`).
    pub finish_cpus: Option<u32>,
    /// `--mem` of each job.
    pub mem: String,
    /// `--time` of each job.
    pub time: String,
    /// `--account`.
    pub account: Option<String>,
    /// At most this many block jobs at once (`--array=0-N%K`).
    pub max_running: Option<u32>,
    /// The program the jobs run instead of the plan's.
    pub program: Option<PathBuf>,
}

impl Default for SlurmOptions {
    /// 4 CPUs, 8 GB and two hours per job, no partition or account.
    fn default() -> Self {
        SlurmOptions {
            partition: None,
            cpus_per_task: 4,
            finish_cpus: None,
            mem: "8G".into(),
            time: "02:00:00".into(),
            account: None,
            max_running: None,
            program: None,
        }
    }
}

/// The Slurm scripts of a planned map, to be written in `out`: (file name, content) of
/// `blocks.sbatch` (the job array), `finish.sbatch` and `submit.sh`.
pub fn slurm_scripts(
    plan: &PlanRecord,
    a: &SlurmOptions,
    out: &Path,
) -> Result<Vec<(String, String)>, JobError> {
    let bad = |m: &str| Err(JobError::Options(m.to_string()));
    if plan.blocks.is_empty() {
        return bad("the plan has no blocks");
    }
    if a.cpus_per_task < 1 {
        return bad("--cpus-per-task must be at least 1");
    }
    let finish_cpus = a.finish_cpus.unwrap_or(a.cpus_per_task);
    if finish_cpus < 1 {
        return bad("--finish-cpus must be at least 1");
    }
    let logs = out.join("logs");
    let program = match &a.program {
        Some(p) => p.display().to_string(),
        None => plan.finish_command[0].clone(),
    };
    let with_program = |argv: &[String]| -> String {
        let mut v = argv.to_vec();
        v[0] = program.clone();
        shell_line(&v)
    };
    let header = |name: &str, log: &str, cpus: u32| {
        let mut h = format!(
            "#!/bin/bash\n#SBATCH --job-name={name}\n#SBATCH --cpus-per-task={cpus}\n\
             #SBATCH --mem={}\n#SBATCH --time={}\n#SBATCH --output={}\n\
             #SBATCH --open-mode=append\n",
            a.mem,
            a.time,
            shell_quote(&logs.join(log).display().to_string())
        );
        if let Some(p) = &a.partition {
            h.push_str(&format!("#SBATCH --partition={p}\n"));
        }
        if let Some(acc) = &a.account {
            h.push_str(&format!("#SBATCH --account={acc}\n"));
        }
        h
    };
    let n = plan.blocks.len();
    let array = match a.max_running {
        Some(k) => format!("0-{}%{k}", n - 1),
        None => format!("0-{}", n - 1),
    };
    // The block id of each array index, and each block's command with `$B` for the id.
    let ids: Vec<String> = plan.blocks.iter().map(|b| b.to_string()).collect();
    let mut block_cmd = plan.block_commands[0].clone();
    if block_cmd.last() != Some(&ids[0]) || block_cmd.len() < 2 {
        return Err(JobError::Options(format!(
            "plan.json: the first block command does not end with its block id {}",
            ids[0]
        )));
    }
    block_cmd.pop();
    let block_line = format!("{} \"$B\"", with_program(&block_cmd));
    let blocks = format!(
        "{}#SBATCH --array={array}\n\
         # One block per array task: SLURM_ARRAY_TASK_ID indexes BLOCKS. A block whose job was\n\
         # killed resumes when its index is submitted again (sbatch --array=K blocks.sbatch).\n\
         set -euo pipefail\n\
         BLOCKS=({})\n\
         B=\"${{BLOCKS[$SLURM_ARRAY_TASK_ID]}}\"\n\
         export RAYON_NUM_THREADS=\"${{SLURM_CPUS_PER_TASK:-1}}\"\n\
         exec {block_line}\n",
        header("matloc-blocks", "block-%a.log", a.cpus_per_task),
        ids.join(" ")
    );
    let finish = format!(
        "{}# Submitted with --dependency=afterok:<array job>: runs once every block succeeded.\n\
         set -euo pipefail\n\
         export RAYON_NUM_THREADS=\"${{SLURM_CPUS_PER_TASK:-1}}\"\n\
         exec {}\n",
        header("matloc-finish", "finish.log", finish_cpus),
        with_program(&plan.finish_command)
    );
    let submit = format!(
        "#!/bin/bash\n\
         # Submits the block array, then the finish job depending on all of it; prints both ids.\n\
         set -euo pipefail\n\
         cd {}\n\
         mkdir -p logs\n\
         array=$(sbatch --parsable \"$@\" blocks.sbatch)\n\
         array=${{array%%;*}}\n\
         finish=$(sbatch --parsable \"$@\" --dependency=afterok:\"$array\" finish.sbatch)\n\
         finish=${{finish%%;*}}\n\
         echo \"$array $finish\"\n",
        shell_quote(&out.display().to_string())
    );
    Ok(vec![
        ("blocks.sbatch".into(), blocks),
        ("finish.sbatch".into(), finish),
        ("submit.sh".into(), submit),
    ])
}

/// Writes the Slurm scripts of `plan` into `out` (created, with `out/logs`), executable;
/// returns the directory as written into the scripts (absolute where it can be).
pub fn write_slurm_scripts(
    plan: &PlanRecord,
    options: &SlurmOptions,
    out: &Path,
) -> Result<PathBuf, JobError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| JobError::Io { path, source }
    };
    std::fs::create_dir_all(out.join("logs")).map_err(io(&out.join("logs")))?;
    let out = absolute(out);
    for (name, text) in slurm_scripts(plan, options, &out)? {
        let path = out.join(&name);
        matloc_core::fsutil::write_atomic(&path, text.as_bytes()).map_err(io(&path))?;
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755))
                .map_err(io(&path))?;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shell_words_are_quoted_only_when_needed() {
        let argv = ["/opt/m atloc", "map", "it's", "--block", "3"].map(String::from);
        assert_eq!(shell_line(&argv), r"'/opt/m atloc' map 'it'\''s' --block 3");
        assert_eq!(shell_line(&[String::new()]), "''");
    }

    #[test]
    fn slurm_scripts_run_an_array_over_the_blocks_and_a_finish_job() {
        let cmd = |tail: &[&str]| -> Vec<String> {
            ["/bin/matloc", "map"]
                .iter()
                .chain(tail)
                .map(|s| s.to_string())
                .collect()
        };
        let plan = PlanRecord {
            format: "matloc-plan".into(),
            version: 1,
            data: "/d".into(),
            blocks: vec![0, 1, 2],
            block_commands: (0..3)
                .map(|b| cmd(&["block", "/maps/m 1", "--block", &b.to_string()]))
                .collect(),
            finish_command: cmd(&["finish", "/maps/m 1"]),
        };
        let args = SlurmOptions {
            partition: Some("cpu".into()),
            cpus_per_task: 8,
            finish_cpus: Some(32),
            mem: "16G".into(),
            time: "04:00:00".into(),
            account: None,
            max_running: Some(2),
            program: None,
        };
        let scripts = slurm_scripts(&plan, &args, Path::new("/maps/m 1/slurm")).unwrap();
        let get = |name: &str| &scripts.iter().find(|(n, _)| n == name).unwrap().1;
        let blocks = get("blocks.sbatch");
        for line in [
            "#SBATCH --array=0-2%2",
            "#SBATCH --cpus-per-task=8",
            "#SBATCH --mem=16G",
            "#SBATCH --time=04:00:00",
            "#SBATCH --partition=cpu",
            "#SBATCH --output='/maps/m 1/slurm/logs/block-%a.log'",
            "BLOCKS=(0 1 2)",
            "exec /bin/matloc map block '/maps/m 1' --block \"$B\"",
        ] {
            assert!(blocks.contains(line), "{line} not in\n{blocks}");
        }
        assert!(!blocks.contains("--account"), "{blocks}");
        let finish = get("finish.sbatch");
        assert!(finish.contains("exec /bin/matloc map finish '/maps/m 1'"));
        assert!(finish.contains("#SBATCH --cpus-per-task=32"), "{finish}");
        assert!(get("submit.sh").contains("--dependency=afterok:\"$array\" finish.sbatch"));
        // A plan whose commands do not end with the block id is refused.
        let mut bad = plan.clone();
        bad.block_commands[0].push("--quiet".into());
        assert!(slurm_scripts(&bad, &args, Path::new("/s")).is_err());
    }
}
