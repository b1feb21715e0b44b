//! A replica whose voter died takes fresh channels from the voter's successor (issue 13, item
//! 2; the handshake is `contract::handshake::Rebind`).
//!
//! The death shows as the end of an input without an `END` frame (the voter sends one before it
//! closes a replica's input on purpose), or as `EPIPE` on an output. Either way the port that
//! sees it calls [`rebind`]: connect to the voter's socket (bootstrap keeps it open across
//! voters, so the connection waits in its backlog while the successor starts), say who we are
//! and how many frames each port has taken and sent, receive fresh pipes and put them on the
//! port numbers, answer `Ready`. Then every port catches up on its next use (a generation
//! counter says a rebind happened): an input first takes the whole frames still in its old pipe
//! (read out here, before the pipe was replaced) and drops a cut one; an output precedes its
//! next frame with `RESUME n`, `n` that frame's number, so the new voter can line the stream
//! up. A successor that never comes (the system is ending: the socket's last holder gone, the
//! connection refused or reset) is the end of the input.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, PoisonError};
use std::time::Duration;

use crate::contract::handshake::{
    FdTransfer, Ready, Rebind, READY_MAGIC, REBIND_MAGIC, REBIND_TIMEOUT_MS, TRANSFER_MAGIC,
};
use crate::contract::{FIRST_PORT_FD, MAX_HANDED_FDS, MAX_PORTS};
use crate::restart::{self, Fd, RestartsHeld};
use crate::sys;

/// Rebinds so far in this process (a fork child inherits its donor's count with its ports).
static GENERATION: AtomicU64 = AtomicU64::new(0);

/// Data frames taken per input port, by port position (fd − 3).
static FRAMES_TAKEN: [AtomicU64; MAX_PORTS] = [const { AtomicU64::new(0) }; MAX_PORTS];

/// Which port positions are inputs (bit per position).
static INPUTS: AtomicU64 = AtomicU64::new(0);

/// Bytes read out of an input's old pipe at a rebind, by port position, for the port to take.
static LEFT_IN_OLD_PIPES: Mutex<Vec<(usize, Vec<u8>)>> = Mutex::new(Vec::new());

/// Rebinds so far: a port that saw fewer catches up.
pub(crate) fn generation() -> u64 {
    GENERATION.load(Ordering::Acquire)
}

/// An input port at `position` exists (its old pipe is read out at a rebind).
pub(crate) fn register_input(position: usize) {
    if position < MAX_PORTS {
        INPUTS.fetch_or(1 << position, Ordering::Relaxed);
    }
}

/// The input at `position` took one more data frame.
pub(crate) fn count_taken(position: usize, taken: u64) {
    if let Some(n) = FRAMES_TAKEN.get(position) {
        n.store(taken, Ordering::Relaxed);
    }
}

/// What was left in the old pipe of the input at `position` at the last rebind.
pub(crate) fn take_left_over(position: usize) -> Vec<u8> {
    let mut left = LEFT_IN_OLD_PIPES
        .lock()
        .unwrap_or_else(PoisonError::into_inner);
    match left.iter().position(|(p, _)| *p == position) {
        Some(k) => left.swap_remove(k).1,
        None => Vec::new(),
    }
}

/// Why a rebind did not happen.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum NoSuccessor {
    /// Not a replica, or no voter took the connection (the system is ending).
    Gone,
}

/// Takes fresh channels from the voter's successor; see the module docs.
pub(crate) fn rebind() -> Result<(), NoSuccessor> {
    rebind_within(Duration::from_millis(REBIND_TIMEOUT_MS))
}

fn rebind_within(timeout: Duration) -> Result<(), NoSuccessor> {
    // No fork in the middle: a child would start with half our channels.
    let _held = RestartsHeld::new();
    let deadline = std::time::Instant::now() + timeout;
    loop {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        if left.is_zero() {
            return Err(NoSuccessor::Gone);
        }
        // No connection at all: nobody holds the socket any more (the system is ending).
        let sock =
            restart::connect_voter(left, restart::Backlog::Wait).map_err(|()| NoSuccessor::Gone)?;
        match handshake(&sock) {
            Ok(()) => {
                drop::<Fd>(sock);
                tracing::info!("voter replaced: took fresh channels from its successor");
                // Our spare line led to the dead voter: a new one, for the successor, at the
                // next `recv` (after this round, once the successor has taken us all back).
                restart::renew_spare_line();
                // A stream replica's frames the dead voter may not have decided (`history`).
                crate::answers::resend_histories();
                return Ok(());
            }
            // The successor died in the middle of the handshake (killed again, say): our old
            // channels are untouched; wait for the next one in the socket's backlog.
            Err(Retry) => {
                drop::<Fd>(sock);
                std::thread::sleep(Duration::from_millis(5));
            }
        }
    }
}

