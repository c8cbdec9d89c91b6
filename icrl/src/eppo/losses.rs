//! The update's terms on one batch: the critic losses Lv and Lc with n-step
//! TD targets, the actor loss Lp, the multiplier step of Eq. (7) and the
//! Polyak update of the target networks.

use serde::Serialize;
use tch::{Device, Kind, Tensor, nn};

use super::config::{EppoConfig, EppoError, PenaltyForm};
use super::net::{EppoNet, Head, tanh_gaussian_sample};
use super::replay::Batch;

/// Scalars of one update.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct UpdateStats {
    pub value_loss: f64,
    pub cost_value_loss: f64,
    pub policy_loss: f64,
    pub entropy: f64,
    pub grad_norm: f64,
    pub lambda: f64,
    /// Diagnostics: mean Q(h_t, a_t) of the reward critics on the replayed
    /// actions, mean reward TD target, and (continuous actions) the actor's
    /// mean log-std; NaN where not defined.
    pub q_mean: f64,
    pub target_mean: f64,
    pub log_std_mean: f64,
    /// The goal-recall loss (NaN without the head).
    pub goal_recall_loss: f64,
    /// Mean Q of the novelty critics on the replayed actions (NaN without).
    pub novelty_q_mean: f64,
}

/// What [`losses`] returns besides the three losses and the entropy.
pub(super) struct LossDiagnostics {
    pub(super) q_mean: Tensor,
    pub(super) target_mean: Tensor,
    pub(super) log_std_mean: Option<Tensor>,
    /// The goal-recall loss (with gradient), where the net has the head.
    pub(super) goal_recall: Option<Tensor>,
    /// Mean Q of the novelty critics on the replayed actions, where the net
    /// has them.
    pub(super) novelty_q_mean: Option<Tensor>,
}

/// Shifts (B, L) left by one along time: out[:, t] = x[:, t + 1], 0 at the end.
pub(super) fn next_step(x: &Tensor) -> Tensor {
    let l = x.size()[1];
    let zero = x.narrow(1, 0, 1).zeros_like(); // (B, 1)
    Tensor::cat(&[x.narrow(1, 1, l - 1), zero], 1) // (B, L)
}

pub(super) fn masked_mean(x: &Tensor, mask: &Tensor) -> Tensor {
    (x * mask).sum(Kind::Float) / mask.sum(Kind::Float).clamp_min(1.0)
}

/// n-step TD targets, (B, L) each: y1_t = r_t + gamma b_t V'_{t+1} and
/// y(m)_t = r_t + gamma b_t [y(m-1)_{t+1} if step t + 1 has a target of its
/// own, else V'_{t+1}], so every sum stops where its bootstrap mask `b`
/// stops (terminal, trajectory or window end) and falls back to the one-step
/// bootstrap at a step without a target (truncated, episodes apart).
/// `v_next` is V'(t + 1) at position t.
pub(super) fn n_step_targets(
    r: &Tensor,
    bootstrap: &Tensor,
    td_valid: &Tensor,
    v_next: &Tensor,
    gamma: f64,
    n: usize,
) -> Tensor {
    let mut y = r + bootstrap * v_next * gamma;
    let valid_next = next_step(td_valid);
    for _ in 1..n {
        let ahead = &valid_next * next_step(&y) + (valid_next.ones_like() - &valid_next) * v_next;
        y = r + bootstrap * ahead * gamma;
    }
    y
}

