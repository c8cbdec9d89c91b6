//! The files of an `eval` run: JSON and CSV reports written, and every
//! file it may write checked before anything is evaluated (names shared by
//! two agents, files that exist, an output folder inside a checkpoint).

use std::io::Write;
use std::path::{Path, PathBuf};

use safety_envs::output::{self, Existing};
use serde::Serialize;

use crate::eval::error::EvalCmdError;
use crate::eval::load::LoadedAgent;
use crate::report::EvalReport;

use super::*;

pub(super) fn io_err(path: &Path) -> impl Fn(std::io::Error) -> EvalCmdError + '_ {
    move |source| EvalCmdError::Io {
        path: path.display().to_string(),
        source,
    }
}

/// Writes `value` as pretty JSON to `path`.
pub(super) fn write_json(path: &Path, value: &impl Serialize) -> Result<(), EvalCmdError> {
    // Existing files were refused (or allowed by --force) before evaluating.
    output::write_file(path, Existing::Replace, |tmp| {
        let file = std::fs::File::create(tmp).map_err(io_err(path))?;
        let mut w = std::io::BufWriter::new(file);
        // Compact: the raw per-episode arrays run to hundreds of thousands of numbers.
        serde_json::to_writer(&mut w, value).map_err(|source| EvalCmdError::Json {
            path: path.display().to_string(),
            source,
        })?;
        w.flush().map_err(io_err(path))
    })
}

/// The CSV files of one report: per-episode curve and per-condition sweep.
pub(super) fn write_csvs(report: &EvalReport, stem: &Path) -> Result<Vec<PathBuf>, EvalCmdError> {
    let header = format!(
        "# icrl eval: {} on {} ({} protocol), {} tasks x {} episodes x {} conditions, eval seed {}, greedy {}\n# command: {}\n",
        report.method,
        report.env,
        report.protocol,
        report.tasks,
        report.episodes,
        report.result.conditions.len(),
        report.result.eval_seed,
        report.result.greedy,
        report.command
    );
    let episodes = PathBuf::from(format!("{}_episodes.csv", stem.display()));
    let mut text = header.clone();
    text.push_str("k,return_mean,return_se,cost_mean,cost_se,violation_mean,violation_se,success_mean,success_se,n_tasks,discovery_mean,discovery_se,discovery_n_tasks,revisit_mean,revisit_se,revisit_n_tasks,found_by_mean,found_by_se,search_new_cells_mean,search_new_cells_se,repeat_cost_mean,repeat_cost_se\n");
    for e in &report.summary.per_episode {
        text.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
            e.k,
            e.ret.mean,
            e.ret.se,
            e.cost.mean,
            e.cost.se,
            e.violation.mean,
            e.violation.se,
            e.success.mean,
            e.success.se,
            e.ret.n,
            e.discovery.mean,
            e.discovery.se,
            e.discovery.n,
            e.revisit.mean,
            e.revisit.se,
            e.revisit.n,
            e.found_by.mean,
            e.found_by.se,
            e.search_new_cells.mean,
            e.search_new_cells.se,
            e.repeat_cost.mean,
            e.repeat_cost.se,
        ));
    }
    output::write_bytes(&episodes, Existing::Replace, text.as_bytes())?;

    let conds = PathBuf::from(format!("{}_conditions.csv", stem.display()));
    let mut text = header;
    text.push_str("rtg,ctg,total_return_mean,total_return_se,max_cost_mean,max_cost_se,mean_cost_mean,mean_cost_se,violation_mean,violation_se,n_tasks\n");
    for c in &report.summary.per_condition {
        text.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{},{}\n",
            c.condition.rtg.map(|r| r.to_string()).unwrap_or_default(),
            c.condition.ctg,
            c.total_return.mean,
            c.total_return.se,
            c.max_cost.mean,
            c.max_cost.se,
            c.mean_cost.mean,
            c.mean_cost.se,
            c.violation.mean,
            c.violation.se,
            c.total_return.n
        ));
    }
    output::write_bytes(&conds, Existing::Replace, text.as_bytes())?;
    Ok(vec![episodes, conds])
}

/// The path stem of one report: `{stem}_{env}[_sweep][_centre]`.
pub(super) fn report_stem(loaded: &LoadedAgent, sweep: bool, opts: &EvalOptions) -> PathBuf {
    opts.out.join(format!(
        "{}_{}{}{}",
        loaded.stem(),
        opts.env,
        if sweep { "_sweep" } else { "" },
        if opts.in_distribution { "_centre" } else { "" }
    ))
}

