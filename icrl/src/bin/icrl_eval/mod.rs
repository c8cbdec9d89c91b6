//! `icrl eval`: evaluate pretrained checkpoints on held-out edge-oriented
//! tasks (SPEC section 5). The work is `icrl::eval::command::run`.

use std::path::PathBuf;

use clap::Args;
use icrl::eval::command::{self, EvalOptions};
use safety_envs::EnvName;

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Checkpoint to evaluate: an EPPO run folder or checkpoints/step_N folder,
    /// or an AD run folder. Repeat to draw several methods on the same axes.
    #[arg(long, value_name = "DIR")]
    checkpoint: Vec<PathBuf>,
    /// A name for each --checkpoint, in order, in legends and file names
    /// (e.g. to compare AD trained on 25%, 50% and 100% of a dataset). With
    /// --from: a name for each folder, whose reports below it (several runs
    /// and evaluation seeds, say) are pooled into one curve of Figure 1.
    #[arg(long, value_name = "NAME")]
    label: Vec<String>,
    /// Environment (required unless --from).
    #[arg(long, value_parser = ["darkroom", "point", "car"])]
    env: Option<String>,
    /// Evaluate nothing: redraw Figures 1 and 2, one column per environment,
    /// from the JSON reports earlier runs wrote into these folders (repeatable).
    #[arg(long, value_name = "DIR", conflicts_with_all = ["checkpoint", "env"])]
    from: Vec<PathBuf>,
    /// Held-out evaluation tasks (edge-oriented).
    #[arg(long, default_value_t = 16, allow_hyphen_values = true, value_parser = crate::parse_count)]
    tasks: usize,
    /// Episodes K per task, context carried across them (default: 50 SafeDarkRoom,
    /// 20 Point and Car, capped by what an EPPO model's context holds).
    #[arg(long, allow_hyphen_values = true, value_parser = crate::parse_count)]
    episodes: Option<usize>,
    /// Budgets (EPPO) or CTGs (AD) instead of the defaults, comma-separated.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    budgets: Option<Vec<f32>>,
    /// Budgets sampled for EPPO when --budgets is not given (paper: 100).
    #[arg(long, default_value_t = 100, allow_hyphen_values = true, value_parser = crate::parse_count)]
    n_budgets: usize,
    /// RTG target for AD (paper: 1).
    #[arg(long, default_value_t = 1.0, allow_hyphen_values = true)]
    rtg: f32,
    /// Also run the budget sweep (Figure 2).
    #[arg(long)]
    sweep: bool,
    /// Leave out the random-policy baseline.
    #[arg(long)]
    no_random: bool,
    /// Write an animation (GIF) of one evaluation task across its K episodes.
    #[arg(long)]
    render: bool,
    /// The task rendered by --render: its index among the --tasks held-out tasks.
    #[arg(long, default_value_t = 0, requires = "render")]
    render_task: usize,
    /// The budget rendered by --render: its index among the evaluated budgets
    /// (the order of the _conditions.csv rows).
    #[arg(long, default_value_t = 0, requires = "render")]
    render_budget: usize,
    /// Output folder.
    #[arg(long, default_value = "results/eval")]
    out: PathBuf,
    /// Evaluation seed (selects the held-out task seeds and sampled budgets).
    #[arg(long, default_value_t = 0, allow_hyphen_values = true, value_parser = crate::parse_seed)]
    seed: u64,
    /// Trajectories acted on together.
    #[arg(long, default_value_t = 256, allow_hyphen_values = true, value_parser = crate::parse_count)]
    batch: usize,
    /// Threads (environment stepping and libtorch); default: all cores. A
    /// reading repeats exactly under the same seed and thread count; on the
    /// robots another thread count can change some trajectories (a last-bit
    /// difference that contacts amplify), so a claim names its count.
    #[arg(long, allow_hyphen_values = true, value_parser = crate::parse_count)]
    threads: Option<usize>,
    /// Act with the policy's mode instead of sampling.
    #[arg(long)]
    greedy: bool,
    /// Diagnostic, not the paper's protocol: evaluate on centre-oriented tasks (the
    /// pretraining distribution, on unseen seeds); outputs get a `_centre` suffix.
    #[arg(long)]
    in_distribution: bool,
    /// Time limit in agent steps (default: the checkpoint's, else the environment's).
    #[arg(long, allow_hyphen_values = true, value_parser = crate::parse_count)]
    max_episode_steps: Option<usize>,
    /// Replace output files that exist (regular files only; without it they
    /// are refused before anything is evaluated).
    #[arg(long)]
    force: bool,
}

pub fn eval(args: EvalArgs) -> anyhow::Result<()> {
    if !args.from.is_empty() {
        let out = command::replot(&args.from, &args.label, &args.out, args.force)?;
        for line in &out.lines {
            println!("{line}");
        }
        println!("wrote {} files to {}", out.files.len(), args.out.display());
        return Ok(());
    }
    let Some(env) = args.env else {
        anyhow::bail!("--env is required (darkroom, point or car), unless redrawing with --from");
    };
    let env: EnvName = env.parse()?;
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let opts = EvalOptions {
        env,
        tasks: args.tasks,
        episodes: args.episodes,
        budgets: args.budgets,
        n_budgets: args.n_budgets,
        rtg: args.rtg,
        sweep: args.sweep,
        random: !args.no_random,
        render: args
            .render
            .then_some((args.render_budget, args.render_task)),
        out: args.out,
        eval_seed: args.seed,
        batch: args.batch,
        threads,
        greedy: args.greedy,
        max_episode_steps: args.max_episode_steps,
        progress: true,
        in_distribution: args.in_distribution,
        seed_torch: true,
        command: std::env::args().collect::<Vec<_>>().join(" "),
        force: args.force,
    };
    // Bad options and an unwritable output folder fail before any loading.
    if !args.label.is_empty() && args.label.len() != args.checkpoint.len() {
        anyhow::bail!(
            "--label given {} times for {} --checkpoint: give one label per checkpoint, in the same order",
            args.label.len(),
            args.checkpoint.len()
        );
    }
    opts.validate()?;
    let made_out = !opts.out.exists();
    command::check_output_dir(&opts.out)?;
    let result = evaluate(&args.checkpoint, &args.label, env, threads, &opts);
    if result.is_err() && made_out {
        // A refused eval leaves no empty --out folder behind (only if empty).
        let _ = std::fs::remove_dir(&opts.out);
    }
    result
}

/// Loads the checkpoints and runs the evaluation.
fn evaluate(
    checkpoints: &[PathBuf],
    labels: &[String],
    env: EnvName,
    threads: usize,
    opts: &EvalOptions,
) -> anyhow::Result<()> {
    tch::set_num_threads(threads as i32);
    let mut agents = checkpoints
        .iter()
        .map(|p| icrl::eval::load::load_checkpoint(p, env))
        .collect::<Result<Vec<_>, _>>()?;
    for (agent, label) in agents.iter_mut().zip(labels) {
        agent.label = Some(label.clone());
    }
    let out = command::run(agents, opts)?;
    for line in &out.lines {
        println!("{line}");
    }
    println!("wrote {} files to {}", out.files.len(), opts.out.display());
    Ok(())
}
