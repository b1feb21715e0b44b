//! End to end: stream mode (S³RES VoterD). `source → batch (protected, "mode": "stream") →
//! sink`, where `s3res-batch` answers nothing for most inputs and then a burst, so outputs are
//! not one per input. Every test runs the real bootstrap, voter and replicas.

use std::time::Duration;

use s3res_tests::{
    assert_sink_whole, echo_pipeline, signals, sink_summary, Event, EventKind, RecoveryMethod, Rng,
    RunningSystem, System,
};

/// Generous, so that a loaded CI machine does not see false hangs; the tests check behaviour,
/// not speed.
const TIMEOUT_US: u64 = 300_000;
const LIMIT: Duration = Duration::from_secs(120);

/// source → batch (stream mode) → sink, with the sink's summary in `summary.json`.
fn batch_system(
    sys: &System,
    redundancy: &str,
    batch_args: &[&str],
    timeout_us: u64,
    count: u32,
    hz: u32,
) -> String {
    let batch = format!(
        r#"{{ "exec": "s3res-batch", "args": {}, "redundancy": "{redundancy}", "mode": "stream", "timeout_us": {timeout_us} }}"#,
        serde_json::to_string(batch_args).unwrap()
    );
    echo_pipeline(&sys.path("summary.json"), &batch, count, hz)
}

fn of_kind(events: &[Event], kind: EventKind) -> Vec<&Event> {
    events
        .iter()
        .filter(|e| e.kind == kind && e.component == "echo")
        .collect()
}

fn is_recovery_of(e: &Event, slot: usize, old_pid: i32) -> bool {
    e.kind == EventKind::Recovery && e.replica == Some(slot) && e.pid == Some(old_pid)
}

fn faults(events: &[Event]) -> Vec<&Event> {
    events
        .iter()
        .filter(|e| !matches!(e.kind, EventKind::Start | EventKind::Recovery))
        .collect()
}

/// Waits until the sink has seen output of the batch (frames are flowing through the voter).
fn wait_for_replicas(run: &mut RunningSystem, replicas: usize) {
    run.wait_for_replicas("echo", replicas);
}

#[test]
fn stream_tmr_passes_bursts_through_whole() {
    let count = 600;
    let sys = System::new();
    let desc = batch_system(
        &sys,
        "tmr",
        &["--every", "7", "--vary", "--stateful"],
        TIMEOUT_US,
        count,
        1000,
    );
    let summary = sys.path("summary.json");
    let mut run = sys.start(&desc);
    let out = run.wait_success(LIMIT);
    assert!(faults(&out.events).is_empty(), "{:?}", faults(&out.events));
    assert_sink_whole(&summary, count);
}

/// Kills a random replica many times while bursts flow; every kill is a crash repaired by fork
/// with the state kept (held frames and counter), and the sink sees every frame once, in order.
#[test]
fn stream_tmr_survives_repeated_kills_with_state() {
    let mut rng = Rng::from_env();
    let kills = 25;
    let count = 5000;
    let sys = System::new();
    let desc = batch_system(
        &sys,
        "tmr",
        &["--every", "9", "--vary", "--stateful"],
        TIMEOUT_US,
        count,
        800,
    );
    let summary = sys.path("summary.json");
    let mut run = sys.start(&desc);
    wait_for_replicas(&mut run, 3);

    let mut killed = Vec::new();
    for _ in 0..kills {
        let pids = run.replica_pids("echo");
        let slot = rng.below(3) as usize;
        let pid = pids[&slot];
        s3res_tests::kill_pid(pid, libc::SIGKILL).expect("kill replica");
        let rec = run.wait_for_event(|e| is_recovery_of(e, slot, pid), Duration::from_secs(20));
        assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
        assert_eq!(rec.state_lost, Some(false), "{rec:?}");
        killed.push((slot, pid));
        std::thread::sleep(Duration::from_millis(rng.range(20, 120)));
    }
    assert!(
        run.try_status().is_none(),
        "the system finished before all {kills} kills were done; make the source longer"
    );
    let out = run.wait_success(LIMIT);
    let crashes = of_kind(&out.events, EventKind::Crash);
    for (slot, pid) in &killed {
        assert!(
            crashes
                .iter()
                .any(|e| e.replica == Some(*slot) && e.pid == Some(*pid)),
            "kill of replica {slot} (pid {pid}) was not recorded as a crash"
        );
    }
    assert_eq!(
        faults(&out.events).len(),
        kills,
        "only the kills: {:?}",
        faults(&out.events)
    );
    assert_sink_whole(&summary, count);
}

