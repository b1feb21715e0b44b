//! Reactive mode (S³RES VoterM): a round per input frame, one answer per output.
//!
//! Between rounds the voter reads its external inputs. A frame on a round-starting input is
//! copied to every replica and opens a [`Round`]; other inputs are copied without one. During a
//! round, answers are collected; an output goes out as soon as [`RoundBallot::early`] says it
//! has a majority. A round closes when every trusted replica has answered, or at its deadline;
//! [`decide_round`] then says who was late, what goes out and whom to blame, and
//! [`Core::apply`] carries it out. Faults are recorded the moment they are seen (a dead
//! replica through its pidfd, not at the deadline) and the faulty replica is killed at once;
//! it is *replaced* after the round closes, when the healthy replicas are idle, so that a
//! donor is forked at a quiet point.

use std::time::Duration;

use crate::clock::{Deadlines, Instant, Timer};
use crate::core::{self, At, Core, Mode, Stop, VoterError};
use crate::decision::{decide_round, Answer, Decision, RoundBallot, RoundClose};
use crate::event::Cause;
use crate::plan::{Framing, VoterPlan};
use crate::recovery::DonorState;
use crate::replica::{PipeBacklog, Replica};
use crate::round::{Look, OutputSet, Round, Stall};
use crate::sched::Schedule;
use crate::starvation::{self, Seen, Window};
use crate::vote::{ReplicaSet, MAX_REPLICAS};
use replica_rt::contract::MAX_PORTS;

pub struct ReactiveVoter {
    core: Core,
    /// `answers[slot][output]`: where each replica's last frame on each output was read,
    /// voted in place (the buffers trade places with the pipes' read buffers, see
    /// [`Answer`]).
    answers: Vec<Vec<Answer>>,
    /// Where a frame that is itself a fault (an extra one, one before its round) is decoded,
    /// so that it overwrites no answer.
    set_aside: Vec<u8>,
    round: Option<Round>,
    rounds_started: u64,
    /// Every deadline the loop waits for (refilled from the state before each wait).
    timers: Deadlines,
    /// The decisions of the last round closed (kept for its capacity).
    close: RoundClose,
    /// The number of the round being closed (taken out of `round`: no early forwarding).
    closing: Option<u64>,
    /// Every replica of the round being closed missed its deadline (their `hang`s say so; a
    /// round still open tells by itself).
    all_late: bool,
    /// Per replica, what the looks before the open round's deadline saw it do, for the
    /// `hang` event's detail.
    evidence: [Option<Evidence>; MAX_REPLICAS],
    /// In a sequential round, the replicas whose answers the last wait watched (see
    /// [`ReactiveVoter::watched`]); `None`: it watched every replica.
    watching: Option<ReplicaSet>,
    /// The replicas that may share a CPU with the voter: pinned to one of its CPUs, or either
    /// of them not pinned.
    shares_cpu: ReplicaSet,
    /// When the last wait was to end at the latest (its nearest timer).
    wake_at: Option<Instant>,
    /// Replicas whose answer stamp was last found stale (older than a moment their turn was
    /// seen open): they are looked for on the timer again until a stamp is believed (see
    /// [`ReactiveVoter::unwatched_turn_check`]).
    stale_stamps: ReplicaSet,
    /// The last wait was for the open round's close alone: every answer had gone out (see
    /// [`ReactiveVoter::run_loop`]).
    waited_for_close_only: bool,
}

impl ReactiveVoter {
    /// Takes over the fds named in `plan`, binds the socket, and starts the replicas.
    pub fn start(plan: VoterPlan) -> Result<ReactiveVoter, VoterError> {
        let core = Core::start(plan)?;
        let n = core.plan.replicas;
        let shares_cpu = shares_cpu(&core.plan.cpus, core.plan.voter_cpu, n);
        let rounds_started = core.adopted_rounds;
        Ok(ReactiveVoter {
            answers: vec![vec![Answer::default(); core.plan.outputs.len()]; n],
            set_aside: Vec::new(),
            timers: Deadlines::new(core.plan.inputs.len(), n),
            core,
            round: None,
            rounds_started,
            close: RoundClose::default(),
            closing: None,
            all_late: false,
            evidence: [None; MAX_REPLICAS],
            watching: None,
            wake_at: None,
            waited_for_close_only: false,
            stale_stamps: ReplicaSet::EMPTY,
            shares_cpu,
        })
    }

    /// Runs until the inputs close (and the replicas have finished) or a stop is requested.
    pub fn run(self) -> Result<(), VoterError> {
        core::run(self)
    }

    // ----- input side -------------------------------------------------------------------

    /// Delivers buffered input frames to the replicas until one of them opens a round.
    fn start_rounds_from_buffered_input(&mut self) {
        if !self.core.faults.is_empty() {
            return;
        }
        if self.core.parks_lines() && self.core.answers_untaken() && !self.core.replaying() {
            return;
        }
        for i in 0..self.core.inputs.len() {
            while self.round.is_none() {
                let limit = input_backlog_limit(self.core.plan.inputs[i].max_frame);
                let Some(delivery) = self.core.deliver_next(i, Some(limit)) else {
                    break;
                };
                if let Some(expected) = self.core.inputs[i].round {
                    self.open_round(i, expected, delivery.members);
                }
                for (r, cause, detail) in delivery.faulty {
                    self.fault(r, cause, detail);
                }
            }
        }
    }

    fn open_round(&mut self, pair: usize, expected: OutputSet, members: ReplicaSet) {
        self.rounds_started += 1;
        self.evidence = [None; MAX_REPLICAS];
        let deadline = Instant::now() + self.allowance(members);
        self.core.monitors.clear_verdicts();
        self.round = Some(Round::new(
            self.rounds_started,
            pair,
            expected,
            deadline,
            members,
        ));
        if self.core.plan.schedule == Schedule::Sequential {
            self.next_turn();
        }
    }

    /// Every input that starts a round is closed (every input, if none starts one). (Called
    /// between rounds, after buffered frames were delivered, so nothing whole is left; a
    /// partial frame left behind can never complete.) Replicas answer only in rounds, so once
    /// no round can start their output is over, whatever their other inputs still carry.
    /// Waiting for those too would deadlock a loop: the navigator's `waypoints` come from a
    /// planner whose voter ends only when the navigator's `request` ends.
    fn all_inputs_done(&self) -> bool {
        let inputs = &self.core.inputs;
        let any_starts_round = inputs.iter().any(|i| i.round.is_some());
        inputs
            .iter()
            .filter(|i| !any_starts_round || i.round.is_some())
            .all(|i| i.reader.is_closed())
    }

    // ----- output side ------------------------------------------------------------------

    /// Why a frame of replica `r` on output `o` cannot be taken, if it cannot.
    fn unexpected(&self, r: usize, o: usize) -> Option<(Cause, &'static str)> {
        let unexpected = |why| Some((Cause::UnexpectedFrame, why));
        match self.round.as_ref() {
            _ if self.core.stop.is_some() => unexpected("frame after the inputs closed"),
            None => unexpected("frame outside any round"),
            Some(round) if !round.expects(o) => {
                unexpected("frame on an output this round does not expect")
            }
            Some(round) if round.has_answered(r, o) => {
                Some((Cause::ExtraFrame, "extra frame in one round"))
            }
            Some(round) if !round.members.contains(r) => {
                unexpected("frame from a replica that joined after the round began")
            }
            Some(_) => None,
        }
    }

