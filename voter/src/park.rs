//! Parking: a replica's pipes (the voter's ends) outlive the voter.
//!
//! Bootstrap makes a `socketpair(AF_UNIX, SOCK_SEQPACKET)` and keeps both ends; the voter
//! inherits them. To park a replica's fds the voter sends them as SCM_RIGHTS from `tx` into
//! `rx`'s receive queue: fds in flight stay open in the kernel for as long as the receiving
//! socket lives, and bootstrap's copy keeps it alive whatever happens to the voter. A
//! successor voter inherits the same two ends and reads the queue back.
//!
//! **The rule: at no instant may a live replica's fds exist only in this process's fd table**
//! (a SIGKILL there would close them, and the replica would see the end of its input). So the
//! queue is only ever read by *rotation*: `recvmsg(MSG_PEEK)` the head (Linux installs
//! duplicates of its fds and leaves it queued), decide, re-send a kept message to the tail,
//! and only then remove the head. A sentinel (no fds, a nonce of this rotation) sent first
//! marks where the rotation ends. A voter killed mid-rotation leaves a duplicate of the set it
//! was moving and its sentinel behind: the next rotation drops sentinels not its own and keeps
//! one message per (slot, pid, start time).
//!
//! Limits, from the kernel: a message in the queue is charged to the sending socket's send
//! buffer (about 270 small messages at the default 208 KiB), so the queue must be compacted
//! ([`ParkingLot::rotate`]) long before that; nothing else may read `rx` while a voter lives.

use std::collections::HashMap;
use std::io;
use std::mem::MaybeUninit;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, FromRawFd, OwnedFd, RawFd};

use replica_rt::sys;

/// The most fds a parked set may have (a replica has five pipe ends).
pub(crate) const MAX_PARKED_FDS: usize = 8;

/// At most this many messages are looked at in one rotation or release: the queue cannot hold
/// nearly as many (see the module doc), so reaching it means someone keeps writing into it.
const MAX_MESSAGES: usize = 4096;

/// "PARK", little-endian: the first word of every message this module sends.
const MAGIC: u32 = u32::from_le_bytes(*b"PARK");
const KIND_FDS: u32 = 0;
const KIND_SENTINEL: u32 = 1;
/// magic u32, kind u32, slot u32, pid i32, start_time u64, nonce u64; little-endian.
const HEADER_LEN: usize = 32;

/// What a parked message says, besides its fds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(crate) struct Parked {
    pub slot: usize,
    pub pid: libc::pid_t,
    /// The process's start time (`/proc/PID/stat` field 22), so a reused pid is not mistaken
    /// for the replica.
    pub start_time: u64,
}

/// One parked set read back: its header and the fds (duplicates now owned by this process),
/// in the order they were parked. The set stays parked; dropping these closes only the copies.
#[derive(Debug)]
pub(crate) struct ParkedSet {
    pub who: Parked,
    pub fds: Vec<OwnedFd>,
}

/// What one rotation found.
#[derive(Debug, Default)]
pub(crate) struct Rotation {
    /// The sets kept in the queue, in queue order, one per (slot, pid, start time).
    pub kept: Vec<ParkedSet>,
    /// The sets removed from the queue (their fds closed), one entry per (slot, pid, start
    /// time): a caller kills a replica process named here that is still running, as nothing
    /// could ever end its input again.
    pub dropped: Vec<Parked>,
}

/// The voter's two ends of bootstrap's parking socketpair.
#[derive(Debug)]
pub(crate) struct ParkingLot {
    tx: OwnedFd,
    rx: OwnedFd,
    /// Messages believed queued: exact after a rotation or release, counted up by parks.
    queued: usize,
    /// Rotations started, mixed into each sentinel's nonce: an earlier rotation of this voter
    /// that failed half-way left a sentinel that must read as foreign.
    rotations: u64,
}

impl ParkingLot {
    /// Takes over the two ends (sets both `O_NONBLOCK`: a voter never waits on the queue).
    /// A successor does not know how many messages its predecessor left: [`queued`] says 0
    /// until its first rotation.
    ///
    /// [`queued`]: ParkingLot::queued
    pub(crate) fn new(tx: OwnedFd, rx: OwnedFd) -> io::Result<ParkingLot> {
        sys::set_nonblocking(tx.as_fd(), true)?;
        sys::set_nonblocking(rx.as_fd(), true)?;
        Ok(ParkingLot {
            tx,
            rx,
            queued: 0,
            rotations: 0,
        })
    }

