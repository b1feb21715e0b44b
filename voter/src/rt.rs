//! Applies the scheme of [`crate::sched`] to the voter and its replicas: SCHED_RR priorities
//! (or the nice values standing in for them), CPU pinning, and the raising of the replica whose
//! turn it is. A refusal is said once, with what to do about it, and the voter runs on with
//! what it has.

use std::fs::File;
use std::io::{self, Write};
use std::path::Path;

use replica_rt::sys;

use crate::plan::{CpuIdle, LockMemory, NiceFallback, VoterPlan, CPU_LATENCY_QOS};
use crate::sched::{self, Schedule};

/// What the voter may do to priorities, learned by trying.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    /// The component has no priority: leave policies and nice values alone.
    Untouched,
    /// SCHED_RR at the scheme's priorities.
    RoundRobin(u8),
    /// SCHED_RR refused: fixed nice values (no raising).
    Nice(NiceFallback),
}

/// Locks the voter's memory as the component's replicas lock theirs (`lock_memory`: every
/// page of its current mappings, or those it touches), so that no page fault delays a round
/// (the voter is in every one) and no page of its recovery code, run seldom, is reclaimed
/// meanwhile and read back from disk in the middle of a recovery. Neither flag is inherited by the replicas it
/// starts (cleared at `execve`). Called once the voter is set up (and, for a successor, has
/// adopted the replicas). A refusal is said once; the voter runs on unlocked.
pub fn lock_voter_memory(policy: LockMemory) {
    // Current mappings only: the voter sizes its buffers before its first round, and a later
    // allocation must not fail for passing a user's RLIMIT_MEMLOCK (`MCL_FUTURE` would).
    let locked = sys::lock_current_memory(policy == LockMemory::Used);
    match locked {
        Ok(()) => tracing::debug!(policy = policy.as_str(), "voter memory locked"),
        // Bootstrap said the limit once for the system.
        Err(e) if replica_rt::memory::lock_limit_said() => {
            tracing::debug!(error = %e, "the voter could not lock its memory; it runs unlocked")
        }
        Err(e) => tracing::warn!(
            error = %e,
            "the voter could not lock its memory (raise RLIMIT_MEMLOCK or run with \
             CAP_IPC_LOCK); it runs unlocked, so page faults may delay rounds"
        ),
    }
}

/// Keeps every CPU from sleeping when idle, for as long as the returned file stays open
/// (`cpu_idle: poll`; `halt`: nothing is asked, `None`). The voter holds it for its life and the
/// kernel withdraws the request when the file closes, so a voter that dies leaves no setting
/// behind, and its successor asks again. A refusal (not root, no such file) is said once; the
/// voter runs on and idle CPUs sleep as the kernel decides.
pub fn keep_cpus_polling(policy: CpuIdle) -> Option<File> {
    if policy == CpuIdle::Halt {
        return None;
    }
    match request_cpu_latency(Path::new(CPU_LATENCY_QOS), 0) {
        Ok(file) => {
            tracing::debug!("idle CPUs poll while the voter runs (cpu_idle: poll)");
            if s3res_protocol::machine::is_virtual() {
                // Measured on a 2-core KVM guest (docs/results.md, stop 54): the slowest of
                // 300,000 rounds 100–113 ms polling against 3–9 ms halting.
                tracing::info!(
                    "idle CPUs poll on a virtual machine (cpu_idle: poll): the host sees them \
                     always busy and may take one away for ~100 ms now and then (steal); \
                     see docs/real-time.md, \"Idle CPUs\""
                );
            }
            Some(file)
        }
        Err(e) => {
            let why = if e.kind() == io::ErrorKind::PermissionDenied {
                format!("writing {CPU_LATENCY_QOS} needs root")
            } else {
                format!("{CPU_LATENCY_QOS}: {e}")
            };
            tracing::warn!(
                "`cpu_idle: poll` could not be applied: {why}; idle CPUs sleep as the kernel \
                 decides, so a wake-up after idle may take longer"
            );
            None
        }
    }
}

