//! Animations of one recorded evaluation trajectory (GIF): SafeDarkRoom cell
//! by cell, SafeDarkMujoco drawn top-down or rendered by MuJoCo.

use std::path::Path;

use plotters::prelude::*;
use safety_envs::output::{self, Existing};

use super::{PlotError, ensure_font};
use crate::report::{Recording, TaskRecord};

/// A GIF of one recorded SafeDarkRoom trajectory: the grid with the obstacles
/// (red; darker once touched in this trajectory), the goal (green), the agent
/// (blue) and its path in the current episode. Episodes for which
/// `step_frames(k)` holds (k from 0) get one frame per step, the others one
/// frame with the whole episode's path (keeps a 50-episode GIF small).
/// Observations are the agent's `[row, col]`. Returns the number of frames.
pub fn darkroom_animation(
    recording: &Recording,
    task: &TaskRecord,
    budget: f32,
    step_frames: &dyn Fn(usize) -> bool,
    path: &Path,
) -> Result<usize, PlotError> {
    write_gif(path, |tmp| {
        darkroom_animation_to(recording, task, budget, step_frames, tmp)
    })
}

/// [`darkroom_animation`] into `path` directly (the temporary file).
fn darkroom_animation_to(
    recording: &Recording,
    task: &TaskRecord,
    budget: f32,
    step_frames: &dyn Fn(usize) -> bool,
    path: &Path,
) -> Result<usize, PlotError> {
    if recording.episodes.is_empty() {
        return Err(PlotError::Empty("the recording has no episodes".into()));
    }
    if recording
        .episodes
        .iter()
        .any(|e| e.observations.is_empty() || e.observations.iter().any(|o| o.len() < 2))
    {
        return Err(PlotError::Empty(
            "the recording's observations are not SafeDarkRoom [row, col] cells".into(),
        ));
    }
    ensure_font()?;
    let g = task.grid_size as i32;
    let cell = 40i32;
    let top = 56i32;
    let size = ((g * cell) as u32, (g * cell + top) as u32);
    let err = |e: String| PlotError::Draw {
        path: path.display().to_string(),
        message: e,
    };
    let root = BitMapBackend::gif(path, size, 120)
        .map_err(|e| err(e.to_string()))?
        .into_drawing_area();
    let mut touched = vec![false; (g * g) as usize];
    let mut frames = 0;
    let caption = Caption {
        task,
        episodes: recording.episodes.len(),
        budget,
    };
    for (k, ep) in recording.episodes.iter().enumerate() {
        let (mut ret, mut cost) = (0.0f32, 0.0f32);
        let last = ep.observations.len() - 1;
        for t in 0..=last {
            if t > 0 {
                ret += ep.rewards[t - 1];
                cost += ep.costs[t - 1];
            }
            let cell_of = |o: &Vec<f32>| (o[0].round() as i32, o[1].round() as i32);
            let (r, c) = cell_of(&ep.observations[t]);
            if (0..g).contains(&r)
                && (0..g).contains(&c)
                && task.obstacles.contains(&[r as usize, c as usize])
            {
                touched[(r * g + c) as usize] = true;
            }
            if !frame_wanted(step_frames(k), 1, t, last) {
                continue;
            }
            root.fill(&WHITE).map_err(|e| err(e.to_string()))?;
            let rect = |r: i32, c: i32| {
                [
                    (c * cell, top + r * cell),
                    ((c + 1) * cell, top + (r + 1) * cell),
                ]
            };
            for rr in 0..g {
                for cc in 0..g {
                    root.draw(&Rectangle::new(
                        rect(rr, cc),
                        RGBColor(235, 235, 235).filled(),
                    ))
                    .map_err(|e| err(e.to_string()))?;
                    root.draw(&Rectangle::new(rect(rr, cc), RGBColor(200, 200, 200)))
                        .map_err(|e| err(e.to_string()))?;
                }
            }
            for o in &task.obstacles {
                let (rr, cc) = (o[0] as i32, o[1] as i32);
                let colour = if touched[(rr * g + cc) as usize] {
                    RGBColor(150, 20, 20)
                } else {
                    RGBColor(240, 130, 130)
                };
                root.draw(&Rectangle::new(rect(rr, cc), colour.filled()))
                    .map_err(|e| err(e.to_string()))?;
            }
            let (gr, gc) = (task.goal[0] as i32, task.goal[1] as i32);
            root.draw(&Rectangle::new(
                rect(gr, gc),
                RGBColor(60, 180, 75).filled(),
            ))
            .map_err(|e| err(e.to_string()))?;
            let centre = |(r, c): (i32, i32)| (c * cell + cell / 2, top + r * cell + cell / 2);
            let trail: Vec<(i32, i32)> = ep.observations[..=t]
                .iter()
                .map(|o| centre(cell_of(o)))
                .collect();
            root.draw(&PathElement::new(
                trail,
                RGBColor(31, 119, 180).stroke_width(3),
            ))
            .map_err(|e| err(e.to_string()))?;
            root.draw(&Circle::new(
                centre((r, c)),
                cell / 3,
                RGBColor(31, 119, 180).filled(),
            ))
            .map_err(|e| err(e.to_string()))?;
            caption
                .draw(&root, k, t, ret, cost)
                .map_err(|e| err(e.to_string()))?;
            root.present().map_err(|e| err(e.to_string()))?;
            frames += 1;
        }
    }
    Ok(frames)
}

