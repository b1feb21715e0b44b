//! The detectors on synthetic robot telemetry: normal motion passes, corrupted values alarm,
//! models survive a save and load bit for bit. Every random choice is seeded.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use s3res_anomaly::model::DetectorModel;
use s3res_anomaly::network::{default_sizes, Network, Sgd};
use s3res_anomaly::synthetic::{
    dmr_campaign, flip, robot_layout, trainer_for, value_ranges, Campaign, Robot, FRAME_LEN,
};
use s3res_anomaly::{AutoencoderConfig, Cause, Detector, FieldType, FloatRepr, Model, Trainer};

const SEED: u64 = 42;

fn trainer(runs: std::ops::Range<u64>, frames: usize, floats: FloatRepr) -> Trainer {
    let runs: Vec<_> = runs
        .map(|r| Robot::new(SEED * 1000 + r).frames(frames))
        .collect();
    trainer_for(runs.iter().map(Vec::as_slice), floats)
}

fn small_autoencoder(trainer: &Trainer) -> Model {
    trainer
        .autoencoder(&AutoencoderConfig {
            seed: SEED,
            sgd: Sgd {
                epochs: 25,
                ..Sgd::default()
            },
            ..Default::default()
        })
        .unwrap()
}

/// Alarms of a detector (one replica) over a held-out fault-free run.
fn false_alarms(detector: &mut Detector, frames: &[[u8; FRAME_LEN]]) -> usize {
    detector.reset_stream(0);
    let mut alarms = 0;
    for f in frames {
        alarms += usize::from(detector.observe(0, f).alarm);
    }
    alarms
}

/// Flips `bit` of every f64 field of a frame in turn (each on a fresh stream state) and
/// returns how many alarmed, out of how many were tried (only values whose magnitude is at
/// least `min_magnitude` are tried: a sign flip of a value near zero changes nothing).
fn flips_detected(
    detector: &mut Detector,
    frames: &[[u8; FRAME_LEN]],
    bit: u32,
    min_magnitude: f64,
) -> (usize, usize) {
    let layout = robot_layout();
    let (mut tried, mut detected) = (0, 0);
    detector.reset_stream(0);
    for (k, f) in frames.iter().enumerate() {
        let v = detector.observe(0, f);
        assert!(!v.alarm || k == 0, "false alarm at frame {k}: {v:?}");
        if k % 10 != 5 {
            continue;
        }
        for field in layout.fields().iter().filter(|f| f.ty == FieldType::F64) {
            let next = &frames[(k + 1).min(frames.len() - 1)];
            if field.read_f64(next).unwrap().abs() < min_magnitude {
                continue;
            }
            let mut corrupted = *next;
            flip(&mut corrupted, field, bit);
            detector.copy_stream(0, 1);
            tried += 1;
            detected += usize::from(detector.observe(1, &corrupted).alarm);
        }
    }
    (detected, tried)
}

#[test]
fn gaussian_passes_smooth_motion_and_flags_sign_and_exponent_flips() {
    println!("seed {SEED}");
    let model = trainer(0..4, 5_000, FloatRepr::Value)
        .gaussian(6.0, 1e-6)
        .unwrap();
    let mut detector = Detector::new(&model, 2).unwrap();
    let held_out = Robot::new(SEED * 1000 + 900).frames(20_000);
    let alarms = false_alarms(&mut detector, &held_out);
    println!(
        "gaussian: {alarms} false alarms in {} frames",
        held_out.len()
    );
    assert!(
        alarms <= 2,
        "{alarms} false alarms in 20,000 fault-free frames"
    );

    let test = &held_out[..3_000];
    // The top exponent bit: the value becomes ~1e±300 or Inf/NaN.
    let (hit, tried) = flips_detected(&mut detector, test, 62, 0.0);
    assert_eq!(hit, tried, "top exponent flips");
    // The sign of a value of magnitude ≥ 1: a jump of at least 2.
    let (hit, tried) = flips_detected(&mut detector, test, 63, 1.0);
    assert!(tried > 100, "{tried}");
    assert_eq!(hit, tried, "sign flips");
    // The lowest mantissa bit changes a value by ~1e-16: invisible, as expected.
    let (hit, _) = flips_detected(&mut detector, test, 0, 0.0);
    assert_eq!(hit, 0, "lowest mantissa bit");
}

