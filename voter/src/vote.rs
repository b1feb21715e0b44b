//! The voting rule. Everything the voter decides about *which output is right* is here.
//!
//! One vote covers one output of one round. Each replica that is still trusted ("alive") has
//! answered with a frame or not yet. Frames are compared byte for byte.
//!
//! * A frame **wins** once more than half of the alive replicas sent exactly that frame:
//!   `needed = alive / 2 + 1`. The winner is forwarded at once, without waiting for the rest.
//! * Replicas that answered something else are **dissenters**: each is an `sdc` fault.
//! * The vote is **pending** while the answers still missing could yet make some frame win.
//! * Otherwise there is **no majority**: nobody is blamed (with two replicas a mismatch can be
//!   seen but not attributed; with three, all three may differ) and nothing is forwarded.
//!
//! "Alive" shrinks when a replica crashes, hangs or breaks the protocol during the round, so a
//! DMR pair that loses one replica forwards the survivor's frame (1 of 1), and a TMR trio that
//! loses one needs its two survivors to agree.

use std::fmt;

/// Largest replica count a voter supports (sets are bitmasks).
pub const MAX_REPLICAS: usize = 32;

/// A set of replica indices.
#[derive(Clone, Copy, Default, PartialEq, Eq, Hash)]
pub struct ReplicaSet(u32);

impl ReplicaSet {
    pub const EMPTY: ReplicaSet = ReplicaSet(0);

    /// Replicas `0..n`.
    pub fn first(n: usize) -> Self {
        ReplicaSet(((1u64 << n.min(MAX_REPLICAS)) - 1) as u32)
    }

    pub fn with(self, i: usize) -> Self {
        ReplicaSet(self.0 | (1 << i))
    }
    pub fn without(self, i: usize) -> Self {
        ReplicaSet(self.0 & !(1 << i))
    }
    pub fn contains(self, i: usize) -> bool {
        self.0 & (1 << i) != 0
    }
    pub fn len(self) -> usize {
        self.0.count_ones() as usize
    }
    pub fn is_empty(self) -> bool {
        self.0 == 0
    }
    pub fn minus(self, other: ReplicaSet) -> Self {
        ReplicaSet(self.0 & !other.0)
    }
    /// The members of both.
    pub fn and(self, other: ReplicaSet) -> Self {
        ReplicaSet(self.0 & other.0)
    }
    /// The members, lowest first.
    pub fn iter(self) -> Members {
        Members(self.0)
    }
}

/// The members of a [`ReplicaSet`], lowest first: one step per member, not per possible slot
/// (the voter walks these sets several times for every answer).
#[derive(Debug, Clone)]
pub struct Members(u32);

impl Iterator for Members {
    type Item = usize;

    fn next(&mut self) -> Option<usize> {
        if self.0 == 0 {
            return None;
        }
        let lowest = self.0.trailing_zeros() as usize;
        self.0 &= self.0 - 1;
        Some(lowest)
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let n = self.0.count_ones() as usize;
        (n, Some(n))
    }
}

impl ExactSizeIterator for Members {}

impl fmt::Debug for ReplicaSet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_set().entries(self.iter()).finish()
    }
}

/// What one vote concluded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VoteOutcome {
    /// `winner`'s frame has a majority; `agree` sent the same frame, `dissent` sent another.
    Majority {
        winner: usize,
        agree: ReplicaSet,
        dissent: ReplicaSet,
    },
    /// The missing answers could still decide it.
    Pending,
    /// No frame can reach a majority any more.
    NoMajority,
}

