//! End to end: the voter does not care whether n is 3 or 5, and a fork child whose donor dies
//! stays under the voter's control (it is a subreaper).

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use s3res_testkit::procs::{self, ProcStat};
use s3res_testkit::{
    assert_sink_whole, echo_pipeline, signals, EventKind, RecoveryMethod, RunningSystem, System,
};

const LIMIT: Duration = Duration::from_secs(90);

/// Five replicas, two of which answer wrongly in the same round: the three good ones outvote
/// them, both are blamed and both are rebuilt by fork.
#[test]
fn five_replicas_outvote_two_corrupt_ones_in_one_round() {
    let count = 400;
    let sys = System::new();
    let echo = r#"{ "exec": "s3res-misbehave", "args": ["--stateful", "--mode", "corrupt", "--replica", "1,3", "--at", "100"],
               "redundancy": "tmr", "replicas": 5, "timeout_us": 300000 }"#;
    let desc = echo_pipeline(&sys.path("summary.json"), echo, count, 500);
    let mut run = sys.start(&desc);
    let out = run.wait_success(LIMIT);

    let sdc: Vec<_> = out
        .events
        .iter()
        .filter(|e| e.kind == EventKind::Sdc)
        .collect();
    assert_eq!(sdc.len(), 2, "{sdc:?}");
    let mut blamed: Vec<usize> = sdc.iter().map(|e| e.replica.expect("attributed")).collect();
    blamed.sort();
    assert_eq!(blamed, [1, 3]);
    assert_eq!(sdc[0].round, sdc[1].round, "both in one round: {sdc:?}");
    let recoveries: Vec<_> = out
        .events
        .iter()
        .filter(|e| e.kind == EventKind::Recovery)
        .collect();
    assert_eq!(recoveries.len(), 2, "{recoveries:?}");
    assert!(recoveries
        .iter()
        .all(|e| e.method == Some(RecoveryMethod::Fork)));
    let starts = out
        .events
        .iter()
        .filter(|e| e.kind == EventKind::Start)
        .count();
    assert_eq!(starts, 5);
    assert_sink_whole(&run.path("summary.json"), count);
}

fn parent_of(pid: i32) -> Option<i32> {
    replica_rt::sys::parent_pid(pid)
}

/// Waits (up to 5 s) until the living and zombie `s3res-echo` processes of the system are
/// exactly the replicas the event log names: a killed replica that was not reaped (zombie) or a
/// fork child nobody controls (stray) fails the test.
fn assert_only_current_replicas(run: &RunningSystem) {
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        let expected: BTreeSet<i32> = run.replica_pids("echo").into_values().collect();
        let found: Vec<ProcStat> = procs::all()
            .into_iter()
            .filter(|p| p.comm == "s3res-echo" && belongs_to(p.pid, run.pid()))
            .collect();
        let pids: BTreeSet<i32> = found.iter().map(|p| p.pid).collect();
        if pids == expected && found.iter().all(|p| !p.is_zombie()) {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "echo processes are not exactly the current replicas {expected:?}:\n{}",
            found
                .iter()
                .map(|p| format!("  {p}"))
                .collect::<Vec<_>>()
                .join("\n")
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Whether `ancestor` is `pid` or one of its ancestors.
fn belongs_to(mut pid: i32, ancestor: i32) -> bool {
    while pid > 1 {
        if pid == ancestor {
            return true;
        }
        match parent_of(pid) {
            Some(p) => pid = p,
            None => return false,
        }
    }
    false
}

/// A replica forked from a donor is the donor's child. Kill the donor right after the
/// recovery: the child is re-parented to the voter, which must still vote on it, detect its
/// faults (a hang, which only the voter's deadline can see), kill, replace and reap it. After
/// every step the system holds exactly the current replicas — no zombie, no stray process.
#[test]
fn orphaned_fork_child_stays_under_control() {
    let count = 2500;
    let sys = System::new();
    let echo = r#"{ "exec": "s3res-echo", "args": ["--stateful"], "redundancy": "tmr", "timeout_us": 300000 }"#;
    let desc = echo_pipeline(&sys.path("summary.json"), echo, count, 500);
    let mut run = sys.start(&desc);
    run.wait_for_replicas("echo", 3);
    let first = run.replica_pids("echo");
    let voter = parent_of(first[&0]).expect("replica 0 has a parent");

    // 1. Kill replica 2: it is rebuilt as a fork child of a donor.
    s3res_testkit::kill_pid(first[&2], libc::SIGKILL).unwrap();
    let rec = run.wait_for_event(
        |e| e.kind == EventKind::Recovery && e.pid == Some(first[&2]),
        Duration::from_secs(20),
    );
    let child = rec.new_pid.unwrap();
    let donor_slot = rec.donor.expect("forked from a donor");
    let donor = first[&donor_slot];
    assert_eq!(
        parent_of(child),
        Some(donor),
        "the new replica is its donor's child"
    );

    // 2. Kill the donor at once: its child is orphaned and must come to the voter.
    s3res_testkit::kill_pid(donor, libc::SIGKILL).unwrap();
    run.wait_for_event(
        |e| e.kind == EventKind::Recovery && e.pid == Some(donor),
        Duration::from_secs(20),
    );
    let deadline = Instant::now() + Duration::from_secs(10);
    while parent_of(child) != Some(voter) {
        assert!(
            Instant::now() < deadline,
            "orphan {child} was not re-parented to the voter {voter}"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_only_current_replicas(&run);

    // 3. The orphan still takes part in the vote: rounds go on (it reads input and answers
    //    100 more times, and frames reach the sink) and it is never blamed.
    let seen = run.events().len();
    let sink = run.sink_mark();
    let before = procs::io(child).expect("the orphan's io");
    s3res_testkit::wait_until(
        "the orphan to take part in 100 more rounds",
        Duration::from_secs(20),
        || {
            let now = procs::io(child)?;
            (now.syscr >= before.syscr + 100 && now.syscw >= before.syscw + 100).then_some(())
        },
    );
    run.assert_sink_progressed(sink, "the orphan's rounds");
    let blamed: Vec<_> = run.events()[seen..]
        .iter()
        .filter(|e| e.pid == Some(child))
        .cloned()
        .collect();
    assert!(blamed.is_empty(), "the orphan was blamed: {blamed:?}");

    // 4. The orphan is still controlled: made to spin, it misses a deadline (a hang, seen by
    //    the voter alone), and the voter kills, replaces and reaps it.
    s3res_testkit::kill_pid(child, signals::inject_cfe()).unwrap();
    run.wait_for_event(
        |e| e.kind == EventKind::Hang && e.pid == Some(child),
        Duration::from_secs(20),
    );
    run.wait_for_event(
        |e| e.kind == EventKind::Recovery && e.pid == Some(child),
        Duration::from_secs(20),
    );
    let deadline = Instant::now() + Duration::from_secs(10);
    while std::path::Path::new(&format!("/proc/{child}")).exists() {
        assert!(
            Instant::now() < deadline,
            "orphan {child} was not reaped (zombie or alive)"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_only_current_replicas(&run);

    run.wait_success(LIMIT);
    assert_sink_whole(&run.path("summary.json"), count);
}
