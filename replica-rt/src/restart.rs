//! Restart by fork: how a healthy replica makes the replacement of a faulty one.
//!
//! # Signals
//!
//! - [`signals::RESTART`] (SIGUSR1), sent by the voter: fork; the child joins the voter in the
//!   faulty replica's place (handshake in [`crate::contract::handshake`]).
//! - SIGCHLD is set to `SIG_IGN` in replica mode, so the children a donor forks are reaped by the
//!   kernel when they die (the donor's code never waits for them). Components must therefore not
//!   rely on SIGCHLD or on waiting for children of their own.
//!
//! # Components must be single-threaded
//!
//! `fork` copies only the thread that takes the signal. Another thread's work, and any lock it
//! held, would be lost or stuck forever in the child. The page walk also relies on it.
//!
//! # What the handler does
//!
//! In the donor: copy what its input pipes hold (below), block every signal that can wait,
//! list its private writable mappings for the child's page walk (`cow::take_snapshot`),
//! `_Fork`, unblock, close the copies, return. (The child unblocks once it has joined.)
//! The donor carries on as if nothing happened.
//!
//! **Unread input.** The child must read exactly what the donor had not read yet at the fork,
//! on its own new pipes. The donor copies each input pipe's content with `tee(2)` (the pipe
//! keeps it; the donor reads it on as before) into a fresh pipe of the same size, right before
//! `_Fork`, in the same handler: nothing is read in between, so the copy is exactly what the
//! child has not read. The child sends the copies to the voter behind `Ready` (their lengths
//! in `Ready::frames_sent` at the inputs' positions), and the voter writes them at the head of
//! the child's new pipes. (The voter used to drain the donor's pipes into its own memory before
//! the RESTART and give the bytes back after the fork: a voter killed in between took input it
//! had committed long before with it, and the donor, finding its input short at the successor,
//! ended.) A copy that comes out short (a pipe the same size could not be made) means no fork:
//! the voter sees no child and tries again or starts a fresh replica.
//!
//! In the child:
//! 1. send [`Hello`] with the attempt's nonce and its pid on the donor's spare line where it has
//!    one (below), else on a new connection to the voter's socket (address prepared at init,
//!    so nothing is allocated here);
//! 2. while the voter checks who it is and sends its pipes, write-fault
//!    every resident private writable page of the mappings the donor listed right before the
//!    fork ([`crate::cow`], "The donor lists the mappings") so that the child has its own
//!    copy of every page it shared with the donor. This happens before `Ready`, so no physical
//!    page of private writable memory that holds live data is shared with the donor once the
//!    voter counts the child in (the main thread's stack below the stack pointer stays shared
//!    until written: `cow`'s dead stack);
//! 3. receive [`FdTransfer`] and the new pipe fds (`SCM_RIGHTS`), check them, `dup2` each onto its
//!    target number and close the received copy: the component's ports keep their numbers, now on
//!    the new pipes;
//! 4. answer [`Ready`] with its pid, the frames sent per output and the bytes of unread input
//!    per input so far, send those bytes (`splice` from the copies), and close the socket;
//! 5. open its own maps file for when it is a donor (`cow::open_own_maps`; the one
//!    inherited shows the donor's mappings);
//! 6. return: the child resumes exactly where the donor was interrupted. A blocking `read` that
//!    was interrupted is restarted (`SA_RESTART`), on the new fd with the same number;
//! 7. once it has answered, at its first moment between rounds ([`between_rounds`]): `mlockall`
//!    again, on fault (locks are not inherited over fork; see
//!    [`crate::memory::defer_fork_child_lock`] for why not before `Ready`), and make a spare
//!    line of its own.
//!
//! Any failure in the child ends it with `_exit(121)`: the voter sees the death or the timeout.
//!
//! Every call made is async-signal-safe: `_Fork`, `pthread_sigmask`, `pipe2`, `tee`, `splice`,
//! `ioctl` (`FIONREAD`, `PROCMAP_QUERY`), `socket`, `connect`, `recvmsg`, `dup2`, `fcntl`,
//! `close`, `send`, `getpid`, `open`, `read`, `fstat`, `mincore`, `madvise`,
//! `_exit`, plain memory accesses and atomics. Nothing allocates, formats, logs or takes a lock. `errno` is saved
//! and restored, so the interrupted code never sees it change.
//!
//! # The spare line
//!
//! Where the voter takes them (`ENV_SPARE_LINE`), a replica keeps one connection to the voter
//! ready for its next fork child ([`Spare`]): `socket`, the socket's timeouts and `connect`
//! in a fresh fork child cost about 30 µs on the project's VM (50 against 20 µs for a send on
//! an inherited connection, measured in C), and they lie on the restart's critical path. The
//! handler takes the line (`SPARE_LINE`, swapped for -1) right before `_Fork`; the child sends
//! its `Hello` on it, and connects as before only if that send fails (a voter replaced since
//! the line was made); the donor closes its copy after the fork. Both then want a new line,
//! made in normal context at the next [`between_rounds`] (replica-rt's `recv`, `recv_timeout`
//! or `wait_any` before it waits for input, `try_recv` before it looks; the voter's round is
//! answered by then), with restarts deferred while it
//! is made, so that a fork never copies half a line. A line the voter refused, or could not
//! take (a full backlog: the connect does not wait), is not tried again until the next fork.
//! A replica that rebinds to a voter's successor drops its line (it led to the dead voter)
//! and makes another at its next [`between_rounds`]; until then a child connects itself. That
//! can come before the successor has taken the other replicas back (an answer to finish, a
//! frame left in the old pipe), and the successor keeps it then too (the voter's `adopt`).
//! The preload library's programs make the next one in its `write`, once a line (or frame) to
//! stdout is whole — the answer is out, as at a `recv`. A program whose output never passes
//! there (C stdio writes from inside libc) has a line at start only: after its first fork its
//! children connect as without one. A component
//! that closed the line's number (and perhaps opened something else on it) has no line: the
//! handler checks the number's device and inode first, and neither writes to nor closes what
//! is not the line.
//!
//! # Output frames stay whole: restarts are deferred, not masked
//!
//! A fork in the middle of a large frame (more than a pipe holds, written in several `write`s)
//! would let the child finish the frame on its *new* output pipe, which would then start with
//! the tail of a frame; a fork between the write and `count_sent` would report a count the
//! pipe disagrees with. So [`crate::OutPort::send`] writes and counts each frame inside a
//! *deferral* ([`hold_restarts`] … [`release_restarts`], through the guard `RestartsHeld`), and the
//! preload library holds one while an unmodified program's stdout is mid-line. No system call
//! is made for it: a deferral is an atomic counter (`Deferral::depth`) and a RESTART that comes
//! meanwhile an atomic note (`Deferral::pending`), not a signal mask (it was a `pthread_sigmask`
//! pair per frame before, two system calls per frame per replica).
//!
//! - The handler (`on_restart`) reads its nonce from the siginfo (as before: `sigqueue`'s
//!   value, 0 for a plain `kill`). If `depth` is non-zero it only records the nonce in
//!   `pending` (one store) and returns: no fork. Otherwise it clears `pending` and forks at
//!   once, in the handler, as it always did.
//! - [`release_restarts`] decrements the depth; the one that brings it to zero then looks at
//!   `pending`, and if a restart is pending it holds again, takes the nonce and runs the
//!   same fork (`restart_now`, async-signal-safe, now in normal context), then releases
//!   again (and looks again). The depth is above zero while that fork runs, so a RESTART
//!   arriving then is recorded, not nested.
//! - `restart_now` keeps the handler's checks: the single-thread check (preload) comes before
//!   every fork, whichever path reaches it, and `errno` is saved and restored around it — the
//!   preload library's `write` returns to a C caller that may read `errno` after it.
//!
//! Every access is a `SeqCst` atomic (the handler runs on the same thread, so this is about the
//! compiler: nothing is moved across the depth's increment or decrement, and the frame's
//! `write`s and its count stay between them). Components are single-threaded (below), so
//! the counter is process-wide, no thread-local (which a handler cannot use safely anyway).
//!
//! The races, each closed:
//!
//! - **RESTART just before the deferral starts**: depth 0, the handler forks; the frame has
//!   not been written, the count does not include it, the child writes it on its new pipe.
//! - **RESTART inside** (during the `write`s, between the last `write` and the count, or after
//!   the count): recorded; the fork happens at the release, after the frame is whole and
//!   counted, so the child's output starts at a frame boundary and `Ready`'s count agrees
//!   with the donor's pipe. A blocked `write` interrupted by the handler returns what it wrote
//!   (or is restarted, `SA_RESTART`), and `send` writes the rest, as for any signal.
//! - **RESTART between the decrement to zero and the look at `pending`**: the handler
//!   sees depth 0, clears `pending` (its own, newer nonce supersedes the recorded one)
//!   and forks; the release then finds nothing pending. One fork, with the newest nonce.
//!   (Looking first and decrementing after would lose a RESTART that lands in between.)
//! - **RESTART between that look and the re-hold**: as above, the handler forks and clears;
//!   the release, holding again, takes nothing, releases and looks again.
//! - **Two RESTARTs inside one deferral**: the later nonce overwrites the earlier; one fork.
//!   The voter sends a donor a second RESTART only once its first attempt is over (joined, or
//!   failed: timed out), and then waits for the second attempt's nonce alone, so the newest is
//!   the one to answer. (A masked
//!   signal did worse: the kernel keeps the *first* of two pending standard signals, so the
//!   child answered with the abandoned attempt's nonce and was refused.)
//! - **RESTART while the deferred fork runs** (depth held): recorded; in the donor the release
//!   loop forks again for it afterwards (the voter abandoned the earlier attempt, so that
//!   child is refused as stale, as before). The fork child inherits the donor's
//!   `pending`, aimed at the donor's pid, and clears it first thing; a RESTART aimed at
//!   the child itself (after its `Ready`) is then recorded and run by the child's own release.
//! - **Nested deferrals** (the counter): only the outermost release forks.
//!
//! The cost for the voter is unchanged: a donor blocked writing a frame forks only once the
//! voter has drained enough of its output for the write to finish.

