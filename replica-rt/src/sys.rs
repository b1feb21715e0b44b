//! The syscall boundary of s3res. Every `unsafe` block of the project that talks to the kernel
//! lives here or in the restart handler, each in a small function with its safety argument.
//! The voter and bootstrap use these too (dependencies point bootstrap → voter → replica-rt).

use std::ffi::CString;
use std::io;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, FromRawFd, OwnedFd, RawFd};
use std::os::unix::process::CommandExt;
use std::process::Command;
use std::time::Duration;

fn cvt(ret: libc::c_int) -> io::Result<libc::c_int> {
    if ret < 0 {
        Err(io::Error::last_os_error())
    } else {
        Ok(ret)
    }
}

/// `cvt` for `libc::syscall`, which returns a `c_long`.
fn cvt_long(ret: libc::c_long) -> io::Result<libc::c_long> {
    if ret < 0 {
        Err(io::Error::last_os_error())
    } else {
        Ok(ret)
    }
}

/// A pipe whose both ends are close-on-exec: `(read, write)`.
pub fn pipe() -> io::Result<(OwnedFd, OwnedFd)> {
    let mut fds = [0 as libc::c_int; 2];
    // SAFETY: `fds` is a valid, writable array of two c_ints as pipe2 requires.
    cvt(unsafe { libc::pipe2(fds.as_mut_ptr(), libc::O_CLOEXEC) })?;
    // SAFETY: pipe2 succeeded, so both fds are open and owned by nobody else.
    Ok(unsafe { (OwnedFd::from_raw_fd(fds[0]), OwnedFd::from_raw_fd(fds[1])) })
}

/// Sets or clears `O_NONBLOCK`.
pub fn set_nonblocking(fd: BorrowedFd<'_>, on: bool) -> io::Result<()> {
    // SAFETY: F_GETFL/F_SETFL on a borrowed (hence open) fd touch no memory of ours.
    let flags = cvt(unsafe { libc::fcntl(fd.as_raw_fd(), libc::F_GETFL) })?;
    let flags = if on {
        flags | libc::O_NONBLOCK
    } else {
        flags & !libc::O_NONBLOCK
    };
    // SAFETY: as above.
    cvt(unsafe { libc::fcntl(fd.as_raw_fd(), libc::F_SETFL, flags) })?;
    Ok(())
}

/// `read(2)` into `buf`; `Ok(0)` is end of stream. EINTR is retried.
pub fn read(fd: BorrowedFd<'_>, buf: &mut [u8]) -> io::Result<usize> {
    loop {
        // SAFETY: `buf` is valid for writes of `buf.len()` bytes for the duration of the call.
        let n = unsafe { libc::read(fd.as_raw_fd(), buf.as_mut_ptr().cast(), buf.len()) };
        if n >= 0 {
            return Ok(n as usize);
        }
        let e = io::Error::last_os_error();
        if e.kind() != io::ErrorKind::Interrupted {
            return Err(e);
        }
    }
}

/// `write(2)` from `buf`; may write less than all of it. EINTR is retried.
pub fn write(fd: BorrowedFd<'_>, buf: &[u8]) -> io::Result<usize> {
    loop {
        // SAFETY: `buf` is valid for reads of `buf.len()` bytes for the duration of the call.
        let n = unsafe { libc::write(fd.as_raw_fd(), buf.as_ptr().cast(), buf.len()) };
        if n >= 0 {
            return Ok(n as usize);
        }
        let e = io::Error::last_os_error();
        if e.kind() != io::ErrorKind::Interrupted {
            return Err(e);
        }
    }
}

/// `writev(2)` of `head` then `body`, as if they were one buffer; may write less than all of
/// it. EINTR is retried. (A frame's header and its payload, without copying them together.)
pub fn write2(fd: BorrowedFd<'_>, head: &[u8], body: &[u8]) -> io::Result<usize> {
    let iov = [
        libc::iovec {
            iov_base: head.as_ptr().cast_mut().cast(),
            iov_len: head.len(),
        },
        libc::iovec {
            iov_base: body.as_ptr().cast_mut().cast(),
            iov_len: body.len(),
        },
    ];
    loop {
        // SAFETY: both iovecs describe live slices, valid for reads of their lengths for the
        // duration of the call; `writev` only reads through them.
        let n = unsafe { libc::writev(fd.as_raw_fd(), iov.as_ptr(), 2) };
        if n >= 0 {
            return Ok(n as usize);
        }
        let e = io::Error::last_os_error();
        if e.kind() != io::ErrorKind::Interrupted {
            return Err(e);
        }
    }
}

/// A pidfd for `pid`: readable once the process has exited, usable for signals without pid
/// reuse races. Works for any process we may signal, not only our children.
pub fn pidfd_open(pid: libc::pid_t) -> io::Result<OwnedFd> {
    // SAFETY: pidfd_open takes two integers and returns a new fd or -1.
    let fd = cvt_long(unsafe { libc::syscall(libc::SYS_pidfd_open, pid, 0) })?;
    // SAFETY: the kernel just created this fd for us; it is open and unowned.
    Ok(unsafe { OwnedFd::from_raw_fd(fd as RawFd) })
}

/// Sends `sig` to the process behind `pidfd`.
pub fn pidfd_send_signal(pidfd: BorrowedFd<'_>, sig: libc::c_int) -> io::Result<()> {
    // SAFETY: a null siginfo is allowed (the kernel fills in SI_USER); no memory is shared.
    let r = unsafe {
        libc::syscall(
            libc::SYS_pidfd_send_signal,
            pidfd.as_raw_fd(),
            sig,
            std::ptr::null::<libc::siginfo_t>(),
            0,
        )
    };
    cvt_long(r).map(drop)
}

/// Who a queued signal says it comes from (`si_pid`, `si_uid`): glibc's `sigqueue` asks the
/// kernel for both on every call; a sender that sends often asks once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SignalSender {
    pub pid: libc::pid_t,
    pub uid: libc::uid_t,
}

impl SignalSender {
    /// The calling process. Kept across a `fork`, it would name the parent: take it again there.
    pub fn this_process() -> SignalSender {
        SignalSender {
            pid: getpid(),
            // SAFETY: getuid takes no argument and cannot fail.
            uid: unsafe { libc::getuid() },
        }
    }
}

/// A `siginfo_t` as `sigqueue` fills it (`SI_QUEUE`), in the kernel's layout on Linux:
/// `si_signo`, `si_errno`, `si_code` (MIPS: `si_code` before `si_errno`), then the union,
/// pointer-aligned (`si_pid`, `si_uid`, `si_value`); 128 bytes in all.
#[repr(C)]
struct QueuedSiginfo {
    signo: libc::c_int,
    #[cfg(not(any(
        target_arch = "mips",
        target_arch = "mips64",
        target_arch = "mips32r6",
        target_arch = "mips64r6"
    )))]
    errno: libc::c_int,
    code: libc::c_int,
    #[cfg(any(
        target_arch = "mips",
        target_arch = "mips64",
        target_arch = "mips32r6",
        target_arch = "mips64r6"
    ))]
    errno: libc::c_int,
    #[cfg(target_pointer_width = "64")]
    _align: libc::c_int,
    pid: libc::pid_t,
    uid: libc::uid_t,
    value: usize,
    _rest: [u8; SIGINFO_REST],
}

/// What follows `si_value` in the 128 bytes: the fields before it take 32 bytes on a 64-bit
/// target (with the padding), 24 on a 32-bit one (the size check below holds it to that).
const SIGINFO_REST: usize = 128
    - if cfg!(target_pointer_width = "64") {
        32
    } else {
        24
    };

const _: () =
    assert!(std::mem::size_of::<QueuedSiginfo>() == std::mem::size_of::<libc::siginfo_t>());

/// Sends `sig` with an integer value, as `sigqueue` does (an `SA_SIGINFO` handler reads it with
/// [`queued_value`]), to the process `pidfd` refers to: never to another one that took its pid
/// after it died. One system call, where `sigqueue` makes three.
pub fn pidfd_sigqueue(
    pidfd: BorrowedFd<'_>,
    sig: libc::c_int,
    value: i32,
    sender: SignalSender,
) -> io::Result<()> {
    let info = QueuedSiginfo {
        signo: sig,
        errno: 0,
        code: libc::SI_QUEUE,
        #[cfg(target_pointer_width = "64")]
        _align: 0,
        pid: sender.pid,
        uid: sender.uid,
        // Sign-extended into the pointer-sized union, as `sigqueue` below stores it.
        value: value as isize as usize,
        _rest: [0; SIGINFO_REST],
    };
    // SAFETY: `info` is a fully initialised siginfo of the kernel's size and layout (checked
    // above), alive for the call; the kernel only reads it. A negative si_code (SI_QUEUE) is
    // what one process may send another.
    let r = unsafe {
        libc::syscall(
            libc::SYS_pidfd_send_signal,
            pidfd.as_raw_fd(),
            sig,
            &info as *const QueuedSiginfo,
            0,
        )
    };
    cvt_long(r).map(drop)
}

/// Sends `sig` to `pid` with an integer value (readable by an SA_SIGINFO handler).
pub fn sigqueue(pid: libc::pid_t, sig: libc::c_int, value: i32) -> io::Result<()> {
    let val = libc::sigval {
        sival_ptr: value as isize as *mut libc::c_void,
    };
    // SAFETY: sigqueue copies `val` by value; no pointer in it is dereferenced by anyone
    // (the receiver reads it back as an integer).
    cvt(unsafe { libc::sigqueue(pid, sig, val) })?;
    Ok(())
}

/// `kill(2)`.
pub fn kill(pid: libc::pid_t, sig: libc::c_int) -> io::Result<()> {
    // SAFETY: plain integer arguments.
    cvt(unsafe { libc::kill(pid, sig) })?;
    Ok(())
}

/// Makes this process a child subreaper: orphaned descendants are re-parented to us, not to
/// init, so we can reap them and nothing escapes our bookkeeping.
pub fn set_child_subreaper() -> io::Result<()> {
    // SAFETY: PR_SET_CHILD_SUBREAPER takes an integer flag only.
    cvt(unsafe { libc::prctl(libc::PR_SET_CHILD_SUBREAPER, 1 as libc::c_ulong, 0, 0, 0) })?;
    Ok(())
}

