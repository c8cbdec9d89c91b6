//! How many agent steps a simple steering controller needs to reach each goal
//! cell from the start (no hazards), per robot: is the time limit long enough?
//!
//! ```text
//! cargo run --release -p safety-envs --example reach [-- FRAME_SKIP]
//! ```

use safety_envs::prelude::*;

fn main() -> Result<(), EnvError> {
    let frame_skip: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(5);
    for robot in [Robot::Point, Robot::Car] {
        let config = NavConfig {
            n_hazards: 0,
            max_episode_steps: 2000,
            frame_skip,
            ..NavConfig::new(robot)
        };
        let mut env = SafeDarkMujoco::new(config.clone())?;
        let mut obs = vec![0.0; robot.obs_dim()];
        println!(
            "{robot} (frame_skip {frame_skip}): steps to reach the goal, by goal cell distance"
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
                let g = config.cell_xy(goal);
                let mut steps = 0;
                loop {
                    let [x, y] = env.robot_xy();
                    // Heading: Point's body +x, Car's body +y.
                    let yaw = env.robot_yaw()
                        + if robot == Robot::Car {
                            std::f64::consts::FRAC_PI_2
                        } else {
                            0.0
                        };
                    let want = (g[1] - y).atan2(g[0] - x);
                    let mut err = want - yaw;
                    while err > std::f64::consts::PI {
                        err -= std::f64::consts::TAU;
                    }
                    while err < -std::f64::consts::PI {
                        err += std::f64::consts::TAU;
                    }
                    let turn = (3.0 * err).clamp(-1.0, 1.0) as f32;
                    let fwd = if err.abs() < 0.5 { 1.0 } else { 0.0 };
                    let a = match robot {
                        Robot::Point => [fwd, turn],
                        Robot::Car => {
                            [(fwd - turn).clamp(-1.0, 1.0), (fwd + turn).clamp(-1.0, 1.0)]
                        }
                    };
                    let out = env.step(Action::Continuous(&a), &mut obs)?;
                    steps += 1;
                    if out.done() {
                        break;
                    }
                }
                by_dist.push((g[0].hypot(g[1]), steps));
            }
        }
        by_dist.sort_by(|a, b| a.partial_cmp(b).unwrap());
        let mut i = 0;
        while i < by_dist.len() {
            let d = by_dist[i].0;
            let group: Vec<usize> = by_dist
                .iter()
                .filter(|(e, _)| (e - d).abs() < 1e-6)
                .map(|x| x.1)
                .collect();
            println!("  d = {d:.2} m: {:?}", group);
            i += group.len();
        }
    }
    Ok(())
}
