//! Runs the real `s3res-bootstrap` binary. Every test is bounded in time, and every process it
//! starts is in a process group of its own that is killed on drop, even when the test fails.

use std::io::{Read, Write};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

const BOOTSTRAP: &str = env!("CARGO_BIN_EXE_s3res-bootstrap");
const LIMIT: Duration = Duration::from_secs(20);

fn fixture(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
        .display()
        .to_string()
}

/// A description in a fresh folder.
fn write_system(text: &str) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("system.json");
    std::fs::write(&path, text).unwrap();
    (dir, path)
}

/// bootstrap running as the leader of its own process group.
struct Bootstrap {
    child: Child,
    pgid: i32,
    stdout: Option<JoinHandle<Vec<u8>>>,
    stderr: Option<JoinHandle<Vec<u8>>>,
}

struct Finished {
    status: ExitStatus,
    /// Text view of stdout (for plans and help).
    stdout: String,
    /// Exact bytes of stdout (for frames).
    stdout_bytes: Vec<u8>,
    stderr: String,
}

fn collect(mut r: impl Read + Send + 'static) -> JoinHandle<Vec<u8>> {
    std::thread::spawn(move || {
        let mut buf = Vec::new();
        let _ = r.read_to_end(&mut buf);
        buf
    })
}

impl Bootstrap {
    fn start(args: &[&str], stdin: Stdio, env: &[(&str, &str)]) -> Self {
        let mut cmd = Command::new(BOOTSTRAP);
        cmd.args(args)
            .stdin(stdin)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .env("RUST_LOG", "debug")
            .process_group(0);
        for (k, v) in env {
            cmd.env(k, v);
        }
        let mut child = cmd.spawn().unwrap();
        let pgid = child.id() as i32;
        let stdout = child.stdout.take().map(collect);
        let stderr = child.stderr.take().map(collect);
        Bootstrap {
            child,
            pgid,
            stdout,
            stderr,
        }
    }

    fn wait(mut self) -> Finished {
        let deadline = Instant::now() + LIMIT;
        let status = loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                break s;
            }
            assert!(
                Instant::now() < deadline,
                "s3res-bootstrap did not finish in {LIMIT:?}"
            );
            std::thread::sleep(Duration::from_millis(10));
        };
        let stdout = self.stdout.take().unwrap().join().unwrap();
        let stderr = self.stderr.take().unwrap().join().unwrap();
        Finished {
            status,
            stdout: String::from_utf8_lossy(&stdout).into_owned(),
            stdout_bytes: stdout,
            stderr: String::from_utf8_lossy(&stderr).into_owned(),
        }
    }
}

impl Drop for Bootstrap {
    fn drop(&mut self) {
        let _ = replica_rt::sys::kill(-self.pgid, libc::SIGKILL);
        let _ = self.child.wait();
    }
}

fn run(args: &[&str]) -> Finished {
    Bootstrap::start(args, Stdio::null(), &[]).wait()
}

/// Processes (other than zombies being reaped) in process group `pgid`.
fn group_members(pgid: i32) -> Vec<i32> {
    std::fs::read_dir("/proc")
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<i32>().ok())
        .filter(|&pid| replica_rt::sys::process_group(pid) == Some(pgid))
        .collect()
}

fn wait_until(what: &str, mut cond: impl FnMut() -> bool) {
    let deadline = Instant::now() + LIMIT;
    while !cond() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn help_teaches_the_format_and_exit_statuses() {
    let out = run(&["--help"]);
    assert!(out.status.success());
    for needle in [
        "\"components\"",
        "redundancy",
        "docs/system-description.md",
        "Exit status",
        "143",
        "stdin",
    ] {
        assert!(
            out.stdout.contains(needle),
            "--help lacks {needle:?}:\n{}",
            out.stdout
        );
    }
}

#[test]
fn check_prints_the_plan_and_starts_nothing() {
    let marker_dir = tempfile::tempdir().unwrap();
    let marker = marker_dir.path().join("started");
    let (_dir, path) = write_system(&format!(
        r#"{{
  "name": "checked",
  "components": {{
    "first": {{ "exec": "{marker_sh}", "args": ["{marker}"], "priority": 10 }},
    "voted": {{ "exec": "{cat}", "redundancy": "tmr", "timeout_us": 5000, "cpus": [0] }}
  }},
  "channels": [
    {{ "from": "stdin", "to": "voted.in" }},
    {{ "from": "voted.out", "to": "stdout" }}
  ]
}}"#,
        marker_sh = fixture("marker.sh"),
        marker = marker.display(),
        cat = fixture("cat-through.sh"),
    ));
    let out = Bootstrap::start(
        &["--check", path.to_str().unwrap()],
        Stdio::null(),
        &[("S3RES_VOTER", &fixture("fake-voter.sh"))],
    )
    .wait();
    assert!(out.status.success(), "{}", out.stderr);
    for needle in [
        "system checked: 2 component(s), 2 channel(s)",
        "component first: runs directly (unprotected)",
        "component voted: runs under s3res-voter with 3 replica(s) (tmr)",
        "in  in       <- stdin (channel 0, max frame 65536 B)",
        "out out      -> stdout (channel 1",
        "timeout   5000 us per round",
        "priority  10",
        "cpus      0",
        "fake-voter.sh",
    ] {
        assert!(
            out.stdout.contains(needle),
            "plan lacks {needle:?}:\n{}",
            out.stdout
        );
    }
    assert!(!marker.exists(), "--check started a component");
}

