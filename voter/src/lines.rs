//! An unmodified program's lines across a voter's death (see "Lines" in `journal.rs`).
//!
//! A program run with the preload library reads lines on stdin through C stdio and writes its
//! answers on stdout: it can neither count what it read nor take fresh pipes from a new voter.
//! So when bootstrap keeps a journal for its voter (`plan.park_fds`), nothing the program
//! holds may die with the voter:
//!
//! - **its pipes** are parked (`park.rs`) as each replica starts: the voter's ends of its stdin,
//!   stdout and stderr, and of the staging pipe beside its stdin. A successor takes them over
//!   ([`crate::adopt::parked_replicas`]);
//! - **each line** goes through the staging pipe, journaled between the `write` into it and
//!   the `splice` out of it ([`give_line`]), so that a successor gives every line once;
//! - **each answer** stays in the program's stdout until its round is committed, and is then
//!   taken with one `read` into the journal ([`Core::take_committed_answers`]), so that a
//!   successor finds the answers of an unfinished round still there, and drops those of a
//!   committed one exactly once.
//!
//! The numbers are the component's numbering of input frames (`Core::delivered`): a replica
//! that was given `given` lines and whose `taken` answers were taken answers line `taken + 1`
//! next. A fresh or forked replica starts at the frames delivered so far (a fork happens at a
//! quiet point, where its donor has answered every line).

use std::os::fd::{AsFd, BorrowedFd};

use crate::core::Core;
use crate::crashpoint;
use crate::event::Cause;
use crate::journal::{Journal, LineCounts};
use crate::park::Parked;
use crate::replica::Replica;

/// What an adopting voter found of its predecessor's lines, for its `voter_restart` event.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct LinesFound {
    /// Replicas with a line (or its rest) in their staging pipe.
    pub(crate) staged: usize,
    /// Answers to committed rounds still in the replicas' pipes, to be taken.
    pub(crate) to_take: u64,
    /// Lines of the unfinished round given already (not given again).
    pub(crate) given_ahead: u64,
}

impl std::fmt::Display for LinesFound {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "lines: {} in staging pipes, {} given before, {} answers of committed rounds to take",
            self.staged, self.given_ahead, self.to_take
        )
    }
}

impl Core {
    /// Whether this voter's replicas are an unmodified program's with parked pipes.
    pub(crate) fn parks_lines(&self) -> bool {
        self.park.is_some()
    }

    /// Parks the pipes of the new replica in `slot` and journals where it starts, before the
    /// journal names it (a successor takes over only a replica it finds both parked and
    /// named). Returns `false` if it could not be parked: a successor would not adopt it.
    pub(crate) fn park_new_replica(&mut self, slot: usize, start_time: u64) -> bool {
        let delivered = self.delivered.first().copied().unwrap_or(0);
        let (Some(park), Some(journal), Some(rep)) = (
            self.park.as_mut(),
            self.journal.as_ref(),
            self.slots[slot].as_mut(),
        ) else {
            return false;
        };
        let at = *rep.lines.get_or_insert(LineCounts {
            given: delivered,
            moved: delivered,
            taken: delivered,
        });
        let (Some(input), Some(output), Some(stderr)) =
            (rep.inputs.first(), rep.outputs.first(), rep.stderr.fd())
        else {
            return false;
        };
        let Some(staging) = input.writer.staging() else {
            return false;
        };
        let [staging_r, staging_w] = staging.ends();
        let fds: [BorrowedFd<'_>; 5] = [
            input.writer.as_fd(),
            output.as_fd(),
            stderr.as_fd(),
            staging_r,
            staging_w,
        ];
        let who = Parked {
            slot,
            pid: rep.pid,
            start_time,
        };
        if let Err(e) = park.park(who, &fds) {
            tracing::warn!(replica = slot, pid = rep.pid, error = %e, "could not park the replica's pipes: a successor of this voter would not adopt it");
            return false;
        }
        journal.set_lines(slot, at);
        if park.queued() > 2 * self.slots.len() {
            self.compact_parked();
        }
        true
    }

    /// Drops from the parking queue every set whose replica is no longer in its slot.
    fn compact_parked(&mut self) {
        let live: Vec<Option<libc::pid_t>> = self
            .slots
            .iter()
            .map(|s| s.as_ref().map(|r| r.pid))
            .collect();
        let Some(park) = self.park.as_mut() else {
            return;
        };
        let keep = |who: &Parked| live.get(who.slot).copied().flatten() == Some(who.pid);
        if let Err(e) = park.rotate(keep) {
            tracing::warn!(error = %e, "could not compact the parked pipes");
        }
    }

