//! The core cases with the system running as an unprivileged user: `nobody` (through
//! `setpriv`) when the tests run as root, else the user running them. Without CAP_SYS_NICE
//! SCHED_RR is refused: bootstrap says so exactly once, and the system runs on nice values
//! with every fault still detected and repaired. (The whole suite can be run this way with
//! `S3RES_TEST_UNPRIVILEGED=1`.)

use std::path::{Path, PathBuf};
use std::time::Duration;

use s3res_testkit::{
    assert_sink_whole, echo_pipeline, signals, EventKind, RecoveryMethod, Rng, RunningSystem,
    System,
};

const LIMIT: Duration = Duration::from_secs(120);
const TIMEOUT_US: u64 = 300_000;
const REFUSED: &str = "SCHED_RR refused";

/// How often the refusal must be said: once where SCHED_RR is refused, never where it is not.
fn expected_refusals(sys: &System) -> usize {
    let allowed = sys.round_robin_allowed();
    eprintln!("SCHED_RR allowed for the unprivileged system: {allowed}");
    usize::from(!allowed)
}

/// The echo demo (`examples/echo-demo.json`, which gives every component a priority), as README
/// runs it.
#[test]
fn unprivileged_echo_demo_runs_clean_and_says_once_that_sched_rr_is_refused() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/echo-demo.json");
    let description = std::fs::read_to_string(&path).unwrap();
    let sys = System::new().unprivileged();
    let refusals = expected_refusals(&sys);
    let mut run = sys.start(&description);
    let out = run.wait_success(LIMIT);
    let starts = out
        .events
        .iter()
        .filter(|e| e.component == "echo" && e.kind == EventKind::Start)
        .count();
    assert_eq!(starts, 3, "{:#?}", out.events);
    assert_said(&out.stderr, refusals);
}

/// source → echo (TMR, priority 30) → sink, started as an unprivileged user, with its three
/// replicas running. Returns the system, the sink's summary path, and how often the refusal
/// of SCHED_RR must be said.
fn start_prioritized_echo(count: u32, hz: u32) -> (RunningSystem, PathBuf, usize) {
    let sys = System::new().unprivileged();
    let refusals = expected_refusals(&sys);
    let echo = format!(
        r#"{{ "exec": "s3res-echo", "args": ["--stateful"], "redundancy": "tmr",
             "timeout_us": {TIMEOUT_US}, "priority": 30 }}"#
    );
    let summary = sys.path("summary.json");
    let mut run = sys.start(&echo_pipeline(&summary, &echo, count, hz));
    run.wait_for_replicas("echo", 3);
    (run, summary, refusals)
}

fn assert_said(stderr: &str, refusals: usize) {
    assert_eq!(stderr.matches(REFUSED).count(), refusals, "{stderr}");
}

/// A component that allocates after `init` (16 MiB, as the docs advise: what the rounds need,
/// before the first round) runs under a user's lock limit (8 MiB by default): replicas lock
/// what they have at start, not later allocations, and bootstrap says so once. Before, every
/// replica locked future memory too, its allocation failed, and so did every replica started
/// again, until the component failed (a newcomer without root found it).
#[test]
fn unprivileged_replicas_that_allocate_after_init_run_under_a_lock_limit() {
    let sys = System::new().unprivileged();
    let echo = format!(
        r#"{{ "exec": "s3res-echo", "args": ["--stateful", "--heap-mib", "16"],
             "redundancy": "tmr", "timeout_us": {TIMEOUT_US} }}"#
    );
    let summary = sys.path("summary.json");
    let count = 200;
    let mut run = sys.start(&echo_pipeline(&summary, &echo, count, 500));
    let out = run.wait_success(LIMIT);
    assert!(
        !out.events.iter().any(|e| e.kind.is_fault()),
        "{:#?}",
        out.events
    );
    assert_sink_whole(&summary, count);
    // The tests' own limit is the system's (inherited); as root they are not bound by it.
    let limited = replica_rt::memory::memlock_limit().is_some();
    let said = out.stderr.matches("memory locking is limited to").count();
    assert_eq!(said, usize::from(limited), "{}", out.stderr);
    // `--check` says it too, before anything runs.
    let sys = System::new().unprivileged();
    let summary = sys.path("summary.json");
    let mut check = sys
        .arg("--check")
        .start(&echo_pipeline(&summary, &echo, count, 500));
    let out = check.wait_success(LIMIT);
    let said = out.stdout.matches("memory locking is limited to").count();
    assert_eq!(said, usize::from(limited), "{}", out.stdout);
}

