//! The voter's journal: what a successor needs to take a component over when this voter dies —
//! the replicas (pid, start time, state kept or lost, and in stream mode where each one's
//! frames stand on every output), and the input frames taken since the last commit together
//! with where every channel stood then.
//!
//! It lives in a memfd that bootstrap made and keeps (`plan.journal_fd`), mapped shared
//! ([`SharedRegion`]). Nothing in it needs the voter to be alive, or to have finished what it
//! was doing, to be right: a SIGKILL lands between any two instructions, and the journal is
//! built so that every such point leaves it saying something true.
//!
//! **Two records and a switch.** A record holds a *committed state* (rounds started; per
//! input, where its decoder stood and how many frames were delivered to the replicas; per
//! output, how many frames were forwarded) and, per input, a *log* of the bytes taken off the
//! channel since. The header's `current` word names the record in force. A commit fills the
//! other record — its state, and an empty log — and then flips `current` with one atomic
//! store: before the store the old record is in force, after it the new one.
//!
//! **Taking bytes off a channel is the journal entry.** The voter peeks its inputs (`tee(2)`)
//! and takes a frame off the pipe only once it has decoded it, with one `read(2)` straight
//! into the log ([`Journal::take`]). Before that read, it writes a marker at the position the
//! read starts at and at the one it will end at. A successor walks the log frame by frame
//! from its start and stops at the first marker: the marker no read has covered. No frame
//! header can be the marker (`0xffff_ffff`: a control word, and not one that exists), so
//! "the frame is in the log" and "the frame is gone from the pipe" come true in the same
//! system call, and a SIGKILL lands before both or after both.
//!
//! A successor thus finds: the state at the last commit, and every byte taken since, which it
//! replays to the replicas behind `RESUME` (they drop what they already took, and answer a
//! replayed round again from their last frames), and whose rounds' outputs it forwards
//! behind `RESUME` with the committed output counts (downstream drops a repeat).
//!
//! The replica table is not part of a record: each slot's entry is rewritten in place when
//! the slot changes. An entry torn by a SIGKILL names a pid whose start time does not match,
//! and the successor treats that slot as empty (it forks it from a sibling).
//!
//! **Lines (an unmodified program).** Its replicas neither count their input nor answer a
//! replayed round again, so a successor must know, per replica, which lines it was given and
//! which answers were taken off its stdout; their pipes outlive the voter (`park.rs`). Per
//! slot the journal keeps three counts in the component's numbering of input frames:
//! - *given*: lines written, each with one `write`, into a staging pipe beside the replica's
//!   stdin (stored after the write); *moved*: lines moved whole from there into its stdin with
//!   `splice` (stored once the staging pipe is empty). A successor that finds bytes in the
//!   staging pipe moves them on: they are line `given + 1` if `moved == given` (the voter died
//!   between the write and the store), else the rest of line `given`. One that finds it empty
//!   with `moved < given` knows that line moved whole. No line is lost or given twice.
//! - *taken*: answers read off the replica's stdout. The voter peeks answers (`tee`) and takes
//!   one only once its round is committed, with one `read` straight into a journal slot it
//!   filled beforehand with the complement of the bytes it peeked, a copy of which lies beside
//!   it ([`Journal::take_line`]): a successor that finds the slot equal to the copy knows the
//!   answer was taken, one that finds the complement knows it is still in the pipe (no byte
//!   equals its complement). So a committed round's answers are dropped exactly once, and an
//!   unfinished round's are still in the pipes for the successor to vote on.

use std::io;
use std::os::fd::{BorrowedFd, OwnedFd};
use std::sync::atomic::Ordering;

use replica_rt::shared::SharedRegion;

use crate::clock::{Clock, Source};
use crate::plan::VoterPlan;
use replica_rt::contract::MAX_PORTS;
use replica_rt::frame::{CONTROL_BIT, HEADER_LEN, RESUME, RESUME_LEN};

/// "s3resjnl", the header's first word.
const MAGIC: u64 = u64::from_le_bytes(*b"s3resjnl");
/// Layout version (a successor refuses a journal of another layout).
const VERSION: u64 = 3;
/// What no frame header is: written where the next read into a log starts and ends.
const MARKER: u32 = u32::MAX;
const PAGE: usize = 4096;
/// The header: identification, `current`, and the replica table.
const HEADER: usize = PAGE;
const OFF_MAGIC: usize = 0;
const OFF_VERSION: usize = 8;
const OFF_INPUTS: usize = 16;
const OFF_OUTPUTS: usize = 24;
const OFF_SLOTS: usize = 32;
const OFF_LOG_CAP: usize = 40;
const OFF_CURRENT: usize = 48;
/// The deadline clock's calibration: source (0 none, 1 tsc, 2 cntvct), Hz and ppm as f64 bits.
const OFF_CLOCK_SOURCE: usize = 56;
const OFF_CLOCK_HZ: usize = 64;
const OFF_CLOCK_PPM: usize = 72;
const OFF_TABLE: usize = 256;
/// Per slot: pid (0: none), start time (clock ticks since boot), flags.
const SLOT_LEN: usize = 24;
const FLAG_STATE_LOST: u64 = 1;
const FLAG_PROVEN: u64 = 2;
/// Stream mode, per slot and output: the number on the output of the slot's process's frame 0
/// (`Ledger`'s `pos - received`), written with the slot's entry.
const OFF_OFFSETS: usize = 1024;
const OFFSETS_LEN: usize = 8 * MAX_PORTS;
/// Lines, per slot: given, moved, taken, and the take in progress: its answer's number and
/// length (see "Lines" above). After the stream outputs' counts (`OFF_WRITTEN`).
const OFF_LINES: usize = 3584;
const LINES_LEN: usize = 40;
/// Stream mode, per output: frames written whole downstream, updated as they go (not part of
/// a record: a stream successor goes on from there whatever its input commit says).
const OFF_WRITTEN: usize = 3072;

