//! The system's priorities and placement as a whole: whether SCHED_RR can be had (found by
//! trying), the nice values that stand in for it when not, what every process will run at
//! (for `--check`), and applying it to the unprotected components. The voters apply the same
//! scheme ([`s3res_protocol::sched`]) to themselves and their replicas.

use std::fmt::Write as _;

use replica_rt::sys;
use s3res_protocol::plan::{CpuIdle, NiceFallback};
use s3res_protocol::sched::{self, Schedule};

use crate::plan::{ComponentPlan, SchedLines, SystemPlan};

/// What the system will run with.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SystemSched {
    /// Some component has a priority.
    pub prioritized: bool,
    /// Why SCHED_RR cannot be used (`None`: it can, or no component asks for it).
    pub refused: Option<String>,
    /// Per component, in plan order: the nice values used where SCHED_RR is refused.
    pub nice: Vec<Option<NiceFallback>>,
    /// More distinct priorities than nice values above bootstrap's own: the weakest share 19.
    pub merged: bool,
    /// This machine is a virtual machine (`machine::is_virtual`): polling idle CPUs
    /// (`cpu_idle: poll`) has a cost there that `--check` names.
    pub virtual_machine: bool,
}

impl SystemSched {
    /// Probes SCHED_RR (only if some component has a priority) and works out the fallback.
    pub fn for_system(plan: &SystemPlan) -> SystemSched {
        let prioritized = plan.components.iter().any(|c| c.priority.is_some());
        let refused = if prioritized {
            probe_round_robin().err()
        } else {
            None
        };
        let base = sys::nice_of(0).unwrap_or(0);
        let polls = plan.components.iter().any(|c| c.cpu_idle == CpuIdle::Poll);
        SystemSched {
            virtual_machine: polls && s3res_protocol::machine::is_virtual(),
            ..Self::with(plan, prioritized, refused, base)
        }
    }

    fn with(
        plan: &SystemPlan,
        prioritized: bool,
        refused: Option<String>,
        base: i32,
    ) -> SystemSched {
        if !prioritized {
            return SystemSched {
                prioritized,
                refused,
                nice: vec![None; plan.components.len()],
                merged: false,
                virtual_machine: false,
            };
        }
        // Levels, two per protected component (its voter, and its replicas represented by the
        // lowest of them), one per unprotected one. Components without a priority come below
        // every prioritized one, as SCHED_OTHER is below SCHED_RR: level 0.
        let mut levels = Vec::new();
        for c in &plan.components {
            let p = c.priority.unwrap_or(0);
            levels.push(p);
            let replicas = match c.priority {
                Some(p) if c.is_protected() => sched::replica_priority(p, c.replicas - 1),
                _ => p,
            };
            levels.push(replicas);
        }
        let (values, merged) = sched::nice_levels(&levels, base);
        let nice = values
            .chunks(2)
            .map(|v| {
                Some(NiceFallback {
                    voter: v[0],
                    replicas: v[1],
                })
            })
            .collect();
        SystemSched {
            prioritized,
            refused,
            nice,
            merged,
            virtual_machine: false,
        }
    }

    /// SCHED_RR is to be used.
    pub fn realtime(&self) -> bool {
        self.refused.is_none()
    }

    /// The nice values of component `index`, if they are to be applied: only where SCHED_RR
    /// is refused and some component has a priority.
    pub fn fallback(&self, index: usize) -> Option<NiceFallback> {
        if self.realtime() {
            None
        } else {
            self.nice.get(index).copied().flatten()
        }
    }

    /// Says once what is degraded and how to get it back.
    pub fn warn_once(&self) {
        if let Some(why) = &self.refused {
            tracing::warn!(
                "SCHED_RR refused ({why}): running with nice values that keep the priority order \
                 instead. That is no real-time guarantee (other processes can delay a component), \
                 and sequential rounds cannot raise the replica whose turn it is (each turn still \
                 has its own deadline). Run as root or grant CAP_SYS_NICE (or raise RLIMIT_RTPRIO \
                 to the highest priority used) to get SCHED_RR"
            );
            if self.merged {
                tracing::warn!(
                    "more distinct priorities than nice values above bootstrap's own: the lowest \
                     share nice 19, so their order is lost"
                );
            }
        }
    }

