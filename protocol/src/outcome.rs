//! Matching a run's injections with the voters' events: what became of each injection, and
//! which fault events nobody caused (false positives). Pure functions of the two logs, so that
//! `merge` and tests compute exactly what a campaign computes. The rule is written out in
//! docs/campaigns.md ("Matching rule").

use serde::{Deserialize, Serialize};

use crate::event::{Event, EventKind};

/// What became of one injection.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// A fault event named the injected replica (same component, slot and pid) within the
    /// window, and a recovery of that slot followed.
    Recovered,
    /// Detected (by an attributed event, or by a "no majority" event of the component), but
    /// no recovery of the slot followed.
    Unrecovered,
    /// No matching fault event, and the run's task failed: an *error* in the paper's sense.
    Undetected,
    /// No matching fault event, and the task succeeded.
    Benign,
    /// Not delivered (the target was being replaced, or had gone), or delivered into a
    /// process an earlier injection had already hit before it was found faulty; not counted
    /// as injected.
    Missed,
}

impl Outcome {
    /// Counts toward "% error" (Table 2): injected and not recovered.
    pub fn is_error(self) -> bool {
        matches!(self, Outcome::Unrecovered | Outcome::Undetected)
    }
}

/// An injection as fired, before matching.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Fired {
    pub ts_ns: u64,
    pub component: String,
    pub slot: Option<usize>,
    pub pid: i32,
}

/// The match found for one injection.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Match {
    /// Kind of the fault event that detected it (`sdc`, `crash`, `hang`, `protocol`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub detected_as: Option<String>,
    /// Fault event ts − injection ts, microseconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub detection_latency_us: Option<u64>,
    /// The voter's own measure: detection → replacement ready, microseconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recovery_us: Option<u64>,
    /// Recovery event ts − injection ts, microseconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recovered_after_us: Option<u64>,
    /// `fork` or `exec`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recovery_method: Option<String>,
    /// This injection went into a process an earlier injection of the run (this index) had
    /// already hit and that was not yet found faulty; it is counted as missed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub already_hit_by: Option<usize>,
}

/// The result of matching one run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RunMatch {
    /// One per fired injection, in the same order.
    pub per_injection: Vec<(Outcome, Match)>,
    /// Attributed fault events no injection explains.
    pub false_positives: u64,
}

fn kind_name(k: EventKind) -> String {
    serde_json::to_value(k)
        .ok()
        .and_then(|v| v.as_str().map(str::to_owned))
        .unwrap_or_default()
}

