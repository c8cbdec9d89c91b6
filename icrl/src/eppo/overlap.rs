//! The overlapped loop (`overlap = true`): an actor thread steps the
//! vectorised environments and acts with its own copy of the policy while
//! this thread samples the replay and updates, so both cores work.
//!
//! The schedule, and why it keeps the learning problem fixed:
//! - Rounds reach the learner in order. After round r it runs exactly the
//!   updates the replay ratio owes ([`Learner::updates_owed`], the same
//!   function the synchronous loop calls), then publishes a copy of its
//!   weights. A faster learner therefore waits for rounds: it never runs
//!   more updates per environment step than the ratio says.
//! - The actor acts rounds 0 and 1 with the starting weights and round
//!   r + 2 with the weights published after round r's updates. A faster
//!   actor therefore waits for weights: it is never more than one round
//!   ahead, and its policy is exactly one round staler than the synchronous
//!   loop's (which acts round r + 1 with those weights).
//! - Each side computes only from what it received, in a fixed order, on
//!   its own RNG (the actor's is drawn from the learner's at the start) and
//!   one libtorch thread each; acting draws nothing from libtorch's
//!   generator, which the learner reseeds per update. A run is therefore
//!   deterministic under its seed, like the synchronous one.
//!
//! Checkpoints are written by the learner with the counters of the last
//! round it received (tasks drawn, environment steps); the round the actor
//! had in flight is dropped on stop and redrawn on resume, as the replay is.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, Sender, SyncSender, channel, sync_channel};
use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::{Tensor, nn};

use safety_envs::VecEnv;

use super::collect::{Collector, RoundStats};
use super::config::{EppoConfig, EppoError};
use super::net::EppoNet;
use super::replay::Trajectory;
use super::timing::{PhaseTimes, thread_cpu_seconds};
use super::{Learner, Session, learn};

/// One collected round, as the actor hands it over.
struct Round {
    trajs: Vec<Trajectory>,
    stats: RoundStats,
    /// The actor's counters after the round (what a checkpoint records).
    env_steps: u64,
    tasks_drawn: u64,
    /// The actor's phase times and thread CPU seconds so far.
    times: PhaseTimes,
    cpu: f64,
}

/// The acting side: a copy of the policy and what collection advances.
struct Actor {
    _vs: nn::VarStore,
    net: EppoNet,
    /// The copy's variables by name, written from the learner's snapshots.
    vars: Vec<Tensor>,
    cfg: EppoConfig,
    rng: ChaCha8Rng,
    env_steps: u64,
    tasks_drawn: u64,
    times: PhaseTimes,
}

/// The learner's variables in name order (the actor's copy has the same names).
fn named_variables(vs: &nn::VarStore) -> Vec<Tensor> {
    let sorted: BTreeMap<String, Tensor> = vs.variables().into_iter().collect();
    sorted.into_values().collect()
}

/// A copy of the weights that the learner's next updates leave alone.
fn snapshot(vars: &[Tensor]) -> Vec<Tensor> {
    tch::no_grad(|| vars.iter().map(|t| t.detach().copy()).collect())
}

