//! The system under test: one component, either run directly (the no-voter baseline) or under
//! the real `s3res-voter`, started the way `s3res-bootstrap` starts it (a `VoterPlan` as JSON,
//! the component's pipes on fds 3 and 4, the events pipe on fd 5, a socket in a private folder).
//! The bench holds the other ends of those pipes itself: frames enter and leave the system
//! without any relay.
//!
//! Everything started here lives in its own process group; dropping the [`System`] (also while
//! unwinding from a panic) kills the group and reaps it, and SIGINT/SIGTERM kill every group at
//! once (see `sys::install_interrupt_handler`). The voter also gets `PR_SET_PDEATHSIG`, so it
//! dies with the bench even if the bench is SIGKILLed.

use std::fs::File;
use std::io::{BufRead, BufReader};
use std::os::fd::{AsRawFd, OwnedFd};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use replica_rt::contract::{
    Direction, PortMap, PortSpec, ENV_COMPONENT, ENV_PORTS, ENV_REPLICA, ENV_VOTER_SOCKET,
    FIRST_PORT_FD,
};
use replica_rt::sys as rsys;
use s3res_protocol::event::{Event, EventKind};
use s3res_protocol::plan::{ExternalPort, RoundTrigger, VoterPlan};

use crate::frames::{nanos, FrameIn, FrameIoError, FrameOut};
use crate::sys;

/// Where the s3res executables are.
#[derive(Debug, Clone)]
pub struct Bins {
    dir: PathBuf,
    /// Where the measured components (`s3res-echo`, `s3res-ballast`) are: `dir` unless
    /// `--component-dir` names another build of them.
    components: PathBuf,
}

/// `dir/name`, if it is a file; else an error that says how to get it (`option`: the one that
/// names `dir`).
fn existing(dir: &Path, name: &str, option: &str) -> Result<PathBuf> {
    let p = dir.join(name);
    if !p.is_file() {
        bail!(
            "{} not found (build the workspace first: cargo build --release; or name the \
             folder with {option})",
            p.display()
        );
    }
    Ok(p)
}

/// The components a bench measures, looked up with [`Bins::component`].
const COMPONENTS: [&str; 2] = ["s3res-echo", "s3res-ballast"];

impl Bins {
    /// `dir` if given, else the folder of the running `s3res-bench` (as bootstrap finds the
    /// voter beside itself); the components in `components` if given, else there too.
    pub fn locate(dir: Option<PathBuf>, components: Option<PathBuf>) -> Result<Bins> {
        let dir = match dir {
            Some(d) => d,
            None => std::env::current_exe()
                .context("finding the running executable")?
                .parent()
                .ok_or_else(|| anyhow!("the running executable has no folder"))?
                .to_path_buf(),
        };
        let components = components.unwrap_or_else(|| dir.clone());
        Ok(Bins { dir, components })
    }

    pub fn path(&self, name: &str) -> Result<PathBuf> {
        existing(&self.dir, name, "--bin-dir")
    }

    /// A measured component's executable (one of [`COMPONENTS`]).
    pub fn component(&self, name: &str) -> Result<PathBuf> {
        debug_assert!(
            COMPONENTS.contains(&name),
            "{name} is not a measured component"
        );
        existing(&self.components, name, "--component-dir")
    }

    /// `Some("static")` when the measured components are statically linked, `None` when they
    /// are dynamically linked (the workspace's own build) or cannot be told (not an ELF
    /// executable of this kind: a wrapper script, say; said once on stderr); an error if the
    /// folder holds one of each, whose rows could not say which they measured.
    pub fn component_linking(&self) -> Result<Option<&'static str>> {
        let mut seen: Vec<(&str, bool)> = Vec::new();
        for name in COMPONENTS {
            let p = self.components.join(name);
            if !p.is_file() {
                continue;
            }
            match crate::elf::is_dynamically_linked(&p) {
                Ok(dynamic) => seen.push((name, dynamic)),
                Err(e) => eprintln!(
                    "s3res-bench: cannot tell how {} is linked ({e}); its rows say nothing of it",
                    p.display()
                ),
            }
        }
        if let (Some(a), Some(b)) = (seen.iter().find(|c| c.1), seen.iter().find(|c| !c.1)) {
            bail!(
                "in {}, {} is dynamically linked and {} statically: build both the same way",
                self.components.display(),
                a.0,
                b.0
            );
        }
        Ok(seen.first().filter(|c| !c.1).map(|_| "static"))
    }
}

