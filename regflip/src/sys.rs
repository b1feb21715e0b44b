//! The syscall boundary of the register injector: typed ptrace, wait and clock wrappers. Every
//! `unsafe` block of this crate lives here, each in a small function with its safety argument.
//!
//! All functions act on one *thread* (`tid`): ptrace attaches to threads, not processes.

use std::io;
use std::mem::MaybeUninit;

pub use libc::{siginfo_t, user_fpregs_struct as FpRegs, user_regs_struct as Regs};

/// A thread id (equal to the pid for a process's main thread).
pub type Tid = libc::pid_t;

fn cvt(ret: libc::c_long) -> io::Result<libc::c_long> {
    if ret < 0 {
        Err(io::Error::last_os_error())
    } else {
        Ok(ret)
    }
}

/// `PTRACE_SEIZE`: become the tracer of `tid` without stopping it (no SIGSTOP is sent, so the
/// thread's parent sees nothing). With `PTRACE_O_TRACESYSGOOD`, so that a syscall-stop (only
/// ever asked for with [`resume_to_syscall`]) tells itself apart from a SIGTRAP.
pub fn seize(tid: Tid) -> io::Result<()> {
    // SAFETY: PTRACE_SEIZE reads no memory of ours; addr must be 0 and data is the option mask.
    cvt(unsafe {
        libc::ptrace(
            libc::PTRACE_SEIZE,
            tid,
            0usize,
            libc::PTRACE_O_TRACESYSGOOD as usize,
        )
    })?;
    Ok(())
}

/// [`seize`], and also trace every child `tid` forks from now on (`PTRACE_O_TRACEFORK`): the
/// fork is reported as a [`Stop::OtherEvent`] of `PTRACE_EVENT_FORK` (the child's pid from
/// [`event_message`]), and the child starts traced, in a [`Stop::Event`].
pub fn seize_following_forks(tid: Tid) -> io::Result<()> {
    let options = libc::PTRACE_O_TRACESYSGOOD | libc::PTRACE_O_TRACEFORK;
    // SAFETY: PTRACE_SEIZE reads no memory of ours; addr must be 0 and data is the option mask.
    cvt(unsafe { libc::ptrace(libc::PTRACE_SEIZE, tid, 0usize, options as usize) })?;
    Ok(())
}

/// `PTRACE_GETEVENTMSG`: for a `PTRACE_EVENT_FORK` stop, the new child's pid.
pub fn event_message(tid: Tid) -> io::Result<u64> {
    let mut msg: libc::c_ulong = 0;
    // SAFETY: the kernel writes one unsigned long to `data`, which points to one.
    cvt(unsafe {
        libc::ptrace(
            libc::PTRACE_GETEVENTMSG,
            tid,
            0usize,
            &mut msg as *mut libc::c_ulong,
        )
    })?;
    Ok(msg as u64)
}

/// `PTRACE_SYSCALL`, delivering `sig` (0 = none): run until the next system call is entered
/// or left (a [`Stop::Syscall`]).
pub fn resume_to_syscall(tid: Tid, sig: libc::c_int) -> io::Result<()> {
    // SAFETY: PTRACE_SYSCALL takes a signal number in `data`, no pointers.
    cvt(unsafe { libc::ptrace(libc::PTRACE_SYSCALL, tid, 0usize, sig as usize) })?;
    Ok(())
}

/// `PTRACE_INTERRUPT`: ask a seized thread to stop (reported by `waitpid` as a
/// `PTRACE_EVENT_STOP`).
pub fn interrupt(tid: Tid) -> io::Result<()> {
    // SAFETY: PTRACE_INTERRUPT takes no pointers; addr and data are ignored and passed as 0.
    cvt(unsafe { libc::ptrace(libc::PTRACE_INTERRUPT, tid, 0usize, 0usize) })?;
    Ok(())
}

