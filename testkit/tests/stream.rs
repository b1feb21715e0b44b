//! End to end: stream mode (S³RES VoterD). `source → batch (protected, "mode": "stream") →
//! sink`, where `s3res-batch` answers nothing for most inputs and then a burst, so outputs are
//! not one per input. Every test runs the real bootstrap, voter and replicas.

use std::path::PathBuf;
use std::time::Duration;

use s3res_testkit::{
    assert_kills_were_crashes, assert_sink_missed_one, assert_sink_whole, echo_pipeline,
    is_recovery_of, signals, Cause, Event, EventKind, RecoveryMethod, Rng, RunningSystem, System,
};

/// Generous, so that a loaded CI machine does not see false hangs; the tests check behaviour,
/// not speed.
const TIMEOUT_US: u64 = 300_000;
const LIMIT: Duration = Duration::from_secs(120);

/// Starts source → batch (stream mode, `redundancy`, `batch_args`) → sink; the source sends
/// `count` frames at `hz`. Returns the running system and the path of the sink's summary.
fn start_batch(
    redundancy: &str,
    batch_args: &[&str],
    timeout_us: u64,
    count: u32,
    hz: u32,
) -> (RunningSystem, PathBuf) {
    let batch = format!(
        r#"{{ "exec": "s3res-batch", "args": {}, "redundancy": "{redundancy}", "mode": "stream", "timeout_us": {timeout_us} }}"#,
        serde_json::to_string(batch_args).unwrap()
    );
    let sys = System::new();
    let summary = sys.path("summary.json");
    let desc = echo_pipeline(&summary, &batch, count, hz);
    (sys.start(&desc), summary)
}

/// The events of `kind` about the echo.
fn of_kind(events: &[Event], kind: EventKind) -> Vec<&Event> {
    s3res_testkit::of_kind(events, "echo", kind)
}

fn faults(events: &[Event]) -> Vec<&Event> {
    events
        .iter()
        .filter(|e| !matches!(e.kind, EventKind::Start | EventKind::Recovery))
        .collect()
}

#[test]
fn stream_tmr_passes_bursts_through_whole() {
    let count = 600;
    let args = ["--every", "7", "--vary", "--stateful"];
    let (mut run, summary) = start_batch("tmr", &args, TIMEOUT_US, count, 1000);
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
    let args = ["--every", "9", "--vary", "--stateful"];
    let (mut run, summary) = start_batch("tmr", &args, TIMEOUT_US, count, 800);
    run.wait_for_replicas("echo", 3);

    let killed = run.kill_random_replicas(&mut rng, "echo", 3, kills, (20, 120));
    let out = run.wait_success(LIMIT);
    assert_kills_were_crashes(&out.events, "echo", &killed);
    assert_eq!(
        faults(&out.events).len(),
        kills,
        "only the kills: {:?}",
        faults(&out.events)
    );
    assert_sink_whole(&summary, count);
}

/// Frames larger than a pipe holds (400 kB against 64 KiB), in bursts, while random replicas
/// are killed: a donor is asked to fork while it streams, so it is often blocked in the middle
/// of writing a frame. The restart is deferred to the end of the frame (replica-rt's
/// `restart` module), so every child's output starts on a frame boundary and its `Ready`
/// count agrees with the donor's pipe: the kills are the only faults (a child that began with
/// the tail of a frame would be a protocol fault, a count off by one an `sdc` or a hang), and
/// the sink gets every frame once, in order, whole, with the state kept.
#[test]
fn stream_tmr_large_frames_survive_kills_whole() {
    let mut rng = Rng::from_env();
    let (kills, count, size) = (16, 500, 400_000);
    let sys = System::new();
    let summary = sys.path("summary.json");
    let desc = format!(
        r#"{{
  "name": "large-frames",
  "components": {{
    "source": {{ "exec": "s3res-source", "args": ["--count", "{count}", "--hz", "250", "--size", "{size}"] }},
    "echo": {{ "exec": "s3res-batch", "args": ["--every", "5", "--stateful"], "redundancy": "tmr", "mode": "stream", "timeout_us": {TIMEOUT_US} }},
    "sink": {{ "exec": "s3res-sink", "args": ["--stateful", "--expect", "{count}", "--summary", "{}"] }}
  }},
  "channels": [
    {{ "from": "source.out", "to": "echo.in", "max_frame": 524288 }},
    {{ "from": "echo.out", "to": "sink.in", "max_frame": 524288 }}
  ]
}}"#,
        summary.display()
    );
    let mut run = sys.start(&desc);
    run.wait_for_replicas("echo", 3);

    let killed = run.kill_random_replicas(&mut rng, "echo", 3, kills, (20, 80));
    let out = run.wait_success(LIMIT);
    assert_kills_were_crashes(&out.events, "echo", &killed);
    assert_eq!(
        faults(&out.events).len(),
        kills,
        "only the kills: {:?}",
        faults(&out.events)
    );
    assert_sink_whole(&summary, count);
}

