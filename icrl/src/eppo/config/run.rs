//! `[run]`, `[tasks]` and `[model]`: the machine and the run's bookkeeping,
//! the trajectories collected, the network's shape.

use serde::{Deserialize, Serialize};

use crate::checkpoint::Retention;
use crate::guard::{Range, check_counts, check_numbers};
use crate::model;

use super::{EppoError, bad, parse_device};

/// `[run]`: the machine and the run's bookkeeping; none of it changes what
/// is learned but the seed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// Seed of every random choice (tasks, budgets, actions, libtorch).
    pub seed: u64,
    /// `cpu` or `cuda` (CUDA device 0).
    pub device: String,
    /// libtorch intra-op threads; 0 keeps libtorch's default (one per core).
    /// 1 is fastest for small-batch acting on a loaded machine, where OpenMP
    /// barriers between oversubscribed threads dominate each tiny operation.
    #[serde(default)]
    pub torch_threads: i32,
    /// Threads stepping the environments.
    pub env_threads: usize,
    // The loop's shape (issue 20): both together, so merges stay simple.
    /// Collect and learn at once on two threads (`overlap.rs`): an actor
    /// steps the environments with a copy of the policy, refreshed after
    /// every round's updates, one round behind the synchronous loop's; the
    /// learner updates meanwhile. The replay ratio holds whatever either
    /// side's speed, and a run stays deterministic under its seed. Wants
    /// `torch_threads = 1` on two cores. false: collect, then update.
    #[serde(default)]
    pub overlap: bool,
    /// Overlapped loop: libtorch threads of the learner's update (0:
    /// `torch_threads`); the actor keeps `torch_threads`. From 2 on, the
    /// target network's forward runs on a thread of its own beside the
    /// online forward, then the backward on all of them. Where the actor
    /// mostly waits (SafeDarkRoom; Car at 32 updates a round) 2 lends its
    /// core to the update: 1.45x SafeDarkRoom's updates/s, 1.30x Car's
    /// (BENCHMARKS.md).
    #[serde(default)]
    pub learner_threads: i32,
    /// Updates between checkpoints (one is always written at the end).
    pub checkpoint_every: u64,
    /// Checkpoints kept (0 keeps all).
    pub keep_checkpoints: usize,
    /// Besides the newest `keep_checkpoints`, keep every checkpoint written
    /// at a multiple of this many updates (0: none), to evaluate the run's
    /// history or fork from a good stretch that later training lost.
    #[serde(default)]
    pub keep_every: u64,
}

impl RunConfig {
    /// Threads in range, a checkpoint interval, a device libtorch has.
    pub fn validate(&self) -> Result<(), EppoError> {
        check_counts(&[
            ("env_threads", self.env_threads as i128),
            ("checkpoint_every", i128::from(self.checkpoint_every)),
        ])
        .or_else(bad)?;
        crate::guard::check_torch_threads(self.torch_threads).or_else(bad)?;
        if !(0..=1024).contains(&self.learner_threads) {
            return bad(format!(
                "learner_threads = {}: must be in [0, 1024] (0: torch_threads)",
                self.learner_threads
            ));
        }
        parse_device(&self.device)?;
        Ok(())
    }
}

/// `[tasks]`: the trajectories collected, each K episodes of one task
/// under one sampled budget.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TasksConfig {
    /// Environment time limit t_max in agent steps (Table 1 "Episode time
    /// limit t_max").
    pub max_episode_steps: usize,
    /// Fewest episodes per trajectory (Table 1 K_min).
    pub k_min: usize,
    /// Most episodes per trajectory (Table 1 K_max).
    pub k_max: usize,
    /// Smallest sampled per-episode cost budget (CTG_min).
    pub ctg_min: f32,
    /// Largest sampled per-episode cost budget (CTG_max); also scales CTG in the tokens.
    pub ctg_max: f32,
    /// Trajectories collected at once (one environment each, acted in one batch).
    pub n_envs: usize,
    /// Point and Car: MuJoCo physics steps per agent action (the macro
    /// action; 5 Safety-Gymnasium steps x 10 physics steps = 50 when absent).
    /// SafeDarkRoom has no physics: leave it out. Checkpoints record the
    /// resolved value; resuming with another is refused.
    #[serde(default = "default_physics_steps_per_action")]
    pub physics_steps_per_action: Option<usize>,
    /// Pretraining task pool: 0 draws a fresh task for every trajectory (the
    /// paper); n > 0 cycles over the first n task seeds (1: one fixed task,
    /// the first rung of the debugging ladder).
    #[serde(default)]
    pub task_pool: u64,
}

