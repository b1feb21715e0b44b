//! Recovery with a healthy donor (S³RES §3.1, §4.4): the donor forks itself on our signal, and
//! its child takes the faulty replica's place with state intact.
//!
//! The sequence, each step bounded so that a dead or stuck donor cannot hang the voter:
//! 1. check that the donor has no half-read answer in our decoder (its fork restarts on a
//!    frame boundary: replica-rt never forks in the middle of a `send`), and take back the input
//!    still buffered in its pipes (the child would not see it otherwise);
//! 2. send the donor [`signals::RESTART`] with a fresh nonce; its handler forks; meanwhile,
//!    make the child's fresh pipes;
//! 3. wait for the child on the donor's spare line ([`SpareLines`]), and on our socket: the
//!    child sends its `Hello` on the line where the donor had one, else it connects. On a
//!    connection of its own `SO_PEERCRED` must name a child of the donor (anyone else is
//!    refused, and killed if it is a child of one of ours, before anything is sent: whatever
//!    waits on the socket from an abandoned earlier attempt, or a stranger); the pipes go out by
//!    `SCM_RIGHTS` at once (it breaks its copy-on-write sharing meanwhile, and puts them on the
//!    donor's fd numbers after); then its `Hello` must carry this attempt's nonce (a late child
//!    of an earlier attempt has an older state). On the spare line, `Hello` comes first, and
//!    names the child, whose parent must be the donor. One that fails is refused (killed) and
//!    its pipes are dropped; the next connection gets a new set. The spare lines of other
//!    replicas that come meanwhile are kept for later attempts;
//! 4. tell the caller that the child has joined ([`Step::Joined`]: the voter moves it to its
//!    slot's CPUs and rests the donor while the child walks its pages), and wait for its `Ready`;
//! 5. give the taken-back input, followed by whatever is still queued for the donor, to both
//!    (to the donor only after the fork: what it read in between would reach the child twice).
//!
//! In stream mode ([`DonorState::Streaming`]) the donor is not idle: it may be writing output
//! while we wait, so its output pipes are read meanwhile, and the child's `Ready` says how many
//! whole frames its process had sent on each output, which is where its own output starts.

use std::io::{self, Read};
use std::os::fd::{AsFd, AsRawFd, OwnedFd, RawFd};
use std::os::unix::net::{UnixListener, UnixStream};
use std::time::Duration;

use crate::clock::Instant;

use replica_rt::contract::handshake::{
    FdTransfer, Hello, Ready, Spare, HELLO_MAGIC, READY_MAGIC, SPARE_MAGIC, TRANSFER_MAGIC,
};
use replica_rt::contract::{signals, MAX_HANDED_FDS};
use replica_rt::sys;
use thiserror::Error;

use crate::plan::VoterPlan;
use crate::replica::{Replica, ReplicaPipes};

#[derive(Debug, Error)]
pub enum RecoveryError {
    #[error("donor (pid {0}) has a partial frame in its output; it is not at a quiet point")]
    DonorMidFrame(libc::pid_t),
    #[error("donor (pid {0}) died during the recovery")]
    DonorDied(libc::pid_t),
    #[error("donor's child did not connect within {0:?}")]
    ConnectTimeout(Duration),
    #[error("new replica (pid {0}) did not confirm its pipes in time")]
    ReadyTimeout(libc::pid_t),
    #[error("new replica sent a bad confirmation: {0}")]
    BadReady(String),
    // The error is in the message, and not a `source` too (said twice in a chain's report).
    #[error("{what}: {error}")]
    Io {
        what: &'static str,
        error: io::Error,
    },
}

fn io_err(what: &'static str) -> impl FnOnce(io::Error) -> RecoveryError {
    move |error| RecoveryError::Io { what, error }
}

/// A connection from the donor's child, checked, which has been sent its pipes.
struct Joined {
    conn: UnixStream,
    pid: libc::pid_t,
    pidfd: OwnedFd,
    /// The voter's ends of the pipes sent (the replica's ends were sent and closed here).
    pipes: ReplicaPipes,
}