/// The three losses on one batch (before any step), and the policy entropy;
/// `lambda` prices the cost, `entropy_coef` weighs the entropy bonus (both
/// the learner's current values). With novelty critics, Lv also holds their
/// TD loss on the novelty rewards.
pub(super) fn losses(
    net: &EppoNet,
    target: &EppoNet,
    batch: &Batch,
    lambda: f64,
    entropy_coef: f64,
    cfg: &EppoConfig,
) -> Result<(Tensor, Tensor, Tensor, Tensor, LossDiagnostics), EppoError> {
    // Dropout and the reparameterisation noise draw from libtorch's generator.
    crate::torch_rng::drawing(|| {
        let (h, ht) = encodings(net, target, &batch.tokens)?; // (B, L, D) each
        let c = cfg.model.n_critics;
        let (y, yc, yn) = td_targets(net, target, &ht, batch, cfg)?; // (B, L) each
        let td_mask = batch.td_valid.unsqueeze(-1); // (B, L, 1)
        let actor = match net.spec.n_actions {
            Some(_) => discrete_actor(net, &h, batch, lambda, entropy_coef, cfg),
            None => continuous_actor(net, &h, batch, lambda, entropy_coef, cfg),
        };
        let diagnostics = LossDiagnostics {
            q_mean: masked_mean(
                &actor.q_taken.detach().mean_dim(-1, false, Kind::Float),
                &batch.td_valid,
            ),
            target_mean: masked_mean(&y, &batch.td_valid),
            log_std_mean: actor.log_std_mean,
            goal_recall: net
                .goal_recall
                .as_ref()
                .map(|head| goal_recall_loss(head, &h, batch)),
            novelty_q_mean: actor.qn_taken.as_ref().map(|qn| {
                masked_mean(
                    &qn.detach().mean_dim(-1, false, Kind::Float),
                    &batch.td_valid,
                )
            }),
        };
        let td_loss = |q: &Tensor, y: &Tensor| {
            masked_mean(
                &(q - y.unsqueeze(-1)).square(),
                &td_mask.expand([-1, -1, c], false),
            )
        };
        let mut value_loss = td_loss(&actor.q_taken, &y);
        if let (Some(qn), Some(yn)) = (&actor.qn_taken, &yn) {
            value_loss += td_loss(qn, yn);
        }
        let cost_value_loss = td_loss(&actor.qc_taken, &yc);
        Ok((
            value_loss,
            cost_value_loss,
            actor.policy_loss,
            actor.entropy,
            diagnostics,
        ))
    })
}

/// Squared distance between the goal read off h_t and the trajectory's goal,
/// averaged over the steps after the window's first success.
pub(super) fn goal_recall_loss(head: &Head, h: &Tensor, batch: &Batch) -> Tensor {
    let recalled = head.forward(h); // (B, L, 2)
    let error = (recalled - batch.goal.unsqueeze(1))
        .square()
        .sum_dim_intlist(-1, false, Kind::Float); // (B, L)
    masked_mean(&error, &batch.goal_known)
}

/// The online encoding h (with gradient, dropout on) and the target
/// network's ht (no gradient), (B, L, D) each. Where the learner has more
/// than one libtorch thread on the CPU, the target's forward runs on a thread of its
/// own beside the online forward, one libtorch thread each, instead of both
/// one after the other on all of them: a 2-layer transformer on 8-wide heads
/// gains little from a second intra-op thread (BENCHMARKS.md). The target's
/// forward draws nothing from libtorch's generator (no dropout), so which
/// thread runs it changes no result, and the schedule is fixed, so a run
/// stays deterministic under its seed.
fn encodings(
    net: &EppoNet,
    target: &EppoNet,
    tokens: &Tensor,
) -> Result<(Tensor, Tensor), EppoError> {
    let threads = tch::get_num_threads();
    let beside = TargetForward {
        target,
        tokens: tokens.shallow_clone(),
    };
    if threads < 2 || tokens.device() != Device::Cpu {
        return Ok((net.encode(tokens, true)?, beside.run()?));
    }
    tch::set_num_threads(1);
    let (h, ht) = std::thread::scope(|s| {
        let ht = s.spawn(move || {
            tch::set_num_threads(1);
            beside.run()
        });
        let h = net.encode(tokens, true);
        let ht = ht.join().unwrap_or_else(|_| {
            Err(EppoError::Config(
                "the target network's forward thread panicked".into(),
            ))
        });
        (h, ht)
    });
    tch::set_num_threads(threads);
    Ok((h?, ht?))
}