/// What to run.
#[derive(Debug, Clone)]
pub struct Spec {
    pub exec: PathBuf,
    pub args: Vec<String>,
    /// 0: the component runs directly, no voter. 1, 2, 3: SMR, DMR, TMR under `s3res-voter`.
    pub replicas: usize,
    pub timeout_us: u64,
    pub max_frame: usize,
    /// Kept for the voter (required when `replicas > 0`).
    pub voter: Option<PathBuf>,
    /// How the processes are scheduled: the voter's plan carries it (see [`Setup::plan_fields`]).
    pub setup: Setup,
    /// An unmodified program: the preload library and how its stdin/stdout are framed.
    pub preload: Option<(PathBuf, s3res_protocol::plan::Framing)>,
    /// The voter keeps the journal a successor would take over from (as under
    /// s3res-bootstrap, which gives one to every reactive component's voter whose replicas
    /// link replica-rt; never to an unmodified program's).
    pub journal: bool,
    /// What the replicas lock (the voter passes it on).
    pub lock_memory: s3res_protocol::plan::LockMemory,
    /// What idle CPUs do while the voter runs.
    pub cpu_idle: s3res_protocol::plan::CpuIdle,
    /// How long the voter may spin for an answer from another CPU, µs.
    pub spin_us: u32,
}

/// Name of the component in plans and events.
const COMPONENT: &str = "bench";
/// Lost rounds whose frames are kept to recognise their answers arriving late.
const LOST_FRAMES_KEPT: usize = 8;

/// The rounds [`System::echo_round`] gave up on: every replica of the round was blamed, so the
/// voter withholds the answer, the bench waits for the replacements and goes on. A fault
/// stamped after the round was sent can still belong to the round before, though, and then
/// the voter may have had a majority after all: that answer comes during a later round. It is
/// recognised by its frame (every round's differs) and counted late, not taken for a wrong
/// answer to the round being waited for.
#[derive(Debug, Default)]
pub struct LostRounds {
    /// Rounds given up on and not answered since.
    pub count: u64,
    /// Rounds given up on whose answer came later.
    pub late: u64,
    /// The frames of the latest rounds given up on, oldest first.
    frames: std::collections::VecDeque<Vec<u8>>,
}

impl LostRounds {
    /// The round of `frame` is given up on.
    pub fn lose(&mut self, frame: &[u8]) {
        self.count += 1;
        if self.frames.len() == LOST_FRAMES_KEPT {
            self.frames.pop_front();
        }
        self.frames.push_back(frame.to_vec());
    }

    /// Whether `reply` is the answer to a round given up on (then counted late, once).
    pub fn answered_late(&mut self, reply: &[u8]) -> bool {
        let Some(k) = self.frames.iter().position(|f| f == reply) else {
            return false;
        };
        self.frames.remove(k);
        self.count -= 1;
        self.late += 1;
        true
    }
}

/// A running system with the bench holding its input and output.
pub struct System {
    pub input: FrameOut,
    pub output: FrameIn,
    /// The process the bench started: the voter, or the component itself.
    pub top_pid: libc::pid_t,
    /// Current pid of every replica slot (from `start` and `recovery` events).
    pub replicas: Vec<libc::pid_t>,
    events: Option<Receiver<Event>>,
    /// The thread that reads the voter's events: the setup places it with the bench.
    events_thread: Option<libc::pid_t>,
    /// Events that are neither `start` nor `recovery`: faults.
    pub faults: Vec<Event>,
    /// Every event in arrival order (kept for the subcommands that need them).
    pub log: Vec<Event>,
    /// Rounds whose answer the voter withheld (every replica found faulty in the round), and
    /// those of them answered late after all.
    pub lost: LostRounds,
    group_slot: Option<usize>,
    workdir: tempfile::TempDir,
    reaped: bool,
    /// An unmodified program (its input is its stdin).
    preloaded: bool,
}

