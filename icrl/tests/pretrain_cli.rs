//! `icrl pretrain` from the command line: a tiny Point run ends by saying
//! whether it learned (against a random policy), where its checkpoint is and
//! the exact command that evaluates it; its manifest records the macro action.

use std::process::Command;

mod common;
use common::{TINY_EPPO_SETS, set_args};

#[test]
fn a_tiny_point_run_prints_its_trend_checkpoint_and_eval_command() {
    let out = std::env::temp_dir().join(format!("icrl-pretrain-cli-{}", std::process::id()));
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_icrl"));
    cmd.args(["pretrain", "--env", "point", "--preset", "quick", "--out"])
        .arg(&out);
    // Point's macro action cut to 10 physics steps (the manifest records it).
    cmd.args(set_args(
        TINY_EPPO_SETS
            .into_iter()
            .chain(["physics_steps_per_action=10"]),
    ));
    let run = cmd.output().expect("run icrl");
    let stdout = String::from_utf8_lossy(&run.stdout);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(stdout.contains("random policy: "), "{stdout}");
    assert!(
        stdout.contains("learning (") || stdout.contains("no episode finished"),
        "{stdout}"
    );
    let ckpt_line = stdout
        .lines()
        .find_map(|l| l.strip_prefix("checkpoint: "))
        .unwrap_or_else(|| panic!("no checkpoint line: {stdout}"));
    assert!(
        stdout.contains(&format!(
            "cargo xtask eval --checkpoint {ckpt_line} --env point --out results/eval_point"
        )),
        "{stdout}"
    );
    let manifest: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(std::path::Path::new(ckpt_line).join("manifest.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(manifest["physics_steps_per_action"], 10);
    std::fs::remove_dir_all(&out).unwrap();
}