use std::mem::{size_of, MaybeUninit};
use std::sync::atomic::{AtomicBool, AtomicI32, AtomicU32, AtomicU64, Ordering};
use std::sync::OnceLock;

use crate::contract::handshake::{
    FdTransfer, Hello, Ready, Spare, CHILD_SOCKET_TIMEOUT_MS, HELLO_MAGIC, READY_MAGIC,
    SPARE_MAGIC, TRANSFER_MAGIC,
};
use crate::contract::{signals, FIRST_PORT_FD, MAX_HANDED_FDS, MAX_PORTS};
use crate::sys;

/// Exit status of a forked child that could not join the voter.
pub const CHILD_FAILED: libc::c_int = 121;

extern "C" {
    /// glibc ≥ 2.34: fork without running `pthread_atfork` handlers or taking malloc's locks,
    /// the one fork that POSIX lists as async-signal-safe.
    fn _Fork() -> libc::pid_t;
}

/// The voter's address, prepared at init: the handler may not allocate or format.
struct VoterAddr {
    addr: libc::sockaddr_un,
    len: libc::socklen_t,
}

static VOTER_ADDR: OnceLock<VoterAddr> = OnceLock::new();

/// The spare line (module docs): a connection to the voter made ahead for the next fork
/// child, above the port numbers; -1 while there is none.
static SPARE_LINE: AtomicI32 = AtomicI32::new(-1);
/// The device and inode of the spare line's socket: the component may close the number and
/// open something else on it, which must be neither written to nor closed.
static SPARE_LINE_DEV: AtomicU64 = AtomicU64::new(0);
static SPARE_LINE_ID: AtomicU64 = AtomicU64::new(0);
/// Whether this replica's voter takes spare lines (`ENV_SPARE_LINE`, read at init).
static SPARE_LINES: AtomicBool = AtomicBool::new(false);
/// A spare line is to be made at the next [`between_rounds`]: set at init and after every
/// fork, in the donor and in the child, where the voter takes them.
static SPARE_WANTED: AtomicBool = AtomicBool::new(false);

/// From now on this replica keeps a spare line for its fork children (module docs): its
/// voter takes them. Called once, from `init`.
pub(crate) fn use_spare_lines() {
    SPARE_LINES.store(true, Ordering::SeqCst);
    SPARE_WANTED.store(true, Ordering::SeqCst);
}

/// A new spare line is to be made at the next [`between_rounds`], where the voter takes
/// them. Async-signal-safe (atomics).
fn want_spare_line() {
    SPARE_WANTED.store(SPARE_LINES.load(Ordering::SeqCst), Ordering::SeqCst);
}

/// Drops the spare line (it led to a voter that is gone) and wants a new one, where the voter
/// takes them. Normal context only.
pub(crate) fn renew_spare_line() {
    let _held = RestartsHeld::new();
    let line = take_spare_line();
    if line >= 0 {
        close(line);
    }
    want_spare_line();
}

/// Does the work a fork (or init) left for the replica's next moment between rounds, if any:
/// a fork child locks its memory (`memory::lock_fork_child`, deferred from the handler), and
/// the spare line is made where one is wanted (module docs, "The spare line"). Two atomic
/// loads when there is nothing to do. Normal context only; restarts are deferred while the
/// line is made. Called where a replica has answered and is about to wait for input:
/// replica-rt's `recv`, `recv_timeout`, `wait_any` and `try_recv`, and the preload library's
/// `write` once a line (or frame) is whole. `errno` is left as it was.
pub fn between_rounds() {
    let unlocked = crate::memory::fork_child_unlocked();
    let line_wanted = SPARE_WANTED.load(Ordering::Relaxed);
    if !unlocked && !line_wanted {
        return;
    }
    let saved = errno();
    // Siblings on this CPU first: right after a fork the donor and its child both have work
    // here at their next `recv`, and the one that answers first would otherwise hold up the
    // other's answer by the time it takes (measured for the spare line alone: the first answer
    // after a 4 KiB restart 26 µs later).
    sys::yield_cpu();
    crate::memory::lock_fork_child();
    if line_wanted {
        make_wanted_spare_line();
    }
    set_errno(saved);
}

