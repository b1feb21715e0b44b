//! Recovery with a healthy donor (S³RES §3.1, §4.4): the donor forks itself on our signal, and
//! its child takes the faulty replica's place with state intact.
//!
//! The sequence, each step bounded so that a dead or stuck donor cannot hang the voter:
//! 1. read back what the donor has written but we have not decoded yet, and take back the
//!    input still buffered in its pipes (the child would not see it otherwise);
//! 2. send the donor [`signals::RESTART`]; its handler forks;
//! 3. accept the child on our Unix socket, only if `SO_PEERCRED` says its parent is the donor;
//! 4. send it fresh pipes by `SCM_RIGHTS`, which it puts on the donor's fd numbers;
//! 5. wait for its `Ready`;
//! 6. give the taken-back input to both, and give the child a copy of the donor's undecoded
//!    output bytes, so that both streams continue from the same point.

use std::io::{self, Read};
use std::os::fd::{AsFd, AsRawFd, OwnedFd, RawFd};
use std::os::unix::net::{UnixListener, UnixStream};
use std::time::{Duration, Instant};

use replica_rt::contract::handshake::{FdTransfer, Ready, READY_MAGIC, TRANSFER_MAGIC};
use replica_rt::contract::{signals, MAX_PORTS};
use replica_rt::sys;
use thiserror::Error;

use crate::channel::drain;
use crate::plan::VoterPlan;
use crate::replica::{Replica, ReplicaPipes};

#[derive(Debug, Error)]
pub enum RecoveryError {
    #[error("donor (pid {0}) died during the recovery")]
    DonorDied(libc::pid_t),
    #[error("donor's child did not connect within {0:?}")]
    ConnectTimeout(Duration),
    #[error("new replica (pid {0}) did not confirm its pipes in time")]
    ReadyTimeout(libc::pid_t),
    #[error("new replica sent a bad confirmation: {0}")]
    BadReady(String),
    #[error("{what}: {source}")]
    Io {
        what: &'static str,
        #[source]
        source: io::Error,
    },
}

fn io_err(what: &'static str) -> impl FnOnce(io::Error) -> RecoveryError {
    move |source| RecoveryError::Io { what, source }
}

/// Makes a copy of `donor` by fork. On success the donor's pipes have their taken-back input
/// restored and the returned replica is ready to be put in the faulty replica's slot.
pub fn fork_from(
    plan: &VoterPlan,
    listener: &UnixListener,
    donor: &mut Replica,
) -> Result<Replica, RecoveryError> {
    let timeout = Duration::from_millis(plan.restart_timeout_ms);
    let deadline = Instant::now() + timeout;

    // 1. Output the donor already wrote belongs to both; input it has not read goes to both.
    for out in &mut donor.outputs {
        out.fill().map_err(io_err("reading the donor's output"))?;
    }
    let mut taken_back = Vec::with_capacity(donor.inputs.len());
    for input in &donor.inputs {
        taken_back.push(drain(input.read_end.as_fd()).map_err(io_err("taking back input"))?);
    }

    // 2. Ask the donor to fork.
    let signalled = sys::pidfd_send_signal(donor.pidfd.as_fd(), signals::RESTART);
    let result = signalled
        .map_err(io_err("signalling the donor"))
        .and_then(|()| accept_child(listener, donor, deadline, timeout))
        .and_then(|(conn, child_pid, child_pidfd)| {
            hand_over_pipes(
                plan,
                conn,
                child_pid,
                child_pidfd.try_clone().map_err(io_err("dup"))?,
                deadline,
            )
            .inspect_err(|_| {
                // The child exists but will never be used: do not leave it behind.
                let _ = sys::pidfd_send_signal(child_pidfd.as_fd(), libc::SIGKILL);
            })
        });

    // 6. Whatever happened, the donor gets its input back.
    for (input, bytes) in donor.inputs.iter_mut().zip(&taken_back) {
        input.writer.prepend_raw(bytes);
        let _ = input.writer.flush();
    }
    let mut child = result?;
    for ((child_in, donor_in), bytes) in child.inputs.iter_mut().zip(&donor.inputs).zip(&taken_back)
    {
        // The donor's queue now starts with `bytes`; the child needs exactly the same stream.
        debug_assert!(donor_in.writer.unwritten().starts_with(bytes));
        child_in.writer.queue_raw(donor_in.writer.unwritten());
        let _ = child_in.writer.flush();
    }
    for (child_out, donor_out) in child.outputs.iter_mut().zip(&mut donor.outputs) {
        let partial = donor_out.decoder.take_pending();
        donor_out.decoder.push(&partial);
        child_out.decoder.push(&partial);
    }
    Ok(child)
}

