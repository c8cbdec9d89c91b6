//! Model / EPPO benchmarks (harness = false): `cargo bench -p icrl --bench model`.
//!
//! 1. Acting one step with the KV cache against recomputing the full context
//!    at length 1500 (Table 1 transformer, 12 trajectories): goal >= 20x.
//! 2. Trajectories collected per second (SafeDarkRoom, quick and Table 1 presets).
//! 3. One EPPO update at the quick SafeDarkRoom preset's size (batch 8 x 480
//!    steps, K = 16; `ICRL_BENCH_UPDATE=table1`: batch 32 x 1500;
//!    `ICRL_BENCH_UPDATE_SET="k_min=25,k_max=25,model.max_len=750"`: the
//!    robot presets' transformer over a context of 750 steps) against
//!    the same model and update in PyTorch eager
//!    (`icrl/benches/eppo_update_torch.py`, run with `$ICRL_TORCH_PYTHON`,
//!    default `python3`), on process CPU time: goal <= 0.8x. Also where the
//!    Rust update's time goes, by phase.
//! 4. Training speed, overlapped loop against synchronous, at the same replay
//!    ratio, on the quick SafeDarkRoom, Point and Car presets: updates per
//!    wall second and the share of a core each thread kept busy.
//!
//! `ICRL_BENCH_THREADS` (default 2) sets the libtorch threads of both sides;
//! `ICRL_BENCH_ONLY=kv,collect,update,overlap` runs a subset (default: all).

use std::process::Command;
use std::time::Instant;

use icrl::eppo::{EppoConfig, Learner, PretrainOptions, Trajectory, train};
use icrl::model::Transformer;
use icrl::presets::preset_table;
use rand::{Rng, SeedableRng};
use safety_envs::{EnvName, EnvOptions, VecEnv, make_env};
use tch::{Device, Kind, Tensor, nn};

fn median(mut xs: Vec<f64>) -> f64 {
    xs.sort_by(f64::total_cmp);
    xs[xs.len() / 2]
}

/// CPU time (user + system) of this process in seconds, from /proc/self/stat.
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // Fields after the parenthesised command name, from `state` (field 3) on:
    // utime and stime are fields 14 and 15, i.e. indices 11 and 12 here.
    let rest = stat.rsplit_once(')').map(|(_, r)| r).unwrap_or("");
    let f: Vec<&str> = rest.split_whitespace().collect();
    let field = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok()).unwrap_or(0.0);
    let ticks = field(11) + field(12);
    ticks / 100.0 // USER_HZ
}

/// Median wall and CPU seconds of `reps` calls after one warm-up.
fn timed_cpu(reps: usize, mut f: impl FnMut()) -> (f64, f64) {
    f();
    let (mut wall, mut cpu) = (vec![], vec![]);
    for _ in 0..reps {
        let (t, c) = (Instant::now(), cpu_seconds());
        f();
        wall.push(t.elapsed().as_secs_f64());
        cpu.push(cpu_seconds() - c);
    }
    (median(wall), median(cpu))
}

fn timed(reps: usize, mut f: impl FnMut()) -> f64 {
    f(); // warm-up
    median(
        (0..reps)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64()
            })
            .collect(),
    )
}

fn config(preset: &str, sets: &[&str]) -> EppoConfig {
    env_config("darkroom", preset, sets)
}

fn env_config(env: &str, preset: &str, sets: &[&str]) -> EppoConfig {
    let mut table = preset_table("eppo", env, preset).expect("built-in preset");
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    EppoConfig::apply_sets(&mut table, &sets).expect("valid overrides");
    EppoConfig::from_table(preset, table).expect("valid preset")
}

