//! SafeDarkMujoco: the Point and Car goal tasks with all lidar off (SPEC
//! sections 2 and 6).
//!
//! - The model (robot + arena, `assets`) is compiled once per environment;
//!   [`CmdpEnv::set_task`] writes the goal and hazard positions into the
//!   compiled model (`site_pos`) and [`CmdpEnv::reset`] resets the data: no
//!   recompilation, ever.
//! - Task grid: `grid_size x grid_size` cells (default 5x5) laid over the
//!   placement extents `[-1.5, 1.5]`, cell `(row, col)` at
//!   `x = -1.5 + col * s`, `y = 1.5 - row * s` with spacing `s = 3 / (g - 1)`
//!   (row 0 is the top, `+y`, edge of a top-down picture), the robot starting
//!   at the centre cell `(0, 0)`. **Why 5x5:** the grid must have a centre cell
//!   (odd size), and its spacing must respect Safety-Gymnasium's keep-outs
//!   between any two objects placed on neighbouring cells. The largest pair is
//!   agent 0.4 + goal 0.305 = 0.705 (then agent + hazard 0.58, goal + hazard
//!   0.485, hazard + hazard 0.36). A 7x7 grid has spacing 0.5 < 0.705 (a goal
//!   or hazard next to the start would sit inside the agent's keep-out); 5x5
//!   has 0.75 >= 0.705, so every keep-out holds, hazards (radius 0.2) and the
//!   goal (radius 0.3) never overlap, and 0.35 m of free floor separates two
//!   neighbouring hazards. 8 hazards (level 1) on the 23 free cells is a 35 %
//!   density, close to SafeDarkRoom's 25 of 79 (32 %).
//! - Actions: continuous, in `[-1, 1]` per actuator (Point: thrust along the
//!   heading, turn rate; Car: left and right wheel torque). NaN, infinity or a
//!   wrong length is an error; finite values outside `[-1, 1]` are **clamped**
//!   to it (MuJoCo's `ctrlrange` would do the same).
//! - **Macro action:** each agent action is held for
//!   [`NavConfig::physics_steps_per_action`] MuJoCo physics steps, default
//!   [`PHYSICS_STEPS_PER_ACTION`] = 50: the paper repeats an action for
//!   [`SG_STEPS_PER_ACTION`] = 5 Safety-Gymnasium environment steps, and each
//!   of those is [`PHYSICS_STEPS_PER_SG_STEP`] = 10 physics steps
//!   (`frameskip_binom_n`). One agent step is therefore 0.1 s of simulated
//!   time for Point (timestep 0.002) and 0.2 s for Car (0.004), and the
//!   75-step time limit 7.5 s / 15 s. (Until 2026-11-30 the default was 5
//!   physics steps, a misreading that left Point about 0.5 m of travel per
//!   episode; [`OLD_PHYSICS_STEPS_PER_ACTION`] names it so that files written
//!   under it can be recognised and refused.)
//! - Reward 1 when the robot's xy position is within the goal radius (0.3) at
//!   the end of an agent step; that terminates the episode.
//! - Cost 1 for an agent step if the robot's xy position was inside any hazard
//!   (radius 0.2) after any of its physics sub-steps.
//! - Truncated after `max_episode_steps` agent steps (default 75).
//! - A MuJoCo warning that means the state was reset (NaN or huge qpos, qvel,
//!   qacc, ctrl) makes `step` return [`EnvError::Unstable`] and ends the
//!   episode, rather than hand back a silently reset state.
//!
//! Observation (Point 23 floats, Car 35), all from the robot's own state:
//!
//! | index | content |
//! |---|---|
//! | 0..2 | position x, y (m) |
//! | 2..11 | body orientation, 3x3 rotation matrix, row-major (body to world) |
//! | 11..14 | accelerometer (body frame, includes gravity) |
//! | 14..17 | velocimeter (body frame) |
//! | 17..20 | gyro (body frame) |
//! | 20..23 | magnetometer (body frame; field (0, -0.5, 0)) |
//! | 23..26 | Car only: rear caster ball angular velocity |
//! | 26..35 | Car only: rear caster ball orientation, 3x3 rotation matrix |
//!
//! Position and rotation are read from `qpos` after the last physics step;
//! the sensors are MuJoCo's `sensordata`, which `mj_step` computes at the start
//! of its step (one physics step, 2 or 4 ms, behind), as in Gymnasium's MuJoCo
//! environments.

