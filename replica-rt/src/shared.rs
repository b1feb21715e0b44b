//! A region of shared memory behind a memfd, with safe accessors: atomics at aligned offsets,
//! bytes copied in and out, and a `read(2)` straight into the region. The voter's journal
//! (`voter/src/journal.rs`) lives in one: bootstrap makes the memfd and keeps it, so what a
//! voter wrote there is still there for its successor.
//!
//! The region is only ever touched through atomics and through system calls and copies that
//! name an offset, never through a Rust reference to its bytes that the kernel could change
//! under it.

use std::io;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, FromRawFd, OwnedFd};
use std::ptr::NonNull;
use std::sync::atomic::AtomicU64;

/// A shared mapping of a whole memfd.
#[derive(Debug)]
pub struct SharedRegion {
    base: NonNull<u8>,
    len: usize,
    fd: OwnedFd,
}

// SAFETY: the mapping is only accessed through atomics, system calls and byte copies at
// checked offsets (see the module comment); it lives until Drop, which needs `&mut self`.
unsafe impl Send for SharedRegion {}

/// A new, empty memfd, close-on-exec (handed on by fd mapping only).
pub fn memfd(name: &std::ffi::CStr) -> io::Result<OwnedFd> {
    // SAFETY: `name` is a valid NUL-terminated string; memfd_create returns a new fd or -1.
    let fd = unsafe { libc::memfd_create(name.as_ptr(), libc::MFD_CLOEXEC) };
    if fd < 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: the kernel just created this fd for us; it is open and unowned.
    Ok(unsafe { OwnedFd::from_raw_fd(fd) })
}

/// The size of the file behind `fd`, in bytes.
pub fn file_size(fd: BorrowedFd<'_>) -> io::Result<usize> {
    // SAFETY: all-zero is a valid `stat`, and `st` is a valid out-pointer for fstat.
    let mut st: libc::stat = unsafe { std::mem::zeroed() };
    // SAFETY: as above; `fd` is open for the borrow.
    if unsafe { libc::fstat(fd.as_raw_fd(), &mut st) } != 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(st.st_size.max(0) as usize)
}

impl SharedRegion {
    /// Maps the file behind `fd`, first making it `len` bytes long (new bytes read as zero).
    pub fn sized(fd: OwnedFd, len: usize) -> io::Result<SharedRegion> {
        // SAFETY: ftruncate on an fd we own.
        if unsafe { libc::ftruncate(fd.as_raw_fd(), len as libc::off_t) } != 0 {
            return Err(io::Error::last_os_error());
        }
        Self::map(fd, len)
    }

    /// Maps the file behind `fd` as it is (a successor adopting its predecessor's region).
    pub fn existing(fd: OwnedFd) -> io::Result<SharedRegion> {
        let len = file_size(fd.as_fd())?;
        if len == 0 {
            return Err(io::Error::new(io::ErrorKind::InvalidData, "empty region"));
        }
        Self::map(fd, len)
    }