    /// A ballot of the current round, as far as it got.
    fn ballot<'a>(&'a self, round: &'a Round, alarmed: &'a [OutputSet]) -> RoundBallot<'a> {
        let alive = self.trusted(round);
        RoundBallot {
            expected: round.expected,
            forwarded: round.forwarded,
            held: round.held,
            alive,
            answered: &round.answered[..self.core.slots.len()],
            answers: &self.answers,
            alarmed,
            fresh: self.core.fresh(),
        }
    }

    /// Per replica, the outputs on which its frame alarmed its detector (no detectors: none).
    fn alarmed(&self, round: &Round) -> [OutputSet; MAX_REPLICAS] {
        let mut alarmed = [0; MAX_REPLICAS];
        if !self.core.monitors.is_empty() {
            for (r, set) in alarmed.iter_mut().enumerate().take(self.core.slots.len()) {
                *set = round
                    .outputs()
                    .filter(|&o| self.core.monitors.alarmed(r, o))
                    .fold(0, |s, o| s | 1 << o);
            }
        }
        alarmed
    }

    /// Forwards output `o` of the current round as soon as some frame has a majority (or holds
    /// it back when it stands on one flagged replica's word).
    fn try_forward(&mut self, o: usize) {
        let Some(round) = self.round.as_ref() else {
            return;
        };
        let alarmed = self.alarmed(round);
        let Some(decision) = self.ballot(round, &alarmed).early(o) else {
            return;
        };
        let number = round.number;
        let round = self.round.as_mut().expect("checked above");
        match decision {
            Decision::HoldBack { .. } => round.held |= 1 << o,
            _ => round.forwarded |= 1 << o,
        }
        self.apply(o, number, &decision, false);
    }

    /// Carries out one decision on output `o` of round `number` (`sent`: its frame already
    /// went out during the round) and faults its suspects.
    fn apply(&mut self, o: usize, number: u64, decision: &Decision, sent: bool) {
        let answers = &self.answers;
        let frame = decision
            .frame(|r| Some(answers[r][o].as_slice()))
            .filter(|_| !sent);
        let blame = self.core.apply(o, At::Round(number), decision, frame);
        if let Some(blame) = blame {
            for r in blame.suspects.iter() {
                self.fault(r, blame.cause, blame.detail.clone());
            }
        }
    }

    /// When the event loop must wake up at the latest: the nearest of the open round's
    /// deadline and the graces of replicas whose output closed. The timers are refilled from
    /// that state before every wait, so none can be left behind stale.
    fn wakeup(&mut self) -> Option<Instant> {
        self.timers.cancel_all();
        if let Some(round) = &self.round {
            // A window before the deadline, the look at the replicas not done yet.
            let (first, second) = self.looks_before(round);
            let at = match (round.look, round.starved) {
                (None, _) => first,
                (Some(_), None) => second,
                (Some(_), Some(_)) => round.deadline,
            };
            // A turn whose answer does not wake the loop is looked for now and then.
            let at = match self.unwatched_turn_check(round) {
                Some(check) => at.min(check),
                None => at,
            };
            let at = match self.unwatched_peek_due(round) {
                Some(look) => at.min(Instant::now() + look),
                None => at,
            };
            self.timers.set(Timer::Round(round.pair), at);
        }
        for (r, rep) in self.core.slots.iter().enumerate() {
            if let Some(ends) = rep.as_ref().and_then(|rep| rep.output_grace_ends) {
                self.timers.set(Timer::Grace(r), ends);
            }
        }
        self.wake_at = self.timers.nearest().map(|(_, at)| at);
        self.wake_at
    }

    // ----- rounds -----------------------------------------------------------------------

    /// Closes the round when everyone trusted has answered, or when its deadline has passed.
    /// In a sequential round, moves the turn on instead (see [`ReactiveVoter::advance_turn`]).
    fn advance_round(&mut self) {
        self.read_unwatched();
        self.read_unwatched_peeks();
        let Some(round) = self.round.as_ref() else {
            return;
        };
        let all_done = round
            .members
            .iter()
            .filter(|&r| self.core.slots[r].is_some())
            .all(|r| round.is_done_by(r));
        if all_done {
            return self.close_round();
        }
        if self.core.plan.schedule == Schedule::Sequential {
            return self.advance_turn();
        }
        let now = Instant::now();
        if now < round.deadline {
            return self.looks_due(now);
        }
        if self.extend_for_the_starved(now) {
            return;
        }
        self.close_round();
    }

    /// How soon the open round must look at a pipe the wait does not watch (see
    /// [`unwatched_look`]) of a replica it waits for, if there is one.
    fn unwatched_peek_due(&self, round: &Round) -> Option<Duration> {
        if !self.core.parks_lines() {
            return None;
        }
        self.pending(round)
            .iter()
            .filter_map(|r| self.core.slots[r].as_ref())
            .flat_map(|rep| rep.outputs.iter().filter_map(unwatched_look))
            .min()
    }

    /// Reads the pipes [`unwatched_peek_due`](Self::unwatched_peek_due) is about.
    fn read_unwatched_peeks(&mut self) {
        let Some(round) = self.round.as_ref() else {
            return;
        };
        if self.unwatched_peek_due(round).is_none() {
            return;
        }
        for r in self.pending(round).iter() {
            let unwatched = self.core.slots[r]
                .as_ref()
                .is_some_and(|rep| rep.outputs.iter().any(|o| unwatched_look(o).is_some()));
            if unwatched {
                self.last_look(r);
            }
            if self.round.is_none() {
                return;
            }
        }
    }

    /// Whether new input may be taken: only between rounds and when downstream keeps up
    /// (back-pressure instead of unbounded buffering), and not while a fault waits for its
    /// recovery.
    fn takes_input(&self) -> bool {
        let backlog = self.core.outputs.iter().any(|o| o.writer.has_pending());
        self.round.is_none() && self.core.faults.is_empty() && !backlog
    }

    /// One read of every input the wait would watch (see `PollSet::reset`), without the wait.
    fn read_inputs_now(&mut self) {
        if !self.takes_input() || self.core.stop.is_some() {
            return;
        }
        let now = Instant::now();
        for input in &mut self.core.inputs {
            if input.may_read(now) {
                input.read();
            }
        }
    }

    /// Whose output pipes the next wait watches. Every replica's, except in a sequential
    /// round: there the answer that can complete the next decision, and the answer of the
    /// replica whose turn it is if the voter is pinned off that replica's CPU.
    ///
    /// Replicas sharing a CPU run their turns in slot order, and the voter outranks them. On
    /// their CPU, every answer the voter waits for preempts the replica that wrote it before
    /// that replica can block on its next input: the voter runs, finds nothing to decide,
    /// sleeps, and the replica runs again only to block. In a TMR round the first answer never
    /// decides anything (a majority needs two), so waking for it cost a voter turn and two
    /// context switches per round (9 switches a TMR round trip against the C floor's 6). The
    /// answers not watched are read whenever the loop wakes (`read_unwatched`): at the answer
    /// that completes a majority, a death (pidfds are always watched), a deadline, a look, or
    /// the turn check ([`unwatched_turn_check`](Self::unwatched_turn_check)), which bounds how
    /// late the next turn's deadline starts. On another CPU, the voter's wake-up preempts no
    /// replica, and the turn's answer is watched so that the next turn starts on time.
    fn watched(&self) -> ReplicaSet {
        let all = ReplicaSet::first(self.core.slots.len());
        let Some(round) = self.round.as_ref() else {
            return all;
        };
        if self.core.plan.schedule != Schedule::Sequential {
            return all;
        }
        let pending = self.pending(round);
        if pending.is_empty() {
            return all;
        }
        let k = if round.expected & !(round.forwarded | round.held) == 0 {
            // Everything went out: only the round's close is left, at the last answer.
            pending.len() - 1
        } else {
            // Answers still missing for a majority if every one agreed: the one that brings
            // the count there is watched (with disagreement, later ones; the last always is).
            let trusted = self.trusted(round).len();
            let done = trusted - pending.len();
            let missing = (trusted / 2 + 1).saturating_sub(done).max(1);
            missing.min(pending.len()) - 1
        };
        let Some(decider) = pending.iter().nth(k) else {
            return all;
        };
        let watched = ReplicaSet::EMPTY.with(decider);
        match round.turn {
            Some(t) if !self.shares_cpu.contains(t) => watched.with(t),
            _ => watched,
        }
    }

    /// The members of `round` still trusted.
    fn trusted(&self, round: &Round) -> ReplicaSet {
        round
            .members
            .iter()
            .filter(|&r| self.core.slots[r].is_some())
            .fold(ReplicaSet::EMPTY, ReplicaSet::with)
    }

    /// The trusted members of `round` that have not answered everything (turn order is slot
    /// order).
    fn pending(&self, round: &Round) -> ReplicaSet {
        self.trusted(round)
            .iter()
            .filter(|&r| !round.is_done_by(r))
            .fold(ReplicaSet::EMPTY, ReplicaSet::with)
    }

    /// Reads the answers that did not wake the loop (see [`watched`](Self::watched)): of the
    /// pending replicas whose turn comes before a watched one's (they ran first), or of
    /// every pending one when a timer woke the loop. (Not of the others after any wake-up:
    /// right after the voter delivered an input, on the replicas' CPU, nobody has answered,
    /// and each read would be a wasted system call.)
    fn read_unwatched(&mut self) {
        let Some(round) = self.round.as_ref() else {
            return;
        };
        let Some(watched) = self.watching else {
            return;
        };
        let last_watched = watched.iter().last().unwrap_or(0);
        let read_at = Instant::now();
        let timer_due = self.wake_at.is_some_and(|at| read_at >= at);
        let unwatched = self
            .pending(round)
            .iter()
            .filter(|&r| timer_due || (r < last_watched && !watched.contains(r)))
            .fold(ReplicaSet::EMPTY, ReplicaSet::with);
        for r in unwatched.iter() {
            self.last_look(r);
            if self.round.is_none() {
                return;
            }
        }
        // The turn was still open when these reads began, if they found it so (if they found
        // it over, the last time it was seen open stays the bound of when it ended: see
        // `turn_ended_at`).
        if timer_due {
            if let Some(round) = self.round.as_mut() {
                if round.turn.is_some_and(|t| !round.is_done_by(t)) {
                    round.checked = Some(read_at);
                }
            }
        }
    }

    /// When the loop must wake to see whether the replica whose turn it is has answered, if
    /// its answer does not wake the loop: half a look window after the last look at the
    /// pipes (`timeout_us / 20`, at least 50 µs), so the next turn's deadline starts at most
    /// that late (never early: a turn is never shortened). A fault-free round is over long
    /// before; the loop's timer (`ports::WakeTimer`) stays armed across rounds, so the check
    /// costs no system call per round, but the timer expires, for nothing, in whatever round
    /// runs once per half window: on one CPU, the round trip's tail (results.md, stop 39).
    fn unwatched_turn_check(&self, round: &Round) -> Option<Instant> {
        let turn = round.turn?;
        // What this wait watches (`build_poll_set` ran just before): `None` is everyone.
        if self.watching.is_none_or(|watched| watched.contains(turn)) {
            return None;
        }
        // A replica that stamps its answers needs no check: whenever the loop finds its
        // answer, the stamp says when its turn ended (see `turn_ended_at`). Unless its last
        // stamp was stale (a program that writes part of its output past the preload
        // library, or a faulty replica): then its turn ends when the loop looks, and without
        // the check a hang of the next turn would be found up to a whole turn later.
        if self.answer_stamp(turn).is_some() && !self.stale_stamps.contains(turn) {
            return None;
        }
        let since = round.checked?;
        Some(since + self.look_window() / 2)
    }

    /// Before a deadline: the two looks at the timed replicas, when due (see
    /// `starvation.rs`).
    fn looks_due(&mut self, now: Instant) {
        let Some(round) = self.round.as_ref() else {
            return;
        };
        let (first, second) = self.looks_before(round);
        match (round.look, round.starved) {
            // (A first look cannot come a window late: by then the deadline has come and it
            // is missed, which moves the deadline on by itself.)
            (None, _) if now >= first => self.look_at_late(now),
            (Some(look), None) if now >= second => {
                self.note_look_late(now.saturating_duration_since(second.max(look.done)));
                let starved = self.second_look(now);
                self.raise_the_starved_turn(starved);
            }
            _ => {}
        }
    }

    /// Keeps how late the voter took its second look before the open deadline: a voter held
    /// up itself did not see the window (`starvation::voter_held_up`).
    fn note_look_late(&mut self, late: Duration) {
        if let Some(round) = self.round.as_mut() {
            round.looked_late = round.looked_late.max(late);
        }
    }

    /// The second look: judges the window since the first (see [`judge_late`](Self::judge_late))
    /// and keeps the verdict for the deadline.
    fn second_look(&mut self, now: Instant) -> ReplicaSet {
        let starved = self.judge_late(now);
        if let Some(round) = self.round.as_mut() {
            round.starved = Some(starved);
        }
        starved
    }

    /// How long before a deadline the replicas not done yet are looked at.
    fn look_window(&self) -> Duration {
        starvation::window(Duration::from_micros(self.core.plan.timeout_us))
    }

    /// When the two looks before `round`'s deadline are due: the first a window before it,
    /// the second just before it.
    fn looks_before(&self, round: &Round) -> (Instant, Instant) {
        let window = self.look_window();
        (
            round.deadline - window,
            round.deadline - starvation::second_look(window),
        )
    }

    /// The replicas the open round's deadline is for: those trusted that have not answered
    /// everything (a sequential round: the one whose turn it is, if it has not).
    fn timed(&self) -> ReplicaSet {
        let Some(round) = self.round.as_ref() else {
            return ReplicaSet::EMPTY;
        };
        self.pending(round)
            .iter()
            .filter(|&r| match self.core.plan.schedule {
                Schedule::Sequential => round.turn == Some(r),
                _ => true,
            })
            .fold(ReplicaSet::EMPTY, |set, r| set.with(r))
    }

    /// Records what the replicas not done yet have run and waited so far (see
    /// `starvation.rs`).
    fn look_at_late(&mut self, now: Instant) {
        // The window starts before the reads (the first look of a replica opens its task
        // clock, 20–260 µs), and so does the wait it is judged by; its run time is judged
        // over the span its clock was read over (see `starvation.rs`).
        let mut look = Look {
            at: now,
            done: now,
            times: [None; MAX_REPLICAS],
        };
        for r in self.timed().iter() {
            look.times[r] = self.core.slots[r]
                .as_ref()
                .and_then(Replica::sched_times)
                .map(|t| (t, Instant::now()));
        }
        look.done = Instant::now();
        if let Some(round) = self.round.as_mut() {
            round.look = Some(look);
        }
    }

    /// Just before the deadline (so that the reads cost the deadline nothing): which of the
    /// replicas not done yet could not run since the look (see `starvation.rs`). Keeps what
    /// each did for the `hang` event's detail.
    fn judge_late(&mut self, now: Instant) -> ReplicaSet {
        let Some(look) = self.round.as_ref().and_then(|rd| rd.look) else {
            return ReplicaSet::EMPTY;
        };
        let span = now.saturating_duration_since(look.at);
        let mut stalls = self
            .round
            .as_ref()
            .map_or([Stall::default(); MAX_REPLICAS], |rd| rd.stalls);
        let mut starved = ReplicaSet::EMPTY;
        for r in self.timed().iter() {
            let Some(rep) = self.core.slots[r].as_ref() else {
                continue;
            };
            let (Some((first, before_at)), Some(second)) = (look.times[r], rep.sched_times())
            else {
                continue;
            };
            let (before, after) = (first.times, second.times);
            let held = first.held.max(second.held);
            let clocked = Instant::now().saturating_duration_since(before_at);
            let mut state = None;
            let runnable = || {
                state = replica_rt::sys::process_state(rep.pid);
                state == Some('R')
            };
            let own = starvation::judge(before, after, span, clocked, runnable);
            let own = starvation::cpu_held(own, held, span);
            let verdict = stalls[r].verdict(own);
            // Asleep and about to be blamed: where it sleeps says why it did not answer.
            let asleep = matches!((verdict, state), (Window::HadItsChance, Some(s)) if s != 'R');
            let wchan = asleep.then(|| replica_rt::sys::wchan(rep.pid)).flatten();
            let evidence = Evidence {
                seen: Seen {
                    state,
                    wchan,
                    on_clock: rep.times_on_clock(),
                    held_us: held.as_micros() as u64,
                    ..Seen::between(before, after, span, clocked)
                },
                pipes_then: asleep.then(|| rep.pipe_backlog()),
            };
            let waited = Duration::from_nanos(after.wait_ns.saturating_sub(before.wait_ns));
            tracing::trace!(
                target: "s3res_voter::starvation",
                replica = r,
                seen = %evidence,
                ?own,
                ?verdict,
                came_back = stalls[r].came_back,
                starved_for_us = stalls[r].starved_for.as_micros() as u64,
                "window judged"
            );
            self.evidence[r] = Some(evidence);
            stalls[r] = stalls[r].after_window(own, waited, span);
            if verdict.starved() {
                starved = starved.with(r);
            }
        }
        if let Some(round) = self.round.as_mut() {
            round.stalls = stalls;
        }
        starved
    }

    /// At the deadline: the late replicas that could not run over the window before it get
    /// one window more (within [`starvation::MAX_EXTENSION`] per round), and those that could
    /// are blamed now. `true` if the round stays open.
    fn extend_for_the_starved(&mut self, now: Instant) -> bool {
        // The voter woke up too late for the second look: it looks now, before its last reads
        // of the pipes, never after them. The host that held the voter often held the
        // replicas too, and they come back with it: one that answers between a read and a
        // look after it is found asleep, had its chance, and was blamed with its answer in
        // its pipe (traced, stop 61: the read found nothing 3 µs before the answer, the look
        // came 80 µs after it).
        if let Some((round, look)) = self
            .round
            .as_ref()
            .filter(|rd| rd.starved.is_none())
            .and_then(|rd| Some((rd, rd.look?)))
        {
            let (_, second) = self.looks_before(round);
            self.note_look_late(now.saturating_duration_since(second.max(look.done)));
            self.second_look(now);
        }
        for r in self.timed().iter() {
            self.last_look(r);
        }
        let late = self.timed();
        let window = self.look_window();
        let Some(round) = self.round.as_ref() else {
            return true;
        };
        if late.is_empty() || round.extended + window > starvation::MAX_EXTENSION {
            return false;
        }
        let number = round.number;
        let starved = match (round.look, round.starved) {
            // The voter took a look late: it was held up, and so was the machine.
            (Some(_), _) if starvation::voter_held_up(round.looked_late, window) => {
                tracing::debug!(
                    round = number,
                    late_us = round.looked_late.as_micros() as u64,
                    "the voter took its look before the deadline late: deadline moved on"
                );
                late
            }
            (Some(_), starved) => starved.unwrap_or(ReplicaSet::EMPTY),
            // The voter itself woke up past the first look: it was held up as much as anyone.
            (None, _) => {
                tracing::debug!(
                    round = number,
                    "the voter missed the look before the deadline: deadline moved on"
                );
                // A window the machine stalled in, for the voter too: it counts in the late
                // replicas' stretch without a CPU (`starvation::after_starving`).
                if let Some(round) = self.round.as_mut() {
                    for r in late.iter() {
                        round.stalls[r].passed_over(window);
                    }
                }
                late
            }
        };
        let starved = late
            .iter()
            .filter(|&r| starved.contains(r))
            .fold(ReplicaSet::EMPTY, |set, r| set.with(r));
        if starved.is_empty() {
            return false;
        }
        self.raise_the_starved_turn(starved);
        tracing::debug!(
            round = number,
            starved = ?starved.iter().collect::<Vec<_>>(),
            "late, but they could not run: deadline moved on"
        );
        // Blamed at the deadline, as without the look: those that had their chance.
        let on_turn = self.core.plan.schedule == Schedule::Sequential;
        let deadline = self.round.as_ref().map_or(now, |rd| rd.deadline);
        for r in late.iter().filter(|&r| !starved.contains(r)) {
            self.blame_late(r, number, on_turn, deadline);
        }
        self.look_at_late(now);
        if let Some(round) = self.round.as_mut() {
            round.deadline = now + window;
            round.extended += window;
            round.starved = None;
            round.looked_late = Duration::ZERO;
        }
        true
    }

    /// Sequential schedule: the replica whose turn it is keeps it until it has answered every
    /// expected output, leaves the quorum (faulty), or misses its own deadline, which makes
    /// it, and only it, the hung one. Then the next replica that has not answered yet gets
    /// the turn with a fresh deadline; when none is left, the round closes.
    fn advance_turn(&mut self) {
        let Some(round) = self.round.as_ref() else {
            return;
        };
        if let Some(t) = round.turn {
            if self.core.slots[t].is_some() && !round.is_done_by(t) {
                let now = Instant::now();
                if now < round.deadline {
                    return self.looks_due(now);
                }
                if self.extend_for_the_starved(now) {
                    return;
                }
                self.last_look(t);
                if let Some(round) = self.round.as_ref().filter(|rd| !rd.is_done_by(t)) {
                    let (number, deadline) = (round.number, round.deadline);
                    self.blame_late(t, number, true, deadline);
                }
            }
        }
        if !self.next_turn() {
            self.close_round();
        }
    }

    /// Gives the turn to the lowest-numbered member that is still trusted and has not
    /// answered yet and starts its deadline (puts the previous one back to rest if it had to
    /// be raised). Returns `false` when no such replica is left.
    ///
    /// The turn is not raised when it begins: turns go in slot order, and replicas rest at
    /// priorities that fall with the slot, so the replica whose turn it is already outranks
    /// every sibling that has not answered, and one that has answered is blocked on its next
    /// input. Only a sibling still running after its answer (a fault) can keep the turn off
    /// the CPU; the look before the deadline sees that and raises the turn then (see
    /// [`raise_the_starved_turn`](Self::raise_the_starved_turn)). So a fault-free round
    /// changes no priority (S³RES raised and lowered every replica in every round).
    fn next_turn(&mut self) -> bool {
        let Some(round) = self.round.as_ref() else {
            return false;
        };
        let previous = round.turn;
        let next = round
            .members
            .iter()
            .filter(|&r| self.core.slots[r].is_some())
            .find(|&r| !round.is_done_by(r) && Some(r) != previous);
        // The previous turn's replica, if it finished (rather than being taken out) and the
        // last wait did not watch for its answer (if it did, the loop woke at the answer).
        let finished = previous.filter(|&p| {
            round.is_done_by(p)
                && self.core.slots[p].is_some()
                && self.watching.is_some_and(|watched| !watched.contains(p))
        });
        let (open, number) = (round.checked, round.number);
        self.rest_the_raised_turn();
        let Some(next) = next else {
            return false;
        };
        let allowance = self.allowance(ReplicaSet::EMPTY.with(next));
        let now = Instant::now();
        let began = match finished {
            Some(p) => {
                let stamp = self.answer_stamp(p);
                let began = self.turn_ended_at(stamp, open, now);
                // A stamp refused (not after the turn was last seen open) is stale.
                let stale = began == now && stamp.is_some();
                self.stale_stamps = if stale {
                    self.stale_stamps.with(p)
                } else {
                    self.stale_stamps.without(p)
                };
                began
            }
            None => now,
        };
        if began < now {
            tracing::trace!(
                round = number,
                replica = finished,
                next,
                before_us = now.saturating_duration_since(began).as_micros() as u64,
                "turn ended at its answer stamp: the next turn's deadline runs from there"
            );
        }
        let round = self.round.as_mut().expect("checked above");
        round.turn = Some(next);
        round.deadline = began + allowance;
        round.checked = Some(began);
        // The looks and extensions were for the previous turn.
        round.look = None;
        round.starved = None;
        round.extended = Duration::ZERO;
        round.looked_late = Duration::ZERO;
        round.stalls = [Stall::default(); MAX_REPLICAS];
        true
    }

    /// When a finished turn ended, found over `now`: when it answered, by its answer `stamp`
    /// (`replica_rt::stamps`), if that falls between `open` (the last time the loop saw the
    /// turn open) and now; else now, as without stamps. The next turn's deadline starts
    /// there: when that turn really began, not when the loop happened to wake and see it; and
    /// never before a moment the loop saw that turn still open, whatever a faulty replica
    /// wrote in the page.
    fn turn_ended_at(&self, stamp: Option<u64>, open: Option<Instant>, now: Instant) -> Instant {
        let answered = stamp.map(|ns| {
            let age = replica_rt::sys::monotonic_ns().saturating_sub(ns);
            now - Duration::from_nanos(age)
        });
        turn_end(answered, open, now)
    }

    /// Replica `r`'s last answer stamp (`CLOCK_MONOTONIC` ns), if it stamps its answers.
    fn answer_stamp(&self, r: usize) -> Option<u64> {
        let pid = self.core.slots[r].as_ref()?.pid;
        self.core.stamps.as_ref()?.answered_at(pid as u32)
    }

    /// Sequential schedule: the replica whose turn it is could not run (a sibling that kept
    /// running after its answer outranks it): raises it above its siblings for the rest of its
    /// turn.
    fn raise_the_starved_turn(&mut self, starved: ReplicaSet) {
        let Some(round) = self.round.as_ref() else {
            return;
        };
        let Some(t) = round
            .turn
            .filter(|&t| starved.contains(t) && round.raised.is_none())
        else {
            return;
        };
        if !self.core.rt.can_raise() {
            return;
        }
        if let Some(pid) = self.core.slots[t].as_ref().map(|r| r.pid) {
            tracing::debug!(
                round = round.number,
                replica = t,
                "turn kept off its CPU: raised"
            );
            self.core.rt.raise(pid);
            if let Some(round) = self.round.as_mut() {
                round.raised = Some(t);
            }
        }
    }

    /// Puts the replica raised for its turn, if any, back to rest.
    fn rest_the_raised_turn(&mut self) {
        let Some(t) = self.round.as_mut().and_then(|rd| rd.raised.take()) else {
            return;
        };
        if let Some(pid) = self.core.slots[t].as_ref().map(|r| r.pid) {
            self.core.rt.rest(pid, t);
        }
    }

    /// How long `replicas` get to answer a round: `timeout_us`, or the start-up allowance
    /// (`start_timeout_ms`, if longer) while one of them has never answered. A replica started
    /// by exec is still being loaded, linked and locked into memory when its first input
    /// arrives; that is start-up, not a hang. A fork child is proven from the start.
    fn allowance(&self, replicas: ReplicaSet) -> Duration {
        let timeout = Duration::from_micros(self.core.plan.timeout_us);
        let starting = replicas
            .iter()
            .any(|r| self.core.slots[r].as_ref().is_some_and(|rep| !rep.proven));
        if starting {
            timeout.max(Duration::from_millis(self.core.plan.start_timeout_ms))
        } else {
            timeout
        }
    }

    /// At a deadline: one last look at replica `r`'s pipes (an answer may have arrived while
    /// the voter itself was busy, and the voter's lateness is not the replica's fault).
    fn last_look(&mut self, r: usize) {
        for o in 0..self.core.outputs.len() {
            self.on_output(r, o);
        }
    }

    /// Blames replica `r`, late in round `number` (`on_turn`: at the deadline of its own
    /// turn): `protocol` with a partial frame in its pipe, else `hang`.
    fn blame_late(&mut self, r: usize, number: u64, on_turn: bool, deadline: Instant) {
        let Some(rep) = self.core.slots[r].as_mut() else {
            return;
        };
        let proven = rep.proven;
        let never_started = if rep.read_started() {
            ""
        } else {
            " (its runtime never started: no s3res start handshake)"
        };
        let turn = if on_turn { " of its turn" } else { "" };
        let plan = &self.core.plan;
        let hang = match (proven, on_turn) {
            (false, _) => Cause::StartDeadline,
            (true, true) => Cause::TurnDeadline,
            (true, false) => Cause::Deadline,
        };
        let (cause, partial) = self.core.late_cause(r, hang);
        let detail = match (cause, partial) {
            (_, Some(o)) => format!(
                "partial frame on `{}` at the deadline{turn} in round {number}",
                plan.outputs[o].name
            ),
            (Cause::Deadline | Cause::TurnDeadline, None) => {
                let pipes = self.core.slots[r].as_ref().map(Replica::pipe_backlog);
                let backlog = pipes.map(|p| format!("; {p}")).unwrap_or_default();
                // How late the voter itself came to the deadline: a stalled voter, not the
                // replica.
                let voter_late = Instant::now()
                    .saturating_duration_since(deadline)
                    .as_micros();
                let seen = match self.evidence[r] {
                    Some(evidence) => format!(" ({evidence})"),
                    None => String::new(),
                };
                // Moved on for want of a CPU (its own or a sibling's): "within" the timeout is
                // then not the whole story.
                let extended = match self.round.as_ref().map_or(Duration::ZERO, |rd| rd.extended) {
                    d if d.is_zero() => String::new(),
                    d => format!(
                        " after its deadline was moved on {} µs for want of a CPU",
                        d.as_micros()
                    ),
                };
                // One replica late is a fault; all of them, round after round, is more often a
                // deadline shorter than the component's work (a newcomer's 300 ms component under
                // 250 ms lost every other input and its state to restarts, and nothing said why).
                // (In a sequential round the others may not have had their turn yet.)
                let none_answered = !on_turn
                    && self
                        .round
                        .as_ref()
                        .is_some_and(|rd| nobody_answered(rd, &self.core.slots));
                let all = if !(self.all_late || none_answered) {
                    String::new()
                } else if self.evidence[r].is_some_and(|e| waits_for_input(&e.seen, pipes)) {
                    // More time cannot help a replica that sleeps on an empty input: it took
                    // the round's input and sent nothing (a user's component that skipped
                    // every fifth answer was told to raise its timeout, 12 times of 12).
                    format!(
                        "; every replica missed this round, and this one waits for more input \
                         with none left to read: did it take the round's input and send nothing \
                         for it? A component sends one answer per input frame (an unmodified \
                         program one line per line), also when it has nothing new to say; if it \
                         needs more than {} µs for a round, raise its timeout_us",
                        plan.timeout_us
                    )
                } else {
                    format!(
                        "; every replica missed this round: if the component needs more than {} \
                         µs for a round, raise its timeout_us",
                        plan.timeout_us
                    )
                };
                format!(
                    "no answer within {} µs{turn}{extended} in round {number}{seen}{backlog}; \
                     the voter blamed it {voter_late} µs after the deadline{all}",
                    plan.timeout_us
                )
            }
            _ => format!(
                "no first answer within {} ms of start-up{turn} in round {number}{never_started}",
                plan.start_timeout_ms.max(plan.timeout_us / 1000)
            ),
        };
        self.fault(r, cause, detail);
    }

    /// Closes the round: the last look at every late replica, then [`decide_round`], then
    /// the late are blamed and every decision applied.
    fn close_round(&mut self) {
        let Some(round) = self.round.as_ref() else {
            return;
        };
        let late: Vec<usize> = round
            .members
            .iter()
            .filter(|&r| self.core.slots[r].is_some() && !round.is_done_by(r))
            .collect();
        for &r in &late {
            self.last_look(r);
        }
        self.rest_the_raised_turn();
        let Some(round) = self.round.take() else {
            return;
        };
        let alarmed = self.alarmed(&round);
        let mut close = std::mem::take(&mut self.close);
        decide_round(&self.ballot(&round, &alarmed), &mut close);
        // Faults from here on name this round, and forward nothing early: the decisions
        // below already count them.
        self.closing = Some(round.number);
        self.all_late = nobody_answered(&round, &self.core.slots);
        for r in close.late.iter() {
            self.blame_late(r, round.number, round.turn == Some(r), round.deadline);
        }
        self.all_late = false;
        let catching_up = self.core.catching_up();
        if !catching_up.is_empty() {
            // A replica started afresh whose frame went out has caught up (see
            // `Replica::catching_up`): from now on a dissent of it is a fault.
            for d in &close.decisions {
                let o = d.output;
                let answers = &self.answers;
                let Some(sent) = d.decision.frame(|r| Some(answers[r][o].as_slice())) else {
                    continue;
                };
                let agreed = catching_up
                    .iter()
                    .filter(|&r| {
                        round.answered[r] & (1 << o) != 0 && answers[r][o].as_slice() == sent
                    })
                    .fold(ReplicaSet::EMPTY, ReplicaSet::with);
                self.core.caught_up(agreed);
            }
        }
        for d in &close.decisions {
            self.apply(d.output, round.number, &d.decision, d.sent);
        }
        self.closing = None;
        self.close = close;
    }

    // ----- the end ---------------------------------------------------------------------

    /// Inputs closed: close the replicas' inputs, let them finish, flush what was voted.
    fn finish(&mut self) -> Result<(), VoterError> {
        tracing::debug!("inputs closed; flushing output and letting the replicas finish");
        // No recovery comes now: a fault's event held for one goes out before the waits below.
        self.core.release_faults();
        crate::ports::heartbeat_ending();
        // Voted output first: it is what the rest of the system is waiting for.
        let drain_deadline = Instant::now() + core::OUTPUT_DRAIN_LIMIT;
        for out in &mut self.core.outputs {
            out.drain(drain_deadline);
        }
        self.core.end_replica_inputs();
        self.core.drain_and_let_finish();
        self.core.output_failure()
    }

    /// Decodes every whole frame replica `r` sent on output `o` and takes it into the round.
    fn on_output(&mut self, r: usize, o: usize) {
        let Some(rep) = self.core.slots[r].as_mut() else {
            return;
        };
        let fill = rep.outputs[o].fill();
        let peeks = rep.outputs[o].peeks();
        if peeks && self.skip_committed_answers(r).is_err() {
            return;
        }
        loop {
            if peeks && self.round.is_none() && self.core.answer_before_its_round(r) {
                break;
            }
            let problem = self.unexpected(r, o);
            let Some(rep) = self.core.slots[r].as_mut() else {
                return;
            };
            // A frame that is a fault is decoded aside: the replica's answer stays as it was.
            let into = match problem {
                Some(_) => &mut self.set_aside,
                None => self.answers[r][o].storage(),
            };
            let at = match rep.outputs[o].next_answer_into(into) {
                Ok(Some(at)) => at,
                Ok(None) => break,
                Err(e) => {
                    let detail = format!("output `{}`: {e}", self.core.plan.outputs[o].name);
                    return self.fault(r, Cause::BadFrame, detail);
                }
            };
            if let Some((cause, problem)) = problem {
                let mut detail = format!("{problem} (output `{}`)", self.core.plan.outputs[o].name);
                if cause == Cause::ExtraFrame && self.core.plan.framing == Framing::Lines {
                    // The usual cause is the program, not a fault: say what the rule is.
                    detail.push_str(&format!(
                        ": a second line for one line in; `{}` must write exactly one line \
                         for each line it reads",
                        self.core.plan.exec.display()
                    ));
                }
                return self.fault(r, cause, detail);
            }
            let newly_proven = !std::mem::replace(&mut rep.proven, true);
            // The program speaks the protocol (the restart budget's message says otherwise).
            self.core.exec_answered = true;
            let pid = rep.pid;
            if newly_proven {
                self.core.journal_proven(r, pid);
            }
            self.answers[r][o].set(at);
            let round = self.round.as_mut().expect("unexpected() checked the round");
            round.answered[r] |= 1 << o;
            let number = round.number;
            // Every answer is scored, also when all agree: each replica's stream of frames
            // must be complete for the next delta to be meaningful.
            if let Some(verdict) = self
                .core
                .monitors
                .observe(r, o, self.answers[r][o].as_slice())
            {
                if verdict.alarm {
                    self.core.anomaly_event(r, pid, o, At::Round(number), false);
                }
            }
            self.try_forward(o);
        }
        core::after_read(self, r, o, fill);
    }

    /// An adopting voter of an unmodified program: the answers replica `r` gave to rounds its
    /// predecessor committed are still in its pipe (they are taken after the commit); they
    /// are passed over here, to be taken, never voted again.
    fn skip_committed_answers(&mut self, r: usize) -> Result<(), ()> {
        self.core
            .decode_committed_answers(r)
            .map_err(|detail| self.fault(r, Cause::BadFrame, detail))
    }
}

