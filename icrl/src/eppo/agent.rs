//! The frozen [`EppoAgent`] that evaluation drives: a checkpoint loaded and
//! checked, acting through the KV cache.

use std::borrow::Cow;
use std::path::Path;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::{Device, nn};

use super::checkpoint::{TrainState, model_manifest};
use super::collect::{Acting, EnvActions, sample_actions};
use super::config::{EppoConfig, EppoError};
use super::net::memory_estimate;
use super::net::{EppoNet, NetSpec};
use crate::agent::{Actions, AgentError, Conditioning, InContextAgent, StepInput};
use crate::checkpoint::{CheckpointError, RunDir, read_manifest};
use safety_envs::EnvName;

/// A pretrained EPPO policy, frozen, acting through the KV cache.
pub struct EppoAgent {
    _vs: nn::VarStore,
    net: EppoNet,
    spec: NetSpec,
    cfg: EppoConfig,
    /// The entries at the end of its observation that it fills blank itself
    /// (the goal slots or the hazard map it was trained with).
    shown_slots: usize,
    acting: Option<Acting>,
    rng: ChaCha8Rng,
}

impl EppoAgent {
    /// Loads `checkpoints/step_N` (or a run folder: its latest checkpoint) onto `device`.
    pub fn load(path: &Path, device: Device) -> Result<Self, EppoError> {
        let dir = if path.join(crate::checkpoint::MANIFEST).is_file() {
            path.to_path_buf()
        } else {
            RunDir::resolve_resume(path)?.1
        };
        let manifest = read_manifest(&dir)?;
        let bad = |file: &str, e: String| {
            EppoError::Checkpoint(CheckpointError::Invalid {
                path: dir.join(file),
                problem: e,
                fix: "load a checkpoint written by `icrl pretrain` (method eppo)".into(),
            })
        };
        if manifest.method != "eppo" {
            return Err(bad(
                crate::checkpoint::MANIFEST,
                format!("method is {:?}, not eppo", manifest.method),
            ));
        }
        let text = std::fs::read_to_string(dir.join("config.toml"))
            .map_err(|e| bad("config.toml", e.to_string()))?;
        let table = text
            .parse::<toml::Table>()
            .map_err(|e| bad("config.toml", e.to_string()))?;
        let mut cfg = EppoConfig::from_table("config.toml", table)
            .map_err(|e| bad("config.toml", e.to_string()))?;
        cfg.run.device = if device == Device::Cpu {
            "cpu".into()
        } else {
            "cuda".into()
        };
        let text = std::fs::read_to_string(dir.join("state.json"))
            .map_err(|e| bad("state.json", e.to_string()))?;
        let state: TrainState =
            serde_json::from_str(&text).map_err(|e| bad("state.json", e.to_string()))?;
        if !cfg.goal.slots_ever_hidden() {
            return Err(EppoError::Checkpoint(CheckpointError::Invalid {
                path: dir.join("config.toml"),
                problem: "it was trained with goal_in_observation = true and goal_hidden_share \
                          = 0, a ladder rung whose agent is always shown the goal that the tasks \
                          it would be evaluated on hide"
                    .into(),
                fix: "evaluate a checkpoint trained without goal_in_observation, or with \
                      goal_hidden_share > 0"
                    .into(),
            }));
        }
        // A manifest naming no environment this version knows is refused here.
        manifest
            .env
            .parse::<EnvName>()
            .map_err(|e| bad(crate::checkpoint::MANIFEST, format!("{e}")))?;
        // The files decide sizes: check them before building anything.
        cfg.validate()
            .map_err(|e| bad("config.toml", e.to_string()))?;
        state.spec.check().map_err(|e| bad("state.json", e))?;
        memory_estimate(&cfg, &state.spec)
            .check()
            .map_err(|e| bad("config.toml", e))?;
        // The manifest's model must be what this version builds from the
        // stored config: a checkpoint from before a token-layout change is
        // refused by name instead of failing on a tensor shape.
        manifest
            .check_compatible(
                &dir,
                "eppo",
                &manifest.env,
                // The macro action is the checkpoint's own (read_manifest
                // refuses Point and Car checkpoints that do not record it).
                manifest.physics_steps_per_action,
                &model_manifest(&cfg, &state.spec),
            )
            .map_err(|e| {
                bad(
                    crate::checkpoint::MANIFEST,
                    format!("{e} (checkpoints written before the token layout changed must be retrained)"),
                )
            })?;
        let mut vs = nn::VarStore::new(device);
        let net = EppoNet::new(vs.root(), &cfg, &state.spec)?;
        vs.load(dir.join("model.safetensors"))
            .map_err(|e| bad("model.safetensors", e.to_string()))?;
        if let Some((name, n)) = crate::guard::non_finite_variable(&vs) {
            return Err(bad(
                "model.safetensors",
                format!("weight {name} holds {n} NaN or infinite values: this model cannot act"),
            ));
        }
        vs.freeze();
        Ok(EppoAgent {
            _vs: vs,
            net,
            shown_slots: cfg.goal.shown_slots(),
            spec: state.spec,
            rng: ChaCha8Rng::seed_from_u64(cfg.run.seed),
            cfg,
            acting: None,
        })
    }

