//! `[goal]`: what pretraining tells the critics or shows the agent of the
//! goal, beyond the paper.

use serde::{Deserialize, Serialize};

use safety_envs::GoalShown;

use crate::guard::{Range, check_numbers};

use super::{EppoError, bad};

/// `[goal]`: what pretraining tells the critics or shows the agent of the
/// goal beyond the paper, each off when absent. The tokens, and so
/// everything at evaluation, stay as the paper's.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GoalConfig {
    /// Hindsight task relabelling (Packer et al., NeurIPS 2021): the share of
    /// sampled trajectories replayed as if the goal had been at a position
    /// they reached ([`relabel`]): rewards, terminations and episode ends
    /// recomputed, costs as recorded. It turns every trajectory into one
    /// that found a goal, and those that pass it again into revisits, the
    /// skill sparse rewards teach slowest. 0: off (the paper).
    pub relabel_prob: f64,
    /// A dense reward for the critics during pretraining only, after PEARL's
    /// sparse-reward point robot: each step's TD reward also gets this times
    /// the decrease in distance to the goal (potential-based shaping, which
    /// keeps the optimal policy). The tokens, and so the policy's context and
    /// everything at evaluation, stay sparse. 0: off (the paper).
    pub dense_reward_coef: f64,
    /// Pay `dense_reward_coef` only on steps whose context already holds a
    /// success (the goal found earlier in the window). Before that the goal
    /// is unknown to the agent, so progress toward it is noise the history
    /// cannot predict, and a critic paid for it drifts toward the centre of
    /// the pretraining goals instead of searching (rung b, rb1). After it,
    /// the dense reward teaches going back (rung r, rr8).
    pub dense_reward_after_goal: bool,
    /// An auxiliary loss for pretraining only: a head reads the goal's
    /// position off the trajectory encoding h_t at every step after the
    /// window's first success (the goal then sits in the context, as the
    /// observation its reward arrived with), weighted by this. Recalling a
    /// found goal is what revisiting needs, and a sparse reward teaches it
    /// slowly (results/eppo_point_ladder); this supervises it directly, as
    /// belief decoders do in meta-RL. The head adds to the checkpoint; the
    /// policy never reads it. 0: off (the paper).
    pub goal_recall_coef: f64,
    /// The ladder's goal-conditioned rung: the goal's position appended to
    /// every observation (`safety_envs::GoalShown`), so reaching it needs no
    /// memory; its success against the shown-goal rung's separates driving
    /// to a position from recalling one. Alone, such a checkpoint cannot be
    /// evaluated (the tasks hide the goal). Off in every preset.
    pub goal_in_observation: bool,
    /// With `goal_in_observation`: the share of trajectories whose goal
    /// slots are blanked (hidden) once `goal_hidden_ramp` ends, rising
    /// linearly from 0 across it. Car drives to a shown goal within 4000
    /// updates (cg1) but never learned to drive back to one it found; here one
    /// policy learns the first and must then read the goal from its context
    /// in a growing share of trajectories, the blank slots standing for
    /// "find it". A checkpoint trained with hidden goals is evaluated with
    /// the slots blank. 0: always shown.
    pub goal_hidden_share: f64,
    /// Environment steps `[from, until]` over which the hidden share rises
    /// from 0 to `goal_hidden_share` (environment steps, as the exploration
    /// schedule, so that collection alone decides it).
    pub goal_hidden_ramp: [u64; 2],
    /// The ladder's "return to a shown goal" rung: the first episode of every
    /// collected trajectory is driven to the goal by the environment's
    /// scripted controller (Point and Car), so the success of episodes 2..K
    /// measures revisiting alone. Off in every preset.
    pub scripted_first_episode: bool,
}

impl GoalConfig {
    /// Shares in [0, 1] and a rising ramp; a hidden share, and the dense
    /// reward's gate, only for what is on.
    pub fn validate(&self) -> Result<(), EppoError> {
        check_numbers(&[
            ("relabel_prob", self.relabel_prob, Range::UNIT),
            (
                "goal_recall_coef",
                self.goal_recall_coef,
                Range::NON_NEGATIVE,
            ),
            (
                "dense_reward_coef",
                self.dense_reward_coef,
                Range::NON_NEGATIVE,
            ),
            ("goal_hidden_share", self.goal_hidden_share, Range::UNIT),
        ])
        .or_else(bad)?;
        if self.dense_reward_after_goal && self.dense_reward_coef == 0.0 {
            return bad(
                "dense_reward_after_goal = true pays nothing with dense_reward_coef = 0: \
                 set dense_reward_coef > 0, or drop dense_reward_after_goal"
                    .to_string(),
            );
        }
        if self.goal_hidden_share > 0.0 && !self.goal_in_observation {
            return bad(
                "goal_hidden_share > 0 hides the goal slots of goal_in_observation in some \
                 trajectories: set goal_in_observation = true, or goal_hidden_share = 0"
                    .to_string(),
            );
        }
        if self.goal_hidden_ramp[0] > self.goal_hidden_ramp[1] {
            return bad(format!(
                "goal_hidden_ramp = {:?} must rise ([from, until] environment steps, from <= until)",
                self.goal_hidden_ramp
            ));
        }
        Ok(())
    }
}

impl GoalConfig {
    /// The share of trajectories collected after `env_steps` environment
    /// steps whose goal is hidden: `goal_hidden_share`, reached linearly
    /// across `goal_hidden_ramp`.
    pub fn goal_hidden_share_at(&self, env_steps: u64) -> f64 {
        let [from, until] = self.goal_hidden_ramp;
        let ramp = if env_steps >= until {
            1.0
        } else if env_steps <= from {
            0.0
        } else {
            (env_steps - from) as f64 / (until - from) as f64
        };
        self.goal_hidden_share * ramp
    }

    /// The entries appended to the environment's observation: the goal
    /// slots (`goal_in_observation`), or none. The agent fills them itself.
    pub fn shown_slots(&self) -> usize {
        if self.goal_in_observation {
            GoalShown::SLOTS
        } else {
            0
        }
    }

    /// Whether the shown goal slots are ever blanked, so that the agent can
    /// be evaluated with them blank.
    pub fn slots_ever_hidden(&self) -> bool {
        !self.goal_in_observation || self.goal_hidden_share > 0.0
    }
}
