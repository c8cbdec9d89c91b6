//! What an evaluation produces: the raw per-episode results with their
//! tasks, conditions and recording ([`EvalResult`]), the summaries drawn from
//! them (curves over the episode index, the budget sweep, trends), and the
//! report the `eval` command writes for one agent and protocol ([`EvalReport`]).

use std::fmt;

use safety_envs::Task;
use serde::{Deserialize, Serialize};

use crate::agent::Conditioning;
use crate::stats::{MeanSe, mean_se};
use crate::task_seeds::PretrainTasks;

/// How the held-out property of the evaluation tasks was established.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum HeldOut {
    /// Every evaluation task was compared with every pretraining task the
    /// checkpoint records, and none was equal.
    Checked(PretrainTasks),
    /// The checkpoint records no pretraining tasks: only the seed ranges
    /// (evaluation seeds are in the reserved range, edge orientation) hold.
    SeedRangesOnly,
}

/// A task, serialisable: grid size, goal and obstacle cells as `[row, col]`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TaskRecord {
    pub seed: u64,
    pub grid_size: usize,
    pub goal: [usize; 2],
    pub obstacles: Vec<[usize; 2]>,
}

impl TaskRecord {
    pub(super) fn new(seed: u64, t: &Task) -> Self {
        TaskRecord {
            seed,
            grid_size: t.grid_size,
            goal: [t.goal.row, t.goal.col],
            obstacles: t.obstacles.iter().map(|c| [c.row, c.col]).collect(),
        }
    }
}

/// A conditioning, serialisable.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ConditionRecord {
    /// Return-to-go target (supervised route only).
    pub rtg: Option<f32>,
    /// The cost budget: CTG at each episode start.
    pub ctg: f32,
}

impl From<Conditioning> for ConditionRecord {
    fn from(c: Conditioning) -> Self {
        match c {
            Conditioning::Budget { ctg } => ConditionRecord { rtg: None, ctg },
            Conditioning::Targets { rtg, ctg } => ConditionRecord {
                rtg: Some(rtg),
                ctg,
            },
        }
    }
}

/// Every step of one episode of a recorded trajectory.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RecordedEpisode {
    /// Observations: the first, then one after each step (`len = steps + 1`).
    pub observations: Vec<Vec<f32>>,
    /// Actions as the environment received them (index or vector).
    pub actions: Vec<Vec<f32>>,
    pub rewards: Vec<f32>,
    pub costs: Vec<f32>,
    /// The episode's reset seed (replaying the actions after
    /// `set_task` + `reset(seed)` reproduces it).
    pub reset_seed: u64,
}

/// One trajectory recorded step by step.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Recording {
    pub condition: usize,
    pub task: usize,
    pub episodes: Vec<RecordedEpisode>,
}

/// What one evaluation measured: per (condition, task, episode) results.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalResult {
    pub tasks: Vec<TaskRecord>,
    pub conditions: Vec<ConditionRecord>,
    pub episodes: usize,
    pub eval_seed: u64,
    pub greedy: bool,
    pub batch: usize,
    pub held_out: HeldOut,
    /// `edge` (held-out evaluation) or `centre` (in-distribution diagnostic).
    pub orientation: String,
    /// Episode returns, `[condition][task][episode]`.
    pub returns: Vec<Vec<Vec<f32>>>,
    /// Episode costs, same layout.
    pub costs: Vec<Vec<Vec<f32>>>,
    /// Episode lengths in agent steps, same layout.
    pub lengths: Vec<Vec<Vec<u32>>>,
    /// The episode ended at the goal (terminated), same layout.
    pub reached_goal: Vec<Vec<Vec<bool>>>,
    /// Cells (side [`EvalConfig::search_cell`](crate::eval::EvalConfig)) the
    /// trajectory first entered in the episode, same layout; empty in older
    /// result files.
    #[serde(default)]
    pub new_cells: Vec<Vec<Vec<u32>>>,
    /// Cost paid in the episode within [`EvalConfig::repeat_radius`](crate::eval::EvalConfig)
    /// of where the trajectory paid a cost in an earlier episode, same
    /// layout; empty in older result files.
    #[serde(default)]
    pub repeat_costs: Vec<Vec<Vec<f32>>>,
    pub recording: Option<Recording>,
}