/// Where one input stood at a commit.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct InputState {
    /// The channel decoder's position (`FrameDecoder::position`).
    pub taken: u64,
    pub next_index: u64,
    /// Frames delivered to the replicas on this input, since the component started: the
    /// numbering every replica's decoder of this input counts in.
    pub delivered: u64,
}

/// What a commit records.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Committed {
    pub rounds_started: u64,
    pub inputs: Vec<InputState>,
    /// Frames forwarded per output.
    pub forwarded: Vec<u64>,
}

/// One slot of the replica table.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct SlotEntry {
    pub pid: libc::pid_t,
    pub start_time: u64,
    pub state_lost: bool,
    pub proven: bool,
    /// Stream mode: per output, the number of the process's frame 0 on it (up to
    /// `MAX_PORTS` outputs; unused in reactive mode).
    pub offsets: [u64; MAX_PORTS],
}

/// Where an unmodified program's replica stands, in the component's numbering of input
/// frames (see "Lines" above).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LineCounts {
    /// Lines written into its staging pipe.
    pub given: u64,
    /// Lines moved whole from the staging pipe into its stdin.
    pub moved: u64,
    /// Answers taken off its stdout.
    pub taken: u64,
}

/// What a successor finds.
#[derive(Debug)]
pub(crate) struct Found {
    pub committed: Committed,
    /// Per input: the bytes taken off the channel since the commit, whole frames.
    pub logs: Vec<Vec<u8>>,
    pub slots: Vec<Option<SlotEntry>>,
    /// An unmodified program: per slot, its counts, a take in progress resolved (else empty).
    pub lines: Vec<LineCounts>,
}

/// The journal, mapped.
pub(crate) struct Journal {
    region: SharedRegion,
    inputs: usize,
    outputs: usize,
    slots: usize,
    log_cap: usize,
    state_len: usize,
    /// An unmodified program: room for one answer as it lies in the pipe (0 otherwise); each
    /// slot has two, for the copy and the take.
    take_cap: usize,
    /// The record in force.
    current: usize,
    /// Per input: bytes in the current record's log.
    log_len: Vec<usize>,
    /// Per input: where in the current record's log the last take began, and its length.
    last_take: Vec<Option<(usize, usize)>>,
    /// Bytes carried from one record's log to the next, kept for its capacity.
    carry_buf: Vec<u8>,
}

#[derive(Debug, thiserror::Error)]
pub(crate) enum JournalError {
    #[error("journal: {0}")]
    Io(#[from] io::Error),
    #[error("journal does not match this component: {0}")]
    Mismatch(String),
}

/// A log holds at least two of the largest frames with their resume frames (rounds may run
/// ahead of a commit while downstream is slow), and never less than 64 KiB.
fn log_cap(max_frame: usize) -> usize {
    let want = (2 * (max_frame + HEADER_LEN + 2 * RESUME_LEN) + 8).max(64 * 1024);
    want.next_multiple_of(PAGE)
}

impl Journal {
    /// The journal of `plan`'s shape in `region`, with record `current` in force.
    fn shaped(region: SharedRegion, plan: &VoterPlan, current: usize) -> Journal {
        let (log_cap, state_len) = Self::layout(plan);
        Journal {
            region,
            inputs: plan.inputs.len(),
            outputs: plan.outputs.len(),
            slots: plan.replicas,
            log_cap,
            state_len,
            take_cap: take_cap(plan),
            current,
            log_len: vec![0; plan.inputs.len()],
            last_take: vec![None; plan.inputs.len()],
            carry_buf: Vec::new(),
        }
    }

    fn layout(plan: &VoterPlan) -> (usize, usize) {
        let max = plan.inputs.iter().map(|p| p.max_frame).max().unwrap_or(0);
        let state_len =
            (8 + 24 * plan.inputs.len() + 8 * plan.outputs.len()).next_multiple_of(PAGE);
        (log_cap(max), state_len)
    }

