//! `safety_envs._native`: the Rust side of the Python package.
//!
//! A thin layer over `safety-envs`; the Gymnasium classes are Python
//! (`safety_envs/`), so that they are what Gymnasium users expect, and call
//! these:
//!
//! - [`Env`](env::Env): one environment (reset, step, task, render).
//! - [`VecEnv`](vec::VecEnv): `safety_envs::VecEnv`, many environments
//!   stepped on its own threads.
//! - [`sample_task_py`], [`rust_rollout`]: a task from a seed; a rollout
//!   stepped in Rust alone, which the tests compare the Python loop with.
//!
//! Every error is a Python exception carrying the Rust error's message:
//! `ValueError` for an action or setting that cannot be used, `RuntimeError`
//! for a call in the wrong state (a closed environment, a step after the
//! episode ended) or an unstable simulation. MuJoCo's own fatal errors are
//! already turned into `Err` by `safety-envs` (its engine-error hook), and
//! PyO3 turns any Rust panic into a Python `PanicException`: nothing here
//! ends the interpreter. The physics runs with the GIL released.

mod env;
mod vec;

use numpy::{PyArray1, PyReadonlyArray2};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use safety_envs::mujoco::RenderError;
use safety_envs::prelude::*;

/// A Rust environment error as the Python exception carrying its message.
pub(crate) fn to_py(err: EnvError) -> PyErr {
    let kind = match &err {
        EnvError::InEnv { source, .. } => source.as_ref(),
        other => other,
    };
    match kind {
        EnvError::InvalidAction(_) | EnvError::InvalidConfig(_) => {
            PyValueError::new_err(err.to_string())
        }
        _ => PyRuntimeError::new_err(err.to_string()),
    }
}

/// A rendering error as a `RuntimeError` carrying its message.
pub(crate) fn render_err(err: RenderError) -> PyErr {
    PyRuntimeError::new_err(err.to_string())
}

/// The environment named `name` (`darkroom`, `point`, `car`).
pub(crate) fn env_name(name: &str) -> PyResult<EnvName> {
    name.parse().map_err(to_py)
}

/// A cell as Python sees it, `(row, col)`.
pub(crate) type PyCell = (usize, usize);

/// A task as Python sees it: `(grid_size, goal, hazards)`.
pub(crate) type PyTask = (usize, PyCell, Vec<PyCell>);

pub(crate) fn task_to_py(task: &Task) -> PyTask {
    (
        task.grid_size,
        (task.goal.row, task.goal.col),
        task.obstacles.iter().map(|c| (c.row, c.col)).collect(),
    )
}

pub(crate) fn task_from_py(grid_size: usize, goal: PyCell, hazards: &[PyCell]) -> Task {
    let cell = |(row, col): PyCell| Cell { row, col };
    Task {
        grid_size,
        goal: cell(goal),
        obstacles: hazards.iter().copied().map(cell).collect(),
    }
}

/// The task of environment `env` drawn from `seed`, centre- or
/// edge-oriented (`orientation`), as `(grid_size, goal, hazards)`:
/// `safety_envs::sample_task` over the environment's own task grid.
#[pyfunction]
#[pyo3(name = "sample_task")]
fn sample_task_py(env: &str, orientation: &str, seed: u64) -> PyResult<PyTask> {
    let orientation: Orientation = orientation.parse().map_err(to_py)?;
    let task = safety_envs::sample_task(&spawn_config(env_name(env)?), orientation, seed)
        .map_err(to_py)?;
    Ok(task_to_py(&task))
}

/// What [`rust_rollout`] returns: the first observation, then per step the
/// observation, reward, cost, terminated and truncated.
type Rollout<'py> = (
    Bound<'py, PyArray1<f32>>,
    Vec<Vec<f32>>,
    Vec<f32>,
    Vec<f32>,
    Vec<bool>,
    Vec<bool>,
);

/// Steps `actions` (one row per step; SafeDarkRoom's action is the row's
/// first value) through environment `env` built by `safety_envs::make_env`
/// alone, with task `(goal, hazards)`, reset with `seed` at the start and
/// after every episode's end. For tests: the reference the Python
/// environment is checked against, step for step.
#[pyfunction]
#[pyo3(signature = (env, goal, hazards, seed, actions, max_episode_steps=None))]
fn rust_rollout<'py>(
    py: Python<'py>,
    env: &str,
    goal: PyCell,
    hazards: Vec<PyCell>,
    seed: u64,
    actions: PyReadonlyArray2<'py, f32>,
    max_episode_steps: Option<usize>,
) -> PyResult<Rollout<'py>> {
    let options = EnvOptions {
        max_episode_steps,
        ..EnvOptions::default()
    };
    let mut e = make_env(env_name(env)?, &options).map_err(to_py)?;
    let grid = e.task().grid_size;
    e.set_task(&task_from_py(grid, goal, &hazards))
        .map_err(to_py)?;
    let mut obs = vec![0.0; e.observation_space().flat_dim()];
    e.reset(seed, &mut obs).map_err(to_py)?;
    let first = PyArray1::from_slice(py, &obs);
    let discrete = matches!(e.action_space(), Space::Discrete { .. });
    let actions = actions.as_array();
    let mut out: Rollout<'py> = (first, vec![], vec![], vec![], vec![], vec![]);
    for row in actions.rows() {
        let row: Vec<f32> = row.iter().copied().collect();
        let action = if discrete {
            let Some(&a) = row.first() else {
                return Err(to_py(EnvError::InvalidAction(
                    "an empty action row for SafeDarkRoom".into(),
                )));
            };
            Action::Discrete(a as usize)
        } else {
            Action::Continuous(&row)
        };
        let step = e.step(action, &mut obs).map_err(to_py)?;
        out.1.push(obs.clone());
        out.2.push(step.reward);
        out.3.push(step.cost);
        out.4.push(step.terminated);
        out.5.push(step.truncated);
        if step.done() {
            e.reset(seed, &mut obs).map_err(to_py)?;
        }
    }
    Ok(out)
}

/// The module: the two classes, the task sampler, the test reference, and
/// the version (the Cargo workspace's).
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<env::Env>()?;
    m.add_class::<vec::VecEnv>()?;
    m.add_function(wrap_pyfunction!(sample_task_py, m)?)?;
    m.add_function(wrap_pyfunction!(rust_rollout, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    // The numpy arrays handed out are created by the numpy crate, which
    // imports numpy's C API on first use; importing here makes a missing
    // numpy an ImportError at `import safety_envs`.
    PyArray1::<f32>::zeros(m.py(), 0, false);
    Ok(())
}
