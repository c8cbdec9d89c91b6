//! EPPO: safe reinforcement pretraining (the paper's Algorithm 1). This file
//! is the algorithm, read top to bottom: the learner's state, [`train`]'s loop
//! (collect, update, checkpoint, log) and [`Learner::update`]. Its parts sit
//! beside it: `config/` (hyperparameters in sections, validation, exploration),
//! `net.rs` (networks, heads, the tanh-Gaussian), `replay.rs` (trajectories,
//! the buffer, tokens and batches), `losses.rs` (Lv, Lc, Lp, Eq. 7, Polyak),
//! `collect.rs` (acting in the vectorised environments), `overlap.rs` (the
//! loop with collection and learning on two threads), `timing.rs` (where the
//! time goes), `checkpoint.rs` (save and resume) and `agent.rs` (the frozen
//! [`EppoAgent`] evaluation drives).
//!
//! The replay ratio is a setting, never a consequence of speed: after each
//! round the learner runs the updates [`Learner::updates_owed`] says
//! (`updates_per_round`, or `replay_ratio` updates per environment step),
//! in the synchronous loop and the overlapped one alike. Overlapped, the
//! learner waits for the next round once they are done, and the actor waits
//! for fresh weights once it is a round ahead, so the only difference from
//! the synchronous loop is a policy one round staler (`overlap.rs`); both
//! loops are deterministic under a seed.
//!
//! Off-policy actor-critic after AMAGO: a time-step MLP encodes each
//! (s_t, a_{t-1}, r_t, c_t, CTG_t, episode-start) tuple; the shared causal
//! transformer reads the whole multi-episode trajectory; heads give the actor,
//! a reward critic Q and a cost critic Qc (one value per action for discrete
//! actions). Losses per step (SPEC section 3):
//! - Lv = (Q(h_t, a_t) - [r_{t+1} + gamma Q'(h_{t+1}, a')])^2
//! - Lc = (Qc(h_t, a_t) - [c_{t+1} + gamma Qc'(h_{t+1}, a')])^2
//! - Lp = -Q(h_t, a_hat) + lambda v_e Qc(h_t, a_hat), v_e = 1 when episode e's
//!   cost exceeded the trajectory's budget delta.
//!
//! Deviations from Algorithm 1, each for a measured reason (results/eppo_ladder):
//! - Each token also carries the observation the previous action arrived at,
//!   so the goal, where the auto-reset replaces the final observation, enters
//!   the context with its reward ([`crate::tokens`]).
//! - The reward critic bootstraps across episode boundaries (the meta-RL
//!   objective is the sum of the K returns); the cost critic never does, since
//!   the budget binds each episode alone (Eq. 6): a violation charges only its
//!   own episode.
//! - Q and the tokens see rewards x `reward_scale`; lambda is in reward units
//!   (the penalty is lambda x reward_scale x Qc), so lambda = 1 prices one unit
//!   of cost like one goal whatever the scale.
//! - Exploration is AMAGO's bilevel epsilon-greedy: annealed over training,
//!   decaying inside each trajectory, scaled per trajectory by a uniform draw.
//!
//! The multiplier follows Eq. (7): lambda <- clip(lambda + eta * mean over the
//! sampled trajectories of max_k (C_k - delta), 0, lambda_max)
//! (`multiplier.rs`).
//!
//! Levers from the robots' ladder (results/eppo_point_ladder,
//! eppo_car_ladder), each off unless a preset sets it: hindsight task
//! relabelling of replayed trajectories (`relabel_prob`, `relabel.rs`), a
//! dense reward for the critics only (`dense_reward_coef`; tokens stay sparse;
//! with `dense_reward_after_goal`, only once a success is in the context,
//! where the agent can know the goal) and SAC's automatic temperature
//! (`target_entropy`: the entropy weight tuned so that a continuous actor
//! cannot collapse onto its action bounds), in both robot presets; the goal
//! in the observation (`goal_in_observation`), hidden in a share of the
//! trajectories that rises over training (`goal_hidden_share`), so that one
//! policy learns to drive to a shown goal and then to read a found one from
//! its context, with an auxiliary loss that reads the found goal off the
//! trajectory encoding (`goal_recall_coef`), in Car's; and a scripted first
//! episode that shows the goal (`scripted_first_episode`), a diagnostic rung
//! in none.
//!
//! Levers from the budget ladder (results/eppo_darkroom_budget), likewise
//! off unless a preset sets them: a critic-only bonus for cells new to the
//! trajectory until its first success (`novelty_bonus`, in every robot and
//! grid preset; gated by the budget with `novelty_budget`: withheld past it,
//! or scaled by the share of it left, the grid's; learned by critics of its
//! own that the actor weighs only until its context holds a success, with
//! `novelty_critic`, the robots'), the actor's penalty at decision time,
//! max(0, Qc - CTG_t), instead of Algorithm 1's hindsight flag
//! (`penalty = "hinge"`), and no multiplier at all: once an episode has spent
//! its budget, the critics' reward for its remaining steps is a fixed
//! unsafe reward (`penalty = "saute"`, after Saute RL) or the usual
//! reward (`penalty = "excess"`: Eq. (5)'s exact penalty with lambda fixed),
//! less `over_budget_cost_price` per unit of cost, so the price of
//! overspending does not depend on where an integrator settles on a given
//! training seed; or the step that overspends ends the critics' value over
//! the K episodes (`penalty = "terminate"`, an early-terminated MDP), so a
//! search past the budget is worth nothing to the episodes after it (given
//! a multiplier, its actor also pays Algorithm 1's penalty). The
//! constraint (multiplier, price and termination alike) waits
//! `lambda_warmup_updates`, and with `constraint_after_revisit` also for the
//! training revisit rate to reach a level (`multiplier::ConstraintStart`):
//! priced before the agent comes back to the goals it finds, it learns to
//! search and never to come back (dx1). `over_budget_price_schedule` raises
//! the price in steps after that start: the price that lets search survive
//! the start is too low to make the budget bind later (dw1 -> dw1q). The
//! presets: the grid's `excess` with a scheduled price, Car's `terminate`
//! from update 6000, Point's Algorithm 1 flag with Eq. (7) from its revisit
//! gate.
//!
//! Metrics (`metrics.jsonl`, one record per collection round, against
//! `env_steps`): `episodic_return`, `episodic_cost` (means over the episodes
//! collected in the round), `first_episode_return`, `last_episode_return`,
//! `first_episode_cost`, `last_episode_cost` (per trajectory, averaged: the
//! in-context signal), `discovery_rate` and `revisit_rate` (P(goal at episode
//! k > 1 | not found / found earlier in the trajectory)), `found_goal`
//! (fraction of trajectories that found it), `search_new_cells` (cells of
//! side `novelty_cell` first entered per episode after the first, over the
//! episodes that start with the goal not found: near 0 when every episode
//! drives the same route), `repeat_cost` (cost per episode paid again, near
//! where the trajectory paid one in an earlier episode), `last_over_budget`
//! (the share of trajectories whose last episode ended over its budget),
//! with goal slots `goal_hidden_share`, `hidden_goal_return`,
//! `hidden_goal_revisit_rate` and `shown_goal_return`, and with goal or
//! hazard slots `hidden_slots_cost` and `shown_slots_cost` (the two kinds of
//! trajectory apart),
//! `lambda`, `constrained`
//! (whether the constraint acted in the round), `over_budget_price` (the
//! excess price charged, 0 when none is), `entropy_coef`,
//! `losses/value_loss`, `losses/cost_value_loss`, `losses/policy_loss`, `losses/entropy`, `losses/grad_norm`,
//! `losses/goal_recall` (NaN without the head), `losses/novelty_q_mean` (the
//! novelty critics' mean Q; NaN without them), `charts/epsilon`,
//! `charts/updates_per_s`, `charts/env_steps_per_s`, `charts/cpu_learner` and
//! (overlapped) `charts/cpu_actor` (the share of a core each thread kept busy
//! since the start), `time/<phase>` and `time/actor/<phase>` (cumulative wall
//! seconds per phase, [`PhaseTimes`]). Losses are averaged over
//! the round's updates and are `null` in rounds without an update (before
//! `learning_starts`).

