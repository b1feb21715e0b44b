//! Named ports: whole frames in, whole frames out.

use std::io;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, OwnedFd, RawFd};
use std::sync::{Arc, Mutex, PoisonError};

use thiserror::Error;

use crate::answers::{self, LastFrame};
use crate::contract::FIRST_PORT_FD;
use crate::frame::{self, FrameBuf, FrameDecoder, FrameError};
use crate::{history, inject, rebind, restart, sys};

/// The most one `read` asks for. A read asks for the room the buffer already has (at least
/// [`SMALL_BUFFER`]), and for more only when the frame at its head needs it: a burst of small
/// frames larger than that room takes more than one read.
const READ_CHUNK: usize = 64 * 1024;
/// What a read reserves room for unless the frame being read needs more: buffers grow to the
/// largest frame actually seen, not to the port's maximum (an output's copy of its frame, a
/// `FrameBuf`, too). In a replica every byte of them is locked and resident, and copied at each fork
/// recovery (see `memory`). Small: a frame buffer also carries a page of slack to place its
/// frame ([`frame::FRAME_SLACK`]), so 512 bytes keep a small frame's buffer within two pages.
/// 8 KiB until stop 50: a 4 KiB ballast replica then had 10 pages of allocator memory to copy
/// at each restart, 6 with 512 bytes, and detection → ready took 0.941 (0.925–0.972) as long;
/// round trips did not change (a buffer grows once, at the first larger frame).
const SMALL_BUFFER: usize = 512;

/// Receiving a frame failed.
#[derive(Debug, Error)]
pub enum RecvError {
    /// The bytes on the channel are not a valid frame stream.
    #[error("input port {port:?}: bad frame stream")]
    Frame {
        port: String,
        #[source]
        source: FrameError,
    },
    #[error("input port {port:?}: read failed")]
    Io {
        port: String,
        #[source]
        source: io::Error,
    },
    /// A voter's successor went on from a frame beyond the last one this replica took: input
    /// it had been given was lost with the voter that died (no known path loses it since fork
    /// recoveries stopped draining a donor's pipes, but a replica must not run on if one
    /// does). Its state is no longer the component's; the component should end, and its voter
    /// rebuilds it from a sibling.
    #[error("input port {port:?}: {frames} input frame(s) were lost with a voter that died; this replica's state is no longer the component's")]
    InputLost { port: String, frames: u64 },
}

/// Sending a frame failed.
#[derive(Debug, Error)]
pub enum SendError {
    #[error("output port {port:?}: payload of {len} bytes exceeds the port maximum of {max}")]
    TooLarge {
        port: String,
        len: usize,
        max: usize,
    },
    #[error("output port {port:?}: write failed")]
    Io {
        port: String,
        #[source]
        source: io::Error,
    },
}

/// An input port. Blocking; see [`InPort::recv`].
///
/// Implements [`AsFd`], so a component with several inputs can `poll` them and call `recv` on
/// the readable one. Note that `recv` reads ahead: after it returns, more whole frames may already
/// be buffered inside the port although the fd polls as not readable; drain with
/// [`InPort::buffered`] in mind.
#[derive(Debug)]
pub struct InPort {
    name: String,
    pub(crate) fd: OwnedFd,
    pub(crate) dec: FrameDecoder,
    /// Where the payload last returned by `recv` lies: handed over by the decoder (see
    /// [`FrameDecoder::next_frame_into`]), in `frame` at `at`.
    pub(crate) frame: Vec<u8>,
    pub(crate) at: std::ops::Range<usize>,
    pub(crate) eof: bool,
    /// The step (see `answers`) at which the last frame was taken.
    pub(crate) taken_at: u64,
    /// Under a voter (replica mode): an end of input without an `END` frame is the voter's
    /// death, and the port rebinds to its successor (see `rebind`).
    replica: bool,
    /// Position in the port map (fd − 3).
    position: Option<usize>,
    /// The rebinds this port has caught up with (see `rebind::generation`).
    generation: u64,
}

