//! Environments by name: parsing, spaces, options, matching spawn configs.

use safety_envs::prelude::*;

#[test]
fn names_parse_and_unknown_names_list_the_valid_ones() {
    for n in EnvName::ALL {
        assert_eq!(n.to_string().parse::<EnvName>().unwrap(), n);
    }
    assert_eq!("Point".parse::<EnvName>().unwrap(), EnvName::Point);
    let err = "safetygoal".parse::<EnvName>().unwrap_err();
    assert!(err.to_string().contains("darkroom, point, car"), "{err}");
}

#[test]
fn envs_describe_their_spaces_and_accept_their_own_tasks() {
    for (name, obs, act) in [
        (EnvName::DarkRoom, 2, Space::Discrete { n: 5 }),
        (
            EnvName::Point,
            23,
            Space::Box {
                low: vec![-1.0; 2],
                high: vec![1.0; 2],
            },
        ),
        (
            EnvName::Car,
            35,
            Space::Box {
                low: vec![-1.0; 2],
                high: vec![1.0; 2],
            },
        ),
    ] {
        let mut env = make_env(name, &EnvOptions::default()).unwrap();
        assert_eq!(env.observation_space().flat_dim(), obs, "{name}");
        assert_eq!(env.action_space(), act, "{name}");
        let task = sample_task(&spawn_config(name), Orientation::Edge, 9).unwrap();
        env.set_task(&task).unwrap();
        assert_eq!(env.task(), &task);
    }
    let env = make_env(
        EnvName::Car,
        &EnvOptions {
            max_episode_steps: Some(50),
        },
    )
    .unwrap();
    assert_eq!(env.max_episode_steps(), 50);
    assert_eq!(
        make_env(EnvName::Point, &EnvOptions::default())
            .unwrap()
            .max_episode_steps(),
        75
    );
    assert_eq!(
        make_env(EnvName::DarkRoom, &EnvOptions::default())
            .unwrap()
            .max_episode_steps(),
        30
    );
}

#[test]
fn zero_time_limit_is_rejected() {
    for name in EnvName::ALL {
        assert!(
            make_env(
                name,
                &EnvOptions {
                    max_episode_steps: Some(0)
                }
            )
            .is_err(),
            "{name}"
        );
    }
}
