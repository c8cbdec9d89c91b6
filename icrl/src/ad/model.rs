//! AD's model: token encoder, the shared transformer and the action head
//! (variable names are the checkpoint format), and the supervised loss
//! (Eq. 16 / 17).

use tch::{Kind, Tensor, nn, nn::Module};

use super::AdError;
use super::config::{AdConfig, AdSpec};
use crate::model::{KvCache, Transformer};

/// Token encoder, the shared transformer, and the action head.
#[derive(Debug)]
pub struct AdModel {
    /// Two-layer MLP: token -> d_model.
    embed: nn::Sequential,
    pub(super) transformer: Transformer,
    /// d_model -> action logits (discrete) or action mean (continuous).
    head: nn::Linear,
}

impl AdModel {
    pub fn new(p: &nn::Path, spec: &AdSpec, cfg: &AdConfig) -> Result<Self, AdError> {
        crate::torch_rng::drawing(|| Self::build(p, spec, cfg))
    }

    fn build(p: &nn::Path, spec: &AdSpec, cfg: &AdConfig) -> Result<Self, AdError> {
        let d = cfg.model.d_model;
        let embed = nn::seq()
            .add(nn::linear(
                p / "embed" / "l1",
                spec.token_dim() as i64,
                d,
                Default::default(),
            ))
            .add_fn(|x| x.gelu("none"))
            .add(nn::linear(p / "embed" / "l2", d, d, Default::default()));
        let transformer = Transformer::new(p / "transformer", &cfg.model)?;
        let head = nn::linear(p / "head", d, spec.action_dim as i64, Default::default());
        Ok(AdModel {
            embed,
            transformer,
            head,
        })
    }

    /// Full forward: tokens (B, T, token_dim) -> (B, T, action_dim).
    pub fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor, AdError> {
        let h = self.embed.forward(x); // (B, T, D)
        let h = self.transformer.forward_t(&h, train)?; // (B, T, D)
        Ok(self.head.forward(&h))
    }

    /// Incremental forward with a KV cache: (B, T_new, token_dim) -> (B, T_new, action_dim).
    pub fn forward_step(&self, x: &Tensor, cache: &mut KvCache) -> Result<Tensor, AdError> {
        let h = self.embed.forward(x);
        let h = self.transformer.forward_step(&h, cache)?;
        Ok(self.head.forward(&h))
    }
}

/// The supervised loss (Eq. 16 / 17) and, for discrete actions, the accuracy.
pub fn loss(out: &Tensor, target: &Tensor, discrete: bool) -> (Tensor, Option<Tensor>) {
    if discrete {
        let a = out.size()[2];
        let logits = out.view([-1, a]); // (B*T, A)
        let y = target.view([-1]); // (B*T,)
        let ce = logits.cross_entropy_for_logits(&y);
        let acc = logits
            .argmax(-1, false)
            .eq_tensor(&y)
            .to_kind(Kind::Float)
            .mean(Kind::Float);
        (ce, Some(acc))
    } else {
        // L2 on the action mean: squared error summed over action dims, mean over steps.
        let l2 = (out - target)
            .square()
            .sum_dim_intlist(-1, false, Kind::Float)
            .mean(Kind::Float);
        (l2, None)
    }
}
