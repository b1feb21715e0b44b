//! Frames: the unit of everything that crosses a channel, and the unit of voting.
//!
//! A frame is a 4-byte little-endian length followed by that many bytes. Each channel has a
//! maximum frame size; a length above it is a protocol error, never an allocation.

use thiserror::Error;

/// Size of the length prefix.
pub const HEADER_LEN: usize = 4;

/// Default maximum payload size of a channel (64 KiB).
pub const DEFAULT_MAX_FRAME: usize = 64 * 1024;

/// What can be wrong with the bytes on a channel.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
pub enum FrameError {
    /// The length prefix announces more than the channel allows.
    #[error("frame length {len} exceeds the channel maximum of {max} bytes")]
    Oversized { len: usize, max: usize },
    /// The writer closed the channel in the middle of a frame.
    #[error("channel closed after {have} of {want} bytes of a frame")]
    Truncated { have: usize, want: usize },
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

/// Incremental frame decoder: bytes go in as they arrive (in any split), whole frames come out.
///
/// The buffer is reused, so a decoder in steady state does not allocate.
#[derive(Debug)]
pub struct FrameDecoder {
    max: usize,
    /// Newline-delimited text instead of length-prefixed frames (see [`FrameDecoder::lines`]).
    lines: bool,
    /// Storage. Its length only grows (zero-filled once); `start..end` are the bytes received
    /// and not yet decoded, so a read into the spare room costs no memset in steady state.
    buf: Vec<u8>,
    start: usize,
    end: usize,
}

impl FrameDecoder {
    pub fn new(max: usize) -> Self {
        FrameDecoder {
            max,
            lines: false,
            buf: Vec::new(),
            start: 0,
            end: 0,
        }
    }

    /// A decoder of newline-delimited text: each line, without its `\n`, is one frame, and a
    /// line longer than `max` bytes is [`FrameError::Oversized`] (an unmodified program's
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
        self.compact();
        if self.buf.len() < self.end + want {
            self.buf.resize(self.end + want, 0);
        }
        &mut self.buf[self.end..self.end + want]
    }

    /// Keeps `filled` bytes of the last [`spare`](Self::spare) region.
    pub fn commit(&mut self, spare_len: usize, filled: usize) {
        debug_assert!(filled <= spare_len);
        self.end += filled.min(spare_len);
    }

    /// The next whole frame's payload, if one has arrived.
    pub fn next_frame(&mut self) -> Result<Option<&[u8]>, FrameError> {
        if self.lines {
            return self.next_line();
        }
        let avail = &self.buf[self.start..self.end];
        if avail.len() < HEADER_LEN {
            return Ok(None);
        }
        let len = u32::from_le_bytes([avail[0], avail[1], avail[2], avail[3]]) as usize;
        if len > self.max {
            return Err(FrameError::Oversized { len, max: self.max });
        }
        if avail.len() < HEADER_LEN + len {
            return Ok(None);
        }
        let from = self.start + HEADER_LEN;
        self.start = from + len;
        Ok(Some(&self.buf[from..from + len]))
    }

    /// Whether a whole frame (or an oversized header, which [`next_frame`](Self::next_frame)
    /// then reports) is waiting, so that the next `next_frame` returns without more bytes.
    pub fn has_frame(&self) -> bool {
        let avail = &self.buf[self.start..self.end];
        if self.lines {
            return avail.len() > self.max || avail.contains(&b'\n');
        }
        if avail.len() < HEADER_LEN {
            return false;
        }
        let len = u32::from_le_bytes([avail[0], avail[1], avail[2], avail[3]]) as usize;
        len > self.max || avail.len() >= HEADER_LEN + len
    }

    /// Called at end of stream: an error if a frame was cut off.
    pub fn finish(&self) -> Result<(), FrameError> {
        let avail = &self.buf[self.start..self.end];
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
                let len = u32::from_le_bytes([avail[0], avail[1], avail[2], avail[3]]) as usize;
                Err(FrameError::Truncated {
                    have: n,
                    want: HEADER_LEN + len,
                })
            }
        }
    }

    /// The next whole line (see [`FrameDecoder::lines`]).
    fn next_line(&mut self) -> Result<Option<&[u8]>, FrameError> {
        let avail = &self.buf[self.start..self.end];
        // A line may be `max` bytes long, and its newline comes after it.
        let look = &avail[..avail.len().min(self.max.saturating_add(1))];
        match look.iter().position(|&b| b == b'\n') {
            Some(len) => {
                let from = self.start;
                self.start = from + len + 1;
                Ok(Some(&self.buf[from..from + len]))
            }
            None if avail.len() > self.max => Err(FrameError::Oversized {
                len: avail.len(),
                max: self.max,
            }),
            None => Ok(None),
        }
    }

    /// Takes every byte not yet decoded (used when a stream changes hands).
    pub fn take_pending(&mut self) -> Vec<u8> {
        let rest = self.buf[self.start..self.end].to_vec();
        self.start = 0;
        self.end = 0;
        rest
    }

    /// Moves the undecoded bytes to the front, so the storage does not grow with the stream.
    fn compact(&mut self) {
        if self.start == 0 {
            return;
        }
        self.buf.copy_within(self.start..self.end, 0);
        self.end -= self.start;
        self.start = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Pushes `bytes` into `dec` in pieces of the sizes in `cuts` (the rest at once), taking
    /// every whole frame after each piece.
    fn decode_in_pieces(dec: &mut FrameDecoder, bytes: &[u8], cuts: Vec<usize>) -> Vec<Vec<u8>> {
        let mut got = Vec::new();
        let mut pos = 0;
        let mut cuts = cuts.into_iter();
        while pos < bytes.len() {
            let step = cuts.next().unwrap_or(bytes.len()).min(bytes.len() - pos);
            dec.push(&bytes[pos..pos + step]);
            pos += step;
            while let Some(f) = dec.next_frame().unwrap() {
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
    fn a_line_longer_than_the_maximum_is_oversized_and_a_cut_line_truncated() {
        let mut dec = FrameDecoder::lines(4);
        dec.push(b"abcd\nabcde");
        assert!(dec.has_frame());
        assert_eq!(dec.next_frame().unwrap(), Some(&b"abcd"[..]));
        assert!(dec.has_frame());
        assert_eq!(
            dec.next_frame(),
            Err(FrameError::Oversized { len: 5, max: 4 })
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
}
