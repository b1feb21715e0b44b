//! A voter that succeeds one that died takes its replicas over instead of starting new ones
//! (`plan.adopt`): the replicas its predecessor's journal names come back through the rebind
//! handshake (`contract::handshake::Rebind`) and get fresh pipes; what its predecessor had
//! taken off the inputs and not finished is replayed (see `journal.rs`).

use std::io;
use std::os::fd::{AsFd, AsRawFd, OwnedFd};
use std::os::unix::net::{UnixListener, UnixStream};
use std::time::Duration;

use replica_rt::contract::handshake::{
    Ready, Rebind, Spare, READY_MAGIC, REBIND_MAGIC, SPARE_MAGIC,
};
use replica_rt::sys;

use crate::clock::Instant;
use crate::journal::{self, SlotEntry};
use crate::park::{Parked, ParkedSet, ParkingLot};
use crate::plan::VoterPlan;
use crate::recovery::{read_exact_by, read_exact_into, send_pipes, spare_line, Line, SpareLines};
use crate::replica::{Replica, ReplicaPipes};

/// A slot whose replica did not come back.
pub(crate) struct Lost {
    pub(crate) slot: usize,
    pub(crate) pid: libc::pid_t,
    /// It was gone (`true`), or alive but did not rebind in time (killed).
    pub(crate) died: bool,
    /// Why it was killed, if not for being late (an unmodified program's replica whose pipes
    /// were not found parked).
    pub(crate) why: Option<&'static str>,
}

/// What the adoption found.
pub(crate) struct Adopted {
    pub(crate) slots: Vec<Option<Replica>>,
    pub(crate) lost: Vec<Lost>,
    /// Spare lines that came while the replicas were taken back (`recovery::SpareLines`).
    pub(crate) spares: SpareLines,
}

/// What a connection taken off the socket while adopting turned out to be.
enum Taken {
    /// An awaited replica, rebound: its slot, and the replica (boxed: the other variants are
    /// small).
    Replica(usize, Box<Replica>),
    /// A spare line of a replica awaited or taken back already.
    Spare(libc::pid_t, UnixStream),
    /// The spare line of a replica that is neither: dropped.
    Stale,
}

/// A replica named in the journal, alive, that has not rebound yet.
struct Awaited {
    slot: usize,
    entry: SlotEntry,
    pidfd: OwnedFd,
}

/// Takes over the replicas `table` names: each must connect within `restart_timeout_ms`.
/// `on_adopt(pid, slot)` runs for each one taken (scheduling settings).
pub(crate) fn replicas(
    plan: &VoterPlan,
    listener: &UnixListener,
    table: &[Option<SlotEntry>],
    mut on_adopt: impl FnMut(libc::pid_t, usize),
) -> Adopted {
    let mut adopted = Adopted {
        slots: (0..plan.replicas).map(|_| None).collect(),
        lost: Vec::new(),
        spares: SpareLines::default(),
    };
    let mut awaited = Vec::new();
    for (slot, entry) in table.iter().enumerate() {
        let Some(entry) = *entry else {
            adopted.lost.push(Lost {
                slot,
                pid: 0,
                died: true,
                why: None,
            });
            continue;
        };
        // The pidfd first: from then on the pid cannot be reused; then the start time says it
        // is still the process the journal named.
        match sys::pidfd_open(entry.pid) {
            Ok(pidfd) if journal::start_time(entry.pid) == Some(entry.start_time) => {
                awaited.push(Awaited { slot, entry, pidfd })
            }
            _ => adopted.lost.push(Lost {
                slot,
                pid: entry.pid,
                died: true,
                why: None,
            }),
        }
    }
    let deadline = Instant::now() + Duration::from_millis(plan.restart_timeout_ms);
    while !awaited.is_empty() {
        let now = Instant::now();
        if now >= deadline {
            break;
        }
        let mut fds = vec![libc::pollfd {
            fd: listener.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        }];
        fds.extend(awaited.iter().map(|a| libc::pollfd {
            fd: a.pidfd.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        }));
        if sys::ppoll(&mut fds, Some(deadline - now)).is_err() {
            continue;
        }
        // The dead first (in reverse, so that indices stay valid).
        for k in (1..fds.len()).rev() {
            if fds[k].revents != 0 {
                let gone = awaited.remove(k - 1);
                adopted.lost.push(Lost {
                    slot: gone.slot,
                    pid: gone.entry.pid,
                    died: true,
                    why: None,
                });
            }
        }
        if fds[0].revents == 0 {
            continue;
        }
        while let Ok((conn, _)) = listener.accept() {
            let rebound: Vec<libc::pid_t> = adopted.slots.iter().flatten().map(|r| r.pid).collect();
            match rebind(plan, conn, &mut awaited, &rebound, deadline) {
                Ok(Taken::Replica(slot, replica)) => {
                    on_adopt(replica.pid, slot);
                    tracing::info!(replica = slot, pid = replica.pid, "adopted");
                    adopted.slots[slot] = Some(*replica);
                }
                // The newest of each replica is kept: one made before its voter died leads
                // nowhere once the replica has rebound (it drops it then, and makes another,
                // which may come before the others are back: see `rebind`).
                Ok(Taken::Spare(pid, line)) => adopted.spares.keep(pid, line),
                Ok(Taken::Stale) => {}
                Err(why) => tracing::warn!("refused a connection while adopting: {why}"),
            }
        }
    }
    for late in awaited {
        // Stopped, or busy past the whole wait: it cannot be trusted with a round now.
        let _ = sys::pidfd_send_signal(late.pidfd.as_fd(), libc::SIGKILL);
        adopted.lost.push(Lost {
            slot: late.slot,
            pid: late.entry.pid,
            died: false,
            why: None,
        });
    }
    adopted
}