fn make_wanted_spare_line() {
    let _held = RestartsHeld::new();
    if !SPARE_WANTED.swap(false, Ordering::SeqCst) || SPARE_LINE.load(Ordering::SeqCst) >= 0 {
        return;
    }
    match make_spare_line() {
        Ok((line, (dev, ino))) => {
            SPARE_LINE_DEV.store(dev, Ordering::SeqCst);
            SPARE_LINE_ID.store(ino, Ordering::SeqCst);
            SPARE_LINE.store(line, Ordering::SeqCst);
        }
        Err(()) => tracing::debug!(
            "no spare line for the next fork child (the voter's socket refused it); \
             it will connect itself"
        ),
    }
}

/// Takes the spare line out of [`SPARE_LINE`] if this process still holds it: its number
/// still names the socket that was made for it (device and inode), else -1 and the number is
/// left alone. Async-signal-safe (`fstat`, atomics).
fn take_spare_line() -> libc::c_int {
    let line = SPARE_LINE.swap(-1, Ordering::SeqCst);
    let ours = line >= 0
        && crate::cow::file_id(line).is_some_and(|(dev, ino)| {
            dev == SPARE_LINE_DEV.load(Ordering::SeqCst)
                && ino == SPARE_LINE_ID.load(Ordering::SeqCst)
        });
    if ours {
        line
    } else {
        -1
    }
}

/// A new spare line: connected without waiting (a full backlog refuses it), with the child's
/// timeouts, announced with [`Spare`], and moved above the port numbers; with its device and
/// inode.
fn make_spare_line() -> Result<(libc::c_int, (u64, u64)), ()> {
    let timeout = std::time::Duration::from_millis(CHILD_SOCKET_TIMEOUT_MS);
    let sock = connect_voter(timeout, Backlog::Refuse)?;
    let spare = Spare {
        magic: SPARE_MAGIC,
        pid: sys::getpid(),
    };
    send_all(sock.0, &spare.to_bytes())?;
    // Above every port number, so that placing a fork child's pipes cannot replace it.
    let line = Fd(dup_above(sock.0, FIRST_PORT_FD + MAX_PORTS as libc::c_int)?);
    let id = crate::cow::file_id(line.0).ok_or(())?;
    let line = std::mem::ManuallyDrop::new(line);
    Ok((line.0, id))
}

/// What [`connect_voter`] does when the voter's socket has no room for another connection.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum Backlog {
    /// Wait for room, up to the timeout (a fork child, a replica rebinding).
    Wait,
    /// Fail at once (a spare line: made ahead, it is not worth a wait).
    Refuse,
}

/// Connects a new socket to the voter's address (prepared at init), with send and receive
/// timeouts; `Err(())` without an address (not a replica), when nobody listens, or (with
/// [`Backlog::Refuse`]) when the backlog is full. Async-signal-safe (`socket`, `setsockopt`,
/// `connect`, `fcntl`): the fork child connects with it in the handler.
pub(crate) fn connect_voter(timeout: std::time::Duration, backlog: Backlog) -> Result<Fd, ()> {
    let addr = VOTER_ADDR.get().ok_or(())?;
    let nonblocking = match backlog {
        Backlog::Wait => 0,
        Backlog::Refuse => libc::SOCK_NONBLOCK,
    };
    // SAFETY: integer arguments only.
    let fd = unsafe {
        libc::socket(
            libc::AF_UNIX,
            libc::SOCK_STREAM | libc::SOCK_CLOEXEC | nonblocking,
            0,
        )
    };
    if fd < 0 {
        return Err(());
    }
    let sock = Fd(fd);
    // A blocking connect waits for room at most the send timeout.
    sys::set_socket_timeouts(sock.0, timeout).map_err(|_| ())?;
    connect(sock.0, addr)?;
    // SAFETY: integer arguments only; a Unix socket has no other status flag set, so 0
    // clears O_NONBLOCK and nothing else.
    if backlog == Backlog::Refuse && unsafe { libc::fcntl(sock.0, libc::F_SETFL, 0) } != 0 {
        return Err(());
    }
    Ok(sock)
}

/// Whole frames sent so far, by port position (see [`FRAMES_SENT`]).
pub(crate) fn frames_sent() -> [u64; MAX_PORTS] {
    std::array::from_fn(|k| FRAMES_SENT[k].load(Ordering::Relaxed))
}

/// Pid of the donor, set in a freshly forked child; the runtime logs it once on the next send or
/// receive (the handler itself cannot log).
static FORKED_FROM: AtomicI32 = AtomicI32::new(0);

/// Whole frames sent on each port since exec, by port position (fd − [`FIRST_PORT_FD`]). Updated
/// by [`crate::OutPort::send`] inside a deferral (module docs), so at a fork it counts exactly the
/// frames that are whole in the donor's output pipes; the child reports it in [`Ready`].
///
/// [`FIRST_PORT_FD`]: crate::contract::FIRST_PORT_FD
static FRAMES_SENT: [AtomicU64; MAX_PORTS] = [const { AtomicU64::new(0) }; MAX_PORTS];

/// Counts one whole frame sent on the port at position `port` (see [`FRAMES_SENT`]).
pub(crate) fn count_sent(port: usize) {
    if let Some(n) = FRAMES_SENT.get(port) {
        n.fetch_add(1, Ordering::Relaxed);
    }
}

/// Port positions that are inputs (set at init: the handler cannot read the port map).
static INPUTS: [AtomicBool; MAX_PORTS] = [const { AtomicBool::new(false) }; MAX_PORTS];

/// Notes that the port at `position` is an input, whose unread bytes a fork child is given.
pub(crate) fn register_input(position: usize) {
    if let Some(flag) = INPUTS.get(position) {
        flag.store(true, Ordering::Relaxed);
    }
}

/// What the donor's input pipes held at the fork, per port position: the read end of a pipe
/// holding a copy (`-1`: nothing unread) and its length in bytes.
struct UnreadInput {
    copies: [libc::c_int; MAX_PORTS],
    bytes: [u64; MAX_PORTS],
}

impl UnreadInput {
    fn close(&self) {
        for &fd in self.copies.iter().filter(|&&fd| fd >= 0) {
            close(fd);
        }
    }
}

/// Copies what every input pipe holds (module docs, "Unread input"). `Err(())` if a copy came
/// out short; whatever was made is closed then.
fn copy_unread_input() -> Result<UnreadInput, ()> {
    let mut unread = UnreadInput {
        copies: [-1; MAX_PORTS],
        bytes: [0; MAX_PORTS],
    };
    for (position, flag) in INPUTS.iter().enumerate() {
        if !flag.load(Ordering::Relaxed) {
            continue;
        }
        let fd = FIRST_PORT_FD + position as libc::c_int;
        match copy_pipe(fd) {
            Ok(Some((copy, bytes))) => {
                unread.copies[position] = copy;
                unread.bytes[position] = bytes;
            }
            Ok(None) => {}
            Err(()) => {
                unread.close();
                return Err(());
            }
        }
    }
    Ok(unread)
}

