//! Fault-injection hooks, compiled into every component (as in S³RES), in every mode, so that
//! unprotected components can be injected too.
//!
//! - [`signals::INJECT_SDC`]: corrupt the next outgoing frame that has a payload (an empty
//!   one has no bit to flip and leaves the request for the next). The handler only stores the
//!   request in an atomic; [`crate::OutPort::send`] consumes it and flips the bit (on its own
//!   copy of the payload) before writing.
//! - [`signals::inject_cfe`]: spin forever inside the handler, a control-flow error that never
//!   answers. Only SIGKILL gets the process out.
//! - [`signals::inject_var`]: variable-level injection (MAVFI): XOR byte masks into chosen bytes
//!   of the next outgoing frame. Each signal stages one byte in a fixed table of atomics; the
//!   request's last byte arms the table, and [`crate::OutPort::send`] applies and clears it.

use std::io;
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU64, Ordering};

use crate::contract::signals::{self, VarRequest};
use crate::sys;

/// No injection pending.
const NONE: i64 = i64::MIN;
/// Injection pending, bit to be chosen at random.
const RANDOM: i64 = -1;

static PENDING_SDC: AtomicI64 = AtomicI64::new(NONE);

/// Most bytes one variable-level request may touch (an f64 is 8).
const VAR_SLOTS: usize = 16;
/// Marks a used slot (an offset of 0 with mask 0 would otherwise look empty).
const SLOT_USED: u64 = 1 << 63;
/// Staged bytes: `SLOT_USED | offset << 8 | mask`, or 0.
static VAR_STAGED: [AtomicU64; VAR_SLOTS] = [const { AtomicU64::new(0) }; VAR_SLOTS];
/// The last byte of a request arrived: apply the staged bytes to the next frame.
static VAR_ARMED: AtomicBool = AtomicBool::new(false);
/// Bytes that found no free slot since the last frame (reported when the frame is sent).
static VAR_DROPPED: AtomicU64 = AtomicU64::new(0);

pub(crate) fn install() -> io::Result<()> {
    // SAFETY: the three handlers below are async-signal-safe: each decodes its value and
    // updates fixed atomics (or spins forever), with no allocation, lock or formatting.
    unsafe {
        sys::install_siginfo_handler(signals::INJECT_SDC, on_inject_sdc, libc::SA_RESTART)?;
        // No SA_RESTART needed: the handler never returns.
        sys::install_siginfo_handler(signals::inject_cfe(), on_inject_cfe, 0)?;
        sys::install_siginfo_handler(signals::inject_var(), on_inject_var, libc::SA_RESTART)?;
    }
    Ok(())
}

/// Async-signal-safe: decodes the value and updates fixed atomics; no allocation, no lock.
/// A value that is not a valid [`VarRequest`] (or a plain `kill`) is ignored.
extern "C" fn on_inject_var(
    _sig: libc::c_int,
    info: *mut libc::siginfo_t,
    _ctx: *mut libc::c_void,
) {
    // SAFETY: the kernel passes a valid (or no) siginfo to an SA_SIGINFO handler.
    let info = unsafe { info.as_ref() };
    if let Some(req) = info
        .and_then(crate::sys::queued_value)
        .and_then(VarRequest::from_value)
    {
        stage_var(req);
    }
}

/// Stages one byte (XORed into an existing slot for the same offset) and arms on `last`.
/// Called only from the handler, which the kernel never re-enters for the same signal, and
/// [`apply_pending`] blocks the signal while it empties the table, so plain loads and stores
/// suffice.
fn stage_var(req: VarRequest) {
    let offset = u64::from(req.offset);
    let mut free = None;
    let mut placed = false;
    for slot in &VAR_STAGED {
        let v = slot.load(Ordering::SeqCst);
        if v == 0 {
            free = free.or(Some(slot));
        } else if (v >> 8) & u64::from(VarRequest::MAX_OFFSET) == offset {
            slot.store(v ^ u64::from(req.mask), Ordering::SeqCst);
            placed = true;
            break;
        }
    }
    if !placed {
        match free {
            Some(slot) => slot.store(
                SLOT_USED | offset << 8 | u64::from(req.mask),
                Ordering::SeqCst,
            ),
            None => {
                VAR_DROPPED.fetch_add(1, Ordering::SeqCst);
            }
        }
    }
    if req.last {
        VAR_ARMED.store(true, Ordering::SeqCst);
    }
}

