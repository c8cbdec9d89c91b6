//! Builds `benches/raw_step.c`, the plain-C baseline of the environment
//! benchmark, and links it into the bench targets only.

use std::env;
use std::path::PathBuf;

fn main() {
    println!("cargo:rerun-if-changed=benches/raw_step.c");
    // mujoco-sys (links = "mujoco") tells us where mujoco/mujoco.h lives.
    let include = env::var("DEP_MUJOCO_INCLUDE").unwrap_or_else(|_| "/usr/include".into());
    cc::Build::new()
        .file("benches/raw_step.c")
        .include(&include)
        .opt_level(2)
        .cargo_metadata(false)
        .compile("raw_step");
    let out = PathBuf::from(env::var("OUT_DIR").expect("cargo sets OUT_DIR"));
    println!(
        "cargo:rustc-link-arg-benches={}",
        out.join("libraw_step.a").display()
    );
    println!("cargo:rustc-link-arg-benches=-lmujoco");
}
