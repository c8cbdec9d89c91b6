//! Collected trajectories, the replay buffer and batch assembly: the token of
//! each step ([`push_token`], one construction for collection, training and
//! evaluation) and the masks that keep `terminated` and `truncated` apart all
//! the way into the TD targets.

use std::collections::{HashMap, HashSet, VecDeque};
use std::path::Path;

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use tch::{Device, Tensor};

use safety_envs::{GoalRule, GoalShown};

use super::config::{EppoConfig, NoveltyBudget, PenaltyForm, PriceChange};
use super::net::NetSpec;
use crate::signals::position_cell;
use crate::tokens::{self, StepToken};

/// K episodes in one task with one budget, as collected.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Trajectory {
    /// The per-episode cost budget delta.
    pub budget: f32,
    /// The task's goal in observation terms ([`GoalRule`]; relabelling moves it).
    pub goal: [f32; 2],
    /// (T, obs_dim) observations s_t.
    pub obs: Vec<f32>,
    /// (T, obs_dim) the observation a_t led to: s_{t+1}, or the episode's
    /// final observation where a_t ended it (the next s_t is then a new start).
    pub next_obs: Vec<f32>,
    /// (T, act_flat) actions a_t as the network sees them (one-hot, or in [-1, 1]).
    pub actions: Vec<f32>,
    /// Discrete action indices (empty for continuous).
    pub action_idx: Vec<i64>,
    /// (T,) reward r_{t+1} and cost c_{t+1} received for a_t.
    pub rewards: Vec<f32>,
    pub costs: Vec<f32>,
    /// (T,) CTG_t before acting at t.
    pub ctg: Vec<f32>,
    /// (T,) s_t is an episode's first state.
    pub start: Vec<bool>,
    /// (T,) the step ended its episode at the goal (terminal: nothing to bootstrap past it).
    pub terminated: Vec<bool>,
    /// (T,) the step ended its episode at the time limit (not terminal).
    pub truncated: Vec<bool>,
    /// (T,) index of the episode the step belongs to.
    pub episode: Vec<u32>,
    /// Per episode: return, cost, and whether it ended at the goal.
    pub episode_returns: Vec<f32>,
    pub episode_costs: Vec<f32>,
    pub episode_success: Vec<bool>,
}

impl Trajectory {
    /// Steps in the trajectory.
    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.rewards.is_empty()
    }

    /// max_k (C_k - delta): the trajectory's term in Eq. (7).
    pub fn max_violation(&self) -> f32 {
        self.episode_costs
            .iter()
            .map(|c| c - self.budget)
            .fold(f32::NEG_INFINITY, f32::max)
    }

    /// Whether the episode's budget is spent once `step` has paid its cost
    /// (the CTG after the step below 0).
    pub fn budget_spent_after(&self, step: usize) -> bool {
        self.ctg[step] - self.costs[step] < 0.0
    }

    /// Per episode, whether its cost passed the budget (the violation flag).
    pub fn episodes_over_budget(&self) -> impl Iterator<Item = bool> + '_ {
        self.episode_costs.iter().map(|&c| c > self.budget)
    }
}

/// Whole trajectories, oldest evicted first once `capacity` steps are exceeded.
#[derive(Debug, Default)]
pub struct Replay {
    pub(super) trajectories: VecDeque<Trajectory>,
    steps: usize,
    capacity: usize,
}

impl Replay {
    pub fn new(capacity: usize) -> Self {
        Replay {
            trajectories: VecDeque::new(),
            steps: 0,
            capacity,
        }
    }

    pub fn push(&mut self, t: Trajectory) {
        self.steps += t.len();
        self.trajectories.push_back(t);
        while self.steps > self.capacity {
            match self.trajectories.pop_front() {
                Some(old) => self.steps -= old.len(),
                None => break,
            }
        }
    }

    pub fn len(&self) -> usize {
        self.trajectories.len()
    }

    pub fn is_empty(&self) -> bool {
        self.trajectories.is_empty()
    }

    /// Steps held.
    pub fn steps(&self) -> usize {
        self.steps
    }

