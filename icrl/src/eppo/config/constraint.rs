//! `[constraint]`: how the cost budget acts, and when it starts.

use serde::{Deserialize, Serialize};

use crate::guard::{Range, check_numbers};

use super::{EppoError, bad};

/// `[constraint]`: how the cost budget acts, through the multiplier lambda
/// of Eq. (7) or a price in the critics' targets, and when it starts.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConstraintConfig {
    /// How the budget acts: through the actor's penalty lambda x Qc (on
    /// which steps), or in the critics' targets (issue 18, issue 19).
    #[serde(default)]
    pub penalty: PenaltyForm,
    /// Multiplier step size eta of Eq. (7).
    pub lambda_lr: f64,
    /// Cap lambda_max of the multiplier (Appendix C).
    pub lambda_max: f64,
    /// Initial multiplier.
    pub lambda_init: f64,
    /// Eq. (6)'s naive primal-dual solver instead of Eq. (7): one multiplier
    /// per episode index k, each moved by its own episode's excess C_k -
    /// delta alone (as RCPO does), and charged on that episode's steps. The
    /// paper's ablation against EPPO's one exact-penalty multiplier
    /// (Figure 5). Under `penalty = "hindsight"` only.
    #[serde(default)]
    pub per_episode_multipliers: bool,
    /// Updates before Eq. (7) starts moving lambda (it stays at `lambda_init`):
    /// the agent first learns to search and return to the goal, then the
    /// constraint prices its costs (a multiplier at its cap from the start
    /// stops search before it is learned; results/eppo_ladder).
    #[serde(default)]
    pub lambda_warmup_updates: u64,
    /// Past the warm-up, the constraint also waits for the training revisit
    /// rate, averaged over the last `constraint_revisit_rounds` rounds, to
    /// reach this (`multiplier::ConstraintStart`): a warm-up that ends on a
    /// measured skill, not a count. Absent: the count alone.
    #[serde(default)]
    pub constraint_after_revisit: Option<f64>,
    /// Rounds in `constraint_after_revisit`'s average.
    #[serde(default = "default_constraint_revisit_rounds")]
    pub constraint_revisit_rounds: usize,
    /// `penalty = "saute"` or `"excess"`: what each unit of cost paid after
    /// the budget is spent takes off that step's reward (under Saute, on top
    /// of its unsafe reward). 0 is Saute's constant, which leaves nothing
    /// to choose between actions once an episode is over budget, so small
    /// budgets came out the most costly (results/eppo_darkroom_budget, sa1).
    #[serde(default, alias = "saute_cost_price")]
    pub over_budget_cost_price: f64,
    /// Later prices: each `{ after = N, price = P }` charges P per unit of
    /// excess cost from N updates past the constraint's start on (N rising).
    /// A price high enough to make the budget bind at the start stops search
    /// on some training seeds, while the one that keeps it lets the budget
    /// slip; seed 0 passed the budget's claims with 0.5 at the start, 1.0
    /// from 5200 and 3.0 from 7200 updates on (results/eppo_darkroom_budget,
    /// dw1 -> dw1p -> dw1q).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub over_budget_price_schedule: Vec<PriceChange>,
}

impl ConstraintConfig {
    /// Multiplier settings of at least 0 (lambda_init <= lambda_max), a
    /// price only under the forms that charge one, and the multiplier held
    /// at 0 under those that price the budget in the critics' targets.
    pub fn validate(&self) -> Result<(), EppoError> {
        check_numbers(&[
            ("lambda_lr", self.lambda_lr, Range::NON_NEGATIVE),
            ("lambda_max", self.lambda_max, Range::NON_NEGATIVE),
            ("lambda_init", self.lambda_init, Range::NON_NEGATIVE),
            (
                "over_budget_cost_price",
                self.over_budget_cost_price,
                Range::NON_NEGATIVE,
            ),
        ])
        .or_else(bad)?;
        if self.lambda_init > self.lambda_max {
            return bad(format!(
                "need 0 <= lambda_init <= lambda_max; got {} and {}",
                self.lambda_init, self.lambda_max
            ));
        }
        self.validate_penalty()?;
        self.validate_schedule()?;
        if let Some(t) = self.constraint_after_revisit
            && !(t > 0.0 && t <= 1.0)
        {
            return bad(format!(
                "constraint_after_revisit = {t} is a revisit rate: set it in (0, 1], or drop it \
                 to start the constraint after lambda_warmup_updates alone"
            ));
        }
        if self.constraint_revisit_rounds == 0 {
            return bad(
                "constraint_revisit_rounds = 0 averages nothing: set it to 1 or more (20 by default)"
                    .to_string(),
            );
        }
        Ok(())
    }

    /// Whether lambda can be other than 0 (it starts above 0, or moves
    /// under a cap above 0).
    pub fn has_multiplier(&self) -> bool {
        self.lambda_init != 0.0 || (self.lambda_lr != 0.0 && self.lambda_max > 0.0)
    }

