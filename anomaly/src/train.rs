//! Training: fault-free frames in, a model out.

use crate::layout::{DecodeError, FieldLayout};
use crate::model::{
    AutoencoderModel, AutoencoderTraining, DetectorModel, GaussianModel, Model, CLAMP,
};
use crate::network::{default_sizes, train, Network, Scratch, Sgd};
use crate::preprocess::{Preprocess, Read};
use crate::stats::{FeatureStats, Welford};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use thiserror::Error;

#[derive(Debug, Error, PartialEq)]
pub enum TrainError {
    #[error("only {have} usable training samples; at least {need} are needed (each stream's first frame only starts its deltas)")]
    TooFewSamples { have: usize, need: usize },
    #[error("{0}")]
    Config(String),
}

/// Collects features from fault-free frames.
///
/// Frames arrive in streams (one replica's or one run's consecutive frames); a delta is taken
/// only between consecutive frames of one stream. A frame that is too short, or has a
/// non-finite float, is skipped, counted, and ends the stream (the next delta starts afresh).
pub struct Trainer {
    layout: FieldLayout,
    preprocess: Preprocess,
    stats: Vec<FeatureStats>,
    /// One row of `layout.len()` features per usable sample.
    rows: Vec<f64>,
    previous: Vec<f64>,
    current: Vec<f64>,
    has_previous: bool,
    /// Every frame offered, and the ones skipped.
    pub frames: u64,
    pub short: u64,
    pub non_finite: u64,
}

impl Trainer {
    pub fn new(layout: FieldLayout, preprocess: Preprocess) -> Self {
        let n = layout.len();
        let stats = layout
            .fields()
            .iter()
            .map(|f| FeatureStats::new(f.name.clone(), preprocess.integral(f.ty)))
            .collect();
        Trainer {
            layout,
            preprocess,
            stats,
            rows: Vec::new(),
            previous: vec![0.0; n],
            current: vec![0.0; n],
            has_previous: false,
            frames: 0,
            short: 0,
            non_finite: 0,
        }
    }

    /// The next frame starts a new stream.
    pub fn begin_stream(&mut self) {
        self.has_previous = false;
    }

    /// Usable samples so far.
    pub fn samples(&self) -> usize {
        self.rows.len() / self.layout.len()
    }

    /// The features of every sample, row after row.
    pub fn rows(&self) -> &[f64] {
        &self.rows
    }

    /// Offers the next frame of the current stream.
    pub fn push(&mut self, frame: &[u8]) -> Result<(), DecodeError> {
        self.frames += 1;
        match self.preprocess.read(&self.layout, frame, &mut self.current) {
            Err(e) => {
                self.short += 1;
                self.has_previous = false;
                return Err(e);
            }
            Ok(Read::NonFinite { .. }) => {
                self.non_finite += 1;
                self.has_previous = false;
                return Ok(());
            }
            Ok(Read::Finite) => {}
        }
        if !self.preprocess.delta || self.has_previous {
            for i in 0..self.current.len() {
                let x = if self.preprocess.delta {
                    self.current[i] - self.previous[i]
                } else {
                    self.current[i]
                };
                self.stats[i].push(x, self.current[i]);
                self.rows.push(x);
            }
        }
        std::mem::swap(&mut self.previous, &mut self.current);
        self.has_previous = true;
        Ok(())
    }

    fn need(&self, need: usize) -> Result<(), TrainError> {
        if self.samples() < need {
            Err(TrainError::TooFewSamples {
                have: self.samples(),
                need,
            })
        } else {
            Ok(())
        }
    }

    /// The Gaussian model of the features seen so far.
    pub fn gaussian(&self, n_sigma: f64, sigma_floor_rel: f64) -> Result<Model, TrainError> {
        self.need(2)?;
        check_sigma_floor(sigma_floor_rel)?;
        if !(n_sigma > 0.0 && n_sigma < CLAMP) {
            return Err(TrainError::Config(format!(
                "n_sigma {n_sigma} must be positive and below {CLAMP}"
            )));
        }
        Ok(Model::new(
            self.layout.clone(),
            self.preprocess,
            DetectorModel::Gaussian(GaussianModel {
                n_sigma,
                sigma_floor_rel,
                features: self.stats.clone(),
            }),
        ))
    }

