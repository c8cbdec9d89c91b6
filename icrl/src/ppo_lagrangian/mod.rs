//! PPO-Lagrangian (Ray et al., 2019), read top to bottom like CleanRL's `ppo.py`:
//! config, small helpers (observation normaliser, Lagrange multiplier, GAE,
//! clipped surrogate), networks, then [`train`].
//!
//! One learning run in one task at one cost limit, from scratch. It records
//! every finished episode, in the order they finished: that is the *learning
//! history* supervised pretraining distils (SPEC section 4).
//!
//! The Lagrangian part follows OmniSafe's `PPOLag`: a multiplier `lambda >= 0`
//! (initial value `lagrange_init`) updated once per rollout by Adam on
//! `-lambda * (J_c - cost_limit)`, with `J_c` the mean cost of the episodes that
//! finished in that rollout, so it rises while episodes cost more than the limit
//! and falls (to 0) otherwise; the policy ascends the combined advantage
//! `(A_r - lambda * A_c) / (1 + lambda)`, with `A_r` standardised and `A_c`
//! centred (OmniSafe's defaults).
//!
//! Acting samples in Rust from a seeded ChaCha generator, and the networks are
//! initialised under a process-wide lock after seeding libtorch, so a run is a
//! function of its seed even when many runs share the process (one per thread).

use std::sync::Mutex;

use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use safety_envs::{Action, CmdpEnv, EnvError, Space, Task};
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor, nn, nn::Module, nn::OptimizerConfig};
use thiserror::Error;

use crate::data::histories::History;

/// Everything PPO-Lagrangian can fail with.
#[derive(Debug, Error)]
pub enum PpoLagError {
    #[error("PPO-Lagrangian config: {0}")]
    Config(String),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Torch(#[from] tch::TchError),
    /// A loss became NaN or infinite: the history would be meaningless.
    #[error(
        "PPO-Lagrangian update {update}: the loss is {loss}; lower learning_rate or check the settings"
    )]
    NonFinite { update: usize, loss: f64 },
}

/// PPO-Lagrangian hyperparameters (defaults: [`PpoLagConfig::darkroom`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PpoLagConfig {
    /// Environment steps of learning per run (the history's length before a
    /// trailing unfinished episode is dropped). SPEC: 50,000.
    pub total_steps: usize,
    /// Environments stepped together, all in the run's task; their episodes
    /// enter the history in the order they finish.
    pub num_envs: usize,
    /// Steps per environment in one rollout (one update per rollout).
    pub rollout_steps: usize,
    /// Width of the two hidden tanh layers of actor and critics.
    pub hidden: i64,
    /// Adam learning rate of actor and critics.
    pub learning_rate: f64,
    /// Decay the learning rate linearly to 0 over the run (CleanRL's `anneal_lr`).
    pub anneal_lr: bool,
    /// Discount of rewards.
    pub gamma: f64,
    /// Discount of costs.
    pub cost_gamma: f64,
    /// GAE lambda (rewards and costs).
    pub gae_lambda: f64,
    /// Passes over each rollout.
    pub update_epochs: usize,
    /// Minibatches per pass.
    pub minibatches: usize,
    /// PPO ratio clip.
    pub clip_coef: f64,
    /// Entropy bonus weight.
    pub ent_coef: f64,
    /// Weight of the two critic losses.
    pub vf_coef: f64,
    /// Global gradient-norm clip.
    pub max_grad_norm: f64,
    /// Normalise observations with running mean and variance (clipped to +-10).
    pub normalize_obs: bool,
    /// Initial Lagrange multiplier (OmniSafe: 0.001).
    pub lagrange_init: f64,
    /// Adam learning rate of the multiplier (OmniSafe: 0.035).
    pub lagrange_lr: f64,
    /// Upper bound of the multiplier.
    pub lagrange_max: f64,
    /// Initial log standard deviation of the Gaussian policy (continuous actions).
    pub init_log_std: f64,
}

impl PpoLagConfig {
    /// SafeDarkRoom: 50k steps, short rollouts so a run has about 200 updates.
    /// The multiplier's learning rate is above OmniSafe's 0.035 because it
    /// steps once per update, and a run has few updates; the entropy bonus
    /// keeps some exploration for the detours a zero cost limit needs.
    pub fn darkroom() -> Self {
        PpoLagConfig {
            total_steps: 50_000,
            num_envs: 4,
            rollout_steps: 64,
            hidden: 64,
            learning_rate: 1e-3,
            anneal_lr: true,
            gamma: 0.99,
            cost_gamma: 0.99,
            gae_lambda: 0.95,
            update_epochs: 4,
            minibatches: 4,
            clip_coef: 0.2,
            ent_coef: 0.02,
            vf_coef: 0.5,
            max_grad_norm: 0.5,
            normalize_obs: true,
            lagrange_init: 0.001,
            lagrange_lr: 0.1,
            lagrange_max: 100.0,
            init_log_std: -0.5,
        }
    }

    /// SafeDarkMujoco (Point, Car): longer rollouts, lower learning rate.
    pub fn mujoco() -> Self {
        PpoLagConfig {
            rollout_steps: 256,
            learning_rate: 3e-4,
            ent_coef: 0.0,
            ..Self::darkroom()
        }
    }

