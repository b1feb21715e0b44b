//! The voter's event loop for stream mode (S³RES VoterD), for components whose outputs are not
//! one per input (a mapper, a planner, a batcher). See `docs/stream-mode.md`.
//!
//! Every external input frame is copied to every replica, as in reactive mode, but nothing
//! waits for an answer. Instead the k-th frame of each output is voted across replicas
//! ([`ledger`]) and forwarded once a majority agrees. The loop keeps the replicas in step:
//! * a replica `window` frames ahead of the slowest is not read (its pipe fills, it blocks);
//! * while replicas are out of step, no new external input is read;
//! * the replica furthest behind runs one step above its siblings ([`boost`]);
//! * a frame some replicas produced and others did not within `timeout_us` makes the laggards
//!   `hang` suspects (or, when the producers are fewer and every laggard sleeps waiting for
//!   input, the producers `protocol` suspects).
//!
//! Faulty replicas are killed at once and replaced at the top of the loop, by fork of a trusted
//! replica that may be in the middle of its work: the child tells how many frames its process
//! had sent on each output, and takes the donor's place in the ledger from there.

pub mod boost;
pub mod ledger;
pub mod liveness;

use std::os::fd::OwnedFd;
use std::os::unix::net::UnixListener;
use std::time::Duration;

use nix::sys::signalfd::SignalFd;

use crate::channel::Fill;
use crate::event::{Event, EventKind, RecoveryMethod};
use crate::monitor::{Captures, Monitors};
use crate::plan::VoterPlan;
use crate::recovery::{self, DonorState};
use crate::replica::Replica;
use crate::vote::ReplicaSet;
use crate::voter::{
    closed_output_fault, kill_replicas, recovery_event, replace_by_exec, shut_down, start_replicas,
    stop_requested, validate, write_event, Endpoints, ExternalInput, ExternalOutput, Fault, Stop,
    Token, VoterError, EXIT_AFTER_EOF, OUTPUT_DRAIN_LIMIT, SHUTDOWN_GRACE,
};
use crate::voter::{wait_until, PollSet};
use boost::Boost;

use crate::clock::{self, Instant};
use crate::rt::RealTime;
use ledger::{Arrival, Decision, Ledger};
use liveness::{Liveness, Sample};

/// How far decoding of a replica's output may go.
#[derive(Debug, Clone, Copy)]
enum Until {
    /// Up to the window (normal operation).
    Window,
    /// Ignoring the window, until this many frames came from the current process (a donor's
    /// frames from before its fork, which its child reported).
    Received(u64),
}

pub struct StreamVoter {
    plan: VoterPlan,
    timeout: Duration,
    inputs: Vec<ExternalInput>,
    outputs: Vec<ExternalOutput>,
    slots: Vec<Option<Replica>>,
    ledger: Ledger,
    faults: Vec<Fault>,
    /// Names the current fork attempt; a child of an older attempt is refused.
    restart_nonce: u32,
    listener: UnixListener,
    signals: SignalFd,
    events: Option<OwnedFd>,
    stop: Option<Stop>,
    /// Every input frame has been handed to the replicas (none is held back in a decoder).
    delivered_all: bool,
    /// The external inputs are over and the replicas' inputs closed: until this instant the
    /// replicas may finish their last outputs.
    ending: Option<Instant>,
    /// Per slot: the process exited after the end began (not a fault then).
    exited: Vec<bool>,
    boost: Boost,
    /// Priorities and pinning (the scheme of `crate::sched`, as in reactive mode).
    rt: RealTime,
    /// The laggard raised to the turn priority under SCHED_RR: `(pid, slot)`.
    boosted: Option<(libc::pid_t, usize)>,
    poll: PollSet,
    /// Hangs no deadline sees: every replica stuck at once (see [`liveness`]).
    liveness: Liveness,
    /// Anomaly detectors on monitored outputs: every frame taken into the ledger is scored.
    monitors: Monitors,
    /// Forwarded frames of captured outputs, for training detectors.
    captures: Captures,
}