/// Where the objects of a SafeDarkMujoco task lie (from the environment's
/// `NavConfig`): cells map to world xy.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ArenaGeometry {
    /// Cells span `[-extent, extent]` in x and y.
    pub extent: f64,
    /// Distance between neighbouring cell centres.
    pub spacing: f64,
    pub goal_radius: f64,
    pub hazard_radius: f64,
}

impl ArenaGeometry {
    /// World xy of cell `[row, col]` (row 0 at +y).
    pub fn cell_xy(&self, cell: [usize; 2]) -> (f64, f64) {
        (
            -self.extent + cell[1] as f64 * self.spacing,
            self.extent - cell[0] as f64 * self.spacing,
        )
    }
}

/// A top-down GIF of one recorded SafeDarkMujoco trajectory, drawn from the
/// robot's recorded position (observation entries 0 and 1): hazards (red;
/// darker once entered in this trajectory), the goal (green), the robot
/// (blue) and its path in the current episode. Episodes for which
/// `step_frames(k)` holds get a frame every `stride` steps, the others one
/// frame with the whole path. Returns the number of frames.
pub fn nav_animation(
    recording: &Recording,
    task: &TaskRecord,
    arena: &ArenaGeometry,
    budget: f32,
    step_frames: &dyn Fn(usize) -> bool,
    stride: usize,
    path: &Path,
) -> Result<usize, PlotError> {
    write_gif(path, |tmp| {
        nav_animation_to(recording, task, arena, budget, step_frames, stride, tmp)
    })
}

