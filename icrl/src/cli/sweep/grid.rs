//! The grid file: read, checked (every task's settings resolved, every
//! string kept inside its line of the script), expanded into array tasks.

use std::path::{Path, PathBuf};

use safety_envs::EnvName;
use serde::Deserialize;

use crate::eppo::EppoConfig;

use super::*;

/// Where the array runs (all optional).
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SlurmOptions {
    pub partition: Option<String>,
    pub account: Option<String>,
    /// Time limit per task (`HH:MM:SS`); default: from the updates per second.
    pub time: Option<String>,
    /// Measured speed of one run on the cluster; default: this project's
    /// measurement for the preset, where there is one.
    pub updates_per_second: Option<f64>,
    /// Default: the preset's threads.
    pub cpus_per_task: Option<usize>,
    /// Default: the learner's memory estimate, with room to spare.
    pub mem: Option<String>,
    /// Default: 1 for a `device = "cuda"` preset, else none.
    pub gpus: Option<usize>,
    /// More `#SBATCH` options, e.g. `"--qos=long"`.
    #[serde(default)]
    pub extra: Vec<String>,
    /// The `icrl` binary the tasks run; default: this one.
    pub icrl: Option<PathBuf>,
}

/// A grid file, as written.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SweepGrid {
    pub env: String,
    #[serde(default = "default_method")]
    pub method: String,
    #[serde(default = "default_preset")]
    pub preset: String,
    pub seeds: Vec<u64>,
    /// The sweep's folder: one `task_K` (or `seedN`) folder per array task.
    pub out: PathBuf,
    /// AD's learning histories.
    pub dataset: Option<PathBuf>,
    /// Overrides for every run (`--set`).
    #[serde(default)]
    pub set: toml::Table,
    /// Setting -> values; runs cover every combination.
    #[serde(default)]
    pub grid: toml::Table,
    #[serde(default)]
    pub slurm: SlurmOptions,
    /// How `--gather` evaluates (absent: evaluation seed 0, the command's flags).
    pub gather: Option<GatherProtocol>,
    /// The file it was read from, for messages.
    #[serde(skip)]
    pub file: PathBuf,
}

/// The evaluation protocol of `--gather`, the grid file's `[gather]`: the
/// evaluation seeds that carry a claim, written down before the runs are
/// evaluated, and what each evaluation covers (each given value overrides
/// the command's flag).
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GatherProtocol {
    pub eval_seeds: Vec<u64>,
    pub tasks: Option<usize>,
    pub episodes: Option<usize>,
    pub n_budgets: Option<usize>,
    /// The random policy evaluated beside every run, on the same tasks.
    #[serde(default)]
    pub random: bool,
}

fn default_method() -> String {
    "eppo".into()
}

fn default_preset() -> String {
    "quick".into()
}

/// One array task: a seed and one value of every grid setting.
#[derive(Clone, Debug, PartialEq)]
pub struct Task {
    pub index: usize,
    pub seed: u64,
    /// `key=value` of every grid setting (TOML values).
    pub settings: Vec<String>,
}

impl Task {
    /// The setting's name in tables: its grid values, or `preset`.
    pub fn label(&self) -> String {
        if self.settings.is_empty() {
            "preset".into()
        } else {
            self.settings.join(" ")
        }
    }
}

