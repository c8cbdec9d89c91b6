//! The reader: the checksum and a merged file's shards first, then the
//! attributes, then every array with the shape it must have, split into
//! histories that each pass the writer's checks.

use std::path::Path;

use hdf5::types::VarLenUnicode;
use safety_envs::{Cell, EnvName, Task};

use super::seal::verify_shards;
use super::{
    DatasetInfo, FORMAT_VERSION, History, HistoryError, HistoryFile, Problem, Shard, verify_seal,
};

/// Reads dataset `name` as a flat row-major vector with its shape. A
/// declared size that would not fit in half the machine's available memory
/// (a damaged or hostile file: chunked datasets can declare any shape) is
/// an error before anything is allocated.
fn get<T: hdf5::H5Type>(f: &hdf5::File, name: &str) -> hdf5::Result<(Vec<T>, Vec<usize>)> {
    let d = f.dataset(name)?;
    let shape = d.shape();
    let bytes = shape
        .iter()
        .try_fold(std::mem::size_of::<T>() as u128, |acc, &n| {
            acc.checked_mul(n as u128)
        });
    let limit = crate::guard::machine_memory().map_or(u128::MAX, |(avail, _)| avail as u128 / 2);
    match bytes {
        Some(b) if b <= limit => Ok((d.read_raw::<T>()?, shape)),
        _ => Err(hdf5::Error::from(
            format!(
                "declares shape {shape:?}, more than half this machine's available memory ({})",
                crate::guard::human_bytes(limit as f64)
            )
            .as_str(),
        )),
    }
}

/// Reads a history file and validates it. With `expected_env`, a file made
/// for another environment is an error.
pub fn read_histories(
    path: &Path,
    expected_env: Option<&str>,
) -> Result<HistoryFile, HistoryError> {
    let err = |p| HistoryError::new(path, p);
    if !path.exists() {
        return Err(err(Problem::Missing));
    }
    if verify_seal(path).map_err(err)?.is_none() {
        eprintln!(
            "warning: {}: no icrl checksum (written elsewhere or by an older icrl): damage cannot be detected before libhdf5 reads it",
            path.display()
        );
    }
    let f = hdf5::File::open(path).map_err(|e| err(Problem::Unreadable(e.to_string())))?;
    // A merged file: its shards are checked before libhdf5 reads through to them.
    verify_shards(&f, path)?;

    let info = read_info(&f, path, expected_env)?;
    let arrays = Arrays::read(&f, path, &info)?;
    let histories = arrays.split(path, &info)?;
    Ok(HistoryFile { info, histories })
}

/// A file's datasets as read, each with the shape it must have: per step
/// (`n` rows), per history (`h` rows), `n_obstacles` obstacles per task.
struct Arrays {
    observations: Vec<f32>,
    next_observations: Vec<f32>,
    actions: Vec<f32>,
    rewards: Vec<f32>,
    costs: Vec<f32>,
    terminals: Vec<f32>,
    timeouts: Vec<f32>,
    cost_limit: Vec<f32>,
    history_id: Vec<i64>,
    goals: Vec<i64>,
    obstacles: Vec<i64>,
    n: usize,
    h: usize,
    n_obstacles: usize,
}

