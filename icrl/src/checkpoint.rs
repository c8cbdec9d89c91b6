//! Run folders, checkpoints and metrics, shared by every learner.
//!
//! A run lives in `runs/{env}__{method}__{seed}__{time}/`:
//! - `config.toml`: the fully resolved configuration of the run;
//! - `metrics.jsonl`: one JSON object per line, always with `env_steps` and
//!   `updates`, plus the learner's fixed metric names (EPPO: `episodic_return`,
//!   `episodic_cost`, `lambda`, `losses/*`, `charts/*`; see `eppo/mod.rs`);
//! - `checkpoints/step_N/`: one folder per checkpoint, written atomically
//!   (filled under `checkpoints/.tmp_step_N/`, then renamed), holding the
//!   learner's files and a `manifest.json` naming the method, environment,
//!   the environment's macro action (Point and Car: physics steps per agent
//!   action), model shape, format version, and the size and SHA-256 of every
//!   file, so a truncated, altered or foreign checkpoint is refused with an
//!   error that names the file. A Point or Car checkpoint that does not
//!   record its macro action was written when an agent action was 5 physics
//!   steps (before 2026-11-30) and is refused: its policy acts on a time
//!   scale 10x shorter than today's environments.
//!
//! Run folders are created exclusively: two runs started in the same second
//! with the same env, method and seed get `..._{time}` and `..._{time}_2`,
//! never one shared folder.

use std::collections::BTreeMap;
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use safety_envs::output::Lock;
use safety_envs::{EnvName, OLD_PHYSICS_STEPS_PER_ACTION, PHYSICS_STEPS_PER_ACTION};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use thiserror::Error;

/// Version of the checkpoint layout; bumped when files or their meaning change.
pub const FORMAT_VERSION: u32 = 1;

/// Name of the manifest inside a checkpoint folder.
pub const MANIFEST: &str = "manifest.json";

/// Bytes a checkpoint holds besides its tensors (manifest, state, config), allowed for
/// in the disk room checked before training.
pub const CHECKPOINT_SLACK: u64 = 64 * 1024;

/// A run folder or checkpoint that cannot be written or used.
#[derive(Debug, Error)]
pub enum CheckpointError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {problem}; {fix}")]
    Invalid {
        path: PathBuf,
        problem: String,
        fix: String,
    },
    /// A checkpoint that could not be written: nothing of it is left, and
    /// the last good one is named.
    #[error(
        "{path}: writing this checkpoint failed: {problem}; nothing of it was kept. {last_good}"
    )]
    WriteFailed {
        path: PathBuf,
        problem: String,
        last_good: String,
    },
    #[error("{path}: checkpoint is for {what} {found:?}, this run has {expected:?}; {fix}")]
    Mismatch {
        path: PathBuf,
        what: String,
        found: String,
        expected: String,
        fix: String,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> CheckpointError + '_ {
    move |source| CheckpointError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// What a checkpoint says about itself.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// [`FORMAT_VERSION`] at writing time.
    pub format_version: u32,
    /// Learner, e.g. `eppo`, `ad`.
    pub method: String,
    /// Environment, e.g. `darkroom`.
    pub env: String,
    /// Point and Car: MuJoCo physics steps per agent action the policy was
    /// trained with (the macro action; default 5 Safety-Gymnasium steps x 10
    /// physics steps = 50). Absent for SafeDarkRoom, and in Point and Car
    /// checkpoints written before it was recorded, which [`read_manifest`]
    /// refuses.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub physics_steps_per_action: Option<usize>,
    /// Model shape and input/output sizes (learner-defined JSON object).
    pub model: serde_json::Value,
    /// Updates done when the checkpoint was written.
    pub updates: u64,
    /// Size in bytes of every other file in the folder.
    pub files: BTreeMap<String, u64>,
    /// SHA-256 (lower-case hex) of every other file in the folder. Empty in
    /// checkpoints written before checksums were recorded: those load with a
    /// warning that their bytes cannot be verified.
    #[serde(default)]
    pub sha256: BTreeMap<String, String>,
}

/// Records a new `max_len` in the manifest of a forked checkpoint whose model
/// has fixed sinusoidal positions (its weights do not depend on it). The
/// manifest is replaced, not written through: it is a hard link to the
/// original checkpoint's.
pub fn record_forked_max_len(step: &Path, max_len: i64) -> Result<(), CheckpointError> {
    let mut manifest = read_manifest(step)?;
    let path = step.join(MANIFEST);
    let len = manifest
        .model
        .get_mut("transformer")
        .and_then(|t| t.get_mut("max_len"))
        .ok_or_else(|| CheckpointError::Invalid {
            path: path.clone(),
            problem: "the manifest's model has no transformer.max_len".into(),
            fix: "fork with the original max_len, or start a new run".into(),
        })?;
    *len = max_len.into();
    let tmp = step.join(format!(".{MANIFEST}.tmp"));
    write_manifest(&tmp, &manifest)?;
    fs::rename(&tmp, &path).map_err(io(&path))
}

