//! Fuzz harness for EPPO's settings at the edges of their bounds (trial 3's
//! third class: settings with no bound that hang a run). Every numeric
//! setting of `EppoConfig`, with the bound its own check holds (`guard::Range`
//! and `check_counts` in `icrl/src/eppo/config/*.rs`, the transformer's in
//! `model.rs`, and the bounds across sections that the tiny run's other
//! settings imply), is given with `--set NAME=VALUE` to a tiny darkroom
//! pretrain (`common::tiny_eppo_args`) at values at, just inside and just
//! outside each bound (the bound, its neighbouring floats or whole numbers),
//! and at 0, -0, tiny, huge, NaN, infinite and whole numbers past i64. The
//! oracle, for every case:
//! - refused at once: exit 1 or 2, an `error:` naming the setting, and no
//!   run folder left in `--out`; or
//! - trained to its end within `ICRL_FUZZ_SETTINGS_SECONDS` (default 60; a
//!   case still running then is a hang): exit 0 and the last checkpoint
//!   written;
//! - never a panic (101), an abort (134), a signal or a backtrace.
//!
//! Two settings make a run long by request (`total_updates` high,
//! `replay_ratio` low, down to the bound its check allows): a case of
//! theirs still running after `ICRL_FUZZ_LONG_SECONDS` (default 4) is sent
//! SIGTERM and must stop within 20 s with exit 130 and the resume command.
//!
//! The cases (about a thousand) are shuffled under `ICRL_FUZZ_SEED` and the first
//! `ICRL_FUZZ_CASES` run (default 32, under a minute); `ICRL_FUZZ_CASES=0`
//! runs them all; `ICRL_FUZZ_VERBOSE=1` prints each case and its verdict.
//! Values that would be accepted yet fill the machine (a batch of a
//! million) are not tried: above the tiny run's own sizes, memory-bounded
//! counts get only values the memory estimate refuses.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;

mod common;
use common::tiny_eppo_args;

fn env_number<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// What a setting's check allows, given the tiny run's other settings.
#[derive(Clone, Copy)]
enum Bounds {
    /// A number between `low` and `high` (either end in or out of range, as
    /// the check says: both neighbours of each end are tried).
    Number(f64, f64),
    /// A whole number in `low ..= high`; `None`: no upper bound but i64's
    /// (or, where `memory` is set, the memory estimate's).
    Count(i128, Option<i128>),
}

struct Setting {
    name: &'static str,
    bounds: Bounds,
    /// Past the tiny run's sizes only values far past the memory estimate.
    memory: bool,
    /// Its value lengthens the run by request (stopped by SIGTERM, not a hang).
    long: bool,
}

const fn number(name: &'static str, low: f64, high: f64) -> Setting {
    Setting {
        name,
        bounds: Bounds::Number(low, high),
        memory: false,
        long: false,
    }
}

const fn count(name: &'static str, low: i128, high: Option<i128>) -> Setting {
    Setting {
        name,
        bounds: Bounds::Count(low, high),
        memory: false,
        long: false,
    }
}

const fn sized(name: &'static str, low: i128) -> Setting {
    Setting {
        memory: true,
        ..count(name, low, None)
    }
}

const INF: f64 = f64::INFINITY;

