//! A short spin before the voter sleeps for an answer from another CPU.
//!
//! Where the voter is pinned to a CPU of its own and its replicas run on others, a replica
//! answers a few µs after its input (an echo: 3–10 µs on the 2-core VM of docs/results.md),
//! while the voter, after its writes, is still on its way into `epoll_wait`. An answer that
//! meets the voter there wakes a task that is still on its CPU: the kernel queues that wake-up
//! on the voter's CPU and sends it an interrupt, and on a VM the interrupt takes ~13 µs to be
//! handled (stop 52: 0.84–0.95 such interrupts a round in SMR across CPUs, and S³RES's voter,
//! asleep in `select` before the answer came, 0.03). An answer that finds the voter already
//! asleep on an idle CPU is cheap, and one that finds it awake costs nothing at all.
//!
//! So before it sleeps for such an answer the voter looks again and again, for at most the
//! component's `spin_us`: `epoll_wait` with no timeout on the very set it would sleep on (an
//! answer, a death, a signal or the timer each end the spin as they would end the sleep),
//! with a `sched_yield` between looks, so that a task of the voter's own priority on its CPU
//! (a downstream component, a benchmark's client) still runs when it wants to. Only then does
//! it sleep.
//!
//! **Where.** Only while a round waits for replicas that all run on CPUs other than the
//! voter's (`voter_cpu` apart from the replicas' `cpus`). A replica on the voter's own CPU can
//! run only when the voter sleeps (the voter outranks it): spinning there would only delay the
//! answer. Unpinned replicas may be anywhere, so there is no spin either. Never while the voter
//! waits for input: what sends it may be waiting for the voter's CPU.
//!
//! **How much.** A spin is real-time CPU time, and the kernel throttles real-time tasks that
//! use more than 95 % of a CPU (`sched_rt_runtime_us`: 50 ms stopped every second, stop 53
//! measured it: a back-to-back SMR benchmark spinning without bound kept CPU 0 96 % busy and
//! had a 45.5 ms round). The spins of a voter take at most [`SHARE`] of the time, in all
//! ([`Spin`]: a budget that fills at that rate, up to [`BURST`], and each spin spends): on a
//! CPU whose real-time load is below 70 % without them, they cannot bring it to the throttle.
//! Back-to-back rounds exhaust the budget and then spin in some rounds only; periodic rounds
//! (a control loop at up to some kHz) never do.

use std::time::Duration;

use crate::clock::Instant;

/// The share of the time the spins may take in all.
pub const SHARE: u32 = 4;

/// How much spin time the budget holds at most: a burst of back-to-back rounds after a quiet
/// spell spins in every round for this long in all.
pub const BURST: Duration = Duration::from_millis(5);

/// The spin budget of one voter (see the module's comment).
#[derive(Debug)]
pub struct Spin {
    /// The longest single spin (the component's `spin_us`); zero: never.
    limit: Duration,
    /// Spin time that may still be spent (negative after a spin longer than what was left).
    left_ns: i64,
    /// When the budget was last filled.
    filled_at: Option<Instant>,
}

impl Spin {
    pub fn new(spin_us: u32) -> Spin {
        Spin {
            limit: Duration::from_micros(u64::from(spin_us)),
            left_ns: BURST.as_nanos() as i64,
            filled_at: None,
        }
    }

    /// How long the wait about to begin may spin, at `now`; `None`: it sleeps at once.
    pub fn grant(&mut self, now: Instant) -> Option<Duration> {
        if self.limit.is_zero() {
            return None;
        }
        if let Some(at) = self.filled_at {
            let earned = now.saturating_duration_since(at).as_nanos() / u128::from(SHARE);
            let cap = BURST.as_nanos() as i64;
            self.left_ns = self
                .left_ns
                .saturating_add(i64::try_from(earned).unwrap_or(cap))
                .min(cap);
        }
        self.filled_at = Some(now);
        (self.left_ns > 0).then_some(self.limit)
    }

    /// A wait spun for `spun`.
    pub fn spent(&mut self, spun: Duration) {
        let spun = i64::try_from(spun.as_nanos()).unwrap_or(i64::MAX);
        self.left_ns = self.left_ns.saturating_sub(spun);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMIT_US: u32 = 50;
    const LIMIT: Duration = Duration::from_micros(LIMIT_US as u64);

    #[test]
    fn zero_never_spins() {
        let mut spin = Spin::new(0);
        assert_eq!(spin.grant(Instant::now()), None);
    }

    #[test]
    fn a_quiet_voter_may_spin_its_limit() {
        let mut spin = Spin::new(LIMIT_US);
        let t0 = Instant::now();
        assert_eq!(spin.grant(t0), Some(LIMIT));
        spin.spent(LIMIT);
        // Periodic rounds, one spin each: the budget fills faster than they spend it.
        for k in 1..=1000u32 {
            assert_eq!(spin.grant(t0 + LIMIT * SHARE * k), Some(LIMIT), "round {k}");
            spin.spent(LIMIT);
        }
    }

    #[test]
    fn back_to_back_spins_take_a_share_of_the_time() {
        let mut spin = Spin::new(LIMIT_US);
        let t0 = Instant::now();
        // Rounds every 60 µs, each spinning its whole 50 µs when allowed.
        let (round, rounds) = (Duration::from_micros(60), 100_000u32);
        let mut spun = Duration::ZERO;
        for k in 0..rounds {
            if let Some(d) = spin.grant(t0 + round * k) {
                spin.spent(d);
                spun += d;
            }
        }
        let span = round * rounds;
        // The burst at the start, then a quarter of the time.
        assert!(
            spun <= span / SHARE + BURST + LIMIT,
            "spun {spun:?} of {span:?}"
        );
        assert!(spun >= span / SHARE - LIMIT, "spun {spun:?} of {span:?}");
    }

    #[test]
    fn the_budget_fills_only_up_to_the_burst() {
        let mut spin = Spin::new(LIMIT_US);
        let t0 = Instant::now();
        assert!(spin.grant(t0).is_some());
        // An hour without a spin, then back to back: spins for one burst, then stops.
        let mut now = t0 + Duration::from_secs(3600);
        let mut spun = Duration::ZERO;
        while let Some(d) = spin.grant(now) {
            spin.spent(d);
            spun += d;
            // Back to back: no time passes between spins but the spin itself.
            now += d;
        }
        // What the burst held, and what a quarter of the spinning earned meanwhile.
        assert!(spun >= BURST, "{spun:?}");
        assert!(spun <= BURST * SHARE / (SHARE - 1) + LIMIT, "{spun:?}");
    }
}
