//! `s3res-bench restart`: a TMR `s3res-ballast` of each state size loses a replica (SIGKILL);
//! the voter's own events time the recovery (the `crash` event's timestamp is the detection,
//! the `recovery` event's the new replica's `Ready`). Next to it, the floor: the bench itself
//! holds the same amount of touched memory, forks, and the child writes every page; the time
//! from before `fork` to the child's "done" byte. The S³RES paper's Figure 4.
//!
//! `gap` idles the bench before each kill and each fork of the floor: back to back (no gap)
//! both run with what the last one left warm, which a fault in a real system does not find.

use std::os::fd::AsFd;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use s3res_protocol::event::{EventKind, RecoveryMethod};

use crate::report::{self, histogram, Row, Summary};
use crate::system::{Setup, Spec, System};
use crate::{sys, Common};

/// Rounds after start (replicas must have answered before they can be donors).
const WARMUP_ROUNDS: u64 = 5;
/// Rounds after each restart before the next kill: the new replica answers (and so finishes
/// its page walk) and proves itself.
const SETTLE_ROUNDS: u64 = 3;
const ROUND_LIMIT: Duration = Duration::from_secs(30);
const EVENT_LIMIT: Duration = Duration::from_secs(30);
/// Frame payload of the rounds in between (bytes).
const FRAME: usize = 64;

pub fn run(
    common: &Common,
    sizes: &[u64],
    count: u64,
    timeout_us: u64,
    setup: Setup,
    gap: Duration,
) -> Result<Vec<Row>> {
    let ballast = common.bins.component("s3res-ballast")?;
    let voter = common.bins.path("s3res-voter")?;
    let bar = common.progress(sizes.len() as u64 * count * 3, "restart");
    let mut rows = Vec::new();
    for &size in sizes {
        bar.set_message(report::bytes_name(size));
        let spec = Spec {
            journal: common.journal,
            lock_memory: common.lock_memory,
            cpu_idle: common.cpu_idle,
            spin_us: common.spin_us,
            exec: ballast.clone(),
            args: vec!["--kib".into(), (size / 1024).to_string()],
            replicas: 3,
            timeout_us,
            max_frame: replica_rt::frame::DEFAULT_MAX_FRAME,
            voter: Some(voter.clone()),
            setup,
            preload: None,
        };
        let steal = report::Steal::start();
        let (restart, extra) = restarts(&spec, setup, count, gap, &bar)
            .with_context(|| format!("restart with {} of state", report::bytes_name(size)))?;
        let stolen = steal.ms();
        let floor = floor(size as usize, count, Own::Touch, gap, &bar)
            .with_context(|| format!("floor for {}", report::bytes_name(size)))?;
        let floor_madvise = floor_madvise_or_none(size as usize, count, gap, &bar)
            .with_context(|| format!("madvise floor for {}", report::bytes_name(size)))?;
        Setup::reset_bench();
        let mut row = Row::new("restart", 3, size, restart);
        row.steal_ms = stolen;
        row.setup = setup.name();
        row.timeout_us = Some(timeout_us);
        row.floor_us = Some(floor.median_us);
        row.floor_p99_us = Some(floor.p99_us);
        row.ratio = Some(restart.median_us / floor.median_us);
        let mut extra = extra;
        if let Some(map) = extra.as_object_mut() {
            map.insert("gap_ms".into(), (gap.as_millis() as u64).into());
            if let Some(f) = floor_madvise {
                map.insert("floor_madvise_us".into(), f.median_us.into());
                map.insert(
                    "ratio_madvise".into(),
                    (restart.median_us / f.median_us).into(),
                );
            }
        }
        row.extra = Some(extra);
        rows.push(row);
    }
    bar.finish_and_clear();
    Ok(rows)
}