#[test]
fn autoencoder_learns_normal_motion_and_flags_exponent_flips() {
    println!("seed {SEED}");
    let trainer = trainer(0..3, 3_000, FloatRepr::Value);
    let model = small_autoencoder(&trainer);
    let DetectorModel::Autoencoder(ae) = &model.detector else {
        panic!("an autoencoder model")
    };
    println!("training: {:?}, threshold {}", ae.training, ae.threshold);
    assert!(
        ae.training.final_loss < ae.training.first_loss,
        "{:?}",
        ae.training
    );
    // The same network before training (same seed, same initialisation), on the same
    // standardised features, reconstructs much worse.
    let untrained = Network::new(&default_sizes(13), &mut ChaCha8Rng::seed_from_u64(SEED));
    let mut scratch = untrained.scratch();
    let mut row = vec![0.0; 13];
    let mut before = 0.0;
    for raw in trainer.rows().chunks_exact(13) {
        for (i, s) in ae.features.iter().enumerate() {
            row[i] = (raw[i] - s.welford.mean) / s.sigma(ae.sigma_floor_rel);
        }
        before += untrained.reconstruction_error(&row, &mut scratch);
    }
    before /= trainer.samples() as f64;
    println!(
        "mean reconstruction error: {before} untrained, {} trained",
        ae.training.mean_error
    );
    assert!(
        ae.training.mean_error < 0.7 * before,
        "{before} → {:?}",
        ae.training
    );

    let mut detector = Detector::new(&model, 2).unwrap();
    let held_out = Robot::new(SEED * 1000 + 901).frames(10_000);
    let alarms = false_alarms(&mut detector, &held_out);
    println!(
        "autoencoder: {alarms} false alarms in {} frames",
        held_out.len()
    );
    assert!(
        alarms <= 1,
        "{alarms} false alarms in 10,000 fault-free frames"
    );

    let (hit, tried) = flips_detected(&mut detector, &held_out[..2_000], 62, 0.0);
    assert_eq!(hit, tried, "top exponent flips");
}

#[test]
fn dmr_campaign_attributes_flips_beyond_the_normal_range() {
    println!("seed {SEED}");
    let layout = robot_layout();
    let train_runs: Vec<_> = (0..3)
        .map(|r| Robot::new(SEED * 1000 + r).frames(3_000))
        .collect();
    let all: Vec<_> = train_runs.iter().flatten().copied().collect();
    let ranges = value_ranges(&layout, &all);
    let trainer = trainer(0..3, 3_000, FloatRepr::Value);
    for model in [
        trainer.gaussian(6.0, 1e-6).unwrap(),
        small_autoencoder(&trainer),
    ] {
        let mut detector = Detector::new(&model, 2).unwrap();
        let mut campaign = Campaign::default();
        let mut rng = ChaCha8Rng::seed_from_u64(SEED);
        let test = Robot::new(SEED * 1000 + 902).frames(10_000);
        dmr_campaign(&mut detector, &test, 5, &ranges, &mut rng, &mut campaign);
        let b = campaign.beyond_range;
        println!("{}: {campaign:?}", model.kind());
        assert!(b.injected > 300, "{b:?}");
        assert!(b.rate() >= 0.95, "{}: attributed {b:?}", model.kind());
        assert!(campaign.false_alarms <= 1, "{campaign:?}");
    }
}

#[test]
fn models_round_trip_bit_exactly() {
    println!("seed {SEED}");
    let dir = tempfile::tempdir().unwrap();
    let trainer = trainer(0..2, 1_000, FloatRepr::Value);
    for model in [
        trainer.gaussian(6.0, 1e-6).unwrap(),
        small_autoencoder(&trainer),
    ] {
        let path = dir.path().join(format!("{}.json", model.kind()));
        model.save(&path).unwrap();
        let loaded = Model::load(&path).unwrap();
        assert_eq!(loaded, model);
        let bits = |m: &Model| -> Vec<u64> {
            let mut all = Vec::new();
            let features = match &m.detector {
                DetectorModel::Gaussian(g) => &g.features,
                DetectorModel::Autoencoder(a) => {
                    for l in &a.network.layers {
                        all.extend(l.weights.iter().chain(&l.bias).map(|v| v.to_bits()));
                    }
                    all.push(a.threshold.to_bits());
                    &a.features
                }
            };
            for s in features {
                all.extend(
                    [s.welford.mean, s.welford.m2, s.min, s.max, s.magnitude].map(f64::to_bits),
                );
            }
            all
        };
        assert_eq!(bits(&loaded), bits(&model));
        // And the detectors made from both agree on every score, bit for bit.
        let (mut a, mut b) = (
            Detector::new(&model, 1).unwrap(),
            Detector::new(&loaded, 1).unwrap(),
        );
        for f in Robot::new(SEED * 1000 + 903).frames(500) {
            assert_eq!(
                a.observe(0, &f).score.to_bits(),
                b.observe(0, &f).score.to_bits()
            );
        }
    }
}