mod agent;
mod checkpoint;
mod collect;
mod config;
mod losses;
mod multiplier;
mod net;
mod overlap;
mod relabel;
mod replay;
#[cfg(test)]
pub(crate) mod tests;
mod timing;

use std::path::PathBuf;
use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::{Device, nn};

use safety_envs::{CmdpEnv, EnvError, EnvName, EnvOptions, GoalRule, GoalShown, VecEnv, make_env};

pub use agent::EppoAgent;
pub use checkpoint::{drop_replay, recorded_pretrain_tasks};
pub use collect::{RoundStats, search_rates};
pub use config::{
    ConstraintConfig, EppoConfig, EppoError, Exploration, ExplorationConfig, GoalConfig,
    ModelConfig, NoveltyBudget, NoveltyConfig, OptimisationConfig, PenaltyForm, PriceChange,
    RunConfig, TargetsConfig, TasksConfig, parse_device,
};
pub use losses::{UpdateStats, lambda_update};
pub use multiplier::{ConstraintStart, Multiplier};
pub use net::memory_estimate;
pub use net::{EppoNet, NetSpec};
pub use relabel::{pick_goal, relabel};
pub use replay::{Replay, Trajectory};
pub use timing::{PhaseTimes, thread_cpu_seconds};

use crate::checkpoint::{MetricsWriter, RunDir};
use crate::optim::{Adam, AdamConfig};
use collect::mean;
use losses::{losses, polyak, tuned_entropy_coef};
use relabel::relabel_some;
use replay::{Batch, make_batch};

