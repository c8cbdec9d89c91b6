//! Collection and what the critics see of it: Algorithm 1's trajectories,
//! hindsight relabelling, the scripted first episode, exploration noise, the
//! dense and novelty rewards, the search rates.

use super::*;

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
    cfg.goal.scripted_first_episode = true;
    cfg.goal.relabel_prob = 1.0;
    let mut darkroom = cfg.clone();
    darkroom.tasks.physics_steps_per_action = None;
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
}

#[test]
fn the_dense_critic_reward_shapes_targets_and_leaves_tokens_sparse() {
    let (mut learner, mut venv) = tiny_learner(0);
    learner.collect(&mut venv).unwrap();
    let trajs: Vec<&Trajectory> = learner.replay.trajectories.iter().collect();
    let sparse_cfg = learner.cfg.clone();
    let mut dense_cfg = sparse_cfg.clone();
    dense_cfg.goal.dense_reward_coef = 0.5;
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
    let scale = sparse_cfg.targets.reward_scale as f32;
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
        let mut cfg = learner.cfg.clone();
        cfg.goal.dense_reward_coef = coef;
        cfg.goal.dense_reward_after_goal = after_goal;
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        to_vec(&unshaped_batch(&[&t], &cfg, &learner.spec, &mut rng).rewards)
    };
    let sparse = rewards(0.0, false);
    let shaping = |r: Vec<f32>| -> Vec<f32> {
        let scale = learner.cfg.targets.reward_scale as f32;
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
    cfg.goal.dense_reward_after_goal = true;
    let e = cfg.validate().unwrap_err().to_string();
    assert!(e.contains("dense_reward_coef"), "{e}");
}

