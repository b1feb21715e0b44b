//! The system description (JSON) and its validation into a [`SystemPlan`].
//!
//! Everything is checked before anything starts. Every error names the file, the line, and the
//! component, channel or field at fault: `echo.json:12: unknown component `ecko` in endpoint
//! `ecko.in` (channels[1].to)`. The format is documented in docs/system-description.md.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};

use serde::Deserialize;
use thiserror::Error;

use s3res_anomaly::{Field, FieldLayout, Model};
use s3res_protocol::contract::MAX_PORTS;
use s3res_protocol::frame::DEFAULT_MAX_FRAME;
use s3res_protocol::plan::{
    default_max_restarts, default_restart_timeout_ms, default_restart_window_ms,
    default_start_timeout_ms, default_stream_window, CapturePlan, CpuIdle, Framing, LockMemory,
    Mode, MonitorPlan, RoundTrigger, DEFAULT_SPIN_US, MAX_SPIN_US,
};
use s3res_protocol::sched::{self, Schedule};

use crate::exec::{self, SearchPath};
use crate::plan::{
    ChannelPlan, ComponentPlan, Endpoint, InjectPlan, PortPlan, Redundancy, SystemPlan,
};
use crate::posindex::{element_path, member_path, IndexError, PositionIndex};

/// Fault kinds a description's `inject` may mix (the signal-based ones: they need no options).
pub const INJECT_FAULTS: [&str; 3] = ["exec", "sdc", "cfe"];
/// Largest `max_frame` a channel may ask for.
pub const MAX_FRAME_LIMIT: usize = 16 * 1024 * 1024;
/// Largest replica count (`replicas`).
pub const MAX_REPLICAS: u64 = 9;
/// Largest `max_restarts`.
pub const MAX_RESTART_BUDGET: u64 = 1000;
/// Longest name of a component or a port, in characters.
pub const MAX_NAME_LEN: usize = 64;
/// Longest system name, in characters.
pub const MAX_SYSTEM_NAME_LEN: usize = 128;
/// Longest any duration in a description may be: one minute. A deadline longer than that
/// detects nothing a user would wait for (and 2^64−1 µs would never detect a spin at all).
pub const MAX_DURATION_MS: u64 = 60_000;
/// Longest `exec` or single argument, in bytes.
pub const MAX_ARG_LEN: usize = 4096;
/// Most arguments a component may have.
pub const MAX_ARGS: usize = 256;

/// Why `name` cannot name a component or a port, if it cannot: names use ASCII letters,
/// digits, `_` and `-` (they appear in endpoints `component.port`, paths, the environment and
/// logs), at most [`MAX_NAME_LEN`] of them.
pub fn name_problem(name: &str) -> Option<String> {
    if name.is_empty() {
        return Some("is empty".into());
    }
    if name.chars().count() > MAX_NAME_LEN {
        return Some(format!("is longer than {MAX_NAME_LEN} characters"));
    }
    let bad = name
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || *c == '_' || *c == '-'))?;
    Some(format!(
        "contains {bad:?}; names use ASCII letters, digits, `_` and `-`"
    ))
}

/// SCHED_RR priorities from here up compete with the kernel's interrupt threads, which run at
/// 50 by default (PREEMPT_RT).
pub const INTERRUPT_THREAD_PRIORITY: u8 = 50;

/// Why a description was refused.
#[derive(Debug, Error)]
pub enum DescriptionError {
    #[error("{file}: cannot read the description: {source}")]
    Read {
        file: String,
        source: std::io::Error,
    },
    #[error("{file}:{line}: {what} ({subject})")]
    Invalid {
        file: String,
        line: usize,
        /// What is wrong.
        what: String,
        /// The component, channel or field at fault, as a path (`channels[1].to`).
        subject: String,
    },
}

impl DescriptionError {
    /// Line of the fault (0 when the file could not be read).
    pub fn line(&self) -> usize {
        match self {
            DescriptionError::Read { .. } => 0,
            DescriptionError::Invalid { line, .. } => *line,
        }
    }
}

/// What validation needs to know about the machine and the file's location.
#[derive(Debug, Clone)]
pub struct HostContext {
    /// Folder of the description: relative `exec` paths start here.
    pub base_dir: PathBuf,
    /// Where bare `exec` names are looked for.
    pub search: SearchPath,
    /// CPUs this process may run on (its `sched_getaffinity` mask).
    pub cpus: Vec<usize>,
}

impl HostContext {
    /// The context for a description file on this machine.
    pub fn for_file(path: &Path) -> Self {
        let abs = exec::absolute(path);
        HostContext {
            base_dir: abs
                .parent()
                .map_or_else(|| PathBuf::from("/"), Path::to_path_buf),
            search: SearchPath::from_environment(),
            cpus: usable_cpus(),
        }
    }
}

/// The CPUs in this process's affinity mask (what `cpus` may name).
pub fn usable_cpus() -> Vec<usize> {
    use nix::sched::{sched_getaffinity, CpuSet};
    use nix::unistd::Pid;
    match sched_getaffinity(Pid::from_raw(0)) {
        Ok(set) => (0..CpuSet::count())
            .filter(|&i| set.is_set(i).unwrap_or(false))
            .collect(),
        // Without a mask, fall back to what the kernel says is online.
        Err(_) => std::fs::read_to_string("/sys/devices/system/cpu/online")
            .map(|s| parse_cpu_list(&s))
            .unwrap_or_default(),
    }
}

/// Parses the kernel's CPU list format (`0-3,6,8-9`).
pub fn parse_cpu_list(s: &str) -> Vec<usize> {
    let mut out = Vec::new();
    for part in s.trim().split(',').filter(|p| !p.is_empty()) {
        match part.split_once('-') {
            Some((a, b)) => {
                if let (Ok(a), Ok(b)) = (a.parse::<usize>(), b.parse::<usize>()) {
                    out.extend(a..=b);
                }
            }
            None => out.extend(part.parse::<usize>().ok()),
        }
    }
    out
}

/// Reads and validates the description at `path`. `label` is how the file is named in errors
/// (usually the path as the user typed it).
pub fn load(path: &Path, ctx: &HostContext) -> Result<SystemPlan, DescriptionError> {
    let label = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| DescriptionError::Read {
        file: label.clone(),
        source,
    })?;
    parse(&label, &text, ctx)
}

