//! The paper's evaluation figures (PNG and SVG) and an animation of one
//! evaluation trajectory in SafeDarkRoom (GIF), drawn with plotters.
//!
//! - [`figure1`]: episode return and episode cost against the episode index k,
//!   mean with a shaded standard-error band, one column per environment, every
//!   method on the same axes, the budget and a random policy as lines.
//! - [`figure2`]: total return `sum_k G(tau_k)` and maximum episode cost
//!   `max_k Gc(tau_k)` against the budget (CTG), same layout.
//! - [`darkroom_animation`]: one frame per step of a recorded trajectory.
//!
//! Text needs a TrueType font, read at run time (plotters' `ab_glyph`
//! feature: no fontconfig or freetype): `ICRL_FONT` if set, else DejaVu Sans
//! from Debian's `fonts-dejavu-core`, else a few other common paths.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::FontStyle;
use thiserror::Error;

use crate::eval::{Recording, Summary, TaskRecord};

/// A figure that could not be drawn or written.
#[derive(Debug, Error)]
pub enum PlotError {
    #[error(
        "no TrueType font for the figures: install Debian's fonts-dejavu-core or set ICRL_FONT to a .ttf file (tried {tried})"
    )]
    NoFont { tried: String },
    #[error("font file {path} is not a usable TrueType/OpenType font")]
    BadFont { path: String },
    #[error("drawing {path}: {message}")]
    Draw { path: String, message: String },
    #[error("nothing to plot: {0}")]
    Empty(String),
    #[error("cannot create {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
}

/// Font files tried after `ICRL_FONT`.
const FONT_CANDIDATES: [&str; 5] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/truetype/freefont/FreeSans.ttf",
];

/// Why no font could be registered (kept for later calls).
#[derive(Clone, Debug)]
enum FontFailure {
    Missing { tried: String },
    Bad { path: String },
}

/// Registers the sans-serif font once per process.
fn ensure_font() -> Result<(), PlotError> {
    static FONT: OnceLock<Result<(), FontFailure>> = OnceLock::new();
    let registered = FONT.get_or_init(|| {
        let mut paths: Vec<String> = std::env::var("ICRL_FONT").into_iter().collect();
        paths.extend(FONT_CANDIDATES.iter().map(|s| s.to_string()));
        let Some((path, bytes)) = paths
            .iter()
            .find_map(|p| std::fs::read(p).ok().map(|b| (p.clone(), b)))
        else {
            return Err(FontFailure::Missing {
                tried: paths.join(", "),
            });
        };
        // plotters keeps a 'static reference: the font lives for the process.
        let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
        plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
            .map_err(|_| FontFailure::Bad { path })
    });
    registered.clone().map_err(|f| match f {
        FontFailure::Missing { tried } => PlotError::NoFont { tried },
        FontFailure::Bad { path } => PlotError::BadFont { path },
    })
}

/// One curve: a mean with a shaded band of one standard error.
#[derive(Clone, Debug, PartialEq)]
pub struct Band {
    pub label: String,
    pub x: Vec<f64>,
    pub mean: Vec<f64>,
    /// Standard errors; empty for a plain line.
    pub se: Vec<f64>,
    pub colour: RGBColor,
    /// A reference curve (random policy): thin line.
    pub thin: bool,
}

/// A horizontal reference line (a budget, a random policy's level).
#[derive(Clone, Debug, PartialEq)]
pub struct HLine {
    pub label: String,
    pub y: f64,
    pub colour: RGBColor,
}

/// One set of axes.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Panel {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub bands: Vec<Band>,
    pub hlines: Vec<HLine>,
    /// Draw the line y = x with this label (cost equal to the budget).
    pub diagonal: Option<String>,
}

/// Colours per method: EPPO blue, AD orange, more in order.
pub const METHOD_COLOURS: [RGBColor; 4] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
];
const RANDOM_COLOUR: RGBColor = RGBColor(127, 127, 127);
const BUDGET_COLOUR: RGBColor = RGBColor(214, 39, 40);

