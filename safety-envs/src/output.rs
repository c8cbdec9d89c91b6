//! Output files and locks, the one construction every writer uses (datasets,
//! eval reports and CSVs, figures, animations, rendered frames).
//!
//! - [`write_file`]: checks the path first ([`check_output`]): a path that
//!   exists is refused unless the caller may replace it ([`Existing::Replace`],
//!   `--force`), and then only when it is a regular file outside any
//!   checkpoint folder, never a device, FIFO, symlink or folder. The bytes go
//!   to a temporary file beside the output, are synced and then published
//!   in one step (a hard link that fails if the name was taken meanwhile, or
//!   a rename when replacing), so a full disk or a kill never leaves a
//!   truncated file under the final name, and the temporary file is removed
//!   on every failure.
//! - [`Lock`]: an OS file lock (`flock`, released by the kernel when the
//!   process dies) holding the owner's pid, so a second process on the same
//!   run or output is refused with the first's pid.

use std::fs;
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};

use thiserror::Error;

/// A path that cannot be written, or a lock held by another process.
#[derive(Debug, Error)]
#[error("{path}: {problem}")]
pub struct OutputError {
    pub path: PathBuf,
    pub problem: String,
}

impl OutputError {
    fn new(path: &Path, problem: impl Into<String>) -> Self {
        OutputError {
            path: path.to_path_buf(),
            problem: problem.into(),
        }
    }
}

/// What to do when the output path exists.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Existing {
    /// Refuse (the default of every command).
    Refuse,
    /// Replace it, if it is a regular file outside a checkpoint folder
    /// (`--force`, or a file the program owns, such as a run's own figure).
    Replace,
}

impl Existing {
    /// `--force` given or not.
    pub fn from_force(force: bool) -> Self {
        if force {
            Existing::Replace
        } else {
            Existing::Refuse
        }
    }
}

/// What kind of thing a path names, for messages ("a FIFO", "a folder", ...).
pub fn kind(ft: &fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if ft.is_dir() {
        "a folder"
    } else if ft.is_symlink() {
        "a symbolic link"
    } else if ft.is_block_device() || ft.is_char_device() {
        "a device"
    } else if ft.is_fifo() {
        "a FIFO"
    } else if ft.is_socket() {
        "a socket"
    } else {
        "a file"
    }
}

