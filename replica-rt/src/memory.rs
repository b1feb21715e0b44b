//! What a replica keeps resident and locked.
//!
//! A replica locks its memory so that no page fault adds latency to a round. How much is the
//! component's `lock_memory` ([`LockMemory`], passed on in `contract::ENV_LOCK_MEMORY`):
//!
//! - **`all`** (the default): every page of every mapping, populated at start
//!   (`mlockall(MCL_CURRENT | MCL_FUTURE)`): no page fault in a round, ever, at the price of the
//!   whole binary and its libraries resident in every replica (about 4.4 MiB for `s3res-echo`).
//! - **`used`**: the pages the replica uses. Memory is locked *on fault* (`mlockall(MCL_CURRENT
//!   | MCL_FUTURE | MCL_ONFAULT)`): the pages present now are locked, every other page the
//!   first time it is touched, and nothing is populated up front (about 3.0 MiB for
//!   `s3res-echo`; glibc's `.bss` and the libraries' unused text stay out). Code first run
//!   later — an error path, the restart handler at the first fork — takes a page fault then,
//!   a read from disk if no process kept that page of the file in memory. For boards short of
//!   memory; a fork recovery also has fewer private pages to copy (see below).
//!
//! Giving back, before locking on fault, the file pages that only start-up used would bring
//! `s3res-echo` to about 1.3 MiB; it was tried and left out: on the machine of
//! docs/results.md it made every 4 KiB round 1–4 µs slower for good (without a single page
//! fault in the rounds, and even when the pages were populated again), for a reason not found.
//!
//! Either way, two kinds of slack are large and never used, and are kept out:
//!
//! - **malloc's top pad.** glibc grows the heap by what was asked plus `M_TOP_PAD` (128 KiB by
//!   default) and keeps the rest for later. Locked, that pad is resident for the replica's
//!   life. [`lock`] trims the heap to [`HEAP_PAD`] first and sets the pad to the same (and the
//!   mmap threshold to [`HEAP_MMAP_THRESHOLD`], which setting the pad would freeze at 128 KiB).
//! - **the untouched part of the stack.** The kernel sets up the main thread's stack mapping
//!   at 128 KiB and more; locking populates all of it, where a component uses a few pages.
//!   [`lock`] keeps [`STACK_LOCKED`] below the current stack pointer locked and resident, and
//!   locks the rest *on fault* (`mlock2(MLOCK_ONFAULT)`): a page there is zero-filled and
//!   locked the first time the stack reaches it (a minor fault, no I/O), and is not resident
//!   until then. The split leaves only the upper part named `[stack]` in `/proc/self/maps`,
//!   so what reads the main thread's stack size from there (`pthread_getattr_np`) sees about
//!   the part kept; the stack can still grow through the rest as before.
//!
//! Every resident private page is one that a fork recovery must copy (the child writes to each
//! one, so that donor and child share no physical page: see [`crate::cow`]), which is why
//! the pages `all` populates and never uses cost restart time too.

use std::io;
use std::sync::atomic::{AtomicBool, Ordering};

pub use s3res_protocol::plan::LockMemory;

use crate::contract::ENV_LOCK_MEMORY;
use crate::sys;

/// What malloc keeps above the heap's top, at most, once the replica is locked.
pub const HEAP_PAD: usize = 16 * 1024;
/// Blocks from this size on get a mapping of their own, given back when freed (see
/// `sys::trim_heap`: setting the pad freezes glibc's otherwise rising threshold).
pub const HEAP_MMAP_THRESHOLD: usize = 1 << 20;
/// Stack kept locked and resident below the stack pointer at [`lock`].
pub const STACK_LOCKED: usize = 32 * 1024;

/// Set when the replica locks everything (`all`): a fork child locks as its donor did.
static LOCK_ALL: AtomicBool = AtomicBool::new(false);
/// Set when later mappings are locked too (`MCL_FUTURE`): only when nothing limits how much
/// this process may lock (see [`locks_future_memory`]). A fork child locks as its donor did.
static LOCK_FUTURE: AtomicBool = AtomicBool::new(false);

/// `CAP_IPC_LOCK` (linux/capability.h): lock memory beyond `RLIMIT_MEMLOCK`.
const CAP_IPC_LOCK: u32 = 14;

/// This process's `RLIMIT_MEMLOCK` in bytes; `None` when unlimited.
pub fn memlock_limit() -> Option<u64> {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes the struct it is given, which lives on this stack.
    let got = unsafe { libc::getrlimit(libc::RLIMIT_MEMLOCK, &mut limit) };
    (got == 0 && limit.rlim_cur != libc::RLIM_INFINITY).then_some(limit.rlim_cur)
}

