//! Campaigns fail loudly and record where they ran: a relative `--out` with `--keep-runs` works
//! from any working folder, a run that never started its system stops the campaign with exit
//! status 1 and the reason on stderr, the progress line counts what the table counts, and
//! `campaign.json` / `runs.jsonl` describe the machine and its load.

mod common;

use std::os::unix::fs::PermissionsExt as _;
use std::sync::Mutex;
use std::time::Duration;

use common::{echo_system, read_json, read_jsonl, spawn_with};

/// One campaign at a time: the machine has two cores, and the verdicts depend on deadlines.
static SERIAL: Mutex<()> = Mutex::new(());
const LIMIT: Duration = Duration::from_secs(300);

#[test]
fn a_relative_out_with_kept_runs_works_and_records_the_machine() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let system = echo_system(dir.path(), "tmr", 1000);
    let args = [
        "campaign",
        "--system",
        "echo-tmr.json",
        "--fault",
        "exec",
        "--rate",
        "2",
        "--arrival",
        "fixed",
        "--duration",
        "1",
        "--runs",
        "2",
        "--seed",
        "7",
        "--components",
        "echo",
        "--keep-runs",
        "--out",
        "out/rel",
    ];
    assert!(system.ends_with("echo-tmr.json"));
    let f = spawn_with(Some(dir.path()), &[], &args).wait(LIMIT);
    assert!(f.success, "campaign failed:\n{}", f.stderr);
    let out = dir.path().join("out/rel");
    for r in ["run-000000", "run-000001"] {
        let events = out.join("runs").join(r).join("events.jsonl");
        assert!(
            events.is_file(),
            "{} missing:\n{}",
            events.display(),
            f.stderr
        );
    }
    let runs = read_jsonl(&out.join("runs.jsonl"));
    assert_eq!(runs.len(), 2);
    for run in &runs {
        assert_eq!(run["ready"], true, "{run}");
        for load in ["load_before", "load_after"] {
            assert!(run[load]["one"].as_f64().is_some(), "{load} missing: {run}");
        }
    }
    let info = read_json(&out.join("campaign.json"));
    let m = &info["machine"];
    assert!(m["cores"].as_u64().is_some_and(|n| n >= 1), "{m}");
    assert!(m["kernel"].as_str().is_some_and(|k| !k.is_empty()), "{m}");
    assert!(m["load"]["one"].as_f64().is_some(), "{m}");
    assert!(m["load_at_end"]["one"].as_f64().is_some(), "{m}");
    assert!(
        ["release", "debug"].contains(&m["build"]["profile"].as_str().unwrap_or("")),
        "{m}"
    );
    // The progress line and the table count the same injections.
    let s = &read_json(&out.join("summary.json"))[0];
    let injected = s["injected"].as_u64().unwrap();
    let progress = format!("| {injected} injected,");
    assert!(
        f.stderr.contains(&progress),
        "the progress does not say {progress:?} as the summary does ({s}):\n{}",
        f.stderr
    );
    let row = format!("| exec | 2 | {injected} |");
    assert!(
        f.stdout.contains(&row),
        "table lacks {row:?}:\n{}",
        f.stdout
    );
}

#[test]
fn a_run_that_never_starts_its_system_stops_the_campaign_with_the_reason() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let system = echo_system(dir.path(), "tmr", 100);
    // A bootstrap that cannot start anything, as one given a path it cannot write would.
    let fake = dir.path().join("fake-bootstrap");
    std::fs::write(
        &fake,
        "#!/bin/sh\necho 'error: cannot create the events file: the disk is on fire' >&2\nexit 1\n",
    )
    .unwrap();
    std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).unwrap();
    let out = dir.path().join("out");
    let args = [
        "campaign",
        "--system",
        system.to_str().unwrap(),
        "--fault",
        "exec",
        "--runs",
        "3",
        "--seed",
        "1",
        "--components",
        "echo",
        "--out",
        out.to_str().unwrap(),
    ];
    let f = spawn_with(None, &[("S3RES_BOOTSTRAP", fake.to_str().unwrap())], &args).wait(LIMIT);
    assert_eq!(
        f.code,
        Some(1),
        "stdout:\n{}\nstderr:\n{}",
        f.stdout,
        f.stderr
    );
    assert!(
        f.stderr.contains("run 1 never started its system")
            && f.stderr.contains("the disk is on fire"),
        "the reason is not on stderr:\n{}",
        f.stderr
    );
    assert!(
        !f.stdout.contains("| exec |"),
        "a table was printed:\n{}",
        f.stdout
    );
    // What was done is written: the one run, with its error.
    let runs = read_jsonl(&out.join("runs.jsonl"));
    assert_eq!(runs.len(), 1, "{runs:?}");
    assert_eq!(runs[0]["ready"], false);
}

/// A mistyped `--task-summary` (a file the task never writes) failed every run without a word;
/// an absolute one judged every run by one stale file. The one is said once, and each run's
/// record tells a missing summary from one that says `"ok": false`; the other is refused.
#[test]
fn a_task_summary_never_written_is_said_and_one_outside_the_run_is_refused() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let system = echo_system(dir.path(), "smr", 300);
    let out = dir.path().join("out");
    let stale = dir.path().join("stale-task.json");
    std::fs::write(&stale, "{\"ok\": true}\n").unwrap();
    let args = |summary: &str| {
        let mut a: Vec<String> = [
            "-q",
            "campaign",
            "--system",
            system.to_str().unwrap(),
            "--fault",
            "none",
            "--runs",
            "2",
            "--seed",
            "1",
            "--run-timeout",
            "30",
            "--out",
            out.to_str().unwrap(),
            "--task-summary",
        ]
        .map(str::to_owned)
        .to_vec();
        a.push(summary.to_owned());
        a
    };
    for bad in [stale.to_str().unwrap(), "../stale-task.json"] {
        let a = args(bad);
        let a: Vec<&str> = a.iter().map(String::as_str).collect();
        let f = spawn_with(None, &[], &a).wait(LIMIT);
        assert_eq!(f.code, Some(1), "{}", f.stderr);
        let want = format!("--task-summary {bad}: give a file in the run's folder");
        assert!(f.stderr.contains(&want), "{}", f.stderr);
        assert!(!out.exists(), "the campaign wrote {out:?}");
    }
    let a = args("tsk.json");
    let a: Vec<&str> = a.iter().map(String::as_str).collect();
    let f = spawn_with(None, &[], &a).wait(LIMIT);
    assert!(f.success, "{}", f.stderr);
    assert_eq!(
        f.stderr.matches("left no task summary tsk.json").count(),
        1,
        "{}",
        f.stderr
    );
    let runs = read_jsonl(&out.join("runs.jsonl"));
    assert_eq!(runs.len(), 2);
    for run in &runs {
        assert_eq!(run["task_ok"], false, "{run}");
        assert_eq!(run["task_summary_ok"], false, "{run}");
        let error = run["error"].as_str().unwrap_or_default();
        assert!(error.contains("no task summary tsk.json"), "{run}");
    }
}