/// `PTRACE_DETACH`, delivering `sig` if the thread is in a signal-delivery-stop (0 = none).
pub fn detach(tid: Tid, sig: libc::c_int) -> io::Result<()> {
    // SAFETY: PTRACE_DETACH takes a signal number in `data`, no pointers.
    cvt(unsafe { libc::ptrace(libc::PTRACE_DETACH, tid, 0usize, sig as usize) })?;
    Ok(())
}

/// `PTRACE_CONT`, delivering `sig` (0 = none).
pub fn cont(tid: Tid, sig: libc::c_int) -> io::Result<()> {
    // SAFETY: PTRACE_CONT takes a signal number in `data`, no pointers.
    cvt(unsafe { libc::ptrace(libc::PTRACE_CONT, tid, 0usize, sig as usize) })?;
    Ok(())
}

/// `PTRACE_SINGLESTEP` without delivering a signal.
pub fn single_step(tid: Tid) -> io::Result<()> {
    // SAFETY: PTRACE_SINGLESTEP takes a signal number (0) in `data`, no pointers.
    cvt(unsafe { libc::ptrace(libc::PTRACE_SINGLESTEP, tid, 0usize, 0usize) })?;
    Ok(())
}

/// `PTRACE_GETREGS`: the general-purpose registers, RIP, RFLAGS and segment registers.
pub fn get_regs(tid: Tid) -> io::Result<Regs> {
    let mut regs = MaybeUninit::<Regs>::uninit();
    // SAFETY: the kernel writes exactly one user_regs_struct to `data`, which points to one.
    cvt(unsafe { libc::ptrace(libc::PTRACE_GETREGS, tid, 0usize, regs.as_mut_ptr()) })?;
    // SAFETY: the call succeeded, so the kernel filled in the whole struct.
    Ok(unsafe { regs.assume_init() })
}

/// `PTRACE_SETREGS`.
pub fn set_regs(tid: Tid, regs: &Regs) -> io::Result<()> {
    // SAFETY: the kernel only reads one user_regs_struct from `data`, which points to one.
    cvt(unsafe { libc::ptrace(libc::PTRACE_SETREGS, tid, 0usize, regs as *const Regs) })?;
    Ok(())
}

/// `PTRACE_GETFPREGS`: the FXSAVE image (x87, MXCSR and XMM0–15 in `xmm_space`).
pub fn get_fpregs(tid: Tid) -> io::Result<FpRegs> {
    let mut regs = MaybeUninit::<FpRegs>::uninit();
    // SAFETY: the kernel writes exactly one user_fpregs_struct (512 bytes) to `data`.
    cvt(unsafe { libc::ptrace(libc::PTRACE_GETFPREGS, tid, 0usize, regs.as_mut_ptr()) })?;
    // SAFETY: the call succeeded, so the kernel filled in the whole struct.
    Ok(unsafe { regs.assume_init() })
}

/// `PTRACE_SETFPREGS`.
pub fn set_fpregs(tid: Tid, regs: &FpRegs) -> io::Result<()> {
    // SAFETY: the kernel only reads one user_fpregs_struct from `data`, which points to one.
    cvt(unsafe { libc::ptrace(libc::PTRACE_SETFPREGS, tid, 0usize, regs as *const FpRegs) })?;
    Ok(())
}

/// `PTRACE_GETSIGINFO`: the signal a thread in signal-delivery-stop is about to receive.
pub fn get_siginfo(tid: Tid) -> io::Result<siginfo_t> {
    let mut info = MaybeUninit::<siginfo_t>::uninit();
    // SAFETY: the kernel writes exactly one siginfo_t to `data`, which points to one.
    cvt(unsafe { libc::ptrace(libc::PTRACE_GETSIGINFO, tid, 0usize, info.as_mut_ptr()) })?;
    // SAFETY: the call succeeded, so the kernel filled in the whole struct.
    Ok(unsafe { info.assume_init() })
}

