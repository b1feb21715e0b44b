//! The voter's ends of the world: the component's external inputs and outputs (non-blocking,
//! with queues), the fds it inherits from bootstrap, the signalfd, the poll set one wait of
//! the event loop watches, the event writer, and the sweep of children at the end.

use std::os::fd::{AsFd, AsRawFd, BorrowedFd, OwnedFd, RawFd};
use std::os::unix::fs::PermissionsExt;
use std::os::unix::net::UnixListener;
use std::time::Duration;

use nix::sys::epoll::{Epoll, EpollCreateFlags, EpollEvent, EpollFlags, EpollTimeout};
use nix::sys::signal::Signal;
use nix::sys::signalfd::SignalFd;
use nix::sys::time::TimeSpec;
use nix::sys::timerfd::{ClockId, Expiration, TimerFd, TimerFlags, TimerSetTimeFlags};
use replica_rt::heartbeat::Heartbeat;
use replica_rt::sys;

use crate::channel::{Fill, FrameReader, FrameWriter, Peek};
use crate::clock::Instant;
use crate::core::{io_err, VoterError};
use crate::event::Event;
use crate::plan::VoterPlan;
use crate::replica::Replica;
use crate::round::OutputSet;

/// An input of the protected component: read by the voter, copied to every replica.
pub(crate) struct ExternalInput {
    pub(crate) name: String,
    pub(crate) reader: FrameReader,
    /// The outputs a frame on this input expects (its round), or `None` if it starts none.
    pub(crate) round: Option<OutputSet>,
    /// Journaled: the channel is peeked, and frames are taken off it into the journal once
    /// decoded (see `journal.rs`). `None`: read as usual.
    pub(crate) peek: Option<Peeked>,
}

/// How far a journaled input's decoder is ahead of its channel.
pub(crate) struct Peeked {
    pub(crate) pipe: Peek,
    /// The decoder's `passed()` when bytes were last taken off the channel.
    pub(crate) mark: u64,
    /// Undecoded bytes at the decoder's head that are already off the channel (the log a
    /// predecessor left, being replayed).
    pub(crate) replay_left: usize,
    /// A frame only partly in the channel (its writer is in the middle of it): peeking again
    /// before this would find the same bytes, so the input is not watched until then.
    pub(crate) stalled_until: Option<Instant>,
}

/// How long a journaled input whose channel holds part of a frame waits before it looks
/// again (the writer of a frame larger than the pipe's free room writes it in pieces).
const PEEK_STALL: Duration = Duration::from_millis(1);

/// An output of the protected component: the voter writes the winners here.
pub(crate) struct ExternalOutput {
    pub(crate) name: String,
    pub(crate) writer: FrameWriter,
    /// The reader went away; later frames are dropped (said once).
    pub(crate) broken: bool,
    /// Why it broke, if not because its reader went away (a full disk behind a redirected
    /// stdout, an I/O error): the frames dropped since are lost, and the component has failed
    /// (see [`ExternalOutput::failure`]).
    pub(crate) failed: Option<String>,
    /// Frames sent (queued) so far by this voter and its predecessors: the next one's number.
    pub(crate) sent: u64,
}

impl ExternalOutput {
    /// Queues `frame` for downstream and writes what the pipe takes now.
    pub(crate) fn send(&mut self, frame: &[u8]) {
        self.sent += 1;
        if self.broken {
            return;
        }
        if let Err(e) = self.writer.send(frame) {
            self.break_on(&e);
            self.writer.discard();
        }
    }

    /// The write failed with `e`: a reader that went away (`EPIPE`: downstream ended, as
    /// `head` does) leaves the rest of the output unwanted; any other error loses it.
    fn break_on(&mut self, e: &std::io::Error) {
        // A reader gone: a pipe's (`EPIPE`) or a socket's (`ECONNRESET`: stdout a socket).
        if matches!(
            e.kind(),
            std::io::ErrorKind::BrokenPipe
                | std::io::ErrorKind::ConnectionReset
                | std::io::ErrorKind::ConnectionAborted
        ) {
            tracing::warn!(output = %self.name, error = %e, "downstream is gone; dropping further output");
        } else {
            tracing::error!(output = %self.name, error = %e, "cannot write the output; dropping further output");
            self.failed = Some(e.to_string());
        }
        self.broken = true;
    }

    /// What was lost because the output could not be written (not because its reader went
    /// away): the output's name and why.
    pub(crate) fn failure(&self) -> Option<String> {
        let why = self.failed.as_ref()?;
        Some(format!(
            "output `{}` could not be written: {why}; what the component sent there since is lost",
            self.name
        ))
    }

    /// Writes what is queued, as far as the pipe takes it now.
    pub(crate) fn flush(&mut self) {
        if let Err(e) = self.writer.flush() {
            if !self.broken {
                self.break_on(&e);
            }
            // Nothing queued for a reader that will never come.
            self.writer.discard();
        }
    }

    /// Writes out what is still queued, blocking up to `deadline`.
    pub(crate) fn drain(&mut self, deadline: Instant) {
        while self.writer.has_pending() && !self.broken {
            let left = deadline.saturating_duration_since(Instant::now());
            let mut pfd = [libc::pollfd {
                fd: self.writer.as_fd().as_raw_fd(),
                events: libc::POLLOUT,
                revents: 0,
            }];
            if left.is_zero() || sys::ppoll(&mut pfd, Some(left)).unwrap_or(0) == 0 {
                tracing::warn!(output = %self.name, "downstream did not take the last frames");
                return;
            }
            self.flush();
        }
    }
}

/// What a slot of the poll set stands for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Token {
    Signal,
    Input(usize),
    OutputWritable(usize),
    ReplicaExit(usize),
    ReplicaOutput(usize, usize),
    ReplicaInputWritable(usize, usize),
    ReplicaStderr(usize),
    ReplicaStarted(usize),
    /// The loop's [`WakeTimer`] expired.
    Timer,
    /// One of the quiet fds is ready (see [`PollSet`]): [`PollSet::ready_quiet`] says which.
    Quiet,
}

/// The fds one wait of an event loop watches, each with the [`Token`] saying what it stands
/// for. Rebuilt before every wait from the loop's state; the vectors keep their capacity, so
/// a steady-state round allocates nothing.
///
/// **Quiet fds** are those watched all the time that are rarely ready: the signalfd, the wake
/// timer, and each replica's pidfd and stderr pipe. They sit in an epoll instance, and the
/// wait watches that one fd instead of all of them: `ppoll` pays per fd it watches, twice
/// (onto each fd's wait queue and off it again), and in a TMR round the voter waits three
/// times. The epoll instance is made afresh whenever the quiet set changes (a replica
/// replaced, a stderr pipe closed): a new instance holds no registration of a file that an
/// old fd number once named, so no stale event can reach a new replica's slot.
///
/// **The wait itself** is an `epoll_wait` on an instance that watches exactly this set
/// ([`WaitEpoll`]), kept from wait to wait: a steady-state loop waits on the same few sets over
/// and over (idle for input; in a round, the replica it is waiting for), and `ppoll` would
/// put the voter onto each fd's wait queue and take it off again on every one of them.
#[derive(Debug, Default)]
pub(crate) struct PollSet {
    pub(crate) fds: Vec<libc::pollfd>,
    pub(crate) tokens: Vec<Token>,
    /// Whose fd each one is (a replica's pid; 0 for the voter's own), beside `fds`.
    owners: Vec<libc::pid_t>,
    /// The quiet fds wanted for this wait, in dispatch order.
    quiet_wanted: Vec<QuietFd>,
    /// The epoll instance and what it holds (`None`: none made yet, or making one failed, and
    /// the quiet fds are watched by `ppoll` directly).
    quiet: Option<QuietSet>,
    /// What `epoll_wait` found, reused.
    quiet_events: Vec<EpollEvent>,
    /// No epoll instance could be made (reported once): the quiet fds are watched one by one
    /// from then on, instead of trying again at every wait.
    quiet_refused: bool,
    /// The quiet fds found ready, in dispatch order (see [`PollSet::ready_quiet`]).
    pub(crate) quiet_ready: Vec<Token>,
    /// Epoll instances for the sets waited on lately (at most [`WAIT_SETS`]).
    waits: Vec<WaitEpoll>,
    /// Waits with an instance so far: the instances' clock of use.
    wait_clock: u64,
    /// What `epoll_wait` found, reused.
    wait_events: Vec<EpollEvent>,
    /// An epoll instance could not be made or waited on (reported once): every wait is a
    /// `ppoll` from then on.
    wait_refused: bool,
    /// Instances made, and waits, in the current window of [`CHURN_WINDOW`] waits.
    made_in_window: u32,
    waits_in_window: u32,
}

