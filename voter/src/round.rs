//! A reactive round (S³RES's timed pair): one input frame, one expected answer per output from
//! every replica, one deadline (parallel), or one deadline per replica's turn (sequential).

use std::time::Duration;

use crate::clock::Instant;
use crate::starvation::{self, Sample, Window};

use crate::vote::{ReplicaSet, MAX_REPLICAS};

/// Set of output indices (bitmask; a component has at most `MAX_PORTS` ports).
pub type OutputSet = u32;

#[derive(Debug)]
pub struct Round {
    pub number: u64,
    /// The timed pair that opened it (the index of its input).
    pub pair: usize,
    /// Outputs every replica must answer on.
    pub expected: OutputSet,
    /// When the round (parallel) or the current turn (sequential) must be complete.
    pub deadline: Instant,
    /// Sequential schedule: the replica whose turn it is (the one a missed deadline blames).
    /// `None` in a parallel round, and before the first turn.
    pub turn: Option<usize>,
    /// Replicas the input was delivered to.
    pub members: ReplicaSet,
    /// Per replica: outputs it has answered (a fixed array: no allocation per round).
    pub answered: [OutputSet; MAX_REPLICAS],
    /// Outputs whose winner has been forwarded.
    pub forwarded: OutputSet,
    /// Outputs whose frame was held back: it stood on one replica's word and its anomaly
    /// detector alarmed.
    pub held: OutputSet,
    /// The look at the replicas not done yet, a window before the deadline (see
    /// `starvation.rs`).
    pub look: Option<Look>,
    /// What the second look, just before the deadline, found: the replicas that could not
    /// run since the first.
    pub starved: Option<ReplicaSet>,
    /// How far the deadline has been moved on for replicas that could not run.
    pub extended: Duration,
    /// How long after it was due the voter took its second look before this deadline (see
    /// `starvation::voter_held_up`).
    pub looked_late: Duration,
    /// Per replica, what its windows so far leave for its next verdict (see `starvation.rs`).
    pub stalls: [Stall; MAX_REPLICAS],
    /// Sequential schedule: the replica whose turn it is, if it had to be raised above its
    /// siblings to run (found starved); put back to rest when its turn ends.
    pub raised: Option<usize>,
    /// Sequential schedule: when the loop last read the answers it does not wait for (see
    /// `ReactiveVoter::watched`).
    pub checked: Option<Instant>,
}

/// What a late replica's windows so far leave for its next verdict (see `starvation.rs`);
/// the default for most.
#[derive(Debug, Clone, Copy, Default)]
pub struct Stall {
    /// How many more windows count as starved because it came back from a long wait for a
    /// CPU (see `starvation::windows_after_coming_back`).
    pub came_back: u32,
    /// How long it has been found starved in a row, window after window (see
    /// `starvation::after_starving`).
    pub starved_for: Duration,
}

impl Stall {
    /// The verdict on a window, from the rule's own (`starvation::judge`) and what the
    /// windows before it left: back from a stretch without a CPU, or still in a backlog.
    pub fn verdict(self, own: Window) -> Window {
        starvation::after_coming_back(
            starvation::after_starving(own, self.starved_for),
            self.came_back > 0,
        )
    }

    /// What is left for the next window after one of `span` judged `own` by the rule (its
    /// verdict in the end: [`Stall::verdict`]), in which the replica's booked wait grew by
    /// `waited`.
    pub fn after_window(self, own: Window, waited: Duration, span: Duration) -> Stall {
        Stall {
            came_back: match self.verdict(own) {
                Window::CameBack => {
                    starvation::windows_after_coming_back(waited.max(self.starved_for), span)
                }
                _ => self.came_back.saturating_sub(1),
            },
            // Only windows starved by the rule itself make a streak: those starved for a
            // backlog do not (a spinner would otherwise come back again and again).
            starved_for: match own {
                Window::Starved => self.starved_for + span,
                _ => Duration::ZERO,
            },
        }
    }

    /// A window the voter passed over (it woke up past its look, held up as much as anyone):
    /// part of the stretch without a CPU.
    pub fn passed_over(&mut self, window: Duration) {
        self.starved_for += window;
    }
}

/// What the replicas that had not answered had run and waited, at one moment.
#[derive(Debug, Clone, Copy)]
pub struct Look {
    pub at: Instant,
    /// When its reads were done (the first look at a replica opens its task clock, 20–260
    /// µs): the second look cannot come sooner, whatever it was due.
    pub done: Instant,
    /// Per replica, its times and when they were read (its task clock counts only from its
    /// opening, at the replica's first look: see `starvation.rs`).
    pub times: [Option<(Sample, Instant)>; MAX_REPLICAS],
}

impl Round {
    pub fn new(
        number: u64,
        pair: usize,
        expected: OutputSet,
        deadline: Instant,
        members: ReplicaSet,
    ) -> Self {
        Round {
            number,
            pair,
            expected,
            deadline,
            turn: None,
            members,
            answered: [0; MAX_REPLICAS],
            forwarded: 0,
            held: 0,
            look: None,
            starved: None,
            extended: Duration::ZERO,
            looked_late: Duration::ZERO,
            stalls: [Stall::default(); MAX_REPLICAS],
            raised: None,
            checked: None,
        }
    }

    pub fn expects(&self, output: usize) -> bool {
        self.expected & (1 << output) != 0
    }

    pub fn has_answered(&self, replica: usize, output: usize) -> bool {
        self.answered[replica] & (1 << output) != 0
    }

    /// Whether `replica` has answered every expected output.
    pub fn is_done_by(&self, replica: usize) -> bool {
        self.answered[replica] & self.expected == self.expected
    }

    pub fn outputs(&self) -> impl Iterator<Item = usize> + '_ {
        (0..32).filter(|&o| self.expects(o))
    }
}
