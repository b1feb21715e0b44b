//! Detection and false-alarm measurement on synthetic robot telemetry (not a test):
//!
//!     cargo run --release -p s3res-anomaly --example evaluate [-- SEED]
//!
//! Trains each detector on fault-free runs, then runs held-out runs as a DMR pair in which one
//! replica's frame gets a single random bit flip every 5th frame, and prints detection by bit
//! class, detection of flips beyond a field's normal range, and false alarms per 10,000
//! fault-free frames.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use s3res_anomaly::synthetic::{
    dmr_campaign, robot_layout, trainer_for, value_ranges, Campaign, Robot,
};
use s3res_anomaly::{AutoencoderConfig, Detector, FloatRepr};

fn main() {
    let seed: u64 = std::env::args()
        .nth(1)
        .map(|s| s.parse().expect("SEED must be a number"))
        .unwrap_or(1);
    println!("seed {seed}");
    let layout = robot_layout();
    let train_runs: Vec<_> = (0..8)
        .map(|r| Robot::new(seed * 1000 + r).frames(5_000))
        .collect();
    let test_runs: Vec<_> = (0..10)
        .map(|r| Robot::new(seed * 1000 + 500 + r).frames(10_000))
        .collect();
    let all_train: Vec<_> = train_runs.iter().flatten().copied().collect();
    let ranges = value_ranges(&layout, &all_train);

    for floats in [FloatRepr::Value, FloatRepr::SignExponent] {
        let trainer = trainer_for(train_runs.iter().map(Vec::as_slice), floats);
        let started = std::time::Instant::now();
        let ae = trainer
            .autoencoder(&AutoencoderConfig {
                seed,
                ..Default::default()
            })
            .expect("training works");
        let trained_in = started.elapsed();
        let models = [
            (
                "gaussian",
                trainer.gaussian(6.0, 1e-6).expect("enough samples"),
            ),
            ("autoencoder", ae),
        ];
        for (name, model) in &models {
            let mut detector = Detector::new(model, 2).expect("a fresh model is valid");
            let mut campaign = Campaign::default();
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            for run in &test_runs {
                dmr_campaign(&mut detector, run, 5, &ranges, &mut rng, &mut campaign);
            }
            println!(
                "\n{name}, floats {floats:?} ({} training samples{}):",
                trainer.samples(),
                if *name == "autoencoder" {
                    format!(", trained in {trained_in:.1?}")
                } else {
                    String::new()
                }
            );
            println!(
                "  false alarms: {} in {} fault-free frames = {:.2} per 10,000",
                campaign.false_alarms,
                campaign.clean_frames,
                campaign.false_alarms as f64 * 1e4 / campaign.clean_frames as f64
            );
            println!(
                "  {:<14} {:>8} {:>9} {:>10}",
                "bit class", "flips", "detected", "attributed"
            );
            for (class, t) in &campaign.by_class {
                println!(
                    "  {:<14} {:>8} {:>8.1}% {:>9.1}%",
                    format!("{class:?}"),
                    t.injected,
                    100.0 * t.detected as f64 / t.injected as f64,
                    100.0 * t.rate()
                );
            }
            let b = campaign.beyond_range;
            println!(
                "  {:<14} {:>8} {:>8.1}% {:>9.1}%",
                "beyond range",
                b.injected,
                100.0 * b.detected as f64 / b.injected.max(1) as f64,
                100.0 * b.rate()
            );
        }
    }
}
