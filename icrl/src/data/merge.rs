//! One dataset from many files: `icrl dataset merge --out ALL.h5 SHARD...`.
//!
//! The shards of one grid (`icrl dataset --shard I/N`) become one file that
//! holds no histories of its own: each of its datasets is an HDF5 virtual
//! dataset (VDS) whose rows map, shard by shard in index order, onto the same
//! dataset in each shard, so libhdf5, and through it h5py and the AD learner,
//! reads it as one file with the layout of [`crate::data::histories`]. Its
//! attributes are the shards' less `shard_index` and `shard_count`, plus
//! `shards`.
//!
//! # The checksum of a view
//! A merged file's own bytes are only the mapping, so its user block seals
//! those bytes as any history file's does, and its `shards` attribute (JSON)
//! lists every shard's file name, relative to the merged file's folder (where
//! libhdf5 looks for it), with the SHA-256 the shard's own seal held at
//! merging. Reading a merged file checks its seal, then each shard's seal
//! against the shard's bytes and against the recorded SHA-256, before libhdf5
//! reads through to any shard: a shard that is missing, damaged, or made
//! again since the merge is an error naming it, never data read through a
//! stale view (libhdf5 fills a source it cannot open with zeros, silently).
//! Move the merged file and its shards together.

use std::path::{Path, PathBuf};

use safety_envs::output::{self, Existing};

use crate::data::histories::{
    self, DatasetInfo, HistoryError, Problem, SHARDS_ATTR, ShardRecord, USER_BLOCK, read_histories,
    verify_seal,
};

/// What `merge` wrote.
#[derive(Clone, Debug)]
pub struct MergeReport {
    pub out: PathBuf,
    pub shards: usize,
    pub histories: usize,
    pub steps: usize,
    pub bytes: u64,
}

/// One checked shard, ready to be mapped.
struct Part {
    path: PathBuf,
    record: ShardRecord,
    info: DatasetInfo,
    steps: usize,
    histories: usize,
    obstacles: usize,
}

/// The generating configuration (JSON) without the dataset settings `keys`;
/// unchanged, byte for byte, when it has none of them.
fn config_without(config: &str, keys: &[&str]) -> String {
    let Ok(mut v) = serde_json::from_str::<serde_json::Value>(config) else {
        return config.to_string();
    };
    let removed = v
        .get_mut("dataset")
        .and_then(|d| d.as_object_mut())
        .map_or(0, |d| {
            keys.iter().filter(|k| d.remove(**k).is_some()).count()
        });
    if removed > 0 {
        v.to_string()
    } else {
        config.to_string()
    }
}

/// Writes `out`: one file whose datasets are virtual datasets over `shards`,
/// all of one grid, every part exactly once. Refused: a file without a
/// checksum or whose bytes fail it, a file that is not a shard, shards of
/// another environment, macro action, seed or configuration, and parts
/// missing or given twice. `out` must sit in the shards' folder or above it,
/// so the shards are named relative to it.
pub fn merge(
    out: &Path,
    shards: &[PathBuf],
    existing: Existing,
) -> Result<MergeReport, HistoryError> {
    let base = check_out(out, shards, existing)?;
    let mut parts = shards
        .iter()
        .map(|path| read_part(path, &base))
        .collect::<Result<Vec<_>, _>>()?;
    check_one_grid(&parts)?;
    parts.sort_by_key(|p| p.info.shard.map_or(0, |s| s.index));
    check_every_part_once(out, &parts)?;

    let info = DatasetInfo {
        shard: None,
        config: config_without(&parts[0].info.config, &["shard"]),
        ..parts[0].info.clone()
    };
    let steps: usize = parts.iter().map(|p| p.steps).sum();
    let n_histories: usize = parts.iter().map(|p| p.histories).sum();
    output::write_file(out, existing, |tmp| {
        write_views(tmp, &info, &parts, steps, n_histories)
            .and_then(|()| {
                histories::seal(tmp).map_err(|e| hdf5::Error::from(e.to_string().as_str()))
            })
            .map_err(|e| histories::write_error(out, tmp, e))
    })?;
    Ok(MergeReport {
        out: out.to_path_buf(),
        shards: parts.len(),
        histories: n_histories,
        steps,
        bytes: std::fs::metadata(out).map_or(0, |m| m.len()),
    })
}

fn refuse(p: &Path, what: String) -> HistoryError {
    HistoryError::new(p, Problem::Invalid(what))
}

