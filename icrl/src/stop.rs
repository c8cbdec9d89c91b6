//! Graceful stop: the first SIGINT or SIGTERM asks training to stop after its
//! current update (the learner then writes a checkpoint and returns an
//! "interrupted" error naming it); a second signal exits at once.
//!
//! Only commands that poll [`requested`] install the handler (`icrl
//! pretrain`); elsewhere Ctrl-C keeps its default meaning.

use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Signals received since the handler was installed (or [`clear`]).
static SIGNALS: AtomicUsize = AtomicUsize::new(0);

/// Once the work is saved ([`saved`]): what the first signal says before it
/// ends the process at once.
static SAVED: Mutex<Option<String>> = Mutex::new(None);

/// Exit code of a run stopped by a signal (128 + SIGINT, as shells report it).
pub const EXIT_INTERRUPTED: u8 = 130;

/// Installs the SIGINT/SIGTERM handler. The second signal prints why and
/// exits with [`EXIT_INTERRUPTED`] without waiting for anything.
pub fn install() -> Result<(), String> {
    ctrlc::set_handler(|| {
        let n = SIGNALS.fetch_add(1, Ordering::SeqCst) + 1;
        let saved = SAVED.lock().map_or(None, |m| m.clone());
        if let Some(message) = saved {
            eprintln!("\nstop requested: {message}");
            // SAFETY: as below; everything worth keeping is on disk.
            unsafe { libc::_exit(i32::from(EXIT_INTERRUPTED)) }
        }
        if n == 1 {
            eprintln!(
                "\nstop requested: finishing the current update and writing a checkpoint \
                 (signal again to exit at once, losing the work since the last checkpoint)"
            );
        } else {
            eprintln!("\nsecond stop signal: exiting now, without a checkpoint");
            // `_exit`, not `std::process::exit`: exit handlers and static
            // destructors (libtorch's, OpenMP's) would run while the training
            // thread is still inside libtorch, and can crash the exit itself.
            // SAFETY: `_exit` ends the process at once; nothing runs after it.
            unsafe { libc::_exit(i32::from(EXIT_INTERRUPTED)) }
        }
    })
    .map_err(|e| format!("cannot install the SIGINT/SIGTERM handler: {e}"))
}

/// Declares the work saved (training over, its last checkpoint written):
/// from now on a signal prints `message` (what is true: the checkpoint, what
/// is skipped) and ends the process at once with [`EXIT_INTERRUPTED`],
/// instead of promising an update and a checkpoint that will not come.
pub fn saved(message: String) {
    if let Ok(mut m) = SAVED.lock() {
        *m = Some(message);
    }
}

/// True once a stop has been asked for.
pub fn requested() -> bool {
    SIGNALS.load(Ordering::SeqCst) > 0
}

/// Asks for a stop as a signal would (tests, embedding programs).
pub fn request() {
    SIGNALS.fetch_add(1, Ordering::SeqCst);
}

/// Forgets earlier requests (and [`saved`]).
pub fn clear() {
    SIGNALS.store(0, Ordering::SeqCst);
    if let Ok(mut m) = SAVED.lock() {
        *m = None;
    }
}
