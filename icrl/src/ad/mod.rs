//! Safe supervised pretraining: algorithm distillation with RTG and CTG
//! (paper Section 3.1, Eq. 16 and 17; SPEC section 4).
//!
//! Read top to bottom: config and presets, the token layout, the data loader,
//! the model, [`train`], then the frozen [`AdAgent`].
//!
//! # Tokens: one per time step
//! Each time step `t` becomes one token of the layout both learners share
//! ([`crate::tokens`]): the observation `s_t` and the observation `a_{t-1}`
//! arrived at (standardised with the dataset's mean and std), `a_{t-1}`
//! (one-hot for discrete actions), `r_t`, `c_t`, the return-to-go `G_t /
//! rtg_scale`, the cost-to-go `G_c,t / ctg_scale` and the episode-start
//! flag; mapped to the model width by a two-layer MLP, through the shared
//! causal transformer ([`crate::model`]), and a linear head predicts `a_t`
//! from the token of step `t`: logits with cross-entropy for discrete
//! actions (Eq. 16), the mean with an L2 loss for continuous ones (Eq. 17).
//!
//! Why one token per step rather than interleaved (RTG, CTG, s, a) tokens as in
//! the constrained decision transformer: the context holds three to four times
//! more steps for the same sequence length, acting is one forward step per
//! environment step through [`crate::agent::InContextAgent`], and EPPO encodes
//! its steps the same way, so the two routes differ only in their learning
//! rule and their conditioning.
//!
//! # Windows that show learning
//! A training window is a run of whole episodes of one history, `episode
//! stride` apart (drawn per window from 1 to `episode_stride_max`), starting
//! at a random step of its first episode and cut at `model.max_len` steps.
//! With a stride above 1 a window spans a longer stretch of the learning run
//! than its length in steps, so the improvement the source learner made
//! between its episodes is visible inside one window, and the model learns
//! to improve faster than the learner did (Laskin et al.'s subsampled
//! histories). The token after a skipped stretch says what the previous
//! episode *in the window* received and where it ended, exactly as at
//! evaluation, where the context is the agent's own episodes.
//!
//! # Conditioning
//! RTG and CTG labels (SPEC section 4): inside each episode, `G_t = sum_{j>=t}
//! r_{j+1}` and `G_c,t = sum_{j>=t} c_{j+1}`, the reward and cost received
//! from acting at `t` to the episode's end, never negative. At test time both
//! start at the targets and decrease by what is received, **floored at 0**:
//! after an episode has spent its budget the token says "no more cost" (the
//! condition the model was trained on) rather than a negative value no
//! training label ever had.
//!
//! # Checkpoints
//! A run folder `{env}__ad__{seed}__{time}` holds `config.toml` (the resolved
//! [`AdConfig`]), `spec.json` ([`AdSpec`]: sizes, normalisation, dataset,
//! pretraining tasks), `metrics.jsonl` (one [`AdMetrics`] per log interval)
//! and `checkpoints/step_N/`: one atomic folder per checkpoint (as EPPO's,
//! through [`crate::checkpoint::RunDir::write_checkpoint`]) with
//! `model.safetensors`, `adam.safetensors` (the optimizer's moments, through
//! the shared [`crate::optim::Adam`]), `state.json` (updates done) and a
//! manifest with every file's size and SHA-256; the newest
//! `keep_checkpoints` are kept. Resuming verifies and loads one, drops the
//! metrics lines logged after it, and continues the schedule where it
//! stopped; `updates` may grow on resume, every other setting must match.

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use rand::distributions::{Distribution, WeightedIndex};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor, nn, nn::Module};
use thiserror::Error;

use crate::agent::{Actions, AgentError, Conditioning, InContextAgent, StepInput};
use crate::checkpoint::{CheckpointError, RunDir, read_manifest};
use crate::data::histories::{History, HistoryError, HistoryFile};
use crate::model::{self, KvCache, ModelError, Transformer};
use crate::optim::{Adam, AdamConfig};
use crate::task_seeds::PretrainTasks;
use crate::tokens::{self, StepToken};

/// Everything supervised pretraining can fail with.
#[derive(Debug, Error)]
pub enum AdError {
    #[error("AD config: {0}")]
    Config(String),
    #[error(transparent)]
    History(#[from] HistoryError),
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error(transparent)]
    Torch(#[from] tch::TchError),
    #[error("{path}: {message}")]
    Io { path: PathBuf, message: String },
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// A loss or gradient became NaN or infinite: the update was not applied.
    #[error(
        "update {update}: {what}; training stopped without applying it. {}",
        crate::checkpoint::last_good(.checkpoint, "lower learning_rate, or check the dataset")
    )]
    NonFinite {
        update: usize,
        what: String,
        checkpoint: Option<PathBuf>,
    },
    /// Stopped by SIGINT/SIGTERM after writing a checkpoint.
    #[error("interrupted after update {updates}: checkpoint written to {}", .checkpoint.display())]
    Interrupted { checkpoint: PathBuf, updates: usize },
}

