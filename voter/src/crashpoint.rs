//! Crash points, for tests that must prove what a voter's successor finds in each window of
//! the journal's protocol (see "Lines" in `journal.rs`; `input-delivered`, between an input
//! frame's writes to the replicas and its take into the journal, `Core::deliver_next`; and
//! `fault-reported`, between a fault's event and its replica's leaving the table,
//! `held.rs`): with `S3RES_VOTER_CRASH_AT=POINT:N` in its environment, the first voter of a
//! component SIGKILLs itself the `N`th time it reaches `POINT`, as an injected fault would
//! kill it between those two system calls. A successor (`plan.adopt`) ignores it, so the
//! component carries on. Without the variable a point costs one relaxed load.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::OnceLock;

/// The environment variable: `POINT:N`.
pub const ENV_CRASH_AT: &str = "S3RES_VOTER_CRASH_AT";

/// The points, in the order an input frame (or a line) and its answer pass them.
pub const POINTS: [&str; 8] = [
    "line-staged",
    "line-given",
    "line-moved",
    "input-delivered",
    "round-committed",
    "answer-announced",
    "answer-read",
    "fault-reported",
];

static POINT: OnceLock<String> = OnceLock::new();
/// Passes left before the crash; 0: disarmed.
static LEFT: AtomicU64 = AtomicU64::new(0);

/// Arms the crash point the environment names, unless this voter succeeds another.
pub(crate) fn arm(adopting: bool) {
    let Ok(spec) = std::env::var(ENV_CRASH_AT) else {
        return;
    };
    let parsed = spec
        .split_once(':')
        .and_then(|(point, n)| Some((point, n.parse::<u64>().ok()?)))
        .filter(|(point, n)| POINTS.contains(point) && *n > 0);
    let Some((point, n)) = parsed else {
        tracing::warn!(
            "{ENV_CRASH_AT}={spec:?} ignored: want POINT:N with POINT one of {POINTS:?}"
        );
        return;
    };
    if adopting {
        return;
    }
    let _ = POINT.set(point.to_owned());
    LEFT.store(n, Ordering::Relaxed);
    tracing::warn!(point, n, "armed to kill itself (a test's crash point)");
}

/// The voter reached `point`: the armed pass kills it.
pub(crate) fn reached(point: &'static str) {
    if LEFT.load(Ordering::Relaxed) == 0 || POINT.get().is_none_or(|p| p != point) {
        return;
    }
    if LEFT.fetch_sub(1, Ordering::Relaxed) == 1 {
        let _ = replica_rt::sys::kill(std::process::id() as libc::pid_t, libc::SIGKILL);
    }
}
