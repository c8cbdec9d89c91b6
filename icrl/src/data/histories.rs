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

use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use hdf5::types::VarLenUnicode;
use safety_envs::output::{self, Existing, OutputError};
use safety_envs::{Cell, EnvName, OLD_PHYSICS_STEPS_PER_ACTION, PHYSICS_STEPS_PER_ACTION, Task};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Version of the layout above; readers refuse any other.
pub const FORMAT_VERSION: u32 = 1;

/// Bytes of the user block that holds the file's checksum.
pub(crate) const USER_BLOCK: usize = 512;
/// How the checksum line in the user block starts.
const CHECKSUM_TAG: &[u8] = b"icrl-histories sha256 ";

/// SHA-256 (hex) of the bytes of `path` after the user block.
fn body_sha256(path: &Path) -> std::io::Result<String> {
    use sha2::Digest;
    use std::io::{Read, Seek, SeekFrom};
    let mut f = std::fs::File::open(path)?;
    f.seek(SeekFrom::Start(USER_BLOCK as u64))?;
    let mut hasher = sha2::Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
    }
    Ok(hasher
        .finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect())
}

/// Writes the checksum line into the user block of a finished file.
pub(crate) fn seal(path: &Path) -> std::io::Result<()> {
    use std::io::{Seek, SeekFrom, Write};
    let line = [CHECKSUM_TAG, body_sha256(path)?.as_bytes(), b"\n"].concat();
    let mut f = std::fs::OpenOptions::new().write(true).open(path)?;
    f.seek(SeekFrom::Start(0))?;
    f.write_all(&line)?;
    f.sync_all()
}

/// Refuses a path that is not a regular file before anything opens it:
/// opening a FIFO blocks until a writer comes, where no stop signal can end
/// the wait, and a device or a folder holds no histories.
fn regular_file(path: &Path) -> Result<(), Problem> {
    std::fs::metadata(path).map_err(|e| Problem::Unreadable(e.to_string()))?;
    crate::guard::regular_file(path)
        .map_err(|what| Problem::Unreadable(format!("{what}: give the dataset's .h5 file")))
}

/// Checks the checksum in the user block and returns it. `Ok(None)`: the
/// file has no checksum (written elsewhere); an error: the bytes do not match it.
pub(crate) fn verify_seal(path: &Path) -> Result<Option<String>, Problem> {
    use std::io::Read;
    regular_file(path)?;
    let mut head = vec![0u8; CHECKSUM_TAG.len() + 64];
    let mut f = std::fs::File::open(path).map_err(|e| Problem::Unreadable(e.to_string()))?;
    if f.read_exact(&mut head).is_err() || !head.starts_with(CHECKSUM_TAG) {
        return Ok(None);
    }
    let want = String::from_utf8_lossy(&head[CHECKSUM_TAG.len()..]).into_owned();
    let got = body_sha256(path).map_err(|e| Problem::Unreadable(e.to_string()))?;
    if got != want {
        return Err(Problem::Damaged(format!(
            "SHA-256 of its contents is {got}, the file records {want}: it was damaged or altered \
             after writing; make it again with `icrl dataset`"
        )));
    }
    Ok(Some(got))
}

/// Rows per chunk of the per-step arrays.
const CHUNK_ROWS: usize = 4096;
/// Deflate level (0-9): 4 is most of the gain for little time.
const DEFLATE_LEVEL: u8 = 4;

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

/// One of `count` disjoint parts of a task x cost-limit grid, `index` from 0
/// (`--shard I/N`, I in 0..N, as Slurm's `$SLURM_ARRAY_TASK_ID` with
/// `--array=0-(N-1)`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

impl Shard {
    /// The grid's histories (in job order) this part holds: contiguous,
    /// so the parts in index order are the grid in order.
    pub fn range(self, grid: usize) -> Range<usize> {
        self.index * grid / self.count..(self.index + 1) * grid / self.count
    }
}

impl fmt::Display for Shard {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

impl FromStr for Shard {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || {
            format!(
                "{s:?} is not a shard: write I/N, the I-th of N parts counted from 0 (0/3, 1/3, 2/3)"
            )
        };
        let (i, n) = s.trim().split_once('/').ok_or_else(bad)?;
        let (index, count) = (
            i.trim().parse::<usize>().map_err(|_| bad())?,
            n.trim().parse::<usize>().map_err(|_| bad())?,
        );
        if index >= count {
            return Err(bad());
        }
        Ok(Shard { index, count })
    }
}

impl TryFrom<String> for Shard {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        s.parse()
    }
}

impl From<Shard> for String {
    fn from(s: Shard) -> String {
        s.to_string()
    }
}

/// File-level facts: which environment, how it was made, sizes.
#[derive(Clone, Debug, PartialEq)]
pub struct DatasetInfo {
    /// Environment name, as `make_env` spells it (`darkroom`, `point`, `car`).
    pub env: String,
    /// The generating configuration, JSON.
    pub config: String,
    /// Master seed of the generation.
    pub seed: u64,
    pub obs_dim: usize,
    /// Columns of `actions`: 1 for a discrete space (the index), else the vector length.
    pub action_dim: usize,
    /// Number of discrete actions; `None` for a continuous space.
    pub action_n: Option<usize>,
    /// Task grid side.
    pub grid_size: usize,
    /// Point and Car: MuJoCo physics steps per agent action (the macro
    /// action) the histories were played with; `None` for SafeDarkRoom.
    pub physics_steps_per_action: Option<usize>,
    /// Histories in the whole task x cost-limit grid.
    pub grid_histories: usize,
    /// The part of the grid a shard holds; `None`: all of it.
    pub shard: Option<Shard>,
}

impl DatasetInfo {
    /// `history_id`s of the file's histories: their places in the grid.
    pub fn history_ids(&self) -> Range<usize> {
        match self.shard {
            Some(s) => s.range(self.grid_histories),
            None => 0..self.grid_histories,
        }
    }
}

/// One learning history: every step of every episode of one learning run, in order.
#[derive(Clone, Debug, PartialEq)]
pub struct History {
    pub cost_limit: f32,
    pub task: Task,
    /// (T, obs_dim)
    pub observations: Vec<f32>,
    /// (T, obs_dim)
    pub next_observations: Vec<f32>,
    /// (T, action_dim)
    pub actions: Vec<f32>,
    /// (T,)
    pub rewards: Vec<f32>,
    /// (T,)
    pub costs: Vec<f32>,
    /// (T,) the episode reached a terminal state at this step.
    pub terminals: Vec<bool>,
    /// (T,) the time limit ended the episode at this step.
    pub timeouts: Vec<bool>,
}