/// Everything a run carries between updates (and into checkpoints).
pub struct Learner {
    pub cfg: EppoConfig,
    pub env: EnvName,
    pub spec: NetSpec,
    pub device: Device,
    pub vs: nn::VarStore,
    pub net: EppoNet,
    pub target_vs: nn::VarStore,
    pub target: EppoNet,
    pub opt: Adam,
    /// The cost multiplier lambda (`multiplier.rs`).
    pub multiplier: Multiplier,
    /// When the constraint comes on (`constraint_after_revisit`).
    pub constraint_start: ConstraintStart,
    /// The entropy bonus's weight: `entropy_coef`, tuned toward
    /// `target_entropy` where one is set.
    pub entropy_coef: f64,
    pub updates: u64,
    pub env_steps: u64,
    /// Pretraining tasks drawn so far: task i comes from
    /// `pretrain_task_seed(cfg.seed, i)`, so checkpoints can record exactly
    /// which tasks were seen and evaluation can prove its tasks held out.
    pub tasks_drawn: u64,
    pub rng: ChaCha8Rng,
    pub replay: Replay,
    /// Where the environment's goal counts as reached (hindsight relabelling).
    pub goal_rule: GoalRule,
    /// Wall seconds per phase on this thread since the run (or resume) began.
    pub times: PhaseTimes,
}

impl Learner {
    /// A fresh learner for `env` (networks initialised from `cfg.run.seed`).
    pub fn new(cfg: EppoConfig, env: EnvName) -> Result<Self, EppoError> {
        cfg.validate()?;
        let device = parse_device(&cfg.run.device)?;
        crate::guard::set_torch_threads("torch_threads", cfg.run.torch_threads);
        let probe = make_training_env(env, &cfg)?;
        let spec = NetSpec::from_spaces(&probe.observation_space(), &probe.action_space())?;
        if cfg.goal.scripted_first_episode && probe.goal_seeking_action().is_none() {
            return Err(EppoError::Config(format!(
                "scripted_first_episode needs an environment with a scripted goal-seeking \
                 controller (point, car); {env} has none: set scripted_first_episode = false"
            )));
        }
        let goal_rule = probe.goal_rule();
        memory_estimate(&cfg, &spec)
            .check()
            .map_err(EppoError::Config)?;
        let vs = nn::VarStore::new(device);
        let net = crate::torch_rng::seeded(cfg.run.seed, || EppoNet::new(vs.root(), &cfg, &spec))?;
        // The target's own initial draws are overwritten by the copy.
        let mut target_vs = nn::VarStore::new(device);
        let target = EppoNet::new(target_vs.root(), &cfg, &spec)?;
        target_vs.copy(&vs)?;
        target_vs.freeze();
        let opt = Adam::new(
            &vs,
            AdamConfig {
                lr: cfg.optimisation.lr,
                beta1: cfg.optimisation.beta1,
                beta2: cfg.optimisation.beta2,
                eps: cfg.optimisation.adam_eps,
                grad_clip: Some(cfg.optimisation.grad_clip),
            },
        );
        Ok(Learner {
            rng: ChaCha8Rng::seed_from_u64(cfg.run.seed),
            replay: Replay::new(cfg.targets.replay_capacity),
            multiplier: if cfg.constraint.per_episode_multipliers {
                Multiplier::per_episode(cfg.constraint.lambda_init, cfg.tasks.k_max)
            } else {
                Multiplier::new(cfg.constraint.lambda_init)
            },
            constraint_start: ConstraintStart::default(),
            entropy_coef: cfg.exploration.entropy_coef,
            updates: 0,
            env_steps: 0,
            tasks_drawn: 0,
            goal_rule,
            times: PhaseTimes::default(),
            env,
            spec,
            device,
            vs,
            net,
            target_vs,
            target,
            opt,
            cfg,
        })
    }