    fn record_len(&self) -> usize {
        self.state_len + self.inputs * self.log_cap
    }

    fn record(&self, r: usize) -> usize {
        HEADER + r * self.record_len()
    }

    /// The whole journal's length.
    fn len(&self) -> usize {
        HEADER + 2 * self.record_len() + 2 * self.slots * self.take_cap
    }

    /// Where slot `s`'s copy of the answer being taken lies; the take itself follows it.
    fn take_area(&self, s: usize) -> usize {
        HEADER + 2 * self.record_len() + 2 * s * self.take_cap
    }

    fn log(&self, r: usize, i: usize) -> usize {
        self.record(r) + self.state_len + i * self.log_cap
    }

    /// A new journal in the (empty) memfd `fd`: nothing delivered, nothing forwarded.
    pub(crate) fn create(fd: OwnedFd, plan: &VoterPlan) -> Result<Journal, JournalError> {
        if OFF_OFFSETS + OFFSETS_LEN * plan.replicas > OFF_WRITTEN
            || OFF_WRITTEN + 8 * MAX_PORTS > OFF_LINES
            || OFF_LINES + LINES_LEN * plan.replicas > HEADER
            || plan.outputs.len() > MAX_PORTS
        {
            return Err(JournalError::Mismatch(format!(
                "{} replicas and {} outputs do not fit a journal's header",
                plan.replicas,
                plan.outputs.len()
            )));
        }
        let (log_cap, state_len) = Self::layout(plan);
        let record_len = state_len + plan.inputs.len() * log_cap;
        let takes = 2 * plan.replicas * take_cap(plan);
        let region = SharedRegion::sized(fd, HEADER + 2 * record_len + takes)?;
        let mut journal = Self::shaped(region, plan, 0);
        let h = &journal.region;
        h.u64_at(OFF_VERSION).store(VERSION, Ordering::Relaxed);
        h.u64_at(OFF_INPUTS)
            .store(journal.inputs as u64, Ordering::Relaxed);
        h.u64_at(OFF_OUTPUTS)
            .store(journal.outputs as u64, Ordering::Relaxed);
        h.u64_at(OFF_SLOTS)
            .store(journal.slots as u64, Ordering::Relaxed);
        h.u64_at(OFF_LOG_CAP)
            .store(log_cap as u64, Ordering::Relaxed);
        for i in 0..journal.inputs {
            let at = journal.log(0, i);
            journal.region.write_bytes(at, &MARKER.to_le_bytes());
        }
        journal
            .region
            .u64_at(OFF_CURRENT)
            .store(0, Ordering::Release);
        // Last: a successor that finds no magic finds no journal.
        journal
            .region
            .u64_at(OFF_MAGIC)
            .store(MAGIC, Ordering::Release);
        Ok(journal)
    }

    /// The journal a predecessor left in `fd`, and what it says.
    pub(crate) fn open(fd: OwnedFd, plan: &VoterPlan) -> Result<(Journal, Found), JournalError> {
        let region = SharedRegion::existing(fd)?;
        let word = |off| region.u64_at(off).load(Ordering::Acquire);
        if word(OFF_MAGIC) != MAGIC || word(OFF_VERSION) != VERSION {
            return Err(JournalError::Mismatch(
                "no journal of this version in it".into(),
            ));
        }
        let (log_cap, _) = Self::layout(plan);
        let dims = [
            (word(OFF_INPUTS), plan.inputs.len(), "inputs"),
            (word(OFF_OUTPUTS), plan.outputs.len(), "outputs"),
            (word(OFF_SLOTS), plan.replicas, "replicas"),
            (word(OFF_LOG_CAP), log_cap, "log size"),
        ];
        for (have, want, what) in dims {
            if have != want as u64 {
                return Err(JournalError::Mismatch(format!(
                    "{what}: {have}, plan says {want}"
                )));
            }
        }
        let current = (word(OFF_CURRENT) & 1) as usize;
        let mut journal = Self::shaped(region, plan, current);
        if journal.region.len() < journal.len() {
            return Err(JournalError::Mismatch("shorter than its layout".into()));
        }
        let committed = journal.read_state(current);
        let mut logs = Vec::with_capacity(journal.inputs);
        for (i, port) in plan.inputs.iter().enumerate() {
            let bytes = journal.read_log(current, i, port.max_frame);
            journal.log_len[i] = bytes.len();
            logs.push(bytes);
        }
        let slots = (0..journal.slots).map(|s| journal.slot(s)).collect();
        let lines = if journal.take_cap > 0 {
            (0..journal.slots).map(|s| journal.line_counts(s)).collect()
        } else {
            Vec::new()
        };
        Ok((
            journal,
            Found {
                committed,
                logs,
                slots,
                lines,
            },
        ))
    }

