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

/// Every `(slot, pid)` in `killed` was recorded as a `crash` of `component`.
pub fn assert_kills_were_crashes(
    events: &[crate::Event],
    component: &str,
    killed: &[(usize, i32)],
) {
    for (slot, pid) in killed {
        assert!(
            events.iter().any(|e| e.kind == crate::EventKind::Crash
                && e.component == component
                && e.replica == Some(*slot)
                && e.pid == Some(*pid)),
            "kill of replica {slot} (pid {pid}) was not recorded as a crash"
        );
    }
}

/// The sink's summary says exactly one of `count` frames is missing (a withheld one) and
/// nothing else went wrong: no duplicate, reorder, corruption or state break.
pub fn assert_sink_missed_one(summary: &Path, count: u32) {
    let s = sink_summary(summary);
    assert_eq!(s["missing"], 1, "{s}");
    assert_eq!(s["frames"], count - 1, "{s}");
    for field in ["duplicated", "reordered", "corrupt", "state_breaks"] {
        assert_eq!(s[field], 0, "{field}: {s}");
    }
}

impl RunningSystem {
    /// SIGKILLs a random replica of `component` (one of `replicas`) `kills` times, waiting
    /// after each for its repair by fork with state kept, then `pause_ms` (a random number of
    /// milliseconds in that range) while frames flow. Returns the `(slot, pid)` of each kill.
    pub fn kill_random_replicas(
        &mut self,
        rng: &mut crate::Rng,
        component: &str,
        replicas: usize,
        kills: usize,
        pause_ms: (u64, u64),
    ) -> Vec<(usize, i32)> {
        // Every kill must be repaired by fork with the state kept: the donors must have
        // answered (a donor that has not is reported as a fresh start, state lost).
        self.wait_for_answers(component);
        let mut killed = Vec::new();
        for _ in 0..kills {
            let slot = rng.below(replicas as u64) as usize;
            let pid = self.replica_pids(component)[&slot];
            crate::kill_pid(pid, libc::SIGKILL).expect("kill replica");
            let rec = self.wait_for_recovery(component, slot, pid);
            assert_eq!(rec.method, Some(crate::RecoveryMethod::Fork), "{rec:?}");
            assert_eq!(rec.state_lost, Some(false), "{rec:?}");
            assert_ne!(rec.new_pid, Some(pid));
            killed.push((slot, pid));
            std::thread::sleep(Duration::from_millis(rng.range(pause_ms.0, pause_ms.1)));
        }
        assert!(
            self.try_status().is_none(),
            "the system finished before all {kills} kills were done; make the source longer"
        );
        killed
    }

    /// DMR: flips `bit` of the next frame of replica 0 of `component` and waits for the
    /// `sdc` that cannot be attributed (no `replica`, the frame withheld). Returns the pids of
    /// the replicas at the injection (nobody should be replaced).
    pub fn inject_unattributable_sdc(
        &mut self,
        component: &str,
        bit: i32,
    ) -> std::collections::BTreeMap<usize, i32> {
        let pids = self.replica_pids(component);
        crate::sigqueue(pids[&0], crate::signals::INJECT_SDC, bit).expect("sigqueue");
        let sdc = self.wait_for_event(
            |e| e.kind == crate::EventKind::Sdc && e.component == component,
            Duration::from_secs(20),
        );
        assert_eq!(sdc.replica, None, "DMR must not attribute: {sdc:?}");
        assert!(
            sdc.detail.as_deref().unwrap_or("").contains("withheld"),
            "{sdc:?}"
        );
        pids
    }

    /// Flips bit `bit` in the same frame of each listed replica `(slot, bit)` of `component`:
    /// pauses the system's `s3res-source` until everything it sent is answered
    /// ([`RunningSystem::pause_source`]), arms the flips, and lets the source go on. Returns
    /// the pids at the injection.
    pub fn flip_bits_in_one_frame(
        &mut self,
        component: &str,
        hits: &[(usize, i32)],
    ) -> std::collections::BTreeMap<usize, i32> {
        let pids = self.replica_pids(component);
        let source = self.pause_source(component);
        for &(slot, bit) in hits {
            crate::sigqueue(pids[&slot], crate::signals::INJECT_SDC, bit).expect("sigqueue");
        }
        crate::kill_pid(source, libc::SIGCONT).expect("SIGCONT the source");
        pids
    }

    /// Waits until every replica of `component` has answered at least once: a frame reached
    /// the sink, then, with the source paused ([`RunningSystem::pause_source`]), everything in
    /// flight was handled (replicas are deterministic: each made the frames the others did),
    /// and the source goes on.
    pub fn wait_for_answers(&mut self, component: &str) {
        let mark = self.sink_mark();
        let sink = self.pid_of("s3res-sink");
        crate::wait::wait_until("a frame at the sink", Duration::from_secs(20), || {
            crate::procs::io(sink).filter(|io| io.rchar > mark)
        });
        let source = self.pause_source(component);
        crate::kill_pid(source, libc::SIGCONT).expect("SIGCONT the source");
    }

    /// The pid of this system's one living process named `comm`; panics if there is none or
    /// more than one.
    pub fn pid_of(&self, comm: &str) -> i32 {
        self.process_named(comm)
            .unwrap_or_else(|| panic!("the system has no single living `{comm}` process"))
    }

