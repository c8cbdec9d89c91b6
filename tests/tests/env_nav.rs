//! SafeDarkMujoco Point and Car: robot motion, cost, goal, time limit,
//! determinism and bad actions.

use safety_envs::prelude::*;

/// Grid cell `(row, col)`.
fn cell(row: usize, col: usize) -> Cell {
    Cell { row, col }
}

/// An environment with one hazard and a chosen goal, and a long time limit.
fn env_with(robot: Robot, goal: Cell, hazard: Cell, max_steps: usize) -> SafeDarkMujoco {
    let config = NavConfig {
        n_hazards: 1,
        max_episode_steps: max_steps,
        ..NavConfig::new(robot)
    };
    let mut env = SafeDarkMujoco::new(config).unwrap();
    env.set_task(&Task {
        grid_size: 5,
        goal,
        obstacles: vec![hazard],
    })
    .unwrap();
    env
}

fn obs_buf(env: &SafeDarkMujoco) -> Vec<f32> {
    vec![0.0; env.observation_space().flat_dim()]
}

/// Angle difference wrapped to (-pi, pi].
fn wrap(a: f64) -> f64 {
    let mut a = a % std::f64::consts::TAU;
    if a > std::f64::consts::PI {
        a -= std::f64::consts::TAU;
    } else if a <= -std::f64::consts::PI {
        a += std::f64::consts::TAU;
    }
    a
}

#[test]
fn observation_sizes_and_first_observation() {
    for (robot, n) in [(Robot::Point, 23), (Robot::Car, 35)] {
        let mut env = SafeDarkMujoco::new(NavConfig::new(robot)).unwrap();
        assert_eq!(env.observation_space().flat_dim(), n);
        assert_eq!(env.action_space().flat_dim(), 2);
        let mut obs = obs_buf(&env);
        env.reset(0, &mut obs).unwrap();
        // At the centre, identity rotation.
        assert_eq!(&obs[..2], &[0.0, 0.0]);
        let eye = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        for (o, e) in obs[2..11].iter().zip(eye) {
            assert!((o - e).abs() < 1e-5, "{robot}: rotation {:?}", &obs[2..11]);
        }
        // Magnetometer reads the field (0, -0.5, 0) in the body frame.
        assert!(
            (obs[21] + 0.5).abs() < 1e-5,
            "{robot}: magnetometer {:?}",
            &obs[20..23]
        );
        // The point (no vertical freedom) rests: its accelerometer reads +g
        // along z. The car settles on its wheels during the first steps.
        if robot == Robot::Point {
            assert!(
                (obs[13] - 9.81).abs() < 0.1,
                "accelerometer {:?}",
                &obs[11..14]
            );
        }
    }
}

#[test]
fn point_thrust_moves_along_heading_and_turn_changes_yaw() {
    let mut env = env_with(Robot::Point, cell(0, 0), cell(4, 4), 200);
    let mut obs = obs_buf(&env);
    env.reset(0, &mut obs).unwrap();
    // Turn only: yaw changes, position barely does.
    let yaw0 = env.robot_yaw();
    for _ in 0..30 {
        env.step(Action::Continuous(&[0.0, 1.0]), &mut obs).unwrap();
    }
    let yaw1 = env.robot_yaw();
    assert!(
        wrap(yaw1 - yaw0).abs() > 0.3,
        "turning moved yaw {yaw0} -> {yaw1}"
    );
    let p1 = env.robot_xy();
    assert!(
        p1[0].hypot(p1[1]) < 0.02,
        "turning alone moved the point to {p1:?}"
    );
    // Thrust only: it moves along its heading.
    for _ in 0..40 {
        env.step(Action::Continuous(&[1.0, 0.0]), &mut obs).unwrap();
    }
    let p2 = env.robot_xy();
    let (dx, dy) = (p2[0] - p1[0], p2[1] - p1[1]);
    let dist = dx.hypot(dy);
    assert!(dist > 0.1, "thrust moved only {dist}");
    let heading = [yaw1.cos(), yaw1.sin()];
    let along = (dx * heading[0] + dy * heading[1]) / dist;
    assert!(along > 0.95, "moved {dx},{dy} against heading {heading:?}");
}

#[test]
fn car_wheels_forward_drive_forward_and_opposite_wheels_turn() {
    let mut env = env_with(Robot::Car, cell(0, 0), cell(4, 4), 200);
    let mut obs = obs_buf(&env);
    env.reset(0, &mut obs).unwrap();
    // 10 agent steps: 2 s of simulated time.
    for _ in 0..10 {
        env.step(Action::Continuous(&[1.0, 1.0]), &mut obs).unwrap();
    }
    // Forward is the chassis +y axis, which is world +y at yaw 0.
    let p = env.robot_xy();
    assert!(
        p[1] > 0.5 && p[0].abs() < 0.1 * p[1],
        "both wheels forward ended at {p:?}"
    );

    env.reset(0, &mut obs).unwrap();
    let yaw0 = env.robot_yaw();
    for _ in 0..40 {
        env.step(Action::Continuous(&[1.0, -1.0]), &mut obs)
            .unwrap();
    }
    let yaw1 = env.robot_yaw();
    let p = env.robot_xy();
    assert!(
        wrap(yaw1 - yaw0).abs() > 0.5,
        "opposite wheels: yaw {yaw0} -> {yaw1}"
    );
    assert!(p[0].hypot(p[1]) < 0.1, "opposite wheels drove it to {p:?}");
}

