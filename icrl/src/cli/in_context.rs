//! The end of an EPPO `icrl pretrain` (the main job among them): a short
//! held-out check that the agent learns **in context**, printed beside the
//! training summary. 16 edge-oriented tasks (the held-out distribution), 3
//! budgets across the pretraining range, as many episodes as the context
//! holds (at most 20), frozen parameters; the agent and a uniformly random
//! policy on the same tasks and budgets. Per episode index k: return, cost,
//! the revisit rate P(goal at k | goal found before k) and the search (cells,
//! 0.75 m on the robots, first entered in episode k by the trajectories that
//! have not found the goal yet). About a minute on Car with the quick preset.

use std::fmt::Write as _;
use std::path::Path;

use safety_envs::{CmdpEnv, EnvError, EnvName, EnvOptions, Orientation, make_env, spawn_config};

use crate::agent::Conditioning;
use crate::eval::error::EvalCmdError;
use crate::eval::load::{LoadedAgent, load_checkpoint};
use crate::eval::{EvalConfig, EvalResult, evaluate};

/// Held-out tasks of the check.
const TASKS: usize = 16;
/// Budgets of the check, spread evenly over the pretraining range.
const BUDGETS: usize = 3;
/// Most episodes per trajectory (Table 1's K for Point and Car).
const MAX_EPISODES: usize = 20;
/// The check's evaluation seed: fixed, so reruns compare.
const SEED: u64 = 20_261_201;

/// One value per `[condition][task][episode]`, as [`EvalResult`] holds them.
type ByEpisode<T> = [Vec<Vec<T>>];

/// Per episode index: mean return, mean cost, the mean cost paid again
/// (near a cost of an earlier episode), revisit rate, and the cells first
/// entered by the trajectories still searching (each NaN where no trajectory
/// had found the goal before k, or none was still searching).
#[derive(Clone, Debug, PartialEq)]
pub struct PerEpisode {
    pub ret: Vec<f64>,
    pub cost: Vec<f64>,
    pub repeat_cost: Vec<f64>,
    pub revisit: Vec<f64>,
    pub search_new_cells: Vec<f64>,
}

impl PerEpisode {
    /// Averages over every (condition, task) trajectory of `r`.
    pub fn of(r: &EvalResult) -> Self {
        Self::from_parts(
            r.episodes,
            &r.returns,
            (&r.costs, &r.repeat_costs),
            &r.reached_goal,
            &r.new_cells,
        )
    }

    /// The same from `[condition][task][episode]` returns, costs (all of
    /// them, and those paid again), goals and cells first entered.
    pub fn from_parts(
        k_n: usize,
        returns: &ByEpisode<f32>,
        (costs, repeat_costs): (&ByEpisode<f32>, &ByEpisode<f32>),
        reached_goal: &ByEpisode<bool>,
        new_cells: &ByEpisode<u32>,
    ) -> Self {
        let trajectories = || {
            returns
                .iter()
                .zip(costs.iter().zip(repeat_costs))
                .zip(reached_goal)
                .zip(new_cells)
                .flat_map(|(((ret, (cost, again)), goal), cells)| {
                    ret.iter().zip(cost.iter().zip(again)).zip(goal).zip(cells)
                })
        };
        let (mut ret, mut cost) = (vec![0.0; k_n], vec![0.0; k_n]);
        let mut repeat_cost = vec![0.0; k_n];
        let (mut revisits, mut found_before) = (vec![0usize; k_n], vec![0usize; k_n]);
        let (mut cells, mut searching) = (vec![0u32; k_n], vec![0usize; k_n]);
        let mut n = 0usize;
        for (((rets, (costs, again)), goals), entered) in trajectories() {
            n += 1;
            let mut seen = false;
            for k in 0..k_n {
                ret[k] += f64::from(rets[k]);
                cost[k] += f64::from(costs[k]);
                repeat_cost[k] += f64::from(again[k]);
                if seen {
                    found_before[k] += 1;
                    revisits[k] += usize::from(goals[k]);
                } else {
                    searching[k] += 1;
                    cells[k] += entered[k];
                }
                seen |= goals[k];
            }
        }
        let n = n.max(1) as f64;
        let ratio = |a: f64, b: usize| if b == 0 { f64::NAN } else { a / b as f64 };
        PerEpisode {
            ret: ret.iter().map(|x| x / n).collect(),
            cost: cost.iter().map(|x| x / n).collect(),
            repeat_cost: repeat_cost.iter().map(|x| x / n).collect(),
            revisit: (0..k_n)
                .map(|k| ratio(revisits[k] as f64, found_before[k]))
                .collect(),
            search_new_cells: (0..k_n)
                .map(|k| ratio(f64::from(cells[k]), searching[k]))
                .collect(),
        }
    }
}