/// Whether this process may lock memory allocated later (`MCL_FUTURE`) without an allocation
/// ever failing for it: its lock limit is unlimited, or it has `CAP_IPC_LOCK` (root has), which
/// the limit does not bind. Under a limit (a user's is 8 MiB by default) `MCL_FUTURE` makes
/// every allocation past it fail: a component that allocates after `init` (as the docs advise:
/// what the rounds need, before the first) died of it, and so did every replica started again.
pub fn locks_future_memory() -> bool {
    memlock_limit().is_none() || sys::has_effective_capability(CAP_IPC_LOCK)
}

/// Whether bootstrap has said, once for the system, that a lock limit binds its processes
/// ([`crate::contract::ENV_MEMORY_LOCK_SAID`]): then a refused lock is not said by each.
pub fn lock_limit_said() -> bool {
    std::env::var_os(crate::contract::ENV_MEMORY_LOCK_SAID).is_some()
}

/// The policy the voter asked for in [`ENV_LOCK_MEMORY`]; the default (`all`) when absent. A
/// value that does not parse is reported and taken as the default.
pub fn policy_from_env() -> LockMemory {
    policy_from(std::env::var(ENV_LOCK_MEMORY).ok().as_deref())
}

/// [`policy_from_env`] for the variable's value (`None`: not set).
fn policy_from(value: Option<&str>) -> LockMemory {
    match value {
        None => LockMemory::default(),
        Some(v) => LockMemory::parse(v).unwrap_or_else(|| {
            let default = LockMemory::default().as_str();
            tracing::warn!(value = %v, "{ENV_LOCK_MEMORY} is neither `all` nor `used`: locking `{default}`");
            LockMemory::default()
        }),
    }
}

/// What [`lock`] did beside locking, in bytes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Locked {
    /// The main thread's stack below [`STACK_LOCKED`], locked on fault.
    pub stack_on_fault: usize,
    /// The idle alternate signal stack, locked on fault (under `all` only: `used` never
    /// populated it).
    pub alt_stack_on_fault: usize,
    /// The relocated read-only data made read-only (see [`protect_relocated_data`]).
    pub relro_read_only: usize,
}

/// Makes the main program's relocated read-only data read-only, as the dynamic linker does for
/// a dynamically linked program and musl's start-up code for a static one does not; returns
/// the bytes protected (0 if none, or if refused). After relocation nothing writes these
/// pages: read-only, a stray write there is a crash the voter sees instead of a silent change.
///
/// A fork child's copy-on-write walk leaves them shared with its donor, as a dynamically
/// linked replica's always were. That is a trade-off, not free: they are private copies (each
/// replica started by exec relocated its own), so a bit flip in one hits a donor and its
/// children alike, where before the walk gave each its own. It is the exposure the program's
/// text and constants have in every replica (one copy in the page cache for all), for 28 KiB
/// of pointers that, corrupted, mostly crash; and it saves 7 page copies a restart (see
/// [`crate::cow`] and docs/architecture.md, "Copy-on-write break").
pub fn protect_relocated_data() -> usize {
    let Some((start, len)) = sys::main_program_relro(crate::cow::page_size()) else {
        return 0;
    };
    // SAFETY: the range is the main program's PT_GNU_RELRO segment as the loaders protect it
    // (`main_program_relro`: its last, partial page left out; its first page holds nothing
    // writable before it), which only relocation writes, and relocation was over before any
    // constructor or `main` ran (musl, glibc: neither binds lazily into it).
    match unsafe { sys::make_read_only(start, len) } {
        Ok(()) => len,
        Err(e) => {
            tracing::debug!(error = %e, "could not make the relocated read-only data read-only");
            0
        }
    }
}

/// Turns the whole pages of this thread's idle alternate signal stack from locked and resident
/// into locked on fault; returns the bytes so released. Rust's runtime gives the main thread
/// one (about 12 KiB) for the handler that reports a stack overflow: locking populates it,
/// and a fork recovery would copy it, for a handler that runs, if ever, in a process about to
/// die. A handler that does run there takes its pages then (a minor fault).
pub fn release_alternate_stack() -> usize {
    let Some((sp, size)) = sys::idle_alternate_stack() else {
        return 0;
    };
    let Some((start, end)) = whole_pages(sp, sp.saturating_add(size), crate::cow::page_size())
    else {
        return 0;
    };
    // SAFETY: the range is whole pages of this thread's alternate signal stack, and the thread
    // is not running on it (`idle_alternate_stack`): nothing in it is live, as a handler that
    // runs there builds its frame afresh and leaves it dead when it returns (also one that
    // runs between these system calls). An alternate stack belongs to its thread alone (POSIX
    // leaves sharing one undefined). `lock_on_fault_instead` says what its pages read back as.
    match unsafe { sys::lock_on_fault_instead(start, end - start) } {
        Ok(()) => end - start,
        Err(e) => {
            tracing::debug!(error = %e, "could not release the alternate signal stack");
            0
        }
    }
}

