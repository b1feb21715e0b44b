//! Fault reports held back until the donor of their recovery has been asked to fork.
//!
//! Writing a fault's event wakes whoever reads the events (bootstrap, or the bench). That
//! reader is an ordinary time-shared process, and an idle CPU, often the replicas', is where
//! the kernel puts it. The `RESTART` signal, a few microseconds later, then finds the donor's
//! CPU busy with the reader: the donor has to be woken with an interrupt instead of by
//! finding the CPU idle. Measured on a virtual machine where an interrupt between CPUs costs
//! a trap to the host, that added 11 µs to the signal and 24 µs to a restart (docs/results.md,
//! stop 36). So a fault's event is held until the donor has been signalled, and written while
//! the donor forks; its replica leaves the journal's table right after, so that a voter that
//! dies before has neither written the event nor cleared the slot, and its successor reports
//! the dead replica itself. (One that dies between the event and the clear has its fault
//! reported twice; bootstrap keeps it once, see `bootstrap/src/events.rs`.)
//!
//! Nothing is held across a wait: what is held is written before the loop's `ppoll`, before a
//! wait for a donor that is not asleep yet, for a dying replica's exit status or for the
//! replaced replica's death, before an exec, at the end of the input and at the shutdown;
//! and before every other event written (their order is kept) and every update of the
//! journal's table.

use std::cell::{Cell, RefCell};
use std::os::fd::OwnedFd;

use crate::event::Event;
use crate::journal::Journal;
use crate::ports::write_event;
use crate::vote::ReplicaSet;

/// The events of faults recorded and not written yet, each with the slot it emptied; and the
/// slots a release took out of the journal's table since [`HeldFaults::take_cleared`].
#[derive(Default)]
pub(crate) struct HeldFaults {
    held: RefCell<Vec<(Event, usize)>>,
    cleared: Cell<ReplicaSet>,
}

impl HeldFaults {
    /// Holds the event of the fault that emptied `slot`.
    pub(crate) fn hold(&self, event: Event, slot: usize) {
        self.held.borrow_mut().push((event, slot));
    }

    /// Writes the held events in the order they were recorded, each followed at once by its
    /// slot's removal from the journal's table. Does nothing if nothing is held.
    pub(crate) fn release(&self, events: Option<&OwnedFd>, journal: Option<&Journal>) {
        // Taken out first: nothing below borrows it again.
        let held = self.held.take();
        for (event, slot) in &held {
            write_event(events, event);
            if let Some(journal) = journal {
                crate::crashpoint::reached("fault-reported");
                journal.set_slot(*slot, None);
                self.cleared.set(self.cleared.get().with(*slot));
            }
        }
    }

    /// The slots released out of the journal's table since the last call (the voter's own
    /// record of what the table names must forget them).
    pub(crate) fn take_cleared(&self) -> ReplicaSet {
        self.cleared.take()
    }

    #[cfg(test)]
    fn len(&self) -> usize {
        self.held.borrow().len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::event::Cause;
    use std::io::Read;

    fn crash(slot: usize, pid: i32) -> Event {
        let mut ev = Event::caused("s", "c", Cause::Died);
        ev.replica = Some(slot);
        ev.pid = Some(pid);
        ev
    }

    fn written(r: OwnedFd) -> Vec<String> {
        let mut text = String::new();
        std::fs::File::from(r).read_to_string(&mut text).unwrap();
        text.lines().map(str::to_owned).collect()
    }

    /// Held events are written at the release, in the order of their faults, once; before it,
    /// nothing is written.
    #[test]
    fn held_events_are_written_at_the_release_in_order_and_once() {
        let (r, w) = nix::unistd::pipe().unwrap();
        let held = HeldFaults::default();
        held.hold(crash(2, 222), 2);
        held.hold(crash(0, 100), 0);
        assert_eq!(held.len(), 2);
        nix::fcntl::fcntl(
            &r,
            nix::fcntl::FcntlArg::F_SETFL(nix::fcntl::OFlag::O_NONBLOCK),
        )
        .unwrap();
        let mut probe = [0u8; 1];
        assert!(
            nix::unistd::read(&r, &mut probe).is_err(),
            "an event was written before the release"
        );
        held.release(Some(&w), None);
        held.release(Some(&w), None);
        drop(w);
        nix::fcntl::fcntl(
            &r,
            nix::fcntl::FcntlArg::F_SETFL(nix::fcntl::OFlag::empty()),
        )
        .unwrap();
        let lines = written(r);
        assert_eq!(lines.len(), 2, "{lines:?}");
        assert!(lines[0].contains("\"pid\":222"), "{}", lines[0]);
        assert!(lines[1].contains("\"pid\":100"), "{}", lines[1]);
        assert_eq!(held.len(), 0);
    }

    /// A held fault's replica stays in the journal's table until its event is written: a
    /// successor that takes over before then finds it there, dead, and reports it itself.
    #[test]
    fn the_slot_leaves_the_journal_with_its_event() {
        let json = r#"{"system":"s","component":"c","exec":"/bin/true","args":[],"replicas":3,
            "timeout_us":1000,"inputs":[{"name":"in","fd":3,"max_frame":64}],
            "outputs":[{"name":"out","fd":4,"max_frame":64}],"rounds":[],
            "events_fd":null,"socket_path":"/nonexistent"}"#;
        let plan: crate::plan::VoterPlan = serde_json::from_str(json).unwrap();
        let fd = replica_rt::shared::memfd(c"journal").unwrap();
        let keep = fd.try_clone().unwrap();
        let journal = Journal::create(fd, &plan).unwrap();
        let entry = |pid| crate::journal::SlotEntry {
            pid,
            start_time: 7,
            state_lost: false,
            proven: true,
            offsets: [0; replica_rt::contract::MAX_PORTS],
        };
        journal.set_slot(0, Some(entry(100)));
        journal.set_slot(1, Some(entry(111)));
        let slots = || {
            Journal::open(keep.try_clone().unwrap(), &plan)
                .unwrap()
                .1
                .slots
        };
        let held = HeldFaults::default();
        held.hold(crash(1, 111), 1);
        assert_eq!(
            slots()[1].map(|e| e.pid),
            Some(111),
            "cleared before its event"
        );
        let (_r, w) = nix::unistd::pipe().unwrap();
        held.release(Some(&w), Some(&journal));
        let after = slots();
        assert_eq!(after[1].map(|e| e.pid), None, "still named after its event");
        assert_eq!(held.take_cleared().iter().collect::<Vec<_>>(), vec![1]);
        assert_eq!(
            held.take_cleared().iter().count(),
            0,
            "each cleared slot is said once"
        );
        assert_eq!(
            after[0].map(|e| e.pid),
            Some(100),
            "another slot was cleared"
        );
    }
}
