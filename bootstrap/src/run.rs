//! Starting a validated system, supervising it, and stopping it.
//!
//! Order matters here: signals are blocked before any thread exists (so every thread inherits
//! the mask and only the signalfd sees them); the pipes are made before any child, and bootstrap
//! closes its copies right after the children have theirs, or end of stream never arrives.

use std::fs::File;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, OwnedFd, RawFd};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use nix::sys::signal::Signal;
use nix::sys::signalfd::SignalFd;
use thiserror::Error;

use replica_rt::contract::{
    Direction, PortMap, PortSpec, ENV_COMPONENT, ENV_MEMORY_LOCK_SAID, ENV_PORTS, ENV_REPLICA,
    ENV_STDERR_RELAYED, ENV_SUPERVISOR_PID, ENV_VOTER_SOCKET, FIRST_PORT_FD,
};
use replica_rt::sys::{self, ExitStatus};
use s3res_protocol::plan::{ExternalPort, VoterPlan};

use crate::component_stderr::ComponentStderr;
use crate::events::{EventReader, EventSummary};
use crate::keeper::Keeper;
use crate::live::LiveState;
use crate::plan::{ComponentPlan, Endpoint, InjectPlan, SystemPlan};
use crate::respawn::{self, RestartBudget, VoterSpawn};
use crate::sched::SystemSched;
use crate::status::{
    forward_stderr, read_injections, status_line, Console, ConsoleMode, Files, Injected, Tally,
    TallyData,
};
use crate::sweep::SweepGuard;
use crate::watch::{VoterWatch, WATCH_PERIOD};

/// Name of the voter binary.
pub const VOTER_BIN: &str = "s3res-voter";
/// Longest Unix socket path (sun_path is 108 bytes including the NUL).
const SUN_PATH_MAX: usize = 107;
/// How long to wait for the events reader after everything has exited.
const EVENTS_DRAIN: Duration = Duration::from_secs(2);

/// How to run.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// The voter binary (required if the system has a protected component).
    pub voter: Option<PathBuf>,
    /// Where to copy the event lines (created or truncated at start).
    pub events_file: Option<PathBuf>,
    /// After SIGTERM to the children, how long before SIGKILL.
    pub stop_timeout: Duration,
    /// Where to keep the live view of the running system (see [`crate::live`]).
    pub state_file: Option<PathBuf>,
    /// `s3res-inject`, to run the description's `inject` (`None`: no injector runs).
    pub injector: Option<PathBuf>,
    /// How the live status is shown.
    pub console: ConsoleMode,
    /// `RUST_LOG` for every process started (voters, replicas, components, injector), when
    /// bootstrap's own verbosity was chosen by `-q`/`-v` rather than by `RUST_LOG`.
    pub child_log: Option<String>,
    /// bootstrap's own binary, to start as the keeper (`keeper.rs`) that kills what the system
    /// started if bootstrap is SIGKILLed; `None`: no keeper.
    pub keeper: Option<PathBuf>,
}

/// Why a system could not be run.
#[derive(Debug, Error)]
pub enum RunError {
    #[error(
        "system has protected components but the voter binary `{VOTER_BIN}` was not found: {0}"
    )]
    VoterMissing(String),
    #[error("cannot make bootstrap a child subreaper: {0}")]
    Subreaper(std::io::Error),
    #[error("cannot set up signal handling: {0}")]
    Signals(nix::Error),
    #[error("cannot create the events file {path}: {source}")]
    EventsFile {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(
        "the {what} {path} is being written by {holder}; give this run its own files \
         (--events, --state) or stop that one"
    )]
    OutputInUse {
        what: &'static str,
        path: PathBuf,
        /// Who: `another s3res-bootstrap that runs (pid N)`, or as far as it is known.
        holder: String,
    },
    #[error("cannot create the socket folder in {dir}: {source}")]
    SocketDir {
        dir: PathBuf,
        source: std::io::Error,
    },
    #[error("socket path {0} is longer than {SUN_PATH_MAX} bytes; set TMPDIR to a shorter folder")]
    SocketPathTooLong(PathBuf),
    #[error("cannot set up channel {index} ({from} -> {to}): {source}")]
    Channel {
        index: usize,
        from: Endpoint,
        to: Endpoint,
        source: std::io::Error,
    },
    #[error("cannot write the state file {path}: {source}")]
    StateFile {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot set up the events pipe: {0}")]
    EventsPipe(std::io::Error),
    #[error("cannot set up the pipe that carries the processes' stderr: {0}")]
    StderrPipe(std::io::Error),
    #[error("cannot create the folder {dir} for {what}: {source}")]
    OutputDir {
        what: &'static str,
        dir: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot start component {component} ({exec}): {source}")]
    Spawn {
        component: String,
        exec: PathBuf,
        source: std::io::Error,
    },
    #[error("internal error: {0}")]
    Internal(String),
    #[error("supervision failed: {0}")]
    Supervise(std::io::Error),
    #[error("cannot create a voter's heartbeat page: {0}")]
    Heartbeat(std::io::Error),
}

/// A component (or its voter) that did not exit cleanly.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Failure {
    pub component: String,
    pub status: ExitStatus,
    /// What bootstrap knows beyond the status (a voter it found stalled and killed).
    pub why: Option<String>,
    /// The last line an unprotected component wrote to stderr that says something: after a
    /// failure it is most often the reason.
    pub last_words: Option<String>,
}

impl Failure {
    /// How it failed: `exit status 3 (why); its last stderr line: error: no map file`.
    pub fn described(&self) -> String {
        let mut text = self.status.to_string();
        if let Some(why) = &self.why {
            text.push_str(&format!(" ({why})"));
        }
        if let Some(words) = &self.last_words {
            text.push_str(&format!("; its last stderr line: {words}"));
        }
        text
    }
}

impl std::fmt::Display for Failure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.component, self.described())
    }
}

/// How the run ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Ending {
    /// Every component exited on its own.
    Finished,
    /// bootstrap was asked to stop by this signal.
    Stopped(i32),
}

/// What happened.
#[derive(Debug, Clone)]
pub struct RunReport {
    pub ending: Ending,
    /// Components that failed (for a stopped run, only those that failed before the stop).
    pub failures: Vec<Failure>,
    /// Counts from the voters' events (`None` if there were no voters or the stream did not end).
    pub events: Option<EventSummary>,
    /// What the live status showed, at the end.
    pub tally: TallyData,
    /// The injector's log, if an injector ran.
    pub injections: Option<Vec<Injected>>,
    /// Where the events, state and injection files are (`None`: not kept).
    pub files: Files,
    pub elapsed: Duration,
}