    pub(super) fn sample<'a>(&'a self, n: usize, rng: &mut ChaCha8Rng) -> Vec<&'a Trajectory> {
        (0..n)
            .map(|_| &self.trajectories[rng.gen_range(0..self.trajectories.len())])
            .collect()
    }

    /// Writes the held trajectories to `path` (safetensors: each field's
    /// values concatenated over trajectories, with their lengths), so that a
    /// resumed run samples what the uninterrupted one would have. A resume
    /// that refilled from an empty replay trained its first rounds on a few
    /// fresh trajectories, and its return and Q dropped for hundreds of
    /// updates (results/eppo_darkroom_budget, session 40).
    pub(super) fn save(&self, path: &Path) -> Result<(), String> {
        let ts = &self.trajectories;
        let floats = |f: fn(&Trajectory) -> &[f32]| {
            Tensor::from_slice(
                &ts.iter()
                    .flat_map(|t| f(t).iter().copied())
                    .collect::<Vec<_>>(),
            )
        };
        let flags = |f: fn(&Trajectory) -> &[bool]| {
            let v: Vec<u8> = ts
                .iter()
                .flat_map(|t| f(t).iter().map(|&b| u8::from(b)))
                .collect();
            Tensor::from_slice(&v)
        };
        let ints = |v: Vec<i64>| Tensor::from_slice(&v);
        let tensors = [
            ("steps", ints(ts.iter().map(|t| t.len() as i64).collect())),
            (
                "episodes",
                ints(ts.iter().map(|t| t.episode_returns.len() as i64).collect()),
            ),
            (
                "budget",
                Tensor::from_slice(&ts.iter().map(|t| t.budget).collect::<Vec<_>>()),
            ),
            ("goal", floats(|t| &t.goal)),
            ("obs", floats(|t| &t.obs)),
            ("next_obs", floats(|t| &t.next_obs)),
            ("actions", floats(|t| &t.actions)),
            (
                "action_idx",
                ints(
                    ts.iter()
                        .flat_map(|t| t.action_idx.iter().copied())
                        .collect(),
                ),
            ),
            ("rewards", floats(|t| &t.rewards)),
            ("costs", floats(|t| &t.costs)),
            ("ctg", floats(|t| &t.ctg)),
            ("start", flags(|t| &t.start)),
            ("terminated", flags(|t| &t.terminated)),
            ("truncated", flags(|t| &t.truncated)),
            (
                "episode",
                ints(
                    ts.iter()
                        .flat_map(|t| t.episode.iter().map(|&e| i64::from(e)))
                        .collect(),
                ),
            ),
            ("episode_returns", floats(|t| &t.episode_returns)),
            ("episode_costs", floats(|t| &t.episode_costs)),
            ("episode_success", flags(|t| &t.episode_success)),
        ];
        Tensor::write_safetensors(&tensors, path).map_err(|e| e.to_string())
    }

    /// Reads a replay written by [`Replay::save`] into a buffer of `capacity`
    /// steps (the oldest trajectories dropped if it holds fewer).
    pub(super) fn load(path: &Path, capacity: usize) -> Result<Self, String> {
        let mut fields: HashMap<String, Tensor> = Tensor::read_safetensors(path)
            .map_err(|e| e.to_string())?
            .into_iter()
            .collect();
        let mut floats = |name: &str| field::<f32>(&mut fields, name);
        let (obs, next_obs, actions) = (floats("obs")?, floats("next_obs")?, floats("actions")?);
        let (rewards, costs, ctg) = (floats("rewards")?, floats("costs")?, floats("ctg")?);
        let (budget, goal) = (floats("budget")?, floats("goal")?);
        let episode_returns = floats("episode_returns")?;
        let episode_costs = floats("episode_costs")?;
        let mut ints = |name: &str| field::<i64>(&mut fields, name);
        let (lengths, episodes) = (ints("steps")?, ints("episodes")?);
        let (action_idx, episode) = (ints("action_idx")?, ints("episode")?);
        let mut flags = |name: &str| {
            field::<u8>(&mut fields, name)
                .map(|v| v.into_iter().map(|b| b != 0).collect::<Vec<_>>())
        };
        let (start, terminated) = (flags("start")?, flags("terminated")?);
        let (truncated, episode_success) = (flags("truncated")?, flags("episode_success")?);

        if let Some(n) = lengths.iter().chain(&episodes).find(|&&n| n < 0) {
            return Err(format!("a trajectory of {n} steps or episodes"));
        }
        let total: usize = lengths.iter().map(|&n| n as usize).sum();
        let n_episodes: usize = episodes.iter().map(|&n| n as usize).sum();
        if total == 0 {
            return Ok(Replay::new(capacity));
        }
        let width = |len: usize, name: &str| {
            if !len.is_multiple_of(total) {
                Err(format!("`{name}` holds {len} values for {total} steps"))
            } else {
                Ok(len / total)
            }
        };
        let n = lengths.len();
        let obs_dim = width(obs.len(), "obs")?;
        let act_dim = width(actions.len(), "actions")?;
        let per_step_ok = [&rewards, &costs, &ctg].iter().all(|v| v.len() == total)
            && [&start, &terminated, &truncated]
                .iter()
                .all(|v| v.len() == total)
            && next_obs.len() == obs.len()
            && episode.len() == total
            && (action_idx.is_empty() || action_idx.len() == total);
        let per_traj_ok = episodes.len() == n && budget.len() == n && goal.len() == 2 * n;
        let per_episode_ok = [&episode_returns, &episode_costs]
            .iter()
            .all(|v| v.len() == n_episodes)
            && episode_success.len() == n_episodes;
        if !(per_step_ok && per_traj_ok && per_episode_ok) {
            return Err(format!(
                "the fields' sizes do not agree with {n} trajectories of {total} steps and \
                 {n_episodes} episodes"
            ));
        }
        let mut replay = Replay::new(capacity);
        let (mut at, mut ep) = (0, 0);
        for i in 0..n {
            let (len, k) = (lengths[i] as usize, episodes[i] as usize);
            let steps = at..at + len;
            let eps = ep..ep + k;
            replay.push(Trajectory {
                budget: budget[i],
                goal: [goal[2 * i], goal[2 * i + 1]],
                obs: obs[at * obs_dim..(at + len) * obs_dim].to_vec(),
                next_obs: next_obs[at * obs_dim..(at + len) * obs_dim].to_vec(),
                actions: actions[at * act_dim..(at + len) * act_dim].to_vec(),
                action_idx: if action_idx.is_empty() {
                    Vec::new()
                } else {
                    action_idx[steps.clone()].to_vec()
                },
                rewards: rewards[steps.clone()].to_vec(),
                costs: costs[steps.clone()].to_vec(),
                ctg: ctg[steps.clone()].to_vec(),
                start: start[steps.clone()].to_vec(),
                terminated: terminated[steps.clone()].to_vec(),
                truncated: truncated[steps.clone()].to_vec(),
                episode: episode[steps].iter().map(|&e| e as u32).collect(),
                episode_returns: episode_returns[eps.clone()].to_vec(),
                episode_costs: episode_costs[eps.clone()].to_vec(),
                episode_success: episode_success[eps].to_vec(),
            });
            at += len;
            ep += k;
        }
        Ok(replay)
    }
}

