//! `--run`: the array's tasks trained on this machine, one after another.

use std::os::unix::process::CommandExt as _;
use std::path::Path;
use std::sync::atomic::{AtomicI32, AtomicUsize, Ordering};

use crate::cli::pretrain::{InOut, run_in_out};

use super::*;

/// What `--run` did: tasks trained here, and tasks already finished.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Ran {
    pub trained: usize,
    pub skipped: usize,
    /// A stop signal ended the sweep after the task in progress checkpointed.
    pub stopped: bool,
}

/// The pid of the `icrl pretrain` a local sweep waits on (0: none).
static TASK_PID: AtomicI32 = AtomicI32::new(0);
/// Stop signals the local sweep has received.
static STOPS: AtomicUsize = AtomicUsize::new(0);

/// Runs the grid's tasks on this machine, one after another, each as the
/// same `icrl pretrain` an array task runs (`icrl` is the binary to call).
/// A finished task is skipped and a stopped one resumes (`--resume-in-out`),
/// so running the grid again continues it. Each task runs in a process group
/// of its own, so a terminal's Ctrl-C reaches it once, through this process:
/// every SIGINT or SIGTERM the sweep gets is passed to the task in progress
/// as SIGTERM (the first makes it checkpoint, a second ends it at once), and
/// no further task starts.
pub fn run_local(grid: &SweepGrid, icrl: &Path) -> Result<Ran, SweepError> {
    static HANDLER: std::sync::OnceLock<Result<(), String>> = std::sync::OnceLock::new();
    HANDLER
        .get_or_init(|| {
            ctrlc::set_handler(|| {
                STOPS.fetch_add(1, Ordering::SeqCst);
                let pid = TASK_PID.load(Ordering::SeqCst);
                if pid > 0 {
                    // SAFETY: kill(2) on a child this process started and has not reaped.
                    unsafe { libc::kill(pid, libc::SIGTERM) };
                }
            })
            .map_err(|e| format!("cannot install the SIGINT/SIGTERM handler: {e}"))
        })
        .clone()
        .map_err(SweepError::Io)?;
    let mut ran = Ran::default();
    for task in grid.tasks() {
        if STOPS.load(Ordering::SeqCst) > 0 {
            ran.stopped = true;
            break;
        }
        let dir = grid.task_dir(&task);
        if let InOut::Finished { run, updates } =
            run_in_out(&dir, &grid.env, &grid.method, &grid.sets(&task))?
        {
            println!(
                "task {} ({}): finished ({updates} updates in {})",
                task.index,
                task.label(),
                run.display()
            );
            ran.skipped += 1;
            continue;
        }
        println!(
            "task {} ({}): training in {}",
            task.index,
            task.label(),
            dir.display()
        );
        let mut child = std::process::Command::new(icrl)
            .args(grid.pretrain_args(&task))
            .process_group(0)
            .spawn()
            .map_err(|e| SweepError::Io(format!("cannot start {}: {e}", icrl.display())))?;
        TASK_PID.store(child.id() as i32, Ordering::SeqCst);
        // A signal between the spawn and the store would miss the task.
        if STOPS.load(Ordering::SeqCst) > 0 {
            // SAFETY: as in the handler.
            unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
        }
        let status = child.wait();
        TASK_PID.store(0, Ordering::SeqCst);
        let status = status.map_err(|e| SweepError::Io(format!("task {}: {e}", task.index)))?;
        if STOPS.load(Ordering::SeqCst) > 0 {
            ran.stopped = true;
            break;
        }
        if !status.success() {
            return Err(SweepError::Io(format!(
                "task {} ({}) failed ({status}); its log is above, and running the grid again \
                 resumes it",
                task.index,
                task.label()
            )));
        }
        ran.trained += 1;
    }
    Ok(ran)
}
