//! `icrl`: the command line of safe in-context RL. `main` parses and runs one
//! subcommand; each subcommand's work is a library function.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};

#[path = "icrl_eval/mod.rs"]
mod icrl_eval;

#[derive(Debug, Parser)]
#[command(
    name = "icrl",
    version,
    about = "Safe in-context RL: pretraining and evaluation"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Pretrain an in-context agent (EPPO: Algorithm 1 of the paper).
    Pretrain(PretrainArgs),
    /// Draw a run's learning curves (return, cost, lambda) into <RUN>/learning_curve.png.
    PlotTraining {
        /// The run folder.
        run: PathBuf,
        /// Moving-average window, in metric records.
        #[arg(long, default_value_t = 10, allow_hyphen_values = true, value_parser = parse_count)]
        window: usize,
    },
    /// Make learning histories (PPO-Lagrangian or AD-eps) for supervised pretraining, as HDF5.
    Dataset(DatasetArgs),
    /// Draw how a history file's episodes improve (return and cost against learning progress).
    PlotHistories {
        /// The HDF5 file.
        file: PathBuf,
        /// Output stem: writes STEM.png and STEM.svg.
        #[arg(long)]
        out: PathBuf,
        /// Bins of learning progress (at least 1).
        #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u32).range(1..=100_000))]
        bins: u32,
        /// Replace existing STEM.png and STEM.svg.
        #[arg(long)]
        force: bool,
    },
    /// Evaluate checkpoints in context on held-out edge-oriented tasks: JSON, CSV, figures.
    Eval(icrl_eval::EvalArgs),
    /// Seeds and settings trained here one after another (--run) or as a Slurm job array
    /// (--emit slurm), then their table (--gather).
    Sweep(SweepArgs),
    /// Remove the replay buffers from finished EPPO checkpoints, keeping them loadable: they
    /// still evaluate and fork, and a resume refills the replay.
    DropReplay {
        /// Checkpoint folders (checkpoints/step_N) or run folders (all their checkpoints).
        #[arg(required = true)]
        paths: Vec<PathBuf>,
    },
}

#[derive(Debug, Args)]
struct SweepArgs {
    /// The grid file (TOML: env, method, preset, seeds, out, [set], [grid], [slurm]).
    #[arg(long, value_name = "FILE")]
    grid: PathBuf,
    /// Write OUT/sweep.sbatch: one array task per seed and setting.
    #[arg(long, value_parser = ["slurm"], required_unless_present_any = ["gather", "run"])]
    emit: Option<String>,
    /// Train every task here, one after another (a finished one is skipped, a stopped one
    /// resumes; Ctrl-C stops the task in progress at a checkpoint and ends the sweep, exit 130).
    #[arg(long, conflicts_with_all = ["emit", "gather"])]
    run: bool,
    /// Evaluate every finished run's last checkpoint and write OUT/gather/table.md and table.csv.
    #[arg(long, conflicts_with = "emit")]
    gather: bool,
    /// Held-out evaluation tasks per run (--gather).
    #[arg(long, default_value_t = 16, allow_hyphen_values = true, value_parser = parse_count)]
    tasks: usize,
    /// Episodes per task (--gather; default: the environment's).
    #[arg(long, allow_hyphen_values = true, value_parser = parse_count)]
    episodes: Option<usize>,
    /// Budgets sampled per evaluation (--gather).
    #[arg(long, default_value_t = 100, allow_hyphen_values = true, value_parser = parse_count)]
    n_budgets: usize,
    /// Threads for evaluation (--gather; default: all cores).
    #[arg(long, allow_hyphen_values = true, value_parser = parse_count)]
    threads: Option<usize>,
    /// Replace files written before (the script, the gathered evaluations and table).
    #[arg(long)]
    force: bool,
}

fn drop_replay(paths: &[PathBuf]) -> anyhow::Result<()> {
    let mut freed = 0;
    for path in paths {
        for (checkpoint, bytes) in icrl::eppo::drop_replay(path)? {
            match bytes {
                Some(b) => {
                    freed += b;
                    println!(
                        "{}: replay removed ({:.1} MB)",
                        checkpoint.display(),
                        b as f64 / 1e6
                    );
                }
                None => println!("{}: holds no replay", checkpoint.display()),
            }
        }
    }
    println!("freed {:.1} MB", freed as f64 / 1e6);
    Ok(())
}