/// Trims malloc's slack, makes the relocated read-only data read-only, locks memory as
/// `policy` says, and releases the stack below [`STACK_LOCKED`] and the idle alternate signal
/// stack to be locked on fault. An error is the `mlockall` refusal (nothing is locked then);
/// the rest is best effort.
pub fn lock(policy: LockMemory) -> io::Result<Locked> {
    // Read before locking (which may be refused): a fork child's copy-on-write walk leaves
    // this stack's dead part shared whether or not the memory is locked.
    let stack = stack_mapping();
    if let Some((low, high)) = stack {
        crate::cow::note_main_stack(low, high);
    }
    sys::trim_heap(HEAP_PAD, HEAP_MMAP_THRESHOLD);
    let relro_read_only = protect_relocated_data();
    let future = locks_future_memory();
    LOCK_FUTURE.store(future, Ordering::Relaxed);
    match (policy, future) {
        (LockMemory::All, true) => {
            LOCK_ALL.store(true, Ordering::Relaxed);
            sys::lock_all_memory()?;
        }
        (LockMemory::Used, true) => {
            LOCK_ALL.store(false, Ordering::Relaxed);
            sys::lock_used_memory()?;
        }
        // Under a lock limit: what is mapped now, not what comes later.
        (LockMemory::All, false) => {
            LOCK_ALL.store(true, Ordering::Relaxed);
            sys::lock_current_memory(false)?;
        }
        (LockMemory::Used, false) => {
            LOCK_ALL.store(false, Ordering::Relaxed);
            sys::lock_current_memory(true)?;
        }
    }
    let mut on_fault = 0;
    // Under `used` the alternate stack was never populated: nothing to give back.
    let alt_stack_on_fault = match policy {
        LockMemory::All => release_alternate_stack(),
        LockMemory::Used => 0,
    };
    if let Some((low, high)) = stack {
        let sp = stack_pointer();
        if let Some(range) = unused_below(low, high, sp, STACK_LOCKED, crate::cow::page_size()) {
            // SAFETY: the range is the part of this thread's stack mapping more than
            // `STACK_LOCKED` below the current frame (`unused_below` checked that the stack
            // pointer lies in that mapping): memory below the stack pointer is dead, and a
            // signal handler cannot run on this thread while it is in the system calls.
            match unsafe { sys::lock_on_fault_instead(range.0, range.1 - range.0) } {
                Ok(()) => on_fault = range.1 - range.0,
                // munlock or madvise refused: nothing changed. mlock2 refused (a kernel before
                // 4.4, a seccomp filter): that part of the stack is unlocked, a page fault the
                // first time the stack reaches it.
                Err(e) => tracing::warn!(
                    error = %e,
                    "could not lock the unused stack on fault; it may fault when first used"
                ),
            }
        }
    }
    Ok(Locked {
        stack_on_fault: on_fault,
        alt_stack_on_fault,
        relro_read_only,
    })
}

/// Set in a fork child from its fork until its memory is locked ([`lock_fork_child`]).
static FORK_CHILD_UNLOCKED: AtomicBool = AtomicBool::new(false);

/// Called by a fork child in the restart handler: its memory is to be locked at its first
/// moment between rounds ([`lock_fork_child`]), not before its `Ready`. Locks are not
/// inherited over fork, and `mlockall(MCL_CURRENT …)` visits every mapping and every present
/// page to lock it: 37–45 µs (traced) of a 4 KiB replica's restart on the AMD host of
/// docs/results.md (stop 50), on the restart's critical path, where the child's page walk and the lock were
/// the part of the restart that the voter waited for. Nothing needs the lock to answer:
/// every page the child shares with its donor or owns after its walk is resident (the donor's
/// locked pages stay locked while it lives), so until the lock only a reclaim under memory
/// pressure could take one away. Async-signal-safe (an atomic store).
pub(crate) fn defer_fork_child_lock() {
    FORK_CHILD_UNLOCKED.store(true, Ordering::SeqCst);
}

