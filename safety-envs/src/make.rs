//! Environments by name, with the task distribution that goes with each.

use std::fmt;
use std::str::FromStr;

use crate::EnvError;
use crate::darkroom::{DarkRoomConfig, SafeDarkRoom};
use crate::env::CmdpEnv;
use crate::spawn::SpawnConfig;

/// The environments this crate provides.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum EnvName {
    /// SafeDarkRoom, `darkroom`.
    DarkRoom,
    /// SafeDarkMujoco Point, `point`.
    Point,
    /// SafeDarkMujoco Car, `car`.
    Car,
}

impl EnvName {
    /// Every environment, in display order.
    pub const ALL: [EnvName; 3] = [EnvName::DarkRoom, EnvName::Point, EnvName::Car];

    /// The name accepted by `FromStr` and printed by `Display`.
    pub fn as_str(self) -> &'static str {
        match self {
            EnvName::DarkRoom => "darkroom",
            EnvName::Point => "point",
            EnvName::Car => "car",
        }
    }
}

impl EnvName {
    /// The macro action `make_env(self, ..)` uses when asked for `asked`
    /// physics steps per agent action: Point and Car `asked`, else
    /// [`crate::nav::PHYSICS_STEPS_PER_ACTION`] (50); SafeDarkRoom has no
    /// physics, `None` (and `make_env` refuses a value for it). Checkpoints
    /// and datasets record this resolved value.
    pub fn physics_steps_per_action(self, asked: Option<usize>) -> Option<usize> {
        match self {
            EnvName::DarkRoom => None,
            EnvName::Point | EnvName::Car => {
                Some(asked.unwrap_or(crate::nav::PHYSICS_STEPS_PER_ACTION))
            }
        }
    }
}

impl fmt::Display for EnvName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for EnvName {
    type Err = EnvError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let lower = s.to_ascii_lowercase();
        EnvName::ALL
            .into_iter()
            .find(|n| n.as_str() == lower)
            .ok_or_else(|| {
                EnvError::InvalidConfig(format!(
                    "unknown environment '{s}'; valid names: darkroom, point, car"
                ))
            })
    }
}

/// Options shared by every environment; `None` keeps the environment default.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EnvOptions {
    /// Time limit in agent steps (defaults: darkroom 30, point/car 75).
    pub max_episode_steps: Option<usize>,
    /// Point and Car: MuJoCo physics steps per agent action (the macro
    /// action), default [`crate::nav::PHYSICS_STEPS_PER_ACTION`] = 5
    /// Safety-Gymnasium steps x 10 physics steps = 50. SafeDarkRoom has no
    /// physics: setting it there is an error.
    pub physics_steps_per_action: Option<usize>,
}

/// The task distribution (grid and obstacle count) of `name`, with alpha 0.5
/// and Euclidean distance; learners sample tasks from it with
/// [`crate::spawn::sample_task`].
pub fn spawn_config(name: EnvName) -> SpawnConfig {
    match name {
        EnvName::DarkRoom => DarkRoomConfig::default().spawn_config(),
        EnvName::Point | EnvName::Car => crate::nav::NavConfig::default().spawn_config(),
    }
}

/// Builds environment `name`.
pub fn make_env(name: EnvName, options: &EnvOptions) -> Result<Box<dyn CmdpEnv>, EnvError> {
    match name {
        EnvName::DarkRoom => {
            if let Some(n) = options.physics_steps_per_action {
                return Err(EnvError::InvalidConfig(format!(
                    "physics_steps_per_action = {n} was given, but darkroom has no physics \
                     (the option is for point and car)"
                )));
            }
            let mut config = DarkRoomConfig::default();
            if let Some(t) = options.max_episode_steps {
                config.max_episode_steps = t;
            }
            Ok(Box::new(SafeDarkRoom::new(config)?))
        }
        EnvName::Point | EnvName::Car => {
            let robot = if name == EnvName::Point {
                crate::nav::Robot::Point
            } else {
                crate::nav::Robot::Car
            };
            let mut config = crate::nav::NavConfig::new(robot);
            if let Some(t) = options.max_episode_steps {
                config.max_episode_steps = t;
            }
            if let Some(n) = options.physics_steps_per_action {
                config.physics_steps_per_action = n;
            }
            Ok(Box::new(crate::nav::SafeDarkMujoco::new(config)?))
        }
    }
}
