//! The voter's policy, as data: what to forward and whom to blame, decided by pure functions.
//!
//! Both modes ask the same question of one voted frame — the answers of one output in a
//! reactive round, or the k-th frame of a stream output — and get a [`Decision`] from
//! [`decide`]. Reactive mode closes a whole round with [`decide_round`], which adds who was
//! late and the order in which anomaly attribution and the vote apply. Nothing here does I/O,
//! kills a process or writes an event: `core::Core::apply` turns decisions into frames and
//! events, and the mode faults the suspects. A policy change is an edit here, with its test
//! below.
//!
//! The rules, in order:
//! 1. A frame that more than half of the trusted replicas sent wins ([`vote`]): it is
//!    forwarded, the replicas that sent something else are `sdc` (`minority`) — unless the
//!    winner stands on one replica's word and its anomaly detector flagged it: then it is
//!    held back and that replica is the suspect (`anomaly_held_back`).
//! 2. No whole frame can win, but every bit has a majority among three or more replicas that
//!    are at most a few bits apart ([`bitwise_majority`]): the rebuilt frame is forwarded and
//!    the replicas that differ from it are `sdc` (`bitwise_minority`).
//! 3. Two copies that differ, exactly one of them flagged by its anomaly detector: the other is
//!    forwarded, the flagged one is the suspect (`anomaly_attributed`).
//! 4. Otherwise the frame is withheld and nobody is blamed (`no_majority`): a fault is certain,
//!    its culprit is not, and we do not guess.
//!
//! Over all of them: **lost state never outvotes kept state.** A replica whose state is lost
//! (started by exec after a fault, or forked from one that was) may confirm the frame of a
//! replica that kept the component's state, but a frame that only fresh replicas sent never
//! wins over a kept replica's: then the kept replicas decide among themselves, and every fresh
//! replica whose frame differs from the result is `sdc` (and is rebuilt by fork from a kept
//! one). A frame waits for the kept replicas' copies while only fresh ones could decide it.
//!
//! And **a loss no restart can mend is not a fault** ([`spare_diverged`]): a fresh replica
//! none of whose frames has matched yet (it is *catching up*) differs because its state is lost.
//! While no other replica can donate by fork (an unmodified program's that runs threads
//! refuses), its rebuild would be another exec that loses the state again — a restart every
//! round, each outvoted, until the restart budget fails the component. So such a dissent is
//! not blamed: the replica stays, outvoted, and is said once as `diverged`. Once a fork could
//! give its state back, or once it has matched a frame that went out (its state caught up, so
//! a later dissent is a fault), it is blamed as any other. A match can be chance (an output
//! coarser than the state): a replica that matched and then dissents all the same marks its
//! slot *relapsed* (`Core::spare_diverged`), and the next one started there is not taken for
//! caught up by a match — until a fork gives the slot the state back.

use replica_rt::contract::MAX_PORTS;

use crate::event::Cause;
use crate::round::OutputSet;
use crate::vote::{bitwise_majority, vote, BitMajority, ReplicaSet, VoteOutcome, MAX_REPLICAS};

/// What the voter does about one voted frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Decision {
    /// `winner`'s frame has a majority and goes out; `dissent` sent another frame.
    Forward { winner: usize, dissent: ReplicaSet },
    /// No whole frame had a majority, every bit did: the rebuilt frame goes out and
    /// `rebuilt.dissent` are the suspects (with `rebuilt.kept` the one spared as donor when
    /// every frame differed).
    Rebuild(BitMajority),
    /// No frame can have a majority; `answered` sent frames that disagree. Nothing goes out.
    Withhold { answered: ReplicaSet },
    /// The frame stands on `suspect`'s word alone and its anomaly detector flagged it: held
    /// back, and `suspect` is faulty.
    HoldBack { suspect: usize },
    /// Two copies differ and only `culprit`'s was flagged: `healthy`'s goes out.
    Attribute { culprit: usize, healthy: usize },
}

