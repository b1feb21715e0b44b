//! Non-blocking ends of pipes, as the voter sees them. The voter never blocks on a replica or a
//! neighbour: what cannot be written now is kept and written when the pipe has room again, and
//! what is read is decoded incrementally.

use std::io;
use std::os::fd::{AsFd, BorrowedFd, OwnedFd};

use replica_rt::frame::{self, FrameDecoder};
use replica_rt::sys;

/// Bytes read per `read(2)` call.
pub(crate) const READ_CHUNK: usize = 64 * 1024;

/// Payloads above this many bytes are written from where they lie ([`FrameWriter::send`]);
/// a smaller one costs less to copy behind its header than a `writev` of two pieces costs
/// the kernel more than a `write` (an 8-byte TMR round was 0.6 µs slower with `writev`).
const DIRECT_FROM: usize = 512;

/// The writing end of a pipe, with the frames that did not fit yet.
#[derive(Debug)]
pub struct FrameWriter {
    fd: OwnedFd,
    /// Writes each frame as a line (`"framing": "lines"`) instead of length-prefixed.
    lines: bool,
    pending: Vec<u8>,
    /// Start of the unwritten part of `pending`.
    start: usize,
    /// Frames go into the pipe whole or not at all (see [`FrameWriter::whole_frames`]).
    whole: Option<Whole>,
    /// An unmodified program's stdin: lines pass through a staging pipe (see
    /// [`FrameWriter::staged`]).
    staging: Option<Staging>,
}

/// The staging pipe of an unmodified program's stdin: each line is written into it with one
/// `write`, and moved on with `splice`, so that a voter's successor can tell a line given
/// from one not written (see "Lines" in `journal.rs`).
#[derive(Debug)]
pub struct Staging {
    r: OwnedFd,
    w: OwnedFd,
    /// Bytes in the staging pipe, not yet moved on.
    held: usize,
    capacity: usize,
    /// The line being staged, kept for its capacity (one `write` takes it whole).
    line: Vec<u8>,
}

impl Staging {
    /// A fresh staging pipe with room for a line of `max_frame` bytes and its newline.
    pub fn new(max_frame: usize) -> io::Result<Staging> {
        let (r, w) = sys::pipe()?;
        Self::adopt(r, w, max_frame)
    }

    /// A staging pipe a predecessor left (with whatever it still holds).
    pub fn adopt(r: OwnedFd, w: OwnedFd, max_frame: usize) -> io::Result<Staging> {
        sys::set_nonblocking(r.as_fd(), true)?;
        sys::set_nonblocking(w.as_fd(), true)?;
        let whole = max_frame + frame::HEADER_LEN;
        let capacity = pipe_room(w.as_fd(), whole, whole)?;
        let held = sys::bytes_in_pipe(r.as_fd())?;
        Ok(Staging {
            r,
            w,
            held,
            capacity,
            line: Vec::new(),
        })
    }

    /// Bytes in it, not yet moved on.
    pub fn held(&self) -> usize {
        self.held
    }

    /// Its two ends (the read end first), for parking beside the program's pipes.
    pub fn ends(&self) -> [BorrowedFd<'_>; 2] {
        [self.r.as_fd(), self.w.as_fd()]
    }
}

/// What a writer of whole frames keeps: where each queued frame ends, and the pipe's room.
///
/// **Room is counted in the pipe's slots, not its bytes.** A pipe holds `capacity / page`
/// buffers of a page each, and a buffer part-filled by one write is filled further by the next
/// only when that write's part beyond whole pages (its first `n % page` bytes) fits in it
/// whole (Linux's `pipe_write`); the rest goes into fresh pages. A pipe of
/// frames a little over a page long is full with far fewer bytes in it than its capacity (64
/// KiB of slots fill with ~10 frames of 5,004 bytes), and a non-blocking write there takes a
/// page and cuts the frame. (Counting bytes, as this writer did, let that happen: found by
/// `a_writer_of_whole_frames_counts_the_room_it_used`.) The bytes of one write of `n` bytes lie
/// in at most `ceil(n / page)` slots, so the writer keeps the sizes of its latest writes: the
/// `held` bytes still in the pipe (`FIONREAD`) are the newest ones written, and lie in at most
/// as many slots as the writes they came from take; bytes older than the writes kept count a
/// slot each. Only the reader frees slots, so the free slots so found, less what the writer
/// takes after, stay a lower bound: it looks again only when they do not cover a frame. The
/// bound is cautious where writes shared a slot (many small frames, or a predecessor's bytes,
/// each counted a slot): a large frame may then wait for a retry (`ROOM_RETRY`) with room
/// for it in the pipe, never be cut.
#[derive(Debug)]
struct Whole {
    /// End offsets in `pending` of the frames queued, in order.
    ends: std::collections::VecDeque<usize>,
    capacity: usize,
    /// The last flush stopped because the next frame did not fit in the pipe's free room.
    waiting_for_room: bool,
    /// The pipe's slots: `capacity` in pages.
    slots: usize,
    /// Slots free at least: what the last look found, less what was written since. While it
    /// covers a frame, no look is needed (a `FIONREAD` per frame larger than `PIPE_BUF`, one
    /// system call in every round of 4 KiB frames, before).
    free_slots_at_least: usize,
    /// Bytes of each of the latest writes, the newest last (at most `slots` of them).
    writes: std::collections::VecDeque<usize>,
}