fn sweep(args: SweepArgs) -> anyhow::Result<ExitCode> {
    use icrl::cli::sweep::{GatherOptions, SweepGrid, emit_slurm, gather, run_local};
    let grid = SweepGrid::load(&args.grid)?;
    if args.run {
        let ran = run_local(&grid, &std::env::current_exe()?)?;
        println!(
            "{} tasks trained, {} already finished{}",
            ran.trained,
            ran.skipped,
            if ran.stopped {
                "; stopped: run the same command again to continue"
            } else {
                ""
            }
        );
        return Ok(if ran.stopped {
            ExitCode::from(icrl::stop::EXIT_INTERRUPTED)
        } else {
            ExitCode::SUCCESS
        });
    }
    if !args.gather {
        let icrl = match &grid.slurm.icrl {
            Some(p) => p.clone(),
            None => std::env::current_exe()?,
        };
        let script = emit_slurm(&grid, &icrl, args.force)?;
        println!(
            "wrote {} ({} array tasks); submit it with:\n  sbatch {}\nthen, when the tasks are done:\n  icrl sweep --grid {} --gather",
            script.display(),
            grid.tasks().len(),
            icrl::run_summary::shell_word(&script),
            icrl::run_summary::shell_word(&args.grid)
        );
        return Ok(ExitCode::SUCCESS);
    }
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let g = gather(
        &grid,
        &GatherOptions {
            tasks: args.tasks,
            episodes: args.episodes,
            n_budgets: args.n_budgets,
            threads,
            force: args.force,
        },
    )?;
    for (task, why) in &g.unfinished {
        eprintln!("task {task}: {why}");
    }
    for (task, why) in &g.left_out {
        eprintln!("task {task}: left out of the table: {why}");
    }
    if g.evaluated == 0 {
        anyhow::bail!(
            "no run to gather ({} not finished, {} left out); nothing was written",
            g.unfinished.len(),
            g.left_out.len()
        );
    }
    print!("{}", g.table);
    println!(
        "{} runs evaluated, {} not finished, {} left out; wrote {}",
        g.evaluated,
        g.unfinished.len(),
        g.left_out.len(),
        g.files
            .iter()
            .filter(|f| f.file_stem().is_some_and(|s| s == "table"))
            .map(|f| f.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(ExitCode::SUCCESS)
}

#[derive(Debug, Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
struct DatasetArgs {
    #[command(subcommand)]
    merge: Option<DatasetMerge>,
    /// Environment.
    #[arg(long, required = true, value_parser = ["darkroom", "point", "car"])]
    env: Option<String>,
    /// Output HDF5 file (written beside it, then renamed); an existing file is
    /// refused unless --force.
    #[arg(long, required = true)]
    out: Option<PathBuf>,
    /// Pretraining tasks (centre-oriented).
    #[arg(long, default_value_t = 10, allow_hyphen_values = true, value_parser = parse_count)]
    tasks: usize,
    /// Environment steps per history (paper: 50000).
    #[arg(long, default_value_t = 50_000, allow_hyphen_values = true, value_parser = parse_count)]
    steps: usize,
    /// Cost limits, one history per task and limit (default: 0,2.5,5 SafeDarkRoom; 0,5,10 Point and Car).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    cost_limits: Option<Vec<f32>>,
    /// Master seed.
    #[arg(long, default_value_t = 0, allow_hyphen_values = true, value_parser = parse_seed)]
    seed: u64,
    /// Worker threads (default: all cores).
    #[arg(long, allow_hyphen_values = true, value_parser = parse_count)]
    threads: Option<usize>,
    /// Which learner makes the histories.
    #[arg(long, default_value = "ppo-lagrangian", value_parser = ["ppo-lagrangian", "noisy-optimal"])]
    source: String,
    /// Point and Car: MuJoCo physics steps per agent action, the macro action
    /// (default 50 = 5 Safety-Gymnasium steps x 10 physics steps each);
    /// recorded in the file.
    #[arg(long, value_name = "N", allow_hyphen_values = true, value_parser = parse_count)]
    physics_steps_per_action: Option<usize>,
    /// Keep N episodes of each learning run, spaced evenly in the logarithm of
    /// the episode index, so that a history spans the early, middle and
    /// expert phases of learning (default: keep every episode). Recorded in
    /// the file's config.
    #[arg(long, value_name = "N", allow_hyphen_values = true, value_parser = parse_count)]
    keep_episodes: Option<usize>,
    /// Make only the I-th of N disjoint parts of the task x cost-limit grid
    /// (I from 0, e.g. $SLURM_ARRAY_TASK_ID); the N shards hold what one
    /// unsharded run with the same seed holds. Join them with `icrl dataset merge`.
    #[arg(long, value_name = "I/N")]
    shard: Option<icrl::data::histories::Shard>,
    /// Set one of the PPO-Lagrangian learner's settings, e.g. `--set
    /// learning_rate=3e-4 --set update_epochs=8` (the names: the error for
    /// an unknown one lists them); recorded in the file's config.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// Replace an existing history file at --out (never a device, link,
    /// folder or checkpoint file).
    #[arg(long)]
    force: bool,
}

#[derive(Debug, Subcommand)]
enum DatasetMerge {
    /// One file over the shards of `icrl dataset --shard I/N`: its datasets are HDF5 virtual
    /// datasets over them, read as one file by the AD learner and h5py. Refuses shards of
    /// another grid, missing or repeated parts, and files that fail their checksum.
    Merge {
        /// The merged file, in the shards' folder or above it (it names them relative to itself).
        #[arg(long)]
        out: PathBuf,
        /// The shard files, in any order.
        #[arg(required = true)]
        shards: Vec<PathBuf>,
        /// Replace an existing history file at --out.
        #[arg(long)]
        force: bool,
    },
}

/// A count (tasks, steps, episodes, threads, ...): a whole number from 0 up.
/// Read with `allow_hyphen_values`, so `-1` is named as a bad count rather
/// than "unexpected argument '-1'"; zero is refused where it matters by the
/// command's own checks.
fn parse_count(s: &str) -> Result<usize, String> {
    s.trim().parse::<usize>().map_err(|_| {
        format!(
            "{s:?} is not a count: counts are whole numbers from 0 to {}",
            usize::MAX
        )
    })
}

/// A seed: a whole number from 0 to 2^64 - 1 (clap would call `-1` an
/// unexpected argument).
fn parse_seed(s: &str) -> Result<u64, String> {
    s.trim().parse::<u64>().map_err(|_| {
        format!(
            "{s:?} is not a seed: seeds are whole numbers from 0 to {}",
            u64::MAX
        )
    })
}

fn dataset(args: DatasetArgs) -> anyhow::Result<()> {
    if let Some(DatasetMerge::Merge { out, shards, force }) = args.merge {
        let r = icrl::data::merge::merge(
            &out,
            &shards,
            safety_envs::output::Existing::from_force(force),
        )?;
        println!(
            "wrote {}: {} histories, {} steps, virtual datasets over {} shards ({} bytes of its own)",
            r.out.display(),
            r.histories,
            r.steps,
            r.shards,
            r.bytes
        );
        return Ok(());
    }
    let (Some(env), Some(out)) = (args.env, args.out) else {
        anyhow::bail!("icrl dataset needs --env and --out");
    };
    let source = match args.source.as_str() {
        "noisy-optimal" => icrl::data::dataset::Source::NoisyOptimal,
        _ => icrl::data::dataset::Source::PpoLagrangian,
    };
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let keep_episodes = args.keep_episodes;
    let r = icrl::cli::dataset::dataset_command(&icrl::cli::dataset::DatasetCommand {
        env,
        out,
        tasks: args.tasks,
        steps: args.steps,
        cost_limits: args.cost_limits,
        seed: args.seed,
        threads,
        source,
        physics_steps_per_action: args.physics_steps_per_action,
        keep_episodes: args.keep_episodes,
        shard: args.shard,
        ppo_sets: args.set,
        force: args.force,
    })?;
    println!(
        "wrote {}: {} histories, {} steps{}, {} episodes, {:.1} MB in {:.0} s ({:.0} environment steps/s{}); \
         first 10% of episodes: return {:.3} cost {:.3}; last 10%: return {:.3} cost {:.3}",
        r.out.display(),
        r.histories,
        r.steps,
        r.physics_steps_per_action
            .map_or(String::new(), |n| format!(" of {n} physics steps each")),
        r.episodes,
        r.bytes as f64 / 1e6,
        r.seconds,
        r.steps_taken as f64 / r.seconds,
        // Only with --keep-episodes were episodes subsampled.
        if keep_episodes.is_some() && r.steps < r.steps_taken {
            format!(", {} steps taken, episodes kept log-spaced", r.steps_taken)
        } else {
            String::new()
        },
        r.early.0,
        r.early.1,
        r.late.0,
        r.late.1
    );
    Ok(())
}

#[derive(Debug, Args)]
struct PretrainArgs {
    /// Environment.
    #[arg(long, value_parser = ["darkroom", "point", "car"])]
    env: String,
    /// Learner.
    #[arg(long, default_value = "eppo", value_parser = ["eppo", "ad"])]
    method: String,
    /// Learning histories for `--method ad` (HDF5 from `icrl dataset`).
    #[arg(long, value_name = "FILE")]
    dataset: Option<PathBuf>,
    /// Preset: `table1` (EPPO, the paper's Table 1, a GPU preset), `table2` (AD, the paper's Table 2,
    /// a GPU preset), `quick` (2 CPU cores, about an hour) or `budget` (EPPO on SafeDarkRoom with
    /// the budget honoured: a rising over-budget price, three to four hours on 2 cores).
    #[arg(long, default_value = "quick", value_parser = ["table1", "table2", "quick", "budget"])]
    preset: String,
    /// Device; overrides the preset's.
    #[arg(long, value_parser = ["cpu", "cuda"])]
    device: Option<String>,
    /// Continue a run: its folder (latest checkpoint) or one checkpoints/step_N folder.
    #[arg(long, value_name = "DIR")]
    resume: Option<PathBuf>,
    /// Seed; overrides the preset's.
    #[arg(long, allow_hyphen_values = true, value_parser = parse_seed)]
    seed: Option<u64>,
    /// Override any config field, e.g. `--set total_updates=500 --set model.n_layers=2`.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// Folder that receives the run folder.
    #[arg(long, default_value = "runs")]
    out: PathBuf,
    /// Resume the run of this env and method under --out that trained furthest, if there is
    /// one (done if it has finished), else start one there: a requeued job array task
    /// (`icrl sweep`) continues its own run instead of starting again.
    #[arg(long, conflicts_with = "resume")]
    resume_in_out: bool,
    /// Branch a new run in this folder from the --resume checkpoint (any step_N, not only the
    /// latest), with --set changing any setting but the network's shape; the original run is
    /// left as it is.
    #[arg(
        long,
        value_name = "DIR",
        requires = "resume",
        conflicts_with = "resume_in_out"
    )]
    fork: Option<PathBuf>,
}

