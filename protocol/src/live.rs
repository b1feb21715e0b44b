//! The live view: a machine-readable picture of the running system — every component, its
//! voter's pid, each replica's *current* pid — kept in a JSON file (`--state FILE`) so that fault
//! injectors find their targets without `ps | grep`.
//!
//! The file is rewritten atomically (write `FILE.tmp`, then `rename`) whenever something in it
//! changes: at start, when each unprotected component or voter is spawned, on every replica
//! start, fault, recovery and failed recovery (from the voters' events), and once more at the
//! end with `running: false`. A reader therefore always sees one whole, consistent version.
//!
//! The types, the reader and the atomic write live here, so that injectors read the view without
//! depending on bootstrap; bootstrap's writer (the view shared by its threads) is
//! `s3res_bootstrap::live`.

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::event::{Event, EventKind};

/// What the state file holds.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LiveView {
    /// The system's `name`.
    pub system: String,
    pub bootstrap_pid: i32,
    /// CLOCK_MONOTONIC (ns) of the last change.
    pub updated_ns: u64,
    /// `false` once bootstrap has stopped everything.
    pub running: bool,
    /// By component name.
    pub components: BTreeMap<String, LiveComponent>,
}

/// One component.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LiveComponent {
    /// `none`, `smr`, `dmr`, `tmr` (or what the description said).
    pub redundancy: String,
    /// Runs under a voter.
    pub protected: bool,
    /// The component's own pid (unprotected components only; `null` until spawned).
    #[serde(default)]
    pub pid: Option<i32>,
    /// The voter's pid (protected components only; `null` until spawned).
    #[serde(default)]
    pub voter_pid: Option<i32>,
    /// One entry per slot (protected components only), in slot order.
    #[serde(default)]
    pub replicas: Vec<LiveReplica>,
}

/// One replica slot of a protected component.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LiveReplica {
    pub slot: usize,
    /// The process now in this slot; `null` before its start event or after a failed recovery.
    pub pid: Option<i32>,
    pub state: ReplicaState,
    /// CLOCK_MONOTONIC (ns) of the event that set `pid` and `state`.
    pub since_ns: u64,
}

/// Where a slot stands, as far as the voter's events tell.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ReplicaState {
    /// No start event yet.
    Starting,
    /// Started or recovered: a valid target.
    Running,
    /// Found faulty; being replaced (the pid is the faulty, killed process).
    Faulty,
    /// Replacement failed: the slot is empty.
    Lost,
}

