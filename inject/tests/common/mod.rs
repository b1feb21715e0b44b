//! Running `s3res-inject` from a test: bounded in time, in a fresh folder, and checked to leave
//! no process behind (every process it causes carries the harness's environment mark).

#![allow(dead_code)] // each test file uses a part

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use s3res_testkit::{bin_path, procs};

pub use s3res_testkit::system::MARK_ENV;

/// What one `s3res-inject` invocation did.
pub struct Finished {
    pub success: bool,
    pub code: Option<i32>,
    pub stdout: String,
    pub stderr: String,
}

/// A running `s3res-inject`.
pub struct Spawned {
    pub child: std::process::Child,
    mark: String,
    args: Vec<String>,
    out_path: PathBuf,
    err_path: PathBuf,
    _dir: tempfile::TempDir,
}

/// Starts `s3res-inject ARGS` with the harness's environment mark.
pub fn spawn(args: &[&str]) -> Spawned {
    spawn_with(None, &[], args)
}

/// Starts `s3res-inject ARGS` in `cwd` (default: the test's) with `env` added.
pub fn spawn_with(cwd: Option<&Path>, env: &[(&str, &str)], args: &[&str]) -> Spawned {
    static N: AtomicU64 = AtomicU64::new(0);
    let mark = format!(
        "inject-{}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    );
    let dir = tempfile::tempdir().unwrap();
    let out_path = dir.path().join("stdout");
    let err_path = dir.path().join("stderr");
    let mut cmd = Command::new(bin_path("s3res-inject"));
    if let Some(cwd) = cwd {
        cmd.current_dir(cwd);
    }
    cmd.args(args)
        .envs(env.iter().copied())
        .env(MARK_ENV, &mark)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&out_path).unwrap())
        .stderr(std::fs::File::create(&err_path).unwrap());
    let child = s3res_testkit::spawn_tied_to_this_process(cmd).unwrap();
    Spawned {
        child,
        mark,
        args: args.iter().map(|a| a.to_string()).collect(),
        out_path,
        err_path,
        _dir: dir,
    }
}

impl Spawned {
    /// Waits up to `limit` (then kills it and everything it started, and fails), and fails if
    /// anything it started outlives it.
    pub fn wait(mut self, limit: Duration) -> Finished {
        let deadline = Instant::now() + limit;
        let status = loop {
            if let Some(st) = self.child.try_wait().unwrap() {
                break Some(st);
            }
            if Instant::now() >= deadline {
                let _ = self.child.kill();
                let _ = self.child.wait();
                break None;
            }
            std::thread::sleep(Duration::from_millis(50));
        };
        let left = kill_marked(&self.mark);
        let stdout = std::fs::read_to_string(&self.out_path).unwrap_or_default();
        let stderr = std::fs::read_to_string(&self.err_path).unwrap_or_default();
        let args = &self.args;
        assert!(
            status.is_some(),
            "s3res-inject {args:?} overran {limit:?}; stderr:\n{stderr}"
        );
        assert!(
            left.is_empty(),
            "s3res-inject left processes behind: {left:?}\n{stderr}"
        );
        Finished {
            success: status.is_some_and(|s| s.success()),
            code: status.and_then(|s| s.code()),
            stdout,
            stderr,
        }
    }
}

impl Spawned {
    /// The live processes it caused to exist, itself included (found by the harness's mark).
    pub fn live(&self) -> Vec<procs::ProcStat> {
        procs::with_env(MARK_ENV, &self.mark)
            .into_iter()
            .filter(|p| !p.is_zombie())
            .collect()
    }

    /// Waits up to `limit` until none of its processes is alive; how long that took, or what
    /// was still alive at the end.
    pub fn gone_within(&self, limit: Duration) -> Result<Duration, Vec<String>> {
        let start = Instant::now();
        loop {
            let live = self.live();
            if live.is_empty() {
                return Ok(start.elapsed());
            }
            if start.elapsed() >= limit {
                return Err(live.iter().map(ToString::to_string).collect());
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

/// Runs `s3res-inject ARGS` to the end, bounded by `limit` (see [`Spawned::wait`]).
pub fn inject(args: &[&str], limit: Duration) -> Finished {
    spawn(args).wait(limit)
}

/// Kills every live process carrying `mark`; returns what was found.
fn kill_marked(mark: &str) -> Vec<String> {
    procs::kill_with_env(MARK_ENV, mark)
}

/// The echo pipeline (source → echo → sink) at `redundancy`, `count` frames at 500 Hz; the
/// sink writes its verdict to `task.json` in the run's folder. The round deadline (150 ms) is
/// loose enough that a loaded test machine (no real-time priorities) does not produce hangs
/// nobody injected, and tight enough that a spinning replica is replaced before the next
/// injection comes (the campaigns use fixed 500 ms inter-arrival times).
pub fn echo_system(dir: &Path, redundancy: &str, count: u64) -> PathBuf {
    let timeout = if redundancy == "none" {
        String::new()
    } else {
        r#", "timeout_us": 150000"#.to_owned()
    };
    let text = format!(
        r#"{{
  "name": "echo-{redundancy}",
  "components": {{
    "source": {{ "exec": "s3res-source", "args": ["--count", "{count}", "--hz", "500"] }},
    "echo":   {{ "exec": "s3res-echo", "args": ["--stateful"], "redundancy": "{redundancy}"{timeout} }},
    "sink":   {{ "exec": "s3res-sink", "args": ["--stateful", "--expect", "{count}", "--summary", "task.json"] }}
  }},
  "channels": [
    {{ "from": "source.out", "to": "echo.in" }},
    {{ "from": "echo.out",   "to": "sink.in" }}
  ]
}}"#
    );
    let path = dir.join(format!("echo-{redundancy}.json"));
    std::fs::write(&path, text).unwrap();
    path
}

pub fn read_json(path: &Path) -> serde_json::Value {
    let text =
        std::fs::read_to_string(path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

pub fn read_jsonl(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("reading {}: {e}", path.display()))
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// The schedule of a campaign: what was planned where, independent of timing.
pub fn schedule(out: &Path) -> BTreeSet<String> {
    read_jsonl(&out.join("injections.jsonl"))
        .into_iter()
        .map(|i| {
            format!(
                "run {} #{} at {} {} value {} into {}",
                i["run"], i["index"], i["at_ns"], i["kind"], i["value"], i["component"]
            )
        })
        .collect()
}

/// The run numbers in a campaign's `runs.jsonl`, in the file's order.
pub fn run_numbers(out: &Path) -> Vec<u64> {
    read_jsonl(&out.join("runs.jsonl"))
        .iter()
        .map(|r| r["run"].as_u64().unwrap())
        .collect()
}
