//! The voter's core: what it does whatever its mode. It owns the component's external ports,
//! the replicas (one slot each), the faults waiting for their replacement, the recovery
//! socket, the event writer, the real-time settings and the anomaly monitors.
//!
//! A mode ([`crate::reactive`], [`crate::stream`]) wraps a [`Core`] and implements [`Mode`]:
//! how it reads replicas' outputs, what it decides about them (through
//! [`crate::decision`]), and what a fault changes in its own bookkeeping. The loop's shared
//! steps are generic over the mode: [`wait_and_dispatch`] (one `ppoll`, then each ready fd),
//! [`fault_closed_outputs`], [`recover_faulty`] (fork from the best donor, else exec).
//! [`Core::apply`] turns a decision into the frame sent and the events written, the same way
//! for both modes.

use std::os::fd::{AsFd, BorrowedFd, OwnedFd};
use std::os::unix::net::UnixListener;
use std::time::Duration;

use nix::sys::signalfd::SignalFd;
use replica_rt::contract::MAX_PORTS;
use replica_rt::frame::{self, FrameError};
use replica_rt::stamps::AnswerStamps;
use replica_rt::sys;
use thiserror::Error;

use crate::adopt;
use crate::channel::Fill;
use crate::clock::{self, ClockError, Instant};
use crate::decision::Decision;
use crate::event::{Cause, Event, EventKind, RecoveryMethod};
use crate::held::HeldFaults;
use crate::journal::{self, Committed, InputState, Journal, SlotEntry};
use crate::monitor::{Captures, Monitors};
use crate::park::ParkingLot;
use crate::plan::{Framing, Mode as PlanMode, VoterPlan};
use crate::ports::{
    beat, heartbeat_ending, kill_all_children, reap_children, stop_requested, write_event,
    Endpoints, ExternalInput, ExternalOutput, PollSet, Token, WakeTimer, HEARTBEAT_PERIOD,
};
use crate::recovery::{self, DonorState, Forked, RecoveryError};
use crate::replica::Replica;
use crate::rt::RealTime;
use crate::sched::Schedule;
use crate::vote::{ReplicaSet, MAX_REPLICAS};

/// How long a replica whose output pipe closed may take to show up as dead before we call it a
/// protocol fault instead of a crash. The kernel closes a dying process's fds before it signals
/// the exit, so the two are seen a moment apart.
pub(crate) const EXIT_AFTER_EOF: Duration = Duration::from_millis(50);
/// How long a replica whose output closed may go on running before it is judged (see
/// `Core::closed_output_fault`).
pub(crate) const EXIT_AFTER_EOF_BUSY: Duration = Duration::from_secs(1);
/// How long a replica seen dying may take to finish, so that its exit status is read rather
/// than replaced by our SIGKILL's.
const EXIT_STATUS_WAIT: Duration = Duration::from_millis(100);
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
    // The error is in the message, and not a `source` too: a report of the chain (anyhow's
    // `{:#}`, the voter's last line) would say it twice.
    #[error("{what}: {error}")]
    Io { what: String, error: std::io::Error },
    #[error("component failed beyond recovery: {0}")]
    Unrecoverable(String),
    /// An input was closed because of what upstream sent on it (see `Core::upstream_broke`).
    #[error("an input ended early: {0}")]
    Upstream(String),
    /// Stream mode: the replicas had not finished their output when the end's time was up.
    #[error("output cut short: {0}")]
    Unfinished(String),
    /// An output could not be written (not that its reader went away): what went there is lost.
    #[error("{0}")]
    OutputLost(String),
    #[error(transparent)]
    Clock(#[from] ClockError),
}

pub(crate) fn io_err(what: impl Into<String>) -> impl FnOnce(std::io::Error) -> VoterError {
    let what = what.into();
    move |error| VoterError::Io { what, error }
}

/// A slot whose replacement could not be made (fork and exec both failed: a process limit, a
/// full memory): the component runs degraded, and the voter tries again, with backoff.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Vacancy {
    pub(crate) slot: usize,
    old_pid: i32,
    detected_ns: u64,
    next_try: Instant,
    backoff: Duration,
}

/// First and longest wait between two tries to fill a vacant slot.
const VACANCY_BACKOFF: (Duration, Duration) = (Duration::from_millis(10), Duration::from_secs(1));

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

/// Where a fork's donor stands during `Core::fork`: raised once signalled, back at rest once
/// its child has joined (or after an attempt that failed in between).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum DonorLevel {
    AtRest,
    Raised,
    RestedAgain,
}

/// Where a decision was made, for events: a reactive round, or a frame of a stream output.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum At {
    Round(u64),
    Frame(u64),
}

impl std::fmt::Display for At {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            At::Round(n) => write!(f, "round {n}"),
            At::Frame(k) => write!(f, "frame {k}"),
        }
    }
}

impl At {
    /// Fills the event's `round` or `frame`.
    fn mark(self, ev: &mut Event) {
        match self {
            At::Round(n) => ev.round = Some(n),
            At::Frame(k) => ev.frame = Some(k),
        }
    }
}

/// The replicas a decision found faulty, with the cause and the text for their events.
pub(crate) struct Blame {
    pub(crate) suspects: ReplicaSet,
    pub(crate) cause: Cause,
    pub(crate) detail: String,
}

/// What a mode adds to the core. The core calls these from the steps it shares.
pub(crate) trait Mode: Sized {
    fn core(&mut self) -> &mut Core;
    /// The mode's event loop: until the inputs close and the replicas finish, or a stop.
    fn run_loop(&mut self) -> Result<(), VoterError>;
    /// Replica `r` is faulty: [`Core::record_fault`], then the mode's own bookkeeping (a
    /// smaller quorum may decide a pending vote).
    fn fault(&mut self, r: usize, cause: Cause, detail: String);
    /// Fills the core's poll set for the next wait.
    fn build_poll_set(&mut self);
    /// When the loop must wake up at the latest.
    fn next_wakeup(&mut self) -> Option<Instant>;
    /// Whether the wait about to begin may spin before it sleeps (`spin.rs`): it waits for
    /// answers from replicas that all run on other CPUs than the voter's.
    fn may_spin(&self) -> bool {
        false
    }
    fn on_input_readable(&mut self, i: usize);
    fn on_replica_output(&mut self, r: usize, o: usize);
    fn on_replica_exit(&mut self, r: usize);
    /// How far each replica has got (frames taken from it): the donor choice prefers the
    /// furthest.
    fn progress(&self) -> [u64; MAX_REPLICAS];
    /// Replica `r` closed an output (see [`output_closed`]).
    fn on_output_closed(&mut self, r: usize) {
        output_closed(self, r);
    }
    /// Forks donor `d` into `slot`: on success the child holds the slot and the donor's place
    /// in the mode's bookkeeping. Returns the child's pid.
    fn fork_into(&mut self, slot: usize, d: usize) -> Result<libc::pid_t, String>;
    /// After the recovery event of a fork into `slot`.
    fn forked(&mut self, _slot: usize) {}
    /// A fresh replica started by exec holds `slot` now.
    fn started_fresh(&mut self, slot: usize);
}

/// The mode-independent state of a voter.
pub(crate) struct Core {
    pub(crate) plan: VoterPlan,
    pub(crate) inputs: Vec<ExternalInput>,
    pub(crate) outputs: Vec<ExternalOutput>,
    /// One per replica slot; `None` while the slot's replica is faulty and not yet replaced.
    pub(crate) slots: Vec<Option<Replica>>,
    pub(crate) faults: Vec<Fault>,
    /// The faulty replica being replaced, until it is retired ([`Fault::retire`]): while its
    /// donor forks, if the slot is filled by fork (see [`Core::fork`]), else before anything
    /// else is tried.
    pub(crate) retiring: Option<Fault>,
    /// Slots whose replacement failed, tried again with backoff.
    pub(crate) vacant: Vec<Vacancy>,
    /// When replicas were started by exec after a fault, within the restart window.
    exec_restarts: std::collections::VecDeque<Instant>,
    /// Replicas started by exec after a fault, since the start, in any window.
    exec_restarts_total: u64,
    /// Slots whose replica started afresh matched once and then dissented all the same: its
    /// matches were chance (an output coarser than the lost state, or one that does not depend
    /// on it), so their next replicas started afresh stay catching up whatever they match,
    /// until a fork gives the slot the state back (see `Core::spare_diverged`).
    relapsed: ReplicaSet,
    /// Some replica started by exec has answered (so the program speaks the protocol).
    pub(crate) exec_answered: bool,
    /// Some replica said, through the start handshake, that its runtime started.
    pub(crate) runtime_started: bool,
    /// The last fault, as its event reads: the budget's message quotes it.
    last_fault: String,
    /// Why an input was closed because of what upstream sent (a frame that cannot be
    /// decoded, or cannot be given to the program): the voter ends as failed, not clean.
    upstream_broke: Option<String>,
    /// Names the current fork attempt; a child of an older attempt is refused. Starts at a
    /// value of this voter's own ([`first_nonce`]), so that a late child of a predecessor's
    /// attempt does not carry a nonce of ours.
    restart_nonce: u32,
    listener: UnixListener,
    /// The replicas' spare lines taken so far (`recovery::SpareLines`).
    spares: recovery::SpareLines,
    signals: SignalFd,
    events: Option<OwnedFd>,
    /// Fault events written once the donor of their recovery has been signalled (`held.rs`).
    held: HeldFaults,
    pub(crate) stop: Option<Stop>,
    pub(crate) poll: PollSet,
    /// Wakes the loop at the mode's next deadline (see [`WakeTimer`]).
    pub(crate) timer: WakeTimer,
    /// When each replica last answered, if they say so (sequential rounds: see
    /// `replica_rt::stamps` and `ReactiveVoter::turn_ended_at`).
    pub(crate) stamps: Option<AnswerStamps>,
    /// Priorities, pinning and the raising of turns.
    pub(crate) rt: RealTime,
    /// Anomaly detectors on the outputs.
    pub(crate) monitors: Monitors,
    /// Voted frames written to files (training data).
    pub(crate) captures: Captures,
    /// What a successor needs, if bootstrap keeps a journal for this voter (`journal.rs`).
    pub(crate) journal: Option<Journal>,
    /// Frames delivered to the replicas per input since the component started: the numbers
    /// their decoders count in (a replayed frame is sent behind `RESUME` with its number).
    pub(crate) delivered: Vec<u64>,
    /// The pid recorded in the journal's replica table, per slot.
    pub(crate) journaled_pids: Vec<libc::pid_t>,
    /// Rounds its predecessors started (an adopting voter numbers on from there).
    pub(crate) adopted_rounds: u64,
    /// The state a commit records, kept for its capacity.
    committing: Committed,
    /// Per input: the bytes (header and payload) of the last frame delivered to the replicas.
    last_delivered_len: Vec<usize>,
    /// Stream mode: per slot, the number on each output of its process's frame 0 (kept up to
    /// date by the stream voter, recorded in the journal with the slot).
    pub(crate) slot_offsets: Vec<[u64; MAX_PORTS]>,
    /// What an adopting voter found: the outputs' committed counts and, per slot, the
    /// adopted replica's offsets (stream mode lines its ledger up with them).
    pub(crate) adopted_streams: Option<AdoptedStreams>,
    /// An unmodified program's voter under a journal: where its replicas' pipes are parked so
    /// that they outlive it (`park.rs`, `lines.rs`).
    pub(crate) park: Option<ParkingLot>,
    /// `cpu_idle: poll`: the open PM QoS request that keeps idle CPUs polling (`rt.rs`).
    _cpu_latency: Option<std::fs::File>,
    /// What the waits may still spin (`spin.rs`).
    spin: crate::spin::Spin,
}

