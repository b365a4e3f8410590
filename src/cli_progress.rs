//! The progress bar of `homing run` (part of the binary, not the library).
//!
//! Shown only when standard error is a terminal and `-q` is not given, so tests, CI and
//! redirected runs print exactly what they did before. Log lines go through [`LogWriter`],
//! which prints them above the bar instead of through it.

use homing::system::{Progress, ProgressHook};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressState, ProgressStyle};
use std::io::{IsTerminal, Write};
use std::sync::{Arc, Mutex};

/// The bar on screen, if any.
static BAR: Mutex<Option<ProgressBar>> = Mutex::new(None);

fn current() -> Option<ProgressBar> {
    BAR.lock().ok().and_then(|b| b.clone())
}

/// Standard error for the log, printing above the progress bar while one is shown.
pub struct LogWriter;

impl Write for LogWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match current() {
            Some(bar) => bar.suspend(|| std::io::stderr().write_all(buf))?,
            None => std::io::stderr().write_all(buf)?,
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}

/// Starts a bar (when standard error is a terminal and not `quiet`) and returns the hook that
/// moves it: frames done of all, frames per second, the controller's state, maps, keyframes.
pub fn start(quiet: bool) -> Option<ProgressHook> {
    if quiet || !std::io::stderr().is_terminal() {
        return None;
    }
    let bar = ProgressBar::with_draw_target(None, ProgressDrawTarget::stderr());
    let style = ProgressStyle::with_template(
        "{elapsed_precise} [{bar:30.cyan/blue}] {pos}/{len} frames  {fps}  {msg}",
    )
    .ok()?
    .with_key("fps", |s: &ProgressState, w: &mut dyn std::fmt::Write| {
        let _ = write!(w, "{:.1} frames/s", s.per_sec());
    })
    .progress_chars("=> ");
    bar.set_style(style);
    *BAR.lock().ok()? = Some(bar.clone());
    Some(ProgressHook(Arc::new(move |p: &Progress<'_>| {
        if bar.length() != Some(p.total as u64) {
            bar.set_length(p.total as u64);
        }
        bar.set_position(p.delivered as u64);
        bar.set_message(format!(
            "state {}  maps {}  keyframes {}",
            p.state, p.maps, p.keyframes
        ));
    })))
}

/// Removes the bar from the screen.
pub fn finish() {
    if let Ok(mut b) = BAR.lock()
        && let Some(bar) = b.take()
    {
        bar.finish_and_clear();
    }
}
