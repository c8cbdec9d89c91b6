//! Token windows ([module docs](super): windows that show learning): each
//! history step as one token with its RTG and CTG labels, and [`TokenSet`],
//! which samples windows of whole episodes for training.

use rand::Rng;
use rand::distributions::{Distribution, WeightedIndex};
use rand_chacha::ChaCha8Rng;
use tch::Tensor;

use super::AdError;
use super::config::{AdConfig, AdSpec, CtgLabel};
use crate::data::histories::History;
use crate::tokens::{self, StepToken};

/// Appends one token: the shared layout ([`crate::tokens`]) with RTG and CTG
/// scaled, the reward as received.
#[allow(clippy::too_many_arguments)]
pub(super) fn push_token(
    spec: &AdSpec,
    cfg: &AdConfig,
    step: StepToken<'_>,
    rtg: f32,
    ctg: f32,
    out: &mut Vec<f32>,
) {
    let to_go = [rtg / cfg.rtg_scale, ctg / cfg.ctg_scale];
    let step = StepToken {
        to_go: &to_go,
        ..step
    };
    tokens::push_token(&step, 1.0, |o, out| spec.normalise_obs(o, out), out);
}

/// The action of history step `t` as a token's action part (one-hot when discrete).
pub(super) fn action_part(spec: &AdSpec, h: &History, t: usize, out: &mut [f32]) {
    out.fill(0.0);
    if spec.discrete {
        let a = h.actions[t] as usize;
        if a < out.len() {
            out[a] = 1.0;
        }
    } else {
        out.copy_from_slice(&h.actions[t * spec.action_dim..(t + 1) * spec.action_dim]);
    }
}

/// RTG and CTG labels of every step. RTG is what is still to come in its
/// episode, including the step's own reward. CTG is, with
/// [`CtgLabel::Hindsight`], the cost still to come likewise; with
/// [`CtgLabel::Budget`], the history's cost limit minus the cost already
/// received in the episode, floored at 0.
pub fn to_go(h: &History, ctg_label: CtgLabel) -> (Vec<f32>, Vec<f32>) {
    let mut rtg = vec![0.0; h.len()];
    let mut ctg = vec![0.0; h.len()];
    for ep in h.episodes() {
        let mut r = 0.0;
        let mut c = 0.0;
        for t in ep.clone().rev() {
            r += h.rewards[t];
            c += h.costs[t];
            rtg[t] = r;
            ctg[t] = c;
        }
        if ctg_label == CtgLabel::Budget {
            let mut spent = 0.0;
            for t in ep {
                ctg[t] = (h.cost_limit - spent).max(0.0);
                spent += h.costs[t];
            }
        }
    }
    (rtg, ctg)
}

/// One history's steps, kept apart so that a window can join episodes that
/// were not adjacent: each token takes what the previous step *in the
/// window* received.
pub(super) struct HistorySteps {
    len: usize,
    /// (T, obs_dim) observations and the observations each action arrived at.
    obs: Vec<f32>,
    next_obs: Vec<f32>,
    /// (T, action width) actions as token parts (one-hot when discrete).
    actions: Vec<f32>,
    rewards: Vec<f32>,
    costs: Vec<f32>,
    rtg: Vec<f32>,
    ctg: Vec<f32>,
    start: Vec<bool>,
    pub(super) episodes: Vec<std::ops::Range<usize>>,
    /// (T,) class indices (discrete targets; continuous targets are `actions`).
    classes: Vec<i64>,
}

/// Histories ready for windows ([module docs](self): windows that show learning).
pub struct TokenSet {
    spec: AdSpec,
    cfg: AdConfig,
    pub(super) histories: Vec<HistorySteps>,
}

impl TokenSet {
    /// Prepares `histories` for windows.
    pub fn new(spec: &AdSpec, cfg: &AdConfig, histories: &[&History]) -> Self {
        let a = spec.action_dim;
        let histories = histories
            .iter()
            .map(|h| {
                let (rtg, ctg) = to_go(h, cfg.ctg_label);
                let episodes = h.episodes();
                let mut start = vec![false; h.len()];
                for ep in &episodes {
                    start[ep.start] = true;
                }
                let mut actions = vec![0.0f32; h.len() * a];
                for t in 0..h.len() {
                    action_part(spec, h, t, &mut actions[t * a..(t + 1) * a]);
                }
                HistorySteps {
                    len: h.len(),
                    obs: h.observations.clone(),
                    next_obs: h.next_observations.clone(),
                    actions,
                    rewards: h.rewards.clone(),
                    costs: h.costs.clone(),
                    rtg,
                    ctg,
                    start,
                    episodes,
                    classes: if spec.discrete {
                        h.actions.iter().map(|&x| x as i64).collect()
                    } else {
                        Vec::new()
                    },
                }
            })
            .collect();
        TokenSet {
            spec: spec.clone(),
            cfg: cfg.clone(),
            histories,
        }
    }

