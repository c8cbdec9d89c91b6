//! EPPO's networks, small parts first: what they read ([`NetSpec`]), an MLP
//! head, the tanh-squashed Gaussian of continuous actions, and [`EppoNet`]
//! (time-step encoder, shared transformer, actor, reward and cost critics,
//! optional novelty critics and goal-recall head).
//! Variable names are the checkpoint format.

use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor, nn, nn::Module};

use safety_envs::Space;

use super::config::{EppoConfig, EppoError};
use crate::model::{KvCache, Transformer};
use crate::tokens;

/// What the networks read and emit, taken from the environment's spaces.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
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

    /// Observation mapped to [-1, 1] where the bounds are finite (the other
    /// entries pass through unchanged).
    pub(super) fn normalise_obs(&self, obs: &[f32], out: &mut Vec<f32>) {
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
pub(super) struct Head {
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

    pub(super) fn forward(&self, x: &Tensor) -> Tensor {
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
    pub(super) spec: NetSpec,
    /// Time-step encoder: token -> encoder_hidden -> d_model.
    pub(super) enc_1: nn::Linear,
    enc_2: nn::Linear,
    transformer: Transformer,
    /// Discrete: logits (A). Continuous: mean and log-std (2 * A).
    pub(super) actor: Head,
    /// Discrete: (C * A) values from h. Continuous: C values from (h, a).
    pub(super) critic: Head,
    pub(super) cost_critic: Head,
    /// With `novelty_critic`: the novelty bonus's own critics, shaped as
    /// the reward critics.
    pub(super) novelty_critic: Option<Head>,
    /// With `goal_recall_coef` > 0: the goal's position (2) from h.
    pub(super) goal_recall: Option<Head>,
    n_critics: i64,
}

const LOG_STD_MIN: f64 = -5.0;
const LOG_STD_MAX: f64 = 2.0;

impl EppoNet {
    /// Builds every part under `p` (names are the checkpoint format).
    pub fn new(p: nn::Path, cfg: &EppoConfig, spec: &NetSpec) -> Result<Self, EppoError> {
        crate::torch_rng::drawing(|| Self::build(p, cfg, spec))
    }

    fn build(p: nn::Path, cfg: &EppoConfig, spec: &NetSpec) -> Result<Self, EppoError> {
        let d = cfg.model.transformer.d_model;
        let a = spec.act_flat() as i64;
        let (actor_out, critic_in, critic_out) = match spec.n_actions {
            Some(_) => (a, d, cfg.model.n_critics * a),
            None => (2 * a, d + a, cfg.model.n_critics),
        };
        Ok(EppoNet {
            spec: spec.clone(),
            enc_1: nn::linear(
                &p / "enc_1",
                spec.token_dim() as i64,
                cfg.model.encoder_hidden,
                Default::default(),
            ),
            enc_2: nn::linear(
                &p / "enc_2",
                cfg.model.encoder_hidden,
                d,
                Default::default(),
            ),
            transformer: Transformer::new(&p / "transformer", &cfg.model.transformer)?,
            actor: Head::new(&p / "actor", d, cfg.model.head_hidden, actor_out),
            critic: Head::new(&p / "critic", critic_in, cfg.model.head_hidden, critic_out),
            cost_critic: Head::new(
                &p / "cost_critic",
                critic_in,
                cfg.model.head_hidden,
                critic_out,
            ),
            novelty_critic: cfg.novelty.novelty_critic.then(|| {
                Head::new(
                    &p / "novelty_critic",
                    critic_in,
                    cfg.model.head_hidden,
                    critic_out,
                )
            }),
            goal_recall: (cfg.goal.goal_recall_coef > 0.0)
                .then(|| Head::new(&p / "goal_recall", d, cfg.model.head_hidden, 2)),
            n_critics: cfg.model.n_critics,
        })
    }

    /// Tokens (B, T, token_dim) -> embeddings (B, T, D).
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
    pub(super) fn critic_values(&self, head: &Head, h: &Tensor, detached: bool) -> Tensor {
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
    pub(super) fn critic_sa(&self, head: &Head, h: &Tensor, a: &Tensor, detached: bool) -> Tensor {
        let x = Tensor::cat(&[h, a], -1); // (.., D + A)
        if detached {
            head.forward_detached(&x)
        } else {
            head.forward(&x)
        }
    }

    /// Continuous actor: h -> (mean, log_std), each (.., A).
    pub(super) fn gaussian(&self, h: &Tensor) -> (Tensor, Tensor) {
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
pub(super) fn tanh_gaussian_sample(
    mean: &Tensor,
    log_std: &Tensor,
    noise: &Tensor,
) -> (Tensor, Tensor) {
    let std = log_std.exp();
    let u = mean + &std * noise;
    let a = u.tanh();
    let log_normal = (noise.square() * -0.5) - log_std - 0.5 * (2.0 * std::f64::consts::PI).ln();
    // Change of variables through tanh: log(1 - tanh(u)^2) = 2 (ln 2 - u - softplus(-2u)).
    let log_det = ((u.neg() * 2.0).softplus() + &u).neg() * 2.0 + 2.0 * 2f64.ln();
    let log_prob = (log_normal - log_det).sum_dim_intlist(-1, false, Kind::Float);
    (a, log_prob)
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
        cfg.model.transformer.d_model as f64,
        cfg.model.encoder_hidden as f64,
        cfg.model.head_hidden as f64,
    );
    let a = f(spec.act_flat());
    let (actor_out, critic_in, critic_out) = match spec.n_actions {
        Some(_) => (a, d, cfg.model.n_critics as f64 * a),
        None => (2.0 * a, d + a, cfg.model.n_critics as f64),
    };
    let head = |i: f64, o: f64| i * hh + hh + hh * hh + hh + hh * o + o;
    let params = f(spec.token_dim()) * eh
        + eh
        + eh * d
        + d
        + transformer_parameters(&cfg.model.transformer)
        + head(d, actor_out)
        + 2.0 * head(critic_in, critic_out);
    let (b, t) = (
        f(cfg.optimisation.batch_size),
        cfg.model.transformer.max_len as f64,
    );
    let step_bytes = 4.0 * (f(spec.obs_dim) + a + 3.0) + 15.0;
    let mut m = crate::guard::MemoryEstimate {
        levers: "batch_size, model.max_len, model.d_model, model.n_layers, model.d_ff, \
                 encoder_hidden, head_hidden, n_critics, n_envs or replay_capacity"
            .into(),
        ..Default::default()
    };
    m.add("replay", f(cfg.targets.replay_capacity) * step_bytes);
    if cfg.run.device == "cuda" {
        return m;
    }
    m.add("parameters (online and target)", 2.0 * 4.0 * params);
    m.add("gradients and Adam moments", 3.0 * 4.0 * params);
    m.add(
        "one batch's activations",
        1.5 * transformer_activation_bytes(&cfg.model.transformer, b)
            + 2.0 * 4.0 * b * t * f(spec.token_dim()),
    );
    m.add(
        "acting cache",
        4.0 * f(cfg.tasks.n_envs)
            * t
            * (2.0 * cfg.model.transformer.n_layers as f64 * d + f(spec.token_dim())),
    );
    m
}