use std::fmt;
use std::str::FromStr;

use crate::EnvError;
use crate::env::{Action, CmdpEnv, GoalRule, Space, StepOutcome};
use crate::mujoco::{Camera, Data, Model, ObjType, RenderError, Renderer, RgbImage};
use crate::spawn::{Cell, Orientation, SpawnConfig, Task, sample_task};

pub use assets::MAX_HAZARDS;

/// Where unused hazards and, before the first task, the goal are parked:
/// under the floor, far from any robot.
const PARKED: [f64; 3] = [0.0, 0.0, -10.0];

/// Height of the goal and hazard discs' centres above the floor.
const MARKER_Z: f64 = 0.01;

/// Safety-Gymnasium environment steps per agent action: the paper's macro
/// action (Appendix C: "a policy action is repeated over five internal
/// simulation steps, reducing the default 250 simulation steps to 250/n";
/// Safety-Gymnasium's 250-step episode limit counts its environment steps,
/// each of them [`PHYSICS_STEPS_PER_SG_STEP`] physics steps).
pub const SG_STEPS_PER_ACTION: usize = 5;

/// MuJoCo physics steps per Safety-Gymnasium environment step
/// (Safety-Gymnasium's `frameskip_binom_n = 10`).
pub const PHYSICS_STEPS_PER_SG_STEP: usize = 10;

/// MuJoCo physics steps per agent action by default:
/// [`SG_STEPS_PER_ACTION`] x [`PHYSICS_STEPS_PER_SG_STEP`] = 50.
pub const PHYSICS_STEPS_PER_ACTION: usize = SG_STEPS_PER_ACTION * PHYSICS_STEPS_PER_SG_STEP;

/// The longest macro action accepted: 200 times the default, 20 s of Point's
/// and 40 s of Car's simulated time per agent action. Beyond it an episode
/// runs for hours of wall time with nothing to learn from.
pub const MAX_PHYSICS_STEPS_PER_ACTION: usize = 200 * PHYSICS_STEPS_PER_ACTION;

/// The default before 2026-11-30 (5 physics steps per action, a misreading
/// of the paper's 5 environment steps). Checkpoints and datasets that do not
/// record their macro action were made under it; loaders refuse them.
pub const OLD_PHYSICS_STEPS_PER_ACTION: usize = 5;

/// The robot of a SafeDarkMujoco task.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Robot {
    Point,
    Car,
}

impl Robot {
    /// The robot in the goal arena, as MJCF.
    pub fn mjcf(self) -> String {
        match self {
            Robot::Point => assets::point_in_arena(),
            Robot::Car => assets::car_in_arena(),
        }
    }

    /// Observation length (see the module table).
    pub fn obs_dim(self) -> usize {
        match self {
            Robot::Point => 23,
            Robot::Car => 35,
        }
    }
}

impl fmt::Display for Robot {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Robot::Point => "point",
            Robot::Car => "car",
        })
    }
}

impl FromStr for Robot {
    type Err = EnvError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "point" => Ok(Robot::Point),
            "car" => Ok(Robot::Car),
            other => Err(EnvError::InvalidConfig(format!(
                "unknown robot '{other}'; valid: point, car"
            ))),
        }
    }
}