/// One fd of a wait as an epoll instance watches it: the instance is kept for a set only
/// while every one of these is the same, the owner too (see [`QuietFd`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Watched {
    fd: RawFd,
    events: libc::c_short,
    token: Token,
    owner: libc::pid_t,
}

/// An epoll instance watching one set, level-triggered like `ppoll`; an event's data is the
/// fd's index in the set, so a wait fills in the same `revents` that `ppoll` would.
///
/// Stale registrations cannot reach a wait: every fd of a replica is keyed by its pid, and
/// all instances go whenever the quiet set changes (a replica replaced or gone, a pipe
/// closed). The voter's own inputs and outputs are opened once.
///
/// Its members sit in an array, so that making one in a steady loop allocates nothing.
#[derive(Debug)]
struct WaitEpoll {
    epoll: Epoll,
    members: [Watched; WAIT_SET_FDS],
    len: usize,
    /// When it was last used, on [`PollSet`]'s count of waits: the least recently used
    /// instance is the one replaced. (Instances stay where they are: reordering them to keep
    /// the most recent last moved hundreds of bytes per wait.)
    used: u64,
}

/// The most fds a set with an instance has; a larger set waits with `ppoll`.
const WAIT_SET_FDS: usize = 24;

/// How many sets keep their epoll instance. A TMR round on one CPU waits on the idle set and
/// on one per replica it waits for; each instance a pipe is in costs every write to it a
/// wake-up callback, so no more are kept than a loop uses.
const WAIT_SETS: usize = 6;

/// A loop that goes round more sets than are kept would make an instance (one system call per
/// fd) at most waits: at most [`MADE_PER_WINDOW`] are made in any [`CHURN_WINDOW`] waits, and
/// a set without one waits with `ppoll`, as it did before there were instances.
const CHURN_WINDOW: u32 = 256;
const MADE_PER_WINDOW: u32 = 8;

impl WaitEpoll {
    /// An instance for the set `fds` (at most [`WAIT_SET_FDS`]), with their tokens and owners,
    /// used at `used`.
    fn new(
        fds: &[libc::pollfd],
        tokens: &[Token],
        owners: &[libc::pid_t],
        used: u64,
    ) -> nix::Result<WaitEpoll> {
        let epoll = Epoll::new(EpollCreateFlags::EPOLL_CLOEXEC)?;
        let unused = Watched {
            fd: -1,
            events: 0,
            token: Token::Quiet,
            owner: 0,
        };
        let mut members = [unused; WAIT_SET_FDS];
        for (k, ((p, &token), &owner)) in fds.iter().zip(tokens).zip(owners).enumerate() {
            // SAFETY: `p.fd` is open: it was taken from a live object of the loop's state in
            // this same turn of the loop, before anything could close it.
            let fd = unsafe { BorrowedFd::borrow_raw(p.fd) };
            let events = EpollFlags::from_bits_truncate(p.events as u16 as libc::c_int);
            epoll.add(fd, EpollEvent::new(events, k as u64))?;
            members[k] = Watched {
                fd: p.fd,
                events: p.events,
                token,
                owner,
            };
        }
        Ok(WaitEpoll {
            epoll,
            members,
            len: fds.len(),
            used,
        })
    }

    fn members(&self) -> &[Watched] {
        &self.members[..self.len]
    }

    fn watches(&self, fds: &[libc::pollfd], tokens: &[Token], owners: &[libc::pid_t]) -> bool {
        self.len == fds.len()
            && self
                .members()
                .iter()
                .zip(fds.iter().zip(tokens).zip(owners))
                .all(|(w, ((p, &token), &owner))| {
                    w.fd == p.fd && w.events == p.events && w.token == token && w.owner == owner
                })
    }
}

/// A quiet fd, with the token it stands for and the pid of the replica it belongs to (0 for
/// the voter's own): a replaced replica's fds may come back under the same numbers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct QuietFd {
    fd: RawFd,
    token: Token,
    owner: libc::pid_t,
}

#[derive(Debug)]
struct QuietSet {
    epoll: Epoll,
    members: Vec<QuietFd>,
}

impl QuietSet {
    fn new(members: &[QuietFd]) -> nix::Result<QuietSet> {
        let epoll = Epoll::new(EpollCreateFlags::EPOLL_CLOEXEC)?;
        for (k, q) in members.iter().enumerate() {
            // SAFETY: `q.fd` is open: it was taken from a live object of the loop's state in
            // this same turn of the loop, before anything could close it.
            let fd = unsafe { BorrowedFd::borrow_raw(q.fd) };
            epoll.add(fd, EpollEvent::new(EpollFlags::EPOLLIN, k as u64))?;
        }
        Ok(QuietSet {
            epoll,
            members: members.to_vec(),
        })
    }
}

impl PollSet {
    fn add(&mut self, fd: RawFd, events: libc::c_short, token: Token, owner: libc::pid_t) {
        self.fds.push(libc::pollfd {
            fd,
            events,
            revents: 0,
        });
        self.tokens.push(token);
        self.owners.push(owner);
    }

    fn add_quiet(&mut self, fd: RawFd, token: Token, owner: libc::pid_t) {
        self.quiet_wanted.push(QuietFd { fd, token, owner });
    }

    /// Ends the set: the quiet fds go into the epoll instance (a new one if they changed),
    /// watched as one fd at the front, so they are dispatched first, as they always were.
    /// If no instance can be made, they are watched one by one instead.
    pub(crate) fn seal(&mut self) {
        let current = self
            .quiet
            .as_ref()
            .is_some_and(|q| q.members == self.quiet_wanted);
        if !current && !self.quiet_refused {
            // Sized now, while the set changes: a steady-state round allocates nothing.
            let n = self.quiet_wanted.len().max(1);
            self.quiet_events.resize(n, EpollEvent::empty());
            self.quiet_ready.reserve(n);
            // Every wait instance holds the old quiet instance, or fds of a replica now gone.
            self.waits.clear();
            self.quiet = match QuietSet::new(&self.quiet_wanted) {
                Ok(set) => Some(set),
                Err(e) => {
                    tracing::warn!("epoll for the quiet fds: {e}; watching them one by one");
                    self.quiet_refused = true;
                    None
                }
            };
        }
        let pollfd = |fd: RawFd| libc::pollfd {
            fd,
            events: libc::POLLIN,
            revents: 0,
        };
        match &self.quiet {
            Some(q) => {
                self.fds.insert(0, pollfd(q.epoll.0.as_raw_fd()));
                self.tokens.insert(0, Token::Quiet);
                self.owners.insert(0, 0);
            }
            None => {
                for (k, q) in self.quiet_wanted.iter().enumerate() {
                    self.fds.insert(k, pollfd(q.fd));
                    self.tokens.insert(k, q.token);
                    self.owners.insert(k, q.owner);
                }
            }
        }
    }