/// Asks for a CPU wake-up latency of at most `max_us` through the PM QoS file at `path` (its
/// binary interface: one native-endian `i32`). 0 µs leaves cpuidle no state but polling.
fn request_cpu_latency(path: &Path, max_us: i32) -> io::Result<File> {
    let mut file = File::options().write(true).open(path)?;
    file.write_all(&max_us.to_ne_bytes())?;
    Ok(file)
}

#[derive(Debug)]
pub struct RealTime {
    mode: Mode,
    schedule: Schedule,
    /// Reactive or stream: where replicas rest (see [`sched::rest_priority`]).
    voting: crate::plan::Mode,
    cpus: Vec<usize>,
    voter_cpus: Vec<usize>,
    /// The CPUs the voter could use before it pinned itself: what an unpinned replica gets
    /// back when the voter is pinned (replicas inherit the voter's mask).
    start_cpus: Vec<usize>,
    nice: Option<NiceFallback>,
    affinity_warned: bool,
}

impl RealTime {
    pub fn new(plan: &VoterPlan) -> RealTime {
        let mode = match (plan.priority, plan.realtime, plan.nice) {
            (Some(p), true, _) => Mode::RoundRobin(p),
            // SCHED_RR refused; a component without a priority also gets a nice value then,
            // below every prioritized one (as SCHED_OTHER is below SCHED_RR).
            (_, false, Some(n)) => Mode::Nice(n),
            _ => Mode::Untouched,
        };
        RealTime {
            mode,
            schedule: plan.schedule,
            voting: plan.mode,
            cpus: plan.cpus.clone(),
            voter_cpus: sched::voter_cpus(&plan.cpus, plan.voter_cpu),
            start_cpus: sys::cpu_affinity(0).unwrap_or_default(),
            nice: plan.nice,
            affinity_warned: false,
        }
    }

    /// Whether the replica whose turn it is can be raised above its siblings (SCHED_RR works).
    pub fn can_raise(&self) -> bool {
        matches!(self.mode, Mode::RoundRobin(_))
    }

    /// The voter's own priority and CPUs. Called before any replica exists, so the replicas
    /// start from the voter's settings and are then set to their own.
    pub fn apply_to_voter(&mut self) {
        match self.mode {
            Mode::Untouched => {}
            Mode::RoundRobin(p) => {
                if let Err(e) = sys::set_round_robin(0, p.into()) {
                    self.refused(e);
                    self.apply_nice(0, |n| n.voter);
                }
            }
            Mode::Nice(n) => self.apply_nice_value(0, n.voter),
        }
        if !self.voter_cpus.is_empty() {
            let cpus = self.voter_cpus.clone();
            self.pin(0, &cpus, "the voter");
        }
        tracing::debug!(mode = ?self.mode, schedule = %self.schedule, cpus = ?self.voter_cpus, "voter scheduling applied");
    }

    /// Replica `slot`'s priority at rest and its CPU; for a replica just started by exec or
    /// adopted (a fork child takes the two at different moments: `Core::fork`).
    pub fn apply_to_replica(&mut self, pid: libc::pid_t, slot: usize) {
        self.set_replica_priority(pid, slot);
        self.place_replica(pid, slot);
    }

    /// Replica `slot`'s priority at rest: SCHED_RR at its level, or the replicas' nice value.
    pub fn set_replica_priority(&mut self, pid: libc::pid_t, slot: usize) {
        match self.mode {
            Mode::Untouched => {}
            Mode::RoundRobin(p) => {
                let prio = sched::rest_priority(p, slot, self.voting);
                if let Err(e) = sys::set_round_robin(pid, prio.into()) {
                    if !gone(&e) {
                        self.refused(e);
                        self.apply_nice(pid, |n| n.replicas);
                    }
                }
            }
            Mode::Nice(n) => self.apply_nice_value(pid, n.replicas),
        }
    }

