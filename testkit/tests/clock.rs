//! End to end: the voter's deadline clock. By default it is the CPU's counter, calibrated and
//! logged at start; `S3RES_CLOCK=monotonic` forces CLOCK_MONOTONIC; a hang is caught on either;
//! a setting that names no clock stops the voter with a clear error.

use std::path::PathBuf;
use std::time::Duration;

use s3res_testkit::{assert_sink_whole, bin_path, echo_pipeline, signals, EventKind, System};

const LIMIT: Duration = Duration::from_secs(90);

/// A script that starts bootstrap with `S3RES_CLOCK=value` (voters inherit the environment).
fn bootstrap_with_clock(sys: &System, value: &str) -> PathBuf {
    use std::os::unix::fs::PermissionsExt;
    let path = sys.path("bootstrap-with-clock.sh");
    let script = format!(
        "#!/bin/sh\nS3RES_CLOCK='{value}' exec {} \"$@\"\n",
        bin_path("s3res-bootstrap").display()
    );
    std::fs::write(&path, script).unwrap();
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755)).unwrap();
    path
}

/// Runs a TMR echo under `clock`, makes replica 1 spin, and checks the hang is caught and
/// repaired; returns bootstrap's stderr.
fn hang_caught_under(clock: &str) -> String {
    let count = 1500;
    let sys = System::new();
    let bootstrap = bootstrap_with_clock(&sys, clock);
    let echo = r#"{ "exec": "s3res-echo", "args": ["--stateful"], "redundancy": "tmr", "timeout_us": 200000 }"#;
    let desc = echo_pipeline(&sys.path("summary.json"), echo, count, 500);
    let mut run = sys.start_with(&bootstrap, &desc);
    run.wait_for_replicas("echo", 3);
    let spinner = run.replica_pids("echo")[&1];
    s3res_testkit::kill_pid(spinner, signals::inject_cfe()).unwrap();
    run.wait_for_event(
        |e| e.kind == EventKind::Hang && e.pid == Some(spinner),
        Duration::from_secs(20),
    );
    run.wait_for_event(
        |e| e.kind == EventKind::Recovery && e.pid == Some(spinner),
        Duration::from_secs(20),
    );
    let out = run.wait_success(LIMIT);
    assert_sink_whole(&run.path("summary.json"), count);
    out.stderr
}

fn clock_lines(stderr: &str) -> Vec<&str> {
    stderr
        .lines()
        .filter(|l| l.contains("deadline clock"))
        .collect()
}

#[test]
fn the_counter_clock_is_calibrated_logged_and_catches_a_hang() {
    let stderr = hang_caught_under("counter");
    let lines = clock_lines(&stderr);
    for l in &lines {
        eprintln!("{l}");
    }
    assert_eq!(lines.len(), 1, "one voter, one clock line:\n{stderr}");
    // Either the counter was calibrated (with its figures) or the reason it is not used.
    let calibrated = lines[0].contains("calibrated against CLOCK_MONOTONIC")
        && lines[0].contains("ticks_per_us=")
        && lines[0].contains("error_ppm=");
    let fell_back = lines[0].contains("CLOCK_MONOTONIC") && lines[0].contains("reason=");
    assert!(calibrated || fell_back, "{}", lines[0]);
}

#[test]
fn forced_monotonic_clock_says_so_and_catches_a_hang() {
    let stderr = hang_caught_under("monotonic");
    let lines = clock_lines(&stderr);
    assert_eq!(lines.len(), 1, "one voter, one clock line:\n{stderr}");
    assert!(
        lines[0].contains("source=monotonic") && lines[0].contains("S3RES_CLOCK=monotonic"),
        "{}",
        lines[0]
    );
}

#[test]
fn a_clock_setting_that_names_no_clock_is_a_clear_error() {
    let sys = System::new();
    let bootstrap = bootstrap_with_clock(&sys, "sundial");
    let echo = r#"{ "exec": "s3res-echo", "redundancy": "tmr", "timeout_us": 200000 }"#;
    let desc = echo_pipeline(&sys.path("summary.json"), echo, 10, 0);
    let mut run = sys.start_with(&bootstrap, &desc);
    let out = run.wait(LIMIT);
    assert!(
        !out.status.success(),
        "bootstrap succeeded:\n{}",
        out.stderr
    );
    assert!(
        out.stderr
            .contains("S3RES_CLOCK=\"sundial\" is not a clock"),
        "{}",
        s3res_testkit::tail(&out.stderr, 30)
    );
    run.assert_nothing_left();
}
