//! Exact binomial confidence intervals (Clopper–Pearson), for every rate a campaign prints: a
//! rate of 0 errors in 578 injections is not "0 %", it is "at most 0.64 % with 95 % confidence".
//!
//! The interval for `k` events in `n` trials at confidence `1 − α` is
//! `[B⁻¹(α/2; k, n − k + 1), B⁻¹(1 − α/2; k + 1, n − k)]`, where `B⁻¹(p; a, b)` is the `p`
//! quantile of the Beta(a, b) distribution, with the lower end 0 when `k = 0` and the upper end
//! 1 when `k = n`. The quantile is found by bisection on the regularised incomplete beta
//! function `I_x(a, b)`, computed by its continued fraction (Lentz's method) with the log-gamma
//! function of Lanczos. Accurate to about 1e-12 absolute, which is far below the two decimals
//! the tables print.

use serde::{Deserialize, Serialize};

/// The confidence level of every interval in tables and summaries.
pub const CONFIDENCE: f64 = 0.95;

/// A rate and what it rests on: `k` of `n`, as a percentage, with its exact 95 % interval.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Rate {
    /// The events counted (errors, successful runs).
    pub k: u64,
    /// The trials they are counted among (delivered injections, runs).
    pub n: u64,
    /// `k / n × 100`.
    pub pct: f64,
    /// The 95 % Clopper–Pearson interval, in percent.
    pub lower_pct: f64,
    pub upper_pct: f64,
}

impl Rate {
    /// `k` of `n` with its interval; `None` when `n` is 0 (no rate at all). `k` above `n` is
    /// taken as `n`.
    pub fn of(k: u64, n: u64) -> Option<Rate> {
        if n == 0 {
            return None;
        }
        let k = k.min(n);
        let (lo, hi) = clopper_pearson(k, n, CONFIDENCE);
        Some(Rate {
            k,
            n,
            pct: k as f64 * 100.0 / n as f64,
            lower_pct: lo * 100.0,
            upper_pct: hi * 100.0,
        })
    }

    /// The rate is one: `k` of `n > 0`, and its interval holds it within [0, 100] %.
    pub fn holds(&self) -> bool {
        self.k <= self.n
            && self.n > 0
            && 0.0 <= self.lower_pct
            && self.lower_pct <= self.pct
            && self.pct <= self.upper_pct
            && self.upper_pct <= 100.0
    }

    /// The interval as tables print it: `[0, 0.64]` (percent, two decimals, the ends 0 and 100
    /// exact).
    pub fn interval(&self) -> String {
        format!("[{}, {}]", pct_end(self.lower_pct), pct_end(self.upper_pct))
    }
}

/// `0.00 % [0, 0.64] of 578`: the rate, its interval and the count it rests on.
impl std::fmt::Display for Rate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:.2} % {} of {}", self.pct, self.interval(), self.n)
    }
}

fn pct_end(p: f64) -> String {
    if p <= 0.0 {
        "0".to_owned()
    } else if p >= 100.0 {
        "100".to_owned()
    } else {
        format!("{p:.2}")
    }
}

/// The exact (Clopper–Pearson) two-sided interval for a binomial proportion: `k` events in `n`
/// trials, at `confidence` (e.g. 0.95). Returns fractions in [0, 1].
///
/// # Panics
/// If `n` is 0, `k > n`, or `confidence` is not strictly between 0 and 1.
pub fn clopper_pearson(k: u64, n: u64, confidence: f64) -> (f64, f64) {
    assert!(n > 0 && k <= n, "{k} events in {n} trials");
    assert!(
        confidence > 0.0 && confidence < 1.0,
        "confidence {confidence}"
    );
    let tail = (1.0 - confidence) / 2.0;
    let (kf, nf) = (k as f64, n as f64);
    let lower = if k == 0 {
        0.0
    } else if k == n {
        // Closed form: I_x(n, 1) = xⁿ.
        tail.powf(1.0 / nf)
    } else {
        beta_quantile(tail, kf, nf - kf + 1.0)
    };
    let upper = if k == n {
        1.0
    } else if k == 0 {
        // Closed form: I_x(1, n) = 1 − (1 − x)ⁿ.
        1.0 - tail.powf(1.0 / nf)
    } else {
        beta_quantile(1.0 - tail, kf + 1.0, nf - kf)
    };
    (lower, upper)
}