impl SweepGrid {
    /// Reads a grid file; relative `out` and `dataset` are taken from the
    /// file's folder and made absolute (array tasks start anywhere).
    pub fn load(path: &Path) -> Result<Self, SweepError> {
        let problem = |problem: String| SweepError::Grid {
            path: path.to_path_buf(),
            problem,
        };
        // A FIFO would block the read below until a writer came.
        crate::guard::regular_file(path)
            .map_err(|e| problem(format!("{e}: give the grid's TOML file")))?;
        let text = std::fs::read_to_string(path).map_err(|e| problem(e.to_string()))?;
        let mut grid: SweepGrid = toml::from_str(&text).map_err(|e| problem(e.to_string()))?;
        grid.file = path.to_path_buf();
        grid.env
            .parse::<EnvName>()
            .map_err(|e| problem(e.to_string()))?;
        if !["eppo", "ad"].contains(&grid.method.as_str()) {
            return Err(problem(format!("method {:?}: eppo or ad", grid.method)));
        }
        if grid.method == "ad" && grid.dataset.is_none() {
            return Err(problem("method \"ad\" needs dataset = \"FILE\"".into()));
        }
        if grid.seeds.is_empty() {
            return Err(problem("seeds is empty: give at least one".into()));
        }
        let mut distinct = grid.seeds.clone();
        distinct.sort_unstable();
        distinct.dedup();
        if distinct.len() != grid.seeds.len() {
            return Err(problem(format!(
                "seeds = {:?} repeats a seed: each seed once",
                grid.seeds
            )));
        }
        for table in ["set", "grid"] {
            let keys = if table == "set" {
                &grid.set
            } else {
                &grid.grid
            };
            if keys.contains_key("seed") {
                return Err(problem(format!(
                    "{table}.seed: the seeds are the grid file's `seeds` list, which the tasks \
                     and the gathered table follow; move the values there"
                )));
            }
        }
        let mut tasks: u128 = grid.seeds.len() as u128;
        for (key, values) in &grid.grid {
            match values.as_array() {
                Some(a) if !a.is_empty() => tasks = tasks.saturating_mul(a.len() as u128),
                _ => {
                    return Err(problem(format!(
                        "grid.{key} must be a non-empty list of values"
                    )));
                }
            }
        }
        if tasks > MAX_TASKS as u128 {
            return Err(problem(format!(
                "{tasks} tasks (seeds x every combination of [grid]): at most {MAX_TASKS}, \
                 Slurm's default MaxArraySize less one; split the grid into several files"
            )));
        }
        grid.check_script_text().map_err(problem)?;
        grid.slurm.check_bounds().map_err(problem)?;
        let base = path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let base = std::path::absolute(base).map_err(|e| problem(e.to_string()))?;
        grid.out = base.join(&grid.out);
        grid.dataset = grid.dataset.map(|d| base.join(d));
        grid.tasks_checked().map_err(problem)?;
        Ok(grid)
    }

    /// Every (setting, seed), settings outermost, in a fixed order.
    pub fn tasks(&self) -> Vec<Task> {
        let mut combos: Vec<Vec<String>> = vec![Vec::new()];
        for (key, values) in &self.grid {
            let values = values.as_array().map_or(&[][..], Vec::as_slice);
            combos = combos
                .iter()
                .flat_map(|c| {
                    values.iter().map(move |v| {
                        let mut c = c.clone();
                        c.push(format!("{key}={v}"));
                        c
                    })
                })
                .collect();
        }
        combos
            .into_iter()
            .flat_map(|settings| self.seeds.iter().map(move |&seed| (seed, settings.clone())))
            .enumerate()
            .map(|(index, (seed, settings))| Task {
                index,
                seed,
                settings,
            })
            .collect()
    }

    /// The tasks, each resolved against the preset once, so that a bad key
    /// or value fails now and not on the cluster.
    pub(super) fn tasks_checked(&self) -> Result<Vec<(Task, toml::Table)>, String> {
        self.tasks()
            .into_iter()
            .map(|t| {
                let table = self.resolved(&t)?;
                Ok((t, table))
            })
            .collect()
    }

    /// The preset with `[set]` and the task's settings applied, checked as
    /// the learner checks its config.
    fn resolved(&self, task: &Task) -> Result<toml::Table, String> {
        let mut table = crate::presets::preset_table(&self.method, &self.env, &self.preset)
            .map_err(|e| e.to_string())?;
        let checked = match self.method.as_str() {
            "ad" => crate::presets::apply_overrides(&mut table, &self.sets(task))
                .map_err(|e| e.to_string())
                .and_then(|()| {
                    crate::ad::AdConfig::from_table(table.clone()).map_err(|e| e.to_string())
                })
                .map(|_| ()),
            _ => EppoConfig::apply_sets(&mut table, &self.sets(task))
                .and_then(|()| EppoConfig::from_table("sweep", table.clone()))
                .and_then(|c| c.validate())
                .map_err(|e| e.to_string()),
        };
        checked.map_err(|e| format!("task {} ({}): {e}", task.index, task.label()))?;
        Ok(table)
    }