/// Mean and standard error over tasks of one episode index.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeStats {
    /// Episode index k, from 1.
    pub k: usize,
    pub ret: MeanSe,
    pub cost: MeanSe,
    /// Fraction of conditions whose episode cost exceeded the budget (CTG).
    pub violation: MeanSe,
    /// Fraction of conditions that reached the goal.
    pub success: MeanSe,
    /// Discovery rate: P(goal at k | not reached in episodes 1..k-1), over the
    /// conditions of each task with no earlier success (tasks with none are
    /// left out; `n` says how many remain). Absent from older result files.
    #[serde(default = "MeanSe::undefined")]
    pub discovery: MeanSe,
    /// Revisit rate: P(goal at k | reached earlier), the same way.
    #[serde(default = "MeanSe::undefined")]
    pub revisit: MeanSe,
    /// Fraction of conditions that reached the goal in some episode 1..=k.
    #[serde(default = "MeanSe::undefined")]
    pub found_by: MeanSe,
    /// Cells first entered in episode k by the conditions of each task with
    /// no earlier success, as [`EpisodeStats::discovery`] counts them: near 0
    /// when the agent drives one route in every episode and a goal off it is
    /// never found. Undefined in older result files.
    #[serde(default = "MeanSe::undefined")]
    pub search_new_cells: MeanSe,
    /// The part of `cost` paid again: near where the trajectory paid a cost
    /// in an earlier episode. An agent that learns from its context lowers
    /// it with k; one that ignores the costs in it pays about its share of
    /// `cost`. Undefined in older result files.
    #[serde(default = "MeanSe::undefined")]
    pub repeat_cost: MeanSe,
}

/// Budget-sweep statistics of one condition, over tasks.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ConditionStats {
    pub condition: ConditionRecord,
    /// `sum_k G(tau_k)`.
    pub total_return: MeanSe,
    /// `max_k Gc(tau_k)`.
    pub max_cost: MeanSe,
    /// Mean episode cost over the K episodes.
    pub mean_cost: MeanSe,
    /// Fraction of the K episodes over budget.
    pub violation: MeanSe,
}

/// First episodes against last episodes: does the agent improve in context?
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Trend {
    /// Episodes in each window (K / 5, at least 1).
    pub window: usize,
    pub first_return: MeanSe,
    pub last_return: MeanSe,
    /// Per task: last-window mean return minus first-window mean return.
    pub return_gain: MeanSe,
    pub first_cost: MeanSe,
    pub last_cost: MeanSe,
    /// Per task: first-window mean cost minus last-window mean cost.
    pub cost_drop: MeanSe,
}

/// Everything plotted and tabulated from one [`EvalResult`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub per_episode: Vec<EpisodeStats>,
    pub per_condition: Vec<ConditionStats>,
    pub trend: Trend,
    /// Mean CTG over the conditions (the budget line of Figure 1).
    pub mean_budget: f32,
    /// Per task, the least-squares slope of the total return against the CTG
    /// over the conditions; mean and s.e. over tasks (`None` with fewer than
    /// two distinct CTGs). Positive: more budget buys more return.
    pub total_return_slope: Option<MeanSe>,
    /// The same for the maximum episode cost.
    pub max_cost_slope: Option<MeanSe>,
}

impl Summary {
    /// Several evaluations' summaries as one curve (runs of one setting at
    /// several evaluation seeds, say): every statistic is the mean of the
    /// parts' means with the standard error over the parts, so the spread
    /// between runs shows, not only between tasks. Parts without a value
    /// (a NaN rate) are left out of that statistic. The budget sweep is not
    /// pooled (its conditions differ between evaluations): empty. `parts`
    /// hold the same number of episodes.
    pub fn pooled(parts: &[Summary]) -> Summary {
        let pool = |get: &dyn Fn(&Summary) -> MeanSe| {
            let means: Vec<f64> = parts
                .iter()
                .map(|p| get(p).mean)
                .filter(|m| m.is_finite())
                .collect();
            ms(&means)
        };
        let episodes = parts.iter().map(|p| p.per_episode.len()).min().unwrap_or(0);
        let per_episode = (0..episodes)
            .map(|k| {
                let at = |get: fn(&EpisodeStats) -> MeanSe| pool(&|p| get(&p.per_episode[k]));
                EpisodeStats {
                    k: k + 1,
                    ret: at(|e| e.ret),
                    cost: at(|e| e.cost),
                    violation: at(|e| e.violation),
                    success: at(|e| e.success),
                    discovery: at(|e| e.discovery),
                    revisit: at(|e| e.revisit),
                    found_by: at(|e| e.found_by),
                    search_new_cells: at(|e| e.search_new_cells),
                    repeat_cost: at(|e| e.repeat_cost),
                }
            })
            .collect();
        let trend = |get: fn(&Trend) -> MeanSe| pool(&|p| get(&p.trend));
        let slope = |get: fn(&Summary) -> Option<MeanSe>| {
            parts
                .iter()
                .all(|p| get(p).is_some())
                .then(|| pool(&|p| get(p).unwrap_or_else(MeanSe::undefined)))
        };
        Summary {
            per_episode,
            per_condition: Vec::new(),
            trend: Trend {
                window: parts.first().map_or(1, |p| p.trend.window),
                first_return: trend(|t| t.first_return),
                last_return: trend(|t| t.last_return),
                return_gain: trend(|t| t.return_gain),
                first_cost: trend(|t| t.first_cost),
                last_cost: trend(|t| t.last_cost),
                cost_drop: trend(|t| t.cost_drop),
            },
            mean_budget: parts.iter().map(|p| p.mean_budget).sum::<f32>()
                / parts.len().max(1) as f32,
            total_return_slope: slope(|p| p.total_return_slope),
            max_cost_slope: slope(|p| p.max_cost_slope),
        }
    }
}