impl Arrays {
    /// Reads every dataset, checking its shape against the attributes and
    /// the others: as many rows per step, histories for the grid part the
    /// file holds.
    fn read(f: &hdf5::File, path: &Path, info: &DatasetInfo) -> Result<Self, HistoryError> {
        let err = |p| HistoryError::new(path, p);
        let malformed = |what: String| err(Problem::Malformed(what));
        // Each dataset with the shape it must have (None: any length, checked below).
        let read = |name: &str, tail: &[usize]| -> Result<(Vec<f32>, usize), HistoryError> {
            let (v, shape) =
                get::<f32>(f, name).map_err(|e| malformed(format!("dataset {name}: {e}")))?;
            if shape.len() != 1 + tail.len() || shape[1..] != *tail {
                return Err(malformed(format!(
                    "dataset {name} has shape {shape:?}, expected (rows, {tail:?})"
                )));
            }
            Ok((v, shape[0]))
        };
        let (observations, n_obs) = read("observations", &[info.obs_dim])?;
        let (next_observations, n_next) = read("next_observations", &[info.obs_dim])?;
        let (actions, n_act) = read("actions", &[info.action_dim])?;
        let (rewards, n) = read("rewards", &[])?;
        let (costs, n_costs) = read("costs", &[])?;
        let (terminals, n_term) = read("terminals", &[])?;
        let (timeouts, n_time) = read("timeouts", &[])?;
        let (cost_limit, h) = read("cost_limit", &[])?;
        let (history_id, id_shape) = get::<i64>(f, "history_id")
            .map_err(|e| malformed(format!("dataset history_id: {e}")))?;
        let (goals, goal_shape) =
            get::<i64>(f, "task_goal").map_err(|e| malformed(format!("dataset task_goal: {e}")))?;
        let (obstacles, obstacle_shape) = get::<i64>(f, "task_obstacles")
            .map_err(|e| malformed(format!("dataset task_obstacles: {e}")))?;

        for (name, len) in [
            ("observations", n_obs),
            ("next_observations", n_next),
            ("actions", n_act),
            ("costs", n_costs),
            ("terminals", n_term),
            ("timeouts", n_time),
            ("history_id", id_shape.first().copied().unwrap_or(0)),
        ] {
            if len != n {
                return Err(malformed(format!(
                    "dataset {name} has {len} rows, rewards has {n}"
                )));
            }
        }
        if h == 0 {
            return Err(err(Problem::Empty("the file holds no histories".into())));
        }
        let n_obstacles = obstacle_shape.get(1).copied().unwrap_or(0);
        if goal_shape != [h, 2] || obstacle_shape != [h, n_obstacles, 2] {
            return Err(malformed(format!(
                "task arrays have shapes {goal_shape:?} and {obstacle_shape:?}, expected [{h}, 2] and [{h}, n, 2]"
            )));
        }

        let ids = info.history_ids();
        if ids.len() != h {
            return Err(malformed(format!(
                "it holds {h} histories, but {} of a grid of {} is {} ({ids:?})",
                info.shard
                    .map_or("all".to_string(), |s| format!("shard {s}")),
                info.grid_histories,
                ids.len()
            )));
        }
        Ok(Arrays {
            observations,
            next_observations,
            actions,
            rewards,
            costs,
            terminals,
            timeouts,
            cost_limit,
            history_id,
            goals,
            obstacles,
            n,
            h,
            n_obstacles,
        })
    }

    /// The flat arrays split by `history_id` (non-decreasing, every id
    /// present) into histories, each passing the writer's checks.
    fn split(&self, path: &Path, info: &DatasetInfo) -> Result<Vec<History>, HistoryError> {
        let err = |p| HistoryError::new(path, p);
        let malformed = |what: String| err(Problem::Malformed(what));
        let (n, h, history_id) = (self.n, self.h, &self.history_id);
        let ids = info.history_ids();
        // Out of order, a history would look empty though its steps are there.
        if let Some(k) = (1..n).find(|&k| history_id[k] < history_id[k - 1]) {
            return Err(malformed(format!(
                "history_id must be non-decreasing (every history's steps together, in order 0..{h}): \
                 step {k} has id {} after id {}",
                history_id[k],
                history_id[k - 1]
            )));
        }
        let mut histories = Vec::with_capacity(h);
        let mut start = 0usize;
        for i in 0..h {
            let mut end = start;
            while end < n && history_id[end] == (ids.start + i) as i64 {
                end += 1;
            }
            if end == start {
                return Err(err(Problem::Empty(format!(
                    "history {i} (cost limit {}) has no steps",
                    self.cost_limit[i]
                ))));
            }
            let hist = self.history(i, start, end, path, info)?;
            hist.check(i, info)
                .map_err(|p| match p {
                    Problem::Invalid(s) => Problem::Malformed(s),
                    other => other,
                })
                .map_err(err)?;
            histories.push(hist);
            start = end;
        }
        if start != n {
            return Err(malformed(format!(
                "history_id is not sorted {ids:?}: step {start} has id {}",
                history_id[start]
            )));
        }
        Ok(histories)
    }

    /// History `i`, the steps `start..end`: its task (every cell inside the
    /// grid) and its rows of the per-step arrays.
    fn history(
        &self,
        i: usize,
        start: usize,
        end: usize,
        path: &Path,
        info: &DatasetInfo,
    ) -> Result<History, HistoryError> {
        let n_obstacles = self.n_obstacles;
        let cell = |r: i64, c: i64| -> Result<Cell, HistoryError> {
            if r < 0 || c < 0 || r as usize >= info.grid_size || c as usize >= info.grid_size {
                return Err(HistoryError::new(
                    path,
                    Problem::Malformed(format!(
                        "history {i}: cell ({r}, {c}) is outside the {g}x{g} grid",
                        g = info.grid_size
                    )),
                ));
            }
            Ok(Cell {
                row: r as usize,
                col: c as usize,
            })
        };
        let task = Task {
            grid_size: info.grid_size,
            goal: cell(self.goals[2 * i], self.goals[2 * i + 1])?,
            obstacles: (0..n_obstacles)
                .map(|j| {
                    let k = 2 * (i * n_obstacles + j);
                    cell(self.obstacles[k], self.obstacles[k + 1])
                })
                .collect::<Result<_, _>>()?,
        };
        let rows = |a: &[f32], cols: usize| a[start * cols..end * cols].to_vec();
        let flags = |a: &[f32]| a[start..end].iter().map(|&x| x != 0.0).collect();
        Ok(History {
            cost_limit: self.cost_limit[i],
            task,
            observations: rows(&self.observations, info.obs_dim),
            next_observations: rows(&self.next_observations, info.obs_dim),
            actions: rows(&self.actions, info.action_dim),
            rewards: rows(&self.rewards, 1),
            costs: rows(&self.costs, 1),
            terminals: flags(&self.terminals),
            timeouts: flags(&self.timeouts),
        })
    }
}

