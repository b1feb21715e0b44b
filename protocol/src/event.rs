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
    /// The component's voter died or stopped making progress, and a new one adopted its
    /// replicas: `pid` is the new voter's, `recovery_us` the time from bootstrap seeing the
    /// old one gone to the new one running the component again, `detail` what happened.
    VoterRestart,
    /// No replica answered a round (or a stream frame): nothing went out on `output` for it.
    /// Not a fault of its own — the replicas' faults are their events — but a frame
    /// downstream never gets (an SMR replica that crashed mid-round, every replica stopped).
    Lost,
    /// A replica whose state is lost (started afresh by exec) sends frames that differ from
    /// those of the replicas that kept the component's state, and no fork can give its state
    /// back (every such donor runs threads): it is kept, outvoted, rather than restarted into
    /// the same loss again. Said once per replica (`replica`, `pid`, `output`, `detail`); not a
    /// fault. See `voter/src/decision.rs`, "lost state never outvotes kept state".
    Diverged,
}

impl EventKind {
    /// A fault a voter blamed on a replica or a round: `sdc`, `crash`, `hang`, `protocol`.
    pub fn is_fault(self) -> bool {
        matches!(
            self,
            EventKind::Sdc | EventKind::Crash | EventKind::Hang | EventKind::Protocol
        )
    }
}

/// Why the voter raised an event: the observation behind a fault, or why a frame was
/// withheld. Every fault event carries one; tools and tests match on it, not on `detail`
/// (the human-readable text, which may change). Each cause belongs to one [`EventKind`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Cause {
    // ----- crash
    /// The replica process died (its pidfd, or its output closed and the pidfd followed).
    Died,
    // ----- hang
    /// No (complete) answer within `timeout_us` of the round, or of its turn (reactive).
    Deadline,
    /// Sequential schedule: no (complete) answer within `timeout_us` of its own turn.
    TurnDeadline,
    /// A replica started by exec gave no first answer within the start-up allowance.
    StartDeadline,
    /// It did not take the input queued for it (beyond the backlog limit).
    InputBacklog,
    /// Stream mode: furthest behind on a frame the others produced `timeout_us` ago.
    Behind,
    /// Stream mode: behind on an overdue frame and not asleep waiting for input.
    BehindNotWaiting,
    /// Stream mode: on a CPU for a whole `timeout_us` without producing or waiting.
    Spinning,
    /// Picked as recovery donor, it never once waited within `timeout_us`.
    DonorSpinning,
    // ----- protocol
    /// An output frame that cannot be decoded (length above the channel's maximum).
    BadFrame,
    /// A partial frame: at the deadline, or left behind when the output closed.
    PartialFrame,
    /// It closed an output while it lives.
    ClosedOutput,
    /// A frame no round asked for: outside any round, after the inputs closed, on an output
    /// the round does not expect, or from a replica that joined after the round began.
    UnexpectedFrame,
    /// A second frame on one output in one round; in stream mode, a frame the others did not
    /// produce while all of them sleep waiting for input.
    ExtraFrame,
    /// Writing its input, or reading its output, failed.
    PipeError,
    // ----- sdc
    /// Its frame differs from the majority's.
    Minority,
    /// No whole frame had a majority; its frame differs from the bitwise majority, which was
    /// forwarded.
    BitwiseMinority,
    /// Unattributed (no `replica`): every frame differs from the bitwise majority (forwarded);
    /// the closest was kept as donor.
    AllDiffer,
    /// Unattributed (no `replica`): no frame has a majority; the frame is withheld.
    NoMajority,
    /// The anomaly detector flagged a frame that stands on this replica's word alone; held back.
    AnomalyHeldBack,
    /// Two copies differ and the anomaly detector flagged only this replica's.
    AnomalyAttributed,
    // ----- anomaly
    /// An anomaly detector's score passed its threshold (the `anomaly` event).
    Alarm,
    /// An alarm on the frame right after an alarmed one of the same replica: often the way
    /// back from a corrupted frame (the detector's reference was the corrupted one).
    AlarmAgain,
}