/// Exit status of a reaped child, as the shell would put it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExitStatus {
    Code(i32),
    Signal(i32),
}

impl ExitStatus {
    /// Decodes a status word as `waitpid(2)` fills it in.
    pub fn from_wait_status(status: libc::c_int) -> Self {
        if libc::WIFEXITED(status) {
            ExitStatus::Code(libc::WEXITSTATUS(status))
        } else {
            ExitStatus::Signal(libc::WTERMSIG(status))
        }
    }

    pub fn success(self) -> bool {
        self == ExitStatus::Code(0)
    }
}

impl std::fmt::Display for ExitStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ExitStatus::Code(c) => write!(f, "exit status {c}"),
            ExitStatus::Signal(s) => write!(f, "killed by signal {s}"),
        }
    }
}

/// Reaps one exited child without blocking: `Ok(None)` when no child has exited (or none is
/// left: ECHILD).
pub fn reap_any() -> io::Result<Option<(libc::pid_t, ExitStatus)>> {
    reap(-1)
}

/// Reaps `pid` if it is our child and has exited.
pub fn reap(pid: libc::pid_t) -> io::Result<Option<(libc::pid_t, ExitStatus)>> {
    let mut status: libc::c_int = 0;
    // SAFETY: `status` is a valid out-pointer for the duration of the call.
    let r = unsafe { libc::waitpid(pid, &mut status, libc::WNOHANG) };
    if r < 0 {
        let e = io::Error::last_os_error();
        return if e.raw_os_error() == Some(libc::ECHILD) {
            Ok(None)
        } else {
            Err(e)
        };
    }
    if r == 0 {
        return Ok(None);
    }
    Ok(Some((r, ExitStatus::from_wait_status(status))))
}

/// `struct pidfd_info` of `<linux/pidfd.h>`, its first version (64 bytes, Linux 6.13+).
#[repr(C)]
#[derive(Default)]
struct PidfdInfo {
    mask: u64,
    cgroupid: u64,
    pid: u32,
    tgid: u32,
    ppid: u32,
    ruid: u32,
    rgid: u32,
    euid: u32,
    egid: u32,
    suid: u32,
    sgid: u32,
    fsuid: u32,
    fsgid: u32,
    exit_code: i32,
}

/// `_IOWR(kind, nr, size)` of `asm-generic/ioctl.h`: an ioctl number that passes `size` bytes
/// in and out. That is the encoding of x86, Arm and RISC-V; PowerPC, MIPS and SPARC encode the
/// direction otherwise, and there the kernel refuses the number: its callers then take their
/// fallbacks (`PROCMAP_QUERY` gives way to the text of `/proc/self/maps`).
pub(crate) const fn iowr(kind: u8, nr: u8, size: usize) -> libc::c_ulong {
    assert!(size < 1 << 14, "an ioctl's size has 14 bits");
    (3 << 30)
        | ((size as libc::c_ulong) << 16)
        | ((kind as libc::c_ulong) << 8)
        | nr as libc::c_ulong
}

/// `PIDFD_GET_INFO`: `_IOWR(PIDFS_IOCTL_MAGIC = 0xFF, 11, struct pidfd_info)`.
const PIDFD_GET_INFO: libc::c_ulong = iowr(0xFF, 11, std::mem::size_of::<PidfdInfo>());
/// Asks `PIDFD_GET_INFO` for the exit status.
const PIDFD_INFO_EXIT: u64 = 1 << 3;

/// How the process behind `pidfd` ended, also when it is not our child (a fork child, reaped
/// by its donor): the kernel keeps the exit status beside the pidfd once the process has been
/// reaped (Linux 6.15+). `Ok(None)` while it runs or is an unreaped zombie (and on 6.13–6.14,
/// which know the request but not the exit status); an error where the kernel lacks it.
pub fn pidfd_exit_status(pidfd: BorrowedFd<'_>) -> io::Result<Option<ExitStatus>> {
    let mut info = PidfdInfo {
        mask: PIDFD_INFO_EXIT,
        ..PidfdInfo::default()
    };
    // SAFETY: `info` is a valid, writable `struct pidfd_info` of the size the request number
    // encodes, for the duration of the call; the kernel writes no more than that.
    let r = unsafe {
        libc::ioctl(
            pidfd.as_raw_fd(),
            PIDFD_GET_INFO as _,
            &mut info as *mut PidfdInfo,
        )
    };
    cvt(r)?;
    Ok((info.mask & PIDFD_INFO_EXIT != 0).then(|| ExitStatus::from_wait_status(info.exit_code)))
}

/// Waits up to `timeout` for `fd` to become readable (or hung up). `Ok(true)` if it did.
pub fn wait_readable(fd: BorrowedFd<'_>, timeout: Duration) -> io::Result<bool> {
    let mut pfd = [libc::pollfd {
        fd: fd.as_raw_fd(),
        events: libc::POLLIN,
        revents: 0,
    }];
    Ok(ppoll(&mut pfd, Some(timeout))? > 0)
}

/// `ppoll(2)` with nanosecond timeout (`None` waits forever). EINTR counts as zero ready fds.
pub fn ppoll(fds: &mut [libc::pollfd], timeout: Option<Duration>) -> io::Result<usize> {
    let ts = timeout.map(|t| libc::timespec {
        tv_sec: t.as_secs() as _,
        tv_nsec: t.subsec_nanos() as libc::c_long,
    });
    let tsp = ts
        .as_ref()
        .map_or(std::ptr::null(), |t| t as *const libc::timespec);
    // SAFETY: `fds` is a valid mutable slice of pollfd of the given length; `tsp` is null or
    // points to a timespec that outlives the call; a null sigmask keeps the current mask.
    let n = unsafe {
        libc::ppoll(
            fds.as_mut_ptr(),
            fds.len() as libc::nfds_t,
            tsp,
            std::ptr::null(),
        )
    };
    if n < 0 {
        let e = io::Error::last_os_error();
        if e.kind() == io::ErrorKind::Interrupted {
            return Ok(0);
        }
        return Err(e);
    }
    Ok(n as usize)
}

/// Process id of the peer of a connected Unix socket (`SO_PEERCRED`).
pub fn peer_pid(sock: BorrowedFd<'_>) -> io::Result<libc::pid_t> {
    let mut cred = libc::ucred {
        pid: 0,
        uid: 0,
        gid: 0,
    };
    let mut len = std::mem::size_of::<libc::ucred>() as libc::socklen_t;
    // SAFETY: `cred` and `len` are valid out-pointers sized for SO_PEERCRED's ucred.
    cvt(unsafe {
        libc::getsockopt(
            sock.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_PEERCRED,
            (&mut cred as *mut libc::ucred).cast(),
            &mut len,
        )
    })?;
    Ok(cred.pid)
}

/// Copies up to `buf.len()` bytes from the head of socket `sock` without taking them off and
/// without waiting (`recv` with `MSG_PEEK | MSG_DONTWAIT`): how many (0 at its end, or
/// `WouldBlock` while nothing has come).
pub fn peek_now(sock: BorrowedFd<'_>, buf: &mut [u8]) -> io::Result<usize> {
    // SAFETY: `buf` is valid for writes of `buf.len()` bytes for the duration of the call.
    let n = unsafe {
        libc::recv(
            sock.as_raw_fd(),
            buf.as_mut_ptr().cast(),
            buf.len(),
            libc::MSG_PEEK | libc::MSG_DONTWAIT,
        )
    };
    if n < 0 {
        Err(io::Error::last_os_error())
    } else {
        Ok(n as usize)
    }
}

/// Parent pid of `pid`, from `/proc/PID/stat` (`None` if the process is gone).
pub fn parent_pid(pid: libc::pid_t) -> Option<libc::pid_t> {
    proc_stat_field(pid, 4)
}

/// Parent pid of the process behind `pidfd`, whose pid is `pid` (`None` if it is gone). Asked
/// of the pidfd itself where the kernel can say (`PIDFD_GET_INFO`, Linux 6.13+): one `ioctl`,
/// 1.0 µs on the AMD host of docs/results.md against 9.2 µs for opening and reading
/// `/proc/PID/stat` (stop 50), and the answer is of that process even if its number has been
/// reused since. Older kernels (`ENOTTY`, `EINVAL`) are answered from `/proc/PID/stat`.
pub fn parent_of(pidfd: BorrowedFd<'_>, pid: libc::pid_t) -> Option<libc::pid_t> {
    let mut info = PidfdInfo::default();
    // SAFETY: `info` is a valid, writable `struct pidfd_info` of the size the request number
    // encodes, for the duration of the call; the kernel writes no more than that.
    let r = unsafe {
        libc::ioctl(
            pidfd.as_raw_fd(),
            PIDFD_GET_INFO as _,
            &mut info as *mut PidfdInfo,
        )
    };
    if r == 0 {
        return libc::pid_t::try_from(info.ppid).ok();
    }
    match io::Error::last_os_error().raw_os_error() {
        // Gone: reaped (a zombie still answers, with its parent, as `/proc` does).
        Some(libc::ESRCH) => None,
        _ => parent_pid(pid),
    }
}

/// Process group of `pid`, from `/proc/PID/stat` (`None` if the process is gone).
pub fn process_group(pid: libc::pid_t) -> Option<libc::pid_t> {
    proc_stat_field(pid, 5)
}

/// Field `n` (1-based, as in proc(5)) of `/proc/PID/stat`, for the numeric fields after `comm`.
fn proc_stat_field(pid: libc::pid_t, n: usize) -> Option<libc::pid_t> {
    with_proc_stat(pid, |rest| rest.split_whitespace().nth(n - 3)?.parse().ok())
}

/// The set of signals `pid` has a handler for (`SigCgt` in `/proc/PID/status`, bit `n - 1`
/// for signal `n`; see [`signal_bit`]); `None` if the process is gone.
pub fn caught_signals(pid: libc::pid_t) -> Option<u64> {
    with_proc_status(pid, |status| {
        status
            .lines()
            .find_map(|l| l.strip_prefix("SigCgt:"))
            .and_then(|mask| u64::from_str_radix(mask.trim(), 16).ok())
    })
}

