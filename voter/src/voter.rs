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
use std::time::{Duration, Instant};

use nix::sys::signal::{SigSet, Signal};
use nix::sys::signalfd::{SfdFlags, SignalFd};
use replica_rt::frame::FrameError;
use replica_rt::sys;
use thiserror::Error;

use crate::channel::{Fill, FrameReader, FrameWriter};
use crate::event::{Event, EventKind, RecoveryMethod};
use crate::plan::VoterPlan;
use crate::recovery;
use crate::replica::Replica;
use crate::round::{OutputSet, Round};
use crate::vote::{vote, ReplicaSet, VoteOutcome, MAX_REPLICAS};

/// How long a replica whose output pipe closed may take to show up as dead before we call it a
/// protocol fault instead of a crash. The kernel closes a dying process's fds before it signals
/// the exit, so the two are seen a moment apart.
const EXIT_AFTER_EOF: Duration = Duration::from_millis(50);
/// How long replicas get to exit by themselves after their input is closed at the end.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(2);
/// How long downstream gets to take the last voted frames at the end.
const OUTPUT_DRAIN_LIMIT: Duration = Duration::from_secs(10);
/// How long to wait for a killed replica to be gone before recovering its slot anyway.
const DEATH_WAIT: Duration = Duration::from_secs(1);

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
}

fn io_err(what: impl Into<String>) -> impl FnOnce(io::Error) -> VoterError {
    let what = what.into();
    move |source| VoterError::Io { what, source }
}

/// An input of the protected component: read by the voter, copied to every replica.
struct ExternalInput {
    name: String,
    reader: FrameReader,
    /// The outputs a frame on this input expects (its round), or `None` if it starts none.
    round: Option<OutputSet>,
}

/// An output of the protected component: the voter writes the winners here.
struct ExternalOutput {
    name: String,
    writer: FrameWriter,
    /// The reader went away; later frames are dropped (said once).
    broken: bool,
}

/// A replica that was found faulty and killed, waiting to be replaced.
struct Fault {
    slot: usize,
    replica: Replica,
    detected_ns: u64,
}

/// Why the loop ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stop {
    /// Every input closed: let replicas finish, then exit cleanly.
    InputsClosed,
    /// SIGTERM/SIGINT.
    Requested,
}

/// What a slot of the poll set stands for.
#[derive(Debug, Clone, Copy)]
enum Token {
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
    poll_fds: Vec<libc::pollfd>,
    poll_tokens: Vec<Token>,
}

