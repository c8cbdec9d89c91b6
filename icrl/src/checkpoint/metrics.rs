//! `metrics.jsonl`: one JSON record per line, appended as a run trains
//! and cut back to its checkpoint when it resumes.

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use super::{CheckpointError, RunDir, io};

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
        writeln!(self.file, "{line}")
            .and_then(|()| self.file.flush())
            .map_err(|e| self.stopped(e))
    }

    /// A failed write while training (a full disk): the error that stops
    /// the run, naming its latest checkpoint ([`RunDir::stopped_writing`]).
    fn stopped(&self, e: std::io::Error) -> CheckpointError {
        let run = RunDir {
            path: self.path.parent().unwrap_or(Path::new(".")).to_path_buf(),
        };
        run.stopped_writing_with(self.path.clone(), e.to_string())
    }
}