/// Least-squares slope of `ys` against `xs`; `None` when the x values do not vary.
fn slope(xs: &[f64], ys: &[f64]) -> Option<f64> {
    let n = xs.len() as f64;
    let (mx, my) = (xs.iter().sum::<f64>() / n, ys.iter().sum::<f64>() / n);
    let sxx: f64 = xs.iter().map(|x| (x - mx).powi(2)).sum();
    let sxy: f64 = xs.iter().zip(ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    (sxx > 0.0).then(|| sxy / sxx)
}

/// Mean and s.e., undefined (NaN) for an empty sample.
fn ms(xs: &[f64]) -> MeanSe {
    mean_se(xs).unwrap_or_else(MeanSe::undefined)
}

impl EvalResult {
    fn n_tasks(&self) -> usize {
        self.tasks.len()
    }

    /// Per task, the mean over conditions of `f(condition, task, episode)`.
    fn per_task_over_conditions(
        &self,
        k: usize,
        f: impl Fn(usize, usize, usize) -> f64,
    ) -> Vec<f64> {
        let nc = self.conditions.len() as f64;
        (0..self.n_tasks())
            .map(|t| (0..self.conditions.len()).map(|c| f(c, t, k)).sum::<f64>() / nc)
            .collect()
    }

    /// Per task, the mean of `f(condition, task)` over the conditions that
    /// had (`found_before`) or had not reached the goal before episode k;
    /// tasks without such a condition are skipped.
    fn per_task_given_found_before(
        &self,
        k: usize,
        found_before: bool,
        f: impl Fn(usize, usize) -> f64,
    ) -> Vec<f64> {
        (0..self.n_tasks())
            .filter_map(|t| {
                let (sum, n) = (0..self.conditions.len())
                    .filter(|&c| self.reached_goal[c][t][..k].contains(&true) == found_before)
                    .fold((0.0, 0usize), |(s, n), c| (s + f(c, t), n + 1));
                (n > 0).then(|| sum / n as f64)
            })
            .collect()
    }

    /// Per task, the fraction of conditions reaching the goal at episode k
    /// among those that had (`found_before`) or had not reached it earlier.
    fn conditional_success(&self, k: usize, found_before: bool) -> Vec<f64> {
        self.per_task_given_found_before(k, found_before, |c, t| {
            f64::from(u8::from(self.reached_goal[c][t][k]))
        })
    }

    /// Per task, the mean over the conditions with no success before
    /// episode k of the cells first entered in episode k; results without
    /// cell counts (older files) give none.
    fn cells_entered_while_searching(&self, k: usize) -> Vec<f64> {
        if self.new_cells.is_empty() {
            return vec![];
        }
        self.per_task_given_found_before(k, false, |c, t| f64::from(self.new_cells[c][t][k]))
    }

    /// Curves, sweep and trend (see the module documentation for the averaging).
    pub fn summary(&self) -> Summary {
        let (total_return_slope, max_cost_slope) = self.budget_slopes();
        Summary {
            per_episode: (0..self.episodes).map(|k| self.episode_stats(k)).collect(),
            per_condition: (0..self.conditions.len())
                .map(|c| self.condition_stats(c))
                .collect(),
            trend: self.trend(),
            mean_budget: self.conditions.iter().map(|c| c.ctg).sum::<f32>()
                / self.conditions.len() as f32,
            total_return_slope,
            max_cost_slope,
        }
    }

    /// The curves' point at episode index `k` (from 0).
    fn episode_stats(&self, k: usize) -> EpisodeStats {
        EpisodeStats {
            k: k + 1,
            ret: ms(&self.per_task_over_conditions(k, |c, t, k| self.returns[c][t][k] as f64)),
            cost: ms(&self.per_task_over_conditions(k, |c, t, k| self.costs[c][t][k] as f64)),
            violation: ms(&self.per_task_over_conditions(k, |c, t, k| {
                f64::from(u8::from(self.costs[c][t][k] > self.conditions[c].ctg))
            })),
            success: ms(&self.per_task_over_conditions(k, |c, t, k| {
                f64::from(u8::from(self.reached_goal[c][t][k]))
            })),
            discovery: ms(&self.conditional_success(k, false)),
            revisit: ms(&self.conditional_success(k, true)),
            found_by: ms(&self.per_task_over_conditions(k, |c, t, k| {
                f64::from(u8::from(self.reached_goal[c][t][..=k].contains(&true)))
            })),
            search_new_cells: ms(&self.cells_entered_while_searching(k)),
            repeat_cost: if self.repeat_costs.is_empty() {
                MeanSe::undefined()
            } else {
                ms(&self
                    .per_task_over_conditions(k, |c, t, k| f64::from(self.repeat_costs[c][t][k])))
            },
        }
    }

    /// The sweep's point for condition `c`: over its K episodes per task,
    /// the total return, the maximum and mean cost, the share over budget.
    fn condition_stats(&self, c: usize) -> ConditionStats {
        let (cond, k_n) = (&self.conditions[c], self.episodes);
        let tasks = 0..self.n_tasks();
        let total: Vec<f64> = tasks
            .clone()
            .map(|t| self.returns[c][t].iter().map(|&g| g as f64).sum())
            .collect();
        let max: Vec<f64> = tasks
            .clone()
            .map(|t| {
                self.costs[c][t]
                    .iter()
                    .fold(f64::NEG_INFINITY, |m, &g| m.max(g as f64))
            })
            .collect();
        let mean: Vec<f64> = tasks
            .clone()
            .map(|t| self.costs[c][t].iter().map(|&g| g as f64).sum::<f64>() / k_n as f64)
            .collect();
        let viol: Vec<f64> = tasks
            .map(|t| self.costs[c][t].iter().filter(|&&g| g > cond.ctg).count() as f64 / k_n as f64)
            .collect();
        ConditionStats {
            condition: *cond,
            total_return: ms(&total),
            max_cost: ms(&max),
            mean_cost: ms(&mean),
            violation: ms(&viol),
        }
    }

    /// Return and cost over the first and the last fifth of the episodes
    /// (at least one), per task over the conditions, and their change.
    fn trend(&self) -> Trend {
        let k_n = self.episodes;
        let window = (k_n / 5).max(1);
        let window_mean = |data: &Vec<Vec<Vec<f32>>>, t: usize, first: bool| -> f64 {
            let ks = if first { 0..window } else { k_n - window..k_n };
            let n = (ks.len() * self.conditions.len()) as f64;
            (0..self.conditions.len())
                .flat_map(|c| ks.clone().map(move |k| data[c][t][k] as f64))
                .sum::<f64>()
                / n
        };
        let per_task = |data: &Vec<Vec<Vec<f32>>>, first: bool| -> Vec<f64> {
            (0..self.n_tasks())
                .map(|t| window_mean(data, t, first))
                .collect()
        };
        let (fr, lr) = (
            per_task(&self.returns, true),
            per_task(&self.returns, false),
        );
        let (fc, lc) = (per_task(&self.costs, true), per_task(&self.costs, false));
        let diff =
            |a: &[f64], b: &[f64]| -> Vec<f64> { a.iter().zip(b).map(|(x, y)| x - y).collect() };
        Trend {
            window,
            first_return: ms(&fr),
            last_return: ms(&lr),
            return_gain: ms(&diff(&lr, &fr)),
            first_cost: ms(&fc),
            last_cost: ms(&lc),
            cost_drop: ms(&diff(&fc, &lc)),
        }
    }

    /// The slopes against the budget (CTG) of the total return and of the
    /// maximum episode cost: per task over the conditions, then mean and
    /// standard error over the tasks.
    fn budget_slopes(&self) -> (Option<MeanSe>, Option<MeanSe>) {
        let ctgs: Vec<f64> = self.conditions.iter().map(|c| c.ctg as f64).collect();
        let slopes = |per_task: &dyn Fn(usize, usize) -> f64| -> Option<MeanSe> {
            let s: Option<Vec<f64>> = (0..self.n_tasks())
                .map(|t| {
                    let ys: Vec<f64> = (0..self.conditions.len()).map(|c| per_task(c, t)).collect();
                    slope(&ctgs, &ys)
                })
                .collect();
            s.and_then(|s| mean_se(&s))
        };
        let total_return_slope =
            slopes(&|c, t| self.returns[c][t].iter().map(|&g| g as f64).sum::<f64>());
        let max_cost_slope = slopes(&|c, t| {
            self.costs[c][t]
                .iter()
                .fold(f64::NEG_INFINITY, |m, &g| m.max(g as f64))
        });
        (total_return_slope, max_cost_slope)
    }
}

/// Which pretraining produced an agent.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum Method {
    /// Safe reinforcement pretraining (EPPO): conditioned on a budget.
    Eppo,
    /// Safe supervised pretraining (algorithm distillation with RTG/CTG).
    Ad,
    /// A uniformly random policy.
    Random,
}