    /// Current epsilon of epsilon-greedy exploration at a trajectory's first step.
    pub fn epsilon(&self) -> f64 {
        self.cfg.exploration.schedule(self.env_steps).first
    }

    /// One update on a batch sampled from the replay: Lv, Lc, Lp, then lambda
    /// (Eq. 7) and the Polyak targets.
    pub fn update(&mut self) -> Result<UpdateStats, EppoError> {
        // libtorch's generator (dropout, reparameterisation noise) is reseeded per
        // update, so a resumed run draws what the uninterrupted one would have.
        let seed = (self.cfg.run.seed ^ 0x5EED_0000).wrapping_add(self.updates);
        crate::torch_rng::seeded(seed, || self.update_seeded())
    }

    fn update_seeded(&mut self) -> Result<UpdateStats, EppoError> {
        let mut clock = Instant::now();
        let sampled = self
            .replay
            .sample(self.cfg.optimisation.batch_size, &mut self.rng);
        let relabelled = relabel_some(
            &sampled,
            self.cfg.goal.relabel_prob,
            &self.spec,
            &self.goal_rule,
            self.cfg.goal.goal_in_observation,
            &mut self.rng,
        );
        let trajs: Vec<&Trajectory> = sampled
            .iter()
            .zip(&relabelled)
            .map(|(&t, r)| r.as_ref().unwrap_or(t))
            .collect();
        let batch = make_batch(
            &trajs,
            &self.cfg,
            &self.spec,
            self.cfg.shaping(self.updates, self.constraint_since()),
            &mut self.rng,
            self.device,
        );
        // The multiplier prices the costs the policy really paid: a
        // relabelled episode cut at its new goal holds only part of them.
        let violations: Vec<f32> = sampled.iter().map(|t| t.max_violation()).collect();
        // Eq. (6)'s per-episode excess, only where its multipliers are on.
        let excess: Vec<Vec<f32>> = if self.cfg.constraint.per_episode_multipliers {
            sampled
                .iter()
                .map(|t| t.episode_costs.iter().map(|c| c - t.budget).collect())
                .collect()
        } else {
            Vec::new()
        };
        // Eq. (6): each step's hindsight flag carries its own episode's
        // multiplier, and the losses' lambda is 1.
        let (batch, lambda) = if self.cfg.constraint.per_episode_multipliers {
            let violated = &batch.violated * self.multiplier.per_step(&batch.episode);
            (Batch { violated, ..batch }, 1.0)
        } else {
            (batch, self.multiplier.lambda)
        };
        self.times.batch += lap(&mut clock);
        let (lv, lc, lp, entropy, diag) = losses(
            &self.net,
            &self.target,
            &batch,
            lambda,
            self.entropy_coef,
            &self.cfg,
        )?;
        let mut loss = (&lv + &lc) * self.cfg.optimisation.critic_weight + &lp;
        if let Some(recall) = &diag.goal_recall {
            loss += recall * self.cfg.goal.goal_recall_coef;
        }
        self.times.forward += lap(&mut clock);
        // A NaN or infinite loss or gradient is never applied: the weights
        // stay those of the last good update and `train` stops with this.
        let non_finite = |e: crate::optim::StepRefused| EppoError::NonFinite {
            update: self.updates + 1,
            what: format!(
                "{e} (value loss {:.4e}, cost value loss {:.4e}, policy loss {:.4e})",
                lv.double_value(&[]),
                lc.double_value(&[]),
                lp.double_value(&[])
            ),
            checkpoint: None,
        };
        self.opt.try_backward(&loss).map_err(non_finite)?;
        self.times.backward += lap(&mut clock);
        let grad_norm = self.opt.try_step().map_err(non_finite)?;
        self.times.optimizer += lap(&mut clock);
        if self.constrained() {
            let (eta, max) = (
                self.cfg.constraint.lambda_lr,
                self.cfg.constraint.lambda_max,
            );
            if self.cfg.constraint.per_episode_multipliers {
                self.multiplier.update_per_episode(&excess, eta, max);
            } else {
                self.multiplier.update(&violations, eta, max);
            }
        }
        let entropy_now = entropy.double_value(&[]);
        if let Some(target) = self.cfg.exploration.target_entropy {
            self.entropy_coef = tuned_entropy_coef(
                self.entropy_coef,
                entropy_now,
                target,
                self.cfg.exploration.entropy_coef_lr,
            );
        }
        polyak(&self.target_vs, &self.vs, self.cfg.targets.tau);
        self.updates += 1;
        let stats = UpdateStats {
            value_loss: lv.double_value(&[]),
            cost_value_loss: lc.double_value(&[]),
            policy_loss: lp.double_value(&[]),
            entropy: entropy_now,
            grad_norm,
            lambda: self.multiplier.lambda,
            q_mean: diag.q_mean.double_value(&[]),
            target_mean: diag.target_mean.double_value(&[]),
            log_std_mean: diag.log_std_mean.map_or(f64::NAN, |t| t.double_value(&[])),
            goal_recall_loss: diag
                .goal_recall
                .as_ref()
                .map_or(f64::NAN, |t| t.double_value(&[])),
            novelty_q_mean: diag
                .novelty_q_mean
                .as_ref()
                .map_or(f64::NAN, |t| t.double_value(&[])),
        };
        self.times.targets += lap(&mut clock);
        Ok(stats)
    }