/// The evaluation results of one environment, one entry per method.
#[derive(Clone, Debug)]
pub struct EnvCurves {
    /// Panel title, e.g. "SafeDarkRoom".
    pub env: String,
    /// (method label, summary), drawn in this order and colour.
    pub methods: Vec<(String, Summary)>,
    /// A random policy's summary, drawn as a grey line.
    pub random: Option<Summary>,
}

fn pixel_size(rows: usize, cols: usize) -> (u32, u32) {
    (480 * cols.max(1) as u32, 380 * rows.max(2) as u32)
}

/// The colour halfway to white (a method's second curve in one panel).
fn lighter(c: RGBColor) -> RGBColor {
    let half = |x: u8| ((u16::from(x) + 255) / 2) as u8;
    RGBColor(half(c.0), half(c.1), half(c.2))
}

/// Figure 1: return and cost against the episode index, one column per
/// environment, and a third row with the in-context search rates (discovery:
/// goal found with no earlier success; revisit: found again after one).
/// Writes `<stem>.png` and `<stem>.svg`.
pub fn figure1(envs: &[EnvCurves], stem: &Path) -> Result<Vec<PathBuf>, PlotError> {
    let mut returns = Vec::new();
    let mut costs = Vec::new();
    let mut searches = Vec::new();
    for e in envs {
        let mut search = Panel {
            title: format!("{}: in-context search", e.env),
            x_label: "episode k".into(),
            y_label: "P(goal at k | earlier)".into(),
            ..Default::default()
        };
        let labelled = e
            .methods
            .iter()
            .enumerate()
            .map(|(i, (l, s))| {
                (
                    l.as_str(),
                    s,
                    METHOD_COLOURS[i % METHOD_COLOURS.len()],
                    false,
                )
            })
            .chain(
                e.random
                    .iter()
                    .map(|s| ("random policy", s, RANDOM_COLOUR, true)),
            );
        for (label, s, colour, thin) in labelled {
            // Episode 1 has no earlier episode: the rates start at k = 2.
            let later = &s.per_episode[1.min(s.per_episode.len())..];
            let x: Vec<f64> = later.iter().map(|p| p.k as f64).collect();
            search.bands.push(Band {
                label: format!("{label}: discovery"),
                x: x.clone(),
                mean: later.iter().map(|p| p.discovery.mean).collect(),
                se: Vec::new(),
                colour,
                thin,
            });
            search.bands.push(Band {
                label: format!("{label}: revisit"),
                x,
                mean: later.iter().map(|p| p.revisit.mean).collect(),
                se: Vec::new(),
                colour: lighter(colour),
                thin,
            });
        }
        searches.push(search);
        let mut ret = Panel {
            title: format!("{}: episode return", e.env),
            x_label: "episode k".into(),
            y_label: "G(tau_k)".into(),
            ..Default::default()
        };
        let mut cost = Panel {
            title: format!("{}: episode cost", e.env),
            x_label: "episode k".into(),
            y_label: "Gc(tau_k)".into(),
            ..Default::default()
        };
        for (i, (label, s)) in e.methods.iter().enumerate() {
            let colour = METHOD_COLOURS[i % METHOD_COLOURS.len()];
            let x: Vec<f64> = s.per_episode.iter().map(|p| p.k as f64).collect();
            ret.bands.push(Band {
                label: label.clone(),
                x: x.clone(),
                mean: s.per_episode.iter().map(|p| p.ret.mean).collect(),
                se: s.per_episode.iter().map(|p| p.ret.se).collect(),
                colour,
                thin: false,
            });
            cost.bands.push(Band {
                label: label.clone(),
                x,
                mean: s.per_episode.iter().map(|p| p.cost.mean).collect(),
                se: s.per_episode.iter().map(|p| p.cost.se).collect(),
                colour,
                thin: false,
            });
            cost.hlines.push(HLine {
                label: format!("budget ({label}, mean {:.2})", s.mean_budget),
                y: s.mean_budget as f64,
                colour: if e.methods.len() > 1 {
                    colour
                } else {
                    BUDGET_COLOUR
                },
            });
        }
        if let Some(r) = &e.random {
            let x: Vec<f64> = r.per_episode.iter().map(|p| p.k as f64).collect();
            for (panel, ys) in [
                (
                    &mut ret,
                    r.per_episode.iter().map(|p| p.ret.mean).collect::<Vec<_>>(),
                ),
                (
                    &mut cost,
                    r.per_episode.iter().map(|p| p.cost.mean).collect(),
                ),
            ] {
                panel.bands.push(Band {
                    label: "random policy".into(),
                    x: x.clone(),
                    mean: ys,
                    se: Vec::new(),
                    colour: RANDOM_COLOUR,
                    thin: true,
                });
            }
        }
        returns.push(ret);
        costs.push(cost);
    }
    returns.extend(costs);
    returns.extend(searches);
    draw_panels(stem, 3, envs.len(), &returns)
}

