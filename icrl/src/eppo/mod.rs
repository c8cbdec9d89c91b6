//! EPPO: safe reinforcement pretraining (the paper's Algorithm 1), read top to
//! bottom: configuration, networks, collection, the update, `train`, and the
//! frozen [`EppoAgent`] that evaluation drives.
//!
//! Off-policy actor-critic after AMAGO: a time-step MLP encodes each
//! (s_t, a_{t-1}, r_t, c_t, CTG_t, episode-start) tuple; the shared causal
//! transformer reads the whole multi-episode trajectory; heads give the actor,
//! a reward critic Q and a cost critic Qc (one value per action for discrete
//! actions). Losses per step (SPEC section 3):
//! - Lv = (Q(h_t, a_t) - [r_{t+1} + gamma Q'(h_{t+1}, a')])^2
//! - Lc = (Qc(h_t, a_t) - [c_{t+1} + gamma Qc'(h_{t+1}, a')])^2
//! - Lp = -Q(h_t, a_hat) + lambda v_e Qc(h_t, a_hat), v_e = 1 when episode e's
//!   cost exceeded the trajectory's budget delta.
//!
//! Deviations from Algorithm 1, each for a measured reason (results/eppo_ladder):
//! - Each token also carries the observation the previous action arrived at,
//!   so the goal, where the auto-reset replaces the final observation, enters
//!   the context with its reward ([`crate::tokens`]).
//! - The reward critic bootstraps across episode boundaries (the meta-RL
//!   objective is the sum of the K returns); the cost critic never does, since
//!   the budget binds each episode alone (Eq. 6): a violation charges only its
//!   own episode.
//! - Q and the tokens see rewards x `reward_scale`; lambda is in reward units
//!   (the penalty is lambda x reward_scale x Qc), so lambda = 1 prices one unit
//!   of cost like one goal whatever the scale.
//! - Exploration is AMAGO's bilevel epsilon-greedy: annealed over training,
//!   decaying inside each trajectory, scaled per trajectory by a uniform draw.
//!
//! The multiplier follows Eq. (7): lambda <- clip(lambda + eta * mean over the
//! sampled trajectories of max_k (C_k - delta), 0, lambda_max).
//!
//! Metrics (`metrics.jsonl`, one record per collection round, against
//! `env_steps`): `episodic_return`, `episodic_cost` (means over the episodes
//! collected in the round), `first_episode_return`, `last_episode_return`,
//! `first_episode_cost`, `last_episode_cost` (per trajectory, averaged: the
//! in-context signal), `discovery_rate` and `revisit_rate` (P(goal at episode
//! k > 1 | not found / found earlier in the trajectory)), `found_goal`
//! (fraction of trajectories that found it), `lambda`, `losses/value_loss`, `losses/cost_value_loss`,
//! `losses/policy_loss`, `losses/entropy`, `losses/grad_norm`, `charts/epsilon`,
//! `charts/updates_per_s`, `charts/env_steps_per_s`. Losses are averaged over
//! the round's updates and are `null` in rounds without an update (before
//! `learning_starts`).

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor, nn, nn::Module};
use thiserror::Error;

use safety_envs::{
    EnvError, EnvName, EnvOptions, Orientation, Space, VecAction, VecEnv, make_env, sample_task,
    spawn_config,
};

use crate::agent::{Actions, AgentError, Conditioning, InContextAgent, StepInput};
use crate::checkpoint::{CheckpointError, MetricsWriter, RunDir, read_manifest};
use crate::model::{self, KvCache, ModelError, Transformer};
use crate::optim::{Adam, AdamConfig};
use crate::task_seeds::{PretrainTasks, pretrain_task_seed};
use crate::tokens::{self, StepToken};

// ---------------------------------------------------------------------------
// Configuration
// ---------------------------------------------------------------------------

/// Every EPPO hyperparameter (presets in `icrl/presets/eppo-*.toml`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EppoConfig {
    /// Seed of every random choice (tasks, budgets, actions, libtorch).
    pub seed: u64,
    /// `cpu` or `cuda` (CUDA device 0).
    pub device: String,
    /// libtorch intra-op threads; 0 keeps libtorch's default (one per core).
    /// 1 is fastest for small-batch acting on a loaded machine, where OpenMP
    /// barriers between oversubscribed threads dominate each tiny operation.
    #[serde(default)]
    pub torch_threads: i32,
    /// Environment time limit t_max in agent steps.
    pub max_episode_steps: usize,
    /// Fewest episodes per trajectory (K_min).
    pub k_min: usize,
    /// Most episodes per trajectory (K_max).
    pub k_max: usize,
    /// Smallest sampled per-episode cost budget (CTG_min).
    pub ctg_min: f32,
    /// Largest sampled per-episode cost budget (CTG_max); also scales CTG in the tokens.
    pub ctg_max: f32,
    /// Trajectories collected at once (one environment each, acted in one batch).
    pub n_envs: usize,
    /// Threads stepping the environments.
    pub env_threads: usize,
    /// Replay capacity in environment steps (whole trajectories are evicted, oldest first).
    pub replay_capacity: usize,
    /// The shared transformer; `max_len` is the sequence length.
    pub model: model::Config,
    /// Hidden width of the time-step encoder MLP.
    pub encoder_hidden: i64,
    /// Hidden width of the actor and critic heads.
    pub head_hidden: i64,
    /// Critics per ensemble (reward target: minimum over them; cost target: mean).
    pub n_critics: i64,
    /// Discount factor gamma.
    pub gamma: f64,
    /// Value targets bootstrap across episode boundaries inside a trajectory
    /// (AMAGO's meta-RL view: the objective is the sum of all K returns).
    pub bootstrap_across_episodes: bool,
    /// Polyak factor of the target networks (target <- (1 - tau) target + tau online).
    pub tau: f64,
    /// Steps of real rewards in each TD target before bootstrapping (n-step
    /// returns, each step's sum stopping where its bootstrap mask stops):
    /// with sparse rewards and gamma near 1 a one-step target moves value
    /// (and corrects stale optimism) one step per target-network lag;
    /// n steps move it n times faster. 1: the paper's one-step target.
    #[serde(default = "default_n_step")]
    pub n_step: usize,
    /// Adam learning rate.
    pub lr: f64,
    /// Adam beta1.
    pub beta1: f64,
    /// Adam beta2.
    pub beta2: f64,
    /// Adam epsilon.
    pub adam_eps: f64,
    /// Global gradient-norm clip.
    pub grad_clip: f64,
    /// Trajectories per update batch (N).
    pub batch_size: usize,
    /// Updates to run in total.
    pub total_updates: u64,
    /// Updates after each collection round.
    pub updates_per_round: u64,
    /// Environment steps collected before the first update.
    pub learning_starts: u64,
    /// Multiplier step size eta of Eq. (7).
    pub lambda_lr: f64,
    /// Cap lambda_max of the multiplier (Appendix C).
    pub lambda_max: f64,
    /// Initial multiplier.
    pub lambda_init: f64,
    /// Updates before Eq. (7) starts moving lambda (it stays at `lambda_init`):
    /// the agent first learns to search and return to the goal, then the
    /// constraint prices its costs (a multiplier at its cap from the start
    /// stops search before it is learned; results/eppo_ladder).
    #[serde(default)]
    pub lambda_warmup_updates: u64,
    /// Weight of the critic losses against the actor loss.
    pub critic_weight: f64,
    /// Entropy bonus weight in the actor loss.
    pub entropy_coef: f64,
    /// Weight of AMAGO's filtered behaviour cloning in the actor loss:
    /// -1[A(h_t, a_t) > 0] log pi(a_t | h_t) on the replayed actions, with
    /// A = Q(h_t, a_t) - E_pi Q(h_t, .) from the reward critics (mean over
    /// the ensemble, no gradient). It anchors the actor to replayed actions
    /// that beat its own (0: off, the paper's Lp alone; AMAGO uses 0.1).
    #[serde(default)]
    pub bc_coef: f64,
    /// Rewards are multiplied by this in the TD targets and the tokens.
    pub reward_scale: f64,
    /// Epsilon-greedy exploration (discrete actions) at a trajectory's first
    /// step, at the start of training. Epsilon is bilevel, after AMAGO: it
    /// anneals over training and, inside each trajectory, moves linearly from
    /// its first-step value to its last-step value (`eps_last_*`).
    pub eps_start: f64,
    /// Epsilon at a trajectory's first step once annealed.
    pub eps_end: f64,
    /// Environment steps over which both ends anneal linearly.
    pub eps_decay_steps: u64,
    /// Epsilon at a trajectory's last step, at the start of training
    /// (absent: equal to `eps_start`, no decay inside a trajectory).
    #[serde(default)]
    pub eps_last_start: Option<f64>,
    /// Epsilon at a trajectory's last step once annealed (absent: `eps_end`).
    #[serde(default)]
    pub eps_last_end: Option<f64>,
    /// Scale each trajectory's epsilon by its own uniform draw in [0, 1]
    /// (AMAGO's `randomize_eps`): the replay then holds the whole range from
    /// near-on-policy to noisy trajectories.
    #[serde(default)]
    pub eps_random_scale: bool,
    /// Pretraining task pool: 0 draws a fresh task for every trajectory (the
    /// paper); n > 0 cycles over the first n task seeds (1: one fixed task,
    /// the first rung of the debugging ladder).
    #[serde(default)]
    pub task_pool: u64,
    /// Updates between checkpoints (one is always written at the end).
    pub checkpoint_every: u64,
    /// Checkpoints kept (0 keeps all).
    pub keep_checkpoints: usize,
    /// Point and Car: MuJoCo physics steps per agent action (the macro
    /// action; 5 Safety-Gymnasium steps x 10 physics steps = 50 when absent).
    /// SafeDarkRoom has no physics: leave it out. Checkpoints record the
    /// resolved value; resuming with another is refused.
    #[serde(default = "default_physics_steps_per_action")]
    pub physics_steps_per_action: Option<usize>,
}

/// Absent from a config: one-step TD targets (the paper's).
fn default_n_step() -> usize {
    1
}

/// Absent from a config: the environment's default macro action.
fn default_physics_steps_per_action() -> Option<usize> {
    None
}

/// A configuration that cannot run, a failing environment, model or checkpoint.
#[derive(Debug, Error)]
pub enum EppoError {
    #[error("eppo config: {0}")]
    Config(String),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error(transparent)]
    Torch(#[from] tch::TchError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// A loss or gradient became NaN or infinite: the update was not applied.
    #[error(
        "update {update}: {what}; training stopped without applying it. {}",
        crate::checkpoint::last_good(.checkpoint, "lower lr, or check the settings")
    )]
    NonFinite {
        update: u64,
        what: String,
        checkpoint: Option<PathBuf>,
    },
    /// Stopped by SIGINT/SIGTERM after writing a checkpoint.
    #[error("interrupted after update {updates}: checkpoint written to {}", .checkpoint.display())]
    Interrupted { checkpoint: PathBuf, updates: u64 },
}

impl EppoConfig {
    /// Checks the values that would otherwise fail deep inside training:
    /// every count at least 1, every number finite and in its range (named
    /// in the error), and the sizes that must fit together.
    pub fn validate(&self) -> Result<(), EppoError> {
        use crate::guard::{Range, check_counts, check_numbers};
        let bad = |m: String| Err(EppoError::Config(m));
        self.model.validate()?;
        check_counts(&[
            ("max_episode_steps", self.max_episode_steps as i128),
            ("k_min", self.k_min as i128),
            ("k_max", self.k_max as i128),
            ("n_envs", self.n_envs as i128),
            ("env_threads", self.env_threads as i128),
            ("replay_capacity", self.replay_capacity as i128),
            ("encoder_hidden", i128::from(self.encoder_hidden)),
            ("head_hidden", i128::from(self.head_hidden)),
            ("n_critics", i128::from(self.n_critics)),
            ("batch_size", self.batch_size as i128),
            ("total_updates", i128::from(self.total_updates)),
            ("updates_per_round", i128::from(self.updates_per_round)),
            ("checkpoint_every", i128::from(self.checkpoint_every)),
            ("n_step", self.n_step as i128),
            (
                "physics_steps_per_action",
                self.physics_steps_per_action.map_or(1, |n| n as i128),
            ),
        ])
        .or_else(bad)?;
        crate::guard::check_torch_threads(self.torch_threads).or_else(bad)?;
        check_numbers(&[
            ("ctg_min", f64::from(self.ctg_min), Range::NON_NEGATIVE),
            ("ctg_max", f64::from(self.ctg_max), Range::POSITIVE),
            ("gamma", self.gamma, Range::UNIT_OPEN_HIGH),
            ("tau", self.tau, Range::UNIT),
            ("lr", self.lr, Range::UNIT_OPEN_LOW),
            ("beta1", self.beta1, Range::UNIT_OPEN_HIGH),
            ("beta2", self.beta2, Range::UNIT_OPEN_HIGH),
            ("adam_eps", self.adam_eps, Range::UNIT_OPEN_LOW),
            ("grad_clip", self.grad_clip, Range::POSITIVE),
            ("lambda_lr", self.lambda_lr, Range::NON_NEGATIVE),
            ("lambda_max", self.lambda_max, Range::NON_NEGATIVE),
            ("lambda_init", self.lambda_init, Range::NON_NEGATIVE),
            ("critic_weight", self.critic_weight, Range::POSITIVE),
            ("entropy_coef", self.entropy_coef, Range::NON_NEGATIVE),
            ("bc_coef", self.bc_coef, Range::NON_NEGATIVE),
            // Scaled rewards go into float32 tokens: keep them far from overflow.
            (
                "reward_scale",
                self.reward_scale,
                Range::new(0.0, true, 1e6, false),
            ),
            ("eps_start", self.eps_start, Range::UNIT),
            ("eps_end", self.eps_end, Range::UNIT),
        ])
        .or_else(bad)?;
        if self.k_min == 0 || self.k_min > self.k_max {
            return bad(format!(
                "need 1 <= k_min <= k_max, got k_min = {}, k_max = {}",
                self.k_min, self.k_max
            ));
        }
        let longest = self.k_max.saturating_mul(self.max_episode_steps);
        if longest as u128 > self.model.max_len as u128 {
            return bad(format!(
                "a trajectory of k_max * max_episode_steps = {} * {} = {longest} steps exceeds model.max_len = {}",
                self.k_max, self.max_episode_steps, self.model.max_len
            ));
        }
        if !(self.ctg_min >= 0.0 && self.ctg_min <= self.ctg_max && self.ctg_max > 0.0) {
            return bad(format!(
                "need 0 <= ctg_min <= ctg_max, ctg_max > 0; got {} and {}",
                self.ctg_min, self.ctg_max
            ));
        }
        if self.lambda_init > self.lambda_max {
            return bad(format!(
                "need 0 <= lambda_init <= lambda_max; got {} and {}",
                self.lambda_init, self.lambda_max
            ));
        }
        for (name, v) in [
            ("eps_start", Some(self.eps_start)),
            ("eps_end", Some(self.eps_end)),
            ("eps_last_start", self.eps_last_start),
            ("eps_last_end", self.eps_last_end),
        ] {
            if let Some(v) = v
                && !(0.0..=1.0).contains(&v)
            {
                return bad(format!("{name} = {v} must lie in [0, 1]"));
            }
        }
        if self.replay_capacity < longest {
            return bad(format!(
                "replay_capacity = {} cannot hold one trajectory of {longest} steps",
                self.replay_capacity
            ));
        }
        parse_device(&self.device)?;
        Ok(())
    }
}

/// The epsilon-greedy schedule inside one trajectory, at one point of training.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Exploration {
    /// Epsilon at the trajectory's first step.
    pub first: f64,
    /// Epsilon at its last possible step (K x t_max).
    pub last: f64,
}

impl Exploration {
    /// Epsilon at step `t` of a trajectory of at most `horizon` steps, scaled
    /// by the trajectory's own draw `scale` (1 without `eps_random_scale`).
    pub fn at(&self, t: usize, horizon: usize, scale: f64) -> f64 {
        let progress = (t as f64 / horizon.max(1) as f64).min(1.0);
        scale * (self.first + (self.last - self.first) * progress)
    }
}

