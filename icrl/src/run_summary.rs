//! What a finished pretraining run tells its user: whether it learned, in
//! numbers a reader can judge (its episodic return early and late in the run
//! against a uniformly random policy's on the same task distribution), and the
//! exact command that evaluates its checkpoint.

use std::collections::VecDeque;
use std::path::Path;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safety_envs::{
    Action, CmdpEnv, EnvError, EnvName, EnvOptions, Orientation, Space, StepOutcome, make_env,
    sample_task, spawn_config,
};

use crate::stats::mean_se;

/// Mean episode return and cost.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReturnCost {
    pub episodic_return: f64,
    pub episodic_cost: f64,
}

/// The run's learning curve, summarised: the mean of `episodic_return` and
/// `episodic_cost` over the first and over the last `fraction` of the
/// collection rounds in `metrics.jsonl` (at least two rounds each where the run has two).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Trend {
    pub first: ReturnCost,
    pub last: ReturnCost,
    /// Rounds with episodes that the means cover.
    pub rounds: usize,
    /// Standard error of the last part's mean return over its rounds (NaN
    /// with a single round).
    pub last_return_se: f64,
}

impl Trend {
    /// Whether the run's late return beats `random`'s by more than two
    /// standard errors: one lucky round is not learning.
    pub fn beats(&self, random: ReturnCost) -> bool {
        self.last.episodic_return - random.episodic_return > 2.0 * self.last_return_se
    }
}

/// Reads `metrics.jsonl` (records without an `episodic_return` number are
/// skipped); `None` when no round finished an episode.
pub fn metrics_trend(metrics: &Path, fraction: f64) -> Option<Trend> {
    let text = std::fs::read_to_string(metrics).ok()?;
    let rows: Vec<ReturnCost> = text
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| {
            Some(ReturnCost {
                episodic_return: v.get("episodic_return")?.as_f64()?,
                episodic_cost: v.get("episodic_cost")?.as_f64()?,
            })
        })
        .collect();
    if rows.is_empty() {
        return None;
    }
    // At least two rounds where there are two, so that the spread is known.
    let k = ((rows.len() as f64 * fraction).ceil() as usize).clamp(2.min(rows.len()), rows.len());
    let mean = |part: &[ReturnCost]| ReturnCost {
        episodic_return: part.iter().map(|r| r.episodic_return).sum::<f64>() / part.len() as f64,
        episodic_cost: part.iter().map(|r| r.episodic_cost).sum::<f64>() / part.len() as f64,
    };
    let last = &rows[rows.len() - k..];
    let last_returns: Vec<f64> = last.iter().map(|r| r.episodic_return).collect();
    // One round has no spread: its error is unknown, not 0.
    let last_return_se = match mean_se(&last_returns) {
        Some(m) if m.n >= 2 => m.se,
        _ => f64::NAN,
    };
    Some(Trend {
        first: mean(&rows[..k]),
        last: mean(last),
        rounds: rows.len(),
        last_return_se,
    })
}

/// A uniformly random policy's mean episode return and cost on `episodes`
/// centre-oriented (pretraining) tasks of `env`, one episode per task.
pub fn random_policy(
    env: EnvName,
    options: &EnvOptions,
    episodes: usize,
    seed: u64,
) -> Result<ReturnCost, EnvError> {
    let (mut ret, mut cost) = (0.0, 0.0);
    random_rollouts(
        make_env(env, options)?.as_mut(),
        env,
        episodes,
        seed,
        |_, out| {
            ret += f64::from(out.reward);
            cost += f64::from(out.cost);
        },
    )?;
    let n = episodes.max(1) as f64;
    Ok(ReturnCost {
        episodic_return: ret / n,
        episodic_cost: cost / n,
    })
}

/// Runs a uniformly random policy in `e` for `episodes` episodes, one per
/// centre-oriented (pretraining) task of `env` drawn from `seed`, and hands
/// every step's observation and outcome to `on_step`.
pub fn random_rollouts(
    e: &mut dyn CmdpEnv,
    env: EnvName,
    episodes: usize,
    seed: u64,
    mut on_step: impl FnMut(&[f32], &StepOutcome),
) -> Result<(), EnvError> {
    let spawn = spawn_config(env);
    let mut obs = vec![0.0; e.observation_space().flat_dim()];
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let space = e.action_space();
    let mut action = vec![0.0f32; space.flat_dim()];
    for i in 0..episodes {
        let task = sample_task(&spawn, Orientation::Centre, seed.wrapping_add(i as u64))?;
        e.set_task(&task)?;
        e.reset(i as u64, &mut obs)?;
        loop {
            let out = match &space {
                Space::Discrete { n } => {
                    e.step(Action::Discrete(rng.gen_range(0..*n)), &mut obs)?
                }
                Space::Box { low, high } => {
                    for (a, (&l, &h)) in action.iter_mut().zip(low.iter().zip(high)) {
                        *a = rng.gen_range(l..=h);
                    }
                    e.step(Action::Continuous(&action), &mut obs)?
                }
            };
            on_step(&obs, &out);
            if out.done() {
                break;
            }
        }
    }
    Ok(())
}