impl System {
    pub fn start(spec: &Spec) -> Result<System> {
        let workdir = tempfile::Builder::new()
            .prefix("s3res-bench-")
            .tempdir()
            .context("creating a temp dir")?;
        let log = File::create(workdir.path().join("stderr.log")).context("log file")?;
        let (in_r, in_w) = rsys::pipe().context("pipe")?;
        let (out_r, out_w) = rsys::pipe().context("pipe")?;
        let mut cmd;
        let mut events_rx = None;
        let mut events_thread = None;
        let mut keep: Vec<OwnedFd> = vec![in_r, out_w];
        if spec.replicas == 0 {
            cmd = Command::new(&spec.exec);
            let ports = PortMap {
                ports: vec![
                    port("in", Direction::In, FIRST_PORT_FD, spec.max_frame),
                    port("out", Direction::Out, FIRST_PORT_FD + 1, spec.max_frame),
                ],
            };
            cmd.args(&spec.args)
                .env(ENV_PORTS, ports.to_env())
                .env_remove(ENV_VOTER_SOCKET)
                .env_remove(ENV_REPLICA)
                .env(ENV_COMPONENT, COMPONENT);
        } else {
            let voter = spec
                .voter
                .as_ref()
                .ok_or_else(|| anyhow!("no voter binary"))?;
            let (ev_r, ev_w) = rsys::pipe().context("events pipe")?;
            keep.push(ev_w);
            let journal_fd = if spec.journal {
                keep.push(replica_rt::shared::memfd(c"s3res-journal").context("journal")?);
                Some(FIRST_PORT_FD + 3)
            } else {
                None
            };
            // As s3res-bootstrap runs an unmodified program's voter: its replicas' pipes are
            // parked in a socket pair, its lines staged and its answers peeked and taken.
            let park_fds = if spec.journal && spec.preload.is_some() {
                let (tx, rx) = rsys::seqpacket_pair().context("park socket pair")?;
                keep.push(tx);
                keep.push(rx);
                Some([FIRST_PORT_FD + 4, FIRST_PORT_FD + 5])
            } else {
                None
            };
            let sched = spec.setup.plan_fields(spec.replicas);
            let plan = VoterPlan {
                system: "s3res-bench".into(),
                component: COMPONENT.into(),
                exec: spec.exec.clone(),
                args: spec.args.clone(),
                replicas: spec.replicas,
                timeout_us: spec.timeout_us,
                inputs: vec![ExternalPort {
                    name: "in".into(),
                    fd: FIRST_PORT_FD,
                    max_frame: spec.max_frame,
                }],
                outputs: vec![ExternalPort {
                    name: "out".into(),
                    fd: FIRST_PORT_FD + 1,
                    max_frame: spec.max_frame,
                }],
                rounds: vec![RoundTrigger {
                    input: "in".into(),
                    outputs: vec!["out".into()],
                }],
                events_fd: Some(FIRST_PORT_FD + 2),
                heartbeat_fd: None,
                socket_path: workdir.path().join("v.sock"),
                socket_fd: None,
                journal_fd,
                park_fds,
                stamps_fd: None,
                adopt: None,
                restart_timeout_ms: s3res_protocol::plan::default_restart_timeout_ms(),
                priority: sched.priority,
                cpus: sched.cpus,
                start_timeout_ms: s3res_protocol::plan::default_start_timeout_ms(),
                max_restarts: s3res_protocol::plan::default_max_restarts(),
                restart_window_ms: s3res_protocol::plan::default_restart_window_ms(),
                voter_cpu: sched.voter_cpu,
                schedule: sched.schedule,
                realtime: true,
                nice: None,
                mode: Default::default(),
                window: s3res_protocol::plan::default_stream_window(),
                monitors: Vec::new(),
                captures: Vec::new(),
                framing: spec.preload.as_ref().map(|p| p.1).unwrap_or_default(),
                lock_memory: spec.lock_memory,
                cpu_idle: spec.cpu_idle,
                spin_us: spec.spin_us,
                preload: spec.preload.as_ref().map(|p| p.0.clone()),
            };
            cmd = Command::new(voter);
            cmd.arg("--plan")
                .arg(plan.to_json())
                .env("RUST_LOG", "warn")
                .env_remove(ENV_VOTER_SOCKET)
                .env_remove(ENV_REPLICA)
                .env(ENV_COMPONENT, COMPONENT);
            let (rx, thread) = spawn_event_reader(ev_r)?;
            events_rx = Some(rx);
            events_thread = Some(thread);
        }
        cmd.stdin(Stdio::null())
            .stdout(Stdio::from(log.try_clone()?))
            .stderr(Stdio::from(log))
            .process_group(0);
        let mapping = keep
            .iter()
            .enumerate()
            .map(|(i, fd)| (fd.as_raw_fd(), FIRST_PORT_FD + i as i32))
            .collect();
        rsys::map_fds_on_exec(&mut cmd, mapping);
        sys::kill_child_with_parent(&mut cmd);
        let child = cmd
            .spawn()
            .with_context(|| format!("starting {:?}", cmd.get_program()))?;
        let top_pid = child.id() as libc::pid_t;
        drop(child);
        // Our copies of the child's ends must go, or end of stream never comes.
        drop(keep);
        let group_slot = sys::register_group(top_pid);
        let mut system = System {
            input: FrameOut::new(in_w)?,
            output: FrameIn::new(out_r, spec.max_frame)?,
            top_pid,
            replicas: vec![0; spec.replicas],
            events: events_rx,
            events_thread,
            faults: Vec::new(),
            log: Vec::new(),
            lost: LostRounds::default(),
            group_slot,
            workdir,
            reaped: false,
            preloaded: spec.preload.is_some(),
        };
        if spec.replicas > 0 {
            let deadline = Instant::now() + Duration::from_secs(10);
            while system.replicas.contains(&0) {
                let left = deadline.saturating_duration_since(Instant::now());
                if system.next_event(left)?.is_none() {
                    bail!(
                        "the voter did not start its replicas within 10 s\n{}",
                        system.log_tail()
                    );
                }
            }
        }
        system.wait_until_idle(Duration::from_secs(30))?;
        Ok(system)
    }