impl EppoConfig {
    /// Both ends of the bilevel schedule after `env_steps` of training: each
    /// anneals linearly from its start to its end value over `eps_decay_steps`.
    pub fn exploration(&self, env_steps: u64) -> Exploration {
        let frac = (env_steps as f64 / self.eps_decay_steps.max(1) as f64).min(1.0);
        let anneal = |from: f64, to: f64| from + (to - from) * frac;
        Exploration {
            first: anneal(self.eps_start, self.eps_end),
            last: anneal(
                self.eps_last_start.unwrap_or(self.eps_start),
                self.eps_last_end.unwrap_or(self.eps_end),
            ),
        }
    }
}

/// `cpu` or `cuda` -> a libtorch device; `cuda` fails clearly without a GPU.
pub fn parse_device(name: &str) -> Result<Device, EppoError> {
    match name {
        "cpu" => Ok(Device::Cpu),
        "cuda" => {
            if tch::Cuda::is_available() {
                Ok(Device::Cuda(0))
            } else {
                Err(EppoError::Config(
                    "device = cuda but libtorch sees no CUDA device (this libtorch is CPU-only or no GPU is present); use --device cpu or link a CUDA libtorch (SPEC section 7)".into(),
                ))
            }
        }
        other => Err(EppoError::Config(format!(
            "device = {other:?}: expected cpu or cuda"
        ))),
    }
}

/// What a run with `cfg` on spaces `spec` will allocate, by part (checked
/// against the machine's memory before anything is built). Parameters count
/// the online and target networks, their gradients and Adam's two moments;
/// one batch's activations are the transformer's saved tensors for
/// `batch_size` sequences of `max_len` steps (plus the target's forward); the
/// acting cache holds keys and values of `n_envs` trajectories. On `cuda`
/// only the replay (host memory) is counted: the rest lives on the GPU,
/// whose memory libtorch reports through no API tch binds.
pub fn memory_estimate(cfg: &EppoConfig, spec: &NetSpec) -> crate::guard::MemoryEstimate {
    use crate::guard::{transformer_activation_bytes, transformer_parameters};
    let f = |x: usize| x as f64;
    let (d, eh, hh) = (
        cfg.model.d_model as f64,
        cfg.encoder_hidden as f64,
        cfg.head_hidden as f64,
    );
    let a = f(spec.act_flat());
    let (actor_out, critic_in, critic_out) = match spec.n_actions {
        Some(_) => (a, d, cfg.n_critics as f64 * a),
        None => (2.0 * a, d + a, cfg.n_critics as f64),
    };
    let head = |i: f64, o: f64| i * hh + hh + hh * hh + hh + hh * o + o;
    let params = f(spec.token_dim()) * eh
        + eh
        + eh * d
        + d
        + transformer_parameters(&cfg.model)
        + head(d, actor_out)
        + 2.0 * head(critic_in, critic_out);
    let (b, t) = (f(cfg.batch_size), cfg.model.max_len as f64);
    let step_bytes = 4.0 * (f(spec.obs_dim) + a + 3.0) + 15.0;
    let mut m = crate::guard::MemoryEstimate {
        levers:
            "batch_size, model.max_len, model.d_model, model.n_layers, n_envs or replay_capacity"
                .into(),
        ..Default::default()
    };
    m.add("replay", f(cfg.replay_capacity) * step_bytes);
    if cfg.device == "cuda" {
        return m;
    }
    m.add("parameters (online and target)", 2.0 * 4.0 * params);
    m.add("gradients and Adam moments", 3.0 * 4.0 * params);
    m.add(
        "one batch's activations",
        1.5 * transformer_activation_bytes(&cfg.model, b) + 2.0 * 4.0 * b * t * f(spec.token_dim()),
    );
    m.add(
        "acting cache",
        4.0 * f(cfg.n_envs) * t * (2.0 * cfg.model.n_layers as f64 * d + f(spec.token_dim())),
    );
    m
}

// ---------------------------------------------------------------------------
// Networks
// ---------------------------------------------------------------------------

/// What the networks read and emit, taken from the environment's spaces.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NetSpec {
    /// Observation length.
    pub obs_dim: usize,
    /// Per-entry observation bounds used to map observations to [-1, 1]
    /// (entries with infinite bounds pass through unchanged).
    #[serde(with = "crate::json_bounds::lower")]
    pub obs_low: Vec<f32>,
    #[serde(with = "crate::json_bounds::upper")]
    pub obs_high: Vec<f32>,
    /// `Some(n)` for n discrete actions, `None` for a box.
    pub n_actions: Option<usize>,
    /// Continuous action bounds (empty for discrete).
    pub act_low: Vec<f32>,
    pub act_high: Vec<f32>,
}

impl NetSpec {
    /// From the environment's spaces.
    pub fn from_spaces(obs: &Space, act: &Space) -> Result<Self, EppoError> {
        let (obs_low, obs_high) = match obs {
            Space::Box { low, high } => (low.clone(), high.clone()),
            Space::Discrete { .. } => {
                return Err(EppoError::Config(
                    "discrete observation spaces are not supported".into(),
                ));
            }
        };
        let (n_actions, act_low, act_high) = match act {
            Space::Discrete { n } => (Some(*n), vec![], vec![]),
            Space::Box { low, high } => (None, low.clone(), high.clone()),
        };
        Ok(NetSpec {
            obs_dim: obs_low.len(),
            obs_low,
            obs_high,
            n_actions,
            act_low,
            act_high,
        })
    }

    /// Checks that the bounds have one entry per dimension (a spec read from
    /// a file may not).
    pub fn check(&self) -> Result<(), String> {
        let act = self.n_actions.map_or(self.act_low.len(), |_| 0);
        if self.obs_low.len() != self.obs_dim
            || self.obs_high.len() != self.obs_dim
            || self.act_high.len() != act
            || self.n_actions == Some(0)
        {
            return Err(format!(
                "spec sizes disagree: obs_dim {} with {} and {} bounds, {:?} discrete actions, {} and {} action bounds",
                self.obs_dim,
                self.obs_low.len(),
                self.obs_high.len(),
                self.n_actions,
                self.act_low.len(),
                self.act_high.len()
            ));
        }
        Ok(())
    }

    /// Width of an action as the network sees it (one-hot for discrete).
    pub fn act_flat(&self) -> usize {
        self.n_actions.unwrap_or(self.act_low.len())
    }

    /// Width of one time-step token: obs, arrived obs, previous action,
    /// reward, cost, CTG, start flag.
    pub fn token_dim(&self) -> usize {
        tokens::token_dim(self.obs_dim, self.act_flat(), 1)
    }

    /// Observation mapped to [-1, 1] where the bounds are finite.
    fn normalise_obs(&self, obs: &[f32], out: &mut Vec<f32>) {
        for (i, &x) in obs.iter().enumerate() {
            let (lo, hi) = (self.obs_low[i], self.obs_high[i]);
            if lo.is_finite() && hi.is_finite() && hi > lo {
                out.push(2.0 * (x - lo) / (hi - lo) - 1.0);
            } else {
                out.push(x);
            }
        }
    }
}

/// An MLP head whose forward can use detached weights, so the actor's loss
/// moves neither critic's parameters (the critic sees gradients only from Lv, Lc).
#[derive(Debug)]
struct Head {
    l1: nn::Linear,
    l2: nn::Linear,
    l3: nn::Linear,
}

impl Head {
    fn new(p: nn::Path, input: i64, hidden: i64, output: i64) -> Self {
        Head {
            l1: nn::linear(&p / "l1", input, hidden, Default::default()),
            l2: nn::linear(&p / "l2", hidden, hidden, Default::default()),
            l3: nn::linear(&p / "l3", hidden, output, Default::default()),
        }
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        self.l3
            .forward(&self.l2.forward(&self.l1.forward(x).relu()).relu())
    }

    /// The same function with the parameters cut from the graph.
    fn forward_detached(&self, x: &Tensor) -> Tensor {
        let lin = |l: &nn::Linear, x: &Tensor| {
            x.linear(&l.ws.detach(), l.bs.as_ref().map(Tensor::detach))
        };
        lin(&self.l3, &lin(&self.l2, &lin(&self.l1, x).relu()).relu())
    }
}

/// Time-step encoder, shared transformer, actor and critic heads.
#[derive(Debug)]
pub struct EppoNet {
    spec: NetSpec,
    /// Time-step encoder: token -> encoder_hidden -> d_model.
    enc_1: nn::Linear,
    enc_2: nn::Linear,
    transformer: Transformer,
    /// Discrete: logits (A). Continuous: mean and log-std (2 * A).
    actor: Head,
    /// Discrete: (C * A) values from h. Continuous: C values from (h, a).
    critic: Head,
    cost_critic: Head,
    n_critics: i64,
}

const LOG_STD_MIN: f64 = -5.0;
const LOG_STD_MAX: f64 = 2.0;

impl EppoNet {
    /// Builds every part under `p` (names are the checkpoint format).
    pub fn new(p: nn::Path, cfg: &EppoConfig, spec: &NetSpec) -> Result<Self, EppoError> {
        let d = cfg.model.d_model;
        let a = spec.act_flat() as i64;
        let (actor_out, critic_in, critic_out) = match spec.n_actions {
            Some(_) => (a, d, cfg.n_critics * a),
            None => (2 * a, d + a, cfg.n_critics),
        };
        Ok(EppoNet {
            spec: spec.clone(),
            enc_1: nn::linear(
                &p / "enc_1",
                spec.token_dim() as i64,
                cfg.encoder_hidden,
                Default::default(),
            ),
            enc_2: nn::linear(&p / "enc_2", cfg.encoder_hidden, d, Default::default()),
            transformer: Transformer::new(&p / "transformer", &cfg.model)?,
            actor: Head::new(&p / "actor", d, cfg.head_hidden, actor_out),
            critic: Head::new(&p / "critic", critic_in, cfg.head_hidden, critic_out),
            cost_critic: Head::new(&p / "cost_critic", critic_in, cfg.head_hidden, critic_out),
            n_critics: cfg.n_critics,
        })
    }

    fn embed(&self, tokens: &Tensor) -> Tensor {
        self.enc_2.forward(&self.enc_1.forward(tokens).gelu("none"))
    }

    /// Whole sequences: tokens (B, T, token_dim) -> h (B, T, D).
    pub fn encode(&self, tokens: &Tensor, train: bool) -> Result<Tensor, EppoError> {
        Ok(self.transformer.forward_t(&self.embed(tokens), train)?)
    }

    /// Next steps after the cached ones: tokens (B, 1, token_dim) -> h (B, 1, D).
    pub fn encode_step(&self, tokens: &Tensor, cache: &mut KvCache) -> Result<Tensor, EppoError> {
        Ok(self.transformer.forward_step(&self.embed(tokens), cache)?)
    }

    /// A fresh KV cache.
    pub fn new_cache(&self) -> KvCache {
        self.transformer.new_cache()
    }

    /// Discrete critics: h (.., D) -> (.., C, A).
    fn critic_values(&self, head: &Head, h: &Tensor, detached: bool) -> Tensor {
        let out = if detached {
            head.forward_detached(h)
        } else {
            head.forward(h)
        };
        let mut shape = h.size();
        shape.pop();
        shape.extend([self.n_critics, self.spec.act_flat() as i64]);
        out.view(shape.as_slice()) // (.., C * A) -> (.., C, A)
    }

    /// Continuous critics: (h (.., D), a (.., A)) -> (.., C).
    fn critic_sa(&self, head: &Head, h: &Tensor, a: &Tensor, detached: bool) -> Tensor {
        let x = Tensor::cat(&[h, a], -1); // (.., D + A)
        if detached {
            head.forward_detached(&x)
        } else {
            head.forward(&x)
        }
    }

    /// Continuous actor: h -> (mean, log_std), each (.., A).
    fn gaussian(&self, h: &Tensor) -> (Tensor, Tensor) {
        let out = self.actor.forward(h);
        let parts = out.chunk(2, -1);
        (
            parts[0].shallow_clone(),
            parts[1].clamp(LOG_STD_MIN, LOG_STD_MAX),
        )
    }
}

/// A tanh-squashed Gaussian sample and its log-probability: (a, log_prob) with
/// a in (-1, 1)^A, (.., A) and (..).
fn tanh_gaussian_sample(mean: &Tensor, log_std: &Tensor, noise: &Tensor) -> (Tensor, Tensor) {
    let std = log_std.exp();
    let u = mean + &std * noise;
    let a = u.tanh();
    let log_normal = (noise.square() * -0.5) - log_std - 0.5 * (2.0 * std::f64::consts::PI).ln();
    // Change of variables through tanh: log(1 - tanh(u)^2) = 2 (ln 2 - u - softplus(-2u)).
    let log_det = ((u.neg() * 2.0).softplus() + &u).neg() * 2.0 + 2.0 * 2f64.ln();
    let log_prob = (log_normal - log_det).sum_dim_intlist(-1, false, Kind::Float);
    (a, log_prob)
}

/// log pi(a | mean, log_std) of given squashed actions a in [-1, 1]^A, (.., A)
/// -> (..): the Gaussian density of u = atanh(a) less log(1 - a^2). Actions
/// are pulled 1e-6 inside the box first (a stored f32 action can be exactly
/// +-1, where atanh is infinite).
fn tanh_gaussian_log_prob(mean: &Tensor, log_std: &Tensor, a: &Tensor) -> Tensor {
    let a = a.clamp(-1.0 + 1e-6, 1.0 - 1e-6);
    let u = ((&a + 1.0) / (a.neg() + 1.0)).log() * 0.5; // atanh(a)
    let z = (u - mean) / log_std.exp();
    let log_normal = (z.square() * -0.5) - log_std - 0.5 * (2.0 * std::f64::consts::PI).ln();
    let log_det = (a.square().neg() + (1.0 + 1e-6)).log();
    (log_normal - log_det).sum_dim_intlist(-1, false, Kind::Float)
}

// ---------------------------------------------------------------------------
// Trajectories and the replay buffer
// ---------------------------------------------------------------------------

/// K episodes in one task with one budget, as collected.
#[derive(Clone, Debug, Default)]
pub struct Trajectory {
    /// The per-episode cost budget delta.
    pub budget: f32,
    /// (T, obs_dim) observations s_t.
    pub obs: Vec<f32>,
    /// (T, obs_dim) the observation a_t led to: s_{t+1}, or the episode's
    /// final observation where a_t ended it (the next s_t is then a new start).
    pub next_obs: Vec<f32>,
    /// (T, act_flat) actions a_t as the network sees them (one-hot, or in [-1, 1]).
    pub actions: Vec<f32>,
    /// Discrete action indices (empty for continuous).
    pub action_idx: Vec<i64>,
    /// (T,) reward r_{t+1} and cost c_{t+1} received for a_t.
    pub rewards: Vec<f32>,
    pub costs: Vec<f32>,
    /// (T,) CTG_t before acting at t.
    pub ctg: Vec<f32>,
    /// (T,) s_t is an episode's first state.
    pub start: Vec<bool>,
    /// (T,) the step ended its episode at the goal (terminal: nothing to bootstrap past it).
    pub terminated: Vec<bool>,
    /// (T,) the step ended its episode at the time limit (not terminal).
    pub truncated: Vec<bool>,
    /// (T,) index of the episode the step belongs to.
    pub episode: Vec<u32>,
    /// Per episode: return, cost, and whether it ended at the goal.
    pub episode_returns: Vec<f32>,
    pub episode_costs: Vec<f32>,
    pub episode_success: Vec<bool>,
}

impl Trajectory {
    /// Steps in the trajectory.
    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.rewards.is_empty()
    }

    /// max_k (C_k - delta): the trajectory's term in Eq. (7).
    pub fn max_violation(&self) -> f32 {
        self.episode_costs
            .iter()
            .map(|c| c - self.budget)
            .fold(f32::NEG_INFINITY, f32::max)
    }
}

