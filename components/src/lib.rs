//! Shared helpers of the example components.
//!
//! # Payload layout (all integers little-endian)
//!
//! A **source frame** (written by `s3res-source`) is `size` bytes:
//!
//! | bytes        | content                                   |
//! |--------------|-------------------------------------------|
//! | `0..8`       | `seq: u64`, 0 for the first frame, then +1 |
//! | `8..size`    | filler: byte `8 + i` is [`filler`]`(seq, i)` |
//!
//! The filler depends on every bit of `seq`, so a corrupted frame is seen as corrupt (unless the
//! frame has no filler, `size == 8`).
//!
//! An **echo answer** (`s3res-echo`) is the source frame unchanged; with `--stateful` it is
//! prefixed with `answered: u64`, the number of frames the echo answered before this one. That
//! counter is the echo's state: a replica restarted by exec starts again at 0 (the sink sees a
//! state break), one restarted by fork carries on.

#![forbid(unsafe_code)]

use std::time::{Duration, Instant};

use serde::Serialize;

pub mod frames;

/// Bytes of the sequence number at the start of a source frame (and its minimum size).
pub const SEQ_LEN: usize = 8;
/// Bytes of the stateful echo's prefix.
pub const PREFIX_LEN: usize = 8;

/// Filler byte `i` (counted from the end of the seq) of source frame `seq`.
pub fn filler(seq: u64, i: usize) -> u8 {
    // SplitMix64's first output for seed `seq`: every bit of seq spread over all 64 bits.
    let h = s3res_protocol::rng::SplitMix64::new(seq).next_u64();
    ((h >> (8 * (i % 8))) as u8)
        .wrapping_add(i as u8)
        .wrapping_mul(31)
}

/// `start + seq * period`, exactly (integer nanoseconds), or `None` past the clock's range: when
/// frame `seq` of a paced stream is due. Deadlines from the start, not from the last send, so a
/// late frame does not delay the ones after it and the rate does not drift.
pub fn due_at(start: Instant, period: Duration, seq: u64) -> Option<Instant> {
    let nanos = period.as_nanos().checked_mul(u128::from(seq))?;
    let secs = u64::try_from(nanos / 1_000_000_000).ok()?;
    start.checked_add(Duration::new(secs, (nanos % 1_000_000_000) as u32))
}

/// Writes source frame `seq` of `size` bytes (at least [`SEQ_LEN`]) into `out`, replacing its
/// contents.
pub fn source_frame(seq: u64, size: usize, out: &mut Vec<u8>) {
    out.clear();
    out.extend_from_slice(&seq.to_le_bytes());
    out.extend((0..size.saturating_sub(SEQ_LEN)).map(|i| filler(seq, i)));
}

/// Reads the seq of a source frame and checks its filler. `None` if it is too short or the
/// filler is wrong.
pub fn check_source_frame(frame: &[u8]) -> Option<u64> {
    let seq = u64::from_le_bytes(frame.get(..SEQ_LEN)?.try_into().ok()?);
    let filler_ok = frame[SEQ_LEN..]
        .iter()
        .enumerate()
        .all(|(i, &b)| b == filler(seq, i));
    filler_ok.then_some(seq)
}

/// The echo's behaviour: the answer to each frame, with the optional state prefix.
#[derive(Debug, Default)]
pub struct Echo {
    stateful: bool,
    answered: u64,
    buf: Vec<u8>,
}

impl Echo {
    pub fn new(stateful: bool) -> Self {
        Echo {
            stateful,
            ..Echo::default()
        }
    }

    /// The answer to `frame`; counts it as answered. Without the state prefix that is
    /// `frame` itself, sent from where the runtime received it (no copy, as a C echo does).
    pub fn answer<'a>(&'a mut self, frame: &'a [u8]) -> &'a [u8] {
        self.answered = self.answered.wrapping_add(1);
        if !self.stateful {
            return frame;
        }
        self.buf.clear();
        self.buf
            .extend_from_slice(&(self.answered - 1).to_le_bytes());
        self.buf.extend_from_slice(frame);
        &self.buf
    }
}

/// The batching of `s3res-batch`: frames are held until a batch is full, then let out together.
#[derive(Debug)]
pub struct Batcher {
    every: usize,
    vary: bool,
    /// Size of the batch being filled (fixed at its first frame).
    size: usize,
    held: Vec<Vec<u8>>,
}

impl Batcher {
    pub fn new(every: usize, vary: bool) -> Self {
        Batcher {
            every: every.max(1),
            vary,
            size: 0,
            held: Vec::new(),
        }
    }