    /// `--set`s of a task: `[set]`, its grid values, its seed.
    pub(super) fn sets(&self, task: &Task) -> Vec<String> {
        let mut leaves = Vec::new();
        crate::cli::pretrain::flatten("", &self.set, &mut leaves);
        let mut sets: Vec<String> = leaves.iter().map(|(k, v)| format!("{k}={v}")).collect();
        sets.extend(task.settings.iter().cloned());
        sets.push(format!("seed={}", task.seed));
        sets
    }

    /// The name of a task's folder (it holds one run folder): `seed<N>` when
    /// only the seed varies (`results/final/<env>/seed<N>`), else `task_<K>`.
    pub fn task_name(&self, task: &Task) -> String {
        if self.grid.is_empty() {
            format!("seed{}", task.seed)
        } else {
            format!("task_{:03}", task.index)
        }
    }

    /// A task's folder under `out`.
    pub fn task_dir(&self, task: &Task) -> PathBuf {
        self.out.join(self.task_name(task))
    }

    /// The `icrl` arguments of a task: a plain `pretrain` into its own folder.
    pub fn pretrain_args(&self, task: &Task) -> Vec<String> {
        let mut args: Vec<String> = [
            "pretrain",
            "--env",
            &self.env,
            "--method",
            &self.method,
            "--preset",
            &self.preset,
        ]
        .map(String::from)
        .to_vec();
        if let Some(d) = &self.dataset {
            args.extend(["--dataset".into(), d.display().to_string()]);
        }
        for s in self.sets(task) {
            args.extend(["--set".into(), s]);
        }
        args.extend([
            "--out".into(),
            self.task_dir(task).display().to_string(),
            "--resume-in-out".into(),
        ]);
        args
    }
}

/// The most array tasks one grid file may ask for (Slurm's default
/// `MaxArraySize` is 1001, indices 0 to 1000).
const MAX_TASKS: usize = 1000;

/// Refuses `text` where it would break out of its line in the generated
/// script: a newline would start a command of its own, a NUL cannot be
/// quoted at all, and other control characters have no place in a Slurm
/// option or a path. Every text of the grid file that reaches the script
/// passes here once, on load; [`slurm_script`] then quotes what it writes.
pub(super) fn check_script_text(what: &str, text: &str) -> Result<(), String> {
    match text.chars().find(|c| c.is_control()) {
        Some(c) => Err(format!(
            "{what} = {text:?} holds the control character {c:?}, which the generated script \
             cannot carry: remove it"
        )),
        None => Ok(()),
    }
}

impl SweepGrid {
    /// Every text of the grid file that the script carries.
    fn check_script_text(&self) -> Result<(), String> {
        let s = &self.slurm;
        let texts = [
            ("env", Some(self.env.clone())),
            ("method", Some(self.method.clone())),
            ("preset", Some(self.preset.clone())),
            ("out", Some(self.out.display().to_string())),
            (
                "dataset",
                self.dataset.as_ref().map(|d| d.display().to_string()),
            ),
            ("slurm.partition", s.partition.clone()),
            ("slurm.account", s.account.clone()),
            ("slurm.time", s.time.clone()),
            ("slurm.mem", s.mem.clone()),
            (
                "slurm.icrl",
                s.icrl.as_ref().map(|p| p.display().to_string()),
            ),
        ];
        for (what, text) in texts {
            if let Some(text) = text {
                check_script_text(what, &text)?;
            }
        }
        for (i, e) in s.extra.iter().enumerate() {
            check_script_text(&format!("slurm.extra[{i}]"), e)?;
        }
        for (table, values) in [("set", &self.set), ("grid", &self.grid)] {
            for (key, value) in values {
                check_toml_text(&format!("{table}.{key}"), value)?;
            }
        }
        Ok(())
    }
}

/// [`check_script_text`] on every string inside `value` (its own
/// characters, not its quoted TOML form).
fn check_toml_text(what: &str, value: &toml::Value) -> Result<(), String> {
    match value {
        toml::Value::String(text) => check_script_text(what, text),
        toml::Value::Array(items) => items.iter().try_for_each(|v| check_toml_text(what, v)),
        toml::Value::Table(table) => table
            .iter()
            .try_for_each(|(k, v)| check_toml_text(&format!("{what}.{k}"), v)),
        _ => Ok(()),
    }
}
