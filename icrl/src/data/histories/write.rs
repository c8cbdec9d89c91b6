//! The writer: checks, then one HDF5 file through `<out>.tmp`, every
//! array chunked, compressed and checksummed, the file sealed last.

use std::path::{Path, PathBuf};

use hdf5::types::VarLenUnicode;
use safety_envs::output::{self, Existing};

use super::{
    DatasetInfo, FORMAT_VERSION, History, HistoryError, HistoryFile, Problem, USER_BLOCK, seal,
};

/// Rows per chunk of the per-step arrays.
const CHUNK_ROWS: usize = 4096;
/// Deflate level (0-9): 4 is most of the gain for little time.
const DEFLATE_LEVEL: u8 = 4;

/// `<path>.tmp`: where the writer puts the file before renaming it.
pub fn temp_path(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(".tmp");
    PathBuf::from(s)
}

/// Checks, before any long work, that `path` can receive a history file:
/// it is not a folder, its folder exists, and it is free (or, with
/// [`Existing::Replace`], a regular file of ours: see
/// [`safety_envs::output::check_output`]).
pub fn check_output_path(path: &Path, existing: Existing) -> Result<(), HistoryError> {
    let err = |m: String| HistoryError::new(path, Problem::Output(m));
    if path.is_dir() {
        return Err(err(format!(
            "it is a folder; pass a file path such as {}",
            path.join("histories.h5").display()
        )));
    }
    output::check_output(path, existing).map_err(|e| err(e.problem))
}

/// Creates dataset `name` of `shape` (row-major `data`), chunked along the
/// first axis and deflate-compressed.
pub(super) fn put<T: hdf5::H5Type>(
    f: &hdf5::File,
    name: &str,
    data: &[T],
    shape: &[usize],
) -> hdf5::Result<()> {
    let mut chunk: Vec<usize> = shape.iter().map(|&d| d.max(1)).collect();
    chunk[0] = chunk[0].min(CHUNK_ROWS);
    f.new_dataset::<T>()
        .shape(shape.to_vec())
        .chunk(chunk)
        .deflate(DEFLATE_LEVEL)
        // A checksum of every chunk: damaged data is an error, not wrong values.
        .fletcher32()
        .create(name)?
        .write_raw(data)
}

/// Writes `histories` to `path` atomically ([`output::write_file`]: a
/// temporary file beside it, synced, then renamed), replacing a history
/// file there but never a device, link, folder or checkpoint file.
pub fn write_histories(path: &Path, file: &HistoryFile) -> Result<(), HistoryError> {
    write_histories_to(path, file, Existing::Replace)
}

/// [`write_histories`], refusing an existing `path` unless `existing` is
/// [`Existing::Replace`] (the `dataset` command's `--force`).
pub fn write_histories_to(
    path: &Path,
    file: &HistoryFile,
    existing: Existing,
) -> Result<(), HistoryError> {
    let err = |p| HistoryError::new(path, p);
    if file.histories.is_empty() {
        return Err(err(Problem::Empty("no histories to write".into())));
    }
    if let (Some(n), d) = (file.info.action_n, file.info.action_dim)
        && (n == 0 || d != 1)
    {
        return Err(err(Problem::Invalid(format!(
            "a discrete action space needs action_n > 0 and action_dim 1, got {n} and {d}"
        ))));
    }
    let ids = file.info.history_ids();
    if ids.len() != file.histories.len() || ids.end > file.info.grid_histories {
        return Err(err(Problem::Invalid(format!(
            "{} histories, but {} of a grid of {} holds {} ({ids:?})",
            file.histories.len(),
            file.info
                .shard
                .map_or("all".to_string(), |s| format!("shard {s}")),
            file.info.grid_histories,
            ids.len()
        ))));
    }
    let n_obstacles = file.histories[0].task.obstacles.len();
    for (i, h) in file.histories.iter().enumerate() {
        h.check(i, &file.info).map_err(err)?;
        if h.task.obstacles.len() != n_obstacles {
            return Err(err(Problem::Invalid(format!(
                "history {i} has {} obstacles, history 0 has {n_obstacles}",
                h.task.obstacles.len()
            ))));
        }
    }
    check_output_path(path, existing)?;
    output::write_file(path, existing, |tmp| {
        write_raw(tmp, file, n_obstacles)
            .and_then(|()| seal(tmp).map_err(|e| hdf5::Error::from(e.to_string().as_str())))
            .map_err(|e| write_error(path, tmp, e))
    })
}

/// An HDF5 error while writing `tmp`, the temporary file of `path`, as the
/// error to show: a full disk named as such (HDF5 words it as a short write
/// of 2^64 - 1 bytes, `18446744073709551615`), else HDF5's message. The
/// writer and `dataset merge` share it.
pub(crate) fn write_error(path: &Path, tmp: &Path, e: hdf5::Error) -> HistoryError {
    match output::full_disk(tmp) {
        Some(full) => HistoryError::new(path, Problem::Output(full)),
        None => HistoryError::new(path, Problem::Unreadable(e.to_string())),
    }
}

