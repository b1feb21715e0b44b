//! The preload library: lets s3res protect an unmodified, dynamically linked program that reads
//! stdin and writes stdout (`"runtime": "preload"` in the system description).
//!
//! The voter starts each replica with this library in `LD_PRELOAD` and the s3res contract in
//! its environment, and with the replica's pipes on fd 0 and fd 1. Before the program's `main`,
//! [`load`] runs (an ELF constructor) and:
//! - refuses a program that already runs more than one thread (a fork copies one);
//! - runs replica-rt's `init`: the restart handler (SIGUSR1: fork, the child joins the voter and
//!   puts its new pipes on fds 0 and 1), the injection hooks, locked memory — exactly what a
//!   component that links replica-rt gets — and asks the restart handler to check for a single
//!   thread before every fork;
//! - makes C stdio's stdout line-buffered, so that each line is one `write` (a pipe is fully
//!   buffered by default, and the voter would wait for a line that sits in the buffer);
//! - notes its pid in the environment (`S3RES_PRELOAD_PID`). The environment is otherwise left
//!   as it is, so that a wrapper that `exec`s the real program (a pyenv shim, `env`, a shell
//!   script) loads the library again in the same process; a *child* process the program
//!   starts finds another pid there, removes the contract and `LD_PRELOAD` from its own
//!   environment and stays out of it.
//!
//! It also defines `write`, which the dynamic linker then resolves to here for the whole
//! program, to keep lines whole across a fork: during a `write` to stdout, and for as long as
//! the program's last one ended in the middle of a line (`print` in `python3 -u` writes the
//! text and its newline separately), restarts are deferred (`replica_rt::restart::hold_restarts`:
//! an atomic counter, no system call), so a fork child never starts its output with the tail
//! of its donor's line, and a RESTART that came meanwhile forks at the end of the `write` that
//! completes the line. The same place applies SDC injections to the outgoing line, and stamps
//! the time when a write completes a line (or a frame), in the answer-stamp page its voter
//! handed it (`replica_rt::stamps`), as replica-rt's output ports do. (C stdio writes from
//! inside libc and does not come here; line-buffered, it writes whole lines, but stamps none:
//! the voter then looks for such a program's answers on its timer, as it did for every
//! unmodified program before.) After a fork, a `write` that completes a line also makes the
//! replica's next spare line to its voter, for its next fork child (replica-rt's `restart`,
//! "The spare line"); a program that writes only through C stdio keeps the one it made at
//! start, and its children after the first fork connect themselves.
//!
//! A program that writes s3res frames itself (`"framing": "frames"`: the voter says so with
//! `S3RES_PRELOAD_FRAMES=1`) has its stdout followed frame by frame instead of line by line:
//! restarts are held while the last `write` ended inside a frame.
//!
//! Outside s3res (no contract in the environment) the library does nothing.

use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};

use replica_rt::contract::{ENV_COMPONENT, ENV_PORTS, ENV_REPLICA, ENV_VOTER_SOCKET};
use replica_rt::restart;

/// The library is active: loaded by a voter into a replica.
static ACTIVE: AtomicBool = AtomicBool::new(false);
/// The last write to stdout ended in the middle of a line (restarts are held meanwhile: this
/// library holds one `hold_restarts` exactly while this is set, or while in `write`).
static MID_LINE: AtomicBool = AtomicBool::new(false);

/// The program writes s3res frames (`framing: frames`), not lines.
static FRAMES: AtomicBool = AtomicBool::new(false);
/// `framing: frames`: where stdout stands in the frame being written — bytes of its 4-byte
/// header seen so far (0–3) and their value, then the bytes of the frame still to come. Only
/// the program's one thread writes them (`write`); the restart handler reads `MID_LINE` only.
static HEADER_SEEN: AtomicU32 = AtomicU32::new(0);
static HEADER_WORD: AtomicU32 = AtomicU32::new(0);
static FRAME_LEFT: AtomicU64 = AtomicU64::new(0);

/// The environment variable the voter sets for a program that writes s3res frames.
const ENV_FRAMES: &str = "S3RES_PRELOAD_FRAMES";

/// Exit status of a replica that cannot be protected this way (refused at load).
const REFUSED: libc::c_int = 125;

/// Run by the dynamic linker before `main` (and before any other constructor of the program's
/// own that runs after ours).
#[used]
#[link_section = ".init_array"]
static LOAD: extern "C" fn() = load;

/// The pid of the replica the library was loaded into first.
const ENV_PID: &str = "S3RES_PRELOAD_PID";

extern "C" fn load() {
    if std::env::var_os(ENV_VOTER_SOCKET).is_none() {
        return;
    }
    let me = std::process::id().to_string();
    if std::env::var(ENV_PID).is_ok_and(|pid| pid != me) {
        // A process the replica started, not the replica: not ours to protect.
        for var in [
            "LD_PRELOAD",
            ENV_PID,
            ENV_PORTS,
            ENV_VOTER_SOCKET,
            ENV_REPLICA,
            ENV_COMPONENT,
        ] {
            // Before `main`, single-threaded: nothing reads the environment concurrently.
            std::env::remove_var(var);
        }
        return;
    }
    // Before `main`, single-threaded (checked just below for the replica itself).
    std::env::set_var(ENV_PID, &me);
    replica_rt::init_logging("s3res-preload");
    if let Some(n) = replica_rt::restart::thread_count().filter(|&n| n != 1) {
        refuse(&format!(
            "the program runs {n} threads at start; an unmodified program must be \
             single-threaded (a fork recovery copies one thread)"
        ));
    }
    match replica_rt::init() {
        Ok(runtime) => {
            // The program uses fds 0 and 1 itself; the runtime only had to install its handlers.
            std::mem::forget(runtime);
        }
        Err(e) => refuse(&format!("replica-rt: {e}")),
    }
    replica_rt::restart::refuse_fork_when_threaded();
    FRAMES.store(std::env::var_os(ENV_FRAMES).is_some(), Ordering::SeqCst);
    line_buffer_stdout();
    ACTIVE.store(true, Ordering::SeqCst);
}

