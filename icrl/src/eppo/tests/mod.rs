//! EPPO's tests, by topic: `collect` (trajectories, relabelling,
//! exploration, the critics' shaped rewards), `constraint` (its start, the
//! multiplier, the penalty forms and prices), `losses` (each loss and mask on
//! a fixed batch), `run` (the cache, determinism, checkpoints, resumes, the
//! overlapped loop). Here: the fixtures they share, and the tiny
//! configuration the evaluation and reliability tests borrow.

use std::path::{Path, PathBuf};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::{Device, Kind, Tensor};

use safety_envs::{EnvName, Orientation, VecEnv, sample_task, spawn_config};

use super::collect::{
    Acting, EnvActions, GoalSlotStats, Policy, last_over_budget, new_cells_while_searching,
    repeat_cost_per_episode, repeated_costs, sample_actions,
};
use super::losses::{goal_recall_loss, losses, n_step_targets, penalised_cost, tuned_entropy_coef};
use super::replay::{Batch, BudgetInTargets, OverBudget, Shaping, make_batch, novel_arrivals};
use super::*;
use crate::agent::{Actions, Conditioning, InContextAgent, StepInput};
use crate::model::Positions;
use crate::task_seeds::pretrain_task_seed;

mod collect;
mod constraint;
mod losses;
mod run;
mod sections;

/// A tiny configuration: trajectories of 2 episodes of 6 steps (also
/// used by the evaluation tests).
pub(crate) fn tiny() -> EppoConfig {
    let mut table = crate::presets::preset_table("eppo", "darkroom", "quick").unwrap();
    let sets = [
        "max_episode_steps=6",
        "k_min=2",
        "k_max=2",
        "n_envs=3",
        "batch_size=3",
        "replay_capacity=1000",
        "encoder_hidden=16",
        "head_hidden=16",
        "model.d_model=16",
        "model.n_heads=2",
        "model.n_layers=1",
        "model.d_ff=32",
        "model.max_len=12",
        "total_updates=4",
        "updates_per_round=2",
        "learning_starts=0",
        "checkpoint_every=2",
        // Tests run the synchronous loop; its overlapped twin has its own.
        "overlap=false",
        "learner_threads=0",
    ]
    .map(String::from);
    EppoConfig::apply_sets(&mut table, &sets).unwrap();
    EppoConfig::from_table("tiny", table).unwrap()
}

fn tiny_learner(seed: u64) -> (Learner, VecEnv) {
    let mut cfg = tiny();
    cfg.run.seed = seed;
    let learner = Learner::new(cfg.clone(), EnvName::DarkRoom).unwrap();
    (learner, training_venv(EnvName::DarkRoom, &cfg))
}

/// [`tiny`] for Point: two trajectories of two 75-step episodes, macro
/// actions of 50 physics steps.
fn tiny_point() -> EppoConfig {
    let mut cfg = tiny();
    cfg.tasks.max_episode_steps = 75;
    cfg.model.transformer.max_len = 150;
    cfg.tasks.n_envs = 2;
    cfg.optimisation.batch_size = 2;
    cfg.tasks.physics_steps_per_action = Some(50);
    cfg
}

/// `cfg.tasks.n_envs` training environments of `env`, stepped on one thread.
fn training_venv(env: EnvName, cfg: &EppoConfig) -> VecEnv {
    let envs = (0..cfg.tasks.n_envs)
        .map(|_| make_training_env(env, cfg).unwrap())
        .collect();
    VecEnv::new(envs, 1, true).unwrap()
}

/// `cfg` fails validation with a message that names `field`.
fn refused(cfg: &EppoConfig, field: &str) -> bool {
    cfg.validate()
        .is_err_and(|err| err.to_string().contains(field))
}

fn to_vec(t: &Tensor) -> Vec<f32> {
    Vec::<f32>::try_from(&t.to_kind(Kind::Float).view([-1])).unwrap()
}

/// Two episodes on a grid (obs = position, one action value): episode 0
/// passes (4, 6) at its second step and goes on to the time limit;
/// episode 1 ends at its real goal (5, 5) without passing (4, 6).
fn two_episode_trajectory() -> Trajectory {
    let path: [([f32; 2], [f32; 2], f32); 5] = [
        ([4.0, 4.0], [4.0, 5.0], 0.0),
        ([4.0, 5.0], [4.0, 6.0], 1.0),
        ([4.0, 6.0], [3.0, 6.0], 0.0),
        ([4.0, 4.0], [5.0, 4.0], 1.0),
        ([5.0, 4.0], [5.0, 5.0], 0.0),
    ];
    let mut t = Trajectory {
        budget: 0.5,
        ..Default::default()
    };
    for (s, (obs, next, cost)) in path.iter().enumerate() {
        t.obs.extend_from_slice(obs);
        t.next_obs.extend_from_slice(next);
        t.actions.push(s as f32);
        t.action_idx.push(s as i64);
        t.costs.push(*cost);
        t.start.push(s == 0 || s == 3);
        t.ctg.push(if s == 0 || s == 3 {
            0.5
        } else {
            0.5 - path[s - 1].2
        });
        t.episode.push(u32::from(s >= 3));
        t.rewards.push(if s == 4 { 1.0 } else { 0.0 });
        t.terminated.push(s == 4);
        t.truncated.push(s == 2);
    }
    t.episode_returns = vec![0.0, 1.0];
    t.episode_costs = vec![1.0, 1.0];
    t.episode_success = vec![false, true];
    t
}

