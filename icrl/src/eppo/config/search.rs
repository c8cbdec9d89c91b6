//! `[exploration]` and `[novelty]`: behaviour noise and the entropy bonus,
//! and the search bonus for new cells.

use serde::{Deserialize, Serialize};

use crate::guard::{Range, check_numbers};

use super::{EppoError, bad};

/// `[exploration]`: behaviour noise, bilevel after AMAGO, and the actor's
/// entropy bonus.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExplorationConfig {
    /// Exploration at a trajectory's first step, at the start of training:
    /// epsilon-greedy for discrete actions, added Gaussian noise of scale
    /// epsilon for continuous ones (`sample_actions`). Epsilon is bilevel, after AMAGO: it
    /// anneals over training and, inside each trajectory, moves linearly from
    /// its first-step value to its last-step value (`eps_last_*`).
    pub eps_start: f64,
    /// Epsilon at a trajectory's first step once annealed.
    pub eps_end: f64,
    /// Environment steps over which both ends anneal linearly.
    pub eps_decay_steps: u64,
    /// Epsilon at a trajectory's last step, at the start of training
    /// (absent: equal to `eps_start`, no decay inside a trajectory).
    #[serde(default)]
    pub eps_last_start: Option<f64>,
    /// Epsilon at a trajectory's last step once annealed (absent: `eps_end`).
    #[serde(default)]
    pub eps_last_end: Option<f64>,
    /// Scale each trajectory's epsilon by its own uniform draw in [0, 1]
    /// (AMAGO's `randomize_eps`): the replay then holds the whole range from
    /// near-on-policy to noisy trajectories.
    #[serde(default)]
    pub eps_random_scale: bool,
    /// Entropy bonus weight in the actor loss (the starting weight with
    /// `target_entropy`).
    pub entropy_coef: f64,
    /// SAC's automatic temperature: after every update the entropy weight
    /// moves in log space by `entropy_coef_lr` x (target - the batch's policy
    /// entropy), so the entropy tracks this target (nats, tanh-corrected for
    /// continuous actions; SAC uses -|A|). A fixed weight lets a continuous
    /// actor's mean run into tanh's saturation, where its gradient vanishes
    /// and the policy collapses onto the action bounds (results/
    /// eppo_point_ladder, rung rg2). Absent: `entropy_coef` stays fixed.
    #[serde(default)]
    pub target_entropy: Option<f64>,
    /// Step size of the entropy weight's log-space update.
    #[serde(default = "default_entropy_coef_lr")]
    pub entropy_coef_lr: f64,
}

impl ExplorationConfig {
    /// Every epsilon in [0, 1]; a tuned entropy weight that can move.
    pub fn validate(&self) -> Result<(), EppoError> {
        check_numbers(&[
            ("entropy_coef", self.entropy_coef, Range::NON_NEGATIVE),
            ("entropy_coef_lr", self.entropy_coef_lr, Range::NON_NEGATIVE),
            ("eps_start", self.eps_start, Range::UNIT),
            ("eps_end", self.eps_end, Range::UNIT),
        ])
        .or_else(bad)?;
        for (name, v) in [
            ("eps_last_start", self.eps_last_start),
            ("eps_last_end", self.eps_last_end),
        ] {
            if let Some(v) = v
                && !(0.0..=1.0).contains(&v)
            {
                return bad(format!("{name} = {v} must lie in [0, 1]"));
            }
        }
        if let Some(t) = self.target_entropy
            && !(t.is_finite() && self.entropy_coef > 0.0)
        {
            return bad(format!(
                "target_entropy = {t} needs a finite target and a positive starting \
                 entropy_coef (got {}): the weight moves in log space",
                self.entropy_coef
            ));
        }
        Ok(())
    }
}

/// `[novelty]`: a bonus for the critics during pretraining only, for cells
/// new to the trajectory. Absent: off (the paper).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NoveltyConfig {
    /// After HyperX's meta-training exploration bonuses: a step that
    /// arrives in a cell this trajectory has not visited earns this much
    /// reward, until the trajectory's first success. Before the goal is
    /// found any unseen cell may hold it; after, search is worth nothing, so
    /// revisits are not taxed. The tokens stay as collected. 0: off (the
    /// paper).
    pub novelty_bonus: f64,
    /// Side of a novelty cell in observation units (the position at
    /// observation indices 0 and 1): 1 (absent) is one SafeDarkRoom cell.
    /// Also the cell of the `search_new_cells` metric.
    pub novelty_cell: f64,
    /// The novelty bonus gets critics of its own, kept apart from the task's
    /// reward critics, and the actor weighs them only on steps whose context
    /// holds no success yet: once a goal is found, nothing of the search
    /// incentive reaches the steps that should drive back to it. In one
    /// shared critic, more pay for search cost the revisits on both domains
    /// (ps3, ps5, ps7, dn1). After RND's separate intrinsic value head.
    pub novelty_critic: bool,
    /// How the episode's budget gates the novelty bonus (issue 18). Paid
    /// everywhere, the bonus let search ignore the budget
    /// (results/eppo_darkroom_budget, ex4). Older configs'
    /// `novelty_within_budget = true` reads as `within_budget`.
    #[serde(
        alias = "novelty_within_budget",
        deserialize_with = "novelty_budget_or_bool"
    )]
    pub novelty_budget: NoveltyBudget,
}