    fn read_state(&self, r: usize) -> Committed {
        let base = self.record(r);
        let word = |off: usize| self.region.u64_at(base + off).load(Ordering::Relaxed);
        Committed {
            rounds_started: word(0),
            inputs: (0..self.inputs)
                .map(|i| InputState {
                    taken: word(8 + 24 * i),
                    next_index: word(16 + 24 * i),
                    delivered: word(24 + 24 * i),
                })
                .collect(),
            forwarded: (0..self.outputs)
                .map(|o| word(8 + 24 * self.inputs + 8 * o))
                .collect(),
        }
    }

    /// The whole frames in log `i` of record `r`, up to the first marker.
    fn read_log(&self, r: usize, i: usize, max_frame: usize) -> Vec<u8> {
        let base = self.log(r, i);
        let mut at = 0;
        loop {
            if at + HEADER_LEN > self.log_cap {
                break;
            }
            let mut word = [0u8; HEADER_LEN];
            self.region.read_bytes(base + at, &mut word);
            let word = u32::from_le_bytes(word);
            let len = match word {
                MARKER => break,
                RESUME => RESUME_LEN,
                w if w & CONTROL_BIT != 0 => HEADER_LEN,
                w if (w as usize) <= max_frame => HEADER_LEN + w as usize,
                // Cannot have been written by a take: the log ends before it.
                _ => break,
            };
            if at + len + HEADER_LEN > self.log_cap {
                break;
            }
            at += len;
        }
        let mut bytes = vec![0u8; at];
        self.region.read_bytes(base, &mut bytes);
        bytes
    }

    /// Records the deadline clock's calibration, for a successor to take over.
    pub(crate) fn record_clock(&self, clock: &Clock) {
        let source = match clock.source() {
            Source::Tsc => 1,
            Source::Cntvct => 2,
            Source::Monotonic => 0,
        };
        let r = &self.region;
        r.u64_at(OFF_CLOCK_HZ)
            .store(clock.hz().to_bits(), Ordering::Relaxed);
        r.u64_at(OFF_CLOCK_PPM)
            .store(clock.error_ppm().to_bits(), Ordering::Relaxed);
        r.u64_at(OFF_CLOCK_SOURCE).store(source, Ordering::Release);
    }

    /// Whether log `i` has room for `n` more bytes (and the marker after them).
    pub(crate) fn has_room(&self, i: usize, n: usize) -> bool {
        self.log_len[i] + n + HEADER_LEN <= self.log_cap
    }

    /// Takes `n` bytes (whole frames, already peeked) off `fd` into log `i`, in one `read`.
    pub(crate) fn take(&mut self, i: usize, fd: BorrowedFd<'_>, n: usize) -> io::Result<()> {
        if !self.has_room(i, n) {
            return Err(io::Error::other(format!(
                "journal log of input {i} full ({} of {} bytes)",
                self.log_len[i], self.log_cap
            )));
        }
        let at = self.log(self.current, i) + self.log_len[i];
        self.region.write_bytes(at + n, &MARKER.to_le_bytes());
        self.region.write_bytes(at, &MARKER.to_le_bytes());
        let mut got = 0;
        // One read takes everything: the bytes are in the pipe (peeked) and nobody else reads
        // it. A short read would be a second entry; the loop only guards against surprises.
        while got < n {
            let k = self.region.read_from(fd, at + got, n - got)?;
            if k == 0 {
                return Err(io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    "peeked bytes gone from the pipe",
                ));
            }
            got += k;
        }
        self.last_take[i] = Some((self.log_len[i], n));
        self.log_len[i] += n;
        Ok(())
    }

    /// How many bytes the last take off input `i` since the commit moved (`None`: none since).
    pub(crate) fn last_take_len(&self, i: usize) -> Option<usize> {
        self.last_take[i].map(|(_, n)| n)
    }

    /// Commits `state`: the other record gets it, with empty logs except that the log of every
    /// input `i` with `carry[i]` starts with the bytes of the last take off it (a frame not yet
    /// written whole to every replica: `state` must stand before it); then it becomes the one
    /// in force.
    pub(crate) fn commit_carrying(&mut self, state: &Committed, carry: &[bool]) {
        let next = 1 - self.current;
        let base = self.record(next);
        let r = &self.region;
        r.u64_at(base)
            .store(state.rounds_started, Ordering::Relaxed);
        for (i, s) in state.inputs.iter().enumerate() {
            r.u64_at(base + 8 + 24 * i)
                .store(s.taken, Ordering::Relaxed);
            r.u64_at(base + 16 + 24 * i)
                .store(s.next_index, Ordering::Relaxed);
            r.u64_at(base + 24 + 24 * i)
                .store(s.delivered, Ordering::Relaxed);
        }
        for (o, &n) in state.forwarded.iter().enumerate() {
            r.u64_at(base + 8 + 24 * self.inputs + 8 * o)
                .store(n, Ordering::Relaxed);
        }
        // No allocation per commit: lengths on the stack, bytes in a buffer kept for it.
        let mut carried = [0usize; MAX_PORTS];
        let mut bytes = std::mem::take(&mut self.carry_buf);
        for (i, len) in carried.iter_mut().enumerate().take(self.inputs) {
            let at = self.log(next, i);
            if let Some((from, n)) = self.last_take[i].filter(|_| carry.get(i) == Some(&true)) {
                bytes.resize(n, 0);
                self.region
                    .read_bytes(self.log(self.current, i) + from, &mut bytes);
                self.region.write_bytes(at + n, &MARKER.to_le_bytes());
                self.region.write_bytes(at, &bytes);
                *len = n;
            } else {
                self.region.write_bytes(at, &MARKER.to_le_bytes());
            }
        }
        // The switch: one store.
        self.region
            .u64_at(OFF_CURRENT)
            .store(next as u64, Ordering::Release);
        self.current = next;
        for ((n, take), c) in self
            .log_len
            .iter_mut()
            .zip(&mut self.last_take)
            .zip(carried)
        {
            *n = c;
            // A carried frame is the new log's last take: still queued, it may be carried again.
            *take = (c > 0).then_some((0, c));
        }
        self.carry_buf = bytes;
    }