#[test]
fn invalid_descriptions_exit_2_with_the_line_and_start_nothing() {
    let marker_dir = tempfile::tempdir().unwrap();
    let marker = marker_dir.path().join("started");
    let component = format!(
        r#""m": {{ "exec": "{}", "args": ["{}"] }}"#,
        fixture("marker.sh"),
        marker.display()
    );
    let cases = [
        (
            format!("{{\n  \"name\": \"x\",\n  \"components\": {{ {component} }},\n  \"channels\": [\n    {{ \"from\": \"m.out\" \"to\": \"stdout\" }}\n  ]\n}}"),
            ":5: malformed JSON",
            "(JSON syntax)",
        ),
        (
            format!("{{\n  \"name\": \"x\",\n  \"components\": {{ {component} }},\n  \"channels\": [\n    {{ \"from\": \"m.out\",\n      \"to\": \"sink.in\" }}\n  ]\n}}"),
            ":6: unknown component `sink` in endpoint `sink.in`",
            "(channels[0].to)",
        ),
        (
            format!("{{\n  \"name\": \"x\",\n  \"components\": {{\n    {component},\n    \"v\": {{ \"exec\": \"{}\", \"redundancy\": \"tmr\" }}\n  }}\n}}", fixture("cat-through.sh")),
            ":5: `timeout_us` is required",
            "(components.v)",
        ),
    ];
    for (text, needle, subject) in cases {
        let (_dir, path) = write_system(&text);
        let out = run(&[path.to_str().unwrap()]);
        assert_eq!(out.status.code(), Some(2), "{}", out.stderr);
        let line = out
            .stderr
            .lines()
            .find(|l| l.starts_with("error: "))
            .unwrap_or_else(|| panic!("no error line in {:?}", out.stderr));
        assert!(
            line.starts_with(&format!("error: {}:", path.display())),
            "{line}"
        );
        assert!(line.contains(needle), "{needle:?} not in {line}");
        assert!(
            line.ends_with(subject),
            "{subject:?} not at the end of {line}"
        );
        assert!(out.stdout.is_empty());
        assert!(
            !marker.exists(),
            "a component was started for an invalid description"
        );
    }
}

#[test]
fn frames_pass_from_stdin_to_stdout() {
    let (_dir, path) = write_system(&format!(
        r#"{{
  "name": "through",
  "components": {{ "a": {{ "exec": "{}" }} }},
  "channels": [
    {{ "from": "stdin", "to": "a.in" }},
    {{ "from": "a.out", "to": "stdout" }}
  ]
}}"#,
        fixture("cat-through.sh")
    ));
    let mut b = Bootstrap::start(&[path.to_str().unwrap()], Stdio::piped(), &[]);
    let payload: Vec<u8> = (0..100_000u32).map(|i| (i % 251) as u8).collect();
    let mut stdin = b.child.stdin.take().unwrap();
    let feeder = {
        let payload = payload.clone();
        std::thread::spawn(move || {
            stdin.write_all(&payload).unwrap();
            // stdin drops here: end of stream reaches the component, which then finishes.
        })
    };
    let pgid = b.pgid;
    let out = b.wait();
    feeder.join().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", out.stderr);
    assert!(
        out.stdout_bytes == payload,
        "stdout differs from stdin: {} bytes out, {} in",
        out.stdout_bytes.len(),
        payload.len()
    );
    assert!(group_members(pgid).is_empty());
}