impl Decision {
    /// The replicas this decision finds faulty, and why.
    pub fn blame(&self) -> (ReplicaSet, Cause) {
        match self {
            Decision::Forward { dissent, .. } => (*dissent, Cause::Minority),
            Decision::Rebuild(rebuilt) => (rebuilt.dissent, Cause::BitwiseMinority),
            Decision::Withhold { .. } => (ReplicaSet::EMPTY, Cause::NoMajority),
            Decision::HoldBack { suspect } => {
                (ReplicaSet::EMPTY.with(*suspect), Cause::AnomalyHeldBack)
            }
            Decision::Attribute { culprit, .. } => {
                (ReplicaSet::EMPTY.with(*culprit), Cause::AnomalyAttributed)
            }
        }
    }

    /// The frame that goes out, given each replica's: `None` when nothing does.
    pub fn frame<'a>(&'a self, of: impl Fn(usize) -> Option<&'a [u8]>) -> Option<&'a [u8]> {
        match self {
            Decision::Forward { winner, .. } => of(*winner),
            Decision::Attribute { healthy, .. } => of(*healthy),
            Decision::Rebuild(rebuilt) => Some(&rebuilt.frame),
            Decision::Withhold { .. } | Decision::HoldBack { .. } => None,
        }
    }
}

/// Decides one frame from each trusted replica's copy (`frames[r]`, `None` where `r` has not
/// sent it), the trusted replicas `alive`, those whose copy its anomaly detector flagged, and
/// those whose state is lost (`fresh`). `None` while the missing copies could still decide it.
pub fn decide<A: AsRef<[u8]>>(
    frames: &[Option<A>],
    alive: ReplicaSet,
    alarmed: ReplicaSet,
    fresh: ReplicaSet,
) -> Option<Decision> {
    let kept = alive.minus(fresh);
    let decision = decide_among(frames, alive, alarmed)?;
    if kept.is_empty() || kept == alive {
        return Some(decision);
    }
    let frame_of = |r: usize| frames.get(r).and_then(|f| f.as_ref()).map(AsRef::as_ref);
    let lost_state_decided = match &decision {
        // Only fresh replicas sent the frame that would go out.
        Decision::Forward { .. } | Decision::Rebuild(_) => {
            let won = decision.frame(frame_of);
            won.is_some_and(|w| !kept.iter().any(|r| frame_of(r) == Some(w)))
        }
        // A fresh replica's disagreement kept a kept replica's frame from winning.
        Decision::Withhold { answered } => !answered.minus(kept).is_empty(),
        Decision::HoldBack { .. } | Decision::Attribute { .. } => false,
    };
    if !lost_state_decided {
        return Some(decision);
    }
    // The kept replicas decide alone.
    let decision = decide_among(frames, kept, alarmed)?;
    let won = decision.frame(frame_of).map(<[u8]>::to_vec);
    let Some(won) = won else {
        return Some(decision);
    };
    let differing = alive
        .minus(kept)
        .iter()
        .filter(|&r| frame_of(r).is_some_and(|f| f != won.as_slice()))
        .fold(ReplicaSet::EMPTY, ReplicaSet::with);
    Some(match decision {
        Decision::Forward { winner, dissent } => Decision::Forward {
            winner,
            dissent: differing.iter().fold(dissent, ReplicaSet::with),
        },
        Decision::Rebuild(mut rebuilt) => {
            rebuilt.dissent = differing.iter().fold(rebuilt.dissent, ReplicaSet::with);
            Decision::Rebuild(rebuilt)
        }
        other => other,
    })
}

/// Of the replicas `blamed` for `cause`, those not to fault: the dissenters `catching_up`
/// (state lost, not a frame matched yet) when none of the other replicas is among `donors`
/// (those that could donate by fork now). Only a vote's dissent is spared (`minority`,
/// `bitwise_minority`): a crash, a hang or a broken protocol is a fault whatever the state.
pub fn spare_diverged(
    blamed: ReplicaSet,
    cause: Cause,
    catching_up: ReplicaSet,
    donors: ReplicaSet,
) -> ReplicaSet {
    let dissent = matches!(cause, Cause::Minority | Cause::BitwiseMinority);
    if !dissent || !donors.minus(blamed).is_empty() {
        return ReplicaSet::EMPTY;
    }
    blamed.and(catching_up)
}

