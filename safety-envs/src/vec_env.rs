//! Many environments stepped together across threads.
//!
//! [`VecEnv`] owns `N` boxed environments with equal spaces and steps them in
//! contiguous chunks, one chunk per thread (a private rayon pool of
//! `n_threads`; with one thread it steps inline). Observations land in one
//! contiguous buffer, `N x obs_dim`, row `i` for environment `i`.
//!
//! Threads pay off only when a batch step is much dearer than handing work to
//! another thread (a few microseconds on a quiet machine, far more when the
//! other core is busy): SafeDarkMujoco (0.1-0.6 ms per agent step with the
//! 50-physics-step macro action) yes; SafeDarkRoom (about 15 ns per step) no.
//! So `VecEnv` decides per step, from measured cost: every chunk times its own
//! work, and the batch goes to the pool only while the smoothed serial cost of
//! a batch is at least [`PARALLEL_MIN_BATCH`]; cheaper batches run inline on
//! the calling thread, so a `VecEnv` of cheap environments never loses to one
//! thread (64 SafeDarkRoom environments on 2 threads ran at 0.07x of one
//! thread before this rule).
//!
//! Determinism: environments share no state and each chunk is a fixed range of
//! them, so the results are bitwise the same for every thread count. With
//! auto-reset, an environment whose episode ended is reset at once with the
//! seed `episode_seed(base_seed_i, episode_index_i)`, its last observation is
//! kept in [`VecEnv::final_observations`] (Gymnasium's `final_observation`), and
//! the returned outcome still reports the step that ended the episode.

use std::time::{Duration, Instant};

use rayon::prelude::*;

use crate::EnvError;
use crate::env::{Action, CmdpEnv, Space, StepOutcome};
use crate::spawn::Task;

/// Smallest serial cost of one batch step (all environments, one after the
/// other) for which the batch is stepped on the thread pool. Ten times a
/// thread hand-off on a quiet machine: a DarkRoom batch (1 us for 64
/// environments) stays inline, a SafeDarkMujoco batch (over 100 us for even a
/// single environment) goes parallel.
pub const PARALLEL_MIN_BATCH: Duration = Duration::from_micros(50);

