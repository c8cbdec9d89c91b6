//! The constraint: its measured start, the multiplier (Eq. 7, PID), the
//! penalty forms (hinge, Saute, the excess price and its schedule) and the
//! novelty bonus's budget gates.

use super::*;

/// cell_walk with costs: episode 0 pays 1 at step 1 (budget 1: not over)
/// and 1 at step 2 (over); episode 1 goes over at step 3, then reaches the
/// goal at step 4; episode 2 never pays.
fn overspent_walk() -> (Trajectory, NetSpec) {
    let mut t = cell_walk();
    t.costs = vec![0.0, 1.0, 1.0, 2.0, 0.0, 0.0, 0.0, 0.0];
    t.ctg = vec![1.0, 1.0, 0.0, 1.0, -1.0, 1.0, 1.0, 1.0];
    t.episode_costs = vec![2.0, 2.0, 0.0];
    (t, grid_spec())
}

/// A config whose constraint (`form`; 2 per unit of cost under the forms
/// that charge a price) starts at update 100, the multiplier held at 0;
/// checks nothing is priced before.
fn priced_from_update_100(form: PenaltyForm) -> EppoConfig {
    let mut cfg = tiny();
    cfg.constraint.penalty = form;
    cfg.constraint.lambda_lr = 0.0;
    cfg.constraint.lambda_init = 0.0;
    cfg.constraint.lambda_warmup_updates = 100;
    if matches!(form, PenaltyForm::Saute | PenaltyForm::Excess) {
        cfg.constraint.over_budget_cost_price = 2.0;
    }
    let count = ConstraintStart::default();
    assert_eq!(
        count.started_at(99, cfg.constraint.lambda_warmup_updates, None),
        None
    );
    assert_eq!(
        count.started_at(100, cfg.constraint.lambda_warmup_updates, None),
        Some(100)
    );
    assert_eq!(
        cfg.shaping(99, None).over_budget(),
        None,
        "not before the constraint"
    );
    cfg
}

/// A form that prices the budget in the critics' targets charges the actor
/// no lambda term, even on steps flagged over budget with the budget spent.
fn assert_no_actor_penalty(form: PenaltyForm) {
    let qc = Tensor::from_slice(&[0.5f32, 2.0]).view([1, 2]);
    let ones = qc.ones_like();
    let spent = ones.zeros_like() - 5.0;
    assert_eq!(
        to_vec(&penalised_cost(&qc, &ones, &spent, form)),
        vec![0.0, 0.0],
        "{form:?}"
    );
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
fn with_goal_slots_the_start_waits_for_the_hidden_trajectories_revisits() {
    let mut cfg = tiny_point();
    cfg.goal.goal_in_observation = true;
    cfg.goal.goal_hidden_share = 0.5;
    cfg.constraint.lambda_warmup_updates = 0;
    cfg.constraint.constraint_after_revisit = Some(0.5);
    cfg.constraint.constraint_revisit_rounds = 1;
    cfg.validate().unwrap();
    let mut learner = Learner::new(cfg, EnvName::Point).unwrap();
    let round = |all: f64, hidden: f64| RoundStats {
        revisit_rate: all,
        goal_slots: GoalSlotStats {
            hidden_revisit_rate: hidden,
            ..Default::default()
        },
        ..Default::default()
    };
    // Shown goals driven back to do not start it, nor does a round with no
    // hidden trajectory that found its goal (NaN: not counted).
    learner.observe_round(&round(0.9, 0.2));
    learner.observe_round(&round(0.9, f64::NAN));
    assert!(!learner.constrained());
    learner.observe_round(&round(0.1, 0.6));
    assert!(learner.constrained(), "the hidden ones' revisits start it");
}

#[test]
fn the_multiplier_waits_for_the_measured_start_and_the_checkpoint_keeps_it() {
    let mut cfg = tiny();
    cfg.constraint.lambda_init = 0.5;
    cfg.constraint.lambda_lr = 0.1;
    cfg.constraint.lambda_max = 10.0;
    cfg.constraint.lambda_warmup_updates = 0;
    cfg.constraint.constraint_after_revisit = Some(0.5);
    cfg.constraint.constraint_revisit_rounds = 1;
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
    let run = crate::checkpoint::RunDir::create(&out, "darkroom", "eppo", cfg.run.seed).unwrap();
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
        EppoConfig::apply_sets(&mut table, &[format!("{key}={value}")]).unwrap();
        let cfg = EppoConfig::from_table("bad", table).unwrap();
        let err = cfg.validate().unwrap_err().to_string();
        assert!(err.contains(says), "{err}");
    }
}