    /// Replica `slot`'s CPUs (those the description gives it, or else those it was started
    /// with when the voter was pinned apart).
    pub fn place_replica(&mut self, pid: libc::pid_t, slot: usize) {
        match sched::replica_cpu(&self.cpus, slot) {
            Some(cpu) => self.pin(pid, &[cpu], "a replica"),
            None if !self.voter_cpus.is_empty() && !self.start_cpus.is_empty() => {
                let cpus = self.start_cpus.clone();
                self.pin(pid, &cpus, "a replica");
            }
            None => {}
        }
    }

    /// Raises `pid` above its siblings (the replica whose turn it is, or a recovery donor).
    /// Without SCHED_RR this does nothing: a nice value once raised cannot be lowered again.
    pub fn raise(&mut self, pid: libc::pid_t) {
        if let Mode::RoundRobin(p) = self.mode {
            self.set_rt(pid, sched::turn_priority(p));
        }
    }

    /// Puts replica `slot` (`pid`) back to its priority at rest.
    pub fn rest(&mut self, pid: libc::pid_t, slot: usize) {
        if let Mode::RoundRobin(p) = self.mode {
            self.set_rt(pid, sched::rest_priority(p, slot, self.voting));
        }
    }

    fn set_rt(&mut self, pid: libc::pid_t, prio: u8) {
        if let Err(e) = sys::set_rt_priority(pid, prio.into()) {
            if !gone(&e) {
                tracing::warn!(pid, priority = prio, error = %e, "could not change a replica's SCHED_RR priority");
            }
        }
    }

    /// SCHED_RR was refused although bootstrap's probe allowed it (or this voter was started
    /// by something else): say so once and fall back to the nice values.
    fn refused(&mut self, e: io::Error) {
        if let Mode::RoundRobin(p) = self.mode {
            tracing::warn!(
                priority = p,
                error = %e,
                "SCHED_RR refused; falling back to nice values that keep the priority order \
                 (no real-time guarantee, no raising of a replica's turn). Run as root or grant \
                 CAP_SYS_NICE (or raise RLIMIT_RTPRIO) to get SCHED_RR"
            );
            self.mode = match self.nice {
                Some(n) => Mode::Nice(n),
                None => Mode::Untouched,
            };
        }
    }

    fn apply_nice(&mut self, pid: libc::pid_t, pick: impl Fn(&NiceFallback) -> i32) {
        if let Mode::Nice(n) = self.mode {
            self.apply_nice_value(pid, pick(&n));
        }
    }

    fn apply_nice_value(&mut self, pid: libc::pid_t, nice: i32) {
        if let Err(e) = sys::set_nice(pid, nice) {
            if !gone(&e) {
                tracing::warn!(pid, nice, error = %e, "could not set a nice value");
            }
        }
    }

    fn pin(&mut self, pid: libc::pid_t, cpus: &[usize], who: &str) {
        if let Err(e) = sys::set_cpu_affinity(pid, cpus) {
            if gone(&e) || self.affinity_warned {
                return;
            }
            self.affinity_warned = true;
            tracing::warn!(
                ?cpus,
                error = %e,
                "could not pin {who} to its CPUs (is a cpuset narrower than the description?); \
                 running where the kernel puts it. Fix `cpus`/`voter_cpu` or the cpuset to pin"
            );
        }
    }
}

/// The process is gone already (its death is reported through its pidfd, not here).
fn gone(e: &io::Error) -> bool {
    e.raw_os_error() == Some(libc::ESRCH)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cpu_latency_request_is_one_native_i32_held_open() {
        let dir = std::env::temp_dir().join(format!("s3res-qos-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("qos");
        std::fs::write(&path, b"").unwrap();
        let held = request_cpu_latency(&path, 0).expect("request");
        assert_eq!(std::fs::read(&path).unwrap(), 0i32.to_ne_bytes());
        drop(held);
        let refused = request_cpu_latency(&dir.join("absent"), 0).unwrap_err();
        assert_eq!(refused.kind(), io::ErrorKind::NotFound);
        std::fs::remove_dir_all(&dir).unwrap();
        assert!(
            keep_cpus_polling(CpuIdle::Halt).is_none(),
            "halt asks for nothing"
        );
    }
}
