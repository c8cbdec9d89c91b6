//! `icrl dataset`: a dataset of learning histories for supervised
//! pretraining, generated with a progress bar, checked for memory first and
//! written to HDF5.

use safety_envs::EnvName;

use safety_envs::output::{Existing, Lock};

use crate::data::dataset::{DatasetConfig, DatasetError, Source, generate};
use crate::data::histories::{HistoryError, Shard};
use crate::ppo_lagrangian::PpoLagConfig;

/// The lock of one output file, `.NAME.lock` beside it (removed at the end):
/// a second `dataset` writing the same file is refused with the first's pid.
fn output_lock(out: &std::path::Path) -> Result<Lock, HistoryError> {
    let name = out
        .file_name()
        .map_or_else(|| "out".into(), |n| n.to_string_lossy().into_owned());
    let lock = out.with_file_name(format!(".{name}.lock"));
    Ok(Lock::acquire(
        &lock,
        &format!("the output {}", out.display()),
        true,
    )?)
}

/// `ppo` with the `--set NAME=VALUE`s applied; an unknown name is refused
/// with the valid ones, and `total_steps` with `--steps`, which sets it.
fn with_sets(ppo: &PpoLagConfig, sets: &[String]) -> Result<PpoLagConfig, DatasetError> {
    if sets.is_empty() {
        return Ok(ppo.clone());
    }
    let refuse = |e: String| DatasetError::Config(format!("--set: {e}"));
    if let Some(set) = sets
        .iter()
        .find(|s| s.split('=').next().map(str::trim) == Some("total_steps"))
    {
        return Err(refuse(format!(
            "{set}: a history's length is --steps; pass --steps instead"
        )));
    }
    let mut table = toml::Table::try_from(ppo).map_err(|e| refuse(e.to_string()))?;
    crate::presets::apply_overrides(&mut table, sets).map_err(|e| refuse(e.to_string()))?;
    let ppo: PpoLagConfig = table
        .try_into()
        .map_err(|e: toml::de::Error| refuse(e.to_string()))?;
    ppo.validate().map_err(|e| refuse(e.to_string()))?;
    Ok(ppo)
}

/// The `dataset` command's options (see `icrl dataset --help`).
#[derive(Clone, Debug)]
pub struct DatasetCommand {
    pub env: String,
    pub out: std::path::PathBuf,
    pub tasks: usize,
    pub steps: usize,
    /// `None`: the paper's limits for the environment.
    pub cost_limits: Option<Vec<f32>>,
    pub seed: u64,
    pub threads: usize,
    pub source: Source,
    /// Point and Car: physics steps per agent action; `None`: the default (50).
    pub physics_steps_per_action: Option<usize>,
    /// Episodes kept per history (log-spaced); `None` keeps all.
    pub keep_episodes: Option<usize>,
    /// Make only this part of the grid (`--shard I/N`).
    pub shard: Option<Shard>,
    /// `NAME=VALUE` changes to the PPO-Lagrangian learner's settings (`--set`).
    pub ppo_sets: Vec<String>,
    /// Replace an existing history file at `out` (`--force`).
    pub force: bool,
}

/// What the `dataset` command made.
#[derive(Clone, Debug)]
pub struct DatasetReport {
    pub out: std::path::PathBuf,
    pub histories: usize,
    /// Steps in the file (fewer than taken when episodes were subsampled).
    pub steps: usize,
    /// Environment steps the learners took.
    pub steps_taken: usize,
    pub episodes: usize,
    pub seconds: f64,
    pub bytes: u64,
    /// Mean episode return and cost over the first and the last 10% of
    /// episodes of every history: how much the histories improve.
    pub early: (f64, f64),
    pub late: (f64, f64),
    /// Point and Car: the macro action recorded in the file.
    pub physics_steps_per_action: Option<usize>,
}