/// Injects one fault into TMR replica 1 while bursts flow; it must be recorded with `cause`,
/// repaired by fork, and invisible to the sink.
fn tmr_single_fault(batch_args: &[&str], inject: impl FnOnce(i32), cause: Cause) {
    let count = 1500;
    let (mut run, summary) = start_batch("tmr", batch_args, TIMEOUT_US, count, 500);
    run.wait_for_replicas("echo", 3);

    let slot = 1;
    let pid = run.replica_pids("echo")[&slot];
    inject(pid);
    let fault = run.wait_for_event(|e| e.kind == cause.kind(), Duration::from_secs(20));
    assert_eq!(
        (fault.replica, fault.pid),
        (Some(slot), Some(pid)),
        "{fault:?}"
    );
    assert_eq!(fault.cause, Some(cause), "{fault:?}");
    let rec = run.wait_for_event(|e| is_recovery_of(e, slot, pid), Duration::from_secs(20));
    assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");

    let out = run.wait_success(LIMIT);
    assert_eq!(faults(&out.events).len(), 1, "{:?}", faults(&out.events));
    assert_sink_whole(&summary, count);
}

/// One corrupted frame in one replica is outvoted: an `sdc` naming that replica.
#[test]
fn stream_tmr_outvotes_a_corrupted_frame() {
    tmr_single_fault(
        &["--every", "5", "--stateful"],
        |pid| s3res_testkit::sigqueue(pid, signals::INJECT_SDC, 77).expect("sigqueue"),
        Cause::Minority,
    );
}

/// A stopped replica falls behind: at the deadline the laggard is the `hang` suspect.
#[test]
fn stream_tmr_replaces_a_stopped_laggard() {
    tmr_single_fault(
        &["--every", "4", "--vary", "--stateful"],
        |pid| s3res_testkit::kill_pid(pid, libc::SIGSTOP).expect("SIGSTOP"),
        Cause::Behind,
    );
}

/// DMR sees a corrupted frame but cannot tell which replica is wrong: an unattributed `sdc`,
/// that one frame withheld, nobody replaced, and the stream does not stall.
#[test]
fn stream_dmr_disagreement_is_recorded_and_does_not_stall() {
    let count = 1500;
    let (mut run, summary) = start_batch(
        "dmr",
        &["--every", "6", "--stateful"],
        TIMEOUT_US,
        count,
        500,
    );
    run.wait_for_replicas("echo", 2);

    let pids = run.inject_unattributable_sdc("echo", 70);

    let out = run.wait(LIMIT);
    run.assert_nothing_left();
    // The sink misses exactly the withheld frame (so it, and bootstrap, report failure); every
    // frame after it came.
    assert!(!out.status.success());
    assert_sink_missed_one(&summary, count);
    assert_eq!(faults(&out.events).len(), 1, "{:?}", faults(&out.events));
    assert!(of_kind(&out.events, EventKind::Recovery).is_empty());
    assert_eq!(run.replica_pids("echo"), pids);
}