/// Whole trajectories, oldest evicted first once `capacity` steps are exceeded.
#[derive(Debug, Default)]
pub struct Replay {
    trajectories: VecDeque<Trajectory>,
    steps: usize,
    capacity: usize,
}

impl Replay {
    pub fn new(capacity: usize) -> Self {
        Replay {
            trajectories: VecDeque::new(),
            steps: 0,
            capacity,
        }
    }

    pub fn push(&mut self, t: Trajectory) {
        self.steps += t.len();
        self.trajectories.push_back(t);
        while self.steps > self.capacity {
            match self.trajectories.pop_front() {
                Some(old) => self.steps -= old.len(),
                None => break,
            }
        }
    }

    pub fn len(&self) -> usize {
        self.trajectories.len()
    }

    pub fn is_empty(&self) -> bool {
        self.trajectories.is_empty()
    }

    /// Steps held.
    pub fn steps(&self) -> usize {
        self.steps
    }

    fn sample<'a>(&'a self, n: usize, rng: &mut ChaCha8Rng) -> Vec<&'a Trajectory> {
        (0..n)
            .map(|_| &self.trajectories[rng.gen_range(0..self.trajectories.len())])
            .collect()
    }
}

// ---------------------------------------------------------------------------
// Tokens: the same construction for collection, training and evaluation
// ---------------------------------------------------------------------------

/// Writes one token ([`crate::tokens`], shared with supervised pretraining):
/// obs s_t and the observation a_{t-1} arrived at (both normalised), a_{t-1},
/// r_t (scaled), c_t, CTG_t / ctg_max, start flag.
#[allow(clippy::too_many_arguments)]
fn push_token(
    spec: &NetSpec,
    cfg: &EppoConfig,
    out: &mut Vec<f32>,
    obs: &[f32],
    arrived_obs: &[f32],
    prev_action: &[f32],
    reward: f32,
    cost: f32,
    ctg: f32,
    start: bool,
) {
    let step = StepToken {
        obs,
        arrived_obs,
        prev_action,
        reward,
        cost,
        to_go: &[ctg / cfg.ctg_max],
        start,
    };
    tokens::push_token(
        &step,
        cfg.reward_scale as f32,
        |o, out| spec.normalise_obs(o, out),
        out,
    );
}

/// A training batch of B windows of length L (right-padded).
struct Batch {
    /// (B, L, token_dim)
    tokens: Tensor,
    /// (B, L) discrete action indices, or (B, L, A) continuous actions.
    actions: Tensor,
    /// (B, L) reward r_{t+1} (scaled) and cost c_{t+1}.
    rewards: Tensor,
    costs: Tensor,
    /// (B, L) 1 where the step's episode exceeded the budget (v_e).
    violated: Tensor,
    /// (B, L) 1 on real (not padded) steps: the actor loss.
    valid: Tensor,
    /// (B, L) 1 where a TD target exists for the step: the critic losses.
    td_valid: Tensor,
    /// (B, L) 1 where the reward target bootstraps from position t + 1.
    bootstrap: Tensor,
    /// (B, L) 1 where the cost target bootstraps from position t + 1: never
    /// past an episode's end, since the budget binds each episode on its own
    /// (Eq. 6, 7): a violation charges only its own episode.
    cost_bootstrap: Tensor,
    /// (B,) max_k (C_k - delta) of each sampled trajectory (Eq. 7).
    max_violation: Vec<f32>,
}

fn make_batch(
    trajs: &[&Trajectory],
    cfg: &EppoConfig,
    spec: &NetSpec,
    rng: &mut ChaCha8Rng,
    device: Device,
) -> Batch {
    let seq = cfg.model.max_len as usize;
    // Each trajectory contributes a window of at most `seq` steps.
    let windows: Vec<(usize, usize)> = trajs
        .iter()
        .map(|t| {
            let len = t.len().min(seq);
            let start = if t.len() > seq {
                rng.gen_range(0..=t.len() - seq)
            } else {
                0
            };
            (start, len)
        })
        .collect();
    let b = trajs.len();
    let l = windows.iter().map(|w| w.1).max().unwrap_or(1);
    let (dtok, a) = (spec.token_dim(), spec.act_flat());
    let mut tokens = Vec::with_capacity(b * l * dtok);
    let mut acts_f = Vec::with_capacity(b * l * a);
    let mut acts_i = Vec::with_capacity(b * l);
    let mut rew = vec![0f32; b * l];
    let mut cost = vec![0f32; b * l];
    let mut viol = vec![0f32; b * l];
    let mut valid = vec![0f32; b * l];
    let mut td_valid = vec![0f32; b * l];
    let mut boot = vec![0f32; b * l];
    let mut cost_boot = vec![0f32; b * l];
    let zeros_a = vec![0f32; a];
    let zeros_o = vec![0f32; spec.obs_dim];
    for (j, (t, &(s, len))) in trajs.iter().zip(&windows).enumerate() {
        let violated: Vec<bool> = t.episode_costs.iter().map(|&c| c > t.budget).collect();
        for i in 0..l {
            let k = j * l + i;
            if i >= len {
                // Padding: a zero token after the end; masked out everywhere.
                push_token(
                    spec,
                    cfg,
                    &mut tokens,
                    &zeros_o,
                    &zeros_o,
                    &zeros_a,
                    0.0,
                    0.0,
                    0.0,
                    false,
                );
                acts_f.extend_from_slice(&zeros_a);
                acts_i.push(0);
                continue;
            }
            let step = s + i;
            let obs = &t.obs[step * spec.obs_dim..(step + 1) * spec.obs_dim];
            let od = spec.obs_dim;
            let (arrived, prev, r, c) = if step == 0 {
                (&zeros_o[..], &zeros_a[..], 0.0, 0.0)
            } else {
                (
                    &t.next_obs[(step - 1) * od..step * od],
                    &t.actions[(step - 1) * a..step * a],
                    t.rewards[step - 1],
                    t.costs[step - 1],
                )
            };
            push_token(
                spec,
                cfg,
                &mut tokens,
                obs,
                arrived,
                prev,
                r,
                c,
                t.ctg[step],
                t.start[step],
            );
            acts_f.extend_from_slice(&t.actions[step * a..(step + 1) * a]);
            acts_i.push(t.action_idx.get(step).copied().unwrap_or(0));
            rew[k] = t.rewards[step] * cfg.reward_scale as f32;
            cost[k] = t.costs[step];
            viol[k] = if violated[t.episode[step] as usize] {
                1.0
            } else {
                0.0
            };
            valid[k] = 1.0;
            let last_of_trajectory = step + 1 == t.len();
            let next_in_window = i + 1 < len;
            let (has_target, bootstraps) = if cfg.bootstrap_across_episodes {
                // Meta-RL view: an episode's end (terminated at the goal or
                // truncated at the time limit) leads to the next episode's
                // first state, which is the next token: bootstrap through it.
                // Only the trajectory's end stops the sum of K returns.
                if last_of_trajectory {
                    (true, false)
                } else {
                    (next_in_window, next_in_window)
                }
            } else if t.terminated[step] {
                // Terminated (goal): a true terminal state, target = r alone.
                (true, false)
            } else if t.truncated[step] {
                // Truncated (time limit): the value goes on past the final
                // state, but that state is not a token (the next token starts
                // another episode), so the step has no target and is skipped.
                (false, false)
            } else {
                (next_in_window, next_in_window)
            };
            td_valid[k] = if has_target { 1.0 } else { 0.0 };
            boot[k] = if bootstraps { 1.0 } else { 0.0 };
            let episode_ends = t.terminated[step] || t.truncated[step];
            cost_boot[k] = if bootstraps && !episode_ends {
                1.0
            } else {
                0.0
            };
        }
    }
    let (bi, li) = (b as i64, l as i64);
    let f = |v: &[f32]| Tensor::from_slice(v).view([bi, li]).to_device(device); // (B*L,) -> (B, L)
    let actions = match spec.n_actions {
        Some(_) => Tensor::from_slice(&acts_i).view([bi, li]).to_device(device), // (B, L)
        None => Tensor::from_slice(&acts_f)
            .view([bi, li, a as i64])
            .to_device(device), // (B, L, A)
    };
    Batch {
        tokens: Tensor::from_slice(&tokens)
            .view([bi, li, dtok as i64])
            .to_device(device), // (B, L, token_dim)
        actions,
        rewards: f(&rew),
        costs: f(&cost),
        violated: f(&viol),
        valid: f(&valid),
        td_valid: f(&td_valid),
        bootstrap: f(&boot),
        cost_bootstrap: f(&cost_boot),
        max_violation: trajs.iter().map(|t| t.max_violation()).collect(),
    }
}

// ---------------------------------------------------------------------------
// The update: Lv, Lc, Lp, lambda (Eq. 7), Polyak targets
// ---------------------------------------------------------------------------

/// Scalars of one update.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct UpdateStats {
    pub value_loss: f64,
    pub cost_value_loss: f64,
    pub policy_loss: f64,
    pub entropy: f64,
    pub grad_norm: f64,
    pub lambda: f64,
    /// Diagnostics: mean Q(h_t, a_t) of the reward critics on the replayed
    /// actions, mean reward TD target, and (continuous actions) the actor's
    /// mean log-std; NaN where not defined.
    pub q_mean: f64,
    pub target_mean: f64,
    pub log_std_mean: f64,
}

/// What [`losses`] returns besides the three losses and the entropy.
struct LossDiagnostics {
    q_mean: Tensor,
    target_mean: Tensor,
    log_std_mean: Option<Tensor>,
}

/// Shifts (B, L) left by one along time: out[:, t] = x[:, t + 1], 0 at the end.
fn next_step(x: &Tensor) -> Tensor {
    let l = x.size()[1];
    let zero = x.narrow(1, 0, 1).zeros_like(); // (B, 1)
    Tensor::cat(&[x.narrow(1, 1, l - 1), zero], 1) // (B, L)
}

fn masked_mean(x: &Tensor, mask: &Tensor) -> Tensor {
    (x * mask).sum(Kind::Float) / mask.sum(Kind::Float).clamp_min(1.0)
}

/// n-step TD targets, (B, L) each: y1_t = r_t + gamma b_t V'_{t+1} and
/// y(m)_t = r_t + gamma b_t [y(m-1)_{t+1} if step t + 1 has a target of its
/// own, else V'_{t+1}], so every sum stops where its bootstrap mask `b`
/// stops (terminal, trajectory or window end) and falls back to the one-step
/// bootstrap at a step without a target (truncated, episodes apart).
/// `v_next` is V'(t + 1) at position t.
fn n_step_targets(
    r: &Tensor,
    bootstrap: &Tensor,
    td_valid: &Tensor,
    v_next: &Tensor,
    gamma: f64,
    n: usize,
) -> Tensor {
    let mut y = r + bootstrap * v_next * gamma;
    let valid_next = next_step(td_valid);
    for _ in 1..n {
        let ahead = &valid_next * next_step(&y) + (valid_next.ones_like() - &valid_next) * v_next;
        y = r + bootstrap * ahead * gamma;
    }
    y
}

/// The three losses on one batch (before any step), and the policy entropy.
fn losses(
    net: &EppoNet,
    target: &EppoNet,
    batch: &Batch,
    lambda: f64,
    cfg: &EppoConfig,
) -> Result<(Tensor, Tensor, Tensor, Tensor, LossDiagnostics), EppoError> {
    let h = net.encode(&batch.tokens, true)?; // (B, L, D)
    let c = cfg.n_critics;
    // Targets from the target networks at t + 1, no gradient.
    let (v_next, vc_next) = tch::no_grad(|| -> Result<(Tensor, Tensor), EppoError> {
        let ht = target.encode(&batch.tokens, false)?; // (B, L, D)
        let (v, vc) =
            match net.spec.n_actions {
                Some(_) => {
                    // Expected value under the target actor: sum_a pi'(a) Q'(h, a).
                    let pi = target
                        .actor
                        .forward(&ht)
                        .softmax(-1, Kind::Float)
                        .unsqueeze(2); // (B, L, 1, A)
                    let q = (target.critic_values(&target.critic, &ht, false) * &pi)
                        .sum_dim_intlist(-1, false, Kind::Float); // (B, L, C)
                    let qc = (target.critic_values(&target.cost_critic, &ht, false) * &pi)
                        .sum_dim_intlist(-1, false, Kind::Float); // (B, L, C)
                    (q.amin(-1, false), qc.mean_dim(-1, false, Kind::Float))
                }
                None => {
                    let (mean, log_std) = target.gaussian(&ht);
                    let (a, _) = tanh_gaussian_sample(&mean, &log_std, &mean.randn_like());
                    let q = target.critic_sa(&target.critic, &ht, &a, false); // (B, L, C)
                    let qc = target.critic_sa(&target.cost_critic, &ht, &a, false); // (B, L, C)
                    (q.amin(-1, false), qc.mean_dim(-1, false, Kind::Float))
                }
            }; // (B, L) each
        Ok((next_step(&v), next_step(&vc)))
    })?;
    // y = r + gamma * [bootstraps] * V'(t + 1); the bootstrap masks carry the
    // terminated / truncated / trajectory-end decision made in `make_batch`;
    // the cost's also stops at every episode end (per-episode constraint).
    let y = n_step_targets(
        &batch.rewards,
        &batch.bootstrap,
        &batch.td_valid,
        &v_next,
        cfg.gamma,
        cfg.n_step,
    ); // (B, L)
    let yc = n_step_targets(
        &batch.costs,
        &batch.cost_bootstrap,
        &batch.td_valid,
        &vc_next,
        cfg.gamma,
        cfg.n_step,
    ); // (B, L)
    let td_mask = batch.td_valid.unsqueeze(-1); // (B, L, 1)
    let mut log_std_mean = None;
    let (q_taken, qc_taken, policy_loss, entropy) = match net.spec.n_actions {
        Some(_) => {
            let q_all = net.critic_values(&net.critic, &h, false); // (B, L, C, A)
            let qc_all = net.critic_values(&net.cost_critic, &h, false); // (B, L, C, A)
            let idx = batch
                .actions
                .view([batch.actions.size()[0], -1, 1, 1])
                .expand([-1, -1, c, 1], false); // (B, L) -> (B, L, C, 1)
            let q_taken = q_all.gather(3, &idx, false).squeeze_dim(3); // (B, L, C)
            let qc_taken = qc_all.gather(3, &idx, false).squeeze_dim(3); // (B, L, C)
            // Actor: expectation of -Q + lambda v_e Qc under its own distribution;
            // critic values are constants here (detached).
            let logits = net.actor.forward(&h); // (B, L, A)
            let logp = logits.log_softmax(-1, Kind::Float);
            let pi = logp.exp();
            let q = q_all.detach().amin(2, false); // (B, L, A)
            let qc = qc_all.detach().mean_dim(2, false, Kind::Float); // (B, L, A)
            let penalty = lambda * cfg.reward_scale;
            let per_action = q.neg() + qc * batch.violated.unsqueeze(-1) * penalty; // (B, L, A)
            let entropy = (&pi * &logp).sum_dim_intlist(-1, false, Kind::Float).neg(); // (B, L)
            let mut objective = (&pi * per_action).sum_dim_intlist(-1, false, Kind::Float)
                - &entropy * cfg.entropy_coef;
            if cfg.bc_coef > 0.0 {
                // Filtered BC: A = Q(a_t) - sum_a pi(a) Q(a), mean over critics.
                let q_mean = q_all.detach().mean_dim(2, false, Kind::Float); // (B, L, A)
                let idx = batch.actions.unsqueeze(-1); // (B, L, 1)
                let q_data = q_mean.gather(2, &idx, false).squeeze_dim(2); // (B, L)
                let v = (&pi.detach() * &q_mean).sum_dim_intlist(-1, false, Kind::Float); // (B, L)
                let keep = (q_data - v).gt(0.0).to_kind(Kind::Float); // (B, L)
                let logp_data = logp.gather(2, &idx, false).squeeze_dim(2); // (B, L)
                objective -= keep * logp_data * cfg.bc_coef;
            }
            (
                q_taken,
                qc_taken,
                masked_mean(&objective, &batch.valid),
                masked_mean(&entropy, &batch.valid),
            )
        }
        None => {
            let q_taken = net.critic_sa(&net.critic, &h, &batch.actions, false); // (B, L, C)
            let qc_taken = net.critic_sa(&net.cost_critic, &h, &batch.actions, false); // (B, L, C)
            let (mean, log_std) = net.gaussian(&h);
            log_std_mean = Some(masked_mean(
                &log_std.detach().mean_dim(-1, false, Kind::Float),
                &batch.valid,
            ));
            let (a_hat, log_prob) = tanh_gaussian_sample(&mean, &log_std, &mean.randn_like());
            // The critics judge a_hat with frozen parameters and a detached
            // trajectory encoding: the actor loss moves only the actor (and the
            // encoder through the actor's input).
            let hd = h.detach();
            let q_hat = net.critic_sa(&net.critic, &hd, &a_hat, true); // (B, L, C)
            let q = q_hat.amin(-1, false); // (B, L)
            let qc =
                net.critic_sa(&net.cost_critic, &hd, &a_hat, true)
                    .mean_dim(-1, false, Kind::Float); // (B, L)
            let penalty = lambda * cfg.reward_scale;
            let mut objective =
                q.neg() + qc * &batch.violated * penalty + &log_prob * cfg.entropy_coef;
            if cfg.bc_coef > 0.0 {
                // Filtered BC: A = Q(a_t) - Q(a_hat) (one sample of E_pi),
                // mean over critics, no gradient anywhere in the filter.
                let keep = tch::no_grad(|| {
                    let q_data = q_taken.mean_dim(-1, false, Kind::Float); // (B, L)
                    let v = q_hat.detach().mean_dim(-1, false, Kind::Float); // (B, L)
                    (q_data - v).gt(0.0).to_kind(Kind::Float)
                });
                let logp_data = tanh_gaussian_log_prob(&mean, &log_std, &batch.actions); // (B, L)
                objective -= keep * logp_data * cfg.bc_coef;
            }
            (
                q_taken,
                qc_taken,
                masked_mean(&objective, &batch.valid),
                masked_mean(&log_prob.neg(), &batch.valid),
            )
        }
    };
    let diagnostics = LossDiagnostics {
        q_mean: masked_mean(
            &q_taken.detach().mean_dim(-1, false, Kind::Float),
            &batch.td_valid,
        ),
        target_mean: masked_mean(&y, &batch.td_valid),
        log_std_mean,
    };
    let value_loss = masked_mean(
        &(q_taken - y.unsqueeze(-1)).square(),
        &td_mask.expand([-1, -1, c], false),
    );
    let cost_value_loss = masked_mean(
        &(qc_taken - yc.unsqueeze(-1)).square(),
        &td_mask.expand([-1, -1, c], false),
    );
    Ok((
        value_loss,
        cost_value_loss,
        policy_loss,
        entropy,
        diagnostics,
    ))
}

