//! What the `eval` command can fail with.

use safety_envs::EnvError;
use thiserror::Error;

use super::EvalError;
use crate::agent::AgentError;
use crate::plots::PlotError;

/// An `eval` command that failed.
#[derive(Debug, Error)]
pub enum EvalCmdError {
    #[error(transparent)]
    Eval(#[from] EvalError),
    #[error(transparent)]
    Plot(#[from] PlotError),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Agent(#[from] AgentError),
    /// A checkpoint that cannot be evaluated here (other environment, shape).
    #[error("checkpoint {path}: {message}")]
    Checkpoint { path: String, message: String },
    #[error("invalid eval options: {0}")]
    Options(String),
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    /// An output path that is not ours to write.
    #[error(transparent)]
    Output(#[from] safety_envs::output::OutputError),
    #[error("{path}: {source}")]
    Json {
        path: String,
        source: serde_json::Error,
    },
}