/// Figure 2: total return and maximum episode cost against the budget (CTG),
/// one column per environment. Writes `<stem>.png` and `<stem>.svg`.
pub fn figure2(envs: &[EnvCurves], stem: &Path) -> Result<Vec<PathBuf>, PlotError> {
    let mut returns = Vec::new();
    let mut costs = Vec::new();
    for e in envs {
        let mut ret = Panel {
            title: format!("{}: total return", e.env),
            x_label: "CTG (budget)".into(),
            y_label: "sum_k G(tau_k)".into(),
            ..Default::default()
        };
        let mut cost = Panel {
            title: format!("{}: max episode cost", e.env),
            x_label: "CTG (budget)".into(),
            y_label: "max_k Gc(tau_k)".into(),
            diagonal: Some("cost = budget".into()),
            ..Default::default()
        };
        for (i, (label, s)) in e.methods.iter().enumerate() {
            let colour = METHOD_COLOURS[i % METHOD_COLOURS.len()];
            // Sorted by budget: sampled budgets come in drawing order.
            let mut pts: Vec<_> = s.per_condition.iter().collect();
            pts.sort_by(|a, b| a.condition.ctg.total_cmp(&b.condition.ctg));
            let x: Vec<f64> = pts.iter().map(|p| p.condition.ctg as f64).collect();
            ret.bands.push(Band {
                label: label.clone(),
                x: x.clone(),
                mean: pts.iter().map(|p| p.total_return.mean).collect(),
                se: pts.iter().map(|p| p.total_return.se).collect(),
                colour,
                thin: false,
            });
            cost.bands.push(Band {
                label: label.clone(),
                x,
                mean: pts.iter().map(|p| p.max_cost.mean).collect(),
                se: pts.iter().map(|p| p.max_cost.se).collect(),
                colour,
                thin: false,
            });
        }
        if let Some(r) = &e.random {
            let mut pts: Vec<_> = r.per_condition.iter().collect();
            pts.sort_by(|a, b| a.condition.ctg.total_cmp(&b.condition.ctg));
            let x: Vec<f64> = pts.iter().map(|p| p.condition.ctg as f64).collect();
            for (panel, ys) in [
                (
                    &mut ret,
                    pts.iter().map(|p| p.total_return.mean).collect::<Vec<_>>(),
                ),
                (&mut cost, pts.iter().map(|p| p.max_cost.mean).collect()),
            ] {
                panel.bands.push(Band {
                    label: "random policy".into(),
                    x: x.clone(),
                    mean: ys,
                    se: Vec::new(),
                    colour: RANDOM_COLOUR,
                    thin: true,
                });
            }
        }
        returns.push(ret);
        costs.push(cost);
    }
    returns.extend(costs);
    draw_panels(stem, 2, envs.len(), &returns)
}

