//! ARCHITECTURE.md's invariants, read off the source: no two rooms of
//! `icrl/src` use each other, and no learner uses evaluation, figures or the
//! command line. A room is a folder (`eppo/`, `eval/`, ...), or one file or
//! folder of the shared core or of `data/`; what a room uses is every
//! `crate::ROOM` path in its code outside comments and test modules. And
//! the size a reader meets: no file longer than [`MAX_FILE_LINES`] before
//! its tests, no function longer than [`MAX_FUNCTION_LINES`].

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

const LEARNERS: [&str; 3] = ["eppo", "ppo_lagrangian", "ad"];
const ABOVE_LEARNERS: [&str; 3] = ["eval", "plots", "cli"];
/// Folders whose files are rooms of their own: `data/` holds the history
/// format below the learners and the dataset maker above them.
const SPLIT_FOLDERS: [&str; 1] = ["data"];
/// Lines a source file may hold before its test module (issue 52): past
/// it, split the file into a folder of parts.
const MAX_FILE_LINES: usize = 900;
/// Lines a function outside tests may span, from its `fn` line to its
/// closing brace: past it, break it into named steps.
const MAX_FUNCTION_LINES: usize = 120;

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

/// The parts of a source file's path relative to `src`, without `.rs`.
fn path_parts(relative: &Path) -> Vec<String> {
    relative
        .iter()
        .map(|p| p.to_string_lossy().trim_end_matches(".rs").to_string())
        .collect()
}

/// A file that holds only tests (`tests.rs`, a `tests/` folder, `*_tests.rs`).
fn test_only(parts: &[String]) -> bool {
    parts.iter().any(|p| p == "tests" || p.ends_with("_tests"))
}

/// The room of a source file, `None` for the binaries, `lib.rs` and
/// test-only files.
fn room(relative: &Path) -> Option<String> {
    let parts = path_parts(relative);
    let first = parts.first()?.as_str();
    if first == "bin" || first == "lib" || test_only(&parts) {
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

/// The lines of `text` before the test module written out at its end
/// (`#[cfg(test)]` then `mod tests {`); a test module in a file of its own
/// (`mod tests;`) ends nothing.
fn before_tests(text: &str) -> Vec<&str> {
    let mut lines = Vec::new();
    let mut previous_cfg_test = false;
    for line in text.lines() {
        let trimmed = line.trim();
        if previous_cfg_test && trimmed.contains("mod tests") && trimmed.ends_with('{') {
            lines.pop();
            break;
        }
        previous_cfg_test = trimmed.starts_with("#[cfg(test)]");
        lines.push(line);
    }
    lines
}

/// The code of `text` without comments and without its test module.
fn code(text: &str) -> String {
    before_tests(text)
        .into_iter()
        .filter(|line| !line.trim_start().starts_with("//"))
        .collect::<Vec<_>>()
        .join("\n")
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
    assert_eq!(room(Path::new("eppo/tests.rs")), None);
    assert_eq!(
        room(Path::new("data/histories/read.rs")).as_deref(),
        Some("data::histories")
    );
    assert_eq!(
        room(Path::new("checkpoint/mod.rs")).as_deref(),
        Some("checkpoint")
    );
    // A test module in its own file ends nothing: the code after it counts.
    let outlined = "#[cfg(test)]\nmod tests;\nuse crate::plots::x;\n";
    assert_eq!(used_rooms(outlined), BTreeSet::from(["plots".to_string()]));
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

/// Every source file of `src` (the binaries and `lib.rs` included, test-only
/// files not), relative to `src`, with its text.
fn source_files() -> Vec<(PathBuf, String)> {
    let root = src();
    let mut files = Vec::new();
    rust_files(&root, &mut files);
    files.sort();
    files
        .into_iter()
        .filter_map(|file| {
            let relative = file.strip_prefix(&root).unwrap().to_path_buf();
            let text = fs::read_to_string(&file).unwrap();
            (!test_only(&path_parts(&relative))).then_some((relative, text))
        })
        .collect()
}

/// Each function of `lines` (rustfmt's layout: its closing brace at the
/// indentation of its `fn` line) with its first line (from 1) and length.
fn functions(lines: &[&str]) -> Vec<(String, usize, usize)> {
    let mut found = Vec::new();
    for (at, line) in lines.iter().enumerate() {
        let code = line.trim_start();
        let indent = &line[..line.len() - code.len()];
        let mut words = code;
        for qualifier in [
            "pub(crate) ",
            "pub(super) ",
            "pub ",
            "const ",
            "async ",
            "unsafe ",
        ] {
            words = words.strip_prefix(qualifier).unwrap_or(words);
        }
        let Some(signature) = words.strip_prefix("fn ") else {
            continue;
        };
        let name: String = signature
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect();
        // A body on one line has nothing to bound; a declaration without a
        // body ends with `;` before any `{`.
        if code.trim_end().ends_with('}') {
            continue;
        }
        let body = lines[at..]
            .iter()
            .map(|l| l.trim_end())
            .find(|l| l.ends_with('{') || l.ends_with(';'))
            .is_some_and(|l| l.ends_with('{'));
        let close = format!("{indent}}}");
        let end = lines[at + 1..].iter().position(|l| *l == close);
        if let (true, Some(end)) = (body, end) {
            found.push((name, at + 1, end + 2));
        }
    }
    found
}

#[test]
fn the_size_reader_finds_tests_and_functions() {
    let text = "fn short() {\n    let x = 1;\n}\n\npub(crate) fn longer(\n    a: u8,\n) -> u8 {\n    a\n}\ntrait T {\n    fn declared(&self);\n    fn empty(&self) {}\n}\n#[cfg(test)]\nmod tests {\n    fn hidden() {}\n}\n";
    let lines = before_tests(text);
    assert_eq!(lines.len(), 13, "{lines:?}");
    assert_eq!(
        functions(&lines),
        vec![("short".to_string(), 1, 3), ("longer".to_string(), 5, 5)]
    );
    assert!(source_files().iter().any(|(p, _)| p.ends_with("lib.rs")));
    assert!(source_files().iter().all(|(p, _)| !p.ends_with("tests.rs")));
}

#[test]
fn no_file_is_longer_than_the_bound_before_its_tests() {
    let long: Vec<String> = source_files()
        .iter()
        .map(|(path, text)| (path, before_tests(text).len()))
        .filter(|(_, n)| *n > MAX_FILE_LINES)
        .map(|(path, n)| format!("{}: {n} lines", path.display()))
        .collect();
    assert!(
        long.is_empty(),
        "files over {MAX_FILE_LINES} lines before their tests: {long:?}; make each a folder \
         of parts (checkpoint/, data/histories/), its public paths re-exported"
    );
}

#[test]
fn no_function_is_longer_than_the_bound() {
    let mut long = Vec::new();
    for (path, text) in source_files() {
        for (name, line, n) in functions(&before_tests(&text)) {
            if n > MAX_FUNCTION_LINES {
                long.push(format!("{}:{line} {name}: {n} lines", path.display()));
            }
        }
    }
    assert!(
        long.is_empty(),
        "functions over {MAX_FUNCTION_LINES} lines: {long:?}; break each into named steps, \
         in the order they run"
    );
}
