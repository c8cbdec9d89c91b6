//! `icrl pretrain`: a preset or a resumed run's config, with `--set`
//! overrides, handed to the learner's `train`.

use std::fs;
use std::path::{Path, PathBuf};

use safety_envs::EnvName;

use crate::ad::{
    self, AdConfig, AdError, AdMetrics, AdSpec, TrainRequest, TrainSummary, preset_table,
};
use crate::checkpoint::{CheckpointError, ForkFrom, Forked, RunDir};
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
            let (run, ckpt) = resolve_resume(path)?;
            RunDir::check_resume_flags(&ckpt, "eppo", env)?;
            let mut p = run.config_path();
            // A lost config.toml: every EPPO checkpoint holds its own copy
            // (training writes it back to the run folder).
            if !p.exists() && ckpt.join("config.toml").is_file() {
                eprintln!(
                    "{} is missing: resuming with the copy in {}",
                    p.display(),
                    ckpt.display()
                );
                p = ckpt.join("config.toml");
            }
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
    // A run's config.toml and the config it resumes with are compared as
    // resolved configs: sections or the flat form, an empty list or none,
    // a default written or left out, are no change.
    let saved = match resume {
        Some(_) => Some(config_table(&EppoConfig::from_table(
            &name,
            table.clone(),
        )?)?),
        None => None,
    };
    EppoConfig::apply_sets(&mut table, sets)?;
    let cfg = EppoConfig::from_table(&name, table)?;
    if let (Some(saved), Some(path)) = (&saved, resume) {
        check_eppo_resume(path, saved, &config_table(&cfg)?)?;
    }
    let opts = PretrainOptions {
        env: env_name,
        cfg,
        out: out.to_path_buf(),
        resume: resume.map(Path::to_path_buf),
        progress: true,
    };
    let report = eppo::train(&opts)?;
    // Training is over and its checkpoint written: a signal now skips what
    // follows (the learning curve, the in-context check) and says so,
    // rather than promise an update and a checkpoint.
    crate::stop::saved(format!(
        "training is over and its checkpoint {} is written; the summary (learning curve, \
         in-context check) is skipped. Evaluate it with:\n  {}",
        report.last_checkpoint.display(),
        crate::run_summary::eval_command(env_name, &report.last_checkpoint)
    ));
    if let Err(e) = crate::plots::training::plot_learning_curve(&report.run_dir, 10) {
        eprintln!("warning: {e}");
    }
    Ok(report)
}

/// A config as the table its run's `config.toml` holds.
fn config_table(cfg: &EppoConfig) -> Result<toml::Table, EppoError> {
    toml::Table::try_from(cfg).map_err(|e| EppoError::Config(e.to_string()))
}

/// [`RunDir::resolve_resume`] for `--resume` and `--fork`, then
/// [`check_run_files`] on the run.
fn resolve_resume(path: &Path) -> Result<(RunDir, PathBuf), CheckpointError> {
    let (run, ckpt) = RunDir::resolve_resume(path)?;
    check_run_files(&run)?;
    Ok((run, ckpt))
}

/// Refuses to continue or branch a run whose files that a resume or fork
/// reads (`config.toml`, `spec.json`, `metrics.jsonl`) are not regular
/// files: a FIFO there blocked the read until the process was killed.
fn check_run_files(run: &RunDir) -> Result<(), CheckpointError> {
    for name in ["config.toml", "spec.json", "metrics.jsonl"] {
        let path = run.path.join(name);
        crate::guard::regular_file(&path).map_err(|problem| CheckpointError::Invalid {
            path,
            problem,
            fix: "a run's files are the regular files icrl wrote: move it away and restore the \
                  run's own from a copy"
                .into(),
        })?;
    }
    Ok(())
}

/// What `pretrain --resume-in-out` does in its `--out` folder.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum InOut {
    /// No run with a checkpoint there: start one.
    Start,
    /// Continue this run folder.
    Resume(PathBuf),
    /// This run has done every update its config (with the `--set`s) asks for.
    Finished { run: PathBuf, updates: u64 },
}

