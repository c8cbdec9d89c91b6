//! The histories in memory: a shard of the task x cost-limit grid, a
//! file's facts, one learning history, a whole file, and the checks every
//! history passes before it is written or after it is read.

use std::fmt;
use std::ops::Range;
use std::path::Path;
use std::str::FromStr;

use safety_envs::Task;
use serde::{Deserialize, Serialize};

use super::{HistoryError, Problem};

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
    pub(super) fn check(&self, i: usize, info: &DatasetInfo) -> Result<(), Problem> {
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
