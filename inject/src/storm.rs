//! `storm`: faults injected into a running system for as long as it runs, at a seeded rate and
//! a seeded mix of kinds. This is the injector a system description can name (`inject`):
//! bootstrap starts it beside the components, hands it the live view, and stops it (SIGTERM)
//! when the components have finished; it reads the log this writes for the verdict.
//!
//! One fault at a time per component: an injection drawn for a component that still has a
//! replica being replaced, or that was injected into less than `settle` ago, is recorded as
//! missed (two faults at once are beyond what TMR masks,
//! and the point of the storm is to show masking, not to defeat it). Every random choice comes
//! from the seed, drawn whether or not the injection is then delivered, so the same seed gives
//! the same sequence of kinds, components, slots and bits.

use std::fs::File;
use std::io::Write as _;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use rand::{Rng as _, SeedableRng as _};
use rand_chacha::ChaCha8Rng;
use thiserror::Error;

use s3res_protocol::live::{LiveView, ReplicaState};

use crate::fault::{fire, Action, FaultKind, RegOptions};
use crate::runner::all_running;
use crate::schedule::{draw_injection, Arrival, Planned, ScheduleParams, VarSpec};
use crate::target::{resolve, Pick, Target};

/// How often the storm looks at the live view and the stop request while it waits.
const POLL: Duration = Duration::from_millis(20);

/// What to inject, how often, where.
#[derive(Debug, Clone)]
pub struct StormOptions {
    /// bootstrap's live view.
    pub state: PathBuf,
    /// The kinds to mix, each equally likely.
    pub faults: Vec<FaultKind>,
    /// Injections per second (Poisson arrivals).
    pub rate_hz: f64,
    pub seed: u64,
    /// Targets; empty: every protected component of the live view.
    pub components: Vec<String>,
    /// Quiet time after every target first runs, before the first injection.
    pub after: Duration,
    /// After an injection into a component, the next one into it waits at least this long
    /// (a fault not yet detected does not show in the live view).
    pub settle: Duration,
    /// Where each injection is written as one JSON line (`None`: stdout).
    pub log: Option<PathBuf>,
    pub var: VarSpec,
    pub reg: RegOptions,
}