impl Whole {
    fn new(capacity: usize) -> Whole {
        let slots = capacity / page();
        Whole {
            ends: Default::default(),
            capacity,
            waiting_for_room: false,
            slots,
            free_slots_at_least: 0,
            writes: std::collections::VecDeque::with_capacity(slots),
        }
    }

    /// Whether a frame of `len` bytes may be written into the pipe now. Up to PIPE_BUF a write
    /// is all or nothing anyway, and a frame larger than the pipe can only go in parts; any
    /// other only into room for all of it.
    fn has_room_for(&mut self, fd: BorrowedFd<'_>, len: usize) -> io::Result<bool> {
        let need = len.div_ceil(page());
        if len <= libc::PIPE_BUF || len > self.capacity || self.free_slots_at_least >= need {
            return Ok(true);
        }
        let held = sys::bytes_in_pipe(fd)?;
        self.free_slots_at_least = self.slots.saturating_sub(self.slots_holding(held));
        Ok(self.free_slots_at_least >= need)
    }

    /// At most how many slots the newest `held` bytes written lie in.
    fn slots_holding(&self, held: usize) -> usize {
        let mut left = held;
        let mut slots = 0;
        for &n in self.writes.iter().rev() {
            if left == 0 {
                break;
            }
            slots += n.div_ceil(page());
            left = left.saturating_sub(n);
        }
        slots + left
    }

    /// One write put `n` bytes into the pipe.
    fn wrote(&mut self, n: usize) {
        if n == 0 {
            return;
        }
        self.free_slots_at_least = self.free_slots_at_least.saturating_sub(n.div_ceil(page()));
        if self.writes.len() >= self.slots {
            self.writes.pop_front();
        }
        self.writes.push_back(n);
    }
}

/// The page size: a pipe buffer's.
fn page() -> usize {
    replica_rt::cow::page_size()
}

impl FrameWriter {
    pub fn new(fd: OwnedFd) -> io::Result<Self> {
        sys::set_nonblocking(fd.as_fd(), true)?;
        Ok(FrameWriter {
            fd,
            lines: false,
            pending: Vec::new(),
            start: 0,
            whole: None,
            staging: None,
        })
    }

    /// A writer of lines (`lines`; else s3res frames) into an unmodified program's stdin
    /// through `staging`:
    /// [`send`](Self::send) only writes the line into the staging pipe, and
    /// [`flush`](Self::flush) moves it on; the caller journals in between (see
    /// `Core::deliver_decoded`). Bytes queued raw (a fork child's unread input) go straight
    /// into the pipe, before the staging pipe's.
    pub fn staged(fd: OwnedFd, staging: Staging, lines: bool) -> io::Result<Self> {
        Ok(FrameWriter {
            staging: Some(staging),
            lines,
            ..FrameWriter::new(fd)?
        })
    }

    /// The staging pipe, if this writer has one.
    pub fn staging(&self) -> Option<&Staging> {
        self.staging.as_ref()
    }

    /// A writer that never leaves part of a frame in the pipe: a frame larger than `PIPE_BUF`
    /// (which the kernel may otherwise write in pieces) is written only once the pipe has room
    /// for all of it. A voter whose successor may write on the same pipe needs this: a cut
    /// frame followed by the successor's `RESUME` would be garbage to the reader. The pipe is
    /// made large enough for `max_frame` where the kernel allows.
    ///
    /// Not a pipe (a file, a terminal: bootstrap's own stdout): nothing to do, a write there
    /// is not cut by the reader's pace; `Ok(false)`.
    pub fn write_whole_frames(&mut self, max_frame: usize) -> io::Result<bool> {
        let want = (max_frame + 2 * frame::RESUME_LEN + frame::HEADER_LEN).next_power_of_two();
        let Ok(mut capacity) = sys::pipe_size(self.fd.as_fd()) else {
            return Ok(false);
        };
        if capacity < want {
            capacity = sys::set_pipe_size(self.fd.as_fd(), want).unwrap_or(capacity);
        }
        self.whole = Some(Whole::new(capacity));
        Ok(true)
    }