impl InPort {
    pub(crate) fn new(name: String, fd: OwnedFd, max_frame: usize, replica: bool) -> Self {
        let position = usize::try_from(fd.as_raw_fd() - FIRST_PORT_FD).ok();
        if replica {
            if let Some(p) = position {
                rebind::register_input(p);
            }
        }
        InPort {
            name,
            fd,
            // A voter restarted mid-round replays it behind a resume frame (see `answers`).
            dec: FrameDecoder::resuming(max_frame),
            frame: Vec::new(),
            at: 0..0,
            eof: false,
            taken_at: 0,
            replica,
            position,
            generation: rebind::generation(),
        }
    }

    /// A rebind happened that this port has not caught up with.
    pub(crate) fn behind_a_rebind(&self) -> bool {
        self.generation != rebind::generation()
    }

    /// After a rebind (this port's or another's): the whole frames left in the old pipe come
    /// first, a frame the dead voter cut off is dropped, and the port reads its new pipe.
    pub(crate) fn catch_up(&mut self) {
        let now = rebind::generation();
        if self.generation == now {
            return;
        }
        self.generation = now;
        if let Some(p) = self.position {
            self.dec.push(&rebind::take_left_over(p));
        }
        let cut = self.dec.discard_partial();
        if cut > 0 {
            tracing::debug!(port = %self.name, bytes = cut, "dropped a frame the old voter cut off");
        }
        self.eof = false;
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn max_frame(&self) -> usize {
        self.dec.max_frame()
    }

    /// Bytes read from the channel but not yet returned as frames.
    pub fn buffered(&self) -> usize {
        self.dec.pending()
    }

    /// The next frame's payload, blocking until it has arrived whole. `Ok(None)` at end of
    /// stream; an error for a frame above the port maximum or a stream cut inside a frame.
    ///
    /// The payload is handed over from the read buffer without a copy where it is the last
    /// byte read (the two buffers trade places, see [`FrameDecoder::next_frame_into`]), so
    /// steady state allocates nothing; the hand-over is what lets the borrow returned here
    /// outlive the decoder's own, which the read loop needs to mutate.
    pub fn recv(&mut self) -> Result<Option<&[u8]>, RecvError> {
        note_fork();
        // Before waiting for input: the round before has been answered.
        restart::between_rounds();
        self.catch_up();
        loop {
            if self.next_buffered()? {
                return Ok(Some(&self.frame[self.at.clone()]));
            }
            if self.eof || !self.fill()? {
                self.eof = true;
                return match self.dec.finish() {
                    Ok(()) => Ok(None),
                    Err(e) => Err(self.frame_error(e)),
                };
            }
        }
    }

    /// Moves the next whole frame from the decoder into `self.frame`; `false` if none is
    /// buffered. A replayed round (its input frame repeated) is answered again on the way.
    pub(crate) fn next_buffered(&mut self) -> Result<bool, RecvError> {
        // A replica started by exec is first told the number of its first frame (a jump from
        // nothing taken); a jump from anything else is input lost.
        let had = self.dec.taken();
        let taken = match self.dec.next_frame_into(&mut self.frame) {
            Ok(Some(at)) => {
                self.at = at;
                true
            }
            Ok(None) => false,
            Err(e) => return Err(self.frame_error(e)),
        };
        let skipped = self.dec.take_skipped();
        if self.replica && skipped > 0 && had > 0 {
            return Err(RecvError::InputLost {
                port: self.name.clone(),
                frames: skipped,
            });
        }
        if self.dec.take_repeats_of_last() > 0 {
            // Before the next frame is taken: the answers to the replayed one are the frames
            // sent after it. A failed write is the voter's end closing, which the next read
            // reports as the end of the stream.
            if let Err(e) = answers::answer_again(self.taken_at) {
                tracing::warn!(port = %self.name, error = %e, "could not answer a replayed round again");
            }
        }
        if taken {
            self.taken_at = answers::step();
            if let Some(p) = self.position.filter(|_| self.replica) {
                rebind::count_taken(p, self.dec.taken());
            }
        }
        Ok(taken)
    }

    /// One `read` into the decoder; `false` at end of stream (a voter's death is not one: the
    /// port rebinds to its successor and reads on).
    pub(crate) fn fill(&mut self) -> Result<bool, RecvError> {
        self.catch_up();
        loop {
            // All the room the buffer has already (it only grows), and more only for a frame
            // that needs it.
            let want = self
                .dec
                .missing()
                .max(self.dec.room())
                .clamp(SMALL_BUFFER, READ_CHUNK);
            let spare = self.dec.spare(want);
            let got = sys::read(self.fd.as_fd(), spare);
            let filled = *got.as_ref().unwrap_or(&0);
            self.dec.commit(want, filled);
            match got {
                Ok(0) if self.replica && !self.dec.ended() => {
                    if rebind::rebind().is_err() {
                        tracing::info!(port = %self.name, "voter gone and no successor took this replica: ending");
                        // Its cut frame is no error of the stream's: the writer died.
                        self.dec.discard_partial();
                        return Ok(false);
                    }
                    self.catch_up();
                    // Whole frames may have come out of the old pipe.
                    return Ok(true);
                }
                Ok(n) => return Ok(n > 0),
                // Whoever made the pipe may have left it non-blocking; recv blocks regardless.
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    wait_for(self.fd.as_fd(), libc::POLLIN).map_err(|e| self.io_error(e))?
                }
                Err(e) => return Err(self.io_error(e)),
            }
        }
    }

