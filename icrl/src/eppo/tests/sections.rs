//! The settings in sections: the one table of each setting's section
//! (`EppoConfig::SECTIONS`), the flat form of every committed config moved
//! into it with its values, `--set` by a setting's name or its section's,
//! and names refused as before.

use super::config::drop_retired;
use super::*;

fn results() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../results")
}

fn read_table(path: &Path) -> toml::Table {
    std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .parse()
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Every leaf of a table by the name `--set` gives it (`lambda_max`, and
/// `model.d_model` for the transformer's).
fn leaves_by_name(table: &toml::Table) -> std::collections::BTreeMap<String, String> {
    let mut out = Vec::new();
    crate::cli::pretrain::flatten("", table, &mut out);
    out.into_iter()
        .map(|(key, value)| (EppoConfig::flat_name(&key).to_string(), value))
        .collect()
}

/// The names a section's struct writes, the transformer's left out.
fn written_names(cfg: &EppoConfig) -> Vec<(String, Vec<String>)> {
    let table: toml::Table = toml::to_string(cfg).unwrap().parse().unwrap();
    let transformer: toml::Table = toml::to_string(&cfg.model.transformer)
        .unwrap()
        .parse()
        .unwrap();
    table
        .into_iter()
        .map(|(section, settings)| {
            let settings = settings
                .as_table()
                .cloned()
                .unwrap_or_else(|| panic!("{section} = {settings}: only sections at the top"));
            let names = settings
                .keys()
                .filter(|k| !(section == "model" && transformer.contains_key(*k)))
                .cloned()
                .collect();
            (section, names)
        })
        .collect()
}

/// The table names every setting the sections write, once, in the section
/// that writes it; besides them it holds only the two older names the
/// fields still read.
#[test]
fn the_section_table_names_every_setting_once() {
    let mut cfg = tiny();
    // The optional settings written too.
    cfg.optimisation.replay_ratio = Some(1.0);
    cfg.tasks.physics_steps_per_action = Some(50);
    cfg.constraint.constraint_after_revisit = Some(0.5);
    cfg.constraint.over_budget_price_schedule = vec![PriceChange {
        after: 1,
        price: 1.0,
    }];
    cfg.exploration.target_entropy = Some(-1.0);
    let written = written_names(&cfg);
    let mut sections: Vec<&str> = written.iter().map(|(s, _)| s.as_str()).collect();
    sections.sort_unstable();
    let mut listed_sections = EppoConfig::SECTIONS.map(|(s, _)| s);
    listed_sections.sort_unstable();
    assert_eq!(sections, listed_sections, "the sections");
    let mut all = Vec::new();
    for (section, names) in &written {
        let (_, listed) = EppoConfig::SECTIONS
            .iter()
            .find(|(s, _)| s == section)
            .unwrap();
        let older: Vec<&str> = listed
            .iter()
            .copied()
            .filter(|n| !names.iter().any(|w| w == n))
            .collect();
        let want: &[&str] = match section.as_str() {
            "constraint" => &["saute_cost_price"],
            "novelty" => &["novelty_within_budget"],
            _ => &[],
        };
        assert_eq!(older, want, "[{section}]");
        assert_eq!(names.len() + older.len(), listed.len(), "[{section}]");
        all.extend(listed.iter().copied());
    }
    let mut unique = all.clone();
    unique.sort_unstable();
    unique.dedup();
    assert_eq!(unique.len(), all.len(), "a name in two sections");
    assert_eq!(all.len(), 68 + 2, "68 settings and 2 older names");
}

/// Every committed EPPO config (all written flat, before the sections)
/// moves into sections with each value as it was, and the config it
/// resolves to reads back the same from the sectioned form it is now saved in.
#[test]
fn every_committed_flat_config_moves_into_sections_with_its_values() {
    let mut configs = Vec::new();
    let mut dirs = vec![results()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap().flatten() {
            let path = entry.path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.file_name().is_some_and(|n| n == "config.toml") {
                configs.push(path);
            }
        }
    }
    let mut moved = 0;
    for path in &configs {
        let Ok(flat) = std::fs::read_to_string(path)
            .unwrap()
            .parse::<toml::Table>()
        else {
            continue;
        };
        if EppoConfig::setting(&flat, "n_critics").is_none() {
            continue; // not an EPPO config
        }
        let Ok(cfg) = EppoConfig::from_table("c", flat.clone()) else {
            continue; // refused by a retired setting's name (constraint.rs)
        };
        let mut table = flat;
        drop_retired(&mut table).unwrap();
        let before = leaves_by_name(&table);
        EppoConfig::migrate(&mut table).unwrap();
        assert!(
            table.values().all(toml::Value::is_table),
            "{}: only sections at the top",
            path.display()
        );
        assert_eq!(leaves_by_name(&table), before, "{}", path.display());
        let sectioned: toml::Table = toml::to_string(&cfg).unwrap().parse().unwrap();
        assert_eq!(
            EppoConfig::from_table("saved", sectioned).unwrap(),
            cfg,
            "{}",
            path.display()
        );
        moved += 1;
    }
    assert!(moved > 100, "{moved} of {} configs moved", configs.len());
}

/// `--set` by a setting's name finds its section, as the dotted name does,
/// on a flat table and a sectioned one; an optional section absent from the
/// table is added; a whole number given for a number with a fraction stays one.
#[test]
fn a_set_finds_its_section_by_name() {
    let flat = crate::presets::preset_table("eppo", "darkroom", "quick").unwrap();
    let mut sectioned = flat.clone();
    EppoConfig::migrate(&mut sectioned).unwrap();
    sectioned.remove("goal");
    for table in [flat, sectioned] {
        let set = |sets: &[&str]| {
            let mut t = table.clone();
            let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
            EppoConfig::apply_sets(&mut t, &sets).unwrap();
            t
        };
        let by_name = set(&["lambda_max=1", "relabel_prob=0.5", "encoder_hidden=32"]);
        let dotted = set(&[
            "constraint.lambda_max=1",
            "goal.relabel_prob=0.5",
            "model.encoder_hidden=32",
        ]);
        assert_eq!(by_name, dotted);
        assert_eq!(
            EppoConfig::setting(&by_name, "lambda_max"),
            Some(&toml::Value::Float(1.0))
        );
        let cfg = EppoConfig::from_table("set", by_name).unwrap();
        assert_eq!(
            (
                cfg.constraint.lambda_max,
                cfg.goal.relabel_prob,
                cfg.model.encoder_hidden
            ),
            (1.0, 0.5, 32)
        );
    }
}

/// Names are refused as before the sections, by name: an unknown one (flat
/// or in a section) with the valid ones, a retired one with its commit, and
/// now also a setting in another section than its own, or given twice.
#[test]
fn unknown_misplaced_and_repeated_settings_are_refused_by_name() {
    let table = crate::presets::preset_table("eppo", "darkroom", "quick").unwrap();
    let refused = |sets: &[&str]| {
        let mut t = table.clone();
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        EppoConfig::apply_sets(&mut t, &sets)
            .and_then(|()| EppoConfig::from_table("t", t))
            .unwrap_err()
            .to_string()
    };
    let err = refused(&["lambda_mx=1"]);
    assert!(
        err.contains("lambda_mx") && err.contains("[constraint]") && err.contains("lambda_max"),
        "{err}"
    );
    let err = refused(&["constraint.lambda_mx=1"]);
    assert!(
        err.contains("lambda_mx") && err.contains("lambda_max"),
        "{err}"
    );
    let err = refused(&["tasks.lambda_max=1"]);
    assert!(
        err.contains("[tasks] holds lambda_max, a setting of [constraint]"),
        "{err}"
    );
    let err = refused(&["lambda_kp=0.5"]);
    assert!(err.contains("lambda_kp = 0.5"), "{err}");
    assert!(
        refused(&["modle.n_layers=1"]).contains("modle.n_layers"),
        "a section that does not exist"
    );
    let mut twice = table.clone();
    EppoConfig::migrate(&mut twice).unwrap();
    twice.insert("lambda_max".into(), toml::Value::Float(0.5));
    let err = EppoConfig::from_table("t", twice).unwrap_err().to_string();
    assert!(err.contains("lambda_max is set twice"), "{err}");
}

/// A committed checkpoint written flat resumes a learner, and the checkpoint
/// the learner then writes holds the sectioned form, which reads back as the
/// same config.
#[test]
fn a_committed_flat_checkpoint_resumes_and_saves_in_sections() {
    let ckpt = results().join("eppo_darkroom_budget/dp0_preset_budget_seed0/checkpoints/step_5291");
    let flat = read_table(&ckpt.join("config.toml"));
    assert!(flat.contains_key("lambda_max"), "written flat");
    let cfg = EppoConfig::from_table("dp0", flat).unwrap();
    let learner = Learner::resume(cfg.clone(), EnvName::DarkRoom, &ckpt).unwrap();
    assert_eq!(learner.updates, 5291);
    let out = std::env::temp_dir().join(format!("icrl-eppo-sections-{}", std::process::id()));
    let run = crate::checkpoint::RunDir::create(&out, "darkroom", "eppo", cfg.run.seed).unwrap();
    let saved = learner.save_checkpoint(&run).unwrap();
    let written = read_table(&saved.join("config.toml"));
    assert!(
        written.values().all(toml::Value::is_table),
        "only sections at the top"
    );
    assert_eq!(EppoConfig::from_table("saved", written).unwrap(), cfg);
    std::fs::remove_dir_all(&out).unwrap();
}