/// `pretrain --resume-in-out`: the run of `env` and `method` in `out` that
/// trained furthest is resumed, or is finished when it has done the updates
/// its `config.toml` with `sets` asks for; with none, a run starts. This is
/// how a job array task that Slurm requeued (preempted, or stopped ahead of
/// its time limit) continues its own run instead of starting again.
pub fn run_in_out(
    out: &Path,
    env: &str,
    method: &str,
    sets: &[String],
) -> Result<InOut, CheckpointError> {
    let Some((run, _, updates)) = RunDir::furthest_in(out, env, method)? else {
        return Ok(InOut::Start);
    };
    check_run_files(&run)?;
    let path = run.config_path();
    let invalid = |problem: String| CheckpointError::Invalid {
        path: path.clone(),
        problem,
        fix: "restore the run's config.toml, or move the run folder away to start again".into(),
    };
    let mut table = fs::read_to_string(&path)
        .map_err(|e| invalid(e.to_string()))?
        .parse::<toml::Table>()
        .map_err(|e| invalid(e.to_string()))?;
    let key = if method == "ad" {
        crate::presets::apply_overrides(&mut table, sets).map_err(|e| invalid(e.to_string()))?;
        "updates"
    } else {
        EppoConfig::apply_sets(&mut table, sets).map_err(|e| invalid(e.to_string()))?;
        "total_updates"
    };
    let total = EppoConfig::setting(&table, key)
        .and_then(toml::Value::as_integer)
        .ok_or_else(|| invalid(format!("no integer {key}")))?;
    Ok(if updates as i64 >= total {
        InOut::Finished {
            run: run.path,
            updates,
        }
    } else {
        InOut::Resume(run.path)
    })
}

/// Settings a resumed EPPO run may change: its length, how it saves, and
/// the machine it runs on (threads, device, and whether collection and
/// learning overlap: the replay ratio stays, so only the policy's lag does
/// not). Any other change (`lr`, `seed`, the model, `replay_ratio`, ...)
/// would make one run of two configurations, and is refused.
pub const EPPO_RESUME_MAY_CHANGE: [&str; 9] = [
    "total_updates",
    "checkpoint_every",
    "keep_checkpoints",
    "keep_every",
    "torch_threads",
    "env_threads",
    "device",
    "overlap",
    "learner_threads",
];

/// The resume rule (EPPO; AD has the same in `ad::check_resumable`): the
/// changes `--set`/`--seed` make to the run's `config.toml` are printed when
/// allowed ([`EPPO_RESUME_MAY_CHANGE`]) and refused otherwise; a
/// `total_updates` that does not extend the run is refused, and so is
/// continuing a run in place from an older checkpoint than its latest
/// (`--fork` branches a new run instead).
fn check_eppo_resume(path: &Path, saved: &toml::Table, now: &toml::Table) -> Result<(), EppoError> {
    let (run, ckpt) = RunDir::resolve_resume(path)?;
    let (allowed, refused): (Vec<_>, Vec<_>) = setting_changes(saved, now)
        .into_iter()
        .partition(|(key, _)| EPPO_RESUME_MAY_CHANGE.contains(&key.as_str()));
    if !refused.is_empty() {
        return Err(EppoError::Config(format!(
            "cannot resume {}: these settings differ from its config.toml: {}; only {} may change \
             (branch a new run with other settings with --fork DIR)",
            run.path.display(),
            refused
                .into_iter()
                .map(|(_, c)| c)
                .collect::<Vec<_>>()
                .join(", "),
            EPPO_RESUME_MAY_CHANGE.join(", ")
        )));
    }
    // Updates done: the checkpoint's manifest records them.
    let done = fs::read_to_string(ckpt.join(crate::checkpoint::MANIFEST))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v["updates"].as_u64());
    let total = EppoConfig::setting(now, "total_updates").and_then(toml::Value::as_integer);
    if let (Some(done), Some(total)) = (done, total)
        && total <= done as i64
    {
        return Err(EppoError::Config(format!(
            "cannot resume {}: it has done {done} updates and total_updates is {total}, so nothing \
             would be trained; pass --set total_updates={} or more to extend it",
            ckpt.display(),
            done + 1
        )));
    }
    run.check_latest(&ckpt)?;
    for (_, change) in &allowed {
        eprintln!("resuming {} with {change}", run.path.display());
    }
    Ok(())
}