/// Runs the `dataset` command: generates with a progress bar, writes the HDF5
/// file (atomically), and summarises it.
pub fn dataset_command(cmd: &DatasetCommand) -> Result<DatasetReport, DatasetError> {
    let env: EnvName = cmd.env.parse()?;
    let mut cfg = DatasetConfig::paper(env, cmd.tasks, cmd.seed);
    cfg.steps = cmd.steps;
    cfg.threads = cmd.threads;
    cfg.source = cmd.source;
    cfg.physics_steps_per_action = cmd.physics_steps_per_action;
    cfg.keep_episodes = cmd.keep_episodes;
    cfg.shard = cmd.shard;
    if let Some(c) = &cmd.cost_limits {
        cfg.cost_limits = c.clone();
    }
    cfg.ppo = with_sets(&cfg.ppo, &cmd.ppo_sets)?;
    cfg.validate()?;
    // PPO-Lagrangian learns in whole rollouts: fewer steps would be rounded
    // up in silence (a history of 236 steps for --steps 1).
    let rollout = cfg.ppo.num_envs * cfg.ppo.rollout_steps;
    if cfg.source == Source::PpoLagrangian && cfg.steps < rollout {
        return Err(DatasetError::Config(format!(
            "--steps {}: a PPO-Lagrangian history is made of whole rollouts of {rollout} \
             environment steps ({} environments x {} steps); pass --steps {rollout} or more",
            cfg.steps, cfg.ppo.num_envs, cfg.ppo.rollout_steps
        )));
    }
    // A bad --out fails now, not after hours of generation; a second
    // process making the same file is refused while this one runs.
    let existing = Existing::from_force(cmd.force);
    crate::data::histories::check_output_path(&cmd.out, existing)?;
    let _lock = output_lock(&cmd.out)?;
    // This shard's part of the grid (all of it unsharded).
    let grid = cfg.tasks * cfg.cost_limits.len();
    let histories = cfg.shard.map_or(grid, |s| s.range(grid).len());
    // All histories are held, then concatenated for writing: check they fit.
    {
        let probe = safety_envs::make_env(env, &safety_envs::EnvOptions::default())?;
        let o = probe.observation_space().flat_dim() as f64;
        let a = match probe.action_space() {
            safety_envs::Space::Discrete { .. } => 1.0,
            safety_envs::Space::Box { low, .. } => low.len() as f64,
        };
        let steps = histories as f64 * cfg.steps as f64;
        let mut m = crate::guard::MemoryEstimate {
            levers: "--tasks, --steps or the number of --cost-limits".into(),
            ..Default::default()
        };
        m.add(
            "histories and their copy for writing",
            2.0 * 4.0 * steps * (2.0 * o + a + 6.0),
        );
        m.check().map_err(DatasetError::Config)?;
    }
    if cfg.threads > 1024 {
        return Err(DatasetError::Config(format!(
            "threads ({}) must be at most 1024",
            cfg.threads
        )));
    }
    let total = (histories * cfg.steps) as u64;
    let bar = indicatif::ProgressBar::new(total);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{prefix} [{elapsed_precise}] {wide_bar} {pos}/{len} steps ({per_sec}, eta {eta})",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_prefix(format!(
        "{} {}{}",
        cmd.env,
        match cmd.source {
            Source::PpoLagrangian => "ppo-lagrangian",
            Source::NoisyOptimal => "noisy-optimal",
        },
        cmd.shard.map_or(String::new(), |s| format!(" shard {s}"))
    ));
    let started = std::time::Instant::now();
    let data = generate(&cfg, &|n| bar.inc(n as u64))?;
    bar.finish();
    crate::data::histories::write_histories_to(&cmd.out, &data.file, existing)?;
    let seconds = started.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(&cmd.out).map_or(0, |m| m.len());
    let (mut early, mut late, mut ne, mut nl) = ((0.0, 0.0), (0.0, 0.0), 0.0, 0.0);
    let mut episodes = 0;
    for h in &data.file.histories {
        let totals = h.episode_totals();
        episodes += totals.len();
        let k = (totals.len() / 10).max(1);
        for &(r, c) in &totals[..k.min(totals.len())] {
            early.0 += r as f64;
            early.1 += c as f64;
            ne += 1.0;
        }
        for &(r, c) in &totals[totals.len().saturating_sub(k)..] {
            late.0 += r as f64;
            late.1 += c as f64;
            nl += 1.0;
        }
    }
    Ok(DatasetReport {
        out: cmd.out.clone(),
        histories: data.file.histories.len(),
        steps: data.file.total_steps(),
        steps_taken: total as usize,
        episodes,
        seconds,
        bytes,
        early: (early.0 / ne, early.1 / ne),
        late: (late.0 / nl, late.1 / nl),
        physics_steps_per_action: data.file.info.physics_steps_per_action,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sets(s: &[&str]) -> Vec<String> {
        s.iter().map(|s| s.to_string()).collect()
    }

    /// `--set` changes the named settings only; a wrong name, a bad value
    /// and `total_steps` (which `--steps` sets) are refused, naming the fix.
    #[test]
    fn sets_change_the_ppo_settings_they_name_and_refuse_the_rest() {
        let paper = PpoLagConfig::darkroom();
        let changed = with_sets(&paper, &sets(&["learning_rate=3e-4", "update_epochs=8"])).unwrap();
        assert_eq!(changed.learning_rate, 3e-4);
        assert_eq!(changed.update_epochs, 8);
        assert_eq!(
            PpoLagConfig {
                learning_rate: paper.learning_rate,
                update_epochs: paper.update_epochs,
                ..changed
            },
            paper
        );
        let err = |s: &[&str]| with_sets(&paper, &sets(s)).unwrap_err().to_string();
        let unknown = err(&["learning_rat=1e-3"]);
        assert!(
            unknown.contains("learning_rat") && unknown.contains("learning_rate"),
            "{unknown}"
        );
        assert!(err(&["total_steps=10"]).contains("pass --steps instead"));
        let negative = err(&["learning_rate=-1"]);
        assert!(negative.contains("learning_rate"), "{negative}");
        assert!(err(&["update_epochs=0"]).contains("update_epochs"));
    }
}