    /// Holds `frame`; returns the batch if it is now full (else nothing).
    pub fn push(&mut self, frame: &[u8]) -> Vec<Vec<u8>> {
        if self.held.is_empty() {
            self.size = if self.vary {
                // From the frame's bytes, so every replica picks the same size.
                let h = frame
                    .iter()
                    .fold(0usize, |h, &b| h.wrapping_mul(31).wrapping_add(b as usize));
                1 + h % self.every
            } else {
                self.every
            };
        }
        self.held.push(frame.to_vec());
        if self.held.len() >= self.size {
            std::mem::take(&mut self.held)
        } else {
            Vec::new()
        }
    }

    /// What is still held, at the end of the input.
    pub fn finish(&mut self) -> Vec<Vec<u8>> {
        std::mem::take(&mut self.held)
    }
}

/// What the sink counted. Serialised as the `--summary` JSON.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct Summary {
    /// Frames received, whatever their content.
    pub frames: u64,
    /// Seqs never received (below the highest seq seen, plus, with `--expect`, those after it).
    pub missing: u64,
    /// Frames whose seq was already received.
    pub duplicated: u64,
    /// Frames that arrived after a higher seq (they were counted missing until then).
    pub reordered: u64,
    /// Frames too short or with the wrong filler.
    pub corrupt: u64,
    /// Stateful frames whose prefix was not what the echo's count should have been.
    pub state_breaks: u64,
    pub ok: bool,
    pub expected: Option<u64>,
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "sink: {} frames, {} missing, {} duplicated, {} reordered, {} corrupt, {} state breaks: {}",
            self.frames,
            self.missing,
            self.duplicated,
            self.reordered,
            self.corrupt,
            self.state_breaks,
            if self.ok { "OK" } else { "FAILED" }
        )
    }
}

/// The sink's checking logic, frame by frame.
///
/// - **Order**: `next` is one past the highest seq seen. A seq above it opens a gap (its seqs
///   count as missing); a seq inside a gap closes that one seq (missing −1, reordered +1); any
///   other seq below `next` is a duplicate. Gaps are kept as ranges, so memory grows with the
///   number of gaps, never with a seq's value.
/// - **Corrupt** frames (bad filler, or too short) are counted and then taken to be the frame
///   that was due, seq `next`: a corrupted frame is most likely the one in its place, and this
///   keeps one corruption from also showing as a missing frame.
/// - **State** (`stateful`): for each frame that advances the order (seq ≥ `next`), the expected
///   prefix is the previous advancing frame's prefix + 1 + the seqs skipped in between (the echo
///   answered those too; they were lost after it); for the first frame, its seq. A mismatch is a
///   state break. A corrupted prefix therefore also shows as a state break.
#[derive(Debug)]
pub struct Checker {
    stateful: bool,
    next: u64,
    /// Open gaps: `(start, end)` half-open ranges of seqs not seen, sorted, disjoint.
    gaps: Vec<(u64, u64)>,
    /// Prefix and seq of the last frame that advanced the order.
    last_state: Option<(u64, u64)>,
    summary: Summary,
}

impl Checker {
    pub fn new(stateful: bool) -> Self {
        Checker {
            stateful,
            next: 0,
            gaps: Vec::new(),
            last_state: None,
            summary: Summary::default(),
        }
    }

    /// Checks one received frame.
    pub fn frame(&mut self, frame: &[u8]) {
        self.summary.frames += 1;
        let (prefix, body) = if self.stateful {
            match frame.split_first_chunk::<PREFIX_LEN>() {
                Some((p, body)) => (Some(u64::from_le_bytes(*p)), body),
                None => {
                    self.corrupt();
                    return;
                }
            }
        } else {
            (None, frame)
        };
        let Some(seq) = check_source_frame(body) else {
            self.corrupt();
            return;
        };
        if seq >= self.next {
            if seq > self.next {
                self.gaps.push((self.next, seq));
                self.summary.missing += seq - self.next;
            }
            if let Some(prefix) = prefix {
                self.check_state(prefix, seq);
            }
            self.next = seq.saturating_add(1);
        } else if self.close_gap(seq) {
            self.summary.missing -= 1;
            self.summary.reordered += 1;
        } else {
            self.summary.duplicated += 1;
        }
    }

    /// The final counts; with `expected`, seqs from the highest seen up to it count as missing.
    pub fn finish(mut self, expected: Option<u64>) -> Summary {
        if let Some(n) = expected {
            self.summary.missing += n.saturating_sub(self.next);
        }
        let s = &mut self.summary;
        s.expected = expected;
        let count_ok = match expected {
            Some(n) => s.frames == n,
            None => true,
        };
        s.ok = s.missing == 0
            && s.duplicated == 0
            && s.reordered == 0
            && s.corrupt == 0
            && s.state_breaks == 0
            && count_ok;
        self.summary
    }

    fn corrupt(&mut self) {
        self.summary.corrupt += 1;
        self.next = self.next.saturating_add(1);
    }

