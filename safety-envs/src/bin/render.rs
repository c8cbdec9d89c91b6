//! `render`: draws one frame off-screen (OSMesa, no display or GPU needed)
//! and writes it as a PNG.
//!
//! ```text
//! render --scene FILE.xml --out frame.png [--width W --height H --camera NAME]
//! render --env {darkroom,point,car} --seed N [--edge] --out task.png
//! render --env {darkroom,point,car} --seed N [--edge] --rollout STEPS --out rollout.gif
//! ```
//!
//! Reached through `cargo xtask render ...`. What to draw is a [`Source`]: an
//! MJCF file, or an environment with the task drawn from seed `N`
//! (centre-oriented, or edge-oriented with `--edge`), seen from above: robot
//! red, goal green, hazards blue. SafeDarkRoom is drawn as a grid by hand.
//! `--rollout STEPS` animates a uniformly random policy for that many agent
//! steps (episodes restart in the same task) into a GIF.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Parser;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safety_envs::darkroom::draw_darkroom;
use safety_envs::mujoco::{Camera, Data, Model, Quality, Renderer, RgbImage};
use safety_envs::output;
use safety_envs::prelude::*;

/// Render a MuJoCo scene off-screen to a PNG.
#[derive(Debug, Parser)]
#[command(name = "render", version, about)]
struct Args {
    #[command(flatten)]
    source: SourceArgs,
    /// PNG file to write (GIF with --rollout); an existing file is refused
    /// unless --force.
    #[arg(long)]
    out: PathBuf,
    /// Replace an existing --out (a regular file only).
    #[arg(long)]
    force: bool,
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
    /// With --env: the task seed (default 0).
    #[arg(long, conflicts_with = "scene", allow_hyphen_values = true, value_parser = parse_seed)]
    seed: Option<u64>,
    /// With --env: draw the task edge-oriented (evaluation) instead of
    /// centre-oriented (pretraining).
    #[arg(long, conflicts_with = "scene")]
    edge: bool,
    /// With --env: animate this many agent steps of a random policy into a GIF.
    #[arg(long, value_name = "STEPS", conflicts_with = "scene",
          value_parser = clap::value_parser!(u32).range(1..=10_000))]
    rollout: Option<u32>,
}

/// A seed: a whole number from 0 to 2^64 - 1 (clap would call `-1` an
/// unexpected argument).
fn parse_seed(s: &str) -> Result<u64, String> {
    s.trim().parse::<u64>().map_err(|_| {
        format!(
            "{s:?} is not a seed: seeds are whole numbers from 0 to {}",
            u64::MAX
        )
    })
}

/// Exactly one thing to render.
#[derive(Debug, clap::Args)]
#[group(required = true, multiple = false)]
struct SourceArgs {
    /// An MJCF scene file.
    #[arg(long, value_name = "FILE.xml")]
    scene: Option<PathBuf>,
    /// An environment: darkroom, point or car.
    #[arg(long, value_parser = parse_env_name)]
    env: Option<EnvName>,
}

fn parse_env_name(s: &str) -> Result<EnvName, String> {
    s.parse().map_err(|e: EnvError| e.to_string())
}

/// What to render, decided from the flags.
enum Source {
    Scene(PathBuf),
    Env(EnvName),
}

impl SourceArgs {
    fn source(self) -> Source {
        match (self.scene, self.env) {
            (Some(path), _) => Source::Scene(path),
            (None, Some(env)) => Source::Env(env),
            // clap's group makes exactly one flag present.
            (None, None) => unreachable!("clap requires one source flag"),
        }
    }
}

