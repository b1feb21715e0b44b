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

use std::time::Duration;

use crate::channel::Fill;
use crate::clock::Instant;
use crate::core::{self, At, Core, Mode, Stop, VoterError};
use crate::event::Cause;
use crate::plan::VoterPlan;
use crate::recovery::DonorState;
use crate::replica::Replica;
use crate::vote::{ReplicaSet, MAX_REPLICAS};
use boost::Boost;
use ledger::{Arrival, Decided, Ledger};
use liveness::{Liveness, Sample};

/// Whether replica `r`'s decoder of output `o` met a `RESUME` beyond the frames it had taken
/// (the count is taken, so each gap is reported once).
fn rep_skipped(core: &mut Core, r: usize, o: usize) -> bool {
    core.slots[r]
        .as_mut()
        .is_some_and(|rep| rep.outputs[o].decoder.take_skipped() > 0)
}

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
    core: Core,
    timeout: Duration,
    ledger: Ledger,
    /// Every input frame has been handed to the replicas (none is held back in a decoder).
    delivered_all: bool,
    /// The external inputs are over and the replicas' inputs closed: the replicas finish
    /// their last outputs (see [`Ending`]).
    ending: Option<Ending>,
    /// Per slot: the process exited after the end began (not a fault then).
    exited: Vec<bool>,
    boost: Boost,
    /// The laggard raised to the turn priority under SCHED_RR: `(pid, slot)`.
    boosted: Option<(libc::pid_t, usize)>,
    /// Hangs no deadline sees: every replica stuck at once (see [`liveness`]).
    liveness: Liveness,
    /// Since when downstream has frames queued that it did not take: meanwhile no replica
    /// output is read (see [`StreamVoter::downstream_backlog`]).
    held_by_downstream: Option<Instant>,
}

/// The end of the stream: the replicas' inputs are closed and they finish their output.
#[derive(Debug, Clone, Copy)]
struct Ending {
    began: Instant,
    /// Until when they may: [`core::SHUTDOWN_GRACE`] and `timeout_us` after the last frame
    /// taken (or the beginning), at most [`ENDING_AT_MOST`] after the beginning.
    limit: Instant,
    /// Frames taken from the trusted replicas, at the beginning and so far.
    at_start: u64,
    taken: u64,
}

/// The longest end of a stream: replicas that still produce after it (a backlog of a minute,
/// or a replica that writes without end) are stopped.
const ENDING_AT_MOST: Duration = Duration::from_secs(60);

impl StreamVoter {
    /// Takes over the fds named in `plan`, binds the socket, and starts the replicas.
    pub fn start(plan: VoterPlan) -> Result<StreamVoter, VoterError> {
        let core = Core::start(plan)?;
        let n = core.plan.replicas;
        let timeout = Duration::from_micros(core.plan.timeout_us);
        let mut voter = StreamVoter {
            boosted: None,
            timeout,
            ledger: Ledger::new(n, core.plan.outputs.len(), core.plan.window),
            liveness: Liveness::new(n, timeout),
            exited: vec![false; n],
            core,
            delivered_all: true,
            ending: None,
            boost: Boost::default(),
            held_by_downstream: None,
        };
        voter.take_over_streams();
        Ok(voter)
    }

    /// An adopting voter lines the ledger up with its predecessor's journal: each output goes
    /// on from the frame committed as forwarded, and each adopted replica's decoder drops the
    /// frames of its history below it (`Ledger::resume`). The replayed input is delivered.
    fn take_over_streams(&mut self) {
        let Some(adopted) = self.core.adopted_streams.take() else {
            return;
        };
        let outputs = self.core.outputs.len();
        let offsets: Vec<Option<Vec<u64>>> = adopted
            .offsets
            .iter()
            .map(|off| off.map(|o| o[..outputs].to_vec()))
            .collect();
        let skip = self.ledger.resume(&adopted.forwarded, &offsets);
        for (slot, rep) in self.core.slots.iter_mut().enumerate() {
            let Some(rep) = rep else { continue };
            for (o, out) in rep.outputs.iter_mut().enumerate() {
                out.decoder.set_position(skip[slot][o], skip[slot][o]);
            }
        }
        self.delivered_all = false;
    }

