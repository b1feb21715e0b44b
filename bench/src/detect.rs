//! `s3res-bench detect`: how fast the voter sees a fault, and whether it sees faults that are not
//! there.
//!
//! - `crash`: SIGKILL to an idle replica; latency = the `crash` event's `ts_ns` − the time just
//!   before `kill` (both CLOCK_MONOTONIC).
//! - `crash-round`: SIGKILL, then at once a frame: the round trip of the round that discovers
//!   the dead replica (it includes the recovery the voter does before it reads the frame).
//! - `hang`: the injection signal (36, glibc's `SIGRTMIN+2`: the replica spins) to an idle replica, then a
//!   frame; latency = the `hang` event's `ts_ns` − (time just before the frame was written +
//!   timeout). The voter opens the round a little after the bench wrote the frame, so this is an
//!   upper bound: it includes the frame's trip into the voter (a few µs, about half the SMR
//!   round trip).
//! - `false-positives`: fault-free TMR rounds at the smallest timeout; every fault event counts.

use std::os::fd::AsFd;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use hdrhistogram::Histogram;
use s3res_protocol::event::{Event, EventKind};

use crate::report::{self, histogram, Row, Summary};
use crate::system::{Setup, Spec, System};
use crate::Common;

const WARMUP_ROUNDS: u64 = 200;
const SETTLE_ROUNDS: u64 = 2;
const ROUND_LIMIT: Duration = Duration::from_secs(10);
const EVENT_LIMIT: Duration = Duration::from_secs(10);
const FRAME: usize = 8;

pub struct DetectOptions {
    pub setup: Setup,
    pub timeouts_us: Vec<u64>,
    pub count: u64,
    pub rounds: u64,
    pub seed: u64,
}

/// Picks victims; seeded by `--seed`.
type Rng = s3res_protocol::rng::SplitMix64;

pub fn run(common: &Common, o: &DetectOptions) -> Result<Vec<Row>> {
    // What s3res-bootstrap holds for its voters (an idle task clock, so that a look's
    // `perf_event_open` never waits for an RCU grace period: `bootstrap/src/run.rs`), held by
    // the bench in its place. Not in `echo`: no replica is late there, and the harness pays
    // perf's context-switch hook for as long as it holds one.
    let _task_clocks_ready = replica_rt::sys::TaskClock::open_idle(0).ok();
    let echo = common.bins.component("s3res-echo")?;
    let voter = common.bins.path("s3res-voter")?;
    let spec = |timeout_us| Spec {
        journal: common.journal,
        lock_memory: common.lock_memory,
        cpu_idle: common.cpu_idle,
        spin_us: common.spin_us,
        exec: echo.clone(),
        args: Vec::new(),
        replicas: 3,
        timeout_us,
        max_frame: replica_rt::frame::DEFAULT_MAX_FRAME,
        voter: Some(voter.clone()),
        setup: o.setup,
        preload: None,
    };
    let mut rng = Rng::new(o.seed);
    let total = o.timeouts_us.len() as u64 * o.count * 3 + o.rounds;
    let bar = common.progress(total, "detect");
    let mut rows = Vec::new();
    for &t in &o.timeouts_us {
        if o.count == 0 {
            break;
        }
        let mut system = System::start(&spec(t))?;
        o.setup.apply(&system)?;
        let mut seq = 0;
        for _ in 0..WARMUP_ROUNDS {
            round(&mut system, &mut seq)?;
        }
        bar.set_message(format!("crash, timeout {t} µs"));
        rows.push(metered(|| {
            crashes(&mut system, &mut seq, t, o.count, &mut rng, &bar)
        })?);
        bar.set_message(format!("crash-round, timeout {t} µs"));
        rows.push(metered(|| {
            crash_rounds(&mut system, &mut seq, t, o.count, &mut rng, &bar)
        })?);
        bar.set_message(format!("hang, timeout {t} µs"));
        rows.push(metered(|| {
            hangs(&mut system, &mut seq, t, o.count, &mut rng, &bar)
        })?);
    }
    if o.rounds > 0 {
        let t = o.timeouts_us.iter().copied().min().unwrap_or(2000);
        bar.set_message(format!("false positives, timeout {t} µs"));
        rows.push(metered(|| {
            false_positives(&spec(t), o.setup, o.rounds, &bar)
        })?);
    }
    bar.finish_and_clear();
    Setup::reset_bench();
    for r in &mut rows {
        r.setup = o.setup.name();
    }
    Ok(rows)
}