/// One corrupted frame in one replica is outvoted: an `sdc` naming that replica, a repair by
/// fork, and the sink sees nothing of it.
#[test]
fn stream_tmr_outvotes_a_corrupted_frame() {
    let count = 1500;
    let sys = System::new();
    let desc = batch_system(
        &sys,
        "tmr",
        &["--every", "5", "--stateful"],
        TIMEOUT_US,
        count,
        500,
    );
    let summary = sys.path("summary.json");
    let mut run = sys.start(&desc);
    wait_for_replicas(&mut run, 3);

    let slot = 1;
    let pid = run.replica_pids("echo")[&slot];
    s3res_tests::sigqueue(pid, signals::INJECT_SDC, 77).expect("sigqueue");
    let sdc = run.wait_for_event(|e| e.kind == EventKind::Sdc, Duration::from_secs(20));
    assert_eq!((sdc.replica, sdc.pid), (Some(slot), Some(pid)), "{sdc:?}");
    let rec = run.wait_for_event(|e| is_recovery_of(e, slot, pid), Duration::from_secs(20));
    assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");

    let out = run.wait_success(LIMIT);
    assert_eq!(faults(&out.events).len(), 1, "{:?}", faults(&out.events));
    assert_sink_whole(&summary, count);
}

/// A stopped replica falls behind: at the deadline the laggard is the `hang` suspect, it is
/// replaced by fork, and the stream goes on whole.
#[test]
fn stream_tmr_replaces_a_stopped_laggard() {
    let count = 1500;
    let sys = System::new();
    let desc = batch_system(
        &sys,
        "tmr",
        &["--every", "4", "--vary", "--stateful"],
        TIMEOUT_US,
        count,
        500,
    );
    let summary = sys.path("summary.json");
    let mut run = sys.start(&desc);
    wait_for_replicas(&mut run, 3);

    let slot = 2;
    let pid = run.replica_pids("echo")[&slot];
    s3res_tests::kill_pid(pid, libc::SIGSTOP).expect("SIGSTOP");
    let hang = run.wait_for_event(|e| e.kind == EventKind::Hang, Duration::from_secs(20));
    assert_eq!(
        (hang.replica, hang.pid),
        (Some(slot), Some(pid)),
        "{hang:?}"
    );
    assert!(
        hang.detail
            .as_deref()
            .unwrap_or("")
            .contains("furthest behind"),
        "{hang:?}"
    );
    let rec = run.wait_for_event(|e| is_recovery_of(e, slot, pid), Duration::from_secs(20));
    assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");

    let out = run.wait_success(LIMIT);
    assert_eq!(faults(&out.events).len(), 1, "{:?}", faults(&out.events));
    assert_sink_whole(&summary, count);
}

