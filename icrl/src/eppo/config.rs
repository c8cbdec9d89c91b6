//! EPPO's hyperparameters ([`EppoConfig`]: nine sections of documented
//! fields, `[run]`, `[tasks]`, `[model]`, `[optimisation]`, `[targets]`,
//! `[constraint]`, `[exploration]`, `[novelty]` and `[goal]`), the flat form
//! of older configs moved into them ([`EppoConfig::SECTIONS`]), and what can
//! fail ([`EppoError`]); the checks run before anything is built
//! (validation, the device, the memory estimate) and the bilevel exploration
//! schedule ([`Exploration`]).

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use tch::Device;
use thiserror::Error;

use safety_envs::{EnvError, EnvName, GoalShown, HazardsShown, spawn_config};

use crate::checkpoint::{CheckpointError, Retention};
use crate::guard::{Range, check_counts, check_numbers};
use crate::model::{self, ModelError};

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
        check_numbers(&[
            ("ctg_min", f64::from(self.ctg_min), Range::NON_NEGATIVE),
            ("ctg_max", f64::from(self.ctg_max), Range::POSITIVE),
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
            ("adam_eps", self.adam_eps, Range::UNIT_OPEN_LOW),
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
    /// `penalty = "terminate"`: the reward the critics see on top of the step
    /// where their value ends, the step that overspends. Sun et al.'s r_e,
    /// at most 0: every reward here is at least 0, so ending the value
    /// already costs what the rest of the trajectory was worth.
    #[serde(default)]
    pub termination_reward: f64,
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
            (
                "termination_reward",
                self.termination_reward,
                Range::new(f64::NEG_INFINITY, true, 0.0, false),
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

    /// What each penalty form takes: the multiplier, the price, the
    /// termination's reward, the per-episode multipliers.
    fn validate_penalty(&self) -> Result<(), EppoError> {
        let priced_in_targets = matches!(
            self.penalty,
            PenaltyForm::Saute | PenaltyForm::Excess | PenaltyForm::Terminate
        );
        if priced_in_targets && (self.lambda_init != 0.0 || self.lambda_lr != 0.0) {
            let form = match self.penalty {
                PenaltyForm::Saute => "saute",
                PenaltyForm::Excess => "excess",
                _ => "terminate",
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
        if self.termination_reward != 0.0 && self.penalty != PenaltyForm::Terminate {
            return bad(format!(
                "termination_reward = {} is the reward where penalty = \"terminate\" ends the \
                 critics' value, and penalty is not \"terminate\": set it, or drop \
                 termination_reward",
                self.termination_reward
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

/// `[goal]`: what pretraining tells the critics or shows the agent of the
/// goal (and the hazards) beyond the paper, each off when absent. The
/// tokens, and so everything at evaluation, stay as the paper's.
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
    /// The robots' ladder's hazard rung: the task's hazard cells appended to
    /// every observation as a map (`safety_envs::HazardsShown`), so that the
    /// policy can route around hazards it has not paid for. Not with
    /// `goal_in_observation` (one kind of slots at a time). Alone, such a
    /// checkpoint cannot be evaluated (the tasks hide the map).
    pub hazards_in_observation: bool,
    /// With `hazards_in_observation`: the share of trajectories whose map is
    /// blanked once `hazard_hidden_ramp` ends, rising linearly from 0 across
    /// it, as `goal_hidden_share` does for the goal: routing around a shown
    /// hazard is learned first, around one the context holds second. A
    /// checkpoint trained with hidden maps is evaluated with the map blank.
    pub hazard_hidden_share: f64,
    /// Environment steps `[from, until]` over which the hidden share rises
    /// from 0 to `hazard_hidden_share`.
    pub hazard_hidden_ramp: [u64; 2],
    /// The ladder's "return to a shown goal" rung: the first episode of every
    /// collected trajectory is driven to the goal by the environment's
    /// scripted controller (Point and Car), so the success of episodes 2..K
    /// measures revisiting alone. Off in every preset.
    pub scripted_first_episode: bool,
}

impl GoalConfig {
    /// Shares in [0, 1] and rising ramps; a hidden share, and the dense
    /// reward's gate, only for what is on; one kind of shown slots at a time.
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
            ("hazard_hidden_share", self.hazard_hidden_share, Range::UNIT),
        ])
        .or_else(bad)?;
        if self.dense_reward_after_goal && self.dense_reward_coef == 0.0 {
            return bad(
                "dense_reward_after_goal = true pays nothing with dense_reward_coef = 0: \
                 set dense_reward_coef > 0, or drop dense_reward_after_goal"
                    .to_string(),
            );
        }
        if self.hazards_in_observation && self.goal_in_observation {
            return bad(
                "hazards_in_observation and goal_in_observation both append slots to the observation: set one of them to false"
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
        if self.hazard_hidden_share > 0.0 && !self.hazards_in_observation {
            return bad(
                "hazard_hidden_share > 0 hides the hazard map of hazards_in_observation in some trajectories: set hazards_in_observation = true, or hazard_hidden_share = 0"
                    .to_string(),
            );
        }
        if self.hazard_hidden_ramp[0] > self.hazard_hidden_ramp[1] {
            return bad(format!(
                "hazard_hidden_ramp = {:?} must rise ([from, until] environment steps, from <= until)",
                self.hazard_hidden_ramp
            ));
        }
        Ok(())
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
    /// own reward plus `termination_reward`, nothing bootstrapped past it).
    /// Overspending then forfeits every later episode's return, what a search
    /// past the budget would learn included: under a price, that knowledge
    /// kept search through hazards worth its cost (Point, pc1-pc7). The
    /// environment and the tokens go on, and the later steps, later episodes
    /// with fresh budgets among them, train as usual.
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

/// A setting that cannot run, as the error each validation returns.
fn bad(problem: String) -> Result<(), EppoError> {
    Err(EppoError::Config(problem))
}

/// The most environment steps a run may need to reach its last update
/// (days of collection at the fastest environment's rate).
const MOST_ENV_STEPS: f64 = 1e10;

/// 0 before `[from, until]`, 1 after, linear across it.
fn ramp_at([from, until]: [u64; 2], env_steps: u64) -> f64 {
    if env_steps >= until {
        1.0
    } else if env_steps <= from {
        0.0
    } else {
        (env_steps - from) as f64 / (until - from) as f64
    }
}

/// Absent from a config: 20 rounds in the revisit gate's average.
fn default_constraint_revisit_rounds() -> usize {
    20
}

fn default_entropy_coef_lr() -> f64 {
    0.003
}

/// Absent from a config: one-step TD targets (the paper's).
fn default_n_step() -> usize {
    1
}

/// Absent from a config: the environment's default macro action.
fn default_physics_steps_per_action() -> Option<usize> {
    None
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

/// Settings tried by a ladder, measured as not helping, and removed with
/// their code: each with the value at which it did nothing, or that the code
/// now holds fixed (`None`: it acted only through another retired setting),
/// and the last commit that had it (`git checkout` it to rerun such a config). A config written before the
/// removal still loads where it holds one at that value; one that used it is
/// refused by name.
pub const RETIRED: [(&str, Option<&str>, &str); 21] = [
    // The PID Lagrangian (results/eppo_darkroom_budget, issue 18).
    ("lambda_kp", Some("0.0"), PID_AND_LATE_RATE),
    ("lambda_kd", Some("0.0"), PID_AND_LATE_RATE),
    ("lambda_smoothing", None, PID_AND_LATE_RATE),
    // The late-episode over-budget rate as the multiplier's signal (lr1, lr2).
    (
        "violation_signal",
        Some("\"worst_excess\""),
        PID_AND_LATE_RATE,
    ),
    ("lambda_target_rate", None, PID_AND_LATE_RATE),
    // The actor's loss reshaped (results/eppo_ladder r3 and the Point ladder):
    // its encoder detached, and AMAGO's filtered behaviour cloning.
    ("actor_detach_encoder", Some("false"), ACTOR_AND_ANNEAL),
    ("bc_coef", Some("0.0"), ACTOR_AND_ANNEAL),
    // The novelty bonus annealed to 0 over training (Point ps6).
    ("novelty_anneal_updates", Some("0"), ACTOR_AND_ANNEAL),
    // A head reading where earlier costs were paid off the encoding (Point
    // pe2: it cost the return trip).
    ("hazard_recall_coef", Some("0.0"), HAZARD_RECALL),
    // The novelty bonus rising with the episode index (dn1, Point ps7) and
    // scaled by the distance from the episode's start (Car cd1, cd2).
    ("novelty_rise", Some("0.0"), NOVELTY_SHAPES_AND_RAMP),
    (
        "novelty_distance_scale",
        Some("0.0"),
        NOVELTY_SHAPES_AND_RAMP,
    ),
    // The over-budget price moved linearly rather than in steps (dw2u).
    (
        "over_budget_price_ramp",
        Some("false"),
        NOVELTY_SHAPES_AND_RAMP,
    ),
    // Behaviour noise capped once the trajectory has found its goal
    // (results/eppo_darkroom_budget ls1; a ceiling of 1 caps nothing).
    ("eps_after_success", Some("1.0"), SEARCH_AND_PRICE_VARIANTS),
    // A share of the first episodes scripted to the goal, the rest searching
    // (Point rb4-rb7, Car cb2 and cs9: the car repeated its first episode).
    ("scripted_share", Some("1.0"), SEARCH_AND_PRICE_VARIANTS),
    // Observations standardised by a random policy's statistics (Point rn1),
    // and each step's index within its episode in the token (built for
    // Point's return trip, never run by a ladder).
    (
        "standardise_observations",
        Some("false"),
        SEARCH_AND_PRICE_VARIANTS,
    ),
    (
        "episode_positions",
        Some("false"),
        SEARCH_AND_PRICE_VARIANTS,
    ),
    // The novelty critics charged the over-budget price (Point pc5, pc7) and
    // paid past the first success (Point ps9, ps10, Car cs7).
    (
        "novelty_pays_price",
        Some("false"),
        SEARCH_AND_PRICE_VARIANTS,
    ),
    (
        "novelty_through_success",
        Some("false"),
        SEARCH_AND_PRICE_VARIANTS,
    ),
    // Saute's unsafe reward other than its default -0.1, now fixed
    // (results/eppo_darkroom_budget sa3-sa5).
    (
        "saute_unsafe_reward",
        Some("-0.1"),
        SEARCH_AND_PRICE_VARIANTS,
    ),
    // The termination sparing the novelty critics' value (Point pt5), and the
    // price or termination narrowed to repeated costs (Point pc7, pt4).
    (
        "termination_spares_search",
        Some("false"),
        SEARCH_AND_PRICE_VARIANTS,
    ),
    ("repeat_cost_radius", Some("0.0"), SEARCH_AND_PRICE_VARIANTS),
];

const PID_AND_LATE_RATE: &str = "b1f1bdb663c9833aefcfffa79f077dcd3d455b0b";
const ACTOR_AND_ANNEAL: &str = "db40554803feeb6dadd0adc8842796b03fa193c4";
const HAZARD_RECALL: &str = "8a5cee241507924037a24029831611b616eec709";
const NOVELTY_SHAPES_AND_RAMP: &str = "1096eed9892161592b2878611d3cef89371e88d3";
const SEARCH_AND_PRICE_VARIANTS: &str = "9441cf84b763fafdac321359355efe089241a33d";

/// Drops the [`RETIRED`] settings of `table`, flat or in a section, that
/// hold their inert value; refuses one that does not, naming it.
pub fn drop_retired(table: &mut toml::Table) -> Result<(), String> {
    drop_retired_from(table)?;
    for (section, _) in EppoConfig::SECTIONS {
        if let Some(toml::Value::Table(settings)) = table.get_mut(section) {
            drop_retired_from(settings)?;
        }
    }
    Ok(())
}

/// [`drop_retired`] on one level of a table.
fn drop_retired_from(table: &mut toml::Table) -> Result<(), String> {
    for (key, inert, commit) in RETIRED {
        let Some(value) = table.get(key) else {
            continue;
        };
        let inert = inert.map(|text| {
            toml::from_str::<toml::Table>(&format!("v = {text}"))
                .expect("RETIRED holds TOML values")["v"]
                .clone()
        });
        let number = |v: &toml::Value| v.as_float().or(v.as_integer().map(|i| i as f64));
        let did_nothing = match &inert {
            None => true,
            Some(inert) => match (number(value), number(inert)) {
                (Some(a), Some(b)) => a == b,
                _ => value == inert,
            },
        };
        if !did_nothing {
            return Err(format!(
                "{key} = {value} is a setting removed after its runs showed it did not help \
                 (the ladders under results/ record them): drop it to train without it, or check \
                 out commit {commit}, the last that had it, to rerun this config as it was"
            ));
        }
        table.remove(key);
    }
    Ok(())
}

impl EppoConfig {
    /// Every setting by its section, in one place: a flat config (every
    /// config written before the sections) is moved into them by
    /// [`EppoConfig::migrate`], and `--set NAME=VALUE` finds NAME's section
    /// here ([`EppoConfig::apply_sets`]). Names are unique across sections.
    /// The transformer's own settings are `model.NAME` in both forms; the
    /// older names `saute_cost_price` and `novelty_within_budget`, which
    /// their fields still read, move with them.
    pub const SECTIONS: [(&'static str, &'static [&'static str]); 9] = [
        (
            "run",
            &[
                "seed",
                "device",
                "torch_threads",
                "env_threads",
                "overlap",
                "learner_threads",
                "checkpoint_every",
                "keep_checkpoints",
                "keep_every",
            ],
        ),
        (
            "tasks",
            &[
                "max_episode_steps",
                "k_min",
                "k_max",
                "ctg_min",
                "ctg_max",
                "n_envs",
                "physics_steps_per_action",
                "task_pool",
            ],
        ),
        ("model", &["encoder_hidden", "head_hidden", "n_critics"]),
        (
            "optimisation",
            &[
                "lr",
                "beta1",
                "beta2",
                "adam_eps",
                "grad_clip",
                "critic_weight",
                "batch_size",
                "total_updates",
                "updates_per_round",
                "learning_starts",
                "replay_ratio",
            ],
        ),
        (
            "targets",
            &[
                "gamma",
                "bootstrap_across_episodes",
                "tau",
                "n_step",
                "reward_scale",
                "replay_capacity",
            ],
        ),
        (
            "constraint",
            &[
                "penalty",
                "lambda_lr",
                "lambda_max",
                "lambda_init",
                "per_episode_multipliers",
                "lambda_warmup_updates",
                "constraint_after_revisit",
                "constraint_revisit_rounds",
                "over_budget_cost_price",
                "saute_cost_price",
                "over_budget_price_schedule",
                "termination_reward",
            ],
        ),
        (
            "exploration",
            &[
                "eps_start",
                "eps_end",
                "eps_decay_steps",
                "eps_last_start",
                "eps_last_end",
                "eps_random_scale",
                "entropy_coef",
                "target_entropy",
                "entropy_coef_lr",
            ],
        ),
        (
            "novelty",
            &[
                "novelty_bonus",
                "novelty_cell",
                "novelty_critic",
                "novelty_budget",
                "novelty_within_budget",
            ],
        ),
        (
            "goal",
            &[
                "relabel_prob",
                "dense_reward_coef",
                "dense_reward_after_goal",
                "goal_recall_coef",
                "goal_in_observation",
                "goal_hidden_share",
                "goal_hidden_ramp",
                "hazards_in_observation",
                "hazard_hidden_share",
                "hazard_hidden_ramp",
                "scripted_first_episode",
            ],
        ),
    ];

    /// The section that holds setting `name` ([`EppoConfig::SECTIONS`]).
    pub fn section_of(name: &str) -> Option<&'static str> {
        Self::SECTIONS
            .iter()
            .find(|(_, names)| names.contains(&name))
            .map(|(section, _)| *section)
    }

    /// Moves each setting of a flat config into its section (the sectioned
    /// form is left as it is; a mix of both is read too). Refuses, by name,
    /// a setting given twice (flat and in its section) or in a section not
    /// its own. Names of no section (retired or unknown) stay where they
    /// are, for [`EppoConfig::from_table`] to drop or refuse.
    pub fn migrate(table: &mut toml::Table) -> Result<(), String> {
        for (section, _) in Self::SECTIONS {
            let Some(settings) = table.get(section).and_then(toml::Value::as_table) else {
                continue;
            };
            if let Some((key, own)) = settings
                .keys()
                .find_map(|key| Some((key, Self::section_of(key)?)).filter(|(_, s)| s != &section))
            {
                return Err(format!(
                    "[{section}] holds {key}, a setting of [{own}]: move it there"
                ));
            }
        }
        let flat: Vec<String> = table
            .keys()
            .filter(|key| Self::section_of(key).is_some())
            .cloned()
            .collect();
        for key in flat {
            let section = Self::section_of(&key).expect("filtered on it");
            let value = table.remove(&key).expect("a key of the table");
            let entry = table
                .entry(section)
                .or_insert_with(|| toml::Value::Table(toml::Table::new()));
            let Some(settings) = entry.as_table_mut() else {
                return Err(format!(
                    "{section} = {entry} must be a table of settings ([{section}])"
                ));
            };
            if settings.contains_key(&key) {
                return Err(format!(
                    "{key} is set twice, at the top (the flat form of older configs) and in \
                     [{section}]: keep one"
                ));
            }
            settings.insert(key, value);
        }
        Ok(())
    }

    /// `--set NAME=VALUE`s on an EPPO config's table, flat or sectioned:
    /// the table moves into sections ([`EppoConfig::migrate`]), then a NAME
    /// of [`EppoConfig::SECTIONS`] applies in its section (`lambda_max=1` as
    /// `constraint.lambda_max=1`), a dotted one (`model.n_layers=2`,
    /// `constraint.lambda_max=1`) as it is, and any other at the top, where
    /// [`EppoConfig::from_table`] refuses it by name.
    pub fn apply_sets(table: &mut toml::Table, sets: &[String]) -> Result<(), EppoError> {
        Self::migrate(table).map_err(EppoError::Config)?;
        let mut sets = sets.to_vec();
        for set in &mut sets {
            let Some((key, value)) = set.split_once('=') else {
                continue; // refused by apply_overrides, as given
            };
            let key = key.trim();
            let section = match (Self::section_of(key), key.split_once('.')) {
                (Some(section), _) => {
                    *set = format!("{section}.{key}={value}");
                    section
                }
                (None, Some((section, _))) => section,
                (None, None) => continue,
            };
            // The optional sections may be absent.
            if Self::SECTIONS.iter().any(|(s, _)| *s == section) {
                table
                    .entry(section)
                    .or_insert_with(|| toml::Value::Table(toml::Table::new()));
            }
        }
        crate::presets::apply_overrides(table, &sets).map_err(|e| EppoError::Config(e.to_string()))
    }

    /// The value of setting `name` in a config's table, flat or sectioned
    /// (any other table: its own `name`).
    pub fn setting<'a>(table: &'a toml::Table, name: &str) -> Option<&'a toml::Value> {
        table
            .get(name)
            .or_else(|| table.get(Self::section_of(name)?)?.get(name))
    }

    /// A setting's name as `--set` and messages give it: `lambda_max` for
    /// `constraint.lambda_max`; the transformer's `model.d_model`, and any
    /// other name, as it is.
    pub fn flat_name(dotted: &str) -> &str {
        match dotted.split_once('.') {
            Some((section, name)) if Self::section_of(name) == Some(section) => name,
            _ => dotted,
        }
    }

    /// A config from a TOML table (a preset with its `--set`s, or a run's
    /// `config.toml`), in sections or in the flat form written before them
    /// ([`EppoConfig::migrate`]), and before or after the [`RETIRED`]
    /// settings went. An unknown name is refused with the valid ones.
    /// `name` says where the table came from, in errors.
    pub fn from_table(name: &str, mut table: toml::Table) -> Result<Self, EppoError> {
        let refuse = |e: String| EppoError::Config(format!("{name}: {e}"));
        drop_retired(&mut table).map_err(refuse)?;
        Self::migrate(&mut table).map_err(refuse)?;
        if let Some(key) = table
            .keys()
            .find(|key| Self::SECTIONS.iter().all(|(section, _)| section != key))
        {
            let known: Vec<String> = Self::SECTIONS
                .iter()
                .map(|(section, names)| format!("[{section}] {}", names.join(", ")))
                .collect();
            return Err(refuse(format!(
                "unknown setting {key:?}; the settings, flat or in their sections, are: {} \
                 (and the transformer's in [model])",
                known.join("; ")
            )));
        }
        crate::presets::resolve::<EppoConfig>(name, table)
            .map_err(|e| EppoError::Config(e.to_string()))
    }
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

impl RunConfig {
    /// Which checkpoints the run keeps.
    pub fn retention(&self) -> Retention {
        Retention {
            newest: self.keep_checkpoints,
            every: self.keep_every,
        }
    }
}

impl GoalConfig {
    /// The share of trajectories collected after `env_steps` environment
    /// steps whose goal is hidden (`goal_hidden_share`, `goal_hidden_ramp`).
    pub fn goal_hidden_share_at(&self, env_steps: u64) -> f64 {
        self.goal_hidden_share * ramp_at(self.goal_hidden_ramp, env_steps)
    }

    /// The entries appended to `env`'s observation: the goal slots
    /// (`goal_in_observation`), the hazard map (`hazards_in_observation`),
    /// or none. The agent fills them itself.
    pub fn shown_slots(&self, env: EnvName) -> usize {
        if self.goal_in_observation {
            GoalShown::SLOTS
        } else if self.hazards_in_observation {
            HazardsShown::slots(spawn_config(env).grid_size)
        } else {
            0
        }
    }

    /// The share of the trajectories collected after `env_steps` environment
    /// steps whose shown slots are blanked (goal or hazard map).
    pub fn hidden_share_at(&self, env_steps: u64) -> f64 {
        if self.hazards_in_observation {
            self.hazard_hidden_share * ramp_at(self.hazard_hidden_ramp, env_steps)
        } else {
            self.goal_hidden_share_at(env_steps)
        }
    }

    /// Whether the shown slots are ever blanked, so that the agent can be
    /// evaluated with them blank.
    pub fn slots_ever_hidden(&self) -> bool {
        match (self.goal_in_observation, self.hazards_in_observation) {
            (true, _) => self.goal_hidden_share > 0.0,
            (_, true) => self.hazard_hidden_share > 0.0,
            _ => true,
        }
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