/// Removes `file` from the checkpoint folder `dir` and from its manifest,
/// after verifying the checkpoint: how a finished run sheds what only a
/// resume needs (the replay). The new manifest is published before the file
/// goes, so a stop between the two leaves a checkpoint that loads. Returns
/// the bytes freed; `None` when the manifest does not list `file`.
pub fn drop_file(dir: &Path, file: &str) -> Result<Option<u64>, CheckpointError> {
    let mut manifest = read_manifest(dir)?;
    let Some(size) = manifest.files.remove(file) else {
        return Ok(None);
    };
    manifest.sha256.remove(file);
    let path = dir.join(MANIFEST);
    // Replaced, not written through: a fork's manifest is a hard link.
    let tmp = dir.join(format!(".{MANIFEST}.tmp"));
    write_manifest(&tmp, &manifest)?;
    fs::rename(&tmp, &path).map_err(io(&path))?;
    let dropped = dir.join(file);
    fs::remove_file(&dropped).map_err(io(&dropped))?;
    Ok(Some(size))
}

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

/// Writes `manifest` to `path` and syncs it, so that a rename that
/// publishes it never publishes an empty file.
fn write_manifest(path: &Path, manifest: &Manifest) -> Result<(), CheckpointError> {
    let text = serde_json::to_string_pretty(manifest).map_err(|e| CheckpointError::Invalid {
        path: path.to_path_buf(),
        problem: e.to_string(),
        fix: "report this bug".into(),
    })?;
    let mut f = fs::File::create(path).map_err(io(path))?;
    f.write_all(text.as_bytes()).map_err(io(path))?;
    f.sync_all().map_err(io(path))
}

/// SHA-256 of a file, lower-case hex.
pub fn sha256_file(path: &Path) -> Result<String, CheckpointError> {
    let mut file = fs::File::open(path).map_err(io(path))?;
    let mut hasher = Sha256::new();
    std::io::copy(&mut file, &mut hasher).map_err(io(path))?;
    Ok(hasher
        .finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect())
}

impl Manifest {
    /// Refuses a checkpoint of another method, environment, macro action
    /// (`physics_steps_per_action`, resolved: see
    /// [`EnvName::physics_steps_per_action`]) or model shape.
    pub fn check_compatible(
        &self,
        dir: &Path,
        method: &str,
        env: &str,
        physics_steps_per_action: Option<usize>,
        model: &serde_json::Value,
    ) -> Result<(), CheckpointError> {
        if self.physics_steps_per_action != physics_steps_per_action {
            let show = |v: Option<usize>| v.map_or("none".to_string(), |n| n.to_string());
            return Err(CheckpointError::Mismatch {
                path: dir.join(MANIFEST),
                what: "physics steps per agent action".into(),
                found: show(self.physics_steps_per_action),
                expected: show(physics_steps_per_action),
                fix: format!(
                    "a policy trained with one macro action does not transfer to another; resume with \
                     physics_steps_per_action = {} (or start a new run)",
                    show(self.physics_steps_per_action)
                ),
            });
        }
        let fix = "resume with the same --env, method and model settings as the original run, or start a new run";
        // Name only the model fields that differ (`model.transformer.n_layers`).
        let mut found_model = Vec::new();
        let mut expected_model = Vec::new();
        diff_json(
            "model",
            &self.model,
            model,
            &mut found_model,
            &mut expected_model,
        );
        let pairs = [
            ("method", self.method.clone(), method.to_string()),
            ("env", self.env.clone(), env.to_string()),
            ("model", found_model.join(", "), expected_model.join(", ")),
        ];
        for (what, found, expected) in pairs {
            if found != expected {
                return Err(CheckpointError::Mismatch {
                    path: dir.join(MANIFEST),
                    what: what.into(),
                    found,
                    expected,
                    fix: fix.into(),
                });
            }
        }
        Ok(())
    }
}

/// Collects `path = value` for every leaf where `a` and `b` differ.
fn diff_json(
    path: &str,
    a: &serde_json::Value,
    b: &serde_json::Value,
    fa: &mut Vec<String>,
    fb: &mut Vec<String>,
) {
    match (a, b) {
        (serde_json::Value::Object(x), serde_json::Value::Object(y)) => {
            let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
            for k in keys {
                let null = serde_json::Value::Null;
                let (va, vb) = (x.get(k).unwrap_or(&null), y.get(k).unwrap_or(&null));
                diff_json(&format!("{path}.{k}"), va, vb, fa, fb);
            }
        }
        _ if a != b => {
            fa.push(format!("{path} = {a}"));
            fb.push(format!("{path} = {b}"));
        }
        _ => {}
    }
}

