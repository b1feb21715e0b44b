//! The bench's syscall boundary: what `replica_rt::sys` does not already wrap. Each function is
//! small and says why its `unsafe` block is sound.

use std::io;
use std::os::unix::process::CommandExt;
use std::process::Command;
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};

fn cvt(r: libc::c_int) -> io::Result<libc::c_int> {
    if r < 0 {
        Err(io::Error::last_os_error())
    } else {
        Ok(r)
    }
}

/// Makes the child of `cmd` receive SIGKILL when the bench dies, so that a bench killed by
/// SIGKILL (which no guard can catch) does not leave a voter running.
pub fn kill_child_with_parent(cmd: &mut Command) {
    // SAFETY: the closure runs in the forked child before exec and only calls prctl, which is
    // async-signal-safe; it neither allocates nor takes a lock.
    unsafe {
        cmd.pre_exec(|| {
            cvt(libc::prctl(
                libc::PR_SET_PDEATHSIG,
                libc::SIGKILL as libc::c_ulong,
                0,
                0,
                0,
            ))?;
            Ok(())
        });
    }
}

/// `kill(-pgid, sig)`: the whole process group.
pub fn kill_group(pgid: libc::pid_t, sig: libc::c_int) -> io::Result<()> {
    // SAFETY: killpg takes two integers and touches no memory of ours.
    cvt(unsafe { libc::killpg(pgid, sig) }).map(|_| ())
}

/// Scheduling of one process (or of the calling thread with pid 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Policy {
    /// SCHED_OTHER, the default time-sharing class.
    Other,
    /// SCHED_RR at this priority (1..=99).
    RoundRobin(i32),
}

/// `sched_setscheduler(pid, policy)`; pid 0 is the calling thread.
pub fn set_policy(pid: libc::pid_t, policy: Policy) -> io::Result<()> {
    let (pol, prio) = match policy {
        Policy::Other => (libc::SCHED_OTHER, 0),
        Policy::RoundRobin(p) => (libc::SCHED_RR, p),
    };
    let param = libc::sched_param {
        sched_priority: prio,
    };
    // SAFETY: `param` is a valid sched_param that the kernel only reads during the call.
    cvt(unsafe { libc::sched_setscheduler(pid, pol, &param) }).map(|_| ())
}

/// `sched_setaffinity(pid, cpus)`; an empty list means every CPU the machine has.
pub fn set_affinity(pid: libc::pid_t, cpus: &[usize]) -> io::Result<()> {
    // SAFETY: cpu_set_t is plain bits; all-zero is the empty set.
    let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
    let all: Vec<usize> = if cpus.is_empty() {
        (0..online_cpus()).collect()
    } else {
        cpus.to_vec()
    };
    for &c in &all {
        if c >= libc::CPU_SETSIZE as usize {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("CPU {c} is beyond CPU_SETSIZE"),
            ));
        }
        // SAFETY: `c` is below CPU_SETSIZE, so CPU_SET stays inside `set`.
        unsafe { libc::CPU_SET(c, &mut set) };
    }
    // SAFETY: `set` is a valid cpu_set_t of the size we pass; the kernel only reads it.
    cvt(unsafe { libc::sched_setaffinity(pid, std::mem::size_of::<libc::cpu_set_t>(), &set) })
        .map(|_| ())
}

/// Number of online CPUs (at least 1).
pub fn online_cpus() -> usize {
    // SAFETY: sysconf takes an integer and returns one.
    let n = unsafe { libc::sysconf(libc::_SC_NPROCESSORS_ONLN) };
    n.max(1) as usize
}

/// `fork()`. The child must do only async-signal-safe work (the bench has other threads, whose
/// locks are copied held) and leave by `_exit`.
pub fn fork() -> io::Result<libc::pid_t> {
    // SAFETY: every caller's child side only writes its own memory, calls write(2) and _exit,
    // all async-signal-safe (documented contract above).
    cvt(unsafe { libc::fork() })
}

/// Writes one volatile byte into each `page`-sized page of `buf` (forces a private copy of a
/// copy-on-write page). Async-signal-safe.
pub fn touch_pages(buf: &mut [u8], page: usize) {
    let mut i = 0;
    while i < buf.len() {
        let p: *mut u8 = &mut buf[i];
        // SAFETY: `p` points into `buf`, which we borrow mutably; volatile keeps the write
        // (the point is the page fault it causes, not the value).
        unsafe { std::ptr::write_volatile(p, std::ptr::read_volatile(p).wrapping_add(1)) };
        i += page;
    }
}