/// Settings a fork keeps: the network's shape, which the checkpoint's
/// weights must fit (loading would refuse them later; refused here, before
/// anything is written), its heads and the observation it was sized for.
const FORK_KEEPS: [&str; 7] = [
    "model.",
    "encoder_hidden",
    "head_hidden",
    "n_critics",
    "goal_recall_coef",
    "novelty_critic",
    "goal_in_observation",
];

/// `pretrain --resume CKPT --fork OUT`: branches a new run under `out` from
/// CKPT (a run folder: its latest checkpoint) with the `sets` applied to its
/// configuration (any setting but the network's shape; `model.max_len` too
/// where positions are sinusoidal), leaving the original
/// run as it is; the branch starts with the weights, optimizer, multiplier
/// and counters of CKPT and its metrics up to there. The settings are
/// checked as a run checks them before anything is made (a refused fork
/// leaves nothing behind). Returns the new run, which the caller resumes
/// (and removes with [`Forked::remove_if_untrained`] if that start is
/// refused).
pub fn fork(
    env: &str,
    method: &str,
    from: &Path,
    sets: &[String],
    out: &Path,
) -> anyhow::Result<Forked> {
    let (run, ckpt) = resolve_resume(from)?;
    RunDir::check_resume_flags(&ckpt, method, env)?;
    // EPPO checkpoints hold a copy of the config (a lost config.toml).
    let path = [run.config_path(), ckpt.join("config.toml")]
        .into_iter()
        .find(|p| p.is_file())
        .unwrap_or_else(|| run.config_path());
    let invalid = |problem: String| CheckpointError::Invalid {
        path: path.clone(),
        problem,
        fix: "restore the run's config.toml from a copy".into(),
    };
    let mut saved = fs::read_to_string(&path)
        .map_err(|e| invalid(e.to_string()))?
        .parse::<toml::Table>()
        .map_err(|e| invalid(e.to_string()))?;
    if method != "ad" {
        // The fork's config.toml is written in sections, whatever the form
        // of the run it branches from.
        EppoConfig::migrate(&mut saved).map_err(invalid)?;
    }
    let mut table = saved.clone();
    let applied = if method == "ad" {
        crate::presets::apply_overrides(&mut table, sets).map_err(|e| e.to_string())
    } else {
        EppoConfig::apply_sets(&mut table, sets).map_err(|e| e.to_string())
    };
    applied.map_err(|problem| CheckpointError::Invalid {
        path: path.clone(),
        problem,
        fix: "correct the --set".into(),
    })?;
    let changes = setting_changes(&saved, &table);
    // Fixed sinusoids hold no weights, so their model takes a longer (or
    // shorter) context as it is: a fork may change the number of episodes.
    // (A change of `model.positions` itself is refused below.)
    let sinusoidal = saved
        .get("model")
        .and_then(|m| m.get("positions"))
        .and_then(toml::Value::as_str)
        == Some("sinusoidal");
    let free = |key: &str| sinusoidal && key == "model.max_len";
    let new_max_len = changes
        .iter()
        .any(|(key, _)| free(key))
        .then(|| table.get("model").and_then(|m| m.get("max_len")))
        .flatten()
        .and_then(toml::Value::as_integer);
    let kept: Vec<&str> = changes
        .iter()
        .filter(|(key, _)| FORK_KEEPS.iter().any(|k| key.starts_with(k)) && !free(key))
        .map(|(_, c)| c.as_str())
        .collect();
    if !kept.is_empty() {
        return Err(CheckpointError::Invalid {
            path: ckpt.clone(),
            problem: format!(
                "a fork starts from this checkpoint's weights, which do not fit another network \
                 shape: {}",
                kept.join(", ")
            ),
            fix: "keep the model's settings, or start a new run".into(),
        }
        .into());
    }
    let seed = EppoConfig::setting(&table, "seed")
        .and_then(toml::Value::as_integer)
        .and_then(|s| u64::try_from(s).ok())
        .ok_or_else(|| invalid("no seed (a whole number of 0 or more)".into()))?;
    let total_updates = fork_total_updates(method, &ckpt, &table)?;
    let text = toml::to_string(&table).map_err(|e| invalid(e.to_string()))?;
    let (metrics_key, total_key) = if method == "ad" {
        ("update", "updates")
    } else {
        ("updates", "total_updates")
    };
    let spec = ForkFrom {
        checkpoint: &ckpt,
        seed,
        config_toml: &text,
        metrics_key,
        total_key,
        total_updates,
    };
    let forked = run.fork(&spec, out)?;
    if let Some(max_len) = new_max_len {
        let recorded = crate::checkpoint::record_forked_max_len(&forked.checkpoint, max_len);
        if let Err(e) = recorded {
            forked.remove_if_untrained();
            return Err(e.into());
        }
    }
    let changes: Vec<String> = changes.into_iter().map(|(_, c)| c).collect();
    eprintln!(
        "forked {} into {}{}",
        ckpt.display(),
        forked.run.path.display(),
        if changes.is_empty() {
            String::new()
        } else {
            format!(" with {}", changes.join(", "))
        }
    );
    warn_unreadable_metrics(&run, &forked.unreadable_metrics);
    Ok(forked)
}