/// Votes one output. `answers[i]` is replica `i`'s frame, if it answered; only replicas in
/// `alive` count. Does not allocate.
pub fn vote<A: AsRef<[u8]>>(answers: &[Option<A>], alive: ReplicaSet) -> VoteOutcome {
    let needed = alive.len() / 2 + 1;
    let answered = alive
        .iter()
        .filter(|&i| answers.get(i).is_some_and(|a| a.is_some()))
        .fold(ReplicaSet::EMPTY, ReplicaSet::with);
    let missing = alive.minus(answered).len();

    let mut largest = 0;
    for i in answered.iter() {
        let frame = answers[i].as_ref().map(AsRef::as_ref);
        // Count each group once, from its lowest member.
        if (0..i).any(|j| answered.contains(j) && answers[j].as_ref().map(AsRef::as_ref) == frame) {
            continue;
        }
        // A frame agrees with itself: no comparison (a 4 KiB one costs a `memcmp` a round).
        let agree = answered
            .iter()
            .filter(|&j| j == i || answers[j].as_ref().map(AsRef::as_ref) == frame)
            .fold(ReplicaSet::EMPTY, ReplicaSet::with);
        if agree.len() >= needed {
            return VoteOutcome::Majority {
                winner: i,
                agree,
                dissent: answered.minus(agree),
            };
        }
        largest = largest.max(agree.len());
    }
    if largest + missing >= needed {
        VoteOutcome::Pending
    } else {
        VoteOutcome::NoMajority
    }
}

/// How far a replica's frame may be from the bitwise majority for [`bitwise_majority`] to be
/// trusted: bit flips, not a different frame. Garbage (a replica that computed something else)
/// differs in about half of its bits and makes the rule step back.
pub const MAX_DIFFERING_BITS: u32 = 32;

/// A frame rebuilt bit by bit when no whole frame had a majority.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BitMajority {
    /// Each bit is the value most trusted replicas sent.
    pub frame: Vec<u8>,
    /// Replicas whose frame differs from it: the suspects.
    pub dissent: ReplicaSet,
    /// When every frame differed, the one replica not blamed, so that a donor is left to rebuild
    /// the others from: the one with the fewest differing bits (then the lowest slot).
    pub kept: Option<usize>,
    /// The largest number of bits any replica's frame differs in.
    pub max_bits: u32,
}

