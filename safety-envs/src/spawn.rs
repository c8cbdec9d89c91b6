//! Task sampling: goal and hazards over a grid, centre- or edge-oriented.
//!
//! The agent always starts at the centre cell `c = (g / 2, g / 2)` of a
//! `g x g` grid. Goal and obstacles are drawn over the other cells with
//!
//! - [`Orientation::Centre`] (pretraining): `P(cell) ∝ exp(-alpha * d(cell, c))`
//! - [`Orientation::Edge`] (evaluation): `P(cell) ∝ exp(+alpha * d(cell, c))`
//!
//! where `d` is measured in cell units (row/column index differences), either
//! Euclidean (default, the paper's main text) or squared (its Appendix B).
//!
//! Order of the draws: the goal is drawn first over every cell except the
//! centre, so its marginal law is exactly the rule above; the obstacles are then
//! drawn one after another *without replacement* over the cells that remain
//! (neither the centre nor the goal), each draw renormalising the weights of the
//! cells still free. So nothing ever lies on the start cell and the goal is
//! never on an obstacle.
//!
//! [`sample_task`] is a pure function of `(config, orientation, seed)`. The
//! random stream is a ChaCha8 generator keyed by *both* the orientation and the
//! seed (they occupy different bytes of the 32-byte key), so the centre- and
//! edge-oriented distributions never share a stream, and evaluation tasks
//! (edge, any seed) cannot replay a pretraining draw.

use std::fmt;
use std::str::FromStr;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::EnvError;

/// A grid cell, `(row, col)` with `0 <= row, col < grid_size`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Cell {
    pub row: usize,
    pub col: usize,
}

impl Cell {
    /// The centre (start) cell of a `grid_size x grid_size` grid.
    pub fn centre(grid_size: usize) -> Cell {
        Cell {
            row: grid_size / 2,
            col: grid_size / 2,
        }
    }
}

/// One task: where the goal and the hazards (obstacles) are. The agent always
/// starts at the centre cell. Continuous environments map cells to positions.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Task {
    pub grid_size: usize,
    pub goal: Cell,
    pub obstacles: Vec<Cell>,
}

impl Task {
    /// Checks that the task fits a grid of `grid_size` with `n_obstacles`
    /// obstacles: cells inside the grid, nothing on the centre, goal not on an
    /// obstacle, obstacles distinct.
    pub fn validate(&self, grid_size: usize, n_obstacles: usize) -> Result<(), EnvError> {
        if self.grid_size != grid_size {
            return Err(EnvError::InvalidConfig(format!(
                "task grid size {} does not match the environment's {grid_size}",
                self.grid_size
            )));
        }
        if self.obstacles.len() != n_obstacles {
            return Err(EnvError::InvalidConfig(format!(
                "task has {} obstacles, the environment expects {n_obstacles}",
                self.obstacles.len()
            )));
        }
        let centre = Cell::centre(grid_size);
        let inside = |c: &Cell| c.row < grid_size && c.col < grid_size;
        if !inside(&self.goal) || self.goal == centre {
            return Err(EnvError::InvalidConfig(format!(
                "goal {:?} must be inside the {grid_size}x{grid_size} grid and off the centre {centre:?}",
                self.goal
            )));
        }
        for (i, o) in self.obstacles.iter().enumerate() {
            if !inside(o) || *o == centre || *o == self.goal {
                return Err(EnvError::InvalidConfig(format!(
                    "obstacle {o:?} must be inside the grid, off the centre {centre:?} and off the goal {:?}",
                    self.goal
                )));
            }
            if self.obstacles[..i].contains(o) {
                return Err(EnvError::InvalidConfig(format!(
                    "obstacle {o:?} appears twice"
                )));
            }
        }
        Ok(())
    }
}

/// Which of the two task distributions to draw from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Orientation {
    /// Pretraining: goal and obstacles concentrate near the centre.
    Centre,
    /// Evaluation (out of distribution): they concentrate near the edges.
    Edge,
}

