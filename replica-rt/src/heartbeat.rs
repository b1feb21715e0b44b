//! A voter's heartbeat: a counter in a page of shared memory that the voter bumps on every
//! turn of its loop (a plain atomic add, no syscall) and bootstrap reads. A voter that is
//! stopped (SIGSTOP, a debugger) or stuck leaves it still; bootstrap sees that without any
//! help from the voter. bootstrap creates the page (a memfd) and hands its fd to the voter
//! like any other inherited fd.

use std::io;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, FromRawFd, OwnedFd};
use std::ptr::NonNull;
use std::sync::atomic::{AtomicU64, Ordering};

/// The shared page's layout.
#[repr(C)]
struct Page {
    /// Turns of the voter's loop so far.
    beats: AtomicU64,
    /// Non-zero once the voter is ending (draining its output, letting replicas finish): its
    /// waits are then bounded by its own limits, not by the heartbeat.
    ending: AtomicU64,
}

/// The size of the mapping (one page; the layout needs 16 bytes of it).
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
    page: NonNull<Page>,
    fd: OwnedFd,
}

// SAFETY: the page is only accessed through atomics, so sharing it between threads (a
// `static` in the voter) is as safe as sharing the atomics themselves; the mapping lives
// until `Drop`, which needs `&mut self`.
unsafe impl Send for Heartbeat {}
// SAFETY: as above.
unsafe impl Sync for Heartbeat {}

impl Heartbeat {
    /// A new, zeroed page (bootstrap): a memfd, close-on-exec (handed on by fd mapping only).
    pub fn create() -> io::Result<Heartbeat> {
        // SAFETY: the name is a valid NUL-terminated string; memfd_create returns a new fd
        // or -1.
        let fd = unsafe { libc::memfd_create(c"s3res-heartbeat".as_ptr(), libc::MFD_CLOEXEC) };
        if fd < 0 {
            return Err(io::Error::last_os_error());
        }
        // SAFETY: the kernel just created this fd for us; it is open and unowned.
        let fd = unsafe { OwnedFd::from_raw_fd(fd) };
        // SAFETY: ftruncate on an fd we own, with a positive length.
        if unsafe { libc::ftruncate(fd.as_raw_fd(), MAP_LEN as libc::off_t) } != 0 {
            return Err(io::Error::last_os_error());
        }
        Self::map(fd)
    }

    /// Maps the page behind `fd` (the voter, from the fd bootstrap handed it). An fd that is
    /// not a page of at least the layout's size is refused (mapping it could SIGBUS later).
    pub fn adopt(fd: OwnedFd) -> io::Result<Heartbeat> {
        // SAFETY: `st` is a valid out-pointer for fstat; all-zero is a valid `stat`.
        let mut st: libc::stat = unsafe { std::mem::zeroed() };
        // SAFETY: as above; `fd` is open (we own it).
        if unsafe { libc::fstat(fd.as_raw_fd(), &mut st) } != 0 {
            return Err(io::Error::last_os_error());
        }
        if (st.st_mode & libc::S_IFMT) != libc::S_IFREG || (st.st_size as usize) < MAP_LEN {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("not a heartbeat page ({} bytes)", st.st_size),
            ));
        }
        Self::map(fd)
    }

    fn map(fd: OwnedFd) -> io::Result<Heartbeat> {
        // SAFETY: a fresh shared mapping of MAP_LEN bytes of a regular file at least that
        // long (checked or set by the callers); the kernel picks the address.
        let ptr = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                MAP_LEN,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_SHARED,
                fd.as_raw_fd(),
                0,
            )
        };
        if ptr == libc::MAP_FAILED {
            return Err(io::Error::last_os_error());
        }
        let page = NonNull::new(ptr.cast::<Page>())
            .ok_or_else(|| io::Error::other("mmap gave a null address"))?;
        Ok(Heartbeat { page, fd })
    }

    fn page(&self) -> &Page {
        // SAFETY: `page` points at a live, page-aligned mapping of MAP_LEN bytes (until
        // Drop), and `Page` is two atomics, valid for any bit pattern (zero at creation).
        unsafe { self.page.as_ref() }
    }

    /// One more turn of the loop.
    pub fn beat(&self) {
        self.page().beats.fetch_add(1, Ordering::Relaxed);
    }

    /// The voter is ending: stop judging it by its heartbeat.
    pub fn set_ending(&self) {
        self.page().ending.store(1, Ordering::Relaxed);
    }

    pub fn read(&self) -> Pulse {
        let page = self.page();
        Pulse {
            beats: page.beats.load(Ordering::Relaxed),
            ending: page.ending.load(Ordering::Relaxed) != 0,
        }
    }
}

impl AsFd for Heartbeat {
    fn as_fd(&self) -> BorrowedFd<'_> {
        self.fd.as_fd()
    }
}

impl Drop for Heartbeat {
    fn drop(&mut self) {
        // SAFETY: the mapping was made by `map` with this address and length and nothing
        // refers to it after Drop (`page()` borrows `self`).
        unsafe { libc::munmap(self.page.as_ptr().cast(), MAP_LEN) };
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

    fn tempfile_fd(len: i64) -> OwnedFd {
        // SAFETY: as in `create`.
        let fd = unsafe { libc::memfd_create(c"test".as_ptr(), libc::MFD_CLOEXEC) };
        assert!(fd >= 0);
        // SAFETY: the fd was just created for us.
        let fd = unsafe { OwnedFd::from_raw_fd(fd) };
        // SAFETY: ftruncate on an fd we own.
        assert_eq!(unsafe { libc::ftruncate(fd.as_raw_fd(), len) }, 0);
        fd
    }
}
