//! Gathering the voters' events: one reader thread on the shared events pipe.
//!
//! Voters write one JSON object per `write` (< PIPE_BUF, so lines never interleave). The reader
//! copies each line to the `--events` file, logs it, and counts faults and recoveries per
//! component for the summary. A line it cannot parse is logged and kept in the file, never fatal.
//!
//! A fault can reach the pipe twice, and is kept once. A voter writes a fault's event and then
//! takes the replica out of its journal's table; a voter SIGKILLed between the two leaves the
//! dead replica named, and its successor reports it again when it finds it dead. No order of
//! the two steps avoids this without losing the report instead (a pipe write and a store to
//! shared memory cannot be made one), so the voters report a fault at least once and this
//! reader keeps it once: a fault naming the same replica slot and pid as that slot's last
//! fault is a repeat (a replica is killed at its first fault; its slot's next fault names its
//! replacement).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufRead, BufReader, Write};
use std::os::fd::OwnedFd;
use std::sync::mpsc;
use std::time::Duration;

use s3res_protocol::event::{Event, EventKind};

use crate::live::LiveState;
use crate::status::{kind_name, Tally};

/// An optional value for a log field: the value, or `-`.
fn shown<T: std::fmt::Display>(v: Option<T>) -> String {
    v.map_or_else(|| "-".to_owned(), |v| v.to_string())
}

/// Counts for one component.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Counts {
    pub starts: u64,
    /// sdc, crash, hang and protocol events.
    pub faults: u64,
    pub recoveries: u64,
    pub failed_recoveries: u64,
    /// Anomaly detector alarms (whatever was done about them).
    pub anomalies: u64,
}

/// Counts per component, and how many lines could not be read.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct EventSummary {
    pub per_component: BTreeMap<String, Counts>,
    pub unparsable: u64,
    /// Faults reported again by a dead voter's successor, kept once (module docs).
    pub repeats: u64,
    /// Why the events file stopped being written (a full disk), and how many events it lacks:
    /// the verdict says so (a run once "ran clean" over a file that held half its faults and
    /// ended in half a line).
    pub unsaved: Option<(String, u64)>,
    /// The pid each (component, replica slot)'s last fault named.
    last_fault: BTreeMap<(String, usize), i32>,
}

/// What one line of the events pipe was.
#[derive(Debug, Clone, PartialEq)]
pub enum Line {
    /// An event, counted and logged.
    Event(Box<Event>),
    /// A fault already reported (module docs): logged, not counted, not saved again.
    Repeat,
    /// A blank or unreadable line (an unreadable one is logged and counted).
    Other,
}