    pub(crate) fn io_error(&self, source: io::Error) -> RecvError {
        RecvError::Io {
            port: self.name.clone(),
            source,
        }
    }

    pub(crate) fn frame_error(&self, source: FrameError) -> RecvError {
        RecvError::Frame {
            port: self.name.clone(),
            source,
        }
    }
}

impl AsFd for InPort {
    fn as_fd(&self) -> BorrowedFd<'_> {
        self.fd.as_fd()
    }
}

impl AsRawFd for InPort {
    fn as_raw_fd(&self) -> RawFd {
        self.fd.as_raw_fd()
    }
}

/// An output port. Dropping it closes the channel, which ends the stream downstream.
#[derive(Debug)]
pub struct OutPort {
    name: String,
    fd: OwnedFd,
    max: usize,
    /// Header and payload of the frame being sent, reused from frame to frame; after a send,
    /// the frame a replayed round is answered with again (see `answers`).
    last: Arc<Mutex<LastFrame>>,
    /// In replica mode a RESTART must not fork in the middle of a frame (see `restart`): it is
    /// deferred to the end of the frame.
    replica: bool,
    /// Position in the port map (fd − 3), under which whole frames sent are counted for the
    /// restart handshake; `None` off the replica fd layout (standalone stdout).
    position: Option<usize>,
    /// The rebinds this port has caught up with: after one, the next frame goes behind
    /// `RESUME n` (see `rebind`).
    generation: u64,
}

