//! ARCHITECTURE.md's invariant, read off the source: no two rooms of
//! `icrl/src` use each other, and no learner uses evaluation, figures or the
//! command line. A room is a folder (`eppo/`, `eval/`, ...), or one file of
//! the shared core or of `data/`; what a room uses is every `crate::ROOM`
//! path in its code outside comments and test modules.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

const LEARNERS: [&str; 3] = ["eppo", "ppo_lagrangian", "ad"];
const ABOVE_LEARNERS: [&str; 3] = ["eval", "plots", "cli"];
/// Folders whose files are rooms of their own: `data/` holds the history
/// format below the learners and the dataset maker above them.
const SPLIT_FOLDERS: [&str; 1] = ["data"];

fn src() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The room of a source file, `None` for the binaries and test-only files.
fn room(relative: &Path) -> Option<String> {
    let parts: Vec<String> = relative
        .iter()
        .map(|p| p.to_string_lossy().trim_end_matches(".rs").to_string())
        .collect();
    let first = parts.first()?.as_str();
    let test_only = parts
        .iter()
        .any(|p| p == "tests" || p.ends_with("_tests") || p == "lib");
    if first == "bin" || test_only {
        return None;
    }
    Some(match parts.as_slice() {
        [one] => one.clone(),
        [folder, file, ..] if SPLIT_FOLDERS.contains(&folder.as_str()) && file != "mod" => {
            format!("{folder}::{file}")
        }
        [folder, ..] => folder.clone(),
        [] => return None,
    })
}

/// The code of `text` without comments and without the test module that
/// ends a file.
fn code(text: &str) -> String {
    let mut lines = Vec::new();
    let mut previous_cfg_test = false;
    for line in text.lines() {
        let trimmed = line.trim_start();
        if previous_cfg_test && trimmed.starts_with("mod tests") {
            break;
        }
        previous_cfg_test = trimmed.starts_with("#[cfg(test)]");
        if !trimmed.starts_with("//") {
            lines.push(line);
        }
    }
    lines.join("\n")
}

/// The rooms `text` names through `crate::` paths.
fn used_rooms(text: &str) -> BTreeSet<String> {
    let code = code(text);
    let mut used = BTreeSet::new();
    for (at, _) in code.match_indices("crate::") {
        let after = &code[at + "crate::".len()..];
        let name = |s: &str| -> String {
            s.chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect()
        };
        let first = name(after);
        if SPLIT_FOLDERS.contains(&first.as_str()) {
            let rest = after[first.len()..].strip_prefix("::").unwrap_or("");
            used.insert(format!("{first}::{}", name(rest)));
        } else if !first.is_empty() {
            used.insert(first);
        }
    }
    used
}

/// Every room with the rooms it uses.
fn uses() -> BTreeMap<String, BTreeSet<String>> {
    let root = src();
    let mut files = Vec::new();
    rust_files(&root, &mut files);
    let mut uses: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for file in files {
        let relative = file.strip_prefix(&root).unwrap();
        let Some(room) = room(relative) else {
            continue;
        };
        let used = used_rooms(&fs::read_to_string(&file).unwrap());
        let entry = uses.entry(room.clone()).or_default();
        entry.extend(used.into_iter().filter(|u| *u != room));
    }
    uses
}

#[test]
fn the_reader_finds_rooms_and_their_uses() {
    assert_eq!(room(Path::new("eppo/losses.rs")).as_deref(), Some("eppo"));
    assert_eq!(
        room(Path::new("data/merge.rs")).as_deref(),
        Some("data::merge")
    );
    assert_eq!(room(Path::new("eppo/tests/run.rs")), None);
    assert_eq!(room(Path::new("bin/icrl.rs")), None);
    let text = "use crate::eval::Summary;\n// crate::plots in a comment\nfn f() { crate::data::merge::verify(); }\n#[cfg(test)]\nmod tests {\n    use crate::cli::x;\n}\n";
    let used = used_rooms(text);
    assert_eq!(
        used,
        BTreeSet::from(["eval".to_string(), "data::merge".to_string()])
    );
    let uses = uses();
    assert!(uses["eval"].contains("eppo"), "eval loads EPPO agents");
    assert!(uses.contains_key("data::histories") && uses.contains_key("signals"));
}

#[test]
fn no_two_rooms_use_each_other() {
    let uses = uses();
    let mut loops = Vec::new();
    for (room, used) in &uses {
        for other in used {
            if room < other && uses.get(other).is_some_and(|u| u.contains(room)) {
                loops.push(format!("{room} <-> {other}"));
            }
        }
    }
    assert!(
        loops.is_empty(),
        "rooms that use each other: {loops:?}; move what both need below both"
    );
}

#[test]
fn no_learner_uses_evaluation_figures_or_the_command_line() {
    let uses = uses();
    for learner in LEARNERS {
        let above: Vec<&String> = uses[learner]
            .iter()
            .filter(|u| ABOVE_LEARNERS.contains(&u.as_str()))
            .collect();
        assert!(
            above.is_empty(),
            "{learner} uses {above:?}, which sit above the learners"
        );
    }
}