/// `pretrain --method ad`: safe supervised pretraining on a history file
/// (libtorch's CUDA device when there is one, else the CPU).
fn pretrain_ad(args: PretrainArgs) -> anyhow::Result<()> {
    let mut sets = args.set;
    if let Some(seed) = args.seed {
        sets.push(format!("seed={seed}"));
    }
    let s = icrl::cli::pretrain::ad(
        &args.env,
        &args.preset,
        args.dataset.as_deref(),
        args.resume.as_deref(),
        &sets,
        &args.out,
    )?;
    let last = s.last.as_ref();
    println!(
        "run {} finished: {} updates (resumed from {}) on {} histories ({} held out); last train loss {}, val loss {}",
        s.run_dir.display(),
        s.updates,
        s.resumed_from,
        s.train_histories,
        s.val_histories,
        last.map_or("-".into(), |m| format!("{:.4}", m.train_loss)),
        last.and_then(|m| m.val_loss)
            .map_or("-".into(), |v| format!("{v:.4}"))
    );
    Ok(())
}

/// `pretrain`: a new run, a resumed one, or a fork; a fork whose start is
/// refused before it trained is removed (it holds nothing the user made).
fn pretrain(mut args: PretrainArgs) -> anyhow::Result<()> {
    let forked = match (&args.fork, &args.resume) {
        (Some(root), Some(from)) => {
            let mut sets = std::mem::take(&mut args.set);
            if let Some(seed) = args.seed.take() {
                sets.push(format!("seed={seed}"));
            }
            if args.method == "eppo"
                && let Some(device) = args.device.take()
            {
                sets.push(format!("device=\"{device}\""));
            }
            let forked = icrl::cli::pretrain::fork(&args.env, &args.method, from, &sets, root)?;
            args.resume = Some(forked.run.path.clone());
            Some(forked)
        }
        _ => None,
    };
    match (train_or_resume(args), forked) {
        (Err(e), Some(forked)) if interrupted(&e).is_none() && forked.remove_if_untrained() => {
            Err(anyhow::anyhow!(
                "{}; the fork {} was removed: nothing was trained in it",
                report(&e),
                forked.run.path.display()
            ))
        }
        (result, _) => result,
    }
}