    /// The last flush left a frame queued because the pipe had no room for all of it: poll
    /// for writability would wake at once (the kernel says writable at `PIPE_BUF` free), so
    /// the caller looks again a little later instead.
    pub fn waiting_for_room(&self) -> bool {
        self.whole.as_ref().is_some_and(|w| w.waiting_for_room)
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

    /// Queues a whole frame and writes as much as the pipe takes now (a staged writer: writes
    /// the line into its staging pipe, whole, and no further).
    pub fn send(&mut self, payload: &[u8]) -> io::Result<()> {
        if let Some(staging) = self.staging.as_mut() {
            return stage_line(staging, payload, self.lines);
        }
        if !self.lines && payload.len() > DIRECT_FROM && !self.has_pending() {
            return self.send_direct(payload);
        }
        self.compact();
        if self.lines {
            self.pending.extend_from_slice(payload);
            self.pending.push(b'\n');
        } else {
            frame::encode_into(payload, &mut self.pending);
        }
        self.frame_queued();
        self.flush()
    }

    /// [`send`](Self::send) with nothing queued before the frame: header and payload go
    /// into the pipe with one `writev`, straight from where the payload lies (no copy into
    /// `pending`, which costs a 4 KiB frame as much as the write itself when the two
    /// buffers alias, see `frame::COPY_ALIGN`). Only what the pipe does not take is queued.
    fn send_direct(&mut self, payload: &[u8]) -> io::Result<()> {
        let header = frame::header(payload.len());
        let total = frame::HEADER_LEN + payload.len();
        let fits = match self.whole.as_mut() {
            Some(whole) => whole.has_room_for(self.fd.as_fd(), total)?,
            None => true,
        };
        let mut failed = None;
        let written = if fits {
            match sys::write2(self.fd.as_fd(), &header, payload) {
                Ok(n) => n,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => 0,
                Err(e) => {
                    failed = Some(e);
                    0
                }
            }
        } else {
            0
        };
        if let Some(whole) = self.whole.as_mut() {
            whole.wrote(written);
        }
        if written == total {
            return Ok(());
        }
        // The rest waits in `pending` for the pipe to have room (`flush`).
        if written < frame::HEADER_LEN {
            self.pending.extend_from_slice(&header[written..]);
            self.pending.extend_from_slice(payload);
        } else {
            self.pending
                .extend_from_slice(&payload[written - frame::HEADER_LEN..]);
        }
        self.frame_queued();
        // As `send` always did: a frame the pipe refused stays queued behind the error.
        if let Some(e) = failed {
            return Err(e);
        }
        match self.whole.as_mut() {
            // A frame larger than the pipe, written in part: the rest goes as a whole frame
            // would, only into room for all of it.
            Some(_) if written > 0 => self.flush_whole(),
            Some(whole) => {
                whole.waiting_for_room = !fits;
                Ok(())
            }
            None => Ok(()),
        }
    }

    /// Queues raw bytes (already framed: whole frames) without writing them yet.
    pub fn queue_raw(&mut self, bytes: &[u8]) {
        self.compact();
        self.pending.extend_from_slice(bytes);
        self.frame_queued();
    }

    fn frame_queued(&mut self) {
        let end = self.pending.len();
        if let Some(whole) = self.whole.as_mut() {
            whole.ends.push_back(end);
        }
    }

    /// Bytes queued and not yet written.
    pub fn unwritten(&self) -> &[u8] {
        &self.pending[self.start..]
    }

    /// How many bytes are not in the pipe yet: queued, or held in the staging pipe.
    pub fn unwritten_len(&self) -> usize {
        self.pending.len() - self.start + self.staging.as_ref().map_or(0, |s| s.held)
    }

    /// Frames queued and not yet written whole, as far as the writer can tell: a writer of
    /// whole frames counts them (control frames too); any other can only say "none" (`Some(0)`)
    /// or "some part of a frame" (`None`).
    pub fn queued_frames(&self) -> Option<usize> {
        match &self.whole {
            Some(whole) => Some(whole.ends.len()),
            None => (!self.has_pending()).then_some(0),
        }
    }

    pub fn has_pending(&self) -> bool {
        self.start < self.pending.len() || self.staging.as_ref().is_some_and(|s| s.held > 0)
    }

    /// Drops everything queued (the reader is gone).
    pub fn discard(&mut self) {
        self.pending.clear();
        self.start = 0;
        if let Some(whole) = self.whole.as_mut() {
            whole.ends.clear();
        }
    }

    /// Writes queued bytes until done or the pipe is full.
    pub fn flush(&mut self) -> io::Result<()> {
        if self.whole.is_some() {
            return self.flush_whole();
        }
        while self.start < self.pending.len() {
            match sys::write(self.fd.as_fd(), &self.pending[self.start..]) {
                Ok(n) => self.start += n,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) => return Err(e),
            }
        }
        if self.start < self.pending.len() {
            return Ok(());
        }
        self.pending.clear();
        self.start = 0;
        if let Some(staging) = self.staging.as_mut() {
            while staging.held > 0 {
                match sys::splice_pipes(staging.r.as_fd(), self.fd.as_fd(), staging.held) {
                    Ok(0) => break,
                    Ok(n) => staging.held -= n.min(staging.held),
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                    Err(e) => return Err(e),
                }
            }
        }
        Ok(())
    }

