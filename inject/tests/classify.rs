//! Unprotected outcome classification on a real echo whose output is bootstrap's stdout: a
//! signal SDC changes exactly one bit of one frame, a variable flip changes exactly the bit it
//! names, SIGKILL is a crash and a control-flow error a hang.

mod common;

use std::path::Path;
use std::time::Duration;

use common::{inject, read_json, read_jsonl, spawn};
use s3res_testkit::Rng;

const DESCRIPTION: &str = r#"{
  "name": "echo-to-stdout",
  "components": {
    "source": { "exec": "s3res-source", "args": ["--count", "400", "--hz", "400"] },
    "echo":   { "exec": "s3res-echo", "args": ["--stateful"] }
  },
  "channels": [
    { "from": "source.out", "to": "echo.in" },
    { "from": "echo.out",   "to": "stdout" }
  ]
}"#;

/// `classify` of the echo description in `dir` with `fault`, into `dir/out-FAULT` (plus
/// `extra` arguments), with a fresh seed.
fn classify(
    dir: &Path,
    fault: &str,
    runs: u64,
    extra: &[&str],
) -> (serde_json::Value, Vec<serde_json::Value>) {
    let out = dir.join(format!("out-{fault}"));
    let seed = Rng::from_env().next_u64().to_string();
    let f = inject(
        &strs(&classify_args(dir, fault, runs, &seed, &out, extra)),
        Duration::from_secs(240),
    );
    assert!(f.success, "{}", f.stderr);
    assert!(f.stdout.contains("| Benign % |"), "{}", f.stdout);
    (
        read_json(&out.join("classify.json")),
        read_jsonl(&out.join("classify.jsonl")),
    )
}

/// The arguments of a `classify` of the echo description (written into `dir`).
fn classify_args(
    dir: &Path,
    fault: &str,
    runs: u64,
    seed: &str,
    out: &Path,
    extra: &[&str],
) -> Vec<String> {
    let system = dir.join("system.json");
    std::fs::write(&system, DESCRIPTION).unwrap();
    let mut args: Vec<String> = [
        "-q",
        "classify",
        "--system",
        system.to_str().unwrap(),
        "--components",
        "echo",
        "--fault",
        fault,
        "--runs",
        &runs.to_string(),
        "--seed",
        seed,
        "--out",
        out.to_str().unwrap(),
        "--duration",
        "0.5",
        "--run-timeout",
        "6",
    ]
    .map(str::to_owned)
    .to_vec();
    args.extend(extra.iter().map(|a| a.to_string()));
    args
}

fn strs(args: &[String]) -> Vec<&str> {
    args.iter().map(String::as_str).collect()
}

#[test]
fn signal_sdc_flips_exactly_one_bit_of_one_frame() {
    let dir = tempfile::tempdir().unwrap();
    let (s, recs) = classify(dir.path(), "sdc", 4, &[]);
    assert_eq!(s["sdc"], 4, "{s}");
    for r in recs {
        assert_eq!(r["class"], "sdc", "{r}");
        assert_eq!(r["diff"]["frames_differing"], 1, "{r}");
        assert_eq!(r["diff"]["bits_differing"], 1, "{r}");
        assert_eq!(r["diff"]["length_differs"], false, "{r}");
    }
}

#[test]
fn var_flips_the_sign_of_the_chosen_f64_and_nothing_else() {
    let dir = tempfile::tempdir().unwrap();
    let extra = ["--var-offset", "8", "--var-field", "sign"];
    let (s, recs) = classify(dir.path(), "var", 3, &extra);
    assert_eq!(s["sdc"], 3, "{s}");
    for r in recs {
        assert_eq!(r["bits"], serde_json::json!([63]), "{r}");
        assert_eq!(r["diff"]["bits_differing"], 1, "{r}");
        // Bit 63 of the value at payload offset 8 is the top bit of payload byte 15.
        assert_eq!(r["diff"]["first"]["payload_offset"], 15, "{r}");
        assert_eq!(r["diff"]["first"]["xor"], 0x80, "{r}");
    }
}

