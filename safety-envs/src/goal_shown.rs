//! [`GoalShown`]: any environment with its goal's position appended to every
//! observation, with a flag that says it is shown. The debugging ladder's
//! goal-conditioned rung: an agent that sees the goal needs no memory to
//! reach it, so its success separates learning to drive to a position from
//! learning to recall one from context. A trainer may blank the slots
//! ([`GoalShown::hide`]) in some trajectories, so that one policy learns both
//! to drive to a shown goal and to find one; evaluation's tasks always hide it.

use crate::env::{Action, CmdpEnv, GoalRule, Space, StepOutcome};
use crate::error::EnvError;
use crate::spawn::Task;

/// `inner` with [`CmdpEnv::goal_position`] and the flag 1 as
/// [`GoalShown::SLOTS`] extra observation entries.
pub struct GoalShown {
    inner: Box<dyn CmdpEnv>,
    inner_dim: usize,
}

impl GoalShown {
    /// The entries appended to the observation: the goal's x and y, then 1
    /// (shown). Hidden, all three are 0: the flag tells a goal at the origin
    /// from none.
    pub const SLOTS: usize = 3;

    /// Wraps `inner`; its observation grows by [`GoalShown::SLOTS`] entries at
    /// the end.
    pub fn new(inner: Box<dyn CmdpEnv>) -> Self {
        let inner_dim = inner.observation_space().flat_dim();
        GoalShown { inner, inner_dim }
    }

    /// Blanks the goal's slots at the end of one observation `row` of this
    /// wrapper's (or of a wider agent's) layout: the goal hidden.
    pub fn hide(row: &mut [f32]) {
        let n = row.len();
        row[n - Self::SLOTS..].fill(0.0);
    }

    /// Whether `row`'s slots show a goal (its flag is set).
    pub fn shows(row: &[f32]) -> bool {
        row[row.len() - 1] > 0.5
    }

    /// Writes `goal` into `row`'s slots, shown.
    pub fn show(row: &mut [f32], goal: [f32; 2]) {
        let n = row.len();
        row[n - Self::SLOTS..].copy_from_slice(&[goal[0], goal[1], 1.0]);
    }

    fn show_goal(&self, obs: &mut [f32]) {
        Self::show(obs, self.inner.goal_position());
    }
}

impl CmdpEnv for GoalShown {
    fn observation_space(&self) -> Space {
        let Space::Box { mut low, mut high } = self.inner.observation_space() else {
            unreachable!("observation spaces are boxes (CmdpEnv)")
        };
        // The goal lies where the agent's position can; the flag is 0 or 1.
        for i in self.inner.goal_rule().xy {
            low.push(low[i]);
            high.push(high[i]);
        }
        low.push(0.0);
        high.push(1.0);
        Space::Box { low, high }
    }

    fn action_space(&self) -> Space {
        self.inner.action_space()
    }

    fn max_episode_steps(&self) -> usize {
        self.inner.max_episode_steps()
    }

    fn set_task(&mut self, task: &Task) -> Result<(), EnvError> {
        self.inner.set_task(task)
    }

    fn task(&self) -> &Task {
        self.inner.task()
    }

    fn reset(&mut self, seed: u64, obs: &mut [f32]) -> Result<(), EnvError> {
        self.inner.reset(seed, &mut obs[..self.inner_dim])?;
        self.show_goal(obs);
        Ok(())
    }

    fn step(&mut self, action: Action<'_>, obs: &mut [f32]) -> Result<StepOutcome, EnvError> {
        let outcome = self.inner.step(action, &mut obs[..self.inner_dim])?;
        self.show_goal(obs);
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

    /// The goal and its flag ride at the end of every observation, the rest
    /// is the inner environment's, bit for bit, and it follows a new task;
    /// hidden, the slots are zeros and the flag reads so.
    #[test]
    fn the_goal_is_appended_and_follows_the_task() {
        for name in [EnvName::DarkRoom, EnvName::Point] {
            let make = || make_env(name, &EnvOptions::default()).unwrap();
            let (mut plain, mut shown) = (make(), GoalShown::new(make()));
            let n = plain.observation_space().flat_dim();
            assert_eq!(shown.observation_space().flat_dim(), n + 3, "{name}");
            for seed in [3, 4] {
                let task = sample_task(&spawn_config(name), Orientation::Centre, seed).unwrap();
                plain.set_task(&task).unwrap();
                shown.set_task(&task).unwrap();
                let (mut a, mut b) = (vec![0.0; n], vec![0.0; n + 3]);
                plain.reset(7, &mut a).unwrap();
                shown.reset(7, &mut b).unwrap();
                assert_eq!(a[..], b[..n], "{name}: the inner observation unchanged");
                let goal = plain.goal_position();
                assert_eq!(b[n..], [goal[0], goal[1], 1.0], "{name}: the goal appended");
                assert!(GoalShown::shows(&b));
                let action = match plain.action_space() {
                    Space::Discrete { .. } => vec![],
                    Space::Box { low, .. } => vec![0.5; low.len()],
                };
                let act = |e: &mut dyn CmdpEnv, o: &mut [f32]| match e.action_space() {
                    Space::Discrete { .. } => e.step(Action::Discrete(1), o).unwrap(),
                    Space::Box { .. } => e.step(Action::Continuous(&action), o).unwrap(),
                };
                let (ra, rb) = (act(plain.as_mut(), &mut a), act(&mut shown, &mut b));
                assert_eq!(ra, rb, "{name}: the same outcome");
                assert_eq!(a[..], b[..n], "{name}: the inner observation after a step");
                assert_eq!(b[n..n + 2], plain.goal_position(), "{name}");
                GoalShown::hide(&mut b);
                assert_eq!(b[..n], a[..], "{name}: hiding keeps the rest");
                assert_eq!(b[n..], [0.0; 3], "{name}");
                assert!(!GoalShown::shows(&b));
            }
        }
    }
}