/// Why the storm could not go on.
#[derive(Debug, Error)]
pub enum StormError {
    #[error("--rate {0}")]
    Rate(#[from] s3res_protocol::campaign::RateError),
    #[error("no fault kind to inject (give --faults, e.g. exec,sdc,cfe)")]
    NoFaults,
    #[error("fault kind `none` cannot be part of a storm")]
    NoneKind,
    #[error("a storm mixes the kinds it is given: name them (--faults exec,sdc,cfe), not `mixed`")]
    MixedKind,
    #[error("cannot write the injection log {path}: {source}")]
    Log {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("the live view names no protected component to inject into")]
    NoTargets,
    #[error("the system {system} has no component {}; it has: {}", unknown.join(", "), known.join(", "))]
    UnknownComponents {
        system: String,
        unknown: Vec<String>,
        known: Vec<String>,
    },
}

/// One line of the log, as `s3res-inject inject` prints it, with the storm's index and, for an
/// injection not delivered, why (`miss`; `ts_ns` and `pid` are then absent).
pub fn record_line(
    index: usize,
    seed: u64,
    system: &str,
    planned: &Planned,
    target: Option<&Target>,
    ts_ns: Option<u64>,
    miss: Option<&str>,
) -> serde_json::Value {
    let mut line = serde_json::json!({
        "index": index,
        "ts_ns": ts_ns,
        "seed": seed,
        "system": system,
        "component": planned.component,
        "replica": target.and_then(|t| t.slot),
        "pid": target.map(|t| t.pid),
    });
    if let (Some(obj), Ok(serde_json::Value::Object(act))) =
        (line.as_object_mut(), serde_json::to_value(&planned.action))
    {
        obj.extend(act);
        if let Some(m) = miss {
            obj.insert("miss".to_owned(), m.into());
        }
    }
    line
}

/// Runs until `stop()` says so or the live view says the system stopped. Returns how many
/// injections were delivered.
pub fn run(o: &StormOptions, stop: &dyn Fn() -> bool) -> Result<u64, StormError> {
    s3res_protocol::campaign::check_rate(o.rate_hz)?;
    if o.faults.is_empty() {
        return Err(StormError::NoFaults);
    }
    if o.faults.contains(&FaultKind::None) {
        return Err(StormError::NoneKind);
    }
    if o.faults.contains(&FaultKind::Mixed) {
        return Err(StormError::MixedKind);
    }
    let mut out: Box<dyn std::io::Write> = match &o.log {
        Some(path) => Box::new(File::create(path).map_err(|source| StormError::Log {
            path: path.clone(),
            source,
        })?),
        None => Box::new(std::io::stdout()),
    };

    // Until every target runs (the view may not exist yet: bootstrap writes it as it starts).
    let waiting_since = Instant::now();
    let mut said_why = false;
    let view = loop {
        if stop() {
            return Ok(0);
        }
        match LiveView::read(&o.state) {
            Ok(v) => {
                if !v.running {
                    return Ok(0);
                }
                let targets = targets_of(&v, &o.components);
                check_targets(&v, &targets)?;
                if all_running(&v, &targets) {
                    break v;
                }
            }
            // Said once, not fatal: a bootstrap may still be starting.
            Err(e) if !said_why && waiting_since.elapsed() >= UNREADABLE_FOR => {
                tracing::warn!(
                    "still no live view to read at {} ({e}); waiting for it (is it bootstrap's \
                     --state file of a running system?)",
                    o.state.display()
                );
                said_why = true;
            }
            Err(_) => {}
        }
        std::thread::sleep(POLL);
    };
    let targets = targets_of(&view, &o.components);
    tracing::info!(
        "injecting {} into {} at {} Hz (seed {}), from {:.1} s on",
        o.faults
            .iter()
            .map(|f| f.name())
            .collect::<Vec<_>>()
            .join("/"),
        targets.join(", "),
        o.rate_hz,
        o.seed,
        o.after.as_secs_f64()
    );
    let started = Instant::now();
    if !sleep_until(started + o.after, &o.state, stop) {
        return Ok(0);
    }

    let mut rng = ChaCha8Rng::seed_from_u64(o.seed);
    let mean = 1.0 / o.rate_hz;
    let mut next = Instant::now();
    let mut delivered = 0;
    let mut last_hit: std::collections::BTreeMap<String, Instant> = Default::default();
    for index in 0.. {
        // 1 - u is in (0, 1]: never ln(0).
        next += Duration::from_secs_f64(-(1.0 - rng.gen::<f64>()).ln() * mean);
        let kind = o.faults[rng.gen_range(0..o.faults.len())];
        let params = ScheduleParams {
            fault: kind,
            rate_hz: o.rate_hz,
            arrival: Arrival::Exponential,
            window: Duration::ZERO,
            components: targets.clone(),
            var: o.var.clone(),
        };
        let at_ns = started.elapsed().as_nanos() as u64;
        let Some(planned) = draw_injection(&params, &mut rng, index, at_ns) else {
            break;
        };
        if !sleep_until(next, &o.state, stop) {
            break;
        }
        let settling = last_hit
            .get(&planned.component)
            .is_some_and(|t| t.elapsed() < o.settle);
        let (line, hit) = if settling {
            let why = "the last fault injected into the component may not be detected yet";
            (
                miss_line(o, index, &view.system, &planned, None, &why),
                false,
            )
        } else {
            inject_one(o, index, &planned)
        };
        if hit {
            last_hit.insert(planned.component.clone(), Instant::now());
            delivered += 1;
        }
        let text = serde_json::to_string(&line).unwrap_or_default();
        writeln!(out, "{text}")
            .and_then(|()| out.flush())
            .map_err(|source| StormError::Log {
                path: o.log.clone().unwrap_or_else(|| "stdout".into()),
                source,
            })?;
    }
    Ok(delivered)
}

/// Fires `planned` if its component is whole; the log line and whether it was delivered.
fn inject_one(o: &StormOptions, index: usize, planned: &Planned) -> (serde_json::Value, bool) {
    let view = match LiveView::read(&o.state) {
        Ok(v) => v,
        Err(e) => return (miss_line(o, index, "", planned, None, &e), false),
    };
    let target = resolve(&view, &planned.component, planned.draw, Pick::Uniform);
    let whole = view
        .components
        .get(&planned.component)
        .is_some_and(|c| c.replicas.iter().all(|r| r.state == ReplicaState::Running));
    if !whole {
        // The replica the draw chose, whether it is the one being replaced or another.
        let slot = match &target {
            Ok(t) => t.slot,
            Err(e) => e.slot(),
        };
        let why = "a replica of the component is still being replaced";
        return (
            miss_line(o, index, &view.system, planned, slot, &why),
            false,
        );
    }
    let target = match target {
        Ok(t) => t,
        Err(e) => {
            return (
                miss_line(o, index, &view.system, planned, e.slot(), &e),
                false,
            )
        }
    };
    let ts = replica_rt::sys::monotonic_ns();
    let (ts, miss, injector) = match fire(&planned.action, target.pid, &o.reg) {
        Ok(injector) => {
            tracing::info!(
                "injected {} into {}#{} (pid {})",
                describe(&planned.action),
                target.component,
                target.slot.map_or("-".to_owned(), |s| s.to_string()),
                target.pid
            );
            let at = crate::fault::injected_at(ts, injector.as_ref());
            (Some(at), None, injector)
        }
        Err(e) => (None, Some(e.to_string()), None),
    };
    let mut line = record_line(
        index,
        o.seed,
        &view.system,
        planned,
        Some(&target),
        ts,
        miss.as_deref(),
    );
    // The register injector's record (instruction, register, bits, values), as a campaign's.
    if let (Some(obj), Some(i)) = (line.as_object_mut(), injector) {
        obj.insert("injector".to_owned(), i);
    }
    (line, ts.is_some())
}

/// The log line of an injection not delivered, with the replica the draw chose if one was
/// (a missed injection's slot said `null` even when it was the slot being replaced).
fn miss_line(
    o: &StormOptions,
    index: usize,
    system: &str,
    planned: &Planned,
    slot: Option<usize>,
    why: &dyn std::fmt::Display,
) -> serde_json::Value {
    let why = why.to_string();
    tracing::debug!("injection {index} into {} missed: {why}", planned.component);
    let mut line = record_line(index, o.seed, system, planned, None, None, Some(&why));
    if let (Some(obj), Some(slot)) = (line.as_object_mut(), slot) {
        obj.insert("replica".to_owned(), slot.into());
    }
    line
}

/// `a crash (SIGKILL)`, `a bit flip`, `a spin`: what the user reads in the log.
fn describe(a: &Action) -> &'static str {
    match a {
        Action::Exec => "a crash (SIGKILL)",
        Action::Sdc { .. } => "a bit flip (sdc)",
        Action::Cfe => "a spin (cfe)",
        Action::Var { .. } => "a variable flip (var)",
        Action::Reg { .. } => "a register flip (reg)",
    }
}

