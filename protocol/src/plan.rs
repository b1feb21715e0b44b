//! The plan a voter is started with. Bootstrap builds it from the system description and passes
//! it as JSON (`s3res-voter --plan JSON`); the voter receives it, so the voter defines it.

use std::os::fd::RawFd;
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::layout::FieldLayout;
use crate::sched::Schedule;

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

/// An output whose frames an anomaly detector watches (see `docs/anomaly-detection.md`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MonitorPlan {
    /// The output port (one of [`VoterPlan::outputs`]).
    pub output: String,
    /// The channel's declared fields; the model must have been trained on exactly these.
    pub fields: FieldLayout,
    /// Absolute path of the model file (`s3res-train`'s output).
    pub model: PathBuf,
    /// Replaces the model's own threshold: σ for a Gaussian model, the reconstruction-error
    /// threshold for an autoencoder.
    #[serde(default)]
    pub threshold: Option<f64>,
}

/// An output whose voted frames are also written to a file, in the s3res framing (training
/// data for `s3res-train`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CapturePlan {
    pub output: String,
    /// Absolute path; created (truncated) at start.
    pub path: PathBuf,
}

/// Everything a voter needs to run one protected component.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
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
    /// Fd of the heartbeat page (`replica_rt::heartbeat`) the voter bumps on every turn of
    /// its loop, so that bootstrap can tell a stopped or stuck voter. `None`: no one watches.
    #[serde(default)]
    pub heartbeat_fd: Option<RawFd>,
    /// Where the voter's Unix socket for the restart handshake lives (replicas find it through
    /// `S3RES_VOTER_SOCKET`).
    pub socket_path: PathBuf,
    /// The socket itself, bound and listening, when bootstrap made it: then it outlives the
    /// voter (bootstrap keeps a copy), and replicas whose voter died wait in its backlog for
    /// the next one. `None`: the voter binds `socket_path` itself.
    #[serde(default)]
    pub socket_fd: Option<RawFd>,
    /// Fd of the voter's journal (a memfd bootstrap made and keeps; `voter/src/journal.rs`):
    /// the replicas, the input frame of the unfinished round, the frames forwarded — what a
    /// successor needs to take the component over. `None`: no journal, no successor.
    #[serde(default)]
    pub journal_fd: Option<RawFd>,
    /// Fd of the replicas' answer-stamp page (a memfd bootstrap made and keeps, like the
    /// journal; `replica_rt::stamps`), so that a successor reads the stamps of the replicas it
    /// adopts. `None`: the voter makes a page of its own.
    #[serde(default)]
    pub stamps_fd: Option<RawFd>,
    /// An unmodified program's voter under a journal: the two ends of a socket pair
    /// (`SOCK_SEQPACKET`, sending end first) that bootstrap made and keeps, in which the voter
    /// parks the voter's ends of every replica's pipes (`voter/src/park.rs`), so that they
    /// outlive it and its successor takes them over.
    #[serde(default)]
    pub park_fds: Option<[RawFd; 2]>,
    /// Set when this voter succeeds one that died or stopped: it adopts the replicas its
    /// journal names instead of starting new ones.
    #[serde(default)]
    pub adopt: Option<Adoption>,
    /// How long a recovery may wait for the donor's child to connect and take its fds.
    #[serde(default = "default_restart_timeout_ms")]
    pub restart_timeout_ms: u64,
    /// How long a replica started by exec may take to give its first answer: until then it is
    /// still starting (exec, linking, `mlockall` faulting in its pages), not hung. A round in
    /// which such a replica takes part runs on `max(timeout_us, start_timeout_ms)`.
    #[serde(default = "default_start_timeout_ms")]
    pub start_timeout_ms: u64,
    /// Restart budget: at most this many replicas started by exec (state lost) within
    /// `restart_window_ms`; one more and the component has failed (after OTP's restart
    /// intensity). Fork recoveries do not count: they keep the state.
    #[serde(default = "default_max_restarts")]
    pub max_restarts: u32,
    #[serde(default = "default_restart_window_ms")]
    pub restart_window_ms: u64,
    /// SCHED_RR priority of the voter (replicas run below it); `None` leaves the default.
    #[serde(default)]
    pub priority: Option<u8>,
    /// CPUs the replicas are spread over, replica `i` on `cpus[i % len]` (empty: not pinned).
    #[serde(default)]
    pub cpus: Vec<usize>,
    /// The CPU the voter itself runs on; `None`: the whole of `cpus` (or anywhere).
    #[serde(default)]
    pub voter_cpu: Option<usize>,
    /// How a round gives its replicas the CPU and times them (bootstrap resolves `auto`).
    #[serde(default)]
    pub schedule: Schedule,
    /// Whether to ask for SCHED_RR. Bootstrap sets it to false when its own probe found
    /// SCHED_RR refused (it has said so once); the voter then goes straight to `nice`.
    #[serde(default = "yes")]
    pub realtime: bool,
    /// Nice values standing in for the priorities where SCHED_RR is refused; `None` leaves
    /// the nice values alone.
    #[serde(default)]
    pub nice: Option<NiceFallback>,
    /// Reactive (rounds) or stream (k-th frame voting).
    #[serde(default)]
    pub mode: Mode,
    /// Stream mode: frames per output a replica may run ahead of the slowest trusted replica
    /// before the voter stops reading it (back-pressure through its pipe).
    #[serde(default = "default_stream_window")]
    pub window: usize,
    /// Outputs watched by anomaly detectors (reactive mode).
    #[serde(default)]
    pub monitors: Vec<MonitorPlan>,
    /// Outputs whose voted frames are captured to a file.
    #[serde(default)]
    pub captures: Vec<CapturePlan>,
    /// How the replicas' own pipes are framed; the channels outside stay in s3res frames.
    #[serde(default)]
    pub framing: Framing,
    /// How much of its memory each replica keeps locked (passed on in
    /// [`crate::contract::ENV_LOCK_MEMORY`]).
    #[serde(default)]
    pub lock_memory: LockMemory,
    /// Whether idle CPUs may sleep while this voter runs (see [`CpuIdle`]).
    #[serde(default)]
    pub cpu_idle: CpuIdle,
    /// How long the voter may spin (look without sleeping) for an answer from replicas that
    /// run on CPUs other than its own before it sleeps, µs; 0: never (`voter/src/spin.rs`).
    #[serde(default = "default_spin_us")]
    pub spin_us: u32,
    /// An unmodified program: this library is put in its `LD_PRELOAD` (it installs the restart
    /// handler and the injection hooks), and its one input and one output are its stdin and
    /// stdout. `None`: the component links replica-rt itself and finds its ports on fd 3, 4, ...
    #[serde(default)]
    pub preload: Option<PathBuf>,
}