impl Voter {
    /// Takes over the fds named in `plan`, binds the socket, and starts the replicas.
    pub fn start(plan: VoterPlan) -> Result<Voter, VoterError> {
        validate(&plan)?;
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

        let n = plan.replicas;
        let mut voter = Voter {
            answers: vec![vec![Vec::new(); plan.outputs.len()]; n],
            slots: (0..n).map(|_| None).collect(),
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
            poll_fds: Vec::new(),
            poll_tokens: Vec::new(),
        };
        for slot in 0..n {
            let replica = Replica::spawn(&voter.plan, slot).map_err(io_err(format!(
                "starting replica {slot} ({})",
                voter.plan.exec.display()
            )))?;
            let mut ev = voter.event(EventKind::Start);
            ev.replica = Some(slot);
            ev.pid = Some(replica.pid);
            voter.emit(ev);
            voter.slots[slot] = Some(replica);
        }
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
        let timeout = self
            .next_wakeup()
            .map(|t| t.saturating_duration_since(Instant::now()));
        // Not `.map_err(io_err("ppoll"))`: that builds its String on every wake-up, error or not.
        let ready = sys::ppoll(&mut self.poll_fds, timeout).map_err(|source| VoterError::Io {
            what: "ppoll".into(),
            source,
        })?;
        if ready == 0 {
            return Ok(());
        }
        for k in 0..self.poll_fds.len() {
            if self.poll_fds[k].revents == 0 {
                continue;
            }
            match self.poll_tokens[k] {
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
                    if let Some(rep) = self.slots[r].as_mut() {
                        if let Err(e) = rep.inputs[i].writer.flush() {
                            let detail =
                                format!("input pipe `{}` broke: {e}", self.plan.inputs[i].name);
                            self.fault(r, EventKind::Protocol, detail);
                        }
                    }
                }
            }
        }
        Ok(())
    }

    fn build_poll_set(&mut self) {
        self.poll_fds.clear();
        self.poll_tokens.clear();
        let add = |fds: &mut Vec<libc::pollfd>, toks: &mut Vec<Token>, fd: RawFd, ev, t| {
            fds.push(libc::pollfd {
                fd,
                events: ev,
                revents: 0,
            });
            toks.push(t);
        };
        let (fds, toks) = (&mut self.poll_fds, &mut self.poll_tokens);
        add(
            fds,
            toks,
            self.signals.as_raw_fd(),
            libc::POLLIN,
            Token::Signal,
        );
        let backlog = self.outputs.iter().any(|o| o.writer.has_pending());
        // New input only between rounds and when downstream keeps up: back-pressure instead
        // of unbounded buffering.
        let take_input = self.round.is_none() && self.faults.is_empty() && !backlog;
        for (i, input) in self.inputs.iter().enumerate() {
            if take_input && !input.reader.is_closed() {
                add(
                    fds,
                    toks,
                    input.reader.as_fd().as_raw_fd(),
                    libc::POLLIN,
                    Token::Input(i),
                );
            }
        }
        for (o, output) in self.outputs.iter().enumerate() {
            if output.writer.has_pending() {
                add(
                    fds,
                    toks,
                    output.writer.as_fd().as_raw_fd(),
                    libc::POLLOUT,
                    Token::OutputWritable(o),
                );
            }
        }
        for (r, rep) in self.slots.iter().enumerate() {
            let Some(rep) = rep else { continue };
            add(
                fds,
                toks,
                rep.pidfd.as_raw_fd(),
                libc::POLLIN,
                Token::ReplicaExit(r),
            );
            for (o, out) in rep.outputs.iter().enumerate() {
                if !out.is_closed() {
                    add(
                        fds,
                        toks,
                        out.as_fd().as_raw_fd(),
                        libc::POLLIN,
                        Token::ReplicaOutput(r, o),
                    );
                }
            }
            for (i, input) in rep.inputs.iter().enumerate() {
                if input.writer.has_pending() {
                    add(
                        fds,
                        toks,
                        input.writer.as_fd().as_raw_fd(),
                        libc::POLLOUT,
                        Token::ReplicaInputWritable(r, i),
                    );
                }
            }
        }
    }

    fn on_signal(&mut self) {
        while let Ok(Some(info)) = self.signals.read_signal() {
            match info.ssi_signo as i32 {
                libc::SIGCHLD => reap_children(),
                sig => {
                    tracing::info!(signal = sig, "stop requested");
                    self.stop = Some(Stop::Requested);
                }
            }
        }
    }

    // ----- input side -------------------------------------------------------------------

    fn on_input_readable(&mut self, i: usize) {
        let input = &mut self.inputs[i];
        match input.reader.fill() {
            Ok(Fill::Open) => {}
            Ok(Fill::Closed) => {
                if let Err(e) = input.reader.decoder.finish() {
                    tracing::warn!(input = %input.name, error = %e, "input closed mid-frame");
                }
                tracing::debug!(input = %input.name, "input closed");
            }
            Err(e) => {
                tracing::error!(input = %input.name, error = %e, "reading input failed; treating it as closed");
                input.reader.close();
            }
        }
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
                for (r, rep) in self.slots.iter_mut().enumerate() {
                    let Some(rep) = rep else { continue };
                    match rep.inputs[i].writer.send(frame) {
                        Ok(()) => members = members.with(r),
                        Err(e) => broken.push((r, e)),
                    }
                }
                if let Some(expected) = round {
                    self.rounds_started += 1;
                    let deadline = Instant::now() + Duration::from_micros(self.plan.timeout_us);
                    self.round = Some(Round::new(self.rounds_started, expected, deadline, members));
                }
                for (r, e) in broken {
                    let detail = format!("input pipe `{}` broke: {e}", self.plan.inputs[i].name);
                    self.fault(r, EventKind::Protocol, detail);
                }
            }
        }
    }

    /// Every input is closed. (Called between rounds, after buffered frames were delivered,
    /// so nothing whole is left; a partial frame left behind can never complete.)
    fn all_inputs_done(&self) -> bool {
        self.inputs.iter().all(|i| i.reader.is_closed())
    }

    // ----- output side ------------------------------------------------------------------

    fn flush_output(&mut self, o: usize) {
        let out = &mut self.outputs[o];
        if let Err(e) = out.writer.flush() {
            if !out.broken {
                tracing::warn!(output = %out.name, error = %e, "downstream is gone; dropping further output");
                out.broken = true;
            }
            // Nothing queued for a reader that will never come.
            out.writer.discard();
        }
    }

    fn forward(&mut self, o: usize, winner: usize) {
        let out = &mut self.outputs[o];
        if out.broken {
            return;
        }
        if let Err(e) = out.writer.send(&self.answers[winner][o]) {
            tracing::warn!(output = %out.name, error = %e, "downstream is gone; dropping further output");
            out.broken = true;
            out.writer.discard();
        }
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
        let Some(rep) = self.slots[r].as_mut() else {
            return;
        };
        if rep.exited_within(Duration::ZERO) {
            self.fault(r, EventKind::Crash, "the replica process died".into());
        } else if rep.output_closed_at.is_none() {
            rep.output_closed_at = Some(Instant::now());
        }
    }

    /// Replicas whose output closed more than [`EXIT_AFTER_EOF`] ago and which still live.
    fn fault_closed_outputs(&mut self) {
        for r in 0..self.slots.len() {
            let Some(rep) = self.slots[r].as_ref() else {
                continue;
            };
            let Some(since) = rep.output_closed_at else {
                continue;
            };
            if since.elapsed() < EXIT_AFTER_EOF {
                continue;
            }
            if rep.exited_within(Duration::ZERO) {
                self.fault(r, EventKind::Crash, "the replica process died".into());
                continue;
            }
            let closed = rep
                .outputs
                .iter()
                .position(|out| out.is_closed())
                .unwrap_or(0);
            let name = &self.plan.outputs[closed].name;
            let detail = match rep.outputs[closed].decoder.finish() {
                Err(e @ FrameError::Truncated { .. }) => format!("output `{name}`: {e}"),
                _ => format!("closed its output `{name}`"),
            };
            self.fault(r, EventKind::Protocol, detail);
        }
    }

    /// When the event loop must wake up at the latest: the round's deadline, or the end of the
    /// grace of a replica whose output closed.
    fn next_wakeup(&self) -> Option<Instant> {
        let graces = self
            .slots
            .iter()
            .flatten()
            .filter_map(|rep| rep.output_closed_at.map(|t| t + EXIT_AFTER_EOF));
        self.round
            .as_ref()
            .map(|r| r.deadline)
            .into_iter()
            .chain(graces)
            .min()
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
        let mut answers: [Option<&[u8]>; MAX_REPLICAS] = [None; MAX_REPLICAS];
        for r in round.members.iter() {
            if round.has_answered(r, o) {
                answers[r] = Some(&self.answers[r][o]);
            }
        }
        vote(&answers[..self.slots.len()], self.alive(round))
    }

    /// Forwards output `o` of the current round as soon as some frame has a majority.
    fn try_forward(&mut self, o: usize) {
        let Some(round) = self.round.as_ref() else {
            return;
        };
        if round.forwarded & (1 << o) != 0 {
            return;
        }
        if let VoteOutcome::Majority { winner, .. } = self.vote_output(round, o) {
            self.round.as_mut().unwrap().forwarded |= 1 << o;
            self.forward(o, winner);
        }
    }

    /// Closes the round when everyone trusted has answered, or when its deadline has passed.
    fn advance_round(&mut self) {
        let Some(round) = self.round.as_ref() else {
            return;
        };
        let alive = self.alive(round);
        if alive.iter().all(|r| round.is_done_by(r)) {
            return self.close_round();
        }
        if Instant::now() < round.deadline {
            return;
        }
        // Before blaming anyone, take one last look: an answer may have arrived while the voter
        // itself was busy, and the voter's lateness is not the replica's fault.
        let late: Vec<usize> = alive.iter().filter(|&r| !round.is_done_by(r)).collect();
        for &r in &late {
            for o in 0..self.plan.outputs.len() {
                self.on_replica_output(r, o);
            }
        }
        let Some(round) = self.round.as_ref() else {
            return;
        };
        let alive = self.alive(round);
        let late: Vec<usize> = alive.iter().filter(|&r| !round.is_done_by(r)).collect();
        let number = round.number;
        for r in late {
            let Some(rep) = self.slots[r].as_ref() else {
                continue;
            };
            let partial = rep.outputs.iter().position(|out| out.decoder.pending() > 0);
            let (kind, detail) = match partial {
                Some(o) => (
                    EventKind::Protocol,
                    format!(
                        "partial frame on `{}` at the deadline of round {number}",
                        self.plan.outputs[o].name
                    ),
                ),
                None => (
                    EventKind::Hang,
                    format!(
                        "no answer within {} µs in round {number}",
                        self.plan.timeout_us
                    ),
                ),
            };
            self.fault(r, kind, detail);
        }
        self.close_round();
    }

    fn close_round(&mut self) {
        let Some(round) = self.round.take() else {
            return;
        };
        let mut dissenters = ReplicaSet::EMPTY;
        let mut withheld = Vec::new();
        for o in round.outputs() {
            match self.vote_output(&round, o) {
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
                VoteOutcome::Pending | VoteOutcome::NoMajority => {
                    let answered: Vec<usize> = self
                        .alive(&round)
                        .iter()
                        .filter(|&r| round.has_answered(r, o))
                        .collect();
                    withheld.push((o, answered));
                }
            }
        }
        let number = round.number;
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
        for r in dissenters.iter() {
            let detail = format!("output differs from the majority in round {number}");
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
            let Fault {
                slot,
                replica: old,
                detected_ns,
            } = fault;
            if !old.exited_within(DEATH_WAIT) {
                tracing::warn!(pid = old.pid, "killed replica has not exited yet");
            }
            if old.our_child {
                let _ = sys::reap(old.pid);
            }
            drop(old.pidfd);
            reap_children();
            self.replace(slot, old.pid, detected_ns)?;
        }
        Ok(())
    }

    fn replace(&mut self, slot: usize, old_pid: i32, detected_ns: u64) -> Result<(), VoterError> {
        let donor =
            (0..self.slots.len()).find(|&d| self.slots[d].as_ref().is_some_and(|r| r.proven));
        if let Some(d) = donor {
            let family: Vec<libc::pid_t> = self.slots.iter().flatten().map(|r| r.pid).collect();
            self.restart_nonce = self.restart_nonce.wrapping_add(1).max(1);
            let donor_rep = self.slots[d].as_mut().expect("donor slot is filled");
            match recovery::fork_from(
                &self.plan,
                &self.listener,
                donor_rep,
                self.restart_nonce,
                &family,
            ) {
                Ok(child) => {
                    let mut ev = self.recovery_event(slot, old_pid, child.pid, detected_ns);
                    ev.donor = Some(d);
                    ev.method = Some(RecoveryMethod::Fork);
                    ev.state_lost = Some(false);
                    self.emit(ev);
                    self.slots[slot] = Some(child);
                    return Ok(());
                }
                Err(e) => {
                    tracing::warn!(replica = slot, donor = d, error = %e, "recovery by fork failed; starting a fresh replica");
                }
            }
        }
        match Replica::spawn(&self.plan, slot) {
            Ok(fresh) => {
                let mut ev = self.recovery_event(slot, old_pid, fresh.pid, detected_ns);
                ev.method = Some(RecoveryMethod::Exec);
                ev.state_lost = Some(true);
                self.emit(ev);
                self.slots[slot] = Some(fresh);
                Ok(())
            }
            Err(e) => {
                let mut ev = self.event(EventKind::RecoveryFailed);
                ev.replica = Some(slot);
                ev.pid = Some(old_pid);
                ev.detail = Some(format!("could not start {}: {e}", self.plan.exec.display()));
                self.emit(ev);
                if self.slots.iter().all(Option::is_none) {
                    return Err(VoterError::Unrecoverable(format!(
                        "no replica left and {} cannot be started: {e}",
                        self.plan.exec.display()
                    )));
                }
                Ok(())
            }
        }
    }

    fn recovery_event(&self, slot: usize, old_pid: i32, new_pid: i32, detected_ns: u64) -> Event {
        let mut ev = self.event(EventKind::Recovery);
        ev.replica = Some(slot);
        ev.pid = Some(old_pid);
        ev.new_pid = Some(new_pid);
        ev.recovery_us = Some(ev.ts_ns.saturating_sub(detected_ns) / 1000);
        ev
    }

    // ----- events ------------------------------------------------------------------------

    fn event(&self, kind: EventKind) -> Event {
        Event::new(&self.plan.system, &self.plan.component, kind)
    }

    fn emit(&self, ev: Event) {
        // Bootstrap logs every event it gathers; here they are only traced, so that a run
        // shows each event once. Without an events fd, the voter's own log is all there is.
        if self.events.is_some() {
            tracing::debug!(kind = ?ev.kind, replica = ev.replica, pid = ev.pid, detail = ev.detail.as_deref(), "event");
        } else {
            tracing::warn!(kind = ?ev.kind, replica = ev.replica, pid = ev.pid, detail = ev.detail.as_deref(), "event");
        }
        let Some(fd) = &self.events else { return };
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
        while self.outputs[o].writer.has_pending() && !self.outputs[o].broken {
            let left = deadline.saturating_duration_since(Instant::now());
            let mut pfd = [libc::pollfd {
                fd: self.outputs[o].writer.as_fd().as_raw_fd(),
                events: libc::POLLOUT,
                revents: 0,
            }];
            if left.is_zero() || sys::ppoll(&mut pfd, Some(left)).unwrap_or(0) == 0 {
                tracing::warn!(output = %self.outputs[o].name, "downstream did not take the last frames");
                return;
            }
            self.flush_output(o);
        }
    }

    /// Kills every replica and everything re-parented to us; removes the socket.
    fn shut_down(&mut self) {
        // On a requested stop, whatever downstream can take right now still goes out.
        for o in 0..self.outputs.len() {
            if self.outputs[o].writer.has_pending() && !self.outputs[o].broken {
                self.flush_output(o);
            }
        }
        for rep in self.slots.iter().flatten() {
            rep.kill();
        }
        for fault in &self.faults {
            fault.replica.kill();
        }
        for rep in self.slots.iter().flatten() {
            rep.exited_within(DEATH_WAIT);
        }
        kill_all_children(Duration::from_secs(3));
        let _ = std::fs::remove_file(&self.plan.socket_path);
    }
}

/// Also on a panic: no replica outlives its voter (bootstrap's sweep would catch them, but the
/// voter should not depend on it).
impl Drop for Voter {
    fn drop(&mut self) {
        for rep in self.slots.iter().flatten() {
            rep.kill();
        }
        for fault in &self.faults {
            fault.replica.kill();
        }
    }
}

fn validate(plan: &VoterPlan) -> Result<(), VoterError> {
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
    if plan.rounds.is_empty() {
        return fail("reactive mode needs at least one input that starts rounds".into());
    }
    Ok(())
}

/// Takes ownership of an fd this process inherited.
fn inherited(fd: RawFd) -> OwnedFd {
    sys::adopt_inherited_fd(fd)
}

/// SIGTERM/SIGINT/SIGCHLD arrive through a signalfd, read in the event loop.
fn block_signals() -> Result<SignalFd, VoterError> {
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
fn reap_children() {
    while let Ok(Some((pid, status))) = sys::reap_any() {
        tracing::trace!(pid, %status, "reaped");
    }
}

/// Kills every child of ours until none is left (or `limit` passes). As a subreaper we inherit
/// the children of dying children, so this converges on the whole subtree.
fn kill_all_children(limit: Duration) {
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
