//! SplitMix64 (Steele, Lea, Flood 2014): the one small, seedable, portable generator of the
//! project. A seed fixes a robot mission (the maze and the sensor noise), a campaign's run seeds,
//! the victims of a benchmark and the random choices of a test; the same seed gives the same
//! numbers on every machine and in every version, so a seed printed by a run replays it.
//!
//! Uniform draws use the multiply-shift reduction ([`SplitMix64::below`]), which the robot's
//! world generation has always used: keeping it keeps every recorded mission the same.

/// The increment of the SplitMix64 state (2⁶⁴ / φ).
pub const GOLDEN_GAMMA: u64 = 0x9e37_79b9_7f4a_7c15;

/// SplitMix64's output function: spreads every bit of `z` over all 64 bits of the result.
/// `mix(seed + k · GOLDEN_GAMMA)` is the k-th output of [`SplitMix64::new(seed)`](SplitMix64::new)
/// (counting from 1), so it also derives independent seeds from one (see [`derive`]).
pub const fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The seed of item `k` (a campaign's run, say) of a whole seeded by `seed`: well spread, and
/// independent of the other items.
pub const fn derive(seed: u64, k: u64) -> u64 {
    mix(seed.wrapping_add(k.wrapping_mul(GOLDEN_GAMMA)))
}

/// The generator.
#[derive(Debug, Clone)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator with exactly this seed (any value, 0 included).
    pub const fn new(seed: u64) -> SplitMix64 {
        SplitMix64(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(GOLDEN_GAMMA);
        mix(self.0)
    }

    /// Uniform in `0..n` (`n > 0`; 0 gives 0), by multiply-shift: branch-free, with a bias of
    /// at most n / 2⁶⁴.
    pub fn below(&mut self, n: u64) -> u64 {
        if n == 0 {
            return 0;
        }
        ((self.next_u64() as u128 * n as u128) >> 64) as u64
    }

    /// Uniform in `lo..hi` (`lo < hi`).
    pub fn range(&mut self, lo: u64, hi: u64) -> u64 {
        lo + self.below(hi - lo)
    }

    /// One element of a non-empty slice.
    pub fn pick<'a, T>(&mut self, items: &'a [T]) -> &'a T {
        assert!(!items.is_empty(), "SplitMix64::pick from an empty slice");
        &items[self.below(items.len() as u64) as usize]
    }

    pub fn bool(&mut self) -> bool {
        self.next_u64() & 1 == 1
    }

    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A seed as people write it: decimal, or hexadecimal with `0x`; surrounding blanks ignored.
pub fn parse_seed(s: &str) -> Option<u64> {
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
    fn known_values_of_the_reference_implementation() {
        let mut r = SplitMix64::new(0);
        assert_eq!(r.next_u64(), 0xe220_a839_7b1d_cdaf);
        assert_eq!(r.next_u64(), 0x6e78_9e6a_a1b9_65f4);
        assert_eq!(mix(GOLDEN_GAMMA), 0xe220_a839_7b1d_cdaf);
        assert_eq!(derive(0, 2), 0x6e78_9e6a_a1b9_65f4);
    }

    #[test]
    fn same_seed_same_sequence_and_draws_in_range() {
        let (mut a, mut b) = (SplitMix64::new(42), SplitMix64::new(42));
        for _ in 0..100 {
            assert_eq!(a.next_u64(), b.next_u64());
        }
        for n in 1..50 {
            for _ in 0..20 {
                assert!(a.below(n) < n);
                assert!((0.0..1.0).contains(&a.unit()));
            }
        }
        assert_eq!(a.below(0), 0);
        assert_eq!(a.range(5, 6), 5);
        assert_eq!(*a.pick(&[9]), 9);
    }

    #[test]
    fn seeds_parse() {
        assert_eq!(parse_seed("123"), Some(123));
        assert_eq!(parse_seed(" 0xff "), Some(255));
        assert_eq!(parse_seed("x"), None);
    }
}