    /// Whether anything was taken since the last commit.
    pub(crate) fn uncommitted(&self) -> bool {
        self.log_len.iter().any(|&n| n > 0)
    }

    /// Stream mode: `n` frames of output `o` are written whole downstream.
    pub(crate) fn set_written(&self, o: usize, n: u64) {
        self.region
            .u64_at(OFF_WRITTEN + 8 * o)
            .store(n, Ordering::Release);
    }

    /// Stream mode: frames of output `o` written whole downstream, as last recorded.
    pub(crate) fn written(&self, o: usize) -> u64 {
        self.region
            .u64_at(OFF_WRITTEN + 8 * o)
            .load(Ordering::Acquire)
    }

    /// The count of frames forwarded on output `o` that the record in force holds.
    pub(crate) fn forwarded_at(&self, o: usize) -> u64 {
        let base = self.record(self.current) + 8 + 24 * self.inputs;
        self.region.u64_at(base + 8 * o).load(Ordering::Relaxed)
    }

    /// Frames delivered on input `i` that the record in force holds: every round up to that
    /// frame is committed.
    pub(crate) fn delivered_at(&self, i: usize) -> u64 {
        let base = self.record(self.current) + 24 + 24 * i;
        self.region.u64_at(base).load(Ordering::Relaxed)
    }

    /// Records who is in `slot` (`None`: nobody).
    pub(crate) fn set_slot(&self, slot: usize, entry: Option<SlotEntry>) {
        let at = OFF_TABLE + SLOT_LEN * slot;
        let r = &self.region;
        match entry {
            None => r.u64_at(at).store(0, Ordering::Release),
            Some(e) => {
                // The pid last: a torn entry has a pid whose start time does not match.
                r.u64_at(at).store(0, Ordering::Release);
                r.u64_at(at + 8).store(e.start_time, Ordering::Relaxed);
                let flags = if e.state_lost { FLAG_STATE_LOST } else { 0 }
                    | if e.proven { FLAG_PROVEN } else { 0 };
                r.u64_at(at + 16).store(flags, Ordering::Relaxed);
                let offsets = OFF_OFFSETS + OFFSETS_LEN * slot;
                for (o, &off) in e.offsets.iter().enumerate().take(self.outputs) {
                    r.u64_at(offsets + 8 * o).store(off, Ordering::Relaxed);
                }
                r.u64_at(at).store(e.pid as u64, Ordering::Release);
            }
        }
    }

    /// Marks the replica `pid` that `slot` names as proven (it has answered).
    pub(crate) fn mark_proven(&self, slot: usize, pid: libc::pid_t) {
        let at = OFF_TABLE + SLOT_LEN * slot;
        let r = &self.region;
        if r.u64_at(at).load(Ordering::Acquire) == pid as u64 {
            r.u64_at(at + 16).fetch_or(FLAG_PROVEN, Ordering::Relaxed);
        }
    }

    // ----- lines (see "Lines" in the module docs) --------------------------------------------

    fn lines_word(&self, slot: usize, k: usize) -> &std::sync::atomic::AtomicU64 {
        self.region.u64_at(OFF_LINES + LINES_LEN * slot + 8 * k)
    }

    /// Records where slot `slot`'s new replica starts (before [`set_slot`](Self::set_slot)
    /// names it), with no take in progress.
    pub(crate) fn set_lines(&self, slot: usize, at: LineCounts) {
        // The counts first, then the take cleared: a take a successor resolved as done stays
        // counted whichever store a SIGKILL comes between (a new replica's slot is not named
        // yet, so for it the order does not matter).
        self.lines_word(slot, 0).store(at.given, Ordering::Relaxed);
        self.lines_word(slot, 1).store(at.moved, Ordering::Relaxed);
        self.lines_word(slot, 2).store(at.taken, Ordering::Release);
        self.lines_word(slot, 3).store(0, Ordering::Release);
    }