/// Reads and verifies a checkpoint folder's manifest: the format version,
/// that every listed file exists with the recorded size (catches truncation)
/// and, where recorded, its SHA-256 (catches altered bytes).
pub fn read_manifest(dir: &Path) -> Result<Manifest, CheckpointError> {
    let path = dir.join(MANIFEST);
    let text = fs::read_to_string(&path).map_err(|e| CheckpointError::Invalid {
        path: path.clone(),
        problem: format!("cannot read the manifest ({e})"),
        fix: "point --resume at a run folder or a checkpoints/step_N folder written by `icrl pretrain`".into(),
    })?;
    let manifest: Manifest = serde_json::from_str(&text).map_err(|e| CheckpointError::Invalid {
        path: path.clone(),
        problem: format!("malformed manifest ({e})"),
        fix: "the checkpoint is damaged: resume from an earlier checkpoints/step_N folder".into(),
    })?;
    if manifest.format_version != FORMAT_VERSION {
        return Err(CheckpointError::Invalid {
            path,
            problem: format!(
                "format version {} (this build reads {FORMAT_VERSION})",
                manifest.format_version
            ),
            fix: "use the icrl version that wrote it, or start a new run".into(),
        });
    }
    let physics = manifest
        .env
        .parse::<EnvName>()
        .ok()
        .and_then(|env| env.physics_steps_per_action(None));
    if physics.is_some() && manifest.physics_steps_per_action.is_none() {
        return Err(CheckpointError::Invalid {
            path,
            problem: format!(
                "this {} checkpoint does not record its macro action, so it was written when an agent \
                 action was {OLD_PHYSICS_STEPS_PER_ACTION} physics steps (before 2026-11-30); the \
                 environments now take {PHYSICS_STEPS_PER_ACTION} (5 Safety-Gymnasium steps x 10 \
                 physics steps), a 10x longer action its policy was never trained on",
                manifest.env
            ),
            fix: "retrain it with the current defaults (`icrl pretrain`)".into(),
        });
    }
    for (name, &size) in &manifest.files {
        let file = dir.join(name);
        let got = fs::metadata(&file)
            .map(|m| m.len())
            .map_err(|e| CheckpointError::Invalid {
                path: file.clone(),
                problem: format!("listed in the manifest but unreadable ({e})"),
                fix:
                    "the checkpoint is incomplete: resume from an earlier checkpoints/step_N folder"
                        .into(),
            })?;
        if got != size {
            return Err(CheckpointError::Invalid {
                path: file,
                problem: format!(
                    "{got} bytes, the manifest records {size} (truncated or replaced)"
                ),
                fix: "resume from an earlier checkpoints/step_N folder".into(),
            });
        }
    }
    if manifest.sha256.is_empty() {
        eprintln!(
            "warning: {}: written before checkpoints recorded checksums; its bytes cannot be verified",
            path.display()
        );
    } else {
        for name in manifest.files.keys() {
            let file = dir.join(name);
            let Some(want) = manifest.sha256.get(name) else {
                return Err(CheckpointError::Invalid {
                    path: path.clone(),
                    problem: format!("no SHA-256 recorded for {name}"),
                    fix:
                        "the manifest is damaged: resume from an earlier checkpoints/step_N folder"
                            .into(),
                });
            };
            let got = sha256_file(&file)?;
            if got != *want {
                return Err(CheckpointError::Invalid {
                    path: file,
                    problem: format!(
                        "SHA-256 {got} differs from the manifest's {want} (the bytes were altered or damaged)"
                    ),
                    fix: "resume from (or evaluate) an earlier checkpoints/step_N folder".into(),
                });
            }
        }
    }
    Ok(manifest)
}

/// Which checkpoints a run keeps: the newest `newest` (0: all) and, besides
/// them, every one written at a multiple of `every` updates (0: none), the
/// run's history to evaluate or fork from after its latest checkpoints have
/// moved past a good stretch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Retention {
    pub newest: usize,
    pub every: u64,
}

