//! `icrl sweep`: seeds and settings trained here one after another or as a
//! Slurm job array, then the finished runs gathered into one table.
//!
//! A grid file (TOML) names one pretraining command and what varies:
//!
//! ```toml
//! env = "darkroom"
//! method = "eppo"          # or "ad", with dataset = "FILE"
//! preset = "quick"
//! seeds = [0, 1]
//! out = "runs/sweep"       # relative to this file; on a filesystem every node sees
//! [set]                    # --set for every run (a name, or section.name)
//! total_updates = 2000
//! [grid]                   # one run per seed x combination of these values
//! lr = [1e-4, 3e-4]
//! [slurm]                  # optional: partition, account, time, updates_per_second,
//! partition = "cpu"        # cpus_per_task, mem, gpus, extra (more #SBATCH lines), icrl
//! ```
//!
//! `--emit slurm` writes `OUT/sweep.sbatch`: one array task per (setting,
//! seed), each a plain `icrl pretrain ... --out OUT/task_K --resume-in-out`
//! (`OUT/seedN` when only the seed varies),
//! so a task that Slurm requeues (`--requeue`: preempted, or stopped by the
//! `--signal` ahead of its time limit, which the script turns into a
//! checkpoint and a requeue) continues its own run. `--run` runs the same
//! commands here, one after another ([`run_local`]). `--gather` evaluates the
//! last checkpoint of every finished run and writes `OUT/gather/table.md`
//! and `table.csv`: per setting, mean and standard error over seeds.
//!
//! The parts: `grid.rs` (the grid file: read, checked, expanded into array
//! tasks), `slurm.rs` (the `[slurm]` settings and the sbatch script, with
//! the resources it asks for), `local.rs` (`--run`) and `gather.rs`
//! (`--gather`: the evaluations and the claims table).

use std::path::PathBuf;

use thiserror::Error;

mod gather;
mod grid;
mod local;
mod slurm;
#[cfg(test)]
mod tests;

pub use gather::{GatherOptions, Gathered, gather};
pub use grid::{GatherProtocol, SlurmOptions, SweepGrid, Task};
pub use local::{Ran, run_local};
pub use slurm::{emit_slurm, slurm_script};

/// What can go wrong with a sweep.
#[derive(Debug, Error)]
pub enum SweepError {
    #[error("grid file {path}: {problem}")]
    Grid { path: PathBuf, problem: String },
    #[error("{0}")]
    Io(String),
    #[error(transparent)]
    Output(#[from] safety_envs::output::OutputError),
    #[error(transparent)]
    Checkpoint(#[from] crate::checkpoint::CheckpointError),
    #[error(transparent)]
    Eval(#[from] crate::eval::error::EvalCmdError),
}
