//! The time-step token both learners feed the transformer: one construction
//! for EPPO's collection, training and acting and for supervised
//! pretraining's windows and acting, so the two routes differ only in their
//! learning rule and in what they are conditioned on.
//!
//! | part | width | value |
//! |---|---|---|
//! | observation `s_t` | obs_dim | normalised by the learner |
//! | arrived observation | obs_dim | where `a_{t-1}` arrived, normalised the same way |
//! | previous action `a_{t-1}` | action width | one-hot for discrete actions |
//! | reward, cost | 2 | received for `a_{t-1}`, the reward times `reward_scale` |
//! | to-go targets | 1 or 2 | EPPO: CTG; supervised: RTG and CTG (scaled) |
//! | episode start | 1 | 1 at the first step of an episode |
//!
//! The arrived observation is what puts the goal in context: at an episode's
//! end the auto-reset replaces `s_t` by the next episode's start, so without
//! it the token carrying reward 1 would never say where the goal was
//! (Algorithm 1 stores `s_{t+1}`; AMAGO keeps the agent on the goal one
//! step). Inside an episode it equals `s_t`; at a sequence's first step
//! everything received is zeros.

/// What one time step contributes to its token, before normalisation.
#[derive(Clone, Copy, Debug)]
pub struct StepToken<'a> {
    pub obs: &'a [f32],
    /// The observation the previous action arrived at.
    pub arrived_obs: &'a [f32],
    /// The previous action (one-hot for discrete actions).
    pub prev_action: &'a [f32],
    /// Reward and cost received for the previous action.
    pub reward: f32,
    pub cost: f32,
    /// Conditioning values, already scaled (EPPO: [CTG]; supervised: [RTG, CTG]).
    pub to_go: &'a [f32],
    pub start: bool,
}

/// Width of a token for `obs_dim`, an action part of `action_width` and
/// `n_to_go` conditioning values.
pub fn token_dim(obs_dim: usize, action_width: usize, n_to_go: usize) -> usize {
    2 * obs_dim + action_width + 2 + n_to_go + 1
}

/// Appends one token to `out`; `normalise` appends a normalised observation.
pub fn push_token(
    step: &StepToken<'_>,
    reward_scale: f32,
    normalise: impl Fn(&[f32], &mut Vec<f32>),
    out: &mut Vec<f32>,
) {
    normalise(step.obs, out);
    normalise(step.arrived_obs, out);
    out.extend_from_slice(step.prev_action);
    out.push(step.reward * reward_scale);
    out.push(step.cost);
    out.extend_from_slice(step.to_go);
    out.push(if step.start { 1.0 } else { 0.0 });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_part_lands_in_its_place() {
        let step = StepToken {
            obs: &[1.0, 2.0],
            arrived_obs: &[3.0, 4.0],
            prev_action: &[0.0, 1.0, 0.0],
            reward: 1.0,
            cost: 1.0,
            to_go: &[0.5, 0.25],
            start: true,
        };
        let mut out = Vec::new();
        push_token(
            &step,
            10.0,
            |o, out| out.extend(o.iter().map(|x| -x)),
            &mut out,
        );
        assert_eq!(out.len(), token_dim(2, 3, 2));
        assert_eq!(
            out,
            [
                -1.0, -2.0, -3.0, -4.0, 0.0, 1.0, 0.0, 10.0, 1.0, 0.5, 0.25, 1.0
            ]
        );
    }
}