/// The last rounds of a training run, averaged for its progress line: one
/// round's 8 trajectories are too few to tell learning from noise.
#[derive(Clone, Debug)]
pub struct RecentRounds {
    window: usize,
    /// Per round: mean return, mean cost, first and last episode's return.
    rounds: VecDeque<[f64; 4]>,
}

impl RecentRounds {
    pub fn new(window: usize) -> Self {
        RecentRounds {
            window: window.max(1),
            rounds: VecDeque::new(),
        }
    }

    /// Adds a round; one that finished no episode (NaN means) is skipped.
    pub fn push(&mut self, mean_return: f64, mean_cost: f64, first_return: f64, last_return: f64) {
        let round = [mean_return, mean_cost, first_return, last_return];
        if round.iter().any(|v| !v.is_finite()) {
            return;
        }
        if self.rounds.len() == self.window {
            self.rounds.pop_front();
        }
        self.rounds.push_back(round);
    }

    /// What the user reads while training runs: return and cost against the
    /// random policy's, and whether the last episode of a trajectory beats
    /// its first (learning in context).
    pub fn progress_line(&self, random: ReturnCost) -> String {
        if self.rounds.is_empty() {
            return format!(
                "no episode yet (random policy: return {:.3}, cost {:.2})",
                random.episodic_return, random.episodic_cost
            );
        }
        let n = self.rounds.len() as f64;
        let mean = |i: usize| self.rounds.iter().map(|r| r[i]).sum::<f64>() / n;
        format!(
            "return {:.3} (random {:.3}; first episode {:.3} -> last {:.3})  cost {:.2} (random {:.2})  over the last {} rounds",
            mean(0),
            random.episodic_return,
            mean(2),
            mean(3),
            mean(1),
            random.episodic_cost,
            self.rounds.len()
        )
    }
}

/// The command that evaluates `checkpoint` on `env` (held-out edge tasks,
/// Figure 1, with a random policy for scale). The checkpoint is named by its
/// absolute path: `cargo xtask` runs only inside the workspace, so a path
/// relative to where `icrl pretrain` ran (`--out runs` from another folder)
/// would name another folder there.
pub fn eval_command(env: EnvName, checkpoint: &Path) -> String {
    let checkpoint = std::path::absolute(checkpoint).unwrap_or_else(|_| checkpoint.to_path_buf());
    // The random policy is evaluated beside it by default.
    format!(
        "cargo xtask eval --checkpoint {} --env {env} --out results/eval_{env}",
        shell_word(&checkpoint)
    )
}

/// `mean ± se` to 3 decimals; a mean of one sample has no spread to give an
/// error, and says so rather than print `± NaN`.
pub fn mean_with_error(mean: f64, se: f64) -> String {
    if se.is_finite() {
        format!("{mean:.3} ± {se:.3}")
    } else {
        format!("{mean:.3} (one round, no standard error)")
    }
}

/// Set by `cargo xtask` in the environment of the binaries it runs, so that
/// the commands they print take the form the user typed.
pub const VIA_XTASK_ENV: &str = "ICRL_VIA_XTASK";

/// The command that continues an interrupted run from its folder (the
/// checkpoint's grandparent, whose latest checkpoint resume picks), as
/// `cargo xtask pretrain` when `via_xtask`, else `icrl pretrain`.
pub fn resume_command(env: &str, method: &str, checkpoint: &Path, via_xtask: bool) -> String {
    let run = checkpoint
        .parent()
        .and_then(Path::parent)
        .unwrap_or(checkpoint);
    let launcher = if via_xtask { "cargo xtask" } else { "icrl" };
    format!(
        "{launcher} pretrain --env {env} --method {method} --resume {}",
        shell_word(run)
    )
}

