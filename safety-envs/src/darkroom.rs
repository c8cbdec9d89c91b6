//! SafeDarkRoom: a dark grid world with a goal and obstacles (SPEC section 2).
//!
//! - Grid `grid_size x grid_size` (default 9x9), `n_obstacles` obstacles
//!   (default 25), one goal; the agent starts at the centre cell.
//! - Actions (discrete, 5): `0` stay, `1` up (row - 1), `2` down (row + 1),
//!   `3` left (col - 1), `4` right (col + 1). A move into the wall leaves the
//!   agent in place.
//! - Observation: the agent's own cell only, as two `f32`: `[row, col]`, the
//!   raw indices in `0..grid_size` (no normalisation; the observation space's
//!   bounds are `[0, grid_size - 1]`). The agent sees neither goal nor obstacles.
//! - Reward 1 on reaching the goal, which terminates the episode.
//! - Cost 1 for every step that *ends* on an obstacle cell.
//! - Truncated at the time limit (default 30 steps) unless terminated first.
//!
//! [`draw_darkroom`] draws it from above (it has no MuJoCo model to render).
//!
//! `step` allocates nothing: the obstacles are kept as a flat `Vec<bool>`
//! built once per [`CmdpEnv::set_task`].

use crate::EnvError;
use crate::env::{Action, CmdpEnv, GoalRule, Space, StepOutcome};
use crate::mujoco::RgbImage;
use crate::spawn::{Cell, Orientation, SpawnConfig, Task, sample_task};

/// Number of discrete actions: stay, up, down, left, right.
pub const DARKROOM_ACTIONS: usize = 5;

/// SafeDarkRoom's configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct DarkRoomConfig {
    /// Cells per side.
    pub grid_size: usize,
    /// Obstacles per task.
    pub n_obstacles: usize,
    /// Time limit in steps.
    pub max_episode_steps: usize,
}

impl Default for DarkRoomConfig {
    fn default() -> Self {
        DarkRoomConfig {
            grid_size: 9,
            n_obstacles: 25,
            max_episode_steps: 30,
        }
    }
}

impl DarkRoomConfig {
    /// The task distribution that matches this grid (alpha 0.5, Euclidean).
    pub fn spawn_config(&self) -> SpawnConfig {
        SpawnConfig {
            grid_size: self.grid_size,
            n_obstacles: self.n_obstacles,
            ..SpawnConfig::darkroom()
        }
    }
}

/// SafeDarkRoom. See the module documentation.
#[derive(Clone, Debug)]
pub struct SafeDarkRoom {
    config: DarkRoomConfig,
    task: Task,
    /// `is_obstacle[row * grid_size + col]`.
    is_obstacle: Vec<bool>,
    row: usize,
    col: usize,
    elapsed: usize,
    /// The current episode ended (terminated or truncated).
    done: bool,
}

impl SafeDarkRoom {
    /// Builds the environment with a first task (centre-oriented, seed 0); call
    /// [`CmdpEnv::set_task`] for another and [`CmdpEnv::reset`] before stepping.
    pub fn new(config: DarkRoomConfig) -> Result<Self, EnvError> {
        if config.max_episode_steps == 0 {
            return Err(EnvError::InvalidConfig(
                "max_episode_steps must be at least 1".into(),
            ));
        }
        let task = sample_task(&config.spawn_config(), Orientation::Centre, 0)?;
        let g = config.grid_size;
        let mut env = SafeDarkRoom {
            is_obstacle: vec![false; g * g],
            row: g / 2,
            col: g / 2,
            elapsed: 0,
            // No episode until the first reset.
            done: true,
            task,
            config,
        };
        let task = env.task.clone();
        env.set_task(&task)?;
        Ok(env)
    }

    /// The configuration.
    pub fn config(&self) -> &DarkRoomConfig {
        &self.config
    }

    /// The agent's current cell.
    pub fn position(&self) -> Cell {
        Cell {
            row: self.row,
            col: self.col,
        }
    }

    fn check_obs(&self, obs: &[f32]) -> Result<(), EnvError> {
        if obs.len() != 2 {
            return Err(EnvError::State(format!(
                "observation buffer has length {}, SafeDarkRoom writes 2",
                obs.len()
            )));
        }
        Ok(())
    }

    #[inline]
    fn write_obs(&self, obs: &mut [f32]) {
        obs[0] = self.row as f32;
        obs[1] = self.col as f32;
    }
}