    /// The training configuration stored with the checkpoint.
    pub fn config(&self) -> &EppoConfig {
        &self.cfg
    }

    /// The observation width it takes from the environment: its network's,
    /// less the slots it fills blank itself (`goal_in_observation`).
    pub fn env_obs_dim(&self) -> usize {
        self.spec.obs_dim - self.shown_slots
    }

    /// Reseeds action sampling.
    pub fn set_seed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }
}

impl InContextAgent for EppoAgent {
    fn reset(&mut self, conditioning: &[Conditioning]) -> Result<(), AgentError> {
        let budgets = conditioning
            .iter()
            .map(|c| match c {
                Conditioning::Budget { ctg } => Ok(*ctg),
                Conditioning::Targets { .. } => Err(AgentError::Input(
                    "EPPO is conditioned on a budget, not on RTG/CTG targets".into(),
                )),
            })
            .collect::<Result<Vec<f32>, _>>()?;
        self.acting = Some(Acting::new(&self.net, &self.spec, &self.cfg, &budgets));
        Ok(())
    }

    fn act(&mut self, input: &StepInput<'_>, greedy: bool) -> Result<Actions, AgentError> {
        // Trained with goal or hazard slots, it sees them blank: the tasks hide them.
        let (slots, env_od) = (self.shown_slots, self.env_obs_dim());
        let acting = self
            .acting
            .as_mut()
            .ok_or_else(|| AgentError::Input("act before reset".into()))?;
        let b = acting.budgets.len();
        let a = self.spec.act_flat();
        let sizes = [
            ("obs", input.obs.len(), b * env_od),
            ("arrived_obs", input.arrived_obs.len(), b * env_od),
            ("prev_action", input.prev_action.len(), b * a),
            ("reward", input.reward.len(), b),
            ("cost", input.cost.len(), b),
            ("episode_start", input.episode_start.len(), b),
        ];
        for (name, got, want) in sizes {
            if got != want {
                return Err(AgentError::Input(format!(
                    "{name} has {got} entries, expected {want}"
                )));
            }
        }
        // Continuous previous actions arrive in the environment's scale; the
        // network saw them in [-1, 1].
        let prev: Vec<f32> = match self.spec.n_actions {
            Some(_) => input.prev_action.to_vec(),
            None => input
                .prev_action
                .iter()
                .enumerate()
                .map(|(j, &x)| {
                    let (lo, hi) = (self.spec.act_low[j % a], self.spec.act_high[j % a]);
                    if hi > lo {
                        2.0 * (x - lo) / (hi - lo) - 1.0
                    } else {
                        x
                    }
                })
                .collect(),
        };
        let (obs, arrived_obs) = (
            with_blank_slots(input.obs, env_od, slots),
            with_blank_slots(input.arrived_obs, env_od, slots),
        );
        let input = StepInput {
            obs: &obs,
            arrived_obs: &arrived_obs,
            prev_action: &prev,
            ..*input
        };
        acting.observe(&input);
        let policy = acting.policy(&self.net, &input).map_err(|e| match e {
            EppoError::Torch(t) => AgentError::Torch(t),
            other => AgentError::Input(other.to_string()),
        })?;
        let (_, env_actions) = sample_actions(&policy, &self.spec, &[], greedy, &mut self.rng);
        Ok(match env_actions {
            EnvActions::Discrete(v) => Actions::Discrete(v),
            EnvActions::Continuous(v) => Actions::Continuous(v),
        })
    }
}

/// `rows`, each `env_od` wide, with `slots` zeros appended to each; copied
/// only where there are slots to append.
fn with_blank_slots(rows: &[f32], env_od: usize, slots: usize) -> Cow<'_, [f32]> {
    if slots == 0 {
        return Cow::Borrowed(rows);
    }
    rows.chunks(env_od)
        .flat_map(|row| row.iter().copied().chain(std::iter::repeat_n(0.0, slots)))
        .collect()
}