    /// Line `n` is in slot `slot`'s staging pipe, written whole.
    pub(crate) fn set_given(&self, slot: usize, n: u64) {
        self.lines_word(slot, 0).store(n, Ordering::Release);
    }

    /// Line `n` has left slot `slot`'s staging pipe, whole, for its stdin.
    pub(crate) fn set_moved(&self, slot: usize, n: u64) {
        self.lines_word(slot, 1).store(n, Ordering::Release);
    }

    /// Takes the next answer of slot `slot` (`line`: its bytes with the newline, as peeked)
    /// off `fd`, with one `read` into the journal that a successor can tell from not having
    /// happened (see "Lines" above). An answer longer than the slot's room cannot be one
    /// (the reader refuses lines over `max_frame`).
    pub(crate) fn take_line(
        &mut self,
        slot: usize,
        fd: BorrowedFd<'_>,
        line: &[u8],
    ) -> io::Result<()> {
        let n = line.len();
        if n == 0 || n > self.take_cap {
            return Err(io::Error::other(format!(
                "an answer of {n} bytes does not fit the journal's {} bytes",
                self.take_cap
            )));
        }
        let copy = self.take_area(slot);
        let body = copy + self.take_cap;
        let number = self.lines_word(slot, 2).load(Ordering::Relaxed) + 1;
        // Filled before the take is announced: a successor compares only announced takes.
        self.region.write_bytes(copy, line);
        let complement: Vec<u8> = line.iter().map(|b| !b).collect();
        self.region.write_bytes(body, &complement);
        let k = OFF_LINES + LINES_LEN * slot;
        self.region
            .u64_at(k + 32)
            .store(n as u64, Ordering::Relaxed);
        self.region.u64_at(k + 24).store(number, Ordering::Release);
        crate::crashpoint::reached("answer-announced");
        let got = self.region.read_from(fd, body, n)?;
        crate::crashpoint::reached("answer-read");
        let mut took = vec![0u8; got];
        self.region.read_bytes(body, &mut took);
        if took != line[..got] || got != n {
            // The pipe did not hold what was peeked: nothing a successor could replay.
            return Err(io::Error::other(format!(
                "took {got} bytes that differ from the {n} peeked"
            )));
        }
        self.lines_word(slot, 2).store(number, Ordering::Release);
        Ok(())
    }

    /// Slot `slot`'s counts, with a take that was in progress resolved: taken if the journal
    /// holds the answer's bytes where the take went, not if it still holds their complement.
    fn line_counts(&self, slot: usize) -> LineCounts {
        let word = |k| self.lines_word(slot, k).load(Ordering::Acquire);
        let mut at = LineCounts {
            given: word(0),
            moved: word(1),
            taken: word(2),
        };
        let (number, n) = (word(3), word(4) as usize);
        if number == at.taken + 1 && n > 0 && n <= self.take_cap {
            let mut copy = vec![0u8; n];
            let mut body = vec![0u8; n];
            self.region.read_bytes(self.take_area(slot), &mut copy);
            self.region
                .read_bytes(self.take_area(slot) + self.take_cap, &mut body);
            if copy == body {
                at.taken = number;
            }
        }
        at
    }

    fn slot(&self, slot: usize) -> Option<SlotEntry> {
        let at = OFF_TABLE + SLOT_LEN * slot;
        let r = &self.region;
        let pid = r.u64_at(at).load(Ordering::Acquire) as libc::pid_t;
        if pid <= 0 {
            return None;
        }
        let flags = r.u64_at(at + 16).load(Ordering::Relaxed);
        let offsets = OFF_OFFSETS + OFFSETS_LEN * slot;
        let mut entry = SlotEntry {
            pid,
            start_time: r.u64_at(at + 8).load(Ordering::Relaxed),
            state_lost: flags & FLAG_STATE_LOST != 0,
            proven: flags & FLAG_PROVEN != 0,
            offsets: [0; MAX_PORTS],
        };
        for (o, off) in entry.offsets.iter_mut().enumerate().take(self.outputs) {
            *off = r.u64_at(offsets + 8 * o).load(Ordering::Relaxed);
        }
        Some(entry)
    }
}

/// Room for one answer of an unmodified program, with its newline or frame header (0 for a
/// component whose replicas link replica-rt).
fn take_cap(plan: &VoterPlan) -> usize {
    if plan.preload.is_none() && plan.framing != crate::plan::Framing::Lines {
        return 0;
    }
    let max = plan.outputs.iter().map(|p| p.max_frame).max().unwrap_or(0);
    (max + HEADER_LEN).next_multiple_of(8)
}