    /// Records in the journal who is in each slot, with where its frames stand on every
    /// output, and commits what was taken and forwarded (a journaled voter only).
    fn keep_journal(&mut self) {
        if self.core.journal.is_none() {
            return;
        }
        for slot in 0..self.core.slots.len() {
            if self.core.slots[slot].is_none() {
                continue;
            }
            for o in 0..self.core.outputs.len() {
                self.core.slot_offsets[slot][o] =
                    self.ledger.pos(slot, o) - self.ledger.received(slot, o);
            }
        }
        self.core.journal_slots();
        self.core.note_written();
        self.core.commit(0);
    }

    /// Runs until the inputs close and the replicas have finished, or a stop is requested.
    pub fn run(self) -> Result<(), VoterError> {
        core::run(self)
    }

    // ----- the loop's wait ---------------------------------------------------------------

    fn poll_set(&mut self) {
        let alive = self.core.alive();
        let take_input = !self.holding_input();
        self.core.reset_poll(take_input);
        let core = &mut self.core;
        for (r, rep) in core.slots.iter().enumerate() {
            let Some(rep) = rep else { continue };
            // Back-pressure: a replica far ahead is not read, so its pipe fills.
            let ledger = &self.ledger;
            let held = self.held_by_downstream.is_some();
            core.poll.add_replica(r, rep, !self.exited[r], |o| {
                !held && ledger.may_read(r, o, alive)
            });
        }
    }

    /// The nearest of: a laggard's deadline, the end of a closed-pipe grace, the end's limit.
    fn wakeup(&self) -> Option<Instant> {
        let graces = self
            .core
            .slots
            .iter()
            .flatten()
            .filter_map(|rep| rep.output_grace_ends);
        // Held by downstream, the replicas' clocks stand still: its pipe's room wakes the loop.
        let held = self.held_by_downstream.is_some();
        let look =
            (self.ending.is_none() && !held).then(|| self.liveness.next_look(Instant::now()));
        let deadline = (!held)
            .then(|| self.ledger.next_deadline(self.core.alive(), self.timeout))
            .flatten();
        deadline
            .into_iter()
            .chain(graces)
            .chain(self.ending.as_ref().map(|e| e.limit))
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
        !self.core.faults.is_empty()
            || self.ending.is_some()
            || self.core.outputs.iter().any(|o| o.writer.has_pending())
            || self
                .core
                .slots
                .iter()
                .flatten()
                .any(|rep| rep.inputs.iter().any(|i| i.writer.has_pending()))
            || self.ledger.out_of_step(self.core.alive())
    }

    /// Copies buffered input frames to every replica, one at a time, while not holding.
    fn deliver_input(&mut self) {
        if self.delivered_all {
            return;
        }
        for i in 0..self.core.inputs.len() {
            loop {
                if self.holding_input() {
                    return;
                }
                // Nothing queued for anyone, nothing out of step: the moment to commit (under a
                // steady flood the top of the loop rarely finds one).
                self.keep_journal();
                if !self.core.journal_has_room(i) {
                    // The log is full of frames delivered since the last commit: commit them
                    // (once they are out of the voter), then go on.
                    self.keep_journal();
                    if !self.core.journal_has_room(i) {
                        return;
                    }
                }
                let Some(delivery) = self.core.deliver_next(i, None) else {
                    break;
                };
                for (r, cause, detail) in delivery.faulty {
                    self.fault(r, cause, detail);
                }
            }
        }
        self.delivered_all = true;
    }

    // ----- output side ---------------------------------------------------------------------

    fn on_output(&mut self, r: usize, o: usize) {
        let Some(rep) = self.core.slots[r].as_mut() else {
            return;
        };
        let fill = rep.outputs[o].fill();
        self.decode(r, o, Until::Window);
        core::after_read(self, r, o, fill);
    }

