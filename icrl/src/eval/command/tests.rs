use super::*;

fn options(out: PathBuf) -> EvalOptions {
    EvalOptions {
        env: EnvName::DarkRoom,
        tasks: 3,
        episodes: Some(4),
        budgets: None,
        n_budgets: 3,
        rtg: 1.0,
        sweep: true,
        random: true,
        render: None,
        out,
        eval_seed: 0,
        batch: 64,
        threads: 1,
        greedy: false,
        max_episode_steps: None,
        progress: false,
        command: "test".into(),
        seed_torch: false,
        in_distribution: false,
        force: false,
    }
}

#[test]
fn labels_name_checkpoints_of_one_method_apart() {
    let probe = make_env(EnvName::DarkRoom, &EnvOptions::default()).unwrap();
    // Naming reads only the method and the label.
    let agent = |label: Option<&str>| LoadedAgent {
        method: Method::Ad,
        label: label.map(String::from),
        ..LoadedAgent::random(probe.action_space(), 0)
    };
    assert_eq!(
        (agent(None).name(), agent(None).stem()),
        ("AD".into(), "ad".into())
    );
    let a = agent(Some("AD 25% of tasks"));
    assert_eq!(
        (a.name(), a.stem()),
        ("AD 25% of tasks".into(), "ad_ad-25--of-tasks".into())
    );
    assert_ne!(agent(Some("AD 50%")).stem(), agent(Some("AD 100%")).stem());
}

