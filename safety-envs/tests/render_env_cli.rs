//! The `render` binary's `--env` mode: task pictures and random-policy GIFs.

use std::path::PathBuf;
use std::process::{Command, Stdio};

use safety_envs::prelude::*;

fn scratch(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("render_env_cli_{}_{name}", std::process::id()))
}

fn render(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_render"))
        .args(args)
        .env_remove("RUST_BACKTRACE")
        .stdin(Stdio::piped())
        .output()
        .expect("run render")
}

fn read_png(path: &PathBuf) -> (u32, u32, Vec<u8>) {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgb);
    (info.width, info.height, buf)
}

#[test]
fn darkroom_picture_shows_the_sampled_goal_and_obstacles() {
    let out = scratch("darkroom.png");
    let o = render(&[
        "--env",
        "darkroom",
        "--seed",
        "3",
        "--edge",
        "--out",
        out.to_str().unwrap(),
        "--width",
        "90",
        "--height",
        "90",
    ]);
    assert!(o.status.success(), "{o:?}");
    let (w, _, px) = read_png(&out);
    // 90 px / 9 cells = 10 px per cell; sample each cell's centre.
    let at = |c: Cell| {
        let i = 3 * ((c.row * 10 + 5) * w as usize + c.col * 10 + 5);
        [px[i], px[i + 1], px[i + 2]]
    };
    let task = sample_task(&spawn_config(EnvName::DarkRoom), Orientation::Edge, 3).unwrap();
    let [r, g, b] = at(task.goal);
    assert!(g > 150 && r < 100 && b < 100, "goal cell {r} {g} {b}");
    for &o in &task.obstacles {
        let [r, g, b] = at(o);
        assert!(b > 200 && r < 100, "obstacle cell {o:?}: {r} {g} {b}");
    }
    std::fs::remove_file(&out).ok();
}

#[test]
fn point_picture_has_goal_and_hazard_colours() {
    let out = scratch("point.png");
    let o = render(&[
        "--env",
        "point",
        "--seed",
        "1",
        "--out",
        out.to_str().unwrap(),
        "--width",
        "64",
        "--height",
        "64",
        "--fast",
    ]);
    assert!(o.status.success(), "{o:?}");
    let (_, _, px) = read_png(&out);
    let pixels: Vec<[u8; 3]> = px.chunks(3).map(|p| [p[0], p[1], p[2]]).collect();
    let green = pixels
        .iter()
        .filter(|p| p[1] > 150 && p[0] < 120 && p[2] < 120)
        .count();
    let blue = pixels
        .iter()
        .filter(|p| p[2] > 180 && p[0] < 140 && p[1] < 170)
        .count();
    let red = pixels.iter().filter(|p| p[0] > 150 && p[1] < 80).count();
    assert!(
        green > 10 && blue > 20 && red > 2,
        "green {green} blue {blue} red {red}"
    );
    std::fs::remove_file(&out).ok();
}

#[test]
fn rollouts_write_one_gif_frame_per_step_plus_the_start() {
    for env in ["darkroom", "car"] {
        let out = scratch(&format!("{env}.gif"));
        let o = render(&[
            "--env",
            env,
            "--rollout",
            "4",
            "--out",
            out.to_str().unwrap(),
            "--width",
            "48",
            "--height",
            "48",
            "--fast",
        ]);
        assert!(o.status.success(), "{o:?}");
        let mut options = gif::DecodeOptions::new();
        options.set_color_output(gif::ColorOutput::RGBA);
        let mut decoder = options
            .read_info(std::fs::File::open(&out).unwrap())
            .unwrap();
        let mut frames = 0;
        while let Some(f) = decoder.read_next_frame().unwrap() {
            assert_eq!((f.width, f.height), (48, 48));
            frames += 1;
        }
        assert_eq!(frames, 5, "{env}");
        std::fs::remove_file(&out).ok();
    }
}

#[test]
fn bad_env_flags_are_clear_errors() {
    let o = render(&["--env", "rover", "--out", "x.png"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("darkroom, point, car"),
        "{err}"
    );
    let o = render(&["--scene", "x.xml", "--edge", "--out", "x.png"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("cannot be used with"),
        "{err}"
    );
}

#[test]
fn an_existing_output_is_refused_unless_forced_and_never_a_device() {
    let out = scratch("twice.png");
    let o = out.to_str().unwrap();
    let args = ["--env", "darkroom", "--out", o];
    assert!(render(&args).status.success());
    let again = render(&args);
    let err = String::from_utf8_lossy(&again.stderr);
    assert!(
        !again.status.success() && err.contains("exists already: pass --force"),
        "{err}"
    );
    assert!(
        render(&["--env", "darkroom", "--out", o, "--force"])
            .status
            .success()
    );
    let dev = render(&["--env", "darkroom", "--out", "/dev/null", "--force"]);
    let err = String::from_utf8_lossy(&dev.stderr);
    assert!(
        !dev.status.success() && err.contains("it is a device"),
        "{err}"
    );
    std::fs::remove_file(&out).unwrap();
}
