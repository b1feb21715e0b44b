//! The voter's event loop for reactive mode (S³RES VoterM).
//!
//! Between rounds the voter reads its external inputs. A frame on a round-starting input is
//! copied to every replica and opens a [`Round`]; other inputs are copied without one. During a
//! round, answers are collected and voted ([`crate::vote`]); a winner is forwarded as soon as it
//! has a majority. A round closes when every trusted replica has answered, or at its deadline.
//! Faults are recorded the moment they are seen (a dead replica through its pidfd, not at the
//! deadline) and the faulty replica is killed at once; it is *replaced* after the round closes,
//! when the healthy replicas are idle, so that a donor is forked at a quiet point.

use std::io;
use std::os::fd::{AsFd, AsRawFd, OwnedFd, RawFd};
use std::os::unix::fs::PermissionsExt;
use std::os::unix::net::UnixListener;
use std::time::Duration;

use nix::sys::signal::{SigSet, Signal};
use nix::sys::signalfd::{SfdFlags, SignalFd};
use replica_rt::frame::FrameError;
use replica_rt::sys;
use thiserror::Error;

use crate::channel::{Fill, FrameReader, FrameWriter};
use crate::clock::{self, ClockError, Deadlines, Instant, Timer};
use crate::event::{Event, EventKind, RecoveryMethod};
use crate::monitor::{Captures, Monitors};
use crate::plan::{Mode, VoterPlan};
use crate::recovery;
use crate::replica::Replica;
use crate::round::{OutputSet, Round};
use crate::rt::RealTime;
use crate::sched::Schedule;
use crate::vote::{bitwise_majority, vote, BitMajority, ReplicaSet, VoteOutcome, MAX_REPLICAS};

/// How long a replica whose output pipe closed may take to show up as dead before we call it a
/// protocol fault instead of a crash. The kernel closes a dying process's fds before it signals
/// the exit, so the two are seen a moment apart.
pub(crate) const EXIT_AFTER_EOF: Duration = Duration::from_millis(50);
/// How long replicas get to exit by themselves after their input is closed at the end.
pub(crate) const SHUTDOWN_GRACE: Duration = Duration::from_secs(2);
/// How long downstream gets to take the last voted frames at the end.
pub(crate) const OUTPUT_DRAIN_LIMIT: Duration = Duration::from_secs(10);
/// How long to wait for a killed replica to be gone before recovering its slot anyway.
pub(crate) const DEATH_WAIT: Duration = Duration::from_secs(1);

#[derive(Debug, Error)]
pub enum VoterError {
    #[error("invalid plan: {0}")]
    Plan(String),
    #[error("{what}: {source}")]
    Io {
        what: String,
        #[source]
        source: io::Error,
    },
    #[error("component failed beyond recovery: {0}")]
    Unrecoverable(String),
    #[error(transparent)]
    Clock(#[from] ClockError),
}

pub(crate) fn io_err(what: impl Into<String>) -> impl FnOnce(io::Error) -> VoterError {
    let what = what.into();
    move |source| VoterError::Io { what, source }
}

/// An input of the protected component: read by the voter, copied to every replica.
pub(crate) struct ExternalInput {
    pub(crate) name: String,
    pub(crate) reader: FrameReader,
    /// The outputs a frame on this input expects (its round), or `None` if it starts none.
    round: Option<OutputSet>,
}

/// An output of the protected component: the voter writes the winners here.
pub(crate) struct ExternalOutput {
    pub(crate) name: String,
    pub(crate) writer: FrameWriter,
    /// The reader went away; later frames are dropped (said once).
    pub(crate) broken: bool,
}

impl ExternalOutput {
    /// Queues `frame` for downstream and writes what the pipe takes now.
    pub(crate) fn send(&mut self, frame: &[u8]) {
        if self.broken {
            return;
        }
        if let Err(e) = self.writer.send(frame) {
            tracing::warn!(output = %self.name, error = %e, "downstream is gone; dropping further output");
            self.broken = true;
            self.writer.discard();
        }
    }