    /// Decodes what is buffered for every trusted replica, as far as the window allows, until
    /// nothing more can be taken: one replica catching up lets another on, and the frames
    /// are already here (no pipe will wake the loop for them).
    fn decode_all(&mut self) {
        loop {
            let before = self.taken();
            for r in 0..self.core.slots.len() {
                for o in 0..self.core.outputs.len() {
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
        self.core
            .alive()
            .iter()
            .flat_map(|r| (0..self.core.outputs.len()).map(move |o| (r, o)))
            .map(|(r, o)| self.ledger.pos(r, o))
            .sum()
    }

    /// Takes the whole frames buffered for replica `r` on output `o` into the ledger.
    fn decode(&mut self, r: usize, o: usize, until: Until) {
        loop {
            let alive = self.core.alive();
            let go_on = match until {
                Until::Window => !self.downstream_full() && self.ledger.may_read(r, o, alive),
                Until::Received(n) => self.ledger.received(r, o) < n,
            };
            let Some(rep) = self.core.slots[r].as_mut().filter(|_| go_on) else {
                return;
            };
            let frame = match rep.outputs[o].decoder.next_frame() {
                Ok(Some(f)) => f,
                Ok(None) => return,
                Err(e) => {
                    let detail = format!("output `{}`: {e}", self.core.plan.outputs[o].name);
                    return self.fault(r, Cause::BadFrame, detail);
                }
            };
            let newly_proven = !std::mem::replace(&mut rep.proven, true);
            // The program speaks the protocol (the restart budget's message says otherwise).
            self.core.exec_answered = true;
            let pid = rep.pid;
            // As `Core::journal_proven` (the frame borrows the slot still).
            if let (true, Some(journal)) = (newly_proven, self.core.journal.as_ref()) {
                if self.core.journaled_pids[r] == pid {
                    journal.mark_proven(r, pid);
                }
            }
            // Every frame is scored, also when all agree and also late copies: each replica's
            // stream must be complete for the next delta to be meaningful.
            let after_alarm = self.core.monitors.alarmed(r, o);
            let verdict = self.core.monitors.observe(r, o, frame);
            let arrival = self.ledger.accept(r, o, frame, Instant::now());
            if verdict.is_some_and(|v| v.alarm) {
                self.ledger.flag_last(r, o);
                // A replica that runs ahead has its frames scored before the vote on a
                // corrupted one removes it, and the frame after a corrupted one alarms on the
                // way back (the detector's reference is the corrupted frame): `after_alarm`.
                let frame = self.ledger.pos(r, o).saturating_sub(1);
                self.core
                    .anomaly_event(r, pid, o, At::Frame(frame), after_alarm);
            }
            if rep_skipped(&mut self.core, r, o) {
                // Its history (after a voter restart) began beyond the last frame decided: the
                // frame just taken is not the one the ledger numbered it.
                let detail = format!(
                    "output `{}` resumed beyond frame {} after the voter restart: it no longer held the frames in between",
                    self.core.plan.outputs[o].name,
                    self.ledger.next(o)
                );
                return self.fault(r, Cause::BadFrame, detail);
            }
            match arrival {
                Arrival::Fine => {}
                Arrival::MatchesForwarded => self.core.caught_up(ReplicaSet::EMPTY.with(r)),
                Arrival::DiffersFromForwarded(index) => {
                    let one = ReplicaSet::EMPTY.with(r);
                    let spared =
                        self.core
                            .spare_diverged(one, Cause::Minority, o, At::Frame(index));
                    if spared.is_empty() {
                        let detail = format!(
                            "`{}` differs from the majority in frame {index}",
                            self.core.plan.outputs[o].name
                        );
                        return self.fault(r, Cause::Minority, detail);
                    }
                }
            }
            self.decide(o);
        }
    }

    /// Forwards (or withholds) every frame of output `o` that can be decided now, and faults
    /// the replicas each decision blames.
    fn decide(&mut self, o: usize) {
        while let Some(Decided {
            index,
            decision,
            frame,
            agreed,
        }) = self.ledger.decide(
            o,
            self.core.alive(),
            self.core.fresh(),
            self.core.catching_up(),
        ) {
            self.core.caught_up(agreed);
            if let Some(blame) = self
                .core
                .apply(o, At::Frame(index), &decision, frame.as_deref())
            {
                for r in blame.suspects.iter() {
                    self.fault(r, blame.cause, blame.detail.clone());
                }
            }
        }
        self.ledger.trim(self.core.alive());
    }

    fn decide_all(&mut self) {
        for o in 0..self.core.outputs.len() {
            self.decide(o);
        }
    }

    /// Back-pressure from downstream: while an output has frames queued that its reader did
    /// not take, no replica output is read (their pipes fill, and they block), so the frames
    /// decided and not yet written stay few — the voter's memory is bounded, and the replicas'
    /// output histories (a successor's only source for them) reach back over them. The
    /// replicas' clocks stop meanwhile: a frame they could not deliver is not late.
    fn downstream_backlog(&mut self) {
        let backlog = self.downstream_full();
        match (backlog, self.held_by_downstream) {
            (true, None) => self.held_by_downstream = Some(Instant::now()),
            (false, Some(since)) => {
                self.held_by_downstream = None;
                self.ledger.postpone(since.elapsed());
                self.liveness.restart(Instant::now());
            }
            _ => {}
        }
    }

    /// Some output has frames queued that its reader has not taken.
    fn downstream_full(&self) -> bool {
        self.core.outputs.iter().any(|o| o.writer.has_pending())
    }

    // ----- faults --------------------------------------------------------------------------

    /// The bookkeeping of a fault of replica `r` (already recorded and killed).
    fn forget(&mut self, r: usize, pid: libc::pid_t) {
        self.boost.forget(pid);
        if self.boosted.is_some_and(|(boosted, _)| boosted == pid) {
            self.boosted = None;
        }
        self.ledger.forget(r);
        self.liveness.forget(r);
        // Fewer trusted replicas may decide a pending frame.
        self.decide_all();
    }

    /// A closed output is a crash if the process is gone within [`EXIT_AFTER_EOF`], else a
    /// protocol fault (see reactive mode). After the end began, closing is finishing.
    /// Blames the replicas on the wrong side of the oldest overdue frame (see
    /// [`ledger::Overdue::blames_laggards`]).
    fn check_deadlines(&mut self) {
        if self
            .ledger
            .overdue(self.core.alive(), self.timeout, Instant::now())
            .is_none()
        {
            return;
        }
        // One last look first: a frame may have arrived while the voter itself was busy, and
        // the voter's lateness is not the replica's fault.
        for r in 0..self.core.slots.len() {
            let Some(rep) = self.core.slots[r].as_mut() else {
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
            .overdue(self.core.alive(), self.timeout, Instant::now())
        else {
            return;
        };
        let name = self.core.plan.outputs[od.output].name.clone();
        if od.blames_laggards() {
            return self.blame_laggards(od.laggards, &od, &name, Cause::Behind);
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
            .filter(|&r| !self.core.slots[r].as_ref().is_some_and(Replica::is_asleep))
            .fold(ReplicaSet::EMPTY, ReplicaSet::with);
        if !stuck.is_empty() {
            return self.blame_laggards(stuck, &od, &name, Cause::BehindNotWaiting);
        }
        for r in od.producers.iter() {
            let detail = format!(
                "produced frame {} of `{name}`, which replicas {:?} did not produce within {} µs",
                od.index, od.laggards, self.core.plan.timeout_us
            );
            self.fault(r, Cause::ExtraFrame, detail);
        }
    }

    /// Blames `laggards` for overdue frame `od`: `protocol` if a laggard left a partial frame
    /// in its pipe, else `hang` with the cause `why` (how it was picked).
    fn blame_laggards(
        &mut self,
        laggards: ReplicaSet,
        od: &ledger::Overdue,
        name: &str,
        why: Cause,
    ) {
        for r in laggards.iter() {
            let (cause, partial) = self.core.late_cause(r, why);
            let detail = match partial {
                Some(p) => format!(
                    "partial frame on `{}` when frame {} of `{name}` was overdue",
                    self.core.plan.outputs[p].name, od.index
                ),
                None => {
                    let how = match why {
                        Cause::Behind => "furthest behind",
                        _ => "behind and not waiting for input",
                    };
                    format!(
                        "{how}: frame {} of `{name}` not produced within {} µs of replicas {:?}",
                        od.index, self.core.plan.timeout_us, od.producers
                    )
                }
            };
            self.fault(r, cause, detail);
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
        for r in 0..self.core.slots.len() {
            let sample = self.core.slots[r]
                .as_ref()
                .and_then(|rep| Sample::take(rep.pid, self.ledger.progress(r)));
            if let Some(ms) = self.liveness.update(r, sample) {
                let detail = format!(
                    "on a CPU for {ms} ms of the last {} µs without producing a frame or waiting for input",
                    self.core.plan.timeout_us
                );
                self.fault(r, Cause::Spinning, detail);
            }
        }
    }

    /// The furthest behind runs first (best effort; see [`boost`]).
    fn boost_laggard(&mut self) {
        let laggard = self
            .ledger
            .laggard(self.core.alive())
            .and_then(|r| self.core.slots[r].as_ref().map(|rep| (rep.pid, r)));
        if !self.core.rt.can_raise() {
            // No SCHED_RR: the best-effort nice boost of `boost`.
            return self.boost.set(laggard.map(|(pid, _)| pid));
        }
        // SCHED_RR: the laggard takes the turn priority, one step below the voter and above
        // every sibling at rest (the scheme of `crate::sched`); the previous one goes back.
        if self.boosted == laggard {
            return;
        }
        if let Some((pid, slot)) = self.boosted.take() {
            self.core.rt.rest(pid, slot);
        }
        if let Some((pid, _)) = laggard {
            self.core.rt.raise(pid);
        }
        self.boosted = laggard;
    }

    // ----- recovery ------------------------------------------------------------------------

    /// Forks `donor` into `slot`, and gives the child the donor's place in the ledger: the
    /// donor's frames from before the fork are read out of its pipe (they are all there: the
    /// fork waits until a frame being written is whole) and the undecided ones are copied to
    /// the child, whose state is already past them.
    fn fork_donor(&mut self, slot: usize, d: usize) -> Result<libc::pid_t, String> {
        let donor_pid = self.core.slots[d].as_ref().map(|r| r.pid);
        // The donor runs above its siblings while it forks (a boosted laggard on its CPU would
        // otherwise starve it into the accept timeout), then goes back to rest.
        let forked = self.core.fork(slot, d, DonorState::Streaming);
        if self.boosted.is_some_and(|(pid, _)| Some(pid) == donor_pid) {
            // Put back to rest: the next `boost_laggard` raises it again if it still lags.
            self.boosted = None;
        }
        let forked = forked.map_err(|e| e.to_string())?;
        for (o, &sent) in forked.frames_sent.iter().enumerate() {
            self.read_donor_until(d, o, sent);
            let short = self.core.slots[d]
                .as_ref()
                .map(|_| self.ledger.received(d, o) < sent);
            let problem = match short {
                None => Some("the donor failed while its frames were read".to_owned()),
                Some(true) => Some(format!(
                    "the donor's output `{}` holds {} frames, its child reported {sent}",
                    self.core.plan.outputs[o].name,
                    self.ledger.received(d, o)
                )),
                Some(false) => None,
            };
            if let Some(problem) = problem {
                forked.replica.kill();
                return Err(problem);
            }
        }
        // The child's frames count on from its donor's: so does its decoder (a `RESUME` the
        // child may start with, if its donor had not sent since a rebind, is no gap).
        let mut forked = forked;
        for (out, &sent) in forked.replica.outputs.iter_mut().zip(&forked.frames_sent) {
            out.decoder.set_position(sent, sent);
        }
        self.ledger.join_from(slot, d, &forked.frames_sent);
        let pid = forked.replica.pid;
        self.core.slots[slot] = Some(forked.replica);
        self.exited[slot] = false;
        Ok(pid)
    }

    /// Reads the donor's output `o` until `sent` frames of its process were received, or its
    /// pipe is empty.
    fn read_donor_until(&mut self, d: usize, o: usize, sent: u64) {
        loop {
            self.decode(d, o, Until::Received(sent));
            let Some(rep) = self.core.slots[d].as_mut() else {
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
        self.core.stop.is_none()
            && self.delivered_all
            && self.core.faults.is_empty()
            && self.core.inputs.iter().all(|i| i.reader.is_closed())
            && !self
                .core
                .slots
                .iter()
                .flatten()
                .any(|rep| rep.inputs.iter().any(|i| i.writer.has_pending()))
    }

    /// Closes the replicas' inputs: they see the end of their input and may write last frames
    /// (a batch flushed at the end), which are voted like any other.
    fn begin_end(&mut self) {
        tracing::debug!("inputs closed; letting the replicas finish their output");
        self.core.end_replica_inputs();
        let now = Instant::now();
        let taken = self.frames_taken();
        self.ending = Some(Ending {
            began: now,
            limit: now + core::SHUTDOWN_GRACE + self.timeout,
            at_start: taken,
            taken,
        });
    }

    /// Frames taken from the trusted replicas so far, on all outputs.
    fn frames_taken(&self) -> u64 {
        let outputs = self.core.outputs.len();
        self.core
            .alive()
            .iter()
            .map(|r| {
                (0..outputs)
                    .map(|o| self.ledger.received(r, o))
                    .sum::<u64>()
            })
            .sum()
    }

    /// Whether the end is over: every replica finished, or none made progress for the grace
    /// (or the end has lasted [`ENDING_AT_MOST`]). A replica still working through a backlog
    /// of input at its pace is not cut off: each frame taken moves the limit on.
    fn ending_over(&mut self) -> bool {
        if self.all_finished() {
            return true;
        }
        let taken = self.frames_taken();
        let now = Instant::now();
        let Some(end) = self.ending.as_mut() else {
            return false;
        };
        if taken > end.taken {
            end.taken = taken;
            end.limit = (now + core::SHUTDOWN_GRACE + self.timeout).min(end.began + ENDING_AT_MOST);
        }
        now >= end.limit
    }

    /// Every trusted replica has closed its outputs, all their frames are taken, and no
    /// frame is owed or undecided.
    fn all_finished(&self) -> bool {
        let alive = self.core.alive();
        self.core.slots.iter().flatten().all(finished) && !self.ledger.out_of_step(alive)
    }

    /// Whether a majority of the trusted replicas finished (closed every output, all their
    /// frames taken) and every frame they sent is decided. What the others have not sent
    /// could then only be copies of frames already decided: nothing is lost if they are
    /// stopped. (A replica that hangs after its last frame, as a fault injected just then:
    /// the maze robot's planner in a CI rehearsal of stop 61 made `s3res-bootstrap
    /// system.json` fail with "what they had not sent is lost", every frame out.)
    fn majority_finished(&self) -> bool {
        let alive = self.core.alive();
        let done: Vec<usize> = alive
            .iter()
            .filter(|&r| self.core.slots[r].as_ref().is_some_and(finished))
            .collect();
        done.len() * 2 > alive.len()
            && (0..self.core.outputs.len()).all(|o| {
                done.iter()
                    .all(|&r| self.ledger.pos(r, o) <= self.ledger.next(o))
            })
    }

    /// Writes out what is queued for downstream and lets the replicas exit. Replicas that had
    /// not finished their output are stopped: what they had not sent is lost, and the
    /// component ends as failed, in a `lost` event and its last line — unless a majority
    /// finished with every frame decided (see [`majority_finished`](Self::majority_finished)).
    fn finish(&mut self) -> Result<(), VoterError> {
        // No recovery comes now: a fault's event held for one goes out before the waits below.
        self.core.release_faults();
        self.say_if_silent();
        let mut unfinished = None;
        let all_finished = self.all_finished();
        if !all_finished && self.majority_finished() {
            tracing::warn!(
                "a replica had not finished its output when its input ended; a majority had, \
                 with every frame decided: it is stopped, nothing is lost"
            );
        } else if !all_finished {
            let alive = self.core.alive();
            let state: Vec<String> = (0..self.core.outputs.len())
                .map(|o| {
                    let per_slot: Vec<String> = alive
                        .iter()
                        .map(|r| {
                            let out = &self.core.slots[r].as_ref().expect("alive").outputs[o];
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
                        self.core.plan.outputs[o].name,
                        self.ledger.next(o),
                        per_slot.join(", ")
                    )
                })
                .collect();
            let (began, at_start, taken) = self
                .ending
                .as_ref()
                .map_or((Instant::now(), 0, 0), |e| (e.began, e.at_start, e.taken));
            let why = format!(
                "the replicas had not finished their output {:.1} s after their input ended \
                 ({} frames taken since, none in the last {:.1} s; {}); stopped, what they had \
                 not sent is lost",
                began.elapsed().as_secs_f64(),
                taken - at_start,
                (core::SHUTDOWN_GRACE + self.timeout).as_secs_f64(),
                state.join("; ")
            );
            tracing::warn!("{why}");
            let mut ev = self.core.event(crate::event::EventKind::Lost);
            ev.detail = Some(why.clone());
            self.core.emit(ev);
            unfinished = Some(why);
        }
        self.core.drain_and_let_finish();
        match unfinished {
            Some(why) => Err(VoterError::Unfinished(why)),
            None => self.core.output_failure(),
        }
    }

    /// Warns when the component took input and sent no frame on any output, the whole run: in
    /// stream mode no answer is owed for an input, so nothing else says it (a program that
    /// writes to stdout, or forgets to flush its port, ran to a clean end with nothing
    /// downstream and not a word).
    fn say_if_silent(&self) {
        let taken: u64 = self.core.delivered.iter().sum();
        if taken == 0
            || self.core.outputs.is_empty()
            || self.core.outputs.iter().any(|o| o.sent > 0)
        {
            return;
        }
        let outputs: Vec<String> = self
            .core
            .outputs
            .iter()
            .map(|o| format!("`{}`", o.name))
            .collect();
        tracing::warn!(
            "its replicas took {taken} input frame(s) and sent no frame on any output ({}): \
             nothing went downstream; unless that is meant (a component that speaks only on \
             events), it must send its results as frames on its output port(s) (replica-rt's \
             OutPort::send, s3res_send in C)",
            outputs.join(", ")
        );
    }
}

/// Whether replica `rep` has closed every output and all its frames are taken.
fn finished(rep: &Replica) -> bool {
    rep.outputs
        .iter()
        .all(|out| out.is_closed() && out.decoder.pending() == 0)
}

impl Mode for StreamVoter {
    fn core(&mut self) -> &mut Core {
        &mut self.core
    }

    fn run_loop(&mut self) -> Result<(), VoterError> {
        loop {
            let away = Instant::now();
            // At the end a replacement would only be closed again; the fault is recorded.
            let replace = self.core.stop.is_none() && self.ending.is_none();
            let recovered = core::recover_faulty(self, replace)?;
            self.keep_journal();
            if recovered {
                // Recovery blocks the loop (waiting for a death, the fork, the child's page
                // walk); the laggards' clocks stop meanwhile.
                self.ledger.postpone(away.elapsed());
                self.liveness.restart(Instant::now());
            }
            if self.core.stop == Some(Stop::Requested) {
                return Ok(());
            }
            self.deliver_input();
            if self.ending.is_none() && self.ready_to_end() {
                self.begin_end();
            }
            if self.ending.is_some() && self.ending_over() {
                return self.finish();
            }
            self.boost_laggard();
            core::wait_and_dispatch(self)?;
            if self.core.stop == Some(Stop::Requested) {
                return Ok(());
            }
            if self.ending.is_none() {
                core::fault_closed_outputs(self);
            }
            self.downstream_backlog();
            if self.held_by_downstream.is_none() {
                self.check_deadlines();
                self.decode_all();
                self.check_liveness();
            }
        }
    }

    fn fault(&mut self, r: usize, cause: Cause, detail: String) {
        if let Some(pid) = self.core.record_fault(r, cause, detail, None) {
            self.forget(r, pid);
        }
    }

    fn build_poll_set(&mut self) {
        self.poll_set();
    }

    fn next_wakeup(&mut self) -> Option<Instant> {
        self.wakeup()
    }

    fn on_input_readable(&mut self, i: usize) {
        self.core.inputs[i].read();
        self.delivered_all = false;
        self.deliver_input();
    }

    fn on_replica_output(&mut self, r: usize, o: usize) {
        self.on_output(r, o);
    }

    fn on_replica_exit(&mut self, r: usize) {
        if self.ending.is_some() {
            // Its input is closed: finishing is what it should do. Its last frames are still
            // in its pipes and are read to the end.
            self.exited[r] = true;
            return;
        }
        if self.core.slots[r].is_some() {
            self.fault(r, Cause::Died, core::DIED.into());
        }
    }

    /// After the end began, closing is finishing.
    fn on_output_closed(&mut self, r: usize) {
        if self.ending.is_none() {
            core::output_closed(self, r);
        }
    }

    fn progress(&self) -> [u64; MAX_REPLICAS] {
        let mut progress = [0; MAX_REPLICAS];
        for (r, p) in progress.iter_mut().enumerate().take(self.core.slots.len()) {
            *p = self.ledger.progress(r);
        }
        progress
    }

    /// After the end began, closing is finishing.
    fn fork_into(&mut self, slot: usize, d: usize) -> Result<libc::pid_t, String> {
        self.fork_donor(slot, d)
    }

    fn forked(&mut self, _slot: usize) {
        // The child brought the donor's undecided frames: they may decide now.
        self.decide_all();
    }

    fn started_fresh(&mut self, slot: usize) {
        self.ledger.start_fresh(slot);
        self.exited[slot] = false;
    }
}