impl RunReport {
    /// bootstrap's exit status: 0 clean, 1 a component failed, 128+signal when stopped.
    pub fn exit_code(&self) -> u8 {
        match self.ending {
            Ending::Stopped(sig) => (128 + sig).clamp(0, 255) as u8,
            Ending::Finished if self.failures.is_empty() => 0,
            Ending::Finished => 1,
        }
    }
}

/// A direct child: an unprotected component or a voter.
#[derive(Debug)]
struct Child {
    component: String,
    pid: libc::pid_t,
    status: Option<ExitStatus>,
    /// Exited after the stop began (its status is then our doing, not a failure).
    after_stop: bool,
    /// Not part of the system (the injector): stopped once every component has ended.
    helper: bool,
    /// Was sent SIGTERM because the components had ended.
    told_to_stop: bool,
    /// A voter's heartbeat.
    watch: Option<VoterWatch>,
    /// What bootstrap did to it and why, for the report.
    why: Option<String>,
    /// An unprotected component's stderr, relayed behind its name (`component_stderr.rs`).
    stderr: Option<ComponentStderr>,
    /// A restartable voter: what it takes to start its successor (see `respawn`).
    respawn: Option<VoterSpawn>,
}

/// Both ends of a channel until they are handed to the components.
#[derive(Debug, Default)]
struct ChannelEnds {
    read: Option<OwnedFd>,
    write: Option<OwnedFd>,
}

/// Runs `plan` to the end. Every child is gone when this returns, whatever it returns.
/// Keeps the voters' task clocks quick to open: a task clock that never counts, held by
/// bootstrap on itself for the system's life (`sys::TaskClock::open_idle`). A voter opens a
/// task clock on a late replica at its first look (`voter/src/starvation.rs`); without an
/// event already open on the machine, that `perf_event_open` waits for an RCU grace period,
/// and when spinning real-time replicas hold every CPU (a hung replica here, one of another
/// component there) the wait took 200 ms: a hang was reported 300 ms late, and the maze robot
/// drove a stale command into a wall. The event is bound to bootstrap, which mostly sleeps:
/// every context switch of the task it is bound to passes through perf, and held by each
/// voter on its parent (3bdcfd7) it was the bench harness's, in every round, for one-CPU round
/// trips 1.0–1.5 µs slower. `None` where perf events are refused: the looks then have no
/// task clock either.
fn hold_task_clocks_ready() -> Option<sys::TaskClock> {
    match sys::TaskClock::open_idle(0) {
        Ok(clock) => Some(clock),
        Err(e) => {
            tracing::debug!(error = %e, "no idle task clock (perf events refused)");
            None
        }
    }
}

