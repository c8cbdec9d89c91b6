//! The interface every pretrained in-context agent offers to evaluation and
//! data collection: B trajectories advanced in lockstep, one time step per call,
//! with parameters frozen and the context carried across episodes.

use thiserror::Error;

/// What the agent is asked to achieve in one trajectory.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Conditioning {
    /// EPPO: the per-episode cost budget (CTG restarts at it each episode and
    /// decreases by the costs received).
    Budget { ctg: f32 },
    /// Supervised pretraining: return-to-go and cost-to-go targets at each
    /// episode start (both decrease by what is received inside the episode).
    Targets { rtg: f32, ctg: f32 },
}

/// One time step of B trajectories, flat row-major buffers.
#[derive(Clone, Copy, Debug)]
pub struct StepInput<'a> {
    /// Current observations, (B, obs_dim).
    pub obs: &'a [f32],
    /// The observation `prev_action` led to, (B, obs_dim): where `reward` and
    /// `cost` were received. It equals `obs` inside an episode; at an episode
    /// start it is the previous episode's final observation (at the goal, say),
    /// which the auto-reset replaced in `obs`; zeros at the trajectory's first step.
    pub arrived_obs: &'a [f32],
    /// The action taken just before, (B, action_dim); a one-hot row for discrete
    /// actions; zeros at the first step of the trajectory.
    pub prev_action: &'a [f32],
    /// Reward and cost received for `prev_action`, (B,); zero at the first step.
    pub reward: &'a [f32],
    pub cost: &'a [f32],
    /// True where this step is the first of an episode, (B,).
    pub episode_start: &'a [bool],
}

/// Actions for B trajectories.
#[derive(Clone, Debug, PartialEq)]
pub enum Actions {
    /// One index per trajectory.
    Discrete(Vec<usize>),
    /// (B, action_dim), row-major.
    Continuous(Vec<f32>),
}

/// An error from an agent (bad input sizes, libtorch failure, bad checkpoint).
#[derive(Debug, Error)]
pub enum AgentError {
    #[error("agent input: {0}")]
    Input(String),
    #[error(transparent)]
    Torch(#[from] tch::TchError),
}

/// A pretrained agent acting in context with frozen parameters.
pub trait InContextAgent {
    /// Starts `conditioning.len()` fresh trajectories: clears the context (KV cache).
    fn reset(&mut self, conditioning: &[Conditioning]) -> Result<(), AgentError>;
    /// Consumes one time step per trajectory and returns the next actions.
    /// `greedy` picks the mode of the policy instead of sampling.
    fn act(&mut self, input: &StepInput<'_>, greedy: bool) -> Result<Actions, AgentError>;
}
