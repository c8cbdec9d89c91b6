//! `icrl pretrain`: a preset or a resumed run's config, with `--set`
//! overrides, handed to the learner's `train`.

use std::fs;
use std::path::{Path, PathBuf};

use safety_envs::EnvName;

use crate::ad::{
    self, AdConfig, AdError, AdMetrics, AdSpec, TrainRequest, TrainSummary, preset_table,
};
use crate::checkpoint::{CheckpointError, RunDir};
use crate::eppo::{self, EppoConfig, EppoError, PretrainOptions, PretrainReport};

/// Resolves the configuration, runs [`eppo::train`] and draws the run's
/// learning curve ([`crate::plots::training::plot_learning_curve`]): a new run from the preset
/// `eppo-{env}-{preset}`, or with `resume` the run's own `config.toml`; the
/// `sets` overrides (`key=value`) apply on top in both cases.
pub fn eppo(
    env: &str,
    preset: &str,
    resume: Option<&Path>,
    sets: &[String],
    out: &Path,
) -> Result<PretrainReport, EppoError> {
    let env_name: EnvName = env.parse().map_err(|e| EppoError::Config(format!("{e}")))?;
    let cfg_err = |e: crate::presets::PresetError| EppoError::Config(e.to_string());
    let (name, mut table) = match resume {
        Some(path) => {
            let (run, _) = RunDir::resolve_resume(path)?;
            let p = run.config_path();
            let text = std::fs::read_to_string(&p).map_err(|e| CheckpointError::Io {
                path: p.clone(),
                source: e,
            })?;
            let table = text.parse::<toml::Table>().map_err(|e| {
                EppoError::Checkpoint(CheckpointError::Invalid {
                    path: p.clone(),
                    problem: e.to_string(),
                    fix: "restore the run's config.toml or start a new run".into(),
                })
            })?;
            (p.display().to_string(), table)
        }
        None => (
            format!("eppo-{env}-{preset}"),
            crate::presets::preset_table("eppo", env, preset).map_err(cfg_err)?,
        ),
    };
    crate::presets::apply_overrides(&mut table, sets).map_err(cfg_err)?;
    let cfg: EppoConfig = crate::presets::resolve(&name, table).map_err(cfg_err)?;
    let opts = PretrainOptions {
        env: env_name,
        cfg,
        out: out.to_path_buf(),
        resume: resume.map(Path::to_path_buf),
        progress: true,
    };
    let report = eppo::train(&opts)?;
    if let Err(e) = crate::plots::training::plot_learning_curve(&report.run_dir, 10) {
        eprintln!("warning: {e}");
    }
    Ok(report)
}

/// The `pretrain --method ad` command: a preset (or a resumed run's config)
/// with `--set` overrides, the dataset, a progress bar; returns the summary.
/// Without a terminal the bar is hidden and each metrics line goes to stderr.
pub fn ad(
    env: &str,
    preset: &str,
    dataset: Option<&Path>,
    resume: Option<&Path>,
    sets: &[String],
    out: &Path,
) -> Result<TrainSummary, AdError> {
    // `--resume` names a run folder (its latest checkpoint) or one
    // checkpoints/step_N folder; every file it reads is named in errors.
    let resume = match resume {
        Some(path) => {
            if path.join("spec.json").is_file() && !path.join("checkpoints").is_dir() {
                return Err(AdError::Config(format!(
                    "{}: an AD run written before checkpoints were atomic folders; it can be \
                     evaluated but not resumed: start a new run",
                    path.display()
                )));
            }
            Some(RunDir::resolve_resume(path)?)
        }
        None => None,
    };
    let damaged = |p: &Path, e: String| {
        AdError::Checkpoint(CheckpointError::Invalid {
            path: p.to_path_buf(),
            problem: e,
            fix: "restore the run's file from a copy, or start a new run".into(),
        })
    };
    let mut table = match &resume {
        Some((run, _)) => {
            let p = run.config_path();
            let text = fs::read_to_string(&p).map_err(|e| damaged(&p, e.to_string()))?;
            text.parse::<toml::Table>()
                .map_err(|e| damaged(&p, e.to_string()))?
        }
        None => preset_table(env, preset)?,
    };
    crate::presets::apply_overrides(&mut table, sets)
        .map_err(|e| AdError::Config(e.to_string()))?;
    let cfg = AdConfig::from_table(table)?;
    let dataset_path = match (dataset, &resume) {
        (Some(p), _) => p.to_path_buf(),
        (None, Some((run, _))) => {
            let p = run.path.join("spec.json");
            let text = fs::read_to_string(&p).map_err(|e| damaged(&p, e.to_string()))?;
            let spec: AdSpec =
                serde_json::from_str(&text).map_err(|e| damaged(&p, e.to_string()))?;
            PathBuf::from(spec.dataset)
        }
        (None, None) => {
            return Err(AdError::Config(
                "--method ad needs --dataset FILE (make one with `icrl dataset --env ...`)".into(),
            ));
        }
    };
    let data = crate::data::histories::read_histories(&dataset_path, Some(env))?;
    let run_dir = match &resume {
        Some((run, _)) => run.path.clone(),
        None => RunDir::create(out, env, "ad", cfg.seed)?.path,
    };
    let bar = indicatif::ProgressBar::new(cfg.updates as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{prefix} [{elapsed_precise}] {wide_bar} {pos}/{len} updates ({per_sec}, eta {eta}) {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_prefix(format!("ad {env}"));
    let hidden = bar.is_hidden();
    let req = TrainRequest {
        cfg: &cfg,
        data: &data,
        dataset_path: &dataset_path,
        run_dir: &run_dir,
        resume: resume.as_ref().map(|(_, ckpt)| ckpt.as_path()),
    };
    let fmt = |m: &AdMetrics| {
        format!(
            "update {} loss {:.4} acc {} val_loss {} val_acc {} lr {:.2e} {:.0}s",
            m.update,
            m.train_loss,
            m.train_accuracy.map_or("-".into(), |a| format!("{a:.3}")),
            m.val_loss.map_or("-".into(), |a| format!("{a:.4}")),
            m.val_accuracy.map_or("-".into(), |a| format!("{a:.3}")),
            m.learning_rate,
            m.seconds
        )
    };
    let result = ad::train(
        &req,
        &mut |m| {
            if hidden {
                eprintln!("{}", fmt(m));
            } else {
                bar.set_message(fmt(m));
            }
        },
        &mut |u| bar.set_position(u as u64),
    );
    if result.is_err() && resume.is_none() {
        // A refused start leaves no empty run folder behind.
        RunDir {
            path: run_dir.clone(),
        }
        .remove_if_unused();
    }
    let summary = result?;
    bar.finish();
    Ok(summary)
}
