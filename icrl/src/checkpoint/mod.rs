//! Run folders, checkpoints and metrics, shared by every learner.
//!
//! A run lives in `runs/{env}__{method}__{seed}__{time}/`:
//! - `config.toml`: the fully resolved configuration of the run;
//! - `metrics.jsonl`: one JSON object per line, always with `env_steps` and
//!   `updates`, plus the learner's fixed metric names (EPPO: `episodic_return`,
//!   `episodic_cost`, `lambda`, `losses/*`, `charts/*`; see `eppo/mod.rs`);
//! - `checkpoints/step_N/`: one folder per checkpoint, written atomically
//!   (filled under `checkpoints/.tmp_step_N/`, then renamed), holding the
//!   learner's files and a `manifest.json` naming the method, environment,
//!   the environment's macro action (Point and Car: physics steps per agent
//!   action), model shape, format version, and the size and SHA-256 of every
//!   file, so a truncated, altered or foreign checkpoint is refused with an
//!   error that names the file. A Point or Car checkpoint that does not
//!   record its macro action was written when an agent action was 5 physics
//!   steps (before 2026-11-30) and is refused: its policy acts on a time
//!   scale 10x shorter than today's environments.
//!
//! Run folders are created exclusively: two runs started in the same second
//! with the same env, method and seed get `..._{time}` and `..._{time}_2`,
//! never one shared folder.
//!
//! The parts: `manifest.rs` (what a checkpoint says about itself, written
//! and verified), `run_dir.rs` (run folders: created, opened, locked, found
//! again to resume, forked), `writing.rs` (checkpoints written atomically
//! and pruned to a [`Retention`], the checks before training that they will
//! fit) and `metrics.rs` (`metrics.jsonl`).

use std::path::{Path, PathBuf};

use thiserror::Error;

mod manifest;
mod metrics;
mod run_dir;
#[cfg(test)]
mod tests;
mod writing;

pub use manifest::{Manifest, drop_file, read_manifest, record_forked_max_len, sha256_file};
pub use metrics::{MetricsWriter, recorded_counters, truncate_metrics};
pub use run_dir::{ForkFrom, Forked, RunDir, checkpoint_folders};
pub use writing::{Retention, last_good, write_part};

/// Version of the checkpoint layout; bumped when files or their meaning change.
pub const FORMAT_VERSION: u32 = 1;

/// Name of the manifest inside a checkpoint folder.
pub const MANIFEST: &str = "manifest.json";

/// Bytes a checkpoint holds besides its tensors (manifest, state, config), allowed for
/// in the disk room checked before training.
pub const CHECKPOINT_SLACK: u64 = 64 * 1024;

/// A run folder or checkpoint that cannot be written or used.
#[derive(Debug, Error)]
pub enum CheckpointError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {problem}; {fix}")]
    Invalid {
        path: PathBuf,
        problem: String,
        fix: String,
    },
    /// A checkpoint that could not be written: nothing of it is left, and
    /// the last good one is named.
    #[error(
        "{path}: writing this checkpoint failed: {problem}; nothing of it was kept. {}",
        crate::checkpoint::last_good(.last_good, "room on its disk")
    )]
    WriteFailed {
        path: PathBuf,
        problem: String,
        last_good: Option<PathBuf>,
    },
    /// A run's file (its metrics) that could not be written while training
    /// (a full disk): training stopped, and the last good checkpoint is
    /// named ([`RunDir::stopped_writing`]).
    #[error(
        "{path}: writing it failed: {problem}; training stopped. {}",
        crate::checkpoint::last_good(.last_good, "room on its disk")
    )]
    StoppedWriting {
        path: PathBuf,
        problem: String,
        last_good: Option<PathBuf>,
    },
    #[error("{path}: checkpoint is for {what} {found:?}, this run has {expected:?}; {fix}")]
    Mismatch {
        path: PathBuf,
        what: String,
        found: String,
        expected: String,
        fix: String,
    },
}

impl CheckpointError {
    /// The last good checkpoint of a run that stopped because a write
    /// failed ([`CheckpointError::WriteFailed`],
    /// [`CheckpointError::StoppedWriting`]): the one to resume from.
    pub fn last_good_checkpoint(&self) -> Option<&Path> {
        match self {
            CheckpointError::WriteFailed { last_good, .. }
            | CheckpointError::StoppedWriting { last_good, .. } => last_good.as_deref(),
            _ => None,
        }
    }
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> CheckpointError + '_ {
    move |source| CheckpointError::Io {
        path: path.to_path_buf(),
        source,
    }
}