/// Actions for all environments at once.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum VecAction<'a> {
    /// One discrete action per environment (`N` entries).
    Discrete(&'a [usize]),
    /// `N x act_dim` values, row-major.
    Continuous(&'a [f32]),
}

/// The reset seed of episode `episode` of an environment whose base seed is
/// `base` (SplitMix64 of the pair), used by auto-reset.
pub fn episode_seed(base: u64, episode: u64) -> u64 {
    let mut z = base ^ episode.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Per-environment bookkeeping, kept beside the environment so a chunk owns
/// everything it touches.
struct Slot {
    env: Box<dyn CmdpEnv>,
    base_seed: u64,
    /// Episodes started so far (index of the current one).
    episode: u64,
}

/// `N` environments stepped together. See the module documentation.
pub struct VecEnv {
    slots: Vec<Slot>,
    obs_dim: usize,
    act_dim: usize,
    discrete: bool,
    auto_reset: bool,
    obs: Vec<f32>,
    final_obs: Vec<f32>,
    outcomes: Vec<StepOutcome>,
    /// `None` means always step inline on the calling thread.
    pool: Option<rayon::ThreadPool>,
    chunk: usize,
    /// Smoothed serial cost of one batch step (sum of the chunks' times), in
    /// seconds; `None` before the first step.
    batch_cost: Option<f64>,
}

impl VecEnv {
    /// Wraps `envs` (at least one, all with the same spaces), stepped on
    /// `n_threads` threads (at least 1).
    pub fn new(
        envs: Vec<Box<dyn CmdpEnv>>,
        n_threads: usize,
        auto_reset: bool,
    ) -> Result<Self, EnvError> {
        let Some(first) = envs.first() else {
            return Err(EnvError::InvalidConfig(
                "VecEnv needs at least one environment".into(),
            ));
        };
        if n_threads == 0 {
            return Err(EnvError::InvalidConfig(
                "VecEnv needs at least one thread".into(),
            ));
        }
        let (obs_space, act_space) = (first.observation_space(), first.action_space());
        for (i, e) in envs.iter().enumerate() {
            if e.observation_space() != obs_space || e.action_space() != act_space {
                return Err(EnvError::InvalidConfig(format!(
                    "environment {i} has different spaces than environment 0"
                )));
            }
        }
        let obs_dim = obs_space.flat_dim();
        let (discrete, act_dim) = match act_space {
            Space::Discrete { .. } => (true, 1),
            Space::Box { ref low, .. } => (false, low.len()),
        };
        let n = envs.len();
        let threads = n_threads.min(n);
        let pool = if threads > 1 {
            Some(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .map_err(|e| EnvError::InvalidConfig(format!("thread pool: {e}")))?,
            )
        } else {
            None
        };
        Ok(VecEnv {
            slots: envs
                .into_iter()
                .enumerate()
                .map(|(i, env)| Slot {
                    env,
                    base_seed: i as u64,
                    episode: 0,
                })
                .collect(),
            obs_dim,
            act_dim,
            discrete,
            auto_reset,
            obs: vec![0.0; n * obs_dim],
            final_obs: vec![0.0; n * obs_dim],
            outcomes: vec![StepOutcome::default(); n],
            pool,
            chunk: n.div_ceil(threads),
            batch_cost: None,
        })
    }

    /// Number of environments.
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    /// Always false: a `VecEnv` holds at least one environment.
    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// Observation length per environment.
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    /// Action length per environment (1 for discrete).
    pub fn act_dim(&self) -> usize {
        self.act_dim
    }

    /// The spaces shared by all environments.
    pub fn observation_space(&self) -> Space {
        self.slots[0].env.observation_space()
    }

    /// The action space shared by all environments.
    pub fn action_space(&self) -> Space {
        self.slots[0].env.action_space()
    }

    /// Environment `i` (for inspection, e.g. its task or elapsed steps).
    pub fn env(&self, i: usize) -> &dyn CmdpEnv {
        self.slots[i].env.as_ref()
    }

    /// Current observations, `N x obs_dim`.
    pub fn observations(&self) -> &[f32] {
        &self.obs
    }

    /// With auto-reset: the last observation of each environment whose episode
    /// ended on the latest step (rows of the others are stale).
    pub fn final_observations(&self) -> &[f32] {
        &self.final_obs
    }

    /// Threads the next [`VecEnv::step`] will use: 1 until a step has shown
    /// that a batch costs at least [`PARALLEL_MIN_BATCH`], then the pool's.
    pub fn threads_in_use(&self) -> usize {
        match (&self.pool, self.batch_cost) {
            (Some(pool), Some(c)) if c >= PARALLEL_MIN_BATCH.as_secs_f64() => {
                pool.current_num_threads()
            }
            _ => 1,
        }
    }

    /// Outcomes of the latest step.
    pub fn outcomes(&self) -> &[StepOutcome] {
        &self.outcomes
    }

    /// Sets the task of environment `i`.
    pub fn set_task(&mut self, i: usize, task: &Task) -> Result<(), EnvError> {
        let n = self.len();
        let slot = self.slots.get_mut(i).ok_or_else(|| {
            EnvError::InvalidConfig(format!("environment index {i} out of range 0..{n}"))
        })?;
        slot.env.set_task(task)
    }

    /// Resets every environment: environment `i` gets `seeds[i]` as its reset
    /// seed and as the base of its later auto-reset seeds.
    pub fn reset(&mut self, seeds: &[u64]) -> Result<&[f32], EnvError> {
        if seeds.len() != self.len() {
            return Err(EnvError::InvalidConfig(format!(
                "reset got {} seeds for {} environments",
                seeds.len(),
                self.len()
            )));
        }
        let d = self.obs_dim;
        for (i, (slot, obs)) in self
            .slots
            .iter_mut()
            .zip(self.obs.chunks_mut(d))
            .enumerate()
        {
            slot.base_seed = seeds[i];
            slot.episode = 0;
            slot.env.reset(seeds[i], obs).map_err(|e| in_env(i, e))?;
        }
        self.outcomes.fill(StepOutcome::default());
        Ok(&self.obs)
    }

    /// Steps every environment once. Without auto-reset, stepping an
    /// environment whose episode ended is an error (reset it first).
    pub fn step(&mut self, actions: VecAction<'_>) -> Result<&[StepOutcome], EnvError> {
        let n = self.len();
        match actions {
            VecAction::Discrete(a) if self.discrete && a.len() == n => {}
            VecAction::Continuous(a) if !self.discrete && a.len() == n * self.act_dim => {}
            VecAction::Discrete(a) => {
                return Err(EnvError::InvalidAction(if self.discrete {
                    format!("{} discrete actions for {n} environments", a.len())
                } else {
                    "discrete actions for continuous-action environments".into()
                }));
            }
            VecAction::Continuous(a) => {
                return Err(EnvError::InvalidAction(if self.discrete {
                    "continuous actions for discrete-action environments".into()
                } else {
                    format!(
                        "{} action values for {n} environments x {} each",
                        a.len(),
                        self.act_dim
                    )
                }));
            }
        }
        let (d, act_dim, auto_reset) = (self.obs_dim, self.act_dim, self.auto_reset);
        let parallel = self.threads_in_use() > 1;
        // In parallel, one job per chunk of `self.chunk` environments; inline,
        // one job for all, so a VecEnv that stays inline costs what one
        // thread does. Each environment's work never depends on the
        // partition, so the results are the same either way.
        let chunk = if parallel { self.chunk } else { n };
        let jobs = self
            .slots
            .chunks_mut(chunk)
            .zip(self.obs.chunks_mut(chunk * d))
            .zip(self.final_obs.chunks_mut(chunk * d))
            .zip(self.outcomes.chunks_mut(chunk))
            .enumerate()
            .map(|(j, (((slots, obs), final_obs), outcomes))| Chunk {
                first: j * chunk,
                slots,
                obs,
                final_obs,
                outcomes,
            });
        // Each chunk reports its result and how long its work took.
        let run = |c: Chunk<'_>| {
            let t = Instant::now();
            let r = c.step(actions, act_dim, d, auto_reset);
            (r, t.elapsed().as_secs_f64())
        };
        let results: Vec<(Result<(), EnvError>, f64)> = match &self.pool {
            Some(pool) if parallel => {
                pool.install(|| jobs.collect::<Vec<_>>().into_par_iter().map(run).collect())
            }
            _ => jobs.map(run).collect(),
        };
        let serial: f64 = results.iter().map(|r| r.1).sum();
        // Smoothed, so one slow step (a preempted thread) does not flip the
        // choice; the first measurement is taken as it is.
        self.batch_cost = Some(match self.batch_cost {
            None => serial,
            Some(c) => 0.8 * c + 0.2 * serial,
        });
        // The first error in environment order, whatever thread hit it.
        results.into_iter().try_for_each(|r| r.0)?;
        Ok(&self.outcomes)
    }
}

fn in_env(index: usize, source: EnvError) -> EnvError {
    EnvError::InEnv {
        index,
        source: Box::new(source),
    }
}

/// A contiguous range of environments `first..first + slots.len()` and the
/// rows of the buffers that belong to them.
struct Chunk<'a> {
    first: usize,
    slots: &'a mut [Slot],
    obs: &'a mut [f32],
    final_obs: &'a mut [f32],
    outcomes: &'a mut [StepOutcome],
}