#[test]
fn the_goal_enters_the_context_with_its_reward() {
    // One fixed task (the ladder's first rung): collect until an episode
    // ends at the goal, then look at the token after it.
    let mut cfg = tiny();
    cfg.tasks.task_pool = 1;
    let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    let goal = sample_task(
        &spawn_config(EnvName::DarkRoom),
        Orientation::Centre,
        pretrain_task_seed(cfg.run.seed, 0),
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
    cfg.exploration.eps_start = 1.0;
    cfg.exploration.eps_end = 0.4;
    cfg.exploration.eps_last_start = Some(0.6);
    cfg.exploration.eps_last_end = Some(0.0);
    cfg.exploration.eps_decay_steps = 1000;
    let start = cfg.exploration.schedule(0);
    assert_eq!((start.first, start.last), (1.0, 0.6));
    let mid = cfg.exploration.schedule(500);
    assert!((mid.first - 0.7).abs() < 1e-12 && (mid.last - 0.3).abs() < 1e-12);
    let end = cfg.exploration.schedule(10_000);
    assert!(
        (end.first - 0.4).abs() < 1e-12 && end.last == 0.0,
        "annealed, then held"
    );
    // Inside a trajectory: linear from the first to the last step, scaled.
    assert!((end.at(0, 100, 1.0) - 0.4).abs() < 1e-12);
    assert!((end.at(50, 100, 1.0) - 0.2).abs() < 1e-12);
    assert!(end.at(100, 100, 1.0).abs() < 1e-12);
    assert!((end.at(0, 100, 0.5) - 0.2).abs() < 1e-12);
    // Without the last-step values, epsilon is flat inside a trajectory.
    cfg.exploration.eps_last_start = None;
    cfg.exploration.eps_last_end = None;
    let flat = cfg.exploration.schedule(500);
    assert_eq!(flat.first, flat.last);
    // An epsilon outside [0, 1] is refused by name.
    assert!(cfg.validate().is_ok());
    cfg.exploration.eps_last_end = Some(1.5);
    assert!(refused(&cfg, "eps_last_end"));
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
    let spec = grid_spec();
    let cfg = tiny();
    let batch = |cfg: &EppoConfig, novelty: f32| {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let shaping = Shaping {
            novelty,
            budget: BudgetInTargets::Absent,
        };
        make_batch(&[&t], cfg, &spec, shaping, &mut rng, Device::Cpu)
    };
    let plain = batch(&cfg, 0.0);
    // What each step's critic reward carries over `plain`'s, in reward units.
    let paid = |shaped: &Batch| -> Vec<f32> {
        to_vec(&shaped.rewards)
            .iter()
            .zip(to_vec(&plain.rewards))
            .map(|(b, p)| ((b - p) / cfg.targets.reward_scale as f32 * 1000.0).round() / 1000.0)
            .collect()
    };
    let bonus = batch(&cfg, 0.1);
    assert_eq!(to_vec(&plain.tokens), to_vec(&bonus.tokens));
    assert_eq!(paid(&bonus), vec![0.1, 0.0, 0.1, 0.0, 0.1, 0.0, 0.0, 0.0]);
}

/// With novelty critics, the bonus a step's reward would carry moves into
/// the novelty critics' reward, all of it and nothing else: under every
/// over-budget rule the two rewards add up to the one critic's, and the
/// tokens are the same.
#[test]
fn novelty_critics_take_the_bonus_out_of_the_reward_critics() {
    let mut t = cell_walk();
    // Step 2's arrival in (3,4) is new and spends the episode's budget.
    t.costs[2] = 2.0;
    let spec = grid_spec();
    let one = tiny();
    let mut apart = tiny();
    apart.novelty.novelty_critic = true;
    apart.novelty.novelty_bonus = 0.1;
    let batch = |cfg: &EppoConfig, over_budget: Option<OverBudget>| {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let shaping = Shaping {
            novelty: 0.1,
            budget: over_budget.map_or(BudgetInTargets::Absent, BudgetInTargets::OverBudget),
        };
        make_batch(&[&t], cfg, &spec, shaping, &mut rng, Device::Cpu)
    };
    assert!(batch(&one, None).novelty_rewards.is_none());
    let scale = one.targets.reward_scale as f32;
    let priced = |replaced_reward, pays_novelty| {
        Some(OverBudget {
            replaced_reward,
            cost_price: 1.0,
            pays_novelty,
        })
    };
    // (over-budget rule, the bonus paid at step 2)
    let rules = [
        (None, 0.1),
        (priced(None, true), 0.1),
        (priced(None, false), 0.0),
        (priced(Some(-0.1), true), 0.0),
    ];
    for (rule, at_step_2) in rules {
        let (shared, split) = (batch(&one, rule), batch(&apart, rule));
        assert_eq!(to_vec(&shared.tokens), to_vec(&split.tokens));
        let novelty = to_vec(split.novelty_rewards.as_ref().unwrap());
        assert_eq!(
            novelty,
            [0.1, 0.0, at_step_2, 0.0, 0.1, 0.0, 0.0, 0.0].map(|b| b * scale),
            "{rule:?}"
        );
        for ((s, r), n) in to_vec(&shared.rewards)
            .iter()
            .zip(to_vec(&split.rewards))
            .zip(&novelty)
        {
            assert!(
                (s - (r + n)).abs() < 1e-5,
                "{rule:?}: {s} against {r} + {n}"
            );
        }
    }
    let mut off = apart.clone();
    off.novelty.novelty_bonus = 0.0;
    assert!(refused(&off, "novelty_critic"));
}

/// The training metrics of safety: a cost counts as paid again where the
/// trajectory paid one in an earlier episode (in `cell_walk`, step 3
/// re-enters episode 0's costly (4,5); steps 4 and 5 meet new costs, and
/// step 6 repeats step 5 inside one episode, which is not yet learning from
/// context), and the share of last episodes over budget.
#[test]
fn repeated_costs_are_those_paid_again_in_a_later_episode() {
    let mut t = cell_walk();
    for step in [0, 3, 4, 5, 6] {
        t.costs[step] = 1.0;
    }
    t.ctg = vec![0.0; t.len()];
    assert_eq!(
        repeated_costs(&t, 2, 0.5),
        [false, false, false, true, false, false, false, false]
    );
    // The training metric: one unit paid again over 3 episodes, then over
    // 6 with a costless trajectory beside it.
    assert_eq!(repeat_cost_per_episode(&[t.clone()], 2, 0.5), 1.0 / 3.0);
    assert_eq!(
        repeat_cost_per_episode(&[t.clone(), cell_walk()], 2, 0.5),
        1.0 / 6.0
    );
    // The share of last episodes over budget: this walk's last episode pays
    // 2 (budget 1), a costless walk's nothing; a cost at the budget is within it.
    let mut over = t.clone();
    over.episode_costs = vec![2.0, 1.0, 2.0];
    assert_eq!(last_over_budget(&[over.clone()]), 1.0);
    assert_eq!(last_over_budget(&[over.clone(), cell_walk()]), 0.5);
    over.episode_costs[2] = 1.0;
    assert_eq!(last_over_budget(&[over]), 0.0);
}

#[test]
fn new_cells_while_searching_counts_cells_first_entered_after_a_miss() {
    // cell_walk: episode 1 starts unfound and enters one new cell, (3,5),
    // the goal; episode 2 comes after the success and is not counted.
    assert_eq!(new_cells_while_searching(&[cell_walk()], 2, 1.0), 1.0);
    // Without the success, episode 2 searches too and enters (5,4), (3,3).
    let mut missed = cell_walk();
    missed.rewards = vec![0.0; missed.len()];
    missed.terminated = vec![false; missed.len()];
    missed.truncated = vec![false, false, true, false, true, false, false, true];
    missed.episode_success = vec![false; 3];
    assert_eq!(new_cells_while_searching(&[missed.clone()], 2, 1.0), 1.5);
    // Episode 2 driving cells seen before adds nothing: the fixed route.
    let mut same_route = missed.clone();
    for (step, cell) in [(5, [4.0, 5.0]), (6, [4.0, 4.0]), (7, [3.0, 4.0])] {
        same_route.next_obs[step * 2..step * 2 + 2].copy_from_slice(&cell);
    }
    assert_eq!(
        new_cells_while_searching(&[same_route.clone()], 2, 1.0),
        0.5
    );
    // Pooled over trajectories: (1 + 2 + 1 + 0) cells over 4 episodes.
    assert_eq!(
        new_cells_while_searching(&[missed, same_route], 2, 1.0),
        1.0
    );
    // Found in the first episode: no episode searches.
    let mut found_first = cell_walk();
    found_first.episode_success = vec![true, true, false];
    assert!(new_cells_while_searching(&[found_first], 2, 1.0).is_nan());
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

/// The goal-conditioned rung: every collected observation ends with the
/// task's goal, and its checkpoint is refused by evaluation by name.
#[test]
fn the_goal_conditioned_rung_sees_the_goal_and_is_never_evaluated() {
    let mut cfg = tiny();
    cfg.goal.goal_in_observation = true;
    let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    assert_eq!(learner.spec.obs_dim, 5, "position, goal, shown");
    let mut venv = training_venv(EnvName::DarkRoom, &cfg);
    learner.collect(&mut venv).unwrap();
    for t in &learner.replay.trajectories {
        for step in t.obs.chunks(5).chain(t.next_obs.chunks(5)) {
            assert_eq!(
                step[2..],
                [t.goal[0], t.goal[1], 1.0],
                "the goal at the end of every observation"
            );
        }
    }
    let (out, report) = train_darkroom(cfg, "goal");
    let err = EppoAgent::load(&report.last_checkpoint, Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("goal_in_observation"), "{err}");
    std::fs::remove_dir_all(&out).unwrap();
}

/// The goal hidden in a share of trajectories (`goal_hidden_share`): the
/// share follows its ramp over environment steps; a hidden trajectory's
/// slots are blank in every observation and arrival, a shown one's hold its
/// goal; relabelling shows a shown trajectory its new goal and leaves a
/// hidden one blank; and the checkpoint acts on the task's own observation,
/// its slots blank, where one always shown is refused.
#[test]
fn hidden_goals_are_blank_throughout_and_such_a_policy_is_evaluated() {
    let mut ramp = tiny();
    ramp.goal.goal_in_observation = true;
    ramp.goal.goal_hidden_share = 0.8;
    ramp.goal.goal_hidden_ramp = [100, 300];
    let share: Vec<f64> = [0, 100, 200, 300, 1000]
        .map(|s| ramp.goal.goal_hidden_share_at(s))
        .to_vec();
    assert_eq!(share, [0.0, 0.0, 0.4, 0.8, 0.8]);
    let mut bad = ramp.clone();
    bad.goal.goal_in_observation = false;
    assert!(refused(&bad, "goal_in_observation"));
    let mut bad = ramp.clone();
    bad.goal.goal_hidden_ramp = [300, 100];
    assert!(refused(&bad, "goal_hidden_ramp"));

    let mut cfg = ramp;
    cfg.goal.goal_hidden_share = 0.5;
    cfg.goal.goal_hidden_ramp = [0, 0];
    cfg.tasks.n_envs = 8;
    cfg.optimisation.batch_size = 8;
    let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    let mut venv = training_venv(EnvName::DarkRoom, &cfg);
    for _ in 0..2 {
        let stats = learner.collect(&mut venv).unwrap();
        let round: Vec<_> = learner.replay.trajectories.iter().rev().take(8).collect();
        let blank = round.iter().filter(|t| !GoalShown::shows(&t.obs[..5]));
        let share = blank.count() as f64 / 8.0;
        assert_eq!(
            stats.goal_slots.hidden_share, share,
            "the metric counts them"
        );
        // The metrics' cost of each kind: the mean episode cost of the
        // round's trajectories that showed or blanked their goal.
        let cost_of = |shown: bool| {
            let kind: Vec<f64> = round
                .iter()
                .filter(|t| GoalShown::shows(&t.obs[..5]) == shown)
                .flat_map(|t| t.episode_costs.iter().map(|&c| f64::from(c)))
                .collect();
            kind.iter().sum::<f64>() / kind.len() as f64
        };
        for (metric, shown) in [
            (stats.goal_slots.shown_cost, true),
            (stats.goal_slots.hidden_cost, false),
        ] {
            let want = cost_of(shown);
            assert!(
                (metric - want).abs() < 1e-9 || (metric.is_nan() && want.is_nan()),
                "{metric} against {want}"
            );
        }
    }
    let (mut shown, mut hidden) = (Vec::new(), Vec::new());
    for t in &learner.replay.trajectories {
        let rows: Vec<&[f32]> = t.obs.chunks(5).chain(t.next_obs.chunks(5)).collect();
        if GoalShown::shows(rows[0]) {
            assert!(rows.iter().all(|r| r[2..] == [t.goal[0], t.goal[1], 1.0]));
            shown.push(t);
        } else {
            assert!(rows.iter().all(|r| r[2..] == [0.0; 3]), "blank throughout");
            hidden.push(t);
        }
    }
    assert!(
        shown.len() >= 2 && hidden.len() >= 2,
        "about half of 16 each: {} shown, {} hidden",
        shown.len(),
        hidden.len()
    );
    let rule = learner.goal_rule;
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for (t, was_shown) in [(shown[0], true), (hidden[0], false)] {
        let out = relabel_some(&[t], 1.0, &learner.spec, &rule, true, &mut rng)
            .pop()
            .unwrap()
            .expect("a grid walk reaches somewhere new");
        assert_ne!(out.goal, t.goal, "moved");
        let want = if was_shown {
            [out.goal[0], out.goal[1], 1.0]
        } else {
            [0.0; 3]
        };
        for r in out.obs.chunks(5).chain(out.next_obs.chunks(5)) {
            assert_eq!(r[2..], want, "shown: {was_shown}");
        }
    }

    // Shown, the goal is known from the first step (the dense reward and the
    // recall head act there); hidden, only once found.
    for (t, was_shown) in [(shown[0], true), (hidden[0], false)] {
        let b = make_batch(
            &[t],
            &cfg,
            &learner.spec,
            cfg.shaping(0, None),
            &mut rng,
            Device::Cpu,
        );
        let known = to_vec(&b.goal_known);
        let first_success = t.terminated.iter().position(|&x| x);
        for (step, &k) in known.iter().take(t.len()).enumerate() {
            let want = was_shown || first_success.is_some_and(|s| step > s);
            assert_eq!(k == 1.0, want, "step {step}, shown: {was_shown}");
        }
    }

    let (out, report) = train_darkroom(cfg, "hidden");
    let mut agent = EppoAgent::load(&report.last_checkpoint, Device::Cpu).unwrap();
    assert_eq!(agent.env_obs_dim(), 2, "the grid's own position");
    agent.reset(&[Conditioning::Budget { ctg: 5.0 }]).unwrap();
    let step = StepInput {
        obs: &[0.5, 0.5],
        arrived_obs: &[0.0, 0.0],
        prev_action: &[0.0; 5],
        reward: &[0.0],
        cost: &[0.0],
        episode_start: &[true],
    };
    assert!(matches!(
        agent.act(&step, true).unwrap(),
        Actions::Discrete(_)
    ));
    let three = StepInput {
        obs: &[0.5; 5],
        arrived_obs: &[0.0; 5],
        ..step
    };
    let err = agent.act(&three, true).unwrap_err().to_string();
    assert!(err.contains("obs has 5 entries, expected 2"), "{err}");
    std::fs::remove_dir_all(&out).unwrap();
}
