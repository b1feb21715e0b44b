//! # s3res-inject
//!
//! Fault injection for s3res systems, after S³RES (signal injection campaigns) and MAVFI
//! (variable- and register-level flips, end-to-end outcome classification).
//!
//! - [`fault`]: the fault kinds and how one is delivered to one process;
//! - [`target`]: finding the process, from bootstrap's live view (`--state`);
//! - [`schedule`]: the seeded plan of instants, targets, bits;
//! - [`runner`]: one bounded run of a system that leaves nothing behind;
//! - [`outcome`]: matching injections with the voters' events;
//! - [`report`]: records (their types are `s3res_protocol::campaign`'s), summaries, tables, merging shards; [`interval`]: the exact 95 %
//!   interval printed with every rate;
//! - [`campaign`] and [`classify`]: the two experiments;
//! - [`stop`]: SIGINT/SIGTERM end the current run cleanly;
//! - [`storm`]: faults into a running system for as long as it runs (a description's `inject`).
//!
//! The command-line guide is docs/campaigns.md.

#![forbid(unsafe_code)]

pub mod campaign;
pub mod classify;
pub mod fault;
pub mod interval;
/// Matching injections with events is the protocol's (`s3res-protocol`), shared with
/// bootstrap, which shows the verdict of a run with an injector; re-exported here under its
/// old name.
pub use s3res_protocol::outcome;
pub mod report;
pub mod runner;
pub mod schedule;
pub mod scratch;
pub mod stop;
pub mod storm;
pub mod target;