/// Kills a replica `count` times (slots in turn) and times each recovery from the events.
fn restarts(
    spec: &Spec,
    setup: Setup,
    count: u64,
    gap: Duration,
    bar: &indicatif::ProgressBar,
) -> Result<(Summary, serde_json::Value)> {
    let mut system = System::start(spec)?;
    // Fork children inherit their donor's policy and affinity.
    setup.apply(&system)?;
    let mut seq = 0u64;
    for _ in 0..WARMUP_ROUNDS {
        round(&mut system, &mut seq)?;
    }
    let mut h = histogram();
    let mut detect = histogram();
    let mut by_exec = 0u64;
    let mut exec_h = histogram();
    let mut service = histogram();
    for k in 0..count {
        let slot = (k % 3) as usize;
        std::thread::sleep(gap);
        let pid = system.replicas[slot];
        let killed_at = replica_rt::sys::monotonic_ns();
        replica_rt::sys::kill(pid, libc::SIGKILL).context("killing a replica")?;
        let crash = system.wait_event(
            |e| e.replica == Some(slot) && e.kind != EventKind::Start,
            EVENT_LIMIT,
        )?;
        if crash.kind != EventKind::Crash {
            bail!("a killed replica was seen as {:?}, not a crash", crash.kind);
        }
        detect.record(crash.ts_ns.saturating_sub(killed_at).max(1))?;
        // The voter takes no input while a fault is pending: these frames wait in the pipe.
        let frames = [frame(seq), frame(seq + 1)];
        for f in &frames {
            system.input.send(f, ROUND_LIMIT)?;
        }
        let rec = system.wait_event(
            |e| {
                e.replica == Some(slot)
                    && matches!(e.kind, EventKind::Recovery | EventKind::RecoveryFailed)
            },
            EVENT_LIMIT,
        )?;
        if rec.kind != EventKind::Recovery {
            bail!("recovery failed: {:?}\n{}", rec.detail, system.log_tail());
        }
        // Detection is the crash event's timestamp (the voter's own `detected_ns`).
        let took = rec.ts_ns.saturating_sub(crash.ts_ns).max(1);
        if rec.method == Some(RecoveryMethod::Fork) {
            h.record(took)?;
        } else {
            by_exec += 1;
            exec_h.record(took)?;
        }
        // Round A (written before recovery finished, read after) includes the new replica; it
        // closes only once the new replica answered, after its page walk. B is read only then.
        let t_b = answers(&mut system, &mut seq, &frames)?;
        service.record(t_b.saturating_sub(crash.ts_ns).max(1))?;
        for _ in 0..SETTLE_ROUNDS {
            round(&mut system, &mut seq)?;
        }
        bar.inc(1);
    }
    system.drain_events()?;
    if h.is_empty() {
        bail!("no recovery was by fork ({by_exec} by exec)");
    }
    let extra = serde_json::json!({
        "crash_detect_median_us": Summary::of(&detect).median_us,
        "in_service_median_us": Summary::of(&service).median_us,
        "in_service_p99_us": Summary::of(&service).p99_us,
        "by_exec": by_exec,
        "exec_median_us": (!exec_h.is_empty()).then(|| Summary::of(&exec_h).median_us),
        "faults": system.faults.len(),
    });
    Ok((Summary::of(&h), extra))
}

fn frame(seq: u64) -> [u8; FRAME] {
    let mut f = [0u8; FRAME];
    crate::echo::fill_frame(seq, &mut f);
    f
}

/// One round; checks that the stateful counter carries on (state kept across restarts).
fn round(system: &mut System, seq: &mut u64) -> Result<()> {
    let frame = frame(*seq);
    let reply = system
        .exchange(&frame, ROUND_LIMIT)
        .with_context(|| format!("round {seq}"))?;
    check(reply, &frame, seq)
}

/// Reads the answers to `frames` (already written); returns when the last one arrived.
fn answers(system: &mut System, seq: &mut u64, frames: &[[u8; FRAME]]) -> Result<u64> {
    let mut at = 0;
    for f in frames {
        let reply = system
            .output
            .recv(ROUND_LIMIT)
            .with_context(|| format!("answer to round {seq}"))?;
        at = replica_rt::sys::monotonic_ns();
        check(reply, f, seq)?;
    }
    Ok(at)
}

/// The answer must be `frame` behind the count of earlier frames (state kept).
fn check(reply: &[u8], frame: &[u8], seq: &mut u64) -> Result<()> {
    let Some((prefix, rest)) = reply.split_first_chunk::<8>() else {
        bail!("answer of {} bytes is too short", reply.len());
    };
    if rest != frame {
        bail!("answer to round {seq} carries another frame");
    }
    let answered = u64::from_le_bytes(*prefix);
    if answered != *seq {
        bail!("state lost: the answer to round {seq} counts {answered} earlier frames");
    }
    *seq += 1;
    Ok(())
}