    /// Waits until something in the (sealed) set is ready, with no time limit (the wake
    /// timer bounds it), after looking for up to `spin` without sleeping (`spin.rs`); fills in
    /// `revents` and returns how many fds are ready (0 if a signal interrupted the wait) and
    /// how long it spun.
    pub(crate) fn wait(&mut self, spin: Option<Duration>) -> Result<(usize, Duration), VoterError> {
        if let Some(k) = self.wait_epoll() {
            self.wait_events.resize(self.fds.len(), EpollEvent::empty());
            // What the wait does not report ready stays 0, as after a `ppoll`.
            for p in &mut self.fds {
                p.revents = 0;
            }
            let mut spun = Duration::ZERO;
            if let Some(limit) = spin {
                let began = Instant::now();
                loop {
                    match self.waits[k]
                        .epoll
                        .wait(&mut self.wait_events, EpollTimeout::ZERO)
                    {
                        Ok(0) => {}
                        Ok(n) => {
                            self.took_events(n);
                            return Ok((n, began.elapsed()));
                        }
                        // The sleep below says what is wrong, if anything.
                        Err(_) => break,
                    }
                    spun = began.elapsed();
                    if spun >= limit {
                        break;
                    }
                    sys::yield_cpu();
                }
            }
            match self.waits[k]
                .epoll
                .wait(&mut self.wait_events, EpollTimeout::NONE)
            {
                Ok(n) => {
                    self.took_events(n);
                    return Ok((n, spun));
                }
                Err(nix::errno::Errno::EINTR) => return Ok((0, spun)),
                Err(e) => {
                    tracing::warn!("epoll_wait: {e}; waiting with ppoll from now on");
                    self.waits.clear();
                    self.wait_refused = true;
                }
            }
        }
        Ok((wait_until(&mut self.fds, None)?, Duration::ZERO))
    }

    /// Copies the first `n` events of the last `epoll_wait` into the set's `revents`.
    fn took_events(&mut self, n: usize) {
        for e in &self.wait_events[..n] {
            // EPOLLIN, EPOLLOUT, EPOLLERR and EPOLLHUP are POLLIN, POLLOUT, POLLERR and
            // POLLHUP: the same bits.
            self.fds[e.data() as usize].revents = e.events().bits() as libc::c_short;
        }
    }

    /// The index in `waits` of the instance that watches the set as it is now, made if
    /// there is none (the least recently used one goes); `None`: wait with `ppoll`.
    fn wait_epoll(&mut self) -> Option<usize> {
        if self.wait_refused {
            return None;
        }
        self.waits_in_window += 1;
        if self.waits_in_window > CHURN_WINDOW {
            self.waits_in_window = 1;
            self.made_in_window = 0;
        }
        self.wait_clock += 1;
        let (fds, tokens, owners) = (&self.fds, &self.tokens, &self.owners);
        if let Some(k) = self
            .waits
            .iter()
            .position(|w| w.watches(fds, tokens, owners))
        {
            self.waits[k].used = self.wait_clock;
            return Some(k);
        }
        if self.made_in_window == MADE_PER_WINDOW || fds.len() > WAIT_SET_FDS {
            return None;
        }
        self.made_in_window += 1;
        // Sized once for good, at the first instance, so that none made later allocates.
        if self.waits.capacity() < WAIT_SETS {
            self.waits.reserve_exact(WAIT_SETS - self.waits.len());
        }
        if self.wait_events.capacity() < WAIT_SET_FDS {
            self.wait_events
                .reserve_exact(WAIT_SET_FDS - self.wait_events.len());
        }
        match WaitEpoll::new(fds, tokens, owners, self.wait_clock) {
            Ok(w) => {
                if self.waits.len() < WAIT_SETS {
                    self.waits.push(w);
                    return Some(self.waits.len() - 1);
                }
                let oldest = (0..self.waits.len()).min_by_key(|&k| self.waits[k].used)?;
                self.waits[oldest] = w;
                Some(oldest)
            }
            Err(e) => {
                // A regular file, say, which epoll refuses and `ppoll` takes.
                tracing::warn!("epoll for the wait: {e}; waiting with ppoll from now on");
                self.waits.clear();
                self.wait_refused = true;
                None
            }
        }
    }

    /// The quiet fds that are ready now, in dispatch order, into [`PollSet::quiet_ready`].
    pub(crate) fn ready_quiet(&mut self) {
        self.quiet_ready.clear();
        let Some(q) = &self.quiet else { return };
        let n = match q.epoll.wait(&mut self.quiet_events, EpollTimeout::ZERO) {
            Ok(n) => n,
            // Still ready: the next wait returns at once and asks again.
            Err(nix::errno::Errno::EINTR) => return,
            Err(e) => {
                // Nothing else is expected of an epoll fd we own; watch them one by one.
                tracing::warn!("epoll_wait on the quiet fds: {e}; watching them one by one");
                self.quiet = None;
                self.quiet_refused = true;
                return;
            }
        };
        // In the order they were added (the kernel reports them in its own).
        for (k, member) in q.members.iter().enumerate() {
            if self.quiet_events[..n].iter().any(|e| e.data() == k as u64) {
                self.quiet_ready.push(member.token);
            }
        }
    }

    /// Starts a new set: the signalfd, the wake-up timer, the external inputs (if
    /// `take_input`) and the external outputs with frames queued.
    pub(crate) fn reset(
        &mut self,
        signals: &SignalFd,
        timer: &WakeTimer,
        inputs: &[ExternalInput],
        take_input: bool,
        outputs: &[ExternalOutput],
    ) {
        self.fds.clear();
        self.tokens.clear();
        self.owners.clear();
        self.quiet_wanted.clear();
        self.add_quiet(signals.as_raw_fd(), Token::Signal, 0);
        self.add_quiet(timer.fd.as_fd().as_raw_fd(), Token::Timer, 0);
        let now = Instant::now();
        for (i, input) in inputs.iter().enumerate() {
            if take_input && input.may_read(now) {
                self.add(
                    input.reader.as_fd().as_raw_fd(),
                    libc::POLLIN,
                    Token::Input(i),
                    0,
                );
            }
        }
        for (o, output) in outputs.iter().enumerate() {
            // Waiting for room for a whole frame: looked at again on a timer (see `core`).
            if output.writer.has_pending() && !output.writer.waiting_for_room() {
                self.add(
                    output.writer.as_fd().as_raw_fd(),
                    libc::POLLOUT,
                    Token::OutputWritable(o),
                    0,
                );
            }
        }
    }

    /// Replica `r`: its pidfd (if `watch_exit`), its open outputs that `may_read` allows, and
    /// its inputs with bytes queued.
    pub(crate) fn add_replica(
        &mut self,
        r: usize,
        rep: &Replica,
        watch_exit: bool,
        may_read: impl Fn(usize) -> bool,
    ) {
        if watch_exit {
            self.add_quiet(rep.pidfd.as_raw_fd(), Token::ReplicaExit(r), rep.pid);
        }
        for (o, out) in rep.outputs.iter().enumerate() {
            if !out.is_closed() && may_read(o) {
                self.add(
                    out.as_fd().as_raw_fd(),
                    libc::POLLIN,
                    Token::ReplicaOutput(r, o),
                    rep.pid,
                );
            }
        }
        if let Some(fd) = rep.stderr.fd() {
            self.add_quiet(fd.as_raw_fd(), Token::ReplicaStderr(r), rep.pid);
        }
        if let Some(fd) = rep.start_pipe.as_ref() {
            self.add(
                fd.as_raw_fd(),
                libc::POLLIN,
                Token::ReplicaStarted(r),
                rep.pid,
            );
        }
        for (i, input) in rep.inputs.iter().enumerate() {
            if input.writer.has_pending() {
                self.add(
                    input.writer.as_fd().as_raw_fd(),
                    libc::POLLOUT,
                    Token::ReplicaInputWritable(r, i),
                    rep.pid,
                );
            }
        }
    }
}