fn refuse(why: &str) -> ! {
    eprintln!("s3res-preload: refused: {why}");
    replica_rt::sys::exit_now(REFUSED)
}

extern "C" {
    /// glibc's `stdout` stream.
    static mut stdout: *mut libc::FILE;
}

fn line_buffer_stdout() {
    // SAFETY: called before `main`, single-threaded; `stdout` is glibc's stream, valid for the
    // whole process, and setvbuf before any output is how C asks for line buffering (a null
    // buffer lets stdio allocate its own).
    unsafe {
        libc::setvbuf(stdout, std::ptr::null_mut(), libc::_IOLBF, 0);
    }
}

/// `write(2)`, as the program calls it. For stdout, in a replica: defers restarts while a line
/// is incomplete, and applies a pending SDC injection to the bytes written.
///
/// # Safety
/// The contract of `write(2)`: `buf` is readable for `count` bytes.
#[no_mangle]
pub unsafe extern "C" fn write(fd: libc::c_int, buf: *const libc::c_void, count: usize) -> isize {
    if fd != libc::STDOUT_FILENO || count == 0 || !ACTIVE.load(Ordering::Relaxed) {
        return raw_write(fd, buf, count);
    }
    // SAFETY: the caller's contract: `buf` is readable for `count` bytes.
    let bytes = unsafe { std::slice::from_raw_parts(buf.cast::<u8>(), count) };
    // Mid-line, the hold taken by the write that left the line open is still on: not twice.
    let held = MID_LINE.load(Ordering::SeqCst);
    if !held {
        restart::hold_restarts();
    }
    // The newline stays: the flip must change a line, not the framing. A write of the newline
    // alone (`python3 -u`'s `print` writes the text, then the newline) leaves an empty body,
    // and an injection waits for the next write that has one (`inject::apply_pending`).
    let body = bytes.len() - usize::from(bytes.last() == Some(&b'\n'));
    let n = if replica_rt::inject::injection_pending() {
        let mut copy = bytes.to_vec();
        replica_rt::inject::corrupt_if_injected("out", &mut copy[..body]);
        raw_write(fd, copy.as_ptr().cast(), copy.len())
    } else {
        raw_write(fd, buf, count)
    };
    if let Ok(written) = usize::try_from(n) {
        if written > 0 {
            let mid = if FRAMES.load(Ordering::Relaxed) {
                !frame_boundary_after(&bytes[..written])
            } else {
                bytes[written - 1] != b'\n'
            };
            MID_LINE.store(mid, Ordering::SeqCst);
        }
    }
    if !MID_LINE.load(Ordering::SeqCst) {
        if n > 0 {
            // An answer (its line, or its frame) is whole in the pipe now: when it went out, for
            // a voter that does not wake for it (`replica_rt::stamps`). Still held, so a fork
            // child never starts with its donor's stamp pending.
            replica_rt::stamps::answered();
        }
        // The line is whole: a RESTART that came meanwhile forks here (errno is kept, for a
        // failed write's caller).
        restart::release_restarts();
        if n > 0 {
            // The answer is out: what a fork left for between rounds — a fork child's memory
            // lock, the next spare line (replica-rt's `restart`, "The spare line") — is done
            // here, as a component's runtime does it at its `recv`. Two atomic loads when
            // nothing is left; errno is kept.
            restart::between_rounds();
        }
    }
    n
}

/// `framing: frames`: follows the frames in `bytes` (the next bytes written to stdout) and
/// says whether they end at a frame's end.
fn frame_boundary_after(bytes: &[u8]) -> bool {
    let mut seen = HEADER_SEEN.load(Ordering::Relaxed);
    let mut word = HEADER_WORD.load(Ordering::Relaxed);
    let mut left = FRAME_LEFT.load(Ordering::Relaxed);
    let mut at = 0;
    while at < bytes.len() {
        if left > 0 {
            let take = left.min((bytes.len() - at) as u64);
            left -= take;
            at += take as usize;
            continue;
        }
        word |= u32::from(bytes[at]) << (8 * seen);
        seen += 1;
        at += 1;
        if seen == 4 {
            left = frame_body_len(word);
            seen = 0;
            word = 0;
        }
    }
    HEADER_SEEN.store(seen, Ordering::Relaxed);
    HEADER_WORD.store(word, Ordering::Relaxed);
    FRAME_LEFT.store(left, Ordering::Relaxed);
    seen == 0 && left == 0
}

/// The bytes after a frame's header word: its payload, or a control frame's argument.
fn frame_body_len(word: u32) -> u64 {
    use replica_rt::frame::{CONTROL_BIT, HEADER_LEN, RESUME, RESUME_LEN};
    match word {
        RESUME => (RESUME_LEN - HEADER_LEN) as u64,
        w if w & CONTROL_BIT != 0 => 0,
        w => u64::from(w),
    }
}

/// The `write` system call itself (libc's `write` is this library's, above).
fn raw_write(fd: libc::c_int, buf: *const libc::c_void, count: usize) -> isize {
    // SAFETY: the write system call with the caller's arguments; the kernel checks the buffer.
    unsafe { libc::syscall(libc::SYS_write, fd, buf, count) as isize }
}
