//! `cargo xtask setup`: installs what the workspace needs, idempotently.
//!
//! Three steps, each checking first so that a set-up machine passes through
//! in well under a second:
//! 1. Debian packages: MuJoCo 2.2 (`libmujoco-dev`), OSMesa, libclang for
//!    bindgen, HDF5, and a C++ compiler for torch-sys.
//! 2. libtorch 2.11.0 in `<repo>/.libtorch/{include,lib}`, taken from the PyPI
//!    wheels (see SPEC section 7): `torch/include` and the four CPU libraries of
//!    the torch wheel, plus `libcudart.so.13` and `libcupti.so.13`, which
//!    `libtorch_cpu.so` names as needed even without a GPU. `.cargo/config.toml`
//!    points `LIBTORCH` at that folder. A `LIBTORCH` set by the user wins.
//! 3. Python's `h5py`, with which the tests read back our HDF5 files.
//! 4. A virtual environment in `target/python-venv` with what the Python
//!    package's tests need (maturin, Gymnasium, numpy, pytest), from PyPI:
//!    Debian's Python is externally managed, so they never go into it.

use std::env;
use std::ffi::OsString;
use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use anyhow::{Context, Result, bail, ensure};

/// The libtorch version tch 0.24 expects.
const LIBTORCH_VERSION: &str = "2.11.0";

/// The CUDA runtime packages torch 2.11.0's metadata names; only two of their
/// libraries are taken (13 MB).
const CUDA_TOOLKIT: &str = "cuda-toolkit[cudart,cupti]==13.0.2";

/// The libraries taken from the torch wheel's `torch/lib/`: enough to link and
/// run on CPU (the linker drops `libtorch.so`, so `libtorch_cuda.so` is not needed).
const TORCH_LIBS: [&str; 4] = [
    "libtorch_cpu.so",
    "libc10.so",
    "libtorch.so",
    "libgomp.so.1",
];

/// The CUDA libraries `libtorch_cpu.so` needs at load time, with the prefix of
/// the wheel each comes in (under `nvidia/cu13/lib/`).
const CUDA_LIBS: [(&str, &str); 2] = [
    ("nvidia_cuda_runtime-", "libcudart.so.13"),
    ("nvidia_cuda_cupti-", "libcupti.so.13"),
];

/// Debian packages every build needs: MuJoCo 2.2.2, OSMesa, libclang (with its
/// `stddef.h`, without which bindgen fails), HDF5, g++ for torch-sys, and the
/// DejaVu font the figures are drawn with (plotters' ab_glyph backend).
const SYSTEM_PACKAGES: [&str; 7] = [
    "libmujoco-dev",
    "libosmesa6-dev",
    "libclang1-14",
    "libclang-common-14-dev",
    "libhdf5-dev",
    "g++",
    "fonts-dejavu-core",
];

/// The folder the libtorch marker names the version in; written last.
const VERSION_FILE: &str = "VERSION";

/// The repository root (xtask lives one level below it).
pub fn repo_root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("xtask's manifest folder has a parent")
}

/// Installs everything that is missing; prints one line per step.
pub fn setup() -> Result<()> {
    let repo = repo_root();
    let libtorch = Libtorch::locate(repo, env::var_os("LIBTORCH"));
    let fetch_libtorch = matches!(libtorch, Libtorch::Repo { present: false, .. });

    let mut packages = SYSTEM_PACKAGES.to_vec();
    if fetch_libtorch {
        packages.push("unzip");
        if !python_has_pip() {
            packages.push("python3-pip");
        }
    }
    apt_ensure(&packages)?;

    libtorch.ensure(repo)?;
    ensure_h5py()?;
    ensure_python_venv(repo)
}

/// Where libtorch comes from.
enum Libtorch {
    /// A folder the user named in `LIBTORCH`: used as is.
    User(PathBuf),
    /// The repository's `.libtorch`, fetched by [`fetch_libtorch`] when absent.
    Repo { dir: PathBuf, present: bool },
}

