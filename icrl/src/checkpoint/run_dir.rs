//! Run folders: created exclusively (never two runs in one), opened,
//! locked, found again to resume, forked from a checkpoint; and the
//! checkpoint folders they hold.

use std::fs;
use std::path::{Path, PathBuf};

use safety_envs::output::Lock;

use super::{CheckpointError, MANIFEST, io, read_manifest, truncate_metrics};

/// The checkpoint folders at `path`: `path` itself when it holds a
/// manifest, else a run folder's `checkpoints/step_N` (and `checkpoints/`
/// itself, where an early run wrote its only checkpoint), by N.
pub fn checkpoint_folders(path: &Path) -> Result<Vec<PathBuf>, CheckpointError> {
    if path.join(MANIFEST).is_file() {
        return Ok(vec![path.to_path_buf()]);
    }
    let run = RunDir::open(path)?;
    let flat = run.path.join("checkpoints");
    let mut folders: Vec<PathBuf> = flat
        .join(MANIFEST)
        .is_file()
        .then_some(flat)
        .into_iter()
        .collect();
    folders.extend(run.checkpoints()?.into_iter().map(|(_, p)| p));
    Ok(folders)
}

/// A run folder.
#[derive(Clone, Debug)]
pub struct RunDir {
    pub path: PathBuf,
}

/// UTC `YYYYMMDDTHHMMSS` of now (no time-zone crate needed).
fn utc_stamp() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs() as i64)
        .unwrap_or(0);
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}{m:02}{d:02}T{:02}{:02}{:02}",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

impl RunDir {
    /// Creates `root/{env}__{method}__{seed}__{time}/checkpoints/`. The run
    /// folder itself is made with `create_dir` (which fails if it exists), so
    /// two runs never share one: on a collision the next free suffix
    /// (`_2`, `_3`, ...) is taken.
    pub fn create(
        root: &Path,
        env: &str,
        method: &str,
        seed: u64,
    ) -> Result<Self, CheckpointError> {
        Self::create_named(root, &format!("{env}__{method}__{seed}__{}", utc_stamp()))
    }