/// The second rule, for a [`VoteOutcome::NoMajority`] among three or more replicas: a hardware
/// TMR voter votes each bit, not each word, so two replicas hit by bit flips in *different*
/// bits are still outvoted bit by bit. This does the same, but only where it is safe:
///
/// * every trusted replica answered, with frames of one length;
/// * every bit has a strict majority (odd counts always do; a tie in any bit: `None`);
/// * no frame differs from the result in more than [`MAX_DIFFERING_BITS`] bits.
///
/// Otherwise `None`, and the caller withholds the frame as before. Allocates the rebuilt frame
/// (this path runs only after a second fault).
pub fn bitwise_majority<A: AsRef<[u8]>>(
    answers: &[Option<A>],
    alive: ReplicaSet,
) -> Option<BitMajority> {
    if alive.len() < 3 {
        return None;
    }
    let mut frames = [&[][..]; MAX_REPLICAS];
    for r in alive.iter() {
        frames[r] = answers.get(r)?.as_ref()?.as_ref();
    }
    let len = frames[alive.iter().next()?].len();
    if alive.iter().any(|r| frames[r].len() != len) {
        return None;
    }
    let n = alive.len();
    let mut frame = vec![0u8; len];
    for (i, byte) in frame.iter_mut().enumerate() {
        for bit in 0..8 {
            let ones = alive
                .iter()
                .filter(|&r| frames[r][i] >> bit & 1 == 1)
                .count();
            if 2 * ones == n {
                return None;
            }
            if 2 * ones > n {
                *byte |= 1 << bit;
            }
        }
    }
    let differing = |r: usize| -> u32 {
        frames[r]
            .iter()
            .zip(&frame)
            .map(|(a, b)| (a ^ b).count_ones())
            .sum()
    };
    let mut dissent = ReplicaSet::EMPTY;
    let mut max_bits = 0;
    let mut closest: Option<(u32, usize)> = None;
    for r in alive.iter() {
        let bits = differing(r);
        if bits > MAX_DIFFERING_BITS {
            return None;
        }
        max_bits = max_bits.max(bits);
        if bits > 0 {
            dissent = dissent.with(r);
        }
        if closest.is_none_or(|c| (bits, r) < c) {
            closest = Some((bits, r));
        }
    }
    let kept = (dissent.len() == n)
        .then(|| closest.map(|(_, r)| r))
        .flatten();
    if let Some(k) = kept {
        dissent = dissent.without(k);
    }
    Some(BitMajority {
        frame,
        dissent,
        kept,
        max_bits,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn set(ids: &[usize]) -> ReplicaSet {
        ids.iter().fold(ReplicaSet::EMPTY, |s, &i| s.with(i))
    }

    fn a(s: &str) -> Option<Vec<u8>> {
        Some(s.as_bytes().to_vec())
    }

    #[test]
    fn a_set_lists_its_members_lowest_first() {
        assert_eq!(ReplicaSet::EMPTY.iter().count(), 0);
        assert_eq!(
            set(&[2, 0, 31, 5]).iter().collect::<Vec<_>>(),
            [0, 2, 5, 31]
        );
        assert_eq!(ReplicaSet::first(32).iter().len(), 32);
        assert_eq!(ReplicaSet::first(3).iter().collect::<Vec<_>>(), [0, 1, 2]);
    }

    #[test]
    fn tmr_two_agree_before_the_third_answers() {
        let answers = [a("x"), a("x"), None];
        assert_eq!(
            vote(&answers, set(&[0, 1, 2])),
            VoteOutcome::Majority {
                winner: 0,
                agree: set(&[0, 1]),
                dissent: set(&[])
            }
        );
    }

    #[test]
    fn tmr_minority_is_a_dissenter() {
        let answers = [a("x"), a("y"), a("x")];
        assert_eq!(
            vote(&answers, set(&[0, 1, 2])),
            VoteOutcome::Majority {
                winner: 0,
                agree: set(&[0, 2]),
                dissent: set(&[1])
            }
        );
    }

    #[test]
    fn tmr_split_waits_for_the_third() {
        assert_eq!(
            vote(&[a("x"), a("y"), None], set(&[0, 1, 2])),
            VoteOutcome::Pending
        );
    }

    #[test]
    fn tmr_all_different_has_no_majority() {
        assert_eq!(
            vote(&[a("x"), a("y"), a("z")], set(&[0, 1, 2])),
            VoteOutcome::NoMajority
        );
    }

    #[test]
    fn dmr_mismatch_cannot_be_attributed() {
        assert_eq!(
            vote(&[a("x"), a("y")], set(&[0, 1])),
            VoteOutcome::NoMajority
        );
    }

    #[test]
    fn dmr_survivor_wins_alone() {
        assert_eq!(
            vote(&[None, a("x")], set(&[1])),
            VoteOutcome::Majority {
                winner: 1,
                agree: set(&[1]),
                dissent: set(&[])
            }
        );
    }

    #[test]
    fn answers_of_replicas_no_longer_alive_do_not_count() {
        // Replica 2 answered "y" and then crashed: it no longer votes.
        let answers = [a("x"), None, a("y")];
        assert_eq!(vote(&answers, set(&[0, 1])), VoteOutcome::Pending);
    }

    #[test]
    fn five_replicas_survive_two_bad_ones() {
        let answers = [a("y"), a("x"), a("z"), a("x"), a("x")];
        assert_eq!(
            vote(&answers, set(&[0, 1, 2, 3, 4])),
            VoteOutcome::Majority {
                winner: 1,
                agree: set(&[1, 3, 4]),
                dissent: set(&[0, 2])
            }
        );
    }

    #[test]
    fn three_frames_flipped_in_different_bits_are_rebuilt() {
        let good = vec![0b1010_1010u8, 0x55, 0x0f];
        let mut one = good.clone();
        one[0] ^= 0x01;
        let mut two = good.clone();
        two[2] ^= 0x80;
        let answers = [Some(one.clone()), Some(good.clone()), Some(two)];
        assert_eq!(vote(&answers, set(&[0, 1, 2])), VoteOutcome::NoMajority);
        let rebuilt = bitwise_majority(&answers, set(&[0, 1, 2])).unwrap();
        assert_eq!(rebuilt.frame, good);
        assert_eq!(
            (rebuilt.dissent, rebuilt.kept, rebuilt.max_bits),
            (set(&[0, 2]), None, 1)
        );
        // All three hit: the frame is still rebuilt, and the closest one is kept as donor.
        let mut three = good.clone();
        three[1] ^= 0x30;
        let answers = [Some(one), Some(three), Some(answers[2].clone().unwrap())];
        let rebuilt = bitwise_majority(&answers, set(&[0, 1, 2])).unwrap();
        assert_eq!(rebuilt.frame, good);
        assert_eq!(
            (rebuilt.dissent, rebuilt.kept, rebuilt.max_bits),
            (set(&[1, 2]), Some(0), 2)
        );
    }

    #[test]
    fn bitwise_majority_steps_back_where_it_is_not_safe() {
        let all = set(&[0, 1, 2]);
        // Lengths differ.
        assert_eq!(bitwise_majority(&[a("ab"), a("ac"), a("abc")], all), None);
        // A replica has not answered.
        assert_eq!(bitwise_majority(&[a("ab"), a("ac"), None], all), None);
        // Two replicas: no majority per bit either.
        assert_eq!(bitwise_majority(&[a("ab"), a("ac")], set(&[0, 1])), None);
        // Four replicas tied 2:2 on a bit.
        assert_eq!(
            bitwise_majority(&[a("a"), a("a"), a("c"), a("c")], set(&[0, 1, 2, 3])),
            None
        );
        // A frame that is something else altogether, not a few flipped bits.
        let good = vec![0u8; 16];
        let other = vec![0xffu8; 16];
        let mut other2 = other.clone();
        other2[0] = 0;
        assert_eq!(
            bitwise_majority(&[Some(good), Some(other), Some(other2)], all),
            None
        );
    }

    proptest! {
        /// Walking the set bits is walking every slot and keeping the members.
        #[test]
        fn members_are_the_slots_the_set_contains(bits in any::<u32>()) {
            let s = ReplicaSet(bits);
            let slots: Vec<usize> = (0..MAX_REPLICAS).filter(|&i| s.contains(i)).collect();
            prop_assert_eq!(s.iter().collect::<Vec<_>>(), slots);
            prop_assert_eq!(s.iter().len(), s.len());
        }
    }

    proptest! {
        /// A majority winner is unique, its group really is a majority, and every alive
        /// replica that answered is either agreeing or dissenting.
        #[test]
        fn majority_is_sound(
            values in proptest::collection::vec(proptest::option::of(0u8..3), 1..8),
            dead in proptest::collection::vec(any::<bool>(), 8),
        ) {
            let n = values.len();
            let answers: Vec<Option<Vec<u8>>> = values.iter().map(|v| v.map(|b| vec![b])).collect();
            let alive = (0..n).filter(|&i| !dead[i]).fold(ReplicaSet::EMPTY, ReplicaSet::with);
            match vote(&answers, alive) {
                VoteOutcome::Majority { winner, agree, dissent } => {
                    prop_assert!(agree.len() > alive.len() / 2);
                    prop_assert!(agree.contains(winner));
                    for i in alive.iter() {
                        let answered = answers[i].is_some();
                        prop_assert_eq!(answered, agree.contains(i) || dissent.contains(i));
                        if agree.contains(i) { prop_assert_eq!(&answers[i], &answers[winner]); }
                        if dissent.contains(i) { prop_assert_ne!(&answers[i], &answers[winner]); }
                    }
                }
                VoteOutcome::Pending => {
                    // Some way of filling in the missing answers must give a majority.
                    let missing = alive.iter().filter(|&i| answers[i].is_none()).count();
                    prop_assert!(missing > 0);
                }
                VoteOutcome::NoMajority => {
                    // Even if every missing replica agreed with the largest group, no majority.
                    let mut best = 0;
                    for v in 0u8..3 {
                        let c = alive.iter().filter(|&i| answers[i] == Some(vec![v])).count();
                        best = best.max(c);
                    }
                    let missing = alive.iter().filter(|&i| answers[i].is_none()).count();
                    prop_assert!(best + missing <= alive.len() / 2);
                }
            }
        }
    }
}
