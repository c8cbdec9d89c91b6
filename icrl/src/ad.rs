//! Safe supervised pretraining: algorithm distillation with RTG and CTG
//! (paper Section 3.1, Eq. 16 and 17; SPEC section 4).
//!
//! Read top to bottom: config and presets, the token layout, the data loader,
//! the model, [`train`], then the frozen [`AdAgent`].
//!
//! # Tokens: one per time step
//! Each time step `t` of a learning history becomes one token, the
//! concatenation of
//!
//! | part | width | value |
//! |---|---|---|
//! | observation `s_t` | obs_dim | standardised with the dataset's mean and std |
//! | previous action `a_{t-1}` | action_dim | one-hot for discrete actions; zeros at the history's first step |
//! | previous reward, cost `r_t, c_t` | 2 | received for `a_{t-1}` (zeros at the first step) |
//! | return-to-go `G_t` | 1 | reward still to come in this episode, `/ rtg_scale` |
//! | cost-to-go `G_c,t` | 1 | cost still to come in this episode, `/ ctg_scale` |
//! | episode start | 1 | 1 at the first step of an episode |
//!
//! mapped to the model width by a two-layer MLP, through the shared causal
//! transformer ([`crate::model`]), and a linear head predicts `a_t` from the
//! token of step `t`: logits with cross-entropy for discrete actions (Eq. 16),
//! the mean with an L2 loss for continuous ones (Eq. 17).
//!
//! Why one token per step rather than interleaved (RTG, CTG, s, a) tokens as in
//! the constrained decision transformer: the context holds three to four times
//! more steps for the same sequence length (Table 2's 100 positions cover about
//! three SafeDarkRoom episodes instead of one), acting is one forward step per
//! environment step through [`crate::agent::InContextAgent`], and EPPO encodes
//! its steps the same way (SPEC section 3), so the two routes differ only in
//! their learning rule.
//!
//! RTG and CTG labels (SPEC section 4): inside each episode, `G_t = sum_{j>=t}
//! r_{j+1}` and `G_c,t = sum_{j>=t} c_{j+1}`, the reward and cost received
//! from acting at `t` to the episode's end. At test time both start at the
//! targets and decrease by what is received.
//!
//! # Checkpoints
//! A run folder `{env}__ad__{seed}__{time}` holds `config.toml` (the resolved
//! [`AdConfig`]), `spec.json` ([`AdSpec`]: sizes, normalisation, dataset,
//! pretraining tasks), `metrics.jsonl` (one [`AdMetrics`] per log interval),
//! `model.safetensors`, `adam.safetensors` (the optimizer's moments, through
//! the shared [`crate::optim::Adam`]) and `state.json` (updates done).
//! Resuming loads all three and continues the schedule where it stopped.

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
use crate::histories::{History, HistoryError, HistoryFile};
use crate::model::{self, KvCache, ModelError, Transformer};
use crate::optim::{Adam, AdamConfig};
use crate::task_seeds::PretrainTasks;

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
    /// Log (and validate) every this many updates.
    pub log_every: usize,
    /// Save a checkpoint every this many updates (and at the end).
    pub checkpoint_every: usize,
    /// Seed of initialisation and window sampling.
    pub seed: u64,
}

