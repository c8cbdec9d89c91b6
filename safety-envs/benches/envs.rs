//! Environment throughput, as ratios measured in the same run.
//!
//! ```text
//! cargo bench -p safety-envs --bench envs      (or: cargo xtask bench envs)
//! ```
//!
//! Plain timing loops (no harness); each figure is the best of several
//! repetitions, interleaved with its baseline so machine noise hits both.
//! Set `ENVS_BENCH_QUICK=1` for a short smoke run, `ENVS_BENCH_ONLY=vec` (or
//! `raw`, `reset`, `darkroom`, `paper`) to run one group.
//!
//! 1. SafeDarkMujoco Point and Car agent steps/s against `raw_step.c`, a plain
//!    C loop doing the same 50 `mj_step` per agent step (the macro action:
//!    5 Safety-Gymnasium steps x 10 physics steps) on the same compiled model
//!    (goal >= 0.95x).
//! 2. Reset time (`set_task` + `reset`, and `reset` alone) (goal <= 0.1 ms).
//! 3. SafeDarkRoom steps/s on one core (goal >= 20M).
//! 4. VecEnv steps/s with 2 threads over 1 thread (goal >= 1.8x for Point and
//!    Car; for DarkRoom, whose steps are far cheaper than a thread hand-off,
//!    goal >= 0.95x: a VecEnv must never lose to one thread).
//! 5. The paper's episode shape: K = 20 episodes of up to 75 agent steps per
//!    task, with resets.

use std::hint::black_box;
use std::time::Instant;

use safety_envs::mujoco::Data;
use safety_envs::prelude::*;

unsafe extern "C" {
    /// `benches/raw_step.c`.
    fn raw_agent_steps(
        m: *const mujoco_sys::mjModel,
        d: *mut mujoco_sys::mjData,
        agent_steps: std::ffi::c_long,
        physics_steps_per_action: std::ffi::c_int,
        actions: *const f32,
        n_actions: std::ffi::c_long,
    ) -> f64;
}

/// A fixed table of pseudo-random actions in [-1, 1] (SplitMix64), shared by
/// the Rust and C loops.
fn action_table(n: usize) -> Vec<f32> {
    let mut s = 42u64;
    (0..2 * n)
        .map(|_| {
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
        })
        .collect()
}

#[repr(C)]
struct Timespec {
    tv_sec: i64,
    tv_nsec: i64,
}

unsafe extern "C" {
    /// POSIX (glibc), for this thread's CPU clock.
    fn clock_gettime(clock: i32, tp: *mut Timespec) -> i32;
}

/// CPU seconds this thread has run (Linux `CLOCK_THREAD_CPUTIME_ID`):
/// unlike wall time, it does not count the time another process held the
/// core, so it compares two loops fairly on a loaded machine.
fn thread_cpu_seconds() -> f64 {
    const CLOCK_THREAD_CPUTIME_ID: i32 = 3;
    let mut t = Timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `t` is a valid, writable timespec.
    unsafe { clock_gettime(CLOCK_THREAD_CPUTIME_ID, &mut t) };
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

/// Wall and thread-CPU seconds taken by `f`.
fn timed(f: impl FnOnce()) -> (f64, f64) {
    let (t, c) = (Instant::now(), thread_cpu_seconds());
    f();
    (t.elapsed().as_secs_f64(), thread_cpu_seconds() - c)
}

/// Seconds taken by `f`, best of `reps`.
fn best_of(reps: usize, mut f: impl FnMut()) -> f64 {
    (0..reps)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

/// User + system CPU seconds of this process, all threads (Linux
/// `/proc/self/stat`, in clock ticks of 1/100 s); 0 where unavailable.
fn process_cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    // Fields after the parenthesised command name; utime and stime are the
    // 14th and 15th fields of the whole line.
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (ticks(11) + ticks(12)) / 100.0
}

/// The 1-minute load average (Linux), to judge how quiet the machine was.
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().map(str::to_owned))
        .unwrap_or_else(|| "?".into())
}

struct Row {
    what: String,
    value: String,
    goal: String,
    met: Option<bool>,
}

fn row(what: impl Into<String>, value: String, goal: &str, met: Option<bool>) -> Row {
    Row {
        what: what.into(),
        value,
        goal: goal.into(),
        met,
    }
}

