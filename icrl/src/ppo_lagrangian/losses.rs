//! The update's small parts: the observation normaliser, the Lagrange
//! multiplier, GAE, the clipped surrogate and the combined advantage.

use tch::{Kind, Tensor};

/// Running mean and variance of observations (parallel Welford update).
#[derive(Clone, Debug)]
pub struct RunningNorm {
    mean: Vec<f64>,
    var: Vec<f64>,
    count: f64,
}

impl RunningNorm {
    pub fn new(dim: usize) -> Self {
        RunningNorm {
            mean: vec![0.0; dim],
            var: vec![1.0; dim],
            count: 1e-4,
        }
    }

    /// Folds in a batch of rows (row-major, `dim` columns).
    pub fn update(&mut self, rows: &[f32]) {
        let dim = self.mean.len();
        let n = (rows.len() / dim) as f64;
        if n == 0.0 {
            return;
        }
        for j in 0..dim {
            let col = rows.iter().skip(j).step_by(dim).map(|&x| x as f64);
            let bmean = col.clone().sum::<f64>() / n;
            let bvar = col.map(|x| (x - bmean).powi(2)).sum::<f64>() / n;
            let delta = bmean - self.mean[j];
            let total = self.count + n;
            self.mean[j] += delta * n / total;
            let m2 = self.var[j] * self.count + bvar * n + delta * delta * self.count * n / total;
            self.var[j] = m2 / total;
        }
        self.count += n;
    }

    /// Normalises `rows` into `out`, clipped to +-10.
    pub fn normalize(&self, rows: &[f32], out: &mut Vec<f32>) {
        let dim = self.mean.len();
        out.clear();
        out.extend(rows.iter().enumerate().map(|(i, &x)| {
            let j = i % dim;
            (((x as f64 - self.mean[j]) / (self.var[j] + 1e-8).sqrt()).clamp(-10.0, 10.0)) as f32
        }));
    }
}

/// The Lagrange multiplier with its own scalar Adam (OmniSafe's `Lagrange`).
#[derive(Clone, Debug)]
pub struct Lagrange {
    pub value: f64,
    lr: f64,
    max: f64,
    m: f64,
    v: f64,
    t: i32,
}

impl Lagrange {
    pub fn new(init: f64, lr: f64, max: f64) -> Self {
        Lagrange {
            value: init,
            lr,
            max,
            m: 0.0,
            v: 0.0,
            t: 0,
        }
    }

    /// One Adam step on `-lambda * (episode_cost - cost_limit)`, then clamps to
    /// `[0, max]`: rises while the measured cost exceeds the limit.
    pub fn update(&mut self, episode_cost: f64, cost_limit: f64) {
        let (b1, b2, eps) = (0.9, 0.999, 1e-8);
        let grad = -(episode_cost - cost_limit);
        self.t += 1;
        self.m = b1 * self.m + (1.0 - b1) * grad;
        self.v = b2 * self.v + (1.0 - b2) * grad * grad;
        let m_hat = self.m / (1.0 - b1.powi(self.t));
        let v_hat = self.v / (1.0 - b2.powi(self.t));
        self.value -= self.lr * m_hat / (v_hat.sqrt() + eps);
        self.value = self.value.clamp(0.0, self.max);
    }
}

/// Generalised advantage estimation over one environment's steps in time
/// order. `next_values[t]` is the value of the observation after step `t`
/// (for a truncated step: the final observation of the cut episode).
///
/// `terminated` steps bootstrap nothing (the goal ends the task); truncated
/// steps bootstrap `next_values` but, like terminated ones, stop the
/// advantage recursion because the next buffered step belongs to a new
/// episode (`done = terminated | truncated`). The last buffered step always
/// bootstraps from `next_values` (the rollout, not the episode, ended there).
/// Returns `(advantages, returns)`.
pub fn gae(
    rewards: &[f32],
    values: &[f32],
    next_values: &[f32],
    terminated: &[bool],
    done: &[bool],
    gamma: f64,
    lambda: f64,
) -> (Vec<f32>, Vec<f32>) {
    let n = rewards.len();
    let mut adv = vec![0.0f32; n];
    let mut last = 0.0f64;
    for t in (0..n).rev() {
        // Terminal: no bootstrap. Truncated or mid-episode: bootstrap.
        let next_v = if terminated[t] {
            0.0
        } else {
            next_values[t] as f64
        };
        let delta = rewards[t] as f64 + gamma * next_v - values[t] as f64;
        // The recursion continues only inside an episode.
        let carry = if done[t] || t == n - 1 { 0.0 } else { last };
        last = delta + gamma * lambda * carry;
        adv[t] = last as f32;
    }
    let ret = adv.iter().zip(values).map(|(a, v)| a + v).collect();
    (adv, ret)
}

/// PPO's clipped surrogate loss (to minimise):
/// `mean(max(-A * ratio, -A * clip(ratio, 1 - c, 1 + c)))`.
pub fn clipped_surrogate(ratio: &Tensor, advantages: &Tensor, clip: f64) -> Tensor {
    let unclipped = -advantages * ratio;
    let clipped = -advantages * ratio.clamp(1.0 - clip, 1.0 + clip);
    unclipped.max_other(&clipped).mean(Kind::Float)
}

