//! Fuzz harness for the command line: random argument vectors (numbers at
//! and past every edge, paths to nothing, files, folders and devices, flags
//! repeated, missing or unknown) for every `icrl` subcommand (`dataset
//! merge` and `sweep` included), run as a child
//! process. Every case must end as a program that knows what happened:
//! - no panic (exit 101), abort (134) or signal, no `panicked at`, Rust
//!   backtrace or C++ `terminate called` at the user;
//! - a failure says so on stderr and exits non-zero; an exit 0 prints no
//!   `error:`;
//! - each case runs in its own folder, and the devices it is handed as
//!   paths (`/dev/null`, `/dev/full`) stay devices.
//!
//! A case still running after `ICRL_FUZZ_CLI_SECONDS` (default 6) had
//! accepted its arguments and started work; it is killed and counts as
//! accepted. Cases: `ICRL_FUZZ_CASES` (default 24, about a minute of CI);
//! `ICRL_FUZZ_SEED` picks another stream; `ICRL_FUZZ_VERBOSE=1` prints each
//! command line before it runs.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn env_number<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// Numbers a user could type, most of them wrong.
const NUMBERS: [&str; 16] = [
    "0",
    "1",
    "2",
    "-1",
    "-0",
    "3.5",
    "1e30",
    "-1e30",
    "nan",
    "inf",
    "18446744073709551616",
    "4294967297",
    "0x10",
    "abc",
    "",
    " 7",
];

/// `--set` keys of either learner, real and not, with a number from [`NUMBERS`].
const SET_KEYS: [&str; 12] = [
    "total_updates",
    "lr",
    "batch_size",
    "n_envs",
    "tau",
    "k_max",
    "lambda_max",
    "model.max_len",
    "model.d_model",
    "max_episode_steps",
    "no_such_key",
    "",
];

/// The flags of each subcommand and the kind of value each takes.
#[derive(Clone, Copy)]
enum Value {
    Number,
    Path,
    Word(&'static [&'static str]),
    Set,
    None,
}

const ENVS: &[&str] = &["darkroom", "point", "car", "Car", "", "mars"];

fn flags(sub: &str) -> Vec<(&'static str, Value)> {
    use Value::*;
    match sub {
        "pretrain" => vec![
            ("--env", Word(ENVS)),
            ("--method", Word(&["eppo", "ad", "ppo", ""])),
            ("--preset", Word(&["quick", "table1", "table2", "x"])),
            ("--device", Word(&["cpu", "cuda", "tpu"])),
            ("--dataset", Path),
            ("--resume", Path),
            ("--seed", Number),
            ("--set", Set),
            ("--out", Path),
        ],
        "dataset" => vec![
            ("--env", Word(ENVS)),
            ("--out", Path),
            ("--tasks", Number),
            ("--steps", Number),
            (
                "--cost-limits",
                Word(&["0", "0,5", "-1", "nan", "5,,", "1e40"]),
            ),
            ("--seed", Number),
            ("--threads", Number),
            ("--source", Word(&["ppo-lagrangian", "ad-eps", "x"])),
            ("--physics-steps-per-action", Number),
            ("--keep-episodes", Number),
            (
                "--shard",
                Word(&["0/2", "1/2", "2/2", "0/0", "-1/3", "a/b", "1"]),
            ),
            ("--force", None),
        ],
        "dataset merge" => vec![("--out", Path), ("--force", None), ("SHARD", Path)],
        "sweep" => vec![
            ("--grid", Path),
            ("--emit", Word(&["slurm", "pbs", ""])),
            ("--gather", None),
            ("--tasks", Number),
            ("--episodes", Number),
            ("--n-budgets", Number),
            ("--threads", Number),
            ("--force", None),
        ],
        "eval" => vec![
            ("--checkpoint", Path),
            ("--label", Word(&["a", "a", "", "../x", "a b"])),
            ("--env", Word(ENVS)),
            ("--from", Path),
            ("--tasks", Number),
            ("--episodes", Number),
            ("--budgets", Word(&["1", "1,2", "-1", "nan", "1e30", ","])),
            ("--n-budgets", Number),
            ("--rtg", Number),
            ("--sweep", None),
            ("--no-random", None),
            ("--out", Path),
            ("--seed", Number),
            ("--batch", Number),
            ("--threads", Number),
            ("--greedy", None),
            ("--in-distribution", None),
            ("--max-episode-steps", Number),
            ("--force", None),
        ],
        "plot-training" => vec![("--window", Number), ("RUN", Path)],
        "plot-histories" => vec![
            ("--out", Path),
            ("--bins", Number),
            ("--force", None),
            ("FILE", Path),
        ],
        _ => unreachable!("{sub}"),
    }
}

/// Paths a user could give, inside the case's folder `dir` (and two devices,
/// which must never be written).
fn path(rng: &mut ChaCha8Rng, dir: &Path) -> String {
    let choices = [
        dir.join("missing/deeper"),
        dir.join("a_file.txt"),
        dir.join("a_folder"),
        dir.join("run"),
        dir.join("out.h5"),
        dir.join("with space"),
        dir.join("grid.toml"),
        PathBuf::from("/dev/null"),
        PathBuf::from("/dev/full"),
        PathBuf::from(""),
    ];
    choices.choose(rng).unwrap().display().to_string()
}