impl Libtorch {
    /// Decides the source from the value of `LIBTORCH`: the user's folder when
    /// it names anything other than the repository's own (which
    /// `.cargo/config.toml` sets), else `.libtorch`.
    fn locate(repo: &Path, libtorch_var: Option<OsString>) -> Self {
        let dir = repo.join(".libtorch");
        match libtorch_var.filter(|v| !v.is_empty()) {
            Some(user) if !same_path(Path::new(&user), &dir) => Self::User(PathBuf::from(user)),
            _ => {
                let present = installed_version(&dir).as_deref() == Some(LIBTORCH_VERSION)
                    && dir.join("lib").join(TORCH_LIBS[0]).is_file();
                Self::Repo { dir, present }
            }
        }
    }

    /// Fetches libtorch when needed and says where it is.
    fn ensure(&self, repo: &Path) -> Result<()> {
        match self {
            Self::User(dir) => {
                println!(
                    "setup: libtorch from LIBTORCH={} (yours; not fetching)",
                    dir.display()
                );
                if !dir.join("lib").is_dir() || !dir.join("include").is_dir() {
                    println!(
                        "setup: warning: {} has no lib/ or include/; torch-sys will fail",
                        dir.display()
                    );
                }
                Ok(())
            }
            Self::Repo { present: true, .. } => {
                println!("setup: libtorch {LIBTORCH_VERSION} present (.libtorch)");
                Ok(())
            }
            Self::Repo {
                dir,
                present: false,
            } => {
                if let Some(found) = installed_version(dir) {
                    println!(
                        "setup: .libtorch holds libtorch {found}, not {LIBTORCH_VERSION}: replacing it"
                    );
                }
                fetch_libtorch(repo, dir)
            }
        }
    }
}

/// The version in a libtorch folder's marker, if the marker is there.
fn installed_version(dir: &Path) -> Option<String> {
    fs::read_to_string(dir.join(VERSION_FILE))
        .ok()
        .map(|s| s.trim().to_owned())
}

/// Whether two paths name the same folder (compared canonically when both exist).
fn same_path(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    }
}