impl OutPort {
    pub(crate) fn new(name: String, fd: OwnedFd, max: usize, replica: bool) -> Self {
        let last = Arc::new(Mutex::new(LastFrame {
            bytes: FrameBuf::default(),
            history: if replica {
                history::for_new_port()
            } else {
                None
            },
            ..LastFrame::default()
        }));
        if replica {
            answers::register(fd.as_raw_fd(), &last);
        }
        OutPort {
            name,
            max,
            last,
            replica,
            position: usize::try_from(fd.as_raw_fd() - FIRST_PORT_FD).ok(),
            fd,
            generation: rebind::generation(),
        }
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn max_frame(&self) -> usize {
        self.max
    }

    /// Sends `payload` as one whole frame (header and payload), blocking until all of it is
    /// written. A pending SDC injection flips one bit of the copy that is sent.
    pub fn send(&mut self, payload: &[u8]) -> Result<(), SendError> {
        note_fork();
        if payload.len() > self.max {
            return Err(SendError::TooLarge {
                port: self.name.clone(),
                len: payload.len(),
                max: self.max,
            });
        }
        let mut last = self.last.lock().unwrap_or_else(PoisonError::into_inner);
        last.bytes.encode(payload);
        inject::apply_pending(&self.name, last.bytes.payload_mut());
        // A RESTART from here until the guard drops forks at the drop, once the frame is whole
        // and counted (no system call: see `restart`, "Output frames stay whole").
        let _deferred = self.replica.then(restart::RestartsHeld::new);
        let replica = self.replica;
        let fd = self.fd.as_fd();
        let mut written = write_frame(
            fd,
            replica,
            &mut self.generation,
            last.bytes.as_slice(),
            last.sent,
        );
        // The voter died with our frame half-written, or before it: its successor gets all of
        // it, on the new pipe, behind `RESUME` (a stream replica's history first: the rebind
        // sent every other port's, but this one's is locked here). The successor may die in
        // turn before the frame is through: then the next one, until no successor comes.
        while self.replica && matches!(&written, Err(e) if e.kind() == io::ErrorKind::BrokenPipe) {
            if rebind::rebind().is_err() {
                break;
            }
            written = match last.history.as_ref().map(|h| h.resend(fd)) {
                Some(Err(e)) => Err(e),
                _ => write_frame(
                    fd,
                    replica,
                    &mut self.generation,
                    last.bytes.as_slice(),
                    last.sent,
                ),
            };
        }
        if let Err(e) = written {
            drop(last);
            return Err(self.io_error(e));
        }
        // Still deferred: a fork sees the count and the pipe agree.
        if let Some(position) = self.position {
            restart::count_sent(position);
        }
        // When this answer went out, for a voter that did not wake for it (`stamps`).
        crate::stamps::answered();
        let last = &mut *last;
        if let Some(history) = last.history.as_mut() {
            history.record(last.sent, last.bytes.as_slice());
        }
        last.sent += 1;
        last.step = answers::step();
        Ok(())
    }

    /// Writes `bytes` as they are, not as a frame. Only for test aids that must produce broken
    /// channels on purpose (a bad header, a cut frame); components use [`OutPort::send`].
    pub fn write_raw(&mut self, bytes: &[u8]) -> Result<(), SendError> {
        write_all(self.fd.as_fd(), bytes).map_err(|e| self.io_error(e))
    }

    fn io_error(&self, source: io::Error) -> SendError {
        SendError::Io {
            port: self.name.clone(),
            source,
        }
    }
}

impl AsFd for OutPort {
    fn as_fd(&self) -> BorrowedFd<'_> {
        self.fd.as_fd()
    }
}

impl AsRawFd for OutPort {
    fn as_raw_fd(&self) -> RawFd {
        self.fd.as_raw_fd()
    }
}

/// Writes a whole frame (`bytes`, header included), numbered `number` on its port: after a
/// rebind the port has not caught up with (`generation`), behind `RESUME number`, in the same
/// write.
fn write_frame(
    fd: BorrowedFd<'_>,
    replica: bool,
    generation: &mut u64,
    bytes: &[u8],
    number: u64,
) -> io::Result<()> {
    let now = rebind::generation();
    if !replica || *generation == now {
        return write_all(fd, bytes);
    }
    let mut resumed = Vec::with_capacity(frame::RESUME_LEN + bytes.len());
    resumed.extend_from_slice(&frame::resume_frame(number));
    resumed.extend_from_slice(bytes);
    write_all(fd, &resumed)?;
    *generation = now;
    Ok(())
}

