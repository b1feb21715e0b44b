//! Frames: the unit of everything that crosses a channel, and the unit of voting.
//!
//! A frame is a 4-byte little-endian length followed by that many bytes. Each channel has a
//! maximum frame size; a length above it is a protocol error, never an allocation.
//!
//! A length word with its top bit set is a *control frame*, not data. There is one:
//! [`RESUME`], followed by a 64-bit little-endian index, says "the next data frame on this
//! channel is number *k*" (counting from 0). A writer that may have sent frames twice — a voter
//! restarted in the middle of a round — sends it first, and a reader that has already taken
//! frame *k* drops the repeats (see [`FrameDecoder::resuming`]). Readers that do not expect
//! control frames see the length as oversized, as before.

use thiserror::Error;

/// Size of the length prefix.
pub const HEADER_LEN: usize = 4;

/// Default maximum payload size of a channel (64 KiB).
pub const DEFAULT_MAX_FRAME: usize = 64 * 1024;

/// Payloads up to this many bytes are copied out of a decoder
/// ([`FrameDecoder::next_frame_into`]) rather than handed over with its storage: copying them
/// costs less than the decoder-sized buffer a hand-over leaves behind, which a fork child
/// would have to copy too (its pages are private).
pub const COPY_UP_TO: usize = 512;

/// The page a frame buffer places its first frame in: the frame starts
/// [`PAYLOAD_ALIGN`]` - `[`HEADER_LEN`] bytes past a page boundary ([`frame_start`]), so that
/// its payload starts on a multiple of [`PAYLOAD_ALIGN`].
///
/// Why: on the CPUs this was measured on (AMD EPYC, Zen 4), copying 4 KiB from `src` to
/// `dst` where `dst - src` is 4 to 28 bytes past a multiple of 4 KiB (4K aliasing: each load
/// looks like it depends on the store just before it) takes 3–25 times as long: 1.2 µs
/// instead of 0.1 for `memcpy` in the voter, 2.2 µs instead of 0.4–0.5 for a pipe `read`
/// into the buffer. A pipe keeps a frame written whole at the start of its own page, so a
/// buffer whose frame starts 60 bytes into a page copies at distance 60, as fast as 0
/// (0.42–0.58 µs against 0.50–0.54 for that `read`), and two such buffers at distance 0; a
/// payload copied to a fresh allocation, 16 bytes into its first page, may not.
pub const COPY_ALIGN: usize = 4096;

/// What a payload handed out of a frame buffer is aligned to at least (a payload of at most
/// [`COPY_UP_TO`] bytes: as the allocator aligns, 16 bytes here), so that C code may read it
/// as a struct, as it may read memory from `malloc`.
pub const PAYLOAD_ALIGN: usize = 64;

/// Where a frame's header goes, past a page boundary.
const FRAME_OFFSET: usize = PAYLOAD_ALIGN - HEADER_LEN;

/// Extra bytes a buffer needs for a frame to fit from [`frame_start`] on, wherever the
/// allocator put it.
pub const FRAME_SLACK: usize = COPY_ALIGN - 1 + FRAME_OFFSET;

/// The index in `buf` where a frame buffer places its first frame (see [`COPY_ALIGN`]); the
/// caller makes `buf` long enough ([`FRAME_SLACK`] more than the frame).
pub fn frame_start(buf: &[u8]) -> usize {
    buf.as_ptr().align_offset(COPY_ALIGN) + FRAME_OFFSET
}

/// Makes room in `buf` for `need` bytes from `start`, the frame buffer's current start: as
/// it is, or grown (zero-filled) with the start placed afresh, since growing may move it.
/// Returns the start to use.
fn room_from(buf: &mut Vec<u8>, start: usize, need: usize) -> usize {
    if buf.len() >= start + need {
        return start;
    }
    buf.resize(FRAME_SLACK + need, 0);
    frame_start(buf)
}

/// Top bit of a length word: the frame is a control frame. No channel's maximum reaches it.
pub const CONTROL_BIT: u32 = 1 << 31;

/// The length word of a resume frame: "the next data frame is number *k*", *k* in the 8 bytes
/// after it.
pub const RESUME: u32 = CONTROL_BIT | 1;

/// Size of a whole resume frame (length word and index).
pub const RESUME_LEN: usize = HEADER_LEN + 8;

/// The length word of an end frame: "no more frames will come on this channel, the writer
/// ended on purpose". A voter sends it to its replicas before it closes their inputs at the
/// normal end, so that a replica can tell that end from the death of its voter (an end of
/// file without it: the replica then rebinds to the voter's successor, see
/// `contract::handshake::Rebind`).
pub const END: u32 = CONTROL_BIT | 2;

/// Size of a whole end frame (the length word alone).
pub const END_LEN: usize = HEADER_LEN;

/// A whole end frame.
pub fn end_frame() -> [u8; END_LEN] {
    END.to_le_bytes()
}

/// A whole resume frame announcing that the next data frame is number `next`.
pub fn resume_frame(next: u64) -> [u8; RESUME_LEN] {
    let mut out = [0u8; RESUME_LEN];
    out[..HEADER_LEN].copy_from_slice(&RESUME.to_le_bytes());
    out[HEADER_LEN..].copy_from_slice(&next.to_le_bytes());
    out
}

