//! Figures of training itself: EPPO's learning curves, AD's loss curves, and
//! how the histories of a dataset improve.

use std::path::{Path, PathBuf};

use safety_envs::output::{self, Existing};

use super::PlotError;
use std::fs;

use crate::ad::{AdError, AdMetrics, io_err};
use crate::data::dataset::DatasetError;

/// Draws the learning curves of a run from its `metrics.jsonl` into
/// `<run>/learning_curve.png`: episodic return (all episodes, first and last
/// episode of each trajectory), episodic cost (same three) and lambda against
/// environment steps, each a moving average over `window` records. Text uses
/// DejaVu Sans (or the `.ttf` named by `ICRL_FONT`).
pub fn plot_learning_curve(run_dir: &Path, window: usize) -> Result<PathBuf, PlotError> {
    use plotters::prelude::*;
    let path = run_dir.join("metrics.jsonl");
    let text = std::fs::read_to_string(&path).map_err(|source| PlotError::Io {
        path: path.display().to_string(),
        source,
    })?;
    let records: Vec<serde_json::Value> = text
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect();
    // Garbage (or an empty file) would draw empty axes: say so instead.
    if !records
        .iter()
        .any(|r| r.get("env_steps").is_some_and(|x| x.is_number()))
    {
        return Err(PlotError::Empty(format!(
            "{}: no metric records ({} lines, none a JSON object with env_steps); is this a run \
             folder written by icrl pretrain?",
            path.display(),
            text.lines().count()
        )));
    }
    let smooth = |key: &str| -> Vec<(f64, f64)> {
        let xs: Vec<(f64, f64)> = records
            .iter()
            .filter_map(|r| Some((r.get("env_steps")?.as_f64()?, r.get(key)?.as_f64()?)))
            .collect();
        (0..xs.len())
            .map(|i| {
                let win = &xs[i.saturating_sub(window.max(1) - 1)..=i];
                (
                    xs[i].0,
                    win.iter().map(|p| p.1).sum::<f64>() / win.len() as f64,
                )
            })
            .collect()
    };
    super::ensure_font()?;
    let out = run_dir.join("learning_curve.png");
    let draw_err = |e: String| PlotError::Draw {
        path: out.display().to_string(),
        message: e,
    };
    let colours = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
    ];
    /// (title, y label, [(metric, legend)]).
    type PanelSpec<'a> = (&'a str, &'a str, Vec<(&'a str, &'a str)>);
    let panels: [PanelSpec; 3] = [
        (
            "return (training tasks)",
            "episode return",
            vec![
                ("episodic_return", "all episodes"),
                ("first_episode_return", "first episode"),
                ("last_episode_return", "last episode"),
            ],
        ),
        (
            "cost (training tasks)",
            "episode cost",
            vec![
                ("episodic_cost", "all episodes"),
                ("first_episode_cost", "first episode"),
                ("last_episode_cost", "last episode"),
            ],
        ),
        ("Lagrange multiplier", "lambda", vec![("lambda", "lambda")]),
    ];
    // The run's own figure: replaced, atomically (never a link or device).
    output::write_file::<PlotError>(&out, Existing::Replace, |tmp| {
        let root = BitMapBackend::new(tmp, (1500, 450)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| draw_err(e.to_string()))?;
        for ((title, y_label, keys), area) in panels.iter().zip(root.split_evenly((1, 3))) {
            let curves: Vec<(&str, Vec<(f64, f64)>)> =
                keys.iter().map(|(k, l)| (*l, smooth(k))).collect();
            let all = curves.iter().flat_map(|c| c.1.iter());
            let (x_max, y_min, y_max) = all.fold((1.0f64, 0.0f64, 1e-3f64), |(a, b, c), p| {
                (a.max(p.0), b.min(p.1), c.max(p.1))
            });
            let mut chart = ChartBuilder::on(&area)
                .caption(*title, ("sans-serif", 20))
                .margin(12)
                .x_label_area_size(40)
                .y_label_area_size(50)
                .build_cartesian_2d(0.0..x_max, y_min..y_max * 1.05)
                .map_err(|e| draw_err(e.to_string()))?;
            chart
                .configure_mesh()
                .x_desc("environment steps")
                .y_desc(*y_label)
                .x_labels(5)
                .x_label_formatter(&|x| format!("{:.0}k", x / 1000.0))
                .draw()
                .map_err(|e| draw_err(e.to_string()))?;
            for (i, (label, points)) in curves.into_iter().enumerate() {
                let c = colours[i % colours.len()];
                chart
                    .draw_series(LineSeries::new(points, c.stroke_width(2)))
                    .map_err(|e| draw_err(e.to_string()))?
                    .label(label)
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 18, y)], c.stroke_width(2))
                    });
            }
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()
                .map_err(|e| draw_err(e.to_string()))?;
        }
        root.present().map_err(|e| draw_err(e.to_string()))
    })?;
    Ok(out)
}

