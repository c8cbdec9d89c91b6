//! EPPO's tests: collection, the losses and their masks, acting through
//! the cache, determinism, and a run end to end (pretrain, resume, load).

use std::path::{Path, PathBuf};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::{Device, Kind, Tensor};

use safety_envs::{EnvName, Orientation, VecEnv, sample_task, spawn_config};

use super::collect::{Acting, EnvActions, Policy, sample_actions};
use super::losses::{goal_recall_loss, losses, n_step_targets, penalised_cost, tuned_entropy_coef};
use super::net::{tanh_gaussian_log_prob, tanh_gaussian_sample};
use super::replay::{Batch, OverBudget, Shaping, make_batch, novel_arrivals};
use super::*;
use crate::agent::{Actions, Conditioning, InContextAgent, StepInput};
use crate::model::Positions;
use crate::task_seeds::pretrain_task_seed;

/// A tiny configuration: trajectories of 2 episodes of 6 steps (also
/// used by the evaluation tests).
pub(crate) fn tiny() -> EppoConfig {
    let mut table = crate::presets::preset_table("eppo", "darkroom", "quick").unwrap();
    let sets = [
        "max_episode_steps=6",
        "k_min=2",
        "k_max=2",
        "n_envs=3",
        "batch_size=3",
        "replay_capacity=1000",
        "encoder_hidden=16",
        "head_hidden=16",
        "model.d_model=16",
        "model.n_heads=2",
        "model.n_layers=1",
        "model.d_ff=32",
        "model.max_len=12",
        "total_updates=4",
        "updates_per_round=2",
        "learning_starts=0",
        "checkpoint_every=2",
        // Tests run the synchronous loop; its overlapped twin has its own.
        "overlap=false",
        "learner_threads=0",
    ]
    .map(String::from);
    crate::presets::apply_overrides(&mut table, &sets).unwrap();
    crate::presets::resolve("tiny", table).unwrap()
}

fn tiny_learner(seed: u64) -> (Learner, VecEnv) {
    let mut cfg = tiny();
    cfg.seed = seed;
    let learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    (learner, training_venv(EnvName::DarkRoom, &cfg))
}

/// [`tiny`] for Point: two trajectories of two 75-step episodes, macro
/// actions of 50 physics steps.
fn tiny_point() -> EppoConfig {
    let mut cfg = tiny();
    cfg.max_episode_steps = 75;
    cfg.model.max_len = 150;
    cfg.n_envs = 2;
    cfg.batch_size = 2;
    cfg.physics_steps_per_action = Some(50);
    cfg
}

/// `cfg.n_envs` training environments of `env`, stepped on one thread.
fn training_venv(env: EnvName, cfg: &EppoConfig) -> VecEnv {
    let envs = (0..cfg.n_envs)
        .map(|_| make_training_env(env, cfg).unwrap())
        .collect();
    VecEnv::new(envs, 1, true).unwrap()
}

fn to_vec(t: &Tensor) -> Vec<f32> {
    Vec::<f32>::try_from(&t.to_kind(Kind::Float).view([-1])).unwrap()
}

#[test]
fn collected_trajectories_follow_algorithm_1() {
    let (mut learner, mut venv) = tiny_learner(0);
    let stats = learner.collect(&mut venv).unwrap();
    assert_eq!(stats.trajectories, 3);
    assert_eq!(learner.replay.len(), 3);
    for t in &learner.replay.trajectories {
        assert_eq!(t.episode_returns.len(), 2, "K = 2 episodes");
        assert!(t.budget >= 1.0 && t.budget <= 15.0);
        assert!(t.len() <= 12 && t.start[0]);
        for s in 0..t.len() {
            // CTG restarts at the budget each episode and decreases by costs.
            let expected = if t.start[s] {
                t.budget
            } else {
                t.ctg[s - 1] - t.costs[s - 1]
            };
            assert_eq!(t.ctg[s], expected, "step {s}");
            assert!(!(t.terminated[s] && t.truncated[s]));
            assert_eq!(
                t.terminated[s],
                t.rewards[s] > 0.0,
                "the goal reward ends the episode"
            );
        }
        let ends = (0..t.len())
            .filter(|&s| t.terminated[s] || t.truncated[s])
            .count();
        assert_eq!(ends, 2);
    }
}

/// Two episodes on a grid (obs = position, one action value): episode 0
/// passes (4, 6) at its second step and goes on to the time limit;
/// episode 1 ends at its real goal (5, 5) without passing (4, 6).
fn two_episode_trajectory() -> Trajectory {
    let path: [([f32; 2], [f32; 2], f32); 5] = [
        ([4.0, 4.0], [4.0, 5.0], 0.0),
        ([4.0, 5.0], [4.0, 6.0], 1.0),
        ([4.0, 6.0], [3.0, 6.0], 0.0),
        ([4.0, 4.0], [5.0, 4.0], 1.0),
        ([5.0, 4.0], [5.0, 5.0], 0.0),
    ];
    let mut t = Trajectory {
        budget: 0.5,
        ..Default::default()
    };
    for (s, (obs, next, cost)) in path.iter().enumerate() {
        t.obs.extend_from_slice(obs);
        t.next_obs.extend_from_slice(next);
        t.actions.push(s as f32);
        t.action_idx.push(s as i64);
        t.costs.push(*cost);
        t.start.push(s == 0 || s == 3);
        t.ctg.push(if s == 0 || s == 3 {
            0.5
        } else {
            0.5 - path[s - 1].2
        });
        t.episode.push(u32::from(s >= 3));
        t.rewards.push(if s == 4 { 1.0 } else { 0.0 });
        t.terminated.push(s == 4);
        t.truncated.push(s == 2);
    }
    t.episode_returns = vec![0.0, 1.0];
    t.episode_costs = vec![1.0, 1.0];
    t.episode_success = vec![false, true];
    t
}

const GRID_RULE: GoalRule = GoalRule {
    xy: [0, 1],
    radius: 0.0,
    min_start_distance: 1.0,
};

#[test]
fn relabelled_trajectory_is_one_where_that_position_was_the_goal() {
    let t = two_episode_trajectory();
    let r = relabel(&t, 2, 1, &GRID_RULE, [4.0, 6.0]);
    // Episode 0 ends on arrival at (4, 6): the third step is cut.
    // Episode 1 never arrives there: its real goal is no goal now, so it
    // ends where it was recorded to, truncated, without reward.
    assert_eq!(r.len(), 4);
    assert_eq!(r.obs, [4.0, 4.0, 4.0, 5.0, 4.0, 4.0, 5.0, 4.0]);
    assert_eq!(r.next_obs, [4.0, 5.0, 4.0, 6.0, 5.0, 4.0, 5.0, 5.0]);
    assert_eq!(r.actions, [0.0, 1.0, 3.0, 4.0]);
    assert_eq!(r.action_idx, [0, 1, 3, 4]);
    assert_eq!(r.rewards, [0.0, 1.0, 0.0, 0.0]);
    assert_eq!(r.terminated, [false, true, false, false]);
    assert_eq!(r.truncated, [false, false, false, true]);
    assert_eq!(r.start, [true, false, true, false]);
    assert_eq!(r.episode, [0, 0, 1, 1]);
    assert_eq!(r.episode_returns, [1.0, 0.0]);
    assert_eq!(r.episode_success, [true, false]);
    // Costs, CTGs and the budget as recorded, for the steps kept.
    assert_eq!(r.costs, [0.0, 1.0, 1.0, 0.0]);
    assert_eq!(r.ctg, [0.5, 0.5, 0.5, -0.5]);
    assert_eq!(r.episode_costs, [1.0, 1.0]);
    assert_eq!(r.budget, t.budget);
    assert_eq!(r.max_violation(), 0.5);
    // Relabelled at its own goal, a trajectory is unchanged.
    let same = relabel(&t, 2, 1, &GRID_RULE, [5.0, 5.0]);
    assert_eq!(same.rewards, t.rewards);
    assert_eq!(same.terminated, t.terminated);
    assert_eq!(same.truncated, t.truncated);
    assert_eq!(same.obs, t.obs);
    assert_eq!(same.episode_success, t.episode_success);
}

#[test]
fn relabelled_goals_are_reached_positions_away_from_the_start() {
    let t = two_episode_trajectory();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let far = GoalRule {
        min_start_distance: 1.9,
        ..GRID_RULE
    };
    for _ in 0..50 {
        let g = pick_goal(&t, 2, &GRID_RULE, &mut rng).unwrap();
        let arrived = t.next_obs.chunks(2).any(|o| o == g);
        assert!(arrived && g != [4.0, 4.0], "{g:?}");
        // Only (4, 6) and (3, 6) are 2 or more from the start (4, 4).
        let g = pick_goal(&t, 2, &far, &mut rng).unwrap();
        assert!(g == [4.0, 6.0] || g == [3.0, 6.0], "{g:?}");
    }
    let none = GoalRule {
        min_start_distance: 10.0,
        ..GRID_RULE
    };
    assert_eq!(pick_goal(&t, 2, &none, &mut rng), None);
}

#[test]
fn the_scripted_first_episode_reaches_the_goal_and_relabelled_updates_run() {
    let mut cfg = tiny_point();
    cfg.scripted_first_episode = true;
    cfg.relabel_prob = 1.0;
    let darkroom = EppoConfig {
        physics_steps_per_action: None,
        ..cfg.clone()
    };
    let e = Learner::new(darkroom, EnvName::DarkRoom).err().unwrap();
    assert!(e.to_string().contains("scripted_first_episode"), "{e}");
    let mut learner = Learner::new(cfg.clone(), EnvName::Point).unwrap();
    let mut venv = training_venv(EnvName::Point, &cfg);
    learner.collect(&mut venv).unwrap();
    for t in &learner.replay.trajectories {
        assert!(t.episode_success[0], "the controller reaches every goal");
        assert!(t.actions.iter().all(|x| x.abs() <= 1.0));
    }
    let stats = learner.update().unwrap();
    assert!(stats.value_loss.is_finite() && stats.policy_loss.is_finite());
    // A share of 0.5: some first episodes are driven to the goal, the rest
    // are the untrained policy's, which rarely reaches it.
    let share = EppoConfig {
        scripted_share: 0.5,
        n_envs: 8,
        ..cfg
    };
    let mut learner = Learner::new(share.clone(), EnvName::Point).unwrap();
    let mut venv = training_venv(EnvName::Point, &share);
    learner.collect(&mut venv).unwrap();
    let first_found: Vec<bool> = learner
        .replay
        .trajectories
        .iter()
        .map(|t| t.episode_success[0])
        .collect();
    assert!(
        first_found.contains(&true) && first_found.contains(&false),
        "{first_found:?}"
    );
}

#[test]
fn the_dense_critic_reward_shapes_targets_and_leaves_tokens_sparse() {
    let (mut learner, mut venv) = tiny_learner(0);
    learner.collect(&mut venv).unwrap();
    let trajs: Vec<&Trajectory> = learner.replay.trajectories.iter().collect();
    let sparse_cfg = learner.cfg.clone();
    let dense_cfg = EppoConfig {
        dense_reward_coef: 0.5,
        ..sparse_cfg.clone()
    };
    let batch = |cfg: &EppoConfig| {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        unshaped_batch(&trajs, cfg, &learner.spec, &mut rng)
    };
    let (sparse, dense) = (batch(&sparse_cfg), batch(&dense_cfg));
    assert_eq!(
        to_vec(&sparse.tokens),
        to_vec(&dense.tokens),
        "tokens stay sparse"
    );
    let (rs, rd) = (to_vec(&sparse.rewards), to_vec(&dense.rewards));
    let valid = to_vec(&sparse.valid);
    let l = rs.len() / trajs.len();
    let scale = sparse_cfg.reward_scale as f32;
    let mut shaped = 0;
    for (j, t) in trajs.iter().enumerate() {
        for step in 0..t.len().min(l) {
            let k = j * l + step;
            assert_eq!(valid[k], 1.0);
            let d = |o: &[f32]| GoalRule::distance([o[0], o[1]], t.goal);
            let progress =
                d(&t.obs[step * 2..step * 2 + 2]) - d(&t.next_obs[step * 2..step * 2 + 2]);
            assert!(
                (rd[k] - rs[k] - 0.5 * progress * scale).abs() < 1e-5,
                "step {step}"
            );
            shaped += usize::from(progress != 0.0);
        }
    }
    assert!(shaped > 0, "some step moved relative to the goal");
}