    /// Waits until every process that should read the input is blocked reading it (fd 3, as
    /// `/proc/PID/syscall` shows): a replica still starting would miss a short first deadline.
    pub fn wait_until_idle(&self, timeout: Duration) -> Result<()> {
        let pids: Vec<libc::pid_t> = if self.replicas.is_empty() {
            vec![self.top_pid]
        } else {
            self.replicas.clone()
        };
        let deadline = Instant::now() + timeout;
        // An unmodified program reads its stdin.
        let input_fd = if self.preloaded {
            libc::STDIN_FILENO
        } else {
            FIRST_PORT_FD
        };
        for pid in pids {
            loop {
                if reading_fd(pid, input_fd) {
                    break;
                }
                if Instant::now() > deadline || sys::interrupted() {
                    bail!(
                        "pid {pid} is not waiting for input after {timeout:?}\n{}",
                        self.log_tail()
                    );
                }
                std::thread::sleep(Duration::from_millis(1));
            }
        }
        Ok(())
    }

    /// The next event within `timeout` (`None` on timeout). Tracks replica pids and faults.
    pub fn next_event(&mut self, timeout: Duration) -> Result<Option<Event>> {
        let Some(rx) = &self.events else {
            std::thread::sleep(timeout);
            return Ok(None);
        };
        let ev = match rx.recv_timeout(timeout) {
            Ok(ev) => ev,
            Err(RecvTimeoutError::Timeout) => return Ok(None),
            Err(RecvTimeoutError::Disconnected) => {
                bail!("the voter's events pipe closed\n{}", self.log_tail())
            }
        };
        match ev.kind {
            EventKind::Start => {
                if let (Some(slot), Some(pid)) = (ev.replica, ev.pid) {
                    self.replicas[slot] = pid;
                }
            }
            EventKind::Recovery => {
                if let (Some(slot), Some(pid)) = (ev.replica, ev.new_pid) {
                    self.replicas[slot] = pid;
                }
            }
            _ => self.faults.push(ev.clone()),
        }
        self.log.push(ev.clone());
        Ok(Some(ev))
    }

    /// Waits for the first event `pred` accepts (others are tracked and kept in the log).
    pub fn wait_event(
        &mut self,
        pred: impl FnMut(&Event) -> bool,
        timeout: Duration,
    ) -> Result<Event> {
        match self.try_wait_event(pred, timeout)? {
            Some(ev) => Ok(ev),
            None => bail!(
                "the expected event did not come within {timeout:?}\n{}",
                self.log_tail()
            ),
        }
    }

