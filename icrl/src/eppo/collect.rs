//! Acting in the vectorised environments: one collection round
//! ([`Learner::collect`]: fresh tasks, budgets and K, one batched forward step
//! per environment step through the KV cache), what the round gathered
//! ([`RoundStats`]), and the acting state the frozen agent shares.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use tch::{Device, Kind, Tensor};

use std::sync::atomic::{AtomicBool, Ordering};

use safety_envs::{
    EnvName, Orientation, StepOutcome, VecAction, VecEnv, sample_task, spawn_config,
};

use super::Learner;
use super::config::{EppoConfig, EppoError};
use super::net::{EppoNet, NetSpec};
use super::replay::{Trajectory, novel_arrivals, push_token};
use super::timing::PhaseTimes;
use crate::agent::{NextInput, StepInput};
use crate::model::KvCache;
use crate::signals::CostMemory;
use crate::task_seeds::pretrain_task_seed;

/// What one collection round gathered.
#[derive(Clone, Debug, Default)]
pub struct RoundStats {
    pub trajectories: usize,
    pub steps: u64,
    pub mean_return: f64,
    pub mean_cost: f64,
    pub first_return: f64,
    pub last_return: f64,
    pub first_cost: f64,
    pub last_cost: f64,
    /// The in-context search signals, pooled over the round's episodes after
    /// the first: P(goal | not found earlier in the trajectory) and
    /// P(goal | found earlier), and the fraction of trajectories that found it.
    pub discovery_rate: f64,
    pub revisit_rate: f64,
    pub found: f64,
    /// Cells first entered per episode after the first, over the episodes
    /// that start with the goal not yet found ([`new_cells_while_searching`]).
    pub search_new_cells: f64,
    /// Mean cost per episode paid again ([`CostMemory`](crate::signals::CostMemory), the evaluation's
    /// `repeat_cost`): what the context could have spared.
    pub repeat_cost: f64,
    /// The share of trajectories whose last episode ended over its budget:
    /// in training, what the evaluation's within-budget rate at K measures.
    pub last_over_budget: f64,
    /// Continuous actions: mean |a| of the collected actions (in [-1, 1])
    /// and the fraction with |a| > 0.99; NaN for discrete actions.
    pub action_abs: f64,
    pub action_saturated: f64,
    /// With shown goal slots (`goal_in_observation`), the round's two kinds
    /// of trajectory apart; NaN without slots, or where a kind is absent.
    pub goal_slots: GoalSlotStats,
}

impl RoundStats {
    /// The revisit rate that says the in-context skill exists: with goal
    /// slots (`goal_in_observation`), that of the trajectories that hid
    /// their goal, since driving back to a shown goal needs no context (on
    /// Car the shown ones alone pass 0.7 before the hidden ones start).
    pub fn skill_revisit_rate(&self, goal_slots: bool) -> f64 {
        if goal_slots {
            self.goal_slots.hidden_revisit_rate
        } else {
            self.revisit_rate
        }
    }
}

/// The round's trajectories that hid their slots (the goal, or the hazard
/// map) against those that showed them.
#[derive(Clone, Copy, Debug)]
pub struct GoalSlotStats {
    /// The share of trajectories whose goal was hidden.
    pub hidden_share: f64,
    /// Mean episode return, and the revisit rate, of the hidden ones: what
    /// evaluation will measure.
    pub hidden_return: f64,
    pub hidden_revisit_rate: f64,
    /// Mean episode return of the shown ones: the control learned.
    pub shown_return: f64,
    /// Mean episode cost of each kind: with the hazard map, a cost the shown
    /// ones still pay is a lack of control, one only the hidden ones pay a
    /// lack of memory.
    pub hidden_cost: f64,
    pub shown_cost: f64,
}

impl Default for GoalSlotStats {
    fn default() -> Self {
        GoalSlotStats {
            hidden_share: f64::NAN,
            hidden_return: f64::NAN,
            hidden_revisit_rate: f64::NAN,
            shown_return: f64::NAN,
            hidden_cost: f64::NAN,
            shown_cost: f64::NAN,
        }
    }
}

