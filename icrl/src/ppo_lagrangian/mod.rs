//! PPO-Lagrangian (Ray et al., 2019), read top to bottom like CleanRL's `ppo.py`:
//! this file is [`train`], then its steps in the order they run (the
//! rollout of the environments, the value targets and GAE, the PPO
//! epochs); beside it are `config.rs` (hyperparameters),
//! `losses.rs` (small helpers: observation normaliser, Lagrange multiplier,
//! GAE, clipped surrogate) and `net.rs` (the actor-critic).
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

mod config;
mod losses;
mod net;

use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use safety_envs::{Action, CmdpEnv, EnvError, Space, Task};
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor, nn, nn::Module};
use thiserror::Error;

use crate::data::histories::History;
use crate::optim::{Adam, AdamConfig, StepRefused};

pub use config::PpoLagConfig;
pub use losses::{Lagrange, RunningNorm, clipped_surrogate, combined_advantage, gae};
use net::ActorCritic;

/// Everything PPO-Lagrangian can fail with.
#[derive(Debug, Error)]
pub enum PpoLagError {
    #[error("PPO-Lagrangian config: {0}")]
    Config(String),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Torch(#[from] tch::TchError),
    /// A step was refused (a loss or gradient that is NaN or infinite, or
    /// libtorch's error from the backward pass): the history would be
    /// meaningless.
    #[error(
        "PPO-Lagrangian update {update}: {why}; no step taken. Lower learning_rate or check the settings"
    )]
    StepRefused { update: usize, why: StepRefused },
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
    let mut envs = Envs::new(cfg, make_env, task, cost_limit)?;
    let (obs_dim, act_dim) = (envs.obs_dim, envs.act_dim);
    check_memory(cfg, obs_dim, act_dim)?;

    // -- networks, optimiser, generators
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let vs = nn::VarStore::new(Device::Cpu);
    let net = crate::torch_rng::seeded(seed, || {
        ActorCritic::new(&vs.root(), obs_dim as i64, &envs.space, cfg)
    });
    // Our Adam, not tch's: its backward pass reports libtorch's errors
    // instead of panicking (tch's defaults otherwise: betas 0.9, 0.999).
    let mut opt = Adam::new(
        &vs,
        AdamConfig {
            lr: cfg.learning_rate,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            grad_clip: Some(cfg.max_grad_norm),
        },
    );
    let mut lagrange = Lagrange::new(cfg.lagrange_init, cfg.lagrange_lr, cfg.lagrange_max);
    let mut norm = RunningNorm::new(obs_dim);

    let n_updates = cfg.total_steps.div_ceil(cfg.num_envs * cfg.rollout_steps);
    envs.reset(&mut rng)?;
    let mut metrics = Vec::with_capacity(n_updates);
    for update in 0..n_updates {
        if cfg.anneal_lr {
            opt.set_lr(cfg.learning_rate * (1.0 - update as f64 / n_updates as f64));
        }
        let (ro, finished) = envs.rollout(cfg, &net, &mut norm, &mut rng, progress)?;

        // ---- Lagrange multiplier from the episodes that finished (OmniSafe
        // updates it before the policy step, from the epoch's mean episode cost).
        let (ep_ret, ep_cost) = episode_means(&finished);
        if !finished.is_empty() {
            lagrange.update(ep_cost, cost_limit as f64);
        }
        let lambda = lagrange.value;

        let targets = value_targets(cfg, &net, &ro, obs_dim, lambda)?;
        let [policy_loss, value_loss, cost_value_loss, entropy, approx_kl] = ppo_epochs(
            cfg, &net, &mut opt, &ro, &targets, act_dim, &mut rng, update,
        )?;
        metrics.push(UpdateMetrics {
            global_step: envs.global_step,
            episodes: finished.len(),
            episodic_return: ep_ret,
            episodic_cost: ep_cost,
            lambda,
            policy_loss,
            value_loss,
            cost_value_loss,
            entropy,
            approx_kl,
        });
    }
    // Steps of unfinished episodes are not part of the history.
    let mut history = envs.history;
    history.truncate_to_finished_episodes(obs_dim, act_dim);
    Ok(PpoLagRun { history, metrics })
}

/// Refuses a run whose history, rollout and networks with Adam's moments
/// would not fit in memory, before anything is allocated.
fn check_memory(cfg: &PpoLagConfig, obs_dim: usize, act_dim: usize) -> Result<(), PpoLagError> {
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
    m.check().map_err(PpoLagError::Config)
}

