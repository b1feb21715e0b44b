//! The bookkeeping of stream mode (S³RES VoterD), without processes or pipes: which frame of
//! each output every replica has produced, which frames are decided, who is late. The event
//! loop in [`crate::stream`] feeds it frames and acts on what it says.
//!
//! Frames of an output are numbered 0, 1, 2, ... in the order each replica produces them. For
//! every output the ledger keeps
//! * `next`: the number of the next frame to decide (everything below is forwarded or withheld);
//! * per slot, `pos`: the number the slot's next frame will get;
//! * the *entries* `base..`: per frame, each slot's copy while it is undecided, the arrival time
//!   of each slot's copy, and the verdict once decided. Entries below every trusted slot's `pos`
//!   are dropped, so memory is bounded by the window (a slot `window` frames ahead of the
//!   slowest is not read: [`Ledger::may_read`]).

use std::collections::VecDeque;
use std::time::Duration;

use crate::clock::Instant;

use crate::decision::{decide, Decision};
use crate::vote::ReplicaSet;

/// What became of a frame number.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Verdict {
    Open,
    /// The majority's frame, kept to check the copies of replicas that were late.
    Forwarded(Vec<u8>),
    /// No two (no majority of) replicas agreed: nothing was forwarded, nobody blamed.
    Withheld,
}

#[derive(Debug)]
struct Entry {
    /// Each slot's copy, while undecided.
    frames: Vec<Option<Vec<u8>>>,
    /// When each slot's copy arrived (kept after the decision: it starts the laggards' clock).
    seen: Vec<Option<Instant>>,
    /// The slots whose copy the output's anomaly detector flagged ([`Ledger::flag_last`]).
    alarmed: ReplicaSet,
    verdict: Verdict,
}

impl Entry {
    fn new(n: usize) -> Self {
        Entry {
            frames: vec![None; n],
            seen: vec![None; n],
            alarmed: ReplicaSet::EMPTY,
            verdict: Verdict::Open,
        }
    }
}

#[derive(Debug)]
struct OutputLedger {
    next: u64,
    base: u64,
    entries: VecDeque<Entry>,
}

impl OutputLedger {
    fn entry(&self, index: u64) -> Option<&Entry> {
        index
            .checked_sub(self.base)
            .and_then(|k| self.entries.get(k as usize))
    }
}

/// What [`Ledger::accept`] found about a frame that came after its number was decided.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Arrival {
    /// Stored for the vote (or it agrees with the frame already forwarded, or that number was
    /// withheld and there is nothing to compare with).
    Fine,
    /// A late copy that differs from the frame the majority forwarded: an `sdc`.
    DiffersFromForwarded(u64),
    /// A late copy of the frame the majority forwarded (a replica whose state is lost has
    /// caught up when it sends one: see `Replica::catching_up`).
    MatchesForwarded,
}

/// One frame of an output, decided.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Decided {
    /// The frame's number on its output.
    pub index: u64,
    pub decision: Decision,
    /// The frame that goes out, if one does.
    pub frame: Option<Vec<u8>>,
    /// The watched slots whose copy is that frame (empty when none goes out).
    pub agreed: ReplicaSet,
}

/// A frame some replicas produced and others did not within the timeout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Overdue {
    pub output: usize,
    pub index: u64,
    /// Trusted slots that produced it.
    pub producers: ReplicaSet,
    /// Trusted slots that did not (and are being read).
    pub laggards: ReplicaSet,
}

impl Overdue {
    /// The documented rule: the larger side is right; on a tie (DMR) the laggards are blamed,
    /// as in S³RES, so that a hung replica can never stall the component. (When this says
    /// no, the voter still blames laggards that are not asleep: see `StreamVoter`'s deadline
    /// check.)
    pub fn blames_laggards(&self) -> bool {
        self.producers.len() >= self.laggards.len()
    }
}