/// Eq. (7): lambda <- clip(lambda + eta * mean_j max_k (C_jk - delta_j), 0, lambda_max).
pub fn lambda_update(lambda: f64, max_violations: &[f32], eta: f64, lambda_max: f64) -> f64 {
    if max_violations.is_empty() {
        return lambda;
    }
    let g = max_violations.iter().map(|&x| f64::from(x)).sum::<f64>() / max_violations.len() as f64;
    (lambda + eta * g).clamp(0.0, lambda_max)
}

/// target <- (1 - tau) target + tau online, for every variable by name.
fn polyak(target: &nn::VarStore, online: &nn::VarStore, tau: f64) {
    let src = online.variables();
    tch::no_grad(|| {
        for (name, mut t) in target.variables() {
            if let Some(o) = src.get(&name) {
                let _ = t.g_mul_scalar_(1.0 - tau).g_add_(&(o * tau));
            }
        }
    });
}

// ---------------------------------------------------------------------------
// The learner's state, collection, and `train`
// ---------------------------------------------------------------------------

/// Everything a run carries between updates (and into checkpoints).
pub struct Learner {
    pub cfg: EppoConfig,
    pub env: EnvName,
    pub spec: NetSpec,
    pub device: Device,
    pub vs: nn::VarStore,
    pub net: EppoNet,
    pub target_vs: nn::VarStore,
    pub target: EppoNet,
    pub opt: Adam,
    pub lambda: f64,
    pub updates: u64,
    pub env_steps: u64,
    /// Pretraining tasks drawn so far: task i comes from
    /// `pretrain_task_seed(cfg.seed, i)`, so checkpoints can record exactly
    /// which tasks were seen and evaluation can prove its tasks held out.
    pub tasks_drawn: u64,
    pub rng: ChaCha8Rng,
    pub replay: Replay,
}

/// What one collection round gathered.
#[derive(Clone, Debug, Default)]
pub struct RoundStats {
    pub trajectories: usize,
    pub steps: u64,
    pub mean_return: f64,
    pub mean_cost: f64,
    pub first_return: f64,
    pub last_return: f64,
    pub first_cost: f64,
    pub last_cost: f64,
    /// The in-context search signals, pooled over the round's episodes after
    /// the first: P(goal | not found earlier in the trajectory) and
    /// P(goal | found earlier), and the fraction of trajectories that found it.
    pub discovery_rate: f64,
    pub revisit_rate: f64,
    pub found: f64,
    /// Continuous actions: mean |a| of the collected actions (in [-1, 1])
    /// and the fraction with |a| > 0.99; NaN for discrete actions.
    pub action_abs: f64,
    pub action_saturated: f64,
}

/// (discovery rate, revisit rate, fraction found at least once) over
/// trajectories given as per-episode successes; a rate with no episode to
/// count is NaN.
pub fn search_rates<'a>(successes: impl Iterator<Item = &'a [bool]>) -> (f64, f64, f64) {
    let (mut disc, mut disc_n, mut rev, mut rev_n, mut found, mut n) = (0, 0, 0, 0, 0, 0);
    for episodes in successes {
        n += 1;
        let mut seen = false;
        for (k, &hit) in episodes.iter().enumerate() {
            if k > 0 {
                let (hits, count) = if seen {
                    (&mut rev, &mut rev_n)
                } else {
                    (&mut disc, &mut disc_n)
                };
                *hits += usize::from(hit);
                *count += 1;
            }
            seen |= hit;
        }
        found += usize::from(seen);
    }
    let rate = |a: usize, b: usize| {
        if b == 0 {
            f64::NAN
        } else {
            a as f64 / b as f64
        }
    };
    (rate(disc, disc_n), rate(rev, rev_n), rate(found, n))
}

fn mean(xs: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = xs.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 { 0.0 } else { s / n as f64 }
}

impl Learner {
    /// A fresh learner for `env` (networks initialised from `cfg.seed`).
    pub fn new(cfg: EppoConfig, env: EnvName) -> Result<Self, EppoError> {
        cfg.validate()?;
        let device = parse_device(&cfg.device)?;
        if cfg.torch_threads > 0 {
            tch::set_num_threads(cfg.torch_threads);
        }
        let probe = make_env(
            env,
            &EnvOptions {
                max_episode_steps: Some(cfg.max_episode_steps),
                physics_steps_per_action: cfg.physics_steps_per_action,
            },
        )?;
        let spec = NetSpec::from_spaces(&probe.observation_space(), &probe.action_space())?;
        memory_estimate(&cfg, &spec)
            .check()
            .map_err(EppoError::Config)?;
        tch::manual_seed(cfg.seed as i64);
        let vs = nn::VarStore::new(device);
        let net = EppoNet::new(vs.root(), &cfg, &spec)?;
        let mut target_vs = nn::VarStore::new(device);
        let target = EppoNet::new(target_vs.root(), &cfg, &spec)?;
        target_vs.copy(&vs)?;
        target_vs.freeze();
        let opt = Adam::new(
            &vs,
            AdamConfig {
                lr: cfg.lr,
                beta1: cfg.beta1,
                beta2: cfg.beta2,
                eps: cfg.adam_eps,
                grad_clip: Some(cfg.grad_clip),
            },
        );
        Ok(Learner {
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            replay: Replay::new(cfg.replay_capacity),
            lambda: cfg.lambda_init,
            updates: 0,
            env_steps: 0,
            tasks_drawn: 0,
            env,
            spec,
            device,
            vs,
            net,
            target_vs,
            target,
            opt,
            cfg,
        })
    }

    /// Current epsilon of epsilon-greedy exploration at a trajectory's first step.
    pub fn epsilon(&self) -> f64 {
        self.cfg.exploration(self.env_steps).first
    }

    /// Collects `cfg.n_envs` trajectories at once: each in a fresh centre-oriented
    /// task with its own budget and K, acted in one batch through the KV cache.
    pub fn collect(&mut self, venv: &mut VecEnv) -> Result<RoundStats, EppoError> {
        let n = venv.len();
        let spawn = spawn_config(self.env);
        let (mut budgets, mut ks, mut seeds) = (vec![0f32; n], vec![0usize; n], vec![0u64; n]);
        let mut eps_scale = vec![1f64; n];
        for i in 0..n {
            let index = match self.cfg.task_pool {
                0 => self.tasks_drawn,
                pool => self.tasks_drawn % pool,
            };
            let seed = pretrain_task_seed(self.cfg.seed, index);
            self.tasks_drawn += 1;
            let task = sample_task(&spawn, Orientation::Centre, seed)?;
            venv.set_task(i, &task)?;
            budgets[i] = self.rng.gen_range(self.cfg.ctg_min..=self.cfg.ctg_max);
            ks[i] = self.rng.gen_range(self.cfg.k_min..=self.cfg.k_max);
            seeds[i] = self.rng.r#gen();
            if self.cfg.eps_random_scale {
                eps_scale[i] = self.rng.r#gen();
            }
        }
        venv.reset(&seeds)?;
        let exploration = self.cfg.exploration(self.env_steps);
        let horizons: Vec<usize> = ks.iter().map(|k| k * self.cfg.max_episode_steps).collect();
        let mut acting = Acting::new(&self.net, &self.spec, &self.cfg, &budgets);
        let mut trajs: Vec<Trajectory> = budgets
            .iter()
            .map(|&budget| Trajectory {
                budget,
                ..Default::default()
            })
            .collect();
        let mut active = vec![true; n];
        let (od, a) = (self.spec.obs_dim, self.spec.act_flat());
        let mut obs = venv.observations().to_vec();
        let mut arrived = vec![0f32; n * od];
        let mut prev_action = vec![0f32; n * a];
        let (mut reward, mut cost, mut start) = (vec![0f32; n], vec![0f32; n], vec![true; n]);
        let (mut ep_ret, mut ep_cost) = (vec![0f32; n], vec![0f32; n]);
        let mut steps = 0u64;
        while active.iter().any(|&x| x) {
            let input = StepInput {
                obs: &obs,
                arrived_obs: &arrived,
                prev_action: &prev_action,
                reward: &reward,
                cost: &cost,
                episode_start: &start,
            };
            let ctg_now = acting.observe(&input);
            let policy = acting.policy(&self.net, &input)?;
            let eps: Vec<f64> = (0..n)
                .map(|i| exploration.at(trajs[i].len(), horizons[i], eps_scale[i]))
                .collect();
            let (net_actions, env_actions) =
                sample_actions(&policy, &self.spec, &eps, false, &mut self.rng);
            for i in (0..n).filter(|&i| active[i]) {
                let t = &mut trajs[i];
                t.obs.extend_from_slice(&obs[i * od..(i + 1) * od]);
                t.actions
                    .extend_from_slice(&net_actions[i * a..(i + 1) * a]);
                if let EnvActions::Discrete(idx) = &env_actions {
                    t.action_idx.push(idx[i] as i64);
                }
                t.ctg.push(ctg_now[i]);
                t.start.push(start[i]);
                t.episode.push(t.episode_returns.len() as u32);
            }
            let outcomes = match &env_actions {
                EnvActions::Discrete(idx) => venv.step(VecAction::Discrete(idx))?,
                EnvActions::Continuous(v) => venv.step(VecAction::Continuous(v))?,
            }
            .to_vec();
            obs.copy_from_slice(venv.observations());
            for i in 0..n {
                let o = outcomes[i];
                // Where the action led: the final observation when it ended
                // the episode (the auto-reset already replaced `obs`).
                let reached = if o.done() {
                    venv.final_observations()
                } else {
                    venv.observations()
                };
                arrived[i * od..(i + 1) * od].copy_from_slice(&reached[i * od..(i + 1) * od]);
                reward[i] = o.reward;
                cost[i] = o.cost;
                start[i] = o.done();
                prev_action[i * a..(i + 1) * a].copy_from_slice(&net_actions[i * a..(i + 1) * a]);
                if !active[i] {
                    continue;
                }
                steps += 1;
                let t = &mut trajs[i];
                t.next_obs.extend_from_slice(&arrived[i * od..(i + 1) * od]);
                t.rewards.push(o.reward);
                t.costs.push(o.cost);
                // Kept apart all the way into the TD targets (see make_batch).
                t.terminated.push(o.terminated);
                t.truncated.push(o.truncated);
                ep_ret[i] += o.reward;
                ep_cost[i] += o.cost;
                if o.done() {
                    t.episode_returns.push(ep_ret[i]);
                    t.episode_costs.push(ep_cost[i]);
                    t.episode_success.push(o.terminated);
                    ep_ret[i] = 0.0;
                    ep_cost[i] = 0.0;
                    if t.episode_returns.len() == ks[i] {
                        active[i] = false;
                    }
                }
            }
        }
        self.env_steps += steps;
        let (discovery_rate, revisit_rate, found) =
            search_rates(trajs.iter().map(|t| t.episode_success.as_slice()));
        let (action_abs, action_saturated) = if self.spec.n_actions.is_some() {
            (f64::NAN, f64::NAN)
        } else {
            let all = || {
                trajs
                    .iter()
                    .flat_map(|t| t.actions.iter().map(|&x| f64::from(x.abs())))
            };
            (
                mean(all()),
                mean(all().map(|x| if x > 0.99 { 1.0 } else { 0.0 })),
            )
        };
        let stats = RoundStats {
            action_abs,
            action_saturated,
            discovery_rate,
            revisit_rate,
            found,
            trajectories: n,
            steps,
            mean_return: mean(
                trajs
                    .iter()
                    .flat_map(|t| t.episode_returns.iter().map(|&x| f64::from(x))),
            ),
            mean_cost: mean(
                trajs
                    .iter()
                    .flat_map(|t| t.episode_costs.iter().map(|&x| f64::from(x))),
            ),
            first_return: mean(trajs.iter().map(|t| f64::from(t.episode_returns[0]))),
            last_return: mean(
                trajs
                    .iter()
                    .map(|t| f64::from(*t.episode_returns.last().unwrap_or(&0.0))),
            ),
            first_cost: mean(trajs.iter().map(|t| f64::from(t.episode_costs[0]))),
            last_cost: mean(
                trajs
                    .iter()
                    .map(|t| f64::from(*t.episode_costs.last().unwrap_or(&0.0))),
            ),
        };
        for t in trajs {
            self.replay.push(t);
        }
        Ok(stats)
    }