impl LiveView {
    /// Reads a state file. `Err` with a readable reason if it is missing or not a view.
    pub fn read(path: &Path) -> Result<Self, String> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("cannot read the state file {}: {e}", path.display()))?;
        LiveView::parse(&text)
            .map_err(|e| format!("{} is not an s3res state file: {e}", path.display()))
    }

    /// A view from the text of a state file, [checked](Self::check).
    pub fn parse(text: &str) -> Result<Self, String> {
        let view: LiveView = serde_json::from_str(text).map_err(|e| e.to_string())?;
        view.check()?;
        Ok(view)
    }

    /// What readers rely on, and bootstrap always writes: every pid is a process (above 0:
    /// an injector sends signals to them, and `kill` takes 0 as its own process group and -1
    /// as every process it may signal), and replica `i` of a component is slot `i` (events name
    /// slots, and a target is taken by position).
    pub fn check(&self) -> Result<(), String> {
        let bad_pid = |what: String, pid: i32| Err(format!("{what} has pid {pid}"));
        if self.bootstrap_pid <= 0 {
            return bad_pid("bootstrap".to_owned(), self.bootstrap_pid);
        }
        for (name, c) in &self.components {
            for (what, pid) in [("component", c.pid), ("voter of", c.voter_pid)] {
                match pid {
                    Some(pid) if pid <= 0 => return bad_pid(format!("{what} {name}"), pid),
                    _ => {}
                }
            }
            for (i, r) in c.replicas.iter().enumerate() {
                if r.slot != i {
                    return Err(format!("replica {i} of {name} says it is slot {}", r.slot));
                }
                match r.pid {
                    Some(pid) if pid <= 0 => return bad_pid(format!("replica {i} of {name}"), pid),
                    _ => {}
                }
            }
        }
        Ok(())
    }

    /// Writes the view to `path` atomically (`path.tmp`, then `rename`): readers see the old
    /// or the new file, never half of one.
    pub fn write(&self, path: &Path) -> std::io::Result<()> {
        let mut tmp = path.as_os_str().to_owned();
        tmp.push(".tmp");
        let tmp = PathBuf::from(tmp);
        let mut f = std::fs::File::create(&tmp)?;
        let mut text = serde_json::to_vec_pretty(self).map_err(std::io::Error::other)?;
        text.push(b'\n');
        f.write_all(&text)?;
        drop(f);
        std::fs::rename(&tmp, path)
    }

    /// Takes one voter event into account; `true` if the view changed.
    pub fn apply(&mut self, e: &Event) -> bool {
        let Some(c) = self.components.get_mut(&e.component) else {
            return false;
        };
        if e.kind == EventKind::VoterRestart {
            // About the voter, not a replica: its successor's pid.
            return match e.pid.filter(|&pid| pid > 0 && c.protected) {
                Some(pid) => {
                    c.voter_pid = Some(pid);
                    true
                }
                None => false,
            };
        }
        let Some(r) = e.replica.and_then(|slot| c.replicas.get_mut(slot)) else {
            return false;
        };
        // A pid that is no process (a corrupted event line) would make the view unreadable.
        if [e.pid, e.new_pid].into_iter().flatten().any(|pid| pid <= 0) {
            return false;
        }
        let (pid, state) = match e.kind {
            EventKind::Start => (e.pid, ReplicaState::Running),
            EventKind::Recovery => (e.new_pid, ReplicaState::Running),
            EventKind::RecoveryFailed => (None, ReplicaState::Lost),
            // An alarm alone changes no replica's state (a fault it leads to is its own event).
            EventKind::Anomaly => return false,
            EventKind::VoterRestart | EventKind::Lost | EventKind::Diverged => return false,
            EventKind::Sdc | EventKind::Crash | EventKind::Hang | EventKind::Protocol => {
                // An event about an older process of this slot changes nothing.
                if e.pid.is_some() && e.pid != r.pid {
                    return false;
                }
                (r.pid, ReplicaState::Faulty)
            }
        };
        r.pid = pid;
        r.state = state;
        r.since_ns = e.ts_ns;
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view() -> LiveView {
        let mut components = BTreeMap::new();
        components.insert(
            "echo".to_owned(),
            LiveComponent {
                redundancy: "dmr".to_owned(),
                protected: true,
                pid: None,
                voter_pid: Some(10),
                replicas: (0..2)
                    .map(|slot| LiveReplica {
                        slot,
                        pid: None,
                        state: ReplicaState::Starting,
                        since_ns: 0,
                    })
                    .collect(),
            },
        );
        LiveView {
            system: "s".to_owned(),
            bootstrap_pid: 1,
            updated_ns: 0,
            running: true,
            components,
        }
    }

    fn event(kind: EventKind, slot: usize, pid: i32) -> Event {
        let mut e = Event::new("s", "echo", kind);
        e.replica = Some(slot);
        e.pid = Some(pid);
        e
    }

    #[test]
    fn follows_starts_faults_and_recoveries() {
        let mut v = view();
        assert!(v.apply(&event(EventKind::Start, 0, 100)));
        assert!(v.apply(&event(EventKind::Start, 1, 101)));
        assert!(v.apply(&event(EventKind::Crash, 1, 101)));
        let r = &v.components["echo"].replicas[1];
        assert_eq!((r.pid, r.state), (Some(101), ReplicaState::Faulty));
        let mut rec = event(EventKind::Recovery, 1, 101);
        rec.new_pid = Some(102);
        assert!(v.apply(&rec));
        let r = &v.components["echo"].replicas[1];
        assert_eq!((r.pid, r.state), (Some(102), ReplicaState::Running));
        // A late event about the old pid does not mark the new one faulty.
        assert!(!v.apply(&event(EventKind::Hang, 1, 101)));
        assert!(v.apply(&event(EventKind::RecoveryFailed, 0, 100)));
        assert_eq!(v.components["echo"].replicas[0].state, ReplicaState::Lost);
        // A voter restart names the successor; the replicas stay as they were.
        let mut restart = Event::new("s", "echo", EventKind::VoterRestart);
        restart.pid = Some(200);
        assert!(v.apply(&restart));
        assert_eq!(v.components["echo"].voter_pid, Some(200));
        assert_eq!(v.components["echo"].replicas[1].pid, Some(102));
        restart.pid = Some(0);
        assert!(!v.apply(&restart));
        // Unknown component or slot: ignored.
        let mut other = event(EventKind::Start, 5, 1);
        assert!(!v.apply(&other));
        other.component = "nope".to_owned();
        assert!(!v.apply(&other));
    }

    #[test]
    fn the_file_is_always_whole_and_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("state.json");
        let mut v = view();
        v.write(&path).unwrap();
        assert!(v.apply(&event(EventKind::Start, 0, 7)));
        v.write(&path).unwrap();
        let back = LiveView::read(&path).unwrap();
        assert_eq!(back.components["echo"].replicas[0].pid, Some(7));
        assert_eq!(back, v);
        assert!(!dir.path().join("state.json.tmp").exists());
        std::fs::write(&path, "{").unwrap();
        assert!(LiveView::read(&path)
            .unwrap_err()
            .contains("not an s3res state file"));
    }

    /// Found by fuzzing (`fuzz/`, target `events_live`): a state file whose pids are not
    /// processes, or whose replica entries are not slots 0, 1, … in order, was read as it was.
    /// An injector then signalled pid 0 or -1 (its own process group, or every process), or
    /// named one slot in its record while signalling another's process.
    #[test]
    fn a_view_with_pids_that_are_no_process_or_slots_out_of_place_is_refused() {
        let good = serde_json::to_string(&view()).unwrap();
        assert!(LiveView::parse(&good).is_ok());
        let mut v = view();
        v.components.get_mut("echo").unwrap().replicas[0].pid = Some(-1);
        let e = LiveView::parse(&serde_json::to_string(&v).unwrap()).unwrap_err();
        assert!(e.contains("replica 0 of echo has pid -1"), "{e}");
        let mut v = view();
        v.components.get_mut("echo").unwrap().voter_pid = Some(0);
        assert!(LiveView::parse(&serde_json::to_string(&v).unwrap()).is_err());
        let mut v = view();
        v.bootstrap_pid = 0;
        assert!(LiveView::parse(&serde_json::to_string(&v).unwrap()).is_err());
        let mut v = view();
        v.components.get_mut("echo").unwrap().replicas[1].slot = 5;
        let e = LiveView::parse(&serde_json::to_string(&v).unwrap()).unwrap_err();
        assert!(e.contains("replica 1 of echo says it is slot 5"), "{e}");
        // An event naming such a pid does not bring one into the view.
        let mut v = view();
        assert!(!v.apply(&event(EventKind::Start, 0, -1)));
        let mut rec = event(EventKind::Recovery, 0, 100);
        rec.new_pid = Some(0);
        assert!(!v.apply(&rec));
        assert!(v.check().is_ok());
    }
}