/// The `num_envs` environments of a run and what acting in them carries
/// from step to step: the raw observations, each environment's running
/// episode, the history of the finished ones, and reused buffers.
struct Envs<'a> {
    envs: Vec<Box<dyn CmdpEnv>>,
    task: &'a Task,
    cost_limit: f32,
    space: Space,
    obs_dim: usize,
    act_dim: usize,
    discrete: bool,
    /// A continuous space's bounds, to which actions are clipped.
    bounds: Option<(Vec<f32>, Vec<f32>)>,
    /// (N, obs_dim) the observations the next actions are taken in.
    raw_obs: Vec<f32>,
    /// Each environment's running episode, flushed into `history` when it ends.
    pending: Vec<History>,
    history: History,
    global_step: usize,
    norm_obs: Vec<f32>,
    norm_next: Vec<f32>,
    next_raw: Vec<f32>,
    env_action: Vec<f32>,
}

impl<'a> Envs<'a> {
    /// Builds the environments in `task`.
    fn new(
        cfg: &PpoLagConfig,
        make_env: &dyn Fn() -> Result<Box<dyn CmdpEnv>, EnvError>,
        task: &'a Task,
        cost_limit: f32,
    ) -> Result<Self, PpoLagError> {
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
        Ok(Envs {
            envs,
            task,
            cost_limit,
            space,
            obs_dim,
            act_dim,
            discrete,
            bounds,
            raw_obs: vec![0.0f32; n_envs * obs_dim],
            pending: (0..n_envs)
                .map(|_| History::new(task.clone(), cost_limit))
                .collect(),
            history: History::new(task.clone(), cost_limit),
            global_step: 0,
            norm_obs: Vec::new(),
            norm_next: Vec::new(),
            next_raw: vec![0.0f32; obs_dim],
            env_action: vec![0.0f32; act_dim],
        })
    }

    /// Resets every environment with a seed drawn from `rng`.
    fn reset(&mut self, rng: &mut ChaCha8Rng) -> Result<(), PpoLagError> {
        let obs_dim = self.obs_dim;
        for (i, env) in self.envs.iter_mut().enumerate() {
            env.reset(
                rng.r#gen(),
                &mut self.raw_obs[i * obs_dim..(i + 1) * obs_dim],
            )?;
        }
        Ok(())
    }

    /// `cfg.rollout_steps` steps of every environment under the current
    /// policy; returns them with the (return, cost) of each episode that
    /// finished.
    fn rollout(
        &mut self,
        cfg: &PpoLagConfig,
        net: &ActorCritic,
        norm: &mut RunningNorm,
        rng: &mut ChaCha8Rng,
        progress: &mut dyn FnMut(usize),
    ) -> Result<(Rollout, Vec<(f32, f32)>), PpoLagError> {
        let n_envs = self.envs.len();
        let mut ro = Rollout::default();
        let mut finished: Vec<(f32, f32)> = Vec::new();
        for _ in 0..cfg.rollout_steps {
            if cfg.normalize_obs {
                norm.update(&self.raw_obs);
                norm.normalize(&self.raw_obs, &mut self.norm_obs);
            } else {
                self.norm_obs.clone_from(&self.raw_obs);
            }
            let policy_out = self.policy(net)?;
            let width = policy_out.len() / n_envs;
            for i in 0..n_envs {
                let row = &policy_out[i * width..(i + 1) * width];
                let (log_prob, index) = sample_action(
                    row,
                    net,
                    self.bounds.as_ref(),
                    rng,
                    &mut ro,
                    &mut self.env_action,
                )?;
                self.step(i, index, cfg, norm, rng, &mut ro, &mut finished)?;
                ro.log_probs.push(log_prob);
            }
            ro.obs.extend_from_slice(&self.norm_obs);
            progress(n_envs);
        }
        Ok((ro, finished))
    }

    /// The policy's output for every environment's normalised observation:
    /// action probabilities (discrete) or the Gaussian's mean, row by row.
    fn policy(&self, net: &ActorCritic) -> Result<Vec<f32>, PpoLagError> {
        let (n_envs, obs_dim) = (self.envs.len(), self.obs_dim);
        Ok(tch::no_grad(|| {
            let x = Tensor::from_slice(&self.norm_obs).view([n_envs as i64, obs_dim as i64]);
            let out = net.actor.forward(&x);
            let out = if self.discrete {
                out.softmax(-1, Kind::Float)
            } else {
                out
            };
            Vec::<f32>::try_from(out.flatten(0, -1))
        })?)
    }

