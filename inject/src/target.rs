//! Finding the process to inject into, from bootstrap's live view (`--state FILE`).

use s3res_protocol::live::{LiveView, ReplicaState};

pub use s3res_protocol::campaign::Pick;

/// The process an injection goes to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Target {
    pub component: String,
    /// Replica slot; `None` for an unprotected component.
    pub slot: Option<usize>,
    pub pid: i32,
}

/// Why no process could be chosen.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Miss {
    #[error("component {0} is not in the live view")]
    UnknownComponent(String),
    #[error("component {component} has not been started (yet)")]
    NotStarted { component: String },
    #[error("replica {slot} of {component} is {state:?}, not running")]
    SlotNotRunning {
        component: String,
        slot: usize,
        state: ReplicaState,
    },
    #[error("no replica of {0} is running")]
    NoneRunning(String),
    #[error("the system has stopped")]
    Stopped,
}

impl Miss {
    /// The replica slot the draw chose, where the miss is that slot's (it was being replaced):
    /// the record says which replica the fault would have hit.
    pub fn slot(&self) -> Option<usize> {
        match self {
            Miss::SlotNotRunning { slot, .. } => Some(*slot),
            _ => None,
        }
    }
}

/// Chooses the target in `component` with `draw` (uniform in [0, 1)).
pub fn resolve(view: &LiveView, component: &str, draw: f64, pick: Pick) -> Result<Target, Miss> {
    if !view.running {
        return Err(Miss::Stopped);
    }
    let c = view
        .components
        .get(component)
        .ok_or_else(|| Miss::UnknownComponent(component.to_owned()))?;
    if !c.protected {
        let pid = c.pid.ok_or_else(|| Miss::NotStarted {
            component: component.to_owned(),
        })?;
        return Ok(Target {
            component: component.to_owned(),
            slot: None,
            pid,
        });
    }
    let running = |r: &&s3res_protocol::live::LiveReplica| {
        r.state == ReplicaState::Running && r.pid.is_some()
    };
    let chosen = match pick {
        Pick::Uniform => {
            let n = c.replicas.len();
            if n == 0 {
                return Err(Miss::NoneRunning(component.to_owned()));
            }
            let slot = ((draw * n as f64) as usize).min(n - 1);
            let r = &c.replicas[slot];
            if !running(&r) {
                return Err(Miss::SlotNotRunning {
                    component: component.to_owned(),
                    slot,
                    state: r.state,
                });
            }
            r
        }
        Pick::Cpu => {
            let live: Vec<_> = c.replicas.iter().filter(running).collect();
            if live.is_empty() {
                return Err(Miss::NoneRunning(component.to_owned()));
            }
            // A process whose time cannot be read (it just died) weighs nothing; if none can
            // be read, fall back to uniform over the running ones.
            let weights: Vec<f64> = live
                .iter()
                .map(|r| r.pid.and_then(cpu_ticks).unwrap_or(0) as f64)
                .collect();
            let total: f64 = weights.iter().sum();
            let idx = if total > 0.0 {
                let mut acc = 0.0;
                let goal = draw * total;
                weights
                    .iter()
                    .position(|w| {
                        acc += w;
                        goal < acc
                    })
                    .unwrap_or(live.len() - 1)
            } else {
                ((draw * live.len() as f64) as usize).min(live.len() - 1)
            };
            live[idx]
        }
    };
    Ok(Target {
        component: component.to_owned(),
        slot: Some(chosen.slot),
        pid: chosen.pid.expect("filtered on a pid"),
    })
}

/// utime + stime of `pid`, in clock ticks, from /proc/PID/stat.
pub fn cpu_ticks(pid: i32) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    parse_cpu_ticks(&stat)
}

/// Fields 14 and 15 of a stat line; the command name (field 2) may hold spaces and parens,
/// so counting starts after its last `)`.
fn parse_cpu_ticks(stat: &str) -> Option<u64> {
    let rest = &stat[stat.rfind(')')? + 1..];
    let mut fields = rest.split_whitespace().skip(11); // field 3 is the first here
    let utime: u64 = fields.next()?.parse().ok()?;
    let stime: u64 = fields.next()?.parse().ok()?;
    Some(utime + stime)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use s3res_protocol::live::{LiveComponent, LiveReplica};
    use std::collections::BTreeMap;

    /// A live view of a TMR `echo` in `states` (pids 100, 101, ...) and an unprotected `sink`.
    pub(crate) fn view(states: &[ReplicaState]) -> LiveView {
        let mut components = BTreeMap::new();
        components.insert(
            "echo".to_owned(),
            LiveComponent {
                redundancy: "tmr".to_owned(),
                protected: true,
                pid: None,
                voter_pid: Some(9),
                replicas: states
                    .iter()
                    .enumerate()
                    .map(|(slot, &state)| LiveReplica {
                        slot,
                        pid: Some(100 + slot as i32),
                        state,
                        since_ns: 0,
                    })
                    .collect(),
            },
        );
        components.insert(
            "sink".to_owned(),
            LiveComponent {
                redundancy: "none".to_owned(),
                protected: false,
                pid: Some(50),
                voter_pid: None,
                replicas: vec![],
            },
        );
        LiveView {
            system: "s".into(),
            bootstrap_pid: 1,
            updated_ns: 0,
            running: true,
            components,
        }
    }

    #[test]
    fn uniform_maps_the_draw_to_a_slot() {
        let v = view(&[ReplicaState::Running; 3]);
        let slot = |d| resolve(&v, "echo", d, Pick::Uniform).unwrap().slot;
        assert_eq!(slot(0.0), Some(0));
        assert_eq!(slot(0.5), Some(1));
        assert_eq!(slot(0.999), Some(2));
        assert_eq!(resolve(&v, "echo", 0.5, Pick::Uniform).unwrap().pid, 101);
        let t = resolve(&v, "sink", 0.3, Pick::Uniform).unwrap();
        assert_eq!((t.slot, t.pid), (None, 50));
        assert!(matches!(
            resolve(&v, "nope", 0.3, Pick::Uniform),
            Err(Miss::UnknownComponent(_))
        ));
    }

    #[test]
    fn a_slot_being_replaced_is_a_miss() {
        let v = view(&[
            ReplicaState::Running,
            ReplicaState::Faulty,
            ReplicaState::Running,
        ]);
        let miss = resolve(&v, "echo", 0.5, Pick::Uniform).unwrap_err();
        assert!(
            matches!(miss, Miss::SlotNotRunning { slot: 1, .. }),
            "{miss:?}"
        );
        assert_eq!(miss.slot(), Some(1));
        // CPU weighting only ever picks running replicas (these pids have no /proc entry, so
        // it falls back to uniform over them).
        for d in [0.0, 0.4, 0.6, 0.99] {
            let t = resolve(&v, "echo", d, Pick::Cpu).unwrap();
            assert_ne!(t.slot, Some(1));
        }
    }

    #[test]
    fn parses_cpu_time_even_with_odd_names() {
        let line = "42 (a b) c) S 1 42 42 0 -1 4194560 100 0 0 0 7 3 0 0 20 0 1 0";
        assert_eq!(parse_cpu_ticks(line), Some(10));
        assert!(cpu_ticks(std::process::id() as i32).is_some());
    }
}