/// What a stream voter needs from its predecessor's journal (see [`Core::slot_offsets`]).
#[derive(Debug, Clone)]
pub(crate) struct AdoptedStreams {
    /// Frames committed as forwarded, per output: the next frame to decide.
    pub(crate) forwarded: Vec<u64>,
    /// Per slot whose replica was adopted: its offsets.
    pub(crate) offsets: Vec<Option<[u64; MAX_PORTS]>>,
}

impl Core {
    /// Frees the answer stamps of replicas this voter no longer has (called when a slot is
    /// filled again: the replica it held is gone by then).
    pub(crate) fn forget_stamps_of_the_gone(&self) {
        if let Some(stamps) = &self.stamps {
            let slots = &self.slots;
            stamps.retain(|pid| slots.iter().flatten().any(|rep| rep.pid as u32 == pid));
        }
    }

    /// Checks the plan, calibrates the clock, loads the detectors, takes over the fds named in
    /// `plan`, binds the socket, and starts the replicas.
    pub(crate) fn start(plan: VoterPlan) -> Result<Core, VoterError> {
        validate(&plan)?;
        crate::crashpoint::arm(plan.adopt.is_some());
        let Endpoints {
            signals,
            mut inputs,
            mut outputs,
            events,
            listener,
            journal,
            park,
            stamps,
        } = Endpoints::open(&plan)?;
        let mut park = match park {
            Some((tx, rx)) => Some(ParkingLot::new(tx, rx).map_err(io_err("the parking socket"))?),
            None => None,
        };
        // Calibrated before the first round, so that it never eats into a deadline; a
        // successor takes its predecessor's calibration over.
        let inherited = journal
            .as_ref()
            .filter(|_| plan.adopt.is_some())
            .and_then(|fd| journal::recorded_clock(fd.as_fd()));
        let clock = clock::init_from(inherited)?;
        // Models are checked before any replica starts: a bad one is an error, not a surprise.
        let monitors = Monitors::load(&plan)?;
        let captures = Captures::open(&plan)?;
        // Only a voter with a CPU of its own spins (`reactive.rs`, `spins_for`), and its
        // headroom is that CPU's.
        let own_cpu = plan
            .voter_cpu
            .filter(|_| crate::sched::voter_apart(&plan.cpus, plan.voter_cpu));
        let spin = crate::spin::Spin::new(plan.spin_us, own_cpu);
        // Before the first replica: replicas start from the voter's settings.
        let mut rt = RealTime::new(&plan);
        rt.apply_to_voter();
        let cpu_latency = crate::rt::keep_cpus_polling(plan.cpu_idle);
        let stamps = answer_stamps(&plan, stamps);
        let mut spares = recovery::SpareLines::default();
        let (journal, slots, adoption) = match journal {
            Some(fd) if plan.adopt.is_some() => {
                let (journal, found) =
                    Journal::open(fd, &plan).map_err(|e| VoterError::Plan(e.to_string()))?;
                journaled_inputs(&mut inputs, &plan)?;
                whole_frame_outputs(&mut outputs, &plan)?;
                let on_adopt = |pid, slot| rt.apply_to_replica(pid, slot);
                let adopted = match park.as_mut() {
                    Some(park) => adopt::parked_replicas(&plan, park, &found, on_adopt)
                        .map_err(io_err("adopting an unmodified program's replicas"))?,
                    None => adopt::replicas(&plan, &listener, &found.slots, on_adopt),
                };
                spares = adopted.spares;
                (Some(journal), adopted.slots, Some((found, adopted.lost)))
            }
            journal_fd => {
                let journal = match journal_fd {
                    Some(fd) => {
                        let journal = Journal::create(fd, &plan)
                            .map_err(|e| VoterError::Plan(e.to_string()))?;
                        journal.record_clock(clock);
                        journaled_inputs(&mut inputs, &plan)?;
                        whole_frame_outputs(&mut outputs, &plan)?;
                        Some(journal)
                    }
                    None => None,
                };
                let stamp_fd = stamps.as_ref().map(AnswerStamps::fd);
                let slots = start_replicas(&plan, events.as_ref(), stamp_fd, |pid, slot| {
                    rt.apply_to_replica(pid, slot)
                })?;
                (journal, slots, None)
            }
        };
        let delivered = vec![0; plan.inputs.len()];
        let journaled_pids = vec![0; plan.replicas];
        let mut core = Core {
            plan,
            inputs,
            outputs,
            slots,
            faults: Vec::new(),
            retiring: None,
            vacant: Vec::new(),
            exec_restarts: std::collections::VecDeque::new(),
            exec_restarts_total: 0,
            relapsed: ReplicaSet::EMPTY,
            exec_answered: false,
            runtime_started: false,
            last_fault: String::new(),
            upstream_broke: None,
            restart_nonce: first_nonce(),
            listener,
            spares,
            signals,
            events,
            held: HeldFaults::default(),
            stop: None,
            poll: PollSet::default(),
            timer: WakeTimer::new()?,
            stamps,
            rt,
            monitors,
            captures,
            journal,
            delivered,
            journaled_pids,
            adopted_rounds: 0,
            committing: Committed::default(),
            slot_offsets: Vec::new(),
            adopted_streams: None,
            last_delivered_len: Vec::new(),
            park,
            _cpu_latency: cpu_latency,
            spin,
        };
        core.last_delivered_len = vec![0; core.plan.inputs.len()];
        core.slot_offsets = vec![[0; MAX_PORTS]; core.plan.replicas];
        if let Some((found, lost)) = adoption {
            core.resume(found, lost);
        }
        core.journal_slots();
        // Last: a successor has adopted the replicas by now, and locking (populating some MiB)
        // does not lengthen its takeover.
        crate::rt::lock_voter_memory(core.plan.lock_memory);
        Ok(core)
    }

    /// Takes over where the predecessor left: the inputs' decoders where they stood at its
    /// last commit, the bytes it took since queued for replay, every adopted replica told the
    /// number of the next frame it will be sent on each input, and every output the number of
    /// the next frame forwarded (`RESUME`: downstream drops what it already has). Slots whose
    /// replica did not come back are refilled by the usual recovery, forked from an adopted
    /// replica if one kept the state.
    fn resume(&mut self, found: journal::Found, lost: Vec<adopt::Lost>) {
        let committed = found.committed;
        let offsets: Vec<_> = (0..self.slots.len())
            .map(|s| {
                self.slots[s].as_ref()?;
                found.slots.get(s).copied().flatten().map(|e| e.offsets)
            })
            .collect();
        for (slot, off) in offsets.iter().enumerate() {
            if let Some(off) = off {
                self.slot_offsets[slot] = *off;
            }
        }
        let mut committed = committed;
        if self.plan.mode == PlanMode::Stream {
            // A stream voter records what it wrote downstream as it goes (`note_written`):
            // its outputs go on from there, whatever its last commit of input said.
            if let Some(journal) = self.journal.as_ref() {
                for (o, n) in committed.forwarded.iter_mut().enumerate() {
                    *n = (*n).max(journal.written(o));
                }
            }
        }
        self.adopted_streams = Some(AdoptedStreams {
            forwarded: committed.forwarded.clone(),
            offsets,
        });
        for (i, input) in self.inputs.iter_mut().enumerate() {
            let at = committed.inputs[i];
            input.reader.decoder.set_position(at.taken, at.next_index);
            input.reader.decoder.push(&found.logs[i]);
            if let Some(peek) = input.peek.as_mut() {
                peek.mark = input.reader.decoder.passed();
                peek.replay_left = found.logs[i].len();
            }
            if !found.logs[i].is_empty() {
                tracing::info!(input = %input.name, bytes = found.logs[i].len(), "replaying the input taken since the predecessor's last commit");
            }
            self.delivered[i] = at.delivered;
        }
        for (out, &sent) in self.outputs.iter_mut().zip(&committed.forwarded) {
            out.sent = sent;
            out.writer.queue_raw(&frame::resume_frame(sent));
            out.flush();
        }
        self.adopted_rounds = committed.rounds_started;
        if self.slots.iter().flatten().any(|r| r.proven) {
            // The program speaks the protocol: its replicas answered the predecessor.
            self.exec_answered = true;
            self.runtime_started = true;
        }
        for slot in 0..self.slots.len() {
            self.number_inputs_of(slot);
        }
        let mut lost = lost;
        let mut lines = None;
        if self.park.is_some() {
            let (gone, found) = self.resume_lines();
            lost.extend(gone);
            lines = Some(found);
            self.take_answers_left_behind();
        }
        let now = Instant::now();
        for gone in lost {
            let cause = if gone.died {
                Cause::Died
            } else {
                Cause::Deadline
            };
            if gone.pid > 0 {
                let mut ev = Event::caused(&self.plan.system, &self.plan.component, cause);
                ev.replica = Some(gone.slot);
                ev.pid = Some(gone.pid);
                ev.detail = Some(if let Some(why) = gone.why {
                    why.into()
                } else if gone.died {
                    "died while its voter was being replaced".into()
                } else {
                    format!(
                        "did not come back to the new voter within {} ms; killed",
                        self.plan.restart_timeout_ms
                    )
                });
                self.emit(ev);
            }
            self.vacant.push(Vacancy {
                slot: gone.slot,
                old_pid: gone.pid,
                detected_ns: s3res_protocol::clock::monotonic_ns(),
                next_try: now,
                backoff: VACANCY_BACKOFF.0,
            });
        }
        let adoption = self
            .plan
            .adopt
            .clone()
            .expect("resume runs for an adopting voter");
        let mut ev = self.event(EventKind::VoterRestart);
        ev.pid = Some(std::process::id() as i32);
        ev.recovery_us =
            Some(s3res_protocol::clock::monotonic_ns().saturating_sub(adoption.gone_ns) / 1000);
        let kept = self.slots.iter().flatten().count();
        let replayed: usize = found.logs.iter().map(Vec::len).sum();
        let lines = lines.map(|l| format!("; {l}")).unwrap_or_default();
        ev.detail = Some(format!(
            "voter {} ({}) replaced; {kept} of {} replicas adopted, {replayed} bytes of input replayed{lines}",
            adoption.previous_pid,
            adoption.why,
            self.slots.len()
        ));
        self.emit(ev);
    }