    /// One update on a batch sampled from the replay: Lv, Lc, Lp, then lambda
    /// (Eq. 7) and the Polyak targets.
    pub fn update(&mut self) -> Result<UpdateStats, EppoError> {
        // libtorch's generator (dropout, reparameterisation noise) is reseeded per
        // update, so a resumed run draws what the uninterrupted one would have.
        tch::manual_seed((self.cfg.seed ^ 0x5EED_0000).wrapping_add(self.updates) as i64);
        let trajs = self.replay.sample(self.cfg.batch_size, &mut self.rng);
        let batch = make_batch(&trajs, &self.cfg, &self.spec, &mut self.rng, self.device);
        let (lv, lc, lp, entropy, diag) =
            losses(&self.net, &self.target, &batch, self.lambda, &self.cfg)?;
        let loss = (&lv + &lc) * self.cfg.critic_weight + &lp;
        // A NaN or infinite loss or gradient is never applied: the weights
        // stay those of the last good update and `train` stops with this.
        let grad_norm = self
            .opt
            .try_backward_step(&loss)
            .map_err(|e| EppoError::NonFinite {
                update: self.updates + 1,
                what: format!(
                    "{e} (value loss {:.4e}, cost value loss {:.4e}, policy loss {:.4e})",
                    lv.double_value(&[]),
                    lc.double_value(&[]),
                    lp.double_value(&[])
                ),
                checkpoint: None,
            })?;
        if self.updates >= self.cfg.lambda_warmup_updates {
            self.lambda = lambda_update(
                self.lambda,
                &batch.max_violation,
                self.cfg.lambda_lr,
                self.cfg.lambda_max,
            );
        }
        polyak(&self.target_vs, &self.vs, self.cfg.tau);
        self.updates += 1;
        Ok(UpdateStats {
            value_loss: lv.double_value(&[]),
            cost_value_loss: lc.double_value(&[]),
            policy_loss: lp.double_value(&[]),
            entropy: entropy.double_value(&[]),
            grad_norm,
            lambda: self.lambda,
            q_mean: diag.q_mean.double_value(&[]),
            target_mean: diag.target_mean.double_value(&[]),
            log_std_mean: diag.log_std_mean.map_or(f64::NAN, |t| t.double_value(&[])),
        })
    }

    /// The model shape recorded in checkpoints (resume and loading check it).
    pub fn model_manifest(&self) -> serde_json::Value {
        model_manifest(&self.cfg, &self.spec)
    }

    /// Writes `checkpoints/step_{updates}` (weights, target weights, Adam
    /// moments, lambda, counters, RNG state, resolved config).
    pub fn save_checkpoint(&self, run: &RunDir) -> Result<PathBuf, EppoError> {
        let state = TrainState {
            lambda: self.lambda,
            updates: self.updates,
            env_steps: self.env_steps,
            rng_seed: self.rng.get_seed(),
            rng_stream: self.rng.get_stream(),
            rng_word_pos: self.rng.get_word_pos().to_string(),
            spec: self.spec.clone(),
            pretrain_tasks: Some(PretrainTasks::centre(
                self.cfg.seed,
                match self.cfg.task_pool {
                    0 => self.tasks_drawn,
                    pool => self.tasks_drawn.min(pool),
                },
            )),
            tasks_drawn: Some(self.tasks_drawn),
        };
        let config = toml::to_string(&self.cfg).map_err(|e| EppoError::Config(e.to_string()))?;
        let dir = run.write_checkpoint(
            self.updates,
            "eppo",
            self.env.as_str(),
            self.env
                .physics_steps_per_action(self.cfg.physics_steps_per_action),
            self.model_manifest(),
            self.cfg.keep_checkpoints,
            |dir| {
                let wrap = |path: PathBuf, e: String| CheckpointError::Invalid {
                    path,
                    problem: e,
                    fix: "check the disk".into(),
                };
                let p = dir.join("model.safetensors");
                self.vs
                    .save(&p)
                    .map_err(|e| wrap(p.clone(), e.to_string()))?;
                let p = dir.join("target.safetensors");
                self.target_vs
                    .save(&p)
                    .map_err(|e| wrap(p.clone(), e.to_string()))?;
                let p = dir.join("optimizer.safetensors");
                self.opt
                    .save(&p)
                    .map_err(|e| wrap(p.clone(), e.to_string()))?;
                let p = dir.join("state.json");
                let text = serde_json::to_string_pretty(&state)
                    .map_err(|e| wrap(p.clone(), e.to_string()))?;
                std::fs::write(&p, text).map_err(|e| wrap(p.clone(), e.to_string()))?;
                let p = dir.join("config.toml");
                std::fs::write(&p, &config).map_err(|e| wrap(p.clone(), e.to_string()))
            },
        )?;
        Ok(dir)
    }

    /// Restores a learner from a checkpoint folder written by
    /// [`Learner::save_checkpoint`], after checking it matches `cfg` and `env`.
    /// The replay buffer is not checkpointed: it refills from the resumed policy.
    pub fn resume(cfg: EppoConfig, env: EnvName, dir: &Path) -> Result<Self, EppoError> {
        let manifest = read_manifest(dir)?;
        let mut learner = Learner::new(cfg, env)?;
        manifest.check_compatible(
            dir,
            "eppo",
            env.as_str(),
            env.physics_steps_per_action(learner.cfg.physics_steps_per_action),
            &learner.model_manifest(),
        )?;
        let bad = |file: &str, e: String| {
            EppoError::Checkpoint(CheckpointError::Invalid {
                path: dir.join(file),
                problem: e,
                fix: "resume from an earlier checkpoints/step_N folder, or start a new run".into(),
            })
        };
        learner
            .vs
            .load(dir.join("model.safetensors"))
            .map_err(|e| bad("model.safetensors", e.to_string()))?;
        learner
            .target_vs
            .load(dir.join("target.safetensors"))
            .map_err(|e| bad("target.safetensors", e.to_string()))?;
        for (file, vs) in [
            ("model.safetensors", &learner.vs),
            ("target.safetensors", &learner.target_vs),
        ] {
            if let Some((name, n)) = crate::guard::non_finite_variable(vs) {
                return Err(bad(
                    file,
                    format!("weight {name} holds {n} NaN or infinite values"),
                ));
            }
        }
        learner
            .opt
            .load(&dir.join("optimizer.safetensors"))
            .map_err(|e| bad("optimizer.safetensors", e))?;
        let text = std::fs::read_to_string(dir.join("state.json"))
            .map_err(|e| bad("state.json", e.to_string()))?;
        let state: TrainState =
            serde_json::from_str(&text).map_err(|e| bad("state.json", e.to_string()))?;
        if state.spec != learner.spec {
            return Err(bad(
                "state.json",
                "the environment's spaces differ from the checkpoint's".into(),
            ));
        }
        learner.lambda = state.lambda;
        learner.updates = state.updates;
        learner.env_steps = state.env_steps;
        // Checkpoints from before tasks were recorded restart the count.
        let recorded = match &state.pretrain_tasks {
            None => 0,
            Some(tasks) => tasks.end.checked_sub(tasks.start).ok_or_else(|| {
                bad(
                    "state.json",
                    format!(
                        "pretrain_tasks end {} is before start {}",
                        tasks.end, tasks.start
                    ),
                )
            })?,
        };
        learner.tasks_drawn = state.tasks_drawn.unwrap_or(recorded);
        let mut rng = ChaCha8Rng::from_seed(state.rng_seed);
        rng.set_stream(state.rng_stream);
        rng.set_word_pos(
            state
                .rng_word_pos
                .parse::<u128>()
                .map_err(|e| bad("state.json", e.to_string()))?,
        );
        learner.rng = rng;
        Ok(learner)
    }
}

/// Counters and RNG state in `state.json`.
#[derive(Debug, Serialize, Deserialize)]
struct TrainState {
    lambda: f64,
    updates: u64,
    env_steps: u64,
    rng_seed: [u8; 32],
    rng_stream: u64,
    /// u128 as a decimal string (JSON numbers cannot hold it).
    rng_word_pos: String,
    spec: NetSpec,
    /// The pretraining tasks seen so far (absent in older checkpoints).
    #[serde(default)]
    pretrain_tasks: Option<PretrainTasks>,
    /// Tasks drawn so far (more than `pretrain_tasks` holds with a task pool).
    #[serde(default)]
    tasks_drawn: Option<u64>,
}

/// The pretraining tasks a checkpoint folder records having seen, if it does
/// (checkpoints written before tasks were recorded return `None`).
pub fn recorded_pretrain_tasks(dir: &Path) -> Result<Option<PretrainTasks>, EppoError> {
    let path = dir.join("state.json");
    let bad = |e: String| {
        EppoError::Checkpoint(CheckpointError::Invalid {
            path: path.clone(),
            problem: e,
            fix: "point at a complete checkpoints/step_N folder".into(),
        })
    };
    let text = std::fs::read_to_string(&path).map_err(|e| bad(e.to_string()))?;
    let state: TrainState = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
    Ok(state.pretrain_tasks)
}

fn model_manifest(cfg: &EppoConfig, spec: &NetSpec) -> serde_json::Value {
    serde_json::json!({
        // The token layout: checkpoints from before the arrived observation
        // was added read a narrower token and are refused by name.
        "token": "obs,arrived_obs,prev_action,reward,cost,ctg,start",
        "transformer": cfg.model,
        "encoder_hidden": cfg.encoder_hidden,
        "head_hidden": cfg.head_hidden,
        "n_critics": cfg.n_critics,
        "obs_dim": spec.obs_dim,
        "n_actions": spec.n_actions,
        "act_dim": spec.act_flat(),
    })
}

/// Options of one `icrl pretrain` run (the CLI fills it).
#[derive(Clone, Debug)]
pub struct PretrainOptions {
    pub env: EnvName,
    pub cfg: EppoConfig,
    /// Parent folder of run folders (`runs`).
    pub out: PathBuf,
    /// A run folder or checkpoint folder to continue from.
    pub resume: Option<PathBuf>,
    /// Draw a progress bar (off in tests).
    pub progress: bool,
}

/// What a finished run reports.
#[derive(Clone, Debug)]
pub struct PretrainReport {
    pub run_dir: PathBuf,
    pub last_checkpoint: PathBuf,
    pub updates: u64,
    pub env_steps: u64,
    pub lambda: f64,
    /// A uniformly random policy on the pretraining tasks, for scale.
    pub random: crate::run_summary::ReturnCost,
}

/// Algorithm 1: collect rounds of trajectories, update, checkpoint, log.
pub fn train(opts: &PretrainOptions) -> Result<PretrainReport, EppoError> {
    let (run, mut learner, resumed_from) = match &opts.resume {
        Some(path) => {
            let (run, ckpt) = RunDir::resolve_resume(path)?;
            let learner = Learner::resume(opts.cfg.clone(), opts.env, &ckpt)?;
            // Rounds logged after the checkpoint are redone: drop their records.
            crate::checkpoint::truncate_metrics(&run.metrics_path(), "updates", learner.updates)?;
            (run, learner, Some(ckpt))
        }
        None => {
            let learner = Learner::new(opts.cfg.clone(), opts.env)?;
            let run = RunDir::create(&opts.out, opts.env.as_str(), "eppo", opts.cfg.seed)?;
            (run, learner, None)
        }
    };
    let cfg = learner.cfg.clone();
    run.write_config(&toml::to_string(&cfg).map_err(|e| EppoError::Config(e.to_string()))?)?;
    let mut metrics = MetricsWriter::open(&run.metrics_path())?;
    let env_options = EnvOptions {
        max_episode_steps: Some(cfg.max_episode_steps),
        physics_steps_per_action: cfg.physics_steps_per_action,
    };
    // The scale the user reads progress against (seconds, even for Car).
    let random = crate::run_summary::random_policy(opts.env, &env_options, 100, cfg.seed)?;
    let mut recent = crate::run_summary::RecentRounds::new(50);
    let envs = (0..cfg.n_envs)
        .map(|_| make_env(opts.env, &env_options))
        .collect::<Result<Vec<_>, _>>()?;
    let mut venv = VecEnv::new(envs, cfg.env_threads, true)?;
    let bar = if opts.progress {
        let bar = indicatif::ProgressBar::new(cfg.total_updates);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{bar:30} {pos}/{len} updates [{elapsed_precise}<{eta_precise}] {msg}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        bar.set_position(learner.updates);
        bar
    } else {
        indicatif::ProgressBar::hidden()
    };
    // Without a terminal indicatif draws nothing: print the bar's line to
    // stderr instead, at most every 30 s, so logs show progress.
    let log_lines = opts.progress && bar.is_hidden();
    let mut last_log_line = Instant::now();
    // The checkpoint resumed from is the last good one (newer step folders, if
    // resuming an earlier one, belong to the abandoned continuation).
    let mut last_ckpt = resumed_from.unwrap_or_default();
    // A NaN update names the last good checkpoint (never one of NaN weights).
    let non_finite = |e: EppoError, last: &Path| match e {
        EppoError::NonFinite { update, what, .. } => EppoError::NonFinite {
            update,
            what,
            checkpoint: (!last.as_os_str().is_empty()).then(|| last.to_path_buf()),
        },
        other => other,
    };
    let started = Instant::now();
    let (start_updates, start_steps) = (learner.updates, learner.env_steps);
    while learner.updates < cfg.total_updates {
        let round = learner.collect(&mut venv)?;
        let mut stats = Vec::new();
        if learner.env_steps >= cfg.learning_starts {
            for _ in 0..cfg.updates_per_round {
                if learner.updates >= cfg.total_updates {
                    break;
                }
                stats.push(learner.update().map_err(|e| non_finite(e, &last_ckpt))?);
                bar.set_position(learner.updates);
                if learner.updates % cfg.checkpoint_every == 0 {
                    last_ckpt = learner.save_checkpoint(&run)?;
                }
                // First SIGINT/SIGTERM: stop after this update with a checkpoint.
                if crate::stop::requested() {
                    break;
                }
            }
        }
        let secs = started.elapsed().as_secs_f64().max(1e-9);
        let ups = (learner.updates - start_updates) as f64 / secs;
        let sps = (learner.env_steps - start_steps) as f64 / secs;
        let avg = |f: fn(&UpdateStats) -> f64| {
            if stats.is_empty() {
                f64::NAN
            } else {
                mean(stats.iter().map(f))
            }
        };
        let record = serde_json::json!({
            "env_steps": learner.env_steps,
            "updates": learner.updates,
            "episodic_return": round.mean_return,
            "episodic_cost": round.mean_cost,
            "first_episode_return": round.first_return,
            "last_episode_return": round.last_return,
            "first_episode_cost": round.first_cost,
            "last_episode_cost": round.last_cost,
            "discovery_rate": round.discovery_rate,
            "revisit_rate": round.revisit_rate,
            "found_goal": round.found,
            "lambda": learner.lambda,
            "losses/value_loss": avg(|s| s.value_loss),
            "losses/cost_value_loss": avg(|s| s.cost_value_loss),
            "losses/policy_loss": avg(|s| s.policy_loss),
            "losses/entropy": avg(|s| s.entropy),
            "losses/grad_norm": avg(|s| s.grad_norm),
            "losses/q_mean": avg(|s| s.q_mean),
            "losses/target_mean": avg(|s| s.target_mean),
            "losses/log_std_mean": avg(|s| s.log_std_mean),
            "charts/action_abs": round.action_abs,
            "charts/action_saturated": round.action_saturated,
            "charts/epsilon": learner.epsilon(),
            "charts/updates_per_s": ups,
            "charts/env_steps_per_s": sps,
        });
        metrics.write(&record)?;
        recent.push(
            round.mean_return,
            round.mean_cost,
            round.first_return,
            round.last_return,
        );
        let line = format!(
            "{}  lambda {:.3}  {ups:.2} upd/s",
            recent.progress_line(random),
            learner.lambda
        );
        if log_lines && last_log_line.elapsed().as_secs() >= 30 {
            eprintln!(
                "update {}/{}  env steps {}  {line}",
                learner.updates, cfg.total_updates, learner.env_steps
            );
            last_log_line = Instant::now();
        }
        bar.set_message(line);
        if crate::stop::requested() {
            if !last_ckpt.ends_with(format!("step_{}", learner.updates)) {
                last_ckpt = learner.save_checkpoint(&run)?;
            }
            bar.abandon();
            return Err(EppoError::Interrupted {
                checkpoint: last_ckpt,
                updates: learner.updates,
            });
        }
    }
    if !last_ckpt.ends_with(format!("step_{}", learner.updates)) {
        last_ckpt = learner.save_checkpoint(&run)?;
    }
    bar.finish();
    if opts.progress
        && let Err(e) = plot_learning_curve(&run.path, 10)
    {
        eprintln!("warning: {e}");
    }
    Ok(PretrainReport {
        run_dir: run.path.clone(),
        last_checkpoint: last_ckpt,
        updates: learner.updates,
        env_steps: learner.env_steps,
        lambda: learner.lambda,
        random,
    })
}