/// Writes all of `bytes`, looping on partial writes (EINTR is retried inside `sys::write`).
pub(crate) fn write_all(fd: BorrowedFd<'_>, mut bytes: &[u8]) -> io::Result<()> {
    while !bytes.is_empty() {
        match sys::write(fd, bytes) {
            Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
            Ok(n) => bytes = &bytes[n..],
            // A non-blocking pipe (not ours to change): wait for room, as a blocking one would.
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => wait_for(fd, libc::POLLOUT)?,
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

/// Blocks until `fd` is ready for `events` (or hung up / in error, which the next read or
/// write then reports).
fn wait_for(fd: BorrowedFd<'_>, events: libc::c_short) -> io::Result<()> {
    let mut pfd = [libc::pollfd {
        fd: fd.as_raw_fd(),
        events,
        revents: 0,
    }];
    while sys::ppoll(&mut pfd, None)? == 0 {}
    Ok(())
}

/// Logs, once, that this process is a replica forked by the restart handler (which may not
/// log itself).
fn note_fork() {
    if let Some(donor) = restart::take_forked_from() {
        // Debug: the voter's recovery event says it, with the slot (this child still carries
        // its donor's slot in its log prefix).
        tracing::debug!(
            donor,
            pid = std::process::id(),
            "restarted: forked from donor, rejoined the voter"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn ports(max: usize) -> (InPort, OutPort) {
        let (r, w) = sys::pipe().unwrap();
        sys::set_nonblocking(r.as_fd(), true).unwrap();
        sys::set_nonblocking(w.as_fd(), true).unwrap();
        (
            InPort::new("in".into(), r, max, false),
            OutPort::new("out".into(), w, max, false),
        )
    }

    /// Non-blocking pipes behave like blocking ones: recv waits, send writes whole frames
    /// larger than a pipe holds.
    #[test]
    fn nonblocking_pipes_still_move_whole_frames() {
        let (mut input, mut output) = ports(300_000);
        let big: Vec<u8> = (0..200_000u32).map(|i| i as u8).collect();
        let expected = big.clone();
        let writer = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(50));
            output.send(b"first").unwrap();
            output.send(&big).unwrap();
            output.send(b"").unwrap();
        });
        assert_eq!(input.recv().unwrap(), Some(&b"first"[..]));
        assert_eq!(input.recv().unwrap(), Some(&expected[..]));
        assert_eq!(input.recv().unwrap(), Some(&b""[..]));
        writer.join().unwrap();
        assert_eq!(input.recv().unwrap(), None);
        assert_eq!(input.recv().unwrap(), None);
    }

    /// A replica told to go on from a frame beyond the last one it took lost input with a
    /// dead voter: an error, not a silent jump. A replica that took nothing yet is only being
    /// told where the numbering starts.
    #[test]
    fn a_replica_that_lost_input_says_so() {
        let (r, w) = sys::pipe().unwrap();
        let mut input = InPort::new("in".into(), r, 64, true);
        let mut bytes = crate::frame::resume_frame(7).to_vec();
        frame::encode_into(b"a", &mut bytes);
        frame::encode_into(b"b", &mut bytes);
        bytes.extend_from_slice(&crate::frame::resume_frame(12));
        frame::encode_into(b"m", &mut bytes);
        write_all(w.as_fd(), &bytes).unwrap();
        assert_eq!(input.recv().unwrap(), Some(&b"a"[..]));
        assert_eq!(input.recv().unwrap(), Some(&b"b"[..]));
        match input.recv() {
            Err(RecvError::InputLost { frames, .. }) => assert_eq!(frames, 3),
            other => panic!("expected InputLost, got {other:?}"),
        }
    }

    #[test]
    fn send_refuses_oversized_payloads_and_recv_reports_bad_streams() {
        let (mut input, mut output) = ports(8);
        let err = output.send(&[0; 9]).unwrap_err();
        assert!(
            matches!(err, SendError::TooLarge { len: 9, max: 8, .. }),
            "{err}"
        );
        output.write_raw(&frame::header(100)).unwrap();
        let err = input.recv().unwrap_err();
        assert!(
            matches!(
                err,
                RecvError::Frame {
                    source: FrameError::Oversized { len: 100, max: 8 },
                    ..
                }
            ),
            "{err}"
        );
        let (mut input, mut output) = ports(8);
        output.write_raw(&[3, 0, 0, 0, 1]).unwrap();
        drop(output);
        let err = input.recv().unwrap_err();
        assert!(
            matches!(
                err,
                RecvError::Frame {
                    source: FrameError::Truncated { .. },
                    ..
                }
            ),
            "{err}"
        );
    }
}
