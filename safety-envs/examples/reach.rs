//! How many agent steps a scripted controller that knows the goal
//! ([`SafeDarkMujoco::goal_seeking_action`]) needs to reach each goal cell
//! from the start (no hazards), per robot: is the time limit long enough?
//! `tests/tests/env_reach.rs` asserts that every cell is reached within 75.
//!
//! ```text
//! cargo run --release -p safety-envs --example reach [-- PHYSICS_STEPS_PER_ACTION]
//! ```

use safety_envs::prelude::*;

fn main() -> Result<(), EnvError> {
    let physics_steps_per_action: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(PHYSICS_STEPS_PER_ACTION);
    for robot in [Robot::Point, Robot::Car] {
        let config = NavConfig {
            n_hazards: 0,
            max_episode_steps: 2000,
            physics_steps_per_action,
            ..NavConfig::new(robot)
        };
        let mut env = SafeDarkMujoco::new(config.clone())?;
        let mut obs = vec![0.0; robot.obs_dim()];
        println!(
            "{robot} ({physics_steps_per_action} physics steps per action): steps to reach the goal, by goal cell distance"
        );
        let mut by_dist: Vec<(f64, usize)> = Vec::new();
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
                })?;
                env.reset(0, &mut obs)?;
                let mut steps = 0;
                loop {
                    let a = env.goal_seeking_action();
                    let out = env.step(Action::Continuous(&a), &mut obs)?;
                    steps += 1;
                    if out.done() {
                        break;
                    }
                }
                let g = config.cell_xy(goal);
                by_dist.push((g[0].hypot(g[1]), steps));
            }
        }
        by_dist.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let mut i = 0;
        while i < by_dist.len() {
            let d = by_dist[i].0;
            let group: Vec<usize> = by_dist
                .iter()
                .filter(|(e, _)| (e - d).abs() < 1e-6)
                .map(|x| x.1)
                .collect();
            println!("  d = {d:.2} m: {group:?}");
            i += group.len();
        }
    }
    Ok(())
}
