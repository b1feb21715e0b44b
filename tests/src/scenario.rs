//! The scenario most end-to-end tests share: `source → echo (protected) → sink`, and the
//! checks that go with it.

use std::path::Path;
use std::time::{Duration, Instant};

use crate::{sink_summary, Outcome, RunningSystem};

/// A description of `source → echo → sink`. `echo` is the echo component's JSON object (exec,
/// args, redundancy, ...); the source sends `count` frames at `hz`, and the stateful sink
/// expects all of them and writes its summary to `summary`.
pub fn echo_pipeline(summary: &Path, echo: &str, count: u32, hz: u32) -> String {
    format!(
        r#"{{
  "name": "echo-pipeline",
  "components": {{
    "source": {{ "exec": "s3res-source", "args": ["--count", "{count}", "--hz", "{hz}"] }},
    "echo": {echo},
    "sink": {{ "exec": "s3res-sink", "args": ["--stateful", "--expect", "{count}", "--summary", "{}"] }}
  }},
  "channels": [
    {{ "from": "source.out", "to": "echo.in" }},
    {{ "from": "echo.out", "to": "sink.in" }}
  ]
}}"#,
        summary.display()
    )
}

/// The sink's summary says every one of `count` frames came once, in order, intact, with the
/// echo's state continuous.
pub fn assert_sink_whole(summary: &Path, count: u32) {
    let summary = sink_summary(summary);
    assert_eq!(summary["frames"], count, "sink summary: {summary}");
    for field in [
        "missing",
        "duplicated",
        "reordered",
        "corrupt",
        "state_breaks",
    ] {
        assert_eq!(summary[field], 0, "{field} in sink summary: {summary}");
    }
    assert_eq!(summary["ok"], true, "sink summary: {summary}");
}

impl RunningSystem {
    /// Waits until `replicas` replicas of `component` have started and each has installed
    /// replica-rt's signal handlers (so a restart or injection signal sent now is handled, not
    /// fatal). Readiness is read from the kernel (`SigCgt` in `/proc/PID/status`), not guessed
    /// with a sleep.
    pub fn wait_for_replicas(&mut self, component: &str, replicas: usize) {
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let pids = self.replica_pids(component);
            if pids.len() >= replicas && pids.values().all(|&pid| crate::procs::handles_hooks(pid))
            {
                return;
            }
            assert!(
                Instant::now() < deadline && self.try_status().is_none(),
                "the replicas of {component} did not start (or never installed their handlers):\n{}",
                crate::tail(&self.stderr(), 30)
            );
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// Waits for the system to finish, and checks it succeeded and left nothing behind.
    pub fn wait_success(&mut self, limit: Duration) -> Outcome {
        let out = self.wait(limit);
        assert!(
            out.status.success(),
            "bootstrap failed: {}",
            crate::tail(&out.stderr, 30)
        );
        self.assert_nothing_left();
        out
    }
}
