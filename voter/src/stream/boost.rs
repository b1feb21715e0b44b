//! "The one furthest behind gets the CPU first" (S³RES VoterD): while replicas are out of
//! step, the laggard runs one step above its siblings; when they are in step again, it goes
//! back to where it was.
//!
//! A replica running a real-time policy (SCHED_RR/FIFO) gets its real-time priority + 1 (at
//! most 99); any other gets its nice value − [`NICE_STEP`]. Both need privileges the voter may
//! not have: the first refusal is logged once and boosting is off for the rest of the run, the
//! voter carries on without it. Like in S³RES this is best effort, never relied on for
//! correctness: on two cores three replicas still share the CPU with everything else.
//!
//! The system calls sit in [`sys`] below, each a small function with its safety argument
//! (`replica-rt/src/sys.rs` gets scheduling wrappers of its own in a parallel change; these can
//! move there).

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
                tracing::warn!(
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
    let policy = sys::scheduler(pid)?;
    if policy == libc::SCHED_RR || policy == libc::SCHED_FIFO {
        let priority = sys::rt_priority(pid)?;
        sys::set_rt_priority(pid, (priority + 1).min(99))?;
        Ok(Base::RealTime { policy, priority })
    } else {
        let nice = sys::nice(pid)?;
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

/// The scheduling system calls boosting needs.
mod sys {
    use std::io;

    fn cvt(ret: libc::c_int) -> io::Result<libc::c_int> {
        if ret < 0 {
            Err(io::Error::last_os_error())
        } else {
            Ok(ret)
        }
    }

    /// The scheduling policy of `pid`.
    pub fn scheduler(pid: libc::pid_t) -> io::Result<i32> {
        // SAFETY: integer argument only; touches no memory of ours.
        cvt(unsafe { libc::sched_getscheduler(pid) })
    }

    /// The real-time priority of `pid` (0 under SCHED_OTHER).
    pub fn rt_priority(pid: libc::pid_t) -> io::Result<i32> {
        let mut param = libc::sched_param { sched_priority: 0 };
        // SAFETY: `param` is a valid, writable sched_param for the duration of the call.
        cvt(unsafe { libc::sched_getparam(pid, &mut param) })?;
        Ok(param.sched_priority)
    }

    /// Sets the real-time priority of `pid`, keeping its policy.
    pub fn set_rt_priority(pid: libc::pid_t, priority: i32) -> io::Result<()> {
        let param = libc::sched_param {
            sched_priority: priority,
        };
        // SAFETY: `param` is a valid sched_param, only read by the kernel.
        cvt(unsafe { libc::sched_setparam(pid, &param) }).map(drop)
    }

    /// The nice value of `pid`.
    pub fn nice(pid: libc::pid_t) -> io::Result<i32> {
        // getpriority may legitimately return -1, so errno is cleared first and checked after.
        // SAFETY: __errno_location returns this thread's errno slot, always valid.
        unsafe { *libc::__errno_location() = 0 };
        // SAFETY: integer arguments only.
        let nice = unsafe { libc::getpriority(libc::PRIO_PROCESS, pid as libc::id_t) };
        // SAFETY: as above.
        if nice == -1 && unsafe { *libc::__errno_location() } != 0 {
            return Err(io::Error::last_os_error());
        }
        Ok(nice)
    }

    /// Sets the nice value of `pid`.
    pub fn set_nice(pid: libc::pid_t, nice: i32) -> io::Result<()> {
        // SAFETY: integer arguments only.
        cvt(unsafe { libc::setpriority(libc::PRIO_PROCESS, pid as libc::id_t, nice) }).map(drop)
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
        let before = sys::nice(me).unwrap();
        let mut b = Boost::default();
        b.set(Some(me));
        if !b.disabled {
            assert_eq!(sys::nice(me).unwrap(), (before - NICE_STEP).max(-20));
        }
        b.set(None);
        assert_eq!(sys::nice(me).unwrap(), before);
    }
}