/// [`nav_animation`] into `path` directly (the temporary file).
fn nav_animation_to(
    recording: &Recording,
    task: &TaskRecord,
    arena: &ArenaGeometry,
    budget: f32,
    step_frames: &dyn Fn(usize) -> bool,
    stride: usize,
    path: &Path,
) -> Result<usize, PlotError> {
    if recording.episodes.is_empty()
        || recording
            .episodes
            .iter()
            .any(|e| e.observations.is_empty() || e.observations.iter().any(|o| o.len() < 2))
    {
        return Err(PlotError::Empty(
            "the recording holds no robot positions".into(),
        ));
    }
    ensure_font()?;
    let err = |e: String| PlotError::Draw {
        path: path.display().to_string(),
        message: e,
    };
    let (w, top) = (400i32, 56i32);
    let root = BitMapBackend::gif(path, (w as u32, (w + top) as u32), 100)
        .map_err(|e| err(e.to_string()))?
        .into_drawing_area();
    // World [-L, L]^2 to pixels, +y up.
    let half = arena.extent + arena.spacing * 0.5;
    let px = |(x, y): (f64, f64)| -> (i32, i32) {
        (
            ((x + half) / (2.0 * half) * w as f64) as i32,
            top + ((half - y) / (2.0 * half) * w as f64) as i32,
        )
    };
    let radius = |r: f64| ((r / (2.0 * half)) * w as f64).round() as i32;
    let hazards: Vec<(f64, f64)> = task.obstacles.iter().map(|&c| arena.cell_xy(c)).collect();
    let goal = arena.cell_xy(task.goal);
    let mut entered = vec![false; hazards.len()];
    let stride = stride.max(1);
    let caption = Caption {
        task,
        episodes: recording.episodes.len(),
        budget,
    };
    let mut frames = 0;
    for (k, ep) in recording.episodes.iter().enumerate() {
        let (mut ret, mut cost) = (0.0f32, 0.0f32);
        let last = ep.observations.len() - 1;
        for t in 0..=last {
            if t > 0 {
                ret += ep.rewards[t - 1];
                cost += ep.costs[t - 1];
            }
            let pos = (ep.observations[t][0] as f64, ep.observations[t][1] as f64);
            for (h, e) in hazards.iter().zip(entered.iter_mut()) {
                if (h.0 - pos.0).hypot(h.1 - pos.1) <= arena.hazard_radius {
                    *e = true;
                }
            }
            if !frame_wanted(step_frames(k), stride, t, last) {
                continue;
            }
            let d = |r: Result<(), DrawingAreaErrorKind<_>>| r.map_err(|e| err(e.to_string()));
            d(root.fill(&RGBColor(235, 235, 235)))?;
            d(root.draw(&Rectangle::new([(0, 0), (w, top)], WHITE.filled())))?;
            for (h, &e) in hazards.iter().zip(&entered) {
                let colour = if e {
                    RGBColor(150, 20, 20)
                } else {
                    RGBColor(240, 130, 130)
                };
                d(root.draw(&Circle::new(
                    px(*h),
                    radius(arena.hazard_radius),
                    colour.filled(),
                )))?;
            }
            d(root.draw(&Circle::new(
                px(goal),
                radius(arena.goal_radius),
                RGBColor(60, 180, 75).filled(),
            )))?;
            let trail: Vec<(i32, i32)> = ep.observations[..=t]
                .iter()
                .map(|o| px((o[0] as f64, o[1] as f64)))
                .collect();
            d(root.draw(&PathElement::new(
                trail,
                RGBColor(31, 119, 180).stroke_width(2),
            )))?;
            d(root.draw(&Circle::new(px(pos), 6, RGBColor(31, 119, 180).filled())))?;
            d(caption.draw(&root, k, t, ret, cost))?;
            d(root.present())?;
            frames += 1;
        }
    }
    Ok(frames)
}

/// A GIF of one recorded SafeDarkMujoco trajectory rendered by MuJoCo
/// (OSMesa, top-down camera `top`): the recorded actions are replayed in
/// `env` (a fresh environment of the same robot and time limit, with the
/// recorded task set), checking at every step that the replay reproduces the
/// recorded observation. Frames as in [`nav_animation`]. Returns the number
/// of frames.
pub fn nav_render_animation(
    env: &mut safety_envs::SafeDarkMujoco,
    recording: &Recording,
    task: &TaskRecord,
    budget: f32,
    step_frames: &dyn Fn(usize) -> bool,
    stride: usize,
    path: &Path,
) -> Result<usize, PlotError> {
    write_gif(path, |tmp| {
        nav_render_animation_to(env, recording, task, budget, step_frames, stride, tmp)
    })
}

