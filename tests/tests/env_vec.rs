//! VecEnv: determinism across thread counts, auto-reset, bad batches.

use safety_envs::prelude::*;

fn vec_env(name: EnvName, n: usize, threads: usize, auto_reset: bool) -> VecEnv {
    let envs = (0..n)
        .map(|_| make_env(name, &EnvOptions::default()).unwrap())
        .collect();
    let mut v = VecEnv::new(envs, threads, auto_reset).unwrap();
    for i in 0..n {
        let task = sample_task(&spawn_config(name), Orientation::Edge, 100 + i as u64).unwrap();
        v.set_task(i, &task).unwrap();
    }
    v.reset(&(0..n as u64).collect::<Vec<_>>()).unwrap();
    v
}

/// Bit patterns of every observation and outcome over `steps` steps.
fn trace(name: EnvName, threads: usize, steps: usize) -> Vec<u32> {
    let n = 5;
    let mut v = vec_env(name, n, threads, true);
    let mut out = Vec::new();
    for t in 0..steps {
        match name {
            EnvName::DarkRoom => {
                let a: Vec<usize> = (0..n).map(|i| (t * 3 + i * 7 + t / 5) % 5).collect();
                v.step(VecAction::Discrete(&a)).unwrap();
            }
            _ => {
                let a: Vec<f32> = (0..2 * n)
                    .map(|i| (((t * 13 + i * 29) % 17) as f32 / 8.0) - 1.0)
                    .collect();
                v.step(VecAction::Continuous(&a)).unwrap();
            }
        }
        out.extend(v.observations().iter().map(|x| x.to_bits()));
        for o in v.outcomes() {
            out.extend([
                o.reward.to_bits(),
                o.cost.to_bits(),
                o.terminated as u32,
                o.truncated as u32,
            ]);
        }
    }
    out
}

#[test]
fn one_and_two_threads_give_bitwise_identical_results() {
    for (name, steps) in [
        (EnvName::DarkRoom, 200),
        (EnvName::Point, 160),
        (EnvName::Car, 80),
    ] {
        let (a, b) = (trace(name, 1, steps), trace(name, 2, steps));
        assert!(a == b, "{name}: 1 and 2 threads differ");
    }
}

#[test]
fn auto_reset_restarts_finished_episodes_and_keeps_the_final_observation() {
    let mut v = vec_env(EnvName::DarkRoom, 3, 2, true);
    // Walk up for 30 steps: every episode truncates at the time limit together.
    let mut last = Vec::new();
    for t in 1..=30 {
        let outs = v.step(VecAction::Discrete(&[1, 1, 1])).unwrap().to_vec();
        if t < 30 {
            assert!(outs.iter().all(|o| !o.done()) || outs.iter().any(|o| o.terminated));
            last = v.observations().to_vec();
        } else {
            for (i, o) in outs.iter().enumerate() {
                if o.truncated {
                    // The final observation is the last cell, the new one the start.
                    assert_eq!(
                        &v.final_observations()[2 * i..2 * i + 2],
                        &last[2 * i..2 * i + 2]
                    );
                    assert_eq!(&v.observations()[2 * i..2 * i + 2], &[4.0, 4.0]);
                    assert_eq!(v.env(i).elapsed_steps(), 0);
                }
            }
        }
    }
}

#[test]
fn without_auto_reset_a_finished_env_must_be_reset() {
    let mut v = vec_env(EnvName::DarkRoom, 2, 1, false);
    for _ in 0..30 {
        v.step(VecAction::Discrete(&[0, 0])).unwrap();
    }
    let err = v.step(VecAction::Discrete(&[0, 0])).unwrap_err();
    assert!(matches!(err, EnvError::InEnv { index: 0, .. }), "{err}");
}

#[test]
fn bad_batches_are_errors() {
    let mut v = vec_env(EnvName::Point, 2, 2, true);
    assert_eq!((v.len(), v.obs_dim(), v.act_dim()), (2, 23, 2));
    assert!(matches!(
        v.step(VecAction::Continuous(&[0.0; 3])),
        Err(EnvError::InvalidAction(_))
    ));
    assert!(matches!(
        v.step(VecAction::Discrete(&[0, 0])),
        Err(EnvError::InvalidAction(_))
    ));
    let err = v
        .step(VecAction::Continuous(&[0.0, 0.0, f32::NAN, 0.0]))
        .unwrap_err();
    assert!(matches!(err, EnvError::InEnv { index: 1, .. }), "{err}");
    assert!(v.reset(&[1]).is_err());
    assert!(VecEnv::new(Vec::new(), 1, true).is_err());
    let mixed = vec![
        make_env(EnvName::DarkRoom, &EnvOptions::default()).unwrap(),
        make_env(EnvName::Point, &EnvOptions::default()).unwrap(),
    ];
    assert!(VecEnv::new(mixed, 1, true).is_err());
}
