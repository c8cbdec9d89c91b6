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
        Self::create_in(root, base, "--out")
    }

    /// [`RunDir::create_named`] under `root`, the folder the option `flag`
    /// (`--out`, `--fork`) named: its refusals name that option.
    fn create_in(root: &Path, base: &str, flag: &str) -> Result<Self, CheckpointError> {
        refuse_nesting(root, flag)?;
        // `--out` at a file, a device or a symlink loop: say so, not EEXIST.
        safety_envs::output::create_folder(root).map_err(|e| CheckpointError::Invalid {
            path: PathBuf::from(crate::guard::short_path(&e.path)),
            problem: e.problem,
            fix: format!("it is the {flag} folder"),
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

    /// Branches a new run under `out` (the `--fork` folder) from
    /// `from.checkpoint` of this run: a new run folder
    /// ([`RunDir::create`]'s, for `from.seed`) holding `from.config_toml`,
    /// the checkpoint (hard links where the file system allows: checkpoint
    /// files are never rewritten in place), the metrics up to the
    /// checkpoint's update, this run's `spec.json` if it has one, and
    /// `forked_from.txt` naming the origin. Before anything is made, a fork
    /// that would train nothing or whose checkpoints' paths would be longer
    /// than the system allows is refused; a failure while making it removes
    /// all it made, the folders of `out` it created included. Resuming the
    /// new run continues the branch.
    pub fn fork(&self, from: &ForkFrom, out: &Path) -> Result<Forked, CheckpointError> {
        let manifest = read_manifest(from.checkpoint)?;
        if from.total_updates <= manifest.updates {
            return Err(CheckpointError::Invalid {
                path: from.checkpoint.to_path_buf(),
                problem: format!(
                    "it has done {} updates and {} is {}, so the fork would train nothing",
                    manifest.updates, from.total_key, from.total_updates
                ),
                fix: format!(
                    "pass --set {}={} or more; nothing was forked",
                    from.total_key,
                    manifest.updates + 1
                ),
            });
        }
        let base = format!(
            "{}__{}__{}__{}",
            manifest.env,
            manifest.method,
            from.seed,
            utc_stamp()
        );
        let longest_file = manifest
            .files
            .keys()
            .map(String::as_str)
            .chain(["optimizer.safetensors", MANIFEST])
            .max_by_key(|n| n.len())
            .unwrap_or(MANIFEST);
        check_path_length(out, &base, from.total_updates, longest_file)?;
        let unreadable = unreadable_lines(&self.metrics_path(), from.metrics_key)?;
        let created = first_missing(out);
        let new = Self::create_in(out, &base, "--fork").inspect_err(|_| {
            remove_made_folders(out, created.as_deref());
        })?;
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
                let (src, to) = (from.checkpoint.join(name), step.join(name));
                if fs::hard_link(&src, &to).is_err() {
                    fs::copy(&src, &to).map_err(io(&to))?;
                }
            }
            for name in ["spec.json", "metrics.jsonl"] {
                let src = self.path.join(name);
                if src.is_file() {
                    let to = new.path.join(name);
                    fs::copy(&src, &to).map_err(io(&to))?;
                }
            }
            truncate_metrics(&new.metrics_path(), from.metrics_key, manifest.updates)?;
            new.write_config(from.config_toml)?;
            let note = new.path.join("forked_from.txt");
            fs::write(&note, format!("{}\n", from.checkpoint.display())).map_err(io(&note))?;
            Ok(step)
        })();
        match made {
            Ok(checkpoint) => Ok(Forked {
                metrics_len: fs::metadata(new.metrics_path()).map_or(0, |m| m.len()),
                run: new,
                checkpoint,
                created,
                unreadable_metrics: unreadable,
            }),
            Err(e) => {
                let _ = fs::remove_dir_all(&new.path);
                remove_made_folders(out, created.as_deref());
                Err(e)
            }
        }
    }
}

/// What [`RunDir::fork`] branches a new run from, and how the run counts.
pub struct ForkFrom<'a> {
    /// The `checkpoints/step_N` folder of the run forked.
    pub checkpoint: &'a Path,
    pub seed: u64,
    /// The fork's `config.toml`, the `--set`s applied and checked.
    pub config_toml: &'a str,
    /// The update counter of `metrics.jsonl` (EPPO `updates`, AD `update`).
    pub metrics_key: &'a str,
    /// The setting of the run's length (EPPO `total_updates`, AD `updates`)
    /// and its value in the fork.
    pub total_key: &'a str,
    pub total_updates: u64,
}

