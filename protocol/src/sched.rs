//! Priorities, CPU placement and the round-scheduling strategy of a protected component
//! (S³RES §3.2, §4.2): the scheme in one place, used by the voter to apply it and by bootstrap
//! to validate it and print it (`--check`).
//!
//! **Priorities.** A protected component of priority `P` with `n` replicas runs its voter at
//! `P` (SCHED_RR), replica `i` at rest at `P - 2 - i`: distinct, all below the voter, so a
//! replica hogging a CPU never starves the voter that must detect it. `P - 1` is the turn
//! level: a sequential turn kept off its CPU is raised to it, and a recovery donor while it
//! forks. Hence `P >= n + 2` ([`min_priority`]).
//!
//! **Placement.** With `cpus = [c0, c1, ...]`, replica `i` is pinned to `cpus[i % len]`; the
//! voter to `voter_cpu` if given, else to the whole list. Without `cpus`, nothing is pinned.
//!
//! **Strategies.** [`Schedule::Parallel`]: every replica gets the input at once and the round
//! has one deadline; a replica that has not answered by then is the hung one. This is exact
//! only when the replicas do not share a CPU. [`Schedule::Sequential`]: every replica still
//! gets the input at once, but only one replica at a time has its *turn*, with its own
//! deadline of `timeout_us`; when it has answered (or is found faulty), the next one's turn
//! begins. Turns go in slot order, which is the order of the resting priorities, so a turn is
//! raised to `P - 1` only if the voter finds it kept off its CPU. A hung replica is then exactly
//! the one whose turn it was. `auto` picks sequential when the placement puts two replicas on
//! one CPU ([`choose`]).

use serde::{Deserialize, Serialize};

/// How the replicas of a round are given the CPU and timed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Schedule {
    /// All replicas at once under one deadline (replicas on distinct CPUs).
    #[default]
    Parallel,
    /// One replica's turn at a time, raised above its siblings, each turn with its own
    /// deadline (replicas sharing a CPU).
    Sequential,
}

impl std::fmt::Display for Schedule {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Schedule::Parallel => "parallel",
            Schedule::Sequential => "sequential",
        })
    }
}

/// The lowest priority a protected component with `replicas` replicas may have: the voter,
/// the turn level, and one distinct level per replica, all at least 1.
pub fn min_priority(replicas: usize) -> u8 {
    (replicas + 2).min(99) as u8
}

/// SCHED_RR priority of a sequential turn kept off its CPU (and of a recovery donor).
pub fn turn_priority(priority: u8) -> u8 {
    priority.saturating_sub(1).max(1)
}

/// SCHED_RR priority of replica `slot` at rest.
pub fn replica_priority(priority: u8, slot: usize) -> u8 {
    let below = 2 + slot.min(97) as u8;
    priority.saturating_sub(below).max(1)
}

/// SCHED_RR priority of replica `slot` at rest in `mode`. Reactive replicas rest at distinct
/// levels (a sequential turn raises one above the others). Stream replicas all rest at the top
/// one: stream mode has no turns, and replicas sharing a CPU at distinct levels would let one
/// that spins starve the others before any of them produced a frame — then nobody is ahead,
/// no deadline runs, and the hang is never seen. At one level SCHED_RR shares the CPU round
/// robin, the spinner falls behind, and the laggard's deadline names it.
pub fn rest_priority(priority: u8, slot: usize, mode: crate::plan::Mode) -> u8 {
    match mode {
        crate::plan::Mode::Reactive => replica_priority(priority, slot),
        crate::plan::Mode::Stream => replica_priority(priority, 0),
    }
}

/// The CPU replica `slot` is pinned to, if the component lists CPUs.
pub fn replica_cpu(cpus: &[usize], slot: usize) -> Option<usize> {
    (!cpus.is_empty()).then(|| cpus[slot % cpus.len()])
}

/// The voter's CPUs: `voter_cpu` if given, else the component's list (empty: not pinned).
pub fn voter_cpus(cpus: &[usize], voter_cpu: Option<usize>) -> Vec<usize> {
    match voter_cpu {
        Some(c) => vec![c],
        None => cpus.to_vec(),
    }
}