impl GoalSlotStats {
    fn of(trajs: &[Trajectory], hidden: &[bool]) -> Self {
        let kind = |h: bool| trajs.iter().zip(hidden).filter(move |(_, x)| **x == h);
        // NaN, not 0, for a kind the round does not hold.
        let episode_mean = |h: bool, of: fn(&Trajectory) -> &[f32]| match kind(h).count() {
            0 => f64::NAN,
            _ => mean(kind(h).flat_map(|(t, _)| of(t).iter().map(|&x| f64::from(x)))),
        };
        let returns = |h: bool| episode_mean(h, |t| &t.episode_returns);
        let costs = |h: bool| episode_mean(h, |t| &t.episode_costs);
        GoalSlotStats {
            hidden_share: mean(hidden.iter().map(|&h| if h { 1.0 } else { 0.0 })),
            hidden_return: returns(true),
            hidden_revisit_rate: search_rates(
                kind(true).map(|(t, _)| t.episode_success.as_slice()),
            )
            .1,
            shown_return: returns(false),
            hidden_cost: costs(true),
            shown_cost: costs(false),
        }
    }
}

/// (discovery rate, revisit rate, fraction found at least once) over
/// trajectories given as per-episode successes; a rate with no episode to
/// count is NaN.
pub fn search_rates<'a>(successes: impl Iterator<Item = &'a [bool]>) -> (f64, f64, f64) {
    let (mut disc, mut disc_n, mut rev, mut rev_n, mut found, mut n) = (0, 0, 0, 0, 0, 0);
    for episodes in successes {
        n += 1;
        let mut seen = false;
        for (k, &hit) in episodes.iter().enumerate() {
            if k > 0 {
                let (hits, count) = if seen {
                    (&mut rev, &mut rev_n)
                } else {
                    (&mut disc, &mut disc_n)
                };
                *hits += usize::from(hit);
                *count += 1;
            }
            seen |= hit;
        }
        found += usize::from(seen);
    }
    let rate = |a: usize, b: usize| {
        if b == 0 {
            f64::NAN
        } else {
            a as f64 / b as f64
        }
    };
    (rate(disc, disc_n), rate(rev, rev_n), rate(found, n))
}

/// The mean number of cells (side `cell`, on the position at observation
/// indices 0 and 1) first entered in an episode after the first, over the
/// episodes that start with the goal not yet found in the trajectory; NaN
/// with no such episode. About 0 for an agent that drives the same route in
/// every episode, a goal off that route never found; higher for one that
/// searches elsewhere after a miss.
pub(super) fn new_cells_while_searching(trajs: &[Trajectory], obs_dim: usize, cell: f64) -> f64 {
    let (mut cells, mut episodes) = (0.0, 0usize);
    for t in trajs {
        // Whether episode k starts with the goal not yet found.
        let searching: Vec<bool> = t
            .episode_success
            .iter()
            .scan(false, |found, &hit| {
                let before = *found;
                *found |= hit;
                Some(!before)
            })
            .collect();
        episodes += searching.iter().skip(1).filter(|&&s| s).count();
        // Arrivals stop at the first success, so episodes after it add nothing.
        for (step, novel) in novel_arrivals(t, obs_dim, cell).into_iter().enumerate() {
            let k = t.episode[step] as usize;
            if k > 0 && searching.get(k).copied().unwrap_or(false) {
                cells += f64::from(novel);
            }
        }
    }
    if episodes == 0 {
        f64::NAN
    } else {
        cells / episodes as f64
    }
}

