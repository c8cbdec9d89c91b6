//! `icrl sweep --run`: a grid trained here one task after another, a finished
//! task skipped, a stopped one continued, and a stop signal passed to the
//! task in progress once.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn tmpdir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("icrl-sweep-cli-{name}-{}", std::process::id()));
    let _ = fs::remove_dir_all(&dir);
    fs::create_dir_all(&dir).unwrap();
    dir
}

/// A grid of `seeds` tiny SafeDarkRoom runs of `updates` updates each.
fn grid_file(dir: &Path, seeds: &str, updates: u64) -> PathBuf {
    let text = format!(
        "env = \"darkroom\"\nseeds = {seeds}\nout = \"runs\"\n[set]\n\
         max_episode_steps = 6\nk_min = 2\nk_max = 2\nn_envs = 2\nbatch_size = 2\n\
         replay_capacity = 1000\nencoder_hidden = 16\nhead_hidden = 16\n\
         total_updates = {updates}\nupdates_per_round = 2\nlearning_starts = 0\n\
         checkpoint_every = 2\ntorch_threads = 1\nenv_threads = 1\nlearner_threads = 0\n\
         [set.model]\nd_model = 16\nn_heads = 2\nn_layers = 1\nd_ff = 32\nmax_len = 12\n"
    );
    let path = dir.join("grid.toml");
    fs::write(&path, text).unwrap();
    path
}

/// `icrl sweep ARGS --grid GRID`, whatever it ends in.
fn run_sweep(grid: &Path, args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_icrl"))
        .arg("sweep")
        .args(args)
        .arg("--grid")
        .arg(grid)
        .stdin(Stdio::null())
        .output()
        .unwrap()
}