/// Whether this process is a fork child that has not locked its memory yet (one atomic load).
pub(crate) fn fork_child_unlocked() -> bool {
    FORK_CHILD_UNLOCKED.load(Ordering::Relaxed)
}

/// Locks a fork child's memory as its donor's was, on fault either way: a plain
/// `mlockall(MCL_CURRENT)` would populate every mapping up front, most of a small component's
/// restart time. With `all` the donor had every page locked, so the child's first touch of a
/// page is a minor fault, never I/O; future mappings are then populated in full, as the
/// donor's were. Does nothing in a process that is not an unlocked fork child. Called where a
/// replica has answered and is about to wait for input (`restart::between_rounds`). A refusal
/// is only logged at debug: the donor logged it at init, where it was refused too.
pub(crate) fn lock_fork_child() {
    if !FORK_CHILD_UNLOCKED.swap(false, Ordering::SeqCst) {
        return;
    }
    let locked = match (
        LOCK_ALL.load(Ordering::Relaxed),
        LOCK_FUTURE.load(Ordering::Relaxed),
    ) {
        (true, true) => sys::lock_memory_on_fault(),
        (false, true) => sys::lock_used_memory(),
        // Under a lock limit, as the donor: what is mapped now.
        (_, false) => sys::lock_current_memory(true),
    };
    if let Err(e) = locked {
        tracing::debug!(error = %e, "a fork child could not lock its memory");
    }
}

/// An address in the current stack frame (its own, below its caller's: not inlined).
#[inline(never)]
pub(crate) fn stack_pointer() -> usize {
    let here = 0u8;
    std::hint::black_box(&here) as *const u8 as usize
}

/// The main thread's stack mapping (`[stack]` in `/proc/self/maps`): `(start, end)`.
fn stack_mapping() -> Option<(usize, usize)> {
    let maps = std::fs::read_to_string("/proc/self/maps").ok()?;
    let line = maps.lines().find(|l| l.ends_with("[stack]"))?;
    crate::cow::parse_line(line.as_bytes()).map(|m| (m.start, m.end))
}

/// The page-aligned part of the stack mapping `low..high` that lies more than `keep` below
/// `sp`, if there is any (`sp` outside the mapping: none — this is not the main thread).
fn unused_below(
    low: usize,
    high: usize,
    sp: usize,
    keep: usize,
    page: usize,
) -> Option<(usize, usize)> {
    if sp < low || sp >= high {
        return None;
    }
    whole_pages(low, sp.checked_sub(keep)?, page)
}

