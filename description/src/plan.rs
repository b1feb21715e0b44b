//! The validated system: what runs, how, and which channel each port is on. Built by
//! [`crate::description`], run by bootstrap (`s3res_bootstrap::run`) and printed by `--check`.

use std::fmt::{self, Write as _};
use std::path::PathBuf;

use s3res_protocol::plan::{
    CapturePlan, CpuIdle, Framing, LockMemory, Mode, MonitorPlan, RoundTrigger,
};
use s3res_protocol::sched::Schedule;
use serde::Deserialize;

/// Replication level of a component, as written in the description.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Redundancy {
    /// No voter: the component runs directly.
    #[default]
    None,
    Smr,
    Dmr,
    Tmr,
}

impl Redundancy {
    /// Replica count the level implies (0: unprotected).
    pub fn default_replicas(self) -> usize {
        match self {
            Redundancy::None => 0,
            Redundancy::Smr => 1,
            Redundancy::Dmr => 2,
            Redundancy::Tmr => 3,
        }
    }
}

impl fmt::Display for Redundancy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Redundancy::None => "none",
            Redundancy::Smr => "smr",
            Redundancy::Dmr => "dmr",
            Redundancy::Tmr => "tmr",
        })
    }
}

/// One end of a channel.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Endpoint {
    /// bootstrap's own standard input (only as a `from`).
    Stdin,
    /// bootstrap's own standard output (only as a `to`).
    Stdout,
    Port {
        component: String,
        port: String,
    },
}

impl fmt::Display for Endpoint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Endpoint::Stdin => f.write_str("stdin"),
            Endpoint::Stdout => f.write_str("stdout"),
            Endpoint::Port { component, port } => write!(f, "{component}.{port}"),
        }
    }
}

/// A channel: one pipe (or bootstrap's stdin/stdout), one writer, one reader.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelPlan {
    pub from: Endpoint,
    pub to: Endpoint,
    pub max_frame: usize,
}

/// A port of a component and the channel it is on.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PortPlan {
    pub name: String,
    /// Index into [`SystemPlan::channels`]; `None` only for a declared output that no channel
    /// reads, whose frames go to /dev/null.
    pub channel: Option<usize>,
    pub max_frame: usize,
}

/// How one component runs.
#[derive(Debug, Clone, PartialEq)]
pub struct ComponentPlan {
    pub name: String,
    /// Absolute path of the component executable.
    pub exec: PathBuf,
    pub args: Vec<String>,
    pub redundancy: Redundancy,
    /// Number of replicas under a voter; 0 for an unprotected component.
    pub replicas: usize,
    /// Round deadline in microseconds; 0 for an unprotected component.
    pub timeout_us: u64,
    pub restart_timeout_ms: u64,
    pub start_timeout_ms: u64,
    /// The restart budget: replicas started by exec within `restart_window_ms`.
    pub max_restarts: u32,
    pub restart_window_ms: u64,
    /// SCHED_RR priority: of the component, or of the voter (replicas run below it).
    pub priority: Option<u8>,
    /// CPUs: the component's mask, or the CPUs the replicas are spread over.
    pub cpus: Vec<usize>,
    /// The voter's own CPU (protected components only).
    pub voter_cpu: Option<usize>,
    /// How a round is scheduled (resolved from `auto` where it was not given).
    pub schedule: Schedule,
    /// `schedule` was chosen by `auto` from the placement.
    pub schedule_auto: bool,
    pub inputs: Vec<PortPlan>,
    pub outputs: Vec<PortPlan>,
    /// Explicit round triggers (empty for an unprotected component and in stream mode).
    pub rounds: Vec<RoundTrigger>,
    /// How its voter votes (meaningful for a protected component only).
    pub mode: Mode,
    /// Stream mode: frames a replica may run ahead of the slowest.
    pub window: usize,
    /// Outputs watched by anomaly detectors (from the channels' `fields` and `detector`).
    pub monitors: Vec<MonitorPlan>,
    /// Outputs whose voted frames are captured to a file (the channels' `capture`).
    pub captures: Vec<CapturePlan>,
    /// How the replicas' stdin/stdout or ports are framed.
    pub framing: Framing,
    /// What each replica keeps locked in memory.
    pub lock_memory: LockMemory,
    /// Whether idle CPUs may sleep while the voter runs.
    pub cpu_idle: CpuIdle,
    /// How long the voter may spin for an answer from replicas on other CPUs, µs.
    pub spin_us: u32,
    /// An unmodified program: the library put in its `LD_PRELOAD`.
    pub preload: Option<PathBuf>,
}

