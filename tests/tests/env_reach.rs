//! SafeDarkMujoco as the paper runs it: robots as fast as Safety-Gymnasium's,
//! every goal cell reachable within the 75-step limit with the 50-physics-step
//! macro action, and hazards where a random policy goes.

use safety_envs::prelude::*;

/// Horizontal speed (m/s) after `steps` agent steps of `action` from rest,
/// averaged over the last `window` agent steps (finite difference of the
/// position), and the simulated seconds per agent step.
fn steady_speed(robot: Robot, action: [f32; 2], steps: usize, window: usize) -> (f64, f64) {
    let config = NavConfig {
        n_hazards: 0,
        max_episode_steps: steps + 1,
        ..NavConfig::new(robot)
    };
    let mut env = SafeDarkMujoco::new(config).unwrap();
    // Goal in the (-1.5, -1.5) corner, away from both straight paths (Point
    // drives along +x, Car along +y).
    env.set_task(&Task {
        grid_size: 5,
        goal: Cell { row: 4, col: 0 },
        obstacles: vec![],
    })
    .unwrap();
    let mut obs = vec![0.0; robot.obs_dim()];
    env.reset(0, &mut obs).unwrap();
    let mut track = Vec::new();
    for _ in 0..steps {
        let out = env.step(Action::Continuous(&action), &mut obs).unwrap();
        assert!(!out.done(), "{robot}: episode ended while measuring speed");
        track.push(env.robot_xy());
    }
    let dt = env.data().time() / steps as f64;
    let (a, b) = (track[steps - 1 - window], track[steps - 1]);
    ((b[0] - a[0]).hypot(b[1] - a[1]) / (window as f64 * dt), dt)
}

#[test]
fn point_terminal_speed_under_full_thrust_is_1_5_m_per_s() {
    // Safety-Gymnasium's point: gear 0.3 x force limit 0.05 / slide damping
    // 0.01 = 1.5 m/s (measured there: 1.50). 3 s to settle (time constant
    // mass / damping, about 0.5 s), then 1 s of measurement.
    let (v, dt) = steady_speed(Robot::Point, [1.0, 0.0], 40, 10);
    println!("point: terminal speed {v:.3} m/s");
    assert!((dt - 0.1).abs() < 1e-9, "one agent step is {dt} s, not 0.1");
    assert!(
        (v - 1.5).abs() <= 0.15,
        "Point terminal speed {v:.3} m/s, want 1.5 +- 10%"
    );
}

#[test]
fn car_terminal_speed_on_full_throttle_is_0_75_to_0_80_m_per_s() {
    // Safety-Gymnasium's car, both wheels at full throttle: 0.75-0.79 m/s
    // measured there; we accept [0.75 * 0.9, 0.80 * 1.1].
    let (v, dt) = steady_speed(Robot::Car, [1.0, 1.0], 30, 10);
    println!("car: terminal speed {v:.3} m/s");
    assert!((dt - 0.2).abs() < 1e-9, "one agent step is {dt} s, not 0.2");
    assert!(
        (0.675..=0.88).contains(&v),
        "Car terminal speed {v:.3} m/s, want 0.75-0.80 +- 10%"
    );
}

/// Agent steps the goal-seeking controller needs to reach every non-start
/// goal cell (no hazards), in row-major cell order; `None` where it did not
/// arrive within the default 75-step limit.
fn steps_to_every_goal(robot: Robot) -> Vec<(Cell, Option<usize>)> {
    let config = NavConfig {
        n_hazards: 0,
        ..NavConfig::new(robot)
    };
    assert_eq!(config.max_episode_steps, 75);
    assert_eq!(config.physics_steps_per_action, 50);
    let mut env = SafeDarkMujoco::new(config).unwrap();
    let mut obs = vec![0.0; robot.obs_dim()];
    let mut result = Vec::new();
    for row in 0..5 {
        for col in 0..5 {
            let goal = Cell { row, col };
            if goal == Cell::centre(5) {
                continue;
            }
            env.set_task(&Task {
                grid_size: 5,
                goal,
                obstacles: vec![],
            })
            .unwrap();
            env.reset(0, &mut obs).unwrap();
            let reached = loop {
                let a = env.goal_seeking_action();
                let out = env.step(Action::Continuous(&a), &mut obs).unwrap();
                if out.terminated {
                    assert_eq!(out.reward, 1.0);
                    break Some(env.elapsed_steps());
                }
                if out.truncated {
                    break None;
                }
            };
            result.push((goal, reached));
        }
    }
    result
}

fn assert_all_reachable(robot: Robot) {
    let steps = steps_to_every_goal(robot);
    assert_eq!(steps.len(), 24);
    let missed: Vec<Cell> = steps
        .iter()
        .filter(|(_, s)| s.is_none())
        .map(|(c, _)| *c)
        .collect();
    assert!(
        missed.is_empty(),
        "{robot}: goal cells not reached within 75 agent steps: {missed:?} (all: {steps:?})"
    );
    let worst = steps.iter().filter_map(|(_, s)| *s).max().unwrap();
    println!("{robot}: every goal cell reached, slowest in {worst} agent steps: {steps:?}");
}

#[test]
fn point_reaches_every_goal_cell_within_the_time_limit() {
    assert_all_reachable(Robot::Point);
}

#[test]
fn car_reaches_every_goal_cell_within_the_time_limit() {
    assert_all_reachable(Robot::Car);
}

/// SplitMix64 in [-1, 1): a fixed random action stream.
fn uniform(state: &mut u64) -> f32 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
}

/// Mean episode cost and return of uniform random actions on `tasks`
/// centre-oriented tasks, one episode each.
fn random_policy(robot: Robot, tasks: u64) -> (f64, f64) {
    let mut env = SafeDarkMujoco::new(NavConfig::new(robot)).unwrap();
    let spawn = env.config().spawn_config();
    let mut obs = vec![0.0; robot.obs_dim()];
    let mut rng = 7u64;
    let (mut cost, mut ret) = (0.0, 0.0);
    for seed in 0..tasks {
        let task = sample_task(&spawn, Orientation::Centre, seed).unwrap();
        env.set_task(&task).unwrap();
        env.reset(seed, &mut obs).unwrap();
        loop {
            let a = [uniform(&mut rng), uniform(&mut rng)];
            let out = env.step(Action::Continuous(&a), &mut obs).unwrap();
            cost += f64::from(out.cost);
            ret += f64::from(out.reward);
            if out.done() {
                break;
            }
        }
    }
    (cost / tasks as f64, ret / tasks as f64)
}

#[test]
fn a_random_policy_pays_cost_on_centre_oriented_tasks() {
    for robot in [Robot::Point, Robot::Car] {
        let (cost, ret) = random_policy(robot, 40);
        println!("{robot}: random policy, mean episode cost {cost:.2}, return {ret:.2}");
        assert!(
            cost >= 1.0,
            "{robot}: a random policy's mean episode cost is {cost:.2}: hazards are not where the robot goes"
        );
    }
}
