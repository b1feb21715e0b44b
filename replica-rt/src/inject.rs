//! Fault-injection hooks, compiled into every component (as in S³RES), in every mode, so that
//! unprotected components can be injected too.
//!
//! - [`signals::INJECT_SDC`]: corrupt the next outgoing frame. The handler only stores the
//!   request in an atomic; [`crate::OutPort::send`] consumes it and flips the bit (on its own
//!   copy of the payload) before writing.
//! - [`signals::inject_cfe`]: spin forever inside the handler, a control-flow error that never
//!   answers. Only SIGKILL gets the process out.

use std::io;
use std::sync::atomic::{AtomicI64, Ordering};

use crate::contract::signals;
use crate::sys;

/// No injection pending.
const NONE: i64 = i64::MIN;
/// Injection pending, bit to be chosen at random.
const RANDOM: i64 = -1;

static PENDING_SDC: AtomicI64 = AtomicI64::new(NONE);

pub(crate) fn install() -> io::Result<()> {
    sys::install_siginfo_handler(signals::INJECT_SDC, on_inject_sdc, libc::SA_RESTART)?;
    // No SA_RESTART needed: the handler never returns.
    sys::install_siginfo_handler(signals::inject_cfe(), on_inject_cfe, 0)?;
    Ok(())
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
}

/// Applies a pending SDC injection to `payload` (the outgoing copy), logging what was done.
pub(crate) fn apply_pending(port: &str, payload: &mut [u8]) {
    let req = PENDING_SDC.swap(NONE, Ordering::SeqCst);
    if req == NONE {
        return;
    }
    let bits = payload.len() as u64 * 8;
    if bits == 0 {
        tracing::warn!(
            port,
            "injected SDC on an empty payload: no bit to flip, frame sent unchanged"
        );
        return;
    }
    let bit = if req >= 0 {
        let bit = req as u64 % bits;
        tracing::warn!(
            port,
            bit,
            requested = req,
            "injected SDC: flipping a chosen bit"
        );
        bit
    } else {
        let seed = sys::monotonic_ns() ^ u64::from(std::process::id());
        let bit = xorshift64(seed) % bits;
        tracing::warn!(port, bit, seed, "injected SDC: flipping a random bit");
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
        PENDING_SDC.store(RANDOM, Ordering::SeqCst);
        apply_pending("out", &mut []);
        assert_eq!(PENDING_SDC.load(Ordering::SeqCst), NONE);
    }

    #[test]
    fn xorshift_never_sticks_at_zero() {
        assert_ne!(xorshift64(0), 0);
        assert_ne!(xorshift64(1), xorshift64(2));
    }
}
