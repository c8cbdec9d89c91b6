//! The paper's evaluation figures, one column per environment: Figure 1
//! (return and cost against the episode index) and Figure 2 (the budget sweep).

use std::path::{Path, PathBuf};

use super::{
    BUDGET_COLOUR, Band, EnvCurves, HLine, METHOD_COLOURS, Panel, PlotError, RANDOM_COLOUR,
    draw_panels, lighter,
};

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
            search.bands.push(Band::line(
                format!("{label}: discovery"),
                x.clone(),
                later.iter().map(|p| p.discovery.mean).collect(),
                colour,
                thin,
            ));
            search.bands.push(Band::line(
                format!("{label}: revisit"),
                x,
                later.iter().map(|p| p.revisit.mean).collect(),
                lighter(colour),
                thin,
            ));
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
            ret.bands.push(Band::shaded(
                label.clone(),
                x.clone(),
                s.per_episode.iter().map(|p| p.ret.mean).collect(),
                s.per_episode.iter().map(|p| p.ret.se).collect(),
                colour,
            ));
            cost.bands.push(Band::shaded(
                label.clone(),
                x,
                s.per_episode.iter().map(|p| p.cost.mean).collect(),
                s.per_episode.iter().map(|p| p.cost.se).collect(),
                colour,
            ));
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
                panel.bands.push(Band::random_policy(x.clone(), ys));
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
            ret.bands.push(Band::shaded(
                label.clone(),
                x.clone(),
                pts.iter().map(|p| p.total_return.mean).collect(),
                pts.iter().map(|p| p.total_return.se).collect(),
                colour,
            ));
            cost.bands.push(Band::shaded(
                label.clone(),
                x,
                pts.iter().map(|p| p.max_cost.mean).collect(),
                pts.iter().map(|p| p.max_cost.se).collect(),
                colour,
            ));
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
                panel.bands.push(Band::random_policy(x.clone(), ys));
            }
        }
        returns.push(ret);
        costs.push(cost);
    }
    returns.extend(costs);
    draw_panels(stem, 2, envs.len(), &returns)
}