/// What bootstrap tells a voter that succeeds another (see [`VoterPlan::adopt`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Adoption {
    /// The voter that died.
    pub previous_pid: i32,
    /// When bootstrap saw it gone (CLOCK_MONOTONIC, ns): the `voter_restart` event's
    /// `recovery_us` runs from here.
    pub gone_ns: u64,
    /// Why it is gone, in words (`killed by signal 9`, `made no progress for 8.0 s`).
    pub why: String,
    /// Voters of this component started so far, this one included.
    pub generation: u32,
}

/// How frames cross the pipes between the voter and its replicas.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Framing {
    /// The s3res framing: a 4-byte little-endian length, then the payload.
    #[default]
    Frames,
    /// Newline-delimited text: each line (without its `\n`) is one frame. The voter writes
    /// each frame reaching the component as one line and votes the k-th line of each replica.
    Lines,
}

/// How much of its memory a replica locks (`mlockall`), so that no page fault adds latency to a
/// round. The component's `lock_memory` in the system description.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LockMemory {
    /// Every page of every mapping, populated at start (`MCL_CURRENT | MCL_FUTURE`): no page
    /// fault in a round, ever, at the price of the whole binary and its libraries resident in
    /// every replica (about 4.4 MiB for the smallest Rust component).
    #[default]
    All,
    /// The pages the replica uses: locked when first touched (`MCL_ONFAULT`), nothing
    /// populated up front (about 3.0 MiB for the smallest component). Code first run later (an
    /// error path, the restart handler at the first fork) takes a page fault then, which reads
    /// from disk if no process kept that page of the file in memory.
    Used,
}