fn value(rng: &mut ChaCha8Rng, kind: Value, dir: &Path) -> Option<String> {
    Some(match kind {
        Value::Number => NUMBERS.choose(rng).unwrap().to_string(),
        Value::Path => path(rng, dir),
        Value::Word(words) => words.choose(rng).unwrap().to_string(),
        Value::Set => format!(
            "{}={}",
            SET_KEYS.choose(rng).unwrap(),
            NUMBERS.choose(rng).unwrap()
        ),
        Value::None => return None,
    })
}

/// One random command line for `sub`: a few of its flags (sometimes
/// repeated, sometimes without their value), now and then an unknown flag.
fn command_line(rng: &mut ChaCha8Rng, sub: &str, dir: &Path) -> Vec<String> {
    let all = flags(sub);
    let mut args: Vec<String> = sub.split(' ').map(String::from).collect();
    for _ in 0..rng.gen_range(0..=6) {
        let (flag, kind) = all[rng.gen_range(0..all.len())];
        if !flag.starts_with("--") {
            args.extend(value(rng, kind, dir)); // a positional argument
            continue;
        }
        args.push(flag.to_string());
        if rng.gen_bool(0.9) {
            args.extend(value(rng, kind, dir));
        }
    }
    if rng.gen_bool(0.1) {
        args.push("--no-such-flag".into());
    }
    args
}

/// The case folder's contents: a file, a folder, nothing else.
fn prepare(dir: &Path) {
    let _ = std::fs::remove_dir_all(dir);
    std::fs::create_dir_all(dir.join("a_folder")).unwrap();
    std::fs::write(dir.join("a_file.txt"), "not a checkpoint\n").unwrap();
    // A sound sweep grid of tiny runs, for `sweep --grid`.
    std::fs::write(
        dir.join("grid.toml"),
        "env = \"darkroom\"\nseeds = [0, 1]\nout = \"runs\"\n[set]\ntotal_updates = 2\n[grid]\nlr = [0.0003]\n",
    )
    .unwrap();
}

/// Runs one case; returns its verdict's failures (empty when it behaved).
fn run(args: &[String], dir: &Path, limit: Duration) -> Vec<String> {
    let mut child = Command::new(env!("CARGO_BIN_EXE_icrl"))
        .args(args)
        .current_dir(dir)
        .env("RUST_BACKTRACE", "1")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start icrl");
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break Some(status);
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let out = child.wait_with_output().unwrap();
    let Some(status) = status else {
        return Vec::new(); // accepted and working: killed by us
    };
    let stderr = String::from_utf8_lossy(&out.stderr);
    let mut failures = Vec::new();
    for crash in [
        "panicked at",
        "stack backtrace",
        "terminate called",
        "core dumped",
    ] {
        if stderr.contains(crash) {
            failures.push(format!("stderr shows `{crash}`"));
        }
    }
    match status.code() {
        None => failures.push(format!("killed by a signal ({status})")),
        Some(101) => failures.push("exit 101 (a panic)".into()),
        Some(134) => failures.push("exit 134 (an abort)".into()),
        Some(0) if stderr.contains("error:") => {
            failures.push("exit 0 after printing an error".into())
        }
        Some(0) => {}
        Some(_) if stderr.trim().is_empty() => failures.push("failed without a word".into()),
        Some(_) => {}
    }
    failures
}

#[test]
fn random_command_lines_never_crash_or_exit_0_on_a_failure() {
    let cases: usize = env_number("ICRL_FUZZ_CASES", 24);
    let limit = Duration::from_secs(env_number("ICRL_FUZZ_CLI_SECONDS", 6));
    let mut rng = ChaCha8Rng::seed_from_u64(env_number("ICRL_FUZZ_SEED", 21));
    let root = std::env::temp_dir().join(format!("icrl-fuzz-cli-{}", std::process::id()));
    let devices_before: Vec<_> = ["/dev/null", "/dev/full"]
        .iter()
        .map(|d| std::fs::metadata(d).map(|m| m.file_type()).ok())
        .collect();
    let subcommands = [
        "pretrain",
        "dataset",
        "eval",
        "plot-training",
        "plot-histories",
        "dataset merge",
        "sweep",
    ];
    let mut bad = Vec::new();
    for case in 0..cases {
        let dir = root.join(format!("case{case}"));
        prepare(&dir);
        let sub = subcommands[case % subcommands.len()];
        let args = command_line(&mut rng, sub, &dir);
        if std::env::var_os("ICRL_FUZZ_VERBOSE").is_some() {
            eprintln!("fuzz cli case {case}: icrl {args:?}");
        }
        let failures = run(&args, &dir, limit);
        if !failures.is_empty() {
            bad.push(format!(
                "case {case}: icrl {args:?}: {}",
                failures.join("; ")
            ));
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
    let devices_after: Vec<_> = ["/dev/null", "/dev/full"]
        .iter()
        .map(|d| std::fs::metadata(d).map(|m| m.file_type()).ok())
        .collect();
    assert_eq!(devices_before, devices_after, "a device was replaced");
    let _ = std::fs::remove_dir_all(&root);
    assert!(
        bad.is_empty(),
        "{} of {cases} cases misbehaved:\n{}",
        bad.len(),
        bad.join("\n")
    );
}
