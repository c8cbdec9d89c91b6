//! The project's entry points, run as `cargo xtask <command>` (an alias in
//! `.cargo/config.toml`).
//!
//! `xtask` is deliberately light (clap, anyhow and std only) so that it
//! compiles on a bare machine before libtorch or MuJoCo exist. Every command
//! first runs [`setup::setup`], which installs whatever is missing, and then
//! hands over to cargo: the real argument parsing lives in the binaries it
//! delegates to (`icrl`, `render`), so their flags pass through verbatim.

mod delegate;
mod setup;

use std::process::ExitCode;

use clap::{Parser, Subcommand, ValueEnum};

/// Set-up, training, evaluation, rendering, benchmarks and tests for safe
/// in-context RL.
#[derive(Parser)]
#[command(name = "cargo xtask", bin_name = "cargo xtask", version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Install what is missing: Debian packages (MuJoCo 2.2, OSMesa, libclang,
    /// HDF5), libtorch 2.11.0 into `.libtorch/`, Python's h5py, and the Python
    /// package's test environment (`target/python-venv`).
    Setup,
    /// Set up, then run `cargo test --workspace [ARGS...]`, then build the
    /// Python package and run its pytest suite (not when ARGS pick packages).
    Test {
        /// Instead: install Slurm (slurm-wlm, munge) when missing, start a one-node
        /// cluster on this machine, and run a sweep and a sharded dataset through it
        /// (tests/slurm/run.sh; as root, a few minutes).
        #[arg(long)]
        slurm: bool,
        /// Passed to `cargo test` verbatim (e.g. `-p safety-envs -- --nocapture`).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Set up, then pretrain a policy: `icrl pretrain [ARGS...]` (e.g. `--env car`).
    #[command(disable_help_flag = true)]
    Pretrain {
        /// Passed to `icrl pretrain` verbatim; `--help` lists them.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Set up, then collect learning histories: `icrl dataset [ARGS...]`.
    #[command(disable_help_flag = true)]
    Dataset {
        /// Passed to `icrl dataset` verbatim; `--help` lists them.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Set up, then evaluate pretrained policies: `icrl eval [ARGS...]`.
    #[command(disable_help_flag = true)]
    Eval {
        /// Passed to `icrl eval` verbatim; `--help` lists them.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Set up, then train a grid of seeds and settings here or as a Slurm array, and gather
    /// its table: `icrl sweep [ARGS...]` (e.g. `--grid results/final/darkroom.toml --run`).
    #[command(disable_help_flag = true)]
    Sweep {
        /// Passed to `icrl sweep` verbatim; `--help` lists them.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Set up, then render a scene or environment off-screen to PNG:
    /// `render [ARGS...]` (e.g. `--scene FILE.xml --out frame.png`).
    #[command(disable_help_flag = true)]
    Render {
        /// Passed to `render` verbatim; `--help` lists them.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Set up, then run the benchmarks (`cargo bench` on safety-envs, icrl or both).
    Bench {
        /// Which benchmarks: the environments, the model, or all.
        #[arg(value_enum, default_value_t = BenchTarget::All)]
        target: BenchTarget,
        /// Passed to `cargo bench` verbatim.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
}

/// The benchmark suites `cargo xtask bench` can run.
#[derive(Clone, Copy, ValueEnum)]
enum BenchTarget {
    /// Environment stepping and rendering (`cargo bench -p safety-envs`).
    Envs,
    /// The transformer policy (`cargo bench -p icrl`).
    Model,
    /// Both suites, environments first.
    All,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Setup => setup::setup().map(|()| ExitCode::SUCCESS),
        Command::Test { slurm: true, .. } => delegate::test_slurm(),
        Command::Test { args, .. } => delegate::test(&args),
        Command::Pretrain { args } => delegate::icrl("pretrain", &args),
        Command::Dataset { args } => delegate::icrl("dataset", &args),
        Command::Eval { args } => delegate::icrl("eval", &args),
        Command::Sweep { args } => delegate::icrl("sweep", &args),
        Command::Render { args } => delegate::render(&args),
        Command::Bench { target, args } => delegate::bench(target, &args),
    };
    result.unwrap_or_else(|err| {
        eprintln!("xtask: error: {err:#}");
        ExitCode::FAILURE
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Command {
        let argv = std::iter::once("xtask").chain(args.iter().copied());
        Cli::try_parse_from(argv).unwrap().command
    }

    #[test]
    fn delegated_arguments_pass_through_verbatim() {
        let Command::Pretrain { args } = parse(&["pretrain", "--env", "car", "--help", "-x"])
        else {
            panic!("not parsed as pretrain");
        };
        assert_eq!(args, ["--env", "car", "--help", "-x"]);

        let Command::Sweep { args } = parse(&["sweep", "--grid", "g.toml", "--run"]) else {
            panic!("not parsed as sweep");
        };
        assert_eq!(args, ["--grid", "g.toml", "--run"]);

        let Command::Test { args, slurm } = parse(&["test", "-p", "icrl", "--", "--nocapture"])
        else {
            panic!("not parsed as test");
        };
        assert_eq!(args, ["-p", "icrl", "--", "--nocapture"]);
        assert!(!slurm);
        assert!(matches!(
            parse(&["test", "--slurm"]),
            Command::Test { slurm: true, .. }
        ));
    }

    #[test]
    fn bench_defaults_to_all() {
        assert!(matches!(
            parse(&["bench"]),
            Command::Bench {
                target: BenchTarget::All,
                ..
            }
        ));
        assert!(matches!(
            parse(&["bench", "model"]),
            Command::Bench {
                target: BenchTarget::Model,
                ..
            }
        ));
    }
}