impl NoveltyConfig {
    /// A bonus of at least 0 on cells of a positive side; its critics and
    /// its gate only with a bonus to pay.
    pub fn validate(&self) -> Result<(), EppoError> {
        check_numbers(&[
            ("novelty_bonus", self.novelty_bonus, Range::NON_NEGATIVE),
            ("novelty_cell", self.novelty_cell, Range::POSITIVE),
        ])
        .or_else(bad)?;
        if self.novelty_budget != NoveltyBudget::Always && self.novelty_bonus == 0.0 {
            return bad(
                "novelty_budget gates the novelty bonus, which is off (novelty_bonus = 0): set \
                 novelty_bonus > 0, or drop novelty_budget"
                    .to_string(),
            );
        }
        if self.novelty_critic && self.novelty_bonus == 0.0 {
            return bad(
                "novelty_critic learns the novelty bonus's value, which is off (novelty_bonus = \
                 0): set novelty_bonus > 0, or drop novelty_critic"
                    .to_string(),
            );
        }
        Ok(())
    }
}

impl Default for NoveltyConfig {
    /// No bonus; a cell of one SafeDarkRoom cell.
    fn default() -> Self {
        NoveltyConfig {
            novelty_bonus: 0.0,
            novelty_cell: 1.0,
            novelty_critic: false,
            novelty_budget: NoveltyBudget::Always,
        }
    }
}

/// How the episode's budget gates the novelty bonus.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NoveltyBudget {
    /// Paid on every novel step.
    #[default]
    Always,
    /// `penalty = "excess"`: withheld on the steps that leave the episode
    /// over budget, once the constraint is on (ex5: it did not help).
    WithinBudget,
    /// Scaled by the share of the episode's budget left before the step,
    /// clamp(CTG_t / budget, 0, 1): a larger budget funds a longer search,
    /// a spent one none, so search and its cost follow the budget.
    RemainingShare,
}

/// `novelty_budget`, or the older `novelty_within_budget` flag.
fn novelty_budget_or_bool<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<NoveltyBudget, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Either {
        Flag(bool),
        Form(NoveltyBudget),
    }
    Ok(match Either::deserialize(d)? {
        Either::Flag(true) => NoveltyBudget::WithinBudget,
        Either::Flag(false) => NoveltyBudget::Always,
        Either::Form(form) => form,
    })
}

fn default_entropy_coef_lr() -> f64 {
    0.003
}

/// The epsilon-greedy schedule inside one trajectory, at one point of training.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Exploration {
    /// Epsilon at the trajectory's first step.
    pub first: f64,
    /// Epsilon at its last possible step (K x t_max).
    pub last: f64,
}

impl Exploration {
    /// Epsilon at step `t` of a trajectory of at most `horizon` steps, scaled
    /// by the trajectory's own draw `scale` (1 without `eps_random_scale`).
    pub fn at(&self, t: usize, horizon: usize, scale: f64) -> f64 {
        let progress = (t as f64 / horizon.max(1) as f64).min(1.0);
        scale * (self.first + (self.last - self.first) * progress)
    }
}

impl ExplorationConfig {
    /// Both ends of the bilevel schedule after `env_steps` of training: each
    /// anneals linearly from its start to its end value over `eps_decay_steps`.
    pub fn schedule(&self, env_steps: u64) -> Exploration {
        let frac = (env_steps as f64 / self.eps_decay_steps.max(1) as f64).min(1.0);
        let anneal = |from: f64, to: f64| from + (to - from) * frac;
        Exploration {
            first: anneal(self.eps_start, self.eps_end),
            last: anneal(
                self.eps_last_start.unwrap_or(self.eps_start),
                self.eps_last_end.unwrap_or(self.eps_end),
            ),
        }
    }
}