#[test]
fn saute_replaces_the_reward_once_the_episode_has_spent_its_budget() {
    let (t, spec) = overspent_walk();
    let mut cfg = priced_from_update_100(PenaltyForm::Saute);
    cfg.validate().unwrap();
    assert_eq!(
        cfg.shaping(100, Some(100)).over_budget(),
        Some(OverBudget {
            replaced_reward: Some(-0.1),
            cost_price: 2.0,
            pays_novelty: false
        })
    );
    let over_budget = |reward: f32, cost_price: f32| Shaping {
        novelty: 0.0,
        budget: BudgetInTargets::OverBudget(OverBudget {
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
    let scale = cfg.targets.reward_scale as f32;
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
    cfg.constraint.penalty = PenaltyForm::Hindsight;
    assert_eq!(cfg.shaping(100, Some(100)).over_budget(), None);
    assert_no_actor_penalty(PenaltyForm::Saute);
}

#[test]
fn saute_refuses_a_multiplier_that_moves() {
    let mut cfg = tiny();
    cfg.constraint.penalty = PenaltyForm::Saute;
    cfg.constraint.lambda_init = 0.0;
    cfg.constraint.lambda_lr = 0.001;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(err.contains("lambda_lr = 0"), "{err}");
    cfg.constraint.lambda_lr = 0.0;
    cfg.constraint.over_budget_cost_price = -1.0;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(err.contains("over_budget_cost_price"), "{err}");
    cfg.constraint.over_budget_cost_price = 1.0;
    cfg.validate().unwrap();
}

#[test]
fn excess_price_charges_each_unit_past_the_budget_and_keeps_the_goal() {
    let (t, spec) = overspent_walk();
    let mut cfg = priced_from_update_100(PenaltyForm::Excess);
    cfg.validate().unwrap();
    let shaping = cfg.shaping(100, Some(100));
    assert_eq!(
        shaping.over_budget(),
        Some(OverBudget {
            replaced_reward: None,
            cost_price: 2.0,
            pays_novelty: true
        })
    );
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let batch = make_batch(&[&t], &cfg, &spec, shaping, &mut rng, Device::Cpu);
    let scale = cfg.targets.reward_scale as f32;
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
    assert_no_actor_penalty(PenaltyForm::Excess);
    // Refused without a price, or with a multiplier that moves.
    cfg.constraint.over_budget_cost_price = 0.0;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(err.contains("over_budget_cost_price > 0"), "{err}");
    cfg.constraint.over_budget_cost_price = 1.0;
    cfg.constraint.lambda_lr = 0.01;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(
        err.contains("penalty = \"excess\"") && err.contains("lambda_lr = 0"),
        "{err}"
    );
}

#[test]
fn termination_ends_the_critics_value_at_the_step_that_overspends() {
    let (t, spec) = overspent_walk();
    let mut cfg = priced_from_update_100(PenaltyForm::Terminate);
    cfg.validate().unwrap();
    assert!(!cfg.shaping(99, None).ends_value());
    let shaping = cfg.shaping(100, Some(100));
    assert!(shaping.ends_value());
    assert_eq!(shaping.over_budget(), None, "no price per unit");
    let batch = |shaping: Shaping| {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        make_batch(&[&t], &cfg, &spec, shaping, &mut rng, Device::Cpu)
    };
    let (plain, ended) = (batch(cfg.shaping(99, None)), batch(shaping));
    assert_eq!(to_vec(&plain.tokens), to_vec(&ended.tokens));
    let scale = cfg.targets.reward_scale as f32;
    let unscaled: Vec<f32> = to_vec(&ended.rewards).iter().map(|r| r / scale).collect();
    // Rewards as paid: the goal reached already over budget (step 4) keeps
    // its reward.
    assert_eq!(unscaled, vec![0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]);
    // Step 2 (episode 0) and step 3 (episode 1) take their episodes past the
    // budget: the value ends there.
    let (before, after) = (to_vec(&plain.bootstrap), to_vec(&ended.bootstrap));
    for step in 0..t.len() {
        let expected = if step == 2 || step == 3 {
            0.0
        } else {
            before[step]
        };
        assert_eq!(after[step], expected, "step {step}");
    }
    assert_eq!(before[2], 1.0, "the walk bootstraps there unconstrained");
    assert_eq!(to_vec(&ended.costs), t.costs, "costs as paid");
    assert_eq!(to_vec(&ended.cost_bootstrap), to_vec(&plain.cost_bootstrap));
    let reading = Learner::new(cfg.clone(), EnvName::DarkRoom)
        .unwrap()
        .penalty_reading();
    assert_eq!(reading, "overspending ends the value");
    // With a multiplier the actor also pays Eq. (7)'s lambda v_e Qc
    // (`violation_flag_gates_the_cost_penalty`), and the reading shows it.
    cfg.constraint.lambda_lr = 0.01;
    cfg.constraint.lambda_max = 1.0;
    cfg.validate().unwrap();
    let reading = Learner::new(cfg.clone(), EnvName::DarkRoom)
        .unwrap()
        .penalty_reading();
    assert_eq!(reading, "overspending ends the value, lambda 0.0000");
    cfg.constraint.over_budget_cost_price = 1.0;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(err.contains("over_budget_cost_price = 1"), "{err}");
}

#[test]
fn the_price_schedule_counts_updates_from_the_constraints_start() {
    let (t, spec) = overspent_walk();
    let mut cfg = priced_from_update_100(PenaltyForm::Excess);
    let mut table = crate::presets::preset_table("eppo", "darkroom", "quick").unwrap();
    let schedule =
        "over_budget_price_schedule=[{ after = 50, price = 3.0 }, { after = 80, price = 5 }]";
    EppoConfig::apply_sets(&mut table, &[schedule.to_string()]).unwrap();
    let parsed = EppoConfig::from_table("schedule", table).unwrap();
    cfg.constraint.over_budget_price_schedule = parsed.constraint.over_budget_price_schedule;
    assert_eq!(
        cfg.constraint.over_budget_price_schedule,
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
            .over_budget()
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
    let scale = cfg.targets.reward_scale as f32;
    let rewards: Vec<f32> = to_vec(&batch.rewards).iter().map(|r| r / scale).collect();
    assert_eq!(rewards, vec![0.0, 0.0, -5.0, -10.0, 1.0, 0.0, 0.0, 0.0]);
    // The learner reads it from its measured start and reports it.
    cfg.constraint.constraint_after_revisit = Some(0.5);
    cfg.constraint.constraint_revisit_rounds = 1;
    cfg.constraint.lambda_warmup_updates = 0;
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
        &|c| c.constraint.over_budget_price_schedule.reverse(),
        "must rise from one change to the next",
    );
    refused(
        &|c| c.constraint.over_budget_price_schedule[1].price = f64::NAN,
        "price = NaN after 80 updates",
    );
    refused(
        &|c| {
            c.constraint.penalty = PenaltyForm::Hinge;
            c.constraint.over_budget_cost_price = 0.0;
        },
        "over_budget_price_schedule changes the price",
    );
}

#[test]
fn the_price_schedule_steps_at_each_change() {
    let mut cfg = priced_from_update_100(PenaltyForm::Excess);
    cfg.constraint.over_budget_price_schedule = vec![
        PriceChange {
            after: 50,
            price: 3.0,
        },
        PriceChange {
            after: 80,
            price: 6.0,
        },
    ];
    cfg.validate().unwrap();
    // 2.0 from the start, 3.0 from 50 updates past it, 6.0 from 80 on.
    for (updates, price) in [
        (100, 2.0),
        (149, 2.0),
        (150, 3.0),
        (179, 3.0),
        (180, 6.0),
        (5000, 6.0),
    ] {
        let got = cfg
            .shaping(updates, Some(100))
            .over_budget()
            .map(|o| o.cost_price)
            .unwrap();
        assert_eq!(got, price as f32, "{updates}");
    }
    // A change at the start itself applies from the start.
    cfg.constraint.over_budget_price_schedule[0].after = 0;
    assert_eq!(cfg.over_budget_price(0), 3.0);
}

#[test]
fn novelty_within_budget_withholds_the_bonus_only_past_the_budget() {
    let (t, spec) = overspent_walk();
    let rewards_at = |updates: u64, within: bool| {
        let mut cfg = priced_from_update_100(PenaltyForm::Excess);
        cfg.novelty.novelty_bonus = 0.1;
        if within {
            cfg.novelty.novelty_budget = NoveltyBudget::WithinBudget;
        }
        cfg.validate().unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let shaping = cfg.shaping(
            updates,
            (updates >= cfg.constraint.lambda_warmup_updates).then_some(100),
        );
        let batch = make_batch(&[&t], &cfg, &spec, shaping, &mut rng, Device::Cpu);
        let scale = cfg.targets.reward_scale as f32;
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
    cfg.novelty.novelty_budget = NoveltyBudget::WithinBudget;
    cfg.novelty.novelty_bonus = 0.0;
    let err = cfg.validate().unwrap_err().to_string();
    assert!(err.contains("novelty_budget"), "{err}");
    cfg.novelty.novelty_bonus = 0.1;
    cfg.constraint.penalty = PenaltyForm::Hindsight;
    cfg.constraint.over_budget_cost_price = 0.0;
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
        cfg.novelty.novelty_bonus = 0.1;
        cfg.novelty.novelty_budget = form;
        cfg.validate().unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let batch = make_batch(
            &[t],
            &cfg,
            &spec,
            cfg.shaping(
                updates,
                (updates >= cfg.constraint.lambda_warmup_updates).then_some(100),
            ),
            &mut rng,
            Device::Cpu,
        );
        let scale = cfg.targets.reward_scale as f32;
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
    cfg.novelty.novelty_budget = NoveltyBudget::RemainingShare;
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
            .novelty
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
    // The learner's multiplier takes the same step, and none on an empty batch.
    let mut m = Multiplier::new(0.2);
    m.update(&[3.0, -1.0, 4.0], 0.1, 1.5);
    assert_eq!(m.lambda, lambda_update(0.2, &[3.0, -1.0, 4.0], 0.1, 1.5));
    m.update(&[], 0.1, 1.5);
    assert_eq!(m.lambda, lambda_update(0.2, &[3.0, -1.0, 4.0], 0.1, 1.5));
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

/// A batch collected by a tiny SafeDarkRoom learner whose actor pays the
/// cost penalty in `form`.
fn penalty_probe(form: PenaltyForm) -> (Learner, Batch) {
    let (mut learner, mut venv) = tiny_learner(2);
    learner.cfg.constraint.penalty = form;
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
            learner.cfg.exploration.entropy_coef,
            &learner.cfg,
        )
    })
    .unwrap();
    lp.double_value(&[])
}

/// Algorithm 1's actor penalty, under `hindsight` and under the termination
/// given a multiplier.
#[test]
fn violation_flag_gates_the_cost_penalty() {
    for form in [PenaltyForm::Hindsight, PenaltyForm::Terminate] {
        let (learner, mut batch) = penalty_probe(form);
        let policy_loss = |batch: &Batch, lambda: f64| policy_loss_at(&learner, batch, lambda);
        batch.violated = batch.valid.zeros_like();
        let (clean_0, clean_5) = (policy_loss(&batch, 0.0), policy_loss(&batch, 5.0));
        assert!(
            (clean_0 - clean_5).abs() < 1e-4,
            "{form:?}: no violation, lambda has no effect"
        );
        batch.violated = batch.valid.ones_like();
        let (viol_0, viol_5) = (policy_loss(&batch, 0.0), policy_loss(&batch, 5.0));
        assert!((viol_0 - clean_0).abs() < 1e-4, "{form:?}");
        assert!(
            (viol_5 - viol_0).abs() > 1e-4,
            "{form:?}: violated episodes pay lambda * Qc"
        );
    }
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

/// The retired multiplier settings (`config::RETIRED`): a committed config
/// that holds them where they did nothing loads as it did, one that used
/// them is refused by name with the commit that had them, and no committed
/// config is refused for them otherwise.
#[test]
fn configs_from_before_the_retirement_load_or_are_refused_by_name() {
    use super::config::{RETIRED, drop_retired};
    let results = Path::new(env!("CARGO_MANIFEST_DIR")).join("../results");
    let table = |rel: &str| -> toml::Table {
        std::fs::read_to_string(results.join(rel))
            .unwrap()
            .parse()
            .unwrap()
    };
    let pe1 = table("eppo_point_ladder/pe1_scratch_eq7_gate0.7/config.toml");
    assert!(pe1.contains_key("lambda_kp") && pe1.contains_key("violation_signal"));
    let loaded = EppoConfig::from_table("pe1", pe1.clone()).unwrap();
    assert_eq!(loaded.constraint.lambda_max, 1.0);
    let mut stripped = pe1.clone();
    for (key, _, _) in RETIRED {
        stripped.remove(key);
    }
    EppoConfig::migrate(&mut stripped).unwrap();
    let plain: EppoConfig = crate::presets::resolve("pe1", stripped).unwrap();
    assert_eq!(
        format!("{loaded:?}"),
        format!("{plain:?}"),
        "the same config"
    );
    for (key, value) in [
        ("lambda_kp", "0.5"),
        ("violation_signal", "\"late_rate\""),
        ("eps_after_success", "0.05"),
        ("scripted_share", "0.5"),
        ("novelty_through_success", "true"),
        ("saute_unsafe_reward", "0.0"),
        ("repeat_cost_radius", "0.4"),
        ("termination_reward", "-1.0"),
    ] {
        let mut used = pe1.clone();
        EppoConfig::apply_sets(&mut used, &[format!("{key}={value}")]).unwrap();
        let err = EppoConfig::from_table("pe1", used).unwrap_err().to_string();
        let (_, _, commit) = RETIRED.iter().find(|(k, _, _)| *k == key).unwrap();
        assert!(err.contains(key) && err.contains(commit), "{err}");
    }
    // In a section as at the top: dropped where inert, refused by name where not.
    for (value, refused) in [("0.0", false), ("0.5", true)] {
        let mut sectioned = pe1.clone();
        sectioned.remove("lambda_kp");
        EppoConfig::apply_sets(&mut sectioned, &[format!("constraint.lambda_kp={value}")]).unwrap();
        let got = EppoConfig::from_table("pe1", sectioned);
        assert_eq!(got.is_err(), refused, "{got:?}");
        if let Err(e) = got {
            assert!(e.to_string().contains("lambda_kp = 0.5"), "{e}");
        }
    }
    let pt2 = table("eppo_point_ladder/pt2_ps8_terminate_reward-1/config.toml");
    let err = EppoConfig::from_table("pt2", pt2).unwrap_err().to_string();
    assert!(err.contains("termination_reward = -1"), "{err}");
    let pe3 = table(
        "eppo_point_ladder/pe3_preset_hazards_shown_then_hidden/point__eppo__0__20261207T063452/config.toml",
    );
    let err = EppoConfig::from_table("pe3", pe3).unwrap_err().to_string();
    assert!(err.contains("hazards_in_observation = true"), "{err}");
    let late = table("eppo_darkroom_budget/lr1_late_rate/config.toml");
    let err = EppoConfig::from_table("lr1", late).unwrap_err().to_string();
    assert!(err.contains("violation_signal = \"late_rate\""), "{err}");
    // Every committed EPPO config loads, or is refused by a retired
    // setting's name, or fails for a reason that is not one of them (an
    // older format): never as an unknown retired field.
    let mut configs = Vec::new();
    let mut dirs = vec![results.clone()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap().flatten() {
            let path = entry.path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.file_name().is_some_and(|n| n == "config.toml") {
                configs.push(path);
            }
        }
    }
    let mut loaded = 0;
    for path in &configs {
        let Ok(t) = std::fs::read_to_string(path)
            .unwrap()
            .parse::<toml::Table>()
        else {
            continue;
        };
        if EppoConfig::setting(&t, "n_critics").is_none() {
            continue; // not an EPPO config
        }
        match EppoConfig::from_table("c", t.clone()) {
            Ok(_) => loaded += 1,
            Err(e) => {
                let e = e.to_string();
                let named = RETIRED
                    .iter()
                    .any(|(k, _, _)| e.contains(&format!("{k} = ")));
                let mut without = t.clone();
                assert_eq!(named, drop_retired(&mut without).is_err(), "{e}");
                assert!(
                    named || RETIRED.iter().all(|(k, _, _)| !e.contains(k)),
                    "{}: {e}",
                    path.display()
                );
            }
        }
    }
    assert!(loaded > 100, "{loaded} of {} configs load", configs.len());
}

/// Eq. (6)'s per-episode multipliers: each lambda_k moves by the mean excess
/// of its own episode k over the trajectories that hold one, and is charged
/// on that episode's steps only; refused outside the hindsight form; kept by
/// the checkpoint.
#[test]
fn each_per_episode_multiplier_moves_on_its_own_episode_only() {
    let mut m = Multiplier::per_episode(0.5, 3);
    // Trajectory 0 overspends in episode 0 only; trajectory 1 holds two
    // episodes, over budget in its first.
    m.update_per_episode(&[vec![3.0, -1.0, -1.0], vec![1.0, -1.0]], 0.1, 1.0);
    let want = [0.5 + 0.1 * 2.0, 0.5 - 0.1, 0.5 - 0.1];
    for (got, want) in m.per_episode.iter().zip(want) {
        assert!((got - want).abs() < 1e-6, "{:?}", m.per_episode);
    }
    assert!((m.lambda - want.iter().sum::<f64>() / 3.0).abs() < 1e-6);
    // Capped and floored like Eq. (7).
    m.update_per_episode(&[vec![100.0, -100.0, 0.0]], 0.1, 1.0);
    assert_eq!(m.per_episode[..2], [1.0, 0.0]);
    // Each step is charged its own episode's multiplier.
    let episode = Tensor::from_slice(&[0i64, 0, 1, 2, 1, 0]).view([2, 3]);
    let per_step: Vec<f32> = to_vec(&m.per_step(&episode));
    let k2 = m.per_episode[2] as f32;
    assert_eq!(per_step, vec![1.0, 1.0, 0.0, k2, 0.0, 1.0]);

    let mut cfg = tiny();
    cfg.constraint.per_episode_multipliers = true;
    cfg.constraint.lambda_lr = 0.1;
    cfg.constraint.lambda_max = 10.0;
    cfg.constraint.lambda_warmup_updates = 0;
    cfg.validate().unwrap();
    let mut wrong = cfg.clone();
    wrong.constraint.penalty = PenaltyForm::Hinge;
    assert!(refused(&wrong, "per_episode_multipliers"));
    // A learner takes one step per episode index and keeps them.
    let (_, mut venv) = tiny_learner(0);
    let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    assert_eq!(learner.multiplier.per_episode, vec![0.0; cfg.tasks.k_max]);
    learner.collect(&mut venv).unwrap();
    learner.update().unwrap();
    let out = std::env::temp_dir().join(format!("icrl-eppo-per-episode-{}", std::process::id()));
    let run = crate::checkpoint::RunDir::create(&out, "darkroom", "eppo", cfg.run.seed).unwrap();
    let saved = learner.save_checkpoint(&run).unwrap();
    let resumed = Learner::resume(cfg, EnvName::DarkRoom, &saved).unwrap();
    assert_eq!(resumed.multiplier, learner.multiplier);
    std::fs::remove_dir_all(&out).unwrap();
}