/// What can be wrong with the bytes on a channel.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
pub enum FrameError {
    /// The length prefix announces more than the channel allows.
    #[error("frame length {len} exceeds the channel maximum of {max} bytes")]
    Oversized { len: usize, max: usize },
    /// Newline-delimited text: `read` bytes without a newline, more than a line may hold (its
    /// length is not known: it has not ended).
    #[error(
        "a line longer than the channel maximum of {max} bytes ({read} bytes without a newline)"
    )]
    LineTooLong { read: usize, max: usize },
    /// The writer closed the channel in the middle of a frame.
    #[error("channel closed after {have} of {want} bytes of a frame")]
    Truncated { have: usize, want: usize },
    /// A control frame this reader does not know (its length word has the top bit set).
    #[error("unknown control frame {word:#010x}")]
    UnknownControl { word: u32 },
}

/// The 4-byte header for a payload of `len` bytes.
pub fn header(len: usize) -> [u8; HEADER_LEN] {
    (len as u32).to_le_bytes()
}

/// Appends a whole frame (header and payload) to `out`.
pub fn encode_into(payload: &[u8], out: &mut Vec<u8>) {
    out.extend_from_slice(&header(payload.len()));
    out.extend_from_slice(payload);
}

/// One frame's bytes, header and payload, placed in a page as [`COPY_ALIGN`] says and reused
/// from frame to frame: a writer's copy of the frame it sends.
#[derive(Debug, Default)]
pub struct FrameBuf {
    buf: Vec<u8>,
    /// Where in `buf` the frame starts ([`frame_start`]).
    base: usize,
    len: usize,
}

impl FrameBuf {
    /// Replaces the contents with `payload` behind its header.
    pub fn encode(&mut self, payload: &[u8]) {
        let len = HEADER_LEN + payload.len();
        self.base = room_from(&mut self.buf, self.base, len);
        let at = self.base;
        self.buf[at..at + HEADER_LEN].copy_from_slice(&header(payload.len()));
        self.buf[at + HEADER_LEN..at + len].copy_from_slice(payload);
        self.len = len;
    }

    /// The frame: header and payload.
    pub fn as_slice(&self) -> &[u8] {
        &self.buf[self.base..self.base + self.len]
    }

    /// The payload.
    pub fn payload(&self) -> &[u8] {
        &self.as_slice()[HEADER_LEN.min(self.len)..]
    }

    /// The payload, to change in place.
    pub fn payload_mut(&mut self) -> &mut [u8] {
        let at = self.base + HEADER_LEN.min(self.len);
        &mut self.buf[at..self.base + self.len]
    }
}

/// What a decoder finds at the head of its bytes.
enum Head {
    /// Not enough bytes yet for what the length word announces.
    Incomplete,
    /// A whole data frame with a payload of this many bytes.
    Data(usize),
    /// A whole `RESUME k`.
    Resume(u64),
    /// An end frame.
    End,
    /// A control frame this decoder does not know.
    Unknown(u32),
    /// A length above the channel's maximum.
    Oversized(usize),
}

/// Incremental frame decoder: bytes go in as they arrive (in any split), whole frames come out.
///
/// The buffer is reused, so a decoder in steady state does not allocate.
#[derive(Debug)]
pub struct FrameDecoder {
    max: usize,
    /// Newline-delimited text instead of length-prefixed frames (see [`FrameDecoder::lines`]).
    lines: bool,
    /// Storage. Its length only grows (zero-filled once), but for a hand-over
    /// ([`next_frame_into`](Self::next_frame_into)), which trades it for the caller's buffer
    /// (as large, in steady state); `start..end` are the bytes received and not yet decoded,
    /// so a read into the spare room costs no memset in steady state.
    buf: Vec<u8>,
    /// Where in `buf` undecoded bytes are kept from ([`frame_start`], see [`COPY_ALIGN`]);
    /// placed when the storage grows or changes hands.
    base: usize,
    start: usize,
    end: usize,
    /// Whether resume frames are understood (see [`FrameDecoder::resuming`]); otherwise their
    /// length word is [`FrameError::Oversized`] like any other.
    resuming: bool,
    /// Number of the next data frame on the channel, as the writer counts it.
    next_index: u64,
    /// Distinct data frames returned so far: frames numbered below it are repeats.
    taken: u64,
    /// Repeats dropped since the last [`take_repeats`](FrameDecoder::take_repeats).
    repeats: u64,
    /// Of those, repeats of the last frame taken (a replayed round), since the last
    /// [`take_repeats_of_last`](FrameDecoder::take_repeats_of_last).
    repeats_of_last: u64,
    /// Frames the writer skipped (a resume past `taken`) since the last
    /// [`take_skipped`](FrameDecoder::take_skipped).
    skipped: u64,
    /// An end frame was decoded: no frame comes after it (see [`END`]).
    ended: bool,
    /// Bytes decoded so far, over the decoder's life: frames returned, repeats and control
    /// frames passed over (see [`passed`](FrameDecoder::passed)).
    passed: u64,
}

impl FrameDecoder {
    pub fn new(max: usize) -> Self {
        FrameDecoder {
            max,
            lines: false,
            buf: Vec::new(),
            base: 0,
            start: 0,
            end: 0,
            resuming: false,
            next_index: 0,
            taken: 0,
            repeats: 0,
            repeats_of_last: 0,
            skipped: 0,
            ended: false,
            passed: 0,
        }
    }

