//! The `icrl` binary under the second hostile trial (issue 21): outputs never
//! replace what is not ours, one process per run, and every message true.
//! Each test runs the binary in a child process on tiny inputs.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod common;
use common::{fresh_dir, icrl, tiny_eppo_args};

fn tmp(name: &str) -> PathBuf {
    fresh_dir(&format!("hostile-{name}"))
}

/// Makes a FIFO at `path`.
fn mkfifo(path: &Path) {
    assert!(Command::new("mkfifo").arg(path).status().unwrap().success());
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

/// Fails unless the command failed with `want` in stderr and no panic.
fn refused(out: &Output, want: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "expected a failure: {err}");
    assert_eq!(out.status.code(), Some(1), "exit 1: {err}");
    assert!(err.contains(want), "expected {want:?} in: {err}");
    assert!(
        !err.contains("panicked") && !err.contains("backtrace"),
        "no panic: {err}"
    );
}

fn succeeded(out: &Output) -> String {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "expected success: {err}");
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// A tiny dataset command writing `out`.
fn dataset(out: &str, extra: &[&str]) -> Output {
    let mut args = vec![
        "dataset",
        "--env",
        "darkroom",
        "--out",
        out,
        "--tasks",
        "1",
        "--steps",
        "300",
        "--cost-limits",
        "0",
        "--threads",
        "1",
    ];
    args.extend(extra);
    icrl(&args)
}

