//! # s3res-voter
//!
//! Runs the replicas of one protected component, copies input frames to all of them, votes on
//! their output frames, detects faulty replicas and replaces them.

pub mod event;
pub mod plan;
