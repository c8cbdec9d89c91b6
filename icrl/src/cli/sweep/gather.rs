//! `--gather`: the last checkpoint of every finished run evaluated, and
//! the claims table over seeds.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::PathBuf;

use safety_envs::EnvName;

use crate::cli::pretrain::{InOut, run_in_out};

use super::*;

/// How the evaluation of `--gather` runs.
#[derive(Clone, Debug)]
pub struct GatherOptions {
    pub tasks: usize,
    pub episodes: Option<usize>,
    pub n_budgets: usize,
    pub threads: usize,
    pub force: bool,
}

/// What `--gather` found and wrote.
#[derive(Clone, Debug)]
pub struct Gathered {
    /// Tasks whose run has not finished (or not started): index and why.
    pub unfinished: Vec<(usize, String)>,
    /// Tasks whose finished run could not be evaluated (a damaged
    /// checkpoint or run file): index and why. The table names them and
    /// holds the rest.
    pub left_out: Vec<(usize, String)>,
    pub evaluated: usize,
    /// The Markdown table; empty, and nothing written, when no run was
    /// evaluated.
    pub table: String,
    pub files: Vec<PathBuf>,
}

/// Evaluates the last checkpoint of every finished run (held-out tasks, as
/// `icrl eval`, one folder per task under `OUT/gather/`), then writes the
/// table of settings: mean and standard error over seeds of each run's
/// first- and last-window return and cost. A run that cannot be evaluated
/// is left out and named in the table's notes, the rest gathered; with no
/// run evaluated nothing is written. An earlier gather's files are refused
/// before any evaluation unless `force`.
pub fn gather(grid: &SweepGrid, opts: &GatherOptions) -> Result<Gathered, SweepError> {
    let env: EnvName = grid
        .env
        .parse()
        .map_err(|e| SweepError::Io(format!("{e}")))?;
    let protocol = grid.gather.clone().unwrap_or(GatherProtocol {
        eval_seeds: vec![0],
        tasks: None,
        episodes: None,
        n_budgets: None,
        random: false,
    });
    check_earlier_gather(grid, opts.force)?;
    let mut unfinished = Vec::new();
    let mut left_out = Vec::new();
    let mut runs = Vec::new();
    let mut files = Vec::new();
    for task in grid.tasks() {
        let dir = grid.task_dir(&task);
        let run = match run_in_out(&dir, &grid.env, &grid.method, &grid.sets(&task)) {
            Ok(InOut::Finished { run, .. }) => run,
            Ok(InOut::Resume(run)) => {
                unfinished.push((task.index, format!("{} has not finished", run.display())));
                continue;
            }
            Ok(InOut::Start) => {
                unfinished.push((
                    task.index,
                    format!("no run with a checkpoint in {}", dir.display()),
                ));
                continue;
            }
            Err(e) => {
                left_out.push((task.index, e.to_string()));
                continue;
            }
        };
        match evaluate_run(grid, &task, &run, env, &protocol, opts) {
            Ok((scores, written)) => {
                runs.extend(scores);
                files.extend(written);
            }
            Err(e) => left_out.push((task.index, e.to_string())),
        }
    }
    let evaluated = runs.len();
    if runs.is_empty() {
        return Ok(Gathered {
            unfinished,
            left_out,
            evaluated,
            table: String::new(),
            files,
        });
    }
    let (mut table, csv) = table(grid, &protocol.eval_seeds, &runs);
    table.push_str(&notes(grid, &left_out, &unfinished));
    let dir = grid.out.join("gather");
    std::fs::create_dir_all(&dir).map_err(|e| SweepError::Io(format!("{}: {e}", dir.display())))?;
    let existing = safety_envs::output::Existing::from_force(opts.force);
    for (name, text) in [("table.md", &table), ("table.csv", &csv)] {
        let path = dir.join(name);
        safety_envs::output::write_bytes(&path, existing, text.as_bytes())?;
        files.push(path);
    }
    Ok(Gathered {
        unfinished,
        left_out,
        evaluated,
        table,
        files,
    })
}

/// Refuses, before any evaluation, to gather into `OUT/gather` when an
/// earlier gather's evaluations or table are there, unless `force`: the
/// refusal used to come after every run was evaluated, at the table.
fn check_earlier_gather(grid: &SweepGrid, force: bool) -> Result<(), SweepError> {
    let dir = grid.out.join("gather");
    let held = std::fs::read_dir(&dir).is_ok_and(|mut d| d.next().is_some());
    if force || !held {
        return Ok(());
    }
    Err(SweepError::Io(format!(
        "{}: it holds an earlier --gather's evaluations or table: pass --force to evaluate \
         again and replace them, or move the folder away; nothing was evaluated",
        dir.display()
    )))
}