impl Orientation {
    /// The sign of the exponent: -1 for centre, +1 for edge.
    fn sign(self) -> f64 {
        match self {
            Orientation::Centre => -1.0,
            Orientation::Edge => 1.0,
        }
    }

    /// A distinct byte per orientation, part of the RNG key.
    fn key_tag(self) -> u8 {
        match self {
            Orientation::Centre => 0xC0,
            Orientation::Edge => 0xED,
        }
    }
}

impl fmt::Display for Orientation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Orientation::Centre => "centre",
            Orientation::Edge => "edge",
        })
    }
}

impl FromStr for Orientation {
    type Err = EnvError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "centre" | "center" => Ok(Orientation::Centre),
            "edge" => Ok(Orientation::Edge),
            other => Err(EnvError::InvalidConfig(format!(
                "unknown orientation '{other}'; valid: centre, edge"
            ))),
        }
    }
}

/// The distance `d(cell, centre)` in the exponent, in cell units.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Distance {
    /// `sqrt(dr^2 + dc^2)` (paper, Section 4). The default.
    #[default]
    Euclidean,
    /// `dr^2 + dc^2` (paper, Appendix B).
    Squared,
}

impl Distance {
    fn between(self, a: Cell, b: Cell) -> f64 {
        let dr = a.row as f64 - b.row as f64;
        let dc = a.col as f64 - b.col as f64;
        let sq = dr * dr + dc * dc;
        match self {
            Distance::Euclidean => sq.sqrt(),
            Distance::Squared => sq,
        }
    }
}

/// The grid and law a task is drawn from.
#[derive(Clone, Debug, PartialEq)]
pub struct SpawnConfig {
    /// Cells per side; the grid is `grid_size x grid_size`, start at the centre.
    pub grid_size: usize,
    /// Obstacles (hazards) per task.
    pub n_obstacles: usize,
    /// Strength of the centre/edge preference (paper: 0.5).
    pub alpha: f64,
    /// Distance in the exponent.
    pub distance: Distance,
}

impl SpawnConfig {
    /// SafeDarkRoom's grid: 9x9 with 25 obstacles.
    pub fn darkroom() -> Self {
        SpawnConfig {
            grid_size: 9,
            n_obstacles: 25,
            alpha: 0.5,
            distance: Distance::Euclidean,
        }
    }

    /// Checks the grid can hold the goal and all obstacles off the centre.
    pub fn validate(&self) -> Result<(), EnvError> {
        if self.grid_size < 2 {
            return Err(EnvError::InvalidConfig(format!(
                "grid_size {} is too small: need at least 2 cells per side",
                self.grid_size
            )));
        }
        let cells = self.grid_size * self.grid_size;
        // One cell is the start, one the goal.
        let free = cells - 2;
        if self.n_obstacles > free {
            return Err(EnvError::InvalidConfig(format!(
                "{} obstacles do not fit a {g}x{g} grid: at most {free} cells are free \
                 (the start and the goal take one each)",
                self.n_obstacles,
                g = self.grid_size
            )));
        }
        if !self.alpha.is_finite() {
            return Err(EnvError::InvalidConfig(format!(
                "alpha must be finite, got {}",
                self.alpha
            )));
        }
        Ok(())
    }
}

/// The 32-byte ChaCha8 key for `(orientation, seed)`: seed in bytes 0..8, the
/// orientation tag in byte 8, a fixed domain tag after it. Distinct pairs give
/// distinct keys, hence unrelated streams.
fn rng_for(orientation: Orientation, seed: u64) -> ChaCha8Rng {
    let mut key = [0u8; 32];
    key[..8].copy_from_slice(&seed.to_le_bytes());
    key[8] = orientation.key_tag();
    key[16..28].copy_from_slice(b"spawn/task/1");
    ChaCha8Rng::from_seed(key)
}