impl CmdpEnv for SafeDarkRoom {
    fn observation_space(&self) -> Space {
        let hi = (self.config.grid_size - 1) as f32;
        Space::Box {
            low: vec![0.0, 0.0],
            high: vec![hi, hi],
        }
    }

    fn action_space(&self) -> Space {
        Space::Discrete {
            n: DARKROOM_ACTIONS,
        }
    }

    fn max_episode_steps(&self) -> usize {
        self.config.max_episode_steps
    }

    fn set_task(&mut self, task: &Task) -> Result<(), EnvError> {
        task.validate(self.config.grid_size, self.config.n_obstacles)?;
        let g = self.config.grid_size;
        self.is_obstacle.iter_mut().for_each(|o| *o = false);
        for o in &task.obstacles {
            self.is_obstacle[o.row * g + o.col] = true;
        }
        self.task.clone_from(task);
        // A new task invalidates the running episode.
        self.done = true;
        Ok(())
    }

    fn task(&self) -> &Task {
        &self.task
    }

    fn reset(&mut self, _seed: u64, obs: &mut [f32]) -> Result<(), EnvError> {
        // The start is always the centre: no per-episode randomness.
        self.check_obs(obs)?;
        let g = self.config.grid_size;
        self.row = g / 2;
        self.col = g / 2;
        self.elapsed = 0;
        self.done = false;
        self.write_obs(obs);
        Ok(())
    }

    #[inline]
    fn step(&mut self, action: Action<'_>, obs: &mut [f32]) -> Result<StepOutcome, EnvError> {
        if self.done {
            return Err(EnvError::State(
                "step called after the episode ended (or before the first reset); call reset"
                    .into(),
            ));
        }
        self.check_obs(obs)?;
        let a = match action {
            Action::Discrete(a) if a < DARKROOM_ACTIONS => a,
            Action::Discrete(a) => {
                return Err(EnvError::InvalidAction(format!(
                    "SafeDarkRoom action {a} is out of range 0..{DARKROOM_ACTIONS}"
                )));
            }
            Action::Continuous(_) => {
                return Err(EnvError::InvalidAction(
                    "SafeDarkRoom takes a discrete action (0..5), got a continuous one".into(),
                ));
            }
        };
        let last = self.config.grid_size - 1;
        match a {
            1 => self.row = self.row.saturating_sub(1),
            2 => self.row = (self.row + 1).min(last),
            3 => self.col = self.col.saturating_sub(1),
            4 => self.col = (self.col + 1).min(last),
            _ => {} // 0: stay
        }
        self.elapsed += 1;
        let at_goal = self.row == self.task.goal.row && self.col == self.task.goal.col;
        let on_obstacle = self.is_obstacle[self.row * self.config.grid_size + self.col];
        let outcome = StepOutcome::goal_task(
            at_goal,
            on_obstacle,
            self.elapsed,
            self.config.max_episode_steps,
        );
        self.done = outcome.done();
        self.write_obs(obs);
        Ok(outcome)
    }

    fn goal_rule(&self) -> GoalRule {
        // (row, col) as floats: the goal is one cell, any other than the start.
        GoalRule {
            xy: [0, 1],
            radius: 0.0,
            min_start_distance: 1.0,
        }
    }

    fn goal_position(&self) -> [f32; 2] {
        [self.task.goal.row as f32, self.task.goal.col as f32]
    }

    fn elapsed_steps(&self) -> usize {
        self.elapsed
    }
}

/// Pictures of SafeDarkRoom are drawn by hand (it has no MuJoCo model for the
/// off-screen renderer), by the `render` binary and the Python package alike.
/// Colours shared by the MuJoCo arena (`assets/xml/arena.xml`) and the grid.
pub const GOAL_RGB: [u8; 3] = [26, 204, 51];
pub const HAZARD_RGB: [u8; 3] = [64, 89, 255];
pub const ROBOT_RGB: [u8; 3] = [189, 11, 47];
pub const FLOOR_RGB: [u8; 3] = [232, 232, 228];
pub const LINE_RGB: [u8; 3] = [170, 170, 165];
pub const TRAIL_RGB: [u8; 3] = [240, 160, 170];