impl Chunk<'_> {
    fn step(
        self,
        actions: VecAction<'_>,
        act_dim: usize,
        d: usize,
        auto_reset: bool,
    ) -> Result<(), EnvError> {
        for (k, slot) in self.slots.iter_mut().enumerate() {
            let i = self.first + k;
            let action = match actions {
                VecAction::Discrete(a) => Action::Discrete(a[i]),
                VecAction::Continuous(a) => Action::Continuous(&a[i * act_dim..(i + 1) * act_dim]),
            };
            let o = &mut self.obs[k * d..(k + 1) * d];
            let out = slot.env.step(action, o).map_err(|e| in_env(i, e))?;
            if auto_reset && out.done() {
                self.final_obs[k * d..(k + 1) * d].copy_from_slice(o);
                slot.episode += 1;
                let seed = episode_seed(slot.base_seed, slot.episode);
                slot.env.reset(seed, o).map_err(|e| in_env(i, e))?;
            }
            self.outcomes[k] = out;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::darkroom::{DarkRoomConfig, SafeDarkRoom};
    use crate::spawn::{Orientation, sample_task};

    fn rollout(threads: usize) -> (Vec<f32>, Vec<StepOutcome>) {
        let cfg = DarkRoomConfig::default();
        let envs: Vec<Box<dyn CmdpEnv>> = (0..5)
            .map(|_| Box::new(SafeDarkRoom::new(cfg.clone()).unwrap()) as Box<dyn CmdpEnv>)
            .collect();
        let mut v = VecEnv::new(envs, threads, true).unwrap();
        for i in 0..5 {
            let t = sample_task(&cfg.spawn_config(), Orientation::Centre, i as u64).unwrap();
            v.set_task(i, &t).unwrap();
        }
        v.reset(&[1, 2, 3, 4, 5]).unwrap();
        let (mut obs, mut outs) = (vec![], vec![]);
        for t in 0..100usize {
            let a: Vec<usize> = (0..5).map(|i| (t * 7 + i * 3) % 5).collect();
            outs.extend_from_slice(v.step(VecAction::Discrete(&a)).unwrap());
            obs.extend_from_slice(v.observations());
        }
        (obs, outs)
    }

    #[test]
    fn thread_count_does_not_change_results() {
        assert_eq!(rollout(1), rollout(2));
        assert_eq!(rollout(1), rollout(3));
    }

    #[test]
    fn cheap_batches_stay_on_the_calling_thread() {
        let cfg = DarkRoomConfig::default();
        let envs: Vec<Box<dyn CmdpEnv>> = (0..64)
            .map(|_| Box::new(SafeDarkRoom::new(cfg.clone()).unwrap()) as Box<dyn CmdpEnv>)
            .collect();
        let mut v = VecEnv::new(envs, 2, true).unwrap();
        v.reset(&[0; 64]).unwrap();
        assert_eq!(v.threads_in_use(), 1, "no cost measured yet");
        for t in 0..100usize {
            let a: Vec<usize> = (0..64).map(|i| (t + i) % 5).collect();
            v.step(VecAction::Discrete(&a)).unwrap();
        }
        // 64 DarkRoom steps take about a microsecond: far below a hand-off.
        assert_eq!(v.threads_in_use(), 1);
    }

    /// An environment whose every step takes `cost` of wall time.
    struct Slow {
        inner: SafeDarkRoom,
        cost: Duration,
    }

    impl CmdpEnv for Slow {
        fn observation_space(&self) -> Space {
            self.inner.observation_space()
        }
        fn action_space(&self) -> Space {
            self.inner.action_space()
        }
        fn max_episode_steps(&self) -> usize {
            self.inner.max_episode_steps()
        }
        fn set_task(&mut self, task: &Task) -> Result<(), EnvError> {
            self.inner.set_task(task)
        }
        fn task(&self) -> &Task {
            self.inner.task()
        }
        fn reset(&mut self, seed: u64, obs: &mut [f32]) -> Result<(), EnvError> {
            self.inner.reset(seed, obs)
        }
        fn step(&mut self, action: Action<'_>, obs: &mut [f32]) -> Result<StepOutcome, EnvError> {
            std::thread::sleep(self.cost);
            self.inner.step(action, obs)
        }
        fn elapsed_steps(&self) -> usize {
            self.inner.elapsed_steps()
        }
        fn goal_rule(&self) -> crate::env::GoalRule {
            self.inner.goal_rule()
        }
        fn goal_position(&self) -> [f32; 2] {
            self.inner.goal_position()
        }
    }

    #[test]
    fn dear_batches_go_to_the_pool() {
        let envs: Vec<Box<dyn CmdpEnv>> = (0..4)
            .map(|_| {
                Box::new(Slow {
                    inner: SafeDarkRoom::new(DarkRoomConfig::default()).unwrap(),
                    cost: Duration::from_micros(200),
                }) as Box<dyn CmdpEnv>
            })
            .collect();
        let mut v = VecEnv::new(envs, 2, true).unwrap();
        v.reset(&[0; 4]).unwrap();
        v.step(VecAction::Discrete(&[1; 4])).unwrap();
        assert_eq!(v.threads_in_use(), 2);
        v.step(VecAction::Discrete(&[1; 4])).unwrap();
        assert_eq!(v.threads_in_use(), 2);
    }

    #[test]
    fn bad_action_batches_are_rejected() {
        let envs: Vec<Box<dyn CmdpEnv>> = (0..2)
            .map(|_| {
                Box::new(SafeDarkRoom::new(DarkRoomConfig::default()).unwrap()) as Box<dyn CmdpEnv>
            })
            .collect();
        let mut v = VecEnv::new(envs, 2, false).unwrap();
        v.reset(&[0, 0]).unwrap();
        assert!(matches!(
            v.step(VecAction::Discrete(&[0])),
            Err(EnvError::InvalidAction(_))
        ));
        assert!(matches!(
            v.step(VecAction::Continuous(&[0.0, 0.0])),
            Err(EnvError::InvalidAction(_))
        ));
        assert!(matches!(
            v.step(VecAction::Discrete(&[0, 9])),
            Err(EnvError::InEnv { index: 1, .. })
        ));
    }
}
