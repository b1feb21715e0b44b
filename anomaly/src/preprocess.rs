//! Preprocessing, after MAVFI §5.2: each field becomes one feature, optionally reduced to its
//! sign and exponent (floats), and the detectors see the feature's change from the previous
//! frame of the same stream (its delta).
//!
//! Non-finite floats (NaN, ±Inf) in a frame are reported as such and never become features:
//! a detector treats them as an alarm whatever its model says (see `detector.rs`).

use crate::layout::{value_of_bits, DecodeError, FieldLayout, FieldType};
use serde::{Deserialize, Serialize};

/// How a float field becomes a feature.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FloatRepr {
    /// The value itself.
    #[default]
    Value,
    /// Only the sign and exponent bits, as a small integer (`sign << 11 | exponent` for f64,
    /// `sign << 8 | exponent` for f32). A mantissa flip then changes nothing; a sign flip
    /// changes the feature by 2048 (f64) or 256 (f32); an exponent bit by its power of two.
    /// Beware fields that cross zero in normal operation: their exponent swings widely near
    /// zero, so their normal deltas are large too.
    SignExponent,
}

/// The preprocessing a model was trained with (saved in the model; the detector applies the
/// same).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Preprocess {
    /// Score the change from the previous frame (true, the default and MAVFI's choice) or the
    /// value itself (false: for fields whose values, not changes, are normally distributed).
    #[serde(default = "yes")]
    pub delta: bool,
    #[serde(default)]
    pub floats: FloatRepr,
}

fn yes() -> bool {
    true
}

impl Default for Preprocess {
    fn default() -> Self {
        Preprocess {
            delta: true,
            floats: FloatRepr::Value,
        }
    }
}

/// What reading a frame's features found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Read {
    /// Every feature is a finite number.
    Finite,
    /// Field `index` is NaN or infinite (the first such field).
    NonFinite { index: usize },
}

impl Preprocess {
    /// True if feature `ty` takes only integer values (integer fields, reduced floats): its
    /// smallest change is 1, which sets the detectors' σ floor.
    pub fn integral(&self, ty: FieldType) -> bool {
        !ty.is_float() || self.floats == FloatRepr::SignExponent
    }

    /// Reads `frame`'s features into `out` (one per field, layout order) without allocating.
    pub fn read(
        &self,
        layout: &FieldLayout,
        frame: &[u8],
        out: &mut [f64],
    ) -> Result<Read, DecodeError> {
        if out.len() != layout.len() {
            return Err(DecodeError::OutputLength {
                have: out.len(),
                want: layout.len(),
            });
        }
        layout.check_len(frame)?;
        let mut read = Read::Finite;
        for (index, (field, o)) in layout.fields().iter().zip(out.iter_mut()).enumerate() {
            let Some(bits) = field.read_bits(frame) else {
                // Unreachable after check_len; kept panic-free.
                return Err(DecodeError::ShortFrame {
                    have: frame.len(),
                    need: layout.min_frame(),
                });
            };
            let value = value_of_bits(field.ty, bits);
            if !value.is_finite() {
                if read == Read::Finite {
                    read = Read::NonFinite { index };
                }
                *o = 0.0;
                continue;
            }
            *o = match (field.ty, self.floats) {
                (FieldType::F64, FloatRepr::SignExponent) => (bits >> 52) as f64,
                (FieldType::F32, FloatRepr::SignExponent) => ((bits as u32) >> 23) as f64,
                _ => value,
            };
        }
        Ok(read)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::Field;

    fn layout() -> FieldLayout {
        FieldLayout::new(vec![
            Field::new("d", FieldType::F64, 0),
            Field::new("s", FieldType::F32, 8),
            Field::new("n", FieldType::I16, 12),
        ])
        .unwrap()
    }

    fn frame(d: f64, s: f32, n: i16) -> Vec<u8> {
        let mut f = Vec::new();
        f.extend_from_slice(&d.to_le_bytes());
        f.extend_from_slice(&s.to_le_bytes());
        f.extend_from_slice(&n.to_le_bytes());
        f
    }

    #[test]
    fn sign_exponent_reduction() {
        let pre = Preprocess {
            delta: true,
            floats: FloatRepr::SignExponent,
        };
        let mut out = [0.0; 3];
        pre.read(&layout(), &frame(1.5, -2.0, -4), &mut out)
            .unwrap();
        // 1.5 = 2^0 × 1.5: exponent 1023, sign 0. -2.0f32: sign 1, exponent 128.
        assert_eq!(out, [1023.0, 256.0 + 128.0, -4.0]);
        // A mantissa change is invisible; a sign flip moves the feature by 2048.
        pre.read(&layout(), &frame(1.75, -2.0, -4), &mut out)
            .unwrap();
        assert_eq!(out[0], 1023.0);
        pre.read(&layout(), &frame(-1.5, -2.0, -4), &mut out)
            .unwrap();
        assert_eq!(out[0], 2048.0 + 1023.0);
    }

    #[test]
    fn non_finite_is_reported_with_its_field() {
        let pre = Preprocess::default();
        let mut out = [0.0; 3];
        assert_eq!(
            pre.read(&layout(), &frame(1.0, 2.0, 3), &mut out),
            Ok(Read::Finite)
        );
        assert_eq!(out, [1.0, 2.0, 3.0]);
        assert_eq!(
            pre.read(&layout(), &frame(1.0, f32::NAN, 3), &mut out),
            Ok(Read::NonFinite { index: 1 })
        );
        assert_eq!(
            pre.read(&layout(), &frame(f64::NEG_INFINITY, f32::NAN, 3), &mut out),
            Ok(Read::NonFinite { index: 0 })
        );
        // The sign-exponent form sees NaN too (its exponent is all ones).
        let reduced = Preprocess {
            delta: true,
            floats: FloatRepr::SignExponent,
        };
        assert_eq!(
            reduced.read(&layout(), &frame(f64::INFINITY, 0.0, 0), &mut out),
            Ok(Read::NonFinite { index: 0 })
        );
    }

    #[test]
    fn json_defaults() {
        let p: Preprocess = serde_json::from_str("{}").unwrap();
        assert_eq!(p, Preprocess::default());
        let p: Preprocess = serde_json::from_str(r#"{"floats":"sign-exponent"}"#).unwrap();
        assert_eq!(p.floats, FloatRepr::SignExponent);
    }
}