    /// Whether every replica stands where a fork may copy it: given every line delivered,
    /// moved whole into its stdin, and answered each (the answers decoded, nothing after
    /// them). An adopting voter replaying its predecessor's unfinished round is not there
    /// yet: a child forked then would be given a line its donor already has.
    pub(crate) fn lines_quiet(&self) -> bool {
        let delivered = self.delivered.first().copied().unwrap_or(0);
        self.slots.iter().flatten().all(|rep| {
            let (Some(at), Some(decoded), Some(out)) = (
                rep.lines.as_ref(),
                rep.answers_decoded(),
                rep.outputs.first(),
            ) else {
                return true;
            };
            at.given == delivered
                && at.moved == at.given
                && decoded == at.given
                && out.decoder.pending() == 0
        })
    }

    /// Whether some replica's stdout holds answers not taken yet: the last round was not
    /// committed (downstream is slow, or a replay is under way). A new round waits for the
    /// commit (unless the predecessor's input is still being replayed), so that a program's
    /// stdout never fills with answers the voter holds.
    pub(crate) fn answers_untaken(&self) -> bool {
        self.slots
            .iter()
            .flatten()
            .any(|rep| rep.outputs.iter().any(|o| o.untaken_lines() > 0))
    }

    /// Between rounds: a replica that answered its line without reading all of it (some is
    /// still in its staging pipe or queued) is faulty; it would hold every commit back. (Not
    /// while a predecessor's input is replayed: a line moved on at the adoption may still be
    /// on its way into a replica that has not answered it.)
    pub(crate) fn fault_unread_lines(&mut self) {
        if self.replaying() {
            return;
        }
        let unread: Vec<usize> = (0..self.slots.len())
            .filter(|&r| {
                self.slots[r].as_ref().is_some_and(|rep| {
                    let answered = rep
                        .lines
                        .as_ref()
                        .is_some_and(|at| rep.answers_decoded() == Some(at.given));
                    answered && rep.inputs.iter().any(|i| i.writer.has_pending())
                })
            })
            .collect();
        for r in unread {
            let detail = "answered its line without reading all of it".to_owned();
            self.record_fault(r, Cause::UnexpectedFrame, detail, None);
        }
    }

    /// After replica `r`'s stdin took more: journals the line in its staging pipe as moved
    /// once none of it is left there.
    pub(crate) fn note_moved(&mut self, r: usize) {
        let (Some(journal), Some(rep)) = (self.journal.as_ref(), self.slots[r].as_mut()) else {
            return;
        };
        let (Some(lines), Some(input)) = (rep.lines.as_mut(), rep.inputs.first()) else {
            return;
        };
        if input.writer.staging().is_some()
            && !input.writer.has_pending()
            && lines.moved < lines.given
        {
            journal.set_moved(r, lines.given);
            lines.moved = lines.given;
        }
    }

    /// Answers of replica `r` to skip before a round may take one: those to rounds committed
    /// already (a successor finds them still in the pipe; they were voted before).
    pub(crate) fn answers_to_skip(&self, r: usize) -> u64 {
        let (Some(journal), Some(decoded)) = (
            self.journal.as_ref(),
            self.slots[r].as_ref().and_then(Replica::answers_decoded),
        ) else {
            return 0;
        };
        journal.delivered_at(0).saturating_sub(decoded)
    }

    /// Passes over the answers replica `r` gave to rounds committed already (they are decoded,
    /// for [`take_committed_answers`](Self::take_committed_answers) to take, never voted
    /// again). `Err`: its stdout breaks the framing.
    pub(crate) fn decode_committed_answers(&mut self, r: usize) -> Result<(), String> {
        let mut skip = self.answers_to_skip(r);
        while skip > 0 {
            let Some(out) = self.slots[r]
                .as_mut()
                .and_then(|rep| rep.outputs.first_mut())
            else {
                return Ok(());
            };
            match out.next_answer() {
                Ok(Some(_)) => skip -= 1,
                Ok(None) => return Ok(()),
                Err(e) => return Err(format!("output `{}`: {e}", self.plan.outputs[0].name)),
            }
        }
        Ok(())
    }

    /// Whether replica `r`'s next answer is to a line it was given whose round is not open
    /// (an adopting voter's replay opens it once it reads that line again): the answer stays
    /// in the pipe until then, instead of counting as a frame outside any round.
    pub(crate) fn answer_before_its_round(&self, r: usize) -> bool {
        let Some(rep) = self.slots[r].as_ref() else {
            return false;
        };
        match (rep.lines.as_ref(), rep.answers_decoded()) {
            (Some(at), Some(decoded)) => decoded < at.given,
            _ => false,
        }
    }

    /// An adopting voter: the answers to rounds its predecessor committed, still in the
    /// pipes, are taken now, before any round opens (a program whose stdout holds one answer
    /// only would otherwise block on the next).
    pub(crate) fn take_answers_left_behind(&mut self) {
        for r in 0..self.slots.len() {
            let Some(rep) = self.slots[r].as_mut() else {
                continue;
            };
            if let Some(out) = rep.outputs.first_mut() {
                let _ = out.fill();
            }
            if let Err(detail) = self.decode_committed_answers(r) {
                self.record_fault(r, Cause::BadFrame, detail, None);
            }
        }
        self.take_committed_answers();
    }