impl History {
    /// An empty history for `task` at `cost_limit`.
    pub fn new(task: Task, cost_limit: f32) -> Self {
        History {
            cost_limit,
            task,
            observations: Vec::new(),
            next_observations: Vec::new(),
            actions: Vec::new(),
            rewards: Vec::new(),
            costs: Vec::new(),
            terminals: Vec::new(),
            timeouts: Vec::new(),
        }
    }

    /// Number of steps.
    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rewards.is_empty()
    }

    /// Appends one step.
    #[allow(clippy::too_many_arguments)]
    pub fn push(
        &mut self,
        obs: &[f32],
        action: &[f32],
        reward: f32,
        cost: f32,
        next_obs: &[f32],
        terminated: bool,
        truncated: bool,
    ) {
        self.observations.extend_from_slice(obs);
        self.actions.extend_from_slice(action);
        self.rewards.push(reward);
        self.costs.push(cost);
        self.next_observations.extend_from_slice(next_obs);
        self.terminals.push(terminated);
        self.timeouts.push(truncated);
    }

    /// Step ranges of the episodes, split at `terminals | timeouts`. A trailing
    /// unfinished episode (none in a valid file) is included as the last range.
    pub fn episodes(&self) -> Vec<Range<usize>> {
        let mut out = Vec::new();
        let mut start = 0;
        for t in 0..self.len() {
            if self.terminals[t] || self.timeouts[t] {
                out.push(start..t + 1);
                start = t + 1;
            }
        }
        if start < self.len() {
            out.push(start..self.len());
        }
        out
    }

    /// (return, cost) of every episode, in order.
    pub fn episode_totals(&self) -> Vec<(f32, f32)> {
        self.episodes()
            .into_iter()
            .map(|r| {
                (
                    self.rewards[r.clone()].iter().sum(),
                    self.costs[r].iter().sum(),
                )
            })
            .collect()
    }

    /// The history of the episodes `keep` (indices in increasing order), in order.
    pub fn keep_episodes(&self, keep: &[usize], obs_dim: usize, action_dim: usize) -> History {
        let episodes = self.episodes();
        let mut out = History::new(self.task.clone(), self.cost_limit);
        for &e in keep {
            for t in episodes[e].clone() {
                out.push(
                    &self.observations[t * obs_dim..(t + 1) * obs_dim],
                    &self.actions[t * action_dim..(t + 1) * action_dim],
                    self.rewards[t],
                    self.costs[t],
                    &self.next_observations[t * obs_dim..(t + 1) * obs_dim],
                    self.terminals[t],
                    self.timeouts[t],
                );
            }
        }
        out
    }

    /// Drops steps after the last finished episode (a learning run stopped by a
    /// step budget mid-episode).
    pub fn truncate_to_finished_episodes(&mut self, obs_dim: usize, action_dim: usize) {
        let keep = (0..self.len())
            .rev()
            .find(|&t| self.terminals[t] || self.timeouts[t])
            .map_or(0, |t| t + 1);
        self.observations.truncate(keep * obs_dim);
        self.next_observations.truncate(keep * obs_dim);
        self.actions.truncate(keep * action_dim);
        self.rewards.truncate(keep);
        self.costs.truncate(keep);
        self.terminals.truncate(keep);
        self.timeouts.truncate(keep);
    }

    /// Checks array lengths against the dimensions and that the history ends
    /// on an episode boundary.
    fn check(&self, i: usize, info: &DatasetInfo) -> Result<(), Problem> {
        let t = self.len();
        if t == 0 {
            return Err(Problem::Empty(format!("history {i} has no steps")));
        }
        let lens = [
            ("observations", self.observations.len(), t * info.obs_dim),
            (
                "next_observations",
                self.next_observations.len(),
                t * info.obs_dim,
            ),
            ("actions", self.actions.len(), t * info.action_dim),
            ("costs", self.costs.len(), t),
            ("terminals", self.terminals.len(), t),
            ("timeouts", self.timeouts.len(), t),
        ];
        for (name, got, want) in lens {
            if got != want {
                return Err(Problem::Invalid(format!(
                    "history {i}: {name} has {got} values, expected {want} ({t} steps)"
                )));
            }
        }
        // Every value finite: one NaN reward would turn a whole training run NaN.
        let values = [
            ("observations", &self.observations, info.obs_dim.max(1)),
            (
                "next_observations",
                &self.next_observations,
                info.obs_dim.max(1),
            ),
            ("actions", &self.actions, info.action_dim.max(1)),
            ("rewards", &self.rewards, 1),
            ("costs", &self.costs, 1),
        ];
        for (name, v, width) in values {
            if let Some(k) = v.iter().position(|x| !x.is_finite()) {
                return Err(Problem::Invalid(format!(
                    "history {i}: {name} holds {} at step {} (values must be finite)",
                    v[k],
                    k / width
                )));
            }
        }
        // A negative cost would pay budget back: no CMDP here has one, and
        // the return- and cost-to-go conditioning assume none.
        if let Some(k) = self.costs.iter().position(|&c| c < 0.0) {
            return Err(Problem::Invalid(format!(
                "history {i}: costs holds {} at step {k} (costs must be non-negative)",
                self.costs[k]
            )));
        }
        if !(self.cost_limit.is_finite() && self.cost_limit >= 0.0) {
            return Err(Problem::Invalid(format!(
                "history {i}: cost limit {} must be finite and non-negative",
                self.cost_limit
            )));
        }
        // A discrete action is an index into the action space.
        if let Some(n) = info.action_n
            && let Some(k) = self
                .actions
                .iter()
                .position(|&a| a < 0.0 || a.fract() != 0.0 || a as usize >= n)
        {
            return Err(Problem::Invalid(format!(
                "history {i}: action {} at step {k} is not one of the {n} discrete actions 0..={}",
                self.actions[k],
                n - 1
            )));
        }
        if !(self.terminals[t - 1] || self.timeouts[t - 1]) {
            return Err(Problem::Invalid(format!(
                "history {i} ends mid-episode (its last step is neither terminal nor a timeout)"
            )));
        }
        if self.task.grid_size != info.grid_size {
            return Err(Problem::Invalid(format!(
                "history {i}: task grid {} differs from the file's {}",
                self.task.grid_size, info.grid_size
            )));
        }
        Ok(())
    }
}