/// How long the live view may be missing or unreadable before the storm says so.
const UNREADABLE_FOR: Duration = Duration::from_secs(5);

/// Targets that the system has: some, and every one named in it. A target it lacks would be
/// waited for until the system ends, firing nothing and saying nothing.
fn check_targets(view: &LiveView, targets: &[String]) -> Result<(), StormError> {
    if targets.is_empty() {
        return Err(StormError::NoTargets);
    }
    let unknown: Vec<String> = targets
        .iter()
        .filter(|t| !view.components.contains_key(*t))
        .cloned()
        .collect();
    if unknown.is_empty() {
        return Ok(());
    }
    Err(StormError::UnknownComponents {
        system: view.system.clone(),
        unknown,
        known: view.components.keys().cloned().collect(),
    })
}

/// The given components, or every protected one of the view.
fn targets_of(view: &LiveView, given: &[String]) -> Vec<String> {
    if !given.is_empty() {
        return given.to_vec();
    }
    view.components
        .iter()
        .filter(|(_, c)| c.protected)
        .map(|(n, _)| n.clone())
        .collect()
}

/// Sleeps until `due`; `false` if a stop was requested or the system stopped meanwhile.
fn sleep_until(due: Instant, state: &std::path::Path, stop: &dyn Fn() -> bool) -> bool {
    let mut last_look = Instant::now();
    loop {
        if stop() {
            return false;
        }
        let now = Instant::now();
        if now >= due {
            return true;
        }
        if now - last_look >= Duration::from_millis(200) {
            last_look = now;
            if LiveView::read(state).is_ok_and(|v| !v.running) {
                return false;
            }
        }
        std::thread::sleep((due - now).min(POLL));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A storm's injection into a component whose replica is being replaced is missed, and
    /// its line names the replica the draw chose (it said `null`), whichever that is; nothing
    /// is fired (these pids are no processes).
    #[test]
    fn a_miss_while_a_replica_is_replaced_names_the_slot_the_draw_chose() {
        let dir = tempfile::tempdir().unwrap();
        let state = dir.path().join("state.json");
        crate::target::tests::view(&[
            ReplicaState::Running,
            ReplicaState::Faulty,
            ReplicaState::Running,
        ])
        .write(&state)
        .unwrap();
        let o = StormOptions {
            state,
            faults: vec![FaultKind::Exec],
            rate_hz: 1.0,
            seed: 1,
            components: vec![],
            after: Duration::ZERO,
            settle: Duration::ZERO,
            log: None,
            var: VarSpec::default(),
            reg: RegOptions::default(),
        };
        for (draw, slot) in [(0.5, 1), (0.1, 0)] {
            let planned = Planned {
                index: 0,
                at_ns: 0,
                component: "echo".to_owned(),
                draw,
                action: Action::Exec,
            };
            let (line, delivered) = inject_one(&o, 0, &planned);
            assert!(!delivered, "{line}");
            assert_eq!(line["replica"], slot, "{line}");
            assert_eq!(line["pid"], serde_json::Value::Null, "{line}");
            assert_eq!(
                line["miss"], "a replica of the component is still being replaced",
                "{line}"
            );
        }
    }
}