    // ----- the journal --------------------------------------------------------------------

    /// Brings the journal's replica table up to date with the slots (a `/proc` read for each
    /// slot whose process changed).
    pub(crate) fn journal_slots(&mut self) {
        // A slot leaves the table only once its fault's event is out (`held.rs`); a slot the
        // release took out is written again whatever its pid (a replacement may have got the
        // dead replica's pid back).
        self.release_faults();
        for slot in self.held.take_cleared().iter() {
            if let Some(pid) = self.journaled_pids.get_mut(slot) {
                *pid = 0;
            }
        }
        if self.journal.is_none() {
            return;
        }
        for slot in 0..self.slots.len() {
            let pid = self.slots[slot].as_ref().map_or(0, |r| r.pid);
            if pid == self.journaled_pids[slot] {
                continue;
            }
            let mut start_time = self.slots[slot]
                .as_ref()
                .and_then(|r| journal::start_time(r.pid));
            // An unmodified program's pipes are parked first: a successor adopts a replica it
            // finds both parked and named.
            if let Some(t) = start_time.filter(|_| self.parks_lines()) {
                if !self.park_new_replica(slot, t) {
                    start_time = None;
                }
            }
            let entry = self.slots[slot].as_ref().and_then(|r| {
                Some(SlotEntry {
                    pid: r.pid,
                    start_time: start_time?,
                    state_lost: r.state_lost,
                    proven: r.proven,
                    offsets: self.slot_offsets[slot],
                })
            });
            if let Some(journal) = self.journal.as_ref() {
                journal.set_slot(slot, entry);
            }
            self.journaled_pids[slot] = pid;
        }
    }

    /// Replica `pid` in `slot` has answered: a successor that adopts it finds it proven (a
    /// replica started by exec was journaled unproven and stayed so; an unmodified program's,
    /// which may donate only once proven, could not be forked from after a voter's death).
    pub(crate) fn journal_proven(&self, slot: usize, pid: libc::pid_t) {
        if let Some(journal) = self.journal.as_ref() {
            if self.journaled_pids[slot] == pid {
                journal.mark_proven(slot, pid);
            }
        }
    }

    /// Commits what was taken off the inputs, once its rounds are over and their output and
    /// input are out of the voter (nothing queued for downstream or for a replica): a
    /// successor then replays nothing of it. Called between rounds.
    pub(crate) fn commit(&mut self, rounds_started: u64) {
        let Some(journal) = self.journal.as_mut() else {
            return;
        };
        // A replay not finished yet lives only in the decoder once the log is emptied: the
        // next successor would find it neither in the journal nor in the channel.
        if self
            .inputs
            .iter()
            .any(|i| i.peek.as_ref().is_some_and(|p| p.replay_left > 0))
        {
            return;
        }
        // A stream voter seldom finds nothing queued anywhere while frames flow, so it commits
        // around what is queued: an output's frames count once written whole, and an input
        // frame not yet written whole to every replica (only the last one delivered can be:
        // the stream voter delivers the next only when none is queued) is carried into the
        // new log, the state recorded before it. A reactive voter commits between rounds,
        // with nothing queued.
        let stream = self.plan.mode == PlanMode::Stream;
        let state = &mut self.committing;
        state.forwarded.clear();
        for out in &self.outputs {
            let queued = if stream {
                out.writer.queued_frames()
            } else {
                (!out.writer.has_pending()).then_some(0)
            };
            let Some(queued) = queued else { return };
            state.forwarded.push(out.sent.saturating_sub(queued as u64));
        }
        let mut carry = [false; MAX_PORTS];
        for (i, carried) in carry.iter_mut().enumerate().take(self.inputs.len()) {
            let pending = self
                .slots
                .iter()
                .flatten()
                .filter_map(|r| r.inputs.get(i))
                .map(|input| input.writer.unwritten_len())
                .max()
                .unwrap_or(0);
            if pending == 0 {
                continue;
            }
            let last = self.last_delivered_len[i];
            if !stream || pending > last || journal.last_take_len(i) != Some(last) {
                return;
            }
            *carried = true;
        }
        let moved = (0..self.outputs.len()).any(|o| journal.forwarded_at(o) != state.forwarded[o]);
        if !journal.uncommitted() && !moved {
            return;
        }
        // Filled in place: a steady-state round allocates nothing.
        state.rounds_started = rounds_started;
        state.inputs.clear();
        state
            .inputs
            .extend(self.inputs.iter().zip(&self.delivered).zip(&carry).map(
                |((input, &delivered), &carried)| {
                    let (taken, next_index) = input.reader.decoder.position();
                    let back = u64::from(carried);
                    InputState {
                        taken: taken - back,
                        next_index: next_index - back,
                        delivered: delivered - back,
                    }
                },
            ));
        journal.commit_carrying(state, &carry[..self.inputs.len()]);
    }

    /// Stream mode: records, per output, the frames written whole downstream so far (a
    /// successor's outputs go on from there; see [`Core::resume`]). Cheap: a load, and a store
    /// when the count moved.
    pub(crate) fn note_written(&mut self) {
        let Some(journal) = self.journal.as_ref() else {
            return;
        };
        for (o, out) in self.outputs.iter().enumerate() {
            if let Some(queued) = out.writer.queued_frames() {
                let written = out.sent.saturating_sub(queued as u64);
                if journal.written(o) != written {
                    journal.set_written(o, written);
                }
            }
        }
    }

    /// Takes the bytes input `i`'s decoder has passed since the last take off its channel,
    /// into the journal.
    fn take_decoded(&mut self, i: usize) {
        let (Some(journal), input) = (self.journal.as_mut(), &mut self.inputs[i]) else {
            return;
        };
        let Some(peek) = input.peek.as_mut() else {
            return;
        };
        let passed = input.reader.decoder.passed();
        let delta = (passed - peek.mark) as usize;
        peek.mark = passed;
        let replayed = delta.min(peek.replay_left);
        peek.replay_left -= replayed;
        let n = delta - replayed;
        if n == 0 {
            return;
        }
        if let Err(e) = journal.take(i, input.reader.as_fd(), n) {
            tracing::error!(input = %input.name, error = %e, "cannot take input into the journal; treating the input as closed");
            input.reader.close();
        }
    }

    /// A replica started by exec counts its inputs from zero: tell it the number of the next
    /// frame, so that a replay after a voter restart lines up (journaled voters only).
    pub(crate) fn number_inputs_of(&mut self, slot: usize) {
        // An unmodified program knows no control frames; its lines are counted for it.
        if self.journal.is_none()
            || self.plan.preload.is_some()
            || self.plan.framing == Framing::Lines
        {
            return;
        }
        let Some(rep) = self.slots[slot].as_mut() else {
            return;
        };
        for (input, &next) in rep.inputs.iter_mut().zip(&self.delivered) {
            input.writer.queue_raw(&frame::resume_frame(next));
            let _ = input.writer.flush();
        }
    }

    /// The end of the replicas' input, on purpose: an END frame (a replica tells it from its
    /// voter's death, after which it would wait for a successor), then our ends closed.
    pub(crate) fn end_replica_inputs(&mut self) {
        // Nobody else may hold their pipes open now, or the program never sees its end.
        self.release_parked();
        let frames = self.plan.framing != Framing::Lines;
        for rep in self.slots.iter_mut().flatten() {
            for input in &mut rep.inputs {
                if frames {
                    input.writer.queue_raw(&frame::end_frame());
                }
                drain_writer(&mut input.writer, Instant::now() + END_FRAME_WAIT);
            }
            // Closing our write ends (and the read ends we kept) gives the replica EOF.
            rep.inputs.clear();
        }
    }

    /// The trusted replicas whose state is lost (see `decision.rs`).
    pub(crate) fn fresh(&self) -> ReplicaSet {
        (0..self.slots.len())
            .filter(|&r| self.slots[r].as_ref().is_some_and(|rep| rep.state_lost))
            .fold(ReplicaSet::EMPTY, ReplicaSet::with)
    }

    /// The trusted replicas whose state is lost and none of whose frames has matched yet
    /// (see [`Replica::catching_up`]).
    pub(crate) fn catching_up(&self) -> ReplicaSet {
        (0..self.slots.len())
            .filter(|&r| self.slots[r].as_ref().is_some_and(|rep| rep.catching_up))
            .fold(ReplicaSet::EMPTY, ReplicaSet::with)
    }