    /// Steps environment `i` with the action just sampled (`index` for a
    /// discrete space, else `env_action`), records the step in its episode
    /// and in `ro`, and on the episode's end moves it into the history and
    /// resets the environment.
    #[allow(clippy::too_many_arguments)]
    fn step(
        &mut self,
        i: usize,
        index: Option<usize>,
        cfg: &PpoLagConfig,
        norm: &RunningNorm,
        rng: &mut ChaCha8Rng,
        ro: &mut Rollout,
        finished: &mut Vec<(f32, f32)>,
    ) -> Result<(), PpoLagError> {
        let obs_dim = self.obs_dim;
        let action = match index {
            Some(a) => Action::Discrete(a),
            None => Action::Continuous(&self.env_action),
        };
        let out = self.envs[i].step(action, &mut self.next_raw)?;
        self.global_step += 1;
        let obs_i = &self.raw_obs[i * obs_dim..(i + 1) * obs_dim];
        self.pending[i].push(
            obs_i,
            &self.env_action,
            out.reward,
            out.cost,
            &self.next_raw,
            out.terminated,
            out.truncated,
        );
        ro.rewards.push(out.reward);
        ro.costs.push(out.cost);
        ro.terminated.push(out.terminated);
        ro.done.push(out.done());
        // The next observation, normalised with the current statistics;
        // for a finished episode it is the final one (bootstrapped on truncation).
        if cfg.normalize_obs {
            norm.normalize(&self.next_raw, &mut self.norm_next);
        } else {
            self.norm_next.clone_from(&self.next_raw);
        }
        ro.next_obs.extend_from_slice(&self.norm_next);
        if out.done() {
            let ep = std::mem::replace(
                &mut self.pending[i],
                History::new(self.task.clone(), self.cost_limit),
            );
            finished.push((ep.rewards.iter().sum(), ep.costs.iter().sum()));
            append(&mut self.history, ep);
            self.envs[i].reset(
                rng.r#gen(),
                &mut self.raw_obs[i * obs_dim..(i + 1) * obs_dim],
            )?;
        } else {
            self.raw_obs[i * obs_dim..(i + 1) * obs_dim].copy_from_slice(&self.next_raw);
        }
        Ok(())
    }
}

/// Samples one environment's action from its `row` of the policy's output
/// (probabilities; or, with `bounds`, a continuous space, the Gaussian's
/// mean) in Rust from `rng`, records it in `ro` and `env_action` (clipped
/// to the bounds); returns its log-probability and, for a discrete space,
/// its index.
fn sample_action(
    row: &[f32],
    net: &ActorCritic,
    bounds: Option<&(Vec<f32>, Vec<f32>)>,
    rng: &mut ChaCha8Rng,
    ro: &mut Rollout,
    env_action: &mut [f32],
) -> Result<(f32, Option<usize>), PpoLagError> {
    let Some((low, high)) = bounds else {
        let u: f32 = rng.r#gen();
        let mut acc = 0.0;
        let mut a = row.len() - 1;
        for (k, &p) in row.iter().enumerate() {
            acc += p;
            if u < acc {
                a = k;
                break;
            }
        }
        ro.actions_idx.push(a as i64);
        env_action[0] = a as f32;
        return Ok((row[a].max(1e-12).ln(), Some(a)));
    };
    let log_std: Vec<f32> = match &net.log_std {
        Some(t) => Vec::<f32>::try_from(t.detach())?,
        None => unreachable!("continuous space has a log-std"),
    };
    let mut lp = 0.0f32;
    for d in 0..env_action.len() {
        let z: f32 = rng.sample(StandardNormal);
        let a = row[d] + log_std[d].exp() * z;
        ro.actions_vec.push(a);
        lp += -0.5 * z * z - log_std[d] - 0.5 * (2.0 * std::f32::consts::PI).ln();
        // The environment gets the action clipped to its bounds.
        env_action[d] = a.clamp(low[d], high[d]);
    }
    Ok((lp, None))
}