/// Signal `sig`'s bit in a [`caught_signals`] mask.
pub fn signal_bit(sig: libc::c_int) -> u64 {
    1u64 << (sig - 1)
}

/// The command name of `pid` (`/proc/PID/comm`: the executable's name, at most 15 bytes);
/// `None` if it is gone.
pub fn command_name(pid: libc::pid_t) -> Option<String> {
    let comm = std::fs::read_to_string(format!("/proc/{pid}/comm")).ok()?;
    Some(comm.trim_end_matches('\n').to_owned())
}

/// The state letter of `pid` (field 3 of `/proc/PID/stat`: `R`, `S`, `D`, `T` stopped, `t`
/// traced, `Z` zombie, ...); `None` if the process is gone.
pub fn process_state(pid: libc::pid_t) -> Option<char> {
    let mut buf = [0u8; 1024];
    state_in_stat(read_proc_small(&format!("/proc/{pid}/stat"), &mut buf)?)
}

/// The state letter in the text of a `/proc/PID/stat` (field 3).
pub fn state_in_stat(stat: &str) -> Option<char> {
    after_comm(stat)?.trim_start().chars().next()
}

/// The number of threads in the text of a `/proc/PID/stat` (field 20, `num_threads`).
pub fn threads_in_stat(stat: &str) -> Option<u64> {
    after_comm(stat)?
        .split_ascii_whitespace()
        .nth(17)?
        .parse()
        .ok()
}

/// What follows `comm` in the text of a `/proc/PID/stat` (field 3 on): comm (field 2) may
/// contain spaces and parentheses, so the rest starts after the last ')'.
fn after_comm(stat: &str) -> Option<&str> {
    Some(&stat[stat.rfind(')')? + 1..])
}

/// The kernel function `pid` sleeps in (`/proc/PID/wchan`: `pipe_read`, `pipe_write`,
/// `futex_wait_queue`, ...); `None` while it runs, or where the kernel does not say (it shows
/// `0` to those who may not ptrace the process). Reading it never waits for the process,
/// unlike `/proc/PID/syscall`.
pub fn wchan(pid: libc::pid_t) -> Option<Wchan> {
    let mut buf = [0u8; 64];
    let text = read_proc_small(&format!("/proc/{pid}/wchan"), &mut buf)?.trim();
    (!text.is_empty() && text != "0").then(|| Wchan::new(text))
}

/// A kernel function name, kept inline (cut at 31 bytes) so that it can be copied around.
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct Wchan {
    len: u8,
    bytes: [u8; 31],
}

impl Wchan {
    pub fn new(name: &str) -> Wchan {
        let mut cut = name.len().min(31);
        while !name.is_char_boundary(cut) {
            cut -= 1;
        }
        let mut bytes = [0u8; 31];
        bytes[..cut].copy_from_slice(&name.as_bytes()[..cut]);
        Wchan {
            len: cut as u8,
            bytes,
        }
    }

    pub fn as_str(&self) -> &str {
        std::str::from_utf8(&self.bytes[..usize::from(self.len)]).unwrap_or("?")
    }
}

impl std::fmt::Debug for Wchan {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:?}", self.as_str())
    }
}

/// A counter of the time another process has spent on a CPU (the `task-clock` software
/// event of `perf_event_open(2)`), exact to the moment it is read: reading a running
/// process's count brings it up to date first, whereas `/proc/PID/schedstat` and `stat`, and
/// the process's CPU-time clock, move on only at scheduler ticks, milliseconds apart.
#[derive(Debug)]
pub struct TaskClock(OwnedFd);

/// `struct perf_event_attr`, its first 64 bytes (`PERF_ATTR_SIZE_VER0`): the fields a
/// task-clock counter needs; the kernel takes the size from `size`.
#[repr(C)]
#[derive(Default)]
struct PerfEventAttr {
    kind: u32,
    size: u32,
    config: u64,
    sample_period: u64,
    sample_type: u64,
    read_format: u64,
    /// The bit fields: `disabled` (bit 0), `inherit`, `pinned`, `exclusive`, `exclude_user`,
    /// `exclude_kernel` (bit 5), `exclude_hv` (bit 6), ...
    flags: u64,
    wakeup_events: u32,
    bp_type: u32,
    config1: u64,
}

impl TaskClock {
    /// Counts `pid`'s time on a CPU from now on. Refused where `perf_event_paranoid` does not
    /// allow watching a process of ours (above 2), and where the kernel has no perf events.
    pub fn open(pid: libc::pid_t) -> io::Result<TaskClock> {
        TaskClock::open_with(pid, false)
    }

    /// A task clock on `pid` that does not count (created disabled): it only keeps the
    /// kernel's perf accounting up. The first process-bound perf event of the whole machine
    /// makes `perf_event_open` wait for an RCU grace period (the kernel switches its
    /// context-switch hooks on, then waits until every CPU has seen that), and the last one
    /// closed switches them off again a second later. RCU's grace-period thread is an
    /// ordinary task, so on a machine whose every CPU runs a spinning real-time process the
    /// wait lasts until the kernel's real-time throttling lets it run: about 200 ms,
    /// measured. While one such event stays open, later opens do not wait. It costs the task
    /// it is bound to: each of that task's context switches passes through perf, so it belongs
    /// on a process that mostly sleeps (bootstrap holds one on itself).
    pub fn open_idle(pid: libc::pid_t) -> io::Result<TaskClock> {
        TaskClock::open_with(pid, true)
    }

    fn open_with(pid: libc::pid_t, disabled: bool) -> io::Result<TaskClock> {
        const PERF_TYPE_SOFTWARE: u32 = 1;
        const PERF_COUNT_SW_TASK_CLOCK: u64 = 1;
        /// `exclude_kernel | exclude_hv`: what `perf_event_paranoid` 2 asks of a user.
        const EXCLUDE_KERNEL_HV: u64 = 1 << 5 | 1 << 6;
        const PERF_FLAG_FD_CLOEXEC: libc::c_ulong = 1 << 3;
        let attr = PerfEventAttr {
            kind: PERF_TYPE_SOFTWARE,
            size: std::mem::size_of::<PerfEventAttr>() as u32,
            config: PERF_COUNT_SW_TASK_CLOCK,
            flags: EXCLUDE_KERNEL_HV | u64::from(disabled),
            ..PerfEventAttr::default()
        };
        // SAFETY: `attr` is a valid `perf_event_attr` of the size it declares, read by the
        // kernel during the call only; the other arguments are integers (any CPU, no group).
        let fd = unsafe {
            libc::syscall(
                libc::SYS_perf_event_open,
                &attr as *const PerfEventAttr,
                pid,
                -1 as libc::c_int,
                -1 as libc::c_int,
                PERF_FLAG_FD_CLOEXEC,
            )
        };
        let fd = cvt_long(fd)?;
        // SAFETY: the kernel just created this fd for us; it is open and unowned.
        Ok(TaskClock(unsafe { OwnedFd::from_raw_fd(fd as RawFd) }))
    }

    /// Time on a CPU since [`TaskClock::open`], ns; `None` once the process is gone.
    pub fn read(&self) -> Option<u64> {
        let mut ns = [0u8; 8];
        let n = read(self.0.as_fd(), &mut ns).ok()?;
        (n == ns.len()).then(|| u64::from_ne_bytes(ns))
    }
}

/// Whether `pid` is on its way out: the kernel has begun its exit (`PF_EXITING` in field 9 of
/// `/proc/PID/stat`, set as a killed or exiting process starts to tear down, before its fds
/// close and well before its exit is signalled), or it is already a zombie or gone.
pub fn process_exiting(pid: libc::pid_t) -> bool {
    /// `PF_EXITING` of the kernel's `include/linux/sched.h`.
    const PF_EXITING: u64 = 0x4;
    with_proc_stat(pid, |rest| {
        // From field 3 on: state, ppid, pgrp, session, tty_nr, tpgid, flags.
        let mut fields = rest.split_ascii_whitespace();
        let state = fields.next()?;
        let flags: u64 = fields.nth(5)?.parse().ok()?;
        Some(state == "Z" || state == "X" || flags & PF_EXITING != 0)
    })
    .unwrap_or(true)
}

/// How `pid` ended, while it is a zombie (exited, not yet reaped by its parent): field 52 of
/// `/proc/PID/stat`, the status as `waitpid` would report it (Linux 3.5+). `None` if the
/// process is not a zombie (running, or reaped and gone) or `/proc` does not say.
///
/// For a process that is not our child, whose parent may take its time to reap it (a fork
/// child whose donor died belongs to a subreaper), this is the status without waiting for the
/// reaping that `PIDFD_INFO_EXIT` needs.
pub fn zombie_exit_status(pid: libc::pid_t) -> Option<ExitStatus> {
    with_proc_stat(pid, |rest| {
        let mut fields = rest.split_ascii_whitespace();
        let state = fields.next()?;
        if state != "Z" && state != "X" {
            return None;
        }
        // Field 3 was `state`; field 52 is 49 further on.
        let code: libc::c_int = fields.nth(48)?.parse().ok()?;
        Some(ExitStatus::from_wait_status(code))
    })
}

/// Reads `/proc/PID/stat` and gives `f` what follows `comm` (from field 3 on).
fn with_proc_stat<R>(pid: libc::pid_t, f: impl FnOnce(&str) -> Option<R>) -> Option<R> {
    // The line is ~300 bytes; comm is at most 16.
    let mut buf = [0u8; 1024];
    f(after_comm(read_proc_small(
        &format!("/proc/{pid}/stat"),
        &mut buf,
    )?)?)
}

/// Reads `/proc/PID/status` (about 1.5 KiB) and gives it to `f`.
pub fn with_proc_status<R>(pid: libc::pid_t, f: impl FnOnce(&str) -> Option<R>) -> Option<R> {
    let mut buf = [0u8; 4096];
    f(read_proc_small(&format!("/proc/{pid}/status"), &mut buf)?)
}