/// The `p` quantile of Beta(a, b): the `x` with `I_x(a, b) = p`, by bisection (`I_x` increases
/// with `x`).
pub fn beta_quantile(p: f64, a: f64, b: f64) -> f64 {
    let (mut lo, mut hi) = (0.0_f64, 1.0_f64);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if mid <= lo || mid >= hi {
            break;
        }
        if reg_inc_beta(a, b, mid) < p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// The regularised incomplete beta function `I_x(a, b)`, for `a, b > 0` and `x` in [0, 1].
pub fn reg_inc_beta(a: f64, b: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    if x >= 1.0 {
        return 1.0;
    }
    let ln_front = ln_gamma(a + b) - ln_gamma(a) - ln_gamma(b) + a * x.ln() + b * (1.0 - x).ln();
    let front = ln_front.exp();
    // The continued fraction converges fast for x below the mean; use the symmetry
    // I_x(a, b) = 1 − I_{1−x}(b, a) above it.
    if x < (a + 1.0) / (a + b + 2.0) {
        front * beta_cf(a, b, x) / a
    } else {
        1.0 - front * beta_cf(b, a, 1.0 - x) / b
    }
}

/// The continued fraction of the incomplete beta function, by the modified Lentz method.
fn beta_cf(a: f64, b: f64, x: f64) -> f64 {
    const TINY: f64 = 1e-300;
    const EPS: f64 = 1e-15;
    let away_from_zero = |v: f64| if v.abs() < TINY { TINY } else { v };
    let (qab, qap, qam) = (a + b, a + 1.0, a - 1.0);
    let mut c = 1.0;
    let mut d = 1.0 / away_from_zero(1.0 - qab * x / qap);
    let mut h = d;
    // One term of the fraction: its coefficient `aa` updates c and d; returns the factor of h.
    let mut term = |aa: f64| {
        d = 1.0 / away_from_zero(1.0 + aa * d);
        c = away_from_zero(1.0 + aa / c);
        d * c
    };
    // Enough for a and b in the millions (the number of terms grows like their square root).
    for m in 1..100_000 {
        let m = f64::from(m);
        let m2 = 2.0 * m;
        h *= term(m * (b - m) * x / ((qam + m2) * (a + m2)));
        let step = term(-(a + m) * (qab + m) * x / ((a + m2) * (qap + m2)));
        h *= step;
        if (step - 1.0).abs() < EPS {
            break;
        }
    }
    h
}

/// `ln Γ(x)` for `x > 0` (Lanczos, g = 7, 9 terms; relative error about 1e-15).
pub fn ln_gamma(x: f64) -> f64 {
    const G: f64 = 7.0;
    const COEF: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        // Reflection: Γ(x) Γ(1 − x) = π / sin(πx).
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut sum = COEF[0];
    for (i, c) in COEF.iter().enumerate().skip(1) {
        sum += c / (x + i as f64);
    }
    let t = x + G + 0.5;
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + sum.ln()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(got: f64, want: f64, tol: f64) {
        assert!((got - want).abs() <= tol, "{got} vs {want}");
    }

    #[test]
    fn log_gamma_of_known_values() {
        close(ln_gamma(1.0), 0.0, 1e-14);
        close(ln_gamma(2.0), 0.0, 1e-14);
        close(ln_gamma(0.5), std::f64::consts::PI.sqrt().ln(), 1e-14);
        // ln(10!) and ln Γ(5001) = ln(5000!).
        close(ln_gamma(11.0), 3_628_800f64.ln(), 1e-12);
        close(ln_gamma(5001.0), 37_591.143_508_876_87, 1e-8);
    }

    #[test]
    fn incomplete_beta_of_known_values() {
        // I_x(1, 1) = x; I_x(2, 1) = x²; I_x(a, b) = 1 − I_{1−x}(b, a).
        close(reg_inc_beta(1.0, 1.0, 0.3), 0.3, 1e-14);
        close(reg_inc_beta(2.0, 1.0, 0.3), 0.09, 1e-14);
        close(
            reg_inc_beta(3.5, 7.25, 0.4),
            1.0 - reg_inc_beta(7.25, 3.5, 0.6),
            1e-13,
        );
        // I_0.5(a, a) = 1/2 by symmetry.
        close(reg_inc_beta(40.0, 40.0, 0.5), 0.5, 1e-13);
        // I_x(2, 3) = 6x² (1/2 − 2x/3 + x²/4) ... = 1 − (1−x)⁴ − 4x(1−x)³ (binomial tail).
        let x: f64 = 0.2;
        close(
            reg_inc_beta(2.0, 3.0, x),
            1.0 - (1.0 - x).powi(4) - 4.0 * x * (1.0 - x).powi(3),
            1e-14,
        );
    }

    #[test]
    fn clopper_pearson_of_known_values() {
        // 0/578 (the robot campaign's DMR exec cell): upper 0.636 %.
        let (lo, hi) = clopper_pearson(0, 578, 0.95);
        assert_eq!(lo, 0.0);
        close(hi, 0.006_361_8, 5e-7);
        // 0/5000: upper 0.0738 %.
        let (lo, hi) = clopper_pearson(0, 5000, 0.95);
        assert_eq!(lo, 0.0);
        close(hi, 0.000_737_5, 5e-7);
        // 5/100: [1.64 %, 11.28 %] (R: binom.test(5, 100)$conf.int = 0.01643 0.11284).
        let (lo, hi) = clopper_pearson(5, 100, 0.95);
        close(lo, 0.016_431, 5e-6);
        close(hi, 0.112_835, 5e-6);
        // 9/12: [42.81 %, 94.51 %] (binom.test(9, 12)).
        let (lo, hi) = clopper_pearson(9, 12, 0.95);
        close(lo, 0.428_142, 5e-6);
        close(hi, 0.945_139, 5e-6);
        // k = n: the mirror of k = 0.
        let (lo, hi) = clopper_pearson(100, 100, 0.95);
        close(lo, 0.963_783_3, 5e-7);
        assert_eq!(hi, 1.0);
        // Large counts stay accurate: 14 of 1034, and 1 of 1,000,000.
        let (lo, hi) = clopper_pearson(14, 1034, 0.95);
        close(lo, 0.007_421, 5e-6);
        close(hi, 0.022_613, 5e-6);
        let (lo, hi) = clopper_pearson(1, 1_000_000, 0.95);
        close(lo, 2.532e-8, 5e-11);
        close(hi, 5.5716e-6, 5e-10);
    }

    #[test]
    fn the_interval_holds_the_rate_and_shrinks_with_n() {
        let mut last_width = 1.0;
        for n in [10u64, 100, 1000, 10_000] {
            for k in [0, 1, n / 3, n - 1, n] {
                let (lo, hi) = clopper_pearson(k, n, 0.95);
                let p = k as f64 / n as f64;
                assert!(lo <= p && p <= hi && (0.0..=1.0).contains(&lo) && hi <= 1.0);
            }
            let (lo, hi) = clopper_pearson(n / 2, n, 0.95);
            assert!(hi - lo < last_width);
            last_width = hi - lo;
        }
    }

    #[test]
    fn rates_print_with_interval_and_count() {
        assert_eq!(
            Rate::of(0, 578).unwrap().to_string(),
            "0.00 % [0, 0.64] of 578"
        );
        assert_eq!(
            Rate::of(5, 100).unwrap().to_string(),
            "5.00 % [1.64, 11.28] of 100"
        );
        assert_eq!(
            Rate::of(3, 3).unwrap().to_string(),
            "100.00 % [29.24, 100] of 3"
        );
        assert_eq!(Rate::of(0, 0), None);
    }
}