/// One named field of a saved replay, as a vector.
fn field<T>(fields: &mut HashMap<String, Tensor>, name: &str) -> Result<Vec<T>, String>
where
    Vec<T>: for<'a> TryFrom<&'a Tensor, Error = tch::TchError>,
{
    let t = fields
        .remove(name)
        .ok_or_else(|| format!("no `{name}` tensor"))?;
    Vec::<T>::try_from(&t).map_err(|e| format!("`{name}`: {e}"))
}

/// Writes one token ([`crate::tokens`], shared with supervised pretraining):
/// obs s_t and the observation a_{t-1} arrived at (both normalised), a_{t-1},
/// r_t (scaled), c_t, CTG_t / ctg_max, start flag.
#[allow(clippy::too_many_arguments)]
pub(super) fn push_token(
    spec: &NetSpec,
    cfg: &EppoConfig,
    out: &mut Vec<f32>,
    obs: &[f32],
    arrived_obs: &[f32],
    prev_action: &[f32],
    reward: f32,
    cost: f32,
    ctg: f32,
    start: bool,
) {
    let step = StepToken {
        obs,
        arrived_obs,
        prev_action,
        reward,
        cost,
        to_go: &[ctg / cfg.tasks.ctg_max],
        start,
    };
    tokens::push_token(
        &step,
        cfg.targets.reward_scale as f32,
        |o, out| spec.normalise_obs(o, out),
        out,
    );
}

