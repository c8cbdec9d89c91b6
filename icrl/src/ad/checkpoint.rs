//! AD checkpoints: `checkpoints/step_N` folders written and loaded (weights,
//! Adam's moments, `state.json`), the model manifest they record, and the
//! config comparison a resume reports.

use std::fs;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use tch::nn;

use super::config::{AdConfig, AdSpec};
use super::{AdError, io_err};
use crate::checkpoint::{CheckpointError, RunDir, read_manifest, write_part};
use crate::optim::Adam;

#[derive(Debug, Serialize, Deserialize)]
pub(super) struct TrainState {
    pub(super) update: usize,
    pub(super) samples: u64,
}

pub(super) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), AdError> {
    let tmp = crate::data::histories::temp_path(path);
    fs::write(&tmp, bytes).map_err(|e| io_err(&tmp, e))?;
    fs::rename(&tmp, path).map_err(|e| io_err(path, e))
}

/// The model shape recorded in each checkpoint's manifest.
pub(super) fn model_manifest(cfg: &AdConfig, spec: &AdSpec) -> serde_json::Value {
    serde_json::json!({
        "transformer": cfg.model,
        "token_dim": spec.token_dim(),
        "obs_dim": spec.obs_dim,
        "act_dim": spec.action_dim,
        "n_actions": spec.discrete.then_some(spec.action_dim),
    })
}

/// Writes `checkpoints/step_{update}` as one atomic folder (weights, Adam's
/// moments, `state.json`, with the manifest's sizes and SHA-256s), keeping the
/// newest `keep_checkpoints`.
pub(super) fn save_checkpoint(
    run: &RunDir,
    cfg: &AdConfig,
    spec: &AdSpec,
    vs: &nn::VarStore,
    opt: &Adam,
    state: &TrainState,
) -> Result<PathBuf, AdError> {
    let dir = run.write_checkpoint(
        state.update as u64,
        "ad",
        &spec.env,
        spec.physics_steps_per_action,
        model_manifest(cfg, spec),
        cfg.retention(),
        |dir| {
            let text = |e: tch::TchError| e.to_string();
            write_part(dir, "model.safetensors", |p| vs.save(p).map_err(text))?;
            write_part(dir, "adam.safetensors", |p| opt.save(p).map_err(text))?;
            write_part(dir, "state.json", |p| {
                let json = serde_json::to_vec_pretty(state).map_err(|e| e.to_string())?;
                fs::write(p, json).map_err(|e| e.to_string())
            })
        },
    )?;
    Ok(dir)
}

/// The fields of two configs that differ, as `name: old -> new`.
pub(super) fn config_diff(old: &AdConfig, new: &AdConfig) -> Vec<String> {
    let (a, b) = (
        serde_json::to_value(old).unwrap_or_default(),
        serde_json::to_value(new).unwrap_or_default(),
    );
    let mut out = Vec::new();
    fn walk(prefix: &str, a: &serde_json::Value, b: &serde_json::Value, out: &mut Vec<String>) {
        match (a, b) {
            (serde_json::Value::Object(x), serde_json::Value::Object(y)) => {
                let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
                let null = serde_json::Value::Null;
                for k in keys {
                    let name = if prefix.is_empty() {
                        k.clone()
                    } else {
                        format!("{prefix}.{k}")
                    };
                    walk(
                        &name,
                        x.get(k).unwrap_or(&null),
                        y.get(k).unwrap_or(&null),
                        out,
                    );
                }
            }
            _ if a != b => out.push(format!("{prefix}: {a} -> {b}")),
            _ => {}
        }
    }
    walk("", &a, &b, &mut out);
    out
}

/// Loads `ckpt` (a `checkpoints/step_N` folder, verified against its
/// manifest) into the model and optimizer; returns its counters.
pub(super) fn load_checkpoint_into(
    ckpt: &Path,
    cfg: &AdConfig,
    spec: &AdSpec,
    vs: &mut nn::VarStore,
    opt: &mut Adam,
) -> Result<TrainState, AdError> {
    let manifest = read_manifest(ckpt)?;
    manifest.check_compatible(
        ckpt,
        "ad",
        &spec.env,
        spec.physics_steps_per_action,
        &model_manifest(cfg, spec),
    )?;
    let bad = |file: &str, e: String| {
        AdError::Checkpoint(CheckpointError::Invalid {
            path: ckpt.join(file),
            problem: e,
            fix: "resume from an earlier checkpoints/step_N folder, or start a new run".into(),
        })
    };
    vs.load(ckpt.join("model.safetensors"))
        .map_err(|e| bad("model.safetensors", e.to_string()))?;
    if let Some((name, n)) = crate::guard::non_finite_variable(vs) {
        return Err(bad(
            "model.safetensors",
            format!("weight {name} holds {n} NaN or infinite values"),
        ));
    }
    opt.load(&ckpt.join("adam.safetensors"))
        .map_err(|e| bad("adam.safetensors", e))?;
    let text = fs::read_to_string(ckpt.join("state.json"))
        .map_err(|e| bad("state.json", e.to_string()))?;
    serde_json::from_str(&text).map_err(|e| bad("state.json", e.to_string()))
}