impl Method {
    /// File-name stem.
    pub fn stem(self) -> &'static str {
        match self {
            Method::Eppo => "eppo",
            Method::Ad => "ad",
            Method::Random => "random",
        }
    }
}

impl fmt::Display for Method {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Method::Eppo => "EPPO",
            Method::Ad => "AD",
            Method::Random => "random policy",
        })
    }
}

/// One evaluation's report: exact settings, raw results and their summary.
#[derive(Debug, Serialize)]
pub struct EvalReport {
    pub env: String,
    pub method: Method,
    /// The `--label` given to this checkpoint, if any.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub label: Option<String>,
    pub checkpoint: Option<String>,
    pub checkpoint_note: String,
    /// "figure1" or "sweep".
    pub protocol: String,
    pub command: String,
    pub tasks: usize,
    pub episodes: usize,
    pub max_episode_steps: usize,
    /// Point and Car: MuJoCo physics steps per agent action (absent for SafeDarkRoom).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub physics_steps_per_action: Option<usize>,
    pub threads: usize,
    /// Parameter checksums before and after the evaluation (equal: frozen).
    pub parameters_checksum: Option<[u64; 2]>,
    pub wall_seconds: f64,
    pub summary: Summary,
    pub result: EvalResult,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn value(mean: f64) -> MeanSe {
        MeanSe {
            mean,
            se: 0.5,
            n: 16,
        }
    }