/// A training batch of B windows of length L (right-padded).
pub(super) struct Batch {
    /// (B, L, token_dim)
    pub(super) tokens: Tensor,
    /// (B, L) discrete action indices, or (B, L, A) continuous actions.
    pub(super) actions: Tensor,
    /// (B, L) reward r_{t+1} (scaled) and cost c_{t+1}.
    pub(super) rewards: Tensor,
    pub(super) costs: Tensor,
    /// (B, L) 1 where the step's episode exceeded the budget (v_e).
    pub(super) violated: Tensor,
    /// (B, L) the step's episode index k within its trajectory (0 on padding).
    pub(super) episode: Tensor,
    /// (B, L) the remaining budget CTG_t when the step was taken (unscaled).
    pub(super) ctg: Tensor,
    /// (B, L) 1 on real (not padded) steps: the actor loss.
    pub(super) valid: Tensor,
    /// (B, L) 1 where a TD target exists for the step: the critic losses.
    pub(super) td_valid: Tensor,
    /// (B, L) 1 where the reward target bootstraps from position t + 1.
    pub(super) bootstrap: Tensor,
    /// (B, L) 1 where the cost target bootstraps from position t + 1: never
    /// past an episode's end, since the budget binds each episode on its own
    /// (Eq. 6, 7): a violation charges only its own episode.
    pub(super) cost_bootstrap: Tensor,
    /// (B, 2) each trajectory's goal position (relabelled where it was moved).
    pub(super) goal: Tensor,
    /// (B, L) 1 on real steps after the window's first success: the goal is
    /// in the context there (the goal-recall loss, the novelty critics'
    /// weight in the actor).
    pub(super) goal_known: Tensor,
    /// With `novelty_critic`: (B, L) the novelty bonus (scaled) that
    /// `rewards` would otherwise carry, the novelty critics' reward (their
    /// targets bootstrap as `bootstrap` says).
    pub(super) novelty_rewards: Option<Tensor>,
}

/// The critics' pretraining-only dense reward for step `step` of `t`:
/// `dense_reward_coef` x (distance to the goal before the step - after it),
/// positions read through the goal rule's indices (the first two entries of
/// every observation here). Zero when off; never in a token.
fn dense_reward(t: &Trajectory, step: usize, spec: &NetSpec, cfg: &EppoConfig) -> f32 {
    if cfg.goal.dense_reward_coef == 0.0 {
        return 0.0;
    }
    let od = spec.obs_dim;
    let before = [t.obs[step * od], t.obs[step * od + 1]];
    let after = [t.next_obs[step * od], t.next_obs[step * od + 1]];
    let progress = GoalRule::distance(before, t.goal) - GoalRule::distance(after, t.goal);
    cfg.goal.dense_reward_coef as f32 * progress
}

/// For each step of `t`, true where the termination ends the critics'
/// value (`penalty = "terminate"`): in each episode, the first step
/// over budget that pays a cost, the step that overspends.
pub(super) fn value_end_steps(t: &Trajectory) -> Vec<bool> {
    let mut ended_in = None;
    (0..t.len())
        .map(|step| {
            let ends = t.budget_spent_after(step)
                && t.costs[step] > 0.0
                && ended_in != Some(t.episode[step]);
            if ends {
                ended_in = Some(t.episode[step]);
            }
            ends
        })
        .collect()
}

/// For each step of `t`, 1 where it arrives in a cell (side `cell`, on the
/// position at observation indices 0 and 1) that the trajectory has not been
/// in before, episode starts included, up to its first success (0 after
/// it); 0 elsewhere. The novelty bonus's indicator
/// ([`EppoConfig::novelty_bonus`]).
pub(super) fn novel_arrivals(t: &Trajectory, obs_dim: usize, cell: f64) -> Vec<f32> {
    let key = |o: &[f32]| position_cell(o, cell);
    let mut seen = HashSet::new();
    let mut novel = vec![0f32; t.len()];
    for (step, flag) in novel.iter_mut().enumerate() {
        seen.insert(key(&t.obs[step * obs_dim..]));
        if seen.insert(key(&t.next_obs[step * obs_dim..])) {
            *flag = 1.0;
        }
        if t.rewards[step] > 0.0 {
            break;
        }
    }
    novel
}

