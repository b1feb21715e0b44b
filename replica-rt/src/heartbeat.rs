//! A voter's heartbeat: a counter in a page of shared memory that the voter bumps on every
//! turn of its loop (a plain atomic add, no syscall) and bootstrap reads. A voter that is
//! stopped (SIGSTOP, a debugger) or stuck leaves it still; bootstrap sees that without any
//! help from the voter. bootstrap creates the page (a memfd) and hands its fd to the voter
//! like any other inherited fd.

use std::io;
use std::os::fd::{AsFd, BorrowedFd, OwnedFd};
use std::sync::atomic::Ordering;

use crate::shared::{memfd, SharedRegion};

/// The page's layout: three 64-bit words.
const BEATS: usize = 0;
/// Non-zero once the voter is ending (draining its output, letting replicas finish): its waits
/// are then bounded by its own limits, not by the heartbeat.
const ENDING: usize = 8;
/// Non-zero once bootstrap stops the system (written before it signals anyone): a voter that
/// got a stop signal from some other process — one sent to a whole process group or cgroup —
/// knows from it that the system stops, not its component alone. (Signals do not tell: a
/// second SIGTERM that comes while the first is pending is lost.)
const SYSTEM_STOPPING: usize = 16;

/// The size of the mapping (one page; the layout needs 24 bytes of it).
const MAP_LEN: usize = 4096;

/// What bootstrap reads of a heartbeat.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pulse {
    pub beats: u64,
    pub ending: bool,
}

/// One heartbeat page, mapped shared.
#[derive(Debug)]
pub struct Heartbeat {
    page: SharedRegion,
}

// SAFETY: the page is only accessed through atomics (`SharedRegion::u64_at`), so sharing it
// between threads (a `static` in the voter) is as safe as sharing the atomics themselves.
unsafe impl Sync for Heartbeat {}

impl Heartbeat {
    /// A new, zeroed page (bootstrap): a memfd, close-on-exec (handed on by fd mapping only).
    pub fn create() -> io::Result<Heartbeat> {
        let fd = memfd(c"s3res-heartbeat")?;
        Ok(Heartbeat {
            page: SharedRegion::sized(fd, MAP_LEN)?,
        })
    }

    /// Maps the page behind `fd` (the voter, from the fd bootstrap handed it). An fd that is
    /// not a page of at least the layout's size is refused (mapping it could SIGBUS later).
    pub fn adopt(fd: OwnedFd) -> io::Result<Heartbeat> {
        Ok(Heartbeat {
            page: SharedRegion::handed(fd, MAP_LEN, "a heartbeat page")?,
        })
    }

    /// One more turn of the loop.
    pub fn beat(&self) {
        self.page.u64_at(BEATS).fetch_add(1, Ordering::Relaxed);
    }

    /// The voter is ending: stop judging it by its heartbeat.
    pub fn set_ending(&self) {
        self.page.u64_at(ENDING).store(1, Ordering::Relaxed);
    }

    /// A new voter took over: judge it by the heartbeat again.
    pub fn clear_ending(&self) {
        self.page.u64_at(ENDING).store(0, Ordering::Relaxed);
    }

    /// Bootstrap stops the system (bootstrap, before it signals the components).
    pub fn set_system_stopping(&self) {
        self.page
            .u64_at(SYSTEM_STOPPING)
            .store(1, Ordering::Release);
    }

    /// Whether bootstrap stops the system.
    pub fn system_stopping(&self) -> bool {
        self.page.u64_at(SYSTEM_STOPPING).load(Ordering::Acquire) != 0
    }

    pub fn read(&self) -> Pulse {
        Pulse {
            beats: self.page.u64_at(BEATS).load(Ordering::Relaxed),
            ending: self.page.u64_at(ENDING).load(Ordering::Relaxed) != 0,
        }
    }
}

impl AsFd for Heartbeat {
    fn as_fd(&self) -> BorrowedFd<'_> {
        self.page.as_fd()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn beats_cross_two_mappings_of_one_page() {
        let bootstrap = Heartbeat::create().unwrap();
        let voter = Heartbeat::adopt(bootstrap.as_fd().try_clone_to_owned().unwrap()).unwrap();
        assert_eq!(
            bootstrap.read(),
            Pulse {
                beats: 0,
                ending: false
            }
        );
        voter.beat();
        voter.beat();
        assert_eq!(bootstrap.read().beats, 2);
        voter.set_ending();
        assert!(bootstrap.read().ending);
    }

    #[test]
    fn an_fd_that_is_not_a_heartbeat_page_is_refused() {
        let (r, _w) = nix::unistd::pipe().unwrap();
        assert!(Heartbeat::adopt(r).is_err());
        let small = tempfile_fd(16);
        assert!(Heartbeat::adopt(small).is_err());
    }

    fn tempfile_fd(len: usize) -> OwnedFd {
        let fd = memfd(c"test").unwrap();
        // Sized, then unmapped: only the file's length matters here.
        drop(SharedRegion::sized(fd.try_clone().unwrap(), len).unwrap());
        fd
    }
}
