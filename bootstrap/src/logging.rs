//! Logging set-up of the command-line tools: one function for the whole project, in replica-rt.

pub use replica_rt::{error_chain, init_cli_logging};

/// bootstrap's own logging: [`init_cli_logging`], its lines printed above the status line when
/// one is shown.
pub fn init_status_logging(quiet: bool, verbose: u8) {
    replica_rt::init_cli_logging_to(quiet, verbose, crate::status::StatusAwareStderr);
}

/// Writes `s3res-bootstrap: {text}` and a newline to stderr in one `write`. Every process of
/// the system shares this stderr, and `eprintln!` writes each piece of its format separately:
/// another process's lines (a component's error report) could land in the middle of ours.
pub fn say(text: &str) {
    use std::io::Write;
    let line = format!("s3res-bootstrap: {text}\n");
    let _ = std::io::stderr().lock().write_all(line.as_bytes());
}