/// SafeDarkMujoco's configuration. Defaults follow SPEC sections 2 and 6.
#[derive(Clone, Debug, PartialEq)]
pub struct NavConfig {
    /// Point or Car.
    pub robot: Robot,
    /// Task grid cells per side (odd, so the start is a cell); see the module
    /// documentation for why 5.
    pub grid_size: usize,
    /// Hazards per task (level 1: 8), at most [`MAX_HAZARDS`].
    pub n_hazards: usize,
    /// Half-width of the placement extents: cells span `[-extent, extent]`.
    pub extent: f64,
    /// The goal is reached within this xy distance of its centre.
    pub goal_radius: f64,
    /// Cost is paid within this xy distance of a hazard's centre.
    pub hazard_radius: f64,
    /// MuJoCo physics steps per agent action (the macro action), default
    /// [`PHYSICS_STEPS_PER_ACTION`] = [`SG_STEPS_PER_ACTION`] (5
    /// Safety-Gymnasium steps) x [`PHYSICS_STEPS_PER_SG_STEP`] (10 physics
    /// steps each) = 50.
    pub physics_steps_per_action: usize,
    /// Time limit in agent steps.
    pub max_episode_steps: usize,
}

impl NavConfig {
    /// The defaults for `robot`.
    pub fn new(robot: Robot) -> Self {
        NavConfig {
            robot,
            grid_size: 5,
            n_hazards: 8,
            extent: 1.5,
            goal_radius: 0.3,
            hazard_radius: 0.2,
            physics_steps_per_action: PHYSICS_STEPS_PER_ACTION,
            max_episode_steps: 75,
        }
    }

    /// The task distribution over this grid (alpha 0.5, Euclidean distance in
    /// cell units).
    pub fn spawn_config(&self) -> SpawnConfig {
        SpawnConfig {
            grid_size: self.grid_size,
            n_obstacles: self.n_hazards,
            ..SpawnConfig::darkroom()
        }
    }

    /// Distance between neighbouring cell centres.
    pub fn spacing(&self) -> f64 {
        2.0 * self.extent / (self.grid_size - 1) as f64
    }

    /// World xy of the centre of `cell`.
    pub fn cell_xy(&self, cell: Cell) -> [f64; 2] {
        let s = self.spacing();
        [
            -self.extent + cell.col as f64 * s,
            self.extent - cell.row as f64 * s,
        ]
    }

    fn validate(&self) -> Result<(), EnvError> {
        let bad = |msg: String| Err(EnvError::InvalidConfig(msg));
        if self.grid_size < 3 || self.grid_size.is_multiple_of(2) {
            return bad(format!(
                "grid_size must be odd and at least 3 (the start is the centre cell), got {}",
                self.grid_size
            ));
        }
        if self.n_hazards > MAX_HAZARDS {
            return bad(format!(
                "{} hazards asked, the arena model holds at most {MAX_HAZARDS}",
                self.n_hazards
            ));
        }
        for (name, v) in [
            ("extent", self.extent),
            ("goal_radius", self.goal_radius),
            ("hazard_radius", self.hazard_radius),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!("{name} must be positive and finite, got {v}"));
            }
        }
        if self.physics_steps_per_action == 0 || self.max_episode_steps == 0 {
            return bad(format!(
                "physics_steps_per_action ({}) and max_episode_steps ({}) must be at least 1",
                self.physics_steps_per_action, self.max_episode_steps
            ));
        }
        if self.physics_steps_per_action > MAX_PHYSICS_STEPS_PER_ACTION {
            return bad(format!(
                "physics_steps_per_action = {}: at most {MAX_PHYSICS_STEPS_PER_ACTION} (200 times \
                 the paper's macro action of {PHYSICS_STEPS_PER_ACTION}; one action would hold \
                 for minutes of simulated time)",
                self.physics_steps_per_action
            ));
        }
        self.spawn_config().validate()
    }
}

impl Default for NavConfig {
    fn default() -> Self {
        NavConfig::new(Robot::Point)
    }
}