    /// [`wait_event`](Self::wait_event), `None` on timeout.
    pub fn try_wait_event(
        &mut self,
        mut pred: impl FnMut(&Event) -> bool,
        timeout: Duration,
    ) -> Result<Option<Event>> {
        let deadline = Instant::now() + timeout;
        loop {
            if sys::interrupted() {
                bail!("interrupted");
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            if let Some(ev) = self.next_event(left.min(Duration::from_millis(100)))? {
                if pred(&ev) {
                    return Ok(Some(ev));
                }
            }
        }
    }

    /// The first event at or after `since` that `pred` accepts, already arrived or to come;
    /// `None` on timeout.
    pub fn try_wait_event_since(
        &mut self,
        mut pred: impl FnMut(&Event) -> bool,
        since: u64,
        timeout: Duration,
    ) -> Result<Option<Event>> {
        if let Some(ev) = self.log.iter().find(|e| e.ts_ns >= since && pred(e)) {
            return Ok(Some(ev.clone()));
        }
        self.try_wait_event(|e| e.ts_ns >= since && pred(e), timeout)
    }

    /// The first event at or after `since` (CLOCK_MONOTONIC ns) that `pred` accepts, whether it
    /// has already arrived (and was kept in the log) or is still to come.
    pub fn wait_event_since(
        &mut self,
        mut pred: impl FnMut(&Event) -> bool,
        since: u64,
        timeout: Duration,
    ) -> Result<Event> {
        if let Some(ev) = self.log.iter().find(|e| e.ts_ns >= since && pred(e)) {
            return Ok(ev.clone());
        }
        self.wait_event(|e| e.ts_ns >= since && pred(e), timeout)
    }

    /// Writes `frame`, waits for the answer and checks that it equals `frame` (an echo).
    /// Returns the round trip (ns from just before the write to just after the read that
    /// completed the answer), or `None` if the voter withheld it because every
    /// replica of the round was found faulty (under heavy load all of them can miss a short
    /// deadline): then it waits for their replacements, counts a lost round, and goes on.
    pub fn echo_round(&mut self, frame: &[u8], limit: Duration) -> Result<Option<u64>> {
        // Between the two timestamps only what the peers' harnesses do between theirs: one
        // write and the reads of the answer (the frame is built before the first). Deadlines
        // are reckoned from `sent_at`.
        self.input.stage(frame);
        let sent_at = rsys::monotonic_ns();
        let workdir = &self.workdir;
        self.input
            .send_staged(limit)
            .map_err(|e| anyhow!("sending a frame: {e}\n{}", log_tail(workdir.path())))?;
        let deadline = sent_at.saturating_add(nanos(limit));
        let n = self.replicas.len();
        let wait = if n == 0 {
            limit
        } else {
            Duration::from_millis(20)
        };
        let mut wait_until = sent_at.saturating_add(nanos(wait)).min(deadline);
        loop {
            match self.output.recv_by(wait_until, wait) {
                Ok(reply) => {
                    let at = rsys::monotonic_ns();
                    if reply != frame {
                        if self.lost.answered_late(reply) {
                            continue;
                        }
                        bail!(
                            "the answer ({} bytes) is not the frame ({} bytes)",
                            reply.len(),
                            frame.len()
                        );
                    }
                    return Ok(Some(at - sent_at));
                }
                Err(FrameIoError::Timeout(_)) if n > 0 && rsys::monotonic_ns() < deadline => {
                    wait_until = rsys::monotonic_ns().saturating_add(nanos(wait));
                    self.drain_events()?;
                    let blamed = self
                        .faults
                        .iter()
                        .filter(|e| e.ts_ns >= sent_at)
                        .filter_map(|e| e.replica)
                        .fold(0u64, |set, r| set | 1 << r);
                    if blamed.count_ones() as usize >= n {
                        self.lost.lose(frame);
                        for slot in 0..n {
                            self.wait_event_since(
                                |e| e.replica == Some(slot) && e.kind == EventKind::Recovery,
                                sent_at,
                                Duration::from_secs(30),
                            )?;
                        }
                        self.wait_until_idle(Duration::from_secs(30))?;
                        return Ok(None);
                    }
                }
                Err(e) => bail!("waiting for the answer: {e}\n{}", self.log_tail()),
            }
        }
    }

    /// Takes every event that has arrived, without waiting.
    pub fn drain_events(&mut self) -> Result<()> {
        while self.next_event(Duration::ZERO)?.is_some() {}
        Ok(())
    }

    /// The last lines the system wrote to stderr (for error messages).
    pub fn log_tail(&self) -> String {
        let from = self.log.len().saturating_sub(8);
        let events: Vec<String> = self.log[from..]
            .iter()
            .map(|e| {
                format!(
                    "{} {:?} replica {:?} pid {:?} round {:?} {}",
                    e.ts_ns,
                    e.kind,
                    e.replica,
                    e.pid,
                    e.round,
                    e.detail.as_deref().unwrap_or("")
                )
            })
            .collect();
        format!(
            "{}\nlast events:\n{}",
            log_tail(self.workdir.path()),
            events.join("\n")
        )
    }

    /// Writes `frame` and waits for the system's answer; errors carry the system's stderr.
    pub fn exchange(&mut self, frame: &[u8], timeout: Duration) -> Result<&[u8]> {
        let dir = self.workdir.path();
        self.input
            .send(frame, timeout)
            .map_err(|e| anyhow!("sending a frame: {e}\n{}", log_tail(dir)))?;
        self.output
            .recv(timeout)
            .map_err(|e| anyhow!("waiting for the answer: {e}\n{}", log_tail(dir)))
    }

    /// Kills the process group and reaps it (and whatever was re-parented to the bench).
    pub fn stop(&mut self) {
        if self.reaped {
            return;
        }
        self.reaped = true;
        let _ = sys::kill_group(self.top_pid, libc::SIGKILL);
        if let Some(slot) = self.group_slot.take() {
            sys::unregister_group(slot);
        }
        let deadline = Instant::now() + Duration::from_secs(5);
        // The top process first (our child), then replicas re-parented to us (subreaper).
        loop {
            match rsys::reap(self.top_pid) {
                Ok(Some(_)) | Err(_) => break,
                Ok(None) if Instant::now() > deadline => break,
                Ok(None) => std::thread::sleep(Duration::from_millis(1)),
            }
        }
        let group = self.top_pid;
        loop {
            let left: Vec<_> = rsys::children_of(std::process::id() as i32)
                .into_iter()
                .filter(|&p| rsys::process_group(p) == Some(group))
                .collect();
            for &p in &left {
                let _ = rsys::kill(p, libc::SIGKILL);
                let _ = rsys::reap(p);
            }
            if left.is_empty() || Instant::now() > deadline {
                break;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }
}

impl Drop for System {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Whether `pid` is blocked in `read(fd, ...)` (`/proc/PID/syscall` starts with `0 0x<fd>`).
/// Readable for our own children (same user, or root).
fn reading_fd(pid: libc::pid_t, fd: i32) -> bool {
    let Ok(text) = std::fs::read_to_string(format!("/proc/{pid}/syscall")) else {
        return false;
    };
    let mut words = text.split_whitespace();
    words.next() == Some("0") && words.next() == Some(format!("{fd:#x}").as_str())
}

/// The last lines a system wrote to `dir/stderr.log`.
fn log_tail(dir: &Path) -> String {
    let text = std::fs::read_to_string(dir.join("stderr.log")).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    let from = lines.len().saturating_sub(20);
    format!(
        "system's stderr (last lines):\n{}",
        lines[from..].join("\n")
    )
}

fn port(name: &str, dir: Direction, fd: i32, max_frame: usize) -> PortSpec {
    PortSpec {
        name: name.into(),
        dir,
        fd,
        max_frame,
    }
}

/// Reads the voter's events pipe on a thread (so a burst of events never blocks the voter)
/// and hands each parsed event over. Returns the thread's kernel id too, for [`Setup::apply`].
fn spawn_event_reader(fd: OwnedFd) -> Result<(Receiver<Event>, libc::pid_t)> {
    let (tx, rx) = mpsc::channel();
    let (tid_tx, tid_rx) = mpsc::sync_channel(1);
    std::thread::Builder::new()
        .name("events".into())
        .spawn(move || {
            let _ = tid_tx.send(sys::this_thread());
            for line in BufReader::new(File::from(fd)).lines() {
                let Ok(line) = line else { return };
                match serde_json::from_str::<Event>(&line) {
                    Ok(ev) => {
                        if tx.send(ev).is_err() {
                            return;
                        }
                    }
                    Err(e) => tracing::warn!(error = %e, line, "unparsable event"),
                }
            }
        })
        .context("starting the events thread")?;
    let tid = tid_rx
        .recv()
        .context("the events thread ended before it started")?;
    Ok((rx, tid))
}

/// How the processes of a configuration are scheduled (rows are labelled with it).
///
/// The voter and its replicas are scheduled by the voter itself, from its plan's `priority`,
/// `cpus`, `voter_cpu` and `schedule` (as `s3res-bootstrap` writes them), so a replacement
/// replica gets its slot's priority and CPU like the first ones. The bench sets only its own
/// thread, and the lone component of a no-voter baseline (as bootstrap sets an unprotected
/// component).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Setup {
    /// Default time-sharing, no pinning: what a user gets without privileges.
    Plain,
    /// SCHED_RR: bench and voter at [`RR_PRIORITY`], replicas below (the voter's scheme).
    Rr,
    /// SCHED_RR as above, bench and voter on CPU 0, the component's processes on CPU 1.
    RrPinned,
    /// Default scheduler, every process (bench, voter, replicas) on CPU 0: no cross-CPU
    /// wake-up at all.
    OneCpu,
    /// SCHED_RR as `rr`, every process on CPU 0.
    RrOneCpu,
}

/// The voter's SCHED_RR priority in the `rr` setups (its replicas run at 58, 57, 56 at rest,
/// 59 at their turn); the bench's thread runs at it too.
pub const RR_PRIORITY: u8 = 60;

/// Priority of the lone component of a no-voter baseline in the `rr` setups (below the bench).
const RR_ALONE_PRIORITY: u8 = 50;

/// The scheduling fields of a voter plan, as bootstrap would fill them in.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlanSched {
    pub priority: Option<u8>,
    pub cpus: Vec<usize>,
    pub voter_cpu: Option<usize>,
    pub schedule: s3res_protocol::sched::Schedule,
}

impl Setup {
    pub const ALL: [Setup; 5] = [
        Setup::Plain,
        Setup::Rr,
        Setup::RrPinned,
        Setup::OneCpu,
        Setup::RrOneCpu,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Setup::Plain => "plain",
            Setup::Rr => "rr",
            Setup::RrPinned => "rr-pinned",
            Setup::OneCpu => "one-cpu",
            Setup::RrOneCpu => "rr-one-cpu",
        }
    }

    pub fn parse(s: &str) -> Result<Setup, String> {
        Setup::ALL
            .into_iter()
            .find(|setup| setup.name() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = Setup::ALL.iter().map(|setup| setup.name()).collect();
                format!("unknown setup `{s}`; expected one of {}", names.join(", "))
            })
    }