    /// Whether the constraint acts now: the multiplier moves and the
    /// over-budget price is charged.
    pub fn constrained(&self) -> bool {
        self.constraint_since().is_some()
    }

    /// The update at which the constraint came on, if it acts now.
    pub fn constraint_since(&self) -> Option<u64> {
        self.constraint_start.started_at(
            self.updates,
            self.cfg.constraint.lambda_warmup_updates,
            self.cfg.constraint.constraint_after_revisit,
        )
    }

    /// The price per unit of cost past an episode's budget that the critics'
    /// rewards carry now (0 before the constraint, or with no priced
    /// `penalty` form).
    pub fn over_budget_price(&self) -> f64 {
        self.cfg
            .shaping(self.updates, self.constraint_since())
            .over_budget()
            .map_or(0.0, |o| f64::from(o.cost_price))
    }

    /// The penalty's state for a progress or summary line: the over-budget
    /// price under the forms that charge one, the termination under
    /// `terminate`, lambda under the others.
    pub fn penalty_reading(&self) -> String {
        match self.cfg.constraint.penalty {
            PenaltyForm::Excess | PenaltyForm::Saute => {
                format!("over-budget price {:.2}", self.over_budget_price())
            }
            PenaltyForm::Terminate if self.cfg.constraint.has_multiplier() => format!(
                "overspending ends the value, lambda {:.4}",
                self.multiplier.lambda
            ),
            PenaltyForm::Terminate => "overspending ends the value".to_string(),
            PenaltyForm::Hindsight | PenaltyForm::Hinge => {
                format!("lambda {:.4}", self.multiplier.lambda)
            }
        }
    }

    /// Takes a collected round's measures into what the learner decides
    /// from them (when the constraint starts).
    pub fn observe_round(&mut self, round: &RoundStats) {
        if let Some(threshold) = self.cfg.constraint.constraint_after_revisit {
            self.constraint_start.observe(
                round.skill_revisit_rate(self.cfg.goal.goal_in_observation),
                self.updates,
                self.cfg.constraint.lambda_warmup_updates,
                threshold,
                self.cfg.constraint.constraint_revisit_rounds,
            );
        }
    }

    /// The replay ratio: updates owed once a round has brought `env_steps`
    /// where it is (none before `learning_starts`, none past `total_updates`).
    /// Both loops ask after each round, so the updates per environment step
    /// are the same whichever side is faster.
    pub fn updates_owed(&self) -> u64 {
        if self.env_steps < self.cfg.optimisation.learning_starts {
            return 0;
        }
        let owed = match self.cfg.optimisation.replay_ratio {
            Some(r) => {
                let total = (r * (self.env_steps - self.cfg.optimisation.learning_starts) as f64)
                    .floor() as u64;
                total.saturating_sub(self.updates)
            }
            None => self.cfg.optimisation.updates_per_round,
        };
        owed.min(
            self.cfg
                .optimisation
                .total_updates
                .saturating_sub(self.updates),
        )
    }
}

/// Seconds since `clock`, which restarts.
fn lap(clock: &mut Instant) -> f64 {
    let now = Instant::now();
    let secs = (now - *clock).as_secs_f64();
    *clock = now;
    secs
}

/// Options of one `icrl pretrain` run (the CLI fills it).
#[derive(Clone, Debug)]
pub struct PretrainOptions {
    pub env: EnvName,
    pub cfg: EppoConfig,
    /// Parent folder of run folders (`runs`).
    pub out: PathBuf,
    /// A run folder or checkpoint folder to continue from.
    pub resume: Option<PathBuf>,
    /// Draw a progress bar (off in tests).
    pub progress: bool,
}