    /// `agreed` sent a frame that went out: any of them catching up has caught up (unless its
    /// slot relapsed before: see [`Core::spare_diverged`]).
    pub(crate) fn caught_up(&mut self, agreed: ReplicaSet) {
        for r in agreed.minus(self.relapsed).iter() {
            if let Some(rep) = self.slots[r].as_mut().filter(|rep| rep.catching_up) {
                rep.catching_up = false;
                tracing::info!(
                    replica = r,
                    pid = rep.pid,
                    "a replica started afresh matches the others again"
                );
            }
        }
    }

    /// The replicas whose fork would give a replica the state the vote goes by: they kept
    /// the component's state (or, once none did, their state matches), their restart handler
    /// is in place, and they run one thread. With the threaded ones passed over.
    fn fork_donors(&self) -> (ReplicaSet, ReplicaSet) {
        let any_kept = !self.alive().minus(self.fresh()).is_empty();
        let (mut donors, mut threaded) = (ReplicaSet::EMPTY, ReplicaSet::EMPTY);
        for (d, rep) in self.slots.iter().enumerate() {
            // A replica catching up has nothing to give; one whose state is lost only what
            // the replicas that kept theirs outvote.
            let gives_nothing = |rep: &Replica| rep.catching_up || (any_kept && rep.state_lost);
            // As `best_donor` ranks them: it may donate, and its look says whether it threads.
            let Some((_, look)) = rep
                .as_ref()
                .filter(|rep| !gives_nothing(rep))
                .and_then(Replica::donor_rank)
            else {
                continue;
            };
            if look.is_some_and(crate::replica::StatLook::threaded) {
                threaded = threaded.with(d);
            } else {
                donors = donors.with(d);
            }
        }
        (donors, threaded)
    }

    /// Of `blamed` (for `cause`, on output `o` at `at`), the replicas not to fault: their
    /// dissent comes of a lost state no fork can give back (see `decision::spare_diverged`).
    /// Each is said once, in a `diverged` event.
    ///
    /// A replica started afresh that had matched (so was no longer catching up) and dissents
    /// now marks its slot as relapsed: one matching frame said nothing of its state, and the
    /// next replica started afresh there is not taken for caught up by a match.
    pub(crate) fn spare_diverged(
        &mut self,
        blamed: ReplicaSet,
        cause: Cause,
        o: usize,
        at: At,
    ) -> ReplicaSet {
        if blamed.is_empty() || !matches!(cause, Cause::Minority | Cause::BitwiseMinority) {
            return ReplicaSet::EMPTY;
        }
        let fresh = self.fresh();
        let catching_up = self.catching_up();
        self.relapsed = blamed
            .and(fresh)
            .minus(catching_up)
            .iter()
            .fold(self.relapsed, ReplicaSet::with);
        if blamed.and(catching_up).is_empty() {
            return ReplicaSet::EMPTY;
        }
        let (donors, threaded) = self.fork_donors();
        let spared = crate::decision::spare_diverged(blamed, cause, catching_up, donors);
        for r in spared.iter() {
            let Some(rep) = self.slots[r].as_mut().filter(|rep| !rep.diverged) else {
                continue;
            };
            rep.diverged = true;
            let pid = rep.pid;
            let name = self.output_name(o).to_owned();
            let why = if threaded.minus(spared).is_empty() {
                "no other replica can donate by fork".to_owned()
            } else {
                format!(
                    "no fork can give it back (replicas {:?} run more than one thread)",
                    threaded.minus(spared)
                )
            };
            let detail = format!(
                "`{name}` differs from the others in {at}: its state was lost (started afresh) \
                 and {why}; kept, outvoted, and not restarted into the same loss"
            );
            tracing::warn!(replica = r, pid, "{detail}");
            let mut ev = self.event(EventKind::Diverged);
            at.mark(&mut ev);
            ev.replica = Some(r);
            ev.pid = Some(pid);
            ev.output = Some(name);
            ev.detail = Some(detail);
            self.emit(ev);
        }
        spared
    }

    /// The trusted replicas: every filled slot.
    pub(crate) fn alive(&self) -> ReplicaSet {
        (0..self.slots.len())
            .filter(|&r| self.slots[r].is_some())
            .fold(ReplicaSet::EMPTY, ReplicaSet::with)
    }

    pub(crate) fn output_name(&self, o: usize) -> &str {
        &self.plan.outputs[o].name
    }

    pub(crate) fn input_name(&self, i: usize) -> &str {
        &self.plan.inputs[i].name
    }

    /// Starts the wait set: the signalfd, the external inputs (if `take_input`) and the
    /// outputs with frames queued.
    pub(crate) fn reset_poll(&mut self, take_input: bool) {
        self.poll.reset(
            &self.signals,
            &self.timer,
            &self.inputs,
            take_input,
            &self.outputs,
        );
    }

    // ----- events ------------------------------------------------------------------------

    pub(crate) fn event(&self, kind: EventKind) -> Event {
        Event::new(&self.plan.system, &self.plan.component, kind)
    }

    /// Writes `ev`, after the fault events held so far (their order is kept).
    pub(crate) fn emit(&self, ev: Event) {
        self.release_faults();
        write_event(self.events.as_ref(), &ev);
    }

    /// Writes the fault events held back for a recovery, and takes their replicas out of the
    /// journal's table (see `held.rs`).
    pub(crate) fn release_faults(&self) {
        self.held
            .release(self.events.as_ref(), self.journal.as_ref());
    }

    /// Every alarm is an `anomaly` event, whatever the voter then does about it. `again`: the
    /// replica's previous frame on `o` alarmed too.
    pub(crate) fn anomaly_event(&self, r: usize, pid: libc::pid_t, o: usize, at: At, again: bool) {
        let Some(alarm) = self.monitors.alarm(r, o) else {
            return;
        };
        let (cause, note) = if again {
            (
                Cause::AlarmAgain,
                "; its previous frame alarmed too (this may be the way back from it)",
            )
        } else {
            (Cause::Alarm, "")
        };
        let mut ev = Event::caused(&self.plan.system, &self.plan.component, cause);
        ev.replica = Some(r);
        ev.pid = Some(pid);
        at.mark(&mut ev);
        ev.output = Some(self.output_name(o).to_owned());
        ev.field = alarm.field;
        ev.score = alarm.score;
        ev.threshold = Some(alarm.threshold);
        ev.detail = Some(match at {
            At::Round(_) => format!("{}{note}", alarm.cause),
            At::Frame(k) => format!("{} (frame {k}){note}", alarm.cause),
        });
        self.emit(ev);
    }

    // ----- faults ------------------------------------------------------------------------

    /// Records a fault of replica `r`: kills it at once, writes the event, and queues its slot
    /// for recovery. Returns its pid, or `None` if the slot was already faulty.
    pub(crate) fn record_fault(
        &mut self,
        r: usize,
        cause: Cause,
        detail: String,
        round: Option<u64>,
    ) -> Option<libc::pid_t> {
        let mut replica = self.slots[r].take()?;
        // A replica that died on its own: its exit status, before our SIGKILL could take its
        // place. It may still be dying (its output closed just before its exit), which is
        // waited for here, within a bound.
        let status = if cause == Cause::Died {
            // A wait (bounded): what is held from an earlier fault goes out before it.
            self.release_faults();
            replica.exit_status(EXIT_STATUS_WAIT)
        } else {
            None
        };
        replica.kill();
        // What it wrote last, for the restart budget's message (more may follow as it dies).
        replica.relay_stderr(&self.plan.component, r);
        let mut ev = Event::caused(&self.plan.system, &self.plan.component, cause);
        ev.replica = Some(r);
        ev.pid = Some(replica.pid);
        ev.round = round;
        match status {
            Some(sys::ExitStatus::Code(code)) => ev.exit_code = Some(code),
            Some(sys::ExitStatus::Signal(sig)) => ev.signal = Some(sig),
            None => {}
        }
        ev.detail = Some(detail);
        self.last_fault = ev.to_string();
        if !replica.stderr.last_line.is_empty() {
            self.last_fault = format!(
                "{}; its last stderr line: {}",
                self.last_fault, replica.stderr.last_line
            );
        }
        let detected_ns = ev.ts_ns;
        // Its event is written, and the journal no longer names it, once the donor of its
        // recovery has been signalled (or before the loop next waits, whichever comes first;
        // `held.rs`). The event first: a successor that adopts the replicas after both refills
        // the slot without reporting its fault a second time, one that adopts them before the
        // event finds the dead replica named and reports it itself (and one in between reports
        // it again, which bootstrap's events reader keeps once).
        self.held.hold(ev, r);
        let pid = replica.pid;
        self.faults.push(Fault {
            slot: r,
            replica,
            detected_ns,
        });
        Some(pid)
    }

    /// What a replica whose output pipe closed turns out to be once [`EXIT_AFTER_EOF`] has
    /// passed: a crash if it is gone, a protocol fault if it lives. `None` while the grace
    /// runs, or if no output of it closed. A replica still running at the end of the grace
    /// gets more, up to [`EXIT_AFTER_EOF_BUSY`]: a program that closes its ports and then
    /// reports an error on its way out (Rust's `main` returning `Err` with `RUST_BACKTRACE`
    /// set symbolizes a backtrace for 100 ms and more) exits a while after its output closed,
    /// and was called a protocol fault ('closed its output') instead of the crash it is.
    fn closed_output_fault(&mut self, r: usize) -> Option<(Cause, String)> {
        let rep = self.slots[r].as_mut()?;
        let (since, ends) = (rep.output_closed_at?, rep.output_grace_ends?);
        // On the counter, exactly as the wake-up was set (a duration read off the counter is
        // rounded down, and could keep the loop spinning a few µs past it).
        let now = Instant::now();
        if now < ends {
            return None;
        }
        // On a loaded machine a killed replica can take longer than the grace to finish
        // dying (its fds closed first): the kernel's own flag says it is on its way out.
        if rep.exited_within(Duration::ZERO) || sys::process_exiting(rep.pid) {
            return Some((Cause::Died, DIED.into()));
        }
        let busy = matches!(rep.proc_stat.state(rep.pidfd.as_fd()), Some('R' | 'D'));
        if busy && now < since + EXIT_AFTER_EOF_BUSY {
            rep.output_grace_ends = Some(now + EXIT_AFTER_EOF);
            return None;
        }
        let closed = rep
            .outputs
            .iter()
            .position(|out| out.is_closed())
            .unwrap_or(0);
        let finished = rep.outputs[closed].decoder.finish();
        let name = self.output_name(closed);
        Some(match finished {
            Err(e @ FrameError::Truncated { .. }) => {
                (Cause::PartialFrame, format!("output `{name}`: {e}"))
            }
            _ => (Cause::ClosedOutput, format!("closed its output `{name}`")),
        })
    }

