//! A seeded random number generator for tests (SplitMix64). Every test that makes a random
//! choice takes its seed from here; the seed is printed so a failure can be replayed with
//! `S3RES_TEST_SEED=<seed> cargo test ...`.

use std::time::{SystemTime, UNIX_EPOCH};

/// Environment variable that fixes the seed (decimal, or hex with `0x`).
pub const SEED_ENV: &str = "S3RES_TEST_SEED";

/// SplitMix64 (Steele, Lea, Flood 2014): tiny, fast, good enough to pick faults and victims.
#[derive(Debug, Clone)]
pub struct Rng {
    state: u64,
}

impl Rng {
    /// A generator with exactly this seed.
    pub fn with_seed(seed: u64) -> Self {
        Rng { state: seed }
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

    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `0..n` (`n > 0`), without modulo bias.
    pub fn below(&mut self, n: u64) -> u64 {
        assert!(n > 0, "Rng::below(0)");
        let zone = u64::MAX - u64::MAX % n;
        loop {
            let x = self.next_u64();
            if x < zone {
                return x % n;
            }
        }
    }

    /// Uniform in `lo..hi` (`lo < hi`).
    pub fn range(&mut self, lo: u64, hi: u64) -> u64 {
        lo + self.below(hi - lo)
    }

    /// One element of a non-empty slice.
    pub fn pick<'a, T>(&mut self, items: &'a [T]) -> &'a T {
        &items[self.below(items.len() as u64) as usize]
    }

    pub fn bool(&mut self) -> bool {
        self.next_u64() & 1 == 1
    }
}

fn parse_seed(s: &str) -> Option<u64> {
    let s = s.trim();
    match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(hex) => u64::from_str_radix(hex, 16).ok(),
        None => s.parse().ok(),
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
    }

    #[test]
    fn known_splitmix64_values() {
        // Reference values of SplitMix64 with seed 0.
        let mut r = Rng::with_seed(0);
        assert_eq!(r.next_u64(), 0xe220_a839_7b1d_cdaf);
        assert_eq!(r.next_u64(), 0x6e78_9e6a_a1b9_65f4);
    }

    #[test]
    fn below_stays_in_range() {
        let mut r = Rng::with_seed(7);
        for n in 1..50 {
            for _ in 0..20 {
                assert!(r.below(n) < n);
            }
        }
        assert_eq!(r.range(5, 6), 5);
    }

    #[test]
    fn seeds_parse() {
        assert_eq!(parse_seed("123"), Some(123));
        assert_eq!(parse_seed(" 0xff "), Some(255));
        assert_eq!(parse_seed("x"), None);
    }
}