/// One rebind: the peer must be an awaited replica, and say so; it gets fresh pipes. Or the
/// peer's spare line (replica-rt's `restart`, "The spare line"), which says so instead: an
/// awaited replica's (made for the predecessor, left in the socket's backlog), or that of one
/// of the `rebound` already. A rebound replica makes its new line at its next moment between
/// rounds, and that can come before the others are back: one that had an answer to finish, or
/// frames left in its old pipe, answers at once. Dropping that line as stale left the replica
/// holding a line to nowhere, and its next fork child connecting without one (a CI run of
/// `voter_restart.rs`'s spare-line test, stop 50).
fn rebind(
    plan: &VoterPlan,
    conn: UnixStream,
    awaited: &mut Vec<Awaited>,
    rebound: &[libc::pid_t],
    deadline: Instant,
) -> Result<Taken, String> {
    let pid = sys::peer_pid(conn.as_fd()).map_err(|e| format!("no peer credentials: {e}"))?;
    let Some(k) = awaited.iter().position(|a| a.entry.pid == pid) else {
        // The spare line of a replica neither awaited nor rebound (one that died with the
        // predecessor, say) is nobody's business: dropped.
        return match spare_line(conn, rebound) {
            Line::Kept(pid, line) => Ok(Taken::Spare(pid, line)),
            Line::Stale => Ok(Taken::Stale),
            Line::Unannounced(why) => Err(why),
            // A fork child its predecessor was handing pipes to, or a stranger.
            Line::Not(_) => Err(format!("peer {pid} is not a replica the journal names")),
        };
    };
    // Magic and pid first: a spare line says no more, and waiting for a whole `Rebind` on it
    // would hold up the adoption until the deadline.
    let mut bytes = [0u8; Rebind::SIZE];
    let (head, rest) = bytes.split_at_mut(Spare::SIZE);
    read_exact_into(&conn, head, deadline).map_err(|e| format!("no Rebind from {pid}: {e}"))?;
    if head[..4] == SPARE_MAGIC.to_ne_bytes() {
        return Ok(Taken::Spare(pid, conn));
    }
    read_exact_into(&conn, rest, deadline).map_err(|e| format!("no Rebind from {pid}: {e}"))?;
    let hello = Rebind::from_bytes(bytes);
    if hello.magic != REBIND_MAGIC || hello.pid != pid {
        return Err(format!(
            "bad Rebind from {pid} (magic {:#x}, pid {})",
            hello.magic, hello.pid
        ));
    }
    let pipes = ReplicaPipes::new(plan).map_err(|e| format!("pipes for {pid}: {e}"))?;
    let pipes = send_pipes(&conn, pipes).map_err(|e| format!("sending pipes to {pid}: {e}"))?;
    let ready = read_exact_by::<{ Ready::SIZE }>(&conn, deadline)
        .map(Ready::from_bytes)
        .map_err(|e: io::Error| format!("no Ready from {pid}: {e}"))?;
    if ready.magic != READY_MAGIC || ready.pid != pid {
        return Err(format!("bad Ready from {pid}"));
    }
    let Awaited { slot, entry, pidfd } = awaited.remove(k);
    let mut replica = Replica::adopted(pid, pidfd, pipes, entry);
    replica.handler_before_answer = plan.preload.is_none();
    Ok(Taken::Replica(slot, Box::new(replica)))
}

