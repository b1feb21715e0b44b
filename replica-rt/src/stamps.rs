//! Answer stamps: when each replica last answered, in a page of shared memory that the
//! replicas write and the voter reads only when it needs to know.
//!
//! In a sequential round the voter does not wake for every answer (on a shared CPU, each
//! wake-up would preempt the replica that wrote it: `voter/src/reactive.rs`, `watched`). So it
//! does not see when an unwatched replica's turn ended, which is when the next turn's deadline
//! starts. Without stamps it looks for that answer on a timer (every half look window), and on
//! a virtual machine every expiry of that timer costs the CPU 20–40 µs, in whatever round runs
//! then. With stamps it needs no timer: when it finds the answer, at whatever wake-up comes
//! first, the answer's stamp says when the turn ended.
//!
//! The page holds [`ENTRIES`] entries of two 64-bit words: a pid (0: free) and that process's
//! last answer, `CLOCK_MONOTONIC` nanoseconds (0: none yet). A replica claims a free entry for
//! its pid the first time it answers (a compare-and-swap, so two replicas never share one) and
//! stamps it after each answer's write ([`answered`]: replica-rt's output ports, and the preload
//! library's `write` for an unmodified program's lines and frames). The voter hands the page to
//! the replicas it starts by exec
//! ([`contract::ENV_STAMPS_FD`](crate::contract::ENV_STAMPS_FD)); a replica forked from a
//! donor shares the donor's mapping and claims its own entry; the voter frees the entries of
//! replicas it no longer has ([`AnswerStamps::retain`]). bootstrap makes the page and keeps it
//! across voters, like the journal, so a voter's successor reads the stamps of the replicas it
//! adopts.
//!
//! Every replica can write the whole page, so a faulty one can write any stamp. The voter
//! believes a stamp only if it falls between the last time it knew the turn still open and
//! now, so a wrong stamp can at worst start the next turn's deadline as early as that, never
//! before its turn began (`ReactiveVoter::turn_ended_at`). The stamp comes after the answer's
//! write, so a deadline never starts before the answer went out; a voter that reads the
//! answer in the instant between the two finds the stamp of the round before, which that
//! bound refuses, and times the next turn from when it found the answer, as without stamps.

use std::io;
use std::os::fd::OwnedFd;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::OnceLock;

use crate::shared::{memfd, SharedRegion};

/// Entries in the page: more than any voter's replicas, with room for the entries of replicas
/// that died since the voter last freed them.
pub const ENTRIES: usize = 64;

/// Bytes per entry: the pid word, then the stamp word.
const ENTRY_LEN: usize = 16;

/// The size of the mapping (one page; the layout needs `ENTRIES * ENTRY_LEN` bytes of it).
const MAP_LEN: usize = 4096;

const _: () = assert!(ENTRIES * ENTRY_LEN <= MAP_LEN);

/// One page of answer stamps, mapped shared.
#[derive(Debug)]
pub struct AnswerStamps {
    page: SharedRegion,
}

// SAFETY: the page is only accessed through atomics (`SharedRegion::u64_at`), so sharing it
// between threads (a `static` in the replica) is as safe as sharing the atomics themselves.
unsafe impl Sync for AnswerStamps {}

impl AnswerStamps {
    /// A new, zeroed page (the voter): a memfd, close-on-exec (handed on by fd mapping only).
    pub fn create() -> io::Result<AnswerStamps> {
        Self::kept(memfd(c"s3res-answer-stamps")?)
    }

    /// Maps the page behind `fd`, which bootstrap keeps across voters: the first voter finds it
    /// empty and makes it a zeroed page; a successor finds it as its predecessor left it.
    pub fn kept(fd: OwnedFd) -> io::Result<AnswerStamps> {
        Ok(AnswerStamps {
            page: SharedRegion::sized(fd, MAP_LEN)?,
        })
    }

    /// Maps the page behind `fd` (a replica, from the fd its voter handed it). An fd that is
    /// not a file of at least a page is refused (mapping it could SIGBUS later).
    pub fn adopt(fd: OwnedFd) -> io::Result<AnswerStamps> {
        Ok(AnswerStamps {
            page: SharedRegion::handed(fd, MAP_LEN, "an answer-stamp page")?,
        })
    }

