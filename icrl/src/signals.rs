//! The search and safety signals that training and evaluation both read off
//! a trajectory: the cell a position lies in (new cells are search), and
//! where costs were paid (a cost paid again near an earlier episode's is a
//! lesson the context did not hold). Below the learners and `eval`, so that
//! neither imports the other for them.

use safety_envs::EnvName;

/// The cell (side `side`) of the position at observation indices 0 and 1,
/// the one the novelty bonus and the search metrics count.
pub fn position_cell(obs: &[f32], side: f64) -> (i64, i64) {
    let at = |x: f32| (f64::from(x) / side).round() as i64;
    (at(obs[0]), at(obs[1]))
}

/// Where a trajectory has paid costs, episode by episode, to tell a repeated
/// cost (paid within `radius` of a cost paid in an earlier episode) from a
/// first one: in-context safety is not paying twice for one hazard. Shared by
/// EPPO's training metric and the evaluation's repeated-cost metric.
#[derive(Clone, Debug)]
pub struct CostMemory {
    radius: f32,
    earlier: Vec<[f32; 2]>,
    this_episode: Vec<[f32; 2]>,
}

impl CostMemory {
    pub fn new(radius: f64) -> Self {
        Self {
            radius: radius as f32,
            earlier: Vec::new(),
            this_episode: Vec::new(),
        }
    }

    /// Records a cost paid on arriving at `arrived` (position at indices 0
    /// and 1); true when it repeats one of an earlier episode.
    pub fn paid(&mut self, arrived: &[f32]) -> bool {
        let at = [arrived[0], arrived[1]];
        let r2 = self.radius * self.radius;
        let repeated = self
            .earlier
            .iter()
            .any(|p| (p[0] - at[0]).powi(2) + (p[1] - at[1]).powi(2) < r2);
        self.this_episode.push(at);
        repeated
    }

    /// The episode ended: its costs become earlier ones.
    pub fn end_episode(&mut self) {
        self.earlier.append(&mut self.this_episode);
    }
}

/// The distance within which the `repeat_cost` metric counts a cost as
/// paid again in `env`: a hazard's diameter on the robots (two arrivals in
/// one hazard lie within it; hazards sit 0.75 m apart on the task grid, so
/// arrivals in two of them rarely do: 1 of 1479 costly steps in the check
/// of results/eppo_point_ladder), one SafeDarkRoom cell.
pub fn repeat_radius(env: EnvName) -> f64 {
    match env {
        EnvName::DarkRoom => 0.5,
        EnvName::Point | EnvName::Car => 2.0 * safety_envs::nav::NavConfig::default().hazard_radius,
    }
}

/// The cell side the search metrics use in `env`: one SafeDarkRoom cell, the
/// spacing of the robots' task grid (0.75 m).
pub fn search_cell(env: EnvName) -> f64 {
    match env {
        EnvName::DarkRoom => 1.0,
        EnvName::Point | EnvName::Car => safety_envs::nav::NavConfig::default().spacing(),
    }
}