/// A whole file: its facts and its histories, in order.
#[derive(Clone, Debug, PartialEq)]
pub struct HistoryFile {
    pub info: DatasetInfo,
    pub histories: Vec<History>,
}

impl HistoryFile {
    /// Checks every history as the reader does (lengths, finite values,
    /// discrete actions inside the action space, whole episodes); `path`
    /// names the data in the error. Learners that take histories from memory
    /// call it before training.
    pub fn validate(&self, path: &Path) -> Result<(), HistoryError> {
        if self.histories.is_empty() {
            return Err(HistoryError::new(
                path,
                Problem::Empty("no histories".into()),
            ));
        }
        for (i, h) in self.histories.iter().enumerate() {
            h.check(i, &self.info)
                .map_err(|p| HistoryError::new(path, p))?;
        }
        Ok(())
    }

    /// Total steps over all histories.
    pub fn total_steps(&self) -> usize {
        self.histories.iter().map(History::len).sum()
    }
}

/// `<path>.tmp`: where the writer puts the file before renaming it.
pub fn temp_path(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(".tmp");
    PathBuf::from(s)
}

/// Checks, before any long work, that `path` can receive a history file:
/// it is not a folder, its folder exists, and it is free (or, with
/// [`Existing::Replace`], a regular file of ours: see
/// [`safety_envs::output::check_output`]).
pub fn check_output_path(path: &Path, existing: Existing) -> Result<(), HistoryError> {
    let err = |m: String| HistoryError::new(path, Problem::Output(m));
    if path.is_dir() {
        return Err(err(format!(
            "it is a folder; pass a file path such as {}",
            path.join("histories.h5").display()
        )));
    }
    output::check_output(path, existing).map_err(|e| err(e.problem))
}

/// Creates dataset `name` of `shape` (row-major `data`), chunked along the
/// first axis and deflate-compressed.
fn put<T: hdf5::H5Type>(
    f: &hdf5::File,
    name: &str,
    data: &[T],
    shape: &[usize],
) -> hdf5::Result<()> {
    let mut chunk: Vec<usize> = shape.iter().map(|&d| d.max(1)).collect();
    chunk[0] = chunk[0].min(CHUNK_ROWS);
    f.new_dataset::<T>()
        .shape(shape.to_vec())
        .chunk(chunk)
        .deflate(DEFLATE_LEVEL)
        // A checksum of every chunk: damaged data is an error, not wrong values.
        .fletcher32()
        .create(name)?
        .write_raw(data)
}

/// Reads dataset `name` as a flat row-major vector with its shape. A
/// declared size that would not fit in half the machine's available memory
/// (a damaged or hostile file: chunked datasets can declare any shape) is
/// an error before anything is allocated.
fn get<T: hdf5::H5Type>(f: &hdf5::File, name: &str) -> hdf5::Result<(Vec<T>, Vec<usize>)> {
    let d = f.dataset(name)?;
    let shape = d.shape();
    let bytes = shape
        .iter()
        .try_fold(std::mem::size_of::<T>() as u128, |acc, &n| {
            acc.checked_mul(n as u128)
        });
    let limit = crate::guard::machine_memory().map_or(u128::MAX, |(avail, _)| avail as u128 / 2);
    match bytes {
        Some(b) if b <= limit => Ok((d.read_raw::<T>()?, shape)),
        _ => Err(hdf5::Error::from(
            format!(
                "declares shape {shape:?}, more than half this machine's available memory ({})",
                crate::guard::human_bytes(limit as f64)
            )
            .as_str(),
        )),
    }
}

/// Writes `histories` to `path` atomically ([`output::write_file`]: a
/// temporary file beside it, synced, then renamed), replacing a history
/// file there but never a device, link, folder or checkpoint file.
pub fn write_histories(path: &Path, file: &HistoryFile) -> Result<(), HistoryError> {
    write_histories_to(path, file, Existing::Replace)
}

/// [`write_histories`], refusing an existing `path` unless `existing` is
/// [`Existing::Replace`] (the `dataset` command's `--force`).
pub fn write_histories_to(
    path: &Path,
    file: &HistoryFile,
    existing: Existing,
) -> Result<(), HistoryError> {
    let err = |p| HistoryError::new(path, p);
    if file.histories.is_empty() {
        return Err(err(Problem::Empty("no histories to write".into())));
    }
    if let (Some(n), d) = (file.info.action_n, file.info.action_dim)
        && (n == 0 || d != 1)
    {
        return Err(err(Problem::Invalid(format!(
            "a discrete action space needs action_n > 0 and action_dim 1, got {n} and {d}"
        ))));
    }
    let ids = file.info.history_ids();
    if ids.len() != file.histories.len() || ids.end > file.info.grid_histories {
        return Err(err(Problem::Invalid(format!(
            "{} histories, but {} of a grid of {} holds {} ({ids:?})",
            file.histories.len(),
            file.info
                .shard
                .map_or("all".to_string(), |s| format!("shard {s}")),
            file.info.grid_histories,
            ids.len()
        ))));
    }
    let n_obstacles = file.histories[0].task.obstacles.len();
    for (i, h) in file.histories.iter().enumerate() {
        h.check(i, &file.info).map_err(err)?;
        if h.task.obstacles.len() != n_obstacles {
            return Err(err(Problem::Invalid(format!(
                "history {i} has {} obstacles, history 0 has {n_obstacles}",
                h.task.obstacles.len()
            ))));
        }
    }
    check_output_path(path, existing)?;
    output::write_file(path, existing, |tmp| {
        write_raw(tmp, file, n_obstacles)
            .and_then(|()| seal(tmp).map_err(|e| hdf5::Error::from(e.to_string().as_str())))
            // HDF5 words a full disk as a short write of 2^64 - 1 bytes.
            .map_err(|e| match output::full_disk(tmp) {
                Some(full) => err(Problem::Output(full)),
                None => err(Problem::Unreadable(e.to_string())),
            })
    })
}