#[test]
fn exec_is_a_crash_and_cfe_a_hang() {
    let dir = tempfile::tempdir().unwrap();
    let (s, _) = classify(dir.path(), "exec", 2, &[]);
    assert_eq!(s["crash"], 2, "{s}");
    let (s, _) = classify(dir.path(), "cfe", 2, &[]);
    assert_eq!(s["hang"], 2, "{s}");
    assert_eq!(s["pct_hang"], 100.0, "{s}");
}

/// The unprotected maze robot, classified by its mission: the sim's summary is the output.
/// SIGKILL to the navigator is a crash, and no successful mission (nothing replaces the
/// navigator: the robot drives on its last command into a wall); the golden mission is kept.
/// `--output FILE` that the golden run never wrote: before, the golden output was empty, every
/// injected run's was too, and every run was benign (exit 0). Refused after the golden run,
/// naming the file (not the run's folder, removed by then), and no run is classified.
#[test]
fn an_output_file_the_golden_run_never_wrote_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out-sdc");
    let args = classify_args(dir.path(), "sdc", 2, "1", &out, &["--output", "nosuch.txt"]);
    let f = inject(&strs(&args), Duration::from_secs(120));
    assert_eq!(f.code, Some(1), "{}", f.stderr);
    assert!(
        f.stderr
            .contains("the golden run left no output file that --output nosuch.txt names")
            && f.stderr.contains("in the folder it ran in, removed since"),
        "{}",
        f.stderr
    );
    assert!(!out.join("classify.json").exists(), "it classified");
}

#[test]
fn a_robot_is_classified_by_its_mission() {
    let dir = tempfile::tempdir().unwrap();
    let system = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/robot/campaign/none.json");
    let out = dir.path().join("out");
    let seed = Rng::from_env().next_u64().to_string();
    let f = inject(
        &[
            "-q",
            "classify",
            "--system",
            system.to_str().unwrap(),
            "--components",
            "navigator",
            "--fault",
            "exec",
            "--runs",
            "2",
            "--seed",
            &seed,
            "--out",
            out.to_str().unwrap(),
            "--duration",
            "1",
            "--mission",
            "mission.json",
            "--run-timeout",
            "60",
        ],
        Duration::from_secs(300),
    );
    assert!(f.success, "{}", f.stderr);
    assert!(f.stdout.contains("| Successful missions |"), "{}", f.stdout);
    // Its seed and folder are said, as a campaign says them (they were not).
    assert!(
        f.stderr.contains(&format!("2 run(s), seed {seed}"))
            && f.stderr.contains(&format!("outputs in {}", out.display())),
        "{}",
        f.stderr
    );
    let s = read_json(&out.join("classify.json"));
    assert_eq!(
        (s["classified"].as_u64(), s["crash"].as_u64()),
        (Some(2), Some(2)),
        "{s}"
    );
    assert_eq!(s["missions"]["golden"]["outcome"], "goal", "{s}");
    assert_eq!(s["missions"]["successful"]["k"], 0, "{s}");
    assert_eq!(s["rates"]["crash"]["pct"], 100.0, "{s}");
    for r in read_jsonl(&out.join("classify.jsonl")) {
        assert_eq!(r["class"], "crash", "{r}");
        assert_eq!(r["failure"], "killed by signal 9", "{r}");
        // The sim judged the mission: the robot drove on, on its last command.
        assert_eq!(r["mission"]["success"], false, "{r}");
    }
}

/// What a classification did, run by run, independent of timing: the schedule and the class.
fn per_run(out: &Path) -> Vec<String> {
    read_jsonl(&out.join("classify.jsonl"))
        .iter()
        .map(|r| {
            format!(
                "{} {} {} {} {}",
                r["run"], r["at_ns"], r["kind"], r["value"], r["class"]
            )
        })
        .collect()
}

