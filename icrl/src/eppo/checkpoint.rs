//! EPPO checkpoints: writing and resuming a [`Learner`] (weights, target
//! weights, Adam moments, the replay, lambda, counters, RNG state, resolved
//! config) and
//! the model manifest that resuming and loading check.

use std::path::{Path, PathBuf};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use safety_envs::EnvName;

use super::Learner;
use super::config::{EppoConfig, EppoError};
use super::multiplier::{ConstraintStart, Multiplier};
use super::net::NetSpec;
use super::replay::Replay;
use crate::checkpoint::{CheckpointError, RunDir, read_manifest, write_part};
use crate::task_seeds::PretrainTasks;

impl Learner {
    /// The model shape recorded in checkpoints (resume and loading check it).
    pub fn model_manifest(&self) -> serde_json::Value {
        model_manifest(&self.cfg, &self.spec)
    }

    /// Writes `checkpoints/step_{updates}` (weights, target weights, Adam
    /// moments, the replay, lambda, counters, RNG state, resolved config).
    pub fn save_checkpoint(&self, run: &RunDir) -> Result<PathBuf, EppoError> {
        let state = TrainState {
            lambda: self.multiplier.lambda,
            multiplier: Some(self.multiplier.clone()),
            constraint_start: Some(self.constraint_start.clone()),
            entropy_coef: Some(self.entropy_coef),
            updates: self.updates,
            env_steps: self.env_steps,
            rng_seed: self.rng.get_seed(),
            rng_stream: self.rng.get_stream(),
            rng_word_pos: self.rng.get_word_pos().to_string(),
            spec: self.spec.clone(),
            pretrain_tasks: Some(PretrainTasks::centre(
                self.cfg.run.seed,
                match self.cfg.tasks.task_pool {
                    0 => self.tasks_drawn,
                    pool => self.tasks_drawn.min(pool),
                },
            )),
            tasks_drawn: Some(self.tasks_drawn),
        };
        let config = toml::to_string(&self.cfg).map_err(|e| EppoError::Config(e.to_string()))?;
        let dir = run.write_checkpoint(
            self.updates,
            "eppo",
            self.env.as_str(),
            self.env
                .physics_steps_per_action(self.cfg.tasks.physics_steps_per_action),
            self.model_manifest(),
            self.cfg.run.retention(),
            |dir| {
                let text = |e: tch::TchError| e.to_string();
                write_part(dir, "model.safetensors", |p| self.vs.save(p).map_err(text))?;
                write_part(dir, "target.safetensors", |p| {
                    self.target_vs.save(p).map_err(text)
                })?;
                write_part(dir, REPLAY_FILE, |p| self.replay.save(p))?;
                write_part(dir, "optimizer.safetensors", |p| {
                    self.opt.save(p).map_err(text)
                })?;
                write_part(dir, "state.json", |p| {
                    let json = serde_json::to_string_pretty(&state).map_err(|e| e.to_string())?;
                    std::fs::write(p, json).map_err(|e| e.to_string())
                })?;
                write_part(dir, "config.toml", |p| {
                    std::fs::write(p, &config).map_err(|e| e.to_string())
                })
            },
        )?;
        Ok(dir)
    }

    /// Restores a learner from a checkpoint folder written by
    /// [`Learner::save_checkpoint`], after checking it matches `cfg` and `env`.
    /// A checkpoint from before the replay was saved resumes with an empty
    /// one, which refills from the resumed policy (one whose manifest lists
    /// the replay and lacks it is refused as incomplete).
    pub fn resume(cfg: EppoConfig, env: EnvName, dir: &Path) -> Result<Self, EppoError> {
        let manifest = read_manifest(dir)?;
        let mut learner = Learner::new(cfg, env)?;
        manifest.check_compatible(
            dir,
            "eppo",
            env.as_str(),
            env.physics_steps_per_action(learner.cfg.tasks.physics_steps_per_action),
            &learner.model_manifest(),
        )?;
        let bad = |file: &str, e: String| {
            EppoError::Checkpoint(CheckpointError::Invalid {
                path: dir.join(file),
                problem: e,
                fix: "resume from an earlier checkpoints/step_N folder, or start a new run".into(),
            })
        };
        learner
            .vs
            .load(dir.join("model.safetensors"))
            .map_err(|e| bad("model.safetensors", e.to_string()))?;
        learner
            .target_vs
            .load(dir.join("target.safetensors"))
            .map_err(|e| bad("target.safetensors", e.to_string()))?;
        for (file, vs) in [
            ("model.safetensors", &learner.vs),
            ("target.safetensors", &learner.target_vs),
        ] {
            if let Some((name, n)) = crate::guard::non_finite_variable(vs) {
                return Err(bad(
                    file,
                    format!("weight {name} holds {n} NaN or infinite values"),
                ));
            }
        }
        learner
            .opt
            .load(&dir.join("optimizer.safetensors"))
            .map_err(|e| bad("optimizer.safetensors", e))?;
        let text = std::fs::read_to_string(dir.join("state.json"))
            .map_err(|e| bad("state.json", e.to_string()))?;
        let state: TrainState =
            serde_json::from_str(&text).map_err(|e| bad("state.json", e.to_string()))?;
        if state.spec != learner.spec {
            return Err(bad(
                "state.json",
                "the environment's spaces differ from the checkpoint's".into(),
            ));
        }
        // Checkpoints from before the PID terms hold lambda alone: the
        // integral Eq. (7) moved.
        learner.multiplier = state
            .multiplier
            .unwrap_or_else(|| Multiplier::new(state.lambda));
        // A fork onto per-episode multipliers, or to another K: the new ones
        // start at the checkpoint's lambda; a fork off them keeps lambda alone.
        let k = if learner.cfg.constraint.per_episode_multipliers {
            learner.cfg.tasks.k_max
        } else {
            0
        };
        let lambda = learner.multiplier.lambda;
        learner.multiplier.per_episode.resize(k, lambda);
        // A tuned weight goes on from where it was; a fixed one is the
        // config's, so that a fork can change it.
        if learner.cfg.exploration.target_entropy.is_some() {
            learner.entropy_coef = state
                .entropy_coef
                .unwrap_or(learner.cfg.exploration.entropy_coef);
        }
        // Older checkpoints have no measured start: a fork that asks for one
        // measures it afresh.
        learner.constraint_start = state.constraint_start.unwrap_or_default();
        learner.updates = state.updates;
        learner.env_steps = state.env_steps;
        // Checkpoints from before tasks were recorded restart the count.
        let recorded = match &state.pretrain_tasks {
            None => 0,
            Some(tasks) => tasks.end.checked_sub(tasks.start).ok_or_else(|| {
                bad(
                    "state.json",
                    format!(
                        "pretrain_tasks end {} is before start {}",
                        tasks.end, tasks.start
                    ),
                )
            })?,
        };
        learner.tasks_drawn = state.tasks_drawn.unwrap_or(recorded);
        let mut rng = ChaCha8Rng::from_seed(state.rng_seed);
        rng.set_stream(state.rng_stream);
        rng.set_word_pos(
            state
                .rng_word_pos
                .parse::<u128>()
                .map_err(|e| bad("state.json", e.to_string()))?,
        );
        learner.rng = rng;
        let replay = dir.join(REPLAY_FILE);
        if replay.exists() {
            learner.replay = Replay::load(&replay, learner.cfg.targets.replay_capacity)
                .map_err(|e| bad(REPLAY_FILE, e))?;
        } else {
            eprintln!(
                "{} holds no {REPLAY_FILE}: the replay refills from the resumed policy, and the \
                 first rounds train on few trajectories",
                dir.display()
            );
        }
        Ok(learner)
    }
}