    /// Why replica `r` missed a frame it owed, seen at a deadline: a partial frame in its pipe
    /// is a protocol fault, nothing at all a hang (`hang` is the cause the mode names).
    pub(crate) fn late_cause(&self, r: usize, hang: Cause) -> (Cause, Option<usize>) {
        let partial = self.slots[r]
            .as_ref()
            .and_then(|rep| rep.outputs.iter().position(|out| out.decoder.pending() > 0));
        match partial {
            Some(o) => (Cause::PartialFrame, Some(o)),
            None => (hang, None),
        }
    }

    // ----- decisions ---------------------------------------------------------------------

    /// Carries out `decision` on output `o`: sends `frame` (what the decision forwards, unless
    /// it was sent already), records it for capture, writes the events of an unattributed
    /// fault, and returns whom the mode must fault.
    pub(crate) fn apply(
        &mut self,
        o: usize,
        at: At,
        decision: &Decision,
        frame: Option<&[u8]>,
    ) -> Option<Blame> {
        if let Some(frame) = frame {
            self.outputs[o].send(frame);
            self.captures.record(o, frame);
        }
        let (suspects, cause) = decision.blame();
        let suspects = suspects.minus(self.spare_diverged(suspects, cause, o, at));
        let name = self.output_name(o);
        let unattributed = match decision {
            Decision::Withhold { answered } if answered.is_empty() => {
                tracing::warn!(%at, output = %name, "no replica answered; nothing forwarded");
                let mut ev = self.event(EventKind::Lost);
                at.mark(&mut ev);
                ev.output = Some(name.to_owned());
                ev.detail = Some(format!("no replica answered on `{name}` in {at}; nothing went out"));
                self.emit(ev);
                None
            }
            Decision::Withhold { answered } => Some((
                Cause::NoMajority,
                format!("no majority on `{name}` in {at}: replicas {answered:?} disagree; withheld"),
            )),
            Decision::Rebuild(rebuilt) => rebuilt.kept.map(|k| {
                (
                    Cause::AllDiffer,
                    format!(
                        "no majority on `{name}` in {at}, every replica's frame differs from the bitwise majority (forwarded); replica {k}, the closest, kept as donor"
                    ),
                )
            }),
            _ => None,
        };
        if let Some((cause, detail)) = unattributed {
            let mut ev = Event::caused(&self.plan.system, &self.plan.component, cause);
            at.mark(&mut ev);
            ev.detail = Some(detail);
            self.emit(ev);
        }
        if suspects.is_empty() {
            return None;
        }
        let detail = match decision {
            Decision::Forward { .. } => format!("`{name}` differs from the majority in {at}"),
            Decision::Rebuild(rebuilt) => format!(
                "`{name}` had no majority in {at} and differs from the bitwise majority, which was forwarded (≤ {} bits apart)",
                rebuilt.max_bits
            ),
            Decision::HoldBack { .. } => format!(
                "the anomaly detector flagged `{name}` in {at} (see its `anomaly` event) and no other replica confirms it; held back"
            ),
            Decision::Attribute { healthy, .. } => format!(
                "`{name}` in {at} differs from replica {healthy}'s and only its copy alarmed the anomaly detector (see its `anomaly` event); replica {healthy}'s was forwarded"
            ),
            Decision::Withhold { .. } => unreachable!("a withheld frame blames nobody"),
        };
        Some(Blame {
            suspects,
            cause,
            detail,
        })
    }

    // ----- input -------------------------------------------------------------------------

    /// Whether a predecessor's input is still being replayed.
    pub(crate) fn replaying(&self) -> bool {
        self.inputs
            .iter()
            .any(|i| i.peek.as_ref().is_some_and(|p| p.replay_left > 0))
    }

    /// Whether input `i`'s journal log has room for its largest frame (always, unjournaled,
    /// or while the predecessor's log is replayed).
    pub(crate) fn journal_has_room(&self, i: usize) -> bool {
        let replaying = self.inputs[i]
            .peek
            .as_ref()
            .is_some_and(|p| p.replay_left > 0);
        // The next frame comes out of the replay, which is in the log already.
        replaying
            || self.journal.as_ref().is_none_or(|journal| {
                let most =
                    self.plan.inputs[i].max_frame + frame::HEADER_LEN + 2 * frame::RESUME_LEN;
                journal.has_room(i, most)
            })
    }

    /// Closes input `i` because of what upstream sent on it: it cannot be resynchronised with
    /// (nor told), so the input ends here, and the component with it, as failed.
    fn upstream_broke(&mut self, i: usize, why: String) {
        tracing::error!("{why}; dropping the rest of this input");
        self.inputs[i].reader.close();
        self.upstream_broke.get_or_insert(why);
    }

    /// Copies the next whole frame buffered on input `i` to every trusted replica. `None` when
    /// no whole frame is buffered (or upstream broke the framing: the input is closed, since
    /// we cannot resynchronise). Replicas whose pipe broke, or that have not taken more than
    /// `backlog_limit` bytes of it, are returned for the mode to fault.
    pub(crate) fn deliver_next(
        &mut self,
        i: usize,
        backlog_limit: Option<usize>,
    ) -> Option<Delivery> {
        // Room for the largest frame and the resume frames before it, or wait for a commit.
        if !self.journal_has_room(i) {
            return None;
        }
        let delivery = self.deliver_decoded(i, backlog_limit);
        if delivery.is_some() {
            crate::crashpoint::reached("input-delivered");
        }
        // The take after the writes, not before: either order leaves replicas on CPUs of
        // their own a window in which an answer meets the voter on its way to sleep and costs
        // an inter-processor interrupt (~10 µs on a virtual machine); which rounds hit it
        // depends on how long the replicas take. Taken first (tried in stop 52), SMR 8 B
        // across CPUs went from 25.7 to 21.7 µs and TMR 4 KiB from 23.3 to 38.9 (results.md).
        self.take_decoded(i);
        delivery
    }

    fn deliver_decoded(&mut self, i: usize, backlog_limit: Option<usize>) -> Option<Delivery> {
        let input = &mut self.inputs[i];
        let number = self.delivered[i] + 1;
        let frame = match input.reader.decoder.next_frame() {
            Ok(Some(f)) => f,
            Ok(None) => return None,
            Err(e) => {
                let why = format!("bad frame from upstream on `{}`: {e}", input.name);
                self.upstream_broke(i, why);
                return None;
            }
        };
        if self.plan.framing == Framing::Lines {
            // A program that reads lines would take this frame for two inputs, answer twice,
            // and have every replica blamed for the extra answer.
            if let Some(at) = frame.iter().position(|&b| b == b'\n') {
                let why = format!(
                    "input frame {number} on `{}` holds a newline (byte {at} of {}), and `{}` \
                     reads one line per frame: whatever sends on `{}` must not put newlines \
                     in its frames",
                    input.name,
                    frame.len(),
                    self.plan.exec.display(),
                    input.name
                );
                self.upstream_broke(i, why);
                return None;
            }
        }
        let frame_len = frame.len();
        let mut delivery = Delivery::default();
        // An unmodified program's lines are each given once (see `lines.rs`).
        let lines = self.journal.as_ref().filter(|_| self.park.is_some());
        for (r, rep) in self.slots.iter_mut().enumerate() {
            let Some(rep) = rep else { continue };
            let given = match lines {
                Some(journal) => crate::lines::give_line(journal, r, rep, i, frame, number),
                None => rep.inputs[i].writer.send(frame).map(|()| true),
            };
            match given {
                Ok(true) => delivery.members = delivery.members.with(r),
                Ok(false) => {}
                Err(e) => delivery.faulty.push((
                    r,
                    Cause::PipeError,
                    format!("input pipe `{}` broke: {e}", input.name),
                )),
            }
            let backlog = rep.inputs[i].writer.unwritten_len();
            if let Some(limit) = backlog_limit.filter(|&l| backlog > l) {
                // A replica that stopped reading an input no round waits on (stopped, spinning,
                // stuck on another port) would make the voter queue for it without end.
                delivery.faulty.push((
                    r,
                    Cause::InputBacklog,
                    format!(
                        "has not taken {backlog} bytes of input on `{}` (limit {limit})",
                        input.name
                    ),
                ));
            }
        }
        self.delivered[i] += 1;
        self.last_delivered_len[i] = frame::HEADER_LEN + frame_len;
        Some(delivery)
    }

    // ----- recovery ----------------------------------------------------------------------