/// Reads a small `/proc` file into `buf` (cut at its length): reads into a stack buffer,
/// normally one, not `read_to_string`'s statx and growing reads (eight for a `status`), since
/// these are on the restart path.
fn read_proc_small<'a>(path: &str, buf: &'a mut [u8]) -> Option<&'a str> {
    use std::io::Read;
    let mut file = std::fs::File::open(path).ok()?;
    let mut len = 0;
    while len < buf.len() {
        match file.read(&mut buf[len..]) {
            Ok(0) => break,
            Ok(k) => len += k,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(_) => return None,
        }
    }
    std::str::from_utf8(&buf[..len]).ok()
}

/// A connected pair of Unix `SOCK_SEQPACKET` sockets, close-on-exec: each `send` is one
/// message, and fds sent with it wait in the other end's queue for as long as that end lives.
pub fn seqpacket_pair() -> io::Result<(OwnedFd, OwnedFd)> {
    use nix::sys::socket::{socketpair, AddressFamily, SockFlag, SockType};
    socketpair(
        AddressFamily::Unix,
        SockType::SeqPacket,
        None,
        SockFlag::SOCK_CLOEXEC,
    )
    .map_err(io::Error::from)
}

/// Sends a whole buffer plus `fds` as SCM_RIGHTS in one `sendmsg`.
pub fn send_with_fds(sock: BorrowedFd<'_>, bytes: &[u8], fds: &[RawFd]) -> io::Result<()> {
    use nix::sys::socket::{sendmsg, ControlMessage, MsgFlags};
    let iov = [io::IoSlice::new(bytes)];
    let cmsg = [ControlMessage::ScmRights(fds)];
    let n = sendmsg::<()>(sock.as_raw_fd(), &iov, &cmsg, MsgFlags::MSG_NOSIGNAL, None)
        .map_err(io::Error::from)?;
    if n != bytes.len() {
        return Err(io::Error::new(io::ErrorKind::WriteZero, "short sendmsg"));
    }
    Ok(())
}

/// Puts `fds[i].0` on fd number `fds[i].1` in the child of `cmd`, and nothing else beyond
/// stdin/stdout/stderr (everything s3res opens is close-on-exec).
pub fn map_fds_on_exec(cmd: &mut Command, fds: Vec<(RawFd, RawFd)>) {
    let floor = fds.iter().map(|&(s, t)| s.max(t)).max().unwrap_or(2) + 1;
    // SAFETY: the closure runs in the forked child before exec and only calls fcntl and dup2,
    // which are async-signal-safe; it neither allocates nor takes locks (`fds` was built
    // before the fork and is only read).
    unsafe {
        cmd.pre_exec(move || {
            // Two passes so a source that sits on another mapping's target is not clobbered:
            // first move every source above all numbers in play, then dup2 onto the targets.
            let mut moved = [0 as RawFd; 2 * crate::contract::MAX_PORTS + 8];
            if fds.len() > moved.len() {
                return Err(io::Error::from_raw_os_error(libc::EMFILE));
            }
            for (i, &(src, _)) in fds.iter().enumerate() {
                moved[i] = cvt(libc::fcntl(src, libc::F_DUPFD_CLOEXEC, floor))?;
            }
            for (i, &(_, target)) in fds.iter().enumerate() {
                // dup2 clears FD_CLOEXEC on the target, so it survives exec.
                cvt(libc::dup2(moved[i], target))?;
            }
            Ok(())
        });
    }
}

/// The signals a process that s3res starts begins with blocked: those a terminal sends
/// (Ctrl-C, Ctrl-\, a hang-up) to its whole foreground process group — bootstrap and
/// everything it started. Bootstrap stops the system in order (SIGTERM to each component, a
/// voter stopping its replicas); a replica that died of a Ctrl-C behind its voter's back would
/// be a crash and a recovery in the middle of the stop.
pub const TERMINAL_SIGNALS: &[libc::c_int] = &[libc::SIGHUP, libc::SIGINT, libc::SIGQUIT];

/// The signals a replica begins with blocked: the terminal's, and SIGTERM. A replica's life is
/// its voter's (it kills one with SIGKILL, and ends them all by closing their input); a SIGTERM
/// sent to a whole process group or cgroup (timeout(1), systemd, Slurm) that killed replicas
/// would be crashes and recoveries in the middle of the stop.
pub const REPLICA_SIGNALS: &[libc::c_int] =
    &[libc::SIGHUP, libc::SIGINT, libc::SIGQUIT, libc::SIGTERM];

/// Starts the child of `cmd` with exactly `signals` blocked ([`TERMINAL_SIGNALS`] for a
/// component, [`REPLICA_SIGNALS`] for a replica), whatever this process blocks. The mask is
/// inherited over fork and exec, and `std::process::Command` passes it on as it is (rustc
/// 1.95); bootstrap and the voter block SIGTERM and SIGCHLD for their signalfds, so without
/// this a component could not catch the SIGTERM that stops it (every stop waited out the stop
/// timeout and ended in SIGKILL) and whatever it started could not be stopped with a plain
/// `kill`.
pub fn start_with_signals_blocked(cmd: &mut Command, signals: &'static [libc::c_int]) {
    // SAFETY: the closure runs in the forked child before exec and only calls sigemptyset,
    // sigaddset and pthread_sigmask on a stack value: async-signal-safe, no allocation, no
    // lock.
    unsafe {
        cmd.pre_exec(move || {
            let mut set = std::mem::zeroed::<libc::sigset_t>();
            libc::sigemptyset(&mut set);
            for &sig in signals {
                libc::sigaddset(&mut set, sig);
            }
            match libc::pthread_sigmask(libc::SIG_SETMASK, &set, std::ptr::null_mut()) {
                0 => Ok(()),
                e => Err(io::Error::from_raw_os_error(e)),
            }
        });
    }
}

/// Makes the child of `cmd` receive `sig` when this process dies (`PR_SET_PDEATHSIG`), so that
/// nothing a supervisor started outlives it, however it dies (SIGKILL included). If this
/// process is already gone when the child sets it up, the child sends itself `sig` at once.
/// The parent is the thread that forks: spawn from a thread that lives as long as the process
/// (the kernel sends the signal when the forking *thread* exits).
pub fn die_with_parent(cmd: &mut Command, sig: libc::c_int) {
    let parent = std::process::id() as libc::pid_t;
    // SAFETY: the closure runs in the forked child before exec and only calls prctl, getppid
    // and raise, which are async-signal-safe; it neither allocates nor takes locks.
    unsafe {
        cmd.pre_exec(move || {
            cvt(libc::prctl(
                libc::PR_SET_PDEATHSIG,
                sig as libc::c_ulong,
                0,
                0,
                0,
            ))?;
            // The parent may have died between fork and prctl: then no signal would come.
            if libc::getppid() != parent {
                libc::raise(sig);
            }
            Ok(())
        });
    }
}

/// Asks for `sig` when this process's parent dies (`PR_SET_PDEATHSIG`), from inside the
/// process: an exec that raises privileges (a set-user-ID or set-group-ID program, or one with
/// file capabilities) clears what [`die_with_parent`] set up before it. `false` if `parent`
/// is no longer this process's parent (it died before the call): no signal will come then, and
/// the caller must act as if it had.
pub fn ask_parent_death_signal(parent: libc::pid_t, sig: libc::c_int) -> io::Result<bool> {
    // SAFETY: PR_SET_PDEATHSIG takes a signal number by value and touches no memory of ours.
    cvt(unsafe { libc::prctl(libc::PR_SET_PDEATHSIG, sig as libc::c_ulong, 0, 0, 0) })?;
    // Read after the request: a parent that dies later sends the signal, one that died before
    // has handed this process to a reaper already.
    // SAFETY: getppid has no preconditions and cannot fail.
    Ok(unsafe { libc::getppid() } == parent)
}

/// Names the calling thread (`PR_SET_NAME`; for the main thread, the process: `/proc/PID/comm`,
/// what `ps` and `pkill` see), cut to 15 bytes by the kernel.
pub fn set_process_name(name: &str) -> io::Result<()> {
    let name = cstring(name)?;
    // SAFETY: PR_SET_NAME reads at most 16 bytes from a NUL-terminated string, which `name`
    // is and which outlives the call.
    cvt(unsafe { libc::prctl(libc::PR_SET_NAME, name.as_ptr() as libc::c_ulong, 0, 0, 0) })?;
    Ok(())
}

/// Whether capability `cap` is in this process's effective set (`CapEff` in
/// `/proc/self/status`); `false` if that cannot be read.
pub fn has_effective_capability(cap: u32) -> bool {
    let Ok(status) = std::fs::read_to_string("/proc/self/status") else {
        return false;
    };
    status
        .lines()
        .find_map(|l| l.strip_prefix("CapEff:"))
        .and_then(|v| u64::from_str_radix(v.trim(), 16).ok())
        .is_some_and(|mask| cap < 64 && mask & (1 << cap) != 0)
}

/// `mlockall(MCL_CURRENT | MCL_FUTURE)`.
pub fn lock_all_memory() -> io::Result<()> {
    mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE)
}

/// Gives back malloc's slack above the heap's top beyond `pad` bytes, and keeps future growth
/// to `pad` above what is asked (`M_TOP_PAD`; glibc's default is 128 KiB). Setting it also
/// freezes glibc's mmap and trim thresholds, which it would otherwise raise after the first
/// large free (so that a buffer allocated and freed every round comes from the heap instead
/// of a fresh, populated and locked, mapping each time): they are set here to what that
/// raising would reach for blocks below `mmap_threshold` (trimmed above twice that). Best
/// effort: the calls only tune the allocator.
pub fn trim_heap(pad: usize, mmap_threshold: usize) {
    #[cfg(target_env = "gnu")]
    {
        let int = |v: usize| libc::c_int::try_from(v).unwrap_or(libc::c_int::MAX);
        // SAFETY: allocator tuning with plain integers; glibc's malloc takes its own locks.
        unsafe {
            libc::mallopt(libc::M_TOP_PAD, int(pad));
            libc::mallopt(libc::M_MMAP_THRESHOLD, int(mmap_threshold));
            libc::mallopt(libc::M_TRIM_THRESHOLD, int(2 * mmap_threshold));
            libc::malloc_trim(pad);
        }
    }
    // musl's allocator has none of these knobs: it keeps no slack above what is asked, and
    // serves blocks from about 128 KiB up from mappings of their own, unmapped when freed (so
    // a block that large allocated every round is a new mapping, populated and locked under
    // `MCL_FUTURE`, each time: docs/writing-a-component.md, "Small replicas").
    #[cfg(not(target_env = "gnu"))]
    let _ = (pad, mmap_threshold);
}