/// Whether the voter has a CPU that none of its replicas runs on: the replicas are pinned
/// (`cpus` given) and `voter_cpu` is not among them. Only such a voter spins for answers
/// (`spin_us`).
pub fn voter_apart(cpus: &[usize], voter_cpu: Option<usize>) -> bool {
    voter_cpu.is_some_and(|v| !cpus.is_empty() && !cpus.contains(&v))
}

/// Whether the placement puts two replicas on one CPU: only when they are pinned
/// (`cpus` given) to fewer CPUs than there are replicas.
pub fn replicas_share_a_cpu(replicas: usize, cpus: &[usize]) -> bool {
    !cpus.is_empty() && replicas > cpus.len()
}

/// `auto`: sequential when replicas share a CPU, else parallel. Unpinned replicas are left to
/// the kernel's load balancing and run in parallel; ask for `sequential` to have them timed
/// one at a time anyway.
pub fn choose(replicas: usize, cpus: &[usize]) -> Schedule {
    if replicas_share_a_cpu(replicas, cpus) {
        Schedule::Sequential
    } else {
        Schedule::Parallel
    }
}

/// The nice values that stand in for SCHED_RR priorities when those are refused: distinct
/// priority levels, highest first, get `base`, `base + 1`, ... (capped at 19). Only raising a
/// nice value needs no privilege, so `base` is the caller's own nice value and every level is
/// at or above it. Returns the value for each level of `levels` (in the given order) and
/// whether the cap merged some levels.
pub fn nice_levels(levels: &[u8], base: i32) -> (Vec<i32>, bool) {
    let mut distinct: Vec<u8> = levels.to_vec();
    distinct.sort_unstable_by(|a, b| b.cmp(a));
    distinct.dedup();
    let mut merged = false;
    let nice_of = |p: u8| {
        let rank = distinct.iter().position(|&d| d == p).unwrap_or(0) as i32;
        base.saturating_add(rank)
    };
    let values = levels
        .iter()
        .map(|&p| {
            let n = nice_of(p);
            if n > 19 {
                merged = true;
            }
            n.min(19)
        })
        .collect();
    (values, merged)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paper_example_voter_30_replicas_28_27_26() {
        assert_eq!(turn_priority(30), 29);
        let rest: Vec<u8> = (0..3).map(|s| replica_priority(30, s)).collect();
        assert_eq!(rest, [28, 27, 26]);
        assert_eq!(min_priority(3), 5);
        // At the minimum every level is still distinct and at least 1.
        let rest: Vec<u8> = (0..3).map(|s| replica_priority(5, s)).collect();
        assert_eq!(rest, [3, 2, 1]);
    }

    #[test]
    fn placement_spreads_replicas_round_robin_over_the_cpus() {
        let cpus = [1, 0];
        let placed: Vec<Option<usize>> = (0..3).map(|s| replica_cpu(&cpus, s)).collect();
        assert_eq!(placed, [Some(1), Some(0), Some(1)]);
        assert_eq!(replica_cpu(&[], 0), None);
        assert_eq!(voter_cpus(&cpus, None), [1, 0]);
        assert_eq!(voter_cpus(&cpus, Some(0)), [0]);
    }

    #[test]
    fn auto_is_sequential_only_when_pinned_replicas_share_a_cpu() {
        assert_eq!(choose(3, &[0, 1]), Schedule::Sequential);
        assert_eq!(choose(3, &[0]), Schedule::Sequential);
        assert_eq!(choose(2, &[0, 1]), Schedule::Parallel);
        assert_eq!(choose(3, &[0, 1, 2]), Schedule::Parallel);
        assert_eq!(choose(3, &[]), Schedule::Parallel);
    }

    #[test]
    fn nice_levels_keep_the_order_from_the_callers_own_value() {
        let (n, merged) = nice_levels(&[40, 30, 26, 20, 30], 0);
        assert_eq!(n, [0, 1, 2, 3, 1]);
        assert!(!merged);
        let (n, merged) = nice_levels(&[50, 40], 18);
        assert_eq!(n, [18, 19]);
        assert!(!merged);
        let (n, merged) = nice_levels(&[50, 40, 30], 18);
        assert_eq!(n, [18, 19, 19]);
        assert!(merged);
    }
}
