//! End to end: the voter does not care whether n is 3 or 5, and a fork child whose donor dies
//! stays under the voter's control (it is a subreaper).

use std::time::{Duration, Instant};

use s3res_tests::{assert_sink_whole, echo_pipeline, EventKind, RecoveryMethod, System};

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

/// A replica forked from a donor is the donor's child. Kill the donor right after the
/// recovery: the child is re-parented to the voter, which must still detect its faults, replace
/// it, and reap it — no zombie, no stray process.
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
    s3res_tests::kill_pid(first[&2], libc::SIGKILL).unwrap();
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
    s3res_tests::kill_pid(donor, libc::SIGKILL).unwrap();
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

    // 3. The orphan is still controlled: its death is a crash, it is replaced and reaped.
    s3res_tests::kill_pid(child, libc::SIGKILL).unwrap();
    run.wait_for_event(
        |e| e.kind == EventKind::Crash && e.pid == Some(child),
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

    run.wait_success(LIMIT);
    assert_sink_whole(&run.path("summary.json"), count);
}
