//! The paper's evaluation figures (PNG and SVG) and an animation of one
//! evaluation trajectory in SafeDarkRoom (GIF), drawn with plotters.
//!
//! - [`figure1`]: episode return and episode cost against the episode index k,
//!   mean with a shaded standard-error band, one column per environment, every
//!   method on the same axes, the budget and a random policy as lines.
//! - [`figure2`]: total return `sum_k G(tau_k)` and maximum episode cost
//!   `max_k Gc(tau_k)` against the budget (CTG), same layout.
//! - [`darkroom_animation`]: one frame per step of a recorded trajectory.
//! - [`training`]: figures of training itself (EPPO's learning curves, AD's
//!   loss, how a dataset's histories improve).
//!
//! This file holds the shared drawing (fonts, panels, bands, colours); the
//! figures are in `figures.rs`, the animations in `animation.rs`.
//!
//! Text needs a TrueType font, read at run time (plotters' `ab_glyph`
//! feature: no fontconfig or freetype): `ICRL_FONT` if set, else DejaVu Sans
//! from Debian's `fonts-dejavu-core`, else a few other common paths.

mod animation;
mod figures;
pub mod training;

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::FontStyle;
use safety_envs::output::{self, Existing};
use thiserror::Error;

use crate::report::Summary;

pub use animation::{ArenaGeometry, darkroom_animation, nav_animation, nav_render_animation};
pub use figures::{figure1, figure2};

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
    /// The output path is not ours to write (see [`safety_envs::output`]).
    #[error(transparent)]
    Output(#[from] safety_envs::output::OutputError),
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

impl Band {
    /// A method's curve: its mean with one standard error shaded.
    pub fn shaded(
        label: impl Into<String>,
        x: Vec<f64>,
        mean: Vec<f64>,
        se: Vec<f64>,
        colour: RGBColor,
    ) -> Self {
        Band {
            label: label.into(),
            x,
            mean,
            se,
            colour,
            thin: false,
        }
    }

    /// A plain line, `thin` for a reference curve (the random policy).
    pub fn line(
        label: impl Into<String>,
        x: Vec<f64>,
        mean: Vec<f64>,
        colour: RGBColor,
        thin: bool,
    ) -> Self {
        Band {
            label: label.into(),
            x,
            mean,
            se: Vec::new(),
            colour,
            thin,
        }
    }

    /// The random policy's reference curve, beside a method's.
    pub fn random_policy(x: Vec<f64>, mean: Vec<f64>) -> Self {
        Band::line("random policy", x, mean, RANDOM_COLOUR, true)
    }
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
    // Each file atomically: a failed write leaves no truncated figure.
    output::write_file::<PlotError>(&png, Existing::Replace, |tmp| {
        let root = BitMapBackend::new(tmp, size).into_drawing_area();
        draw_grid(&root, rows, cols, panels).map_err(err(&png))?;
        root.present().map_err(|e| err(&png)(e.to_string()))
    })?;
    output::write_file::<PlotError>(&svg, Existing::Replace, |tmp| {
        let root = SVGBackend::new(tmp, size).into_drawing_area();
        draw_grid(&root, rows, cols, panels).map_err(err(&svg))?;
        root.present().map_err(|e| err(&svg)(e.to_string()))
    })?;
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