/// The last checkpoint of `run` (task `task`'s) evaluated at every
/// evaluation seed of the protocol: its scores and the files written.
fn evaluate_run(
    grid: &SweepGrid,
    task: &Task,
    run: &std::path::Path,
    env: EnvName,
    protocol: &GatherProtocol,
    opts: &GatherOptions,
) -> Result<(Vec<RunScore>, Vec<PathBuf>), SweepError> {
    let (mut scores, mut files) = (Vec::new(), Vec::new());
    for &eval_seed in &protocol.eval_seeds {
        let mut agent = crate::eval::load::load_checkpoint(run, env)?;
        agent.label = Some(grid.task_name(task));
        let eval = crate::eval::command::EvalOptions {
            env,
            tasks: protocol.tasks.unwrap_or(opts.tasks),
            episodes: protocol.episodes.or(opts.episodes),
            budgets: None,
            n_budgets: protocol.n_budgets.unwrap_or(opts.n_budgets),
            rtg: 1.0,
            sweep: false,
            random: protocol.random,
            render: None,
            out: grid
                .out
                .join("gather")
                .join(grid.task_name(task))
                .join(format!("eval_seed{eval_seed}")),
            eval_seed,
            batch: 256,
            threads: opts.threads,
            greedy: false,
            max_episode_steps: None,
            progress: false,
            in_distribution: false,
            seed_torch: true,
            command: format!(
                "icrl sweep --gather (task {}, evaluation seed {eval_seed})",
                task.index
            ),
            force: opts.force,
        };
        let out = crate::eval::command::run(vec![agent], &eval)?;
        let report = |random: bool| -> Result<serde_json::Value, SweepError> {
            let path = out
                .files
                .iter()
                .find(|f| {
                    f.extension().is_some_and(|e| e == "json")
                        && f.file_name()
                            .is_some_and(|n| n.to_string_lossy().starts_with("random_"))
                            == random
                })
                .ok_or_else(|| {
                    SweepError::Io(format!("task {}: eval wrote no JSON report", task.index))
                })?;
            std::fs::read_to_string(path)
                .ok()
                .and_then(|t| serde_json::from_str(&t).ok())
                .ok_or_else(|| SweepError::Io(format!("{}: unreadable report", path.display())))
        };
        let mut score = Score::of(&report(false)?["summary"]);
        if protocol.random {
            score.random_within = Score::of(&report(true)?["summary"]).within;
        }
        scores.push(RunScore {
            label: task.label(),
            seed: task.seed,
            eval_seed,
            score,
        });
        files.extend(out.files);
    }
    Ok((scores, files))
}

/// The table's notes: the tasks left out (each by name, with why) and
/// those not finished, so a table of fewer runs says which are missing.
fn notes(grid: &SweepGrid, left_out: &[(usize, String)], unfinished: &[(usize, String)]) -> String {
    let tasks = grid.tasks();
    let name = |index: usize| {
        tasks
            .iter()
            .find(|t| t.index == index)
            .map_or(format!("task {index}"), |t| {
                format!("task {index} ({}, seed {})", t.label(), t.seed)
            })
    };
    let mut md = String::new();
    for (title, list) in [
        (
            "Left out: finished runs that could not be evaluated",
            left_out,
        ),
        ("Not finished, not in the table", unfinished),
    ] {
        if list.is_empty() {
            continue;
        }
        let _ = write!(md, "\n{title}:\n\n");
        for (index, why) in list {
            let _ = writeln!(md, "- {}: {why}", name(*index));
        }
    }
    md
}

/// What the claims are judged on, read off one evaluation's summary: the
/// return over the first and last window of episodes and its gain in
/// standard errors, the share of (task, budget) pairs within budget in the
/// last episode (the agent's, and the random policy's on the same tasks),
/// the cost over the first and last window, the share of pairs that have
/// found the goal by the last episode, the revisit rate pooled over the
/// episodes after the first, and Spearman's rho between each budget and the
/// total return under it.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Score {
    first_return: f64,
    last_return: f64,
    gain_se: f64,
    within: f64,
    random_within: f64,
    first_cost: f64,
    last_cost: f64,
    found: f64,
    revisit: f64,
    rho: f64,
}

/// The table's columns: Markdown header, CSV key.
const SCORE_COLUMNS: [(&str, &str); 10] = [
    ("return, first", "first_return"),
    ("return, last", "last_return"),
    ("gain (s.e.)", "gain_se"),
    ("within budget at K", "within"),
    ("random, within at K", "random_within"),
    ("cost, first", "first_cost"),
    ("cost, last", "last_cost"),
    ("found by K", "found"),
    ("revisit", "revisit"),
    ("rho(return, budget)", "rho"),
];