pub fn run(plan: &SystemPlan, opts: &RunOptions) -> Result<RunReport, RunError> {
    // Before any thread: every thread inherits this mask, so the signals reach only the
    // signalfd. Children inherit it too, and get their own (`base_command`).
    // SIGHUP (a closed terminal, a dropped ssh connection) and SIGQUIT stop the system like
    // SIGTERM: nothing bootstrap started may outlive it.
    let signals = sys::signal_fd(&[
        Signal::SIGINT,
        Signal::SIGTERM,
        Signal::SIGHUP,
        Signal::SIGQUIT,
        Signal::SIGCHLD,
    ])
    .map_err(RunError::Signals)?;

    let voter = if plan.has_protected() {
        match &opts.voter {
            Some(v) => Some(v.clone()),
            None => {
                return Err(RunError::VoterMissing(
                    "no voter binary was given".to_owned(),
                ))
            }
        }
    } else {
        None
    };

    let _task_clocks_ready = voter.as_ref().and_then(|_| hold_task_clocks_ready());

    sys::set_child_subreaper().map_err(RunError::Subreaper)?;
    // From here on, whatever happens, the guard sweeps.
    let mut guard = SweepGuard::new();
    let mark = crate::keeper::new_mark();
    if let Some(exe) = &opts.keeper {
        match Keeper::start(exe, &mark) {
            Ok(keeper) => {
                tracing::debug!(pid = keeper.pid(), "keeper started");
                guard.own_keeper(keeper);
            }
            Err(e) => tracing::warn!(
                "cannot start the keeper ({e}): if bootstrap is SIGKILLed, what a component \
                 started itself will outlive it"
            ),
        }
    }

    let started = Instant::now();
    // Before the events file is emptied: a refused run must leave its files as they were.
    // (Written whole and renamed into place at each change, a live view takes no lock: the
    // file says whose it is.)
    if let Some(path) = &opts.state_file {
        if let Some(pid) = crate::live::running_bootstrap_of(path) {
            return Err(RunError::OutputInUse {
                what: "state file",
                path: path.clone(),
                holder: format!("another s3res-bootstrap that runs (pid {pid})"),
            });
        }
    }
    let events_log = match &opts.events_file {
        Some(path) => {
            make_parent(path, "the events file")?;
            Some(open_events_file(path)?)
        }
        None => None,
    };

    let socket_dir = if voter.is_some() {
        let tmp = std::env::temp_dir();
        let dir = crate::runtime_dir::make(&tmp)
            .map_err(|source| RunError::SocketDir { dir: tmp, source })?;
        let path = dir.path().to_owned();
        guard.own_socket_dir(dir);
        Some(path)
    } else {
        None
    };

    let mut channels = open_channels(plan)?;

    // Whether SCHED_RR can be had is found out once, here, and said once; the voters are told.
    let sched = SystemSched::for_system(plan);
    sched.warn_once();
    say_memory_lock_limit(plan);
    // An injector needs the live view; without a file named for it, one in the private folder.
    let injector = match (&opts.injector, &plan.inject, &socket_dir) {
        (Some(bin), Some(inject), Some(dir)) => Some((bin, inject, dir)),
        _ => None,
    };
    let state_file = match (&opts.state_file, &injector) {
        (Some(p), _) => Some(p.clone()),
        (None, Some((_, _, dir))) => Some(dir.join("state.json")),
        (None, None) => None,
    };
    let live = match &state_file {
        Some(path) => {
            make_parent(path, "the state file")?;
            Some(
                LiveState::create(crate::live::initial_view(plan), path.clone()).map_err(
                    |source| RunError::StateFile {
                        path: path.clone(),
                        source,
                    },
                )?,
            )
        }
        None => None,
    };
    // The injector's log goes beside the events file, or into the private folder.
    let injections_file = injector.map(|(_, _, dir)| match &opts.events_file {
        Some(ev) => ev.with_file_name("injections.jsonl"),
        None => dir.join("injections.jsonl"),
    });

    let tally = Tally::default();
    let (events_reader, events_write) = if voter.is_some() {
        let (r, w) = sys::pipe().map_err(RunError::EventsPipe)?;
        let allowed = sys::cpu_affinity(0).unwrap_or_default();
        let cpus = crate::sched::events_reader_cpus(plan, &allowed);
        let reader = EventReader::spawn(r, events_log, live.clone(), Some(tally.clone()), cpus)
            .map_err(RunError::EventsPipe)?;
        (Some(reader), Some(w))
    } else {
        (None, None)
    };

    // On a terminal every process's stderr comes through bootstrap, printed whole above the
    // status line.
    let mut console = Console::start(opts.console);
    let (stderr_done, stderr_write) = if opts.console == ConsoleMode::Terminal {
        let (r, w) = sys::pipe().map_err(RunError::StderrPipe)?;
        (
            Some(forward_stderr(r).map_err(RunError::StderrPipe)?),
            Some(w),
        )
    } else {
        (None, None)
    };
    let out = Outputs {
        stdout_to_stderr: plan.uses_stdout(),
        stderr: stderr_write.as_ref().map(|w| w.as_fd()),
        log: opts.child_log.as_deref(),
        mark: &mark,
    };

    let mut children: Vec<Child> = Vec::with_capacity(plan.components.len());
    for (index, c) in plan.components.iter().enumerate() {
        let mut watch = None;
        let mut respawn = None;
        let mut stderr = None;
        let pid = match (&voter, &socket_dir, &events_write) {
            (Some(voter), Some(dir), Some(ev)) if c.is_protected() => {
                let w = VoterWatch::new(c).map_err(RunError::Heartbeat)?;
                let (pid, spawn) = spawn_voter(
                    plan,
                    c,
                    index,
                    &sched,
                    voter,
                    dir,
                    ev.as_fd(),
                    w.page().as_fd(),
                    &mut channels,
                    &out,
                )?;
                watch = Some(w);
                respawn = spawn;
                pid
            }
            _ if c.is_protected() => {
                return Err(RunError::Internal(format!(
                    "protected component {} without a voter",
                    c.name
                )))
            }
            _ => {
                let (pid, relayed) = spawn_direct(c, &mut channels, &out)?;
                sched.apply_direct(index, c, pid);
                stderr = relayed;
                pid
            }
        };
        tracing::info!(
            component = %c.name,
            pid,
            "started {}",
            if c.is_protected() {
                format!("under {VOTER_BIN} with {} replica(s)", c.replicas)
            } else {
                "directly".to_owned()
            }
        );
        if let Some(live) = &live {
            live.update(|v| match v.components.get_mut(&c.name) {
                Some(lc) if lc.protected => {
                    lc.voter_pid = Some(pid);
                    true
                }
                Some(lc) => {
                    lc.pid = Some(pid);
                    true
                }
                None => false,
            });
        }
        children.push(Child {
            component: c.name.clone(),
            pid,
            status: None,
            after_stop: false,
            helper: false,
            told_to_stop: false,
            watch,
            why: None,
            respawn,
            stderr,
        });
    }
    if let (Some((bin, inject, _)), Some(state), Some(log)) =
        (injector, &state_file, &injections_file)
    {
        let pid = spawn_injector(bin, inject, state, log, &out)?;
        tracing::info!(
            pid,
            "started the injector: {} at {} Hz into {} (seed {})",
            inject.faults.join("/"),
            inject.rate_hz,
            inject.components.join(", "),
            inject.seed
        );
        children.push(Child {
            component: "injector".to_owned(),
            pid,
            status: None,
            after_stop: false,
            helper: true,
            told_to_stop: false,
            watch: None,
            why: None,
            respawn: None,
            stderr: None,
        });
    }
    // Our copies of every pipe end must go, or readers never see end of stream.
    drop(channels);
    drop(events_write);
    drop(stderr_write);

    let injected = |path: &Option<PathBuf>| {
        path.as_ref().map_or(0, |p| {
            read_injections(p)
                .0
                .iter()
                .filter(|i| i.ts_ns.is_some())
                .count()
        })
    };
    let mut last_count = (Instant::now(), 0u64);
    let ending = supervise(
        &signals,
        &mut children,
        opts.stop_timeout,
        console.period(),
        &mut |children| {
            // The injector's log is read at most once a second for the count.
            if last_count.0.elapsed() >= Duration::from_secs(1) {
                last_count = (Instant::now(), injected(&injections_file) as u64);
            }
            let snapshot = tally.snapshot();
            console.tick(|elapsed| {
                // Unprotected components only: a voter that died is replaced, or its
                // component's failure stops the system, and its replicas' state is the tally's.
                let failed: Vec<String> = children
                    .iter()
                    .filter(|c| !c.after_stop && !c.helper && c.watch.is_none())
                    .filter_map(|c| {
                        let status = c.status.filter(|s| !s.success())?;
                        Some(format!("{} (failed: {status})", c.component))
                    })
                    .collect();
                status_line(plan, &snapshot, elapsed, last_count.1, &failed)
            });
        },
    )?;
    // What was kept for voters' successors: the events pipe (and the channels downstream)
    // end only once these copies are gone.
    for c in &mut children {
        c.respawn = None;
    }
    // Read before the private folder (which may hold it) goes.
    let injections = injections_file.as_ref().map(|p| {
        let (list, bad) = read_injections(p);
        if bad > 0 {
            tracing::warn!(
                "{bad} unreadable line(s) in the injection log {}",
                p.display()
            );
        }
        list
    });

    // A state file in the private folder goes with it: nobody reads it after the sweep, and
    // the updates below would fail on a missing folder and warn about it.
    if let (Some(live), None) = (&live, &opts.state_file) {
        live.close();
    }
    guard.finish();
    let events = events_reader.and_then(|r| {
        let s = r.finish(EVENTS_DRAIN);
        if s.is_none() {
            tracing::warn!("the events pipe is still open; the summary is incomplete");
        }
        s
    });
    if let Some(live) = &live {
        live.update(|v| {
            v.running = false;
            true
        });
    }
    // Every writer is gone after the sweep; the last lines are on their way, also those of
    // components that ended well (printed after the verdict, or not at all, otherwise).
    let drained_by = Instant::now() + EVENTS_DRAIN;
    if let Some(done) = stderr_done {
        let _ = done.recv_timeout(drained_by.saturating_duration_since(Instant::now()));
    }
    for c in &mut children {
        if let Some(relay) = c.stderr.as_mut() {
            relay.wait_ended(drained_by);
        }
    }
    console.finish();

    let in_private = |p: &Option<PathBuf>| {
        p.clone()
            .filter(|p| socket_dir.as_ref().is_none_or(|d| !p.starts_with(d)))
    };
    let files = Files {
        events: opts.events_file.clone(),
        events_unsaved: events.as_ref().and_then(|e| e.unsaved.clone()),
        state: in_private(&state_file),
        injections: in_private(&injections_file),
        outcome: plan.outcome.clone(),
    };
    let failures = children
        .iter_mut()
        .filter(|c| !c.after_stop)
        .filter_map(|c| match c.status {
            Some(s) if !s.success() => Some(Failure {
                component: c.component.clone(),
                status: s,
                why: c.why.clone(),
                // Read to its end above (or as far as the drain allowed).
                last_words: c.stderr.as_mut().and_then(|e| e.last_words(Duration::ZERO)),
            }),
            _ => None,
        })
        .collect();
    Ok(RunReport {
        ending,
        failures,
        events,
        tally: tally.snapshot(),
        injections,
        files,
        elapsed: started.elapsed(),
    })
}