    /// Checks the sizes fit together and every number lies in its range
    /// (named in the error).
    pub fn validate(&self) -> Result<(), PpoLagError> {
        use crate::guard::{Range, check_counts, check_numbers};
        check_counts(&[
            ("total_steps", self.total_steps as i128),
            ("num_envs", self.num_envs as i128),
            ("rollout_steps", self.rollout_steps as i128),
            ("hidden", i128::from(self.hidden)),
            ("update_epochs", self.update_epochs as i128),
            ("minibatches", self.minibatches as i128),
        ])
        .map_err(PpoLagError::Config)?;
        check_numbers(&[
            ("learning_rate", self.learning_rate, Range::UNIT_OPEN_LOW),
            ("gamma", self.gamma, Range::UNIT),
            ("cost_gamma", self.cost_gamma, Range::UNIT),
            ("gae_lambda", self.gae_lambda, Range::UNIT),
            ("clip_coef", self.clip_coef, Range::POSITIVE),
            ("ent_coef", self.ent_coef, Range::NON_NEGATIVE),
            ("vf_coef", self.vf_coef, Range::POSITIVE),
            ("max_grad_norm", self.max_grad_norm, Range::POSITIVE),
            ("lagrange_init", self.lagrange_init, Range::NON_NEGATIVE),
            ("lagrange_lr", self.lagrange_lr, Range::NON_NEGATIVE),
            ("lagrange_max", self.lagrange_max, Range::NON_NEGATIVE),
            (
                "init_log_std",
                self.init_log_std,
                Range::new(-20.0, false, 2.0, false),
            ),
        ])
        .map_err(PpoLagError::Config)?;
        let batch = self.num_envs.saturating_mul(self.rollout_steps);
        if self.minibatches == 0 || !batch.is_multiple_of(self.minibatches) {
            return Err(PpoLagError::Config(format!(
                "minibatches ({}) must divide num_envs * rollout_steps ({batch})",
                self.minibatches
            )));
        }
        if !(0.0..=1.0).contains(&self.gamma) || !(0.0..=1.0).contains(&self.gae_lambda) {
            return Err(PpoLagError::Config(format!(
                "gamma ({}) and gae_lambda ({}) must lie in [0, 1]",
                self.gamma, self.gae_lambda
            )));
        }
        if self.lagrange_init < 0.0 || self.lagrange_max < self.lagrange_init {
            return Err(PpoLagError::Config(format!(
                "need 0 <= lagrange_init ({}) <= lagrange_max ({})",
                self.lagrange_init, self.lagrange_max
            )));
        }
        Ok(())
    }
}

/// Metrics of one update, against environment steps. Names as CleanRL logs
/// them: `charts/episodic_return`, `charts/episodic_cost`, `charts/lambda`,
/// `losses/policy_loss`, `losses/value_loss`, `losses/cost_value_loss`,
/// `losses/entropy`, `losses/approx_kl`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct UpdateMetrics {
    pub global_step: usize,
    /// Episodes that finished in this rollout.
    pub episodes: usize,
    /// Mean return and cost of those episodes (NaN when none finished).
    pub episodic_return: f64,
    pub episodic_cost: f64,
    /// The multiplier used for this update.
    pub lambda: f64,
    pub policy_loss: f64,
    pub value_loss: f64,
    pub cost_value_loss: f64,
    pub entropy: f64,
    pub approx_kl: f64,
}

/// What a run leaves behind.
#[derive(Clone, Debug)]
pub struct PpoLagRun {
    /// Every finished episode, in order (steps of a trailing unfinished
    /// episode are dropped).
    pub history: History,
    pub metrics: Vec<UpdateMetrics>,
}

// ---------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------

/// Running mean and variance of observations (parallel Welford update).
#[derive(Clone, Debug)]
pub struct RunningNorm {
    mean: Vec<f64>,
    var: Vec<f64>,
    count: f64,
}

impl RunningNorm {
    pub fn new(dim: usize) -> Self {
        RunningNorm {
            mean: vec![0.0; dim],
            var: vec![1.0; dim],
            count: 1e-4,
        }
    }

    /// Folds in a batch of rows (row-major, `dim` columns).
    pub fn update(&mut self, rows: &[f32]) {
        let dim = self.mean.len();
        let n = (rows.len() / dim) as f64;
        if n == 0.0 {
            return;
        }
        for j in 0..dim {
            let col = rows.iter().skip(j).step_by(dim).map(|&x| x as f64);
            let bmean = col.clone().sum::<f64>() / n;
            let bvar = col.map(|x| (x - bmean).powi(2)).sum::<f64>() / n;
            let delta = bmean - self.mean[j];
            let total = self.count + n;
            self.mean[j] += delta * n / total;
            let m2 = self.var[j] * self.count + bvar * n + delta * delta * self.count * n / total;
            self.var[j] = m2 / total;
        }
        self.count += n;
    }

    /// Normalises `rows` into `out`, clipped to +-10.
    pub fn normalize(&self, rows: &[f32], out: &mut Vec<f32>) {
        let dim = self.mean.len();
        out.clear();
        out.extend(rows.iter().enumerate().map(|(i, &x)| {
            let j = i % dim;
            (((x as f64 - self.mean[j]) / (self.var[j] + 1e-8).sqrt()).clamp(-10.0, 10.0)) as f32
        }));
    }
}