    /// A decoder that understands resume frames: after `RESUME k`, the data frames numbered
    /// below the count already taken are dropped (counted by
    /// [`take_repeats`](Self::take_repeats)), and a `k` beyond it is a gap (counted by
    /// [`take_skipped`](Self::take_skipped)). Any other control frame is
    /// [`FrameError::UnknownControl`]. For channels whose writer may be restarted.
    pub fn resuming(max: usize) -> Self {
        FrameDecoder {
            resuming: true,
            ..FrameDecoder::new(max)
        }
    }

    /// Distinct data frames returned so far (repeats not counted).
    pub fn taken(&self) -> u64 {
        self.taken
    }

    /// Bytes decoded so far over the decoder's life (frames returned, repeats and control
    /// frames passed over): a reader that takes bytes off its channel only once they are
    /// decoded takes exactly the growth of this.
    pub fn passed(&self) -> u64 {
        self.passed
    }

    /// Keeps only the first `keep` undecoded bytes (a reader that peeks its channel drops
    /// what it peeked before it peeks again).
    pub fn keep_pending(&mut self, keep: usize) {
        self.end = self.start + keep.min(self.end - self.start);
    }

    /// Where the stream stands: (distinct data frames taken, number of the next data frame).
    pub fn position(&self) -> (u64, u64) {
        (self.taken, self.next_index)
    }

    /// Puts the decoder where [`position`](Self::position) said another one stood (a voter
    /// taking over its predecessor's channel).
    pub fn set_position(&mut self, taken: u64, next_index: u64) {
        self.taken = taken;
        self.next_index = next_index;
    }

    /// Whether the writer sent an end frame: the stream is over, on purpose (resuming
    /// decoders only). Bytes after it are ignored.
    pub fn ended(&self) -> bool {
        self.ended
    }

    /// Drops the bytes after the last whole frame (a writer that died in the middle of one,
    /// whose channel is then replaced by a fresh one). Whole frames already received stay.
    /// Returns how many bytes were dropped.
    pub fn discard_partial(&mut self) -> usize {
        if self.lines {
            let avail = &self.buf[self.start..self.end];
            let keep = avail.iter().rposition(|&b| b == b'\n').map_or(0, |i| i + 1);
            let dropped = avail.len() - keep;
            self.end = self.start + keep;
            return dropped;
        }
        let mut at = self.start;
        loop {
            match self.head(&self.buf[at..self.end]) {
                Head::Incomplete => break,
                Head::Resume(_) => at += RESUME_LEN,
                Head::End => at += END_LEN,
                Head::Data(len) => at += HEADER_LEN + len,
                // Not a frame boundary anyone can pass: the reader reports it as it is.
                Head::Unknown(_) | Head::Oversized(_) => return 0,
            }
        }
        let dropped = self.end - at;
        self.end = at;
        dropped
    }

    /// Repeats dropped since the last call.
    pub fn take_repeats(&mut self) -> u64 {
        std::mem::take(&mut self.repeats)
    }

    /// Repeats of the last frame taken dropped since the last call: a writer that replays its
    /// last round wants its answer again (`replica_rt` re-sends it).
    pub fn take_repeats_of_last(&mut self) -> u64 {
        std::mem::take(&mut self.repeats_of_last)
    }

    /// Frames the writer announced it skipped since the last call.
    pub fn take_skipped(&mut self) -> u64 {
        std::mem::take(&mut self.skipped)
    }

    /// A decoder of newline-delimited text: each line, without its `\n`, is one frame, and a
    /// line longer than `max` bytes is [`FrameError::LineTooLong`] (an unmodified program's
    /// stdout, `"framing": "lines"`).
    pub fn lines(max: usize) -> Self {
        FrameDecoder {
            lines: true,
            ..FrameDecoder::new(max)
        }
    }

    pub fn max_frame(&self) -> usize {
        self.max
    }

    /// Bytes received but not yet returned as frames.
    pub fn pending(&self) -> usize {
        self.end - self.start
    }