/// What the critics' rewards carry beyond the collected reward at one update
/// ([`EppoConfig::shaping`]); the tokens never do.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct Shaping {
    /// The novelty bonus's weight (annealed).
    pub(super) novelty: f32,
    /// How the budget acts in the critics' targets.
    pub(super) budget: BudgetInTargets,
}

/// The budget's part in the critics' targets, by penalty form.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) enum BudgetInTargets {
    /// None: the forms that act through the actor's multiplier, and every
    /// form before the constraint starts.
    #[default]
    Absent,
    /// Saute and the excess price: the reward of every step of an episode
    /// once its cost has passed its budget (CTG after the step below 0).
    OverBudget(OverBudget),
    /// `penalty = "terminate"`: the reward and novelty critics' value ends
    /// where an episode's cost first passes its budget.
    EndsValue,
}

impl Shaping {
    /// The over-budget reward, under the forms that price cost.
    pub(super) fn over_budget(&self) -> Option<OverBudget> {
        match self.budget {
            BudgetInTargets::OverBudget(o) => Some(o),
            _ => None,
        }
    }

    /// Whether overspending ends the critics' value (`penalty = "terminate"`).
    pub(super) fn ends_value(&self) -> bool {
        matches!(self.budget, BudgetInTargets::EndsValue)
    }
}

/// The reward of a step taken over budget: `r - cost_price x c`, where r is
/// `replaced_reward` (Saute: the collected, dense and novelty rewards
/// dropped) or, if `None`, the step's shaped reward as usual, less the
/// novelty bonus unless `pays_novelty`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct OverBudget {
    pub(super) replaced_reward: Option<f32>,
    pub(super) cost_price: f32,
    pub(super) pays_novelty: bool,
}

/// A batch of windows of `trajs`, the critics' rewards shaped by `shaping`.
pub(super) fn make_batch(
    trajs: &[&Trajectory],
    cfg: &EppoConfig,
    spec: &NetSpec,
    shaping: Shaping,
    rng: &mut ChaCha8Rng,
    device: Device,
) -> Batch {
    let seq = cfg.model.transformer.max_len as usize;
    let windows = sample_windows(trajs, seq, rng);
    let l = windows.iter().map(|w| w.1).max().unwrap_or(1);
    let mut columns = Columns::new(trajs.len(), l, spec);
    for (j, (t, &window)) in trajs.iter().zip(&windows).enumerate() {
        columns.push_window(j * l, t, window, l, cfg, spec, shaping);
    }
    columns.into_batch(trajs, l, cfg, spec, device)
}

/// A batch's columns as [`make_batch`] fills them, window by window: tokens
/// and actions pushed step by step, the rest (B*L,) at `window * L + step`.
struct Columns {
    tokens: Vec<f32>,
    acts_f: Vec<f32>,
    acts_i: Vec<i64>,
    rew: Vec<f32>,
    novelty_rew: Vec<f32>,
    cost: Vec<f32>,
    viol: Vec<f32>,
    episode: Vec<i64>,
    ctg: Vec<f32>,
    valid: Vec<f32>,
    td_valid: Vec<f32>,
    boot: Vec<f32>,
    cost_boot: Vec<f32>,
    goal_known: Vec<f32>,
    zeros_a: Vec<f32>,
    zeros_o: Vec<f32>,
}