/// The Lagrange multiplier with its own scalar Adam (OmniSafe's `Lagrange`).
#[derive(Clone, Debug)]
pub struct Lagrange {
    pub value: f64,
    lr: f64,
    max: f64,
    m: f64,
    v: f64,
    t: i32,
}

impl Lagrange {
    pub fn new(init: f64, lr: f64, max: f64) -> Self {
        Lagrange {
            value: init,
            lr,
            max,
            m: 0.0,
            v: 0.0,
            t: 0,
        }
    }

    /// One Adam step on `-lambda * (episode_cost - cost_limit)`, then clamps to
    /// `[0, max]`: rises while the measured cost exceeds the limit.
    pub fn update(&mut self, episode_cost: f64, cost_limit: f64) {
        let (b1, b2, eps) = (0.9, 0.999, 1e-8);
        let grad = -(episode_cost - cost_limit);
        self.t += 1;
        self.m = b1 * self.m + (1.0 - b1) * grad;
        self.v = b2 * self.v + (1.0 - b2) * grad * grad;
        let m_hat = self.m / (1.0 - b1.powi(self.t));
        let v_hat = self.v / (1.0 - b2.powi(self.t));
        self.value -= self.lr * m_hat / (v_hat.sqrt() + eps);
        self.value = self.value.clamp(0.0, self.max);
    }
}

/// Generalised advantage estimation over one environment's steps in time
/// order. `next_values[t]` is the value of the observation after step `t`
/// (for a truncated step: the final observation of the cut episode).
///
/// `terminated` steps bootstrap nothing (the goal ends the task); truncated
/// steps bootstrap `next_values` but, like terminated ones, stop the
/// advantage recursion because the next buffered step belongs to a new
/// episode (`done = terminated | truncated`). The last buffered step always
/// bootstraps from `next_values` (the rollout, not the episode, ended there).
/// Returns `(advantages, returns)`.
pub fn gae(
    rewards: &[f32],
    values: &[f32],
    next_values: &[f32],
    terminated: &[bool],
    done: &[bool],
    gamma: f64,
    lambda: f64,
) -> (Vec<f32>, Vec<f32>) {
    let n = rewards.len();
    let mut adv = vec![0.0f32; n];
    let mut last = 0.0f64;
    for t in (0..n).rev() {
        // Terminal: no bootstrap. Truncated or mid-episode: bootstrap.
        let next_v = if terminated[t] {
            0.0
        } else {
            next_values[t] as f64
        };
        let delta = rewards[t] as f64 + gamma * next_v - values[t] as f64;
        // The recursion continues only inside an episode.
        let carry = if done[t] || t == n - 1 { 0.0 } else { last };
        last = delta + gamma * lambda * carry;
        adv[t] = last as f32;
    }
    let ret = adv.iter().zip(values).map(|(a, v)| a + v).collect();
    (adv, ret)
}

/// PPO's clipped surrogate loss (to minimise):
/// `mean(max(-A * ratio, -A * clip(ratio, 1 - c, 1 + c)))`.
pub fn clipped_surrogate(ratio: &Tensor, advantages: &Tensor, clip: f64) -> Tensor {
    let unclipped = -advantages * ratio;
    let clipped = -advantages * ratio.clamp(1.0 - clip, 1.0 + clip);
    unclipped.max_other(&clipped).mean(Kind::Float)
}

/// The combined advantage `(A_r - lambda * A_c) / (1 + lambda)`, `A_r`
/// standardised and `A_c` centred (OmniSafe).
pub fn combined_advantage(adv_r: &[f32], adv_c: &[f32], lambda: f64) -> Vec<f32> {
    let n = adv_r.len().max(1) as f64;
    let mean_r = adv_r.iter().map(|&x| x as f64).sum::<f64>() / n;
    let std_r = (adv_r
        .iter()
        .map(|&x| (x as f64 - mean_r).powi(2))
        .sum::<f64>()
        / n)
        .sqrt();
    let mean_c = adv_c.iter().map(|&x| x as f64).sum::<f64>() / n;
    adv_r
        .iter()
        .zip(adv_c)
        .map(|(&r, &c)| {
            let r = (r as f64 - mean_r) / (std_r + 1e-8);
            let c = c as f64 - mean_c;
            ((r - lambda * c) / (1.0 + lambda)) as f32
        })
        .collect()
}

// ---------------------------------------------------------------------------
// Networks
// ---------------------------------------------------------------------------

/// libtorch's generator is process-wide: seed and initialise under one lock.
static INIT_LOCK: Mutex<()> = Mutex::new(());

/// A two-hidden-layer tanh MLP with CleanRL's orthogonal initialisation.
fn mlp(p: nn::Path, input: i64, hidden: i64, output: i64, out_gain: f64) -> nn::Sequential {
    let lin = |p: nn::Path, i, o, gain| {
        nn::linear(
            p,
            i,
            o,
            nn::LinearConfig {
                ws_init: nn::Init::Orthogonal { gain },
                bs_init: Some(nn::Init::Const(0.0)),
                bias: true,
            },
        )
    };
    nn::seq()
        .add(lin(&p / "l1", input, hidden, 2f64.sqrt()))
        .add_fn(|x| x.tanh())
        .add(lin(&p / "l2", hidden, hidden, 2f64.sqrt()))
        .add_fn(|x| x.tanh())
        .add(lin(&p / "l3", hidden, output, out_gain))
}