/// Where the robot's state lives in `qpos`, per robot.
#[derive(Clone, Copy, Debug)]
enum Pose {
    /// Slide x, slide y, hinge z (yaw) at these `qpos` addresses.
    Planar { x: usize, y: usize, yaw: usize },
    /// Free joint: position at `adr..adr + 3`, quaternion (w x y z) after it.
    Free { adr: usize },
}

/// Sensor slices of `sensordata` copied into the observation, in order, and
/// whether each is a quaternion to expand into a rotation matrix.
#[derive(Clone, Debug)]
struct SensorLayout {
    ranges: Vec<(std::ops::Range<usize>, bool)>,
}

/// SafeDarkMujoco Point or Car. See the module documentation.
pub struct SafeDarkMujoco {
    config: NavConfig,
    model: Model,
    data: Data,
    task: Task,
    goal_xy: [f64; 2],
    /// xy of the task's hazards (`n_hazards` entries).
    hazards_xy: Vec<[f64; 2]>,
    goal_site: usize,
    hazard_sites: Vec<usize>,
    pose: Pose,
    sensors: SensorLayout,
    elapsed: usize,
    done: bool,
}

impl fmt::Debug for SafeDarkMujoco {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SafeDarkMujoco")
            .field("config", &self.config)
            .field("task", &self.task)
            .field("elapsed", &self.elapsed)
            .finish()
    }
}

impl SafeDarkMujoco {
    /// Compiles the robot in the arena and sets a first task (centre-oriented,
    /// seed 0); call [`CmdpEnv::reset`] before stepping.
    pub fn new(config: NavConfig) -> Result<Self, EnvError> {
        config.validate()?;
        let model = Model::from_xml_str(&config.robot.mjcf())?;
        let data = Data::new(&model)?;
        let goal_site = model.id(ObjType::Site, "goal")?;
        let hazard_sites = (0..MAX_HAZARDS)
            .map(|i| model.id(ObjType::Site, &format!("hazard{i}")))
            .collect::<Result<Vec<_>, _>>()?;
        let joint_adr = |name: &str| -> Result<usize, EnvError> {
            let id = model.id(ObjType::Joint, name)?;
            // SAFETY: `id < njnt` (checked by `Model::id`); jnt_qposadr holds njnt ints.
            let adr = unsafe { *model.raw().jnt_qposadr.add(id) };
            Ok(adr as usize)
        };
        let pose = match config.robot {
            Robot::Point => Pose::Planar {
                x: joint_adr("x")?,
                y: joint_adr("y")?,
                yaw: joint_adr("z")?,
            },
            Robot::Car => Pose::Free {
                adr: joint_adr("robot")?,
            },
        };
        let mut names = vec!["accelerometer", "velocimeter", "gyro", "magnetometer"];
        if config.robot == Robot::Car {
            names.extend(["ball_angvel", "ball_quat"]);
        }
        let sensors = SensorLayout {
            ranges: names
                .iter()
                .map(|n| Ok((model.sensor_range(n)?, *n == "ball_quat")))
                .collect::<Result<Vec<_>, EnvError>>()?,
        };
        let task = sample_task(&config.spawn_config(), Orientation::Centre, 0)?;
        let mut env = SafeDarkMujoco {
            hazards_xy: Vec::with_capacity(MAX_HAZARDS),
            goal_xy: [0.0; 2],
            model,
            data,
            task: task.clone(),
            goal_site,
            hazard_sites,
            pose,
            sensors,
            elapsed: 0,
            done: true,
            config,
        };
        env.set_task(&task)?;
        Ok(env)
    }

    /// The configuration.
    pub fn config(&self) -> &NavConfig {
        &self.config
    }

    /// The compiled model (for rendering).
    pub fn model(&self) -> &Model {
        &self.model
    }

    /// The compiled model, for experiments that change physics parameters in
    /// place (friction, gravity, timestep, ...). Sizes cannot change through
    /// it; edits take effect at the next step. The goal and hazard sites are
    /// rewritten by every [`CmdpEnv::set_task`].
    pub fn model_mut(&mut self) -> &mut Model {
        &mut self.model
    }