/// Draws SafeDarkRoom from above: floor cells, obstacles blue, goal green,
/// the start cell outlined, the cells visited in `trail` pink, the agent a red
/// disc. Row 0 is the top of the image, as in the observation.
pub fn draw_darkroom(
    env: &SafeDarkRoom,
    trail: &[Cell],
    (width, height): (usize, usize),
) -> RgbImage {
    let task = env.task();
    let g = task.grid_size;
    let cell = (width.min(height) / g).max(3);
    // A picture smaller than the grid at 3 pixels a cell shows its top-left part.
    let (x0, y0) = (
        width.saturating_sub(cell * g) / 2,
        height.saturating_sub(cell * g) / 2,
    );
    let mut pixels = vec![255u8; width * height * 3];
    let mut put = |x: usize, y: usize, rgb: [u8; 3]| {
        if x < width && y < height {
            let i = 3 * (y * width + x);
            pixels[i..i + 3].copy_from_slice(&rgb);
        }
    };
    let centre = Cell::centre(g);
    for row in 0..g {
        for col in 0..g {
            let c = Cell { row, col };
            let fill = if c == task.goal {
                GOAL_RGB
            } else if task.obstacles.contains(&c) {
                HAZARD_RGB
            } else if trail.contains(&c) {
                TRAIL_RGB
            } else {
                FLOOR_RGB
            };
            for dy in 0..cell {
                for dx in 0..cell {
                    let border = dx == 0 || dy == 0 || dx == cell - 1 || dy == cell - 1;
                    let start_ring =
                        c == centre && (dx < 3 || dy < 3 || dx >= cell - 3 || dy >= cell - 3);
                    let rgb = if start_ring {
                        ROBOT_RGB
                    } else if border {
                        LINE_RGB
                    } else {
                        fill
                    };
                    put(x0 + col * cell + dx, y0 + row * cell + dy, rgb);
                }
            }
        }
    }
    // The agent: a disc in its cell.
    let p = env.position();
    let (cx, cy) = (x0 + p.col * cell + cell / 2, y0 + p.row * cell + cell / 2);
    let r = (cell as f64 * 0.32) as i64;
    for dy in -r..=r {
        for dx in -r..=r {
            if dx * dx + dy * dy <= r * r {
                put(
                    (cx as i64 + dx) as usize,
                    (cy as i64 + dy) as usize,
                    ROBOT_RGB,
                );
            }
        }
    }
    RgbImage {
        width,
        height,
        pixels,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env_with(goal: Cell, obstacles: Vec<Cell>) -> SafeDarkRoom {
        let config = DarkRoomConfig {
            grid_size: 5,
            n_obstacles: obstacles.len(),
            max_episode_steps: 4,
        };
        let mut env = SafeDarkRoom::new(config).unwrap();
        env.set_task(&Task {
            grid_size: 5,
            goal,
            obstacles,
        })
        .unwrap();
        env
    }

    #[test]
    fn moves_walls_and_obs() {
        let mut env = env_with(Cell { row: 0, col: 0 }, vec![]);
        let mut obs = [0.0; 2];
        env.reset(0, &mut obs).unwrap();
        assert_eq!(obs, [2.0, 2.0]);
        env.step(Action::Discrete(4), &mut obs).unwrap();
        assert_eq!(obs, [2.0, 3.0]);
        env.step(Action::Discrete(4), &mut obs).unwrap();
        env.step(Action::Discrete(4), &mut obs).unwrap(); // wall
        assert_eq!(obs, [2.0, 4.0]);
        let out = env.step(Action::Discrete(2), &mut obs).unwrap();
        assert_eq!(obs, [3.0, 4.0]);
        assert!(out.truncated && !out.terminated);
        assert!(matches!(
            env.step(Action::Discrete(0), &mut obs),
            Err(EnvError::State(_))
        ));
    }

    #[test]
    fn draws_goal_hazards_and_agent_at_any_size() {
        let mut env = SafeDarkRoom::new(DarkRoomConfig::default()).unwrap();
        env.reset(0, &mut [0.0; 2]).unwrap();
        let img = draw_darkroom(&env, &[], (90, 90));
        assert_eq!(img.pixels.len(), 90 * 90 * 3);
        let has = |rgb: [u8; 3]| img.pixels.chunks(3).any(|p| p == rgb);
        assert!(has(GOAL_RGB) && has(HAZARD_RGB) && has(ROBOT_RGB));
        // Smaller than 3 pixels a cell: cropped, not a panic.
        let tiny = draw_darkroom(&env, &[], (5, 4));
        assert_eq!(tiny.pixels.len(), 5 * 4 * 3);
    }
}