fn write_raw(tmp: &Path, file: &HistoryFile, n_obstacles: usize) -> hdf5::Result<()> {
    let info = &file.info;
    let n: usize = file.total_steps();
    let h = file.histories.len();
    let concat = |f: &dyn Fn(&History) -> &[f32]| -> Vec<f32> {
        file.histories
            .iter()
            .flat_map(|h| f(h).iter().copied())
            .collect()
    };
    let flag = |f: &dyn Fn(&History) -> &[bool]| -> Vec<f32> {
        file.histories
            .iter()
            .flat_map(|h| f(h).iter().map(|&b| if b { 1.0 } else { 0.0 }))
            .collect()
    };
    let observations = concat(&|h| &h.observations);
    let next_observations = concat(&|h| &h.next_observations);
    let actions = concat(&|h| &h.actions);
    let rewards = concat(&|h| &h.rewards);
    let costs = concat(&|h| &h.costs);
    let terminals = flag(&|h| &h.terminals);
    let timeouts = flag(&|h| &h.timeouts);
    let mut history_id = Vec::with_capacity(n);
    let mut episode_id = Vec::with_capacity(n);
    for (i, hist) in info.history_ids().zip(&file.histories) {
        for (e, r) in hist.episodes().into_iter().enumerate() {
            for _ in r {
                history_id.push(i as i64);
                episode_id.push(e as i64);
            }
        }
    }
    let cost_limit: Vec<f32> = file.histories.iter().map(|h| h.cost_limit).collect();
    let goals: Vec<i64> = file
        .histories
        .iter()
        .flat_map(|h| [h.task.goal.row as i64, h.task.goal.col as i64])
        .collect();
    let obstacles: Vec<i64> = file
        .histories
        .iter()
        .flat_map(|h| {
            h.task
                .obstacles
                .iter()
                .flat_map(|c| [c.row as i64, c.col as i64])
        })
        .collect();

    // The 1.8+ object formats carry checksums of their metadata, so a damaged
    // file is an error when read rather than a crash inside libhdf5.
    let f = hdf5::File::with_options()
        .with_fapl(|p| p.libver_v18())
        .with_fcpl(|p| p.userblock(USER_BLOCK as u64))
        .create(tmp)?;
    put(&f, "observations", &observations, &[n, info.obs_dim])?;
    put(
        &f,
        "next_observations",
        &next_observations,
        &[n, info.obs_dim],
    )?;
    put(&f, "actions", &actions, &[n, info.action_dim])?;
    put(&f, "rewards", &rewards, &[n])?;
    put(&f, "costs", &costs, &[n])?;
    put(&f, "terminals", &terminals, &[n])?;
    put(&f, "timeouts", &timeouts, &[n])?;
    put(&f, "history_id", &history_id, &[n])?;
    put(&f, "episode_id", &episode_id, &[n])?;
    put(&f, "cost_limit", &cost_limit, &[h])?;
    put(&f, "task_goal", &goals, &[h, 2])?;
    put(&f, "task_obstacles", &obstacles, &[h, n_obstacles, 2])?;

    write_attrs(&f, info)?;
    f.flush()?;
    Ok(())
}

/// A string attribute.
pub(crate) fn put_text(f: &hdf5::File, name: &str, value: &str) -> hdf5::Result<()> {
    let text = value
        .parse::<VarLenUnicode>()
        .map_err(|e| hdf5::Error::from(e.to_string().as_str()))?;
    f.new_attr::<VarLenUnicode>()
        .create(name)?
        .write_scalar(&text)
}

/// The file attributes of the layout, from `info`.
pub(crate) fn write_attrs(f: &hdf5::File, info: &DatasetInfo) -> hdf5::Result<()> {
    put_text(f, "env", &info.env)?;
    put_text(f, "config", &info.config)?;
    f.new_attr::<u64>()
        .create("seed")?
        .write_scalar(&info.seed)?;
    f.new_attr::<u32>()
        .create("format_version")?
        .write_scalar(&FORMAT_VERSION)?;
    for (name, v) in [
        ("obs_dim", info.obs_dim),
        ("action_dim", info.action_dim),
        ("action_n", info.action_n.unwrap_or(0)),
        ("grid_size", info.grid_size),
        (
            "physics_steps_per_action",
            info.physics_steps_per_action.unwrap_or(0),
        ),
        ("grid_histories", info.grid_histories),
    ]
    .into_iter()
    .chain(
        info.shard
            .into_iter()
            .flat_map(|s| [("shard_index", s.index), ("shard_count", s.count)]),
    ) {
        f.new_attr::<u64>()
            .create(name)?
            .write_scalar(&(v as u64))?;
    }
    Ok(())
}