/// The presets shipped in `icrl/presets/ad-{env}-{preset}.toml`: `table2` is
/// the paper's Table 2 (a GPU preset), `quick` fits 2 CPU cores.
pub const PRESETS: [(&str, &str); 6] = [
    (
        "ad-darkroom-table2",
        include_str!("../presets/ad-darkroom-table2.toml"),
    ),
    (
        "ad-point-table2",
        include_str!("../presets/ad-point-table2.toml"),
    ),
    (
        "ad-car-table2",
        include_str!("../presets/ad-car-table2.toml"),
    ),
    (
        "ad-darkroom-quick",
        include_str!("../presets/ad-darkroom-quick.toml"),
    ),
    (
        "ad-point-quick",
        include_str!("../presets/ad-point-quick.toml"),
    ),
    ("ad-car-quick", include_str!("../presets/ad-car-quick.toml")),
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

    /// Checks the values, naming the ones that do not fit.
    pub fn validate(&self) -> Result<(), AdError> {
        self.model.validate()?;
        if self.batch_size <= 0
            || self.updates == 0
            || self.log_every == 0
            || self.checkpoint_every == 0
        {
            return Err(AdError::Config(format!(
                "batch_size ({}), updates ({}), log_every ({}) and checkpoint_every ({}) must be positive",
                self.batch_size, self.updates, self.log_every, self.checkpoint_every
            )));
        }
        if self.learning_rate.is_nan()
            || self.learning_rate <= 0.0
            || !(0.0..1.0).contains(&self.warmup_fraction)
        {
            return Err(AdError::Config(format!(
                "need learning_rate > 0 ({}) and warmup_fraction in [0, 1) ({})",
                self.learning_rate, self.warmup_fraction
            )));
        }
        if !(self.rtg_scale > 0.0 && self.ctg_scale > 0.0) {
            return Err(AdError::Config(format!(
                "rtg_scale ({}) and ctg_scale ({}) must be positive",
                self.rtg_scale, self.ctg_scale
            )));
        }
        if !(0.0..0.9).contains(&self.val_fraction) {
            return Err(AdError::Config(format!(
                "val_fraction {} must lie in [0, 0.9)",
                self.val_fraction
            )));
        }
        Ok(())
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
}

impl AdSpec {
    /// Token width: obs, previous action, reward, cost, RTG, CTG, episode start.
    pub fn token_dim(&self) -> usize {
        self.obs_dim + self.action_dim + 5
    }
}

// ---------------------------------------------------------------------------
// Tokens and the data loader
// ---------------------------------------------------------------------------

/// Writes one token into `out` (length `spec.token_dim()`).
#[allow(clippy::too_many_arguments)]
fn write_token(
    spec: &AdSpec,
    cfg: &AdConfig,
    obs: &[f32],
    prev_action: &[f32],
    reward: f32,
    cost: f32,
    rtg: f32,
    ctg: f32,
    episode_start: bool,
    out: &mut [f32],
) {
    let (o, a) = (spec.obs_dim, spec.action_dim);
    for i in 0..o {
        out[i] = (obs[i] - spec.obs_mean[i]) / spec.obs_std[i];
    }
    out[o..o + a].copy_from_slice(prev_action);
    out[o + a] = reward;
    out[o + a + 1] = cost;
    out[o + a + 2] = rtg / cfg.rtg_scale;
    out[o + a + 3] = ctg / cfg.ctg_scale;
    out[o + a + 4] = if episode_start { 1.0 } else { 0.0 };
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

/// RTG and CTG labels of every step: what is still to come in its episode,
/// including the step's own reward and cost.
pub fn to_go(h: &History) -> (Vec<f32>, Vec<f32>) {
    let mut rtg = vec![0.0; h.len()];
    let mut ctg = vec![0.0; h.len()];
    for ep in h.episodes() {
        let (mut r, mut c) = (0.0, 0.0);
        for t in ep.rev() {
            r += h.rewards[t];
            c += h.costs[t];
            rtg[t] = r;
            ctg[t] = c;
        }
    }
    (rtg, ctg)
}

/// Histories turned into token rows and action targets, ready for windows.
pub struct TokenSet {
    token_dim: usize,
    action_dim: usize,
    discrete: bool,
    /// Per history: (T, token_dim) tokens.
    tokens: Vec<Vec<f32>>,
    /// Per history: (T,) class indices (discrete) ...
    classes: Vec<Vec<i64>>,
    /// ... or (T, action_dim) target actions (continuous).
    targets: Vec<Vec<f32>>,
}

impl TokenSet {
    /// Tokenises `histories`.
    pub fn new(spec: &AdSpec, cfg: &AdConfig, histories: &[&History]) -> Self {
        let d = spec.token_dim();
        let mut set = TokenSet {
            token_dim: d,
            action_dim: spec.action_dim,
            discrete: spec.discrete,
            tokens: Vec::new(),
            classes: Vec::new(),
            targets: Vec::new(),
        };
        let mut prev = vec![0.0f32; spec.action_dim];
        for h in histories {
            let (rtg, ctg) = to_go(h);
            let mut rows = vec![0.0f32; h.len() * d];
            let mut starts = vec![false; h.len()];
            for ep in h.episodes() {
                starts[ep.start] = true;
            }
            for t in 0..h.len() {
                let (r, c) = if t == 0 {
                    prev.fill(0.0);
                    (0.0, 0.0)
                } else {
                    action_part(spec, h, t - 1, &mut prev);
                    (h.rewards[t - 1], h.costs[t - 1])
                };
                write_token(
                    spec,
                    cfg,
                    &h.observations[t * spec.obs_dim..(t + 1) * spec.obs_dim],
                    &prev,
                    r,
                    c,
                    rtg[t],
                    ctg[t],
                    starts[t],
                    &mut rows[t * d..(t + 1) * d],
                );
            }
            set.tokens.push(rows);
            if spec.discrete {
                set.classes
                    .push(h.actions.iter().map(|&a| a as i64).collect());
            } else {
                set.targets.push(h.actions.clone());
            }
        }
        set
    }

    /// Samples `batch` windows of `len` steps, uniformly over all window
    /// positions of histories at least `len` long (so every learning phase,
    /// early and late, is drawn). Returns tokens (B, T, token_dim) and targets
    /// (B, T) int64 or (B, T, action_dim) float.
    pub fn sample(
        &self,
        batch: i64,
        len: i64,
        rng: &mut ChaCha8Rng,
    ) -> Result<(Tensor, Tensor), AdError> {
        let l = len as usize;
        let weights: Vec<f64> = self
            .tokens
            .iter()
            .map(|t| ((t.len() / self.token_dim) + 1).saturating_sub(l) as f64)
            .collect();
        let dist = WeightedIndex::new(&weights).map_err(|_| {
            AdError::Config(format!(
                "no history is at least {l} steps long: lower the sequence length (model.max_len)"
            ))
        })?;
        let d = self.token_dim;
        let mut x = Vec::with_capacity(batch as usize * l * d);
        let mut ycls = Vec::new();
        let mut yvec = Vec::new();
        for _ in 0..batch {
            let h = dist.sample(rng);
            let steps = self.tokens[h].len() / d;
            let start = rng.gen_range(0..=steps - l);
            x.extend_from_slice(&self.tokens[h][start * d..(start + l) * d]);
            if self.discrete {
                ycls.extend_from_slice(&self.classes[h][start..start + l]);
            } else {
                let a = self.action_dim;
                yvec.extend_from_slice(&self.targets[h][start * a..(start + l) * a]);
            }
        }
        let x = Tensor::from_slice(&x).view([batch, len, d as i64]);
        let y = if self.discrete {
            Tensor::from_slice(&ycls).view([batch, len])
        } else {
            Tensor::from_slice(&yvec).view([batch, len, self.action_dim as i64])
        };
        Ok((x, y))
    }

    /// Number of histories.
    pub fn len(&self) -> usize {
        self.tokens.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tokens.is_empty()
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
    /// Continue from the folder's checkpoint if there is one.
    pub resume: bool,
}

/// What a finished run reports.
#[derive(Clone, Debug)]
pub struct TrainSummary {
    pub run_dir: PathBuf,
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
    }
}

#[derive(Serialize, Deserialize)]
struct TrainState {
    update: usize,
    samples: u64,
}

fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), AdError> {
    let tmp = crate::histories::temp_path(path);
    fs::write(&tmp, bytes).map_err(|e| io_err(&tmp, e))?;
    fs::rename(&tmp, path).map_err(|e| io_err(path, e))
}

/// Writes weights, Adam's moments, then `state.json` (last, so it never names
/// an update whose weights are not on disk).
fn save_checkpoint(
    dir: &Path,
    vs: &nn::VarStore,
    opt: &Adam,
    state: &TrainState,
) -> Result<(), AdError> {
    let model = dir.join("model.safetensors");
    // tch picks the format from the extension: keep `.safetensors` last.
    let tmp = dir.join("model.tmp.safetensors");
    vs.save(&tmp)?;
    fs::rename(&tmp, &model).map_err(|e| io_err(&model, e))?;
    let adam = dir.join("adam.safetensors");
    let tmp = dir.join("adam.tmp.safetensors");
    opt.save(&tmp)?;
    fs::rename(&tmp, &adam).map_err(|e| io_err(&adam, e))?;
    let json = serde_json::to_vec_pretty(state).map_err(|e| io_err(dir, e))?;
    write_atomic(&dir.join("state.json"), &json)
}

/// Trains (or resumes) a model on the histories, writing the run folder.
/// `on_log` sees every metrics line (for a progress bar), `on_update` every update.
pub fn train(
    req: &TrainRequest<'_>,
    on_log: &mut dyn FnMut(&AdMetrics),
    on_update: &mut dyn FnMut(usize),
) -> Result<TrainSummary, AdError> {
    let cfg = req.cfg;
    cfg.validate()?;
    let dir = req.run_dir;
    fs::create_dir_all(dir).map_err(|e| io_err(dir, e))?;
    let spec = spec_for(req.data, req.dataset_path);

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
    let (train_h, val_h): (Vec<&History>, Vec<&History>) =
        hists.iter().partition(|h| !val_tasks.contains(&&h.task));
    let train_set = TokenSet::new(&spec, cfg, &train_h);
    let val_set = TokenSet::new(&spec, cfg, &val_h);

    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let mut vs = nn::VarStore::new(Device::cuda_if_available());
    tch::manual_seed(cfg.seed as i64);
    let model = AdModel::new(&vs.root(), &spec, cfg)?;

    // Resume or start fresh; the config and spec must match the folder's.
    let state_path = dir.join("state.json");
    let mut state = TrainState {
        update: 0,
        samples: 0,
    };
    let config_toml = toml::to_string_pretty(cfg).map_err(|e| io_err(dir, e))?;
    if req.resume && state_path.exists() {
        let old_cfg = fs::read_to_string(dir.join("config.toml")).map_err(|e| io_err(dir, e))?;
        let old: AdConfig =
            toml::from_str(&old_cfg).map_err(|e| io_err(&dir.join("config.toml"), e))?;
        if old != *cfg {
            return Err(AdError::Config(format!(
                "cannot resume {}: its config.toml differs from the requested config",
                dir.display()
            )));
        }
        let s = fs::read_to_string(&state_path).map_err(|e| io_err(&state_path, e))?;
        state = serde_json::from_str(&s).map_err(|e| io_err(&state_path, e))?;
        vs.load(dir.join("model.safetensors"))?;
    } else {
        write_atomic(&dir.join("config.toml"), config_toml.as_bytes())?;
        let spec_json = serde_json::to_vec_pretty(&spec).map_err(|e| io_err(dir, e))?;
        write_atomic(&dir.join("spec.json"), &spec_json)?;
    }
    let resumed_from = state.update;
    // Skip the sampling stream forward so a resumed run does not replay windows.
    rng.set_word_pos((resumed_from as u128) << 16);

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
    if resumed_from > 0 {
        let p = dir.join("adam.safetensors");
        opt.load(&p).map_err(|e| io_err(&p, e))?;
    }

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

    let mut metrics_file = fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(dir.join("metrics.jsonl"))
        .map_err(|e| io_err(dir, e))?;
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
        opt.backward_step(&l);
        loss_sum += l.double_value(&[]);
        acc_sum += acc.map_or(0.0, |a| a.double_value(&[]));
        n_sum += 1.0;
        state.update += 1;
        state.samples += (cfg.batch_size * window) as u64;
        on_update(state.update);

        let done = state.update == cfg.updates;
        if state.update.is_multiple_of(cfg.log_every) || done {
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
            writeln!(metrics_file, "{line}").map_err(|e| io_err(dir, e))?;
            on_log(&m);
            if first.is_none() {
                first = Some(m.clone());
            }
            last = Some(m);
            (loss_sum, acc_sum, n_sum) = (0.0, 0.0, 0.0);
        }
        if state.update.is_multiple_of(cfg.checkpoint_every) || done {
            save_checkpoint(dir, &vs, &opt, &state)?;
        }
    }
    Ok(TrainSummary {
        run_dir: dir.to_path_buf(),
        updates: state.update,
        first,
        last,
        resumed_from,
    })
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
    let mut table = match resume {
        Some(dir) => {
            let p = dir.join("config.toml");
            let text = fs::read_to_string(&p).map_err(|e| io_err(&p, e))?;
            text.parse::<toml::Table>().map_err(|e| io_err(&p, e))?
        }
        None => preset_table(env, preset)?,
    };
    crate::presets::apply_overrides(&mut table, sets)
        .map_err(|e| AdError::Config(e.to_string()))?;
    let cfg = AdConfig::from_table(table)?;
    let dataset_path = match (dataset, resume) {
        (Some(p), _) => p.to_path_buf(),
        (None, Some(dir)) => {
            let p = dir.join("spec.json");
            let text = fs::read_to_string(&p).map_err(|e| io_err(&p, e))?;
            let spec: AdSpec = serde_json::from_str(&text).map_err(|e| io_err(&p, e))?;
            PathBuf::from(spec.dataset)
        }
        (None, None) => {
            return Err(AdError::Config(
                "--method ad needs --dataset FILE (make one with `icrl dataset --env ...`)".into(),
            ));
        }
    };
    let data = crate::histories::read_histories(&dataset_path, Some(env))?;
    let run_dir = match resume {
        Some(dir) => dir.to_path_buf(),
        None => {
            let run = crate::checkpoint::RunDir::create(out, env, "ad", cfg.seed)
                .map_err(|e| io_err(out, e))?;
            // AD keeps its checkpoint files at the top of the run folder.
            let _ = fs::remove_dir(run.path.join("checkpoints"));
            run.path
        }
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
        resume: resume.is_some(),
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
    /// Loads a run folder written by [`train`].
    pub fn load(dir: &Path) -> Result<(Self, CheckpointInfo), AdError> {
        let read = |name: &str| {
            let p = dir.join(name);
            fs::read_to_string(&p).map_err(|e| io_err(&p, e))
        };
        let cfg: AdConfig = toml::from_str(&read("config.toml")?)
            .map_err(|e| io_err(&dir.join("config.toml"), e))?;
        let spec: AdSpec = serde_json::from_str(&read("spec.json")?)
            .map_err(|e| io_err(&dir.join("spec.json"), e))?;
        let state: TrainState = serde_json::from_str(&read("state.json")?)
            .map_err(|e| io_err(&dir.join("state.json"), e))?;
        let physics = spec
            .env
            .parse::<safety_envs::EnvName>()
            .ok()
            .and_then(|env| env.physics_steps_per_action(None));
        if physics.is_some() && spec.physics_steps_per_action.is_none() {
            return Err(io_err(
                &dir.join("spec.json"),
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
        vs.load(dir.join("model.safetensors"))?;
        vs.freeze();
        let info = CheckpointInfo {
            dir: dir.to_path_buf(),
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
            || input.prev_action.len() != b * a
            || input.reward.len() != b
            || input.cost.len() != b
            || input.episode_start.len() != b
        {
            return Err(AgentError::Input(format!(
                "expected {b} trajectories with obs_dim {o} and action width {a}; got obs {}, prev_action {}, reward {}, cost {}, episode_start {}",
                input.obs.len(),
                input.prev_action.len(),
                input.reward.len(),
                input.cost.len(),
                input.episode_start.len()
            )));
        }
        let d = self.spec.token_dim();
        let mut rows = vec![0.0f32; b * d];
        for i in 0..b {
            // RTG/CTG restart at the targets each episode and decrease by what
            // the previous action brought inside the episode.
            if input.episode_start[i] {
                (self.rtg[i], self.ctg[i]) = self.targets[i];
            } else {
                self.rtg[i] -= input.reward[i];
                self.ctg[i] -= input.cost[i];
            }
            write_token(
                &self.spec,
                &self.cfg,
                &input.obs[i * o..(i + 1) * o],
                &input.prev_action[i * a..(i + 1) * a],
                input.reward[i],
                input.cost[i],
                self.rtg[i],
                self.ctg[i],
                input.episode_start[i],
                &mut rows[i * d..(i + 1) * d],
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
    use crate::dataset::{DatasetConfig, Source, generate};
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

    fn tiny_data() -> HistoryFile {
        let mut d = DatasetConfig::paper(EnvName::DarkRoom, 2, 11);
        d.source = Source::NoisyOptimal;
        d.steps = 1500;
        d.cost_limits = vec![0.0];
        generate(&d, &|_| {}).unwrap().file
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
        let (rtg, ctg) = to_go(h);
        let eps = h.episodes();
        let e = &eps[0];
        let ret: f32 = h.rewards[e.clone()].iter().sum();
        let cost: f32 = h.costs[e.clone()].iter().sum();
        assert_eq!(rtg[e.start], ret);
        assert_eq!(ctg[e.start], cost);
        assert_eq!(rtg[e.end - 1], h.rewards[e.end - 1]);
        assert_eq!(ctg[e.end - 1], h.costs[e.end - 1]);
    }

    #[test]
    fn supervised_loss_falls_and_the_agent_acts_from_a_checkpoint() {
        let data = tiny_data();
        let cfg = tiny_cfg();
        let dir = std::env::temp_dir().join(format!("icrl-ad-test-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        let req = TrainRequest {
            cfg: &cfg,
            data: &data,
            dataset_path: Path::new("tiny.h5"),
            run_dir: &dir,
            resume: false,
        };
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
        // CTG fell by the cost received since the last episode start (t = 90).
        assert_eq!(agent.ctg[1], -9.0);
        assert!(matches!(
            agent.reset(&[Conditioning::Budget { ctg: 1.0 }]),
            Err(AgentError::Input(_))
        ));

        // An interrupted run resumes from its checkpoint with the same config ...
        fs::write(dir.join("state.json"), r#"{"update": 100, "samples": 0}"#).unwrap();
        let resume = TrainRequest {
            resume: true,
            ..req.clone()
        };
        let s = train(&resume, &mut |_| {}, &mut |_| {}).unwrap();
        assert_eq!((s.resumed_from, s.updates), (100, 120));
        // ... and refuses a different one.
        let mut more = cfg.clone();
        more.updates = 140;
        let other = TrainRequest {
            cfg: &more,
            ..resume
        };
        let e = train(&other, &mut |_| {}, &mut |_| {}).unwrap_err();
        assert!(e.to_string().contains("differs"), "{e}");
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
