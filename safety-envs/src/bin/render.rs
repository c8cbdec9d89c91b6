//! `render`: draws one frame off-screen (OSMesa, no display or GPU needed)
//! and writes it as a PNG.
//!
//! ```text
//! render --scene FILE.xml --out frame.png [--width W --height H --camera NAME]
//! ```
//!
//! Reached through `cargo xtask render ...`. What to draw is a [`Source`]:
//! today an MJCF file; environments (`--env`) plug in as another variant.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Parser;
use safety_envs::mujoco::{Camera, Data, Model, Quality, Renderer};

/// Render a MuJoCo scene off-screen to a PNG.
#[derive(Debug, Parser)]
#[command(name = "render", version, about)]
struct Args {
    #[command(flatten)]
    source: SourceArgs,
    /// PNG file to write.
    #[arg(long)]
    out: PathBuf,
    /// Image width in pixels.
    #[arg(long, default_value_t = 480, value_parser = clap::value_parser!(u32).range(1..=8192))]
    width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 480, value_parser = clap::value_parser!(u32).range(1..=8192))]
    height: u32,
    /// A camera named in the model; without it, MuJoCo's default free camera.
    #[arg(long)]
    camera: Option<String>,
    /// Skip shadows, reflections and multisampling (several times faster).
    #[arg(long)]
    fast: bool,
}

/// Exactly one thing to render.
#[derive(Debug, clap::Args)]
#[group(required = true, multiple = false)]
struct SourceArgs {
    /// An MJCF scene file.
    #[arg(long, value_name = "FILE.xml")]
    scene: Option<PathBuf>,
    // Environments add their flags here (`--env {darkroom,point,car}`), and
    // their options (`--seed N`, `--rollout N`) as fields of `Args`, then a
    // `Source::Env` variant below.
}

/// What to render, decided from the flags.
enum Source {
    Scene(PathBuf),
}

impl SourceArgs {
    fn source(self) -> Source {
        match self.scene {
            Some(path) => Source::Scene(path),
            // clap's group makes exactly one flag present.
            None => unreachable!("clap requires one source flag"),
        }
    }
}

fn main() -> ExitCode {
    let args = Args::parse();
    let camera = match &args.camera {
        Some(name) => Camera::Named(name.clone()),
        None => Camera::ModelDefault,
    };
    let quality = if args.fast {
        Quality::Fast
    } else {
        Quality::Model
    };
    let size = (args.width as usize, args.height as usize);
    let result = match args.source.source() {
        Source::Scene(path) => render_scene(&path, &args.out, size, &camera, quality),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

/// Loads an MJCF file, computes its initial state and writes one frame.
fn render_scene(
    scene: &std::path::Path,
    out: &std::path::Path,
    (width, height): (usize, usize),
    camera: &Camera,
    quality: Quality,
) -> Result<()> {
    let started = Instant::now();
    let model = Model::from_xml_file(scene)?;
    let mut data = Data::new(&model)?;
    data.forward(&model)
        .with_context(|| format!("computing the initial state of {}", scene.display()))?;
    let mut renderer = Renderer::with_quality(&model, width, height, quality)?;
    let image = renderer.render(&model, &mut data, camera)?;
    image.save_png(out)?;
    println!(
        "wrote {} ({width}x{height}, {} camera) in {:.2} s",
        out.display(),
        match camera {
            Camera::Named(name) => format!("'{name}'"),
            Camera::Free { .. } => String::from("free"),
            Camera::ModelDefault => String::from("default free"),
        },
        started.elapsed().as_secs_f64()
    );
    Ok(())
}