/// A long-episode environment for pure stepping: the time limit out of reach.
fn stepping_env(robot: Robot) -> SafeDarkMujoco {
    let config = NavConfig {
        max_episode_steps: usize::MAX,
        ..NavConfig::new(robot)
    };
    let mut env = SafeDarkMujoco::new(config).expect("env");
    let task = sample_task(&env.config().spawn_config(), Orientation::Edge, 1).expect("task");
    env.set_task(&task).expect("task");
    env
}

/// Agent steps/s of the environment and of the raw C loop, interleaved.
fn mujoco_vs_raw(robot: Robot, steps: usize, reps: usize, rows: &mut Vec<Row>) {
    let actions = action_table(1024);
    let mut env = stepping_env(robot);
    let mut obs = vec![0.0f32; env.observation_space().flat_dim()];
    let model = env.model().clone();
    let mut raw_data = Data::new(&model).expect("data");
    let mut resets = 0usize;
    // Best wall and best thread-CPU time of each side.
    let (mut t_env, mut t_raw) = ([f64::INFINITY; 2], [f64::INFINITY; 2]);
    let min2 = |best: &mut [f64; 2], (w, c): (f64, f64)| {
        best[0] = best[0].min(w);
        best[1] = best[1].min(c);
    };
    for _ in 0..reps {
        env.reset(0, &mut obs).expect("reset");
        min2(
            &mut t_env,
            timed(|| {
                for t in 0..steps {
                    let a = &actions[2 * (t % 1024)..2 * (t % 1024) + 2];
                    let out = env.step(Action::Continuous(a), &mut obs).expect("step");
                    if out.done() {
                        resets += 1;
                        env.reset(0, &mut obs).expect("reset");
                    }
                }
                black_box(&obs);
            }),
        );
        raw_data.reset(&model).expect("reset");
        let (m, d) = (
            model.raw() as *const mujoco_sys::mjModel,
            raw_data.raw_mut() as *mut mujoco_sys::mjData,
        );
        min2(
            &mut t_raw,
            timed(|| {
                // SAFETY: model and data belong together and outlive the call;
                // `actions` holds 1024 pairs.
                black_box(unsafe {
                    raw_agent_steps(
                        m,
                        d,
                        steps as _,
                        PHYSICS_STEPS_PER_ACTION as _,
                        actions.as_ptr(),
                        1024,
                    )
                });
            }),
        );
    }
    let (env_rate, raw_rate) = (steps as f64 / t_env[0], steps as f64 / t_raw[0]);
    let wall_ratio = env_rate / raw_rate;
    // On a loaded machine the CPU-time ratio is the one to read.
    let ratio = t_raw[1] / t_env[1];
    rows.push(row(
        format!("{robot}: agent steps/s, env vs raw C ({PHYSICS_STEPS_PER_ACTION} mj_step each)"),
        format!(
            "CPU time {ratio:.3}x; wall {:.0} vs {:.0} = {wall_ratio:.3}x{}",
            env_rate,
            raw_rate,
            if resets > 0 {
                format!(" ({resets} goal resets)")
            } else {
                String::new()
            }
        ),
        ">= 0.95x",
        Some(ratio >= 0.95),
    ));
}

fn reset_time(robot: Robot, n: usize, rows: &mut Vec<Row>) {
    let mut env = SafeDarkMujoco::new(NavConfig::new(robot)).expect("env");
    let spawn = env.config().spawn_config();
    let tasks: Vec<Task> = (0..64)
        .map(|s| sample_task(&spawn, Orientation::Centre, s).expect("task"))
        .collect();
    let mut obs = vec![0.0f32; env.observation_space().flat_dim()];
    let t_both = best_of(3, || {
        for i in 0..n {
            env.set_task(&tasks[i % 64]).expect("task");
            env.reset(i as u64, &mut obs).expect("reset");
        }
    }) / n as f64;
    let t_reset = best_of(3, || {
        for i in 0..n {
            env.reset(i as u64, &mut obs).expect("reset");
        }
    }) / n as f64;
    let t_sample = best_of(3, || {
        for i in 0..n {
            black_box(sample_task(&spawn, Orientation::Edge, i as u64).expect("task"));
        }
    }) / n as f64;
    rows.push(row(
        format!("{robot}: set_task + reset"),
        format!(
            "{:.2} us (reset alone {:.2} us; sample_task {:.2} us)",
            t_both * 1e6,
            t_reset * 1e6,
            t_sample * 1e6
        ),
        "<= 100 us",
        Some(t_both <= 1e-4),
    ));
}