/// Where the donor is when it is asked to fork.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DonorState {
    /// Reactive mode: between rounds, idle. A partial frame of it in our decoder is an error.
    Quiet,
    /// Stream mode: it may be writing output right now. Its output pipes are read while we wait
    /// for the child (a donor blocked on a full pipe defers RESTART until its frame is out), and
    /// the child's [`Forked::frames_sent`] says where its output starts.
    Streaming,
}

/// A new replica made by fork, and where its output starts.
#[derive(Debug)]
pub struct Forked {
    pub replica: Replica,
    /// Whole frames the process had sent per output at the fork, indexed like `plan.outputs`:
    /// the child's next frame on output `o` is frame number `frames_sent[o]` of its process.
    pub frames_sent: Vec<u64>,
}

/// The replicas' spare lines (replica-rt's `restart`, "The spare line"; the contract's
/// `handshake::Spare`): connections each replica makes ahead for its next fork child, taken off
/// our socket during recovery attempts, at most one kept per replica (its newest). A fork
/// child sends its `Hello` on its donor's, and so skips making a connection of its own.
#[derive(Default)]
pub struct SpareLines(Vec<(libc::pid_t, UnixStream)>);

impl SpareLines {
    /// Keeps `line`, the newest of replica `pid` (an older one of it was used by a fork child).
    pub(crate) fn keep(&mut self, pid: libc::pid_t, line: UnixStream) {
        self.0.retain(|(p, _)| *p != pid);
        self.0.push((pid, line));
    }

    /// The line of replica `pid`, if one was kept; it is used once.
    pub(crate) fn take(&mut self, pid: libc::pid_t) -> Option<UnixStream> {
        let k = self.0.iter().position(|(p, _)| *p == pid)?;
        Some(self.0.swap_remove(k).1)
    }

    /// Drops the lines of replicas not in `family` any more.
    fn forget_all_but(&mut self, family: &[libc::pid_t]) {
        self.0.retain(|(p, _)| family.contains(p));
    }
}

/// How long the announcement of a spare line may take to arrive once its connection is
/// accepted: the replica sends it right after `connect`, so only a replica stopped in between
/// takes longer, and its line is dropped rather than let it hold up the recovery.
const SPARE_ANNOUNCEMENT_WAIT: Duration = Duration::from_millis(10);

/// Where an attempt has got to, for the caller's work that can be done while it goes on
/// (see [`fork`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Step {
    /// The donor has been asked to fork, and does.
    Signalled,
    /// The child (this pid) has been identified as this attempt's and has its pipes; it is
    /// breaking its copy-on-write sharing, and its `Ready` is awaited next.
    Joined(libc::pid_t),
}

