//! Fuzz harness for `icrl sweep --emit slurm` (trial 3's first class: a grid
//! file that executes commands). Each case writes a grid file whose
//! user-written strings (`out`, the `icrl` binary's path, `[slurm]`
//! `partition`, `account`, `mem`, `extra`) are built from shell-hostile
//! pieces: command substitutions, quotes, separators, globs, comment marks,
//! newlines, NUL and other control characters. Every hostile command would
//! create a file named `CANARY`. The oracle, for every case:
//! - the command ends knowing what happened: exit 0, or a failure exit with
//!   an `error:` line; never a panic (101), an abort (134) or a signal;
//! - a script is written only when its text holds no control character;
//! - a written script passes `bash -n`; run under bash once per array task
//!   (Slurm's variables set, `scontrol` a stub on `PATH`, the `icrl` path a
//!   stub that records the arguments it is handed), it hands `icrl` exactly
//!   the task's `SweepGrid::pretrain_args`, one word each;
//! - no `CANARY` ever appears: nothing from the grid file ran.
//!
//! Cases: `ICRL_FUZZ_CASES` (default 30, about a minute); `ICRL_FUZZ_SEED`
//! picks another stream; `ICRL_FUZZ_VERBOSE=1` prints each grid file.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use icrl::cli::sweep::SweepGrid;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn env_number<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// Pieces of the strings a grid file's author controls. The first ones
/// would run `touch CANARY` if any reached a shell unquoted; the last ones
/// are control characters, which a script must never hold.
const HOSTILE: [&str; 24] = [
    "$(touch CANARY)",
    "`touch CANARY`",
    ";touch CANARY;",
    "&& touch CANARY",
    "|touch CANARY",
    ">CANARY",
    "' ; touch CANARY ; '",
    "\" ; touch CANARY ; \"",
    "${IFS}touch${IFS}CANARY",
    "$HOME",
    "*",
    "?",
    "~",
    "\\",
    "#",
    " ",
    "%A",
    "-",
    "{a,b}",
    "é",
    "\n",
    "\r",
    "\t",
    "\u{0}",
];

/// Plain pieces, so that most strings are mostly ordinary.
const PLAIN: [&str; 4] = ["runs", "cpu", "x1", "long"];

fn hostile_string(rng: &mut ChaCha8Rng) -> String {
    let n = rng.gen_range(1..=3);
    (0..n)
        .map(|_| {
            if rng.gen_bool(0.6) {
                *HOSTILE.choose(rng).unwrap()
            } else {
                *PLAIN.choose(rng).unwrap()
            }
        })
        .collect()
}

/// A file name from hostile pieces: no `/` (a path separator, not a
/// name's) and no NUL (which no file name can hold).
fn hostile_file_name(rng: &mut ChaCha8Rng) -> String {
    let name: String = hostile_string(rng)
        .chars()
        .filter(|c| *c != '/' && *c != '\0')
        .collect();
    if name.is_empty() || name == "." || name == ".." {
        "icrl".into()
    } else {
        name
    }
}

fn has_control(s: &str) -> bool {
    s.chars().any(char::is_control)
}

/// What the records `icrl` stub writes: its arguments, NUL-terminated.
const STUB: &str =
    "#!/bin/bash\nfor a in \"$@\"; do printf '%s\\0' \"$a\"; done >> \"$ICRL_STUB_LOG\"\n";

fn write_executable(path: &Path, text: &str) {
    use std::os::unix::fs::PermissionsExt;
    std::fs::write(path, text).unwrap();
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o755)).unwrap();
}

fn canaries(dir: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap().flatten() {
            let path = entry.path();
            if entry.file_name() == "CANARY" {
                found.push(path.clone());
            }
            if entry.file_type().map(|t| t.is_dir()).unwrap_or(false) {
                stack.push(path);
            }
        }
    }
    found
}

/// One case's grid file: a TOML table (so every string is escaped as TOML
/// needs, NUL included) with hostile strings where a user writes text.
fn grid_table(rng: &mut ChaCha8Rng, icrl_stub: &Path) -> toml::Table {
    let mut grid = toml::Table::new();
    grid.insert("env".into(), "darkroom".into());
    grid.insert("preset".into(), "quick".into());
    let seeds: Vec<toml::Value> = if rng.gen_bool(0.5) {
        vec![0.into()]
    } else {
        vec![0.into(), 1.into()]
    };
    grid.insert("seeds".into(), toml::Value::Array(seeds));
    let out = if rng.gen_bool(0.7) {
        hostile_string(rng)
    } else {
        "runs".into()
    };
    grid.insert("out".into(), out.into());
    let mut set = toml::Table::new();
    set.insert("total_updates".into(), 20.into());
    grid.insert("set".into(), toml::Value::Table(set));
    if rng.gen_bool(0.3) {
        let mut values = toml::Table::new();
        values.insert(
            "lr".into(),
            toml::Value::Array(vec![1e-4.into(), 3e-4.into()]),
        );
        grid.insert("grid".into(), toml::Value::Table(values));
    }
    let mut slurm = toml::Table::new();
    for key in ["partition", "account", "mem"] {
        if rng.gen_bool(0.4) {
            slurm.insert(key.into(), hostile_string(rng).into());
        }
    }
    if rng.gen_bool(0.4) {
        let extra = (0..rng.gen_range(1..=2))
            .map(|_| toml::Value::String(hostile_string(rng)))
            .collect();
        slurm.insert("extra".into(), toml::Value::Array(extra));
    }
    slurm.insert("icrl".into(), icrl_stub.display().to_string().into());
    grid.insert("slurm".into(), toml::Value::Table(slurm));
    grid
}