    /// Appends received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        let spare = self.spare(bytes.len());
        spare.copy_from_slice(bytes);
        self.end += bytes.len();
    }

    /// Gives a spare region of exactly `want` bytes to read into; call
    /// [`commit`](Self::commit) with how many were filled. Saves the copy of
    /// [`push`](Self::push) on the hot path.
    pub fn spare(&mut self, want: usize) -> &mut [u8] {
        // Where the pending bytes go, with room behind them (`compact` moves them there).
        self.base = room_from(&mut self.buf, self.base, self.end - self.start + want);
        self.compact();
        &mut self.buf[self.end..self.end + want]
    }

    /// Keeps `filled` bytes of the last [`spare`](Self::spare) region.
    pub fn commit(&mut self, spare_len: usize, filled: usize) {
        debug_assert!(filled <= spare_len);
        self.end += filled.min(spare_len);
    }

    /// The next whole frame's payload, if one has arrived.
    pub fn next_frame(&mut self) -> Result<Option<&[u8]>, FrameError> {
        Ok(self.next_range()?.map(|at| &self.buf[at]))
    }

    /// The next whole frame's payload, as [`next_frame`](Self::next_frame), handed over
    /// into `into` and located by the range returned, without a copy where it can be: when
    /// the frame is the last byte the decoder holds (a replica's answer, read whole) and its
    /// payload is aligned to [`PAYLOAD_ALIGN`], the decoder's storage and `into` trade
    /// places, and the decoder reads on into what `into` was. Otherwise the payload is copied
    /// into `into` at its offset in a page rounded down to [`PAYLOAD_ALIGN`] (a distance that
    /// copies fast, see [`COPY_ALIGN`]). A payload of at most [`COPY_UP_TO`] bytes is simply
    /// copied to the front of `into`. Only the range returned counts in `into`.
    pub fn next_frame_into(
        &mut self,
        into: &mut Vec<u8>,
    ) -> Result<Option<std::ops::Range<usize>>, FrameError> {
        let Some(at) = self.next_range()? else {
            return Ok(None);
        };
        let len = at.len();
        if len <= COPY_UP_TO {
            // `into` only grows, so that a storage it trades with the decoder later is not
            // zero-filled again.
            if into.len() < len {
                into.resize(len, 0);
            }
            into[..len].copy_from_slice(&self.buf[at]);
            return Ok(Some(0..len));
        }
        let address = self.buf[at.start..].as_ptr() as usize;
        if self.start == self.end && address.is_multiple_of(PAYLOAD_ALIGN) {
            std::mem::swap(&mut self.buf, into);
            // A storage too short for a frame: `spare` grows and places it.
            self.base = if self.buf.len() >= FRAME_SLACK {
                frame_start(&self.buf)
            } else {
                0
            };
            self.start = self.base;
            self.end = self.base;
            return Ok(Some(at));
        }
        let in_page = address % COPY_ALIGN / PAYLOAD_ALIGN * PAYLOAD_ALIGN;
        if into.len() < 2 * COPY_ALIGN + len {
            into.resize(2 * COPY_ALIGN + len, 0);
        }
        let from = into.as_ptr().align_offset(COPY_ALIGN) + in_page;
        into[from..from + len].copy_from_slice(&self.buf[at]);
        Ok(Some(from..from + len))
    }

    /// Where in `buf` the next whole frame's payload lies, if one has arrived.
    fn next_range(&mut self) -> Result<Option<std::ops::Range<usize>>, FrameError> {
        if self.lines {
            return self.next_line();
        }
        loop {
            if self.ended {
                return Ok(None);
            }
            let len = match self.head(&self.buf[self.start..self.end]) {
                Head::Incomplete => return Ok(None),
                Head::End => {
                    self.passed += END_LEN as u64;
                    self.start = self.end;
                    self.ended = true;
                    return Ok(None);
                }
                Head::Resume(next) => {
                    self.start += RESUME_LEN;
                    self.passed += RESUME_LEN as u64;
                    self.resume(next);
                    continue;
                }
                Head::Unknown(word) => return Err(FrameError::UnknownControl { word }),
                Head::Oversized(len) => return Err(FrameError::Oversized { len, max: self.max }),
                Head::Data(len) => len,
            };
            let from = self.start + HEADER_LEN;
            self.start = from + len;
            self.passed += (HEADER_LEN + len) as u64;
            let index = self.next_index;
            self.next_index = index.saturating_add(1);
            if index < self.taken {
                self.repeats += 1;
                if index + 1 == self.taken {
                    self.repeats_of_last += 1;
                }
                continue;
            }
            self.taken = self.next_index;
            return Ok(Some(from..from + len));
        }
    }

    /// `RESUME next`: the writer's next data frame is number `next`.
    fn resume(&mut self, next: u64) {
        if next > self.taken {
            self.skipped = self.skipped.saturating_add(next - self.taken);
            self.taken = next;
        }
        self.next_index = next;
    }

    /// Room the buffer has for a read without growing (after [`spare`](Self::spare) moves
    /// the pending bytes to `base`).
    pub fn room(&self) -> usize {
        self.buf.len() - self.base - (self.end - self.start)
    }

    /// Bytes still to come before the frame at the head is whole, when its length word has
    /// arrived; 0 otherwise (no length word yet or only part of it, a control frame, an
    /// oversized length, lines). A reader sizes its next read by it, so that a large frame
    /// takes one read without every read reserving room for the largest.
    pub fn missing(&self) -> usize {
        if self.lines || self.ended {
            return 0;
        }
        let avail = &self.buf[self.start..self.end];
        let Some(word) = avail.first_chunk::<HEADER_LEN>() else {
            return 0;
        };
        let word = u32::from_le_bytes(*word);
        let len = word as usize;
        if (self.resuming && word & CONTROL_BIT != 0) || len > self.max {
            return 0;
        }
        (HEADER_LEN + len).saturating_sub(avail.len())
    }

    /// Whether a whole frame (or an oversized header, which [`next_frame`](Self::next_frame)
    /// then reports) is waiting, so that the next `next_frame` returns without more bytes.
    pub fn has_frame(&self) -> bool {
        let avail = &self.buf[self.start..self.end];
        if self.lines {
            return avail.len() > self.max || avail.contains(&b'\n');
        }
        // Walks what `next_frame` would do, without doing it: resume frames and repeats are
        // passed over, as `next_frame` passes over them.
        let (mut at, mut next, mut taken) = (0, self.next_index, self.taken);
        if self.ended {
            return false;
        }
        loop {
            match self.head(&avail[at..]) {
                Head::Incomplete | Head::End => return false,
                Head::Resume(k) => {
                    (next, taken) = (k, taken.max(k));
                    at += RESUME_LEN;
                }
                // `next_frame` reports these.
                Head::Unknown(_) | Head::Oversized(_) => return true,
                Head::Data(_) if next >= taken => return true,
                Head::Data(len) => {
                    next += 1;
                    at += HEADER_LEN + len;
                }
            }
        }
    }

    /// What the bytes at the head of `avail` are (frames, not lines).
    fn head(&self, avail: &[u8]) -> Head {
        let Some(word) = avail.first_chunk::<HEADER_LEN>() else {
            return Head::Incomplete;
        };
        let word = u32::from_le_bytes(*word);
        if self.resuming && word & CONTROL_BIT != 0 {
            if word == END {
                return Head::End;
            }
            if word != RESUME {
                return Head::Unknown(word);
            }
            return match avail[HEADER_LEN..].first_chunk::<8>() {
                Some(index) => Head::Resume(u64::from_le_bytes(*index)),
                None => Head::Incomplete,
            };
        }
        let len = word as usize;
        if len > self.max {
            Head::Oversized(len)
        } else if avail.len() < HEADER_LEN + len {
            Head::Incomplete
        } else {
            Head::Data(len)
        }
    }

    /// Called at end of stream: an error if a frame was cut off.
    pub fn finish(&self) -> Result<(), FrameError> {
        let avail = &self.buf[self.start..self.end];
        if self.ended {
            return Ok(());
        }
        if self.lines && !avail.is_empty() {
            // The last line has no newline: it may be whole, but there is no telling.
            return Err(FrameError::Truncated {
                have: avail.len(),
                want: avail.len() + 1,
            });
        }
        match avail.len() {
            0 => Ok(()),
            n if n < HEADER_LEN => Err(FrameError::Truncated {
                have: n,
                want: HEADER_LEN,
            }),
            n => {
                let word = u32::from_le_bytes([avail[0], avail[1], avail[2], avail[3]]);
                let want = if self.resuming && word == RESUME {
                    RESUME_LEN
                } else {
                    HEADER_LEN + word as usize
                };
                Err(FrameError::Truncated { have: n, want })
            }
        }
    }

    /// Where the next whole line lies (see [`FrameDecoder::lines`]).
    fn next_line(&mut self) -> Result<Option<std::ops::Range<usize>>, FrameError> {
        let avail = &self.buf[self.start..self.end];
        // A line may be `max` bytes long, and its newline comes after it.
        let look = &avail[..avail.len().min(self.max.saturating_add(1))];
        match look.iter().position(|&b| b == b'\n') {
            Some(len) => {
                let from = self.start;
                self.start = from + len + 1;
                Ok(Some(from..from + len))
            }
            None if avail.len() > self.max => Err(FrameError::LineTooLong {
                read: avail.len(),
                max: self.max,
            }),
            None => Ok(None),
        }
    }

    /// Takes every byte not yet decoded (used when a stream changes hands).
    pub fn take_pending(&mut self) -> Vec<u8> {
        let rest = self.buf[self.start..self.end].to_vec();
        self.start = self.base;
        self.end = self.base;
        rest
    }

    /// Moves the undecoded bytes to `base`, so the storage does not grow with the stream, and
    /// a frame read whole off a pipe lies where [`COPY_ALIGN`] says.
    fn compact(&mut self) {
        if self.start == self.base {
            return;
        }
        self.buf.copy_within(self.start..self.end, self.base);
        self.end = self.base + (self.end - self.start);
        self.start = self.base;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Pushes `bytes` into `dec` in pieces of the sizes in `cuts` (the rest at once), taking
    /// every whole frame after each piece, and checks that `has_frame` promised each one.
    fn decode_in_pieces(dec: &mut FrameDecoder, bytes: &[u8], cuts: Vec<usize>) -> Vec<Vec<u8>> {
        let mut got = Vec::new();
        let mut pos = 0;
        let mut cuts = cuts.into_iter();
        while pos < bytes.len() {
            let step = cuts.next().unwrap_or(bytes.len()).min(bytes.len() - pos);
            dec.push(&bytes[pos..pos + step]);
            pos += step;
            loop {
                let promised = dec.has_frame();
                let Some(f) = dec.next_frame().unwrap() else {
                    assert!(
                        !promised,
                        "has_frame promised a frame that next_frame did not give"
                    );
                    break;
                };
                assert!(
                    promised,
                    "next_frame gave a frame that has_frame did not promise"
                );
                got.push(f.to_vec());
            }
        }
        got
    }

    fn encode_all(frames: &[Vec<u8>]) -> Vec<u8> {
        let mut out = Vec::new();
        for f in frames {
            encode_into(f, &mut out);
        }
        out
    }

    fn page_offset(p: *const u8) -> usize {
        p as usize % COPY_ALIGN
    }

    /// A reader's room starts where `COPY_ALIGN` says, also after a partial frame was moved
    /// to the front and after the storage grew; a frame read whole then has its payload
    /// aligned and is handed over without a copy.
    #[test]
    fn frames_are_read_where_copy_align_says_and_handed_over_in_place() {
        let mut dec = FrameDecoder::new(64 * 1024);
        assert_eq!(page_offset(dec.spare(100).as_ptr()), FRAME_OFFSET);
        dec.push(&header(5000));
        dec.push(&[1; 10]);
        // The partial frame moved to the front as the storage grows for the rest.
        let spare = dec.spare(60 * 1024);
        assert_eq!(page_offset(spare.as_ptr()), FRAME_OFFSET + HEADER_LEN + 10);
        spare[..4990].fill(1);
        dec.commit(60 * 1024, 4990);
        let read_into = dec.buf.as_ptr();
        let mut into = Vec::new();
        let at = dec.next_frame_into(&mut into).unwrap().unwrap();
        assert_eq!(&into[at.clone()], &[1; 5000][..]);
        assert_eq!(
            into.as_ptr(),
            read_into,
            "the read buffer itself, not a copy"
        );
        assert_eq!(page_offset(into[at].as_ptr()), PAYLOAD_ALIGN);
        // The decoder reads on into the buffer it got, placed once it is large enough.
        assert_eq!(page_offset(dec.spare(60 * 1024).as_ptr()), FRAME_OFFSET);
        // A frame with more bytes behind it is copied, to its page offset rounded down to
        // PAYLOAD_ALIGN; a small one to the front of a buffer that does not shrink.
        let (first, second) = ([2; COPY_UP_TO + 1], *b"second");
        let mut three = Vec::new();
        encode_into(&first, &mut three);
        encode_into(&second, &mut three);
        encode_into(&first, &mut three);
        let n = three.len();
        dec.spare(n).copy_from_slice(&three);
        dec.commit(n, n);
        let mut other = Vec::new();
        let at = dec.next_frame_into(&mut other).unwrap().unwrap();
        assert_eq!(&other[at.clone()], &first[..]);
        assert_eq!(page_offset(other[at].as_ptr()), PAYLOAD_ALIGN);
        let had = into.len();
        let at = dec.next_frame_into(&mut into).unwrap().unwrap();
        assert_eq!((&into[at.clone()], at.start), (&second[..], 0));
        assert_eq!(
            into.len(),
            had,
            "a small frame leaves the buffer as large as it was"
        );
        // The last frame, its payload off the alignment: copied, to an aligned place.
        let at = dec.next_frame_into(&mut other).unwrap().unwrap();
        assert_eq!(&other[at.clone()], &first[..]);
        assert_eq!(other[at].as_ptr() as usize % PAYLOAD_ALIGN, 0);
        assert_eq!(dec.next_frame_into(&mut into).unwrap(), None);
    }

    /// A writer's frame stays where `COPY_ALIGN` says however it grows, its payload aligned.
    #[test]
    fn a_frame_buffer_keeps_its_frame_where_copy_align_says() {
        let mut buf = FrameBuf::default();
        for len in [0, 8, 4096, 100, 70_000, 3] {
            let payload: Vec<u8> = (0..len).map(|i| i as u8).collect();
            buf.encode(&payload);
            assert_eq!(page_offset(buf.as_slice().as_ptr()), FRAME_OFFSET);
            assert_eq!(
                buf.as_slice()[HEADER_LEN..].as_ptr() as usize % PAYLOAD_ALIGN,
                0
            );
            assert_eq!(buf.as_slice()[..HEADER_LEN], header(len));
            assert_eq!(&buf.as_slice()[HEADER_LEN..], &payload[..]);
            buf.payload_mut().iter_mut().for_each(|b| *b ^= 0xff);
            assert!(buf.as_slice()[HEADER_LEN..]
                .iter()
                .zip(&payload)
                .all(|(a, b)| *a == !b));
        }
    }

    proptest! {
        /// Any split of a valid stream decodes to the same frames.
        #[test]
        fn any_split_decodes_the_same(
            frames in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..300), 0..20),
            cuts in proptest::collection::vec(1usize..97, 0..40),
        ) {
            let bytes = encode_all(&frames);
            let mut dec = FrameDecoder::new(1024);
            let got = decode_in_pieces(&mut dec, &bytes, cuts);
            prop_assert_eq!(got, frames);
            prop_assert!(dec.finish().is_ok());
        }

        /// Frames handed over (`next_frame_into`, the decoder's storage trading places with two
        /// buffers in turn) are the frames `next_frame` gives, however the bytes arrive through
        /// `spare`/`commit` as a reader's do; each one lies where its page offset says.
        #[test]
        fn frames_handed_over_are_the_frames_decoded(
            frames in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..5000), 0..12),
            cuts in proptest::collection::vec(1usize..9000, 0..30),
        ) {
            let bytes = encode_all(&frames);
            let mut dec = FrameDecoder::new(8192);
            let mut pool = [Vec::new(), Vec::new()];
            let mut got = Vec::new();
            let (mut pos, mut cuts) = (0, cuts.into_iter());
            while pos < bytes.len() {
                let step = cuts.next().unwrap_or(bytes.len()).min(bytes.len() - pos);
                let spare = dec.spare(step);
                spare.copy_from_slice(&bytes[pos..pos + step]);
                dec.commit(step, step);
                pos += step;
                while let Some(at) = dec.next_frame_into(&mut pool[got.len() % 2]).unwrap() {
                    let buf = &pool[got.len() % 2];
                    prop_assert!(at.len() <= COPY_UP_TO || (buf[at.clone()].as_ptr() as usize).is_multiple_of(PAYLOAD_ALIGN));
                    got.push(buf[at].to_vec());
                }
            }
            prop_assert_eq!(got, frames);
            prop_assert!(dec.finish().is_ok());
        }

        /// A length above the maximum is an error however the header arrives, never a panic.
        #[test]
        fn oversized_is_rejected(len in 1025u32.., split in 0usize..4) {
            let mut dec = FrameDecoder::new(1024);
            let h = len.to_le_bytes();
            dec.push(&h[..split]);
            prop_assert_eq!(dec.next_frame(), Ok(None));
            dec.push(&h[split..]);
            prop_assert_eq!(dec.next_frame(), Err(FrameError::Oversized { len: len as usize, max: 1024 }));
        }

        /// A stream cut anywhere inside a frame reports truncation at the end.
        #[test]
        fn truncation_is_reported(payload in proptest::collection::vec(any::<u8>(), 1..200), cut_back in 1usize..200) {
            let mut bytes = encode_all(&[payload]);
            let cut = cut_back.min(bytes.len() - 1);
            bytes.truncate(bytes.len() - cut);
            let mut dec = FrameDecoder::new(1024);
            dec.push(&bytes);
            prop_assert_eq!(dec.next_frame(), Ok(None));
            let truncated = matches!(dec.finish(), Err(FrameError::Truncated { .. }));
            prop_assert!(truncated);
        }
    }

    /// What a writer restarted at the points in `restarts` sends: frames `0..frames.len()`,
    /// and at each restart `(after, back)` — after sending `after` frames — a resume frame that
    /// goes `back` frames back and sends them again.
    fn replayed_stream(frames: &[Vec<u8>], restarts: &[(usize, usize)]) -> Vec<u8> {
        let mut out = Vec::new();
        let mut sent = 0;
        let mut restarts = restarts.to_vec();
        restarts.sort();
        let mut restarts = restarts.into_iter().peekable();
        while sent < frames.len() {
            while let Some(&(after, back)) = restarts.peek() {
                if after > sent {
                    break;
                }
                restarts.next();
                sent -= back.min(sent);
                out.extend_from_slice(&resume_frame(sent as u64));
            }
            encode_into(&frames[sent], &mut out);
            sent += 1;
        }
        out
    }

    proptest! {
        /// A writer that resumes anywhere, going back any number of frames, is read as if it
        /// had sent each frame once, however the bytes are split; the repeats are counted.
        #[test]
        fn repeats_after_a_resume_are_dropped(
            frames in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..40), 0..20),
            restarts in proptest::collection::vec((0usize..20, 0usize..4), 0..5),
            cuts in proptest::collection::vec(1usize..23, 0..60),
        ) {
            let bytes = replayed_stream(&frames, &restarts);
            let mut dec = FrameDecoder::resuming(64);
            let got = decode_in_pieces(&mut dec, &bytes, cuts);
            prop_assert!(dec.finish().is_ok());
            prop_assert_eq!(&got, &frames);
            prop_assert_eq!(dec.taken(), frames.len() as u64);
            prop_assert_eq!(dec.take_skipped(), 0);
        }
    }

    /// A stream of data frames (`Ok(payload)`) and resume frames (`Err(next)`).
    fn stream(parts: &[Result<&[u8], u64>]) -> Vec<u8> {
        let mut bytes = Vec::new();
        for part in parts {
            match part {
                Ok(payload) => encode_into(payload, &mut bytes),
                Err(next) => bytes.extend_from_slice(&resume_frame(*next)),
            }
        }
        bytes
    }

    #[test]
    fn missing_is_what_the_head_frame_still_lacks() {
        let mut dec = FrameDecoder::resuming(100);
        assert_eq!(dec.missing(), 0, "no length word yet");
        dec.push(&[50, 0]);
        assert_eq!(dec.missing(), 0, "half a length word");
        dec.push(&[0, 0, 1, 2, 3]);
        assert_eq!(dec.missing(), 47);
        dec.push(&[0; 47]);
        assert_eq!(dec.missing(), 0, "whole");
        assert_eq!(dec.next_frame().unwrap().map(<[u8]>::len), Some(50));
        dec.push(&resume_frame(7));
        assert_eq!(dec.missing(), 0, "a control frame");
        let mut big = FrameDecoder::new(10);
        big.push(&[200, 0, 0, 0]);
        assert_eq!(big.missing(), 0, "oversized: next_frame reports it");
        let mut lines = FrameDecoder::lines(100);
        lines.push(b"abc");
        assert_eq!(lines.missing(), 0);
    }

    #[test]
    fn a_resume_past_what_was_taken_is_a_gap() {
        let mut dec = FrameDecoder::resuming(16);
        dec.push(&stream(&[Ok(b"a"), Err(3), Ok(b"d")]));
        assert_eq!(dec.next_frame().unwrap(), Some(&b"a"[..]));
        assert_eq!(dec.next_frame().unwrap(), Some(&b"d"[..]));
        assert_eq!((dec.taken(), dec.take_skipped()), (4, 2));
        assert_eq!(dec.take_skipped(), 0);
    }

    #[test]
    fn a_resume_is_counted_as_repeats_and_cut_resumes_are_truncated() {
        let mut dec = FrameDecoder::resuming(16);
        dec.push(&stream(&[Ok(b"a"), Ok(b"b"), Err(1), Ok(b"b"), Ok(b"c")]));
        let mut got = Vec::new();
        while let Some(f) = dec.next_frame().unwrap() {
            got.push(f.to_vec());
        }
        assert_eq!(got, [b"a".to_vec(), b"b".to_vec(), b"c".to_vec()]);
        assert_eq!((dec.take_repeats(), dec.take_repeats_of_last()), (1, 1));
        assert_eq!((dec.take_repeats(), dec.take_repeats_of_last()), (0, 0));

        // Two back: two repeats, one of them of the last frame.
        dec.push(&stream(&[Err(1), Ok(b"b"), Ok(b"c")]));
        assert_eq!(dec.next_frame().unwrap(), None);
        assert_eq!((dec.take_repeats(), dec.take_repeats_of_last()), (2, 1));

        dec.push(&resume_frame(0)[..7]);
        assert!(!dec.has_frame());
        assert_eq!(dec.next_frame().unwrap(), None);
        assert_eq!(
            dec.finish(),
            Err(FrameError::Truncated {
                have: 7,
                want: RESUME_LEN
            })
        );
    }

    #[test]
    fn control_frames_are_oversized_to_a_reader_that_does_not_resume() {
        let mut dec = FrameDecoder::new(16);
        dec.push(&resume_frame(0));
        assert!(dec.has_frame());
        assert_eq!(
            dec.next_frame(),
            Err(FrameError::Oversized {
                len: RESUME as usize,
                max: 16
            })
        );
        let mut dec = FrameDecoder::resuming(16);
        dec.push(&(CONTROL_BIT | 7).to_le_bytes());
        assert!(dec.has_frame());
        assert_eq!(
            dec.next_frame(),
            Err(FrameError::UnknownControl {
                word: CONTROL_BIT | 7
            })
        );
    }

    proptest! {
        /// Lines, split anywhere, decode to the lines without their newlines.
        #[test]
        fn lines_decode_however_split(
            lines in proptest::collection::vec("[ -~]{0,40}", 0..20),
            cuts in proptest::collection::vec(1usize..17, 0..40),
        ) {
            let bytes: Vec<u8> = lines.iter().flat_map(|l| l.bytes().chain([b'\n'])).collect();
            let mut dec = FrameDecoder::lines(40);
            let got: Vec<String> = decode_in_pieces(&mut dec, &bytes, cuts)
                .into_iter()
                .map(|f| String::from_utf8(f).unwrap())
                .collect();
            prop_assert_eq!(got, lines);
            prop_assert!(dec.finish().is_ok());
        }
    }

    #[test]
    fn a_line_longer_than_the_maximum_is_too_long_and_a_cut_line_truncated() {
        let mut dec = FrameDecoder::lines(4);
        dec.push(b"abcd\nabcde");
        assert!(dec.has_frame());
        assert_eq!(dec.next_frame().unwrap(), Some(&b"abcd"[..]));
        assert!(dec.has_frame());
        let e = dec.next_frame().unwrap_err();
        assert_eq!(e, FrameError::LineTooLong { read: 5, max: 4 });
        // Its length is not known (it has not ended): the message says what was read.
        assert_eq!(
            e.to_string(),
            "a line longer than the channel maximum of 4 bytes (5 bytes without a newline)"
        );
        let mut dec = FrameDecoder::lines(4);
        dec.push(b"ab");
        assert!(!dec.has_frame());
        assert_eq!(dec.next_frame().unwrap(), None);
        assert!(matches!(dec.finish(), Err(FrameError::Truncated { .. })));
    }

    #[test]
    fn spare_and_commit_roundtrip() {
        let mut dec = FrameDecoder::new(16);
        let bytes = encode_all(&[b"abc".to_vec()]);
        let spare = dec.spare(64);
        spare[..bytes.len()].copy_from_slice(&bytes);
        dec.commit(64, bytes.len());
        assert_eq!(dec.next_frame().unwrap(), Some(&b"abc"[..]));
        assert_eq!(dec.next_frame().unwrap(), None);
        assert_eq!(dec.pending(), 0);
    }

    #[test]
    fn an_end_frame_ends_a_resuming_stream_and_nothing_after_it_counts() {
        let mut bytes = Vec::new();
        encode_into(b"a", &mut bytes);
        bytes.extend_from_slice(&end_frame());
        encode_into(b"late", &mut bytes);
        let mut dec = FrameDecoder::resuming(16);
        dec.push(&bytes);
        assert!(dec.has_frame());
        assert_eq!(dec.next_frame().unwrap(), Some(&b"a"[..]));
        assert!(!dec.has_frame());
        assert_eq!(dec.next_frame().unwrap(), None);
        assert!(dec.ended());
        assert_eq!(dec.next_frame().unwrap(), None);
        assert_eq!(dec.finish(), Ok(()));
        // To a reader that does not resume, it is a length like any other: oversized.
        let mut plain = FrameDecoder::new(16);
        plain.push(&end_frame());
        assert!(matches!(
            plain.next_frame(),
            Err(FrameError::Oversized { .. })
        ));
    }

    #[test]
    fn discard_partial_keeps_whole_frames_and_drops_the_cut_tail() {
        let mut bytes = Vec::new();
        encode_into(b"one", &mut bytes);
        bytes.extend_from_slice(&resume_frame(1));
        encode_into(b"two", &mut bytes);
        let whole = bytes.len();
        encode_into(b"three", &mut bytes);
        for cut in whole..bytes.len() {
            let mut dec = FrameDecoder::resuming(16);
            dec.push(&bytes[..cut]);
            assert_eq!(dec.discard_partial(), cut - whole, "cut at {cut}");
            // The stream goes on on a fresh channel, from a frame boundary.
            dec.push(&resume_frame(2));
            let mut rest = Vec::new();
            encode_into(b"three", &mut rest);
            dec.push(&rest);
            let mut got = Vec::new();
            while let Some(f) = dec.next_frame().unwrap() {
                got.push(f.to_vec());
            }
            assert_eq!(
                got,
                vec![b"one".to_vec(), b"two".to_vec(), b"three".to_vec()]
            );
        }
        let mut lines = FrameDecoder::lines(16);
        lines.push(b"a\nbc");
        assert_eq!(lines.discard_partial(), 2);
        assert_eq!(lines.next_frame().unwrap(), Some(&b"a"[..]));
        assert_eq!(lines.next_frame().unwrap(), None);
    }
}