impl Columns {
    /// Room for `b` windows of `l` steps.
    fn new(b: usize, l: usize, spec: &NetSpec) -> Self {
        let (dtok, a) = (spec.token_dim(), spec.act_flat());
        Columns {
            tokens: Vec::with_capacity(b * l * dtok),
            acts_f: Vec::with_capacity(b * l * a),
            acts_i: Vec::with_capacity(b * l),
            rew: vec![0f32; b * l],
            novelty_rew: vec![0f32; b * l],
            cost: vec![0f32; b * l],
            viol: vec![0f32; b * l],
            episode: vec![0i64; b * l],
            ctg: vec![0f32; b * l],
            valid: vec![0f32; b * l],
            td_valid: vec![0f32; b * l],
            boot: vec![0f32; b * l],
            cost_boot: vec![0f32; b * l],
            goal_known: vec![0f32; b * l],
            zeros_a: vec![0f32; a],
            zeros_o: vec![0f32; spec.obs_dim],
        }
    }

    /// The window `(s, len)` of `t`, padded to `l` steps, at row `k0`: each
    /// step's token and action, the critics' rewards, labels and TD masks.
    #[allow(clippy::too_many_arguments)]
    fn push_window(
        &mut self,
        k0: usize,
        t: &Trajectory,
        (s, len): (usize, usize),
        l: usize,
        cfg: &EppoConfig,
        spec: &NetSpec,
        shaping: Shaping,
    ) {
        let violated: Vec<bool> = t.episodes_over_budget().collect();
        let novel = if shaping.novelty > 0.0 {
            novel_arrivals(t, spec.obs_dim, cfg.novelty.novelty_cell)
        } else {
            vec![0.0; t.len()]
        };
        let value_ends = shaping.ends_value().then(|| value_end_steps(t));
        // The goal is known once found, or throughout when shown.
        let mut found =
            cfg.goal.goal_in_observation && t.obs.get(..spec.obs_dim).is_some_and(GoalShown::shows);
        for i in 0..l {
            let k = k0 + i;
            if i >= len {
                self.push_padding(spec, cfg);
                continue;
            }
            let step = s + i;
            self.push_step(t, step, spec, cfg);
            (self.rew[k], self.novelty_rew[k]) =
                critic_rewards(t, step, novel[step], found, spec, cfg, shaping);
            self.cost[k] = t.costs[step];
            self.ctg[k] = t.ctg[step];
            self.episode[k] = i64::from(t.episode[step]);
            self.viol[k] = if violated[t.episode[step] as usize] {
                1.0
            } else {
                0.0
            };
            self.valid[k] = 1.0;
            self.goal_known[k] = if found { 1.0 } else { 0.0 };
            found |= t.terminated[step];
            let (has_target, mut bootstraps, cost_bootstraps) = td_masks(cfg, t, step, i + 1 < len);
            if value_ends.as_ref().is_some_and(|ends| ends[step]) {
                bootstraps = false;
            }
            self.td_valid[k] = if has_target { 1.0 } else { 0.0 };
            self.boot[k] = if bootstraps { 1.0 } else { 0.0 };
            self.cost_boot[k] = if cost_bootstraps { 1.0 } else { 0.0 };
        }
    }

    /// Padding: a zero token after a window's end; masked out everywhere.
    fn push_padding(&mut self, spec: &NetSpec, cfg: &EppoConfig) {
        push_token(
            spec,
            cfg,
            &mut self.tokens,
            &self.zeros_o,
            &self.zeros_o,
            &self.zeros_a,
            0.0,
            0.0,
            0.0,
            false,
        );
        self.acts_f.extend_from_slice(&self.zeros_a);
        self.acts_i.push(0);
    }

    /// The token of step `step` of `t` (what arrived before it: zeros at
    /// the trajectory's start) and the action taken at it.
    fn push_step(&mut self, t: &Trajectory, step: usize, spec: &NetSpec, cfg: &EppoConfig) {
        let (od, a) = (spec.obs_dim, spec.act_flat());
        let obs = &t.obs[step * od..(step + 1) * od];
        let (arrived, prev, r, c) = if step == 0 {
            (&self.zeros_o[..], &self.zeros_a[..], 0.0, 0.0)
        } else {
            (
                &t.next_obs[(step - 1) * od..step * od],
                &t.actions[(step - 1) * a..step * a],
                t.rewards[step - 1],
                t.costs[step - 1],
            )
        };
        push_token(
            spec,
            cfg,
            &mut self.tokens,
            obs,
            arrived,
            prev,
            r,
            c,
            t.ctg[step],
            t.start[step],
        );
        self.acts_f
            .extend_from_slice(&t.actions[step * a..(step + 1) * a]);
        self.acts_i
            .push(t.action_idx.get(step).copied().unwrap_or(0));
    }

