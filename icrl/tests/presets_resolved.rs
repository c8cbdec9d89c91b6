//! Every EPPO preset resolves to the settings recorded in
//! `tests/presets_resolved/`: a refactor of the config (settings moved into
//! sections, levers retired) must leave what each preset trains with as it
//! was. After a deliberate change of a preset, record it again with
//! `ICRL_RECORD_PRESETS=1 cargo test -p icrl --test presets_resolved`.

use std::collections::BTreeMap;
use std::path::Path;

use icrl::eppo::EppoConfig;

/// Every leaf of a TOML table by its flat name (`a.b`), so that a setting
/// moved into a section compares with the recorded one after renaming.
fn leaves(table: &toml::Table) -> BTreeMap<String, String> {
    let mut out = Vec::new();
    icrl::cli::pretrain::flatten("", table, &mut out);
    out.into_iter().collect()
}

#[test]
fn every_eppo_preset_resolves_to_its_recorded_settings() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/presets_resolved");
    let record = std::env::var_os("ICRL_RECORD_PRESETS").is_some();
    let mut compared = 0;
    for env in ["darkroom", "point", "car"] {
        for preset in ["quick", "table1", "budget"] {
            let Ok(table) = icrl::presets::preset_table("eppo", env, preset) else {
                continue;
            };
            let name = format!("eppo-{env}-{preset}");
            let cfg = EppoConfig::from_table(&name, table).unwrap();
            let text = toml::to_string(&cfg).unwrap();
            let path = dir.join(format!("{name}.toml"));
            if record {
                std::fs::create_dir_all(&dir).unwrap();
                std::fs::write(&path, &text).unwrap();
            }
            let recorded: toml::Table = std::fs::read_to_string(&path)
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
                .parse()
                .unwrap();
            assert_eq!(leaves(&text.parse().unwrap()), leaves(&recorded), "{name}");
            compared += 1;
        }
    }
    assert_eq!(compared, 7, "the seven EPPO presets");
}
