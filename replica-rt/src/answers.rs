//! Answering a replayed round again, from the frames already sent.
//!
//! A voter that is restarted in the middle of a round does not know which replicas took the
//! round's input, nor whether their answers reached the voter that died. So it replays the
//! round: `RESUME k` and input frame `k` again on every replica's input (see
//! [`crate::frame`]). A replica that already took frame `k` must not run it a second time —
//! its state would move on twice — but its answer is wanted again. The input port's decoder
//! drops the repeat, and this module re-sends, on every output that answered frame `k`, the
//! frame it sent, behind a `RESUME` that gives that frame's number on the output, so that the
//! voter can tell the answer from what was already in the pipe.
//!
//! Each output port of a replica registers its last frame here (shared with the port, so
//! nothing is copied per frame). "Answered frame `k`" is "sent after frame `k` was taken": a
//! process-wide step counter orders takes and sends. That is exact for the reactive contract
//! (one frame on each output per round, sent before the next input is taken).

use std::io;
use std::os::fd::{BorrowedFd, RawFd};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError, Weak};

use crate::frame::{resume_frame, FrameBuf};
use crate::history::History;
use crate::restart;

/// Orders every frame taken and every frame sent in this process.
static STEP: AtomicU64 = AtomicU64::new(0);

/// The next step: called once per frame taken and once per frame sent.
pub(crate) fn step() -> u64 {
    STEP.fetch_add(1, Ordering::Relaxed) + 1
}

/// The last whole frame (length word and payload, as written) an output sent: the port's send
/// buffer itself.
#[derive(Debug, Default)]
pub(crate) struct LastFrame {
    pub(crate) bytes: FrameBuf,
    /// The step at which it was sent (0: nothing sent yet).
    pub(crate) step: u64,
    /// Frames this port has sent: the last one is number `sent - 1` on its channel. A fork
    /// child inherits it with the port, as it inherits the channel's count.
    pub(crate) sent: u64,
    /// A stream replica's frames its voter may not have decided (see `history`).
    pub(crate) history: Option<History>,
}

/// An output port as this module sees it.
struct Registered {
    fd: RawFd,
    last: Weak<Mutex<LastFrame>>,
}

static OUTPUTS: Mutex<Vec<Registered>> = Mutex::new(Vec::new());

/// Registers a replica's output port: its last frame is sent again when the round it answered
/// is replayed.
pub(crate) fn register(fd: RawFd, last: &Arc<Mutex<LastFrame>>) {
    let mut outputs = OUTPUTS.lock().unwrap_or_else(PoisonError::into_inner);
    outputs.retain(|o| o.last.strong_count() > 0);
    outputs.push(Registered {
        fd,
        last: Arc::downgrade(last),
    });
}

/// The input frame taken at step `taken` was replayed: sends again every output's frame sent
/// after it, each behind `RESUME n` with its number `n` on that output. Returns how many
/// frames were sent again.
pub(crate) fn answer_again(taken: u64) -> io::Result<usize> {
    let outputs = OUTPUTS.lock().unwrap_or_else(PoisonError::into_inner);
    let mut again = 0;
    let mut bytes = Vec::new();
    for out in outputs.iter() {
        let Some(last) = out.last.upgrade() else {
            continue;
        };
        let last = last.lock().unwrap_or_else(PoisonError::into_inner);
        if last.step <= taken {
            continue;
        }
        bytes.clear();
        bytes.extend_from_slice(&resume_frame(last.sent.saturating_sub(1)));
        bytes.extend_from_slice(last.bytes.as_slice());
        // One write for both, and no fork in the middle of it (as for `OutPort::send`).
        let _held = restart::RestartsHeld::new();
        // SAFETY: `out.fd` is the fd of a live `OutPort` (its `LastFrame` was upgraded above,
        // and the port owns both), so it is open for as long as this borrow is used.
        let fd = unsafe { BorrowedFd::borrow_raw(out.fd) };
        crate::port::write_all(fd, &bytes)?;
        again += 1;
    }
    Ok(again)
}