/// For each step of `t`, true where it pays a repeated cost ([`CostMemory`]
/// with `radius`, on the arrival's position).
pub(super) fn repeated_costs(t: &Trajectory, obs_dim: usize, radius: f64) -> Vec<bool> {
    let mut memory = CostMemory::new(radius);
    (0..t.len())
        .map(|step| {
            let repeated = t.costs[step] > 0.0 && memory.paid(&t.next_obs[step * obs_dim..]);
            if t.terminated[step] || t.truncated[step] {
                memory.end_episode();
            }
            repeated
        })
        .collect()
}

/// The mean cost per episode paid again ([`repeated_costs`] with
/// `radius`), over every episode of `trajs`; 0 with none.
pub(super) fn repeat_cost_per_episode(trajs: &[Trajectory], obs_dim: usize, radius: f64) -> f64 {
    let again: f64 = trajs
        .iter()
        .flat_map(|t| {
            let repeated = repeated_costs(t, obs_dim, radius);
            t.costs
                .iter()
                .zip(repeated)
                .filter(|c| c.1)
                .map(|c| f64::from(*c.0))
        })
        .sum();
    let episodes: usize = trajs.iter().map(|t| t.episode_costs.len()).sum();
    again / episodes.max(1) as f64
}

pub(super) fn mean(xs: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = xs.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 { 0.0 } else { s / n as f64 }
}

/// Each trajectory's budget, K and exploration scale, drawn for one round.
type RoundDraws = (Vec<f32>, Vec<usize>, Vec<f64>);

/// What a round of `steps` environment steps gathered in `trajs`.
fn round_stats(
    trajs: &[Trajectory],
    steps: u64,
    spec: &NetSpec,
    (cell, repeat_radius): (f64, f64),
) -> RoundStats {
    let discrete = spec.n_actions.is_some();
    let (discovery_rate, revisit_rate, found) =
        search_rates(trajs.iter().map(|t| t.episode_success.as_slice()));
    let (action_abs, action_saturated) = if discrete {
        (f64::NAN, f64::NAN)
    } else {
        let all = || {
            trajs
                .iter()
                .flat_map(|t| t.actions.iter().map(|&x| f64::from(x.abs())))
        };
        (
            mean(all()),
            mean(all().map(|x| if x > 0.99 { 1.0 } else { 0.0 })),
        )
    };
    RoundStats {
        action_abs,
        action_saturated,
        discovery_rate,
        revisit_rate,
        found,
        search_new_cells: new_cells_while_searching(trajs, spec.obs_dim, cell),
        repeat_cost: repeat_cost_per_episode(trajs, spec.obs_dim, repeat_radius),
        trajectories: trajs.len(),
        steps,
        mean_return: mean(
            trajs
                .iter()
                .flat_map(|t| t.episode_returns.iter().map(|&x| f64::from(x))),
        ),
        mean_cost: mean(
            trajs
                .iter()
                .flat_map(|t| t.episode_costs.iter().map(|&x| f64::from(x))),
        ),
        first_return: mean(trajs.iter().map(|t| f64::from(t.episode_returns[0]))),
        last_return: mean(
            trajs
                .iter()
                .map(|t| f64::from(*t.episode_returns.last().unwrap_or(&0.0))),
        ),
        first_cost: mean(trajs.iter().map(|t| f64::from(t.episode_costs[0]))),
        last_cost: mean(
            trajs
                .iter()
                .map(|t| f64::from(*t.episode_costs.last().unwrap_or(&0.0))),
        ),
        last_over_budget: last_over_budget(trajs),
        goal_slots: GoalSlotStats::default(),
    }
}

/// The share of `trajs` whose last episode's cost passed the budget.
pub(super) fn last_over_budget(trajs: &[Trajectory]) -> f64 {
    mean(trajs.iter().map(|t| {
        let over = t.episodes_over_budget().last().unwrap_or(false);
        if over { 1.0 } else { 0.0 }
    }))
}