/// `icrl sweep ARGS --grid GRID`, which must succeed; its stdout.
fn sweep(grid: &Path, args: &[&str]) -> String {
    let out = run_sweep(grid, args);
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// The run folders under a task's folder.
fn runs_of(task: &Path) -> Vec<PathBuf> {
    fs::read_dir(task)
        .map(|d| {
            d.map(|e| e.unwrap().path())
                .filter(|p| p.is_dir())
                .collect()
        })
        .unwrap_or_default()
}

#[test]
fn a_grid_runs_here_task_after_task_and_a_second_run_skips_the_finished() {
    let dir = tmpdir("run");
    let grid = grid_file(&dir, "[0, 1]", 2);
    let stdout = sweep(&grid, &["--run"]);
    assert!(
        stdout.contains("2 tasks trained, 0 already finished"),
        "{stdout}"
    );
    for task in ["seed0", "seed1"] {
        let runs = runs_of(&dir.join("runs").join(task));
        assert_eq!(runs.len(), 1, "{task}: one run folder");
        assert!(
            runs[0].join("checkpoints").join("step_2").is_dir(),
            "{task}"
        );
    }
    let stdout = sweep(&grid, &["--run"]);
    assert!(
        stdout.contains("0 tasks trained, 2 already finished"),
        "{stdout}"
    );
    assert_eq!(
        runs_of(&dir.join("runs").join("seed0")).len(),
        1,
        "nothing new"
    );
    // Gathered at the evaluation seeds the grid declares, the random policy
    // beside each run: one row per setting, one per run and seed.
    let mut text = fs::read_to_string(&grid).unwrap();
    text.push_str(
        "[gather]\neval_seeds = [3, 5]\ntasks = 2\nepisodes = 2\nn_budgets = 2\nrandom = true\n",
    );
    fs::write(&grid, text).unwrap();
    let stdout = sweep(&grid, &["--gather", "--threads", "1"]);
    assert!(
        stdout.contains("4 runs evaluated"),
        "2 runs x 2 seeds: {stdout}"
    );
    let table = fs::read_to_string(dir.join("runs/gather/table.md")).unwrap();
    assert!(table.contains("evaluation seeds 3, 5"), "{table}");
    assert!(table.contains("| preset | 2 |"), "{table}");
    for (seed, eval_seed) in [(0, 3), (0, 5), (1, 3), (1, 5)] {
        assert!(
            table.contains(&format!("| preset | {seed} | {eval_seed} |")),
            "{table}"
        );
        let folder = dir.join(format!("runs/gather/seed{seed}/eval_seed{eval_seed}"));
        assert!(
            folder.join("random_darkroom.json").is_file(),
            "{}",
            folder.display()
        );
    }
    fs::remove_dir_all(&dir).unwrap();
}

/// `icrl sweep ARGS --grid GRID`, which must fail with exit 1; its stderr.
fn sweep_refused(grid: &Path, args: &[&str]) -> String {
    let out = run_sweep(grid, args);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    stderr
}

/// Trial 3, weak: `--gather` wrote empty tables when no run had finished,
/// then refused its own leftovers after evaluating every run, and one
/// damaged run aborted the whole table. Now nothing is written when there
/// is nothing to gather, an earlier gather is refused before evaluating,
/// and a damaged run is named in the table's notes, the rest gathered.
#[test]
fn a_gather_leaves_out_a_damaged_run_by_name_and_writes_nothing_it_cannot_fill() {
    let dir = tmpdir("gather-damaged");
    let grid = grid_file(&dir, "[0, 1, 2]", 2);
    let mut text = fs::read_to_string(&grid).unwrap();
    text.push_str("[gather]\neval_seeds = [3]\ntasks = 2\nepisodes = 2\nn_budgets = 2\n");
    fs::write(&grid, text).unwrap();
    let gather = ["--gather", "--threads", "1"];
    let err = sweep_refused(&grid, &gather);
    assert!(
        err.contains("no run to gather (3 not finished, 0 left out); nothing was written"),
        "{err}"
    );
    assert!(!dir.join("runs/gather").exists(), "no empty table");
    sweep(&grid, &["--run"]);
    let run = runs_of(&dir.join("runs/seed1")).remove(0);
    let weights = run.join("checkpoints/step_2/model.safetensors");
    let mut bytes = fs::read(&weights).unwrap();
    bytes[100] ^= 0xff;
    fs::write(&weights, bytes).unwrap();
    let stdout = sweep(&grid, &gather);
    assert!(
        stdout.contains("2 runs evaluated, 0 not finished, 1 left out"),
        "{stdout}"
    );
    let table = fs::read_to_string(dir.join("runs/gather/table.md")).unwrap();
    assert!(
        table.contains("| preset | 0 | 3 |") && table.contains("| preset | 2 | 3 |"),
        "{table}"
    );
    assert!(!table.contains("| preset | 1 | 3 |"), "{table}");
    let note = format!(
        "Left out: finished runs that could not be evaluated:\n\n- task 1 (preset, seed 1): \
         checkpoint {}",
        run.join("checkpoints/step_2").display()
    );
    assert!(table.contains(&note), "{table}");
    assert!(table.contains("differs from the manifest's"), "{table}");
    // Again without --force: refused before any evaluation.
    let err = sweep_refused(&grid, &gather);
    assert!(
        err.contains(&format!(
            "{}: it holds an earlier --gather's evaluations or table: pass --force to evaluate \
             again and replace them, or move the folder away; nothing was evaluated",
            dir.join("runs/gather").display()
        )),
        "{err}"
    );
    assert_eq!(
        fs::read_to_string(dir.join("runs/gather/table.md")).unwrap(),
        table
    );
    fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_stop_reaches_the_task_in_progress_once_and_the_next_run_continues_it() {
    let dir = tmpdir("stop");
    // Long enough to be stopped in its first task, which then checkpoints.
    let grid = grid_file(&dir, "[0, 1]", 100_000);
    // Into files: a pipe nobody reads while the task trains would fill.
    let (stdout_path, stderr_path) = (dir.join("stdout.txt"), dir.join("stderr.txt"));
    let mut child = Command::new(env!("CARGO_BIN_EXE_icrl"))
        .args(["sweep", "--run", "--grid"])
        .arg(&grid)
        .stdin(Stdio::null())
        .stdout(fs::File::create(&stdout_path).unwrap())
        .stderr(fs::File::create(&stderr_path).unwrap())
        .spawn()
        .unwrap();
    // Wait for the task's first checkpoint, then stop the sweep (as a
    // scheduler would: the signal goes to the sweep's pid only).
    let task = dir.join("runs").join("seed0");
    let start = Instant::now();
    let checkpointed = |run: &PathBuf| {
        fs::read_dir(run.join("checkpoints")).is_ok_and(|d| {
            d.flatten()
                .any(|e| e.file_name().to_string_lossy().starts_with("step_"))
        })
    };
    while !runs_of(&task).iter().any(checkpointed) {
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "no checkpoint: {}",
            fs::read_to_string(&stderr_path).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    // SAFETY: kill(2) on the child this test started.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let status = child.wait().unwrap();
    let stdout = fs::read_to_string(&stdout_path).unwrap();
    let stderr = fs::read_to_string(&stderr_path).unwrap();
    assert_eq!(status.code(), Some(130), "{stdout}\n{stderr}");
    assert!(
        stdout.contains("stopped: run the same command again"),
        "{stdout}"
    );
    assert!(
        stderr.contains("stop requested"),
        "the task heard it: {stderr}"
    );
    assert!(
        !dir.join("runs").join("seed1").exists(),
        "no task starts after a stop"
    );
    // Run again with a reachable end: the stopped run continues in its own
    // folder rather than starting over.
    let run = runs_of(&task).remove(0);
    let text = fs::read_to_string(grid.clone()).unwrap();
    fs::write(
        &grid,
        text.replace("total_updates = 100000", "total_updates = 4"),
    )
    .unwrap();
    let before = fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(before.contains("total_updates = 100000"));
    // The stopped run asked for more updates than the grid now does: it is
    // either finished as it stands or resumed to the new end, never restarted.
    let stdout = sweep(&grid, &["--run"]);
    assert_eq!(runs_of(&task).len(), 1, "the same run folder: {stdout}");
    assert_eq!(runs_of(&dir.join("runs").join("seed1")).len(), 1);
    fs::remove_dir_all(&dir).unwrap();
}