    /// Forks `d` for a new replica in `slot`: the donor runs above its siblings while it forks
    /// (S³RES §4.4), and goes back to rest once its child has joined. The replica being
    /// replaced is retired while the donor forks: waiting for it to finish dying (its memory
    /// torn down, milliseconds for a large state after a hang's SIGKILL), relaying its last
    /// words and reaping it need not hold up the fork. The child is moved to its slot's CPUs
    /// as soon as it has joined, while it walks its pages (done after its `Ready`, that call
    /// and the donor's rest lay between the `Ready` and the replica counted in). It keeps the
    /// raised priority it inherited through its walk, as before: at its slot's rest a busy
    /// sibling above it (a stream's) could hold its walk up; `replace` gives it its slot's
    /// priority after the `Ready`.
    pub(crate) fn fork(
        &mut self,
        slot: usize,
        d: usize,
        state: DonorState,
    ) -> Result<Forked, RecoveryError> {
        let family: Vec<libc::pid_t> = self.slots.iter().flatten().map(|r| r.pid).collect();
        self.restart_nonce = self.restart_nonce.wrapping_add(1).max(1);
        let donor = self.slots[d].as_mut().expect("donor slot is filled");
        // What the donor has said up to the signal, for its child's relay (read now, so that
        // what it writes after the fork stays its own).
        donor.relay_stderr(&self.plan.component, d);
        let said = donor.stderr.memory();
        let donor_pid = donor.pid;
        let mut retiring = self.retiring.take();
        let component = &self.plan.component;
        let (held, events, journal) = (&self.held, self.events.as_ref(), self.journal.as_ref());
        let rt = &mut self.rt;
        // The faults' events out (held until now, see `held.rs`), and the replaced replica
        // retired: once the donor is signalled, or after an attempt that failed before that.
        let mut settle_the_fault = || {
            held.release(events, journal);
            Fault::retire_if_any(&mut retiring, component);
        };
        let mut donor_level = DonorLevel::AtRest;
        let forked = recovery::fork(
            &self.plan,
            &self.listener,
            &mut self.spares,
            donor,
            self.restart_nonce,
            &family,
            state,
            &mut |step| match step {
                recovery::Step::Signalled => {
                    // Raised right after the signal, not before it: the donor's wake-up does
                    // not wait for the call, and a sibling running on its CPU keeps it waiting
                    // only until the call lands.
                    rt.raise(donor_pid);
                    donor_level = DonorLevel::Raised;
                    settle_the_fault();
                }
                recovery::Step::Joined(child) => {
                    rt.rest(donor_pid, d);
                    donor_level = DonorLevel::RestedAgain;
                    rt.place_replica(child, slot);
                }
            },
        );
        // The attempt failed before the donor was signalled, or before a child joined.
        settle_the_fault();
        if donor_level == DonorLevel::Raised {
            rt.rest(donor_pid, d);
        }
        let mut forked = forked?;
        // The child remembers what its donor said, as it remembers the rest of its memory: a
        // donor forked while it reported an error on its way out has a child that writes only
        // the rest (a backtrace) and dies, and the restart budget's line must still quote the
        // error.
        forked.replica.stderr.continue_from(&said);
        Ok(forked)
    }

    /// Retires the replica being replaced now, if that has not happened yet.
    pub(crate) fn retire_pending(&mut self) {
        Fault::retire_if_any(&mut self.retiring, &self.plan.component);
    }

    /// A `recovery` event: `slot` went from `old_pid` to `new_pid`, `detected_ns` after the
    /// fault.
    fn recovery_event(&self, slot: usize, old_pid: i32, new_pid: i32, detected_ns: u64) -> Event {
        let mut ev = self.event(EventKind::Recovery);
        ev.replica = Some(slot);
        ev.pid = Some(old_pid);
        ev.new_pid = Some(new_pid);
        ev.recovery_us = Some(ev.ts_ns.saturating_sub(detected_ns) / 1000);
        ev
    }

    /// Fills `slot` with a fresh replica started by exec (state lost, and the event says so).
    /// `Ok(false)` if it could not be started but other replicas remain; an error if none does.
    fn replace_by_exec(
        &mut self,
        slot: usize,
        old_pid: i32,
        detected_ns: u64,
        retry: bool,
    ) -> Result<bool, VoterError> {
        self.check_restart_budget()?;
        match Replica::spawn(&self.plan, slot, self.stamps.as_ref().map(AnswerStamps::fd)) {
            Ok(fresh) => {
                self.exec_restarts.push_back(Instant::now());
                self.exec_restarts_total += 1;
                self.rt.apply_to_replica(fresh.pid, slot);
                // A fresh process has the state of one that was never given a frame: before
                // the first, nothing is lost.
                let state_lost = !self.untouched();
                let mut ev = self.recovery_event(slot, old_pid, fresh.pid, detected_ns);
                ev.method = Some(RecoveryMethod::Exec);
                ev.state_lost = Some(state_lost);
                self.emit(ev);
                let mut fresh = fresh;
                fresh.state_lost = state_lost;
                fresh.catching_up = state_lost;
                self.slots[slot] = Some(fresh);
                self.forget_stamps_of_the_gone();
                self.number_inputs_of(slot);
                // A fresh process: its first frame is a warm-up for the detectors.
                self.monitors.reset_stream(slot);
                Ok(true)
            }
            Err(e) if retry => {
                tracing::debug!(replica = slot, error = %e, "still cannot start a replica");
                Ok(false)
            }
            Err(e) => {
                let mut ev = self.event(EventKind::RecoveryFailed);
                ev.replica = Some(slot);
                ev.pid = Some(old_pid);
                ev.detail = Some(format!(
                    "could not start {}: {e}; the component runs degraded and the voter tries again",
                    self.plan.exec.display()
                ));
                self.emit(ev);
                if self.slots.iter().all(Option::is_none) {
                    return Err(VoterError::Unrecoverable(format!(
                        "no replica left and {} cannot be started: {e}",
                        self.plan.exec.display()
                    )));
                }
                Ok(false)
            }
        }
    }

    /// Whether no replica of this component has been given a frame and none of its outputs
    /// has sent one: a replica started now has the state every replica has. A component
    /// without inputs (a source) is never untouched: its state may grow without input.
    fn untouched(&self) -> bool {
        !self.inputs.is_empty()
            && self.delivered.iter().all(|&d| d == 0)
            && self.outputs.iter().all(|o| o.sent == 0)
    }

    /// Checks the budget before a restart by exec (`max_restarts` replicas started within
    /// `restart_window_ms`, after OTP's restart intensity; only replicas that were started
    /// count, not attempts that the kernel refused): one more and the component has failed,
    /// with one line that says why.
    fn check_restart_budget(&mut self) -> Result<(), VoterError> {
        let now = Instant::now();
        let window = Duration::from_millis(self.plan.restart_window_ms);
        while self
            .exec_restarts
            .front()
            .is_some_and(|&t| now.saturating_duration_since(t) > window)
        {
            self.exec_restarts.pop_front();
        }
        // A replica that never answers is restarted at the pace of its start deadline (1 s by
        // default), slower than any window: the budget also ends a component none of whose
        // replicas ever answered, however slowly it was restarted.
        let max = self.plan.max_restarts as usize;
        let never_answered = !self.exec_answered && self.exec_restarts_total >= max as u64;
        if self.exec_restarts.len() < max && !never_answered {
            return Ok(());
        }
        // A program that never answered and never said a word did not speak the protocol; one
        // that said something (a panic, an error) is quoted in `last_fault` instead.
        let started =
            self.runtime_started || self.slots.iter_mut().flatten().any(Replica::read_started);
        let exec = self.plan.exec.display();
        let hint = if self.exec_answered || self.last_fault.contains("its last stderr line") {
            String::new()
        } else if !started {
            format!(
                "; no replica ever completed the s3res start (its runtime's init never ran): \
                 `{exec}` does not speak the s3res protocol. Protect it one of three ways \
                 (docs/writing-a-component.md): link replica-rt (Rust), link libs3res_replica_c \
                 (C, C++), or declare it an unmodified stdin/stdout program with \
                 \"runtime\": \"preload\""
            )
        } else if self.plan.preload.is_some() {
            format!(
                "; its replicas started but none ever answered: does `{exec}` write one line to \
                 stdout for each line it reads, and flush it (`python3 -u`, awk's `fflush()`)?"
            )
        } else {
            format!(
                "; its replicas started (replica-rt's init ran) but none ever answered: does \
                 `{exec}` answer every round with one frame on each of its outputs?"
            )
        };
        let how_often = if self.exec_restarts.len() >= max {
            format!(
                "{} times within {} ms",
                self.exec_restarts.len(),
                self.plan.restart_window_ms
            )
        } else {
            format!(
                "{} times and none of its replicas ever answered",
                self.exec_restarts_total
            )
        };
        Err(VoterError::Unrecoverable(format!(
            "component {} restarted a replica by exec {how_often} (max_restarts {}) and needs another; last fault: {}{hint}",
            self.plan.component,
            self.plan.max_restarts,
            self.last_fault
        )))
    }

    // ----- the end -----------------------------------------------------------------------

    /// Writes out what is still queued for downstream (blocking up to [`OUTPUT_DRAIN_LIMIT`]),
    /// then gives the replicas [`SHUTDOWN_GRACE`] to exit by themselves.
    /// At the end of a run: an output that could not be written (a full disk behind a
    /// redirected stdout) lost what the component sent there, and the run is no success (the
    /// voter's exit says why; not a `lost` event, which counts frames no replica answered).
    /// Before, such a run ended "ran clean", exit 0, with none of 2000 frames written.
    pub(crate) fn output_failure(&self) -> Result<(), VoterError> {
        match self.outputs.iter().find_map(ExternalOutput::failure) {
            Some(why) => Err(VoterError::OutputLost(why)),
            None => Ok(()),
        }
    }

    pub(crate) fn drain_and_let_finish(&mut self) {
        heartbeat_ending();
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
                    "replica did not finish after its input closed; killing it"
                );
            }
        }
    }

    /// Kills every replica (trusted or faulty) and everything re-parented to us, after giving
    /// downstream whatever it takes at once; removes the socket.
    pub(crate) fn shut_down(&mut self) {
        self.release_faults();
        heartbeat_ending();
        self.captures.flush();
        self.monitors.log_cost();
        // On a requested stop, whatever downstream can take right now still goes out.
        for out in self.outputs.iter_mut() {
            if out.writer.has_pending() && !out.broken {
                out.flush();
            }
        }
        self.kill_replicas();
        let component = self.plan.component.clone();
        for (r, rep) in self.slots.iter_mut().enumerate() {
            if let Some(rep) = rep {
                rep.exited_within(DEATH_WAIT);
                rep.relay_stderr(&component, r);
            }
        }
        for fault in &mut self.faults {
            fault.replica.relay_stderr(&component, fault.slot);
        }
        kill_all_children(Duration::from_secs(3));
        let _ = std::fs::remove_file(&self.plan.socket_path);
    }

    /// Kills every replica, trusted or faulty.
    fn kill_replicas(&self) {
        for rep in self.slots.iter().flatten() {
            rep.kill();
        }
        for fault in &self.faults {
            fault.replica.kill();
        }
    }
}

/// Also on a panic: no replica outlives its voter (bootstrap's sweep would catch them, but the
/// voter should not depend on it).
impl Drop for Core {
    fn drop(&mut self) {
        self.kill_replicas();
    }
}

