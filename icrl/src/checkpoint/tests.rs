use super::*;
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

/// The newest `n` checkpoints, no history.
fn keep(n: usize) -> Retention {
    Retention {
        newest: n,
        every: 0,
    }
}

/// A checkpoint of one small file at `step`, pruned to what `keep` retains.
fn write_small(run: &RunDir, step: u64, keep: Retention) -> Result<PathBuf, CheckpointError> {
    let write = |d: &Path| fs::write(d.join("w.bin"), [1u8; 8]).map_err(io(d));
    run.write_checkpoint(
        step,
        "test",
        "darkroom",
        None,
        serde_json::json!({}),
        keep,
        write,
    )
}

#[test]
fn a_checkpoint_path_the_file_system_refuses_fails_before_training() {
    let base = std::env::temp_dir().join(format!("icrl-ckpt-probe-{}", std::process::id()));
    let run = RunDir::create_named(&base, "run").unwrap();
    run.probe_checkpoint_path(7000).unwrap();
    assert!(
        !run.path.join("checkpoints/.tmp_step_7000").exists(),
        "the probe leaves nothing behind"
    );
    // A run folder whose checkpoints would pass the 4,095-byte path limit:
    // refused at the probe, naming the path, not after training.
    let mut root = base.join("deep");
    while root.as_os_str().len() < 4064 {
        let room = 4064 - root.as_os_str().len() - 1;
        root.push("x".repeat(room.clamp(1, 200)));
    }
    let deep = RunDir::create_named(&root, "run").unwrap();
    let e = deep.probe_checkpoint_path(7000).unwrap_err().to_string();
    assert!(
        e.contains("optimizer.safetensors") && e.contains("too long"),
        "{e}"
    );
    fs::remove_dir_all(base).unwrap();
}

#[test]
fn a_failed_checkpoint_leaves_nothing_and_names_the_last_good_one() {
    let base = std::env::temp_dir().join(format!("icrl-ckpt-failed-{}", std::process::id()));
    let _ = fs::remove_dir_all(&base);
    let run = RunDir::create_named(&base, "run").unwrap();
    let good = write_small(&run, 10, keep(2)).unwrap();
    let e = run
        .write_checkpoint(
            20,
            "test",
            "darkroom",
            None,
            serde_json::json!({}),
            keep(2),
            |d| {
                fs::write(d.join("w.bin"), [1u8; 8]).map_err(io(d))?;
                Err(CheckpointError::Invalid {
                    path: d.join("optimizer.safetensors"),
                    problem: "No space left on device (os error 28)".into(),
                    fix: "check the disk".into(),
                })
            },
        )
        .unwrap_err()
        .to_string();
    assert!(e.contains("step_20: writing this checkpoint failed"), "{e}");
    assert!(e.contains("No space left on device"), "{e}");
    assert!(
        e.contains(&format!("The last good checkpoint is {}", good.display())),
        "{e}"
    );
    assert!(
        !run.path.join("checkpoints/.tmp_step_20").exists(),
        "nothing left behind"
    );
    assert!(!run.path.join("checkpoints/step_20").exists());
    // Room for the checkpoints still to come is checked before training.
    run.check_room(1 << 20, keep(2), 9900, 100).unwrap();
    let e = run
        .check_room(u64::MAX / 4, keep(2), 9900, 100)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("free, but 2 more checkpoints of about") && e.contains("keep_checkpoints = 2"),
        "{e}"
    );
    let e = run
        .check_room(u64::MAX / 4, keep(0), 0, 100)
        .unwrap_err()
        .to_string();
    assert!(e.contains("1 more checkpoint of about"), "{e}");
    fs::remove_dir_all(base).unwrap();
}