/// `path` quoted for a POSIX shell where it needs it (spaces, quotes), so a
/// printed command works when pasted.
pub fn shell_word(path: &Path) -> String {
    let text = path.to_string_lossy();
    shlex::try_quote(&text).map_or_else(|_| text.to_string(), |q| q.into_owned())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_single_round_is_reported_without_a_nan_error() {
        assert_eq!(mean_with_error(0.1456, 0.02), "0.146 ± 0.020");
        assert_eq!(
            mean_with_error(0.1456, f64::NAN),
            "0.146 (one round, no standard error)"
        );
    }

    #[test]
    fn the_resume_line_takes_the_form_the_run_was_started_in() {
        let ckpt = Path::new("runs/my run/checkpoints/step_40");
        assert_eq!(
            resume_command("car", "eppo", ckpt, true),
            "cargo xtask pretrain --env car --method eppo --resume 'runs/my run'"
        );
        assert_eq!(
            resume_command("darkroom", "ad", ckpt, false),
            "icrl pretrain --env darkroom --method ad --resume 'runs/my run'"
        );
    }

    #[test]
    fn trend_averages_first_and_last_rounds_and_skips_rounds_without_episodes() {
        let dir = std::env::temp_dir().join(format!("icrl-run-summary-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("metrics.jsonl");
        let mut text = String::from("{\"env_steps\": 1, \"episodic_return\": null}\n");
        for i in 0..10 {
            text += &format!(
                "{{\"env_steps\": {i}, \"episodic_return\": {}, \"episodic_cost\": {}}}\n",
                i as f64 / 10.0,
                10 - i
            );
        }
        std::fs::write(&path, text).unwrap();
        let t = metrics_trend(&path, 0.2).unwrap();
        assert_eq!(t.rounds, 10);
        assert!((t.first.episodic_return - 0.05).abs() < 1e-12, "{t:?}");
        assert!((t.last.episodic_return - 0.85).abs() < 1e-12, "{t:?}");
        assert!((t.first.episodic_cost - 9.5).abs() < 1e-12, "{t:?}");
        // Last two rounds 0.8 and 0.9: standard error 0.05.
        assert!((t.last_return_se - 0.05).abs() < 1e-9, "{t:?}");
        let random = |r| ReturnCost {
            episodic_return: r,
            episodic_cost: 0.0,
        };
        assert!(t.beats(random(0.74)) && !t.beats(random(0.76)));
        assert_eq!(
            metrics_trend(&path, 0.01).unwrap(),
            t,
            "at least two rounds"
        );
        let single = dir.join("single.jsonl");
        std::fs::write(
            &single,
            "{\"episodic_return\": 1.0, \"episodic_cost\": 0.0}\n",
        )
        .unwrap();
        let one = metrics_trend(&single, 0.1).unwrap();
        assert!(
            one.last_return_se.is_nan() && !one.beats(random(0.0)),
            "one round decides nothing"
        );
        assert!(metrics_trend(&dir.join("none.jsonl"), 0.1).is_none());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn progress_line_averages_the_last_rounds_against_the_random_policy() {
        let random = ReturnCost {
            episodic_return: 0.05,
            episodic_cost: 3.0,
        };
        let mut recent = RecentRounds::new(2);
        assert!(recent.progress_line(random).starts_with("no episode yet"));
        recent.push(9.0, 9.0, 9.0, 9.0);
        recent.push(0.2, 4.0, 0.1, 0.3);
        recent.push(f64::NAN, f64::NAN, f64::NAN, f64::NAN);
        recent.push(0.4, 2.0, 0.3, 0.5);
        assert_eq!(
            recent.progress_line(random),
            "return 0.300 (random 0.050; first episode 0.200 -> last 0.400)  cost 3.00 (random 3.00)  over the last 2 rounds"
        );
    }

    #[test]
    fn random_policy_pays_cost_and_rarely_reaches_the_goal_on_point() {
        let r = random_policy(EnvName::Point, &EnvOptions::default(), 20, 3).unwrap();
        assert!(r.episodic_cost > 1.0, "{r:?}");
        assert!(r.episodic_return < 0.5, "{r:?}");
        let cmd = eval_command(EnvName::Car, Path::new("runs/x/checkpoints/step_9"));
        let here = std::env::current_dir().unwrap();
        assert_eq!(
            cmd,
            format!(
                "cargo xtask eval --checkpoint {} --env car --out results/eval_car",
                shell_word(&here.join("runs/x/checkpoints/step_9"))
            )
        );
    }
}