/// Async-signal-safe: reads the siginfo, stores one atomic.
extern "C" fn on_inject_sdc(
    _sig: libc::c_int,
    info: *mut libc::siginfo_t,
    _ctx: *mut libc::c_void,
) {
    PENDING_SDC.store(requested_bit(info), Ordering::SeqCst);
}

/// The bit a `sigqueue` asked for, or [`RANDOM`] for a plain `kill` or a negative value.
fn requested_bit(info: *const libc::siginfo_t) -> i64 {
    // SAFETY: the kernel passes a valid (or no) siginfo to an SA_SIGINFO handler.
    let info = unsafe { info.as_ref() };
    match info.and_then(crate::sys::queued_value) {
        Some(bit) if bit >= 0 => i64::from(bit),
        _ => RANDOM,
    }
}

/// Spins forever: the injected control-flow error.
extern "C" fn on_inject_cfe(
    _sig: libc::c_int,
    _info: *mut libc::siginfo_t,
    _ctx: *mut libc::c_void,
) {
    loop {
        core::hint::spin_loop();
    }
}

/// Forgets a pending injection. A forked replacement calls this: the injection was aimed at
/// its donor's pid, not at it.
pub(crate) fn clear_pending() {
    PENDING_SDC.store(NONE, Ordering::SeqCst);
    for slot in &VAR_STAGED {
        slot.store(0, Ordering::SeqCst);
    }
    VAR_ARMED.store(false, Ordering::SeqCst);
    VAR_DROPPED.store(0, Ordering::SeqCst);
}

/// Applies an armed variable-level request to `payload` and empties the table.
fn apply_var(port: &str, payload: &mut [u8]) {
    // Looked at before it is taken: a load is a plain read, a swap a locked one on every
    // frame sent. A request armed between the two is taken by the swap; one armed after it
    // waits for the next frame, as it would have after a swap alone.
    if !VAR_ARMED.load(Ordering::SeqCst) || !VAR_ARMED.swap(false, Ordering::SeqCst) {
        return;
    }
    // While the table is emptied, a new request must not be half taken: hold the signal.
    let _held = sys::block_signal(signals::inject_var());
    let mut applied = [(0u32, 0u8); VAR_SLOTS];
    let mut n_applied = 0;
    let mut outside = 0u32;
    for slot in &VAR_STAGED {
        let v = slot.swap(0, Ordering::SeqCst);
        if v == 0 {
            continue;
        }
        let offset = ((v >> 8) & u64::from(VarRequest::MAX_OFFSET)) as u32;
        let mask = (v & 0xff) as u8;
        match payload.get_mut(offset as usize) {
            Some(byte) => {
                *byte ^= mask;
                applied[n_applied] = (offset, mask);
                n_applied += 1;
            }
            None => outside += 1,
        }
    }
    let dropped = VAR_DROPPED.swap(0, Ordering::SeqCst);
    tracing::warn!(
        port,
        bytes = ?&applied[..n_applied],
        outside_payload = outside,
        dropped,
        len = payload.len(),
        "injected variable flip: (offset, mask) XORed into the outgoing frame"
    );
}

/// Applies a pending SDC or variable injection to `payload`, an outgoing frame that does not
/// go through [`crate::OutPort::send`] (the preload library's lines on an unmodified program's
/// stdout). Components that use `OutPort` never call this.
pub fn corrupt_if_injected(port: &str, payload: &mut [u8]) {
    apply_pending(port, payload);
}

/// Whether an SDC or variable injection waits for the next outgoing frame.
pub fn injection_pending() -> bool {
    PENDING_SDC.load(Ordering::SeqCst) != NONE || VAR_ARMED.load(Ordering::SeqCst)
}

/// Applies a pending SDC injection to `payload` (the outgoing copy), logging what was done.
pub(crate) fn apply_pending(port: &str, payload: &mut [u8]) {
    apply_var(port, payload);
    // As for VAR_ARMED: read first, taken only if there is something to take. A frame with
    // no payload has no bit to flip: the injection waits for the next one that has (as an
    // unmodified program's lone newline leaves it for its next line), rather than being
    // used up on nothing and counted as injected.
    if payload.is_empty() || PENDING_SDC.load(Ordering::SeqCst) == NONE {
        return;
    }
    let req = PENDING_SDC.swap(NONE, Ordering::SeqCst);
    if req == NONE {
        return;
    }
    let bits = payload.len() as u64 * 8;
    let bit = if req >= 0 {
        let bit = req as u64 % bits;
        // Debug: the injector and the voter's events already say it (one line each).
        tracing::debug!(
            port,
            bit,
            requested = req,
            "injected SDC: flipping a chosen bit"
        );
        bit
    } else {
        let seed = sys::monotonic_ns() ^ u64::from(std::process::id());
        let bit = xorshift64(seed) % bits;
        tracing::debug!(port, bit, seed, "injected SDC: flipping a random bit");
        bit
    };
    flip_bit(payload, bit);
}