    /// The simulation state (for rendering and tests).
    pub fn data(&self) -> &Data {
        &self.data
    }

    /// Renders the current state (robot, goal, hazards) with `renderer` (made
    /// for [`SafeDarkMujoco::model`]); `Camera::Named("top".into())` looks
    /// straight down on the arena.
    pub fn render(
        &mut self,
        renderer: &mut Renderer,
        camera: &Camera,
    ) -> Result<RgbImage, RenderError> {
        renderer.render(&self.model, &mut self.data, camera)
    }

    /// The goal's xy position.
    pub fn goal_xy(&self) -> [f64; 2] {
        self.goal_xy
    }

    /// The task's hazards' xy positions.
    pub fn hazards_xy(&self) -> &[[f64; 2]] {
        &self.hazards_xy
    }

    /// The robot's current xy position.
    pub fn robot_xy(&self) -> [f64; 2] {
        let q = self.data.qpos();
        match self.pose {
            Pose::Planar { x, y, .. } => [q[x], q[y]],
            Pose::Free { adr } => [q[adr], q[adr + 1]],
        }
    }

    /// The robot's current yaw (heading angle about z, radians). Point's
    /// heading is its body +x axis, Car's its chassis +y axis; the yaw is the
    /// angle of the body +x axis in both cases.
    pub fn robot_yaw(&self) -> f64 {
        let r = self.rotation();
        r[3].atan2(r[0])
    }

    /// The robot's heading: the direction it drives when pushed forward
    /// (Point's body +x axis, Car's chassis +y axis), as an angle about z.
    pub fn robot_heading(&self) -> f64 {
        match self.config.robot {
            Robot::Point => self.robot_yaw(),
            Robot::Car => self.robot_yaw() + std::f64::consts::FRAC_PI_2,
        }
    }

    /// A scripted controller that **knows** the goal (the agent never does):
    /// turn towards the goal, drive forward when roughly facing it. Used to
    /// prove that every goal cell is reachable within the time limit
    /// (`tests/tests/env_reach.rs`, `examples/reach.rs`); not a baseline.
    pub fn goal_seeking_action(&self) -> [f32; 2] {
        let [x, y] = self.robot_xy();
        let [gx, gy] = self.goal_xy;
        let err = wrap_angle((gy - y).atan2(gx - x) - self.robot_heading());
        let turn = (3.0 * err).clamp(-1.0, 1.0) as f32;
        let forward = if err.abs() < 0.5 { 1.0 } else { 0.0 };
        match self.config.robot {
            Robot::Point => [forward, turn],
            // Differential drive: left wheel (x = -0.1) slower to turn left.
            Robot::Car => [
                (forward - turn).clamp(-1.0, 1.0),
                (forward + turn).clamp(-1.0, 1.0),
            ],
        }
    }

    /// The body-to-world rotation, row-major.
    fn rotation(&self) -> [f64; 9] {
        let q = self.data.qpos();
        match self.pose {
            Pose::Planar { yaw, .. } => {
                let (s, c) = q[yaw].sin_cos();
                [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0]
            }
            Pose::Free { adr } => quat_to_mat([q[adr + 3], q[adr + 4], q[adr + 5], q[adr + 6]]),
        }
    }

    fn in_hazard(&self, xy: [f64; 2]) -> bool {
        let r2 = self.config.hazard_radius * self.config.hazard_radius;
        self.hazards_xy.iter().any(|h| {
            let (dx, dy) = (xy[0] - h[0], xy[1] - h[1]);
            dx * dx + dy * dy <= r2
        })
    }

    fn check_obs(&self, obs: &[f32]) -> Result<(), EnvError> {
        let want = self.config.robot.obs_dim();
        if obs.len() != want {
            return Err(EnvError::State(format!(
                "observation buffer has length {}, {} writes {want}",
                obs.len(),
                self.config.robot
            )));
        }
        Ok(())
    }