impl ComponentPlan {
    pub fn is_protected(&self) -> bool {
        self.replicas > 0
    }

    /// Whether its voter spins for its replicas' answers (`voter/src/spin.rs`): a reactive
    /// voter with a CPU none of its replicas runs on, and `spin_us` above 0.
    pub fn voter_spins(&self) -> bool {
        self.is_protected()
            && self.mode == Mode::Reactive
            && self.spin_us > 0
            && s3res_protocol::sched::voter_apart(&self.cpus, self.voter_cpu)
    }
}

/// The whole validated system.
#[derive(Debug, Clone, PartialEq)]
pub struct SystemPlan {
    pub name: String,
    /// In the order of the description.
    pub components: Vec<ComponentPlan>,
    pub channels: Vec<ChannelPlan>,
    /// Things accepted but ignored (e.g. `timeout_us` on an unprotected component).
    pub warnings: Vec<String>,
    /// Faults injected while the system runs, if the description asks for them.
    pub inject: Option<InjectPlan>,
    /// Default events and state files (`--events`, `--state` override), relative to the
    /// current directory.
    pub events: Option<PathBuf>,
    pub state: Option<PathBuf>,
    /// File holding the task's verdict (JSON with `ok` or `success`), written by a component.
    pub outcome: Option<PathBuf>,
}

/// `inject` of a description: an `s3res-inject storm` started beside the components.
#[derive(Debug, Clone, PartialEq)]
pub struct InjectPlan {
    /// `exec`, `sdc`, `cfe`.
    pub faults: Vec<String>,
    pub rate_hz: f64,
    pub seed: u64,
    /// Protected components to inject into.
    pub components: Vec<String>,
    /// Quiet seconds after every target runs.
    pub after_s: f64,
}

/// What `--check` says about priorities and CPUs, beside the plan: bootstrap's
/// `sched::SystemSched`, which finds out by probing the machine.
pub trait SchedLines {
    /// One line about the system as a whole, if there is something to say.
    fn headline(&self) -> Option<String>;
    /// The lines of component `index` (`c`), appended to `out`.
    fn describe(&self, index: usize, c: &ComponentPlan, out: &mut String);
}

impl SystemPlan {
    /// True if some channel ends at bootstrap's stdout: then fd 1 carries frames, and every
    /// component's own stdout is sent to stderr instead so text never mixes with frames.
    pub fn uses_stdout(&self) -> bool {
        self.channels.iter().any(|c| c.to == Endpoint::Stdout)
    }

    pub fn has_protected(&self) -> bool {
        self.components.iter().any(ComponentPlan::is_protected)
    }

    /// Readable form for `--check`. `voter` is the voter binary that would be used, if found;
    /// `sched` adds the priority and CPUs of every process.
    pub fn describe(
        &self,
        voter: Option<&std::path::Path>,
        sched: Option<&dyn SchedLines>,
    ) -> String {
        let mut out = String::new();
        let _ = writeln!(
            out,
            "system {}: {} component(s), {} channel(s)",
            self.name,
            self.components.len(),
            self.channels.len()
        );
        if let Some(line) = sched.and_then(|s| s.headline()) {
            let _ = writeln!(out, "{line}");
        }
        for (index, c) in self.components.iter().enumerate() {
            out.push('\n');
            self.describe_component(c, voter, &mut out);
            if let Some(s) = sched {
                s.describe(index, c, &mut out);
            }
        }
        if let Some(i) = &self.inject {
            let _ = writeln!(
                out,
                "\ninjector: s3res-inject storm, {} at {} Hz into {}, seed {}, from {} s after \
                 every target runs (--no-inject: none)",
                i.faults.join("/"),
                i.rate_hz,
                i.components.join(", "),
                i.seed,
                i.after_s
            );
        }
        out
    }