// ---------------------------------------------------------------------------
// Acting: shared by collection and the frozen agent
// ---------------------------------------------------------------------------

/// Per-batch acting state: the KV cache and each trajectory's CTG.
struct Acting {
    cache: KvCache,
    budgets: Vec<f32>,
    ctg: Vec<f32>,
    tokens: Vec<f32>,
    spec: NetSpec,
    cfg: EppoConfig,
}

/// The policy's output for B trajectories, on the CPU.
enum Policy {
    /// (B, A) probabilities.
    Discrete(Vec<f32>, usize),
    /// (B, A) means and log-stds.
    Continuous(Vec<f32>, Vec<f32>, usize),
}

enum EnvActions {
    Discrete(Vec<usize>),
    Continuous(Vec<f32>),
}

impl Acting {
    fn new(net: &EppoNet, spec: &NetSpec, cfg: &EppoConfig, budgets: &[f32]) -> Self {
        Acting {
            cache: net.new_cache(),
            budgets: budgets.to_vec(),
            ctg: budgets.to_vec(),
            tokens: Vec::new(),
            spec: spec.clone(),
            cfg: cfg.clone(),
        }
    }

    /// Updates each CTG from the step's input (restart at the budget on an
    /// episode's first step, else decrease by the cost just received) and
    /// returns the CTGs the policy sees.
    fn observe(&mut self, input: &StepInput<'_>) -> Vec<f32> {
        for i in 0..self.budgets.len() {
            self.ctg[i] = if input.episode_start[i] {
                self.budgets[i]
            } else {
                self.ctg[i] - input.cost[i]
            };
        }
        self.ctg.clone()
    }

    /// Encodes one step of B trajectories through the cache; returns the policy.
    fn policy(&mut self, net: &EppoNet, input: &StepInput<'_>) -> Result<Policy, EppoError> {
        let b = self.budgets.len();
        let (od, a) = (self.spec.obs_dim, self.spec.act_flat());
        self.tokens.clear();
        for i in 0..b {
            push_token(
                &self.spec,
                &self.cfg,
                &mut self.tokens,
                &input.obs[i * od..(i + 1) * od],
                &input.arrived_obs[i * od..(i + 1) * od],
                &input.prev_action[i * a..(i + 1) * a],
                input.reward[i],
                input.cost[i],
                self.ctg[i],
                input.episode_start[i],
            );
        }
        let device = net.enc_1.ws.device();
        let x = Tensor::from_slice(&self.tokens)
            .view([b as i64, 1, self.spec.token_dim() as i64])
            .to_device(device); // (B, 1, token_dim)
        tch::no_grad(|| {
            let h = net.encode_step(&x, &mut self.cache)?.squeeze_dim(1); // (B, 1, D) -> (B, D)
            Ok(match self.spec.n_actions {
                Some(n) => {
                    let p = net
                        .actor
                        .forward(&h)
                        .softmax(-1, Kind::Float)
                        .to_device(Device::Cpu);
                    Policy::Discrete(Vec::<f32>::try_from(&p.view([-1]))?, n)
                }
                None => {
                    let (m, s) = net.gaussian(&h);
                    let m = Vec::<f32>::try_from(&m.to_device(Device::Cpu).reshape([-1]))?;
                    let s = Vec::<f32>::try_from(&s.to_device(Device::Cpu).reshape([-1]))?;
                    Policy::Continuous(m, s, a)
                }
            })
        })
    }
}

/// Picks actions: sampled (epsilon-greedy on top for discrete, row i with
/// probability `eps[i]`; rows past the slice take none) or the mode. Returns the actions as the network sees them and as the environment takes them.
fn sample_actions(
    policy: &Policy,
    spec: &NetSpec,
    eps: &[f64],
    greedy: bool,
    rng: &mut ChaCha8Rng,
) -> (Vec<f32>, EnvActions) {
    match policy {
        Policy::Discrete(p, n) => {
            let n = *n;
            let b = p.len() / n;
            let mut onehot = vec![0f32; b * n];
            let idx: Vec<usize> = (0..b)
                .map(|i| {
                    let row = &p[i * n..(i + 1) * n];
                    let k = if greedy {
                        row.iter()
                            .enumerate()
                            .fold(0, |best, (k, &x)| if x > row[best] { k } else { best })
                    } else if rng.r#gen::<f64>() < eps.get(i).copied().unwrap_or(0.0) {
                        rng.gen_range(0..n)
                    } else {
                        let u: f32 = rng.r#gen();
                        let mut acc = 0.0;
                        row.iter()
                            .position(|&x| {
                                acc += x;
                                u < acc
                            })
                            .unwrap_or(n - 1)
                    };
                    onehot[i * n + k] = 1.0;
                    k
                })
                .collect();
            (onehot, EnvActions::Discrete(idx))
        }
        Policy::Continuous(m, s, a) => {
            let mut net = Vec::with_capacity(m.len());
            let mut env = Vec::with_capacity(m.len());
            for (j, (&mu, &log_std)) in m.iter().zip(s).enumerate() {
                let z = if greedy {
                    0.0
                } else {
                    rng.sample::<f32, _>(rand_distr::StandardNormal)
                };
                let x = (mu + log_std.exp() * z).tanh();
                let k = j % a;
                let (lo, hi) = (spec.act_low[k], spec.act_high[k]);
                net.push(x);
                env.push(lo + (x + 1.0) * 0.5 * (hi - lo));
            }
            (net, EnvActions::Continuous(env))
        }
    }
}

// ---------------------------------------------------------------------------
// The frozen agent for evaluation
// ---------------------------------------------------------------------------

/// A pretrained EPPO policy, frozen, acting through the KV cache.
pub struct EppoAgent {
    _vs: nn::VarStore,
    net: EppoNet,
    spec: NetSpec,
    cfg: EppoConfig,
    acting: Option<Acting>,
    rng: ChaCha8Rng,
}

impl EppoAgent {
    /// Loads `checkpoints/step_N` (or a run folder: its latest checkpoint) onto `device`.
    pub fn load(path: &Path, device: Device) -> Result<Self, EppoError> {
        let dir = if path.join(crate::checkpoint::MANIFEST).is_file() {
            path.to_path_buf()
        } else {
            RunDir::resolve_resume(path)?.1
        };
        let manifest = read_manifest(&dir)?;
        let bad = |file: &str, e: String| {
            EppoError::Checkpoint(CheckpointError::Invalid {
                path: dir.join(file),
                problem: e,
                fix: "load a checkpoint written by `icrl pretrain` (method eppo)".into(),
            })
        };
        if manifest.method != "eppo" {
            return Err(bad(
                crate::checkpoint::MANIFEST,
                format!("method is {:?}, not eppo", manifest.method),
            ));
        }
        let text = std::fs::read_to_string(dir.join("config.toml"))
            .map_err(|e| bad("config.toml", e.to_string()))?;
        let mut cfg: EppoConfig =
            toml::from_str(&text).map_err(|e| bad("config.toml", e.to_string()))?;
        cfg.device = if device == Device::Cpu {
            "cpu".into()
        } else {
            "cuda".into()
        };
        let text = std::fs::read_to_string(dir.join("state.json"))
            .map_err(|e| bad("state.json", e.to_string()))?;
        let state: TrainState =
            serde_json::from_str(&text).map_err(|e| bad("state.json", e.to_string()))?;
        // The files decide sizes: check them before building anything.
        cfg.validate()
            .map_err(|e| bad("config.toml", e.to_string()))?;
        state.spec.check().map_err(|e| bad("state.json", e))?;
        memory_estimate(&cfg, &state.spec)
            .check()
            .map_err(|e| bad("config.toml", e))?;
        // The manifest's model must be what this version builds from the
        // stored config: a checkpoint from before a token-layout change is
        // refused by name instead of failing on a tensor shape.
        manifest
            .check_compatible(
                &dir,
                "eppo",
                &manifest.env,
                // The macro action is the checkpoint's own (read_manifest
                // refuses Point and Car checkpoints that do not record it).
                manifest.physics_steps_per_action,
                &model_manifest(&cfg, &state.spec),
            )
            .map_err(|e| {
                bad(
                    crate::checkpoint::MANIFEST,
                    format!("{e} (checkpoints written before the token layout changed must be retrained)"),
                )
            })?;
        let mut vs = nn::VarStore::new(device);
        let net = EppoNet::new(vs.root(), &cfg, &state.spec)?;
        vs.load(dir.join("model.safetensors"))
            .map_err(|e| bad("model.safetensors", e.to_string()))?;
        if let Some((name, n)) = crate::guard::non_finite_variable(&vs) {
            return Err(bad(
                "model.safetensors",
                format!("weight {name} holds {n} NaN or infinite values: this model cannot act"),
            ));
        }
        vs.freeze();
        Ok(EppoAgent {
            _vs: vs,
            net,
            spec: state.spec,
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            cfg,
            acting: None,
        })
    }

    /// The training configuration stored with the checkpoint.
    pub fn config(&self) -> &EppoConfig {
        &self.cfg
    }

    /// Reseeds action sampling.
    pub fn set_seed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }
}

impl InContextAgent for EppoAgent {
    fn reset(&mut self, conditioning: &[Conditioning]) -> Result<(), AgentError> {
        let budgets = conditioning
            .iter()
            .map(|c| match c {
                Conditioning::Budget { ctg } => Ok(*ctg),
                Conditioning::Targets { .. } => Err(AgentError::Input(
                    "EPPO is conditioned on a budget, not on RTG/CTG targets".into(),
                )),
            })
            .collect::<Result<Vec<f32>, _>>()?;
        self.acting = Some(Acting::new(&self.net, &self.spec, &self.cfg, &budgets));
        Ok(())
    }

    fn act(&mut self, input: &StepInput<'_>, greedy: bool) -> Result<Actions, AgentError> {
        let acting = self
            .acting
            .as_mut()
            .ok_or_else(|| AgentError::Input("act before reset".into()))?;
        let b = acting.budgets.len();
        let (od, a) = (self.spec.obs_dim, self.spec.act_flat());
        let sizes = [
            ("obs", input.obs.len(), b * od),
            ("arrived_obs", input.arrived_obs.len(), b * od),
            ("prev_action", input.prev_action.len(), b * a),
            ("reward", input.reward.len(), b),
            ("cost", input.cost.len(), b),
            ("episode_start", input.episode_start.len(), b),
        ];
        for (name, got, want) in sizes {
            if got != want {
                return Err(AgentError::Input(format!(
                    "{name} has {got} entries, expected {want}"
                )));
            }
        }
        // Continuous previous actions arrive in the environment's scale; the
        // network saw them in [-1, 1].
        let prev: Vec<f32> = match self.spec.n_actions {
            Some(_) => input.prev_action.to_vec(),
            None => input
                .prev_action
                .iter()
                .enumerate()
                .map(|(j, &x)| {
                    let (lo, hi) = (self.spec.act_low[j % a], self.spec.act_high[j % a]);
                    if hi > lo {
                        2.0 * (x - lo) / (hi - lo) - 1.0
                    } else {
                        x
                    }
                })
                .collect(),
        };
        let input = StepInput {
            prev_action: &prev,
            ..*input
        };
        acting.observe(&input);
        let policy = acting.policy(&self.net, &input).map_err(|e| match e {
            EppoError::Torch(t) => AgentError::Torch(t),
            other => AgentError::Input(other.to_string()),
        })?;
        let (_, env_actions) = sample_actions(&policy, &self.spec, &[], greedy, &mut self.rng);
        Ok(match env_actions {
            EnvActions::Discrete(v) => Actions::Discrete(v),
            EnvActions::Continuous(v) => Actions::Continuous(v),
        })
    }
}

// ---------------------------------------------------------------------------
// The `pretrain` subcommand's body
// ---------------------------------------------------------------------------

/// Resolves the configuration and runs [`train`]: a new run from the preset
/// `eppo-{env}-{preset}`, or with `resume` the run's own `config.toml`; the
/// `sets` overrides (`key=value`) apply on top in both cases.
pub fn pretrain_command(
    env: &str,
    preset: &str,
    resume: Option<&Path>,
    sets: &[String],
    out: &Path,
) -> Result<PretrainReport, EppoError> {
    let env_name: EnvName = env.parse().map_err(|e| EppoError::Config(format!("{e}")))?;
    let cfg_err = |e: crate::presets::PresetError| EppoError::Config(e.to_string());
    let (name, mut table) = match resume {
        Some(path) => {
            let (run, _) = RunDir::resolve_resume(path)?;
            let p = run.config_path();
            let text = std::fs::read_to_string(&p).map_err(|e| CheckpointError::Io {
                path: p.clone(),
                source: e,
            })?;
            let table = text.parse::<toml::Table>().map_err(|e| {
                EppoError::Checkpoint(CheckpointError::Invalid {
                    path: p.clone(),
                    problem: e.to_string(),
                    fix: "restore the run's config.toml or start a new run".into(),
                })
            })?;
            (p.display().to_string(), table)
        }
        None => (
            format!("eppo-{env}-{preset}"),
            crate::presets::preset_table("eppo", env, preset).map_err(cfg_err)?,
        ),
    };
    crate::presets::apply_overrides(&mut table, sets).map_err(cfg_err)?;
    let cfg: EppoConfig = crate::presets::resolve(&name, table).map_err(cfg_err)?;
    let opts = PretrainOptions {
        env: env_name,
        cfg,
        out: out.to_path_buf(),
        resume: resume.map(Path::to_path_buf),
        progress: true,
    };
    train(&opts)
}

