//! The `render` binary end to end: a scene file in, a PNG of the requested
//! size out; clear errors for bad input.

use std::path::PathBuf;
use std::process::{Command, Stdio};

const SCENE: &str = r#"<mujoco>
  <visual><quality offsamples="0"/></visual>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1" directional="true"/>
    <geom type="plane" size="2 2 0.1" rgba="0.5 0.5 0.5 1"/>
    <geom type="box" pos="0 0 0.1" size="0.3 0.3 0.1" rgba="1 0 0 1"/>
    <camera name="top" pos="0 0 2" xyaxes="1 0 0 0 1 0"/>
  </worldbody>
</mujoco>"#;

fn scratch(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("render_cli_{}_{name}", std::process::id()))
}

fn render(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_render"))
        .args(args)
        .env_remove("RUST_BACKTRACE")
        .stdin(Stdio::piped())
        .output()
        .expect("run render")
}

#[test]
fn renders_a_scene_to_png_of_the_requested_size() {
    let scene = scratch("scene.xml");
    let out = scratch("frame.png");
    std::fs::write(&scene, SCENE).unwrap();
    let output = render(&[
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--width",
        "80",
        "--height",
        "60",
        "--camera",
        "top",
    ]);
    assert!(output.status.success(), "{output:?}");
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&out).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    assert_eq!((reader.info().width, reader.info().height), (80, 60));
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let frame = reader.next_frame(&mut buf).unwrap();
    let centre = 3 * (30 * 80 + 40);
    let [r, g, b] = [buf[centre], buf[centre + 1], buf[centre + 2]];
    assert_eq!(frame.color_type, png::ColorType::Rgb);
    assert!(r > 100 && g < r / 2 && b < r / 2, "centre {r} {g} {b}");
    std::fs::remove_file(&scene).ok();
    std::fs::remove_file(&out).ok();
}

#[test]
fn missing_scene_and_bad_flags_are_clear_errors() {
    let output = render(&["--scene", "/nonexistent/s.xml", "--out", "x.png"]);
    assert_eq!(output.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("/nonexistent/s.xml"), "{stderr}");

    let output = render(&["--out", "x.png"]);
    assert_eq!(output.status.code(), Some(2), "clap's usage error");
    assert!(String::from_utf8_lossy(&output.stderr).contains("--scene"));

    let output = render(&["--scene", "s.xml", "--out", "x.png", "--width", "0"]);
    assert_eq!(output.status.code(), Some(2));
}