/// [`decide`] among `alive`, all of whom count alike.
fn decide_among<A: AsRef<[u8]>>(
    frames: &[Option<A>],
    alive: ReplicaSet,
    alarmed: ReplicaSet,
) -> Option<Decision> {
    match vote(frames, alive) {
        VoteOutcome::Pending => None,
        VoteOutcome::Majority { winner, agree, .. }
            if agree.len() == 1 && alarmed.contains(winner) =>
        {
            Some(Decision::HoldBack { suspect: winner })
        }
        VoteOutcome::Majority {
            winner, dissent, ..
        } => Some(Decision::Forward { winner, dissent }),
        VoteOutcome::NoMajority => Some(match bitwise_majority(frames, alive) {
            Some(rebuilt) => Decision::Rebuild(rebuilt),
            None => {
                let answered = alive
                    .iter()
                    .filter(|&r| frames.get(r).is_some_and(Option::is_some))
                    .fold(ReplicaSet::EMPTY, ReplicaSet::with);
                let flagged = answered
                    .iter()
                    .filter(|&r| alarmed.contains(r))
                    .fold(ReplicaSet::EMPTY, ReplicaSet::with);
                let healthy = answered.minus(flagged);
                match (answered.len(), flagged.iter().next(), healthy.iter().next()) {
                    (2, Some(culprit), Some(healthy)) if flagged.len() == 1 => {
                        Decision::Attribute { culprit, healthy }
                    }
                    _ => Decision::Withhold { answered },
                }
            }
        }),
    }
}

/// A reactive round as the voter saw it when it closes (at the deadline, or once every
/// trusted replica answered), after one last read of the late replicas' pipes.
#[derive(Debug, Clone, Copy)]
pub struct RoundBallot<'a> {
    /// The outputs every replica had to answer.
    pub expected: OutputSet,
    /// Outputs whose winner already went out during the round (it had a majority early).
    pub forwarded: OutputSet,
    /// Outputs held back during the round.
    pub held: OutputSet,
    /// Replicas still trusted that took part in the round.
    pub alive: ReplicaSet,
    /// `answered[r]`: the outputs replica `r` answered.
    pub answered: &'a [OutputSet],
    /// `answers[r][o]`: replica `r`'s frame on output `o` (meaningful where it answered).
    pub answers: &'a [Vec<Answer>],
    /// `alarmed[r]`: the outputs on which replica `r`'s frame alarmed its detector.
    pub alarmed: &'a [OutputSet],
    /// Replicas whose state is lost (see the module's rules).
    pub fresh: ReplicaSet,
}

/// One replica's frame on one output, where the voter read it: in a buffer that was its
/// pipe's read buffer a moment before (see `FrameDecoder::next_frame_into`), so that the
/// frame is voted, scored and forwarded in place. (A payload of at most `frame::COPY_UP_TO`
/// bytes, or one read together with more bytes behind it, is copied there instead.)
#[derive(Debug, Clone, Default)]
pub struct Answer {
    buf: Vec<u8>,
    at: std::ops::Range<usize>,
}

impl Answer {
    pub fn as_slice(&self) -> &[u8] {
        &self.buf[self.at.clone()]
    }

    /// The storage to decode the next frame into; [`set`](Self::set) says where it landed.
    pub fn storage(&mut self) -> &mut Vec<u8> {
        &mut self.buf
    }

    pub fn set(&mut self, at: std::ops::Range<usize>) {
        debug_assert!(at.end <= self.buf.len());
        self.at = at;
    }
}

impl From<Vec<u8>> for Answer {
    fn from(buf: Vec<u8>) -> Self {
        let at = 0..buf.len();
        Answer { buf, at }
    }
}

/// One decision of a closing round.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RoundDecision {
    pub output: usize,
    pub decision: Decision,
    /// Its frame already went out during the round: only the blame is left to apply.
    pub sent: bool,
}

