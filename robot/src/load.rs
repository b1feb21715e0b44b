//! The background load: a fixed amount of CPU-bound work per tick, summed into a checksum.
//!
//! As in the S³RES evaluation, a low-priority compute task competes for the CPU with the control
//! loop. The work is deterministic (a xorshift chain seeded by the tick), so replicas of the load
//! agree and a corrupted one is outvoted like any other component.

use crate::msg::{LoadSum, Tick};

/// The checksum of `rounds` rounds of work for `tick`.
pub fn work(tick: Tick, rounds: u32) -> LoadSum {
    let mut x = 0x9e37_79b9_7f4a_7c15u64 ^ u64::from(tick.seq).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    let mut sum = 0u64;
    for i in 0..rounds {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        sum = sum.wrapping_add(x.rotate_left(i % 64));
    }
    LoadSum { seq: tick.seq, sum }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn work_is_deterministic_and_depends_on_tick_and_amount() {
        let a = work(Tick { seq: 1 }, 1000);
        assert_eq!(a, work(Tick { seq: 1 }, 1000));
        assert_ne!(a.sum, work(Tick { seq: 2 }, 1000).sum);
        assert_ne!(a.sum, work(Tick { seq: 1 }, 1001).sum);
        assert_eq!(work(Tick { seq: 3 }, 0).sum, 0);
    }
}
