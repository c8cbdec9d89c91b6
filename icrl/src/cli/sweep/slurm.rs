//! The `[slurm]` settings' bounds and the sbatch script of the whole
//! sweep, with the resources it asks for (threads, memory, time).

use std::path::{Path, PathBuf};

use safety_envs::EnvName;

use crate::eppo::EppoConfig;
use crate::run_summary::shell_word;

use super::grid::check_script_text;
use super::*;

impl SlurmOptions {
    /// Numbers and formats Slurm would refuse, or that would give a
    /// nonsensical script.
    pub(super) fn check_bounds(&self) -> Result<(), String> {
        if let Some(rate) = self.updates_per_second
            && !(rate.is_finite() && rate >= MIN_UPDATES_PER_SECOND)
        {
            return Err(format!(
                "slurm.updates_per_second = {}: must be at least {MIN_UPDATES_PER_SECOND:.3e} \
                 (one update a day; measure it with a short run on the cluster), or set \
                 slurm.time instead",
                crate::guard::short_number(rate)
            ));
        }
        if self.cpus_per_task == Some(0) {
            return Err("slurm.cpus_per_task = 0: give 1 or more".into());
        }
        if let Some(time) = &self.time
            && !slurm_time(time)
        {
            return Err(format!(
                "slurm.time = {time:?} is not a Slurm time limit: MM, MM:SS, HH:MM:SS, D-HH, \
                 D-HH:MM or D-HH:MM:SS"
            ));
        }
        if let Some(mem) = &self.mem
            && !slurm_mem(mem)
        {
            return Err(format!(
                "slurm.mem = {mem:?} is not a Slurm memory size: a whole number with an \
                 optional unit K, M, G or T (\"64G\")"
            ));
        }
        Ok(())
    }
}

/// One update a day: below it the time limit says nothing useful.
const MIN_UPDATES_PER_SECOND: f64 = 1.0 / 86_400.0;

/// Slurm's time formats: MM, MM:SS, HH:MM:SS, D-HH, D-HH:MM, D-HH:MM:SS.
pub(super) fn slurm_time(text: &str) -> bool {
    let numbers = |part: &str, most: usize| {
        let fields: Vec<&str> = part.split(':').collect();
        fields.len() <= most
            && fields
                .iter()
                .all(|f| !f.is_empty() && f.len() <= 6 && f.bytes().all(|b| b.is_ascii_digit()))
    };
    match text.split_once('-') {
        Some((days, rest)) => numbers(days, 1) && numbers(rest, 3),
        None => numbers(text, 3),
    }
}

/// Slurm's memory sizes: digits, then at most one of K, M, G, T.
fn slurm_mem(text: &str) -> bool {
    let digits = text.trim_end_matches(['K', 'M', 'G', 'T']);
    text.len() - digits.len() <= 1
        && !digits.is_empty()
        && digits.len() <= 12
        && digits.bytes().all(|b| b.is_ascii_digit())
}

/// Updates per second of the quick presets, measured on one CPU core shared
/// with other jobs (USAGE.md): the default speed for the time limit.
fn measured_updates_per_second(method: &str, env: &str, preset: &str) -> Option<f64> {
    match (method, env, preset) {
        // 7000 updates in about 90 minutes.
        ("eppo", "darkroom", "quick") => Some(1.3),
        // 4500 updates in 78 minutes (results/eppo_point_ladder, ps8).
        ("eppo", "point", "quick") => Some(0.95),
        // 11093 updates in about 95 minutes, partly beside another run
        // (results/eppo_car_ladder, ch1).
        ("eppo", "car", "quick") => Some(1.4),
        // AD: 1200 updates at 1.1-1.3 s each, one libtorch thread
        // (results/ad_darkroom_icl); Point 2.9 s and Car 2.1 s per update
        // beside other jobs (results/ad_mujoco).
        ("ad", "darkroom", "quick") => Some(0.75),
        ("ad", "point", "quick") => Some(0.34),
        ("ad", "car", "quick") => Some(0.45),
        _ => None,
    }
}

/// The `#SBATCH` resources of the array: threads and device from the
/// preset, memory from the learner's estimate, time from the updates and the
/// measured speed (1.5x, plus 10 minutes for start-up and the final check).
struct Resources {
    cpus: usize,
    /// `slurm.mem`, else the estimate in GiB (`"4G"`).
    mem: String,
    gpus: usize,
    time: String,
}