/// The fork's settings checked as its run will check them, before anything
/// is made (a `--set lr=nan` refused at the start of training left a fork
/// folder the user never saw named, holding a run that could not train);
/// returns its length in updates.
fn fork_total_updates(method: &str, ckpt: &Path, table: &toml::Table) -> anyhow::Result<u64> {
    if method == "ad" {
        let cfg = AdConfig::from_table(table.clone())?;
        return Ok(cfg.updates as u64);
    }
    let cfg = EppoConfig::from_table(&format!("the fork of {}", ckpt.display()), table.clone())?;
    cfg.validate()?;
    Ok(cfg.optimisation.total_updates)
}

/// Says which lines of the forked run's `metrics.jsonl` the fork left out
/// (lines that are not metric records: garbage, or a line cut by a kill).
/// A warning, not a refusal: the metrics are the run's log, not its state,
/// and the run itself resumes with them as they are.
fn warn_unreadable_metrics(run: &RunDir, lines: &[usize]) {
    if lines.is_empty() {
        return;
    }
    let mut named: Vec<String> = lines.iter().take(5).map(usize::to_string).collect();
    if lines.len() > 5 {
        named.push("...".into());
    }
    let what = if lines.len() == 1 {
        format!("line {} is not a metric record", named[0])
    } else {
        format!(
            "{} lines are not metric records (lines {})",
            lines.len(),
            named.join(", ")
        )
    };
    eprintln!(
        "warning: {}: {what}: not JSON, or without its update counter; the fork's metrics.jsonl \
         leaves {} out, the original keeps {}",
        run.metrics_path().display(),
        if lines.len() == 1 { "it" } else { "them" },
        if lines.len() == 1 { "it" } else { "them" },
    );
}