/// `MLOCK_ONFAULT` for `mlock2` (Linux >= 4.4; not exported by the `libc` crate for every
/// target).
const MLOCK_ONFAULT: libc::c_uint = 1;

/// Turns `len` bytes at `addr` (page-aligned, holding no data the process needs: the unused
/// part of its stack, an idle alternate signal stack) from locked and populated into locked on
/// fault: unlocks them, drops their pages, and locks the range again with `MLOCK_ONFAULT`, so
/// that a page is locked when first touched. On an error the range may be left unlocked (a
/// later touch is an ordinary fault).
///
/// # Safety
/// Nothing in `addr..addr + len` may be live, now or once this returns: its pages are dropped,
/// and read back as zeros (in a private mapping of a file, as the file's bytes; in a shared
/// mapping, as they were). Something that runs in between, such as a signal handler, may use
/// the range only as scratch that is dead again when it returns.
pub unsafe fn lock_on_fault_instead(addr: usize, len: usize) -> io::Result<()> {
    let ptr = addr as *mut libc::c_void;
    // SAFETY: unlocking has no memory-safety effect.
    cvt(unsafe { libc::munlock(ptr, len) })?;
    // SAFETY: the caller guarantees that nothing in `addr..addr + len` is in use;
    // MADV_DONTNEED on private anonymous memory makes the next touch read zeros.
    cvt(unsafe { libc::madvise(ptr, len, libc::MADV_DONTNEED) })?;
    // SAFETY: mlock2 with a range and a flag; locking has no memory-safety effect.
    cvt_long(unsafe { libc::syscall(libc::SYS_mlock2, ptr, len, MLOCK_ONFAULT) })?;
    Ok(())
}

/// The pages of the main program's `PT_GNU_RELRO` segment, `(start, len)`, as the dynamic
/// linker protects them: from the page the segment starts in to the last page it fills. That
/// is the data only relocation at start writes (vtables, function pointers, the global offset
/// table), to be made read-only once it is done. `None` when the program has no such segment
/// or it fills no page. The dynamic linker protects it for a dynamically linked program;
/// musl's start-up code for a statically linked position-independent one does not.
pub fn main_program_relro(page: usize) -> Option<(usize, usize)> {
    /// What the callback looks for and what it found.
    struct Search {
        /// The main program's program header table (`AT_PHDR`).
        phdr: usize,
        found: Option<(usize, usize)>,
    }
    /// `dl_iterate_phdr`'s callback: in the object whose program headers are the main
    /// program's, records the segment's address and size, and stops.
    unsafe extern "C" fn look(
        info: *mut libc::dl_phdr_info,
        _size: libc::size_t,
        data: *mut libc::c_void,
    ) -> libc::c_int {
        // SAFETY: `dl_iterate_phdr` passes an `info` valid for the duration of this call, and
        // `data` is the `Search` that `main_program_relro` lent it below, alive and not
        // otherwise borrowed while the iteration runs.
        let (info, search) = unsafe { (&*info, &mut *data.cast::<Search>()) };
        if info.dlpi_phdr.is_null() || info.dlpi_phdr as usize != search.phdr {
            return 0;
        }
        // SAFETY: the C library's program header table of the object has `dlpi_phnum` entries
        // at `dlpi_phdr`, mapped for the life of the object.
        let headers =
            unsafe { std::slice::from_raw_parts(info.dlpi_phdr, usize::from(info.dlpi_phnum)) };
        search.found = headers
            .iter()
            .find(|h| h.p_type == libc::PT_GNU_RELRO)
            .and_then(|h| {
                let at = (info.dlpi_addr as usize).checked_add(h.p_vaddr as usize)?;
                Some((at, h.p_memsz as usize))
            });
        1
    }
    // SAFETY: getauxval reads the auxiliary vector the kernel gave the process; 0 if absent.
    let phdr = unsafe { libc::getauxval(libc::AT_PHDR) } as usize;
    if phdr == 0 {
        return None;
    }
    let mut search = Search { phdr, found: None };
    // SAFETY: the callback only reads what the C library passes it and writes `search`, which
    // outlives the call.
    unsafe { libc::dl_iterate_phdr(Some(look), (&raw mut search).cast::<libc::c_void>()) };
    let (addr, len) = search.found?;
    // Rounded down at both ends, as glibc's `_dl_protect_relro` and musl's `reloc_all` do. The
    // linker puts the segment at the head of the writable load segment, so what precedes it
    // in its first page is no writable data; its end is page-aligned by the linker, or the
    // page it ends in stays writable.
    let start = addr & !(page - 1);
    let end = addr.checked_add(len)? & !(page - 1);
    (end > start).then_some((start, end - start))
}

/// Makes `len` bytes at `addr` (page-aligned) read-only: a write to them is then a SIGSEGV.
///
/// # Safety
/// Nothing may write to `addr..addr + len` from now on (the caller's knowledge: the relocated
/// read-only data of [`main_program_relro`], after start-up).
pub unsafe fn make_read_only(addr: usize, len: usize) -> io::Result<()> {
    // SAFETY: changes protection only; the caller guarantees that no write is due there.
    cvt(unsafe { libc::mprotect(addr as *mut libc::c_void, len, libc::PROT_READ) })?;
    Ok(())
}

/// This thread's alternate signal stack, `(start, len)`, while it is set and the thread is not
/// running on it (Rust's runtime gives every thread one, for the handler that reports a stack
/// overflow).
pub fn idle_alternate_stack() -> Option<(usize, usize)> {
    // SAFETY: `stack_t` is plain data; all zeros is a valid value to be overwritten.
    let mut current: libc::stack_t = unsafe { std::mem::zeroed() };
    // SAFETY: a null new stack only asks; the kernel writes the current one to `current`.
    cvt(unsafe { libc::sigaltstack(std::ptr::null(), &mut current) }).ok()?;
    let unused = current.ss_flags & (libc::SS_DISABLE | libc::SS_ONSTACK) == 0;
    (unused && !current.ss_sp.is_null()).then_some((current.ss_sp as usize, current.ss_size))
}

/// `MCL_ONFAULT` (Linux ≥ 4.4; the value is the same on every architecture Linux has, and glibc's
/// `libc` crate does not export it for x86-64).
const MCL_ONFAULT: libc::c_int = 4;

/// Locks the pages of the current mappings as they are faulted in (`mlockall(MCL_CURRENT |
/// MCL_ONFAULT)`: pages present now are locked at once, the others when first touched, nothing
/// is populated up front), and every future mapping in full (`mlockall(MCL_FUTURE)`, which
/// leaves the current mappings as they are). A kernel without `MCL_ONFAULT` (EINVAL) gets
/// both populated, as [`lock_all_memory`] does. Async-signal-safe: two or three system calls,
/// no allocation.
pub fn lock_memory_on_fault() -> io::Result<()> {
    mlockall_on_fault(libc::MCL_CURRENT)?;
    // MCL_FUTURE alone only sets the flags for future mappings.
    mlockall(libc::MCL_FUTURE)
}

/// Locks every page, present or future, as it is faulted in (`mlockall(MCL_CURRENT |
/// MCL_FUTURE | MCL_ONFAULT)`): nothing is populated up front. A kernel without `MCL_ONFAULT`
/// (EINVAL) gets [`lock_all_memory`] instead. Async-signal-safe: one or two system calls.
pub fn lock_used_memory() -> io::Result<()> {
    mlockall_on_fault(libc::MCL_CURRENT | libc::MCL_FUTURE)
}

/// Locks the pages of the current mappings (`mlockall(MCL_CURRENT)`, populating them all, or
/// with `on_fault` `MCL_CURRENT | MCL_ONFAULT`, locking each when first touched), but not those
/// of later mappings: under a `RLIMIT_MEMLOCK` (8 MiB for a user by default) `MCL_FUTURE` would
/// make every later allocation past the limit fail. A kernel without `MCL_ONFAULT` (EINVAL)
/// gets plain `MCL_CURRENT`.
pub fn lock_current_memory(on_fault: bool) -> io::Result<()> {
    if on_fault {
        mlockall_on_fault(libc::MCL_CURRENT)
    } else {
        mlockall(libc::MCL_CURRENT)
    }
}

/// `mlockall(flags | MCL_ONFAULT)`, or `mlockall(flags)` on a kernel without `MCL_ONFAULT`
/// (EINVAL).
fn mlockall_on_fault(flags: libc::c_int) -> io::Result<()> {
    match mlockall(flags | MCL_ONFAULT) {
        Err(e) if e.raw_os_error() == Some(libc::EINVAL) => mlockall(flags),
        r => r,
    }
}

fn mlockall(flags: libc::c_int) -> io::Result<()> {
    // SAFETY: flags only; locking memory has no memory-safety effect.
    cvt(unsafe { libc::mlockall(flags) })?;
    Ok(())
}

/// A path as a C string (for the few calls made without std).
pub fn cstring(s: &str) -> io::Result<CString> {
    CString::new(s).map_err(|_| io::Error::new(io::ErrorKind::InvalidInput, "NUL in path"))
}

/// CLOCK_MONOTONIC in nanoseconds (the clock all s3res events share; the protocol's).
pub use s3res_protocol::clock::monotonic_ns;

