//! EPPO's hyperparameters ([`EppoConfig`]: nine sections of documented
//! fields, `[run]`, `[tasks]`, `[model]`, `[optimisation]`, `[targets]`,
//! `[constraint]`, `[exploration]`, `[novelty]` and `[goal]`), the flat form
//! of older configs moved into them ([`EppoConfig::SECTIONS`]), and what can
//! fail ([`EppoError`]); the checks run before anything is built
//! (validation, the device, the memory estimate) and the bilevel exploration
//! schedule ([`Exploration`]). This file holds the config, the checks across
//! sections and the errors; each section sits with its own checks in
//! `run.rs` (run, tasks, model), `learning.rs` (optimisation, targets),
//! `constraint.rs`, `search.rs` (exploration, novelty) and `goal.rs`;
//! `migrate.rs` reads the flat form, retired settings and `--set`s.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use tch::Device;
use thiserror::Error;

use safety_envs::EnvError;

use crate::checkpoint::CheckpointError;
use crate::model::ModelError;

mod constraint;
mod goal;
mod learning;
mod migrate;
mod run;
mod search;

pub use constraint::{ConstraintConfig, PenaltyForm, PriceChange};
pub use goal::GoalConfig;
pub use learning::{OptimisationConfig, TargetsConfig};
#[cfg(test)]
pub use migrate::{RETIRED, drop_retired};
pub use run::{ModelConfig, RunConfig, TasksConfig};
pub use search::{Exploration, ExplorationConfig, NoveltyBudget, NoveltyConfig};

/// Every EPPO hyperparameter (presets in `icrl/presets/eppo-*.toml`), by
/// concern. A setting's name is unique across the sections, so that
/// `--set lambda_max=1` finds `[constraint]` as `--set
/// constraint.lambda_max=1` does, and a flat config written before the
/// sections loads ([`EppoConfig::from_table`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EppoConfig {
    /// The machine and the run's bookkeeping: seed, device, threads, the
    /// loop's shape, checkpoints.
    pub run: RunConfig,
    /// The trajectories collected: tasks, episodes, budgets.
    pub tasks: TasksConfig,
    /// The network's shape: the transformer, the MLPs around it, the critics.
    pub model: ModelConfig,
    /// Adam and the update schedule: how many updates, how often, on what batches.
    pub optimisation: OptimisationConfig,
    /// The critics' TD targets and the replay they are computed from.
    pub targets: TargetsConfig,
    /// The cost budget: the multiplier of Eq. (7), or the price the critics
    /// charge instead, and when it starts.
    pub constraint: ConstraintConfig,
    /// Behaviour noise (bilevel epsilon) and the actor's entropy bonus.
    pub exploration: ExplorationConfig,
    /// The search bonus for cells new to a trajectory (pretraining only).
    #[serde(default)]
    pub novelty: NoveltyConfig,
    /// What pretraining tells the critics or shows the agent of the goal (and
    /// the hazards) beyond the paper: hindsight relabelling, a dense reward,
    /// a recall head, the goal or hazard map in the observation, a scripted
    /// first episode.
    #[serde(default)]
    pub goal: GoalConfig,
}

/// A setting that cannot run, as the error each validation returns.
fn bad(problem: String) -> Result<(), EppoError> {
    Err(EppoError::Config(problem))
}

/// A configuration that cannot run, a failing environment, model or checkpoint.
#[derive(Debug, Error)]
pub enum EppoError {
    #[error("eppo config: {0}")]
    Config(String),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error(transparent)]
    Torch(#[from] tch::TchError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// A loss or gradient became NaN or infinite, or libtorch's backward
    /// pass failed: the update was not applied.
    #[error(
        "update {update}: {what}; training stopped without applying it. {}",
        crate::checkpoint::last_good(.checkpoint, "lower lr, or check the settings")
    )]
    NonFinite {
        update: u64,
        what: String,
        checkpoint: Option<PathBuf>,
    },
    /// Stopped by SIGINT/SIGTERM after writing a checkpoint.
    #[error("interrupted after update {updates}: checkpoint written to {}", .checkpoint.display())]
    Interrupted { checkpoint: PathBuf, updates: u64 },
}

impl EppoConfig {
    /// Checks the values that would otherwise fail deep inside training:
    /// each section its own (every count at least 1, every number finite
    /// and in its range, named in the error), then the sizes that must fit
    /// across sections.
    pub fn validate(&self) -> Result<(), EppoError> {
        self.model.validate()?;
        self.run.validate()?;
        self.tasks.validate()?;
        self.optimisation.validate()?;
        self.targets.validate()?;
        self.constraint.validate()?;
        self.exploration.validate()?;
        self.novelty.validate()?;
        self.goal.validate()?;
        if self.novelty.novelty_budget == NoveltyBudget::WithinBudget
            && self.constraint.penalty != PenaltyForm::Excess
        {
            return bad(
                "novelty_budget = \"within_budget\" needs penalty = \"excess\" (it withholds \
                 the bonus on the steps that form prices): set it, or drop it"
                    .to_string(),
            );
        }
        // A trajectory fits the model and the replay; counts bounded by what
        // the run can use, so that no setting leaves it computing one update
        // for hours or waiting forever.
        let longest = self.tasks.longest_trajectory();
        let (k_max, t_max) = (self.tasks.k_max, self.tasks.max_episode_steps);
        let max_len = self.model.transformer.max_len;
        if longest as u128 > max_len as u128 {
            return bad(format!(
                "a trajectory of k_max * max_episode_steps = {k_max} * {t_max} = {longest} steps \
                 exceeds model.max_len = {max_len}"
            ));
        }
        let capacity = self.targets.replay_capacity;
        if capacity < longest {
            return bad(format!(
                "replay_capacity = {capacity} cannot hold one trajectory of {longest} steps"
            ));
        }
        if self.targets.n_step > longest {
            return bad(format!(
                "n_step = {}: at most k_max * max_episode_steps = {longest}, the longest \
                 trajectory (a target sums rewards inside one)",
                self.targets.n_step
            ));
        }
        if self.optimisation.learning_starts > capacity as u64 {
            return bad(format!(
                "learning_starts = {}: at most replay_capacity = {capacity} environment steps \
                 (updates would wait for more steps than the replay keeps)",
                self.optimisation.learning_starts
            ));
        }
        Ok(())
    }
}

/// `cpu` or `cuda` -> a libtorch device; `cuda` fails clearly without a GPU.
pub fn parse_device(name: &str) -> Result<Device, EppoError> {
    match name {
        "cpu" => Ok(Device::Cpu),
        "cuda" => {
            if tch::Cuda::is_available() {
                Ok(Device::Cuda(0))
            } else {
                Err(EppoError::Config(
                    "device = cuda but libtorch sees no CUDA device (this libtorch is CPU-only or no GPU is present); use --device cpu or link a CUDA libtorch (SPEC section 7)".into(),
                ))
            }
        }
        other => Err(EppoError::Config(format!(
            "device = {other:?}: expected cpu or cuda"
        ))),
    }
}
