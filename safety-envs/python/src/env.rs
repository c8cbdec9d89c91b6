//! One environment: `safety_envs._native.Env`.

use numpy::{PyArray1, PyArray3, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::{PyRuntimeError, PyTypeError};
use pyo3::prelude::*;
use safety_envs::darkroom::draw_darkroom;
use safety_envs::mujoco::{Camera, Renderer};
use safety_envs::prelude::*;

use crate::{PyCell, PyTask, env_name, render_err, task_from_py, task_to_py, to_py};

/// The environment itself, by kind: SafeDarkRoom is drawn by hand (with the
/// cells its current episode visited), the robots through MuJoCo.
enum Sim {
    DarkRoom { env: SafeDarkRoom, trail: Vec<Cell> },
    Nav(SafeDarkMujoco),
}

impl Sim {
    fn env(&mut self) -> &mut dyn CmdpEnv {
        match self {
            Sim::DarkRoom { env, .. } => env,
            Sim::Nav(env) => env,
        }
    }

    fn env_ref(&self) -> &dyn CmdpEnv {
        match self {
            Sim::DarkRoom { env, .. } => env,
            Sim::Nav(env) => env,
        }
    }
}

/// The space of an observation or action, as Python sees it:
/// `("discrete", n, [], [])` or `("box", 0, low, high)`.
type PySpace = (&'static str, usize, Vec<f32>, Vec<f32>);

fn space_to_py(space: Space) -> PySpace {
    match space {
        Space::Discrete { n } => ("discrete", n, vec![], vec![]),
        Space::Box { low, high } => ("box", 0, low, high),
    }
}

/// One environment. `unsendable`: the MuJoCo renderer's OpenGL context is
/// bound to the thread that made it, so the environment is used from the
/// Python thread that created it (PyO3 raises an error on any other).
#[pyclass(module = "safety_envs._native", unsendable)]
pub struct Env {
    name: EnvName,
    /// `None` once closed.
    sim: Option<Sim>,
    /// Made on the first render, for one image size.
    renderer: Option<Renderer>,
    obs_dim: usize,
    observation_space: PySpace,
    action_space: PySpace,
    max_episode_steps: usize,
}

impl Env {
    fn sim(&mut self) -> PyResult<&mut Sim> {
        self.sim.as_mut().ok_or_else(closed)
    }
}

fn closed() -> PyErr {
    PyRuntimeError::new_err("the environment is closed")
}

#[pymethods]
impl Env {
    /// Environment `name` (`darkroom`, `point`, `car`); `None` keeps a
    /// default (time limit: darkroom 30, point and car 75 agent steps;
    /// point and car: 50 physics steps per agent action).
    #[new]
    #[pyo3(signature = (name, max_episode_steps=None, physics_steps_per_action=None))]
    fn new(
        name: &str,
        max_episode_steps: Option<usize>,
        physics_steps_per_action: Option<usize>,
    ) -> PyResult<Self> {
        let name = env_name(name)?;
        let options = EnvOptions {
            max_episode_steps,
            physics_steps_per_action,
        };
        // Built as `make_env` builds them (same checks), but kept concrete
        // for rendering.
        let sim = match name {
            EnvName::DarkRoom => {
                make_env(name, &options).map_err(to_py)?;
                let mut config = DarkRoomConfig::default();
                if let Some(t) = max_episode_steps {
                    config.max_episode_steps = t;
                }
                Sim::DarkRoom {
                    env: SafeDarkRoom::new(config).map_err(to_py)?,
                    trail: vec![],
                }
            }
            EnvName::Point | EnvName::Car => {
                let robot = if name == EnvName::Point {
                    Robot::Point
                } else {
                    Robot::Car
                };
                let mut config = NavConfig::new(robot);
                if let Some(t) = max_episode_steps {
                    config.max_episode_steps = t;
                }
                if let Some(n) = physics_steps_per_action {
                    config.physics_steps_per_action = n;
                }
                Sim::Nav(SafeDarkMujoco::new(config).map_err(to_py)?)
            }
        };
        let env = sim.env_ref();
        Ok(Env {
            name,
            obs_dim: env.observation_space().flat_dim(),
            observation_space: space_to_py(env.observation_space()),
            action_space: space_to_py(env.action_space()),
            max_episode_steps: env.max_episode_steps(),
            sim: Some(sim),
            renderer: None,
        })
    }

    /// `darkroom`, `point` or `car`.
    #[getter]
    fn name(&self) -> &'static str {
        self.name.as_str()
    }

    /// `("box", 0, low, high)`.
    #[getter]
    fn observation_space(&self) -> PySpace {
        self.observation_space.clone()
    }

    /// `("discrete", n, [], [])` or `("box", 0, low, high)`.
    #[getter]
    fn action_space(&self) -> PySpace {
        self.action_space.clone()
    }

    /// The time limit in agent steps.
    #[getter]
    fn max_episode_steps(&self) -> usize {
        self.max_episode_steps
    }

    /// MuJoCo physics steps per agent action; `None` for SafeDarkRoom.
    #[getter]
    fn physics_steps_per_action(&self) -> PyResult<Option<usize>> {
        let sim = self.sim.as_ref().ok_or_else(closed)?;
        Ok(sim.env_ref().physics_steps_per_action())
    }

    /// Agent steps taken in the current episode.
    #[getter]
    fn elapsed_steps(&self) -> PyResult<usize> {
        let sim = self.sim.as_ref().ok_or_else(closed)?;
        Ok(sim.env_ref().elapsed_steps())
    }

    /// The current task, `(grid_size, goal, hazards)`.
    fn task(&self) -> PyResult<PyTask> {
        let sim = self.sim.as_ref().ok_or_else(closed)?;
        Ok(task_to_py(sim.env_ref().task()))
    }

    /// Places the goal and hazards for the following episodes (kept across
    /// resets); the environment's own checks apply (inside the grid, off the
    /// start, the right number of hazards).
    fn set_task(&mut self, goal: PyCell, hazards: Vec<PyCell>) -> PyResult<()> {
        let env = self.sim()?.env();
        let task = task_from_py(env.task().grid_size, goal, &hazards);
        env.set_task(&task).map_err(to_py)
    }

    /// Starts an episode in the current task; returns the first observation.
    fn reset<'py>(&mut self, py: Python<'py>, seed: u64) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let mut obs = vec![0.0f32; self.obs_dim];
        match self.sim()? {
            Sim::DarkRoom { env, trail } => {
                env.reset(seed, &mut obs).map_err(to_py)?;
                trail.clear();
                trail.push(env.position());
            }
            Sim::Nav(env) => py.detach(|| env.reset(seed, &mut obs)).map_err(to_py)?,
        }
        // The numpy array takes the vector's memory: no copy.
        Ok(PyArray1::from_vec(py, obs))
    }

    /// Applies one action: an integer (SafeDarkRoom) or a 1-D float32 array
    /// (Point, Car). Returns `(obs, reward, cost, terminated, truncated)`.
    #[allow(clippy::type_complexity)]
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        action: &Bound<'py, PyAny>,
    ) -> PyResult<(Bound<'py, PyArray1<f32>>, f32, f32, bool, bool)> {
        let mut obs = vec![0.0f32; self.obs_dim];
        let out = match self.sim()? {
            Sim::DarkRoom { env, trail } => {
                let a = discrete_action(action)?;
                let out = env.step(Action::Discrete(a), &mut obs).map_err(to_py)?;
                trail.push(env.position());
                out
            }
            Sim::Nav(env) => {
                let a = continuous_action(action, env.config().robot)?;
                py.detach(|| env.step(Action::Continuous(&a), &mut obs))
                    .map_err(to_py)?
            }
        };
        Ok((
            PyArray1::from_vec(py, obs),
            out.reward,
            out.cost,
            out.terminated,
            out.truncated,
        ))
    }

    /// The current state as an RGB image, `(height, width, 3)` uint8, seen
    /// from above: robot red, goal green, hazards blue (SafeDarkRoom drawn
    /// by hand, the robots by MuJoCo through OSMesa, headless).
    fn render<'py>(
        &mut self,
        py: Python<'py>,
        width: usize,
        height: usize,
    ) -> PyResult<Bound<'py, PyArray3<u8>>> {
        let Some(sim) = self.sim.as_mut() else {
            return Err(closed());
        };
        let image = match sim {
            Sim::DarkRoom { env, trail } => draw_darkroom(env, trail, (width, height)),
            Sim::Nav(env) => {
                let fits = |r: &Renderer| r.width() == width && r.height() == height;
                if !self.renderer.as_ref().is_some_and(fits) {
                    self.renderer = None;
                    self.renderer =
                        Some(Renderer::new(env.model(), width, height).map_err(render_err)?);
                }
                let renderer = self.renderer.as_mut().ok_or_else(closed)?;
                env.render(renderer, &Camera::Named("top".into()))
                    .map_err(render_err)?
            }
        };
        let (w, h) = (image.width, image.height);
        PyArray1::from_vec(py, image.pixels).reshape([h, w, 3])
    }

    /// Frees the simulation and the renderer; later calls raise
    /// `RuntimeError`. Closing twice is allowed.
    fn close(&mut self) {
        self.renderer = None;
        self.sim = None;
    }

    /// Whether [`Env::close`] was called.
    #[getter]
    fn closed(&self) -> bool {
        self.sim.is_none()
    }
}

