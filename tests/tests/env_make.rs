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
            ..EnvOptions::default()
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
                    max_episode_steps: Some(0),
                    ..EnvOptions::default()
                }
            )
            .is_err(),
            "{name}"
        );
    }
}

#[test]
fn the_macro_action_is_50_physics_steps_and_an_option() {
    // 5 Safety-Gymnasium steps per action x 10 physics steps each.
    assert_eq!(safety_envs::SG_STEPS_PER_ACTION, 5);
    assert_eq!(safety_envs::PHYSICS_STEPS_PER_SG_STEP, 10);
    assert_eq!(PHYSICS_STEPS_PER_ACTION, 50);
    for name in [EnvName::Point, EnvName::Car] {
        let env = make_env(name, &EnvOptions::default()).unwrap();
        assert_eq!(env.physics_steps_per_action(), Some(50), "{name}");
        let env = make_env(
            name,
            &EnvOptions {
                physics_steps_per_action: Some(20),
                ..EnvOptions::default()
            },
        )
        .unwrap();
        assert_eq!(env.physics_steps_per_action(), Some(20), "{name}");
        let zero = EnvOptions {
            physics_steps_per_action: Some(0),
            ..EnvOptions::default()
        };
        assert!(make_env(name, &zero).is_err(), "{name}");
        let huge = EnvOptions {
            physics_steps_per_action: Some(1_000_000_000),
            ..EnvOptions::default()
        };
        let err = make_env(name, &huge).err().expect("bounded");
        assert!(err.to_string().contains("at most 10000"), "{err}");
    }
    // What checkpoints and datasets record.
    assert_eq!(EnvName::Point.physics_steps_per_action(None), Some(50));
    assert_eq!(EnvName::Car.physics_steps_per_action(Some(20)), Some(20));
    assert_eq!(EnvName::DarkRoom.physics_steps_per_action(None), None);
    let darkroom = make_env(EnvName::DarkRoom, &EnvOptions::default()).unwrap();
    assert_eq!(darkroom.physics_steps_per_action(), None);
    let err = make_env(
        EnvName::DarkRoom,
        &EnvOptions {
            physics_steps_per_action: Some(50),
            ..EnvOptions::default()
        },
    )
    .err()
    .expect("darkroom has no physics steps");
    assert!(err.to_string().contains("no physics"), "{err}");
}

#[test]
fn one_agent_step_simulates_the_macro_action() {
    // Point's timestep is 0.002 s, Car's 0.004 s: 50 physics steps are 0.1 s
    // and 0.2 s of simulated time.
    for (robot, dt) in [(Robot::Point, 0.1), (Robot::Car, 0.2)] {
        let mut env = SafeDarkMujoco::new(NavConfig::new(robot)).unwrap();
        let mut obs = vec![0.0; robot.obs_dim()];
        env.reset(0, &mut obs).unwrap();
        env.step(Action::Continuous(&[0.0, 0.0]), &mut obs).unwrap();
        let t = env.data().time();
        assert!((t - dt).abs() < 1e-9, "{robot}: one agent step took {t} s");
    }
}