/// A copy of what pipe `fd` holds, in a new pipe above the port numbers: its read end and
/// length; `None` if `fd` holds nothing (or is no pipe: a port that is not one has no unread
/// input to give).
fn copy_pipe(fd: libc::c_int) -> Result<Option<(libc::c_int, u64)>, ()> {
    let held = bytes_in_pipe(fd);
    if held <= 0 {
        return Ok(None);
    }
    let size = pipe_size(fd);
    if size < 0 {
        return Ok(None);
    }
    let mut ends = [-1 as libc::c_int; 2];
    // SAFETY: `ends` is a valid array of two fds for the kernel to fill.
    if unsafe { libc::pipe2(ends.as_mut_ptr(), libc::O_CLOEXEC) } != 0 {
        return Err(());
    }
    let [read_end, write_end] = ends;
    let copied = (|| {
        // A pipe as large as the one copied takes all it holds.
        if pipe_size(write_end) < size && set_pipe_size(write_end, size) < size {
            return Err(());
        }
        // SAFETY: integer arguments only; `tee` copies pipe buffers without consuming them,
        // and does not block (SPLICE_F_NONBLOCK).
        let n = unsafe { libc::tee(fd, write_end, held as usize, libc::SPLICE_F_NONBLOCK) };
        if n != held as isize {
            return Err(());
        }
        // Above every port number, so that placing the new pipes cannot replace it.
        dup_above(read_end, FIRST_PORT_FD + MAX_PORTS as libc::c_int)
    })();
    close(write_end);
    close(read_end);
    copied.map(|copy| Some((copy, held as u64)))
}

/// The capacity of pipe `fd` in bytes; negative if it is no pipe.
fn pipe_size(fd: libc::c_int) -> libc::c_int {
    // SAFETY: integer arguments only.
    unsafe { libc::fcntl(fd, libc::F_GETPIPE_SZ) }
}

/// Sets the capacity of pipe `fd`; the capacity now, negative if refused.
fn set_pipe_size(fd: libc::c_int, size: libc::c_int) -> libc::c_int {
    // SAFETY: integer arguments only.
    unsafe { libc::fcntl(fd, libc::F_SETPIPE_SZ, size) }
}

/// Bytes pipe `fd` holds now (`FIONREAD`); 0 where it cannot say.
fn bytes_in_pipe(fd: libc::c_int) -> libc::c_int {
    let mut held: libc::c_int = 0;
    // SAFETY: FIONREAD writes one int through the valid pointer given.
    let r = unsafe { libc::ioctl(fd, libc::FIONREAD, &mut held as *mut libc::c_int) };
    if r < 0 {
        0
    } else {
        held
    }
}

/// Sends all `bytes` of pipe `from` to socket `to` (the unread input behind `Ready`).
fn splice_all(from: libc::c_int, to: libc::c_int, bytes: u64) -> Result<(), ()> {
    let mut left = bytes as usize;
    while left > 0 {
        // SAFETY: integer arguments and null offsets (both ends are a pipe and a socket).
        let n = unsafe {
            libc::splice(
                from,
                std::ptr::null_mut(),
                to,
                std::ptr::null_mut(),
                left,
                libc::SPLICE_F_MOVE,
            )
        };
        match n {
            n if n > 0 => left -= n as usize,
            -1 if errno() == libc::EINTR => {}
            _ => return Err(()),
        }
    }
    Ok(())
}

/// A value of the pending nonce: a RESTART is pending, its nonce in the low 32 bits.
const PENDING: u64 = 1 << 32;

/// Where restarts are deferred (module docs, "Output frames stay whole"): one per process,
/// [`DEFERRAL`]; the unit tests make their own.
struct Deferral {
    /// Deferrals open now (nested ones count). RESTART forks only at zero.
    depth: AtomicU32,
    /// `PENDING | nonce` of the RESTART that came last while `depth` was above zero; 0 if none.
    pending: AtomicU64,
}

/// The process's deferral: held by [`crate::OutPort::send`] around each frame, by the preload
/// library while a line is incomplete, and read by the handler.
static DEFERRAL: Deferral = Deferral::new();

impl Deferral {
    const fn new() -> Self {
        Deferral {
            depth: AtomicU32::new(0),
            pending: AtomicU64::new(0),
        }
    }

    fn hold(&self) {
        self.depth.fetch_add(1, Ordering::SeqCst);
    }

    /// What the handler does with a RESTART carrying `nonce`: record it while deferred, else
    /// `restart` now (superseding any nonce recorded earlier that nobody has taken yet).
    /// Async-signal-safe: atomics only, then `restart`.
    fn signal(&self, nonce: u32, restart: impl FnOnce(u32)) {
        if self.depth.load(Ordering::SeqCst) > 0 {
            self.pending
                .store(PENDING | u64::from(nonce), Ordering::SeqCst);
        } else {
            self.pending.store(0, Ordering::SeqCst);
            restart(nonce);
        }
    }

    /// Ends one deferral; the outermost runs `restart` for a RESTART that came meanwhile,
    /// holding again while it runs, until none is pending. A release without a hold is ignored.
    fn release(&self, mut restart: impl FnMut(u32)) {
        loop {
            // Decrement first, look after: a RESTART landing in between finds depth 0 and
            // forks in its handler; looking first would leave it recorded and nobody to run it.
            let Ok(was) = self
                .depth
                .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |d| d.checked_sub(1))
            else {
                return;
            };
            if was != 1 || self.pending.load(Ordering::SeqCst) == 0 {
                return;
            }
            self.hold();
            let pending = self.pending.swap(0, Ordering::SeqCst);
            if pending != 0 {
                restart(pending as u32);
            }
        }
    }

    /// Drops a recorded RESTART (a fork child: it was aimed at the donor).
    fn forget_pending(&self) {
        self.pending.store(0, Ordering::SeqCst);
    }
}

/// Defers RESTART until the matching [`release_restarts`]: a RESTART that arrives meanwhile
/// forks there, after the caller's output is whole, instead of in its handler. No system call,
/// async-signal-safe. Holds nest; every hold must be ended by exactly one release. The preload
/// library holds while an unmodified program's stdout is mid-line; replica-rt's own
/// [`crate::OutPort::send`] holds around every frame.
pub fn hold_restarts() {
    DEFERRAL.hold();
}

/// Ends a [`hold_restarts`]. The outermost release forks for a RESTART that came meanwhile
/// (the newest one's nonce), in the caller's context, and returns in the donor and — once it
/// has joined the voter — in the child, as the handler would. `errno` is left as it was.
pub fn release_restarts() {
    DEFERRAL.release(restart_now);
}

/// [`hold_restarts`] until dropped.
#[must_use = "restarts are deferred only while the guard lives"]
pub(crate) struct RestartsHeld(());

impl RestartsHeld {
    pub(crate) fn new() -> Self {
        hold_restarts();
        RestartsHeld(())
    }
}

impl Drop for RestartsHeld {
    fn drop(&mut self) {
        release_restarts();
    }
}

/// The socket path does not fit in a `sockaddr_un` (or is empty).
#[derive(Debug, thiserror::Error)]
#[error("voter socket path {path:?} ({len} bytes) does not fit a Unix socket address (1 to {max} bytes)")]
pub struct PathTooLong {
    pub path: String,
    pub len: usize,
    pub max: usize,
}

