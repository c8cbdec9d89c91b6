//! Many environments stepped together: `safety_envs._native.VecEnv`, on
//! `safety_envs::VecEnv` and its threads.

use numpy::{PyArray1, PyArray2, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::{PyRuntimeError, PyTypeError};
use pyo3::prelude::*;
use safety_envs::prelude::*;

use crate::{PyCell, PyTask, env_name, task_from_py, task_to_py, to_py};

/// What a batch step returns: observations `(N, obs_dim)`, rewards, costs,
/// terminated, truncated (`(N,)` each), and the final observations
/// `(N, obs_dim)` of the episodes that ended (rows of the others are stale).
type BatchStep<'py> = (
    Bound<'py, PyArray2<f32>>,
    Bound<'py, PyArray1<f32>>,
    Bound<'py, PyArray1<f32>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray2<f32>>,
);

/// `N` environments with auto-reset: an environment whose episode ended is
/// reset within the same step (its last observation is returned as a final
/// observation), in its current task, with a seed derived from its reset
/// seed and episode index. `unsendable`: a `VecEnv` is used from the Python
/// thread that made it.
#[pyclass(module = "safety_envs._native", unsendable)]
pub struct VecEnv {
    /// `None` once closed.
    inner: Option<safety_envs::VecEnv>,
    discrete: bool,
}

impl VecEnv {
    fn inner(&mut self) -> PyResult<&mut safety_envs::VecEnv> {
        self.inner
            .as_mut()
            .ok_or_else(|| PyRuntimeError::new_err("the vector environment is closed"))
    }
}

#[pymethods]
impl VecEnv {
    /// `num_envs` copies of environment `name`, stepped on `num_threads`
    /// threads (the `VecEnv` steps inline while a batch is cheaper than a
    /// hand-off to its threads, so SafeDarkRoom stays on one).
    #[new]
    #[pyo3(signature = (name, num_envs, num_threads, max_episode_steps=None, physics_steps_per_action=None))]
    fn new(
        name: &str,
        num_envs: usize,
        num_threads: usize,
        max_episode_steps: Option<usize>,
        physics_steps_per_action: Option<usize>,
    ) -> PyResult<Self> {
        let name = env_name(name)?;
        let options = EnvOptions {
            max_episode_steps,
            physics_steps_per_action,
        };
        let envs = (0..num_envs)
            .map(|_| make_env(name, &options))
            .collect::<Result<Vec<_>, _>>()
            .map_err(to_py)?;
        let inner = safety_envs::VecEnv::new(envs, num_threads, true).map_err(to_py)?;
        let discrete = matches!(inner.action_space(), Space::Discrete { .. });
        Ok(VecEnv {
            inner: Some(inner),
            discrete,
        })
    }

    /// The number of environments.
    #[getter]
    fn num_envs(&mut self) -> PyResult<usize> {
        Ok(self.inner()?.len())
    }

    /// The task of environment `i`, `(grid_size, goal, hazards)`.
    fn task(&mut self, i: usize) -> PyResult<PyTask> {
        let inner = self.inner()?;
        if i >= inner.len() {
            return Err(to_py(EnvError::InvalidConfig(format!(
                "environment index {i} out of range 0..{}",
                inner.len()
            ))));
        }
        Ok(task_to_py(inner.env(i).task()))
    }

    /// Sets the task of environment `i` (kept across its resets).
    fn set_task(&mut self, i: usize, goal: PyCell, hazards: Vec<PyCell>) -> PyResult<()> {
        let inner = self.inner()?;
        let grid = inner.env(i.min(inner.len() - 1)).task().grid_size;
        inner
            .set_task(i, &task_from_py(grid, goal, &hazards))
            .map_err(to_py)
    }

