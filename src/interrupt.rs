//! The Interruptible top state's user stop (paper Fig. 8): SIGINT and SIGTERM raise the
//! `user_stop` event instead of killing the process, so that a stopped run still reaches Final,
//! refines and writes every output.
//!
//! The first signal stops the frame loop after the current frame (the state machine then goes
//! to Final as at the end of data, its refinement bounded by `mapping.final_refinement_max_s`);
//! a second one skips what is left of the refinement (what is posed is still written); a third
//! exits at once, for a process that no longer answers.
//!
//! Only the command-line tool installs the handler; the library only reads the count, which
//! stays 0 without it.

use std::sync::atomic::{AtomicUsize, Ordering};

static REQUESTS: AtomicUsize = AtomicUsize::new(0);

/// Exit status of a process that a user stop ended (128 + SIGINT, as shells report it).
pub const EXIT_STATUS: i32 = 130;

/// Routes SIGINT and SIGTERM to the user-stop event (once per process).
pub fn install() -> crate::Result<()> {
    ctrlc::set_handler(|| {
        let n = REQUESTS.fetch_add(1, Ordering::SeqCst) + 1;
        match n {
            1 => eprintln!(
                "\nstopping after this frame: Final refines and writes the outputs (signal again to skip the refinement)"
            ),
            2 => eprintln!("\nskipping the refinement: writing what is posed"),
            _ => std::process::exit(EXIT_STATUS),
        }
    })
    .map_err(|e| crate::Error::invalid(format!("cannot install the SIGINT/SIGTERM handler: {e}")))
}

/// Stop signals received so far.
pub fn requests() -> usize {
    REQUESTS.load(Ordering::SeqCst)
}

/// The user asked the run to stop.
pub fn stop_requested() -> bool {
    requests() >= 1
}

/// The user asked twice: Final's refinement is skipped.
pub fn skip_refinement() -> bool {
    requests() >= 2
}
