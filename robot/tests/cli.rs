//! The simulator's offline commands, run as a user would: `golden` and `render`.

use std::process::Command;

use s3res_testkit::bin_path;

fn sim() -> Command {
    Command::new(bin_path("s3res-sim"))
}

#[test]
fn golden_runs_replay_and_render_with_an_overlay() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.json");
    let b = dir.path().join("b.json");
    for out in [&a, &b] {
        let st = sim()
            .args(["golden", "--seed", "5", "--summary"])
            .arg(out)
            .status()
            .unwrap();
        assert!(st.success(), "golden mission of seed 5 fails: {st}");
    }
    // Same seed, same mission, byte for byte.
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());

    // A run that fails (too little time) exits 1 and says so in its summary.
    let short = dir.path().join("short.json");
    let st = sim()
        .args(["golden", "--seed", "5", "--time-limit", "3", "--summary"])
        .arg(&short)
        .status()
        .unwrap();
    assert_eq!(st.code(), Some(1));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&short).unwrap()).unwrap();
    assert_eq!(summary["success"], false);
    assert_eq!(summary["outcome"], "time_limit");

    let svg = dir.path().join("maze.svg");
    let st = sim()
        .arg("render")
        .arg(&a)
        .arg("--overlay")
        .arg(&short)
        .arg("--out")
        .arg(&svg)
        .status()
        .unwrap();
    assert!(st.success());
    let text = std::fs::read_to_string(&svg).unwrap();
    assert!(text.starts_with("<svg") && text.matches("<polyline").count() == 2);

    // Another maze cannot be overlaid; a missing file is a clear error, not a panic.
    let other = dir.path().join("other.json");
    assert!(sim()
        .args(["golden", "--seed", "6", "--summary"])
        .arg(&other)
        .status()
        .unwrap()
        .success());
    let out = sim()
        .arg("render")
        .arg(&a)
        .arg("--overlay")
        .arg(&other)
        .arg("--out")
        .arg(&svg)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("another maze"));
    let out = sim()
        .args(["render", "/nonexistent.json", "--out"])
        .arg(&svg)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent.json"));
}
