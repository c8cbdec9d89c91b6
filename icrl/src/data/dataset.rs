//! Learning-history datasets for supervised pretraining (SPEC section 4).
//!
//! For every pretraining task (centre-oriented, seeds from
//! [`crate::task_seeds::pretrain_task_seed`]) and every cost limit, one
//! learning history, made by either source:
//!
//! - [`Source::PpoLagrangian`]: PPO-Lagrangian from scratch (the paper's dataset).
//! - [`Source::NoisyOptimal`]: AD-eps (Zisman et al., 2023; paper Appendix D): an
//!   optimal policy that knows the task's layout, with action noise falling
//!   linearly from 1 (uniform random) to 0 over the history. SafeDarkRoom only.
//!   "Optimal" under a cost limit `d`: among paths that enter at most
//!   `floor(d)` obstacle cells, the shortest; when noise has spent the budget,
//!   the path of least further cost, then the shortest.
//!
//! Runs go in parallel on a private rayon pool, libtorch at one thread per
//! worker; the histories come back in job order (task-major, then cost limit),
//! so the file does not depend on the thread count.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use safety_envs::{
    Action, Cell, CmdpEnv, EnvError, EnvName, EnvOptions, Orientation, Space, Task, make_env,
    sample_task, spawn_config,
};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::data::histories::{DatasetInfo, History, HistoryFile, Shard};
use crate::ppo_lagrangian::{self, PpoLagConfig, PpoLagError, UpdateMetrics};
use crate::task_seeds::{PretrainTasks, pretrain_task_seed};

/// What can go wrong making a dataset.
#[derive(Debug, Error)]
pub enum DatasetError {
    #[error("dataset config: {0}")]
    Config(String),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Ppo(#[from] PpoLagError),
    #[error(transparent)]
    History(#[from] crate::data::histories::HistoryError),
}

/// Which learner makes the histories.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Source {
    /// PPO-Lagrangian from scratch.
    PpoLagrangian,
    /// AD-eps: an optimal policy with decreasing action noise.
    NoisyOptimal,
}

/// How to make a dataset.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DatasetConfig {
    /// Environment name (`darkroom`, `point`, `car`).
    pub env: String,
    /// Pretraining tasks.
    pub tasks: usize,
    /// One history per task and cost limit (SPEC: 0, 2.5, 5 / 0, 5, 10).
    pub cost_limits: Vec<f32>,
    /// Environment steps per history (SPEC: 50,000).
    pub steps: usize,
    /// Master seed: task seeds and run seeds derive from it.
    pub seed: u64,
    /// Worker threads.
    pub threads: usize,
    pub source: Source,
    /// Time limit override (agent steps).
    pub max_episode_steps: Option<usize>,
    /// Point and Car: MuJoCo physics steps per agent action (the macro
    /// action); `None` takes the default, 5 Safety-Gymnasium steps x 10
    /// physics steps = 50. The file records the resolved value.
    #[serde(default)]
    pub physics_steps_per_action: Option<usize>,
    /// PPO-Lagrangian settings (`total_steps` is replaced by `steps`).
    pub ppo: PpoLagConfig,
    /// AD-eps: fraction of the history after which the noise is 0.
    pub noise_end_fraction: f64,
    /// Keep this many episodes of each learning run, spaced evenly in the
    /// logarithm of the episode index ([`log_spaced`]); `None` keeps all.
    #[serde(default)]
    pub keep_episodes: Option<usize>,
    /// Make only this part of the task x cost-limit grid (`--shard I/N`);
    /// `None`: all of it. Each history's seeds come from its place in the
    /// whole grid, so the parts together are the unsharded dataset.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shard: Option<Shard>,
}