/// The kernel's signal mask of a thread: bit `n - 1` is signal `n`.
pub type SigMask = u64;

/// `PTRACE_GETSIGMASK` (request 0x420a, Linux 3.11+).
pub fn get_sigmask(tid: Tid) -> io::Result<SigMask> {
    let mut mask: SigMask = 0;
    // SAFETY: the kernel writes `addr` = 8 bytes (its sigset_t) to `data`, a valid u64.
    cvt(unsafe {
        libc::ptrace(
            0x420a,
            tid,
            std::mem::size_of::<SigMask>(),
            &mut mask as *mut SigMask,
        )
    })?;
    Ok(mask)
}

/// `PTRACE_SETSIGMASK` (request 0x420b). The kernel never blocks SIGKILL or SIGSTOP.
pub fn set_sigmask(tid: Tid, mask: SigMask) -> io::Result<()> {
    // SAFETY: the kernel reads `addr` = 8 bytes from `data`, a valid u64.
    cvt(unsafe {
        libc::ptrace(
            0x420b,
            tid,
            std::mem::size_of::<SigMask>(),
            &mask as *const SigMask,
        )
    })?;
    Ok(())
}

/// `PTRACE_PEEKDATA`: one aligned word of the tracee's memory.
pub fn peek_word(tid: Tid, addr: u64) -> io::Result<u64> {
    // PEEKDATA returns the word itself, so -1 is ambiguous: clear errno first and look at it.
    // SAFETY: __errno_location returns this thread's errno slot, valid for the thread's life.
    unsafe { *libc::__errno_location() = 0 };
    // SAFETY: with the glibc wrapper, PEEKDATA reads tracee memory and returns it; `data` unused.
    let word = unsafe { libc::ptrace(libc::PTRACE_PEEKDATA, tid, addr as usize, 0usize) };
    if word == -1 {
        let err = io::Error::last_os_error();
        if err.raw_os_error() != Some(0) {
            return Err(err);
        }
    }
    Ok(word as u64)
}

/// `rt_tgsigqueueinfo`: queue a signal with a full siginfo (so a `sigqueue` payload survives).
/// The kernel refuses `si_code >= 0` to other processes; callers fall back to [`tgkill`].
pub fn tgsigqueueinfo(tgid: Tid, tid: Tid, info: &siginfo_t) -> io::Result<()> {
    // SAFETY: the kernel reads one siginfo_t from the pointer, which points to one.
    cvt(unsafe {
        libc::syscall(
            libc::SYS_rt_tgsigqueueinfo,
            tgid,
            tid,
            info.si_signo,
            info as *const siginfo_t,
        )
    })?;
    Ok(())
}

/// `tgkill`: send `sig` to thread `tid` of thread group `tgid`.
pub fn tgkill(tgid: Tid, tid: Tid, sig: libc::c_int) -> io::Result<()> {
    // SAFETY: tgkill takes three integers and touches no memory of ours.
    cvt(unsafe { libc::syscall(libc::SYS_tgkill, tgid, tid, sig) })?;
    Ok(())
}

/// What `waitpid` reported about a traced thread.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stop {
    /// A `PTRACE_EVENT_STOP` (after `PTRACE_INTERRUPT`, or a group-stop) with its signal.
    Event { sig: libc::c_int },
    /// A SIGTRAP stop that is not an event (single-step completed, or a breakpoint).
    Trap,
    /// A syscall-entry- or syscall-exit-stop (after [`resume_to_syscall`]).
    Syscall,
    /// A signal-delivery-stop: the thread is about to receive `sig`.
    Signal { sig: libc::c_int },
    /// Any other ptrace event (`status >> 16`).
    OtherEvent { event: libc::c_int },
    /// The thread (process) exited with this status.
    Exited { code: libc::c_int },
    /// The thread (process) was killed by this signal.
    Killed { sig: libc::c_int },
}

