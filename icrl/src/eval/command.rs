//! The `eval` command: load checkpoints, run the paper's evaluation protocol
//! on held-out edge-oriented tasks, write JSON, CSV, figures and an animation.
//!
//! Protocols (SPEC section 5):
//! - *Figure 1* (always): K episodes per task; EPPO conditioned on `n_budgets`
//!   budgets drawn from the pretraining range ([1, 15] SafeDarkRoom,
//!   [10, 50] Point and Car), averaged; supervised (AD) with RTG 1, CTG 0;
//!   explicit `budgets` replace either.
//! - *Figure 2* (`sweep`): EPPO over a budget grid (1..15 step 1, 10..50
//!   step 5); AD over CTG 5..15 / 0..10 step 1 with RTG = max(0.5, CTG / 10).
//! - A random policy is evaluated beside them for scale.
//!
//! Files in `out`: `{method}_{env}[_sweep].json` (settings, raw per-episode
//! results, summary), `{method}_{env}_episodes.csv`,
//! `{method}_{env}[_sweep]_conditions.csv`, `figure1_{env}.{png,svg}`,
//! `figure2_{env}.{png,svg}`, `render_{method}_{env}.gif`.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use safety_envs::output::{self, Existing};
use safety_envs::{CmdpEnv, EnvError, EnvName, EnvOptions, Orientation, make_env, spawn_config};
use serde::Serialize;

use super::error::EvalCmdError;
use super::load::{ContextLimit, LoadedAgent};
use super::render::render;
use crate::agent::{AgentError, Conditioning};
use crate::eval::{
    self, BudgetRange, EvalConfig, EvalError, Summary, grid, sample_budgets, targets_sweep,
};
use crate::plots::{self, EnvCurves};
use crate::report::{EvalReport, Method};

/// Everything the `eval` command needs, already parsed.
#[derive(Clone, Debug, PartialEq)]
pub struct EvalOptions {
    pub env: EnvName,
    /// Evaluation tasks (paper: 16).
    pub tasks: usize,
    /// Episodes per task; `None`: 50 SafeDarkRoom, 20 Point and Car.
    pub episodes: Option<usize>,
    /// Explicit budgets (EPPO) or CTGs (AD) for the Figure 1 protocol.
    pub budgets: Option<Vec<f32>>,
    /// Budgets sampled for EPPO when `budgets` is `None` (paper: 100).
    pub n_budgets: usize,
    /// RTG for AD in the Figure 1 protocol (paper: 1).
    pub rtg: f32,
    /// Also run the budget sweep (Figure 2).
    pub sweep: bool,
    /// Also evaluate a random policy for scale.
    pub random: bool,
    /// Write an animation of one task across its K episodes.
    pub render: bool,
    pub out: PathBuf,
    pub eval_seed: u64,
    pub batch: usize,
    pub threads: usize,
    pub greedy: bool,
    /// Time limit override (agent steps); `None` keeps the environment's.
    pub max_episode_steps: Option<usize>,
    /// Show a progress bar.
    pub progress: bool,
    /// Reseed libtorch's process-wide generator with `eval_seed` before each
    /// evaluation (the CLI does; tests, which share it, do not).
    pub seed_torch: bool,
    /// Diagnostic: evaluate on centre-oriented tasks (the pretraining
    /// distribution, unseen seeds) instead of the held-out edge-oriented ones.
    pub in_distribution: bool,
    /// The command line, stored in every output file.
    pub command: String,
    /// Replace output files that exist (`--force`); otherwise they are
    /// refused before anything is evaluated.
    pub force: bool,
}

/// The defaults of one environment.
#[derive(Clone, Debug, PartialEq)]
pub struct EnvDefaults {
    pub title: &'static str,
    pub episodes: usize,
    pub budget_range: BudgetRange,
    /// EPPO's sweep grid.
    pub budget_grid: Vec<f32>,
    /// AD's sweep CTGs.
    pub ctg_grid: Vec<f32>,
}