/// When the event loop must wake up at the latest, as a timerfd the wait watches, armed only
/// when the wake-up comes sooner than the one it is armed for.
///
/// A deadline given to `ppoll` as its timeout arms a kernel timer on every wait; when it comes
/// before the CPU's next scheduler tick (4 ms at `HZ=250`), arming it reprograms the CPU's
/// timer, and so does cancelling it when the wait ends early, as it does in every fault-free
/// round. On this VM that cost ~13 µs of CPU per round, in proportion to how often the deadline
/// fell before the tick: at a 2 ms `timeout_us`, most rounds. Deadlines only move later from
/// round to round, so one timer armed for the first round's stays valid for the next ones:
/// it expires early, the loop finds nothing due, and it is armed again for what is due then,
/// once per `timeout_us` or so instead of twice per round.
///
/// That early expiry is not free either: on this VM an hrtimer interrupt costs the CPU it
/// lands on 20–40 µs, and at a 2 ms `timeout_us` it came every 1.8 ms, in whatever round ran
/// then (the one-CPU tail, results.md, stops 40 and 41). So a timer about to expire for
/// nothing is moved instead (one `timerfd_settime`, about 1 µs): when it is due within
/// [`MOVE_WITHIN`] and the wake-up needed now is at least [`MOVE_GAIN`] later. Each move thus
/// pushes the timer at least `MOVE_GAIN` on, so a wake-up that keeps receding by a little (a
/// turn check every 100 µs, for a program that does not stamp its answers) is left to
/// expire, as before, rather than moved every other round.
pub(crate) struct WakeTimer {
    fd: TimerFd,
    /// What it is armed for; `None`: disarmed, or expired.
    armed: Option<Instant>,
}

impl WakeTimer {
    pub(crate) fn new() -> Result<WakeTimer, VoterError> {
        let fd = TimerFd::new(
            ClockId::CLOCK_MONOTONIC,
            TimerFlags::TFD_NONBLOCK | TimerFlags::TFD_CLOEXEC,
        )
        .map_err(|e| io_err("timerfd_create")(e.into()))?;
        Ok(WakeTimer { fd, armed: None })
    }

    /// Makes sure the loop wakes up by `at`: arms the timer unless it already expires by then
    /// (and is not about to expire long before it: `move_instead`).
    pub(crate) fn wake_by(&mut self, at: Instant) -> Result<(), VoterError> {
        let now = Instant::now();
        if self
            .armed
            .is_some_and(|armed| armed <= at && !move_instead(armed, at, now))
        {
            return Ok(());
        }
        // Relative to now on the deadline clock, floored, so never later than `at`; a zero
        // would disarm the timer, so at least a nanosecond.
        let left = at
            .saturating_duration_since(now)
            .max(Duration::from_nanos(1));
        self.fd
            .set(
                Expiration::OneShot(TimeSpec::from_duration(left)),
                TimerSetTimeFlags::empty(),
            )
            .map_err(|e| io_err("timerfd_settime")(e.into()))?;
        self.armed = Some(at);
        Ok(())
    }

    /// The timer expired (the wait saw its fd readable): takes the expiry off the fd.
    pub(crate) fn expired(&mut self) {
        let mut count = [0u8; 8];
        let _ = sys::read(self.fd.as_fd(), &mut count);
        self.armed = None;
    }
}

/// How close to its expiry a timer armed for a sooner wake-up than the one needed is moved.
pub(crate) const MOVE_WITHIN: Duration = Duration::from_micros(50);
/// How much later the wake-up needed must be for such a timer to be moved.
pub(crate) const MOVE_GAIN: Duration = Duration::from_micros(500);

/// Whether a timer armed for `armed`, sooner than the wake-up needed `at`, is moved to `at`
/// now rather than left to expire for nothing: it is due within [`MOVE_WITHIN`] and `at` is
/// at least [`MOVE_GAIN`] after it (see [`WakeTimer`]).
fn move_instead(armed: Instant, at: Instant, now: Instant) -> bool {
    armed.saturating_duration_since(now) < MOVE_WITHIN
        && at.saturating_duration_since(armed) >= MOVE_GAIN
}

/// One `ppoll` on `fds` until something is ready or `deadline` (none: no limit) comes;
/// returns how many fds are ready. The timeout is read off the deadline clock, so it never
/// outlasts the deadline (see `clock`).
pub(crate) fn wait_until(
    fds: &mut [libc::pollfd],
    deadline: Option<Instant>,
) -> Result<usize, VoterError> {
    let timeout = deadline.map(|t| t.saturating_duration_since(Instant::now()));
    // Not `.map_err(io_err("ppoll"))`: that builds its String on every wake-up, error or not.
    sys::ppoll(fds, timeout).map_err(|error| VoterError::Io {
        what: "ppoll".into(),
        error,
    })
}

impl ExternalInput {
    /// Whether a read may find something new: it is open, and not a peek stalled on a partial
    /// frame (looked at again on a timer).
    pub(crate) fn may_read(&self, now: Instant) -> bool {
        let stalled = self
            .peek
            .as_ref()
            .and_then(|p| p.stalled_until)
            .is_some_and(|t| t > now);
        !self.reader.is_closed() && !stalled
    }

    /// One read from upstream into the decoder (a peek, if journaled); an end or an error
    /// closes the input (logged).
    pub(crate) fn read(&mut self) {
        let filled = match self.peek.as_mut() {
            None => self.reader.fill(),
            Some(p) => {
                let filled = self.reader.peek_fill(&p.pipe, p.replay_left);
                let partial = !self.reader.decoder.has_frame()
                    && self.reader.decoder.pending() > p.replay_left;
                p.stalled_until = partial.then(|| Instant::now() + PEEK_STALL);
                filled
            }
        };
        match filled {
            Ok(Fill::Open) => {}
            Ok(Fill::Closed) => {
                if let Err(e) = self.reader.decoder.finish() {
                    tracing::warn!(input = %self.name, error = %e, "input closed mid-frame");
                }
                tracing::debug!(input = %self.name, "input closed");
            }
            Err(e) => {
                tracing::error!(input = %self.name, error = %e, "reading input failed; treating it as closed");
                self.reader.close();
            }
        }
    }
}

/// The heartbeat page bootstrap watches (see `replica_rt::heartbeat`), if it gave us one.
static HEARTBEAT: std::sync::OnceLock<Heartbeat> = std::sync::OnceLock::new();

/// The longest the loop sleeps without a beat: bootstrap's deadline is seconds, so this only
/// has to be well below that, and costs a wake-up ten times a second on an idle voter.
pub(crate) const HEARTBEAT_PERIOD: Duration = Duration::from_millis(100);

/// One more turn of the loop, for bootstrap's watch.
pub(crate) fn beat() {
    if let Some(h) = HEARTBEAT.get() {
        h.beat();
    }
}

/// The voter is ending: its waits are bounded by its own limits from here on, and bootstrap
/// stops judging it by its heartbeat.
pub(crate) fn heartbeat_ending() {
    if let Some(h) = HEARTBEAT.get() {
        h.set_ending();
    }
}

