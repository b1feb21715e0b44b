//! The live view and one-off injections into a running TMR echo: bootstrap's `--state` file
//! names the current pid of every replica slot (also after a recovery), and each kind of
//! injection produces the fault event it says, for the pid it printed.

mod common;

use std::time::{Duration, Instant};

use common::inject;
use s3res_protocol::live::{LiveView, ReplicaState};
use s3res_testkit::{Event, EventKind, RunningSystem, System};

const LIMIT: Duration = Duration::from_secs(60);

const DESCRIPTION: &str = r#"{
  "name": "one-off",
  "components": {
    "source": { "exec": "s3res-source", "args": ["--count", "15000", "--hz", "500"] },
    "echo":   { "exec": "s3res-echo", "args": ["--stateful"], "redundancy": "tmr", "timeout_us": 50000 },
    "sink":   { "exec": "s3res-sink", "args": ["--stateful"] }
  },
  "channels": [
    { "from": "source.out", "to": "echo.in" },
    { "from": "echo.out",   "to": "sink.in" }
  ]
}"#;

/// Waits until the state file shows every echo replica running.
fn running_view(run: &mut RunningSystem, state: &std::path::Path) -> LiveView {
    let deadline = Instant::now() + LIMIT;
    loop {
        if let Ok(v) = LiveView::read(state) {
            let echo = &v.components["echo"];
            if echo
                .replicas
                .iter()
                .all(|r| r.state == ReplicaState::Running)
            {
                return v;
            }
        }
        assert!(
            run.try_status().is_none(),
            "bootstrap exited:\n{}",
            run.stderr()
        );
        assert!(Instant::now() < deadline, "replicas never all ran");
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn one_off(state: &std::path::Path, args: &[&str]) -> serde_json::Value {
    let mut all = vec![
        "inject",
        "--state",
        state.to_str().unwrap(),
        "--component",
        "echo",
    ];
    all.extend_from_slice(args);
    let f = inject(&all, Duration::from_secs(30));
    assert!(f.success, "{}", f.stderr);
    serde_json::from_str(f.stdout.trim()).unwrap_or_else(|e| panic!("{e}: {}", f.stdout))
}

fn fault_for(run: &mut RunningSystem, pid: i64, kind: EventKind) -> Event {
    run.wait_for_event(
        |e| e.kind == kind && e.pid == Some(pid as i32) && e.component == "echo",
        LIMIT,
    )
}

#[test]
fn the_live_view_follows_recoveries_and_each_kind_does_what_it_says() {
    let sys = System::new();
    let state = sys.path("state.json");
    let mut run = sys.arg("--state").arg(&state).start(DESCRIPTION);
    let view = running_view(&mut run, &state);
    assert!(view.running);
    assert_eq!(view.bootstrap_pid, run.pid());
    assert!(view.components["echo"].voter_pid.is_some());
    assert!(view.components["source"].pid.is_some() && !view.components["source"].protected);
    // The view agrees with the event log.
    let from_events = run.replica_pids("echo");
    for r in &view.components["echo"].replicas {
        assert_eq!(Some(&r.pid.unwrap()), from_events.get(&r.slot));
    }

    // exec into slot 1: a crash of exactly that pid, then a recovery the view shows.
    let rec = one_off(
        &state,
        &["--replica", "1", "--fault", "exec", "--seed", "1"],
    );
    assert_eq!(
        (rec["kind"].as_str(), rec["replica"].as_u64()),
        (Some("exec"), Some(1))
    );
    for field in ["ts_ns", "seed", "component", "pid"] {
        assert!(!rec[field].is_null(), "{field} in {rec}");
    }
    let pid = rec["pid"].as_i64().unwrap();
    assert_eq!(
        pid,
        i64::from(view.components["echo"].replicas[1].pid.unwrap())
    );
    let crash = fault_for(&mut run, pid, EventKind::Crash);
    assert!(crash.ts_ns >= rec["ts_ns"].as_u64().unwrap());
    let recovery = fault_for(&mut run, pid, EventKind::Recovery);
    let view = running_view(&mut run, &state);
    assert_eq!(view.components["echo"].replicas[1].pid, recovery.new_pid);

    // sdc (bit chosen), var (the sign of the f64 at offset 8), cfe: each into the new pid of
    // slot 1 shows up as the fault it is.
    for (args, kind) in [
        (vec!["--fault", "sdc", "--bit", "77"], EventKind::Sdc),
        (
            vec!["--fault", "var", "--var-offset", "8", "--var-field", "sign"],
            EventKind::Sdc,
        ),
        (vec!["--fault", "cfe"], EventKind::Hang),
    ] {
        let view = running_view(&mut run, &state);
        let mut a = vec!["--replica", "1", "--seed", "2"];
        a.extend(args);
        let rec = one_off(&state, &a);
        let pid = rec["pid"].as_i64().unwrap();
        assert_eq!(
            pid,
            i64::from(view.components["echo"].replicas[1].pid.unwrap())
        );
        fault_for(&mut run, pid, kind);
        fault_for(&mut run, pid, EventKind::Recovery);
        if kind == EventKind::Sdc && rec["kind"] == "var" {
            assert_eq!(rec["bits"], serde_json::json!([63]), "{rec}");
        }
    }
    // Without --replica the draw picks a slot; an unknown component is a clear error.
    let rec = one_off(&state, &["--fault", "sdc", "--seed", "3"]);
    assert!(rec["replica"].as_u64().unwrap() < 3);
    let f = inject(
        &[
            "inject",
            "--state",
            state.to_str().unwrap(),
            "--component",
            "nope",
            "--fault",
            "exec",
        ],
        Duration::from_secs(30),
    );
    assert!(!f.success && f.stderr.contains("nope"), "{}", f.stderr);

    run.stop();
    run.wait(LIMIT);
    let view = LiveView::read(&state).unwrap();
    assert!(!view.running, "the view says the system stopped");
    run.assert_nothing_left();
}

/// A register flip (`--fault reg`, the s3res-regflip injector) into a TMR replica: the printed
/// line carries the injector's whole record — seed, instruction, register, the one bit, the
/// value before and after — and whatever the flip does to that replica, the voter masks it and
/// the slot is running again afterwards.
#[test]
fn a_register_flip_is_logged_whole_and_tmr_carries_on() {
    let sys = System::new();
    let state = sys.path("state.json");
    let mut run = sys.arg("--state").arg(&state).start(DESCRIPTION);
    let view = running_view(&mut run, &state);
    let rec = one_off(&state, &["--replica", "2", "--fault", "reg", "--seed", "5"]);
    assert_eq!(rec["kind"], "reg", "{rec}");
    let pid = rec["pid"].as_i64().unwrap();
    assert_eq!(
        pid,
        i64::from(view.components["echo"].replicas[2].pid.unwrap())
    );
    let flip = &rec["injector"];
    assert_eq!(flip["pid"].as_i64(), Some(pid), "{rec}");
    // The injection's own seed (drawn from --seed), the one that replays this flip: written
    // `reg_seed` beside the line's `seed` (the --seed given).
    assert_eq!(flip["seed"], rec["reg_seed"], "{rec}");
    assert_eq!(rec["seed"], 5, "{rec}");
    assert!(flip["attempts"].as_u64().unwrap() >= 1, "{rec}");
    assert!(!flip["instruction"].as_str().unwrap().is_empty(), "{rec}");
    assert!(!flip["register"].as_str().unwrap().is_empty(), "{rec}");
    let bits = flip["bits"].as_array().unwrap();
    assert_eq!(bits.len(), 1, "one bit by default: {rec}");
    // before XOR after is exactly that bit (values are hex, up to 128 bits for XMM).
    let hex = |k: &str| {
        let s = flip[k].as_str().unwrap();
        u128::from_str_radix(s.trim_start_matches("0x"), 16)
            .unwrap_or_else(|e| panic!("{k} = {s}: {e}"))
    };
    let bit = bits[0].as_u64().unwrap();
    assert_eq!(hex("before") ^ hex("after"), 1u128 << bit, "{rec}");
    // The line's time is the flip's, not when the injector began to wait for its target to
    // run (it said the latter, up to 200 ms early).
    assert_eq!(rec["ts_ns"], flip["time_ns"], "{rec}");

    // Crash, hang, corruption or nothing at all: the slot ends up running again.
    let deadline = Instant::now() + LIMIT;
    loop {
        let v = running_view(&mut run, &state);
        let now = v.components["echo"].replicas[2].pid.unwrap();
        let faulted = run
            .events()
            .iter()
            .any(|e| e.pid == Some(pid as i32) && e.kind == EventKind::Recovery);
        if i64::from(now) == pid || faulted {
            break;
        }
        assert!(Instant::now() < deadline, "slot 2 never ran again");
    }
    run.stop();
    run.wait(LIMIT);
    run.assert_nothing_left();
}
