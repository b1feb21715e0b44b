//! A description with `inject` runs its injector beside the components and ends with a verdict
//! block that accounts for every injection; `--no-inject` runs the same system fault-free. Each
//! run is a real bootstrap in a temp folder, as its own process group, killed and reaped by the
//! harness, which fails the test if anything is left behind.

use std::time::Duration;

use s3res_testkit::System;

/// Bound on one run; the system itself takes about four seconds.
const LIMIT: Duration = Duration::from_secs(120);

/// The echo pipeline under TMR, 2000 frames at 500 Hz, faults at 4 Hz from 0.5 s on, its files
/// in `out/`; the sink's verdict is the outcome. The round deadline is loose so that a loaded
/// test machine does not produce hangs nobody injected.
const SYSTEM: &str = r#"{
  "name": "echo-under-fire",
  "inject": {"faults": ["exec", "sdc", "cfe"], "rate_hz": 4, "seed": 3, "after_s": 0.5},
  "events": "out/events.jsonl",
  "state": "out/state.json",
  "outcome": "out/task.json",
  "components": {
    "source": { "exec": "s3res-source", "args": ["--count", "2000", "--hz", "500"] },
    "echo":   { "exec": "s3res-echo", "args": ["--stateful"], "redundancy": "tmr", "timeout_us": 150000 },
    "sink":   { "exec": "s3res-sink", "args": ["--stateful", "--expect", "2000", "--summary", "out/task.json"] }
  },
  "channels": [
    { "from": "source.out", "to": "echo.in" },
    { "from": "echo.out",   "to": "sink.in" }
  ]
}"#;

#[test]
fn the_injector_runs_and_the_verdict_accounts_for_it() {
    let mut run = System::new().without_events().start(SYSTEM);
    let out = run.wait(LIMIT);
    let dir = run.dir().to_path_buf();
    assert!(out.status.success(), "{}\n{}", out.status, out.stderr);
    let log = std::fs::read_to_string(dir.join("out/injections.jsonl")).unwrap();
    let delivered = log.lines().filter(|l| !l.contains("\"miss\"")).count();
    assert!(delivered > 0, "nothing injected:\n{log}\n{}", out.stderr);
    for needle in [
        "echo-under-fire: ran clean",
        "  outcome      succeeded",
        &format!("  injected     {delivered} ("),
        "  false pos.   ",
        "  files        events out/events.jsonl · state out/state.json · injections \
         out/injections.jsonl · outcome out/task.json",
    ] {
        assert!(
            out.stderr.contains(needle),
            "{needle:?} missing:\n{}",
            out.stderr
        );
    }
    assert!(dir.join("out/events.jsonl").is_file());
    run.assert_nothing_left();
}

#[test]
fn no_inject_runs_the_same_system_without_faults() {
    let mut run = System::new()
        .without_events()
        .arg("--no-inject")
        .start(SYSTEM);
    let out = run.wait(LIMIT);
    let dir = run.dir().to_path_buf();
    assert!(out.status.success(), "{}\n{}", out.status, out.stderr);
    assert!(!dir.join("out/injections.jsonl").exists());
    assert!(!out.stderr.contains("  injected "), "{}", out.stderr);
    assert!(
        out.stderr.contains("  outcome      succeeded"),
        "{}",
        out.stderr
    );
    run.assert_nothing_left();
}

/// Without `state`, the injector's live view lives in bootstrap's private folder, which the
/// final sweep removes: the run still ends clean, with no warning about that file (the last
/// updates of the view once wrote to the removed folder and warned at every such run).
#[test]
fn a_private_state_file_ends_without_a_warning() {
    let system = SYSTEM.replace("  \"state\": \"out/state.json\",\n", "");
    assert!(
        !system.contains("\"state\""),
        "the description still names a state file"
    );
    let mut run = System::new().without_events().start(&system);
    let out = run.wait(LIMIT);
    assert!(out.status.success(), "{}\n{}", out.status, out.stderr);
    assert!(
        out.stderr.contains("  outcome      succeeded"),
        "{}",
        out.stderr
    );
    assert!(
        !out.stderr.contains("cannot update the state file"),
        "{}",
        out.stderr
    );
    run.assert_nothing_left();
}
