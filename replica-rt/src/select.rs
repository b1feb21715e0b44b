//! Waiting on several input ports at once, and receiving without blocking.
//!
//! [`InPort::recv`] blocks until a frame arrives, which is all a one-input component needs. A
//! component with several inputs (a navigator that takes sensor frames and waypoints) waits with
//! [`wait_any`] and then receives from the ready port; a loop with a period of its own (a
//! simulator that must not wait for a late command) uses [`InPort::try_recv`] or
//! [`InPort::recv_timeout`].
//!
//! All of it is EINTR-safe: the restart signal interrupts `ppoll`, which the kernel never
//! restarts, so every wait here retries with the time that is left. Nothing here allocates.
//!
//! A port reads ahead, so "ready" means *a whole frame is already buffered in the port, or its
//! fd is readable (data, end of stream or error)*: a port whose fd polls empty may still hold
//! frames. After [`wait_any`] says a port is ready, `try_recv` on it may still return
//! [`TryRecv::Empty`] (only part of a frame has arrived); wait again.

use std::io;
use std::os::fd::{AsFd, AsRawFd};
use std::time::Duration;

use crate::contract::MAX_PORTS;
use crate::port::{InPort, RecvError};
use crate::{restart, sys};

/// What a non-blocking receive found.
#[derive(Debug, PartialEq, Eq)]
pub enum TryRecv<'a> {
    /// The next frame's payload.
    Frame(&'a [u8]),
    /// No whole frame yet (for [`InPort::recv_timeout`]: none before the timeout).
    Empty,
    /// End of stream: the writer closed the channel and every frame has been returned.
    Closed,
}

/// Which of the ports given to [`wait_any`] are ready, as a bit set by position.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Ready(u32);

impl Ready {
    /// Whether the port at `index` (in the slice given to [`wait_any`]) is ready.
    pub fn is_ready(self, index: usize) -> bool {
        index < 32 && self.0 & (1 << index) != 0
    }

    /// Whether no port is ready (the wait timed out).
    pub fn is_empty(self) -> bool {
        self.0 == 0
    }
}

/// Waits until at least one of `ports` is ready (see the module docs), or `timeout` passes
/// (`None`: no limit). Returns the ready set, empty on timeout. At most [`MAX_PORTS`] ports.
pub fn wait_any(ports: &[&InPort], timeout: Option<Duration>) -> io::Result<Ready> {
    if ports.len() > MAX_PORTS {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            "wait_any: more ports than a component may have",
        ));
    }
    // Before waiting for input: the round before has been answered (as in `recv`).
    restart::between_rounds();
    let deadline = timeout.map(|t| sys::monotonic_ns().saturating_add(nanos(t)));
    let mut pfds = [libc::pollfd {
        fd: -1,
        events: 0,
        revents: 0,
    }; MAX_PORTS];
    loop {
        // Frames already buffered (or a port already at its end) need no system call.
        let mut ready = 0u32;
        for (i, port) in ports.iter().enumerate() {
            // A port behind a rebind has its old pipe's last frames to take (see `rebind`).
            if port.dec.has_frame() || port.eof || port.behind_a_rebind() {
                ready |= 1 << i;
            }
        }
        if ready != 0 {
            return Ok(Ready(ready));
        }
        for (pfd, port) in pfds.iter_mut().zip(ports) {
            *pfd = libc::pollfd {
                fd: port.as_fd().as_raw_fd(),
                events: libc::POLLIN,
                revents: 0,
            };
        }
        let left = match deadline {
            None => None,
            Some(d) => {
                let now = sys::monotonic_ns();
                if now >= d {
                    return Ok(Ready(0));
                }
                Some(Duration::from_nanos(d - now))
            }
        };
        // EINTR comes back as 0 ready fds: loop, with the time that is left.
        if sys::ppoll(&mut pfds[..ports.len()], left)? == 0 {
            continue;
        }
        for (i, pfd) in pfds[..ports.len()].iter().enumerate() {
            if pfd.revents != 0 {
                ready |= 1 << i;
            }
        }
        if ready != 0 {
            return Ok(Ready(ready));
        }
    }
}

fn nanos(t: Duration) -> u64 {
    u64::try_from(t.as_nanos()).unwrap_or(u64::MAX)
}

impl InPort {
    /// Whether a whole frame is buffered in the port already (a `recv` would not read).
    pub fn has_buffered_frame(&self) -> bool {
        self.dec.has_frame()
    }