impl StreamVoter {
    /// Takes over the fds named in `plan`, binds the socket, and starts the replicas.
    pub fn start(plan: VoterPlan) -> Result<StreamVoter, VoterError> {
        validate(&plan)?;
        // Calibrated before the first frame, so that it never eats into a deadline.
        clock::init()?;
        // Models are loaded and capture files made before any replica runs.
        let monitors = Monitors::load(&plan)?;
        let captures = Captures::open(&plan)?;
        let Endpoints {
            signals,
            inputs,
            outputs,
            events,
            listener,
        } = Endpoints::open(&plan)?;
        let n = plan.replicas;
        // Before the first replica: replicas start from the voter's settings.
        let mut rt = RealTime::new(&plan);
        rt.apply_to_voter();
        let slots = start_replicas(&plan, events.as_ref(), |pid, slot| {
            rt.apply_to_replica(pid, slot)
        })?;
        Ok(StreamVoter {
            rt,
            boosted: None,
            timeout: Duration::from_micros(plan.timeout_us),
            ledger: Ledger::new(n, plan.outputs.len(), plan.window),
            liveness: Liveness::new(n, Duration::from_micros(plan.timeout_us)),
            slots,
            exited: vec![false; n],
            plan,
            inputs,
            outputs,
            faults: Vec::new(),
            restart_nonce: 0,
            listener,
            signals,
            events,
            stop: None,
            delivered_all: true,
            ending: None,
            boost: Boost::default(),
            poll: PollSet::default(),
            monitors,
            captures,
        })
    }

    /// Runs until the inputs close and the replicas have finished, or a stop is requested.
    pub fn run(mut self) -> Result<(), VoterError> {
        let result = self.run_loop();
        self.captures.flush();
        self.monitors.log_cost();
        shut_down(
            &self.plan,
            &mut self.outputs,
            self.slots.iter().flatten(),
            &self.faults,
        );
        result
    }

    fn run_loop(&mut self) -> Result<(), VoterError> {
        loop {
            let away = Instant::now();
            let recovered = !self.faults.is_empty();
            self.recover_faulty()?;
            if recovered {
                // Recovery blocks the loop (waiting for a death, the fork, the child's page
                // walk); the laggards' clocks stop meanwhile.
                self.ledger.postpone(away.elapsed());
                self.liveness.restart(Instant::now());
            }
            if self.stop == Some(Stop::Requested) {
                return Ok(());
            }
            self.deliver_input();
            if self.ending.is_none() && self.ready_to_end() {
                self.begin_end();
            }
            if let Some(limit) = self.ending {
                if self.all_finished() || Instant::now() >= limit {
                    return self.finish();
                }
            }
            self.boost_laggard();
            self.wait_and_dispatch()?;
            if self.stop == Some(Stop::Requested) {
                return Ok(());
            }
            if self.ending.is_none() {
                self.fault_closed_outputs();
            }
            self.check_deadlines();
            self.decode_all();
            self.check_liveness();
        }
    }

    /// Trusted replicas.
    fn alive(&self) -> ReplicaSet {
        (0..self.slots.len())
            .filter(|&r| self.slots[r].is_some())
            .fold(ReplicaSet::EMPTY, ReplicaSet::with)
    }