/// Makes a copy of `donor` by fork. `nonce` must differ from every earlier attempt's.
/// `steps` is called as the attempt reaches each [`Step`], at most once for each: what the
/// caller does there runs while the donor forks, or while the child walks its pages, not
/// after the child's `Ready` (on two CPUs in parallel with them; on one, the voter outranks
/// them either way). `spares` are the replicas' spare lines taken so far; the donor's is used
/// (whatever the outcome), and those that come during the attempt are kept.
#[allow(clippy::too_many_arguments)]
pub fn fork(
    plan: &VoterPlan,
    listener: &UnixListener,
    spares: &mut SpareLines,
    donor: &mut Replica,
    nonce: u32,
    family: &[libc::pid_t],
    state: DonorState,
    steps: &mut dyn FnMut(Step),
) -> Result<Forked, RecoveryError> {
    let timeout = Duration::from_millis(plan.restart_timeout_ms);
    let deadline = Instant::now() + timeout;

    // 1. At a quiet point the donor must not be in the middle of an answer we have partly read.
    if state == DonorState::Quiet {
        for out in &mut donor.outputs {
            out.fill().map_err(io_err("reading the donor's output"))?;
            if out.decoder.pending() > 0 {
                return Err(RecoveryError::DonorMidFrame(donor.pid));
            }
        }
    }
    // What the donor has yet to read stays in its pipes: the donor copies it at the fork and
    // the child sends us the copy behind `Ready` (replica-rt's `restart`, "Unread input"). So a
    // voter killed during the fork takes no input with it. What is still queued here for the
    // donor follows that copy in the child's pipe; nothing is written to the donor meanwhile.
    //
    // Nothing is taken off the socket before the signal: whatever waits there (spare lines,
    // children of abandoned attempts, strangers) is dealt with while the donor forks.
    let mut refused = Refusals::default();
    spares.forget_all_but(family);
    let lines: Vec<UnixStream> = spares.take(donor.pid).into_iter().collect();
    let signalled = sys::pidfd_sigqueue(
        donor.pidfd.as_fd(),
        signals::RESTART,
        nonce as i32,
        signal_sender(),
    )
    .map_err(io_err("signalling the donor"));
    // The caller's work while the donor forks does not count against the child's time.
    let deadline = if signalled.is_ok() {
        steps(Step::Signalled);
        Instant::now() + timeout
    } else {
        deadline
    };
    let joined = signalled.and_then(|()| {
        let attempt = Attempt {
            plan,
            nonce,
            family,
            deadline,
            timeout,
            state,
        };
        accept_child(listener, spares, lines, donor, &attempt, &mut refused)
    });
    refused.report();
    let joined = joined?;
    steps(Step::Joined(joined.pid));
    let (mut child, ready, unread) = await_ready(joined, plan.inputs.len(), deadline)?;

    // 6. Exactly what the donor had yet to read: its pipe's content, then our queue.
    for ((input, copy), donors) in child.inputs.iter_mut().zip(&unread).zip(&donor.inputs) {
        input.writer.queue_raw(copy);
        input.writer.queue_raw(donors.writer.unwritten());
        let _ = input.writer.flush();
    }
    let first_output = plan.inputs.len();
    let frames_sent = (0..plan.outputs.len())
        .map(|o| {
            ready
                .frames_sent
                .get(first_output + o)
                .copied()
                .unwrap_or(0)
        })
        .collect();
    Ok(Forked {
        replica: child,
        frames_sent,
    })
}

/// This voter as the sender of a RESTART: taken once (the voter never forks without `exec`).
fn signal_sender() -> sys::SignalSender {
    static SENDER: std::sync::OnceLock<sys::SignalSender> = std::sync::OnceLock::new();
    *SENDER.get_or_init(sys::SignalSender::this_process)
}

/// One fork attempt, as the accept loop needs it.
struct Attempt<'a> {
    plan: &'a VoterPlan,
    nonce: u32,
    family: &'a [libc::pid_t],
    deadline: Instant,
    timeout: Duration,
    state: DonorState,
}

/// Connections refused during one attempt. The first is logged with its reason; the rest are
/// counted and reported once at the end, so that a flood of connections costs a counter, not
/// a log line each (a flood once wrote 21 MB of warnings and stretched a recovery to 6 s).
#[derive(Default)]
struct Refusals {
    count: u64,
    killed: u64,
}

impl Refusals {
    /// A spare line dropped: it ended, or what came on it was not what a line carries.
    fn note_line(&mut self, why: &str) {
        tracing::warn!(why, "dropped a spare line on the voter socket");
    }

    fn report(&self) {
        if self.count > 1 {
            tracing::warn!(
                refused = self.count,
                killed = self.killed,
                "refused connections on the voter socket during one recovery"
            );
        }
    }
}

/// Disconnects a peer; kills it too if it is one of ours (a fork child of one of our replicas,
/// or an orphan re-parented to the voter), through a pidfd so a reused pid is never hit.
fn refuse(conn: UnixStream, family: &[libc::pid_t], why: &str, refused: &mut Refusals) {
    refused.count += 1;
    let first = refused.count == 1;
    let Ok(pid) = sys::peer_pid(conn.as_fd()) else {
        if first {
            tracing::warn!(why, "refused a connection on the voter socket");
        }
        return;
    };
    let Ok(pidfd) = sys::pidfd_open(pid) else {
        return;
    };
    let me = std::process::id() as libc::pid_t;
    let ours = sys::parent_of(pidfd.as_fd(), pid)
        .is_some_and(|parent| parent == me || family.contains(&parent));
    if first || ours {
        tracing::warn!(pid, ours, why, "refused a connection on the voter socket");
    }
    if ours {
        refused.killed += 1;
        let _ = sys::pidfd_send_signal(pidfd.as_fd(), libc::SIGKILL);
    }
}