/// Mean return and cost of the episodes that finished in a rollout (NaN
/// when none did).
fn episode_means(finished: &[(f32, f32)]) -> (f64, f64) {
    if finished.is_empty() {
        (f64::NAN, f64::NAN)
    } else {
        let k = finished.len() as f64;
        (
            finished.iter().map(|e| e.0 as f64).sum::<f64>() / k,
            finished.iter().map(|e| e.1 as f64).sum::<f64>() / k,
        )
    }
}

/// What the PPO epochs fit: the rollout's observations as a tensor, the
/// combined advantage and the reward and cost value targets, row by row.
struct Targets {
    obs: Tensor,
    adv: Vec<f32>,
    ret_r: Vec<f32>,
    ret_c: Vec<f32>,
}

/// The values of every buffered observation and next observation (batched),
/// GAE per environment for reward and cost, and the advantage that combines
/// them at `lambda`.
fn value_targets(
    cfg: &PpoLagConfig,
    net: &ActorCritic,
    ro: &Rollout,
    obs_dim: usize,
    lambda: f64,
) -> Result<Targets, PpoLagError> {
    let n_envs = cfg.num_envs;
    let batch = n_envs * cfg.rollout_steps;
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
    Ok(Targets {
        obs: obs_t,
        adv: combined_advantage(&adv_r, &adv_c, lambda),
        ret_r,
        ret_c,
    })
}

/// The PPO epochs of one update: clipped surrogate, both value losses and
/// the entropy bonus over shuffled minibatches of the rollout. Returns the
/// mean policy loss, value loss, cost value loss, entropy and approximate KL.
#[allow(clippy::too_many_arguments)]
fn ppo_epochs(
    cfg: &PpoLagConfig,
    net: &ActorCritic,
    opt: &mut Adam,
    ro: &Rollout,
    targets: &Targets,
    act_dim: usize,
    rng: &mut ChaCha8Rng,
    update: usize,
) -> Result<[f64; 5], PpoLagError> {
    let batch = cfg.num_envs * cfg.rollout_steps;
    let minibatch = batch / cfg.minibatches;
    let b = batch as i64;
    let obs_t = &targets.obs;
    // A discrete space's policy has no log-std.
    let actions_t = if net.log_std.is_none() {
        Tensor::from_slice(&ro.actions_idx)
    } else {
        Tensor::from_slice(&ro.actions_vec).view([b, act_dim as i64])
    };
    let old_logp_t = Tensor::from_slice(&ro.log_probs);
    let adv_t = Tensor::from_slice(&targets.adv);
    let ret_r_t = Tensor::from_slice(&targets.ret_r);
    let ret_c_t = Tensor::from_slice(&targets.ret_c);
    let mut order: Vec<i64> = (0..b).collect();
    let mut sums = [0.0f64; 5];
    let mut n_mb = 0.0;
    for _ in 0..cfg.update_epochs {
        order.shuffle(rng);
        for mb in order.chunks(minibatch) {
            let ix = Tensor::from_slice(mb);
            let (logp, entropy) =
                net.log_prob_entropy(&obs_t.index_select(0, &ix), &actions_t.index_select(0, &ix));
            let log_ratio = &logp - old_logp_t.index_select(0, &ix);
            let ratio = log_ratio.exp();
            let pg_loss = clipped_surrogate(&ratio, &adv_t.index_select(0, &ix), cfg.clip_coef);
            let mb_obs = obs_t.index_select(0, &ix);
            let v_loss = (net.critic.forward(&mb_obs).view([-1]) - ret_r_t.index_select(0, &ix))
                .square()
                .mean(Kind::Float);
            let c_loss = (net.cost_critic.forward(&mb_obs).view([-1])
                - ret_c_t.index_select(0, &ix))
            .square()
            .mean(Kind::Float);
            let ent = entropy.mean(Kind::Float);
            let loss = &pg_loss - cfg.ent_coef * &ent + cfg.vf_coef * (&v_loss + &c_loss);
            opt.try_backward_step(&loss)
                .map_err(|why| PpoLagError::StepRefused {
                    update: update + 1,
                    why,
                })?;
            // http://joschu.net/blog/kl-approx.html: E[(r - 1) - log r]
            let kl = tch::no_grad(|| ((&ratio - 1.0) - &log_ratio).mean(Kind::Float));
            for (s, t) in sums.iter_mut().zip([&pg_loss, &v_loss, &c_loss, &ent, &kl]) {
                *s += t.double_value(&[]);
            }
            n_mb += 1.0;
        }
    }
    Ok(sums.map(|s| s / n_mb))
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