fn resources(grid: &SweepGrid) -> Result<Resources, String> {
    let s = &grid.slurm;
    let tables: Vec<toml::Table> = grid.tasks_checked()?.into_iter().map(|(_, t)| t).collect();
    // An EPPO table is in sections, an AD one flat: `setting` reads both.
    let int = |t: &toml::Table, k: &str| {
        EppoConfig::setting(t, k)
            .and_then(toml::Value::as_integer)
            .unwrap_or(0)
    };
    let updates_key = if grid.method == "ad" {
        "updates"
    } else {
        "total_updates"
    };
    let updates = tables
        .iter()
        .map(|t| int(t, updates_key))
        .max()
        .unwrap_or(0);
    // torch_threads = 0 means one per core: ask for 8.
    let threads = tables
        .iter()
        .map(|t| match int(t, "torch_threads") {
            0 => 8,
            n => n.max(int(t, "env_threads")),
        })
        .max()
        .unwrap_or(1);
    let cuda = tables
        .iter()
        .any(|t| EppoConfig::setting(t, "device").and_then(toml::Value::as_str) == Some("cuda"));
    let mem_gib = match grid.method.as_str() {
        "ad" => ad_memory_gib(grid, &tables)?,
        _ => eppo_memory_gib(grid, &tables)?,
    };
    let time = match (&s.time, s.updates_per_second) {
        (Some(t), _) => t.clone(),
        (None, rate) => {
            let rate = rate
                .or_else(|| measured_updates_per_second(&grid.method, &grid.env, &grid.preset))
                .ok_or_else(|| {
                    format!(
                        "no measured speed for {} {} {}: set [slurm] time = \"HH:MM:SS\" or \
                         [slurm] updates_per_second from a short run on the cluster",
                        grid.method, grid.env, grid.preset
                    )
                })?;
            // Bounded by check_bounds: at most 1.5 days per update.
            let seconds = (1.5 * updates as f64 / rate).min(u64::MAX as f64 / 2.0) as u64 + 600;
            format!(
                "{:02}:{:02}:{:02}",
                seconds / 3600,
                seconds % 3600 / 60,
                seconds % 60
            )
        }
    };
    Ok(Resources {
        cpus: s.cpus_per_task.unwrap_or(threads as usize),
        mem: s.mem.clone().unwrap_or_else(|| format!("{mem_gib}G")),
        gpus: s.gpus.unwrap_or(usize::from(cuda)),
        time,
    })
}

/// The sizes of the grid's environment (observation, actions).
fn net_spec(grid: &SweepGrid) -> Result<crate::eppo::NetSpec, String> {
    let env: EnvName = grid.env.parse().map_err(|e| format!("{e}"))?;
    let probe = safety_envs::make_env(env, &safety_envs::EnvOptions::default())
        .map_err(|e| e.to_string())?;
    crate::eppo::NetSpec::from_spaces(&probe.observation_space(), &probe.action_space())
        .map_err(|e| e.to_string())
}

/// Bytes to whole GiB, doubled for room to spare, at least 2.
fn doubled_gib(bytes: f64) -> u64 {
    ((2.0 * bytes) / (1u64 << 30) as f64).ceil().max(2.0) as u64
}

/// EPPO's memory estimate of the largest task, doubled, in whole GiB.
fn eppo_memory_gib(grid: &SweepGrid, tables: &[toml::Table]) -> Result<u64, String> {
    let spec = net_spec(grid)?;
    let mut most: f64 = 0.0;
    for t in tables {
        let cfg = EppoConfig::from_table("sweep", t.clone()).map_err(|e| e.to_string())?;
        most = most.max(crate::eppo::memory_estimate(&cfg, &spec).total());
    }
    Ok(doubled_gib(most))
}

/// Dataset steps AD's memory estimate assumes in a sweep: a paper-sized
/// dataset (100 tasks x 3 cost limits x 50k steps), as
/// `reliability_tests::every_shipped_preset_fits_the_memory_estimate` does.
const AD_SWEEP_DATASET_STEPS: usize = 15_000_000;

/// AD's own memory estimate ([`crate::ad::memory_estimate`]) of the largest
/// task, doubled, in whole GiB. Its largest part, the tokenised
/// dataset, grows with the dataset's steps, which are not read here (the
/// file may be large, or only on the cluster): the estimate takes a
/// paper-sized dataset ([`AD_SWEEP_DATASET_STEPS`]); `[slurm] mem` overrides it.
fn ad_memory_gib(grid: &SweepGrid, tables: &[toml::Table]) -> Result<u64, String> {
    let net = net_spec(grid)?;
    let spec = crate::ad::AdSpec {
        env: grid.env.clone(),
        obs_dim: net.obs_dim,
        action_dim: net.act_flat(),
        discrete: net.n_actions.is_some(),
        obs_mean: vec![0.0; net.obs_dim],
        obs_std: vec![1.0; net.obs_dim],
        dataset: String::new(),
        dataset_config: String::new(),
        pretrain_tasks: None,
        physics_steps_per_action: None,
        token: Some(crate::ad::TOKEN_LAYOUT.into()),
    };
    let mut most: f64 = 0.0;
    for t in tables {
        let cfg = crate::ad::AdConfig::from_table(t.clone()).map_err(|e| e.to_string())?;
        let m = crate::ad::memory_estimate(&cfg, &spec, AD_SWEEP_DATASET_STEPS);
        most = most.max(m.total());
    }
    Ok(doubled_gib(most))
}

