//! The losses and their masks on fixed batches: the critics, the entropy
//! weight, n-step targets, the tanh-Gaussian policy.

use super::*;

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
            learner.cfg.exploration.entropy_coef,
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
    let mut cfg = tiny();
    cfg.goal.goal_recall_coef = 1.0;
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

/// With two libtorch threads the target network's forward runs on a thread
/// of its own beside the online forward, each on one libtorch thread: the
/// losses are bit for bit those of one thread, and the caller's thread count
/// is given back.
#[test]
fn the_target_forward_beside_the_online_one_computes_the_same_losses() {
    let (mut learner, mut venv) = tiny_learner(3);
    learner.collect(&mut venv).unwrap();
    let batch = replay_batch(&learner);
    let before = tch::get_num_threads();
    let losses_at = |threads: i32| {
        tch::set_num_threads(threads);
        let seeded = crate::torch_rng::seeded(5, || {
            losses(
                &learner.net,
                &learner.target,
                &batch,
                0.5,
                learner.cfg.exploration.entropy_coef,
                &learner.cfg,
            )
            .unwrap()
        });
        assert_eq!(
            tch::get_num_threads(),
            threads,
            "the thread count was not given back"
        );
        let (lv, lc, lp, entropy, _) = seeded;
        [lv, lc, lp, entropy].map(|t| t.double_value(&[]))
    };
    let one = losses_at(1);
    let two = losses_at(2);
    tch::set_num_threads(before);
    assert_eq!(one, two);
}

/// The novelty critics: their TD loss is part of Lv, and the actor weighs
/// their value only on steps whose context holds no success yet (shifting
/// their values moves Lp there and nowhere else), for discrete and
/// continuous actions alike; without `novelty_critic` there are none.
#[test]
fn the_actor_weighs_the_novelty_critics_only_before_a_success() {
    assert!(tiny_learner(0).0.net.novelty_critic.is_none());
    let mut cfg = tiny();
    cfg.novelty.novelty_critic = true;
    cfg.novelty.novelty_bonus = 0.1;
    cfg.model.transformer.embd_dropout = 0.0;
    let shaping = Shaping {
        novelty: 0.1,
        budget: BudgetInTargets::Absent,
    };
    // A discrete learner on SafeDarkRoom's cells, and a continuous net.
    let discrete = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    let walk = cell_walk();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let grid = make_batch(
        &[&walk],
        &cfg,
        &discrete.spec,
        shaping,
        &mut rng,
        Device::Cpu,
    );
    // Found at step 4: known from step 5 on.
    assert_eq!(
        to_vec(&grid.goal_known),
        [0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0]
    );
    let spec = NetSpec {
        obs_dim: 2,
        obs_low: vec![f32::NEG_INFINITY; 2],
        obs_high: vec![f32::INFINITY; 2],
        n_actions: None,
        act_low: vec![-1.0; 5],
        act_high: vec![1.0; 5],
    };
    let (vs, tvs) = (
        nn::VarStore::new(Device::Cpu),
        nn::VarStore::new(Device::Cpu),
    );
    let net = EppoNet::new(vs.root(), &cfg, &spec).unwrap();
    let target = EppoNet::new(tvs.root(), &cfg, &spec).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let drive = make_batch(&[&walk], &cfg, &spec, shaping, &mut rng, Device::Cpu);
    let cases = [
        (&discrete.net, &discrete.target, &discrete.vs, grid),
        (&net, &target, &vs, drive),
    ];
    for (net, target, vs, mut batch) in cases {
        let run = |batch: &Batch| {
            let (lv, _, lp, ..) = crate::torch_rng::seeded(7, || {
                losses(net, target, batch, 0.0, cfg.exploration.entropy_coef, &cfg).unwrap()
            });
            (lv.double_value(&[]), lp.double_value(&[]))
        };
        let bias = &vs.variables()["novelty_critic.l3.bias"];
        let shift = |by: f64| {
            let _ = tch::no_grad(|| bias.shallow_clone().g_add_scalar_(by));
        };
        let (lv, _) = run(&batch);
        let rewarded = batch
            .novelty_rewards
            .replace(Tensor::zeros_like(batch.novelty_rewards.as_ref().unwrap()));
        assert_ne!(run(&batch).0, lv, "Lv holds the novelty critics' TD loss");
        batch.novelty_rewards = rewarded;
        for (known, moves) in [(1.0, false), (0.0, true)] {
            batch.goal_known = batch.goal_known.ones_like() * known;
            let before = run(&batch).1;
            shift(5.0);
            let after = run(&batch).1;
            shift(-5.0);
            assert_eq!(
                before != after,
                moves,
                "goal known {known}: Lp {before} -> {after}"
            );
        }
    }
}

/// SAC's temperature: the entropy weight rises while the policy's entropy is
/// below its target and falls while above, stays fixed without a target, is
/// logged, and a resumed run goes on from the checkpoint's weight.
#[test]
fn the_entropy_weight_tracks_its_target() {
    assert!(tuned_entropy_coef(0.1, -3.0, -2.0, 0.01) > 0.1);
    assert!(tuned_entropy_coef(0.1, -1.0, -2.0, 0.01) < 0.1);
    assert!((tuned_entropy_coef(0.1, -2.0, -2.0, 0.01) - 0.1).abs() < 1e-12);
    let start = tiny().exploration.entropy_coef;
    // Five discrete actions hold at most ln 5 = 1.61 nats and at least 0.
    let after_updates = |target: Option<f64>| {
        let (mut learner, mut venv) = tiny_learner(3);
        learner.cfg.exploration.target_entropy = target;
        learner.cfg.exploration.entropy_coef_lr = 0.1;
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

    let mut cfg = tiny();
    cfg.exploration.target_entropy = Some(5.0);
    cfg.exploration.entropy_coef_lr = 0.1;
    let (out, report) = train_darkroom(cfg.clone(), "alpha");
    let lines = std::fs::read_to_string(report.run_dir.join("metrics.jsonl")).unwrap();
    let last: serde_json::Value = serde_json::from_str(lines.lines().last().unwrap()).unwrap();
    let logged = last["entropy_coef"].as_f64().unwrap();
    assert!(logged > start, "{logged}");
    let resumed = Learner::resume(cfg, EnvName::DarkRoom, &report.last_checkpoint).unwrap();
    assert!((resumed.entropy_coef - logged).abs() < 1e-12);
    std::fs::remove_dir_all(&out).unwrap();
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
    across.targets.bootstrap_across_episodes = true;
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
    within.targets.bootstrap_across_episodes = false;
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
fn continuous_shapes_and_gradients() {
    let mut cfg = tiny();
    cfg.model.transformer.positions = Positions::Learned;
    let spec = NetSpec {
        obs_dim: 3,
        obs_low: vec![f32::NEG_INFINITY; 3],
        obs_high: vec![f32::INFINITY; 3],
        n_actions: None,
        act_low: vec![-1.0, -1.0],
        act_high: vec![1.0, 1.0],
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
    let (lv, lc, lp, ..) = losses(
        &net,
        &target,
        &batch,
        1.0,
        cfg.exploration.entropy_coef,
        &cfg,
    )
    .unwrap();
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
    let (lv2, lc2, lp2, ..) = losses(
        &net,
        &target,
        &batch,
        1.0,
        cfg.exploration.entropy_coef,
        &cfg,
    )
    .unwrap();
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