    /// Trains an autoencoder on the features seen so far.
    pub fn autoencoder(&self, config: &AutoencoderConfig) -> Result<Model, TrainError> {
        self.need(10)?;
        let n = self.layout.len();
        let sizes = match &config.hidden {
            None => default_sizes(n),
            Some(h) if h.is_empty() => {
                return Err(TrainError::Config("give at least one hidden layer".into()))
            }
            Some(h) if h.contains(&0) => {
                return Err(TrainError::Config("a hidden layer has zero width".into()))
            }
            Some(h) => std::iter::once(n)
                .chain(h.iter().copied())
                .chain([n])
                .collect(),
        };
        check_sigma_floor(config.sigma_floor_rel)?;
        if config.sgd.epochs == 0 || config.sgd.batch == 0 {
            return Err(TrainError::Config(
                "epochs and batch must be at least 1".into(),
            ));
        }
        if !(config.sgd.learning_rate > 0.0 && config.sgd.learning_rate.is_finite()) {
            return Err(TrainError::Config(format!(
                "learning rate {} must be a positive number",
                config.sgd.learning_rate
            )));
        }
        if !(config.margin >= 1.0 && config.margin.is_finite()) {
            return Err(TrainError::Config(format!(
                "margin {} must be at least 1",
                config.margin
            )));
        }
        let mean: Vec<f64> = self.stats.iter().map(|s| s.welford.mean).collect();
        let inv: Vec<f64> = self
            .stats
            .iter()
            .map(|s| 1.0 / s.sigma(config.sigma_floor_rel))
            .collect();
        let standard: Vec<f64> = self
            .rows
            .chunks_exact(n)
            .flat_map(|row| {
                row.iter()
                    .zip(&mean)
                    .zip(&inv)
                    .map(|((x, m), i)| ((x - m) * i).clamp(-CLAMP, CLAMP))
            })
            .collect();
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        let mut network = Network::new(&sizes, &mut rng);
        let losses = train(&mut network, &standard, config.sgd, &mut rng);
        let mut scratch: Scratch = network.scratch();
        let mut errors = Welford::default();
        let mut max_error = 0.0f64;
        for row in standard.chunks_exact(n) {
            let e = network.reconstruction_error(row, &mut scratch);
            errors.push(e);
            max_error = max_error.max(e);
        }
        if !max_error.is_finite() || network.check().is_err() {
            return Err(TrainError::Config(
                "training diverged (non-finite error); lower the learning rate".into(),
            ));
        }
        let threshold = (config.margin * max_error).max(f64::MIN_POSITIVE);
        Ok(Model::new(
            self.layout.clone(),
            self.preprocess,
            DetectorModel::Autoencoder(AutoencoderModel {
                sigma_floor_rel: config.sigma_floor_rel,
                features: self.stats.clone(),
                network,
                threshold,
                training: AutoencoderTraining {
                    frames: self.frames,
                    epochs: config.sgd.epochs,
                    batch: config.sgd.batch,
                    learning_rate: config.sgd.learning_rate,
                    seed: config.seed,
                    first_loss: losses.first().copied().unwrap_or(f64::NAN),
                    final_loss: losses.last().copied().unwrap_or(f64::NAN),
                    max_error,
                    mean_error: errors.mean,
                    std_error: errors.std_dev(),
                    margin: config.margin,
                },
            }),
        ))
    }
}

/// Default threshold margin over the largest training reconstruction error.
pub const DEFAULT_MARGIN: f64 = 2.0;

/// How to train an autoencoder.
#[derive(Debug, Clone, PartialEq)]
pub struct AutoencoderConfig {
    /// Hidden layer widths (the output layer, as wide as the input, is added); `None` for
    /// n → ⌊n/2⌋ → ⌊n/4⌋ → n.
    pub hidden: Option<Vec<usize>>,
    pub sgd: Sgd,
    pub seed: u64,
    /// threshold = margin × the largest reconstruction error over the training data.
    pub margin: f64,
    pub sigma_floor_rel: f64,
}

impl Default for AutoencoderConfig {
    fn default() -> Self {
        AutoencoderConfig {
            hidden: None,
            sgd: Sgd::default(),
            seed: 0,
            margin: DEFAULT_MARGIN,
            sigma_floor_rel: crate::stats::DEFAULT_SIGMA_FLOOR_REL,
        }
    }
}

/// The σ floor a model may be loaded with (what `Model` checks at load): a model written with
/// NaN or a negative floor could not be read back.
fn check_sigma_floor(floor: f64) -> Result<(), TrainError> {
    if floor.is_finite() && floor >= 0.0 {
        Ok(())
    } else {
        Err(TrainError::Config(format!(
            "sigma floor {floor} must be a non-negative number"
        )))
    }
}