/// Matches `fired` (in firing order) against `events` of the run. `window_ns`: how long after
/// an injection a fault event may come and still be its consequence. `task_ok`: the run's
/// verdict (decides benign versus undetected).
pub fn match_run(fired: &[Fired], events: &[Event], window_ns: u64, task_ok: bool) -> RunMatch {
    let mut events: Vec<&Event> = events.iter().collect();
    events.sort_by_key(|e| e.ts_ns);
    let mut detection: Vec<Option<&Event>> = vec![None; fired.len()];
    let mut false_positives = 0;

    // Events that name a replica are matched first, unattributed ones after them: when two
    // replicas of a component are hit before one frame (two flips, one per replica, so all
    // three frames differ), the voter reports a "no majority" event and then one event per
    // faulty replica. Taken in time order alone, the "no majority" event would take the
    // injection its replica's own event explains, leaving that injection unrecovered and the
    // replica's event a false positive.
    let (attributed, unattributed): (Vec<&Event>, Vec<&Event>) = events
        .iter()
        .copied()
        .filter(|e| e.kind.is_fault())
        .partition(|e| e.replica.is_some());
    for e in attributed.into_iter().chain(unattributed) {
        let in_window = |f: &Fired| e.ts_ns >= f.ts_ns && e.ts_ns - f.ts_ns <= window_ns;
        let can_explain = |i: usize, f: &Fired| {
            detection[i].is_none()
                && f.component == e.component
                && in_window(f)
                && match e.replica {
                    Some(slot) => f.slot == Some(slot) && !matches!(e.pid, Some(p) if p != f.pid),
                    // "No majority": the component saw a fault it cannot attribute.
                    None => true,
                }
        };
        // An event about a process goes to the earliest injection into it (a later one hit a
        // process that was already failing); an unattributed event to the most recent
        // injection into the component (a vote fails in the round right after the flip).
        let candidate = if e.replica.is_some() {
            fired
                .iter()
                .enumerate()
                .position(|(i, f)| can_explain(i, f))
        } else {
            fired
                .iter()
                .enumerate()
                .rposition(|(i, f)| can_explain(i, f))
        };
        match candidate {
            Some(i) => detection[i] = Some(e),
            None if e.replica.is_some() => false_positives += 1,
            // An unattributed event nobody explains blames no replica: not a false positive
            // in the paper's sense (no replica was recovered), but it is in the event log.
            None => {}
        }
    }

    let per_injection = fired
        .iter()
        .zip(&detection)
        .map(|(f, det)| {
            // Into a process that an earlier injection had already hit, before that one was
            // detected: it found a failing process, it did not make one.
            let earlier = fired.iter().zip(&detection).position(|(g, d)| {
                d.is_some_and(|d| {
                    g.pid == f.pid
                        && g.component == f.component
                        && g.ts_ns <= f.ts_ns
                        && f.ts_ns <= d.ts_ns
                        && !std::ptr::eq(g, f)
                })
            });
            if let (None, Some(k)) = (det, earlier) {
                let m = Match {
                    already_hit_by: Some(k),
                    ..Match::default()
                };
                return (Outcome::Missed, m);
            }
            let Some(det) = det else {
                let outcome = if task_ok {
                    Outcome::Benign
                } else {
                    Outcome::Undetected
                };
                return (outcome, Match::default());
            };
            let mut m = Match {
                detected_as: Some(kind_name(det.kind)),
                detection_latency_us: Some((det.ts_ns - f.ts_ns) / 1000),
                ..Match::default()
            };
            let recovery = det.replica.and_then(|slot| {
                events.iter().find(|r| {
                    r.kind == EventKind::Recovery
                        && r.component == f.component
                        && r.replica == Some(slot)
                        && !matches!(r.pid, Some(p) if p != f.pid)
                        && r.ts_ns >= det.ts_ns
                })
            });
            match recovery {
                Some(r) => {
                    m.recovery_us = r.recovery_us;
                    m.recovered_after_us = Some(r.ts_ns.saturating_sub(f.ts_ns) / 1000);
                    m.recovery_method = r
                        .method
                        .and_then(|x| serde_json::to_value(x).ok())
                        .and_then(|v| v.as_str().map(str::to_owned));
                    (Outcome::Recovered, m)
                }
                None => (Outcome::Unrecovered, m),
            }
        })
        .collect();
    RunMatch {
        per_injection,
        false_positives,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::event::RecoveryMethod;

    const MS: u64 = 1_000_000;

    fn ev(ts_ms: u64, kind: EventKind, slot: Option<usize>, pid: i32) -> Event {
        let mut e = Event::new("s", "echo", kind);
        e.ts_ns = ts_ms * MS;
        e.replica = slot;
        e.pid = slot.map(|_| pid);
        e
    }

    fn fired(ts_ms: u64, slot: usize, pid: i32) -> Fired {
        Fired {
            ts_ns: ts_ms * MS,
            component: "echo".into(),
            slot: Some(slot),
            pid,
        }
    }

    #[test]
    fn detection_recovery_and_latencies() {
        let mut rec = ev(130, EventKind::Recovery, Some(1), 101);
        rec.new_pid = Some(200);
        rec.recovery_us = Some(25_000);
        rec.method = Some(RecoveryMethod::Fork);
        let events = vec![ev(105, EventKind::Crash, Some(1), 101), rec];
        let m = match_run(&[fired(100, 1, 101)], &events, 2000 * MS, true);
        assert_eq!(m.false_positives, 0);
        let (o, d) = &m.per_injection[0];
        assert_eq!(*o, Outcome::Recovered);
        assert_eq!(d.detected_as.as_deref(), Some("crash"));
        assert_eq!(d.detection_latency_us, Some(5000));
        assert_eq!(d.recovered_after_us, Some(30_000));
        assert_eq!(d.recovery_us, Some(25_000));
        assert_eq!(d.recovery_method.as_deref(), Some("fork"));
    }

    #[test]
    fn wrong_pid_slot_or_window_is_a_false_positive() {
        let events = vec![
            ev(105, EventKind::Sdc, Some(0), 100), // another slot
            ev(106, EventKind::Sdc, Some(1), 999), // same slot, other pid
            ev(95, EventKind::Hang, Some(1), 101), // before the injection
        ];
        let m = match_run(&[fired(100, 1, 101)], &events, 2000 * MS, false);
        assert_eq!(m.false_positives, 3);
        assert_eq!(m.per_injection[0].0, Outcome::Undetected);
        // Too late: outside a 10 ms window.
        let m = match_run(
            &[fired(100, 1, 101)],
            &[ev(111, EventKind::Sdc, Some(1), 101)],
            10 * MS,
            true,
        );
        assert_eq!(
            (m.per_injection[0].0, m.false_positives),
            (Outcome::Benign, 1)
        );
    }

    #[test]
    fn one_event_explains_one_injection_and_no_majority_detects_without_recovery() {
        let events = vec![
            ev(105, EventKind::Sdc, Some(1), 101),
            ev(300, EventKind::Sdc, None, 0),
        ];
        let m = match_run(
            &[fired(100, 1, 101), fired(101, 1, 101), fired(290, 0, 100)],
            &events,
            2000 * MS,
            false,
        );
        let outcomes: Vec<Outcome> = m.per_injection.iter().map(|x| x.0).collect();
        // The second injection hit pid 101 after the first and before its detection.
        assert_eq!(
            outcomes,
            vec![Outcome::Unrecovered, Outcome::Missed, Outcome::Unrecovered]
        );
        assert_eq!(m.per_injection[1].1.already_hit_by, Some(0));
        assert_eq!(m.false_positives, 0);
        assert!(Outcome::Undetected.is_error() && !Outcome::Benign.is_error());
    }

    /// A TMR stream component, two replicas flipped before the same frame (campaign TMR sdc,
    /// run 39): the voter reports "no majority" first, then each faulty replica, and replaces
    /// both. Both injections are recovered and nothing is a false positive; before, the "no
    /// majority" event took the later injection (unrecovered) and its replica's own event
    /// counted as a false positive.
    #[test]
    fn two_replicas_hit_before_one_frame_are_both_recovered_despite_the_no_majority_event() {
        let recovery = |ts_ms, slot, pid| {
            let mut r = ev(ts_ms, EventKind::Recovery, Some(slot), pid);
            r.new_pid = Some(pid + 100);
            r
        };
        let events = vec![
            ev(334, EventKind::Sdc, None, 0),
            ev(334, EventKind::Sdc, Some(1), 101),
            ev(335, EventKind::Sdc, Some(2), 102),
            recovery(336, 2, 102),
            recovery(337, 1, 101),
        ];
        let m = match_run(
            &[fired(0, 1, 101), fired(200, 2, 102)],
            &events,
            2000 * MS,
            true,
        );
        let outcomes: Vec<Outcome> = m.per_injection.iter().map(|x| x.0).collect();
        assert_eq!(outcomes, vec![Outcome::Recovered, Outcome::Recovered]);
        assert_eq!(m.false_positives, 0);
    }
}
