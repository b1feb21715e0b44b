//! The bench's syscall boundary: only what `replica_rt::sys` (the project's boundary) does not
//! wrap, and the bench's Ctrl-C policy built on it. Each function is small and says why its
//! `unsafe` block is sound.

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
    replica_rt::sys::kill(-pgid, sig)
}

/// Scheduling policy and the CPU count: replica-rt's.
pub use replica_rt::sys::{online_cpus, set_normal_policy, set_round_robin};

/// `sched_setaffinity(pid, cpus)`; an empty list means every CPU the machine has.
pub fn set_affinity(pid: libc::pid_t, cpus: &[usize]) -> io::Result<()> {
    if cpus.is_empty() {
        let all: Vec<usize> = (0..online_cpus()).collect();
        return replica_rt::sys::set_cpu_affinity(pid, &all);
    }
    replica_rt::sys::set_cpu_affinity(pid, cpus)
}

/// `fork()`.
///
/// # Safety
///
/// The bench has other threads, whose locks the child inherits held and whose memory it
/// inherits mid-update. In the child, the caller must do only async-signal-safe work (write
/// its own memory, raw system calls; no allocation, no lock, no `std` I/O) and leave by
/// [`exit_now`], never by returning or unwinding.
pub unsafe fn fork() -> io::Result<libc::pid_t> {
    // SAFETY: fork itself touches no memory of ours; what the child may do afterwards is this
    // function's precondition.
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

/// Leaves the process at once, without destructors or atexit handlers (fork child).
pub use replica_rt::sys::exit_now;

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

/// Async-signal-safe: one store and a few kill(2) (`replica_rt::sys::kill` neither allocates
/// nor locks).
extern "C" fn on_interrupt(_sig: libc::c_int, _info: *mut libc::siginfo_t, _: *mut libc::c_void) {
    INTERRUPTED.store(true, Ordering::SeqCst);
    for g in &GROUPS {
        let pgid = g.load(Ordering::SeqCst);
        if pgid > 0 {
            let _ = replica_rt::sys::kill(-pgid, libc::SIGKILL);
        }
    }
}

/// SIGINT/SIGTERM: kill every registered process group at once and set [`interrupted`]; the
/// bench then unwinds through its guards, which reap. No SA_RESTART, so a blocked `ppoll`
/// returns EINTR.
pub fn install_interrupt_handler() -> io::Result<()> {
    for sig in [libc::SIGINT, libc::SIGTERM] {
        // SAFETY: on_interrupt is async-signal-safe (atomics and kill(2) only).
        unsafe { replica_rt::sys::install_siginfo_handler(sig, on_interrupt, 0)? };
    }
    Ok(())
}

/// Whether the process runs as root (SCHED_RR and pinning of other processes need it, or
/// CAP_SYS_NICE).
pub fn is_root() -> bool {
    replica_rt::sys::effective_uid() == 0
}

thread_local! {
    /// This thread's kernel id, asked once (a read must not cost a system call more).
    static THIS_THREAD: libc::pid_t =
        // SAFETY: gettid takes no arguments and cannot fail.
        unsafe { libc::syscall(libc::SYS_gettid) as libc::pid_t };
}

/// The calling thread's kernel id (`gettid`), asked once per thread.
pub fn this_thread() -> libc::pid_t {
    THIS_THREAD.with(|tid| *tid)
}

/// Blocking reads with a deadline, without a timed wait per read.
///
/// The peers' harnesses wait for a round trip's answer in a blocking `read`; a `ppoll` with a
/// timeout before each read costs the bench's side of every round a system call and a kernel
/// timer that theirs do not pay. So [`crate::frames::FrameIn`] reads blocking, and this
/// watchdog bounds the wait instead: a reader publishes its deadline (an atomic store, no
/// system call) and its thread; a thread that wakes every [`WATCHDOG_PERIOD`] sends that
/// thread [`WAKE_SIGNAL`] while the deadline has passed. The handler does nothing and is
/// installed without `SA_RESTART`, so the read returns `EINTR` and the reader sees its deadline.
/// A signal that arrives just before the read blocks is followed by another a period later.
pub mod read_deadline {
    use std::sync::atomic::{AtomicI32, AtomicU64, Ordering};
    use std::sync::OnceLock;
    use std::time::Duration;

    /// The signal that interrupts a read past its deadline.
    pub const WAKE_SIGNAL: libc::c_int = libc::SIGALRM;
    /// How often the watchdog looks: a timed-out read returns within this of its deadline.
    pub const WATCHDOG_PERIOD: Duration = Duration::from_millis(20);

    /// The deadline of the read in progress (CLOCK_MONOTONIC ns), 0 when none is.
    static DEADLINE_NS: AtomicU64 = AtomicU64::new(0);
    /// The thread that reads (its kernel thread id).
    static READER: AtomicI32 = AtomicI32::new(0);
    static STARTED: OnceLock<std::io::Result<()>> = OnceLock::new();

    extern "C" fn on_wake(_sig: libc::c_int, _info: *mut libc::siginfo_t, _: *mut libc::c_void) {
        // Nothing: being delivered is the point (the read returns EINTR).
    }

    fn now_ns() -> u64 {
        s3res_protocol::clock::monotonic_ns()
    }

    /// Installs the handler and starts the watchdog thread, once per process.
    fn start() -> std::io::Result<()> {
        let started = STARTED.get_or_init(|| {
            // SAFETY: on_wake does nothing, which is async-signal-safe.
            unsafe { replica_rt::sys::install_siginfo_handler(WAKE_SIGNAL, on_wake, 0)? };
            std::thread::Builder::new()
                .name("read-deadline".into())
                .spawn(watch)?;
            Ok(())
        });
        match started {
            Ok(()) => Ok(()),
            Err(e) => Err(std::io::Error::new(e.kind(), e.to_string())),
        }
    }

    fn watch() {
        // Whatever the bench's thread had when this one was spawned (a setup's SCHED_RR and
        // pinning, or none), the watchdog must run whatever the system under test does: at the
        // top real-time priority where that is allowed, on every CPU. (A watchdog starved by
        // a spinning SCHED_RR system would let a read block for good.)
        let _ = replica_rt::sys::set_round_robin(0, 99);
        let all: Vec<usize> = (0..replica_rt::sys::online_cpus()).collect();
        let _ = replica_rt::sys::set_cpu_affinity(0, &all);
        // SAFETY: getpid cannot fail.
        let pid = unsafe { libc::getpid() };
        loop {
            std::thread::sleep(WATCHDOG_PERIOD);
            let deadline = DEADLINE_NS.load(Ordering::SeqCst);
            let reader = READER.load(Ordering::SeqCst);
            if deadline != 0 && reader != 0 && now_ns() >= deadline {
                // SAFETY: tgkill takes plain integers; a thread that has gone makes it fail
                // with ESRCH, which is harmless.
                unsafe { libc::syscall(libc::SYS_tgkill, pid, reader, WAKE_SIGNAL) };
            }
        }
    }

    /// One `read(2)`, **not** retried on EINTR (`replica_rt::sys::read` retries it, which would
    /// swallow the watchdog's wake-up and block for good on a system that never answers).
    pub fn read(fd: std::os::fd::BorrowedFd<'_>, buf: &mut [u8]) -> std::io::Result<usize> {
        use std::os::fd::AsRawFd;
        // SAFETY: `buf` is valid for writes of `buf.len()` bytes for the duration of the call.
        let n = unsafe { libc::read(fd.as_raw_fd(), buf.as_mut_ptr().cast(), buf.len()) };
        if n < 0 {
            return Err(std::io::Error::last_os_error());
        }
        Ok(n as usize)
    }

    /// While it lives, the calling thread's blocking reads are interrupted once `deadline`
    /// (CLOCK_MONOTONIC ns) has passed. One reader at a time.
    pub struct Armed(());

    impl Armed {
        pub fn new(deadline_ns: u64) -> std::io::Result<Armed> {
            start()?;
            READER.store(super::this_thread(), Ordering::SeqCst);
            DEADLINE_NS.store(deadline_ns.max(1), Ordering::SeqCst);
            Ok(Armed(()))
        }

        /// Whether the deadline has passed.
        pub fn expired(&self) -> bool {
            now_ns() >= DEADLINE_NS.load(Ordering::SeqCst)
        }
    }

    impl Drop for Armed {
        fn drop(&mut self) {
            DEADLINE_NS.store(0, Ordering::SeqCst);
        }
    }
}
