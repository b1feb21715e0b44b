//! Running a system once, bounded, with a schedule of injections, and leaving nothing behind.
//!
//! bootstrap is started in its own process group, in the run's own folder (its working
//! directory, so a sink's `--summary task.json` lands there), with an environment mark that every
//! process of the run inherits. When the run ends — on its own, or killed at the time limit —
//! whatever still carries the mark is killed, and this process, a child subreaper, reaps it.
//!
//! If this process dies without that (SIGKILL, an out-of-memory kill, a batch system's kill),
//! bootstrap gets SIGKILL from the kernel (`PR_SET_PDEATHSIG`): its voters then get SIGTERM and
//! kill their replicas, its unprotected components get SIGKILL (bootstrap's own death signals),
//! so a run never outlives the injector that started it, whatever process group it is in.

use std::fs::File;
use std::os::unix::process::CommandExt as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use s3res_protocol::event::Event;
use s3res_protocol::live::{LiveView, ReplicaState};

use crate::fault::{fire, FireError, RegOptions};
use crate::schedule::Planned;
use crate::target::{resolve, Pick};

/// Why an injection planned after its run had ended was not delivered (`miss`): not a miss of
/// the target, so the tables count these apart (`after_end`).
pub const SYSTEM_ENDED: &str = "the system had ended (or hit the time limit)";

/// Environment variable carrying the run's mark; inherited by every process of the run.
pub const MARK_ENV: &str = "S3RES_INJECT_RUN";
/// How long bootstrap gets after SIGTERM (at the time limit) before its group is killed.
const STOP_GRACE: Duration = Duration::from_secs(5);

/// How to run.
#[derive(Debug, Clone)]
pub struct RunSetup {
    pub bootstrap: PathBuf,
    /// Absolute path of the description.
    pub system: PathBuf,
    /// The run's folder (exists; files are written into it).
    pub dir: PathBuf,
    /// Unique text marking this run's processes.
    pub mark: String,
    /// Components whose every replica must be running before the window opens.
    pub targets: Vec<String>,
    pub pick: Pick,
    pub reg: RegOptions,
    /// Bound on the whole run (start to exit).
    pub limit: Duration,
    /// Bound on start-up (until every target runs).
    pub ready_limit: Duration,
}

/// One planned injection after its instant.
#[derive(Debug, Clone)]
pub struct Attempt {
    pub planned: Planned,
    /// CLOCK_MONOTONIC just before the signal went out; `None` if it did not.
    pub ts_ns: Option<u64>,
    pub slot: Option<usize>,
    pub pid: Option<i32>,
    /// Why it was not delivered.
    pub miss: Option<String>,
    /// What the injector reported (register flips).
    pub injector: Option<serde_json::Value>,
}

/// What happened in one run.
#[derive(Debug)]
pub struct RunResult {
    pub attempts: Vec<Attempt>,
    /// bootstrap's exit (None if it could not be started).
    pub status: Option<ExitStatus>,
    /// Killed at the time limit.
    pub timed_out: bool,
    /// Every target was running before the window opened.
    pub ready: bool,
    pub events: Vec<Event>,
    pub unreadable_events: u64,
    pub duration: Duration,
    /// Processes of the run still alive after bootstrap ended (killed by the sweep).
    pub leftovers: usize,
    /// Could not start bootstrap at all.
    pub error: Option<String>,
    /// Cut short by a stop request (SIGINT/SIGTERM to the injector): not a result.
    pub interrupted: bool,
}

impl RunResult {
    pub fn stdout_path(dir: &Path) -> PathBuf {
        dir.join("stdout")
    }
}