    /// SCHED_RR: needs root or CAP_SYS_NICE.
    pub fn realtime(self) -> bool {
        matches!(self, Setup::Rr | Setup::RrPinned | Setup::RrOneCpu)
    }

    /// (CPUs of the bench and the voter, CPUs of the component's processes); empty: not pinned.
    fn cpus(self) -> (&'static [usize], &'static [usize]) {
        match self {
            Setup::Plain | Setup::Rr => (&[], &[]),
            Setup::RrPinned => (&[0], &[1]),
            Setup::OneCpu | Setup::RrOneCpu => (&[0], &[0]),
        }
    }

    /// The plan's scheduling fields for a voter of `replicas` replicas. `schedule` is what
    /// bootstrap's `auto` resolves to: sequential where two replicas share a CPU.
    pub fn plan_fields(self, replicas: usize) -> PlanSched {
        let (top, rest) = self.cpus();
        PlanSched {
            priority: self.realtime().then_some(RR_PRIORITY),
            cpus: rest.to_vec(),
            voter_cpu: top.first().copied(),
            schedule: s3res_protocol::sched::choose(replicas, rest),
        }
    }

    /// Applies the setup to the bench's calling thread and, for a no-voter baseline, to the
    /// component. A voter applies the plan's fields itself.
    pub fn apply(self, system: &System) -> Result<()> {
        let what = |who: &str, pid: i32| format!("SCHED_RR/affinity for {who} (pid {pid})");
        let (cpus_top, cpus_rest) = self.cpus();
        let cpus = sys::online_cpus();
        if cpus_rest.contains(&1) && cpus < 2 {
            bail!("{} needs 2 CPUs, this machine has {cpus}", self.name());
        }
        let apply = |pid: i32, who: &str, priority: u8, cpus: &[usize]| -> Result<()> {
            if self.realtime() {
                sys::set_round_robin(pid, i32::from(priority)).with_context(|| what(who, pid))?;
            }
            if !cpus.is_empty() {
                sys::set_affinity(pid, cpus).with_context(|| what(who, pid))?;
            }
            Ok(())
        };
        apply(0, "the bench", RR_PRIORITY, cpus_top)?;
        // The bench's events thread stays time-shared, but on the bench's CPUs: left to the
        // kernel, it wakes on an idle CPU (the replicas', when they are pinned apart) at each
        // fault event, and a donor's `RESTART` then has to interrupt it there (measured: 20 to
        // 30 µs more a restart, docs/results.md, stop 36).
        if let (Some(tid), false) = (system.events_thread, cpus_top.is_empty()) {
            sys::set_affinity(tid, cpus_top).with_context(|| what("the events thread", tid))?;
        }
        if system.replicas.is_empty() {
            apply(
                system.top_pid,
                "the component",
                RR_ALONE_PRIORITY,
                cpus_rest,
            )?;
        }
        Ok(())
    }