/// Takes ownership of an fd this process inherited from its parent (a port or the events pipe,
/// or one whose owner gave it up with `into_raw_fd`) and marks it close-on-exec, so it does not
/// leak into processes we start. Checks what the number allows: it is above the standard
/// streams and open (`EBADF` otherwise).
///
/// # Safety
///
/// Nothing else in this process may own `fd` or use it after this call (no other `OwnedFd`,
/// `File` or raw use of the number): the returned `OwnedFd` closes it. That cannot be told from
/// the number (a registry of adopted numbers fails when a closed number is reused); an fd named
/// by the plan the process was started with, adopted once, satisfies it.
pub unsafe fn try_adopt_inherited_fd(fd: RawFd) -> io::Result<OwnedFd> {
    if fd <= libc::STDERR_FILENO {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            "the standard streams are not adopted",
        ));
    }
    // SAFETY: F_GETFD on any integer only reads the fd table; EBADF if it is not open.
    let flags = cvt(unsafe { libc::fcntl(fd, libc::F_GETFD) })?;
    // SAFETY: F_SETFD with an integer flag touches no memory; the fd is open (checked above).
    cvt(unsafe { libc::fcntl(fd, libc::F_SETFD, flags | libc::FD_CLOEXEC) })?;
    // SAFETY: the fd is open (checked above), and the caller guarantees nothing else owns it.
    Ok(unsafe { OwnedFd::from_raw_fd(fd) })
}

/// Pids of the living children of `parent` (scans `/proc`; zombies included).
pub fn children_of(parent: libc::pid_t) -> Vec<libc::pid_t> {
    all_pids()
        .into_iter()
        .filter(|&pid| parent_pid(pid) == Some(parent))
        .collect()
}

/// Every pid in `/proc` now (empty if it cannot be read).
pub fn all_pids() -> Vec<libc::pid_t> {
    let Ok(dir) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    dir.filter_map(|e| e.ok()?.file_name().to_str()?.parse::<libc::pid_t>().ok())
        .collect()
}

/// What [`sweep_children`] did.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct SweepReport {
    /// Processes that got SIGKILL (each counted once).
    pub killed: usize,
    /// Children still present when the time limit ran out (stuck in the kernel).
    pub resisted: Vec<libc::pid_t>,
}

