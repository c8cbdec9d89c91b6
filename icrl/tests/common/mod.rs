//! What several integration tests share: the arguments of a tiny
//! SafeDarkRoom EPPO run, running the binary, a fresh folder.

// Each test crate compiles this module and uses a part of it.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Runs the `icrl` binary with `args` to its end.
pub fn icrl(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_icrl"))
        .args(args)
        .output()
        .expect("run icrl")
}

/// An empty folder `icrl-{name}-{pid}` in the temporary directory, made anew.
pub fn fresh_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("icrl-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The `--set`s of a tiny EPPO run: trajectories of 2 episodes of 6 steps
/// from 2 environments, a 1-layer transformer of width 16, 2 updates and one
/// checkpoint, on one thread. A later `--set` of the same name wins.
pub const TINY_EPPO_SETS: [&str; 19] = [
    "max_episode_steps=6",
    "k_min=2",
    "k_max=2",
    "n_envs=2",
    "batch_size=2",
    "replay_capacity=1000",
    "encoder_hidden=16",
    "head_hidden=16",
    "model.d_model=16",
    "model.n_heads=2",
    "model.n_layers=1",
    "model.d_ff=32",
    "model.max_len=12",
    "total_updates=2",
    "updates_per_round=2",
    "learning_starts=0",
    "checkpoint_every=2",
    "torch_threads=1",
    "env_threads=1",
];

/// `sets` as `--set` arguments.
pub fn set_args<'a>(sets: impl IntoIterator<Item = &'a str>) -> Vec<String> {
    sets.into_iter()
        .flat_map(|set| ["--set".to_string(), set.to_string()])
        .collect()
}

/// The arguments of a tiny darkroom EPPO run ([`TINY_EPPO_SETS`]) into
/// `out`, pretrained on budgets [2, 4].
pub fn tiny_eppo_args(out: &Path) -> Vec<String> {
    let mut args: Vec<String> = ["pretrain", "--env", "darkroom", "--out"]
        .map(String::from)
        .to_vec();
    args.push(out.display().to_string());
    args.extend(set_args(
        TINY_EPPO_SETS.into_iter().chain(["ctg_min=2", "ctg_max=4"]),
    ));
    args
}