fn write_raw(tmp: &Path, file: &HistoryFile, n_obstacles: usize) -> hdf5::Result<()> {
    let info = &file.info;
    let n: usize = file.total_steps();
    let h = file.histories.len();
    let concat = |f: &dyn Fn(&History) -> &[f32]| -> Vec<f32> {
        file.histories
            .iter()
            .flat_map(|h| f(h).iter().copied())
            .collect()
    };
    let flag = |f: &dyn Fn(&History) -> &[bool]| -> Vec<f32> {
        file.histories
            .iter()
            .flat_map(|h| f(h).iter().map(|&b| if b { 1.0 } else { 0.0 }))
            .collect()
    };
    let observations = concat(&|h| &h.observations);
    let next_observations = concat(&|h| &h.next_observations);
    let actions = concat(&|h| &h.actions);
    let rewards = concat(&|h| &h.rewards);
    let costs = concat(&|h| &h.costs);
    let terminals = flag(&|h| &h.terminals);
    let timeouts = flag(&|h| &h.timeouts);
    let mut history_id = Vec::with_capacity(n);
    let mut episode_id = Vec::with_capacity(n);
    for (i, hist) in info.history_ids().zip(&file.histories) {
        for (e, r) in hist.episodes().into_iter().enumerate() {
            for _ in r {
                history_id.push(i as i64);
                episode_id.push(e as i64);
            }
        }
    }
    let cost_limit: Vec<f32> = file.histories.iter().map(|h| h.cost_limit).collect();
    let goals: Vec<i64> = file
        .histories
        .iter()
        .flat_map(|h| [h.task.goal.row as i64, h.task.goal.col as i64])
        .collect();
    let obstacles: Vec<i64> = file
        .histories
        .iter()
        .flat_map(|h| {
            h.task
                .obstacles
                .iter()
                .flat_map(|c| [c.row as i64, c.col as i64])
        })
        .collect();

    // The 1.8+ object formats carry checksums of their metadata, so a damaged
    // file is an error when read rather than a crash inside libhdf5.
    let f = hdf5::File::with_options()
        .with_fapl(|p| p.libver_v18())
        .with_fcpl(|p| p.userblock(USER_BLOCK as u64))
        .create(tmp)?;
    put(&f, "observations", &observations, &[n, info.obs_dim])?;
    put(
        &f,
        "next_observations",
        &next_observations,
        &[n, info.obs_dim],
    )?;
    put(&f, "actions", &actions, &[n, info.action_dim])?;
    put(&f, "rewards", &rewards, &[n])?;
    put(&f, "costs", &costs, &[n])?;
    put(&f, "terminals", &terminals, &[n])?;
    put(&f, "timeouts", &timeouts, &[n])?;
    put(&f, "history_id", &history_id, &[n])?;
    put(&f, "episode_id", &episode_id, &[n])?;
    put(&f, "cost_limit", &cost_limit, &[h])?;
    put(&f, "task_goal", &goals, &[h, 2])?;
    put(&f, "task_obstacles", &obstacles, &[h, n_obstacles, 2])?;

    write_attrs(&f, info)?;
    f.flush()?;
    Ok(())
}

/// A string attribute.
pub(crate) fn put_text(f: &hdf5::File, name: &str, value: &str) -> hdf5::Result<()> {
    let text = value
        .parse::<VarLenUnicode>()
        .map_err(|e| hdf5::Error::from(e.to_string().as_str()))?;
    f.new_attr::<VarLenUnicode>()
        .create(name)?
        .write_scalar(&text)
}

/// The file attributes of the layout, from `info`.
pub(crate) fn write_attrs(f: &hdf5::File, info: &DatasetInfo) -> hdf5::Result<()> {
    put_text(f, "env", &info.env)?;
    put_text(f, "config", &info.config)?;
    f.new_attr::<u64>()
        .create("seed")?
        .write_scalar(&info.seed)?;
    f.new_attr::<u32>()
        .create("format_version")?
        .write_scalar(&FORMAT_VERSION)?;
    for (name, v) in [
        ("obs_dim", info.obs_dim),
        ("action_dim", info.action_dim),
        ("action_n", info.action_n.unwrap_or(0)),
        ("grid_size", info.grid_size),
        (
            "physics_steps_per_action",
            info.physics_steps_per_action.unwrap_or(0),
        ),
        ("grid_histories", info.grid_histories),
    ]
    .into_iter()
    .chain(
        info.shard
            .into_iter()
            .flat_map(|s| [("shard_index", s.index), ("shard_count", s.count)]),
    ) {
        f.new_attr::<u64>()
            .create(name)?
            .write_scalar(&(v as u64))?;
    }
    Ok(())
}
