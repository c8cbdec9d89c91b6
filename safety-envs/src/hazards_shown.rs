//! [`HazardsShown`]: any environment with its task's hazard cells appended to
//! every observation as a map, with a flag that says it is shown. The
//! hazards' twin of [`GoalShown`](crate::GoalShown) for the robots' ladder:
//! with lidar off a hazard is felt only by paying for it, so a policy that is
//! shown where the hazards are first learns to route around them, and a
//! trainer that blanks the map ([`HazardsShown::hide`]) in a growing share of
//! trajectories then asks it to route around the ones its context holds.
//! Evaluation's tasks always hide it.

use crate::env::{Action, CmdpEnv, GoalRule, Space, StepOutcome};
use crate::error::EnvError;
use crate::spawn::Task;

/// `inner` with its task's hazard cells (1 where a hazard is, row-major over
/// the task grid) and the flag 1 as [`HazardsShown::slots`] extra observation
/// entries.
pub struct HazardsShown {
    inner: Box<dyn CmdpEnv>,
    inner_dim: usize,
    /// The map and flag of the current task.
    shown: Vec<f32>,
}

impl HazardsShown {
    /// The entries appended for a `grid_size x grid_size` task grid: one per
    /// cell, then the flag. Hidden, all are 0: the flag tells an empty map
    /// from none.
    pub fn slots(grid_size: usize) -> usize {
        grid_size * grid_size + 1
    }

    /// Wraps `inner`, whose tasks lie on a `grid_size x grid_size` grid; its
    /// observation grows by [`HazardsShown::slots`] entries at the end.
    pub fn new(inner: Box<dyn CmdpEnv>, grid_size: usize) -> Self {
        let inner_dim = inner.observation_space().flat_dim();
        let mut shown = vec![0.0; Self::slots(grid_size)];
        shown[grid_size * grid_size] = 1.0;
        HazardsShown {
            inner,
            inner_dim,
            shown,
        }
    }

    /// Blanks the `slots` entries at the end of one observation `row`: the
    /// hazards hidden.
    pub fn hide(row: &mut [f32], slots: usize) {
        let n = row.len();
        row[n - slots..].fill(0.0);
    }

    fn grid_size(&self) -> usize {
        (self.shown.len() - 1).isqrt()
    }
}

impl CmdpEnv for HazardsShown {
    fn observation_space(&self) -> Space {
        let Space::Box { mut low, mut high } = self.inner.observation_space() else {
            unreachable!("observation spaces are boxes (CmdpEnv)")
        };
        low.resize(self.inner_dim + self.shown.len(), 0.0);
        high.resize(self.inner_dim + self.shown.len(), 1.0);
        Space::Box { low, high }
    }

    fn action_space(&self) -> Space {
        self.inner.action_space()
    }

    fn max_episode_steps(&self) -> usize {
        self.inner.max_episode_steps()
    }

    fn set_task(&mut self, task: &Task) -> Result<(), EnvError> {
        let g = self.grid_size();
        if task.grid_size != g {
            return Err(EnvError::InvalidConfig(format!(
                "task grid size {} does not match the hazard map's {g}",
                task.grid_size
            )));
        }
        self.inner.set_task(task)?;
        self.shown[..g * g].fill(0.0);
        for cell in &task.obstacles {
            self.shown[cell.row * g + cell.col] = 1.0;
        }
        Ok(())
    }

    fn task(&self) -> &Task {
        self.inner.task()
    }

    fn reset(&mut self, seed: u64, obs: &mut [f32]) -> Result<(), EnvError> {
        self.inner.reset(seed, &mut obs[..self.inner_dim])?;
        obs[self.inner_dim..].copy_from_slice(&self.shown);
        Ok(())
    }

    fn step(&mut self, action: Action<'_>, obs: &mut [f32]) -> Result<StepOutcome, EnvError> {
        let outcome = self.inner.step(action, &mut obs[..self.inner_dim])?;
        obs[self.inner_dim..].copy_from_slice(&self.shown);
        Ok(outcome)
    }

    fn elapsed_steps(&self) -> usize {
        self.inner.elapsed_steps()
    }

    fn physics_steps_per_action(&self) -> Option<usize> {
        self.inner.physics_steps_per_action()
    }

    fn goal_rule(&self) -> GoalRule {
        self.inner.goal_rule()
    }

    fn goal_position(&self) -> [f32; 2] {
        self.inner.goal_position()
    }

    fn goal_seeking_action(&self) -> Option<Vec<f32>> {
        self.inner.goal_seeking_action()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::make::{EnvName, EnvOptions, make_env, spawn_config};
    use crate::spawn::{Orientation, sample_task};

    /// The map marks exactly the task's hazard cells and follows a new task,
    /// the flag reads shown, the rest is the inner environment's bit for
    /// bit; hidden, all zeros.
    #[test]
    fn the_hazard_map_is_appended_and_follows_the_task() {
        for name in [EnvName::DarkRoom, EnvName::Point] {
            let g = spawn_config(name).grid_size;
            let make = || make_env(name, &EnvOptions::default()).unwrap();
            let (mut plain, mut shown) = (make(), HazardsShown::new(make(), g));
            let n = plain.observation_space().flat_dim();
            let slots = HazardsShown::slots(g);
            assert_eq!(shown.observation_space().flat_dim(), n + slots, "{name}");
            for seed in [3, 4] {
                let task = sample_task(&spawn_config(name), Orientation::Edge, seed).unwrap();
                plain.set_task(&task).unwrap();
                shown.set_task(&task).unwrap();
                let (mut a, mut b) = (vec![0.0; n], vec![0.0; n + slots]);
                plain.reset(7, &mut a).unwrap();
                shown.reset(7, &mut b).unwrap();
                assert_eq!(a[..], b[..n], "{name}: the inner observation unchanged");
                let marked: Vec<(usize, usize)> = (0..g * g)
                    .filter(|&i| b[n + i] == 1.0)
                    .map(|i| (i / g, i % g))
                    .collect();
                let mut hazards: Vec<(usize, usize)> =
                    task.obstacles.iter().map(|c| (c.row, c.col)).collect();
                hazards.sort();
                assert_eq!(marked, hazards, "{name}: the map marks the task's hazards");
                assert_eq!(b[n + g * g], 1.0, "{name}: the flag");
                HazardsShown::hide(&mut b, slots);
                assert_eq!(b[..n], a[..], "{name}: hiding keeps the rest");
                assert!(b[n..].iter().all(|&x| x == 0.0), "{name}");
            }
        }
    }

    /// A task from another grid is refused, naming both sizes.
    #[test]
    fn a_task_of_another_grid_is_refused() {
        let mut shown =
            HazardsShown::new(make_env(EnvName::Point, &EnvOptions::default()).unwrap(), 5);
        let task = sample_task(&spawn_config(EnvName::DarkRoom), Orientation::Edge, 1).unwrap();
        let err = shown.set_task(&task).unwrap_err().to_string();
        assert!(err.contains("9") && err.contains("5"), "{err}");
    }
}