    fn write_obs(&self, obs: &mut [f32]) {
        let xy = self.robot_xy();
        obs[0] = xy[0] as f32;
        obs[1] = xy[1] as f32;
        for (o, r) in obs[2..11].iter_mut().zip(self.rotation()) {
            *o = r as f32;
        }
        let sd = self.data.sensordata();
        let mut k = 11;
        for (range, is_quat) in &self.sensors.ranges {
            let s = &sd[range.clone()];
            if *is_quat {
                let m = quat_to_mat([s[0], s[1], s[2], s[3]]);
                for (o, v) in obs[k..k + 9].iter_mut().zip(m) {
                    *o = v as f32;
                }
                k += 9;
            } else {
                for (o, v) in obs[k..k + s.len()].iter_mut().zip(s) {
                    *o = *v as f32;
                }
                k += s.len();
            }
        }
    }

    /// Ends the episode and turns a state-resetting warning into an error.
    fn unstable(&mut self, what: String) -> EnvError {
        self.done = true;
        EnvError::Unstable(what)
    }
}

/// `a` wrapped to [-pi, pi].
fn wrap_angle(a: f64) -> f64 {
    let a = a.rem_euclid(std::f64::consts::TAU);
    if a > std::f64::consts::PI {
        a - std::f64::consts::TAU
    } else {
        a
    }
}

/// Rotation matrix (row-major) of a unit quaternion `(w, x, y, z)`;
/// normalises first so a slightly denormalised quaternion stays a rotation.
fn quat_to_mat(q: [f64; 4]) -> [f64; 9] {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    let [w, x, y, z] = if n > 0.0 {
        [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
    } else {
        [1.0, 0.0, 0.0, 0.0]
    };
    [
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * z + w * y),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - w * x),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    ]
}

impl CmdpEnv for SafeDarkMujoco {
    fn observation_space(&self) -> Space {
        let n = self.config.robot.obs_dim();
        let mut low = vec![f32::NEG_INFINITY; n];
        let mut high = vec![f32::INFINITY; n];
        // The rotation matrices' entries lie in [-1, 1].
        let rot = (2..11).chain(if n == 35 { 26..35 } else { 0..0 });
        for i in rot {
            low[i] = -1.0;
            high[i] = 1.0;
        }
        Space::Box { low, high }
    }

    fn action_space(&self) -> Space {
        Space::Box {
            low: vec![-1.0, -1.0],
            high: vec![1.0, 1.0],
        }
    }

    fn max_episode_steps(&self) -> usize {
        self.config.max_episode_steps
    }

    fn set_task(&mut self, task: &Task) -> Result<(), EnvError> {
        task.validate(self.config.grid_size, self.config.n_hazards)?;
        let [gx, gy] = self.config.cell_xy(task.goal);
        *self.model.site_pos_mut(self.goal_site)? = [gx, gy, MARKER_Z];
        self.goal_xy = [gx, gy];
        self.hazards_xy.clear();
        for (i, &site) in self.hazard_sites.iter().enumerate() {
            let pos = match task.obstacles.get(i) {
                Some(&cell) => {
                    let [hx, hy] = self.config.cell_xy(cell);
                    self.hazards_xy.push([hx, hy]);
                    [hx, hy, MARKER_Z]
                }
                None => PARKED,
            };
            *self.model.site_pos_mut(site)? = pos;
        }
        self.task.clone_from(task);
        // A new task invalidates the running episode.
        self.done = true;
        Ok(())
    }

    fn task(&self) -> &Task {
        &self.task
    }

    /// The start is deterministic (robot at the centre, heading +x, at rest),
    /// so `seed` has no effect.
    fn reset(&mut self, _seed: u64, obs: &mut [f32]) -> Result<(), EnvError> {
        self.check_obs(obs)?;
        self.data.reset(&self.model)?;
        // Fill the sensors (and site positions) of the initial state.
        let warnings = self.data.forward(&self.model)?;
        if warnings.state_was_reset() {
            return Err(self.unstable(format!("MuJoCo warnings on reset: {warnings:?}")));
        }
        self.elapsed = 0;
        self.done = false;
        self.write_obs(obs);
        Ok(())
    }

