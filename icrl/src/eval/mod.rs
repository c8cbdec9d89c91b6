//! In-context evaluation on held-out, edge-oriented tasks (SPEC section 5).
//!
//! This file is the protocol: tasks, conditions and the batched rollout.
//! Beside it: `report.rs` (results and their summaries), `load.rs` (the
//! agents: checkpoints loaded, the random policy), `command/` (the `eval`
//! command: checkpoints in, JSON, CSV, figures and an animation out, drawn
//! by `render.rs` and [`crate::plots`]) and `error.rs` (the command's errors).
//!
//! One *trajectory* is K episodes in one task under one conditioning (a cost
//! budget for EPPO, RTG/CTG targets for supervised pretraining), the agent's
//! context carried across the episodes and its parameters frozen. An
//! evaluation runs every (condition, task) pair: `conditions x tasks`
//! trajectories, acted on in lockstep batches of at most `batch` through one
//! [`VecEnv`] (auto-reset between episodes, environments stepped on `threads`
//! threads) and one batched `act` call per time step.
//!
//! Protocol decisions (the paper is silent):
//! - Curves over the episode index: for each task, the value of episode k is
//!   averaged over the conditions (the paper averages over 100 budgets), then
//!   the mean and standard error are taken over the tasks.
//! - Budget sweep: for each condition, the total return `sum_k G(tau_k)` and
//!   the maximum episode cost `max_k Gc(tau_k)` per task, mean and standard
//!   error over the tasks.
//! - The step input at an episode start inside a trajectory carries the last
//!   action, reward and cost of the previous episode (zeros only at the very
//!   first step), with `episode_start` set: the agent restarts its CTG there.
//! - The search itself, beside its outcome (discovery, revisit, found by
//!   k): the cells (side [`search_cell`](crate::signals::search_cell)) a trajectory first enters in each
//!   episode, averaged over the conditions with no earlier success
//!   (`search_new_cells`). An agent that drives one route in every episode
//!   scores near 0 after the first, however many goals it misses.
//! - In-context safety: the cost of each episode paid again, within
//!   [`repeat_radius`](crate::signals::repeat_radius) of where the trajectory paid a cost in an earlier
//!   episode (`repeat_cost`). With the hazards unseen, a first cost is the
//!   price of search; a repeat is a lesson the context held and the agent
//!   did not use.
//! - Trajectories that finished their K episodes keep being fed (their
//!   actions ignored) until the batch's longest one ends; no trajectory sees
//!   more than `K x t_max` steps.

pub mod command;
pub mod error;
pub mod load;
mod render;

use std::collections::HashSet;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safety_envs::vec_env::{VecAction, VecEnv, episode_seed};
use safety_envs::{
    CmdpEnv, EnvError, Orientation, Space, SpawnConfig, StepOutcome, Task, sample_task,
};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::agent::{Actions, AgentError, Conditioning, InContextAgent, NextInput, StepInput};
use crate::signals::{CostMemory, position_cell};
use crate::task_seeds::{self, PretrainTasks, SeedError};

pub use crate::report::{
    ConditionRecord, ConditionStats, EpisodeStats, EvalResult, HeldOut, RecordedEpisode, Recording,
    Summary, TaskRecord, Trend,
};

/// Something that builds one fresh environment (all with equal spaces).
pub type EnvFactory<'a> = dyn Fn() -> Result<Box<dyn CmdpEnv>, EnvError> + Sync + 'a;

/// An evaluation that cannot run or whose parts failed.
#[derive(Debug, Error)]
pub enum EvalError {
    /// Settings that make no sense (no tasks, no episodes, bad budgets, ...).
    #[error("invalid evaluation settings: {0}")]
    Config(String),
    /// The agent answered with the wrong number or kind of actions.
    #[error("agent output: {0}")]
    AgentOutput(String),
    /// A trajectory did not finish its episodes within `K x t_max` steps.
    #[error(
        "trajectory {trajectory} finished {done} of {episodes} episodes within {steps} steps: the environment does not end its episodes at its time limit"
    )]
    Stuck {
        trajectory: usize,
        done: usize,
        episodes: usize,
        steps: usize,
    },
    #[error(transparent)]
    Seeds(#[from] SeedError),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Agent(#[from] AgentError),
}

/// Settings of one evaluation.
#[derive(Clone, Debug, PartialEq)]
pub struct EvalConfig {
    /// Number of edge-oriented evaluation tasks (paper: 16).
    pub tasks: usize,
    /// Episodes per trajectory, K (paper: 50 SafeDarkRoom, 20 Point and Car).
    pub episodes: usize,
    /// One trajectory per condition and task.
    pub conditions: Vec<Conditioning>,
    /// Evaluation seed: picks the task seeds inside the reserved range.
    pub eval_seed: u64,
    /// Trajectories acted on together (memory grows with batch x context).
    pub batch: usize,
    /// Threads that step the environments.
    pub threads: usize,
    /// Act with the policy's mode instead of sampling.
    pub greedy: bool,
    /// The pretraining tasks of the checkpoint, when it records them: every
    /// evaluation task is checked against them.
    pub pretrain_tasks: Option<PretrainTasks>,
    /// Record every step of trajectory (condition, task) for rendering.
    pub record: Option<(usize, usize)>,
    /// Reseed libtorch's process-wide generator (used by agents that sample
    /// with `multinomial`) with this before evaluating, so results do not
    /// depend on what ran before in the process. The CLI sets it; tests leave
    /// it `None`, as tests running in parallel share that generator.
    pub torch_seed: Option<u64>,
    /// Task distribution: [`Orientation::Edge`] is the paper's held-out
    /// evaluation; [`Orientation::Centre`] (the pretraining distribution, on
    /// unseen seeds) is a diagnostic only.
    pub orientation: Orientation,
    /// Side of the cells that `new_cells` counts, in the units of the
    /// position at observation indices 0 and 1 ([`search_cell`](crate::signals::search_cell)).
    pub search_cell: f64,
    /// How near an earlier cost a cost counts as repeated, in the same
    /// units ([`repeat_radius`](crate::signals::repeat_radius)).
    pub repeat_radius: f64,
}