/// Draws `panels` (row-major, `rows x cols`) into `<stem>.png` and `<stem>.svg`.
pub fn draw_panels(
    stem: &Path,
    rows: usize,
    cols: usize,
    panels: &[Panel],
) -> Result<Vec<PathBuf>, PlotError> {
    if panels.is_empty() || rows * cols != panels.len() {
        return Err(PlotError::Empty(format!(
            "{} panels for a {rows}x{cols} grid",
            panels.len()
        )));
    }
    ensure_font()?;
    if let Some(dir) = stem.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|source| PlotError::Io {
            path: dir.display().to_string(),
            source,
        })?;
    }
    let size = pixel_size(rows, cols);
    let png = stem.with_extension("png");
    let svg = stem.with_extension("svg");
    let err = |p: &Path| {
        let path = p.display().to_string();
        move |e: String| PlotError::Draw {
            path: path.clone(),
            message: e,
        }
    };
    {
        let root = BitMapBackend::new(&png, size).into_drawing_area();
        draw_grid(&root, rows, cols, panels).map_err(err(&png))?;
        root.present().map_err(|e| err(&png)(e.to_string()))?;
    }
    {
        let root = SVGBackend::new(&svg, size).into_drawing_area();
        draw_grid(&root, rows, cols, panels).map_err(err(&svg))?;
        root.present().map_err(|e| err(&svg)(e.to_string()))?;
    }
    Ok(vec![png, svg])
}

fn draw_grid<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    rows: usize,
    cols: usize,
    panels: &[Panel],
) -> Result<(), String> {
    root.fill(&WHITE).map_err(|e| e.to_string())?;
    for (area, panel) in root.split_evenly((rows, cols)).iter().zip(panels) {
        draw_panel(area, panel).map_err(|e| format!("panel '{}': {e}", panel.title))?;
    }
    Ok(())
}