/// How a round ends.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct RoundClose {
    /// Trusted replicas that did not answer every expected output: `hang` (or `protocol` with
    /// a partial frame in their pipe). They do not count in the votes below.
    pub late: ReplicaSet,
    /// Per expected output (not held back), in output order, after the attributions.
    pub decisions: Vec<RoundDecision>,
}

impl RoundBallot<'_> {
    /// Each trusted replica's answer on output `o`.
    fn frames(&self, o: usize) -> [Option<&[u8]>; MAX_REPLICAS] {
        let mut frames = [None; MAX_REPLICAS];
        for r in self.alive.iter() {
            if self.answered.get(r).is_some_and(|a| a & (1 << o) != 0) {
                frames[r] = Some(self.answers[r][o].as_slice());
            }
        }
        frames
    }

    fn alarmed_on(&self, o: usize) -> ReplicaSet {
        self.alive
            .iter()
            .filter(|&r| self.alarmed.get(r).is_some_and(|a| a & (1 << o) != 0))
            .fold(ReplicaSet::EMPTY, ReplicaSet::with)
    }

    fn outputs(&self) -> impl Iterator<Item = usize> + '_ {
        (0..MAX_PORTS).filter(|&o| self.expected & (1 << o) != 0)
    }

    /// While the round is open: output `o` can go out now (`Forward`), or must be held back
    /// (`HoldBack`); `None` otherwise (wait for more answers, or for the close).
    pub fn early(&self, o: usize) -> Option<Decision> {
        if (self.forwarded | self.held) & (1 << o) != 0 {
            return None;
        }
        match decide(&self.frames(o), self.alive, self.alarmed_on(o), self.fresh) {
            d @ Some(Decision::Forward { .. } | Decision::HoldBack { .. }) => d,
            _ => None,
        }
    }
}

/// Closes a reactive round: the late replicas leave the quorum, then a pair that disagrees
/// where exactly one copy alarmed loses its flagged replica (on every output of the round),
/// then every output is decided among the replicas left. An output whose frame already went
/// out only has its dissenters blamed. Writes the decisions into `close` (its vector keeps
/// its capacity from round to round).
pub fn decide_round(ballot: &RoundBallot, close: &mut RoundClose) {
    close.decisions.clear();
    let done = |r: usize| {
        ballot
            .answered
            .get(r)
            .is_some_and(|a| a & ballot.expected == ballot.expected)
    };
    close.late = ballot
        .alive
        .iter()
        .filter(|&r| !done(r))
        .fold(ReplicaSet::EMPTY, ReplicaSet::with);
    let on_time = RoundBallot {
        alive: ballot.alive.minus(close.late),
        ..*ballot
    };
    let open = |o: usize| (ballot.forwarded | ballot.held) & (1 << o) == 0;
    let mut culprits = ReplicaSet::EMPTY;
    let mut attributed: OutputSet = 0;
    for o in on_time.outputs().filter(|&o| open(o)) {
        if let Some(d @ Decision::Attribute { culprit, .. }) = decide(
            &on_time.frames(o),
            on_time.alive,
            on_time.alarmed_on(o),
            on_time.fresh,
        ) {
            culprits = culprits.with(culprit);
            attributed |= 1 << o;
            close.decisions.push(RoundDecision {
                output: o,
                decision: d,
                sent: false,
            });
        }
    }
    let trusted = RoundBallot {
        alive: on_time.alive.minus(culprits),
        ..on_time
    };
    for o in trusted.outputs() {
        if (ballot.held | attributed) & (1 << o) != 0 {
            continue;
        }
        let sent = !open(o);
        let answered = trusted
            .alive
            .iter()
            .filter(|&r| trusted.answered[r] & (1 << o) != 0)
            .fold(ReplicaSet::EMPTY, ReplicaSet::with);
        let decision = match decide(
            &trusted.frames(o),
            trusted.alive,
            trusted.alarmed_on(o),
            trusted.fresh,
        ) {
            // Sent already: what is left is to blame the replicas that disagree with it.
            Some(d @ Decision::Forward { .. }) if sent => d,
            _ if sent => continue,
            Some(d) => d,
            None => Decision::Withhold { answered },
        };
        close.decisions.push(RoundDecision {
            output: o,
            decision,
            sent,
        });
    }
    close.decisions.sort_by_key(|d| d.output);
}

