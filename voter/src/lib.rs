//! # s3res-voter
//!
//! Runs the replicas of one protected component, copies input frames to all of them, votes on
//! their output frames, detects faulty replicas and replaces them.
//!
//! Read top-down: [`vote`] is the voting rule; [`round`] a reactive round; [`voter`] the event
//! loop that detects faults; [`clock`] its deadlines on the CPU's counter; [`stream`] the event
//! loop of stream mode (its bookkeeping in [`stream::ledger`]); [`recovery`] the
//! fork-and-hand-over sequence; [`replica`] the
//! process handle; [`channel`] the non-blocking pipe ends; [`plan`] and [`event`] the contracts
//! with bootstrap; [`monitor`] the anomaly detectors on the outputs and frame capture.

pub mod channel;
pub mod clock;
pub mod monitor;
pub mod recovery;
pub mod replica;
pub mod round;
pub mod rt;
pub mod stream;
pub mod vote;
pub mod voter;

/// The plan, its priority scheme and the events are the protocol's (`s3res-protocol`); the old
/// paths stay.
pub use s3res_protocol::{event, plan, sched};
