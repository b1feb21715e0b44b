//! Model files: what training produced, as JSON. A model carries the layout and preprocessing it
//! was trained with, so a detector can refuse a channel whose frames are laid out differently.

use crate::layout::FieldLayout;
use crate::network::Network;
use crate::preprocess::Preprocess;
use crate::stats::FeatureStats;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// The `format` string of every model file.
pub const FORMAT: &str = "s3res-anomaly-model";
/// The model file version this code reads and writes.
pub const VERSION: u32 = 1;

/// Standardised features are clamped to ±`CLAMP` before scoring, so a corrupted value of 1e300
/// cannot overflow the network into NaN; it still scores far above any threshold.
pub const CLAMP: f64 = 1e6;

/// A trained detector model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Model {
    pub format: String,
    pub version: u32,
    pub layout: FieldLayout,
    pub preprocess: Preprocess,
    pub detector: DetectorModel,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum DetectorModel {
    Gaussian(GaussianModel),
    Autoencoder(AutoencoderModel),
}

/// Per-feature Gaussian model (MAVFI's GAD): alarm when a feature is more than `n_sigma`
/// standard deviations from its training mean.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GaussianModel {
    pub n_sigma: f64,
    /// See [`FeatureStats::sigma`].
    pub sigma_floor_rel: f64,
    pub features: Vec<FeatureStats>,
}

/// Default alarm distance for the Gaussian detector, in σ.
pub const DEFAULT_N_SIGMA: f64 = 6.0;

/// Autoencoder model (MAVFI's AAD): standardise the features with the training statistics,
/// reconstruct them, alarm when the mean squared reconstruction error exceeds `threshold`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AutoencoderModel {
    pub sigma_floor_rel: f64,
    /// Standardisation: each feature's training mean and σ (after the floor).
    pub features: Vec<FeatureStats>,
    pub network: Network,
    pub threshold: f64,
    /// How the threshold and network came about (informative; not used to score).
    pub training: AutoencoderTraining,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AutoencoderTraining {
    pub frames: u64,
    pub epochs: usize,
    pub batch: usize,
    pub learning_rate: f64,
    pub seed: u64,
    pub first_loss: f64,
    pub final_loss: f64,
    /// Reconstruction error over the training features: largest, mean, standard deviation.
    pub max_error: f64,
    pub mean_error: f64,
    pub std_error: f64,
    /// threshold = margin × max_error.
    pub margin: f64,
}

#[derive(Debug, Error)]
pub enum ModelError {
    #[error("cannot read model {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot write model {path}: {source}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("model {path}: {source}")]
    Json {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("{0}")]
    Invalid(String),
}

impl Model {
    pub fn new(layout: FieldLayout, preprocess: Preprocess, detector: DetectorModel) -> Self {
        Model {
            format: FORMAT.into(),
            version: VERSION,
            layout,
            preprocess,
            detector,
        }
    }

    /// Reads and checks a model file. JSON errors carry line and column.
    pub fn load(path: &Path) -> Result<Model, ModelError> {
        let text = std::fs::read_to_string(path).map_err(|source| ModelError::Read {
            path: path.into(),
            source,
        })?;
        let model: Model = serde_json::from_str(&text).map_err(|source| ModelError::Json {
            path: path.into(),
            source,
        })?;
        model
            .check()
            .map_err(|e| ModelError::Invalid(format!("model {}: {e}", path.display())))?;
        Ok(model)
    }

    pub fn save(&self, path: &Path) -> Result<(), ModelError> {
        let mut text = serde_json::to_string_pretty(self).map_err(|source| ModelError::Json {
            path: path.into(),
            source,
        })?;
        text.push('\n');
        std::fs::write(path, text).map_err(|source| ModelError::Write {
            path: path.into(),
            source,
        })
    }

    pub fn kind(&self) -> &'static str {
        match self.detector {
            DetectorModel::Gaussian(_) => "gaussian",
            DetectorModel::Autoencoder(_) => "autoencoder",
        }
    }

    /// Checks that the model is usable: right format and version, one feature per field with
    /// the field's name, sane numbers, a network that maps the features onto themselves.
    pub fn check(&self) -> Result<(), String> {
        if self.format != FORMAT {
            return Err(format!(
                "format is {:?}, expected {FORMAT:?} (is this a model file?)",
                self.format
            ));
        }
        if self.version != VERSION {
            return Err(format!(
                "version {} is not supported (this build reads version {VERSION})",
                self.version
            ));
        }
        let (features, floor) = match &self.detector {
            DetectorModel::Gaussian(g) => {
                if !(g.n_sigma > 0.0 && g.n_sigma < CLAMP) {
                    return Err(format!(
                        "n_sigma {} must be positive and below {CLAMP}",
                        g.n_sigma
                    ));
                }
                (&g.features, g.sigma_floor_rel)
            }
            DetectorModel::Autoencoder(a) => {
                a.network.check()?;
                let n = self.layout.len();
                if a.network.inputs() != n || a.network.outputs() != n {
                    return Err(format!(
                        "the network maps {} inputs to {} outputs; the layout has {n} fields",
                        a.network.inputs(),
                        a.network.outputs()
                    ));
                }
                if !(a.threshold.is_finite() && a.threshold > 0.0) {
                    return Err(format!(
                        "threshold {} must be a positive number",
                        a.threshold
                    ));
                }
                (&a.features, a.sigma_floor_rel)
            }
        };
        if !(floor.is_finite() && floor >= 0.0) {
            return Err(format!(
                "sigma_floor_rel {floor} must be a non-negative number"
            ));
        }
        if features.len() != self.layout.len() {
            return Err(format!(
                "{} feature statistics for {} fields",
                features.len(),
                self.layout.len()
            ));
        }
        for (f, s) in self.layout.fields().iter().zip(features) {
            if f.name != s.name {
                return Err(format!(
                    "statistics for `{}` where field `{}` is expected",
                    s.name, f.name
                ));
            }
            let w = &s.welford;
            if !(w.mean.is_finite() && w.m2.is_finite() && w.m2 >= 0.0 && s.magnitude >= 0.0) {
                return Err(format!("statistics of `{}` are not finite", s.name));
            }
        }
        Ok(())
    }

    /// An error unless `layout` (say, a channel's declared fields) is the one the model was
    /// trained on.
    pub fn check_layout(&self, layout: &FieldLayout) -> Result<(), ModelError> {
        if &self.layout == layout {
            Ok(())
        } else {
            Err(ModelError::Invalid(format!(
                "the model was trained on fields {} but the channel declares {}",
                describe(&self.layout),
                describe(layout)
            )))
        }
    }
}

fn describe(layout: &FieldLayout) -> String {
    let parts: Vec<String> = layout
        .fields()
        .iter()
        .map(|f| format!("{}:{}@{}", f.name, f.ty.name(), f.offset))
        .collect();
    format!("[{}]", parts.join(", "))
}