    /// Applies component `index`'s priority and CPUs to its process `pid` (an unprotected
    /// component; voters apply their own). A refusal is logged and the component runs on.
    pub fn apply_direct(&self, index: usize, c: &ComponentPlan, pid: libc::pid_t) {
        let result = match (c.priority, self.fallback(index)) {
            (Some(p), None) => sys::set_round_robin(pid, p.into()),
            (_, Some(n)) => sys::set_nice(pid, n.voter),
            (None, None) => Ok(()),
        };
        if let Err(e) = result {
            tracing::warn!(component = %c.name, pid, error = %e, "could not set the component's priority; it runs at the default");
        }
        if !c.cpus.is_empty() {
            if let Err(e) = sys::set_cpu_affinity(pid, &c.cpus) {
                tracing::warn!(component = %c.name, pid, cpus = ?c.cpus, error = %e, "could not pin the component to its CPUs; it runs where the kernel puts it");
            }
        }
    }

    /// `--check`'s lines for component `index`: the schedule, and each process's priority
    /// (or nice value) and CPUs.
    pub fn describe(&self, index: usize, c: &ComponentPlan, out: &mut String) {
        let nice = self.nice.get(index).copied().flatten();
        if !c.is_protected() {
            let prio = self.describe_priority(c.priority, nice.map(|n| n.voter), None);
            let _ = writeln!(out, "  process   component  {prio}, {}", cpu_text(&c.cpus));
            return;
        }
        let why = if c.schedule_auto {
            match c.schedule {
                Schedule::Sequential => format!(
                    " (auto: {} replicas share {})",
                    c.replicas,
                    cpu_text(&c.cpus)
                ),
                Schedule::Parallel if c.cpus.is_empty() => {
                    " (auto: replicas not pinned)".to_owned()
                }
                Schedule::Parallel => " (auto: one CPU per replica)".to_owned(),
            }
        } else {
            " (set in the description)".to_owned()
        };
        let _ = writeln!(out, "  schedule  {}{why}", c.schedule);
        let voter = self.describe_priority(c.priority, nice.map(|n| n.voter), None);
        let voter_cpus = sched::voter_cpus(&c.cpus, c.voter_cpu);
        let idle = match c.cpu_idle {
            CpuIdle::Poll => format!(
                "; keeps idle CPUs polling (cpu_idle: poll, needs root{})",
                // Measured on a 2-core KVM guest (docs/results.md, stop 54).
                if self.virtual_machine {
                    "; on this virtual machine the host may take a polling CPU away for ~100 ms \
                     now and then, see docs/real-time.md, \"Idle CPUs\""
                } else {
                    ""
                }
            ),
            CpuIdle::Halt => String::new(),
        };
        let spin = if c.voter_spins() {
            format!(
                "; looks for answers up to {} µs before it sleeps (spin_us)",
                c.spin_us
            )
        } else {
            String::new()
        };
        let _ = writeln!(
            out,
            "  process   voter      {voter}, {}{idle}{spin}",
            cpu_text(&voter_cpus)
        );
        for slot in 0..c.replicas {
            let turn = (c.schedule == Schedule::Sequential).then_some(slot);
            let prio = self.describe_priority(
                c.priority.map(|p| sched::rest_priority(p, slot, c.mode)),
                nice.map(|n| n.replicas),
                turn.and(c.priority.map(sched::turn_priority)),
            );
            let cpu = match sched::replica_cpu(&c.cpus, slot) {
                Some(cpu) => format!("CPU {cpu}"),
                None => "any CPU".to_owned(),
            };
            let _ = writeln!(out, "  process   replica {slot:<2} {prio}, {cpu}");
        }
    }

    fn describe_priority(&self, rt: Option<u8>, nice: Option<i32>, turn: Option<u8>) -> String {
        match (rt, self.realtime(), nice) {
            (Some(p), true, _) => match turn {
                Some(t) => format!("SCHED_RR {p} ({t} if its turn is kept off the CPU)"),
                None => format!("SCHED_RR {p}"),
            },
            (Some(p), false, Some(n)) => format!("nice {n} (instead of SCHED_RR {p}: refused)"),
            (None, false, Some(n)) => {
                format!("nice {n} (no priority: below every prioritized process)")
            }
            _ => "default priority (SCHED_OTHER)".to_owned(),
        }
    }

    /// One line for `--check` about SCHED_RR itself.
    pub fn headline(&self) -> Option<String> {
        if !self.prioritized {
            return None;
        }
        Some(match &self.refused {
            None => "real-time SCHED_RR available".to_owned(),
            Some(why) => format!(
                "real-time SCHED_RR refused ({why}); nice values keep the order instead \
                 (run as root or grant CAP_SYS_NICE)"
            ),
        })
    }
}

impl SchedLines for SystemSched {
    fn headline(&self) -> Option<String> {
        SystemSched::headline(self)
    }

    fn describe(&self, index: usize, c: &ComponentPlan, out: &mut String) {
        SystemSched::describe(self, index, c, out)
    }
}

