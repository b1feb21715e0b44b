//! Synthetic robot telemetry for tests, the cost benchmark and detection measurements: the
//! output frame of a ground robot's controller, moving smoothly with sensor noise. It stands in
//! for real captures until the maze robot's are available (issue 7, step 6); figures measured
//! on it say how the detectors behave on smooth signals, not how they do on the maze.

use crate::layout::{Field, FieldLayout, FieldType};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Bytes in one synthetic frame.
pub const FRAME_LEN: usize = 88;

/// The 13 monitored fields of a synthetic frame (MAVFI monitors 13 values too).
pub fn robot_layout() -> FieldLayout {
    use FieldType::*;
    let fields = [
        ("seq", U32, 0),
        ("waypoint", U16, 4),
        ("x", F64, 8),
        ("y", F64, 16),
        ("heading", F64, 24),
        ("speed", F64, 32),
        ("yaw_rate", F64, 40),
        ("accel", F64, 48),
        ("goal_x", F64, 56),
        ("goal_y", F64, 64),
        ("goal_dist", F64, 72),
        ("range_front", F32, 80),
        ("range_left", F32, 84),
    ];
    FieldLayout::new(
        fields
            .iter()
            .map(|&(n, t, o)| Field::new(n, t, o))
            .collect(),
    )
    .expect("the synthetic layout is valid")
}

/// One run of the robot: an iterator of frames, deterministic for its seed.
pub struct Robot {
    rng: ChaCha8Rng,
    t: f64,
    seq: u32,
    x: f64,
    y: f64,
    heading: f64,
    speed: f64,
    phase: [f64; 5],
}

/// Control period, seconds (20 Hz).
const DT: f64 = 0.05;

impl Robot {
    pub fn new(seed: u64) -> Robot {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let phase = [(); 5].map(|_| rng.gen_range(0.0..std::f64::consts::TAU));
        Robot {
            x: rng.gen_range(-10.0..10.0),
            y: rng.gen_range(-10.0..10.0),
            heading: rng.gen_range(-3.0..3.0),
            // Already at the cruise speed: no start-up transient, which a detector would only
            // know if the training runs had shown it often enough.
            speed: 0.6 + 0.4 * phase[0].sin(),
            seq: rng.gen_range(0..1000),
            t: 0.0,
            rng,
            phase,
        }
    }

    fn noise(&mut self, sigma: f64) -> f64 {
        // Box–Muller.
        let u1: f64 = self.rng.gen_range(f64::EPSILON..1.0);
        let u2: f64 = self.rng.gen();
        sigma * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// The next frame.
    pub fn step(&mut self) -> [u8; FRAME_LEN] {
        let p = self.phase;
        self.t += DT;
        let t = self.t;
        let target = 0.6 + 0.4 * (0.21 * t + p[0]).sin();
        let accel = (target - self.speed) * 2.0 + self.noise(0.02);
        self.speed += accel * DT;
        let yaw_rate =
            0.5 * (0.13 * t + p[1]).sin() + 0.2 * (0.37 * t + p[2]).sin() + self.noise(0.005);
        self.heading += yaw_rate * DT;
        self.x += self.speed * self.heading.cos() * DT + self.noise(0.0005);
        self.y += self.speed * self.heading.sin() * DT + self.noise(0.0005);
        let look = 1.5 + 0.2 * (0.05 * t + p[3]).sin();
        let goal_x = self.x + look * (self.heading + 0.4 * yaw_rate).cos();
        let goal_y = self.y + look * (self.heading + 0.4 * yaw_rate).sin();
        let goal_dist =
            ((goal_x - self.x).powi(2) + (goal_y - self.y).powi(2)).sqrt() + self.noise(0.002);
        let range_front = (2.0 + 1.2 * (0.09 * t + p[4]).sin() + self.noise(0.01)) as f32;
        let range_left = (1.0 + 0.5 * (0.11 * t + p[4] * 0.5).cos() + self.noise(0.01)) as f32;
        self.seq = self.seq.wrapping_add(1);
        let waypoint = (self.t / 10.0) as u16;

        let mut f = [0u8; FRAME_LEN];
        f[0..4].copy_from_slice(&self.seq.to_le_bytes());
        f[4..6].copy_from_slice(&waypoint.to_le_bytes());
        let floats = [
            self.x,
            self.y,
            self.heading,
            self.speed,
            yaw_rate,
            accel,
            goal_x,
            goal_y,
            goal_dist,
        ];
        for (k, v) in floats.iter().enumerate() {
            f[8 + 8 * k..16 + 8 * k].copy_from_slice(&v.to_le_bytes());
        }
        f[80..84].copy_from_slice(&range_front.to_le_bytes());
        f[84..88].copy_from_slice(&range_left.to_le_bytes());
        f
    }

    /// `count` consecutive frames.
    pub fn frames(&mut self, count: usize) -> Vec<[u8; FRAME_LEN]> {
        (0..count).map(|_| self.step()).collect()
    }
}

/// Flips bit `bit` (0 = least significant) of field `field` of `frame`, in place.
pub fn flip(frame: &mut [u8], field: &Field, bit: u32) {
    let byte = field.offset + (bit / 8) as usize;
    frame[byte] ^= 1 << (bit % 8);
}

/// Which part of a field a bit is in, for tabulating detection by bit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum BitClass {
    Sign,
    /// The exponent's most significant bit (f64 bit 62, f32 bit 30): flips to ~1e±300 / 1e±38.
    ExponentTop,
    /// The other exponent bits.
    Exponent,
    /// The upper half of the mantissa (f64 bits 26..52, f32 bits 12..23).
    MantissaHigh,
    /// The lower half of the mantissa.
    MantissaLow,
    /// Integer fields: the upper and lower half of the bits.
    IntegerHigh,
    IntegerLow,
}