#[derive(Debug)]
pub struct Ledger {
    n: usize,
    window: u64,
    outputs: Vec<OutputLedger>,
    /// `pos[slot][output]`: the number the slot's next frame on that output gets.
    pos: Vec<Vec<u64>>,
    /// `received[slot][output]`: frames received from the slot's current process. `pos -
    /// received` maps the process's own frame count onto the output's numbering.
    received: Vec<Vec<u64>>,
}

impl Ledger {
    pub fn new(replicas: usize, outputs: usize, window: usize) -> Self {
        Ledger {
            n: replicas,
            window: window.max(1) as u64,
            outputs: (0..outputs)
                .map(|_| OutputLedger {
                    next: 0,
                    base: 0,
                    entries: VecDeque::new(),
                })
                .collect(),
            pos: vec![vec![0; outputs]; replicas],
            received: vec![vec![0; outputs]; replicas],
        }
    }

    /// Number of the next frame to decide on `o`.
    pub fn next(&self, o: usize) -> u64 {
        self.outputs[o].next
    }

    /// Number the next frame of `slot` on `o` gets.
    pub fn pos(&self, slot: usize, o: usize) -> u64 {
        self.pos[slot][o]
    }

    /// Frames received from the current process of `slot` on `o`.
    pub fn received(&self, slot: usize, o: usize) -> u64 {
        self.received[slot][o]
    }

    fn slowest(&self, o: usize, alive: ReplicaSet) -> Option<u64> {
        alive.iter().map(|s| self.pos[s][o]).min()
    }

    /// Whether the voter should read `slot`'s output `o` now: not while it is `window` frames
    /// (or more) ahead of the slowest trusted replica.
    pub fn may_read(&self, slot: usize, o: usize, alive: ReplicaSet) -> bool {
        match self.slowest(o, alive) {
            Some(min) => self.pos[slot][o] < min + self.window,
            None => true,
        }
    }

    /// Whether `slot` is held back on some output (then it is not blamed for being late).
    pub fn held_back(&self, slot: usize, alive: ReplicaSet) -> bool {
        (0..self.outputs.len()).any(|o| !self.may_read(slot, o, alive))
    }

    /// Some trusted replica has produced a frame another has not, or a frame is undecided.
    pub fn out_of_step(&self, alive: ReplicaSet) -> bool {
        self.outputs.iter().enumerate().any(|(o, out)| {
            let mut positions = alive.iter().map(|s| self.pos[s][o]);
            let first = positions.next();
            positions.any(|p| Some(p) != first)
                || out
                    .entries
                    .iter()
                    .any(|e| e.verdict == Verdict::Open && e.seen.iter().any(Option::is_some))
        })
    }

    /// How far `slot` has got: its frames over all outputs.
    pub fn progress(&self, slot: usize) -> u64 {
        self.pos[slot].iter().sum()
    }

    /// The trusted slot furthest behind (fewest frames over all outputs), if they differ.
    pub fn laggard(&self, alive: ReplicaSet) -> Option<usize> {
        let total = |s: usize| self.progress(s);
        let lowest = alive.iter().min_by_key(|&s| (total(s), s))?;
        let highest = alive.iter().map(total).max()?;
        (total(lowest) < highest).then_some(lowest)
    }

    /// Takes frame `pos(slot, o)` of `slot`.
    pub fn accept(&mut self, slot: usize, o: usize, frame: &[u8], now: Instant) -> Arrival {
        let index = self.pos[slot][o];
        self.pos[slot][o] += 1;
        self.received[slot][o] += 1;
        let n = self.n;
        let out = &mut self.outputs[o];
        let Some(k) = index.checked_sub(out.base) else {
            // Behind every trusted replica's position: cannot happen for a trusted slot.
            return Arrival::Fine;
        };
        while out.entries.len() <= k as usize {
            out.entries.push_back(Entry::new(n));
        }
        let entry = &mut out.entries[k as usize];
        entry.seen[slot] = Some(now);
        match &entry.verdict {
            Verdict::Open => {
                entry.frames[slot] = Some(frame.to_vec());
                Arrival::Fine
            }
            Verdict::Forwarded(winner) if winner.as_slice() != frame => {
                Arrival::DiffersFromForwarded(index)
            }
            Verdict::Forwarded(_) => Arrival::MatchesForwarded,
            Verdict::Withheld => Arrival::Fine,
        }
    }