/// The events file at `path`, emptied — once this bootstrap holds its lock: another bootstrap
/// running on the same file (the same description started twice in one folder) would have
/// truncated it under the first one's feet and mixed its lines into it. The lock goes with
/// the file, when the events reader closes it at the end.
fn open_events_file(path: &Path) -> Result<File, RunError> {
    let err = |source| RunError::EventsFile {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(false)
        .open(path)
        .map_err(err)?;
    match file.try_lock() {
        Ok(()) => {}
        Err(std::fs::TryLockError::WouldBlock) => {
            return Err(RunError::OutputInUse {
                what: "events file",
                path: path.to_path_buf(),
                // A lock says nobody's name; a bootstrap is who takes this one.
                holder: "another process that holds its lock (an s3res-bootstrap that runs?)"
                    .to_owned(),
            });
        }
        // A file system that takes no lock: as before, unguarded.
        Err(std::fs::TryLockError::Error(e)) => tracing::warn!(
            path = %path.display(),
            "cannot lock the events file ({e}); another bootstrap writing it would not be noticed"
        ),
    }
    file.set_len(0).map_err(err)?;
    Ok(file)
}

/// Says once, for the whole system, that replicas lock only the memory they have at start when
/// a lock limit binds them (their processes are this one's user and limits): each replica
/// would otherwise say it, and the voters too.
fn say_memory_lock_limit(plan: &SystemPlan) {
    if let Some(note) = memory_lock_note(plan) {
        tracing::warn!("{note}");
    }
}

/// What a lock limit leaves of the replicas' memory locking, if one binds them (`--check` says
/// it too); `None` without protected components or without a limit that binds.
pub fn memory_lock_note(plan: &SystemPlan) -> Option<String> {
    if !plan.components.iter().any(|c| c.is_protected()) {
        return None;
    }
    let limit = binding_lock_limit()?;
    Some(format!(
        "memory locking is limited to {} KiB (RLIMIT_MEMLOCK, no CAP_IPC_LOCK): replicas and \
         voters lock the memory they have at start where it fits under the limit (a replica \
         has a few MiB by then; each one it does not fit runs unlocked), never what they \
         allocate later (that could then fail), so a round may still take a page fault. Raise \
         the limit (`ulimit -l`, memlock in limits.conf) or grant CAP_IPC_LOCK to lock it all",
        limit / 1024
    ))
}

/// This process's lock limit, if it binds the processes it starts: they run as its user, with
/// its limits and capabilities.
fn binding_lock_limit() -> Option<u64> {
    replica_rt::memory::memlock_limit().filter(|_| !replica_rt::memory::locks_future_memory())
}

/// Creates the folder `path` goes into, if it has one and it is missing.
fn make_parent(path: &Path, what: &'static str) -> Result<(), RunError> {
    match path.parent().filter(|d| !d.as_os_str().is_empty()) {
        Some(dir) => std::fs::create_dir_all(dir).map_err(|source| RunError::OutputDir {
            what,
            dir: dir.to_path_buf(),
            source,
        }),
        None => Ok(()),
    }
}

/// Where the processes' output goes.
struct Outputs<'a> {
    /// fd 1 carries frames: every process's stdout goes to its stderr.
    stdout_to_stderr: bool,
    /// The pipe bootstrap reads stderr from (terminal mode); `None`: inherited.
    stderr: Option<std::os::fd::BorrowedFd<'a>>,
    /// `RUST_LOG` to set.
    log: Option<&'a str>,
    /// This run's [`crate::keeper::ENV_SYSTEM_MARK`].
    mark: &'a str,
}

/// `s3res-inject storm` with the description's `inject`, the live view and the log file.
fn spawn_injector(
    bin: &Path,
    inject: &InjectPlan,
    state: &Path,
    log: &Path,
    out: &Outputs,
) -> Result<libc::pid_t, RunError> {
    let spawn_err = |source| RunError::Spawn {
        component: "injector".to_owned(),
        exec: bin.to_path_buf(),
        source,
    };
    let mut cmd = base_command(bin, "injector", out).map_err(spawn_err)?;
    cmd.arg("storm")
        .arg("--state")
        .arg(state)
        .arg("--log")
        .arg(log)
        .arg("--faults")
        .arg(inject.faults.join(","))
        .arg("--rate")
        .arg(inject.rate_hz.to_string())
        .arg("--seed")
        .arg(inject.seed.to_string())
        .arg("--components")
        .arg(inject.components.join(","))
        .arg("--after")
        .arg(inject.after_s.to_string());
    // If bootstrap dies (even by SIGKILL), the injector stops: it would go on firing faults
    // at the pids of a system that is gone (SIGTERM: it stops as when bootstrap stops it).
    sys::die_with_parent(&mut cmd, libc::SIGTERM);
    let child = cmd.spawn().map_err(spawn_err)?;
    Ok(child.id() as libc::pid_t)
}

/// One pipe per channel; `stdin`/`stdout` endpoints get a duplicate of bootstrap's fd 0/1.
fn open_channels(plan: &SystemPlan) -> Result<Vec<ChannelEnds>, RunError> {
    let mut out = Vec::with_capacity(plan.channels.len());
    for (index, ch) in plan.channels.iter().enumerate() {
        let fail = |source| RunError::Channel {
            index,
            from: ch.from.clone(),
            to: ch.to.clone(),
            source,
        };
        let ends = match (&ch.from, &ch.to) {
            (Endpoint::Stdin, _) => ChannelEnds {
                read: Some(
                    std::io::stdin()
                        .as_fd()
                        .try_clone_to_owned()
                        .map_err(fail)?,
                ),
                write: None,
            },
            (_, Endpoint::Stdout) => ChannelEnds {
                read: None,
                write: Some(
                    std::io::stdout()
                        .as_fd()
                        .try_clone_to_owned()
                        .map_err(fail)?,
                ),
            },
            _ => {
                let (r, w) = sys::pipe().map_err(fail)?;
                ChannelEnds {
                    read: Some(r),
                    write: Some(w),
                }
            }
        };
        out.push(ends);
    }
    Ok(out)
}

