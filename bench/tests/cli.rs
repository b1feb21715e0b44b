//! `s3res-bench` runs each subcommand against the real binaries, prints what it promises, and
//! leaves no process behind, also when interrupted. Speed is never checked: these are tests of
//! the tool, not benchmarks.

use std::process::{Command, Output, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use serde_json::Value;

/// The tests share the check "no process left", so they run one at a time.
static SERIAL: Mutex<()> = Mutex::new(());

const LIMIT: Duration = Duration::from_secs(300);

fn bench() -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_s3res-bench"));
    cmd.arg("--bin-dir")
        .arg(s3res_testkit::bin_dir())
        .arg("--quiet")
        .stdin(Stdio::null());
    cmd
}

/// Runs `cmd` to the end (killed after LIMIT), then checks that nothing it started is left.
fn run(mut cmd: Command) -> Output {
    // Orphans of the bench come to us, so "left behind" is visible as our children.
    replica_rt::sys::set_child_subreaper().unwrap();
    let out_file = tempfile::tempfile().unwrap();
    let err_file = tempfile::tempfile().unwrap();
    cmd.stdout(out_file.try_clone().unwrap())
        .stderr(err_file.try_clone().unwrap());
    let mut child = s3res_testkit::spawn_tied_to_this_process(cmd).expect("starting s3res-bench");
    let started = Instant::now();
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        if started.elapsed() > LIMIT {
            let _ = child.kill();
            let _ = child.wait();
            panic!("s3res-bench did not finish within {LIMIT:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let output = Output {
        status,
        stdout: read_back(out_file),
        stderr: read_back(err_file),
    };
    assert_nothing_left();
    output
}

fn read_back(mut f: std::fs::File) -> Vec<u8> {
    use std::io::{Read, Seek};
    let mut v = Vec::new();
    f.rewind().unwrap();
    f.read_to_end(&mut v).unwrap();
    v
}

fn assert_nothing_left() {
    let me = std::process::id() as i32;
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        while let Ok(Some(_)) = replica_rt::sys::reap_any() {}
        let left = replica_rt::sys::children_of(me);
        if left.is_empty() {
            return;
        }
        if Instant::now() > deadline {
            for &p in &left {
                let _ = replica_rt::sys::kill(p, libc::SIGKILL);
            }
            panic!("processes left behind: {left:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn json_lines(out: &Output) -> Vec<Value> {
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "s3res-bench failed: {}\nstdout:\n{stdout}\nstderr:\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not JSON ({e}): {l}")))
        .collect()
}

fn assert_keys(v: &Value, keys: &[&str]) {
    for k in keys {
        assert!(v.get(k).is_some(), "key {k} missing in {v}");
    }
}

const KEYS: [&str; 7] = [
    "bench",
    "replicas",
    "size",
    "count",
    "median_us",
    "p99_us",
    "max_us",
];

#[test]
fn echo_reports_every_configuration_with_its_ratio_and_plots() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let plots = tempfile::tempdir().unwrap();
    let mut cmd = bench();
    cmd.args(["echo", "--replicas", "0,1,3", "--size", "8,4k"])
        .args(["--count", "200", "--warmup", "20", "--json", "--plot"])
        .arg(plots.path());
    let out = run(cmd);
    let rows = json_lines(&out);
    assert_eq!(rows.len(), 6, "{rows:?}");
    for r in &rows {
        assert_keys(r, &KEYS);
        assert_eq!(r["bench"], "echo");
        assert_eq!(r["count"], 200);
        let base = rows
            .iter()
            .find(|b| b["replicas"] == 0 && b["size"] == r["size"])
            .unwrap();
        let ratio = r["ratio"].as_f64().unwrap();
        let expect = r["median_us"].as_f64().unwrap() / base["median_us"].as_f64().unwrap();
        assert!((ratio - expect).abs() < 1e-6, "ratio {ratio} vs {expect}");
    }
    let sizes: Vec<u64> = rows.iter().map(|r| r["size"].as_u64().unwrap()).collect();
    assert!(sizes.contains(&8) && sizes.contains(&4096), "{sizes:?}");
    let svg = std::fs::read_to_string(plots.path().join("fig3-round-trip.svg")).unwrap();
    assert!(
        svg.contains("<svg") && svg.contains("<text"),
        "no text in the SVG"
    );
    assert!(
        svg.contains("tmr") && svg.contains("none"),
        "legend missing"
    );
}

#[test]
fn echo_table_is_readable() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let mut cmd = bench();
    cmd.args(["echo", "--replicas", "0,2", "--size", "64"])
        .args(["--count", "50", "--warmup", "5"]);
    let out = run(cmd);
    assert!(out.status.success());
    let table = String::from_utf8_lossy(&out.stdout);
    // Under the table, a note for a row the host took CPUs from (on a VM, now and then).
    let lines: Vec<&str> = table
        .lines()
        .filter(|l| !l.starts_with("note: the host took"))
        .collect();
    assert_eq!(lines.len(), 4, "{table}");
    assert!(lines[0].contains("median µs") && lines[0].contains("p99.9 µs"));
    assert!(
        lines[2].contains("none") && lines[3].contains("dmr"),
        "{table}"
    );
}

#[test]
fn restart_reports_the_floor_and_keeps_state() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let plots = tempfile::tempdir().unwrap();
    let mut cmd = bench();
    cmd.args([
        "restart", "--size", "256k,1m", "--count", "3", "--json", "--plot",
    ])
    .arg(plots.path());
    let rows = json_lines(&run(cmd));
    assert_eq!(rows.len(), 2, "{rows:?}");
    for r in &rows {
        assert_keys(r, &KEYS);
        assert_keys(r, &["floor_us", "ratio"]);
        assert_eq!(r["count"], 3);
        // Every restart was by fork (state kept); the bench checks the counter itself.
        assert_eq!(r["extra"]["by_exec"], 0, "{r}");
        assert_eq!(r["extra"]["gap_ms"], 0, "back to back by default: {r}");
    }
    assert!(plots.path().join("fig4-restart.svg").is_file());
}

