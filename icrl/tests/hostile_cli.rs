//! The `icrl` binary under the second hostile trial (issue 21): outputs never
//! replace what is not ours, one process per run, and every message true.
//! Each test runs the binary in a child process on tiny inputs.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn icrl(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_icrl"))
        .args(args)
        .output()
        .expect("run icrl")
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("icrl-hostile-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

/// Fails unless the command failed with `want` in stderr and no panic.
fn refused(out: &Output, want: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "expected a failure: {err}");
    assert_eq!(out.status.code(), Some(1), "exit 1: {err}");
    assert!(err.contains(want), "expected {want:?} in: {err}");
    assert!(
        !err.contains("panicked") && !err.contains("backtrace"),
        "no panic: {err}"
    );
}

fn succeeded(out: &Output) -> String {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "expected success: {err}");
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// A tiny dataset command writing `out`.
fn dataset(out: &str, extra: &[&str]) -> Output {
    let mut args = vec![
        "dataset",
        "--env",
        "darkroom",
        "--out",
        out,
        "--tasks",
        "1",
        "--steps",
        "300",
        "--cost-limits",
        "0",
        "--threads",
        "1",
    ];
    args.extend(extra);
    icrl(&args)
}

#[test]
fn dataset_never_replaces_what_is_not_ours() {
    let dir = tmp("dataset-out");
    // A device, a FIFO, a symlink: refused, even with --force, untouched.
    refused(&dataset("/dev/null", &["--force"]), "it is a device");
    assert!(!std::fs::metadata("/dev/null").unwrap().is_file());
    let fifo = dir.join("fifo");
    assert!(
        Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success()
    );
    refused(&dataset(&s(&fifo), &["--force"]), "it is a FIFO");
    // A checkpoint's weights.
    let ck = dir.join("run/checkpoints/step_20");
    std::fs::create_dir_all(&ck).unwrap();
    std::fs::write(ck.join("manifest.json"), "{}").unwrap();
    std::fs::write(ck.join("model.safetensors"), "weights").unwrap();
    refused(
        &dataset(&s(&ck.join("model.safetensors")), &["--force"]),
        "a file of a checkpoint folder",
    );
    assert_eq!(
        std::fs::read(ck.join("model.safetensors")).unwrap(),
        b"weights"
    );
    // A file where the folder should be: named as such.
    let afile = dir.join("afile");
    std::fs::write(&afile, "notes").unwrap();
    refused(
        &dataset(&s(&afile.join("x.h5")), &[]),
        "is a file, not a folder",
    );
    // An existing dataset: refused without --force, replaced with it.
    let h5 = dir.join("h.h5");
    succeeded(&dataset(&s(&h5), &[]));
    let first = std::fs::read(&h5).unwrap();
    refused(
        &dataset(&s(&h5), &["--seed", "1"]),
        "exists already: pass --force",
    );
    assert_eq!(std::fs::read(&h5).unwrap(), first, "untouched");
    succeeded(&dataset(&s(&h5), &["--seed", "1", "--force"]));
    assert_ne!(std::fs::read(&h5).unwrap(), first, "replaced with --force");
    let left: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(left.is_empty(), "no temporary or lock file left: {left:?}");
    std::fs::remove_dir_all(&dir).unwrap();
}
