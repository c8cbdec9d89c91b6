//! The frozen [`AdAgent`]: a trained model acting in context, RTG and CTG
//! restarting at the targets each episode, the KV cache rebuilt when the
//! context is full.

use std::fs;
use std::path::{Path, PathBuf};

use tch::{Device, Kind, Tensor, nn};

use super::AdError;
use super::checkpoint::TrainState;
use super::config::{AdConfig, AdSpec, TOKEN_LAYOUT, memory_estimate};
use super::model::AdModel;
use super::windows::push_token;
use crate::agent::{Actions, AgentError, Conditioning, InContextAgent, StepInput};
use crate::checkpoint::{CheckpointError, RunDir, read_manifest};
use crate::model::KvCache;
use crate::task_seeds::PretrainTasks;
use crate::tokens::StepToken;

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
    pub(super) spec: AdSpec,
    cfg: AdConfig,
    pub(super) cache: KvCache,
    /// The tokens in the cache, (B, L, token_dim).
    pub(super) window: Option<Tensor>,
    targets: Vec<(f32, f32)>,
    rtg: Vec<f32>,
    pub(super) ctg: Vec<f32>,
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
        // Conditioning far outside the training data (an RTG of 1e30) can
        // overflow the model: say so instead of sampling from NaN.
        if !bool::try_from(out.isfinite().all())? {
            return Err(AgentError::Input(format!(
                "the model's outputs are NaN or infinite for the conditioning (RTG, CTG) {:?}: \
                 condition on values like those of its training data",
                self.targets.first().copied().unwrap_or_default()
            )));
        }
        if self.spec.discrete {
            let idx = if greedy {
                out.argmax(-1, false)
            } else {
                out.f_softmax(-1, Kind::Float)?
                    .f_multinomial(1, true)?
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
