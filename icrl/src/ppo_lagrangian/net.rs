//! The actor-critic: MLPs with orthogonal initialisation, a categorical or
//! diagonal-Gaussian policy, and reward and cost value heads.

use safety_envs::Space;
use tch::{Kind, Tensor, nn, nn::Module};

use super::config::PpoLagConfig;

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
pub(super) struct ActorCritic {
    pub(super) actor: nn::Sequential,
    /// `Some` for a continuous action space: (action_dim,)
    pub(super) log_std: Option<Tensor>,
    pub(super) critic: nn::Sequential,
    pub(super) cost_critic: nn::Sequential,
}

impl ActorCritic {
    pub(super) fn new(p: &nn::Path, obs_dim: i64, space: &Space, cfg: &PpoLagConfig) -> Self {
        crate::torch_rng::drawing(|| Self::build(p, obs_dim, space, cfg))
    }

    fn build(p: &nn::Path, obs_dim: i64, space: &Space, cfg: &PpoLagConfig) -> Self {
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
    pub(super) fn log_prob_entropy(&self, obs: &Tensor, actions: &Tensor) -> (Tensor, Tensor) {
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