#[test]
fn stream_rules() {
    let trainer = trainer(0..2, 1_000, FloatRepr::Value);
    let model = trainer.gaussian(6.0, 1e-6).unwrap();
    let mut d = Detector::new(&model, 2).unwrap();
    let frames = Robot::new(SEED * 1000 + 904).frames(10);
    let layout = robot_layout();
    let x = &layout.fields()[2];

    // First frame: warm-up. Then normal.
    assert_eq!(d.observe(0, &frames[0]).cause, Cause::Warmup);
    let v = d.observe(0, &frames[1]);
    assert_eq!((v.cause, v.alarm), (Cause::Normal, false));

    // NaN is always an alarm, even on a stream's first frame, and names its field.
    let mut nan = frames[2];
    nan[x.offset..x.offset + 8].copy_from_slice(&f64::NAN.to_le_bytes());
    let v = d.observe(1, &nan);
    assert_eq!(
        (v.cause, v.alarm, v.field),
        (Cause::NonFinite, true, Some(2))
    );
    assert_eq!(d.field_name(2), "x");
    // A short frame is an alarm, not a panic.
    let v = d.observe(0, &frames[2][..40]);
    assert_eq!((v.cause, v.alarm, v.field), (Cause::ShortFrame, true, None));

    // A corrupted frame alarms and names its field; it becomes the stream's reference (the
    // way back alarms too), but after the voter recovers the replica by fork, copy_stream
    // gives it the donor's reference and the next true frame passes.
    let mut bad = frames[2];
    flip(&mut bad, x, 62);
    d.copy_stream(0, 1);
    let v = d.observe(1, &bad);
    assert!(v.alarm && v.field == Some(2), "{v:?}");
    assert!(!d.observe(0, &frames[2]).alarm);
    d.copy_stream(0, 1);
    assert_eq!(d.observe(1, &frames[3]).cause, Cause::Normal);

    // A genuine jump alarms once, and the stream goes on from there: no alarm storm.
    let mut jumped = frames[4];
    jumped[x.offset..x.offset + 8].copy_from_slice(&1000.0f64.to_le_bytes());
    assert!(d.observe(1, &jumped).alarm);
    let mut after = frames[5];
    after[x.offset..x.offset + 8].copy_from_slice(&1000.01f64.to_le_bytes());
    assert!(!d.observe(1, &after).alarm);

    // reset_stream starts afresh; resync sets the reference without scoring.
    d.reset_stream(1);
    assert_eq!(d.observe(1, &frames[6]).cause, Cause::Warmup);
    d.reset_stream(1);
    d.resync(1, &frames[7]);
    assert_eq!(d.observe(1, &frames[8]).cause, Cause::Normal);
}

#[test]
fn a_model_for_other_fields_is_refused() {
    let trainer = trainer(0..1, 100, FloatRepr::Value);
    let model = trainer.gaussian(6.0, 1e-6).unwrap();
    let mut fields = robot_layout().fields().to_vec();
    fields[2].offset += 0;
    fields[3].name = "why".into();
    let other = s3res_anomaly::FieldLayout::new(fields).unwrap();
    let err = model.check_layout(&other).unwrap_err().to_string();
    assert!(
        err.contains("y:f64@16") && err.contains("why:f64@16"),
        "{err}"
    );
    assert!(model.check_layout(&robot_layout()).is_ok());

    let mut broken = model.clone();
    if let DetectorModel::Gaussian(g) = &mut broken.detector {
        g.features.pop();
    }
    assert!(Detector::new(&broken, 1).is_err());
    let mut wrong = model;
    wrong.version = 99;
    assert!(wrong.check().unwrap_err().contains("version 99"));
}

#[test]
fn random_flips_never_panic_and_non_finite_always_alarms() {
    let seed: u64 = 5;
    println!("seed {seed}");
    let trainer = trainer(0..1, 1_000, FloatRepr::SignExponent);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for model in [
        trainer.gaussian(6.0, 1e-6).unwrap(),
        small_autoencoder(&trainer),
    ] {
        let mut d = Detector::new(&model, 2).unwrap();
        let layout = robot_layout();
        for f in Robot::new(seed).frames(3_000) {
            d.observe(0, &f);
            let mut g = f;
            for _ in 0..rng.gen_range(1..6) {
                let byte = rng.gen_range(0..FRAME_LEN);
                g[byte] ^= 1 << rng.gen_range(0..8);
            }
            d.copy_stream(0, 1);
            let v = d.observe(1, &g);
            let non_finite = layout
                .fields()
                .iter()
                .any(|fl| !fl.read_f64(&g).unwrap().is_finite());
            if non_finite {
                assert!(v.alarm && v.cause == Cause::NonFinite, "{v:?}");
            }
            assert!(!v.score.is_nan(), "{v:?}");
        }
    }
}