impl Score {
    fn of(summary: &serde_json::Value) -> Self {
        let num = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
        let trend = &summary["trend"];
        let per_episode = summary["per_episode"]
            .as_array()
            .cloned()
            .unwrap_or_default();
        let last = per_episode.last().cloned().unwrap_or_default();
        let (mut hits, mut count) = (0.0, 0.0);
        for e in per_episode.iter().skip(1) {
            let n = num(&e["revisit"]["n"]);
            if n > 0.0 {
                hits += num(&e["revisit"]["mean"]) * n;
                count += n;
            }
        }
        let conditions = summary["per_condition"]
            .as_array()
            .cloned()
            .unwrap_or_default();
        let budgets: Vec<f64> = conditions
            .iter()
            .map(|c| num(&c["condition"]["ctg"]))
            .collect();
        let totals: Vec<f64> = conditions
            .iter()
            .map(|c| num(&c["total_return"]["mean"]))
            .collect();
        Score {
            first_return: num(&trend["first_return"]["mean"]),
            last_return: num(&trend["last_return"]["mean"]),
            gain_se: num(&trend["return_gain"]["mean"]) / num(&trend["return_gain"]["se"]),
            within: 1.0 - num(&last["violation"]["mean"]),
            random_within: f64::NAN,
            first_cost: num(&trend["first_cost"]["mean"]),
            last_cost: num(&trend["last_cost"]["mean"]),
            found: num(&last["found_by"]["mean"]),
            revisit: if count > 0.0 { hits / count } else { f64::NAN },
            rho: crate::stats::spearman(&budgets, &totals).unwrap_or(f64::NAN),
        }
    }

    fn columns(&self) -> [f64; 10] {
        [
            self.first_return,
            self.last_return,
            self.gain_se,
            self.within,
            self.random_within,
            self.first_cost,
            self.last_cost,
            self.found,
            self.revisit,
            self.rho,
        ]
    }
}

/// One run's score at one evaluation seed.
#[derive(Clone, Debug)]
struct RunScore {
    label: String,
    seed: u64,
    eval_seed: u64,
    score: Score,
}

