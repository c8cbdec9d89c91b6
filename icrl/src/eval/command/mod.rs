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
//!
//! The parts: this file (the options, the conditions and the run of every
//! agent), `files.rs` (the files a run writes, checked before it starts)
//! and `replot.rs` (`--from`: figures redrawn from earlier reports).

use std::path::PathBuf;
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use safety_envs::{CmdpEnv, EnvError, EnvName, EnvOptions, Orientation, make_env, spawn_config};

use super::error::EvalCmdError;
use super::load::{ContextLimit, LoadedAgent};
use super::render::render;
use crate::agent::{AgentError, Conditioning};
use crate::eval::{self, BudgetRange, EvalConfig, EvalError, grid, sample_budgets, targets_sweep};
use crate::plots::{self, EnvCurves};
use crate::report::{EvalReport, Method};

mod files;
mod replot;
#[cfg(test)]
mod tests;

pub use files::check_output_dir;
use files::{check_planned_files, checkpoint_name, report_stem, write_csvs, write_json};
pub use replot::replot;

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
    /// Write an animation of one trajectory across its K episodes: (budget
    /// index, task index).
    pub render: Option<(usize, usize)>,
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

/// Runs one protocol for one agent and writes its JSON and CSVs.
fn run_one(
    loaded: &mut LoadedAgent,
    sweep: bool,
    opts: &EvalOptions,
    record: Option<(usize, usize)>,
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
        record,
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
        let n_conditions = self.budgets.as_ref().map_or(self.n_budgets, Vec::len);
        if let Some((budget, task)) = self.render
            && (budget >= n_conditions || task >= self.tasks)
        {
            return bad(format!(
                "--render-budget {budget} --render-task {task}: the rendered trajectory (budget \
                 index {budget}, task index {task}) is outside the {n_conditions} budgets x {} tasks \
                 evaluated; give each below its count (they count from 0)",
                self.tasks
            ));
        }
        // The work, before its memory: an evaluation of hours with no end in
        // sight is refused, not started.
        let conds = n_conditions as u128;
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
        // Record the chosen trajectory of every pretrained agent (the random
        // policy comes last: recorded only when it is alone).
        let record = opts
            .render
            .filter(|_| loaded.method != Method::Random || i == 0);
        let mut opts = opts.clone();
        if loaded.method == Method::Random {
            opts.episodes = opts.episodes.or(longest_episodes);
        }
        let opts = &opts;
        let like = like.map(|l| l.0);
        let report = run_one(loaded, false, opts, record, like, &mut out.files)?;
        longest_episodes = Some(longest_episodes.unwrap_or(0).max(report.episodes));
        out.lines.push(headline(&report));
        if record.is_some()
            && let Some(rec) = &report.result.recording
        {
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
            let report = run_one(loaded, true, opts, None, like, &mut out.files)?;
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