    /// Resets every environment, environment `i` with `seeds[i]`; returns the
    /// observations `(N, obs_dim)`.
    fn reset<'py>(
        &mut self,
        py: Python<'py>,
        seeds: Vec<u64>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let inner = self.inner()?;
        let d = inner.obs_dim();
        let obs = py.detach(|| inner.reset(&seeds).map(<[f32]>::to_vec));
        rows(py, obs.map_err(to_py)?, d)
    }

    /// Steps every environment once with `actions`: `(N,)` integers
    /// (SafeDarkRoom) or `(N, act_dim)` float32 (Point, Car).
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        actions: &Bound<'py, PyAny>,
    ) -> PyResult<BatchStep<'py>> {
        let discrete = self.discrete;
        let inner = self.inner()?;
        let (n, d) = (inner.len(), inner.obs_dim());
        // The actions are copied (a few values per environment), so the
        // physics runs without the GIL while Python may touch the array.
        let stepped = if discrete {
            let a = discrete_actions(actions, n)?;
            py.detach(|| inner.step(VecAction::Discrete(&a)).map(<[_]>::to_vec))
        } else {
            let a = continuous_actions(actions, n, inner.act_dim())?;
            py.detach(|| inner.step(VecAction::Continuous(&a)).map(<[_]>::to_vec))
        };
        let outcomes = stepped.map_err(to_py)?;
        // One copy out of the VecEnv's buffers into fresh arrays, which the
        // caller may keep.
        let obs = rows(py, inner.observations().to_vec(), d)?;
        let final_obs = rows(py, inner.final_observations().to_vec(), d)?;
        let column = |f: fn(&StepOutcome) -> f32| -> Vec<f32> { outcomes.iter().map(f).collect() };
        let flag = |f: fn(&StepOutcome) -> bool| -> Vec<bool> { outcomes.iter().map(f).collect() };
        debug_assert_eq!(outcomes.len(), n);
        Ok((
            obs,
            PyArray1::from_vec(py, column(|o| o.reward)),
            PyArray1::from_vec(py, column(|o| o.cost)),
            PyArray1::from_vec(py, flag(|o| o.terminated)),
            PyArray1::from_vec(py, flag(|o| o.truncated)),
            final_obs,
        ))
    }

    /// Frees the environments and their threads; closing twice is allowed.
    fn close(&mut self) {
        self.inner = None;
    }
}

/// `values` (`n x d`, row-major) as an `(n, d)` array, without a copy.
fn rows(py: Python<'_>, values: Vec<f32>, d: usize) -> PyResult<Bound<'_, PyArray2<f32>>> {
    let n = values.len() / d.max(1);
    PyArray1::from_vec(py, values).reshape([n, d])
}

/// SafeDarkRoom's actions: `n` integers (a 1-D integer array or sequence).
fn discrete_actions(actions: &Bound<'_, PyAny>, n: usize) -> PyResult<Vec<usize>> {
    let values: Vec<i64> = actions.extract().map_err(|_| {
        PyTypeError::new_err(format!(
            "SafeDarkRoom takes {n} integer actions (one per environment)"
        ))
    })?;
    values
        .into_iter()
        .map(|a| {
            usize::try_from(a).map_err(|_| {
                to_py(EnvError::InvalidAction(format!(
                    "SafeDarkRoom action {a} is out of range 0..5"
                )))
            })
        })
        .collect()
}

/// The robots' actions: an `(n, act_dim)` float32 array, copied row-major.
fn continuous_actions(actions: &Bound<'_, PyAny>, n: usize, act_dim: usize) -> PyResult<Vec<f32>> {
    let array: PyReadonlyArrayDyn<'_, f32> = actions.extract().map_err(|_| {
        PyTypeError::new_err(format!(
            "the robots take a float32 numpy array of shape ({n}, {act_dim})"
        ))
    })?;
    if array.shape() != [n, act_dim] {
        return Err(to_py(EnvError::InvalidAction(format!(
            "actions of shape {:?} for {n} environments x {act_dim} values; expected ({n}, {act_dim})",
            array.shape()
        ))));
    }
    Ok(array.as_array().iter().copied().collect())
}