impl EvalConfig {
    /// Number of trajectories (conditions x tasks).
    pub fn trajectories(&self) -> usize {
        self.conditions.len() * self.tasks
    }

    /// Rejects settings that cannot give a meaningful evaluation.
    pub fn validate(&self) -> Result<(), EvalError> {
        if self.tasks == 0 {
            return Err(EvalError::Config(
                "the task set is empty: ask for at least one evaluation task (--tasks)".into(),
            ));
        }
        if self.episodes == 0 {
            return Err(EvalError::Config(
                "episodes per task must be at least 1 (--episodes)".into(),
            ));
        }
        if self.conditions.is_empty() {
            return Err(EvalError::Config(
                "no budgets (or RTG/CTG targets) to evaluate".into(),
            ));
        }
        if self.batch == 0 || self.threads == 0 {
            return Err(EvalError::Config(format!(
                "batch ({}) and threads ({}) must be at least 1",
                self.batch, self.threads
            )));
        }
        for c in &self.conditions {
            let (rtg, ctg) = match *c {
                Conditioning::Budget { ctg } => (0.0, ctg),
                Conditioning::Targets { rtg, ctg } => (rtg, ctg),
            };
            if !rtg.is_finite() || !ctg.is_finite() || ctg < 0.0 {
                return Err(EvalError::Config(format!(
                    "condition {c:?}: budgets and targets must be finite and the CTG non-negative"
                )));
            }
        }
        if let Some((c, t)) = self.record
            && (c >= self.conditions.len() || t >= self.tasks)
        {
            return Err(EvalError::Config(format!(
                "record = (budget index {c}, task index {t}) is outside the {} budgets x {} tasks \
                 evaluated: record one below those counts (indices count from 0)",
                self.conditions.len(),
                self.tasks
            )));
        }
        Ok(())
    }
}

/// A closed budget interval `[low, high]`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BudgetRange {
    pub low: f32,
    pub high: f32,
}

impl BudgetRange {
    /// Fails with a message naming the budget and the range when `b` lies outside.
    pub fn check(&self, b: f32) -> Result<f32, EvalError> {
        if b.is_finite() && b >= self.low && b <= self.high {
            Ok(b)
        } else {
            Err(EvalError::Config(format!(
                "budget {b} is outside the range [{}, {}] the policy was pretrained on",
                self.low, self.high
            )))
        }
    }
}