/// What a finished run reports.
#[derive(Clone, Debug)]
pub struct PretrainReport {
    pub run_dir: PathBuf,
    pub last_checkpoint: PathBuf,
    pub updates: u64,
    pub env_steps: u64,
    pub lambda: f64,
    /// The penalty's state at the end ([`Learner::penalty_reading`]).
    pub penalty: String,
    /// A uniformly random policy on the pretraining tasks, for scale.
    pub random: crate::run_summary::ReturnCost,
}

/// Algorithm 1: collect rounds of trajectories, update, checkpoint, log;
/// one after the other, or at once with `overlap` (`overlap.rs`).
pub fn train(opts: &PretrainOptions) -> Result<PretrainReport, EppoError> {
    // `_lock`: one process per run folder until training returns.
    let (run, mut learner, resumed_from, _lock) = match &opts.resume {
        Some(path) => {
            let (run, ckpt) = RunDir::resolve_resume(path)?;
            let lock = run.lock()?;
            let learner = Learner::resume(opts.cfg.clone(), opts.env, &ckpt)?;
            // Rounds logged after the checkpoint are redone: drop their records.
            crate::checkpoint::truncate_metrics(&run.metrics_path(), "updates", learner.updates)?;
            (run, learner, Some(ckpt), lock)
        }
        None => {
            let learner = Learner::new(opts.cfg.clone(), opts.env)?;
            let run = RunDir::create(&opts.out, opts.env.as_str(), "eppo", opts.cfg.run.seed)?;
            let lock = run.lock()?;
            (run, learner, None, lock)
        }
    };
    let cfg = learner.cfg.clone();
    let ready = (|| -> Result<(), EppoError> {
        run.write_config(&toml::to_string(&cfg).map_err(|e| EppoError::Config(e.to_string()))?)?;
        run.probe_checkpoint_path(cfg.optimisation.total_updates)?;
        // Weights, Adam's moments and the target weights (a third of the first).
        run.check_room(
            learner.opt.checkpoint_bytes() * 4 / 3 + crate::checkpoint::CHECKPOINT_SLACK,
            cfg.run.retention(),
            cfg.optimisation
                .total_updates
                .saturating_sub(learner.updates),
            cfg.run.checkpoint_every,
        )?;
        Ok(())
    })();
    if let Err(e) = ready {
        // A refused start leaves no empty run folder behind.
        if resumed_from.is_none() {
            run.remove_if_unused();
        }
        return Err(e);
    }
    let env_options = EnvOptions {
        max_episode_steps: Some(cfg.tasks.max_episode_steps),
        physics_steps_per_action: cfg.tasks.physics_steps_per_action,
    };
    // The scale the user reads progress against (seconds, even for Car).
    let random = crate::run_summary::random_policy(opts.env, &env_options, 100, cfg.run.seed)?;
    let envs = (0..cfg.tasks.n_envs)
        .map(|_| make_training_env(opts.env, &cfg))
        .collect::<Result<Vec<_>, _>>()?;
    let mut venv = VecEnv::new(envs, cfg.run.env_threads, true)?;
    let mut session = Session::start(run, &learner, opts.progress, random, resumed_from)?;
    if cfg.run.overlap {
        overlap::train(&mut learner, &mut venv, &mut session)?;
    } else {
        while learner.updates < cfg.optimisation.total_updates {
            let round = learner.collect(&mut venv)?;
            learner.observe_round(&round);
            let stats = learn(&mut learner, &mut session)?;
            session.log_round(&mut learner, &round, &stats, None)?;
            if crate::stop::requested() {
                break;
            }
        }
    }
    session.finish(&learner)
}

/// One of the environments training collects in: `env` with the run's time
/// limit and macro action, its goal in the observation where the ladder's
/// goal-conditioned rung asks for it (`goal_in_observation`).
fn make_training_env(env: EnvName, cfg: &EppoConfig) -> Result<Box<dyn CmdpEnv>, EnvError> {
    let inner = make_env(
        env,
        &EnvOptions {
            max_episode_steps: Some(cfg.tasks.max_episode_steps),
            physics_steps_per_action: cfg.tasks.physics_steps_per_action,
        },
    )?;
    Ok(if cfg.goal.goal_in_observation {
        Box::new(GoalShown::new(inner))
    } else {
        inner
    })
}