impl Mode for ReactiveVoter {
    fn core(&mut self) -> &mut Core {
        &mut self.core
    }

    fn run_loop(&mut self) -> Result<(), VoterError> {
        loop {
            if self.round.is_none() {
                let replace = self.core.stop.is_none();
                if self.core.parks_lines() {
                    self.core.fault_unread_lines();
                }
                core::recover_faulty(self, replace)?;
                self.core.journal_slots();
                self.core.commit(self.rounds_started);
                if self.core.parks_lines() {
                    if self.core.answers_untaken() {
                        crate::crashpoint::reached("round-committed");
                    }
                    self.core.take_committed_answers();
                }
                if self.core.stop == Some(Stop::Requested) {
                    return Ok(());
                }
                self.start_rounds_from_buffered_input();
                // A round that forwarded its answers at a majority closes at its last answer;
                // back to back, the next input came meanwhile (downstream answered the
                // forward). A round closes only after a wait (`advance_round`), so with no
                // round open here, a last wait for the close alone means such a close.
                // Reading the input now saves the wait that would only say so, one `ppoll` a
                // round. Where input comes periodically, the read finds nothing (one `tee` of a
                // journaled input, or `read`), and the wait follows. A round that closes at
                // its forward (SMR, DMR) is read for only after the wait: downstream has not
                // seen its answer yet.
                if std::mem::take(&mut self.waited_for_close_only) && self.round.is_none() {
                    self.read_inputs_now();
                    self.start_rounds_from_buffered_input();
                }
                if self.round.is_none() && self.core.stop.is_none() && self.all_inputs_done() {
                    self.core.stop = Some(Stop::InputsClosed);
                    return self.finish();
                }
            }
            core::wait_and_dispatch(self)?;
            if self.core.stop == Some(Stop::Requested) {
                return Ok(());
            }
            core::fault_closed_outputs(self);
            self.advance_round();
        }
    }

