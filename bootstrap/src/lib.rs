//! # s3res-bootstrap
//!
//! Reads a system description, checks it, starts every component (unprotected ones directly,
//! protected ones under one `s3res-voter` each), supervises them, gathers the voters' events,
//! and on exit — however it exits — makes sure nothing it started is left running.

#![forbid(unsafe_code)]

pub mod description;
pub mod events;
pub mod exec;
pub mod live;
pub mod logging;
pub mod outcome;
pub mod plan;
pub mod posindex;
pub mod run;
pub mod sched;
pub mod status;
pub mod sweep;
pub mod watch;