    /// Puts the bench's calling thread back to the default.
    pub fn reset_bench() {
        let _ = sys::set_normal_policy(0);
        let _ = sys::set_affinity(0, &[]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::elf::tests::elf;

    #[test]
    fn a_lost_rounds_answer_arriving_later_is_counted_late_once() {
        let mut lost = LostRounds::default();
        lost.lose(b"round 7");
        lost.lose(b"round 9");
        assert_eq!((lost.count, lost.late), (2, 0));
        // Not the answer to a lost round: a wrong answer, for the caller to report.
        assert!(!lost.answered_late(b"round 8"));
        assert!(lost.answered_late(b"round 7"));
        assert_eq!((lost.count, lost.late), (1, 1));
        // The same answer twice is a wrong answer the second time.
        assert!(!lost.answered_late(b"round 7"));
        assert!(lost.answered_late(b"round 9"));
        assert_eq!((lost.count, lost.late), (0, 2));
    }

    #[test]
    fn only_the_latest_lost_rounds_are_remembered() {
        let mut lost = LostRounds::default();
        for k in 0..=LOST_FRAMES_KEPT {
            lost.lose(format!("round {k}").as_bytes());
        }
        assert_eq!(lost.count, LOST_FRAMES_KEPT as u64 + 1);
        assert!(!lost.answered_late(b"round 0"));
        assert!(lost.answered_late(format!("round {LOST_FRAMES_KEPT}").as_bytes()));
    }

    /// A folder of components as `Bins` sees it: each `(name, contents)` written there.
    fn bins_with(files: &[(&str, &[u8])]) -> (tempfile::TempDir, Bins) {
        let dir = tempfile::tempdir().unwrap();
        for (name, bytes) in files {
            std::fs::write(dir.path().join(name), bytes).unwrap();
        }
        let bins = Bins::locate(Some(dir.path().into()), None).unwrap();
        (dir, bins)
    }

    #[test]
    fn the_components_linking_is_read_from_their_headers_and_a_mix_is_refused() {
        let (dynamic, stat) = (elf(&[3, 1]), elf(&[1]));
        let (_d, bins) = bins_with(&[("s3res-echo", &dynamic), ("s3res-ballast", &dynamic)]);
        assert_eq!(bins.component_linking().unwrap(), None);
        let (_d, bins) = bins_with(&[("s3res-echo", &stat), ("s3res-ballast", &stat)]);
        assert_eq!(bins.component_linking().unwrap(), Some("static"));
        // One of them missing: the other says.
        let (_d, bins) = bins_with(&[("s3res-echo", &stat)]);
        assert_eq!(bins.component_linking().unwrap(), Some("static"));
        // Not an ELF executable (a wrapper script): unlabelled, not an error.
        let script = b"#!/bin/sh\nexec s3res-echo-real \"$@\"\n".as_slice();
        let (_d, bins) = bins_with(&[("s3res-echo", script), ("s3res-ballast", script)]);
        assert_eq!(bins.component_linking().unwrap(), None);
        // One of each: refused, naming both.
        let (_d, bins) = bins_with(&[("s3res-echo", &stat), ("s3res-ballast", &dynamic)]);
        let e = bins.component_linking().unwrap_err().to_string();
        assert!(
            e.contains("s3res-ballast is dynamically linked and s3res-echo statically"),
            "{e}"
        );
    }
}