/// How the floor's child takes its own copy of the state's pages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Own {
    /// Write one byte into every page: one write fault per page.
    Touch,
    /// One `madvise(MADV_POPULATE_WRITE)` over the state: the kernel write-faults every page in
    /// one call, as the restart child does (Linux ≥ 5.14).
    Populate,
}

/// The floor with [`Own::Populate`], or `None` where the kernel does not have it.
fn floor_madvise_or_none(
    size: usize,
    count: u64,
    gap: Duration,
    bar: &indicatif::ProgressBar,
) -> Result<Option<Summary>> {
    if size > 0 && !sys::populate_write_supported() {
        bar.inc(count);
        return Ok(None);
    }
    floor(size, count, Own::Populate, gap, bar).map(Some)
}

/// fork + take a private copy of every page of `size` bytes of touched memory, `count` times,
/// in the bench.
fn floor(
    size: usize,
    count: u64,
    own: Own,
    gap: Duration,
    bar: &indicatif::ProgressBar,
) -> Result<Summary> {
    let page = replica_rt::cow::page_size();
    let mut state = vec![0u8; size];
    sys::touch_pages(&mut state, page);
    let mut h = histogram();
    for _ in 0..count {
        std::thread::sleep(gap);
        let (r, w) = replica_rt::sys::pipe().context("pipe")?;
        let t0 = replica_rt::sys::monotonic_ns();
        // SAFETY: the child below only writes its own copy of `state` (touch or one madvise),
        // writes one byte to a pipe and leaves by _exit: async-signal-safe only.
        let pid = unsafe { sys::fork() }.context("fork")?;
        if pid == 0 {
            // Child: async-signal-safe only (the bench has other threads).
            match own {
                Own::Touch => sys::touch_pages(&mut state, page),
                Own::Populate => {
                    if sys::populate_write(&mut state).is_err() {
                        sys::exit_now(1);
                    }
                }
            }
            let _ = replica_rt::sys::write(w.as_fd(), &[1]);
            sys::exit_now(0);
        }
        drop(w);
        let ready = replica_rt::sys::wait_readable(r.as_fd(), Duration::from_secs(30));
        let t1 = replica_rt::sys::monotonic_ns();
        let _ = replica_rt::sys::kill(pid, libc::SIGKILL);
        let _ = wait_child(pid);
        if !ready.context("waiting for the floor's child")? {
            bail!("the floor's child did not finish within 30 s");
        }
        h.record(t1 - t0)?;
        bar.inc(1);
    }
    std::hint::black_box(&state);
    Ok(Summary::of(&h))
}

fn wait_child(pid: libc::pid_t) -> Result<()> {
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    loop {
        match replica_rt::sys::reap(pid)? {
            Some(_) => return Ok(()),
            None if std::time::Instant::now() > deadline => bail!("child {pid} not reaped"),
            None => std::thread::sleep(Duration::from_micros(200)),
        }
    }
}

pub fn render(rows: &[Row]) -> String {
    let cells: Vec<Vec<String>> = rows
        .iter()
        .map(|r| {
            let extra = r.extra.as_ref();
            let get = |k: &str| extra.and_then(|e| e.get(k)).cloned();
            let num = |k: &str| get(k).and_then(|v| v.as_f64());
            let us = |k: &str| num(k).map(report::us).unwrap_or_default();
            let times = |x: f64| format!("{x:.2}");
            vec![
                report::bytes_name(r.size),
                r.count.to_string(),
                report::us(r.median_us),
                report::us(r.p99_us),
                report::us(r.max_us),
                r.floor_us.map(report::us).unwrap_or_default(),
                r.ratio.map(times).unwrap_or_default(),
                us("crash_detect_median_us"),
                us("in_service_median_us"),
                r.floor_us
                    .zip(num("in_service_median_us"))
                    .map(|(f, s)| times(s / f))
                    .unwrap_or_default(),
                get("by_exec").map(|v| v.to_string()).unwrap_or_default(),
                us("floor_madvise_us"),
                num("ratio_madvise").map(times).unwrap_or_default(),
            ]
        })
        .collect();
    report::table(
        &[
            "state",
            "restarts",
            "→ready µs",
            "p99 µs",
            "max µs",
            "floor µs",
            "×floor",
            "kill→crash µs",
            "in service µs",
            "×floor",
            "by exec",
            "floor (madvise) µs",
            "×floor (madvise)",
        ],
        &cells,
    )
}
