//! The sensor filter: a per-beam running median over the last few scans.
//!
//! A single spurious echo (or a missed one) on one beam is an outlier the median of three
//! removes, while a real wall, seen on consecutive scans, passes with one scan of delay at most.
//! The filter is a pure function of the scans it has seen, so replicas agree byte for byte.

use crate::msg::{Scan, RANGES};

/// Longest window the filter accepts.
pub const MAX_WINDOW: usize = 9;

/// Per-beam running median over a window of `window` scans.
#[derive(Debug, Clone)]
pub struct MedianFilter {
    window: usize,
    /// Ring buffer of the last `window` range sets.
    history: [[f64; RANGES]; MAX_WINDOW],
    /// Scans seen (saturating), for the warm-up.
    seen: usize,
    next: usize,
}

impl MedianFilter {
    /// `window` is clamped to 1..=[`MAX_WINDOW`].
    pub fn new(window: usize) -> MedianFilter {
        MedianFilter {
            window: window.clamp(1, MAX_WINDOW),
            history: [[0.0; RANGES]; MAX_WINDOW],
            seen: 0,
            next: 0,
        }
    }

    /// Takes a raw scan, returns it with each range replaced by the median of that beam over
    /// the window (over the scans seen so far during the warm-up).
    pub fn apply(&mut self, raw: &Scan) -> Scan {
        self.history[self.next] = raw.ranges;
        self.next = (self.next + 1) % self.window;
        self.seen = (self.seen + 1).min(self.window);
        let mut out = raw.clone();
        let mut column = [0.0f64; MAX_WINDOW];
        for (beam, r) in out.ranges.iter_mut().enumerate() {
            for (slot, v) in column[..self.seen].iter_mut().enumerate() {
                *v = self.history[slot][beam];
            }
            let col = &mut column[..self.seen];
            col.sort_by(f64::total_cmp);
            // Lower median for an even count: never invents a value.
            *r = col[(self.seen - 1) / 2];
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan(ranges: [f64; RANGES]) -> Scan {
        Scan {
            seq: 0,
            grid_w: 1,
            grid_h: 1,
            block: 0.25,
            x: 0.0,
            y: 0.0,
            theta: 0.0,
            goal_x: 0.0,
            goal_y: 0.0,
            ranges,
        }
    }

    #[test]
    fn a_single_outlier_is_rejected_and_a_real_change_passes() {
        let mut f = MedianFilter::new(3);
        let base = [1.0; RANGES];
        f.apply(&scan(base));
        f.apply(&scan(base));
        let mut spike = base;
        spike[4] = 0.05; // spurious echo
        spike[9] = 2.0; // missed echo
        let out = f.apply(&scan(spike));
        assert_eq!(out.ranges, base, "outliers must not pass");
        // A wall that appears and stays is reported from its second scan on.
        let mut wall = base;
        wall[0] = 0.4;
        assert_eq!(f.apply(&scan(wall)).ranges[0], 1.0);
        assert_eq!(f.apply(&scan(wall)).ranges[0], 0.4);
        assert_eq!(f.apply(&scan(wall)).ranges[0], 0.4);
    }

    #[test]
    fn warm_up_and_nan_do_not_break_it() {
        let mut f = MedianFilter::new(3);
        let mut r = [1.0; RANGES];
        r[2] = f64::NAN;
        let out = f.apply(&scan(r));
        assert_eq!(out.ranges[0], 1.0);
        let out = f.apply(&scan([0.5; RANGES]));
        // Lower median of {1.0, 0.5} is 0.5.
        assert_eq!(out.ranges[0], 0.5);
        assert_eq!(MedianFilter::new(0).window, 1);
        assert_eq!(MedianFilter::new(100).window, MAX_WINDOW);
    }
}