/// The folder an output goes into (`.` for a bare file name).
fn parent_of(path: &Path) -> PathBuf {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Checks that `path` can receive a new file, before any long work: its
/// folder exists and is a folder, and the path is free (or, with
/// [`Existing::Replace`], a regular file that is not part of a checkpoint).
pub fn check_output(path: &Path, existing: Existing) -> Result<(), OutputError> {
    let err = |m: String| Err(OutputError::new(path, m));
    match fs::symlink_metadata(path) {
        Ok(meta) => {
            let ft = meta.file_type();
            if !ft.is_file() {
                return err(format!(
                    "it is {}, not a file this program wrote: choose another path",
                    kind(&ft)
                ));
            }
            if parent_of(path).join("manifest.json").is_file() {
                return err(
                    "it is a file of a checkpoint folder (beside its manifest.json): choose another path"
                        .into(),
                );
            }
            if existing == Existing::Refuse {
                return err(
                    "it exists already: pass --force to replace it, or choose another path".into(),
                );
            }
            Ok(())
        }
        Err(e)
            if matches!(
                e.kind(),
                std::io::ErrorKind::NotFound | std::io::ErrorKind::NotADirectory
            ) =>
        {
            check_folder(path)
        }
        Err(e) if is_loop(&e) => err(format!(
            "a folder on its path is a symbolic link loop (links that lead back to themselves, {e}): \
             choose another path"
        )),
        Err(e) => err(format!("cannot use this path: {e}")),
    }
}

/// Bytes an unprivileged writer may still use on the file system holding
/// `path` (or its nearest existing ancestor); `None` when that cannot be read.
pub fn free_bytes(path: &Path) -> Option<u64> {
    let existing = path
        .ancestors()
        .find(|a| !a.as_os_str().is_empty() && a.exists());
    let s = nix::sys::statvfs::statvfs(existing.unwrap_or(Path::new("."))).ok()?;
    Some(s.blocks_available().saturating_mul(s.fragment_size()))
}

/// Refuses to start writing about `need` bytes of `what` at `path` when its
/// disk has less room, naming both sizes and the fix.
pub fn check_room(path: &Path, need: u64, what: &str, fix: &str) -> Result<(), OutputError> {
    match free_bytes(path) {
        Some(free) if free < need => Err(OutputError::new(
            path,
            format!(
                "its disk has {} free, but {what} needs about {}: {fix}",
                human_bytes(free as f64),
                human_bytes(need as f64)
            ),
        )),
        _ => Ok(()),
    }
}

/// The sentence for a write that failed on a disk now (nearly) full, so
/// the cause is named instead of a library's account of the short write;
/// `None` when the disk has room (the failure had another cause).
pub fn full_disk(path: &Path) -> Option<String> {
    const NEARLY_FULL: u64 = 1 << 20;
    let free = free_bytes(path)?;
    (free < NEARLY_FULL).then(|| {
        format!(
            "the disk is full ({} free): free space on it, or choose a path on another disk",
            human_bytes(free as f64)
        )
    })
}

/// Bytes as `12.3 MB`, `4.8 TB` (f64: a silly size must not overflow).
pub fn human_bytes(b: f64) -> String {
    let units = ["B", "kB", "MB", "GB", "TB", "PB", "EB"];
    let mut x = b;
    let mut i = 0;
    while x >= 1000.0 && i + 1 < units.len() {
        x /= 1000.0;
        i += 1;
    }
    if x.is_finite() {
        format!("{x:.1} {}", units[i])
    } else {
        "more than 1e18 B".into()
    }
}

/// ELOOP (Linux): symbolic links that lead back to themselves.
fn is_loop(e: &std::io::Error) -> bool {
    const ELOOP: i32 = 40;
    e.raw_os_error() == Some(ELOOP)
}

/// Makes the output folder `dir` (and its parents) unless it is one
/// already; a file, device, dangling link or symbolic link loop where the
/// folder should be is named, not reported as the OS's `File exists`.
pub fn create_folder(dir: &Path) -> Result<(), OutputError> {
    // Create first and diagnose after: checking before creating races with
    // another process (or thread) creating the same folder in between.
    let created = fs::create_dir_all(dir);
    if dir.is_dir() {
        return Ok(());
    }
    let err = |m: String| Err(OutputError::new(dir, m));
    if let Ok(meta) = fs::symlink_metadata(dir) {
        return match fs::metadata(dir) {
            Err(e) if is_loop(&e) => err(
                "a symbolic link loop (links that lead back to themselves), not a folder: \
                 choose another folder"
                    .into(),
            ),
            Err(_) => err("a symbolic link to nothing, not a folder: choose another folder".into()),
            Ok(target) => err(format!(
                "{}, not a folder: choose another folder (it is created if missing)",
                if meta.file_type().is_symlink() {
                    format!("a symbolic link to {}", kind(&target.file_type()))
                } else {
                    kind(&meta.file_type()).to_string()
                }
            )),
        };
    }
    match created {
        Ok(()) => Ok(()),
        Err(e) if is_loop(&e) => err(format!(
            "cannot create it: a folder on its path is a symbolic link loop ({e}): choose another folder"
        )),
        // A file where a parent folder should be: name which one.
        Err(e) if e.kind() == std::io::ErrorKind::NotADirectory => {
            match check_folder(&dir.join("x")) {
                Err(named) => err(named.problem),
                Ok(()) => err(format!("cannot create it: {e}")),
            }
        }
        Err(e) => err(format!("cannot create it: {e}")),
    }
}

/// The folder of `path` exists and is a folder; otherwise names the first
/// ancestor that is missing or is not a folder.
fn check_folder(path: &Path) -> Result<(), OutputError> {
    let parent = parent_of(path);
    if parent.is_dir() {
        return Ok(());
    }
    // Walk up to the first ancestor that exists.
    let mut missing = parent.clone();
    for a in parent.ancestors().skip(1) {
        let a = if a.as_os_str().is_empty() {
            Path::new(".")
        } else {
            a
        };
        match fs::metadata(a) {
            Ok(m) if m.is_dir() => break,
            Ok(_) => {
                return Err(OutputError::new(
                    path,
                    format!("{} is a file, not a folder", a.display()),
                ));
            }
            Err(_) => missing = a.to_path_buf(),
        }
    }
    if let Ok(m) = fs::symlink_metadata(&missing)
        && !m.is_dir()
    {
        return Err(OutputError::new(
            path,
            format!(
                "{} is {}, not a folder",
                missing.display(),
                kind(&m.file_type())
            ),
        ));
    }
    Err(OutputError::new(
        path,
        format!(
            "the folder {} does not exist; create it first (mkdir -p {})",
            parent.display(),
            parent.display()
        ),
    ))
}

/// The temporary file an output is written to: beside it (same file system,
/// so publishing is one step), hidden, with the process id and the output's
/// extension (image writers choose the format by it).
pub fn temp_path(path: &Path) -> PathBuf {
    let stem = path
        .file_stem()
        .map_or_else(|| "out".into(), |s| s.to_string_lossy().into_owned());
    let ext = path
        .extension()
        .map_or_else(String::new, |e| format!(".{}", e.to_string_lossy()));
    parent_of(path).join(format!(".{stem}.tmp-{}{ext}", std::process::id()))
}

/// Writes `path` through `write`, which fills the temporary file it is
/// given: checked by [`check_output`], synced, then published atomically.
/// On any failure the temporary file is removed and `path` is untouched.
pub fn write_file<E: From<OutputError>>(
    path: &Path,
    existing: Existing,
    write: impl FnOnce(&Path) -> Result<(), E>,
) -> Result<(), E> {
    check_output(path, existing)?;
    let tmp = temp_path(path);
    let _ = fs::remove_file(&tmp);
    // Created here first, so an unwritable folder is named by the OS's own
    // words before a writer (plotters, HDF5) words it its own way.
    if let Err(e) = fs::File::create(&tmp) {
        return Err(OutputError::new(path, format!("cannot write here: {e}")).into());
    }
    let result = write(&tmp).and_then(|()| publish(&tmp, path, existing).map_err(E::from));
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

/// [`write_file`] for bytes already in memory.
pub fn write_bytes(path: &Path, existing: Existing, bytes: &[u8]) -> Result<(), OutputError> {
    write_file(path, existing, |tmp| {
        fs::write(tmp, bytes).map_err(|e| OutputError::new(tmp, format!("cannot write: {e}")))
    })
}

/// Syncs `tmp` and moves it to `path`; without `Replace`, a hard link that
/// fails if `path` appeared since the check.
fn publish(tmp: &Path, path: &Path, existing: Existing) -> Result<(), OutputError> {
    let sync = fs::File::open(tmp).and_then(|f| f.sync_all());
    sync.map_err(|e| OutputError::new(tmp, format!("cannot write: {e}")))?;
    if existing == Existing::Refuse {
        match fs::hard_link(tmp, path) {
            Ok(()) => {
                let _ = fs::remove_file(tmp);
                return Ok(());
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                return Err(OutputError::new(
                    path,
                    "it was created by something else while this command ran: nothing was written \
                     (pass --force to replace it, or choose another path)",
                ));
            }
            // File systems without hard links: check, then rename.
            Err(_) => check_output(path, Existing::Refuse)?,
        }
    } else {
        check_output(path, Existing::Replace)?;
    }
    fs::rename(tmp, path).map_err(|e| {
        OutputError::new(
            path,
            format!("cannot move {} into place: {e}", tmp.display()),
        )
    })
}

/// An exclusive OS lock on a file, with the owner's pid written in it;
/// released when dropped or when the process dies.
#[derive(Debug)]
pub struct Lock {
    path: PathBuf,
    _file: fs::File,
    remove: bool,
}

impl Lock {
    /// Takes the lock at `lock_path`, or says which process holds it.
    /// `what` names what is locked in the refusal (e.g. `the run RUN`).
    /// `remove`: delete the lock file when done (a lock beside an output;
    /// a run keeps its `.lock`).
    pub fn acquire(lock_path: &Path, what: &str, remove: bool) -> Result<Self, OutputError> {
        use std::os::unix::fs::{FileTypeExt, MetadataExt, OpenOptionsExt};
        loop {
            // A lock is never written through a link: the pid would land in
            // whatever file the link names.
            if fs::symlink_metadata(lock_path).is_ok_and(|m| m.file_type().is_symlink()) {
                return Err(OutputError::new(
                    lock_path,
                    "the lock file is a symbolic link, which icrl never writes through: remove it"
                        .to_string(),
                ));
            }
            let mut file = fs::OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false)
                .custom_flags(nix::fcntl::OFlag::O_NOFOLLOW.bits())
                .open(lock_path)
                .map_err(|e| {
                    OutputError::new(lock_path, format!("cannot create the lock file: {e}"))
                })?;
            let kind = file
                .metadata()
                .map_err(|e| {
                    OutputError::new(lock_path, format!("cannot read the lock file: {e}"))
                })?
                .file_type();
            if !kind.is_file() {
                let is = if kind.is_fifo() {
                    "a FIFO"
                } else if kind.is_dir() {
                    "a folder"
                } else {
                    "a device"
                };
                return Err(OutputError::new(
                    lock_path,
                    format!("the lock file is {is}, not a regular file: remove it"),
                ));
            }
            match file.try_lock() {
                Ok(()) => {}
                Err(fs::TryLockError::WouldBlock) => {
                    let mut text = String::new();
                    let _ = file.read_to_string(&mut text);
                    let pid = text.trim();
                    let pid = if pid.is_empty() { "unknown" } else { pid };
                    return Err(OutputError::new(
                        lock_path,
                        format!(
                            "{what} is in use by another icrl process (pid {pid}): wait for it to end or stop it; \
                             two processes would interleave their files"
                        ),
                    ));
                }
                Err(fs::TryLockError::Error(e)) => {
                    return Err(OutputError::new(lock_path, format!("cannot lock: {e}")));
                }
            }
            // A holder that removed the file after we opened it: lock the new one.
            let same = match (file.metadata(), fs::metadata(lock_path)) {
                (Ok(a), Ok(b)) => a.ino() == b.ino() && a.dev() == b.dev(),
                _ => false,
            };
            if !same {
                continue;
            }
            let write = file
                .set_len(0)
                .and_then(|()| file.rewind())
                .and_then(|()| writeln!(file, "{}", std::process::id()))
                .and_then(|()| file.flush());
            write.map_err(|e| {
                OutputError::new(lock_path, format!("cannot write the lock file: {e}"))
            })?;
            return Ok(Lock {
                path: lock_path.to_path_buf(),
                _file: file,
                remove,
            });
        }
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for Lock {
    fn drop(&mut self) {
        if self.remove {
            // Removed while still held: a waiter re-checks the inode.
            let _ = fs::remove_file(&self.path);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(name: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("safety-envs-output-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&d);
        fs::create_dir_all(&d).unwrap();
        d
    }

    /// A lock file that is a symbolic link (to a user's file) or a FIFO is
    /// refused by name, and the link's target keeps its contents.
    #[test]
    fn a_lock_is_never_written_through_a_link_or_into_a_fifo() {
        let d = dir("lock-link");
        let theirs = d.join("notes.txt");
        fs::write(&theirs, "mine").unwrap();
        let link = d.join(".lock");
        std::os::unix::fs::symlink(&theirs, &link).unwrap();
        let err = Lock::acquire(&link, "the run", false)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("symbolic link"), "{err}");
        assert_eq!(fs::read_to_string(&theirs).unwrap(), "mine");
        let dangling = d.join("dangling.lock");
        std::os::unix::fs::symlink(d.join("nowhere"), &dangling).unwrap();
        let err = Lock::acquire(&dangling, "the run", false)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("symbolic link"), "{err}");
        assert!(
            !d.join("nowhere").exists(),
            "a dangling link is not followed"
        );
        let fifo = d.join("fifo.lock");
        nix::unistd::mkfifo(&fifo, nix::sys::stat::Mode::S_IRWXU).unwrap();
        let err = Lock::acquire(&fifo, "the run", false)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("a FIFO, not a regular file"), "{err}");
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn an_unwritable_folder_is_named_before_the_writer_runs() {
        // /proc takes no new files, not even from root (CI runs as root, so
        // permissions alone cannot make a folder unwritable here).
        let path = Path::new("/proc/icrl-output-test.png");
        let mut ran = false;
        let err = write_file::<OutputError>(path, Existing::Refuse, |_| {
            ran = true;
            Ok(())
        })
        .unwrap_err()
        .to_string();
        assert!(!ran, "the writer never saw the path");
        assert!(
            err.contains("/proc/icrl-output-test.png") && err.contains("cannot write here"),
            "{err}"
        );
    }

    #[test]
    fn outputs_never_replace_what_is_not_ours() {
        let d = dir("replace");
        let f = d.join("a.h5");
        write_bytes(&f, Existing::Refuse, b"one").unwrap();
        assert_eq!(fs::read(&f).unwrap(), b"one");
        let e = write_bytes(&f, Existing::Refuse, b"two")
            .unwrap_err()
            .to_string();
        assert!(e.contains("exists already") && e.contains("--force"), "{e}");
        write_bytes(&f, Existing::Replace, b"two").unwrap();
        assert_eq!(fs::read(&f).unwrap(), b"two");
        // Not a regular file: refused even with --force; /dev/null untouched.
        for (p, what) in [
            (Path::new("/dev/null"), "a device"),
            (d.as_path(), "a folder"),
        ] {
            let e = write_bytes(p, Existing::Replace, b"x")
                .unwrap_err()
                .to_string();
            assert!(e.contains(what), "{e}");
        }
        assert!(!fs::metadata("/dev/null").unwrap().is_file());
        let link = d.join("link");
        std::os::unix::fs::symlink(&f, &link).unwrap();
        let e = write_bytes(&link, Existing::Replace, b"x")
            .unwrap_err()
            .to_string();
        assert!(e.contains("symbolic link"), "{e}");
        // A checkpoint's file.
        let ck = d.join("step_1");
        fs::create_dir(&ck).unwrap();
        fs::write(ck.join("manifest.json"), "{}").unwrap();
        fs::write(ck.join("model.safetensors"), "w").unwrap();
        let e = write_bytes(&ck.join("model.safetensors"), Existing::Replace, b"x")
            .unwrap_err()
            .to_string();
        assert!(e.contains("checkpoint"), "{e}");
        assert_eq!(fs::read(ck.join("model.safetensors")).unwrap(), b"w");
        // A file where a folder should be; a missing folder.
        let e = write_bytes(&f.join("x.h5"), Existing::Refuse, b"x")
            .unwrap_err()
            .to_string();
        assert!(e.contains("is a file, not a folder"), "{e}");
        let e = write_bytes(&d.join("no/x.h5"), Existing::Refuse, b"x")
            .unwrap_err()
            .to_string();
        assert!(e.contains("does not exist"), "{e}");
        // A failing writer leaves nothing, not even its temporary file.
        let r: Result<(), OutputError> = write_file(&d.join("b.png"), Existing::Refuse, |tmp| {
            fs::write(tmp, b"half").unwrap();
            Err(OutputError::new(tmp, "disk full"))
        });
        assert!(r.is_err());
        let names: Vec<_> = fs::read_dir(&d)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names.len(), 3, "{names:?}");
        fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn output_folders_that_cannot_be_made_are_named() {
        let d = dir("folders");
        let problem = |p: &Path| create_folder(p).unwrap_err().problem;
        std::os::unix::fs::symlink(d.join("loop"), d.join("loop")).unwrap();
        assert!(problem(&d.join("loop")).contains("a symbolic link loop"));
        assert!(
            problem(&d.join("loop/sub")).contains("a folder on its path is a symbolic link loop")
        );
        std::os::unix::fs::symlink(d.join("nothing"), d.join("dangling")).unwrap();
        assert!(problem(&d.join("dangling")).contains("a symbolic link to nothing"));
        fs::write(d.join("afile"), b"x").unwrap();
        assert!(problem(&d.join("afile")).starts_with("a file, not a folder"));
        let p = problem(&d.join("afile/sub/deeper"));
        assert!(p.contains("afile is a file, not a folder"), "{p}");
        assert!(problem(Path::new("/dev/null")).starts_with("a device, not a folder"));
        // A folder is made, with its parents, and an existing one is kept.
        create_folder(&d.join("a/b")).unwrap();
        create_folder(&d.join("a/b")).unwrap();
        assert!(d.join("a/b").is_dir());
        let _ = fs::remove_dir_all(&d);
    }

    #[test]
    fn a_second_lock_is_refused_with_the_first_pid() {
        let d = dir("lock");
        let p = d.join(".lock");
        let first = Lock::acquire(&p, "the run R", false).unwrap();
        let e = Lock::acquire(&p, "the run R", false)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(&format!("pid {}", std::process::id())) && e.contains("the run R"),
            "{e}"
        );
        drop(first);
        let again = Lock::acquire(&p, "the run R", true).unwrap();
        drop(again);
        assert!(!p.exists(), "removed when asked");
        fs::remove_dir_all(&d).unwrap();
    }
}