/// The updates the replay ratio owes after a round ([`Learner::updates_owed`]),
/// each followed by its checkpoint when due; the first SIGINT/SIGTERM stops
/// them after the current one.
fn learn(learner: &mut Learner, session: &mut Session) -> Result<Vec<UpdateStats>, EppoError> {
    let mut stats = Vec::new();
    for _ in 0..learner.updates_owed() {
        stats.push(learner.update().map_err(|e| session.non_finite(e))?);
        session.after_update(learner)?;
        if crate::stop::requested() {
            break;
        }
    }
    Ok(stats)
}

/// A run's bookkeeping around the loop: its folder and metrics, the
/// progress bar and log lines, the last good checkpoint, the clocks.
struct Session {
    run: RunDir,
    metrics: MetricsWriter,
    recent: crate::run_summary::RecentRounds,
    random: crate::run_summary::ReturnCost,
    bar: indicatif::ProgressBar,
    /// Without a terminal indicatif draws nothing: the bar's line goes to
    /// stderr instead, at most every 30 s, so logs show progress.
    log_lines: bool,
    last_log_line: Instant,
    /// The checkpoint resumed from is the last good one (newer step folders,
    /// if resuming an earlier one, belong to the abandoned continuation).
    last_ckpt: PathBuf,
    started: Instant,
    /// This thread's CPU seconds at the start.
    started_cpu: f64,
    start_updates: u64,
    start_steps: u64,
}

impl Session {
    fn start(
        run: RunDir,
        learner: &Learner,
        progress: bool,
        random: crate::run_summary::ReturnCost,
        resumed_from: Option<PathBuf>,
    ) -> Result<Self, EppoError> {
        let bar = progress_bar(
            progress,
            learner.cfg.optimisation.total_updates,
            learner.updates,
        );
        Ok(Session {
            metrics: MetricsWriter::open(&run.metrics_path())?,
            run,
            recent: crate::run_summary::RecentRounds::new(50),
            random,
            log_lines: progress && bar.is_hidden(),
            bar,
            last_log_line: Instant::now(),
            last_ckpt: resumed_from.unwrap_or_default(),
            started: Instant::now(),
            started_cpu: thread_cpu_seconds(),
            start_updates: learner.updates,
            start_steps: learner.env_steps,
        })
    }

    /// A NaN update names the last good checkpoint (never one of NaN weights).
    fn non_finite(&self, e: EppoError) -> EppoError {
        match e {
            EppoError::NonFinite { update, what, .. } => EppoError::NonFinite {
                update,
                what,
                checkpoint: (!self.last_ckpt.as_os_str().is_empty())
                    .then(|| self.last_ckpt.clone()),
            },
            other => other,
        }
    }

    /// Progress, and the checkpoint every `checkpoint_every` updates.
    fn after_update(&mut self, learner: &mut Learner) -> Result<(), EppoError> {
        self.bar.set_position(learner.updates);
        if learner
            .updates
            .is_multiple_of(learner.cfg.run.checkpoint_every)
        {
            let clock = Instant::now();
            self.last_ckpt = learner.save_checkpoint(&self.run)?;
            learner.times.logging += clock.elapsed().as_secs_f64();
        }
        Ok(())
    }

    /// One round's metrics record and progress line; `actor`: the
    /// overlapped actor's phase times and CPU seconds.
    fn log_round(
        &mut self,
        learner: &mut Learner,
        round: &RoundStats,
        stats: &[UpdateStats],
        actor: Option<(&PhaseTimes, f64)>,
    ) -> Result<(), EppoError> {
        let clock = Instant::now();
        let secs = self.started.elapsed().as_secs_f64().max(1e-9);
        let ups = (learner.updates - self.start_updates) as f64 / secs;
        let sps = (learner.env_steps - self.start_steps) as f64 / secs;
        let mut record = round_record(learner, round, stats, ups, sps);
        if let Some(map) = record.as_object_mut() {
            learner.times.record("", map);
            let cpu = (thread_cpu_seconds() - self.started_cpu) / secs;
            map.insert("charts/cpu_learner".into(), cpu.into());
            if let Some((times, actor_cpu)) = actor {
                times.record("actor/", map);
                map.insert("charts/cpu_actor".into(), (actor_cpu / secs).into());
            }
        }
        self.metrics.write(&record)?;
        self.recent.push(
            round.mean_return,
            round.mean_cost,
            round.first_return,
            round.last_return,
        );
        let waiting = if learner.constrained() {
            ""
        } else {
            " (constraint not on yet)"
        };
        let line = format!(
            "{}  {}{waiting}  {ups:.2} upd/s",
            self.recent.progress_line(self.random),
            learner.penalty_reading(),
        );
        if self.log_lines && self.last_log_line.elapsed().as_secs() >= 30 {
            eprintln!(
                "update {}/{}  env steps {}  {line}",
                learner.updates, learner.cfg.optimisation.total_updates, learner.env_steps
            );
            self.last_log_line = Instant::now();
        }
        self.bar.set_message(line);
        // Logging's own time lands in the next record.
        learner.times.logging += clock.elapsed().as_secs_f64();
        Ok(())
    }