/// The fds a component's ports need, in port order (inputs then outputs), taken out of
/// `channels` so that bootstrap's copies close as soon as the child has its own.
fn take_port_fds(
    c: &ComponentPlan,
    channels: &mut [ChannelEnds],
) -> Result<Vec<OwnedFd>, RunError> {
    let mut fds = Vec::with_capacity(c.inputs.len() + c.outputs.len());
    for (p, is_input) in c
        .inputs
        .iter()
        .map(|p| (p, true))
        .chain(c.outputs.iter().map(|p| (p, false)))
    {
        let fd = match p.channel {
            Some(i) => {
                let ends = channels.get_mut(i).ok_or_else(|| {
                    RunError::Internal(format!("port {}.{} names channel {i}", c.name, p.name))
                })?;
                let end = if is_input {
                    ends.read.take()
                } else {
                    ends.write.take()
                };
                end.ok_or_else(|| {
                    RunError::Internal(format!(
                        "channel {i} end for {}.{} was already handed out",
                        c.name, p.name
                    ))
                })?
            }
            // A declared output nobody reads: its frames are discarded.
            None => File::options()
                .write(true)
                .open("/dev/null")
                .map_err(|source| RunError::Spawn {
                    component: c.name.clone(),
                    exec: c.exec.clone(),
                    source,
                })?
                .into(),
        };
        fds.push(fd);
    }
    Ok(fds)
}

/// Target fd numbers 3, 4, ... for `fds`.
fn fd_mapping(fds: &[OwnedFd]) -> Vec<(RawFd, RawFd)> {
    fds.iter()
        .enumerate()
        .map(|(i, fd)| (fd.as_raw_fd(), FIRST_PORT_FD + i as RawFd))
        .collect()
}

fn base_command(exec: &Path, component: &str, out: &Outputs) -> Result<Command, std::io::Error> {
    let mut cmd = Command::new(exec);
    // Not this process's mask (SIGTERM and SIGCHLD blocked for the signalfd): a component
    // must be able to catch the SIGTERM that stops it.
    sys::start_with_signals_blocked(&mut cmd, sys::TERMINAL_SIGNALS);
    cmd.stdin(Stdio::null());
    let stderr = match out.stderr {
        Some(fd) => fd.try_clone_to_owned()?,
        None => std::io::stderr().as_fd().try_clone_to_owned()?,
    };
    if out.stdout_to_stderr {
        cmd.stdout(Stdio::from(stderr.try_clone()?));
    }
    if out.stderr.is_some() {
        cmd.stderr(Stdio::from(stderr));
    }
    if let Some(filter) = out.log {
        cmd.env("RUST_LOG", filter);
    }
    // Whatever bootstrap inherited must not make a component believe it is a replica.
    cmd.env_remove(ENV_VOTER_SOCKET)
        .env_remove(ENV_REPLICA)
        .env_remove(ENV_STDERR_RELAYED)
        .env_remove(crate::keeper::ENV_KEEPER_OF)
        .env(ENV_COMPONENT, component)
        // Inherited by whatever the process starts: the keeper finds them all by it.
        .env(crate::keeper::ENV_SYSTEM_MARK, out.mark);
    // The lock limit was said once (`say_memory_lock_limit`): a voter's or replica's refused
    // lock is not said again by each.
    if binding_lock_limit().is_some() {
        cmd.env(ENV_MEMORY_LOCK_SAID, "1");
    } else {
        cmd.env_remove(ENV_MEMORY_LOCK_SAID);
    }
    Ok(cmd)
}

fn spawn_direct(
    c: &ComponentPlan,
    channels: &mut [ChannelEnds],
    out: &Outputs,
) -> Result<(libc::pid_t, Option<ComponentStderr>), RunError> {
    let spawn_err = |source| RunError::Spawn {
        component: c.name.clone(),
        exec: c.exec.clone(),
        source,
    };
    let fds = take_port_fds(c, channels)?;
    let mapping = fd_mapping(&fds);
    let ports = PortMap {
        ports: c
            .inputs
            .iter()
            .map(|p| (p, Direction::In))
            .chain(c.outputs.iter().map(|p| (p, Direction::Out)))
            .zip(&mapping)
            .map(|((p, dir), &(_, fd))| PortSpec {
                name: p.name.clone(),
                dir,
                fd,
                max_frame: p.max_frame,
            })
            .collect(),
    };
    let mut cmd = base_command(&c.exec, &c.name, out).map_err(spawn_err)?;
    // If bootstrap dies (even by SIGKILL), an unprotected component dies with it.
    sys::die_with_parent(&mut cmd, libc::SIGKILL);
    cmd.args(&c.args).env(ENV_PORTS, ports.to_env());
    // Its stderr (and its stdout, where fd 1 carries frames) into a pipe of its own, whose
    // lines bootstrap relays behind its name; without a pipe or a thread to read it, bare
    // lines as before.
    let mut relay = match sys::pipe().and_then(|(r, w)| Ok((ComponentStderr::start(r)?, w))) {
        Ok((relay, w)) => {
            if out.stdout_to_stderr {
                cmd.stdout(Stdio::from(w.try_clone().map_err(spawn_err)?));
            }
            cmd.stderr(Stdio::from(w));
            cmd.env(ENV_STDERR_RELAYED, "1");
            Some(relay)
        }
        Err(e) => {
            tracing::warn!(component = %c.name, "its stderr is not relayed behind its name: {e}");
            None
        }
    };
    sys::map_fds_on_exec(&mut cmd, mapping);
    let child = cmd.spawn().map_err(spawn_err)?;
    let pid = child.id() as libc::pid_t;
    // The command holds our copy of the pipe's write end: the relay would never see its end.
    drop(cmd);
    // `fds` drops here: the child has its copies.
    drop(fds);
    if let Some(relay) = relay.as_mut() {
        relay.relay_as(format!("[{} pid {pid}] ", c.name));
    }
    Ok((pid, relay))
}