/// Waits for the donor's child, on the donor's spare `lines` and on the socket; refuses anyone
/// else, and keeps the spare lines of the other replicas that come meanwhile.
/// A streaming donor's output pipes are read meanwhile (into their decoders, not decoded), so a
/// donor blocked writing a frame can finish it and take the signal.
fn accept_child(
    listener: &UnixListener,
    spares: &mut SpareLines,
    mut lines: Vec<UnixStream>,
    donor: &mut Replica,
    attempt: &Attempt,
    refused: &mut Refusals,
) -> Result<Joined, RecoveryError> {
    let &Attempt {
        plan,
        nonce,
        family,
        deadline,
        timeout,
        state,
    } = attempt;
    // Made while the donor forks (the signal is sent): the child's pipes are ready when it
    // connects.
    let mut pipes = Some(ReplicaPipes::new(plan).map_err(io_err("creating pipes"))?);
    let mut fds = Vec::with_capacity(2 + donor.outputs.len());
    loop {
        let now = Instant::now();
        if now >= deadline {
            return Err(RecoveryError::ConnectTimeout(timeout));
        }
        fds.clear();
        let polled = [listener.as_raw_fd(), donor.pidfd.as_raw_fd()]
            .into_iter()
            .chain(lines.iter().map(AsRawFd::as_raw_fd));
        for fd in polled {
            fds.push(libc::pollfd {
                fd,
                events: libc::POLLIN,
                revents: 0,
            });
        }
        let first_output = fds.len();
        if state == DonorState::Streaming {
            for out in donor.outputs.iter().filter(|out| !out.is_closed()) {
                fds.push(libc::pollfd {
                    fd: out.as_fd().as_raw_fd(),
                    events: libc::POLLIN,
                    revents: 0,
                });
            }
        }
        sys::ppoll(&mut fds, Some(deadline - now)).map_err(io_err("waiting for the child"))?;
        if fds[first_output..].iter().any(|p| p.revents != 0) {
            for out in donor.outputs.iter_mut().filter(|out| !out.is_closed()) {
                // A read error or a closed pipe shows again in the voter's own loop.
                let _ = out.fill();
            }
        }
        // A line with something to read: the child's `Hello`, or the end (a line whose
        // fork child is gone, or used already).
        if let Some(k) = (0..lines.len()).find(|&k| fds[2 + k].revents != 0) {
            let line = lines.swap_remove(k);
            match joined_on_line(plan, line, &mut pipes, donor, nonce, deadline) {
                Ok(joined) => {
                    tracing::debug!(
                        pid = joined.pid,
                        "the donor's child joined on its spare line"
                    );
                    return Ok(joined);
                }
                Err(Some(why)) => refused.note_line(&why),
                Err(None) => {}
            }
            continue;
        }
        if fds[0].revents == 0 {
            if fds[1].revents != 0 {
                return Err(RecoveryError::DonorDied(donor.pid));
            }
            continue;
        }
        let conn = match listener.accept() {
            Ok((conn, _)) => conn,
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => continue,
            Err(e) => return Err(io_err("accepting the child")(e)),
        };
        // A replica's spare line: the donor's is watched from now on, another's kept.
        let conn = match spare_line(conn, family) {
            Line::Kept(pid, line) if pid == donor.pid => {
                lines.push(line);
                continue;
            }
            Line::Kept(pid, line) => {
                spares.keep(pid, line);
                continue;
            }
            Line::Stale => continue,
            Line::Unannounced(why) => {
                refused.note_line(&why);
                continue;
            }
            Line::Not(conn) => conn,
        };
        // Who it is first (cheap: a stranger costs no pipes); then the pipes go out at once,
        // before the nonce in its `Hello` is read: the child puts them in place and starts on
        // its copy-on-write sharing while the voter reads it. A child of the donor that turns
        // out to belong to an abandoned attempt is refused (killed) and its pipes are dropped
        // (the voter closes its ends, so they lead nowhere); the next connection gets a new set.
        let (conn, pid, pidfd) = match identify_child(conn, donor) {
            Ok(known) => known,
            Err((conn, why)) => {
                refuse(conn, family, &why, refused);
                continue;
            }
        };
        let sent = match pipes.take() {
            Some(p) => p,
            None => ReplicaPipes::new(plan).map_err(io_err("creating pipes"))?,
        };
        let sent = match send_pipes(&conn, sent) {
            Ok(sent) => sent,
            Err(e) => {
                refuse(conn, family, &format!("sending the pipes: {e}"), refused);
                continue;
            }
        };
        match check_hello(conn, pid, nonce, deadline) {
            Ok(conn) => {
                tracing::debug!(pid, "the donor's child connected (no spare line)");
                return Ok(Joined {
                    conn,
                    pid,
                    pidfd,
                    pipes: sent,
                });
            }
            Err((conn, why)) => refuse(conn, family, &why, refused),
        }
    }
}