    /// [`flush`](Self::flush) for a writer of whole frames: frame by frame, each one only
    /// when it fits.
    fn flush_whole(&mut self) -> io::Result<()> {
        let Some(whole) = self.whole.as_mut() else {
            return Ok(());
        };
        whole.waiting_for_room = false;
        while let Some(&end) = whole.ends.front() {
            let frame = &self.pending[self.start..end];
            if !whole.has_room_for(self.fd.as_fd(), frame.len())? {
                whole.waiting_for_room = true;
                break;
            }
            match sys::write(self.fd.as_fd(), frame) {
                Ok(n) => {
                    self.start += n;
                    whole.wrote(n);
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) => return Err(e),
            }
            if self.start >= end {
                whole.ends.pop_front();
            }
        }
        if self.start >= self.pending.len() {
            self.pending.clear();
            self.start = 0;
            whole.ends.clear();
        }
        Ok(())
    }

    fn compact(&mut self) {
        if self.start > 0 {
            self.pending.drain(..self.start);
            if let Some(whole) = self.whole.as_mut() {
                whole.ends.iter_mut().for_each(|e| *e -= self.start);
            }
            self.start = 0;
        }
    }
}

impl AsFd for FrameWriter {
    fn as_fd(&self) -> BorrowedFd<'_> {
        self.fd.as_fd()
    }
}

/// Makes the pipe behind `fd` hold `want` bytes, or at least `need` (a line of an unmodified
/// program and its newline, which must fit whole): its size, or an error that says which limit
/// stands in the way.
pub fn pipe_room(fd: BorrowedFd<'_>, want: usize, need: usize) -> io::Result<usize> {
    let mut capacity = sys::pipe_size(fd)?;
    for size in [want, need] {
        if capacity < size {
            capacity = sys::set_pipe_size(fd, size).unwrap_or(capacity);
        }
    }
    if capacity < need {
        let limit = std::fs::read_to_string("/proc/sys/fs/pipe-max-size").unwrap_or_default();
        return Err(io::Error::other(format!(
            "an unmodified program's line (or frame) of up to the channel's max_frame, with its \
             newline (or header), needs a pipe of {need} bytes, and this system gives {capacity} \
             (/proc/sys/fs/pipe-max-size: {}): lower the channel's max_frame",
            limit.trim()
        )));
    }
    Ok(capacity)
}

/// Writes `payload` as a line (`lines`: with its newline; else as an s3res frame) into an
/// empty staging pipe with one `write`.
fn stage_line(staging: &mut Staging, payload: &[u8], lines: bool) -> io::Result<()> {
    if staging.held > 0 {
        // Only a program that answered without reading its whole line leaves one here.
        return Err(io::Error::other(
            "the program has not read all of its previous line",
        ));
    }
    let mut line = std::mem::take(&mut staging.line);
    line.clear();
    if lines {
        line.extend_from_slice(payload);
        line.push(b'\n');
    } else {
        frame::encode_into(payload, &mut line);
    }
    let len = line.len();
    if len > staging.capacity {
        return Err(io::Error::other(format!(
            "a line of {len} bytes does not fit the staging pipe ({} bytes)",
            staging.capacity
        )));
    }
    // Into an empty pipe with room for all of it, a non-blocking write writes everything.
    let written = sys::write(staging.w.as_fd(), &line);
    staging.line = line;
    let n = written?;
    staging.held = n;
    if n != len {
        return Err(io::Error::other(format!(
            "wrote {n} of a line's {len} bytes into the staging pipe"
        )));
    }
    Ok(())
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
    /// An unmodified program's stdout under a journaled voter: peeked, not read (see
    /// [`FrameReader::peeked_lines`]).
    lines_peek: Option<LinePeek>,
}

