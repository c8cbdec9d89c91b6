//! The commands that set up and then hand over to cargo. Arguments after the
//! command name pass through verbatim, so the delegated binary's own parser
//! (clap) reports bad flags.

use std::env;
use std::fs;
use std::path::Path;
use std::process::{Command, ExitCode, ExitStatus};

use anyhow::{Context, Result};

use crate::BenchTarget;
use crate::setup::{python_venv, repo_root, setup};

/// `cargo xtask test`: `cargo test --workspace ARGS`, then the Python
/// package's tests ([`python_tests`]); or only `cargo test ARGS` when ARGS
/// pick packages (`-p`), since `--workspace` would override them.
pub fn test(args: &[String]) -> Result<ExitCode> {
    setup()?;
    let cargo_args = args.iter().take_while(|a| a.as_str() != "--");
    let picks_packages = cargo_args
        .map(String::as_str)
        .any(|a| a == "-p" || a.starts_with("--package") || (a.starts_with("-p") && a.len() > 2));
    if picks_packages {
        return cargo(&["test"], args);
    }
    let code = cargo(&["test", "--workspace"], args)?;
    if code != ExitCode::SUCCESS {
        return Ok(code);
    }
    python_tests()
}

/// The Python package (`safety-envs/python`): built into the set-up's virtual
/// environment with `maturin develop` (the dev profile, sharing `target/`
/// with the cargo tests), then its pytest suite.
fn python_tests() -> Result<ExitCode> {
    let root = repo_root();
    let venv = python_venv(root);
    let bin = venv.join("bin");
    let path = env::join_paths(
        std::iter::once(bin.clone())
            .chain(env::split_paths(&env::var_os("PATH").unwrap_or_default())),
    )?;
    let package = root.join("safety-envs").join("python");
    let steps: [(&str, Command); 2] = [
        ("maturin develop (safety-envs/python)", {
            let mut c = Command::new(bin.join("maturin"));
            c.args(["develop", "--quiet"]).current_dir(&package);
            c
        }),
        ("pytest safety-envs/python/tests", {
            let mut c = Command::new(bin.join("python"));
            c.args(["-m", "pytest", "-q", "tests"])
                .current_dir(&package);
            c
        }),
    ];
    for (what, mut command) in steps {
        println!("xtask: {what}");
        let status = command
            .env("VIRTUAL_ENV", &venv)
            .env("PATH", &path)
            .status()
            .with_context(|| format!("could not start {what}"))?;
        if !status.success() {
            return Ok(exit_code(status));
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `cargo xtask test --slurm`: builds `icrl`, then runs `tests/slurm/run.sh`
/// with it: a one-node Slurm cluster on this machine (installed when
/// missing) running a sweep's job array and a sharded dataset with its merge.
pub fn test_slurm() -> Result<ExitCode> {
    setup()?;
    let code = cargo(&["build", "-p", "icrl", "--bin", "icrl"], &[])?;
    if code != ExitCode::SUCCESS {
        return Ok(code);
    }
    let root = repo_root();
    let script = root.join("tests").join("slurm").join("run.sh");
    let icrl = root.join("target").join("debug").join("icrl");
    println!("xtask: {} --install {}", script.display(), icrl.display());
    let status = Command::new(&script)
        .arg("--install")
        .arg(&icrl)
        .status()
        .with_context(|| format!("could not start {}", script.display()))?;
    Ok(exit_code(status))
}

/// The main job, run by `cargo xtask pretrain` without arguments.
const DEFAULT_PRETRAIN: [&str; 2] = ["--env", "car"];

/// `cargo xtask pretrain|dataset|eval`: `icrl <subcommand> ARGS` in release;
/// `pretrain` without arguments runs the main job ([`DEFAULT_PRETRAIN`]).
pub fn icrl(subcommand: &str, args: &[String]) -> Result<ExitCode> {
    setup()?;
    if !has_bin(repo_root(), "icrl", "icrl") {
        return not_built_yet(subcommand, "icrl/src/bin/icrl.rs");
    }
    let default: Vec<String> = DEFAULT_PRETRAIN.map(String::from).to_vec();
    let args = if subcommand == "pretrain" && args.is_empty() {
        &default
    } else {
        args
    };
    let leading = [
        "run",
        "--release",
        "-p",
        "icrl",
        "--bin",
        "icrl",
        "--",
        subcommand,
    ];
    // icrl prints its resume line as a `cargo xtask` command when set. Only
    // here: the tests that `cargo xtask test` runs check the `icrl` form.
    cargo_with_env(&leading, args, &[("ICRL_VIA_XTASK", "1")])
}

/// `cargo xtask render`: safety-envs' `render` binary in release.
pub fn render(args: &[String]) -> Result<ExitCode> {
    setup()?;
    if !has_bin(repo_root(), "safety-envs", "render") {
        return not_built_yet("render", "safety-envs/src/bin/render.rs");
    }
    cargo(
        &[
            "run",
            "--release",
            "-p",
            "safety-envs",
            "--bin",
            "render",
            "--",
        ],
        args,
    )
}

/// `cargo xtask bench`: `cargo bench` on the environments, the model, or both.
pub fn bench(target: BenchTarget, args: &[String]) -> Result<ExitCode> {
    setup()?;
    let packages: &[&str] = match target {
        BenchTarget::Envs => &["safety-envs"],
        BenchTarget::Model => &["icrl"],
        BenchTarget::All => &["safety-envs", "icrl"],
    };
    for package in packages {
        let code = cargo(&["bench", "-p", package], args)?;
        if code != ExitCode::SUCCESS {
            return Ok(code);
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Whether `package` (a folder under `root`) has a binary target named `bin`:
/// `src/bin/<bin>.rs`, `src/bin/<bin>/main.rs`, or a `[[bin]]` entry in its
/// manifest.
fn has_bin(root: &Path, package: &str, bin: &str) -> bool {
    let dir = root.join(package);
    let manifest = fs::read_to_string(dir.join("Cargo.toml")).unwrap_or_default();
    dir.join(format!("src/bin/{bin}.rs")).is_file()
        || dir.join(format!("src/bin/{bin}/main.rs")).is_file()
        || (manifest.contains("[[bin]]") && manifest.contains(&format!("name = \"{bin}\"")))
}

/// Used while a delegated binary does not exist yet: builds everything that
/// does exist (so the set-up is complete and proven to link), then says
/// plainly what is missing.
fn not_built_yet(command: &str, source: &str) -> Result<ExitCode> {
    println!("xtask: building what exists (cargo build --release --workspace)");
    let code = cargo(&["build", "--release", "--workspace"], &[])?;
    if code != ExitCode::SUCCESS {
        return Ok(code);
    }
    println!(
        "xtask: `{command}` is not built yet: this checkout has no {source}. \
         Everything it needs is installed and the workspace builds; \
         `cargo xtask test` runs the tests of what exists."
    );
    Ok(ExitCode::SUCCESS)
}

/// Runs the cargo that runs us (or `cargo` from PATH) with `leading` then
/// `args`, and returns its exit code. It runs in the caller's folder, so
/// relative paths in `args` (`--out`, `--scene`) mean what the user typed.
fn cargo(leading: &[&str], args: &[String]) -> Result<ExitCode> {
    cargo_with_env(leading, args, &[])
}

/// [`cargo`] with `vars` added to the child's environment.
fn cargo_with_env(leading: &[&str], args: &[String], vars: &[(&str, &str)]) -> Result<ExitCode> {
    let cargo = env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    println!("xtask: cargo {}", shell_words(leading, args));
    let status = Command::new(&cargo)
        .args(leading)
        .args(args)
        .envs(vars.iter().copied())
        .status()
        .with_context(|| format!("could not start {}", Path::new(&cargo).display()))?;
    Ok(exit_code(status))
}

/// The command line as one string, for the progress line.
fn shell_words(leading: &[&str], args: &[String]) -> String {
    leading
        .iter()
        .copied()
        .chain(args.iter().map(String::as_str))
        .collect::<Vec<_>>()
        .join(" ")
}

/// A child's exit status as our exit code: its own code, or 128 + the signal
/// that killed it (as shells report it).
fn exit_code(status: ExitStatus) -> ExitCode {
    use std::os::unix::process::ExitStatusExt;
    let code = status
        .code()
        .unwrap_or_else(|| 128 + status.signal().unwrap_or(0));
    ExitCode::from(u8::try_from(code).unwrap_or(1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exit_codes_are_forwarded() {
        let status = Command::new("sh").args(["-c", "exit 3"]).status().unwrap();
        assert_eq!(exit_code(status), ExitCode::from(3));
        let status = Command::new("sh")
            .args(["-c", "kill -9 $$"])
            .status()
            .unwrap();
        assert_eq!(exit_code(status), ExitCode::from(137));
    }

    #[test]
    fn finds_binaries_by_file_or_manifest() {
        let root = repo_root()
            .join("target")
            .join("xtask-tests")
            .join(format!("bins-{}", std::process::id()));
        let bin_dir = root.join("by-file").join("src").join("bin");
        fs::create_dir_all(&bin_dir).unwrap();
        fs::write(bin_dir.join("tool.rs"), "fn main() {}").unwrap();
        fs::create_dir_all(root.join("by-manifest")).unwrap();
        fs::write(
            root.join("by-manifest").join("Cargo.toml"),
            "[[bin]]\nname = \"tool\"\npath = \"src/tool.rs\"\n",
        )
        .unwrap();

        assert!(has_bin(&root, "by-file", "tool"));
        assert!(has_bin(&root, "by-manifest", "tool"));
        assert!(!has_bin(&root, "by-file", "other"));
        assert!(!has_bin(&root, "by-manifest", "other"));
        assert!(!has_bin(&root, "no-such-package", "tool"));
        fs::remove_dir_all(&root).unwrap();
    }
}