fn cpu_text(cpus: &[usize]) -> String {
    match cpus {
        [] => "any CPU".to_owned(),
        [c] => format!("CPU {c}"),
        _ => {
            let list: Vec<String> = cpus.iter().map(usize::to_string).collect();
            format!("CPUs {}", list.join(", "))
        }
    }
}

/// Whether this process may use SCHED_RR, found by switching itself to it for a moment (this
/// covers CAP_SYS_NICE, RLIMIT_RTPRIO and a cgroup without real-time runtime alike). Its own
/// policy is put back at once.
fn probe_round_robin() -> Result<(), String> {
    let before = sys::sched_policy(0).map_err(|e| e.to_string())?;
    if before.is_round_robin() || before.policy == libc::SCHED_FIFO {
        return Ok(());
    }
    match sys::set_round_robin(0, 1) {
        Ok(()) => {
            if let Err(e) = sys::set_normal_policy(0) {
                tracing::warn!(error = %e, "could not put bootstrap back to SCHED_OTHER after probing SCHED_RR");
            }
            Ok(())
        }
        Err(e) => Err(e.to_string()),
    }
}

/// Where bootstrap's events reader may run: each CPU bootstrap may run on (`allowed`) that no
/// replica of a protected component is pinned to. Empty, meaning where bootstrap runs, where no
/// replica is pinned or every allowed CPU has one.
///
/// The reader is time-shared and wakes at each event the voters write. Left to the kernel it
/// lands on an idle CPU, often the replicas': a fault's event woke it there just before the
/// voter asked a donor on that CPU to fork, and waking the donor then took an interrupt
/// between CPUs (on a virtual machine, a trap to the host), and the reader shared the CPU
/// with the fork and the copy that followed (measured with `s3res-bench`'s own reader: a
/// 256 KiB restart 10–30 µs slower; docs/results.md, stop 36).
pub fn events_reader_cpus(plan: &SystemPlan, allowed: &[usize]) -> Vec<usize> {
    let replica_cpus: Vec<usize> = plan
        .components
        .iter()
        .filter(|c| c.is_protected())
        .flat_map(|c| (0..c.replicas).filter_map(|slot| sched::replica_cpu(&c.cpus, slot)))
        .collect();
    if replica_cpus.is_empty() {
        return Vec::new();
    }
    allowed
        .iter()
        .copied()
        .filter(|c| !replica_cpus.contains(c))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::description::{self, HostContext};

    fn plan(text: &str) -> SystemPlan {
        let dir = tempfile::tempdir().unwrap();
        let exe = dir.path().join("run.sh");
        std::fs::write(&exe, "#!/bin/sh\n").unwrap();
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&exe, std::fs::Permissions::from_mode(0o755)).unwrap();
        let mut ctx = HostContext::for_file(&dir.path().join("s.json"));
        ctx.cpus = vec![0, 1];
        description::parse("s.json", text, &ctx).unwrap()
    }

    const SYSTEM: &str = r#"{ "name": "n", "components": {
        "a": { "exec": "./run.sh", "priority": 40 },
        "b": { "exec": "./run.sh", "redundancy": "tmr", "timeout_us": 100, "priority": 30,
               "cpus": [0, 1], "voter_cpu": 1, "cpu_idle": "poll" },
        "c": { "exec": "./run.sh" } },
      "channels": [ { "from": "a.out", "to": "b.in" }, { "from": "b.out", "to": "c.in" } ] }"#;

    #[test]
    fn fallback_nice_values_keep_the_order_of_every_process() {
        let p = plan(SYSTEM);
        let s = SystemSched::with(&p, true, Some("EPERM".into()), 0);
        let n: Vec<NiceFallback> = s.nice.iter().map(|n| n.unwrap()).collect();
        // a 40 > b's voter 30 > b's replicas (26..28) > c (no priority).
        assert_eq!(
            (n[0].voter, n[1].voter, n[1].replicas, n[2].voter),
            (0, 1, 2, 3)
        );
        assert_eq!(s.fallback(1), Some(n[1]));
        let rt = SystemSched::with(&p, true, None, 0);
        assert_eq!(rt.fallback(1), None);
    }

    #[test]
    fn check_lines_name_every_process_with_priority_and_cpu() {
        let p = plan(SYSTEM);
        let s = SystemSched::with(&p, true, None, 0);
        let mut out = String::new();
        s.describe(1, &p.components[1], &mut out);
        assert!(
            out.contains("schedule  sequential (auto: 3 replicas share CPUs 0, 1)"),
            "{out}"
        );
        assert!(
            out.contains(
                "process   voter      SCHED_RR 30, CPU 1; keeps idle CPUs polling (cpu_idle: poll, needs root)"
            ),
            "{out}"
        );
        assert!(
            out.contains(
                "process   replica 0  SCHED_RR 28 (29 if its turn is kept off the CPU), CPU 0"
            ),
            "{out}"
        );
        assert!(
            out.contains(
                "process   replica 2  SCHED_RR 26 (29 if its turn is kept off the CPU), CPU 0"
            ),
            "{out}"
        );
        let refused = SystemSched::with(&p, true, Some("EPERM".into()), 0);
        let mut out = String::new();
        refused.describe(0, &p.components[0], &mut out);
        assert!(
            out.contains("nice 0 (instead of SCHED_RR 40: refused), any CPU"),
            "{out}"
        );
    }

    /// The `--check` line of the second component's voter.
    fn voter_line_of(s: &SystemSched, p: &SystemPlan) -> String {
        let mut out = String::new();
        s.describe(1, &p.components[1], &mut out);
        out.lines()
            .find(|l| l.contains("process   voter"))
            .unwrap()
            .trim()
            .to_owned()
    }

    #[test]
    fn check_lines_say_what_polling_costs_on_a_virtual_machine() {
        let p = plan(SYSTEM);
        let voter_line = |virtual_machine: bool| {
            let s = SystemSched {
                virtual_machine,
                ..SystemSched::with(&p, true, None, 0)
            };
            voter_line_of(&s, &p)
        };
        assert_eq!(
            voter_line(false),
            "process   voter      SCHED_RR 30, CPU 1; keeps idle CPUs polling (cpu_idle: poll, \
             needs root)"
        );
        assert_eq!(
            voter_line(true),
            "process   voter      SCHED_RR 30, CPU 1; keeps idle CPUs polling (cpu_idle: poll, \
             needs root; on this virtual machine the host may take a polling CPU away for ~100 \
             ms now and then, see docs/real-time.md, \"Idle CPUs\")"
        );
        // Only a system that polls asks the machine.
        let halting = plan(&SYSTEM.replace(r#", "cpu_idle": "poll""#, ""));
        assert!(!SystemSched::for_system(&halting).virtual_machine);
        assert_eq!(
            SystemSched::for_system(&p).virtual_machine,
            s3res_protocol::machine::is_virtual()
        );
    }

    #[test]
    fn check_lines_say_where_the_voter_spins() {
        let voter_line = |extra: &str| {
            let p = plan(&format!(
                r#"{{ "name": "n", "components": {{ "a": {{ "exec": "./run.sh" }},
                "b": {{ "exec": "./run.sh", "redundancy": "tmr", "timeout_us": 100,
                       "priority": 30{extra} }} }},
                "channels": [ {{ "from": "a.out", "to": "b.in" }} ] }}"#
            ));
            voter_line_of(&SystemSched::with(&p, true, None, 0), &p)
        };
        assert_eq!(
            voter_line(r#", "cpus": [1], "voter_cpu": 0"#),
            "process   voter      SCHED_RR 30, CPU 0; looks for answers up to 50 µs before it \
             sleeps (spin_us)"
        );
        assert_eq!(
            voter_line(r#", "cpus": [1], "voter_cpu": 0, "spin_us": 0"#),
            "process   voter      SCHED_RR 30, CPU 0"
        );
        // Sharing a CPU with a replica, or not pinned: no spin, nothing said.
        assert_eq!(
            voter_line(r#", "cpus": [0, 1], "voter_cpu": 1"#),
            "process   voter      SCHED_RR 30, CPU 1"
        );
        assert_eq!(voter_line(""), "process   voter      SCHED_RR 30, any CPU");
    }

    #[test]
    fn the_events_reader_keeps_off_the_replicas_cpus() {
        // b's replicas on CPUs 0 and 1: nowhere is free, the reader may run anywhere.
        assert_eq!(
            events_reader_cpus(&plan(SYSTEM), &[0, 1]),
            Vec::<usize>::new()
        );
        let pinned = SYSTEM.replace(
            r#""cpus": [0, 1], "voter_cpu": 1"#,
            r#""cpus": [1], "voter_cpu": 0"#,
        );
        assert_eq!(events_reader_cpus(&plan(&pinned), &[0, 1]), vec![0]);
        assert_eq!(
            events_reader_cpus(&plan(&pinned), &[0, 1, 2, 3]),
            vec![0, 2, 3]
        );
        // Bootstrap itself kept off CPU 0 (a cpuset, taskset): no CPU left, so where it runs.
        assert_eq!(
            events_reader_cpus(&plan(&pinned), &[1]),
            Vec::<usize>::new()
        );
        // Nothing pinned: anywhere, as before.
        let unpinned = SYSTEM.replace(r#""cpus": [0, 1], "voter_cpu": 1, "#, "");
        assert_eq!(
            events_reader_cpus(&plan(&unpinned), &[0, 1]),
            Vec::<usize>::new()
        );
    }
}