#[cfg(test)]
mod tests {
    /// A fresh replica that differs because its state is lost is spared only while nothing
    /// could give the state back; every other blame stands.
    #[test]
    fn a_loss_no_fork_can_mend_is_spared() {
        let (fresh, kept) = (set(&[2]), set(&[0, 1]));
        // No donor: the dissenter catching up is spared, a kept dissenter is not.
        let none = ReplicaSet::EMPTY;
        assert_eq!(
            spare_diverged(set(&[2]), Cause::Minority, fresh, none),
            fresh
        );
        assert_eq!(
            spare_diverged(set(&[1, 2]), Cause::BitwiseMinority, fresh, none),
            fresh
        );
        assert_eq!(
            spare_diverged(set(&[1]), Cause::Minority, fresh, none),
            none
        );
        // A kept replica could fork: the dissenter is rebuilt with the state, as before.
        assert_eq!(
            spare_diverged(set(&[2]), Cause::Minority, fresh, kept),
            none
        );
        // Only itself, or another dissenter, could donate: nobody that stays.
        assert_eq!(
            spare_diverged(set(&[2]), Cause::Minority, fresh, fresh),
            fresh
        );
        assert_eq!(
            spare_diverged(set(&[1, 2]), Cause::Minority, fresh, set(&[1])),
            fresh
        );
        // Not a vote's dissent: a fault whatever the state.
        for cause in [
            Cause::Deadline,
            Cause::Died,
            Cause::AnomalyAttributed,
            Cause::AnomalyHeldBack,
        ] {
            assert_eq!(spare_diverged(fresh, cause, fresh, none), none, "{cause:?}");
        }
        // Caught up: a dissent is a fault.
        assert_eq!(spare_diverged(set(&[2]), Cause::Minority, none, none), none);
    }

    use super::*;

    fn set(ids: &[usize]) -> ReplicaSet {
        ids.iter().fold(ReplicaSet::EMPTY, |s, &i| s.with(i))
    }

    /// [`decide`] where every replica kept its state.
    fn d(frames: &[Option<Vec<u8>>], alive: ReplicaSet, alarmed: ReplicaSet) -> Option<Decision> {
        decide(frames, alive, alarmed, ReplicaSet::EMPTY)
    }

    fn f(s: &str) -> Option<Vec<u8>> {
        Some(s.as_bytes().to_vec())
    }

    // ----- one frame ------------------------------------------------------------------

    #[test]
    fn all_agree_forwards_and_blames_nobody() {
        let d = d(
            &[f("x"), f("x"), f("x")],
            set(&[0, 1, 2]),
            ReplicaSet::EMPTY,
        );
        assert_eq!(
            d,
            Some(Decision::Forward {
                winner: 0,
                dissent: ReplicaSet::EMPTY
            })
        );
        assert!(d.unwrap().blame().0.is_empty());
    }

    #[test]
    fn one_differs_is_outvoted_as_minority() {
        let d = d(
            &[f("x"), f("y"), f("x")],
            set(&[0, 1, 2]),
            ReplicaSet::EMPTY,
        )
        .unwrap();
        assert_eq!(
            d,
            Decision::Forward {
                winner: 0,
                dissent: set(&[1])
            }
        );
        assert_eq!(d.blame(), (set(&[1]), Cause::Minority));
    }

    #[test]
    fn two_agree_before_the_third_answers() {
        let d = d(&[f("x"), None, f("x")], set(&[0, 1, 2]), ReplicaSet::EMPTY);
        assert!(matches!(d, Some(Decision::Forward { winner: 0, .. })));
    }

    #[test]
    fn a_split_waits_for_the_missing_replica() {
        assert_eq!(
            d(&[f("x"), f("y"), None], set(&[0, 1, 2]), ReplicaSet::EMPTY),
            None
        );
    }

