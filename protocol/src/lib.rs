//! # s3res-protocol
//!
//! The formats that pass between s3res processes, in one crate that tools can depend on
//! without the voter or bootstrap:
//!
//! - [`frame`]: the wire format of every channel (4-byte little-endian length, payload).
//! - [`contract`]: what a component receives (environment, port map), the restart handshake
//!   between voter and fork child, and the signals a replica understands.
//! - [`plan`]: the plan bootstrap starts a voter with (`s3res-voter --plan JSON`); [`sched`]
//!   its priorities, placement and round schedule; [`layout`] the monitored fields of a channel.
//! - [`event`]: the events a voter writes (JSON lines), which bootstrap gathers and campaigns
//!   match against.
//! - [`live`]: bootstrap's live view (`--state FILE`), which injectors read.
//! - [`outcome`]: what became of an injection (matched against the events), and
//!   [`campaign`]: the records a campaign writes (`campaign.json`, `runs.jsonl`,
//!   `injections.jsonl`); [`machine`] the machine and build they ran on.
//! - [`clock`]: the clock of every timestamp in them.
//! - [`rng`]: the seeded generator (SplitMix64) that makes a mission, a campaign or a test
//!   replayable from one number.

#![deny(unsafe_code)]

pub mod campaign;
pub mod clock;
pub mod contract;
pub mod event;
pub mod frame;
pub mod layout;
pub mod live;
pub mod machine;
pub mod outcome;
pub mod plan;
pub mod rng;
pub mod sched;