/// Checks that `out` can receive the merged file and is none of the
/// `shards`, and that there are shards; returns `out`'s folder, resolved,
/// which the shards' names are relative to.
fn check_out(out: &Path, shards: &[PathBuf], existing: Existing) -> Result<PathBuf, HistoryError> {
    // Whatever `--force` says: writing the view over a shard would replace
    // the shard's histories with a view of themselves.
    // The same file by any path (a link, another spelling): device and inode.
    let file_id = |p: &Path| {
        use std::os::unix::fs::MetadataExt;
        std::fs::metadata(p).ok().map(|m| (m.dev(), m.ino()))
    };
    if let Some(target) = file_id(out)
        && let Some(shard) = shards.iter().find(|s| file_id(s) == Some(target))
    {
        return Err(refuse(
            out,
            format!(
                "it is also the shard {} to merge: the merged file would replace it; give \
                 --out a new file",
                shard.display()
            ),
        ));
    }
    histories::check_output_path(out, existing)?;
    if shards.is_empty() {
        return Err(refuse(out, "no shards to merge".into()));
    }
    let base = out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    base.canonicalize()
        .map_err(|e| HistoryError::new(out, Problem::Output(e.to_string())))
}

/// Reads and checks one shard: its checksum (recorded for the merged file),
/// that it is a shard, and that it lies inside `base`.
fn read_part(path: &Path, base: &Path) -> Result<Part, HistoryError> {
    let sha256 = verify_seal(path)
        .map_err(|p| HistoryError::new(path, p))?
        .ok_or_else(|| {
            refuse(
                path,
                "it has no icrl checksum, so a merged file could not tell if it changed; \
                 make shards with `icrl dataset --shard I/N`"
                    .into(),
            )
        })?;
    let file = read_histories(path, None)?;
    let Some(shard) = file.info.shard else {
        return Err(refuse(
            path,
            "it is not a shard (no shard_index): merge the files of `icrl dataset --shard I/N`"
                .into(),
        ));
    };
    let relative = path
        .canonicalize()
        .ok()
        .and_then(|p| p.strip_prefix(base).ok().map(Path::to_path_buf))
        .ok_or_else(|| {
            refuse(
                path,
                format!(
                    "it is not inside {}, the merged file's folder; write the merged file \
                     beside the shards or in a folder above them",
                    base.display()
                ),
            )
        })?;
    Ok(Part {
        path: path.to_path_buf(),
        record: ShardRecord {
            file: relative.to_string_lossy().into_owned(),
            sha256,
        },
        steps: file.total_steps(),
        histories: file.histories.len(),
        obstacles: file.histories[0].task.obstacles.len(),
        info: DatasetInfo {
            shard: Some(shard),
            ..file.info
        },
    })
}

/// Refuses shards that are not parts of the first one's grid: another
/// environment, macro action, seed, sizes, grid, obstacles or generating
/// configuration.
fn check_one_grid(parts: &[Part]) -> Result<(), HistoryError> {
    let first = &parts[0];
    for p in &parts[1..] {
        let (a, b) = (&first.info, &p.info);
        let differs = [
            ("environment", a.env.clone(), b.env.clone()),
            (
                "physics steps per action",
                format!("{:?}", a.physics_steps_per_action),
                format!("{:?}", b.physics_steps_per_action),
            ),
            ("seed", a.seed.to_string(), b.seed.to_string()),
            (
                "observation and action sizes",
                format!("{} {} {:?}", a.obs_dim, a.action_dim, a.action_n),
                format!("{} {} {:?}", b.obs_dim, b.action_dim, b.action_n),
            ),
            (
                "grid (histories, shards)",
                format!("{} {:?}", a.grid_histories, a.shard.map(|s| s.count)),
                format!("{} {:?}", b.grid_histories, b.shard.map(|s| s.count)),
            ),
            (
                "obstacles per task",
                first.obstacles.to_string(),
                p.obstacles.to_string(),
            ),
            // What may differ between the shards of one grid: their part
            // and the worker threads.
            (
                "generating configuration",
                config_without(&a.config, &["shard", "threads"]),
                config_without(&b.config, &["shard", "threads"]),
            ),
        ];
        if let Some((what, x, y)) = differs.into_iter().find(|(_, x, y)| x != y) {
            return Err(refuse(
                &p.path,
                format!(
                    "its {what} ({y}) differs from {}'s ({x}): the shards are not parts of one dataset",
                    first.path.display()
                ),
            ));
        }
    }
    Ok(())
}

