//! Whole runs: acting through the cache against the full forward,
//! determinism, checkpoints and resumes, the overlapped loop.

use super::*;

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
        let run =
            crate::checkpoint::RunDir::create(&out, env.as_str(), "eppo", cfg.run.seed).unwrap();
        let saved = learner.save_checkpoint(&run).unwrap();
        let mut resumed = Learner::resume(cfg.clone(), env, &saved).unwrap();
        assert_eq!(resumed.replay.len(), 2 * cfg.tasks.n_envs, "{env:?}");
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

/// `drop_replay` sheds a finished run's replays: each checkpoint still
/// verifies and resumes, with its weights, counters and an empty replay.
#[test]
fn a_checkpoint_without_its_dropped_replay_resumes_with_the_same_weights() {
    let cfg = tiny();
    let (mut learner, mut venv) = tiny_learner(cfg.run.seed);
    learner.collect(&mut venv).unwrap();
    learner.update().unwrap();
    let out = std::env::temp_dir().join(format!("icrl-eppo-drop-{}", std::process::id()));
    let run = crate::checkpoint::RunDir::create(&out, "darkroom", "eppo", cfg.run.seed).unwrap();
    let saved = learner.save_checkpoint(&run).unwrap();
    let dropped = drop_replay(&run.path).unwrap();
    assert_eq!(dropped.len(), 1);
    assert_eq!(dropped[0].0, saved);
    assert!(dropped[0].1.is_some_and(|bytes| bytes > 0));
    assert!(!saved.join(super::checkpoint::REPLAY_FILE).exists());
    let resumed = Learner::resume(cfg, EnvName::DarkRoom, &saved).unwrap();
    assert_eq!(resumed.replay.len(), 0, "the replay refills");
    assert_eq!(resumed.updates, learner.updates);
    let weights = |l: &Learner| {
        l.vs.variables()
            .into_iter()
            .map(|(name, t)| (name, Vec::<f32>::try_from(t.flatten(0, -1)).unwrap()))
            .collect::<std::collections::BTreeMap<_, _>>()
    };
    assert_eq!(weights(&resumed), weights(&learner));
    assert_eq!(drop_replay(&saved).unwrap(), vec![(saved.clone(), None)]);
    std::fs::remove_dir_all(&out).unwrap();
}

/// Steps one collected trajectory through the KV cache and compares each
/// step's policy with the whole trajectory's forward.
#[test]
fn acting_through_the_cache_matches_the_full_forward() {
    let (mut learner, mut venv) = tiny_learner(3);
    learner.collect(&mut venv).unwrap();
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
        "revisit_rate",
        "search_new_cells",
        "repeat_cost",
        "last_over_budget",
    ] {
        assert!(first.get(key).is_some(), "{key}");
    }
    // Resume to 6 updates from the run folder.
    let mut cfg = tiny();
    cfg.optimisation.total_updates = 6;
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
    other.model.transformer.n_layers = 2;
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

/// A run with novelty critics logs their mean Q, checkpoints them (the
/// manifest says so), loads for evaluation, and refuses a resume without them.
#[test]
fn a_run_with_novelty_critics_checkpoints_and_loads_them() {
    let out = std::env::temp_dir().join(format!("icrl-eppo-novelty-{}", std::process::id()));
    let mut cfg = tiny();
    cfg.novelty.novelty_critic = true;
    cfg.novelty.novelty_bonus = 0.1;
    let opts = PretrainOptions {
        env: EnvName::DarkRoom,
        cfg: cfg.clone(),
        out: out.clone(),
        resume: None,
        progress: false,
    };
    let report = train(&opts).unwrap();
    let lines = std::fs::read_to_string(report.run_dir.join("metrics.jsonl")).unwrap();
    let last: serde_json::Value = serde_json::from_str(lines.lines().last().unwrap()).unwrap();
    assert!(last["losses/novelty_q_mean"].as_f64().unwrap().is_finite());
    let ckpt = report.run_dir.join("checkpoints/step_4");
    let manifest = std::fs::read_to_string(ckpt.join("manifest.json")).unwrap();
    assert!(manifest.contains("novelty_critic"), "{manifest}");
    let agent = EppoAgent::load(&ckpt, Device::Cpu).unwrap();
    assert!(agent.config().novelty.novelty_critic);
    let err = train(&PretrainOptions {
        cfg: {
            let mut c = tiny();
            c.optimisation.total_updates = 6;
            c
        },
        resume: Some(report.run_dir.clone()),
        ..opts
    })
    .err()
    .unwrap()
    .to_string();
    assert!(err.contains("manifest.json"), "{err}");
    std::fs::remove_dir_all(&out).unwrap();
}

