//! Learning histories on disk: one HDF5 file, DSRL-compatible.
//!
//! A *learning history* is the ordered sequence of every episode one learning
//! run (PPO-Lagrangian from scratch, or a noisy optimal policy) played in one
//! task at one cost limit. A file holds many of them, concatenated.
//!
//! # Layout (format version [`FORMAT_VERSION`])
//! Flat per-step arrays over all `N` steps of all histories, in order, with the
//! names DSRL uses so its readers work unchanged:
//!
//! | dataset | shape | dtype | meaning |
//! |---|---|---|---|
//! | `observations` | (N, obs_dim) | float32 | observation before the action |
//! | `next_observations` | (N, obs_dim) | float32 | observation after it |
//! | `actions` | (N, action_dim) | float32 | the action; for a discrete space one column holding the index |
//! | `rewards`, `costs` | (N,) | float32 | received for the action |
//! | `terminals` | (N,) | float32 | 1 where the episode reached the goal (no bootstrap) |
//! | `timeouts` | (N,) | float32 | 1 where the time limit ended the episode |
//! | `history_id` | (N,) | int64 | which history of the grid the step belongs to, `0..H` (a shard: its part of the grid), non-decreasing |
//! | `episode_id` | (N,) | int64 | episode index within its history, from 0 |
//! | `cost_limit` | (H,) | float32 | the history's cost limit |
//! | `task_goal` | (H, 2) | int64 | goal cell (row, col) |
//! | `task_obstacles` | (H, n_obstacles, 2) | int64 | obstacle cells (row, col) |
//!
//! File attributes: `env` (string), `config` (string: the generating
//! configuration as JSON), `seed` (uint64), `format_version` (uint32),
//! `obs_dim`, `action_dim`, `action_n` (number of discrete actions, 0 for a
//! continuous space), `grid_size` (uint64), `physics_steps_per_action`
//! (uint64: Point and Car, the MuJoCo physics steps per agent action the
//! histories were played with, the macro action; 0 for SafeDarkRoom, which has
//! no physics), `grid_histories` (uint64: histories in the whole task x
//! cost-limit grid; absent in files from before sharding: the file's own
//! count). A shard (`icrl dataset --shard I/N`) also records `shard_index`
//! and `shard_count` (uint64), holds the histories `I*G/N..(I+1)*G/N` of
//! the grid's `G`, and numbers them in `history_id` as the whole grid does, so
//! that the shards side by side read as one file (`icrl dataset merge`,
//! [`crate::data::merge`]). A Point or Car file without it was made when an agent action
//! was 5 physics steps (before 2026-11-30) and is refused: its steps are 10x
//! shorter than today's environment's. Every array is chunked and
//! deflate-compressed. Episodes split at `terminals | timeouts`; every history
//! ends on an episode boundary.
//!
//! The writer goes through `<out>.tmp` and renames it, so an interrupted run
//! never leaves a half-written file under the final name.
//!
//! # Integrity
//! The file starts with a 512-byte HDF5 *user block* (which HDF5 and h5py
//! skip) holding `icrl-histories sha256 <hex>`: the SHA-256 of every byte
//! after the block. The reader checks it before libhdf5 parses anything, so a
//! damaged file is a clear error rather than a crash inside the C library
//! (libhdf5 1.10 can segfault on damaged metadata). Files without the block
//! (written elsewhere, DSRL's) are read as they are, with a warning. Inside,
//! metadata uses the 1.8 object formats (checksummed) and every chunk carries
//! a Fletcher-32 checksum.
//!
//! The parts: `history.rs` (the histories in memory and the checks each
//! passes), `write.rs` (the writer), `read.rs` (the reader) and `seal.rs`
//! (the checksum in the user block, and a merged file's record of its
//! shards).

use std::fmt;
use std::path::{Path, PathBuf};

use safety_envs::output::OutputError;
use safety_envs::{OLD_PHYSICS_STEPS_PER_ACTION, PHYSICS_STEPS_PER_ACTION};
use thiserror::Error;

mod history;
mod read;
mod seal;
#[cfg(test)]
pub(crate) mod tests;
mod write;

pub use history::{DatasetInfo, History, HistoryFile, Shard};
pub use read::read_histories;
pub(crate) use seal::{SHARDS_ATTR, ShardRecord, USER_BLOCK, seal, verify_seal};
pub use write::{check_output_path, temp_path, write_histories, write_histories_to};
pub(crate) use write::{put_text, write_attrs, write_error};

/// Version of the layout above; readers refuse any other.
pub const FORMAT_VERSION: u32 = 1;

/// What is wrong with a history file.
#[derive(Debug)]
pub enum Problem {
    /// No file at that path.
    Missing,
    /// HDF5 could not open or read it (not an HDF5 file, truncated, ...).
    Unreadable(String),
    /// Made for another environment.
    WrongEnv { found: String, expected: String },
    /// Written by another layout version.
    WrongVersion { found: u32, expected: u32 },
    /// A Point or Car file that does not record its macro action: made under
    /// the old 5-physics-step action.
    UnrecordedMacroAction { env: String },
    /// A required dataset or attribute is absent or has the wrong shape.
    Malformed(String),
    /// A history with no steps, or a file with no histories.
    Empty(String),
    /// The caller asked to write something inconsistent.
    Invalid(String),
    /// The output path cannot receive the file.
    Output(String),
    /// The bytes do not match the checksum the writer recorded.
    Damaged(String),
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Problem::Missing => write!(f, "no such file"),
            Problem::Unreadable(e) => write!(f, "not a readable HDF5 file ({e})"),
            Problem::WrongEnv { found, expected } => write!(
                f,
                "histories were made in env '{found}', but '{expected}' was requested"
            ),
            Problem::WrongVersion { found, expected } => write!(
                f,
                "format version {found} is not supported (this build reads version {expected})"
            ),
            Problem::UnrecordedMacroAction { env } => write!(
                f,
                "this {env} dataset does not record its macro action, so it was made when an agent \
                 action was {OLD_PHYSICS_STEPS_PER_ACTION} physics steps (before 2026-11-30); the \
                 environments now take {PHYSICS_STEPS_PER_ACTION} (5 Safety-Gymnasium steps x 10 physics \
                 steps each), so its histories would teach a 10x shorter action: regenerate it with \
                 `icrl dataset --env {env}`"
            ),
            Problem::Malformed(what) => write!(f, "malformed: {what}"),
            Problem::Empty(what) => write!(f, "empty: {what}"),
            Problem::Invalid(what) => write!(f, "invalid histories: {what}"),
            Problem::Output(what) => write!(f, "cannot write the file here: {what}"),
            Problem::Damaged(what) => write!(f, "damaged: {what}"),
        }
    }
}

impl From<OutputError> for HistoryError {
    fn from(e: OutputError) -> Self {
        HistoryError::new(&e.path, Problem::Output(e.problem))
    }
}

/// An error reading or writing a history file: names the file and the problem.
#[derive(Debug, Error)]
#[error("history file {}: {problem}", path.display())]
pub struct HistoryError {
    pub path: PathBuf,
    pub problem: Problem,
}

impl HistoryError {
    pub(crate) fn new(path: &Path, problem: Problem) -> Self {
        HistoryError {
            path: path.to_path_buf(),
            problem,
        }
    }
}