#[test]
fn the_dense_reward_after_the_goal_waits_for_a_success_in_the_context() {
    let (learner, _) = tiny_learner(0);
    // Relabelled at (4, 6): episode 0 reaches it at step 1; steps 2 and 3
    // (episode 1) have that success in their context.
    let mut t = relabel(&two_episode_trajectory(), 2, 1, &GRID_RULE, [4.0, 6.0]);
    t.actions = vec![0.0; t.len() * learner.spec.act_flat()];
    let rewards = |coef: f64, after_goal: bool| {
        let cfg = EppoConfig {
            dense_reward_coef: coef,
            dense_reward_after_goal: after_goal,
            ..learner.cfg.clone()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        to_vec(&unshaped_batch(&[&t], &cfg, &learner.spec, &mut rng).rewards)
    };
    let sparse = rewards(0.0, false);
    let shaping = |r: Vec<f32>| -> Vec<f32> {
        let scale = learner.cfg.reward_scale as f32;
        r.iter()
            .zip(&sparse)
            .take(4)
            .map(|(d, s)| (d - s) / scale)
            .collect()
    };
    let always = shaping(rewards(1.0, false));
    let after_goal = shaping(rewards(1.0, true));
    let progress = |step: usize| {
        let d = |o: &[f32]| GoalRule::distance([o[0], o[1]], [4.0, 6.0]);
        d(&t.obs[step * 2..step * 2 + 2]) - d(&t.next_obs[step * 2..step * 2 + 2])
    };
    for step in 0..4 {
        assert!((always[step] - progress(step)).abs() < 1e-5, "step {step}");
        let expected = if step < 2 { 0.0 } else { progress(step) };
        assert!((after_goal[step] - expected).abs() < 1e-5, "step {step}");
    }
    assert!(always[0] != 0.0 && after_goal[3] != 0.0);
    let mut cfg = learner.cfg.clone();
    cfg.dense_reward_after_goal = true;
    let e = cfg.validate().unwrap_err().to_string();
    assert!(e.contains("dense_reward_coef"), "{e}");
}

#[test]
fn the_goal_enters_the_context_with_its_reward() {
    // One fixed task (the ladder's first rung): collect until an episode
    // ends at the goal, then look at the token after it.
    let mut cfg = tiny();
    cfg.task_pool = 1;
    let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    let goal = sample_task(
        &spawn_config(EnvName::DarkRoom),
        Orientation::Centre,
        pretrain_task_seed(cfg.seed, 0),
    )
    .unwrap()
    .goal;
    let goal_obs = [goal.row as f32, goal.col as f32];
    let (_, mut venv) = tiny_learner(0);
    let mut checked = 0;
    for _ in 0..300 {
        learner.collect(&mut venv).unwrap();
        if learner
            .replay
            .trajectories
            .iter()
            .any(|t| t.terminated.contains(&true))
        {
            break;
        }
    }
    let norm = |x: f32| 2.0 * x / 8.0 - 1.0; // 9x9 grid: [0, 8] -> [-1, 1]
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    for t in &learner.replay.trajectories {
        let batch = unshaped_batch(&[t], &cfg, &learner.spec, &mut rng);
        let tok = to_vec(&batch.tokens);
        let d = learner.spec.token_dim();
        for s in (0..t.len() - 1).filter(|&s| t.terminated[s]) {
            assert_eq!(&t.next_obs[2 * s..2 * s + 2], &goal_obs, "step {s}");
            let next = &tok[(s + 1) * d..(s + 2) * d];
            // The token carrying reward 1: the new episode's start as the
            // observation, the goal as where the last action arrived.
            assert_eq!(next[2..4], [norm(goal_obs[0]), norm(goal_obs[1])]);
            assert_eq!(next[0..2], [0.0, 0.0], "the centre start");
            assert_eq!(next[2 + 2 + 5], 10.0, "reward x reward_scale");
            assert_eq!(next[d - 1], 1.0, "episode start flag");
            checked += 1;
        }
    }
    // A pool of one: every goal reached above was the same task's.
    assert!(checked > 0, "no episode reached the goal in 300 rounds");
}

#[test]
fn exploration_is_bilevel() {
    let mut cfg = tiny();
    cfg.eps_start = 1.0;
    cfg.eps_end = 0.4;
    cfg.eps_last_start = Some(0.6);
    cfg.eps_last_end = Some(0.0);
    cfg.eps_decay_steps = 1000;
    let start = cfg.exploration(0);
    assert_eq!((start.first, start.last), (1.0, 0.6));
    let mid = cfg.exploration(500);
    assert!((mid.first - 0.7).abs() < 1e-12 && (mid.last - 0.3).abs() < 1e-12);
    let end = cfg.exploration(10_000);
    assert!(
        (end.first - 0.4).abs() < 1e-12 && end.last == 0.0,
        "annealed, then held"
    );
    // Inside a trajectory: linear from the first to the last step, scaled.
    assert!((end.at(0, 100, 1.0, false) - 0.4).abs() < 1e-12);
    assert!((end.at(50, 100, 1.0, false) - 0.2).abs() < 1e-12);
    assert!(end.at(100, 100, 1.0, false).abs() < 1e-12);
    assert!((end.at(0, 100, 0.5, false) - 0.2).abs() < 1e-12);
    // Without the last-step values, epsilon is flat inside a trajectory.
    cfg.eps_last_start = None;
    cfg.eps_last_end = None;
    let flat = cfg.exploration(500);
    assert_eq!(flat.first, flat.last);
    // An epsilon outside [0, 1] is refused by name.
    assert!(cfg.validate().is_ok());
    cfg.eps_last_end = Some(1.5);
    assert!(
        cfg.validate()
            .unwrap_err()
            .to_string()
            .contains("eps_last_end")
    );
}

#[test]
fn noise_drops_to_its_ceiling_once_the_goal_is_found() {
    let mut cfg = tiny();
    cfg.eps_start = 0.6;
    cfg.eps_end = 0.6;
    cfg.eps_after_success = Some(0.5);
    let e = cfg.exploration(0);
    assert_eq!(
        e.at(0, 100, 1.0, false),
        0.6,
        "still searching: the schedule"
    );
    assert_eq!(e.at(0, 100, 1.0, true), 0.5, "found: the ceiling");
    assert_eq!(e.at(0, 100, 0.5, true), 0.3, "a ceiling, not a floor");
    cfg.eps_after_success = None;
    assert_eq!(cfg.exploration(0).at(0, 100, 1.0, true), 0.6);
    cfg.eps_after_success = Some(1.5);
    assert!(
        cfg.validate()
            .unwrap_err()
            .to_string()
            .contains("eps_after_success")
    );
}

/// A SafeDarkRoom-like trajectory over cells (row, col): episode 0 walks
/// (4,4) -> (4,5) -> (4,4) -> (3,4); episode 1 from (4,4) -> (4,5) -> (3,5)
/// reaches the goal there, then (4,4) -> (5,4) after it.
fn cell_walk() -> Trajectory {
    let cells: [[f32; 2]; 8] = [
        [4.0, 4.0],
        [4.0, 5.0],
        [4.0, 4.0],
        [4.0, 4.0],
        [4.0, 5.0],
        [4.0, 4.0],
        [4.0, 4.0],
        [4.0, 4.0],
    ];
    let next: [[f32; 2]; 8] = [
        [4.0, 5.0],
        [4.0, 4.0],
        [3.0, 4.0],
        [4.0, 5.0],
        [3.0, 5.0],
        [5.0, 4.0],
        [5.0, 4.0],
        [3.0, 3.0],
    ];
    let n = cells.len();
    Trajectory {
        budget: 1.0,
        goal: [3.0, 5.0],
        obs: cells.concat(),
        next_obs: next.concat(),
        actions: vec![0.0; 5 * n],
        action_idx: vec![0; n],
        rewards: vec![0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        costs: vec![0.0; n],
        ctg: vec![1.0; n],
        start: vec![true, false, false, true, false, true, false, false],
        terminated: vec![false, false, false, false, true, false, false, false],
        truncated: vec![false, false, true, false, false, false, false, true],
        episode: vec![0, 0, 0, 1, 1, 2, 2, 2],
        episode_returns: vec![0.0, 1.0, 0.0],
        episode_costs: vec![0.0; 3],
        episode_success: vec![false, true, false],
    }
}

#[test]
fn the_novelty_bonus_pays_new_cells_until_the_first_success() {
    let t = cell_walk();
    assert_eq!(
        novel_arrivals(&t, 2, 1.0),
        // new (4,5); seen (4,4); new (3,4); seen (4,5); new (3,5), the goal;
        // nothing after the first success, new cells included.
        vec![1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    );
    // Coarser cells (side 2) hold (3,4) with (4,4) and (3,5) with (4,5).
    assert_eq!(
        novel_arrivals(&t, 2, 2.0),
        vec![1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    );
    // Into the critics' rewards only, at the weight given; tokens unchanged.
    let spec = NetSpec {
        obs_dim: 2,
        obs_low: vec![0.0; 2],
        obs_high: vec![8.0; 2],
        n_actions: Some(5),
        act_low: vec![],
        act_high: vec![],
        ..Default::default()
    };
    let cfg = tiny();
    let batch = |novelty: f32| {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let shaping = Shaping {
            novelty,
            over_budget: None,
        };
        make_batch(&[&t], &cfg, &spec, shaping, &mut rng, Device::Cpu)
    };
    let (plain, bonus) = (batch(0.0), batch(0.1));
    assert_eq!(to_vec(&plain.tokens), to_vec(&bonus.tokens));
    let diff: Vec<f32> = to_vec(&bonus.rewards)
        .iter()
        .zip(to_vec(&plain.rewards))
        .map(|(b, p)| ((b - p) / cfg.reward_scale as f32 * 100.0).round() / 100.0)
        .collect();
    assert_eq!(diff, vec![0.1, 0.0, 0.1, 0.0, 0.1, 0.0, 0.0, 0.0]);
    // Annealed linearly to zero, then held there.
    let mut cfg = tiny();
    cfg.novelty_bonus = 0.2;
    assert_eq!(cfg.novelty_weight(500), 0.2, "no anneal: constant");
    cfg.novelty_anneal_updates = 1000;
    assert!((cfg.novelty_weight(500) - 0.1).abs() < 1e-12);
    assert_eq!(cfg.novelty_weight(1000), 0.0);
    assert_eq!(cfg.novelty_weight(5000), 0.0);
}

/// cell_walk with costs: episode 0 pays 1 at step 1 (budget 1: not over)
/// and 1 at step 2 (over); episode 1 goes over at step 3, then reaches the
/// goal at step 4; episode 2 never pays.
fn overspent_walk() -> (Trajectory, NetSpec) {
    let mut t = cell_walk();
    t.costs = vec![0.0, 1.0, 1.0, 2.0, 0.0, 0.0, 0.0, 0.0];
    t.ctg = vec![1.0, 1.0, 0.0, 1.0, -1.0, 1.0, 1.0, 1.0];
    t.episode_costs = vec![2.0, 2.0, 0.0];
    let spec = NetSpec {
        obs_dim: 2,
        obs_low: vec![0.0; 2],
        obs_high: vec![8.0; 2],
        n_actions: Some(5),
        ..Default::default()
    };
    (t, spec)
}

/// A config whose over-budget price (`form`, 2 per unit of cost) starts at
/// update 100, the multiplier held at 0; checks nothing is priced before.
fn priced_from_update_100(form: PenaltyForm) -> EppoConfig {
    let mut cfg = tiny();
    cfg.penalty = form;
    cfg.lambda_lr = 0.0;
    cfg.lambda_init = 0.0;
    cfg.lambda_warmup_updates = 100;
    cfg.over_budget_cost_price = 2.0;
    let count = ConstraintStart::default();
    assert_eq!(count.started_at(99, cfg.lambda_warmup_updates, None), None);
    assert_eq!(
        count.started_at(100, cfg.lambda_warmup_updates, None),
        Some(100)
    );
    assert_eq!(
        cfg.shaping(99, None).over_budget,
        None,
        "not before the constraint"
    );
    cfg
}

#[test]
fn a_measured_constraint_start_waits_for_the_warmup_and_the_revisit_rate() {
    let (warmup, threshold, rounds) = (100, 0.8, 3);
    let mut start = ConstraintStart::default();
    let observe = |start: &mut ConstraintStart, rate: f64, updates: u64| {
        start.observe(rate, updates, warmup, threshold, rounds);
        start.started_at(updates, warmup, Some(threshold)).is_some()
    };
    // Revisiting, but inside the warm-up: off, though the count alone would not say so.
    for updates in [50, 60, 70] {
        assert!(!observe(&mut start, 0.9, updates));
    }
    assert!(start.started_at(100, warmup, None).is_some());
    // A round with nothing to revisit (NaN) does not count, either way.
    let mut low = ConstraintStart::default();
    for rate in [0.9, 0.9, 0.5, f64::NAN, 0.9] {
        assert!(!observe(&mut low, rate, 200), "{rate}: mean under 0.8");
    }
    assert_eq!(low.recent_revisits, vec![0.9, 0.5, 0.9]);
    assert!(
        !observe(&mut low, 0.9, 205),
        "0.5, 0.9, 0.9: mean under 0.8"
    );
    assert!(observe(&mut low, 0.9, 210), "0.9, 0.9, 0.9");
    assert_eq!(low.since, Some(210));
    // Past the warm-up the full window starts it, and it stays on.
    assert!(observe(&mut start, 0.9, 100));
    assert_eq!(start.since, Some(100));
    assert!(observe(&mut start, 0.0, 150), "once on, it stays on");
    assert_eq!(start.since, Some(100));
}

#[test]
fn the_multiplier_waits_for_the_measured_start_and_the_checkpoint_keeps_it() {
    let mut cfg = tiny();
    cfg.lambda_init = 0.5;
    cfg.lambda_lr = 0.1;
    cfg.lambda_max = 10.0;
    cfg.lambda_warmup_updates = 0;
    cfg.constraint_after_revisit = Some(0.5);
    cfg.constraint_revisit_rounds = 1;
    cfg.validate().unwrap();
    let (_, mut venv) = tiny_learner(0);
    let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    learner.collect(&mut venv).unwrap();
    learner.observe_round(&RoundStats {
        revisit_rate: 0.4,
        ..Default::default()
    });
    learner.update().unwrap();
    assert!(!learner.constrained());
    assert_eq!(learner.multiplier.lambda, 0.5, "held before the start");
    learner.observe_round(&RoundStats {
        revisit_rate: 0.6,
        ..Default::default()
    });
    assert!(learner.constrained());
    assert_eq!(learner.constraint_start.since, Some(1));
    learner.update().unwrap();
    assert_ne!(learner.multiplier.lambda, 0.5, "moves once on");
    let out = std::env::temp_dir().join(format!("icrl-eppo-start-{}", std::process::id()));
    let run = crate::checkpoint::RunDir::create(&out, "darkroom", "eppo", cfg.seed).unwrap();
    let saved = learner.save_checkpoint(&run).unwrap();
    let resumed = Learner::resume(cfg, EnvName::DarkRoom, &saved).unwrap();
    assert_eq!(resumed.constraint_start, learner.constraint_start);
    assert!(resumed.constrained());
    std::fs::remove_dir_all(&out).unwrap();
    for (key, value, says) in [
        (
            "constraint_after_revisit",
            "1.5",
            "constraint_after_revisit = 1.5",
        ),
        (
            "constraint_revisit_rounds",
            "0",
            "constraint_revisit_rounds = 0",
        ),
    ] {
        let mut table = crate::presets::preset_table("eppo", "darkroom", "quick").unwrap();
        crate::presets::apply_overrides(&mut table, &[format!("{key}={value}")]).unwrap();
        let cfg: EppoConfig = crate::presets::resolve("bad", table).unwrap();
        let err = cfg.validate().unwrap_err().to_string();
        assert!(err.contains(says), "{err}");
    }
}

/// A checkpoint holds the replay, so the update after a resume is the one
/// the uninterrupted run makes (discrete and continuous actions); one
/// copied without it is refused as incomplete.
#[test]
fn a_resumed_learner_samples_the_saved_replay_and_updates_as_the_uninterrupted_one() {
    for (env, cfg) in [(EnvName::DarkRoom, tiny()), (EnvName::Point, tiny_point())] {
        let mut learner = Learner::new(cfg.clone(), env).unwrap();
        let mut venv = training_venv(env, &cfg);
        learner.collect(&mut venv).unwrap();
        learner.collect(&mut venv).unwrap();
        learner.update().unwrap();
        let out = std::env::temp_dir().join(format!(
            "icrl-eppo-replay-{}-{}",
            env.as_str(),
            std::process::id()
        ));
        let run = crate::checkpoint::RunDir::create(&out, env.as_str(), "eppo", cfg.seed).unwrap();
        let saved = learner.save_checkpoint(&run).unwrap();
        let mut resumed = Learner::resume(cfg.clone(), env, &saved).unwrap();
        assert_eq!(resumed.replay.len(), 2 * cfg.n_envs, "{env:?}");
        assert_eq!(resumed.replay.steps(), learner.replay.steps());
        assert!(
            resumed
                .replay
                .trajectories
                .iter()
                .eq(learner.replay.trajectories.iter()),
            "{env:?}: every field of every trajectory"
        );
        let (next, after_resume) = (learner.update().unwrap(), resumed.update().unwrap());
        for (name, a, b) in [
            ("value", next.value_loss, after_resume.value_loss),
            (
                "cost value",
                next.cost_value_loss,
                after_resume.cost_value_loss,
            ),
            ("policy", next.policy_loss, after_resume.policy_loss),
            ("q", next.q_mean, after_resume.q_mean),
        ] {
            assert_eq!(a, b, "{env:?}: the {name} after a resume");
        }
        std::fs::remove_file(saved.join(super::checkpoint::REPLAY_FILE)).unwrap();
        let bare = Learner::resume(cfg, env, &saved);
        std::fs::remove_dir_all(&out).unwrap();
        // The manifest lists the replay's file, so a checkpoint copied
        // without it is refused as incomplete rather than resumed quietly.
        let err = bare.err().map(|e| e.to_string()).unwrap_or_default();
        assert!(err.contains("replay.safetensors"), "{env:?}: {err}");
    }
}

#[test]
fn saute_replaces_the_reward_once_the_episode_has_spent_its_budget() {
    let (t, spec) = overspent_walk();
    let mut cfg = priced_from_update_100(PenaltyForm::Saute);
    cfg.saute_unsafe_reward = -0.25;
    cfg.validate().unwrap();
    assert_eq!(
        cfg.shaping(100, Some(100)).over_budget,
        Some(OverBudget {
            replaced_reward: Some(-0.25),
            cost_price: 2.0,
            pays_novelty: false
        })
    );
    let over_budget = |reward: f32, cost_price: f32| Shaping {
        novelty: 0.0,
        over_budget: Some(OverBudget {
            replaced_reward: Some(reward),
            cost_price,
            pays_novelty: false,
        }),
    };
    let batch = |shaping: Shaping| {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        make_batch(&[&t], &cfg, &spec, shaping, &mut rng, Device::Cpu)
    };
    let (plain, saute) = (batch(Shaping::default()), batch(over_budget(-0.25, 0.0)));
    assert_eq!(
        to_vec(&plain.tokens),
        to_vec(&saute.tokens),
        "tokens as collected"
    );
    let scale = cfg.reward_scale as f32;
    let unscaled =
        |b: &Batch| -> Vec<f32> { to_vec(&b.rewards).iter().map(|r| r / scale).collect() };
    assert_eq!(
        unscaled(&plain),
        vec![0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    );
    assert_eq!(
        unscaled(&saute),
        // at the budget is within it; past it, every step of the episode,
        // the goal's too; the next episode starts clean.
        vec![0.0, 0.0, -0.25, -0.25, -0.25, 0.0, 0.0, 0.0]
    );
    // With a price on cost, each unit paid past the budget costs it too.
    assert_eq!(
        unscaled(&batch(over_budget(-0.25, 2.0))),
        vec![0.0, 0.0, -2.25, -4.25, -0.25, 0.0, 0.0, 0.0]
    );
    // Under another penalty form the same settings shape nothing.
    cfg.penalty = PenaltyForm::Hindsight;
    assert_eq!(cfg.shaping(100, Some(100)).over_budget, None);
    // The actor pays no lambda term: the price is in the reward.
    let qc = Tensor::from_slice(&[0.5f32, 2.0]).view([1, 2]);
    let ones = qc.ones_like();
    assert_eq!(
        to_vec(&penalised_cost(
            &qc,
            &ones,
            &(ones.zeros_like() - 5.0),
            PenaltyForm::Saute
        )),
        vec![0.0, 0.0]
    );
}

#[test]
fn saute_refuses_a_multiplier_that_moves() {
    let mut cfg = tiny();
    cfg.penalty = PenaltyForm::Saute;
    cfg.lambda_init = 0.0;
    cfg.lambda_lr = 0.001;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(err.contains("lambda_lr = 0"), "{err}");
    cfg.lambda_lr = 0.0;
    cfg.saute_unsafe_reward = 0.5;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(err.contains("saute_unsafe_reward"), "{err}");
    cfg.saute_unsafe_reward = -0.1;
    cfg.over_budget_cost_price = -1.0;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(err.contains("over_budget_cost_price"), "{err}");
    cfg.over_budget_cost_price = 1.0;
    cfg.validate().unwrap();
}

#[test]
fn excess_price_charges_each_unit_past_the_budget_and_keeps_the_goal() {
    let (t, spec) = overspent_walk();
    let mut cfg = priced_from_update_100(PenaltyForm::Excess);
    cfg.validate().unwrap();
    let shaping = cfg.shaping(100, Some(100));
    assert_eq!(
        shaping.over_budget,
        Some(OverBudget {
            replaced_reward: None,
            cost_price: 2.0,
            pays_novelty: true
        })
    );
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let batch = make_batch(&[&t], &cfg, &spec, shaping, &mut rng, Device::Cpu);
    let scale = cfg.reward_scale as f32;
    let rewards: Vec<f32> = to_vec(&batch.rewards).iter().map(|r| r / scale).collect();
    assert_eq!(
        rewards,
        // within the budget nothing is charged; past it each unit costs the
        // price and the goal still pays; the next episode starts clean.
        vec![0.0, 0.0, -2.0, -4.0, 1.0, 0.0, 0.0, 0.0]
    );
    assert_eq!(
        to_vec(&batch.costs),
        t.costs,
        "the cost critic's targets are the costs as paid"
    );
    // No actor penalty: the price is in the reward.
    let qc = Tensor::from_slice(&[0.5f32, 2.0]).view([1, 2]);
    let ones = qc.ones_like();
    assert_eq!(
        to_vec(&penalised_cost(
            &qc,
            &ones,
            &ones.zeros_like(),
            PenaltyForm::Excess
        )),
        vec![0.0, 0.0]
    );
    // Refused without a price, or with a multiplier that moves.
    cfg.over_budget_cost_price = 0.0;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(err.contains("over_budget_cost_price > 0"), "{err}");
    cfg.over_budget_cost_price = 1.0;
    cfg.lambda_lr = 0.01;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(
        err.contains("penalty = \"excess\"") && err.contains("lambda_lr = 0"),
        "{err}"
    );
}

#[test]
fn the_price_schedule_counts_updates_from_the_constraints_start() {
    let (t, spec) = overspent_walk();
    let mut cfg = priced_from_update_100(PenaltyForm::Excess);
    let mut table = crate::presets::preset_table("eppo", "darkroom", "quick").unwrap();
    let schedule =
        "over_budget_price_schedule=[{ after = 50, price = 3.0 }, { after = 80, price = 5 }]";
    crate::presets::apply_overrides(&mut table, &[schedule.to_string()]).unwrap();
    let parsed: EppoConfig = crate::presets::resolve("schedule", table).unwrap();
    cfg.over_budget_price_schedule = parsed.over_budget_price_schedule;
    assert_eq!(
        cfg.over_budget_price_schedule,
        vec![
            PriceChange {
                after: 50,
                price: 3.0
            },
            PriceChange {
                after: 80,
                price: 5.0
            }
        ]
    );
    cfg.validate().unwrap();
    let price_at = |updates: u64, since: Option<u64>| {
        cfg.shaping(updates, since)
            .over_budget
            .map(|o| o.cost_price)
    };
    assert_eq!(price_at(99, None), None, "nothing before the start");
    for (updates, since, price) in [
        (100, 100, 2.0),
        (149, 100, 2.0),
        (150, 100, 3.0),
        (179, 100, 3.0),
        (180, 100, 5.0),
        (5000, 100, 5.0),
        // From a measured start, not from update 0 or the warm-up.
        (190, 140, 3.0),
        (180, 131, 2.0),
    ] {
        assert_eq!(
            price_at(updates, Some(since)),
            Some(price),
            "{updates} since {since}"
        );
    }
    // The critics' rewards carry it: the walk's 1 and 2 units past the budget.
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let batch = make_batch(
        &[&t],
        &cfg,
        &spec,
        cfg.shaping(180, Some(100)),
        &mut rng,
        Device::Cpu,
    );
    let scale = cfg.reward_scale as f32;
    let rewards: Vec<f32> = to_vec(&batch.rewards).iter().map(|r| r / scale).collect();
    assert_eq!(rewards, vec![0.0, 0.0, -5.0, -10.0, 1.0, 0.0, 0.0, 0.0]);
    // The learner reads it from its measured start and reports it.
    cfg.constraint_after_revisit = Some(0.5);
    cfg.constraint_revisit_rounds = 1;
    cfg.lambda_warmup_updates = 0;
    let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    assert_eq!(
        learner.over_budget_price(),
        0.0,
        "not charged before the start"
    );
    learner.updates = 10;
    learner.observe_round(&RoundStats {
        revisit_rate: 0.9,
        ..Default::default()
    });
    assert_eq!(learner.constraint_since(), Some(10));
    assert_eq!(learner.over_budget_price(), 2.0);
    learner.updates = 60;
    assert_eq!(learner.over_budget_price(), 3.0);
    learner.updates = 90;
    assert_eq!(learner.over_budget_price(), 5.0);
    // Refused where it would charge nothing or be read out of order.
    let refused = |change: &dyn Fn(&mut EppoConfig), says: &str| {
        let mut bad = cfg.clone();
        change(&mut bad);
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains(says), "{err}");
    };
    refused(
        &|c| c.over_budget_price_schedule.reverse(),
        "must rise from one change to the next",
    );
    refused(
        &|c| c.over_budget_price_schedule[1].price = f64::NAN,
        "price = NaN after 80 updates",
    );
    refused(
        &|c| {
            c.penalty = PenaltyForm::Hinge;
            c.over_budget_cost_price = 0.0;
        },
        "over_budget_price_schedule changes the price",
    );
    refused(
        &|c| {
            c.over_budget_price_ramp = true;
            c.over_budget_price_schedule.clear();
        },
        "over_budget_price_ramp = true moves the price",
    );
}

#[test]
fn the_price_ramp_moves_linearly_from_the_start_price_through_each_change() {
    let mut cfg = priced_from_update_100(PenaltyForm::Excess);
    cfg.over_budget_price_schedule = vec![
        PriceChange {
            after: 50,
            price: 3.0,
        },
        PriceChange {
            after: 80,
            price: 6.0,
        },
    ];
    cfg.over_budget_price_ramp = true;
    cfg.validate().unwrap();
    let price_at = |updates: u64| {
        cfg.shaping(updates, Some(100))
            .over_budget
            .map(|o| o.cost_price)
    };
    // 2.0 at the start, 3.0 at 50 updates past it, 6.0 at 80 and after.
    for (updates, price) in [
        (100, 2.0),
        (125, 2.5),
        (149, 2.98),
        (150, 3.0),
        (160, 4.0),
        (170, 5.0),
        (180, 6.0),
        (5000, 6.0),
    ] {
        let got = price_at(updates).unwrap();
        assert!((got - price).abs() < 1e-6, "{updates}: {got} != {price}");
    }
    // A change at the start itself is a step, as without the ramp.
    cfg.over_budget_price_schedule[0].after = 0;
    assert_eq!(cfg.over_budget_price(0), 3.0);
    assert!((cfg.over_budget_price(40) - 4.5).abs() < 1e-9);
    // Without the ramp the same schedule steps.
    cfg.over_budget_price_ramp = false;
    assert_eq!(cfg.over_budget_price(79), 3.0);
}

#[test]
fn novelty_within_budget_withholds_the_bonus_only_past_the_budget() {
    let (t, spec) = overspent_walk();
    let rewards_at = |updates: u64, within: bool| {
        let mut cfg = priced_from_update_100(PenaltyForm::Excess);
        cfg.novelty_bonus = 0.1;
        if within {
            cfg.novelty_budget = NoveltyBudget::WithinBudget;
        }
        cfg.validate().unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let shaping = cfg.shaping(
            updates,
            (updates >= cfg.lambda_warmup_updates).then_some(100),
        );
        let batch = make_batch(&[&t], &cfg, &spec, shaping, &mut rng, Device::Cpu);
        let scale = cfg.reward_scale as f32;
        to_vec(&batch.rewards)
            .iter()
            .map(|r| (r / scale * 100.0).round() / 100.0)
            .collect::<Vec<f32>>()
    };
    // New cells at steps 0, 2 and 4; the budget is spent at steps 2-4.
    assert_eq!(
        rewards_at(100, false),
        vec![0.1, 0.0, -1.9, -4.0, 1.1, 0.0, 0.0, 0.0]
    );
    assert_eq!(
        rewards_at(100, true),
        vec![0.1, 0.0, -2.0, -4.0, 1.0, 0.0, 0.0, 0.0],
        "the bonus is paid within the budget and withheld past it"
    );
    assert_eq!(
        rewards_at(99, true),
        vec![0.1, 0.0, 0.1, 0.0, 1.1, 0.0, 0.0, 0.0],
        "before the constraint nothing is priced and the bonus is paid"
    );
    // Refused where it would do nothing.
    let mut cfg = priced_from_update_100(PenaltyForm::Excess);
    cfg.novelty_budget = NoveltyBudget::WithinBudget;
    cfg.novelty_bonus = 0.0;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(err.contains("novelty_budget"), "{err}");
    cfg.novelty_bonus = 0.1;
    cfg.penalty = PenaltyForm::Hindsight;
    cfg.over_budget_cost_price = 0.0;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(err.contains("penalty = \"excess\""), "{err}");
}

#[test]
fn novelty_by_remaining_share_scales_the_bonus_by_the_budget_left() {
    let (mut t, spec) = overspent_walk();
    // Budget 2: 2 left at steps 0-1, 1 at step 2 (after a cost of 1), a new
    // episode at step 3 spends all of it, so none is left at step 4.
    t.budget = 2.0;
    t.ctg = vec![2.0, 2.0, 1.0, 2.0, 0.0, 2.0, 2.0, 2.0];
    let rewards_at = |t: &Trajectory, updates: u64, form: NoveltyBudget| {
        let mut cfg = priced_from_update_100(PenaltyForm::Excess);
        cfg.novelty_bonus = 0.1;
        cfg.novelty_budget = form;
        cfg.validate().unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let batch = make_batch(
            &[t],
            &cfg,
            &spec,
            cfg.shaping(
                updates,
                (updates >= cfg.lambda_warmup_updates).then_some(100),
            ),
            &mut rng,
            Device::Cpu,
        );
        let scale = cfg.reward_scale as f32;
        to_vec(&batch.rewards)
            .iter()
            .map(|r| (r / scale * 1000.0).round() / 1000.0)
            .collect::<Vec<f32>>()
    };
    // New cells at steps 0, 2 and 4, with all, half and none of the budget left.
    for updates in [99, 100] {
        assert_eq!(
            rewards_at(&t, updates, NoveltyBudget::RemainingShare),
            vec![0.1, 0.0, 0.05, 0.0, 1.0, 0.0, 0.0, 0.0],
            "update {updates}"
        );
    }
    assert_eq!(
        rewards_at(&t, 100, NoveltyBudget::Always),
        vec![0.1, 0.0, 0.1, 0.0, 1.1, 0.0, 0.0, 0.0],
        "ungated, the full bonus at every new cell"
    );
    // A larger share than the whole budget (none here) or an overspent one
    // is clamped: a budget of 1 leaves a negative CTG at step 4.
    t.budget = 1.0;
    t.ctg = vec![1.0, 1.0, 0.0, 1.0, -1.0, 1.0, 1.0, 1.0];
    assert_eq!(
        rewards_at(&t, 99, NoveltyBudget::RemainingShare),
        vec![0.1, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    );
    let mut cfg = priced_from_update_100(PenaltyForm::Hindsight);
    cfg.novelty_budget = NoveltyBudget::RemainingShare;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(err.contains("novelty_bonus > 0"), "{err}");
}

#[test]
fn an_older_novelty_within_budget_flag_reads_as_the_gate() {
    let text = toml::to_string(&tiny()).unwrap();
    assert!(text.contains("novelty_budget = \"always\""), "{text}");
    let read = |line: &str| {
        toml::from_str::<EppoConfig>(&text.replace("novelty_budget = \"always\"", line))
            .unwrap()
            .novelty_budget
    };
    assert_eq!(
        read("novelty_within_budget = true"),
        NoveltyBudget::WithinBudget
    );
    assert_eq!(read("novelty_within_budget = false"), NoveltyBudget::Always);
    assert_eq!(
        read("novelty_budget = \"remaining_share\""),
        NoveltyBudget::RemainingShare
    );
}

#[test]
fn search_rates_count_discovery_and_revisits() {
    let a = [false, true, true, false];
    let b = [false, false, false, false];
    let c = [true, true, false, true];
    let (disc, rev, found) = search_rates([&a[..], &b[..], &c[..]].into_iter());
    // After episode 1: a discovers at 2 (1 of a's 1 undiscovered tries),
    // b never (3 tries); a revisits 1 of 2, c 2 of 3.
    assert!((disc - 1.0 / 4.0).abs() < 1e-12, "{disc}");
    assert!((rev - 3.0 / 5.0).abs() < 1e-12, "{rev}");
    assert!((found - 2.0 / 3.0).abs() < 1e-12);
    assert!(search_rates([&b[..1]].into_iter()).0.is_nan());
}

#[test]
fn critic_losses_fall_on_a_fixed_batch() {
    let (mut learner, mut venv) = tiny_learner(1);
    learner.collect(&mut venv).unwrap();
    let batch = replay_batch(&learner);
    let mut first = None;
    let mut last = (0.0, 0.0);
    for _ in 0..300 {
        let (lv, lc, ..) = losses(
            &learner.net,
            &learner.target,
            &batch,
            0.0,
            learner.cfg.entropy_coef,
            &learner.cfg,
        )
        .unwrap();
        let now = (lv.double_value(&[]), lc.double_value(&[]));
        first.get_or_insert(now);
        last = now;
        learner.opt.backward_step(&(lv + lc));
    }
    let first = first.unwrap();
    assert!(last.0 < 0.3 * first.0, "value loss {first:?} -> {last:?}");
    assert!(
        last.1 < 0.3 * first.1 || last.1 < 1e-3,
        "cost value loss {first:?} -> {last:?}"
    );
}

/// The goal-recall loss is the squared recall error on the steps after the
/// window's first success only, and it teaches the head (and the encoder)
/// to read the goal off the context; without its weight there is no head.
#[test]
fn goal_recall_counts_only_steps_after_a_success_and_falls() {
    assert!(tiny_learner(0).0.net.goal_recall.is_none());
    let cfg = EppoConfig {
        goal_recall_coef: 1.0,
        ..tiny()
    };
    let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    let mut t = two_episode_trajectory();
    t.goal = [5.0, 5.0];
    t.terminated[1] = true; // found at step 1: known from step 2 on
    t.actions = (0..5)
        .flat_map(|s| (0..5).map(move |a| f32::from(u8::from(a == s))))
        .collect(); // one-hot, SafeDarkRoom's 5 actions
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut batch = unshaped_batch(&[&t], &cfg, &learner.spec, &mut rng);
    assert_eq!(to_vec(&batch.goal_known), [0.0, 0.0, 1.0, 1.0, 1.0]);
    assert_eq!(to_vec(&batch.goal), [5.0, 5.0]);
    let recall = |learner: &Learner, batch: &Batch| {
        let h = learner.net.encode(&batch.tokens, false).unwrap();
        let head = learner.net.goal_recall.as_ref().unwrap();
        let per_step = to_vec(
            &(head.forward(&h) - batch.goal.unsqueeze(1))
                .square()
                .sum_dim_intlist(-1, false, Kind::Float),
        );
        (goal_recall_loss(head, &h, batch), per_step)
    };
    let (loss, per_step) = recall(&learner, &batch);
    let known_mean = per_step[2..].iter().sum::<f32>() / 3.0;
    assert!((loss.double_value(&[]) as f32 - known_mean).abs() < 1e-4);
    assert!(
        per_step[..2].iter().all(|&e| e > 0.0),
        "the unknown steps would count"
    );
    let first = loss.double_value(&[]);
    for _ in 0..200 {
        learner.opt.backward_step(&recall(&learner, &batch).0);
    }
    let last = recall(&learner, &batch).0.double_value(&[]);
    assert!(last < 0.1 * first, "recall loss {first} -> {last}");
    batch.goal_known = batch.goal_known.zeros_like();
    assert_eq!(recall(&learner, &batch).0.double_value(&[]), 0.0);
}

#[test]
fn the_pid_multiplier_is_eq_7_without_its_p_and_d_terms_and_damps_with_them() {
    let integrator = Gains {
        ki: 0.1,
        kp: 0.0,
        kd: 0.0,
        smoothing: 0.9,
        max: 1.5,
    };
    let batches: Vec<Vec<f32>> = (0..60)
        .map(|i| {
            if i < 30 {
                vec![3.0, -1.0]
            } else {
                vec![-2.0, -0.5]
            }
        })
        .collect();
    let (mut m, mut lambda) = (Multiplier::new(0.2), 0.2);
    for b in &batches {
        m.update(b, &integrator);
        lambda = lambda_update(lambda, b, 0.1, 1.5);
        assert_eq!(m.lambda, lambda, "Eq. (7) exactly");
    }
    // With P and D: lambda answers a violation at once, above the integral,
    // and falls below it as soon as the cost is under budget.
    let pid = Gains {
        kp: 0.5,
        kd: 1.0,
        ..integrator
    };
    let mut m = Multiplier::new(0.0);
    m.update(&[1.0], &pid);
    assert!(m.lambda > m.integral, "{m:?}");
    assert!((m.integral - 0.1).abs() < 1e-12);
    // kp e + kd rise, e = 0.1 after one step from 0.
    assert!(
        (m.lambda - (0.1 + 0.5 * 0.1 + 1.0 * 0.1)).abs() < 1e-9,
        "{m:?}"
    );
    for _ in 0..20 {
        m.update(&[1.0], &pid);
    }
    assert!(m.lambda <= 1.5, "capped: {m:?}");
    let before = m;
    // The smoothed violation turns negative after three batches under budget.
    for _ in 0..3 {
        m.update(&[-3.0], &pid);
    }
    assert!(m.smoothed < 0.0, "{m:?}");
    assert!(m.lambda < m.integral, "damped below the integral: {m:?}");
    assert!(m.integral < before.integral);
    m.update(&[], &pid);
    assert!(m.lambda >= 0.0);
}

#[test]
fn lambda_rises_falls_and_respects_the_cap() {
    let mut lambda = 0.0;
    let mut seen = vec![];
    for _ in 0..50 {
        lambda = lambda_update(lambda, &[3.0, -1.0, 4.0], 0.1, 1.5);
        seen.push(lambda);
    }
    assert!(
        seen.windows(2).take(5).all(|w| w[1] > w[0]),
        "rises while costs exceed the budget"
    );
    assert_eq!(lambda, 1.5, "capped");
    assert!(seen.iter().all(|&l| l <= 1.5));
    for _ in 0..50 {
        lambda = lambda_update(lambda, &[-2.0, -0.5], 0.1, 1.5);
    }
    assert_eq!(
        lambda, 0.0,
        "falls back to 0 once every episode is within budget"
    );
    // Eq. (7) takes the worst episode of each trajectory, then the mean.
    let t = Trajectory {
        budget: 2.0,
        episode_costs: vec![1.0, 5.0, 0.0],
        ..Default::default()
    };
    assert_eq!(t.max_violation(), 3.0);
}

/// SAC's temperature: the entropy weight rises while the policy's entropy is
/// below its target and falls while above, stays fixed without a target, is
/// logged, and a resumed run goes on from the checkpoint's weight.
#[test]
fn the_entropy_weight_tracks_its_target() {
    assert!(tuned_entropy_coef(0.1, -3.0, -2.0, 0.01) > 0.1);
    assert!(tuned_entropy_coef(0.1, -1.0, -2.0, 0.01) < 0.1);
    assert!((tuned_entropy_coef(0.1, -2.0, -2.0, 0.01) - 0.1).abs() < 1e-12);
    let start = tiny().entropy_coef;
    // Five discrete actions hold at most ln 5 = 1.61 nats and at least 0.
    let after_updates = |target: Option<f64>| {
        let (mut learner, mut venv) = tiny_learner(3);
        learner.cfg.target_entropy = target;
        learner.cfg.entropy_coef_lr = 0.1;
        learner.collect(&mut venv).unwrap();
        for _ in 0..3 {
            learner.update().unwrap();
        }
        learner.entropy_coef
    };
    assert!(
        after_updates(Some(5.0)) > start * 1.2,
        "below target: rises"
    );
    assert!(
        after_updates(Some(-1.0)) < start / 1.2,
        "above target: falls"
    );
    assert_eq!(after_updates(None), start, "no target: fixed");

    let out = std::env::temp_dir().join(format!("icrl-eppo-alpha-{}", std::process::id()));
    let mut cfg = tiny();
    cfg.target_entropy = Some(5.0);
    cfg.entropy_coef_lr = 0.1;
    let report = train(&PretrainOptions {
        env: EnvName::DarkRoom,
        cfg: cfg.clone(),
        out: out.clone(),
        resume: None,
        progress: false,
    })
    .unwrap();
    let lines = std::fs::read_to_string(report.run_dir.join("metrics.jsonl")).unwrap();
    let last: serde_json::Value = serde_json::from_str(lines.lines().last().unwrap()).unwrap();
    let logged = last["entropy_coef"].as_f64().unwrap();
    assert!(logged > start, "{logged}");
    let resumed = Learner::resume(cfg, EnvName::DarkRoom, &report.last_checkpoint).unwrap();
    assert!((resumed.entropy_coef - logged).abs() < 1e-12);
    std::fs::remove_dir_all(&out).unwrap();
}

/// The late-rate signal counts only episodes k > K/2 and subtracts its
/// target, so blind early episodes cannot hold lambda up, and a trajectory
/// whose later episodes keep the budget pulls lambda down.
#[test]
fn late_rate_signal_ignores_the_blind_first_half() {
    let t = Trajectory {
        budget: 2.0,
        episode_costs: vec![9.0, 9.0, 0.0, 3.0],
        ..Default::default()
    };
    assert_eq!(t.late_over_budget_rate(), 0.5, "episode 4 of 3..4 over");
    assert_eq!(t.violation(ViolationSignal::WorstExcess, 0.05), 7.0);
    assert!((t.violation(ViolationSignal::LateRate, 0.05) - 0.45).abs() < 1e-6);
    let kept = Trajectory {
        budget: 2.0,
        episode_costs: vec![9.0, 9.0, 9.0, 2.0, 1.0, 0.0],
        ..Default::default()
    };
    assert!((kept.violation(ViolationSignal::LateRate, 0.05) + 0.05).abs() < 1e-6);
    let mut m = Multiplier::new(0.5);
    let gains = Gains {
        ki: 0.1,
        kp: 0.0,
        kd: 0.0,
        smoothing: 0.9,
        max: 1.0,
    };
    m.update(&[kept.violation(ViolationSignal::LateRate, 0.05)], &gains);
    assert!(m.lambda < 0.5, "falls while later episodes keep the budget");
    assert!(kept.max_violation() > 0.0, "where Eq. (7) would still rise");
}

/// A batch of `trajs` whose critics see the collected rewards only.
fn unshaped_batch(
    trajs: &[&Trajectory],
    cfg: &EppoConfig,
    spec: &NetSpec,
    rng: &mut ChaCha8Rng,
) -> Batch {
    make_batch(trajs, cfg, spec, Shaping::default(), rng, Device::Cpu)
}

/// One batch of every trajectory in `learner`'s replay (windows drawn with
/// seed 0, no novelty bonus).
fn replay_batch(learner: &Learner) -> Batch {
    let trajs: Vec<&Trajectory> = learner.replay.trajectories.iter().collect();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    unshaped_batch(&trajs, &learner.cfg, &learner.spec, &mut rng)
}

/// A batch collected by a tiny SafeDarkRoom learner whose actor pays the
/// cost penalty in `form`.
fn penalty_probe(form: PenaltyForm) -> (Learner, Batch) {
    let (mut learner, mut venv) = tiny_learner(2);
    learner.cfg.penalty = form;
    learner.collect(&mut venv).unwrap();
    let batch = replay_batch(&learner);
    (learner, batch)
}

/// Lp on `batch` with multiplier `lambda`, the same libtorch draws each call.
fn policy_loss_at(learner: &Learner, batch: &Batch, lambda: f64) -> f64 {
    let (_, _, lp, ..) = crate::torch_rng::seeded(0, || {
        losses(
            &learner.net,
            &learner.target,
            batch,
            lambda,
            learner.cfg.entropy_coef,
            &learner.cfg,
        )
    })
    .unwrap();
    lp.double_value(&[])
}

#[test]
fn violation_flag_gates_the_cost_penalty() {
    let (learner, mut batch) = penalty_probe(PenaltyForm::Hindsight);
    let policy_loss = |batch: &Batch, lambda: f64| policy_loss_at(&learner, batch, lambda);
    batch.violated = batch.valid.zeros_like();
    let (clean_0, clean_5) = (policy_loss(&batch, 0.0), policy_loss(&batch, 5.0));
    assert!(
        (clean_0 - clean_5).abs() < 1e-4,
        "no violation: lambda has no effect"
    );
    batch.violated = batch.valid.ones_like();
    let (viol_0, viol_5) = (policy_loss(&batch, 0.0), policy_loss(&batch, 5.0));
    assert!((viol_0 - clean_0).abs() < 1e-4);
    assert!(
        (viol_5 - viol_0).abs() > 1e-4,
        "violated episodes pay lambda * Qc"
    );
}

#[test]
fn the_hinge_charges_predicted_cost_past_the_remaining_budget_only() {
    let row = |v: &[f32]| Tensor::from_slice(v).view([1, v.len() as i64]);
    let qc = row(&[0.5, 2.0, 3.0, 1.0]);
    let ctg = row(&[1.0, 1.0, 1.0, 0.0]);
    let violated = row(&[1.0, 0.0, 0.0, 1.0]);
    assert_eq!(
        to_vec(&penalised_cost(&qc, &violated, &ctg, PenaltyForm::Hinge)),
        vec![0.0, 1.0, 2.0, 1.0],
        "zero within the budget, growing past it, blind to the flag"
    );
    assert_eq!(
        to_vec(&penalised_cost(
            &qc,
            &violated,
            &ctg,
            PenaltyForm::Hindsight
        )),
        vec![0.5, 0.0, 0.0, 1.0],
        "Algorithm 1: Qc where the episode ended over budget"
    );
    // Through the whole actor loss: with the hinge, lambda bites only when
    // the cost critic predicts more than the remaining budget.
    let (learner, mut batch) = penalty_probe(PenaltyForm::Hinge);
    let policy_loss = |batch: &Batch, lambda: f64| policy_loss_at(&learner, batch, lambda);
    batch.ctg = batch.valid.ones_like() * 1e6;
    let (rich_0, rich_5) = (policy_loss(&batch, 0.0), policy_loss(&batch, 5.0));
    assert!((rich_0 - rich_5).abs() < 1e-4, "ample budget: no penalty");
    batch.violated = batch.valid.ones_like();
    assert!(
        (policy_loss(&batch, 5.0) - rich_5).abs() < 1e-4,
        "the hindsight flag plays no part"
    );
    batch.ctg = batch.valid.ones_like() * -1e3;
    assert!(
        (policy_loss(&batch, 5.0) - rich_0).abs() > 1e-4,
        "a spent budget: every predicted cost is charged"
    );
}

#[test]
fn terminated_and_truncated_reach_the_targets_apart() {
    let cfg = tiny();
    let spec = NetSpec {
        obs_dim: 1,
        obs_low: vec![0.0],
        obs_high: vec![1.0],
        n_actions: Some(2),
        act_low: vec![],
        act_high: vec![],
        ..Default::default()
    };
    // Episode 0: 2 steps, truncated at 0.9. Episode 1: 2 steps,
    // terminated at the goal, 1.0.
    let t = Trajectory {
        budget: 1.0,
        goal: [0.0; 2],
        obs: vec![0.0, 0.25, 0.5, 0.75],
        next_obs: vec![0.25, 0.9, 0.75, 1.0],
        actions: vec![1.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 1.0],
        action_idx: vec![0, 0, 1, 1],
        rewards: vec![0.0, 0.0, 0.0, 1.0],
        costs: vec![1.0, 1.0, 0.0, 0.0],
        ctg: vec![1.0, 0.0, 1.0, 1.0],
        start: vec![true, false, true, false],
        terminated: vec![false, false, false, true],
        truncated: vec![false, true, false, false],
        episode: vec![0, 0, 1, 1],
        episode_returns: vec![0.0, 1.0],
        episode_costs: vec![2.0, 0.0],
        episode_success: vec![false, true],
    };
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut across = cfg.clone();
    across.bootstrap_across_episodes = true;
    let b = unshaped_batch(&[&t], &across, &spec, &mut rng);
    assert_eq!(to_vec(&b.bootstrap), vec![1.0, 1.0, 1.0, 0.0]);
    // The cost's target stops at every episode end: episode 0's costs
    // are not charged with episode 1's.
    assert_eq!(to_vec(&b.cost_bootstrap), vec![1.0, 0.0, 1.0, 0.0]);
    assert_eq!(to_vec(&b.td_valid), vec![1.0, 1.0, 1.0, 1.0]);
    assert_eq!(
        to_vec(&b.violated),
        vec![1.0, 1.0, 0.0, 0.0],
        "v_e per episode: 2 > 1, 0 <= 1"
    );
    assert_eq!(to_vec(&b.ctg), t.ctg, "CTG_t as recorded, unscaled");
    let mut within = cfg;
    within.bootstrap_across_episodes = false;
    let b = unshaped_batch(&[&t], &within, &spec, &mut rng);
    // Truncated: no target (its final state is not a token); terminated: r alone.
    assert_eq!(to_vec(&b.td_valid), vec![1.0, 0.0, 1.0, 1.0]);
    assert_eq!(to_vec(&b.bootstrap), vec![1.0, 0.0, 1.0, 0.0]);
    // Tokens carry the observation, the observation the previous action
    // arrived at, the previous action, reward, cost, CTG and start flag.
    let tok = to_vec(&b.tokens);
    let d = spec.token_dim();
    assert_eq!(
        &tok[3 * d..4 * d],
        &[0.5, 0.5, 0.0, 1.0, 0.0, 0.0, 1.0 / 15.0, 0.0]
    );
    // An episode's first token shows where the last one ended (0.9 -> 0.8
    // normalised), not only the new start (0.5 -> 0).
    assert_eq!(tok[2 * d], 0.0);
    assert!((tok[2 * d + 1] - 0.8).abs() < 1e-6, "{}", tok[2 * d + 1]);
    assert_eq!(
        &tok[..2],
        &[-1.0, -1.0],
        "nothing arrived before the first step"
    );
}

#[test]
fn acting_through_the_cache_matches_the_full_forward() {
    let (mut learner, mut venv) = tiny_learner(3);
    acting_matches_the_full_forward(&mut learner, &mut venv);
}

#[test]
fn acting_with_episode_positions_matches_the_full_forward() {
    let mut cfg = tiny();
    cfg.seed = 3;
    cfg.episode_positions = true;
    let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    let mut venv = training_venv(EnvName::DarkRoom, &cfg);
    acting_matches_the_full_forward(&mut learner, &mut venv);
}

/// Steps one collected trajectory through the KV cache and compares each
/// step's policy with the whole trajectory's forward.
fn acting_matches_the_full_forward(learner: &mut Learner, venv: &mut VecEnv) {
    learner.collect(venv).unwrap();
    let t = learner.replay.trajectories[0].clone();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let batch = unshaped_batch(&[&t], &learner.cfg, &learner.spec, &mut rng);
    let full = tch::no_grad(|| {
        learner
            .net
            .actor
            .forward(&learner.net.encode(&batch.tokens, false).unwrap())
    })
    .softmax(-1, Kind::Float); // (1, T, A)
    let mut acting = Acting::new(&learner.net, &learner.spec, &learner.cfg, &[t.budget]);
    let (od, a) = (learner.spec.obs_dim, learner.spec.act_flat());
    for s in 0..t.len() {
        let zeros = vec![0f32; a];
        let (prev, r, c) = if s == 0 {
            (&zeros[..], 0.0, 0.0)
        } else {
            (
                &t.actions[(s - 1) * a..s * a],
                t.rewards[s - 1],
                t.costs[s - 1],
            )
        };
        let zeros_o = vec![0f32; od];
        let arrived = if s == 0 {
            &zeros_o[..]
        } else {
            &t.next_obs[(s - 1) * od..s * od]
        };
        let input = StepInput {
            obs: &t.obs[s * od..(s + 1) * od],
            arrived_obs: arrived,
            prev_action: prev,
            reward: &[r],
            cost: &[c],
            episode_start: &[t.start[s]],
        };
        assert_eq!(acting.observe(&input), vec![t.ctg[s]]);
        let Policy::Discrete(p, _) = acting.policy(&learner.net, &input).unwrap() else {
            panic!()
        };
        let expected = to_vec(&full.narrow(1, s as i64, 1));
        for (x, y) in p.iter().zip(&expected) {
            assert!((x - y).abs() < 1e-5, "step {s}: {p:?} vs {expected:?}");
        }
    }
}

#[test]
fn episode_positions_count_steps_from_each_start_and_change_the_encoding() {
    let mut cfg = tiny();
    let (learner, _) = tiny_learner(0);
    let d = learner.spec.token_dim() as i64;
    // Two sequences of 5 steps: starts at 0 and 3, and at 0 only.
    let tokens = Tensor::zeros([2, 5, d], (Kind::Float, Device::Cpu));
    for (row, t) in [(0, 0), (0, 3), (1, 0)] {
        let _ = tokens.get(row).get(t).get(d - 1).fill_(1.0);
    }
    assert_eq!(
        to_vec(&super::net::episode_steps(&tokens)),
        vec![0.0, 1.0, 2.0, 0.0, 1.0, 0.0, 1.0, 2.0, 3.0, 4.0]
    );
    // The same weights with the sinusoid on encode differently.
    cfg.episode_positions = true;
    let mut with = Learner::new(cfg, EnvName::DarkRoom).unwrap();
    with.vs.copy(&learner.vs).unwrap();
    let (h0, h1) = tch::no_grad(|| {
        (
            learner.net.encode(&tokens, false).unwrap(),
            with.net.encode(&tokens, false).unwrap(),
        )
    });
    assert!(
        !h1.allclose(&h0, 1e-4, 1e-4, false),
        "the sinusoid changed nothing"
    );
}

#[test]
fn same_seed_same_run_on_cpu() {
    let run = |seed| {
        let (mut learner, mut venv) = tiny_learner(seed);
        let mut out = vec![];
        for _ in 0..2 {
            let r = learner.collect(&mut venv).unwrap();
            out.push(r.mean_cost);
            let u = learner.update().unwrap();
            out.extend([u.value_loss, u.cost_value_loss, u.policy_loss, u.lambda]);
        }
        let w = learner.vs.variables()["transformer.h.0.attn.c_attn.weight"]
            .sum(Kind::Float)
            .double_value(&[]);
        out.push(w);
        out
    };
    assert_eq!(run(5), run(5));
    assert_ne!(run(5), run(6));
}

#[test]
fn continuous_shapes_and_gradients() {
    let mut cfg = tiny();
    cfg.model.positions = Positions::Learned;
    let spec = NetSpec {
        obs_dim: 3,
        obs_low: vec![f32::NEG_INFINITY; 3],
        obs_high: vec![f32::INFINITY; 3],
        n_actions: None,
        act_low: vec![-1.0, -1.0],
        act_high: vec![1.0, 1.0],
        ..Default::default()
    };
    let vs = nn::VarStore::new(Device::Cpu);
    let net = EppoNet::new(vs.root(), &cfg, &spec).unwrap();
    let tvs = nn::VarStore::new(Device::Cpu);
    let target = EppoNet::new(tvs.root(), &cfg, &spec).unwrap();
    let n = 5;
    let t = Trajectory {
        budget: 10.0,
        goal: [0.0; 2],
        obs: (0..n * 3).map(|i| i as f32 * 0.1).collect(),
        next_obs: (3..n * 3 + 3).map(|i| i as f32 * 0.1).collect(),
        actions: (0..n * 2).map(|i| (i as f32 * 0.37).sin()).collect(),
        action_idx: vec![],
        rewards: vec![0.0, 0.0, 0.0, 0.0, 1.0],
        costs: vec![0.0, 1.0, 1.0, 0.0, 0.0],
        ctg: vec![10.0, 10.0, 9.0, 8.0, 8.0],
        start: vec![true, false, false, false, false],
        terminated: vec![false, false, false, false, true],
        truncated: vec![false; 5],
        episode: vec![0; 5],
        episode_returns: vec![1.0],
        episode_costs: vec![2.0],
        episode_success: vec![true],
    };
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let batch = unshaped_batch(&[&t, &t], &cfg, &spec, &mut rng);
    assert_eq!(batch.tokens.size(), vec![2, 5, 3 + 3 + 2 + 4]);
    assert_eq!(batch.actions.size(), vec![2, 5, 2]);
    let (lv, lc, lp, ..) = losses(&net, &target, &batch, 1.0, cfg.entropy_coef, &cfg).unwrap();
    let mut opt = Adam::new(
        &vs,
        AdamConfig {
            lr: 1e-3,
            beta1: 0.9,
            beta2: 0.99,
            eps: 1e-8,
            grad_clip: Some(1.0),
        },
    );
    let grad_sum = |name: &str| {
        let g = vs.variables()[name].grad();
        if g.defined() {
            g.abs().sum(Kind::Float).double_value(&[])
        } else {
            0.0
        }
    };
    // The actor loss alone leaves both critics untouched.
    opt.zero_grad();
    lp.backward();
    assert_eq!(grad_sum("critic.l1.weight"), 0.0);
    assert!(grad_sum("actor.l1.weight") > 0.0);
    assert!(
        grad_sum("enc_1.weight") > 0.0,
        "shared: Lp reaches the encoder"
    );
    // With the encoder detached for the actor, Lp moves the actor alone.
    let mut detached = cfg.clone();
    detached.actor_detach_encoder = true;
    opt.zero_grad();
    let (_, _, lp_detached, ..) =
        losses(&net, &target, &batch, 1.0, cfg.entropy_coef, &detached).unwrap();
    lp_detached.backward();
    assert_eq!(grad_sum("enc_1.weight"), 0.0);
    assert!(grad_sum("actor.l1.weight") > 0.0);
    let (lv2, lc2, lp2, ..) = losses(&net, &target, &batch, 1.0, cfg.entropy_coef, &cfg).unwrap();
    assert!(opt.backward_step(&(lv2 + lc2 + lp2)) > 0.0);
    assert!(lv.double_value(&[]).is_finite() && lc.double_value(&[]).is_finite());
    // Acting: actions land inside the box.
    let mut acting = Acting::new(&net, &spec, &cfg, &[10.0, 20.0]);
    let input = StepInput {
        obs: &[0.0; 6],
        arrived_obs: &[0.0; 6],
        prev_action: &[0.0; 4],
        reward: &[0.0; 2],
        cost: &[0.0; 2],
        episode_start: &[true; 2],
    };
    acting.observe(&input);
    let policy = acting.policy(&net, &input).unwrap();
    let (_, env) = sample_actions(&policy, &spec, &[], false, &mut rng);
    let EnvActions::Continuous(v) = env else {
        panic!()
    };
    assert_eq!(v.len(), 4);
    assert!(v.iter().all(|x| (-1.0..=1.0).contains(x)));
}

#[test]
fn continuous_exploration_noise_widens_the_sampled_actions_within_the_box() {
    // Two rows, one action dimension, a near-deterministic policy at 0.5.
    let spec = NetSpec {
        obs_dim: 1,
        act_low: vec![-2.0],
        act_high: vec![2.0],
        ..Default::default()
    };
    let policy = Policy::Continuous(vec![0.5; 2], vec![-10.0; 2], 1);
    let draw = |eps: &[f64], greedy: bool, seed: u64| {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (net, env) = sample_actions(&policy, &spec, eps, greedy, &mut rng);
        let EnvActions::Continuous(env) = env else {
            panic!("continuous policy, discrete actions")
        };
        (net, env)
    };
    let spread = |eps: &[f64], row: usize| -> f32 {
        let xs: Vec<f32> = (0..400).map(|seed| draw(eps, false, seed).0[row]).collect();
        let mean = xs.iter().sum::<f32>() / xs.len() as f32;
        (xs.iter().map(|x| (x - mean).powi(2)).sum::<f32>() / xs.len() as f32).sqrt()
    };
    // No epsilon: exactly the policy's own sample, as before the noise existed.
    assert!(spread(&[0.0, 0.0], 0) < 1e-3);
    assert_eq!(draw(&[], false, 7), draw(&[0.0, 0.0], false, 7));
    // Epsilon 0.5 on row 0 only: its spread is about 0.5 (less a little for
    // the clamp); row 1 keeps the policy's.
    let s0 = spread(&[0.5, 0.0], 0);
    assert!((0.35..0.55).contains(&s0), "row 0 spread {s0}");
    assert!(spread(&[0.5, 0.0], 1) < 1e-3);
    // Large noise stays inside the box: network actions in [-1, 1], the
    // environment's in [low, high], some of them on the bounds.
    let (mut hits, mut all_in) = (0, true);
    for seed in 0..200 {
        let (net, env) = draw(&[1.0, 1.0], false, seed);
        all_in &= net.iter().all(|x| (-1.0..=1.0).contains(x));
        all_in &= env.iter().all(|x| (-2.0..=2.0).contains(x));
        hits += net.iter().filter(|x| x.abs() == 1.0).count();
    }
    assert!(all_in && hits > 0, "clamped onto the bounds {hits} times");
    // The mode ignores epsilon.
    let (net, _) = draw(&[1.0, 1.0], true, 0);
    assert_eq!(net, vec![0.5f32.tanh(); 2]);
}

#[test]
fn tanh_gaussian_log_prob_matches_the_sampler() {
    let randn = || Tensor::randn([4, 5, 2], (Kind::Float, Device::Cpu));
    let (mean, log_std, noise) = crate::torch_rng::seeded(3, || (randn(), randn(), randn()));
    let log_std = log_std * 0.5 - 0.5;
    let (a, want) = tanh_gaussian_sample(&mean, &log_std, &noise);
    let got = tanh_gaussian_log_prob(&mean, &log_std, &a);
    let err = (got - want).abs().max().double_value(&[]);
    assert!(err < 1e-2, "max |log pi difference| {err}");
    // Saturated f32 actions (exactly +-1) stay finite.
    let edge = Tensor::from_slice(&[1.0f32, -1.0]).view([1, 2]);
    let lp = tanh_gaussian_log_prob(
        &mean.narrow(0, 0, 1).narrow(1, 0, 1).view([1, 2]),
        &log_std.narrow(0, 0, 1).narrow(1, 0, 1).view([1, 2]),
        &edge,
    );
    assert!(lp.double_value(&[0]).is_finite());
}

#[test]
fn filtered_bc_raises_the_log_prob_of_kept_replayed_actions() {
    for discrete in [true, false] {
        let (mut learner, mut venv) = tiny_learner(2);
        learner.collect(&mut venv).unwrap();
        let trajs: Vec<&Trajectory> = learner.replay.trajectories.iter().collect();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut cfg = learner.cfg.clone();
        cfg.entropy_coef = 0.0;
        let (batch, net, target, vs) = if discrete {
            let batch = unshaped_batch(&trajs, &cfg, &learner.spec, &mut rng);
            let vs = nn::VarStore::new(Device::Cpu);
            let net = EppoNet::new(vs.root(), &cfg, &learner.spec).unwrap();
            let tvs = nn::VarStore::new(Device::Cpu);
            let target = EppoNet::new(tvs.root(), &cfg, &learner.spec).unwrap();
            (batch, net, target, vs)
        } else {
            // The same steps with a 2-D action in [-1, 1] per step.
            let spec = NetSpec {
                n_actions: None,
                act_low: vec![-1.0, -1.0],
                act_high: vec![1.0, 1.0],
                ..learner.spec.clone()
            };
            let owned: Vec<Trajectory> = trajs
                .iter()
                .map(|t| {
                    let mut t = (*t).clone();
                    t.actions = (0..t.len() * 2)
                        .map(|i| (i as f32 * 0.7).sin() * 0.9)
                        .collect();
                    t.action_idx.clear();
                    t
                })
                .collect();
            let refs: Vec<&Trajectory> = owned.iter().collect();
            let batch = unshaped_batch(&refs, &cfg, &spec, &mut rng);
            let vs = nn::VarStore::new(Device::Cpu);
            let net = EppoNet::new(vs.root(), &cfg, &spec).unwrap();
            let tvs = nn::VarStore::new(Device::Cpu);
            let target = EppoNet::new(tvs.root(), &cfg, &spec).unwrap();
            (batch, net, target, vs)
        };
        // The BC term alone: Lp(bc = 1) - Lp(bc = 0) under the same noise.
        let bc_term = || {
            let mut with = cfg.clone();
            with.bc_coef = 1.0;
            let (_, _, a, ..) = crate::torch_rng::seeded(0, || {
                losses(&net, &target, &batch, 0.0, with.entropy_coef, &with)
            })
            .unwrap();
            let (_, _, b, ..) = crate::torch_rng::seeded(0, || {
                losses(&net, &target, &batch, 0.0, cfg.entropy_coef, &cfg)
            })
            .unwrap();
            a - b
        };
        let first = bc_term().double_value(&[]);
        let mut opt = Adam::new(
            &vs,
            AdamConfig {
                lr: 1e-2,
                beta1: 0.9,
                beta2: 0.99,
                eps: 1e-8,
                grad_clip: None,
            },
        );
        for _ in 0..30 {
            opt.backward_step(&bc_term());
        }
        let last = bc_term().double_value(&[]);
        assert!(
            last < first - 1e-3,
            "discrete {discrete}: BC term {first} -> {last} (-mean keep * log pi must fall)"
        );
    }
}

#[test]
fn n_step_targets_sum_rewards_until_the_bootstrap_stops() {
    let t = |v: &[f32]| Tensor::from_slice(v).view([1, v.len() as i64]);
    // Steps 0..5: reward at step 2 (terminal: no bootstrap past it), then
    // a step 3 without a target of its own (truncated), then 4 and 5.
    let r = t(&[0.0, 0.0, 1.0, 0.0, 0.0, 2.0]);
    let boot = t(&[1.0, 1.0, 0.0, 1.0, 1.0, 0.0]);
    let valid = t(&[1.0, 1.0, 1.0, 0.0, 1.0, 1.0]);
    let v_next = t(&[10.0, 20.0, 30.0, 40.0, 50.0, 60.0]);
    let g = 0.5;
    let y1 = to_vec(&n_step_targets(&r, &boot, &valid, &v_next, g, 1));
    assert_eq!(y1, vec![5.0, 10.0, 1.0, 20.0, 25.0, 2.0]);
    let y3 = to_vec(&n_step_targets(&r, &boot, &valid, &v_next, g, 3));
    // 0: 0 + g (0 + g (1)) = 0.25; 1: 0 + g 1 = 0.5; 2: 1;
    // 3: r3 + g [valid 4] y(2)_4 = 0 + g (0 + g 2) = 0.5;
    // 4: 0 + g 2 = 1; 5: 2.
    assert_eq!(y3, vec![0.25, 0.5, 1.0, 0.5, 1.0, 2.0]);
    // Step 2 bootstraps into step 3, which has no target: one-step there.
    let boot2 = t(&[1.0, 1.0, 1.0, 0.0, 1.0, 0.0]);
    let y2 = to_vec(&n_step_targets(&r, &boot2, &valid, &v_next, g, 2));
    // 1: 0 + g y(1)_2 = g (1 + g 30) = 8; 2: 1 + g V'_3 (step 3 has no target) = 1 + 15.
    assert_eq!(y2[1], 8.0);
    assert_eq!(y2[2], 16.0);
}

/// Standardised observations: the entries without finite bounds are
/// centred and scaled by a random policy's statistics (the accelerometer's
/// spread of about 9 comes to 1), the bounded ones keep their [-1, 1] map,
/// the statistics ride in the checkpoint's spec, and the run is the same
/// under its seed.
#[test]
fn standardised_observations_come_from_a_random_policy_and_stay_fixed() {
    let mut cfg = EppoConfig {
        standardise_observations: true,
        physics_steps_per_action: Some(50),
        max_episode_steps: 75,
        ..tiny()
    };
    cfg.model.max_len = 150;
    let learner = Learner::new(cfg.clone(), EnvName::Point).unwrap();
    let spec = &learner.spec;
    assert_eq!(spec.obs_mean.len(), 23);
    spec.check().unwrap();
    assert!((spec.obs_mean[13] - 9.81).abs() < 0.01, "gravity, constant");
    assert_eq!(spec.obs_scale[13], 1.0, "a constant entry is only centred");
    assert!(spec.obs_scale[12] > 3.0, "the accelerometer's spread");
    let mut obs = vec![0.0f32; 23];
    obs[12] = spec.obs_mean[12] + spec.obs_scale[12];
    obs[13] = 9.81;
    obs[2] = 1.0; // a rotation entry: bounded, mapped to [-1, 1] as before
    let mut out = Vec::new();
    spec.normalise_obs(&obs, &mut out);
    assert!((out[12] - 1.0).abs() < 1e-5 && out[13].abs() < 0.01 && out[2] == 1.0);
    let again = Learner::new(cfg, EnvName::Point).unwrap();
    assert_eq!(again.spec, learner.spec, "deterministic under the seed");
    let plain = Learner::new(tiny(), EnvName::DarkRoom).unwrap();
    assert!(plain.spec.obs_mean.is_empty(), "off: raw as before");
}

/// The goal-conditioned rung: every collected observation ends with the
/// task's goal, and its checkpoint is refused by evaluation by name.
#[test]
fn the_goal_conditioned_rung_sees_the_goal_and_is_never_evaluated() {
    let cfg = EppoConfig {
        goal_in_observation: true,
        ..tiny()
    };
    let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    assert_eq!(learner.spec.obs_dim, 4, "position and goal");
    let mut venv = training_venv(EnvName::DarkRoom, &cfg);
    learner.collect(&mut venv).unwrap();
    for t in &learner.replay.trajectories {
        for step in t.obs.chunks(4) {
            assert_eq!(
                step[2..],
                t.goal,
                "the goal at the end of every observation"
            );
        }
    }
    let out = std::env::temp_dir().join(format!("icrl-eppo-goal-{}", std::process::id()));
    let report = train(&PretrainOptions {
        env: EnvName::DarkRoom,
        cfg,
        out: out.clone(),
        resume: None,
        progress: false,
    })
    .unwrap();
    let err = EppoAgent::load(&report.last_checkpoint, Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("goal_in_observation"), "{err}");
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn pretrain_end_to_end_checkpoints_resumes_and_loads() {
    let out = std::env::temp_dir().join(format!("icrl-eppo-e2e-{}", std::process::id()));
    let opts = PretrainOptions {
        env: EnvName::DarkRoom,
        cfg: tiny(),
        out: out.clone(),
        resume: None,
        progress: false,
    };
    let report = train(&opts).unwrap();
    assert_eq!(report.updates, 4);
    assert!(report.last_checkpoint.ends_with("step_4"));
    let lines = std::fs::read_to_string(report.run_dir.join("metrics.jsonl")).unwrap();
    let first: serde_json::Value = serde_json::from_str(lines.lines().next().unwrap()).unwrap();
    for key in [
        "env_steps",
        "episodic_return",
        "episodic_cost",
        "lambda",
        "losses/value_loss",
    ] {
        assert!(first.get(key).is_some(), "{key}");
    }
    // Resume to 6 updates from the run folder.
    let mut cfg = tiny();
    cfg.total_updates = 6;
    let resumed = train(&PretrainOptions {
        cfg,
        resume: Some(report.run_dir.clone()),
        ..opts.clone()
    })
    .unwrap();
    assert_eq!(
        (resumed.updates, resumed.run_dir.clone()),
        (6, report.run_dir.clone())
    );
    assert!(resumed.env_steps > report.env_steps);
    // An incompatible config is refused with the manifest named.
    let mut other = tiny();
    other.model.n_layers = 2;
    let err = train(&PretrainOptions {
        cfg: other,
        resume: Some(report.run_dir.clone()),
        ..opts.clone()
    })
    .err()
    .unwrap()
    .to_string();
    assert!(
        err.contains("manifest.json") && err.contains("model"),
        "{err}"
    );
    // A truncated weight file is refused with its name.
    let ckpt = report.run_dir.join("checkpoints/step_6");
    let w = ckpt.join("model.safetensors");
    let bytes = std::fs::read(&w).unwrap();
    let mut agent = EppoAgent::load(&ckpt, Device::Cpu).unwrap();
    std::fs::write(&w, &bytes[..bytes.len() / 2]).unwrap();
    let err = EppoAgent::load(&ckpt, Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("model.safetensors"), "{err}");
    // The frozen agent acts for two trajectories at once.
    agent
        .reset(&[
            Conditioning::Budget { ctg: 3.0 },
            Conditioning::Budget { ctg: 9.0 },
        ])
        .unwrap();
    let input = StepInput {
        obs: &[4.0, 4.0, 4.0, 4.0],
        arrived_obs: &[0.0; 4],
        prev_action: &[0.0; 10],
        reward: &[0.0; 2],
        cost: &[0.0; 2],
        episode_start: &[true; 2],
    };
    let Actions::Discrete(a) = agent.act(&input, true).unwrap() else {
        panic!()
    };
    assert!(a.len() == 2 && a.iter().all(|&x| x < 5));
    assert!(
        agent
            .act(
                &StepInput {
                    obs: &[0.0; 2],
                    ..input
                },
                false
            )
            .is_err()
    );
    std::fs::remove_dir_all(&out).unwrap();
}

/// An overlapped run's metrics and final weights, less what depends on the
/// machine's speed (rates, phase times, CPU shares).
fn overlapped_run(seed: u64, out: &std::path::Path) -> (Vec<serde_json::Value>, Vec<u8>) {
    let mut cfg = tiny();
    cfg.seed = seed;
    cfg.overlap = true;
    cfg.total_updates = 8;
    let report = train(&PretrainOptions {
        env: EnvName::DarkRoom,
        cfg,
        out: out.to_path_buf(),
        resume: None,
        progress: false,
    })
    .unwrap();
    assert_eq!(report.updates, 8);
    let records = std::fs::read_to_string(report.run_dir.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| {
            let mut v: serde_json::Value = serde_json::from_str(l).unwrap();
            v.as_object_mut().unwrap().retain(|k, _| {
                !(k.starts_with("time/") || k.starts_with("charts/cpu") || k.ends_with("_per_s"))
            });
            v
        })
        .collect();
    let weights = std::fs::read(report.last_checkpoint.join("model.safetensors")).unwrap();
    (records, weights)
}

#[test]
fn the_overlapped_loop_is_deterministic_and_keeps_the_replay_ratio() {
    tch::set_num_threads(1);
    let out = std::env::temp_dir().join(format!("icrl-eppo-overlap-{}", std::process::id()));
    let (a, wa) = overlapped_run(3, &out);
    let (b, wb) = overlapped_run(3, &out);
    assert_eq!(a, b, "same seed, same metrics, whichever thread was faster");
    assert!(wa == wb, "same seed, same weights");
    let (c, _) = overlapped_run(4, &out);
    assert_ne!(a, c);
    // updates_per_round = 2 after every round (learning_starts = 0): the
    // ratio of the synchronous loop, one record per round.
    let updates: Vec<u64> = a.iter().map(|r| r["updates"].as_u64().unwrap()).collect();
    assert_eq!(updates, vec![2, 4, 6, 8]);
    let steps: Vec<u64> = a.iter().map(|r| r["env_steps"].as_u64().unwrap()).collect();
    assert!(steps.windows(2).all(|w| w[1] > w[0]), "{steps:?}");
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn the_replay_ratio_sets_updates_per_environment_step() {
    let (mut learner, mut venv) = tiny_learner(0);
    learner.cfg.replay_ratio = Some(0.1);
    learner.cfg.total_updates = 1000;
    learner.cfg.learning_starts = 5;
    for _ in 0..3 {
        learner.collect(&mut venv).unwrap();
        let owed = learner.updates_owed();
        let expected = (0.1 * (learner.env_steps - 5) as f64).floor() as u64 - learner.updates;
        assert_eq!(owed, expected);
        for _ in 0..owed {
            learner.update().unwrap();
        }
    }
    assert_eq!(
        learner.updates,
        (0.1 * (learner.env_steps - 5) as f64).floor() as u64
    );
    // Without it: updates_per_round, none before learning_starts, none past the end.
    learner.cfg.replay_ratio = None;
    assert_eq!(learner.updates_owed(), 2);
    learner.cfg.learning_starts = learner.env_steps + 1;
    assert_eq!(learner.updates_owed(), 0);
    learner.cfg.learning_starts = 0;
    learner.cfg.total_updates = learner.updates + 1;
    assert_eq!(learner.updates_owed(), 1);
    let mut bad = tiny();
    bad.replay_ratio = Some(0.0);
    assert!(
        bad.validate()
            .unwrap_err()
            .to_string()
            .contains("replay_ratio = 0")
    );
    let mut bad = tiny();
    bad.learner_threads = -1;
    assert!(
        bad.validate()
            .unwrap_err()
            .to_string()
            .contains("learner_threads = -1")
    );
}

/// Trains `cfg` into `out` with a stop requested from the start: the run must
/// stop after update 1 with checkpoint `step_1`. Then resumes that run to its
/// end; returns the updates done and the `updates` of every metrics record.
pub(crate) fn stop_after_one_then_resume(cfg: &EppoConfig, out: &Path) -> (u64, Vec<u64>) {
    let options = |resume: Option<PathBuf>| PretrainOptions {
        env: EnvName::DarkRoom,
        cfg: cfg.clone(),
        out: out.to_path_buf(),
        resume,
        progress: false,
    };
    crate::stop::request();
    let e = train(&options(None)).unwrap_err();
    crate::stop::clear();
    let EppoError::Interrupted {
        checkpoint,
        updates,
    } = e
    else {
        panic!("{e}");
    };
    assert_eq!(updates, 1, "stopped after the first update");
    assert!(checkpoint.ends_with("step_1"), "{}", checkpoint.display());
    let run_dir = checkpoint.parent().unwrap().parent().unwrap().to_path_buf();
    let done = train(&options(Some(run_dir.clone()))).unwrap();
    let recorded =
        crate::checkpoint::recorded_counters(&run_dir.join("metrics.jsonl"), "updates").unwrap();
    (done.updates, recorded)
}

/// A stop while both sides run: the learner stops after its current update,
/// the actor abandons its round, the checkpoint is written, and the run
/// resumes (overlapped) to its end without a repeated record.
#[test]
fn an_overlapped_stop_checkpoints_and_resumes() {
    tch::set_num_threads(1);
    let out = std::env::temp_dir().join(format!("icrl-eppo-overlap-stop-{}", std::process::id()));
    let cfg = EppoConfig {
        overlap: true,
        total_updates: 6,
        checkpoint_every: 100,
        ..tiny()
    };
    let (done, updates) = stop_after_one_then_resume(&cfg, &out);
    assert_eq!(done, 6);
    assert_eq!(
        updates,
        vec![1, 3, 5, 6],
        "one record per round, none repeated"
    );
    std::fs::remove_dir_all(&out).unwrap();
}
