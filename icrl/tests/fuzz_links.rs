//! Fuzz harness for symbolic links in run folders (trial 3's second class:
//! writes through links into files that are not ours). Each case copies a
//! finished tiny run, replaces one of its files (the lock, the config, the
//! metrics, a checkpoint's files, the learning curve) by a symbolic link to
//! a user's file (holding the file's own bytes, or other text) or by a
//! dangling link, then runs one command on it: resume, fork, evaluate, drop
//! the replay. The oracle, for every case:
//! - the user's file keeps its bytes and stays a regular file; a dangling
//!   link's target is never created;
//! - the command ends knowing what happened: exit 0, or a failure exit with
//!   an `error:` line; never a panic (101), an abort (134) or a signal.
//!
//! Cases: `ICRL_FUZZ_CASES` (default 16, about a minute); `ICRL_FUZZ_SEED`
//! picks another stream; `ICRL_FUZZ_VERBOSE=1` prints each case.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod common;
use common::tiny_eppo_args;

fn env_number<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

fn icrl(args: &[String]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_icrl"))
        .args(args)
        .stdin(Stdio::null())
        .output()
        .expect("run icrl")
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

/// A finished darkroom EPPO run of 2 updates (tiny network, budgets [2, 4])
/// in `out`; returns its run folder.
fn tiny_run(out: &Path) -> PathBuf {
    let made = icrl(&tiny_eppo_args(out));
    assert!(
        made.status.success(),
        "{}",
        String::from_utf8_lossy(&made.stderr)
    );
    std::fs::read_dir(out)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path()
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap().flatten() {
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), &target).unwrap();
        }
    }
}

/// The run folder's files a command may read or write.
const FILES: [&str; 10] = [
    ".lock",
    "config.toml",
    "metrics.jsonl",
    "learning_curve.png",
    "checkpoints/step_2/manifest.json",
    "checkpoints/step_2/config.toml",
    "checkpoints/step_2/state.json",
    "checkpoints/step_2/model.safetensors",
    "checkpoints/step_2/optimizer.safetensors",
    "checkpoints/step_2/replay.safetensors",
];

/// The commands tried on a run folder `run`, with `case` for their outputs.
fn command(rng: &mut ChaCha8Rng, run: &Path, case: &Path) -> Vec<String> {
    let run = s(run);
    let words: Vec<&str> = match rng.gen_range(0..4) {
        0 => vec!["pretrain", "--resume", &run, "--set", "total_updates=4"],
        1 => {
            let fork = s(&case.join("fork"));
            return ["pretrain", "--resume", &run, "--fork", &fork]
                .into_iter()
                .chain(["--set", "total_updates=4"])
                .map(String::from)
                .collect();
        }
        2 => {
            let out = s(&case.join("eval"));
            return [
                "eval",
                "--checkpoint",
                &run,
                "--env",
                "darkroom",
                "--tasks",
                "1",
                "--episodes",
                "2",
                "--n-budgets",
                "1",
                "--threads",
                "1",
                "--no-random",
                "--out",
                &out,
            ]
            .map(String::from)
            .to_vec();
        }
        _ => vec!["drop-replay", &run],
    };
    words.into_iter().map(String::from).collect()
}

#[test]
fn no_command_writes_through_a_link_in_a_run_folder() {
    let cases: usize = env_number("ICRL_FUZZ_CASES", 16);
    let seed: u64 = env_number("ICRL_FUZZ_SEED", 0);
    let verbose = std::env::var("ICRL_FUZZ_VERBOSE").is_ok_and(|v| v == "1");
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let root = std::env::temp_dir().join(format!("icrl-fuzz-links-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let template = tiny_run(&root.join("template"));
    let (mut accepted, mut refused) = (0, 0);
    for case in 0..cases {
        let dir = root.join(format!("case_{case}"));
        let run = dir.join("run");
        copy_dir(&template, &run);
        let victim = run.join(FILES.choose(&mut rng).unwrap());
        let user_file = dir.join("user_file");
        let dangling = rng.gen_bool(0.2);
        let user_bytes = if rng.gen_bool(0.5) {
            std::fs::read(&victim).unwrap()
        } else {
            b"a user's notes\n".to_vec()
        };
        if !dangling {
            std::fs::write(&user_file, &user_bytes).unwrap();
        }
        std::fs::remove_file(&victim).unwrap();
        std::os::unix::fs::symlink(&user_file, &victim).unwrap();
        let args = command(&mut rng, &run, &dir);
        let what = format!(
            "case {case}: {} a {} link to {}; icrl {}",
            victim.display(),
            if dangling { "dangling" } else { "live" },
            user_file.display(),
            args.join(" ")
        );
        if verbose {
            eprintln!("{what}");
        }
        let out = icrl(&args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        let what = format!("{what}\nexit {:?}, stderr:\n{stderr}", out.status.code());
        assert!(!stderr.contains("panicked at"), "{what}");
        if verbose {
            eprintln!(
                "  exit {:?}: {}",
                out.status.code(),
                stderr.lines().last().unwrap_or("")
            );
        }
        match out.status.code() {
            Some(0) => accepted += 1,
            Some(code) if code != 101 && code != 134 => {
                assert!(stderr.contains("error:"), "{what}");
                refused += 1;
            }
            _ => panic!("{what}"),
        }
        if dangling {
            assert!(
                std::fs::symlink_metadata(&user_file).is_err(),
                "a dangling link's target was created: {what}"
            );
        } else {
            let meta = std::fs::symlink_metadata(&user_file).unwrap();
            assert!(meta.is_file(), "the user's file was replaced: {what}");
            assert_eq!(
                std::fs::read(&user_file).unwrap(),
                user_bytes,
                "written through the link: {what}"
            );
        }
    }
    std::fs::remove_dir_all(&root).unwrap();
    assert!(accepted + refused == cases);
}
