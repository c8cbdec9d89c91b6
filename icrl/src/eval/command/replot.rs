//! `eval --from DIR`: Figures 1 and 2 redrawn with one column per
//! environment from the JSON reports of earlier runs; with `--label`, one
//! curve per folder, pooled over the reports below it (an ablation's runs
//! against the preset's).

use std::path::{Path, PathBuf};

use safety_envs::EnvName;
use safety_envs::output::{self, Existing};

use crate::eval::Summary;
use crate::eval::error::EvalCmdError;
use crate::plots::{self, EnvCurves};
use crate::report::Method;

use super::files::{io_err, refuse_checkpoint_folder};
use super::*;

/// Redraws Figures 1 and 2 with one column per environment from the JSON
/// reports earlier `eval` runs wrote into `dirs` (files that are not reports
/// are skipped). Writes `figure1_all` and, when sweeps are present,
/// `figure2_all` (PNG and SVG) into `out`.
pub fn replot(
    dirs: &[PathBuf],
    labels: &[String],
    out: &Path,
    force: bool,
) -> Result<EvalOutputs, EvalCmdError> {
    refuse_checkpoint_folder(out)?;
    for f in [
        "figure1_all.png",
        "figure1_all.svg",
        "figure2_all.png",
        "figure2_all.svg",
    ] {
        // A missing `out` is created below: nothing in it to replace.
        if out.is_dir() {
            output::check_output(&out.join(f), Existing::from_force(force))?;
        }
    }
    if !labels.is_empty() {
        return replot_pooled(dirs, labels, out);
    }
    let reports = read_reports(dirs)?;
    if reports.is_empty() {
        return Err(EvalCmdError::Options(format!(
            "no eval reports (*.json written by icrl eval) in {}",
            dirs.iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        )));
    }
    output::create_folder(out)?;
    let mut outputs = EvalOutputs::default();
    let fig1 = env_curves(&reports, false);
    if !fig1.is_empty() {
        outputs
            .files
            .extend(plots::figure1(&fig1, &out.join("figure1_all"))?);
    }
    let fig2 = env_curves(&reports, true);
    if !fig2.is_empty() {
        outputs
            .files
            .extend(plots::figure2(&fig2, &out.join("figure2_all"))?);
    }
    outputs.lines.push(format!(
        "redrew {} reports ({} environments)",
        reports.len(),
        fig1.len().max(fig2.len())
    ));
    Ok(outputs)
}

/// Figure 1 with one curve per label: the EPPO and AD reports found
/// anywhere below its folders (each run at each evaluation seed, say; a
/// label may name several folders) pooled into one curve, mean over the reports and standard error over them
/// ([`Summary::pooled`]), and the random policy's reports of every folder
/// pooled into its line. All reports must be of one environment. Budget
/// sweeps are not pooled (their budgets differ between evaluations).
fn replot_pooled(
    dirs: &[PathBuf],
    labels: &[String],
    out: &Path,
) -> Result<EvalOutputs, EvalCmdError> {
    if labels.len() != dirs.len() {
        return Err(EvalCmdError::Options(format!(
            "{} --label for {} --from: give one label per --from folder, in order, or none",
            labels.len(),
            dirs.len()
        )));
    }
    let mut outputs = EvalOutputs::default();
    let mut env = None;
    let (mut methods, mut random) = (Vec::new(), Vec::new());
    // A label given to several folders pools them all into its curve.
    let mut curves: Vec<(&String, Vec<Summary>, Vec<String>)> = Vec::new();
    for (label, dir) in labels.iter().zip(dirs) {
        let mut parts = Vec::new();
        for (e, method, sweep, summary) in read_reports_below(dir)? {
            if sweep {
                continue;
            }
            if *env.get_or_insert(e) != e {
                return Err(EvalCmdError::Options(format!(
                    "--from {}: it holds {e} reports beside {} ones: pool one environment at a time",
                    dir.display(),
                    env.map_or(String::new(), |x| x.to_string())
                )));
            }
            match method {
                Method::Random => random.push(summary),
                _ => parts.push(summary),
            }
        }
        if parts.is_empty() {
            return Err(EvalCmdError::Options(format!(
                "--from {}: no EPPO or AD eval report (*.json written by icrl eval) below it",
                dir.display()
            )));
        }
        let from = dir.display().to_string();
        match curves.iter_mut().find(|c| c.0 == label) {
            Some(c) => {
                c.1.extend(parts);
                c.2.push(from);
            }
            None => curves.push((label, parts, vec![from])),
        }
    }
    for (label, parts, from) in curves {
        outputs.lines.push(format!(
            "{label}: {} reports pooled from {}",
            parts.len(),
            from.join(", ")
        ));
        methods.push((label.clone(), Summary::pooled(&parts)));
    }
    let Some(env) = env else {
        return Err(EvalCmdError::Options("no --from folder given".into()));
    };
    output::create_folder(out)?;
    let curves = EnvCurves {
        env: env_defaults(env).title.into(),
        methods,
        random: (!random.is_empty()).then(|| Summary::pooled(&random)),
    };
    outputs
        .files
        .extend(plots::figure1(&[curves], &out.join("figure1_all"))?);
    Ok(outputs)
}