/// What a reader that peeks an unmodified program's answers keeps: the lines decoded but
/// still in the pipe, taken off only once their round is committed (see "Lines" in
/// `journal.rs`).
#[derive(Debug)]
struct LinePeek {
    peek: Peek,
    /// The bytes of the lines decoded and not taken off the pipe yet, as they lie at the
    /// pipe's head (each with its newline, or its frame header): what every fresh peek starts
    /// with.
    untaken: Vec<u8>,
    /// Their lengths, oldest first.
    untaken_lens: std::collections::VecDeque<usize>,
    /// Newline-delimited (else s3res frames).
    lines: bool,
    /// Bytes the pipe held at the last peek: while it holds as many, nothing came (a replica
    /// stopped in the middle of a large line is looked at with one `ioctl`, not a copy).
    seen: usize,
    buf: Vec<u8>,
}

impl LinePeek {
    /// `answer` was decoded: it lies at the pipe's head, untaken, behind the ones before it.
    fn decoded(&mut self, answer: &[u8]) {
        let before = self.untaken.len();
        if self.lines {
            self.untaken.extend_from_slice(answer);
            self.untaken.push(b'\n');
        } else {
            frame::encode_into(answer, &mut self.untaken);
        }
        self.untaken_lens.push_back(self.untaken.len() - before);
    }
}

impl FrameReader {
    pub fn new(fd: OwnedFd, max_frame: usize) -> io::Result<Self> {
        sys::set_nonblocking(fd.as_fd(), true)?;
        Ok(FrameReader {
            fd,
            decoder: FrameDecoder::new(max_frame),
            closed: false,
            lines_peek: None,
        })
    }

    /// A reader of an unmodified program's stdout that leaves the answers in the pipe until
    /// they are taken ([`front_line`](Self::front_line)): each fill peeks the pipe afresh
    /// (`tee`) past the lines already decoded. Its answers are decoded with
    /// [`next_answer`](Self::next_answer), which keeps count of them.
    pub fn peeked_lines(fd: OwnedFd, max_frame: usize, lines: bool) -> io::Result<Self> {
        let mut reader = if lines {
            FrameReader::lines(fd, max_frame)?
        } else {
            FrameReader::new(fd, max_frame)?
        };
        let mut peek = Peek::for_channel(reader.fd.as_fd())?;
        // A whole answer must fit in one look.
        let whole = max_frame + frame::HEADER_LEN;
        peek.cap = pipe_room(peek.w.as_fd(), peek.cap.max(whole), whole)?;
        reader.lines_peek = Some(LinePeek {
            peek,
            untaken: Vec::new(),
            untaken_lens: Default::default(),
            lines,
            seen: 0,
            buf: Vec::new(),
        });
        Ok(reader)
    }

    /// The next whole frame (line) decoded, if one has arrived. A peeking reader also counts
    /// it as decoded and not taken: it stays in the pipe until taken.
    pub fn next_answer(&mut self) -> Result<Option<&[u8]>, replica_rt::frame::FrameError> {
        let Some(answer) = self.decoder.next_frame()? else {
            return Ok(None);
        };
        if let Some(lp) = self.lines_peek.as_mut() {
            lp.decoded(answer);
        }
        Ok(Some(answer))
    }

    /// [`next_answer`](Self::next_answer), handed over into `into` without a copy where it
    /// can be (see [`FrameDecoder::next_frame_into`]); the answer lies at the range returned.
    pub fn next_answer_into(
        &mut self,
        into: &mut Vec<u8>,
    ) -> Result<Option<std::ops::Range<usize>>, replica_rt::frame::FrameError> {
        let Some(at) = self.decoder.next_frame_into(into)? else {
            return Ok(None);
        };
        if let Some(lp) = self.lines_peek.as_mut() {
            lp.decoded(&into[at.clone()]);
        }
        Ok(Some(at))
    }

