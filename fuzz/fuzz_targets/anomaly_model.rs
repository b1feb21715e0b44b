//! The anomaly model loader: a model file as `Model::load` reads it (JSON, then `check`), then
//! a detector built from it (`Detector::new`) scoring frames. The input is the model file, a
//! NUL byte, then frame bytes. A model that passes `check` must give a detector that scores any
//! frame without panicking; nothing may panic on the way to an error.
#![no_main]

use libfuzzer_sys::fuzz_target;
use s3res_anomaly::detector::Detector;
use s3res_anomaly::model::Model;

const REPLICAS: usize = 3;

fuzz_target!(|data: &[u8]| {
    let (text, frames) = match data.iter().position(|&b| b == 0) {
        Some(i) => (&data[..i], &data[i + 1..]),
        None => (data, &[][..]),
    };
    let Ok(model) = serde_json::from_slice::<Model>(text) else {
        return;
    };
    if model.check().is_err() {
        assert!(Detector::new(&model, REPLICAS).is_err());
        return;
    }
    let mut det = Detector::new(&model, REPLICAS).expect("a checked model makes a detector");
    let _ = det.threshold();
    let len = model.layout.min_frame().max(1);
    for (i, frame) in frames.chunks(len).take(64).enumerate() {
        let r = i % REPLICAS;
        let _ = det.observe(r, frame);
        match i % 7 {
            3 => det.copy_stream(r, (r + 1) % REPLICAS),
            5 => det.reset_stream(r),
            6 => det.resync(r, frame),
            _ => {}
        }
    }
});