/// Shards merge into what one machine classifies, run for run; a classification stopped by
/// SIGTERM keeps its finished runs and `--resume` completes it the same way.
#[test]
fn shards_merge_into_the_whole_and_a_stopped_classification_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let seed = Rng::from_env().next_u64().to_string();
    let args = |out: &Path, extra: &[&str]| classify_args(dir.path(), "sdc", 4, &seed, out, extra);
    let limit = Duration::from_secs(240);

    let whole = dir.path().join("whole");
    let f = inject(&strs(&args(&whole, &[])), limit);
    assert!(f.success, "{}", f.stderr);
    let expected = per_run(&whole);
    assert_eq!(expected.len(), 4);

    let mut shards = Vec::new();
    for k in ["1/2", "2/2"] {
        let out = dir.path().join(format!("shard-{}", &k[..1]));
        let f = inject(&strs(&args(&out, &["--shard", k])), limit);
        assert!(f.success, "{}", f.stderr);
        assert_eq!(per_run(&out).len(), 2, "{k}");
        shards.push(out);
    }
    let merged = dir.path().join("merged");
    let mut merge = vec!["-q", "merge", "--out", merged.to_str().unwrap()];
    merge.push(shards[0].to_str().unwrap());
    let f = inject(&merge, limit);
    assert!(f.success, "{}", f.stderr);
    assert!(f.stderr.contains("has 2 of its 4 runs"), "{}", f.stderr);
    let merged = dir.path().join("merged-all");
    let mut merge = vec!["-q", "merge", "--out", merged.to_str().unwrap()];
    merge.extend(shards.iter().map(|p| p.to_str().unwrap()));
    let f = inject(&merge, limit);
    assert!(f.success, "{}", f.stderr);
    assert_eq!(per_run(&merged), expected);
    let (a, b) = (
        read_json(&whole.join("classify.json")),
        read_json(&merged.join("classify.json")),
    );
    for k in [
        "runs",
        "classified",
        "sdc",
        "benign",
        "crash",
        "hang",
        "seed",
    ] {
        assert_eq!(a[k], b[k], "{k}");
    }
    // A shard twice is refused (other refusals: the unit tests of `classify::merge`).
    let twice = dir.path().join("twice");
    let f = inject(
        &[
            "-q",
            "merge",
            "--out",
            twice.to_str().unwrap(),
            shards[0].to_str().unwrap(),
            shards[0].to_str().unwrap(),
        ],
        limit,
    );
    assert!(
        f.code == Some(1) && f.stderr.contains("more than one input"),
        "{}",
        f.stderr
    );

    // Stopped after a run or two: the finished runs are kept, and the stop says how to go on.
    let stopped = dir.path().join("stopped");
    let p = spawn(&strs(&args(&stopped, &[])));
    let deadline = std::time::Instant::now() + limit;
    while std::fs::read_to_string(stopped.join("classify.jsonl")).map_or(0, |t| t.lines().count())
        < 1
    {
        assert!(std::time::Instant::now() < deadline, "no run finished");
        std::thread::sleep(Duration::from_millis(20));
    }
    s3res_testkit::kill_pid(p.child.id() as i32, libc::SIGTERM).unwrap();
    let f = p.wait(limit);
    assert_eq!(f.code, Some(143), "{}", f.stderr);
    assert!(f.stderr.contains("--resume"), "{}", f.stderr);
    let kept = per_run(&stopped);
    assert!((1..4).contains(&kept.len()), "{kept:?}");
    assert_eq!(kept[..], expected[..kept.len()]);

    // Not overwritten without --resume; not resumed with other parameters.
    let f = inject(&strs(&args(&stopped, &[])), limit);
    assert!(
        f.code == Some(1) && f.stderr.contains("already holds a classification"),
        "{}",
        f.stderr
    );
    let other = classify_args(dir.path(), "sdc", 5, &seed, &stopped, &["--resume"]);
    let f = inject(&strs(&other), limit);
    assert!(
        f.code == Some(1) && f.stderr.contains("another classification"),
        "{}",
        f.stderr
    );
    assert_eq!(
        per_run(&stopped),
        kept,
        "a refused resume changed the records"
    );

    let f = inject(&strs(&args(&stopped, &["--resume"])), limit);
    assert!(f.success, "{}", f.stderr);
    let said = format!("resuming: {} run(s) already done", kept.len());
    assert!(f.stderr.contains(&said), "{}", f.stderr);
    assert_eq!(per_run(&stopped), expected);
}
