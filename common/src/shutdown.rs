//! How both binaries end after Ctrl-C.

/// Ends the process by SIGINT with the default action, after stdout is flushed. A shell
/// script without an INT trap takes a Ctrl-C whose child exits normally as handled by the
/// child and goes on, so a `for seed in 1 2 3; do learner serve …; done` would start its next
/// run; a process that stopped cleanly on Ctrl-C calls this so that the script stops too.
pub fn end_by_sigint() {
    let _ = std::io::Write::flush(&mut std::io::stdout());
    // SAFETY: signal(2) and raise(3) with constants; the caller has finished its work.
    unsafe {
        libc::signal(libc::SIGINT, libc::SIG_DFL);
        libc::raise(libc::SIGINT);
    }
}