/// Actor (categorical logits or Gaussian mean with a free log-std), reward
/// critic and cost critic: three separate MLPs.
struct ActorCritic {
    actor: nn::Sequential,
    /// `Some` for a continuous action space: (action_dim,)
    log_std: Option<Tensor>,
    critic: nn::Sequential,
    cost_critic: nn::Sequential,
}

impl ActorCritic {
    fn new(p: &nn::Path, obs_dim: i64, space: &Space, cfg: &PpoLagConfig) -> Self {
        let out = space.flat_dim() as i64;
        let log_std = match space {
            Space::Discrete { .. } => None,
            Space::Box { .. } => Some(p.var("log_std", &[out], nn::Init::Const(cfg.init_log_std))),
        };
        ActorCritic {
            actor: mlp(p / "actor", obs_dim, cfg.hidden, out, 0.01),
            log_std,
            critic: mlp(p / "critic", obs_dim, cfg.hidden, 1, 1.0),
            cost_critic: mlp(p / "cost_critic", obs_dim, cfg.hidden, 1, 1.0),
        }
    }

    /// Log-probabilities of `actions` and the entropy, both (B,).
    /// `actions`: (B,) int64 indices, or (B, action_dim) floats.
    fn log_prob_entropy(&self, obs: &Tensor, actions: &Tensor) -> (Tensor, Tensor) {
        let out = self.actor.forward(obs);
        match &self.log_std {
            None => {
                let logp = out.log_softmax(-1, Kind::Float); // (B, n)
                let chosen = logp.gather(1, &actions.unsqueeze(1), false).squeeze_dim(1);
                let entropy = -(logp.exp() * &logp).sum_dim_intlist(-1, false, Kind::Float);
                (chosen, entropy)
            }
            Some(log_std) => {
                let std = log_std.exp();
                let z = (actions - &out) / &std; // (B, d)
                let per_dim = z.square() * -0.5 - log_std - 0.5 * (2.0 * std::f64::consts::PI).ln();
                let logp = per_dim.sum_dim_intlist(-1, false, Kind::Float);
                let ent_one = (log_std
                    + 0.5 * (2.0 * std::f64::consts::PI * std::f64::consts::E).ln())
                .sum(Kind::Float);
                let entropy = ent_one.expand([out.size()[0]], false);
                (logp, entropy)
            }
        }
    }
}

// ---------------------------------------------------------------------------
// Training
// ---------------------------------------------------------------------------

/// One step of all environments, kept for the update.
#[derive(Default)]
struct Rollout {
    /// (T*N, obs_dim) normalised, row `t * N + i`.
    obs: Vec<f32>,
    next_obs: Vec<f32>,
    /// Discrete: (T*N,) indices; continuous: (T*N, action_dim) raw samples.
    actions_idx: Vec<i64>,
    actions_vec: Vec<f32>,
    log_probs: Vec<f32>,
    rewards: Vec<f32>,
    costs: Vec<f32>,
    terminated: Vec<bool>,
    done: Vec<bool>,
}