    #[test]
    fn two_differ_in_different_bits_are_rebuilt_bit_by_bit() {
        // 'a' = 0x61; 0x60 and 0x63 differ from it in different bits.
        let d = d(
            &[f("a"), f("`"), f("c")],
            set(&[0, 1, 2]),
            ReplicaSet::EMPTY,
        )
        .unwrap();
        let Decision::Rebuild(rebuilt) = &d else {
            panic!("expected a rebuild, got {d:?}");
        };
        assert_eq!(rebuilt.frame, b"a");
        assert_eq!(d.blame(), (set(&[1, 2]), Cause::BitwiseMinority));
        assert_eq!(d.frame(|_| None), Some(&b"a"[..]));
    }

    #[test]
    fn no_majority_is_withheld_and_blames_nobody() {
        let d = d(
            &[f("first answer"), f("something else"), f("a third thing")],
            set(&[0, 1, 2]),
            ReplicaSet::EMPTY,
        )
        .unwrap();
        assert_eq!(
            d,
            Decision::Withhold {
                answered: set(&[0, 1, 2])
            }
        );
        assert!(d.blame().0.is_empty());
        assert_eq!(d.frame(|_| Some(b"no")), None);
    }

    #[test]
    fn dmr_mismatch_without_an_alarm_is_withheld() {
        let d = d(&[f("x"), f("y")], set(&[0, 1]), ReplicaSet::EMPTY).unwrap();
        assert_eq!(
            d,
            Decision::Withhold {
                answered: set(&[0, 1])
            }
        );
    }

    #[test]
    fn dmr_mismatch_with_one_alarm_blames_the_flagged_copy() {
        let frames = [f("x"), f("y")];
        let d = d(&frames, set(&[0, 1]), set(&[1])).unwrap();
        assert_eq!(
            d,
            Decision::Attribute {
                culprit: 1,
                healthy: 0
            }
        );
        assert_eq!(d.blame(), (set(&[1]), Cause::AnomalyAttributed));
        assert_eq!(d.frame(|r| frames[r].as_deref()), Some(&b"x"[..]));
    }

    #[test]
    fn dmr_mismatch_with_both_alarmed_is_withheld() {
        let d = d(&[f("x"), f("y")], set(&[0, 1]), set(&[0, 1])).unwrap();
        assert!(matches!(d, Decision::Withhold { .. }));
    }

    #[test]
    fn smr_alarm_holds_the_frame_back() {
        let d = d(&[f("x")], set(&[0]), set(&[0])).unwrap();
        assert_eq!(d, Decision::HoldBack { suspect: 0 });
        assert_eq!(d.blame(), (set(&[0]), Cause::AnomalyHeldBack));
        assert_eq!(d.frame(|_| Some(b"x")), None);
    }

    #[test]
    fn smr_without_alarm_forwards() {
        let d = d(&[f("x")], set(&[0]), ReplicaSet::EMPTY).unwrap();
        assert!(matches!(d, Decision::Forward { winner: 0, .. }));
    }

    #[test]
    fn an_alarm_on_a_confirmed_frame_changes_nothing() {
        // TMR logs alarms: two replicas confirm the flagged frame.
        let d = d(&[f("x"), f("x"), f("x")], set(&[0, 1, 2]), set(&[0])).unwrap();
        assert!(matches!(d, Decision::Forward { winner: 0, .. }));
    }

    // ----- lost state -----------------------------------------------------------------

    #[test]
    fn two_fresh_replicas_never_outvote_the_one_that_kept_its_state() {
        // Replicas 0 and 1 were restarted by exec (their state is lost) and agree with each
        // other; replica 2 kept the component's state. Its frame goes out; the fresh ones are
        // the suspects (and are rebuilt from it by fork).
        let frames = [f("reset"), f("reset"), f("kept")];
        let dec = decide(&frames, set(&[0, 1, 2]), ReplicaSet::EMPTY, set(&[0, 1])).unwrap();
        assert_eq!(
            dec,
            Decision::Forward {
                winner: 2,
                dissent: set(&[0, 1])
            }
        );
        assert_eq!(dec.frame(|r| frames[r].as_deref()), Some(&b"kept"[..]));
    }

    #[test]
    fn fresh_copies_wait_for_the_kept_replica() {
        let frames = [f("reset"), f("reset"), None];
        assert_eq!(
            decide(&frames, set(&[0, 1, 2]), ReplicaSet::EMPTY, set(&[0, 1])),
            None
        );
    }