/// The whole pages inside `start..end` (`start` rounded up, `end` down to a page boundary),
/// if there is one: what can be locked on fault without touching a byte outside the range.
fn whole_pages(start: usize, end: usize, page: usize) -> Option<(usize, usize)> {
    let (start, end) = (start.checked_next_multiple_of(page)?, end & !(page - 1));
    (end > start).then_some((start, end))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Whether the page at `addr` is in memory, from `/proc/self/pagemap` (the present bit is
    /// shown to any process for its own pages).
    fn resident(addr: usize) -> bool {
        use std::os::unix::fs::FileExt;
        let pagemap = std::fs::File::open("/proc/self/pagemap").expect("/proc/self/pagemap");
        let mut entry = [0u8; 8];
        let at = (addr / crate::cow::page_size()) as u64 * 8;
        pagemap
            .read_exact_at(&mut entry, at)
            .expect("a pagemap entry");
        u64::from_le_bytes(entry) & (1 << 63) != 0
    }

    #[test]
    fn the_idle_alternate_stack_is_given_back() {
        // Rust's runtime gives every thread, this test's too, an alternate signal stack.
        let (sp, size) =
            sys::idle_alternate_stack().expect("this thread has an alternate signal stack");
        let page = crate::cow::page_size();
        let (start, end) = (sp.next_multiple_of(page), (sp + size) & !(page - 1));
        assert!(
            end > start,
            "an alternate stack of {size} bytes holds no whole page"
        );
        for at in (start..end).step_by(page) {
            // SAFETY: a whole page of this thread's alternate signal stack, which the thread
            // is not running on (`idle_alternate_stack`), and on which no handler runs in this
            // test: the byte is dead, and writing it only makes the page resident.
            unsafe { (at as *mut u8).write_volatile(0x5a) };
            assert!(resident(at), "page {at:#x} written but not resident");
        }
        let released = release_alternate_stack();
        // The pages are dropped before they are locked again; only that last step needs
        // locked memory, which RLIMIT_MEMLOCK may refuse an unprivileged test.
        let refused = sys::effective_uid() != 0
            && memlock_limit().is_some_and(|limit| limit < (end - start) as u64);
        assert!(
            released == end - start || (released == 0 && refused),
            "released {released} of {} bytes",
            end - start
        );
        for at in (start..end).step_by(page) {
            assert!(
                !resident(at),
                "page {at:#x} of the alternate stack is still resident"
            );
        }
    }

    #[test]
    fn the_relocated_read_only_data_is_made_read_only() {
        let page = crate::cow::page_size();
        let (start, len) = sys::main_program_relro(page).expect("the test binary has PT_GNU_RELRO");
        assert!(
            start % page == 0 && len % page == 0 && len > 0,
            "{start:#x} + {len}"
        );
        // Writable again, as musl's static start-up leaves it (this test binary's loader
        // protected it already).
        let rw = libc::PROT_READ | libc::PROT_WRITE;
        // SAFETY: only the protection changes, to what it was before the loader's `mprotect`.
        let made = unsafe { libc::mprotect(start as *mut libc::c_void, len, rw) };
        assert_eq!(made, 0);
        let permissions = || {
            // Every byte of it lies in mappings of this executable (a wrong load address would
            // land elsewhere): their permissions.
            let exe = std::fs::read_link("/proc/self/exe").expect("/proc/self/exe");
            let maps = std::fs::read_to_string("/proc/self/maps").expect("/proc/self/maps");
            let mut seen = Vec::new();
            let mut covered = 0;
            for line in maps.lines() {
                let m = crate::cow::parse_line(line.as_bytes()).expect("a maps line");
                let (a, b) = (m.start.max(start), m.end.min(start + len));
                if a < b {
                    assert!(
                        line.ends_with(exe.to_str().expect("a UTF-8 path")),
                        "{line}"
                    );
                    seen.push(line.split_whitespace().nth(1).unwrap()[..2].to_owned());
                    covered += b - a;
                }
            }
            assert_eq!(
                covered, len,
                "{start:#x} + {len} is not all mapped:\n{maps}"
            );
            seen
        };
        assert!(
            permissions().iter().all(|p| p == "rw"),
            "{:?}",
            permissions()
        );
        assert_eq!(protect_relocated_data(), len);
        assert!(
            permissions().iter().all(|p| p == "r-"),
            "{:?}",
            permissions()
        );
    }

    #[test]
    fn an_unreadable_policy_locks_everything() {
        assert_eq!(policy_from(None), LockMemory::All);
        assert_eq!(policy_from(Some("used")), LockMemory::Used);
        assert_eq!(policy_from(Some("all")), LockMemory::All);
        for bad in ["", "USED", "used ", "none", "all,used", "\u{0}"] {
            assert_eq!(policy_from(Some(bad)), LockMemory::All, "{bad:?}");
        }
    }

    #[test]
    fn the_stack_is_released_only_well_below_the_stack_pointer() {
        let page = 4096;
        let (low, high) = (0x7000_0000, 0x7002_1000);
        // The stack pointer 32 KiB below the top of a 132 KiB stack, 64 KiB kept: the lowest
        // 36 KiB are released, page-aligned.
        let sp = high - 32 * 1024 + 123;
        let (a, b) = unused_below(low, high, sp, 64 * 1024, page).unwrap();
        assert_eq!(a, low);
        assert_eq!(b, (sp - 64 * 1024) & !(page - 1));
        assert!(b <= sp - 64 * 1024);
        // Too shallow a mapping: nothing to release.
        assert_eq!(unused_below(low, high, low + 1000, 64 * 1024, page), None);
        // Another thread's stack pointer: not this mapping.
        assert_eq!(unused_below(low, high, high + 10, 64 * 1024, page), None);
    }

    /// Only whole pages, never a byte outside the range; none in less than a page.
    #[test]
    fn whole_pages_round_inwards() {
        let page = 4096;
        assert_eq!(whole_pages(0x1000, 0x4000, page), Some((0x1000, 0x4000)));
        assert_eq!(whole_pages(0x1001, 0x3fff, page), Some((0x2000, 0x3000)));
        assert_eq!(whole_pages(0x1001, 0x2fff, page), None);
        assert_eq!(whole_pages(0x1000, 0x1fff, page), None);
        assert_eq!(whole_pages(0x3000, 0x1000, page), None);
        assert_eq!(whole_pages(usize::MAX - 10, usize::MAX, page), None);
    }
}