/// Runs the overlapped loop until `total_updates` or a stop request; the
/// caller writes the final checkpoint.
pub(super) fn train(
    learner: &mut Learner,
    venv: &mut VecEnv,
    session: &mut Session,
) -> Result<(), EppoError> {
    // Built here, not on the actor's thread: initialising the copy draws
    // from libtorch's generator, which belongs to the learner.
    let vs = nn::VarStore::new(learner.device);
    let net = EppoNet::new(vs.root(), &learner.cfg, &learner.spec)?;
    let learner_vars = named_variables(&learner.vs);
    let mut actor = Actor {
        vars: named_variables(&vs),
        _vs: vs,
        net,
        cfg: learner.cfg.clone(),
        rng: ChaCha8Rng::seed_from_u64(learner.rng.r#gen()),
        env_steps: learner.env_steps,
        tasks_drawn: learner.tasks_drawn,
        times: PhaseTimes::default(),
    };
    let (weights_tx, weights_rx) = sync_channel(2);
    let (rounds_tx, rounds_rx) = channel();
    // Rounds 0 and 1 act with the starting weights (the one-round lag).
    for _ in 0..2 {
        weights_tx
            .send(snapshot(&learner_vars))
            .map_err(|_| EppoError::Config("the actor's weight channel closed".into()))?;
    }
    let quit = AtomicBool::new(false);
    let (env, spec) = (learner.env, learner.spec.clone());
    let (torch_threads, learner_threads) = (
        learner.cfg.run.torch_threads,
        learner.cfg.run.learner_threads,
    );
    crate::guard::set_torch_threads("learner_threads", learner_threads);
    let result = std::thread::scope(|s| {
        let actor_thread = s.spawn(|| {
            // libtorch's intra-op thread count is per OS thread.
            crate::guard::set_torch_threads("torch_threads", actor.cfg.run.torch_threads);
            actor.run(venv, env, &spec, weights_rx, rounds_tx, &quit)
        });
        let learned = learner_side(learner, session, &learner_vars, rounds_rx, weights_tx);
        // Whatever ended the learner's side, the actor stops at its next step.
        quit.store(true, Ordering::Relaxed);
        let acted = actor_thread
            .join()
            .unwrap_or_else(|_| Err(EppoError::Config("the actor thread panicked".into())));
        learned.and(acted)
    });
    if learner_threads > 0 {
        crate::guard::set_torch_threads("torch_threads", torch_threads);
    }
    result
}

/// The learner's side: take each round, run the updates it owes, publish
/// the weights, log. Returns when training is done, stopped, or the actor
/// ended (its error then comes from joining it).
fn learner_side(
    learner: &mut Learner,
    session: &mut Session,
    vars: &[Tensor],
    rounds: Receiver<Round>,
    weights: SyncSender<Vec<Tensor>>,
) -> Result<(), EppoError> {
    while learner.updates < learner.cfg.optimisation.total_updates {
        let clock = Instant::now();
        let Ok(round) = rounds.recv() else {
            return Ok(());
        };
        learner.times.wait += clock.elapsed().as_secs_f64();
        learner.env_steps = round.env_steps;
        learner.tasks_drawn = round.tasks_drawn;
        for t in round.trajs {
            learner.replay.push(t);
        }
        learner.observe_round(&round.stats);
        let stats = learn(learner, session)?;
        // Published before logging, so the actor waits as little as possible.
        if weights.send(snapshot(vars)).is_err() {
            return Ok(());
        }
        session.log_round(
            learner,
            &round.stats,
            &stats,
            Some((&round.times, round.cpu)),
        )?;
        if crate::stop::requested() {
            break;
        }
    }
    Ok(())
}

impl Actor {
    /// Collects rounds, each with the next published weights, until the
    /// learner stops publishing or asks it to quit.
    fn run(
        &mut self,
        venv: &mut VecEnv,
        env: safety_envs::EnvName,
        spec: &super::net::NetSpec,
        weights: Receiver<Vec<Tensor>>,
        rounds: Sender<Round>,
        quit: &AtomicBool,
    ) -> Result<(), EppoError> {
        let started_cpu = thread_cpu_seconds();
        loop {
            let clock = Instant::now();
            let Ok(published) = weights.recv() else {
                return Ok(());
            };
            self.times.wait += clock.elapsed().as_secs_f64();
            tch::no_grad(|| {
                for (mine, theirs) in self.vars.iter_mut().zip(&published) {
                    mine.copy_(theirs);
                }
            });
            let (trajs, stats) = Collector {
                net: &self.net,
                cfg: &self.cfg,
                spec,
                env,
                rng: &mut self.rng,
                env_steps: &mut self.env_steps,
                tasks_drawn: &mut self.tasks_drawn,
                times: &mut self.times,
                quit: Some(quit),
            }
            .round(venv)?;
            if quit.load(Ordering::Relaxed) {
                return Ok(());
            }
            let round = Round {
                trajs,
                stats,
                env_steps: self.env_steps,
                tasks_drawn: self.tasks_drawn,
                times: self.times,
                cpu: thread_cpu_seconds() - started_cpu,
            };
            if rounds.send(round).is_err() {
                return Ok(());
            }
        }
    }
}
