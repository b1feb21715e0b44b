//! The component binaries in standalone mode, chained by pipes as a user would in a shell.

use std::io::Write;
use std::process::{Command, Stdio};

fn bin(name: &str) -> Command {
    let path = match name {
        "source" => env!("CARGO_BIN_EXE_s3res-source"),
        "echo" => env!("CARGO_BIN_EXE_s3res-echo"),
        "sink" => env!("CARGO_BIN_EXE_s3res-sink"),
        _ => env!("CARGO_BIN_EXE_s3res-misbehave"),
    };
    let mut c = Command::new(path);
    c.env_remove("S3RES_PORTS")
        .env_remove("S3RES_VOTER_SOCKET")
        .env_remove("S3RES_REPLICA")
        .env("RUST_LOG", "warn");
    c
}

/// Runs `source | middle | sink` and returns (sink exit code, sink stdout, summary JSON).
fn pipeline(
    source: &[&str],
    middle: (&str, &[&str], Option<&str>),
    sink: &[&str],
) -> (i32, String, serde_json::Value) {
    let dir = tempfile::tempdir().unwrap();
    let summary = dir.path().join("summary.json");
    let mut src = bin("source")
        .args(source)
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut mid_cmd = bin(middle.0);
    mid_cmd.args(middle.1);
    if let Some(r) = middle.2 {
        mid_cmd.env("S3RES_REPLICA", r);
    }
    let mut mid = mid_cmd
        .stdin(src.stdout.take().unwrap())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let out = bin("sink")
        .args(sink)
        .arg("--summary")
        .arg(&summary)
        .stdin(mid.stdout.take().unwrap())
        .output()
        .unwrap();
    src.wait().unwrap();
    mid.wait().unwrap();
    let json = std::fs::read_to_string(&summary).unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        serde_json::from_str(&json).unwrap(),
    )
}

#[test]
fn stateful_echo_pipeline_is_ok() {
    let (code, line, json) = pipeline(
        &["--count", "200", "--hz", "0", "--size", "64"],
        ("echo", &["--stateful"], None),
        &["--stateful", "--expect", "200"],
    );
    assert_eq!(code, 0, "{line}");
    assert_eq!(
        line.trim(),
        "sink: 200 frames, 0 missing, 0 duplicated, 0 reordered, 0 corrupt, 0 state breaks: OK"
    );
    assert_eq!(json["ok"], true);
    assert_eq!(json["frames"], 200);
}

#[test]
fn paced_source_takes_its_time() {
    let t = std::time::Instant::now();
    let (code, line, _) = pipeline(
        &["--count", "11", "--hz", "100"],
        ("echo", &[], None),
        &["--expect", "11"],
    );
    assert_eq!(code, 0, "{line}");
    // Frame 10 is due 100 ms after frame 0.
    assert!(
        t.elapsed() >= std::time::Duration::from_millis(100),
        "{:?}",
        t.elapsed()
    );
}

#[test]
fn sink_fails_on_a_short_stream() {
    let (code, line, json) = pipeline(
        &["--count", "5", "--hz", "0"],
        ("echo", &[], None),
        &["--expect", "7"],
    );
    assert_eq!(code, 1);
    assert!(
        line.contains("2 missing") && line.ends_with("FAILED\n"),
        "{line}"
    );
    assert_eq!(json["missing"], 2);
    assert_eq!(json["expected"], 7);
}

#[test]
fn misbehave_extra_frame_is_seen_by_the_sink() {
    // The extra frame is not a source frame: the sink counts it corrupt.
    let (code, line, json) = pipeline(
        &["--count", "5", "--hz", "0"],
        (
            "misbehave",
            &["--mode", "extra", "--replica", "1", "--at", "2"],
            Some("1"),
        ),
        &["--expect", "5"],
    );
    assert_eq!(code, 1, "{line}");
    assert_eq!(json["frames"], 6);
    assert_eq!(json["corrupt"], 1);
}

#[test]
fn misbehave_only_as_the_named_replica() {
    let (code, line, _) = pipeline(
        &["--count", "5", "--hz", "0"],
        (
            "misbehave",
            &[
                "--mode",
                "truncate",
                "--replica",
                "1",
                "--at",
                "2",
                "--stateful",
            ],
            Some("0"),
        ),
        &["--stateful", "--expect", "5"],
    );
    assert_eq!(code, 0, "{line}");
}

#[test]
fn misbehave_truncate_breaks_the_stream() {
    let (code, line, json) = pipeline(
        &["--count", "5", "--hz", "0"],
        (
            "misbehave",
            &["--mode", "truncate", "--replica", "0", "--at", "2"],
            Some("0"),
        ),
        &["--expect", "5"],
    );
    assert_eq!(code, 1, "{line}");
    // Frames 0 and 1 arrived whole, then the stream was cut.
    assert_eq!(json["frames"], 2);
}

#[test]
fn echo_rejects_an_oversized_header() {
    let mut echo = bin("echo")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    echo.stdin
        .take()
        .unwrap()
        .write_all(&[0xff, 0xff, 0xff, 0x7f, 1, 2])
        .unwrap();
    let out = echo.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(out.stdout.is_empty());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("exceeds the channel maximum"), "{err}");
}

/// A sink whose stdout cannot be written (a full disk) says so in its error and exits 1,
/// after writing its --summary file; before, `println!` panicked.
#[test]
fn a_sink_whose_stdout_is_full_fails_with_an_error_not_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let summary = dir.path().join("summary.json");
    let mut src = bin("source")
        .args(["--count", "3", "--hz", "0"])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let full = std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/full")
        .unwrap();
    let out = bin("sink")
        .arg("--summary")
        .arg(&summary)
        .stdin(src.stdout.take().unwrap())
        .stdout(full)
        .stderr(Stdio::piped())
        .output()
        .unwrap();
    src.wait().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("writing the summary to stdout"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(summary.is_file(), "the summary file is written first");
}
