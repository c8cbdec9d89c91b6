//! Constrained navigation environments over a safe MuJoCo wrapper.
//!
//! - [`mujoco`]: safe `Model`, `Data`, engine-error hook, warnings, off-screen renderer.
//! - [`env`]: the one CMDP interface ([`CmdpEnv`]).
//! - [`spawn`]: centre- and edge-oriented task sampling.
//! - [`darkroom`]: SafeDarkRoom, the 9x9 grid world.

pub mod darkroom;
pub mod env;
pub mod error;
pub mod mujoco;
pub mod spawn;

pub use darkroom::{DarkRoomConfig, SafeDarkRoom};
pub use env::{Action, CmdpEnv, Space, StepOutcome};
pub use error::{EnvError, MujocoError};
pub use spawn::{Cell, Distance, Orientation, SpawnConfig, Task, sample_task};

/// The names most users need, in one import.
pub mod prelude {
    pub use crate::darkroom::{DarkRoomConfig, SafeDarkRoom};
    pub use crate::env::{Action, CmdpEnv, Space, StepOutcome};
    pub use crate::error::{EnvError, MujocoError};
    pub use crate::spawn::{Cell, Distance, Orientation, SpawnConfig, Task, sample_task};
}