/// The sbatch script of the whole sweep.
pub fn slurm_script(grid: &SweepGrid, icrl: &Path) -> Result<String, SweepError> {
    let grid_err = |problem: String| SweepError::Grid {
        path: grid.file.clone(),
        problem,
    };
    check_script_text("the icrl binary's path", &icrl.display().to_string()).map_err(grid_err)?;
    let r = resources(grid).map_err(grid_err)?;
    let tasks = grid.tasks();
    let mut s = String::new();
    let mut line = |l: String| {
        s.push_str(&l);
        s.push('\n');
    };
    line("#!/bin/bash".into());
    line(format!(
        "# {} x {} seeds of icrl pretrain --env {} --method {} --preset {}; written by icrl sweep --emit slurm.",
        tasks.len() / grid.seeds.len(),
        grid.seeds.len(),
        grid.env,
        grid.method,
        grid.preset
    ));
    line(format!(
        "#SBATCH --job-name=icrl-{}-{}",
        grid.env, grid.method
    ));
    line(format!("#SBATCH --array=0-{}", tasks.len() - 1));
    line(format!("#SBATCH --cpus-per-task={}", r.cpus));
    line(format!("#SBATCH --mem={}", r.mem));
    line(format!("#SBATCH --time={}", r.time));
    if r.gpus > 0 {
        line(format!("#SBATCH --gres=gpu:{}", r.gpus));
    }
    if let Some(p) = &grid.slurm.partition {
        line(format!("#SBATCH --partition={p}"));
    }
    if let Some(a) = &grid.slurm.account {
        line(format!("#SBATCH --account={a}"));
    }
    // Preempted or stopped ahead of the time limit: back in the queue, and
    // the run resumes from its checkpoint (--resume-in-out).
    line("#SBATCH --requeue".into());
    // USR1 to this script 5 minutes before the limit (TERM is preemption's).
    line("#SBATCH --signal=B:USR1@300".into());
    line(format!(
        "#SBATCH --output={}",
        grid.out.join("logs").join("%A_%a.out").display()
    ));
    // A requeued task adds to its log rather than replacing it.
    line("#SBATCH --open-mode=append".into());
    for e in &grid.slurm.extra {
        line(format!("#SBATCH {e}"));
    }
    line("set -u".into());
    line("case \"$SLURM_ARRAY_TASK_ID\" in".into());
    for t in &tasks {
        let args: Vec<String> = grid
            .pretrain_args(t)
            .iter()
            .map(|a| shell_word(Path::new(a)))
            .collect();
        line(format!("  {}) args=({}) ;;", t.index, args.join(" ")));
    }
    line("  *) echo \"no task $SLURM_ARRAY_TASK_ID\" >&2; exit 2 ;;".into());
    line("esac".into());
    line(format!(
        "\
# icrl checkpoints on SIGTERM and exits 130. Near the time limit (USR1, to
# this script only) the script sends it TERM, then requeues the task. On
# preemption or `scontrol requeue`, Slurm sends TERM to icrl itself (and
# requeues): the script only outlives it (a second TERM would stop icrl
# without its checkpoint).
requeue=0
trap 'requeue=1; kill -TERM \"$pid\" 2>/dev/null' USR1
trap ':' TERM
{} \"${{args[@]}}\" &
pid=$!
# A trapped signal ends `wait` early: wait again while icrl runs.
while :; do
  wait \"$pid\"; status=$?
  kill -0 \"$pid\" 2>/dev/null || break
done
if [ \"$requeue\" = 1 ] && [ \"$status\" = 130 ]; then
  scontrol requeue \"${{SLURM_ARRAY_JOB_ID}}_${{SLURM_ARRAY_TASK_ID}}\"
fi
exit \"$status\"",
        shell_word(icrl)
    ));
    Ok(s)
}

/// Writes `OUT/sweep.sbatch` (and `OUT/logs/`), returns its path.
pub fn emit_slurm(grid: &SweepGrid, icrl: &Path, force: bool) -> Result<PathBuf, SweepError> {
    let script = slurm_script(grid, icrl)?;
    let io = |e: std::io::Error| SweepError::Io(format!("{}: {e}", grid.out.display()));
    std::fs::create_dir_all(grid.out.join("logs")).map_err(io)?;
    let path = grid.out.join("sweep.sbatch");
    let existing = safety_envs::output::Existing::from_force(force);
    safety_envs::output::write_bytes(&path, existing, script.as_bytes())?;
    Ok(path)
}
