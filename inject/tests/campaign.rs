//! Campaigns against the real echo pipeline: TMR masks every kind of signal injection, the
//! unprotected echo does not (so the campaign can tell the difference), the same seed gives the
//! same schedule, and shards merged give the unsharded campaign.

mod common;

use std::path::Path;
use std::sync::Mutex;
use std::time::Duration;

use common::{echo_system, inject, read_json, read_jsonl, run_numbers, schedule};
use s3res_testkit::Rng;

/// One campaign at a time: the machine has two cores, and the verdicts depend on deadlines.
static SERIAL: Mutex<()> = Mutex::new(());
const LIMIT: Duration = Duration::from_secs(300);

/// Runs a campaign at S³RES's 2 Hz over a 1.5 s window per run (the system runs 2 s).
fn campaign(
    system: &Path,
    fault: &str,
    runs: u64,
    seed: u64,
    out: &Path,
    extra: &[&str],
) -> serde_json::Value {
    let (runs, seed) = (runs.to_string(), seed.to_string());
    let mut args = vec![
        "-q",
        "campaign",
        "--system",
        system.to_str().unwrap(),
        "--fault",
        fault,
        "--rate",
        "2",
        "--duration",
        "1.5",
        "--runs",
        &runs,
        "--seed",
        &seed,
        "--out",
        out.to_str().unwrap(),
        "--task-summary",
        "task.json",
        "--components",
        "echo",
    ];
    args.extend_from_slice(extra);
    let f = inject(&args, LIMIT);
    assert!(f.success, "campaign failed:\n{}", f.stderr);
    // `-q`: only warnings and errors (the progress line came all the same before).
    assert!(
        !f.stderr.contains(" runs, ETA") && !f.stderr.contains("ETA "),
        "-q, yet:\n{}",
        f.stderr
    );
    for file in [
        "campaign.json",
        "injections.jsonl",
        "runs.jsonl",
        "summary.json",
        "table.md",
    ] {
        assert!(out.join(file).is_file(), "{file} missing");
    }
    let s = read_json(&out.join("summary.json"));
    s[0].clone()
}

#[test]
fn tmr_masks_exec_sdc_and_cfe_without_errors_or_false_positives() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let seed = Rng::from_env().next_u64();
    let dir = tempfile::tempdir().unwrap();
    let system = echo_system(dir.path(), "tmr", 1000);
    for fault in ["exec", "sdc", "cfe"] {
        let out = dir.path().join(fault);
        // Fixed inter-arrival times: two faults in one TMR round are beyond what TMR masks, and
        // the test must not depend on how close an exponential draw puts two injections.
        let s = campaign(&system, fault, 3, seed, &out, &["--arrival", "fixed"]);
        eprintln!("{fault}: {s}");
        let injected = s["injected"].as_u64().unwrap();
        assert!(injected > 0, "{fault}: nothing injected: {s}");
        assert_eq!(s["recovered"].as_u64().unwrap(), injected, "{fault}: {s}");
        assert_eq!(s["pct_error"].as_f64(), Some(0.0), "{fault}: {s}");
        assert_eq!(s["false_positives"], 0, "{fault}: {s}");
        assert_eq!(s["successful_runs"], 3, "{fault}: {s}");
        let kind = match fault {
            "exec" => "crash",
            "sdc" => "sdc",
            _ => "hang",
        };
        for i in read_jsonl(&out.join("injections.jsonl")) {
            if i["outcome"] == "recovered" {
                assert_eq!(i["detected_as"], kind, "{i}");
                assert!(
                    i["detection_latency_us"].is_u64() && i["recovery_us"].is_u64(),
                    "{i}"
                );
            }
            for field in ["ts_ns", "seed", "kind", "component", "replica", "pid"] {
                assert!(
                    !i[field].is_null() || i["outcome"] == "missed",
                    "{field} in {i}"
                );
            }
        }
    }
}

#[test]
fn without_protection_the_same_campaign_fails() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let seed = Rng::from_env().next_u64();
    let dir = tempfile::tempdir().unwrap();
    let system = echo_system(dir.path(), "none", 1000);
    for fault in ["exec", "sdc", "cfe"] {
        let out = dir.path().join(fault);
        // A spinning unprotected echo never ends: the time limit ends the run.
        let limit = if fault == "cfe" { "8" } else { "30" };
        // Fixed arrivals: 2 Hz exponential over the 1.5 s window draws no injection at all
        // for about one seed in twenty (e^-3), and then the unprotected run rightly succeeds.
        let extra = ["--run-timeout", limit, "--arrival", "fixed"];
        let s = campaign(&system, fault, 1, seed, &out, &extra);
        eprintln!("{fault}: {s}");
        assert_eq!(s["config"], "none");
        assert_eq!(s["successful_runs"], 0, "{fault}: {s}");
        assert!(s["undetected"].as_u64().unwrap() > 0, "{fault}: {s}");
        assert_eq!(s["recovered"], 0, "{fault}: {s}");
        if fault == "cfe" {
            assert_eq!(s["timed_out_runs"], 1, "{s}");
        }
    }
}