    /// The final checkpoint (unless the last update wrote one) and the report;
    /// after a stop request, the "interrupted" error naming it.
    fn finish(mut self, learner: &Learner) -> Result<PretrainReport, EppoError> {
        if !self
            .last_ckpt
            .ends_with(format!("step_{}", learner.updates))
        {
            self.last_ckpt = learner.save_checkpoint(&self.run)?;
        }
        if crate::stop::requested() {
            self.bar.abandon();
            return Err(EppoError::Interrupted {
                checkpoint: self.last_ckpt,
                updates: learner.updates,
            });
        }
        self.bar.finish();
        Ok(PretrainReport {
            run_dir: self.run.path.clone(),
            last_checkpoint: self.last_ckpt,
            updates: learner.updates,
            env_steps: learner.env_steps,
            lambda: learner.multiplier.lambda,
            penalty: learner.penalty_reading(),
            random: self.random,
        })
    }
}

/// The progress bar over `total_updates` (hidden without `progress`).
fn progress_bar(progress: bool, total_updates: u64, updates: u64) -> indicatif::ProgressBar {
    if progress {
        let bar = indicatif::ProgressBar::new(total_updates);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{bar:30} {pos}/{len} updates [{elapsed_precise}<{eta_precise}] {msg}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        bar.set_position(updates);
        bar
    } else {
        indicatif::ProgressBar::hidden()
    }
}

/// One collection round's line of `metrics.jsonl` (names in the module docs):
/// the round's episodes, the learner's counters and the means of its updates.
fn round_record(
    learner: &Learner,
    round: &RoundStats,
    stats: &[UpdateStats],
    ups: f64,
    sps: f64,
) -> serde_json::Value {
    let avg = |f: fn(&UpdateStats) -> f64| {
        if stats.is_empty() {
            f64::NAN
        } else {
            mean(stats.iter().map(f))
        }
    };
    serde_json::json!({
        "env_steps": learner.env_steps,
        "updates": learner.updates,
        "episodic_return": round.mean_return,
        "episodic_cost": round.mean_cost,
        "first_episode_return": round.first_return,
        "last_episode_return": round.last_return,
        "first_episode_cost": round.first_cost,
        "last_episode_cost": round.last_cost,
        "discovery_rate": round.discovery_rate,
        "revisit_rate": round.revisit_rate,
        "found_goal": round.found,
        "search_new_cells": round.search_new_cells,
        "repeat_cost": round.repeat_cost,
        "last_over_budget": round.last_over_budget,
        "goal_hidden_share": round.goal_slots.hidden_share,
        "hidden_goal_return": round.goal_slots.hidden_return,
        "hidden_goal_revisit_rate": round.goal_slots.hidden_revisit_rate,
        "shown_goal_return": round.goal_slots.shown_return,
        "hidden_slots_cost": round.goal_slots.hidden_cost,
        "shown_slots_cost": round.goal_slots.shown_cost,
        "lambda": learner.multiplier.lambda,
        "constrained": learner.constrained(),
        "over_budget_price": learner.over_budget_price(),
        "entropy_coef": learner.entropy_coef,
        "losses/value_loss": avg(|s| s.value_loss),
        "losses/cost_value_loss": avg(|s| s.cost_value_loss),
        "losses/policy_loss": avg(|s| s.policy_loss),
        "losses/entropy": avg(|s| s.entropy),
        "losses/grad_norm": avg(|s| s.grad_norm),
        "losses/q_mean": avg(|s| s.q_mean),
        "losses/target_mean": avg(|s| s.target_mean),
        "losses/log_std_mean": avg(|s| s.log_std_mean),
        "losses/goal_recall": avg(|s| s.goal_recall_loss),
        "losses/novelty_q_mean": avg(|s| s.novelty_q_mean),
        "charts/action_abs": round.action_abs,
        "charts/action_saturated": round.action_saturated,
        "charts/epsilon": learner.epsilon(),
        "charts/updates_per_s": ups,
        "charts/env_steps_per_s": sps,
    })
}