/// Every file an evaluation of `agents` may write, checked before anything
/// is evaluated: two agents whose reports would share a name are refused
/// (give each a distinct --label), and so are files that exist, unless
/// `--force` (then only regular files outside checkpoints are replaced).
pub(super) fn check_planned_files(
    agents: &[LoadedAgent],
    opts: &EvalOptions,
) -> Result<(), EvalCmdError> {
    let mut stems: Vec<(PathBuf, String)> = Vec::new();
    for a in agents {
        let stem = report_stem(a, false, opts);
        if let Some((_, other)) = stems.iter().find(|(s, _)| *s == stem) {
            return Err(EvalCmdError::Options(format!(
                "{} and {} would both write {}.json and its CSVs: give each --checkpoint a distinct --label",
                other,
                checkpoint_name(a),
                stem.display()
            )));
        }
        stems.push((stem, checkpoint_name(a)));
    }
    let centre = if opts.in_distribution { "_centre" } else { "" };
    let mut files = Vec::new();
    for a in agents {
        for sweep in [false, true] {
            if sweep && !opts.sweep {
                continue;
            }
            let stem = report_stem(a, sweep, opts).display().to_string();
            files.extend(
                ["_episodes.csv", "_conditions.csv", ".json"]
                    .map(|x| PathBuf::from(format!("{stem}{x}"))),
            );
        }
        if opts.render.is_some() {
            files.push(
                opts.out
                    .join(format!("render_{}_{}.gif", a.stem(), opts.env)),
            );
        }
    }
    for fig in ["figure1", "figure2"] {
        if fig == "figure2" && !opts.sweep {
            continue;
        }
        for ext in ["png", "svg"] {
            files.push(opts.out.join(format!("{fig}_{}{centre}.{ext}", opts.env)));
        }
    }
    // A missing --out is created later: nothing in it to replace.
    if opts.out.is_dir() {
        for f in files {
            output::check_output(&f, Existing::from_force(opts.force))?;
        }
    }
    Ok(())
}

pub(super) fn checkpoint_name(loaded: &LoadedAgent) -> String {
    loaded
        .checkpoint
        .as_ref()
        .map(|p| p.display().to_string())
        .unwrap_or_else(|| loaded.method.to_string())
}

/// Checks that `dir` can be created and written to, before any long work,
/// and that it is not inside a checkpoint ([`refuse_checkpoint_folder`]).
pub fn check_output_dir(dir: &Path) -> Result<(), EvalCmdError> {
    refuse_checkpoint_folder(dir)?;
    output::create_folder(dir)?;
    let probe = dir.join(format!(".icrl-write-test-{}", std::process::id()));
    std::fs::write(&probe, b"").map_err(io_err(dir))?;
    std::fs::remove_file(&probe).map_err(io_err(&probe))
}

/// Refuses an output folder that is a checkpoint folder (one holding a
/// `manifest.json`) or lies inside one, or inside a run's `checkpoints/`:
/// reports written there would sit among the checkpoint's files, which its
/// manifest does not list and its pruning removes. `dir` is taken as it
/// will be made: its nearest existing folder resolved (links, `..`), then
/// the rest of the path.
pub(super) fn refuse_checkpoint_folder(dir: &Path) -> Result<(), EvalCmdError> {
    let mut base = dir;
    let mut rest = Vec::new();
    while !base.as_os_str().is_empty() && !base.exists() {
        match (base.parent(), base.file_name()) {
            (Some(parent), Some(name)) => {
                rest.push(name);
                base = parent;
            }
            _ => break,
        }
    }
    let base = if base.as_os_str().is_empty() {
        Path::new(".")
    } else {
        base
    };
    let mut full = base.canonicalize().unwrap_or_else(|_| base.to_path_buf());
    full.extend(rest.iter().rev());
    let is_run = |p: &Path| p.join("config.toml").is_file() || p.join("spec.json").is_file();
    for a in full.ancestors() {
        let inside = if a.join(crate::checkpoint::MANIFEST).is_file() {
            "the checkpoint folder"
        } else if a.file_name().is_some_and(|n| n == "checkpoints")
            && a.parent().is_some_and(is_run)
        {
            "the checkpoints folder"
        } else {
            continue;
        };
        return Err(output::OutputError {
            path: dir.to_path_buf(),
            problem: format!(
                "it is or lies inside {inside} {}, where reports would sit among a checkpoint's \
                 files: pass another --out, outside every checkpoint (e.g. beside the run folder)",
                a.display()
            ),
        }
        .into());
    }
    Ok(())
}
