//! Task sampling: the centre/edge laws, their invariants and their errors.

use safety_envs::prelude::*;

fn dist(c: Cell, g: usize) -> f64 {
    let m = (g / 2) as f64;
    (c.row as f64 - m).hypot(c.col as f64 - m)
}

/// Mean distance from the centre of goals and of obstacles over `n` draws.
fn mean_distances(cfg: &SpawnConfig, o: Orientation, n: u64) -> (f64, f64) {
    let (mut goal, mut obst, mut n_obst) = (0.0, 0.0, 0usize);
    for seed in 0..n {
        let t = sample_task(cfg, o, seed).unwrap();
        goal += dist(t.goal, cfg.grid_size);
        for &c in &t.obstacles {
            obst += dist(c, cfg.grid_size);
            n_obst += 1;
        }
    }
    (goal / n as f64, obst / n_obst as f64)
}

#[test]
fn edge_oriented_tasks_sit_farther_from_the_centre() {
    // Margins in cells: the 5x5 MuJoCo grid has less room to prefer (its
    // distances span 1 to 2.8 cells) than the 9x9 room (1 to 5.7). Obstacles
    // fill a third of the free cells, which dilutes the preference further.
    for (cfg, goal_margin, obstacle_margin) in [
        (spawn_config(EnvName::DarkRoom), 0.5, 0.2),
        (spawn_config(EnvName::Point), 0.25, 0.05),
    ] {
        let (gc, oc) = mean_distances(&cfg, Orientation::Centre, 2000);
        let (ge, oe) = mean_distances(&cfg, Orientation::Edge, 2000);
        eprintln!("{cfg:?}: goal {gc:.3} -> {ge:.3}, obstacles {oc:.3} -> {oe:.3}");
        assert!(
            ge > gc + goal_margin,
            "{cfg:?}: goal {gc:.3} (centre) vs {ge:.3} (edge)"
        );
        assert!(
            oe > oc + obstacle_margin,
            "{cfg:?}: obstacles {oc:.3} (centre) vs {oe:.3} (edge)"
        );
    }
}

#[test]
fn nothing_on_the_start_cell_and_goal_never_on_an_obstacle() {
    for cfg in [spawn_config(EnvName::DarkRoom), spawn_config(EnvName::Car)] {
        let centre = Cell::centre(cfg.grid_size);
        for o in [Orientation::Centre, Orientation::Edge] {
            for seed in 0..2000 {
                let t = sample_task(&cfg, o, seed).unwrap();
                assert_ne!(t.goal, centre);
                assert!(!t.obstacles.contains(&centre));
                assert!(
                    !t.obstacles.contains(&t.goal),
                    "seed {seed}: goal on an obstacle"
                );
                let mut sorted = t.obstacles.clone();
                sorted.sort();
                sorted.dedup();
                assert_eq!(sorted.len(), cfg.n_obstacles, "repeated obstacle");
                t.validate(cfg.grid_size, cfg.n_obstacles).unwrap();
            }
        }
    }
}

#[test]
fn goal_frequencies_follow_the_exponential_law() {
    // The goal is drawn first, so its law is exactly exp(-+alpha d) / Z over
    // the cells other than the centre.
    let cfg = SpawnConfig {
        grid_size: 5,
        n_obstacles: 3,
        alpha: 0.5,
        distance: Distance::Euclidean,
    };
    let g = cfg.grid_size;
    let n = 40_000;
    for (o, sign) in [(Orientation::Centre, -1.0), (Orientation::Edge, 1.0)] {
        let mut counts = vec![0usize; g * g];
        for seed in 0..n {
            let t = sample_task(&cfg, o, seed).unwrap();
            counts[t.goal.row * g + t.goal.col] += 1;
        }
        let weights: Vec<f64> = (0..g * g)
            .map(|i| {
                let c = Cell {
                    row: i / g,
                    col: i % g,
                };
                if c == Cell::centre(g) {
                    0.0
                } else {
                    (sign * 0.5 * dist(c, g)).exp()
                }
            })
            .collect();
        let z: f64 = weights.iter().sum();
        for i in 0..g * g {
            let p = weights[i] / z;
            let freq = counts[i] as f64 / n as f64;
            // Five standard errors of a binomial frequency.
            let tol = 5.0 * (p * (1.0 - p) / n as f64).sqrt() + 1e-9;
            assert!(
                (freq - p).abs() <= tol,
                "{o}: cell {i}: {freq:.4} vs {p:.4}"
            );
        }
    }
}

#[test]
fn squared_distance_sharpens_the_preference() {
    let euclid = spawn_config(EnvName::DarkRoom);
    let squared = SpawnConfig {
        distance: Distance::Squared,
        ..euclid.clone()
    };
    let (ge, _) = mean_distances(&euclid, Orientation::Centre, 1000);
    let (gs, _) = mean_distances(&squared, Orientation::Centre, 1000);
    assert!(gs < ge - 0.3, "squared {gs:.3} vs euclidean {ge:.3}");
}

#[test]
fn sampling_is_a_pure_function_of_config_orientation_and_seed() {
    let cfg = spawn_config(EnvName::DarkRoom);
    for seed in [0, 1, 17, u64::MAX] {
        assert_eq!(
            sample_task(&cfg, Orientation::Edge, seed).unwrap(),
            sample_task(&cfg, Orientation::Edge, seed).unwrap()
        );
    }
    // Centre and edge streams are unrelated: the same seed gives a different
    // task almost always.
    let same = (0..200)
        .filter(|&s| {
            sample_task(&cfg, Orientation::Centre, s).unwrap()
                == sample_task(&cfg, Orientation::Edge, s).unwrap()
        })
        .count();
    assert_eq!(same, 0);
}

#[test]
fn impossible_configs_are_clear_errors() {
    let too_many = SpawnConfig {
        grid_size: 9,
        n_obstacles: 80,
        ..spawn_config(EnvName::DarkRoom)
    };
    let err = sample_task(&too_many, Orientation::Centre, 0).unwrap_err();
    assert!(matches!(err, EnvError::InvalidConfig(_)));
    assert!(err.to_string().contains("at most 79"), "{err}");
    let tiny = SpawnConfig {
        grid_size: 1,
        n_obstacles: 0,
        ..spawn_config(EnvName::DarkRoom)
    };
    assert!(sample_task(&tiny, Orientation::Centre, 0).is_err());
    let nan = SpawnConfig {
        alpha: f64::NAN,
        ..spawn_config(EnvName::DarkRoom)
    };
    assert!(sample_task(&nan, Orientation::Centre, 0).is_err());
    assert!("middle".parse::<Orientation>().is_err());
    assert_eq!("edge".parse::<Orientation>().unwrap(), Orientation::Edge);
}