    fn describe_component(
        &self,
        c: &ComponentPlan,
        voter: Option<&std::path::Path>,
        out: &mut String,
    ) {
        if c.is_protected() {
            let _ = writeln!(
                out,
                "component {}: runs under s3res-voter with {} replica(s) ({})",
                c.name, c.replicas, c.redundancy
            );
            match voter {
                Some(v) => {
                    let _ = writeln!(out, "  voter     {}", v.display());
                }
                None => {
                    let _ = writeln!(out, "  voter     s3res-voter NOT FOUND");
                }
            }
        } else {
            let _ = writeln!(out, "component {}: runs directly (unprotected)", c.name);
        }
        let _ = write!(out, "  exec      {}", c.exec.display());
        for a in &c.args {
            let _ = write!(out, " {a}");
        }
        out.push('\n');
        for p in &c.inputs {
            let _ = writeln!(out, "  in  {:<8} <- {}", p.name, self.port_peer(p, true));
        }
        for p in &c.outputs {
            let _ = writeln!(out, "  out {:<8} -> {}", p.name, self.port_peer(p, false));
        }
        if c.is_protected() && c.mode == Mode::Stream {
            let _ = writeln!(
                out,
                "  stream    the k-th frame of each output is voted; a replica may run {} frame(s) ahead",
                c.window
            );
        }
        if c.is_protected() {
            for r in &c.rounds {
                let _ = writeln!(
                    out,
                    "  round     a frame on {} expects one frame on each of [{}]",
                    r.input,
                    r.outputs.join(", ")
                );
            }
            let per = match c.mode {
                Mode::Reactive => "per round",
                Mode::Stream => "for a replica behind the others",
            };
            let _ = writeln!(
                out,
                "  timeout   {} us {per}, {} ms per restart, {} ms for a fresh replica's first answer",
                c.timeout_us, c.restart_timeout_ms, c.start_timeout_ms
            );
            let _ = writeln!(
                out,
                "  budget    {} restarts by exec within {} ms, then the component has failed",
                c.max_restarts, c.restart_window_ms
            );
            for m in &c.monitors {
                let names: Vec<&str> = m.fields.fields().iter().map(|f| f.name.as_str()).collect();
                let _ = writeln!(
                    out,
                    "  detector  on {}: fields [{}], model {}",
                    m.output,
                    names.join(", "),
                    m.model.display()
                );
            }
            for cap in &c.captures {
                let _ = writeln!(
                    out,
                    "  capture   voted frames of {} -> {}",
                    cap.output,
                    cap.path.display()
                );
            }
        }
        match c.priority {
            Some(p) => {
                let _ = writeln!(out, "  priority  {p}");
            }
            None => {
                let _ = writeln!(out, "  priority  default");
            }
        }
        if c.cpus.is_empty() {
            let _ = writeln!(out, "  cpus      any");
        } else {
            let list: Vec<String> = c.cpus.iter().map(usize::to_string).collect();
            let _ = writeln!(out, "  cpus      {}", list.join(", "));
        }
    }

    /// What is on the other side of a port, e.g. `source.out (channel 0, max frame 65536 B)`.
    fn port_peer(&self, p: &PortPlan, input: bool) -> String {
        match p.channel.and_then(|i| self.channels.get(i).map(|c| (i, c))) {
            Some((i, ch)) => {
                let peer = if input { &ch.from } else { &ch.to };
                format!("{peer} (channel {i}, max frame {} B)", p.max_frame)
            }
            None => format!("/dev/null (no channel, max frame {} B)", p.max_frame),
        }
    }
}
