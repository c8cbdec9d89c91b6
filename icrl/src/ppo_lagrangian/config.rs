//! PPO-Lagrangian's hyperparameters ([`PpoLagConfig`], one documented field
//! each), the paper's defaults and their validation.

use serde::{Deserialize, Serialize};

use super::PpoLagError;

/// PPO-Lagrangian hyperparameters (defaults: [`PpoLagConfig::darkroom`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PpoLagConfig {
    /// Environment steps of learning per run (the history's length before a
    /// trailing unfinished episode is dropped). SPEC: 50,000.
    pub total_steps: usize,
    /// Environments stepped together, all in the run's task; their episodes
    /// enter the history in the order they finish.
    pub num_envs: usize,
    /// Steps per environment in one rollout (one update per rollout).
    pub rollout_steps: usize,
    /// Width of the two hidden tanh layers of actor and critics.
    pub hidden: i64,
    /// Adam learning rate of actor and critics.
    pub learning_rate: f64,
    /// Decay the learning rate linearly to 0 over the run (CleanRL's `anneal_lr`).
    pub anneal_lr: bool,
    /// Discount of rewards.
    pub gamma: f64,
    /// Discount of costs.
    pub cost_gamma: f64,
    /// GAE lambda (rewards and costs).
    pub gae_lambda: f64,
    /// Passes over each rollout.
    pub update_epochs: usize,
    /// Minibatches per pass.
    pub minibatches: usize,
    /// PPO ratio clip.
    pub clip_coef: f64,
    /// Entropy bonus weight.
    pub ent_coef: f64,
    /// Weight of the two critic losses.
    pub vf_coef: f64,
    /// Global gradient-norm clip.
    pub max_grad_norm: f64,
    /// Normalise observations with running mean and variance (clipped to +-10).
    pub normalize_obs: bool,
    /// Initial Lagrange multiplier (OmniSafe: 0.001).
    pub lagrange_init: f64,
    /// Adam learning rate of the multiplier (OmniSafe: 0.035).
    pub lagrange_lr: f64,
    /// Upper bound of the multiplier.
    pub lagrange_max: f64,
    /// Initial log standard deviation of the Gaussian policy (continuous actions).
    pub init_log_std: f64,
}

impl PpoLagConfig {
    /// SafeDarkRoom: 50k steps, short rollouts so a run has about 200 updates.
    /// The multiplier's learning rate is above OmniSafe's 0.035 because it
    /// steps once per update, and a run has few updates; the entropy bonus
    /// keeps some exploration for the detours a zero cost limit needs.
    pub fn darkroom() -> Self {
        PpoLagConfig {
            total_steps: 50_000,
            num_envs: 4,
            rollout_steps: 64,
            hidden: 64,
            learning_rate: 1e-3,
            anneal_lr: true,
            gamma: 0.99,
            cost_gamma: 0.99,
            gae_lambda: 0.95,
            update_epochs: 4,
            minibatches: 4,
            clip_coef: 0.2,
            ent_coef: 0.02,
            vf_coef: 0.5,
            max_grad_norm: 0.5,
            normalize_obs: true,
            lagrange_init: 0.001,
            lagrange_lr: 0.1,
            lagrange_max: 100.0,
            init_log_std: -0.5,
        }
    }

    /// SafeDarkMujoco (Point, Car): longer rollouts, lower learning rate.
    pub fn mujoco() -> Self {
        PpoLagConfig {
            rollout_steps: 256,
            learning_rate: 3e-4,
            ent_coef: 0.0,
            ..Self::darkroom()
        }
    }

    /// Checks the sizes fit together and every number lies in its range
    /// (named in the error).
    pub fn validate(&self) -> Result<(), PpoLagError> {
        use crate::guard::{Range, check_counts, check_numbers};
        check_counts(&[
            ("total_steps", self.total_steps as i128),
            ("num_envs", self.num_envs as i128),
            ("rollout_steps", self.rollout_steps as i128),
            ("hidden", i128::from(self.hidden)),
            ("update_epochs", self.update_epochs as i128),
            ("minibatches", self.minibatches as i128),
        ])
        .map_err(PpoLagError::Config)?;
        check_numbers(&[
            ("learning_rate", self.learning_rate, Range::UNIT_OPEN_LOW),
            ("gamma", self.gamma, Range::UNIT),
            ("cost_gamma", self.cost_gamma, Range::UNIT),
            ("gae_lambda", self.gae_lambda, Range::UNIT),
            ("clip_coef", self.clip_coef, Range::POSITIVE),
            ("ent_coef", self.ent_coef, Range::NON_NEGATIVE),
            ("vf_coef", self.vf_coef, Range::POSITIVE),
            ("max_grad_norm", self.max_grad_norm, Range::POSITIVE),
            ("lagrange_init", self.lagrange_init, Range::NON_NEGATIVE),
            ("lagrange_lr", self.lagrange_lr, Range::NON_NEGATIVE),
            ("lagrange_max", self.lagrange_max, Range::NON_NEGATIVE),
            (
                "init_log_std",
                self.init_log_std,
                Range::new(-20.0, false, 2.0, false),
            ),
        ])
        .map_err(PpoLagError::Config)?;
        let batch = self.num_envs.saturating_mul(self.rollout_steps);
        if self.minibatches == 0 || !batch.is_multiple_of(self.minibatches) {
            return Err(PpoLagError::Config(format!(
                "minibatches ({}) must divide num_envs * rollout_steps ({batch})",
                self.minibatches
            )));
        }
        if !(0.0..=1.0).contains(&self.gamma) || !(0.0..=1.0).contains(&self.gae_lambda) {
            return Err(PpoLagError::Config(format!(
                "gamma ({}) and gae_lambda ({}) must lie in [0, 1]",
                self.gamma, self.gae_lambda
            )));
        }
        if self.lagrange_init < 0.0 || self.lagrange_max < self.lagrange_init {
            return Err(PpoLagError::Config(format!(
                "need 0 <= lagrange_init ({}) <= lagrange_max ({})",
                self.lagrange_init, self.lagrange_max
            )));
        }
        Ok(())
    }
}