/// The text of every `crash` event.
pub(crate) const DIED: &str = "the replica process died";

/// What copying one input frame to the replicas found.
#[derive(Debug, Default)]
pub(crate) struct Delivery {
    /// The replicas it was written (or queued) to.
    pub(crate) members: ReplicaSet,
    /// Replicas to fault: a broken pipe, or a backlog beyond the limit.
    pub(crate) faulty: Vec<(usize, Cause, String)>,
}

// ----- the loop's shared steps, generic over the mode ---------------------------------------

/// Runs the mode's loop, then stops everything: every replica and everything re-parented to
/// the voter is killed, also after an error.
pub(crate) fn run(mut m: impl Mode) -> Result<(), VoterError> {
    let result = m.run_loop();
    m.core().shut_down();
    result?;
    match m.core().upstream_broke.take() {
        Some(why) => Err(VoterError::Upstream(why)),
        None => Ok(()),
    }
}

/// One `ppoll` on everything that can make progress, bounded by the mode's next wake-up, then
/// each ready fd to the core or the mode.
pub(crate) fn wait_and_dispatch(m: &mut impl Mode) -> Result<(), VoterError> {
    // No fault event waits with the loop (`held.rs`).
    m.core().release_faults();
    m.build_poll_set();
    let core = m.core();
    let stalled_input = core
        .inputs
        .iter()
        .filter_map(|i| i.peek.as_ref().and_then(|p| p.stalled_until))
        .min();
    let output_room = core
        .outputs
        .iter()
        .any(|o| o.writer.waiting_for_room())
        .then(|| Instant::now() + ROOM_RETRY);
    let retry = core
        .vacant
        .iter()
        .map(|v| v.next_try)
        .chain(stalled_input)
        .chain(output_room)
        .min();
    // Never asleep longer than a heartbeat period: bootstrap must see the loop turn. That bound
    // is the wake timer's too, so the wait itself has no timeout: a `ppoll` timeout arms and
    // cancels a kernel timer on every wait, twice per round for nothing.
    let heartbeat = Instant::now() + HEARTBEAT_PERIOD;
    let wake = [m.next_wakeup(), retry]
        .into_iter()
        .flatten()
        .fold(heartbeat, Instant::min);
    m.core().timer.wake_by(wake)?;
    beat();
    let spin = if m.may_spin() {
        m.core().spin.grant(Instant::now())
    } else {
        None
    };
    let core = m.core();
    core.poll.seal();
    let (ready, _spun) = core.poll.wait(spin)?;
    for out in &mut m.core().outputs {
        if out.writer.waiting_for_room() {
            out.flush();
        }
    }
    if ready == 0 {
        return Ok(());
    }
    for k in 0..m.core().poll.fds.len() {
        let core = m.core();
        if core.poll.fds[k].revents == 0 {
            continue;
        }
        if core.poll.tokens[k] == Token::Quiet {
            core.poll.ready_quiet();
            // Taken out while dispatched (a handler may use the core), and put back with its
            // capacity.
            let quiet = std::mem::take(&mut core.poll.quiet_ready);
            for &token in &quiet {
                dispatch(m, token);
            }
            m.core().poll.quiet_ready = quiet;
        } else {
            let token = core.poll.tokens[k];
            dispatch(m, token);
        }
    }
    Ok(())
}

/// Hands one ready fd to the core or the mode.
fn dispatch(m: &mut impl Mode, token: Token) {
    let core = m.core();
    match token {
        Token::Signal => {
            if stop_requested(&core.signals) {
                core.stop = Some(Stop::Requested);
            }
        }
        Token::Input(i) => m.on_input_readable(i),
        // Stopping at a request (SIGTERM, SIGINT): an answer ready in the same wait would be
        // judged against rounds that no longer start, its replica blamed for the stop
        // ("frame after the inputs closed"). It is left unread.
        Token::ReplicaOutput(..) if core.stop == Some(Stop::Requested) => {}
        Token::OutputWritable(o) => core.outputs[o].flush(),
        Token::Timer => core.timer.expired(),
        Token::ReplicaExit(r) => m.on_replica_exit(r),
        Token::ReplicaOutput(r, o) => m.on_replica_output(r, o),
        Token::ReplicaStderr(r) => {
            let component = &core.plan.component;
            if let Some(rep) = core.slots[r].as_mut() {
                rep.relay_stderr(component, r);
            }
        }
        Token::ReplicaStarted(r) => {
            if core.slots[r].as_mut().is_some_and(Replica::read_started) {
                core.runtime_started = true;
            }
        }
        Token::ReplicaInputWritable(r, i) => {
            let flushed = core.slots[r].as_mut().map(|rep| rep.flush_input(i));
            core.note_moved(r);
            if let Some(Err(e)) = flushed {
                let detail = format!("input pipe `{}` broke: {e}", core.input_name(i));
                m.fault(r, Cause::PipeError, detail);
            }
        }
        // Handled by `wait_and_dispatch`, which asks the poll set which quiet fds are ready.
        Token::Quiet => {}
    }
}

/// A replica closed an output. The kernel closes a dying process's fds just before it
/// reports the exit, so this is a crash if the pidfd follows within [`EXIT_AFTER_EOF`] (the
/// event loop watches it, without blocking), else a protocol fault.
pub(crate) fn output_closed(m: &mut impl Mode, r: usize) {
    if m.core().slots[r]
        .as_mut()
        .is_some_and(Replica::note_output_closed)
    {
        m.fault(r, Cause::Died, DIED.into());
    }
}

/// What a read of replica `r`'s output `o` found besides frames: the end of the pipe (see
/// [`output_closed`]) or an error, a protocol fault.
pub(crate) fn after_read(m: &mut impl Mode, r: usize, o: usize, fill: std::io::Result<Fill>) {
    match fill {
        Ok(Fill::Open) => {}
        Ok(Fill::Closed) => m.on_output_closed(r),
        Err(e) => {
            let detail = format!("reading output `{}`: {e}", m.core().output_name(o));
            m.fault(r, Cause::PipeError, detail);
        }
    }
}

/// Faults the replicas whose output closed more than [`EXIT_AFTER_EOF`] ago: crashed, or
/// (still alive) broke the protocol.
pub(crate) fn fault_closed_outputs(m: &mut impl Mode) {
    for r in 0..m.core().slots.len() {
        if let Some((cause, detail)) = m.core().closed_output_fault(r) {
            m.fault(r, cause, detail);
        }
    }
}

/// Replaces every faulty replica (see [`replace`]), and tries again to fill the slots whose
/// replacement failed before, once their backoff has passed; with `replace_them` false (the
/// voter is stopping or ending) the faults stay recorded and nothing is started. Returns
/// whether it did anything (the loop was away meanwhile).
pub(crate) fn recover_faulty(m: &mut impl Mode, replace_them: bool) -> Result<bool, VoterError> {
    let mut worked = false;
    while let Some(fault) = m.core().faults.pop() {
        worked = true;
        if !replace_them {
            continue;
        }
        let (slot, old_pid, detected_ns) = (fault.slot, fault.replica.pid, fault.detected_ns);
        // Retired while a donor forks for it, or before whatever else fills the slot.
        m.core().retiring = Some(fault);
        let filled = replace(m, slot, old_pid, detected_ns, false);
        m.core().retire_pending();
        if !filled? {
            m.core().vacant.push(Vacancy {
                slot,
                old_pid,
                detected_ns,
                next_try: Instant::now() + VACANCY_BACKOFF.0,
                backoff: VACANCY_BACKOFF.0,
            });
        }
    }
    if !replace_them {
        return Ok(worked);
    }
    let now = Instant::now();
    let due: Vec<Vacancy> = m
        .core()
        .vacant
        .iter()
        .filter(|v| v.next_try <= now)
        .copied()
        .collect();
    for v in due {
        worked = true;
        let filled = replace(m, v.slot, v.old_pid, v.detected_ns, true)?;
        let vacant = &mut m.core().vacant;
        let Some(k) = vacant.iter().position(|w| w.slot == v.slot) else {
            continue;
        };
        if filled {
            vacant.remove(k);
            tracing::info!(replica = v.slot, "redundancy restored");
        } else {
            let backoff = (v.backoff * 2).min(VACANCY_BACKOFF.1);
            vacant[k].backoff = backoff;
            vacant[k].next_try = Instant::now() + backoff;
        }
    }
    Ok(worked)
}