impl Learner {
    /// Collects one round with the learner's own policy, RNG and counters
    /// (the synchronous loop) and adds it to the replay.
    pub fn collect(&mut self, venv: &mut VecEnv) -> Result<RoundStats, EppoError> {
        let (trajs, stats) = Collector {
            net: &self.net,
            cfg: &self.cfg,
            spec: &self.spec,
            env: self.env,
            rng: &mut self.rng,
            env_steps: &mut self.env_steps,
            tasks_drawn: &mut self.tasks_drawn,
            times: &mut self.times,
            quit: None,
        }
        .round(venv)?;
        for t in trajs {
            self.replay.push(t);
        }
        Ok(stats)
    }
}

/// What collection reads and advances: the acting policy, the RNG of tasks,
/// budgets and actions, and the counters behind the next task seeds and the
/// exploration schedule. The synchronous loop lends the learner's own
/// ([`Learner::collect`]); the overlapped loop's actor owns a copy
/// (`overlap.rs`).
pub(super) struct Collector<'a> {
    pub(super) net: &'a EppoNet,
    pub(super) cfg: &'a EppoConfig,
    pub(super) spec: &'a NetSpec,
    pub(super) env: EnvName,
    pub(super) rng: &'a mut ChaCha8Rng,
    pub(super) env_steps: &'a mut u64,
    pub(super) tasks_drawn: &'a mut u64,
    pub(super) times: &'a mut PhaseTimes,
    /// Set by the overlapped learner when training stops: the round is
    /// abandoned at the next step and gathers nothing.
    pub(super) quit: Option<&'a AtomicBool>,
}