/// Tick labels: whole numbers without a fraction, others with up to 3 digits.
fn tick(v: &f64) -> String {
    if (v - v.round()).abs() < 1e-9 {
        format!("{v:.0}")
    } else {
        let s = format!("{v:.3}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

/// The x and y extents of everything in a panel, padded.
fn extents(panel: &Panel) -> ((f64, f64), (f64, f64)) {
    let mut x = (f64::INFINITY, f64::NEG_INFINITY);
    let mut y = (f64::INFINITY, f64::NEG_INFINITY);
    let grow = |r: &mut (f64, f64), v: f64| {
        if v.is_finite() {
            r.0 = r.0.min(v);
            r.1 = r.1.max(v);
        }
    };
    for b in &panel.bands {
        for (i, (&xi, &m)) in b.x.iter().zip(&b.mean).enumerate() {
            grow(&mut x, xi);
            let se = b.se.get(i).copied().unwrap_or(0.0);
            grow(&mut y, m - se);
            grow(&mut y, m + se);
        }
    }
    for h in &panel.hlines {
        grow(&mut y, h.y);
    }
    if !x.0.is_finite() {
        x = (0.0, 1.0);
    }
    if panel.diagonal.is_some() {
        grow(&mut y, x.0);
        grow(&mut y, x.1);
    }
    if !y.0.is_finite() {
        y = (0.0, 1.0);
    }
    // Costs and returns are non-negative: start the axis at zero; a flat
    // curve gets a unit-high axis.
    y.0 = y.0.min(0.0);
    if y.1 - y.0 < 1e-9 {
        y.1 = y.0 + 1.0;
    }
    let pad = |(lo, hi): (f64, f64)| {
        let span = (hi - lo).max(1e-6);
        (lo - 0.04 * span, hi + 0.08 * span)
    };
    let xs = if x.1 > x.0 { x } else { (x.0 - 0.5, x.1 + 0.5) };
    (xs, pad(y))
}

fn draw_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    panel: &Panel,
) -> Result<(), String> {
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    let ((x0, x1), (y0, y1)) = extents(panel);
    let mut chart = ChartBuilder::on(area)
        .caption(&panel.title, ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(55)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_label_formatter(&tick)
        .y_label_formatter(&tick)
        .x_desc(&panel.x_label)
        .y_desc(&panel.y_label)
        .label_style(("sans-serif", 13))
        .axis_desc_style(("sans-serif", 14))
        .light_line_style(WHITE.mix(0.0))
        .draw()
        .map_err(e)?;
    for b in &panel.bands {
        if b.se.len() == b.mean.len() && !b.se.is_empty() {
            // The band: upper edge left to right, lower edge back.
            let mut poly: Vec<(f64, f64)> =
                b.x.iter()
                    .zip(&b.mean)
                    .zip(&b.se)
                    .map(|((&x, &m), &s)| (x, m + s))
                    .collect();
            poly.extend(
                b.x.iter()
                    .zip(&b.mean)
                    .zip(&b.se)
                    .rev()
                    .map(|((&x, &m), &s)| (x, m - s)),
            );
            chart
                .draw_series(std::iter::once(Polygon::new(
                    poly,
                    b.colour.mix(0.2).filled(),
                )))
                .map_err(e)?;
        }
        // Undefined points (a rate with nothing to count) are left out.
        let pts: Vec<(f64, f64)> =
            b.x.iter()
                .copied()
                .zip(b.mean.iter().copied())
                .filter(|p| p.1.is_finite())
                .collect();
        let colour = b.colour;
        let style = colour.stroke_width(2);
        // Reference curves thin and solid (thick dashed polylines leave
        // marks at sharp corners).
        let series = if b.thin {
            chart.draw_series(LineSeries::new(pts, colour.stroke_width(1)))
        } else {
            chart.draw_series(LineSeries::new(pts, style))
        };
        series.map_err(e)?.label(&b.label).legend(move |(x, y)| {
            PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2))
        });
    }
    for h in &panel.hlines {
        let colour = h.colour;
        chart
            .draw_series(DashedLineSeries::new(
                vec![(x0, h.y), (x1, h.y)],
                3,
                3,
                colour.stroke_width(1),
            ))
            .map_err(e)?
            .label(&h.label)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(1))
            });
    }
    if let Some(label) = &panel.diagonal {
        let lo = x0.max(y0);
        let hi = x1.min(y1);
        if hi > lo {
            chart
                .draw_series(DashedLineSeries::new(
                    vec![(lo, lo), (hi, hi)],
                    3,
                    3,
                    BUDGET_COLOUR.stroke_width(1),
                ))
                .map_err(e)?
                .label(label)
                .legend(|(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], BUDGET_COLOUR.stroke_width(1))
                });
        }
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .label_font(("sans-serif", 12))
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK.mix(0.3))
        .draw()
        .map_err(e)?;
    Ok(())
}

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
    let k_n = recording.episodes.len();
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
            if t < last && !step_frames(k) {
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
            let line1 = format!(
                "task seed ...{:06}  episode {}/{k_n}  step {t}",
                task.seed % 1_000_000,
                k + 1
            );
            let line2 = format!("return {ret:.0}  cost {cost:.0}  budget {budget:.1}");
            root.draw(&Text::new(line1, (6, 6), ("sans-serif", 16)))
                .map_err(|e| err(e.to_string()))?;
            root.draw(&Text::new(line2, (6, 28), ("sans-serif", 16)))
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
    let k_n = recording.episodes.len();
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
            let wanted = if step_frames(k) {
                t % stride == 0 || t == last
            } else {
                t == last
            };
            if !wanted {
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
            let line1 = format!(
                "task seed ...{:06}  episode {}/{k_n}  step {t}",
                task.seed % 1_000_000,
                k + 1
            );
            let line2 = format!("return {ret:.0}  cost {cost:.0}  budget {budget:.1}");
            d(root.draw(&Text::new(line1, (6, 6), ("sans-serif", 16))))?;
            d(root.draw(&Text::new(line2, (6, 28), ("sans-serif", 16))))?;
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
    let k_n = recording.episodes.len();
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
            let wanted = if step_frames(k) {
                t % stride == 0 || t == last
            } else {
                t == last
            };
            if wanted {
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
                let line1 = format!(
                    "task seed ...{:06}  episode {}/{k_n}  step {t}",
                    task.seed % 1_000_000,
                    k + 1
                );
                let line2 = format!("return {ret:.0}  cost {cost:.0}  budget {budget:.1}");
                d(root.draw(&Text::new(line1, (6, 6), ("sans-serif", 16))))?;
                d(root.draw(&Text::new(line2, (6, 28), ("sans-serif", 16))))?;
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