/// [`nav_render_animation`] into `path` directly (the temporary file).
fn nav_render_animation_to(
    env: &mut safety_envs::SafeDarkMujoco,
    recording: &Recording,
    task: &TaskRecord,
    budget: f32,
    step_frames: &dyn Fn(usize) -> bool,
    stride: usize,
    path: &Path,
) -> Result<usize, PlotError> {
    use safety_envs::mujoco::{Camera, Quality, Renderer};
    use safety_envs::{Action, CmdpEnv};
    ensure_font()?;
    let err = |e: String| PlotError::Draw {
        path: path.display().to_string(),
        message: e,
    };
    let size = 360usize;
    let top = 56i32;
    let mut renderer = Renderer::with_quality(env.model(), size, size, Quality::Fast)
        .map_err(|e| err(e.to_string()))?;
    let camera = Camera::Named("top".into());
    let root = BitMapBackend::gif(path, (size as u32, size as u32 + top as u32), 100)
        .map_err(|e| err(e.to_string()))?
        .into_drawing_area();
    let obs_dim = env.observation_space().flat_dim();
    let mut obs = vec![0.0f32; obs_dim];
    let stride = stride.max(1);
    let caption = Caption {
        task,
        episodes: recording.episodes.len(),
        budget,
    };
    let mut frames = 0;
    for (k, ep) in recording.episodes.iter().enumerate() {
        env.reset(ep.reset_seed, &mut obs)
            .map_err(|e| err(e.to_string()))?;
        let (mut ret, mut cost) = (0.0f32, 0.0f32);
        let last = ep.actions.len();
        for t in 0..=last {
            if ep
                .observations
                .get(t)
                .is_none_or(|o| o.as_slice() != obs.as_slice())
            {
                return Err(err(format!(
                    "replay of episode {} diverged from the recording at step {t}",
                    k + 1
                )));
            }
            if frame_wanted(step_frames(k), stride, t, last) {
                let img = env
                    .render(&mut renderer, &camera)
                    .map_err(|e| err(e.to_string()))?;
                let d = |r: Result<(), DrawingAreaErrorKind<_>>| r.map_err(|e| err(e.to_string()));
                d(root.fill(&WHITE))?;
                let bitmap = BitMapElement::with_owned_buffer(
                    (0, top),
                    (img.width as u32, img.height as u32),
                    img.pixels,
                )
                .ok_or_else(|| err("rendered image smaller than its size".into()))?;
                d(root.draw(&bitmap))?;
                d(caption.draw(&root, k, t, ret, cost))?;
                d(root.present())?;
                frames += 1;
            }
            if t < last {
                let o = env
                    .step(Action::Continuous(&ep.actions[t]), &mut obs)
                    .map_err(|e| err(e.to_string()))?;
                ret += o.reward;
                cost += o.cost;
            }
        }
    }
    Ok(frames)
}

/// Writes a GIF atomically: `draw` fills the temporary file and returns
/// the number of frames.
fn write_gif(
    path: &Path,
    draw: impl FnOnce(&Path) -> Result<usize, PlotError>,
) -> Result<usize, PlotError> {
    let mut frames = 0;
    output::write_file::<PlotError>(path, Existing::Replace, |tmp| {
        frames = draw(tmp)?;
        Ok(())
    })?;
    Ok(frames)
}

/// Whether step `t` of an episode whose last step is `last` gets a frame:
/// every `stride`-th step of an episode shown step by step, else its last.
fn frame_wanted(step_by_step: bool, stride: usize, t: usize, last: usize) -> bool {
    t == last || (step_by_step && t.is_multiple_of(stride))
}

/// The two lines above every frame: the task, the episode and the step, and
/// the episode's return and cost so far against the budget.
struct Caption<'a> {
    task: &'a TaskRecord,
    episodes: usize,
    budget: f32,
}

impl Caption<'_> {
    fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, plotters::coord::Shift>,
        k: usize,
        t: usize,
        ret: f32,
        cost: f32,
    ) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
        let line1 = format!(
            "task seed ...{:06}  episode {}/{}  step {t}",
            self.task.seed % 1_000_000,
            k + 1,
            self.episodes
        );
        let line2 = format!("return {ret:.0}  cost {cost:.0}  budget {:.1}", self.budget);
        root.draw(&Text::new(line1, (6, 6), ("sans-serif", 16)))?;
        root.draw(&Text::new(line2, (6, 28), ("sans-serif", 16)))
    }
}