impl TasksConfig {
    /// Counts of at least 1, 1 <= K_min <= K_max, 0 <= CTG_min <= CTG_max.
    pub fn validate(&self) -> Result<(), EppoError> {
        check_counts(&[
            ("max_episode_steps", self.max_episode_steps as i128),
            ("k_min", self.k_min as i128),
            ("k_max", self.k_max as i128),
            ("n_envs", self.n_envs as i128),
            (
                "physics_steps_per_action",
                self.physics_steps_per_action.map_or(1, |n| n as i128),
            ),
        ])
        .or_else(bad)?;
        // Budgets are drawn between the two in float32: near its largest
        // value their difference overflows (trial 3's edge fuzz:
        // `ctg_max=3.4e38` panicked in the draw), and no episode costs
        // anywhere near a million.
        check_numbers(&[
            (
                "ctg_min",
                f64::from(self.ctg_min),
                Range::new(0.0, false, MOST_CTG, false),
            ),
            (
                "ctg_max",
                f64::from(self.ctg_max),
                Range::new(0.0, true, MOST_CTG, false),
            ),
        ])
        .or_else(bad)?;
        if self.k_min == 0 || self.k_min > self.k_max {
            return bad(format!(
                "need 1 <= k_min <= k_max, got k_min = {}, k_max = {}",
                self.k_min, self.k_max
            ));
        }
        if !(self.ctg_min >= 0.0 && self.ctg_min <= self.ctg_max && self.ctg_max > 0.0) {
            return bad(format!(
                "need 0 <= ctg_min <= ctg_max, ctg_max > 0; got {} and {}",
                self.ctg_min, self.ctg_max
            ));
        }
        Ok(())
    }

    /// The longest trajectory in steps, K_max x t_max.
    pub fn longest_trajectory(&self) -> usize {
        self.k_max.saturating_mul(self.max_episode_steps)
    }
}

/// `[model]`: the network's shape. The transformer's own settings
/// ([`model::Config`], Table 1's "Embedding Dim", "Num Layers", "Num
/// Heads", "Seq Len" and dropouts) sit in the same table as the MLPs
/// around it; a checkpoint's weights fit only this shape.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelConfig {
    /// The shared transformer; `max_len` is the sequence length.
    pub transformer: model::Config,
    /// Hidden width of the time-step encoder MLP.
    pub encoder_hidden: i64,
    /// Hidden width of the actor and critic heads.
    pub head_hidden: i64,
    /// Critics per ensemble (reward target: minimum over them; cost target: mean).
    pub n_critics: i64,
}

impl ModelConfig {
    /// The transformer's own checks, and widths of at least 1.
    pub fn validate(&self) -> Result<(), EppoError> {
        self.transformer.validate()?;
        check_counts(&[
            ("encoder_hidden", i128::from(self.encoder_hidden)),
            ("head_hidden", i128::from(self.head_hidden)),
            ("n_critics", i128::from(self.n_critics)),
        ])
        .or_else(bad)
    }
}

impl Serialize for ModelConfig {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        #[derive(Serialize)]
        struct Table<'a> {
            #[serde(flatten)]
            transformer: &'a model::Config,
            encoder_hidden: i64,
            head_hidden: i64,
            n_critics: i64,
        }
        Table {
            transformer: &self.transformer,
            encoder_hidden: self.encoder_hidden,
            head_hidden: self.head_hidden,
            n_critics: self.n_critics,
        }
        .serialize(s)
    }
}

impl<'de> Deserialize<'de> for ModelConfig {
    /// `[model]`'s own settings taken out, the rest is the transformer's
    /// (which refuses a key it does not know).
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let mut table = toml::Table::deserialize(d)?;
        let mut take = |key: &'static str| -> Result<i64, D::Error> {
            let value = table
                .remove(key)
                .ok_or_else(|| D::Error::missing_field(key))?;
            value
                .try_into::<i64>()
                .map_err(|e| D::Error::custom(format!("model.{key}: {e}")))
        };
        let (encoder_hidden, head_hidden, n_critics) = (
            take("encoder_hidden")?,
            take("head_hidden")?,
            take("n_critics")?,
        );
        let transformer = model::Config::deserialize(toml::Value::Table(table))
            .map_err(|e| D::Error::custom(format!("model: {e}")))?;
        Ok(ModelConfig {
            transformer,
            encoder_hidden,
            head_hidden,
            n_critics,
        })
    }
}

/// The largest cost budget (CTG_min, CTG_max) a run samples.
const MOST_CTG: f64 = 1e6;

/// Absent from a config: the environment's default macro action.
fn default_physics_steps_per_action() -> Option<usize> {
    None
}

impl RunConfig {
    /// Which checkpoints the run keeps.
    pub fn retention(&self) -> Retention {
        Retention {
            newest: self.keep_checkpoints,
            every: self.keep_every,
        }
    }
}
