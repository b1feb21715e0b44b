//! The set of deadlines the event loop waits for.
//!
//! Every timed thing has its own slot: a round per timed pair (an input that starts rounds),
//! a grace timer per replica (an output closed: crash or protocol fault?). The set is sized once
//! when the voter starts and never allocates afterwards. The loop's `ppoll` timeout is the time
//! to the [`Deadlines::nearest`] one, so several deadlines running at once are each kept, and a
//! wait never outlasts the first of them. A new kind of timer (say, stream mode's per-output
//! deadline) is a new [`Timer`] variant and one more range of slots.

use std::time::Duration;

use super::Instant;

/// What a deadline belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Timer {
    /// The open round of timed pair `k` (the index of its input).
    Round(usize),
    /// The grace after replica `r`'s output closed.
    Grace(usize),
}

/// Fixed-capacity deadlines, one slot per [`Timer`].
#[derive(Debug, Clone)]
pub struct Deadlines {
    pairs: usize,
    replicas: usize,
    at: Vec<Option<Instant>>,
}

impl Deadlines {
    /// Room for `pairs` round deadlines and `replicas` grace timers.
    pub fn new(pairs: usize, replicas: usize) -> Deadlines {
        Deadlines {
            pairs,
            replicas,
            at: vec![None; pairs + replicas],
        }
    }

    fn slot(&self, timer: Timer) -> usize {
        match timer {
            Timer::Round(k) => {
                assert!(k < self.pairs, "round timer {k} of {}", self.pairs);
                k
            }
            Timer::Grace(r) => {
                assert!(r < self.replicas, "grace timer {r} of {}", self.replicas);
                self.pairs + r
            }
        }
    }

    fn timer(&self, slot: usize) -> Timer {
        if slot < self.pairs {
            Timer::Round(slot)
        } else {
            Timer::Grace(slot - self.pairs)
        }
    }

    /// Sets (or moves) `timer`'s deadline.
    pub fn set(&mut self, timer: Timer, at: Instant) {
        let s = self.slot(timer);
        self.at[s] = Some(at);
    }

    pub fn cancel(&mut self, timer: Timer) {
        let s = self.slot(timer);
        self.at[s] = None;
    }

    pub fn cancel_all(&mut self) {
        self.at.fill(None);
    }

    pub fn get(&self, timer: Timer) -> Option<Instant> {
        self.at[self.slot(timer)]
    }

    /// The earliest deadline set, and whose it is.
    pub fn nearest(&self) -> Option<(Timer, Instant)> {
        let (slot, at) = self
            .at
            .iter()
            .enumerate()
            .filter_map(|(s, at)| at.map(|at| (s, at)))
            .min_by_key(|&(_, at)| at)?;
        Some((self.timer(slot), at))
    }

    /// The timers whose deadline has come by `now`.
    pub fn due(&self, now: Instant) -> impl Iterator<Item = Timer> + '_ {
        self.at
            .iter()
            .enumerate()
            .filter(move |(_, at)| at.is_some_and(|at| at <= now))
            .map(|(s, _)| self.timer(s))
    }

    /// How long a wait may last from `now`: until the nearest deadline, rounded down (see
    /// [`super::Clock::duration_floor`]), so it never overshoots it; `None` if nothing is set.
    pub fn timeout(&self, now: Instant) -> Option<Duration> {
        self.nearest()
            .map(|(_, at)| at.saturating_duration_since(now))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn at(base: Instant, us: u64) -> Instant {
        base + Duration::from_micros(us)
    }

    #[test]
    fn empty_set_has_no_deadline() {
        let d = Deadlines::new(2, 3);
        assert_eq!(d.nearest(), None);
        assert_eq!(d.timeout(Instant::now()), None);
        assert_eq!(d.due(Instant::now()).count(), 0);
    }

    #[test]
    fn each_timer_is_kept_and_the_nearest_wins() {
        let base = Instant::now();
        let mut d = Deadlines::new(3, 5);
        d.set(Timer::Round(0), at(base, 300));
        d.set(Timer::Round(2), at(base, 100));
        d.set(Timer::Grace(4), at(base, 200));
        d.set(Timer::Grace(1), at(base, 500));
        assert_eq!(d.nearest(), Some((Timer::Round(2), at(base, 100))));
        d.cancel(Timer::Round(2));
        assert_eq!(d.nearest(), Some((Timer::Grace(4), at(base, 200))));
        // Moving a timer replaces its deadline rather than adding one.
        d.set(Timer::Grace(4), at(base, 900));
        assert_eq!(d.nearest(), Some((Timer::Round(0), at(base, 300))));
        assert_eq!(d.get(Timer::Grace(4)), Some(at(base, 900)));
        let due: Vec<Timer> = d.due(at(base, 500)).collect();
        assert_eq!(due, [Timer::Round(0), Timer::Grace(1)]);
        d.cancel_all();
        assert_eq!(d.nearest(), None);
    }

    #[test]
    fn timeout_is_zero_once_a_deadline_passed() {
        let base = Instant::now();
        let mut d = Deadlines::new(1, 1);
        d.set(Timer::Round(0), base);
        assert_eq!(d.timeout(at(base, 10)), Some(Duration::ZERO));
    }

    #[test]
    #[should_panic(expected = "grace timer 3 of 3")]
    fn a_timer_outside_the_layout_is_a_bug_not_a_silent_miss() {
        Deadlines::new(1, 3).set(Timer::Grace(3), Instant::now());
    }

    proptest! {
        /// With any mix of deadlines set, the timeout ends no later than the earliest of them:
        /// `now + timeout <= every deadline` on the counter, and nothing earlier is missed.
        #[test]
        fn the_wait_never_passes_the_nearest_deadline(
            rounds in proptest::collection::vec(proptest::option::of(0u64..5_000_000), 4),
            graces in proptest::collection::vec(proptest::option::of(0u64..5_000_000), 5),
            now_us in 0u64..5_000_000,
        ) {
            let base = Instant::now();
            let mut d = Deadlines::new(4, 5);
            for (k, us) in rounds.iter().enumerate() {
                if let Some(us) = us { d.set(Timer::Round(k), at(base, *us)); }
            }
            for (r, us) in graces.iter().enumerate() {
                if let Some(us) = us { d.set(Timer::Grace(r), at(base, *us)); }
            }
            let now = at(base, now_us);
            let all: Vec<Instant> = rounds.iter().chain(&graces).flatten().map(|&us| at(base, us)).collect();
            match d.timeout(now) {
                None => prop_assert!(all.is_empty()),
                Some(t) => {
                    let wake = now + t;
                    for &deadline in &all {
                        prop_assert!(wake <= deadline.max(now), "wake {wake:?} after {deadline:?}");
                    }
                    prop_assert_eq!(d.due(now).count(), all.iter().filter(|&&x| x <= now).count());
                }
            }
        }
    }
}
