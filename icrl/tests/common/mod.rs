//! What several integration tests share: the arguments of a tiny
//! SafeDarkRoom EPPO run.

use std::path::Path;

/// The arguments of a tiny darkroom EPPO run (2 updates, a 1-layer
/// transformer of width 16) into `out`, pretrained on budgets [2, 4].
pub fn tiny_eppo_args(out: &Path) -> Vec<String> {
    let mut args: Vec<String> = ["pretrain", "--env", "darkroom", "--out"]
        .map(String::from)
        .to_vec();
    args.push(out.display().to_string());
    for set in [
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
        "ctg_min=2",
        "ctg_max=4",
    ] {
        args.extend(["--set".to_string(), set.to_string()]);
    }
    args
}