/// Stores the voter's socket path for the handler. Called once, from `init`.
pub(crate) fn prepare(path: &str) -> Result<(), PathTooLong> {
    // SAFETY: sockaddr_un is plain old data; all-zero is valid (and NUL-terminates the path).
    let mut addr: libc::sockaddr_un = unsafe { std::mem::zeroed() };
    let bytes = path.as_bytes();
    // Keep one byte for the terminating NUL.
    let max = addr.sun_path.len() - 1;
    if bytes.len() > max || bytes.is_empty() {
        return Err(PathTooLong {
            path: path.to_owned(),
            len: bytes.len(),
            max,
        });
    }
    addr.sun_family = libc::AF_UNIX as libc::sa_family_t;
    for (dst, &b) in addr.sun_path.iter_mut().zip(bytes) {
        *dst = b as libc::c_char;
    }
    let len =
        (std::mem::offset_of!(libc::sockaddr_un, sun_path) + bytes.len() + 1) as libc::socklen_t;
    // A second init is refused before it gets here, so the cell is always empty.
    let _ = VOTER_ADDR.set(VoterAddr { addr, len });
    Ok(())
}

/// Installs the RESTART handler. `prepare` must have run.
pub(crate) fn install() -> std::io::Result<()> {
    // SAFETY: on_restart is async-signal-safe by construction (module docs): raw syscalls,
    // `_Fork`, fixed statics and atomics; no allocation, no lock, no formatting.
    unsafe { sys::install_siginfo_handler(signals::RESTART, on_restart, libc::SA_RESTART) }
}

/// The donor pid if this process was forked by the restart handler and nobody asked yet.
pub(crate) fn take_forked_from() -> Option<libc::pid_t> {
    match FORKED_FROM.swap(0, Ordering::Relaxed) {
        0 => None,
        pid => Some(pid),
    }
}

/// Forks with `_Fork`.
///
/// # Safety
///
/// If the calling process has other threads, the child may only do async-signal-safe work
/// (their locks are copied held) and must leave by `_exit`.
pub(crate) unsafe fn raw_fork() -> libc::pid_t {
    // SAFETY: plain fork() is not allowed in a signal handler: it runs pthread_atfork handlers
    // and takes malloc's locks, which the interrupted code may hold. _Fork does neither; it is
    // the bare system call plus glibc's own consistent bookkeeping of the new pid. The caller
    // upholds the contract above for whatever runs in the child.
    unsafe { _Fork() }
}

/// Set by [`refuse_fork_when_threaded`].
static REFUSE_WHEN_THREADED: std::sync::atomic::AtomicBool =
    std::sync::atomic::AtomicBool::new(false);

/// From now on the restart handler checks, before every fork, that the process has a single
/// thread, and refuses to fork (saying so on stderr) if it has more: a fork copies only the
/// calling thread. Replica-rt components are single-threaded by contract; the preload library
/// turns this on for unmodified programs, which promise nothing.
pub fn refuse_fork_when_threaded() {
    REFUSE_WHEN_THREADED.store(true, Ordering::SeqCst);
}

/// Threads of this process, from `/proc/self/stat` (field 20); `None` if it cannot be read.
/// Async-signal-safe: `open`, `read` and `close` on a stack buffer.
pub fn thread_count() -> Option<u64> {
    let mut buf = [0u8; 1024];
    // SAFETY: a NUL-terminated literal path; the fd is closed below.
    let fd = unsafe {
        libc::open(
            c"/proc/self/stat".as_ptr(),
            libc::O_RDONLY | libc::O_CLOEXEC,
        )
    };
    if fd < 0 {
        return None;
    }
    // SAFETY: `buf` is writable for its whole length.
    let n = unsafe { libc::read(fd, buf.as_mut_ptr().cast(), buf.len()) };
    // SAFETY: `fd` was opened above and is not used after this.
    unsafe { libc::close(fd) };
    let text = buf.get(..usize::try_from(n).ok()?)?;
    // The command name (field 2) may hold spaces and parentheses: count from the last `)`.
    let after = &text[text.iter().rposition(|&b| b == b')')? + 1..];
    let field = after
        .split(|&b| b == b' ')
        .filter(|f| !f.is_empty())
        .nth(17)?;
    field.iter().try_fold(0u64, |acc, &b| {
        b.is_ascii_digit()
            .then(|| acc.saturating_mul(10).saturating_add(u64::from(b - b'0')))
    })
}

extern "C" fn on_restart(_sig: libc::c_int, info: *mut libc::siginfo_t, _ctx: *mut libc::c_void) {
    // The attempt's nonce, kept (deferred) or taken onto the stack before the fork, so the
    // child has it.
    // SAFETY: the kernel passes a valid (or no) siginfo to an SA_SIGINFO handler.
    let info = unsafe { info.as_ref() };
    let nonce = info.and_then(sys::queued_value).unwrap_or(0) as u32;
    DEFERRAL.signal(nonce, restart_now);
}

/// The restart itself: fork, and in the child join the voter. Runs in the handler, or at the
/// release of a deferral (then in normal context); async-signal-safe either way. `errno` is
/// saved and restored, so neither the interrupted code nor the caller of a release sees it
/// change.
fn restart_now(nonce: u32) {
    let saved = errno();
    if REFUSE_WHEN_THREADED.load(Ordering::SeqCst) && thread_count() != Some(1) {
        const MSG: &[u8] = b"s3res: this program runs more than one thread; a fork copies only \
one, so it cannot be a recovery donor (refused)\n";
        // SAFETY: write(2) of a static buffer to stderr, async-signal-safe.
        unsafe { libc::write(libc::STDERR_FILENO, MSG.as_ptr().cast(), MSG.len()) };
        set_errno(saved);
        return;
    }
    let Ok(unread) = copy_unread_input() else {
        const MSG: &[u8] = b"s3res: could not copy this replica's unread input for a fork \
(a pipe as large as its input pipe was refused); not forking\n";
        // SAFETY: write(2) of a static buffer to stderr, async-signal-safe.
        unsafe { libc::write(libc::STDERR_FILENO, MSG.as_ptr().cast(), MSG.len()) };
        set_errno(saved);
        return;
    };
    // The child's page walk works from this list of our mappings, so nothing may map, unmap
    // or protect memory between the list and the fork, nor in the child before its walk: a
    // handler of the component's own (a preloaded C program's) could, so every signal that
    // can wait waits, in the donor until the fork is done, in the child until it has joined
    // (`cow`, "The donor lists the mappings"). Two system calls; a refusal (there is none for
    // a valid mask) leaves signals as they were.
    let blocked = sys::block_all_signals().ok();
    crate::cow::take_snapshot();
    // The spare line is the child's (module docs, "The spare line").
    let line = take_spare_line();
    // SAFETY: components are single-threaded (module doc), and the child runs only
    // async-signal-safe code (`become_replacement`) before returning to the component.
    let pid = unsafe { raw_fork() };
    if pid == 0 {
        // A RESTART recorded in the donor after its nonce was taken was aimed at the donor,
        // which keeps its own copy and forks for it; it is not the child's.
        DEFERRAL.forget_pending();
        become_replacement(nonce, &unread, line);
        // The copies and the line were closed as the child joined.
        drop(blocked);
        set_errno(saved);
        return;
    }
    // The signals that waited come now (in the handler, only those its own mask lets through).
    drop(blocked);
    // In the donor: the copies and the line were the child's. A failed fork (-1) is seen by
    // the voter as a connect timeout.
    unread.close();
    if line >= 0 {
        close(line);
    }
    want_spare_line();
    set_errno(saved);
}