impl EventSummary {
    /// Takes one line into account (and logs it).
    pub fn record_line(&mut self, line: &str) -> Line {
        let line = line.trim_end();
        if line.is_empty() {
            return Line::Other;
        }
        let event: Event = match serde_json::from_str(line) {
            Ok(e) => e,
            Err(e) => {
                self.unparsable += 1;
                tracing::warn!("unreadable event line ({e}): {line}");
                return Line::Other;
            }
        };
        if self.is_repeat(&event) {
            self.repeats += 1;
            tracing::info!(component = %event.component, replica = %shown(event.replica), pid = %shown(event.pid),
                "fault reported again by the successor of the voter that reported it (that voter died before it took the replica out of its journal); kept once");
            return Line::Repeat;
        }
        let counts = self
            .per_component
            .entry(event.component.clone())
            .or_default();
        match event.kind {
            EventKind::Start => {
                counts.starts += 1;
                tracing::debug!(component = %event.component, replica = %shown(event.replica), pid = %shown(event.pid), "replica started");
            }
            EventKind::Sdc | EventKind::Crash | EventKind::Hang | EventKind::Protocol => {
                counts.faults += 1;
                tracing::warn!(
                    component = %event.component,
                    replica = %shown(event.replica),
                    pid = %shown(event.pid),
                    round = %shown(event.round),
                    detail = event.detail.as_deref().unwrap_or(""),
                    "fault: {}",
                    kind_name(event.kind)
                );
            }
            EventKind::Recovery => {
                counts.recoveries += 1;
                tracing::info!(
                    component = %event.component,
                    replica = %shown(event.replica),
                    new_pid = %shown(event.new_pid),
                    method = %shown(event.method.map(|m| match m {
                        s3res_protocol::event::RecoveryMethod::Fork => "fork",
                        s3res_protocol::event::RecoveryMethod::Exec => "exec",
                    })),
                    recovery_us = %shown(event.recovery_us),
                    "recovered"
                );
            }
            EventKind::Anomaly => {
                counts.anomalies += 1;
                tracing::warn!(
                    component = %event.component,
                    replica = %shown(event.replica),
                    round = %shown(event.round),
                    output = event.output.as_deref().unwrap_or(""),
                    field = event.field.as_deref().unwrap_or(""),
                    score = %shown(event.score),
                    threshold = %shown(event.threshold),
                    "anomaly"
                );
            }
            EventKind::VoterRestart => {
                tracing::warn!(
                    component = %event.component,
                    pid = %shown(event.pid),
                    recovery_us = %shown(event.recovery_us),
                    detail = event.detail.as_deref().unwrap_or(""),
                    "voter restarted"
                );
            }
            EventKind::RecoveryFailed => {
                counts.failed_recoveries += 1;
                tracing::error!(
                    component = %event.component,
                    replica = %shown(event.replica),
                    detail = event.detail.as_deref().unwrap_or(""),
                    "recovery failed; the component runs with fewer replicas"
                );
            }
            EventKind::Lost => {
                // The detail names the output and the round (or frame).
                let what = event.detail.as_deref().unwrap_or("no replica answered");
                tracing::warn!(component = %event.component, "frame lost: {what}");
            }
            EventKind::Diverged => {
                // The detail says what differs and why no restart is made.
                tracing::warn!(
                    component = %event.component,
                    replica = %shown(event.replica),
                    pid = %shown(event.pid),
                    "replica diverged: {}",
                    event.detail.as_deref().unwrap_or("its state is lost")
                );
            }
        }
        Line::Event(Box::new(event))
    }

    /// Whether `event` is a fault whose replica's fault was reported already; remembers it if
    /// not.
    fn is_repeat(&mut self, event: &Event) -> bool {
        let (true, Some(slot), Some(pid)) = (event.kind.is_fault(), event.replica, event.pid)
        else {
            return false;
        };
        let last = self.last_fault.insert((event.component.clone(), slot), pid);
        last == Some(pid)
    }

    /// The one-line summary printed at exit, e.g.
    /// `events: echo 2 faults, 2 recoveries, 0 failed recoveries`.
    pub fn line(&self) -> String {
        let mut parts: Vec<String> = self
            .per_component
            .iter()
            .map(|(name, c)| {
                let mut s = format!(
                    "{name} {} fault(s), {} recovery(ies), {} failed recovery(ies)",
                    c.faults, c.recoveries, c.failed_recoveries
                );
                if c.anomalies > 0 {
                    s.push_str(&format!(", {} anomaly alarm(s)", c.anomalies));
                }
                s
            })
            .collect();
        if parts.is_empty() {
            parts.push("none".to_owned());
        }
        let mut s = format!("events: {}", parts.join("; "));
        if self.unparsable > 0 {
            s.push_str(&format!(" ({} unreadable line(s))", self.unparsable));
        }
        if self.repeats > 0 {
            s.push_str(&format!(
                " ({} fault(s) reported again by a voter's successor, kept once)",
                self.repeats
            ));
        }
        s
    }
}

/// The running reader thread.
#[derive(Debug)]
pub struct EventReader {
    done: mpsc::Receiver<EventSummary>,
}

