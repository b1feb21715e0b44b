//! A seeded random number generator for tests (the project's SplitMix64,
//! [`s3res_protocol::rng`]). Every test that makes a random choice takes its seed from here; the
//! seed is printed so a failure can be replayed with `S3RES_TEST_SEED=<seed> cargo test ...`.

use std::ops::{Deref, DerefMut};
use std::time::{SystemTime, UNIX_EPOCH};

use s3res_protocol::rng::{parse_seed, SplitMix64};

/// Environment variable that fixes the seed (decimal, or hex with `0x`).
pub const SEED_ENV: &str = "S3RES_TEST_SEED";

/// A [`SplitMix64`] whose seed was printed (its draws: `next_u64`, `below`, `range`, `pick`,
/// `bool`, `unit`).
#[derive(Debug, Clone)]
pub struct Rng(SplitMix64);

impl Rng {
    /// A generator with exactly this seed.
    pub fn with_seed(seed: u64) -> Self {
        Rng(SplitMix64::new(seed))
    }

    /// Seed from `S3RES_TEST_SEED`, else from the clock; prints `seed = N` to stderr (which the
    /// test runner shows when the test fails).
    pub fn from_env() -> Self {
        let seed = match std::env::var(SEED_ENV) {
            Ok(s) => parse_seed(&s).unwrap_or_else(|| panic!("{SEED_ENV}={s:?} is not a number")),
            Err(_) => SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map(|d| d.as_nanos() as u64)
                .unwrap_or(0x5eed),
        };
        eprintln!("seed = {seed} (replay with {SEED_ENV}={seed})");
        Rng::with_seed(seed)
    }
}

impl Deref for Rng {
    type Target = SplitMix64;

    fn deref(&self) -> &SplitMix64 {
        &self.0
    }
}

impl DerefMut for Rng {
    fn deref_mut(&mut self) -> &mut SplitMix64 {
        &mut self.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_sequence() {
        let mut a = Rng::with_seed(42);
        let mut b = Rng::with_seed(42);
        for _ in 0..100 {
            assert_eq!(a.next_u64(), b.next_u64());
        }
        assert!(a.below(7) < 7);
    }
}