/// Removes the replay from every checkpoint at `path` (a checkpoint folder
/// or a run folder), rewriting each manifest: the checkpoint still loads,
/// evaluates and forks, and a resume refills its replay. Returns each
/// checkpoint with the bytes freed (`None`: it held no replay).
pub fn drop_replay(path: &Path) -> Result<Vec<(PathBuf, Option<u64>)>, CheckpointError> {
    crate::checkpoint::checkpoint_folders(path)?
        .into_iter()
        .map(|dir| {
            let freed = crate::checkpoint::drop_file(&dir, REPLAY_FILE)?;
            Ok((dir, freed))
        })
        .collect()
}

/// The replay buffer's file in a checkpoint folder.
pub(super) const REPLAY_FILE: &str = "replay.safetensors";

/// Counters and RNG state in `state.json`.
#[derive(Debug, Serialize, Deserialize)]
pub(super) struct TrainState {
    pub(super) lambda: f64,
    /// The multiplier's whole state (absent in older checkpoints).
    #[serde(default)]
    pub(super) multiplier: Option<Multiplier>,
    /// When the constraint came on (absent in older checkpoints).
    #[serde(default)]
    pub(super) constraint_start: Option<ConstraintStart>,
    /// The entropy weight (absent in checkpoints from before it was tuned).
    #[serde(default)]
    pub(super) entropy_coef: Option<f64>,
    pub(super) updates: u64,
    pub(super) env_steps: u64,
    pub(super) rng_seed: [u8; 32],
    pub(super) rng_stream: u64,
    /// u128 as a decimal string (JSON numbers cannot hold it).
    pub(super) rng_word_pos: String,
    pub(super) spec: NetSpec,
    /// The pretraining tasks seen so far (absent in older checkpoints).
    #[serde(default)]
    pub(super) pretrain_tasks: Option<PretrainTasks>,
    /// Tasks drawn so far (more than `pretrain_tasks` holds with a task pool).
    #[serde(default)]
    pub(super) tasks_drawn: Option<u64>,
}

/// The pretraining tasks a checkpoint folder records having seen, if it does
/// (checkpoints written before tasks were recorded return `None`).
pub fn recorded_pretrain_tasks(dir: &Path) -> Result<Option<PretrainTasks>, EppoError> {
    let path = dir.join("state.json");
    let bad = |e: String| {
        EppoError::Checkpoint(CheckpointError::Invalid {
            path: path.clone(),
            problem: e,
            fix: "point at a complete checkpoints/step_N folder".into(),
        })
    };
    let text = std::fs::read_to_string(&path).map_err(|e| bad(e.to_string()))?;
    let state: TrainState = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
    Ok(state.pretrain_tasks)
}

pub(super) fn model_manifest(cfg: &EppoConfig, spec: &NetSpec) -> serde_json::Value {
    let mut manifest = serde_json::json!({
        // The token layout: checkpoints from before the arrived observation
        // was added read a narrower token and are refused by name.
        "token": "obs,arrived_obs,prev_action,reward,cost,ctg,start",
        "transformer": cfg.model.transformer,
        "encoder_hidden": cfg.model.encoder_hidden,
        "head_hidden": cfg.model.head_hidden,
        "n_critics": cfg.model.n_critics,
        "obs_dim": spec.obs_dim,
        "n_actions": spec.n_actions,
        "act_dim": spec.act_flat(),
    });
    // Only runs with these heads record them, so older checkpoints stay loadable.
    if cfg.goal.goal_recall_coef > 0.0 {
        manifest["goal_recall_head"] = true.into();
    }
    if cfg.novelty.novelty_critic {
        manifest["novelty_critic"] = true.into();
    }
    manifest
}
