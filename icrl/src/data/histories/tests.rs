use super::seal::CHECKSUM_TAG;
use super::write::put;
use super::*;
use safety_envs::output::{self, Existing};
use safety_envs::{Orientation, SpawnConfig, sample_task};

pub(crate) fn tiny_file(histories: usize) -> HistoryFile {
    let cfg = SpawnConfig::darkroom();
    let histories: Vec<History> = (0..histories)
        .map(|i| {
            let task = sample_task(&cfg, Orientation::Centre, i as u64).unwrap();
            let mut h = History::new(task, 2.5 * i as f32);
            // Two episodes: 3 steps ending on the goal, 2 steps timed out.
            for t in 0..5 {
                let x = (i * 10 + t) as f32;
                h.push(
                    &[x, -x],
                    &[(t % 5) as f32],
                    if t == 2 { 1.0 } else { 0.0 },
                    (t % 2) as f32,
                    &[x + 1.0, -x - 1.0],
                    t == 2,
                    t == 4,
                );
            }
            h
        })
        .collect();
    HistoryFile {
        info: DatasetInfo {
            env: "darkroom".into(),
            config: r#"{"steps": 5}"#.into(),
            seed: 7,
            obs_dim: 2,
            action_dim: 1,
            action_n: Some(5),
            grid_size: 9,
            physics_steps_per_action: None,
            grid_histories: histories.len(),
            shard: None,
        },
        histories,
    }
}

pub(crate) fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("icrl-histories-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn round_trip_keeps_everything() {
    let dir = tmpdir("roundtrip");
    let path = dir.join("h.h5");
    let file = tiny_file(3);
    write_histories(&path, &file).unwrap();
    assert!(
        !output::temp_path(&path).exists(),
        "the temporary file must be renamed away"
    );
    let back = read_histories(&path, Some("darkroom")).unwrap();
    assert_eq!(back, file);
    assert_eq!(back.histories[1].episodes(), vec![0..3, 3..5]);
    assert_eq!(
        back.histories[1].episode_totals(),
        vec![(1.0, 1.0), (0.0, 1.0)]
    );
    std::fs::remove_dir_all(dir).unwrap();
}

fn problem_of(path: &Path, env: Option<&str>) -> (Problem, String) {
    let e = read_histories(path, env).unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains(&path.display().to_string()),
        "message must name the file: {msg}"
    );
    (e.problem, msg)
}

#[test]
fn missing_and_corrupt_files_are_named() {
    let dir = tmpdir("bad");
    let missing = dir.join("nothing.h5");
    assert!(matches!(problem_of(&missing, None).0, Problem::Missing));
    let junk = dir.join("junk.h5");
    std::fs::write(&junk, b"this is not hdf5").unwrap();
    assert!(matches!(problem_of(&junk, None).0, Problem::Unreadable(_)));
    // A real file cut in half.
    let good = dir.join("good.h5");
    write_histories(&good, &tiny_file(2)).unwrap();
    let bytes = std::fs::read(&good).unwrap();
    let cut = dir.join("cut.h5");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let (p, msg) = problem_of(&cut, None);
    assert!(matches!(p, Problem::Damaged(_)), "{msg}");
    // One flipped bit anywhere after the user block: caught by the
    // checksum before libhdf5 parses anything.
    for at in [
        USER_BLOCK,
        USER_BLOCK + 100,
        bytes.len() / 2,
        bytes.len() - 1,
    ] {
        let mut b = bytes.clone();
        b[at] ^= 0x10;
        std::fs::write(&cut, &b).unwrap();
        let (p, msg) = problem_of(&cut, None);
        assert!(matches!(p, Problem::Damaged(_)), "byte {at}: {msg}");
        assert!(msg.contains("make it again with `icrl dataset`"), "{msg}");
    }
    // Without the checksum (a file written elsewhere) it still reads.
    let mut b = bytes.clone();
    b[..CHECKSUM_TAG.len()].fill(0);
    std::fs::write(&cut, &b).unwrap();
    assert_eq!(read_histories(&cut, None).unwrap(), tiny_file(2));
    std::fs::remove_dir_all(dir).unwrap();
}