/// The combined advantage `(A_r - lambda * A_c) / (1 + lambda)`, `A_r`
/// standardised and `A_c` centred (OmniSafe).
pub fn combined_advantage(adv_r: &[f32], adv_c: &[f32], lambda: f64) -> Vec<f32> {
    let n = adv_r.len().max(1) as f64;
    let mean_r = adv_r.iter().map(|&x| x as f64).sum::<f64>() / n;
    let std_r = (adv_r
        .iter()
        .map(|&x| (x as f64 - mean_r).powi(2))
        .sum::<f64>()
        / n)
        .sqrt();
    let mean_c = adv_c.iter().map(|&x| x as f64).sum::<f64>() / n;
    adv_r
        .iter()
        .zip(adv_c)
        .map(|(&r, &c)| {
            let r = (r as f64 - mean_r) / (std_r + 1e-8);
            let c = c as f64 - mean_c;
            ((r - lambda * c) / (1.0 + lambda)) as f32
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gae_bootstraps_on_truncation_only() {
        // Two one-step episodes, reward 1, V = 0.5 everywhere, next V = 2.
        let r = [1.0, 1.0];
        let v = [0.5, 0.5];
        let nv = [2.0, 2.0];
        let done = [true, true];
        let (a_term, _) = gae(&r, &v, &nv, &[true, true], &done, 0.9, 0.95);
        let (a_trunc, ret) = gae(&r, &v, &nv, &[false, false], &done, 0.9, 0.95);
        assert!(
            (a_term[0] - 0.5).abs() < 1e-6,
            "terminal: 1 - 0.5, got {}",
            a_term[0]
        );
        assert!(
            (a_trunc[0] - (1.0 + 0.9 * 2.0 - 0.5)).abs() < 1e-6,
            "truncated bootstraps"
        );
        assert!((ret[0] - 2.8).abs() < 1e-6);
        // Inside an episode the recursion carries: a0 = d0 + g*l*a1.
        let (a, _) = gae(
            &r,
            &v,
            &[0.5, 2.0],
            &[false, true],
            &[false, true],
            0.9,
            0.95,
        );
        let d1 = 1.0 - 0.5;
        let d0 = 1.0 + 0.9 * 0.5 - 0.5;
        assert!((a[0] - (d0 + 0.9 * 0.95 * d1)).abs() < 1e-6);
        // ... and stops at an episode boundary.
        let (a, _) = gae(&r, &v, &nv, &[false, false], &[true, false], 0.9, 0.95);
        assert!((a[0] - (1.0 + 1.8 - 0.5)).abs() < 1e-6);
    }

    #[test]
    fn clipped_surrogate_clips_in_the_pessimistic_direction() {
        let ratio = Tensor::from_slice(&[1.5f32, 0.5]);
        let adv = Tensor::from_slice(&[1.0f32, -1.0]);
        // ratio 1.5 with A > 0: clipped to 1.2 -> -1.2; ratio 0.5 with A < 0: clipped to 0.8 -> 0.8.
        let loss = clipped_surrogate(&ratio, &adv, 0.2).double_value(&[]);
        assert!((loss - (-1.2 + 0.8) / 2.0).abs() < 1e-6, "{loss}");
        // Where clipping would be optimistic the unclipped term wins.
        let loss = clipped_surrogate(
            &Tensor::from_slice(&[0.5f32]),
            &Tensor::from_slice(&[1.0f32]),
            0.2,
        );
        assert!((loss.double_value(&[]) + 0.5).abs() < 1e-6);
    }

    #[test]
    fn lagrange_rises_with_violation_and_stays_in_bounds() {
        let mut l = Lagrange::new(0.001, 0.035, 0.05);
        l.update(3.0, 0.0);
        assert!(l.value > 0.001 + 0.03, "rises by about lr: {}", l.value);
        l.update(3.0, 0.0);
        assert_eq!(l.value, 0.05, "capped at max");
        for _ in 0..20 {
            l.update(0.0, 5.0);
        }
        assert_eq!(l.value, 0.0, "falls to, and is clamped at, zero");
    }

    #[test]
    fn combined_advantage_penalises_cost_by_lambda() {
        let ar = [1.0, -1.0];
        let ac = [1.0, -1.0];
        let a0 = combined_advantage(&ar, &ac, 0.0);
        assert!((a0[0] - 1.0).abs() < 1e-4);
        // lambda 1: (1 - 1) / 2 = 0.
        let a1 = combined_advantage(&ar, &ac, 1.0);
        assert!(a1[0].abs() < 1e-4, "{a1:?}");
    }

    #[test]
    fn running_norm_matches_batch_statistics() {
        let mut n = RunningNorm::new(2);
        n.update(&[1.0, 10.0, 3.0, 10.0]);
        n.update(&[5.0, 10.0]);
        let mut out = Vec::new();
        // Column 0 holds 1, 3, 5: mean 3, variance 8/3 (the 1e-4 prior count barely moves it).
        n.normalize(&[5.0, 10.0], &mut out);
        assert!(
            (out[0] - 2.0 / (8.0f32 / 3.0).sqrt()).abs() < 1e-3,
            "{out:?}"
        );
        // A constant column normalises to about 0.
        assert!(out[1].abs() < 1e-2, "{out:?}");
    }
}