#[allow(clippy::too_many_arguments)]
fn spawn_voter(
    plan: &SystemPlan,
    c: &ComponentPlan,
    index: usize,
    sched: &SystemSched,
    voter: &Path,
    socket_dir: &Path,
    events_fd: BorrowedFd<'_>,
    heartbeat_fd: BorrowedFd<'_>,
    channels: &mut [ChannelEnds],
    out: &Outputs,
) -> Result<(libc::pid_t, Option<VoterSpawn>), RunError> {
    let spawn_err = |source| RunError::Spawn {
        component: c.name.clone(),
        exec: voter.to_path_buf(),
        source,
    };
    let socket_path = socket_dir.join(format!("v{index}.sock"));
    if socket_path.as_os_str().len() > SUN_PATH_MAX {
        return Err(RunError::SocketPathTooLong(socket_path));
    }
    let fds = take_port_fds(c, channels)?;
    // Every fd the voter gets, with the number it lands on.
    let mut handed: Vec<(BorrowedFd, RawFd)> = fds
        .iter()
        .enumerate()
        .map(|(i, fd)| (fd.as_fd(), FIRST_PORT_FD + i as RawFd))
        .collect();
    let events_target = FIRST_PORT_FD + handed.len() as RawFd;
    handed.push((events_fd, events_target));
    let heartbeat_target = events_target + 1;
    handed.push((heartbeat_fd, heartbeat_target));
    // A restartable voter's socket and journal are bootstrap's: they outlive the voter.
    let restartable = respawn::restartable(c);
    let owned = if restartable {
        let socket = respawn::bind_socket(&socket_path).map_err(|source| RunError::Spawn {
            component: c.name.clone(),
            exec: socket_path.clone(),
            source,
        })?;
        let journal = replica_rt::shared::memfd(c"s3res-journal").map_err(spawn_err)?;
        let park = if respawn::parks_pipes(c) {
            Some(respawn::park_pair().map_err(spawn_err)?)
        } else {
            None
        };
        // The replicas' answer stamps, so that a successor reads those of the replicas it
        // adopts (they keep the page they were given).
        let stamps = replica_rt::shared::memfd(c"s3res-answer-stamps").map_err(spawn_err)?;
        Some((socket, journal, park, stamps))
    } else {
        None
    };
    let (socket_fd, journal_fd, park_fds, stamps_fd) = match &owned {
        Some((socket, journal, park, stamps)) => {
            let socket_target = heartbeat_target + 1;
            handed.push((socket.as_fd(), socket_target));
            handed.push((journal.as_fd(), socket_target + 1));
            let park_fds = park.as_ref().map(|(tx, rx)| {
                handed.push((tx.as_fd(), socket_target + 2));
                handed.push((rx.as_fd(), socket_target + 3));
                [socket_target + 2, socket_target + 3]
            });
            handed.push((stamps.as_fd(), socket_target + 4));
            (
                Some(socket_target),
                Some(socket_target + 1),
                park_fds,
                Some(socket_target + 4),
            )
        }
        None => (None, None, None, None),
    };
    let external = |ports: &[crate::plan::PortPlan], first: usize| -> Vec<ExternalPort> {
        ports
            .iter()
            .enumerate()
            .map(|(i, p)| ExternalPort {
                name: p.name.clone(),
                fd: FIRST_PORT_FD + (first + i) as RawFd,
                max_frame: p.max_frame,
            })
            .collect()
    };
    let voter_plan = VoterPlan {
        system: plan.name.clone(),
        component: c.name.clone(),
        exec: c.exec.clone(),
        args: c.args.clone(),
        replicas: c.replicas,
        timeout_us: c.timeout_us,
        inputs: external(&c.inputs, 0),
        outputs: external(&c.outputs, c.inputs.len()),
        rounds: c.rounds.clone(),
        events_fd: Some(events_target),
        heartbeat_fd: Some(heartbeat_target),
        socket_path,
        socket_fd,
        journal_fd,
        park_fds,
        stamps_fd,
        adopt: None,
        restart_timeout_ms: c.restart_timeout_ms,
        start_timeout_ms: c.start_timeout_ms,
        max_restarts: c.max_restarts,
        restart_window_ms: c.restart_window_ms,
        priority: c.priority,
        cpus: c.cpus.clone(),
        voter_cpu: c.voter_cpu,
        schedule: c.schedule,
        realtime: sched.realtime(),
        nice: sched.fallback(index),
        mode: c.mode,
        window: c.window,
        monitors: c.monitors.clone(),
        captures: c.captures.clone(),
        framing: c.framing,
        lock_memory: c.lock_memory,
        cpu_idle: c.cpu_idle,
        spin_us: c.spin_us,
        preload: c.preload.clone(),
    };
    let mapping: Vec<(RawFd, RawFd)> = handed
        .iter()
        .map(|(fd, target)| (fd.as_raw_fd(), *target))
        .collect();
    let spawn = if restartable {
        Some(VoterSpawn {
            voter: voter.to_path_buf(),
            plan: voter_plan.clone(),
            kept: respawn::keep(&handed).map_err(spawn_err)?,
            stderr: out
                .stderr
                .map(|fd| fd.try_clone_to_owned())
                .transpose()
                .map_err(spawn_err)?,
            stdout_to_stderr: out.stdout_to_stderr,
            log: out.log.map(str::to_owned),
            mark: out.mark.to_owned(),
            budget: RestartBudget::new(c.max_restarts, Duration::from_millis(c.restart_window_ms)),
            generation: 1,
        })
    } else {
        None
    };
    let pid = start_voter(voter, &c.name, &voter_plan, mapping, out).map_err(spawn_err)?;
    drop(fds);
    drop(owned);
    Ok((pid, spawn))
}

/// Starts `s3res-voter` with `plan`, its fds mapped as `mapping` says.
fn start_voter(
    voter: &Path,
    component: &str,
    plan: &VoterPlan,
    mapping: Vec<(RawFd, RawFd)>,
    out: &Outputs,
) -> std::io::Result<libc::pid_t> {
    let mut cmd = base_command(voter, component, out)?;
    // If bootstrap dies (even by SIGKILL), the voter is asked to stop: it kills its replicas
    // and everything re-parented to it, then exits.
    sys::die_with_parent(&mut cmd, libc::SIGTERM);
    // Cleared at the exec if the voter has file capabilities: it asks again (contract).
    cmd.env(ENV_SUPERVISOR_PID, std::process::id().to_string());
    cmd.arg("--plan").arg(plan.to_json());
    sys::map_fds_on_exec(&mut cmd, mapping);
    let child = cmd.spawn()?;
    Ok(child.id() as libc::pid_t)
}