    /// Marks `slot`'s latest frame on `o` as flagged by the anomaly detector. A flagged copy
    /// of an undecided frame changes how it is decided (see [`Decision::HoldBack`] and
    /// [`Decision::Attribute`]); on a decided frame the mark changes nothing.
    pub fn flag_last(&mut self, slot: usize, o: usize) {
        let Some(index) = self.pos[slot][o].checked_sub(1) else {
            return;
        };
        let out = &mut self.outputs[o];
        if let Some(e) = index
            .checked_sub(out.base)
            .and_then(|k| out.entries.get_mut(k as usize))
        {
            e.alarmed = e.alarmed.with(slot);
        }
    }

    /// Decides the next frame of `o` if it can be decided now (call until `None`).
    ///
    /// The anomaly detector's marks count where the vote cannot decide alone, as in reactive
    /// mode: a majority of one whose copy is flagged is held back, and two differing copies of
    /// which exactly one is flagged forward the other. With three or more copies the vote (and
    /// the bitwise majority) decides; marks are only logged.
    /// `watch`: the slots whose agreement the caller wants in [`Decided::agreed`] (the
    /// others' copies are not compared with the frame that goes out).
    pub fn decide(
        &mut self,
        o: usize,
        alive: ReplicaSet,
        fresh: ReplicaSet,
        watch: ReplicaSet,
    ) -> Option<Decided> {
        let out = &mut self.outputs[o];
        let k = out.next.checked_sub(out.base)? as usize;
        let entry = out.entries.get_mut(k)?;
        let decision = decide(&entry.frames, alive, entry.alarmed, fresh)?;
        let frame = decision
            .frame(|r| entry.frames.get(r).and_then(|f| f.as_deref()))
            .map(<[u8]>::to_vec);
        let agreed = match &frame {
            Some(f) => watch
                .iter()
                .filter(|&r| entry.frames.get(r).and_then(Option::as_ref) == Some(f))
                .fold(ReplicaSet::EMPTY, ReplicaSet::with),
            None => ReplicaSet::EMPTY,
        };
        entry.verdict = match &frame {
            Some(f) => Verdict::Forwarded(f.clone()),
            None => Verdict::Withheld,
        };
        entry.frames.iter_mut().for_each(|f| *f = None);
        let index = out.next;
        out.next += 1;
        Some(Decided {
            index,
            decision,
            frame,
            agreed,
        })
    }

    /// Drops decided entries every trusted slot is past.
    pub fn trim(&mut self, alive: ReplicaSet) {
        for o in 0..self.outputs.len() {
            let slowest = self.slowest(o, alive);
            let out = &mut self.outputs[o];
            while out.base < out.next && !matches!(slowest, Some(min) if out.base >= min) {
                out.entries.pop_front();
                out.base += 1;
            }
        }
    }

    /// Moves every arrival time `by` later: the voter was away (recovering a replica, during
    /// which it neither fed the replicas' inputs nor read their outputs), and that time must
    /// not count against the laggards' deadlines.
    pub fn postpone(&mut self, by: std::time::Duration) {
        for out in &mut self.outputs {
            for entry in &mut out.entries {
                for seen in entry.seen.iter_mut().flatten() {
                    *seen += by;
                }
            }
        }
    }

    /// `slot` is no longer trusted: its undecided copies and arrival times no longer count.
    pub fn forget(&mut self, slot: usize) {
        for out in &mut self.outputs {
            for e in &mut out.entries {
                e.frames[slot] = None;
                e.seen[slot] = None;
                e.alarmed = e.alarmed.without(slot);
            }
        }
    }