    /// Records the fault; a smaller quorum may decide a pending vote.
    fn fault(&mut self, r: usize, cause: Cause, detail: String) {
        let number = self.round.as_ref().map(|rd| rd.number).or(self.closing);
        if self.core.record_fault(r, cause, detail, number).is_none() {
            return;
        }
        let expected = self.round.as_ref().map_or(0, |rd| rd.expected);
        for o in (0..MAX_PORTS).filter(|o| expected & (1 << o) != 0) {
            self.try_forward(o);
        }
    }

    fn build_poll_set(&mut self) {
        self.waited_for_close_only = self
            .round
            .as_ref()
            .is_some_and(|round| round.expected & !round.forwarded == 0);
        let take_input = self.takes_input();
        self.core.reset_poll(take_input);
        let watched = self.watched();
        let all = ReplicaSet::first(self.core.slots.len());
        self.watching = (watched != all).then_some(watched);
        let core = &mut self.core;
        for (r, rep) in core.slots.iter().enumerate() {
            if let Some(rep) = rep {
                // A peeked pipe holding what was seen already would wake the wait at once,
                // every time: it is looked at on a timer instead (`unwatched_look`).
                let may_read =
                    |o: usize| watched.contains(r) && unwatched_look(&rep.outputs[o]).is_none();
                core.poll.add_replica(r, rep, true, may_read);
            }
        }
    }