/// A stop signal this soon after the first is a copy of it, not a second stop (which kills at
/// once): a wrapper that forwards what it got with the process group (timeout(1) does) turned
/// one Ctrl-C into two, and the components were SIGKILLed without their SIGTERM. A person
/// pressing Ctrl-C again takes longer.
const SAME_STOP: Duration = Duration::from_millis(250);

/// Starts a successor to the voter of `c` that adopts its replicas (see `respawn`); its pid.
fn restart_voter(c: &mut Child, why: &str) -> std::io::Result<libc::pid_t> {
    let spawn = c
        .respawn
        .as_mut()
        .ok_or_else(|| std::io::Error::other("not restartable"))?;
    let plan = spawn.successor_plan(c.pid, why);
    let out = Outputs {
        stdout_to_stderr: spawn.stdout_to_stderr,
        stderr: spawn.stderr.as_ref().map(|fd| fd.as_fd()),
        log: spawn.log.as_deref(),
        mark: &spawn.mark,
    };
    start_voter(&spawn.voter, &c.component, &plan, spawn.mapping(), &out)
}

/// Waits for every child, reaping as SIGCHLD arrives; on SIGINT/SIGTERM stops them: SIGTERM,
/// then SIGKILL after `stop_timeout`. A second stop signal kills at once. Helpers (the
/// injector) get SIGTERM once every component has ended, SIGKILL `stop_timeout` later.
/// `tick` runs after every wake-up, and at least every `period`.
fn supervise(
    signals: &SignalFd,
    children: &mut [Child],
    stop_timeout: Duration,
    period: Option<Duration>,
    tick: &mut dyn FnMut(&[Child]),
) -> Result<Ending, RunError> {
    let mut stop: Option<(i32, Instant)> = None;
    // The stop signal that began the stop, and when it came (not a stop bootstrap began).
    let mut first_signal: Option<(i32, Instant)> = None;
    let mut killed = false;
    let mut helpers_deadline: Option<Instant> = None;
    // A component failed beyond recovery (its voter gave up): the system stops, and the run
    // ends as failed rather than as stopped by a signal.
    let mut failed = false;
    loop {
        // Stop signals before the children's deaths: a child killed by the same signal as
        // bootstrap (one sent to the whole process group or cgroup: timeout(1), systemd,
        // Slurm) is reaped as stopped, not as failed.
        loop {
            match signals.read_signal() {
                Ok(Some(info)) => {
                    let sig = info.ssi_signo as i32;
                    if STOP_SIGNALS.contains(&sig) {
                        match stop {
                            None => {
                                tracing::info!(
                                    "stopping (signal {}): SIGTERM to every component",
                                    signal_name(sig)
                                );
                                stop = Some((sig, Instant::now() + stop_timeout));
                                first_signal = Some((sig, Instant::now()));
                                stop_live(children);
                            }
                            // A copy of the first: a wrapper that forwards the signal it got
                            // with the whole process group (timeout(1), a supervisor's script)
                            // makes one Ctrl-C two. Not a second stop.
                            Some(_)
                                if first_signal.is_some_and(|(first, at)| {
                                    first == sig && at.elapsed() < SAME_STOP
                                }) =>
                            {
                                tracing::debug!(
                                    "a second stop signal right after the first: the same stop"
                                );
                            }
                            Some(_) if !killed => {
                                tracing::warn!("second stop signal: killing every component now");
                                signal_live(children, libc::SIGKILL);
                                killed = true;
                            }
                            Some(_) => {}
                        }
                    }
                }
                Ok(None) => break,
                Err(e) => return Err(RunError::Supervise(std::io::Error::from(e))),
            }
        }
        reap_all(children, stop.is_some());
        tick(children);
        if children.iter().all(|c| c.status.is_some()) {
            // Everything ended in one pass: a voter killed first takes its neighbours with it
            // (a broken pipe, an end of input), all reaped together. Its death is still why.
            if stop.is_none() {
                if let Some(why) = children.iter().find_map(unreplaced_voter_death) {
                    crate::logging::say(&format!("{why}; stopping the system"));
                    failed = true;
                }
            }
            break;
        }
        let now = Instant::now();
        if stop.is_none() {
            if let Some(why) = voter_failure(children, now) {
                // One line on stderr, whatever the log level: this is why the run failed.
                crate::logging::say(&format!("{why}; stopping the system"));
                failed = true;
                stop = Some((libc::SIGTERM, now + stop_timeout));
                stop_live(children);
            }
        }
        let system_done = children
            .iter()
            .filter(|c| !c.helper)
            .all(|c| c.status.is_some());
        if system_done && stop.is_none() {
            match helpers_deadline {
                None => {
                    for c in children
                        .iter_mut()
                        .filter(|c| c.helper && c.status.is_none())
                    {
                        c.told_to_stop = true;
                        let _ = sys::kill(c.pid, libc::SIGTERM);
                    }
                    helpers_deadline = Some(now + stop_timeout);
                }
                Some(d) if now >= d => {
                    for c in children.iter().filter(|c| c.helper && c.status.is_none()) {
                        tracing::warn!(component = %c.component, "did not stop on SIGTERM; killing it");
                        let _ = sys::kill(c.pid, libc::SIGKILL);
                    }
                    helpers_deadline = Some(now + Duration::from_millis(50));
                }
                Some(_) => {}
            }
        }
        if let Some((_, deadline)) = stop {
            if now >= deadline && !killed {
                tracing::warn!(
                    "components still running {} ms after SIGTERM; killing them",
                    stop_timeout.as_millis()
                );
                signal_live(children, libc::SIGKILL);
                killed = true;
            }
        }
        let timeout = match stop {
            // After SIGKILL the children die promptly; poll so a lost wake-up cannot hang us,
            // and leave the rest to the sweep if one is stuck in the kernel.
            Some(_) if killed => Some(Duration::from_millis(50)),
            Some((_, deadline)) => Some(deadline.saturating_duration_since(now)),
            None => helpers_deadline.map(|d| d.saturating_duration_since(now)),
        };
        // The voters' heartbeats are looked at while the system runs.
        let watching = stop.is_none() && children.iter().any(|c| c.watch.is_some());
        let period = match (period, watching) {
            (Some(p), true) => Some(p.min(WATCH_PERIOD)),
            (None, true) => Some(WATCH_PERIOD),
            (p, false) => p,
        };
        let timeout = match (timeout, period) {
            (Some(t), Some(p)) => Some(t.min(p)),
            (t, p) => t.or(p),
        };
        let mut pfd = [libc::pollfd {
            fd: signals.as_fd().as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        }];
        sys::ppoll(&mut pfd, timeout).map_err(RunError::Supervise)?;
        if killed && stop.is_some_and(|(_, d)| Instant::now() >= d + Duration::from_secs(1)) {
            // Whatever is still there resists SIGKILL; the sweep will report it.
            break;
        }
    }
    Ok(match stop {
        Some((sig, _)) if !failed => Ending::Stopped(sig),
        _ => Ending::Finished,
    })
}