/// A SafeDarkRoom-like trajectory over cells (row, col): episode 0 walks
/// (4,4) -> (4,5) -> (4,4) -> (3,4); episode 1 from (4,4) -> (4,5) -> (3,5)
/// reaches the goal there, then (4,4) -> (5,4) after it.
fn cell_walk() -> Trajectory {
    let cells: [[f32; 2]; 8] = [
        [4.0, 4.0],
        [4.0, 5.0],
        [4.0, 4.0],
        [4.0, 4.0],
        [4.0, 5.0],
        [4.0, 4.0],
        [4.0, 4.0],
        [4.0, 4.0],
    ];
    let next: [[f32; 2]; 8] = [
        [4.0, 5.0],
        [4.0, 4.0],
        [3.0, 4.0],
        [4.0, 5.0],
        [3.0, 5.0],
        [5.0, 4.0],
        [5.0, 4.0],
        [3.0, 3.0],
    ];
    let n = cells.len();
    Trajectory {
        budget: 1.0,
        goal: [3.0, 5.0],
        obs: cells.concat(),
        next_obs: next.concat(),
        actions: vec![0.0; 5 * n],
        action_idx: vec![0; n],
        rewards: vec![0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        costs: vec![0.0; n],
        ctg: vec![1.0; n],
        start: vec![true, false, false, true, false, true, false, false],
        terminated: vec![false, false, false, false, true, false, false, false],
        truncated: vec![false, false, true, false, false, false, false, true],
        episode: vec![0, 0, 0, 1, 1, 2, 2, 2],
        episode_returns: vec![0.0, 1.0, 0.0],
        episode_costs: vec![0.0; 3],
        episode_success: vec![false, true, false],
    }
}

/// The network's view of [`cell_walk`]: positions on SafeDarkRoom's 9x9
/// grid, its 5 actions.
fn grid_spec() -> NetSpec {
    NetSpec {
        obs_dim: 2,
        obs_low: vec![0.0; 2],
        obs_high: vec![8.0; 2],
        n_actions: Some(5),
        ..Default::default()
    }
}

/// A batch of `trajs` whose critics see the collected rewards only.
fn unshaped_batch(
    trajs: &[&Trajectory],
    cfg: &EppoConfig,
    spec: &NetSpec,
    rng: &mut ChaCha8Rng,
) -> Batch {
    make_batch(trajs, cfg, spec, Shaping::default(), rng, Device::Cpu)
}

/// One batch of every trajectory in `learner`'s replay (windows drawn with
/// seed 0, no novelty bonus).
fn replay_batch(learner: &Learner) -> Batch {
    let trajs: Vec<&Trajectory> = learner.replay.trajectories.iter().collect();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    unshaped_batch(&trajs, &learner.cfg, &learner.spec, &mut rng)
}

/// Trains `cfg` on SafeDarkRoom to its end in a fresh temporary folder named
/// after `name`; returns the folder (for the caller to remove) and the report.
pub(crate) fn train_darkroom(cfg: EppoConfig, name: &str) -> (PathBuf, PretrainReport) {
    let out = std::env::temp_dir().join(format!("icrl-eppo-{name}-{}", std::process::id()));
    let report = train(&PretrainOptions {
        env: EnvName::DarkRoom,
        cfg,
        out: out.clone(),
        resume: None,
        progress: false,
    })
    .unwrap();
    (out, report)
}

/// Trains `cfg` into `out` with a stop requested from the start: the run must
/// stop after update 1 with checkpoint `step_1`. Then resumes that run to its
/// end; returns the updates done and the `updates` of every metrics record.
pub(crate) fn stop_after_one_then_resume(cfg: &EppoConfig, out: &Path) -> (u64, Vec<u64>) {
    let options = |resume: Option<PathBuf>| PretrainOptions {
        env: EnvName::DarkRoom,
        cfg: cfg.clone(),
        out: out.to_path_buf(),
        resume,
        progress: false,
    };
    crate::stop::request();
    let e = train(&options(None)).unwrap_err();
    crate::stop::clear();
    let EppoError::Interrupted {
        checkpoint,
        updates,
    } = e
    else {
        panic!("{e}");
    };
    assert_eq!(updates, 1, "stopped after the first update");
    assert!(checkpoint.ends_with("step_1"), "{}", checkpoint.display());
    let run_dir = checkpoint.parent().unwrap().parent().unwrap().to_path_buf();
    let done = train(&options(Some(run_dir.clone()))).unwrap();
    let recorded =
        crate::checkpoint::recorded_counters(&run_dir.join("metrics.jsonl"), "updates").unwrap();
    (done.updates, recorded)
}