impl Retention {
    fn kept_for_history(&self, updates: u64) -> bool {
        self.every > 0 && updates.is_multiple_of(self.every)
    }
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
    fn checkpoints(&self) -> Result<Vec<(u64, PathBuf)>, CheckpointError> {
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

    /// Makes and removes the deepest path a checkpoint at update `last` will
    /// write, so that a path the file system refuses (too long, a read-only
    /// or full folder) fails before training, not after it.
    pub fn probe_checkpoint_path(&self, last: u64) -> Result<(), CheckpointError> {
        let tmp = self
            .path
            .join("checkpoints")
            .join(format!(".tmp_step_{last}"));
        let file = tmp.join("optimizer.safetensors");
        let probe = fs::create_dir_all(&tmp)
            .map_err(io(&tmp))
            .and_then(|()| fs::write(&file, [0u8; 4096]).map_err(io(&file)));
        let _ = fs::remove_dir_all(&tmp);
        probe
    }

    /// Refuses to train when the run's disk lacks room for the checkpoints
    /// still to come: each about `checkpoint_bytes`; with the newest
    /// `keep.newest` kept (0: all), that many + 1 are on disk at once while
    /// the newest is written, plus those kept for history; one is written
    /// every `every` of the `updates_left` updates and at the end.
    pub fn check_room(
        &self,
        checkpoint_bytes: u64,
        keep: Retention,
        updates_left: u64,
        every: u64,
    ) -> Result<(), CheckpointError> {
        let future = updates_left / every.max(1) + 1;
        let dir = self.path.join("checkpoints");
        let existing = self.checkpoints()?;
        let recent = existing
            .iter()
            .filter(|(updates, _)| !keep.kept_for_history(*updates))
            .count() as u64;
        let more = if keep.newest == 0 {
            future
        } else {
            let history = match keep.every {
                0 => 0,
                n => updates_left / n,
            };
            (keep.newest as u64 + 1)
                .saturating_sub(recent)
                .clamp(1, future)
                + history
        };
        let need = more.saturating_mul(checkpoint_bytes);
        safety_envs::output::check_room(
            &dir,
            need,
            &format!(
                "{more} more checkpoint{} of about {} each (keep_checkpoints = {}, keep_every = {})",
                if more == 1 { "" } else { "s" },
                safety_envs::output::human_bytes(checkpoint_bytes as f64),
                keep.newest,
                keep.every
            ),
            "free space on it, lower keep_checkpoints, raise keep_every, or pass another --out",
        )
        .map_err(|e| CheckpointError::Invalid {
            path: e.path,
            problem: e.problem,
            fix: "nothing was trained".into(),
        })
    }

    /// Writes `checkpoints/step_{updates}` atomically: `write` fills a
    /// temporary folder, the manifest (with every file's size) is added, and
    /// the folder is renamed into place. Prunes to what `keep` retains.
    #[allow(clippy::too_many_arguments)]
    pub fn write_checkpoint(
        &self,
        updates: u64,
        method: &str,
        env: &str,
        physics_steps_per_action: Option<usize>,
        model: serde_json::Value,
        keep: Retention,
        write: impl FnOnce(&Path) -> Result<(), CheckpointError>,
    ) -> Result<PathBuf, CheckpointError> {
        self.check_present()?;
        let root = self.path.join("checkpoints");
        let tmp = root.join(format!(".tmp_step_{updates}"));
        let dest = root.join(format!("step_{updates}"));
        if tmp.exists() {
            fs::remove_dir_all(&tmp).map_err(io(&tmp))?;
        }
        // A failed write leaves nothing behind (a full disk is not filled
        // further by a partial `.tmp_step_N`) and names the last good one.
        let failed = |e: CheckpointError| {
            let _ = fs::remove_dir_all(&tmp);
            CheckpointError::WriteFailed {
                path: dest.clone(),
                problem: safety_envs::output::full_disk(&root).unwrap_or_else(|| e.to_string()),
                last_good: last_good(&self.latest_checkpoint().ok().flatten(), "room on its disk"),
            }
        };
        // Not create_dir_all: a run folder deleted meanwhile is not remade.
        fs::create_dir(&tmp).map_err(io(&tmp)).map_err(failed)?;
        self.fill_checkpoint(
            &tmp,
            &dest,
            updates,
            method,
            env,
            physics_steps_per_action,
            model,
            write,
        )
        .map_err(failed)?;
        self.prune(keep)?;
        Ok(dest)
    }

    /// [`RunDir::write_checkpoint`]'s body: the files, the manifest, the
    /// rename into place.
    #[allow(clippy::too_many_arguments)]
    fn fill_checkpoint(
        &self,
        tmp: &Path,
        dest: &Path,
        updates: u64,
        method: &str,
        env: &str,
        physics_steps_per_action: Option<usize>,
        model: serde_json::Value,
        write: impl FnOnce(&Path) -> Result<(), CheckpointError>,
    ) -> Result<(), CheckpointError> {
        write(tmp)?;
        let mut files = BTreeMap::new();
        let mut sha256 = BTreeMap::new();
        for entry in fs::read_dir(tmp).map_err(io(tmp))? {
            let entry = entry.map_err(io(tmp))?;
            let len = entry.metadata().map_err(io(&entry.path()))?.len();
            let name = entry.file_name().to_string_lossy().into_owned();
            sha256.insert(name.clone(), sha256_file(&entry.path())?);
            files.insert(name, len);
        }
        let manifest = Manifest {
            format_version: FORMAT_VERSION,
            method: method.into(),
            env: env.into(),
            physics_steps_per_action,
            model,
            updates,
            files,
            sha256,
        };
        write_manifest(&tmp.join(MANIFEST), &manifest)?;
        if dest.exists() {
            remove_checkpoint(dest)?;
        }
        fs::rename(tmp, dest).map_err(io(dest))
    }

    /// Removes the checkpoints `keep` does not retain.
    fn prune(&self, keep: Retention) -> Result<(), CheckpointError> {
        if keep.newest == 0 {
            return Ok(());
        }
        let steps = self.checkpoints()?;
        let older = steps.len().saturating_sub(keep.newest);
        for (updates, p) in steps.into_iter().take(older) {
            if !keep.kept_for_history(updates) {
                remove_checkpoint(&p)?;
            }
        }
        Ok(())
    }
}

/// Removes one checkpoint: only the files its manifest lists and the
/// manifest, then the folder if that left it empty. A `step_N` folder
/// without a readable manifest is not a checkpoint and is left alone, and
/// so is anything else in it (a user's notes, a nested folder), with a
/// warning naming what was kept.
fn remove_checkpoint(dir: &Path) -> Result<(), CheckpointError> {
    let manifest = fs::read_to_string(dir.join(MANIFEST))
        .ok()
        .and_then(|t| serde_json::from_str::<Manifest>(&t).ok());
    let Some(manifest) = manifest else {
        eprintln!(
            "warning: {} has no readable {MANIFEST}: not a checkpoint, so it was not removed",
            dir.display()
        );
        return Ok(());
    };
    for name in manifest.files.keys() {
        // Manifest names are plain file names; anything else is not ours.
        if Path::new(name).components().count() != 1 {
            continue;
        }
        let p = dir.join(name);
        if fs::symlink_metadata(&p).is_ok_and(|m| m.is_file()) {
            fs::remove_file(&p).map_err(io(&p))?;
        }
    }
    let m = dir.join(MANIFEST);
    fs::remove_file(&m).map_err(io(&m))?;
    if fs::remove_dir(dir).is_err() {
        eprintln!(
            "warning: {} holds files that are not part of the checkpoint: the checkpoint's files were \
             removed, the rest was kept",
            dir.display()
        );
    }
    Ok(())
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

/// The sentence of a "training stopped" error that names the last good
/// checkpoint (or says there is none yet) and the fix.
pub fn last_good(checkpoint: &Option<PathBuf>, fix: &str) -> String {
    match checkpoint {
        Some(c) => format!(
            "The last good checkpoint is {} (resume from it with --resume and {fix})",
            c.display()
        ),
        None => format!("No checkpoint had been written yet: start again and {fix}"),
    }
}

/// Appends one JSON object per line to `metrics.jsonl`.
#[derive(Debug)]
pub struct MetricsWriter {
    path: PathBuf,
    file: fs::File,
}

/// Drops the records of `metrics.jsonl` written after the checkpoint a run
/// resumes from (those whose `key`, e.g. `updates`, exceeds `updates`), so no
/// update is counted twice. Lines that are not JSON (a line cut by a kill)
/// are dropped too. Returns how many lines were dropped.
pub fn truncate_metrics(path: &Path, key: &str, updates: u64) -> Result<usize, CheckpointError> {
    let text = match fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
        Err(e) => return Err(io(path)(e)),
    };
    let mut kept = String::with_capacity(text.len());
    let mut dropped = 0;
    for line in text.lines() {
        let keep = record_counter(line, key).is_some_and(|u| u <= updates);
        if keep {
            kept.push_str(line);
            kept.push('\n');
        } else {
            dropped += 1;
        }
    }
    if dropped > 0 {
        let tmp = path.with_extension("jsonl.tmp");
        fs::write(&tmp, kept).map_err(io(&tmp))?;
        fs::rename(&tmp, path).map_err(io(path))?;
    }
    Ok(dropped)
}

/// The counter `key` (e.g. `updates`) of one `metrics.jsonl` line, if the
/// line is a JSON record that has it.
fn record_counter(line: &str, key: &str) -> Option<u64> {
    serde_json::from_str::<serde_json::Value>(line)
        .ok()?
        .get(key)?
        .as_u64()
}

/// The counter `key` of every record of a `metrics.jsonl`, in order (lines
/// that are not records with it are skipped): which updates a run logged.
pub fn recorded_counters(path: &Path, key: &str) -> Result<Vec<u64>, CheckpointError> {
    let text = fs::read_to_string(path).map_err(io(path))?;
    Ok(text
        .lines()
        .filter_map(|l| record_counter(l, key))
        .collect())
}

impl MetricsWriter {
    /// Opens (appending: a resumed run continues the same file).
    pub fn open(path: &Path) -> Result<Self, CheckpointError> {
        let file = fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .map_err(io(path))?;
        Ok(MetricsWriter {
            path: path.to_path_buf(),
            file,
        })
    }

