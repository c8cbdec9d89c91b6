//! `[optimisation]` and `[targets]`: how the learner updates, and what its
//! critics learn from.

use serde::{Deserialize, Serialize};

use crate::guard::{Range, check_counts, check_numbers};

use super::{EppoError, bad};

/// `[optimisation]`: Adam and the update schedule.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OptimisationConfig {
    /// Adam learning rate (Table 1 "Learning Rate").
    pub lr: f64,
    /// Adam beta1 (Table 1 "Betas").
    pub beta1: f64,
    /// Adam beta2 (Table 1 "Betas").
    pub beta2: f64,
    /// Adam epsilon.
    pub adam_eps: f64,
    /// Global gradient-norm clip (Table 1 "Clip Grad").
    pub grad_clip: f64,
    /// Weight of the critic losses against the actor loss.
    pub critic_weight: f64,
    /// Trajectories per update batch (N; Table 1 "Batch Size").
    pub batch_size: usize,
    /// Updates to run in total (Table 1 "Num Updates").
    pub total_updates: u64,
    /// Updates after each collection round.
    pub updates_per_round: u64,
    /// Environment steps collected before the first update.
    pub learning_starts: u64,
    /// The replay ratio as updates per environment step: after each round
    /// the learner catches up to floor(replay_ratio x (env_steps -
    /// learning_starts)) updates in total. Absent: `updates_per_round`
    /// updates after each round (updates per collected trajectory =
    /// updates_per_round / n_envs), as in the paper's loop.
    #[serde(default)]
    pub replay_ratio: Option<f64>,
}

impl OptimisationConfig {
    /// Adam's numbers in range, counts of at least 1, and a replay ratio
    /// that reaches the last update in a bounded number of environment steps.
    pub fn validate(&self) -> Result<(), EppoError> {
        check_counts(&[
            ("batch_size", self.batch_size as i128),
            ("total_updates", i128::from(self.total_updates)),
            ("updates_per_round", i128::from(self.updates_per_round)),
        ])
        .or_else(bad)?;
        check_numbers(&[
            ("lr", self.lr, Range::UNIT_OPEN_LOW),
            ("beta1", self.beta1, Range::UNIT_OPEN_HIGH),
            ("beta2", self.beta2, Range::UNIT_OPEN_HIGH),
            // Added to float32 moments: below float32's smallest normal
            // number it rounds to 0, and 0 / 0 is NaN (trial 3's edge fuzz:
            // `adam_eps=1e-300` stopped on a NaN loss at update 2).
            (
                "adam_eps",
                self.adam_eps,
                Range::new(f32::MIN_POSITIVE as f64, false, 1.0, false),
            ),
            ("grad_clip", self.grad_clip, Range::POSITIVE),
            ("critic_weight", self.critic_weight, Range::POSITIVE),
        ])
        .or_else(bad)?;
        let Some(r) = self.replay_ratio else {
            return Ok(());
        };
        if !(r.is_finite() && r > 0.0) {
            return bad(format!(
                "replay_ratio = {r} must be a positive number (updates per environment step)"
            ));
        }
        // Bounded, so that no setting leaves the run waiting forever.
        let needed = self.learning_starts as f64 + self.total_updates as f64 / r;
        if needed > MOST_ENV_STEPS {
            return bad(format!(
                "replay_ratio = {r:e}: total_updates = {} would need {needed:.3e} environment \
                 steps, more than {MOST_ENV_STEPS:e}; raise it to at least {:.3e}",
                self.total_updates,
                self.total_updates as f64 / MOST_ENV_STEPS
            ));
        }
        Ok(())
    }
}

/// `[targets]`: the critics' TD targets, and the replay they are computed from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TargetsConfig {
    /// Discount factor gamma.
    pub gamma: f64,
    /// Value targets bootstrap across episode boundaries inside a trajectory
    /// (AMAGO's meta-RL view: the objective is the sum of all K returns).
    pub bootstrap_across_episodes: bool,
    /// Polyak factor of the target networks (target <- (1 - tau) target + tau online).
    pub tau: f64,
    /// Steps of real rewards in each TD target before bootstrapping (n-step
    /// returns, each step's sum stopping where its bootstrap mask stops):
    /// with sparse rewards and gamma near 1 a one-step target moves value
    /// (and corrects stale optimism) one step per target-network lag;
    /// n steps move it n times faster. 1: the paper's one-step target.
    #[serde(default = "default_n_step")]
    pub n_step: usize,
    /// Rewards are multiplied by this in the TD targets and the tokens.
    pub reward_scale: f64,
    /// Replay capacity in environment steps (whole trajectories are evicted,
    /// oldest first; Table 1 "Replay buffer capacity").
    pub replay_capacity: usize,
}

impl TargetsConfig {
    /// Gamma in [0, 1), tau in (0, 1], a reward scale far from overflow.
    pub fn validate(&self) -> Result<(), EppoError> {
        check_counts(&[
            ("replay_capacity", self.replay_capacity as i128),
            ("n_step", self.n_step as i128),
        ])
        .or_else(bad)?;
        check_numbers(&[
            ("gamma", self.gamma, Range::UNIT_OPEN_HIGH),
            ("tau", self.tau, Range::UNIT_OPEN_LOW),
            // Scaled rewards go into float32 tokens: keep them far from overflow.
            (
                "reward_scale",
                self.reward_scale,
                Range::new(0.0, true, 1e6, false),
            ),
        ])
        .or_else(bad)
    }
}

/// The most environment steps a run may need to reach its last update
/// (days of collection at the fastest environment's rate).
const MOST_ENV_STEPS: f64 = 1e10;

/// Absent from a config: one-step TD targets (the paper's).
fn default_n_step() -> usize {
    1
}