    /// Takes off every replica's stdout the answers to committed rounds (into the journal,
    /// see [`crate::journal::Journal::take_line`]). A replica whose pipe does not hold what
    /// was peeked is faulty.
    pub(crate) fn take_committed_answers(&mut self) {
        let Some(journal) = self.journal.as_mut() else {
            return;
        };
        let committed = journal.delivered_at(0);
        let mut broken = Vec::new();
        for (r, rep) in self.slots.iter_mut().enumerate() {
            let Some(rep) = rep.as_mut() else { continue };
            let (Some(lines), Some(out)) = (rep.lines.as_mut(), rep.outputs.first_mut()) else {
                continue;
            };
            while lines.taken < committed {
                let Some(line) = out.front_line() else { break };
                if let Err(e) = journal.take_line(r, out.as_fd(), line) {
                    broken.push((r, e));
                    break;
                }
                out.took_front_line();
                lines.taken += 1;
            }
        }
        for (r, e) in broken {
            let detail = format!("taking its answer off stdout: {e}");
            self.record_fault(r, Cause::PipeError, detail, None);
        }
    }

    /// An adopting voter: where each adopted replica of its predecessor stands. A line found
    /// in a staging pipe is moved on (and counted as given if the predecessor died before it
    /// said so); the counts are journaled again as resolved. A replica that was not given
    /// every committed line cannot be (it would have answered them) and is given up.
    pub(crate) fn resume_lines(&mut self) -> (Vec<crate::adopt::Lost>, LinesFound) {
        let committed = self.delivered.first().copied().unwrap_or(0);
        let mut lost = Vec::new();
        let mut found = LinesFound::default();
        for slot in 0..self.slots.len() {
            let (Some(journal), Some(rep)) = (self.journal.as_ref(), self.slots[slot].as_mut())
            else {
                continue;
            };
            let pid = rep.pid;
            let held = rep
                .inputs
                .first()
                .and_then(|i| i.writer.staging())
                .map_or(0, |s| s.held());
            let Some(at) = rep.lines.as_mut() else {
                continue;
            };
            if held > 0 && at.moved == at.given {
                // Written whole, and the predecessor died before it journaled the number.
                at.given += 1;
            } else if held == 0 && at.moved < at.given {
                // Moved whole, and the predecessor died before it journaled that.
                at.moved = at.given;
            }
            let at = *at;
            found.staged += usize::from(held > 0);
            found.to_take += committed.saturating_sub(at.taken);
            found.given_ahead += at.given.saturating_sub(committed);
            if at.given < committed || at.taken > at.given {
                tracing::warn!(
                    replica = slot,
                    pid,
                    ?at,
                    committed,
                    "adopted replica's lines do not add up; replacing it"
                );
                rep.kill();
                self.slots[slot] = None;
                lost.push(crate::adopt::Lost {
                    slot,
                    pid,
                    died: false,
                    why: Some("its lines given and answers taken did not add up; killed"),
                });
                continue;
            }
            journal.set_lines(slot, at);
            let flushed = rep.inputs[0].writer.flush();
            if let Err(e) = flushed {
                tracing::warn!(replica = slot, pid, error = %e, "the adopted replica's stdin broke");
            }
            self.note_moved(slot);
            // Parked and named already: not again.
            self.journaled_pids[slot] = pid;
        }
        (lost, found)
    }

    /// The end, on purpose: the parked copies of the replicas' pipes go, so that the program
    /// sees the end of its input when the voter closes its own ends.
    pub(crate) fn release_parked(&mut self) {
        if let Some(park) = self.park.as_mut() {
            if let Err(e) = park.release() {
                tracing::warn!(error = %e, "could not release the parked pipes");
            }
        }
    }
}

/// Gives line `number` (`frame`) to replica `r` on input `i`: into its staging pipe, the
/// number journaled, then moved on into its stdin as far as it takes it now. A line it was
/// given before (by a predecessor: a replayed round) is not given again.
///
/// Returns whether the replica answers the line in the pipe this voter reads: not a
/// replica started after the line's round closed (a fork child has the line in its
/// donor's memory, and its answer lies in the donor's pipe), which a successor replaying
/// that round finds with the answer counted as taken.
pub(crate) fn give_line(
    journal: &Journal,
    r: usize,
    rep: &mut Replica,
    i: usize,
    frame: &[u8],
    number: u64,
) -> std::io::Result<bool> {
    let Some(lines) = rep.lines.as_mut() else {
        return Err(std::io::Error::other("a replica not journaled yet"));
    };
    if lines.given >= number {
        return Ok(lines.taken < number);
    }
    let writer = &mut rep.inputs[i].writer;
    writer.send(frame)?;
    crashpoint::reached("line-staged");
    journal.set_given(r, number);
    lines.given = number;
    crashpoint::reached("line-given");
    writer.flush()?;
    crashpoint::reached("line-moved");
    if !writer.has_pending() {
        journal.set_moved(r, number);
        lines.moved = number;
    }
    Ok(true)
}
