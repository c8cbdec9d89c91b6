//! Checkpoints written atomically (filled under `.tmp_step_N`, the
//! manifest added, renamed into place) and pruned to what a [`Retention`]
//! keeps; before training, the checks that they will fit (the deepest
//! path, the disk room).

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};

use super::manifest::write_manifest;
use super::{CheckpointError, FORMAT_VERSION, MANIFEST, Manifest, RunDir, io, sha256_file};

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

/// Writes one file `name` of a checkpoint being filled in `dir` (the
/// temporary folder [`RunDir::write_checkpoint`] hands its `write`), naming
/// the file in the error: what every learner's checkpoint is made of.
pub fn write_part(
    dir: &Path,
    name: &str,
    write: impl FnOnce(&Path) -> Result<(), String>,
) -> Result<(), CheckpointError> {
    let path = dir.join(name);
    write(&path).map_err(|problem| CheckpointError::Invalid {
        path,
        problem,
        fix: "check the disk".into(),
    })
}

impl RunDir {
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
                last_good: self.latest_checkpoint().ok().flatten(),
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

    /// A write to one of the run's files (`metrics.jsonl`) that failed
    /// while training, as the error that stops it: a full disk named as
    /// such, not the OS's account twice, and the run's latest checkpoint
    /// named as the one to resume from. Other errors pass through.
    pub fn stopped_writing(&self, e: CheckpointError) -> CheckpointError {
        match e {
            CheckpointError::Io { path, source } => {
                self.stopped_writing_with(path, source.to_string())
            }
            other => other,
        }
    }

    /// [`RunDir::stopped_writing`] of a failed write to `path` said as
    /// `problem`.
    pub fn stopped_writing_with(&self, path: PathBuf, problem: String) -> CheckpointError {
        CheckpointError::StoppedWriting {
            problem: safety_envs::output::full_disk(&self.path).unwrap_or(problem),
            path,
            last_good: self.latest_checkpoint().ok().flatten(),
        }
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
pub(super) fn remove_checkpoint(dir: &Path) -> Result<(), CheckpointError> {
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