    /// Stops (SIGSTOP) the system's `s3res-source` and waits until everything it sent has
    /// been handled: `component`'s voter sleeps and each of its replicas sleeps reading its
    /// input pipe, at three looks in a row. (A replica given input is woken at once, and a
    /// voter holding input or an open round has a replica to wait for, so with the source
    /// stopped this state means nothing is in flight.) Returns the source's pid, for SIGCONT.
    pub fn pause_source(&mut self, component: &str) -> i32 {
        let source = self.pid_of("s3res-source");
        crate::kill_pid(source, libc::SIGSTOP).expect("SIGSTOP the source");
        let voter = self.pid_of("s3res-voter");
        let mut quiet_looks = 0;
        crate::wait::wait_until(
            &format!("`{component}` to handle everything the stopped source sent"),
            Duration::from_secs(20),
            || {
                let replicas = self.replica_pids(component);
                let quiet = replica_rt::sys::process_state(voter) == Some('S')
                    && replicas
                        .values()
                        .all(|&pid| crate::procs::waits_on_pipe_read(pid))
                    && replica_rt::sys::process_state(voter) == Some('S');
                quiet_looks = if quiet { quiet_looks + 1 } else { 0 };
                (quiet_looks >= 3).then_some(())
            },
        );
        source
    }

    /// Whole length-prefixed frames bootstrap's stdout holds so far (a channel `"to":
    /// "stdout"` writes them there); a frame still being written is not counted.
    pub fn stdout_frames(&self) -> usize {
        let bytes = std::fs::read(self.path("stdout.txt")).unwrap_or_default();
        let mut at = 0;
        let mut frames = 0;
        while let Some(len) = bytes.get(at..at + 4) {
            let len = u32::from_le_bytes(len.try_into().expect("4 bytes")) as usize;
            if at + 4 + len > bytes.len() {
                break;
            }
            at += 4 + len;
            frames += 1;
        }
        frames
    }

    /// Waits (at most `timeout`) until bootstrap's stdout holds `frames` whole frames.
    pub fn wait_for_stdout_frames(&mut self, frames: usize, timeout: Duration) {
        crate::wait::wait_until(
            &format!("{frames} frames on bootstrap's stdout"),
            timeout,
            || {
                assert!(
                    self.try_status().is_none(),
                    "bootstrap exited with {} frames on its stdout, waiting for {frames}",
                    self.stdout_frames()
                );
                (self.stdout_frames() >= frames).then_some(())
            },
        );
    }

    /// The sink's read count (`rchar`) once it waits for input (its start-up reads are
    /// over): the mark for [`RunningSystem::assert_sink_progressed`].
    pub fn sink_mark(&self) -> u64 {
        let sink = self.pid_of("s3res-sink");
        crate::wait::wait_until(
            "the sink to wait for its input",
            Duration::from_secs(20),
            || {
                if !crate::procs::waits_on_pipe_read(sink) {
                    return None;
                }
                crate::procs::io(sink).map(|io| io.rchar)
            },
        )
    }

    /// Frames reached the sink since `mark` (its read count grew): the system did not stall.
    /// Panics naming `window` (what the test was checking meanwhile) otherwise.
    pub fn assert_sink_progressed(&self, mark: u64, window: &str) {
        let sink = self.pid_of("s3res-sink");
        let now = crate::procs::io(sink).map_or(0, |io| io.rchar);
        assert!(
            now > mark,
            "no frame reached the sink during {window}: the system stalled (sink read {mark} B before, {now} B after)"
        );
    }

    /// Waits for the `sdc` that names `slot` (process `pid`) of `component` as outvoted bit by
    /// bit, and for its repair by fork; returns the recovery event.
    pub fn wait_for_bitwise_repair(
        &mut self,
        component: &str,
        slot: usize,
        pid: i32,
    ) -> crate::Event {
        let limit = Duration::from_secs(20);
        let fault = self.wait_for_event(
            |e| {
                e.kind == crate::EventKind::Sdc
                    && e.component == component
                    && e.replica == Some(slot)
            },
            limit,
        );
        let detail = fault.detail.as_deref().unwrap_or("");
        assert!(detail.contains("bitwise majority"), "{fault:?}");
        assert_eq!(fault.pid, Some(pid), "{fault:?}");
        let rec = self.wait_for_recovery(component, slot, pid);
        assert_eq!(rec.method, Some(crate::RecoveryMethod::Fork), "{rec:?}");
        rec
    }

    /// Waits (20 s at most) for the recovery of `slot` of `component` whose old pid is `pid`.
    pub fn wait_for_recovery(&mut self, component: &str, slot: usize, pid: i32) -> crate::Event {
        self.wait_for_event(
            |e| {
                e.kind == crate::EventKind::Recovery
                    && e.component == component
                    && e.replica == Some(slot)
                    && e.pid == Some(pid)
            },
            Duration::from_secs(20),
        )
    }

    /// Waits until `replicas` replicas of `component` have started and each has installed
    /// replica-rt's signal handlers (an injection signal before replica-rt's `init` would
    /// simply kill a replica). Readiness is read from the kernel (`SigCgt` in
    /// `/proc/PID/status`), not guessed with a sleep.
    pub fn wait_for_replicas(&mut self, component: &str, replicas: usize) {
        let deadline = Instant::now() + Duration::from_secs(20);
        let ready = |pids: &std::collections::BTreeMap<usize, i32>| {
            pids.len() >= replicas && pids.values().all(|&pid| crate::procs::handles_hooks(pid))
        };
        while !ready(&self.replica_pids(component)) {
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

/// Asserts that `joined` fork children joined their voter on their donor's spare line and none
/// connected by itself, from the voter's log in `stderr` (it needs
/// `RUST_LOG=s3res_voter::recovery=debug`; replica-rt's `restart`, "The spare line").
pub fn assert_children_joined_on_spare_lines(stderr: &str, joined: usize) {
    let on_line = stderr
        .matches("the donor's child joined on its spare line")
        .count();
    let connected = stderr.matches("the donor's child connected").count();
    assert_eq!(
        (on_line, connected),
        (joined, 0),
        "every child on its donor's line (joined, connected):\n{}",
        crate::tail(stderr, 40)
    );
}