    /// Writes one record and flushes it. Fails when `metrics.jsonl` is no
    /// longer the file opened (deleted or moved with its run folder): the
    /// records would go nowhere.
    pub fn write(&mut self, record: &serde_json::Value) -> Result<(), CheckpointError> {
        use std::os::unix::fs::MetadataExt;
        let same = match (self.file.metadata(), fs::metadata(&self.path)) {
            (Ok(a), Ok(b)) => a.ino() == b.ino() && a.dev() == b.dev(),
            _ => false,
        };
        if !same {
            return Err(CheckpointError::Invalid {
                path: self.path.clone(),
                problem: "the run's metrics file is gone (its run folder was deleted or moved while training)"
                    .into(),
                fix: "training stopped; restore the folder from a copy and resume it, or start a new run"
                    .into(),
            });
        }
        let line = record.to_string();
        writeln!(self.file, "{line}").map_err(io(&self.path))?;
        self.file.flush().map_err(io(&self.path))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The newest `n` checkpoints, no history.
    fn keep(n: usize) -> Retention {
        Retention {
            newest: n,
            every: 0,
        }
    }

    /// A checkpoint of one small file at `step`, pruned to what `keep` retains.
    fn write_small(run: &RunDir, step: u64, keep: Retention) -> Result<PathBuf, CheckpointError> {
        let write = |d: &Path| fs::write(d.join("w.bin"), [1u8; 8]).map_err(io(d));
        run.write_checkpoint(
            step,
            "test",
            "darkroom",
            None,
            serde_json::json!({}),
            keep,
            write,
        )
    }

    #[test]
    fn a_checkpoint_path_the_file_system_refuses_fails_before_training() {
        let base = std::env::temp_dir().join(format!("icrl-ckpt-probe-{}", std::process::id()));
        let run = RunDir::create_named(&base, "run").unwrap();
        run.probe_checkpoint_path(7000).unwrap();
        assert!(
            !run.path.join("checkpoints/.tmp_step_7000").exists(),
            "the probe leaves nothing behind"
        );
        // A run folder whose checkpoints would pass the 4,095-byte path limit:
        // refused at the probe, naming the path, not after training.
        let mut root = base.join("deep");
        while root.as_os_str().len() < 4064 {
            let room = 4064 - root.as_os_str().len() - 1;
            root.push("x".repeat(room.clamp(1, 200)));
        }
        let deep = RunDir::create_named(&root, "run").unwrap();
        let e = deep.probe_checkpoint_path(7000).unwrap_err().to_string();
        assert!(
            e.contains("optimizer.safetensors") && e.contains("too long"),
            "{e}"
        );
        fs::remove_dir_all(base).unwrap();
    }

    #[test]
    fn a_failed_checkpoint_leaves_nothing_and_names_the_last_good_one() {
        let base = std::env::temp_dir().join(format!("icrl-ckpt-failed-{}", std::process::id()));
        let _ = fs::remove_dir_all(&base);
        let run = RunDir::create_named(&base, "run").unwrap();
        let good = write_small(&run, 10, keep(2)).unwrap();
        let e = run
            .write_checkpoint(
                20,
                "test",
                "darkroom",
                None,
                serde_json::json!({}),
                keep(2),
                |d| {
                    fs::write(d.join("w.bin"), [1u8; 8]).map_err(io(d))?;
                    Err(CheckpointError::Invalid {
                        path: d.join("optimizer.safetensors"),
                        problem: "No space left on device (os error 28)".into(),
                        fix: "check the disk".into(),
                    })
                },
            )
            .unwrap_err()
            .to_string();
        assert!(e.contains("step_20: writing this checkpoint failed"), "{e}");
        assert!(e.contains("No space left on device"), "{e}");
        assert!(
            e.contains(&format!("The last good checkpoint is {}", good.display())),
            "{e}"
        );
        assert!(
            !run.path.join("checkpoints/.tmp_step_20").exists(),
            "nothing left behind"
        );
        assert!(!run.path.join("checkpoints/step_20").exists());
        // Room for the checkpoints still to come is checked before training.
        run.check_room(1 << 20, keep(2), 9900, 100).unwrap();
        let e = run
            .check_room(u64::MAX / 4, keep(2), 9900, 100)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("free, but 2 more checkpoints of about")
                && e.contains("keep_checkpoints = 2"),
            "{e}"
        );
        let e = run
            .check_room(u64::MAX / 4, keep(0), 0, 100)
            .unwrap_err()
            .to_string();
        assert!(e.contains("1 more checkpoint of about"), "{e}");
        fs::remove_dir_all(base).unwrap();
    }