#[test]
fn cost_appears_inside_a_hazard_and_stops_after_leaving() {
    // Hazard east of the start, at (0.75, 0); the goal far away in the corner.
    let mut env = env_with(Robot::Point, cell(0, 0), cell(2, 3), 300);
    let mut obs = obs_buf(&env);
    env.reset(0, &mut obs).unwrap();
    let mut costs = Vec::new();
    let mut xs = Vec::new();
    while env.robot_xy()[0] < 1.2 {
        let out = env.step(Action::Continuous(&[1.0, 0.0]), &mut obs).unwrap();
        assert!(!out.done(), "episode ended at x = {}", env.robot_xy()[0]);
        assert_eq!(out.reward, 0.0);
        costs.push(out.cost);
        xs.push(env.robot_xy()[0]);
    }
    let first = costs
        .iter()
        .position(|&c| c == 1.0)
        .expect("never paid a cost");
    let last = costs.iter().rposition(|&c| c == 1.0).unwrap();
    // No cost before entering, every step inside costs, none after leaving.
    assert!(
        xs[first] >= 0.55 - 0.05 && first > 0,
        "first cost at x = {}",
        xs[first]
    );
    assert!(costs[first..=last].iter().all(|&c| c == 1.0));
    assert!(xs[last] <= 0.95 + 0.05, "last cost at x = {}", xs[last]);
    assert!(costs[last + 1..].iter().all(|&c| c == 0.0) && last + 1 < costs.len());
}

#[test]
fn reaching_the_goal_gives_reward_one_and_terminates() {
    // Goal east of the start at (0.75, 0): reached when x >= 0.45.
    let mut env = env_with(Robot::Point, cell(2, 3), cell(0, 0), 300);
    let mut obs = obs_buf(&env);
    env.reset(0, &mut obs).unwrap();
    let mut rewards = 0.0;
    loop {
        let out = env.step(Action::Continuous(&[1.0, 0.0]), &mut obs).unwrap();
        rewards += out.reward;
        if out.done() {
            assert!(out.terminated && !out.truncated);
            assert_eq!(out.reward, 1.0);
            break;
        }
        assert!(env.elapsed_steps() < 300);
    }
    assert_eq!(rewards, 1.0);
    let x = env.robot_xy()[0];
    assert!((0.45..0.6).contains(&x), "terminated at x = {x}");
    assert!(matches!(
        env.step(Action::Continuous(&[0.0, 0.0]), &mut obs),
        Err(EnvError::State(_))
    ));
}

#[test]
fn time_limit_truncates() {
    for robot in [Robot::Point, Robot::Car] {
        let mut env = env_with(robot, cell(0, 0), cell(4, 4), 10);
        let mut obs = obs_buf(&env);
        env.reset(0, &mut obs).unwrap();
        for t in 1..=10 {
            let out = env.step(Action::Continuous(&[0.0, 0.0]), &mut obs).unwrap();
            assert_eq!(out.truncated, t == 10);
            assert!(!out.terminated);
        }
        assert!(env.step(Action::Continuous(&[0.0, 0.0]), &mut obs).is_err());
        env.reset(1, &mut obs).unwrap();
        assert_eq!(env.elapsed_steps(), 0);
    }
}

/// A fixed pseudo-random action sequence (SplitMix64), identical everywhere.
fn actions(n: usize) -> Vec<[f32; 2]> {
    let mut s = 0x1234_5678_u64;
    let mut next = || {
        s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
    };
    (0..n).map(|_| [next(), next()]).collect()
}

fn rollout(robot: Robot, seed: u64) -> Vec<u32> {
    let mut env = SafeDarkMujoco::new(NavConfig::new(robot)).unwrap();
    let task = sample_task(&env.config().spawn_config(), Orientation::Edge, seed).unwrap();
    env.set_task(&task).unwrap();
    let mut obs = obs_buf(&env);
    let mut trace = Vec::new();
    env.reset(seed, &mut obs).unwrap();
    for a in actions(200) {
        let out = env.step(Action::Continuous(&a), &mut obs).unwrap();
        trace.extend(obs.iter().map(|v| v.to_bits()));
        trace.extend([out.reward.to_bits(), out.cost.to_bits()]);
        if out.done() {
            env.reset(seed, &mut obs).unwrap();
        }
    }
    trace
}

#[test]
fn same_seed_gives_bitwise_identical_rollouts() {
    for robot in [Robot::Point, Robot::Car] {
        let (a, b) = (rollout(robot, 5), rollout(robot, 5));
        assert!(a == b, "{robot}: two rollouts with seed 5 differ");
        assert_eq!(a.len(), 200 * (robot.obs_dim() + 2));
    }
}

