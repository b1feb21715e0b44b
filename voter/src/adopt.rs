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
use crate::recovery::{peek_announcement, read_exact_by, read_exact_into, send_pipes, SpareLines};
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
    /// An awaited replica, rebound: its slot, and the replica.
    Replica(usize, Replica),
    /// An awaited replica's spare line.
    Spare(libc::pid_t, UnixStream),
    /// The spare line of a replica not awaited: dropped.
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
            match rebind(plan, conn, &mut awaited, deadline) {
                Ok(Taken::Replica(slot, replica)) => {
                    on_adopt(replica.pid, slot);
                    tracing::info!(replica = slot, pid = replica.pid, "adopted");
                    adopted.slots[slot] = Some(replica);
                }
                // The newest of each replica is kept: one made before its voter died leads
                // nowhere once the replica has rebound (it drops it then, and makes another).
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
/// peer's spare line (replica-rt's `restart`, "The spare line"), which says so instead.
fn rebind(
    plan: &VoterPlan,
    conn: UnixStream,
    awaited: &mut Vec<Awaited>,
    deadline: Instant,
) -> Result<Taken, String> {
    let pid = sys::peer_pid(conn.as_fd()).map_err(|e| format!("no peer credentials: {e}"))?;
    let Some(k) = awaited.iter().position(|a| a.entry.pid == pid) else {
        // The spare line of a replica that is not awaited (one that died with the predecessor,
        // say) is nobody's business: dropped without a word.
        if peek_announcement(&conn, pid) == Some(true) {
            return Ok(Taken::Stale);
        }
        // A fork child its predecessor was handing pipes to, or a stranger.
        return Err(format!("peer {pid} is not a replica the journal names"));
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
    Ok(Taken::Replica(
        slot,
        Replica::adopted(pid, pidfd, pipes, entry),
    ))
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