/// The reports of the JSON files in `dir` and every folder below it, in
/// path order, but for run folders and checkpoints (whose JSON files are
/// not reports); a folder that is not there is refused.
fn read_reports_below(dir: &Path) -> Result<Vec<Report>, EvalCmdError> {
    let mut reports = read_reports(&[dir.to_path_buf()])?;
    let run_or_checkpoint = |d: &Path| {
        d.join("checkpoints").is_dir()
            || ["manifest.json", "spec.json"]
                .iter()
                .any(|f| d.join(f).is_file())
    };
    let mut below: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io_err(dir))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir() && !run_or_checkpoint(p))
        .collect();
    below.sort();
    for d in below {
        reports.extend(read_reports_below(&d)?);
    }
    Ok(reports)
}

/// One report as the figures take it: environment, method, whether it is a
/// sweep, and its summary.
type Report = (EnvName, Method, bool, Summary);

/// The reports of the JSON files in `dirs`, in file-name order for
/// stability; a folder that is not there is refused.
fn read_reports(dirs: &[PathBuf]) -> Result<Vec<Report>, EvalCmdError> {
    let mut reports = Vec::new();
    for dir in dirs {
        if !dir.is_dir() {
            return Err(EvalCmdError::Options(format!(
                "--from {}: no such folder (pass folders that `icrl eval` wrote its reports into)",
                dir.display()
            )));
        }
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(io_err(dir))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "json"))
            .collect();
        files.sort();
        for f in files {
            reports.extend(read_report(&f)?);
        }
    }
    Ok(reports)
}

/// The report in the JSON file `f`; `None` for one the paper's figures do
/// not draw (in-distribution diagnostics, an unknown environment or
/// method). A damaged or foreign JSON file is named, never skipped in
/// silence: the figure would lack a curve without saying so.
fn read_report(f: &Path) -> Result<Option<Report>, EvalCmdError> {
    let text = std::fs::read(f).map_err(io_err(f))?;
    let v = serde_json::from_slice::<serde_json::Value>(&text).map_err(|e| {
        EvalCmdError::Options(format!(
            "--from: {} is not readable JSON ({e}): a damaged eval report? Re-run the eval \
             that wrote it, or move the file out of the folder",
            f.display()
        ))
    })?;
    let (Some(env), Some(method), Some(protocol), Some(summary)) = (
        v.get("env").and_then(|e| e.as_str()),
        v.get("method").and_then(|m| m.as_str()),
        v.get("protocol").and_then(|p| p.as_str()),
        v.get("summary"),
    ) else {
        return Err(EvalCmdError::Options(format!(
            "--from: {} is JSON but not an icrl eval report (it lacks env, method, protocol or \
             summary): move it out of the folder",
            f.display()
        )));
    };
    // In-distribution diagnostics are not the paper's figures.
    let Ok(env) = env.parse::<EnvName>() else {
        return Ok(None);
    };
    if protocol.ends_with("-centre") {
        return Ok(None);
    }
    let method = match method {
        "Eppo" => Method::Eppo,
        "Ad" => Method::Ad,
        "Random" => Method::Random,
        _ => return Ok(None),
    };
    let summary: Summary =
        serde_json::from_value(summary.clone()).map_err(|source| EvalCmdError::Json {
            path: f.display().to_string(),
            source,
        })?;
    Ok(Some((env, method, protocol == "sweep", summary)))
}

/// One figure's columns: an environment's curves wherever `reports` has
/// one of its protocol (`sweep` or not), EPPO, AD and the random policy.
fn env_curves(reports: &[Report], sweep: bool) -> Vec<EnvCurves> {
    EnvName::ALL
        .into_iter()
        .filter_map(|env| {
            let mut c = EnvCurves {
                env: env_defaults(env).title.into(),
                methods: Vec::new(),
                random: None,
            };
            for method in [Method::Eppo, Method::Ad, Method::Random] {
                if let Some((.., s)) = reports
                    .iter()
                    .find(|r| r.0 == env && r.1 == method && r.2 == sweep)
                {
                    match method {
                        Method::Random => c.random = Some(s.clone()),
                        m => c.methods.push((m.to_string(), s.clone())),
                    }
                }
            }
            (!c.methods.is_empty() || c.random.is_some()).then_some(c)
        })
        .collect()
}