/// The child's part. Returns only when it has taken the faulty replica's place. `line` is the
/// donor's spare line, or -1.
fn become_replacement(nonce: u32, unread: &UnreadInput, line: libc::c_int) {
    let donor = getppid();
    crate::inject::clear_pending();
    let Ok(sock) = join_voter(nonce, line) else {
        sys::exit_now(CHILD_FAILED);
    };
    // The voter now checks who we are and sends our pipes; meanwhile we do the part of the
    // restart that does not need them (on two CPUs the two overlap, and on one the voter,
    // which outranks us, does its part as soon as it is woken). Own pages *before* `Ready`:
    // the voter counts us as a member of the next
    // round from `Ready` on, and a page walk after it (milliseconds for a few MiB, tens of ms
    // for tens of MiB) would make us miss that round's deadline and be killed as hung, again
    // and again. It also makes the voter's recovery time the time to a replica that can answer.
    //
    // Locks are not inherited over fork; the child locks again at its first moment between
    // rounds, once it has answered (`memory::defer_fork_child_lock`): nothing needs the lock
    // to answer, and it was the dearest single call of the child's part.
    crate::memory::defer_fork_child_lock();
    // Break the sharing of every resident private writable page.
    // SAFETY: the fork child has a single thread, and has mapped nothing since the fork.
    let _ = unsafe { crate::cow::break_cow_sharing_after_fork() };
    // Our pipes, onto the donor's fd numbers (nothing has used the donor's copies meanwhile:
    // this runs in the restart handler, before the component's code).
    if take_pipes(&sock).is_err() {
        sys::exit_now(CHILD_FAILED);
    }
    // Whole frames the donor had sent per port at the fork (stream mode lines our output up
    // with the donor's from these).
    let mut frames_sent = [0u64; MAX_PORTS];
    for (dst, n) in frames_sent.iter_mut().zip(&FRAMES_SENT) {
        *dst = n.load(Ordering::Relaxed);
    }
    // At the inputs' positions: the bytes of unread input that follow `Ready`.
    for (position, flag) in INPUTS.iter().enumerate() {
        if flag.load(Ordering::Relaxed) {
            frames_sent[position] = unread.bytes[position];
        }
    }
    let ready = Ready {
        magic: READY_MAGIC,
        pid: sys::getpid(),
        frames_sent,
    };
    // A voter that gave up meanwhile has closed the connection: leave.
    if send_all(sock.0, &ready.to_bytes()).is_err() {
        sys::exit_now(CHILD_FAILED);
    }
    for (position, &copy) in unread.copies.iter().enumerate() {
        if copy >= 0 && splice_all(copy, sock.0, unread.bytes[position]).is_err() {
            sys::exit_now(CHILD_FAILED);
        }
    }
    unread.close();
    drop(sock);
    // Our own maps file, for when we are a donor (the inherited one shows the donor's
    // mappings). After `Ready`: it is not needed before.
    crate::cow::open_own_maps();
    crate::stamps::forked(ready.pid);
    // A line of our own for our own fork children, made at our next `recv`.
    want_spare_line();
    FORKED_FROM.store(donor, Ordering::Relaxed);
}

/// Steps 1–2 of the handshake: say which attempt we are (`Hello`), on the donor's spare line
/// `line` if it still leads to the voter, else on a new connection; returns the connection.
/// `Err(())` carries no detail: there is nobody to tell but the voter, which sees the exit.
fn join_voter(nonce: u32, line: libc::c_int) -> Result<Fd, ()> {
    let hello = Hello {
        magic: HELLO_MAGIC,
        nonce,
        pid: sys::getpid(),
    }
    .to_bytes();
    if line >= 0 {
        // Made with the same timeouts as below. A failed send closes it (a voter replaced
        // since: the line leads nowhere).
        let line = Fd(line);
        if send_all(line.0, &hello).is_ok() {
            return Ok(line);
        }
    }
    // A voter that gave up on this attempt never answers: time out and exit, rather than
    // keep a whole copy of the donor's memory waiting forever.
    let timeout = std::time::Duration::from_millis(CHILD_SOCKET_TIMEOUT_MS);
    let sock = connect_voter(timeout, Backlog::Wait)?;
    send_all(sock.0, &hello)?;
    Ok(sock)
}

/// Step 3: receive our pipes and put them on their fd numbers.
fn take_pipes(sock: &Fd) -> Result<(), ()> {
    let mut transfer = FdTransfer {
        magic: 0,
        count: 0,
        targets: [-1; MAX_HANDED_FDS],
    };
    let mut received = [-1 as libc::c_int; MAX_HANDED_FDS];
    let n = recv_transfer(sock.0, &mut transfer, &mut received)?;
    let fds = &received[..n];
    let valid = transfer.magic == TRANSFER_MAGIC && transfer.count as usize == n;
    if !valid {
        close_all(fds);
        return Err(());
    }
    place_fds(fds, &transfer.targets[..n])
}

/// Puts `fds[i]` on fd number `targets[i]` and closes `fds[i]`.
pub(crate) fn place_fds(fds: &[libc::c_int], targets: &[libc::c_int]) -> Result<(), ()> {
    // A received fd may sit on a target number (a port the component had closed), where a later
    // dup2 would clobber it, or on its own target, where dup2 is a no-op that keeps CLOEXEC and
    // the close below would lose it. So first move such fds above every target.
    // Saturating: the targets come from outside, and nothing here may panic.
    let floor = targets.iter().copied().max().unwrap_or(0).saturating_add(1);
    let mut moved = [-1 as libc::c_int; MAX_HANDED_FDS];
    for (i, &fd) in fds.iter().enumerate() {
        moved[i] = if targets.contains(&fd) {
            let m = dup_above(fd, floor)?;
            close(fd);
            m
        } else {
            fd
        };
    }
    for (&fd, &target) in moved[..fds.len()].iter().zip(targets) {
        // dup2 clears CLOEXEC on the target: these are the component's ports, as before.
        dup2(fd, target)?;
        close(fd);
    }
    Ok(())
}

/// Receives the whole [`FdTransfer`] and the fds that came with it; returns how many fds.
pub(crate) fn recv_transfer(
    sock: libc::c_int,
    transfer: &mut FdTransfer,
    fds: &mut [libc::c_int; MAX_HANDED_FDS],
) -> Result<usize, ()> {
    let want = size_of::<FdTransfer>();
    let dst = (transfer as *mut FdTransfer).cast::<u8>();
    let (got, nfds) = recvmsg_with_fds(sock, dst, want, fds)?;
    // SOCK_STREAM may split the payload; the fds arrive with its first byte, the rest is data.
    let mut have = got;
    while have < want {
        // SAFETY: `dst + have .. dst + want` lies inside `*transfer`, which is plain integers.
        let n = recv(sock, unsafe { dst.add(have) }, want - have);
        if n <= 0 {
            close_all(&fds[..nfds]);
            return Err(());
        }
        have += n as usize;
    }
    Ok(nfds)
}

