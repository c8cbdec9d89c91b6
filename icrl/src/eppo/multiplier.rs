//! The cost multiplier lambda of Eq. (7), an integrator,
//! lambda <- clip(lambda + eta g, 0, lambda_max), with g the batch mean of
//! each trajectory's max_k (C_k - delta), and when the constraint comes on.
//! (A PID Lagrangian and a late-episode violation signal were tried on the
//! grid and removed: `config/migrate.rs::RETIRED`.)

use serde::{Deserialize, Serialize};

use super::losses::lambda_update;

/// The multiplier's state, checkpointed with the run.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Multiplier {
    /// lambda as the losses use it (with per-episode multipliers, their mean,
    /// for the record).
    pub lambda: f64,
    /// `per_episode_multipliers`: Eq. (6)'s lambda_k, one per episode index.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub per_episode: Vec<f64>,
}

impl Multiplier {
    pub fn new(lambda: f64) -> Self {
        Multiplier {
            lambda,
            per_episode: Vec::new(),
        }
    }

    /// Eq. (6)'s multipliers for `episodes` episode indices, each starting at
    /// `lambda`.
    pub fn per_episode(lambda: f64, episodes: usize) -> Self {
        Multiplier {
            lambda,
            per_episode: vec![lambda; episodes],
        }
    }

    /// Eq. (7)'s step on a batch's per-trajectory violations with step size
    /// `eta` and cap `max`; an empty batch changes nothing.
    pub fn update(&mut self, violations: &[f32], eta: f64, max: f64) {
        self.lambda = lambda_update(self.lambda, violations, eta, max);
    }

    /// Eq. (6)'s step: each lambda_k moves by the batch mean of C_k - delta
    /// over the trajectories that hold an episode k (`excess[j][k]`), and on
    /// nothing else.
    pub fn update_per_episode(&mut self, excess: &[Vec<f32>], eta: f64, max: f64) {
        for (k, lambda) in self.per_episode.iter_mut().enumerate() {
            let at_k: Vec<f32> = excess.iter().filter_map(|e| e.get(k).copied()).collect();
            *lambda = lambda_update(*lambda, &at_k, eta, max);
        }
        if !self.per_episode.is_empty() {
            self.lambda = self.per_episode.iter().sum::<f64>() / self.per_episode.len() as f64;
        }
    }

    /// The multiplier each step is charged with, (B, L), from its episode
    /// index `episode` (B, L).
    pub fn per_step(&self, episode: &tch::Tensor) -> tch::Tensor {
        let lambdas: Vec<f32> = self.per_episode.iter().map(|&l| l as f32).collect();
        tch::Tensor::from_slice(&lambdas)
            .to_device(episode.device())
            .index_select(0, &episode.flatten(0, -1))
            .view_as(episode)
    }
}

/// When the constraint (the multiplier's updates, the over-budget price)
/// comes on: after `lambda_warmup_updates`, and, with
/// `constraint_after_revisit`, once the training revisit rate, averaged over
/// the last `constraint_revisit_rounds` rounds, reaches it. A count alone
/// prices search on some seeds before the agent has learned to come back to
/// a found goal, and then it never does (issue 18, dx1: revisit 0.47 when
/// the price came at 3000); a condition waits for the skill itself. Once on,
/// it stays on. Checkpointed, so a resumed run starts it where the
/// uninterrupted one would.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ConstraintStart {
    /// The update at which it came on (a measured start only).
    pub since: Option<u64>,
    /// The revisit rates of the latest rounds, oldest first.
    pub recent_revisits: Vec<f64>,
}

impl ConstraintStart {
    /// The update at which the constraint came on, if it acts at update
    /// `updates`.
    pub fn started_at(&self, updates: u64, warmup: u64, after_revisit: Option<f64>) -> Option<u64> {
        match after_revisit {
            None => (updates >= warmup).then_some(warmup),
            Some(_) => self.since,
        }
    }

    /// Takes one collection round's revisit rate (NaN when no trajectory
    /// found the goal before its last episode: not counted) and starts the
    /// constraint once the window's mean reaches `threshold`.
    pub fn observe(
        &mut self,
        revisit_rate: f64,
        updates: u64,
        warmup: u64,
        threshold: f64,
        rounds: usize,
    ) {
        if self.since.is_some() {
            return;
        }
        if revisit_rate.is_finite() {
            self.recent_revisits.push(revisit_rate);
            let excess = self.recent_revisits.len().saturating_sub(rounds);
            self.recent_revisits.drain(..excess);
        }
        let full = self.recent_revisits.len() == rounds;
        let mean = self.recent_revisits.iter().sum::<f64>() / rounds as f64;
        if updates >= warmup && full && mean >= threshold {
            self.since = Some(updates);
        }
    }
}