    /// `slot` now holds a fork child of `donor` whose process had sent `frames_sent[o]` frames
    /// on each output. The child's next frame on `o` is numbered like the donor's frame of that
    /// count; the donor's frames before it (which the child's state is already past) are
    /// copied to the child as if it had produced them. The donor's frames up to there must
    /// have been received already ([`Ledger::received`] ≥ `frames_sent`).
    pub fn join_from(&mut self, slot: usize, donor: usize, frames_sent: &[u64]) {
        for (o, &sent) in frames_sent.iter().enumerate() {
            let offset = self.pos[donor][o] - self.received[donor][o];
            let child_pos = offset + sent;
            self.pos[slot][o] = child_pos;
            self.received[slot][o] = sent;
            let out = &mut self.outputs[o];
            for index in out.base.max(out.next)..child_pos {
                let Some(e) = out.entries.get_mut((index - out.base) as usize) else {
                    break;
                };
                e.frames[slot] = e.frames[donor].clone();
                e.seen[slot] = e.seen[donor];
                if e.alarmed.contains(donor) {
                    e.alarmed = e.alarmed.with(slot);
                }
            }
        }
    }

    /// A voter that took over from one that died: every output goes on from the frame its
    /// predecessor committed as forwarded (`next[o]`); each adopted slot's process, whose
    /// frame 0 is frame `offsets[o]` of the output, sends again what it kept from there (see
    /// `replica_rt`'s output history). Returns, per adopted slot and output, the count of the
    /// process's frames already decided: its decoder drops those.
    pub fn resume(&mut self, next: &[u64], offsets: &[Option<Vec<u64>>]) -> Vec<Vec<u64>> {
        for (out, &n) in self.outputs.iter_mut().zip(next) {
            out.next = n;
            out.base = n;
            out.entries.clear();
        }
        let mut skip = vec![vec![0; self.outputs.len()]; self.n];
        for (slot, off) in offsets.iter().enumerate() {
            let Some(off) = off else { continue };
            for (o, &n) in next.iter().enumerate() {
                let offset = off.get(o).copied().unwrap_or(0);
                let pos = n.max(offset);
                self.pos[slot][o] = pos;
                self.received[slot][o] = pos - offset;
                skip[slot][o] = pos - offset;
            }
        }
        skip
    }

    /// `slot` now holds a fresh process (exec, state lost): its first frame on each output is
    /// taken as the next one to decide.
    pub fn start_fresh(&mut self, slot: usize) {
        for o in 0..self.outputs.len() {
            self.pos[slot][o] = self.outputs[o].next;
            self.received[slot][o] = 0;
        }
    }

    /// When the earliest laggard deadline falls: `timeout` after the first trusted copy of the
    /// oldest frame some trusted, read replica has not produced. `None` while nobody is ahead.
    pub fn next_deadline(&self, alive: ReplicaSet, timeout: Duration) -> Option<Instant> {
        (0..self.outputs.len())
            .filter_map(|o| self.oldest_owed(o, alive).map(|(_, since)| since + timeout))
            .min()
    }

    /// The oldest frame of `o` owed by a trusted replica that is being read, and since when.
    fn oldest_owed(&self, o: usize, alive: ReplicaSet) -> Option<(u64, Instant)> {
        let read = alive
            .iter()
            .filter(|&s| !self.held_back(s, alive))
            .fold(ReplicaSet::EMPTY, ReplicaSet::with);
        let out = &self.outputs[o];
        let lowest = read.iter().map(|s| self.pos[s][o]).min()?;
        let mut index = lowest.max(out.base);
        while let Some(e) = out.entry(index) {
            let since = alive.iter().filter_map(|s| e.seen[s]).min();
            let owed = read.iter().any(|s| self.pos[s][o] <= index);
            if let (Some(since), true) = (since, owed) {
                return Some((index, since));
            }
            index += 1;
        }
        None
    }

