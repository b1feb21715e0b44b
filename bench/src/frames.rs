//! The bench's own ends of the pipes into and out of the system under test: whole frames
//! (4-byte little-endian length, then the payload), every wait bounded by a deadline so a stuck
//! system can never hang the bench. Writes are non-blocking and wait with `ppoll`; reads block
//! in `read`, as the peers' harnesses do, bounded by `crate::sys::read_deadline`.

use std::io;
use std::os::fd::{AsFd, AsRawFd, OwnedFd};
use std::time::{Duration, Instant};

use replica_rt::frame::{frame_start, FrameBuf, FRAME_SLACK};
use replica_rt::sys;

use crate::sys::read_deadline;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum FrameIoError {
    #[error("no frame within {0:?}")]
    Timeout(Duration),
    #[error("the pipe closed")]
    Closed,
    #[error("interrupted (SIGINT/SIGTERM)")]
    Interrupted,
    #[error("frame of {0} bytes is larger than the {1}-byte limit")]
    Oversized(usize, usize),
    #[error(transparent)]
    Io(#[from] io::Error),
}

/// Waits for `events` on `fd` until `deadline`.
fn wait(fd: &OwnedFd, events: libc::c_short, deadline: Instant) -> Result<(), FrameIoError> {
    loop {
        if crate::sys::interrupted() {
            return Err(FrameIoError::Interrupted);
        }
        let now = Instant::now();
        if now >= deadline {
            return Err(FrameIoError::Timeout(Duration::ZERO));
        }
        let mut pfd = [libc::pollfd {
            fd: fd.as_raw_fd(),
            events,
            revents: 0,
        }];
        match sys::ppoll(&mut pfd, Some(deadline - now)) {
            Ok(0) => continue,
            Ok(_) => return Ok(()),
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e.into()),
        }
    }
}

/// Writes frames into a pipe.
pub struct FrameOut {
    fd: OwnedFd,
    /// The frame being sent, placed in a page as `frame::COPY_ALIGN` says.
    buf: FrameBuf,
}

impl FrameOut {
    pub fn new(fd: OwnedFd) -> io::Result<Self> {
        sys::set_nonblocking(fd.as_fd(), true)?;
        Ok(FrameOut {
            fd,
            buf: FrameBuf::default(),
        })
    }

    /// Writes one whole frame, waiting for room until `timeout` has passed.
    pub fn send(&mut self, payload: &[u8], timeout: Duration) -> Result<(), FrameIoError> {
        self.stage(payload);
        self.send_staged(timeout)
    }

    /// Frames `payload` (header, then a copy of it) for [`send_staged`](Self::send_staged):
    /// a timed round trip frames its request before its first timestamp, as the peers'
    /// harnesses have theirs ready before theirs.
    pub fn stage(&mut self, payload: &[u8]) {
        self.buf.encode(payload);
    }

    /// Writes the frame [`stage`](Self::stage) made, waiting for room until `timeout` has
    /// passed.
    pub fn send_staged(&mut self, timeout: Duration) -> Result<(), FrameIoError> {
        let frame = self.buf.as_slice();
        // Read off the clock only if the pipe is full: a round trip's clock reads are the
        // bench's two timestamps, as in the peers' harnesses.
        let mut deadline = None;
        let mut done = 0;
        while done < frame.len() {
            match sys::write(self.fd.as_fd(), &frame[done..]) {
                Ok(n) => done += n,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    let by = *deadline.get_or_insert_with(|| Instant::now() + timeout);
                    wait(&self.fd, libc::POLLOUT, by).map_err(|e| match e {
                        FrameIoError::Timeout(_) => FrameIoError::Timeout(timeout),
                        e => e,
                    })?
                }
                Err(e) if e.kind() == io::ErrorKind::BrokenPipe => {
                    return Err(FrameIoError::Closed)
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e.into()),
            }
        }
        Ok(())
    }
}

/// Reads frames from a pipe.
pub struct FrameIn {
    fd: OwnedFd,
    max_frame: usize,
    buf: Vec<u8>,
    /// Where in `buf` frames are read from ([`frame_start`], see `frame::COPY_ALIGN`).
    base: usize,
    /// Bytes `start..end` of `buf` are received and not yet returned.
    start: usize,
    end: usize,
}