/// A handshake that broke off before our channels were replaced.
struct Retry;

/// `Rebind`, the fresh pipes, `Ready` (see the module docs).
fn handshake(sock: &Fd) -> Result<(), Retry> {
    let hello = Rebind {
        magic: REBIND_MAGIC,
        pid: sys::getpid(),
        frames_taken: std::array::from_fn(|k| FRAMES_TAKEN[k].load(Ordering::Relaxed)),
        frames_sent: restart::frames_sent(),
    };
    restart::send_all(sock.0, &hello.to_bytes()).map_err(|()| Retry)?;
    let mut transfer = FdTransfer {
        magic: 0,
        count: 0,
        targets: [-1; MAX_HANDED_FDS],
    };
    let mut received = [-1 as libc::c_int; MAX_HANDED_FDS];
    let n = restart::recv_transfer(sock.0, &mut transfer, &mut received).map_err(|()| Retry)?;
    let fds = &received[..n];
    if transfer.magic != TRANSFER_MAGIC || transfer.count as usize != n {
        restart::close_all(fds);
        return Err(Retry);
    }
    let targets = &transfer.targets[..n];
    read_out_old_inputs(targets);
    if restart::place_fds(fds, targets).is_err() {
        return Err(Retry);
    }
    GENERATION.fetch_add(1, Ordering::Release);
    let ready = Ready {
        magic: READY_MAGIC,
        pid: sys::getpid(),
        frames_sent: restart::frames_sent(),
    };
    // The pipes are ours now; a voter that closed meanwhile will find us through them.
    let _ = restart::send_all(sock.0, &ready.to_bytes());
    Ok(())
}

/// Reads what the old pipes of the inputs among `targets` still hold (whole frames the dead
/// voter had written and we had not read yet), before they are replaced. Their writer is gone,
/// so each read ends at the end of the pipe; a pipe that still has a writer (it should not) is
/// read only as far as it holds bytes now.
fn read_out_old_inputs(targets: &[libc::c_int]) {
    let inputs = INPUTS.load(Ordering::Relaxed);
    let mut left = LEFT_IN_OLD_PIPES
        .lock()
        .unwrap_or_else(PoisonError::into_inner);
    for &fd in targets {
        let Ok(position) = usize::try_from(fd - FIRST_PORT_FD) else {
            continue;
        };
        if position >= MAX_PORTS || inputs & (1 << position) == 0 {
            continue;
        }
        let bytes = sys::read_available(fd);
        if bytes.is_empty() {
            continue;
        }
        match left.iter_mut().find(|(p, _)| *p == position) {
            // Rebound again before the port caught up (a successor that died in turn): what
            // its pipe held comes after what the one before held, whose cut frame goes.
            Some((_, earlier)) => {
                earlier.truncate(whole_frames_len(earlier));
                earlier.extend_from_slice(&bytes);
            }
            None => left.push((position, bytes)),
        }
    }
}

/// How many leading bytes of `bytes` are whole frames (data, `RESUME` or `END`): the rest is a
/// frame its writer died in the middle of.
fn whole_frames_len(bytes: &[u8]) -> usize {
    use crate::frame::{CONTROL_BIT, END, END_LEN, HEADER_LEN, RESUME, RESUME_LEN};
    let mut at = 0;
    while let Some(head) = bytes.get(at..at + HEADER_LEN) {
        let word = u32::from_le_bytes([head[0], head[1], head[2], head[3]]);
        let len = match word {
            RESUME => RESUME_LEN,
            END => END_LEN,
            w if w & CONTROL_BIT != 0 => return at,
            w => HEADER_LEN + w as usize,
        };
        if at + len > bytes.len() {
            return at;
        }
        at += len;
    }
    at
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::{encode_into, resume_frame};

    #[test]
    fn a_cut_frame_is_not_whole() {
        let mut bytes = resume_frame(3).to_vec();
        encode_into(b"abc", &mut bytes);
        let whole = bytes.len();
        encode_into(b"defgh", &mut bytes);
        assert_eq!(whole_frames_len(&bytes), bytes.len());
        assert_eq!(whole_frames_len(&bytes[..bytes.len() - 2]), whole);
        assert_eq!(whole_frames_len(&bytes[..whole + 2]), whole);
        assert_eq!(whole_frames_len(&[]), 0);
    }
}