/// 3. Waits for the donor's child to connect; refuses anyone else.
fn accept_child(
    listener: &UnixListener,
    donor: &Replica,
    deadline: Instant,
    timeout: Duration,
) -> Result<(UnixStream, libc::pid_t, OwnedFd), RecoveryError> {
    loop {
        let now = Instant::now();
        if now >= deadline {
            return Err(RecoveryError::ConnectTimeout(timeout));
        }
        let mut fds = [
            libc::pollfd {
                fd: listener.as_raw_fd(),
                events: libc::POLLIN,
                revents: 0,
            },
            libc::pollfd {
                fd: donor.pidfd.as_raw_fd(),
                events: libc::POLLIN,
                revents: 0,
            },
        ];
        sys::ppoll(&mut fds, Some(deadline - now)).map_err(io_err("waiting for the child"))?;
        if fds[1].revents != 0 {
            return Err(RecoveryError::DonorDied(donor.pid));
        }
        if fds[0].revents == 0 {
            continue;
        }
        let conn = match listener.accept() {
            Ok((conn, _)) => conn,
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => continue,
            Err(e) => return Err(io_err("accepting the child")(e)),
        };
        let pid = sys::peer_pid(conn.as_fd()).map_err(io_err("reading SO_PEERCRED"))?;
        // Open the pidfd before checking the parent: from then on the pid cannot be reused.
        let pidfd = sys::pidfd_open(pid).map_err(io_err("opening the child's pidfd"))?;
        if sys::parent_pid(pid) == Some(donor.pid) {
            return Ok((conn, pid, pidfd));
        }
        tracing::warn!(
            pid,
            donor = donor.pid,
            "refused a connection on the voter socket: not a child of the donor"
        );
    }
}

/// 4.–5. Sends fresh pipes to the child and waits for its confirmation.
fn hand_over_pipes(
    plan: &VoterPlan,
    mut conn: UnixStream,
    child_pid: libc::pid_t,
    pidfd: OwnedFd,
    deadline: Instant,
) -> Result<Replica, RecoveryError> {
    let pipes = ReplicaPipes::new(plan).map_err(io_err("creating pipes"))?;
    let mut transfer = FdTransfer {
        magic: TRANSFER_MAGIC,
        count: pipes.replica_ends.len() as u32,
        targets: [-1; MAX_PORTS],
    };
    for (slot, target) in transfer.targets.iter_mut().zip(pipes.targets()) {
        *slot = target;
    }
    let raw: Vec<RawFd> = pipes.replica_ends.iter().map(AsRawFd::as_raw_fd).collect();
    sys::send_with_fds(conn.as_fd(), transfer.as_bytes(), &raw)
        .map_err(io_err("sending the pipes"))?;
    let ReplicaPipes {
        replica_ends,
        inputs,
        outputs,
    } = pipes;
    drop::<Vec<OwnedFd>>(replica_ends);

    let remaining = deadline.saturating_duration_since(Instant::now());
    if !sys::wait_readable(conn.as_fd(), remaining).map_err(io_err("waiting for Ready"))? {
        return Err(RecoveryError::ReadyTimeout(child_pid));
    }
    conn.set_read_timeout(Some(remaining.max(Duration::from_millis(1))))
        .map_err(io_err("setting a read timeout"))?;
    let mut buf = [0u8; Ready::SIZE];
    conn.read_exact(&mut buf).map_err(io_err("reading Ready"))?;
    let ready = Ready::from_bytes(buf);
    if ready.magic != READY_MAGIC || ready.pid != child_pid {
        return Err(RecoveryError::BadReady(format!(
            "magic {:#x}, pid {} (expected pid {child_pid})",
            ready.magic, ready.pid
        )));
    }
    Ok(Replica {
        pid: child_pid,
        pidfd,
        inputs,
        outputs,
        our_child: false,
        // A fork of a replica that has answered: its handler is in place.
        proven: true,
    })
}
