//! Logging set-up of the command-line tools: one function for the whole project, in replica-rt.

pub use replica_rt::{error_chain, init_cli_logging};

/// bootstrap's own logging: [`init_cli_logging`], its lines printed above the status line when
/// one is shown.
pub fn init_status_logging(quiet: bool, verbose: u8) {
    replica_rt::init_cli_logging_to(quiet, verbose, crate::status::StatusAwareStderr);
}
