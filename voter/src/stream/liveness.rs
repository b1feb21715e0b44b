//! Hangs the deadlines cannot see. A stream deadline starts when one replica produces a frame
//! the others have not: if *every* replica hangs at once (two control-flow errors in a DMR
//! pair, three in a trio) nobody produces, no frame is owed, and the component would stall
//! with no fault recorded. So every `timeout_us` the voter also looks at what each replica did
//! since the last look, from `/proc`:
//!
//! * it produced a frame → alive;
//! * it blocked (its count of voluntary context switches grew: it slept waiting for input, or
//!   for its output pipe) → alive;
//! * it is asleep now → alive;
//! * otherwise, if it was on a CPU for at least a quarter of the interval, it has computed
//!   for a whole `timeout_us` without producing anything or waiting for anything: a `hang`.
//!
//! A replica that cannot run (a sibling spinning above it on a shared CPU) gains no CPU time
//! and is not blamed. The cost: a stream replica must not compute for longer than
//! `timeout_us` without producing a frame or blocking — the same bound reactive rounds put on
//! every answer.

use std::time::Duration;

use crate::clock::Instant;
use crate::replica::{cpu_time_ns, is_asleep, voluntary_switches};

/// What `/proc` said about one replica at one look.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sample {
    pub pid: libc::pid_t,
    /// Frames produced so far (the ledger's progress).
    pub progress: u64,
    /// Voluntary context switches (`/proc/PID/status`).
    pub blocked: u64,
    /// Time on a CPU, ns (`/proc/PID/schedstat`).
    pub cpu_ns: u64,
    /// Asleep (`S`) at the look.
    pub asleep: bool,
}

impl Sample {
    /// Reads one replica; `None` if the process is gone (its exit is seen elsewhere).
    pub fn take(pid: libc::pid_t, progress: u64) -> Option<Sample> {
        Some(Sample {
            pid,
            progress,
            blocked: voluntary_switches(pid)?,
            cpu_ns: cpu_time_ns(pid)?,
            asleep: is_asleep(pid),
        })
    }
}

/// The per-slot memory of the last look.
#[derive(Debug)]
pub struct Liveness {
    interval: Duration,
    last: Option<Instant>,
    samples: Vec<Option<Sample>>,
}

impl Liveness {
    pub fn new(replicas: usize, interval: Duration) -> Self {
        Liveness {
            interval,
            last: None,
            samples: vec![None; replicas],
        }
    }

    /// When the next look is due.
    pub fn next_look(&self, now: Instant) -> Instant {
        self.last.map_or(now, |t| t + self.interval)
    }

    /// Whether a look is due at `now`.
    pub fn due(&self, now: Instant) -> bool {
        now >= self.next_look(now)
    }

    /// Records `now` as the time of a look.
    pub fn looked(&mut self, now: Instant) {
        self.last = Some(now);
    }

    /// Compares `slot`'s new sample with the previous one of the same process and remembers
    /// it; `Some(ms on a CPU)` if the replica looks hung.
    pub fn update(&mut self, slot: usize, new: Option<Sample>) -> Option<u64> {
        let old = std::mem::replace(&mut self.samples[slot], new);
        let (old, new) = (old?, new?);
        verdict(&old, &new, self.interval)
    }

    /// Forgets `slot` (its process was replaced).
    pub fn forget(&mut self, slot: usize) {
        self.samples[slot] = None;
    }

    /// Moves the next look on: the voter was away (recovering), the replicas were not.
    pub fn restart(&mut self, now: Instant) {
        self.last = Some(now);
        self.samples.iter_mut().for_each(|s| *s = None);
    }
}

/// The rule of the module's comment: `Some(ms on a CPU)` if `new` shows a hang since `old`.
pub fn verdict(old: &Sample, new: &Sample, interval: Duration) -> Option<u64> {
    let ran = new.cpu_ns.saturating_sub(old.cpu_ns);
    let hung = old.pid == new.pid
        && new.progress == old.progress
        && new.blocked == old.blocked
        && !new.asleep
        && u128::from(ran) * 4 >= interval.as_nanos();
    hung.then_some(ran / 1_000_000)
}

#[cfg(test)]
mod tests {
    use super::*;

    const T: Duration = Duration::from_millis(100);

    fn sample(progress: u64, blocked: u64, cpu_ms: u64, asleep: bool) -> Sample {
        Sample {
            pid: 7,
            progress,
            blocked,
            cpu_ns: cpu_ms * 1_000_000,
            asleep,
        }
    }

    #[test]
    fn a_spinner_is_hung_and_a_busy_or_idle_replica_is_not() {
        let old = sample(5, 10, 0, false);
        // Ran 90 ms of 100, no frame, never blocked, running now: spinning.
        assert_eq!(verdict(&old, &sample(5, 10, 90, false), T), Some(90));
        // It produced a frame meanwhile.
        assert_eq!(verdict(&old, &sample(6, 10, 90, false), T), None);
        // It blocked at least once (waited for input or for its output pipe).
        assert_eq!(verdict(&old, &sample(5, 11, 90, false), T), None);
        // It sleeps now.
        assert_eq!(verdict(&old, &sample(5, 10, 90, true), T), None);
        // Runnable but starved (a spinner above it on its CPU): not its fault.
        assert_eq!(verdict(&old, &sample(5, 10, 3, false), T), None);
        // Another process in the slot.
        let mut other = sample(5, 10, 90, false);
        other.pid = 8;
        assert_eq!(verdict(&old, &other, T), None);
    }

    #[test]
    fn this_process_reads_as_alive() {
        let me = std::process::id() as libc::pid_t;
        let s = Sample::take(me, 0).expect("our own /proc entry");
        assert!(s.cpu_ns > 0);
        assert_eq!(Sample::take(-1, 0), None);
    }

    #[test]
    fn the_memory_compares_only_the_same_slots_looks() {
        let mut l = Liveness::new(2, T);
        assert_eq!(l.update(0, Some(sample(1, 1, 0, false))), None);
        assert_eq!(l.update(0, Some(sample(1, 1, 80, false))), Some(80));
        l.forget(0);
        assert_eq!(l.update(0, Some(sample(1, 1, 160, false))), None);
        assert_eq!(l.update(1, None), None);
    }
}