/// Room for MAX_HANDED_FDS fds in one SCM_RIGHTS message, aligned as `cmsghdr` requires.
#[repr(C, align(8))]
struct CmsgBuf([u8; CMSG_SPACE]);

// SAFETY: CMSG_SPACE is a pure size computation.
const CMSG_SPACE: usize =
    unsafe { libc::CMSG_SPACE((MAX_HANDED_FDS * size_of::<libc::c_int>()) as u32) } as usize;

/// One `recvmsg` into `dst[..len]`; returns (bytes, fds received into `fds`).
fn recvmsg_with_fds(
    sock: libc::c_int,
    dst: *mut u8,
    len: usize,
    fds: &mut [libc::c_int; MAX_HANDED_FDS],
) -> Result<(usize, usize), ()> {
    let mut cbuf = CmsgBuf([0; CMSG_SPACE]);
    let mut iov = libc::iovec {
        iov_base: dst.cast(),
        iov_len: len,
    };
    // SAFETY: msghdr is plain old data; all-zero is valid (no name, no flags).
    let mut msg: libc::msghdr = unsafe { MaybeUninit::zeroed().assume_init() };
    msg.msg_iov = &mut iov;
    msg.msg_iovlen = 1;
    msg.msg_control = cbuf.0.as_mut_ptr().cast();
    msg.msg_controllen = CMSG_SPACE as _;
    let n = loop {
        // SAFETY: `msg` points at `iov` (valid for `len` bytes at `dst`, which the caller owns)
        // and at `cbuf` (CMSG_SPACE bytes, cmsghdr-aligned), all alive for the call.
        let n = unsafe { libc::recvmsg(sock, &mut msg, libc::MSG_CMSG_CLOEXEC) };
        if n >= 0 || errno() != libc::EINTR {
            break n;
        }
    };
    let nfds = collect_fds(&msg, fds);
    // Cut control data means fds were lost in transit (and closed by the kernel).
    if n <= 0 || msg.msg_flags & libc::MSG_CTRUNC != 0 {
        close_all(&fds[..nfds]);
        return Err(());
    }
    Ok((n as usize, nfds))
}

/// Copies the SCM_RIGHTS fds of `msg` into `fds`; returns how many.
fn collect_fds(msg: &libc::msghdr, fds: &mut [libc::c_int; MAX_HANDED_FDS]) -> usize {
    let mut count = 0;
    // SAFETY: `msg` was filled in by recvmsg; the CMSG_* macros stay within msg_controllen.
    let mut cmsg = unsafe { libc::CMSG_FIRSTHDR(msg) };
    while !cmsg.is_null() {
        // SAFETY: CMSG_FIRSTHDR/CMSG_NXTHDR return either null or a header inside the buffer.
        let hdr = unsafe { &*cmsg };
        if hdr.cmsg_level == libc::SOL_SOCKET && hdr.cmsg_type == libc::SCM_RIGHTS {
            // SAFETY: CMSG_LEN(0) is a pure size computation.
            let data_len =
                (hdr.cmsg_len as usize).saturating_sub(unsafe { libc::CMSG_LEN(0) } as usize);
            // SAFETY: the header is valid, so its data follows within the buffer.
            let data = unsafe { libc::CMSG_DATA(cmsg) }.cast::<libc::c_int>();
            for i in 0..data_len / size_of::<libc::c_int>() {
                // SAFETY: `i` is within the data of this header; read_unaligned because cmsg
                // data carries no alignment promise for its contents.
                let fd = unsafe { data.add(i).read_unaligned() };
                // The buffer holds at most MAX_HANDED_FDS fds, so this never overflows; the check
                // keeps it so even for a kernel that packed differently.
                if count < MAX_HANDED_FDS {
                    fds[count] = fd;
                    count += 1;
                } else {
                    close(fd);
                }
            }
        }
        // SAFETY: `cmsg` is a valid header of `msg`.
        cmsg = unsafe { libc::CMSG_NXTHDR(msg, cmsg) };
    }
    count
}

/// Closes the fd when dropped (also on the error paths of `join_voter`).
pub(crate) struct Fd(pub(crate) libc::c_int);

impl Drop for Fd {
    fn drop(&mut self) {
        close(self.0);
    }
}

fn connect(sock: libc::c_int, addr: &VoterAddr) -> Result<(), ()> {
    loop {
        // SAFETY: `addr.addr` is an initialised sockaddr_un of which `addr.len` bytes are used.
        let r = unsafe {
            libc::connect(
                sock,
                (&addr.addr as *const libc::sockaddr_un).cast(),
                addr.len,
            )
        };
        if r == 0 {
            return Ok(());
        }
        // After EINTR the connection attempt continues in the kernel; retrying reports
        // EISCONN once it has completed, or EALREADY while it is still in progress.
        match errno() {
            libc::EINTR | libc::EALREADY => continue,
            libc::EISCONN => return Ok(()),
            _ => return Err(()),
        }
    }
}

fn recv(sock: libc::c_int, dst: *mut u8, len: usize) -> isize {
    loop {
        // SAFETY: the caller passes `dst` valid for `len` bytes of writes.
        let n = unsafe { libc::recv(sock, dst.cast(), len, 0) };
        if n >= 0 || errno() != libc::EINTR {
            return n;
        }
    }
}

pub(crate) fn send_all(sock: libc::c_int, bytes: &[u8]) -> Result<(), ()> {
    let mut sent = 0;
    while sent < bytes.len() {
        // SAFETY: the range is inside `bytes`. MSG_NOSIGNAL: a voter that gave up must not
        // kill us with SIGPIPE; we exit with our own status instead.
        let n = unsafe {
            libc::send(
                sock,
                bytes[sent..].as_ptr().cast(),
                bytes.len() - sent,
                libc::MSG_NOSIGNAL,
            )
        };
        if n > 0 {
            sent += n as usize;
        } else if n < 0 && errno() == libc::EINTR {
            continue;
        } else {
            return Err(());
        }
    }
    Ok(())
}

fn dup2(fd: libc::c_int, target: libc::c_int) -> Result<(), ()> {
    loop {
        // SAFETY: integer arguments only. Replacing `target` is the point: it is the component's
        // port number, whose old pipe is to be dropped.
        let r = unsafe { libc::dup2(fd, target) };
        if r >= 0 {
            return Ok(());
        }
        if errno() != libc::EINTR {
            return Err(());
        }
    }
}

fn dup_above(fd: libc::c_int, floor: libc::c_int) -> Result<libc::c_int, ()> {
    // SAFETY: integer arguments only.
    let r = unsafe { libc::fcntl(fd, libc::F_DUPFD_CLOEXEC, floor) };
    if r < 0 {
        Err(())
    } else {
        Ok(r)
    }
}

