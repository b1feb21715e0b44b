//! A stream replica's recent output frames, sent again to a voter's successor (issue 13, item
//! 2, stream mode).
//!
//! A reactive replica's frames answer input frames, so a voter that dies in the middle of a
//! round has its successor replay the round, and the replica answers again from its last frame
//! (`answers`). A stream replica's frames answer nothing in particular: the frames it had sent
//! and its voter had not decided yet die with the voter's ends of the pipes. So each output
//! keeps the frames its voter may not have decided, and after a rebind they are written to the
//! successor's fresh pipe behind `RESUME n`, `n` the number of the oldest kept
//! ([`History::resend`]). The successor starts every replica's output at the count its
//! predecessor committed, so its decoder drops the frames below it as repeats.
//!
//! Which frames the voter may not have decided ([`Limits`], from
//! `contract::ENV_OUTPUT_HISTORY`): it decides each output's frames in order; it holds at most
//! `frames` of a replica's decoded frames undecided (its window); and at most `bytes` of the
//! newest frames are not decoded yet (in the pipe, or in its read buffer). So a frame with
//! more than `bytes` of newer frames beyond the `frames` frames right after it is decided: it
//! is dropped. Memory is thus about `bytes` plus `frames` of the replica's own frames.

use std::collections::VecDeque;
use std::io;
use std::os::fd::BorrowedFd;
use std::sync::OnceLock;

use crate::contract::ENV_OUTPUT_HISTORY;
use crate::frame::resume_frame;

/// How much every output keeps (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Limits {
    pub(crate) frames: usize,
    pub(crate) bytes: usize,
}

impl Limits {
    /// `"FRAMES,BYTES"`.
    fn parse(s: &str) -> Option<Limits> {
        let (frames, bytes) = s.split_once(',')?;
        Some(Limits {
            frames: frames.trim().parse().ok()?,
            bytes: bytes.trim().parse().ok()?,
        })
    }
}

static LIMITS: OnceLock<Limits> = OnceLock::new();

/// Reads the limits the voter set (replica mode only, at `init`); a value that does not parse
/// is reported and keeps no history (a voter restart then finds this replica short of frames,
/// and replaces it).
pub(crate) fn configure_from_env() {
    let Ok(value) = std::env::var(ENV_OUTPUT_HISTORY) else {
        return;
    };
    match Limits::parse(&value) {
        Some(limits) => {
            let _ = LIMITS.set(limits);
        }
        None => tracing::warn!(
            value,
            "{ENV_OUTPUT_HISTORY} is not FRAMES,BYTES: keeping no output history"
        ),
    }
}

/// A history for a new output port, if this replica keeps them.
pub(crate) fn for_new_port() -> Option<History> {
    LIMITS.get().map(|&limits| History::new(limits))
}

/// One output's kept frames.
#[derive(Debug)]
pub(crate) struct History {
    limits: Limits,
    /// Number of the oldest frame kept.
    first: u64,
    /// Whole frames (header and payload, as sent), oldest first.
    frames: VecDeque<Vec<u8>>,
    /// Their bytes.
    bytes: usize,
    /// Buffers of dropped frames, reused for new ones.
    spare: Vec<Vec<u8>>,
}

impl History {
    pub(crate) fn new(limits: Limits) -> History {
        History {
            limits,
            first: 0,
            frames: VecDeque::new(),
            bytes: 0,
            spare: Vec::new(),
        }
    }

    /// Frame number `number` (`frame`: header and payload, as written) went out.
    pub(crate) fn record(&mut self, number: u64, frame: &[u8]) {
        if self.first + self.frames.len() as u64 != number {
            // Not the next one (cannot happen on a port's own count): start again from it.
            while let Some(old) = self.frames.pop_front() {
                self.spare.push(old);
            }
            self.bytes = 0;
            self.first = number;
        }
        let mut buf = self.spare.pop().unwrap_or_default();
        buf.clear();
        buf.extend_from_slice(frame);
        self.bytes += buf.len();
        self.frames.push_back(buf);
        self.trim();
    }

    /// Drops the oldest frames while they are decided for sure (module docs).
    fn trim(&mut self) {
        let Limits { frames, bytes } = self.limits;
        while self.frames.len() > frames + 1 {
            let front = self.frames[0].len();
            let after: usize = self.frames.iter().skip(1).take(frames).map(Vec::len).sum();
            if self.bytes - front - after <= bytes {
                return;
            }
            if let Some(old) = self.frames.pop_front() {
                self.bytes -= old.len();
                self.first += 1;
                if self.spare.len() < 4 {
                    self.spare.push(old);
                }
            }
        }
    }

    /// Numbers of the frames kept: `first..first + len`.
    #[cfg(test)]
    fn kept(&self) -> std::ops::Range<u64> {
        self.first..self.first + self.frames.len() as u64
    }

    /// Writes the kept frames to `fd` (a successor's fresh pipe) behind `RESUME first`, in one
    /// write as far as the pipe takes it.
    pub(crate) fn resend(&self, fd: BorrowedFd<'_>) -> io::Result<()> {
        if self.frames.is_empty() {
            return Ok(());
        }
        let mut bytes = Vec::with_capacity(crate::frame::RESUME_LEN + self.bytes);
        bytes.extend_from_slice(&resume_frame(self.first));
        for f in &self.frames {
            bytes.extend_from_slice(f);
        }
        crate::port::write_all(fd, &bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::{encode_into, FrameDecoder};
    use crate::sys;
    use std::os::fd::{AsFd, AsRawFd};

    fn frame(len: usize, fill: u8) -> Vec<u8> {
        let mut out = Vec::new();
        encode_into(&vec![fill; len], &mut out);
        out
    }

    /// Every frame within the limits stays, the ones beyond go; frames of 100 B payload.
    #[test]
    fn keeps_the_window_and_the_bytes_beyond_it() {
        let mut h = History::new(Limits {
            frames: 3,
            bytes: 250,
        });
        for n in 0..20 {
            h.record(n, &frame(100, n as u8));
        }
        // Frame k stays while the frames after the next 3 hold <= 250 B: two frames of 104 B.
        // So the newest 3 + 2 and the one before them: 6 frames.
        assert_eq!(h.kept(), 14..20);
        // A gap starts over.
        h.record(30, &frame(1, 0));
        assert_eq!(h.kept(), 30..31);
    }

    /// What a successor reads: RESUME first, then the kept frames; its decoder, started at a
    /// count inside them, gets exactly the rest.
    #[test]
    fn resend_lines_up_with_a_decoder_started_at_the_committed_count() {
        let mut h = History::new(Limits {
            frames: 64,
            bytes: 1 << 20,
        });
        for n in 0..10 {
            h.record(n, &frame(8, n as u8));
        }
        let (r, w) = sys::pipe().unwrap();
        h.resend(w.as_fd()).unwrap();
        drop(w);
        let mut dec = FrameDecoder::resuming(64);
        dec.set_position(7, 7);
        dec.push(&sys::read_available(r.as_raw_fd()));
        let mut got = Vec::new();
        while let Some(f) = dec.next_frame().unwrap() {
            got.push(f[0]);
        }
        assert_eq!(got, [7, 8, 9]);
        assert_eq!(dec.take_repeats(), 7);
        assert_eq!(dec.take_skipped(), 0);
    }

    #[test]
    fn limits_parse() {
        assert_eq!(
            Limits::parse("66, 200000"),
            Some(Limits {
                frames: 66,
                bytes: 200_000
            })
        );
        assert_eq!(Limits::parse("66"), None);
        assert_eq!(Limits::parse("x,1"), None);
    }
}
