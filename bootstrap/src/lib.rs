//! # s3res-bootstrap
//!
//! Reads a system description, checks it, starts every component (unprotected ones directly,
//! protected ones under one `s3res-voter` each), supervises them, gathers the voters' events,
//! and on exit — however it exits — makes sure nothing it started is left running.

#![forbid(unsafe_code)]

pub mod component_stderr;
pub mod events;
pub mod keeper;
pub mod live;
pub mod logging;
pub mod respawn;
pub mod run;
pub mod runtime_dir;
pub mod sched;
pub mod status;
pub mod sweep;
pub mod watch;

/// The description, its checks, the checked plan and finding programs are
/// `s3res-description`'s, shared with `s3res-inject`.
pub use s3res_description::{description, exec, plan, posindex};

/// Matching injections with events is the protocol's (`s3res-protocol`), shared with
/// `s3res-inject`.
pub use s3res_protocol::outcome;
