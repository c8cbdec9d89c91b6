//! Task sampling: goal and hazards over a grid, centre- or edge-oriented.
//!
//! (Sampling is filled in by the environments issue; this file holds the shared `Task`.)

/// A grid cell, `(row, col)` with `0 <= row, col < grid_size`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Cell {
    pub row: usize,
    pub col: usize,
}

/// One task: where the goal and the hazards (obstacles) are. The agent always
/// starts at the centre cell. Continuous environments map cells to positions.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Task {
    pub grid_size: usize,
    pub goal: Cell,
    pub obstacles: Vec<Cell>,
}