    /// Parks `fds` (1 to [`MAX_PARKED_FDS`] of them) for `who`: one `sendmsg`. `WouldBlock`
    /// means the queue is full (compact it with [`rotate`](ParkingLot::rotate)).
    pub(crate) fn park(&mut self, who: Parked, fds: &[BorrowedFd<'_>]) -> io::Result<()> {
        if fds.is_empty() || fds.len() > MAX_PARKED_FDS {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!(
                    "a parked set has 1 to {MAX_PARKED_FDS} fds, not {}",
                    fds.len()
                ),
            ));
        }
        let slot = u32::try_from(who.slot).map_err(|_| {
            io::Error::new(io::ErrorKind::InvalidInput, "slot does not fit the header")
        })?;
        let raw: Vec<RawFd> = fds.iter().map(|fd| fd.as_raw_fd()).collect();
        let header = encode(KIND_FDS, slot, who.pid, who.start_time, 0);
        send(self.tx.as_fd(), &header, &raw)?;
        self.queued += 1;
        Ok(())
    }

    /// Rotates the whole queue once (sentinel first). A message is kept (re-sent to the tail)
    /// when `keep(&who)` is true and no message for the same (slot, pid, start time) was kept
    /// earlier in this rotation; others are dropped (their fds closed). `keep` is asked once
    /// per distinct (slot, pid, start time), at its first message.
    ///
    /// Returns the kept sets, their fds duplicated into this process (for the caller to use or
    /// drop: the queue holds them either way), and the `Parked` of every dropped set that is
    /// not a duplicate of one seen before. Sentinels not this rotation's (left by a voter that
    /// died rotating) and malformed messages are dropped.
    ///
    /// On an error the rotation stops where it is, with the head still queued: nothing is
    /// lost, the next rotation finds this one's sentinel foreign and the re-sent sets
    /// duplicated, and cleans both up.
    pub(crate) fn rotate(&mut self, mut keep: impl FnMut(&Parked) -> bool) -> io::Result<Rotation> {
        self.rotations += 1;
        let nonce = sentinel_nonce(self.rotations);
        let me = sys::getpid();
        send(
            self.tx.as_fd(),
            &encode(KIND_SENTINEL, 0, me, 0, nonce),
            &[],
        )?;
        self.queued += 1;

        let mut rotation = Rotation::default();
        let mut decided: HashMap<Parked, bool> = HashMap::new();
        for _ in 0..MAX_MESSAGES {
            let head = match recv(self.rx.as_fd(), true) {
                Ok(head) => head,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    // Only a reader other than us takes messages off this queue.
                    tracing::warn!(
                        "the parking queue ran empty before this rotation's sentinel came back"
                    );
                    self.queued = rotation.kept.len();
                    return Ok(rotation);
                }
                Err(e) => return Err(e),
            };
            match head.parse() {
                Message::Sentinel { nonce: n, .. } if n == nonce => {
                    self.remove(&head)?;
                    // Everything before the sentinel came round: the queue is what was kept.
                    self.queued = rotation.kept.len();
                    return Ok(rotation);
                }
                Message::Sentinel { pid, .. } => {
                    tracing::debug!(pid, "dropping the sentinel of an unfinished rotation");
                }
                Message::Malformed(why) => {
                    tracing::warn!(
                        len = head.len,
                        why,
                        "dropping a malformed message from the parking queue"
                    );
                }
                Message::Unreadable(who) => {
                    // The fds could not all be installed here (the control buffer has room
                    // for any SCM_RIGHTS message, so: our fd table is full). Dropping it would
                    // close a live replica's pipes over a shortage of our own; leave it at the
                    // head and let the caller try again.
                    return Err(io::Error::other(format!(
                        "the parked set of slot {} (pid {}) could not be received whole \
                         (control data truncated: fd table full?)",
                        who.slot, who.pid
                    )));
                }
                Message::Fds(who) => match decided.get(&who) {
                    Some(_) => {
                        tracing::debug!(
                            slot = who.slot,
                            pid = who.pid,
                            "dropping a duplicate parked set"
                        );
                    }
                    None => {
                        let kept = keep(&who);
                        decided.insert(who, kept);
                        if kept {
                            // Re-sent before the head is removed: there is no instant at which
                            // the queue lacks this set.
                            let raw: Vec<RawFd> =
                                head.fds.iter().map(|fd| fd.as_raw_fd()).collect();
                            send(self.tx.as_fd(), &head.bytes[..head.len], &raw)?;
                            self.queued += 1;
                            self.remove(&head)?;
                            rotation.kept.push(ParkedSet { who, fds: head.fds });
                            continue;
                        }
                        rotation.dropped.push(who);
                    }
                },
            }
            self.remove(&head)?;
        }
        Err(io::Error::other(format!(
            "no end of the parking queue within {MAX_MESSAGES} messages"
        )))
    }

    /// Removes every message (closing all parked fds): the normal end, when the replicas must
    /// see the end of their input.
    pub(crate) fn release(&mut self) -> io::Result<()> {
        for _ in 0..MAX_MESSAGES {
            // No control buffer: the kernel closes the fds without installing them here.
            match recv(self.rx.as_fd(), false) {
                Ok(_) => self.queued = self.queued.saturating_sub(1),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    self.queued = 0;
                    return Ok(());
                }
                Err(e) => return Err(e),
            }
        }
        Err(io::Error::other(format!(
            "the parking queue did not run empty within {MAX_MESSAGES} messages"
        )))
    }

    /// Messages believed in the queue (the caller compacts it by rotating when it exceeds
    /// twice the replicas).
    pub(crate) fn queued(&self) -> usize {
        self.queued
    }

    /// Removes the head, which was just peeked as `head`. Its fds are closed by the kernel,
    /// never installed here.
    fn remove(&mut self, head: &Received) -> io::Result<()> {
        let gone = recv(self.rx.as_fd(), false)?;
        self.queued = self.queued.saturating_sub(1);
        if gone.bytes[..gone.len] != head.bytes[..head.len] {
            // Only possible with a second reader of the queue: what it took is lost to us.
            tracing::error!("the parking queue's head changed between peek and remove");
        }
        Ok(())
    }
}