impl Cause {
    /// The kind of event this cause raises.
    pub fn kind(self) -> EventKind {
        use Cause::*;
        match self {
            Died => EventKind::Crash,
            Deadline | TurnDeadline | StartDeadline | InputBacklog | Behind | BehindNotWaiting
            | Spinning | DonorSpinning => EventKind::Hang,
            BadFrame | PartialFrame | ClosedOutput | UnexpectedFrame | ExtraFrame | PipeError => {
                EventKind::Protocol
            }
            Minority | BitwiseMinority | AllDiffer | NoMajority | AnomalyHeldBack
            | AnomalyAttributed => EventKind::Sdc,
            Alarm | AlarmAgain => EventKind::Anomaly,
        }
    }
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
    /// Round number the fault was seen in (reactive mode).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub round: Option<u64>,
    /// The frame's number on its output (stream mode: decisions and alarms).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<u64>,
    /// Why (faults, unattributed `sdc`, `anomaly`): match on this, not on `detail`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cause: Option<Cause>,
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
    /// `crash` of a replica the voter started: its exit status, or the signal that killed it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exit_code: Option<i32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub signal: Option<i32>,
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
            frame: None,
            cause: None,
            detail: None,
            new_pid: None,
            donor: None,
            method: None,
            state_lost: None,
            exit_code: None,
            signal: None,
            recovery_us: None,
            output: None,
            field: None,
            score: None,
            threshold: None,
        }
    }

    /// An event raised for `cause` (its kind is the cause's).
    pub fn caused(system: &str, component: &str, cause: Cause) -> Self {
        let mut ev = Event::new(system, component, cause.kind());
        ev.cause = Some(cause);
        ev
    }

    /// The event as one line of JSON, newline included.
    pub fn to_line(&self) -> String {
        let mut s = serde_json::to_string(self).expect("an event always serializes");
        s.push('\n');
        s
    }
}

/// One line for logs: `sdc replica 1 pid 4242 (minority): detail`, only the fields present.
impl std::fmt::Display for Event {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let kind = serde_json::to_value(self.kind).ok();
        write!(
            f,
            "{}",
            kind.as_ref().and_then(|k| k.as_str()).unwrap_or("?")
        )?;
        if let Some(r) = self.replica {
            write!(f, " replica {r}")?;
        }
        if let Some(pid) = self.pid {
            write!(f, " pid {pid}")?;
        }
        if let Some(new_pid) = self.new_pid {
            write!(f, " → pid {new_pid}")?;
        }
        if let Some(method) = self.method {
            let how = match method {
                RecoveryMethod::Fork => "fork",
                RecoveryMethod::Exec => "exec",
            };
            write!(f, " by {how}")?;
        }
        if let Some(d) = self.donor {
            write!(f, " of replica {d}")?;
        }
        if let Some(us) = self.recovery_us {
            write!(f, " in {us} µs")?;
        }
        if self.state_lost == Some(true) {
            write!(f, ", state lost")?;
        }
        if let Some(code) = self.exit_code {
            write!(f, ", exited with status {code}")?;
        }
        if let Some(sig) = self.signal {
            write!(f, ", killed by signal {sig}")?;
        }
        if let Some(cause) = self.cause {
            let c = serde_json::to_value(cause).ok();
            write!(
                f,
                " ({})",
                c.as_ref().and_then(|c| c.as_str()).unwrap_or("?")
            )?;
        }
        if let Some(detail) = &self.detail {
            write!(f, ": {detail}")?;
        }
        Ok(())
    }
}

pub use crate::clock::monotonic_ns;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fault_reads_as_one_line_of_values() {
        let mut ev = Event::caused("sys", "echo", Cause::Minority);
        ev.replica = Some(1);
        ev.pid = Some(4242);
        ev.detail = Some("`out` differs from the majority in round 7".into());
        assert_eq!(
            ev.to_string(),
            "sdc replica 1 pid 4242 (minority): `out` differs from the majority in round 7"
        );
        let mut rec = Event::new("sys", "echo", EventKind::Recovery);
        rec.replica = Some(1);
        rec.pid = Some(4242);
        rec.new_pid = Some(4300);
        rec.method = Some(RecoveryMethod::Exec);
        rec.recovery_us = Some(812);
        rec.state_lost = Some(true);
        assert_eq!(
            rec.to_string(),
            "recovery replica 1 pid 4242 → pid 4300 by exec in 812 µs, state lost"
        );
    }

    #[test]
    fn every_cause_round_trips_and_names_its_kind() {
        let mut ev = Event::caused("s", "c", Cause::Spinning);
        ev.replica = Some(0);
        let back: Event = serde_json::from_str(ev.to_line().trim()).unwrap();
        assert_eq!(back.cause, Some(Cause::Spinning));
        assert_eq!(back.kind, EventKind::Hang);
        assert!(ev.to_line().contains(r#""cause":"spinning""#));
    }
}