/// DMR sees a corrupted frame but cannot tell which replica is wrong: an unattributed `sdc`,
/// that one frame withheld, nobody replaced, and the stream does not stall.
#[test]
fn stream_dmr_disagreement_is_recorded_and_does_not_stall() {
    let count = 1500;
    let sys = System::new();
    let desc = batch_system(
        &sys,
        "dmr",
        &["--every", "6", "--stateful"],
        TIMEOUT_US,
        count,
        500,
    );
    let summary = sys.path("summary.json");
    let mut run = sys.start(&desc);
    wait_for_replicas(&mut run, 2);

    let pids = run.replica_pids("echo");
    s3res_tests::sigqueue(pids[&0], signals::INJECT_SDC, 70).expect("sigqueue");
    let sdc = run.wait_for_event(|e| e.kind == EventKind::Sdc, Duration::from_secs(20));
    assert_eq!(sdc.replica, None, "DMR must not attribute: {sdc:?}");
    assert!(
        sdc.detail.as_deref().unwrap_or("").contains("withheld"),
        "{sdc:?}"
    );

    let out = run.wait(LIMIT);
    run.assert_nothing_left();
    // The sink misses exactly the withheld frame (so it, and bootstrap, report failure); every
    // frame after it came.
    assert!(!out.status.success());
    let s = sink_summary(&summary);
    assert_eq!(s["missing"], 1, "{s}");
    assert_eq!(s["frames"], count - 1, "{s}");
    for field in ["duplicated", "reordered", "corrupt", "state_breaks"] {
        assert_eq!(s[field], 0, "{field}: {s}");
    }
    assert_eq!(faults(&out.events).len(), 1, "{:?}", faults(&out.events));
    assert!(of_kind(&out.events, EventKind::Recovery).is_empty());
    assert_eq!(run.replica_pids("echo"), pids);
}

/// Inputs that produce no output start no deadline: with batches far apart (a burst every
/// 25 inputs at 100 Hz, a quarter second) and a deadline of 50 ms, nothing is called a hang.
#[test]
fn stream_inputs_without_output_cause_no_false_hang() {
    let count = 300;
    let sys = System::new();
    let desc = batch_system(
        &sys,
        "tmr",
        &["--every", "25", "--stateful"],
        50_000,
        count,
        100,
    );
    let summary = sys.path("summary.json");
    let mut run = sys.start(&desc);
    let out = run.wait_success(LIMIT);
    assert!(faults(&out.events).is_empty(), "{:?}", faults(&out.events));
    assert_sink_whole(&summary, count);
}

/// The stream example of `docs/system-description.md`, verbatim, runs clean: the sink
/// (`--stateful --expect 2000`) fails, and so bootstrap fails, unless every frame came once, in
/// order, with the batch's state intact.
#[test]
fn the_documented_stream_example_runs_clean() {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/system-description.md");
    let doc = std::fs::read_to_string(&path).unwrap();
    let section = doc
        .split("## Example: a stream component (TMR)")
        .nth(1)
        .expect("the doc has the stream example");
    let json = section
        .split("```json")
        .nth(1)
        .and_then(|s| s.split("```").next())
        .expect("the example is a json block");
    let mut run = System::new().start(json);
    let out = run.wait_success(LIMIT);
    let starts = out
        .events
        .iter()
        .filter(|e| e.component == "batch" && e.kind == EventKind::Start)
        .count();
    assert_eq!(starts, 3, "{:?}", out.events);
}

/// The tightest window (a replica may be one frame ahead) with bursts sent as fast as the
/// pipes take them: the replicas are read in lockstep, and the voter takes frames that are
/// already buffered without waiting for a pipe to wake it (an earlier version stalled here at
/// the end of the stream).
#[test]
fn stream_window_of_one_passes_fast_bursts_whole() {
    let count = 3000;
    let sys = System::new();
    let batch = r#"{ "exec": "s3res-batch", "args": ["--every", "9", "--vary", "--stateful"], "redundancy": "tmr", "mode": "stream", "timeout_us": 300000, "window": 1 }"#;
    let summary = sys.path("summary.json");
    let desc = echo_pipeline(&summary, batch, count, 0);
    let mut run = sys.start(&desc);
    let out = run.wait_success(LIMIT);
    assert!(faults(&out.events).is_empty(), "{:?}", faults(&out.events));
    assert_sink_whole(&summary, count);
}