    // ----- the loop's wait ---------------------------------------------------------------

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
                Token::Signal => {
                    if stop_requested(&self.signals) {
                        self.stop = Some(Stop::Requested);
                    }
                }
                Token::Input(i) => self.on_input_readable(i),
                Token::OutputWritable(o) => self.outputs[o].flush(),
                Token::ReplicaExit(r) => self.on_replica_exit(r),
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
        let alive = self.alive();
        let take_input = !self.holding_input();
        self.poll
            .reset(&self.signals, &self.inputs, take_input, &self.outputs);
        for (r, rep) in self.slots.iter().enumerate() {
            let Some(rep) = rep else { continue };
            // Back-pressure: a replica far ahead is not read, so its pipe fills.
            let ledger = &self.ledger;
            self.poll
                .add_replica(r, rep, !self.exited[r], |o| ledger.may_read(r, o, alive));
        }
    }

    /// The nearest of: a laggard's deadline, the end of a closed-pipe grace, the end's limit.
    fn next_wakeup(&self) -> Option<Instant> {
        let graces = self
            .slots
            .iter()
            .flatten()
            .filter_map(|rep| rep.output_closed_at.map(|t| t + EXIT_AFTER_EOF));
        let look = self
            .ending
            .is_none()
            .then(|| self.liveness.next_look(Instant::now()));
        self.ledger
            .next_deadline(self.alive(), self.timeout)
            .into_iter()
            .chain(graces)
            .chain(self.ending)
            .chain(look)
            .min()
    }

    // ----- input side ----------------------------------------------------------------------

    /// New external input waits while replicas are out of step (one has produced a frame
    /// another has not, or a frame is undecided), while a faulty replica awaits its
    /// replacement, while a replica has not taken the input it was given, and while downstream
    /// has not taken the last output. The replicas always have the input the frames they owe
    /// depend on, and the voter keeps reading their outputs, so holding never deadlocks.
    fn holding_input(&self) -> bool {
        !self.faults.is_empty()
            || self.ending.is_some()
            || self.outputs.iter().any(|o| o.writer.has_pending())
            || self
                .slots
                .iter()
                .flatten()
                .any(|rep| rep.inputs.iter().any(|i| i.writer.has_pending()))
            || self.ledger.out_of_step(self.alive())
    }

    fn on_input_readable(&mut self, i: usize) {
        self.inputs[i].read();
        self.delivered_all = false;
        self.deliver_input();
    }

    /// Copies buffered input frames to every replica, one at a time, while not holding.
    fn deliver_input(&mut self) {
        if self.delivered_all {
            return;
        }
        for i in 0..self.inputs.len() {
            loop {
                if self.holding_input() {
                    return;
                }
                let input = &mut self.inputs[i];
                let frame = match input.reader.decoder.next_frame() {
                    Ok(Some(f)) => f,
                    Ok(None) => break,
                    Err(e) => {
                        tracing::error!(input = %input.name, error = %e, "bad frame from upstream; dropping the rest of this input");
                        input.reader.close();
                        break;
                    }
                };
                let mut broken = Vec::new();
                for (r, rep) in self.slots.iter_mut().enumerate() {
                    let Some(rep) = rep else { continue };
                    if let Err(e) = rep.inputs[i].writer.send(frame) {
                        broken.push((r, e));
                    }
                }
                for (r, e) in broken {
                    let detail = format!("input pipe `{}` broke: {e}", self.plan.inputs[i].name);
                    self.fault(r, EventKind::Protocol, detail);
                }
            }
        }
        self.delivered_all = true;
    }

    // ----- output side ---------------------------------------------------------------------

    fn on_replica_output(&mut self, r: usize, o: usize) {
        let Some(rep) = self.slots[r].as_mut() else {
            return;
        };
        let fill = rep.outputs[o].fill();
        self.decode(r, o, Until::Window);
        match fill {
            Ok(Fill::Open) => {}
            Ok(Fill::Closed) => self.on_output_closed(r),
            Err(e) => {
                let detail = format!("reading output `{}`: {e}", self.plan.outputs[o].name);
                self.fault(r, EventKind::Protocol, detail);
            }
        }
    }

    /// Decodes what is buffered for every trusted replica, as far as the window allows, until
    /// nothing more can be taken: one replica catching up lets another on, and the frames
    /// are already here (no pipe will wake the loop for them).
    fn decode_all(&mut self) {
        loop {
            let before = self.taken();
            for r in 0..self.slots.len() {
                for o in 0..self.outputs.len() {
                    self.decode(r, o, Until::Window);
                }
            }
            if self.taken() == before {
                return;
            }
        }
    }

    /// Frames taken into the ledger so far, over all trusted replicas and outputs.
    fn taken(&self) -> u64 {
        self.alive()
            .iter()
            .flat_map(|r| (0..self.outputs.len()).map(move |o| (r, o)))
            .map(|(r, o)| self.ledger.pos(r, o))
            .sum()
    }

    /// Takes the whole frames buffered for replica `r` on output `o` into the ledger.
    fn decode(&mut self, r: usize, o: usize, until: Until) {
        loop {
            let alive = self.alive();
            let go_on = match until {
                Until::Window => self.ledger.may_read(r, o, alive),
                Until::Received(n) => self.ledger.received(r, o) < n,
            };
            let Some(rep) = self.slots[r].as_mut().filter(|_| go_on) else {
                return;
            };
            let frame = match rep.outputs[o].decoder.next_frame() {
                Ok(Some(f)) => f,
                Ok(None) => return,
                Err(e) => {
                    let detail = format!("output `{}`: {e}", self.plan.outputs[o].name);
                    return self.fault(r, EventKind::Protocol, detail);
                }
            };
            rep.proven = true;
            let pid = rep.pid;
            // Every frame is scored, also when all agree and also late copies: each replica's
            // stream must be complete for the next delta to be meaningful.
            let after_alarm = self.monitors.alarmed(r, o);
            let verdict = self.monitors.observe(r, o, frame);
            let arrival = self.ledger.accept(r, o, frame, Instant::now());
            if verdict.is_some_and(|v| v.alarm) {
                self.ledger.flag_last(r, o);
                self.anomaly_event(r, pid, o, after_alarm);
            }
            match arrival {
                Arrival::Fine => {}
                Arrival::DiffersFromForwarded(index) => {
                    let detail = format!(
                        "frame {index} of `{}` differs from the majority's",
                        self.plan.outputs[o].name
                    );
                    return self.fault(r, EventKind::Sdc, detail);
                }
            }
            self.decide(o);
        }
    }

    /// Forwards (or withholds) every frame of output `o` that can be decided now; minority
    /// replicas are `sdc` faults.
    fn decide(&mut self, o: usize) {
        while let Some(decision) = self.ledger.decide(o, self.alive()) {
            match decision {
                Decision::Forward {
                    index,
                    frame,
                    dissent,
                } => {
                    self.outputs[o].send(&frame);
                    self.captures.record(o, &frame);
                    for r in dissent.iter() {
                        let detail = format!(
                            "frame {index} of `{}` differs from the majority's",
                            self.plan.outputs[o].name
                        );
                        self.fault(r, EventKind::Sdc, detail);
                    }
                }
                Decision::Rebuild { index, rebuilt } => {
                    self.outputs[o].send(&rebuilt.frame);
                    self.captures.record(o, &rebuilt.frame);
                    let name = &self.plan.outputs[o].name;
                    if let Some(k) = rebuilt.kept {
                        // Every replica's frame was hit: one must stay to fork the others from.
                        let mut ev = self.event(EventKind::Sdc);
                        ev.detail = Some(format!(
                            "no majority on frame {index} of `{name}`, every replica's differs from the bitwise majority (forwarded); replica {k}, the closest, kept as donor"
                        ));
                        self.emit(ev);
                    }
                    let detail = format!(
                        "frame {index} of `{name}` had no majority and differs from the bitwise majority, which was forwarded (≤ {} bits apart)",
                        rebuilt.max_bits
                    );
                    for r in rebuilt.dissent.iter() {
                        self.fault(r, EventKind::Sdc, detail.clone());
                    }
                }
                Decision::Withhold { index, answered } => {
                    // A fault is certain, its culprit is not: withhold the frame, blame
                    // nobody, go on with the next frame (never stall).
                    let mut ev = self.event(EventKind::Sdc);
                    ev.detail = Some(format!(
                        "no majority on frame {index} of `{}`: replicas {answered:?} disagree; frame withheld",
                        self.plan.outputs[o].name
                    ));
                    self.emit(ev);
                }
                Decision::HoldBack { index, replica } => {
                    let detail = format!(
                        "anomaly detector flagged frame {index} of `{}` (see its `anomaly` event) and no other replica confirms it; frame held back",
                        self.plan.outputs[o].name
                    );
                    self.fault(replica, EventKind::Sdc, detail);
                }
                Decision::Attribute {
                    index,
                    frame,
                    culprit,
                    healthy,
                } => {
                    self.outputs[o].send(&frame);
                    self.captures.record(o, &frame);
                    let detail = format!(
                        "frame {index} of `{}` differs from replica {healthy}'s and the anomaly detector flagged it (see its `anomaly` event) but not replica {healthy}'s, which was forwarded",
                        self.plan.outputs[o].name
                    );
                    self.fault(culprit, EventKind::Sdc, detail);
                }
            }
        }
        self.ledger.trim(self.alive());
    }

    /// Every alarm is an `anomaly` event (replica `r`'s latest frame on `o`), whatever the
    /// ledger then does about it. `after_alarm`: the replica's previous frame on `o` alarmed
    /// too. A replica that runs ahead has its frames scored before the vote on a corrupted
    /// one removes it, and the frame after a corrupted one alarms on the way back (the
    /// detector's reference is the corrupted frame); the detail says so.
    fn anomaly_event(&self, r: usize, pid: libc::pid_t, o: usize, after_alarm: bool) {
        let Some(alarm) = self.monitors.alarm(r, o) else {
            return;
        };
        let frame = self.ledger.pos(r, o).saturating_sub(1);
        let mut ev = self.event(EventKind::Anomaly);
        ev.replica = Some(r);
        ev.pid = Some(pid);
        ev.output = Some(self.plan.outputs[o].name.clone());
        ev.field = alarm.field;
        ev.score = alarm.score;
        ev.threshold = Some(alarm.threshold);
        let way_back = if after_alarm {
            "; its previous frame alarmed too (this may be the way back from it)"
        } else {
            ""
        };
        ev.detail = Some(format!("{} (frame {frame}){way_back}", alarm.cause));
        self.emit(ev);
    }

    fn decide_all(&mut self) {
        for o in 0..self.outputs.len() {
            self.decide(o);
        }
    }

    // ----- faults --------------------------------------------------------------------------

    /// Records a fault, kills the replica at once and queues its slot for recovery.
    fn fault(&mut self, r: usize, kind: EventKind, detail: String) {
        let Some(replica) = self.slots[r].take() else {
            return;
        };
        replica.kill();
        self.boost.forget(replica.pid);
        if self.boosted.is_some_and(|(pid, _)| pid == replica.pid) {
            self.boosted = None;
        }
        self.ledger.forget(r);
        self.liveness.forget(r);
        let mut ev = self.event(kind);
        ev.replica = Some(r);
        ev.pid = Some(replica.pid);
        ev.detail = Some(detail);
        let detected_ns = ev.ts_ns;
        self.emit(ev);
        self.faults.push(Fault {
            slot: r,
            replica,
            detected_ns,
        });
        // Fewer trusted replicas may decide a pending frame.
        self.decide_all();
    }

    fn on_replica_exit(&mut self, r: usize) {
        if self.ending.is_some() {
            // Its input is closed: finishing is what it should do. Its last frames are still
            // in its pipes and are read to the end.
            self.exited[r] = true;
            return;
        }
        if self.slots[r].is_some() {
            self.fault(r, EventKind::Crash, "the replica process died".into());
        }
    }

    /// A closed output is a crash if the process is gone within [`EXIT_AFTER_EOF`], else a
    /// protocol fault (see reactive mode). After the end began, closing is finishing.
    fn on_output_closed(&mut self, r: usize) {
        if self.ending.is_some() {
            return;
        }
        if self.slots[r]
            .as_mut()
            .is_some_and(Replica::note_output_closed)
        {
            self.fault(r, EventKind::Crash, "the replica process died".into());
        }
    }

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

    /// Blames the replicas on the wrong side of the oldest overdue frame (see
    /// [`ledger::Overdue::blames_laggards`]).
    fn check_deadlines(&mut self) {
        if self
            .ledger
            .overdue(self.alive(), self.timeout, Instant::now())
            .is_none()
        {
            return;
        }
        // One last look first: a frame may have arrived while the voter itself was busy, and
        // the voter's lateness is not the replica's fault.
        for r in 0..self.slots.len() {
            let Some(rep) = self.slots[r].as_mut() else {
                continue;
            };
            // A read error shows on the next read; a closed pipe is handled like any other.
            let closed = rep
                .outputs
                .iter_mut()
                .filter(|out| !out.is_closed())
                .any(|out| matches!(out.fill(), Ok(Fill::Closed)));
            if closed {
                self.on_output_closed(r);
            }
        }
        self.decode_all();
        let Some(od) = self
            .ledger
            .overdue(self.alive(), self.timeout, Instant::now())
        else {
            return;
        };
        let name = self.plan.outputs[od.output].name.clone();
        if od.blames_laggards() {
            return self.blame_laggards(od.laggards, &od, &name, "furthest behind");
        }
        // Fewer producers than laggards: usually the producers made a frame nobody owes (an
        // extra frame). But a laggard that is still running (or stopped) at the deadline has
        // not finished its work and gone back to wait for input: it is hung — spinning in a
        // control-flow error, say — and two hung replicas must not outvote the healthy one.
        // So laggards that are not asleep are blamed; only when every laggard sleeps are the
        // producers the suspects.
        let stuck = od
            .laggards
            .iter()
            .filter(|&r| !self.slots[r].as_ref().is_some_and(Replica::is_asleep))
            .fold(ReplicaSet::EMPTY, ReplicaSet::with);
        if !stuck.is_empty() {
            return self.blame_laggards(stuck, &od, &name, "behind and not waiting for input");
        }
        for r in od.producers.iter() {
            let detail = format!(
                "produced frame {} of `{name}`, which replicas {:?} did not produce within {} µs",
                od.index, od.laggards, self.plan.timeout_us
            );
            self.fault(r, EventKind::Protocol, detail);
        }
    }

    /// Blames `laggards` for overdue frame `od`: `protocol` if a laggard left a partial frame
    /// in its pipe, else `hang` (`why` says how it was picked).
    fn blame_laggards(
        &mut self,
        laggards: ReplicaSet,
        od: &ledger::Overdue,
        name: &str,
        why: &str,
    ) {
        for r in laggards.iter() {
            let partial = self.slots[r]
                .as_ref()
                .and_then(|rep| rep.outputs.iter().position(|out| out.decoder.pending() > 0));
            let (kind, detail) = match partial {
                Some(p) => (
                    EventKind::Protocol,
                    format!(
                        "partial frame on `{}` when frame {} of `{name}` was overdue",
                        self.plan.outputs[p].name, od.index
                    ),
                ),
                None => (
                    EventKind::Hang,
                    format!(
                        "{why}: frame {} of `{name}` not produced within {} µs of replicas {:?}",
                        od.index, self.plan.timeout_us, od.producers
                    ),
                ),
            };
            self.fault(r, kind, detail);
        }
    }

    /// Every `timeout_us`: a replica that computed all that time without producing a frame or
    /// waiting for anything is a `hang`, also when no frame is owed (see [`liveness`]).
    fn check_liveness(&mut self) {
        let now = Instant::now();
        if self.ending.is_some() || !self.liveness.due(now) {
            return;
        }
        self.liveness.looked(now);
        for r in 0..self.slots.len() {
            let sample = self.slots[r]
                .as_ref()
                .and_then(|rep| Sample::take(rep.pid, self.ledger.progress(r)));
            if let Some(ms) = self.liveness.update(r, sample) {
                let detail = format!(
                    "on a CPU for {ms} ms of the last {} µs without producing a frame or waiting for input",
                    self.plan.timeout_us
                );
                self.fault(r, EventKind::Hang, detail);
            }
        }
    }

    /// The furthest behind runs first (best effort; see [`boost`]).
    fn boost_laggard(&mut self) {
        let laggard = self
            .ledger
            .laggard(self.alive())
            .and_then(|r| self.slots[r].as_ref().map(|rep| (rep.pid, r)));
        if !self.rt.can_raise() {
            // No SCHED_RR: the best-effort nice boost of `boost`.
            return self.boost.set(laggard.map(|(pid, _)| pid));
        }
        // SCHED_RR: the laggard takes the turn priority, one step below the voter and above
        // every sibling at rest (the scheme of `crate::sched`); the previous one goes back.
        if self.boosted == laggard {
            return;
        }
        if let Some((pid, slot)) = self.boosted.take() {
            self.rt.rest(pid, slot);
        }
        if let Some((pid, _)) = laggard {
            self.rt.raise(pid);
        }
        self.boosted = laggard;
    }

    // ----- recovery ------------------------------------------------------------------------

    fn recover_faulty(&mut self) -> Result<(), VoterError> {
        while let Some(fault) = self.faults.pop() {
            if self.stop.is_some() || self.ending.is_some() {
                // At the end a replacement would only be closed again; the fault is recorded.
                continue;
            }
            let (slot, old_pid, detected_ns) = fault.retire();
            self.replace(slot, old_pid, detected_ns)?;
        }
        Ok(())
    }

    fn replace(&mut self, slot: usize, old_pid: i32, detected_ns: u64) -> Result<(), VoterError> {
        let pick =
            crate::replica::best_donor(&self.slots, |d| self.ledger.progress(d), self.timeout);
        for r in pick.hung {
            let detail = format!(
                "picked as recovery donor, it ran for {} µs without once producing a frame or waiting for input",
                self.plan.timeout_us
            );
            self.fault(r, EventKind::Hang, detail);
        }
        let donor = pick.donor;
        if let Some(d) = donor {
            let donor_proven = self.slots[d].as_ref().is_some_and(|r| r.proven);
            match self.fork_into(slot, d) {
                Ok(pid) => {
                    // The child continues the donor's frames, so its detector stream too.
                    self.monitors.copy_stream(d, slot);
                    // The child inherited the donor's priority and CPU; it takes the slot's.
                    self.rt.apply_to_replica(pid, slot);
                    let mut ev = recovery_event(&self.plan, slot, old_pid, pid, detected_ns);
                    ev.donor = Some(d);
                    ev.method = Some(RecoveryMethod::Fork);
                    // A donor that has not answered yet was itself just started by exec.
                    ev.state_lost = Some(!donor_proven);
                    self.emit(ev);
                    self.decide_all();
                    return Ok(());
                }
                Err(e) => {
                    tracing::warn!(replica = slot, donor = d, error = %e, "recovery by fork failed; starting a fresh replica");
                }
            }
        }
        let started = replace_by_exec(
            &self.plan,
            self.events.as_ref(),
            &mut self.slots,
            (slot, old_pid, detected_ns),
            |pid, slot| self.rt.apply_to_replica(pid, slot),
        )?;
        if started {
            self.ledger.start_fresh(slot);
            self.monitors.reset_stream(slot);
            self.exited[slot] = false;
        }
        Ok(())
    }

    /// Forks `donor` into `slot`, and gives the child the donor's place in the ledger: the
    /// donor's frames from before the fork are read out of its pipe (they are all there: the
    /// fork waits until a frame being written is whole) and the undecided ones are copied to
    /// the child, whose state is already past them.
    fn fork_into(&mut self, slot: usize, d: usize) -> Result<libc::pid_t, String> {
        let family: Vec<libc::pid_t> = self.slots.iter().flatten().map(|r| r.pid).collect();
        self.restart_nonce = self.restart_nonce.wrapping_add(1).max(1);
        let donor = self.slots[d].as_mut().expect("donor slot is filled");
        let donor_pid = donor.pid;
        // S³RES §4.4, as in reactive mode: the donor runs above its siblings while it forks (a
        // boosted laggard on its CPU would otherwise starve it into the accept timeout).
        self.rt.raise(donor_pid);
        let forked = recovery::fork(
            &self.plan,
            &self.listener,
            donor,
            self.restart_nonce,
            &family,
            DonorState::Streaming,
        );
        self.rt.rest(donor_pid, d);
        if self.boosted.is_some_and(|(pid, _)| pid == donor_pid) {
            // Put back to rest above: the next `boost_laggard` raises it again if it still lags.
            self.boosted = None;
        }
        let forked = forked.map_err(|e| e.to_string())?;
        for (o, &sent) in forked.frames_sent.iter().enumerate() {
            self.read_donor_until(d, o, sent);
            let short = self.slots[d]
                .as_ref()
                .map(|_| self.ledger.received(d, o) < sent);
            let problem = match short {
                None => Some("the donor failed while its frames were read".to_owned()),
                Some(true) => Some(format!(
                    "the donor's output `{}` holds {} frames, its child reported {sent}",
                    self.plan.outputs[o].name,
                    self.ledger.received(d, o)
                )),
                Some(false) => None,
            };
            if let Some(problem) = problem {
                forked.replica.kill();
                return Err(problem);
            }
        }
        self.ledger.join_from(slot, d, &forked.frames_sent);
        let pid = forked.replica.pid;
        self.slots[slot] = Some(forked.replica);
        self.exited[slot] = false;
        Ok(pid)
    }

    /// Reads the donor's output `o` until `sent` frames of its process were received, or its
    /// pipe is empty.
    fn read_donor_until(&mut self, d: usize, o: usize, sent: u64) {
        loop {
            self.decode(d, o, Until::Received(sent));
            let Some(rep) = self.slots[d].as_mut() else {
                return;
            };
            if self.ledger.received(d, o) >= sent || rep.outputs[o].is_closed() {
                return;
            }
            let before = rep.outputs[o].decoder.pending();
            let _ = rep.outputs[o].fill();
            if rep.outputs[o].decoder.pending() == before {
                return;
            }
        }
    }

    // ----- the end -------------------------------------------------------------------------

    /// Every external input closed, all of it handed over and taken by the replicas, and
    /// nothing to repair.
    fn ready_to_end(&self) -> bool {
        self.stop.is_none()
            && self.delivered_all
            && self.faults.is_empty()
            && self.inputs.iter().all(|i| i.reader.is_closed())
            && !self
                .slots
                .iter()
                .flatten()
                .any(|rep| rep.inputs.iter().any(|i| i.writer.has_pending()))
    }

    /// Closes the replicas' inputs: they see the end of their input and may write last frames
    /// (a batch flushed at the end), which are voted like any other.
    fn begin_end(&mut self) {
        tracing::debug!("inputs closed; letting the replicas finish their output");
        for rep in self.slots.iter_mut().flatten() {
            rep.inputs.clear();
        }
        self.ending = Some(Instant::now() + SHUTDOWN_GRACE + self.timeout);
    }

    /// Every trusted replica has closed its outputs, all their frames are taken, and no
    /// frame is owed or undecided.
    fn all_finished(&self) -> bool {
        let alive = self.alive();
        self.slots.iter().flatten().all(|rep| {
            rep.outputs
                .iter()
                .all(|out| out.is_closed() && out.decoder.pending() == 0)
        }) && !self.ledger.out_of_step(alive)
    }

    /// Writes out what is queued for downstream and lets the replicas exit.
    fn finish(&mut self) -> Result<(), VoterError> {
        if !self.all_finished() {
            let alive = self.alive();
            let state: Vec<String> = (0..self.outputs.len())
                .map(|o| {
                    let per_slot: Vec<String> = alive
                        .iter()
                        .map(|r| {
                            let out = &self.slots[r].as_ref().expect("alive").outputs[o];
                            format!(
                                "{r}: frame {} (buffered {} B{})",
                                self.ledger.pos(r, o),
                                out.decoder.pending(),
                                if out.is_closed() { ", closed" } else { "" }
                            )
                        })
                        .collect();
                    format!(
                        "`{}` next {}: {}",
                        self.plan.outputs[o].name,
                        self.ledger.next(o),
                        per_slot.join(", ")
                    )
                })
                .collect();
            tracing::warn!(state = %state.join("; "), "replicas did not finish their output in time; stopping them");
        }
        let drain_deadline = Instant::now() + OUTPUT_DRAIN_LIMIT;
        for out in &mut self.outputs {
            out.drain(drain_deadline);
        }
        let deadline = Instant::now() + SHUTDOWN_GRACE;
        for rep in self.slots.iter().flatten() {
            let left = deadline.saturating_duration_since(Instant::now());
            if !rep.exited_within(left) {
                tracing::warn!(
                    pid = rep.pid,
                    "replica did not exit after its input closed; killing it"
                );
            }
        }
        Ok(())
    }

    // ----- events --------------------------------------------------------------------------

    fn event(&self, kind: EventKind) -> Event {
        Event::new(&self.plan.system, &self.plan.component, kind)
    }

    fn emit(&self, ev: Event) {
        write_event(self.events.as_ref(), &ev);
    }
}

/// Also on a panic: no replica outlives its voter.
impl Drop for StreamVoter {
    fn drop(&mut self) {
        kill_replicas(&self.slots, &self.faults);
    }
}
