//! Every executable of the workspace answers `--help` and `-V` by itself: exit status 0, its own
//! name, and no port error (a component started by hand with `--help` prints its help before it
//! looks for its ports). The list of executables comes from `cargo metadata`, so a new binary is
//! covered without editing this test.

use std::os::unix::process::CommandExt as _;
use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Bound on one `--help` or `-V` (they do no work; this only stops a hang from hanging the test).
const LIMIT: Duration = Duration::from_secs(20);

/// The names of every bin target of the workspace's packages.
fn workspace_binaries() -> Vec<String> {
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR")).join("../Cargo.toml");
    let out = Command::new(env!("CARGO"))
        .args([
            "metadata",
            "--no-deps",
            "--format-version",
            "1",
            "--offline",
        ])
        .arg("--manifest-path")
        .arg(&manifest)
        .stdin(Stdio::null())
        .output()
        .expect("running cargo metadata");
    assert!(out.status.success(), "cargo metadata failed: {out:?}");
    let meta: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let mut bins: Vec<String> = meta["packages"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|p| p["targets"].as_array().unwrap().iter())
        .filter(|t| t["kind"].as_array().unwrap().iter().any(|k| k == "bin"))
        .map(|t| t["name"].as_str().unwrap().to_owned())
        .collect();
    bins.sort();
    bins
}

/// Runs `bin arg` in an empty folder, with no port map, in its own process group; bounded by
/// [`LIMIT`], after which the group is killed and the test fails.
fn run(bin: &Path, arg: &str, cwd: &Path) -> Output {
    let dir = tempfile::tempdir().unwrap();
    let (out_path, err_path) = (dir.path().join("out"), dir.path().join("err"));
    let mut child = Command::new(bin)
        .arg(arg)
        .current_dir(cwd)
        .env_remove("S3RES_PORTS")
        .env_remove("S3RES_VOTER_SOCKET")
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&out_path).unwrap())
        .stderr(std::fs::File::create(&err_path).unwrap())
        .process_group(0)
        .spawn()
        .unwrap_or_else(|e| panic!("starting {}: {e}", bin.display()));
    let pgid = child.id() as i32;
    let deadline = Instant::now() + LIMIT;
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break Some(st);
        }
        if Instant::now() >= deadline {
            break None;
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    // Whatever it started (nothing, normally) goes with it.
    let _ = s3res_testkit::kill_pid(-pgid, libc::SIGKILL);
    let status = status.unwrap_or_else(|| {
        let _ = child.wait();
        panic!("{} {arg} did not end within {LIMIT:?}", bin.display())
    });
    Output {
        status,
        stdout: std::fs::read(&out_path).unwrap(),
        stderr: std::fs::read(&err_path).unwrap(),
    }
}

#[test]
fn every_binary_answers_help_and_version_with_its_own_name() {
    let bins = workspace_binaries();
    assert!(
        bins.len() >= 20 && bins.iter().any(|b| b == "s3res-bootstrap"),
        "cargo metadata listed too few binaries: {bins:?}"
    );
    let cwd = tempfile::tempdir().unwrap();
    let version = env!("CARGO_PKG_VERSION");
    let mut wrong = Vec::new();
    for name in &bins {
        let path = s3res_testkit::bin_path(name);
        let help = run(&path, "--help", cwd.path());
        let (out, err) = (
            String::from_utf8_lossy(&help.stdout),
            String::from_utf8_lossy(&help.stderr),
        );
        if !help.status.success() || !out.contains(name.as_str()) || !err.is_empty() {
            wrong.push(format!(
                "{name} --help: {}, stdout:\n{out}\nstderr:\n{err}",
                help.status
            ));
        }
        let v = run(&path, "-V", cwd.path());
        let out = String::from_utf8_lossy(&v.stdout);
        if !v.status.success() || out.trim() != format!("{name} {version}") {
            wrong.push(format!(
                "{name} -V: {}, stdout {out:?}, stderr {:?}",
                v.status,
                String::from_utf8_lossy(&v.stderr)
            ));
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n\n"));
}
