//! The cost multiplier lambda. Eq. (7) is an integrator,
//! lambda <- clip(lambda + eta g, 0, lambda_max), with g the batch mean of
//! max_k (C_k - delta) (or, with `violation_signal = "late_rate"`, of the
//! share of later episodes over budget less its target). An
//! integrator overshoots: it keeps rising until the cost is under budget, then
//! takes as long to unwind, and on some training seeds that stops search
//! before the cost falls (issue 18, run E1). The PID Lagrangian (Stooke,
//! Achiam and Abbeel, ICML 2020) adds a proportional and a derivative term on
//! the smoothed violation, which respond at once and damp the overshoot:
//!
//! lambda = clip(I + kp e + kd max(0, e - e_prev), 0, lambda_max),
//! I <- clip(I + ki g, 0, lambda_max), e <- a e + (1 - a) g,
//!
//! with ki = `lambda_lr`. With kp = kd = 0 it is Eq. (7) exactly.

use serde::{Deserialize, Serialize};

use super::losses::mean_violation;

/// The gains and limits, read from the config.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Gains {
    /// Integral gain (Eq. 7's eta).
    pub ki: f64,
    /// Proportional gain on the smoothed violation.
    pub kp: f64,
    /// Derivative gain on the smoothed violation's rise.
    pub kd: f64,
    /// Smoothing of the violation for the P and D terms (EMA weight of the past).
    pub smoothing: f64,
    /// The cap lambda_max.
    pub max: f64,
}

/// The multiplier's state, checkpointed with the run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Multiplier {
    /// lambda as the losses use it.
    pub lambda: f64,
    /// The integral term I (equal to lambda when kp = kd = 0).
    pub integral: f64,
    /// The smoothed violation e.
    pub smoothed: f64,
}

impl Multiplier {
    /// A multiplier starting at `lambda` (the integral starts there too).
    pub fn new(lambda: f64) -> Self {
        Multiplier {
            lambda,
            integral: lambda,
            smoothed: 0.0,
        }
    }

    /// One step on a batch's per-trajectory violations (Eq. 7's max_k (C_k -
    /// delta), or the late over-budget rate less its target); an empty batch
    /// changes nothing.
    pub fn update(&mut self, violations: &[f32], gains: &Gains) {
        let Some(g) = mean_violation(violations) else {
            return;
        };
        self.integral = (self.integral + gains.ki * g).clamp(0.0, gains.max);
        let previous = self.smoothed;
        self.smoothed = gains.smoothing * self.smoothed + (1.0 - gains.smoothing) * g;
        let rise = (self.smoothed - previous).max(0.0);
        self.lambda =
            (self.integral + gains.kp * self.smoothed + gains.kd * rise).clamp(0.0, gains.max);
    }
}

/// When the constraint (the multiplier's updates, the over-budget price)
/// comes on: after `lambda_warmup_updates`, and, with
/// `constraint_after_revisit`, once the training revisit rate, averaged over
/// the last `constraint_revisit_rounds` rounds, reaches it. A count alone
/// prices search on some seeds before the agent has learned to come back to
/// a found goal, and then it never does (issue 18, dx1: revisit 0.47 when
/// the price came at 3000); a condition waits for the skill itself. Once on,
/// it stays on. Checkpointed, so a resumed run starts it where the
/// uninterrupted one would.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ConstraintStart {
    /// The update at which it came on (a measured start only).
    pub since: Option<u64>,
    /// The revisit rates of the latest rounds, oldest first.
    pub recent_revisits: Vec<f64>,
}

impl ConstraintStart {
    /// The update at which the constraint came on, if it acts at update
    /// `updates`.
    pub fn started_at(&self, updates: u64, warmup: u64, after_revisit: Option<f64>) -> Option<u64> {
        match after_revisit {
            None => (updates >= warmup).then_some(warmup),
            Some(_) => self.since,
        }
    }

    /// Takes one collection round's revisit rate (NaN when no trajectory
    /// found the goal before its last episode: not counted) and starts the
    /// constraint once the window's mean reaches `threshold`.
    pub fn observe(
        &mut self,
        revisit_rate: f64,
        updates: u64,
        warmup: u64,
        threshold: f64,
        rounds: usize,
    ) {
        if self.since.is_some() {
            return;
        }
        if revisit_rate.is_finite() {
            self.recent_revisits.push(revisit_rate);
            let excess = self.recent_revisits.len().saturating_sub(rounds);
            self.recent_revisits.drain(..excess);
        }
        let full = self.recent_revisits.len() == rounds;
        let mean = self.recent_revisits.iter().sum::<f64>() / rounds as f64;
        if updates >= warmup && full && mean >= threshold {
            self.since = Some(updates);
        }
    }
}
