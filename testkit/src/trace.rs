//! Catching a replica's fork child at an exact point of its restart, by ptrace: where a test
//! must act on a child between two of its steps, a race against the child's own speed (how
//! long a page walk takes on this machine today) is no test.
//!
//! [`catch_fork_child`] traces the candidate donors with `PTRACE_O_TRACEFORK`, lets the one
//! that forks go as soon as it has (the donors are otherwise left to run: every signal they
//! get meanwhile is passed on), and runs the child system call by system call until it enters
//! one of the calls asked for, where it stays stopped for as long as the test holds the
//! [`CaughtChild`]. A stopped tracee looks to everyone else (the voter) like a child that
//! stopped by itself; SIGKILL still ends it.
//!
//! All of it runs on the calling thread: ptrace requests come only from the tracer thread.

use s3res_regflip::sys::{self as ptrace, Stop};
use std::io;
use std::time::{Duration, Instant};

/// A fork child held in a syscall-entry stop by the test thread.
#[derive(Debug)]
pub struct CaughtChild {
    /// The donor that forked it.
    pub parent: i32,
    /// The child.
    pub pid: i32,
    /// The system call it is stopped at the entry of.
    pub call: i64,
    /// Reaped by us: its death was reported to us as its tracer.
    reaped: bool,
}

/// How long a step of the catch (a donor's fork, the child's next stop) may take.
const STEP: Duration = Duration::from_secs(20);

/// Traces `parents`, calls `go` (which makes one of them fork, e.g. by killing a sibling), and
/// catches the first fork child of any of them at the entry of one of `calls` (syscall numbers).
/// The parents are no longer traced when this returns. Panics with what went wrong.
pub fn catch_fork_child(parents: &[i32], calls: &[i64], go: impl FnOnce()) -> CaughtChild {
    let mut traced: Vec<i32> = Vec::new();
    for &p in parents {
        match ptrace::seize_following_forks(p) {
            Ok(()) => traced.push(p),
            Err(e) => {
                let err = format!("cannot trace donor {p}: {e}");
                release(&traced);
                panic!("{err}");
            }
        }
    }
    go();
    let (parent, child) = match wait_for_fork(&mut traced) {
        Ok(found) => found,
        Err(e) => {
            release(&traced);
            panic!("no fork child of {parents:?}: {e}");
        }
    };
    release(&traced);
    let mut caught = CaughtChild {
        parent,
        pid: child,
        call: -1,
        reaped: false,
    };
    // Dropped on a panic here: the child is killed and reaped.
    caught.call = run_to_call(child, calls).unwrap_or_else(|e| {
        panic!("fork child {child} of {parent} not caught at any of the calls {calls:?}: {e}")
    });
    caught
}

/// Polls the traced parents until one reports its fork; passes on whatever else stops them.
/// The parent that forked is detached and dropped from `traced`.
fn wait_for_fork(traced: &mut Vec<i32>) -> io::Result<(i32, i32)> {
    let deadline = Instant::now() + STEP;
    while Instant::now() < deadline {
        for i in 0..traced.len() {
            let p = traced[i];
            let Some(stop) = ptrace::wait_stop_until(p, replica_rt::sys::monotonic_ns())? else {
                continue;
            };
            match stop {
                Stop::OtherEvent { event } if event == libc::PTRACE_EVENT_FORK => {
                    let child = ptrace::event_message(p)? as i32;
                    traced.remove(i);
                    ptrace::detach(p, 0)?;
                    return Ok((p, child));
                }
                // The voter's RESTART, or any other signal: delivered as if nobody looked.
                Stop::Signal { sig } => ptrace::cont(p, sig)?,
                Stop::Exited { .. } | Stop::Killed { .. } => {
                    traced.remove(i);
                    break;
                }
                _ => ptrace::cont(p, 0)?,
            }
        }
        std::thread::sleep(Duration::from_micros(100));
    }
    Err(io::Error::new(
        io::ErrorKind::TimedOut,
        format!("none forked within {STEP:?}"),
    ))
}