fn darkroom_rate(steps: usize, rows: &mut Vec<Row>) {
    let mut env = SafeDarkRoom::new(DarkRoomConfig::default()).expect("env");
    let task = sample_task(&env.config().spawn_config(), Orientation::Centre, 7).expect("task");
    env.set_task(&task).expect("task");
    // A fixed table of actions 0..5 (no RNG in the timed loop).
    let acts: Vec<usize> = action_table(4096)
        .iter()
        .map(|v| ((v + 1.0) * 2.4999) as usize)
        .collect();
    let mut obs = [0.0f32; 2];
    let t = best_of(5, || {
        env.reset(0, &mut obs).expect("reset");
        let mut cost = 0.0;
        for i in 0..steps {
            let out = env
                .step(Action::Discrete(acts[i & 4095]), &mut obs)
                .expect("step");
            cost += out.cost;
            if out.done() {
                env.reset(0, &mut obs).expect("reset");
            }
        }
        black_box((cost, obs));
    });
    let rate = steps as f64 / t;
    rows.push(row(
        "darkroom: steps/s on one core (with resets at episode ends)",
        format!("{:.1} M", rate / 1e6),
        ">= 20 M",
        Some(rate >= 20e6),
    ));
}

fn vec_scaling(name: EnvName, n_envs: usize, steps: usize, rows: &mut Vec<Row>) {
    let make = |threads| {
        let envs: Vec<Box<dyn CmdpEnv>> = (0..n_envs)
            .map(|_| make_env(name, &EnvOptions::default()).expect("env"))
            .collect();
        let mut v = VecEnv::new(envs, threads, true).expect("vec");
        let spawn = spawn_config(name);
        for i in 0..n_envs {
            let task = sample_task(&spawn, Orientation::Centre, i as u64).expect("task");
            v.set_task(i, &task).expect("task");
        }
        v.reset(&(0..n_envs as u64).collect::<Vec<_>>())
            .expect("reset");
        v
    };
    let table = action_table(256);
    let discrete: Vec<usize> = table
        .iter()
        .map(|v| ((v + 1.0) * 2.4999) as usize)
        .collect();
    let run = |v: &mut VecEnv| {
        best_of(3, || {
            for t in 0..steps {
                match name {
                    EnvName::DarkRoom => {
                        let o = (t * 7) % (discrete.len() - n_envs);
                        v.step(VecAction::Discrete(&discrete[o..o + n_envs]))
                            .expect("step");
                    }
                    _ => {
                        let o = 2 * ((t * 7) % (table.len() / 2 - n_envs));
                        v.step(VecAction::Continuous(&table[o..o + 2 * n_envs]))
                            .expect("step");
                    }
                }
            }
            black_box(v.observations());
        })
    };
    let (mut v1, mut v2) = (make(1), make(2));
    // Interleave so a burst of load elsewhere hits both; also record the CPU
    // time the process spent, which tells whether the work split well even
    // when the other core was busy with someone else's job.
    let (mut t1, mut t2) = (f64::INFINITY, f64::INFINITY);
    let (mut cpu1, mut cpu2) = (0.0, 0.0);
    for _ in 0..2 {
        let c = process_cpu_seconds();
        t1 = t1.min(run(&mut v1));
        cpu1 += process_cpu_seconds() - c;
        let c = process_cpu_seconds();
        t2 = t2.min(run(&mut v2));
        cpu2 += process_cpu_seconds() - c;
    }
    let total = (steps * n_envs) as f64;
    let ratio = t1 / t2;
    // 6 timed runs per thread count (2 rounds x best of 3).
    let per_step = |cpu: f64| cpu / (6.0 * total) * 1e6;
    // Cheap environments stay on the calling thread (VecEnv measures the
    // batch cost): the goal there is not to lose to one thread.
    let (goal, want) = match name {
        EnvName::DarkRoom => (">= 0.95x (never lose to 1 thread)", 0.95),
        _ => (">= 1.8x", 1.8),
    };
    rows.push(row(
        format!("{name}: VecEnv {n_envs} envs, 2 threads vs 1"),
        format!(
            "{:.0} vs {:.0} env steps/s = {ratio:.2}x (threads used {}; CPU per env step {:.2} vs {:.2} us)",
            total / t2,
            total / t1,
            v2.threads_in_use(),
            per_step(cpu2),
            per_step(cpu1)
        ),
        goal,
        Some(ratio >= want),
    ));
}