    /// The columns as tensors on `device`: (B, L), tokens (B, L, token_dim),
    /// continuous actions (B, L, A), goals (B, 2).
    fn into_batch(
        self,
        trajs: &[&Trajectory],
        l: usize,
        cfg: &EppoConfig,
        spec: &NetSpec,
        device: Device,
    ) -> Batch {
        let (dtok, a) = (spec.token_dim(), spec.act_flat());
        let (bi, li) = (trajs.len() as i64, l as i64);
        let f = |v: &[f32]| Tensor::from_slice(v).view([bi, li]).to_device(device); // (B*L,) -> (B, L)
        let actions = match spec.n_actions {
            Some(_) => Tensor::from_slice(&self.acts_i)
                .view([bi, li])
                .to_device(device), // (B, L)
            None => Tensor::from_slice(&self.acts_f)
                .view([bi, li, a as i64])
                .to_device(device), // (B, L, A)
        };
        Batch {
            tokens: Tensor::from_slice(&self.tokens)
                .view([bi, li, dtok as i64])
                .to_device(device), // (B, L, token_dim)
            actions,
            rewards: f(&self.rew),
            costs: f(&self.cost),
            violated: f(&self.viol),
            episode: Tensor::from_slice(&self.episode)
                .view([bi, li])
                .to_device(device),
            ctg: f(&self.ctg),
            valid: f(&self.valid),
            td_valid: f(&self.td_valid),
            bootstrap: f(&self.boot),
            cost_bootstrap: f(&self.cost_boot),
            goal: Tensor::from_slice(&trajs.iter().flat_map(|t| t.goal).collect::<Vec<f32>>())
                .view([bi, 2])
                .to_device(device),
            goal_known: f(&self.goal_known),
            novelty_rewards: cfg.novelty.novelty_critic.then(|| f(&self.novelty_rew)),
        }
    }
}

/// The critics' reward for step `step` of `t`, and the novelty critic's (0
/// without one), both times `reward_scale`: the collected reward, the dense
/// reward (once the goal is `found`, with `dense_reward_after_goal`) and the
/// novelty bonus (`novel`: the step's arrival indicator), priced as
/// `shaping` says once the episode's budget is spent.
fn critic_rewards(
    t: &Trajectory,
    step: usize,
    novel: f32,
    found: bool,
    spec: &NetSpec,
    cfg: &EppoConfig,
    shaping: Shaping,
) -> (f32, f32) {
    let over_budget = shaping.over_budget();
    let dense = if cfg.goal.dense_reward_after_goal && !found {
        0.0
    } else {
        dense_reward(t, step, spec, cfg)
    };
    let budget_spent = t.budget_spent_after(step);
    let share = match cfg.novelty.novelty_budget {
        NoveltyBudget::RemainingShare => (t.ctg[step] / t.budget).clamp(0.0, 1.0),
        NoveltyBudget::Always | NoveltyBudget::WithinBudget => 1.0,
    };
    let novelty = shaping.novelty * novel * share;
    // The step's reward with `bonus` for novelty (nothing of it once
    // the episode's budget is spent, unless the price leaves it).
    let priced = |bonus: f32| {
        let shaped = t.rewards[step] + dense + bonus;
        match over_budget {
            Some(o) if budget_spent => {
                let kept = if o.pays_novelty {
                    shaped
                } else {
                    shaped - bonus
                };
                o.replaced_reward.unwrap_or(kept) - o.cost_price * t.costs[step]
            }
            _ => shaped,
        }
    };
    let scale = cfg.targets.reward_scale as f32;
    if cfg.novelty.novelty_critic {
        let paid = match over_budget {
            Some(o) if budget_spent && (o.replaced_reward.is_some() || !o.pays_novelty) => 0.0,
            _ => novelty,
        };
        (priced(0.0) * scale, paid * scale)
    } else {
        (priced(novelty) * scale, 0.0)
    }
}