#[test]
fn random_policy_evaluation_writes_every_file() {
    let dir = std::env::temp_dir().join(format!("icrl-eval-cmd-{}", std::process::id()));
    let out = run(Vec::new(), &options(dir.clone())).unwrap();
    for name in [
        "random_darkroom.json",
        "random_darkroom_episodes.csv",
        "random_darkroom_conditions.csv",
        "random_darkroom_sweep.json",
        "random_darkroom_sweep_conditions.csv",
        "figure1_darkroom.png",
        "figure1_darkroom.svg",
        "figure2_darkroom.png",
        "figure2_darkroom.svg",
    ] {
        let p = dir.join(name);
        assert!(out.files.contains(&p), "{name} not reported");
        assert!(
            std::fs::metadata(&p).unwrap().len() > 100,
            "{name} is empty"
        );
    }
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("random_darkroom_sweep.json")).unwrap())
            .unwrap();
    assert_eq!(json["result"]["conditions"].as_array().unwrap().len(), 15);
    assert_eq!(json["episodes"], 4);
    let csv = std::fs::read_to_string(dir.join("random_darkroom_episodes.csv")).unwrap();
    assert_eq!(csv.lines().filter(|l| !l.starts_with('#')).count(), 1 + 4);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn reports_of_two_environments_are_redrawn_side_by_side() {
    let dir = std::env::temp_dir().join(format!("icrl-eval-replot-{}", std::process::id()));
    let mut a = options(dir.join("darkroom"));
    a.sweep = false;
    run(Vec::new(), &a).unwrap();
    let mut b = options(dir.join("point"));
    b.env = EnvName::Point;
    b.episodes = Some(2);
    b.sweep = false;
    run(Vec::new(), &b).unwrap();
    let out = replot(
        &[dir.join("darkroom"), dir.join("point")],
        &[],
        &dir.join("all"),
        false,
    )
    .unwrap();
    assert_eq!(out.files.len(), 2, "figure 1 only: no sweeps");
    assert!(
        out.lines[0].contains("2 reports (2 environments)"),
        "{:?}",
        out.lines
    );
    assert!(
        std::fs::metadata(dir.join("all/figure1_all.png"))
            .unwrap()
            .len()
            > 1000
    );
    let e = replot(&[dir.join("all")], &[], &dir.join("x"), false)
        .unwrap_err()
        .to_string();
    assert!(e.contains("no eval reports"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn labelled_folders_are_pooled_into_one_curve_each() {
    let dir = std::env::temp_dir().join(format!("icrl-eval-pooled-{}", std::process::id()));
    // Two evaluation seeds of one "run": the random policy's reports, a copy
    // of each relabelled as EPPO's so that the folder holds a method's curve.
    for seed in [1u64, 2] {
        let mut o = options(dir.join(format!("runs/eval_seed{seed}")));
        o.sweep = false;
        o.eval_seed = seed;
        run(Vec::new(), &o).unwrap();
        let folder = dir.join(format!("runs/eval_seed{seed}"));
        let mut report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(folder.join("random_darkroom.json")).unwrap())
                .unwrap();
        report["method"] = "Eppo".into();
        std::fs::write(
            folder.join("eppo_run_darkroom.json"),
            serde_json::to_vec(&report).unwrap(),
        )
        .unwrap();
    }
    let runs = [dir.join("runs")];
    let out = replot(&runs, &["ablation".into()], &dir.join("fig"), false).unwrap();
    assert!(
        out.lines[0].starts_with("ablation: 2 reports pooled"),
        "{:?}",
        out.lines
    );
    assert_eq!(out.files.len(), 2, "figure 1, PNG and SVG");
    assert!(
        std::fs::metadata(dir.join("fig/figure1_all.svg"))
            .unwrap()
            .len()
            > 1000
    );

    // One label over two folders: one curve of both folders' reports.
    let both = [dir.join("runs/eval_seed1"), dir.join("runs/eval_seed2")];
    let labels = ["ablation".to_string(), "ablation".to_string()];
    let out = replot(&both, &labels, &dir.join("fig"), true).unwrap();
    assert_eq!(out.lines.len(), 1, "{:?}", out.lines);
    assert!(
        out.lines[0].starts_with("ablation: 2 reports pooled from "),
        "{:?}",
        out.lines
    );
    let e = replot(&runs, &["a".into(), "b".into()], &dir.join("x"), false)
        .unwrap_err()
        .to_string();
    assert!(e.contains("2 --label for 1 --from"), "{e}");
    std::fs::remove_file(dir.join("runs/eval_seed1/eppo_run_darkroom.json")).unwrap();
    std::fs::remove_file(dir.join("runs/eval_seed2/eppo_run_darkroom.json")).unwrap();
    let e = replot(&runs, &["a".into()], &dir.join("x"), false)
        .unwrap_err()
        .to_string();
    assert!(e.contains("no EPPO or AD eval report"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn eppo_sweep_stays_inside_the_pretrained_budget_range() {
    let dir = std::env::temp_dir().join(format!("icrl-eval-cmd-sweep-{}", std::process::id()));
    let opts = options(dir);
    let budgets = |range: BudgetRange| -> Vec<f32> {
        conditions(Method::Eppo, true, &opts, range)
            .unwrap()
            .into_iter()
            .map(|c| match c {
                Conditioning::Budget { ctg } => ctg,
                other => panic!("{other:?}"),
            })
            .collect()
    };
    let paper = env_defaults(EnvName::DarkRoom).budget_range;
    assert_eq!(budgets(paper), grid(1.0, 15.0, 1.0), "the paper's grid");
    let narrow = BudgetRange {
        low: 2.0,
        high: 20.0,
    };
    assert_eq!(
        sweep_grid(&env_defaults(EnvName::Point).budget_grid, narrow),
        [2.0, 4.25, 6.5, 8.75, 11.0, 13.25, 15.5, 17.75, 20.0],
        "Point's quick range holds only 10, 15, 20 of the paper's grid"
    );
}

#[test]
fn out_of_range_budgets_and_empty_task_sets_are_refused() {
    let dir = std::env::temp_dir().join(format!("icrl-eval-cmd-bad-{}", std::process::id()));
    let mut opts = options(dir.clone());
    opts.budgets = Some(vec![5.0, 20.0]);
    let range = env_defaults(EnvName::DarkRoom).budget_range;
    let e = conditions(Method::Eppo, false, &opts, range)
        .unwrap_err()
        .to_string();
    assert!(e.contains("budget 20 is outside the range [1, 15]"), "{e}");
    opts.budgets = Some(vec![]);
    let e = conditions(Method::Eppo, false, &opts, range)
        .unwrap_err()
        .to_string();
    assert!(e.contains("no budgets"), "{e}");
    let mut opts = options(dir.clone());
    opts.tasks = 0;
    let e = run(Vec::new(), &opts).unwrap_err().to_string();
    assert!(e.contains("task set is empty"), "{e}");
    // Hours of work with no end in sight: refused before anything runs.
    let mut opts = options(dir.clone());
    (opts.tasks, opts.episodes, opts.n_budgets) = (2, Some(2), 10_000_000);
    let e = run(Vec::new(), &opts).unwrap_err().to_string();
    assert!(
        e.contains("this evaluation is 40000000 episodes per method (10000000 budgets x 2 tasks x 2 episodes)"),
        "{e}"
    );
    let mut opts = options(dir);
    opts.random = false;
    let e = run(Vec::new(), &opts).unwrap_err().to_string();
    assert!(e.contains("nothing to evaluate"), "{e}");
}
