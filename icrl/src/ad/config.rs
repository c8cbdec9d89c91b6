//! AD's hyperparameters ([`AdConfig`], presets, the learning-rate schedule),
//! [`AdSpec`] (what a model trained on a dataset reads: sizes, observation
//! normalisation, dataset, token layout; saved as `spec.json`), and the memory
//! estimate checked before training.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::AdError;
use crate::checkpoint::Retention;
use crate::data::histories::HistoryFile;
use crate::model::{self};
use crate::task_seeds::PretrainTasks;
use crate::tokens;

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
    /// Besides the newest `keep_checkpoints`, keep every checkpoint written
    /// at a multiple of this many updates (0: none).
    #[serde(default)]
    pub keep_every: u64,
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

/// The preset `ad-{env}-{preset}` as a TOML table.
pub fn preset_table(env: &str, preset: &str) -> Result<toml::Table, AdError> {
    crate::presets::preset_table("ad", env, preset).map_err(|e| AdError::Config(e.to_string()))
}

impl AdConfig {
    /// Which checkpoints the run keeps.
    pub fn retention(&self) -> Retention {
        Retention {
            newest: self.keep_checkpoints,
            every: self.keep_every,
        }
    }

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
        if self.model.max_len < 2 {
            return Err(AdError::Config(format!(
                "model.max_len = {}: must be at least 2 (a context of one step holds no history \
                 to learn from in context)",
                self.model.max_len
            )));
        }
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
    pub(super) fn normalise_obs(&self, obs: &[f32], out: &mut Vec<f32>) {
        out.extend(
            obs.iter()
                .zip(self.obs_mean.iter().zip(&self.obs_std))
                .map(|(x, (m, s))| (x - m) / s),
        );
    }
}

/// The spec of a model trained on `data`.
pub(super) fn spec_for(data: &HistoryFile, dataset_path: &Path) -> AdSpec {
    let info = &data.info;
    let (discrete, action_dim) = match info.action_n {
        Some(n) => (true, n),
        None => (false, info.action_dim),
    };
    let o = info.obs_dim;
    let (mean, std) = crate::stats::column_mean_std(
        data.histories.iter().flat_map(|h| h.observations.chunks(o)),
        o,
    );
    let std: Vec<f32> = std.into_iter().map(|s| s.max(1e-3)).collect();
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
        levers: "batch_size, model.max_len, model.d_model, model.n_layers or model.d_ff".into(),
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