impl Collector<'_> {
    /// Collects `cfg.tasks.n_envs` trajectories at once: each in a fresh centre-oriented
    /// task with its own budget and K, acted in one batch through the KV cache.
    pub(super) fn round(
        &mut self,
        venv: &mut VecEnv,
    ) -> Result<(Vec<Trajectory>, RoundStats), EppoError> {
        let (budgets, ks, eps_scale) = self.draw_tasks(venv)?;
        let exploration = self.cfg.exploration.schedule(*self.env_steps);
        let horizons: Vec<usize> = ks
            .iter()
            .map(|k| k * self.cfg.tasks.max_episode_steps)
            .collect();
        let mut acting = Acting::new(self.net, self.spec, self.cfg, &budgets);
        let mut round = self.start_round(venv, &budgets, ks);
        while round.active.iter().any(|&x| x) {
            if self.quit.is_some_and(|q| q.load(Ordering::Relaxed)) {
                return Ok((Vec::new(), RoundStats::default()));
            }
            let eps: Vec<f64> = (0..venv.len())
                .map(|i| exploration.at(round.trajs[i].len(), horizons[i], eps_scale[i]))
                .collect();
            let (net_actions, env_actions, ctg_now) = self.act(venv, &mut acting, &round, &eps)?;
            round.record_inputs(&ctg_now, &net_actions, &env_actions);
            let outcomes = self.step_envs(venv, &env_actions)?;
            round.record_outcomes(venv, &outcomes, &net_actions);
        }
        *self.env_steps += round.steps;
        let radii = (
            self.cfg.novelty.novelty_cell,
            crate::signals::repeat_radius(self.env),
        );
        let mut stats = round_stats(&round.trajs, round.steps, self.spec, radii);
        if round.slots > 0 {
            stats.goal_slots = GoalSlotStats::of(&round.trajs, &round.hidden);
        }
        Ok((round.trajs, stats))
    }

    /// The round's trajectories, empty but for their budgets and goals,
    /// which of them hide their goal slots, and the first step's input.
    fn start_round(&mut self, venv: &VecEnv, budgets: &[f32], ks: Vec<usize>) -> InRound {
        let n = venv.len();
        let trajs: Vec<Trajectory> = budgets
            .iter()
            .enumerate()
            .map(|(i, &budget)| Trajectory {
                budget,
                goal: venv.env(i).goal_position(),
                ..Default::default()
            })
            .collect();
        // Drawn only while some goal is hidden, so other runs keep their stream.
        let hide_share = self.cfg.goal.goal_hidden_share_at(*self.env_steps);
        let hidden: Vec<bool> = (0..n)
            .map(|_| hide_share > 0.0 && self.rng.r#gen::<f64>() < hide_share)
            .collect();
        let (od, a) = (self.spec.obs_dim, self.spec.act_flat());
        let slots = self.cfg.goal.shown_slots();
        let mut obs = venv.observations().to_vec();
        hide_slots(&mut obs, od, slots, &hidden);
        InRound {
            trajs,
            active: vec![true; n],
            hidden,
            ks,
            od,
            a,
            slots,
            next: NextInput::first(obs, od, a),
            ep_ret: vec![0f32; n],
            ep_cost: vec![0f32; n],
            steps: 0,
        }
    }

    /// The actions at the round's next step: the CTGs updated, the tokens
    /// written, one forward step through the cache, actions sampled with
    /// exploration `eps` (scripted in first episodes with
    /// `scripted_first_episode`). Returns them as the network sees them and
    /// as the environments take them, with the CTGs the policy saw.
    fn act(
        &mut self,
        venv: &VecEnv,
        acting: &mut Acting,
        round: &InRound,
        eps: &[f64],
    ) -> Result<(Vec<f32>, EnvActions, Vec<f32>), EppoError> {
        let input = round.input();
        let ctg_now = acting.observe(&input);
        self.times
            .time(|t| &mut t.tokens, || acting.write_tokens(&input));
        let (net, spec, rng) = (self.net, self.spec, &mut *self.rng);
        let (mut net_actions, mut env_actions) = self.times.time(
            |t| &mut t.acting,
            || -> Result<_, EppoError> {
                let policy = acting.forward(net)?;
                Ok(sample_actions(&policy, spec, eps, false, rng))
            },
        )?;
        if self.cfg.goal.scripted_first_episode {
            let first_episode: Vec<bool> = (0..venv.len())
                .map(|i| round.active[i] && round.trajs[i].episode_returns.is_empty())
                .collect();
            script_actions(
                venv,
                self.spec,
                &first_episode,
                &mut net_actions,
                &mut env_actions,
            );
        }
        Ok((net_actions, env_actions, ctg_now))
    }

    /// Steps every environment with its action.
    fn step_envs(
        &mut self,
        venv: &mut VecEnv,
        env_actions: &EnvActions,
    ) -> Result<Vec<StepOutcome>, EppoError> {
        self.times.time(
            |t| &mut t.env_step,
            || -> Result<_, EppoError> {
                Ok(match env_actions {
                    EnvActions::Discrete(idx) => venv.step(VecAction::Discrete(idx))?,
                    EnvActions::Continuous(v) => venv.step(VecAction::Continuous(v))?,
                }
                .to_vec())
            },
        )
    }

    /// Draws one round's tasks (fresh centre-oriented, or from the pool),
    /// sets them in the environments and resets them; returns each
    /// trajectory's budget, K and exploration scale.
    fn draw_tasks(&mut self, venv: &mut VecEnv) -> Result<RoundDraws, EppoError> {
        let n = venv.len();
        let spawn = spawn_config(self.env);
        let (mut budgets, mut ks, mut seeds) = (vec![0f32; n], vec![0usize; n], vec![0u64; n]);
        let mut eps_scale = vec![1f64; n];
        for i in 0..n {
            let index = match self.cfg.tasks.task_pool {
                0 => *self.tasks_drawn,
                pool => *self.tasks_drawn % pool,
            };
            let seed = pretrain_task_seed(self.cfg.run.seed, index);
            *self.tasks_drawn += 1;
            let task = sample_task(&spawn, Orientation::Centre, seed)?;
            venv.set_task(i, &task)?;
            budgets[i] = self
                .rng
                .gen_range(self.cfg.tasks.ctg_min..=self.cfg.tasks.ctg_max);
            ks[i] = self
                .rng
                .gen_range(self.cfg.tasks.k_min..=self.cfg.tasks.k_max);
            seeds[i] = self.rng.r#gen();
            if self.cfg.exploration.eps_random_scale {
                eps_scale[i] = self.rng.r#gen();
            }
        }
        self.times
            .time(|t| &mut t.env_step, || venv.reset(&seeds))?;
        Ok((budgets, ks, eps_scale))
    }
}