/// Reads a history file and validates it. With `expected_env`, a file made
/// for another environment is an error.
pub fn read_histories(
    path: &Path,
    expected_env: Option<&str>,
) -> Result<HistoryFile, HistoryError> {
    let err = |p| HistoryError::new(path, p);
    if !path.exists() {
        return Err(err(Problem::Missing));
    }
    if verify_seal(path).map_err(err)?.is_none() {
        eprintln!(
            "warning: {}: no icrl checksum (written elsewhere or by an older icrl): damage cannot be detected before libhdf5 reads it",
            path.display()
        );
    }
    let f = hdf5::File::open(path).map_err(|e| err(Problem::Unreadable(e.to_string())))?;
    let malformed = |what: String| err(Problem::Malformed(what));
    // A merged file: its shards are checked before libhdf5 reads through to them.
    verify_shards(&f, path)?;

    let info = read_info(&f, path, expected_env)?;

    // Each dataset with the shape it must have (None: any length, checked below).
    let read = |name: &str, tail: &[usize]| -> Result<(Vec<f32>, usize), HistoryError> {
        let (v, shape) =
            get::<f32>(&f, name).map_err(|e| malformed(format!("dataset {name}: {e}")))?;
        if shape.len() != 1 + tail.len() || shape[1..] != *tail {
            return Err(malformed(format!(
                "dataset {name} has shape {shape:?}, expected (rows, {tail:?})"
            )));
        }
        Ok((v, shape[0]))
    };
    let (observations, n_obs) = read("observations", &[info.obs_dim])?;
    let (next_observations, n_next) = read("next_observations", &[info.obs_dim])?;
    let (actions, n_act) = read("actions", &[info.action_dim])?;
    let (rewards, n) = read("rewards", &[])?;
    let (costs, n_costs) = read("costs", &[])?;
    let (terminals, n_term) = read("terminals", &[])?;
    let (timeouts, n_time) = read("timeouts", &[])?;
    let (cost_limit, h) = read("cost_limit", &[])?;
    let (history_id, id_shape) =
        get::<i64>(&f, "history_id").map_err(|e| malformed(format!("dataset history_id: {e}")))?;
    let (goals, goal_shape) =
        get::<i64>(&f, "task_goal").map_err(|e| malformed(format!("dataset task_goal: {e}")))?;
    let (obstacles, obstacle_shape) = get::<i64>(&f, "task_obstacles")
        .map_err(|e| malformed(format!("dataset task_obstacles: {e}")))?;

    for (name, len) in [
        ("observations", n_obs),
        ("next_observations", n_next),
        ("actions", n_act),
        ("costs", n_costs),
        ("terminals", n_term),
        ("timeouts", n_time),
        ("history_id", id_shape.first().copied().unwrap_or(0)),
    ] {
        if len != n {
            return Err(malformed(format!(
                "dataset {name} has {len} rows, rewards has {n}"
            )));
        }
    }
    if h == 0 {
        return Err(err(Problem::Empty("the file holds no histories".into())));
    }
    let n_obstacles = obstacle_shape.get(1).copied().unwrap_or(0);
    if goal_shape != [h, 2] || obstacle_shape != [h, n_obstacles, 2] {
        return Err(malformed(format!(
            "task arrays have shapes {goal_shape:?} and {obstacle_shape:?}, expected [{h}, 2] and [{h}, n, 2]"
        )));
    }

    let ids = info.history_ids();
    if ids.len() != h {
        return Err(malformed(format!(
            "it holds {h} histories, but {} of a grid of {} is {} ({ids:?})",
            info.shard
                .map_or("all".to_string(), |s| format!("shard {s}")),
            info.grid_histories,
            ids.len()
        )));
    }
    // Split the flat arrays by history_id (non-decreasing, every id present).
    // Out of order, a history would look empty though its steps are there.
    if let Some(k) = (1..n).find(|&k| history_id[k] < history_id[k - 1]) {
        return Err(malformed(format!(
            "history_id must be non-decreasing (every history's steps together, in order 0..{h}): \
             step {k} has id {} after id {}",
            history_id[k],
            history_id[k - 1]
        )));
    }
    let mut histories = Vec::with_capacity(h);
    let mut start = 0usize;
    for i in 0..h {
        let mut end = start;
        while end < n && history_id[end] == (ids.start + i) as i64 {
            end += 1;
        }
        if end == start {
            return Err(err(Problem::Empty(format!(
                "history {i} (cost limit {}) has no steps",
                cost_limit[i]
            ))));
        }
        let cell = |r: i64, c: i64| -> Result<Cell, HistoryError> {
            if r < 0 || c < 0 || r as usize >= info.grid_size || c as usize >= info.grid_size {
                return Err(malformed(format!(
                    "history {i}: cell ({r}, {c}) is outside the {g}x{g} grid",
                    g = info.grid_size
                )));
            }
            Ok(Cell {
                row: r as usize,
                col: c as usize,
            })
        };
        let task = Task {
            grid_size: info.grid_size,
            goal: cell(goals[2 * i], goals[2 * i + 1])?,
            obstacles: (0..n_obstacles)
                .map(|j| {
                    let k = 2 * (i * n_obstacles + j);
                    cell(obstacles[k], obstacles[k + 1])
                })
                .collect::<Result<_, _>>()?,
        };
        let rows = |a: &[f32], cols: usize| a[start * cols..end * cols].to_vec();
        let flags = |a: &[f32]| a[start..end].iter().map(|&x| x != 0.0).collect();
        let hist = History {
            cost_limit: cost_limit[i],
            task,
            observations: rows(&observations, info.obs_dim),
            next_observations: rows(&next_observations, info.obs_dim),
            actions: rows(&actions, info.action_dim),
            rewards: rows(&rewards, 1),
            costs: rows(&costs, 1),
            terminals: flags(&terminals),
            timeouts: flags(&timeouts),
        };
        hist.check(i, &info)
            .map_err(|p| match p {
                Problem::Invalid(s) => Problem::Malformed(s),
                other => other,
            })
            .map_err(err)?;
        histories.push(hist);
        start = end;
    }
    if start != n {
        return Err(malformed(format!(
            "history_id is not sorted {ids:?}: step {start} has id {}",
            history_id[start]
        )));
    }
    Ok(HistoryFile { info, histories })
}

/// The file's attributes (format version first: a file of another version
/// may lack everything else), checked: the environment asked for, the macro
/// action recorded for Point and Car, one action column for discrete actions.
fn read_info(
    f: &hdf5::File,
    path: &Path,
    expected_env: Option<&str>,
) -> Result<DatasetInfo, HistoryError> {
    let err = |p| HistoryError::new(path, p);
    let malformed = |what: String| err(Problem::Malformed(what));
    let version = f
        .attr("format_version")
        .and_then(|a| a.read_scalar::<u32>())
        .map_err(|e| malformed(format!("attribute format_version: {e}")))?;
    if version != FORMAT_VERSION {
        return Err(err(Problem::WrongVersion {
            found: version,
            expected: FORMAT_VERSION,
        }));
    }
    let text_attr = |name: &str| -> Result<String, HistoryError> {
        f.attr(name)
            .and_then(|a| a.read_scalar::<VarLenUnicode>())
            .map(|s| s.as_str().to_string())
            .map_err(|e| malformed(format!("attribute {name}: {e}")))
    };
    let u64_attr = |name: &str| -> Result<u64, HistoryError> {
        f.attr(name)
            .and_then(|a| a.read_scalar::<u64>())
            .map_err(|e| malformed(format!("attribute {name}: {e}")))
    };
    let env = text_attr("env")?;
    if let Some(expected) = expected_env
        && env != expected
    {
        return Err(err(Problem::WrongEnv {
            found: env,
            expected: expected.to_string(),
        }));
    }
    let action_n = u64_attr("action_n")? as usize;
    let optional_u64 = |name: &str| -> Result<Option<u64>, HistoryError> {
        match f.attr(name) {
            Ok(a) => a
                .read_scalar::<u64>()
                .map(Some)
                .map_err(|e| malformed(format!("attribute {name}: {e}"))),
            Err(_) => Ok(None),
        }
    };
    // Absent in files from before it was recorded: refused for Point and Car.
    let physics_steps_per_action = optional_u64("physics_steps_per_action")?.unwrap_or(0) as usize;
    // Absent in files from before sharding: the file's own histories.
    let histories = f
        .dataset("cost_limit")
        .map(|d| d.shape().first().copied().unwrap_or(0))
        .unwrap_or(0);
    let has_physics = env
        .parse::<EnvName>()
        .ok()
        .and_then(|e| e.physics_steps_per_action(None))
        .is_some();
    if has_physics && physics_steps_per_action == 0 {
        return Err(err(Problem::UnrecordedMacroAction { env }));
    }
    let info = DatasetInfo {
        env,
        config: text_attr("config")?,
        seed: u64_attr("seed")?,
        obs_dim: u64_attr("obs_dim")? as usize,
        action_dim: u64_attr("action_dim")? as usize,
        action_n: (action_n > 0).then_some(action_n),
        grid_size: u64_attr("grid_size")? as usize,
        physics_steps_per_action: (physics_steps_per_action > 0)
            .then_some(physics_steps_per_action),
        grid_histories: optional_u64("grid_histories")?.map_or(histories, |g| g as usize),
        shard: match (optional_u64("shard_index")?, optional_u64("shard_count")?) {
            (None, None) => None,
            (Some(index), Some(count)) if index < count => Some(Shard {
                index: index as usize,
                count: count as usize,
            }),
            (i, c) => {
                return Err(malformed(format!(
                    "shard_index {i:?} and shard_count {c:?} do not name one part of a grid"
                )));
            }
        },
    };
    if info.action_n.is_some() && info.action_dim != 1 {
        return Err(malformed(format!(
            "a discrete action space (action_n {action_n}) needs action_dim 1, got {}",
            info.action_dim
        )));
    }
    Ok(info)
}

