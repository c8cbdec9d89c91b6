//! Loading a checkpoint for evaluation: dispatch on what the folder holds.
//!
//! - A folder with `manifest.json` (an EPPO `checkpoints/step_N`, or any
//!   learner that writes one): the manifest's `method` decides.
//! - A folder with `spec.json` (a supervised AD run): AD.
//! - A folder with `checkpoints/` (an EPPO run folder): its latest checkpoint.
//!
//! Every loader checks that the checkpoint was trained on the environment
//! asked for and that its observation and action sizes match the
//! environment's, so a foreign checkpoint fails here with its path named.

use std::path::Path;

use safety_envs::{EnvName, EnvOptions, Space, make_env};

use crate::ad::AdAgent;
use crate::checkpoint::{MANIFEST, RunDir, read_manifest};
use crate::eppo::EppoAgent;
use crate::eval::{BudgetRange, shared_parameters};
use crate::eval_cmd::{ContextLimit, EvalCmdError, LoadedAgent, Method};

fn bad(path: &Path, message: impl Into<String>) -> EvalCmdError {
    EvalCmdError::Checkpoint {
        path: path.display().to_string(),
        message: message.into(),
    }
}

/// The method of the checkpoint at `path`, from its files.
pub fn detect_method(path: &Path) -> Result<Method, EvalCmdError> {
    if !path.is_dir() {
        return Err(bad(path, "not a folder"));
    }
    if path.join(MANIFEST).is_file() {
        let m = read_manifest(path).map_err(|e| bad(path, e.to_string()))?;
        return match m.method.as_str() {
            "eppo" => Ok(Method::Eppo),
            "ad" => Ok(Method::Ad),
            other => Err(bad(
                path,
                format!("method {other:?} in {MANIFEST} cannot be evaluated (eppo, ad)"),
            )),
        };
    }
    if path.join("spec.json").is_file() {
        return Ok(Method::Ad);
    }
    if path.join("checkpoints").is_dir() {
        return Ok(Method::Eppo);
    }
    Err(bad(
        path,
        format!(
            "not a checkpoint: no {MANIFEST} (EPPO checkpoint), spec.json (AD run) or checkpoints/ (EPPO run)"
        ),
    ))
}

/// Compares the model's input/output sizes with the environment's.
fn check_shape(
    path: &Path,
    env: EnvName,
    obs_dim: usize,
    discrete: Option<usize>,
    act_dim: usize,
) -> Result<(), EvalCmdError> {
    let probe = make_env(env, &EnvOptions::default())?;
    let env_obs = probe.observation_space().flat_dim();
    let (env_discrete, env_act) = match probe.action_space() {
        Space::Discrete { n } => (Some(n), n),
        Space::Box { low, .. } => (None, low.len()),
    };
    if obs_dim != env_obs || act_dim != env_act || discrete.is_some() != env_discrete.is_some() {
        return Err(bad(
            path,
            format!(
                "model shape does not fit {env}: the model takes {obs_dim} observation values and {} {act_dim}-wide actions, \
                 {env} has {env_obs} observation values and {} {env_act}-wide actions",
                if discrete.is_some() {
                    "discrete"
                } else {
                    "continuous"
                },
                if env_discrete.is_some() {
                    "discrete"
                } else {
                    "continuous"
                },
            ),
        ));
    }
    Ok(())
}

/// Loads the checkpoint at `path` for evaluation on `env`.
pub fn load_checkpoint(path: &Path, env: EnvName) -> Result<LoadedAgent, EvalCmdError> {
    match detect_method(path)? {
        Method::Eppo => {
            let ckpt = if path.join(MANIFEST).is_file() {
                path.to_path_buf()
            } else {
                RunDir::resolve_resume(path)
                    .map_err(|e| bad(path, e.to_string()))?
                    .1
            };
            let manifest = read_manifest(&ckpt).map_err(|e| bad(&ckpt, e.to_string()))?;
            if manifest.env != env.as_str() {
                return Err(bad(
                    &ckpt,
                    format!(
                        "trained on {:?}, asked to evaluate on {env}: pass --env {}",
                        manifest.env, manifest.env
                    ),
                ));
            }
            let m = &manifest.model;
            let get = |k: &str| m.get(k).and_then(|v| v.as_u64()).map(|v| v as usize);
            let (Some(obs_dim), Some(act_dim)) = (get("obs_dim"), get("act_dim")) else {
                return Err(bad(&ckpt, format!("{MANIFEST} records no obs_dim/act_dim")));
            };
            check_shape(&ckpt, env, obs_dim, get("n_actions"), act_dim)?;
            let agent = EppoAgent::load(&ckpt, tch::Device::cuda_if_available())
                .map_err(|e| bad(&ckpt, e.to_string()))?;
            let cfg = agent.config().clone();
            let context = ContextLimit {
                max_episode_steps: cfg.max_episode_steps,
                max_len: cfg.model.max_len.max(0) as usize,
            };
            let loaded = LoadedAgent {
                method: Method::Eppo,
                agent: Box::new(agent),
                checkpoint: Some(ckpt.clone()),
                // EPPO draws its pretraining tasks from random seeds it does
                // not record: only the seed-range/orientation split applies.
                pretrain_tasks: None,
                budget_range: Some(BudgetRange {
                    low: cfg.ctg_min,
                    high: cfg.ctg_max,
                }),
                // EppoAgent keeps its VarStore private: no checksum handle.
                parameters: Vec::new(),
                context: Some(context),
                note: format!(
                    "EPPO checkpoint after {} updates (run planned {}), K_max {}, context {} steps",
                    manifest.updates, cfg.total_updates, cfg.k_max, cfg.model.max_len
                ),
            };
            Ok(loaded)
        }
        Method::Ad => {
            let (agent, info) = AdAgent::load(path).map_err(|e| bad(path, e.to_string()))?;
            if info.env != env.as_str() {
                return Err(bad(
                    path,
                    format!(
                        "trained on {:?}, asked to evaluate on {env}: pass --env {}",
                        info.env, info.env
                    ),
                ));
            }
            let spec = agent.spec();
            check_shape(
                path,
                env,
                spec.obs_dim,
                spec.discrete.then_some(spec.action_dim),
                spec.action_dim,
            )?;
            let parameters = shared_parameters(agent.varstore());
            let loaded = LoadedAgent {
                method: Method::Ad,
                agent: Box::new(agent),
                checkpoint: Some(path.to_path_buf()),
                pretrain_tasks: info.pretrain_tasks.clone(),
                budget_range: None,
                parameters,
                // AD slides its context window: any number of episodes runs.
                context: None,
                note: format!(
                    "AD run after {} of {} updates",
                    info.updates_done, info.updates_planned
                ),
            };
            Ok(loaded)
        }
        Method::Random => Err(bad(path, "a random policy has no checkpoint")),
    }
}
