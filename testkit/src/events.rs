//! The event log as the harness reads it: JSON lines written by the voters and gathered by
//! bootstrap (`--events FILE`).

use std::collections::BTreeMap;

use s3res_protocol::event::{Event, EventKind};

/// Parses every *complete* line of an event log (a last line without its newline is still
/// being written and is left for the next read). Blank lines are skipped. A complete line that
/// is not an event is an error: the log is a contract.
pub fn parse_events(text: &str) -> Result<Vec<Event>, String> {
    let complete = match text.rfind('\n') {
        Some(i) => &text[..=i],
        None => "",
    };
    complete
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(i, l)| {
            serde_json::from_str(l).map_err(|e| format!("event log line {}: {e}: {l}", i + 1))
        })
        .collect()
}

/// The events of `kind` about `component`.
pub fn of_kind<'a>(events: &'a [Event], component: &str, kind: EventKind) -> Vec<&'a Event> {
    events
        .iter()
        .filter(|e| e.kind == kind && e.component == component)
        .collect()
}

/// Whether `e` is the recovery of `slot` whose faulty replica had `old_pid`.
pub fn is_recovery_of(e: &Event, slot: usize, old_pid: i32) -> bool {
    e.kind == EventKind::Recovery && e.replica == Some(slot) && e.pid == Some(old_pid)
}

/// The current pid of each replica slot of `component`: a `start` event puts its pid in its
/// slot, a `recovery` event puts its `new_pid` there, a `recovery_failed` event empties it.
pub fn replica_pids(events: &[Event], component: &str) -> BTreeMap<usize, i32> {
    let mut slots = BTreeMap::new();
    for e in events.iter().filter(|e| e.component == component) {
        let Some(slot) = e.replica else { continue };
        match e.kind {
            EventKind::Start => {
                if let Some(pid) = e.pid {
                    slots.insert(slot, pid);
                }
            }
            EventKind::Recovery => {
                if let Some(pid) = e.new_pid {
                    slots.insert(slot, pid);
                }
            }
            EventKind::RecoveryFailed => {
                slots.remove(&slot);
            }
            _ => {}
        }
    }
    slots
}

#[cfg(test)]
mod tests {
    use super::*;
    use s3res_protocol::event::RecoveryMethod;

    fn ev(component: &str, kind: EventKind, replica: usize, pid: i32) -> Event {
        let mut e = Event::new("sys", component, kind);
        e.replica = Some(replica);
        e.pid = Some(pid);
        e
    }

    #[test]
    fn parses_complete_lines_only() {
        let a = ev("echo", EventKind::Start, 0, 10).to_line();
        let b = ev("echo", EventKind::Crash, 0, 10).to_line();
        let partial = &b[..b.len() / 2];
        let text = format!("{a}\n{b}{partial}");
        let evs = parse_events(&text).unwrap();
        assert_eq!(evs.len(), 2);
        assert_eq!(evs[0].kind, EventKind::Start);
        assert_eq!(evs[1].kind, EventKind::Crash);
        assert_eq!(parse_events("").unwrap(), vec![]);
        assert_eq!(parse_events(partial).unwrap(), vec![]);
    }

    #[test]
    fn parses_the_documented_wire_format() {
        let line = r#"{"ts_ns":5,"system":"s","component":"echo","kind":"recovery","replica":1,"pid":20,"new_pid":21,"donor":0,"method":"fork","state_lost":false,"recovery_us":350}"#;
        let evs = parse_events(&format!("{line}\n")).unwrap();
        assert_eq!(evs[0].kind, EventKind::Recovery);
        assert_eq!(evs[0].method, Some(RecoveryMethod::Fork));
        assert_eq!(evs[0].new_pid, Some(21));
        let line = r#"{"ts_ns":6,"system":"s","component":"echo","kind":"recovery_failed"}"#;
        assert_eq!(
            parse_events(&format!("{line}\n")).unwrap()[0].kind,
            EventKind::RecoveryFailed
        );
    }

    #[test]
    fn rejects_a_bad_complete_line() {
        let err = parse_events("{\"not\":\"an event\"}\n").unwrap_err();
        assert!(err.contains("line 1"), "{err}");
    }

    #[test]
    fn replica_pids_follow_starts_and_recoveries() {
        let mut rec = ev("echo", EventKind::Recovery, 1, 11);
        rec.new_pid = Some(21);
        let mut failed = Event::new("sys", "echo", EventKind::RecoveryFailed);
        failed.replica = Some(2);
        let evs = vec![
            ev("echo", EventKind::Start, 0, 10),
            ev("echo", EventKind::Start, 1, 11),
            ev("echo", EventKind::Start, 2, 12),
            ev("other", EventKind::Start, 0, 99),
            ev("echo", EventKind::Sdc, 1, 11),
            rec,
            ev("echo", EventKind::Hang, 2, 12),
            failed,
        ];
        let pids = replica_pids(&evs, "echo");
        assert_eq!(pids, BTreeMap::from([(0, 10), (1, 21)]));
        assert_eq!(replica_pids(&evs, "other"), BTreeMap::from([(0, 99)]));
        assert!(replica_pids(&evs, "nobody").is_empty());
    }
}