/// SPEC section 5's settings for `env`.
pub fn env_defaults(env: EnvName) -> EnvDefaults {
    match env {
        EnvName::DarkRoom => EnvDefaults {
            title: "SafeDarkRoom",
            episodes: 50,
            budget_range: BudgetRange {
                low: 1.0,
                high: 15.0,
            },
            budget_grid: grid(1.0, 15.0, 1.0),
            ctg_grid: grid(5.0, 15.0, 1.0),
        },
        EnvName::Point | EnvName::Car => EnvDefaults {
            title: if env == EnvName::Point {
                "SafeDarkMujoco Point"
            } else {
                "SafeDarkMujoco Car"
            },
            episodes: 20,
            budget_range: BudgetRange {
                low: 10.0,
                high: 50.0,
            },
            budget_grid: grid(10.0, 50.0, 5.0),
            ctg_grid: grid(0.0, 10.0, 1.0),
        },
    }
}

/// The conditions of a protocol for a method, validated.
pub fn conditions(
    method: Method,
    sweep: bool,
    opts: &EvalOptions,
    range: BudgetRange,
) -> Result<Vec<Conditioning>, EvalCmdError> {
    let d = env_defaults(opts.env);
    let conds = match (method, sweep) {
        (Method::Eppo, false) => {
            let budgets = match &opts.budgets {
                Some(b) => b.clone(),
                None => sample_budgets(range, opts.n_budgets, opts.eval_seed)?,
            };
            for &b in &budgets {
                range.check(b)?;
            }
            budgets
                .into_iter()
                .map(|ctg| Conditioning::Budget { ctg })
                .collect()
        }
        (Method::Eppo, true) => sweep_grid(&d.budget_grid, range)
            .into_iter()
            .map(|ctg| Conditioning::Budget { ctg })
            .collect(),
        (Method::Ad, false) => match &opts.budgets {
            Some(b) => b
                .iter()
                .map(|&ctg| Conditioning::Targets { rtg: opts.rtg, ctg })
                .collect(),
            None => vec![Conditioning::Targets {
                rtg: opts.rtg,
                ctg: 0.0,
            }],
        },
        (Method::Ad, true) => targets_sweep(&d.ctg_grid),
        // The random policy ignores its conditioning; the budgets (EPPO's)
        // only decide what counts as a violation.
        (Method::Random, false) => match &opts.budgets {
            Some(b) => b.iter().map(|&ctg| Conditioning::Budget { ctg }).collect(),
            None => sample_budgets(range, opts.n_budgets, opts.eval_seed)?
                .into_iter()
                .map(|ctg| Conditioning::Budget { ctg })
                .collect(),
        },
        (Method::Random, true) => d
            .budget_grid
            .iter()
            .map(|&ctg| Conditioning::Budget { ctg })
            .collect(),
    };
    if conds.is_empty() {
        return Err(EvalCmdError::Options(
            "no budgets to evaluate (--budgets is empty)".into(),
        ));
    }
    Ok(conds)
}

/// EPPO's sweep: the environment's grid where it lies inside the budgets the
/// policy was pretrained on; when fewer than 5 of its points do (a preset
/// with its own range, e.g. Point's [2, 20] against the paper's [10, 50]),
/// 9 budgets evenly spread over that range instead.
fn sweep_grid(grid: &[f32], range: BudgetRange) -> Vec<f32> {
    let inside: Vec<f32> = grid
        .iter()
        .copied()
        .filter(|&b| range.check(b).is_ok())
        .collect();
    if inside.len() >= 5 {
        return inside;
    }
    let n = 9;
    (0..n)
        .map(|i| range.low + (range.high - range.low) * i as f32 / (n - 1) as f32)
        .collect()
}

fn io_err(path: &Path) -> impl Fn(std::io::Error) -> EvalCmdError + '_ {
    move |source| EvalCmdError::Io {
        path: path.display().to_string(),
        source,
    }
}