/// After a rebind: every output that keeps a history sends it to its fresh pipe (see
/// `history`). An output whose frame is being sent by this thread right now (its lock held:
/// the send that met the voter's death) sends its own, from `OutPort::send`.
pub(crate) fn resend_histories() {
    let outputs = OUTPUTS.lock().unwrap_or_else(PoisonError::into_inner);
    for out in outputs.iter() {
        let Some(last) = out.last.upgrade() else {
            continue;
        };
        let Ok(last) = last.try_lock() else {
            continue;
        };
        let Some(history) = last.history.as_ref() else {
            continue;
        };
        // SAFETY: `out.fd` is the fd of a live `OutPort` (its `LastFrame` was upgraded above,
        // and the port owns both), so it is open for as long as this borrow is used.
        let fd = unsafe { BorrowedFd::borrow_raw(out.fd) };
        if let Err(e) = history.resend(fd) {
            tracing::warn!(fd = out.fd, error = %e, "could not send the output history to the new voter");
        }
    }
}

/// Whether `fd` is an output this module would answer on (for tests).
#[cfg(test)]
fn registered(fd: RawFd) -> bool {
    let outputs = OUTPUTS.lock().unwrap_or_else(PoisonError::into_inner);
    outputs
        .iter()
        .any(|o| o.fd == fd && o.last.strong_count() > 0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::FrameDecoder;
    use crate::{sys, InPort, OutPort};
    use std::os::fd::{AsFd, AsRawFd};

    /// A replica's round, replayed: the input is not taken twice and the answer comes again,
    /// behind a resume that the reader uses to drop what it already has.
    #[test]
    fn a_replayed_round_is_answered_again_and_not_run_twice() {
        let (in_r, in_w) = sys::pipe().unwrap();
        let (out_r, out_w) = sys::pipe().unwrap();
        let mut input = InPort::new("in".into(), in_r, 64, false);
        let mut output = OutPort::new("out".into(), out_w, 64, true);
        assert!(registered(output.as_raw_fd()));

        let mut to_replica = Vec::new();
        for (i, payload) in [&b"a"[..], b"b"].iter().enumerate() {
            to_replica.clear();
            crate::frame::encode_into(payload, &mut to_replica);
            crate::port::write_all(in_w.as_fd(), &to_replica).unwrap();
            let got = input.recv().unwrap().unwrap().to_vec();
            output.send(&[got[0], i as u8]).unwrap();
        }
        // The round of frame 1 replayed, then frame 2.
        to_replica.clear();
        to_replica.extend_from_slice(&resume_frame(1));
        crate::frame::encode_into(b"b", &mut to_replica);
        crate::frame::encode_into(b"c", &mut to_replica);
        crate::port::write_all(in_w.as_fd(), &to_replica).unwrap();
        let got = input.recv().unwrap().unwrap().to_vec();
        assert_eq!(got, b"c", "the repeat of frame 1 was dropped");
        output.send(&[got[0], 2]).unwrap();
        drop(output);

        let mut dec = FrameDecoder::resuming(64);
        let mut raw = Vec::new();
        let mut chunk = [0u8; 256];
        loop {
            let n = sys::read(out_r.as_fd(), &mut chunk).unwrap();
            if n == 0 {
                break;
            }
            raw.extend_from_slice(&chunk[..n]);
        }
        dec.push(&raw);
        let mut frames = Vec::new();
        while let Some(f) = dec.next_frame().unwrap() {
            frames.push(f.to_vec());
        }
        assert_eq!(
            frames,
            [b"a\x00".to_vec(), b"b\x01".to_vec(), b"c\x02".to_vec()]
        );
        assert_eq!(dec.take_repeats(), 1, "the answer to frame 1 came twice");
        // Exactly: a, b, RESUME 1, b again, c.
        let mut expected = Vec::new();
        crate::frame::encode_into(b"a\x00", &mut expected);
        crate::frame::encode_into(b"b\x01", &mut expected);
        expected.extend_from_slice(&resume_frame(1));
        crate::frame::encode_into(b"b\x01", &mut expected);
        crate::frame::encode_into(b"c\x02", &mut expected);
        assert_eq!(raw, expected);
    }
}