/// Draws `metrics.jsonl` of an AD run: loss and accuracy (training windows and
/// held-out tasks) against updates, into `<run>/training_loss.{png,svg}`.
pub fn plot_training(run_dir: &Path) -> Result<Vec<PathBuf>, AdError> {
    use crate::plots::{Band, METHOD_COLOURS, Panel, draw_panels};
    let path = run_dir.join("metrics.jsonl");
    let text = fs::read_to_string(&path).map_err(|e| io_err(&path, e))?;
    let records: Vec<AdMetrics> = text
        .lines()
        .map(serde_json::from_str)
        .collect::<Result<_, _>>()
        .map_err(|e| io_err(&path, e))?;
    if records.is_empty() {
        return Err(io_err(&path, "no metrics recorded yet"));
    }
    let x: Vec<f64> = records.iter().map(|m| m.update as f64).collect();
    let band = |label: &str, ys: Vec<Option<f64>>, colour| {
        let pts: Vec<(f64, f64)> = x
            .iter()
            .zip(ys)
            .filter_map(|(&x, y)| y.map(|y| (x, y)))
            .collect();
        Band::line(
            label,
            pts.iter().map(|p| p.0).collect(),
            pts.iter().map(|p| p.1).collect(),
            colour,
            false,
        )
    };
    let loss = Panel {
        title: "supervised loss (Eq. 16)".into(),
        x_label: "update".into(),
        y_label: "cross-entropy".into(),
        bands: vec![
            band(
                "training windows",
                records.iter().map(|m| Some(m.train_loss)).collect(),
                METHOD_COLOURS[0],
            ),
            band(
                "held-out tasks",
                records.iter().map(|m| m.val_loss).collect(),
                METHOD_COLOURS[1],
            ),
        ],
        ..Default::default()
    };
    let acc = Panel {
        title: "action accuracy".into(),
        x_label: "update".into(),
        y_label: "fraction of actions predicted".into(),
        bands: vec![
            band(
                "training windows",
                records.iter().map(|m| m.train_accuracy).collect(),
                METHOD_COLOURS[0],
            ),
            band(
                "held-out tasks",
                records.iter().map(|m| m.val_accuracy).collect(),
                METHOD_COLOURS[1],
            ),
        ],
        ..Default::default()
    };
    let panels: Vec<Panel> = if records[0].train_accuracy.is_some() {
        vec![loss, acc]
    } else {
        vec![Panel {
            title: "supervised loss (Eq. 17)".into(),
            y_label: "squared error".into(),
            ..loss
        }]
    };
    draw_panels(&run_dir.join("training_loss"), 1, panels.len(), &panels)
        .map_err(|e| io_err(run_dir, e))
}

/// Draws how the histories of a file improve: mean episode return and cost
/// against learning progress (each history cut into `bins` equal parts of its
/// episodes), one curve per cost limit with a band of one standard error over
/// histories, the limits as dashed lines. Writes `<stem>.png` and `<stem>.svg`.
pub fn plot_histories(
    path: &std::path::Path,
    stem: &std::path::Path,
    bins: usize,
    existing: Existing,
) -> Result<Vec<std::path::PathBuf>, DatasetError> {
    use crate::plots::{Band, HLine, METHOD_COLOURS, Panel, draw_panels};
    for ext in ["png", "svg"] {
        let p = stem.with_extension(ext);
        output::check_output(&p, existing).map_err(|e| DatasetError::Config(e.to_string()))?;
    }
    let file = crate::data::histories::read_histories(path, None)?;
    let bins = bins.max(1);
    let mut limits: Vec<f32> = Vec::new();
    for h in &file.histories {
        if !limits.contains(&h.cost_limit) {
            limits.push(h.cost_limit);
        }
    }
    let x: Vec<f64> = (0..bins).map(|b| (b as f64 + 0.5) / bins as f64).collect();
    let source = serde_json::from_str::<serde_json::Value>(&file.info.config)
        .ok()
        .and_then(|v| v["dataset"]["source"].as_str().map(str::to_string))
        .map_or("", |s| {
            if s == "noisy-optimal" {
                "AD-eps (noisy optimal)"
            } else {
                "PPO-Lagrangian"
            }
        })
        .to_string();
    let mut ret = Panel {
        title: format!("{}: {source} learning histories", file.info.env),
        x_label: "fraction of the history's episodes".into(),
        y_label: "episode return".into(),
        ..Default::default()
    };
    let mut cost = Panel {
        title: format!("{}: episode cost", file.info.env),
        x_label: "fraction of the history's episodes".into(),
        y_label: "episode cost".into(),
        ..Default::default()
    };
    for (i, &limit) in limits.iter().enumerate() {
        // Per history, the mean of each bin; then mean and s.e. over histories.
        let mut per_hist: Vec<Vec<(f64, f64)>> = Vec::new();
        for h in file.histories.iter().filter(|h| h.cost_limit == limit) {
            let totals = h.episode_totals();
            if totals.len() < bins {
                continue;
            }
            per_hist.push(
                (0..bins)
                    .map(|b| {
                        let part = &totals[b * totals.len() / bins..(b + 1) * totals.len() / bins];
                        let n = part.len() as f64;
                        (
                            part.iter().map(|e| e.0 as f64).sum::<f64>() / n,
                            part.iter().map(|e| e.1 as f64).sum::<f64>() / n,
                        )
                    })
                    .collect(),
            );
        }
        let n = per_hist.len() as f64;
        if n == 0.0 {
            continue;
        }
        let stat = |f: &dyn Fn(&(f64, f64)) -> f64| -> (Vec<f64>, Vec<f64>) {
            (0..bins)
                .map(|b| {
                    let v: Vec<f64> = per_hist.iter().map(|h| f(&h[b])).collect();
                    let m = v.iter().sum::<f64>() / n;
                    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
                    (m, (var / n).sqrt())
                })
                .unzip()
        };
        let colour = METHOD_COLOURS[i % METHOD_COLOURS.len()];
        let label = format!("cost limit {limit} ({} histories)", per_hist.len());
        let (m, se) = stat(&|p| p.0);
        ret.bands
            .push(Band::shaded(label.clone(), x.clone(), m, se, colour));
        let (m, se) = stat(&|p| p.1);
        cost.bands
            .push(Band::shaded(label, x.clone(), m, se, colour));
        cost.hlines.push(HLine {
            label: format!("limit {limit}"),
            y: limit as f64,
            colour,
        });
    }
    draw_panels(stem, 1, 2, &[ret, cost])
        .map_err(|e| DatasetError::Config(format!("plotting {}: {e}", stem.display())))
}
