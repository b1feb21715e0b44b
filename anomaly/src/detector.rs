//! The detector a voter holds per monitored output: it scores each replica's output frames
//! against that replica's previous frame, without allocating.
//!
//! Every buffer is sized when the detector is made (`replicas × fields` previous values, one
//! feature vector, the network's layer outputs); [`Detector::observe`] only reads and writes
//! them.

use crate::layout::FieldLayout;
use crate::model::{DetectorModel, Model, ModelError, CLAMP};
use crate::network::{Network, Scratch};
use crate::preprocess::{Preprocess, Read};
use std::path::Path;

/// Why a verdict is what it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cause {
    /// Scored, within the model's normal range.
    Normal,
    /// The stream's first frame (after [`Detector::reset_stream`]): no previous frame to take a
    /// delta from. Not scored, not an alarm; it becomes the stream's previous frame.
    Warmup,
    /// Scored above the threshold.
    Deviation,
    /// A float field is NaN or infinite. Always an alarm: no control value is meant to be.
    NonFinite,
    /// The frame is shorter than the layout. Always an alarm.
    ShortFrame,
}

/// The detector's opinion of one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Verdict {
    pub alarm: bool,
    /// Gaussian: the largest |z| over the fields (in σ). Autoencoder: the mean squared
    /// reconstruction error of the standardised features. +∞ for non-finite and short frames,
    /// 0 for warm-up.
    pub score: f64,
    /// What `score` is compared with (alarm ⇔ score > threshold).
    pub threshold: f64,
    /// The most anomalous field (index into the layout), if there is one.
    pub field: Option<usize>,
    pub cause: Cause,
}

enum Scorer {
    Gaussian {
        n_sigma: f64,
    },
    Autoencoder {
        network: Network,
        scratch: Scratch,
        threshold: f64,
    },
}

/// A detector for one monitored output of a component with `replicas` replicas.
pub struct Detector {
    layout: FieldLayout,
    preprocess: Preprocess,
    /// Standardisation, per feature: subtract `mean`, multiply by `inv_sigma`.
    mean: Box<[f64]>,
    inv_sigma: Box<[f64]>,
    scorer: Scorer,
    /// `replicas × fields` feature values of each replica's last accepted frame.
    prev: Box<[f64]>,
    has_prev: Box<[bool]>,
    /// Working buffers for one frame.
    current: Box<[f64]>,
    standard: Box<[f64]>,
}

impl Detector {
    /// A detector for `replicas` replica streams, from a checked model.
    pub fn new(model: &Model, replicas: usize) -> Result<Detector, ModelError> {
        model.check().map_err(ModelError::Invalid)?;
        let n = model.layout.len();
        let (features, floor, scorer) = match &model.detector {
            DetectorModel::Gaussian(g) => (
                &g.features,
                g.sigma_floor_rel,
                Scorer::Gaussian { n_sigma: g.n_sigma },
            ),
            DetectorModel::Autoencoder(a) => (
                &a.features,
                a.sigma_floor_rel,
                Scorer::Autoencoder {
                    network: a.network.clone(),
                    scratch: a.network.scratch(),
                    threshold: a.threshold,
                },
            ),
        };
        Ok(Detector {
            layout: model.layout.clone(),
            preprocess: model.preprocess,
            mean: features.iter().map(|s| s.welford.mean).collect(),
            inv_sigma: features.iter().map(|s| 1.0 / s.sigma(floor)).collect(),
            scorer,
            prev: vec![0.0; replicas * n].into_boxed_slice(),
            has_prev: vec![false; replicas].into_boxed_slice(),
            current: vec![0.0; n].into_boxed_slice(),
            standard: vec![0.0; n].into_boxed_slice(),
        })
    }

    /// Loads a model file and makes a detector for `replicas` replicas.
    pub fn load(path: &Path, replicas: usize) -> Result<Detector, ModelError> {
        Detector::new(&Model::load(path)?, replicas)
    }

    pub fn layout(&self) -> &FieldLayout {
        &self.layout
    }

    pub fn replicas(&self) -> usize {
        self.has_prev.len()
    }

    /// The name of field `index` (for events and logs).
    pub fn field_name(&self, index: usize) -> &str {
        self.layout.fields().get(index).map_or("?", |f| &f.name)
    }

    /// What the score is compared with.
    pub fn threshold(&self) -> f64 {
        match &self.scorer {
            Scorer::Gaussian { n_sigma } => *n_sigma,
            Scorer::Autoencoder { threshold, .. } => *threshold,
        }
    }

