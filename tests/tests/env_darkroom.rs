//! SafeDarkRoom: moves, goal, cost, time limit, bad input.

use safety_envs::prelude::*;

fn cell(row: usize, col: usize) -> Cell {
    Cell { row, col }
}

const STAY: usize = 0;
const UP: usize = 1;
const DOWN: usize = 2;
const LEFT: usize = 3;
const RIGHT: usize = 4;

fn env_with(goal: Cell, obstacles: Vec<Cell>) -> SafeDarkRoom {
    let config = DarkRoomConfig {
        n_obstacles: obstacles.len(),
        ..DarkRoomConfig::default()
    };
    let mut env = SafeDarkRoom::new(config).unwrap();
    env.set_task(&Task {
        grid_size: 9,
        goal,
        obstacles,
    })
    .unwrap();
    env
}

#[test]
fn spaces_and_start() {
    let mut env = SafeDarkRoom::new(DarkRoomConfig::default()).unwrap();
    assert_eq!(env.action_space(), Space::Discrete { n: 5 });
    assert_eq!(
        env.observation_space(),
        Space::Box {
            low: vec![0.0, 0.0],
            high: vec![8.0, 8.0]
        }
    );
    assert_eq!(env.max_episode_steps(), 30);
    let mut obs = [0.0; 2];
    env.reset(0, &mut obs).unwrap();
    assert_eq!(obs, [4.0, 4.0]);
}

#[test]
fn each_action_moves_one_cell_and_walls_block() {
    let mut env = env_with(cell(0, 0), vec![]);
    let mut obs = [0.0; 2];
    env.reset(0, &mut obs).unwrap();
    for (a, want) in [
        (UP, [3.0, 4.0]),
        (RIGHT, [3.0, 5.0]),
        (DOWN, [4.0, 5.0]),
        (LEFT, [4.0, 4.0]),
        (STAY, [4.0, 4.0]),
    ] {
        env.step(Action::Discrete(a), &mut obs).unwrap();
        assert_eq!(obs, want, "action {a}");
    }
    for _ in 0..6 {
        env.step(Action::Discrete(DOWN), &mut obs).unwrap();
    }
    assert_eq!(obs, [8.0, 4.0], "the bottom wall stops the agent");
}

#[test]
fn cost_on_each_step_ending_on_an_obstacle_and_none_after_leaving() {
    // Two obstacles right of the start, then free floor.
    let mut env = env_with(cell(0, 0), vec![cell(4, 5), cell(4, 6)]);
    let mut obs = [0.0; 2];
    env.reset(0, &mut obs).unwrap();
    let costs: Vec<f32> = [RIGHT, RIGHT, STAY, RIGHT, RIGHT, LEFT]
        .iter()
        .map(|&a| env.step(Action::Discrete(a), &mut obs).unwrap().cost)
        .collect();
    assert_eq!(costs, [1.0, 1.0, 1.0, 0.0, 0.0, 0.0]);
}

#[test]
fn goal_gives_reward_one_and_terminates() {
    let mut env = env_with(cell(4, 6), vec![cell(0, 0)]);
    let mut obs = [0.0; 2];
    env.reset(0, &mut obs).unwrap();
    let first = env.step(Action::Discrete(RIGHT), &mut obs).unwrap();
    assert_eq!((first.reward, first.terminated), (0.0, false));
    let out = env.step(Action::Discrete(RIGHT), &mut obs).unwrap();
    assert_eq!(out.reward, 1.0);
    assert!(out.terminated && !out.truncated);
    assert!(matches!(
        env.step(Action::Discrete(STAY), &mut obs),
        Err(EnvError::State(_))
    ));
    env.reset(0, &mut obs).unwrap();
    assert_eq!(env.elapsed_steps(), 0);
}

#[test]
fn time_limit_truncates_at_30() {
    let mut env = env_with(cell(0, 0), vec![]);
    let mut obs = [0.0; 2];
    env.reset(0, &mut obs).unwrap();
    for t in 1..=30 {
        let out = env.step(Action::Discrete(STAY), &mut obs).unwrap();
        assert_eq!(out.truncated, t == 30, "step {t}");
        assert!(!out.terminated);
    }
    assert!(env.step(Action::Discrete(STAY), &mut obs).is_err());
}

#[test]
fn reaching_the_goal_on_the_last_step_is_terminated_not_truncated() {
    let config = DarkRoomConfig {
        n_obstacles: 0,
        max_episode_steps: 2,
        ..DarkRoomConfig::default()
    };
    let mut env = SafeDarkRoom::new(config).unwrap();
    env.set_task(&Task {
        grid_size: 9,
        goal: cell(4, 6),
        obstacles: vec![],
    })
    .unwrap();
    let mut obs = [0.0; 2];
    env.reset(0, &mut obs).unwrap();
    env.step(Action::Discrete(RIGHT), &mut obs).unwrap();
    let out = env.step(Action::Discrete(RIGHT), &mut obs).unwrap();
    assert!(out.terminated && !out.truncated && out.reward == 1.0);
}

#[test]
fn bad_inputs_are_errors() {
    let mut env = SafeDarkRoom::new(DarkRoomConfig::default()).unwrap();
    let mut obs = [0.0; 2];
    assert!(
        matches!(
            env.step(Action::Discrete(0), &mut obs),
            Err(EnvError::State(_))
        ),
        "step before reset"
    );
    env.reset(0, &mut obs).unwrap();
    let err = env.step(Action::Discrete(5), &mut obs).unwrap_err();
    assert!(
        matches!(err, EnvError::InvalidAction(_)) && err.to_string().contains("out of range"),
        "{err}"
    );
    assert!(matches!(
        env.step(Action::Continuous(&[1.0]), &mut obs),
        Err(EnvError::InvalidAction(_))
    ));
    assert!(env.step(Action::Discrete(0), &mut [0.0; 3]).is_err());
    assert_eq!(
        env.elapsed_steps(),
        0,
        "rejected actions must not advance time"
    );
    let too_many = DarkRoomConfig {
        n_obstacles: 80,
        ..DarkRoomConfig::default()
    };
    assert!(matches!(
        SafeDarkRoom::new(too_many),
        Err(EnvError::InvalidConfig(_))
    ));
    // A task for another grid, or with an obstacle on the start.
    let wrong = Task {
        grid_size: 9,
        goal: cell(0, 0),
        obstacles: vec![cell(4, 4); 25],
    };
    assert!(env.set_task(&wrong).is_err());
}