/// Runs the system once with `schedule`. `stop` is asked now and then whether to cut the run
/// short (it is then stopped like a run at its time limit, and marked interrupted).
pub fn run_once(setup: &RunSetup, schedule: &[Planned], stop: &dyn Fn() -> bool) -> RunResult {
    let started = Instant::now();
    let events_path = setup.dir.join("events.jsonl");
    let state_path = setup.dir.join("state.json");
    let mut result = RunResult {
        attempts: Vec::new(),
        status: None,
        timed_out: false,
        ready: false,
        events: Vec::new(),
        unreadable_events: 0,
        duration: Duration::ZERO,
        leftovers: 0,
        error: None,
        interrupted: false,
    };
    let mut child = match spawn(setup, &events_path, &state_path) {
        Ok(c) => c,
        Err(e) => {
            result.error = Some(format!("cannot start {}: {e}", setup.bootstrap.display()));
            result.attempts = schedule
                .iter()
                .map(|p| missed(p, "the system did not start"))
                .collect();
            return result;
        }
    };
    let deadline = started + setup.limit;

    result.ready = wait_ready(
        &mut child,
        &state_path,
        &setup.targets,
        started + setup.ready_limit.min(setup.limit),
        stop,
    );
    let window_start = Instant::now();
    for p in schedule {
        if !result.ready {
            result.attempts.push(missed(p, "the targets never all ran"));
            continue;
        }
        let due = window_start + Duration::from_nanos(p.at_ns);
        if !sleep_until_or_exit(&mut child, due.min(deadline), stop) || Instant::now() >= deadline {
            result.attempts.push(missed(p, SYSTEM_ENDED));
            continue;
        }
        result.attempts.push(inject_now(setup, &state_path, p));
    }

    let (status, timed_out) = finish(&mut child, deadline, stop);
    result.interrupted = stop();
    result.status = status;
    result.timed_out = timed_out && !result.interrupted;
    result.leftovers = sweep(&setup.mark);
    result.duration = started.elapsed();
    let (events, bad) = read_events(&events_path);
    result.events = events;
    result.unreadable_events = bad;
    result
}

fn spawn(setup: &RunSetup, events: &Path, state: &Path) -> std::io::Result<Child> {
    let stdout = File::create(RunResult::stdout_path(&setup.dir))?;
    let stderr = File::create(setup.dir.join("stderr"))?;
    let mut cmd = Command::new(&setup.bootstrap);
    cmd.arg("-q")
        .arg("--events")
        .arg(events)
        .arg("--state")
        .arg(state)
        .arg(&setup.system)
        .current_dir(&setup.dir)
        .env(MARK_ENV, &setup.mark)
        .stdin(Stdio::null())
        .stdout(stdout)
        .stderr(stderr)
        .process_group(0);
    // Its own group (so a terminal's ^C reaches only us, and the run is killed as one group),
    // but it dies with us: nothing tracks it otherwise once we are gone (a batch system's
    // process tracking by group, for one, does not see it).
    replica_rt::sys::die_with_parent(&mut cmd, libc::SIGKILL);
    cmd.spawn()
}

fn missed(p: &Planned, why: &str) -> Attempt {
    Attempt {
        planned: p.clone(),
        ts_ns: None,
        slot: None,
        pid: None,
        miss: Some(why.to_owned()),
        injector: None,
    }
}

/// Resolves the target in the live view and fires.
pub fn inject_now(setup: &RunSetup, state_path: &Path, p: &Planned) -> Attempt {
    let view = match LiveView::read(state_path) {
        Ok(v) => v,
        Err(e) => return missed(p, &e),
    };
    let target = match resolve(&view, &p.component, p.draw, setup.pick) {
        Ok(t) => t,
        Err(e) => {
            let mut a = missed(p, &e.to_string());
            a.slot = e.slot();
            return a;
        }
    };
    let ts = replica_rt::sys::monotonic_ns();
    let mut a = Attempt {
        planned: p.clone(),
        ts_ns: Some(ts),
        slot: target.slot,
        pid: Some(target.pid),
        miss: None,
        injector: None,
    };
    match fire(&p.action, target.pid, &setup.reg) {
        Ok(rep) => {
            a.ts_ns = Some(crate::fault::injected_at(ts, rep.as_ref()));
            a.injector = rep;
        }
        Err(e @ FireError::Gone(_)) | Err(e @ FireError::Signal { .. }) => {
            a.ts_ns = None;
            a.miss = Some(e.to_string());
        }
        Err(e) => {
            a.ts_ns = None;
            a.miss = Some(e.to_string());
            tracing::error!("{e}");
        }
    }
    a
}