    #[test]
    fn atomic_checkpoint_and_truncation_detected() {
        let root = std::env::temp_dir().join(format!("icrl-ckpt-{}", std::process::id()));
        let run = RunDir::create(&root, "darkroom", "test", 3).unwrap();
        let model = serde_json::json!({"d_model": 8});
        for step in [5, 10, 15] {
            run.write_checkpoint(
                step,
                "test",
                "darkroom",
                None,
                model.clone(),
                keep(2),
                |dir| fs::write(dir.join("w.bin"), vec![1u8; 100]).map_err(io(dir)),
            )
            .unwrap();
        }
        let latest = run.latest_checkpoint().unwrap().unwrap();
        assert!(latest.ends_with("step_15"));
        assert!(!run.path.join("checkpoints/step_5").exists(), "pruned to 2");
        let m = read_manifest(&latest).unwrap();
        m.check_compatible(&latest, "test", "darkroom", None, &model)
            .unwrap();
        let err = m
            .check_compatible(&latest, "test", "point", None, &model)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("\"darkroom\"") && err.contains("\"point\""),
            "{err}"
        );
        let other = serde_json::json!({"d_model": 16});
        let err = m
            .check_compatible(&latest, "test", "darkroom", None, &other)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("model.d_model = 8") && err.contains("model.d_model = 16"),
            "{err}"
        );
        // Truncate a file: the error names it.
        fs::write(latest.join("w.bin"), vec![1u8; 10]).unwrap();
        let err = read_manifest(&latest).unwrap_err().to_string();
        assert!(err.contains("w.bin") && err.contains("10 bytes"), "{err}");
        let (_, ckpt) = RunDir::resolve_resume(&run.path).unwrap();
        assert_eq!(ckpt, latest);
        assert!(RunDir::resolve_resume(&root).is_err());
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn macro_action_is_recorded_checked_and_old_checkpoints_refused() {
        let root = std::env::temp_dir().join(format!("icrl-ckpt-macro-{}", std::process::id()));
        let run = RunDir::create(&root, "point", "test", 1).unwrap();
        let model = serde_json::json!({"d_model": 8});
        let dir = run
            .write_checkpoint(
                1,
                "test",
                "point",
                Some(50),
                model.clone(),
                keep(0),
                |dir| fs::write(dir.join("w.bin"), [0u8; 4]).map_err(io(dir)),
            )
            .unwrap();
        let m = read_manifest(&dir).unwrap();
        assert_eq!(m.physics_steps_per_action, Some(50));
        m.check_compatible(&dir, "test", "point", Some(50), &model)
            .unwrap();
        let err = m
            .check_compatible(&dir, "test", "point", Some(5), &model)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("physics steps per agent action") && err.contains("\"50\""),
            "{err}"
        );
        // A manifest from before the macro action was recorded: the field is
        // absent. Point and Car refuse it, saying why; DarkRoom has no physics.
        let path = dir.join(MANIFEST);
        let mut json: serde_json::Value =
            serde_json::from_str(&fs::read_to_string(&path).unwrap()).unwrap();
        json.as_object_mut()
            .unwrap()
            .remove("physics_steps_per_action");
        fs::write(&path, json.to_string()).unwrap();
        let err = read_manifest(&dir).unwrap_err().to_string();
        assert!(
            err.contains("does not record its macro action")
                && err.contains("5 physics steps")
                && err.contains("retrain"),
            "{err}"
        );
        json["env"] = "darkroom".into();
        fs::write(&path, json.to_string()).unwrap();
        assert_eq!(read_manifest(&dir).unwrap().physics_steps_per_action, None);
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn a_dropped_file_leaves_a_checkpoint_that_verifies_and_a_damaged_one_is_left_alone() {
        let root = std::env::temp_dir().join(format!("icrl-ckpt-drop-{}", std::process::id()));
        let run = RunDir::create(&root, "darkroom", "test", 3).unwrap();
        let write = |updates| {
            run.write_checkpoint(
                updates,
                "test",
                "darkroom",
                None,
                serde_json::json!({}),
                keep(0),
                |dir| {
                    fs::write(dir.join("model.safetensors"), vec![7u8; 256]).map_err(io(dir))?;
                    fs::write(dir.join("replay.safetensors"), vec![1u8; 1000]).map_err(io(dir))
                },
            )
            .unwrap()
        };
        let (first, second) = (write(1), write(2));
        assert_eq!(
            checkpoint_folders(&run.path).unwrap(),
            vec![first.clone(), second.clone()]
        );
        assert_eq!(checkpoint_folders(&second).unwrap(), vec![second.clone()]);
        assert_eq!(drop_file(&first, "replay.safetensors").unwrap(), Some(1000));
        assert!(!first.join("replay.safetensors").exists());
        let m = read_manifest(&first).unwrap();
        assert!(!m.files.contains_key("replay.safetensors"));
        assert!(!m.sha256.contains_key("replay.safetensors"));
        assert_eq!(m.files["model.safetensors"], 256, "the rest is kept");
        assert_eq!(drop_file(&first, "replay.safetensors").unwrap(), None);
        // A damaged checkpoint is refused before anything is removed.
        let mut bytes = fs::read(second.join("model.safetensors")).unwrap();
        bytes[0] ^= 0xff;
        fs::write(second.join("model.safetensors"), &bytes).unwrap();
        let err = drop_file(&second, "replay.safetensors").unwrap_err();
        assert!(err.to_string().contains("SHA-256"), "{err}");
        assert!(second.join("replay.safetensors").exists());
        assert!(read_manifest(&second).is_err(), "its manifest is as it was");
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn altered_bytes_of_the_same_size_are_caught_by_the_checksum() {
        let root = std::env::temp_dir().join(format!("icrl-ckpt-sha-{}", std::process::id()));
        let run = RunDir::create(&root, "darkroom", "test", 3).unwrap();
        let dir = run
            .write_checkpoint(
                1,
                "test",
                "darkroom",
                None,
                serde_json::json!({}),
                keep(0),
                |dir| fs::write(dir.join("model.safetensors"), vec![7u8; 256]).map_err(io(dir)),
            )
            .unwrap();
        let m = read_manifest(&dir).unwrap();
        assert_eq!(m.sha256.len(), 1);
        assert_eq!(
            m.sha256["model.safetensors"],
            sha256_file(&dir.join("model.safetensors")).unwrap()
        );
        // Same size, one byte replaced: the size check passes, the hash does not.
        let mut bytes = fs::read(dir.join("model.safetensors")).unwrap();
        bytes[100] ^= 0xff;
        fs::write(dir.join("model.safetensors"), &bytes).unwrap();
        let err = read_manifest(&dir).unwrap_err().to_string();
        assert!(
            err.contains("model.safetensors") && err.contains("SHA-256") && err.contains("altered"),
            "{err}"
        );
        // A manifest that lists a file without its checksum is damaged.
        let mut m2 = m.clone();
        m2.files.insert("extra.bin".into(), 0);
        fs::write(dir.join("extra.bin"), b"").unwrap();
        fs::write(dir.join(MANIFEST), serde_json::to_string(&m2).unwrap()).unwrap();
        let err = read_manifest(&dir).unwrap_err().to_string();
        assert!(err.contains("no SHA-256 recorded for extra.bin"), "{err}");
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn racing_creators_never_share_a_run_folder() {
        let root = std::env::temp_dir().join(format!("icrl-ckpt-race-{}", std::process::id()));
        // Rounds, because a race shows only sometimes: each starts without
        // the --out folder, so the creators also race to make it.
        for _ in 0..20 {
            let _ = fs::remove_dir_all(&root);
            // Eight threads, released together, all asking for the same name.
            let barrier = std::sync::Arc::new(std::sync::Barrier::new(8));
            let handles: Vec<_> = (0..8)
                .map(|_| {
                    let (root, barrier) = (root.clone(), barrier.clone());
                    std::thread::spawn(move || {
                        barrier.wait();
                        RunDir::create_named(&root, "darkroom__eppo__0__20260101T000000")
                            .map(|run| run.path)
                            .map_err(|e| e.to_string())
                    })
                })
                .collect();
            let mut paths: Vec<PathBuf> = handles
                .into_iter()
                .map(|h| h.join().unwrap().unwrap())
                .collect();
            paths.sort();
            paths.dedup();
            assert_eq!(
                paths.len(),
                8,
                "every creator got its own folder: {paths:?}"
            );
            assert!(paths.contains(&root.join("darkroom__eppo__0__20260101T000000")));
            assert!(paths.contains(&root.join("darkroom__eppo__0__20260101T000000_8")));
            assert!(paths.iter().all(|p| p.join("checkpoints").is_dir()));
        }
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn resuming_drops_metrics_written_after_the_checkpoint() {
        let dir = std::env::temp_dir().join(format!("icrl-ckpt-metrics-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let path = dir.join("metrics.jsonl");
        let mut w = MetricsWriter::open(&path).unwrap();
        for u in [10u64, 20, 30, 40] {
            w.write(&serde_json::json!({"updates": u, "env_steps": u * 7}))
                .unwrap();
        }
        drop(w);
        // A line cut by a kill at the end.
        let mut f = fs::OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(b"{\"updates\": 5").unwrap();
        drop(f);
        assert_eq!(truncate_metrics(&path, "updates", 20).unwrap(), 3);
        assert_eq!(recorded_counters(&path, "updates").unwrap(), vec![10, 20]);
        assert_eq!(truncate_metrics(&path, "updates", 20).unwrap(), 0);
        assert_eq!(
            truncate_metrics(&dir.join("none.jsonl"), "updates", 0).unwrap(),
            0
        );
        fs::remove_dir_all(&dir).unwrap();
    }

    /// A run's config.toml that is a symbolic link (to a user's file) is
    /// refused by name on write, and the file it names keeps its contents.
    #[test]
    fn a_config_is_never_written_through_a_link() {
        let root = std::env::temp_dir().join(format!("icrl-ckpt-config-{}", std::process::id()));
        let _ = fs::remove_dir_all(&root);
        let run = RunDir::create(&root, "darkroom", "test", 1).unwrap();
        let theirs = root.join("notes.toml");
        fs::write(&theirs, "mine = true").unwrap();
        std::os::unix::fs::symlink(&theirs, run.config_path()).unwrap();
        let err = run.write_config("x = 1").unwrap_err().to_string();
        assert!(err.contains("symbolic link"), "{err}");
        assert_eq!(fs::read_to_string(&theirs).unwrap(), "mine = true");
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn pruning_removes_only_checkpoint_files_and_runs_do_not_nest() {
        let root = std::env::temp_dir().join(format!("icrl-ckpt-prune-{}", std::process::id()));
        let _ = fs::remove_dir_all(&root);
        let run = RunDir::create(&root, "darkroom", "test", 1).unwrap();
        run.write_config("x = 1").unwrap();
        let write = |step: u64| write_small(&run, step, keep(2)).unwrap();
        let first = write(10);
        // A user's notes in a checkpoint, and a run nested inside one: refused.
        fs::write(first.join("notes.txt"), "mine").unwrap();
        let e = RunDir::create(&first, "darkroom", "test", 2)
            .unwrap_err()
            .to_string();
        assert!(e.contains("lies inside the checkpoint"), "{e}");
        let e = RunDir::create(&first.join("model.bin"), "darkroom", "test", 2)
            .unwrap_err()
            .to_string();
        assert!(e.contains("lies inside the checkpoint"), "{e}");
        let file = root.join("a-file");
        fs::write(&file, "x").unwrap();
        let e = RunDir::create(&file, "darkroom", "test", 2)
            .unwrap_err()
            .to_string();
        assert!(e.contains("not a folder") && e.contains("--out"), "{e}");
        let e = RunDir::create(&run.path.join("sub"), "darkroom", "test", 2)
            .unwrap_err()
            .to_string();
        assert!(e.contains("lies inside the run"), "{e}");
        // A step_N folder that is no checkpoint.
        let fake = run.path.join("checkpoints/step_1");
        fs::create_dir(&fake).unwrap();
        fs::write(fake.join("data.txt"), "x").unwrap();
        write(20);
        write(30);
        assert_eq!(fs::read_to_string(first.join("notes.txt")).unwrap(), "mine");
        assert!(!first.join("w.bin").exists() && !first.join(MANIFEST).exists());
        assert!(fake.join("data.txt").exists(), "not a checkpoint: kept");
        assert!(run.path.join("checkpoints/step_20").is_dir());
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn checkpoints_at_multiples_of_keep_every_outlive_pruning() {
        let root = std::env::temp_dir().join(format!("icrl-ckpt-every-{}", std::process::id()));
        let _ = fs::remove_dir_all(&root);
        let run = RunDir::create(&root, "darkroom", "test", 1).unwrap();
        let history = Retention {
            newest: 2,
            every: 100,
        };
        for step in (50..=400).step_by(50) {
            write_small(&run, step, history).unwrap();
        }
        let kept: Vec<u64> = run.checkpoints().unwrap().iter().map(|c| c.0).collect();
        assert_eq!(
            kept,
            vec![100, 200, 300, 350, 400],
            "history + the newest 2"
        );
        // The room asked for counts the history still to come: the newest 2
        // and the one being written, less 350 already there, and the
        // 1000 / 100 kept on the way.
        let e = run
            .check_room(u64::MAX / 64, history, 1000, 50)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("12 more checkpoints") && e.contains("keep_every = 100"),
            "{e}"
        );
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn a_run_whose_folder_disappears_stops_instead_of_remaking_it() {
        let root = std::env::temp_dir().join(format!("icrl-ckpt-gone-{}", std::process::id()));
        let _ = fs::remove_dir_all(&root);
        let run = RunDir::create(&root, "darkroom", "test", 1).unwrap();
        run.write_config("x = 1").unwrap();
        let _lock = run.lock().unwrap();
        let e = run.lock().unwrap_err().to_string();
        assert!(e.contains(&format!("pid {}", std::process::id())), "{e}");
        let mut metrics = MetricsWriter::open(&run.metrics_path()).unwrap();
        metrics.write(&serde_json::json!({"updates": 1})).unwrap();
        fs::remove_dir_all(&run.path).unwrap();
        let e = metrics
            .write(&serde_json::json!({"updates": 2}))
            .unwrap_err()
            .to_string();
        assert!(e.contains("metrics file is gone"), "{e}");
        let e = write_small(&run, 5, keep(0)).unwrap_err().to_string();
        assert!(e.contains("the run folder is gone"), "{e}");
        assert!(!run.path.exists(), "the run folder is not remade");
        fs::remove_dir_all(&root).unwrap();
    }
}