/// Draws one index from `weights` (non-negative, not all zero) in proportion.
fn draw_weighted(weights: &[f64], rng: &mut ChaCha8Rng) -> usize {
    let total: f64 = weights.iter().sum();
    let mut u = rng.gen_range(0.0..total);
    let mut last = 0;
    for (i, &w) in weights.iter().enumerate() {
        if w > 0.0 {
            if u < w {
                return i;
            }
            u -= w;
            last = i;
        }
    }
    // Rounding can leave `u` a hair above the sum: take the last positive cell.
    last
}

/// Samples one task: goal first, then obstacles without replacement (see the
/// module documentation for the law). Pure in `(config, orientation, seed)`.
pub fn sample_task(
    config: &SpawnConfig,
    orientation: Orientation,
    seed: u64,
) -> Result<Task, EnvError> {
    config.validate()?;
    let g = config.grid_size;
    let centre = Cell::centre(g);
    let cells: Vec<Cell> = (0..g)
        .flat_map(|row| (0..g).map(move |col| Cell { row, col }))
        .collect();
    // Weights relative to the largest, so exp never overflows; with a huge alpha
    // the far-from-optimal ones underflow to 0 (handled in the obstacle loop).
    let exponents: Vec<f64> = cells
        .iter()
        .map(|&c| orientation.sign() * config.alpha * config.distance.between(c, centre))
        .collect();
    let max_exp = exponents
        .iter()
        .zip(&cells)
        .filter(|(_, c)| **c != centre)
        .map(|(e, _)| *e)
        .fold(f64::NEG_INFINITY, f64::max);
    let mut weights: Vec<f64> = exponents
        .iter()
        .zip(&cells)
        .map(|(e, &c)| {
            if c == centre {
                0.0
            } else {
                (e - max_exp).exp()
            }
        })
        .collect();
    let mut rng = rng_for(orientation, seed);

    let goal_index = draw_weighted(&weights, &mut rng);
    weights[goal_index] = 0.0;
    let mut obstacles = Vec::with_capacity(config.n_obstacles);
    for _ in 0..config.n_obstacles {
        if weights.iter().all(|&w| w == 0.0) {
            // Only underflowed cells remain: fall back to uniform over them.
            for (w, &c) in weights.iter_mut().zip(&cells) {
                if c != centre && c != cells[goal_index] && !obstacles.contains(&c) {
                    *w = 1.0;
                }
            }
        }
        let i = draw_weighted(&weights, &mut rng);
        weights[i] = 0.0;
        obstacles.push(cells[i]);
    }
    Ok(Task {
        grid_size: g,
        goal: cells[goal_index],
        obstacles,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::RngCore;

    #[test]
    fn same_inputs_same_task_and_orientations_differ() {
        let cfg = SpawnConfig::darkroom();
        let a = sample_task(&cfg, Orientation::Centre, 7).unwrap();
        let b = sample_task(&cfg, Orientation::Centre, 7).unwrap();
        assert_eq!(a, b);
        let first = |o| rng_for(o, 7).next_u64();
        assert_ne!(first(Orientation::Centre), first(Orientation::Edge));
        a.validate(9, 25).unwrap();
    }

    #[test]
    fn full_grid_is_allowed_and_one_more_is_not() {
        let mut cfg = SpawnConfig {
            grid_size: 3,
            n_obstacles: 7,
            alpha: 0.5,
            distance: Distance::Squared,
        };
        let t = sample_task(&cfg, Orientation::Edge, 1).unwrap();
        t.validate(3, 7).unwrap();
        cfg.n_obstacles = 8;
        assert!(matches!(
            sample_task(&cfg, Orientation::Edge, 1),
            Err(EnvError::InvalidConfig(_))
        ));
    }

    #[test]
    fn huge_alpha_still_fills_the_grid() {
        let cfg = SpawnConfig {
            grid_size: 9,
            n_obstacles: 79,
            alpha: 1e4,
            distance: Distance::Squared,
        };
        let t = sample_task(&cfg, Orientation::Centre, 3).unwrap();
        t.validate(9, 79).unwrap();
    }
}
