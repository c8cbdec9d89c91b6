//! Constrained navigation environments over a safe MuJoCo wrapper.
//!
//! - [`mujoco`]: safe `Model`, `Data`, engine-error hook, warnings, off-screen renderer.
//! - [`env`](mod@env): the one CMDP interface ([`CmdpEnv`]).
//! - [`spawn`]: centre- and edge-oriented task sampling.
//! - [`darkroom`]: SafeDarkRoom, the 9x9 grid world.
//! - [`nav`]: SafeDarkMujoco Point and Car, the MuJoCo goal tasks.
//! - [`make`]: environments by name ([`EnvName`], [`make_env`]).
//! - [`goal_shown`]: the goal appended to the observation, for the debugging
//!   ladder and Car's goal shown, then hidden.
//! - [`vec_env`]: [`VecEnv`], many environments stepped across threads.
//! - [`output`]: output files written atomically, never over what is not
//!   ours, and the run and output locks.

pub mod darkroom;
pub mod env;
pub mod error;
pub mod goal_shown;
pub mod make;
pub mod mujoco;
pub mod nav;
pub mod output;
pub mod spawn;
pub mod vec_env;

pub use darkroom::{DarkRoomConfig, SafeDarkRoom};
pub use env::{Action, CmdpEnv, GoalRule, Space, StepOutcome};
pub use error::{EnvError, MujocoError};
pub use goal_shown::GoalShown;
pub use make::{EnvName, EnvOptions, make_env, spawn_config};
pub use nav::{
    NavConfig, OLD_PHYSICS_STEPS_PER_ACTION, PHYSICS_STEPS_PER_ACTION, PHYSICS_STEPS_PER_SG_STEP,
    Robot, SG_STEPS_PER_ACTION, SafeDarkMujoco,
};
pub use spawn::{Cell, Distance, Orientation, SpawnConfig, Task, sample_task};
pub use vec_env::{VecAction, VecEnv};

/// The names most users need, in one import.
pub mod prelude {
    pub use crate::darkroom::{DarkRoomConfig, SafeDarkRoom};
    pub use crate::env::{Action, CmdpEnv, GoalRule, Space, StepOutcome};
    pub use crate::error::{EnvError, MujocoError};
    pub use crate::make::{EnvName, EnvOptions, make_env, spawn_config};
    pub use crate::nav::{NavConfig, PHYSICS_STEPS_PER_ACTION, Robot, SafeDarkMujoco};
    pub use crate::spawn::{Cell, Distance, Orientation, SpawnConfig, Task, sample_task};
    pub use crate::vec_env::{VecAction, VecEnv};
}
