//! `icrl eval` from the command line: bad input fails with a clear message
//! and a non-zero exit code; a small random-policy evaluation writes its files.

use std::process::Command;

fn icrl(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_icrl"))
        .arg("eval")
        .args(args)
        .output()
        .expect("run icrl");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn bad_input_is_refused_with_a_clear_message() {
    let (ok, _, err) = icrl(&["--env", "nowhere"]);
    assert!(!ok && err.contains("invalid value 'nowhere'"), "{err}");
    let (ok, _, err) = icrl(&["--env", "darkroom", "--tasks", "0"]);
    assert!(!ok && err.contains("task set is empty"), "{err}");
    let (ok, _, err) = icrl(&["--env", "darkroom", "--checkpoint", "/nonexistent/run"]);
    assert!(
        !ok && err.contains("/nonexistent/run: not a folder"),
        "{err}"
    );
    let (ok, _, err) = icrl(&["--env", "darkroom", "--no-random"]);
    assert!(!ok && err.contains("nothing to evaluate"), "{err}");
    let (ok, _, err) = icrl(&["--env", "darkroom", "--budgets", "nan"]);
    assert!(!ok && err.contains("finite"), "{err}");
    let (ok, _, err) = icrl(&["--env", "darkroom", "--render-task", "1"]);
    assert!(!ok && err.contains("--render"), "{err}");
    let render_past_the_tasks: Vec<&str> =
        "--env darkroom --tasks 2 --episodes 2 --n-budgets 3 --render --render-task 2"
            .split(' ')
            .collect();
    let (ok, _, err) = icrl(&render_past_the_tasks);
    assert!(
        !ok && err.contains("--render-budget 0 --render-task 2: the rendered trajectory")
            && err.contains("outside the 3 budgets x 2 tasks"),
        "{err}"
    );
}

#[test]
fn random_policy_evaluation_from_the_command_line() {
    let out = std::env::temp_dir().join(format!("icrl-eval-cli-{}", std::process::id()));
    let out_s = out.display().to_string();
    let (ok, stdout, err) = icrl(&[
        "--env",
        "darkroom",
        "--tasks",
        "2",
        "--episodes",
        "3",
        "--n-budgets",
        "2",
        "--sweep",
        "--render",
        "--render-task",
        "1",
        "--render-budget",
        "1",
        "--out",
        &out_s,
    ]);
    assert!(ok, "{err}");
    // The trajectory asked for is the one recorded and rendered.
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("random_darkroom.json")).unwrap()).unwrap();
    let recording = &report["result"]["recording"];
    assert_eq!(recording["task"], 1, "{recording}");
    assert_eq!(recording["condition"], 1, "{recording}");
    assert!(
        stdout.contains("random policy darkroom figure1"),
        "{stdout}"
    );
    for name in [
        "random_darkroom.json",
        "figure1_darkroom.png",
        "figure2_darkroom.svg",
        "render_random_darkroom.gif",
    ] {
        let len = std::fs::metadata(out.join(name))
            .map(|m| m.len())
            .unwrap_or(0);
        assert!(len > 100, "{name}: {len} bytes");
    }
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn point_render_replays_the_recorded_actions() {
    let out = std::env::temp_dir().join(format!("icrl-eval-cli-point-{}", std::process::id()));
    let out_s = out.display().to_string();
    let (ok, _, err) = icrl(&[
        "--env",
        "point",
        "--tasks",
        "1",
        "--episodes",
        "2",
        "--n-budgets",
        "1",
        "--render",
        "--out",
        &out_s,
    ]);
    assert!(ok, "{err}");
    // MuJoCo renders a replay that must match the recording step for step;
    // a divergence (or no OpenGL) would be reported on stderr.
    assert!(!err.contains("MuJoCo rendering failed"), "{err}");
    assert!(
        std::fs::metadata(out.join("render_random_point.gif"))
            .unwrap()
            .len()
            > 1000
    );
    std::fs::remove_dir_all(&out).unwrap();
}