/// Sends fresh pipes by `SCM_RIGHTS`, with the fd numbers they must land on, and closes the
/// replica's ends here; returns the voter's ends.
pub(crate) fn send_pipes(conn: &UnixStream, pipes: ReplicaPipes) -> io::Result<ReplicaPipes> {
    let mut transfer = FdTransfer {
        magic: TRANSFER_MAGIC,
        count: pipes.replica_ends.len() as u32,
        targets: [-1; MAX_HANDED_FDS],
    };
    for (slot, target) in transfer.targets.iter_mut().zip(pipes.targets()) {
        *slot = target;
    }
    let raw: Vec<RawFd> = pipes.replica_ends.iter().map(AsRawFd::as_raw_fd).collect();
    sys::send_with_fds(conn.as_fd(), transfer.as_bytes(), &raw)?;
    let mut pipes = pipes;
    drop::<Vec<OwnedFd>>(std::mem::take(&mut pipes.replica_ends));
    Ok(pipes)
}

/// What a connection taken off the socket during an attempt (or an adoption) is, as far as
/// spare lines go.
pub(crate) enum Line {
    /// A spare line of replica `pid`, one of ours now; its announcement read.
    Kept(libc::pid_t, UnixStream),
    /// A spare line of a replica that is no longer ours (replaced since it made it): dropped.
    Stale,
    /// One of our replicas connected and did not announce a line: dropped, and why.
    Unannounced(String),
    /// Not a spare line: a fork child's connection, or a stranger's.
    Not(UnixStream),
}

/// Tells a spare line from the rest: its first bytes are a [`Spare`] announcement of the
/// replica that connected (`SO_PEERCRED`), looked at without taking them, or, for one of ours
/// (`family`) that has not sent them yet, waited for briefly.
pub(crate) fn spare_line(conn: UnixStream, family: &[libc::pid_t]) -> Line {
    let Ok(pid) = sys::peer_pid(conn.as_fd()) else {
        return Line::Not(conn);
    };
    let ours = family.contains(&pid);
    let peeked = peek_announcement(&conn, pid);
    if peeked == Some(true) && !ours {
        tracing::debug!(pid, "dropped the spare line of a replica replaced since");
        return Line::Stale;
    }
    if !ours || peeked == Some(false) {
        return Line::Not(conn);
    }
    let by = Instant::now() + SPARE_ANNOUNCEMENT_WAIT;
    match read_exact_by::<{ Spare::SIZE }>(&conn, by) {
        Ok(bytes) if is_announcement(bytes, pid) => Line::Kept(pid, conn),
        Ok(bytes) => Line::Unannounced(format!(
            "replica {pid} connected without announcing a spare line (magic {:#x})",
            Spare::from_bytes(bytes).magic
        )),
        Err(e) => Line::Unannounced(format!("replica {pid}'s spare line said nothing: {e}")),
    }
}

/// Whether `bytes` are the announcement of a spare line made by `pid`.
fn is_announcement(bytes: [u8; Spare::SIZE], pid: libc::pid_t) -> bool {
    Spare::from_bytes(bytes)
        == Spare {
            magic: SPARE_MAGIC,
            pid,
        }
}

/// Whether `conn`, from `pid`, starts with a spare line's announcement, looked at without
/// taking it and without waiting: `None` while fewer bytes than one have come.
fn peek_announcement(conn: &UnixStream, pid: libc::pid_t) -> Option<bool> {
    let mut head = [0u8; Spare::SIZE];
    let peeked = sys::peek_now(conn.as_fd(), &mut head).unwrap_or(0);
    (peeked == Spare::SIZE).then(|| is_announcement(head, pid))
}