    /// The page's fd (the voter maps it into the replicas it starts).
    pub fn fd(&self) -> std::os::fd::BorrowedFd<'_> {
        std::os::fd::AsFd::as_fd(&self.page)
    }

    fn pid_word(&self, entry: usize) -> &AtomicU64 {
        self.page.u64_at(entry * ENTRY_LEN)
    }

    fn stamp_word(&self, entry: usize) -> &AtomicU64 {
        self.page.u64_at(entry * ENTRY_LEN + 8)
    }

    /// The entry that holds `pid`, if one does.
    fn entry_of(&self, pid: u32) -> Option<usize> {
        let pid = u64::from(pid);
        (0..ENTRIES).find(|&e| pid != 0 && self.pid_word(e).load(Ordering::Acquire) == pid)
    }

    /// Claims a free entry for `pid` (its stamp cleared) and returns it; `None` if the page is
    /// full.
    pub fn claim(&self, pid: u32) -> Option<usize> {
        if pid == 0 {
            return None;
        }
        if let Some(e) = self.entry_of(pid) {
            return Some(e);
        }
        let pid = u64::from(pid);
        (0..ENTRIES).find(|&e| {
            let word = self.pid_word(e);
            if word.load(Ordering::Relaxed) != 0 {
                return false;
            }
            // The stamp is cleared before the pid is published, so that the voter never
            // takes a previous holder's stamp for this process's.
            self.stamp_word(e).store(0, Ordering::Relaxed);
            match word.compare_exchange(0, pid, Ordering::Release, Ordering::Relaxed) {
                Ok(_) => true,
                // This same process claimed it meanwhile (a `write` from a signal handler
                // that came in the middle of this claim, under the preload library): it is
                // ours, and taking a second entry would leave the one the voter reads (the
                // first with our pid) never stamped again.
                Err(holder) => holder == pid,
            }
        })
    }

    /// Stamps `entry` with `now_ns` if it still belongs to `pid` (`false`: it does not, and
    /// the caller must claim one again).
    pub fn stamp(&self, entry: usize, pid: u32, now_ns: u64) -> bool {
        if entry >= ENTRIES || self.pid_word(entry).load(Ordering::Relaxed) != u64::from(pid) {
            return false;
        }
        self.stamp_word(entry).store(now_ns, Ordering::Release);
        true
    }

    /// When `pid` last answered (`CLOCK_MONOTONIC` ns), if it holds an entry and has stamped
    /// it since.
    pub fn answered_at(&self, pid: u32) -> Option<u64> {
        let e = self.entry_of(pid)?;
        match self.stamp_word(e).load(Ordering::Acquire) {
            0 => None,
            ns => Some(ns),
        }
    }

    /// Frees every entry whose pid `keep` refuses (the voter: replicas it no longer has).
    pub fn retain(&self, keep: impl Fn(u32) -> bool) {
        for e in 0..ENTRIES {
            let word = self.pid_word(e);
            let pid = word.load(Ordering::Relaxed);
            if pid != 0 && !u32::try_from(pid).is_ok_and(&keep) {
                let _ = word.compare_exchange(pid, 0, Ordering::Relaxed, Ordering::Relaxed);
            }
        }
    }
}

/// This process's page, if its voter handed it one (set once, at `init`).
static PAGE: OnceLock<AnswerStamps> = OnceLock::new();
/// This process's pid (set at `init`, and by the restart handler in a forked child).
static PID: AtomicU64 = AtomicU64::new(0);
/// The entry this process claimed, or `usize::MAX` before it has one.
static ENTRY: AtomicUsize = AtomicUsize::new(usize::MAX);

/// Takes the page handed at `init` (a replica started by exec).
pub(crate) fn install(page: AnswerStamps) {
    PID.store(u64::from(std::process::id()), Ordering::Relaxed);
    let _ = PAGE.set(page);
}

/// In a child the restart handler forked: it is another process, with no entry yet. Only
/// atomics: async-signal-safe.
pub(crate) fn forked(pid: libc::pid_t) {
    PID.store(pid as u64, Ordering::Relaxed);
    ENTRY.store(usize::MAX, Ordering::Relaxed);
}