/// Why a voter's end stops the system, where nothing would replace it: it gave up on its
/// component, or it died and nothing was kept to restart it with.
fn unreplaced_voter_death(c: &Child) -> Option<String> {
    c.watch.as_ref()?;
    match c.status? {
        ExitStatus::Code(VOTER_GAVE_UP) => Some(format!(
            "component {} failed beyond recovery (its voter's reason is above)",
            c.component
        )),
        status if !status.success() && c.respawn.is_none() => {
            let died = c.why.clone().unwrap_or_else(|| status.to_string());
            Some(format!(
                "the voter of component {} (pid {}) died: {died}; nothing was kept to restart it with",
                c.component, c.pid
            ))
        }
        _ => None,
    }
}

/// Looks at every voter: one that died is replaced by a successor that adopts its replicas,
/// if its component is restartable and its restart budget allows; one that stands still is
/// killed (and replaced once reaped). Returns why the system must stop, if it must: a voter
/// gave up on its component (its reason is already on stderr), or died and cannot be
/// replaced.
fn voter_failure(children: &mut [Child], now: Instant) -> Option<String> {
    for c in children.iter_mut().filter(|c| c.watch.is_some()) {
        match c.status {
            Some(status) if !status.success() => {
                if let Some(why) = unreplaced_voter_death(c) {
                    return Some(why);
                }
                let died = c.why.take().unwrap_or_else(|| status.to_string());
                let spawn = c.respawn.as_mut()?;
                if let ExitStatus::Code(_) = status {
                    // It ended itself with an error (said above): a successor would meet the
                    // same one. Only a voter killed (or found standing still) is replaced.
                    return Some(format!(
                        "the voter of component {} (pid {}) failed: {died}",
                        c.component, c.pid
                    ));
                }
                if !spawn.budget.take(now) {
                    return Some(format!(
                        "the voter of component {} (pid {}) died: {died}; its restart budget is spent ({})",
                        c.component,
                        c.pid,
                        spawn.budget.describe()
                    ));
                }
                let old = c.pid;
                match restart_voter(c, &died) {
                    Ok(pid) => {
                        crate::logging::say(&format!(
                            "the voter of component {} (pid {old}) died: {died}; started voter pid {pid} to adopt its replicas",
                            c.component
                        ));
                        c.pid = pid;
                        c.status = None;
                        c.after_stop = false;
                        if let Some(w) = c.watch.as_mut() {
                            w.restart(now);
                        }
                    }
                    Err(e) => {
                        return Some(format!(
                            "the voter of component {} (pid {old}) died: {died}; could not start its successor: {e}",
                            c.component
                        ))
                    }
                }
            }
            // It ended cleanly: what bootstrap kept for a successor must go, or the readers
            // downstream of it would never see the end of their input.
            Some(_) => c.respawn = None,
            None => {
                let Some(still) = c.watch.as_mut().and_then(|w| w.stalled(now)) else {
                    continue;
                };
                let state = match sys::process_state(c.pid) {
                    Some('T' | 't') => "it is stopped",
                    Some('D') => "it is blocked in the kernel",
                    Some(_) => "it is stuck",
                    None => "it is gone",
                };
                let what = format!(
                    "made no progress for {:.1} s ({state})",
                    still.as_secs_f64()
                );
                // Not reaped yet, so the pid is still the voter's. SIGKILL reaches a
                // stopped process too.
                let _ = sys::kill(c.pid, libc::SIGKILL);
                if c.respawn.is_some() {
                    // Replaced once reaped (above), with this as the reason.
                    c.why = Some(what);
                    continue;
                }
                c.why = Some(format!("made no progress for {:.1} s", still.as_secs_f64()));
                return Some(format!(
                    "the voter of component {} (pid {}) {what}; killed it",
                    c.component, c.pid
                ));
            }
        }
    }
    None
}

fn reap_all(children: &mut [Child], stopping: bool) {
    loop {
        match sys::reap_any() {
            Ok(Some((pid, status))) => match children.iter_mut().find(|c| c.pid == pid) {
                Some(c) => {
                    c.status = Some(status);
                    // A voter bootstrap killed for standing still failed, stop or not.
                    c.after_stop = (stopping || c.told_to_stop) && c.why.is_none();
                    if status.success() {
                        tracing::info!(component = %c.component, pid, "exited cleanly");
                    } else if stopping {
                        tracing::debug!(component = %c.component, pid, "stopped: {status}");
                    } else {
                        tracing::warn!(component = %c.component, pid, "failed: {status}");
                    }
                }
                // A descendant re-parented to us because its parent died.
                None => tracing::debug!(pid, "reaped orphaned descendant: {status}"),
            },
            Ok(None) => return,
            Err(e) => {
                tracing::warn!("waitpid failed: {e}");
                return;
            }
        }
    }
}

/// Stops the system: tells the voters through their heartbeat pages that it is the system
/// that stops (a voter that got a SIGTERM from elsewhere first reads it there), then SIGTERM to
/// every child still running.
fn stop_live(children: &[Child]) {
    for w in children.iter().filter_map(|c| c.watch.as_ref()) {
        w.system_stopping();
    }
    signal_live(children, libc::SIGTERM);
}

fn signal_live(children: &[Child], sig: i32) {
    for c in children.iter().filter(|c| c.status.is_none()) {
        // Not reaped yet, so the pid is still this child's (at worst a zombie).
        if let Err(e) = sys::kill(c.pid, sig) {
            tracing::debug!(component = %c.component, pid = c.pid, "kill({sig}) failed: {e}");
        }
    }
}

/// `s3res-voter`'s exit status when its component failed beyond recovery (restart budget spent,
/// or no replica can be started).
const VOTER_GAVE_UP: i32 = 3;

/// The signals that stop the system.
const STOP_SIGNALS: [i32; 4] = [libc::SIGINT, libc::SIGTERM, libc::SIGHUP, libc::SIGQUIT];

fn signal_name(sig: i32) -> &'static str {
    match sig {
        libc::SIGINT => "SIGINT",
        libc::SIGTERM => "SIGTERM",
        libc::SIGHUP => "SIGHUP",
        libc::SIGQUIT => "SIGQUIT",
        _ => "signal",
    }
}
