//! What a checkpoint says about itself (`manifest.json`): written with
//! every file's size and SHA-256, read back and verified, and rewritten for
//! a fork's `max_len` or a dropped file.

use std::collections::BTreeMap;
use std::fs;
use std::io::Write;
use std::path::Path;

use safety_envs::{EnvName, OLD_PHYSICS_STEPS_PER_ACTION, PHYSICS_STEPS_PER_ACTION};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use super::{CheckpointError, FORMAT_VERSION, MANIFEST, io};

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

/// Writes `manifest` to `path` and syncs it, so that a rename that
/// publishes it never publishes an empty file.
pub(super) fn write_manifest(path: &Path, manifest: &Manifest) -> Result<(), CheckpointError> {
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