/// Stamps this process's entry with the time now, right after an answer's write: the runtime's
/// output ports call it ([`crate::OutPort::send`]), and so does the preload library's `write`
/// when a write completes a line or a frame. Without a page, or with the page full, nothing:
/// the voter then looks for the answer on its timer. Only atomics and the vDSO clock:
/// async-signal-safe, no allocation.
pub fn answered() {
    let Some(page) = PAGE.get() else {
        return;
    };
    let Ok(pid) = u32::try_from(PID.load(Ordering::Relaxed)) else {
        return;
    };
    let now = crate::sys::monotonic_ns();
    let entry = ENTRY.load(Ordering::Relaxed);
    if page.stamp(entry, pid, now) {
        return;
    }
    if let Some(entry) = page.claim(pid) {
        ENTRY.store(entry, Ordering::Relaxed);
        page.stamp(entry, pid, now);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_mappings() -> (AnswerStamps, AnswerStamps) {
        let voter = AnswerStamps::create().unwrap();
        let fd = voter.fd().try_clone_to_owned().unwrap();
        (voter, AnswerStamps::adopt(fd).unwrap())
    }

    #[test]
    fn a_replica_stamps_its_own_entry_and_the_voter_reads_it_by_pid() {
        let (voter, replica) = two_mappings();
        assert_eq!(voter.answered_at(100), None, "nobody has an entry yet");
        let e = replica.claim(100).unwrap();
        assert_eq!(voter.answered_at(100), None, "claimed, not stamped");
        assert!(replica.stamp(e, 100, 5_000));
        assert_eq!(voter.answered_at(100), Some(5_000));
        let f = replica.claim(200).unwrap();
        assert_ne!(e, f, "two processes never share an entry");
        assert!(replica.stamp(f, 200, 7_000));
        assert_eq!(voter.answered_at(100), Some(5_000));
        assert_eq!(voter.answered_at(200), Some(7_000));
        assert_eq!(
            replica.claim(100),
            Some(e),
            "a second claim finds the first"
        );
    }

    #[test]
    fn a_freed_entry_is_not_stamped_and_its_next_holder_starts_without_a_stamp() {
        let (voter, replica) = two_mappings();
        let e = replica.claim(100).unwrap();
        assert!(replica.stamp(e, 100, 5_000));
        voter.retain(|pid| pid != 100);
        assert_eq!(voter.answered_at(100), None);
        assert!(
            !replica.stamp(e, 100, 6_000),
            "the entry is no longer 100's"
        );
        let again = replica.claim(300).unwrap();
        assert_eq!(again, e, "the freed entry is reused");
        assert_eq!(
            voter.answered_at(300),
            None,
            "not the previous holder's stamp"
        );
        assert!(
            !replica.stamp(e, 100, 6_000),
            "nor can 100 stamp 300's entry"
        );
    }

    #[test]
    fn a_full_page_gives_no_entry_and_retain_keeps_whom_it_is_told() {
        let (voter, replica) = two_mappings();
        for pid in 1..=ENTRIES as u32 {
            assert!(replica.claim(pid).is_some());
        }
        assert_eq!(replica.claim(9_999), None);
        voter.retain(|pid| pid % 2 == 0);
        assert!(replica.claim(9_999).is_some());
        assert!(voter.entry_of(2).is_some() && voter.entry_of(3).is_none());
    }

    #[test]
    fn a_kept_page_is_sized_once_and_keeps_its_entries_for_the_next_voter() {
        let fd = memfd(c"test").unwrap();
        let first = AnswerStamps::kept(fd.try_clone().unwrap()).unwrap();
        let e = first.claim(100).unwrap();
        assert!(first.stamp(e, 100, 5_000));
        drop(first);
        let successor = AnswerStamps::kept(fd).unwrap();
        assert_eq!(successor.answered_at(100), Some(5_000));
    }

    /// The only test that installs the process's page (other tests' sends stamp it too).
    #[test]
    fn the_runtime_stamps_its_own_entry_and_a_forked_child_claims_another() {
        let voter = AnswerStamps::create().unwrap();
        install(AnswerStamps::adopt(voter.fd().try_clone_to_owned().unwrap()).unwrap());
        let me = std::process::id();
        answered();
        let mine = voter
            .answered_at(me)
            .expect("the runtime stamped its answer");
        // What the restart handler does in a child: another pid, no entry yet.
        let child = 4_000_000;
        forked(child);
        answered();
        let childs = voter
            .answered_at(child as u32)
            .expect("the child claimed an entry");
        assert!(childs >= mine);
        assert_ne!(voter.entry_of(me), voter.entry_of(child as u32));
    }

    #[test]
    fn a_file_smaller_than_a_page_is_refused() {
        let fd = memfd(c"test").unwrap();
        let err = AnswerStamps::adopt(fd).unwrap_err();
        assert!(
            err.to_string().contains("not an answer-stamp page"),
            "{err}"
        );
    }
}