/// The donor's child on the donor's spare line: its `Hello` (this attempt's nonce, and its pid,
/// whose parent must be the donor), then its pipes. A child that fails is killed: a late child
/// of an abandoned attempt of this donor, with an older state. `Err(None)`: the line ended
/// (not worth a warning: see below); `Err(Some(why))`: refused.
fn joined_on_line(
    plan: &VoterPlan,
    line: UnixStream,
    pipes: &mut Option<ReplicaPipes>,
    donor: &Replica,
    nonce: u32,
    deadline: Instant,
) -> Result<Joined, Option<String>> {
    let hello = match read_exact_by::<{ Hello::SIZE }>(&line, deadline) {
        Ok(bytes) => Hello::from_bytes(bytes),
        // A line its replica dropped: one made for a voter since replaced (the replica made
        // another after its rebind, which waits on the socket), or one whose child is gone
        // before it said anything (the attempt times out, as without a line).
        Err(e) => {
            tracing::debug!(donor = donor.pid, "the donor's spare line ended: {e}");
            return Err(None);
        }
    };
    let pid = hello.pid;
    let pidfd = sys::pidfd_open(pid).map_err(|e| {
        Some(format!(
            "the child {pid} named on the donor's spare line is gone: {e}"
        ))
    })?;
    if sys::parent_of(pidfd.as_fd(), pid) != Some(donor.pid) {
        return Err(Some(format!(
            "the spare line of donor {} named {pid}, not a child of it",
            donor.pid
        )));
    }
    let kill = |why: String| {
        let _ = sys::pidfd_send_signal(pidfd.as_fd(), libc::SIGKILL);
        Some(format!("{why}; killed"))
    };
    if hello.magic != HELLO_MAGIC || hello.nonce != nonce {
        return Err(kill(format!(
            "child {pid} belongs to another attempt (nonce {:#x}, expected {nonce:#x})",
            hello.nonce
        )));
    }
    let pipes = match pipes.take() {
        Some(p) => p,
        None => ReplicaPipes::new(plan).map_err(|e| kill(format!("creating pipes: {e}")))?,
    };
    match send_pipes(&line, pipes) {
        Ok(pipes) => Ok(Joined {
            conn: line,
            pid,
            pidfd,
            pipes,
        }),
        Err(e) => Err(kill(format!("sending the pipes to {pid}: {e}"))),
    }
}

/// `SO_PEERCRED` names a child of the donor; returns its pid and a pidfd of it. Cheap (no
/// read from the peer), and done before anything is sent: a stranger (a flood of connections)
/// costs no pipes.
fn identify_child(
    conn: UnixStream,
    donor: &Replica,
) -> Result<(UnixStream, libc::pid_t, OwnedFd), (UnixStream, String)> {
    let pid = match sys::peer_pid(conn.as_fd()) {
        Ok(pid) => pid,
        Err(e) => return Err((conn, format!("no peer credentials: {e}"))),
    };
    // Open the pidfd before checking the parent. It holds the process, not its number: a child
    // that dies now is reaped at once (its donor ignores SIGCHLD), and its number could go to
    // another process; but one with the donor as its parent only by the donor's next fork,
    // which comes only when this voter asks.
    let pidfd = match sys::pidfd_open(pid) {
        Ok(fd) => fd,
        Err(e) => return Err((conn, format!("peer {pid} is gone: {e}"))),
    };
    if sys::parent_of(pidfd.as_fd(), pid) != Some(donor.pid) {
        return Err((
            conn,
            format!("peer {pid} is not a child of the donor {}", donor.pid),
        ));
    }
    Ok((conn, pid, pidfd))
}