    /// The steps of one window of `len` steps: whole episodes `stride` apart
    /// after a random start inside the first. Where the history ends before
    /// the window is full the draw is repeated; after 32 misses the window is
    /// a contiguous run from a uniform position.
    pub(super) fn window_steps(
        &self,
        h: &HistorySteps,
        len: usize,
        rng: &mut ChaCha8Rng,
    ) -> Vec<usize> {
        for _ in 0..32 {
            let stride = rng.gen_range(1..=self.cfg.episode_stride_max);
            let e0 = rng.gen_range(0..h.episodes.len());
            let first = &h.episodes[e0];
            let mut steps: Vec<usize> = (rng.gen_range(first.clone())..first.end).collect();
            let mut e = e0 + stride;
            while steps.len() < len && e < h.episodes.len() {
                steps.extend(h.episodes[e].clone());
                e += stride;
            }
            if steps.len() >= len {
                steps.truncate(len);
                return steps;
            }
        }
        let start = rng.gen_range(0..=h.len - len);
        (start..start + len).collect()
    }

    /// Appends the tokens of `steps` of `h` to `out`.
    pub(super) fn push_window(&self, h: &HistorySteps, steps: &[usize], out: &mut Vec<f32>) {
        let (o, a) = (self.spec.obs_dim, self.spec.action_dim);
        let (zeros_o, zeros_a) = (vec![0.0f32; o], vec![0.0f32; a]);
        for (i, &t) in steps.iter().enumerate() {
            let received = match i.checked_sub(1).map(|j| steps[j]) {
                None => (&zeros_o[..], &zeros_a[..], 0.0, 0.0),
                Some(p) => (
                    &h.next_obs[p * o..(p + 1) * o],
                    &h.actions[p * a..(p + 1) * a],
                    h.rewards[p],
                    h.costs[p],
                ),
            };
            let step = StepToken {
                obs: &h.obs[t * o..(t + 1) * o],
                arrived_obs: received.0,
                prev_action: received.1,
                reward: received.2,
                cost: received.3,
                to_go: &[],
                start: h.start[t],
            };
            push_token(&self.spec, &self.cfg, step, h.rtg[t], h.ctg[t], out);
        }
    }

    /// Samples `batch` windows of `len` steps from histories at least `len`
    /// long, each history drawn in proportion to its length. Returns tokens
    /// (B, T, token_dim) and targets (B, T) int64 or (B, T, action_dim) float.
    pub fn sample(
        &self,
        batch: i64,
        len: i64,
        rng: &mut ChaCha8Rng,
    ) -> Result<(Tensor, Tensor), AdError> {
        let l = len as usize;
        let weights: Vec<f64> = self
            .histories
            .iter()
            .map(|h| if h.len >= l { h.len as f64 } else { 0.0 })
            .collect();
        let dist = WeightedIndex::new(&weights).map_err(|_| {
            AdError::Config(format!(
                "no history is at least {l} steps long: lower the sequence length (model.max_len)"
            ))
        })?;
        let (d, a) = (self.spec.token_dim(), self.spec.action_dim);
        let mut x = Vec::with_capacity(batch as usize * l * d);
        let mut ycls = Vec::new();
        let mut yvec = Vec::new();
        for _ in 0..batch {
            let h = &self.histories[dist.sample(rng)];
            let steps = self.window_steps(h, l, rng);
            self.push_window(h, &steps, &mut x);
            for &t in &steps {
                if self.spec.discrete {
                    ycls.push(h.classes[t]);
                } else {
                    yvec.extend_from_slice(&h.actions[t * a..(t + 1) * a]);
                }
            }
        }
        let x = Tensor::from_slice(&x).view([batch, len, d as i64]);
        let y = if self.spec.discrete {
            Tensor::from_slice(&ycls).view([batch, len])
        } else {
            Tensor::from_slice(&yvec).view([batch, len, a as i64])
        };
        Ok((x, y))
    }

    /// Number of histories.
    pub fn len(&self) -> usize {
        self.histories.len()
    }

    pub fn is_empty(&self) -> bool {
        self.histories.is_empty()
    }
}