impl FrameIn {
    pub fn new(fd: OwnedFd, max_frame: usize) -> io::Result<Self> {
        // Blocking: `recv` waits in `read`, bounded by `crate::sys::read_deadline`.
        sys::set_nonblocking(fd.as_fd(), false)?;
        let buf = vec![0; FRAME_SLACK + 2 * (max_frame + 4)];
        let base = frame_start(&buf);
        Ok(FrameIn {
            fd,
            max_frame,
            buf,
            base,
            start: base,
            end: base,
        })
    }

    /// The length of the whole frame at `start`, if it is all here.
    fn whole_frame(&self) -> Result<Option<usize>, FrameIoError> {
        let have = self.end - self.start;
        if have < 4 {
            return Ok(None);
        }
        let b = &self.buf[self.start..self.start + 4];
        let len = u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize;
        if len > self.max_frame {
            return Err(FrameIoError::Oversized(len, self.max_frame));
        }
        Ok((have >= 4 + len).then_some(len))
    }

    /// The next whole frame's payload, waiting up to `timeout` (and at most
    /// [`read_deadline::WATCHDOG_PERIOD`] more).
    pub fn recv(&mut self, timeout: Duration) -> Result<&[u8], FrameIoError> {
        let by = s3res_protocol::clock::monotonic_ns().saturating_add(nanos(timeout));
        self.recv_by(by, timeout)
    }

    /// [`recv`](Self::recv) until `by` (CLOCK_MONOTONIC ns; `timeout` is what a timeout
    /// reports): for a caller that has just read the clock, so that the wait reads it only
    /// once a read is interrupted.
    pub fn recv_by(&mut self, by: u64, timeout: Duration) -> Result<&[u8], FrameIoError> {
        let deadline = read_deadline::Armed::new(by)?;
        let mut first = true;
        loop {
            if let Some(len) = self.whole_frame()? {
                let at = self.start + 4;
                self.start = at + len;
                return Ok(&self.buf[at..at + len]);
            }
            // Keep the partial frame at the front so the rest fits behind it.
            if self.start > self.base {
                self.buf.copy_within(self.start..self.end, self.base);
                self.end = self.base + (self.end - self.start);
                self.start = self.base;
            }
            if crate::sys::interrupted() {
                return Err(FrameIoError::Interrupted);
            }
            // Before the first read the deadline is ahead (the caller just set it).
            if !first && deadline.expired() {
                return Err(FrameIoError::Timeout(timeout));
            }
            first = false;
            // One blocking read, as the peers' harnesses wait: no `ppoll` (and its timer)
            // before it. The watchdog interrupts it once the deadline has passed.
            match read_deadline::read(self.fd.as_fd(), &mut self.buf[self.end..]) {
                // After Ctrl-C the handler killed the system, which closed the pipe.
                Ok(0) if crate::sys::interrupted() => return Err(FrameIoError::Interrupted),
                Ok(0) => return Err(FrameIoError::Closed),
                Ok(n) => self.end += n,
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(e.into()),
            }
        }
    }
}

/// `d` in nanoseconds, saturated.
pub fn nanos(d: Duration) -> u64 {
    d.as_nanos().min(u64::MAX as u128) as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A system that never answers: the blocking read is ended by the watchdog and reported as
    /// a timeout, not left blocked; a partial frame does not count as an answer; a closed pipe
    /// is `Closed`. Run on a thread of its own, so that a read left blocked fails the test
    /// instead of hanging it.
    #[test]
    fn a_silent_pipe_times_out_and_a_closed_one_says_so() {
        let (done, finished) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            silent_then_closed();
            let _ = done.send(());
        });
        finished
            .recv_timeout(Duration::from_secs(30))
            .expect("a read was left blocked past its deadline (or the checks failed)");
    }

    fn silent_then_closed() {
        let (r, w) = sys::pipe().unwrap();
        let mut input = FrameIn::new(r, 64).unwrap();
        let timeout = Duration::from_millis(50);
        assert!(matches!(
            input.recv(timeout),
            Err(FrameIoError::Timeout(t)) if t == timeout
        ));
        // Half a frame: its header says 8 bytes, 3 come.
        sys::write(w.as_fd(), &[8, 0, 0, 0, 1, 2, 3]).unwrap();
        assert!(matches!(input.recv(timeout), Err(FrameIoError::Timeout(_))));
        // The rest, and the frame is whole.
        sys::write(w.as_fd(), &[4, 5, 6, 7, 8]).unwrap();
        assert_eq!(input.recv(timeout).unwrap(), [1, 2, 3, 4, 5, 6, 7, 8]);
        drop(w);
        assert!(matches!(input.recv(timeout), Err(FrameIoError::Closed)));
    }
}