/// The target network's forward, handed to a thread of its own.
struct TargetForward<'a> {
    target: &'a EppoNet,
    tokens: Tensor,
}

// SAFETY: the thread only reads the target network's weights, which nothing
// writes until it is joined (the Polyak step comes after the losses), and
// libtorch's CPU kernels may read one tensor from several threads at once.
unsafe impl Send for TargetForward<'_> {}

impl TargetForward<'_> {
    fn run(self) -> Result<Tensor, EppoError> {
        tch::no_grad(|| self.target.encode(&self.tokens, false))
    }
}

/// The reward, cost and (with novelty critics) novelty TD targets y, yc
/// and yn, (B, L) each, from the target networks at t + 1 (no gradient),
/// given the target network's encoding `ht`.
fn td_targets(
    net: &EppoNet,
    target: &EppoNet,
    ht: &Tensor,
    batch: &Batch,
    cfg: &EppoConfig,
) -> Result<(Tensor, Tensor, Option<Tensor>), EppoError> {
    // Each step's values from the target networks under the target actor,
    // no gradient: (B, L, C) per head, then over the C critics.
    let (v, vc, vn) = tch::no_grad(|| -> Result<_, EppoError> {
        let values: Box<dyn Fn(&Head) -> Tensor + '_> = match net.spec.n_actions {
            Some(_) => {
                // Expected value under the target actor: sum_a pi'(a) Q'(h, a).
                let pi = target
                    .actor
                    .forward(ht)
                    .softmax(-1, Kind::Float)
                    .unsqueeze(2); // (B, L, 1, A)
                Box::new(move |head| {
                    (target.critic_values(head, ht, false) * &pi).sum_dim_intlist(
                        -1,
                        false,
                        Kind::Float,
                    )
                })
            }
            None => {
                let (mean, log_std) = target.gaussian(ht);
                let (a, _) = tanh_gaussian_sample(&mean, &log_std, &mean.randn_like());
                Box::new(move |head| target.critic_sa(head, ht, &a, false))
            }
        };
        let mean = |q: Tensor| q.mean_dim(-1, false, Kind::Float);
        Ok((
            values(&target.critic).amin(-1, false),
            mean(values(&target.cost_critic)),
            target
                .novelty_critic
                .as_ref()
                .map(|head| mean(values(head))),
        )) // (B, L) each
    })?;
    // y = r + gamma * [bootstraps] * V'(t + 1); the bootstrap masks carry the
    // terminated / truncated / trajectory-end decision made in `make_batch`;
    // the cost's also stops at every episode end (per-episode constraint).
    let targets = |r: &Tensor, bootstrap: &Tensor, v: &Tensor| {
        n_step_targets(
            r,
            bootstrap,
            &batch.td_valid,
            &next_step(v),
            cfg.targets.gamma,
            cfg.targets.n_step,
        ) // (B, L)
    };
    let y = targets(&batch.rewards, &batch.bootstrap, &v);
    let yc = targets(&batch.costs, &batch.cost_bootstrap, &vc);
    // The novelty critics bootstrap as the reward critics do; their reward
    // stops at the trajectory's first success.
    let yn = batch
        .novelty_rewards
        .as_ref()
        .zip(vn.as_ref())
        .map(|(r, v)| targets(r, &batch.bootstrap, v));
    Ok((y, yc, yn))
}

/// The actor's terms and the critics on the replayed actions.
struct ActorTerms {
    /// (B, L, C) the reward, cost and (where the net has them) novelty
    /// critics at (h_t, a_t).
    q_taken: Tensor,
    qc_taken: Tensor,
    qn_taken: Option<Tensor>,
    /// Lp and the policy entropy, masked means.
    policy_loss: Tensor,
    entropy: Tensor,
    /// Continuous actions: the actor's mean log-std.
    log_std_mean: Option<Tensor>,
}

