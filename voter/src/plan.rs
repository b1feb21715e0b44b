//! The plan a voter is started with. Bootstrap builds it from the system description and passes
//! it as JSON (`s3res-voter --plan JSON`); the voter receives it, so the voter defines it.

use std::os::fd::RawFd;
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

/// One external port of the protected component: the fd the voter inherited for it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ExternalPort {
    /// Port name as the component knows it (`in`, `out`, ...).
    pub name: String,
    /// Fd number in the voter's process (an input is readable, an output writable).
    pub fd: RawFd,
    /// Largest payload allowed on this port's channel.
    pub max_frame: usize,
}

/// S³RES's timed pair: a frame on `input` starts a round in which every replica must answer
/// exactly one frame on each of `outputs` before the deadline.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RoundTrigger {
    pub input: String,
    pub outputs: Vec<String>,
}

/// How the voter paces and votes a component.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// S³RES VoterM: a frame on a round-starting input opens a round; every replica answers
    /// exactly one frame on each of the round's outputs before the deadline.
    #[default]
    Reactive,
    /// S³RES VoterD: outputs are not one per input; the k-th frame of each output is voted
    /// across replicas (see `docs/stream-mode.md`).
    Stream,
}

/// Default [`VoterPlan::window`]: how many frames a replica may run ahead of the slowest.
pub const DEFAULT_STREAM_WINDOW: usize = 64;

pub fn default_stream_window() -> usize {
    DEFAULT_STREAM_WINDOW
}

/// Everything a voter needs to run one protected component.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct VoterPlan {
    /// System name (goes into every event).
    pub system: String,
    /// Component name.
    pub component: String,
    /// Absolute path of the component executable.
    pub exec: PathBuf,
    pub args: Vec<String>,
    /// Number of replicas: 1 (SMR), 2 (DMR), 3 (TMR), or more.
    pub replicas: usize,
    /// Round deadline, microseconds after the round's input was delivered.
    pub timeout_us: u64,
    pub inputs: Vec<ExternalPort>,
    pub outputs: Vec<ExternalPort>,
    /// Which inputs start rounds. Inputs not named here are copied to the replicas without one.
    pub rounds: Vec<RoundTrigger>,
    /// Fd to write events to, one JSON object per line (bootstrap gathers them).
    pub events_fd: Option<RawFd>,
    /// Where the voter binds its Unix socket for the restart handshake.
    pub socket_path: PathBuf,
    /// How long a recovery may wait for the donor's child to connect and take its fds.
    #[serde(default = "default_restart_timeout_ms")]
    pub restart_timeout_ms: u64,
    /// SCHED_RR priority of the voter (replicas run below it); `None` leaves the default.
    #[serde(default)]
    pub priority: Option<u8>,
    /// CPUs the replicas may run on (empty: any).
    #[serde(default)]
    pub cpus: Vec<usize>,
    /// Reactive (rounds) or stream (k-th frame voting).
    #[serde(default)]
    pub mode: Mode,
    /// Stream mode: frames per output a replica may run ahead of the slowest trusted replica
    /// before the voter stops reading it (back-pressure through its pipe).
    #[serde(default = "default_stream_window")]
    pub window: usize,
}

pub fn default_restart_timeout_ms() -> u64 {
    1000
}

impl VoterPlan {
    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("a plan always serializes")
    }

    pub fn from_json(s: &str) -> Result<Self, serde_json::Error> {
        serde_json::from_str(s)
    }
}