/// An overlapped run's metrics and final weights, less what depends on the
/// machine's speed (rates, phase times, CPU shares).
fn overlapped_run(seed: u64, out: &std::path::Path) -> (Vec<serde_json::Value>, Vec<u8>) {
    let mut cfg = tiny();
    cfg.run.seed = seed;
    cfg.run.overlap = true;
    cfg.optimisation.total_updates = 8;
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
    learner.cfg.optimisation.replay_ratio = Some(0.1);
    learner.cfg.optimisation.total_updates = 1000;
    learner.cfg.optimisation.learning_starts = 5;
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
    learner.cfg.optimisation.replay_ratio = None;
    assert_eq!(learner.updates_owed(), 2);
    learner.cfg.optimisation.learning_starts = learner.env_steps + 1;
    assert_eq!(learner.updates_owed(), 0);
    learner.cfg.optimisation.learning_starts = 0;
    learner.cfg.optimisation.total_updates = learner.updates + 1;
    assert_eq!(learner.updates_owed(), 1);
    let mut bad = tiny();
    bad.optimisation.replay_ratio = Some(0.0);
    assert!(refused(&bad, "replay_ratio = 0"));
    let mut bad = tiny();
    bad.run.learner_threads = -1;
    assert!(refused(&bad, "learner_threads = -1"));
}

/// A stop while both sides run: the learner stops after its current update,
/// the actor abandons its round, the checkpoint is written, and the run
/// resumes (overlapped) to its end without a repeated record.
#[test]
fn an_overlapped_stop_checkpoints_and_resumes() {
    tch::set_num_threads(1);
    let out = std::env::temp_dir().join(format!("icrl-eppo-overlap-stop-{}", std::process::id()));
    let mut cfg = tiny();
    cfg.run.overlap = true;
    cfg.optimisation.total_updates = 6;
    cfg.run.checkpoint_every = 100;
    let (done, updates) = stop_after_one_then_resume(&cfg, &out);
    assert_eq!(done, 6);
    assert_eq!(
        updates,
        vec![1, 3, 5, 6],
        "one record per round, none repeated"
    );
    std::fs::remove_dir_all(&out).unwrap();
}

/// Settings that hung a run in the third hostile trial are refused with
/// their bound: `n_step` past the longest trajectory (one update took 40 s
/// at 10^6), `learning_starts` past what the replay keeps (10^12 never
/// reached update 1), a `replay_ratio` too small to reach `total_updates`
/// (10^-300 never owed an update); the presets' values pass.
#[test]
fn settings_that_would_hang_a_run_are_refused_with_their_bound() {
    let longest = tiny().tasks.k_max * tiny().tasks.max_episode_steps;
    let cases = [
        (
            {
                let mut c = tiny();
                c.targets.n_step = 1_000_000;
                c
            },
            format!("n_step = 1000000: at most k_max * max_episode_steps = {longest}"),
        ),
        (
            {
                let mut c = tiny();
                c.optimisation.learning_starts = 1_000_000_000_000;
                c
            },
            "learning_starts = 1000000000000: at most replay_capacity = 1000".into(),
        ),
        (
            {
                let mut c = tiny();
                c.optimisation.replay_ratio = Some(1e-300);
                c
            },
            "replay_ratio = 1e-300: total_updates = 4 would need".into(),
        ),
    ];
    for (cfg, want) in cases {
        let err = cfg.validate().unwrap_err().to_string();
        assert!(err.contains(&want), "{want}: {err}");
    }
    let err = {
        let mut c = tiny();
        c.optimisation.replay_ratio = Some(1e-300);
        c
    }
    .validate()
    .unwrap_err()
    .to_string();
    assert!(err.contains("raise it to at least"), "{err}");
    assert!(
        {
            let mut c = tiny();
            c.targets.n_step = longest;
            c
        }
        .validate()
        .is_ok()
    );
    for env in ["darkroom", "point", "car"] {
        for preset in ["quick", "table1"] {
            let table = crate::presets::preset_table("eppo", env, preset).unwrap();
            let cfg = EppoConfig::from_table(preset, table).unwrap();
            cfg.validate().unwrap();
        }
    }
}

