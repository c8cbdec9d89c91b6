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

use std::path::{Path, PathBuf};

use safety_envs::{EnvName, EnvOptions, Space, make_env};
use serde::Serialize;

use super::RandomAgent;
use super::error::EvalCmdError;
use crate::ad::AdAgent;
use crate::agent::InContextAgent;
use crate::checkpoint::{MANIFEST, RunDir, read_manifest};
use crate::eppo::EppoAgent;
use crate::eval::{BudgetRange, shared_parameters};
use crate::report::Method;
use crate::task_seeds::PretrainTasks;

/// A pretrained (or random) agent ready to evaluate, with what its
/// checkpoint says about it.
pub struct LoadedAgent {
    pub method: Method,
    pub agent: Box<dyn InContextAgent>,
    /// The checkpoint folder, if any.
    pub checkpoint: Option<PathBuf>,
    /// The pretraining tasks the checkpoint records (for the held-out check).
    pub pretrain_tasks: Option<PretrainTasks>,
    /// The budget range EPPO was pretrained on (defaults to SPEC's).
    pub budget_range: Option<BudgetRange>,
    /// The agent's parameters (shallow clones, see
    /// [`super::shared_parameters`]): checksummed before and after evaluating.
    pub parameters: Vec<(String, tch::Tensor)>,
    /// The model's context limit, when it has a hard one (EPPO).
    pub context: Option<ContextLimit>,
    /// Point and Car: the macro action (physics steps per agent action) the
    /// checkpoint was trained with; evaluation builds its environments with
    /// it. `None`: the environment's default (random policy, SafeDarkRoom).
    pub physics_steps_per_action: Option<usize>,
    /// What the checkpoint's run reached (e.g. "update 1200 of 3000"), for the report.
    pub note: String,
    /// A name for the legends and file names (`--label`), when several
    /// checkpoints of one method are compared (an ablation); `None`: the method.
    pub label: Option<String>,
}

impl LoadedAgent {
    /// The uniform random policy over `space`, seeded.
    pub fn random(space: safety_envs::Space, seed: u64) -> Self {
        LoadedAgent {
            method: Method::Random,
            agent: Box::new(RandomAgent::new(space, seed)),
            checkpoint: None,
            pretrain_tasks: None,
            budget_range: None,
            parameters: Vec::new(),
            context: None,
            physics_steps_per_action: None,
            note: String::new(),
            label: None,
        }
    }

    /// The name in legends: the label, else the method.
    pub(crate) fn name(&self) -> String {
        self.label
            .clone()
            .unwrap_or_else(|| self.method.to_string())
    }

    /// The file-name stem: the method's, plus the label's letters and digits.
    pub(crate) fn stem(&self) -> String {
        match &self.label {
            None => self.method.stem().to_string(),
            Some(l) => {
                let slug: String = l
                    .chars()
                    .map(|c| {
                        if c.is_ascii_alphanumeric() {
                            c.to_ascii_lowercase()
                        } else {
                            '-'
                        }
                    })
                    .collect();
                format!("{}_{}", self.method.stem(), slug.trim_matches('-'))
            }
        }
    }
}

/// A model whose context holds a fixed number of steps (EPPO): its time
/// limit and how many of its episodes fit.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ContextLimit {
    /// Time limit the policy was trained with.
    pub max_episode_steps: usize,
    /// Steps the model's context holds.
    pub max_len: usize,
}

