//! Per-feature statistics: Welford's online mean and variance, and the σ floor both detectors
//! standardise with.

use serde::{Deserialize, Serialize};

/// Welford's recurrence (as in MAVFI §5.3.1): `M_k = M_{k-1} + (x_k − M_{k-1}) / k`,
/// `S_k = S_{k-1} + (x_k − M_{k-1})(x_k − M_k)`, `σ² = S_k / (k − 1)`. Numerically stable in
/// one pass, constant memory, so it can keep learning online.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Welford {
    pub count: u64,
    pub mean: f64,
    /// S_k: the sum of squared deviations from the running mean.
    pub m2: f64,
}

impl Welford {
    #[inline]
    pub fn push(&mut self, x: f64) {
        self.count += 1;
        let before = x - self.mean;
        self.mean += before / self.count as f64;
        self.m2 += before * (x - self.mean);
    }

    /// The sample variance S_k / (k − 1); 0 with fewer than two samples.
    pub fn variance(&self) -> f64 {
        if self.count < 2 {
            0.0
        } else {
            self.m2 / (self.count - 1) as f64
        }
    }

    pub fn std_dev(&self) -> f64 {
        self.variance().sqrt()
    }
}

/// Default relative σ floor (see [`FeatureStats::sigma`]).
pub const DEFAULT_SIGMA_FLOOR_REL: f64 = 1e-6;

/// What training learned about one feature (a field's delta, or value).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FeatureStats {
    /// The field's name (from the layout).
    pub name: String,
    #[serde(flatten)]
    pub welford: Welford,
    /// The smallest and largest value seen in training.
    pub min: f64,
    pub max: f64,
    /// The largest magnitude of the field's *feature value* (before the delta) seen in
    /// training: a scale for the σ floor of float fields.
    pub magnitude: f64,
    /// True if the feature only takes integer values (integer fields, sign-exponent floats).
    pub integral: bool,
}

impl FeatureStats {
    pub fn new(name: impl Into<String>, integral: bool) -> Self {
        FeatureStats {
            name: name.into(),
            welford: Welford::default(),
            min: f64::INFINITY,
            max: f64::NEG_INFINITY,
            magnitude: 0.0,
            integral,
        }
    }

    /// Adds one training sample: the feature `x` and the field's feature value it came from.
    pub fn push(&mut self, x: f64, value: f64) {
        self.welford.push(x);
        self.min = self.min.min(x);
        self.max = self.max.max(x);
        self.magnitude = self.magnitude.max(value.abs());
    }

    /// The σ a detector divides by: the learned σ, but never below a floor, so that a field
    /// that hardly moved in training does not alarm on its first tiny change:
    ///
    /// `σ_eff = max(σ, 1 if integral, floor_rel × magnitude, f64::MIN_POSITIVE)`
    ///
    /// An integer feature's smallest change is 1; a float field's changes are measured against
    /// its size (`floor_rel`, default 1e-6: a change of a millionth of the field's largest
    /// value is never more than one σ). A float field that was exactly zero throughout
    /// training has no scale and alarms on any change.
    pub fn sigma(&self, floor_rel: f64) -> f64 {
        let mut floor = (floor_rel * self.magnitude).max(f64::MIN_POSITIVE);
        if self.integral {
            floor = floor.max(1.0);
        }
        self.welford.std_dev().max(floor)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn two_pass(xs: &[f64]) -> (f64, f64) {
        let n = xs.len() as f64;
        let mean = xs.iter().sum::<f64>() / n;
        let var = if xs.len() < 2 {
            0.0
        } else {
            xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)
        };
        (mean, var)
    }

    proptest! {
        /// Welford's one pass agrees with the textbook two-pass mean and variance.
        #[test]
        fn welford_equals_two_pass(
            xs in proptest::collection::vec(-1e6f64..1e6, 1..500),
            offset in -1e9f64..1e9,
        ) {
            let xs: Vec<f64> = xs.iter().map(|x| x + offset).collect();
            let mut w = Welford::default();
            for &x in &xs {
                w.push(x);
            }
            let (mean, var) = two_pass(&xs);
            prop_assert_eq!(w.count, xs.len() as u64);
            let scale = 1.0 + offset.abs() + 1e6;
            prop_assert!((w.mean - mean).abs() <= 1e-12 * scale, "{} vs {}", w.mean, mean);
            prop_assert!((w.variance() - var).abs() <= 1e-9 * (var + 1.0), "{} vs {}", w.variance(), var);
        }
    }

    #[test]
    fn sigma_floor_rule() {
        let mut constant = FeatureStats::new("c", false);
        for _ in 0..100 {
            constant.push(0.0, 50.0);
        }
        assert_eq!(constant.welford.std_dev(), 0.0);
        assert_eq!(constant.sigma(1e-6), 50.0 * 1e-6);
        let mut counter = FeatureStats::new("seq", true);
        for i in 0..100 {
            counter.push(1.0, i as f64);
        }
        assert_eq!(counter.sigma(1e-6), 1.0);
        let zero = FeatureStats::new("z", false);
        assert_eq!(zero.sigma(1e-6), f64::MIN_POSITIVE);
    }
}
