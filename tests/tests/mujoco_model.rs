//! Loading models, stepping, and a thrust actuator on tiny scenes.

use integration_tests::{BOGUS_ATTRIBUTE, SLIDER, THRUSTER, THRUSTER_YAW_DEG};
use safety_envs::MujocoError;
use safety_envs::mujoco::{Data, Model, ObjType};

#[test]
fn load_and_step() {
    let model = Model::from_xml_str(SLIDER).expect("fixture compiles");
    assert_eq!((model.nq(), model.nv(), model.nu()), (1, 1, 1));
    let mut data = Data::new(&model).unwrap();
    data.ctrl_mut()[0] = 2.0;
    for _ in 0..50 {
        let warnings = data.step(&model).unwrap();
        assert!(warnings.is_empty(), "{warnings:?}");
    }
    assert!((data.time() - 50.0 * model.timestep()).abs() < 1e-12);
    // Constant force 2 N on 1 kg from rest: x = a t^2 / 2 (semi-implicit Euler
    // lands within a step of that).
    let t = data.time();
    let x = data.qpos()[0];
    assert!(
        (x - t * t).abs() < 2.0 * t * model.timestep() * 2.0,
        "x = {x}"
    );
    // The position sensor reads the joint after the step's forward pass.
    let range = model.sensor_range("x_pos").unwrap();
    assert_eq!(range.len(), 1);
    assert!(data.sensordata()[range.start] > 0.0);
}

#[test]
fn from_file_equals_from_string() {
    let path = std::env::temp_dir().join(format!("slider_{}.xml", std::process::id()));
    std::fs::write(&path, SLIDER).unwrap();
    let from_file = Model::from_xml_file(&path).expect("file loads");
    std::fs::remove_file(&path).ok();
    let from_str = Model::from_xml_str(SLIDER).unwrap();
    assert_eq!(from_file.nq(), from_str.nq());
    assert_eq!(from_file.timestep(), from_str.timestep());
    assert_eq!(
        from_file.id(ObjType::Body, "ball").unwrap(),
        from_str.id(ObjType::Body, "ball").unwrap()
    );
}

#[test]
fn thrust_moves_the_body_along_its_heading() {
    let model = Model::from_xml_str(THRUSTER).expect("fixture compiles");
    let mut data = Data::new(&model).unwrap();
    let body = model.id(ObjType::Body, "robot").unwrap();
    data.forward(&model).unwrap();
    let start: Vec<f64> = data.xpos()[3 * body..3 * body + 3].to_vec();
    data.ctrl_mut()[0] = 1.0;
    for _ in 0..250 {
        assert!(data.step(&model).unwrap().is_empty());
    }
    let end = &data.xpos()[3 * body..3 * body + 3];
    let d = [end[0] - start[0], end[1] - start[1], end[2] - start[2]];
    let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    assert!(dist > 0.1, "moved only {dist}");
    let yaw = THRUSTER_YAW_DEG.to_radians();
    let heading = [yaw.cos(), yaw.sin(), 0.0];
    let cos = (d[0] * heading[0] + d[1] * heading[1] + d[2] * heading[2]) / dist;
    assert!(
        cos > 0.999,
        "moved along {d:?}, not the heading {heading:?}"
    );

    // Reverse thrust moves it back the other way.
    data.reset(&model).unwrap();
    data.ctrl_mut()[0] = -1.0;
    for _ in 0..250 {
        data.step(&model).unwrap();
    }
    let back = &data.xpos()[3 * body..3 * body + 3];
    assert!((back[0] - start[0]) * heading[0] + (back[1] - start[1]) * heading[1] < -0.1);
}

#[test]
fn broken_xml_yields_mujocos_message() {
    let err = Model::from_xml_str(BOGUS_ATTRIBUTE).unwrap_err();
    match &err {
        MujocoError::Load { message, .. } => {
            assert!(message.contains("bogus_attr"), "{message}");
            assert!(message.contains("unrecognized attribute"), "{message}");
        }
        other => panic!("expected a load error, got {other:?}"),
    }
}

#[test]
fn missing_file_names_the_path() {
    let path = "/nonexistent/dir/scene.xml";
    let err = Model::from_xml_file(path).unwrap_err();
    assert!(matches!(err, MujocoError::Load { .. }));
    let text = err.to_string();
    assert!(
        text.contains(path) && text.contains("no such file"),
        "{text}"
    );
}

#[test]
fn unknown_names_and_ids_are_errors() {
    let mut model = Model::from_xml_str(SLIDER).unwrap();
    let err = model.id(ObjType::Site, "nope").unwrap_err();
    assert!(err.to_string().contains("nope"));
    assert!(model.body_pos_mut(99).is_err());
    assert!(model.sensor_range("nope").is_err());
}

#[test]
fn model_edits_apply_without_recompiling() {
    // Moving a body in the compiled model moves its joint frame: the slider's
    // world position is body_pos + qpos along x. (A free body's position lives
    // in qpos instead; body_pos only sets its initial qpos0 at compile time.)
    let mut model = Model::from_xml_str(SLIDER).unwrap();
    let body = model.id(ObjType::Body, "ball").unwrap();
    model.body_pos_mut(body).unwrap()[1] = 3.0;
    let mut data = Data::new(&model).unwrap();
    data.qpos_mut()[0] = 0.5;
    data.forward(&model).unwrap();
    assert_eq!(&data.xpos()[3 * body..3 * body + 3], &[0.5, 3.0, 0.0]);
}

#[test]
fn model_and_data_move_across_threads() {
    let model = std::sync::Arc::new(Model::from_xml_str(SLIDER).unwrap());
    let handles: Vec<_> = (0..2)
        .map(|i| {
            let model = model.clone();
            std::thread::spawn(move || {
                let mut data = Data::new(&model).unwrap();
                data.ctrl_mut()[0] = i as f64 + 1.0;
                for _ in 0..20 {
                    data.step(&model).unwrap();
                }
                data
            })
        })
        .collect();
    let datas: Vec<Data> = handles.into_iter().map(|h| h.join().unwrap()).collect();
    assert!(datas[1].qpos()[0] > datas[0].qpos()[0]);
}