#[test]
fn sigterm_stops_everything_with_143() {
    let (_dir, path) = write_system(&format!(
        r#"{{
  "name": "sleepy",
  "components": {{
    "a": {{ "exec": "{s}" }},
    "b": {{ "exec": "{s}" }}
  }}
}}"#,
        s = fixture("sleeper.sh")
    ));
    let b = Bootstrap::start(
        &["--stop-timeout-ms", "3000", path.to_str().unwrap()],
        Stdio::null(),
        &[],
    );
    let pid = b.pgid;
    // Both components (now `sleep`) are running.
    wait_until("both components to start", || {
        replica_rt::sys::children_of(pid)
            .iter()
            .filter(|&&c| {
                std::fs::read_to_string(format!("/proc/{c}/comm"))
                    .is_ok_and(|s| s.trim() == "sleep")
            })
            .count()
            == 2
    });
    replica_rt::sys::kill(pid, libc::SIGTERM).unwrap();
    let out = b.wait();
    assert_eq!(out.status.code(), Some(143), "{}", out.stderr);
    assert!(out.stderr.contains("stopping"), "{}", out.stderr);
    assert!(
        !out.stderr.contains("failed:"),
        "a stopped component is not a failure: {}",
        out.stderr
    );
    assert_eq!(
        group_members(pid),
        Vec::<i32>::new(),
        "processes survived bootstrap"
    );
}

#[test]
fn failing_component_exits_1_with_one_line_per_failure() {
    let (_dir, path) = write_system(&format!(
        r#"{{ "name": "f", "components": {{ "bad": {{ "exec": "{}" }}, "good": {{ "exec": "{}" }} }} }}"#,
        fixture("fail.sh"),
        fixture("leave-orphan.sh")
    ));
    let b = Bootstrap::start(&[path.to_str().unwrap()], Stdio::null(), &[]);
    let pgid = b.pgid;
    let start = Instant::now();
    let out = b.wait();
    assert_eq!(out.status.code(), Some(1), "{}", out.stderr);
    assert!(
        out.stderr
            .contains("s3res-bootstrap: component bad failed: exit status 3"),
        "{}",
        out.stderr
    );
    assert!(!out.stderr.contains("component good failed"));
    // The orphaned `sleep 100` of `good` was swept, not waited for.
    assert!(start.elapsed() < Duration::from_secs(10));
    assert_eq!(group_members(pgid), Vec::<i32>::new());
}

#[test]
fn protected_component_runs_under_the_voter_and_events_are_saved() {
    let (dir, path) = write_system(&format!(
        r#"{{
  "name": "voted",
  "components": {{ "a": {{ "exec": "{}", "redundancy": "tmr", "timeout_us": 1000 }} }},
  "channels": [
    {{ "from": "stdin", "to": "a.in" }},
    {{ "from": "a.out", "to": "stdout" }}
  ]
}}"#,
        fixture("cat-through.sh")
    ));
    let events = dir.path().join("events.jsonl");
    let mut b = Bootstrap::start(
        &["--events", events.to_str().unwrap(), path.to_str().unwrap()],
        Stdio::piped(),
        &[("S3RES_VOTER", &fixture("fake-voter.sh"))],
    );
    let mut stdin = b.child.stdin.take().unwrap();
    stdin.write_all(b"\x03\0\0\0abc").unwrap();
    drop(stdin);
    let out = b.wait();
    assert_eq!(out.status.code(), Some(0), "{}", out.stderr);
    assert_eq!(out.stdout_bytes, b"\x03\0\0\0abc");
    let saved = std::fs::read_to_string(&events).unwrap();
    let lines: Vec<&str> = saved.lines().collect();
    assert_eq!(lines.len(), 2, "{saved}");
    assert!(lines[0].contains("\"kind\":\"start\""));
    assert!(lines[0].contains("\"component\":\"a\""));
    assert!(
        out.stderr.contains("unreadable event line"),
        "{}",
        out.stderr
    );
    assert!(
        out.stderr.contains("  faults       0")
            && out.stderr.contains("event line(s) could not be read"),
        "{}",
        out.stderr
    );
}

#[test]
fn missing_voter_is_an_error_before_anything_starts() {
    let marker_dir = tempfile::tempdir().unwrap();
    let marker = marker_dir.path().join("started");
    let (_dir, path) = write_system(&format!(
        r#"{{ "name": "v", "components": {{
  "m": {{ "exec": "{}", "args": ["{}"] }},
  "a": {{ "exec": "{}", "redundancy": "smr", "timeout_us": 1000 }} }},
  "channels": [ {{ "from": "stdin", "to": "a.in" }} ] }}"#,
        fixture("marker.sh"),
        marker.display(),
        fixture("cat-through.sh")
    ));
    let out = Bootstrap::start(
        &[path.to_str().unwrap()],
        Stdio::null(),
        &[("S3RES_VOTER", "/nonexistent/s3res-voter")],
    )
    .wait();
    assert_eq!(out.status.code(), Some(1), "{}", out.stderr);
    assert!(out.stderr.contains("voter"), "{}", out.stderr);
    assert!(!marker.exists());
}