/// A message of the queue, as far as its bytes and fds say.
enum Message {
    Fds(Parked),
    Sentinel {
        pid: libc::pid_t,
        nonce: u64,
    },
    /// A well-formed set whose fds did not all arrive (`MSG_CTRUNC`).
    Unreadable(Parked),
    Malformed(&'static str),
}

fn encode(kind: u32, slot: u32, pid: libc::pid_t, start_time: u64, nonce: u64) -> [u8; HEADER_LEN] {
    let mut h = [0u8; HEADER_LEN];
    h[0..4].copy_from_slice(&MAGIC.to_le_bytes());
    h[4..8].copy_from_slice(&kind.to_le_bytes());
    h[8..12].copy_from_slice(&slot.to_le_bytes());
    h[12..16].copy_from_slice(&pid.to_le_bytes());
    h[16..24].copy_from_slice(&start_time.to_le_bytes());
    h[24..32].copy_from_slice(&nonce.to_le_bytes());
    h
}

/// A nonce no other rotation has: this process's pid and the time, and the rotation count,
/// spread by the project's SplitMix64 so that nearby inputs give far-apart nonces.
fn sentinel_nonce(rotation: u64) -> u64 {
    let seed = sys::monotonic_ns() ^ ((sys::getpid() as u64) << 40);
    s3res_protocol::rng::derive(seed, rotation)
}

fn send(sock: BorrowedFd<'_>, bytes: &[u8], fds: &[RawFd]) -> io::Result<()> {
    loop {
        match sys::send_with_fds(sock, bytes, fds) {
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            r => return r,
        }
    }
}

/// Room for more payload than a header, so a longer message shows as too long.
const PAYLOAD_ROOM: usize = 64;

/// One message as `recvmsg` gave it.
struct Received {
    bytes: [u8; PAYLOAD_ROOM],
    len: usize,
    /// `msg_flags` (MSG_TRUNC, MSG_CTRUNC).
    flags: libc::c_int,
    fds: Vec<OwnedFd>,
}

impl Received {
    fn parse(&self) -> Message {
        if self.flags & libc::MSG_TRUNC != 0 || self.len != HEADER_LEN {
            return Message::Malformed("not a header's length");
        }
        let b = &self.bytes;
        let u32_at = |i: usize| u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        let u64_at = |i: usize| {
            let mut w = [0u8; 8];
            w.copy_from_slice(&b[i..i + 8]);
            u64::from_le_bytes(w)
        };
        if u32_at(0) != MAGIC {
            return Message::Malformed("bad magic");
        }
        let pid = u32_at(12) as libc::pid_t;
        match u32_at(4) {
            KIND_SENTINEL => Message::Sentinel {
                pid,
                nonce: u64_at(24),
            },
            KIND_FDS => {
                let who = Parked {
                    slot: u32_at(8) as usize,
                    pid,
                    start_time: u64_at(16),
                };
                if self.flags & libc::MSG_CTRUNC != 0 {
                    Message::Unreadable(who)
                } else if self.fds.is_empty() || self.fds.len() > MAX_PARKED_FDS {
                    Message::Malformed("a set of no fds, or of too many")
                } else {
                    Message::Fds(who)
                }
            }
            _ => Message::Malformed("unknown kind"),
        }
    }
}

/// Control buffer: room for the most fds one message can carry (SCM_MAX_FD, 253) and more, so
/// that `MSG_CTRUNC` on a peek can only mean the kernel failed to install them (our fd table
/// full), never a message too big for us. Aligned as `cmsghdr` requires.
#[repr(C, align(8))]
struct ControlBuf([u8; 4096]);

/// One non-blocking `recvmsg` from `sock`: with `peek`, the head stays queued and its fds are
/// duplicated into this process (close-on-exec); without, the head is removed and, as no
/// control buffer is given, its fds are released by the kernel without being installed here.
fn recv(sock: BorrowedFd<'_>, peek: bool) -> io::Result<Received> {
    let mut out = Received {
        bytes: [0; PAYLOAD_ROOM],
        len: 0,
        flags: 0,
        fds: Vec::new(),
    };
    let mut control = ControlBuf([0; 4096]);
    let mut iov = libc::iovec {
        iov_base: out.bytes.as_mut_ptr().cast(),
        iov_len: PAYLOAD_ROOM,
    };
    // SAFETY: msghdr is plain old data; all-zero is valid (no name, no control, no flags).
    let mut msg: libc::msghdr = unsafe { MaybeUninit::zeroed().assume_init() };
    msg.msg_iov = &mut iov;
    msg.msg_iovlen = 1;
    if peek {
        msg.msg_control = control.0.as_mut_ptr().cast();
        msg.msg_controllen = control.0.len() as _;
    }
    let flags = libc::MSG_DONTWAIT | libc::MSG_CMSG_CLOEXEC | if peek { libc::MSG_PEEK } else { 0 };
    let n = loop {
        // SAFETY: `msg` points at `iov` (PAYLOAD_ROOM writable bytes of `out.bytes`) and, for
        // a peek, at `control` (its full length, cmsghdr-aligned); all live across the call.
        let n = unsafe { libc::recvmsg(sock.as_raw_fd(), &mut msg, flags) };
        if n >= 0 {
            break n;
        }
        let e = io::Error::last_os_error();
        if e.kind() != io::ErrorKind::Interrupted {
            return Err(e);
        }
    };
    out.len = n as usize;
    out.flags = msg.msg_flags;
    // Taken even when MSG_CTRUNC is set: the kernel may have installed some of the fds.
    out.fds = installed_fds(&msg);
    Ok(out)
}

/// The fds `recvmsg` installed in this process (SCM_RIGHTS of `msg`), owned from here on.
fn installed_fds(msg: &libc::msghdr) -> Vec<OwnedFd> {
    let mut fds = Vec::new();
    if msg.msg_control.is_null() {
        return fds;
    }
    // SAFETY: `msg` was filled in by recvmsg; CMSG_FIRSTHDR stays within msg_controllen.
    let mut cmsg = unsafe { libc::CMSG_FIRSTHDR(msg) };
    while !cmsg.is_null() {
        // SAFETY: CMSG_FIRSTHDR/CMSG_NXTHDR return either null or a header inside the buffer.
        let hdr = unsafe { &*cmsg };
        if hdr.cmsg_level == libc::SOL_SOCKET && hdr.cmsg_type == libc::SCM_RIGHTS {
            // SAFETY: CMSG_LEN(0) is a pure size computation.
            let head = unsafe { libc::CMSG_LEN(0) } as usize;
            let count = (hdr.cmsg_len as usize).saturating_sub(head) / size_of::<libc::c_int>();
            // SAFETY: the header is valid, so its data follows it within the buffer.
            let data = unsafe { libc::CMSG_DATA(cmsg) }.cast::<libc::c_int>();
            for i in 0..count {
                // SAFETY: `i` indexes the data of this header (cmsg_len covers it);
                // read_unaligned because cmsg data promises no alignment for its contents.
                let fd = unsafe { data.add(i).read_unaligned() };
                // SAFETY: the kernel installed this fd in our table for this very call;
                // nothing else knows of it, so it is ours to own and close.
                fds.push(unsafe { OwnedFd::from_raw_fd(fd) });
            }
        }
        // SAFETY: `cmsg` is a valid header of `msg`.
        cmsg = unsafe { libc::CMSG_NXTHDR(msg, cmsg) };
    }
    fds
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lot, plus "bootstrap's" copies of both ends, which keep the queue alive and let a
    /// test write into it by hand.
    fn lot() -> (ParkingLot, OwnedFd, OwnedFd) {
        let (tx, rx) = sys::seqpacket_pair().unwrap();
        let (tx2, rx2) = (tx.try_clone().unwrap(), rx.try_clone().unwrap());
        (ParkingLot::new(tx, rx).unwrap(), tx2, rx2)
    }

    fn who(slot: usize, pid: libc::pid_t) -> Parked {
        Parked {
            slot,
            pid,
            start_time: 1000 + pid as u64,
        }
    }

    fn keep_all(_: &Parked) -> bool {
        true
    }

    /// A pipe whose read end does not block: an empty pipe reads WouldBlock, a closed one 0.
    fn pipe() -> (OwnedFd, OwnedFd) {
        let (r, w) = sys::pipe().unwrap();
        sys::set_nonblocking(r.as_fd(), true).unwrap();
        (r, w)
    }

    fn is_eof(r: &OwnedFd) -> bool {
        match sys::read(r.as_fd(), &mut [0u8; 16]) {
            Ok(0) => true,
            Ok(_) => panic!("unexpected bytes"),
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => false,
            Err(e) => panic!("read: {e}"),
        }
    }

    /// Passes `bytes` through `w` and back out of `r`.
    fn carries(w: BorrowedFd<'_>, r: BorrowedFd<'_>, bytes: &[u8]) {
        assert_eq!(sys::write(w, bytes).unwrap(), bytes.len());
        let mut buf = [0u8; 64];
        let n = sys::read(r, &mut buf).unwrap();
        assert_eq!(&buf[..n], bytes);
    }

    /// Messages in the queue, counted by taking them all off (through bootstrap's copy).
    fn drain(rx: &OwnedFd) -> usize {
        let mut n = 0;
        while recv(rx.as_fd(), false).is_ok() {
            n += 1;
        }
        n
    }

    #[test]
    fn parked_sets_come_back_usable_and_stay_parked() {
        let (mut lot, _tx, _rx) = lot();
        // Per slot: `a` written through the parked write end, `b` read through the parked
        // read end.
        let pipes: Vec<_> = (0..2).map(|_| (pipe(), pipe())).collect();
        for (slot, ((_, a_w), (b_r, _))) in pipes.iter().enumerate() {
            lot.park(who(slot, 10 + slot as i32), &[a_w.as_fd(), b_r.as_fd()])
                .unwrap();
        }
        assert_eq!(lot.queued(), 2);
        for round in 0..2 {
            let rotation = lot.rotate(keep_all).unwrap();
            assert!(rotation.dropped.is_empty());
            assert_eq!(rotation.kept.len(), 2, "round {round}");
            for (slot, set) in rotation.kept.iter().enumerate() {
                assert_eq!(set.who, who(slot, 10 + slot as i32));
                assert_eq!(set.fds.len(), 2);
                let ((a_r, _), (_, b_w)) = &pipes[slot];
                carries(
                    set.fds[0].as_fd(),
                    a_r.as_fd(),
                    b"through the parked write end",
                );
                carries(
                    b_w.as_fd(),
                    set.fds[1].as_fd(),
                    b"out of the parked read end",
                );
            }
            assert_eq!(lot.queued(), 2);
        }
    }

    #[test]
    fn a_rotation_drops_duplicates_and_stale_sets() {
        let (mut lot, _tx, rx) = lot();
        let (stale_r, stale_w) = pipe();
        let (live_r, live_w) = pipe();
        lot.park(who(0, 10), &[stale_w.as_fd()]).unwrap();
        lot.park(who(0, 11), &[live_w.as_fd()]).unwrap();
        lot.park(who(0, 11), &[live_w.as_fd()]).unwrap();
        drop((stale_w, live_w));
        let mut asked = Vec::new();
        let rotation = lot
            .rotate(|p| {
                asked.push(p.pid);
                p.pid == 11
            })
            .unwrap();
        assert_eq!(asked, [10, 11], "asked once per set");
        assert_eq!(rotation.kept.len(), 1);
        assert_eq!(rotation.kept[0].who, who(0, 11));
        assert_eq!(rotation.dropped, [who(0, 10)]);
        assert_eq!(lot.queued(), 1);
        drop(rotation);
        // The stale set's write end is gone with it; the live one is still held by the queue.
        assert!(is_eof(&stale_r));
        assert!(!is_eof(&live_r));
        assert_eq!(drain(&rx), 1);
    }

    #[test]
    fn a_foreign_sentinel_is_dropped_and_does_not_end_the_rotation() {
        let (mut lot, tx, rx) = lot();
        let (_r0, w0) = pipe();
        let (_r1, w1) = pipe();
        lot.park(who(0, 10), &[w0.as_fd()]).unwrap();
        // Left by a voter killed mid-rotation.
        send(
            tx.as_fd(),
            &encode(KIND_SENTINEL, 0, 4242, 0, 0xdead_beef),
            &[],
        )
        .unwrap();
        lot.park(who(1, 20), &[w1.as_fd()]).unwrap();
        let rotation = lot.rotate(keep_all).unwrap();
        let kept: Vec<_> = rotation.kept.iter().map(|s| s.who).collect();
        assert_eq!(kept, [who(0, 10), who(1, 20)]);
        assert!(rotation.dropped.is_empty());
        assert_eq!(lot.queued(), 2);
        assert_eq!(drain(&rx), 2, "only the two sets are left");
    }

    #[test]
    fn release_closes_the_parked_pipes() {
        let (mut lot, _tx, rx) = lot();
        let (r, w) = pipe();
        lot.park(who(0, 10), &[w.as_fd()]).unwrap();
        drop(w);
        // The queue alone keeps the write end open.
        assert!(!is_eof(&r));
        lot.release().unwrap();
        assert_eq!(lot.queued(), 0);
        assert!(is_eof(&r));
        assert_eq!(drain(&rx), 0);
        assert!(lot.rotate(keep_all).unwrap().kept.is_empty());
    }

    #[test]
    fn malformed_messages_are_dropped() {
        let (mut lot, tx, rx) = lot();
        let (_r, w) = pipe();
        lot.park(who(0, 10), &[w.as_fd()]).unwrap();
        send(tx.as_fd(), &[1, 2, 3], &[]).unwrap();
        // A set's header with no fds, and a set with too many.
        send(tx.as_fd(), &encode(KIND_FDS, 1, 20, 0, 0), &[]).unwrap();
        let nine = vec![w.as_raw_fd(); MAX_PARKED_FDS + 1];
        send(tx.as_fd(), &encode(KIND_FDS, 2, 30, 0, 0), &nine).unwrap();
        let mut bad_magic = encode(KIND_FDS, 3, 40, 0, 0);
        bad_magic[0] ^= 1;
        send(tx.as_fd(), &bad_magic, &[w.as_raw_fd()]).unwrap();
        let rotation = lot.rotate(keep_all).unwrap();
        let kept: Vec<_> = rotation.kept.iter().map(|s| s.who).collect();
        assert_eq!(kept, [who(0, 10)]);
        assert!(rotation.dropped.is_empty());
        assert_eq!(drain(&rx), 1);
    }

    #[test]
    fn a_successor_finds_what_a_dead_voter_parked() {
        let (mut lot, tx, rx) = lot();
        let (r, w) = pipe();
        lot.park(who(2, 77), &[w.as_fd()]).unwrap();
        drop(w);
        // The voter dies: its ends and everything in its fd table close.
        drop(lot);
        assert!(!is_eof(&r));
        let mut successor = ParkingLot::new(tx, rx).unwrap();
        let rotation = successor.rotate(keep_all).unwrap();
        assert_eq!(rotation.kept.len(), 1);
        assert_eq!(rotation.kept[0].who, who(2, 77));
        carries(rotation.kept[0].fds[0].as_fd(), r.as_fd(), b"still there");
    }

    #[test]
    fn a_set_of_no_fds_or_too_many_is_refused() {
        let (mut lot, _tx, _rx) = lot();
        let (_r, w) = pipe();
        assert!(lot.park(who(0, 1), &[]).is_err());
        let nine = vec![w.as_fd(); MAX_PARKED_FDS + 1];
        assert!(lot.park(who(0, 1), &nine).is_err());
        assert_eq!(lot.queued(), 0);
    }
}