#[test]
fn emitted_scripts_run_only_our_commands() {
    let cases: usize = env_number("ICRL_FUZZ_CASES", 30);
    let seed: u64 = env_number("ICRL_FUZZ_SEED", 0);
    let verbose = std::env::var("ICRL_FUZZ_VERBOSE").is_ok_and(|v| v == "1");
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let root = std::env::temp_dir().join(format!("icrl-fuzz-sweep-{}", std::process::id()));
    std::fs::create_dir_all(&root).unwrap();
    let bin = root.join("bin");
    std::fs::create_dir(&bin).unwrap();
    write_executable(
        &bin.join("scontrol"),
        "#!/bin/bash\necho \"scontrol $*\" >> scontrol.log\n",
    );
    let path = format!("{}:{}", bin.display(), std::env::var("PATH").unwrap());
    let (mut written, mut refused) = (0, 0);
    for case in 0..cases {
        let dir = root.join(format!("case_{case}"));
        std::fs::create_dir(&dir).unwrap();
        let stub = dir.join(hostile_file_name(&mut rng));
        write_executable(&stub, STUB);
        let table = grid_table(&mut rng, &stub);
        let text = toml::to_string(&table).unwrap();
        let grid_file = dir.join("grid.toml");
        std::fs::write(&grid_file, &text).unwrap();
        if verbose {
            eprintln!("case {case}:\n{text}");
        }
        let emitted = Command::new(env!("CARGO_BIN_EXE_icrl"))
            .args(["sweep", "--grid"])
            .arg(&grid_file)
            .args(["--emit", "slurm"])
            .current_dir(&dir)
            .stdin(Stdio::null())
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&emitted.stderr);
        let what = format!(
            "case {case} (grid:\n{text}): exit {:?}, stderr:\n{stderr}",
            emitted.status.code()
        );
        assert!(!stderr.contains("panicked at"), "{what}");
        let control = text_has_control(&table);
        match emitted.status.code() {
            Some(0) => {
                assert!(
                    !control,
                    "a script was written from control characters: {what}"
                );
                written += 1;
            }
            Some(code) if code != 101 && code != 134 => {
                assert!(stderr.contains("error:"), "{what}");
                refused += 1;
                assert!(canaries(&dir).is_empty(), "{what}");
                continue;
            }
            _ => panic!("{what}"),
        }
        let grid = SweepGrid::load(&grid_file).unwrap();
        let script = grid.out.join("sweep.sbatch");
        let syntax = Command::new("bash")
            .arg("-n")
            .arg(&script)
            .output()
            .unwrap();
        assert!(
            syntax.status.success(),
            "bash -n: {what}\n{}",
            String::from_utf8_lossy(&syntax.stderr)
        );
        for task in grid.tasks() {
            let log = dir.join(format!("args_{}.log", task.index));
            let ran = Command::new("bash")
                .arg(&script)
                .current_dir(&dir)
                .env("PATH", &path)
                .env("SLURM_ARRAY_TASK_ID", task.index.to_string())
                .env("SLURM_ARRAY_JOB_ID", "7")
                .env("ICRL_STUB_LOG", &log)
                .stdin(Stdio::null())
                .output()
                .unwrap();
            assert!(
                ran.status.success(),
                "task {}: {what}\n{}",
                task.index,
                String::from_utf8_lossy(&ran.stderr)
            );
            let bytes = std::fs::read(&log).unwrap();
            let handed: Vec<String> = bytes
                .split(|b| *b == 0)
                .filter(|w| !w.is_empty())
                .map(|w| String::from_utf8(w.to_vec()).unwrap())
                .collect();
            assert_eq!(
                handed,
                grid.pretrain_args(&task),
                "task {}: {what}",
                task.index
            );
        }
        assert!(
            canaries(&dir).is_empty(),
            "a command from the grid file ran: {what}"
        );
    }
    std::fs::remove_dir_all(&root).unwrap();
    // The stream reaches both sides, or the oracle checked nothing.
    assert!(
        written > 0 && refused > 0,
        "written {written}, refused {refused}"
    );
}

/// Whether any string of the grid file (at any depth) holds a control
/// character.
fn text_has_control(table: &toml::Table) -> bool {
    fn value(v: &toml::Value) -> bool {
        match v {
            toml::Value::String(s) => has_control(s),
            toml::Value::Array(a) => a.iter().any(value),
            toml::Value::Table(t) => t.values().any(value),
            _ => false,
        }
    }
    table.values().any(value)
}
