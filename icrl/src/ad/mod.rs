//! Safe supervised pretraining: algorithm distillation with RTG and CTG
//! (paper Section 3.1, Eq. 16 and 17; SPEC section 4).
//!
//! This file is the training run, read top to bottom: what can fail, the
//! request and metrics, and [`train`], then its steps (the run opened, the
//! fixed validation windows, the metrics log, the model, the resume). Its
//! parts sit beside it: `config.rs`
//! (hyperparameters, presets, [`AdSpec`], the memory estimate), `windows.rs`
//! (tokens, RTG/CTG labels, training windows), `model.rs` (the model and the
//! loss), `checkpoint.rs` (save and load) and `agent.rs` (the frozen
//! [`AdAgent`]).
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

mod agent;
mod checkpoint;
mod config;
mod model;
#[cfg(test)]
mod tests;
mod windows;

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tch::{Device, Tensor, nn};
use thiserror::Error;

use crate::checkpoint::{CheckpointError, RunDir};
use crate::data::histories::{History, HistoryError, HistoryFile};
use crate::model::ModelError;
use crate::optim::{Adam, AdamConfig};

pub use agent::{AdAgent, CheckpointInfo};
pub use config::{AdConfig, AdSpec, CtgLabel, TOKEN_LAYOUT, memory_estimate, preset_table};
pub use model::{AdModel, loss};
pub use windows::{TokenSet, to_go};

use checkpoint::{TrainState, config_diff, load_checkpoint_into, save_checkpoint, write_atomic};
use config::spec_for;

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
    /// A loss or gradient became NaN or infinite, or libtorch's backward
    /// pass failed: the update was not applied.
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

pub(crate) fn io_err(path: &Path, e: impl std::fmt::Display) -> AdError {
    AdError::Io {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

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
    let (run, spec) = open_run(req)?;
    // One process per run folder until training returns.
    let _lock = run.lock()?;

    let (train_h, val_h) = split_histories(&req.data.histories, cfg);
    let train_set = TokenSet::new(&spec, cfg, &train_h);
    let val_set = TokenSet::new(&spec, cfg, &val_h);

    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let (mut vs, model, mut opt) = new_model(&spec, cfg)?;

    let (mut state, mut last_ckpt) = resume_or_start(req, &spec, &mut vs, &mut opt)?;
    let resumed_from = state.update;
    // Skip the sampling stream forward so a resumed run does not replay windows.
    rng.set_word_pos((resumed_from as u128) << 16);

    let device = vs.device();
    let val_batches = validation_windows(&val_set, cfg)?;
    let mut log = MetricsLog::open(req.run_dir)?;
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
        log.add(
            l.double_value(&[]),
            acc.map_or(0.0, |a| a.double_value(&[])),
        );
        state.update += 1;
        state.samples += (cfg.batch_size * window) as u64;
        on_update(state.update);

        let stop = crate::stop::requested();
        let done = state.update == cfg.updates;
        if state.update.is_multiple_of(cfg.log_every) || done || stop {
            let val = validation(&model, &val_batches, device, spec.discrete)?;
            on_log(&log.write(&state, lr, val, spec.discrete)?);
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
        run_dir: req.run_dir.to_path_buf(),
        train_histories: train_set.len(),
        val_histories: val_set.len(),
        updates: state.update,
        first: log.first,
        last: log.last,
        resumed_from,
    })
}

/// Checks the settings, the data (finite values and actions inside the
/// action space, or libtorch would train to NaN or abort on an out-of-range
/// class index) and the memory the run needs, and makes the run folder.
/// Returns it with the model's sizes.
fn open_run(req: &TrainRequest<'_>) -> Result<(RunDir, AdSpec), AdError> {
    let cfg = req.cfg;
    cfg.validate()?;
    req.data.validate(req.dataset_path)?;
    let dir = req.run_dir;
    crate::guard::set_torch_threads("torch_threads", cfg.torch_threads);
    let spec = spec_for(req.data, req.dataset_path);
    memory_estimate(cfg, &spec, req.data.total_steps())
        .check()
        .map_err(AdError::Config)?;
    let ck = dir.join("checkpoints");
    fs::create_dir_all(&ck).map_err(|e| io_err(&ck, e))?;
    let run = RunDir {
        path: dir.to_path_buf(),
    };
    Ok((run, spec))
}