/// Stops tracing `traced`: each is interrupted, and detached at its next stop (a signal it was
/// about to take is handed over with the detach).
fn release(traced: &[i32]) {
    for &p in traced {
        if ptrace::interrupt(p).is_err() {
            continue; // gone
        }
        match ptrace::wait_stop(p) {
            Ok(Stop::Signal { sig }) => {
                let _ = ptrace::detach(p, sig);
            }
            Ok(Stop::Exited { .. } | Stop::Killed { .. }) | Err(_) => {}
            Ok(Stop::OtherEvent { event }) if event == libc::PTRACE_EVENT_FORK => {
                // It forked meanwhile: its child is traced too, and let go at once.
                if let Ok(child) = ptrace::event_message(p) {
                    let child = child as i32;
                    let _ = ptrace::wait_stop(child);
                    let _ = ptrace::detach(child, 0);
                }
                let _ = ptrace::detach(p, 0);
            }
            Ok(_) => {
                let _ = ptrace::detach(p, 0);
            }
        }
    }
}

/// Runs the traced `child` from its first stop to a syscall-entry stop at one of `calls`,
/// passing on any signal it gets on the way. Returns the call it stopped at.
fn run_to_call(child: i32, calls: &[i64]) -> io::Result<i64> {
    // Entry and exit stops alternate; the child's first syscall stop is an entry.
    let mut entering = true;
    loop {
        let deadline = replica_rt::sys::monotonic_ns() + STEP.as_nanos() as u64;
        let Some(stop) = ptrace::wait_stop_until(child, deadline)? else {
            return Err(io::Error::new(
                io::ErrorKind::TimedOut,
                format!("no stop within {STEP:?}"),
            ));
        };
        match stop {
            Stop::Syscall => {
                let call = ptrace::get_regs(child)?.orig_rax as i64;
                if entering && calls.contains(&call) {
                    return Ok(call);
                }
                entering = !entering;
                ptrace::resume_to_syscall(child, 0)?;
            }
            Stop::Signal { sig } if sig != libc::SIGSTOP => ptrace::resume_to_syscall(child, sig)?,
            Stop::Exited { code } => {
                return Err(io::Error::other(format!("it exited with {code}")))
            }
            Stop::Killed { sig } => {
                return Err(io::Error::other(format!("it was killed by signal {sig}")))
            }
            // Its first stop (an event stop, as its parent was seized), or a SIGSTOP meant for it.
            _ => ptrace::resume_to_syscall(child, 0)?,
        }
    }
}

impl CaughtChild {
    /// Waits until the child has been killed by someone else (reported to us as its tracer), and
    /// reaps that report so that its parent can reap the child. Returns the signal it died of.
    pub fn wait_killed(&mut self, timeout: Duration) -> i32 {
        match self.wait_end(timeout) {
            Ok(Some(Stop::Killed { sig })) => sig,
            Ok(Some(Stop::Exited { code })) => {
                panic!("the caught child {} exited with {code}", self.pid)
            }
            Ok(_) => panic!(
                "the caught child {} was not killed in {timeout:?}",
                self.pid
            ),
            Err(e) => panic!("waiting for the caught child {}: {e}", self.pid),
        }
    }

    /// Waits up to `timeout` for the report of the child's end, passing over any other stop
    /// (a signal sent to it while it is held, such as the group's teardown: it stays held).
    /// `Ok(None)` if it has not ended by then.
    fn wait_end(&mut self, timeout: Duration) -> io::Result<Option<Stop>> {
        let deadline = replica_rt::sys::monotonic_ns() + timeout.as_nanos() as u64;
        while let Some(stop) = ptrace::wait_stop_until(self.pid, deadline)? {
            if matches!(stop, Stop::Killed { .. } | Stop::Exited { .. }) {
                self.reaped = true;
                return Ok(Some(stop));
            }
        }
        Ok(None)
    }
}

impl Drop for CaughtChild {
    /// A child still held (the test failed before it was killed) is killed and reaped here.
    fn drop(&mut self) {
        if !self.reaped {
            let _ = crate::kill_pid(self.pid, libc::SIGKILL);
            let _ = self.wait_end(Duration::from_secs(5));
        }
    }
}
