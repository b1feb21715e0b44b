//! What a replica keeps resident and locked.
//!
//! A replica locks its memory (`mlockall(MCL_CURRENT | MCL_FUTURE)`) so that no page fault
//! adds latency to a round. Locking populates every page of every mapping, so whatever slack
//! the process carries becomes resident — and every resident private page is a page that a
//! fork recovery must copy (the child writes to each one, so that donor and child share no
//! physical page: see [`crate::cow`]). Two kinds of slack are large and never used:
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
//! Text and read-only data stay locked in full: a page of code not yet run would otherwise
//! be read from disk the first time it runs, a major fault in the middle of a round.

use std::io;

use crate::sys;

/// What malloc keeps above the heap's top, at most, once the replica is locked.
pub const HEAP_PAD: usize = 16 * 1024;
/// Blocks from this size on get a mapping of their own, given back when freed (see
/// `sys::trim_heap`: setting the pad freezes glibc's otherwise rising threshold).
pub const HEAP_MMAP_THRESHOLD: usize = 1 << 20;
/// Stack kept locked and resident below the stack pointer at [`lock`].
pub const STACK_LOCKED: usize = 32 * 1024;

/// Trims malloc's slack, locks all memory, and releases the stack below [`STACK_LOCKED`] to
/// be locked on fault; returns the bytes of stack released so. An error is the `mlockall`
/// refusal (nothing is locked then); trimming and the stack are best effort.
pub fn lock() -> io::Result<usize> {
    sys::trim_heap(HEAP_PAD, HEAP_MMAP_THRESHOLD);
    sys::lock_all_memory()?;
    let mut on_fault = 0;
    if let Some((low, high)) = stack_mapping() {
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

/// An address in the current stack frame.
#[inline(never)]
fn stack_pointer() -> usize {
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