    fn check_state(&mut self, prefix: u64, seq: u64) {
        let expected = match self.last_state {
            None => seq,
            Some((last_prefix, last_seq)) => last_prefix.wrapping_add(seq.wrapping_sub(last_seq)),
        };
        if prefix != expected {
            self.summary.state_breaks += 1;
        }
        self.last_state = Some((prefix, seq));
    }

    /// Removes `seq` from the gap holding it; `false` if no gap does.
    fn close_gap(&mut self, seq: u64) -> bool {
        let Some(i) = self.gaps.iter().position(|&(s, e)| s <= seq && seq < e) else {
            return false;
        };
        let (start, end) = self.gaps[i];
        match (seq == start, seq + 1 == end) {
            (true, true) => {
                self.gaps.remove(i);
            }
            (true, false) => self.gaps[i].0 = seq + 1,
            (false, true) => self.gaps[i].1 = seq,
            (false, false) => {
                self.gaps[i].1 = seq;
                self.gaps.insert(i + 1, (seq + 1, end));
            }
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn src(seq: u64) -> Vec<u8> {
        let mut v = Vec::new();
        source_frame(seq, 16, &mut v);
        v
    }

    fn echoed(prefix: u64, seq: u64) -> Vec<u8> {
        let mut v = prefix.to_le_bytes().to_vec();
        v.extend(src(seq));
        v
    }

    fn run(stateful: bool, frames: &[Vec<u8>], expected: Option<u64>) -> Summary {
        let mut c = Checker::new(stateful);
        for f in frames {
            c.frame(f);
        }
        c.finish(expected)
    }

    #[test]
    fn filler_roundtrips_and_depends_on_all_of_seq() {
        for seq in [0, 1, 255, 256, 1 << 40] {
            assert_eq!(check_source_frame(&src(seq)), Some(seq));
        }
        let mut f = src(7);
        f[6] ^= 1; // a high byte of seq: the filler no longer matches
        assert_eq!(check_source_frame(&f), None);
        assert_eq!(check_source_frame(&[1, 2, 3]), None);
        let mut minimal = Vec::new();
        source_frame(9, 8, &mut minimal);
        assert_eq!(check_source_frame(&minimal), Some(9));
    }

    #[test]
    fn clean_stream_is_ok() {
        let s = run(false, &[src(0), src(1), src(2)], Some(3));
        assert!(s.ok, "{s}");
        assert_eq!(
            s.to_string(),
            "sink: 3 frames, 0 missing, 0 duplicated, 0 reordered, 0 corrupt, 0 state breaks: OK"
        );
    }

    #[test]
    fn missing_in_the_middle_and_at_the_end() {
        let s = run(false, &[src(0), src(2), src(3)], Some(6));
        assert_eq!((s.frames, s.missing), (3, 3));
        assert!(!s.ok);
        // Without --expect, a stream that simply stops early is fine.
        assert!(run(false, &[src(0), src(1)], None).ok);
    }

    #[test]
    fn duplicates() {
        let s = run(false, &[src(0), src(1), src(1), src(0)], None);
        assert_eq!((s.duplicated, s.missing, s.reordered), (2, 0, 0));
        assert!(!s.ok);
    }

    #[test]
    fn reorders_close_gaps() {
        let s = run(false, &[src(0), src(3), src(1), src(2), src(4)], Some(5));
        assert_eq!((s.missing, s.reordered, s.duplicated), (0, 2, 0));
        // A middle seq of a gap splits it; a second copy of it is then a duplicate.
        let s = run(false, &[src(0), src(5), src(3), src(3)], None);
        assert_eq!((s.missing, s.reordered, s.duplicated), (3, 1, 1));
    }

    #[test]
    fn corrupt_frames_take_the_due_slot() {
        let mut bad = src(1);
        bad[10] ^= 0x10;
        let s = run(false, &[src(0), bad, src(2)], Some(3));
        assert_eq!((s.corrupt, s.missing, s.frames), (1, 0, 3));
        assert!(!s.ok);
        let s = run(true, &[vec![1, 2, 3]], None);
        assert_eq!(s.corrupt, 1);
    }

    #[test]
    fn huge_seq_does_not_blow_up() {
        let mut f = Vec::new();
        source_frame(u64::MAX - 1, 8, &mut f);
        let s = run(false, &[src(0), f, src(1)], None);
        assert_eq!(s.reordered, 1);
        assert_eq!(s.missing, u64::MAX - 3);
    }

    #[test]
    fn state_is_checked_across_gaps() {
        // The echo answered 0,1,2,3; frame 2 was lost after it: no state break.
        let s = run(true, &[echoed(0, 0), echoed(1, 1), echoed(3, 3)], None);
        assert_eq!((s.state_breaks, s.missing), (0, 1));
        // An echo restarted by exec starts counting again at 0.
        let s = run(
            true,
            &[echoed(0, 0), echoed(1, 1), echoed(0, 2), echoed(1, 3)],
            Some(4),
        );
        assert_eq!(s.state_breaks, 1);
        assert!(!s.ok);
        // The first frame's prefix must equal its seq.
        assert_eq!(run(true, &[echoed(5, 0)], None).state_breaks, 1);
        assert!(run(true, &[echoed(0, 0), echoed(1, 1)], Some(2)).ok);
    }

    #[test]
    fn batches_hold_frames_and_let_them_out_together() {
        let mut b = Batcher::new(3, false);
        assert!(b.push(b"a").is_empty());
        assert!(b.push(b"b").is_empty());
        assert_eq!(b.push(b"c"), [b"a".to_vec(), b"b".to_vec(), b"c".to_vec()]);
        assert!(b.push(b"d").is_empty());
        assert_eq!(b.finish(), [b"d".to_vec()]);
        // Varying sizes stay within 1..=N and every frame comes out once, in order.
        let mut b = Batcher::new(5, true);
        let mut out = Vec::new();
        let mut sizes = std::collections::BTreeSet::new();
        for seq in 0..200u64 {
            let batch = b.push(&src(seq));
            if !batch.is_empty() {
                sizes.insert(batch.len());
            }
            out.extend(batch);
        }
        out.extend(b.finish());
        assert_eq!(out, (0..200).map(src).collect::<Vec<_>>());
        assert!(
            sizes.len() > 1 && sizes.iter().all(|&n| (1..=5).contains(&n)),
            "{sizes:?}"
        );
    }

    #[test]
    fn echo_prefixes_its_count() {
        let mut e = Echo::new(true);
        assert_eq!(e.answer(b"a"), [0, 0, 0, 0, 0, 0, 0, 0, b'a']);
        assert_eq!(e.answer(b"b")[0], 1);
        let mut plain = Echo::new(false);
        assert_eq!(plain.answer(b"xy"), b"xy");
    }

    #[test]
    fn summary_json_has_the_documented_fields() {
        let s = run(false, &[src(0)], Some(1));
        let v: serde_json::Value = serde_json::to_value(&s).unwrap();
        for k in [
            "frames",
            "missing",
            "duplicated",
            "reordered",
            "corrupt",
            "state_breaks",
            "ok",
            "expected",
        ] {
            assert!(v.get(k).is_some(), "{k}");
        }
        assert_eq!(v["expected"], 1);
    }
}

/// Size of a [`Signal`] frame.
pub const SIGNAL_FRAME: usize = 40;

/// The smooth telemetry `s3res-signal` answers each source frame with: a point moving on a
/// Lissajous-like curve, its speed, and its odometer (the distance travelled so far, the
/// component's state). Little-endian, [`SIGNAL_FRAME`] bytes:
///
/// | bytes    | field                 |
/// |----------|-----------------------|
/// | `0..8`   | `seq: u64` (+ offset) |
/// | `8..16`  | `x: f64`              |
/// | `16..24` | `y: f64`              |
/// | `24..32` | `speed: f64`          |
/// | `32..40` | `odometer: f64`       |
///
/// x stays in 30..70, y in 20..40: a flip of any exponent bit of either changes it by at least
/// 10, far beyond its change from one frame to the next (below 0.5). Everything is a function
/// of the sequence numbers seen, so two runs over the same input give the same bytes.
#[derive(Debug, Clone, Default)]
pub struct Signal {
    offset: u64,
    odometer: f64,
}

impl Signal {
    /// `offset` is added to every sequence number (a run over other data than the training).
    pub fn new(offset: u64) -> Self {
        Signal {
            offset,
            odometer: 0.0,
        }
    }

    /// The point at time `t`.
    fn position(t: f64) -> (f64, f64) {
        (
            50.0 + 20.0 * (t * 0.02).sin(),
            30.0 + 10.0 * (t * 0.013).cos(),
        )
    }

    /// The answer to source frame number `seq`.
    pub fn answer(&mut self, seq: u64) -> [u8; SIGNAL_FRAME] {
        let t = (seq + self.offset) as f64;
        let (x, y) = Signal::position(t);
        // From the point one step earlier, also for the first frame: a speed that starts at 0
        // would be a jump no later frame shows.
        let (px, py) = Signal::position(t - 1.0);
        let step = ((x - px).powi(2) + (y - py).powi(2)).sqrt();
        self.odometer += step;
        let mut out = [0u8; SIGNAL_FRAME];
        out[0..8].copy_from_slice(&(seq + self.offset).to_le_bytes());
        for (k, v) in [x, y, step, self.odometer].into_iter().enumerate() {
            out[8 + 8 * k..16 + 8 * k].copy_from_slice(&v.to_le_bytes());
        }
        out
    }
}