    /// [`RunDir::create`] with the base name given.
    pub fn create_named(root: &Path, base: &str) -> Result<Self, CheckpointError> {
        refuse_nesting(root)?;
        // `--out` at a file, a device or a symlink loop: say so, not EEXIST.
        safety_envs::output::create_folder(root).map_err(|e| CheckpointError::Invalid {
            path: e.path,
            problem: e.problem,
            fix: "it is the --out folder".into(),
        })?;
        for n in 1..10_000u32 {
            let name = if n == 1 {
                base.to_string()
            } else {
                format!("{base}_{n}")
            };
            let path = root.join(name);
            match fs::create_dir(&path) {
                Ok(()) => {
                    let ck = path.join("checkpoints");
                    fs::create_dir(&ck).map_err(io(&ck))?;
                    return Ok(RunDir { path });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                Err(e) => return Err(io(&path)(e)),
            }
        }
        Err(CheckpointError::Invalid {
            path: root.join(base),
            problem: "9999 run folders of this name exist already".into(),
            fix: "clean up the runs folder or pass another --out".into(),
        })
    }

    /// Opens an existing run folder.
    pub fn open(path: &Path) -> Result<Self, CheckpointError> {
        if !path.join("checkpoints").is_dir() {
            return Err(CheckpointError::Invalid {
                path: path.to_path_buf(),
                problem: "not a run folder (no checkpoints/ inside)".into(),
                fix: "pass the runs/{env}__{method}__{seed}__{time} folder of an earlier run"
                    .into(),
            });
        }
        Ok(RunDir {
            path: path.to_path_buf(),
        })
    }

    /// Takes the run's lock (`RUN/.lock`, an OS file lock the kernel
    /// releases when the process dies): a second process training, resuming
    /// or extending the same run is refused with the first's pid. Hold the
    /// returned lock for as long as the run is written.
    pub fn lock(&self) -> Result<Lock, CheckpointError> {
        Lock::acquire(
            &self.path.join(".lock"),
            &format!("the run {}", self.path.display()),
            false,
        )
        .map_err(|e| CheckpointError::Invalid {
            path: e.path,
            problem: e.problem,
            fix: "one process per run".into(),
        })
    }

    /// Fails, naming what is gone, when the run folder or its
    /// `checkpoints/` folder disappeared (deleted or moved while the run
    /// was training): the run stops instead of writing into a new, partial
    /// folder.
    pub fn check_present(&self) -> Result<(), CheckpointError> {
        for (what, path) in [
            ("the run folder", self.path.clone()),
            ("its checkpoints/ folder", self.path.join("checkpoints")),
        ] {
            if fs::symlink_metadata(&path).is_err() {
                return Err(CheckpointError::Invalid {
                    path,
                    problem: format!("{what} is gone (deleted or moved while the run was training)"),
                    fix: "training stopped; restore the folder from a copy and resume it, or start a new run"
                        .into(),
                });
            }
        }
        Ok(())
    }

    /// Removes a run folder that a refused or failed start left without a
    /// checkpoint: only the files a run writes (`.lock`, `config.toml`,
    /// `spec.json`, `metrics.jsonl`, the empty `checkpoints/`), then the
    /// folder if that emptied it. A run with any checkpoint is kept.
    pub fn remove_if_unused(&self) {
        let ck = self.path.join("checkpoints");
        if fs::read_dir(&ck).map_or(true, |mut d| d.next().is_some()) {
            return;
        }
        for f in [".lock", "config.toml", "spec.json", "metrics.jsonl"] {
            let _ = fs::remove_file(self.path.join(f));
        }
        let _ = fs::remove_dir(&ck);
        let _ = fs::remove_dir(&self.path);
    }

    /// The run of `env` and `method` under `root` that has trained furthest:
    /// among the folders `{env}__{method}__*` with a checkpoint, the one whose
    /// latest checkpoint has the most updates, with that checkpoint and its
    /// update count. `None` when there is none (or no `root`). A requeued
    /// job array task finds its own run this way (`pretrain --resume-in-out`).
    pub fn furthest_in(
        root: &Path,
        env: &str,
        method: &str,
    ) -> Result<Option<(Self, PathBuf, u64)>, CheckpointError> {
        let Ok(entries) = fs::read_dir(root) else {
            return Ok(None);
        };
        let prefix = format!("{env}__{method}__");
        let mut best: Option<(Self, PathBuf, u64)> = None;
        for entry in entries {
            let entry = entry.map_err(io(root))?;
            let run = RunDir { path: entry.path() };
            if !entry.file_name().to_string_lossy().starts_with(&prefix)
                || !run.path.join("checkpoints").is_dir()
            {
                continue;
            }
            let Some(ckpt) = run.latest_checkpoint()? else {
                continue;
            };
            let updates = ckpt
                .file_name()
                .and_then(|n| n.to_string_lossy().strip_prefix("step_")?.parse().ok())
                .unwrap_or(0);
            if best.as_ref().is_none_or(|(_, _, u)| updates > *u) {
                best = Some((run, ckpt, updates));
            }
        }
        Ok(best)
    }

    /// Resolves `--resume PATH`: a run folder (its latest checkpoint) or one
    /// `checkpoints/step_N` folder. Returns the run and the checkpoint folder.
    pub fn resolve_resume(path: &Path) -> Result<(Self, PathBuf), CheckpointError> {
        if path.join(MANIFEST).is_file() {
            let run_path =
                path.parent()
                    .and_then(Path::parent)
                    .ok_or_else(|| CheckpointError::Invalid {
                        path: path.to_path_buf(),
                        problem: "checkpoint folder outside a run folder".into(),
                        fix: "pass the run folder instead".into(),
                    })?;
            return Ok((RunDir::open(run_path)?, path.to_path_buf()));
        }
        let run = RunDir::open(path)?;
        let ckpt = run
            .latest_checkpoint()?
            .ok_or_else(|| CheckpointError::Invalid {
                path: run.path.join("checkpoints"),
                problem: "no checkpoint has been written yet".into(),
                fix: "there is nothing to resume or evaluate: let the run reach its first \
                      checkpoint (checkpoint_every), or start a new run"
                    .into(),
            })?;
        Ok((run, ckpt))
    }

    /// Refuses `--resume` of a checkpoint of another method or environment
    /// before its config is read, naming the flags that resume it (the
    /// manifest's `method` and `env`; its checksums are verified later).
    pub fn check_resume_flags(
        checkpoint: &Path,
        method: &str,
        env: &str,
    ) -> Result<(), CheckpointError> {
        let Some(m) = fs::read_to_string(checkpoint.join(MANIFEST))
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        else {
            return Ok(());
        };
        let (Some(found_method), Some(found_env)) = (m["method"].as_str(), m["env"].as_str())
        else {
            return Ok(());
        };
        if found_method != method || found_env != env {
            return Err(CheckpointError::Invalid {
                path: checkpoint.to_path_buf(),
                problem: format!(
                    "this is a {found_env} {} run, not {env} {}",
                    found_method.to_uppercase(),
                    method.to_uppercase()
                ),
                fix: format!("resume it with --env {found_env} --method {found_method}"),
            });
        }
        Ok(())
    }

    /// `config.toml` of the run.
    pub fn config_path(&self) -> PathBuf {
        self.path.join("config.toml")
    }

    /// `metrics.jsonl` of the run.
    pub fn metrics_path(&self) -> PathBuf {
        self.path.join("metrics.jsonl")
    }

    /// Writes the resolved configuration.
    pub fn write_config(&self, toml_text: &str) -> Result<(), CheckpointError> {
        let path = self.config_path();
        // Never through a link: a resume with --set would rewrite whatever
        // file the link names.
        if fs::symlink_metadata(&path).is_ok_and(|m| m.file_type().is_symlink()) {
            return Err(CheckpointError::Invalid {
                path,
                problem: "it is a symbolic link, which icrl never writes through".into(),
                fix: "replace the link by the run's own config.toml (a copy of what it names)"
                    .into(),
            });
        }
        fs::write(&path, toml_text).map_err(io(&path))
    }

    /// The `checkpoints/step_N` folders, by N.
    pub(super) fn checkpoints(&self) -> Result<Vec<(u64, PathBuf)>, CheckpointError> {
        let dir = self.path.join("checkpoints");
        let mut steps = Vec::new();
        for entry in fs::read_dir(&dir).map_err(io(&dir))? {
            let entry = entry.map_err(io(&dir))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if let Some(n) = name
                .strip_prefix("step_")
                .and_then(|s| s.parse::<u64>().ok())
            {
                steps.push((n, entry.path()));
            }
        }
        steps.sort();
        Ok(steps)
    }

    /// The `checkpoints/step_N` folder with the largest N, if any.
    pub fn latest_checkpoint(&self) -> Result<Option<PathBuf>, CheckpointError> {
        Ok(self.checkpoints()?.pop().map(|(_, p)| p))
    }

    /// Refuses to continue a run in place from `checkpoint` when the run has
    /// a later one: its metrics and checkpoints would then hold two
    /// histories. A branch from an earlier checkpoint is a new run
    /// (`pretrain --fork`, [`RunDir::fork`]).
    pub fn check_latest(&self, checkpoint: &Path) -> Result<(), CheckpointError> {
        match self.latest_checkpoint()? {
            Some(latest) if latest != checkpoint => Err(CheckpointError::Invalid {
                path: checkpoint.to_path_buf(),
                problem: format!(
                    "the run's latest checkpoint is {}: continuing this run from an earlier one \
                     would mix two histories in one run folder",
                    latest.display()
                ),
                fix: format!(
                    "resume {} to continue from the latest, or branch a new run from this \
                     checkpoint with --fork DIR (it may change settings with --set)",
                    self.path.display()
                ),
            }),
            _ => Ok(()),
        }
    }

    /// Branches a new run under `out` from `checkpoint` of this run: a new
    /// run folder ([`RunDir::create`]'s, for `seed`) holding
    /// `config_toml`, the checkpoint (hard links where the file system
    /// allows: checkpoint files are never rewritten in place), the metrics
    /// up to the checkpoint's update (`metrics_key`), this run's `spec.json`
    /// if it has one, and `forked_from.txt` naming the origin. Returns the
    /// new run and its checkpoint folder; resuming that continues the branch.
    pub fn fork(
        &self,
        checkpoint: &Path,
        out: &Path,
        seed: u64,
        config_toml: &str,
        metrics_key: &str,
    ) -> Result<(Self, PathBuf), CheckpointError> {
        let manifest = read_manifest(checkpoint)?;
        let new = Self::create(out, &manifest.env, &manifest.method, seed)?;
        let made = (|| {
            let step = new
                .path
                .join("checkpoints")
                .join(format!("step_{}", manifest.updates));
            fs::create_dir(&step).map_err(io(&step))?;
            // Manifest names are plain file names; anything else is not a
            // checkpoint's file.
            let names = manifest.files.keys().map(String::as_str).chain([MANIFEST]);
            for name in names.filter(|n| Path::new(n).components().count() == 1) {
                let (from, to) = (checkpoint.join(name), step.join(name));
                if fs::hard_link(&from, &to).is_err() {
                    fs::copy(&from, &to).map_err(io(&from))?;
                }
            }
            for name in ["spec.json", "metrics.jsonl"] {
                let from = self.path.join(name);
                if from.is_file() {
                    fs::copy(&from, new.path.join(name)).map_err(io(&from))?;
                }
            }
            truncate_metrics(&new.metrics_path(), metrics_key, manifest.updates)?;
            new.write_config(config_toml)?;
            let note = new.path.join("forked_from.txt");
            fs::write(
                &note,
                format!(
                    "{}
",
                    checkpoint.display()
                ),
            )
            .map_err(io(&note))?;
            Ok(step)
        })();
        match made {
            Ok(step) => Ok((new, step)),
            Err(e) => {
                let _ = fs::remove_dir_all(&new.path);
                Err(e)
            }
        }
    }
}

/// Refuses to create runs under `root` when `root` lies inside a run folder
/// or a checkpoint folder: pruning and resuming the outer run would remove
/// or mix the inner run's files.
fn refuse_nesting(root: &Path) -> Result<(), CheckpointError> {
    let Some(existing) = root
        .ancestors()
        .find(|a| !a.as_os_str().is_empty() && a.exists())
    else {
        return Ok(());
    };
    let Ok(existing) = existing.canonicalize() else {
        return Ok(());
    };
    for a in existing.ancestors() {
        let is_checkpoint = a.join(MANIFEST).is_file();
        let is_run = a.join("checkpoints").is_dir()
            && (a.join("config.toml").is_file() || a.join("spec.json").is_file());
        if is_checkpoint || is_run {
            return Err(CheckpointError::Invalid {
                path: root.to_path_buf(),
                problem: format!(
                    "it lies inside the {} {}; a run nested in another would be pruned or mixed with its files",
                    if is_checkpoint { "checkpoint" } else { "run" },
                    a.display()
                ),
                fix: "pass an --out folder outside every run folder".into(),
            });
        }
    }
    Ok(())
}
