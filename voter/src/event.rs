//! Events: one JSON object per line for every fault and recovery (and each replica start), so
//! that bootstrap can gather them and campaigns can match injections against them.

use serde::{Deserialize, Serialize};

/// What happened.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EventKind {
    /// A replica was started (initially by exec); `pid` is its pid.
    Start,
    /// Minority output (or, with `replica` absent, no majority at all).
    Sdc,
    /// The replica died.
    Crash,
    /// The replica missed the round's deadline.
    Hang,
    /// Bad frame, extra frame, or closed pipe.
    Protocol,
    /// A faulty replica was replaced; `new_pid`, `method`, `recovery_us` say how.
    Recovery,
    /// A replacement could not be made; the component runs with fewer replicas.
    RecoveryFailed,
    /// An anomaly detector flagged a replica's frame: `output`, `field`, `score`, `threshold`
    /// say where and how much. What the voter did about it is a separate event (`sdc` with the
    /// replica, when the alarm decided something); see `docs/anomaly-detection.md`.
    Anomaly,
}

/// How a replacement replica was made.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RecoveryMethod {
    /// Forked from a healthy donor: state kept.
    Fork,
    /// Started afresh by exec: state lost.
    Exec,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Event {
    /// CLOCK_MONOTONIC, nanoseconds.
    pub ts_ns: u64,
    pub system: String,
    pub component: String,
    pub kind: EventKind,
    /// Replica index (slot); absent when no single replica is to blame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub replica: Option<usize>,
    /// Pid of the replica the event is about.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pid: Option<i32>,
    /// Round number the fault was seen in.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub round: Option<u64>,
    /// Human-readable specifics.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub detail: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub new_pid: Option<i32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub donor: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<RecoveryMethod>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub state_lost: Option<bool>,
    /// Fault detected → new replica ready, microseconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recovery_us: Option<u64>,
    /// `anomaly`: the output port whose frame was flagged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub output: Option<String>,
    /// `anomaly`: the most anomalous monitored field (absent for a frame too short to read).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
    /// `anomaly`: the detector's score (absent when it is infinite: NaN/Inf or short frame).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub score: Option<f64>,
    /// `anomaly`: what the score was compared with.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub threshold: Option<f64>,
}

impl Event {
    pub fn new(system: &str, component: &str, kind: EventKind) -> Self {
        Event {
            ts_ns: monotonic_ns(),
            system: system.to_owned(),
            component: component.to_owned(),
            kind,
            replica: None,
            pid: None,
            round: None,
            detail: None,
            new_pid: None,
            donor: None,
            method: None,
            state_lost: None,
            recovery_us: None,
            output: None,
            field: None,
            score: None,
            threshold: None,
        }
    }

    /// The event as one line of JSON, newline included.
    pub fn to_line(&self) -> String {
        let mut s = serde_json::to_string(self).expect("an event always serializes");
        s.push('\n');
        s
    }
}

pub use replica_rt::sys::monotonic_ns;