fn kv_cache_vs_full(cfg: &EppoConfig) -> (f64, f64) {
    let vs = nn::VarStore::new(Device::Cpu);
    let model = Transformer::new(vs.root(), &cfg.model.transformer).expect("valid model");
    let (b, l) = (12, cfg.model.transformer.max_len);
    let x = Tensor::randn(
        [b, l, cfg.model.transformer.d_model],
        (Kind::Float, Device::Cpu),
    );
    let full = tch::no_grad(|| timed(3, || drop(model.forward_t(&x, false).expect("forward"))));
    // Prefill 1400 positions, then time the last 100 steps one at a time.
    let prefix = l - 100;
    let steps = tch::no_grad(|| {
        let mut total = vec![];
        for _ in 0..3 {
            let mut cache = model.new_cache();
            drop(
                model
                    .forward_step(&x.narrow(1, 0, prefix), &mut cache)
                    .expect("prefill"),
            );
            let t = Instant::now();
            for i in prefix..l {
                drop(
                    model
                        .forward_step(&x.narrow(1, i, 1), &mut cache)
                        .expect("step"),
                );
            }
            total.push(t.elapsed().as_secs_f64() / 100.0);
        }
        median(total)
    });
    (full, steps)
}

fn collection(cfg: EppoConfig, rounds: usize) -> (f64, f64) {
    let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).expect("learner");
    let envs = (0..cfg.tasks.n_envs)
        .map(|_| {
            make_env(
                EnvName::DarkRoom,
                &EnvOptions {
                    max_episode_steps: Some(cfg.tasks.max_episode_steps),
                    physics_steps_per_action: cfg.tasks.physics_steps_per_action,
                },
            )
            .expect("env")
        })
        .collect();
    let mut venv = VecEnv::new(envs, cfg.run.env_threads, true).expect("vec env");
    let t = Instant::now();
    let (mut trajs, mut steps) = (0, 0);
    for _ in 0..rounds {
        let r = learner.collect(&mut venv).expect("collect");
        trajs += r.trajectories;
        steps += r.steps;
    }
    let s = t.elapsed().as_secs_f64();
    (trajs as f64 / s, steps as f64 / s)
}

/// A k-episode x 30-step trajectory of random data.
fn synthetic(k: usize, rng: &mut rand_chacha::ChaCha8Rng) -> Trajectory {
    let (t_max, n_act) = (30, 5);
    let n = k * t_max;
    let mut t = Trajectory {
        budget: rng.gen_range(1.0..15.0),
        ..Default::default()
    };
    for s in 0..n {
        t.obs
            .extend([rng.gen_range(0..9) as f32, rng.gen_range(0..9) as f32]);
        t.next_obs
            .extend([rng.gen_range(0..9) as f32, rng.gen_range(0..9) as f32]);
        let a = rng.gen_range(0..n_act);
        t.actions
            .extend((0..n_act).map(|j| if j == a { 1.0 } else { 0.0 }));
        t.action_idx.push(a as i64);
        let last = s % t_max == t_max - 1;
        t.rewards.push(0.0);
        t.costs.push(if rng.gen_bool(0.2) { 1.0 } else { 0.0 });
        t.ctg.push(t.budget);
        t.start.push(s % t_max == 0);
        t.terminated.push(false);
        t.truncated.push(last);
        t.episode.push((s / t_max) as u32);
        if last {
            t.episode_returns.push(0.0);
            t.episode_costs
                .push(t.costs[s + 1 - t_max..=s].iter().sum());
        }
    }
    t
}

