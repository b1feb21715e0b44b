//! The frame decoder (`s3res_protocol::frame::FrameDecoder`), driven by arbitrary sequences of
//! pushes, reads into its spare room, decodes, hand-overs and ends of stream, and checked
//! against a plain model of the format: whatever the bytes and however they are split, it
//! returns the frames the model finds, refuses an oversized length, and never panics or
//! allocates beyond what it was given. A resuming decoder is checked against the model's
//! plain reading of resume frames: repeats dropped, each frame returned once, and nothing
//! after an end frame.
#![no_main]

use arbitrary::Arbitrary;
use libfuzzer_sys::fuzz_target;
use s3res_protocol::frame::{
    resume_frame, FrameDecoder, FrameError, CONTROL_BIT, END, HEADER_LEN, RESUME, RESUME_LEN,
};

#[derive(Debug, Arbitrary)]
enum Op {
    Push(Vec<u8>),
    /// `spare(want)`, fill `filled` bytes of it (at most `want`) with `byte`, `commit`.
    Read {
        want: u16,
        filled: u16,
        byte: u8,
    },
    /// A resume frame announcing frame `next` (small, so that repeats and gaps both occur).
    Resume(u8),
    Next,
    /// `next_frame_into` one of two buffers, which trade places with the decoder's storage.
    NextInto(bool),
    Take,
    Finish,
}

#[derive(Debug, Arbitrary)]
struct Input {
    max: u16,
    resuming: bool,
    ops: Vec<Op>,
}

/// The format, read the simple way.
struct Model {
    max: usize,
    resuming: bool,
    bytes: Vec<u8>,
    at: usize,
    next: u64,
    taken: u64,
    /// An end frame was read (a resuming channel's writer ended it on purpose): the stream
    /// is over, and what came with or after it is never decoded.
    ended: bool,
}

impl Model {
    fn next(&mut self) -> Result<Option<Vec<u8>>, FrameError> {
        loop {
            if self.ended {
                return Ok(None);
            }
            let avail = &self.bytes[self.at..];
            if avail.len() < HEADER_LEN {
                return Ok(None);
            }
            let word = u32::from_le_bytes(avail[..4].try_into().unwrap());
            if self.resuming && word & CONTROL_BIT != 0 {
                if word == END {
                    self.at = self.bytes.len();
                    self.ended = true;
                    return Ok(None);
                }
                if word != RESUME {
                    return Err(FrameError::UnknownControl { word });
                }
                if avail.len() < RESUME_LEN {
                    return Ok(None);
                }
                self.next = u64::from_le_bytes(avail[HEADER_LEN..RESUME_LEN].try_into().unwrap());
                self.taken = self.taken.max(self.next);
                self.at += RESUME_LEN;
                continue;
            }
            let len = word as usize;
            if len > self.max {
                return Err(FrameError::Oversized { len, max: self.max });
            }
            if avail.len() < HEADER_LEN + len {
                return Ok(None);
            }
            let frame = avail[HEADER_LEN..HEADER_LEN + len].to_vec();
            self.at += HEADER_LEN + len;
            let index = self.next;
            self.next += 1;
            if index >= self.taken {
                self.taken = self.next;
                return Ok(Some(frame));
            }
        }
    }
}

fuzz_target!(|input: Input| {
    let max = usize::from(input.max);
    let mut dec = if input.resuming {
        FrameDecoder::resuming(max)
    } else {
        FrameDecoder::new(max)
    };
    let mut pool = [Vec::new(), Vec::new()];
    let mut model = Model {
        max,
        resuming: input.resuming,
        bytes: Vec::new(),
        at: 0,
        next: 0,
        taken: 0,
        ended: false,
    };
    for op in input.ops {
        match op {
            Op::Push(bytes) => {
                dec.push(&bytes);
                model.bytes.extend_from_slice(&bytes);
            }
            Op::Read { want, filled, byte } => {
                let (want, filled) = (usize::from(want), usize::from(filled.min(want)));
                let spare = dec.spare(want);
                assert_eq!(spare.len(), want);
                spare[..filled].fill(byte);
                dec.commit(want, filled);
                model.bytes.extend(std::iter::repeat(byte).take(filled));
            }
            Op::Resume(next) => {
                let bytes = resume_frame(u64::from(next));
                dec.push(&bytes);
                model.bytes.extend_from_slice(&bytes);
            }
            Op::Next => {
                let waiting = dec.has_frame();
                let want = model.next();
                let got = dec.next_frame().map(|f| f.map(<[u8]>::to_vec));
                assert_eq!(got, want);
                assert_eq!(dec.taken(), model.taken);
                assert_eq!(waiting, !matches!(got, Ok(None)));
            }
            Op::NextInto(which) => {
                let waiting = dec.has_frame();
                let want = model.next();
                let into = &mut pool[usize::from(which)];
                let got = dec
                    .next_frame_into(into)
                    .map(|at| at.map(|at| into[at].to_vec()));
                assert_eq!(got, want);
                assert_eq!(dec.taken(), model.taken);
                assert_eq!(waiting, !matches!(got, Ok(None)));
            }
            Op::Take => {
                assert_eq!(dec.take_pending(), model.bytes[model.at..].to_vec());
                model.bytes.clear();
                model.at = 0;
            }
            Op::Finish => {
                let rest = model.bytes.len() - model.at;
                assert_eq!(dec.finish().is_ok(), model.ended || rest == 0);
            }
        }
        assert_eq!(dec.pending(), model.bytes.len() - model.at);
    }
});
