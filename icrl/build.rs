//! Gives icrl's binaries, tests and benchmarks an rpath to libtorch, so they run
//! without anyone setting LD_LIBRARY_PATH. `LIBTORCH` is set by
//! `.cargo/config.toml` (the folder `cargo xtask setup` fills) or by the user.

fn main() {
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    if let Ok(libtorch) = std::env::var("LIBTORCH") {
        println!("cargo:rustc-link-arg=-Wl,-rpath,{libtorch}/lib");
    }
}