/// Fixed validation windows: four batches of the held-out histories, drawn
/// once (none without held-out histories).
fn validation_windows(
    val_set: &TokenSet,
    cfg: &AdConfig,
) -> Result<Vec<(Tensor, Tensor)>, AdError> {
    if val_set.is_empty() {
        return Ok(Vec::new());
    }
    let mut vrng = ChaCha8Rng::seed_from_u64(cfg.seed ^ 0x5eed);
    (0..4)
        .map(|_| val_set.sample(cfg.batch_size.min(64), cfg.model.max_len, &mut vrng))
        .collect()
}

/// The run's `metrics.jsonl` (appended to), the training loss and accuracy
/// summed since its last line, and the first and last lines written.
struct MetricsLog {
    dir: PathBuf,
    path: PathBuf,
    file: fs::File,
    started: Instant,
    loss_sum: f64,
    acc_sum: f64,
    n_sum: f64,
    first: Option<AdMetrics>,
    last: Option<AdMetrics>,
}

impl MetricsLog {
    fn open(dir: &Path) -> Result<Self, AdError> {
        let path = dir.join("metrics.jsonl");
        let file = fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(|e| io_err(&path, e))?;
        Ok(MetricsLog {
            dir: dir.to_path_buf(),
            path,
            file,
            started: Instant::now(),
            loss_sum: 0.0,
            acc_sum: 0.0,
            n_sum: 0.0,
            first: None,
            last: None,
        })
    }

    /// One update's training loss and accuracy.
    fn add(&mut self, loss: f64, accuracy: f64) {
        self.loss_sum += loss;
        self.acc_sum += accuracy;
        self.n_sum += 1.0;
    }

    /// Writes the line of `state`'s update: the means since the last line,
    /// the validation loss and accuracy `val`, the learning rate; returns it.
    fn write(
        &mut self,
        state: &TrainState,
        learning_rate: f64,
        (val_loss, val_accuracy): (Option<f64>, Option<f64>),
        discrete: bool,
    ) -> Result<AdMetrics, AdError> {
        let m = AdMetrics {
            update: state.update,
            samples: state.samples,
            train_loss: self.loss_sum / self.n_sum,
            train_accuracy: discrete.then_some(self.acc_sum / self.n_sum),
            val_loss,
            val_accuracy,
            learning_rate,
            seconds: self.started.elapsed().as_secs_f64(),
        };
        let line = serde_json::to_string(&m).map_err(|e| io_err(&self.dir, e))?;
        // A failed write (a full disk) stops the run naming its last good
        // checkpoint.
        writeln!(self.file, "{line}").map_err(|e| {
            let run = RunDir {
                path: self.dir.clone(),
            };
            AdError::Checkpoint(run.stopped_writing_with(self.path.clone(), e.to_string()))
        })?;
        if self.first.is_none() {
            self.first = Some(m.clone());
        }
        self.last = Some(m.clone());
        (self.loss_sum, self.acc_sum, self.n_sum) = (0.0, 0.0, 0.0);
        Ok(m)
    }
}

/// A fresh model and its optimizer, initialised from `cfg.seed`, on the GPU
/// when libtorch sees one.
fn new_model(spec: &AdSpec, cfg: &AdConfig) -> Result<(nn::VarStore, AdModel, Adam), AdError> {
    let vs = nn::VarStore::new(Device::cuda_if_available());
    let model = crate::torch_rng::seeded(cfg.seed, || AdModel::new(&vs.root(), spec, cfg))?;
    let opt = Adam::new(
        &vs,
        AdamConfig {
            lr: cfg.learning_rate,
            beta1: cfg.beta1,
            beta2: cfg.beta2,
            eps: 1e-8,
            grad_clip: Some(cfg.grad_clip),
        },
    );
    Ok((vs, model, opt))
}