/// K episodes of 75 agent steps (time limit 75, random actions), a new task
/// per trajectory: the shape of the paper's in-context trajectories.
fn paper_shape(robot: Robot, trajectories: usize, k: usize, rows: &mut Vec<Row>) {
    let mut env = SafeDarkMujoco::new(NavConfig::new(robot)).expect("env");
    let spawn = env.config().spawn_config();
    let actions = action_table(1024);
    let mut obs = vec![0.0f32; env.observation_space().flat_dim()];
    let mut steps = 0usize;
    let t = best_of(3, || {
        steps = 0;
        for traj in 0..trajectories {
            let task = sample_task(&spawn, Orientation::Centre, traj as u64).expect("task");
            env.set_task(&task).expect("task");
            for ep in 0..k {
                env.reset(ep as u64, &mut obs).expect("reset");
                loop {
                    let i = 2 * (steps % 1024);
                    let out = env
                        .step(Action::Continuous(&actions[i..i + 2]), &mut obs)
                        .expect("step");
                    steps += 1;
                    if out.done() {
                        break;
                    }
                }
            }
        }
    });
    rows.push(row(
        format!("{robot}: paper shape, {k} episodes x 75 steps per task, with resets"),
        format!(
            "{:.0} agent steps/s ({:.0} episodes/s)",
            steps as f64 / t,
            (trajectories * k) as f64 / t
        ),
        "(Safety-Gymnasium: ~40)",
        None,
    ));
}

fn main() {
    let quick = std::env::var("ENVS_BENCH_QUICK").is_ok_and(|v| v == "1");
    let scale = if quick { 10 } else { 1 };
    let only = std::env::var("ENVS_BENCH_ONLY").ok();
    let run = |group: &str| only.as_deref().is_none_or(|o| o == group);
    let mut rows = Vec::new();
    let started = Instant::now();
    if run("raw") {
        // 50 mj_step per agent step: Point about 0.15 ms, Car about 0.6 ms.
        for (robot, steps) in [(Robot::Point, 2_000), (Robot::Car, 500)] {
            mujoco_vs_raw(robot, steps / scale, 15, &mut rows);
        }
    }
    if run("reset") {
        for robot in [Robot::Point, Robot::Car] {
            reset_time(robot, 20_000 / scale, &mut rows);
        }
    }
    if run("darkroom") {
        darkroom_rate(50_000_000 / scale, &mut rows);
    }
    if run("vec") {
        vec_scaling(EnvName::Point, 16, 400 / scale, &mut rows);
        vec_scaling(EnvName::Car, 16, 100 / scale, &mut rows);
        vec_scaling(EnvName::DarkRoom, 64, 100_000 / scale, &mut rows);
    }
    if run("paper") {
        for robot in [Robot::Point, Robot::Car] {
            // K = 20 episodes per task (Table 1, Point and Car).
            paper_shape(robot, (4 / scale).max(1), 20, &mut rows);
        }
    }

    let threads = std::thread::available_parallelism().map_or(0, |n| n.get());
    println!(
        "\nEnvironment benchmark ({threads} hardware threads, load average {} at the end{}), {:.0} s\n",
        load_average(),
        if quick { ", QUICK run" } else { "" },
        started.elapsed().as_secs_f64()
    );
    println!("| measurement | result | goal | met |");
    println!("|---|---|---|---|");
    for r in &rows {
        let met = match r.met {
            Some(true) => "yes",
            Some(false) => "NO",
            None => "-",
        };
        println!("| {} | {} | {} | {met} |", r.what, r.value, r.goal);
    }
}
