//! Test harness: boots the real `s3res-bootstrap` on a real system description in a fresh temp
//! dir, watches its event log, and tears the whole system down on drop (also when the test
//! panics). A test that leaves a process behind fails.
//!
//! How a leftover is found: bootstrap leads its own process group, and carries an environment
//! mark (`S3RES_TEST_SYSTEM`) that every descendant inherits, so a process that left the group
//! is found too. The test process is a child subreaper, so orphans are reaped here rather than
//! lingering as zombies under an init that may not reap. A test process that is killed runs no
//! drop guard; its bootstraps die with it all the same ([`spawn_tied_to_this_process`]), and a
//! dead bootstrap takes its system with it.
//!
//! Binaries: [`bin_path`] builds the workspace's executables once per test process (see
//! [`bins`]). Random choices: [`Rng::from_env`] prints its seed; `S3RES_TEST_SEED` replays it.
//!
//! ```no_run
//! use std::time::Duration;
//! use s3res_testkit::System;
//!
//! let sys = System::new();
//! let summary = sys.path("summary.json"); // a file in the system's temp dir
//! let mut run = sys.start(r#"{ "name": "t", "components": {}, "channels": [] }"#);
//! let first = run.wait_for_event(|e| e.component == "echo", Duration::from_secs(60));
//! let out = run.wait(Duration::from_secs(60));
//! assert!(out.status.success(), "{}", out.stderr);
//! run.assert_nothing_left(); // bootstrap cleaned up by itself
//! # let _ = (summary, first);
//! ```

#![forbid(unsafe_code)]

pub mod bins;
pub mod events;
pub mod procs;
pub mod rng;
pub mod scenario;
mod spawner;
pub mod system;
pub mod trace;
pub mod wait;

pub use bins::{bin_dir, bin_path};
pub use events::{is_recovery_of, of_kind, parse_events, replica_pids};
pub use rng::Rng;
pub use scenario::{
    assert_children_joined_on_spare_lines, assert_kills_were_crashes, assert_sink_missed_one,
    assert_sink_whole, echo_pipeline,
};
pub use spawner::spawn_tied_to_this_process;
pub use system::{is_root, Outcome, RunningSystem, System};
pub use wait::{wait_spinning, wait_state, wait_until};

use std::path::Path;

pub use s3res_protocol::event::{Cause, Event, EventKind, RecoveryMethod};

/// Sends `sig` to `pid` (`kill(2)`).
pub fn kill_pid(pid: i32, sig: i32) -> std::io::Result<()> {
    replica_rt::sys::kill(pid, sig)
}

/// Sends `sig` to `pid` with an integer value (`sigqueue(3)`); for `SIGUSR2` the value is the
/// bit to flip in the next outgoing frame.
pub fn sigqueue(pid: i32, sig: i32, value: i32) -> std::io::Result<()> {
    replica_rt::sys::sigqueue(pid, sig, value)
}

/// The injection signals a replica understands (re-exported from replica-rt's contract).
pub use replica_rt::contract::signals;

/// Reads and parses the JSON summary a sink writes; panics with the path and the text if it is
/// missing or not JSON.
pub fn sink_summary(path: impl AsRef<Path>) -> serde_json::Value {
    let path = path.as_ref();
    let text = std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("reading sink summary {}: {e}", path.display()));
    serde_json::from_str(&text)
        .unwrap_or_else(|e| panic!("sink summary {} is not JSON ({e}): {text}", path.display()))
}

/// The run-time half of the skip mechanism (see `build.rs`): a test that `build.rs` let run
/// here checks that the machine still gives it what it needs, and fails naming `missing` if
/// not (the crate was built elsewhere, say as root, and run as a user).
pub fn require(available: bool, missing: &str) {
    assert!(
        available,
        "{missing}, but this test crate was built where it was not missing: rebuild it \
         (cargo clean -p s3res-testkit) to have this test listed as ignored"
    );
}

/// The last `max_lines` lines of `text` (for failure messages).
pub fn tail(text: &str, max_lines: usize) -> String {
    let lines: Vec<&str> = text.lines().collect();
    let start = lines.len().saturating_sub(max_lines);
    lines[start..].join("\n")
}
