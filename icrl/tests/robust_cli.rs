//! The `icrl` binary under bad input and signals (issue 12): each bad input
//! ends in a clear message and a non-zero exit, never a panic or backtrace;
//! SIGINT/SIGTERM during `pretrain` stops with a checkpoint and the resume
//! command.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::{TINY_EPPO_SETS, fresh_dir, icrl, set_args};

fn tmp(name: &str) -> PathBuf {
    fresh_dir(&format!("robust-{name}"))
}

/// Fails unless the command failed with `want` in stderr and no panic.
fn refused(out: &Output, want: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "expected a failure: {err}");
    assert!(err.contains(want), "expected {want:?} in: {err}");
    assert!(
        !err.contains("panicked") && !err.contains("backtrace"),
        "no panic: {err}"
    );
}

#[test]
fn bad_settings_and_arguments_are_refused_clearly() {
    let dir = tmp("args");
    let out = dir.join("runs").display().to_string();
    let pretrain = |sets: &[&str]| {
        let mut args = vec!["pretrain", "--env", "darkroom", "--out", &out];
        for s in sets {
            args.extend(["--set", s]);
        }
        icrl(&args)
    };
    refused(
        &pretrain(&["lr=nan"]),
        "lr = NaN: must be a finite number in (0, 1]",
    );
    refused(&pretrain(&["lr=-1"]), "lr = -1");
    refused(
        &pretrain(&["updates_per_round=0"]),
        "updates_per_round = 0: must be at least 1",
    );
    refused(&pretrain(&["batch_size=1000000000"]), "needs about");
    refused(&pretrain(&["model.max_len=1000000000"]), "needs about");
    assert!(
        !dir.join("runs").exists(),
        "no run folder for refused settings"
    );
    refused(
        &icrl(&["pretrain", "--env", "darkroom", "--seed", "-1"]),
        "\"-1\" is not a seed",
    );
    // dataset: the output path is checked before any generation.
    let missing = dir.join("missing/h.h5").display().to_string();
    let t = Instant::now();
    refused(
        &icrl(&["dataset", "--env", "darkroom", "--out", &missing]),
        "does not exist; create it first",
    );
    assert!(
        t.elapsed() < Duration::from_secs(30),
        "refused before generating"
    );
    let out_file = dir.join("h.h5").display().to_string();
    refused(
        &icrl(&[
            "dataset",
            "--env",
            "darkroom",
            "--out",
            &out_file,
            "--tasks",
            "1000000000",
            "--steps",
            "1000000",
        ]),
        "needs about",
    );
    let as_dir = dir.display().to_string();
    refused(
        &icrl(&["dataset", "--env", "darkroom", "--out", &as_dir]),
        "it is a folder",
    );
    assert!(!PathBuf::from(format!("{as_dir}.tmp")).exists());
    // eval options.
    let eval = |extra: &[&str]| {
        let mut args = vec!["eval", "--env", "darkroom", "--out", &as_dir];
        args.extend(extra);
        icrl(&args)
    };
    refused(
        &eval(&["--episodes", "0"]),
        "--episodes 0: must be at least 1",
    );
    refused(
        &eval(&["--n-budgets", "0"]),
        "--n-budgets 0: must be at least 1",
    );
    refused(
        &eval(&["--max-episode-steps", "0"]),
        "--max-episode-steps 0",
    );
    refused(
        &eval(&["--threads", "100000"]),
        "--threads 100000: must be at most 1024",
    );
    refused(
        &icrl(&["eval", "--from", "/nonexistent/reports"]),
        "--from /nonexistent/reports: no such folder",
    );
    refused(
        &icrl(&["plot-histories", "x.h5", "--out", "x", "--bins", "0"]),
        "0 is not in 1..=100000",
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Starts a tiny EPPO run that would take very long, and waits until it has
/// logged its first round (so the signal handler is installed).
// The child goes back to the caller, which waits for it (`wait` below).
#[allow(clippy::zombie_processes)]
fn start_long_run(out: &Path) -> (Child, PathBuf) {
    // Tiny, but with more updates and checkpoints than it will ever reach.
    let sets = TINY_EPPO_SETS
        .into_iter()
        .chain(["total_updates=1000000", "checkpoint_every=1000000"]);
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_icrl"));
    // The `icrl` form of the resume line is checked: not started by xtask.
    cmd.env_remove("ICRL_VIA_XTASK")
        .args(["pretrain", "--env", "darkroom", "--out"])
        .arg(out);
    cmd.args(set_args(sets));
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start icrl pretrain");
    let t = Instant::now();
    loop {
        let run = std::fs::read_dir(out)
            .ok()
            .and_then(|mut d| d.next())
            .and_then(|e| e.ok())
            .map(|e| e.path());
        if let Some(run) = run
            && std::fs::read_to_string(run.join("metrics.jsonl"))
                .is_ok_and(|m| m.lines().count() >= 2)
        {
            return (child, run);
        }
        if t.elapsed() > Duration::from_secs(120) {
            let _ = child.kill();
            let out = child.wait_with_output().unwrap();
            panic!(
                "the run never logged a round: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn wait(mut child: Child, limit: Duration) -> Output {
    let t = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!("the run did not stop within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

fn signal(pids: &str, script: &str) {
    let status = Command::new("bash")
        .arg("-c")
        .arg(script.replace("PID", pids))
        .status()
        .unwrap();
    assert!(status.success());
}

#[test]
fn first_signal_checkpoints_and_prints_the_resume_command() {
    let out = tmp("sigint");
    let (child, run) = start_long_run(&out);
    signal(&child.id().to_string(), "kill -INT PID");
    let o = wait(child, Duration::from_secs(60));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(130), "{err}");
    assert!(err.contains("stop requested"), "{err}");
    let resume = format!(
        "resume with: icrl pretrain --env darkroom --method eppo --resume {}",
        run.display()
    );
    assert!(err.contains(&resume), "{err}");
    // The checkpoint holds the last update that metrics.jsonl reports.
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let last: serde_json::Value = serde_json::from_str(metrics.lines().last().unwrap()).unwrap();
    let updates = last["updates"].as_u64().unwrap();
    assert!(updates >= 2);
    let ckpt = run.join(format!("checkpoints/step_{updates}"));
    assert!(ckpt.join("manifest.json").is_file(), "{}", ckpt.display());
    // The printed command continues the run (here to two more updates).
    let total = format!("total_updates={}", updates + 2);
    let run_s = run.display().to_string();
    let o = icrl(&[
        "pretrain", "--env", "darkroom", "--resume", &run_s, "--set", &total,
    ]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(text.contains(&format!("{} updates", updates + 2)), "{text}");
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn second_signal_exits_at_once() {
    let out = tmp("sigterm");
    let (child, _) = start_long_run(&out);
    // Two different signals back to back: they cannot merge into one.
    signal(&child.id().to_string(), "kill -INT PID; kill -TERM PID");
    let o = wait(child, Duration::from_secs(30));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(130), "{err}");
    assert!(err.contains("second stop signal: exiting now"), "{err}");
    std::fs::remove_dir_all(&out).unwrap();
}