    /// The oldest frame that is overdue at `now`, on any output.
    pub fn overdue(&self, alive: ReplicaSet, timeout: Duration, now: Instant) -> Option<Overdue> {
        (0..self.outputs.len())
            .filter_map(|o| {
                let (index, since) = self.oldest_owed(o, alive)?;
                (now >= since + timeout).then_some((o, index, since))
            })
            .min_by_key(|&(_, _, since)| since)
            .map(|(output, index, _)| {
                let mut producers = ReplicaSet::EMPTY;
                let mut laggards = ReplicaSet::EMPTY;
                for s in alive.iter() {
                    if self.pos[s][output] > index {
                        producers = producers.with(s);
                    } else if !self.held_back(s, alive) {
                        laggards = laggards.with(s);
                    }
                }
                Overdue {
                    output,
                    index,
                    producers,
                    laggards,
                }
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(ids: &[usize]) -> ReplicaSet {
        ids.iter().fold(ReplicaSet::EMPTY, |s, &i| s.with(i))
    }

    fn decide_all(l: &mut Ledger, o: usize, alive: ReplicaSet) -> Vec<Decided> {
        std::iter::from_fn(|| l.decide(o, alive, ReplicaSet::EMPTY, alive)).collect()
    }

    fn forward(
        index: u64,
        frame: &[u8],
        winner: usize,
        dissent: ReplicaSet,
        agreed: ReplicaSet,
    ) -> Decided {
        Decided {
            index,
            decision: Decision::Forward { winner, dissent },
            frame: Some(frame.to_vec()),
            agreed,
        }
    }

    fn withheld(index: u64, answered: ReplicaSet) -> Decided {
        Decided {
            index,
            decision: Decision::Withhold { answered },
            frame: None,
            agreed: ReplicaSet::EMPTY,
        }
    }

    fn held_back(index: u64, suspect: usize) -> Decided {
        Decided {
            index,
            decision: Decision::HoldBack { suspect },
            frame: None,
            agreed: ReplicaSet::EMPTY,
        }
    }

    const T: Duration = Duration::from_millis(100);

    #[test]
    fn majority_forwards_each_frame_once_in_order() {
        let mut l = Ledger::new(3, 1, 8);
        let all = set(&[0, 1, 2]);
        let t = Instant::now();
        l.accept(0, 0, b"a", t);
        l.accept(0, 0, b"b", t);
        assert!(
            decide_all(&mut l, 0, all).is_empty(),
            "one copy decides nothing"
        );
        l.accept(1, 0, b"a", t);
        let d = decide_all(&mut l, 0, all);
        assert_eq!(d, [forward(0, b"a", 0, ReplicaSet::EMPTY, set(&[0, 1]))]);
        l.accept(1, 0, b"b", t);
        assert_eq!(decide_all(&mut l, 0, all).len(), 1);
        assert_eq!(l.next(0), 2);
        // The third replica is late; its copies are checked against what was forwarded.
        assert_eq!(l.accept(2, 0, b"a", t), Arrival::MatchesForwarded);
        assert_eq!(l.accept(2, 0, b"X", t), Arrival::DiffersFromForwarded(1));
    }

    #[test]
    fn minority_is_dissent_and_no_majority_is_withheld() {
        let mut l = Ledger::new(3, 1, 8);
        let all = set(&[0, 1, 2]);
        let t = Instant::now();
        for (s, f) in [(0, "x"), (1, "y"), (2, "x")] {
            l.accept(s, 0, f.as_bytes(), t);
        }
        assert_eq!(
            decide_all(&mut l, 0, all),
            [forward(0, b"x", 0, set(&[1]), set(&[0, 2]))]
        );
        // No whole frame has a majority, every bit does ('p' 0x70, 'q' 0x71, 'r' 0x72).
        for (s, f) in [(0, "p"), (1, "q"), (2, "r")] {
            l.accept(s, 0, f.as_bytes(), t);
        }
        match &decide_all(&mut l, 0, all)[..] {
            [Decided {
                index: 1,
                decision: Decision::Rebuild(rebuilt),
                ..
            }] => {
                assert_eq!(
                    (&rebuilt.frame[..], rebuilt.dissent),
                    (&b"p"[..], set(&[1, 2]))
                );
            }
            other => panic!("{other:?}"),
        }
        // Not even that (lengths differ): withheld.
        for (s, f) in [(0, "p"), (1, "qq"), (2, "r")] {
            l.accept(s, 0, f.as_bytes(), t);
        }
        assert_eq!(decide_all(&mut l, 0, all), [withheld(2, all)]);
        assert_eq!(l.next(0), 3, "a withheld frame does not stall the output");
    }

    #[test]
    fn time_the_voter_was_away_does_not_count_against_a_laggard() {
        let mut l = Ledger::new(3, 1, 8);
        let all = set(&[0, 1, 2]);
        let t0 = Instant::now();
        l.accept(0, 0, b"a", t0);
        l.accept(1, 0, b"a", t0);
        decide_all(&mut l, 0, all);
        assert_eq!(l.next_deadline(all, T), Some(t0 + T));
        assert!(
            l.overdue(all, T, t0 + T).is_some(),
            "replica 2 owes frame 0"
        );
        l.postpone(3 * T);
        // The same additions the ledger makes (each rounds to whole counter ticks).
        assert_eq!(l.next_deadline(all, T), Some(t0 + 3 * T + T));
        assert!(
            l.overdue(all, T, t0 + T).is_none(),
            "the clock stopped while away"
        );
        assert!(l.overdue(all, T, t0 + 3 * T + T).is_some());
    }

    #[test]
    fn dmr_disagreement_is_withheld_not_stalled() {
        let mut l = Ledger::new(2, 1, 8);
        let both = set(&[0, 1]);
        let t = Instant::now();
        l.accept(0, 0, b"x", t);
        l.accept(1, 0, b"y", t);
        l.accept(0, 0, b"z", t);
        l.accept(1, 0, b"z", t);
        let d = decide_all(&mut l, 0, both);
        assert_eq!(
            d,
            [
                withheld(0, both),
                forward(1, b"z", 0, ReplicaSet::EMPTY, both)
            ]
        );
    }

    #[test]
    fn window_holds_back_a_replica_far_ahead_and_deadlines_name_the_laggard() {
        let mut l = Ledger::new(3, 1, 2);
        let all = set(&[0, 1, 2]);
        let t0 = Instant::now();
        assert!(!l.out_of_step(all));
        assert_eq!(l.next_deadline(all, T), None, "nobody ahead: no deadline");
        l.accept(0, 0, b"a", t0);
        l.accept(0, 0, b"b", t0 + T);
        assert!(!l.may_read(0, 0, all), "two ahead with a window of two");
        assert!(l.may_read(1, 0, all));
        assert!(l.out_of_step(all));
        assert_eq!(l.laggard(all), Some(1));
        l.accept(1, 0, b"a", t0);
        l.accept(1, 0, b"b", t0);
        decide_all(&mut l, 0, all);
        // Replica 2 owes frame 0 since t0 (the first copy); the two others agree.
        assert_eq!(l.next_deadline(all, T), Some(t0 + T));
        assert_eq!(l.overdue(all, T, t0 + T / 2), None);
        let od = l.overdue(all, T, t0 + T).unwrap();
        assert_eq!(
            (od.index, od.producers, od.laggards),
            (0, set(&[0, 1]), set(&[2]))
        );
        assert!(od.blames_laggards());
        // Once 2 is no longer trusted, nobody is late and old entries go.
        l.forget(2);
        let two = set(&[0, 1]);
        assert_eq!(l.next_deadline(two, T), None);
        l.trim(two);
        assert!(!l.out_of_step(two));
    }

    #[test]
    fn a_lone_producer_of_an_extra_frame_is_the_suspect() {
        let mut l = Ledger::new(3, 1, 8);
        let all = set(&[0, 1, 2]);
        let t0 = Instant::now();
        l.accept(2, 0, b"extra", t0);
        let od = l.overdue(all, T, t0 + T).unwrap();
        assert_eq!((od.producers, od.laggards), (set(&[2]), set(&[0, 1])));
        assert!(!od.blames_laggards());
        // DMR: one against one, the laggard is blamed (it might be hung; never stall).
        let mut l = Ledger::new(2, 1, 8);
        l.accept(0, 0, b"f", t0);
        let od = l.overdue(set(&[0, 1]), T, t0 + T).unwrap();
        assert!(od.blames_laggards());
        assert_eq!(od.laggards, set(&[1]));
    }

    #[test]
    fn a_fork_child_joins_at_its_donors_position() {
        let mut l = Ledger::new(3, 2, 8);
        let all = set(&[0, 1, 2]);
        let t = Instant::now();
        // Donor 0 produced three frames on output 0, one on output 1; replica 1 one each.
        for f in ["a", "b", "c"] {
            l.accept(0, 0, f.as_bytes(), t);
        }
        l.accept(0, 1, b"m", t);
        l.accept(1, 0, b"a", t);
        l.accept(1, 1, b"m", t);
        decide_all(&mut l, 0, all);
        decide_all(&mut l, 1, all);
        // Replica 2 crashed; the child was forked when the donor had sent 2 and 1 frames.
        l.forget(2);
        l.join_from(2, 0, &[2, 1]);
        assert_eq!((l.pos(2, 0), l.pos(2, 1)), (2, 1));
        // The child inherited the donor's undecided frame 1 ("b"), so with replica 1 it
        // makes a majority; frame 2 ("c") came after the fork: the child makes its own.
        l.accept(1, 0, b"b", t);
        let d = decide_all(&mut l, 0, all);
        assert_eq!(d.len(), 1);
        assert_eq!(d[0], forward(1, b"b", 0, ReplicaSet::EMPTY, all));
        l.accept(2, 0, b"c", t);
        assert_eq!(decide_all(&mut l, 0, all).len(), 1);
        assert_eq!(l.next(0), 3);
    }

    /// A successor's ledger: output 0 goes on from frame 10 (committed); slot 0's process
    /// started at frame 0, slot 1's (exec'd later) at frame 4, slot 2's at frame 12 (it started
    /// after the commit). Each is told how many of its own frames are already decided.
    #[test]
    fn a_successor_goes_on_from_the_committed_frame() {
        let mut l = Ledger::new(3, 1, 8);
        let all = set(&[0, 1, 2]);
        let skip = l.resume(&[10], &[Some(vec![0]), Some(vec![4]), Some(vec![12])]);
        assert_eq!(skip, vec![vec![10], vec![6], vec![0]]);
        assert_eq!((l.pos(0, 0), l.pos(1, 0), l.pos(2, 0)), (10, 10, 12));
        assert_eq!(l.next(0), 10);
        let t = Instant::now();
        l.accept(0, 0, b"k", t);
        l.accept(1, 0, b"k", t);
        let d = decide_all(&mut l, 0, all);
        assert_eq!(
            d,
            vec![forward(10, b"k", 0, ReplicaSet::EMPTY, set(&[0, 1]))]
        );
    }

    #[test]
    fn a_fresh_replica_starts_at_the_next_undecided_frame() {
        let mut l = Ledger::new(1, 1, 8);
        let one = set(&[0]);
        let t = Instant::now();
        l.accept(0, 0, b"a", t);
        decide_all(&mut l, 0, one);
        l.forget(0);
        l.start_fresh(0);
        assert_eq!(l.pos(0, 0), 1);
        l.accept(0, 0, b"b", t);
        assert_eq!(decide_all(&mut l, 0, one).len(), 1);
    }

    /// Accepts `frame` from `slot` and, if `alarm`, marks it flagged by the detector.
    fn scored(l: &mut Ledger, slot: usize, frame: &[u8], alarm: bool, t: Instant) {
        l.accept(slot, 0, frame, t);
        if alarm {
            l.flag_last(slot, 0);
        }
    }

    #[test]
    fn a_lone_flagged_frame_is_held_back_and_an_unflagged_one_forwarded() {
        let mut l = Ledger::new(1, 1, 8);
        let one = set(&[0]);
        let t = Instant::now();
        scored(&mut l, 0, b"a", false, t);
        scored(&mut l, 0, b"b", true, t);
        scored(&mut l, 0, b"c", false, t);
        let d = decide_all(&mut l, 0, one);
        assert_eq!(
            d,
            [
                forward(0, b"a", 0, ReplicaSet::EMPTY, one),
                held_back(1, 0),
                forward(2, b"c", 0, ReplicaSet::EMPTY, one)
            ]
        );
        // A DMR pair down to one: the survivor's flagged frame stands on its word alone.
        let mut l = Ledger::new(2, 1, 8);
        scored(&mut l, 1, b"x", true, t);
        assert!(
            decide_all(&mut l, 0, set(&[0, 1])).is_empty(),
            "waits for 0"
        );
        l.forget(0);
        assert_eq!(decide_all(&mut l, 0, set(&[1])), [held_back(0, 1)]);
    }

    #[test]
    fn dmr_forwards_the_unflagged_copy_of_two_that_differ() {
        let pair = set(&[0, 1]);
        let t = Instant::now();
        for culprit in [0, 1] {
            let mut l = Ledger::new(2, 1, 8);
            scored(&mut l, culprit, b"bad", true, t);
            scored(&mut l, 1 - culprit, b"good", false, t);
            assert_eq!(
                decide_all(&mut l, 0, pair),
                [Decided {
                    index: 0,
                    decision: Decision::Attribute {
                        culprit,
                        healthy: 1 - culprit
                    },
                    frame: Some(b"good".to_vec()),
                    agreed: set(&[1 - culprit]),
                }]
            );
            // A late copy is checked against the forwarded frame.
            assert_eq!(l.next(0), 1);
        }
        // Both or neither flagged: no attribution, withheld as before.
        for flags in [(true, true), (false, false)] {
            let mut l = Ledger::new(2, 1, 8);
            scored(&mut l, 0, b"p", flags.0, t);
            scored(&mut l, 1, b"q", flags.1, t);
            assert!(
                matches!(
                    &decide_all(&mut l, 0, pair)[..],
                    [Decided {
                        index: 0,
                        decision: Decision::Withhold { .. },
                        ..
                    }]
                ),
                "{flags:?}"
            );
        }
        // Copies that agree are forwarded whatever the detector says.
        let mut l = Ledger::new(2, 1, 8);
        scored(&mut l, 0, b"same", true, t);
        scored(&mut l, 1, b"same", false, t);
        assert!(matches!(
            &decide_all(&mut l, 0, pair)[..],
            [Decided {
                index: 0,
                decision: Decision::Forward { .. },
                ..
            }]
        ));
    }

    #[test]
    fn tmr_votes_whatever_the_detector_says() {
        let all = set(&[0, 1, 2]);
        let t = Instant::now();
        let mut l = Ledger::new(3, 1, 8);
        // The flagged copy is the majority's: forwarded. A lone flagged dissent is outvoted.
        scored(&mut l, 0, b"a", true, t);
        scored(&mut l, 1, b"a", true, t);
        scored(&mut l, 2, b"b", false, t);
        assert_eq!(
            decide_all(&mut l, 0, all),
            [forward(0, b"a", 0, set(&[2]), set(&[0, 1]))]
        );
        // Two of three copies that differ and one flagged: the third may still confirm one.
        scored(&mut l, 0, b"c", true, t);
        scored(&mut l, 1, b"d", false, t);
        assert!(decide_all(&mut l, 0, all).is_empty());
    }

    #[test]
    fn a_flag_on_a_decided_or_unsent_frame_changes_nothing() {
        let t = Instant::now();
        let mut l = Ledger::new(1, 1, 8);
        scored(&mut l, 0, b"a", false, t);
        assert_eq!(decide_all(&mut l, 0, set(&[0])).len(), 1);
        l.flag_last(0, 0);
        scored(&mut l, 0, b"b", false, t);
        assert!(matches!(
            &decide_all(&mut l, 0, set(&[0]))[..],
            [Decided {
                index: 1,
                decision: Decision::Forward { .. },
                ..
            }]
        ));
        let mut fresh = Ledger::new(1, 1, 8);
        fresh.flag_last(0, 0);
        assert!(decide_all(&mut fresh, 0, set(&[0])).is_empty());
    }
}