/// Attribute of a merged file listing its shards.
pub(crate) const SHARDS_ATTR: &str = "shards";

/// One shard as a merged file records it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct ShardRecord {
    /// Path relative to the merged file's folder.
    pub(crate) file: String,
    /// The shard's SHA-256 (of the bytes after its user block) at merging.
    pub(crate) sha256: String,
}

/// For a merged file (one with a `shards` attribute): checks that every
/// shard is there, passes its own checksum, and is the file that was
/// merged (its SHA-256 is the recorded one). Other files pass unchecked.
fn verify_shards(f: &hdf5::File, path: &Path) -> Result<(), HistoryError> {
    let Ok(attr) = f.attr(SHARDS_ATTR) else {
        return Ok(());
    };
    let damaged = |what: String| HistoryError::new(path, Problem::Damaged(what));
    let text = attr
        .read_scalar::<hdf5::types::VarLenUnicode>()
        .map_err(|e| damaged(format!("attribute {SHARDS_ATTR}: {e}")))?;
    let records: Vec<ShardRecord> = serde_json::from_str(text.as_str())
        .map_err(|e| damaged(format!("attribute {SHARDS_ATTR}: {e}")))?;
    let base = path.parent().unwrap_or(Path::new("."));
    for r in &records {
        let shard = base.join(&r.file);
        if !shard.is_file() {
            return Err(damaged(format!(
                "its shard {} is missing; keep the merged file and its shards together",
                shard.display()
            )));
        }
        let got = verify_seal(&shard)
            .map_err(|p| HistoryError::new(&shard, p))?
            .ok_or_else(|| damaged(format!("its shard {} has no checksum", shard.display())))?;
        if got != r.sha256 {
            return Err(damaged(format!(
                "its shard {} is not the file that was merged (SHA-256 {got}, merged {}): it was \
                 made again or replaced; merge again with `icrl dataset merge`",
                shard.display(),
                r.sha256
            )));
        }
    }
    Ok(())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use safety_envs::{Orientation, SpawnConfig, sample_task};

    pub(crate) fn tiny_file(histories: usize) -> HistoryFile {
        let cfg = SpawnConfig::darkroom();
        let histories: Vec<History> = (0..histories)
            .map(|i| {
                let task = sample_task(&cfg, Orientation::Centre, i as u64).unwrap();
                let mut h = History::new(task, 2.5 * i as f32);
                // Two episodes: 3 steps ending on the goal, 2 steps timed out.
                for t in 0..5 {
                    let x = (i * 10 + t) as f32;
                    h.push(
                        &[x, -x],
                        &[(t % 5) as f32],
                        if t == 2 { 1.0 } else { 0.0 },
                        (t % 2) as f32,
                        &[x + 1.0, -x - 1.0],
                        t == 2,
                        t == 4,
                    );
                }
                h
            })
            .collect();
        HistoryFile {
            info: DatasetInfo {
                env: "darkroom".into(),
                config: r#"{"steps": 5}"#.into(),
                seed: 7,
                obs_dim: 2,
                action_dim: 1,
                action_n: Some(5),
                grid_size: 9,
                physics_steps_per_action: None,
                grid_histories: histories.len(),
                shard: None,
            },
            histories,
        }
    }

    pub(crate) fn tmpdir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("icrl-histories-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn round_trip_keeps_everything() {
        let dir = tmpdir("roundtrip");
        let path = dir.join("h.h5");
        let file = tiny_file(3);
        write_histories(&path, &file).unwrap();
        assert!(
            !output::temp_path(&path).exists(),
            "the temporary file must be renamed away"
        );
        let back = read_histories(&path, Some("darkroom")).unwrap();
        assert_eq!(back, file);
        assert_eq!(back.histories[1].episodes(), vec![0..3, 3..5]);
        assert_eq!(
            back.histories[1].episode_totals(),
            vec![(1.0, 1.0), (0.0, 1.0)]
        );
        std::fs::remove_dir_all(dir).unwrap();
    }

    fn problem_of(path: &Path, env: Option<&str>) -> (Problem, String) {
        let e = read_histories(path, env).unwrap_err();
        let msg = e.to_string();
        assert!(
            msg.contains(&path.display().to_string()),
            "message must name the file: {msg}"
        );
        (e.problem, msg)
    }

    #[test]
    fn missing_and_corrupt_files_are_named() {
        let dir = tmpdir("bad");
        let missing = dir.join("nothing.h5");
        assert!(matches!(problem_of(&missing, None).0, Problem::Missing));
        let junk = dir.join("junk.h5");
        std::fs::write(&junk, b"this is not hdf5").unwrap();
        assert!(matches!(problem_of(&junk, None).0, Problem::Unreadable(_)));
        // A real file cut in half.
        let good = dir.join("good.h5");
        write_histories(&good, &tiny_file(2)).unwrap();
        let bytes = std::fs::read(&good).unwrap();
        let cut = dir.join("cut.h5");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let (p, msg) = problem_of(&cut, None);
        assert!(matches!(p, Problem::Damaged(_)), "{msg}");
        // One flipped bit anywhere after the user block: caught by the
        // checksum before libhdf5 parses anything.
        for at in [
            USER_BLOCK,
            USER_BLOCK + 100,
            bytes.len() / 2,
            bytes.len() - 1,
        ] {
            let mut b = bytes.clone();
            b[at] ^= 0x10;
            std::fs::write(&cut, &b).unwrap();
            let (p, msg) = problem_of(&cut, None);
            assert!(matches!(p, Problem::Damaged(_)), "byte {at}: {msg}");
            assert!(msg.contains("make it again with `icrl dataset`"), "{msg}");
        }
        // Without the checksum (a file written elsewhere) it still reads.
        let mut b = bytes.clone();
        b[..CHECKSUM_TAG.len()].fill(0);
        std::fs::write(&cut, &b).unwrap();
        assert_eq!(read_histories(&cut, None).unwrap(), tiny_file(2));
        std::fs::remove_dir_all(dir).unwrap();
    }

    /// Edits a written file through HDF5, then re-seals it (as a writer of
    /// such a file would have), so the reader's checks behind the checksum
    /// are what the test sees.
    fn edit(path: &Path, change: impl FnOnce(&hdf5::File)) {
        {
            let f = hdf5::File::open_rw(path).unwrap();
            change(&f);
        }
        seal(path).unwrap();
    }

    #[test]
    fn other_env_and_other_version_are_refused() {
        let dir = tmpdir("env");
        let path = dir.join("h.h5");
        write_histories(&path, &tiny_file(1)).unwrap();
        let (p, msg) = problem_of(&path, Some("point"));
        assert!(matches!(p, Problem::WrongEnv { .. }), "{msg}");
        assert!(msg.contains("darkroom") && msg.contains("point"), "{msg}");
        edit(&path, |f| {
            f.attr("format_version")
                .unwrap()
                .write_scalar(&99u32)
                .unwrap();
        });
        let (p, msg) = problem_of(&path, Some("darkroom"));
        assert!(
            matches!(
                p,
                Problem::WrongVersion {
                    found: 99,
                    expected: FORMAT_VERSION
                }
            ),
            "{msg}"
        );
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn macro_action_round_trips_and_old_mujoco_files_are_refused() {
        let dir = tmpdir("macro");
        let path = dir.join("h.h5");
        let mut file = tiny_file(1);
        // Relabelled as a Point file (the layout does not care what the
        // observations mean).
        file.info.env = "point".into();
        file.info.physics_steps_per_action = Some(50);
        write_histories(&path, &file).unwrap();
        let back = read_histories(&path, Some("point")).unwrap();
        assert_eq!(back.info.physics_steps_per_action, Some(50));
        // A file from before the attribute existed.
        edit(&path, |f| {
            f.delete_attr("physics_steps_per_action").unwrap()
        });
        let (p, msg) = problem_of(&path, Some("point"));
        assert!(matches!(p, Problem::UnrecordedMacroAction { .. }), "{msg}");
        assert!(
            msg.contains("5 physics steps") && msg.contains("icrl dataset --env point"),
            "{msg}"
        );
        // SafeDarkRoom has no physics: no attribute is fine.
        let path = dir.join("d.h5");
        write_histories(&path, &tiny_file(1)).unwrap();
        edit(&path, |f| {
            f.delete_attr("physics_steps_per_action").unwrap()
        });
        let back = read_histories(&path, Some("darkroom")).unwrap();
        assert_eq!(back.info.physics_steps_per_action, None);
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn empty_histories_are_refused_on_write_and_read() {
        let dir = tmpdir("empty");
        let path = dir.join("h.h5");
        let mut file = tiny_file(2);
        file.histories[1] = History::new(file.histories[1].task.clone(), 5.0);
        let e = write_histories(&path, &file).unwrap_err();
        assert!(matches!(e.problem, Problem::Empty(_)), "{e}");
        assert!(!path.exists() && !output::temp_path(&path).exists());
        // A file whose per-history table names a history without steps.
        let mut file = tiny_file(2);
        write_histories(&path, &file).unwrap();
        edit(&path, |f| {
            f.unlink("cost_limit").unwrap();
            put(f, "cost_limit", &[0.0f32, 2.5, 5.0], &[3]).unwrap();
            f.unlink("task_goal").unwrap();
            put(f, "task_goal", &[0i64; 6], &[3, 2]).unwrap();
            f.unlink("task_obstacles").unwrap();
            put(f, "task_obstacles", &[0i64; 150], &[3, 25, 2]).unwrap();
            f.attr("grid_histories")
                .unwrap()
                .write_scalar(&3u64)
                .unwrap();
        });
        let (p, msg) = problem_of(&path, None);
        assert!(matches!(p, Problem::Empty(_)), "{msg}");
        assert!(msg.contains("history 2"), "{msg}");
        // Two histories' steps out of order: named as such, not as a
        // history without steps.
        let shuffled = dir.join("shuffled.h5");
        write_histories(&shuffled, &tiny_file(2)).unwrap();
        edit(&shuffled, |f| {
            let mut ids: Vec<i64> = f.dataset("history_id").unwrap().read_raw().unwrap();
            let last = ids.len() - 1;
            ids.swap(0, last);
            f.unlink("history_id").unwrap();
            put(f, "history_id", &ids, &[ids.len()]).unwrap();
        });
        let (_, msg) = problem_of(&shuffled, None);
        assert!(
            msg.contains("history_id must be non-decreasing")
                && msg.contains("step 1 has id 0 after id 1"),
            "{msg}"
        );
        // A history that stops mid-episode cannot be written.
        file.histories[0].timeouts[4] = false;
        let e = write_histories(&path, &file).unwrap_err();
        assert!(matches!(e.problem, Problem::Invalid(_)), "{e}");
        std::fs::remove_dir_all(dir).unwrap();
    }

    /// Replaces dataset `name` of a written file with `data` (same shape).
    fn overwrite(path: &Path, name: &str, data: &[f32]) {
        edit(path, |f| {
            let shape = f.dataset(name).unwrap().shape();
            f.unlink(name).unwrap();
            put(f, name, data, &shape).unwrap();
        });
    }

    #[test]
    fn output_paths_are_checked_before_any_work() {
        let dir = tmpdir("out");
        let e = check_output_path(&dir, Existing::Refuse).unwrap_err();
        assert!(matches!(e.problem, Problem::Output(_)), "{e}");
        assert!(e.to_string().contains("it is a folder"), "{e}");
        assert!(
            !output::temp_path(&dir).exists(),
            "no DIR.tmp beside the folder"
        );
        let e = check_output_path(&dir.join("missing/h.h5"), Existing::Refuse)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("does not exist") && e.contains("mkdir -p"),
            "{e}"
        );
        check_output_path(&dir.join("h.h5"), Existing::Refuse).unwrap();
        assert!(
            !output::temp_path(&dir.join("h.h5")).exists(),
            "the probe is removed"
        );
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn non_finite_values_and_out_of_range_actions_are_refused() {
        let dir = tmpdir("values");
        let path = dir.join("h.h5");
        let file = tiny_file(2);
        // The writer refuses them ...
        let mut nan = file.clone();
        nan.histories[1].rewards[3] = f32::NAN;
        let e = write_histories(&path, &nan).unwrap_err().to_string();
        assert!(e.contains("history 1: rewards holds NaN at step 3"), "{e}");
        // ... and so does the reader, for files written elsewhere.
        write_histories(&path, &file).unwrap();
        let mut rewards: Vec<f32> = file
            .histories
            .iter()
            .flat_map(|h| h.rewards.clone())
            .collect();
        rewards[7] = f32::NAN;
        overwrite(&path, "rewards", &rewards);
        let (p, msg) = problem_of(&path, None);
        assert!(matches!(p, Problem::Malformed(_)), "{msg}");
        assert!(
            msg.contains("history 1: rewards holds NaN at step 2"),
            "{msg}"
        );
        write_histories(&path, &file).unwrap();
        let mut obs: Vec<f32> = file
            .histories
            .iter()
            .flat_map(|h| h.observations.clone())
            .collect();
        obs[1] = f32::INFINITY;
        overwrite(&path, "observations", &obs);
        let (_, msg) = problem_of(&path, None);
        assert!(msg.contains("observations holds inf at step 0"), "{msg}");
        // A negative cost, which would pay budget back.
        write_histories(&path, &file).unwrap();
        let mut costs: Vec<f32> = file
            .histories
            .iter()
            .flat_map(|h| h.costs.clone())
            .collect();
        costs[6] = -1.0;
        overwrite(&path, "costs", &costs);
        let (_, msg) = problem_of(&path, None);
        assert!(
            msg.contains("history 1: costs holds -1 at step 1 (costs must be non-negative)"),
            "{msg}"
        );
        // Action 17 in a 5-action space, and a fractional action.
        for (bad, shown) in [
            (17.0f32, "action 17 "),
            (1.5, "action 1.5 "),
            (-1.0, "action -1 "),
        ] {
            write_histories(&path, &file).unwrap();
            let mut actions: Vec<f32> = file
                .histories
                .iter()
                .flat_map(|h| h.actions.clone())
                .collect();
            actions[4] = bad;
            overwrite(&path, "actions", &actions);
            let (_, msg) = problem_of(&path, None);
            assert!(
                msg.contains(shown)
                    && msg.contains("at step 4 is not one of the 5 discrete actions 0..=4"),
                "{msg}"
            );
        }
        std::fs::remove_dir_all(dir).unwrap();
    }

    /// Opens a written file of `tiny_file(3)`'s histories with Python's
    /// h5py and checks names, shapes, dtypes and values; `merged`: every
    /// dataset is a virtual dataset over shards (no chunks or compression of
    /// its own). Fails (does not skip) when python3 or h5py is missing: the
    /// test set-up (`cargo xtask test`) installs h5py.
    pub(crate) fn h5py_check(path: &Path, merged: bool) {
        let script = r#"
import sys, h5py
f = h5py.File(sys.argv[1], "r")
merged = sys.argv[2] == "merged"
want = {
    "observations": ((15, 2), "float32"), "next_observations": ((15, 2), "float32"),
    "actions": ((15, 1), "float32"), "rewards": ((15,), "float32"), "costs": ((15,), "float32"),
    "terminals": ((15,), "float32"), "timeouts": ((15,), "float32"),
    "history_id": ((15,), "int64"), "episode_id": ((15,), "int64"),
    "cost_limit": ((3,), "float32"), "task_goal": ((3, 2), "int64"),
    "task_obstacles": ((3, 25, 2), "int64"),
}
assert set(f.keys()) == set(want), sorted(f.keys())
for name, (shape, dtype) in want.items():
    d = f[name]
    assert d.shape == shape and str(d.dtype) == dtype, (name, d.shape, d.dtype)
    if merged:
        assert d.is_virtual and len(d.virtual_sources()) == 3, (name, d.is_virtual)
    else:
        assert d.compression == "gzip" and d.chunks is not None, (name, d.compression, d.chunks)
a = f.attrs
assert a["env"] == "darkroom" and int(a["format_version"]) == 1 and int(a["seed"]) == 7, dict(a)
assert int(a["action_n"]) == 5 and int(a["obs_dim"]) == 2
assert int(a["physics_steps_per_action"]) == 0, dict(a)
assert int(a["grid_histories"]) == 3 and "shard_index" not in a, dict(a)
assert list(f["episode_id"][:5]) == [0, 0, 0, 1, 1]
assert list(f["history_id"][:]) == [0] * 5 + [1] * 5 + [2] * 5
assert float(f["rewards"][:].sum()) == 3.0
assert list(f["observations"][10]) == [20.0, -20.0], f["observations"][10]
assert list(f["cost_limit"][:]) == [0.0, 2.5, 5.0]
print("h5py ok")
"#;
        let out = std::process::Command::new("python3")
            .arg("-c")
            .arg(script)
            .arg(path)
            .arg(if merged { "merged" } else { "one" })
            .output();
        let out = match out {
            Ok(o) => o,
            Err(e) => {
                panic!("python3 is needed for this test (install it, then `pip install h5py`): {e}")
            }
        };
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            !stderr.contains("No module named 'h5py'"),
            "h5py is missing: run `pip install h5py` (cargo xtask test does): {stderr}"
        );
        assert!(out.status.success(), "h5py check failed: {stderr}");
    }

    #[test]
    fn h5py_reads_the_layout() {
        let dir = tmpdir("h5py");
        let path = dir.join("h.h5");
        write_histories(&path, &tiny_file(3)).unwrap();
        h5py_check(&path, false);
        std::fs::remove_dir_all(dir).unwrap();
    }
}