/// The rest of `pretrain`: `--resume-in-out`, then EPPO or AD.
fn train_or_resume(mut args: PretrainArgs) -> anyhow::Result<()> {
    if args.resume_in_out {
        use icrl::cli::pretrain::{InOut, run_in_out};
        match run_in_out(&args.out, &args.env, &args.method, &args.set)? {
            InOut::Start => {}
            InOut::Resume(run) => {
                eprintln!("--resume-in-out: resuming {}", run.display());
                args.resume = Some(run);
            }
            InOut::Finished { run, updates } => {
                println!(
                    "run {} finished: {updates} updates, as its config asks; nothing to do",
                    run.display()
                );
                return Ok(());
            }
        }
    }
    if args.method == "ad" {
        return pretrain_ad(args);
    }
    if let Some(d) = &args.dataset {
        anyhow::bail!(
            "--dataset {} is for --method ad: EPPO collects its own experience (leave out --dataset, \
             or add --method ad)",
            d.display()
        );
    }
    let mut sets = args.set;
    if let Some(seed) = args.seed {
        sets.push(format!("seed={seed}"));
    }
    if let Some(device) = &args.device {
        sets.push(format!("device=\"{device}\""));
    }
    let report = icrl::cli::pretrain::eppo(
        &args.env,
        &args.preset,
        args.resume.as_deref(),
        &sets,
        &args.out,
    )?;
    println!(
        "run {} finished: {} updates, {} env steps, {}",
        report.run_dir.display(),
        report.updates,
        report.env_steps,
        report.penalty,
    );
    print_learning_summary(&args.env, &report)?;
    Ok(())
}