/// The child's `Hello` carries our nonce (a late child of an abandoned attempt carries an older
/// one).
fn check_hello(
    conn: UnixStream,
    pid: libc::pid_t,
    nonce: u32,
    deadline: Instant,
) -> Result<UnixStream, (UnixStream, String)> {
    let hello = match read_exact_by(&conn, deadline) {
        Ok(bytes) => Hello::from_bytes(bytes),
        Err(e) => return Err((conn, format!("no Hello from {pid}: {e}"))),
    };
    if hello.magic != HELLO_MAGIC || hello.nonce != nonce || hello.pid != pid {
        return Err((
            conn,
            format!(
                "child {pid} belongs to another attempt (nonce {:#x}, expected {nonce:#x}; \
                 pid {})",
                hello.nonce, hello.pid
            ),
        ));
    }
    Ok(conn)
}

/// Reads exactly `N` bytes, giving up at `deadline`.
pub(crate) fn read_exact_by<const N: usize>(
    conn: &UnixStream,
    deadline: Instant,
) -> io::Result<[u8; N]> {
    let mut buf = [0u8; N];
    read_exact_into(conn, &mut buf, deadline)?;
    Ok(buf)
}

/// Fills `buf` from `conn` by `deadline`.
pub(crate) fn read_exact_into(
    conn: &UnixStream,
    buf: &mut [u8],
    deadline: Instant,
) -> io::Result<()> {
    let left = deadline.saturating_duration_since(Instant::now());
    conn.set_nonblocking(false)?;
    conn.set_read_timeout(Some(left.max(Duration::from_millis(1))))?;
    (&*conn).read_exact(buf)
}

/// The child's unread input per input is at most this long: a pipe holds 64 KiB unless it
/// was grown, and `/proc/sys/fs/pipe-max-size` is 1 MiB by default. More is a broken child.
const MAX_UNREAD_INPUT: u64 = 1 << 24;

/// Waits for the confirmation of a child that has been sent its pipes, and the unread input
/// of each of the `inputs` that follows it. A child that fails to give them is killed: it
/// exists, but will never be used.
fn await_ready(
    joined: Joined,
    inputs_count: usize,
    deadline: Instant,
) -> Result<(Replica, Ready, Vec<Vec<u8>>), RecoveryError> {
    let Joined {
        conn,
        pid,
        pidfd,
        pipes,
    } = joined;
    let (ready, unread) = read_ready(&conn, pid, inputs_count, deadline).inspect_err(|_| {
        let _ = sys::pidfd_send_signal(pidfd.as_fd(), libc::SIGKILL);
    })?;
    let replica = Replica::forked(pid, pidfd, pipes);
    Ok((replica, ready, unread))
}

/// `Ready` from the child `pid`, checked, and the unread input of each of the `inputs_count`
/// inputs that follows it.
fn read_ready(
    conn: &UnixStream,
    pid: libc::pid_t,
    inputs_count: usize,
    deadline: Instant,
) -> Result<(Ready, Vec<Vec<u8>>), RecoveryError> {
    let ready = match read_exact_by::<{ Ready::SIZE }>(conn, deadline) {
        Ok(bytes) => Ready::from_bytes(bytes),
        Err(e)
            if matches!(
                e.kind(),
                io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
            ) =>
        {
            return Err(RecoveryError::ReadyTimeout(pid))
        }
        Err(e) => return Err(io_err("reading Ready")(e)),
    };
    if ready.magic != READY_MAGIC || ready.pid != pid {
        return Err(RecoveryError::BadReady(format!(
            "magic {:#x}, pid {} (expected pid {pid})",
            ready.magic, ready.pid
        )));
    }
    let mut unread = Vec::with_capacity(inputs_count);
    for &bytes in ready.frames_sent.iter().take(inputs_count) {
        if bytes > MAX_UNREAD_INPUT {
            return Err(RecoveryError::BadReady(format!(
                "{bytes} bytes of unread input (at most {MAX_UNREAD_INPUT})"
            )));
        }
        let mut copy = vec![0u8; bytes as usize];
        // Nothing to read, nothing to set up: the socket's options cost two system calls
        // between `Ready` and the child counted in, and most restarts have no unread input.
        if bytes > 0 {
            read_exact_into(conn, &mut copy, deadline).map_err(|e| match e.kind() {
                io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut => {
                    RecoveryError::ReadyTimeout(pid)
                }
                _ => io_err("reading the child's unread input")(e),
            })?;
        }
        unread.push(copy);
    }
    Ok((ready, unread))
}