/// Every numeric EPPO setting and its bounds in the tiny run
/// (`max_episode_steps = 6`, `k_min = k_max = 2`, `model.max_len = 12`,
/// `replay_capacity = 1000`, `total_updates = 2`, `ctg` in [2, 4], the
/// quick preset's `lambda_max = 0.3` and penalty `hindsight`).
fn settings() -> Vec<Setting> {
    vec![
        // [run]
        count("seed", 0, Some(i64::MAX as i128)),
        count("torch_threads", 0, Some(1024)),
        count("learner_threads", 0, Some(1024)),
        count("env_threads", 1, None),
        count("checkpoint_every", 1, None),
        count("keep_checkpoints", 0, None),
        count("keep_every", 0, None),
        // [tasks]: a trajectory of k_max * max_episode_steps fits max_len 12.
        count("max_episode_steps", 1, Some(6)),
        count("k_min", 1, Some(2)),
        count("k_max", 2, Some(2)),
        // Budgets at most 1e6 (float32 draws between them).
        number("ctg_min", 0.0, 4.0),
        number("ctg_max", 2.0, 1e6),
        sized("n_envs", 1),
        count("task_pool", 0, None),
        // [model]: d_model divisible by n_heads = 2 and even (sinusoids).
        sized("model.d_model", 2),
        count("model.n_heads", 1, Some(16)),
        count("model.n_layers", 1, Some(64)),
        sized("model.d_ff", 1),
        sized("model.max_len", 12),
        number("model.attn_dropout", 0.0, 1.0),
        number("model.resid_dropout", 0.0, 1.0),
        number("model.embd_dropout", 0.0, 1.0),
        sized("encoder_hidden", 1),
        sized("head_hidden", 1),
        sized("n_critics", 1),
        // [optimisation]
        number("lr", 0.0, 1.0),
        number("beta1", 0.0, 1.0),
        number("beta2", 0.0, 1.0),
        // At least float32's smallest normal number.
        number("adam_eps", f64::from(f32::MIN_POSITIVE), 1.0),
        number("grad_clip", 0.0, INF),
        number("critic_weight", 0.0, INF),
        sized("batch_size", 1),
        Setting {
            long: true,
            ..count("total_updates", 1, None)
        },
        count("updates_per_round", 1, None),
        count("learning_starts", 0, Some(1000)),
        // At least total_updates / 1e10 environment steps.
        Setting {
            long: true,
            ..number("replay_ratio", 2e-10, INF)
        },
        // [targets]: n_step within the longest trajectory, 12 steps.
        number("gamma", 0.0, 1.0),
        number("tau", 0.0, 1.0),
        count("n_step", 1, Some(12)),
        number("reward_scale", 0.0, 1e6),
        Setting {
            memory: true,
            ..count("replay_capacity", 12, None)
        },
        // [constraint]: lambda_init <= lambda_max = 0.3; a price only under
        // penalty "excess" or "saute".
        number("lambda_lr", 0.0, INF),
        number("lambda_max", 0.0, INF),
        number("lambda_init", 0.0, 0.3),
        count("lambda_warmup_updates", 0, None),
        number("constraint_after_revisit", 0.0, 1.0),
        count("constraint_revisit_rounds", 1, None),
        number("over_budget_cost_price", 0.0, 0.0),
        // [exploration]: a target entropy moves a positive entropy_coef.
        number("eps_start", 0.0, 1.0),
        number("eps_end", 0.0, 1.0),
        number("eps_last_start", 0.0, 1.0),
        number("eps_last_end", 0.0, 1.0),
        count("eps_decay_steps", 0, None),
        number("entropy_coef", 0.0, INF),
        number("entropy_coef_lr", 0.0, INF),
        number("target_entropy", -INF, INF),
        // [novelty] and [goal]: the shares hide slots not shown here.
        number("novelty_bonus", 0.0, INF),
        number("novelty_cell", 0.0, INF),
        number("relabel_prob", 0.0, 1.0),
        number("dense_reward_coef", 0.0, INF),
        number("goal_recall_coef", 0.0, INF),
        number("goal_hidden_share", 0.0, 0.0),
        number("hazard_hidden_share", 0.0, 0.0),
    ]
}

/// Values any number may meet: zero, signed zero, tiny, huge, not numbers,
/// whole numbers past i64.
const ANY_NUMBER: [&str; 17] = [
    "0",
    "-0",
    "-0.0",
    "5e-324",
    "1e-300",
    "-1e-300",
    "1e300",
    "-1e300",
    "nan",
    "inf",
    "-inf",
    "1",
    "-1",
    "9223372036854775808",
    "18446744073709551616",
    "1e400",
    "0x10",
];

/// Values any count may meet; none of them a size the machine could hold
/// yet would be slow to fill (those are left out on purpose).
const ANY_COUNT: [&str; 16] = [
    "0",
    "-0",
    "-1",
    "1",
    "1.5",
    "1e-300",
    "nan",
    "inf",
    "1e12",
    "4294967296",
    "9223372036854775807",
    "9223372036854775808",
    "-9223372036854775809",
    "18446744073709551616",
    "\"7\"",
    "",
];

/// A float as TOML reads it back exactly (Rust's shortest round trip).
fn float(x: f64) -> String {
    match x {
        x if x.is_nan() => "nan".into(),
        x if x == INF => "inf".into(),
        x if x == -INF => "-inf".into(),
        x => format!("{x:?}"),
    }
}

/// Every value tried for `s`: the common ones, each bound, and the
/// neighbouring floats or whole numbers either side of it.
fn values(s: &Setting) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    match s.bounds {
        Bounds::Number(low, high) => {
            out.extend(ANY_NUMBER.map(String::from));
            for b in [low, high].into_iter().filter(|b| b.is_finite()) {
                out.extend([b.next_down(), b, b.next_up()].map(float));
                out.extend([b - 1e-9, b + 1e-9].map(float));
            }
        }
        Bounds::Count(low, high) => {
            let safe =
                |v: &str| !s.memory || v.parse::<i128>().map_or(true, |n| n <= 2 || n >= 1 << 32);
            out.extend(ANY_COUNT.iter().filter(|v| safe(v)).map(|v| v.to_string()));
            for b in [Some(low), high].into_iter().flatten() {
                out.extend([b - 1, b, b + 1].map(|n| n.to_string()));
            }
        }
    }
    out.sort();
    out.dedup();
    out
}