/// A run [`RunDir::fork`] made.
#[derive(Debug)]
pub struct Forked {
    pub run: RunDir,
    /// Its copy of the checkpoint forked.
    pub checkpoint: PathBuf,
    /// The first folder of the `--fork` path this fork created (`None`:
    /// it existed already).
    created: Option<PathBuf>,
    /// The size of its `metrics.jsonl` when made: larger once it trained.
    metrics_len: u64,
    /// Lines (from 1) of the origin's `metrics.jsonl` that are not metric
    /// records (not JSON, or without the update counter): the fork's
    /// metrics leave them out.
    pub unreadable_metrics: Vec<usize>,
}

impl Forked {
    /// Removes the fork when its start was refused before it trained: no
    /// checkpoint but the one forked and its metrics as they were made.
    /// Only what the fork wrote goes (the checkpoint's files by its
    /// manifest, the run's own files), then the folders it made, each only
    /// if empty. Returns whether it was removed.
    pub fn remove_if_untrained(&self) -> bool {
        let ck = self.run.path.join("checkpoints");
        let only_forked = fs::read_dir(&ck).is_ok_and(|entries| {
            entries
                .filter_map(Result::ok)
                .all(|e| e.path() == self.checkpoint)
        });
        let metrics_len = fs::metadata(self.run.metrics_path()).map_or(0, |m| m.len());
        if !only_forked || metrics_len != self.metrics_len {
            return false;
        }
        if super::writing::remove_checkpoint(&self.checkpoint).is_err() {
            return false;
        }
        for f in [
            ".lock",
            "config.toml",
            "spec.json",
            "metrics.jsonl",
            "forked_from.txt",
        ] {
            let _ = fs::remove_file(self.run.path.join(f));
        }
        let _ = fs::remove_dir(&ck);
        let removed = fs::remove_dir(&self.run.path).is_ok();
        if let Some(out) = self.run.path.parent() {
            remove_made_folders(out, self.created.as_deref());
        }
        removed
    }
}

/// Refuses a run under `root` (named `base`, or `base_N`) whose deepest
/// file, `checkpoints/.tmp_step_{last}/{file}`, would have a longer path
/// than the system allows (`PATH_MAX`), before anything is made: training
/// would fail at its first checkpoint. `root` is named shortened.
fn check_path_length(
    root: &Path,
    base: &str,
    last: u64,
    file: &str,
) -> Result<(), CheckpointError> {
    let deepest = root
        .join(format!("{base}_9999"))
        .join("checkpoints")
        .join(format!(".tmp_step_{last}"))
        .join(file);
    let limit = libc::PATH_MAX as usize - 1;
    let len = deepest.as_os_str().len();
    if len <= limit {
        return Ok(());
    }
    let room = limit - (len - root.as_os_str().len());
    Err(CheckpointError::Invalid {
        path: PathBuf::from(crate::guard::short_path(root)),
        problem: format!(
            "the fork's checkpoint files would lie at paths of up to {len} bytes \
             (…/{base}/checkpoints/.tmp_step_{last}/{file}), more than the {limit} this \
             system allows in a path"
        ),
        fix: format!(
            "pass --fork a folder whose path is at most {room} bytes long; nothing was forked"
        ),
    })
}

/// The line numbers (from 1) of `path`'s lines that are not metric records
/// with the counter `key`: not JSON (garbage, a line cut by a kill) or
/// without it. None when there is no file.
fn unreadable_lines(path: &Path, key: &str) -> Result<Vec<usize>, CheckpointError> {
    let text = match fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(io(path)(e)),
    };
    Ok(text
        .lines()
        .enumerate()
        .filter(|(_, line)| {
            serde_json::from_str::<serde_json::Value>(line)
                .ok()
                .and_then(|v| v.get(key)?.as_u64())
                .is_none()
        })
        .map(|(i, _)| i + 1)
        .collect())
}

/// The outermost folder of `dir` (or `dir` itself) that does not exist yet:
/// what creating `dir` makes.
fn first_missing(dir: &Path) -> Option<PathBuf> {
    dir.ancestors()
        .take_while(|a| !a.as_os_str().is_empty() && fs::symlink_metadata(a).is_err())
        .last()
        .map(Path::to_path_buf)
}

/// Removes the folders from `dir` up to `created` (a [`first_missing`] of
/// `dir`), innermost first, each only if it is empty.
fn remove_made_folders(dir: &Path, created: Option<&Path>) {
    let Some(created) = created else {
        return;
    };
    for a in dir.ancestors() {
        if fs::remove_dir(a).is_err() || a == created {
            return;
        }
    }
}

/// Refuses to create runs under `root` when `root` lies inside a run folder
/// or a checkpoint folder: pruning and resuming the outer run would remove
/// or mix the inner run's files.
fn refuse_nesting(root: &Path, flag: &str) -> Result<(), CheckpointError> {
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
                fix: format!("pass {flag} a folder outside every run folder"),
            });
        }
    }
    Ok(())
}
