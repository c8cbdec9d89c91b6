//! The animation of an evaluation's recorded trajectory: SafeDarkRoom drawn
//! cell by cell; Point and Car rendered by MuJoCo from a replay of the
//! recorded actions, or drawn from the recorded positions without
//! off-screen OpenGL.

use std::path::Path;

use safety_envs::{CmdpEnv, EnvName, Orientation, sample_task, spawn_config};

use super::error::EvalCmdError;
use crate::plots;
use crate::report::{EvalReport, Recording};

/// The animation of the recorded trajectory.
pub(super) fn render(
    env: EnvName,
    report: &EvalReport,
    rec: &Recording,
    path: &Path,
) -> Result<(), EvalCmdError> {
    let task = &report.result.tasks[rec.task];
    let budget = report.result.conditions[rec.condition].ctg;
    match env {
        EnvName::DarkRoom => {
            let k_n = rec.episodes.len();
            // Every step of the first three and the last two episodes; one
            // frame per episode in between.
            plots::darkroom_animation(rec, task, budget, &|k| k < 3 || k + 2 >= k_n, path)?;
            Ok(())
        }
        EnvName::Point | EnvName::Car => {
            let robot = if env == EnvName::Point {
                safety_envs::nav::Robot::Point
            } else {
                safety_envs::nav::Robot::Car
            };
            let nav = safety_envs::nav::NavConfig {
                max_episode_steps: report.max_episode_steps,
                ..safety_envs::nav::NavConfig::new(robot)
            };
            let k_n = rec.episodes.len();
            // Every 3rd step of the first two and the last episode, rendered
            // by MuJoCo from a replay of the recorded actions; without
            // off-screen OpenGL, a drawing from the recorded positions.
            let steps = |k: usize| k < 2 || k + 1 == k_n;
            let orientation: Orientation = report.result.orientation.parse()?;
            let task_value = sample_task(&spawn_config(env), orientation, task.seed)?;
            let mut sim = safety_envs::SafeDarkMujoco::new(nav.clone())?;
            sim.set_task(&task_value)?;
            match plots::nav_render_animation(&mut sim, rec, task, budget, &steps, 3, path) {
                Ok(_) => return Ok(()),
                Err(e) => eprintln!(
                    "MuJoCo rendering failed ({e}); drawing the recorded positions instead"
                ),
            }
            let arena = plots::ArenaGeometry {
                extent: nav.extent,
                spacing: nav.spacing(),
                goal_radius: nav.goal_radius,
                hazard_radius: nav.hazard_radius,
            };
            plots::nav_animation(rec, task, &arena, budget, &steps, 3, path)?;
            Ok(())
        }
    }
}