/// The deadline clock's calibration a predecessor recorded in the journal behind `fd`, if any
/// (read before the journal is opened: the clock comes first).
pub(crate) fn recorded_clock(fd: BorrowedFd<'_>) -> Option<(Source, f64, f64)> {
    let region = SharedRegion::existing(fd.try_clone_to_owned().ok()?).ok()?;
    if region.len() < HEADER || region.u64_at(OFF_MAGIC).load(Ordering::Acquire) != MAGIC {
        return None;
    }
    let source = match region.u64_at(OFF_CLOCK_SOURCE).load(Ordering::Relaxed) {
        1 => Source::Tsc,
        2 => Source::Cntvct,
        _ => return None,
    };
    let hz = f64::from_bits(region.u64_at(OFF_CLOCK_HZ).load(Ordering::Relaxed));
    let ppm = f64::from_bits(region.u64_at(OFF_CLOCK_PPM).load(Ordering::Relaxed));
    Some((source, hz, ppm))
}

/// A process's start time (field 22 of `/proc/PID/stat`, clock ticks since boot): with the
/// pid, it names one process for good.
pub(crate) fn start_time(pid: libc::pid_t) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The command name may hold spaces and parentheses: fields count from the last ')'.
    let rest = &stat[stat.rfind(')')? + 2..];
    rest.split(' ').nth(19)?.parse().ok()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use replica_rt::frame::{encode_into, resume_frame};
    use replica_rt::shared::memfd;
    use std::os::fd::AsFd;

    /// A TMR plan with one input and one output (also `adopt.rs`'s tests').
    pub(crate) fn plan() -> VoterPlan {
        let json = r#"{"system":"s","component":"c","exec":"/bin/true","args":[],"replicas":3,
            "timeout_us":1000,"inputs":[{"name":"in","fd":3,"max_frame":64}],
            "outputs":[{"name":"out","fd":4,"max_frame":64}],"rounds":[],
            "events_fd":null,"socket_path":"/nonexistent"}"#;
        serde_json::from_str(json).unwrap()
    }

    /// Frames taken since the last commit are what a successor finds, whole, in order, and a
    /// commit empties the log with the state it records; a take cut short by death (the
    /// markers written, the read not done) leaves nothing.
    #[test]
    fn a_successor_finds_the_last_commit_and_every_frame_taken_since() {
        let plan = plan();
        let fd = memfd(c"journal").unwrap();
        let keep = fd.try_clone().unwrap();
        let mut journal = Journal::create(fd, &plan).unwrap();
        let (r, w) = nix::unistd::pipe().unwrap();
        let mut bytes = Vec::new();
        encode_into(b"zero", &mut bytes);
        nix::unistd::write(&w, &bytes).unwrap();
        journal.take(0, r.as_fd(), bytes.len()).unwrap();
        let state = Committed {
            rounds_started: 1,
            inputs: vec![InputState {
                taken: 1,
                next_index: 1,
                delivered: 1,
            }],
            forwarded: vec![1],
        };
        journal.commit_carrying(&state, &[]);
        let mut more = resume_frame(1).to_vec();
        encode_into(b"one", &mut more);
        let mut two = Vec::new();
        encode_into(b"", &mut two);
        nix::unistd::write(&w, &more).unwrap();
        nix::unistd::write(&w, &two).unwrap();
        journal.take(0, r.as_fd(), more.len()).unwrap();
        journal.take(0, r.as_fd(), two.len()).unwrap();
        journal.set_slot(
            1,
            Some(SlotEntry {
                pid: 1234,
                start_time: 99,
                state_lost: true,
                proven: true,
                offsets: [7; MAX_PORTS],
            }),
        );
        let (_, found) = Journal::open(keep.try_clone().unwrap(), &plan).unwrap();
        assert_eq!(found.committed, state);
        let mut want = more.clone();
        want.extend_from_slice(&two);
        assert_eq!(found.logs, vec![want]);
        assert_eq!(found.slots[0], None);
        assert_eq!(found.slots[1].unwrap().pid, 1234);
        assert!(found.slots[1].unwrap().state_lost);
        assert_eq!(found.slots[1].unwrap().offsets[0], 7);
        assert_eq!(journal.forwarded_at(0), 1);
        // A take that died between its markers and its read: the log ends where it was.
        let at = journal.log(journal.current, 0) + journal.log_len[0];
        journal.region.write_bytes(at + 12, &MARKER.to_le_bytes());
        journal.region.write_bytes(at, &MARKER.to_le_bytes());
        let (_, found) = Journal::open(keep, &plan).unwrap();
        assert_eq!(found.logs[0].len(), more.len() + two.len());
    }

    /// A replica journaled before it answered is found proven once it has (its voter marks
    /// it), and a mark for a pid the slot no longer names changes nothing.
    #[test]
    fn a_replica_that_answered_since_it_was_journaled_is_found_proven() {
        let plan = plan();
        let fd = memfd(c"journal").unwrap();
        let keep = fd.try_clone().unwrap();
        let journal = Journal::create(fd, &plan).unwrap();
        let entry = |pid| SlotEntry {
            pid,
            start_time: 99,
            state_lost: false,
            proven: false,
            offsets: [0; MAX_PORTS],
        };
        journal.set_slot(0, Some(entry(1234)));
        journal.set_slot(1, Some(entry(1235)));
        journal.mark_proven(0, 1234);
        journal.mark_proven(1, 999);
        let (_, found) = Journal::open(keep, &plan).unwrap();
        assert!(found.slots[0].unwrap().proven);
        assert!(!found.slots[1].unwrap().proven);
    }

    /// An unmodified program's answer is taken into the journal with one `read`: a successor
    /// tells a take that happened (the slot holds the answer) from one announced but not done
    /// (the slot holds the complement), whether or not the count was stored after it.
    #[test]
    fn a_successor_tells_an_answer_taken_from_one_still_in_the_pipe() {
        let mut plan = plan();
        plan.framing = crate::plan::Framing::Lines;
        let fd = memfd(c"journal").unwrap();
        let keep = fd.try_clone().unwrap();
        let mut journal = Journal::create(fd, &plan).unwrap();
        let start = LineCounts {
            given: 5,
            moved: 5,
            taken: 4,
        };
        journal.set_lines(2, start);
        let (_, found) = Journal::open(keep.try_clone().unwrap(), &plan).unwrap();
        assert_eq!(found.lines[2], start);
        let (r, w) = nix::unistd::pipe().unwrap();
        nix::unistd::write(&w, b"15\n21\n").unwrap();
        journal.take_line(2, r.as_fd(), b"15\n").unwrap();
        let (_, found) = Journal::open(keep.try_clone().unwrap(), &plan).unwrap();
        assert_eq!(found.lines[2].taken, 5);
        // Taken, and the voter died before it stored the count: still taken.
        journal.lines_word(2, 2).store(4, Ordering::Release);
        journal.lines_word(2, 3).store(5, Ordering::Release);
        let (_, found) = Journal::open(keep.try_clone().unwrap(), &plan).unwrap();
        assert_eq!(found.lines[2].taken, 5);
        // Announced, and the voter died before the read: the complement is there; not taken.
        journal.lines_word(2, 2).store(5, Ordering::Release);
        let copy = journal.take_area(2);
        journal.region.write_bytes(copy, b"21\n");
        journal
            .region
            .write_bytes(copy + journal.take_cap, &[!b'2', !b'1', !b'\n']);
        journal.lines_word(2, 4).store(3, Ordering::Relaxed);
        journal.lines_word(2, 3).store(6, Ordering::Release);
        let (_, found) = Journal::open(keep.try_clone().unwrap(), &plan).unwrap();
        assert_eq!(found.lines[2].taken, 5);
        let mut left = [0u8; 8];
        assert_eq!(
            nix::unistd::read(&r, &mut left).unwrap(),
            3,
            "21 is still in the pipe"
        );
        // A pipe that does not hold what was peeked is an error, not a take.
        nix::unistd::write(&w, b"99\n").unwrap();
        assert!(journal.take_line(2, r.as_fd(), b"98\n").is_err());
    }

    /// Every part of the header stays apart at the most replicas a journal takes (the lines
    /// once overlapped the stream offsets of a fifth replica, and a 5-replica voter refused
    /// its journal).
    #[test]
    fn eight_replicas_keep_their_entries_apart() {
        let mut plan = plan();
        plan.replicas = 8;
        plan.framing = crate::plan::Framing::Lines;
        let fd = memfd(c"journal").unwrap();
        let keep = fd.try_clone().unwrap();
        let journal = Journal::create(fd, &plan).unwrap();
        for slot in 0..8 {
            let n = slot as u64 + 1;
            journal.set_slot(
                slot,
                Some(SlotEntry {
                    pid: 100 + slot as i32,
                    start_time: n,
                    state_lost: false,
                    proven: true,
                    offsets: [n; MAX_PORTS],
                }),
            );
            journal.set_lines(
                slot,
                LineCounts {
                    given: 10 * n,
                    moved: 10 * n,
                    taken: 10 * n - 1,
                },
            );
        }
        journal.set_written(0, 77);
        let (journal, found) = Journal::open(keep, &plan).unwrap();
        for slot in 0..8 {
            let n = slot as u64 + 1;
            let entry = found.slots[slot].unwrap();
            assert_eq!((entry.pid, entry.offsets[0]), (100 + slot as i32, n));
            assert_eq!(found.lines[slot].taken, 10 * n - 1);
        }
        assert_eq!(journal.written(0), 77);
        plan.replicas = 9;
        assert!(Journal::create(memfd(c"journal").unwrap(), &plan).is_err());
    }

    #[test]
    fn a_journal_of_another_shape_is_refused() {
        let plan = plan();
        let fd = memfd(c"journal").unwrap();
        let keep = fd.try_clone().unwrap();
        Journal::create(fd, &plan).unwrap();
        let mut other = plan.clone();
        other.replicas = 2;
        assert!(matches!(
            Journal::open(keep, &other),
            Err(JournalError::Mismatch(_))
        ));
        assert!(Journal::open(memfd(c"empty").unwrap(), &plan).is_err());
    }
}