fn main() {
    let threads: i32 = std::env::var("ICRL_BENCH_THREADS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(2);
    tch::set_num_threads(threads);
    let only =
        std::env::var("ICRL_BENCH_ONLY").unwrap_or_else(|_| "kv,collect,update,overlap".into());
    let run = |part: &str| only.split(',').any(|p| p.trim() == part);
    let table1 = config("table1", &[]);
    println!("# Model / EPPO benchmarks ({threads} libtorch threads)\n");
    println!("| measure | value | goal |\n|---|---|---|");
    if run("kv") {
        kv_part(&table1);
    }
    if run("collect") {
        collect_part();
    }
    if run("update") {
        let preset = std::env::var("ICRL_BENCH_UPDATE").unwrap_or_else(|_| "quick".into());
        let sets = std::env::var("ICRL_BENCH_UPDATE_SET").unwrap_or_default();
        let sets: Vec<&str> = sets.split(',').filter(|s| !s.is_empty()).collect();
        update_part(&config(&preset, &sets), threads);
    }
    if run("overlap") {
        overlap_part();
    }
}

fn kv_part(table1: &EppoConfig) {
    let (full, step) = kv_cache_vs_full(table1);
    println!(
        "| full forward, 12 x 1500 steps (Table 1 transformer) | {:.1} ms | |\n| one KV-cached step at position 1400..1500 | {:.2} ms | |\n| speed-up of cached acting | {:.1}x | >= 20x |",
        full * 1e3,
        step * 1e3,
        full / step
    );
}

fn collect_part() {
    let (tps, sps) = collection(config("quick", &[]), 3);
    println!(
        "| trajectories/s, quick preset (8 envs, K 8, t_max 30) | {tps:.2} ({sps:.0} env steps/s) | |"
    );
    let (tps, sps) = collection(config("table1", &[]), 1);
    println!(
        "| trajectories/s, Table 1 preset (12 envs, K 50, t_max 30) | {tps:.2} ({sps:.0} env steps/s) | |"
    );
}

fn update_part(cfg: &EppoConfig, threads: i32) {
    let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).expect("learner");
    // The learner sets the preset's torch_threads: the bench's count rules.
    tch::set_num_threads(threads);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    for _ in 0..cfg.optimisation.batch_size {
        learner.replay.push(synthetic(cfg.tasks.k_max, &mut rng));
    }
    let reps = 5;
    learner.update().expect("warm-up update");
    let before = learner.times;
    let (rust, rust_cpu) = timed_cpu(reps, || {
        learner.update().expect("update");
    });
    let (b, l, m) = (
        cfg.optimisation.batch_size,
        cfg.model.transformer.max_len,
        &cfg.model.transformer,
    );
    println!(
        "| one EPPO update, batch {b} x {l}, {} layers (tch) | {rust:.3} s wall, {rust_cpu:.3} s CPU | |",
        m.n_layers
    );
    // Phase shares of the timed updates (the warm-up excluded).
    let t = learner.times;
    let phases = [
        ("batch assembly", t.batch - before.batch),
        (
            "forward (online, target, heads, losses)",
            t.forward - before.forward,
        ),
        ("backward", t.backward - before.backward),
        ("grad norm, clip, Adam", t.optimizer - before.optimizer),
        ("lambda, Polyak, scalars", t.targets - before.targets),
    ];
    let total: f64 = phases.iter().map(|p| p.1).sum();
    for (name, secs) in phases {
        println!(
            "| update phase: {name} | {:.1} ms ({:.1} %) | |",
            secs / (reps + 1) as f64 * 1e3,
            100.0 * secs / total
        );
    }
    let python = std::env::var("ICRL_TORCH_PYTHON").unwrap_or_else(|_| "python3".into());
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/benches/eppo_update_torch.py");
    let arg = |x: f64| x.to_string();
    let out = Command::new(&python)
        .args([script, "--batch", &b.to_string(), "--seq", &l.to_string()])
        .args([
            "--d-model",
            &m.d_model.to_string(),
            "--heads",
            &m.n_heads.to_string(),
        ])
        .args([
            "--layers",
            &m.n_layers.to_string(),
            "--d-ff",
            &m.d_ff.to_string(),
        ])
        .args(["--hidden", &cfg.model.head_hidden.to_string()])
        .args([
            "--n-step",
            &cfg.targets.n_step.to_string(),
            "--gamma",
            &arg(cfg.targets.gamma),
        ])
        .args([
            "--tau",
            &arg(cfg.targets.tau),
            "--entropy-coef",
            &arg(cfg.exploration.entropy_coef),
        ])
        .args(["--reward-scale", &arg(cfg.targets.reward_scale)])
        .args(["--critic-weight", &arg(cfg.optimisation.critic_weight)])
        .args([
            "--reps",
            &reps.to_string(),
            "--threads",
            &threads.to_string(),
        ])
        .output();
    match out {
        Ok(o) if o.status.success() => {
            let text = String::from_utf8_lossy(&o.stdout);
            let field = |key: &str| {
                text.lines()
                    .find_map(|l| l.strip_prefix(key)?.trim().parse::<f64>().ok())
            };
            match (
                field("torch_update_seconds "),
                field("torch_update_cpu_seconds "),
            ) {
                (Some(torch), Some(torch_cpu)) => println!(
                    "| the same update, PyTorch eager | {torch:.3} s wall, {torch_cpu:.3} s CPU | |\n\
                     | tch / PyTorch, wall time | {:.2}x | |\n\
                     | **tch / PyTorch, CPU time** | **{:.2}x** | <= 0.8x |",
                    rust / torch,
                    rust_cpu / torch_cpu
                ),
                _ => println!("| PyTorch eager | unparsable output: {text} | |"),
            }
        }
        Ok(o) => println!(
            "| PyTorch eager | not run: `{python}` failed ({}); set ICRL_TORCH_PYTHON to a Python with torch 2.11 | |",
            String::from_utf8_lossy(&o.stderr)
                .lines()
                .last()
                .unwrap_or("")
        ),
        Err(e) => println!("| PyTorch eager | not run: cannot start `{python}` ({e}) | |"),
    }
}

