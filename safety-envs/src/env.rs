//! The one constrained-MDP interface all environments share.
//!
//! A *task* (goal and hazard placement) is fixed with [`CmdpEnv::set_task`] and
//! stays until the next call: an in-context trajectory is K episodes in one
//! task. [`CmdpEnv::reset`] starts a new episode in the current task.
//! `terminated` and `truncated` keep Gymnasium's meaning: terminated means the
//! episode reached a terminal state (the goal), so no value is bootstrapped
//! past it; truncated means the time limit cut it short.

use crate::EnvError;
use crate::spawn::Task;

/// Shape and bounds of an observation or action space, so models size
/// themselves from the environment.
#[derive(Clone, Debug, PartialEq)]
pub enum Space {
    /// `n` discrete choices, numbered `0..n`.
    Discrete { n: usize },
    /// A real vector of `low.len()` entries, each within `[low[i], high[i]]`.
    Box { low: Vec<f32>, high: Vec<f32> },
}

impl Space {
    /// Number of scalars a model sees for this space: `n` (one-hot) for a
    /// discrete space, the vector length for a box.
    pub fn flat_dim(&self) -> usize {
        match self {
            Space::Discrete { n } => *n,
            Space::Box { low, .. } => low.len(),
        }
    }
}

/// Where a goal counts as reached, read off observations alone: the
/// observation's `xy` entries within `radius` of the goal. Hindsight
/// relabelling uses it to make any reached position a goal; a relabelled goal
/// is at least `min_start_distance` from the episode's start, as every real
/// goal is (no goal on the start cell).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GoalRule {
    /// Indices of the agent's position in the observation.
    pub xy: [usize; 2],
    /// Reached when the position is within this distance (0: equal).
    pub radius: f32,
    /// The nearest a real goal can be to the start.
    pub min_start_distance: f32,
}

impl GoalRule {
    /// The observation's position.
    pub fn position(&self, obs: &[f32]) -> [f32; 2] {
        [obs[self.xy[0]], obs[self.xy[1]]]
    }

    /// Distance between two positions.
    pub fn distance(a: [f32; 2], b: [f32; 2]) -> f32 {
        (a[0] - b[0]).hypot(a[1] - b[1])
    }

    /// The observation is at the goal `goal`.
    pub fn reached(&self, obs: &[f32], goal: [f32; 2]) -> bool {
        Self::distance(self.position(obs), goal) <= self.radius
    }
}

/// An action for one environment step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Action<'a> {
    Discrete(usize),
    Continuous(&'a [f32]),
}

/// What one step returns besides the observation (written into a caller's buffer).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepOutcome {
    pub reward: f32,
    pub cost: f32,
    /// The episode reached a terminal state (goal): do not bootstrap past it.
    pub terminated: bool,
    /// The time limit ended the episode: bootstrapping past it is still valid.
    pub truncated: bool,
}

impl StepOutcome {
    /// The episode is over, for either reason.
    pub fn done(&self) -> bool {
        self.terminated || self.truncated
    }

    /// The rule every goal task here shares: reward 1 and termination on
    /// reaching the goal, cost 1 for a step in a hazard, truncation at the
    /// time limit only when the goal did not end the episode on this step.
    pub fn goal_task(at_goal: bool, in_hazard: bool, elapsed: usize, time_limit: usize) -> Self {
        StepOutcome {
            reward: if at_goal { 1.0 } else { 0.0 },
            cost: if in_hazard { 1.0 } else { 0.0 },
            terminated: at_goal,
            truncated: !at_goal && elapsed >= time_limit,
        }
    }
}

/// A constrained MDP with a goal, hazards and a time limit.
pub trait CmdpEnv: Send {
    /// Observation space (always a `Space::Box`).
    fn observation_space(&self) -> Space;
    /// Action space.
    fn action_space(&self) -> Space;
    /// Time limit in agent steps.
    fn max_episode_steps(&self) -> usize;
    /// Places the goal and hazards for the following episodes.
    fn set_task(&mut self, task: &Task) -> Result<(), EnvError>;
    /// The task currently set.
    fn task(&self) -> &Task;
    /// Starts a new episode in the current task and writes the first observation
    /// into `obs` (length `observation_space().flat_dim()`). `seed` drives any
    /// per-episode randomness, so equal seeds give bitwise-equal episodes.
    fn reset(&mut self, seed: u64, obs: &mut [f32]) -> Result<(), EnvError>;
    /// Applies one agent action and writes the next observation into `obs`.
    /// Stepping after the episode ended is an error; call `reset` first.
    fn step(&mut self, action: Action<'_>, obs: &mut [f32]) -> Result<StepOutcome, EnvError>;
    /// Agent steps taken in the current episode.
    fn elapsed_steps(&self) -> usize;
    /// MuJoCo physics steps per agent action (the macro action), for
    /// environments simulated in MuJoCo; `None` for those without physics
    /// (SafeDarkRoom). Checkpoints and datasets record it.
    fn physics_steps_per_action(&self) -> Option<usize> {
        None
    }
    /// Where the goal counts as reached, in observation terms.
    fn goal_rule(&self) -> GoalRule;
    /// The current task's goal in observation terms (at [`GoalRule::xy`]):
    /// for pretraining-only signals such as a dense critic reward, never
    /// for the agent's input.
    fn goal_position(&self) -> [f32; 2];
    /// A scripted controller's action towards the goal, which it **knows**
    /// (the agent never does): the debugging ladder's "return to a shown
    /// goal" rung drives a trajectory's first episode with it. `None` where
    /// the environment has no such controller.
    fn goal_seeking_action(&self) -> Option<Vec<f32>> {
        None
    }
}
