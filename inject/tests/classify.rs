//! Unprotected outcome classification on a real echo whose output is bootstrap's stdout: a
//! signal SDC changes exactly one bit of one frame, a variable flip changes exactly the bit it
//! names, SIGKILL is a crash and a control-flow error a hang.

mod common;

use std::path::Path;
use std::time::Duration;

use common::{inject, read_json, read_jsonl};
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

fn classify(
    dir: &Path,
    fault: &str,
    runs: u64,
    extra: &[&str],
) -> (serde_json::Value, Vec<serde_json::Value>) {
    let system = dir.join("system.json");
    std::fs::write(&system, DESCRIPTION).unwrap();
    let out = dir.join(format!("out-{fault}"));
    let seed = Rng::from_env().next_u64().to_string();
    let runs = runs.to_string();
    let mut args = vec![
        "-q",
        "classify",
        "--system",
        system.to_str().unwrap(),
        "--components",
        "echo",
        "--fault",
        fault,
        "--runs",
        &runs,
        "--seed",
        &seed,
        "--out",
        out.to_str().unwrap(),
        "--duration",
        "0.5",
        "--run-timeout",
        "6",
    ];
    args.extend_from_slice(extra);
    let f = inject(&args, Duration::from_secs(240));
    assert!(f.success, "{}", f.stderr);
    assert!(f.stdout.contains("| Benign % |"), "{}", f.stdout);
    (
        read_json(&out.join("classify.json")),
        read_jsonl(&out.join("classify.jsonl")),
    )
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
        assert_ne!(r["mission"]["success"], true, "{r}");
    }
}
