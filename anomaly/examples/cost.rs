//! Cost of `Detector::observe` per frame, at 13 monitored fields (a benchmark, not a test):
//!
//!     cargo run --release -p s3res-anomaly --example cost
//!
//! Each call is timed on its own with `Instant` (whose own cost, measured the same way on an
//! empty call, is printed too and not subtracted); the batch figure is the mean over 1000
//! calls timed together, free of the timer's cost.

use s3res_anomaly::synthetic::{robot_layout, trainer_for, Robot, FRAME_LEN};
use s3res_anomaly::{AutoencoderConfig, Detector, FloatRepr, Model};
use std::hint::black_box;
use std::time::Instant;

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn measure(name: &str, model: &Model, frames: &[[u8; FRAME_LEN]]) {
    let mut detector = Detector::new(model, 2).expect("valid model");
    let mut each = Vec::with_capacity(frames.len());
    let mut alarms = 0u32;
    for f in frames {
        let start = Instant::now();
        let v = detector.observe(0, black_box(f));
        each.push(start.elapsed().as_nanos() as u64);
        alarms += u32::from(v.alarm);
    }
    each.sort_unstable();
    let batches = frames.chunks_exact(1000).map(|chunk| {
        let start = Instant::now();
        for f in chunk {
            black_box(detector.observe(1, black_box(f)));
        }
        start.elapsed().as_nanos() as f64 / chunk.len() as f64
    });
    let mut batch: Vec<f64> = batches.collect();
    batch.sort_by(f64::total_cmp);
    println!(
        "{name:<28} median {:>4} ns  p99 {:>5} ns  max {:>6} ns  | batch mean (median of {}) {:>6.1} ns  | {alarms} alarms",
        percentile(&each, 0.5),
        percentile(&each, 0.99),
        each[each.len() - 1],
        batch.len(),
        batch[batch.len() / 2]
    );
}

fn main() {
    let layout = robot_layout();
    let frames = Robot::new(99).frames(50_000);
    let mut timer = Vec::with_capacity(50_000);
    for _ in 0..50_000 {
        let start = Instant::now();
        timer.push(black_box(start).elapsed().as_nanos() as u64);
    }
    timer.sort_unstable();
    println!(
        "{} fields, {} frames; timer alone: median {} ns, p99 {} ns",
        layout.len(),
        frames.len(),
        percentile(&timer, 0.5),
        percentile(&timer, 0.99)
    );
    for floats in [FloatRepr::Value, FloatRepr::SignExponent] {
        let runs: Vec<_> = (0..4).map(|run| Robot::new(run).frames(5_000)).collect();
        let trainer = trainer_for(runs.iter().map(Vec::as_slice), floats);
        let gaussian = trainer.gaussian(6.0, 1e-6).expect("enough samples");
        let autoencoder = trainer
            .autoencoder(&AutoencoderConfig::default())
            .expect("training works");
        measure(&format!("gaussian ({floats:?})"), &gaussian, &frames);
        measure(&format!("autoencoder ({floats:?})"), &autoencoder, &frames);
    }
}