/// Waits until the live view shows every target running. `false` if bootstrap exited or the
/// deadline passed first.
fn wait_ready(
    child: &mut Child,
    state: &Path,
    targets: &[String],
    deadline: Instant,
    stop: &dyn Fn() -> bool,
) -> bool {
    loop {
        if let Ok(view) = LiveView::read(state) {
            if all_running(&view, targets) {
                return true;
            }
        }
        if Instant::now() >= deadline || stop() || matches!(child.try_wait(), Ok(Some(_)) | Err(_))
        {
            return false;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Every target component is spawned and, if protected, each of its replicas runs.
pub fn all_running(view: &LiveView, targets: &[String]) -> bool {
    view.running
        && targets.iter().all(|t| match view.components.get(t) {
            Some(c) if c.protected => {
                c.voter_pid.is_some()
                    && c.replicas
                        .iter()
                        .all(|r| r.state == ReplicaState::Running && r.pid.is_some())
            }
            Some(c) => c.pid.is_some(),
            None => false,
        })
}

/// Sleeps until `due`; `false` if bootstrap exited meanwhile (it is not reaped here) or a stop
/// was requested.
fn sleep_until_or_exit(child: &mut Child, due: Instant, stop: &dyn Fn() -> bool) -> bool {
    loop {
        if !matches!(child.try_wait(), Ok(None)) || stop() {
            return false;
        }
        let now = Instant::now();
        if now >= due {
            return true;
        }
        std::thread::sleep((due - now).min(Duration::from_millis(20)));
    }
}

/// Waits for bootstrap until `deadline`; then SIGTERM, and after a grace SIGKILL to its whole
/// process group. Returns its status and whether it had to be stopped.
fn finish(
    child: &mut Child,
    deadline: Instant,
    stop: &dyn Fn() -> bool,
) -> (Option<ExitStatus>, bool) {
    loop {
        match child.try_wait() {
            Ok(Some(st)) => return (Some(st), false),
            Ok(None) => {}
            Err(_) => break,
        }
        if Instant::now() >= deadline || stop() {
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let pid = child.id() as i32;
    tracing::debug!(pid, "run hit its time limit: stopping bootstrap");
    let _ = replica_rt::sys::kill(pid, libc::SIGTERM);
    let grace = Instant::now() + STOP_GRACE;
    while Instant::now() < grace {
        if let Ok(Some(st)) = child.try_wait() {
            return (Some(st), true);
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    // bootstrap is not reaped yet, so its pid still names its group.
    let _ = replica_rt::sys::kill(-pid, libc::SIGKILL);
    (child.wait().ok(), true)
}

/// Kills every process carrying `mark` and reaps what is re-parented to us; returns how many
/// were found alive.
pub fn sweep(mark: &str) -> usize {
    let needle = format!("{MARK_ENV}={mark}");
    let mut found = 0;
    for round in 0..100 {
        let pids = marked(&needle);
        if pids.is_empty() {
            break;
        }
        if round == 0 {
            found = pids.len();
            tracing::debug!(?pids, "processes of the run still alive: killing them");
        }
        for pid in pids {
            let _ = replica_rt::sys::kill(pid, libc::SIGKILL);
        }
        reap_orphans();
        std::thread::sleep(Duration::from_millis(20));
    }
    reap_orphans();
    found
}

/// Live (not zombie) processes whose environment holds `needle`.
fn marked(needle: &str) -> Vec<i32> {
    let Ok(dir) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    let me = std::process::id() as i32;
    dir.filter_map(|e| e.ok()?.file_name().to_str()?.parse::<i32>().ok())
        .filter(|&pid| pid != me)
        .filter(|&pid| {
            std::fs::read(format!("/proc/{pid}/environ"))
                .is_ok_and(|env| env.split(|&b| b == 0).any(|var| var == needle.as_bytes()))
        })
        .collect()
}

/// Reaps any exited child without blocking (orphans re-parented to us as subreaper).
fn reap_orphans() {
    while let Ok(Some(_)) = replica_rt::sys::reap_any() {}
}

/// Reads an events file; the events and how many lines were not events.
pub fn read_events(path: &Path) -> (Vec<Event>, u64) {
    let Ok(text) = std::fs::read_to_string(path) else {
        return (Vec::new(), 0);
    };
    let mut bad = 0;
    let events = text
        .lines()
        .filter(|l| !l.trim().is_empty())
        .filter_map(|l| match serde_json::from_str(l) {
            Ok(e) => Some(e),
            Err(_) => {
                bad += 1;
                None
            }
        })
        .collect();
    (events, bad)
}