    /// A peeking reader: the oldest line decoded and not taken yet, as it lies in the pipe.
    pub fn front_line(&self) -> Option<&[u8]> {
        let lp = self.lines_peek.as_ref()?;
        lp.untaken_lens.front().map(|&n| &lp.untaken[..n])
    }

    /// A peeking reader: the oldest line decoded is off the pipe now.
    pub fn took_front_line(&mut self) {
        if let Some(lp) = self.lines_peek.as_mut() {
            if let Some(n) = lp.untaken_lens.pop_front() {
                lp.untaken.drain(..n);
                lp.seen = lp.seen.saturating_sub(n);
            }
        }
    }

    /// A peeking reader: how many lines it decoded that are not taken yet.
    pub fn untaken_lines(&self) -> usize {
        self.lines_peek
            .as_ref()
            .map_or(0, |lp| lp.untaken_lens.len())
    }

    /// Whether this reader peeks (an unmodified program's stdout under a journaled voter).
    pub fn peeks(&self) -> bool {
        self.lines_peek.is_some()
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

    /// Bytes the replica wrote that the voter has not read off the pipe yet (`FIONREAD`);
    /// `None` where the kernel does not say. A peeking reader leaves the answers it decoded in
    /// the pipe until they are taken: those are not counted.
    pub fn unread(&self) -> Option<usize> {
        let held = sys::bytes_in_pipe(self.fd.as_fd()).ok()?;
        let decoded = self.lines_peek.as_ref().map_or(0, |lp| lp.untaken.len());
        Some(held.saturating_sub(decoded))
    }

    /// Reads everything available now into the decoder.
    pub fn fill(&mut self) -> io::Result<Fill> {
        if self.closed {
            return Ok(Fill::Closed);
        }
        if self.lines_peek.is_some() {
            return self.fill_peeked_lines();
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
        let n = match self.tee_all(peek)? {
            Some(0) => return Ok(Fill::Open),
            Some(n) => n,
            None => return Ok(Fill::Closed),
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

    /// [`fill`](Self::fill) of a reader that peeks lines: everything in the pipe past the
    /// lines decoded and not taken replaces what was peeked before.
    fn fill_peeked_lines(&mut self) -> io::Result<Fill> {
        let Some(mut lp) = self.lines_peek.take() else {
            return Ok(Fill::Open);
        };
        let filled = self.fill_past_untaken(&mut lp);
        self.lines_peek = Some(lp);
        filled
    }

    fn fill_past_untaken(&mut self, lp: &mut LinePeek) -> io::Result<Fill> {
        if lp.seen > 0 && sys::bytes_in_pipe(self.fd.as_fd())? == lp.seen {
            return Ok(Fill::Open);
        }
        let n = match self.tee_all(&lp.peek)? {
            Some(0) => return Ok(Fill::Open),
            Some(n) => n,
            None => return Ok(Fill::Closed),
        };
        lp.buf.resize(n, 0);
        let mut got = 0;
        while got < n {
            match sys::read(lp.peek.r.as_fd(), &mut lp.buf[got..]) {
                Ok(0) => break,
                Ok(k) => got += k,
                Err(e) => return Err(e),
            }
        }
        let untaken = lp.untaken.len();
        if got < untaken {
            return Err(io::Error::other(format!(
                "the pipe holds {got} bytes, less than the {untaken} of its answers not taken"
            )));
        }
        lp.seen = got;
        self.decoder.keep_pending(0);
        self.decoder.push(&lp.buf[untaken..got]);
        if !self.decoder.has_frame() && got == untaken && self.hung_up()? {
            // Nothing new, and the writer is gone: the lines decoded are all there is.
            self.closed = true;
            return Ok(Fill::Closed);
        }
        Ok(Fill::Open)
    }

    /// Copies everything the pipe holds into `peek` without taking it off: how many bytes
    /// (`Some(0)`: none now), or `None` at the end (empty, and its writer gone: the reader is
    /// closed).
    fn tee_all(&mut self, peek: &Peek) -> io::Result<Option<usize>> {
        match sys::tee(self.fd.as_fd(), peek.w.as_fd(), peek.cap) {
            Ok(0) => {
                self.closed = true;
                Ok(None)
            }
            Ok(n) => Ok(Some(n)),
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => Ok(Some(0)),
            Err(e) => Err(e),
        }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Reads whatever a pipe holds right now. `fd` must be non-blocking.
    fn drain(fd: BorrowedFd<'_>) -> io::Result<Vec<u8>> {
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

    /// A frame larger than PIPE_BUF waits until the pipe has room for all of it, so a reader
    /// never holds part of one when its writer dies; smaller frames go as usual.
    #[test]
    fn a_writer_of_whole_frames_never_leaves_part_of_one_in_the_pipe() {
        let (r, w) = sys::pipe().unwrap();
        sys::set_nonblocking(r.as_fd(), true).unwrap();
        let mut writer = FrameWriter::new(w).unwrap();
        writer.write_whole_frames(16 * 1024).unwrap();
        let capacity = sys::pipe_size(writer.as_fd()).unwrap();
        // Fill the pipe but for 6000 bytes.
        let filler = vec![0u8; capacity - 6000 - frame::HEADER_LEN];
        writer.send(&filler).unwrap();
        assert!(!writer.has_pending());
        let big = vec![7u8; 10_000];
        writer.send(&big).unwrap();
        assert!(writer.has_pending(), "written in part");
        assert!(writer.waiting_for_room());
        assert_eq!(sys::bytes_in_pipe(r.as_fd()).unwrap(), capacity - 6000);
        // A small frame queued behind it waits its turn.
        writer.send(b"small").unwrap();
        let drained = drain(r.as_fd()).unwrap();
        assert_eq!(drained.len(), filler.len() + frame::HEADER_LEN);
        writer.flush().unwrap();
        assert!(!writer.has_pending());
        assert!(!writer.waiting_for_room());
        let mut dec = FrameDecoder::new(16 * 1024);
        dec.push(&drain(r.as_fd()).unwrap());
        assert_eq!(dec.next_frame().unwrap(), Some(&big[..]));
        assert_eq!(dec.next_frame().unwrap(), Some(&b"small"[..]));
    }

    /// Frames larger than PIPE_BUF, one after another into a pipe nobody reads: each goes in
    /// whole while the room it knows of (looked at once, less what it wrote since) covers it,
    /// and the one that would be cut waits; once the reader makes room, the rest follow.
    #[test]
    fn a_writer_of_whole_frames_counts_the_room_it_used() {
        let (r, w) = sys::pipe().unwrap();
        sys::set_nonblocking(r.as_fd(), true).unwrap();
        let mut writer = FrameWriter::new(w).unwrap();
        // A little over a page (5,004 bytes with 4 KiB pages): two slots at most each.
        let payload = page() + 904;
        writer.write_whole_frames(payload).unwrap();
        let capacity = sys::pipe_size(writer.as_fd()).unwrap();
        let whole = payload + frame::HEADER_LEN;
        let fit = capacity / page() / 2;
        if fit < 4 {
            eprintln!("a pipe of {capacity} bytes holds too few such frames to tell; skipped");
            return;
        }
        let frames: Vec<Vec<u8>> = (0..fit + 5).map(|k| vec![k as u8; payload]).collect();
        for (k, f) in frames.iter().enumerate() {
            writer.send(f).unwrap();
            let held = sys::bytes_in_pipe(r.as_fd()).unwrap();
            assert_eq!(
                held % whole,
                0,
                "frame {k}: {held} bytes in the pipe, a frame cut"
            );
        }
        assert!(writer.waiting_for_room(), "more frames than the pipe holds");
        assert_eq!(sys::bytes_in_pipe(r.as_fd()).unwrap(), fit * whole);
        // The reader takes three frames: the slots they held are counted free again, and as
        // many frames follow, whole.
        let mut got = vec![0u8; 3 * whole];
        assert_eq!(sys::read(r.as_fd(), &mut got).unwrap(), 3 * whole);
        writer.flush().unwrap();
        assert!(writer.waiting_for_room());
        assert_eq!(sys::bytes_in_pipe(r.as_fd()).unwrap(), fit * whole);
        got.extend(drain(r.as_fd()).unwrap());
        writer.flush().unwrap();
        assert!(!writer.has_pending());
        got.extend(drain(r.as_fd()).unwrap());
        let mut dec = FrameDecoder::new(payload);
        dec.push(&got);
        for f in &frames {
            assert_eq!(dec.next_frame().unwrap(), Some(&f[..]));
        }
        assert_eq!(dec.next_frame().unwrap(), None);
    }

    /// A large frame goes into the pipe straight from the caller's payload; what the pipe
    /// has no room for waits in the writer, behind the part written, and the reader gets the
    /// frame whole once it is flushed.
    #[test]
    fn a_frame_written_in_part_is_finished_by_a_flush() {
        let (r, w) = sys::pipe().unwrap();
        sys::set_nonblocking(r.as_fd(), true).unwrap();
        let mut writer = FrameWriter::new(w).unwrap();
        let capacity = sys::pipe_size(writer.as_fd()).unwrap();
        let big: Vec<u8> = (0..capacity + 3000).map(|i| (i % 251) as u8).collect();
        writer.send(&big).unwrap();
        assert!(writer.has_pending(), "the pipe cannot hold all of it");
        assert_eq!(
            writer.unwritten_len(),
            big.len() + frame::HEADER_LEN - capacity
        );
        writer.send(&[9; 600]).unwrap();
        let mut got = drain(r.as_fd()).unwrap();
        writer.flush().unwrap();
        assert!(!writer.has_pending());
        got.extend(drain(r.as_fd()).unwrap());
        let mut dec = FrameDecoder::new(capacity + 3000);
        dec.push(&got);
        assert_eq!(dec.next_frame().unwrap(), Some(&big[..]));
        assert_eq!(dec.next_frame().unwrap(), Some(&[9; 600][..]));
        assert_eq!(dec.next_frame().unwrap(), None);
    }

    /// A staged writer puts the line into its staging pipe only; a flush moves it on, as far
    /// as the program's pipe takes it, and the rest waits in the staging pipe.
    #[test]
    fn a_staged_line_waits_in_its_staging_pipe_until_flushed() {
        let (r, w) = sys::pipe().unwrap();
        sys::set_nonblocking(r.as_fd(), true).unwrap();
        let mut writer = FrameWriter::staged(w, Staging::new(100_000).unwrap(), true).unwrap();
        writer.send(b"abc").unwrap();
        assert!(writer.has_pending());
        assert_eq!(writer.unwritten_len(), 4);
        assert_eq!(drain(r.as_fd()).unwrap(), b"");
        writer.flush().unwrap();
        assert!(!writer.has_pending());
        assert_eq!(drain(r.as_fd()).unwrap(), b"abc\n");
        // A line larger than the room left: part moves, the rest stays staged.
        let capacity = sys::pipe_size(writer.as_fd()).unwrap();
        let big = vec![b'x'; capacity + 1000];
        writer.send(&big).unwrap();
        writer.flush().unwrap();
        assert!(writer.has_pending(), "the pipe cannot hold all of it");
        assert!(writer.send(b"next").is_err(), "one line at a time");
        let mut got = drain(r.as_fd()).unwrap();
        writer.flush().unwrap();
        got.extend(drain(r.as_fd()).unwrap());
        assert!(!writer.has_pending());
        assert_eq!(got.len(), big.len() + 1);
    }

    /// A peeking reader leaves the answers in the pipe: each fill decodes only what came after
    /// the lines it decoded, until they are taken off.
    #[test]
    fn a_peeking_reader_decodes_each_line_once_and_leaves_it_in_the_pipe() {
        let (r, w) = sys::pipe().unwrap();
        let probe = r.try_clone().unwrap();
        let mut reader = FrameReader::peeked_lines(r, 64, true).unwrap();
        sys::write(w.as_fd(), b"1\n2\n3").unwrap();
        assert_eq!(reader.fill().unwrap(), Fill::Open);
        let mut seen = Vec::new();
        while let Some(line) = reader.next_answer().unwrap() {
            seen.push(line.to_vec());
        }
        assert_eq!(seen, vec![b"1".to_vec(), b"2".to_vec()]);
        assert_eq!(
            sys::bytes_in_pipe(probe.as_fd()).unwrap(),
            5,
            "nothing taken"
        );
        sys::write(w.as_fd(), b"\n").unwrap();
        reader.fill().unwrap();
        assert_eq!(reader.next_answer().unwrap(), Some(&b"3"[..]));
        assert_eq!(reader.next_answer().unwrap(), None);
        assert_eq!(reader.front_line(), Some(&b"1\n"[..]));
        // Taken off (as the journal does it), the next fill still decodes nothing twice.
        let mut two = [0u8; 2];
        assert_eq!(sys::read(probe.as_fd(), &mut two).unwrap(), 2);
        reader.took_front_line();
        assert_eq!(reader.untaken_lines(), 2);
        reader.fill().unwrap();
        assert_eq!(reader.next_answer().unwrap(), None);
        drop(w);
        let mut rest = [0u8; 4];
        assert_eq!(sys::read(probe.as_fd(), &mut rest).unwrap(), 4);
        reader.took_front_line();
        reader.took_front_line();
        assert_eq!(
            reader.fill().unwrap(),
            Fill::Closed,
            "empty, and its writer gone"
        );
    }
}