#[test]
fn set_task_moves_the_sites_of_the_compiled_model() {
    let env = env_with(Robot::Car, cell(0, 4), cell(3, 1), 75);
    let m = env.model();
    let goal = m.id(safety_envs::mujoco::ObjType::Site, "goal").unwrap();
    let hz0 = m.id(safety_envs::mujoco::ObjType::Site, "hazard0").unwrap();
    let hz1 = m.id(safety_envs::mujoco::ObjType::Site, "hazard1").unwrap();
    // SAFETY: ids come from `Model::id`, and site_pos holds nsite x 3 numbers.
    let pos = |id: usize| unsafe { std::slice::from_raw_parts(m.raw().site_pos.add(3 * id), 3) };
    assert_eq!(&pos(goal)[..2], &[1.5, 1.5]);
    assert_eq!(&pos(hz0)[..2], &[-0.75, -0.75]);
    assert!(
        pos(hz1)[2] < -1.0,
        "unused hazard not parked: {:?}",
        pos(hz1)
    );
    assert_eq!(env.goal_xy(), [1.5, 1.5]);
}

#[test]
fn bad_actions_are_errors_and_out_of_range_is_clamped() {
    let mut env = SafeDarkMujoco::new(NavConfig::new(Robot::Point)).unwrap();
    let mut obs = obs_buf(&env);
    env.reset(0, &mut obs).unwrap();
    for bad in [
        vec![f32::NAN, 0.0],
        vec![0.0, f32::INFINITY],
        vec![f32::NEG_INFINITY, 0.0],
        vec![0.0],
        vec![0.0, 0.0, 0.0],
    ] {
        let r = env.step(Action::Continuous(&bad), &mut obs);
        assert!(
            matches!(r, Err(EnvError::InvalidAction(_))),
            "{bad:?} gave {r:?}"
        );
    }
    assert!(matches!(
        env.step(Action::Discrete(1), &mut obs),
        Err(EnvError::InvalidAction(_))
    ));
    assert!(matches!(
        env.step(Action::Continuous(&[0.0, 0.0]), &mut [0.0; 3]),
        Err(EnvError::State(_))
    ));
    // None of the rejected actions advanced the episode.
    assert_eq!(env.elapsed_steps(), 0);

    let mut clamped = obs_buf(&env);
    let mut reference = obs_buf(&env);
    let mut other = SafeDarkMujoco::new(NavConfig::new(Robot::Point)).unwrap();
    other.reset(0, &mut reference).unwrap();
    for _ in 0..5 {
        env.step(Action::Continuous(&[7.0, -3.0]), &mut clamped)
            .unwrap();
        other
            .step(Action::Continuous(&[1.0, -1.0]), &mut reference)
            .unwrap();
    }
    assert_eq!(clamped, reference);
}

#[test]
fn bad_configs_are_errors() {
    let too_many = NavConfig {
        n_hazards: 25,
        ..NavConfig::default()
    };
    assert!(matches!(
        SafeDarkMujoco::new(too_many),
        Err(EnvError::InvalidConfig(_))
    ));
    let even = NavConfig {
        grid_size: 6,
        ..NavConfig::default()
    };
    assert!(SafeDarkMujoco::new(even).is_err());
    let mut env = SafeDarkMujoco::new(NavConfig::default()).unwrap();
    let wrong = Task {
        grid_size: 5,
        goal: cell(2, 2),
        obstacles: vec![cell(0, 0); 8],
    };
    assert!(matches!(
        env.set_task(&wrong),
        Err(EnvError::InvalidConfig(_))
    ));
}

#[test]
fn a_blown_up_simulation_is_an_error_not_a_silent_reset() {
    let mut env = SafeDarkMujoco::new(NavConfig::new(Robot::Car)).unwrap();
    let mut obs = obs_buf(&env);
    env.reset(0, &mut obs).unwrap();
    // An absurd time step makes the integrator diverge to NaN or huge values,
    // which MuJoCo answers by resetting the state with a warning.
    env.model_mut().raw_mut().opt.timestep = 1e6;
    let mut result = Ok(StepOutcome::default());
    for _ in 0..50 {
        result = env.step(Action::Continuous(&[1.0, -1.0]), &mut obs);
        if result.is_err() {
            break;
        }
    }
    let err = result.expect_err("no step reported the instability");
    assert!(matches!(err, EnvError::Unstable(_)), "{err}");
    // The episode is over; a reset (with a sane time step) starts a new one.
    assert!(matches!(
        env.step(Action::Continuous(&[0.0, 0.0]), &mut obs),
        Err(EnvError::State(_))
    ));
    env.model_mut().raw_mut().opt.timestep = 0.004;
    env.reset(0, &mut obs).unwrap();
    env.step(Action::Continuous(&[0.0, 0.0]), &mut obs).unwrap();
}
