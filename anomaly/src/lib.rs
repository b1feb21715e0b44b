//! Anomaly detection for s3res output frames, after MAVFI §5: a Gaussian model of each monitored
//! value's change and a small autoencoder over all of them, learned from fault-free runs.
//!
//! With one replica a silent data corruption cannot be seen by comparing outputs; with two it
//! can be seen but not attributed. A detector scores each replica's frame on its own, so the
//! voter can tell which of two disagreeing replicas is implausible, and can catch a corruption
//! that a lone replica produces.
//!
//! - [`layout`]: which numeric fields of a frame to watch ([`FieldLayout`]), zero-alloc decode.
//! - [`preprocess`]: delta from the previous frame, optional sign+exponent reduction.
//! - [`stats`]: Welford mean/variance and the σ floor.
//! - [`network`]: the dense autoencoder and its Adam training.
//! - [`model`]: model files (JSON).
//! - [`detector`]: [`Detector::observe`], called by the voter per replica frame.
//! - [`train`]: [`Trainer`], fault-free frames in, a model out (the `s3res-train` binary).
//! - [`capture`]: files of length-prefixed frames.
//! - [`synthetic`]: smooth synthetic robot telemetry for tests and measurements.
//!
//! See `docs/anomaly-detection.md`.

#![forbid(unsafe_code)]

pub mod capture;
pub mod detector;
/// The layout is part of the plan a voter receives, so it is the protocol's (`s3res-protocol`).
pub use s3res_protocol::layout;
pub mod model;
pub mod network;
pub mod preprocess;
pub mod stats;
pub mod synthetic;
pub mod train;

pub use detector::{Cause, Detector, Verdict};
pub use layout::{DecodeError, Field, FieldLayout, FieldType, LayoutError};
pub use model::{Model, ModelError};
pub use preprocess::{FloatRepr, Preprocess};
pub use train::{AutoencoderConfig, TrainError, Trainer};