impl BitClass {
    pub fn of(ty: FieldType, bit: u32) -> BitClass {
        let (mantissa, exponent) = match ty {
            FieldType::F64 => (52, 11),
            FieldType::F32 => (23, 8),
            other => {
                let bits = 8 * other.size() as u32;
                return if bit >= bits / 2 {
                    BitClass::IntegerHigh
                } else {
                    BitClass::IntegerLow
                };
            }
        };
        if bit == mantissa + exponent {
            BitClass::Sign
        } else if bit == mantissa + exponent - 1 {
            BitClass::ExponentTop
        } else if bit >= mantissa {
            BitClass::Exponent
        } else if bit >= mantissa / 2 {
            BitClass::MantissaHigh
        } else {
            BitClass::MantissaLow
        }
    }
}

/// Detection counts of one class of injected flips.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Tally {
    pub injected: u64,
    /// The corrupted replica's frame alarmed.
    pub detected: u64,
    /// It alarmed and the healthy replica's frame (the same frame uncorrupted) did not: a DMR
    /// voter can blame the right replica.
    pub attributed: u64,
}

impl Tally {
    fn add(&mut self, corrupted: &crate::Verdict, healthy: &crate::Verdict) {
        self.injected += 1;
        self.detected += u64::from(corrupted.alarm);
        self.attributed += u64::from(corrupted.alarm && !healthy.alarm);
    }

    pub fn rate(&self) -> f64 {
        self.attributed as f64 / self.injected.max(1) as f64
    }
}

/// What a DMR injection campaign over one stream of frames saw.
#[derive(Debug, Clone, Default)]
pub struct Campaign {
    /// Frames of the healthy replica that were scored (not warm-up) and their alarms.
    pub clean_frames: u64,
    pub false_alarms: u64,
    pub by_class: std::collections::BTreeMap<BitClass, Tally>,
    /// Flips that moved their field's value by more than the field's normal range (largest
    /// minus smallest value in training), or to NaN/Inf.
    pub beyond_range: Tally,
}

/// Runs `frames` through `detector` (two replicas) as a DMR voter would: replica 0 always gets
/// the true frame; every `every`-th frame, replica 1 gets it with one random bit of one random
/// field flipped (seeded by `rng`), otherwise the true frame. After an injection replica 1's
/// stream is restored from replica 0's, as recovery by fork would do. `ranges[i]` is field
/// i's normal value range.
pub fn dmr_campaign(
    detector: &mut crate::Detector,
    frames: &[[u8; FRAME_LEN]],
    every: usize,
    ranges: &[f64],
    rng: &mut ChaCha8Rng,
    campaign: &mut Campaign,
) {
    let layout = detector.layout().clone();
    detector.reset_stream(0);
    detector.reset_stream(1);
    for (k, frame) in frames.iter().enumerate() {
        let healthy = detector.observe(0, frame);
        if healthy.cause != crate::Cause::Warmup {
            campaign.clean_frames += 1;
            campaign.false_alarms += u64::from(healthy.alarm);
        }
        if k == 0 || k % every != 0 {
            detector.observe(1, frame);
            continue;
        }
        let index = rng.gen_range(0..layout.len());
        let field = &layout.fields()[index];
        let bit = rng.gen_range(0..8 * field.ty.size() as u32);
        let mut corrupted = *frame;
        flip(&mut corrupted, field, bit);
        let verdict = detector.observe(1, &corrupted);
        campaign
            .by_class
            .entry(BitClass::of(field.ty, bit))
            .or_default()
            .add(&verdict, &healthy);
        let before = field.read_f64(frame).unwrap_or(f64::NAN);
        let after = field.read_f64(&corrupted).unwrap_or(f64::NAN);
        if !after.is_finite() || (after - before).abs() > ranges[index] {
            campaign.beyond_range.add(&verdict, &healthy);
        }
        detector.copy_stream(0, 1);
    }
}

/// Each field's normal range (largest minus smallest value) over `frames`.
pub fn value_ranges(layout: &FieldLayout, frames: &[[u8; FRAME_LEN]]) -> Vec<f64> {
    let mut lo = vec![f64::INFINITY; layout.len()];
    let mut hi = vec![f64::NEG_INFINITY; layout.len()];
    let mut values = vec![0.0; layout.len()];
    for f in frames {
        if layout.decode(f, &mut values).is_ok() {
            for i in 0..values.len() {
                lo[i] = lo[i].min(values[i]);
                hi[i] = hi[i].max(values[i]);
            }
        }
    }
    lo.iter().zip(&hi).map(|(l, h)| (h - l).max(0.0)).collect()
}

/// A trainer fed with `runs`, each run one stream, features as `floats` says (deltas).
pub fn trainer_for<'a>(
    runs: impl IntoIterator<Item = &'a [[u8; FRAME_LEN]]>,
    floats: crate::FloatRepr,
) -> crate::Trainer {
    let mut trainer = crate::Trainer::new(
        robot_layout(),
        crate::Preprocess {
            delta: true,
            floats,
        },
    );
    for run in runs {
        trainer.begin_stream();
        for f in run {
            // Cannot fail: synthetic frames are as long as the layout needs.
            let _ = trainer.push(f);
        }
    }
    trainer
}