    fn next_wakeup(&mut self) -> Option<Instant> {
        self.wakeup()
    }

    fn may_spin(&self) -> bool {
        self.round
            .as_ref()
            .is_some_and(|round| spins_for(self.pending(round), self.shares_cpu))
    }

    fn on_input_readable(&mut self, i: usize) {
        self.core.inputs[i].read();
        self.start_rounds_from_buffered_input();
    }

    fn on_replica_output(&mut self, r: usize, o: usize) {
        self.on_output(r, o);
    }

    fn on_replica_exit(&mut self, r: usize) {
        if self.core.slots[r].is_some() {
            self.fault(r, Cause::Died, core::DIED.into());
        }
    }

    /// Every trusted replica has answered the last round: no progress to tell them apart.
    fn progress(&self) -> [u64; MAX_REPLICAS] {
        [0; MAX_REPLICAS]
    }

    fn fork_into(&mut self, slot: usize, d: usize) -> Result<libc::pid_t, String> {
        let forked = self
            .core
            .fork(slot, d, DonorState::Quiet)
            .map_err(|e| e.to_string())?;
        let pid = forked.replica.pid;
        self.core.slots[slot] = Some(forked.replica);
        self.core.forget_stamps_of_the_gone();
        Ok(pid)
    }

    fn started_fresh(&mut self, _slot: usize) {}
}