/// `keep` episode indices out of `n`, spaced evenly in log(index + 1):
/// every episode at the start, where a learner changes fastest, then ever
/// sparser, so the kept history spans the early, middle and expert phases
/// (PPO-Lagrangian converges within the first tenth of a SafeDarkRoom run, so
/// a history cut to its first episodes, or subsampled evenly, shows either no
/// expert phase or almost no learning). Strictly increasing, from 0 to n - 1.
pub fn log_spaced(n: usize, keep: usize) -> Vec<usize> {
    if keep >= n {
        return (0..n).collect();
    }
    let mut out: Vec<usize> = Vec::with_capacity(keep);
    for j in 0..keep {
        let x = (n as f64).powf(j as f64 / (keep - 1).max(1) as f64).round() as usize;
        let floor = out.last().map_or(0, |&p| p + 1);
        out.push(x.saturating_sub(1).max(floor).min(n - keep + j));
    }
    out
}

impl DatasetConfig {
    /// The paper's setting for `env` with `tasks` tasks.
    pub fn paper(env: EnvName, tasks: usize, seed: u64) -> Self {
        let (cost_limits, ppo) = match env {
            EnvName::DarkRoom => (vec![0.0, 2.5, 5.0], PpoLagConfig::darkroom()),
            EnvName::Point | EnvName::Car => (vec![0.0, 5.0, 10.0], PpoLagConfig::mujoco()),
        };
        DatasetConfig {
            env: env.to_string(),
            tasks,
            cost_limits,
            steps: 50_000,
            seed,
            threads: 1,
            source: Source::PpoLagrangian,
            max_episode_steps: None,
            physics_steps_per_action: None,
            ppo,
            noise_end_fraction: 0.8,
            keep_episodes: None,
            shard: None,
        }
    }

    pub(crate) fn validate(&self) -> Result<EnvName, DatasetError> {
        let env: EnvName = self.env.parse()?;
        if self.tasks == 0 || self.cost_limits.is_empty() || self.steps == 0 || self.threads == 0 {
            return Err(DatasetError::Config(format!(
                "tasks ({}), cost limits ({}), steps ({}) and threads ({}) must all be positive",
                self.tasks,
                self.cost_limits.len(),
                self.steps,
                self.threads
            )));
        }
        if let Some(c) = self
            .cost_limits
            .iter()
            .find(|c| !c.is_finite() || **c < 0.0)
        {
            return Err(DatasetError::Config(format!(
                "cost limit {c} must be finite and non-negative"
            )));
        }
        if self.source == Source::NoisyOptimal && env != EnvName::DarkRoom {
            return Err(DatasetError::Config(format!(
                "the noisy-optimal source plans on SafeDarkRoom's grid; {env} is not supported"
            )));
        }
        if self.keep_episodes == Some(0) {
            return Err(DatasetError::Config(
                "keep_episodes must be at least 1 (or absent to keep every episode)".into(),
            ));
        }
        if !(self.noise_end_fraction > 0.0 && self.noise_end_fraction <= 1.0) {
            return Err(DatasetError::Config(format!(
                "noise_end_fraction {} must lie in (0, 1]",
                self.noise_end_fraction
            )));
        }
        let grid = self.tasks * self.cost_limits.len();
        if let Some(s) = self.shard
            && s.count > grid
        {
            return Err(DatasetError::Config(format!(
                "shard {s}: {} shards of a grid of {grid} histories ({} tasks x {} cost limits) \
                 would leave some empty; use at most {grid}",
                s.count,
                self.tasks,
                self.cost_limits.len()
            )));
        }
        Ok(env)
    }
}

/// A finished dataset and the learning curves of its runs.
#[derive(Debug)]
pub struct Dataset {
    pub file: HistoryFile,
    /// Per history, PPO-Lagrangian's per-update metrics (empty for AD-eps).
    pub metrics: Vec<Vec<UpdateMetrics>>,
}

