//! Non-blocking ends of pipes, as the voter sees them. The voter never blocks on a replica or a
//! neighbour: what cannot be written now is kept and written when the pipe has room again, and
//! what is read is decoded incrementally.

use std::io;
use std::os::fd::{AsFd, BorrowedFd, OwnedFd};

use replica_rt::frame::{self, FrameDecoder};
use replica_rt::sys;

/// Bytes read per `read(2)` call.
const READ_CHUNK: usize = 64 * 1024;

/// The writing end of a pipe, with the frames that did not fit yet.
#[derive(Debug)]
pub struct FrameWriter {
    fd: OwnedFd,
    /// Writes each frame as a line (`"framing": "lines"`) instead of length-prefixed.
    lines: bool,
    pending: Vec<u8>,
    /// Start of the unwritten part of `pending`.
    start: usize,
}

impl FrameWriter {
    pub fn new(fd: OwnedFd) -> io::Result<Self> {
        sys::set_nonblocking(fd.as_fd(), true)?;
        Ok(FrameWriter {
            fd,
            lines: false,
            pending: Vec::new(),
            start: 0,
        })
    }

    /// A writer of newline-delimited text: each frame is written as its payload and a `\n`.
    /// (A payload that holds a newline reaches the program as more than one line: the
    /// channel's writer must not send one.)
    pub fn lines(fd: OwnedFd) -> io::Result<Self> {
        Ok(FrameWriter {
            lines: true,
            ..FrameWriter::new(fd)?
        })
    }

    /// Queues a whole frame and writes as much as the pipe takes now.
    pub fn send(&mut self, payload: &[u8]) -> io::Result<()> {
        self.compact();
        if self.lines {
            self.pending.extend_from_slice(payload);
            self.pending.push(b'\n');
        } else {
            frame::encode_into(payload, &mut self.pending);
        }
        self.flush()
    }

    /// Queues raw bytes (already framed) without writing them yet.
    pub fn queue_raw(&mut self, bytes: &[u8]) {
        self.compact();
        self.pending.extend_from_slice(bytes);
    }

    /// Puts raw bytes in front of everything queued (input taken back from a pipe).
    pub fn prepend_raw(&mut self, bytes: &[u8]) {
        self.compact();
        self.pending.splice(0..0, bytes.iter().copied());
    }

    /// Bytes queued and not yet written.
    pub fn unwritten(&self) -> &[u8] {
        &self.pending[self.start..]
    }

    pub fn has_pending(&self) -> bool {
        self.start < self.pending.len()
    }

    /// Drops everything queued (the reader is gone).
    pub fn discard(&mut self) {
        self.pending.clear();
        self.start = 0;
    }

    /// Writes queued bytes until done or the pipe is full.
    pub fn flush(&mut self) -> io::Result<()> {
        while self.has_pending() {
            match sys::write(self.fd.as_fd(), &self.pending[self.start..]) {
                Ok(n) => self.start += n,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) => return Err(e),
            }
        }
        if !self.has_pending() {
            self.pending.clear();
            self.start = 0;
        }
        Ok(())
    }

    fn compact(&mut self) {
        if self.start > 0 {
            self.pending.drain(..self.start);
            self.start = 0;
        }
    }
}

impl AsFd for FrameWriter {
    fn as_fd(&self) -> BorrowedFd<'_> {
        self.fd.as_fd()
    }
}

/// What one [`FrameReader::fill`] saw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fill {
    /// Read what there was; the pipe is still open.
    Open,
    /// The writer closed its end.
    Closed,
}

/// The reading end of a pipe, decoding frames.
#[derive(Debug)]
pub struct FrameReader {
    fd: OwnedFd,
    pub decoder: FrameDecoder,
    closed: bool,
}

impl FrameReader {
    pub fn new(fd: OwnedFd, max_frame: usize) -> io::Result<Self> {
        sys::set_nonblocking(fd.as_fd(), true)?;
        Ok(FrameReader {
            fd,
            decoder: FrameDecoder::new(max_frame),
            closed: false,
        })
    }

    /// A reader of a channel whose writer may be restarted and replay frames behind a resume
    /// frame (another component's voter): the repeats are dropped (see
    /// [`FrameDecoder::resuming`]).
    pub fn resuming(fd: OwnedFd, max_frame: usize) -> io::Result<Self> {
        let mut reader = FrameReader::new(fd, max_frame)?;
        reader.decoder = FrameDecoder::resuming(max_frame);
        Ok(reader)
    }