    #[test]
    fn a_fresh_replica_may_confirm_a_kept_one() {
        // Kept 0 and 1 disagree; fresh 2 sends what 0 sent: two independent copies of one
        // frame, and 0's frame wins.
        let frames = [f("a"), f("b"), f("a")];
        let dec = decide(&frames, set(&[0, 1, 2]), ReplicaSet::EMPTY, set(&[2])).unwrap();
        assert_eq!(
            dec,
            Decision::Forward {
                winner: 0,
                dissent: set(&[1])
            }
        );
    }

    #[test]
    fn a_fresh_replica_that_agrees_is_not_blamed() {
        let frames = [f("a"), f("a"), f("a")];
        let dec = decide(&frames, set(&[0, 1, 2]), ReplicaSet::EMPTY, set(&[1, 2])).unwrap();
        assert!(dec.blame().0.is_empty(), "{dec:?}");
    }

    #[test]
    fn with_only_fresh_replicas_left_they_vote_as_usual() {
        let frames = [f("a"), f("a"), f("b")];
        let dec = decide(&frames, set(&[0, 1, 2]), ReplicaSet::EMPTY, set(&[0, 1, 2])).unwrap();
        assert_eq!(
            dec,
            Decision::Forward {
                winner: 0,
                dissent: set(&[2])
            }
        );
    }

    #[test]
    fn dmr_kept_and_fresh_that_differ_forward_the_kept_frame() {
        // The sequence of issue 13: a DMR pair where one was rebuilt by exec.
        let frames = [f("reset"), f("kept")];
        let dec = decide(&frames, set(&[0, 1]), ReplicaSet::EMPTY, set(&[0])).unwrap();
        assert_eq!(
            dec,
            Decision::Forward {
                winner: 1,
                dissent: set(&[0])
            }
        );
    }

    // ----- a reactive round -------------------------------------------------------------

    /// A round over `outputs` outputs: `answers[r]` is replica r's frames (None: no answer).
    struct Fixture {
        answered: Vec<OutputSet>,
        answers: Vec<Vec<Answer>>,
        alarmed: Vec<OutputSet>,
    }

    impl Fixture {
        fn new(answers: &[&[Option<&str>]]) -> Self {
            let mut fx = Fixture {
                answered: vec![0; answers.len()],
                answers: vec![],
                alarmed: vec![0; answers.len()],
            };
            for (r, outs) in answers.iter().enumerate() {
                let mut row = Vec::new();
                for (o, a) in outs.iter().enumerate() {
                    if a.is_some() {
                        fx.answered[r] |= 1 << o;
                    }
                    row.push(Answer::from(a.unwrap_or("").as_bytes().to_vec()));
                }
                fx.answers.push(row);
            }
            fx
        }

        fn ballot(&self, expected: OutputSet) -> RoundBallot<'_> {
            RoundBallot {
                expected,
                forwarded: 0,
                held: 0,
                alive: (0..self.answers.len()).fold(ReplicaSet::EMPTY, ReplicaSet::with),
                answered: &self.answered,
                answers: &self.answers,
                alarmed: &self.alarmed,
                fresh: ReplicaSet::EMPTY,
            }
        }