/// One collection round under way: its trajectories as they grow, which
/// still collect, and the step input each environment gives the policy next.
struct InRound {
    trajs: Vec<Trajectory>,
    /// Fewer than its K episodes finished.
    active: Vec<bool>,
    /// Its goal slots blanked throughout.
    hidden: Vec<bool>,
    ks: Vec<usize>,
    /// Observation width, action width, goal slots at the observation's end.
    od: usize,
    a: usize,
    slots: usize,
    next: NextInput,
    /// Return and cost of each running episode so far.
    ep_ret: Vec<f32>,
    ep_cost: Vec<f32>,
    /// Environment steps of the active trajectories.
    steps: u64,
}

impl InRound {
    /// The policy's input at the next step.
    fn input(&self) -> StepInput<'_> {
        self.next.input()
    }

    /// Appends the step's input and action to each active trajectory.
    fn record_inputs(&mut self, ctg_now: &[f32], net_actions: &[f32], env_actions: &EnvActions) {
        let (od, a) = (self.od, self.a);
        for i in (0..self.trajs.len()).filter(|&i| self.active[i]) {
            let t = &mut self.trajs[i];
            t.obs
                .extend_from_slice(&self.next.obs[i * od..(i + 1) * od]);
            t.actions
                .extend_from_slice(&net_actions[i * a..(i + 1) * a]);
            if let EnvActions::Discrete(idx) = env_actions {
                t.action_idx.push(idx[i] as i64);
            }
            t.ctg.push(ctg_now[i]);
            t.start.push(self.next.start[i]);
            t.episode.push(t.episode_returns.len() as u32);
        }
    }

    /// Takes the step's outcomes: the next input of every environment, and
    /// what each active trajectory received.
    fn record_outcomes(&mut self, venv: &VecEnv, outcomes: &[StepOutcome], net_actions: &[f32]) {
        let (od, a, slots) = (self.od, self.a, self.slots);
        self.next.obs.copy_from_slice(venv.observations());
        hide_slots(&mut self.next.obs, od, slots, &self.hidden);
        for (i, &o) in outcomes.iter().enumerate() {
            self.next
                .take_outcome(i, &o, &net_actions[i * a..(i + 1) * a], venv);
            if self.hidden[i] {
                self.next.arrived_row(i)[od - slots..].fill(0.0);
            }
            if self.active[i] {
                self.extend_trajectory(i, o);
            }
        }
    }

    /// Appends outcome `o` to trajectory `i`, closing its episode when the
    /// step ended one, and the trajectory after its K episodes.
    fn extend_trajectory(&mut self, i: usize, o: StepOutcome) {
        let od = self.od;
        self.steps += 1;
        let t = &mut self.trajs[i];
        t.next_obs
            .extend_from_slice(&self.next.arrived[i * od..(i + 1) * od]);
        t.rewards.push(o.reward);
        t.costs.push(o.cost);
        // Kept apart all the way into the TD targets (see make_batch).
        t.terminated.push(o.terminated);
        t.truncated.push(o.truncated);
        self.ep_ret[i] += o.reward;
        self.ep_cost[i] += o.cost;
        if o.done() {
            t.episode_returns.push(self.ep_ret[i]);
            t.episode_costs.push(self.ep_cost[i]);
            t.episode_success.push(o.terminated);
            self.ep_ret[i] = 0.0;
            self.ep_cost[i] = 0.0;
            if t.episode_returns.len() == self.ks[i] {
                self.active[i] = false;
            }
        }
    }
}