fn close(fd: libc::c_int) {
    // SAFETY: closes an fd this module received or opened, once.
    unsafe { libc::close(fd) };
}

pub(crate) fn close_all(fds: &[libc::c_int]) {
    for &fd in fds {
        close(fd);
    }
}

fn getppid() -> libc::pid_t {
    // SAFETY: no arguments, cannot fail.
    unsafe { libc::getppid() }
}

fn errno() -> libc::c_int {
    // SAFETY: __errno_location returns this thread's errno slot, always valid.
    unsafe { *libc::__errno_location() }
}

fn set_errno(v: libc::c_int) {
    // SAFETY: as in `errno`.
    unsafe { *libc::__errno_location() = v };
}

#[cfg(test)]
mod tests {
    use super::{Deferral, Ordering};
    use std::cell::RefCell;

    /// Records the nonces a deferral's restarts ran with.
    #[derive(Default)]
    struct Forks(RefCell<Vec<u32>>);

    impl Forks {
        fn run(&self) -> impl FnMut(u32) + '_ {
            |nonce| self.0.borrow_mut().push(nonce)
        }
        fn take(&self) -> Vec<u32> {
            std::mem::take(&mut self.0.borrow_mut())
        }
    }

    fn never(nonce: u32) {
        panic!("restart {nonce:#x} ran while deferred");
    }

    #[test]
    fn restart_outside_a_deferral_runs_at_once() {
        let d = Deferral::new();
        let forks = Forks::default();
        d.signal(7, forks.run());
        assert_eq!(forks.take(), [7]);
        // Nothing left for a later release.
        d.hold();
        d.release(forks.run());
        assert_eq!(forks.take(), [] as [u32; 0]);
    }

    #[test]
    fn restart_inside_runs_once_at_the_release_with_the_newest_nonce() {
        let d = Deferral::new();
        let forks = Forks::default();
        d.hold();
        d.signal(1, never);
        d.signal(2, never);
        assert_eq!(forks.take(), [] as [u32; 0]);
        d.release(forks.run());
        assert_eq!(forks.take(), [2]);
        assert_eq!(d.depth.load(Ordering::SeqCst), 0);
        assert_eq!(d.pending.load(Ordering::SeqCst), 0);
        // A nonce of 0 (a plain `kill`) is still a pending restart.
        d.hold();
        d.signal(0, never);
        d.release(forks.run());
        assert_eq!(forks.take(), [0]);
    }

    #[test]
    fn only_the_outermost_release_restarts() {
        let d = Deferral::new();
        let forks = Forks::default();
        d.hold();
        d.hold();
        d.signal(3, never);
        d.release(forks.run());
        assert_eq!(forks.take(), [] as [u32; 0], "inner release");
        d.release(forks.run());
        assert_eq!(forks.take(), [3]);
    }

    /// A RESTART that lands while the deferred restart runs is recorded (the depth is held, so
    /// it does not nest) and run after it, once.
    #[test]
    fn restart_during_the_deferred_restart_runs_after_it() {
        let d = Deferral::new();
        let mut ran = Vec::new();
        d.hold();
        d.signal(10, never);
        d.release(|nonce| {
            assert!(
                d.depth.load(Ordering::SeqCst) > 0,
                "deferred restart runs held"
            );
            ran.push(nonce);
            if nonce == 10 {
                d.signal(11, never);
            }
        });
        assert_eq!(ran, [10, 11]);
        assert_eq!(d.depth.load(Ordering::SeqCst), 0);
    }

    /// A release that finds a RESTART recorded, and one that arrives once the depth is zero
    /// again: the handler runs the new one itself and the recorded one is superseded, not run
    /// a second time.
    #[test]
    fn restart_after_the_depth_reaches_zero_supersedes_the_recorded_one() {
        let d = Deferral::new();
        let forks = Forks::default();
        d.hold();
        d.signal(20, never);
        // As if the release had decremented and the handler came before its look.
        d.depth.store(0, Ordering::SeqCst);
        d.signal(21, forks.run());
        assert_eq!(forks.take(), [21]);
        assert_eq!(d.pending.load(Ordering::SeqCst), 0);
    }

    #[test]
    fn release_without_hold_is_ignored() {
        let d = Deferral::new();
        let forks = Forks::default();
        d.release(forks.run());
        assert_eq!(d.depth.load(Ordering::SeqCst), 0);
        d.signal(5, forks.run());
        assert_eq!(forks.take(), [5], "not deferred by an unbalanced release");
    }

    #[test]
    fn a_fork_child_forgets_what_was_aimed_at_its_donor() {
        let d = Deferral::new();
        let forks = Forks::default();
        d.hold();
        d.signal(30, never);
        d.forget_pending();
        d.release(forks.run());
        assert_eq!(forks.take(), [] as [u32; 0]);
    }

    /// The spare line is taken only while its number still names the socket made for it: a
    /// number the component closed and reused for a file of its own is neither handed to a
    /// fork child (which would write its `Hello` into the file) nor closed.
    #[test]
    fn a_spare_line_whose_number_was_reused_is_left_alone() {
        use super::{take_spare_line, SPARE_LINE, SPARE_LINE_DEV, SPARE_LINE_ID};
        use std::os::fd::AsRawFd;
        let (line, _voter) = std::os::unix::net::UnixStream::pair().unwrap();
        let (dev, ino) = crate::cow::file_id(line.as_raw_fd()).unwrap();
        SPARE_LINE_DEV.store(dev, Ordering::SeqCst);
        SPARE_LINE_ID.store(ino, Ordering::SeqCst);
        SPARE_LINE.store(line.as_raw_fd(), Ordering::SeqCst);
        assert_eq!(take_spare_line(), line.as_raw_fd(), "still the line");
        assert_eq!(SPARE_LINE.load(Ordering::SeqCst), -1, "taken once");
        assert_eq!(take_spare_line(), -1, "none left");
        // The component closes the number and opens a file on it (here in one step, so that
        // no other test's thread gets the number in between).
        let file = std::fs::File::open("/proc/self/stat").unwrap();
        let number = std::os::fd::IntoRawFd::into_raw_fd(line);
        // SAFETY: `number` is this test's socket; dup2 replaces it with a copy of the test's
        // own file, atomically.
        assert_eq!(unsafe { libc::dup2(file.as_raw_fd(), number) }, number);
        SPARE_LINE.store(number, Ordering::SeqCst);
        assert_eq!(take_spare_line(), -1, "a file is not the line");
        assert!(
            crate::cow::file_id(number).is_some(),
            "and it is still open"
        );
        // SAFETY: closes the copy this test put on `number`.
        unsafe { libc::close(number) };
    }

    #[test]
    fn threads_are_counted() {
        let before = super::thread_count().expect("/proc/self/stat");
        let (tx, rx) = std::sync::mpsc::channel::<()>();
        let t = std::thread::spawn(move || rx.recv());
        let during = super::thread_count().expect("/proc/self/stat");
        assert!(
            during > before.saturating_sub(1) && during >= 2,
            "{before} → {during}"
        );
        tx.send(()).unwrap();
        let _ = t.join();
    }
}