/// Whether a wait for the answers of `pending` may spin before it sleeps (`spin.rs`): when
/// there are some and no replica runs on the voter's CPU (`shares_cpu`; see
/// `sched::voter_apart`).
fn spins_for(pending: ReplicaSet, shares_cpu: ReplicaSet) -> bool {
    !pending.is_empty() && shares_cpu.is_empty()
}

/// The replicas of a component placed on `cpus` (voter on `voter_cpu`) that may run on one of
/// the voter's CPUs (see `sched`): all unless both sides are pinned apart.
fn shares_cpu(cpus: &[usize], voter_cpu: Option<usize>, replicas: usize) -> ReplicaSet {
    let voter = crate::sched::voter_cpus(cpus, voter_cpu);
    (0..replicas)
        .filter(|&r| match crate::sched::replica_cpu(cpus, r) {
            Some(c) => voter.is_empty() || voter.contains(&c),
            None => true,
        })
        .fold(ReplicaSet::EMPTY, ReplicaSet::with)
}

/// An unmodified program's stdout is peeked, not read (see `lines.rs`): what it holds stays
/// there, and a pipe holding anything already seen would make every wait return at once. Such
/// a pipe is not watched, and is looked at on a timer while its replica's answer is awaited:
/// after [`PARTIAL_LOOK`] when it holds part of a line (the rest comes in microseconds:
/// `print` in `python3 -u` writes the text and the newline apart), after [`UNTAKEN_LOOK`] when
/// it holds whole answers not taken yet (a round replayed before its predecessor's commit).
fn unwatched_look(out: &crate::channel::FrameReader) -> Option<Duration> {
    if !out.peeks() {
        None
    } else if out.decoder.pending() > 0 {
        Some(PARTIAL_LOOK)
    } else if out.untaken_lines() > 0 {
        Some(UNTAKEN_LOOK)
    } else {
        None
    }
}