/// Inputs that produce no output start no deadline: with bursts far apart (one every 50
/// inputs at 50 Hz, a second) and a deadline of 300 ms, nothing is called a hang. (Reactive
/// mode would want an answer to each input within the deadline.)
#[test]
fn stream_inputs_without_output_cause_no_false_hang() {
    let count = 300;
    let (mut run, summary) = start_batch(
        "tmr",
        &["--every", "50", "--stateful"],
        TIMEOUT_US,
        count,
        50,
    );
    let out = run.wait_success(LIMIT);
    assert!(faults(&out.events).is_empty(), "{:?}", faults(&out.events));
    assert_sink_whole(&summary, count);
}

/// A stream component that takes its input and sends nothing on its output ran to a clean end
/// without a word: no answer is owed for an input in stream mode, so no deadline says it. Its
/// voter now says so at the end, naming the output.
#[test]
fn a_stream_component_that_sends_nothing_says_so() {
    let sys = System::new();
    let desc = serde_json::json!({
        "name": "silent",
        "components": {
            "source": {"exec": "s3res-source", "args": ["--count", "50", "--hz", "500"]},
            "echo": {
                "exec": "s3res-misbehave",
                "args": ["--mode", "silent", "--replica", "0,1,2", "--at", "0"],
                "redundancy": "tmr", "mode": "stream", "timeout_us": TIMEOUT_US
            },
            "sink": {"exec": "s3res-sink"}
        },
        "channels": [
            {"from": "source.out", "to": "echo.in"},
            {"from": "echo.out", "to": "sink.in"}
        ]
    });
    let mut run = sys.start_json(&desc);
    let out = run.wait_success(LIMIT);
    assert!(
        out.stderr.contains(
            "its replicas took 50 input frame(s) and sent no frame on any output (`out`)"
        ),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    run.assert_nothing_left();
}

/// Starts source → echo (stream mode, TMR, `work_us` of work per frame) → sink, the source
/// sending `count` frames as fast as it can: the replicas still have most of the work ahead of
/// them when their input ends.
/// A second of deadline: three replicas spinning on two CPUs (and a loaded test machine) fall
/// out of step by more than the usual 300 ms, which is not what these tests are about.
fn start_slow_stream(work_us: u64, count: u32) -> (RunningSystem, PathBuf) {
    let echo = format!(
        r#"{{ "exec": "s3res-echo", "args": ["--stateful", "--work-us", "{work_us}"], "redundancy": "tmr", "mode": "stream", "timeout_us": 1000000 }}"#
    );
    let sys = System::new();
    let summary = sys.path("summary.json");
    let desc = echo_pipeline(&summary, &echo, count, 0);
    (sys.start(&desc), summary)
}

/// Replicas that work through a backlog of input after it ended, at their pace (30 ms a frame,
/// 3.6 s each, more on two CPUs), finish it: the end lasts while they produce. Before, they were stopped 2 s +
/// `timeout_us` after their input ended, what they had not sent was lost, and the run ended
/// 'clean' (a newcomer's slow component lost 26 of 60 frames so).
#[test]
fn stream_replicas_working_through_a_backlog_at_the_end_finish_it() {
    let count = 120;
    let (mut run, summary) = start_slow_stream(30_000, count);
    let out = run.wait_success(LIMIT);
    assert!(faults(&out.events).is_empty(), "{:?}", faults(&out.events));
    assert_sink_whole(&summary, count);
}

/// Replicas that produce nothing for 2 s + `timeout_us` (3 s) after their input ended are stopped,
/// and the component fails saying so: a `lost` event and its last line, not a clean end.
#[test]
fn stream_replicas_that_do_not_finish_their_output_fail_the_component() {
    let (mut run, _) = start_slow_stream(4_000_000, 3);
    let out = run.wait(LIMIT);
    assert!(!out.status.success(), "{}", out.stderr);
    let lost = of_kind(&out.events, EventKind::Lost);
    assert_eq!(lost.len(), 1, "{:#?}", out.events);
    let detail = lost[0].detail.as_deref().unwrap_or_default();
    assert!(
        detail.contains("the replicas had not finished their output"),
        "{detail}"
    );
    assert!(
        out.stderr
            .contains("s3res-voter: output cut short: the replicas had not finished"),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    run.assert_nothing_left();
}

/// A replica that hangs after its last frame (a control-flow error that strikes just then,
/// as a fault injected into the maze robot's planner did in a CI rehearsal of stop 61) owes
/// nothing: its siblings finished, every frame is decided. It is stopped at the end, and the
/// component ends clean, every frame out once — before, the voter said "what they had not
/// sent is lost" and the component, and `s3res-bootstrap system.json`, failed.
#[test]
fn a_stream_replica_hung_after_its_last_frame_loses_nothing_and_fails_nothing() {
    let count: u32 = 40;
    let last = count - 1;
    let comp = format!(
        r#"{{ "exec": "s3res-misbehave", "args": ["--stateful", "--mode", "spin", "--replica", "2", "--at", "{last}"], "redundancy": "tmr", "mode": "stream", "timeout_us": 200000 }}"#
    );
    let sys = System::new();
    let summary = sys.path("summary.json");
    let desc = echo_pipeline(&summary, &comp, count, 0);
    let mut run = sys.start(&desc);
    let out = run.wait(LIMIT);
    assert!(
        out.status.success(),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    let lost = of_kind(&out.events, EventKind::Lost);
    assert!(lost.is_empty(), "{lost:#?}");
    assert_sink_whole(&summary, count);
    run.assert_nothing_left();
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

/// SMR has no donor: a killed replica is started afresh by exec, the event says the state is
/// lost, and the stream goes on from the next frame: the frames the dead replica held are
/// missing at the sink and its counter starts again (a state break), but nothing is doubled
/// and the voter does not stall.
#[test]
fn stream_smr_restarts_by_exec_and_goes_on() {
    let count = 1500;
    let every = 10;
    let args = ["--every", "10", "--stateful"];
    let (mut run, summary) = start_batch("smr", &args, TIMEOUT_US, count, 500);
    run.wait_for_replicas("echo", 1);
    // It has counted a batch: a replica killed before its first would come back counting from
    // zero with no break to see.
    run.wait_for_answers("echo");

    let pid = run.replica_pids("echo")[&0];
    s3res_testkit::kill_pid(pid, libc::SIGKILL).expect("kill");
    let rec = run.wait_for_event(|e| is_recovery_of(e, 0, pid), Duration::from_secs(20));
    assert_eq!(rec.method, Some(RecoveryMethod::Exec), "{rec:?}");
    assert_eq!(rec.state_lost, Some(true), "{rec:?}");

    let out = run.wait(LIMIT);
    run.assert_nothing_left();
    assert_eq!(faults(&out.events).len(), 1, "{:?}", faults(&out.events));
    let s = s3res_testkit::sink_summary(&summary);
    assert_eq!(s["state_breaks"], 1, "{s}");
    let missing = s["missing"].as_u64().unwrap();
    // What the dead replica held (under one batch) and what was in its input pipe.
    assert!(missing < 3 * every, "{s}");
    assert_eq!(s["frames"].as_u64().unwrap(), count as u64 - missing, "{s}");
    for field in ["duplicated", "reordered", "corrupt"] {
        assert_eq!(s[field], 0, "{field}: {s}");
    }
}

/// Two faults in two slots: replicas 1 and 2 are stopped, so the frames replica 0 goes on
/// producing from the input it already has cannot be decided; then replica 1 is killed. The
/// fork child of replica 0 joins with those undecided frames, which its state is already past
/// (they count as its own, and with replica 0's make a majority); then the stopped laggard 2
/// is the `hang` suspect and is replaced too. No stall, no frame lost or doubled.
#[test]
fn stream_tmr_child_joins_while_frames_are_undecided() {
    let count = 2000;
    let args = ["--every", "3", "--stateful"];
    let (mut run, summary) = start_batch("tmr", &args, TIMEOUT_US, count, 1000);
    run.wait_for_replicas("echo", 3);

    let pids = run.replica_pids("echo");
    for slot in [1, 2] {
        s3res_testkit::kill_pid(pids[&slot], libc::SIGSTOP).expect("SIGSTOP");
        s3res_testkit::wait_state(pids[&slot], "T", Duration::from_secs(20));
    }
    // Replica 0 writes the frames it can from the input it already has, which nobody can
    // confirm now, and waits for more input (held while the replicas are out of step).
    let mut looks = 0;
    s3res_testkit::wait_until(
        "replica 0 to use up its input",
        Duration::from_secs(20),
        || {
            looks = if s3res_testkit::procs::waits_on_pipe_read(pids[&0]) {
                looks + 1
            } else {
                0
            };
            (looks >= 3).then_some(())
        },
    );
    s3res_testkit::kill_pid(pids[&1], libc::SIGKILL).expect("SIGKILL");
    let rec = run.wait_for_event(|e| is_recovery_of(e, 1, pids[&1]), Duration::from_secs(20));
    assert_eq!(
        (rec.method, rec.donor),
        (Some(RecoveryMethod::Fork), Some(0)),
        "{rec:?}"
    );
    let hang = run.wait_for_event(|e| e.kind == EventKind::Hang, Duration::from_secs(20));
    assert_eq!(
        (hang.replica, hang.pid),
        (Some(2), Some(pids[&2])),
        "{hang:?}"
    );
    run.wait_for_event(|e| is_recovery_of(e, 2, pids[&2]), Duration::from_secs(20));

    let out = run.wait_success(LIMIT);
    assert_eq!(faults(&out.events).len(), 2, "{:?}", faults(&out.events));
    assert_sink_whole(&summary, count);
}

/// Two control-flow errors at once: replicas 1 and 2 spin. Replica 0 goes on producing, so at
/// the deadline it is one producer against two laggards — but the laggards are running, not
/// waiting for input: they are the `hang` suspects, and both are rebuilt from replica 0. (The
/// rule "fewer producers are the suspects" alone blamed the healthy replica and, forking a
/// spinner over it, stalled the component: a robot campaign found this.)
#[test]
fn stream_tmr_two_spinning_replicas_do_not_outvote_the_healthy_one() {
    let count = 1500;
    let args = ["--every", "3", "--stateful"];
    let (mut run, summary) = start_batch("tmr", &args, TIMEOUT_US, count, 500);
    run.wait_for_replicas("echo", 3);

    let pids = run.replica_pids("echo");
    for slot in [1, 2] {
        s3res_testkit::kill_pid(pids[&slot], signals::inject_cfe()).expect("inject cfe");
    }
    for slot in [1, 2] {
        let hang = run.wait_for_event(
            |e| e.kind == EventKind::Hang && e.replica == Some(slot),
            Duration::from_secs(20),
        );
        assert_eq!(hang.pid, Some(pids[&slot]), "{hang:?}");
        let rec = run.wait_for_event(
            |e| is_recovery_of(e, slot, pids[&slot]),
            Duration::from_secs(20),
        );
        assert_eq!(
            (rec.method, rec.donor),
            (Some(RecoveryMethod::Fork), Some(0)),
            "{rec:?}"
        );
    }

    let out = run.wait_success(LIMIT);
    assert_eq!(faults(&out.events).len(), 2, "{:?}", faults(&out.events));
    assert_sink_whole(&summary, count);
}

/// A control-flow error in replica 0 that nobody has caught yet (it spins, but has not been
/// overdue long), then a crash of replica 1: the replacement is forked from replica 2, which
/// waits for input, not from the spinning replica 0 (the lowest slot, and as far on as 2).
/// Replica 0 is then caught as the `hang` it is, and the stream is whole.
#[test]
fn stream_recovery_does_not_fork_a_spinning_replica() {
    let count = 1500;
    let args = ["--every", "3", "--stateful"];
    let (mut run, summary) = start_batch("tmr", &args, TIMEOUT_US, count, 200);
    run.wait_for_replicas("echo", 3);

    let pids = run.replica_pids("echo");
    s3res_testkit::kill_pid(pids[&0], signals::inject_cfe()).expect("inject cfe");
    // Until replica 0 has taken the signal and spins (on a loaded machine that may wait).
    s3res_testkit::wait_spinning(pids[&0], Duration::from_secs(20));
    s3res_testkit::kill_pid(pids[&1], libc::SIGKILL).expect("SIGKILL");
    let rec = run.wait_for_event(|e| is_recovery_of(e, 1, pids[&1]), Duration::from_secs(20));
    assert_eq!(
        (rec.method, rec.donor),
        (Some(RecoveryMethod::Fork), Some(2)),
        "{rec:?}"
    );
    let hang = run.wait_for_event(
        |e| e.kind == EventKind::Hang && e.replica == Some(0),
        Duration::from_secs(20),
    );
    assert_eq!(hang.pid, Some(pids[&0]), "{hang:?}");
    run.wait_for_event(|e| is_recovery_of(e, 0, pids[&0]), Duration::from_secs(20));

    let out = run.wait_success(LIMIT);
    assert_eq!(faults(&out.events).len(), 2, "{:?}", faults(&out.events));
    assert_sink_whole(&summary, count);
}

/// The same with replicas that have not answered yet (a replica is *proven* once it has sent a
/// frame): DMR, replica 0 spins from before its first frame, then replica 1 is killed. Replica 0
/// may donate (its restart handler is installed) but must not, since it never waits: its child
/// would spin too (the restart handler returns into the spin). So replica 1 is started afresh,
/// replica 0 is then found as the `hang` it is, and nothing else is blamed. (Before the donor's
/// clean-point check covered unproven replicas too, `stream_dmr_both_replicas_spinning_…` saw a
/// third `hang` now and then: slot 1's fork child of the spinning, not yet proven slot 0.)
#[test]
fn stream_recovery_does_not_fork_a_spinning_replica_that_never_answered() {
    // One burst every 100 inputs at 50 Hz: no replica sends a frame in its first 2 s.
    let count = 300;
    let args = ["--every", "100", "--stateful"];
    let (mut run, summary) = start_batch("dmr", &args, TIMEOUT_US, count, 50);
    run.wait_for_replicas("echo", 2);

    let pids = run.replica_pids("echo");
    s3res_testkit::kill_pid(pids[&0], signals::inject_cfe()).expect("inject cfe");
    s3res_testkit::wait_spinning(pids[&0], Duration::from_secs(20));
    assert!(
        run.events().iter().all(|e| e.kind == EventKind::Start),
        "replica 0 was blamed before the kill: {:?}",
        run.events()
    );
    s3res_testkit::kill_pid(pids[&1], libc::SIGKILL).expect("SIGKILL");
    let rec = run.wait_for_event(|e| is_recovery_of(e, 1, pids[&1]), Duration::from_secs(20));
    assert_ne!(
        rec.donor,
        Some(0),
        "forked from the spinning replica 0: {rec:?}"
    );
    assert_eq!(rec.method, Some(RecoveryMethod::Exec), "{rec:?}");
    let hang = run.wait_for_event(
        |e| e.kind == EventKind::Hang && e.replica == Some(0),
        Duration::from_secs(20),
    );
    assert_eq!(hang.pid, Some(pids[&0]), "{hang:?}");
    run.wait_for_event(|e| is_recovery_of(e, 0, pids[&0]), Duration::from_secs(20));

    let out = run.wait(LIMIT);
    run.assert_nothing_left();
    let faults = faults(&out.events);
    let kinds: Vec<_> = faults.iter().map(|e| (e.kind, e.replica, e.pid)).collect();
    assert_eq!(
        kinds,
        [
            (EventKind::Crash, Some(1), Some(pids[&1])),
            (EventKind::Hang, Some(0), Some(pids[&0]))
        ],
        "{faults:?}"
    );
    // Input taken by the replicas before the exec is lost with them (state lost); nothing is
    // doubled or corrupted, and the stream reached the sink's end.
    let s = s3res_testkit::sink_summary(&summary);
    for field in ["duplicated", "reordered", "corrupt"] {
        assert_eq!(s[field], 0, "{field}: {s}");
    }
    assert!(s["frames"].as_u64().unwrap() > 0, "{s}");
}

/// Stream mode: two replicas' copies of one frame flipped in different bits. No whole frame
/// has a majority, every bit does: the bitwise majority is forwarded (the sink's stream is
/// whole), and both are blamed and rebuilt from the third.
#[test]
fn stream_tmr_two_frames_flipped_in_different_bits_are_outvoted_bit_by_bit() {
    let count = 600;
    let args = ["--every", "5", "--stateful"];
    let (mut run, summary) = start_batch("tmr", &args, TIMEOUT_US, count, 100);
    run.wait_for_replicas("echo", 3);
    let pids = run.flip_bits_in_one_frame("echo", &[(0, 13), (1, 40)]);
    for slot in [0, 1] {
        run.wait_for_bitwise_repair("echo", slot, pids[&slot]);
    }
    let out = run.wait_success(LIMIT);
    assert_eq!(faults(&out.events).len(), 2, "{:?}", faults(&out.events));
    assert_sink_whole(&summary, count);
}

/// Both replicas of a DMR pair hit by control-flow errors at once: nobody produces, so no
/// frame is ever owed and no deadline runs. The voter's look at `/proc` every `timeout_us`
/// finds one computing without producing or waiting, and the other — in the same look, or
/// looked at as its recovery donor and never waiting, or (if it has not sent a frame yet, so
/// is not blamed as a donor) in a later look — is found too: two `hang`s, both restarted (no
/// healthy donor is left, state lost), and the stream goes on to the end instead of stalling.
/// A third `hang` would be a fork of a spinner (see
/// `stream_recovery_does_not_fork_a_spinning_replica_that_never_answered`).
#[test]
fn stream_dmr_both_replicas_spinning_are_found_without_a_deadline() {
    let count = 1500;
    let hz = 500;
    let args = ["--every", "10", "--stateful"];
    // CLOCK_MONOTONIC, as the events: the source cannot have started before this.
    let started_ns = replica_rt::sys::monotonic_ns();
    let (mut run, summary) = start_batch("dmr", &args, TIMEOUT_US, count, hz);
    run.wait_for_replicas("echo", 2);

    let pids = run.replica_pids("echo");
    for slot in [0, 1] {
        s3res_testkit::kill_pid(pids[&slot], signals::inject_cfe()).expect("inject cfe");
    }
    let mut found_by_looking = 0;
    let mut replaced_ns = 0;
    for slot in [0, 1] {
        let hang = run.wait_for_event(
            |e| e.kind == EventKind::Hang && e.replica == Some(slot),
            Duration::from_secs(20),
        );
        assert_eq!(hang.pid, Some(pids[&slot]), "{hang:?}");
        // One replica may still produce a frame before its spin starts (a slow machine): then
        // the other is simply the laggard at that frame's deadline.
        // Found by a look at /proc: the liveness look, the deadline's look at the laggards,
        // or the donor choice's (the other one's replacement wanted it as donor).
        let looked = matches!(
            hang.cause,
            Some(Cause::Spinning | Cause::BehindNotWaiting | Cause::DonorSpinning)
        );
        assert!(looked || hang.cause == Some(Cause::Behind), "{hang:?}");
        found_by_looking += usize::from(looked);
        let rec = run.wait_for_event(
            |e| is_recovery_of(e, slot, pids[&slot]),
            Duration::from_secs(20),
        );
        replaced_ns = replaced_ns.max(rec.ts_ns);
    }
    assert!(
        found_by_looking >= 1,
        "no hang was found by the look at /proc"
    );

    let out = run.wait(LIMIT);
    run.assert_nothing_left();
    assert_eq!(faults(&out.events).len(), 2, "{:?}", faults(&out.events));
    let s = s3res_testkit::sink_summary(&summary);
    let missing = s["missing"].as_u64().unwrap();
    // Lost: the input the spinners held and what was queued for them until both were
    // replaced — how much depends on how soon a loaded machine lets them be seen spinning (a
    // starved spinner is not blamed). Never lost: anything the source (paced from its start,
    // after `started_ns`) sent after that. So the stream went on and did not stall.
    let sent_before_replaced = (replaced_ns - started_ns) * u64::from(hz) / 1_000_000_000 + 1;
    assert!(
        missing <= sent_before_replaced,
        "{missing} missing, but the source can have sent only {sent_before_replaced} frames \
         before both replicas were replaced: {s}"
    );
    assert!(missing < u64::from(count), "nothing reached the sink: {s}");
    assert_eq!(s["frames"].as_u64().unwrap(), count as u64 - missing, "{s}");
    for field in ["duplicated", "reordered", "corrupt"] {
        assert_eq!(s[field], 0, "{field}: {s}");
    }
}