/// `n` distinct budgets drawn uniformly from `range` (SPEC section 5: 100 of
/// them, [1, 15] SafeDarkRoom, [10, 50] SafeDarkMujoco), in drawing order.
pub fn sample_budgets(range: BudgetRange, n: usize, seed: u64) -> Result<Vec<f32>, EvalError> {
    if !(range.low.is_finite() && range.high.is_finite() && range.low < range.high) {
        return Err(EvalError::Config(format!(
            "budget range [{}, {}] is empty or not finite",
            range.low, range.high
        )));
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut seen = HashSet::new();
    let mut out = Vec::with_capacity(n);
    // f32 has millions of values in any such range: duplicates are rare
    // redraws, and the loop cannot spin forever for the sizes used here.
    while out.len() < n {
        let b: f32 = rng.gen_range(range.low..=range.high);
        if seen.insert(b.to_bits()) {
            out.push(b);
        }
    }
    Ok(out)
}

/// The supervised route's sweep (SPEC section 4): CTG over `ctgs` and
/// RTG = max(0.5, CTG / 10).
pub fn targets_sweep(ctgs: &[f32]) -> Vec<Conditioning> {
    ctgs.iter()
        .map(|&ctg| Conditioning::Targets {
            rtg: (ctg / 10.0).max(0.5),
            ctg,
        })
        .collect()
}

/// `low, low + step, ..., high` (inclusive when it lands on it).
pub fn grid(low: f32, high: f32, step: f32) -> Vec<f32> {
    let n = ((high - low) / step).floor() as usize;
    (0..=n).map(|i| low + step * i as f32).collect()
}

/// The evaluation tasks of `eval_seed` (edge-oriented for the paper's
/// protocol), checked held out from the recorded pretraining tasks.
pub fn eval_tasks(
    spawn: &SpawnConfig,
    orientation: Orientation,
    tasks: usize,
    eval_seed: u64,
    pretrain: Option<&PretrainTasks>,
) -> Result<(Vec<(u64, Task)>, HeldOut), EvalError> {
    if tasks == 0 {
        return Err(EvalError::Config(
            "the task set is empty: ask for at least one evaluation task (--tasks)".into(),
        ));
    }
    let drawn = task_seeds::eval_task_seeds(eval_seed, tasks)?
        .into_iter()
        .map(|s| Ok((s, sample_task(spawn, orientation, s)?)))
        .collect::<Result<Vec<_>, EnvError>>()?;
    let held_out = match pretrain {
        Some(p) => {
            task_seeds::check_held_out(&drawn, p, spawn)?;
            HeldOut::Checked(p.clone())
        }
        None => HeldOut::SeedRangesOnly,
    };
    Ok((drawn, held_out))
}

/// Runs the evaluation: see the module documentation. `on_episodes` is told
/// how many episodes finished after each step (for a progress bar).
pub fn evaluate(
    agent: &mut dyn InContextAgent,
    make_env: &EnvFactory<'_>,
    spawn: &SpawnConfig,
    cfg: &EvalConfig,
    on_episodes: &mut dyn FnMut(usize),
) -> Result<EvalResult, EvalError> {
    cfg.validate()?;
    let (tasks, held_out) = eval_tasks(
        spawn,
        cfg.orientation,
        cfg.tasks,
        cfg.eval_seed,
        cfg.pretrain_tasks.as_ref(),
    )?;
    let (nc, nt, k_n) = (cfg.conditions.len(), cfg.tasks, cfg.episodes);
    let total = nc * nt;
    let b = cfg.batch.min(total);

    let envs = (0..b).map(|_| make_env()).collect::<Result<Vec<_>, _>>()?;
    let mut venv = VecEnv::new(envs, cfg.threads, true)?;
    let (obs_dim, act_space) = (venv.obs_dim(), venv.action_space());
    let t_max = venv.env(0).max_episode_steps();

    let mut result = EvalResult {
        tasks: tasks.iter().map(|(s, t)| TaskRecord::new(*s, t)).collect(),
        conditions: cfg.conditions.iter().map(|&c| c.into()).collect(),
        episodes: k_n,
        eval_seed: cfg.eval_seed,
        greedy: cfg.greedy,
        batch: b,
        held_out,
        orientation: cfg.orientation.to_string(),
        returns: vec![vec![Vec::with_capacity(k_n); nt]; nc],
        costs: vec![vec![Vec::with_capacity(k_n); nt]; nc],
        lengths: vec![vec![Vec::with_capacity(k_n); nt]; nc],
        reached_goal: vec![vec![Vec::with_capacity(k_n); nt]; nc],
        new_cells: vec![vec![Vec::with_capacity(k_n); nt]; nc],
        repeat_costs: vec![vec![Vec::with_capacity(k_n); nt]; nc],
        recording: None,
    };

    // Parameters frozen: nothing below builds a graph or touches an optimizer.
    let rollouts = || {
        tch::no_grad(|| -> Result<(), EvalError> {
            for first in (0..total).step_by(b) {
                // Trajectory j = condition * tasks + task; the last batch is padded
                // with copies of its first trajectory, whose results are dropped.
                let rows: Vec<usize> = (0..b)
                    .map(|i| if first + i < total { first + i } else { first })
                    .collect();
                let live = (total - first).min(b);
                run_batch(
                    agent,
                    &mut venv,
                    &tasks,
                    cfg,
                    &rows,
                    live,
                    (obs_dim, &act_space, t_max),
                    &mut result,
                    on_episodes,
                )?;
            }
            Ok(())
        })
    };
    // Sampled actions draw from libtorch's generator (AD's policy).
    match cfg.torch_seed {
        Some(seed) => crate::torch_rng::seeded(seed, rollouts),
        None => crate::torch_rng::drawing(rollouts),
    }?;
    Ok(result)
}

/// Per-row episode bookkeeping inside a batch.
#[derive(Clone, Default)]
struct RowState {
    /// Episodes finished.
    done: usize,
    ret: f32,
    cost: f32,
    len: u32,
    /// Cells first entered in this episode, of the trajectory's `visited`.
    new_cells: u32,
    /// Cost paid again in this episode ([`CostMemory`]).
    repeat_cost: f32,
}

impl RowState {
    /// Counts one step of the running episode, which arrived at `arrived`:
    /// its reward, cost and length, the cell it entered (new to the
    /// trajectory's `visited` or not), and its cost if paid again near one
    /// of an earlier episode (`cost_memory`).
    fn count_step(
        &mut self,
        o: StepOutcome,
        arrived: &[f32],
        visited: &mut HashSet<(i64, i64)>,
        cost_memory: &mut CostMemory,
        search_cell: f64,
    ) {
        self.ret += o.reward;
        self.cost += o.cost;
        self.len += 1;
        let cell = position_cell(arrived, search_cell);
        self.new_cells += u32::from(visited.insert(cell));
        if o.cost > 0.0 && cost_memory.paid(arrived) {
            self.repeat_cost += o.cost;
        }
    }

    /// Stores the finished episode of trajectory `row` (condition `row /
    /// tasks`, task `row % tasks`) in `result`, and starts the next.
    fn end_episode(
        &mut self,
        result: &mut EvalResult,
        row: usize,
        tasks: usize,
        reached_goal: bool,
    ) {
        let (c, t) = (row / tasks, row % tasks);
        result.returns[c][t].push(self.ret);
        result.costs[c][t].push(self.cost);
        result.lengths[c][t].push(self.len);
        result.reached_goal[c][t].push(reached_goal);
        result.new_cells[c][t].push(self.new_cells);
        result.repeat_costs[c][t].push(self.repeat_cost);
        *self = RowState {
            done: self.done + 1,
            ..Default::default()
        };
    }
}

#[allow(clippy::too_many_arguments)]
fn run_batch(
    agent: &mut dyn InContextAgent,
    venv: &mut VecEnv,
    tasks: &[(u64, Task)],
    cfg: &EvalConfig,
    rows: &[usize],
    live: usize,
    (obs_dim, act_space, t_max): (usize, &Space, usize),
    result: &mut EvalResult,
    on_episodes: &mut dyn FnMut(usize),
) -> Result<(), EvalError> {
    let (nt, k_n) = (cfg.tasks, cfg.episodes);
    let b = rows.len();
    let act_dim = act_space.flat_dim();
    let (seeds, recorded_row, mut recording) =
        start_batch(agent, venv, tasks, cfg, rows, live, obs_dim)?;

    let mut state = vec![RowState::default(); b];
    let mut visited = vec![HashSet::new(); b];
    let mut cost_memory = vec![CostMemory::new(cfg.repeat_radius); b];
    let mut input = NextInput::first(venv.observations().to_vec(), obs_dim, act_dim);
    let mut action_row = vec![0.0f32; act_dim];
    let mut discrete = Vec::with_capacity(b);
    let mut continuous = Vec::with_capacity(b * act_dim);
    let max_steps = k_n * t_max;

    for step in 0.. {
        if state[..live].iter().all(|s| s.done >= k_n) {
            break;
        }
        if step >= max_steps {
            let i = state[..live].iter().position(|s| s.done < k_n).unwrap_or(0);
            return Err(EvalError::Stuck {
                trajectory: rows[i],
                done: state[i].done,
                episodes: k_n,
                steps: max_steps,
            });
        }
        // Every later position is an arrival, counted below.
        for (i, seen) in visited
            .iter_mut()
            .enumerate()
            .filter(|&(i, _)| input.start[i])
        {
            seen.insert(position_cell(&input.obs[i * obs_dim..], cfg.search_cell));
        }
        let actions = agent.act(&input.input(), cfg.greedy)?;
        let outcomes = step_envs(venv, &actions, act_space, &mut discrete, &mut continuous)?;

        let mut finished = 0;
        for i in 0..b {
            let o = outcomes[i];
            match &actions {
                Actions::Discrete(a) => {
                    action_row.fill(0.0);
                    action_row[a[i]] = 1.0;
                }
                Actions::Continuous(_) => {
                    action_row.copy_from_slice(&continuous[i * act_dim..(i + 1) * act_dim]);
                }
            }
            input.take_outcome(i, &o, &action_row, venv);
            if recorded_row == Some(i)
                && let Some(r) = recording.as_mut()
                && state[i].done < k_n
            {
                let row = (i, obs_dim, act_dim);
                record_step(
                    r,
                    venv,
                    &actions,
                    &continuous,
                    &input.arrived,
                    o,
                    row,
                    (state[i].done, k_n, seeds[i]),
                );
            }
            let s = &mut state[i];
            if s.done >= k_n || i >= live {
                continue;
            }
            let arrived = &input.arrived[i * obs_dim..];
            s.count_step(
                o,
                arrived,
                &mut visited[i],
                &mut cost_memory[i],
                cfg.search_cell,
            );
            if o.done() {
                cost_memory[i].end_episode();
                s.end_episode(result, rows[i], nt, o.terminated);
                finished += 1;
            }
        }
        input.obs.copy_from_slice(venv.observations());
        if finished > 0 {
            on_episodes(finished);
        }
    }
    if let Some(r) = recording {
        result.recording = Some(r);
    }
    Ok(())
}

/// A batch's reset seeds, and the row recorded with its recording so far.
type BatchStart = (Vec<u64>, Option<usize>, Option<Recording>);

/// Sets each row's task, resets the agent with the rows' conditions and the
/// environments with their seeds; returns the seeds, and the row recorded
/// (if `cfg.record` falls in this batch) with its recording's first state.
fn start_batch(
    agent: &mut dyn InContextAgent,
    venv: &mut VecEnv,
    tasks: &[(u64, Task)],
    cfg: &EvalConfig,
    rows: &[usize],
    live: usize,
    obs_dim: usize,
) -> Result<BatchStart, EvalError> {
    let nt = cfg.tasks;
    let b = rows.len();
    let mut seeds = Vec::with_capacity(b);
    let mut conditioning = Vec::with_capacity(b);
    for (i, &j) in rows.iter().enumerate() {
        let (c, t) = (j / nt, j % nt);
        venv.set_task(i, &tasks[t].1)?;
        // Reset seeds depend on the task and the condition only, so a
        // trajectory's episodes do not depend on the batch it falls in.
        seeds.push(task_seeds::splitmix64(
            tasks[t].0 ^ task_seeds::splitmix64(c as u64),
        ));
        conditioning.push(cfg.conditions[c]);
    }
    agent.reset(&conditioning)?;
    venv.reset(&seeds)?;

    let recorded_row = cfg
        .record
        .map(|(c, t)| c * nt + t)
        .and_then(|j| rows[..live].iter().position(|&r| r == j));
    let recording = recorded_row.map(|i| {
        let (c, t) = (rows[i] / nt, rows[i] % nt);
        let first = RecordedEpisode {
            observations: vec![venv.observations()[i * obs_dim..(i + 1) * obs_dim].to_vec()],
            // VecEnv resets episode 0 with the base seed itself.
            reset_seed: seeds[i],
            ..Default::default()
        };
        Recording {
            condition: c,
            task: t,
            episodes: vec![first],
        }
    });
    Ok((seeds, recorded_row, recording))
}

/// Validates the agent's actions, converts them for the environments and
/// steps every environment once.
fn step_envs(
    venv: &mut VecEnv,
    actions: &Actions,
    act_space: &Space,
    discrete: &mut Vec<usize>,
    continuous: &mut Vec<f32>,
) -> Result<Vec<StepOutcome>, EvalError> {
    let b = venv.len();
    let act_dim = act_space.flat_dim();
    Ok(match (actions, act_space) {
        (Actions::Discrete(a), Space::Discrete { n }) if a.len() == b => {
            if let Some(bad) = a.iter().find(|&&x| x >= *n) {
                return Err(EvalError::AgentOutput(format!(
                    "discrete action {bad} outside 0..{n}"
                )));
            }
            discrete.clear();
            discrete.extend_from_slice(a);
            venv.step(VecAction::Discrete(discrete))?
        }
        (Actions::Continuous(a), Space::Box { low, high }) if a.len() == b * act_dim => {
            // Clip into the box, as Gymnasium's ClipAction would; NaN stays
            // NaN and the environment rejects it.
            continuous.clear();
            continuous.extend(
                a.iter()
                    .enumerate()
                    .map(|(i, &x)| x.clamp(low[i % act_dim], high[i % act_dim])),
            );
            venv.step(VecAction::Continuous(continuous))?
        }
        (got, space) => {
            return Err(EvalError::AgentOutput(format!(
                "{} for {b} trajectories in action space {space:?}",
                match got {
                    Actions::Discrete(a) => format!("{} discrete actions", a.len()),
                    Actions::Continuous(a) => format!("{} continuous values", a.len()),
                }
            )));
        }
    }
    .to_vec())
}

/// Appends row `i`'s step to the recording: where the action led, the
/// action, reward and cost; an episode's end opens the next episode.
#[allow(clippy::too_many_arguments)]
fn record_step(
    r: &mut Recording,
    venv: &VecEnv,
    actions: &Actions,
    continuous: &[f32],
    arrived: &[f32],
    o: StepOutcome,
    (i, obs_dim, act_dim): (usize, usize, usize),
    (done, k_n, seed): (usize, usize, u64),
) {
    let ep = r.episodes.last_mut().expect("one episode is always open");
    ep.observations
        .push(arrived[i * obs_dim..(i + 1) * obs_dim].to_vec());
    ep.actions.push(match actions {
        Actions::Discrete(a) => vec![a[i] as f32],
        Actions::Continuous(_) => continuous[i * act_dim..(i + 1) * act_dim].to_vec(),
    });
    ep.rewards.push(o.reward);
    ep.costs.push(o.cost);
    if o.done() && done + 1 < k_n {
        r.episodes.push(RecordedEpisode {
            observations: vec![venv.observations()[i * obs_dim..(i + 1) * obs_dim].to_vec()],
            reset_seed: episode_seed(seed, (done + 1) as u64),
            ..Default::default()
        });
    }
}

/// A uniformly random policy, for scale: ignores its context.
pub struct RandomAgent {
    space: Space,
    rng: ChaCha8Rng,
    batch: usize,
}

impl RandomAgent {
    /// A random policy over `action_space`, seeded.
    pub fn new(action_space: Space, seed: u64) -> Self {
        RandomAgent {
            space: action_space,
            rng: ChaCha8Rng::seed_from_u64(seed),
            batch: 0,
        }
    }
}

impl InContextAgent for RandomAgent {
    fn reset(&mut self, conditioning: &[Conditioning]) -> Result<(), AgentError> {
        self.batch = conditioning.len();
        Ok(())
    }

    fn act(&mut self, input: &StepInput<'_>, _greedy: bool) -> Result<Actions, AgentError> {
        if input.reward.len() != self.batch {
            return Err(AgentError::Input(format!(
                "{} rows for a batch of {}",
                input.reward.len(),
                self.batch
            )));
        }
        Ok(match &self.space {
            Space::Discrete { n } => {
                Actions::Discrete((0..self.batch).map(|_| self.rng.gen_range(0..*n)).collect())
            }
            Space::Box { low, high } => Actions::Continuous(
                (0..self.batch)
                    .flat_map(|_| low.iter().zip(high))
                    .map(|(&l, &h)| self.rng.gen_range(l..=h))
                    .collect::<Vec<_>>(),
            ),
        })
    }
}

/// The variables of `vs` as shallow clones (sharing storage), sorted by name:
/// a handle to read the current parameters while the agent owns `vs`.
pub fn shared_parameters(vs: &tch::nn::VarStore) -> Vec<(String, tch::Tensor)> {
    let mut vars: Vec<(String, tch::Tensor)> = vs
        .variables()
        .into_iter()
        .map(|(n, t)| (n, t.shallow_clone()))
        .collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    vars
}

/// A checksum of `params` (names and exact bit patterns, in the given order):
/// equal before and after an evaluation iff no parameter changed.
pub fn parameters_checksum(params: &[(String, tch::Tensor)]) -> Result<u64, AgentError> {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    let mut mix = |x: u64| h = task_seeds::splitmix64(h ^ x);
    for (name, t) in params {
        for b in name.bytes() {
            mix(b as u64);
        }
        let flat = t
            .detach()
            .to_kind(tch::Kind::Double)
            .flatten(0, -1)
            .to_device(tch::Device::Cpu);
        let values: Vec<f64> = Vec::<f64>::try_from(&flat)?;
        mix(values.len() as u64);
        for v in values {
            mix(v.to_bits());
        }
    }
    Ok(h)
}

/// [`parameters_checksum`] over every variable of `vs`.
pub fn varstore_checksum(vs: &tch::nn::VarStore) -> Result<u64, AgentError> {
    parameters_checksum(&shared_parameters(vs))
}

#[cfg(test)]
mod tests {
    use super::*;
    use safety_envs::{EnvName, EnvOptions, make_env, spawn_config};
    use tch::nn::{self, Module};

    fn darkroom() -> Result<Box<dyn CmdpEnv>, EnvError> {
        make_env(EnvName::DarkRoom, &EnvOptions::default())
    }

    fn small_config(conditions: Vec<Conditioning>) -> EvalConfig {
        EvalConfig {
            tasks: 4,
            episodes: 3,
            conditions,
            eval_seed: 0,
            batch: 5,
            threads: 2,
            greedy: false,
            pretrain_tasks: Some(PretrainTasks::centre(0, 1000)),
            record: Some((1, 2)),
            torch_seed: None,
            orientation: Orientation::Edge,
            search_cell: 1.0,
            repeat_radius: 0.5,
        }
    }

    /// A tiny libtorch policy: logits = W [obs, ctg-flag] + b, sampled.
    /// Records whether any forward ran with gradients enabled.
    struct TinyTorchAgent {
        vs: nn::VarStore,
        layer: nn::Linear,
        batch: usize,
        saw_grad: bool,
    }

    impl TinyTorchAgent {
        fn new() -> Self {
            let vs = nn::VarStore::new(tch::Device::Cpu);
            let layer = crate::torch_rng::drawing(|| {
                nn::linear(vs.root() / "policy", 2, 5, Default::default())
            });
            // Fixed weights, independent of libtorch's global generator (which
            // tests running in parallel share).
            tch::no_grad(|| {
                let w: Vec<f32> = (0..10).map(|i| ((i * 7 % 10) as f32 - 4.5) / 5.0).collect();
                layer
                    .ws
                    .shallow_clone()
                    .copy_(&tch::Tensor::from_slice(&w).view([5, 2]));
                if let Some(b) = &layer.bs {
                    let _ = b.shallow_clone().fill_(0.1);
                }
            });
            TinyTorchAgent {
                vs,
                layer,
                batch: 0,
                saw_grad: false,
            }
        }
    }

    impl InContextAgent for TinyTorchAgent {
        fn reset(&mut self, c: &[Conditioning]) -> Result<(), AgentError> {
            self.batch = c.len();
            Ok(())
        }
        fn act(&mut self, input: &StepInput<'_>, greedy: bool) -> Result<Actions, AgentError> {
            let obs = tch::Tensor::from_slice(input.obs).view([self.batch as i64, 2]);
            let logits = self.layer.forward(&obs);
            self.saw_grad |= logits.requires_grad();
            let a = if greedy {
                logits.argmax(-1, false)
            } else {
                logits
                    .softmax(-1, tch::Kind::Float)
                    .multinomial(1, true)
                    .squeeze_dim(-1)
            };
            let a: Vec<i64> = Vec::<i64>::try_from(&a)?;
            Ok(Actions::Discrete(
                a.into_iter().map(|x| x as usize).collect(),
            ))
        }
    }

    #[test]
    fn parameters_are_frozen_and_no_graph_is_built() {
        let mut agent = TinyTorchAgent::new();
        let before = varstore_checksum(&agent.vs).unwrap();
        let cfg = small_config(vec![Conditioning::Budget { ctg: 2.0 }]);
        let cfg = EvalConfig {
            record: None,
            ..cfg
        };
        let r = evaluate(
            &mut agent,
            &darkroom,
            &spawn_config(EnvName::DarkRoom),
            &cfg,
            &mut |_| {},
        )
        .unwrap();
        assert_eq!(varstore_checksum(&agent.vs).unwrap(), before);
        assert!(!agent.saw_grad, "a forward pass ran with gradients enabled");
        assert!(
            agent
                .vs
                .trainable_variables()
                .iter()
                .all(|v| !v.grad().defined())
        );
        assert_eq!(r.returns[0].len(), 4);
        // The checksum does see a change of one parameter by one ulp.
        tch::no_grad(|| {
            let mut w = agent.vs.variables()["policy.weight"].shallow_clone();
            let _ = w.get(0).get(0).fill_(f64::from(f32::from_bits(
                f32::to_bits(Vec::<f32>::try_from(&w.flatten(0, -1)).unwrap()[0]) + 1,
            )));
            let _ = &mut w;
        });
        assert_ne!(varstore_checksum(&agent.vs).unwrap(), before);
    }

    #[test]
    fn random_policy_runs_k_episodes_per_trajectory_and_records_one() {
        let conditions = vec![
            Conditioning::Budget { ctg: 1.0 },
            Conditioning::Budget { ctg: 5.0 },
        ];
        let cfg = small_config(conditions);
        let mut agent = RandomAgent::new(Space::Discrete { n: 5 }, 1);
        let mut finished = 0;
        let spawn = spawn_config(EnvName::DarkRoom);
        let r = evaluate(&mut agent, &darkroom, &spawn, &cfg, &mut |n| finished += n).unwrap();
        assert_eq!(finished, 2 * 4 * 3);
        assert!(matches!(r.held_out, HeldOut::Checked(_)));
        for c in 0..2 {
            for t in 0..4 {
                assert_eq!(r.returns[c][t].len(), 3);
                for k in 0..3 {
                    let len = r.lengths[c][t][k];
                    assert!((1..=30).contains(&len));
                    // Reward 1 exactly when the episode ended at the goal.
                    assert_eq!(r.returns[c][t][k] == 1.0, r.reached_goal[c][t][k]);
                    assert_eq!(
                        r.reached_goal[c][t][k],
                        len < 30 || r.returns[c][t][k] == 1.0
                    );
                    assert!(r.costs[c][t][k] <= len as f32);
                }
            }
        }
        // Tasks are the edge-oriented draws of the reserved seeds.
        let seeds = task_seeds::eval_task_seeds(0, 4).unwrap();
        for (rec, s) in r.tasks.iter().zip(&seeds) {
            let t = sample_task(&spawn, Orientation::Edge, *s).unwrap();
            assert_eq!(*rec, TaskRecord::new(*s, &t));
        }
        // The recording matches the recorded trajectory's results.
        let rec = r.recording.as_ref().unwrap();
        assert_eq!((rec.condition, rec.task, rec.episodes.len()), (1, 2, 3));
        for (k, ep) in rec.episodes.iter().enumerate() {
            assert_eq!(ep.actions.len(), r.lengths[1][2][k] as usize);
            assert_eq!(ep.observations.len(), ep.actions.len() + 1);
            assert_eq!(ep.rewards.iter().sum::<f32>(), r.returns[1][2][k]);
            assert_eq!(ep.costs.iter().sum::<f32>(), r.costs[1][2][k]);
            // Replaying the actions from the recorded reset seed reproduces it.
            let mut env = darkroom().unwrap();
            env.set_task(&sample_task(&spawn, Orientation::Edge, seeds[2]).unwrap())
                .unwrap();
            let mut obs = vec![0.0; 2];
            env.reset(ep.reset_seed, &mut obs).unwrap();
            assert_eq!(obs, ep.observations[0]);
            for (i, a) in ep.actions.iter().enumerate() {
                let o = env
                    .step(safety_envs::Action::Discrete(a[0] as usize), &mut obs)
                    .unwrap();
                assert_eq!(obs, ep.observations[i + 1]);
                assert_eq!((o.reward, o.cost), (ep.rewards[i], ep.costs[i]));
            }
        }
        // Cells first entered per episode: the recorded positions not seen
        // earlier in the trajectory, episode starts included.
        let mut seen = HashSet::new();
        for (k, ep) in rec.episodes.iter().enumerate() {
            seen.insert(position_cell(&ep.observations[0], 1.0));
            let fresh = ep.observations[1..]
                .iter()
                .filter(|o| seen.insert(position_cell(o, 1.0)))
                .count();
            assert_eq!(fresh as u32, r.new_cells[1][2][k], "episode {k}");
        }
        assert!(
            r.new_cells[1][2].iter().sum::<u32>() > 0,
            "a random walk enters new cells"
        );
        // Repeated cost per episode: the recorded costs paid on arriving in a
        // cell where an earlier episode paid one (radius 0.5: the same cell).
        let mut costly = HashSet::new();
        for (k, ep) in rec.episodes.iter().enumerate() {
            let arrivals = ep.observations[1..].iter().zip(&ep.costs);
            let paid: Vec<_> = arrivals.filter(|&(_, &c)| c > 0.0).collect();
            let again: f32 = paid
                .iter()
                .filter(|(o, _)| costly.contains(&position_cell(o, 1.0)))
                .map(|&(_, &c)| c)
                .sum();
            assert_eq!(again, r.repeat_costs[1][2][k], "episode {k}");
            costly.extend(paid.iter().map(|(o, _)| position_cell(o, 1.0)));
        }
        let again: f32 = r.repeat_costs.iter().flatten().flatten().sum();
        assert!(again > 0.0, "a random walk pays some cost twice");
    }

    #[test]
    fn batch_size_and_threads_do_not_change_a_deterministic_agents_results() {
        let spawn = spawn_config(EnvName::DarkRoom);
        let conditions = vec![
            Conditioning::Budget { ctg: 1.0 },
            Conditioning::Budget { ctg: 5.0 },
        ];
        let cfg = EvalConfig {
            greedy: true,
            ..small_config(conditions)
        };
        // 8 trajectories in batches of 5 (the last one padded), then all at once.
        let a = evaluate(
            &mut TinyTorchAgent::new(),
            &darkroom,
            &spawn,
            &cfg,
            &mut |_| {},
        )
        .unwrap();
        let cfg = EvalConfig {
            batch: 8,
            threads: 1,
            ..cfg
        };
        let b = evaluate(
            &mut TinyTorchAgent::new(),
            &darkroom,
            &spawn,
            &cfg,
            &mut |_| {},
        )
        .unwrap();
        assert_eq!(a.returns, b.returns);
        assert_eq!(a.costs, b.costs);
        assert_eq!(a.lengths, b.lengths);
        assert_eq!(a.recording, b.recording);
    }

    #[test]
    fn bad_settings_are_rejected_with_clear_errors() {
        let spawn = spawn_config(EnvName::DarkRoom);
        let mut agent = RandomAgent::new(Space::Discrete { n: 5 }, 1);
        let base = small_config(vec![Conditioning::Budget { ctg: 1.0 }]);
        let e = evaluate(&mut agent, &darkroom, &spawn, &base, &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("record = (budget index 1, task index 2) is outside"),
            "{e}"
        );
        let base = EvalConfig {
            record: None,
            ..base
        };
        let run = |cfg: EvalConfig, agent: &mut RandomAgent| {
            evaluate(agent, &darkroom, &spawn, &cfg, &mut |_| {})
                .unwrap_err()
                .to_string()
        };
        let e = run(
            EvalConfig {
                tasks: 0,
                ..base.clone()
            },
            &mut agent,
        );
        assert!(e.contains("task set is empty"), "{e}");
        let e = run(
            EvalConfig {
                conditions: vec![],
                ..base.clone()
            },
            &mut agent,
        );
        assert!(e.contains("no budgets"), "{e}");
        let e = run(
            EvalConfig {
                conditions: vec![Conditioning::Budget { ctg: f32::NAN }],
                ..base.clone()
            },
            &mut agent,
        );
        assert!(e.contains("finite"), "{e}");
        // A continuous-action agent on a discrete environment.
        let mut wrong = RandomAgent::new(
            Space::Box {
                low: vec![-1.0; 2],
                high: vec![1.0; 2],
            },
            0,
        );
        let e = evaluate(&mut wrong, &darkroom, &spawn, &base, &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(e.contains("continuous values"), "{e}");
        let range = BudgetRange {
            low: 1.0,
            high: 15.0,
        };
        assert!(
            range
                .check(0.5)
                .unwrap_err()
                .to_string()
                .contains("outside the range [1, 15]")
        );
        assert_eq!(range.check(15.0).unwrap(), 15.0);
    }

    #[test]
    fn budgets_are_distinct_in_range_and_sweeps_follow_the_spec() {
        let range = BudgetRange {
            low: 1.0,
            high: 15.0,
        };
        let b = sample_budgets(range, 100, 3).unwrap();
        assert_eq!(b.len(), 100);
        assert!(b.iter().all(|&x| (1.0..=15.0).contains(&x)));
        let distinct: HashSet<u32> = b.iter().map(|x| x.to_bits()).collect();
        assert_eq!(distinct.len(), 100);
        assert_eq!(b, sample_budgets(range, 100, 3).unwrap());
        let sweep = targets_sweep(&grid(5.0, 15.0, 1.0));
        assert_eq!(sweep.len(), 11);
        assert_eq!(sweep[0], Conditioning::Targets { rtg: 0.5, ctg: 5.0 });
        assert_eq!(
            sweep[10],
            Conditioning::Targets {
                rtg: 1.5,
                ctg: 15.0
            }
        );
        assert_eq!(grid(0.0, 10.0, 1.0).len(), 11);
    }

    /// A fixed result: 2 conditions (CTG 1 and 3), 3 tasks, 2 episodes.
    fn fake_result() -> EvalResult {
        let task = TaskRecord {
            seed: 0,
            grid_size: 9,
            goal: [0, 0],
            obstacles: vec![],
        };
        EvalResult {
            tasks: vec![task; 3],
            conditions: vec![
                ConditionRecord {
                    rtg: None,
                    ctg: 1.0,
                },
                ConditionRecord {
                    rtg: None,
                    ctg: 3.0,
                },
            ],
            episodes: 2,
            eval_seed: 0,
            greedy: false,
            batch: 6,
            held_out: HeldOut::SeedRangesOnly,
            orientation: "edge".into(),
            returns: vec![
                vec![vec![0.0, 1.0], vec![1.0, 1.0], vec![0.0, 0.0]],
                vec![vec![0.0, 1.0], vec![1.0, 1.0], vec![1.0, 1.0]],
            ],
            costs: vec![
                vec![vec![2.0, 0.0], vec![0.0, 0.0], vec![4.0, 2.0]],
                vec![vec![2.0, 0.0], vec![0.0, 0.0], vec![4.0, 4.0]],
            ],
            lengths: vec![vec![vec![1, 1]; 3]; 2],
            reached_goal: vec![
                vec![vec![false, true], vec![true, true], vec![false, false]],
                vec![vec![false, true], vec![true, true], vec![true, true]],
            ],
            new_cells: vec![
                vec![vec![3, 2], vec![4, 0], vec![5, 1]],
                vec![vec![1, 6], vec![2, 0], vec![7, 0]],
            ],
            // Task 2's second episodes pay all their cost again.
            repeat_costs: vec![
                vec![vec![0.0, 0.0], vec![0.0, 0.0], vec![0.0, 2.0]],
                vec![vec![0.0, 0.0], vec![0.0, 0.0], vec![0.0, 4.0]],
            ],
            recording: None,
        }
    }

    #[test]
    fn statistics_of_a_fixed_result_are_exact() {
        let s = fake_result().summary();
        let close = |a: f64, b: f64| assert!((a - b).abs() < 1e-12, "{a} != {b}");
        // Episode 1: per task (averaged over conditions) returns 0, 1, 0.5.
        let e1 = &s.per_episode[0];
        assert_eq!(e1.k, 1);
        close(e1.ret.mean, 0.5);
        close(e1.ret.se, (0.25f64 / 3.0).sqrt());
        // Costs 2, 0, 4: mean 2, sample variance 4, s.e. sqrt(4/3).
        close(e1.cost.mean, 2.0);
        close(e1.cost.se, (4.0f64 / 3.0).sqrt());
        // Over budget: task 0 (2 > 1 only), task 1 never, task 2 both.
        close(e1.violation.mean, 0.5);
        close(e1.success.mean, 0.5);
        // Episode 1: nothing earlier, so discovery is success and revisit undefined.
        close(e1.discovery.mean, 0.5);
        assert!(e1.revisit.mean.is_nan() && e1.revisit.n == 0);
        // Episode 2: task 0 discovers in both conditions (1), task 2's
        // undiscovered condition fails (0); tasks 1 and 2 revisit (1, 1).
        let e2 = &s.per_episode[1];
        close(e2.discovery.mean, 0.5);
        assert_eq!(e2.discovery.n, 2);
        close(e2.revisit.mean, 1.0);
        assert_eq!(e2.revisit.n, 2);
        close(e2.found_by.mean, 2.5 / 3.0);
        close(e1.found_by.mean, 0.5);
        // New cells while searching: episode 1 counts every condition (tasks
        // 2, 3, 6); episode 2 only those without a success in episode 1:
        // task 0's two (2, 6), task 2's first (1); task 1 has none.
        close(e1.search_new_cells.mean, 11.0 / 3.0);
        close(e2.search_new_cells.mean, 2.5);
        assert_eq!(e2.search_new_cells.n, 2);
        // Older result files have no cell counts: undefined, not zero.
        let older = EvalResult {
            new_cells: vec![],
            ..fake_result()
        };
        assert!(
            older.summary().per_episode[1]
                .search_new_cells
                .mean
                .is_nan()
        );
        // Repeated cost per task: none in episode 1; 0, 0, 3 in episode 2.
        close(e1.repeat_cost.mean, 0.0);
        close(e2.repeat_cost.mean, 1.0);
        let older = EvalResult {
            repeat_costs: vec![],
            ..fake_result()
        };
        assert!(older.summary().per_episode[1].repeat_cost.mean.is_nan());
        // Episode 2: returns 1, 1, 0.5; costs 0, 0, 3.
        close(s.per_episode[1].ret.mean, 2.5 / 3.0);
        close(s.per_episode[1].cost.mean, 1.0);
        // Condition CTG 3: totals 1, 2, 2; max costs 2, 0, 4; violations 0, 0, 1.
        let c1 = &s.per_condition[1];
        close(c1.total_return.mean, 5.0 / 3.0);
        close(c1.total_return.se, ((1.0f64 / 3.0) / 3.0).sqrt());
        close(c1.max_cost.mean, 2.0);
        close(c1.violation.mean, 1.0 / 3.0);
        close(c1.mean_cost.mean, (1.0 + 0.0 + 4.0) / 3.0);
        // Trend (window 1): gains 1, 0, 0; cost drops 2, 0, 1.
        assert_eq!(s.trend.window, 1);
        close(s.trend.return_gain.mean, 1.0 / 3.0);
        close(s.trend.cost_drop.mean, 1.0);
        close(s.trend.first_cost.mean, 2.0);
        close(s.mean_budget as f64, 2.0);
        // Slopes over CTG 1 -> 3: totals (1, 1), (2, 2), (0, 2) -> 0, 0, 1;
        // max costs (2, 2), (0, 0), (4, 4) -> 0.
        let r = s.total_return_slope.unwrap();
        close(r.mean, 1.0 / 3.0);
        close(
            r.se,
            ((2.0 * (1.0f64 / 9.0) + 4.0 / 9.0) / 2.0 / 3.0).sqrt(),
        );
        close(s.max_cost_slope.unwrap().mean, 0.0);
        // One condition: no slope.
        let mut one = fake_result();
        one.conditions.truncate(1);
        assert!(one.summary().total_return_slope.is_none());
        assert_eq!(s.per_episode[0].ret.n, 3);
    }

    #[test]
    fn figures_and_animation_are_written_and_non_empty() {
        let dir = std::env::temp_dir().join(format!("icrl-eval-figures-{}", std::process::id()));
        let spawn = spawn_config(EnvName::DarkRoom);
        let cfg = small_config(vec![
            Conditioning::Budget { ctg: 1.0 },
            Conditioning::Budget { ctg: 5.0 },
        ]);
        let r = evaluate(
            &mut RandomAgent::new(Space::Discrete { n: 5 }, 2),
            &darkroom,
            &spawn,
            &cfg,
            &mut |_| {},
        )
        .unwrap();
        let envs = [crate::plots::EnvCurves {
            env: "SafeDarkRoom".into(),
            methods: vec![
                ("EPPO".into(), fake_result().summary()),
                ("AD".into(), r.summary()),
            ],
            random: Some(r.summary()),
        }];
        let mut files = crate::plots::figure1(&envs, &dir.join("figure1")).unwrap();
        files.extend(crate::plots::figure2(&envs, &dir.join("figure2")).unwrap());
        let rec = r.recording.as_ref().unwrap();
        let gif = dir.join("task.gif");
        let frames =
            crate::plots::darkroom_animation(rec, &r.tasks[rec.task], 5.0, &|k| k == 0, &gif)
                .unwrap();
        let first_len = rec.episodes[0].observations.len();
        assert_eq!(frames, first_len + rec.episodes.len() - 1);
        files.push(gif);
        for f in &files {
            let len = std::fs::metadata(f).unwrap().len();
            assert!(len > 1000, "{} has {len} bytes", f.display());
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
