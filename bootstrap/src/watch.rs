//! Watching voters: each voter bumps a counter in a page it shares with bootstrap on every turn
//! of its loop (`replica_rt::heartbeat`), and wakes at least every 100 ms to do so. A counter
//! that stands still past a deadline derived from the component's plan means the voter is
//! stopped (SIGSTOP, a debugger) or stuck: bootstrap kills it, and replaces it with a voter
//! that adopts its replicas (`respawn.rs`), or, where that cannot be done, stops the system
//! with one line that says which voter and how long.

use std::time::{Duration, Instant};

use replica_rt::heartbeat::Heartbeat;

use crate::plan::ComponentPlan;

/// How often bootstrap looks at the heartbeats.
pub const WATCH_PERIOD: Duration = Duration::from_millis(250);

/// One voter's heartbeat, as bootstrap follows it.
#[derive(Debug)]
pub struct VoterWatch {
    page: Heartbeat,
    deadline: Duration,
    last: u64,
    since: Instant,
}

impl VoterWatch {
    /// A fresh page for the voter of `c`, with the deadline its plan allows.
    pub fn new(c: &ComponentPlan) -> std::io::Result<VoterWatch> {
        Ok(VoterWatch {
            page: Heartbeat::create()?,
            deadline: stall_deadline(c),
            last: 0,
            since: Instant::now(),
        })
    }

    /// The page, to hand to the voter.
    pub fn page(&self) -> &Heartbeat {
        &self.page
    }

    /// The system stops: the voter is told through its page (see
    /// `Heartbeat::set_system_stopping`).
    pub fn system_stopping(&self) {
        self.page.set_system_stopping();
    }

    /// A new voter took over the page: it is judged from `now` on.
    pub fn restart(&mut self, now: Instant) {
        self.last = self.page.read().beats;
        self.since = now;
    }

    /// How long the voter has made no progress, once that is longer than its deadline;
    /// `None` while it beats, or once it is ending (its own limits bound its last waits).
    pub fn stalled(&mut self, now: Instant) -> Option<Duration> {
        let pulse = self.page.read();
        if pulse.ending {
            return None;
        }
        if pulse.beats != self.last {
            self.last = pulse.beats;
            self.since = now;
            return None;
        }
        let still = now.saturating_duration_since(self.since);
        (still > self.deadline).then_some(still)
    }
}

/// How long a voter may go without a beat: the longest it may legitimately block inside one
/// turn of its loop, with room to spare. That is a recovery by fork of every replica, each
/// waiting up to `restart_timeout_ms` for its child and up to a second for the faulty
/// replica to be gone, plus two seconds for the machine being busy.
pub fn stall_deadline(c: &ComponentPlan) -> Duration {
    let per_replica = Duration::from_millis(c.restart_timeout_ms) + Duration::from_secs(1);
    Duration::from_secs(2) + per_replica * c.replicas.max(1) as u32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_voter_is_stalled_only_when_its_counter_stands_still_past_the_deadline() {
        let page = Heartbeat::create().unwrap();
        let voter = Heartbeat::adopt(
            std::os::fd::AsFd::as_fd(&page)
                .try_clone_to_owned()
                .unwrap(),
        )
        .unwrap();
        let t0 = Instant::now();
        let mut w = VoterWatch {
            page,
            deadline: Duration::from_secs(1),
            last: 0,
            since: t0,
        };
        assert_eq!(w.stalled(t0 + Duration::from_millis(900)), None);
        assert_eq!(
            w.stalled(t0 + Duration::from_millis(1500)),
            Some(Duration::from_millis(1500))
        );
        voter.beat();
        assert_eq!(w.stalled(t0 + Duration::from_millis(1600)), None);
        assert_eq!(w.stalled(t0 + Duration::from_millis(2500)), None);
        assert!(w.stalled(t0 + Duration::from_millis(2700)).is_some());
        voter.set_ending();
        assert_eq!(w.stalled(t0 + Duration::from_secs(60)), None);
    }
}