        fn close(&self, ballot: &RoundBallot) -> RoundClose {
            let mut close = RoundClose::default();
            decide_round(ballot, &mut close);
            close
        }
    }

    #[test]
    fn round_all_agree() {
        let fx = Fixture::new(&[&[Some("a")], &[Some("a")], &[Some("a")]]);
        let close = fx.close(&fx.ballot(0b1));
        assert!(close.late.is_empty());
        assert_eq!(close.decisions.len(), 1);
        assert!(matches!(
            close.decisions[0].decision,
            Decision::Forward { winner: 0, dissent } if dissent.is_empty()
        ));
    }

    #[test]
    fn round_late_replica_is_late_and_does_not_vote() {
        // Replica 2 answered only one of two outputs by the close.
        let fx = Fixture::new(&[
            &[Some("a"), Some("b")],
            &[Some("a"), Some("b")],
            &[Some("a"), None],
        ]);
        let close = fx.close(&fx.ballot(0b11));
        assert_eq!(close.late, set(&[2]));
        for d in &close.decisions {
            assert!(matches!(d.decision, Decision::Forward { dissent, .. } if dissent.is_empty()));
        }
    }

    #[test]
    fn round_missing_replica_leaves_a_pair_that_must_agree() {
        // Replica 1 crashed during the round: it is not alive.
        let fx = Fixture::new(&[&[Some("a")], &[None], &[Some("b")]]);
        let mut ballot = fx.ballot(0b1);
        ballot.alive = set(&[0, 2]);
        let close = fx.close(&ballot);
        assert!(close.late.is_empty());
        assert_eq!(
            close.decisions[0].decision,
            Decision::Withhold {
                answered: set(&[0, 2])
            }
        );
    }

    #[test]
    fn round_forwarded_early_only_blames_the_dissenter() {
        let fx = Fixture::new(&[&[Some("a")], &[Some("a")], &[Some("z")]]);
        let mut ballot = fx.ballot(0b1);
        ballot.forwarded = 0b1;
        let close = fx.close(&ballot);
        assert_eq!(
            close.decisions,
            vec![RoundDecision {
                output: 0,
                decision: Decision::Forward {
                    winner: 0,
                    dissent: set(&[2])
                },
                sent: true
            }]
        );
    }

    #[test]
    fn round_held_output_is_not_decided_again() {
        let fx = Fixture::new(&[&[Some("a")]]);
        let mut ballot = fx.ballot(0b1);
        ballot.held = 0b1;
        assert!(fx.close(&ballot).decisions.is_empty());
    }

    #[test]
    fn round_dmr_attribution_removes_the_culprit_from_every_output() {
        // Output 0 differs and only replica 1's copy alarmed; output 1 differs without any
        // alarm. The culprit leaves the quorum, so replica 0's output 1 goes out too.
        let mut fx = Fixture::new(&[&[Some("a"), Some("p")], &[Some("b"), Some("q")]]);
        fx.alarmed[1] = 0b01;
        let close = fx.close(&fx.ballot(0b11));
        assert_eq!(
            close.decisions[0].decision,
            Decision::Attribute {
                culprit: 1,
                healthy: 0
            }
        );
        assert!(matches!(
            close.decisions[1].decision,
            Decision::Forward { winner: 0, .. }
        ));
    }

    #[test]
    fn round_smr_alarm_at_close_holds_back() {
        let mut fx = Fixture::new(&[&[Some("a")]]);
        fx.alarmed[0] = 0b1;
        let close = fx.close(&fx.ballot(0b1));
        assert_eq!(
            close.decisions[0].decision,
            Decision::HoldBack { suspect: 0 }
        );
    }

    #[test]
    fn round_nobody_answered_withholds_with_nobody_answered() {
        let fx = Fixture::new(&[&[None], &[None], &[None]]);
        let close = fx.close(&fx.ballot(0b1));
        assert_eq!(close.late, set(&[0, 1, 2]));
        assert_eq!(
            close.decisions[0].decision,
            Decision::Withhold {
                answered: ReplicaSet::EMPTY
            }
        );
    }

    #[test]
    fn early_forwards_a_majority_and_waits_otherwise() {
        let fx = Fixture::new(&[&[Some("a")], &[Some("a")], &[None]]);
        let ballot = fx.ballot(0b1);
        assert!(matches!(
            ballot.early(0),
            Some(Decision::Forward { winner: 0, .. })
        ));
        let fx = Fixture::new(&[&[Some("a")], &[Some("b")], &[None]]);
        assert_eq!(fx.ballot(0b1).early(0), None);
    }

    #[test]
    fn early_does_not_decide_an_output_twice() {
        let fx = Fixture::new(&[&[Some("a")], &[Some("a")], &[Some("a")]]);
        let mut ballot = fx.ballot(0b1);
        ballot.forwarded = 0b1;
        assert_eq!(ballot.early(0), None);
    }
}