/// Random replicas are killed while frames flow; each is a crash, repaired by fork with state.
#[test]
fn unprivileged_tmr_survives_kills_with_state() {
    let mut rng = Rng::from_env();
    let count = 4000;
    let kills = 20;
    let (mut run, summary, refusals) = start_prioritized_echo(count, 1000);
    for _ in 0..kills {
        let slot = rng.below(3) as usize;
        let pid = run.replica_pids("echo")[&slot];
        s3res_testkit::kill_pid(pid, libc::SIGKILL).expect("kill replica");
        let rec = run.wait_for_event(
            |e| e.kind == EventKind::Recovery && e.replica == Some(slot) && e.pid == Some(pid),
            Duration::from_secs(20),
        );
        assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
        assert_eq!(rec.state_lost, Some(false), "{rec:?}");
        std::thread::sleep(Duration::from_millis(rng.range(5, 30)));
    }
    assert!(
        run.try_status().is_none(),
        "the system finished before all kills were done; make the source longer"
    );
    let out = run.wait_success(LIMIT);
    let crashes = out
        .events
        .iter()
        .filter(|e| e.kind == EventKind::Crash)
        .count();
    assert_eq!(crashes, kills, "{:#?}", out.events);
    assert_sink_whole(&summary, count);
    assert_said(&out.stderr, refusals);
}

/// One corrupted frame is outvoted and its replica replaced.
#[test]
fn unprivileged_tmr_outvotes_a_corrupted_frame() {
    let count = 1500;
    let (mut run, summary, refusals) = start_prioritized_echo(count, 500);
    let pid = run.replica_pids("echo")[&2];
    s3res_testkit::sigqueue(pid, signals::INJECT_SDC, 13).expect("sigqueue");
    let sdc = run.wait_for_event(|e| e.kind == EventKind::Sdc, Duration::from_secs(20));
    assert_eq!(sdc.replica, Some(2), "{sdc:?}");
    assert_eq!(sdc.pid, Some(pid), "{sdc:?}");
    let rec = run.wait_for_event(
        |e| e.kind == EventKind::Recovery && e.pid == Some(pid),
        Duration::from_secs(20),
    );
    assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
    let out = run.wait_success(LIMIT);
    assert_sink_whole(&summary, count);
    assert_said(&out.stderr, refusals);
}

/// A voter given a file capability (docs/real-time.md's `setcap cap_sys_nice+ep`, for users
/// without root) lost the parent-death signal bootstrap set up for it: an exec that raises
/// privileges clears it. A SIGKILLed bootstrap then left that voter and its three replicas
/// running on, fed by bootstrap's stdin (here a pipe the test keeps open, as a producer piped
/// into bootstrap would), with nobody supervising them. The voter asks for the signal again
/// once it runs.
#[test]
#[cfg_attr(
    not(s3res_setcap),
    ignore = "needs root, `setpriv` and `setcap` (libcap2-bin) to run a voter with a file capability as a user"
)]
fn a_voter_with_a_file_capability_still_ends_with_a_sigkilled_bootstrap() {
    s3res_testkit::require(s3res_testkit::is_root(), "not root");
    let (read_end, write_end) = std::io::pipe().expect("a pipe for bootstrap's stdin");
    let sys = System::new()
        .unprivileged()
        .stdin_pipe(std::os::fd::OwnedFd::from(read_end));
    // In a folder of its own: handing the temp dir to the user chowns its entries, and a
    // chown drops a file's capabilities.
    let folder = sys.path("capped");
    std::fs::create_dir(&folder).unwrap();
    let voter = folder.join("s3res-voter");
    std::fs::copy(s3res_testkit::bin_path("s3res-voter"), &voter).unwrap();
    let setcap = std::process::Command::new("setcap")
        .arg("cap_sys_nice+ep")
        .arg(&voter)
        .status()
        .expect("running setcap");
    assert!(setcap.success(), "setcap: {setcap}");
    let sys = sys.env("S3RES_VOTER", &voter);
    let desc = format!(
        r#"{{ "name": "capped",
  "components": {{ "echo": {{ "exec": "s3res-echo", "redundancy": "tmr", "timeout_us": {TIMEOUT_US} }} }},
  "channels": [ {{ "from": "stdin", "to": "echo.in" }}, {{ "from": "echo.out", "to": "stdout" }} ] }}"#
    );
    let mut run = sys.start(&desc);
    run.wait_for_replicas("echo", 3);
    let pid = run.voter_of("echo").expect("the echo's voter runs");
    assert_eq!(
        std::fs::read_link(format!("/proc/{pid}/exe")).unwrap(),
        voter,
        "the voter is the copy with the capability"
    );
    let group = |run: &RunningSystem| -> Vec<s3res_testkit::procs::ProcStat> {
        s3res_testkit::procs::in_group(run.pgid())
            .into_iter()
            .filter(|p| !p.is_zombie())
            .collect()
    };
    assert!(group(&run).len() >= 5, "bootstrap, voter, three replicas");
    s3res_testkit::kill_pid(run.pid(), libc::SIGKILL).expect("SIGKILL bootstrap");
    s3res_testkit::wait_until(
        "every process of the system to end after bootstrap's SIGKILL",
        Duration::from_secs(10),
        || (run.try_status().is_some() && group(&run).is_empty()).then_some(()),
    );
    drop(write_end);
    run.assert_nothing_left();
}