/// Validates description `text`; `file` names it in errors.
pub fn parse(file: &str, text: &str, ctx: &HostContext) -> Result<SystemPlan, DescriptionError> {
    // 1. Syntax, as serde_json sees it (its messages and positions are good).
    if let Err(e) = serde_json::from_str::<serde_json::Value>(text) {
        return Err(DescriptionError::Invalid {
            file: file.to_owned(),
            line: e.line().max(1),
            what: format!(
                "malformed JSON: {} at column {}",
                strip_position(&e),
                e.column()
            ),
            subject: "JSON syntax".to_owned(),
        });
    }
    // 2. Positions, and the duplicate keys serde_json would silently merge.
    let index = PositionIndex::build(text).map_err(|e| {
        let (what, subject) = match &e {
            IndexError::DuplicateKey { key, path, .. } => (
                if path.starts_with("components.") && path.matches('.').count() == 1 {
                    format!("duplicate component name `{key}`")
                } else {
                    format!("duplicate key `{key}`")
                },
                path.clone(),
            ),
            IndexError::Syntax { what, .. } => {
                (format!("malformed JSON: {what}"), "JSON syntax".to_owned())
            }
        };
        DescriptionError::Invalid {
            file: file.to_owned(),
            line: e.line(),
            what,
            subject,
        }
    })?;
    // 3. Shape: fields, types, enum values, unknown fields.
    let mut de = serde_json::Deserializer::from_str(text);
    let desc: SystemDesc = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let subject = if path == "." {
            "top level".to_owned()
        } else {
            path.clone()
        };
        // serde_json's line is where it stopped reading; for a missing field that is the
        // object's closing brace, so prefer where the path itself starts when it is known.
        let line = index.line(&path).unwrap_or_else(|| inner.line().max(1));
        DescriptionError::Invalid {
            file: file.to_owned(),
            line,
            what: strip_position(&inner),
            subject,
        }
    })?;
    // 4. Meaning.
    Checker {
        file,
        index: &index,
        ctx,
    }
    .check(desc)
}