const PARTIAL_LOOK: Duration = Duration::from_micros(50);
const UNTAKEN_LOOK: Duration = Duration::from_millis(1);

/// When a turn ended: at its answer stamp `answered`, if that lies between `open` (a time
/// the turn was seen open) and `now`; else `now`.
fn turn_end(answered: Option<Instant>, open: Option<Instant>, now: Instant) -> Instant {
    match (answered, open) {
        (Some(at), Some(open)) if open <= at && at <= now => at,
        _ => now,
    }
}

/// How many bytes the voter queues for one replica input beyond what its pipe holds before
/// the replica counts as not taking its input (a `hang`): 64 frames of the channel's maximum,
/// and at least 4 MiB, so a burst of an upstream neighbour never trips it, while a replica
/// that stopped reading cannot make the voter's memory grow without bound.
fn input_backlog_limit(max_frame: usize) -> usize {
    (64 * (max_frame + replica_rt::frame::HEADER_LEN)).max(4 << 20)
}

/// What the looks before a round's deadline saw a late replica do, for its `hang` detail.
#[derive(Debug, Clone, Copy)]
struct Evidence {
    seen: Seen,
    /// Found asleep at the look just before the deadline: where its frames stood then (see
    /// [`Replica::pipe_backlog`]). Beside where they stand at the blame, it tells an answer
    /// already in the pipe a window before the deadline from one that came after it.
    pipes_then: Option<PipeBacklog>,
}

