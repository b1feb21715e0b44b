//! "The one furthest behind gets the CPU first" (S³RES VoterD): while replicas are out of
//! step, the laggard runs one step above its siblings; when they are in step again, it goes
//! back to where it was.
//!
//! A replica running a real-time policy (SCHED_RR/FIFO) gets its real-time priority + 1 (at
//! most 99); any other gets its nice value − [`NICE_STEP`]. Both need privileges the voter may
//! not have: the first refusal is logged (at debug) and boosting is off for the rest of the run, the
//! voter carries on without it. Like in S³RES this is best effort, never relied on for
//! correctness: on two cores three replicas still share the CPU with everything else.
//!
//! The system calls are replica-rt's ([`replica_rt::sys`], the project's syscall boundary).

use replica_rt::sys::{self, SchedPolicy};

/// How many nice levels a laggard running SCHED_OTHER is raised (about 3× the CPU weight).
pub const NICE_STEP: i32 = 5;

/// A replica's scheduling before it was boosted, to put back.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Base {
    RealTime { policy: i32, priority: i32 },
    Nice(i32),
}

#[derive(Debug, Default)]
pub struct Boost {
    /// The boosted process and how to restore it.
    current: Option<(libc::pid_t, Base)>,
    /// A refusal was seen: boosting is off.
    disabled: bool,
}

impl Boost {
    /// Makes `laggard` (a pid) the one boosted replica, or none.
    pub fn set(&mut self, laggard: Option<libc::pid_t>) {
        if self.disabled || self.current.map(|(pid, _)| pid) == laggard {
            return;
        }
        if let Some((pid, base)) = self.current.take() {
            // A replica that is gone cannot be restored; any other error was seen on raising.
            let _ = restore(pid, base);
        }
        let Some(pid) = laggard else { return };
        match raise(pid) {
            Ok(base) => self.current = Some((pid, base)),
            Err(e) if e.raw_os_error() == Some(libc::ESRCH) => {}
            Err(e) => {
                // Not a warning: this boost is used only without SCHED_RR, where bootstrap has
                // said once for the system what is missing and how to get it (or where no
                // priority was asked for at all); each stream voter saying it again was noise.
                tracing::debug!(
                    pid,
                    error = %e,
                    "cannot raise the priority of the replica furthest behind; stream mode carries on without (needs CAP_SYS_NICE or root)"
                );
                self.disabled = true;
            }
        }
    }

    /// Forgets a process that is gone (its slot was faulted).
    pub fn forget(&mut self, pid: libc::pid_t) {
        if self.current.is_some_and(|(p, _)| p == pid) {
            self.current = None;
        }
    }
}

fn raise(pid: libc::pid_t) -> std::io::Result<Base> {
    let SchedPolicy { policy, priority } = sys::sched_policy(pid)?;
    if policy == libc::SCHED_RR || policy == libc::SCHED_FIFO {
        sys::set_rt_priority(pid, (priority + 1).min(99))?;
        Ok(Base::RealTime { policy, priority })
    } else {
        let nice = sys::nice_of(pid)?;
        sys::set_nice(pid, (nice - NICE_STEP).max(-20))?;
        Ok(Base::Nice(nice))
    }
}

fn restore(pid: libc::pid_t, base: Base) -> std::io::Result<()> {
    match base {
        Base::RealTime { priority, .. } => sys::set_rt_priority(pid, priority),
        Base::Nice(nice) => sys::set_nice(pid, nice),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Boosting and restoring our own process: works as root, degrades (once) otherwise;
    /// either way the nice value ends where it began.
    #[test]
    fn boost_and_restore_round_trip() {
        let me = std::process::id() as libc::pid_t;
        let before = sys::nice_of(me).unwrap();
        let mut b = Boost::default();
        b.set(Some(me));
        if !b.disabled {
            assert_eq!(sys::nice_of(me).unwrap(), (before - NICE_STEP).max(-20));
        }
        b.set(None);
        assert_eq!(sys::nice_of(me).unwrap(), before);
    }
}