/// SplitMix64: decorrelates the run seeds of neighbouring jobs.
fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Makes every history. `progress` is told how many environment steps were
/// just taken (from any worker).
pub fn generate(
    cfg: &DatasetConfig,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<Dataset, DatasetError> {
    let env_name = cfg.validate()?;
    let options = EnvOptions {
        max_episode_steps: cfg.max_episode_steps,
        physics_steps_per_action: cfg.physics_steps_per_action,
    };
    let probe = make_env(env_name, &options)?;
    let obs_dim = probe.observation_space().flat_dim();
    let physics_steps_per_action = probe.physics_steps_per_action();
    let (action_dim, action_n) = match probe.action_space() {
        Space::Discrete { n } => (1, Some(n)),
        Space::Box { low, .. } => (low.len(), None),
    };
    drop(probe);
    let spawn = spawn_config(env_name);
    let tasks: Vec<Task> = (0..cfg.tasks as u64)
        .map(|i| sample_task(&spawn, Orientation::Centre, pretrain_task_seed(cfg.seed, i)))
        .collect::<Result<_, _>>()?;
    // (job index in the whole grid, task, cost limit): the index seeds the run.
    let grid: Vec<(usize, f32)> = (0..cfg.tasks)
        .flat_map(|t| cfg.cost_limits.iter().map(move |&c| (t, c)))
        .collect();
    let part = cfg.shard.map_or(0..grid.len(), |s| s.range(grid.len()));
    let jobs: Vec<(usize, (usize, f32))> = part.clone().map(|j| (j, grid[j])).collect();
    let ppo = PpoLagConfig {
        total_steps: cfg.steps,
        ..cfg.ppo.clone()
    };
    ppo.validate()?;
    let make = || make_env(env_name, &options);

    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(cfg.threads)
        .build()
        .map_err(|e| DatasetError::Config(format!("thread pool: {e}")))?;
    let results: Vec<Result<(History, Vec<UpdateMetrics>), DatasetError>> = pool.install(|| {
        jobs.par_iter()
            .map(|&(j, (t, limit))| {
                // Small networks: one libtorch thread per worker beats sharing.
                tch::set_num_threads(1);
                let run_seed = splitmix64(cfg.seed ^ splitmix64(j as u64));
                // Subsampled in the worker: only the kept episodes are held.
                let keep = |h: History| match cfg.keep_episodes {
                    Some(k) => {
                        h.keep_episodes(&log_spaced(h.episodes().len(), k), obs_dim, action_dim)
                    }
                    None => h,
                };
                match cfg.source {
                    Source::PpoLagrangian => {
                        let run = ppo_lagrangian::train(
                            &ppo,
                            &make,
                            &tasks[t],
                            limit,
                            run_seed,
                            &mut |n| progress(n),
                        )?;
                        Ok((keep(run.history), run.metrics))
                    }
                    Source::NoisyOptimal => {
                        let mut env = make()?;
                        let h = noisy_optimal_history(
                            env.as_mut(),
                            &tasks[t],
                            limit,
                            cfg.steps,
                            cfg.noise_end_fraction,
                            run_seed,
                        )?;
                        progress(cfg.steps);
                        Ok((keep(h), Vec::new()))
                    }
                }
            })
            .collect()
    });
    let mut histories = Vec::with_capacity(jobs.len());
    let mut metrics = Vec::with_capacity(jobs.len());
    for r in results {
        let (h, m) = r?;
        histories.push(h);
        metrics.push(m);
    }
    let config = serde_json::json!({
        "dataset": cfg,
        "pretrain_tasks": PretrainTasks::centre(cfg.seed, cfg.tasks as u64),
    })
    .to_string();
    Ok(Dataset {
        file: HistoryFile {
            info: DatasetInfo {
                env: env_name.to_string(),
                config,
                seed: cfg.seed,
                obs_dim,
                action_dim,
                action_n,
                grid_size: spawn.grid_size,
                physics_steps_per_action,
                grid_histories: grid.len(),
                shard: cfg.shard,
            },
            histories,
        },
        metrics,
    })
}

// ---------------------------------------------------------------------------
// AD-eps: the noisy optimal policy on SafeDarkRoom
// ---------------------------------------------------------------------------

/// SafeDarkRoom's moves: 0 stay, 1 up, 2 down, 3 left, 4 right (walls stop).
fn move_cell(c: Cell, a: usize, g: usize) -> Cell {
    match a {
        1 => Cell {
            row: c.row.saturating_sub(1),
            ..c
        },
        2 => Cell {
            row: (c.row + 1).min(g - 1),
            ..c
        },
        3 => Cell {
            col: c.col.saturating_sub(1),
            ..c
        },
        4 => Cell {
            col: (c.col + 1).min(g - 1),
            ..c
        },
        _ => c,
    }
}

/// Optimal plans for every (budget left, cell): lexicographically least
/// (cost beyond the budget, steps) to the goal. Entering an obstacle cell
/// (or staying on one) costs 1, paid from the budget while any is left.
pub struct Planner {
    g: usize,
    budget: usize,
    obstacle: Vec<bool>,
    /// (overspend, steps), index `b * g * g + cell`.
    table: Vec<(u32, u32)>,
}

impl Planner {
    pub fn new(task: &Task, budget: usize) -> Self {
        let g = task.grid_size;
        let mut obstacle = vec![false; g * g];
        for o in &task.obstacles {
            obstacle[o.row * g + o.col] = true;
        }
        let inf = (u32::MAX / 2, u32::MAX / 2);
        let goal = task.goal.row * g + task.goal.col;
        let mut table = vec![inf; (budget + 1) * g * g];
        for b in 0..=budget {
            table[b * g * g + goal] = (0, 0);
        }
        let mut p = Planner {
            g,
            budget,
            obstacle,
            table,
        };
        // Bellman-Ford sweeps until nothing improves (at most cells x budgets).
        loop {
            let mut changed = false;
            for b in 0..=budget {
                for cell in 0..g * g {
                    if cell == goal {
                        continue;
                    }
                    let c = Cell {
                        row: cell / g,
                        col: cell % g,
                    };
                    let best = (0..5).map(|a| p.value_after(c, b, a)).min().unwrap_or(inf);
                    if best < p.table[b * g * g + cell] {
                        p.table[b * g * g + cell] = best;
                        changed = true;
                    }
                }
            }
            if !changed {
                break;
            }
        }
        p
    }

    /// (overspend, steps) of taking `a` in `c` with budget `b`, then acting optimally.
    fn value_after(&self, c: Cell, b: usize, a: usize) -> (u32, u32) {
        let next = move_cell(c, a, self.g);
        let k = next.row * self.g + next.col;
        let (over, b2) = if self.obstacle[k] {
            if b > 0 { (0, b - 1) } else { (1, 0) }
        } else {
            (0, b)
        };
        let (o, s) = self.table[b2 * self.g * self.g + k];
        (o.saturating_add(over), s.saturating_add(1))
    }

    /// The optimal action in `c` with `budget_left` (lowest index on ties).
    pub fn action(&self, c: Cell, budget_left: usize) -> usize {
        let b = budget_left.min(self.budget);
        (0..5)
            .min_by_key(|&a| self.value_after(c, b, a))
            .unwrap_or(0)
    }

    /// (overspend, steps) of the optimal plan from `c` with `budget_left`.
    pub fn value(&self, c: Cell, budget_left: usize) -> (u32, u32) {
        self.table[budget_left.min(self.budget) * self.g * self.g + c.row * self.g + c.col]
    }
}

/// One AD-eps history: `steps` environment steps (whole episodes only), the
/// chance of a uniformly random action falling linearly from 1 to 0 at
/// `noise_end_fraction * steps`.
pub fn noisy_optimal_history(
    env: &mut dyn CmdpEnv,
    task: &Task,
    cost_limit: f32,
    steps: usize,
    noise_end_fraction: f64,
    seed: u64,
) -> Result<History, DatasetError> {
    env.set_task(task)?;
    let n_actions = match env.action_space() {
        Space::Discrete { n } => n,
        Space::Box { .. } => {
            return Err(DatasetError::Config(
                "the noisy-optimal source needs a discrete action space".into(),
            ));
        }
    };
    let budget = cost_limit.floor() as usize;
    let planner = Planner::new(task, budget);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut history = History::new(task.clone(), cost_limit);
    let mut obs = [0.0f32; 2];
    let mut next = [0.0f32; 2];
    let mut t = 0usize;
    while t < steps {
        env.reset(rng.r#gen(), &mut obs)?;
        let mut left = budget;
        loop {
            let eps = (1.0 - t as f64 / (noise_end_fraction * steps as f64)).max(0.0);
            let cell = Cell {
                row: obs[0] as usize,
                col: obs[1] as usize,
            };
            let a = if rng.r#gen::<f64>() < eps {
                rng.gen_range(0..n_actions)
            } else {
                planner.action(cell, left)
            };
            let out = env.step(Action::Discrete(a), &mut next)?;
            if out.cost > 0.0 {
                left = left.saturating_sub(1);
            }
            history.push(
                &obs,
                &[a as f32],
                out.reward,
                out.cost,
                &next,
                out.terminated,
                out.truncated,
            );
            t += 1;
            obs = next;
            if out.done() {
                break;
            }
        }
    }
    // Whole episodes only: stop at the last that fits in `steps`.
    if history.len() > steps {
        let mut keep = History::new(task.clone(), cost_limit);
        for r in history.episodes() {
            if r.end > steps {
                break;
            }
            for i in r {
                keep.push(
                    &history.observations[2 * i..2 * i + 2],
                    &history.actions[i..i + 1],
                    history.rewards[i],
                    history.costs[i],
                    &history.next_observations[2 * i..2 * i + 2],
                    history.terminals[i],
                    history.timeouts[i],
                );
            }
        }
        history = keep;
    }
    Ok(history)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn corridor_task() -> Task {
        // Goal at (4, 7); the direct row is blocked at (4, 5) and (4, 6); rows
        // 0 and 8 and the left of row 1 take the other 23 obstacles.
        let mut obstacles = vec![Cell { row: 4, col: 5 }, Cell { row: 4, col: 6 }];
        for col in 0..9 {
            obstacles.push(Cell { row: 0, col });
            obstacles.push(Cell { row: 8, col });
        }
        for col in 0..5 {
            obstacles.push(Cell { row: 1, col });
        }
        Task {
            grid_size: 9,
            goal: Cell { row: 4, col: 7 },
            obstacles,
        }
    }

    #[test]
    fn planner_detours_at_budget_zero_and_cuts_through_with_budget() {
        let task = Task {
            grid_size: 9,
            goal: Cell { row: 4, col: 7 },
            obstacles: vec![Cell { row: 4, col: 5 }, Cell { row: 4, col: 6 }],
        };
        let start = Cell { row: 4, col: 4 };
        let safe = Planner::new(&task, 0);
        // Around the two obstacles: up, 3 right, down = 5 steps, no cost.
        assert_eq!(safe.value(start, 0), (0, 5));
        let loose = Planner::new(&task, 2);
        // Straight through both: 3 steps.
        assert_eq!(loose.value(start, 2), (0, 3));
        assert_eq!(loose.action(start, 2), 4);
        // One unit of budget does not help: still the detour.
        assert_eq!(loose.value(start, 1), (0, 5));
    }

    #[test]
    fn noise_falls_and_the_policy_becomes_optimal_and_safe() {
        let task = corridor_task();
        let mut env = make_env(EnvName::DarkRoom, &EnvOptions::default()).unwrap();
        let h = noisy_optimal_history(env.as_mut(), &task, 0.0, 3000, 0.5, 9).unwrap();
        task.validate(9, 25).unwrap();
        assert!(h.len() <= 3000);
        assert!(h.terminals[h.len() - 1] || h.timeouts[h.len() - 1]);
        let totals = h.episode_totals();
        let eps = h.episodes();
        let k = totals.len();
        // The last episodes are noise-free: reach the goal in 5 steps at no cost.
        for (r, e) in totals[k - 10..].iter().zip(&eps[k - 10..]) {
            assert_eq!(*r, (1.0, 0.0));
            assert_eq!(e.len(), 5);
        }
        let first_ret: f32 = totals[..10].iter().map(|e| e.0).sum();
        assert!(first_ret < 10.0, "early episodes are noisy");
    }

    #[test]
    fn generate_is_ordered_and_thread_count_free() {
        let mut cfg = DatasetConfig::paper(EnvName::DarkRoom, 2, 5);
        cfg.steps = 600;
        cfg.source = Source::NoisyOptimal;
        let one = generate(&cfg, &|_| {}).unwrap();
        cfg.threads = 2;
        let two = generate(&cfg, &|_| {}).unwrap();
        // (The config string records the thread count; the histories must not depend on it.)
        assert!(one.file.histories == two.file.histories);
        let h = &one.file.histories;
        assert_eq!(h.len(), 6);
        assert_eq!(
            h.iter().map(|h| h.cost_limit).collect::<Vec<_>>(),
            vec![0.0, 2.5, 5.0, 0.0, 2.5, 5.0]
        );
        assert_eq!(h[0].task, h[2].task);
        assert_ne!(h[0].task, h[3].task);
        // Tasks are the pretraining (centre-oriented) ones.
        let spawn = spawn_config(EnvName::DarkRoom);
        assert_eq!(
            h[3].task,
            sample_task(&spawn, Orientation::Centre, pretrain_task_seed(5, 1)).unwrap()
        );
        // Bad configs are refused with a reason.
        cfg.env = "point".into();
        let e = generate(&cfg, &|_| {}).unwrap_err();
        assert!(e.to_string().contains("noisy-optimal"), "{e}");
    }

    #[test]
    fn ppo_source_makes_histories() {
        let mut cfg = DatasetConfig::paper(EnvName::DarkRoom, 1, 3);
        cfg.steps = 1024;
        cfg.cost_limits = vec![0.0, 5.0];
        cfg.threads = 2;
        let d = generate(&cfg, &|_| {}).unwrap();
        assert_eq!(d.file.histories.len(), 2);
        assert_eq!(d.metrics.len(), 2);
        let per_update = cfg.ppo.num_envs * cfg.ppo.rollout_steps;
        assert_eq!(d.metrics[0].len(), 1024usize.div_ceil(per_update));
        assert!(!d.file.histories[1].is_empty());
        let json: serde_json::Value = serde_json::from_str(&d.file.info.config).unwrap();
        assert_eq!(json["dataset"]["steps"], 1024);
    }

    /// Every value's bits, so that -0.0 against 0.0 or two NaNs count.
    fn bits(h: &History) -> Vec<u32> {
        [
            &h.observations,
            &h.next_observations,
            &h.actions,
            &h.rewards,
            &h.costs,
        ]
        .iter()
        .flat_map(|v| v.iter().map(|x| x.to_bits()))
        .chain([h.cost_limit.to_bits()])
        .collect()
    }

    #[test]
    fn three_shards_hold_the_unsharded_histories_bit_for_bit() {
        let mut cfg = DatasetConfig::paper(EnvName::DarkRoom, 2, 4);
        cfg.steps = 512;
        cfg.cost_limits = vec![0.0, 5.0];
        let whole = generate(&cfg, &|_| {}).unwrap().file;
        assert_eq!((whole.info.grid_histories, whole.info.shard), (4, None));
        let mut union = Vec::new();
        for index in 0..3 {
            let shard = Shard { index, count: 3 };
            cfg.shard = Some(shard);
            let part = generate(&cfg, &|_| {}).unwrap().file;
            // A shard records which part it is.
            assert_eq!(part.info.shard, Some(shard));
            assert_eq!(part.info.grid_histories, 4);
            assert_eq!(part.info.history_ids(), shard.range(4));
            union.extend(part.histories);
        }
        assert_eq!(union.len(), whole.histories.len());
        for (a, b) in union.iter().zip(&whole.histories) {
            assert_eq!(a.task, b.task);
            assert_eq!((&a.terminals, &a.timeouts), (&b.terminals, &b.timeouts));
            assert!(
                bits(a) == bits(b),
                "a shard's history differs from the unsharded one"
            );
        }
        // More shards than histories would leave some empty.
        cfg.shard = Some(Shard { index: 0, count: 5 });
        let e = generate(&cfg, &|_| {}).unwrap_err().to_string();
        assert!(e.contains("at most 4"), "{e}");
    }

    #[test]
    fn shards_parse_as_i_of_n() {
        assert_eq!("1/3".parse::<Shard>(), Ok(Shard { index: 1, count: 3 }));
        for bad in ["3/3", "1", "a/3", "-1/3", "0/0"] {
            let e = bad.parse::<Shard>().unwrap_err();
            assert!(e.contains("I/N"), "{bad}: {e}");
        }
        // Contiguous parts that cover the grid once.
        let parts: Vec<_> = (0..3)
            .map(|i| Shard { index: i, count: 3 }.range(4))
            .collect();
        assert_eq!(parts, vec![0..1, 1..2, 2..4]);
    }

    #[test]
    fn log_spaced_keeps_every_early_episode_and_thins_later_ones() {
        let idx = log_spaced(10_000, 200);
        assert_eq!(idx.len(), 200);
        assert_eq!((idx[0], idx[199]), (0, 9_999));
        assert!(idx.windows(2).all(|w| w[0] < w[1]));
        // Dense at the start (where a learner changes fastest) ...
        assert_eq!(&idx[..20], &(0..20).collect::<Vec<_>>()[..]);
        // ... and a quarter of the kept episodes after the first tenth.
        let early = idx.iter().filter(|&&i| i < 1_000).count();
        assert!(
            (140..=160).contains(&early),
            "{early} of 200 in the first tenth"
        );
        assert_eq!(log_spaced(5, 9), vec![0, 1, 2, 3, 4]);
        assert_eq!(log_spaced(7, 7), (0..7).collect::<Vec<_>>());
        assert_eq!(log_spaced(100, 1), vec![0]);
    }

    #[test]
    fn kept_episodes_are_whole_and_in_order() {
        let mut cfg = DatasetConfig::paper(EnvName::DarkRoom, 1, 5);
        cfg.steps = 3000;
        cfg.cost_limits = vec![0.0];
        cfg.source = Source::NoisyOptimal;
        let full = generate(&cfg, &|_| {}).unwrap().file.histories.remove(0);
        cfg.keep_episodes = Some(40);
        let kept = generate(&cfg, &|_| {}).unwrap().file.histories.remove(0);
        let (fe, ke) = (full.episodes(), kept.episodes());
        let picked = log_spaced(fe.len(), 40);
        assert_eq!(ke.len(), 40);
        for (k, &e) in ke.iter().zip(&picked) {
            let f = fe[e].clone();
            assert_eq!(kept.rewards[k.clone()], full.rewards[f.clone()]);
            assert_eq!(kept.costs[k.clone()], full.costs[f.clone()]);
            assert_eq!(
                kept.observations[k.start * 2..k.end * 2],
                full.observations[f.start * 2..f.end * 2]
            );
        }
        let json: serde_json::Value =
            serde_json::from_str(&generate(&cfg, &|_| {}).unwrap().file.info.config).unwrap();
        assert_eq!(json["dataset"]["keep_episodes"], 40);
        cfg.keep_episodes = Some(0);
        assert!(
            generate(&cfg, &|_| {})
                .unwrap_err()
                .to_string()
                .contains("keep_episodes")
        );
    }
}