/// Runs PPO-Lagrangian from scratch in `task` at `cost_limit`.
///
/// `make_env` builds each of the `num_envs` environments; `progress` is told
/// how many environment steps were just taken.
pub fn train(
    cfg: &PpoLagConfig,
    make_env: &dyn Fn() -> Result<Box<dyn CmdpEnv>, EnvError>,
    task: &Task,
    cost_limit: f32,
    seed: u64,
    progress: &mut dyn FnMut(usize),
) -> Result<PpoLagRun, PpoLagError> {
    cfg.validate()?;
    let n_envs = cfg.num_envs;
    let mut envs = (0..n_envs)
        .map(|_| make_env())
        .collect::<Result<Vec<_>, _>>()?;
    for env in envs.iter_mut() {
        env.set_task(task)?;
    }
    let obs_dim = envs[0].observation_space().flat_dim();
    let space = envs[0].action_space();
    let (discrete, act_dim, bounds) = match &space {
        Space::Discrete { .. } => (true, 1usize, None),
        Space::Box { low, high } => (false, low.len(), Some((low.clone(), high.clone()))),
    };
    // What the run will hold: the history it records, one rollout, and the
    // networks with Adam's moments (before anything is allocated).
    {
        let (o, a, h) = (obs_dim as f64, act_dim as f64, cfg.hidden as f64);
        let mut m = crate::guard::MemoryEstimate {
            levers: "total_steps, num_envs, rollout_steps or hidden".into(),
            ..Default::default()
        };
        m.add(
            "history",
            4.0 * cfg.total_steps as f64 * (2.0 * o + a + 4.0),
        );
        m.add(
            "rollout",
            4.0 * 3.0 * (cfg.num_envs as f64 * cfg.rollout_steps as f64) * (o + a + 8.0),
        );
        m.add(
            "networks and Adam moments",
            4.0 * 4.0 * 3.0 * (o * h + h * h + 2.0 * h * a),
        );
        m.check().map_err(PpoLagError::Config)?;
    }

    // -- networks, optimiser, generators
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let vs = nn::VarStore::new(Device::Cpu);
    let net = {
        // A poisoned lock only means another run panicked mid-initialisation.
        let _guard = INIT_LOCK.lock().unwrap_or_else(|e| e.into_inner());
        tch::manual_seed(seed as i64);
        ActorCritic::new(&vs.root(), obs_dim as i64, &space, cfg)
    };
    let mut opt = nn::Adam::default().build(&vs, cfg.learning_rate)?;
    let mut lagrange = Lagrange::new(cfg.lagrange_init, cfg.lagrange_lr, cfg.lagrange_max);
    let mut norm = RunningNorm::new(obs_dim);

    // -- derived sizes
    let batch = n_envs * cfg.rollout_steps;
    let minibatch = batch / cfg.minibatches;
    let n_updates = cfg.total_steps.div_ceil(batch);

    // -- state
    let mut raw_obs = vec![0.0f32; n_envs * obs_dim];
    for (i, env) in envs.iter_mut().enumerate() {
        env.reset(rng.r#gen(), &mut raw_obs[i * obs_dim..(i + 1) * obs_dim])?;
    }
    // Each environment's running episode, flushed into `history` when it ends.
    let mut pending: Vec<History> = (0..n_envs)
        .map(|_| History::new(task.clone(), cost_limit))
        .collect();
    let mut history = History::new(task.clone(), cost_limit);
    let mut metrics = Vec::with_capacity(n_updates);
    let mut global_step = 0usize;
    let mut norm_obs = Vec::new();
    let mut norm_next = Vec::new();
    let mut next_raw = vec![0.0f32; obs_dim];
    let mut env_action = vec![0.0f32; act_dim];

    for update in 0..n_updates {
        if cfg.anneal_lr {
            opt.set_lr(cfg.learning_rate * (1.0 - update as f64 / n_updates as f64));
        }
        let mut ro = Rollout::default();
        let mut finished: Vec<(f32, f32)> = Vec::new();

        // ---- rollout
        for _ in 0..cfg.rollout_steps {
            if cfg.normalize_obs {
                norm.update(&raw_obs);
                norm.normalize(&raw_obs, &mut norm_obs);
            } else {
                norm_obs.clone_from(&raw_obs);
            }
            let policy_out: Vec<f32> = tch::no_grad(|| {
                let x = Tensor::from_slice(&norm_obs).view([n_envs as i64, obs_dim as i64]);
                let out = net.actor.forward(&x);
                let out = if discrete {
                    out.softmax(-1, Kind::Float)
                } else {
                    out
                };
                Vec::<f32>::try_from(out.flatten(0, -1))
            })?;
            let width = policy_out.len() / n_envs;
            for i in 0..n_envs {
                let row = &policy_out[i * width..(i + 1) * width];
                // Sample in Rust (seeded), compute the log-probability of the sample.
                let (log_prob, action) = if discrete {
                    let u: f32 = rng.r#gen();
                    let mut acc = 0.0;
                    let mut a = width - 1;
                    for (k, &p) in row.iter().enumerate() {
                        acc += p;
                        if u < acc {
                            a = k;
                            break;
                        }
                    }
                    ro.actions_idx.push(a as i64);
                    env_action[0] = a as f32;
                    (row[a].max(1e-12).ln(), Action::Discrete(a))
                } else {
                    let log_std: Vec<f32> = match &net.log_std {
                        Some(t) => Vec::<f32>::try_from(t.detach())?,
                        None => unreachable!("continuous space has a log-std"),
                    };
                    let mut lp = 0.0f32;
                    for d in 0..act_dim {
                        let z: f32 = rng.sample(StandardNormal);
                        let a = row[d] + log_std[d].exp() * z;
                        ro.actions_vec.push(a);
                        lp += -0.5 * z * z - log_std[d] - 0.5 * (2.0 * std::f32::consts::PI).ln();
                        // The environment gets the action clipped to its bounds.
                        let (lo, hi) = bounds.as_ref().map_or((-1.0, 1.0), |(l, h)| (l[d], h[d]));
                        env_action[d] = a.clamp(lo, hi);
                    }
                    (lp, Action::Continuous(&env_action))
                };
                let out = envs[i].step(action, &mut next_raw)?;
                global_step += 1;
                let obs_i = &raw_obs[i * obs_dim..(i + 1) * obs_dim];
                pending[i].push(
                    obs_i,
                    &env_action,
                    out.reward,
                    out.cost,
                    &next_raw,
                    out.terminated,
                    out.truncated,
                );
                ro.log_probs.push(log_prob);
                ro.rewards.push(out.reward);
                ro.costs.push(out.cost);
                ro.terminated.push(out.terminated);
                ro.done.push(out.done());
                // The next observation, normalised with the current statistics;
                // for a finished episode it is the final one (bootstrapped on truncation).
                if cfg.normalize_obs {
                    norm.normalize(&next_raw, &mut norm_next);
                } else {
                    norm_next.clone_from(&next_raw);
                }
                ro.next_obs.extend_from_slice(&norm_next);
                if out.done() {
                    let ep =
                        std::mem::replace(&mut pending[i], History::new(task.clone(), cost_limit));
                    finished.push((ep.rewards.iter().sum(), ep.costs.iter().sum()));
                    append(&mut history, ep);
                    envs[i].reset(rng.r#gen(), &mut raw_obs[i * obs_dim..(i + 1) * obs_dim])?;
                } else {
                    raw_obs[i * obs_dim..(i + 1) * obs_dim].copy_from_slice(&next_raw);
                }
            }
            ro.obs.extend_from_slice(&norm_obs);
            progress(n_envs);
        }

        // ---- Lagrange multiplier from the episodes that finished (OmniSafe
        // updates it before the policy step, from the epoch's mean episode cost).
        let (ep_ret, ep_cost) = if finished.is_empty() {
            (f64::NAN, f64::NAN)
        } else {
            let k = finished.len() as f64;
            (
                finished.iter().map(|e| e.0 as f64).sum::<f64>() / k,
                finished.iter().map(|e| e.1 as f64).sum::<f64>() / k,
            )
        };
        if !finished.is_empty() {
            lagrange.update(ep_cost, cost_limit as f64);
        }
        let lambda = lagrange.value;

        // ---- values of every buffered observation and next observation, batched
        let b = batch as i64;
        let obs_t = Tensor::from_slice(&ro.obs).view([b, obs_dim as i64]);
        let next_t = Tensor::from_slice(&ro.next_obs).view([b, obs_dim as i64]);
        let (v, nv, vc, nvc): (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) = tch::no_grad(|| {
            let f = |m: &nn::Sequential, x: &Tensor| Vec::<f32>::try_from(m.forward(x).view([-1]));
            Ok::<_, tch::TchError>((
                f(&net.critic, &obs_t)?,
                f(&net.critic, &next_t)?,
                f(&net.cost_critic, &obs_t)?,
                f(&net.cost_critic, &next_t)?,
            ))
        })?;
        // GAE per environment: rows i, i + N, i + 2N, ... are env i's steps in order.
        let mut adv_r = vec![0.0f32; batch];
        let mut adv_c = vec![0.0f32; batch];
        let mut ret_r = vec![0.0f32; batch];
        let mut ret_c = vec![0.0f32; batch];
        for i in 0..n_envs {
            let idx: Vec<usize> = (0..cfg.rollout_steps).map(|t| t * n_envs + i).collect();
            let pick = |a: &[f32]| idx.iter().map(|&j| a[j]).collect::<Vec<_>>();
            let pickb = |a: &[bool]| idx.iter().map(|&j| a[j]).collect::<Vec<_>>();
            let (term, done) = (pickb(&ro.terminated), pickb(&ro.done));
            let (ar, rr) = gae(
                &pick(&ro.rewards),
                &pick(&v),
                &pick(&nv),
                &term,
                &done,
                cfg.gamma,
                cfg.gae_lambda,
            );
            let (ac, rc) = gae(
                &pick(&ro.costs),
                &pick(&vc),
                &pick(&nvc),
                &term,
                &done,
                cfg.cost_gamma,
                cfg.gae_lambda,
            );
            for (k, &j) in idx.iter().enumerate() {
                adv_r[j] = ar[k];
                adv_c[j] = ac[k];
                ret_r[j] = rr[k];
                ret_c[j] = rc[k];
            }
        }
        let adv = combined_advantage(&adv_r, &adv_c, lambda);

        // ---- PPO epochs
        let actions_t = if discrete {
            Tensor::from_slice(&ro.actions_idx)
        } else {
            Tensor::from_slice(&ro.actions_vec).view([b, act_dim as i64])
        };
        let old_logp_t = Tensor::from_slice(&ro.log_probs);
        let adv_t = Tensor::from_slice(&adv);
        let ret_r_t = Tensor::from_slice(&ret_r);
        let ret_c_t = Tensor::from_slice(&ret_c);
        let mut order: Vec<i64> = (0..b).collect();
        let mut sums = [0.0f64; 5];
        let mut n_mb = 0.0;
        for _ in 0..cfg.update_epochs {
            order.shuffle(&mut rng);
            for mb in order.chunks(minibatch) {
                let ix = Tensor::from_slice(mb);
                let (logp, entropy) = net
                    .log_prob_entropy(&obs_t.index_select(0, &ix), &actions_t.index_select(0, &ix));
                let log_ratio = &logp - old_logp_t.index_select(0, &ix);
                let ratio = log_ratio.exp();
                let pg_loss = clipped_surrogate(&ratio, &adv_t.index_select(0, &ix), cfg.clip_coef);
                let mb_obs = obs_t.index_select(0, &ix);
                let v_loss = (net.critic.forward(&mb_obs).view([-1])
                    - ret_r_t.index_select(0, &ix))
                .square()
                .mean(Kind::Float);
                let c_loss = (net.cost_critic.forward(&mb_obs).view([-1])
                    - ret_c_t.index_select(0, &ix))
                .square()
                .mean(Kind::Float);
                let ent = entropy.mean(Kind::Float);
                let loss = &pg_loss - cfg.ent_coef * &ent + cfg.vf_coef * (&v_loss + &c_loss);
                let value = loss.double_value(&[]);
                if !value.is_finite() {
                    return Err(PpoLagError::NonFinite {
                        update: update + 1,
                        loss: value,
                    });
                }
                opt.backward_step_clip_norm(&loss, cfg.max_grad_norm);
                // http://joschu.net/blog/kl-approx.html: E[(r - 1) - log r]
                let kl = tch::no_grad(|| ((&ratio - 1.0) - &log_ratio).mean(Kind::Float));
                for (s, t) in sums.iter_mut().zip([&pg_loss, &v_loss, &c_loss, &ent, &kl]) {
                    *s += t.double_value(&[]);
                }
                n_mb += 1.0;
            }
        }
        metrics.push(UpdateMetrics {
            global_step,
            episodes: finished.len(),
            episodic_return: ep_ret,
            episodic_cost: ep_cost,
            lambda,
            policy_loss: sums[0] / n_mb,
            value_loss: sums[1] / n_mb,
            cost_value_loss: sums[2] / n_mb,
            entropy: sums[3] / n_mb,
            approx_kl: sums[4] / n_mb,
        });
    }
    // Steps of unfinished episodes are not part of the history.
    history.truncate_to_finished_episodes(obs_dim, act_dim);
    Ok(PpoLagRun { history, metrics })
}

/// Appends a finished episode to a history.
fn append(history: &mut History, ep: History) {
    history.observations.extend(ep.observations);
    history.next_observations.extend(ep.next_observations);
    history.actions.extend(ep.actions);
    history.rewards.extend(ep.rewards);
    history.costs.extend(ep.costs);
    history.terminals.extend(ep.terminals);
    history.timeouts.extend(ep.timeouts);
}

#[cfg(test)]
mod tests {
    use super::*;
    use safety_envs::{Cell, EnvName, EnvOptions, make_env};

    #[test]
    fn gae_bootstraps_on_truncation_only() {
        // Two one-step episodes, reward 1, V = 0.5 everywhere, next V = 2.
        let r = [1.0, 1.0];
        let v = [0.5, 0.5];
        let nv = [2.0, 2.0];
        let done = [true, true];
        let (a_term, _) = gae(&r, &v, &nv, &[true, true], &done, 0.9, 0.95);
        let (a_trunc, ret) = gae(&r, &v, &nv, &[false, false], &done, 0.9, 0.95);
        assert!(
            (a_term[0] - 0.5).abs() < 1e-6,
            "terminal: 1 - 0.5, got {}",
            a_term[0]
        );
        assert!(
            (a_trunc[0] - (1.0 + 0.9 * 2.0 - 0.5)).abs() < 1e-6,
            "truncated bootstraps"
        );
        assert!((ret[0] - 2.8).abs() < 1e-6);
        // Inside an episode the recursion carries: a0 = d0 + g*l*a1.
        let (a, _) = gae(
            &r,
            &v,
            &[0.5, 2.0],
            &[false, true],
            &[false, true],
            0.9,
            0.95,
        );
        let d1 = 1.0 - 0.5;
        let d0 = 1.0 + 0.9 * 0.5 - 0.5;
        assert!((a[0] - (d0 + 0.9 * 0.95 * d1)).abs() < 1e-6);
        // ... and stops at an episode boundary.
        let (a, _) = gae(&r, &v, &nv, &[false, false], &[true, false], 0.9, 0.95);
        assert!((a[0] - (1.0 + 1.8 - 0.5)).abs() < 1e-6);
    }

    #[test]
    fn clipped_surrogate_clips_in_the_pessimistic_direction() {
        let ratio = Tensor::from_slice(&[1.5f32, 0.5]);
        let adv = Tensor::from_slice(&[1.0f32, -1.0]);
        // ratio 1.5 with A > 0: clipped to 1.2 -> -1.2; ratio 0.5 with A < 0: clipped to 0.8 -> 0.8.
        let loss = clipped_surrogate(&ratio, &adv, 0.2).double_value(&[]);
        assert!((loss - (-1.2 + 0.8) / 2.0).abs() < 1e-6, "{loss}");
        // Where clipping would be optimistic the unclipped term wins.
        let loss = clipped_surrogate(
            &Tensor::from_slice(&[0.5f32]),
            &Tensor::from_slice(&[1.0f32]),
            0.2,
        );
        assert!((loss.double_value(&[]) + 0.5).abs() < 1e-6);
    }

    #[test]
    fn lagrange_rises_with_violation_and_stays_in_bounds() {
        let mut l = Lagrange::new(0.001, 0.035, 0.05);
        l.update(3.0, 0.0);
        assert!(l.value > 0.001 + 0.03, "rises by about lr: {}", l.value);
        l.update(3.0, 0.0);
        assert_eq!(l.value, 0.05, "capped at max");
        for _ in 0..20 {
            l.update(0.0, 5.0);
        }
        assert_eq!(l.value, 0.0, "falls to, and is clamped at, zero");
    }

    #[test]
    fn combined_advantage_penalises_cost_by_lambda() {
        let ar = [1.0, -1.0];
        let ac = [1.0, -1.0];
        let a0 = combined_advantage(&ar, &ac, 0.0);
        assert!((a0[0] - 1.0).abs() < 1e-4);
        // lambda 1: (1 - 1) / 2 = 0.
        let a1 = combined_advantage(&ar, &ac, 1.0);
        assert!(a1[0].abs() < 1e-4, "{a1:?}");
    }

    #[test]
    fn running_norm_matches_batch_statistics() {
        let mut n = RunningNorm::new(2);
        n.update(&[1.0, 10.0, 3.0, 10.0]);
        n.update(&[5.0, 10.0]);
        let mut out = Vec::new();
        // Column 0 holds 1, 3, 5: mean 3, variance 8/3 (the 1e-4 prior count barely moves it).
        n.normalize(&[5.0, 10.0], &mut out);
        assert!(
            (out[0] - 2.0 / (8.0f32 / 3.0).sqrt()).abs() < 1e-3,
            "{out:?}"
        );
        // A constant column normalises to about 0.
        assert!(out[1].abs() < 1e-2, "{out:?}");
    }

    fn darkroom() -> Result<Box<dyn CmdpEnv>, EnvError> {
        make_env(EnvName::DarkRoom, &EnvOptions::default())
    }

    /// A task with the goal two cells right of the centre behind no obstacle on
    /// the direct path, obstacles elsewhere.
    fn easy_task() -> Task {
        let mut obstacles = Vec::new();
        'outer: for row in 0..9 {
            for col in 0..9 {
                if obstacles.len() == 25 {
                    break 'outer;
                }
                if row == 4 || row == 3 {
                    continue; // keep the centre rows free
                }
                obstacles.push(Cell { row, col });
            }
        }
        Task {
            grid_size: 9,
            goal: Cell { row: 4, col: 6 },
            obstacles,
        }
    }

    #[test]
    fn improves_return_on_darkroom() {
        let cfg = PpoLagConfig {
            total_steps: 12_000,
            ..PpoLagConfig::darkroom()
        };
        let run = train(&cfg, &darkroom, &easy_task(), 5.0, 1, &mut |_| {}).unwrap();
        let totals = run.history.episode_totals();
        assert!(totals.len() > 200, "{} episodes", totals.len());
        let mean = |s: &[(f32, f32)]| s.iter().map(|e| e.0).sum::<f32>() / s.len() as f32;
        let first = mean(&totals[..50]);
        let last = mean(&totals[totals.len() - 50..]);
        assert!(last > 0.9 && last > first + 0.2, "return {first} -> {last}");
        // Reaching the goal quickly: episodes get short.
        let eps = run.history.episodes();
        let last_len = eps[eps.len() - 50..].iter().map(|r| r.len()).sum::<usize>() as f32 / 50.0;
        assert!(
            last_len < 6.0,
            "mean length of the last episodes {last_len}"
        );
    }

    #[test]
    fn multiplier_rises_when_cost_exceeds_the_limit() {
        // A uniform-ish initial policy wanders onto obstacles: cost > 0 = limit.
        let cfg = PpoLagConfig {
            total_steps: 4 * 128 * 3,
            ..PpoLagConfig::darkroom()
        };
        let run = train(&cfg, &darkroom, &easy_task(), 0.0, 2, &mut |_| {}).unwrap();
        let m = &run.metrics;
        assert!(
            m[0].episodic_cost > 0.0,
            "the random policy should pay some cost"
        );
        assert!(
            m[2].lambda > m[0].lambda && m[0].lambda > cfg.lagrange_init,
            "lambda {:?}",
            m.iter().map(|x| x.lambda).collect::<Vec<_>>()
        );
        // With a loose limit it falls back to zero.
        let run = train(&cfg, &darkroom, &easy_task(), 30.0, 2, &mut |_| {}).unwrap();
        assert_eq!(run.metrics[2].lambda, 0.0);
    }

    #[test]
    fn history_holds_whole_episodes_in_order() {
        let cfg = PpoLagConfig {
            total_steps: 4 * 128,
            ..PpoLagConfig::darkroom()
        };
        let run = train(&cfg, &darkroom, &easy_task(), 2.5, 3, &mut |_| {}).unwrap();
        let h = &run.history;
        assert!(h.len() <= 4 * 128 && !h.is_empty());
        assert!(h.terminals[h.len() - 1] || h.timeouts[h.len() - 1]);
        for r in h.episodes() {
            // Every episode starts at the centre cell.
            assert_eq!(&h.observations[2 * r.start..2 * r.start + 2], &[4.0, 4.0]);
            assert!(r.len() <= 30);
        }
        // Same seed, same history.
        let again = train(&cfg, &darkroom, &easy_task(), 2.5, 3, &mut |_| {}).unwrap();
        assert_eq!(again.history, run.history);
    }

    #[test]
    fn gaussian_policy_on_point_records_clipped_actions() {
        let cfg = PpoLagConfig {
            total_steps: 2 * 2 * 128,
            num_envs: 2,
            rollout_steps: 128,
            ..PpoLagConfig::mujoco()
        };
        let point = || make_env(EnvName::Point, &EnvOptions::default());
        let spawn = safety_envs::spawn_config(EnvName::Point);
        let task = safety_envs::sample_task(&spawn, safety_envs::Orientation::Centre, 4).unwrap();
        let run = train(&cfg, &point, &task, 5.0, 4, &mut |_| {}).unwrap();
        assert_eq!(run.metrics.len(), 2);
        let h = &run.history;
        assert!(!h.is_empty() && h.actions.len() == 2 * h.len());
        assert!(h.actions.iter().all(|a| (-1.0..=1.0).contains(a)));
        // Some actions were clipped: the Gaussian samples leave the box.
        assert!(h.actions.iter().any(|a| a.abs() == 1.0));
        assert!(
            run.metrics
                .iter()
                .all(|m| m.entropy.is_finite() && m.policy_loss.is_finite())
        );
    }
}