/// Whether the run learned, in numbers: episodic return and cost early and
/// late in the run against a random policy on the same task distribution,
/// then the checkpoint and the command that evaluates it.
fn print_learning_summary(env: &str, report: &icrl::eppo::PretrainReport) -> anyhow::Result<()> {
    use icrl::run_summary::{eval_command, metrics_trend};
    let env: safety_envs::EnvName = env.parse()?;
    let random = report.random;
    match metrics_trend(&report.run_dir.join("metrics.jsonl"), 0.1) {
        Some(t) => println!(
            "learning ({} collection rounds): episodic return {:.3} in the first 10% -> {} in the last 10% \
             (random policy: {:.3}); episodic cost {:.2} -> {:.2} (random policy: {:.2}){}",
            t.rounds,
            t.first.episodic_return,
            icrl::run_summary::mean_with_error(t.last.episodic_return, t.last_return_se),
            random.episodic_return,
            t.first.episodic_cost,
            t.last.episodic_cost,
            random.episodic_cost,
            if t.beats(random) {
                ": it learns, its return is above the random policy's by more than 2 standard errors"
            } else {
                ": its return is not clearly above the random policy's yet"
            }
        ),
        None => println!(
            "learning: no episode finished during the run (random policy: return {:.3}, cost {:.2})",
            random.episodic_return, random.episodic_cost
        ),
    }
    // The check is a summary: a failure is reported, the run stays done.
    match icrl::cli::in_context::check(&report.last_checkpoint, env) {
        Ok(table) => print!("{table}"),
        Err(e) => eprintln!("warning: the in-context check did not run: {e}"),
    }
    println!("checkpoint: {}", report.last_checkpoint.display());
    println!(
        "evaluate it with:\n  {}",
        eval_command(env, &report.last_checkpoint)
    );
    Ok(())
}

/// The checkpoint and update count of a run stopped by SIGINT/SIGTERM.
fn interrupted(e: &anyhow::Error) -> Option<(PathBuf, usize)> {
    match e.downcast_ref::<icrl::eppo::EppoError>() {
        Some(icrl::eppo::EppoError::Interrupted {
            checkpoint,
            updates,
        }) => Some((checkpoint.clone(), *updates as usize)),
        _ => match e.downcast_ref::<icrl::ad::AdError>() {
            Some(icrl::ad::AdError::Interrupted {
                checkpoint,
                updates,
            }) => Some((checkpoint.clone(), *updates)),
            _ => None,
        },
    }
}

