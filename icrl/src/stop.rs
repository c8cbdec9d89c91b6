//! Graceful stop: the first SIGINT or SIGTERM asks training to stop after its
//! current update (the learner then writes a checkpoint and returns an
//! "interrupted" error naming it); a second signal exits at once.
//!
//! Only commands that poll [`requested`] install the handler (`icrl
//! pretrain`); elsewhere Ctrl-C keeps its default meaning.

use std::sync::atomic::{AtomicUsize, Ordering};

/// Signals received since the handler was installed (or [`clear`]).
static SIGNALS: AtomicUsize = AtomicUsize::new(0);

/// Exit code of a run stopped by a signal (128 + SIGINT, as shells report it).
pub const EXIT_INTERRUPTED: u8 = 130;

/// Installs the SIGINT/SIGTERM handler. The second signal prints why and
/// exits with [`EXIT_INTERRUPTED`] without waiting for anything.
pub fn install() -> Result<(), String> {
    ctrlc::set_handler(|| {
        let n = SIGNALS.fetch_add(1, Ordering::SeqCst) + 1;
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

/// True once a stop has been asked for.
pub fn requested() -> bool {
    SIGNALS.load(Ordering::SeqCst) > 0
}

/// Asks for a stop as a signal would (tests, embedding programs).
pub fn request() {
    SIGNALS.fetch_add(1, Ordering::SeqCst);
}

/// Forgets earlier requests.
pub fn clear() {
    SIGNALS.store(0, Ordering::SeqCst);
}