/// Takes over an unmodified program's replicas (see `lines.rs`): they cannot rebind, so each
/// one the journal names comes back on the pipes its predecessor parked (`park.rs`), found
/// by slot, pid and start time. A replica named but not parked (its voter died in between)
/// has no pipes a successor could write to: it is killed, and its slot refilled. A parked set
/// the journal does not name belongs to a replica started by a voter that died before it
/// named it: that process, if it is still the one parked, is killed (nothing would ever end
/// its input). The parking queue keeps the sets taken (see [`ParkingLot::rotate`]).
pub(crate) fn parked_replicas(
    plan: &VoterPlan,
    park: &mut ParkingLot,
    found: &journal::Found,
    mut on_adopt: impl FnMut(libc::pid_t, usize),
) -> io::Result<Adopted> {
    let table = &found.slots;
    let named = |who: &Parked| {
        table
            .get(who.slot)
            .copied()
            .flatten()
            .is_some_and(|e| e.pid == who.pid && e.start_time == who.start_time)
    };
    let mut sets: Vec<Option<ParkedSet>> = (0..plan.replicas).map(|_| None).collect();
    // Without the parked sets every replica would be killed, its state lost: better to fail
    // (bootstrap tries another successor within the component's budget).
    let rotation = park
        .rotate(named)
        .map_err(|e| io::Error::new(e.kind(), format!("reading the parked pipes back: {e}")))?;
    for stray in rotation.dropped {
        kill_if_still(stray.pid, stray.start_time);
    }
    for set in rotation.kept {
        let slot = set.who.slot;
        if let Some(place) = sets.get_mut(slot) {
            *place = Some(set);
        }
    }
    let mut adopted = Adopted {
        slots: (0..plan.replicas).map(|_| None).collect(),
        lost: Vec::new(),
        spares: SpareLines::default(),
    };
    for (slot, entry) in table.iter().enumerate() {
        let lost = |pid, died, why| Lost {
            slot,
            pid,
            died,
            why,
        };
        let Some(entry) = *entry else {
            adopted.lost.push(lost(0, true, None));
            continue;
        };
        let pidfd = match sys::pidfd_open(entry.pid) {
            Ok(pidfd) if journal::start_time(entry.pid) == Some(entry.start_time) => pidfd,
            _ => {
                adopted.lost.push(lost(entry.pid, true, None));
                continue;
            }
        };
        let Some(set) = sets[slot].take() else {
            let _ = sys::pidfd_send_signal(pidfd.as_fd(), libc::SIGKILL);
            adopted.lost.push(lost(
                entry.pid,
                false,
                Some("its pipes were not found parked by the voter that died; killed"),
            ));
            continue;
        };
        let counts = found.lines.get(slot).copied().unwrap_or_default();
        match Replica::adopted_parked(plan, entry, pidfd, set.fds, counts) {
            Ok(replica) => {
                on_adopt(replica.pid, slot);
                tracing::info!(
                    replica = slot,
                    pid = replica.pid,
                    "adopted on its parked pipes"
                );
                adopted.slots[slot] = Some(replica);
            }
            Err((pidfd, e)) => {
                tracing::warn!(replica = slot, pid = entry.pid, error = %e, "cannot take over its parked pipes");
                let _ = sys::pidfd_send_signal(pidfd.as_fd(), libc::SIGKILL);
                adopted.lost.push(lost(
                    entry.pid,
                    false,
                    Some("its parked pipes could not be taken over; killed"),
                ));
            }
        }
    }
    Ok(adopted)
}

/// SIGKILL to `pid` if it is still the process that started at `start_time`.
fn kill_if_still(pid: libc::pid_t, start_time: u64) {
    if let Ok(pidfd) = sys::pidfd_open(pid) {
        if journal::start_time(pid) == Some(start_time) {
            tracing::info!(pid, "killing a replica whose voter died before naming it");
            let _ = sys::pidfd_send_signal(pidfd.as_fd(), libc::SIGKILL);
        }
    }
}

#[cfg(test)]
mod tests {
    use std::io::{IoSliceMut, Read, Write};
    use std::os::fd::{AsRawFd, RawFd};
    use std::path::Path;