/// Updates per wall second and busy shares of one short quick-preset run,
/// with `extra` settings on top.
fn training_speed(env: EnvName, overlap: bool, updates: u64, extra: &[&str]) -> (f64, f64, f64) {
    let out = std::env::temp_dir().join(format!("icrl-bench-overlap-{}", std::process::id()));
    let sets = [
        format!("total_updates={updates}"),
        format!("overlap={overlap}"),
        // Updates from the first round on; the ratio is the preset's.
        "learning_starts=0".into(),
        "checkpoint_every=100000".into(),
    ];
    let sets: Vec<&str> = sets
        .iter()
        .map(String::as_str)
        .chain(extra.iter().copied())
        .collect();
    let cfg = env_config(env.as_str(), "quick", &sets);
    tch::set_num_threads(cfg.run.torch_threads);
    let report = train(&PretrainOptions {
        env,
        cfg,
        out: out.clone(),
        resume: None,
        progress: false,
    })
    .expect("training");
    let text = std::fs::read_to_string(report.run_dir.join("metrics.jsonl")).expect("metrics");
    let last: serde_json::Value =
        serde_json::from_str(text.lines().last().expect("a record")).expect("json");
    let f = |k: &str| last[k].as_f64().unwrap_or(f64::NAN);
    let _ = std::fs::remove_dir_all(&out);
    (
        f("charts/updates_per_s"),
        f("charts/cpu_learner"),
        f("charts/cpu_actor"),
    )
}

fn overlap_part() {
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "| load average at the start of the training-speed runs | {} | |",
        load.split_whitespace()
            .take(3)
            .collect::<Vec<_>>()
            .join(" ")
    );
    // The idle side lends its core to the busy one: the learner's update on
    // two libtorch threads where acting is light (SafeDarkRoom, Point), the
    // environments on two threads where stepping dominates (Car).
    for (env, updates, goal, lend) in [
        (EnvName::DarkRoom, 64, 1.3, "learner_threads=2"),
        (EnvName::Point, 64, 1.5, "learner_threads=2"),
        (EnvName::Car, 32, 1.6, "env_threads=2"),
    ] {
        let (sync, sync_cpu, _) = training_speed(env, false, updates, &[]);
        for extra in [&[][..], &[lend][..]] {
            let (over, learner_cpu, actor_cpu) = training_speed(env, true, updates, extra);
            let how = extra.first().map_or(String::new(), |s| format!(", {s}"));
            println!(
                "| {env} quick, {updates} updates: updates/s synchronous vs overlapped{how} | {sync:.2} vs {over:.2}: **{:.2}x** (busy: synchronous {:.0} % of a core; overlapped learner {:.0} %, actor {:.0} %) | >= {goal}x |",
                over / sync,
                100.0 * sync_cpu,
                100.0 * learner_cpu,
                100.0 * actor_cpu
            );
        }
    }
}