/// One measurement's row, with the host's steal over it (`report::Steal`): a false positive
/// or a slow detection in a row the host took CPUs from may be the host's.
fn metered(measure: impl FnOnce() -> Result<Row>) -> Result<Row> {
    let steal = report::Steal::start();
    let mut row = measure()?;
    row.steal_ms = steal.ms();
    Ok(row)
}

fn row(what: &str, h: &Histogram<u64>, timeout_us: u64, faults: u64) -> Row {
    let mut r = Row::new("detect", 3, FRAME as u64, Summary::of(h));
    r.what = Some(what.into());
    r.timeout_us = Some(timeout_us);
    r.faults = Some(faults);
    r
}

/// Injections not seen as what they were.
#[derive(Debug, Default)]
struct Tally {
    /// Seen as another kind of fault.
    misclassified: u64,
    /// No fault event about the victim within [`EVENT_LIMIT`].
    undetected: u64,
}

impl Tally {
    fn row(&self, what: &str, h: &Histogram<u64>, timeout_us: u64, system: &System) -> Row {
        let mut r = row(what, h, timeout_us, self.misclassified + self.undetected);
        r.extra = Some(serde_json::json!({
            "misclassified": self.misclassified,
            "undetected": self.undetected,
            "lost_rounds": system.lost.count,
            "late_answers": system.lost.late,
        }));
        r
    }
}

/// After an injection into `slot` at `since`: the victim's fault event's timestamp if it is of
/// kind `want` (else it is tallied), then the victim's replacement and two quiet rounds.
fn observe(
    system: &mut System,
    seq: &mut u64,
    slot: usize,
    since: u64,
    want: EventKind,
    tally: &mut Tally,
) -> Result<Option<u64>> {
    let Some(ev) = fault_of(system, slot, since)? else {
        tally.undetected += 1;
        return Ok(None);
    };
    let ts = (ev.kind == want).then_some(ev.ts_ns);
    if ts.is_none() {
        tally.misclassified += 1;
    }
    recovered(system, slot, since)?;
    settle(system, seq)?;
    Ok(ts)
}

/// Kill an idle replica; time to its `crash` event.
fn crashes(
    system: &mut System,
    seq: &mut u64,
    timeout_us: u64,
    count: u64,
    rng: &mut Rng,
    bar: &indicatif::ProgressBar,
) -> Result<Row> {
    let mut h = histogram();
    let mut exit_h = histogram();
    let mut tally = Tally::default();
    for _ in 0..count {
        let slot = rng.below(3) as usize;
        // The bench watches the death itself too: kill → pidfd readable is the kernel's part
        // (the dying process's memory is torn down before its exit is reported).
        let (t_kill, pidfd) = inject_watched(system, slot, libc::SIGKILL)?;
        if let Some(fd) = &pidfd {
            if replica_rt::sys::wait_readable(fd.as_fd(), EVENT_LIMIT).unwrap_or(false) {
                exit_h.record(
                    replica_rt::sys::monotonic_ns()
                        .saturating_sub(t_kill)
                        .max(1),
                )?;
            }
        }
        if let Some(ts) = observe(system, seq, slot, t_kill, EventKind::Crash, &mut tally)? {
            h.record(ts.saturating_sub(t_kill).max(1))?;
        }
        bar.inc(1);
    }
    let mut r = tally.row("crash", &h, timeout_us, system);
    let exit = Summary::of(&exit_h);
    if let Some(extra) = r.extra.as_mut() {
        extra["kill_to_exit_median_us"] = exit.median_us.into();
        extra["kill_to_exit_p99_us"] = exit.p99_us.into();
    }
    Ok(r)
}