/// Resumes the run from `req.resume` (checked against the folder's config
/// and data, its later metrics dropped) or starts it (writing `spec.json`);
/// writes the resolved `config.toml` either way. Returns the counters and
/// the checkpoint resumed from.
fn resume_or_start(
    req: &TrainRequest<'_>,
    spec: &AdSpec,
    vs: &mut nn::VarStore,
    opt: &mut Adam,
) -> Result<(TrainState, Option<PathBuf>), AdError> {
    let (cfg, dir) = (req.cfg, req.run_dir);
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
        check_resumable(req, spec, &config_path)?;
        state = load_checkpoint_into(ckpt, cfg, spec, vs, opt)?;
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
        let spec_json = serde_json::to_vec_pretty(spec).map_err(|e| io_err(dir, e))?;
        write_atomic(&dir.join("spec.json"), &spec_json)?;
    }
    // The resolved config (a grown `updates` included).
    write_atomic(&config_path, config_toml.as_bytes())?;
    let run = RunDir::open(dir)?;
    run.probe_checkpoint_path(cfg.updates as u64)?;
    run.check_room(
        opt.checkpoint_bytes() + crate::checkpoint::CHECKPOINT_SLACK,
        cfg.retention(),
        cfg.updates.saturating_sub(state.update) as u64,
        cfg.checkpoint_every as u64,
    )?;
    Ok((state, last_ckpt))
}

/// The histories to train on and those held out for the validation loss:
/// the held-out ones are every history of the last `val_fraction` of the
/// tasks; training uses the first `train_fraction` of the others.
fn split_histories<'a>(
    hists: &'a [History],
    cfg: &AdConfig,
) -> (Vec<&'a History>, Vec<&'a History>) {
    // Hold out the histories of the last `val_fraction` of the tasks.
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
    (train_h, val_h)
}

/// Refuses to resume a run whose `config.toml` differs from `req.cfg` in
/// anything but `updates`, `keep_checkpoints` and `keep_every`, or whose `spec.json` says
/// it was trained on other data than `spec`'s.
fn check_resumable(
    req: &TrainRequest<'_>,
    spec: &AdSpec,
    config_path: &Path,
) -> Result<(), AdError> {
    let (cfg, dir) = (req.cfg, req.run_dir);
    let old_text = fs::read_to_string(config_path).map_err(|e| io_err(config_path, e))?;
    let old = AdConfig::from_toml(&old_text).map_err(|e| io_err(config_path, e))?;
    let differ: Vec<String> = config_diff(&old, cfg)
        .into_iter()
        .filter(|d| {
            !["updates:", "keep_checkpoints:", "keep_every:"]
                .iter()
                .any(|key| d.starts_with(key))
        })
        .collect();
    if !differ.is_empty() {
        return Err(AdError::Config(format!(
            "cannot resume {}: these settings differ from its config.toml: {}; only updates \
             (to extend the run), keep_checkpoints and keep_every may change",
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
    if key(&saved) != key(spec) {
        return Err(AdError::Config(format!(
            "cannot resume {}: the dataset {} is not the one the run was trained on ({}, \
             recorded in {}); resume with that dataset or start a new run",
            dir.display(),
            req.dataset_path.display(),
            saved.dataset,
            spec_path.display()
        )));
    }
    Ok(())
}

/// Mean loss and (discrete) accuracy over the fixed validation windows;
/// `None` without held-out tasks.
fn validation(
    model: &AdModel,
    val_batches: &[(Tensor, Tensor)],
    device: Device,
    discrete: bool,
) -> Result<(Option<f64>, Option<f64>), AdError> {
    Ok(if val_batches.is_empty() {
        (None, None)
    } else {
        let (mut vl, mut va) = (0.0, 0.0);
        tch::no_grad(|| -> Result<(), AdError> {
            for (vx, vy) in val_batches {
                let out = model.forward_t(&vx.to_device(device), false)?;
                let (l, a) = loss(&out, &vy.to_device(device), discrete);
                vl += l.double_value(&[]);
                va += a.map_or(0.0, |a| a.double_value(&[]));
            }
            Ok(())
        })?;
        let k = val_batches.len() as f64;
        (Some(vl / k), discrete.then_some(va / k))
    })
}