impl LockMemory {
    /// The value of [`crate::contract::ENV_LOCK_MEMORY`].
    pub fn as_str(self) -> &'static str {
        match self {
            LockMemory::Used => "used",
            LockMemory::All => "all",
        }
    }

    /// Reads [`crate::contract::ENV_LOCK_MEMORY`]'s value.
    pub fn parse(s: &str) -> Option<LockMemory> {
        match s {
            "used" => Some(LockMemory::Used),
            "all" => Some(LockMemory::All),
            _ => None,
        }
    }
}

/// The kernel's PM QoS CPU latency file, through which `cpu_idle: poll` asks (see [`CpuIdle`]):
/// a request written here holds while the file stays open. Root's alone.
pub const CPU_LATENCY_QOS: &str = "/dev/cpu_dma_latency";

/// What an idle CPU does while the voter runs: the component's `cpu_idle` in the system
/// description.
///
/// An idle CPU normally halts; on a virtual machine a halted vCPU is given back to the host,
/// and the wake-up that ends a round's wait (a replica's answer, the voter's next input) then
/// takes tens of µs. `poll` asks the kernel to keep every CPU polling when idle instead, for
/// as long as the voter runs: a PM QoS CPU latency request of 0 µs on `/dev/cpu_dma_latency`,
/// as cyclictest makes, which the kernel drops when the voter's file closes (also when it
/// dies). The request is machine-wide, needs root, and costs power: an idle CPU keeps
/// running.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CpuIdle {
    /// The kernel's choice: idle CPUs sleep as deep as its governor decides.
    #[default]
    Halt,
    /// Idle CPUs poll (no sleep state) while the voter runs.
    Poll,
}

impl CpuIdle {
    /// The name used in a system description.
    pub fn as_str(self) -> &'static str {
        match self {
            CpuIdle::Halt => "halt",
            CpuIdle::Poll => "poll",
        }
    }

    /// Reads a name written by [`as_str`](Self::as_str).
    pub fn parse(s: &str) -> Option<CpuIdle> {
        match s {
            "halt" => Some(CpuIdle::Halt),
            "poll" => Some(CpuIdle::Poll),
            _ => None,
        }
    }
}

/// Nice values used instead of SCHED_RR priorities, chosen by bootstrap so that the order of
/// every process of the system is kept (see `docs/real-time.md`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct NiceFallback {
    pub voter: i32,
    /// Every replica of the component: one value, because without privilege a nice value
    /// cannot be lowered again, so a turn could not be raised nor a forked replica be given
    /// a stronger value than its donor's.
    pub replicas: i32,
}

fn yes() -> bool {
    true
}

/// The voter's spin for an answer from another CPU, µs, unless the component says (measured
/// on the 2-core VM of docs/results.md, stop 53: an echo across CPUs answers in 3–10 µs after
/// its input, a TMR round's third answer 20–40 µs after it).
pub const DEFAULT_SPIN_US: u32 = 50;

/// The longest spin a component may ask for, µs.
pub const MAX_SPIN_US: u32 = 1000;

pub fn default_spin_us() -> u32 {
    DEFAULT_SPIN_US
}

pub fn default_start_timeout_ms() -> u64 {
    1000
}

pub fn default_restart_timeout_ms() -> u64 {
    1000
}

pub fn default_max_restarts() -> u32 {
    10
}

pub fn default_restart_window_ms() -> u64 {
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A plan written before the real-time fields existed still parses, with the defaults:
    /// parallel rounds, SCHED_RR where a priority is given, no nice fallback, no voter CPU.
    #[test]
    fn an_older_plan_without_the_real_time_fields_parses() {
        let old = r#"{"system":"s","component":"c","exec":"/bin/true","args":[],"replicas":3,
            "timeout_us":1000,"inputs":[],"outputs":[],"rounds":[],"events_fd":null,
            "socket_path":"/tmp/x.sock","priority":30,"cpus":[0]}"#;
        let plan = VoterPlan::from_json(old).unwrap();
        assert_eq!(plan.schedule, Schedule::Parallel);
        assert!(plan.realtime);
        assert_eq!(plan.nice, None);
        assert_eq!(plan.voter_cpu, None);
        assert!(plan.monitors.is_empty() && plan.captures.is_empty());
        assert_eq!(plan.priority, Some(30));
        assert_eq!(VoterPlan::from_json(&plan.to_json()).unwrap(), plan);
    }
}
