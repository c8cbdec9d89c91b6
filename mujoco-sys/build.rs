//! Generates raw bindings to MuJoCo 2.2 and links `libmujoco`.
//!
//! By default the headers and library come from Debian's `libmujoco-dev`
//! (`/usr/include/mujoco`, `/usr/lib/x86_64-linux-gnu`). Set `MUJOCO_DIR` to the
//! root of another MuJoCo 2.2 install (with `include/mujoco/mujoco.h` and
//! `lib/libmujoco.so`) to use that one instead.

use std::env;
use std::path::PathBuf;

/// Reads an override variable and asks cargo to rerun when it changes.
fn env_override(name: &str) -> Option<String> {
    println!("cargo:rerun-if-env-changed={name}");
    env::var(name).ok().filter(|v| !v.is_empty())
}

fn main() {
    let (include_dir, lib_dir) = match env_override("MUJOCO_DIR") {
        Some(root) => {
            let root = PathBuf::from(root);
            (root.join("include"), Some(root.join("lib")))
        }
        None => (PathBuf::from("/usr/include"), None),
    };
    let header = include_dir.join("mujoco").join("mujoco.h");
    if !header.exists() {
        panic!(
            "MuJoCo 2.2 headers not found at {}: install them with \
             `apt-get install libmujoco-dev` (or run `cargo xtask setup`), \
             or set MUJOCO_DIR to a MuJoCo 2.2 install",
            header.display()
        );
    }

    if let Some(lib_dir) = &lib_dir {
        println!("cargo:rustc-link-search=native={}", lib_dir.display());
    }
    println!("cargo:rustc-link-lib=dylib=mujoco");
    println!("cargo:include={}", include_dir.display());
    println!("cargo:rerun-if-changed={}", header.display());

    let bindings = bindgen::Builder::default()
        .header_contents("wrapper.h", "#include <mujoco/mujoco.h>\n")
        .clang_arg(format!("-I{}", include_dir.display()))
        .allowlist_function("mj_.*|mjv_.*|mjr_.*|mju_.*|mjd_.*")
        .allowlist_type("mj.*")
        .allowlist_var("mj.*|mju_user_.*|mjcb_.*")
        // MuJoCo's error hook may unwind (the safe wrapper turns engine errors
        // into Rust panics caught at the call site), so every entry point must
        // be declared as possibly unwinding.
        .override_abi(bindgen::Abi::CUnwind, "mj.*")
        .derive_default(true)
        .layout_tests(false)
        .generate()
        .unwrap_or_else(|err| {
            panic!(
                "bindgen could not parse MuJoCo's headers ({err}); if clang reports \
                 'stddef.h' file not found, run `apt-get install libclang-common-14-dev`"
            )
        });
    let out = PathBuf::from(env::var("OUT_DIR").expect("cargo sets OUT_DIR"));
    bindings
        .write_to_file(out.join("bindings.rs"))
        .expect("writing bindings.rs into OUT_DIR");
}