/// `waitpid(tid, __WALL)`, retrying EINTR, decoded into a [`Stop`]. Blocks until the thread
/// changes state: this is how the injector waits, never by sleeping.
pub fn wait_stop(tid: Tid) -> io::Result<Stop> {
    let mut status: libc::c_int = 0;
    loop {
        // SAFETY: waitpid writes one c_int to `status`, which is a valid local.
        let ret = unsafe { libc::waitpid(tid, &mut status, libc::__WALL) };
        if ret >= 0 {
            break;
        }
        let err = io::Error::last_os_error();
        if err.kind() != io::ErrorKind::Interrupted {
            return Err(err);
        }
    }
    Ok(decode_status(status))
}

/// `waitpid(tid, __WALL | WNOHANG)` until the thread changes state or `deadline` (monotonic
/// ns) passes (`Ok(None)`): for a thread that runs, or waits on its input, for as long as it
/// likes. Looks every 20 µs at first, then less and less often, down to every 500 µs: a stop
/// that comes soon is met at once, and a long wait for input costs the machine little.
pub fn wait_stop_until(tid: Tid, deadline_ns: u64) -> io::Result<Option<Stop>> {
    let mut status: libc::c_int = 0;
    let mut pause = std::time::Duration::from_micros(20);
    loop {
        // SAFETY: waitpid writes one c_int to `status`, which is a valid local.
        let ret = unsafe { libc::waitpid(tid, &mut status, libc::__WALL | libc::WNOHANG) };
        if ret > 0 {
            return Ok(Some(decode_status(status)));
        }
        if ret < 0 {
            let err = io::Error::last_os_error();
            if err.kind() != io::ErrorKind::Interrupted {
                return Err(err);
            }
        }
        if replica_rt::sys::monotonic_ns() >= deadline_ns {
            return Ok(None);
        }
        std::thread::sleep(pause);
        pause = (pause * 5 / 4).min(std::time::Duration::from_micros(500));
    }
}

fn decode_status(status: libc::c_int) -> Stop {
    if libc::WIFEXITED(status) {
        return Stop::Exited {
            code: libc::WEXITSTATUS(status),
        };
    }
    if libc::WIFSIGNALED(status) {
        return Stop::Killed {
            sig: libc::WTERMSIG(status),
        };
    }
    let sig = libc::WSTOPSIG(status);
    match status >> 16 {
        0 if sig == libc::SIGTRAP | 0x80 => Stop::Syscall,
        0 if sig == libc::SIGTRAP => Stop::Trap,
        0 => Stop::Signal { sig },
        libc::PTRACE_EVENT_STOP => Stop::Event { sig },
        event => Stop::OtherEvent { event },
    }
}

/// An all-zero register state, for unit tests.
#[cfg(test)]
pub fn zeroed_state() -> (Regs, FpRegs) {
    // SAFETY: both structs are plain integers and integer arrays; all-zero is a valid value.
    unsafe { (std::mem::zeroed(), std::mem::zeroed()) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn status_decoding_tells_stops_apart() {
        // Layouts as the kernel builds them (wait(2)): exit code << 8, signal, stop = 0x7f.
        assert_eq!(decode_status(3 << 8), Stop::Exited { code: 3 });
        assert_eq!(
            decode_status(libc::SIGKILL),
            Stop::Killed { sig: libc::SIGKILL }
        );
        assert_eq!(decode_status((libc::SIGTRAP << 8) | 0x7f), Stop::Trap);
        assert_eq!(
            decode_status(((libc::SIGTRAP | 0x80) << 8) | 0x7f),
            Stop::Syscall
        );
        assert_eq!(
            decode_status((libc::SIGUSR1 << 8) | 0x7f),
            Stop::Signal { sig: libc::SIGUSR1 }
        );
        assert_eq!(
            decode_status((libc::PTRACE_EVENT_STOP << 16) | (libc::SIGTRAP << 8) | 0x7f),
            Stop::Event { sig: libc::SIGTRAP }
        );
    }
}