/// Per-batch acting state: the KV cache and each trajectory's CTG.
pub(super) struct Acting {
    pub(super) cache: KvCache,
    pub(super) budgets: Vec<f32>,
    pub(super) ctg: Vec<f32>,
    pub(super) tokens: Vec<f32>,
    pub(super) spec: NetSpec,
    pub(super) cfg: EppoConfig,
}

/// The policy's output for B trajectories, on the CPU.
pub(super) enum Policy {
    /// (B, A) probabilities.
    Discrete(Vec<f32>, usize),
    /// (B, A) means and log-stds.
    Continuous(Vec<f32>, Vec<f32>, usize),
}

pub(super) enum EnvActions {
    Discrete(Vec<usize>),
    Continuous(Vec<f32>),
}

impl Acting {
    pub(super) fn new(net: &EppoNet, spec: &NetSpec, cfg: &EppoConfig, budgets: &[f32]) -> Self {
        Acting {
            cache: net.new_cache(),
            budgets: budgets.to_vec(),
            ctg: budgets.to_vec(),
            tokens: Vec::new(),
            spec: spec.clone(),
            cfg: cfg.clone(),
        }
    }

    /// Updates each CTG from the step's input (restart at the budget on an
    /// episode's first step, else decrease by the cost just received) and
    /// returns the CTGs the policy sees.
    pub(super) fn observe(&mut self, input: &StepInput<'_>) -> Vec<f32> {
        for i in 0..self.budgets.len() {
            self.ctg[i] = if input.episode_start[i] {
                self.budgets[i]
            } else {
                self.ctg[i] - input.cost[i]
            };
        }
        self.ctg.clone()
    }

    /// Encodes one step of B trajectories through the cache; returns the policy.
    pub(super) fn policy(
        &mut self,
        net: &EppoNet,
        input: &StepInput<'_>,
    ) -> Result<Policy, EppoError> {
        self.write_tokens(input);
        self.forward(net)
    }

    /// Writes the step's B tokens (after [`Acting::observe`] set the CTGs).
    pub(super) fn write_tokens(&mut self, input: &StepInput<'_>) {
        let b = self.budgets.len();
        let (od, a) = (self.spec.obs_dim, self.spec.act_flat());
        self.tokens.clear();
        for i in 0..b {
            push_token(
                &self.spec,
                &self.cfg,
                &mut self.tokens,
                &input.obs[i * od..(i + 1) * od],
                &input.arrived_obs[i * od..(i + 1) * od],
                &input.prev_action[i * a..(i + 1) * a],
                input.reward[i],
                input.cost[i],
                self.ctg[i],
                input.episode_start[i],
            );
        }
    }

    /// The KV-cached forward step over the written tokens; returns the policy.
    pub(super) fn forward(&mut self, net: &EppoNet) -> Result<Policy, EppoError> {
        let b = self.budgets.len();
        let a = self.spec.act_flat();
        let device = net.enc_1.ws.device();
        let x = Tensor::from_slice(&self.tokens)
            .view([b as i64, 1, self.spec.token_dim() as i64])
            .to_device(device); // (B, 1, token_dim)
        tch::no_grad(|| {
            let h = net.encode_step(&x, &mut self.cache)?.squeeze_dim(1); // (B, 1, D) -> (B, D)
            Ok(match self.spec.n_actions {
                Some(n) => {
                    let p = net
                        .actor
                        .forward(&h)
                        .softmax(-1, Kind::Float)
                        .to_device(Device::Cpu);
                    Policy::Discrete(Vec::<f32>::try_from(&p.view([-1]))?, n)
                }
                None => {
                    let (m, s) = net.gaussian(&h);
                    let m = Vec::<f32>::try_from(&m.to_device(Device::Cpu).reshape([-1]))?;
                    let s = Vec::<f32>::try_from(&s.to_device(Device::Cpu).reshape([-1]))?;
                    Policy::Continuous(m, s, a)
                }
            })
        })
    }
}

