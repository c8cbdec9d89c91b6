//! Safe in-context reinforcement learning on top of libtorch.
//!
//! - [`agent`]: the interface a pretrained in-context agent offers (reset, act).
//! - [`eval`]: in-context evaluation on held-out edge-oriented tasks, budget sweeps.
//! - [`eval_cmd`]: the `eval` command (checkpoints in, JSON/CSV/figures/GIF out).
//! - [`eval_load`]: loading EPPO and AD checkpoints for evaluation.
//! - [`plots`]: the paper's evaluation figures and a SafeDarkRoom animation.
//! - [`stats`]: mean and standard error.
//! - [`task_seeds`]: the split of task seeds between pretraining and evaluation.
//! - [`checkpoint`]: run folders, atomic checkpoints with manifests, metrics (JSONL).
//! - [`eppo`]: EPPO, safe reinforcement pretraining (Algorithm 1), and its frozen agent.
//! - [`optim`]: Adam whose moments can be checkpointed.
//! - [`presets`]: built-in TOML presets and `--set key=value` overrides.
//! - [`model`]: the one causal transformer (with KV cache) every learner shares.
//! - [`histories`]: learning histories in HDF5 (DSRL-compatible layout).
//! - [`ppo_lagrangian`]: PPO-Lagrangian, the learner whose histories supervised pretraining distils.
//! - [`dataset`]: learning-history datasets (PPO-Lagrangian or noisy optimal) written to HDF5.
//! - [`ad`]: safe supervised pretraining (algorithm distillation with RTG and CTG).

pub mod agent;
pub mod checkpoint;
pub mod eppo;
pub mod eval;
pub mod eval_cmd;
pub mod eval_load;
pub mod plots;
pub mod stats;
pub mod task_seeds;
pub mod model;
pub mod optim;
pub mod presets;
pub mod histories;
pub mod ppo_lagrangian;
pub mod dataset;
pub mod ad;

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