/// What the settings' edge fuzz (`icrl/tests/fuzz_settings.rs`) found, each
/// refused naming the setting and its bound: `ctg_max` near float32's
/// largest (the budget draw panicked on the overflowing range), `adam_eps`
/// below float32's smallest normal number (rounded to 0: a NaN loss at
/// update 2), a 100000-layer transformer (16.8 GB and no first update in
/// 60 s, past a memory estimate of 8 GB), and sizes the memory message did
/// not name as what to lower (`model.d_ff`, `encoder_hidden`, `head_hidden`,
/// `n_critics`); numbers far from 1 are shown as `1e-300`, not 300 digits.
#[test]
fn settings_at_the_edges_the_fuzz_found_are_refused_by_name() {
    let refused = |change: &dyn Fn(&mut EppoConfig), want: &str| {
        let mut c = tiny();
        change(&mut c);
        let err = c.validate().unwrap_err().to_string();
        assert!(err.contains(want), "{want}: {err}");
    };
    refused(
        &|c| c.tasks.ctg_max = f32::MAX,
        "ctg_max = 3.4028234663852886e38: must be a finite number in (0, 1000000]",
    );
    refused(
        &|c| c.tasks.ctg_min = 2e6,
        "ctg_min = 2000000: must be a finite number in [0, 1000000]",
    );
    refused(
        &|c| c.optimisation.adam_eps = 1e-300,
        "adam_eps = 1e-300: must be a finite number in [1.1754943508222875e-38, 1]",
    );
    refused(
        &|c| c.model.transformer.n_layers = 100_000,
        "n_layers = 100000: at most 64",
    );
    let mut edge = tiny();
    edge.tasks.ctg_max = 1e6;
    edge.optimisation.adam_eps = f64::from(f32::MIN_POSITIVE);
    edge.model.transformer.n_layers = crate::model::MOST_LAYERS;
    edge.validate().unwrap();
    let spec = NetSpec::from_spaces(
        &safety_envs::Space::Box {
            low: vec![0.0; 4],
            high: vec![1.0; 4],
        },
        &safety_envs::Space::Discrete { n: 5 },
    )
    .unwrap();
    type Change = fn(&mut EppoConfig);
    let sizes: [(&str, Change); 4] = [
        ("model.d_ff", |c| c.model.transformer.d_ff = i64::MAX),
        ("encoder_hidden", |c| c.model.encoder_hidden = i64::MAX),
        ("head_hidden", |c| c.model.head_hidden = 100_000_000),
        ("n_critics", |c| c.model.n_critics = 1_000_000_000),
    ];
    for (name, change) in sizes {
        let mut c = tiny();
        change(&mut c);
        let err = crate::eppo::memory_estimate(&c, &spec)
            .check_against(Some((1 << 34, 1 << 35)))
            .unwrap_err();
        assert!(err.contains(name), "{name}: {err}");
    }
}

/// A committed checkpoint trained with a retired setting is refused by its
/// name and the last commit that had it (Point's rn1, whose spec holds the
/// statistics `standardise_observations` took), while one trained without
/// it loads: its spec's empty statistics of the time are read past.
#[test]
fn a_committed_checkpoint_loads_or_is_refused_by_a_retired_setting() {
    let ladder = Path::new(env!("CARGO_MANIFEST_DIR")).join("../results/eppo_point_ladder");
    let rn1 = ladder.join("rn1_shown_goal_standardised/checkpoints/step_2945");
    let err = EppoAgent::load(&rn1, Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(
        err.contains("standardise_observations = true")
            && err.contains("9441cf84b763fafdac321359355efe089241a33d"),
        "{err}"
    );
    let pe1 = ladder.join("pe1_scratch_eq7_gate0.7/checkpoints/step_7000");
    let state = std::fs::read_to_string(pe1.join("state.json")).unwrap();
    assert!(
        state.contains("\"obs_mean\": []"),
        "written before the retirement"
    );
    EppoAgent::load(&pe1, Device::Cpu).unwrap();
}