/// Draws the learning curves of a run from its `metrics.jsonl` into
/// `<run>/learning_curve.png`: episodic return (all episodes, first and last
/// episode of each trajectory), episodic cost (same three) and lambda against
/// environment steps, each a moving average over `window` records. Text uses
/// DejaVu Sans (or the `.ttf` named by `ICRL_FONT`).
pub fn plot_learning_curve(run_dir: &Path, window: usize) -> Result<PathBuf, EppoError> {
    use plotters::prelude::*;
    let path = run_dir.join("metrics.jsonl");
    let text = std::fs::read_to_string(&path).map_err(|e| CheckpointError::Io {
        path: path.clone(),
        source: e,
    })?;
    let records: Vec<serde_json::Value> = text
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect();
    let smooth = |key: &str| -> Vec<(f64, f64)> {
        let xs: Vec<(f64, f64)> = records
            .iter()
            .filter_map(|r| Some((r.get("env_steps")?.as_f64()?, r.get(key)?.as_f64()?)))
            .collect();
        (0..xs.len())
            .map(|i| {
                let win = &xs[i.saturating_sub(window.max(1) - 1)..=i];
                (
                    xs[i].0,
                    win.iter().map(|p| p.1).sum::<f64>() / win.len() as f64,
                )
            })
            .collect()
    };
    let font_path = std::env::var("ICRL_FONT")
        .unwrap_or_else(|_| "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf".into());
    let font_err = |e: String| EppoError::Config(format!("learning curve: font {font_path}: {e}"));
    let bytes = std::fs::read(&font_path).map_err(|e| font_err(e.to_string()))?;
    // plotters keeps a 'static reference: the font lives for the process.
    let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
    plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
        .map_err(|_| font_err("not a TrueType font".into()))?;
    let out = run_dir.join("learning_curve.png");
    let draw_err = |e: String| EppoError::Config(format!("learning curve {}: {e}", out.display()));
    let colours = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
    ];
    /// (title, y label, [(metric, legend)]).
    type PanelSpec<'a> = (&'a str, &'a str, Vec<(&'a str, &'a str)>);
    let panels: [PanelSpec; 3] = [
        (
            "return (training tasks)",
            "episode return",
            vec![
                ("episodic_return", "all episodes"),
                ("first_episode_return", "first episode"),
                ("last_episode_return", "last episode"),
            ],
        ),
        (
            "cost (training tasks)",
            "episode cost",
            vec![
                ("episodic_cost", "all episodes"),
                ("first_episode_cost", "first episode"),
                ("last_episode_cost", "last episode"),
            ],
        ),
        ("Lagrange multiplier", "lambda", vec![("lambda", "lambda")]),
    ];
    let root = BitMapBackend::new(&out, (1500, 450)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| draw_err(e.to_string()))?;
    for ((title, y_label, keys), area) in panels.iter().zip(root.split_evenly((1, 3))) {
        let curves: Vec<(&str, Vec<(f64, f64)>)> =
            keys.iter().map(|(k, l)| (*l, smooth(k))).collect();
        let all = curves.iter().flat_map(|c| c.1.iter());
        let (x_max, y_min, y_max) = all.fold((1.0f64, 0.0f64, 1e-3f64), |(a, b, c), p| {
            (a.max(p.0), b.min(p.1), c.max(p.1))
        });
        let mut chart = ChartBuilder::on(&area)
            .caption(*title, ("sans-serif", 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(50)
            .build_cartesian_2d(0.0..x_max, y_min..y_max * 1.05)
            .map_err(|e| draw_err(e.to_string()))?;
        chart
            .configure_mesh()
            .x_desc("environment steps")
            .y_desc(*y_label)
            .x_labels(5)
            .x_label_formatter(&|x| format!("{:.0}k", x / 1000.0))
            .draw()
            .map_err(|e| draw_err(e.to_string()))?;
        for (i, (label, points)) in curves.into_iter().enumerate() {
            let c = colours[i % colours.len()];
            chart
                .draw_series(LineSeries::new(points, c.stroke_width(2)))
                .map_err(|e| draw_err(e.to_string()))?
                .label(label)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], c.stroke_width(2))
                });
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| draw_err(e.to_string()))?;
    }
    root.present().map_err(|e| draw_err(e.to_string()))?;
    drop(root);
    Ok(out)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::model::Positions;

    /// A tiny configuration: trajectories of 2 episodes of 6 steps (also
    /// used by the evaluation tests).
    pub(crate) fn tiny() -> EppoConfig {
        let mut table = crate::presets::preset_table("eppo", "darkroom", "quick").unwrap();
        let sets = [
            "max_episode_steps=6",
            "k_min=2",
            "k_max=2",
            "n_envs=3",
            "batch_size=3",
            "replay_capacity=1000",
            "encoder_hidden=16",
            "head_hidden=16",
            "model.d_model=16",
            "model.n_heads=2",
            "model.n_layers=1",
            "model.d_ff=32",
            "model.max_len=12",
            "total_updates=4",
            "updates_per_round=2",
            "learning_starts=0",
            "checkpoint_every=2",
        ]
        .map(String::from);
        crate::presets::apply_overrides(&mut table, &sets).unwrap();
        crate::presets::resolve("tiny", table).unwrap()
    }

    fn tiny_learner(seed: u64) -> (Learner, VecEnv) {
        let mut cfg = tiny();
        cfg.seed = seed;
        let learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
        let envs = (0..cfg.n_envs)
            .map(|_| {
                make_env(
                    EnvName::DarkRoom,
                    &EnvOptions {
                        max_episode_steps: Some(cfg.max_episode_steps),
                        physics_steps_per_action: cfg.physics_steps_per_action,
                    },
                )
                .unwrap()
            })
            .collect();
        (learner, VecEnv::new(envs, 1, true).unwrap())
    }

    fn to_vec(t: &Tensor) -> Vec<f32> {
        Vec::<f32>::try_from(&t.to_kind(Kind::Float).view([-1])).unwrap()
    }

    #[test]
    fn collected_trajectories_follow_algorithm_1() {
        let (mut learner, mut venv) = tiny_learner(0);
        let stats = learner.collect(&mut venv).unwrap();
        assert_eq!(stats.trajectories, 3);
        assert_eq!(learner.replay.len(), 3);
        for t in &learner.replay.trajectories {
            assert_eq!(t.episode_returns.len(), 2, "K = 2 episodes");
            assert!(t.budget >= 1.0 && t.budget <= 15.0);
            assert!(t.len() <= 12 && t.start[0]);
            for s in 0..t.len() {
                // CTG restarts at the budget each episode and decreases by costs.
                let expected = if t.start[s] {
                    t.budget
                } else {
                    t.ctg[s - 1] - t.costs[s - 1]
                };
                assert_eq!(t.ctg[s], expected, "step {s}");
                assert!(!(t.terminated[s] && t.truncated[s]));
                assert_eq!(
                    t.terminated[s],
                    t.rewards[s] > 0.0,
                    "the goal reward ends the episode"
                );
            }
            let ends = (0..t.len())
                .filter(|&s| t.terminated[s] || t.truncated[s])
                .count();
            assert_eq!(ends, 2);
        }
    }

    #[test]
    fn the_goal_enters_the_context_with_its_reward() {
        // One fixed task (the ladder's first rung): collect until an episode
        // ends at the goal, then look at the token after it.
        let mut cfg = tiny();
        cfg.task_pool = 1;
        let mut learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
        let goal = sample_task(
            &spawn_config(EnvName::DarkRoom),
            Orientation::Centre,
            pretrain_task_seed(cfg.seed, 0),
        )
        .unwrap()
        .goal;
        let goal_obs = [goal.row as f32, goal.col as f32];
        let (_, mut venv) = tiny_learner(0);
        let mut checked = 0;
        for _ in 0..300 {
            learner.collect(&mut venv).unwrap();
            if learner
                .replay
                .trajectories
                .iter()
                .any(|t| t.terminated.contains(&true))
            {
                break;
            }
        }
        let norm = |x: f32| 2.0 * x / 8.0 - 1.0; // 9x9 grid: [0, 8] -> [-1, 1]
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        for t in &learner.replay.trajectories {
            let batch = make_batch(&[t], &cfg, &learner.spec, &mut rng, Device::Cpu);
            let tok = to_vec(&batch.tokens);
            let d = learner.spec.token_dim();
            for s in (0..t.len() - 1).filter(|&s| t.terminated[s]) {
                assert_eq!(&t.next_obs[2 * s..2 * s + 2], &goal_obs, "step {s}");
                let next = &tok[(s + 1) * d..(s + 2) * d];
                // The token carrying reward 1: the new episode's start as the
                // observation, the goal as where the last action arrived.
                assert_eq!(next[2..4], [norm(goal_obs[0]), norm(goal_obs[1])]);
                assert_eq!(next[0..2], [0.0, 0.0], "the centre start");
                assert_eq!(next[2 + 2 + 5], 10.0, "reward x reward_scale");
                assert_eq!(next[d - 1], 1.0, "episode start flag");
                checked += 1;
            }
        }
        // A pool of one: every goal reached above was the same task's.
        assert!(checked > 0, "no episode reached the goal in 300 rounds");
    }

    #[test]
    fn exploration_is_bilevel() {
        let mut cfg = tiny();
        cfg.eps_start = 1.0;
        cfg.eps_end = 0.4;
        cfg.eps_last_start = Some(0.6);
        cfg.eps_last_end = Some(0.0);
        cfg.eps_decay_steps = 1000;
        let start = cfg.exploration(0);
        assert_eq!((start.first, start.last), (1.0, 0.6));
        let mid = cfg.exploration(500);
        assert!((mid.first - 0.7).abs() < 1e-12 && (mid.last - 0.3).abs() < 1e-12);
        let end = cfg.exploration(10_000);
        assert!(
            (end.first - 0.4).abs() < 1e-12 && end.last == 0.0,
            "annealed, then held"
        );
        // Inside a trajectory: linear from the first to the last step, scaled.
        assert!((end.at(0, 100, 1.0) - 0.4).abs() < 1e-12);
        assert!((end.at(50, 100, 1.0) - 0.2).abs() < 1e-12);
        assert!(end.at(100, 100, 1.0).abs() < 1e-12);
        assert!((end.at(0, 100, 0.5) - 0.2).abs() < 1e-12);
        // Without the last-step values, epsilon is flat inside a trajectory.
        cfg.eps_last_start = None;
        cfg.eps_last_end = None;
        let flat = cfg.exploration(500);
        assert_eq!(flat.first, flat.last);
        // An epsilon outside [0, 1] is refused by name.
        assert!(cfg.validate().is_ok());
        cfg.eps_last_end = Some(1.5);
        assert!(
            cfg.validate()
                .unwrap_err()
                .to_string()
                .contains("eps_last_end")
        );
    }

    #[test]
    fn search_rates_count_discovery_and_revisits() {
        let a = [false, true, true, false];
        let b = [false, false, false, false];
        let c = [true, true, false, true];
        let (disc, rev, found) = search_rates([&a[..], &b[..], &c[..]].into_iter());
        // After episode 1: a discovers at 2 (1 of a's 1 undiscovered tries),
        // b never (3 tries); a revisits 1 of 2, c 2 of 3.
        assert!((disc - 1.0 / 4.0).abs() < 1e-12, "{disc}");
        assert!((rev - 3.0 / 5.0).abs() < 1e-12, "{rev}");
        assert!((found - 2.0 / 3.0).abs() < 1e-12);
        assert!(search_rates([&b[..1]].into_iter()).0.is_nan());
    }

    #[test]
    fn critic_losses_fall_on_a_fixed_batch() {
        let (mut learner, mut venv) = tiny_learner(1);
        learner.collect(&mut venv).unwrap();
        let trajs: Vec<&Trajectory> = learner.replay.trajectories.iter().collect();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let batch = make_batch(&trajs, &learner.cfg, &learner.spec, &mut rng, Device::Cpu);
        let mut first = None;
        let mut last = (0.0, 0.0);
        for _ in 0..300 {
            let (lv, lc, ..) =
                losses(&learner.net, &learner.target, &batch, 0.0, &learner.cfg).unwrap();
            let now = (lv.double_value(&[]), lc.double_value(&[]));
            first.get_or_insert(now);
            last = now;
            learner.opt.backward_step(&(lv + lc));
        }
        let first = first.unwrap();
        assert!(last.0 < 0.3 * first.0, "value loss {first:?} -> {last:?}");
        assert!(
            last.1 < 0.3 * first.1 || last.1 < 1e-3,
            "cost value loss {first:?} -> {last:?}"
        );
    }

    #[test]
    fn lambda_rises_falls_and_respects_the_cap() {
        let mut lambda = 0.0;
        let mut seen = vec![];
        for _ in 0..50 {
            lambda = lambda_update(lambda, &[3.0, -1.0, 4.0], 0.1, 1.5);
            seen.push(lambda);
        }
        assert!(
            seen.windows(2).take(5).all(|w| w[1] > w[0]),
            "rises while costs exceed the budget"
        );
        assert_eq!(lambda, 1.5, "capped");
        assert!(seen.iter().all(|&l| l <= 1.5));
        for _ in 0..50 {
            lambda = lambda_update(lambda, &[-2.0, -0.5], 0.1, 1.5);
        }
        assert_eq!(
            lambda, 0.0,
            "falls back to 0 once every episode is within budget"
        );
        // Eq. (7) takes the worst episode of each trajectory, then the mean.
        let t = Trajectory {
            budget: 2.0,
            episode_costs: vec![1.0, 5.0, 0.0],
            ..Default::default()
        };
        assert_eq!(t.max_violation(), 3.0);
    }

    #[test]
    fn violation_flag_gates_the_cost_penalty() {
        let (mut learner, mut venv) = tiny_learner(2);
        learner.collect(&mut venv).unwrap();
        let trajs: Vec<&Trajectory> = learner.replay.trajectories.iter().collect();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut batch = make_batch(&trajs, &learner.cfg, &learner.spec, &mut rng, Device::Cpu);
        let policy_loss = |batch: &Batch, lambda: f64| {
            tch::manual_seed(0);
            let (_, _, lp, ..) =
                losses(&learner.net, &learner.target, batch, lambda, &learner.cfg).unwrap();
            lp.double_value(&[])
        };
        batch.violated = batch.valid.zeros_like();
        let (clean_0, clean_5) = (policy_loss(&batch, 0.0), policy_loss(&batch, 5.0));
        assert!(
            (clean_0 - clean_5).abs() < 1e-4,
            "no violation: lambda has no effect"
        );
        batch.violated = batch.valid.ones_like();
        let (viol_0, viol_5) = (policy_loss(&batch, 0.0), policy_loss(&batch, 5.0));
        assert!((viol_0 - clean_0).abs() < 1e-4);
        assert!(
            (viol_5 - viol_0).abs() > 1e-4,
            "violated episodes pay lambda * Qc"
        );
    }

    #[test]
    fn terminated_and_truncated_reach_the_targets_apart() {
        let cfg = tiny();
        let spec = NetSpec {
            obs_dim: 1,
            obs_low: vec![0.0],
            obs_high: vec![1.0],
            n_actions: Some(2),
            act_low: vec![],
            act_high: vec![],
        };
        // Episode 0: 2 steps, truncated at 0.9. Episode 1: 2 steps,
        // terminated at the goal, 1.0.
        let t = Trajectory {
            budget: 1.0,
            obs: vec![0.0, 0.25, 0.5, 0.75],
            next_obs: vec![0.25, 0.9, 0.75, 1.0],
            actions: vec![1.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 1.0],
            action_idx: vec![0, 0, 1, 1],
            rewards: vec![0.0, 0.0, 0.0, 1.0],
            costs: vec![1.0, 1.0, 0.0, 0.0],
            ctg: vec![1.0, 0.0, 1.0, 1.0],
            start: vec![true, false, true, false],
            terminated: vec![false, false, false, true],
            truncated: vec![false, true, false, false],
            episode: vec![0, 0, 1, 1],
            episode_returns: vec![0.0, 1.0],
            episode_costs: vec![2.0, 0.0],
            episode_success: vec![false, true],
        };
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut across = cfg.clone();
        across.bootstrap_across_episodes = true;
        let b = make_batch(&[&t], &across, &spec, &mut rng, Device::Cpu);
        assert_eq!(to_vec(&b.bootstrap), vec![1.0, 1.0, 1.0, 0.0]);
        // The cost's target stops at every episode end: episode 0's costs
        // are not charged with episode 1's.
        assert_eq!(to_vec(&b.cost_bootstrap), vec![1.0, 0.0, 1.0, 0.0]);
        assert_eq!(to_vec(&b.td_valid), vec![1.0, 1.0, 1.0, 1.0]);
        assert_eq!(
            to_vec(&b.violated),
            vec![1.0, 1.0, 0.0, 0.0],
            "v_e per episode: 2 > 1, 0 <= 1"
        );
        let mut within = cfg;
        within.bootstrap_across_episodes = false;
        let b = make_batch(&[&t], &within, &spec, &mut rng, Device::Cpu);
        // Truncated: no target (its final state is not a token); terminated: r alone.
        assert_eq!(to_vec(&b.td_valid), vec![1.0, 0.0, 1.0, 1.0]);
        assert_eq!(to_vec(&b.bootstrap), vec![1.0, 0.0, 1.0, 0.0]);
        // Tokens carry the observation, the observation the previous action
        // arrived at, the previous action, reward, cost, CTG and start flag.
        let tok = to_vec(&b.tokens);
        let d = spec.token_dim();
        assert_eq!(
            &tok[3 * d..4 * d],
            &[0.5, 0.5, 0.0, 1.0, 0.0, 0.0, 1.0 / 15.0, 0.0]
        );
        // An episode's first token shows where the last one ended (0.9 -> 0.8
        // normalised), not only the new start (0.5 -> 0).
        assert_eq!(tok[2 * d], 0.0);
        assert!((tok[2 * d + 1] - 0.8).abs() < 1e-6, "{}", tok[2 * d + 1]);
        assert_eq!(
            &tok[..2],
            &[-1.0, -1.0],
            "nothing arrived before the first step"
        );
    }

    #[test]
    fn acting_through_the_cache_matches_the_full_forward() {
        let (mut learner, mut venv) = tiny_learner(3);
        learner.collect(&mut venv).unwrap();
        let t = learner.replay.trajectories[0].clone();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let batch = make_batch(&[&t], &learner.cfg, &learner.spec, &mut rng, Device::Cpu);
        let full = tch::no_grad(|| {
            learner
                .net
                .actor
                .forward(&learner.net.encode(&batch.tokens, false).unwrap())
        })
        .softmax(-1, Kind::Float); // (1, T, A)
        let mut acting = Acting::new(&learner.net, &learner.spec, &learner.cfg, &[t.budget]);
        let (od, a) = (learner.spec.obs_dim, learner.spec.act_flat());
        for s in 0..t.len() {
            let zeros = vec![0f32; a];
            let (prev, r, c) = if s == 0 {
                (&zeros[..], 0.0, 0.0)
            } else {
                (
                    &t.actions[(s - 1) * a..s * a],
                    t.rewards[s - 1],
                    t.costs[s - 1],
                )
            };
            let zeros_o = vec![0f32; od];
            let arrived = if s == 0 {
                &zeros_o[..]
            } else {
                &t.next_obs[(s - 1) * od..s * od]
            };
            let input = StepInput {
                obs: &t.obs[s * od..(s + 1) * od],
                arrived_obs: arrived,
                prev_action: prev,
                reward: &[r],
                cost: &[c],
                episode_start: &[t.start[s]],
            };
            assert_eq!(acting.observe(&input), vec![t.ctg[s]]);
            let Policy::Discrete(p, _) = acting.policy(&learner.net, &input).unwrap() else {
                panic!()
            };
            let expected = to_vec(&full.narrow(1, s as i64, 1));
            for (x, y) in p.iter().zip(&expected) {
                assert!((x - y).abs() < 1e-5, "step {s}: {p:?} vs {expected:?}");
            }
        }
    }

    #[test]
    fn same_seed_same_run_on_cpu() {
        let run = |seed| {
            let (mut learner, mut venv) = tiny_learner(seed);
            let mut out = vec![];
            for _ in 0..2 {
                let r = learner.collect(&mut venv).unwrap();
                out.push(r.mean_cost);
                let u = learner.update().unwrap();
                out.extend([u.value_loss, u.cost_value_loss, u.policy_loss, u.lambda]);
            }
            let w = learner.vs.variables()["transformer.h.0.attn.c_attn.weight"]
                .sum(Kind::Float)
                .double_value(&[]);
            out.push(w);
            out
        };
        tch::set_num_threads(1);
        assert_eq!(run(5), run(5));
        assert_ne!(run(5), run(6));
    }

    #[test]
    fn continuous_shapes_and_gradients() {
        let mut cfg = tiny();
        cfg.model.positions = Positions::Learned;
        let spec = NetSpec {
            obs_dim: 3,
            obs_low: vec![f32::NEG_INFINITY; 3],
            obs_high: vec![f32::INFINITY; 3],
            n_actions: None,
            act_low: vec![-1.0, -1.0],
            act_high: vec![1.0, 1.0],
        };
        let vs = nn::VarStore::new(Device::Cpu);
        let net = EppoNet::new(vs.root(), &cfg, &spec).unwrap();
        let tvs = nn::VarStore::new(Device::Cpu);
        let target = EppoNet::new(tvs.root(), &cfg, &spec).unwrap();
        let n = 5;
        let t = Trajectory {
            budget: 10.0,
            obs: (0..n * 3).map(|i| i as f32 * 0.1).collect(),
            next_obs: (3..n * 3 + 3).map(|i| i as f32 * 0.1).collect(),
            actions: (0..n * 2).map(|i| (i as f32 * 0.37).sin()).collect(),
            action_idx: vec![],
            rewards: vec![0.0, 0.0, 0.0, 0.0, 1.0],
            costs: vec![0.0, 1.0, 1.0, 0.0, 0.0],
            ctg: vec![10.0, 10.0, 9.0, 8.0, 8.0],
            start: vec![true, false, false, false, false],
            terminated: vec![false, false, false, false, true],
            truncated: vec![false; 5],
            episode: vec![0; 5],
            episode_returns: vec![1.0],
            episode_costs: vec![2.0],
            episode_success: vec![true],
        };
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let batch = make_batch(&[&t, &t], &cfg, &spec, &mut rng, Device::Cpu);
        assert_eq!(batch.tokens.size(), vec![2, 5, 3 + 3 + 2 + 4]);
        assert_eq!(batch.actions.size(), vec![2, 5, 2]);
        let (lv, lc, lp, ..) = losses(&net, &target, &batch, 1.0, &cfg).unwrap();
        let mut opt = Adam::new(
            &vs,
            AdamConfig {
                lr: 1e-3,
                beta1: 0.9,
                beta2: 0.99,
                eps: 1e-8,
                grad_clip: Some(1.0),
            },
        );
        // The actor loss alone leaves both critics untouched.
        opt.zero_grad();
        lp.backward();
        let vars = vs.variables();
        assert!(
            !vars["critic.l1.weight"].grad().defined()
                || vars["critic.l1.weight"]
                    .grad()
                    .abs()
                    .sum(Kind::Float)
                    .double_value(&[])
                    == 0.0
        );
        assert!(
            vars["actor.l1.weight"]
                .grad()
                .abs()
                .sum(Kind::Float)
                .double_value(&[])
                > 0.0
        );
        let (lv2, lc2, lp2, ..) = losses(&net, &target, &batch, 1.0, &cfg).unwrap();
        assert!(opt.backward_step(&(lv2 + lc2 + lp2)) > 0.0);
        assert!(lv.double_value(&[]).is_finite() && lc.double_value(&[]).is_finite());
        // Acting: actions land inside the box.
        let mut acting = Acting::new(&net, &spec, &cfg, &[10.0, 20.0]);
        let input = StepInput {
            obs: &[0.0; 6],
            arrived_obs: &[0.0; 6],
            prev_action: &[0.0; 4],
            reward: &[0.0; 2],
            cost: &[0.0; 2],
            episode_start: &[true; 2],
        };
        acting.observe(&input);
        let policy = acting.policy(&net, &input).unwrap();
        let (_, env) = sample_actions(&policy, &spec, &[], false, &mut rng);
        let EnvActions::Continuous(v) = env else {
            panic!()
        };
        assert_eq!(v.len(), 4);
        assert!(v.iter().all(|x| (-1.0..=1.0).contains(x)));
    }

    #[test]
    fn tanh_gaussian_log_prob_matches_the_sampler() {
        tch::manual_seed(3);
        let mean = Tensor::randn([4, 5, 2], (Kind::Float, Device::Cpu));
        let log_std = Tensor::randn([4, 5, 2], (Kind::Float, Device::Cpu)) * 0.5 - 0.5;
        let noise = Tensor::randn([4, 5, 2], (Kind::Float, Device::Cpu));
        let (a, want) = tanh_gaussian_sample(&mean, &log_std, &noise);
        let got = tanh_gaussian_log_prob(&mean, &log_std, &a);
        let err = (got - want).abs().max().double_value(&[]);
        assert!(err < 1e-2, "max |log pi difference| {err}");
        // Saturated f32 actions (exactly +-1) stay finite.
        let edge = Tensor::from_slice(&[1.0f32, -1.0]).view([1, 2]);
        let lp = tanh_gaussian_log_prob(
            &mean.narrow(0, 0, 1).narrow(1, 0, 1).view([1, 2]),
            &log_std.narrow(0, 0, 1).narrow(1, 0, 1).view([1, 2]),
            &edge,
        );
        assert!(lp.double_value(&[0]).is_finite());
    }

    #[test]
    fn filtered_bc_raises_the_log_prob_of_kept_replayed_actions() {
        for discrete in [true, false] {
            let (mut learner, mut venv) = tiny_learner(2);
            learner.collect(&mut venv).unwrap();
            let trajs: Vec<&Trajectory> = learner.replay.trajectories.iter().collect();
            let mut rng = ChaCha8Rng::seed_from_u64(0);
            let mut cfg = learner.cfg.clone();
            cfg.entropy_coef = 0.0;
            let (batch, net, target, vs) = if discrete {
                let batch = make_batch(&trajs, &cfg, &learner.spec, &mut rng, Device::Cpu);
                let vs = nn::VarStore::new(Device::Cpu);
                let net = EppoNet::new(vs.root(), &cfg, &learner.spec).unwrap();
                let tvs = nn::VarStore::new(Device::Cpu);
                let target = EppoNet::new(tvs.root(), &cfg, &learner.spec).unwrap();
                (batch, net, target, vs)
            } else {
                // The same steps with a 2-D action in [-1, 1] per step.
                let spec = NetSpec {
                    n_actions: None,
                    act_low: vec![-1.0, -1.0],
                    act_high: vec![1.0, 1.0],
                    ..learner.spec.clone()
                };
                let owned: Vec<Trajectory> = trajs
                    .iter()
                    .map(|t| {
                        let mut t = (*t).clone();
                        t.actions = (0..t.len() * 2)
                            .map(|i| (i as f32 * 0.7).sin() * 0.9)
                            .collect();
                        t.action_idx.clear();
                        t
                    })
                    .collect();
                let refs: Vec<&Trajectory> = owned.iter().collect();
                let batch = make_batch(&refs, &cfg, &spec, &mut rng, Device::Cpu);
                let vs = nn::VarStore::new(Device::Cpu);
                let net = EppoNet::new(vs.root(), &cfg, &spec).unwrap();
                let tvs = nn::VarStore::new(Device::Cpu);
                let target = EppoNet::new(tvs.root(), &cfg, &spec).unwrap();
                (batch, net, target, vs)
            };
            // The BC term alone: Lp(bc = 1) - Lp(bc = 0) under the same noise.
            let bc_term = || {
                let mut with = cfg.clone();
                with.bc_coef = 1.0;
                tch::manual_seed(0);
                let (_, _, a, ..) = losses(&net, &target, &batch, 0.0, &with).unwrap();
                tch::manual_seed(0);
                let (_, _, b, ..) = losses(&net, &target, &batch, 0.0, &cfg).unwrap();
                a - b
            };
            let first = bc_term().double_value(&[]);
            let mut opt = Adam::new(
                &vs,
                AdamConfig {
                    lr: 1e-2,
                    beta1: 0.9,
                    beta2: 0.99,
                    eps: 1e-8,
                    grad_clip: None,
                },
            );
            for _ in 0..30 {
                opt.backward_step(&bc_term());
            }
            let last = bc_term().double_value(&[]);
            assert!(
                last < first - 1e-3,
                "discrete {discrete}: BC term {first} -> {last} (-mean keep * log pi must fall)"
            );
        }
    }

    #[test]
    fn n_step_targets_sum_rewards_until_the_bootstrap_stops() {
        let t = |v: &[f32]| Tensor::from_slice(v).view([1, v.len() as i64]);
        // Steps 0..5: reward at step 2 (terminal: no bootstrap past it), then
        // a step 3 without a target of its own (truncated), then 4 and 5.
        let r = t(&[0.0, 0.0, 1.0, 0.0, 0.0, 2.0]);
        let boot = t(&[1.0, 1.0, 0.0, 1.0, 1.0, 0.0]);
        let valid = t(&[1.0, 1.0, 1.0, 0.0, 1.0, 1.0]);
        let v_next = t(&[10.0, 20.0, 30.0, 40.0, 50.0, 60.0]);
        let g = 0.5;
        let y1 = to_vec(&n_step_targets(&r, &boot, &valid, &v_next, g, 1));
        assert_eq!(y1, vec![5.0, 10.0, 1.0, 20.0, 25.0, 2.0]);
        let y3 = to_vec(&n_step_targets(&r, &boot, &valid, &v_next, g, 3));
        // 0: 0 + g (0 + g (1)) = 0.25; 1: 0 + g 1 = 0.5; 2: 1;
        // 3: r3 + g [valid 4] y(2)_4 = 0 + g (0 + g 2) = 0.5;
        // 4: 0 + g 2 = 1; 5: 2.
        assert_eq!(y3, vec![0.25, 0.5, 1.0, 0.5, 1.0, 2.0]);
        // Step 2 bootstraps into step 3, which has no target: one-step there.
        let boot2 = t(&[1.0, 1.0, 1.0, 0.0, 1.0, 0.0]);
        let y2 = to_vec(&n_step_targets(&r, &boot2, &valid, &v_next, g, 2));
        // 1: 0 + g y(1)_2 = g (1 + g 30) = 8; 2: 1 + g V'_3 (step 3 has no target) = 1 + 15.
        assert_eq!(y2[1], 8.0);
        assert_eq!(y2[2], 16.0);
    }

    #[test]
    fn pretrain_end_to_end_checkpoints_resumes_and_loads() {
        let out = std::env::temp_dir().join(format!("icrl-eppo-e2e-{}", std::process::id()));
        let opts = PretrainOptions {
            env: EnvName::DarkRoom,
            cfg: tiny(),
            out: out.clone(),
            resume: None,
            progress: false,
        };
        let report = train(&opts).unwrap();
        assert_eq!(report.updates, 4);
        assert!(report.last_checkpoint.ends_with("step_4"));
        let lines = std::fs::read_to_string(report.run_dir.join("metrics.jsonl")).unwrap();
        let first: serde_json::Value = serde_json::from_str(lines.lines().next().unwrap()).unwrap();
        for key in [
            "env_steps",
            "episodic_return",
            "episodic_cost",
            "lambda",
            "losses/value_loss",
        ] {
            assert!(first.get(key).is_some(), "{key}");
        }
        // Resume to 6 updates from the run folder.
        let mut cfg = tiny();
        cfg.total_updates = 6;
        let resumed = train(&PretrainOptions {
            cfg,
            resume: Some(report.run_dir.clone()),
            ..opts.clone()
        })
        .unwrap();
        assert_eq!(
            (resumed.updates, resumed.run_dir.clone()),
            (6, report.run_dir.clone())
        );
        assert!(resumed.env_steps > report.env_steps);
        // An incompatible config is refused with the manifest named.
        let mut other = tiny();
        other.model.n_layers = 2;
        let err = train(&PretrainOptions {
            cfg: other,
            resume: Some(report.run_dir.clone()),
            ..opts.clone()
        })
        .err()
        .unwrap()
        .to_string();
        assert!(
            err.contains("manifest.json") && err.contains("model"),
            "{err}"
        );
        // A truncated weight file is refused with its name.
        let ckpt = report.run_dir.join("checkpoints/step_6");
        let w = ckpt.join("model.safetensors");
        let bytes = std::fs::read(&w).unwrap();
        let mut agent = EppoAgent::load(&ckpt, Device::Cpu).unwrap();
        std::fs::write(&w, &bytes[..bytes.len() / 2]).unwrap();
        let err = EppoAgent::load(&ckpt, Device::Cpu)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("model.safetensors"), "{err}");
        // The frozen agent acts for two trajectories at once.
        agent
            .reset(&[
                Conditioning::Budget { ctg: 3.0 },
                Conditioning::Budget { ctg: 9.0 },
            ])
            .unwrap();
        let input = StepInput {
            obs: &[4.0, 4.0, 4.0, 4.0],
            arrived_obs: &[0.0; 4],
            prev_action: &[0.0; 10],
            reward: &[0.0; 2],
            cost: &[0.0; 2],
            episode_start: &[true; 2],
        };
        let Actions::Discrete(a) = agent.act(&input, true).unwrap() else {
            panic!()
        };
        assert!(a.len() == 2 && a.iter().all(|&x| x < 5));
        assert!(
            agent
                .act(
                    &StepInput {
                        obs: &[0.0; 2],
                        ..input
                    },
                    false
                )
                .is_err()
        );
        std::fs::remove_dir_all(&out).unwrap();
    }
}