/// The same description started twice in one folder: the second bootstrap refuses before it
/// starts anything, naming the file the first one writes, and leaves that file alone. Before,
/// it emptied the first's events file under it (whose later lines then sat behind NUL bytes,
/// mixed with its own) and took over its live view, so that an injector reading it aimed at
/// the wrong system; both runs ended with status 0.
#[test]
fn a_second_bootstrap_on_the_same_files_refuses_and_leaves_them_alone() {
    let (dir, path) = write_system(&format!(
        r#"{{ "name": "sleepy", "components": {{ "a": {{ "exec": "{}" }} }} }}"#,
        fixture("sleeper.sh")
    ));
    let out = dir.path().join("out");
    let (events, state, other_events, other_state) = (
        out.join("events.jsonl"),
        out.join("state.json"),
        out.join("other.jsonl"),
        out.join("other-state.json"),
    );
    let arg = |p: &Path| p.to_str().unwrap().to_owned();
    let system = arg(&path);
    let first = Bootstrap::start(
        &["--events", &arg(&events), "--state", &arg(&state), &system],
        Stdio::null(),
        &[],
    );
    let live_pid = || {
        let text = std::fs::read_to_string(&state).unwrap_or_default();
        serde_json::from_str::<serde_json::Value>(&text).ok()?["bootstrap_pid"].as_i64()
    };
    let mine = Some(i64::from(first.pgid));
    wait_until("the first bootstrap's live view", || live_pid() == mine);
    std::fs::write(&events, "a line of the first run\n").unwrap();
    std::fs::write(&other_events, "a line of an earlier run\n").unwrap();

    let second = run(&[
        "--events",
        &arg(&events),
        "--state",
        &arg(&other_state),
        &system,
    ]);
    assert_eq!(second.status.code(), Some(1), "{}", second.stderr);
    assert!(
        second.stderr.contains(&format!(
            "the events file {} is being written by another process that holds its lock",
            events.display()
        )),
        "{}",
        second.stderr
    );
    let third = run(&[
        "--events",
        &arg(&other_events),
        "--state",
        &arg(&state),
        &system,
    ]);
    assert_eq!(third.status.code(), Some(1), "{}", third.stderr);
    assert!(
        third.stderr.contains(&format!(
            "the state file {} is being written by another s3res-bootstrap that runs (pid {});",
            state.display(),
            first.pgid
        )),
        "{}",
        third.stderr
    );
    assert_eq!(
        std::fs::read_to_string(&events).unwrap(),
        "a line of the first run\n"
    );
    // A refused run empties nothing of its own either.
    assert_eq!(
        std::fs::read_to_string(&other_events).unwrap(),
        "a line of an earlier run\n"
    );
    assert_eq!(live_pid(), mine, "the live view is no longer the first's");

    replica_rt::sys::kill(first.pgid, libc::SIGTERM).unwrap();
    let end = first.wait();
    assert_eq!(end.status.code(), Some(143), "{}", end.stderr);
}

/// A system of one unprotected component that sleeps.
fn sleepy_system() -> String {
    format!(
        r#"{{ "name": "sleepy", "components": {{ "a": {{ "exec": "{}" }} }} }}"#,
        fixture("sleeper.sh")
    )
}

/// `--events` naming the description would empty the file the system was read from.
#[test]
fn an_events_file_that_is_the_description_is_refused() {
    let text = sleepy_system();
    let (_dir, path) = write_system(&text);
    let system = path.to_str().unwrap();
    let out = run(&["--events", system, system]);
    assert_eq!(out.status.code(), Some(2), "{}", out.stderr);
    assert!(
        out.stderr.contains("error: the events file ")
            && out.stderr.contains("is the description itself"),
        "{}",
        out.stderr
    );
    assert_eq!(std::fs::read_to_string(&path).unwrap(), text);
}

/// `--events` or `--state` that cannot be a file is refused in one line before anything
/// starts: before, a folder on the way that was a file failed the run with `File exists`, and
/// a folder as the state file with `Device or resource busy`.
#[test]
fn run_files_that_cannot_be_made_are_refused_in_one_line() {
    let (dir, path) = write_system(&sleepy_system());
    let system = path.to_str().unwrap();
    let under_a_file = format!("{system}/events.jsonl");
    let folder = dir.path().to_str().unwrap();
    for (flag, file, want) in [
        ("--events", under_a_file.as_str(), "is a file, not a folder"),
        ("--state", folder, "is a folder: give the path of a file"),
    ] {
        let out = run(&[flag, file, system]);
        assert_eq!(out.status.code(), Some(2), "{flag}: {}", out.stderr);
        let lines: Vec<&str> = out.stderr.lines().collect();
        assert!(
            lines.len() == 1 && lines[0].starts_with("error: the ") && lines[0].contains(want),
            "{flag}: {}",
            out.stderr
        );
    }
}
