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
            Ok(Box::new(crate::nav::SafeDarkMujoco::new(config)?))
        }
    }
}