/// The novelty critics' weight in the actor, (B, L): 1 on the steps whose
/// context holds no success yet, 0 after one (nothing to search for).
fn searching(batch: &Batch) -> Tensor {
    batch.goal_known.ones_like() - &batch.goal_known
}

/// Discrete actions: Lp as the expectation of -Q + lambda v_e Qc under the
/// actor's own distribution, minus the entropy bonus; Q
/// holds the novelty critics' value while searching.
fn discrete_actor(
    net: &EppoNet,
    h: &Tensor,
    batch: &Batch,
    lambda: f64,
    entropy_coef: f64,
    cfg: &EppoConfig,
) -> ActorTerms {
    let q_all = net.critic_values(&net.critic, h, false); // (B, L, C, A)
    let qc_all = net.critic_values(&net.cost_critic, h, false); // (B, L, C, A)
    let idx = batch
        .actions
        .view([batch.actions.size()[0], -1, 1, 1])
        .expand([-1, -1, cfg.model.n_critics, 1], false); // (B, L) -> (B, L, C, 1)
    let q_taken = q_all.gather(3, &idx, false).squeeze_dim(3); // (B, L, C)
    let qc_taken = qc_all.gather(3, &idx, false).squeeze_dim(3); // (B, L, C)
    let qn_all = net
        .novelty_critic
        .as_ref()
        .map(|head| net.critic_values(head, h, false)); // (B, L, C, A)
    let qn_taken = qn_all
        .as_ref()
        .map(|qn| qn.gather(3, &idx, false).squeeze_dim(3)); // (B, L, C)
    // Actor: expectation of -Q + lambda v_e Qc under its own distribution;
    // critic values are constants here (detached).
    let logits = net.actor.forward(h); // (B, L, A)
    let logp = logits.log_softmax(-1, Kind::Float);
    let pi = logp.exp();
    let mut q = q_all.detach().amin(2, false); // (B, L, A)
    if let Some(qn) = &qn_all {
        q += qn.detach().mean_dim(2, false, Kind::Float) * searching(batch).unsqueeze(-1);
    }
    let qc = qc_all.detach().mean_dim(2, false, Kind::Float); // (B, L, A)
    let penalty = lambda * cfg.targets.reward_scale;
    let paid = penalised_cost(
        &qc,
        &batch.violated.unsqueeze(-1),
        &batch.ctg.unsqueeze(-1),
        cfg.constraint.penalty,
    ); // (B, L, A)
    let per_action = q.neg() + paid * penalty; // (B, L, A)
    let entropy = (&pi * &logp).sum_dim_intlist(-1, false, Kind::Float).neg(); // (B, L)
    let objective =
        (&pi * per_action).sum_dim_intlist(-1, false, Kind::Float) - &entropy * entropy_coef;
    ActorTerms {
        q_taken,
        qc_taken,
        qn_taken,
        policy_loss: masked_mean(&objective, &batch.valid),
        entropy: masked_mean(&entropy, &batch.valid),
        log_std_mean: None,
    }
}

