//! The harness's own guarantees, checked with shell scripts standing in for bootstrap: output
//! and events are captured, a process left behind is found and killed, a stuck system is torn
//! down, and a timeout fails the test without leaving anything.

use std::os::unix::fs::PermissionsExt;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;
use std::time::Duration;

use s3res_testkit::{procs, EventKind, RunningSystem, System};

/// Writes an executable shell script into the system's dir and returns its path.
fn script(sys: &System, name: &str, body: &str) -> PathBuf {
    let p = sys.path(name);
    std::fs::write(&p, format!("#!/bin/sh\n{body}\n")).unwrap();
    std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755)).unwrap();
    p
}

fn panic_text(e: Box<dyn std::any::Any + Send>) -> String {
    e.downcast_ref::<String>()
        .cloned()
        .or_else(|| e.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_default()
}

fn assert_group_empty(pgid: i32) {
    let left: Vec<_> = procs::in_group(pgid)
        .into_iter()
        .filter(|p| !p.is_zombie())
        .collect();
    assert!(left.is_empty(), "group {pgid} not empty: {left:?}");
}

#[test]
fn captures_output_events_and_stdin() {
    let sys = System::new().stdin("hello from stdin\n");
    // $2 is the events path, $3 the description (argv: --events EVENTS SYSTEM.json).
    let prog = script(
        &sys,
        "fake-bootstrap",
        r#"test "$1" = --events || exit 9
cat > stdin-copy
printf '{"ts_ns":1,"system":"s","component":"echo","kind":"start","replica":0,"pid":100}\n' >> "$2"
printf '{"ts_ns":2,"system":"s","component":"echo","kind":"start","replica":1,"pid":101}\n' >> "$2"
printf '{"ts_ns":3,"system":"s","component":"echo","kind":"recovery","replica":1,"pid":101,"new_pid":102}\n' >> "$2"
grep -c components "$3"
echo to-stderr >&2
exit 3"#,
    );
    let mut run = sys.start_with(&prog, "{\n  \"components\": {}\n}\n");
    let out = run.wait(Duration::from_secs(30));
    assert_eq!(out.status.code(), Some(3), "{}", out.stderr);
    assert_eq!(out.stdout, "1\n");
    assert_eq!(out.stderr, "to-stderr\n");
    assert_eq!(out.events.len(), 3);
    assert_eq!(
        std::fs::read_to_string(run.path("stdin-copy")).unwrap(),
        "hello from stdin\n"
    );
    let e = run.wait_for_event(|e| e.kind == EventKind::Recovery, Duration::from_secs(5));
    assert_eq!(e.new_pid, Some(102));
    assert_eq!(
        run.replica_pids("echo").into_iter().collect::<Vec<_>>(),
        [(0, 100), (1, 102)]
    );
    run.assert_nothing_left();
}

#[test]
fn a_process_left_behind_fails_and_is_killed() {
    let sys = System::new();
    let prog = script(&sys, "leaky", "sleep 300 &\necho $! > leaked.pid\nexit 0");
    let mut run = sys.start_with(&prog, "{}");
    let pgid = run.pgid();
    let out = run.wait(Duration::from_secs(30));
    assert!(out.status.success());
    let leaked: i32 = std::fs::read_to_string(run.path("leaked.pid"))
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    let err = catch_unwind(AssertUnwindSafe(|| run.assert_nothing_left())).unwrap_err();
    let msg = panic_text(err);
    assert!(msg.contains("left processes behind"), "{msg}");
    assert!(msg.contains(&format!("pid {leaked} ")), "{msg}");
    drop(run);
    assert_group_empty(pgid);
}

#[test]
fn drop_fails_the_test_when_something_survives_bootstrap() {
    let sys = System::new();
    let prog = script(&sys, "leaky", "sleep 300 &\nexit 0");
    let mut run = sys.start_with(&prog, "{}");
    let pgid = run.pgid();
    run.wait(Duration::from_secs(30));
    let err = catch_unwind(AssertUnwindSafe(move || drop(run))).unwrap_err();
    assert!(panic_text(err).contains("left processes behind"));
    assert_group_empty(pgid);
}

#[test]
fn drop_kills_a_system_that_ignores_sigterm() {
    let sys = System::new();
    let prog = script(
        &sys,
        "stubborn",
        "trap '' TERM\nsleep 300 &\nsleep 300 &\nwait",
    );
    let run: RunningSystem = sys.start_with(&prog, "{}");
    let pgid = run.pgid();
    // Both sleeps are up (the group holds the shell and two sleeps).
    let t0 = std::time::Instant::now();
    while procs::in_group(pgid).len() < 3 {
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "sleeps did not start"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    // Still running when dropped: the harness SIGKILLs the group; that is no leak of the test.
    drop(run);
    assert_group_empty(pgid);
}

#[test]
fn wait_timeout_panics_with_stderr_and_cleans_up() {
    let sys = System::new();
    let prog = script(&sys, "hangs", "echo 'I am stuck' >&2\nexec sleep 300");
    let mut run = sys.start_with(&prog, "{}");
    let pgid = run.pgid();
    let err = catch_unwind(AssertUnwindSafe(|| run.wait(Duration::from_millis(300)))).unwrap_err();
    let msg = panic_text(err);
    assert!(msg.contains("did not exit within"), "{msg}");
    assert!(msg.contains("I am stuck"), "{msg}");
    drop(run);
    assert_group_empty(pgid);
}

#[test]
fn wait_for_event_fails_when_bootstrap_exits_without_it() {
    let sys = System::new();
    let prog = script(&sys, "quiet", "exit 0");
    let mut run = sys.start_with(&prog, "{}");
    let err = catch_unwind(AssertUnwindSafe(|| {
        run.wait_for_event(|_| true, Duration::from_secs(30))
    }))
    .unwrap_err();
    assert!(panic_text(err).contains("without the awaited event"));
}

#[test]
fn a_process_that_left_the_group_is_still_found() {
    let sys = System::new();
    let prog = script(&sys, "escapes", "setsid sleep 300 &\nsleep 0.2\nexit 0");
    let mut run = sys.start_with(&prog, "{}");
    run.wait(Duration::from_secs(30));
    let err = catch_unwind(AssertUnwindSafe(move || drop(run))).unwrap_err();
    let msg = panic_text(err);
    assert!(msg.contains("left processes behind"), "{msg}");
    assert!(msg.contains("(sleep)"), "{msg}");
}