    /// The next frame if one can be had without blocking: from the port's buffer, or from what
    /// the channel holds right now. Errors as [`InPort::recv`].
    pub fn try_recv(&mut self) -> Result<TryRecv<'_>, RecvError> {
        // As in `recv`: a component that only polls must also lock a fork child's memory and
        // keep a spare line (`restart::between_rounds`; two atomic loads when there is nothing
        // to do). One that looks here in the middle of a round, after `wait_any`, has done
        // that work there already.
        restart::between_rounds();
        self.recv_until(Some(0))
    }

    /// The next frame, waiting at most `timeout` for it; [`TryRecv::Empty`] if none came whole
    /// in time.
    pub fn recv_timeout(&mut self, timeout: Duration) -> Result<TryRecv<'_>, RecvError> {
        // Before waiting for input: the round before has been answered (as in `recv`).
        restart::between_rounds();
        self.recv_until(Some(sys::monotonic_ns().saturating_add(nanos(timeout))))
    }

    /// `deadline`: CLOCK_MONOTONIC ns; `Some(0)` means "do not wait at all".
    fn recv_until(&mut self, deadline: Option<u64>) -> Result<TryRecv<'_>, RecvError> {
        self.catch_up();
        loop {
            if self.next_buffered()? {
                return Ok(TryRecv::Frame(&self.frame[self.at.clone()]));
            }
            if self.eof {
                return match self.dec.finish() {
                    Ok(()) => Ok(TryRecv::Closed),
                    Err(e) => Err(self.frame_error(e)),
                };
            }
            let left =
                deadline.map(|d| Duration::from_nanos(d.saturating_sub(sys::monotonic_ns())));
            let mut pfd = [libc::pollfd {
                fd: self.fd.as_raw_fd(),
                events: libc::POLLIN,
                revents: 0,
            }];
            let readable = sys::ppoll(&mut pfd, left).map_err(|e| self.io_error(e))? > 0;
            if !readable {
                // Timed out, or interrupted by a signal (EINTR): try again while time is left.
                if deadline.is_some_and(|d| sys::monotonic_ns() >= d) {
                    return Ok(TryRecv::Empty);
                }
                continue;
            }
            // Readable: this read does not block (data, end of stream, or an error).
            if !self.fill()? {
                self.eof = true;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::port::OutPort;
    use std::time::Instant;

    fn channel() -> (InPort, OutPort) {
        let (r, w) = sys::pipe().unwrap();
        (
            InPort::new("in".into(), r, 1024, false),
            OutPort::new("out".into(), w, 1024, false),
        )
    }

    #[test]
    fn try_recv_returns_frames_empty_and_closed() {
        let (mut input, mut output) = channel();
        assert_eq!(input.try_recv().unwrap(), TryRecv::Empty);
        output.send(b"one").unwrap();
        output.send(b"two").unwrap();
        assert_eq!(input.try_recv().unwrap(), TryRecv::Frame(b"one"));
        // The second frame was read ahead with the first.
        assert!(input.has_buffered_frame());
        assert_eq!(input.try_recv().unwrap(), TryRecv::Frame(b"two"));
        assert_eq!(input.try_recv().unwrap(), TryRecv::Empty);
        // Half a frame is not a frame.
        output.write_raw(&[5, 0, 0, 0, b'a']).unwrap();
        assert_eq!(input.try_recv().unwrap(), TryRecv::Empty);
        output.write_raw(b"bcde").unwrap();
        assert_eq!(input.try_recv().unwrap(), TryRecv::Frame(b"abcde"));
        drop(output);
        assert_eq!(input.try_recv().unwrap(), TryRecv::Closed);
        assert_eq!(input.try_recv().unwrap(), TryRecv::Closed);
    }

    #[test]
    fn recv_timeout_waits_then_gives_up() {
        let (mut input, mut output) = channel();
        let t0 = Instant::now();
        assert_eq!(
            input.recv_timeout(Duration::from_millis(30)).unwrap(),
            TryRecv::Empty
        );
        assert!(t0.elapsed() >= Duration::from_millis(30));
        let writer = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(20));
            output.send(b"late").unwrap();
        });
        assert_eq!(
            input.recv_timeout(Duration::from_secs(10)).unwrap(),
            TryRecv::Frame(b"late")
        );
        writer.join().unwrap();
        assert_eq!(
            input.recv_timeout(Duration::from_secs(10)).unwrap(),
            TryRecv::Closed
        );
    }

    #[test]
    fn wait_any_names_the_ready_port_and_sees_buffered_frames() {
        let (mut a, mut a_out) = channel();
        let (b, mut b_out) = channel();
        assert!(wait_any(&[&a, &b], Some(Duration::from_millis(10)))
            .unwrap()
            .is_empty());
        b_out.send(b"x").unwrap();
        let ready = wait_any(&[&a, &b], Some(Duration::from_secs(10))).unwrap();
        assert!(!ready.is_ready(0) && ready.is_ready(1));
        // Two frames in one read: the second is buffered, the fd is empty, the port is ready.
        a_out.send(b"1").unwrap();
        a_out.send(b"2").unwrap();
        assert_eq!(a.try_recv().unwrap(), TryRecv::Frame(b"1"));
        let ready = wait_any(&[&a], Some(Duration::ZERO)).unwrap();
        assert!(ready.is_ready(0));
        assert_eq!(a.try_recv().unwrap(), TryRecv::Frame(b"2"));
        drop(a_out);
        // End of stream counts as ready (the next receive reports it).
        assert!(wait_any(&[&a], None).unwrap().is_ready(0));
        assert_eq!(a.try_recv().unwrap(), TryRecv::Closed);
    }
}
