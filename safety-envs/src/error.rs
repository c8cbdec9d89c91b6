//! Error types of the safe MuJoCo wrapper and of the environments.

use thiserror::Error;

/// An error from MuJoCo: a model that does not compile, or an engine error
/// (`mju_error`) caught by the process-wide hook instead of exiting.
#[derive(Debug, Error)]
pub enum MujocoError {
    /// The MJCF did not compile; `message` is MuJoCo's own text.
    #[error("cannot load MuJoCo model {source_name}: {message}")]
    Load {
        source_name: String,
        message: String,
    },
    /// MuJoCo raised a fatal error during a call; the data must be reset.
    #[error("MuJoCo engine error: {0}")]
    Engine(String),
    /// Any other failure of the wrapper (bad name, size mismatch, ...).
    #[error("{0}")]
    Invalid(String),
}

/// An error from an environment.
#[derive(Debug, Error)]
pub enum EnvError {
    #[error(transparent)]
    Mujoco(#[from] MujocoError),
    /// An action that cannot be applied (NaN, wrong length, out of range).
    #[error("invalid action: {0}")]
    InvalidAction(String),
    /// A configuration that cannot be satisfied.
    #[error("invalid environment config: {0}")]
    InvalidConfig(String),
    /// A call in the wrong state, e.g. `step` after the episode ended.
    #[error("{0}")]
    State(String),
    /// MuJoCo found a NaN or huge value and reset the simulation state (or
    /// zeroed the controls) during a step; the episode is over, call `reset`.
    #[error("simulation became unstable: {0}")]
    Unstable(String),
    /// An error from environment `index` of a `VecEnv`.
    #[error("environment {index}: {source}")]
    InEnv { index: usize, source: Box<EnvError> },
}