    use nix::sys::socket::{recvmsg, ControlMessageOwned, MsgFlags};
    use replica_rt::contract::handshake::{FdTransfer, Ready, Rebind, Spare};
    use replica_rt::contract::handshake::{READY_MAGIC, REBIND_MAGIC, SPARE_MAGIC};
    use replica_rt::contract::{MAX_HANDED_FDS, MAX_PORTS};

    use super::*;
    use crate::journal::tests::plan;
    use crate::test_support::Sleeper;

    fn entry(pid: libc::pid_t) -> SlotEntry {
        SlotEntry {
            pid,
            start_time: journal::start_time(pid).expect("a live process's start time"),
            state_lost: false,
            proven: true,
            offsets: [0; MAX_PORTS],
        }
    }

    /// The replica's side of the rebind handshake: `Rebind`, the pipes (closed at once), `Ready`.
    fn rebind_as(me: libc::pid_t, socket: &Path) {
        let mut sock = UnixStream::connect(socket).unwrap();
        let hello = Rebind {
            magic: REBIND_MAGIC,
            pid: me,
            frames_taken: [0; MAX_PORTS],
            frames_sent: [0; MAX_PORTS],
        };
        sock.write_all(&hello.to_bytes()).unwrap();
        let mut transfer = [0u8; std::mem::size_of::<FdTransfer>()];
        let mut iov = [IoSliceMut::new(&mut transfer)];
        let mut space = nix::cmsg_space!([RawFd; MAX_HANDED_FDS]);
        let msg = recvmsg::<()>(
            sock.as_raw_fd(),
            &mut iov,
            Some(&mut space),
            MsgFlags::MSG_CMSG_CLOEXEC,
        )
        .unwrap();
        for cmsg in msg.cmsgs().unwrap() {
            if let ControlMessageOwned::ScmRights(fds) = cmsg {
                fds.into_iter()
                    .for_each(|fd| nix::unistd::close(fd).unwrap());
            }
        }
        let ready = Ready {
            magic: READY_MAGIC,
            pid: me,
            frames_sent: [0; MAX_PORTS],
        };
        sock.write_all(&ready.to_bytes()).unwrap();
    }

    /// A replica taken back makes its new spare line at its next moment between rounds, which
    /// can come while the successor still waits for another replica (stop 50's CI failure):
    /// the line is kept for the successor's first recovery, not dropped as a stale one. Here
    /// this test process is replica 0 (a thread speaks for it) and a `sleep` replica 1, which
    /// never rebinds and is killed once replica 0's line is in the socket's backlog.
    #[test]
    fn a_spare_line_made_while_another_replica_is_awaited_is_kept() {
        let socket = std::env::temp_dir().join(format!(
            "s3res-adopt-test-{}-{:?}.sock",
            std::process::id(),
            std::time::SystemTime::now()
        ));
        let listener = UnixListener::bind(&socket).unwrap();
        listener.set_nonblocking(true).unwrap();
        let late = Sleeper::start();
        let late_pid = late.pid();
        let me = std::process::id() as libc::pid_t;
        let table = [Some(entry(me)), Some(entry(late_pid))];
        let path = socket.clone();
        let replica = std::thread::spawn(move || {
            rebind_as(me, &path);
            let mut line = UnixStream::connect(&path).unwrap();
            let spare = Spare {
                magic: SPARE_MAGIC,
                pid: me,
            };
            line.write_all(&spare.to_bytes()).unwrap();
            // Connected and announced: the adoption ends at replica 1's death, which it sees
            // in the same wait as the line or after it.
            sys::kill(late_pid, libc::SIGKILL).unwrap();
            line
        });
        let mut adopted = replicas(&plan(), &listener, &table, |_, _| {});
        let mut line = replica.join().unwrap();
        drop(late);
        let _ = std::fs::remove_file(&socket);

        assert_eq!(adopted.slots[0].as_ref().map(|r| r.pid), Some(me));
        assert!(adopted.slots[1].is_none());
        let lost: Vec<_> = adopted.lost.iter().map(|l| (l.slot, l.died)).collect();
        assert_eq!(lost, [(1, true)]);
        let mut kept = adopted
            .spares
            .take(me)
            .expect("the spare line of a replica taken back was dropped");
        // It is that line, its announcement read: what one end writes, the other reads.
        line.write_all(b"hi").unwrap();
        let mut said = [0u8; 2];
        kept.read_exact(&mut said).unwrap();
        assert_eq!(&said, b"hi");
    }
}