/// `(key, "key: before -> after")` for every setting that differs between
/// `saved` and `now`, set in either, both in the same form: dotted keys for
/// nested tables, but an EPPO setting by its own name (`lambda_max`, not
/// `constraint.lambda_max`: [`EppoConfig::flat_name`]).
fn setting_changes(saved: &toml::Table, now: &toml::Table) -> Vec<(String, String)> {
    let leaves = |table: &toml::Table| {
        let mut out = Vec::new();
        flatten("", table, &mut out);
        out.into_iter()
            .map(|(key, value)| (EppoConfig::flat_name(&key).to_string(), value))
            .collect::<std::collections::BTreeMap<_, _>>()
    };
    let (old, new) = (leaves(saved), leaves(now));
    let keys: std::collections::BTreeSet<&String> = old.keys().chain(new.keys()).collect();
    keys.into_iter()
        .filter(|key| old.get(*key) != new.get(*key))
        .map(|key| {
            let value = |v: Option<&String>| v.map_or("(unset)".to_string(), String::clone);
            let change = format!("{key}: {} -> {}", value(old.get(key)), value(new.get(key)));
            (key.clone(), change)
        })
        .collect()
}

/// `(dotted.key, value)` for every leaf of a TOML table.
pub fn flatten(prefix: &str, table: &toml::Table, out: &mut Vec<(String, String)>) {
    for (k, v) in table {
        let key = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        match v {
            toml::Value::Table(t) => flatten(&key, t, out),
            other => out.push((key, other.to_string())),
        }
    }
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
            let (run, ckpt) = resolve_resume(path)?;
            RunDir::check_resume_flags(&ckpt, "ad", env)?;
            run.check_latest(&ckpt)?;
            Some((run, ckpt))
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A run whose config.toml is flat (every run written before the
    /// settings had sections) is compared with the `--set`s in sections:
    /// unchanged (an empty list where it wrote none included), only its
    /// length is asked for; changed, each change is named by its setting.
    #[test]
    fn a_flat_run_resumes_against_sets_in_sections() {
        let from = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../results/eppo_darkroom_budget/dp0_preset_budget_seed0");
        let out = std::env::temp_dir().join(format!("icrl-flat-resume-{}", std::process::id()));
        let run = out.join("dp0");
        let step = run.join("checkpoints/step_5291");
        fs::create_dir_all(&step).unwrap();
        for file in ["config.toml", "metrics.jsonl"] {
            fs::copy(from.join(file), run.join(file)).unwrap();
        }
        for entry in fs::read_dir(from.join("checkpoints/step_5291")).unwrap() {
            let entry = entry.unwrap();
            fs::copy(entry.path(), step.join(entry.file_name())).unwrap();
        }
        let flat: toml::Table = fs::read_to_string(run.join("config.toml"))
            .unwrap()
            .parse()
            .unwrap();
        assert!(flat.contains_key("lambda_max"), "written flat");
        let resume = |sets: &[&str]| {
            let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
            eppo("darkroom", "quick", Some(&run), &sets, &out)
                .err()
                .unwrap()
                .to_string()
        };
        let err = resume(&["total_updates=5291", "torch_threads=1"]);
        assert!(
            err.contains("it has done 5291 updates and total_updates is 5291"),
            "{err}"
        );
        // Emptying a list the run wrote is a change; an empty list where it
        // wrote none (resolved, the same config) is not.
        let emptied = [
            "total_updates=5291",
            "constraint.over_budget_price_schedule=[]",
        ];
        let err = resume(&emptied);
        assert!(
            err.contains("over_budget_price_schedule: [{ after = 4000, price = 1.0 }, { after = 6000, price = 2.0 }] -> (unset)"),
            "{err}"
        );
        for config in [run.join("config.toml"), step.join("config.toml")] {
            let text = fs::read_to_string(&config).unwrap();
            let cut = text.find("[[over_budget_price_schedule]]").unwrap();
            fs::write(&config, &text[..cut]).unwrap();
        }
        let err = resume(&emptied);
        assert!(err.contains("it has done 5291 updates"), "{err}");
        let err = resume(&["lr=0.1", "constraint.lambda_max=0.5"]);
        assert!(
            err.contains("these settings differ from its config.toml: ")
                && err.contains("lr: 0.0003 -> 0.1")
                && err.contains("lambda_max: 0.3 -> 0.5")
                && !err.contains("(unset)"),
            "{err}"
        );
        fs::remove_dir_all(&out).unwrap();
    }
}