/// Reads the signalfd: reaps on SIGCHLD; `true` if SIGTERM/SIGINT came.
///
/// A stop is normally the supervisor's (bootstrap's, also as its parent-death signal, which
/// names the dead bootstrap) or the terminal's (the kernel's, to the whole foreground group,
/// bootstrap included): then the system stops, and the voter ends cleanly with it. A stop
/// signal that another process sent may end this component alone, and nothing else would say
/// so (the voter exited 0 and bootstrap blamed the components starved by it): it is kept for
/// the exit ([`stray_stop`]).
pub(crate) fn stop_requested(signals: &SignalFd) -> bool {
    let mut stop = false;
    while let Ok(Some(info)) = signals.read_signal() {
        match info.ssi_signo as i32 {
            libc::SIGCHLD => reap_children(),
            sig => {
                note_stop(sig, info.ssi_pid);
                stop = true;
            }
        }
    }
    stop
}

/// Notes a stop signal `sig` from process `from` (0: the kernel): the supervisor's, or stray.
fn note_stop(sig: libc::c_int, from: u32) {
    // From itself: bootstrap was gone when it started (`Endpoints::open`).
    if from == 0 || Some(&from) == SUPERVISOR.get() || from == std::process::id() {
        tracing::info!(signal = sig, "stop requested");
        SUPERVISOR_STOPPED.store(true, std::sync::atomic::Ordering::Relaxed);
    } else {
        // A signal to the whole process group (a terminal's Ctrl-C sent by a shell, timeout(1),
        // Slurm) reaches bootstrap too, and the system stops: said at the exit only if it does
        // not (`stray_stop`), not here by every voter (five warnings for one Ctrl-C before).
        tracing::debug!(signal = sig, from, "stop requested, not by bootstrap");
        let _ = STRAY_STOP.set(StrayStop {
            signal: sig,
            from: from as libc::pid_t,
        });
    }
}

/// The voter's parent when it started: bootstrap (or whoever runs it). Not the parent of the
/// moment: when bootstrap dies, the voter is handed to a reaper before the parent-death signal
/// comes, and that signal names bootstrap.
static SUPERVISOR: std::sync::OnceLock<u32> = std::sync::OnceLock::new();

/// bootstrap's pid as it gave it ([`ENV_SUPERVISOR_PID`]), or the parent of the moment.
fn supervisor_pid() -> u32 {
    std::env::var(replica_rt::contract::ENV_SUPERVISOR_PID)
        .ok()
        .and_then(|v| v.parse().ok())
        .filter(|&pid: &u32| pid > 1)
        .unwrap_or_else(std::os::unix::process::parent_id)
}

/// A stop came from the supervisor or the kernel (the system stops).
static SUPERVISOR_STOPPED: std::sync::atomic::AtomicBool =
    std::sync::atomic::AtomicBool::new(false);

/// How long a voter stopped by another process waits for the system's stop: a signal sent to a
/// whole process group or cgroup (timeout(1), pkill, systemd, Slurm) reaches it before
/// bootstrap, which gets it too, has marked the heartbeat pages (`set_system_stopping`).
const SUPERVISOR_GRACE: Duration = Duration::from_millis(200);

/// A stop signal that neither bootstrap nor the terminal sent: which, and from whom.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StrayStop {
    pub signal: libc::c_int,
    pub from: libc::pid_t,
}

/// The first [`StrayStop`] this voter got, if one came.
static STRAY_STOP: std::sync::OnceLock<StrayStop> = std::sync::OnceLock::new();