/// Fills `slot` by fork of the best donor, else by exec (state lost). A candidate donor that
/// never waits within `timeout_us` is a hang itself (its child would spin too). A donor that
/// fails during the fork (it died, or stopped) is passed over for the next best before the
/// voter falls back to exec: a fresh replica must not replace one that could still have been
/// rebuilt with the component's state.
fn replace(
    m: &mut impl Mode,
    slot: usize,
    old_pid: i32,
    detected_ns: u64,
    retry: bool,
) -> Result<bool, VoterError> {
    let waited_ms = s3res_protocol::clock::monotonic_ns().saturating_sub(detected_ns) / 1_000_000;
    if m.core().parks_lines()
        && !m.core().lines_quiet()
        && waited_ms < m.core().plan.restart_timeout_ms
    {
        // Not yet (see `Core::lines_quiet`): the slot is tried again with backoff, for as long
        // as a recovery may take; then as it can (a fork would fail, an exec loses the state).
        // No donor is signalled now: the fault's event goes out first.
        m.core().release_faults();
        m.core().retire_pending();
        return Ok(false);
    }
    let patience = Duration::from_micros(m.core().plan.timeout_us);
    let mut failed = ReplicaSet::EMPTY;
    let mut threaded: Vec<usize>;
    loop {
        let progress = m.progress();
        let core = m.core();
        // A donor not seen asleep is waited for: the fault's event does not wait with it.
        let pick =
            crate::replica::best_donor(&core.slots, |d| progress[d], patience, failed, &|| {
                core.release_faults()
            });
        threaded = pick.threaded;
        for r in pick.hung {
            let detail = format!(
                "picked as recovery donor, it ran for {} µs without once waiting for input or producing a frame",
                m.core().plan.timeout_us
            );
            m.fault(r, Cause::DonorSpinning, detail);
        }
        let Some(d) = pick.donor else { break };
        let (state_lost, catching_up) = m.core().slots[d]
            .as_ref()
            .map_or((false, false), |r| (r.state_lost, r.catching_up));
        match m.fork_into(slot, d) {
            Ok(pid) => {
                let core = m.core();
                if let Some(child) = core.slots[slot].as_mut() {
                    child.state_lost = state_lost;
                    child.catching_up = catching_up;
                }
                if !state_lost {
                    // The slot has the component's state again.
                    core.relapsed = core.relapsed.without(slot);
                }
                // The child took the slot's CPUs when it joined (`Core::fork`); it ran its
                // page walk at the donor's raised priority, and takes the slot's now.
                core.rt.set_replica_priority(pid, slot);
                // The child continues the donor's frames, so its detector stream too.
                core.monitors.copy_stream(d, slot);
                let mut ev = core.recovery_event(slot, old_pid, pid, detected_ns);
                ev.donor = Some(d);
                ev.method = Some(RecoveryMethod::Fork);
                ev.state_lost = Some(state_lost);
                core.emit(ev);
                // Its `/proc/PID/stat`, for when it is a donor candidate: opened here, off the
                // path the `recovery` event measures.
                if let Some(child) = core.slots[slot].as_ref() {
                    child.proc_stat.open_now(child.pidfd.as_fd());
                }
                m.forked(slot);
                return Ok(true);
            }
            Err(e) => {
                tracing::warn!(replica = slot, donor = d, error = %e, "recovery by fork failed; trying the next donor");
                failed = failed.with(d);
            }
        }
    }
    if !threaded.is_empty() {
        let also = if failed.is_empty() {
            String::new()
        } else {
            format!(" (and the fork of {failed:?} failed)")
        };
        tracing::warn!(
            replica = slot,
            "no recovery donor: replicas {threaded:?} run more than one thread, and a fork \
             copies only the thread that makes it{also}; starting replica {slot} afresh (state \
             lost)"
        );
    }
    // Retiring the replaced replica (its death awaited, up to a second) and an exec (milliseconds)
    // come after the fault's event.
    m.core().release_faults();
    m.core().retire_pending();
    let started = m
        .core()
        .replace_by_exec(slot, old_pid, detected_ns, retry)?;
    if started {
        m.started_fresh(slot);
    }
    Ok(started)
}

impl Fault {
    /// Retires the fault `pending` holds, if any, and leaves it empty.
    fn retire_if_any(pending: &mut Option<Fault>, component: &str) {
        if let Some(fault) = pending.take() {
            fault.retire(component);
        }
    }

    /// Makes sure the killed replica is gone (bounded) and reaped.
    pub(crate) fn retire(self, component: &str) {
        let Fault {
            slot,
            replica: mut old,
            ..
        } = self;
        if !old.exited_within(DEATH_WAIT) {
            tracing::warn!(pid = old.pid, "killed replica has not exited yet");
        }
        // Its last words (a panic report, an error) are in its stderr pipe.
        old.relay_stderr(component, slot);
        if old.our_child {
            let _ = sys::reap(old.pid);
        }
        drop(old.pidfd);
        reap_children();
    }
}

/// How soon an output waiting for room for a whole frame looks again.
const ROOM_RETRY: Duration = Duration::from_millis(1);

/// How long the end frame may wait for room in a replica's input pipe: a replica that does not
/// read its input for that long takes the closed pipe for its voter's death, looks for a
/// successor, finds none that takes it, and ends all the same.
const END_FRAME_WAIT: Duration = Duration::from_millis(100);

/// Writes out what `writer` has queued, waiting for room up to `deadline`.
fn drain_writer(writer: &mut crate::channel::FrameWriter, deadline: Instant) {
    use std::os::fd::AsRawFd;
    while writer.has_pending() {
        if writer.flush().is_err() || !writer.has_pending() {
            return;
        }
        let left = deadline.saturating_duration_since(Instant::now());
        let mut pfd = [libc::pollfd {
            fd: writer.as_fd().as_raw_fd(),
            events: libc::POLLOUT,
            revents: 0,
        }];
        if left.is_zero() || sys::ppoll(&mut pfd, Some(left)).unwrap_or(0) == 0 {
            return;
        }
    }
}

/// Makes every output write whole frames only, for a journaled voter: its successor writes on
/// the same pipes.
fn whole_frame_outputs(outputs: &mut [ExternalOutput], plan: &VoterPlan) -> Result<(), VoterError> {
    for (out, port) in outputs.iter_mut().zip(&plan.outputs) {
        let whole = out
            .writer
            .write_whole_frames(port.max_frame)
            .map_err(io_err(format!("output `{}`", out.name)))?;
        if !whole {
            tracing::debug!(output = %out.name, "output is not a pipe: written as it comes");
        }
    }
    Ok(())
}

/// Makes every input peeked rather than read, for a journaled voter (see `journal.rs`). An
/// input that is not a pipe (bootstrap's stdin from a file or a terminal) cannot be peeked:
/// it is read as before, and what a voter that dies had read of it is lost (said once).
///
/// A frame is taken off the channel only once it is whole in it, so the channel must be able
/// to hold the largest frame whole: it is made that large (`F_SETPIPE_SZ`). Where the kernel
/// refuses (above `/proc/sys/fs/pipe-max-size`, 1 MiB, without privilege) the input is not
/// journaled either.
fn journaled_inputs(inputs: &mut [ExternalInput], plan: &VoterPlan) -> Result<(), VoterError> {
    for (input, port) in inputs.iter_mut().zip(&plan.inputs) {
        let fd = input.reader.as_fd();
        let Ok(size) = sys::pipe_size(fd) else {
            tracing::info!(input = %input.name, "input is not a pipe: not journaled (a voter restart may lose what it had read of it)");
            continue;
        };
        let want = (port.max_frame + frame::HEADER_LEN + 2 * frame::RESUME_LEN).next_power_of_two();
        if size < want {
            if let Err(e) = sys::set_pipe_size(fd, want) {
                tracing::warn!(input = %input.name, want, error = %e, "cannot make the input's pipe hold its largest frame: not journaled (a voter restart may lose what it had read of it)");
                continue;
            }
        }
        let pipe = crate::channel::Peek::for_channel(input.reader.as_fd())
            .map_err(io_err(format!("peek pipe for input `{}`", input.name)))?;
        input.peek = Some(crate::ports::Peeked {
            pipe,
            mark: input.reader.decoder.passed(),
            replay_left: 0,
            stalled_until: None,
        });
    }
    Ok(())
}

/// The answer-stamp page for the replicas of a sequential reactive voter (the only voter that
/// does not wake for every answer): the one bootstrap keeps across voters (`kept`; a
/// successor finds its predecessor's replicas' entries there), else one of its own. Programs
/// under the preload library get it too: the library stamps each line or frame that the
/// program's `write` completes (one whose output goes through C stdio stamps nothing, and the
/// voter goes on looking for its answers on the timer: `unwatched_turn_check`). `None` for
/// the other voters, or if it cannot be mapped (logged: the voter then looks for answers on
/// its timer, as without stamps).
fn answer_stamps(plan: &VoterPlan, kept: Option<OwnedFd>) -> Option<AnswerStamps> {
    let sequential = plan.mode == PlanMode::Reactive && plan.schedule == Schedule::Sequential;
    if !sequential {
        return None;
    }
    let page = match kept {
        Some(fd) => AnswerStamps::kept(fd),
        None => AnswerStamps::create(),
    };
    page.inspect_err(|e| {
        tracing::warn!(error = %e, "no answer-stamp page: turns are timed on the voter's timer")
    })
    .ok()
}

/// Starts every replica by exec, in slot order, each with a `start` event. `on_spawn(pid,
/// slot)` runs for each new process first (to apply scheduling settings).
fn start_replicas(
    plan: &VoterPlan,
    events: Option<&OwnedFd>,
    stamps: Option<BorrowedFd<'_>>,
    mut on_spawn: impl FnMut(libc::pid_t, usize),
) -> Result<Vec<Option<Replica>>, VoterError> {
    let mut slots: Vec<Option<Replica>> = (0..plan.replicas).map(|_| None).collect();
    for slot in 0..plan.replicas {
        let replica = match Replica::spawn(plan, slot, stamps) {
            Ok(r) => r,
            Err(e) => {
                // The ones already running must not outlive this failed start.
                for rep in slots.iter().flatten() {
                    rep.kill();
                }
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

/// Checks what a plan must hold before anything starts.
pub fn validate(plan: &VoterPlan) -> Result<(), VoterError> {
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
        PlanMode::Reactive if plan.rounds.is_empty() => {
            fail("reactive mode needs at least one input that starts rounds".into())
        }
        PlanMode::Stream if !plan.rounds.is_empty() => {
            fail("stream mode has no rounds; the plan lists some".into())
        }
        PlanMode::Stream if plan.window == 0 => fail("the stream window must be above 0".into()),
        PlanMode::Stream if plan.inputs.is_empty() => {
            fail("stream mode needs an input (its end ends the component)".into())
        }
        _ => Ok(()),
    }
}

/// Where this voter's fork-attempt nonces start: random (the hasher keys std draws from the
/// OS for each process). A voter that dies during a fork attempt leaves a donor that forks
/// for it; that child, with the donor's state at that moment, may reach the voter's successor
/// (on the donor's spare line, or connecting late), and counting from the same start the
/// successor's first attempt would carry its nonce and take it (found by
/// `voter_restart::a_fault_reported_again_by_the_voters_successor_is_kept_once`: a fork child
/// of the dead voter's attempt joined the successor and disagreed in the replayed round).
fn first_nonce() -> u32 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u64(s3res_protocol::clock::monotonic_ns());
    h.finish() as u32
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The voter's last line is its error's chain (`{:#}`): an I/O error is said once in it.
    #[test]
    fn an_io_error_is_said_once_in_the_report() {
        let e =
            io_err("starting replica 0 (/x/y.sh)")(std::io::Error::from_raw_os_error(libc::ENOENT));
        let report = format!("{:#}", anyhow::Error::from(e));
        assert_eq!(
            report,
            "starting replica 0 (/x/y.sh): No such file or directory (os error 2)"
        );
    }
}