fn main() -> ExitCode {
    let args = Args::parse();
    let camera = match (&args.camera, &args.source.env) {
        (Some(name), _) => Camera::Named(name.clone()),
        // The arena's own top-down camera.
        (None, Some(_)) => Camera::Named("top".into()),
        (None, None) => Camera::ModelDefault,
    };
    let quality = if args.fast {
        Quality::Fast
    } else {
        Quality::Model
    };
    let size = (args.width as usize, args.height as usize);
    // Written beside --out and renamed into place; never over what is not ours.
    let existing = output::Existing::from_force(args.force);
    let write = |f: &dyn Fn(&std::path::Path) -> Result<()>| -> Result<()> {
        output::write_file(&args.out, existing, |tmp| f(tmp))
    };
    let result = match args.source.source() {
        Source::Scene(path) => {
            write(&|tmp| render_scene(&path, tmp, &args.out, size, &camera, quality))
        }
        Source::Env(name) => {
            let orientation = if args.edge {
                Orientation::Edge
            } else {
                Orientation::Centre
            };
            let view = EnvView {
                name,
                seed: args.seed.unwrap_or(0),
                orientation,
                size,
                camera,
                quality,
            };
            match args.rollout {
                None => write(&|tmp| view.task_png(tmp, &args.out)),
                Some(steps) => write(&|tmp| view.rollout_gif(steps as usize, tmp, &args.out)),
            }
        }
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
    dest: &std::path::Path,
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
        dest.display(),
        match camera {
            Camera::Named(name) => format!("'{name}'"),
            Camera::Free { .. } => String::from("free"),
            Camera::ModelDefault => String::from("default free"),
        },
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// One environment and task to draw.
struct EnvView {
    name: EnvName,
    seed: u64,
    orientation: Orientation,
    size: (usize, usize),
    camera: Camera,
    quality: Quality,
}

impl EnvView {
    fn task(&self) -> Result<Task> {
        Ok(sample_task(
            &spawn_config(self.name),
            self.orientation,
            self.seed,
        )?)
    }

    /// Writes the task (robot at its start) as a PNG.
    fn task_png(&self, out: &std::path::Path, dest: &std::path::Path) -> Result<()> {
        let started = Instant::now();
        let task = self.task()?;
        let image = match self.name {
            EnvName::DarkRoom => {
                let mut env = SafeDarkRoom::new(DarkRoomConfig::default())?;
                env.set_task(&task)?;
                env.reset(self.seed, &mut [0.0; 2])?;
                draw_darkroom(&env, &[], self.size)
            }
            EnvName::Point | EnvName::Car => {
                let mut env = self.nav_env(&task)?;
                let mut renderer =
                    Renderer::with_quality(env.model(), self.size.0, self.size.1, self.quality)?;
                let mut obs = vec![0.0; env.observation_space().flat_dim()];
                env.reset(self.seed, &mut obs)?;
                env.render(&mut renderer, &self.camera)?
            }
        };
        image.save_png(out)?;
        println!(
            "wrote {} ({} task, seed {}, {}-oriented: goal {:?}, {} obstacles) in {:.2} s",
            dest.display(),
            self.name,
            self.seed,
            self.orientation,
            (task.goal.row, task.goal.col),
            task.obstacles.len(),
            started.elapsed().as_secs_f64()
        );
        Ok(())
    }

    fn nav_env(&self, task: &Task) -> Result<SafeDarkMujoco> {
        let robot = match self.name {
            EnvName::Point => Robot::Point,
            EnvName::Car => Robot::Car,
            EnvName::DarkRoom => bail!("darkroom is not a MuJoCo environment"),
        };
        let mut env = SafeDarkMujoco::new(NavConfig::new(robot))?;
        env.set_task(task)?;
        Ok(env)
    }

    /// Animates `steps` agent steps of a uniformly random policy (seeded by
    /// `--seed`) into a GIF; episodes restart in the same task.
    fn rollout_gif(
        &self,
        steps: usize,
        out: &std::path::Path,
        dest: &std::path::Path,
    ) -> Result<()> {
        let started = Instant::now();
        let task = self.task()?;
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        let (w, h) = self.size;
        let (gw, gh) = (u16::try_from(w)?, u16::try_from(h)?);
        let file =
            std::fs::File::create(out).with_context(|| format!("creating {}", out.display()))?;
        let mut encoder = gif::Encoder::new(std::io::BufWriter::new(file), gw, gh, &[])?;
        encoder.set_repeat(gif::Repeat::Infinite)?;
        let mut frame = |image: &RgbImage, delay_cs: u16| -> Result<()> {
            let mut f = gif::Frame::from_rgb_speed(gw, gh, &image.pixels, 10);
            f.delay = delay_cs;
            encoder.write_frame(&f)?;
            Ok(())
        };
        let (mut episodes, mut total_reward, mut total_cost) = (1, 0.0, 0.0);
        match self.name {
            EnvName::DarkRoom => {
                let mut env = SafeDarkRoom::new(DarkRoomConfig::default())?;
                env.set_task(&task)?;
                let mut obs = [0.0; 2];
                env.reset(self.seed, &mut obs)?;
                let mut trail = vec![env.position()];
                frame(&draw_darkroom(&env, &trail, self.size), 20)?;
                for _ in 0..steps {
                    let out = env.step(Action::Discrete(rng.gen_range(0..5)), &mut obs)?;
                    (total_reward, total_cost) = (total_reward + out.reward, total_cost + out.cost);
                    trail.push(env.position());
                    frame(&draw_darkroom(&env, &trail, self.size), 20)?;
                    if out.done() {
                        env.reset(self.seed, &mut obs)?;
                        trail = vec![env.position()];
                        episodes += 1;
                    }
                }
            }
            EnvName::Point | EnvName::Car => {
                let mut env = self.nav_env(&task)?;
                let mut renderer = Renderer::with_quality(env.model(), w, h, self.quality)?;
                let mut obs = vec![0.0; env.observation_space().flat_dim()];
                env.reset(self.seed, &mut obs)?;
                frame(&env.render(&mut renderer, &self.camera)?, 4)?;
                for _ in 0..steps {
                    let a = [rng.gen_range(-1.0..=1.0), rng.gen_range(-1.0..=1.0)];
                    let out = env.step(Action::Continuous(&a), &mut obs)?;
                    (total_reward, total_cost) = (total_reward + out.reward, total_cost + out.cost);
                    frame(&env.render(&mut renderer, &self.camera)?, 4)?;
                    if out.done() {
                        env.reset(self.seed, &mut obs)?;
                        episodes += 1;
                    }
                }
            }
        }
        println!(
            "wrote {} ({} random-policy steps of {} task seed {}, {}-oriented; {episodes} episode(s), \
             reward {total_reward}, cost {total_cost}) in {:.2} s",
            dest.display(),
            steps,
            self.name,
            self.seed,
            self.orientation,
            started.elapsed().as_secs_f64()
        );
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_negative_seed_is_named_not_read_as_a_flag() {
        let e = Args::try_parse_from([
            "render", "--env", "darkroom", "--seed", "-1", "--out", "x.png",
        ])
        .unwrap_err()
        .to_string();
        assert!(e.contains("\"-1\" is not a seed"), "{e}");
    }
}