    /// A reader of newline-delimited text, one frame per line (see [`FrameDecoder::lines`]).
    pub fn lines(fd: OwnedFd, max_frame: usize) -> io::Result<Self> {
        let mut reader = FrameReader::new(fd, max_frame)?;
        reader.decoder = FrameDecoder::lines(max_frame);
        Ok(reader)
    }

    pub fn is_closed(&self) -> bool {
        self.closed
    }

    /// Reads everything available now into the decoder.
    pub fn fill(&mut self) -> io::Result<Fill> {
        if self.closed {
            return Ok(Fill::Closed);
        }
        // One read per call: a replica that floods its pipe gets decoded (and stopped at its
        // first bad or extra frame) before we read more, so memory stays bounded.
        let spare = self.decoder.spare(READ_CHUNK);
        let res = sys::read(self.fd.as_fd(), spare);
        let filled = *res.as_ref().unwrap_or(&0);
        self.decoder.commit(READ_CHUNK, filled);
        match res {
            Ok(0) => {
                self.closed = true;
                Ok(Fill::Closed)
            }
            Ok(_) => Ok(Fill::Open),
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => Ok(Fill::Open),
            Err(e) => Err(e),
        }
    }

    /// Stops reading: the stream is broken beyond repair (bad framing or a read error).
    pub fn close(&mut self) {
        self.closed = true;
        let _ = self.decoder.take_pending();
    }
}

/// A private pipe through which a journaled input peeks its channel (`tee(2)`): the bytes
/// stay in the channel until the voter takes them into its journal (see `journal.rs`).
#[derive(Debug)]
pub struct Peek {
    r: OwnedFd,
    w: OwnedFd,
    cap: usize,
}

impl Peek {
    /// A peek pipe as large as `channel`'s, so that one `tee` copies all it holds.
    pub fn for_channel(channel: BorrowedFd<'_>) -> io::Result<Peek> {
        let (r, w) = sys::pipe()?;
        sys::set_nonblocking(r.as_fd(), true)?;
        sys::set_nonblocking(w.as_fd(), true)?;
        let want = sys::pipe_size(channel)?;
        let cap = sys::set_pipe_size(w.as_fd(), want).or_else(|_| sys::pipe_size(w.as_fd()))?;
        Ok(Peek { r, w, cap })
    }
}

impl FrameReader {
    /// Replaces what was peeked before (keeping the first `keep` undecoded bytes: input
    /// already taken off the channel, being replayed) with a fresh copy of everything the
    /// channel holds, without taking it off the channel.
    pub fn peek_fill(&mut self, peek: &Peek, keep: usize) -> io::Result<Fill> {
        if self.closed {
            return Ok(Fill::Closed);
        }
        let n = match sys::tee(self.fd.as_fd(), peek.w.as_fd(), peek.cap) {
            Ok(0) => {
                self.closed = true;
                return Ok(Fill::Closed);
            }
            Ok(n) => n,
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(Fill::Open),
            Err(e) => return Err(e),
        };
        self.decoder.keep_pending(keep);
        let mut left = n;
        while left > 0 {
            let spare = self.decoder.spare(left);
            let got = sys::read(peek.r.as_fd(), spare)?;
            self.decoder.commit(left, got);
            if got == 0 {
                break;
            }
            left -= got;
        }
        if !self.decoder.has_frame() && self.hung_up()? {
            // A frame cut off by a writer that is gone: it never completes.
            self.closed = true;
            return Ok(Fill::Closed);
        }
        Ok(Fill::Open)
    }

    /// Whether the writer has closed its end (the pipe may still hold bytes).
    fn hung_up(&self) -> io::Result<bool> {
        let mut pfd = [libc::pollfd {
            fd: std::os::fd::AsRawFd::as_raw_fd(&self.fd),
            events: libc::POLLIN,
            revents: 0,
        }];
        sys::ppoll(&mut pfd, Some(std::time::Duration::ZERO))?;
        Ok(pfd[0].revents & libc::POLLHUP != 0)
    }
}

impl AsFd for FrameReader {
    fn as_fd(&self) -> BorrowedFd<'_> {
        self.fd.as_fd()
    }
}

/// Reads whatever a pipe holds right now (used to take back input that a donor replica has not
/// consumed, so that its fork child gets the same). `fd` must be non-blocking.
pub fn drain(fd: BorrowedFd<'_>) -> io::Result<Vec<u8>> {
    let mut out = Vec::new();
    let mut buf = [0u8; 16 * 1024];
    loop {
        match sys::read(fd, &mut buf) {
            Ok(0) => return Ok(out),
            Ok(n) => out.extend_from_slice(&buf[..n]),
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(out),
            Err(e) => return Err(e),
        }
    }
}