/// Each trajectory's window (start, length): at most `seq` steps, starting
/// anywhere in a longer trajectory.
fn sample_windows(trajs: &[&Trajectory], seq: usize, rng: &mut ChaCha8Rng) -> Vec<(usize, usize)> {
    trajs
        .iter()
        .map(|t| {
            let len = t.len().min(seq);
            let start = if t.len() > seq {
                rng.gen_range(0..=t.len() - seq)
            } else {
                0
            };
            (start, len)
        })
        .collect()
}

/// For step `step` of `t`: (the step has a TD target, its reward target
/// bootstraps from position t + 1, its cost target does). `next_in_window`:
/// position t + 1 is inside the batch's window.
fn td_masks(
    cfg: &EppoConfig,
    t: &Trajectory,
    step: usize,
    next_in_window: bool,
) -> (bool, bool, bool) {
    let last_of_trajectory = step + 1 == t.len();
    let (has_target, bootstraps) = if cfg.targets.bootstrap_across_episodes {
        // Meta-RL view: an episode's end (terminated at the goal or
        // truncated at the time limit) leads to the next episode's
        // first state, which is the next token: bootstrap through it.
        // Only the trajectory's end stops the sum of K returns.
        if last_of_trajectory {
            (true, false)
        } else {
            (next_in_window, next_in_window)
        }
    } else if t.terminated[step] {
        // Terminated (goal): a true terminal state, target = r alone.
        (true, false)
    } else if t.truncated[step] {
        // Truncated (time limit): the value goes on past the final
        // state, but that state is not a token (the next token starts
        // another episode), so the step has no target and is skipped.
        (false, false)
    } else {
        (next_in_window, next_in_window)
    };
    // The cost target never bootstraps past an episode's end: the budget
    // binds each episode on its own (Eq. 6, 7).
    let episode_ends = t.terminated[step] || t.truncated[step];
    (has_target, bootstraps, bootstraps && !episode_ends)
}

/// `penalty = "saute"`: the critics' reward for every step of an episode
/// once its cost has passed its budget, in place of the collected reward: a
/// tenth of a goal (OmniSafe's Saute default is -1 per step on dense-reward
/// tasks; the goal here is worth 1 once).
const SAUTE_UNSAFE_REWARD: f32 = -0.1;

/// The critics' shaping over training, owned here beside what applies it.
impl EppoConfig {
    /// The price per unit of excess cost `updates_constrained` updates after
    /// the constraint came on (`over_budget_price_schedule`).
    pub fn over_budget_price(&self, updates_constrained: u64) -> f64 {
        let mut reached = PriceChange {
            after: 0,
            price: self.constraint.over_budget_cost_price,
        };
        for &next in &self.constraint.over_budget_price_schedule {
            if updates_constrained < next.after {
                return reached.price;
            }
            reached = next;
        }
        reached.price
    }

    /// What the critics' rewards carry at update `updates` beyond the
    /// collected reward. The over-budget reward (Saute's, the excess price)
    /// starts with the constraint (`constrained_since`: the update it came
    /// on at), as the multiplier does.
    pub(super) fn shaping(&self, updates: u64, constrained_since: Option<u64>) -> Shaping {
        let Some(since) = constrained_since else {
            return Shaping {
                novelty: self.novelty.novelty_bonus as f32,
                ..Shaping::default()
            };
        };
        let cost_price = self.over_budget_price(updates.saturating_sub(since)) as f32;
        Shaping {
            novelty: self.novelty.novelty_bonus as f32,
            budget: match self.constraint.penalty {
                PenaltyForm::Saute => BudgetInTargets::OverBudget(OverBudget {
                    replaced_reward: Some(SAUTE_UNSAFE_REWARD),
                    cost_price,
                    pays_novelty: false,
                }),
                PenaltyForm::Excess => BudgetInTargets::OverBudget(OverBudget {
                    replaced_reward: None,
                    cost_price,
                    pays_novelty: self.novelty.novelty_budget != NoveltyBudget::WithinBudget,
                }),
                PenaltyForm::Terminate => BudgetInTargets::EndsValue,
                PenaltyForm::Hindsight | PenaltyForm::Hinge => BudgetInTargets::Absent,
            },
        }
    }
}
