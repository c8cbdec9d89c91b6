//! Hindsight task relabelling (Packer et al., NeurIPS 2021, "Hindsight Task
//! Relabelling: Experience Replay for Sparse Reward Meta-RL"): a replayed
//! trajectory is read as if its goal had been at a position it reached, so
//! every trajectory becomes one that found a goal, and those that pass that
//! position again become revisits, the skill sparse rewards teach slowest.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use safety_envs::{GoalRule, GoalShown};

use super::net::NetSpec;
use super::replay::Trajectory;

/// Each sampled trajectory relabelled, with probability `prob`, at a goal
/// drawn by [`pick_goal`]; `None` replays it as collected. Draws nothing
/// when `prob` is 0, so runs without relabelling keep their random stream.
/// With `goal_slots` (`goal_in_observation`), a trajectory that was shown
/// its goal is shown the new one, as if collected in the relabelled task;
/// one that hid it stays blank.
pub(super) fn relabel_some(
    sampled: &[&Trajectory],
    prob: f64,
    spec: &NetSpec,
    rule: &GoalRule,
    goal_slots: bool,
    rng: &mut ChaCha8Rng,
) -> Vec<Option<Trajectory>> {
    if prob == 0.0 {
        return vec![None; sampled.len()];
    }
    sampled
        .iter()
        .map(|t| {
            if rng.r#gen::<f64>() >= prob {
                return None;
            }
            let goal = pick_goal(t, spec.obs_dim, rule, rng)?;
            let mut out = relabel(t, spec.obs_dim, spec.act_flat(), rule, goal);
            if goal_slots && GoalShown::shows(&t.obs[..spec.obs_dim]) {
                let od = spec.obs_dim;
                for row in out.obs.chunks_mut(od).chain(out.next_obs.chunks_mut(od)) {
                    GoalShown::show(row, goal);
                }
            }
            Some(out)
        })
        .collect()
}

/// A goal for [`relabel`]: the position a uniformly drawn step of `t` arrived
/// at, among the steps that arrived at least `rule.min_start_distance` from
/// their episode's start (as far as any real goal is); `None` when no step did.
pub fn pick_goal(
    t: &Trajectory,
    obs_dim: usize,
    rule: &GoalRule,
    rng: &mut ChaCha8Rng,
) -> Option<[f32; 2]> {
    let mut episode_start = [0f32; 2];
    let mut candidates = Vec::new();
    for step in 0..t.len() {
        if t.start[step] {
            episode_start = rule.position(&t.obs[step * obs_dim..(step + 1) * obs_dim]);
        }
        let arrived = rule.position(&t.next_obs[step * obs_dim..(step + 1) * obs_dim]);
        if GoalRule::distance(arrived, episode_start) >= rule.min_start_distance {
            candidates.push(arrived);
        }
    }
    if candidates.is_empty() {
        None
    } else {
        Some(candidates[rng.gen_range(0..candidates.len())])
    }
}

/// `t` as if the goal had been at `goal`: every episode keeps its steps up
/// to the first that arrives at `goal` (by `rule`), which earns reward 1 and
/// terminates it; the rest of that episode is cut. An episode that never
/// arrives there ends where it was recorded to end, truncated (one that ended
/// at the real goal too: in the relabelled task it would have gone on). Each
/// later episode starts from its own recorded spawn, as every episode of a
/// trajectory does, so the relabelled trajectory is one the task could give.
/// Costs, CTGs and the budget stay as recorded.
pub fn relabel(
    t: &Trajectory,
    obs_dim: usize,
    act_flat: usize,
    rule: &GoalRule,
    goal: [f32; 2],
) -> Trajectory {
    let (od, a) = (obs_dim, act_flat);
    let mut out = Trajectory {
        budget: t.budget,
        goal,
        ..Default::default()
    };
    let mut first = 0;
    while first < t.len() {
        let mut end = first + 1;
        while end < t.len() && !t.start[end] {
            end += 1;
        }
        let episode = out.episode_returns.len() as u32;
        let mut cost = 0.0;
        let mut success = false;
        for step in first..end {
            let arrived = &t.next_obs[step * od..(step + 1) * od];
            success = rule.reached(arrived, goal);
            let last = success || step + 1 == end;
            out.obs
                .extend_from_slice(&t.obs[step * od..(step + 1) * od]);
            out.next_obs.extend_from_slice(arrived);
            out.actions
                .extend_from_slice(&t.actions[step * a..(step + 1) * a]);
            if let Some(&idx) = t.action_idx.get(step) {
                out.action_idx.push(idx);
            }
            out.rewards.push(if success { 1.0 } else { 0.0 });
            out.costs.push(t.costs[step]);
            out.ctg.push(t.ctg[step]);
            out.start.push(t.start[step]);
            out.terminated.push(success);
            out.truncated.push(last && !success);
            out.episode.push(episode);
            cost += t.costs[step];
            if last {
                break;
            }
        }
        out.episode_returns.push(if success { 1.0 } else { 0.0 });
        out.episode_costs.push(cost);
        out.episode_success.push(success);
        first = end;
    }
    out
}