impl std::fmt::Display for Evidence {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.seen)?;
        match self.pipes_then {
            Some(then) => write!(f, "; at that look {then}"),
            None => Ok(()),
        }
    }
}

/// Whether a late replica, as the voter last saw it, sleeps on its input pipe with nothing
/// in it and nothing unread in its output, and ran not at all meanwhile: it is not working on
/// the round but waiting for the next input.
fn waits_for_input(seen: &Seen, pipes: Option<PipeBacklog>) -> bool {
    let asleep_on_a_pipe = seen.state == Some('S')
        && seen.ran_us == 0
        && seen.wchan.is_some_and(|w| w.as_str().contains("pipe_read"));
    asleep_on_a_pipe
        && pipes.is_some_and(|p| {
            p.input_unread == Some(0) && p.input_queued == 0 && p.output_unread == Some(0)
        })
}

/// Whether no trusted member of `round` has answered (and it has some): every replica missed
/// it, which the `hang`s say (see `ReactiveVoter::blame_late`).
fn nobody_answered(round: &Round, slots: &[Option<Replica>]) -> bool {
    let mut members = round.members.iter().filter(|&m| slots[m].is_some());
    members.clone().next().is_some() && members.all(|m| !round.is_done_by(m))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(slots: &[usize]) -> ReplicaSet {
        slots.iter().fold(ReplicaSet::EMPTY, |s, &r| s.with(r))
    }

    #[test]
    fn a_turn_ends_at_its_answer_stamp_only_between_its_last_sighting_open_and_now() {
        let now = Instant::now();
        let us = Duration::from_micros;
        let open = Some(now - us(1_000));
        // The stamp inside the bracket: the turn ended then, not when the loop found it.
        assert_eq!(turn_end(Some(now - us(900)), open, now), now - us(900));
        assert_eq!(turn_end(Some(now - us(1_000)), open, now), now - us(1_000));
        // Before the turn was last seen open (a stale or a forged stamp): now, as without.
        assert_eq!(turn_end(Some(now - us(1_001)), open, now), now);
        // No stamp, or no sighting to bound it by: now.
        assert_eq!(turn_end(None, open, now), now);
        assert_eq!(turn_end(Some(now - us(10)), None, now), now);
    }

    #[test]
    fn replicas_share_the_voters_cpu_unless_both_are_pinned_apart() {
        // Nothing pinned: anyone may run anywhere.
        assert_eq!(shares_cpu(&[], None, 3), set(&[0, 1, 2]));
        // Everything on CPU 0 (the voter goes to the component's list).
        assert_eq!(shares_cpu(&[0], None, 3), set(&[0, 1, 2]));
        assert_eq!(shares_cpu(&[0], Some(0), 3), set(&[0, 1, 2]));
        // Replicas on CPU 1, voter on CPU 0.
        assert_eq!(shares_cpu(&[1], Some(0), 3), ReplicaSet::EMPTY);
        // Replicas over CPUs 0 and 1 (0, 1, 0), voter on 1.
        assert_eq!(shares_cpu(&[0, 1], Some(1), 3), set(&[1]));
        // Voter pinned, replicas not: they may come to its CPU.
        assert_eq!(shares_cpu(&[], Some(0), 2), set(&[0, 1]));
    }

    #[test]
    fn a_wait_spins_only_for_answers_from_other_cpus() {
        // Voter on CPU 0, replicas on CPU 1: every wait in a round.
        let apart = shares_cpu(&[1], Some(0), 3);
        assert!(spins_for(set(&[0, 1, 2]), apart));
        assert!(spins_for(set(&[2]), apart));
        // Nobody to wait for (between rounds, for input): no spin.
        assert!(!spins_for(ReplicaSet::EMPTY, apart));
        // One CPU, or replicas not pinned: they run only when the voter sleeps.
        assert!(!spins_for(set(&[0]), shares_cpu(&[0], Some(0), 3)));
        assert!(!spins_for(set(&[0]), shares_cpu(&[], Some(0), 1)));
        // Replicas over CPUs 0 and 1 (0, 1, 0), voter on 1: replica 1 runs only when the
        // voter sleeps, and the voter does not tell its waits apart.
        let mixed = shares_cpu(&[0, 1], Some(1), 3);
        assert!(!spins_for(set(&[0, 2]), mixed));
        assert!(!spins_for(set(&[1, 2]), mixed));
        // As `sched::voter_apart` says, which bootstrap and the description check by.
        for (cpus, voter) in [
            (&[1][..], Some(0)),
            (&[0], Some(0)),
            (&[], Some(0)),
            (&[0, 1], Some(1)),
        ] {
            assert_eq!(
                shares_cpu(cpus, voter, 3).is_empty(),
                crate::sched::voter_apart(cpus, voter),
                "{cpus:?} {voter:?}"
            );
        }
    }

    #[test]
    fn the_first_replicas() {
        assert_eq!(ReplicaSet::first(0), ReplicaSet::EMPTY);
        assert_eq!(ReplicaSet::first(3), set(&[0, 1, 2]));
        assert_eq!(ReplicaSet::first(MAX_REPLICAS).len(), MAX_REPLICAS);
    }
}