/// Kill an idle replica and send a frame at once: the round that discovers the death.
fn crash_rounds(
    system: &mut System,
    seq: &mut u64,
    timeout_us: u64,
    count: u64,
    rng: &mut Rng,
    bar: &indicatif::ProgressBar,
) -> Result<Row> {
    let mut h = histogram();
    let mut tally = Tally::default();
    for _ in 0..count {
        let slot = rng.below(3) as usize;
        let t0 = inject(system, slot, libc::SIGKILL)?;
        if round(system, seq)? {
            h.record(replica_rt::sys::monotonic_ns() - t0)?;
        }
        observe(system, seq, slot, t0, EventKind::Crash, &mut tally)?;
        bar.inc(1);
    }
    Ok(tally.row("crash-round", &h, timeout_us, system))
}

/// Make an idle replica spin, send a frame: time from the deadline to the `hang` event.
fn hangs(
    system: &mut System,
    seq: &mut u64,
    timeout_us: u64,
    count: u64,
    rng: &mut Rng,
    bar: &indicatif::ProgressBar,
) -> Result<Row> {
    let mut h = histogram();
    let mut tally = Tally::default();
    let cfe = replica_rt::contract::signals::inject_cfe();
    for _ in 0..count {
        let slot = rng.below(3) as usize;
        let t_inject = inject(system, slot, cfe)?;
        let t_send = replica_rt::sys::monotonic_ns();
        round(system, seq)?;
        if let Some(ts) = observe(system, seq, slot, t_inject, EventKind::Hang, &mut tally)? {
            let deadline = t_send + timeout_us * 1000;
            // Clamped at 1 ns: the voter cannot fire before its deadline, so an event "before"
            // it would only be clock granularity.
            h.record(ts.saturating_sub(deadline).max(1))?;
        }
        bar.inc(1);
    }
    Ok(tally.row("hang", &h, timeout_us, system))
}

/// Fault-free rounds; counts every fault event.
fn false_positives(
    spec: &Spec,
    setup: Setup,
    rounds: u64,
    bar: &indicatif::ProgressBar,
) -> Result<Row> {
    let mut system = System::start(spec)?;
    setup.apply(&system)?;
    let mut seq = 0;
    for _ in 0..WARMUP_ROUNDS {
        round(&mut system, &mut seq)?;
    }
    let before = system.faults.len();
    let mut h = histogram();
    for k in 0..rounds {
        let t0 = replica_rt::sys::monotonic_ns();
        if round(&mut system, &mut seq)? {
            h.record(replica_rt::sys::monotonic_ns() - t0)?;
        }
        if k % 4096 == 4095 {
            bar.inc(4096);
            system.drain_events()?;
        }
    }
    bar.inc(rounds % 4096);
    // Let a fault of the last round arrive.
    std::thread::sleep(Duration::from_micros(2 * spec.timeout_us) + Duration::from_millis(10));
    system.drain_events()?;
    let faults: Vec<&Event> = system.faults[before..].iter().collect();
    for f in &faults {
        tracing::warn!(kind = ?f.kind, replica = f.replica, detail = f.detail.as_deref(), "false positive");
    }
    let mut r = row("false-positives", &h, spec.timeout_us, faults.len() as u64);
    r.extra = Some(serde_json::json!({
        "rounds": rounds,
        "lost_rounds": system.lost.count,
        "late_answers": system.lost.late,
        "kinds": faults.iter().map(|f| format!("{:?}", f.kind).to_lowercase()).collect::<Vec<_>>(),
    }));
    Ok(r)
}

/// Sends `sig` to the current replica of `slot`; returns the time just before. If that
/// replica is already gone (a fault the bench did not cause, whose events are still on their
/// way: under load a replica can miss a short deadline), waits for its replacement and retries.
fn inject(system: &mut System, slot: usize, sig: i32) -> Result<u64> {
    inject_watched(system, slot, sig).map(|(t, _)| t)
}