/// Writes `value` as pretty JSON to `path`.
fn write_json(path: &Path, value: &impl Serialize) -> Result<(), EvalCmdError> {
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
fn write_csvs(report: &EvalReport, stem: &Path) -> Result<Vec<PathBuf>, EvalCmdError> {
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

/// Runs one protocol for one agent and writes its JSON and CSVs.
fn run_one(
    loaded: &mut LoadedAgent,
    sweep: bool,
    opts: &EvalOptions,
    record: bool,
    like: Option<Method>,
    written: &mut Vec<PathBuf>,
) -> Result<EvalReport, EvalCmdError> {
    let d = env_defaults(opts.env);
    let range = loaded.budget_range.unwrap_or(d.budget_range);
    // The random policy gets the conditions of the agents it is drawn
    // beside (`like`: the first pretrained one), so its over-budget rate is
    // measured against the same budgets.
    let protocol_of = match (loaded.method, like) {
        (Method::Random, Some(m)) => m,
        (m, _) => m,
    };
    let conds = conditions(protocol_of, sweep, opts, range)?;
    // The time limit: asked for, else the one the policy was trained with,
    // else the environment's.
    let env = opts.env;
    // The macro action: the one the checkpoint was trained with.
    let env_options = EnvOptions {
        max_episode_steps: opts
            .max_episode_steps
            .or(loaded.context.map(|c| c.max_episode_steps)),
        physics_steps_per_action: loaded.physics_steps_per_action,
    };
    let make = move || -> Result<Box<dyn CmdpEnv>, EnvError> { make_env(env, &env_options) };
    let t_max = make()?.max_episode_steps();
    let episodes = episodes_for(loaded.context, opts.episodes, d.episodes, t_max)?;
    let cfg = EvalConfig {
        tasks: opts.tasks,
        episodes,
        conditions: conds,
        eval_seed: opts.eval_seed,
        batch: opts.batch,
        threads: opts.threads,
        greedy: opts.greedy,
        pretrain_tasks: loaded.pretrain_tasks.clone(),
        record: record.then_some((0, 0)),
        torch_seed: opts.seed_torch.then_some(opts.eval_seed),
        orientation: if opts.in_distribution {
            Orientation::Centre
        } else {
            Orientation::Edge
        },
        search_cell: crate::signals::search_cell(env),
        repeat_radius: crate::signals::repeat_radius(env),
    };
    cfg.validate()?;

    let protocol = match (sweep, opts.in_distribution) {
        (false, false) => "figure1",
        (true, false) => "sweep",
        (false, true) => "figure1-centre",
        (true, true) => "sweep-centre",
    };
    let total_episodes = (cfg.trajectories() * episodes) as u64;
    let bar = progress_bar(
        opts.progress,
        total_episodes,
        &format!("{} {protocol}", loaded.method),
    );
    let checksum = |l: &LoadedAgent| -> Result<Option<u64>, AgentError> {
        if l.parameters.is_empty() {
            Ok(None)
        } else {
            eval::parameters_checksum(&l.parameters).map(Some)
        }
    };
    let before = checksum(loaded)?;
    let start = Instant::now();
    let result = eval::evaluate(
        loaded.agent.as_mut(),
        &make,
        &spawn_config(env),
        &cfg,
        &mut |n| bar.inc(n as u64),
    )?;
    let wall_seconds = start.elapsed().as_secs_f64();
    bar.finish_and_clear();
    let after = checksum(loaded)?;
    if let (Some(b), Some(a)) = (before, after)
        && a != b
    {
        return Err(EvalCmdError::Checkpoint {
            path: checkpoint_name(loaded),
            message: format!(
                "parameters changed during evaluation (checksum {b:#x} -> {a:#x}): evaluation must be frozen"
            ),
        });
    }
    let report = EvalReport {
        env: env.to_string(),
        method: loaded.method,
        label: loaded.label.clone(),
        checkpoint: loaded.checkpoint.as_ref().map(|p| p.display().to_string()),
        checkpoint_note: loaded.note.clone(),
        protocol: protocol.into(),
        command: opts.command.clone(),
        tasks: opts.tasks,
        episodes,
        max_episode_steps: t_max,
        physics_steps_per_action: env.physics_steps_per_action(loaded.physics_steps_per_action),
        threads: opts.threads,
        parameters_checksum: before.zip(after).map(|(b, a)| [b, a]),
        wall_seconds,
        summary: result.summary(),
        result,
    };
    let stem = report_stem(loaded, sweep, opts);
    let json = stem.with_extension("json");
    write_json(&json, &report)?;
    written.push(json);
    written.extend(write_csvs(&report, &stem)?);
    Ok(report)
}

/// The path stem of one report: `{stem}_{env}[_sweep][_centre]`.
fn report_stem(loaded: &LoadedAgent, sweep: bool, opts: &EvalOptions) -> PathBuf {
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
fn check_planned_files(agents: &[LoadedAgent], opts: &EvalOptions) -> Result<(), EvalCmdError> {
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
        if opts.render {
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

/// Episodes per trajectory: `asked`, else the environment's `default`
/// capped by what the model's `context` holds; refused, with the option to
/// pass, when an episode of `t_max` steps or the asked episodes do not fit.
fn episodes_for(
    context: Option<ContextLimit>,
    asked: Option<usize>,
    default: usize,
    t_max: usize,
) -> Result<usize, EvalCmdError> {
    if let Some(c) = context
        && t_max > c.max_len
    {
        return Err(EvalCmdError::Options(format!(
            "one episode of {t_max} steps does not fit the checkpoint's context of {} steps: \
             pass --max-episode-steps {} or less (the checkpoint was trained with {})",
            c.max_len, c.max_len, c.max_episode_steps
        )));
    }
    // Episodes: asked for, else the paper's K capped by what the context holds.
    let episodes = match (asked, context) {
        (Some(k), Some(c)) if k * t_max > c.max_len => {
            return Err(EvalCmdError::Options(format!(
                "{} episodes of {t_max} steps need a context of {} steps; the checkpoint's model holds {} \
                 ({} episodes): pass --episodes {} or less",
                k,
                k * t_max,
                c.max_len,
                c.episodes(t_max),
                c.episodes(t_max)
            )));
        }
        (Some(k), _) => k,
        (None, Some(c)) => default.min(c.episodes(t_max)),
        (None, None) => default,
    };
    if episodes == 0 {
        return Err(EvalCmdError::Options(format!(
            "no whole episode of {t_max} steps fits the model's context"
        )));
    }
    Ok(episodes)
}

/// The episodes' progress bar, named `prefix` (hidden without `progress`).
fn progress_bar(progress: bool, total: u64, prefix: &str) -> ProgressBar {
    if progress {
        let bar = ProgressBar::new(total);
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix:>24} [{elapsed_precise}] {wide_bar} {pos}/{len} episodes (eta {eta})",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar.set_prefix(prefix.to_string());
        bar
    } else {
        ProgressBar::hidden()
    }
}

fn checkpoint_name(loaded: &LoadedAgent) -> String {
    loaded
        .checkpoint
        .as_ref()
        .map(|p| p.display().to_string())
        .unwrap_or_else(|| loaded.method.to_string())
}

/// What one `eval` run produced.
#[derive(Debug, Default)]
pub struct EvalOutputs {
    /// Every file written.
    pub files: Vec<PathBuf>,
    /// One line per (method, protocol): the headline numbers.
    pub lines: Vec<String>,
}

fn headline(r: &EvalReport) -> String {
    let t = &r.summary.trend;
    format!(
        "{} {} {}: return first {} eps {:.3}±{:.3} -> last {:.3}±{:.3}; cost {:.3}±{:.3} -> {:.3}±{:.3}; \
         over-budget rate last {:.3}{}; {:.1} s",
        r.method,
        r.env,
        r.protocol,
        t.window,
        t.first_return.mean,
        t.first_return.se,
        t.last_return.mean,
        t.last_return.se,
        t.first_cost.mean,
        t.first_cost.se,
        t.last_cost.mean,
        t.last_cost.se,
        r.summary
            .per_episode
            .last()
            .map(|e| e.violation.mean)
            .unwrap_or(f64::NAN),
        match (&r.summary.total_return_slope, &r.summary.max_cost_slope) {
            (Some(a), Some(b)) => format!(
                "; d total return / d CTG {:.3}±{:.3}, d max cost / d CTG {:.3}±{:.3}",
                a.mean, a.se, b.mean, b.se
            ),
            _ => String::new(),
        },
        r.wall_seconds
    )
}

impl EvalOptions {
    /// Refuses counts of zero and numbers that are not finite, naming the
    /// command-line option.
    pub fn validate(&self) -> Result<(), EvalCmdError> {
        let bad = |m: String| Err(EvalCmdError::Options(m));
        for (name, v) in [
            ("--batch", Some(self.batch)),
            ("--threads", Some(self.threads)),
            ("--episodes", self.episodes),
            ("--max-episode-steps", self.max_episode_steps),
        ] {
            if v == Some(0) {
                return bad(format!("{name} 0: must be at least 1"));
            }
        }
        if self.threads > 1024 {
            return bad(format!("--threads {}: must be at most 1024", self.threads));
        }
        if self.budgets.is_none() && self.n_budgets == 0 {
            return bad("--n-budgets 0: must be at least 1 (or give --budgets)".into());
        }
        if let Some(b) = self.budgets.iter().flatten().find(|b| !b.is_finite()) {
            return bad(format!("--budgets: {b} is not a finite number"));
        }
        if !self.rtg.is_finite() {
            return bad(format!("--rtg {}: must be a finite number", self.rtg));
        }
        // Conditioning values: EPPO's budgets are checked against the range
        // the checkpoint was pretrained on; AD's RTG and CTG here.
        let (lo, hi) = CONDITIONING_RANGE;
        if !(lo..=hi).contains(&self.rtg) {
            return bad(format!(
                "--rtg {}: must be in [{lo}, {hi}] (episode returns are small numbers; the paper uses 1)",
                self.rtg
            ));
        }
        if let Some(b) = self
            .budgets
            .iter()
            .flatten()
            .find(|b| !(lo..=hi).contains(*b))
        {
            return bad(format!(
                "--budgets: {b} must be in [{lo}, {hi}] (a cost budget per episode)"
            ));
        }
        // The work, before its memory: an evaluation of hours with no end in
        // sight is refused, not started.
        let conds = self.budgets.as_ref().map_or(self.n_budgets, Vec::len) as u128;
        let k = self.episodes.unwrap_or(env_defaults(self.env).episodes) as u128;
        let episodes = conds * self.tasks as u128 * k;
        if episodes > MAX_EVAL_EPISODES {
            return bad(format!(
                "this evaluation is {episodes} episodes per method ({conds} budgets x {} tasks x {k} \
                 episodes), more than the {MAX_EVAL_EPISODES} one evaluation may hold (the paper's \
                 largest protocol is 100 x 16 x 50 = 80000); lower --n-budgets (or the number of \
                 --budgets), --tasks or --episodes",
                self.tasks
            ));
        }
        self.memory_estimate()
            .check()
            .map_err(EvalCmdError::Options)
    }

    /// The memory the results of one protocol take: every (budget, task,
    /// episode) result and the sampled budgets, before anything is sampled.
    pub fn memory_estimate(&self) -> crate::guard::MemoryEstimate {
        let conds = self.budgets.as_ref().map_or(self.n_budgets, Vec::len) as f64;
        let k = self.episodes.unwrap_or(env_defaults(self.env).episodes) as f64;
        let mut m = crate::guard::MemoryEstimate {
            levers: "--n-budgets (or the number of --budgets), --tasks or --episodes".into(),
            ..Default::default()
        };
        m.add("budgets and their records", 64.0 * conds);
        // Return, cost, length, goal flag, and the summary's working copies.
        m.add(
            "per-episode results of every budget, task and episode",
            64.0 * conds * self.tasks as f64 * k,
        );
        m
    }
}

/// Episodes one evaluation may run per method: 12.5 times the paper's
/// largest protocol (100 budgets x 16 tasks x 50 episodes).
pub const MAX_EVAL_EPISODES: u128 = 1_000_000;

/// The RTG and CTG values `eval` accepts (`--rtg`, `--budgets`).
pub const CONDITIONING_RANGE: (f32, f32) = (0.0, 10_000.0);

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
fn refuse_checkpoint_folder(dir: &Path) -> Result<(), EvalCmdError> {
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

/// Runs the `eval` command for `agents` (plus a random policy when asked).
pub fn run(mut agents: Vec<LoadedAgent>, opts: &EvalOptions) -> Result<EvalOutputs, EvalCmdError> {
    opts.validate()?;
    if opts.tasks == 0 {
        return Err(EvalError::Config(
            "the task set is empty: ask for at least one evaluation task (--tasks)".into(),
        )
        .into());
    }
    if agents.is_empty() && !opts.random {
        return Err(EvalCmdError::Options(
            "nothing to evaluate: give --checkpoint DIR, or leave out --no-random to evaluate the random policy".into(),
        ));
    }
    let probe = make_env(
        opts.env,
        &EnvOptions {
            max_episode_steps: opts.max_episode_steps,
            ..EnvOptions::default()
        },
    )?;
    // The agent the random policy is compared with (EPPO before AD).
    let like = agents
        .iter()
        .filter(|a| a.method != Method::Random)
        .min_by_key(|a| a.method as u8)
        .map(|a| (a.method, a.budget_range, a.physics_steps_per_action));
    if opts.random {
        let mut random = LoadedAgent::random(probe.action_space(), opts.eval_seed);
        if let Some((_, range, physics)) = like {
            // The same budgets and macro action as the agent it is drawn beside.
            random.budget_range = range;
            random.physics_steps_per_action = physics;
        }
        agents.push(random);
    }
    check_planned_files(&agents, opts)?;
    check_output_dir(&opts.out)?;
    let d = env_defaults(opts.env);
    let mut out = EvalOutputs::default();
    let mut fig1 = EnvCurves {
        env: d.title.into(),
        methods: Vec::new(),
        random: None,
    };
    let mut fig2 = fig1.clone();
    // EPPO before AD (colours and file order); the random policy last, with
    // as many episodes as the longest evaluation before it.
    agents.sort_by_key(|a| a.method as u8);
    let mut longest_episodes: Option<usize> = None;
    for (i, loaded) in agents.iter_mut().enumerate() {
        // Record the first trajectory of every pretrained agent (the random
        // policy comes last: recorded only when it is alone).
        let record = opts.render && (loaded.method != Method::Random || i == 0);
        let mut opts = opts.clone();
        if loaded.method == Method::Random {
            opts.episodes = opts.episodes.or(longest_episodes);
        }
        let opts = &opts;
        let like = like.map(|l| l.0);
        let report = run_one(loaded, false, opts, record, like, &mut out.files)?;
        longest_episodes = Some(longest_episodes.unwrap_or(0).max(report.episodes));
        out.lines.push(headline(&report));
        if record && let Some(rec) = &report.result.recording {
            let gif = opts
                .out
                .join(format!("render_{}_{}.gif", loaded.stem(), opts.env));
            render(opts.env, &report, rec, &gif)?;
            out.files.push(gif);
        }
        match loaded.method {
            Method::Random => fig1.random = Some(report.summary),
            _ => fig1.methods.push((loaded.name(), report.summary)),
        }
        if opts.sweep {
            let report = run_one(loaded, true, opts, false, like, &mut out.files)?;
            out.lines.push(headline(&report));
            match loaded.method {
                Method::Random => fig2.random = Some(report.summary),
                _ => fig2.methods.push((loaded.name(), report.summary)),
            }
        }
    }
    let centre = if opts.in_distribution { "_centre" } else { "" };
    out.files.extend(plots::figure1(
        &[fig1],
        &opts.out.join(format!("figure1_{}{}", opts.env, centre)),
    )?);
    if opts.sweep {
        out.files.extend(plots::figure2(
            &[fig2],
            &opts.out.join(format!("figure2_{}{}", opts.env, centre)),
        )?);
    }
    Ok(out)
}

/// Redraws Figures 1 and 2 with one column per environment from the JSON
/// reports earlier `eval` runs wrote into `dirs` (files that are not reports
/// are skipped). Writes `figure1_all` and, when sweeps are present,
/// `figure2_all` (PNG and SVG) into `out`.
pub fn replot(dirs: &[PathBuf], out: &Path, force: bool) -> Result<EvalOutputs, EvalCmdError> {
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
    // (env, method, sweep) -> summary, in file-name order for stability.
    let mut reports: Vec<(EnvName, Method, bool, Summary)> = Vec::new();
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
            let text = std::fs::read(&f).map_err(io_err(&f))?;
            // A damaged or foreign JSON file is named, never skipped in
            // silence: the figure would lack a curve without saying so.
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
                continue;
            };
            if protocol.ends_with("-centre") {
                continue;
            }
            let method = match method {
                "Eppo" => Method::Eppo,
                "Ad" => Method::Ad,
                "Random" => Method::Random,
                _ => continue,
            };
            let summary: Summary =
                serde_json::from_value(summary.clone()).map_err(|source| EvalCmdError::Json {
                    path: f.display().to_string(),
                    source,
                })?;
            reports.push((env, method, protocol == "sweep", summary));
        }
    }
    if reports.is_empty() {
        return Err(EvalCmdError::Options(format!(
            "no eval reports (*.json written by icrl eval) in {}",
            dirs.iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        )));
    }
    let curves = |sweep: bool| -> Vec<EnvCurves> {
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
    };
    output::create_folder(out)?;
    let mut outputs = EvalOutputs::default();
    let fig1 = curves(false);
    if !fig1.is_empty() {
        outputs
            .files
            .extend(plots::figure1(&fig1, &out.join("figure1_all"))?);
    }
    let fig2 = curves(true);
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

#[cfg(test)]
mod tests {
    use super::*;

    fn options(out: PathBuf) -> EvalOptions {
        EvalOptions {
            env: EnvName::DarkRoom,
            tasks: 3,
            episodes: Some(4),
            budgets: None,
            n_budgets: 3,
            rtg: 1.0,
            sweep: true,
            random: true,
            render: false,
            out,
            eval_seed: 0,
            batch: 64,
            threads: 1,
            greedy: false,
            max_episode_steps: None,
            progress: false,
            command: "test".into(),
            seed_torch: false,
            in_distribution: false,
            force: false,
        }
    }

    #[test]
    fn labels_name_checkpoints_of_one_method_apart() {
        let probe = make_env(EnvName::DarkRoom, &EnvOptions::default()).unwrap();
        // Naming reads only the method and the label.
        let agent = |label: Option<&str>| LoadedAgent {
            method: Method::Ad,
            label: label.map(String::from),
            ..LoadedAgent::random(probe.action_space(), 0)
        };
        assert_eq!(
            (agent(None).name(), agent(None).stem()),
            ("AD".into(), "ad".into())
        );
        let a = agent(Some("AD 25% of tasks"));
        assert_eq!(
            (a.name(), a.stem()),
            ("AD 25% of tasks".into(), "ad_ad-25--of-tasks".into())
        );
        assert_ne!(agent(Some("AD 50%")).stem(), agent(Some("AD 100%")).stem());
    }

    #[test]
    fn random_policy_evaluation_writes_every_file() {
        let dir = std::env::temp_dir().join(format!("icrl-eval-cmd-{}", std::process::id()));
        let out = run(Vec::new(), &options(dir.clone())).unwrap();
        for name in [
            "random_darkroom.json",
            "random_darkroom_episodes.csv",
            "random_darkroom_conditions.csv",
            "random_darkroom_sweep.json",
            "random_darkroom_sweep_conditions.csv",
            "figure1_darkroom.png",
            "figure1_darkroom.svg",
            "figure2_darkroom.png",
            "figure2_darkroom.svg",
        ] {
            let p = dir.join(name);
            assert!(out.files.contains(&p), "{name} not reported");
            assert!(
                std::fs::metadata(&p).unwrap().len() > 100,
                "{name} is empty"
            );
        }
        let json: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join("random_darkroom_sweep.json")).unwrap())
                .unwrap();
        assert_eq!(json["result"]["conditions"].as_array().unwrap().len(), 15);
        assert_eq!(json["episodes"], 4);
        let csv = std::fs::read_to_string(dir.join("random_darkroom_episodes.csv")).unwrap();
        assert_eq!(csv.lines().filter(|l| !l.starts_with('#')).count(), 1 + 4);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn reports_of_two_environments_are_redrawn_side_by_side() {
        let dir = std::env::temp_dir().join(format!("icrl-eval-replot-{}", std::process::id()));
        let mut a = options(dir.join("darkroom"));
        a.sweep = false;
        run(Vec::new(), &a).unwrap();
        let mut b = options(dir.join("point"));
        b.env = EnvName::Point;
        b.episodes = Some(2);
        b.sweep = false;
        run(Vec::new(), &b).unwrap();
        let out = replot(
            &[dir.join("darkroom"), dir.join("point")],
            &dir.join("all"),
            false,
        )
        .unwrap();
        assert_eq!(out.files.len(), 2, "figure 1 only: no sweeps");
        assert!(
            out.lines[0].contains("2 reports (2 environments)"),
            "{:?}",
            out.lines
        );
        assert!(
            std::fs::metadata(dir.join("all/figure1_all.png"))
                .unwrap()
                .len()
                > 1000
        );
        let e = replot(&[dir.join("all")], &dir.join("x"), false)
            .unwrap_err()
            .to_string();
        assert!(e.contains("no eval reports"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn eppo_sweep_stays_inside_the_pretrained_budget_range() {
        let dir = std::env::temp_dir().join(format!("icrl-eval-cmd-sweep-{}", std::process::id()));
        let opts = options(dir);
        let budgets = |range: BudgetRange| -> Vec<f32> {
            conditions(Method::Eppo, true, &opts, range)
                .unwrap()
                .into_iter()
                .map(|c| match c {
                    Conditioning::Budget { ctg } => ctg,
                    other => panic!("{other:?}"),
                })
                .collect()
        };
        let paper = env_defaults(EnvName::DarkRoom).budget_range;
        assert_eq!(budgets(paper), grid(1.0, 15.0, 1.0), "the paper's grid");
        let narrow = BudgetRange {
            low: 2.0,
            high: 20.0,
        };
        assert_eq!(
            sweep_grid(&env_defaults(EnvName::Point).budget_grid, narrow),
            [2.0, 4.25, 6.5, 8.75, 11.0, 13.25, 15.5, 17.75, 20.0],
            "Point's quick range holds only 10, 15, 20 of the paper's grid"
        );
    }

    #[test]
    fn out_of_range_budgets_and_empty_task_sets_are_refused() {
        let dir = std::env::temp_dir().join(format!("icrl-eval-cmd-bad-{}", std::process::id()));
        let mut opts = options(dir.clone());
        opts.budgets = Some(vec![5.0, 20.0]);
        let range = env_defaults(EnvName::DarkRoom).budget_range;
        let e = conditions(Method::Eppo, false, &opts, range)
            .unwrap_err()
            .to_string();
        assert!(e.contains("budget 20 is outside the range [1, 15]"), "{e}");
        opts.budgets = Some(vec![]);
        let e = conditions(Method::Eppo, false, &opts, range)
            .unwrap_err()
            .to_string();
        assert!(e.contains("no budgets"), "{e}");
        let mut opts = options(dir.clone());
        opts.tasks = 0;
        let e = run(Vec::new(), &opts).unwrap_err().to_string();
        assert!(e.contains("task set is empty"), "{e}");
        // Hours of work with no end in sight: refused before anything runs.
        let mut opts = options(dir.clone());
        (opts.tasks, opts.episodes, opts.n_budgets) = (2, Some(2), 10_000_000);
        let e = run(Vec::new(), &opts).unwrap_err().to_string();
        assert!(
            e.contains("this evaluation is 40000000 episodes per method (10000000 budgets x 2 tasks x 2 episodes)"),
            "{e}"
        );
        let mut opts = options(dir);
        opts.random = false;
        let e = run(Vec::new(), &opts).unwrap_err().to_string();
        assert!(e.contains("nothing to evaluate"), "{e}");
    }
}