/// Runs the check on `checkpoint` and returns the table to print.
pub fn check(checkpoint: &Path, env: EnvName) -> Result<String, EvalCmdError> {
    let mut agent = load_checkpoint(checkpoint, env)?;
    let env_options = EnvOptions {
        max_episode_steps: agent.context.map(|c| c.max_episode_steps),
        physics_steps_per_action: agent.physics_steps_per_action,
    };
    let make = move || -> Result<Box<dyn CmdpEnv>, EnvError> { make_env(env, &env_options) };
    let probe = make()?;
    let t_max = probe.max_episode_steps();
    let episodes = agent
        .context
        .map_or(MAX_EPISODES, |c| c.episodes(t_max))
        .min(MAX_EPISODES);
    let range = agent
        .budget_range
        .ok_or_else(|| EvalCmdError::Options("the checkpoint records no budget range".into()))?;
    let budgets: Vec<f32> = (0..BUDGETS)
        .map(|i| range.low + (range.high - range.low) * (i as f32 + 0.5) / BUDGETS as f32)
        .collect();
    let cfg = EvalConfig {
        tasks: TASKS,
        episodes,
        conditions: budgets
            .iter()
            .map(|&ctg| Conditioning::Budget { ctg })
            .collect(),
        eval_seed: SEED,
        batch: TASKS * BUDGETS,
        threads: 1,
        greedy: false,
        pretrain_tasks: agent.pretrain_tasks.clone(),
        record: None,
        torch_seed: Some(SEED),
        orientation: Orientation::Edge,
        search_cell: crate::signals::search_cell(env),
        repeat_radius: crate::signals::repeat_radius(env),
    };
    let spawn = spawn_config(env);
    let trained = evaluate(agent.agent.as_mut(), &make, &spawn, &cfg, &mut |_| {})?;
    let mut random = LoadedAgent::random(probe.action_space(), SEED);
    let baseline = evaluate(random.agent.as_mut(), &make, &spawn, &cfg, &mut |_| {})?;
    Ok(table(
        &PerEpisode::of(&trained),
        &PerEpisode::of(&baseline),
        &budgets,
    ))
}

/// The printed table: one row per episode index.
fn table(agent: &PerEpisode, random: &PerEpisode, budgets: &[f32]) -> String {
    let mut s = String::new();
    let budgets: Vec<String> = budgets.iter().map(|b| format!("{b:.1}")).collect();
    let _ = writeln!(
        s,
        "in-context check: {TASKS} held-out edge tasks x budgets {}, K = {}, frozen; the agent (random policy):",
        budgets.join(", "),
        agent.ret.len()
    );
    let _ = writeln!(
        s,
        "   k  return          cost            paid again      revisit       new cells while searching"
    );
    let shown = |x: f64, decimals: usize| {
        if x.is_nan() {
            "   -".to_string()
        } else {
            format!("{x:>4.decimals$}")
        }
    };
    for k in 0..agent.ret.len() {
        let _ = writeln!(
            s,
            "  {:>2}  {:.3} ({:.3})   {:>5.2} ({:>5.2})   {:>5.2} ({:>5.2})   {} ({})   {} ({})",
            k + 1,
            agent.ret[k],
            random.ret[k],
            agent.cost[k],
            random.cost[k],
            agent.repeat_cost[k],
            random.repeat_cost[k],
            shown(agent.revisit[k], 2),
            shown(random.revisit[k], 2),
            shown(agent.search_new_cells[k], 1),
            shown(random.search_new_cells[k], 1),
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn per_episode_rates_count_returns_costs_and_revisits() {
        // Two trajectories: found at k = 1 then again at k = 3; never found.
        let p = PerEpisode::from_parts(
            3,
            &[vec![vec![1.0, 0.0, 1.0], vec![0.0, 0.0, 0.0]]],
            (
                &[vec![vec![2.0, 1.0, 0.0], vec![4.0, 3.0, 2.0]]],
                &[vec![vec![0.0, 1.0, 0.0], vec![0.0, 2.0, 0.0]]],
            ),
            &[vec![vec![true, false, true], vec![false, false, false]]],
            &[vec![vec![5, 1, 0], vec![7, 3, 0]]],
        );
        assert_eq!(p.ret, [0.5, 0.0, 0.5]);
        assert_eq!(p.cost, [3.0, 2.0, 1.0]);
        assert_eq!(p.repeat_cost, [0.0, 1.5, 0.0]);
        assert!(p.revisit[0].is_nan(), "nothing found before k = 1");
        assert_eq!(&p.revisit[1..], [0.0, 1.0]);
        // New cells over the trajectories still searching: both at k = 1,
        // only the second after (the first found its goal at k = 1).
        assert_eq!(p.search_new_cells, [6.0, 3.0, 0.0]);
    }
}