#[test]
fn atomic_checkpoint_and_truncation_detected() {
    let root = std::env::temp_dir().join(format!("icrl-ckpt-{}", std::process::id()));
    let run = RunDir::create(&root, "darkroom", "test", 3).unwrap();
    let model = serde_json::json!({"d_model": 8});
    for step in [5, 10, 15] {
        run.write_checkpoint(
            step,
            "test",
            "darkroom",
            None,
            model.clone(),
            keep(2),
            |dir| fs::write(dir.join("w.bin"), vec![1u8; 100]).map_err(io(dir)),
        )
        .unwrap();
    }
    let latest = run.latest_checkpoint().unwrap().unwrap();
    assert!(latest.ends_with("step_15"));
    assert!(!run.path.join("checkpoints/step_5").exists(), "pruned to 2");
    let m = read_manifest(&latest).unwrap();
    m.check_compatible(&latest, "test", "darkroom", None, &model)
        .unwrap();
    let err = m
        .check_compatible(&latest, "test", "point", None, &model)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("\"darkroom\"") && err.contains("\"point\""),
        "{err}"
    );
    let other = serde_json::json!({"d_model": 16});
    let err = m
        .check_compatible(&latest, "test", "darkroom", None, &other)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("model.d_model = 8") && err.contains("model.d_model = 16"),
        "{err}"
    );
    // Truncate a file: the error names it.
    fs::write(latest.join("w.bin"), vec![1u8; 10]).unwrap();
    let err = read_manifest(&latest).unwrap_err().to_string();
    assert!(err.contains("w.bin") && err.contains("10 bytes"), "{err}");
    let (_, ckpt) = RunDir::resolve_resume(&run.path).unwrap();
    assert_eq!(ckpt, latest);
    assert!(RunDir::resolve_resume(&root).is_err());
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn macro_action_is_recorded_checked_and_old_checkpoints_refused() {
    let root = std::env::temp_dir().join(format!("icrl-ckpt-macro-{}", std::process::id()));
    let run = RunDir::create(&root, "point", "test", 1).unwrap();
    let model = serde_json::json!({"d_model": 8});
    let dir = run
        .write_checkpoint(
            1,
            "test",
            "point",
            Some(50),
            model.clone(),
            keep(0),
            |dir| fs::write(dir.join("w.bin"), [0u8; 4]).map_err(io(dir)),
        )
        .unwrap();
    let m = read_manifest(&dir).unwrap();
    assert_eq!(m.physics_steps_per_action, Some(50));
    m.check_compatible(&dir, "test", "point", Some(50), &model)
        .unwrap();
    let err = m
        .check_compatible(&dir, "test", "point", Some(5), &model)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("physics steps per agent action") && err.contains("\"50\""),
        "{err}"
    );
    // A manifest from before the macro action was recorded: the field is
    // absent. Point and Car refuse it, saying why; DarkRoom has no physics.
    let path = dir.join(MANIFEST);
    let mut json: serde_json::Value =
        serde_json::from_str(&fs::read_to_string(&path).unwrap()).unwrap();
    json.as_object_mut()
        .unwrap()
        .remove("physics_steps_per_action");
    fs::write(&path, json.to_string()).unwrap();
    let err = read_manifest(&dir).unwrap_err().to_string();
    assert!(
        err.contains("does not record its macro action")
            && err.contains("5 physics steps")
            && err.contains("retrain"),
        "{err}"
    );
    json["env"] = "darkroom".into();
    fs::write(&path, json.to_string()).unwrap();
    assert_eq!(read_manifest(&dir).unwrap().physics_steps_per_action, None);
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn a_dropped_file_leaves_a_checkpoint_that_verifies_and_a_damaged_one_is_left_alone() {
    let root = std::env::temp_dir().join(format!("icrl-ckpt-drop-{}", std::process::id()));
    let run = RunDir::create(&root, "darkroom", "test", 3).unwrap();
    let write = |updates| {
        run.write_checkpoint(
            updates,
            "test",
            "darkroom",
            None,
            serde_json::json!({}),
            keep(0),
            |dir| {
                fs::write(dir.join("model.safetensors"), vec![7u8; 256]).map_err(io(dir))?;
                fs::write(dir.join("replay.safetensors"), vec![1u8; 1000]).map_err(io(dir))
            },
        )
        .unwrap()
    };
    let (first, second) = (write(1), write(2));
    assert_eq!(
        checkpoint_folders(&run.path).unwrap(),
        vec![first.clone(), second.clone()]
    );
    assert_eq!(checkpoint_folders(&second).unwrap(), vec![second.clone()]);
    assert_eq!(drop_file(&first, "replay.safetensors").unwrap(), Some(1000));
    assert!(!first.join("replay.safetensors").exists());
    let m = read_manifest(&first).unwrap();
    assert!(!m.files.contains_key("replay.safetensors"));
    assert!(!m.sha256.contains_key("replay.safetensors"));
    assert_eq!(m.files["model.safetensors"], 256, "the rest is kept");
    assert_eq!(drop_file(&first, "replay.safetensors").unwrap(), None);
    // A damaged checkpoint is refused before anything is removed.
    let mut bytes = fs::read(second.join("model.safetensors")).unwrap();
    bytes[0] ^= 0xff;
    fs::write(second.join("model.safetensors"), &bytes).unwrap();
    let err = drop_file(&second, "replay.safetensors").unwrap_err();
    assert!(err.to_string().contains("SHA-256"), "{err}");
    assert!(second.join("replay.safetensors").exists());
    assert!(read_manifest(&second).is_err(), "its manifest is as it was");
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn altered_bytes_of_the_same_size_are_caught_by_the_checksum() {
    let root = std::env::temp_dir().join(format!("icrl-ckpt-sha-{}", std::process::id()));
    let run = RunDir::create(&root, "darkroom", "test", 3).unwrap();
    let dir = run
        .write_checkpoint(
            1,
            "test",
            "darkroom",
            None,
            serde_json::json!({}),
            keep(0),
            |dir| fs::write(dir.join("model.safetensors"), vec![7u8; 256]).map_err(io(dir)),
        )
        .unwrap();
    let m = read_manifest(&dir).unwrap();
    assert_eq!(m.sha256.len(), 1);
    assert_eq!(
        m.sha256["model.safetensors"],
        sha256_file(&dir.join("model.safetensors")).unwrap()
    );
    // Same size, one byte replaced: the size check passes, the hash does not.
    let mut bytes = fs::read(dir.join("model.safetensors")).unwrap();
    bytes[100] ^= 0xff;
    fs::write(dir.join("model.safetensors"), &bytes).unwrap();
    let err = read_manifest(&dir).unwrap_err().to_string();
    assert!(
        err.contains("model.safetensors") && err.contains("SHA-256") && err.contains("altered"),
        "{err}"
    );
    // A manifest that lists a file without its checksum is damaged.
    let mut m2 = m.clone();
    m2.files.insert("extra.bin".into(), 0);
    fs::write(dir.join("extra.bin"), b"").unwrap();
    fs::write(dir.join(MANIFEST), serde_json::to_string(&m2).unwrap()).unwrap();
    let err = read_manifest(&dir).unwrap_err().to_string();
    assert!(err.contains("no SHA-256 recorded for extra.bin"), "{err}");
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn racing_creators_never_share_a_run_folder() {
    let root = std::env::temp_dir().join(format!("icrl-ckpt-race-{}", std::process::id()));
    // Rounds, because a race shows only sometimes: each starts without
    // the --out folder, so the creators also race to make it.
    for _ in 0..20 {
        let _ = fs::remove_dir_all(&root);
        // Eight threads, released together, all asking for the same name.
        let barrier = std::sync::Arc::new(std::sync::Barrier::new(8));
        let handles: Vec<_> = (0..8)
            .map(|_| {
                let (root, barrier) = (root.clone(), barrier.clone());
                std::thread::spawn(move || {
                    barrier.wait();
                    RunDir::create_named(&root, "darkroom__eppo__0__20260101T000000")
                        .map(|run| run.path)
                        .map_err(|e| e.to_string())
                })
            })
            .collect();
        let mut paths: Vec<PathBuf> = handles
            .into_iter()
            .map(|h| h.join().unwrap().unwrap())
            .collect();
        paths.sort();
        paths.dedup();
        assert_eq!(
            paths.len(),
            8,
            "every creator got its own folder: {paths:?}"
        );
        assert!(paths.contains(&root.join("darkroom__eppo__0__20260101T000000")));
        assert!(paths.contains(&root.join("darkroom__eppo__0__20260101T000000_8")));
        assert!(paths.iter().all(|p| p.join("checkpoints").is_dir()));
    }
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn resuming_drops_metrics_written_after_the_checkpoint() {
    let dir = std::env::temp_dir().join(format!("icrl-ckpt-metrics-{}", std::process::id()));
    fs::create_dir_all(&dir).unwrap();
    let path = dir.join("metrics.jsonl");
    let mut w = MetricsWriter::open(&path).unwrap();
    for u in [10u64, 20, 30, 40] {
        w.write(&serde_json::json!({"updates": u, "env_steps": u * 7}))
            .unwrap();
    }
    drop(w);
    // A line cut by a kill at the end.
    let mut f = fs::OpenOptions::new().append(true).open(&path).unwrap();
    f.write_all(b"{\"updates\": 5").unwrap();
    drop(f);
    assert_eq!(truncate_metrics(&path, "updates", 20).unwrap(), 3);
    assert_eq!(recorded_counters(&path, "updates").unwrap(), vec![10, 20]);
    assert_eq!(truncate_metrics(&path, "updates", 20).unwrap(), 0);
    assert_eq!(
        truncate_metrics(&dir.join("none.jsonl"), "updates", 0).unwrap(),
        0
    );
    fs::remove_dir_all(&dir).unwrap();
}

/// A run's config.toml that is a symbolic link (to a user's file) is
/// refused by name on write, and the file it names keeps its contents.
#[test]
fn a_config_is_never_written_through_a_link() {
    let root = std::env::temp_dir().join(format!("icrl-ckpt-config-{}", std::process::id()));
    let _ = fs::remove_dir_all(&root);
    let run = RunDir::create(&root, "darkroom", "test", 1).unwrap();
    let theirs = root.join("notes.toml");
    fs::write(&theirs, "mine = true").unwrap();
    std::os::unix::fs::symlink(&theirs, run.config_path()).unwrap();
    let err = run.write_config("x = 1").unwrap_err().to_string();
    assert!(err.contains("symbolic link"), "{err}");
    assert_eq!(fs::read_to_string(&theirs).unwrap(), "mine = true");
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn pruning_removes_only_checkpoint_files_and_runs_do_not_nest() {
    let root = std::env::temp_dir().join(format!("icrl-ckpt-prune-{}", std::process::id()));
    let _ = fs::remove_dir_all(&root);
    let run = RunDir::create(&root, "darkroom", "test", 1).unwrap();
    run.write_config("x = 1").unwrap();
    let write = |step: u64| write_small(&run, step, keep(2)).unwrap();
    let first = write(10);
    // A user's notes in a checkpoint, and a run nested inside one: refused.
    fs::write(first.join("notes.txt"), "mine").unwrap();
    let e = RunDir::create(&first, "darkroom", "test", 2)
        .unwrap_err()
        .to_string();
    assert!(e.contains("lies inside the checkpoint"), "{e}");
    let e = RunDir::create(&first.join("model.bin"), "darkroom", "test", 2)
        .unwrap_err()
        .to_string();
    assert!(e.contains("lies inside the checkpoint"), "{e}");
    let file = root.join("a-file");
    fs::write(&file, "x").unwrap();
    let e = RunDir::create(&file, "darkroom", "test", 2)
        .unwrap_err()
        .to_string();
    assert!(e.contains("not a folder") && e.contains("--out"), "{e}");
    let e = RunDir::create(&run.path.join("sub"), "darkroom", "test", 2)
        .unwrap_err()
        .to_string();
    assert!(e.contains("lies inside the run"), "{e}");
    // A step_N folder that is no checkpoint.
    let fake = run.path.join("checkpoints/step_1");
    fs::create_dir(&fake).unwrap();
    fs::write(fake.join("data.txt"), "x").unwrap();
    write(20);
    write(30);
    assert_eq!(fs::read_to_string(first.join("notes.txt")).unwrap(), "mine");
    assert!(!first.join("w.bin").exists() && !first.join(MANIFEST).exists());
    assert!(fake.join("data.txt").exists(), "not a checkpoint: kept");
    assert!(run.path.join("checkpoints/step_20").is_dir());
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn checkpoints_at_multiples_of_keep_every_outlive_pruning() {
    let root = std::env::temp_dir().join(format!("icrl-ckpt-every-{}", std::process::id()));
    let _ = fs::remove_dir_all(&root);
    let run = RunDir::create(&root, "darkroom", "test", 1).unwrap();
    let history = Retention {
        newest: 2,
        every: 100,
    };
    for step in (50..=400).step_by(50) {
        write_small(&run, step, history).unwrap();
    }
    let kept: Vec<u64> = run.checkpoints().unwrap().iter().map(|c| c.0).collect();
    assert_eq!(
        kept,
        vec![100, 200, 300, 350, 400],
        "history + the newest 2"
    );
    // The room asked for counts the history still to come: the newest 2
    // and the one being written, less 350 already there, and the
    // 1000 / 100 kept on the way.
    let e = run
        .check_room(u64::MAX / 64, history, 1000, 50)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("12 more checkpoints") && e.contains("keep_every = 100"),
        "{e}"
    );
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn a_run_whose_folder_disappears_stops_instead_of_remaking_it() {
    let root = std::env::temp_dir().join(format!("icrl-ckpt-gone-{}", std::process::id()));
    let _ = fs::remove_dir_all(&root);
    let run = RunDir::create(&root, "darkroom", "test", 1).unwrap();
    run.write_config("x = 1").unwrap();
    let _lock = run.lock().unwrap();
    let e = run.lock().unwrap_err().to_string();
    assert!(e.contains(&format!("pid {}", std::process::id())), "{e}");
    let mut metrics = MetricsWriter::open(&run.metrics_path()).unwrap();
    metrics.write(&serde_json::json!({"updates": 1})).unwrap();
    fs::remove_dir_all(&run.path).unwrap();
    let e = metrics
        .write(&serde_json::json!({"updates": 2}))
        .unwrap_err()
        .to_string();
    assert!(e.contains("metrics file is gone"), "{e}");
    let e = write_small(&run, 5, keep(0)).unwrap_err().to_string();
    assert!(e.contains("the run folder is gone"), "{e}");
    assert!(!run.path.exists(), "the run folder is not remade");
    fs::remove_dir_all(&root).unwrap();
}