/// Whether this voter was stopped by a signal that another process than bootstrap sent, and
/// the system did not stop meanwhile (see [`stop_requested`]); its exit should say so. Waits
/// up to [`SUPERVISOR_GRACE`] for bootstrap to mark the system stopping, if it has not yet.
pub fn stray_stop() -> Option<StrayStop> {
    use std::sync::atomic::Ordering;
    let stray = *STRAY_STOP.get()?;
    let deadline = Instant::now() + SUPERVISOR_GRACE;
    let system_stops = || {
        SUPERVISOR_STOPPED.load(Ordering::Relaxed)
            || HEARTBEAT.get().is_some_and(Heartbeat::system_stopping)
    };
    while !system_stops() {
        if Instant::now() >= deadline {
            return Some(stray);
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    None
}

/// What a voter opens before it starts replicas, whatever its mode.
pub(crate) struct Endpoints {
    pub(crate) signals: SignalFd,
    pub(crate) inputs: Vec<ExternalInput>,
    pub(crate) outputs: Vec<ExternalOutput>,
    pub(crate) events: Option<OwnedFd>,
    pub(crate) listener: UnixListener,
    /// The journal's memfd, if bootstrap gave one (`journal.rs`).
    pub(crate) journal: Option<OwnedFd>,
    /// Where an unmodified program's pipes are parked (`park.rs`), if bootstrap made it.
    pub(crate) park: Option<(OwnedFd, OwnedFd)>,
    /// The replicas' answer-stamp page, if bootstrap made it (`replica_rt::stamps`).
    pub(crate) stamps: Option<OwnedFd>,
}

impl Endpoints {
    /// Becomes a subreaper, takes the signals, adopts the fds named in `plan`, binds the socket.
    pub(crate) fn open(plan: &VoterPlan) -> Result<Endpoints, VoterError> {
        // Orphans (children of a donor that died) come to us, so they are reaped and killed.
        sys::set_child_subreaper().map_err(io_err("becoming a child subreaper"))?;
        let supervisor = supervisor_pid();
        let _ = SUPERVISOR.set(supervisor);
        let signals = sys::signal_fd(&[Signal::SIGTERM, Signal::SIGINT, Signal::SIGCHLD])
            .map_err(|e| io_err("blocking signals (signalfd)")(e.into()))?;
        // Once SIGTERM goes to the signalfd: a stop like any other.
        match sys::ask_parent_death_signal(supervisor as libc::pid_t, libc::SIGTERM) {
            Ok(true) => {}
            Ok(false) => {
                tracing::warn!(
                    supervisor,
                    "bootstrap is gone before this voter started: stopping"
                );
                // The signal that will not come, sent now: the loop's first look at the
                // signalfd stops the voter, as bootstrap's death would have.
                if let Err(e) = sys::kill(std::process::id() as libc::pid_t, libc::SIGTERM) {
                    return Err(io_err("stopping, bootstrap gone")(e));
                }
            }
            Err(e) => tracing::warn!(
                error = %e,
                "could not ask for a signal at bootstrap's death: this voter may outlive it"
            ),
        }
        let mut adopted = Inherited::default();

        let inputs = plan
            .inputs
            .iter()
            .map(|p| {
                let round = plan.rounds.iter().find(|r| r.input == p.name).map(|r| {
                    r.outputs.iter().fold(0, |set, name| {
                        set | 1 << plan.outputs.iter().position(|o| &o.name == name).unwrap()
                    })
                });
                Ok(ExternalInput {
                    name: p.name.clone(),
                    reader: FrameReader::resuming(adopted.take(p.fd, &p.name)?, p.max_frame)
                        .map_err(io_err(format!("input `{}` (fd {})", p.name, p.fd)))?,
                    round,
                    peek: None,
                })
            })
            .collect::<Result<Vec<_>, VoterError>>()?;
        let outputs = plan
            .outputs
            .iter()
            .map(|p| {
                Ok(ExternalOutput {
                    name: p.name.clone(),
                    writer: FrameWriter::new(adopted.take(p.fd, &p.name)?)
                        .map_err(io_err(format!("output `{}` (fd {})", p.name, p.fd)))?,
                    broken: false,
                    failed: None,
                    sent: 0,
                })
            })
            .collect::<Result<Vec<_>, VoterError>>()?;
        let events = plan
            .events_fd
            .map(|fd| adopted.take(fd, "events"))
            .transpose()?;
        if let Some(fd) = plan.heartbeat_fd {
            let page = Heartbeat::adopt(adopted.take(fd, "heartbeat")?)
                .map_err(io_err(format!("heartbeat (fd {fd})")))?;
            if plan.adopt.is_some() {
                // The predecessor may have died while ending; this voter is judged afresh.
                page.clear_ending();
            }
            // A second voter in this process (tests) keeps the first page: one is watched.
            let _ = HEARTBEAT.set(page);
        }

        let journal = plan
            .journal_fd
            .map(|fd| adopted.take(fd, "journal"))
            .transpose()?;
        let park = match plan.park_fds {
            Some([tx, rx]) => Some((adopted.take(tx, "park")?, adopted.take(rx, "park")?)),
            None => None,
        };
        let stamps = plan
            .stamps_fd
            .map(|fd| adopted.take(fd, "answer stamps"))
            .transpose()?;
        let listener = match plan.socket_fd {
            // Bound and listening already: bootstrap keeps it across voters.
            Some(fd) => UnixListener::from(adopted.take(fd, "socket")?),
            None => {
                let _ = std::fs::remove_file(&plan.socket_path);
                let listener = UnixListener::bind(&plan.socket_path)
                    .map_err(io_err(format!("binding {}", plan.socket_path.display())))?;
                // Only our own user may connect; SO_PEERCRED narrows it to the donor's child.
                let _ = std::fs::set_permissions(
                    &plan.socket_path,
                    std::fs::Permissions::from_mode(0o600),
                );
                listener
            }
        };
        listener.set_nonblocking(true).map_err(io_err("socket"))?;
        Ok(Endpoints {
            signals,
            inputs,
            outputs,
            events,
            listener,
            journal,
            park,
            stamps,
        })
    }
}

/// Writes one event line to the events fd (and traces it).
pub(crate) fn write_event(events: Option<&OwnedFd>, ev: &Event) {
    // Bootstrap logs every event it gathers; here they are only traced, so that a run
    // shows each event once. Without an events fd, the voter's own log is all there is.
    if events.is_some() {
        tracing::debug!("event: {ev}");
    } else {
        tracing::warn!("event: {ev}");
    }
    let Some(fd) = events else { return };
    let line = ev.to_line();
    let mut bytes = line.as_bytes();
    // One write per line: below PIPE_BUF it is atomic, so lines of several voters never mix.
    while !bytes.is_empty() {
        match sys::write(fd.as_fd(), bytes) {
            Ok(n) => bytes = &bytes[n..],
            Err(e) => {
                tracing::warn!(error = %e, "cannot write events");
                return;
            }
        }
    }
}

/// The fds taken over from bootstrap, each once.
#[derive(Default)]
struct Inherited(Vec<RawFd>);

impl Inherited {
    /// Takes ownership of `fd`, which the plan names for `what`: an error if it is not open,
    /// is a standard stream, or was named twice.
    fn take(&mut self, fd: RawFd, what: &str) -> Result<OwnedFd, VoterError> {
        if self.0.contains(&fd) {
            return Err(VoterError::Plan(format!(
                "fd {fd} (`{what}`) is named twice in the plan"
            )));
        }
        self.0.push(fd);
        // SAFETY: `fd` comes from the plan bootstrap started this voter with, which hands each
        // fd to exactly one port (checked just above: each number is adopted once), and no
        // other code of the voter touches the inherited numbers.
        unsafe { sys::try_adopt_inherited_fd(fd) }
            .map_err(io_err(format!("`{what}` (inherited fd {fd})")))
    }
}

/// Reaps every child that has exited (replicas we started, orphans re-parented to us).
pub(crate) fn reap_children() {
    while let Ok(Some((pid, status))) = sys::reap_any() {
        tracing::trace!(pid, %status, "reaped");
        remember_exit(pid, status);
    }
}

/// How many exit statuses of reaped children are kept for [`exit_of`].
const EXITS_KEPT: usize = 64;

thread_local! {
    /// The latest reaped children and how they ended (the voter is single-threaded).
    static EXITS: std::cell::RefCell<std::collections::VecDeque<(libc::pid_t, sys::ExitStatus)>> =
        const { std::cell::RefCell::new(std::collections::VecDeque::new()) };
}

fn remember_exit(pid: libc::pid_t, status: sys::ExitStatus) {
    EXITS.with_borrow_mut(|exits| {
        if exits.len() == EXITS_KEPT {
            exits.pop_front();
        }
        exits.push_back((pid, status));
    });
}

/// How child `pid` ended: reaped now if it has exited, or found among the children reaped
/// before (on SIGCHLD). `None` while it runs, or if it is not our child (a fork child belongs
/// to its donor, whose exit status the kernel discards).
pub(crate) fn exit_of(pid: libc::pid_t) -> Option<sys::ExitStatus> {
    if let Ok(Some((_, status))) = sys::reap(pid) {
        remember_exit(pid, status);
    }
    EXITS.with_borrow(|exits| {
        exits
            .iter()
            .rev()
            .find(|&&(p, _)| p == pid)
            .map(|&(_, s)| s)
    })
}

/// Kills every child of ours until none is left (or `limit` passes). As a subreaper we inherit
/// the children of dying children, so this converges on the whole subtree.
pub(crate) fn kill_all_children(limit: Duration) {
    let report = sys::sweep_children(limit);
    if !report.resisted.is_empty() {
        tracing::error!(children = ?report.resisted, "children survived SIGKILL");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn readable(timer: &WakeTimer, within: Duration) -> bool {
        let mut pfd = [libc::pollfd {
            fd: timer.fd.as_fd().as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        }];
        sys::ppoll(&mut pfd, Some(within)).unwrap() == 1
    }

    #[test]
    fn the_wake_timer_is_armed_only_for_a_sooner_wake_up() {
        crate::clock::init().unwrap();
        let mut timer = WakeTimer::new().unwrap();
        // Seconds ahead: a stall of the test (a loaded machine) must not bring it within
        // MOVE_WITHIN, where a later wake-up would move it.
        let soon = Instant::now() + Duration::from_secs(10);
        timer.wake_by(soon).unwrap();
        assert_eq!(timer.armed, Some(soon));
        // A later wake-up keeps the sooner one: the loop wakes early and arms again.
        timer.wake_by(soon + Duration::from_secs(5)).unwrap();
        assert_eq!(timer.armed, Some(soon));
        // A sooner one re-arms.
        let sooner = Instant::now() + Duration::from_millis(5);
        timer.wake_by(sooner).unwrap();
        assert_eq!(timer.armed, Some(sooner));
        assert!(readable(&timer, Duration::from_secs(2)), "it expires");
        timer.expired();
        assert_eq!(timer.armed, None);
        assert!(
            !readable(&timer, Duration::ZERO),
            "the expiry was taken off"
        );
        // A wake-up already due fires at once.
        timer.wake_by(Instant::now()).unwrap();
        assert!(readable(&timer, Duration::from_secs(2)));
    }

    #[test]
    fn a_timer_about_to_expire_for_nothing_is_moved_to_the_wake_up_needed() {
        crate::clock::init().unwrap();
        let now = Instant::now();
        let ms = Duration::from_millis;
        let us = Duration::from_micros;
        // Due within MOVE_WITHIN, and the wake-up needed far later: moved.
        assert!(move_instead(now + us(20), now + ms(2), now));
        // Already due (expired, not yet taken off): moved too.
        assert!(move_instead(now, now + ms(2), now));
        // Due later than MOVE_WITHIN: left, it may still be moved nearer its expiry.
        assert!(!move_instead(now + us(60), now + ms(2), now));
        // The wake-up needed only a little later (a turn check moving on): left to expire.
        assert!(!move_instead(now + us(20), now + us(120), now));
        assert!(!move_instead(
            now + us(20),
            now + us(20) + MOVE_GAIN - us(1),
            now
        ));
        assert!(move_instead(now + us(20), now + us(21) + MOVE_GAIN, now));

        let mut timer = WakeTimer::new().unwrap();
        let soon = Instant::now() + us(10);
        timer.wake_by(soon).unwrap();
        let later = soon + Duration::from_secs(5);
        timer.wake_by(later).unwrap();
        assert_eq!(timer.armed, Some(later), "moved");
        assert!(
            !readable(&timer, ms(50)),
            "the timer moved does not expire at its old time"
        );
        // Armed far ahead, a later wake-up keeps it (moved only near its expiry).
        let far = Instant::now() + Duration::from_secs(10);
        let mut timer = WakeTimer::new().unwrap();
        timer.wake_by(far).unwrap();
        timer.wake_by(far + Duration::from_secs(5)).unwrap();
        assert_eq!(timer.armed, Some(far));
    }

    /// The quiet fds the wait found ready, through the one epoll fd.
    fn quiet_ready(set: &mut PollSet) -> Vec<Token> {
        set.fds.clear();
        set.tokens.clear();
        set.seal();
        assert_eq!(
            set.tokens,
            [Token::Quiet],
            "the quiet fds are one fd in the wait"
        );
        let ready = sys::ppoll(&mut set.fds, Some(Duration::ZERO)).unwrap();
        set.quiet_ready.clear();
        if ready > 0 {
            set.ready_quiet();
        }
        set.quiet_ready.clone()
    }

    #[test]
    fn quiet_fds_are_watched_through_one_epoll_fd_and_never_for_a_replaced_owner() {
        let (r1, w1) = sys::pipe().unwrap();
        let (r2, w2) = sys::pipe().unwrap();
        let mut set = PollSet::default();
        let want = |set: &mut PollSet, r1: RawFd, r2: RawFd, owner2: libc::pid_t| {
            set.quiet_wanted.clear();
            set.add_quiet(r1, Token::ReplicaExit(0), 100);
            set.add_quiet(r2, Token::ReplicaStderr(1), owner2);
        };
        want(&mut set, r1.as_raw_fd(), r2.as_raw_fd(), 200);
        assert!(quiet_ready(&mut set).is_empty(), "nothing written yet");
        sys::write(w2.as_fd(), b"x").unwrap();
        sys::write(w1.as_fd(), b"x").unwrap();
        // Both, in the order they were added, whatever order the kernel saw them in.
        assert_eq!(
            quiet_ready(&mut set),
            [Token::ReplicaExit(0), Token::ReplicaStderr(1)]
        );
        let epoll_before = set.quiet.as_ref().unwrap().epoll.0.as_raw_fd();
        want(&mut set, r1.as_raw_fd(), r2.as_raw_fd(), 200);
        quiet_ready(&mut set);
        assert_eq!(
            set.quiet.as_ref().unwrap().epoll.0.as_raw_fd(),
            epoll_before,
            "an unchanged set keeps its epoll instance"
        );

        // Replica 1 is replaced: its pipe closes and a new one comes, most often under the
        // same fd number. A new owner means a new epoll instance, so the old file (which a
        // stale registration would keep watching under the number) is not, and the new one is.
        drop(r2);
        drop(w2);
        let (r3, w3) = sys::pipe().unwrap();
        want(&mut set, r1.as_raw_fd(), r3.as_raw_fd(), 300);
        let mut buf = [0u8; 8];
        sys::read(r1.as_fd(), &mut buf).unwrap();
        assert!(quiet_ready(&mut set).is_empty(), "the new pipe is empty");
        assert_ne!(
            set.quiet.as_ref().unwrap().epoll.0.as_raw_fd(),
            epoll_before,
            "a new owner, a new epoll instance"
        );
        sys::write(w3.as_fd(), b"y").unwrap();
        assert_eq!(quiet_ready(&mut set), [Token::ReplicaStderr(1)]);
    }

    /// One wait on `(fd, token, owner)`s (each watched for input), as the loop makes it: the
    /// ready tokens, and the wait instance's fd.
    fn wait_on(set: &mut PollSet, fds: &[(RawFd, Token, libc::pid_t)]) -> (Vec<Token>, RawFd) {
        set.fds.clear();
        set.tokens.clear();
        set.owners.clear();
        set.quiet_wanted.clear();
        for &(fd, token, owner) in fds {
            set.add(fd, libc::POLLIN, token, owner);
        }
        set.seal();
        let n = set.wait(None).unwrap().0;
        let ready: Vec<Token> = (set.fds.iter().zip(&set.tokens))
            .filter(|(p, _)| p.revents != 0)
            .map(|(_, &t)| t)
            .collect();
        assert_eq!(ready.len(), n, "as many ready as the wait said");
        let epoll = latest(set).expect("waited with epoll").epoll.0.as_raw_fd();
        (ready, epoll)
    }

    /// The instance used last.
    fn latest(set: &PollSet) -> Option<&WaitEpoll> {
        set.waits.iter().max_by_key(|w| w.used)
    }

    /// `n` pipes, each with a byte to read.
    fn ready_pipes(n: usize) -> Vec<(OwnedFd, OwnedFd)> {
        let pipes: Vec<(OwnedFd, OwnedFd)> = (0..n).map(|_| sys::pipe().unwrap()).collect();
        for (_, w) in &pipes {
            sys::write(w.as_fd(), b"x").unwrap();
        }
        pipes
    }

    /// The pipe a one-pipe set's instance watches: the quiet instance is the first member of
    /// every set, the pipe the last.
    fn pipe_of(w: &WaitEpoll) -> RawFd {
        w.members().last().unwrap().fd
    }

    #[test]
    fn a_wait_sees_what_ppoll_sees_and_never_a_replaced_owners_old_pipe() {
        let (in_r, in_w) = sys::pipe().unwrap();
        let (out_r, out_w) = sys::pipe().unwrap();
        let mut set = PollSet::default();
        let input = (in_r.as_raw_fd(), Token::Input(0), 0);
        let answer = |fd: &OwnedFd, pid| (fd.as_raw_fd(), Token::ReplicaOutput(0, 0), pid);

        sys::write(in_w.as_fd(), b"i").unwrap();
        let (ready, idle) = wait_on(&mut set, &[input, answer(&out_r, 100)]);
        assert_eq!(ready, [Token::Input(0)]);
        let mut buf = [0u8; 8];
        sys::read(in_r.as_fd(), &mut buf).unwrap();

        // In a round: only the replica's pipe, a set of its own.
        sys::write(out_w.as_fd(), b"a").unwrap();
        let (ready, round) = wait_on(&mut set, &[answer(&out_r, 100)]);
        assert_eq!(ready, [Token::ReplicaOutput(0, 0)]);
        assert_ne!(round, idle, "another set, another instance");
        sys::read(out_r.as_fd(), &mut buf).unwrap();

        // Idle again: the same instance, level-triggered as ppoll is (the input was written
        // while it was not waited on).
        sys::write(in_w.as_fd(), b"j").unwrap();
        let (ready, again) = wait_on(&mut set, &[input, answer(&out_r, 100)]);
        assert_eq!(ready, [Token::Input(0)]);
        assert_eq!(again, idle, "an unchanged set keeps its instance");
        let (ready, _) = wait_on(&mut set, &[input, answer(&out_r, 100)]);
        assert_eq!(ready, [Token::Input(0)], "still there: nothing read it");
        sys::read(in_r.as_fd(), &mut buf).unwrap();

        // The writer ends: a hang-up, as ppoll reports it, though only input was asked for.
        drop(in_w);
        let (ready, _) = wait_on(&mut set, &[input, answer(&out_r, 100)]);
        assert_eq!(ready, [Token::Input(0)]);
        let k = set
            .tokens
            .iter()
            .position(|&t| t == Token::Input(0))
            .unwrap();
        assert_ne!(set.fds[k].revents & libc::POLLHUP, 0);

        // The replica is replaced: its pipe closes and a new one comes under the same number.
        // The old pipe lives on elsewhere (as a parked copy would), so the old instances keep
        // its registration; a new owner means a new instance, which watches the new pipe.
        let _parked = out_r.try_clone().unwrap();
        let (fresh_r, new_w) = sys::pipe().unwrap();
        let mut new_r = out_r;
        nix::unistd::dup2(&fresh_r, &mut new_r).unwrap();
        drop(fresh_r);
        sys::write(out_w.as_fd(), b"old").unwrap();
        // The old pipe is ready, the new one is not: the wait must last until the new one is
        // written (a stale instance would return at once, for the old pipe).
        let written = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let writer = std::thread::spawn({
            let written = written.clone();
            move || {
                std::thread::sleep(Duration::from_millis(100));
                written.store(true, std::sync::atomic::Ordering::SeqCst);
                sys::write(new_w.as_fd(), b"new").unwrap();
            }
        });
        let (ready, replaced) = wait_on(&mut set, &[answer(&new_r, 200)]);
        assert!(
            written.load(std::sync::atomic::Ordering::SeqCst),
            "the wait returned for the replaced replica's old pipe"
        );
        writer.join().unwrap();
        assert_eq!(ready, [Token::ReplicaOutput(0, 0)]);
        assert_ne!(replaced, round, "a new owner, a new instance");
        let mut got = [0u8; 8];
        let n = sys::read(new_r.as_fd(), &mut got).unwrap();
        assert_eq!(&got[..n], b"new");
    }

    /// A spin sees what the sleep would: an answer that comes while it spins ends it; one that
    /// comes after it is waited for asleep.
    #[test]
    fn a_spinning_wait_returns_what_comes_during_the_spin_or_after_it() {
        let (r, w) = sys::pipe().unwrap();
        let mut set = PollSet::default();
        let writes_after = |delay: Duration| {
            let w = w.try_clone().unwrap();
            std::thread::spawn(move || {
                std::thread::sleep(delay);
                sys::write(w.as_fd(), b"x").unwrap();
            })
        };
        let wait = |set: &mut PollSet, spin: Duration| {
            set.fds.clear();
            set.tokens.clear();
            set.owners.clear();
            set.add(r.as_raw_fd(), libc::POLLIN, Token::ReplicaOutput(0, 0), 7);
            set.seal();
            let (n, spun) = set.wait(Some(spin)).unwrap();
            let ready: Vec<Token> = (set.fds.iter().zip(&set.tokens))
                .filter(|(p, _)| p.revents != 0)
                .map(|(_, &t)| t)
                .collect();
            assert_eq!((n, ready), (1, vec![Token::ReplicaOutput(0, 0)]));
            let mut buf = [0u8; 1];
            assert_eq!(sys::read(r.as_fd(), &mut buf).unwrap(), 1);
            spun
        };
        // The answer within a spin of 10 s: found spinning (the spin did not run out).
        let writer = writes_after(Duration::from_millis(5));
        let spun = wait(&mut set, Duration::from_secs(10));
        writer.join().unwrap();
        assert!(spun < Duration::from_secs(10), "{spun:?}");
        // Already there: found at the first look.
        sys::write(w.as_fd(), b"x").unwrap();
        assert!(wait(&mut set, Duration::from_secs(10)) < Duration::from_secs(10));
        // The answer long after a spin of 1 µs: the spin ran out, the sleep found it.
        let writer = writes_after(Duration::from_millis(50));
        let spun = wait(&mut set, Duration::from_micros(1));
        writer.join().unwrap();
        assert!(spun >= Duration::from_micros(1), "{spun:?}");
        assert!(spun < Duration::from_millis(50), "spun {spun:?}, not slept");
    }

    #[test]
    fn a_loop_that_churns_through_sets_waits_with_ppoll() {
        let pipes = ready_pipes(MADE_PER_WINDOW as usize + 4);
        let mut set = PollSet::default();
        let mut made = Vec::new();
        for (k, (r, _)) in pipes.iter().enumerate() {
            set.fds.clear();
            set.tokens.clear();
            set.owners.clear();
            set.add(r.as_raw_fd(), libc::POLLIN, Token::Input(k), 0);
            set.seal();
            let before = latest(&set).map(|w| w.epoll.0.as_raw_fd());
            assert_eq!(set.wait(None).unwrap().0, 1);
            assert_ne!(
                set.fds.last().unwrap().revents,
                0,
                "set {k}: the pipe is ready"
            );
            made.push(latest(&set).map(|w| w.epoll.0.as_raw_fd()) != before);
        }
        // Each set was new: the first ones got an instance, the rest of the window waits with
        // ppoll (and still sees what is ready).
        let expected: Vec<bool> = (0..pipes.len())
            .map(|k| k < MADE_PER_WINDOW as usize)
            .collect();
        assert_eq!(made, expected);
        // A new window makes instances again.
        set.waits_in_window = CHURN_WINDOW;
        let (ready, _) = wait_on(&mut set, &[(pipes[0].0.as_raw_fd(), Token::Input(0), 0)]);
        assert_eq!(ready, [Token::Input(0)]);
        assert_eq!(set.made_in_window, 1);
    }

    #[test]
    fn no_more_wait_instances_are_kept_than_a_loop_uses() {
        let pipes = ready_pipes(WAIT_SETS + 2);
        let mut set = PollSet::default();
        for (k, (r, _)) in pipes.iter().enumerate() {
            let (ready, _) = wait_on(&mut set, &[(r.as_raw_fd(), Token::Input(k), 0)]);
            assert_eq!(ready, [Token::Input(k)]);
            assert!(set.waits.len() <= WAIT_SETS);
        }
        assert_eq!(set.waits.len(), WAIT_SETS);
        // The first sets went, the most recent stayed.
        let newest = pipes.last().unwrap().0.as_raw_fd();
        assert_eq!(pipe_of(latest(&set).unwrap()), newest);
        assert!(set
            .waits
            .iter()
            .all(|w| pipe_of(w) != pipes[0].0.as_raw_fd()));
    }

    /// The instance replaced is the one used least recently, not the one made first: a set
    /// waited on again keeps its instance.
    #[test]
    fn the_least_recently_used_wait_instance_goes() {
        let pipes = ready_pipes(WAIT_SETS + 1);
        let on = |k: usize| [(pipes[k].0.as_raw_fd(), Token::Input(k), 0)];
        let mut set = PollSet::default();
        let mut first = Vec::new();
        for k in 0..WAIT_SETS {
            first.push(wait_on(&mut set, &on(k)).1);
        }
        // Set 0 again: the same instance, now the most recent.
        assert_eq!(wait_on(&mut set, &on(0)).1, first[0]);
        // A new set takes the place of set 1's instance, the least recently used.
        let (ready, _) = wait_on(&mut set, &on(WAIT_SETS));
        assert_eq!(ready, [Token::Input(WAIT_SETS)]);
        assert_eq!(set.waits.len(), WAIT_SETS);
        let kept: Vec<RawFd> = set.waits.iter().map(pipe_of).collect();
        assert!(kept.contains(&pipes[0].0.as_raw_fd()), "set 0 went");
        assert!(!kept.contains(&pipes[1].0.as_raw_fd()), "set 1 stayed");
        assert_eq!(wait_on(&mut set, &on(0)).1, first[0]);
        for (k, &epoll) in first.iter().enumerate().skip(2) {
            assert_eq!(wait_on(&mut set, &on(k)).1, epoll, "set {k}");
        }
    }
}