/// The case's verdict: its failures (empty when it behaved).
fn verdict(s: &Setting, value: &str, dir: &Path, limit: Duration, long: Duration) -> Vec<String> {
    let out = dir.join("runs");
    let mut args = tiny_eppo_args(&out);
    args.extend(["--set".to_string(), format!("{}={value}", s.name)]);
    let child = Command::new(env!("CARGO_BIN_EXE_icrl"))
        .args(&args)
        .current_dir(dir)
        .env("RUST_BACKTRACE", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start icrl");
    let wait = if s.long { long } else { limit };
    let (status, stdout, stderr, stopped) = finish(child, wait);
    let mut failures = crashes(&stderr);
    if stopped && !s.long {
        failures.push(format!("still running after {} s (a hang)", wait.as_secs()));
    }
    let Some(code) = status else {
        failures.push("still running 20 s after SIGTERM, or killed by a signal".into());
        return failures;
    };
    let runs: Vec<_> = std::fs::read_dir(&out)
        .map(|d| d.flatten().map(|e| e.path()).collect())
        .unwrap_or_default();
    let short = s.name.rsplit('.').next().unwrap();
    match code {
        130 if stopped => {
            if !stderr.contains("resume with") {
                failures.push("stopped by SIGTERM without the resume command".into());
            }
        }
        _ if stopped => failures.push(format!("SIGTERM ended it with exit {code}, not 130")),
        0 => {
            let total = if s.name == "total_updates" {
                value
            } else {
                "2"
            };
            let step = Path::new("checkpoints").join(format!("step_{total}"));
            if runs.len() != 1 || !runs[0].join(&step).join("manifest.json").is_file() {
                failures.push(format!("exit 0 but no {} in {runs:?}", step.display()));
            }
            if !stdout.contains("finished") {
                failures.push("exit 0 without `finished`".into());
            }
        }
        1 | 2 => {
            if !stderr.contains("error:") || !stderr.contains(short) {
                failures.push(format!("refused without naming {short}: {}", stderr.trim()));
            }
            if !runs.is_empty() {
                failures.push(format!("refused, leaving {runs:?} behind"));
            }
        }
        code => failures.push(format!("exit {code}: {}", stderr.trim())),
    }
    failures
}

/// Waits for `child` until `limit`; past it, SIGTERM and 20 s more. Returns
/// its exit code (`None`: killed by us, or by a signal), its output and
/// whether it was sent SIGTERM.
fn finish(mut child: Child, limit: Duration) -> (Option<i32>, String, String, bool) {
    let start = Instant::now();
    let mut stopped = false;
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status.code();
        }
        if !stopped && start.elapsed() > limit {
            let pid = child.id().to_string();
            let _ = Command::new("kill").args(["-TERM", &pid]).status();
            stopped = true;
        }
        if stopped && start.elapsed() > limit + Duration::from_secs(20) {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let out = child.wait_with_output().unwrap();
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    (status, text(&out.stdout), text(&out.stderr), stopped)
}

/// A crash's marks on stderr.
fn crashes(stderr: &str) -> Vec<String> {
    [
        "panicked at",
        "stack backtrace",
        "terminate called",
        "core dumped",
    ]
    .into_iter()
    .filter(|mark| stderr.contains(mark))
    .map(|mark| format!("stderr shows `{mark}`"))
    .collect()
}

#[test]
fn settings_at_their_bounds_are_refused_by_name_or_train_to_the_end() {
    let limit = Duration::from_secs(env_number("ICRL_FUZZ_SETTINGS_SECONDS", 60));
    let long = Duration::from_secs(env_number("ICRL_FUZZ_LONG_SECONDS", 4));
    let mut rng = ChaCha8Rng::seed_from_u64(env_number("ICRL_FUZZ_SEED", 55));
    let all = settings();
    let mut cases: Vec<(&Setting, String)> = all
        .iter()
        .flat_map(|s| values(s).into_iter().map(move |v| (s, v)))
        .collect();
    cases.shuffle(&mut rng);
    let n = match env_number("ICRL_FUZZ_CASES", 32) {
        0 => cases.len(),
        n => n.min(cases.len()),
    };
    let root = std::env::temp_dir().join(format!("icrl-fuzz-settings-{}", std::process::id()));
    let verbose = std::env::var_os("ICRL_FUZZ_VERBOSE").is_some();
    let mut bad = Vec::new();
    for (i, (s, value)) in cases.iter().take(n).enumerate() {
        let dir = root.join(format!("case{i}"));
        std::fs::create_dir_all(&dir).unwrap();
        let start = Instant::now();
        let failures = verdict(s, value, &dir, limit, long);
        if verbose {
            let took = start.elapsed().as_secs_f64();
            eprintln!("case {i}: {}={value} ({took:.1} s): {failures:?}", s.name);
        }
        if !failures.is_empty() {
            bad.push(format!("--set {}={value}: {}", s.name, failures.join("; ")));
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
    let _ = std::fs::remove_dir_all(&root);
    assert!(
        bad.is_empty(),
        "{} of {n} cases misbehaved:\n{}",
        bad.len(),
        bad.join("\n")
    );
}