    /// Scores `frame`, the next output frame of `replica`, against that replica's previous
    /// frame, and makes it the replica's previous frame (unless it is short or holds NaN/Inf).
    /// Never allocates.
    ///
    /// An alarming frame becomes the reference too: a detector that kept the last good frame
    /// instead would alarm on every later frame after a single false alarm. What happens to
    /// the culprit's stream is the voter's business: [`copy_stream`](Self::copy_stream) when
    /// it replaces the replica by a fork of a healthy one, [`reset_stream`](Self::reset_stream)
    /// when it restarts it from scratch.
    ///
    /// # Panics
    /// If `replica >= self.replicas()` (a caller bug, like an out-of-range slice index).
    pub fn observe(&mut self, replica: usize, frame: &[u8]) -> Verdict {
        let threshold = self.threshold();
        let alarm = |cause, field| Verdict {
            alarm: true,
            score: f64::INFINITY,
            threshold,
            field,
            cause,
        };
        match self.preprocess.read(&self.layout, frame, &mut self.current) {
            Err(_) => return alarm(Cause::ShortFrame, None),
            Ok(Read::NonFinite { index }) => return alarm(Cause::NonFinite, Some(index)),
            Ok(Read::Finite) => {}
        }
        let n = self.current.len();
        let prev = &mut self.prev[replica * n..(replica + 1) * n];
        if self.preprocess.delta && !self.has_prev[replica] {
            prev.copy_from_slice(&self.current);
            self.has_prev[replica] = true;
            return Verdict {
                alarm: false,
                score: 0.0,
                threshold,
                field: None,
                cause: Cause::Warmup,
            };
        }
        let delta = self.preprocess.delta;
        for ((((z, cur), old), mean), inv) in self
            .standard
            .iter_mut()
            .zip(self.current.iter())
            .zip(prev.iter())
            .zip(self.mean.iter())
            .zip(self.inv_sigma.iter())
        {
            let x = if delta { cur - old } else { *cur };
            // x is finite or ±∞ (a finite difference can overflow), never NaN; so is z.
            *z = ((x - mean) * inv).clamp(-CLAMP, CLAMP);
        }
        let (score, field) = match &mut self.scorer {
            Scorer::Gaussian { .. } => largest(self.standard.iter().map(|z| z.abs())),
            Scorer::Autoencoder {
                network, scratch, ..
            } => {
                let out = network.forward(&self.standard, scratch);
                let (_, field) = largest(
                    self.standard
                        .iter()
                        .zip(out)
                        .map(|(x, y)| (x - y) * (x - y)),
                );
                (crate::network::mean_squared(&self.standard, out), field)
            }
        };
        let alarm = score > threshold;
        prev.copy_from_slice(&self.current);
        Verdict {
            alarm,
            score,
            threshold,
            field,
            cause: if alarm {
                Cause::Deviation
            } else {
                Cause::Normal
            },
        }
    }

    /// Makes `frame` the previous frame of `replica` without scoring it (say, the frame the
    /// voter forwarded, when it did not score every replica). A frame that cannot be read
    /// (short, non-finite) resets the stream instead.
    pub fn resync(&mut self, replica: usize, frame: &[u8]) {
        let n = self.current.len();
        match self.preprocess.read(&self.layout, frame, &mut self.current) {
            Ok(Read::Finite) => {
                self.prev[replica * n..(replica + 1) * n].copy_from_slice(&self.current);
                self.has_prev[replica] = true;
            }
            _ => self.has_prev[replica] = false,
        }
    }

    /// Gives replica `to` the stream state of `from`: after `to` was replaced by a fork of
    /// `from`, its next frame continues `from`'s stream.
    pub fn copy_stream(&mut self, from: usize, to: usize) {
        let n = self.current.len();
        self.prev.copy_within(from * n..(from + 1) * n, to * n);
        self.has_prev[to] = self.has_prev[from];
    }

    /// Forgets replica `replica`'s previous frame (it was restarted from scratch): its next
    /// frame is a warm-up.
    pub fn reset_stream(&mut self, replica: usize) {
        self.has_prev[replica] = false;
    }
}

/// The largest value and its index (first on ties); (0, None) for an empty sequence.
#[inline]
fn largest(values: impl Iterator<Item = f64>) -> (f64, Option<usize>) {
    let mut best = (0.0, None);
    for (i, v) in values.enumerate() {
        if best.1.is_none() || v > best.0 {
            best = (v, Some(i));
        }
    }
    best
}