/// `madvise(MADV_POPULATE_WRITE)` over `buf`: write-faults every page of it in one call (a
/// private copy of each copy-on-write page), without changing a byte. Async-signal-safe.
pub fn populate_write(buf: &mut [u8]) -> std::io::Result<()> {
    if buf.is_empty() {
        return Ok(());
    }
    let page = replica_rt::cow::page_size();
    let start = buf.as_mut_ptr() as usize;
    // madvise wants a page-aligned start: round down to the start of `buf`'s first page.
    let aligned = start / page * page;
    let len = start + buf.len() - aligned;
    // SAFETY: `[aligned, aligned + len)` is `buf` (which we borrow mutably) plus the start of
    // its first page, which lies in the same mapping as `buf`'s first byte; MADV_POPULATE_WRITE
    // only faults pages in writable and changes no memory contents.
    let r = unsafe { libc::madvise(aligned as *mut libc::c_void, len, libc::MADV_POPULATE_WRITE) };
    if r == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// Whether this kernel has `MADV_POPULATE_WRITE` (Linux ≥ 5.14).
pub fn populate_write_supported() -> bool {
    let mut probe = vec![0u8; replica_rt::cow::page_size()];
    populate_write(&mut probe).is_ok()
}

/// Leaves the process at once, without running destructors or atexit handlers (fork child).
pub fn exit_now(code: libc::c_int) -> ! {
    // SAFETY: _exit never returns and is async-signal-safe.
    unsafe { libc::_exit(code) }
}

// ----- Ctrl-C --------------------------------------------------------------------------------

/// Process groups the SIGINT/SIGTERM handler kills (0 = free slot).
static GROUPS: [AtomicI32; 16] = [const { AtomicI32::new(0) }; 16];
static INTERRUPTED: AtomicBool = AtomicBool::new(false);

/// Registers a process group to be killed on SIGINT/SIGTERM. Returns the slot to release.
pub fn register_group(pgid: libc::pid_t) -> Option<usize> {
    GROUPS.iter().position(|g| {
        g.compare_exchange(0, pgid, Ordering::SeqCst, Ordering::SeqCst)
            .is_ok()
    })
}

pub fn unregister_group(slot: usize) {
    GROUPS[slot].store(0, Ordering::SeqCst);
}

/// Whether SIGINT/SIGTERM arrived.
pub fn interrupted() -> bool {
    INTERRUPTED.load(Ordering::SeqCst)
}

/// Async-signal-safe: one store and a few killpg.
extern "C" fn on_interrupt(_sig: libc::c_int) {
    INTERRUPTED.store(true, Ordering::SeqCst);
    for g in &GROUPS {
        let pgid = g.load(Ordering::SeqCst);
        if pgid > 0 {
            // SAFETY: killpg is async-signal-safe and takes integers only.
            unsafe { libc::killpg(pgid, libc::SIGKILL) };
        }
    }
}

/// SIGINT/SIGTERM: kill every registered process group at once and set [`interrupted`]; the
/// bench then unwinds through its guards, which reap. No SA_RESTART, so a blocked `ppoll`
/// returns EINTR.
pub fn install_interrupt_handler() -> io::Result<()> {
    for sig in [libc::SIGINT, libc::SIGTERM] {
        // SAFETY: an all-zero sigaction is valid; we fill in the handler and an empty mask.
        let mut sa: libc::sigaction = unsafe { std::mem::zeroed() };
        sa.sa_sigaction = on_interrupt as extern "C" fn(libc::c_int) as usize;
        // SAFETY: `sa.sa_mask` is a valid sigset_t to initialise.
        unsafe { libc::sigemptyset(&mut sa.sa_mask) };
        // SAFETY: `sa` is fully initialised; the old action is not wanted.
        cvt(unsafe { libc::sigaction(sig, &sa, std::ptr::null_mut()) })?;
    }
    Ok(())
}

/// Whether the process runs as root (SCHED_RR and pinning of other processes need it, or
/// CAP_SYS_NICE).
pub fn is_root() -> bool {
    // SAFETY: geteuid cannot fail.
    unsafe { libc::geteuid() == 0 }
}