/// Picks actions: sampled or the mode. On top of a sample, row i explores
/// by `eps[i]` (rows past the slice take none): for discrete actions, a
/// uniform action with probability `eps[i]`; for continuous ones, AMAGO's
/// TD3-style noise, `clamp(x + eps[i] N(0, 1), -1, 1)` on the tanh-squashed
/// action. Returns the actions as the network sees them and as the
/// environment takes them.
pub(super) fn sample_actions(
    policy: &Policy,
    spec: &NetSpec,
    eps: &[f64],
    greedy: bool,
    rng: &mut ChaCha8Rng,
) -> (Vec<f32>, EnvActions) {
    match policy {
        Policy::Discrete(p, n) => {
            let n = *n;
            let b = p.len() / n;
            let mut onehot = vec![0f32; b * n];
            let idx: Vec<usize> = (0..b)
                .map(|i| {
                    let row = &p[i * n..(i + 1) * n];
                    let k = if greedy {
                        row.iter()
                            .enumerate()
                            .fold(0, |best, (k, &x)| if x > row[best] { k } else { best })
                    } else if rng.r#gen::<f64>() < eps.get(i).copied().unwrap_or(0.0) {
                        rng.gen_range(0..n)
                    } else {
                        let u: f32 = rng.r#gen();
                        let mut acc = 0.0;
                        row.iter()
                            .position(|&x| {
                                acc += x;
                                u < acc
                            })
                            .unwrap_or(n - 1)
                    };
                    onehot[i * n + k] = 1.0;
                    k
                })
                .collect();
            (onehot, EnvActions::Discrete(idx))
        }
        Policy::Continuous(m, s, a) => {
            let mut net = Vec::with_capacity(m.len());
            let mut env = Vec::with_capacity(m.len());
            for (j, (&mu, &log_std)) in m.iter().zip(s).enumerate() {
                let k = j % a;
                let x = if greedy {
                    mu.tanh()
                } else {
                    let z: f32 = rng.sample(rand_distr::StandardNormal);
                    let x = (mu + log_std.exp() * z).tanh();
                    match eps.get(j / a).copied().unwrap_or(0.0) as f32 {
                        0.0 => x,
                        e => (x + e * rng.sample::<f32, _>(rand_distr::StandardNormal))
                            .clamp(-1.0, 1.0),
                    }
                };
                let (lo, hi) = (spec.act_low[k], spec.act_high[k]);
                net.push(x);
                env.push(lo + (x + 1.0) * 0.5 * (hi - lo));
            }
            (net, EnvActions::Continuous(env))
        }
    }
}

/// Blanks the `slots` shown at the end of the rows of `obs`, each `od` wide
/// (the goal of `goal_in_observation`), whose trajectory hides them.
fn hide_slots(obs: &mut [f32], od: usize, slots: usize, hidden: &[bool]) {
    for (row, _) in obs.chunks_mut(od).zip(hidden).filter(|(_, h)| **h) {
        row[od - slots..].fill(0.0);
    }
}

/// Replaces row i of the actions by the environment's scripted goal-seeking
/// action where `rows[i]` (the ladder's "return to a shown goal" rung).
fn script_actions(
    venv: &VecEnv,
    spec: &NetSpec,
    rows: &[bool],
    net_actions: &mut [f32],
    env_actions: &mut EnvActions,
) {
    let EnvActions::Continuous(env) = env_actions else {
        return;
    };
    let a = spec.act_flat();
    for i in (0..rows.len()).filter(|&i| rows[i]) {
        // `Learner::new` refuses the setting for environments without one.
        let Some(scripted) = venv.env(i).goal_seeking_action() else {
            continue;
        };
        for (k, &x) in scripted.iter().enumerate().take(a) {
            let (lo, hi) = (spec.act_low[k], spec.act_high[k]);
            let x = x.clamp(lo, hi);
            env[i * a + k] = x;
            net_actions[i * a + k] = 2.0 * (x - lo) / (hi - lo) - 1.0;
        }
    }
}