    /// A summary whose every statistic at episode k is `base + k`, the
    /// revisit rate undefined where `no_revisit`.
    fn summary(base: f64, no_revisit: bool) -> Summary {
        let stats = |k: usize| {
            let v = value(base + k as f64);
            EpisodeStats {
                k: k + 1,
                ret: v,
                cost: v,
                violation: v,
                success: v,
                discovery: v,
                revisit: if no_revisit { MeanSe::undefined() } else { v },
                found_by: v,
                search_new_cells: v,
                repeat_cost: v,
            }
        };
        let v = value(base);
        Summary {
            per_episode: (0..3).map(stats).collect(),
            per_condition: Vec::new(),
            trend: Trend {
                window: 1,
                first_return: v,
                last_return: v,
                return_gain: v,
                first_cost: v,
                last_cost: v,
                cost_drop: v,
            },
            mean_budget: base as f32,
            total_return_slope: Some(v),
            max_cost_slope: None,
        }
    }

    #[test]
    fn pooled_summaries_average_the_means_with_the_spread_between_them() {
        let pooled =
            Summary::pooled(&[summary(1.0, false), summary(3.0, false), summary(5.0, true)]);
        assert_eq!(pooled.per_episode.len(), 3);
        let at = &pooled.per_episode[2];
        assert_eq!(at.k, 3);
        // Means 3, 5, 7: mean 5, s.e. 2 / sqrt(3) over the three parts (not
        // the parts' own s.e. of 0.5).
        assert!((at.ret.mean - 5.0).abs() < 1e-12 && at.ret.n == 3);
        assert!((at.cost.se - 2.0 / 3f64.sqrt()).abs() < 1e-12);
        // The part without a revisit rate is left out of that statistic only.
        assert!((at.revisit.mean - 4.0).abs() < 1e-12 && at.revisit.n == 2);
        assert!((pooled.trend.return_gain.mean - 3.0).abs() < 1e-12);
        assert_eq!(pooled.mean_budget, 3.0);
        assert!((pooled.total_return_slope.unwrap().mean - 3.0).abs() < 1e-12);
        assert_eq!(pooled.max_cost_slope, None, "undefined in every part");
        assert!(pooled.per_condition.is_empty());
        // Parts of different lengths pool the episodes they all hold.
        let mut short = summary(0.0, false);
        short.per_episode.truncate(2);
        assert_eq!(
            Summary::pooled(&[summary(1.0, false), short])
                .per_episode
                .len(),
            2
        );
    }
}