/// `pretrain` with the graceful stop: the first SIGINT/SIGTERM ends training
/// after the current update with a checkpoint and the resume command (exit
/// 130); a second exits at once.
fn pretrain_with_stop(args: PretrainArgs) -> ExitCode {
    if let Err(e) = icrl::stop::install() {
        eprintln!("warning: {e}; Ctrl-C will stop without a checkpoint");
    }
    let (env, method) = (args.env.clone(), args.method.clone());
    let result = pretrain(args);
    let stopped = result.as_ref().err().and_then(interrupted);
    match (result, stopped) {
        (Ok(()), _) => ExitCode::SUCCESS,
        (Err(_), Some((checkpoint, updates))) => {
            eprintln!(
                "stopped after update {updates}; checkpoint {}\nresume with: {}",
                checkpoint.display(),
                icrl::run_summary::resume_command(
                    &env,
                    &method,
                    &checkpoint,
                    std::env::var_os(icrl::run_summary::VIA_XTASK_ENV).is_some()
                )
            );
            ExitCode::from(icrl::stop::EXIT_INTERRUPTED)
        }
        (Err(e), None) => {
            eprintln!("error: {}", report(&e));
            // A run stopped by a failed write (a full disk) continues from
            // its last good checkpoint once there is room.
            if let Some(checkpoint) = last_good(&e) {
                eprintln!(
                    "resume with: {}",
                    icrl::run_summary::resume_command(
                        &env,
                        &method,
                        checkpoint,
                        std::env::var_os(icrl::run_summary::VIA_XTASK_ENV).is_some()
                    )
                );
            }
            ExitCode::FAILURE
        }
    }
}

/// The last good checkpoint of a run stopped by a failed write.
fn last_good(e: &anyhow::Error) -> Option<&std::path::Path> {
    let checkpoint = match (
        e.downcast_ref::<icrl::eppo::EppoError>(),
        e.downcast_ref::<icrl::ad::AdError>(),
    ) {
        (Some(icrl::eppo::EppoError::Checkpoint(c)), _) => c,
        (_, Some(icrl::ad::AdError::Checkpoint(c))) => c,
        _ => e.downcast_ref::<icrl::checkpoint::CheckpointError>()?,
    };
    checkpoint.last_good_checkpoint()
}

/// An error with its causes, each said once: a cause whose words the
/// message already holds (an OS error the message quotes) is not repeated
/// (`No space left on device (os error 28): No space left on device (os
/// error 28)`).
fn report(e: &anyhow::Error) -> String {
    let mut text = e.to_string();
    for cause in e.chain().skip(1) {
        let cause = cause.to_string();
        if !text.contains(&cause) {
            text = format!("{text}: {cause}");
        }
    }
    text
}

fn main() -> ExitCode {
    // A closed stdout (`icrl pretrain ... | head -n 1`) ends the process
    // quietly, as it ends any Unix filter, not with a panic in `println!`:
    // what the output reports (checkpoints, datasets) is on disk before it.
    // SAFETY: at the start of main, before any other thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Pretrain(args) => return pretrain_with_stop(args),
        // An AD run folder has spec.json; EPPO's has a manifest.
        Command::PlotTraining { run, .. } if run.join("spec.json").exists() => {
            icrl::plots::training::plot_training(&run)
                .map(|fs| fs.iter().for_each(|f| println!("wrote {}", f.display())))
                .map_err(Into::into)
        }
        Command::PlotTraining { run, window } => {
            icrl::plots::training::plot_learning_curve(&run, window)
                .map(|f| println!("wrote {}", f.display()))
                .map_err(Into::into)
        }
        Command::PlotHistories {
            file,
            out,
            bins,
            force,
        } => {
            let existing = safety_envs::output::Existing::from_force(force);
            icrl::plots::training::plot_histories(&file, &out, bins as usize, existing)
                .map(|fs| fs.iter().for_each(|f| println!("wrote {}", f.display())))
                .map_err(Into::into)
        }
        Command::Dataset(args) => dataset(args),
        Command::Eval(args) => icrl_eval::eval(args),
        Command::Sweep(args) => match sweep(args) {
            Ok(code) => return code,
            Err(e) => Err(e),
        },
        Command::DropReplay { paths } => drop_replay(&paths),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", report(&e));
            ExitCode::FAILURE
        }
    }
}
