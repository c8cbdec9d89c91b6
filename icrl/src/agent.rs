//! The interface every pretrained in-context agent offers to evaluation and
//! data collection: B trajectories advanced in lockstep, one time step per call,
//! with parameters frozen and the context carried across episodes.

use safety_envs::StepOutcome;
use safety_envs::vec_env::VecEnv;
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

/// The buffers a [`StepInput`] borrows, owned and refilled after every step
/// of B environments: what training's collection and evaluation both keep.
pub struct NextInput {
    obs_dim: usize,
    act_dim: usize,
    pub obs: Vec<f32>,
    pub arrived: Vec<f32>,
    pub prev_action: Vec<f32>,
    pub reward: Vec<f32>,
    pub cost: Vec<f32>,
    pub start: Vec<bool>,
}

impl NextInput {
    /// A trajectory's first step: the observations after the reset
    /// (obs_dim per row), nothing taken or received yet.
    pub fn first(obs: Vec<f32>, obs_dim: usize, act_dim: usize) -> Self {
        let b = obs.len() / obs_dim;
        NextInput {
            obs_dim,
            act_dim,
            obs,
            arrived: vec![0.0; b * obs_dim],
            prev_action: vec![0.0; b * act_dim],
            reward: vec![0.0; b],
            cost: vec![0.0; b],
            start: vec![true; b],
        }
    }

    pub fn input(&self) -> StepInput<'_> {
        StepInput {
            obs: &self.obs,
            arrived_obs: &self.arrived,
            prev_action: &self.prev_action,
            reward: &self.reward,
            cost: &self.cost,
            episode_start: &self.start,
        }
    }

    /// Row `i`'s action and where it led, from its `outcome`: the reward,
    /// the cost, whether an episode starts, and the observation arrived at,
    /// `venv`'s final one where the episode ended (the auto-reset already
    /// replaced its current one). `action` is the row the network saw (one-hot
    /// for a discrete action). The next observations are the caller's to copy.
    pub fn take_outcome(&mut self, i: usize, outcome: &StepOutcome, action: &[f32], venv: &VecEnv) {
        let (od, a) = (self.obs_dim, self.act_dim);
        self.prev_action[i * a..(i + 1) * a].copy_from_slice(action);
        self.reward[i] = outcome.reward;
        self.cost[i] = outcome.cost;
        self.start[i] = outcome.done();
        let reached = if outcome.done() {
            venv.final_observations()
        } else {
            venv.observations()
        };
        self.arrived[i * od..(i + 1) * od].copy_from_slice(&reached[i * od..(i + 1) * od]);
    }

    /// Row `i`'s arrived observation.
    pub fn arrived_row(&mut self, i: usize) -> &mut [f32] {
        &mut self.arrived[i * self.obs_dim..(i + 1) * self.obs_dim]
    }
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
