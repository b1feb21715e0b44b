//! # s3res-voter
//!
//! Runs the replicas of one protected component, copies input frames to all of them, votes on
//! their output frames, detects faulty replicas and replaces them.
//!
//! Read top-down: [`vote`] is the voting rule and [`decision`] the policy built on it (what to
//! forward, whom to blame), pure functions with their tests. `core` is what a voter does in
//! either mode: the replicas, the ports (`ports`), faults, recovery ([`recovery`]: fork from a
//! donor and hand over its pipes, else exec) and events; it applies the decisions. The two
//! modes use it: [`reactive`] (a [`round`] per input frame) and [`stream`] (the k-th frame of
//! each output, its bookkeeping in [`stream::ledger`]). [`clock`] keeps the deadlines on the
//! CPU's counter; [`replica`] is the process handle, [`stderr`] the relay of its stderr;
//! [`channel`] the non-blocking pipe ends;
//! [`plan`] and [`event`] the contracts with bootstrap; [`monitor`] the anomaly detectors on
//! the outputs and frame capture; [`rt`] and [`sched`] priorities and pinning.

mod adopt;
pub mod channel;
pub mod clock;
mod core;
pub mod crashpoint;
pub mod decision;
mod held;
mod journal;
mod lines;
pub mod monitor;
mod park;
mod ports;
pub mod reactive;
pub mod recovery;
pub mod replica;
pub mod round;
pub mod rt;
pub mod spin;
pub mod starvation;
pub mod stream;
pub mod vote;

#[cfg(test)]
mod test_support;

/// The plan, its priority scheme and the events are the protocol's (`s3res-protocol`); the old
/// paths stay.
pub use s3res_protocol::{event, plan, sched};

pub use crate::core::{validate as validate_plan, VoterError};
pub use crate::ports::{stray_stop, StrayStop};
pub use reactive::ReactiveVoter;
pub use stream::StreamVoter;