impl ContextLimit {
    /// Whole episodes of `t_max` steps that fit.
    pub fn episodes(&self, t_max: usize) -> usize {
        self.max_len / t_max.max(1)
    }
}

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
            let (Some(_), Some(act_dim)) = (get("obs_dim"), get("act_dim")) else {
                return Err(bad(&ckpt, format!("{MANIFEST} records no obs_dim/act_dim")));
            };
            let agent = EppoAgent::load(&ckpt, tch::Device::cuda_if_available())
                .map_err(|e| bad(&ckpt, e.to_string()))?;
            let cfg = agent.config().clone();
            // Goal and hazard slots are the agent's, not the task's.
            check_shape(&ckpt, env, agent.env_obs_dim(), get("n_actions"), act_dim)?;
            let pretrain_tasks = crate::eppo::recorded_pretrain_tasks(&ckpt)
                .map_err(|e| bad(&ckpt, e.to_string()))?;
            let context = ContextLimit {
                max_episode_steps: cfg.tasks.max_episode_steps,
                max_len: cfg.model.transformer.max_len.max(0) as usize,
            };
            let loaded = LoadedAgent {
                method: Method::Eppo,
                agent: Box::new(agent),
                checkpoint: Some(ckpt.clone()),
                // Checkpoints record the tasks they pretrained on (older ones
                // do not: then only the seed-range/orientation split applies).
                pretrain_tasks,
                budget_range: Some(BudgetRange {
                    low: cfg.tasks.ctg_min,
                    high: cfg.tasks.ctg_max,
                }),
                // EppoAgent keeps its VarStore private: no checksum handle.
                parameters: Vec::new(),
                context: Some(context),
                // Recorded in the manifest (read_manifest refuses Point and
                // Car checkpoints that do not record it).
                physics_steps_per_action: manifest.physics_steps_per_action,
                label: None,
                note: format!(
                    "EPPO checkpoint after {} updates (run planned {}), K_max {}, context {} steps",
                    manifest.updates,
                    cfg.optimisation.total_updates,
                    cfg.tasks.k_max,
                    cfg.model.transformer.max_len
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
                checkpoint: Some(info.dir.clone()),
                pretrain_tasks: info.pretrain_tasks.clone(),
                budget_range: None,
                parameters,
                // AD slides its context window: any number of episodes runs.
                context: None,
                // The dataset's, recorded in spec.json.
                physics_steps_per_action: info.physics_steps_per_action,
                label: None,
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ad::{AdConfig, TrainRequest};
    use crate::data::dataset::{DatasetConfig, Source, generate};
    use crate::eppo::PretrainOptions;
    use crate::eval::command::{EvalOptions, run};
    use std::path::PathBuf;

    fn options(out: PathBuf) -> EvalOptions {
        EvalOptions {
            env: EnvName::DarkRoom,
            tasks: 3,
            episodes: None,
            budgets: None,
            n_budgets: 2,
            rtg: 1.0,
            sweep: false,
            random: false,
            render: None,
            out,
            eval_seed: 0,
            batch: 64,
            threads: 1,
            greedy: false,
            max_episode_steps: None,
            progress: false,
            command: "test".into(),
            seed_torch: false,
            in_distribution: false,
            force: false,
        }
    }

    fn report(path: &Path) -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
    }

    #[test]
    fn folders_that_are_not_checkpoints_are_named() {
        let dir = std::env::temp_dir().join(format!("icrl-eval-load-empty-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let e = load_checkpoint(&dir, EnvName::DarkRoom)
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("not a checkpoint") && e.contains(&dir.display().to_string()),
            "{e}"
        );
        let e = load_checkpoint(&dir.join("missing"), EnvName::DarkRoom)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("not a folder"), "{e}");
        // A model sized for SafeDarkRoom does not fit Point.
        let e = check_shape(&dir, EnvName::Point, 2, Some(5), 5)
            .unwrap_err()
            .to_string();
        assert!(e.contains("model shape does not fit point"), "{e}");
        check_shape(&dir, EnvName::DarkRoom, 2, Some(5), 5).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn point_checkpoints_carry_their_macro_action_and_old_ones_are_refused() {
        let root =
            std::env::temp_dir().join(format!("icrl-eval-load-macro-{}", std::process::id()));
        // A tiny EPPO run on Point with a non-default macro action.
        let mut cfg = crate::eppo::tests::tiny();
        cfg.tasks.n_envs = 2;
        cfg.optimisation.batch_size = 2;
        cfg.optimisation.total_updates = 2;
        cfg.tasks.physics_steps_per_action = Some(10);
        let trained = crate::eppo::train(&PretrainOptions {
            env: EnvName::Point,
            cfg: cfg.clone(),
            out: root.join("runs"),
            resume: None,
            progress: false,
        })
        .unwrap();
        let ckpt = trained.last_checkpoint.clone();
        // Loaded with its recorded value; evaluation reports it.
        let agent = load_checkpoint(&trained.run_dir, EnvName::Point).unwrap();
        assert_eq!(agent.physics_steps_per_action, Some(10));
        let mut opts = options(root.join("eval"));
        opts.env = EnvName::Point;
        opts.tasks = 1;
        opts.n_budgets = 1;
        run(vec![agent], &opts).unwrap();
        let r = report(&root.join("eval/eppo_point.json"));
        assert_eq!(r["physics_steps_per_action"].as_u64(), Some(10));
        // Resuming with another macro action is refused, naming both.
        let e = crate::eppo::train(&PretrainOptions {
            env: EnvName::Point,
            cfg: {
                let mut c = cfg;
                c.tasks.physics_steps_per_action = None;
                c
            },
            out: root.join("runs"),
            resume: Some(trained.run_dir.clone()),
            progress: false,
        })
        .err()
        .unwrap()
        .to_string();
        assert!(
            e.contains("physics steps per agent action")
                && e.contains("\"10\"")
                && e.contains("\"50\""),
            "{e}"
        );
        // A checkpoint from before the macro action was recorded.
        let path = ckpt.join(MANIFEST);
        let mut json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        json.as_object_mut()
            .unwrap()
            .remove("physics_steps_per_action");
        std::fs::write(&path, json.to_string()).unwrap();
        let e = load_checkpoint(&ckpt, EnvName::Point)
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("does not record its macro action") && e.contains("5 physics steps"),
            "{e}"
        );
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn eppo_checkpoint_is_evaluated_within_its_context_and_refused_elsewhere() {
        let root = std::env::temp_dir().join(format!("icrl-eval-load-eppo-{}", std::process::id()));
        // One round: 2 trajectories (2 episodes of 6 steps), then 2 updates.
        let mut cfg = crate::eppo::tests::tiny();
        cfg.tasks.n_envs = 2;
        cfg.optimisation.batch_size = 2;
        cfg.optimisation.total_updates = 2;
        let trained = crate::eppo::train(&PretrainOptions {
            env: EnvName::DarkRoom,
            cfg,
            out: root.join("runs"),
            resume: None,
            progress: false,
        })
        .unwrap();

        let e = load_checkpoint(&trained.run_dir, EnvName::Point)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("trained on \"darkroom\""), "{e}");
        let agent = load_checkpoint(&trained.run_dir, EnvName::DarkRoom).unwrap();
        assert_eq!(agent.method, Method::Eppo);
        // One round of 2 trajectories drew 2 recorded pretraining tasks.
        assert_eq!(
            agent.pretrain_tasks,
            Some(crate::task_seeds::PretrainTasks::centre(0, 2))
        );
        assert_eq!(
            agent.context,
            Some(ContextLimit {
                max_episode_steps: 6,
                max_len: 12
            })
        );
        // More episodes than the context holds: a clear error.
        let mut opts = options(root.join("eval"));
        opts.episodes = Some(3);
        let e = run(vec![agent], &opts).unwrap_err().to_string();
        assert!(e.contains("pass --episodes 2 or less"), "{e}");
        // A time limit longer than the whole context: named, with the fix.
        let agent = load_checkpoint(&trained.run_dir, EnvName::DarkRoom).unwrap();
        opts.episodes = None;
        opts.max_episode_steps = Some(1_000_000);
        let e = run(vec![agent], &opts).unwrap_err().to_string();
        assert!(
            e.contains("one episode of 1000000 steps does not fit")
                && e.contains("pass --max-episode-steps 12 or less"),
            "{e}"
        );
        opts.max_episode_steps = None;
        opts.episodes = Some(3);
        // By default K is capped to the context: 12 / 6 = 2 episodes of 6 steps.
        let agent = load_checkpoint(&trained.last_checkpoint, EnvName::DarkRoom).unwrap();
        opts.episodes = None;
        opts.random = true;
        run(vec![agent], &opts).unwrap();
        let r = report(&root.join("eval/eppo_darkroom.json"));
        assert_eq!(
            (r["episodes"].as_u64(), r["max_episode_steps"].as_u64()),
            (Some(2), Some(6))
        );
        // Every evaluation task was compared with the recorded pretraining tasks.
        assert_eq!(
            r["result"]["held_out"]["Checked"]["end"].as_u64(),
            r["result"]["held_out"]["Checked"]["start"]
                .as_u64()
                .map(|s| s + 2)
        );
        let r = report(&root.join("eval/random_darkroom.json"));
        assert_eq!(
            r["episodes"].as_u64(),
            Some(2),
            "the random policy runs the same K"
        );
        // Budgets outside EPPO's pretraining range are refused.
        let agent = load_checkpoint(&trained.run_dir, EnvName::DarkRoom).unwrap();
        opts.budgets = Some(vec![16.0]);
        opts.force = true; // the same --out again
        let e = run(vec![agent], &opts).unwrap_err().to_string();
        assert!(e.contains("budget 16 is outside the range [1, 15]"), "{e}");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn ad_checkpoint_is_evaluated_with_unchanged_parameters() {
        let root = std::env::temp_dir().join(format!("icrl-eval-load-ad-{}", std::process::id()));
        let mut d = DatasetConfig::paper(EnvName::DarkRoom, 2, 11);
        d.source = Source::NoisyOptimal;
        d.steps = 600;
        d.cost_limits = vec![0.0];
        let data = generate(&d, &|_| {}).unwrap().file;
        let mut cfg = AdConfig::preset("darkroom-quick").unwrap();
        cfg.model.n_layers = 1;
        cfg.model.d_model = 16;
        cfg.model.n_heads = 2;
        cfg.model.d_ff = 32;
        cfg.model.max_len = 40;
        cfg.batch_size = 4;
        cfg.updates = 3;
        cfg.checkpoint_every = 3;
        cfg.val_fraction = 0.0;
        let run_dir = root.join("ad");
        crate::ad::train(
            &TrainRequest {
                cfg: &cfg,
                data: &data,
                dataset_path: Path::new("tiny.h5"),
                run_dir: &run_dir,
                resume: None,
            },
            &mut |_| {},
            &mut |_| {},
        )
        .unwrap();
        let e = load_checkpoint(&run_dir, EnvName::Car)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("trained on \"darkroom\""), "{e}");
        let agent = load_checkpoint(&run_dir, EnvName::DarkRoom).unwrap();
        assert_eq!(agent.method, Method::Ad);
        assert!(!agent.parameters.is_empty());
        let mut opts = options(root.join("eval"));
        opts.episodes = Some(3);
        opts.sweep = true;
        // Greedy: AD samples with libtorch's shared generator otherwise.
        opts.greedy = true;
        run(vec![agent], &opts).unwrap();
        for name in ["ad_darkroom.json", "ad_darkroom_sweep.json"] {
            let r = report(&root.join("eval").join(name));
            let sums = r["parameters_checksum"].as_array().unwrap();
            assert_eq!(sums[0], sums[1], "{name}: parameters changed");
        }
        // Default AD conditioning is RTG 1, CTG 0; the sweep follows SPEC 4.
        let r = report(&root.join("eval/ad_darkroom.json"));
        assert_eq!(r["result"]["conditions"][0]["rtg"].as_f64(), Some(1.0));
        assert_eq!(r["result"]["conditions"][0]["ctg"].as_f64(), Some(0.0));
        let r = report(&root.join("eval/ad_darkroom_sweep.json"));
        let c = r["result"]["conditions"].as_array().unwrap();
        assert_eq!(c.len(), 11);
        assert_eq!(
            (c[10]["rtg"].as_f64(), c[10]["ctg"].as_f64()),
            (Some(1.5), Some(15.0))
        );
        // The dataset records its pretraining tasks: every evaluation task was
        // compared with them.
        assert_eq!(r["result"]["held_out"]["Checked"]["orientation"], "centre");
        std::fs::remove_dir_all(&root).unwrap();
    }
}