/// The file's attributes (format version first: a file of another version
/// may lack everything else), checked: the environment asked for, the macro
/// action recorded for Point and Car, one action column for discrete actions.
fn read_info(
    f: &hdf5::File,
    path: &Path,
    expected_env: Option<&str>,
) -> Result<DatasetInfo, HistoryError> {
    let err = |p| HistoryError::new(path, p);
    let malformed = |what: String| err(Problem::Malformed(what));
    let version = f
        .attr("format_version")
        .and_then(|a| a.read_scalar::<u32>())
        .map_err(|e| malformed(format!("attribute format_version: {e}")))?;
    if version != FORMAT_VERSION {
        return Err(err(Problem::WrongVersion {
            found: version,
            expected: FORMAT_VERSION,
        }));
    }
    let text_attr = |name: &str| -> Result<String, HistoryError> {
        f.attr(name)
            .and_then(|a| a.read_scalar::<VarLenUnicode>())
            .map(|s| s.as_str().to_string())
            .map_err(|e| malformed(format!("attribute {name}: {e}")))
    };
    let u64_attr = |name: &str| -> Result<u64, HistoryError> {
        f.attr(name)
            .and_then(|a| a.read_scalar::<u64>())
            .map_err(|e| malformed(format!("attribute {name}: {e}")))
    };
    let env = text_attr("env")?;
    if let Some(expected) = expected_env
        && env != expected
    {
        return Err(err(Problem::WrongEnv {
            found: env,
            expected: expected.to_string(),
        }));
    }
    let action_n = u64_attr("action_n")? as usize;
    let optional_u64 = |name: &str| -> Result<Option<u64>, HistoryError> {
        match f.attr(name) {
            Ok(a) => a
                .read_scalar::<u64>()
                .map(Some)
                .map_err(|e| malformed(format!("attribute {name}: {e}"))),
            Err(_) => Ok(None),
        }
    };
    // Absent in files from before it was recorded: refused for Point and Car.
    let physics_steps_per_action = optional_u64("physics_steps_per_action")?.unwrap_or(0) as usize;
    // Absent in files from before sharding: the file's own histories.
    let histories = f
        .dataset("cost_limit")
        .map(|d| d.shape().first().copied().unwrap_or(0))
        .unwrap_or(0);
    let has_physics = env
        .parse::<EnvName>()
        .ok()
        .and_then(|e| e.physics_steps_per_action(None))
        .is_some();
    if has_physics && physics_steps_per_action == 0 {
        return Err(err(Problem::UnrecordedMacroAction { env }));
    }
    let info = DatasetInfo {
        env,
        config: text_attr("config")?,
        seed: u64_attr("seed")?,
        obs_dim: u64_attr("obs_dim")? as usize,
        action_dim: u64_attr("action_dim")? as usize,
        action_n: (action_n > 0).then_some(action_n),
        grid_size: u64_attr("grid_size")? as usize,
        physics_steps_per_action: (physics_steps_per_action > 0)
            .then_some(physics_steps_per_action),
        grid_histories: optional_u64("grid_histories")?.map_or(histories, |g| g as usize),
        shard: match (optional_u64("shard_index")?, optional_u64("shard_count")?) {
            (None, None) => None,
            (Some(index), Some(count)) if index < count => Some(Shard {
                index: index as usize,
                count: count as usize,
            }),
            (i, c) => {
                return Err(malformed(format!(
                    "shard_index {i:?} and shard_count {c:?} do not name one part of a grid"
                )));
            }
        },
    };
    if info.action_n.is_some() && info.action_dim != 1 {
        return Err(malformed(format!(
            "a discrete action space (action_n {action_n}) needs action_dim 1, got {}",
            info.action_dim
        )));
    }
    Ok(info)
}