/// Refuses `parts` (sorted by shard index) where a part comes twice or is
/// missing.
fn check_every_part_once(out: &Path, parts: &[Part]) -> Result<(), HistoryError> {
    let count = parts[0].info.shard.map_or(1, |s| s.count);
    for w in parts.windows(2) {
        if w[0].info.shard == w[1].info.shard {
            return Err(refuse(
                &w[1].path,
                format!(
                    "it is shard {} again (also {}): parts overlap",
                    w[1].info.shard.map_or(String::new(), |s| s.to_string()),
                    w[0].path.display()
                ),
            ));
        }
    }
    let have: Vec<usize> = parts
        .iter()
        .filter_map(|p| p.info.shard.map(|s| s.index))
        .collect();
    let missing: Vec<String> = (0..count)
        .filter(|i| !have.contains(i))
        .map(|i| format!("{i}/{count}"))
        .collect();
    if !missing.is_empty() {
        return Err(refuse(
            out,
            format!(
                "shard {} missing: the merged file would lack those histories",
                missing.join(", ")
            ),
        ));
    }
    Ok(())
}

/// The merged file's datasets, each a virtual dataset whose rows are the
/// shards' rows in index order, and its attributes.
fn write_views(
    tmp: &Path,
    info: &DatasetInfo,
    parts: &[Part],
    steps: usize,
    n_histories: usize,
) -> hdf5::Result<()> {
    let f = hdf5::File::with_options()
        .with_fapl(|p| p.libver_v18())
        .with_fcpl(|p| p.userblock(USER_BLOCK as u64))
        .create(tmp)?;
    // The layout's datasets: name, float32 (else int64), rows are steps
    // (else histories), trailing dimensions.
    let (o, a, obstacles) = (info.obs_dim, info.action_dim, parts[0].obstacles);
    let layout: [(&str, bool, bool, Vec<usize>); 12] = [
        ("observations", true, true, vec![o]),
        ("next_observations", true, true, vec![o]),
        ("actions", true, true, vec![a]),
        ("rewards", true, true, vec![]),
        ("costs", true, true, vec![]),
        ("terminals", true, true, vec![]),
        ("timeouts", true, true, vec![]),
        ("history_id", false, true, vec![]),
        ("episode_id", false, true, vec![]),
        ("cost_limit", true, false, vec![]),
        ("task_goal", false, false, vec![2]),
        ("task_obstacles", false, false, vec![obstacles, 2]),
    ];
    for (name, is_f32, per_step, tail) in layout {
        let rows = |p: &Part| if per_step { p.steps } else { p.histories };
        let shape = |n: usize| [vec![n], tail.clone()].concat();
        let total = shape(if per_step { steps } else { n_histories });
        let mut builder = if is_f32 {
            f.new_dataset::<f32>()
        } else {
            f.new_dataset::<i64>()
        }
        .shape(total.clone());
        // The shard's rows land at `at..at + n` of the view's first axis.
        let mut at = 0;
        for p in parts {
            let n = rows(p);
            let rows_of_view: Vec<hdf5::SliceOrIndex> = std::iter::once((at..at + n).into())
                .chain(tail.iter().map(|_| (..).into()))
                .collect();
            builder = builder.virtual_map(
                &p.record.file,
                name,
                shape(n),
                ..,
                total.clone(),
                hdf5::Hyperslab::from(rows_of_view),
            );
            at += n;
        }
        builder.create(name)?;
    }
    histories::write_attrs(&f, info)?;
    let records: Vec<&ShardRecord> = parts.iter().map(|p| &p.record).collect();
    let json =
        serde_json::to_string(&records).map_err(|e| hdf5::Error::from(e.to_string().as_str()))?;
    histories::put_text(&f, SHARDS_ATTR, &json)?;
    f.flush()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::histories::tests::{h5py_check, tiny_file, tmpdir};
    use crate::data::histories::{HistoryFile, Shard, write_histories};

    /// `tiny_file(3)` written as three shards of one history each.
    fn write_shards(dir: &Path) -> Vec<PathBuf> {
        let whole = tiny_file(3);
        (0..3)
            .map(|i| {
                let path = dir.join(format!("shard{i}.h5"));
                let mut info = whole.info.clone();
                info.shard = Some(Shard { index: i, count: 3 });
                let part = HistoryFile {
                    info,
                    histories: vec![whole.histories[i].clone()],
                };
                write_histories(&path, &part).unwrap();
                path
            })
            .collect()
    }

    #[test]
    fn merged_shards_read_as_the_whole_file() {
        let dir = tmpdir("merge");
        let mut shards = write_shards(&dir);
        // Given in any order: the parts go in index order.
        shards.swap(0, 2);
        let out = dir.join("all.h5");
        let r = merge(&out, &shards, Existing::Refuse).unwrap();
        assert_eq!((r.shards, r.histories, r.steps), (3, 3, 15));
        assert_eq!(
            read_histories(&out, Some("darkroom")).unwrap(),
            tiny_file(3)
        );
        h5py_check(&out, true);
        // Read from another working directory: libhdf5 finds the shards
        // beside the merged file.
        let out_abs = out.canonicalize().unwrap();
        let here = std::env::current_dir().unwrap();
        std::env::set_current_dir("/").unwrap();
        let back = read_histories(&out_abs, None);
        std::env::set_current_dir(here).unwrap();
        assert_eq!(back.unwrap(), tiny_file(3));
        std::fs::remove_dir_all(dir).unwrap();
    }

    /// An output that is one of the shards (by any path to it: another
    /// spelling, a hard link) is refused, with or without force, and the
    /// shard keeps its histories.
    #[test]
    fn a_merge_never_writes_over_one_of_its_shards() {
        let dir = tmpdir("merge-self");
        let shards = write_shards(&dir);
        let before = std::fs::read(&shards[0]).unwrap();
        let hard_link = dir.join("alias.h5");
        std::fs::hard_link(&shards[0], &hard_link).unwrap();
        let aliases = [
            shards[0].clone(),
            dir.join(".").join(shards[0].file_name().unwrap()),
            hard_link,
        ];
        for out in aliases {
            for existing in [Existing::Refuse, Existing::Replace] {
                let err = merge(&out, &shards, existing).unwrap_err().to_string();
                assert!(err.contains("also the shard"), "{err}");
            }
        }
        assert_eq!(
            std::fs::read(&shards[0]).unwrap(),
            before,
            "the shard is untouched"
        );
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn shards_that_do_not_fit_together_are_refused() {
        let dir = tmpdir("merge-bad");
        let shards = write_shards(&dir);
        let out = dir.join("all.h5");
        let refused = |shards: &[PathBuf]| {
            merge(&out, shards, Existing::Refuse)
                .unwrap_err()
                .to_string()
        };
        let e = refused(&shards[..2]);
        assert!(e.contains("shard 2/3 missing"), "{e}");
        let e = refused(&[shards[0].clone(), shards[1].clone(), shards[1].clone()]);
        assert!(
            e.contains("shard 1/3 again") && e.contains("overlap"),
            "{e}"
        );
        // Another environment, another macro action.
        let whole = tiny_file(3);
        let other = dir.join("other.h5");
        for (change, what) in [
            (
                (|i: &mut DatasetInfo| {
                    i.env = "point".into();
                    i.physics_steps_per_action = Some(50);
                }) as fn(&mut DatasetInfo),
                "environment",
            ),
            (
                |i: &mut DatasetInfo| i.physics_steps_per_action = Some(5),
                "physics steps per action",
            ),
            (|i: &mut DatasetInfo| i.seed = 8, "seed"),
        ] {
            let mut info = whole.info.clone();
            info.shard = Some(Shard { index: 2, count: 3 });
            change(&mut info);
            let f = HistoryFile {
                info,
                histories: vec![whole.histories[2].clone()],
            };
            write_histories(&other, &f).unwrap();
            let e = refused(&[shards[0].clone(), shards[1].clone(), other.clone()]);
            assert!(
                e.contains(what) && e.contains("not parts of one dataset"),
                "{what}: {e}"
            );
        }
        // A whole (unsharded) file.
        write_histories(&other, &whole).unwrap();
        let e = refused(std::slice::from_ref(&other));
        assert!(e.contains("not a shard"), "{e}");
        // A damaged shard fails its checksum.
        let mut bytes = std::fs::read(&shards[1]).unwrap();
        let at = bytes.len() / 2;
        bytes[at] ^= 0x10;
        std::fs::write(&other, &bytes).unwrap();
        let e = refused(&[shards[0].clone(), other.clone(), shards[2].clone()]);
        assert!(e.contains("damaged"), "{e}");
        assert!(!out.exists());
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn a_merged_file_refuses_shards_missing_or_changed_since() {
        let dir = tmpdir("merge-after");
        let shards = write_shards(&dir);
        let out = dir.join("all.h5");
        merge(&out, &shards, Existing::Refuse).unwrap();
        // The shard made again with other values: its own seal is fine, the
        // merged file's record of it is not.
        let mut whole = tiny_file(3);
        whole.histories[1].rewards[0] = 0.5;
        let mut info = whole.info.clone();
        info.shard = Some(Shard { index: 1, count: 3 });
        let part = HistoryFile {
            info,
            histories: vec![whole.histories[1].clone()],
        };
        write_histories(&shards[1], &part).unwrap();
        let e = read_histories(&out, None).unwrap_err().to_string();
        assert!(
            e.contains("shard1.h5") && e.contains("not the file that was merged"),
            "{e}"
        );
        std::fs::remove_file(&shards[1]).unwrap();
        let e = read_histories(&out, None).unwrap_err().to_string();
        assert!(e.contains("shard1.h5 is missing"), "{e}");
        std::fs::remove_dir_all(dir).unwrap();
    }
}
