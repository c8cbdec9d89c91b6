//! Where a training second goes: wall seconds per phase of the loop, kept by
//! each side (the learner's thread and, when overlapped, the actor's) and
//! logged as `time/*` (cumulative seconds since the run or resume started);
//! BENCHMARKS.md's profile reads them.

use std::time::Instant;

/// Cumulative wall seconds per phase of one thread.
#[derive(Clone, Copy, Debug, Default)]
pub struct PhaseTimes {
    /// `VecEnv::step` (and the round's task draws and resets).
    pub env_step: f64,
    /// Writing the acting step's tokens.
    pub tokens: f64,
    /// The KV-cached forward step and the action sampling.
    pub acting: f64,
    /// Sampling trajectories, relabelling and building the batch tensors.
    pub batch: f64,
    /// The losses' forward passes (online and target networks, heads, targets).
    pub forward: f64,
    /// Backpropagation.
    pub backward: f64,
    /// Gradient norm, clipping and the Adam step.
    pub optimizer: f64,
    /// The multiplier step and the Polyak update of the target networks.
    pub targets: f64,
    /// Checkpoints, metric records and progress lines.
    pub logging: f64,
    /// Overlapped loop only: waiting for the other side (a round to learn
    /// from, or fresh weights to act with) under the replay ratio.
    pub wait: f64,
}

impl PhaseTimes {
    /// Runs `f`, adding its wall time to the phase `slot` picks.
    pub(super) fn time<T>(&mut self, slot: fn(&mut Self) -> &mut f64, f: impl FnOnce() -> T) -> T {
        let start = Instant::now();
        let out = f();
        *slot(self) += start.elapsed().as_secs_f64();
        out
    }

    /// The phases as `time/<name>` metric entries, with `prefix` before the
    /// name (`actor/` for the overlapped loop's actor thread).
    pub(super) fn record(
        &self,
        prefix: &str,
        out: &mut serde_json::Map<String, serde_json::Value>,
    ) {
        let phases = [
            ("env_step", self.env_step),
            ("tokens", self.tokens),
            ("acting", self.acting),
            ("batch", self.batch),
            ("forward", self.forward),
            ("backward", self.backward),
            ("optimizer", self.optimizer),
            ("targets", self.targets),
            ("logging", self.logging),
            ("wait", self.wait),
        ];
        for (name, secs) in phases {
            out.insert(format!("time/{prefix}{name}"), secs.into());
        }
    }
}

/// CPU seconds the calling thread has run (`CLOCK_THREAD_CPUTIME_ID`): with
/// the wall time, the share of a core the thread kept busy.
pub fn thread_cpu_seconds() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid timespec for clock_gettime to fill.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return f64::NAN;
    }
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}