/// Downloads the torch and CUDA runtime wheels with pip (its cache makes a
/// second download fast), unpacks the CPU parts into `.libtorch.partial`,
/// writes the version marker last and renames the folder into place, so an
/// interrupted set-up never leaves a half `.libtorch`.
fn fetch_libtorch(repo: &Path, dir: &Path) -> Result<()> {
    let start = Instant::now();
    println!(
        "setup: fetching libtorch {LIBTORCH_VERSION} (CPU parts of the PyPI torch wheel, a 530 MB download)"
    );
    let downloads = repo.join(".libtorch.download");
    let partial = repo.join(".libtorch.partial");
    fs::create_dir_all(&downloads).with_context(|| format!("creating {}", downloads.display()))?;
    run(
        Command::new("python3")
            .args(["-m", "pip", "download", "--quiet", "--no-deps"])
            .arg(format!("torch=={LIBTORCH_VERSION}"))
            .arg("-d")
            .arg(&downloads),
        "pip download torch",
    )?;
    // With dependencies: cuda-toolkit is a metapackage; the libraries come in
    // the nvidia-cuda-runtime and nvidia-cuda-cupti wheels it depends on.
    run(
        Command::new("python3")
            .args(["-m", "pip", "download", "--quiet", CUDA_TOOLKIT, "-d"])
            .arg(&downloads),
        "pip download cuda-toolkit",
    )?;

    if partial.exists() {
        fs::remove_dir_all(&partial).with_context(|| format!("removing {}", partial.display()))?;
    }
    let lib = partial.join("lib");
    fs::create_dir_all(&lib).with_context(|| format!("creating {}", lib.display()))?;

    let torch_wheel = find_wheel(&downloads, &format!("torch-{LIBTORCH_VERSION}-"))?;
    unzip(&torch_wheel, &["torch/include/*"], &partial, false)?;
    fs::rename(partial.join("torch/include"), partial.join("include"))
        .context("moving torch/include into place")?;
    fs::remove_dir_all(partial.join("torch")).context("removing the emptied torch/ folder")?;
    let torch_libs: Vec<String> = TORCH_LIBS
        .iter()
        .map(|l| format!("torch/lib/{l}"))
        .collect();
    let torch_libs: Vec<&str> = torch_libs.iter().map(String::as_str).collect();
    unzip(&torch_wheel, &torch_libs, &lib, true)?;
    for (prefix, name) in CUDA_LIBS {
        let wheel = find_wheel(&downloads, prefix)?;
        unzip(&wheel, &[&format!("*/lib/{name}")], &lib, true)?;
    }
    for name in TORCH_LIBS
        .iter()
        .chain(CUDA_LIBS.iter().map(|(_, name)| name))
    {
        ensure!(
            lib.join(name).is_file(),
            "{name} is missing from the unpacked wheels"
        );
    }

    // The marker goes in last: a folder with it is complete.
    fs::write(partial.join(VERSION_FILE), format!("{LIBTORCH_VERSION}\n"))
        .context("writing the libtorch version marker")?;
    if dir.exists() {
        let old = repo.join(".libtorch.old");
        if old.exists() {
            fs::remove_dir_all(&old).with_context(|| format!("removing {}", old.display()))?;
        }
        fs::rename(dir, &old).with_context(|| format!("moving {} aside", dir.display()))?;
        fs::remove_dir_all(&old).with_context(|| format!("removing {}", old.display()))?;
    }
    fs::rename(&partial, dir).with_context(|| format!("moving libtorch into {}", dir.display()))?;
    fs::remove_dir_all(&downloads).with_context(|| format!("removing {}", downloads.display()))?;
    println!(
        "setup: libtorch {LIBTORCH_VERSION} installed in .libtorch ({:.0} s)",
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// The one wheel in `dir` whose file name starts with `prefix`.
fn find_wheel(dir: &Path, prefix: &str) -> Result<PathBuf> {
    let mut found = Vec::new();
    for entry in fs::read_dir(dir).with_context(|| format!("listing {}", dir.display()))? {
        let name = entry?.file_name();
        let name = name.to_string_lossy();
        if name.starts_with(prefix) && name.ends_with(".whl") {
            found.push(dir.join(&*name));
        }
    }
    found.sort();
    found
        .pop()
        .with_context(|| format!("pip downloaded no {prefix}*.whl into {}", dir.display()))
}

/// Extracts the members matching `patterns` (unzip wildcards) from `wheel`
/// into `dest`; `flat` drops the members' folders.
fn unzip(wheel: &Path, patterns: &[&str], dest: &Path, flat: bool) -> Result<()> {
    let mut cmd = Command::new("unzip");
    cmd.arg("-q").arg("-o");
    if flat {
        cmd.arg("-j");
    }
    cmd.arg(wheel).args(patterns).arg("-d").arg(dest);
    run(&mut cmd, &format!("unzip {}", wheel.display()))
}

/// Makes sure Python can import h5py: through apt (`python3-h5py`) when the
/// system Python is externally managed (Debian 12's is), else through pip.
fn ensure_h5py() -> Result<()> {
    if python_ok("import importlib.util, sys; sys.exit(importlib.util.find_spec('h5py') is None)") {
        println!("setup: Python h5py present");
        return Ok(());
    }
    let externally_managed = "import os, sys, sysconfig; sys.exit(not (sys.prefix == sys.base_prefix \
        and os.path.isfile(os.path.join(sysconfig.get_path('stdlib'), 'EXTERNALLY-MANAGED'))))";
    if !python_ok("pass") || python_ok(externally_managed) {
        apt_ensure(&["python3-h5py"])?;
    } else {
        if !python_has_pip() {
            apt_ensure(&["python3-pip"])?;
        }
        println!("setup: installing Python h5py (pip)");
        run(
            Command::new("python3").args(["-m", "pip", "install", "--quiet", "h5py"]),
            "pip install h5py",
        )?;
    }
    ensure!(
        python_ok("import h5py"),
        "h5py was installed but `python3 -c 'import h5py'` still fails"
    );
    println!("setup: Python h5py installed");
    Ok(())
}

/// What the Python package's tests need, installed into [`python_venv`]:
/// the build backend, the package's own dependencies, and pytest.
const PYTHON_TEST_PACKAGES: [&str; 4] = [
    "maturin>=1.9,<2",
    "gymnasium>=1.0,<2",
    "numpy>=1.24",
    "pytest>=7",
];

/// The virtual environment the Python package is built into and tested
/// from (ignored by git, under `target/`).
pub fn python_venv(repo: &Path) -> PathBuf {
    repo.join("target").join("python-venv")
}

/// Makes sure [`python_venv`] exists and imports everything in
/// [`PYTHON_TEST_PACKAGES`]: creates it (Debian's `python3-venv` first, when
/// `python3 -m venv` would fail without it) and `pip install`s into it.
fn ensure_python_venv(repo: &Path) -> Result<()> {
    let venv = python_venv(repo);
    let python = venv.join("bin").join("python");
    let has_all = "import importlib.util, sys; \
        sys.exit(any(importlib.util.find_spec(m) is None for m in ('maturin', 'gymnasium', 'numpy', 'pytest')))";
    if python_ok_with(&python, has_all) {
        println!("setup: Python test environment present (target/python-venv)");
        return Ok(());
    }
    let start = Instant::now();
    if !python.is_file() {
        // Debian ships venv's pip bootstrap (ensurepip) in python3-venv.
        if !python_ok("import ensurepip, venv") {
            apt_ensure(&["python3-venv"])?;
        }
        println!("setup: creating the Python test environment (target/python-venv)");
        run(
            Command::new("python3").args(["-m", "venv"]).arg(&venv),
            "python3 -m venv target/python-venv",
        )?;
    }
    println!(
        "setup: installing {} into target/python-venv (pip)",
        PYTHON_TEST_PACKAGES.join(", ")
    );
    run(
        Command::new(&python)
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
            ])
            .args(PYTHON_TEST_PACKAGES),
        "pip install into target/python-venv",
    )?;
    ensure!(
        python_ok_with(&python, has_all),
        "the packages were installed but {} still cannot import them",
        python.display()
    );
    println!(
        "setup: Python test environment installed ({:.0} s)",
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Whether `python3 -c code` runs and exits 0 (false when there is no python3).
fn python_ok(code: &str) -> bool {
    python_ok_with(Path::new("python3"), code)
}

/// Whether `python -c code` runs and exits 0 (false when `python` is missing).
fn python_ok_with(python: &Path, code: &str) -> bool {
    Command::new(python)
        .args(["-c", code])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// Whether `python3 -m pip` is available.
fn python_has_pip() -> bool {
    python_ok("import importlib.util, sys; sys.exit(importlib.util.find_spec('pip') is None)")
}

/// Set once `apt-get update` has run in this process.
static APT_UPDATED: AtomicBool = AtomicBool::new(false);

/// Installs the Debian packages of `packages` that are not installed yet. A
/// non-root user gets the exact command to run instead.
fn apt_ensure(packages: &[&str]) -> Result<()> {
    let Some(missing) = missing_packages(packages)? else {
        println!(
            "setup: no dpkg here (not Debian): assuming {} are installed",
            packages.join(" ")
        );
        return Ok(());
    };
    if missing.is_empty() {
        println!("setup: Debian packages present ({})", packages.join(" "));
        return Ok(());
    }
    let list = missing.join(" ");
    if !is_root() {
        bail!(
            "missing Debian packages: {list}\n\
             Install them (as root) with:\n\n    \
             sudo apt-get update && sudo apt-get install -y --no-install-recommends {list}\n\n\
             then run this command again."
        );
    }
    println!("setup: installing {list} (apt-get)");
    let start = Instant::now();
    if !APT_UPDATED.swap(true, Ordering::Relaxed) {
        run(apt_get().args(["update", "-qq"]), "apt-get update")?;
    }
    run(
        apt_get()
            .args(["install", "-y", "-qq", "--no-install-recommends"])
            .args(&missing),
        "apt-get install",
    )?;
    let still = missing_packages(&missing)?.unwrap_or_default();
    ensure!(
        still.is_empty(),
        "apt-get finished but {} are still not installed",
        still.join(" ")
    );
    println!(
        "setup: installed {list} ({:.0} s)",
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// `apt-get`, non-interactive, with no stdin.
fn apt_get() -> Command {
    let mut cmd = Command::new("apt-get");
    cmd.env("DEBIAN_FRONTEND", "noninteractive")
        .stdin(Stdio::null());
    cmd
}

/// The packages of `packages` that dpkg does not list as installed, or `None`
/// when there is no dpkg-query (not a Debian system).
fn missing_packages<S: AsRef<str>>(packages: &[S]) -> Result<Option<Vec<String>>> {
    let output = match Command::new("dpkg-query")
        .arg("-W")
        .arg("-f=${Package} ${Status}\n")
        .args(packages.iter().map(AsRef::as_ref))
        .stdin(Stdio::null())
        .output()
    {
        Ok(output) => output,
        Err(err) if err.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(err) => return Err(err).context("running dpkg-query"),
    };
    // dpkg-query exits 1 when some package is unknown: that is a missing one,
    // so read stdout whatever the exit code.
    let stdout = String::from_utf8_lossy(&output.stdout);
    let installed: Vec<&str> = stdout
        .lines()
        .filter(|line| line.ends_with(" install ok installed"))
        .filter_map(|line| line.split_whitespace().next())
        .collect();
    Ok(Some(
        packages
            .iter()
            .map(AsRef::as_ref)
            .filter(|p| !installed.contains(p))
            .map(str::to_owned)
            .collect(),
    ))
}

/// Whether this process runs as root (`id -u` prints 0).
fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|out| String::from_utf8_lossy(&out.stdout).trim() == "0")
}

/// Runs a command with no stdin and fails, naming `what`, unless it succeeds.
fn run(cmd: &mut Command, what: &str) -> Result<()> {
    let status = cmd
        .stdin(Stdio::null())
        .status()
        .with_context(|| format!("{what}: could not start {:?}", cmd.get_program()))?;
    ensure!(status.success(), "{what} failed ({status})");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fresh scratch folder under the target directory.
    fn scratch(name: &str) -> PathBuf {
        let dir = repo_root()
            .join("target")
            .join("xtask-tests")
            .join(format!("{name}-{}", std::process::id()));
        if dir.exists() {
            fs::remove_dir_all(&dir).unwrap();
        }
        fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn libtorch_is_present_only_with_marker_and_library() {
        let repo = scratch("locate");
        let dir = repo.join(".libtorch");
        let present = |var: Option<&Path>| match Libtorch::locate(
            &repo,
            var.map(|p| p.as_os_str().to_owned()),
        ) {
            Libtorch::Repo { present, .. } => present,
            Libtorch::User(_) => panic!("the repository's own folder was taken for the user's"),
        };
        assert!(!present(None), "an empty repository has no libtorch");

        fs::create_dir_all(dir.join("lib")).unwrap();
        fs::write(dir.join("lib").join(TORCH_LIBS[0]), b"").unwrap();
        assert!(!present(None), "no VERSION marker: an interrupted unpack");

        fs::write(dir.join(VERSION_FILE), "2.10.0\n").unwrap();
        assert!(!present(None), "another version must be replaced");

        fs::write(dir.join(VERSION_FILE), format!("{LIBTORCH_VERSION}\n")).unwrap();
        assert!(present(None));
        // `.cargo/config.toml` sets LIBTORCH to this very folder.
        assert!(present(Some(&dir)));
        fs::remove_dir_all(&repo).unwrap();
    }

    #[test]
    fn a_user_libtorch_wins() {
        let repo = scratch("user");
        let theirs = repo.join("elsewhere");
        match Libtorch::locate(&repo, Some(theirs.clone().into_os_string())) {
            Libtorch::User(dir) => assert_eq!(dir, theirs),
            Libtorch::Repo { .. } => panic!("LIBTORCH set by the user was ignored"),
        }
        fs::remove_dir_all(&repo).unwrap();
    }

    #[test]
    fn dpkg_query_reports_unknown_packages_as_missing() {
        let unknown = "no-such-package-for-xtask-tests";
        // Every Debian system has dpkg itself installed.
        let Some(missing) = missing_packages(&["dpkg", unknown]).unwrap() else {
            return; // not Debian: nothing to check
        };
        assert_eq!(missing, vec![unknown.to_owned()]);
    }

    #[test]
    fn find_wheel_picks_by_prefix() {
        let dir = scratch("wheels");
        for name in [
            "torch-2.11.0-cp311-cp311-manylinux_2_28_x86_64.whl",
            "nvidia_cuda_runtime-13.0.96-py3-none-manylinux2014_x86_64.whl",
            "nvidia_cuda_cupti-13.0.85-py3-none-manylinux_2_25_x86_64.whl",
        ] {
            fs::write(dir.join(name), b"").unwrap();
        }
        let found = find_wheel(&dir, "nvidia_cuda_cupti-").unwrap();
        assert!(found.ends_with("nvidia_cuda_cupti-13.0.85-py3-none-manylinux_2_25_x86_64.whl"));
        assert!(find_wheel(&dir, "torch-2.10.0-").is_err());
        fs::remove_dir_all(&dir).unwrap();
    }
}