    /// Maps the file behind `fd`, handed over by another process as a `what`: refused unless
    /// it is a regular file of at least `min_len` bytes (mapping a shorter one could SIGBUS
    /// later).
    pub fn handed(fd: OwnedFd, min_len: usize, what: &str) -> io::Result<SharedRegion> {
        // SAFETY: `st` is a valid out-pointer for fstat; all-zero is a valid `stat`.
        let mut st: libc::stat = unsafe { std::mem::zeroed() };
        // SAFETY: as above; `fd` is open (we own it).
        if unsafe { libc::fstat(fd.as_raw_fd(), &mut st) } != 0 {
            return Err(io::Error::last_os_error());
        }
        if (st.st_mode & libc::S_IFMT) != libc::S_IFREG || (st.st_size as usize) < min_len {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("not {what} ({} bytes)", st.st_size),
            ));
        }
        Self::existing(fd)
    }

    fn map(fd: OwnedFd, len: usize) -> io::Result<SharedRegion> {
        if len == 0 {
            return Err(io::Error::new(io::ErrorKind::InvalidInput, "empty region"));
        }
        // SAFETY: a fresh shared mapping of `len` bytes of a file at least that long (made so
        // by `sized`, or measured by `existing`); the kernel picks the address.
        let ptr = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                len,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_SHARED,
                fd.as_raw_fd(),
                0,
            )
        };
        if ptr == libc::MAP_FAILED {
            return Err(io::Error::last_os_error());
        }
        let base = NonNull::new(ptr.cast::<u8>())
            .ok_or_else(|| io::Error::other("mmap gave a null address"))?;
        Ok(SharedRegion { base, len, fd })
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    fn check(&self, off: usize, n: usize) {
        assert!(
            off.checked_add(n).is_some_and(|end| end <= self.len),
            "offset {off}+{n} outside a shared region of {} bytes",
            self.len
        );
    }

    /// The 64-bit atomic at `off` (a multiple of 8, inside the region; panics otherwise: the
    /// offsets are the caller's layout, not input).
    pub fn u64_at(&self, off: usize) -> &AtomicU64 {
        self.check(off, 8);
        assert_eq!(off % 8, 0, "unaligned atomic at {off}");
        // SAFETY: in bounds and 8-aligned (the mapping is page-aligned), valid for the borrow
        // of `self` (the mapping lives until Drop); any bit pattern is a valid AtomicU64, and
        // other processes touch the word only atomically or through the kernel.
        unsafe { &*self.base.as_ptr().add(off).cast::<AtomicU64>() }
    }

    /// Copies `src` into the region at `off`.
    pub fn write_bytes(&mut self, off: usize, src: &[u8]) {
        self.check(off, src.len());
        // SAFETY: in bounds (checked); the source is a Rust slice outside the mapping, so the
        // two do not overlap.
        unsafe {
            std::ptr::copy_nonoverlapping(src.as_ptr(), self.base.as_ptr().add(off), src.len())
        };
    }

    /// Copies `dst.len()` bytes at `off` out of the region.
    pub fn read_bytes(&self, off: usize, dst: &mut [u8]) {
        self.check(off, dst.len());
        // SAFETY: in bounds (checked); `dst` is a Rust slice outside the mapping.
        unsafe {
            std::ptr::copy_nonoverlapping(self.base.as_ptr().add(off), dst.as_mut_ptr(), dst.len())
        };
    }

    /// One `read(2)` from `fd` of up to `n` bytes straight into the region at `off`: what it
    /// takes from `fd` is in the region the moment the call returns, in one system call.
    pub fn read_from(&mut self, fd: BorrowedFd<'_>, off: usize, n: usize) -> io::Result<usize> {
        self.check(off, n);
        loop {
            // SAFETY: the destination is `n` bytes inside the mapping (checked), writable,
            // and not borrowed by any Rust reference while the kernel writes it.
            let got = unsafe { libc::read(fd.as_raw_fd(), self.base.as_ptr().add(off).cast(), n) };
            if got >= 0 {
                return Ok(got as usize);
            }
            let e = io::Error::last_os_error();
            if e.kind() != io::ErrorKind::Interrupted {
                return Err(e);
            }
        }
    }
}

impl AsFd for SharedRegion {
    fn as_fd(&self) -> BorrowedFd<'_> {
        self.fd.as_fd()
    }
}

impl Drop for SharedRegion {
    fn drop(&mut self) {
        // SAFETY: the mapping was made by `map` with this address and length, and nothing
        // borrows it after Drop (every accessor borrows `self`).
        unsafe { libc::munmap(self.base.as_ptr().cast(), self.len) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::Ordering;

    #[test]
    fn two_mappings_of_one_memfd_see_each_others_writes_and_reads() {
        let fd = memfd(c"test").unwrap();
        let copy = fd.try_clone().unwrap();
        let mut a = SharedRegion::sized(fd, 8192).unwrap();
        let b = SharedRegion::existing(copy).unwrap();
        assert_eq!(b.len(), 8192);
        a.u64_at(8).store(42, Ordering::Relaxed);
        assert_eq!(b.u64_at(8).load(Ordering::Relaxed), 42);
        a.write_bytes(100, b"hello");
        let mut got = [0u8; 5];
        b.read_bytes(100, &mut got);
        assert_eq!(&got, b"hello");
        let (r, w) = nix::unistd::pipe().unwrap();
        nix::unistd::write(&w, b"piped").unwrap();
        assert_eq!(a.read_from(r.as_fd(), 4000, 16).unwrap(), 5);
        b.read_bytes(4000, &mut got);
        assert_eq!(&got, b"piped");
    }

    #[test]
    #[should_panic(expected = "outside a shared region")]
    fn an_offset_outside_the_region_is_refused() {
        let region = SharedRegion::sized(memfd(c"test").unwrap(), 4096).unwrap();
        region.u64_at(4096);
    }
}
