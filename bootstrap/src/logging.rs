//! Logging set-up of the command-line tools: one function for the whole project, in replica-rt.

pub use replica_rt::init_cli_logging;