/// The claims table, as Markdown and CSV: per setting, the mean ± s.e. over
/// training seeds of each run's mean over the evaluation seeds; then every
/// run at every evaluation seed.
fn table(grid: &SweepGrid, eval_seeds: &[u64], runs: &[RunScore]) -> (String, String) {
    let seeds_text = eval_seeds
        .iter()
        .map(u64::to_string)
        .collect::<Vec<_>>()
        .join(", ");
    let header = SCORE_COLUMNS
        .iter()
        .map(|(h, _)| *h)
        .collect::<Vec<_>>()
        .join(" | ");
    let rule = "---|".repeat(SCORE_COLUMNS.len());
    let mut md = format!(
        "{} {} ({} preset), held-out evaluation of each run's last checkpoint at evaluation \
         seeds {seeds_text}; per setting, mean ± s.e. over training seeds of each run's mean \
         over the evaluation seeds\n\n| setting | seeds | {header} |\n|---|---|{rule}\n",
        grid.env, grid.method, grid.preset
    );
    let keys = SCORE_COLUMNS
        .iter()
        .map(|(_, k)| format!("{k},{k}_se"))
        .collect::<Vec<_>>()
        .join(",");
    let mut csv = format!("setting,seeds,{keys}\n");
    // label -> seed -> that run's columns at each evaluation seed
    let mut by_setting: BTreeMap<&str, BTreeMap<u64, Vec<[f64; 10]>>> = BTreeMap::new();
    for r in runs {
        by_setting
            .entry(&r.label)
            .or_default()
            .entry(r.seed)
            .or_default()
            .push(r.score.columns());
    }
    for (label, seeds) in &by_setting {
        let per_seed: Vec<[f64; 10]> = seeds
            .values()
            .map(|at| {
                std::array::from_fn(|i| at.iter().map(|c| c[i]).sum::<f64>() / at.len() as f64)
            })
            .collect();
        let _ = write!(md, "| {label} | {} |", per_seed.len());
        // CSV quotes a field's quotes by doubling them (RFC 4180).
        let _ = write!(csv, "\"{}\",{}", label.replace('"', "\"\""), per_seed.len());
        for i in 0..SCORE_COLUMNS.len() {
            let xs: Vec<f64> = per_seed.iter().map(|s| s[i]).collect();
            let c = crate::stats::mean_se(&xs).unwrap_or_else(crate::stats::MeanSe::undefined);
            // One seed has no standard error: say so rather than "± 0.000".
            if per_seed.len() < 2 {
                let _ = write!(md, " {:.3} (one seed) |", c.mean);
                let _ = write!(csv, ",{},", c.mean);
            } else {
                let _ = write!(md, " {:.3} ± {:.3} |", c.mean, c.se);
                let _ = write!(csv, ",{},{}", c.mean, c.se);
            }
        }
        md.push('\n');
        csv.push('\n');
    }
    let _ = write!(
        md,
        "\nEach run at each evaluation seed:\n\n| setting | seed | evaluation seed | {header} |\n|---|---|---|{rule}\n"
    );
    for r in runs {
        let _ = write!(md, "| {} | {} | {} |", r.label, r.seed, r.eval_seed);
        for x in r.score.columns() {
            let _ = write!(md, " {x:.3} |");
        }
        md.push('\n');
    }
    (md, csv)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::sweep::tests::grid_file;

    /// The gathered table says "one seed" where a setting has no standard
    /// error (it printed "± 0.000"), and its CSV doubles a label's quotes.
    #[test]
    fn a_single_seed_has_no_standard_error_and_csv_quotes_are_escaped() {
        let dir = std::env::temp_dir().join(format!("icrl-sweep-table-{}", std::process::id()));
        let grid = SweepGrid::load(&grid_file(
            &dir,
            "env = \"darkroom\"\nseeds = [0, 1]\nout = \"runs\"\n",
        ))
        .unwrap();
        let score = |first_return: f64| Score {
            first_return,
            last_return: 0.2,
            gain_se: 3.0,
            within: 0.9,
            random_within: 0.6,
            first_cost: 3.0,
            last_cost: 2.0,
            found: 0.8,
            revisit: 0.9,
            rho: 0.5,
        };
        let run = |label: &str, seed, eval_seed, first| RunScore {
            label: label.into(),
            seed,
            eval_seed,
            score: score(first),
        };
        // lr=0.001: seed 0 scores 0.1 and 0.3 at the two evaluation seeds
        // (its mean 0.2), seed 1 scores 0.4: mean 0.3 ± 0.1 over seeds.
        let runs = [
            run("preset=\"a\"", 0, 7, 0.1),
            run("lr=0.001", 0, 7, 0.1),
            run("lr=0.001", 0, 9, 0.3),
            run("lr=0.001", 1, 7, 0.4),
            run("lr=0.001", 1, 9, 0.4),
        ];
        let (md, csv) = table(&grid, &[7, 9], &runs);
        assert!(md.contains("evaluation seeds 7, 9"), "{md}");
        assert!(
            md.contains("| preset=\"a\" | 1 | 0.100 (one seed) |"),
            "{md}"
        );
        let one_seed = md.lines().find(|l| l.starts_with("| preset")).unwrap();
        assert!(!one_seed.contains('±'), "{md}");
        assert!(md.contains("| lr=0.001 | 2 | 0.300 ± 0.100 |"), "{md}");
        assert!(
            md.contains("| lr=0.001 | 1 | 9 | 0.400 |"),
            "each run at each seed: {md}"
        );
        assert!(csv.contains("\"preset=\"\"a\"\"\",1,0.1,,"), "{csv}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The score reads the last episode's violation and found rate, pools
    /// the revisit rate over the episodes after the first by their counts,
    /// and ranks total return against budget.
    #[test]
    fn a_score_is_read_off_an_evaluation_summary() {
        let stat = |mean: f64, n: usize| serde_json::json!({"mean": mean, "se": 0.05, "n": n});
        let summary = serde_json::json!({
            "trend": {
                "first_return": stat(0.1, 16), "last_return": stat(0.5, 16),
                "return_gain": {"mean": 0.4, "se": 0.1, "n": 16},
                "first_cost": stat(4.0, 16), "last_cost": stat(1.0, 16),
            },
            "per_episode": [
                {"violation": stat(0.5, 16), "found_by": stat(0.2, 16),
                 "revisit": {"mean": null, "se": null, "n": 0}},
                {"violation": stat(0.3, 16), "found_by": stat(0.4, 16), "revisit": stat(1.0, 2)},
                {"violation": stat(0.25, 16), "found_by": stat(0.6, 16), "revisit": stat(0.5, 6)},
            ],
            "per_condition": [
                {"condition": {"ctg": 1.0}, "total_return": stat(0.5, 16)},
                {"condition": {"ctg": 5.0}, "total_return": stat(2.0, 16)},
                {"condition": {"ctg": 3.0}, "total_return": stat(1.0, 16)},
            ],
        });
        let s = Score::of(&summary);
        assert!((s.gain_se - 4.0).abs() < 1e-12);
        assert_eq!((s.within, s.found), (0.75, 0.6));
        assert_eq!(s.revisit, (2.0 * 1.0 + 6.0 * 0.5) / 8.0);
        assert_eq!(s.rho, 1.0);
        assert_eq!((s.first_cost, s.last_cost), (4.0, 1.0));
        assert!(
            s.random_within.is_nan(),
            "filled only beside a random policy"
        );
    }
}