impl EventReader {
    /// Starts reading `pipe` (the read end of the events pipe) until every writer has closed
    /// it; each line is also appended to `log` if given, and applied to the live view if given.
    /// The thread runs on `cpus` (empty: anywhere; see `sched::events_reader_cpus`).
    pub fn spawn(
        pipe: OwnedFd,
        log: Option<File>,
        live: Option<LiveState>,
        tally: Option<Tally>,
        cpus: Vec<usize>,
    ) -> std::io::Result<Self> {
        let (tx, rx) = mpsc::channel();
        std::thread::Builder::new()
            .name("events".to_owned())
            .spawn(move || {
                // This thread only (it starts no process, so no child inherits the mask).
                if !cpus.is_empty() {
                    if let Err(e) = replica_rt::sys::set_cpu_affinity(0, &cpus) {
                        tracing::debug!(error = %e, ?cpus, "could not place the events reader");
                    }
                }
                let summary = read_all(
                    BufReader::new(File::from(pipe)),
                    log,
                    live.as_ref(),
                    tally.as_ref(),
                );
                // The receiver may have given up waiting; nothing more to do then.
                let _ = tx.send(summary);
            })?;
        Ok(EventReader { done: rx })
    }

    /// Waits up to `limit` for the end of the stream. `None` if a writer still holds the pipe
    /// open (the thread is then left behind; the process is about to exit anyway).
    pub fn finish(self, limit: Duration) -> Option<EventSummary> {
        self.done.recv_timeout(limit).ok()
    }
}