/// serde_json's message without its " at line L column C" tail (we print our own position).
fn strip_position(e: &serde_json::Error) -> String {
    let s = e.to_string();
    match s.rfind(" at line ") {
        Some(cut) => s[..cut].to_owned(),
        None => s,
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct SystemDesc {
    name: String,
    components: BTreeMap<String, ComponentDesc>,
    #[serde(default)]
    channels: Vec<ChannelDesc>,
    /// Faults injected while the system runs (an `s3res-inject storm` beside the components).
    inject: Option<InjectDesc>,
    /// Default `--events` file, relative to the current directory.
    events: Option<String>,
    /// Default `--state` file, relative to the current directory.
    state: Option<String>,
    /// The file a component writes its task's verdict to (JSON with `ok` or `success`),
    /// relative to the current directory; bootstrap's verdict shows it.
    outcome: Option<String>,
}

/// `inject`: what the injector started beside the components does.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct InjectDesc {
    /// Kinds mixed, each equally likely (default exec, sdc, cfe).
    faults: Option<Vec<String>>,
    /// Injections per second (default 2).
    rate_hz: Option<f64>,
    /// Seed of every random choice (default 1).
    seed: Option<u64>,
    /// Targets (default: every protected component).
    components: Option<Vec<String>>,
    /// Seconds of quiet after every target runs (default 1).
    after_s: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ComponentDesc {
    exec: String,
    #[serde(default)]
    args: Vec<String>,
    #[serde(default)]
    redundancy: Redundancy,
    replicas: Option<u64>,
    #[serde(default)]
    mode: Mode,
    /// Stream mode: how many frames a replica may run ahead of the slowest.
    window: Option<u64>,
    timeout_us: Option<u64>,
    // Signed, so that `-1` gets our range message rather than a type error.
    priority: Option<i64>,
    cpus: Option<Vec<u64>>,
    voter_cpu: Option<u64>,
    schedule: Option<ScheduleChoice>,
    rounds: Option<Vec<RoundDesc>>,
    restart_timeout_ms: Option<u64>,
    start_timeout_ms: Option<u64>,
    /// Restart budget: replicas started by exec within `restart_window_ms`.
    max_restarts: Option<u64>,
    restart_window_ms: Option<u64>,
    inputs: Option<Vec<String>>,
    outputs: Option<Vec<String>>,
    /// How the program takes part: it links replica-rt (or the C library), or it is an
    /// unmodified program that the preload library is injected into.
    runtime: Option<RuntimeChoice>,
    /// An unmodified program's stdin/stdout: lines (the default) or s3res frames.
    framing: Option<Framing>,
    /// What each replica keeps locked in memory: `all` (default) or `used`.
    lock_memory: Option<LockMemory>,
    /// Whether idle CPUs may sleep while the voter runs: `halt` (default) or `poll`.
    cpu_idle: Option<CpuIdle>,
    /// How long the voter may spin for an answer from replicas on other CPUs before it
    /// sleeps, µs (0: never).
    spin_us: Option<u64>,
}

/// `runtime` as written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
enum RuntimeChoice {
    /// The program links replica-rt (Rust) or libs3res (C, C++): ports on fd 3, 4, ...
    #[serde(rename = "replica-rt")]
    ReplicaRt,
    /// An unmodified program reading stdin and writing stdout; the voter puts the preload
    /// library in its `LD_PRELOAD`.
    #[serde(rename = "preload")]
    Preload,
}

/// The ports of an unmodified program: its stdin and its stdout.
const PRELOAD_INPUT: &str = "in";
const PRELOAD_OUTPUT: &str = "out";

/// `schedule` as written: `auto` resolves from the placement ([`sched::choose`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
enum ScheduleChoice {
    Auto,
    Parallel,
    Sequential,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RoundDesc {
    input: String,
    /// Absent: every output of the component.
    outputs: Option<Vec<String>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ChannelDesc {
    from: String,
    to: String,
    max_frame: Option<u64>,
    /// The numeric fields of the channel's frames worth watching.
    fields: Option<Vec<Field>>,
    /// The anomaly detector the writer's voter runs on them.
    detector: Option<DetectorDesc>,
    /// File (relative to the description) to write the voted frames to.
    capture: Option<String>,
}

/// `detector` of a channel.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct DetectorDesc {
    /// Model file from `s3res-train`, relative to the description.
    model: String,
    /// If given, the model must be of this kind.
    kind: Option<DetectorKind>,
    /// Gaussian: alarm above this many σ (replaces the model's).
    sigma: Option<f64>,
    /// Autoencoder: alarm above this reconstruction error (replaces the model's).
    threshold: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
enum DetectorKind {
    Gaussian,
    Autoencoder,
}

/// Per-component facts gathered before the ports are known.
struct Draft {
    name: String,
    desc: ComponentDesc,
    exec: PathBuf,
    replicas: usize,
    timeout_us: u64,
    priority: Option<u8>,
    cpus: Vec<usize>,
    voter_cpu: Option<usize>,
    schedule: Schedule,
    schedule_auto: bool,
    window: usize,
    framing: Framing,
    /// The preload library, for an unmodified program.
    preload: Option<PathBuf>,
}

/// Largest stream window: frames are buffered per replica and output, so keep it sane.
const MAX_STREAM_WINDOW: u64 = 65_536;

/// A port as the channels use it: which channel, and where that was written.
#[derive(Debug, Clone)]
struct PortUse {
    channel: usize,
    /// Path of the endpoint field (`channels[2].to`).
    path: String,
}

struct Checker<'a> {
    file: &'a str,
    index: &'a PositionIndex,
    ctx: &'a HostContext,
}

impl Checker<'_> {
    fn err(&self, path: &str, what: impl Into<String>) -> DescriptionError {
        DescriptionError::Invalid {
            file: self.file.to_owned(),
            line: self.index.line_or_parent(path),
            what: what.into(),
            subject: path.to_owned(),
        }
    }

    fn check(&self, desc: SystemDesc) -> Result<SystemPlan, DescriptionError> {
        let mut warnings = Vec::new();
        if desc.name.trim().is_empty() {
            return Err(self.err("name", "the system name is empty"));
        }
        if desc.name.chars().count() > MAX_SYSTEM_NAME_LEN {
            return Err(self.err(
                "name",
                format!("the system name is longer than {MAX_SYSTEM_NAME_LEN} characters"),
            ));
        }
        if let Some(c) = desc.name.chars().find(|c| c.is_control()) {
            return Err(self.err(
                "name",
                format!("the system name contains the control character {c:?}"),
            ));
        }
        if desc.components.is_empty() {
            return Err(self.err("components", "a system needs at least one component"));
        }

        // Components in document order (the map is sorted; the index remembers the order).
        let mut by_name = desc.components;
        let mut order: Vec<String> = self
            .index
            .keys("components")
            .iter()
            .filter(|k| by_name.contains_key(*k))
            .cloned()
            .collect();
        for k in by_name.keys() {
            if !order.contains(k) {
                order.push(k.clone());
            }
        }
        let mut drafts = Vec::with_capacity(order.len());
        for name in order {
            if let Some(desc) = by_name.remove(&name) {
                drafts.push(self.check_component(name, desc, &mut warnings)?);
            }
        }

        let (channels, inputs_used, outputs_used) = self.check_channels(&desc.channels, &drafts)?;

        let mut components = Vec::with_capacity(drafts.len());
        for d in drafts {
            components.push(self.check_ports(d, &channels, &inputs_used, &outputs_used)?);
        }
        for (i, ch) in desc.channels.iter().enumerate() {
            self.check_monitoring(i, ch, &channels[i], &mut components)?;
        }
        self.check_rounds_can_start(&components, &channels)?;
        let inject = match &desc.inject {
            Some(i) => Some(self.check_inject(i, &components)?),
            None => None,
        };
        let path_of = |field: &str, v: &Option<String>| match v.as_deref() {
            Some("") => Err(self.err(field, "an empty path")),
            Some(p) => {
                let path = PathBuf::from(p);
                let example = format!(
                    "{field}.{}",
                    if field == "events" { "jsonl" } else { "json" }
                );
                match crate::exec::not_a_file_path(&path, &example) {
                    Some(why) => Err(self.err(field, why)),
                    None => Ok(Some(path)),
                }
            }
            None => Ok(None),
        };
        Ok(SystemPlan {
            name: desc.name,
            components,
            channels,
            warnings,
            inject,
            events: path_of("events", &desc.events)?,
            state: path_of("state", &desc.state)?,
            outcome: path_of("outcome", &desc.outcome)?,
        })
    }

    fn check_inject(
        &self,
        i: &InjectDesc,
        components: &[ComponentPlan],
    ) -> Result<InjectPlan, DescriptionError> {
        let faults = i
            .faults
            .clone()
            .unwrap_or_else(|| INJECT_FAULTS.iter().map(|f| f.to_string()).collect());
        if faults.is_empty() {
            return Err(self.err(
                "inject.faults",
                "no fault kind (give e.g. [\"exec\", \"sdc\"])",
            ));
        }
        for (k, f) in faults.iter().enumerate() {
            if !INJECT_FAULTS.contains(&f.as_str()) {
                return Err(self.err(
                    &format!("inject.faults[{k}]"),
                    format!(
                        "unknown fault kind `{f}` (known: {})",
                        INJECT_FAULTS.join(", ")
                    ),
                ));
            }
        }
        let rate_hz = i.rate_hz.unwrap_or(2.0);
        s3res_protocol::campaign::check_rate(rate_hz)
            .map_err(|e| self.err("inject.rate_hz", e.to_string()))?;
        let after_s = i.after_s.unwrap_or(1.0);
        if !(after_s.is_finite() && after_s >= 0.0) {
            return Err(self.err(
                "inject.after_s",
                format!("{after_s} is not a number of seconds"),
            ));
        }
        let protected: Vec<&str> = components
            .iter()
            .filter(|c| c.is_protected())
            .map(|c| c.name.as_str())
            .collect();
        let targets = match &i.components {
            Some(list) => {
                for (k, c) in list.iter().enumerate() {
                    if !protected.contains(&c.as_str()) {
                        return Err(self.err(
                            &format!("inject.components[{k}]"),
                            format!(
                                "`{c}` is not a protected component (protected: {})",
                                protected.join(", ")
                            ),
                        ));
                    }
                }
                list.clone()
            }
            None => protected.iter().map(|c| c.to_string()).collect(),
        };
        if targets.is_empty() {
            return Err(self.err(
                "inject",
                "the system has no protected component to inject into",
            ));
        }
        Ok(InjectPlan {
            faults,
            rate_hz,
            seed: i.seed.unwrap_or(1),
            components: targets,
            after_s,
        })
    }

    /// Every reactive protected component can be given a round. Its replicas answer only in
    /// rounds, so it sends nothing until a frame arrives on an input that starts one; a loop of
    /// such components that nothing outside feeds would wait for each other forever. A
    /// component sends on its own when it is unprotected or in stream mode, or once one of its
    /// round inputs is fed by stdin or by a component that sends.
    fn check_rounds_can_start(
        &self,
        components: &[ComponentPlan],
        channels: &[ChannelPlan],
    ) -> Result<(), DescriptionError> {
        let waits =
            |c: &ComponentPlan| c.redundancy != Redundancy::None && c.mode == Mode::Reactive;
        let mut sends: HashSet<&str> = components
            .iter()
            .filter(|c| !waits(c))
            .map(|c| c.name.as_str())
            .collect();
        loop {
            let before = sends.len();
            for c in components.iter().filter(|c| waits(c)) {
                let fed = c.rounds.iter().any(|r| {
                    channels.iter().any(|ch| {
                        matches!(&ch.to, Endpoint::Port { component, port } if *component == c.name && *port == r.input)
                            && match &ch.from {
                                Endpoint::Stdin => true,
                                Endpoint::Port { component, .. } => sends.contains(component.as_str()),
                                Endpoint::Stdout => false,
                            }
                    })
                });
                if fed {
                    sends.insert(&c.name);
                }
            }
            if sends.len() == before {
                break;
            }
        }
        let stuck: Vec<&str> = components
            .iter()
            .map(|c| c.name.as_str())
            .filter(|n| !sends.contains(n))
            .collect();
        let Some(first) = stuck.first() else {
            return Ok(());
        };
        Err(self.err(
            &member_path("components", first),
            format!(
                "reactive component{} {} can never start a round: {} fed only by reactive components that wait for {} in turn; a loop needs a component that sends on its own (unprotected, \"mode\": \"stream\", or fed from stdin)",
                if stuck.len() > 1 { "s" } else { "" },
                stuck.iter().map(|n| format!("`{n}`")).collect::<Vec<_>>().join(", "),
                if stuck.len() > 1 { "their round inputs are" } else { "its round inputs are" },
                if stuck.len() > 1 { "them" } else { "it" },
            ),
        ))
    }

    /// `exec` and `args`: no NUL byte (it cannot be passed to a program), bounded lengths.
    fn check_command(&self, at: &str, desc: &ComponentDesc) -> Result<(), DescriptionError> {
        let field = |f: &str| member_path(at, f);
        if desc.args.len() > MAX_ARGS {
            return Err(self.err(
                &field("args"),
                format!("{} arguments; at most {MAX_ARGS}", desc.args.len()),
            ));
        }
        let strings = std::iter::once((field("exec"), &desc.exec)).chain(
            desc.args
                .iter()
                .enumerate()
                .map(|(i, a)| (element_path(&field("args"), i), a)),
        );
        for (path, s) in strings {
            if s.contains('\0') {
                return Err(self.err(&path, "contains a NUL byte, which no program can be given"));
            }
            if s.len() > MAX_ARG_LEN {
                return Err(self.err(
                    &path,
                    format!("is {} bytes long; at most {MAX_ARG_LEN}", s.len()),
                ));
            }
        }
        Ok(())
    }

    fn check_component(
        &self,
        name: String,
        desc: ComponentDesc,
        warnings: &mut Vec<String>,
    ) -> Result<Draft, DescriptionError> {
        let at = member_path("components", &name);
        let field = |f: &str| member_path(&at, f);
        if name.is_empty() {
            return Err(self.err(&at, "a component name is empty"));
        }
        if let Some(problem) = name_problem(&name) {
            return Err(self.err(&at, format!("component name {name:?} {problem}")));
        }
        self.check_command(&at, &desc)?;
        if name == "stdin" || name == "stdout" {
            return Err(self.err(
                &at,
                format!(
                    "`{name}` is reserved for bootstrap's own {name} and cannot name a component"
                ),
            ));
        }
        let protected = desc.redundancy != Redundancy::None;
        let replicas =
            match desc.replicas {
                Some(_) if !protected => return Err(self.err(
                    &field("replicas"),
                    "`replicas` needs a redundancy of smr, dmr or tmr (this component has none)",
                )),
                Some(n) if !(1..=MAX_REPLICAS).contains(&n) => {
                    return Err(self.err(
                        &field("replicas"),
                        format!("replicas {n} is outside 1..={MAX_REPLICAS}"),
                    ))
                }
                Some(n) => n as usize,
                None => desc.redundancy.default_replicas(),
            };

        let timeout_us = if protected {
            match desc.timeout_us {
                None => {
                    return Err(self.err(
                        &at,
                        format!(
                            "`timeout_us` is required for a protected component (redundancy {})",
                            desc.redundancy
                        ),
                    ))
                }
                Some(0) => {
                    return Err(self.err(&field("timeout_us"), "timeout_us must be more than 0"))
                }
                Some(t) if t > MAX_DURATION_MS * 1000 => {
                    return Err(self.err(
                        &field("timeout_us"),
                        format!(
                            "timeout_us {t} is above {} (one minute, the longest deadline)",
                            MAX_DURATION_MS * 1000
                        ),
                    ))
                }
                Some(t) => t,
            }
        } else {
            for (present, what) in [
                (desc.timeout_us.is_some(), "timeout_us"),
                (desc.rounds.is_some(), "rounds"),
                (desc.restart_timeout_ms.is_some(), "restart_timeout_ms"),
                (desc.start_timeout_ms.is_some(), "start_timeout_ms"),
                (desc.max_restarts.is_some(), "max_restarts"),
                (desc.restart_window_ms.is_some(), "restart_window_ms"),
            ] {
                if present {
                    warnings.push(format!(
                        "component {name}: `{what}` is ignored without redundancy"
                    ));
                }
            }
            0
        };
        if desc.restart_timeout_ms == Some(0) {
            return Err(self.err(
                &field("restart_timeout_ms"),
                "restart_timeout_ms must be more than 0",
            ));
        }
        if desc.start_timeout_ms == Some(0) {
            return Err(self.err(
                &field("start_timeout_ms"),
                "start_timeout_ms must be more than 0",
            ));
        }
        if let Some(n) = desc
            .max_restarts
            .filter(|n| !(1..=MAX_RESTART_BUDGET).contains(n))
        {
            return Err(self.err(
                &field("max_restarts"),
                format!("max_restarts {n} is outside 1..={MAX_RESTART_BUDGET}"),
            ));
        }
        if desc.restart_window_ms == Some(0) {
            return Err(self.err(
                &field("restart_window_ms"),
                "restart_window_ms must be more than 0",
            ));
        }
        for (value, what) in [
            (desc.restart_timeout_ms, "restart_timeout_ms"),
            (desc.start_timeout_ms, "start_timeout_ms"),
            (desc.restart_window_ms, "restart_window_ms"),
        ] {
            if let Some(ms) = value.filter(|&ms| ms > MAX_DURATION_MS) {
                return Err(self.err(
                    &field(what),
                    format!("{what} {ms} is above {MAX_DURATION_MS} (one minute)"),
                ));
            }
        }
        let window = self.stream_window(&name, &desc, protected, warnings)?;

        let priority = match desc.priority {
            None => None,
            Some(p) if (1..=99).contains(&p) => Some(p as u8),
            Some(p) => {
                return Err(self.err(
                    &field("priority"),
                    format!("priority {p} is outside 1..=99"),
                ))
            }
        };
        if let Some(p) = priority {
            let least = sched::min_priority(replicas);
            if protected && p < least {
                return Err(self.err(
                    &field("priority"),
                    format!(
                        "priority {p} is too low for {replicas} replica(s): the voter runs at the \
                         priority, the replica whose turn it is one below, and each replica below \
                         that at its own level, so it must be at least {least}"
                    ),
                ));
            }
            if p >= INTERRUPT_THREAD_PRIORITY {
                warnings.push(format!(
                    "component {name}: priority {p} is at or above {INTERRUPT_THREAD_PRIORITY}, \
                     where the kernel's interrupt threads run by default: a busy component there \
                     can delay interrupt handling; keep components below {INTERRUPT_THREAD_PRIORITY} \
                     unless that is what you want"
                ));
            }
        }

        let mut cpus = Vec::new();
        for (i, &cpu) in desc.cpus.iter().flatten().enumerate() {
            let path = element_path(&field("cpus"), i);
            let cpu = self.usable_cpu(&path, cpu)?;
            if cpus.contains(&cpu) {
                return Err(self.err(&path, format!("CPU {cpu} is listed twice")));
            }
            cpus.push(cpu);
        }
        let voter_cpu = match desc.voter_cpu {
            Some(cpu) => Some(self.usable_cpu(&field("voter_cpu"), cpu)?),
            None => None,
        };

        if let Some(us) = desc.spin_us.filter(|&us| us > u64::from(MAX_SPIN_US)) {
            return Err(self.err(
                &field("spin_us"),
                format!(
                    "spin_us {us} is above {MAX_SPIN_US}: a voter spinning longer than that \
                     only holds its CPU (0 turns the spin off)"
                ),
            ));
        }
        if protected && desc.spin_us.is_some_and(|us| us > 0) {
            if desc.mode == Mode::Stream {
                warnings.push(format!(
                    "component {name}: `spin_us` has no effect in stream mode (only a reactive \
                     voter spins for its replicas' answers)"
                ));
            } else if !sched::voter_apart(&cpus, voter_cpu) {
                warnings.push(format!(
                    "component {name}: `spin_us` has no effect unless `voter_cpu` is a CPU \
                     apart from the replicas' `cpus` (the voter spins only for answers from \
                     other CPUs)"
                ));
            }
        }

        let choice = desc.schedule.unwrap_or(ScheduleChoice::Auto);
        let schedule = match choice {
            ScheduleChoice::Auto => sched::choose(replicas, &cpus),
            ScheduleChoice::Parallel => Schedule::Parallel,
            ScheduleChoice::Sequential => Schedule::Sequential,
        };
        if protected {
            if choice == ScheduleChoice::Parallel && sched::replicas_share_a_cpu(replicas, &cpus) {
                warnings.push(format!(
                    "component {name}: `schedule: parallel` with {replicas} replicas on {} CPU(s): \
                     replicas sharing a CPU share one deadline, so a hang may be blamed on a \
                     replica that was only waiting for the CPU; `sequential` (or `auto`) times \
                     each replica on its own",
                    cpus.len()
                ));
            }
        } else {
            for (present, what) in [
                (desc.schedule.is_some(), "schedule"),
                (desc.voter_cpu.is_some(), "voter_cpu"),
                (desc.lock_memory.is_some(), "lock_memory"),
                (desc.cpu_idle.is_some(), "cpu_idle"),
                (desc.spin_us.is_some(), "spin_us"),
            ] {
                if present {
                    warnings.push(format!(
                        "component {name}: `{what}` is ignored without redundancy"
                    ));
                }
            }
        }

        let exec = exec::resolve(&desc.exec, &self.ctx.base_dir, &self.ctx.search)
            .map_err(|what| self.err(&field("exec"), what))?;
        let (framing, preload) = self.check_runtime(&at, &desc, &exec, protected)?;
        if preload.is_some() && desc.lock_memory.is_some() {
            warnings.push(format!(
                "component {name}: `lock_memory` is ignored for an unmodified program (the \
                 preload library does not lock its memory)"
            ));
        }

        Ok(Draft {
            name,
            desc,
            exec,
            replicas,
            timeout_us,
            priority,
            cpus,
            voter_cpu,
            schedule,
            schedule_auto: choice == ScheduleChoice::Auto,
            window,
            framing,
            preload,
        })
    }

    /// `runtime` and `framing`: for an unmodified program, its framing and the preload library
    /// (found now, so that `--check` reports a missing one).
    fn check_runtime(
        &self,
        at: &str,
        desc: &ComponentDesc,
        exec: &Path,
        protected: bool,
    ) -> Result<(Framing, Option<PathBuf>), DescriptionError> {
        let field = |f: &str| member_path(at, f);
        if desc.runtime != Some(RuntimeChoice::Preload) {
            if desc.framing == Some(Framing::Lines) {
                return Err(self.err(
                    &field("framing"),
                    "`framing: lines` is for an unmodified program: add `\"runtime\": \"preload\"`",
                ));
            }
            return Ok((Framing::Frames, None));
        }
        if !protected {
            return Err(self.err(
                &field("runtime"),
                "`runtime: preload` needs a voter to frame and vote the program's lines: give \
                 the component a redundancy (smr, dmr or tmr)",
            ));
        }
        if desc.mode == Mode::Stream {
            return Err(self.err(
                &field("mode"),
                "an unmodified program (`runtime: preload`) is voted in rounds, one answer per \
                 input frame; stream mode is not supported for it yet",
            ));
        }
        if let Some(problem) = exec::preload_problem(exec) {
            return Err(self.err(&field("exec"), problem));
        }
        let library = exec::find_preload_library().map_err(|e| self.err(&field("runtime"), e))?;
        Ok((desc.framing.unwrap_or(Framing::Lines), Some(library)))
    }

    /// `cpu` as a CPU of this machine that bootstrap may use, or an error at `path`.
    fn usable_cpu(&self, path: &str, cpu: u64) -> Result<usize, DescriptionError> {
        usize::try_from(cpu)
            .ok()
            .filter(|c| self.ctx.cpus.contains(c))
            .ok_or_else(|| {
                self.err(
                    path,
                    format!(
                        "CPU {cpu} does not exist on this machine (usable CPUs: {})",
                        cpu_list(&self.ctx.cpus)
                    ),
                )
            })
    }

    /// The stream window (frames a replica may run ahead); checks the mode-specific fields.
    fn stream_window(
        &self,
        name: &str,
        desc: &ComponentDesc,
        protected: bool,
        warnings: &mut Vec<String>,
    ) -> Result<usize, DescriptionError> {
        let field = |f: &str| member_path(&member_path("components", name), f);
        if desc.mode == Mode::Stream && protected {
            if desc.rounds.is_some() {
                return Err(self.err(
                    &field("rounds"),
                    "`rounds` belong to reactive mode; a stream component has no rounds (its outputs are voted frame by frame)",
                ));
            }
        } else if desc.window.is_some() {
            let why = if protected {
                "is for stream mode only (this component is reactive)"
            } else {
                "is ignored without redundancy"
            };
            warnings.push(format!("component {name}: `window` {why}"));
        }
        match desc.window {
            None => Ok(default_stream_window()),
            Some(w) if (1..=MAX_STREAM_WINDOW).contains(&w) => Ok(w as usize),
            Some(w) => Err(self.err(
                &field("window"),
                format!("window {w} is outside 1..={MAX_STREAM_WINDOW} frames"),
            )),
        }
    }

    /// Checks every channel; returns them with, per `(component, port)`, the channel that
    /// feeds it (inputs) or that it feeds (outputs).
    #[allow(clippy::type_complexity)]
    fn check_channels(
        &self,
        descs: &[ChannelDesc],
        drafts: &[Draft],
    ) -> Result<
        (
            Vec<ChannelPlan>,
            HashMap<(String, String), PortUse>,
            HashMap<(String, String), PortUse>,
        ),
        DescriptionError,
    > {
        let known: HashSet<&str> = drafts.iter().map(|d| d.name.as_str()).collect();
        let mut inputs: HashMap<(String, String), PortUse> = HashMap::new();
        let mut outputs: HashMap<(String, String), PortUse> = HashMap::new();
        let mut stdin_use: Option<usize> = None;
        let mut stdout_use: Option<usize> = None;
        let mut channels = Vec::with_capacity(descs.len());

        for (i, ch) in descs.iter().enumerate() {
            let at = element_path("channels", i);
            let from_path = member_path(&at, "from");
            let to_path = member_path(&at, "to");
            let from = self.endpoint(&ch.from, &from_path, &known, true)?;
            let to = self.endpoint(&ch.to, &to_path, &known, false)?;
            if from == Endpoint::Stdin && to == Endpoint::Stdout {
                return Err(self.err(
                    &at,
                    "a channel from stdin straight to stdout connects no component",
                ));
            }
            let max_frame = match ch.max_frame {
                None => DEFAULT_MAX_FRAME,
                Some(m) if m >= 1 && m <= MAX_FRAME_LIMIT as u64 => m as usize,
                Some(m) => {
                    return Err(self.err(
                        &member_path(&at, "max_frame"),
                        format!("max_frame {m} is outside 1..={MAX_FRAME_LIMIT} bytes (16 MiB)"),
                    ))
                }
            };

            match &from {
                Endpoint::Stdin => {
                    if let Some(j) = stdin_use.replace(i) {
                        return Err(self.err(
                            &from_path,
                            format!("stdin is already read by channels[{j}]; a channel has one reader and one writer"),
                        ));
                    }
                }
                Endpoint::Port { component, port } => {
                    let key = (component.clone(), port.clone());
                    if let Some(prev) = outputs.get(&key) {
                        return Err(self.err(
                            &from_path,
                            format!("output port `{component}.{port}` is already connected by channels[{}]; a pipe has one writer", prev.channel),
                        ));
                    }
                    if let Some(prev) = inputs.get(&key) {
                        return Err(self.err(
                            &from_path,
                            format!("port `{component}.{port}` is used both as an input ({}) and as an output", prev.path),
                        ));
                    }
                    outputs.insert(
                        key,
                        PortUse {
                            channel: i,
                            path: from_path.clone(),
                        },
                    );
                }
                Endpoint::Stdout => {}
            }
            match &to {
                Endpoint::Stdout => {
                    if let Some(j) = stdout_use.replace(i) {
                        return Err(self.err(
                            &to_path,
                            format!("stdout is already written by channels[{j}]; frames of two writers would mix"),
                        ));
                    }
                }
                Endpoint::Port { component, port } => {
                    let key = (component.clone(), port.clone());
                    if let Some(prev) = inputs.get(&key) {
                        return Err(self.err(
                            &to_path,
                            format!("input port `{component}.{port}` is already connected by channels[{}]; a pipe has one reader", prev.channel),
                        ));
                    }
                    if let Some(prev) = outputs.get(&key) {
                        return Err(self.err(
                            &to_path,
                            format!("port `{component}.{port}` is used both as an output ({}) and as an input", prev.path),
                        ));
                    }
                    inputs.insert(
                        key,
                        PortUse {
                            channel: i,
                            path: to_path.clone(),
                        },
                    );
                }
                Endpoint::Stdin => {}
            }
            channels.push(ChannelPlan {
                from,
                to,
                max_frame,
            });
        }
        Ok((channels, inputs, outputs))
    }

    fn endpoint(
        &self,
        text: &str,
        path: &str,
        known: &HashSet<&str>,
        is_from: bool,
    ) -> Result<Endpoint, DescriptionError> {
        match (text, is_from) {
            ("stdin", true) => return Ok(Endpoint::Stdin),
            ("stdout", false) => return Ok(Endpoint::Stdout),
            ("stdin", false) => {
                return Err(self.err(
                    path,
                    "`stdin` can only be a channel's `from` (it is bootstrap's input)",
                ))
            }
            ("stdout", true) => {
                return Err(self.err(
                    path,
                    "`stdout` can only be a channel's `to` (it is bootstrap's output)",
                ))
            }
            _ => {}
        }
        let Some((component, port)) = text.split_once('.') else {
            return Err(self.err(
                path,
                format!("endpoint `{text}` must be `component.port`, `stdin` or `stdout`"),
            ));
        };
        if !known.contains(component) {
            return Err(self.err(
                path,
                format!("unknown component `{component}` in endpoint `{text}`"),
            ));
        }
        if let Some(problem) = name_problem(port) {
            return Err(self.err(
                path,
                format!("the port name in endpoint {text:?} {problem}"),
            ));
        }
        Ok(Endpoint::Port {
            component: component.to_owned(),
            port: port.to_owned(),
        })
    }

    fn check_ports(
        &self,
        d: Draft,
        channels: &[ChannelPlan],
        inputs_used: &HashMap<(String, String), PortUse>,
        outputs_used: &HashMap<(String, String), PortUse>,
    ) -> Result<ComponentPlan, DescriptionError> {
        let at = member_path("components", &d.name);
        let used_in = ports_of(&d.name, inputs_used);
        let used_out = ports_of(&d.name, outputs_used);

        // An unmodified program has exactly its stdin and its stdout.
        let stdin_port = [PRELOAD_INPUT.to_owned()];
        let stdout_port = [PRELOAD_OUTPUT.to_owned()];
        let (declared_in, declared_out) = if d.preload.is_some() {
            for (field, declared, only) in [
                ("inputs", &d.desc.inputs, PRELOAD_INPUT),
                ("outputs", &d.desc.outputs, PRELOAD_OUTPUT),
            ] {
                if declared.as_ref().is_some_and(|l| l != &[only.to_owned()]) {
                    return Err(self.err(
                        &member_path(&at, field),
                        format!(
                            "an unmodified program (`runtime: preload`) has one input, \
                             `{PRELOAD_INPUT}` (its stdin), and one output, `{PRELOAD_OUTPUT}` \
                             (its stdout); `{field}` must be [\"{only}\"] or left out"
                        ),
                    ));
                }
            }
            (Some(&stdin_port[..]), Some(&stdout_port[..]))
        } else {
            (d.desc.inputs.as_deref(), d.desc.outputs.as_deref())
        };
        let inputs = self.port_list(&d, "inputs", declared_in, &used_in, channels, true)?;
        let outputs = self.port_list(&d, "outputs", declared_out, &used_out, channels, false)?;
        if let Some(declared) = &d.desc.outputs {
            for (k, name) in declared.iter().enumerate() {
                if inputs.iter().any(|p| &p.name == name) {
                    return Err(self.err(
                        &element_path(&member_path(&at, "outputs"), k),
                        format!(
                            "port `{name}` of component `{}` is both an input and an output",
                            d.name
                        ),
                    ));
                }
            }
        }
        let total = inputs.len() + outputs.len();
        if total > MAX_PORTS {
            return Err(self.err(
                &at,
                format!(
                    "component `{}` has {total} ports, more than the limit of {MAX_PORTS}",
                    d.name
                ),
            ));
        }

        let rounds = if d.replicas > 0 && d.desc.mode == Mode::Stream {
            if inputs.is_empty() {
                // The voter ends a stream component when its input ends; one that produces
                // output on its own would be cut off (and its replicas' normal exit taken
                // for crashes).
                return Err(self.err(
                    &member_path(&member_path("components", &d.name), "mode"),
                    format!(
                        "protected stream component `{}` has no input; stream mode needs one (components that produce output on their own are not supported yet)",
                        d.name
                    ),
                ));
            }
            Vec::new()
        } else if d.replicas > 0 {
            let rounds = self.rounds(&d, &inputs, &outputs)?;
            if rounds.is_empty() {
                // The voter paces a reactive component by its input: without a round-starting
                // input it would never vote anything.
                return Err(self.err(
                    &member_path(&member_path("components", &d.name), "redundancy"),
                    format!(
                        "protected component `{}` has no input that starts a round; reactive mode needs one (a protected component without inputs needs `\"mode\": \"stream\"`)",
                        d.name
                    ),
                ));
            }
            rounds
        } else {
            Vec::new()
        };

        Ok(ComponentPlan {
            name: d.name,
            exec: d.exec,
            args: d.desc.args,
            redundancy: d.desc.redundancy,
            replicas: d.replicas,
            timeout_us: d.timeout_us,
            restart_timeout_ms: d
                .desc
                .restart_timeout_ms
                .unwrap_or_else(default_restart_timeout_ms),
            start_timeout_ms: d
                .desc
                .start_timeout_ms
                .unwrap_or_else(default_start_timeout_ms),
            max_restarts: d
                .desc
                .max_restarts
                .map_or_else(default_max_restarts, |n| n as u32),
            restart_window_ms: d
                .desc
                .restart_window_ms
                .unwrap_or_else(default_restart_window_ms),
            priority: d.priority,
            cpus: d.cpus,
            voter_cpu: d.voter_cpu,
            schedule: d.schedule,
            schedule_auto: d.schedule_auto,
            inputs,
            outputs,
            rounds,
            mode: d.desc.mode,
            window: d.window,
            monitors: Vec::new(),
            captures: Vec::new(),
            framing: d.framing,
            lock_memory: d.desc.lock_memory.unwrap_or_default(),
            cpu_idle: d.desc.cpu_idle.unwrap_or_default(),
            // Checked against MAX_SPIN_US above.
            spin_us: d.desc.spin_us.map_or(DEFAULT_SPIN_US, |us| us as u32),
            preload: d.preload,
        })
    }

    /// A channel's `fields`, `detector` and `capture`: the layout fits the channel's frames,
    /// the model exists and was trained on exactly that layout, and the channel's writer is a
    /// protected reactive component (its voter is what runs the detector and writes the
    /// capture). The result goes into the writer's plan.
    fn check_monitoring(
        &self,
        i: usize,
        ch: &ChannelDesc,
        plan: &ChannelPlan,
        components: &mut [ComponentPlan],
    ) -> Result<(), DescriptionError> {
        let at = element_path("channels", i);
        let field = |f: &str| member_path(&at, f);
        if ch.fields.is_none() && ch.detector.is_none() && ch.capture.is_none() {
            return Ok(());
        }
        let layout = match &ch.fields {
            None => None,
            Some(fields) => {
                let layout = FieldLayout::new(fields.clone())
                    .and_then(|l| l.within(plan.max_frame).map(|()| l))
                    .map_err(|e| {
                        self.err(
                            &self.layout_path(&field("fields"), fields, &e),
                            e.to_string(),
                        )
                    })?;
                Some(layout)
            }
        };
        let needs_voter = if ch.detector.is_some() {
            Some("detector")
        } else if ch.capture.is_some() {
            Some("capture")
        } else {
            None
        };
        let Some(what) = needs_voter else {
            // Fields alone document the layout (and are checked); nothing runs on them.
            return Ok(());
        };
        let writer = match &plan.from {
            Endpoint::Port { component, port } => components
                .iter_mut()
                .find(|c| &c.name == component)
                .map(|c| (c, port.clone())),
            _ => None,
        };
        let Some((writer, port)) = writer.filter(|(c, _)| c.is_protected()) else {
            return Err(self.err(
                &field(what),
                format!(
                    "`{what}` needs a channel written by a protected component (its voter runs it); `{}` is not one (give it a redundancy; smr is enough)",
                    plan.from
                ),
            ));
        };
        if let Some(capture) = &ch.capture {
            if capture.trim().is_empty() {
                return Err(self.err(&field("capture"), "the capture file name is empty"));
            }
            writer.captures.push(CapturePlan {
                output: port.clone(),
                path: self.ctx.base_dir.join(capture),
            });
        }
        let Some(det) = &ch.detector else {
            return Ok(());
        };
        let Some(layout) = layout else {
            return Err(self.err(
                &field("detector"),
                "a `detector` needs the channel's `fields` (the layout its model was trained on)",
            ));
        };
        let model_path = self.ctx.base_dir.join(&det.model);
        let model = Model::load(&model_path)
            .map_err(|e| self.err(&member_path(&field("detector"), "model"), e.to_string()))?;
        model.check_layout(&layout).map_err(|e| {
            self.err(
                &member_path(&field("detector"), "model"),
                format!("model {}: {e}", model_path.display()),
            )
        })?;
        let kind = model.kind();
        if let Some(want) = det.kind {
            let want = match want {
                DetectorKind::Gaussian => "gaussian",
                DetectorKind::Autoencoder => "autoencoder",
            };
            if want != kind {
                return Err(self.err(
                    &member_path(&field("detector"), "kind"),
                    format!(
                        "`kind` is {want} but the model {} is a {kind} model",
                        model_path.display()
                    ),
                ));
            }
        }
        let threshold = match (det.sigma, det.threshold) {
            (Some(_), Some(_)) => {
                return Err(self.err(
                    &field("detector"),
                    "give `sigma` (Gaussian) or `threshold` (autoencoder), not both",
                ))
            }
            (Some(s), None) if kind == "gaussian" => Some(("sigma", s)),
            (None, Some(t)) if kind == "autoencoder" => Some(("threshold", t)),
            (Some(_), None) => {
                return Err(self.err(
                    &member_path(&field("detector"), "sigma"),
                    format!(
                        "`sigma` is for a Gaussian model; {} is a {kind} model (use `threshold`)",
                        model_path.display()
                    ),
                ))
            }
            (None, Some(_)) => {
                return Err(self.err(
                    &member_path(&field("detector"), "threshold"),
                    format!(
                    "`threshold` is for an autoencoder model; {} is a {kind} model (use `sigma`)",
                    model_path.display()
                ),
                ))
            }
            (None, None) => None,
        };
        if let Some((name, t)) = threshold {
            if !(t.is_finite() && t > 0.0) {
                return Err(self.err(
                    &member_path(&field("detector"), name),
                    format!("`{name}` {t} must be a positive number"),
                ));
            }
        }
        writer.monitors.push(MonitorPlan {
            output: port,
            fields: layout,
            model: model_path,
            threshold: threshold.map(|(_, t)| t),
        });
        Ok(())
    }

    /// Where a layout error points: the field it names (`channels[0].fields[2]`), else the
    /// whole list.
    fn layout_path(&self, at: &str, fields: &[Field], e: &s3res_anomaly::LayoutError) -> String {
        use s3res_anomaly::LayoutError as L;
        let index = match e {
            L::EmptyName { index } => Some(*index),
            L::DuplicateName { second, .. } => Some(*second),
            L::BeyondFrame { name, .. } | L::Overlap { name, .. } => {
                fields.iter().position(|f| &f.name == name)
            }
            L::Empty | L::TooMany { .. } => None,
        };
        index.map_or_else(|| at.to_owned(), |k| element_path(at, k))
    }

    /// The inputs (or outputs) of a component: the declared list checked against the channels,
    /// or, when none is declared, the ports the channels use, in channel order.
    fn port_list(
        &self,
        d: &Draft,
        field: &str,
        declared: Option<&[String]>,
        used: &[(String, PortUse)],
        channels: &[ChannelPlan],
        is_input: bool,
    ) -> Result<Vec<PortPlan>, DescriptionError> {
        let at = member_path(&member_path("components", &d.name), field);
        let plan_of = |name: &str, u: Option<&PortUse>| PortPlan {
            name: name.to_owned(),
            channel: u.map(|u| u.channel),
            max_frame: u
                .and_then(|u| channels.get(u.channel))
                .map_or(DEFAULT_MAX_FRAME, |c| c.max_frame),
        };
        let Some(declared) = declared else {
            return Ok(used.iter().map(|(n, u)| plan_of(n, Some(u))).collect());
        };
        for (k, name) in declared.iter().enumerate() {
            let path = element_path(&at, k);
            if let Some(problem) = name_problem(name) {
                return Err(self.err(&path, format!("port name {name:?} {problem}")));
            }
            if declared[..k].contains(name) {
                return Err(self.err(&path, format!("port `{name}` is declared twice")));
            }
        }
        for (name, u) in used {
            if !declared.contains(name) {
                return Err(self.err(
                    &u.path,
                    format!(
                        "unknown port `{name}`: component `{}` declares {field} [{}]",
                        d.name,
                        declared.join(", ")
                    ),
                ));
            }
        }
        let mut out = Vec::with_capacity(declared.len());
        for (k, name) in declared.iter().enumerate() {
            let u = used.iter().find(|(n, _)| n == name).map(|(_, u)| u);
            if is_input && u.is_none() {
                return Err(self.err(
                    &element_path(&at, k),
                    format!(
                        "input port `{}.{name}` is connected nowhere (no channel has `to`: \"{}.{name}\")",
                        d.name, d.name
                    ),
                ));
            }
            out.push(plan_of(name, u));
        }
        Ok(out)
    }

    fn rounds(
        &self,
        d: &Draft,
        inputs: &[PortPlan],
        outputs: &[PortPlan],
    ) -> Result<Vec<RoundTrigger>, DescriptionError> {
        let all_outputs: Vec<String> = outputs.iter().map(|p| p.name.clone()).collect();
        let Some(rounds) = &d.desc.rounds else {
            return Ok(inputs
                .iter()
                .map(|p| RoundTrigger {
                    input: p.name.clone(),
                    outputs: all_outputs.clone(),
                })
                .collect());
        };
        let at = member_path(&member_path("components", &d.name), "rounds");
        let mut out: Vec<RoundTrigger> = Vec::with_capacity(rounds.len());
        for (k, r) in rounds.iter().enumerate() {
            let here = element_path(&at, k);
            let input_path = member_path(&here, "input");
            if !inputs.iter().any(|p| p.name == r.input) {
                let what = if d.desc.inputs.is_some() {
                    format!(
                        "unknown input port `{}` in a round of component `{}`",
                        r.input, d.name
                    )
                } else {
                    format!(
                        "round input `{}.{}` is connected nowhere (no channel has `to`: \"{}.{}\")",
                        d.name, r.input, d.name, r.input
                    )
                };
                return Err(self.err(&input_path, what));
            }
            if out.iter().any(|t| t.input == r.input) {
                return Err(self.err(
                    &input_path,
                    format!("two rounds start on input `{}`", r.input),
                ));
            }
            let outs = match &r.outputs {
                None => all_outputs.clone(),
                Some(list) => {
                    for (j, o) in list.iter().enumerate() {
                        let opath = element_path(&member_path(&here, "outputs"), j);
                        if !all_outputs.contains(o) {
                            return Err(self.err(
                                &opath,
                                format!(
                                    "unknown output port `{o}` in a round of component `{}` (no channel starts at `{}.{o}`)",
                                    d.name, d.name
                                ),
                            ));
                        }
                        if list[..j].contains(o) {
                            return Err(self.err(
                                &opath,
                                format!("output `{o}` is listed twice in this round"),
                            ));
                        }
                    }
                    list.clone()
                }
            };
            out.push(RoundTrigger {
                input: r.input.clone(),
                outputs: outs,
            });
        }
        Ok(out)
    }
}

/// The ports of `component` in `used`, ordered by channel.
fn ports_of(component: &str, used: &HashMap<(String, String), PortUse>) -> Vec<(String, PortUse)> {
    let mut v: Vec<(String, PortUse)> = used
        .iter()
        .filter(|((c, _), _)| c == component)
        .map(|((_, p), u)| (p.clone(), u.clone()))
        .collect();
    v.sort_by_key(|(_, u)| u.channel);
    v
}

fn cpu_list(cpus: &[usize]) -> String {
    if cpus.is_empty() {
        return "none known".to_owned();
    }
    cpus.iter()
        .map(usize::to_string)
        .collect::<Vec<_>>()
        .join(", ")
}

#[cfg(test)]
mod tests;
