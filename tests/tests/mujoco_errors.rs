//! Engine fatal errors and warnings: an `Err` or a typed event, never an exit
//! or a hang.

use std::io::Read;
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use integration_tests::{SLIDER, SMALL_STACK};
use safety_envs::MujocoError;
use safety_envs::mujoco::{Data, Model, Warning};

/// Steps the small-stack scene until the engine error comes back.
fn step_until_engine_error() -> Result<String, String> {
    let model = Model::from_xml_str(SMALL_STACK).map_err(|e| e.to_string())?;
    let mut data = Data::new(&model).map_err(|e| e.to_string())?;
    for _ in 0..1000 {
        match data.step(&model) {
            Ok(_) => {}
            Err(MujocoError::Engine(msg)) => {
                // The data was reset and is usable again.
                if data.time() != 0.0 {
                    return Err(format!("data not reset: time {}", data.time()));
                }
                data.step(&model).map_err(|e| e.to_string())?;
                return Ok(msg);
            }
            Err(other) => return Err(format!("unexpected error {other}")),
        }
    }
    Err(String::from("no engine error within 1000 steps"))
}

#[test]
fn engine_error_is_err_within_seconds() {
    // A timeout thread: a hang fails the test instead of blocking the suite.
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || tx.send(step_until_engine_error()));
    match rx.recv_timeout(Duration::from_secs(20)) {
        Ok(Ok(msg)) => assert!(msg.contains("Stack overflow"), "{msg}"),
        Ok(Err(problem)) => panic!("{problem}"),
        Err(_) => panic!("the engine error did not come back within 20 s"),
    }
}

/// Run by [`engine_error_with_stdin_open_in_a_child_process`] in a child
/// process whose stdin is an open pipe (MuJoCo's default handler would wait
/// on it for Enter); ignored in a normal run.
#[test]
#[ignore = "run as a child process by engine_error_with_stdin_open_in_a_child_process"]
fn child_engine_error() {
    let msg = step_until_engine_error().expect("engine error as Err");
    println!("CHILD-ENGINE-ERROR: {msg}");
}

#[test]
fn engine_error_with_stdin_open_in_a_child_process() {
    let exe = std::env::current_exe().unwrap();
    let mut child = Command::new(exe)
        .args(["child_engine_error", "--exact", "--ignored", "--nocapture"])
        .arg("--test-threads=1")
        // Kept open and never written: a handler waiting for Enter would block.
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn the test binary");
    let started = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if started.elapsed() > Duration::from_secs(30) {
            child.kill().ok();
            child.wait().ok();
            panic!("the child hung on MuJoCo's engine error (killed after 30 s)");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut stdout = String::new();
    child
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut stdout)
        .ok();
    let mut stderr = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut stderr)
        .ok();
    assert!(status.success(), "child failed: {stdout}\n{stderr}");
    assert!(
        stdout.contains("CHILD-ENGINE-ERROR: Stack overflow"),
        "child did not run the engine error: {stdout}"
    );
    // MuJoCo's own printing stayed off stdout.
    assert!(!stdout.contains("Press Enter"), "{stdout}");
    drop(child.stdin.take());
}

#[test]
fn nan_control_raises_the_warning_event() {
    let model = Model::from_xml_str(SLIDER).unwrap();
    let mut data = Data::new(&model).unwrap();
    data.ctrl_mut()[0] = 1.0;
    for _ in 0..10 {
        assert!(data.step(&model).unwrap().is_empty());
    }
    data.ctrl_mut()[0] = f64::NAN;
    let warnings = data.step(&model).unwrap();
    assert!(warnings.contains(Warning::BadCtrl), "{warnings:?}");
    assert!(warnings.state_was_reset());
    assert_eq!(warnings.iter().collect::<Vec<_>>(), vec![Warning::BadCtrl]);
    // A second NaN step is reported again (the counter grows each time).
    data.ctrl_mut()[0] = f64::NAN;
    assert!(data.step(&model).unwrap().contains(Warning::BadCtrl));
}

#[test]
fn nan_state_raises_a_bad_state_warning_every_time() {
    let model = Model::from_xml_str(SLIDER).unwrap();
    let mut data = Data::new(&model).unwrap();
    // MuJoCo resets the state on a NaN velocity, which also zeroes its warning
    // counters: each occurrence must still be reported.
    for round in 0..3 {
        for _ in 0..10 {
            data.step(&model).unwrap();
        }
        assert!(data.time() > 0.0);
        data.qvel_mut()[0] = f64::NAN;
        let warnings = data.step(&model).unwrap();
        assert!(
            warnings.contains(Warning::BadQvel) || warnings.contains(Warning::BadQacc),
            "round {round}: {warnings:?}"
        );
        assert!(warnings.state_was_reset());
        assert!(data.qvel().iter().all(|v| v.is_finite()));
    }
}

#[test]
fn data_for_another_model_is_rejected() {
    let slider = Model::from_xml_str(SLIDER).unwrap();
    let other = Model::from_xml_str(SMALL_STACK).unwrap();
    let mut data = Data::new(&slider).unwrap();
    assert!(matches!(data.step(&other), Err(MujocoError::Invalid(_))));
    assert!(matches!(data.forward(&other), Err(MujocoError::Invalid(_))));
}