/// The child sweep: SIGKILLs every child of this process and reaps, again and again, until no
/// child is left or `limit` has passed. In a child subreaper (bootstrap, the voter) every
/// descendant whose parent dies is re-parented to us, so this reaches the whole subtree,
/// including processes forked after the first pass. Reaps *every* child: call it only where no
/// other code waits for a child of its own.
pub fn sweep_children(limit: Duration) -> SweepReport {
    let me = std::process::id() as libc::pid_t;
    let deadline = std::time::Instant::now() + limit;
    let mut report = SweepReport::default();
    let mut signalled: Vec<libc::pid_t> = Vec::new();
    loop {
        while let Ok(Some(_)) = reap_any() {}
        let children = children_of(me);
        if children.is_empty() {
            return report;
        }
        for &pid in &children {
            // The pid cannot be reused under us: it is our child until we reap it.
            if kill(pid, libc::SIGKILL).is_ok() && !signalled.contains(&pid) {
                signalled.push(pid);
                report.killed += 1;
            }
        }
        while let Ok(Some(_)) = reap_any() {}
        if std::time::Instant::now() >= deadline {
            report.resisted = children_of(me);
            return report;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// Takes `signals` through a file descriptor instead of handlers: blocks them in the calling
/// thread (call it before any thread exists, so that every thread inherits the mask) and
/// returns a non-blocking, close-on-exec signalfd that reads them. Children inherit the mask:
/// start them with [`start_with_signals_blocked`].
pub fn signal_fd(
    signals: &[nix::sys::signal::Signal],
) -> nix::Result<nix::sys::signalfd::SignalFd> {
    use nix::sys::signalfd::{SfdFlags, SignalFd};
    let mut mask = nix::sys::signal::SigSet::empty();
    for &s in signals {
        mask.add(s);
    }
    mask.thread_block()?;
    SignalFd::with_flags(&mask, SfdFlags::SFD_CLOEXEC | SfdFlags::SFD_NONBLOCK)
}

/// Takes ownership of an fd this process inherited at exec (a port), after checking it is open.
///
/// Crate-private: only [`crate::init`] calls it, once per port, guarded by the init-once flag, so
/// no other owner of these fd numbers exists in the process.
pub(crate) fn take_inherited_fd(fd: RawFd) -> io::Result<OwnedFd> {
    // SAFETY: F_GETFD on any integer only reads the fd table; EBADF if it is not open.
    cvt(unsafe { libc::fcntl(fd, libc::F_GETFD) })?;
    // SAFETY: the fd is open (checked just above) and, per this function's contract, nothing
    // else in the process owns it.
    Ok(unsafe { OwnedFd::from_raw_fd(fd) })
}

/// The access mode of an open fd: `O_RDONLY`, `O_WRONLY` or `O_RDWR`.
pub fn access_mode(fd: BorrowedFd<'_>) -> io::Result<libc::c_int> {
    // SAFETY: F_GETFL on a borrowed (hence open) fd touches no memory of ours.
    let flags = cvt(unsafe { libc::fcntl(fd.as_raw_fd(), libc::F_GETFL) })?;
    Ok(flags & libc::O_ACCMODE)
}

/// Signature of an `SA_SIGINFO` handler.
pub type SigInfoHandler = extern "C" fn(libc::c_int, *mut libc::siginfo_t, *mut libc::c_void);

/// Installs `handler` for `sig` with `SA_SIGINFO | extra_flags` and an empty extra mask (the
/// signal itself is blocked while its handler runs, as usual).
///
/// # Safety
///
/// `handler` runs at any instruction of the thread the signal interrupts, so it must be
/// async-signal-safe: no allocation, no locks, no `std` I/O or formatting, and it may touch
/// shared state only through atomics (or through state the interrupted code cannot be using,
/// as the restart handler's own statics). Otherwise it can deadlock or race with the code it
/// interrupted.
pub unsafe fn install_siginfo_handler(
    sig: libc::c_int,
    handler: SigInfoHandler,
    extra_flags: libc::c_int,
) -> io::Result<()> {
    // SAFETY: sigaction is plain old data; all-zero is a valid value (empty mask, no flags).
    let mut sa: libc::sigaction = unsafe { std::mem::zeroed() };
    sa.sa_sigaction = handler as usize;
    sa.sa_flags = libc::SA_SIGINFO | extra_flags;
    // SAFETY: `sa.sa_mask` is a valid sigset_t to initialise.
    unsafe { libc::sigemptyset(&mut sa.sa_mask) };
    // SAFETY: `sa` is fully initialised and outlives the call; a null old-action is allowed.
    // That `handler` is async-signal-safe is this function's precondition.
    cvt(unsafe { libc::sigaction(sig, &sa, std::ptr::null_mut()) })?;
    Ok(())
}

/// Sets `sig` to `SIG_IGN`.
pub fn ignore_signal(sig: libc::c_int) -> io::Result<()> {
    // SAFETY: SIG_IGN is a valid disposition for every catchable signal; no memory is shared.
    if unsafe { libc::signal(sig, libc::SIG_IGN) } == libc::SIG_ERR {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

/// Signals blocked for the calling thread until the guard is dropped (then the previous mask
/// comes back, and a signal that arrived meanwhile is delivered at that moment).
pub struct BlockedSignal {
    old: libc::sigset_t,
}

/// Blocks `sig` for the calling thread; see [`BlockedSignal`].
pub fn block_signal(sig: libc::c_int) -> io::Result<BlockedSignal> {
    // SAFETY: sigset_t is plain old data; sigemptyset/sigaddset initialise it fully.
    let mut set: libc::sigset_t = unsafe { std::mem::zeroed() };
    // SAFETY: `set` is a valid sigset_t; sigemptyset/sigaddset only write into it.
    unsafe {
        libc::sigemptyset(&mut set);
        libc::sigaddset(&mut set, sig);
    }
    block(&set)
}

/// Blocks every signal that can be blocked for the calling thread; see [`BlockedSignal`].
/// Async-signal-safe (`pthread_sigmask`).
pub fn block_all_signals() -> io::Result<BlockedSignal> {
    // SAFETY: sigset_t is plain old data and sigfillset initialises it fully.
    let mut set: libc::sigset_t = unsafe { std::mem::zeroed() };
    // SAFETY: `set` is a valid sigset_t; sigfillset only writes into it.
    unsafe { libc::sigfillset(&mut set) };
    block(&set)
}

/// Adds `set` to the calling thread's blocked signals until the guard is dropped.
fn block(set: &libc::sigset_t) -> io::Result<BlockedSignal> {
    // SAFETY: sigset_t is plain old data; pthread_sigmask fills it before it is read.
    let mut old: libc::sigset_t = unsafe { std::mem::zeroed() };
    // SAFETY: both pointers are valid for the call; pthread_sigmask returns an error number.
    let r = unsafe { libc::pthread_sigmask(libc::SIG_BLOCK, set, &mut old) };
    if r != 0 {
        return Err(io::Error::from_raw_os_error(r));
    }
    Ok(BlockedSignal { old })
}

impl Drop for BlockedSignal {
    fn drop(&mut self) {
        // SAFETY: `self.old` is the mask pthread_sigmask gave us; setting it cannot fail with a
        // valid `how` and valid pointers.
        unsafe { libc::pthread_sigmask(libc::SIG_SETMASK, &self.old, std::ptr::null_mut()) };
    }
}

/// `_exit(2)`: ends the process at once, without running atexit handlers or flushing stdio
/// (async-signal-safe; the only way out of a forked child that must not touch shared state).
pub fn exit_now(code: libc::c_int) -> ! {
    // SAFETY: _exit never returns and touches no memory of ours.
    unsafe { libc::_exit(code) }
}

/// Lets the other runnable threads of this CPU's priority run first (`sched_yield`); it
/// cannot fail on Linux.
pub fn yield_cpu() {
    // SAFETY: no arguments.
    unsafe { libc::sched_yield() };
}

/// Pid of the calling process.
pub fn getpid() -> libc::pid_t {
    // SAFETY: getpid has no arguments and cannot fail.
    unsafe { libc::getpid() }
}

/// The value a `sigqueue` sender attached to a signal, read in an `SA_SIGINFO` handler; `None`
/// when the signal came without one (`kill`). Only reads memory: async-signal-safe.
pub fn queued_value(info: &libc::siginfo_t) -> Option<i32> {
    if info.si_code != libc::SI_QUEUE {
        return None;
    }
    // SAFETY: for SI_QUEUE the kernel filled in si_value (the sigqueue payload). The value
    // travels in a pointer-sized union; `sigqueue` above stores the int sign-extended in the
    // pointer, so truncating it back gives the int.
    Some(unsafe { info.si_value() }.sival_ptr as isize as i32)
}

/// Sets a socket's send and receive timeouts. Async-signal-safe (one system call each).
pub fn set_socket_timeouts(sock: RawFd, timeout: Duration) -> io::Result<()> {
    let tv = libc::timeval {
        tv_sec: timeout.as_secs() as _,
        tv_usec: timeout.subsec_micros() as _,
    };
    for opt in [libc::SO_RCVTIMEO, libc::SO_SNDTIMEO] {
        // SAFETY: `tv` is a valid timeval for the duration of the call and its size is passed.
        cvt(unsafe {
            libc::setsockopt(
                sock,
                libc::SOL_SOCKET,
                opt,
                (&tv as *const libc::timeval).cast(),
                std::mem::size_of::<libc::timeval>() as libc::socklen_t,
            )
        })?;
    }
    Ok(())
}

// ----- scheduling: policy, priority, nice value, CPU affinity -----------------------------
//
// These act on any process we may act on (`pid` 0 is the caller). They are used by the voter
// on itself and its replicas, and by bootstrap on unprotected components; a refusal (EPERM
// without CAP_SYS_NICE, EINVAL for a CPU outside the cpuset) is returned, never hidden.

/// A process's scheduling policy and its real-time priority (0 for the normal policies).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SchedPolicy {
    /// `libc::SCHED_OTHER`, `SCHED_RR`, `SCHED_FIFO`, ...
    pub policy: libc::c_int,
    pub priority: libc::c_int,
}

impl SchedPolicy {
    pub fn is_round_robin(self) -> bool {
        self.policy == libc::SCHED_RR
    }
}

/// A `sched_param` holding `priority` alone. musl's has more fields than glibc's (for
/// `SCHED_SPORADIC`, which Linux does not have), so it is built from zeroes.
fn sched_param(priority: libc::c_int) -> libc::sched_param {
    // SAFETY: `sched_param` is a plain C struct of integers (and, on musl, timespecs of
    // integers), for which all-zero bytes are a valid value.
    let mut param: libc::sched_param = unsafe { std::mem::zeroed() };
    param.sched_priority = priority;
    param
}

// The scheduler calls go to the kernel directly: musl's wrappers of `sched_setscheduler`,
// `sched_setparam`, `sched_getscheduler` and `sched_getparam` fail with ENOSYS by design
// (POSIX means them for processes, Linux applies them to threads), and glibc's are the bare
// system calls. One form serves replicas built on either C library.

/// `sched_setscheduler(pid, policy, priority)`.
fn set_scheduler(pid: libc::pid_t, policy: libc::c_int, priority: libc::c_int) -> io::Result<()> {
    let param = sched_param(priority);
    // SAFETY: `param` is a valid sched_param read by the kernel during the call only.
    let r = unsafe {
        libc::syscall(
            libc::SYS_sched_setscheduler,
            pid,
            policy,
            std::ptr::from_ref(&param),
        )
    };
    cvt_long(r).map(drop)
}

/// `sched_setscheduler(pid, SCHED_RR, priority)`.
pub fn set_round_robin(pid: libc::pid_t, priority: libc::c_int) -> io::Result<()> {
    set_scheduler(pid, libc::SCHED_RR, priority)
}

/// `sched_setscheduler(pid, SCHED_OTHER, 0)`: back to the normal time-sharing policy.
pub fn set_normal_policy(pid: libc::pid_t) -> io::Result<()> {
    set_scheduler(pid, libc::SCHED_OTHER, 0)
}

/// `sched_setparam(pid, priority)`: a new real-time priority within the current policy (the
/// cheap call the voter makes at every turn of a sequential round).
pub fn set_rt_priority(pid: libc::pid_t, priority: libc::c_int) -> io::Result<()> {
    let param = sched_param(priority);
    // SAFETY: `param` is a valid sched_param read by the kernel during the call only.
    let r = unsafe { libc::syscall(libc::SYS_sched_setparam, pid, std::ptr::from_ref(&param)) };
    cvt_long(r).map(drop)
}

/// `sched_getscheduler` and `sched_getparam` of `pid`.
pub fn sched_policy(pid: libc::pid_t) -> io::Result<SchedPolicy> {
    // SAFETY: integer argument only.
    let policy = cvt_long(unsafe { libc::syscall(libc::SYS_sched_getscheduler, pid) })?;
    let mut param = sched_param(0);
    // SAFETY: `param` is a valid out-pointer for the duration of the call.
    let r = unsafe {
        libc::syscall(
            libc::SYS_sched_getparam,
            pid,
            std::ptr::from_mut(&mut param),
        )
    };
    cvt_long(r)?;
    Ok(SchedPolicy {
        // The kernel ORs `SCHED_RESET_ON_FORK` into the policy of a process that has it
        // (`chrt -R`, systemd's `CPUSchedulingResetOnFork=`): without the flag, such a process
        // under SCHED_RR would read as some other policy, and a caller that tells RR by
        // equality would take it for a time-shared one. A policy is a small integer.
        policy: (policy as libc::c_int) & !libc::SCHED_RESET_ON_FORK,
        priority: param.sched_priority,
    })
}

/// `setpriority(PRIO_PROCESS, pid, nice)`. Without CAP_SYS_NICE a nice value can only go up
/// (weaker), never back down below the process's current one (or RLIMIT_NICE).
pub fn set_nice(pid: libc::pid_t, nice: libc::c_int) -> io::Result<()> {
    // SAFETY: integer arguments only.
    cvt(unsafe { libc::setpriority(libc::PRIO_PROCESS, pid as libc::id_t, nice) })?;
    Ok(())
}

/// `getpriority(PRIO_PROCESS, pid)`: the nice value (-20..=19).
pub fn nice_of(pid: libc::pid_t) -> io::Result<libc::c_int> {
    // getpriority may legitimately return -1, so success is told by errno, cleared first.
    // SAFETY: __errno_location returns this thread's errno slot, always valid to write.
    unsafe { *libc::__errno_location() = 0 };
    // SAFETY: integer arguments only.
    let nice = unsafe { libc::getpriority(libc::PRIO_PROCESS, pid as libc::id_t) };
    let e = io::Error::last_os_error();
    if nice == -1 && e.raw_os_error() != Some(0) {
        return Err(e);
    }
    Ok(nice)
}

/// `sched_setaffinity(pid, cpus)`: the process may run only on `cpus`.
pub fn set_cpu_affinity(pid: libc::pid_t, cpus: &[usize]) -> io::Result<()> {
    let mut set = nix::sched::CpuSet::new();
    for &cpu in cpus {
        set.set(cpu).map_err(io::Error::from)?;
    }
    nix::sched::sched_setaffinity(nix::unistd::Pid::from_raw(pid), &set).map_err(io::Error::from)
}

/// `sched_getaffinity(pid)`: the CPUs `pid` may run on, ascending.
pub fn cpu_affinity(pid: libc::pid_t) -> io::Result<Vec<usize>> {
    let set =
        nix::sched::sched_getaffinity(nix::unistd::Pid::from_raw(pid)).map_err(io::Error::from)?;
    Ok((0..nix::sched::CpuSet::count())
        .filter(|&c| set.is_set(c).unwrap_or(false))
        .collect())
}

/// Number of online CPUs (at least 1).
pub fn online_cpus() -> usize {
    // SAFETY: sysconf takes an integer and returns one.
    let n = unsafe { libc::sysconf(libc::_SC_NPROCESSORS_ONLN) };
    n.max(1) as usize
}

/// This process's effective user id.
pub fn effective_uid() -> u32 {
    nix::unistd::geteuid().as_raw()
}

/// `tee(2)` without blocking: copies up to `len` bytes from the head of pipe `from` into pipe
/// `to` without consuming them. `Ok(0)`: `from` is empty and has no writer left.
pub fn tee(from: BorrowedFd<'_>, to: BorrowedFd<'_>, len: usize) -> io::Result<usize> {
    loop {
        // SAFETY: two pipe fds open for the borrow; tee copies between kernel buffers only.
        let n = unsafe {
            libc::tee(
                from.as_raw_fd(),
                to.as_raw_fd(),
                len,
                libc::SPLICE_F_NONBLOCK,
            )
        };
        if n >= 0 {
            return Ok(n as usize);
        }
        let e = io::Error::last_os_error();
        if e.kind() != io::ErrorKind::Interrupted {
            return Err(e);
        }
    }
}

/// `splice(2)` between two pipes without blocking: moves up to `len` bytes from the head of
/// pipe `from` to the tail of pipe `to` (the kernel moves its buffers: no copy). `Ok(0)`:
/// `from` is empty and has no writer left; `WouldBlock`: `from` is empty, or `to` is full.
pub fn splice_pipes(from: BorrowedFd<'_>, to: BorrowedFd<'_>, len: usize) -> io::Result<usize> {
    loop {
        // SAFETY: two pipe fds open for the borrow; null offsets are what splice takes for
        // pipes; no memory of ours is touched.
        let n = unsafe {
            libc::splice(
                from.as_raw_fd(),
                std::ptr::null_mut(),
                to.as_raw_fd(),
                std::ptr::null_mut(),
                len,
                libc::SPLICE_F_NONBLOCK | libc::SPLICE_F_MOVE,
            )
        };
        if n >= 0 {
            return Ok(n as usize);
        }
        let e = io::Error::last_os_error();
        if e.kind() != io::ErrorKind::Interrupted {
            return Err(e);
        }
    }
}

/// Everything readable from `fd` now, without blocking: reads while a zero-timeout poll says
/// there are bytes, until the end of the stream. For a pipe whose writer is gone (a dead
/// voter's), that is all it holds.
pub fn read_available(fd: RawFd) -> Vec<u8> {
    let mut out = Vec::new();
    let mut buf = [0u8; 16 * 1024];
    loop {
        let mut pfd = [libc::pollfd {
            fd,
            events: libc::POLLIN,
            revents: 0,
        }];
        if !matches!(ppoll(&mut pfd, Some(Duration::ZERO)), Ok(1))
            || pfd[0].revents & libc::POLLIN == 0
        {
            return out;
        }
        // SAFETY: `buf` is valid for writes of its length; `fd` is the caller's open fd.
        let n = unsafe { libc::read(fd, buf.as_mut_ptr().cast(), buf.len()) };
        if n <= 0 {
            return out;
        }
        out.extend_from_slice(&buf[..n as usize]);
    }
}

/// Bytes waiting in a pipe (`FIONREAD`; works on either end).
pub fn bytes_in_pipe(fd: BorrowedFd<'_>) -> io::Result<usize> {
    let mut n: libc::c_int = 0;
    // SAFETY: FIONREAD writes one c_int through the pointer, which is valid for that.
    cvt(unsafe { libc::ioctl(fd.as_raw_fd(), libc::FIONREAD, &mut n) })?;
    Ok(n.max(0) as usize)
}

/// A pipe's capacity (`F_GETPIPE_SZ`).
pub fn pipe_size(fd: BorrowedFd<'_>) -> io::Result<usize> {
    // SAFETY: fcntl with F_GETPIPE_SZ takes no pointer.
    Ok(cvt(unsafe { libc::fcntl(fd.as_raw_fd(), libc::F_GETPIPE_SZ) })? as usize)
}

/// Sets a pipe's capacity (`F_SETPIPE_SZ`); returns what the kernel made it.
pub fn set_pipe_size(fd: BorrowedFd<'_>, size: usize) -> io::Result<usize> {
    // SAFETY: fcntl with F_SETPIPE_SZ takes an integer, no pointer.
    Ok(
        cvt(unsafe { libc::fcntl(fd.as_raw_fd(), libc::F_SETPIPE_SZ, size as libc::c_int) })?
            as usize,
    )
}

#[cfg(test)]
mod tests {
    use std::os::fd::IntoRawFd;

    use super::*;

    /// A signal sent with `pidfd_sigqueue` arrives as `sigqueue`'s would: `SI_QUEUE`, the value
    /// (negative too), and the sender given. In a forked child (one thread), which blocks the
    /// signal and takes it with `sigtimedwait`: the test's other threads never see it.
    #[test]
    fn a_signal_queued_through_a_pidfd_carries_its_value_and_sender() {
        // SAFETY: the child makes only async-signal-safe calls (no allocation) and leaves by
        // `_exit`.
        let pid = unsafe { crate::restart::raw_fork() };
        assert!(pid >= 0, "fork failed");
        if pid == 0 {
            let code = (|| {
                // SAFETY: sigset calls on a local set; the mask of this single thread.
                let set = unsafe {
                    let mut set = std::mem::zeroed::<libc::sigset_t>();
                    libc::sigemptyset(&mut set);
                    libc::sigaddset(&mut set, libc::SIGUSR1);
                    libc::sigprocmask(libc::SIG_BLOCK, &set, std::ptr::null_mut());
                    set
                };
                // SAFETY: pidfd_open takes a pid and flags.
                let fd = unsafe { libc::syscall(libc::SYS_pidfd_open, getpid(), 0) };
                if fd < 0 {
                    return 10;
                }
                // SAFETY: `fd` was just opened and is owned here alone.
                let pidfd = unsafe { OwnedFd::from_raw_fd(fd as RawFd) };
                let sender = SignalSender { pid: 4242, uid: 77 };
                if pidfd_sigqueue(pidfd.as_fd(), libc::SIGUSR1, -7, sender).is_err() {
                    return 11;
                }
                // SAFETY: siginfo_t is plain data; all zeroes is a valid value.
                let mut info = unsafe { std::mem::zeroed::<libc::siginfo_t>() };
                let timeout = libc::timespec {
                    tv_sec: 10,
                    tv_nsec: 0,
                };
                // SAFETY: valid set, siginfo and timeout, alive for the call.
                if unsafe { libc::sigtimedwait(&set, &mut info, &timeout) } != libc::SIGUSR1 {
                    return 12;
                }
                if queued_value(&info) != Some(-7) {
                    return 13;
                }
                // SAFETY: for SI_QUEUE the kernel filled in the sender's pid and uid.
                if unsafe { (info.si_pid(), info.si_uid()) } != (4242, 77) {
                    return 14;
                }
                0
            })();
            exit_now(code);
        }
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        let code = loop {
            match reap(pid).expect("waitpid") {
                Some((_, ExitStatus::Code(c))) => break c,
                Some((_, ExitStatus::Signal(s))) => panic!("child killed by signal {s}"),
                None if std::time::Instant::now() > deadline => {
                    let _ = kill(pid, libc::SIGKILL);
                    let _ = reap(pid);
                    panic!("child did not finish in time");
                }
                None => std::thread::sleep(Duration::from_millis(5)),
            }
        };
        assert_eq!(
            code, 0,
            "10: no pidfd, 11: not sent, 12: not taken, 13: value, 14: sender"
        );
    }

    #[test]
    fn another_process_task_clock_is_exact_while_it_runs() {
        let mut child = std::process::Command::new("sh")
            .args(["-c", "while :; do :; done"])
            .spawn()
            .unwrap();
        let pid = child.id() as libc::pid_t;
        let clock = match TaskClock::open(pid) {
            Ok(c) => c,
            Err(e) => {
                child.kill().unwrap();
                child.wait().unwrap();
                // Where perf events are not allowed (perf_event_paranoid 3, no
                // CONFIG_PERF_EVENTS), the refusal is one of these, and the voter does without.
                let refused = [libc::EACCES, libc::EPERM, libc::ENOENT, libc::ENOSYS];
                assert!(refused.contains(&e.raw_os_error().unwrap_or(0)), "{e}");
                eprintln!("task clock refused here: {e}");
                return;
            }
        };
        let start = std::time::Instant::now();
        let first = clock.read().expect("a live child");
        let mut seen = first;
        // Far less than a scheduler tick apart, the count still moves on.
        while seen == first && start.elapsed() < Duration::from_secs(10) {
            std::thread::sleep(Duration::from_micros(200));
            seen = clock.read().expect("a live child");
        }
        child.kill().unwrap();
        child.wait().unwrap();
        assert!(seen > first, "{first} {seen}");
    }

    #[test]
    fn a_zombie_is_exiting_and_a_live_process_is_not() {
        assert!(!process_exiting(std::process::id() as libc::pid_t));
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let pid = child.id() as libc::pid_t;
        // Not reaped yet: a zombie once it has exited.
        until_zombie(pid);
        assert!(process_exiting(pid));
        child.wait().unwrap();
        // Gone counts as on its way out, too.
        assert!(process_exiting(pid));
    }

    /// Waits (bounded) until `pid`, our child, is a zombie.
    fn until_zombie(pid: libc::pid_t) {
        let start = std::time::Instant::now();
        while process_state(pid) != Some('Z') {
            assert!(
                start.elapsed() < Duration::from_secs(10),
                "{pid} did not exit"
            );
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    /// A child killed and reaped when dropped, also when the test fails.
    struct Reaped(std::process::Child);

    impl Drop for Reaped {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }

    #[test]
    fn a_zombie_tells_how_it_ended_before_it_is_reaped() {
        let spawn = |cmd: &str, args: &[&str]| {
            Reaped(std::process::Command::new(cmd).args(args).spawn().unwrap())
        };
        let Reaped(code) = &mut spawn("sh", &["-c", "exit 7"]);
        let Reaped(sleeper) = &mut spawn("sleep", &["30"]);
        let (code_pid, sleeper_pid) = (code.id() as libc::pid_t, sleeper.id() as libc::pid_t);
        assert_eq!(zombie_exit_status(sleeper_pid), None, "a live process");
        sleeper.kill().unwrap();
        until_zombie(code_pid);
        until_zombie(sleeper_pid);
        assert_eq!(zombie_exit_status(code_pid), Some(ExitStatus::Code(7)));
        assert_eq!(
            zombie_exit_status(sleeper_pid),
            Some(ExitStatus::Signal(libc::SIGKILL))
        );
        code.wait().unwrap();
        sleeper.wait().unwrap();
        assert_eq!(zombie_exit_status(code_pid), None, "reaped: gone");
    }

    #[test]
    fn a_pidfd_names_its_process_parent_until_it_is_reaped() {
        let mut sleeper = Reaped(
            std::process::Command::new("sleep")
                .arg("30")
                .spawn()
                .unwrap(),
        );
        let pid = sleeper.0.id() as libc::pid_t;
        let pidfd = pidfd_open(pid).unwrap();
        let me = std::process::id() as libc::pid_t;
        assert_eq!(parent_of(pidfd.as_fd(), pid), Some(me));
        assert_eq!(
            parent_of(pidfd.as_fd(), pid),
            parent_pid(pid),
            "as /proc says"
        );
        sleeper.0.kill().unwrap();
        until_zombie(pid);
        assert_eq!(parent_of(pidfd.as_fd(), pid), Some(me), "a zombie");
        sleeper.0.wait().unwrap();
        assert_eq!(parent_of(pidfd.as_fd(), pid), None, "reaped: gone");
    }

    #[test]
    fn an_fd_is_adopted_only_if_open() {
        // nix's pipe is not close-on-exec, like an fd inherited at exec.
        let (r, w) = nix::unistd::pipe().unwrap();
        let raw = r.into_raw_fd();
        // SAFETY: `raw` was just given up by its only owner (`into_raw_fd`).
        let owned = unsafe { try_adopt_inherited_fd(raw) }.unwrap();
        drop((owned, w));
        // A number that is not open (beyond any fd limit): refused, nothing owned.
        // SAFETY: nothing owns fd 2^30 (it is not open); the call returns an error.
        let closed = unsafe { try_adopt_inherited_fd(1 << 30) };
        assert_eq!(closed.unwrap_err().raw_os_error(), Some(libc::EBADF));
        // SAFETY: a standard stream is refused before anything is taken over.
        assert!(unsafe { try_adopt_inherited_fd(1) }.is_err());
    }
}