/// SafeDarkRoom's action: a Python or numpy integer. A negative one gets the
/// message the environment gives any action out of range.
fn discrete_action(action: &Bound<'_, PyAny>) -> PyResult<usize> {
    let a: i64 = action.extract().map_err(|_| {
        PyTypeError::new_err(format!(
            "SafeDarkRoom takes an integer action in 0..5, got {}",
            action
                .repr()
                .map(|r| r.to_string())
                .unwrap_or_else(|_| "an object without a repr".into())
        ))
    })?;
    usize::try_from(a).map_err(|_| {
        to_py(EnvError::InvalidAction(format!(
            "SafeDarkRoom action {a} is out of range 0..5"
        )))
    })
}

/// A robot's action: a 1-D float32 array, copied (a few values) so the
/// physics can run without the GIL while Python may touch the array.
fn continuous_action(action: &Bound<'_, PyAny>, robot: Robot) -> PyResult<Vec<f32>> {
    let array: PyReadonlyArrayDyn<'_, f32> = action.extract().map_err(|_| {
        PyTypeError::new_err(format!(
            "{robot} takes a float32 numpy array of 2 values, got {}",
            action
                .get_type()
                .name()
                .map(|n| n.to_string())
                .unwrap_or_default()
        ))
    })?;
    if array.ndim() != 1 {
        return Err(to_py(EnvError::InvalidAction(format!(
            "{robot} takes an action of shape (2,), got shape {:?}",
            array.shape()
        ))));
    }
    Ok(array.as_array().iter().copied().collect())
}