    fn step(&mut self, action: Action<'_>, obs: &mut [f32]) -> Result<StepOutcome, EnvError> {
        if self.done {
            return Err(EnvError::State(
                "step called after the episode ended (or before the first reset); call reset"
                    .into(),
            ));
        }
        self.check_obs(obs)?;
        let a = match action {
            Action::Continuous(a) => a,
            Action::Discrete(_) => {
                return Err(EnvError::InvalidAction(format!(
                    "{} takes a continuous action of 2 values in [-1, 1], got a discrete one",
                    self.config.robot
                )));
            }
        };
        if a.len() != 2 {
            return Err(EnvError::InvalidAction(format!(
                "{} takes 2 action values, got {}",
                self.config.robot,
                a.len()
            )));
        }
        if let Some(bad) = a.iter().find(|v| !v.is_finite()) {
            return Err(EnvError::InvalidAction(format!(
                "action {a:?} contains a non-finite value ({bad})"
            )));
        }
        let ctrl = self.data.ctrl_mut();
        // Out-of-range values are clamped to the control range [-1, 1].
        ctrl[0] = f64::from(a[0].clamp(-1.0, 1.0));
        ctrl[1] = f64::from(a[1].clamp(-1.0, 1.0));

        let mut hit_hazard = false;
        for _ in 0..self.config.physics_steps_per_action {
            let warnings = match self.data.step(&self.model) {
                Ok(w) => w,
                Err(e) => {
                    self.done = true;
                    return Err(e.into());
                }
            };
            if warnings.state_was_reset() {
                return Err(self.unstable(format!(
                    "MuJoCo reset the state during a physics step ({warnings:?}); reset the environment"
                )));
            }
            // Counted at every sub-step, so a fast robot cannot skip through.
            hit_hazard |= self.in_hazard(self.robot_xy());
        }
        self.elapsed += 1;
        let [x, y] = self.robot_xy();
        let (dx, dy) = (x - self.goal_xy[0], y - self.goal_xy[1]);
        let at_goal = dx * dx + dy * dy <= self.config.goal_radius * self.config.goal_radius;
        let outcome = StepOutcome::goal_task(
            at_goal,
            hit_hazard,
            self.elapsed,
            self.config.max_episode_steps,
        );
        self.done = outcome.done();
        self.write_obs(obs);
        Ok(outcome)
    }

    fn elapsed_steps(&self) -> usize {
        self.elapsed
    }

    fn physics_steps_per_action(&self) -> Option<usize> {
        Some(self.config.physics_steps_per_action)
    }

    fn goal_rule(&self) -> GoalRule {
        GoalRule {
            xy: [0, 1],
            radius: self.config.goal_radius as f32,
            min_start_distance: self.config.spacing() as f32,
        }
    }

    fn goal_position(&self) -> [f32; 2] {
        [self.goal_xy[0] as f32, self.goal_xy[1] as f32]
    }

    fn goal_seeking_action(&self) -> Option<Vec<f32>> {
        Some(SafeDarkMujoco::goal_seeking_action(self).to_vec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_maps_centre_to_origin_and_respects_keepouts() {
        let c = NavConfig::default();
        assert_eq!(c.cell_xy(Cell::centre(5)), [0.0, 0.0]);
        assert_eq!(c.cell_xy(Cell { row: 0, col: 0 }), [-1.5, 1.5]);
        // Largest keep-out pair (agent 0.4 + goal 0.305).
        assert!(c.spacing() >= 0.705);
    }

    #[test]
    fn quaternion_matrix_is_a_rotation() {
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let m = quat_to_mat([h, 0.0, 0.0, h]); // 90 degrees about z
        let want = [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
        for (a, b) in m.iter().zip(want) {
            assert!((a - b).abs() < 1e-12);
        }
    }
}
