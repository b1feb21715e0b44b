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

/// Trims malloc's slack, locks memory as `policy` says, and releases the stack below
/// [`STACK_LOCKED`] to be locked on fault; returns the bytes of stack released so. An error is
/// the `mlockall` refusal (nothing is locked then); trimming and the stack are best effort.
pub fn lock(policy: LockMemory) -> io::Result<usize> {
    // Read before locking (which may be refused): a fork child's copy-on-write walk leaves
    // this stack's dead part shared whether or not the memory is locked.
    let stack = stack_mapping();
    if let Some((low, high)) = stack {
        crate::cow::note_main_stack(low, high);
    }
    sys::trim_heap(HEAP_PAD, HEAP_MMAP_THRESHOLD);
    match policy {
        LockMemory::All => {
            LOCK_ALL.store(true, Ordering::Relaxed);
            sys::lock_all_memory()?;
        }
        LockMemory::Used => {
            LOCK_ALL.store(false, Ordering::Relaxed);
            sys::lock_used_memory()?;
        }
    }
    let mut on_fault = 0;
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
    Ok(on_fault)
}

/// Locks a fork child's memory as its donor's was (locks are not inherited over fork), on
/// fault either way: a plain `mlockall(MCL_CURRENT)` would populate every mapping up front,
/// most of a small component's restart time. With `all` the donor had every page locked, so
/// the child's first touch of a page is a minor fault, never I/O; future mappings are then
/// populated in full, as the donor's were. Async-signal-safe (an atomic load, two or three
/// system calls).
pub(crate) fn lock_fork_child() -> io::Result<()> {
    if LOCK_ALL.load(Ordering::Relaxed) {
        sys::lock_memory_on_fault()
    } else {
        sys::lock_used_memory()
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
    let end = sp.checked_sub(keep)? & !(page - 1);
    (end > low).then_some((low, end))
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