/// `--gap-ms` spaces the kills (and the floor's forks), and the row says so.
#[test]
fn restart_spaced_by_a_gap_says_so() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let mut cmd = bench();
    cmd.args([
        "restart", "--size", "4k", "--count", "2", "--gap-ms", "30", "--json",
    ]);
    let rows = json_lines(&run(cmd));
    assert_eq!(rows.len(), 1, "{rows:?}");
    assert_eq!(rows[0]["extra"]["gap_ms"], 30, "{}", rows[0]);
    assert_eq!(rows[0]["extra"]["by_exec"], 0, "{}", rows[0]);
}

#[test]
fn detect_measures_crashes_hangs_and_false_positives() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let mut cmd = bench();
    cmd.args(["detect", "--timeout-us", "20000", "--count", "5"])
        .args(["--rounds", "300", "--seed", "42", "--json"]);
    let out = run(cmd);
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    let rows = json_lines(&out);
    assert!(stderr.contains("seed = 42"), "{stderr}");
    let what: Vec<&str> = rows.iter().map(|r| r["what"].as_str().unwrap()).collect();
    assert_eq!(
        what,
        ["crash", "crash-round", "hang", "false-positives"],
        "{rows:?}"
    );
    for r in &rows {
        assert_keys(r, &KEYS);
        assert_eq!(r["timeout_us"], 20000);
    }
    // Every injected crash and hang was seen as what it was.
    assert_eq!(rows[0]["count"], 5, "{rows:?}");
    assert_eq!(rows[2]["count"], 5, "{rows:?}");
}

#[test]
fn memory_reports_resident_sizes() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let mut cmd = bench();
    cmd.args(["memory", "--size", "1m", "--json"]);
    let rows = json_lines(&run(cmd));
    // echo direct, echo voter + replica, ballast direct, ballast voter + replica.
    assert_eq!(rows.len(), 6, "{rows:?}");
    for r in &rows {
        assert_keys(r, &KEYS);
        assert!(r["rss_kib"].as_u64().unwrap() > 0, "{r}");
    }
    let ballast = rows
        .iter()
        .find(|r| r["what"] == "replica" && r["size"] == 1 << 20)
        .unwrap();
    assert!(ballast["rss_kib"].as_u64().unwrap() >= 1024, "{ballast}");
}

#[test]
fn ctrl_c_stops_and_reaps_everything() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    replica_rt::sys::set_child_subreaper().unwrap();
    let mut cmd = bench();
    cmd.args([
        "echo",
        "--replicas",
        "3",
        "--size",
        "8",
        "--count",
        "100000000",
    ])
    .stdout(Stdio::null())
    .stderr(Stdio::piped());
    let mut child = s3res_testkit::spawn_tied_to_this_process(cmd).unwrap();
    // Let it start the voter and its replicas.
    std::thread::sleep(Duration::from_millis(1500));
    let pid = child.id() as i32;
    assert!(
        !replica_rt::sys::children_of(pid).is_empty(),
        "the bench has not started anything yet"
    );
    replica_rt::sys::kill(pid, libc::SIGINT).unwrap();
    let started = Instant::now();
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        if started.elapsed() > Duration::from_secs(20) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("s3res-bench did not stop within 20 s of SIGINT");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(
        !status.success(),
        "an interrupted run must not report success"
    );
    assert_nothing_left();
}

/// `--cpu-idle poll`: rows measured under a voter say so and the no-voter baseline does not;
/// where the voters could not open the PM QoS file (as `nobody` when the tests run as root,
/// else as the user running them), the bench stops at once with a one-line error, starting
/// nothing.
#[test]
fn cpu_idle_poll_labels_voter_rows_and_stops_without_the_right() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let qos = s3res_protocol::plan::CPU_LATENCY_QOS;
    let args = ["echo", "--replicas", "0,3", "--size", "8", "--count", "50"];
    let can_open = std::fs::File::options().write(true).open(qos).is_ok();
    if can_open {
        let mut cmd = bench();
        cmd.args(args)
            .args(["--warmup", "5", "--json", "--cpu-idle", "poll"]);
        let rows = json_lines(&run(cmd));
        assert_eq!(rows.len(), 2, "{rows:?}");
        for r in &rows {
            let expected = (r["replicas"] != 0).then_some("poll");
            assert_eq!(r["cpu_idle"].as_str(), expected, "{r}");
        }
    }
    let refused = if s3res_testkit::is_root() {
        // The test binaries are readable by everyone, as the unprivileged system tests need.
        let mut cmd = s3res_testkit::system::as_nobody(env!("CARGO_BIN_EXE_s3res-bench"));
        cmd.arg("--bin-dir")
            .arg(s3res_testkit::bin_dir())
            .arg("--quiet")
            .stdin(Stdio::null());
        Some(cmd)
    } else {
        (!can_open).then(bench)
    };
    let Some(mut cmd) = refused else {
        eprintln!("{qos} is open to this user: no refusal to check");
        return;
    };
    cmd.args(args).args(["--cpu-idle", "poll"]);
    let out = run(cmd);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(out.stdout.is_empty(), "rows were measured");
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(
        stderr.contains(&format!("--cpu-idle poll: the voters could not open {qos}")),
        "{stderr}"
    );
}