/// Continuous actions: Lp on a reparameterised tanh-Gaussian sample a_hat,
/// judged by frozen critics (the novelty critics' value added while
/// searching).
fn continuous_actor(
    net: &EppoNet,
    h: &Tensor,
    batch: &Batch,
    lambda: f64,
    entropy_coef: f64,
    cfg: &EppoConfig,
) -> ActorTerms {
    let q_taken = net.critic_sa(&net.critic, h, &batch.actions, false); // (B, L, C)
    let qc_taken = net.critic_sa(&net.cost_critic, h, &batch.actions, false); // (B, L, C)
    let qn_taken = net
        .novelty_critic
        .as_ref()
        .map(|head| net.critic_sa(head, h, &batch.actions, false)); // (B, L, C)
    let (mean, log_std) = net.gaussian(h);
    let log_std_mean = Some(masked_mean(
        &log_std.detach().mean_dim(-1, false, Kind::Float),
        &batch.valid,
    ));
    let (a_hat, log_prob) = tanh_gaussian_sample(&mean, &log_std, &mean.randn_like());
    // The critics judge a_hat with frozen parameters and a detached
    // trajectory encoding: the actor loss moves only the actor (and the
    // encoder through the actor's input).
    let hd = h.detach();
    let q_hat = net.critic_sa(&net.critic, &hd, &a_hat, true); // (B, L, C)
    // Not `+=` (in place): amin's backward still needs its output.
    let q = match &net.novelty_critic {
        Some(head) => {
            let qn = net.critic_sa(head, &hd, &a_hat, true); // (B, L, C)
            q_hat.amin(-1, false) + qn.mean_dim(-1, false, Kind::Float) * searching(batch)
        }
        None => q_hat.amin(-1, false),
    }; // (B, L)
    let qc = net
        .critic_sa(&net.cost_critic, &hd, &a_hat, true)
        .mean_dim(-1, false, Kind::Float); // (B, L)
    let penalty = lambda * cfg.targets.reward_scale;
    let paid = penalised_cost(&qc, &batch.violated, &batch.ctg, cfg.constraint.penalty); // (B, L)
    let objective = q.neg() + paid * penalty + &log_prob * entropy_coef;
    ActorTerms {
        q_taken,
        qc_taken,
        qn_taken,
        policy_loss: masked_mean(&objective, &batch.valid),
        entropy: masked_mean(&log_prob.neg(), &batch.valid),
        log_std_mean,
    }
}

/// The cost the actor is charged for, before lambda x reward_scale:
/// Qc on the steps of episodes that ended over budget (`violated` 1; the
/// termination too, whose multiplier stays at 0 unless it is given one), or,
/// for the hinge, max(0, Qc - CTG), the predicted remaining cost past the
/// remaining budget; nothing under Saute or the excess price, whose price is
/// in the critics' targets. `violated` and `ctg` broadcast against `qc`.
pub(super) fn penalised_cost(
    qc: &Tensor,
    violated: &Tensor,
    ctg: &Tensor,
    form: PenaltyForm,
) -> Tensor {
    match form {
        PenaltyForm::Hindsight | PenaltyForm::Terminate => qc * violated,
        PenaltyForm::Hinge => (qc - ctg).relu(),
        PenaltyForm::Saute | PenaltyForm::Excess => qc.zeros_like(),
    }
}

/// SAC's temperature step in log space: the weight rises while the policy's
/// entropy is below `target` and falls while above it.
pub(super) fn tuned_entropy_coef(coef: f64, entropy: f64, target: f64, lr: f64) -> f64 {
    // Kept inside [1e-8, 1e3] so that one bad batch cannot zero or explode it.
    (coef.ln() + lr * (target - entropy)).exp().clamp(1e-8, 1e3)
}

/// Eq. (7): lambda <- clip(lambda + eta * mean_j max_k (C_jk - delta_j), 0, lambda_max).
pub fn lambda_update(lambda: f64, max_violations: &[f32], eta: f64, lambda_max: f64) -> f64 {
    match mean_violation(max_violations) {
        Some(g) => (lambda + eta * g).clamp(0.0, lambda_max),
        None => lambda,
    }
}

/// The batch mean of the trajectories' violations (Eq. 7: mean_j max_k (C_jk
/// - delta_j)); `None` for no trajectory.
pub(super) fn mean_violation(violations: &[f32]) -> Option<f64> {
    if violations.is_empty() {
        return None;
    }
    Some(violations.iter().map(|&x| f64::from(x)).sum::<f64>() / violations.len() as f64)
}

/// target <- (1 - tau) target + tau online, for every variable by name.
pub(super) fn polyak(target: &nn::VarStore, online: &nn::VarStore, tau: f64) {
    let src = online.variables();
    tch::no_grad(|| {
        for (name, mut t) in target.variables() {
            if let Some(o) = src.get(&name) {
                let _ = t.g_mul_scalar_(1.0 - tau).g_add_(&(o * tau));
            }
        }
    });
}