/// Reads lines to the end, copying each to `log` and applying each event to `live` and
/// `tally`.
pub fn read_all(
    mut input: impl BufRead,
    mut log: Option<File>,
    live: Option<&LiveState>,
    tally: Option<&Tally>,
) -> EventSummary {
    let mut summary = EventSummary::default();
    let mut buf = Vec::with_capacity(4096);
    // The length of the file's whole lines: a line cut short by a failed write is cut off.
    let mut saved: u64 = 0;
    loop {
        buf.clear();
        match input.read_until(b'\n', &mut buf) {
            Ok(0) => break,
            Ok(_) => {}
            Err(e) => {
                tracing::warn!("reading events failed: {e}");
                break;
            }
        }
        let line = summary.record_line(&String::from_utf8_lossy(&buf));
        if matches!(line, Line::Repeat) {
            continue;
        }
        if let Some(f) = log.as_mut() {
            let mut res = f.write_all(&buf);
            if res.is_ok() && !buf.ends_with(b"\n") {
                res = f.write_all(b"\n");
            }
            match res.and_then(|()| f.flush()) {
                Ok(()) => saved += buf.len() as u64 + u64::from(!buf.ends_with(b"\n")),
                Err(e) => {
                    tracing::warn!(
                        "cannot write the events file ({e}); events are no longer saved"
                    );
                    // Whole lines only: a reader parses it line by line.
                    if let Err(e) = f.set_len(saved) {
                        tracing::warn!("cannot cut the events file's last line off ({e})");
                    }
                    summary.unsaved = Some((e.to_string(), 0));
                    log = None;
                }
            }
        }
        if let (None, Some((_, n))) = (&log, summary.unsaved.as_mut()) {
            *n += 1;
        }
        if let Line::Event(event) = line {
            if let Some(live) = live {
                live.update(|v| v.apply(&event));
            }
            if let Some(t) = tally {
                t.apply(&event);
            }
        }
    }
    summary
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Read, Seek};

    /// An events file that cannot be written (a full disk) stops being written, and the
    /// summary says why and how many events it lacks; the events still count.
    #[test]
    fn an_events_file_that_cannot_be_written_is_said_incomplete() {
        let e = Event::new("sys", "echo", EventKind::Crash);
        let input = format!("{}{}{}", e.to_line(), e.to_line(), e.to_line());
        let full = std::fs::OpenOptions::new()
            .write(true)
            .open("/dev/full")
            .unwrap();
        let summary = read_all(input.as_bytes(), Some(full), None, None);
        let (why, n) = summary.unsaved.expect("said incomplete");
        assert!(why.contains("No space left on device"), "{why}");
        assert_eq!(n, 3);
        assert_eq!(
            summary.per_component["echo"].faults, 3,
            "counted all the same"
        );
    }

    #[test]
    fn counts_copies_and_tolerates_garbage() {
        let mut e1 = Event::new("sys", "echo", EventKind::Crash);
        e1.replica = Some(1);
        let e2 = Event::new("sys", "echo", EventKind::Recovery);
        let e3 = Event::new("sys", "nav", EventKind::Start);
        let input = format!(
            "{}not json\n{}{}{}",
            e1.to_line(),
            e2.to_line(),
            e3.to_line(),
            "{\"half\":"
        );
        let mut log = tempfile::tempfile().unwrap();
        let summary = read_all(input.as_bytes(), Some(log.try_clone().unwrap()), None, None);
        assert_eq!(summary.unparsable, 2);
        let echo = summary.per_component["echo"];
        assert_eq!((echo.faults, echo.recoveries), (1, 1));
        assert_eq!(summary.per_component["nav"].starts, 1);
        let mut saved = String::new();
        log.rewind().unwrap();
        log.read_to_string(&mut saved).unwrap();
        assert_eq!(saved.lines().count(), 5);
        assert!(saved.starts_with(&e1.to_line()));
        assert!(summary.line().contains("echo 1 fault(s), 1 recovery(ies)"));
    }

    fn fault(component: &str, slot: usize, pid: i32, detail: &str) -> Event {
        let mut e = Event::new("sys", component, EventKind::Crash);
        e.replica = Some(slot);
        e.pid = Some(pid);
        e.detail = Some(detail.to_owned());
        e
    }

    /// A dead voter's successor that reports a fault again (the same slot and pid as that
    /// slot's last fault) is kept once: counted once, saved once. Any other fault counts,
    /// also one whose pid an earlier replica of the slot had.
    #[test]
    fn a_fault_reported_again_by_a_successor_is_kept_once() {
        let lines = [
            fault("echo", 0, 100, "the replica process died"),
            fault("echo", 0, 100, "died while its voter was being replaced"),
            // The same pid in another slot or component is another replica.
            fault("echo", 1, 100, "x"),
            fault("nav", 0, 100, "x"),
            // Slot 0's replacement, then a replica that got pid 100 back.
            fault("echo", 0, 101, "x"),
            fault("echo", 0, 100, "x"),
        ];
        let input: String = lines.iter().map(Event::to_line).collect();
        let mut log = tempfile::tempfile().unwrap();
        let summary = read_all(input.as_bytes(), Some(log.try_clone().unwrap()), None, None);
        assert_eq!(summary.repeats, 1);
        assert_eq!(summary.per_component["echo"].faults, 4);
        assert_eq!(summary.per_component["nav"].faults, 1);
        let mut saved = String::new();
        log.rewind().unwrap();
        log.read_to_string(&mut saved).unwrap();
        assert_eq!(saved.lines().count(), 5, "{saved}");
        assert!(
            !saved.contains("died while its voter was being replaced"),
            "{saved}"
        );
        assert!(
            summary.line().contains("1 fault(s) reported again"),
            "{}",
            summary.line()
        );
    }

    #[test]
    fn reader_thread_ends_at_eof() {
        let (r, w) = replica_rt::sys::pipe().unwrap();
        let reader = EventReader::spawn(r, None, None, None, Vec::new()).unwrap();
        let line = Event::new("s", "c", EventKind::Hang).to_line();
        replica_rt::sys::write(std::os::fd::AsFd::as_fd(&w), line.as_bytes()).unwrap();
        drop(w);
        let summary = reader.finish(Duration::from_secs(5)).unwrap();
        assert_eq!(summary.per_component["c"].faults, 1);
    }
}
