//! Safe in-context reinforcement learning on top of libtorch.
//!
//! Shared parts:
//! - [`agent`]: the interface a pretrained in-context agent offers (reset, act).
//! - [`model`]: the one causal transformer (with KV cache) every learner shares.
//! - [`optim`]: Adam whose moments can be checkpointed.
//! - [`checkpoint`]: run folders, atomic checkpoints with manifests, metrics (JSONL).
//! - [`json_bounds`]: space bounds (possibly infinite) in checkpoint JSON.
//! - [`presets`]: built-in TOML presets and `--set key=value` overrides.
//! - [`task_seeds`]: the split of task seeds between pretraining and evaluation.
//! - [`tokens`]: the time-step token both learners feed the transformer.
//! - [`guard`]: setting ranges, finite-weight checks and the memory estimate.
//! - [`stop`]: graceful stop on the first SIGINT/SIGTERM.
//! - [`torch_rng`]: the lock on libtorch's process-wide generator.
//!
//! Learners (each a folder whose `mod.rs` reads top to bottom):
//! - [`eppo`]: EPPO, safe reinforcement pretraining (Algorithm 1), and its frozen agent.
//! - [`ppo_lagrangian`]: PPO-Lagrangian, the learner whose histories supervised pretraining distils.
//! - [`ad`]: safe supervised pretraining (algorithm distillation with RTG and CTG).
//!
//! Data and evaluation:
//! - [`data`]: learning histories in HDF5 ([`data::histories`]) and the
//!   datasets made of them ([`data::dataset`]).
//! - [`eval`]: in-context evaluation on held-out edge-oriented tasks, budget
//!   sweeps, and the `eval` command ([`eval::command`], [`eval::load`]).
//! - [`plots`]: the paper's evaluation figures and animations.
//! - [`run_summary`]: a finished run's learning trend against a random policy, and its eval command.
//! - [`stats`]: mean and standard error.

pub mod ad;
pub mod agent;
pub mod checkpoint;
pub mod cli;
pub mod data;
pub mod eppo;
pub mod eval;
pub mod guard;
pub mod json_bounds;
pub mod model;
pub mod optim;
pub mod plots;
pub mod ppo_lagrangian;
pub mod presets;
pub mod report;
pub mod run_summary;
pub mod signals;
pub mod stats;
pub mod stop;
pub mod task_seeds;
pub mod tokens;
pub mod torch_rng;

#[cfg(test)]
mod reliability_tests;

#[cfg(test)]
mod tests {
    use tch::{Kind, Tensor};

    #[test]
    fn libtorch_links_and_backpropagates() {
        let x = Tensor::from_slice(&[1.0f32, 2.0, 3.0]).set_requires_grad(true);
        let y = (&x * &x).sum(Kind::Float);
        y.backward();
        let grad: Vec<f32> = x.grad().try_into().unwrap();
        assert_eq!(grad, vec![2.0, 4.0, 6.0]);
    }
}