/// [`inject`], also returning a pidfd of the process that got the signal.
fn inject_watched(
    system: &mut System,
    slot: usize,
    sig: i32,
) -> Result<(u64, Option<std::os::fd::OwnedFd>)> {
    system.drain_events()?;
    for _ in 0..3 {
        let pid = system.replicas[slot];
        let pidfd = replica_rt::sys::pidfd_open(pid).ok();
        let t = replica_rt::sys::monotonic_ns();
        // A zombie accepts signals too: a replica the voter has killed but whose event has not
        // arrived yet must not "take" the injection.
        let result = if running(pid) {
            replica_rt::sys::kill(pid, sig)
        } else {
            Err(std::io::Error::from_raw_os_error(libc::ESRCH))
        };
        match result {
            Ok(()) => return Ok((t, pidfd)),
            Err(e) if e.raw_os_error() == Some(libc::ESRCH) => {
                tracing::debug!(
                    slot,
                    pid,
                    "replica already gone; waiting for its replacement"
                );
                system.wait_event(
                    |e| e.replica == Some(slot) && e.kind == EventKind::Recovery,
                    EVENT_LIMIT,
                )?;
            }
            Err(e) => return Err(e).context(format!("signal {sig} to replica {slot} (pid {pid})")),
        }
    }
    bail!("replica {slot} kept disappearing before the injection")
}

/// Whether `pid` exists and is not a zombie (its state in `/proc/PID/stat`).
fn running(pid: libc::pid_t) -> bool {
    replica_rt::sys::process_state(pid).is_some_and(|state| state != 'Z' && state != 'X')
}

/// The first fault event about `slot` at or after `since` (CLOCK_MONOTONIC ns); `None` if none
/// came within [`EVENT_LIMIT`] (an undetected injection: counted, and the run goes on).
fn fault_of(system: &mut System, slot: usize, since: u64) -> Result<Option<Event>> {
    system.try_wait_event_since(
        |e| {
            e.replica == Some(slot)
                && !matches!(
                    e.kind,
                    EventKind::Start | EventKind::Recovery | EventKind::RecoveryFailed
                )
        },
        since,
        EVENT_LIMIT,
    )
}

fn recovered(system: &mut System, slot: usize, since: u64) -> Result<()> {
    let ev = system.wait_event_since(
        |e| {
            e.replica == Some(slot)
                && matches!(e.kind, EventKind::Recovery | EventKind::RecoveryFailed)
        },
        since,
        EVENT_LIMIT,
    )?;
    if ev.kind != EventKind::Recovery {
        bail!("recovery failed: {:?}\n{}", ev.detail, system.log_tail());
    }
    Ok(())
}

fn settle(system: &mut System, seq: &mut u64) -> Result<()> {
    for _ in 0..SETTLE_ROUNDS {
        round(system, seq)?;
    }
    Ok(())
}

/// One round; `false` if the voter withheld the answer (see `System::echo_round`).
fn round(system: &mut System, seq: &mut u64) -> Result<bool> {
    let mut frame = [0u8; FRAME];
    crate::echo::fill_frame(*seq, &mut frame);
    *seq += 1;
    let answered = system
        .echo_round(&frame, ROUND_LIMIT)
        .with_context(|| format!("round {}", *seq - 1))?;
    Ok(answered.is_some())
}

pub fn render(rows: &[Row]) -> String {
    let cells: Vec<Vec<String>> = rows
        .iter()
        .map(|r| {
            vec![
                r.what.clone().unwrap_or_default(),
                r.timeout_us.map(|t| t.to_string()).unwrap_or_default(),
                r.count.to_string(),
                report::us(r.median_us),
                report::us(r.p99_us),
                report::us(r.max_us),
                r.faults.map(|f| f.to_string()).unwrap_or_default(),
                r.extra
                    .as_ref()
                    .and_then(|e| e.get("lost_rounds"))
                    .map(|v| v.to_string())
                    .unwrap_or_default(),
                r.extra
                    .as_ref()
                    .and_then(|e| e.get("kill_to_exit_median_us"))
                    .and_then(|v| v.as_f64())
                    .map(report::us)
                    .unwrap_or_default(),
            ]
        })
        .collect();
    report::table(
        &[
            "measure",
            "timeout µs",
            "count",
            "median µs",
            "p99 µs",
            "max µs",
            "faults/misclassified",
            "lost rounds",
            "kill→exit µs (kernel)",
        ],
        &cells,
    )
}