fn io_err(path: &Path, e: impl std::fmt::Display) -> AdError {
    AdError::Io {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

// ---------------------------------------------------------------------------
// Config and presets
// ---------------------------------------------------------------------------

/// Supervised-pretraining hyperparameters. `model.max_len` is the context
/// window in time steps (Table 2 "Seq Len").
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AdConfig {
    /// The shared transformer's shape and dropouts.
    pub model: model::Config,
    /// Windows per batch (Table 2 "Batch Size").
    pub batch_size: i64,
    /// Gradient updates (Table 2 "Num Updates").
    pub updates: usize,
    /// Adam learning rate (peak, after warm-up).
    pub learning_rate: f64,
    /// Adam betas.
    pub beta1: f64,
    pub beta2: f64,
    /// Global gradient-norm clip.
    pub grad_clip: f64,
    /// Fraction of the updates spent warming the learning rate up linearly;
    /// afterwards it follows a cosine down to 10% of the peak.
    pub warmup_fraction: f64,
    /// Return-to-go is divided by this in the token.
    pub rtg_scale: f32,
    /// Cost-to-go is divided by this in the token.
    pub ctg_scale: f32,
    /// Fraction of the tasks whose histories are held out for a validation loss.
    pub val_fraction: f64,
    /// What the CTG in a token says (module docs: conditioning).
    #[serde(default)]
    pub ctg_label: CtgLabel,
    /// Fraction of the training tasks (those not held out) whose histories
    /// are trained on: the dataset-size ablation (paper Figure 6c).
    #[serde(default = "default_train_fraction")]
    pub train_fraction: f64,
    /// A window takes every s-th episode of a history, s drawn per window
    /// from 1 to this (1: contiguous windows).
    #[serde(default = "default_episode_stride_max")]
    pub episode_stride_max: usize,
    /// Log (and validate) every this many updates.
    pub log_every: usize,
    /// Save a checkpoint every this many updates (and at the end).
    pub checkpoint_every: usize,
    /// Checkpoints kept (0 keeps all).
    #[serde(default = "default_keep_checkpoints")]
    pub keep_checkpoints: usize,
    /// Seed of initialisation and window sampling.
    pub seed: u64,
    /// libtorch intra-op threads; 0 keeps libtorch's default (one per core).
    #[serde(default)]
    pub torch_threads: i32,
}

/// What a training token's CTG says.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CtgLabel {
    /// The cost the episode still received (the paper's cost-to-go).
    #[default]
    Hindsight,
    /// The history's cost limit minus the cost received so far in the
    /// episode: the budget the source learner was held to, known in every
    /// phase of its learning, as the user's budget is at test time.
    Budget,
}

fn default_keep_checkpoints() -> usize {
    3
}

fn default_episode_stride_max() -> usize {
    1
}

fn default_train_fraction() -> f64 {
    1.0
}

/// The presets shipped in `icrl/presets/ad-{env}-{preset}.toml`: `table2` is
/// the paper's Table 2 (a GPU preset), `quick` fits 2 CPU cores.
pub const PRESETS: [(&str, &str); 6] = [
    (
        "ad-darkroom-table2",
        include_str!("../../presets/ad-darkroom-table2.toml"),
    ),
    (
        "ad-point-table2",
        include_str!("../../presets/ad-point-table2.toml"),
    ),
    (
        "ad-car-table2",
        include_str!("../../presets/ad-car-table2.toml"),
    ),
    (
        "ad-darkroom-quick",
        include_str!("../../presets/ad-darkroom-quick.toml"),
    ),
    (
        "ad-point-quick",
        include_str!("../../presets/ad-point-quick.toml"),
    ),
    ("ad-car-quick", include_str!("../../presets/ad-car-quick.toml")),
];

/// The preset `ad-{env}-{preset}` as a TOML table.
pub fn preset_table(env: &str, preset: &str) -> Result<toml::Table, AdError> {
    let name = format!("ad-{env}-{preset}");
    let (_, text) = PRESETS.iter().find(|(n, _)| *n == name).ok_or_else(|| {
        AdError::Config(format!(
            "no AD preset '{name}'; available: {}",
            PRESETS.map(|p| p.0).join(", ")
        ))
    })?;
    text.parse::<toml::Table>()
        .map_err(|e| AdError::Config(format!("preset {name}: {e}")))
}

impl AdConfig {
    /// Parses a TOML config.
    pub fn from_toml(text: &str) -> Result<Self, AdError> {
        let cfg: AdConfig = toml::from_str(text).map_err(|e| AdError::Config(e.to_string()))?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// A shipped preset by `{env}-{preset}`: `darkroom-table2`, `car-quick`, ...
    pub fn preset(name: &str) -> Result<Self, AdError> {
        let (env, preset) = name.rsplit_once('-').ok_or_else(|| {
            AdError::Config(format!(
                "AD preset name '{name}' is not {{env}}-{{preset}}, e.g. darkroom-quick"
            ))
        })?;
        Self::from_table(preset_table(env, preset)?)
    }

    /// A config from a (possibly overridden) TOML table.
    pub fn from_table(table: toml::Table) -> Result<Self, AdError> {
        let cfg = crate::presets::resolve::<AdConfig>("ad", table)
            .map_err(|e| AdError::Config(e.to_string()))?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks the values: every count at least 1, every number finite and in
    /// its range (named in the error).
    pub fn validate(&self) -> Result<(), AdError> {
        use crate::guard::{Range, check_counts, check_numbers};
        self.model.validate()?;
        check_counts(&[
            ("batch_size", i128::from(self.batch_size)),
            ("updates", self.updates as i128),
            ("log_every", self.log_every as i128),
            ("checkpoint_every", self.checkpoint_every as i128),
            ("episode_stride_max", self.episode_stride_max as i128),
        ])
        .map_err(AdError::Config)?;
        crate::guard::check_torch_threads(self.torch_threads).map_err(AdError::Config)?;
        check_numbers(&[
            ("learning_rate", self.learning_rate, Range::UNIT_OPEN_LOW),
            ("beta1", self.beta1, Range::UNIT_OPEN_HIGH),
            ("beta2", self.beta2, Range::UNIT_OPEN_HIGH),
            ("grad_clip", self.grad_clip, Range::POSITIVE),
            (
                "warmup_fraction",
                self.warmup_fraction,
                Range::UNIT_OPEN_HIGH,
            ),
            ("rtg_scale", f64::from(self.rtg_scale), Range::POSITIVE),
            ("ctg_scale", f64::from(self.ctg_scale), Range::POSITIVE),
            (
                "val_fraction",
                self.val_fraction,
                Range::new(0.0, false, 0.9, true),
            ),
            ("train_fraction", self.train_fraction, Range::UNIT_OPEN_LOW),
        ])
        .map_err(AdError::Config)
    }

    /// Learning rate at `update`: linear warm-up, then cosine to 10% of the peak.
    pub fn lr_at(&self, update: usize) -> f64 {
        let warm = (self.warmup_fraction * self.updates as f64).max(1.0);
        let u = update as f64;
        if u < warm {
            return self.learning_rate * (u + 1.0) / warm;
        }
        let progress = ((u - warm) / (self.updates as f64 - warm).max(1.0)).min(1.0);
        let floor = 0.1 * self.learning_rate;
        floor + 0.5 * (self.learning_rate - floor) * (1.0 + (std::f64::consts::PI * progress).cos())
    }
}

/// What a checkpoint must know besides the weights: sizes, normalisation and
/// the data it was trained on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdSpec {
    pub env: String,
    pub obs_dim: usize,
    /// Width of the action part of a token (n for discrete, else the vector length).
    pub action_dim: usize,
    pub discrete: bool,
    pub obs_mean: Vec<f32>,
    pub obs_std: Vec<f32>,
    /// The dataset file and its generating config (JSON).
    pub dataset: String,
    pub dataset_config: String,
    /// The pretraining tasks behind the dataset (for the held-out check).
    pub pretrain_tasks: Option<PretrainTasks>,
    /// Point and Car: the dataset's macro action (MuJoCo physics steps per
    /// agent action); evaluation builds its environments with it. Absent for
    /// SafeDarkRoom, and in Point and Car runs from before it was recorded,
    /// which [`AdAgent::load`] refuses.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub physics_steps_per_action: Option<usize>,
    /// The token layout ([`TOKEN_LAYOUT`]); absent in runs from before the
    /// arrived observation, which [`AdAgent::load`] refuses.
    #[serde(default)]
    pub token: Option<String>,
}

/// The token layout this code writes, recorded in every spec.
pub const TOKEN_LAYOUT: &str = "obs,arrived_obs,prev_action,reward,cost,rtg,ctg,start";

impl AdSpec {
    /// Checks sizes and normalisation read from a file: one mean and one
    /// positive, finite std per observation value, at least one action.
    pub fn check(&self) -> Result<(), String> {
        if self.obs_mean.len() != self.obs_dim || self.obs_std.len() != self.obs_dim {
            return Err(format!(
                "obs_dim {} with {} means and {} stds",
                self.obs_dim,
                self.obs_mean.len(),
                self.obs_std.len()
            ));
        }
        if self.action_dim == 0 {
            return Err("action_dim is 0".into());
        }
        if self.obs_mean.iter().any(|m| !m.is_finite())
            || self.obs_std.iter().any(|s| !(s.is_finite() && *s > 0.0))
        {
            return Err(
                "the observation normalisation holds values that are not finite (or a std <= 0)"
                    .into(),
            );
        }
        Ok(())
    }

    /// Token width: obs, arrived obs, previous action, reward, cost, RTG,
    /// CTG, episode start.
    pub fn token_dim(&self) -> usize {
        tokens::token_dim(self.obs_dim, self.action_dim, 2)
    }

    /// Appends an observation standardised with the dataset's mean and std.
    fn normalise_obs(&self, obs: &[f32], out: &mut Vec<f32>) {
        out.extend(
            obs.iter()
                .zip(self.obs_mean.iter().zip(&self.obs_std))
                .map(|(x, (m, s))| (x - m) / s),
        );
    }
}

// ---------------------------------------------------------------------------
// Tokens and the data loader
// ---------------------------------------------------------------------------

/// Appends one token: the shared layout ([`crate::tokens`]) with RTG and CTG
/// scaled, the reward as received.
#[allow(clippy::too_many_arguments)]
fn push_token(
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
fn action_part(spec: &AdSpec, h: &History, t: usize, out: &mut [f32]) {
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
struct HistorySteps {
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
    episodes: Vec<std::ops::Range<usize>>,
    /// (T,) class indices (discrete targets; continuous targets are `actions`).
    classes: Vec<i64>,
}

/// Histories ready for windows ([module docs](self): windows that show learning).
pub struct TokenSet {
    spec: AdSpec,
    cfg: AdConfig,
    histories: Vec<HistorySteps>,
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
    fn window_steps(&self, h: &HistorySteps, len: usize, rng: &mut ChaCha8Rng) -> Vec<usize> {
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
    fn push_window(&self, h: &HistorySteps, steps: &[usize], out: &mut Vec<f32>) {
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

// ---------------------------------------------------------------------------
// Model
// ---------------------------------------------------------------------------

/// Token encoder, the shared transformer, and the action head.
#[derive(Debug)]
pub struct AdModel {
    /// Two-layer MLP: token -> d_model.
    embed: nn::Sequential,
    transformer: Transformer,
    /// d_model -> action logits (discrete) or action mean (continuous).
    head: nn::Linear,
}

impl AdModel {
    pub fn new(p: &nn::Path, spec: &AdSpec, cfg: &AdConfig) -> Result<Self, AdError> {
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

// ---------------------------------------------------------------------------
// Training
// ---------------------------------------------------------------------------

/// One line of `metrics.jsonl`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdMetrics {
    pub update: usize,
    /// Environment steps of data in the training windows seen so far.
    pub samples: u64,
    /// Mean training loss since the previous line.
    pub train_loss: f64,
    /// Mean training accuracy since the previous line (discrete only).
    pub train_accuracy: Option<f64>,
    /// Loss on fixed windows from held-out tasks (None without held-out tasks).
    pub val_loss: Option<f64>,
    pub val_accuracy: Option<f64>,
    pub learning_rate: f64,
    /// Wall-clock seconds since the run (or its resumption) started.
    pub seconds: f64,
}

/// Where and how to train.
#[derive(Clone, Debug)]
pub struct TrainRequest<'a> {
    pub cfg: &'a AdConfig,
    pub data: &'a HistoryFile,
    /// The dataset's path (recorded in the checkpoint).
    pub dataset_path: &'a Path,
    /// The run folder; created if missing.
    pub run_dir: &'a Path,
    /// Continue from this `checkpoints/step_N` folder of `run_dir`.
    pub resume: Option<&'a Path>,
}

/// What a finished run reports.
#[derive(Clone, Debug)]
pub struct TrainSummary {
    pub run_dir: PathBuf,
    /// Histories trained on and held out for the validation loss.
    pub train_histories: usize,
    pub val_histories: usize,
    pub updates: usize,
    pub first: Option<AdMetrics>,
    pub last: Option<AdMetrics>,
    pub resumed_from: usize,
}

/// The spec of a model trained on `data`.
fn spec_for(data: &HistoryFile, dataset_path: &Path) -> AdSpec {
    let info = &data.info;
    let (discrete, action_dim) = match info.action_n {
        Some(n) => (true, n),
        None => (false, info.action_dim),
    };
    let o = info.obs_dim;
    let mut sum = vec![0.0f64; o];
    let mut sq = vec![0.0f64; o];
    let mut n = 0.0f64;
    for h in &data.histories {
        for row in h.observations.chunks(o) {
            for i in 0..o {
                sum[i] += row[i] as f64;
                sq[i] += (row[i] as f64).powi(2);
            }
            n += 1.0;
        }
    }
    let mean: Vec<f32> = sum.iter().map(|s| (s / n.max(1.0)) as f32).collect();
    let std: Vec<f32> = sq
        .iter()
        .zip(&mean)
        .map(|(s, &m)| {
            ((s / n.max(1.0) - (m as f64).powi(2))
                .max(0.0)
                .sqrt()
                .max(1e-3)) as f32
        })
        .collect();
    let pretrain_tasks = serde_json::from_str::<serde_json::Value>(&info.config)
        .ok()
        .and_then(|v| serde_json::from_value(v["pretrain_tasks"].clone()).ok());
    AdSpec {
        env: info.env.clone(),
        obs_dim: o,
        action_dim,
        discrete,
        obs_mean: mean,
        obs_std: std,
        dataset: dataset_path.display().to_string(),
        dataset_config: info.config.clone(),
        pretrain_tasks,
        physics_steps_per_action: info.physics_steps_per_action,
        token: Some(TOKEN_LAYOUT.into()),
    }
}

#[derive(Debug, Serialize, Deserialize)]
struct TrainState {
    update: usize,
    samples: u64,
}

fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), AdError> {
    let tmp = crate::data::histories::temp_path(path);
    fs::write(&tmp, bytes).map_err(|e| io_err(&tmp, e))?;
    fs::rename(&tmp, path).map_err(|e| io_err(path, e))
}

/// The model shape recorded in each checkpoint's manifest.
fn model_manifest(cfg: &AdConfig, spec: &AdSpec) -> serde_json::Value {
    serde_json::json!({
        "transformer": cfg.model,
        "token_dim": spec.token_dim(),
        "obs_dim": spec.obs_dim,
        "act_dim": spec.action_dim,
        "n_actions": spec.discrete.then_some(spec.action_dim),
    })
}

/// Writes `checkpoints/step_{update}` as one atomic folder (weights, Adam's
/// moments, `state.json`, with the manifest's sizes and SHA-256s), keeping the
/// newest `keep_checkpoints`.
fn save_checkpoint(
    run: &RunDir,
    cfg: &AdConfig,
    spec: &AdSpec,
    vs: &nn::VarStore,
    opt: &Adam,
    state: &TrainState,
) -> Result<PathBuf, AdError> {
    let dir = run.write_checkpoint(
        state.update as u64,
        "ad",
        &spec.env,
        spec.physics_steps_per_action,
        model_manifest(cfg, spec),
        cfg.keep_checkpoints,
        |dir| {
            let wrap = |path: PathBuf, e: String| CheckpointError::Invalid {
                path,
                problem: e,
                fix: "check the disk".into(),
            };
            let p = dir.join("model.safetensors");
            vs.save(&p).map_err(|e| wrap(p.clone(), e.to_string()))?;
            let p = dir.join("adam.safetensors");
            opt.save(&p).map_err(|e| wrap(p.clone(), e.to_string()))?;
            let p = dir.join("state.json");
            let json =
                serde_json::to_vec_pretty(state).map_err(|e| wrap(p.clone(), e.to_string()))?;
            fs::write(&p, json).map_err(|e| wrap(p.clone(), e.to_string()))
        },
    )?;
    Ok(dir)
}

/// The fields of two configs that differ, as `name: old -> new`.
fn config_diff(old: &AdConfig, new: &AdConfig) -> Vec<String> {
    let (a, b) = (
        serde_json::to_value(old).unwrap_or_default(),
        serde_json::to_value(new).unwrap_or_default(),
    );
    let mut out = Vec::new();
    fn walk(prefix: &str, a: &serde_json::Value, b: &serde_json::Value, out: &mut Vec<String>) {
        match (a, b) {
            (serde_json::Value::Object(x), serde_json::Value::Object(y)) => {
                let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
                let null = serde_json::Value::Null;
                for k in keys {
                    let name = if prefix.is_empty() {
                        k.clone()
                    } else {
                        format!("{prefix}.{k}")
                    };
                    walk(
                        &name,
                        x.get(k).unwrap_or(&null),
                        y.get(k).unwrap_or(&null),
                        out,
                    );
                }
            }
            _ if a != b => out.push(format!("{prefix}: {a} -> {b}")),
            _ => {}
        }
    }
    walk("", &a, &b, &mut out);
    out
}

/// Loads `ckpt` (a `checkpoints/step_N` folder, verified against its
/// manifest) into the model and optimizer; returns its counters.
fn load_checkpoint_into(
    ckpt: &Path,
    cfg: &AdConfig,
    spec: &AdSpec,
    vs: &mut nn::VarStore,
    opt: &mut Adam,
) -> Result<TrainState, AdError> {
    let manifest = read_manifest(ckpt)?;
    manifest.check_compatible(
        ckpt,
        "ad",
        &spec.env,
        spec.physics_steps_per_action,
        &model_manifest(cfg, spec),
    )?;
    let bad = |file: &str, e: String| {
        AdError::Checkpoint(CheckpointError::Invalid {
            path: ckpt.join(file),
            problem: e,
            fix: "resume from an earlier checkpoints/step_N folder, or start a new run".into(),
        })
    };
    vs.load(ckpt.join("model.safetensors"))
        .map_err(|e| bad("model.safetensors", e.to_string()))?;
    if let Some((name, n)) = crate::guard::non_finite_variable(vs) {
        return Err(bad(
            "model.safetensors",
            format!("weight {name} holds {n} NaN or infinite values"),
        ));
    }
    opt.load(&ckpt.join("adam.safetensors"))
        .map_err(|e| bad("adam.safetensors", e))?;
    let text = fs::read_to_string(ckpt.join("state.json"))
        .map_err(|e| bad("state.json", e.to_string()))?;
    serde_json::from_str(&text).map_err(|e| bad("state.json", e.to_string()))
}

/// Trains (or resumes) a model on the histories, writing the run folder.
/// `on_log` sees every metrics line (for a progress bar), `on_update` every update.
///
/// A NaN or infinite loss or gradient stops training before the update is
/// applied ([`AdError::NonFinite`], naming the update and the last good
/// checkpoint); a stop request ([`crate::stop`]) ends it after the current
/// update with a checkpoint ([`AdError::Interrupted`]).
pub fn train(
    req: &TrainRequest<'_>,
    on_log: &mut dyn FnMut(&AdMetrics),
    on_update: &mut dyn FnMut(usize),
) -> Result<TrainSummary, AdError> {
    let cfg = req.cfg;
    cfg.validate()?;
    // Finite values and actions inside the action space, or libtorch would
    // train to NaN or abort on an out-of-range class index.
    req.data.validate(req.dataset_path)?;
    let dir = req.run_dir;
    if cfg.torch_threads > 0 {
        tch::set_num_threads(cfg.torch_threads);
    }
    let spec = spec_for(req.data, req.dataset_path);
    memory_estimate(cfg, &spec, req.data.total_steps())
        .check()
        .map_err(AdError::Config)?;
    let ck = dir.join("checkpoints");
    fs::create_dir_all(&ck).map_err(|e| io_err(&ck, e))?;
    let run = RunDir {
        path: dir.to_path_buf(),
    };

    // Hold out the histories of the last `val_fraction` of the tasks.
    let hists = &req.data.histories;
    let mut tasks: Vec<&safety_envs::Task> = Vec::new();
    for h in hists {
        if !tasks.contains(&&h.task) {
            tasks.push(&h.task);
        }
    }
    let n_val_tasks = ((tasks.len() as f64) * cfg.val_fraction).floor() as usize;
    let val_tasks = &tasks[tasks.len() - n_val_tasks..];
    // The dataset-size ablation trains on the first `train_fraction` of the
    // other tasks (every cost limit of each), against the same held-out ones.
    let n_train_tasks = tasks.len() - n_val_tasks;
    let kept = ((n_train_tasks as f64 * cfg.train_fraction).ceil() as usize)
        .clamp(1, n_train_tasks.max(1));
    let train_tasks = &tasks[..kept];
    let train_h: Vec<&History> = hists
        .iter()
        .filter(|h| train_tasks.contains(&&h.task))
        .collect();
    let val_h: Vec<&History> = hists
        .iter()
        .filter(|h| val_tasks.contains(&&h.task))
        .collect();
    let train_set = TokenSet::new(&spec, cfg, &train_h);
    let val_set = TokenSet::new(&spec, cfg, &val_h);

    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let mut vs = nn::VarStore::new(Device::cuda_if_available());
    tch::manual_seed(cfg.seed as i64);
    let model = AdModel::new(&vs.root(), &spec, cfg)?;
    let mut opt = Adam::new(
        &vs,
        AdamConfig {
            lr: cfg.learning_rate,
            beta1: cfg.beta1,
            beta2: cfg.beta2,
            eps: 1e-8,
            grad_clip: Some(cfg.grad_clip),
        },
    );

    // Resume or start fresh; the config must match the folder's except for
    // `updates`, which may grow (the learning-rate schedule then stretches to
    // the new total).
    let mut state = TrainState {
        update: 0,
        samples: 0,
    };
    let config_path = dir.join("config.toml");
    let config_toml = toml::to_string_pretty(cfg).map_err(|e| io_err(dir, e))?;
    let mut last_ckpt: Option<PathBuf> = None;
    if let Some(ckpt) = req.resume {
        let old_text = fs::read_to_string(&config_path).map_err(|e| io_err(&config_path, e))?;
        let old = AdConfig::from_toml(&old_text).map_err(|e| io_err(&config_path, e))?;
        let differ: Vec<String> = config_diff(&old, cfg)
            .into_iter()
            .filter(|d| !d.starts_with("updates:") && !d.starts_with("keep_checkpoints:"))
            .collect();
        if !differ.is_empty() {
            return Err(AdError::Config(format!(
                "cannot resume {}: these settings differ from its config.toml: {}; only updates \
                 (to extend the run) and keep_checkpoints may change",
                dir.display(),
                differ.join(", ")
            )));
        }
        // The data must be what the run was trained on: same sizes and the
        // same observation normalisation (the agent reads spec.json).
        let spec_path = dir.join("spec.json");
        let text = fs::read_to_string(&spec_path).map_err(|e| io_err(&spec_path, e))?;
        let saved: AdSpec = serde_json::from_str(&text).map_err(|e| io_err(&spec_path, e))?;
        fn key(s: &AdSpec) -> (usize, usize, bool, &[f32], &[f32], &str) {
            (
                s.obs_dim,
                s.action_dim,
                s.discrete,
                &s.obs_mean,
                &s.obs_std,
                &s.dataset_config,
            )
        }
        if key(&saved) != key(&spec) {
            return Err(AdError::Config(format!(
                "cannot resume {}: the dataset {} is not the one the run was trained on ({}, \
                 recorded in {}); resume with that dataset or start a new run",
                dir.display(),
                req.dataset_path.display(),
                saved.dataset,
                spec_path.display()
            )));
        }
        state = load_checkpoint_into(ckpt, cfg, &spec, &mut vs, &mut opt)?;
        if state.update > cfg.updates {
            return Err(AdError::Config(format!(
                "cannot resume {}: it has done {} updates, more than updates = {}; pass --set updates={} or more",
                ckpt.display(),
                state.update,
                cfg.updates,
                state.update
            )));
        }
        // Lines logged after the checkpoint are redone: drop them.
        crate::checkpoint::truncate_metrics(
            &dir.join("metrics.jsonl"),
            "update",
            state.update as u64,
        )?;
        last_ckpt = Some(ckpt.to_path_buf());
    } else {
        let spec_json = serde_json::to_vec_pretty(&spec).map_err(|e| io_err(dir, e))?;
        write_atomic(&dir.join("spec.json"), &spec_json)?;
    }
    // The resolved config (a grown `updates` included).
    write_atomic(&config_path, config_toml.as_bytes())?;
    let resumed_from = state.update;
    // Skip the sampling stream forward so a resumed run does not replay windows.
    rng.set_word_pos((resumed_from as u128) << 16);

    // Fixed validation windows.
    let device = vs.device();
    let val_batches: Vec<(Tensor, Tensor)> = if val_set.is_empty() {
        Vec::new()
    } else {
        let mut vrng = ChaCha8Rng::seed_from_u64(cfg.seed ^ 0x5eed);
        (0..4)
            .map(|_| val_set.sample(cfg.batch_size.min(64), cfg.model.max_len, &mut vrng))
            .collect::<Result<_, _>>()?
    };

    let metrics_path = dir.join("metrics.jsonl");
    let mut metrics_file = fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&metrics_path)
        .map_err(|e| io_err(&metrics_path, e))?;
    let started = Instant::now();
    let (mut loss_sum, mut acc_sum, mut n_sum) = (0.0, 0.0, 0.0);
    let mut first = None;
    let mut last = None;
    let window = cfg.model.max_len;
    while state.update < cfg.updates {
        let lr = cfg.lr_at(state.update);
        opt.set_lr(lr);
        let (x, y) = train_set.sample(cfg.batch_size, window, &mut rng)?;
        let out = model.forward_t(&x.to_device(device), true)?;
        let (l, acc) = loss(&out, &y.to_device(device), spec.discrete);
        // Never apply a NaN or infinite step: stop with the last good checkpoint.
        opt.try_backward_step(&l).map_err(|e| AdError::NonFinite {
            update: state.update + 1,
            what: e.to_string(),
            checkpoint: last_ckpt.clone(),
        })?;
        loss_sum += l.double_value(&[]);
        acc_sum += acc.map_or(0.0, |a| a.double_value(&[]));
        n_sum += 1.0;
        state.update += 1;
        state.samples += (cfg.batch_size * window) as u64;
        on_update(state.update);

        let stop = crate::stop::requested();
        let done = state.update == cfg.updates;
        if state.update.is_multiple_of(cfg.log_every) || done || stop {
            let (val_loss, val_acc) = if val_batches.is_empty() {
                (None, None)
            } else {
                let (mut vl, mut va) = (0.0, 0.0);
                tch::no_grad(|| -> Result<(), AdError> {
                    for (vx, vy) in &val_batches {
                        let out = model.forward_t(&vx.to_device(device), false)?;
                        let (l, a) = loss(&out, &vy.to_device(device), spec.discrete);
                        vl += l.double_value(&[]);
                        va += a.map_or(0.0, |a| a.double_value(&[]));
                    }
                    Ok(())
                })?;
                let k = val_batches.len() as f64;
                (Some(vl / k), spec.discrete.then_some(va / k))
            };
            let m = AdMetrics {
                update: state.update,
                samples: state.samples,
                train_loss: loss_sum / n_sum,
                train_accuracy: spec.discrete.then_some(acc_sum / n_sum),
                val_loss,
                val_accuracy: val_acc,
                learning_rate: lr,
                seconds: started.elapsed().as_secs_f64(),
            };
            let line = serde_json::to_string(&m).map_err(|e| io_err(dir, e))?;
            writeln!(metrics_file, "{line}").map_err(|e| io_err(&metrics_path, e))?;
            on_log(&m);
            if first.is_none() {
                first = Some(m.clone());
            }
            last = Some(m);
            (loss_sum, acc_sum, n_sum) = (0.0, 0.0, 0.0);
        }
        if state.update.is_multiple_of(cfg.checkpoint_every) || done || stop {
            last_ckpt = Some(save_checkpoint(&run, cfg, &spec, &vs, &opt, &state)?);
        }
        if stop && !done {
            return Err(AdError::Interrupted {
                checkpoint: last_ckpt.unwrap_or_default(),
                updates: state.update,
            });
        }
    }
    Ok(TrainSummary {
        run_dir: dir.to_path_buf(),
        train_histories: train_set.len(),
        val_histories: val_set.len(),
        updates: state.update,
        first,
        last,
        resumed_from,
    })
}

/// What supervised pretraining with `cfg` on `steps` dataset steps will
/// allocate: the tokenised dataset, parameters with their gradients and
/// Adam's moments, one sampled batch and its activations. With a CUDA device
/// (AD takes one when libtorch sees it) only the host's part is counted: the
/// tokens and one sampled batch.
pub fn memory_estimate(
    cfg: &AdConfig,
    spec: &AdSpec,
    steps: usize,
) -> crate::guard::MemoryEstimate {
    use crate::guard::{transformer_activation_bytes, transformer_parameters};
    let (d, k, a) = (
        cfg.model.d_model as f64,
        spec.token_dim() as f64,
        spec.action_dim as f64,
    );
    let params = k * d + d + d * d + d + transformer_parameters(&cfg.model) + d * a + a;
    let (b, t) = (cfg.batch_size as f64, cfg.model.max_len as f64);
    let mut m = crate::guard::MemoryEstimate {
        levers: "batch_size, model.max_len, model.d_model or model.n_layers".into(),
        ..Default::default()
    };
    m.add("tokenised dataset", 4.0 * steps as f64 * (k + a + 2.0));
    if tch::Cuda::is_available() {
        m.add("one sampled batch", 4.0 * b * t * (k + a));
        return m;
    }
    m.add("parameters", 4.0 * params);
    m.add("gradients and Adam moments", 3.0 * 4.0 * params);
    m.add(
        "one batch's activations",
        transformer_activation_bytes(&cfg.model, b) + 4.0 * b * t * (2.0 * k + 3.0 * d + 2.0 * a),
    );
    m
}

/// The `pretrain --method ad` command: a preset (or a resumed run's config)
/// with `--set` overrides, the dataset, a progress bar; returns the summary.
/// Without a terminal the bar is hidden and each metrics line goes to stderr.
pub fn pretrain_command(
    env: &str,
    preset: &str,
    dataset: Option<&Path>,
    resume: Option<&Path>,
    sets: &[String],
    out: &Path,
) -> Result<TrainSummary, AdError> {
    // `--resume` names a run folder (its latest checkpoint) or one
    // checkpoints/step_N folder; every file it reads is named in errors.
    let resume = match resume {
        Some(path) => {
            if path.join("spec.json").is_file() && !path.join("checkpoints").is_dir() {
                return Err(AdError::Config(format!(
                    "{}: an AD run written before checkpoints were atomic folders; it can be \
                     evaluated but not resumed: start a new run",
                    path.display()
                )));
            }
            Some(RunDir::resolve_resume(path)?)
        }
        None => None,
    };
    let damaged = |p: &Path, e: String| {
        AdError::Checkpoint(CheckpointError::Invalid {
            path: p.to_path_buf(),
            problem: e,
            fix: "restore the run's file from a copy, or start a new run".into(),
        })
    };
    let mut table = match &resume {
        Some((run, _)) => {
            let p = run.config_path();
            let text = fs::read_to_string(&p).map_err(|e| damaged(&p, e.to_string()))?;
            text.parse::<toml::Table>()
                .map_err(|e| damaged(&p, e.to_string()))?
        }
        None => preset_table(env, preset)?,
    };
    crate::presets::apply_overrides(&mut table, sets)
        .map_err(|e| AdError::Config(e.to_string()))?;
    let cfg = AdConfig::from_table(table)?;
    let dataset_path = match (dataset, &resume) {
        (Some(p), _) => p.to_path_buf(),
        (None, Some((run, _))) => {
            let p = run.path.join("spec.json");
            let text = fs::read_to_string(&p).map_err(|e| damaged(&p, e.to_string()))?;
            let spec: AdSpec =
                serde_json::from_str(&text).map_err(|e| damaged(&p, e.to_string()))?;
            PathBuf::from(spec.dataset)
        }
        (None, None) => {
            return Err(AdError::Config(
                "--method ad needs --dataset FILE (make one with `icrl dataset --env ...`)".into(),
            ));
        }
    };
    let data = crate::data::histories::read_histories(&dataset_path, Some(env))?;
    let run_dir = match &resume {
        Some((run, _)) => run.path.clone(),
        None => RunDir::create(out, env, "ad", cfg.seed)?.path,
    };
    let bar = indicatif::ProgressBar::new(cfg.updates as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{prefix} [{elapsed_precise}] {wide_bar} {pos}/{len} updates ({per_sec}, eta {eta}) {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_prefix(format!("ad {env}"));
    let hidden = bar.is_hidden();
    let req = TrainRequest {
        cfg: &cfg,
        data: &data,
        dataset_path: &dataset_path,
        run_dir: &run_dir,
        resume: resume.as_ref().map(|(_, ckpt)| ckpt.as_path()),
    };
    let fmt = |m: &AdMetrics| {
        format!(
            "update {} loss {:.4} acc {} val_loss {} val_acc {} lr {:.2e} {:.0}s",
            m.update,
            m.train_loss,
            m.train_accuracy.map_or("-".into(), |a| format!("{a:.3}")),
            m.val_loss.map_or("-".into(), |a| format!("{a:.4}")),
            m.val_accuracy.map_or("-".into(), |a| format!("{a:.3}")),
            m.learning_rate,
            m.seconds
        )
    };
    let summary = train(
        &req,
        &mut |m| {
            if hidden {
                eprintln!("{}", fmt(m));
            } else {
                bar.set_message(fmt(m));
            }
        },
        &mut |u| bar.set_position(u as u64),
    )?;
    bar.finish();
    Ok(summary)
}

/// Draws `metrics.jsonl` of an AD run: loss and accuracy (training windows and
/// held-out tasks) against updates, into `<run>/training_loss.{png,svg}`.
pub fn plot_training(run_dir: &Path) -> Result<Vec<PathBuf>, AdError> {
    use crate::plots::{Band, METHOD_COLOURS, Panel, draw_panels};
    let path = run_dir.join("metrics.jsonl");
    let text = fs::read_to_string(&path).map_err(|e| io_err(&path, e))?;
    let records: Vec<AdMetrics> = text
        .lines()
        .map(serde_json::from_str)
        .collect::<Result<_, _>>()
        .map_err(|e| io_err(&path, e))?;
    if records.is_empty() {
        return Err(io_err(&path, "no metrics recorded yet"));
    }
    let x: Vec<f64> = records.iter().map(|m| m.update as f64).collect();
    let band = |label: &str, ys: Vec<Option<f64>>, colour| {
        let pts: Vec<(f64, f64)> = x
            .iter()
            .zip(ys)
            .filter_map(|(&x, y)| y.map(|y| (x, y)))
            .collect();
        Band {
            label: label.into(),
            x: pts.iter().map(|p| p.0).collect(),
            mean: pts.iter().map(|p| p.1).collect(),
            se: Vec::new(),
            colour,
            thin: false,
        }
    };
    let loss = Panel {
        title: "supervised loss (Eq. 16)".into(),
        x_label: "update".into(),
        y_label: "cross-entropy".into(),
        bands: vec![
            band(
                "training windows",
                records.iter().map(|m| Some(m.train_loss)).collect(),
                METHOD_COLOURS[0],
            ),
            band(
                "held-out tasks",
                records.iter().map(|m| m.val_loss).collect(),
                METHOD_COLOURS[1],
            ),
        ],
        ..Default::default()
    };
    let acc = Panel {
        title: "action accuracy".into(),
        x_label: "update".into(),
        y_label: "fraction of actions predicted".into(),
        bands: vec![
            band(
                "training windows",
                records.iter().map(|m| m.train_accuracy).collect(),
                METHOD_COLOURS[0],
            ),
            band(
                "held-out tasks",
                records.iter().map(|m| m.val_accuracy).collect(),
                METHOD_COLOURS[1],
            ),
        ],
        ..Default::default()
    };
    let panels: Vec<Panel> = if records[0].train_accuracy.is_some() {
        vec![loss, acc]
    } else {
        vec![Panel {
            title: "supervised loss (Eq. 17)".into(),
            y_label: "squared error".into(),
            ..loss
        }]
    };
    draw_panels(&run_dir.join("training_loss"), 1, panels.len(), &panels)
        .map_err(|e| io_err(run_dir, e))
}

// ---------------------------------------------------------------------------
// The frozen agent
// ---------------------------------------------------------------------------

/// A trained AD model acting in context: parameters frozen, a KV cache over
/// the trajectory so far, RTG and CTG restarting at the targets each episode
/// and decreasing by the rewards and costs received.
///
/// The context holds at most `max_len` steps (the training window). When it
/// is full, the cache is rebuilt from the most recent `max_len / 2` steps at
/// positions starting from 0, as training windows start anywhere in a history.
pub struct AdAgent {
    vs: nn::VarStore,
    model: AdModel,
    spec: AdSpec,
    cfg: AdConfig,
    cache: KvCache,
    /// The tokens in the cache, (B, L, token_dim).
    window: Option<Tensor>,
    targets: Vec<(f32, f32)>,
    rtg: Vec<f32>,
    ctg: Vec<f32>,
}

/// What a checkpoint folder says about its run.
#[derive(Clone, Debug)]
pub struct CheckpointInfo {
    pub dir: PathBuf,
    pub updates_done: usize,
    pub updates_planned: usize,
    pub pretrain_tasks: Option<PretrainTasks>,
    pub env: String,
    /// Point and Car: physics steps per agent action of the training data.
    pub physics_steps_per_action: Option<usize>,
}

impl AdAgent {
    /// Loads a run written by [`train`]: its folder (the latest checkpoint)
    /// or one `checkpoints/step_N` folder, verified against the manifest's
    /// sizes and SHA-256s. A run written before checkpoints were folders
    /// (weights at the top of the run folder) loads with a warning that its
    /// bytes cannot be verified. Weights holding NaN or infinity are refused.
    pub fn load(path: &Path) -> Result<(Self, CheckpointInfo), AdError> {
        let (run_dir, ckpt) = if path.join(crate::checkpoint::MANIFEST).is_file()
            || path.join("checkpoints").is_dir()
        {
            let (run, ckpt) = RunDir::resolve_resume(path)?;
            (run.path, ckpt)
        } else {
            eprintln!(
                "warning: {}: an AD run written before checkpoints were folders with checksums; \
                 its bytes cannot be verified",
                path.display()
            );
            (path.to_path_buf(), path.to_path_buf())
        };
        if ckpt != run_dir {
            let manifest = read_manifest(&ckpt)?;
            if manifest.method != "ad" {
                return Err(AdError::Config(format!(
                    "{}: a {} checkpoint, not an AD one",
                    ckpt.display(),
                    manifest.method
                )));
            }
        }
        let bad = |p: PathBuf, e: String| {
            AdError::Checkpoint(CheckpointError::Invalid {
                path: p,
                problem: e,
                fix: "evaluate an earlier checkpoints/step_N folder, or a complete AD run folder"
                    .into(),
            })
        };
        let read = |p: PathBuf| fs::read_to_string(&p).map_err(|e| bad(p.clone(), e.to_string()));
        let p = run_dir.join("config.toml");
        let cfg = AdConfig::from_toml(&read(p.clone())?).map_err(|e| bad(p, e.to_string()))?;
        let p = run_dir.join("spec.json");
        let spec: AdSpec =
            serde_json::from_str(&read(p.clone())?).map_err(|e| bad(p.clone(), e.to_string()))?;
        spec.check().map_err(|e| bad(p.clone(), e))?;
        if spec.token.as_deref() != Some(TOKEN_LAYOUT) {
            return Err(bad(
                p,
                format!(
                    "this run's tokens have the layout {:?}; this version reads {TOKEN_LAYOUT:?} \
                     (since 2026-11-30 a token also carries the observation the previous action \
                     arrived at): retrain it with `icrl pretrain --method ad`",
                    spec.token
                        .as_deref()
                        .unwrap_or("obs,prev_action,reward,cost,rtg,ctg,start")
                ),
            ));
        }
        memory_estimate(&cfg, &spec, 0)
            .check()
            .map_err(|e| bad(run_dir.join("config.toml"), e))?;
        let p = ckpt.join("state.json");
        let state: TrainState =
            serde_json::from_str(&read(p.clone())?).map_err(|e| bad(p, e.to_string()))?;
        let physics = spec
            .env
            .parse::<safety_envs::EnvName>()
            .ok()
            .and_then(|env| env.physics_steps_per_action(None));
        if physics.is_some() && spec.physics_steps_per_action.is_none() {
            return Err(bad(
                run_dir.join("spec.json"),
                format!(
                    "this {} run does not record its data's macro action, so it was trained on a dataset \
                     made when an agent action was {} physics steps (before 2026-11-30); the environments \
                     now take {} (5 Safety-Gymnasium steps x 10 physics steps): regenerate the dataset \
                     (`icrl dataset`) and retrain",
                    spec.env,
                    safety_envs::OLD_PHYSICS_STEPS_PER_ACTION,
                    safety_envs::PHYSICS_STEPS_PER_ACTION
                ),
            ));
        }
        let mut vs = nn::VarStore::new(Device::cuda_if_available());
        let model = AdModel::new(&vs.root(), &spec, &cfg)?;
        let p = ckpt.join("model.safetensors");
        vs.load(&p).map_err(|e| bad(p.clone(), e.to_string()))?;
        if let Some((name, n)) = crate::guard::non_finite_variable(&vs) {
            return Err(bad(
                p,
                format!("weight {name} holds {n} NaN or infinite values: this model cannot act"),
            ));
        }
        vs.freeze();
        let info = CheckpointInfo {
            dir: ckpt.clone(),
            updates_done: state.update,
            updates_planned: cfg.updates,
            pretrain_tasks: spec.pretrain_tasks.clone(),
            env: spec.env.clone(),
            physics_steps_per_action: spec.physics_steps_per_action,
        };
        let cache = model.transformer.new_cache();
        Ok((
            AdAgent {
                vs,
                model,
                spec,
                cfg,
                cache,
                window: None,
                targets: Vec::new(),
                rtg: Vec::new(),
                ctg: Vec::new(),
            },
            info,
        ))
    }

    /// The parameters (for a checksum before and after evaluation).
    pub fn varstore(&self) -> &nn::VarStore {
        &self.vs
    }

    pub fn spec(&self) -> &AdSpec {
        &self.spec
    }
}

impl InContextAgent for AdAgent {
    fn reset(&mut self, conditioning: &[Conditioning]) -> Result<(), AgentError> {
        self.targets = conditioning
            .iter()
            .map(|c| match *c {
                Conditioning::Targets { rtg, ctg } => Ok((rtg, ctg)),
                Conditioning::Budget { ctg } => Err(AgentError::Input(format!(
                    "the AD agent is conditioned on RTG and CTG targets, got a bare budget {ctg}"
                ))),
            })
            .collect::<Result<_, _>>()?;
        self.rtg = self.targets.iter().map(|t| t.0).collect();
        self.ctg = self.targets.iter().map(|t| t.1).collect();
        self.cache.reset();
        self.window = None;
        Ok(())
    }

    fn act(&mut self, input: &StepInput<'_>, greedy: bool) -> Result<Actions, AgentError> {
        let b = self.targets.len();
        let (o, a) = (self.spec.obs_dim, self.spec.action_dim);
        if b == 0
            || input.obs.len() != b * o
            || input.arrived_obs.len() != b * o
            || input.prev_action.len() != b * a
            || input.reward.len() != b
            || input.cost.len() != b
            || input.episode_start.len() != b
        {
            return Err(AgentError::Input(format!(
                "expected {b} trajectories with obs_dim {o} and action width {a}; got obs {}, arrived_obs {}, prev_action {}, reward {}, cost {}, episode_start {}",
                input.obs.len(),
                input.arrived_obs.len(),
                input.prev_action.len(),
                input.reward.len(),
                input.cost.len(),
                input.episode_start.len()
            )));
        }
        let d = self.spec.token_dim();
        let mut rows = Vec::with_capacity(b * d);
        for i in 0..b {
            // RTG/CTG restart at the targets each episode and decrease by what
            // the previous action brought inside the episode, floored at 0 as
            // every training label is (module docs: conditioning).
            if input.episode_start[i] {
                (self.rtg[i], self.ctg[i]) = self.targets[i];
            } else {
                self.rtg[i] = (self.rtg[i] - input.reward[i]).max(0.0);
                self.ctg[i] = (self.ctg[i] - input.cost[i]).max(0.0);
            }
            let step = StepToken {
                obs: &input.obs[i * o..(i + 1) * o],
                arrived_obs: &input.arrived_obs[i * o..(i + 1) * o],
                prev_action: &input.prev_action[i * a..(i + 1) * a],
                reward: input.reward[i],
                cost: input.cost[i],
                to_go: &[],
                start: input.episode_start[i],
            };
            push_token(
                &self.spec,
                &self.cfg,
                step,
                self.rtg[i],
                self.ctg[i],
                &mut rows,
            );
        }
        let device = self.vs.device();
        let token = Tensor::from_slice(&rows)
            .view([b as i64, 1, d as i64])
            .to_device(device);
        let max_len = self.cfg.model.max_len;
        let out = tch::no_grad(|| -> Result<Tensor, AdError> {
            if self.cache.len() + 1 > max_len {
                // Slide: rebuild the cache from the most recent half window.
                let keep = (max_len / 2).max(1) - 1;
                let recent = match &self.window {
                    Some(w) => w.narrow(1, w.size()[1] - keep, keep),
                    None => Tensor::zeros([b as i64, 0, d as i64], (Kind::Float, device)),
                };
                self.cache.reset();
                if keep > 0 {
                    // Only the cache matters here; the outputs for old steps are dropped.
                    let _ = self.model.forward_step(&recent, &mut self.cache)?;
                }
                self.window = Some(recent);
            }
            let out = self.model.forward_step(&token, &mut self.cache)?; // (B, 1, A)
            self.window = Some(match &self.window {
                Some(w) => Tensor::cat(&[w, &token], 1),
                None => token.shallow_clone(),
            });
            Ok(out.squeeze_dim(1)) // (B, A)
        })
        .map_err(|e| match e {
            AdError::Torch(t) => AgentError::Torch(t),
            other => AgentError::Input(other.to_string()),
        })?;
        if self.spec.discrete {
            let idx = if greedy {
                out.argmax(-1, false)
            } else {
                out.softmax(-1, Kind::Float)
                    .multinomial(1, true)
                    .squeeze_dim(1)
            };
            let v: Vec<i64> = Vec::try_from(idx.to_device(Device::Cpu))?;
            Ok(Actions::Discrete(
                v.into_iter().map(|x| x as usize).collect(),
            ))
        } else {
            // The L2 head predicts the mean; acting uses it as is.
            let v: Vec<f32> = Vec::try_from(out.to_device(Device::Cpu).flatten(0, -1))?;
            Ok(Actions::Continuous(
                v.into_iter().map(|x| x.clamp(-1.0, 1.0)).collect(),
            ))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::dataset::{DatasetConfig, Source, generate};
    use safety_envs::EnvName;

    fn tiny_cfg() -> AdConfig {
        let mut cfg = AdConfig::preset("darkroom-quick").unwrap();
        cfg.model.n_layers = 2;
        cfg.model.d_model = 32;
        cfg.model.n_heads = 4;
        cfg.model.d_ff = 64;
        cfg.model.max_len = 40;
        cfg.model.attn_dropout = 0.0;
        cfg.model.resid_dropout = 0.0;
        cfg.model.embd_dropout = 0.0;
        cfg.batch_size = 16;
        cfg.updates = 120;
        cfg.learning_rate = 3e-3;
        cfg.log_every = 20;
        cfg.checkpoint_every = 60;
        cfg.val_fraction = 0.0;
        cfg
    }

    /// An empty temporary folder named after `what` and this process.
    fn fresh_dir(what: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("icrl-ad-{what}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        dir
    }

    /// A fresh training run of `cfg` on `data` into `dir`.
    fn request<'a>(cfg: &'a AdConfig, data: &'a HistoryFile, dir: &'a Path) -> TrainRequest<'a> {
        TrainRequest {
            cfg,
            data,
            dataset_path: Path::new("tiny.h5"),
            run_dir: dir,
            resume: None,
        }
    }

    fn tiny_data() -> HistoryFile {
        let mut d = DatasetConfig::paper(EnvName::DarkRoom, 2, 11);
        d.source = Source::NoisyOptimal;
        d.steps = 1500;
        d.cost_limits = vec![0.0];
        generate(&d, &|_| {}).unwrap().file
    }

    /// A history of `lens.len()` episodes of the given lengths: observation
    /// (episode, step), action = episode % 5, reward 1 and cost 1 at each
    /// episode's last step, next observation (episode, 100 + step).
    fn history_of(lens: &[usize]) -> History {
        let task = safety_envs::Task {
            grid_size: 9,
            goal: safety_envs::Cell { row: 0, col: 0 },
            obstacles: vec![],
        };
        let mut h = History::new(task, 0.0);
        for (e, &len) in lens.iter().enumerate() {
            for t in 0..len {
                let last = t + 1 == len;
                h.push(
                    &[e as f32, t as f32],
                    &[(e % 5) as f32],
                    if last { 1.0 } else { 0.0 },
                    if last { 1.0 } else { 0.0 },
                    &[e as f32, 100.0 + t as f32],
                    last,
                    false,
                );
            }
        }
        h
    }

    #[test]
    fn windows_join_whole_episodes_stride_apart() {
        let h = history_of(&[3, 4, 2, 5, 3, 4, 2, 3, 5, 4, 3, 2, 4, 3, 5, 2, 3, 4]);
        let mut spec = spec_for(&tiny_data(), Path::new("x.h5"));
        (spec.obs_mean, spec.obs_std) = (vec![0.0; 2], vec![1.0; 2]);
        let mut cfg = tiny_cfg();
        cfg.episode_stride_max = 3;
        let set = TokenSet::new(&spec, &cfg, &[&h]);
        let hs = &set.histories[0];
        let episode_of = |t: usize| hs.episodes.iter().position(|r| r.contains(&t)).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut strides_seen = [false; 4];
        for _ in 0..200 {
            let steps = set.window_steps(hs, 12, &mut rng);
            assert_eq!(steps.len(), 12);
            // Episodes in the window: whole after the first, one stride apart.
            let eps: Vec<usize> = steps.iter().map(|&t| episode_of(t)).collect();
            let mut distinct = eps.clone();
            distinct.dedup();
            let stride = distinct.get(1).map(|e| e - distinct[0]);
            for w in distinct.windows(2) {
                assert_eq!(Some(w[1] - w[0]), stride, "{eps:?}");
            }
            for (i, &t) in steps.iter().enumerate().skip(1) {
                if eps[i] != eps[i - 1] {
                    assert_eq!(t, hs.episodes[eps[i]].start, "{steps:?}");
                } else {
                    assert_eq!(t, steps[i - 1] + 1);
                }
            }
            if let Some(s) = stride {
                assert!((1..=3).contains(&s));
                strides_seen[s] = true;
            }
            // Each token says what the previous step in the window received.
            let mut x = Vec::new();
            set.push_window(hs, &steps, &mut x);
            let d = spec.token_dim();
            for (i, &t) in steps.iter().enumerate() {
                let tok = &x[i * d..(i + 1) * d];
                assert_eq!(
                    &tok[..2],
                    &[eps[i] as f32, (t - hs.episodes[eps[i]].start) as f32]
                );
                if i == 0 {
                    assert!(tok[2..11].iter().all(|&v| v == 0.0), "{tok:?}");
                    continue;
                }
                let p = steps[i - 1];
                let (pe, pt) = (eps[i - 1], p - hs.episodes[eps[i - 1]].start);
                // Arrived observation, the previous action (one-hot), reward, cost.
                assert_eq!(&tok[2..4], &[pe as f32, 100.0 + pt as f32]);
                let mut onehot = [0.0f32; 5];
                onehot[pe % 5] = 1.0;
                assert_eq!(&tok[4..9], &onehot);
                let ended = eps[i] != pe;
                assert_eq!(tok[9], if ended { 1.0 } else { 0.0 });
                assert_eq!(tok[10], if ended { 1.0 } else { 0.0 });
                assert_eq!(tok[d - 1], if ended { 1.0 } else { 0.0 });
                // CTG: the cost still to come in the episode, scaled; never negative.
                assert_eq!(tok[d - 2], 1.0 / cfg.ctg_scale);
            }
        }
        assert_eq!(strides_seen, [false, true, true, true]);
        // Stride 1 is the contiguous history.
        cfg.episode_stride_max = 1;
        let set = TokenSet::new(&spec, &cfg, &[&h]);
        for _ in 0..50 {
            let steps = set.window_steps(&set.histories[0], 12, &mut rng);
            assert!(steps.windows(2).all(|w| w[1] == w[0] + 1), "{steps:?}");
        }
    }

    #[test]
    fn the_ablation_trains_on_a_fraction_of_the_tasks() {
        let mut d = DatasetConfig::paper(EnvName::DarkRoom, 8, 11);
        d.source = Source::NoisyOptimal;
        d.steps = 300;
        d.cost_limits = vec![0.0, 5.0];
        let data = generate(&d, &|_| {}).unwrap().file;
        let mut cfg = tiny_cfg();
        (cfg.updates, cfg.val_fraction, cfg.train_fraction) = (2, 0.25, 0.5);
        let dir = fresh_dir("frac");
        let s = train(&request(&cfg, &data, &dir), &mut |_| {}, &mut |_| {}).unwrap();
        // 8 tasks: 2 held out; half of the other 6 trained on; 2 limits each.
        assert_eq!((s.train_histories, s.val_histories), (6, 4));
        let _ = fs::remove_dir_all(&dir);
    }

    #[test]
    fn presets_parse_and_match_table_2() {
        let t2 = AdConfig::preset("darkroom-table2").unwrap();
        assert_eq!(
            (
                t2.model.d_model,
                t2.model.d_ff,
                t2.model.n_layers,
                t2.model.n_heads,
                t2.model.max_len
            ),
            (64, 512, 8, 8, 100)
        );
        assert_eq!((t2.batch_size, t2.updates), (512, 300_000));
        assert_eq!(
            (
                t2.model.attn_dropout,
                t2.model.resid_dropout,
                t2.model.embd_dropout
            ),
            (0.5, 0.1, 0.3)
        );
        for env in ["darkroom", "point", "car"] {
            for p in ["table2", "quick"] {
                AdConfig::preset(&format!("{env}-{p}")).unwrap();
            }
        }
        let e = AdConfig::preset("darkroom-table1").unwrap_err().to_string();
        assert!(e.contains("ad-darkroom-quick"), "{e}");
    }

    #[test]
    fn to_go_labels_count_what_is_still_to_come() {
        let data = tiny_data();
        let h = &data.histories[0];
        let (rtg, ctg) = to_go(h, CtgLabel::Hindsight);
        let eps = h.episodes();
        let e = &eps[0];
        let ret: f32 = h.rewards[e.clone()].iter().sum();
        let cost: f32 = h.costs[e.clone()].iter().sum();
        assert_eq!(rtg[e.start], ret);
        assert_eq!(ctg[e.start], cost);
        assert_eq!(rtg[e.end - 1], h.rewards[e.end - 1]);
        assert_eq!(ctg[e.end - 1], h.costs[e.end - 1]);
        // Budget labels: the limit left before each step, never below 0.
        let mut h = history_of(&[4, 3]);
        h.costs = vec![1.0, 1.0, 0.0, 1.0, 1.0, 0.0, 0.0];
        h.cost_limit = 1.5;
        let (_, ctg) = to_go(&h, CtgLabel::Budget);
        assert_eq!(ctg, vec![1.5, 0.5, 0.0, 0.0, 1.5, 0.5, 0.5]);
    }

    #[test]
    fn supervised_loss_falls_and_the_agent_acts_from_a_checkpoint() {
        let data = tiny_data();
        let cfg = tiny_cfg();
        let dir = fresh_dir("test");
        let req = request(&cfg, &data, &dir);
        let mut logs = Vec::new();
        let s = train(&req, &mut |m| logs.push(m.clone()), &mut |_| {}).unwrap();
        assert_eq!(s.updates, 120);
        let (first, last) = (logs[0].train_loss, logs[logs.len() - 1].train_loss);
        // Uniform over 5 actions is ln 5 = 1.61.
        assert!(last < 0.8 * first && last < 1.3, "loss {first} -> {last}");

        // The agent loads, acts past its context (sliding) and the cache agrees
        // with a full forward on the same tokens.
        let (mut agent, info) = AdAgent::load(&dir).unwrap();
        assert_eq!(info.updates_done, 120);
        agent
            .reset(&[Conditioning::Targets { rtg: 1.0, ctg: 0.0 }; 2])
            .unwrap();
        let mut outs = Vec::new();
        for t in 0..100 {
            let input = StepInput {
                obs: &[4.0, 4.0, 4.0, 5.0],
                arrived_obs: &[4.0, 4.0, 4.0, 5.0],
                prev_action: &[0.0; 10],
                reward: &[0.0, 0.0],
                cost: &[0.0, 1.0],
                episode_start: &[t % 30 == 0, t % 30 == 0],
            };
            outs.push(agent.act(&input, true).unwrap());
        }
        assert!(matches!(&outs[99], Actions::Discrete(v) if v.len() == 2 && v[0] < 5));
        assert!(agent.cache.len() <= cfg.model.max_len);
        // CTG fell by the cost received since the last episode start (t = 90)
        // and stopped at 0, the lowest label training ever showed.
        assert_eq!(agent.ctg[1], 0.0);
        assert_eq!(agent.ctg[0], 0.0);
        let last = agent.window.as_ref().unwrap().select(1, -1); // (B, token_dim)
        let ctg_part: Vec<f32> = last
            .select(1, agent.spec.token_dim() as i64 - 2)
            .try_into()
            .unwrap();
        assert_eq!(ctg_part, vec![0.0, 0.0]);
        assert!(matches!(
            agent.reset(&[Conditioning::Budget { ctg: 1.0 }]),
            Err(AgentError::Input(_))
        ));

        // Checkpoints are atomic step folders with checksummed manifests.
        let step_60 = dir.join("checkpoints/step_60");
        let m = read_manifest(&step_60).unwrap();
        assert_eq!((m.method.as_str(), m.updates), ("ad", 60));
        assert_eq!(m.sha256.len(), 3, "model, adam, state: {:?}", m.sha256);
        assert!(dir.join("checkpoints/step_120").is_dir());
        // One step folder loads too, for evaluation of an earlier checkpoint.
        let (_, info) = AdAgent::load(&step_60).unwrap();
        assert_eq!((info.updates_done, info.dir.clone()), (60, step_60.clone()));
        let loaded = crate::eval::load::load_checkpoint(&step_60, EnvName::DarkRoom).unwrap();
        assert_eq!(loaded.checkpoint, Some(step_60.clone()));

        // Resuming from step 60 redoes 61..120: the metrics lines logged after
        // the checkpoint are dropped, so no update is counted twice.
        let resume = TrainRequest {
            resume: Some(&step_60),
            ..req.clone()
        };
        let s = train(&resume, &mut |_| {}, &mut |_| {}).unwrap();
        assert_eq!((s.resumed_from, s.updates), (60, 120));
        let updates: Vec<usize> = fs::read_to_string(dir.join("metrics.jsonl"))
            .unwrap()
            .lines()
            .map(|l| serde_json::from_str::<AdMetrics>(l).unwrap().update)
            .collect();
        assert_eq!(updates, vec![20, 40, 60, 80, 100, 120]);
        // A longer run continues from the latest checkpoint ...
        let mut more = cfg.clone();
        more.updates = 140;
        let step_120 = dir.join("checkpoints/step_120");
        let longer = TrainRequest {
            cfg: &more,
            resume: Some(&step_120),
            ..req.clone()
        };
        let s = train(&longer, &mut |_| {}, &mut |_| {}).unwrap();
        assert_eq!((s.resumed_from, s.updates), (120, 140));
        // ... and any other change is refused, naming the field.
        let mut other_lr = more.clone();
        other_lr.learning_rate = 1e-3;
        let other = TrainRequest {
            cfg: &other_lr,
            ..longer
        };
        let e = train(&other, &mut |_| {}, &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(e.contains("learning_rate: 0.003 -> 0.001"), "{e}");
        // Other data (here: every observation shifted) is refused by name.
        let mut shifted = data.clone();
        for h in &mut shifted.histories {
            h.observations.iter_mut().for_each(|o| *o += 1.0);
        }
        let other_data = TrainRequest {
            data: &shifted,
            ..longer.clone()
        };
        let e = train(&other_data, &mut |_| {}, &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(e.contains("is not the one the run was trained on"), "{e}");
        // Fewer updates than done: refused with the fix.
        let step_140 = dir.join("checkpoints/step_140");
        let shorter = TrainRequest {
            resume: Some(&step_140),
            ..req.clone()
        };
        let e = train(&shorter, &mut |_| {}, &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(e.contains("--set updates=140"), "{e}");
        // A run whose tokens lack the arrived observation is refused by name.
        let spec_path = dir.join("spec.json");
        let spec_text = fs::read_to_string(&spec_path).unwrap();
        let mut old: serde_json::Value = serde_json::from_str(&spec_text).unwrap();
        old.as_object_mut().unwrap().remove("token");
        fs::write(&spec_path, old.to_string()).unwrap();
        let e = AdAgent::load(&dir).err().unwrap().to_string();
        assert!(e.contains("arrived") && e.contains("retrain"), "{e}");
        fs::write(&spec_path, spec_text).unwrap();
        // Altered weights (same size) are refused on resume and on load.
        let model = step_140.join("model.safetensors");
        let mut bytes = fs::read(&model).unwrap();
        let n = bytes.len();
        for b in &mut bytes[n - 64..] {
            *b = b.wrapping_add(1);
        }
        fs::write(&model, bytes).unwrap();
        let e = AdAgent::load(&dir).err().unwrap().to_string();
        assert!(
            e.contains("model.safetensors") && e.contains("SHA-256"),
            "{e}"
        );
        let _ = fs::remove_dir_all(&dir);
    }

    #[test]
    fn kv_cache_step_equals_full_forward() {
        let data = tiny_data();
        let cfg = tiny_cfg();
        let spec = spec_for(&data, Path::new("x"));
        let vs = nn::VarStore::new(Device::Cpu);
        let model = AdModel::new(&vs.root(), &spec, &cfg).unwrap();
        let set = TokenSet::new(&spec, &cfg, &[&data.histories[0]]);
        let (x, _) = set
            .sample(2, 12, &mut ChaCha8Rng::seed_from_u64(0))
            .unwrap();
        let full = model.forward_t(&x, false).unwrap();
        let mut cache = model.transformer.new_cache();
        let steps: Vec<Tensor> = (0..12)
            .map(|t| model.forward_step(&x.narrow(1, t, 1), &mut cache).unwrap())
            .collect();
        let stepped = Tensor::cat(&steps, 1);
        let diff = (full - stepped).abs().max().double_value(&[]);
        assert!(diff < 1e-4, "{diff}");
    }
}