    /// What each penalty form takes: the multiplier, the price, the
    /// per-episode multipliers.
    fn validate_penalty(&self) -> Result<(), EppoError> {
        let priced_in_targets = matches!(self.penalty, PenaltyForm::Saute | PenaltyForm::Excess);
        if priced_in_targets && (self.lambda_init != 0.0 || self.lambda_lr != 0.0) {
            let form = match self.penalty {
                PenaltyForm::Saute => "saute",
                _ => "excess",
            };
            return bad(format!(
                "penalty = \"{form}\" prices the budget in the critics' targets, so the \
                 multiplier must stay at 0: set lambda_init = 0 and lambda_lr = 0"
            ));
        }
        if self.over_budget_cost_price > 0.0
            && !matches!(self.penalty, PenaltyForm::Saute | PenaltyForm::Excess)
        {
            return bad(format!(
                "over_budget_cost_price = {} is charged only under penalty = \"excess\" or \
                 \"saute\": set one of them, or set over_budget_cost_price = 0",
                self.over_budget_cost_price
            ));
        }
        if self.penalty == PenaltyForm::Excess && self.over_budget_cost_price <= 0.0 {
            return bad(format!(
                "penalty = \"excess\" with over_budget_cost_price = {} charges nothing past the \
                 budget: set over_budget_cost_price > 0 (1.0 prices a unit of excess cost \
                 like one goal)",
                self.over_budget_cost_price
            ));
        }
        if self.per_episode_multipliers && self.penalty != PenaltyForm::Hindsight {
            return bad(
                "per_episode_multipliers charges each episode's multiplier on its steps' hindsight \
                 flag: set penalty = \"hindsight\", or drop per_episode_multipliers"
                    .to_string(),
            );
        }
        Ok(())
    }

    /// Later prices only for a form that charges one, each finite and at
    /// least 0, their `after`s rising.
    fn validate_schedule(&self) -> Result<(), EppoError> {
        if self.over_budget_price_schedule.is_empty() {
            return Ok(());
        }
        if !matches!(self.penalty, PenaltyForm::Saute | PenaltyForm::Excess) {
            return bad(
                "over_budget_price_schedule changes the price that penalty = \"excess\" or \
                 \"saute\" charges: set one of them, or drop the schedule"
                    .to_string(),
            );
        }
        let afters = self.over_budget_price_schedule.iter().map(|c| c.after);
        if afters.clone().zip(afters.skip(1)).any(|(a, b)| a >= b) {
            return bad(
                "over_budget_price_schedule's `after` values must rise from one change to \
                 the next (updates since the constraint came on)"
                    .to_string(),
            );
        }
        if let Some(c) = self
            .over_budget_price_schedule
            .iter()
            .find(|c| !(c.price.is_finite() && c.price >= 0.0))
        {
            return bad(format!(
                "over_budget_price_schedule: price = {} after {} updates must be a finite \
                 number >= 0",
                c.price, c.after
            ));
        }
        Ok(())
    }
}

/// How the budget acts: where the actor pays lambda x reward_scale x Qc, or
/// what the critics' targets charge instead.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PenaltyForm {
    /// Algorithm 1: on every step of an episode that, in hindsight, ended over
    /// the budget (v_e), a flag the agent cannot see when it acts.
    #[default]
    Hindsight,
    /// At decision time: on the predicted remaining cost beyond the remaining
    /// budget, max(0, Qc(h_t, a) - CTG_t). Zero while the cost critic expects
    /// the episode to stay within its budget, whatever happened elsewhere.
    Hinge,
    /// Saute RL (Sootla et al., ICML 2022): no multiplier and no actor
    /// penalty. The remaining budget is already in every token (CTG_t), and
    /// once an episode's cost passes its budget the critics see an unsafe
    /// reward of -0.1, a tenth of a goal (less `over_budget_cost_price` per
    /// unit of cost), on each of its remaining steps instead of the reward,
    /// goal included: overspending loses the episode, whatever lambda would
    /// have been on this training seed.
    Saute,
    /// The exact penalty at a fixed price, charged where it is incurred: no
    /// multiplier and no actor penalty; every unit of cost paid past the
    /// episode's budget takes `over_budget_cost_price` off that step's reward
    /// in the critics' targets, the goal's reward kept. The episode's return
    /// is then R - price x max(0, C - budget), Eq. (5)'s penalty with lambda
    /// fixed. Saute's form, which also drops the goal once overspent, made a
    /// spent budget a reason to rush to the next episode (sa1, sa3).
    Excess,
    /// The early-terminated MDP of Sun et al. (2021, "Safe Exploration by
    /// Solving Early Terminated MDP"), over the K episodes: no multiplier and
    /// no actor penalty; the step that takes an episode's cost past its
    /// budget ends the value in the reward and novelty critics' targets (its
    /// own reward, nothing bootstrapped past it: Sun et al.'s r_e at 0, as
    /// every reward here is at least 0; pt2's -1 did not help).
    /// Overspending then forfeits every later episode's return, what a search
    /// past the budget would learn included: under a price, that knowledge
    /// kept search through hazards worth its cost (Point, pc1-pc7). The
    /// environment and the tokens go on, and the later steps, later episodes
    /// with fresh budgets among them, train as usual. With a multiplier
    /// (`lambda_lr`, `lambda_max` above 0) the actor also pays Eq. (7)'s
    /// `lambda v_e Q^c`, as under `hindsight`: a trajectory still searching
    /// has no return to forfeit, and it is the one that overspends (Point
    /// ladder, session 59).
    Terminate,
}

/// One step of `over_budget_price_schedule`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PriceChange {
    /// Updates since the constraint came on.
    pub after: u64,
    /// The price per unit of excess cost from then on.
    pub price: f64,
}

/// Absent from a config: 20 rounds in the revisit gate's average.
fn default_constraint_revisit_rounds() -> usize {
    20
}
