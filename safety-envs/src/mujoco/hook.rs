//! The process-wide MuJoCo error and warning hooks.
//!
//! MuJoCo's default fatal-error handler prints the message, waits for Enter on
//! stdin and exits: under a pipe it hangs forever. [`ensure_hooks`] replaces it,
//! once per process and before any other MuJoCo call, with a hook that unwinds
//! back into Rust; [`guarded`] runs one FFI call and turns that unwind into
//! [`MujocoError::Engine`].
//!
//! After an engine error the `mjData` involved is in an unspecified state (its
//! stack pointer, contact list and time may be half-updated): reset it with
//! `mj_resetData` (`Data::reset`) before using it again. `Data::step` and
//! `Data::forward` do that themselves before returning the error.
//!
//! Limits, both from MuJoCo 2.2's global hooks:
//! - A raw `mujoco_sys` call that fails outside [`guarded`] unwinds as an
//!   ordinary Rust panic carrying MuJoCo's message (still no exit or hang).
//! - While `mj_loadXML` compiles a model, MuJoCo's compiler swaps in its own
//!   process-wide error handler (which throws a C++ exception) and restores
//!   ours afterwards. An engine error raised by *another* thread during that
//!   window would reach the compiler's handler and abort the process. Loads
//!   are serialised (see `Model`), and environments compile their models
//!   once, before stepping, so the window does not arise in this workspace.
//!
//! Warnings (bad qacc, NaN reset, full contact buffer, ...) do not go through a
//! hook we can rely on (MuJoCo calls it only the first time per `mjData`), so
//! they are read from the `warning[i].number` counters (see `Warnings`); the
//! warning hook only keeps MuJoCo's printing off stdout and remembers the text.

use std::any::Any;
use std::cell::RefCell;
use std::ffi::{CStr, c_char};
use std::panic::{AssertUnwindSafe, catch_unwind, resume_unwind};
use std::sync::Once;

use crate::error::MujocoError;

/// The unwind payload the error hook raises: MuJoCo's message.
#[derive(Debug)]
struct EngineError(String);

static INSTALL: Once = Once::new();

thread_local! {
    /// The last warning text MuJoCo emitted on this thread.
    static LAST_WARNING: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Copies a C string from MuJoCo into an owned `String` (lossy, null-safe).
fn message_from(msg: *const c_char) -> String {
    if msg.is_null() {
        return String::from("(no message)");
    }
    // SAFETY: MuJoCo passes a NUL-terminated buffer that lives for this call.
    unsafe { CStr::from_ptr(msg) }
        .to_string_lossy()
        .trim()
        .to_owned()
}

/// Replaces `mju_error`'s print-wait-exit: unwinds back to the nearest
/// [`guarded`] call. `resume_unwind` does not run the panic hook, so nothing is
/// printed. Every MuJoCo entry point is declared `C-unwind` by `mujoco-sys`.
unsafe extern "C-unwind" fn error_hook(msg: *const c_char) {
    resume_unwind(Box::new(EngineError(message_from(msg))));
}

/// Replaces `mju_warning`'s `printf`: keeps the text for [`last_warning`].
unsafe extern "C-unwind" fn warning_hook(msg: *const c_char) {
    let text = message_from(msg);
    LAST_WARNING.with(|w| *w.borrow_mut() = Some(text));
}

/// Installs the error and warning hooks, once per process. Every constructor
/// of the wrapper (`Model`, `Data`, `Renderer`) calls this first.
pub fn ensure_hooks() {
    INSTALL.call_once(|| {
        // SAFETY: written once, under `Once`, before any other call into MuJoCo
        // made by this crate; the functions have the exact C signature.
        unsafe {
            mujoco_sys::mju_user_error = Some(error_hook);
            mujoco_sys::mju_user_warning = Some(warning_hook);
        }
    });
}

/// The last warning text MuJoCo emitted on this thread, if any (taken).
pub fn last_warning() -> Option<String> {
    LAST_WARNING.with(|w| w.borrow_mut().take())
}

/// Runs `f` (one or more MuJoCo calls) and turns an engine error raised inside
/// into `Err(MujocoError::Engine)`. Any other panic is re-raised unchanged.
pub fn guarded<T>(f: impl FnOnce() -> T) -> Result<T, MujocoError> {
    ensure_hooks();
    catch_unwind(AssertUnwindSafe(f)).map_err(engine_error_or_resume)
}

fn engine_error_or_resume(payload: Box<dyn Any + Send>) -> MujocoError {
    match payload.downcast::<EngineError>() {
        Ok(err) => MujocoError::Engine(err.0),
        Err(other) => resume_unwind(other),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::ffi::CString;

    #[test]
    fn mju_error_becomes_err_not_exit() {
        let msg = CString::new("test error from Rust").unwrap();
        let result = guarded(|| unsafe { mujoco_sys::mju_error(msg.as_ptr()) });
        match result {
            Err(MujocoError::Engine(text)) => assert_eq!(text, "test error from Rust"),
            other => panic!("expected an engine error, got {other:?}"),
        }
    }

    #[test]
    fn other_panics_pass_through() {
        let caught = std::panic::catch_unwind(|| guarded(|| panic!("not MuJoCo's")));
        assert!(caught.is_err());
    }

    #[test]
    fn warnings_are_kept_off_stdout() {
        ensure_hooks();
        let msg = CString::new("a warning").unwrap();
        unsafe { mujoco_sys::mju_warning(msg.as_ptr()) };
        assert_eq!(last_warning().as_deref(), Some("a warning"));
        assert_eq!(last_warning(), None);
    }
}