/// Edits a written file through HDF5, then re-seals it (as a writer of
/// such a file would have), so the reader's checks behind the checksum
/// are what the test sees.
fn edit(path: &Path, change: impl FnOnce(&hdf5::File)) {
    {
        let f = hdf5::File::open_rw(path).unwrap();
        change(&f);
    }
    seal(path).unwrap();
}

#[test]
fn other_env_and_other_version_are_refused() {
    let dir = tmpdir("env");
    let path = dir.join("h.h5");
    write_histories(&path, &tiny_file(1)).unwrap();
    let (p, msg) = problem_of(&path, Some("point"));
    assert!(matches!(p, Problem::WrongEnv { .. }), "{msg}");
    assert!(msg.contains("darkroom") && msg.contains("point"), "{msg}");
    edit(&path, |f| {
        f.attr("format_version")
            .unwrap()
            .write_scalar(&99u32)
            .unwrap();
    });
    let (p, msg) = problem_of(&path, Some("darkroom"));
    assert!(
        matches!(
            p,
            Problem::WrongVersion {
                found: 99,
                expected: FORMAT_VERSION
            }
        ),
        "{msg}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn macro_action_round_trips_and_old_mujoco_files_are_refused() {
    let dir = tmpdir("macro");
    let path = dir.join("h.h5");
    let mut file = tiny_file(1);
    // Relabelled as a Point file (the layout does not care what the
    // observations mean).
    file.info.env = "point".into();
    file.info.physics_steps_per_action = Some(50);
    write_histories(&path, &file).unwrap();
    let back = read_histories(&path, Some("point")).unwrap();
    assert_eq!(back.info.physics_steps_per_action, Some(50));
    // A file from before the attribute existed.
    edit(&path, |f| {
        f.delete_attr("physics_steps_per_action").unwrap()
    });
    let (p, msg) = problem_of(&path, Some("point"));
    assert!(matches!(p, Problem::UnrecordedMacroAction { .. }), "{msg}");
    assert!(
        msg.contains("5 physics steps") && msg.contains("icrl dataset --env point"),
        "{msg}"
    );
    // SafeDarkRoom has no physics: no attribute is fine.
    let path = dir.join("d.h5");
    write_histories(&path, &tiny_file(1)).unwrap();
    edit(&path, |f| {
        f.delete_attr("physics_steps_per_action").unwrap()
    });
    let back = read_histories(&path, Some("darkroom")).unwrap();
    assert_eq!(back.info.physics_steps_per_action, None);
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn empty_histories_are_refused_on_write_and_read() {
    let dir = tmpdir("empty");
    let path = dir.join("h.h5");
    let mut file = tiny_file(2);
    file.histories[1] = History::new(file.histories[1].task.clone(), 5.0);
    let e = write_histories(&path, &file).unwrap_err();
    assert!(matches!(e.problem, Problem::Empty(_)), "{e}");
    assert!(!path.exists() && !output::temp_path(&path).exists());
    // A file whose per-history table names a history without steps.
    let mut file = tiny_file(2);
    write_histories(&path, &file).unwrap();
    edit(&path, |f| {
        f.unlink("cost_limit").unwrap();
        put(f, "cost_limit", &[0.0f32, 2.5, 5.0], &[3]).unwrap();
        f.unlink("task_goal").unwrap();
        put(f, "task_goal", &[0i64; 6], &[3, 2]).unwrap();
        f.unlink("task_obstacles").unwrap();
        put(f, "task_obstacles", &[0i64; 150], &[3, 25, 2]).unwrap();
        f.attr("grid_histories")
            .unwrap()
            .write_scalar(&3u64)
            .unwrap();
    });
    let (p, msg) = problem_of(&path, None);
    assert!(matches!(p, Problem::Empty(_)), "{msg}");
    assert!(msg.contains("history 2"), "{msg}");
    // Two histories' steps out of order: named as such, not as a
    // history without steps.
    let shuffled = dir.join("shuffled.h5");
    write_histories(&shuffled, &tiny_file(2)).unwrap();
    edit(&shuffled, |f| {
        let mut ids: Vec<i64> = f.dataset("history_id").unwrap().read_raw().unwrap();
        let last = ids.len() - 1;
        ids.swap(0, last);
        f.unlink("history_id").unwrap();
        put(f, "history_id", &ids, &[ids.len()]).unwrap();
    });
    let (_, msg) = problem_of(&shuffled, None);
    assert!(
        msg.contains("history_id must be non-decreasing")
            && msg.contains("step 1 has id 0 after id 1"),
        "{msg}"
    );
    // A history that stops mid-episode cannot be written.
    file.histories[0].timeouts[4] = false;
    let e = write_histories(&path, &file).unwrap_err();
    assert!(matches!(e.problem, Problem::Invalid(_)), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

/// Replaces dataset `name` of a written file with `data` (same shape).
fn overwrite(path: &Path, name: &str, data: &[f32]) {
    edit(path, |f| {
        let shape = f.dataset(name).unwrap().shape();
        f.unlink(name).unwrap();
        put(f, name, data, &shape).unwrap();
    });
}

#[test]
fn output_paths_are_checked_before_any_work() {
    let dir = tmpdir("out");
    let e = check_output_path(&dir, Existing::Refuse).unwrap_err();
    assert!(matches!(e.problem, Problem::Output(_)), "{e}");
    assert!(e.to_string().contains("it is a folder"), "{e}");
    assert!(
        !output::temp_path(&dir).exists(),
        "no DIR.tmp beside the folder"
    );
    let e = check_output_path(&dir.join("missing/h.h5"), Existing::Refuse)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("does not exist") && e.contains("mkdir -p"),
        "{e}"
    );
    check_output_path(&dir.join("h.h5"), Existing::Refuse).unwrap();
    assert!(
        !output::temp_path(&dir.join("h.h5")).exists(),
        "the probe is removed"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn non_finite_values_and_out_of_range_actions_are_refused() {
    let dir = tmpdir("values");
    let path = dir.join("h.h5");
    let file = tiny_file(2);
    // The writer refuses them ...
    let mut nan = file.clone();
    nan.histories[1].rewards[3] = f32::NAN;
    let e = write_histories(&path, &nan).unwrap_err().to_string();
    assert!(e.contains("history 1: rewards holds NaN at step 3"), "{e}");
    // ... and so does the reader, for files written elsewhere.
    write_histories(&path, &file).unwrap();
    let mut rewards: Vec<f32> = file
        .histories
        .iter()
        .flat_map(|h| h.rewards.clone())
        .collect();
    rewards[7] = f32::NAN;
    overwrite(&path, "rewards", &rewards);
    let (p, msg) = problem_of(&path, None);
    assert!(matches!(p, Problem::Malformed(_)), "{msg}");
    assert!(
        msg.contains("history 1: rewards holds NaN at step 2"),
        "{msg}"
    );
    write_histories(&path, &file).unwrap();
    let mut obs: Vec<f32> = file
        .histories
        .iter()
        .flat_map(|h| h.observations.clone())
        .collect();
    obs[1] = f32::INFINITY;
    overwrite(&path, "observations", &obs);
    let (_, msg) = problem_of(&path, None);
    assert!(msg.contains("observations holds inf at step 0"), "{msg}");
    // A negative cost, which would pay budget back.
    write_histories(&path, &file).unwrap();
    let mut costs: Vec<f32> = file
        .histories
        .iter()
        .flat_map(|h| h.costs.clone())
        .collect();
    costs[6] = -1.0;
    overwrite(&path, "costs", &costs);
    let (_, msg) = problem_of(&path, None);
    assert!(
        msg.contains("history 1: costs holds -1 at step 1 (costs must be non-negative)"),
        "{msg}"
    );
    // Action 17 in a 5-action space, and a fractional action.
    for (bad, shown) in [
        (17.0f32, "action 17 "),
        (1.5, "action 1.5 "),
        (-1.0, "action -1 "),
    ] {
        write_histories(&path, &file).unwrap();
        let mut actions: Vec<f32> = file
            .histories
            .iter()
            .flat_map(|h| h.actions.clone())
            .collect();
        actions[4] = bad;
        overwrite(&path, "actions", &actions);
        let (_, msg) = problem_of(&path, None);
        assert!(
            msg.contains(shown)
                && msg.contains("at step 4 is not one of the 5 discrete actions 0..=4"),
            "{msg}"
        );
    }
    std::fs::remove_dir_all(dir).unwrap();
}

/// Opens a written file of `tiny_file(3)`'s histories with Python's
/// h5py and checks names, shapes, dtypes and values; `merged`: every
/// dataset is a virtual dataset over shards (no chunks or compression of
/// its own). Fails (does not skip) when python3 or h5py is missing: the
/// test set-up (`cargo xtask test`) installs h5py.
pub(crate) fn h5py_check(path: &Path, merged: bool) {
    let script = r#"
import sys, h5py
f = h5py.File(sys.argv[1], "r")
merged = sys.argv[2] == "merged"
want = {
    "observations": ((15, 2), "float32"), "next_observations": ((15, 2), "float32"),
    "actions": ((15, 1), "float32"), "rewards": ((15,), "float32"), "costs": ((15,), "float32"),
    "terminals": ((15,), "float32"), "timeouts": ((15,), "float32"),
    "history_id": ((15,), "int64"), "episode_id": ((15,), "int64"),
    "cost_limit": ((3,), "float32"), "task_goal": ((3, 2), "int64"),
    "task_obstacles": ((3, 25, 2), "int64"),
}
assert set(f.keys()) == set(want), sorted(f.keys())
for name, (shape, dtype) in want.items():
    d = f[name]
    assert d.shape == shape and str(d.dtype) == dtype, (name, d.shape, d.dtype)
    if merged:
        assert d.is_virtual and len(d.virtual_sources()) == 3, (name, d.is_virtual)
    else:
        assert d.compression == "gzip" and d.chunks is not None, (name, d.compression, d.chunks)
a = f.attrs
assert a["env"] == "darkroom" and int(a["format_version"]) == 1 and int(a["seed"]) == 7, dict(a)
assert int(a["action_n"]) == 5 and int(a["obs_dim"]) == 2
assert int(a["physics_steps_per_action"]) == 0, dict(a)
assert int(a["grid_histories"]) == 3 and "shard_index" not in a, dict(a)
assert list(f["episode_id"][:5]) == [0, 0, 0, 1, 1]
assert list(f["history_id"][:]) == [0] * 5 + [1] * 5 + [2] * 5
assert float(f["rewards"][:].sum()) == 3.0
assert list(f["observations"][10]) == [20.0, -20.0], f["observations"][10]
assert list(f["cost_limit"][:]) == [0.0, 2.5, 5.0]
print("h5py ok")
"#;
    let out = std::process::Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(path)
        .arg(if merged { "merged" } else { "one" })
        .output();
    let out = match out {
        Ok(o) => o,
        Err(e) => {
            panic!("python3 is needed for this test (install it, then `pip install h5py`): {e}")
        }
    };
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !stderr.contains("No module named 'h5py'"),
        "h5py is missing: run `pip install h5py` (cargo xtask test does): {stderr}"
    );
    assert!(out.status.success(), "h5py check failed: {stderr}");
}

#[test]
fn h5py_reads_the_layout() {
    let dir = tmpdir("h5py");
    let path = dir.join("h.h5");
    write_histories(&path, &tiny_file(3)).unwrap();
    h5py_check(&path, false);
    std::fs::remove_dir_all(dir).unwrap();
}