/// Bit 0 is the lowest bit of the first byte.
fn flip_bit(payload: &mut [u8], bit: u64) {
    payload[(bit / 8) as usize] ^= 1 << (bit % 8);
}

/// One step of Marsaglia's xorshift64 (a zero seed would stay zero, so it is replaced).
fn xorshift64(seed: u64) -> u64 {
    let mut x = if seed == 0 {
        0x9e37_79b9_7f4a_7c15
    } else {
        seed
    };
    x ^= x << 13;
    x ^= x >> 7;
    x ^= x << 17;
    x
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flips_the_named_bit() {
        let mut p = [0u8; 3];
        flip_bit(&mut p, 0);
        assert_eq!(p, [1, 0, 0]);
        flip_bit(&mut p, 23);
        assert_eq!(p, [1, 0, 0x80]);
    }

    /// The only test touching the process-wide pending injection.
    #[test]
    fn pending_injection_flips_exactly_one_bit_once() {
        let clean = [0x55u8; 16];
        for req in [RANDOM, 3, 1000] {
            PENDING_SDC.store(req, Ordering::SeqCst);
            let mut p = clean;
            apply_pending("out", &mut p);
            let flipped: u32 = p
                .iter()
                .zip(&clean)
                .map(|(a, b)| (a ^ b).count_ones())
                .sum();
            assert_eq!(flipped, 1, "request {req}");
            if req >= 0 {
                let bit = req as usize % 128;
                assert_eq!(p[bit / 8] ^ clean[bit / 8], 1 << (bit % 8));
            }
            // Consumed: the next frame goes out clean.
            let mut p = clean;
            apply_pending("out", &mut p);
            assert_eq!(p, clean);
        }
        // An empty frame has no bit to flip: the injection waits for the next frame that has.
        PENDING_SDC.store(RANDOM, Ordering::SeqCst);
        apply_pending("out", &mut []);
        assert_eq!(PENDING_SDC.load(Ordering::SeqCst), RANDOM);
        let mut p = clean;
        apply_pending("out", &mut p);
        assert_ne!(p, clean, "the frame after the empty one carries the flip");
        assert_eq!(PENDING_SDC.load(Ordering::SeqCst), NONE);
    }

    /// The only test touching the process-wide variable-injection table.
    #[test]
    fn var_request_applies_all_its_bytes_to_one_frame_only_when_armed() {
        let clean = [0u8; 16];
        let reqs = VarRequest::for_bits(8, &[52, 62, 63]);
        let (last, first) = reqs.split_last().unwrap();
        for r in first {
            stage_var(*r);
        }
        // Not armed yet: a frame sent now goes out clean.
        let mut p = clean;
        apply_var("out", &mut p);
        assert_eq!(p, clean);
        stage_var(*last);
        apply_var("out", &mut p);
        let bits = u64::from_le_bytes(p[8..16].try_into().unwrap());
        assert_eq!(bits, (1 << 52) | (1 << 62) | (1 << 63));
        assert_eq!(p[..8], clean[..8]);
        let mut q = clean;
        apply_var("out", &mut q);
        assert_eq!(q, clean, "consumed by the first frame");
        // A byte beyond the payload is skipped, the others still apply.
        stage_var(VarRequest {
            offset: 2,
            mask: 1,
            last: false,
        });
        stage_var(VarRequest {
            offset: 100,
            mask: 1,
            last: true,
        });
        apply_var("out", &mut q);
        assert_eq!(q[2], 1);
        assert_eq!(q.iter().map(|b| b.count_ones()).sum::<u32>(), 1);
    }

    #[test]
    fn xorshift_never_sticks_at_zero() {
        assert_ne!(xorshift64(0), 0);
        assert_ne!(xorshift64(1), xorshift64(2));
    }
}