    /// Writes what is queued, as far as the pipe takes it now.
    pub(crate) fn flush(&mut self) {
        if let Err(e) = self.writer.flush() {
            if !self.broken {
                tracing::warn!(output = %self.name, error = %e, "downstream is gone; dropping further output");
                self.broken = true;
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

/// A replica that was found faulty and killed, waiting to be replaced.
pub(crate) struct Fault {
    pub(crate) slot: usize,
    pub(crate) replica: Replica,
    pub(crate) detected_ns: u64,
}

/// Why the loop ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Stop {
    /// Every input closed: let replicas finish, then exit cleanly.
    InputsClosed,
    /// SIGTERM/SIGINT.
    Requested,
}

/// What a slot of the poll set stands for.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Token {
    Signal,
    Input(usize),
    OutputWritable(usize),
    ReplicaExit(usize),
    ReplicaOutput(usize, usize),
    ReplicaInputWritable(usize, usize),
}

pub struct Voter {
    plan: VoterPlan,
    inputs: Vec<ExternalInput>,
    outputs: Vec<ExternalOutput>,
    slots: Vec<Option<Replica>>,
    /// `answers[slot][output]`: buffers reused from round to round.
    answers: Vec<Vec<Vec<u8>>>,
    faults: Vec<Fault>,
    round: Option<Round>,
    rounds_started: u64,
    /// Names the current fork attempt; a child of an older attempt is refused.
    restart_nonce: u32,
    listener: UnixListener,
    signals: SignalFd,
    events: Option<OwnedFd>,
    stop: Option<Stop>,
    poll: PollSet,
    /// Every deadline the loop waits for (refilled from the state before each wait).
    timers: Deadlines,
    /// Priorities, pinning and the raising of turns.
    rt: RealTime,
    /// Anomaly detectors on the outputs (see [`Voter::try_forward`] and [`Voter::close_round`]
    /// for what an alarm does).
    monitors: Monitors,
    /// Voted frames written to files (training data).
    captures: Captures,
}

impl Voter {
    /// Takes over the fds named in `plan`, binds the socket, and starts the replicas.
    pub fn start(plan: VoterPlan) -> Result<Voter, VoterError> {
        validate(&plan)?;
        // Calibrated before the first round, so that it never eats into a deadline.
        clock::init()?;
        // Models are checked before any replica starts: a bad one is an error, not a surprise.
        let monitors = Monitors::load(&plan)?;
        let captures = Captures::open(&plan)?;
        let Endpoints {
            signals,
            inputs,
            outputs,
            events,
            listener,
        } = Endpoints::open(&plan)?;

        // Before the first replica: replicas start from the voter's settings.
        let mut rt = RealTime::new(&plan);
        rt.apply_to_voter();

        let n = plan.replicas;
        let n_inputs = plan.inputs.len();
        let slots = start_replicas(&plan, events.as_ref(), |pid, slot| {
            rt.apply_to_replica(pid, slot)
        })?;
        let voter = Voter {
            rt,
            monitors,
            captures,
            answers: vec![vec![Vec::new(); plan.outputs.len()]; n],
            slots,
            plan,
            inputs,
            outputs,
            faults: Vec::new(),
            round: None,
            rounds_started: 0,
            restart_nonce: 0,
            listener,
            signals,
            events,
            stop: None,
            poll: PollSet::default(),
            timers: Deadlines::new(n_inputs, n),
        };
        Ok(voter)
    }

    /// Runs until the inputs close (and the replicas have finished) or a stop is requested.
    pub fn run(mut self) -> Result<(), VoterError> {
        let result = self.run_loop();
        self.shut_down();
        result
    }

    fn run_loop(&mut self) -> Result<(), VoterError> {
        loop {
            if self.round.is_none() {
                self.recover_faulty()?;
                if self.stop == Some(Stop::Requested) {
                    return Ok(());
                }
                self.start_rounds_from_buffered_input();
                if self.round.is_none() && self.stop.is_none() && self.all_inputs_done() {
                    self.stop = Some(Stop::InputsClosed);
                    return self.finish();
                }
            }
            self.wait_and_dispatch()?;
            if self.stop == Some(Stop::Requested) {
                return Ok(());
            }
            self.fault_closed_outputs();
            self.advance_round();
        }
    }

    /// One `ppoll` on everything that can make progress, bounded by the next deadline.
    fn wait_and_dispatch(&mut self) -> Result<(), VoterError> {
        self.build_poll_set();
        let wake = self.next_wakeup();
        let ready = wait_until(&mut self.poll.fds, wake)?;
        if ready == 0 {
            return Ok(());
        }
        for k in 0..self.poll.fds.len() {
            if self.poll.fds[k].revents == 0 {
                continue;
            }
            match self.poll.tokens[k] {
                Token::Signal => self.on_signal(),
                Token::Input(i) => self.on_input_readable(i),
                Token::OutputWritable(o) => self.flush_output(o),
                Token::ReplicaExit(r) => {
                    if self.slots[r].is_some() {
                        self.fault(r, EventKind::Crash, "the replica process died".into());
                    }
                }
                Token::ReplicaOutput(r, o) => self.on_replica_output(r, o),
                Token::ReplicaInputWritable(r, i) => {
                    let flushed = self.slots[r].as_mut().map(|rep| rep.flush_input(i));
                    if let Some(Err(e)) = flushed {
                        let detail =
                            format!("input pipe `{}` broke: {e}", self.plan.inputs[i].name);
                        self.fault(r, EventKind::Protocol, detail);
                    }
                }
            }
        }
        Ok(())
    }

    fn build_poll_set(&mut self) {
        let backlog = self.outputs.iter().any(|o| o.writer.has_pending());
        // New input only between rounds and when downstream keeps up: back-pressure instead
        // of unbounded buffering.
        let take_input = self.round.is_none() && self.faults.is_empty() && !backlog;
        self.poll
            .reset(&self.signals, &self.inputs, take_input, &self.outputs);
        for (r, rep) in self.slots.iter().enumerate() {
            if let Some(rep) = rep {
                self.poll.add_replica(r, rep, true, |_| true);
            }
        }
    }

    fn on_signal(&mut self) {
        if stop_requested(&self.signals) {
            self.stop = Some(Stop::Requested);
        }
    }

    // ----- input side -------------------------------------------------------------------

    fn on_input_readable(&mut self, i: usize) {
        self.inputs[i].read();
        self.start_rounds_from_buffered_input();
    }

    /// Delivers buffered input frames to the replicas until one of them opens a round.
    fn start_rounds_from_buffered_input(&mut self) {
        if !self.faults.is_empty() {
            return;
        }
        for i in 0..self.inputs.len() {
            while self.round.is_none() {
                let input = &mut self.inputs[i];
                let frame = match input.reader.decoder.next_frame() {
                    Ok(Some(f)) => f,
                    Ok(None) => break,
                    Err(e) => {
                        // An upstream neighbour broke the framing; we cannot resynchronise.
                        tracing::error!(input = %input.name, error = %e, "bad frame from upstream; dropping the rest of this input");
                        input.reader.close();
                        break;
                    }
                };
                let round = input.round;
                let mut members = ReplicaSet::EMPTY;
                let mut broken = Vec::new();
                let mut stalled = Vec::new();
                let limit = input_backlog_limit(self.plan.inputs[i].max_frame);
                for (r, rep) in self.slots.iter_mut().enumerate() {
                    let Some(rep) = rep else { continue };
                    match rep.inputs[i].writer.send(frame) {
                        Ok(()) => members = members.with(r),
                        Err(e) => broken.push((r, e)),
                    }
                    let backlog = rep.inputs[i].writer.unwritten().len();
                    if backlog > limit {
                        stalled.push((r, backlog));
                    }
                }
                if let Some(expected) = round {
                    self.rounds_started += 1;
                    let deadline = Instant::now() + self.allowance(members);
                    self.monitors.clear_verdicts();
                    self.round = Some(Round::new(
                        self.rounds_started,
                        i,
                        expected,
                        deadline,
                        members,
                    ));
                    if self.plan.schedule == Schedule::Sequential {
                        self.next_turn();
                    }
                }
                for (r, e) in broken {
                    let detail = format!("input pipe `{}` broke: {e}", self.plan.inputs[i].name);
                    self.fault(r, EventKind::Protocol, detail);
                }
                // A replica that stopped reading an input no round waits on (stopped, spinning,
                // stuck on another port) would make the voter queue for it without end.
                for (r, backlog) in stalled {
                    let detail = format!(
                        "has not taken {backlog} bytes of input on `{}` (limit {limit})",
                        self.plan.inputs[i].name
                    );
                    self.fault(r, EventKind::Hang, detail);
                }
            }
        }
    }

    /// Every input that starts a round is closed (every input, if none starts one). (Called
    /// between rounds, after buffered frames were delivered, so nothing whole is left; a
    /// partial frame left behind can never complete.) Replicas answer only in rounds, so once
    /// no round can start their output is over, whatever their other inputs still carry.
    /// Waiting for those too would deadlock a loop: the navigator's `waypoints` come from a
    /// planner whose voter ends only when the navigator's `request` ends.
    fn all_inputs_done(&self) -> bool {
        let starts_round = |i: &&ExternalInput| i.round.is_some();
        if self.inputs.iter().any(|i| i.round.is_some()) {
            self.inputs
                .iter()
                .filter(starts_round)
                .all(|i| i.reader.is_closed())
        } else {
            self.inputs.iter().all(|i| i.reader.is_closed())
        }
    }

    // ----- output side ------------------------------------------------------------------

    fn flush_output(&mut self, o: usize) {
        self.outputs[o].flush();
    }

    fn forward(&mut self, o: usize, winner: usize) {
        self.outputs[o].send(&self.answers[winner][o]);
        self.captures.record(o, &self.answers[winner][o]);
    }

    fn on_replica_output(&mut self, r: usize, o: usize) {
        let Some(rep) = self.slots[r].as_mut() else {
            return;
        };
        let fill = rep.outputs[o].fill();
        // Decode every whole frame that arrived.
        loop {
            let Some(rep) = self.slots[r].as_mut() else {
                return;
            };
            let frame = match rep.outputs[o].decoder.next_frame() {
                Ok(Some(f)) => f,
                Ok(None) => break,
                Err(e) => {
                    let detail = format!("output `{}`: {e}", self.plan.outputs[o].name);
                    return self.fault(r, EventKind::Protocol, detail);
                }
            };
            let problem = match self.round.as_mut() {
                _ if self.stop.is_some() => Some("frame after the inputs closed"),
                None => Some("frame outside any round"),
                Some(round) if !round.expects(o) => {
                    Some("frame on an output this round does not expect")
                }
                Some(round) if round.has_answered(r, o) => Some("extra frame in one round"),
                Some(round) if !round.members.contains(r) => {
                    Some("frame from a replica that joined after the round began")
                }
                Some(round) => {
                    round.answered[r] |= 1 << o;
                    rep.proven = true;
                    let buf = &mut self.answers[r][o];
                    buf.clear();
                    buf.extend_from_slice(frame);
                    None
                }
            };
            if let Some(problem) = problem {
                let detail = format!("{problem} (output `{}`)", self.plan.outputs[o].name);
                return self.fault(r, EventKind::Protocol, detail);
            }
            // Every answer is scored, also when all agree: each replica's stream of frames
            // must be complete for the next delta to be meaningful.
            if let Some(verdict) = self.monitors.observe(r, o, &self.answers[r][o]) {
                if verdict.alarm {
                    self.anomaly_event(r, o);
                }
            }
            self.try_forward(o);
        }
        match fill {
            Ok(Fill::Open) => {}
            Ok(Fill::Closed) => self.on_output_closed(r),
            Err(e) => {
                let detail = format!("reading output `{}`: {e}", self.plan.outputs[o].name);
                self.fault(r, EventKind::Protocol, detail);
            }
        }
    }

    /// A replica closed an output. The kernel closes a dying process's fds just before it
    /// reports the exit, so this is a crash if the pidfd follows within [`EXIT_AFTER_EOF`] (the
    /// event loop watches it, without blocking), else a protocol fault.
    fn on_output_closed(&mut self, r: usize) {
        if self.slots[r]
            .as_mut()
            .is_some_and(Replica::note_output_closed)
        {
            self.fault(r, EventKind::Crash, "the replica process died".into());
        }
    }

    /// Replicas whose output closed more than [`EXIT_AFTER_EOF`] ago and which still live.
    fn fault_closed_outputs(&mut self) {
        for r in 0..self.slots.len() {
            let verdict = self.slots[r]
                .as_ref()
                .and_then(|rep| closed_output_fault(rep, &self.plan));
            if let Some((kind, detail)) = verdict {
                self.fault(r, kind, detail);
            }
        }
    }

    /// When the event loop must wake up at the latest: the nearest of the open round's
    /// deadline and the graces of replicas whose output closed. The timers are refilled from
    /// that state before every wait, so none can be left behind stale.
    fn next_wakeup(&mut self) -> Option<Instant> {
        self.timers.cancel_all();
        if let Some(round) = &self.round {
            self.timers.set(Timer::Round(round.pair), round.deadline);
        }
        for (r, rep) in self.slots.iter().enumerate() {
            if let Some(since) = rep.as_ref().and_then(|rep| rep.output_closed_at) {
                self.timers.set(Timer::Grace(r), since + EXIT_AFTER_EOF);
            }
        }
        self.timers.nearest().map(|(_, at)| at)
    }

    // ----- voting and rounds ----------------------------------------------------------

    /// Replicas still trusted in the current round.
    fn alive(&self, round: &Round) -> ReplicaSet {
        round
            .members
            .iter()
            .filter(|&r| self.slots[r].is_some())
            .fold(ReplicaSet::EMPTY, ReplicaSet::with)
    }

    fn vote_output(&self, round: &Round, o: usize) -> VoteOutcome {
        vote(
            &self.round_answers(round, o)[..self.slots.len()],
            self.alive(round),
        )
    }

    /// The second rule when no whole frame of output `o` has a majority (see `vote.rs`).
    fn rebuild_output(&self, round: &Round, o: usize) -> Option<BitMajority> {
        bitwise_majority(
            &self.round_answers(round, o)[..self.slots.len()],
            self.alive(round),
        )
    }

    /// The trusted replicas that answered output `o` of `round`.
    fn answered(&self, round: &Round, o: usize) -> Vec<usize> {
        self.alive(round)
            .iter()
            .filter(|&r| round.has_answered(r, o))
            .collect()
    }

    fn round_answers(&self, round: &Round, o: usize) -> [Option<&[u8]>; MAX_REPLICAS] {
        let mut answers: [Option<&[u8]>; MAX_REPLICAS] = [None; MAX_REPLICAS];
        for r in round.members.iter() {
            if round.has_answered(r, o) {
                answers[r] = Some(&self.answers[r][o]);
            }
        }
        answers
    }

    /// Forwards output `o` of the current round as soon as some frame has a majority.
    fn try_forward(&mut self, o: usize) {
        let Some(round) = self.round.as_ref() else {
            return;
        };
        if (round.forwarded | round.held) & (1 << o) != 0 {
            return;
        }
        if let VoteOutcome::Majority { winner, agree, .. } = self.vote_output(round, o) {
            if self.lone_alarm(agree, winner, o) {
                return self.hold_back(winner, o);
            }
            self.round.as_mut().unwrap().forwarded |= 1 << o;
            self.forward(o, winner);
        }
    }

    /// A frame that stands on the word of a single replica (SMR, or a pair or trio down to
    /// one) and that its detector flags: no other replica can confirm or overrule it.
    fn lone_alarm(&self, agree: ReplicaSet, winner: usize, o: usize) -> bool {
        agree.len() == 1 && self.monitors.alarmed(winner, o)
    }

    /// Holds back replica `r`'s flagged frame on output `o` and treats `r` as faulty (`sdc`):
    /// it is replaced after the round, by exec when no healthy replica is left (state lost,
    /// and the recovery event says so).
    fn hold_back(&mut self, r: usize, o: usize) {
        if let Some(round) = self.round.as_mut() {
            round.held |= 1 << o;
        }
        let detail = self.held_back_detail(r, o);
        self.fault(r, EventKind::Sdc, detail);
    }

    fn held_back_detail(&self, r: usize, o: usize) -> String {
        format!(
            "anomaly detector flagged its frame on `{}` ({}) and no other replica confirms it; frame held back",
            self.plan.outputs[o].name,
            self.alarm_text(r, o)
        )
    }

    /// DMR attribution: two trusted replicas answered output `o` with different frames and
    /// exactly one of them was flagged by the detector. Returns `(culprit, healthy)`.
    fn attribute(&self, round: &Round, o: usize) -> Option<(usize, usize)> {
        let answered: Vec<usize> = self
            .alive(round)
            .iter()
            .filter(|&r| round.has_answered(r, o))
            .collect();
        let [a, b] = answered[..] else {
            return None;
        };
        if self.answers[a][o] == self.answers[b][o] {
            return None;
        }
        match (self.monitors.alarmed(a, o), self.monitors.alarmed(b, o)) {
            (true, false) => Some((a, b)),
            (false, true) => Some((b, a)),
            _ => None,
        }
    }

    /// How a flagged frame looked to its detector, for an event's detail.
    fn alarm_text(&self, r: usize, o: usize) -> String {
        match self.monitors.alarm(r, o) {
            Some(a) => format!(
                "field `{}`, score {}, threshold {}: {}",
                a.field.as_deref().unwrap_or("?"),
                a.score.map_or("inf".to_owned(), |s| format!("{s:.3e}")),
                a.threshold,
                a.cause
            ),
            None => "no verdict".to_owned(),
        }
    }

    /// Every alarm is an `anomaly` event, whatever the voter then does about it.
    fn anomaly_event(&self, r: usize, o: usize) {
        let Some(alarm) = self.monitors.alarm(r, o) else {
            return;
        };
        let mut ev = self.event(EventKind::Anomaly);
        ev.replica = Some(r);
        ev.pid = self.slots[r].as_ref().map(|rep| rep.pid);
        ev.round = self.round.as_ref().map(|rd| rd.number);
        ev.output = Some(self.plan.outputs[o].name.clone());
        ev.field = alarm.field;
        ev.score = alarm.score;
        ev.threshold = Some(alarm.threshold);
        ev.detail = Some(alarm.cause.to_owned());
        self.emit(ev);
    }

    /// Closes the round when everyone trusted has answered, or when its deadline has passed.
    /// In a sequential round, moves the turn on instead (see [`Voter::advance_turn`]).
    fn advance_round(&mut self) {
        let Some(round) = self.round.as_ref() else {
            return;
        };
        let alive = self.alive(round);
        if alive.iter().all(|r| round.is_done_by(r)) {
            return self.close_round();
        }
        if self.plan.schedule == Schedule::Sequential {
            return self.advance_turn();
        }
        if Instant::now() < round.deadline {
            return;
        }
        let late: Vec<usize> = alive.iter().filter(|&r| !round.is_done_by(r)).collect();
        let number = round.number;
        for r in late {
            self.blame_if_late(r, number);
        }
        self.close_round();
    }

    /// Sequential schedule: the replica whose turn it is keeps it until it has answered every
    /// expected output, leaves the quorum (faulty), or misses its own deadline, which makes
    /// it, and only it, the hung one. Then the next replica that has not answered yet gets
    /// the turn with a fresh deadline; when none is left, the round closes.
    fn advance_turn(&mut self) {
        loop {
            let Some(round) = self.round.as_ref() else {
                return;
            };
            let number = round.number;
            if let Some(t) = round.turn {
                if self.slots[t].is_some() && !round.is_done_by(t) {
                    if Instant::now() < round.deadline {
                        return;
                    }
                    self.blame_if_late(t, number);
                    continue;
                }
            }
            if !self.next_turn() {
                return self.close_round();
            }
            return;
        }
    }

    /// Gives the turn to the lowest-numbered member that is still trusted and has not
    /// answered yet: raises it above its siblings (puts the previous one back to rest) and
    /// starts its deadline. Returns `false` when no such replica is left.
    fn next_turn(&mut self) -> bool {
        let Some(round) = self.round.as_ref() else {
            return false;
        };
        let previous = round.turn;
        let next = self
            .alive(round)
            .iter()
            .find(|&r| !round.is_done_by(r) && Some(r) != previous);
        if let Some(prev) = previous {
            if let Some(rep) = self.slots[prev].as_ref() {
                let pid = rep.pid;
                self.rt.rest(pid, prev);
            }
        }
        let Some(next) = next else {
            return false;
        };
        let pid = self.slots[next].as_ref().map(|r| r.pid);
        if let Some(pid) = pid {
            self.rt.raise(pid);
        }
        let allowance = self.allowance(ReplicaSet::EMPTY.with(next));
        let round = self.round.as_mut().expect("checked above");
        round.turn = Some(next);
        round.deadline = Instant::now() + allowance;
        true
    }

    /// How long `replicas` get to answer a round: `timeout_us`, or the start-up allowance
    /// (`start_timeout_ms`, if longer) while one of them has never answered. A replica started
    /// by exec is still being loaded, linked and locked into memory when its first input
    /// arrives; that is start-up, not a hang. A fork child is proven from the start.
    fn allowance(&self, replicas: ReplicaSet) -> Duration {
        let timeout = Duration::from_micros(self.plan.timeout_us);
        let starting = replicas
            .iter()
            .any(|r| self.slots[r].as_ref().is_some_and(|rep| !rep.proven));
        if starting {
            timeout.max(Duration::from_millis(self.plan.start_timeout_ms))
        } else {
            timeout
        }
    }

    /// At a deadline: takes one last look at replica `r`'s pipes (an answer may have arrived
    /// while the voter itself was busy, and the voter's lateness is not the replica's fault);
    /// if it still has not answered everything, it is faulty: `protocol` with a partial frame
    /// in its pipe, else `hang`.
    fn blame_if_late(&mut self, r: usize, number: u64) {
        for o in 0..self.plan.outputs.len() {
            self.on_replica_output(r, o);
        }
        let Some(round) = self.round.as_ref() else {
            return;
        };
        if round.is_done_by(r) {
            return;
        }
        let Some(rep) = self.slots[r].as_ref() else {
            return;
        };
        let partial = rep.outputs.iter().position(|out| out.decoder.pending() > 0);
        let turn = if round.turn == Some(r) {
            " of its turn"
        } else {
            ""
        };
        let (kind, detail) = match partial {
            Some(o) => (
                EventKind::Protocol,
                format!(
                    "partial frame on `{}` at the deadline{turn} in round {number}",
                    self.plan.outputs[o].name
                ),
            ),
            None if rep.proven => (
                EventKind::Hang,
                format!(
                    "no answer within {} µs{turn} in round {number}",
                    self.plan.timeout_us
                ),
            ),
            None => (
                EventKind::Hang,
                format!(
                    "no first answer within {} ms of start-up{turn} in round {number}",
                    self.plan.start_timeout_ms.max(self.plan.timeout_us / 1000)
                ),
            ),
        };
        self.fault(r, kind, detail);
    }

    fn close_round(&mut self) {
        let Some(round) = self.round.take() else {
            return;
        };
        if let Some(t) = round.turn {
            if let Some(pid) = self.slots[t].as_ref().map(|r| r.pid) {
                self.rt.rest(pid, t);
            }
        }
        let number = round.number;
        // DMR attribution first: the flagged replica of a disagreeing pair leaves the quorum,
        // so the vote below forwards the other's frame (on this and every other output).
        if !self.monitors.is_empty() {
            let blamed: Vec<(usize, usize, usize)> = round
                .outputs()
                .filter(|&o| (round.forwarded | round.held) & (1 << o) == 0)
                .filter_map(|o| self.attribute(&round, o).map(|(c, h)| (o, c, h)))
                .collect();
            for (o, culprit, healthy) in blamed {
                let detail = format!(
                    "output `{}` differs from replica {healthy}'s and the anomaly detector flagged it ({}) but not replica {healthy}'s",
                    self.plan.outputs[o].name,
                    self.alarm_text(culprit, o)
                );
                self.fault_in_round(culprit, EventKind::Sdc, detail, Some(number));
            }
        }
        let mut dissenters = ReplicaSet::EMPTY;
        let mut withheld = Vec::new();
        let mut rebuilt_outputs = Vec::new();
        for o in round.outputs() {
            if round.held & (1 << o) != 0 {
                continue;
            }
            match self.vote_output(&round, o) {
                VoteOutcome::Majority { winner, agree, .. }
                    if round.forwarded & (1 << o) == 0 && self.lone_alarm(agree, winner, o) =>
                {
                    let detail = self.held_back_detail(winner, o);
                    self.fault_in_round(winner, EventKind::Sdc, detail, Some(number));
                }
                VoteOutcome::Majority {
                    winner, dissent, ..
                } => {
                    if round.forwarded & (1 << o) == 0 {
                        self.forward(o, winner);
                    }
                    for r in dissent.iter() {
                        dissenters = dissenters.with(r);
                    }
                }
                VoteOutcome::NoMajority if round.forwarded & (1 << o) == 0 => {
                    match self.rebuild_output(&round, o) {
                        Some(rebuilt) => rebuilt_outputs.push((o, rebuilt)),
                        None => withheld.push((o, self.answered(&round, o))),
                    }
                }
                VoteOutcome::Pending | VoteOutcome::NoMajority => {
                    withheld.push((o, self.answered(&round, o)));
                }
            }
        }
        for (o, answered) in withheld {
            let name = &self.plan.outputs[o].name;
            if answered.is_empty() {
                tracing::warn!(round = number, output = %name, "no replica answered; nothing forwarded");
                continue;
            }
            // Two replicas that differ, or three that all differ: a fault is certain, its
            // culprit is not. The documented policy: withhold the output, blame nobody.
            let mut ev = self.event(EventKind::Sdc);
            ev.round = Some(number);
            ev.detail = Some(format!(
                "no majority on `{name}`: replicas {answered:?} disagree; output withheld"
            ));
            self.emit(ev);
        }
        let mut rebuilt_dissent = Vec::new();
        for (o, rebuilt) in rebuilt_outputs {
            // No whole frame had a majority, every bit did: forward the rebuilt frame.
            self.outputs[o].send(&rebuilt.frame);
            self.captures.record(o, &rebuilt.frame);
            let name = &self.plan.outputs[o].name;
            if let Some(k) = rebuilt.kept {
                // Every replica's frame was hit: one must stay to fork the others from.
                let mut ev = self.event(EventKind::Sdc);
                ev.round = Some(number);
                ev.detail = Some(format!(
                    "no majority on `{name}`, every replica's output differs from the bitwise majority (forwarded); replica {k}, the closest, kept as donor"
                ));
                self.emit(ev);
            }
            for r in rebuilt.dissent.iter() {
                rebuilt_dissent.push((r, format!(
                    "output `{name}` had no majority in round {number} and differs from the bitwise majority, which was forwarded (≤ {} bits apart)",
                    rebuilt.max_bits
                )));
            }
        }
        for r in dissenters.iter() {
            let detail = format!("output differs from the majority in round {number}");
            self.fault_in_round(r, EventKind::Sdc, detail, Some(number));
        }
        for (r, detail) in rebuilt_dissent {
            self.fault_in_round(r, EventKind::Sdc, detail, Some(number));
        }
    }

    // ----- faults and recovery --------------------------------------------------------

    fn fault(&mut self, r: usize, kind: EventKind, detail: String) {
        let round = self.round.as_ref().map(|rd| rd.number);
        self.fault_in_round(r, kind, detail, round);
        // Fewer trusted replicas may turn a pending vote into a decided one.
        let outputs: Vec<usize> = self
            .round
            .as_ref()
            .map(|rd| rd.outputs().collect())
            .unwrap_or_default();
        for o in outputs {
            self.try_forward(o);
        }
    }

    /// Records a fault, kills the replica at once and queues its slot for recovery.
    fn fault_in_round(&mut self, r: usize, kind: EventKind, detail: String, round: Option<u64>) {
        let Some(replica) = self.slots[r].take() else {
            return;
        };
        replica.kill();
        let mut ev = self.event(kind);
        ev.replica = Some(r);
        ev.pid = Some(replica.pid);
        ev.round = round;
        ev.detail = Some(detail);
        let detected_ns = ev.ts_ns;
        self.emit(ev);
        self.faults.push(Fault {
            slot: r,
            replica,
            detected_ns,
        });
    }

    /// Replaces every faulty replica: by fork of a healthy one if there is one, else by exec.
    fn recover_faulty(&mut self) -> Result<(), VoterError> {
        while let Some(fault) = self.faults.pop() {
            if self.stop.is_some() {
                continue;
            }
            let (slot, old_pid, detected_ns) = fault.retire();
            self.replace(slot, old_pid, detected_ns)?;
        }
        Ok(())
    }

    fn replace(&mut self, slot: usize, old_pid: i32, detected_ns: u64) -> Result<(), VoterError> {
        // Every trusted replica has answered the last round: no progress to tell them apart.
        let patience = std::time::Duration::from_micros(self.plan.timeout_us);
        let pick = crate::replica::best_donor(&self.slots, |_| 0, patience);
        for r in pick.hung {
            let detail = format!(
                "picked as recovery donor, it ran for {} µs without once waiting for input",
                self.plan.timeout_us
            );
            self.fault(r, EventKind::Hang, detail);
        }
        let donor = pick.donor;
        if let Some(d) = donor {
            let donor_proven = self.slots[d].as_ref().is_some_and(|r| r.proven);
            let family: Vec<libc::pid_t> = self.slots.iter().flatten().map(|r| r.pid).collect();
            self.restart_nonce = self.restart_nonce.wrapping_add(1).max(1);
            let donor_rep = self.slots[d].as_mut().expect("donor slot is filled");
            let donor_pid = donor_rep.pid;
            // S³RES §4.4: the donor runs above its siblings while it forks.
            self.rt.raise(donor_pid);
            let forked = recovery::fork_from(
                &self.plan,
                &self.listener,
                donor_rep,
                self.restart_nonce,
                &family,
            );
            self.rt.rest(donor_pid, d);
            match forked {
                Ok(child) => {
                    // The child inherited the donor's priority and CPU; it takes the slot's.
                    self.rt.apply_to_replica(child.pid, slot);
                    let mut ev = recovery_event(&self.plan, slot, old_pid, child.pid, detected_ns);
                    ev.donor = Some(d);
                    ev.method = Some(RecoveryMethod::Fork);
                    // A donor that has not answered yet was itself just started by exec.
                    ev.state_lost = Some(!donor_proven);
                    self.emit(ev);
                    self.slots[slot] = Some(child);
                    // The child's next frame continues the donor's stream.
                    self.monitors.copy_stream(d, slot);
                    return Ok(());
                }
                Err(e) => {
                    tracing::warn!(replica = slot, donor = d, error = %e, "recovery by fork failed; starting a fresh replica");
                }
            }
        }
        let replaced = replace_by_exec(
            &self.plan,
            self.events.as_ref(),
            &mut self.slots,
            (slot, old_pid, detected_ns),
            |pid, slot| self.rt.apply_to_replica(pid, slot),
        )?;
        if replaced {
            // A fresh process: its first frame is a warm-up.
            self.monitors.reset_stream(slot);
        }
        Ok(())
    }

    // ----- events ------------------------------------------------------------------------

    fn event(&self, kind: EventKind) -> Event {
        Event::new(&self.plan.system, &self.plan.component, kind)
    }

    fn emit(&self, ev: Event) {
        write_event(self.events.as_ref(), &ev);
    }

    // ----- the end ---------------------------------------------------------------------

    /// Inputs closed: close the replicas' inputs, let them finish, flush what was voted.
    fn finish(&mut self) -> Result<(), VoterError> {
        tracing::debug!("inputs closed; flushing output and letting the replicas finish");
        // Voted output first: it is what the rest of the system is waiting for.
        let drain_deadline = Instant::now() + OUTPUT_DRAIN_LIMIT;
        for o in 0..self.outputs.len() {
            self.drain_output(o, drain_deadline);
        }
        for rep in self.slots.iter_mut().flatten() {
            for input in &mut rep.inputs {
                let _ = input.writer.flush();
            }
            // Closing our write ends (and the read ends we kept) gives the replica EOF.
            rep.inputs.clear();
        }
        let deadline = Instant::now() + SHUTDOWN_GRACE;
        for rep in self.slots.iter().flatten() {
            let left = deadline.saturating_duration_since(Instant::now());
            if !rep.exited_within(left) {
                tracing::warn!(
                    pid = rep.pid,
                    "replica did not finish after its input closed; killing it"
                );
            }
        }
        Ok(())
    }

    /// Writes out what is still queued for downstream, blocking up to `deadline`.
    fn drain_output(&mut self, o: usize, deadline: Instant) {
        self.outputs[o].drain(deadline);
    }

    /// Kills every replica and everything re-parented to us; removes the socket.
    fn shut_down(&mut self) {
        self.captures.flush();
        self.monitors.log_cost();
        shut_down(
            &self.plan,
            &mut self.outputs,
            self.slots.iter().flatten(),
            &self.faults,
        );
    }
}

/// Also on a panic: no replica outlives its voter (bootstrap's sweep would catch them, but the
/// voter should not depend on it).
impl Drop for Voter {
    fn drop(&mut self) {
        kill_replicas(&self.slots, &self.faults);
    }
}

/// Kills every replica, trusted or faulty.
pub(crate) fn kill_replicas(slots: &[Option<Replica>], faults: &[Fault]) {
    for rep in slots.iter().flatten() {
        rep.kill();
    }
    for fault in faults {
        fault.replica.kill();
    }
}

/// The fds one wait of an event loop watches, each with the [`Token`] saying what it stands
/// for. Rebuilt before every wait from the loop's state; the vectors keep their capacity, so
/// a steady-state round allocates nothing.
#[derive(Debug, Default)]
pub(crate) struct PollSet {
    pub(crate) fds: Vec<libc::pollfd>,
    pub(crate) tokens: Vec<Token>,
}

impl PollSet {
    fn add(&mut self, fd: RawFd, events: libc::c_short, token: Token) {
        self.fds.push(libc::pollfd {
            fd,
            events,
            revents: 0,
        });
        self.tokens.push(token);
    }

    /// Starts a new set: the signalfd, the external inputs (if `take_input`) and the external
    /// outputs with frames queued.
    pub(crate) fn reset(
        &mut self,
        signals: &SignalFd,
        inputs: &[ExternalInput],
        take_input: bool,
        outputs: &[ExternalOutput],
    ) {
        self.fds.clear();
        self.tokens.clear();
        self.add(signals.as_raw_fd(), libc::POLLIN, Token::Signal);
        for (i, input) in inputs.iter().enumerate() {
            if take_input && !input.reader.is_closed() {
                self.add(
                    input.reader.as_fd().as_raw_fd(),
                    libc::POLLIN,
                    Token::Input(i),
                );
            }
        }
        for (o, output) in outputs.iter().enumerate() {
            if output.writer.has_pending() {
                self.add(
                    output.writer.as_fd().as_raw_fd(),
                    libc::POLLOUT,
                    Token::OutputWritable(o),
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
            self.add(rep.pidfd.as_raw_fd(), libc::POLLIN, Token::ReplicaExit(r));
        }
        for (o, out) in rep.outputs.iter().enumerate() {
            if !out.is_closed() && may_read(o) {
                self.add(
                    out.as_fd().as_raw_fd(),
                    libc::POLLIN,
                    Token::ReplicaOutput(r, o),
                );
            }
        }
        for (i, input) in rep.inputs.iter().enumerate() {
            if input.writer.has_pending() {
                self.add(
                    input.writer.as_fd().as_raw_fd(),
                    libc::POLLOUT,
                    Token::ReplicaInputWritable(r, i),
                );
            }
        }
    }
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
    sys::ppoll(fds, timeout).map_err(|source| VoterError::Io {
        what: "ppoll".into(),
        source,
    })
}

/// How many bytes the voter queues for one replica input beyond what its pipe holds before
/// the replica counts as not taking its input (a `hang`): 64 frames of the channel's maximum,
/// and at least 4 MiB, so a burst of an upstream neighbour never trips it, while a replica
/// that stopped reading cannot make the voter's memory grow without bound.
fn input_backlog_limit(max_frame: usize) -> usize {
    (64 * (max_frame + replica_rt::frame::HEADER_LEN)).max(4 << 20)
}

/// Starts every replica by exec, in slot order, each with a `start` event. `on_spawn(pid,
/// slot)` runs for each new process first (to apply scheduling settings).
pub(crate) fn start_replicas(
    plan: &VoterPlan,
    events: Option<&OwnedFd>,
    mut on_spawn: impl FnMut(libc::pid_t, usize),
) -> Result<Vec<Option<Replica>>, VoterError> {
    let mut slots: Vec<Option<Replica>> = (0..plan.replicas).map(|_| None).collect();
    for slot in 0..plan.replicas {
        let replica = match Replica::spawn(plan, slot) {
            Ok(r) => r,
            Err(e) => {
                // The ones already running must not outlive this failed start.
                kill_replicas(&slots, &[]);
                for rep in slots.iter().flatten() {
                    rep.exited_within(DEATH_WAIT);
                    let _ = sys::reap(rep.pid);
                }
                return Err(io_err(format!(
                    "starting replica {slot} ({})",
                    plan.exec.display()
                ))(e));
            }
        };
        on_spawn(replica.pid, slot);
        let mut ev = Event::new(&plan.system, &plan.component, EventKind::Start);
        ev.replica = Some(slot);
        ev.pid = Some(replica.pid);
        write_event(events, &ev);
        slots[slot] = Some(replica);
    }
    Ok(slots)
}

/// A `recovery` event: `slot` went from `old_pid` to `new_pid`, `detected_ns` after the fault.
pub(crate) fn recovery_event(
    plan: &VoterPlan,
    slot: usize,
    old_pid: i32,
    new_pid: i32,
    detected_ns: u64,
) -> Event {
    let mut ev = Event::new(&plan.system, &plan.component, EventKind::Recovery);
    ev.replica = Some(slot);
    ev.pid = Some(old_pid);
    ev.new_pid = Some(new_pid);
    ev.recovery_us = Some(ev.ts_ns.saturating_sub(detected_ns) / 1000);
    ev
}

/// Fills `slot` with a fresh replica started by exec (state lost, and the event says so);
/// `on_spawn(pid, slot)` runs for the new process first. `Ok(false)` if it could not be
/// started but other replicas remain; an error if none does.
pub(crate) fn replace_by_exec(
    plan: &VoterPlan,
    events: Option<&OwnedFd>,
    slots: &mut [Option<Replica>],
    (slot, old_pid, detected_ns): (usize, i32, u64),
    on_spawn: impl FnOnce(libc::pid_t, usize),
) -> Result<bool, VoterError> {
    match Replica::spawn(plan, slot) {
        Ok(fresh) => {
            on_spawn(fresh.pid, slot);
            let mut ev = recovery_event(plan, slot, old_pid, fresh.pid, detected_ns);
            ev.method = Some(RecoveryMethod::Exec);
            ev.state_lost = Some(true);
            write_event(events, &ev);
            slots[slot] = Some(fresh);
            Ok(true)
        }
        Err(e) => {
            let mut ev = Event::new(&plan.system, &plan.component, EventKind::RecoveryFailed);
            ev.replica = Some(slot);
            ev.pid = Some(old_pid);
            ev.detail = Some(format!("could not start {}: {e}", plan.exec.display()));
            write_event(events, &ev);
            if slots.iter().all(Option::is_none) {
                return Err(VoterError::Unrecoverable(format!(
                    "no replica left and {} cannot be started: {e}",
                    plan.exec.display()
                )));
            }
            Ok(false)
        }
    }
}

/// What a replica whose output pipe closed turns out to be once [`EXIT_AFTER_EOF`] has passed:
/// a crash if it is gone, a protocol fault if it lives. `None` while the grace runs, or if no
/// output of it closed.
pub(crate) fn closed_output_fault(rep: &Replica, plan: &VoterPlan) -> Option<(EventKind, String)> {
    let since = rep.output_closed_at?;
    // On the counter, exactly as `next_wakeup` set the timer (a duration read off the counter
    // is rounded down, and could keep the loop spinning a few µs past it).
    if Instant::now() < since + EXIT_AFTER_EOF {
        return None;
    }
    if rep.exited_within(Duration::ZERO) {
        return Some((EventKind::Crash, "the replica process died".into()));
    }
    let closed = rep
        .outputs
        .iter()
        .position(|out| out.is_closed())
        .unwrap_or(0);
    let name = &plan.outputs[closed].name;
    let detail = match rep.outputs[closed].decoder.finish() {
        Err(e @ FrameError::Truncated { .. }) => format!("output `{name}`: {e}"),
        _ => format!("closed its output `{name}`"),
    };
    Some((EventKind::Protocol, detail))
}

impl Fault {
    /// Makes sure the killed replica is gone (bounded) and reaped; returns its slot, pid and
    /// when it was found faulty.
    pub(crate) fn retire(self) -> (usize, i32, u64) {
        let Fault {
            slot,
            replica: old,
            detected_ns,
        } = self;
        if !old.exited_within(DEATH_WAIT) {
            tracing::warn!(pid = old.pid, "killed replica has not exited yet");
        }
        if old.our_child {
            let _ = sys::reap(old.pid);
        }
        drop(old.pidfd);
        reap_children();
        (slot, old.pid, detected_ns)
    }
}

impl ExternalInput {
    /// One read from upstream into the decoder; an end or an error closes the input (logged).
    pub(crate) fn read(&mut self) {
        match self.reader.fill() {
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

/// Kills every replica (trusted or faulty) and everything re-parented to us, after giving
/// downstream whatever it takes at once; removes the socket.
pub(crate) fn shut_down<'a>(
    plan: &VoterPlan,
    outputs: &mut [ExternalOutput],
    replicas: impl Iterator<Item = &'a Replica> + Clone,
    faults: &[Fault],
) {
    // On a requested stop, whatever downstream can take right now still goes out.
    for out in outputs.iter_mut() {
        if out.writer.has_pending() && !out.broken {
            out.flush();
        }
    }
    for rep in replicas.clone() {
        rep.kill();
    }
    for fault in faults {
        fault.replica.kill();
    }
    for rep in replicas {
        rep.exited_within(DEATH_WAIT);
    }
    kill_all_children(Duration::from_secs(3));
    let _ = std::fs::remove_file(&plan.socket_path);
}

/// Reads the signalfd: reaps on SIGCHLD; `true` if SIGTERM/SIGINT came.
pub(crate) fn stop_requested(signals: &SignalFd) -> bool {
    let mut stop = false;
    while let Ok(Some(info)) = signals.read_signal() {
        match info.ssi_signo as i32 {
            libc::SIGCHLD => reap_children(),
            sig => {
                tracing::info!(signal = sig, "stop requested");
                stop = true;
            }
        }
    }
    stop
}

pub(crate) fn validate(plan: &VoterPlan) -> Result<(), VoterError> {
    let fail = |m: String| Err(VoterError::Plan(m));
    if plan.replicas == 0 || plan.replicas > MAX_REPLICAS {
        return fail(format!(
            "replicas must be 1..={MAX_REPLICAS}, got {}",
            plan.replicas
        ));
    }
    if plan.timeout_us == 0 {
        return fail("timeout_us must be above 0".into());
    }
    if plan.inputs.len() + plan.outputs.len() > replica_rt::contract::MAX_PORTS {
        return fail(format!(
            "more than {} ports",
            replica_rt::contract::MAX_PORTS
        ));
    }
    for r in &plan.rounds {
        if !plan.inputs.iter().any(|p| p.name == r.input) {
            return fail(format!("round input `{}` is not an input", r.input));
        }
        for o in &r.outputs {
            if !plan.outputs.iter().any(|p| &p.name == o) {
                return fail(format!("round output `{o}` is not an output"));
            }
        }
    }
    match plan.mode {
        Mode::Reactive if plan.rounds.is_empty() => {
            fail("reactive mode needs at least one input that starts rounds".into())
        }
        Mode::Stream if !plan.rounds.is_empty() => {
            fail("stream mode has no rounds; the plan lists some".into())
        }
        Mode::Stream if plan.window == 0 => fail("the stream window must be above 0".into()),
        Mode::Stream if plan.inputs.is_empty() => {
            fail("stream mode needs an input (its end ends the component)".into())
        }
        _ => Ok(()),
    }
}

/// What a voter opens before it starts replicas, whatever its mode.
pub(crate) struct Endpoints {
    pub(crate) signals: SignalFd,
    pub(crate) inputs: Vec<ExternalInput>,
    pub(crate) outputs: Vec<ExternalOutput>,
    pub(crate) events: Option<OwnedFd>,
    pub(crate) listener: UnixListener,
}

impl Endpoints {
    /// Becomes a subreaper, takes the signals, adopts the fds named in `plan`, binds the socket.
    pub(crate) fn open(plan: &VoterPlan) -> Result<Endpoints, VoterError> {
        // Orphans (children of a donor that died) come to us, so they are reaped and killed.
        sys::set_child_subreaper().map_err(io_err("becoming a child subreaper"))?;
        let signals = block_signals()?;

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
                    reader: FrameReader::new(inherited(p.fd), p.max_frame)
                        .map_err(io_err(format!("input `{}` (fd {})", p.name, p.fd)))?,
                    round,
                })
            })
            .collect::<Result<Vec<_>, VoterError>>()?;
        let outputs = plan
            .outputs
            .iter()
            .map(|p| {
                Ok(ExternalOutput {
                    name: p.name.clone(),
                    writer: FrameWriter::new(inherited(p.fd))
                        .map_err(io_err(format!("output `{}` (fd {})", p.name, p.fd)))?,
                    broken: false,
                })
            })
            .collect::<Result<Vec<_>, VoterError>>()?;
        let events = plan.events_fd.map(inherited);

        let _ = std::fs::remove_file(&plan.socket_path);
        let listener = UnixListener::bind(&plan.socket_path)
            .map_err(io_err(format!("binding {}", plan.socket_path.display())))?;
        // Only our own user may connect; SO_PEERCRED narrows it to the donor's child.
        let _ = std::fs::set_permissions(&plan.socket_path, std::fs::Permissions::from_mode(0o600));
        listener.set_nonblocking(true).map_err(io_err("socket"))?;
        Ok(Endpoints {
            signals,
            inputs,
            outputs,
            events,
            listener,
        })
    }
}

/// Writes one event line to the events fd (and traces it).
pub(crate) fn write_event(events: Option<&OwnedFd>, ev: &Event) {
    // Bootstrap logs every event it gathers; here they are only traced, so that a run
    // shows each event once. Without an events fd, the voter's own log is all there is.
    if events.is_some() {
        tracing::debug!(kind = ?ev.kind, replica = ev.replica, pid = ev.pid, detail = ev.detail.as_deref(), "event");
    } else {
        tracing::warn!(kind = ?ev.kind, replica = ev.replica, pid = ev.pid, detail = ev.detail.as_deref(), "event");
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

/// Takes ownership of an fd this process inherited.
fn inherited(fd: RawFd) -> OwnedFd {
    sys::adopt_inherited_fd(fd)
}

/// SIGTERM/SIGINT/SIGCHLD arrive through a signalfd, read in the event loop.
pub(crate) fn block_signals() -> Result<SignalFd, VoterError> {
    let mut mask = SigSet::empty();
    for s in [Signal::SIGTERM, Signal::SIGINT, Signal::SIGCHLD] {
        mask.add(s);
    }
    mask.thread_block()
        .map_err(|e| io_err("blocking signals")(e.into()))?;
    SignalFd::with_flags(&mask, SfdFlags::SFD_NONBLOCK | SfdFlags::SFD_CLOEXEC)
        .map_err(|e| io_err("signalfd")(e.into()))
}

/// Reaps every child that has exited (replicas we started, orphans re-parented to us).
pub(crate) fn reap_children() {
    while let Ok(Some((pid, status))) = sys::reap_any() {
        tracing::trace!(pid, %status, "reaped");
    }
}

/// Kills every child of ours until none is left (or `limit` passes). As a subreaper we inherit
/// the children of dying children, so this converges on the whole subtree.
pub(crate) fn kill_all_children(limit: Duration) {
    let end = Instant::now() + limit;
    let me = std::process::id() as i32;
    loop {
        reap_children();
        let children = sys::children_of(me);
        if children.is_empty() || Instant::now() >= end {
            if !children.is_empty() {
                tracing::error!(?children, "children survived SIGKILL");
            }
            return;
        }
        for pid in children {
            let _ = sys::kill(pid, libc::SIGKILL);
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}