#[test]
fn same_seed_same_schedule_and_shards_merge_into_the_whole() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let seed = Rng::from_env().next_u64();
    let dir = tempfile::tempdir().unwrap();
    let system = echo_system(dir.path(), "tmr", 1000);
    let whole = dir.path().join("whole");
    let s_whole = campaign(&system, "sdc", 3, seed, &whole, &[]);
    let (a, b) = (dir.path().join("s1"), dir.path().join("s2"));
    campaign(&system, "sdc", 3, seed, &a, &["--shard", "1/2"]);
    campaign(&system, "sdc", 3, seed, &b, &["--shard", "2/2"]);
    assert_eq!(run_numbers(&a), vec![0, 2]);
    assert_eq!(run_numbers(&b), vec![1]);

    let merge = |out: &Path, inputs: &[&Path]| {
        let mut args = vec!["merge", "--out", out.to_str().unwrap()];
        args.extend(inputs.iter().map(|p| p.to_str().unwrap()));
        inject(&args, Duration::from_secs(30))
    };
    let merged = dir.path().join("merged");
    let f = merge(&merged, &[&b, &a]);
    assert!(f.success, "{}", f.stderr);
    assert!(f.stdout.contains("| tmr | sdc | 3 |"), "{}", f.stdout);
    let s_merged = read_json(&merged.join("summary.json"))[0].clone();

    // Same seed, separate processes and machines' worth of slicing: the same schedule.
    assert!(!schedule(&whole).is_empty());
    assert_eq!(schedule(&whole), schedule(&merged));
    for k in ["runs", "runs_done", "planned", "seed", "config", "fault"] {
        assert_eq!(s_whole[k], s_merged[k], "{k}");
    }
    // What happened at each instant is the machine's business (an injection can find its
    // slot being replaced); that merging identical records gives identical tables is
    // report::tests::shards_merge_into_the_whole_and_duplicates_are_refused.

    // Merging a shard twice is refused.
    let f = merge(&dir.path().join("again"), &[&a, &a]);
    assert!(
        !f.success && f.stderr.contains("appears in two inputs"),
        "{}",
        f.stderr
    );
}

#[test]
fn sigint_stops_the_run_in_progress_and_keeps_the_completed_ones() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let system = echo_system(dir.path(), "tmr", 1000);
    let out = dir.path().join("out");
    let p = common::spawn(&[
        "-q",
        "campaign",
        "--system",
        system.to_str().unwrap(),
        "--fault",
        "exec",
        "--runs",
        "20",
        "--seed",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]);
    let runs = out.join("runs.jsonl");
    let deadline = std::time::Instant::now() + LIMIT;
    while std::fs::read_to_string(&runs).map_or(0, |t| t.lines().count()) < 1 {
        assert!(std::time::Instant::now() < deadline, "no run completed");
        std::thread::sleep(Duration::from_millis(50));
    }
    // Into the next run.
    std::thread::sleep(Duration::from_millis(700));
    s3res_testkit::kill_pid(p.child.id() as i32, libc::SIGINT).unwrap();
    let f = p.wait(Duration::from_secs(60)); // fails if any process of the run is left
    assert_eq!(f.code, Some(130), "{}", f.stderr);
    let kept = read_jsonl(&runs).len();
    assert!((1..20).contains(&kept), "{kept} runs kept");
    // Counted from 1, as the progress line counts (it said run 1 of the second run).
    let said = format!("stopped by signal during run {}; ", kept + 1);
    assert!(f.stderr.contains(&said), "{}", f.stderr);
    assert_eq!(
        read_json(&out.join("summary.json"))[0]["runs_done"],
        kept as u64
    );
}

#[test]
fn bad_usage_gets_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let system = echo_system(dir.path(), "tmr", 10);
    let broken = dir.path().join("broken.json");
    std::fs::write(&broken, "{\n  \"name\": 3\n}").unwrap();
    let out = dir.path().join("o");
    let fails_as = |fault: &str, system: &Path, extra: &[&str], expected: &str| {
        let mut args = vec![
            "campaign",
            "--system",
            system.to_str().unwrap(),
            "--fault",
            fault,
            "--runs",
            "1",
            "--seed",
            "1",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let f = inject(&args, Duration::from_secs(30));
        assert!(
            !f.success && f.stderr.contains(expected),
            "{extra:?}: {}",
            f.stderr
        );
    };
    let fails_with =
        |system: &Path, extra: &[&str], expected: &str| fails_as("exec", system, extra, expected);
    fails_with(&system, &["--components", "nope"], "no component `nope`");
    fails_with(&system, &["--shard", "3/2"], "K must be in 1..=2");
    // A var option with a var fault (with exec it is refused as another kind's option).
    fails_as(
        "var",
        &system,
        &["--var-field", "sign", "--var-flips", "2"],
        "does not fit field",
    );
    fails_with(&broken, &[], "broken.json:2");
}