#[test]
fn dataset_never_replaces_what_is_not_ours() {
    let dir = tmp("dataset-out");
    // A device, a FIFO, a symlink: refused, even with --force, untouched.
    refused(&dataset("/dev/null", &["--force"]), "it is a device");
    assert!(!std::fs::metadata("/dev/null").unwrap().is_file());
    let fifo = dir.join("fifo");
    mkfifo(&fifo);
    refused(&dataset(&s(&fifo), &["--force"]), "it is a FIFO");
    // A checkpoint's weights.
    let ck = dir.join("run/checkpoints/step_20");
    std::fs::create_dir_all(&ck).unwrap();
    std::fs::write(ck.join("manifest.json"), "{}").unwrap();
    std::fs::write(ck.join("model.safetensors"), "weights").unwrap();
    refused(
        &dataset(&s(&ck.join("model.safetensors")), &["--force"]),
        "a file of a checkpoint folder",
    );
    assert_eq!(
        std::fs::read(ck.join("model.safetensors")).unwrap(),
        b"weights"
    );
    // A file where the folder should be: named as such.
    let afile = dir.join("afile");
    std::fs::write(&afile, "notes").unwrap();
    refused(
        &dataset(&s(&afile.join("x.h5")), &[]),
        "is a file, not a folder",
    );
    refused(
        &icrl(&["pretrain", "--env", "darkroom", "--out", &s(&afile)]),
        "afile: a file, not a folder: choose another folder",
    );
    // An existing dataset: refused without --force, replaced with it.
    let h5 = dir.join("h.h5");
    let summary = succeeded(&dataset(&s(&h5), &[]));
    assert!(
        !summary.contains("log-spaced"),
        "no --keep-episodes: {summary}"
    );
    let first = std::fs::read(&h5).unwrap();
    refused(
        &dataset(&s(&h5), &["--seed", "1"]),
        "exists already: pass --force",
    );
    assert_eq!(std::fs::read(&h5).unwrap(), first, "untouched");
    succeeded(&dataset(&s(&h5), &["--seed", "1", "--force"]));
    assert_ne!(std::fs::read(&h5).unwrap(), first, "replaced with --force");
    let left: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(left.is_empty(), "no temporary or lock file left: {left:?}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A tiny darkroom EPPO run (2 updates) pretrained on budgets [2, 4];
/// returns its run folder and what it printed.
fn tiny_eppo_run(out: &Path) -> (PathBuf, String) {
    let args = tiny_eppo_args(out);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let stdout = succeeded(&icrl(&args));
    let run = std::fs::read_dir(out)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    assert!(run.join("checkpoints/step_2").is_dir(), "{}", run.display());
    (run, stdout)
}

/// Trial 3, class 6: `icrl pretrain ... | head -n 1` panicked after training
/// ("failed printing to stdout: Broken pipe", exit 101). With stdout's
/// reader gone the run still trains to its end and writes its checkpoint,
/// then ends quietly on the closed pipe: no panic, no backtrace.
#[test]
fn a_closed_stdout_ends_a_run_quietly_after_its_checkpoint() {
    use std::os::unix::process::ExitStatusExt;
    let dir = tmp("closed-stdout");
    let args = tiny_eppo_args(&dir);
    let mut child = Command::new(env!("CARGO_BIN_EXE_icrl"))
        .args(&args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take()); // the reader is gone before anything is printed
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !err.contains("panicked") && !err.contains("backtrace") && !err.contains("Broken pipe"),
        "{err}"
    );
    assert!(
        out.status.success() || out.status.signal() == Some(libc::SIGPIPE),
        "ended by {:?}: {err}",
        out.status
    );
    let run = std::fs::read_dir(&dir)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    assert!(
        run.join("checkpoints/step_2").is_dir(),
        "the checkpoint is on disk"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Trial 3, class 7: `pretrain --method ad --dataset FIFO` blocked on the
/// read where no stop could end it; a FIFO as a merge shard or as
/// `plot-histories` input blocked likewise. Each is refused at once, naming
/// what the path is.
#[test]
fn a_fifo_where_histories_are_read_is_refused_at_once() {
    let dir = tmp("fifo-read");
    let fifo = dir.join("data.h5");
    mkfifo(&fifo);
    let f = s(&fifo);
    let out = s(&dir.join("x"));
    let merged = s(&dir.join("all.h5"));
    for args in [
        vec![
            "pretrain",
            "--env",
            "darkroom",
            "--method",
            "ad",
            "--dataset",
            &f,
            "--out",
            &out,
        ],
        vec!["plot-histories", &f, "--out", &out],
        vec!["dataset", "merge", "--out", &merged, &f],
    ] {
        refused(&unblocked(&args), "it is a FIFO, not a regular file");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Runs icrl with `args`, killing it (and failing) if it is still running
/// after 60 s: blocked on a FIFO, say.
fn unblocked<S: AsRef<std::ffi::OsStr> + std::fmt::Debug>(args: &[S]) -> Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_icrl"))
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let started = std::time::Instant::now();
    while child.try_wait().unwrap().is_none() {
        if started.elapsed().as_secs() > 60 {
            child.kill().unwrap();
            panic!("{args:?} blocked");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    child.wait_with_output().unwrap()
}

/// Trial 3, weak: `sweep --grid FIFO`, and a run whose `metrics.jsonl` is a
/// FIFO resumed (`--resume`, `--resume-in-out`) or forked, blocked on the
/// read until signalled. Each is refused at once, naming the path and what
/// it is.
#[test]
fn a_fifo_grid_or_run_file_is_refused_at_once() {
    let dir = tmp("fifo-run");
    let grid = dir.join("grid.toml");
    mkfifo(&grid);
    let out = unblocked(&["sweep", "--grid", &s(&grid), "--emit", "slurm"]);
    refused(
        &out,
        "it is a FIFO, not a regular file: give the grid's TOML file",
    );
    refused(&out, &s(&grid));
    let runs = dir.join("runs");
    let (run, _) = tiny_eppo_run(&runs);
    let metrics = run.join("metrics.jsonl");
    std::fs::remove_file(&metrics).unwrap();
    mkfifo(&metrics);
    let more = ["--set", "total_updates=4"];
    let (r, fork, out) = (s(&run), s(&dir.join("fork")), s(&runs));
    for extra in [
        vec!["--resume", &r],
        vec!["--resume", &r, "--fork", &fork],
        vec!["--out", &out, "--resume-in-out"],
    ] {
        let mut args = vec!["pretrain", "--env", "darkroom"];
        args.extend(extra);
        args.extend(more);
        let got = unblocked(&args);
        refused(&got, "it is a FIFO, not a regular file");
        refused(&got, &s(&metrics));
    }
    assert!(!dir.join("fork").exists(), "no fork was made");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `eval` of `checkpoints` (none: the random policy alone), tiny.
fn eval(checkpoints: &[&Path], out: &Path, extra: &[&str]) -> Output {
    let out = s(out);
    let mut args = vec![
        "eval",
        "--env",
        "darkroom",
        "--tasks",
        "2",
        "--episodes",
        "2",
        "--n-budgets",
        "3",
        "--threads",
        "1",
        "--out",
        &out,
    ];
    if extra.contains(&"--n-budgets") {
        args.retain(|a| *a != "--n-budgets" && *a != "3");
    }
    let cks: Vec<String> = checkpoints.iter().map(|c| s(c)).collect();
    for c in &cks {
        args.extend(["--checkpoint", c.as_str()]);
    }
    args.extend(extra);
    icrl(&args)
}

#[test]
fn eval_outputs_conditions_and_reports_are_checked() {
    let dir = tmp("eval");
    let (run, _) = tiny_eppo_run(&dir.join("runs"));
    let out = dir.join("eval");
    // Bad 8: the random policy is judged against the agent's budgets.
    succeeded(&eval(&[&run], &out, &[]));
    let budgets = |name: &str| -> Vec<f64> {
        let v: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join(name)).unwrap()).unwrap();
        v["result"]["conditions"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c["ctg"].as_f64().unwrap())
            .collect()
    };
    let (agent, random) = (
        budgets("eppo_darkroom.json"),
        budgets("random_darkroom.json"),
    );
    assert!(agent.iter().all(|b| (2.0..=4.0).contains(b)), "{agent:?}");
    assert_eq!(agent, random, "the random policy gets the agent's budgets");
    // Bad 1: existing reports are refused before evaluating; --force replaces.
    refused(&eval(&[&run], &out, &[]), "exists already: pass --force");
    succeeded(&eval(&[&run], &out, &["--force"]));
    // Bad 4: two reports of one name.
    refused(
        &eval(&[&run, &run], &dir.join("eval2"), &[]),
        "distinct --label",
    );
    refused(
        &eval(
            &[&run, &run],
            &dir.join("eval2"),
            &["--label", "a", "--label", "a"],
        ),
        "distinct --label",
    );
    let two = dir.join("eval3");
    let o = eval(
        &[&run, &run],
        &two,
        &["--label", "a", "--label", "b", "--no-random"],
    );
    let stdout = succeeded(&o);
    let n = std::fs::read_dir(&two).unwrap().count();
    assert!(
        stdout.contains(&format!("wrote {n} files")),
        "{stdout} vs {n} files"
    );
    // Bad 2 and 3: sizes under a limit on the work (and the memory
    // estimate), conditioning in range.
    let t = std::time::Instant::now();
    refused(
        &eval(&[&run], &dir.join("e4"), &["--n-budgets", "100000000000"]),
        "this evaluation is 400000000000 episodes per method",
    );
    refused(
        &eval(&[&run], &dir.join("e4"), &["--n-budgets", "10000000"]),
        "lower --n-budgets (or the number of --budgets), --tasks or --episodes",
    );
    assert!(t.elapsed().as_secs() < 30, "refused before sampling");
    refused(
        &eval(&[], &dir.join("e4"), &["--rtg", "1e30"]),
        "--rtg 1000000000000000000000000000000: must be in [0, 10000]",
    );
    refused(
        &eval(&[], &dir.join("e4"), &["--budgets", "1e30"]),
        "must be in [0, 10000]",
    );
    // Bad 5: a damaged report in --from is named, not skipped.
    let json = out.join("eppo_darkroom.json");
    let bytes = std::fs::read(&json).unwrap();
    std::fs::write(&json, &bytes[..bytes.len() / 2]).unwrap();
    refused(
        &icrl(&["eval", "--from", &s(&out), "--out", &s(&dir.join("all"))]),
        "eppo_darkroom.json is not readable JSON",
    );
    std::fs::write(&json, "{\"a\": 1}").unwrap();
    refused(
        &icrl(&["eval", "--from", &s(&out), "--out", &s(&dir.join("all"))]),
        "not an icrl eval report",
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_run_held_by_another_process_is_refused_with_its_pid() {
    let dir = tmp("lock");
    let (run, _) = tiny_eppo_run(&dir.join("runs"));
    // Another process holds the run (this test, through the same OS lock).
    let lock = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(run.join(".lock"))
        .unwrap();
    lock.try_lock().unwrap();
    std::fs::write(run.join(".lock"), format!("{}\n", std::process::id())).unwrap();
    let before = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    refused(
        &icrl(&[
            "pretrain",
            "--env",
            "darkroom",
            "--resume",
            &s(&run),
            "--set",
            "total_updates=4",
        ]),
        &format!(
            "is in use by another icrl process (pid {})",
            std::process::id()
        ),
    );
    assert_eq!(
        std::fs::read_to_string(run.join("metrics.jsonl")).unwrap(),
        before
    );
    drop(lock);
    // The other environment or method: named, with the flags that resume it.
    let r = s(&run);
    refused(
        &icrl(&["pretrain", "--env", "point", "--resume", &r]),
        "this is a darkroom EPPO run, not point EPPO; resume it with --env darkroom --method eppo",
    );
    refused(
        &icrl(&[
            "pretrain", "--env", "darkroom", "--method", "ad", "--resume", &r,
        ]),
        "this is a darkroom EPPO run, not darkroom AD",
    );
    refused(
        &icrl(&["pretrain", "--env", "darkroom", "--dataset", "h.h5"]),
        "--dataset h.h5 is for --method ad",
    );
    // The resume rule: listed changes are printed, others refused.
    let resume = |extra: &[&str]| {
        let mut args = vec!["pretrain", "--env", "darkroom", "--resume"];
        let r = s(&run);
        args.push(&r);
        args.extend(extra);
        icrl(&args)
    };
    refused(
        &resume(&["--set", "lr=0.01"]),
        "these settings differ from its config.toml: lr:",
    );
    refused(
        &resume(&["--seed", "5", "--set", "total_updates=4"]),
        "seed: ",
    );
    refused(
        &resume(&["--set", "total_updates=1"]),
        "it has done 2 updates and total_updates is 1, so nothing would be trained; pass --set total_updates=3",
    );
    // Released (as when its process dies): the resume goes ahead, even
    // with config.toml lost (the checkpoint's copy is used and written back).
    std::fs::remove_file(run.join("config.toml")).unwrap();
    let o = resume(&["--set", "total_updates=4"]);
    succeeded(&o);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("with total_updates: 2 -> 4"), "{err}");
    assert!(
        err.contains("config.toml is missing: resuming with the copy in"),
        "{err}"
    );
    assert!(run.join("config.toml").is_file(), "written back");
    assert!(run.join("checkpoints/step_4").is_dir());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn an_older_checkpoint_is_forked_into_a_new_run_not_resumed_in_place() {
    let dir = tmp("fork");
    let (run, _) = tiny_eppo_run(&dir.join("runs"));
    let r = s(&run);
    let pretrain = |extra: &[&str]| {
        let mut args = vec!["pretrain", "--env", "darkroom"];
        args.extend(extra);
        icrl(&args)
    };
    succeeded(&pretrain(&["--resume", &r, "--set", "total_updates=4"]));
    let step2 = s(&run.join("checkpoints/step_2"));
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    // In place, an older checkpoint would mix two histories in one run.
    refused(
        &pretrain(&["--resume", &step2, "--set", "total_updates=6"]),
        "the run's latest checkpoint is",
    );
    refused(
        &pretrain(&["--resume", &step2, "--set", "total_updates=6"]),
        "--fork DIR",
    );
    // A fork may not change the network the weights were made for.
    let forks = dir.join("forks");
    let f = s(&forks);
    refused(
        &pretrain(&[
            "--resume",
            &step2,
            "--fork",
            &f,
            "--set",
            "model.d_model=32",
        ]),
        "model.d_model: 16 -> 32",
    );
    assert!(!forks.exists() || std::fs::read_dir(&forks).unwrap().next().is_none());
    // Any other setting: a new run from step_2, the original untouched.
    let o = pretrain(&[
        "--resume",
        &step2,
        "--fork",
        &f,
        "--set",
        "lambda_max=0.6",
        "--set",
        "total_updates=4",
    ]);
    succeeded(&o);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("forked ") && err.contains("lambda_max: "),
        "{err}"
    );
    let branch = std::fs::read_dir(&forks)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let config = std::fs::read_to_string(branch.join("config.toml")).unwrap();
    assert!(config.contains("lambda_max = 0.6"), "{config}");
    assert!(branch.join("checkpoints/step_4").is_dir());
    assert_eq!(
        std::fs::read_to_string(branch.join("forked_from.txt"))
            .unwrap()
            .trim(),
        step2
    );
    // The branch's metrics: the origin's up to update 2, then its own.
    let updates =
        icrl::checkpoint::recorded_counters(&branch.join("metrics.jsonl"), "updates").unwrap();
    assert!(updates.windows(2).all(|w| w[0] <= w[1]), "{updates:?}");
    assert_eq!(updates.last(), Some(&4), "{updates:?}");
    assert_eq!(
        std::fs::read_to_string(run.join("metrics.jsonl")).unwrap(),
        metrics
    );
    assert!(run.join("checkpoints/step_4").is_dir() && run.join("checkpoints/step_2").is_dir());
    // The branch resumes as a run of its own.
    succeeded(&pretrain(&[
        "--resume",
        &s(&branch),
        "--set",
        "total_updates=6",
    ]));
    // Sinusoidal positions hold no weights: a fork may lengthen the context
    // to more episodes, and the original's manifest keeps its own length.
    let longer = dir.join("longer");
    let o = pretrain(&[
        "--resume",
        &step2,
        "--fork",
        &s(&longer),
        "--set",
        "model.max_len=24",
        "--set",
        "k_max=4",
        "--set",
        "total_updates=4",
    ]);
    succeeded(&o);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("model.max_len: 12 -> 24"), "{err}");
    let branch = std::fs::read_dir(&longer)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let max_len = |step: &Path| {
        icrl::checkpoint::read_manifest(step).unwrap().model["transformer"]["max_len"].as_i64()
    };
    assert_eq!(max_len(&branch.join("checkpoints/step_4")), Some(24));
    assert_eq!(max_len(&run.join("checkpoints/step_2")), Some(12));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A small RAM disk (tmpfs) mounted for one test and unmounted on drop.
struct SmallDisk(PathBuf);

impl SmallDisk {
    /// A tmpfs of `bytes` at `dir`, made for it; `None`, said on stderr,
    /// where this process may not mount file systems (not root, or a
    /// container without the capability).
    fn mount(dir: &Path, bytes: u64) -> Option<Self> {
        std::fs::create_dir_all(dir).unwrap();
        let ok = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={bytes}"), "tmpfs"])
            .arg(dir)
            .output()
            .is_ok_and(|o| o.status.success());
        if !ok {
            eprintln!(
                "cannot mount a tmpfs here (not root?): the full-disk cases need one; skipped"
            );
        }
        ok.then(|| SmallDisk(dir.to_path_buf()))
    }

    /// Fills the disk until about `left` bytes are free.
    fn fill_to(&self, left: u64) {
        let free = safety_envs::output::free_bytes(&self.0).unwrap();
        let n = free.saturating_sub(left) as usize;
        std::fs::write(self.0.join(format!("filler{left}")), vec![7u8; n]).unwrap();
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
    }
}

#[test]
fn a_full_disk_is_named_before_training_and_when_a_dataset_fills_it() {
    let dir = tmp("full");
    let mnt = dir.join("disk");
    let Some(disk) = SmallDisk::mount(&mnt, 4 << 20) else {
        return;
    };
    // Training refuses at once when its checkpoints will not fit.
    disk.fill_to(100_000);
    let o = icrl(&[
        "pretrain",
        "--env",
        "darkroom",
        "--out",
        &s(&mnt.join("runs")),
    ]);
    refused(&o, "free, but 3 more checkpoints of about");
    refused(&o, "nothing was trained");
    let runs = mnt.join("runs");
    assert!(
        !runs.exists() || std::fs::read_dir(&runs).unwrap().next().is_none(),
        "no run folder left"
    );
    // A dataset that fills the disk is named as such, not as HDF5's short
    // write of 18446744073709551615 bytes, and leaves no partial file.
    disk.fill_to(20_000);
    let out = mnt.join("h.h5");
    let o = icrl(&[
        "dataset",
        "--env",
        "darkroom",
        "--out",
        &s(&out),
        "--tasks",
        "4",
        "--steps",
        "20000",
        "--cost-limits",
        "0",
        "--threads",
        "1",
    ]);
    refused(&o, "the disk is full");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!err.contains("18446744073709551615"), "{err}");
    let left: Vec<_> = std::fs::read_dir(&mnt)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| !n.starts_with("filler") && n != "runs")
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
    // A merge that fills the disk likewise (trial 3, weak: HDF5's
    // `18446744073709551615 bytes`), whatever room its first writes find.
    for filler in std::fs::read_dir(&mnt).unwrap() {
        let filler = filler.unwrap().path();
        if filler.is_file() {
            std::fs::remove_file(filler).unwrap();
        }
    }
    let shards: Vec<String> = (0..2)
        .map(|i| {
            let shard = s(&mnt.join(format!("s{i}.h5")));
            let part = format!("{i}/2");
            succeeded(&icrl(&[
                "dataset",
                "--env",
                "darkroom",
                "--out",
                &shard,
                "--tasks",
                "2",
                "--steps",
                "300",
                "--cost-limits",
                "0",
                "--threads",
                "1",
                "--shard",
                &part,
            ]));
            shard
        })
        .collect();
    let merged = mnt.join("all.h5");
    for room in [3_000, 6_000, 9_000, 12_000] {
        disk.fill_to(room);
        let o = icrl(&[
            "dataset",
            "merge",
            "--out",
            &s(&merged),
            &shards[0],
            &shards[1],
        ]);
        refused(&o, "the disk is full");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!err.contains("18446744073709551615"), "{room}: {err}");
        let left: Vec<_> = std::fs::read_dir(&mnt)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| !n.starts_with("filler") && !n.starts_with('s') && n != "runs")
            .collect();
        assert!(left.is_empty(), "{room}: left behind: {left:?}");
    }
    drop(disk);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Trial 3, weak: a disk that fills while a run trains ended it with the
/// OS's message twice (`metrics.jsonl: No space left on device (os error
/// 28): No space left on device (os error 28)`), without the last good
/// checkpoint or the command that resumes it. Now one message names the
/// full disk, the last good checkpoint and the resume command, and the run
/// resumes from it once there is room.
#[test]
fn a_disk_that_fills_mid_run_names_the_last_good_checkpoint_and_the_resume_command() {
    let dir = tmp("full-mid-run");
    let mnt = dir.join("disk");
    let Some(disk) = SmallDisk::mount(&mnt, 8 << 20) else {
        return;
    };
    let runs = mnt.join("runs");
    let mut args = tiny_eppo_args(&runs);
    args.extend(
        [
            "--set",
            "total_updates=100000",
            "--set",
            "checkpoint_every=20",
        ]
        .map(String::from),
    );
    let child = Command::new(env!("CARGO_BIN_EXE_icrl"))
        .args(&args)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let started = std::time::Instant::now();
    let run = loop {
        let run = std::fs::read_dir(&runs)
            .ok()
            .and_then(|mut d| d.next())
            .map(|e| e.unwrap().path());
        if let Some(run) = run.filter(|r| r.join("checkpoints/step_20").is_dir()) {
            break run;
        }
        assert!(started.elapsed().as_secs() < 120, "no first checkpoint");
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    // Filled to the last byte: the run writes meanwhile, so the filler's
    // own write may end short on the full disk.
    let filler = mnt.join("filler");
    let free = safety_envs::output::free_bytes(&mnt).unwrap() as usize;
    let _ = std::fs::write(&filler, vec![7u8; free + (1 << 20)]);
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("the disk is full"), "{err}");
    assert!(
        err.contains(&format!(
            "The last good checkpoint is {}/checkpoints/step_",
            s(&run)
        )) && err.contains("(resume from it with --resume and room on its disk)"),
        "{err}"
    );
    assert!(
        err.contains(&format!(
            "resume with: icrl pretrain --env darkroom --method eppo --resume {}",
            s(&run)
        )),
        "{err}"
    );
    assert!(
        !err.contains("os error 28") && !err.contains("No space left on device"),
        "the OS's account, once at most, not twice: {err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    let left: Vec<_> = std::fs::read_dir(run.join("checkpoints"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".tmp"))
        .collect();
    assert!(left.is_empty(), "no partial checkpoint: {left:?}");
    // With room again, the run resumes from its last good checkpoint.
    for filler in std::fs::read_dir(&mnt).unwrap() {
        let filler = filler.unwrap().path();
        if filler.is_file() {
            std::fs::remove_file(filler).unwrap();
        }
    }
    let (r, last) = (s(&run), icrl::checkpoint::RunDir::open(&run).unwrap());
    let last = last.latest_checkpoint().unwrap().unwrap();
    let done: u64 = last
        .to_string_lossy()
        .rsplit("step_")
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let more = format!("total_updates={}", done + 2);
    succeeded(&icrl(&[
        "pretrain", "--env", "darkroom", "--resume", &r, "--set", &more,
    ]));
    drop(disk);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Trial 3, weak: SIGINT during the in-context check at the end of a run
/// printed "finishing the current update and writing a checkpoint" (training
/// was over, its checkpoint written) and the check went on. Now the signal
/// says what is true, that the checkpoint is written and the summary is
/// skipped, with the command that evaluates it, and ends the process.
#[test]
fn a_stop_after_training_says_the_checkpoint_is_written_and_skips_the_check() {
    use std::io::BufRead;
    let dir = tmp("stop-in-check");
    let mut args = tiny_eppo_args(&dir);
    // Long episodes in a long context: the check takes seconds.
    for set in [
        "max_episode_steps=200",
        "k_min=1",
        "k_max=1",
        "n_envs=1",
        "model.max_len=4000",
    ] {
        args.extend(["--set".to_string(), set.to_string()]);
    }
    let mut child = Command::new(env!("CARGO_BIN_EXE_icrl"))
        .args(&args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdout = std::io::BufReader::new(child.stdout.take().unwrap());
    let mut printed = String::new();
    while !printed.contains(" finished: ") {
        assert!(stdout.read_line(&mut printed).unwrap() > 0, "{printed}");
    }
    // SAFETY: kill(2) on the child this test started.
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut stdout, &mut rest).unwrap();
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    let run = std::fs::read_dir(&dir)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let checkpoint = run.join("checkpoints/step_2");
    assert!(checkpoint.join("manifest.json").is_file());
    assert_eq!(out.status.code(), Some(130), "{err}");
    assert!(
        err.contains(&format!(
            "stop requested: training is over and its checkpoint {} is written; the summary \
             (learning curve, in-context check) is skipped. Evaluate it with:\n  cargo xtask \
             eval --checkpoint {}",
            s(&checkpoint),
            s(&std::path::absolute(&checkpoint).unwrap())
        )),
        "{err}"
    );
    assert!(!err.contains("finishing the current update"), "{err}");
    assert!(!rest.contains("in-context check"), "skipped: {rest}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The printed eval command works from any folder (trial 3, weak: with a
/// relative `--out`, it named the checkpoint relative to where pretrain ran,
/// not where `cargo xtask` runs, the workspace): pretrain here runs in `dir`
/// with `--out "my runs"`, the printed command in the test's own folder.
#[test]
fn the_printed_eval_command_works_as_printed() {
    // A path with a space: the command must be quoted to survive pasting.
    let dir = tmp("printed");
    let args = tiny_eppo_args(Path::new("my runs"));
    let stdout = succeeded(
        &Command::new(env!("CARGO_BIN_EXE_icrl"))
            .args(&args)
            .current_dir(&dir)
            .output()
            .unwrap(),
    );
    let run = std::fs::read_dir(dir.join("my runs"))
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    assert_ne!(std::env::current_dir().unwrap(), dir);
    let line = stdout
        .lines()
        .skip_while(|l| !l.starts_with("evaluate it with:"))
        .nth(1)
        .unwrap_or_else(|| panic!("no eval command: {stdout}"));
    let words = shlex::split(line.trim()).unwrap_or_else(|| panic!("not shell words: {line}"));
    assert_eq!(words[..3], ["cargo", "xtask", "eval"], "{line}");
    let ck = words.iter().position(|w| w == "--checkpoint").unwrap();
    assert_eq!(
        Path::new(&words[ck + 1]).canonicalize().ok(),
        run.join("checkpoints/step_2").canonicalize().ok(),
        "{line}"
    );
    // `cargo xtask eval` passes its arguments to `icrl eval`: run them, on a
    // tiny task set, into a temporary folder.
    let mut args: Vec<String> = vec!["eval".into()];
    let mut rest = words[3..].iter();
    while let Some(w) = rest.next() {
        if w == "--out" {
            rest.next();
        } else {
            args.push(w.clone());
        }
    }
    let out = s(&dir.join("eval"));
    for a in [
        "--tasks",
        "1",
        "--episodes",
        "2",
        "--n-budgets",
        "1",
        "--threads",
        "1",
        "--out",
        &out,
    ] {
        args.push(a.into());
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    succeeded(&icrl(&args));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Trial 3, weak: `eval --checkpoint RUN/checkpoints/step_N --out
/// RUN/checkpoints/step_N` wrote its reports among the checkpoint's files.
/// An --out that is or lies inside a checkpoint folder, or inside a run's
/// `checkpoints/`, is refused by name before anything is written; one
/// beside the checkpoints is not.
#[test]
fn eval_never_writes_into_a_checkpoint_folder() {
    let dir = tmp("eval-into-checkpoint").canonicalize().unwrap();
    let run = dir.join("run");
    let ck = run.join("checkpoints/step_4");
    std::fs::create_dir_all(&ck).unwrap();
    std::fs::write(run.join("config.toml"), "seed = 0\n").unwrap();
    std::fs::write(ck.join("manifest.json"), "{}").unwrap();
    let listing = |p: &Path| -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(p)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    };
    let before = (listing(&ck), listing(&run.join("checkpoints")));
    for (out, inside) in [
        (ck.clone(), ck.clone()),
        (ck.join("eval"), ck.clone()),
        (ck.join("a/../b"), ck.clone()),
        (run.join("checkpoints"), run.join("checkpoints")),
        (run.join("checkpoints/eval"), run.join("checkpoints")),
    ] {
        let got = eval(&[&ck], &out, &[]);
        refused(&got, "lies inside the checkpoint");
        refused(&got, &s(&inside));
        refused(&got, "pass another --out");
        let replot = icrl(&["eval", "--from", &s(&dir), "--out", &s(&out)]);
        refused(&replot, "pass another --out");
    }
    assert_eq!(
        (listing(&ck), listing(&run.join("checkpoints"))),
        before,
        "nothing written"
    );
    // Beside the checkpoints, in the run folder, is allowed.
    succeeded(&eval(&[], &run.join("eval"), &[]));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Fails unless clap refused the arguments (exit 2) with `want`.
fn usage_error(out: &Output, want: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "a usage error: {err}");
    assert!(err.contains(want), "expected {want:?} in: {err}");
}

#[test]
fn negative_numbers_are_named_not_read_as_flags() {
    let dir = tmp("negative");
    let h5 = s(&dir.join("h.h5"));
    let not_a_count = "\"-1\" is not a count";
    let d = |flag: &str, v: &str| icrl(&["dataset", "--env", "darkroom", "--out", &h5, flag, v]);
    usage_error(&d("--tasks", "-1"), not_a_count);
    usage_error(&d("--steps", "-1"), not_a_count);
    refused(
        &d("--cost-limits", "-1"),
        "cost limit -1 must be finite and non-negative",
    );
    // Fewer steps than one PPO-Lagrangian rollout were rounded up in silence.
    refused(
        &d("--steps", "1"),
        "--steps 1: a PPO-Lagrangian history is made of whole rollouts of",
    );
    assert!(!dir.join("h.h5").exists());
    let e = |flag: &str| icrl(&["eval", "--env", "darkroom", flag, "-1"]);
    usage_error(&e("--episodes"), not_a_count);
    usage_error(&e("--tasks"), not_a_count);
    usage_error(&e("--n-budgets"), not_a_count);
    refused(&e("--rtg"), "--rtg -1: must be in [0, 10000]");
    usage_error(
        &icrl(&["plot-training", &s(&dir), "--window", "-1"]),
        not_a_count,
    );
    // plot-training of a garbage metrics.jsonl: refused, no empty figure.
    std::fs::write(dir.join("metrics.jsonl"), "garbage\n{\"x\": 1}\n").unwrap();
    refused(
        &icrl(&["plot-training", &s(&dir)]),
        "no metric records (2 lines, none a JSON object with env_steps)",
    );
    assert!(!dir.join("learning_curve.png").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn refused_runs_and_evals_leave_no_empty_folders() {
    let dir = tmp("leftovers");
    let out = dir.join("eval");
    refused(
        &icrl(&[
            "eval",
            "--env",
            "darkroom",
            "--checkpoint",
            &s(&dir.join("none")),
            "--out",
            &s(&out),
        ]),
        "none",
    );
    assert!(!out.exists(), "no empty --out folder");
    let h5 = dir.join("h.h5");
    succeeded(&dataset(&s(&h5), &[]));
    let runs = dir.join("runs");
    refused(
        &icrl(&[
            "pretrain",
            "--env",
            "darkroom",
            "--method",
            "ad",
            "--dataset",
            &s(&h5),
            "--out",
            &s(&runs),
            "--set",
            "batch_size=1000000000",
        ]),
        "needs about",
    );
    refused(
        &icrl(&[
            "pretrain",
            "--env",
            "darkroom",
            "--method",
            "ad",
            "--dataset",
            &s(&h5),
            "--out",
            &s(&runs),
            "--set",
            "model.max_len=1",
        ]),
        "model.max_len = 1: must be at least 2",
    );
    let left: Vec<_> = std::fs::read_dir(&runs)
        .map(|d| d.map(|e| e.unwrap().path()).collect())
        .unwrap_or_default();
    assert!(left.is_empty(), "no empty run folder: {left:?}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Trial 3, weak: a fork refused after its folder was made (the folder left
/// behind, the error naming a folder the user never asked for), refusals
/// that spoke of "the --out folder", a 4,000-character `--fork` path named
/// by the source file, garbage lines of `metrics.jsonl` left out of a fork
/// in silence. Settings are checked before anything is made; a start
/// refused later removes the fork (and the folders made for it); each
/// refusal names `--fork` and a long path shortened; left-out lines are
/// named in a warning.
#[test]
fn a_refused_fork_leaves_nothing_and_names_the_fork_option() {
    let dir = tmp("fork-refused");
    let (run, _) = tiny_eppo_run(&dir.join("runs"));
    let forks = dir.join("forks");
    let fork = |to: &Path, sets: &[&str]| {
        let (r, f) = (s(&run), s(to));
        let mut args = vec![
            "pretrain", "--env", "darkroom", "--resume", &r, "--fork", &f,
        ];
        for set in sets {
            args.extend(["--set", set]);
        }
        icrl(&args)
    };
    let nothing_made = |what: &str| assert!(!forks.exists(), "{what}: no fork folder left");
    refused(
        &fork(&forks, &["lr=nan"]),
        "eppo config: lr = NaN: must be a finite number in (0, 1]",
    );
    nothing_made("lr=nan");
    refused(
        &fork(&forks, &[]),
        "step_2: it has done 2 updates and total_updates is 2, so the fork would train \
         nothing; pass --set total_updates=3 or more; nothing was forked",
    );
    nothing_made("total_updates");
    // Refused once the fork was made (the memory estimate needs the
    // environment): removed, named as removed.
    let big = fork(&forks, &["total_updates=4", "batch_size=1000000000"]);
    refused(&big, "needs about");
    refused(&big, "was removed: nothing was trained in it");
    nothing_made("batch_size");
    // A --fork folder the user made keeps what it held.
    std::fs::create_dir(&forks).unwrap();
    std::fs::write(forks.join("notes.txt"), "mine").unwrap();
    refused(
        &fork(&forks, &["total_updates=4", "batch_size=1000000000"]),
        "was removed",
    );
    let held: Vec<_> = std::fs::read_dir(&forks)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(held, ["notes.txt"]);
    std::fs::remove_dir_all(&forks).unwrap();
    // Refusals of the folder name --fork, not --out.
    let null = fork(Path::new("/dev/null"), &["total_updates=4"]);
    refused(&null, "/dev/null: a device, not a folder");
    refused(&null, "it is the --fork folder");
    refused(
        &fork(&run.join("sub"), &["total_updates=4"]),
        "pass --fork a folder outside every run folder",
    );
    assert!(!run.join("sub").exists());
    // A path too long for a checkpoint's files: named shortened, before
    // anything is made (it was named by the checkpoint's source file).
    let long = dir.join(
        std::iter::repeat_n("d".repeat(240), 16)
            .chain(["e".repeat(180)])
            .collect::<Vec<_>>()
            .join("/"),
    );
    let chars = s(&long).len();
    let got = fork(&long, &["total_updates=4"]);
    refused(&got, &format!("…{} ({chars} characters)", "e".repeat(48)));
    refused(&got, "more than the 4095 this system allows in a path");
    refused(&got, "pass --fork a folder whose path is at most");
    let err = String::from_utf8_lossy(&got.stderr);
    assert!(!err.contains(&s(&run)) && err.len() < 700, "{err}");
    assert!(!dir.join("d".repeat(240)).exists(), "no folder made");
    // One name of 4,000 characters, relative: the system refuses it.
    let got = Command::new(env!("CARGO_BIN_EXE_icrl"))
        .current_dir(&dir)
        .args(["pretrain", "--env", "darkroom", "--resume", &s(&run)])
        .args(["--fork", &"d".repeat(4000), "--set", "total_updates=4"])
        .output()
        .unwrap();
    refused(
        &got,
        "(4000 characters): cannot create it: File name too long",
    );
    refused(&got, "it is the --fork folder");
    // Lines of the origin's metrics that are not records: named.
    let metrics = run.join("metrics.jsonl");
    let mut text = std::fs::read_to_string(&metrics).unwrap();
    text.push_str("garbage {\n{\"updates\": \"two\"}\n");
    std::fs::write(&metrics, &text).unwrap();
    let got = fork(&forks, &["total_updates=4"]);
    let err = String::from_utf8_lossy(&got.stderr).into_owned();
    succeeded(&got);
    let lines = text.lines().count();
    assert!(
        err.contains(&format!(
            "warning: {}: 2 lines are not metric records (lines {}, {}): not JSON, or without \
             its update counter; the fork's metrics.jsonl leaves them out, the original keeps \
             them",
            s(&metrics),
            lines - 1,
            lines
        )),
        "{err}"
    );
    assert_eq!(std::fs::read_to_string(&metrics).unwrap(), text);
    std::fs::remove_dir_all(&dir).unwrap();
}
